"""Issue 4 drivers: the clocks that timestamp driver data."""

from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest

from oralnav.drivers.clock import Clock, VirtualClock, WallClock


def test_wall_clock_is_monotonic_time():
    """issue 4 drivers: WallClock reads time.monotonic() seconds; both clocks are Clocks."""
    before = time.monotonic()
    now = WallClock().now()
    assert before <= now <= time.monotonic()
    assert isinstance(WallClock(), Clock) and isinstance(VirtualClock(), Clock)


def test_virtual_clock_moves_only_forward_when_told():
    """issue 4 drivers: VirtualClock starts where told, advances by dt, jumps with set(),
    and never runs backwards."""
    clock = VirtualClock(start=10.0)
    assert clock.now() == 10.0
    assert clock.now() == 10.0  # does not move by itself
    assert clock.advance(0.5) == 10.5
    clock.advance(0.0)
    clock.set(12.0)
    assert clock.now() == 12.0
    clock.set(12.0)  # same time is fine
    with pytest.raises(ValueError, match="dt must be >= 0"):
        clock.advance(-0.001)
    with pytest.raises(ValueError, match="earlier than now"):
        clock.set(11.0)
    for bad in (math.nan, math.inf, "x", True):
        with pytest.raises(ValueError, match="finite number of seconds"):
            clock.advance(bad)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="start"):
        VirtualClock(start=math.nan)
    assert clock.now() == 12.0  # failed calls changed nothing


def test_virtual_clock_is_thread_safe():
    """issue 4 drivers: concurrent advance() calls lose no time."""
    clock = VirtualClock()

    def work() -> None:
        for _ in range(2000):
            clock.advance(0.5)  # exact in binary floating point

    threads = [threading.Thread(target=work) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert clock.now() == 4 * 2000 * 0.5


# -- the device clock map (issue 32: camera device clocks on the monotonic clock) -----------

def test_device_clock_map_finds_the_offset_plus_the_shortest_delay():
    """Issue 32 (time): frames captured every 10 ms on a device clock 1000 s ahead, each
    arriving 2-6 ms later: the mapped time is capture + the shortest delay (2 ms), within
    20 us once the shortest delay has been seen (the offset may creep up by the drift
    allowance, 100 ppm of the 170 ms between two shortest delays), never later than
    arrival."""
    from oralnav.drivers.clock import DeviceClockMap

    rng = np.random.default_rng(3)
    m = DeviceClockMap()
    for k in range(200):
        capture = 50.0 + 0.01 * k
        delay = 0.002 if k % 17 == 0 else 0.002 + 0.004 * rng.random()
        mapped = m.map(capture + 1000.0, capture + delay)
        assert mapped <= capture + delay + 1e-12
        if k >= 17:
            assert abs(mapped - (capture + 0.002)) < 2e-5


def test_device_clock_map_follows_a_slow_device_clock():
    """Issue 32 (time): a device clock 50 ppm slow is followed (the offset may rise by
    up to 100 ppm): the mapped time stays within 0.2 ms of capture + the delay."""
    from oralnav.drivers.clock import DeviceClockMap

    m = DeviceClockMap()
    for k in range(3000):
        capture = 0.01 * k
        mapped = m.map(capture * (1 - 50e-6), capture + 0.003)
        assert abs(mapped - (capture + 0.003)) < 2e-4


@pytest.mark.parametrize("device, words", [
    (lambda k: 1000.0 + 0.01 * k - (0.05 if k == 20 else 0.0), "went back by"),
    (lambda k: 1000.0 + 0.01 * k if k < 20 else 1000.0 + 0.01 * k + 5.0, r"jumped by \+5000"),
    (lambda k: 1000.0 + 0.01 * min(k, 19), r"went back by 0.000 ms \(or stood still\)"),
])
def test_device_clock_errors_are_named_and_the_map_starts_afresh(device, words):
    """Issue 32 (bad input: a camera whose clock jumps or runs backwards): ClockError
    naming the jump, a DriverIOError; the next frames are mapped afresh."""
    from oralnav.drivers.clock import DeviceClockMap
    from oralnav.drivers.errors import ClockError, DriverIOError

    m = DeviceClockMap()
    for k in range(20):
        m.map(device(k), 0.01 * k + 0.002)
    with pytest.raises(ClockError, match=words) as err:
        m.map(device(20), 0.2 + 0.002)
    assert isinstance(err.value, DriverIOError) and m.offset is None
    m.map(device(21) + 10.0, 0.21 + 0.002)  # a fresh start
    assert m.offset is not None


def test_device_clock_map_refuses_bad_settings():
    """Bad drift or jump settings are ValueErrors naming them."""
    from oralnav.drivers.clock import DeviceClockMap

    with pytest.raises(ValueError, match="drift must be >= 0 and jump > 0"):
        DeviceClockMap(drift=-1.0)
    with pytest.raises(ValueError, match="jump"):
        DeviceClockMap(jump=math.nan)


def test_ptp_time_maps_to_the_capture_instant_on_the_monotonic_clock():
    """issue 32, "Time": a PTP-synchronised camera's TAI stamp maps onto time.monotonic()
    through the host's own TAI - monotonic difference: the capture instant itself, without
    the transfer delay (checked against the host's clocks read now)."""
    from oralnav.drivers.clock import PtpClockMap, tai_minus_monotonic

    off = tai_minus_monotonic()
    now = time.monotonic()
    assert abs((time.clock_gettime(time.CLOCK_TAI) - now) - off) < 1e-3
    m = PtpClockMap()
    capture = now - 0.4
    assert m.map(capture + off, arrival=now, tai_minus_mono=off) == pytest.approx(capture)
    assert m.map(capture + 0.1 + off, arrival=now) == pytest.approx(capture + 0.1, abs=1e-4)


@pytest.mark.parametrize(("device", "words"), [
    (0.5, "ahead of the frame's arrival"),     # stamped after it arrived: not synchronised
    (-30.0, "behind the frame's arrival"),     # a free-running camera clock
    (-0.2, "went back"),                       # stepped back after the first frame
])
def test_ptp_clock_errors_are_named(device, words):
    """A PTP time that cannot be the capture instant is a ClockError naming why: after the
    frame's arrival, far older than it, or going back; never a frame placed wrongly."""
    from oralnav.drivers.clock import PtpClockMap
    from oralnav.drivers.errors import ClockError

    m = PtpClockMap()
    m.map(99.9, arrival=100.0, tai_minus_mono=0.0)
    with pytest.raises(ClockError, match=words):
        m.map(100.0 + device if device != -0.2 else 99.7, arrival=100.05, tai_minus_mono=0.0)
