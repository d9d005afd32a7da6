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

__all__ = ["Clock", "VirtualClock", "WallClock"]

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
