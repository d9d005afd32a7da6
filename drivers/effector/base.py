"""The end-effector contract: a tendon-driven wrist commanded in joint space.

Joints ``q = [roll, pitch, yaw, jaw]`` in radians; motors ``m`` in radians (see
:mod:`.kinematics`). Every method except ``start()``/``close()`` is synchronous, thread-safe
and non-blocking (the 500 Hz control thread and the event loop both call them).
:meth:`EndEffector.command` checks the target against the joint and motor limits and refuses
it (never clamps); :meth:`EndEffector.stop` never raises.
"""

from __future__ import annotations

import abc
import logging
from dataclasses import dataclass

import numpy as np

from ..lifecycle import AsyncLifecycle
from .kinematics import WristKinematics

__all__ = ["EffectorState", "EndEffector"]

log = logging.getLogger(__name__)


def _readonly(array: np.ndarray) -> np.ndarray:
    out = np.array(array, dtype=float)
    out.flags.writeable = False
    return out


@dataclass(frozen=True, eq=False)
class EffectorState:
    """One consistent snapshot of the wrist.

    Attributes:
        timestamp: when the device reported it, seconds on the driver's clock (a timestamp
            that stops advancing means the device went silent).
        joints: (4,) ``[roll, pitch, yaw, jaw]``, rad (read-only array).
        motors: (4,) motor angles, rad (read-only array).
        connected: the driver talks to the device.
        fault: the device's fault message, or None when healthy.
    """

    timestamp: float
    joints: np.ndarray
    motors: np.ndarray
    connected: bool
    fault: str | None

    def __post_init__(self) -> None:
        object.__setattr__(self, "joints", _readonly(self.joints))
        object.__setattr__(self, "motors", _readonly(self.motors))


class EndEffector(AsyncLifecycle, abc.ABC):
    """Abstract wrist. Backends implement :meth:`state`, ``_command``, ``_stop``,
    :meth:`start` and :meth:`close`; ``kinematics`` holds the coupling and limits."""

    def __init__(self, kinematics: WristKinematics, name: str = "effector") -> None:
        self.kinematics = kinematics
        self.name = name

    @abc.abstractmethod
    def state(self) -> EffectorState:
        """The latest state snapshot."""

    def command(self, q: np.ndarray) -> None:
        """Move the joints toward ``q`` (4,) rad.

        Raises:
            EffectorCommandError: malformed ``q`` or outside the joint or motor limits
                (refused, not clamped; the message names the joint and the limit).
            DriverIOError: the device cannot obey (not started, closed, disconnected,
                faulted).
        """
        self._command(self.kinematics.check_joints(q))

    def stop(self) -> None:
        """Hold the current position. Idempotent; never raises, never blocks."""
        try:
            self._stop()
        except Exception:
            log.exception("end-effector %r: stop() failed", self.name)

    @abc.abstractmethod
    def _command(self, q: np.ndarray) -> None:
        """Backend command; ``q`` already checked."""

    @abc.abstractmethod
    def _stop(self) -> None:
        """Backend stop; may raise (``stop()`` catches and logs), must not block."""

    @abc.abstractmethod
    async def start(self) -> None:
        """Connect; ``DriverInitError`` naming what failed."""

    @abc.abstractmethod
    async def close(self) -> None:
        """Stop (hold), then disconnect. Idempotent; safe before ``start()``."""
