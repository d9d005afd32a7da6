"""Admittance control inside the virtual fixture: M v' + D v = F_operator + F_fixture.

The operator pushes the instrument (a wrist force sensor measures the push; in simulation
``oralnav.sim.world.hand.ScriptedHand`` scripts it) and the robot moves as a virtual mass ``M``
(kg) in a viscous medium ``D`` (N s/m): a steady push ``F`` gives the steady speed
``F / D``, reached with the time constant ``M / D``. The virtual fixture
(``oralnav.control.guidance.virtual_fixture``) adds a forbidden-region wall and the axial guidance.

Translation only: the controller moves the commanded tool point; the caller holds the
tool's orientation along the planned axis. Everything is in the fixture's frame ``F``
(forces in N, positions in m, velocities in m/s, the same frame as the fixture's points):
the caller rotates the sensor's force into ``F`` and transforms the commanded point
(the TCP setpoint) from ``F`` to the robot base frame before sending it.

One period (:meth:`AdmittanceController.step`), in order:

1. the operator force: a non-finite one is refused (:class:`AdmittanceError`, the state
   untouched, so the control loop can latch its stop); its magnitude is clamped to
   ``max_force`` (sensor spikes) and shrunk by ``deadband`` (sensor noise; continuous:
   ``|F| -> max(|F| - deadband, 0)``, direction kept);
2. guidance: with ``w`` the fixture's guidance weight at the commanded point (1 in the
   cylinder), ``w`` times the lateral component is removed from the operator force and
   from the carried velocity, so in the cylinder only axial motion is commanded;
3. integration over ``dt`` with the force held constant (zero-order hold), **exact**
   for the mass-damper: ``a = exp(-dt D / M)``,
   ``v1 = a v0 + (1 - a) F / D``, ``x1 = x0 + (M / D)(1 - a) v0 + (dt - (M / D)(1 - a)) F / D``.
   So the steady speed and the time constant are exactly those of the continuous law at
   any ``dt``, and ``|a| < 1`` makes it unconditionally stable. Where this free step
   would end outside the region (in the forbidden region), the wall acts: along its
   inward normal ``n`` at that end point, the motion is integrated again with the wall's
   spring taken at the *end* of the step (implicit; a 1-D linear solve across the wall's
   plane, ``y1 = (y0 + c v0 + e F) / (1 + e k)`` with ``c, e`` the coefficients above),
   and with the wall's damping added to ``D`` while the point moves deeper. An explicit
   spring would overshoot and ring once ``k dt / D > 2``; the implicit one has a 2x2
   step matrix of determinant ``a / (1 + e k) < 1`` that passes Jury's test for all
   ``dt, k, M, D > 0``, and at a large ``dt`` it lands on the wall's static equilibrium
   ``F / k`` in one step. The wall only pushes (it acts only on steps that end outside).
   Only this restoring push can move the tool laterally in the cylinder.
4. the speed clamp: the velocity and the step's displacement are scaled so that neither
   exceeds ``max_speed`` (m/s; default 0.05, well under ISO 10218's reduced 0.25 m/s);
5. the hard projection: the point is clamped axially to ``s >= 0`` (never past the
   target) and radially to ``R(s) + wall_tolerance`` (:meth:`VirtualFixture.project`),
   the velocity component driving further out is dropped (an inelastic stop), and the
   displacement re-checked against the speed limit (the funnel is not convex at its
   kinks; in the rare case a re-clamp still leaves the step too long, the point holds).

Costs: the period is plain float arithmetic (no numpy inside), about 10-20 us in CPython;
``tests/control/guidance/test_admittance.py`` measures it against the 0.2 ms budget of a 500 Hz
loop on a slow 2-core machine.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike

from oralnav.control.errors import AdmittanceError
from oralnav.control.guidance.virtual_fixture import VirtualFixture, finite_number

__all__ = ["AdmittanceError", "AdmittanceSettings", "AdmittanceState",
           "AdmittanceController", "ISO_10218_REDUCED_SPEED"]

#: ISO 10218 reduced speed (m/s); no admittance speed limit may exceed it (the same figure
#: as ``oralnav.safety.limits``, kept here too: control must not import safety).
ISO_10218_REDUCED_SPEED = 0.25

#: Hold the point when a re-clamped step still exceeds the speed limit by this fraction.
_SPEED_SLACK = 1e-9
#: Shorten-and-reclamp rounds tried before holding the point (see step 5).
_RECLAMPS = 3


def _setting(x: object, what: str, *, positive: bool = True) -> float:
    v = finite_number(x, what, AdmittanceError)
    if positive and v <= 0.0:
        raise AdmittanceError(f"{what} must be positive, got {x!r}")
    if not positive and v < 0.0:
        raise AdmittanceError(f"{what} must be >= 0, got {x!r}")
    return v


@dataclass(frozen=True)
class AdmittanceSettings:
    """Parameters of the admittance law and its limits (SI units), validated on creation.

    - ``mass`` M (kg) and ``damping`` D (N s/m): a push F reaches the speed F / D with the
      time constant M / D (defaults: 5 N -> 0.05 m/s in 20 ms);
    - ``fixture_stiffness`` (N/m) and ``fixture_damping`` (N s/m, >= 0): the forbidden-
      region wall; the damping resists only motion deeper into the wall;
    - ``max_speed`` (m/s): the commanded point's speed limit, at most ISO 10218's reduced
      speed 0.25 m/s;
    - ``max_force`` (N): the operator force's magnitude is clamped to this (sensor spikes);
    - ``deadband`` (N, >= 0, below ``max_force``): forces below it are ignored (noise);
    - ``wall_tolerance`` (m, >= 0): how far past the wall (radially) the commanded point
      may go, the band in which the wall's spring acts, before the hard clamp.
    """

    mass: float = 2.0
    damping: float = 100.0
    fixture_stiffness: float = 10_000.0
    fixture_damping: float = 200.0
    max_speed: float = 0.05
    max_force: float = 30.0
    deadband: float = 0.3
    wall_tolerance: float = 5e-4

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        set_(self, "mass", _setting(self.mass, "mass (kg)"))
        set_(self, "damping", _setting(self.damping, "damping (N s/m)"))
        set_(self, "fixture_stiffness",
             _setting(self.fixture_stiffness, "fixture_stiffness (N/m)"))
        set_(self, "fixture_damping",
             _setting(self.fixture_damping, "fixture_damping (N s/m)", positive=False))
        set_(self, "max_speed", _setting(self.max_speed, "max_speed (m/s)"))
        set_(self, "max_force", _setting(self.max_force, "max_force (N)"))
        set_(self, "deadband", _setting(self.deadband, "deadband (N)", positive=False))
        set_(self, "wall_tolerance",
             _setting(self.wall_tolerance, "wall_tolerance (m)", positive=False))
        if self.max_speed > ISO_10218_REDUCED_SPEED:
            raise AdmittanceError(f"max_speed (m/s) {self.max_speed} exceeds the ISO 10218 "
                                  f"reduced speed, {ISO_10218_REDUCED_SPEED} m/s")
        if self.deadband >= self.max_force:
            raise AdmittanceError(f"deadband (N) {self.deadband} must be below max_force "
                                  f"(N) {self.max_force}: no force would get through")

    @property
    def time_constant(self) -> float:
        """M / D (s): how fast the speed follows a change of force."""
        return self.mass / self.damping


class AdmittanceState(NamedTuple):
    """The controller's output for one period; all in the fixture frame ``F``.

    ``position`` (3,), m: the commanded tool point (the setpoint for the arm's TCP);
    ``velocity`` (3,), m/s; ``boundary_distance`` (m): the radial signed distance to the
    fixture's wall (> 0 inside, >= ``-wall_tolerance`` always, to rounding); ``guided``: the axial
    guidance acted (weight > 0); ``pushed``: the wall's spring or damper acted this
    period; ``clamped``: the hard projection (or the speed re-check) moved the point;
    ``force_fixture`` (3,), N: the wall's force this period (zero when not pushed).
    """

    position: np.ndarray
    velocity: np.ndarray
    boundary_distance: float
    guided: bool
    pushed: bool
    clamped: bool
    force_fixture: np.ndarray


class _Coefficients(NamedTuple):
    a: float   # velocity decay over dt
    b: float   # velocity gain of the force (s/kg... m/s per N)
    c: float   # position gain of the initial velocity (s)
    e: float   # position gain of the force (m per N)


def _zoh(h: float, mass: float, damping: float) -> _Coefficients:
    """Exact zero-order-hold coefficients of M v' + D v = F over ``h`` seconds."""
    tau = mass / damping
    x = h / tau
    one_minus_a = -math.expm1(-x)
    c = tau * one_minus_a
    # h - c = tau (x - 1 + exp(-x)): a series where the difference would cancel
    rest = tau * x * x * (0.5 - x / 6.0 + x * x / 24.0) if x < 1e-3 else h - c
    return _Coefficients(1.0 - one_minus_a, one_minus_a / damping, c, rest / damping)


class AdmittanceController:
    """The admittance law inside a :class:`VirtualFixture`; see the module docstring.

    Call :meth:`reset` with the tool's current point, then :meth:`step` once per control
    period with the operator force. The controller's state is the commanded point (the
    setpoint to send to the arm's TCP, after the caller's transform to the base frame)
    and its velocity, both in the fixture frame ``F``; it does no I/O and reads no clock.
    Translation only: the caller holds the tool's orientation along the planned axis.
    """

    def __init__(self, settings: AdmittanceSettings, fixture: VirtualFixture) -> None:
        if not isinstance(settings, AdmittanceSettings):
            raise AdmittanceError(f"settings must be AdmittanceSettings, got {settings!r}")
        if not isinstance(fixture, VirtualFixture):
            raise AdmittanceError(f"fixture must be a VirtualFixture, got {fixture!r}")
        self.settings = settings
        self.fixture = fixture
        self._p: tuple[float, float, float] | None = None
        self._v = (0.0, 0.0, 0.0)
        self._dt = math.nan
        self._free = self._wall = _Coefficients(1.0, 0.0, 0.0, 0.0)

    # -- state -------------------------------------------------------------------------
    @property
    def position(self) -> np.ndarray:
        """The commanded point (3,), m, frame ``F`` (:class:`AdmittanceError` before
        :meth:`reset`)."""
        if self._p is None:
            raise AdmittanceError("the admittance has no position yet: call reset(p) first")
        return np.array(self._p)

    @property
    def velocity(self) -> np.ndarray:
        """The commanded velocity (3,), m/s, frame ``F``."""
        return np.array(self._v)

    def reset(self, p: ArrayLike, v: ArrayLike | None = None) -> AdmittanceState:
        """Start from the point ``p`` (3,), m, frame ``F`` (the tool's current point),
        at rest or with velocity ``v`` (3,), m/s (clamped to ``max_speed``).

        ``p`` must lie in the fixture, widened by ``wall_tolerance`` (within 1 um, then
        it is snapped onto it): the controller never jumps the arm onto the fixture;
        move it there first. Otherwise :class:`AdmittanceError`, the state untouched.
        """
        fx = self.fixture
        x, y, z = self._vec(p, "start position p (m, fixture frame)")
        vx, vy, vz = (0.0, 0.0, 0.0) if v is None else self._vec(v, "start velocity v (m/s)")
        tol = self.settings.wall_tolerance
        px, py, pz, _, _ = fx._project(x, y, z, tol)
        off = math.sqrt((px - x) ** 2 + (py - y) ** 2 + (pz - z) ** 2)
        if off > 1e-6:
            s, _, _, _, r = fx._local(x, y, z)
            raise AdmittanceError(
                f"start position {[x, y, z]} m lies {off * 1e3:.3f} mm outside the virtual "
                f"fixture (axial s = {s * 1e3:.3f} mm, radius {r * 1e3:.3f} mm, allowed "
                f"{fx._radius(max(s, 0.0)) * 1e3:.3f} mm + {tol * 1e3:.3f} mm tolerance): "
                f"move the tool onto the fixture first")
        speed = math.sqrt(vx * vx + vy * vy + vz * vz)
        vmax = self.settings.max_speed
        if speed > vmax:
            f = vmax / speed
            vx, vy, vz = vx * f, vy * f, vz * f
        self._p, self._v = (px, py, pz), (vx, vy, vz)
        s, rx, ry, rz, r = fx._local(px, py, pz)
        return AdmittanceState(np.array(self._p), np.array(self._v),
                               fx._signed(s, rx, ry, rz, r), fx._weight(s) > 0.0,
                               False, off > 0.0, np.zeros(3))

    @staticmethod
    def _vec(a: ArrayLike, what: str) -> tuple[float, float, float]:
        try:
            x, y, z = (float(c) for c in np.asarray(a, dtype=float).reshape(-1))
        except (TypeError, ValueError):
            raise AdmittanceError(f"{what} must be a 3-vector, got {a!r}") from None
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
            raise AdmittanceError(f"{what} has non-finite entries: {[x, y, z]}")
        return x, y, z

    # -- one period ----------------------------------------------------------------------
    def step(self, force_operator: ArrayLike, dt: float) -> AdmittanceState:
        """Advance one period of ``dt`` s (> 0) under the operator force (3,), N, frame
        ``F``; return the new commanded state. Refuses (:class:`AdmittanceError`, state
        untouched) a non-finite force or ``dt``, or a call before :meth:`reset`."""
        if self._p is None:
            raise AdmittanceError("the admittance has no position yet: call reset(p) first")
        try:
            fx_, fy_, fz_ = force_operator  # type: ignore[misc]
            fx, fy, fz = float(fx_), float(fy_), float(fz_)
            h = float(dt)
        except (TypeError, ValueError):
            raise AdmittanceError(f"force_operator must be a 3-vector (N) and dt a number "
                                  f"(s), got {force_operator!r}, {dt!r}") from None
        if not (math.isfinite(fx) and math.isfinite(fy) and math.isfinite(fz)):
            raise AdmittanceError(f"operator force has non-finite entries: {[fx, fy, fz]}")
        if not (h > 0.0 and math.isfinite(h)):
            raise AdmittanceError(f"dt (s) must be positive and finite, got {dt!r}")
        st = self.settings
        fix = self.fixture

        # 1. force: spike clamp, then a continuous deadband
        fmag = math.sqrt(fx * fx + fy * fy + fz * fz)
        if fmag <= st.deadband:
            fx = fy = fz = 0.0
        else:
            g = (min(fmag, st.max_force) - st.deadband) / fmag
            fx, fy, fz = fx * g, fy * g, fz * g

        x0, y0, z0 = self._p
        vx, vy, vz = self._v
        s0 = fix._local(x0, y0, z0)[0]

        # 2. guidance: drop w times the lateral part of the force and the carried velocity
        w = fix._weight(s0)
        if w > 0.0:
            dx, dy, dz = fix._d  # type: ignore[attr-defined]
            a = fx * dx + fy * dy + fz * dz
            fx, fy, fz = fx - w * (fx - a * dx), fy - w * (fy - a * dy), fz - w * (fz - a * dz)
            a = vx * dx + vy * dy + vz * dz
            vx, vy, vz = vx - w * (vx - a * dx), vy - w * (vy - a * dy), vz - w * (vz - a * dz)

        # 3. integration: exact ZOH for M, D; then the wall, implicit, along its normal
        if h != self._dt:
            self._dt = h
            self._free = _zoh(h, st.mass, st.damping)
            self._wall = _zoh(h, st.mass, st.damping + st.fixture_damping)
        cf = self._free
        v0x, v0y, v0z = vx, vy, vz
        ddx = cf.c * vx + cf.e * fx
        ddy = cf.c * vy + cf.e * fy
        ddz = cf.c * vz + cf.e * fz
        vx = cf.a * vx + cf.b * fx
        vy = cf.a * vy + cf.b * fy
        vz = cf.a * vz + cf.b * fz
        # Where the free step ends outside the region, the wall acts: its spring taken at
        # the end of the step, across the plane of the wall there (inward normal n).
        depth, nx, ny, nz = fix._contact(x0 + ddx, y0 + ddy, z0 + ddz)
        pushed = False
        ffix = 0.0
        if depth > 0.0:
            vn0 = v0x * nx + v0y * ny + v0z * nz
            fn = fx * nx + fy * ny + fz * nz
            dn = ddx * nx + ddy * ny + ddz * nz
            yw = -depth - dn  # the start's position across the wall's plane (> 0 inside)
            k = st.fixture_stiffness
            # The wall's damper resists only going deeper. If, damped, the step would end
            # inside, it is solved again undamped: the free step ends outside, so the
            # spring alone then acts (the wall force is set by where the step ends).
            for cn in ((self._wall, cf) if vn0 < 0.0 < st.fixture_damping else (cf,)):
                y_free = yw + cn.c * vn0 + cn.e * fn
                if y_free < 0.0:
                    y1 = y_free / (1.0 + cn.e * k)
                    spring = -k * y1
                    vn1 = cn.a * vn0 + cn.b * (fn + spring)
                    gd = (y1 - yw) - dn  # the normal displacement replaces the free one
                    gv = vn1 - (vx * nx + vy * ny + vz * nz)
                    ddx, ddy, ddz = ddx + gd * nx, ddy + gd * ny, ddz + gd * nz
                    vx, vy, vz = vx + gv * nx, vy + gv * ny, vz + gv * nz
                    damper = st.fixture_damping * -vn1 if cn is not cf and vn1 < 0.0 else 0.0
                    ffix = spring + damper
                    pushed = True
                    break

        # 4. speed clamp on the velocity and on the step
        vmax = st.max_speed
        sp = math.sqrt(vx * vx + vy * vy + vz * vz)
        if sp > vmax:
            g = vmax / sp
            vx, vy, vz = vx * g, vy * g, vz * g
        lmax = vmax * h
        ln = math.sqrt(ddx * ddx + ddy * ddy + ddz * ddz)
        if ln > lmax:
            g = lmax / ln
            ddx, ddy, ddz = ddx * g, ddy * g, ddz * g

        # 5. hard projection, inelastic stop, and the speed re-check
        tol = st.wall_tolerance
        x1, y1_, z1, ax_hit, rad_hit = fix._project(x0 + ddx, y0 + ddy, z0 + ddz, tol)
        clamped = ax_hit or rad_hit
        if clamped:
            for attempt in range(_RECLAMPS + 1):
                ex, ey, ez = x1 - x0, y1_ - y0, z1 - z0
                ln = math.sqrt(ex * ex + ey * ey + ez * ez)
                if ln <= lmax * (1.0 + _SPEED_SLACK):
                    break
                if attempt == _RECLAMPS:
                    x1, y1_, z1 = x0, y0, z0  # rare: hold rather than speed up
                    break
                g = lmax / ln
                x1, y1_, z1, _, _ = fix._project(x0 + g * ex, y0 + g * ey, z0 + g * ez, tol)
            s1, rx, ry, rz, r1 = fix._local(x1, y1_, z1)
            dx, dy, dz = fix._d  # type: ignore[attr-defined]
            if ax_hit:  # no velocity past the target
                a = vx * dx + vy * dy + vz * dz
                if a < 0.0:
                    vx, vy, vz = vx - a * dx, vy - a * dy, vz - a * dz
            if rad_hit and r1 > 0.0:  # no velocity further out of the wall
                a = (vx * rx + vy * ry + vz * rz) / r1
                if a > 0.0:
                    vx, vy, vz = vx - a * rx / r1, vy - a * ry / r1, vz - a * rz / r1
        else:
            s1, rx, ry, rz, r1 = fix._local(x1, y1_, z1)

        self._p = (x1, y1_, z1)
        self._v = (vx, vy, vz)
        return AdmittanceState(
            np.array(self._p), np.array(self._v), fix._signed(s1, rx, ry, rz, r1), w > 0.0,
            pushed, clamped,
            np.array((ffix * nx, ffix * ny, ffix * nz)) if pushed else np.zeros(3))
