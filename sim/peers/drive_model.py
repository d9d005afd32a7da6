"""The motor axes of a simulated tendon drive unit, shared by the emulated CANopen and
Modbus drives (``sim/peers/cia402_drive.py``, ``sim/peers/modbus_drive.py``).

Each axis follows its target position with a first-order lag (time constant ``lag_s``) under
a speed limit, only while enabled and not faulted; a faulted axis holds where it is. Time is
the caller's: :meth:`DriveAxes.advance` integrates to the instant it is given, so the
emulators can step on their own clock (a SYNC, a Modbus request) without a thread.
"""

from __future__ import annotations

import math
import threading

import numpy as np

__all__ = ["DriveAxes"]


class DriveAxes:
    """``n`` position-controlled motor axes in encoder counts.

    Args:
        n: number of axes.
        lag_s: first-order following time constant, s.
        max_speed: counts/s.
        initial: (n,) starting positions, counts.
    """

    def __init__(self, n: int = 4, *, lag_s: float = 0.01, max_speed: float = 20000.0,
                 initial: np.ndarray | None = None) -> None:
        if not (lag_s > 0 and max_speed > 0):
            raise ValueError("lag_s and max_speed must be > 0")
        self.n, self.lag_s, self.max_speed = n, float(lag_s), float(max_speed)
        self.lock = threading.RLock()
        self.position = np.zeros(n) if initial is None else np.array(initial, float)
        self.target = self.position.copy()
        self.enabled = np.zeros(n, bool)
        self.fault = np.zeros(n, np.int64)  # error code per axis, 0: none
        self._t: float | None = None

    def advance(self, now: float) -> None:
        """Integrate every axis up to ``now`` (s)."""
        with self.lock:
            if self._t is None or now <= self._t:
                self._t = now if self._t is None else self._t
                return
            dt, self._t = now - self._t, now
            moving = self.enabled & (self.fault == 0)
            gap = self.target - self.position
            step = gap * (1.0 - math.exp(-dt / self.lag_s))
            step = np.clip(step, -self.max_speed * dt, self.max_speed * dt)
            self.position = np.where(moving, self.position + step, self.position)

    def counts(self) -> np.ndarray:
        """Positions rounded to whole counts (int64)."""
        with self.lock:
            return np.rint(self.position).astype(np.int64)

    def reached(self, tol: float = 2.0) -> np.ndarray:
        """Per axis: within ``tol`` counts of the target."""
        with self.lock:
            return np.abs(self.target - self.position) <= tol

    def set_fault(self, axis: int, code: int) -> None:
        """Fault one axis with an error code: it holds and disables."""
        with self.lock:
            self.fault[axis] = int(code)
            self.enabled[axis] = False
            self.target[axis] = self.position[axis]
