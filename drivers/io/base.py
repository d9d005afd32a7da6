"""Safety inputs: the e-stop button and the foot pedal.

Both inputs are read fail-safe. :meth:`SafetyInputs.state` reports a disconnected (or not yet
started, or closed) input as the safe reading: the e-stop **pressed** and the pedal
**released**. The pedal is an enabling device (motion only while it is held), so "released"
is its safe value; the e-stop must stop the robot when its wiring or link is lost, so
"pressed" is its. A silent input (its timestamp stops advancing) is the safety layer's
watchdog's to catch.

``state()`` is synchronous, thread-safe and non-blocking.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass, replace

from ..lifecycle import AsyncLifecycle

__all__ = ["InputState", "SafetyInputs"]


@dataclass(frozen=True)
class InputState:
    """One reading of the safety inputs.

    Attributes:
        timestamp: when it was read, seconds on the driver's clock.
        estop_pressed: the e-stop is pressed, or cannot be read (fail-safe).
        pedal_pressed: the foot pedal is held (False when it cannot be read).
        connected: the driver talks to the input device.
        fault: why it does not (silent line, garbage, lost port), when the backend knows;
            None while connected.
    """

    timestamp: float
    estop_pressed: bool
    pedal_pressed: bool
    connected: bool
    fault: str | None = None

    def fail_safe(self) -> InputState:
        """This reading, or its safe version when not connected (e-stop pressed, pedal
        released)."""
        if self.connected:
            return self
        return replace(self, estop_pressed=True, pedal_pressed=False)


class SafetyInputs(AsyncLifecycle, abc.ABC):
    """Abstract safety inputs. Backends implement ``_read`` (the raw reading), ``start`` and
    ``close``; :meth:`state` applies the fail-safe rule so no backend can forget it."""

    def __init__(self, name: str = "inputs") -> None:
        self.name = name

    def state(self) -> InputState:
        """The current reading, fail-safe (see the module docstring)."""
        return self._read().fail_safe()

    @abc.abstractmethod
    def _read(self) -> InputState:
        """The raw reading; must not block."""

    @abc.abstractmethod
    async def start(self) -> None:
        """Connect; ``DriverInitError`` naming what failed."""

    @abc.abstractmethod
    async def close(self) -> None:
        """Disconnect. Idempotent; safe before ``start()``."""
