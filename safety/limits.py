"""Motion limits: the Cartesian speed limiter and the workspace box (docs/safety.md).

Poses are ``T_B_tcp``: 4x4 poses of the tool centre point in the robot base frame ``B``,
metres. Speeds are m/s and rad/s, periods s. Pure math, no I/O, no clock.
"""

from __future__ import annotations

import math
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike

from oralnav.checks import NumberMessages, positive_number, rigid_transform
from oralnav.control.motion import step_toward

from .errors import InputError, LimitError

#: ISO 10218 reduced speed (m/s): no Cartesian TCP speed limit may exceed it. Kept here as
#: well as in ``oralnav.config.daemon`` because safety must not import config (config
#: builds safety objects); a test checks that the two agree.
ISO_10218_REDUCED_SPEED = 0.25

#: Tolerance on a pose's rotation block (orthonormality) and bottom row.
POSE_TOL = 1e-6

_AXES = "xyz"


def as_pose(T: ArrayLike, what: str = "pose") -> np.ndarray:
    """``T`` as a float 4x4 rigid transform, or :class:`InputError` saying what is wrong.

    Rigid within :data:`POSE_TOL`; not a copy when ``T`` already is a float array."""
    # oralnav.checks' default wording is this function's (tests match on it)
    return rigid_transform(T, what, InputError, tol=POSE_TOL)


def as_point(p: ArrayLike, what: str = "point") -> np.ndarray:
    """``p`` as a finite float 3-vector (m), or :class:`InputError`."""
    try:
        a = np.asarray(p, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"{what} must be a 3-vector, got {p!r}") from None
    if a.shape != (3,):
        raise InputError(f"{what} must be a 3-vector, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise InputError(f"{what} has non-finite entries: {a.tolist()}")
    return a


def _as_points(p: ArrayLike | None, what: str) -> np.ndarray | None:
    if p is None:
        return None
    try:
        a = np.asarray(p, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"{what} must be a 3-vector or an (N, 3) array, got {p!r}") from None
    if a.ndim == 1 and a.shape == (3,):
        a = a[None]
    if a.ndim != 2 or a.shape[1] != 3:
        raise InputError(f"{what} must be a 3-vector or an (N, 3) array, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise InputError(f"{what} has non-finite entries")
    return a if len(a) else None


#: A speed limit's wording: NaN, infinities and values <= 0 are refused alike.
_SPEED = NumberMessages(not_finite="{what} must be positive and finite, got {value!r}",
                        not_positive="{what} must be positive and finite, got {value!r}")


def _speed(x: float, what: str) -> float:
    """A speed limit (m/s or rad/s) as a float > 0, or :class:`InputError`."""
    return positive_number(x, what, InputError, allow_bool=True, messages=_SPEED)


class SpeedSettings(Protocol):
    """What :meth:`SpeedLimiter.from_settings` reads (``[safety]``, ``SafetySection``)."""

    max_speed: float
    near_patient_speed: float
    max_angular_speed: float
    near_patient_angular_speed: float
    near_patient_distance: float


class SpeedLimiter:
    """Steps a TCP setpoint toward a target without exceeding a linear speed (m/s) or an
    angular speed (rad/s).

    Translation moves along the straight line, rotation along the slerp geodesic (scipy
    ``Rotation``), both by the same fraction of the way each period, so they arrive
    together. Within ``near_patient_distance`` (m) of any given point (the opener, the
    targets) the lower near-patient speeds apply.
    """

    def __init__(self, max_speed: float, max_angular_speed: float, *,
                 near_patient_speed: float | None = None,
                 near_patient_angular_speed: float | None = None,
                 near_patient_distance: float = 0.0) -> None:
        self.max_speed = _speed(max_speed, "max_speed (m/s)")
        self.max_angular_speed = _speed(max_angular_speed, "max_angular_speed (rad/s)")
        self.near_patient_speed = (self.max_speed if near_patient_speed is None else
                                   _speed(near_patient_speed, "near_patient_speed (m/s)"))
        self.near_patient_angular_speed = (
            self.max_angular_speed if near_patient_angular_speed is None
            else _speed(near_patient_angular_speed, "near_patient_angular_speed (rad/s)"))
        for v, what in ((self.max_speed, "max_speed"),
                        (self.near_patient_speed, "near_patient_speed")):
            if v > ISO_10218_REDUCED_SPEED:
                raise LimitError(f"{what} {v} m/s exceeds the ISO 10218 reduced speed, "
                                 f"{ISO_10218_REDUCED_SPEED} m/s")
        if self.near_patient_speed > self.max_speed:
            raise InputError(f"near_patient_speed ({self.near_patient_speed} m/s) must not "
                             f"exceed max_speed ({self.max_speed} m/s)")
        if self.near_patient_angular_speed > self.max_angular_speed:
            raise InputError(f"near_patient_angular_speed ({self.near_patient_angular_speed}"
                             f" rad/s) must not exceed max_angular_speed "
                             f"({self.max_angular_speed} rad/s)")
        try:
            d = float(near_patient_distance)
        except (TypeError, ValueError):
            d = math.nan
        if not math.isfinite(d) or d < 0:
            raise InputError(f"near_patient_distance (m) must be >= 0 and finite, "
                             f"got {near_patient_distance!r}")
        self.near_patient_distance = d

    @classmethod
    def from_settings(cls, settings: SpeedSettings) -> SpeedLimiter:
        s = settings
        return cls(s.max_speed, s.max_angular_speed, near_patient_speed=s.near_patient_speed,
                   near_patient_angular_speed=s.near_patient_angular_speed,
                   near_patient_distance=s.near_patient_distance)

    def is_near(self, position: ArrayLike, near: ArrayLike | None) -> bool:
        """Whether ``position`` (m, base frame) lies within ``near_patient_distance`` of any
        of the ``near`` points ((3,) or (N, 3), m, base frame; None: none)."""
        pts = _as_points(near, "near-patient points")
        return self._near(as_point(position, "position"), pts)

    def _near(self, p: np.ndarray, pts: np.ndarray | None) -> bool:
        if pts is None:
            return False
        return bool(np.min(np.linalg.norm(pts - p, axis=1)) <= self.near_patient_distance)

    def speeds(self, position: ArrayLike, near: ArrayLike | None = None
               ) -> tuple[float, float]:
        """The (linear m/s, angular rad/s) limits that apply at ``position``."""
        if self.is_near(position, near):
            return self.near_patient_speed, self.near_patient_angular_speed
        return self.max_speed, self.max_angular_speed

    def step(self, T_B_current: ArrayLike, T_B_target: ArrayLike, dt: float,
             near: ArrayLike | None = None) -> np.ndarray:
        """The next setpoint, ``dt`` s after ``T_B_current``, toward ``T_B_target``.

        ``T_B_current`` is the last commanded setpoint (or the measured TCP pose); the
        result moves at most ``v dt`` metres and ``w dt`` radians from it, where (v, w)
        are the near-patient speeds if the current position or the full-speed step lies
        within ``near_patient_distance`` of a ``near`` point, else the maximum speeds.
        Returns a copy of the target once it is within one step.
        """
        Tc = as_pose(T_B_current, "current TCP pose T_B_tcp")
        Tt = as_pose(T_B_target, "target TCP pose T_B_tcp")
        dt = _speed(dt, "dt (s)")
        pts = _as_points(near, "near-patient points")
        pc, dp = Tc[:3, 3], Tt[:3, 3] - Tc[:3, 3]
        v, w = self.max_speed, self.max_angular_speed
        if self._near(pc, pts):
            v, w = self.near_patient_speed, self.near_patient_angular_speed
        # control.motion's geodesic step: SciPy's Rotation costs ~0.1 ms here, 5 % of
        # a 2 ms period (oralnav bench control)
        out, s = step_toward(Tc, Tt, v * dt, w * dt)
        # entering the zone this period: take the slow step (the conservative choice)
        if (v, w) != (self.near_patient_speed, self.near_patient_angular_speed) \
                and self._near(pc + s * dp, pts):
            out, s = step_toward(Tc, Tt, self.near_patient_speed * dt,
                                 self.near_patient_angular_speed * dt)
        return out


class WorkspaceSettings(Protocol):
    workspace_min: tuple[float, float, float]
    workspace_max: tuple[float, float, float]


class WorkspaceBox:
    """An axis-aligned box in the base frame (m) that the TCP must stay in; bounds
    inclusive."""

    def __init__(self, minimum: ArrayLike, maximum: ArrayLike) -> None:
        lo = as_point(minimum, "workspace minimum (m)")
        hi = as_point(maximum, "workspace maximum (m)")
        bad = [f"{a}: {lo[i]} >= {hi[i]}" for i, a in enumerate(_AXES) if not lo[i] < hi[i]]
        if bad:
            raise InputError("workspace minimum must be below maximum on every axis ("
                             + ", ".join(bad) + ")")
        self.minimum, self.maximum = lo, hi
        self.minimum.flags.writeable = False
        self.maximum.flags.writeable = False

    @classmethod
    def from_settings(cls, settings: WorkspaceSettings) -> WorkspaceBox:
        return cls(settings.workspace_min, settings.workspace_max)

    @staticmethod
    def _position(x: ArrayLike) -> np.ndarray:
        try:
            shape = np.shape(x)
        except (TypeError, ValueError):  # ragged: as_point says what is wrong
            shape = None
        if shape == (4, 4):
            return as_pose(x, "TCP pose T_B_tcp")[:3, 3]
        return as_point(x, "TCP position")

    def violations(self, x: ArrayLike) -> list[tuple[str, float]]:
        """Per axis outside the box: (axis, signed excess in m; > 0 above the maximum,
        < 0 below the minimum). ``x`` is a 3-vector or a 4x4 pose, base frame."""
        p = self._position(x)
        out = []
        for i, a in enumerate(_AXES):
            if p[i] > self.maximum[i]:
                out.append((a, float(p[i] - self.maximum[i])))
            elif p[i] < self.minimum[i]:
                out.append((a, float(p[i] - self.minimum[i])))
        return out

    def contains(self, x: ArrayLike) -> bool:
        """Whether the point (or the pose's position) lies in the box, bounds included."""
        return not self.violations(x)

    def check(self, x: ArrayLike, what: str = "TCP") -> None:
        """Raise :class:`LimitError` naming each axis outside the box and by how much."""
        p = self._position(x)
        parts = []
        for a, excess in self.violations(p):
            i = _AXES.index(a)
            if excess > 0:
                parts.append(f"{a} = {p[i]:.4f} m is {excess:.4f} m above the maximum "
                             f"{self.maximum[i]:.4f} m")
            else:
                parts.append(f"{a} = {p[i]:.4f} m is {-excess:.4f} m below the minimum "
                             f"{self.minimum[i]:.4f} m")
        if parts:
            raise LimitError(f"{what} outside the workspace (base frame): " + "; ".join(parts))
