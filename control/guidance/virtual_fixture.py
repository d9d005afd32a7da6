"""The conical virtual fixture (VF) of oral surgery (seed 004, section 2.2, after its ref. [12]).

The instrument enters the mouth along a planned straight axis. The allowed region is a
funnel around that axis: a final cylinder at the target (mainly inside the oral cavity) and
cone segments widening outward along the entry path. Outside the funnel (the forbidden
region) the fixture pushes the instrument back; inside the cylinder it guides the
instrument along the axis only.

Geometry. Everything lives in one frame ``F`` chosen by the caller (the seed works in the
oral-cavity frame, here the opener marker frame ``OM``); every point and velocity passed
in must be expressed in ``F``, and everything returned is in ``F``. With ``t`` the target
and ``d`` the unit direction from the target *out* along the entry path, a point ``p`` has

- axial position ``s = (p - t) . d`` (m): 0 at the target, growing outward;
- radial vector ``p - t - s d`` and radius ``r`` (m), its length.

The profile ``R(s)`` (m) is piecewise linear: ``R = r_cyl`` for ``0 <= s <= L_cyl`` (the
cylinder), then each cone segment ``(length, end_radius)`` widens linearly to its end
radius. Beyond the last segment the last cone goes on with its own slope (an open-ended
final cone; with no cone segments, the cylinder goes on): so the region is defined
everywhere in front of the mouth, and a tool far out along the entry path is free within
a wide cone rather than in an undefined zone. Behind the target (``s < 0``) nothing is
allowed: that is the axial end stop. The allowed region is ``{s >= 0, r <= R(s)}``.

What is constrained is one point: the tool centre point on the tool's axis. The seed's
cylinder "of the tool's radius" bounds the tool *body*; a body of radius ``r_tool`` stays
inside a VF of radius ``R`` when its axis point stays within ``R - r_tool``, so pass that
(a small positive radius, e.g. 0.5 mm, for the seed's pure axial motion).

Distances are radial (perpendicular to the axis), not Euclidean to the conical wall: the
admittance pushes and clamps radially, so the cone's wall is approached and left along the
same direction that is measured. For a cone of half-angle ``a`` the radial penetration is
``1 / cos a`` times the Euclidean one (conservative: it never under-reports).

The seed (and its ref. [12]) leaves three things open, settled here: what lies beyond the
last cone segment (here the open-ended final cone above), how "pushes the instrument back"
is realised (here a radial spring-damper wall that only pushes, :meth:`fixture_force`,
backed in the admittance by a hard clamp), and whether the cylinder's radius bounds the
tool's axis or its body (here the axis point, as above).

Hot path. :class:`VirtualFixture`'s public queries take and return numpy arrays;
``oralnav.control.guidance.admittance`` calls the private ``_local`` / ``_radius`` / ``_weight``
on plain floats, which costs a few microseconds rather than tens per control period.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from oralnav import checks
from oralnav.control.errors import GeometryError, PlanningError

__all__ = ["VirtualFixture"]

#: A direction whose norm is off 1 by more than this is renormalised (and accepted).
_UNIT_TOL = 1e-9
#: Below this norm (m or m/s) a radial vector has no direction: the point is on the axis.
_TINY = 1e-15


def finite_number(x: object, what: str, error: type[Exception] = PlanningError) -> float:
    """``x`` as a finite float (bools refused), or ``error`` naming ``what``."""
    return checks.finite_number(x, what, error)


_number = finite_number


def _vector(x: ArrayLike, what: str, error: type[Exception] = PlanningError) -> np.ndarray:
    try:
        a = np.asarray(x, dtype=float)
    except (TypeError, ValueError):
        raise error(f"{what} must be a 3-vector, got {x!r}") from None
    if a.shape != (3,):
        raise error(f"{what} must be a 3-vector, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise error(f"{what} has non-finite entries: {a.tolist()}")
    return a


def _point(p: ArrayLike, what: str = "point") -> tuple[float, float, float]:
    a = _vector(p, f"{what} (m, fixture frame)", GeometryError)
    return float(a[0]), float(a[1]), float(a[2])


@dataclass(frozen=True, eq=False)
class VirtualFixture:
    """The funnel-shaped allowed region around a planned axis, in the caller's frame ``F``.

    Build it with :meth:`from_axis` (the constructor takes the same fields and validates
    them the same way). Attributes (all SI, frame ``F``):

    - ``target`` (3,), m: where the instrument's axis ends inside the mouth (``s = 0``);
    - ``direction`` (3,), unit: from the target out along the entry path;
    - ``cylinder_radius``, ``cylinder_length`` (m): the final cylinder, ``0 <= s <= L``;
    - ``cones``: ``((length, end_radius), ...)`` (m), from the cylinder outward;
    - ``guidance_blend`` (m): over this axial length past the cylinder's mouth the axial
      guidance fades linearly from full to none (0: it stops at the mouth), see
      :meth:`guidance_weight`.
    """

    target: np.ndarray
    direction: np.ndarray
    cylinder_radius: float
    cylinder_length: float
    cones: tuple[tuple[float, float], ...] = ()
    guidance_blend: float = 0.0

    # -- construction ----------------------------------------------------------------
    @classmethod
    def from_axis(cls, target: ArrayLike, direction: ArrayLike, cylinder_radius: float,
                  cylinder_length: float, cones: Sequence[tuple[float, float]] = (),
                  guidance_blend: float = 0.0) -> VirtualFixture:
        """Validate and build the fixture; :class:`PlanningError` names a bad parameter.

        ``target`` (3,) m and ``direction`` (3,) in frame ``F``; ``direction`` points from
        the target out along the entry path and is normalised (a zero one is refused).
        ``cylinder_radius`` and ``cylinder_length`` (m) must be positive; each cone
        segment ``(length_m, end_radius_m)`` must have a positive length and an end radius
        no smaller than the radius it starts from (the funnel never narrows outward).
        ``guidance_blend`` (m) must be >= 0. All values finite.
        """
        return cls(target, direction, cylinder_radius, cylinder_length,  # type: ignore[arg-type]
                   cones, guidance_blend)  # type: ignore[arg-type]

    def __post_init__(self) -> None:
        set_ = object.__setattr__  # frozen: normalised fields are set through object
        t = _vector(self.target, "target (m, fixture frame)")
        d = _vector(self.direction, "direction (fixture frame)")
        n = float(np.linalg.norm(d))
        if n < 1e-12:
            raise PlanningError(f"direction must be a non-zero vector, got {d.tolist()}")
        if abs(n - 1.0) > _UNIT_TOL:
            d = d / n
        rc = checks.positive_number(self.cylinder_radius, "cylinder_radius (m)", PlanningError)
        lc = checks.positive_number(self.cylinder_length, "cylinder_length (m)", PlanningError)
        try:
            segs = list(self.cones)
        except TypeError:
            raise PlanningError(f"cones must be a sequence of (length_m, end_radius_m) "
                                f"pairs, got {self.cones!r}") from None
        cones: list[tuple[float, float]] = []
        r_prev = rc
        for i, seg in enumerate(segs):
            try:
                length, radius = seg
            except (TypeError, ValueError):
                raise PlanningError(f"cones[{i}] must be a (length_m, end_radius_m) pair, "
                                    f"got {seg!r}") from None
            length = checks.positive_number(length, f"cones[{i}] length (m)", PlanningError)
            radius = checks.positive_number(radius, f"cones[{i}] end_radius (m)",
                                            PlanningError)
            if radius < r_prev:
                raise PlanningError(
                    f"cones[{i}] end_radius {radius} m is smaller than the radius it starts "
                    f"from ({r_prev} m): the fixture's radii must not decrease outward")
            cones.append((length, radius))
            r_prev = radius
        blend = _number(self.guidance_blend, "guidance_blend (m)")
        if blend < 0.0:
            raise PlanningError(f"guidance_blend (m) must be >= 0, got {self.guidance_blend!r}")
        t = np.array(t, dtype=float)
        d = np.array(d, dtype=float)
        t.flags.writeable = False
        d.flags.writeable = False
        set_(self, "target", t)
        set_(self, "direction", d)
        set_(self, "cylinder_radius", rc)
        set_(self, "cylinder_length", lc)
        set_(self, "cones", tuple(cones))
        set_(self, "guidance_blend", blend)

        # Plain-float copies and the profile's pieces for the per-period code.
        pieces = []
        s, r = lc, rc
        for length, radius in cones:
            # (start s, start radius, slope, end s); the last cone runs on (end s = inf)
            pieces.append((s, r, (radius - r) / length, s + length))
            s += length
            r = radius
        if pieces:
            pieces[-1] = pieces[-1][:3] + (math.inf,)
        set_(self, "_t", (float(t[0]), float(t[1]), float(t[2])))
        set_(self, "_d", (float(d[0]), float(d[1]), float(d[2])))
        set_(self, "_pieces", tuple(pieces))
        set_(self, "_outer_s", s)

    # -- profile ---------------------------------------------------------------------
    @property
    def breakpoints(self) -> tuple[float, ...]:
        """Axial positions (m) where the segments end: the cylinder's mouth, then each
        cone's end; the last cone goes on beyond its end with the same slope."""
        out, s = [self.cylinder_length], self.cylinder_length
        for length, _ in self.cones:
            s += length
            out.append(s)
        return tuple(out)

    @property
    def length(self) -> float:
        """Axial length (m) of the specified profile (cylinder plus cone segments)."""
        return self._outer_s  # type: ignore[attr-defined]

    def allowed_radius(self, s: float) -> float:
        """Radius (m) of the allowed region at axial position ``s`` (m from the target,
        positive outward). Behind the target (``s < 0``) nothing is allowed whatever this
        returns (the end stop); it returns the cylinder radius there so the profile is
        continuous."""
        return self._radius(float(s))

    def _radius(self, s: float) -> float:
        if s <= self.cylinder_length:
            return self.cylinder_radius
        for s0, r0, k, s1 in self._pieces:  # type: ignore[attr-defined]
            if s <= s1:
                return r0 + k * (s - s0)
        return self.cylinder_radius  # no cones: the cylinder goes on

    def guidance_weight(self, s: float) -> float:
        """How much of the lateral motion the guidance removes at axial position ``s``
        (m): 1 in the cylinder (and behind the target), falling linearly to 0 over
        ``guidance_blend`` metres past the cylinder's mouth, 0 beyond."""
        return self._weight(float(s))

    def _weight(self, s: float) -> float:
        over = s - self.cylinder_length
        if over <= 0.0:
            return 1.0
        if over >= self.guidance_blend:
            return 0.0
        return 1.0 - over / self.guidance_blend

    # -- queries on points -----------------------------------------------------------
    def _local(self, x: float, y: float, z: float) -> tuple[float, float, float, float, float]:
        """(s, radial vector x, y, z, r) of the point (x, y, z); all m, frame ``F``."""
        tx, ty, tz = self._t  # type: ignore[attr-defined]
        dx, dy, dz = self._d  # type: ignore[attr-defined]
        wx, wy, wz = x - tx, y - ty, z - tz
        s = wx * dx + wy * dy + wz * dz
        rx, ry, rz = wx - s * dx, wy - s * dy, wz - s * dz
        return s, rx, ry, rz, math.sqrt(rx * rx + ry * ry + rz * rz)

    def axial(self, p: ArrayLike) -> float:
        """Signed distance (m) of ``p`` (3,), frame ``F``, along the axis from the target:
        positive out along the entry path, negative past the target."""
        return self._local(*_point(p))[0]

    def radial(self, p: ArrayLike) -> float:
        """Distance (m) of ``p`` (3,), frame ``F``, from the axis line."""
        return self._local(*_point(p))[4]

    def boundary_distance(self, p: ArrayLike) -> float:
        """Signed distance (m) of ``p`` (3,), frame ``F``, to the fixture's wall:
        positive inside the allowed region (the radial margin ``R(s) - r`` to the wall),
        negative outside (the penetration depth).

        Measured radially, perpendicular to the axis, as the admittance pushes and clamps
        (see the module docstring); behind the target it is minus the distance to the
        target's disc of the cylinder radius, the nearest allowed points there.
        """
        return self._signed(*self._local(*_point(p)))

    def _signed(self, s: float, rx: float, ry: float, rz: float, r: float) -> float:
        if s >= 0.0:
            return self._radius(s) - r
        over = max(r - self.cylinder_radius, 0.0)
        return -math.sqrt(s * s + over * over)

    def contains(self, p: ArrayLike, margin: float = 0.0) -> bool:
        """Whether ``p`` (3,), frame ``F``, lies in the allowed region widened radially by
        ``margin`` (m, >= 0); the end stop at the target is never widened."""
        s, _, _, _, r = self._local(*_point(p))
        return s >= 0.0 and r <= self._radius(s) + margin

    def in_cylinder(self, p: ArrayLike) -> bool:
        """Whether ``p`` (3,), frame ``F``, lies inside the final cylinder:
        ``0 <= s <= cylinder_length`` and ``r <= cylinder_radius``."""
        s, _, _, _, r = self._local(*_point(p))
        return 0.0 <= s <= self.cylinder_length and r <= self.cylinder_radius

    def project(self, p: ArrayLike, margin: float = 0.0) -> np.ndarray:
        """The allowed point (3,), m, frame ``F``, for ``p`` (3,): ``s`` clamped to
        ``>= 0`` (it cannot pass the target), then the radius clamped to
        ``R(s) + margin`` keeping the radial direction (``margin`` m, >= 0, widens the
        region radially). Idempotent; ``p`` itself (a copy) when already allowed.

        This is the radial clamp the admittance applies, not the Euclidean nearest point
        of a cone's wall (the two differ by the cone's half-angle, see the module
        docstring)."""
        x, y, z = _point(p)
        return np.array(self._project(x, y, z, float(margin))[:3])

    def _project(self, x: float, y: float, z: float, margin: float
                 ) -> tuple[float, float, float, bool, bool]:
        """(x, y, z, clamped axially, clamped radially) of the projected point."""
        s, rx, ry, rz, r = self._local(x, y, z)
        axial = s < 0.0
        if axial:
            tx, ty, tz = self._t  # type: ignore[attr-defined]
            x, y, z = tx + rx, ty + ry, tz + rz  # s = 0, same radial vector
            s = 0.0
        rmax = self._radius(s) + margin
        radial = r > rmax
        if radial:
            f = rmax / r - 1.0
            x, y, z = x + f * rx, y + f * ry, z + f * rz
        return x, y, z, axial, radial

    def _contact(self, x: float, y: float, z: float
                 ) -> tuple[float, float, float, float]:
        """(depth m, inward unit normal x, y, z) of a point outside the region; depth 0
        (and a zero normal) inside. The normal points from the point to its projection."""
        px, py, pz, axial, radial = self._project(x, y, z, 0.0)
        if not (axial or radial):
            return 0.0, 0.0, 0.0, 0.0
        ex, ey, ez = px - x, py - y, pz - z
        depth = math.sqrt(ex * ex + ey * ey + ez * ez)
        if depth < _TINY:
            return 0.0, 0.0, 0.0, 0.0
        return depth, ex / depth, ey / depth, ez / depth

    # -- forces and guidance ---------------------------------------------------------
    def fixture_force(self, p: ArrayLike, v: ArrayLike, stiffness: float,
                      damping: float) -> np.ndarray:
        """Force (3,), N, frame ``F``, of the forbidden-region wall on a tool point at
        ``p`` (3,), m, moving at ``v`` (3,), m/s: zero inside the allowed region;
        outside, ``(stiffness * depth + damping * max(0, v . n_out)) * (-n_out)``, with
        ``depth`` the penetration (m) and ``n_out`` the outward normal (from the
        projection, :meth:`project`, to ``p``). This includes the end stop behind the
        target. The damping resists only motion deeper into the wall, so the wall pushes
        and never pulls. ``stiffness`` N/m and ``damping`` N s/m, both >= 0."""
        x, y, z = _point(p)
        vx, vy, vz = _point(v, "velocity")
        depth, nx, ny, nz = self._contact(x, y, z)
        if depth == 0.0:
            return np.zeros(3)
        outward = -(vx * nx + vy * ny + vz * nz)
        f = float(stiffness) * depth + float(damping) * max(outward, 0.0)
        return np.array((f * nx, f * ny, f * nz))

    def guidance(self, p: ArrayLike, v: ArrayLike) -> np.ndarray:
        """The guided velocity (3,), m/s, frame ``F``, of the velocity ``v`` (3,) at the
        point ``p`` (3,): ``v`` less ``guidance_weight(s)`` times its lateral (off-axis)
        component. In the cylinder only the axial component survives; beyond the blend
        ``v`` passes unchanged (free within the cone). Works on forces (N) alike."""
        s = self._local(*_point(p))[0]
        vx, vy, vz = _point(v, "velocity")
        w = self._weight(s)
        if w == 0.0:
            return np.array((vx, vy, vz))
        dx, dy, dz = self._d  # type: ignore[attr-defined]
        a = vx * dx + vy * dy + vz * dz
        return np.array((vx - w * (vx - a * dx), vy - w * (vy - a * dy),
                         vz - w * (vz - a * dz)))
