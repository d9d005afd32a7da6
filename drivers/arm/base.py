"""The arm contract: a Cartesian, servoL/speedL-style robot arm (a UR arm through ur-rtde).

All poses are ``T_B_tcp``: the 4x4 pose of the tool centre point in the robot base frame B,
metres. Twists are ``[vx, vy, vz, wx, wy, wz]`` in the base frame, m/s and rad/s.

Every method except ``start()``/``close()`` is synchronous, thread-safe and non-blocking: the
500 Hz control thread and the event loop both call them. The public methods here are
template methods: they validate their arguments, then call the backend's ``_servo``,
``_speed`` and ``_stop``; :meth:`Arm.stop` catches and logs everything so that the latched
stop path can never be interrupted by a driver error.
"""

from __future__ import annotations

import abc
import logging
from dataclasses import dataclass, field

import numpy as np

from oralnav.checks import NumberMessages, TransformMessages, positive_number, rigid_transform

from ..errors import DriverIOError
from ..lifecycle import AsyncLifecycle

__all__ = ["Arm", "ArmCommandError", "ArmState", "check_pose", "check_twist"]

log = logging.getLogger(__name__)

# Tolerance of the rigid-transform check: a pose built from float math (or read from a
# TOML file with 6-7 digits) is orthonormal to about 1e-6, not to machine precision.
_RIGID_TOL = 1e-6

# The arm's wording (tests match on it).
_POSE_MESSAGES = TransformMessages(
    not_numbers="{what} must be a 4x4 array of numbers, got {value!r}",
    shape="{what} must have shape (4, 4), got {shape}",
    non_finite="{what} has non-finite entries: {entries}",
    bottom_row="{what} bottom row must be [0, 0, 0, 1], got {row}",
    rotation="{what} rotation block is not a proper rotation (orthonormal, det +1)",
)
_SECONDS = NumberMessages.uniform("{what} must be a finite number of seconds > 0, got {value!r}")
_M_PER_S2 = NumberMessages.uniform("{what} must be a finite number of m/s^2 > 0, got {value!r}")


class ArmCommandError(DriverIOError, ValueError):
    """A motion command was refused because an argument is malformed (the message names it).

    Both a :class:`DriverIOError` (the command did not reach the arm) and a ``ValueError``.
    """


def _readonly(array: np.ndarray) -> np.ndarray:
    out = np.array(array, dtype=float)  # always a private copy
    out.flags.writeable = False
    return out


@dataclass(frozen=True, eq=False)
class ArmState:
    """One consistent snapshot of the arm.

    Attributes:
        timestamp: when the arm reported this state, seconds on the driver's clock. A
            timestamp that stops advancing means the arm went silent.
        T_B_tcp: (4, 4) pose of the TCP in the base frame B, metres (read-only array).
        tcp_speed: (6,) TCP twist ``[vx, vy, vz, wx, wy, wz]`` in the base frame, m/s and
            rad/s (read-only array).
        connected: the driver talks to the arm.
        protective_stop: the arm is in a protective stop (must be cleared at the arm).
        emergency_stop: the arm's own e-stop chain is open.
        ready: the arm accepts motion commands (control program running, no stop active).
        tcp_force: (6,) wrench the TCP force sensor measures ``[fx, fy, fz, tx, ty, tz]`` in
            the base frame, N and N m (read-only array; zeros for an arm without one). The
            operator's push in guided (admittance) motion.
    """

    timestamp: float
    T_B_tcp: np.ndarray
    tcp_speed: np.ndarray
    connected: bool
    protective_stop: bool
    emergency_stop: bool
    ready: bool
    tcp_force: np.ndarray = field(default_factory=lambda: np.zeros(6))

    def __post_init__(self) -> None:
        object.__setattr__(self, "T_B_tcp", _readonly(self.T_B_tcp))
        object.__setattr__(self, "tcp_speed", _readonly(self.tcp_speed))
        object.__setattr__(self, "tcp_force", _readonly(self.tcp_force))


def check_pose(T: object, what: str = "T_B_tcp") -> np.ndarray:
    """Return ``T`` as a float (4, 4) copy if it is a finite rigid transform, its bottom row
    exactly [0, 0, 0, 1].

    Raises:
        ArmCommandError: wrong shape, non-finite entries, a bottom row other than
            [0, 0, 0, 1], or a rotation block that is not orthonormal with determinant +1.
    """
    out = rigid_transform(T, what, ArmCommandError, tol=_RIGID_TOL, copy=True,
                          messages=_POSE_MESSAGES)
    out[3] = [0.0, 0.0, 0.0, 1.0]  # within _RIGID_TOL: the arm gets the exact row
    return out


def check_twist(twist: object, what: str = "twist") -> np.ndarray:
    """Return ``twist`` as a float (6,) copy if it is finite; ``ArmCommandError`` if not."""
    try:
        out = np.array(twist, dtype=float)
    except (TypeError, ValueError):
        raise ArmCommandError(f"{what} must be 6 numbers, got {twist!r}") from None
    if out.shape != (6,):
        raise ArmCommandError(f"{what} must have shape (6,) [vx vy vz wx wy wz], got {out.shape}")
    if not np.isfinite(out).all():
        raise ArmCommandError(f"{what} has non-finite entries: {out.tolist()}")
    return out


class Arm(AsyncLifecycle, abc.ABC):
    """Abstract arm. Backends implement :meth:`state`, :meth:`kick`, ``_servo``, ``_speed``,
    ``_stop``, :meth:`start` and :meth:`close`.

    Motion commands raise :class:`DriverIOError` when the arm cannot obey them (not started,
    closed, disconnected, protective or emergency stop, not ready): the caller must never
    believe the arm moves when it does not. :meth:`stop` is the exception: it never raises.
    A backend has a watchdog: the arm stops itself when it has received neither a motion
    command nor :meth:`kick` for ``watchdog_timeout`` seconds.
    """

    def __init__(self, name: str = "arm") -> None:
        self.name = name

    @abc.abstractmethod
    def state(self) -> ArmState:
        """The latest state snapshot (consistent, read under the driver's lock)."""

    def servo(self, T_B_tcp: np.ndarray, dt: float) -> None:
        """Move the TCP to ``T_B_tcp`` (4x4, base frame, m) over the next period ``dt`` (s).

        Like ur-rtde ``servoL``: called once per control period with the next set point.
        Raises ``ArmCommandError`` for a malformed pose or ``dt``, ``DriverIOError`` when the
        arm cannot obey.
        """
        T = check_pose(T_B_tcp, "T_B_tcp")
        self._servo(T, positive_number(dt, "dt", ArmCommandError, messages=_SECONDS))

    def speed(self, twist: np.ndarray, accel: float) -> None:
        """Move at ``twist`` (6,) [m/s, rad/s], base frame, reached with linear acceleration
        ``accel`` (m/s^2). Like ur-rtde ``speedL``; it lasts until the next command, a stop or
        the watchdog. Raises like :meth:`servo`."""
        v = check_twist(twist, "twist")
        self._speed(v, positive_number(accel, "accel", ArmCommandError, messages=_M_PER_S2))

    def stop(self) -> None:
        """Decelerate to a stand-still and hold. Idempotent; never raises, never blocks.

        On the latched-stop path: a failure is logged (the arm's own watchdog then stops it).
        """
        try:
            self._stop()
        except Exception:
            log.exception("arm %r: stop() failed; relying on the arm's watchdog", self.name)

    @abc.abstractmethod
    def kick(self) -> None:
        """Feed the arm's watchdog without commanding motion; ``DriverIOError`` if the arm
        cannot be reached."""

    @abc.abstractmethod
    def _servo(self, T_B_tcp: np.ndarray, dt: float) -> None:
        """Backend servo; arguments already checked."""

    @abc.abstractmethod
    def _speed(self, twist: np.ndarray, accel: float) -> None:
        """Backend speed; arguments already checked."""

    @abc.abstractmethod
    def _stop(self) -> None:
        """Backend stop; may raise (``stop()`` catches and logs), must not block."""

    @abc.abstractmethod
    async def start(self) -> None:
        """Connect; ``DriverInitError`` naming what failed."""

    @abc.abstractmethod
    async def close(self) -> None:
        """Stop the arm, then disconnect. Idempotent; safe before ``start()``."""
