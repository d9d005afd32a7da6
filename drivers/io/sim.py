"""Simulated safety inputs: buttons that tests (or the operator UI in simulation) press.

Readings are stamped with the clock's time when read, as a polled input would be, except
after :meth:`SimInputs.inject_silence`, which freezes the reported reading (timestamp and
values). :meth:`SimInputs.inject_disconnect` makes the input read fail-safe (e-stop pressed,
pedal released) until :meth:`SimInputs.clear`.
"""

from __future__ import annotations

import threading

from ..clock import Clock, WallClock
from ..errors import DriverInitError
from ..lifecycle import LifecycleState
from .base import InputState, SafetyInputs

__all__ = ["SimInputs"]


class SimInputs(SafetyInputs):
    """Simulated e-stop and pedal; both start released.

    Args:
        clock: timestamps (default: the wall clock).
        name: for messages and logs.
    """

    def __init__(self, clock: Clock | None = None, name: str = "inputs") -> None:
        super().__init__(name)
        self.clock: Clock = WallClock() if clock is None else clock
        if not callable(getattr(self.clock, "now", None)):
            raise DriverInitError(f"clock must have now() -> seconds, got {clock!r}")
        self._lock = threading.Lock()
        self._life = LifecycleState()  # changed under _lock
        self._link = True  # False after inject_disconnect()
        self._estop = False
        self._pedal = False
        self._silent: InputState | None = None  # the frozen reading while silent

    async def start(self) -> None:
        with self._lock:
            self._life.start(
                f"inputs {self.name!r}: start() called twice (build new ones after close)"
            )

    async def close(self) -> None:
        with self._lock:
            self._life.close()

    def _read(self) -> InputState:
        with self._lock:
            if self._silent is not None:
                return self._silent
            return self._now()

    def _now(self) -> InputState:
        return InputState(
            timestamp=float(self.clock.now()),
            estop_pressed=self._estop,
            pedal_pressed=self._pedal,
            connected=self._life.running and self._link,
        )

    def press_estop(self) -> None:
        with self._lock:
            self._estop = True

    def release_estop(self) -> None:
        with self._lock:
            self._estop = False

    def press_pedal(self) -> None:
        with self._lock:
            self._pedal = True

    def release_pedal(self) -> None:
        with self._lock:
            self._pedal = False

    def inject_silence(self) -> None:
        """The input goes silent: ``state()`` repeats the current reading, timestamp included."""
        with self._lock:
            if self._silent is None:
                self._silent = self._now()

    def inject_disconnect(self) -> None:
        """The link drops: the input reads fail-safe until :meth:`clear`."""
        with self._lock:
            self._link = False

    def clear(self) -> None:
        """End silence and disconnection."""
        with self._lock:
            self._silent = None
            self._link = True
