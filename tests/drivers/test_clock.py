"""Issue 4 drivers: the clocks that timestamp driver data."""

from __future__ import annotations

import math
import threading
import time

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
