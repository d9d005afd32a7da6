"""Kinematics of the tendon-driven wrist: joint angles <-> motor angles.

Joints ``q = [roll, pitch, yaw, jaw]`` (rad) and motors ``m`` (rad, motor shaft angles, one
motor per joint in the same order) are related by a constant coupling matrix ``C`` (4x4) and
a motor offset ``m0`` (4,):

    m = C q + m0,        q = C^-1 (m - m0)

The diagonal holds the pulley ratios (motor radians per joint radian). Off-diagonal terms
come from tendons routed over another joint's pulley: when the pitch pulley turns, the yaw
and jaw tendons that wrap around it are pulled along, so their motors must turn to hold yaw
and jaw still.

:data:`DEFAULT_COUPLING` is an example for tests and the simulated cell, NOT a measured
device: roll 1:1, pitch 1.2:1, yaw and jaw 1:1, and the yaw and jaw tendons wrapping the
pitch pulley with 0.6 motor rad per pitch rad. It is lower triangular, det = 1.2.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from ..errors import DriverInitError, DriverIOError

__all__ = [
    "DEFAULT_COUPLING",
    "DEFAULT_JOINT_MAX",
    "DEFAULT_JOINT_MIN",
    "DEFAULT_MOTOR_MAX",
    "DEFAULT_MOTOR_MIN",
    "JOINTS",
    "EffectorCommandError",
    "WristKinematics",
]

#: Joint (and motor) names, in vector order.
JOINTS = ("roll", "pitch", "yaw", "jaw")

#: Example coupling (see the module docstring): rows are motors, columns joints.
DEFAULT_COUPLING = np.array(
    [
        [1.0, 0.0, 0.0, 0.0],  # roll motor: roll only
        [0.0, 1.2, 0.0, 0.0],  # pitch motor: pitch pulley ratio 1.2
        [0.0, 0.6, 1.0, 0.0],  # yaw tendon wraps the pitch pulley
        [0.0, 0.6, 0.0, 1.0],  # jaw tendon wraps the pitch pulley
    ]
)
#: Example joint limits, rad: roll +-180 deg, pitch and yaw +-80 deg, jaw 0 (closed) to 60 deg.
DEFAULT_JOINT_MIN = np.array([-math.pi, -math.radians(80), -math.radians(80), 0.0])
DEFAULT_JOINT_MAX = np.array([math.pi, math.radians(80), math.radians(80), math.radians(60)])
#: Example motor travel, rad (one turn either way).
DEFAULT_MOTOR_MIN = np.full(4, -2.0 * math.pi)
DEFAULT_MOTOR_MAX = np.full(4, 2.0 * math.pi)

# A coupling this ill-conditioned amplifies motor encoder noise into joint angles by more
# than this factor: a modelling error, not a wrist.
_MAX_CONDITION = 1e6


class EffectorCommandError(DriverIOError, ValueError):
    """An end-effector command was refused: a malformed vector or a target outside the joint
    or motor limits (the message names the joint and the limit). Both a
    :class:`DriverIOError` and a ``ValueError``."""


def _vector(value: object, what: str, error: type[Exception]) -> np.ndarray:
    try:
        out = np.array(value, dtype=float)
    except (TypeError, ValueError):
        raise error(f"{what} must be 4 numbers {list(JOINTS)}, got {value!r}") from None
    if out.shape != (4,):
        raise error(f"{what} must have shape (4,) {list(JOINTS)}, got {out.shape}")
    if not np.isfinite(out).all():
        raise error(f"{what} has non-finite entries: {out.tolist()}")
    return out


class WristKinematics:
    """The wrist's coupling and limits (immutable).

    Args:
        coupling: (4, 4) ``C`` with ``m = C q + m0``; must be well conditioned (invertible).
        joint_min, joint_max: (4,) joint limits, rad, min < max.
        motor_min, motor_max: (4,) motor limits, rad, min < max.
        motor_offset: (4,) ``m0``, motor angles at q = 0, rad.

    Raises:
        DriverInitError: bad shapes, non-finite values, empty ranges, or a singular coupling.
    """

    def __init__(
        self,
        coupling: Sequence[Sequence[float]] | np.ndarray = DEFAULT_COUPLING,
        joint_min: Sequence[float] | np.ndarray = DEFAULT_JOINT_MIN,
        joint_max: Sequence[float] | np.ndarray = DEFAULT_JOINT_MAX,
        motor_min: Sequence[float] | np.ndarray = DEFAULT_MOTOR_MIN,
        motor_max: Sequence[float] | np.ndarray = DEFAULT_MOTOR_MAX,
        motor_offset: Sequence[float] | np.ndarray = (0.0, 0.0, 0.0, 0.0),
    ) -> None:
        try:
            C = np.array(coupling, dtype=float)
        except (TypeError, ValueError):
            raise DriverInitError(f"coupling must be a 4x4 matrix, got {coupling!r}") from None
        if C.shape != (4, 4) or not np.isfinite(C).all():
            raise DriverInitError(f"coupling must be a finite 4x4 matrix, got shape {C.shape}")
        cond = float(np.linalg.cond(C))
        if not math.isfinite(cond) or cond > _MAX_CONDITION:
            raise DriverInitError(
                f"coupling is singular or ill-conditioned (condition number {cond:.3g} > "
                f"{_MAX_CONDITION:.0e}): joint angles cannot be recovered from motor angles"
            )
        vectors = {}
        for what, value in (
            ("joint_min", joint_min),
            ("joint_max", joint_max),
            ("motor_min", motor_min),
            ("motor_max", motor_max),
            ("motor_offset", motor_offset),
        ):
            vectors[what] = _vector(value, what, DriverInitError)
        for kind in ("joint", "motor"):
            low, high = vectors[f"{kind}_min"], vectors[f"{kind}_max"]
            for i, name in enumerate(JOINTS):
                if not low[i] < high[i]:
                    raise DriverInitError(
                        f"{kind} {name!r}: {kind}_min {float(low[i])!r} must be below "
                        f"{kind}_max {float(high[i])!r}"
                    )
        self.coupling = C
        self.coupling_inv = np.linalg.inv(C)
        self.joint_min = vectors["joint_min"]
        self.joint_max = vectors["joint_max"]
        self.motor_min = vectors["motor_min"]
        self.motor_max = vectors["motor_max"]
        self.motor_offset = vectors["motor_offset"]
        for array in (
            self.coupling, self.coupling_inv, self.joint_min, self.joint_max,
            self.motor_min, self.motor_max, self.motor_offset,
        ):
            array.flags.writeable = False

    def joints_to_motors(self, q: Sequence[float] | np.ndarray) -> np.ndarray:
        """(4,) motor angles (rad) for joint angles ``q`` (rad); no limit check."""
        return self.coupling @ _vector(q, "q", EffectorCommandError) + self.motor_offset

    def motors_to_joints(self, m: Sequence[float] | np.ndarray) -> np.ndarray:
        """(4,) joint angles (rad) for motor angles ``m`` (rad); no limit check."""
        return self.coupling_inv @ (_vector(m, "m", EffectorCommandError) - self.motor_offset)

    def check_joints(self, q: Sequence[float] | np.ndarray) -> np.ndarray:
        """Return ``q`` as a (4,) float copy if it and its motor angles are within limits.

        Raises:
            EffectorCommandError: malformed ``q``, or a joint or motor outside its limits
                (the message names it, its value and the limit, in rad and degrees).
        """
        q = _vector(q, "q", EffectorCommandError)
        _within(q, self.joint_min, self.joint_max, "joint")
        _within(self.coupling @ q + self.motor_offset, self.motor_min, self.motor_max, "motor")
        return q

    def check_motors(self, m: Sequence[float] | np.ndarray) -> np.ndarray:
        """Return ``m`` as a (4,) float copy if within the motor limits;
        ``EffectorCommandError`` otherwise."""
        m = _vector(m, "m", EffectorCommandError)
        _within(m, self.motor_min, self.motor_max, "motor")
        return m

    def __repr__(self) -> str:
        return f"WristKinematics(coupling={self.coupling.tolist()})"


def _within(x: np.ndarray, low: np.ndarray, high: np.ndarray, kind: str) -> None:
    for i, name in enumerate(JOINTS):
        if x[i] < low[i]:
            side, limit = "below its lower", low[i]
        elif x[i] > high[i]:
            side, limit = "above its upper", high[i]
        else:
            continue
        raise EffectorCommandError(
            f"{kind} {name!r} = {x[i]:.4f} rad ({math.degrees(x[i]):.1f} deg) is {side} limit "
            f"{limit:.4f} rad ({math.degrees(limit):.1f} deg)"
        )
