"""Clocks that timestamp driver data: the wall clock on hardware, a virtual one in simulation.

Every timestamp is in seconds on a monotonic time line. Simulated drivers take a
:class:`Clock` so a simulated cell (and the tests) can run faster or slower than real time
and still produce consistent, reproducible timestamps.
"""

from __future__ import annotations

import threading
import time
from typing import Protocol, runtime_checkable

from oralnav.checks import NumberMessages, finite_number

__all__ = ["Clock", "DeviceClockMap", "PtpClockMap", "VirtualClock", "WallClock",
           "tai_minus_monotonic"]

# One wording for every refused time value; ValueError, as the clocks always raised.
_SECONDS = NumberMessages.uniform("{what} must be a finite number of seconds, got {value!r}")


@runtime_checkable
class Clock(Protocol):
    """Anything with ``now() -> float``: monotonic, non-decreasing time in seconds."""

    def now(self) -> float:
        """Current time, seconds."""
        ...


class WallClock:
    """``time.monotonic()``: the clock of live hardware (and of camera timestamps)."""

    def now(self) -> float:
        return time.monotonic()

    def __repr__(self) -> str:
        return "WallClock()"


class VirtualClock:
    """A clock that moves only when told to; thread-safe.

    ``advance(dt)`` and ``set(t)`` move it forward. Time never goes back: a negative ``dt``
    or an earlier ``t`` raises ``ValueError``, as does any non-finite value.
    """

    def __init__(self, start: float = 0.0) -> None:
        self._now = finite_number(start, "start", ValueError, messages=_SECONDS)
        self._lock = threading.Lock()

    def now(self) -> float:
        with self._lock:
            return self._now

    def advance(self, dt: float) -> float:
        """Move forward by ``dt`` >= 0 seconds; return the new time."""
        dt = finite_number(dt, "dt", ValueError, messages=_SECONDS)
        if dt < 0.0:
            raise ValueError(f"dt must be >= 0 s (a clock does not run backwards), got {dt!r}")
        with self._lock:
            self._now += dt
            return self._now

    def set(self, t: float) -> None:
        """Jump to time ``t`` seconds, which must not be earlier than now."""
        t = finite_number(t, "t", ValueError, messages=_SECONDS)
        with self._lock:
            if t < self._now:
                raise ValueError(
                    f"t = {t!r} s is earlier than now ({self._now!r} s); a clock does not run "
                    "backwards"
                )
            self._now = t

    def __repr__(self) -> str:
        return f"VirtualClock(now={self.now()!r})"


class DeviceClockMap:
    """Maps a device's clock (a camera's frame timestamps, s) onto the host's monotonic
    clock, from each frame's device timestamp and its arrival time on the host.

    ``arrival - device`` is the clocks' offset plus the frame's transfer delay, so its
    smallest value seen is the offset plus the shortest delay: the mapped time
    ``device + offset`` is the capture instant plus that shortest delay (a constant the
    temporal calibration measures). The estimate follows the smallest value down at once,
    and may rise by ``drift`` s per s (1e-4: 100 ppm, far above a crystal's), so a device
    clock that runs slower than the host's is followed too.

    A device timestamp that does not increase, or a device clock suddenly ahead by more
    than ``jump`` s (a clock set forward, a camera that restarted its clock), raises
    :class:`~oralnav.drivers.errors.ClockError`; the map then starts afresh from the next
    frame. A frame that arrives late is no error: the smallest difference is kept. Pure
    arithmetic, no I/O; not thread-safe (one camera's reader).
    """

    def __init__(self, *, drift: float = 1e-4, jump: float = 0.5) -> None:
        self.drift = finite_number(drift, "drift", ValueError, messages=_SECONDS)
        self.jump = finite_number(jump, "jump", ValueError, messages=_SECONDS)
        if self.drift < 0 or self.jump <= 0:
            raise ValueError(f"drift must be >= 0 and jump > 0 s, got {drift!r}, {jump!r}")
        self.reset()

    def reset(self) -> None:
        """Forget the offset (a new link, or after a clock error)."""
        self.offset: float | None = None
        self._device: float | None = None
        self._host = 0.0

    def map(self, device: float, arrival: float) -> float:
        """The host-clock time (s) of device time ``device`` (s), given that its frame
        arrived at host time ``arrival`` (s). Raises ``ClockError`` (module docstring)."""
        from .errors import ClockError

        seen = arrival - device
        if self.offset is None or self._device is None:
            self.offset, self._device, self._host = seen, device, arrival
            return device + seen
        if device <= self._device:
            back = self._device - device
            self.reset()
            raise ClockError(f"the device clock went back by {back * 1e3:.3f} ms (or stood "
                             "still): its frames cannot be placed in time")
        allowed = self.offset + self.drift * max(arrival - self._host, 0.0)
        if seen < allowed - self.jump:
            # the device is suddenly ahead by more than any transfer delay shrinks: its
            # clock was set forward (a frame that arrives late is only late: the map
            # keeps the smallest difference, so it changes nothing)
            moved = allowed - seen
            self.reset()
            raise ClockError(f"the device clock jumped by {moved * 1e3:+.1f} ms against the "
                             f"host's (more than {self.jump * 1e3:.0f} ms in one frame)")
        self.offset = min(allowed, seen)
        self._device, self._host = device, arrival
        return device + self.offset


def tai_minus_monotonic() -> float:
    """``CLOCK_TAI - CLOCK_MONOTONIC`` now (s), from the closest of three back-to-back
    reads (the kernel keeps both; TAI is what IEEE 1588 (PTP) distributes)."""
    best = None
    for _ in range(3):
        a = time.monotonic()
        tai = time.clock_gettime(time.CLOCK_TAI)
        b = time.monotonic()
        if best is None or b - a < best[0]:
            best = (b - a, tai - 0.5 * (a + b))
    return best[1]


class PtpClockMap:
    """Maps a PTP-synchronised camera's timestamps (s of TAI, as GigE Vision 2.0 cameras
    with IEEE 1588 enabled stamp frames) onto the host's monotonic clock with the host's
    own ``TAI - monotonic`` (:func:`tai_minus_monotonic`): the capture instant itself, no
    transfer delay in it, once the host's clock is synchronised to the same grandmaster.

    A mapped instant after the frame's arrival (beyond ``ahead`` s) or older than
    ``behind`` s at arrival means the clocks are not synchronised (PTP not running, a
    camera on its own free-running clock), and an instant that goes back or stands still
    means its clock was stepped: each raises :class:`~oralnav.drivers.errors.ClockError`,
    never a frame placed wrongly. Pure arithmetic besides reading the host's clocks; not
    thread-safe (one camera's reader)."""

    def __init__(self, *, ahead: float = 0.005, behind: float = 10.0) -> None:
        self.ahead = finite_number(ahead, "ahead", ValueError, messages=_SECONDS)
        self.behind = finite_number(behind, "behind", ValueError, messages=_SECONDS)
        if self.ahead < 0 or self.behind <= 0:
            raise ValueError(f"ahead must be >= 0 and behind > 0 s, got {ahead!r}, {behind!r}")
        self.reset()

    def reset(self) -> None:
        """Forget the last instant (a new link)."""
        self._last: float | None = None

    def map(self, device: float, arrival: float, tai_minus_mono: float | None = None
            ) -> float:
        """The monotonic instant (s) of PTP time ``device`` (s), for a frame that arrived
        at monotonic ``arrival`` (s); ``tai_minus_mono``: the host's offset (read now when
        None)."""
        from .errors import ClockError

        offset = tai_minus_monotonic() if tai_minus_mono is None else tai_minus_mono
        t = device - offset
        if t > arrival + self.ahead:
            raise ClockError(f"the camera's PTP time is {(t - arrival) * 1e3:.1f} ms ahead of "
                             "the frame's arrival: its clock is not synchronised to this "
                             "computer's (is PTP running on both?)")
        if t < arrival - self.behind:
            raise ClockError(f"the camera's PTP time is {arrival - t:.1f} s behind the frame's "
                             "arrival: its clock is not synchronised to this computer's")
        if self._last is not None and t <= self._last:
            back = self._last - t
            self._last = None
            raise ClockError(f"the camera's PTP time went back by {back * 1e3:.3f} ms (or "
                             "stood still): its frames cannot be placed in time")
        self._last = t
        return t
