"""The needle grasp ``G_TN`` (seed 002, §III.C, eq. 1) and the choice of a driving grasp.

Frames. ``T``, the gripper: origin at the tip of the jaws, ``z`` along the gripper (out of
the tip), ``y`` across the jaws. ``N``, the needle (:mod:`.needle`): origin at the arc's
centre, ``x`` toward the base (swage), ``y`` toward the body, ``z = x × y``. ``G_TN`` (the
seed's notation; ``T_T_N`` in the guide's) is the pose of N in T.

Parameters (seed 002, Fig. 3, after its ref. [8]): ``theta0`` (m), how deep the needle
sits in the jaws, a translation along ``-z_T``; ``w1``, ``w2`` (rad), rotations about
axes through T's origin: ``w1`` about the gripper axis ``z_T``, ``w2`` about ``y_T``;
``w3`` (rad), a rotation about the needle's own axis through its centre, which slides the
grasp along the arc. Composition (checked against the printed matrix in the tests)::

    G_TN = Trans(0, 0, -theta0) · Rot_z(w1) · Rot_y(w2) · G0 · Rot_zN(-w3)

with ``G0`` the grasp at zero parameters: centre at ``(0, 0, -r)`` in T, ``x_N = z_T``,
``y_N = -y_T``, ``z_N = x_T``. So at zero the jaws hold the base, the wire runs along
``y_T`` there, and the needle lies in the gripper's ``y-z`` plane. The jaw point (T's
origin moved ``theta0`` along ``-z_T``) is always the arc point at ``phi = w3`` (mod 2 pi):
**``w3`` alone moves the grasp along the arc, and the grasp's arc angle is ``phi = w3``**
(0 the base, ``needle.arc`` the tip). ``w1`` turns the wire about the gripper axis, ``w2``
tilts the needle plane about the wire; the wire at the grasp always crosses the gripper
axis at a right angle. We read "y perpendicular to the jaws" as ``y`` across the jaws, so
``w1 = 0`` holds the wire straight across them; a gripper whose ``y`` is the closing
direction shifts ``w1`` by a quarter turn.

**Eq. 1 as printed** (:func:`eq1_as_printed`) differs from the text in two ways:

1. Its rotation ``R`` is a proper rotation for every angle and equals
   ``Rot_z(w1) Rot_y(w2) R0 Rot_y(w3)`` with ``R0 = [[0, -1, 0], [0, 0, 1], [-1, 0, 0]]``,
   and its ``p`` (at ``theta0 = 0``) is the translation of a turn ``w3`` about an axis
   parallel to that frame's ``y`` through the point ``(r, 0, 0)`` of that frame. So the
   printed ``G`` is the pose of the needle in a frame of ref. [8], call it N8, whose origin
   is on the arc (the point grasped at ``w3 = 0``), whose ``x`` points to the centre and
   whose ``y`` is the needle's normal: not Fig. 3's N (origin at the centre, needle in the
   ``x-y`` plane), under which the printed ``w3`` would tilt the needle out of its plane
   instead of sliding the grasp. We map N8 to N by the constant ``G_N8N`` (centre at
   ``(r, 0, 0)``; ``x_N = -x_N8``, ``y_N = -z_N8``, ``z_N = -y_N8``), chosen so that the
   printed rotation senses carry over and ``w3 = 0`` grasps the base.
2. ``-theta0`` stands on the ``x`` row of ``p``, a translation along ``-x_T``; the text (and
   Fig. 3) make ``theta0`` the insertion along ``-z_T``. We put it on the ``z`` row.

Hence ``G_TN = [R, p_z-corrected] · G_N8N``; the tests check that this equals the
composition above and that the printed ``R`` is the composition's rotation.

**Choosing a driving grasp** (:func:`select_grasp`). The seed takes the "most feasible"
grasp from its ref. [8] (Liu & Cavusoglu, ICRA 2015), whose cost we do not have. The rule
here: candidates on a grid of the four parameters, the grasp point kept a margin away from
swage and tip; a candidate is feasible if, at every pose of the drive, the gripper tip and
a shaft segment behind it stay ``clearance`` above the tissue plane and the shaft never
falls below ``min_shaft_elevation`` (its angle above the tissue plane, seen from the tip),
the shaft rises at least ``approach_elevation`` at entry (the seed approaches the entry
point along the gripper's z axis: that only lifts the needle clear of the tissue if the
gripper points into it), and the optional ``reachable(G_PT)`` check (inverse kinematics,
workspace, collisions) accepts the pose. Among feasible grasps the score is::

    score = min shaft elevation over the drive - swing_weight * shaft swing

both in radians. Every grasp turns the gripper by the same angle over the drive (the
needle's sweep); what differs is how that turn splits into a roll about the gripper axis,
which one wrist joint does without moving the shaft, and a swing of the shaft axis, which
moves the arm and sweeps the shaft through the mouth. A high shaft keeps it clear of the
tissue and the teeth, and the needle visible. The two pull against each other (the shaft
can only be steep over the whole drive if it swings with the needle), hence the weight.

Pure math, no I/O. Metres and radians.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from itertools import product

import numpy as np

from oralnav.control.errors import GeometryError, NeedleError
from oralnav.control.geometry import as_transform, invert, rotation_angle
from oralnav.control.needle.drive import Drive
from oralnav.control.needle.model import Needle

#: Printed eq. 1 rotation at zero angles (N8 in T, see the module docstring).
R0 = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0]])
#: Axes of N in ref. [8]'s needle frame N8: columns x_N, y_N, z_N.
R_N8N = np.array([[-1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, -1.0, 0.0]])


def eq1_as_printed(theta0: float, w1: float, w2: float, w3: float,
                   radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 1 exactly as printed: ``(R (3, 3), p (3,))``, ``-theta0`` on the ``x`` row.

    Kept to compare against; see the module docstring for why it is not ``G_TN``."""
    s1, c1 = math.sin(w1), math.cos(w1)
    s2, c2 = math.sin(w2), math.cos(w2)
    s3, c3 = math.sin(w3), math.cos(w3)
    R = np.array([[s1 * s3 - c1 * c3 * s2, -c1 * c2, -c3 * s1 - c1 * s2 * s3],
                  [-c1 * s3 - c3 * s1 * s2, -c2 * s1, c1 * c3 - s1 * s2 * s3],
                  [-c2 * c3, s2, -c2 * s3]])
    p = np.array([radius * (c1 * s2 * (c3 - 1) - s1 * s3) - theta0,
                  radius * (c1 * s3 + s1 * s2 * (c3 - 1)),
                  radius * c2 * (c3 - 1)])
    return R, p


def _grasp_transforms(theta0, w1, w2, w3, radius: float) -> np.ndarray:
    """Vectorised :func:`grasp_transform`: broadcast arrays -> (..., 4, 4)."""
    theta0, w1, w2, w3 = np.broadcast_arrays(*(np.asarray(v, dtype=float)
                                               for v in (theta0, w1, w2, w3)))
    s1, c1, s2, c2, s3, c3 = (np.sin(w1), np.cos(w1), np.sin(w2), np.cos(w2),
                              np.sin(w3), np.cos(w3))
    # Columns of the printed R (axes of N8 in T).
    x8 = np.stack([s1 * s3 - c1 * c3 * s2, -c1 * s3 - c3 * s1 * s2, -c2 * c3], axis=-1)
    y8 = np.stack([-c1 * c2, -c2 * s1, s2], axis=-1)
    z8 = np.stack([-c3 * s1 - c1 * s2 * s3, c1 * c3 - s1 * s2 * s3, -c2 * s3], axis=-1)
    # Printed p with theta0 moved to the z row (the insertion along -z_T).
    p8 = radius * np.stack([c1 * s2 * (c3 - 1) - s1 * s3,
                            c1 * s3 + s1 * s2 * (c3 - 1),
                            c2 * (c3 - 1)], axis=-1)
    p8[..., 2] -= theta0
    G = np.zeros(theta0.shape + (4, 4))
    # G_TN = G_TN8 · G_N8N: the centre is (r, 0, 0) in N8; N's axes are -x8, -z8, -y8.
    G[..., :3, 0] = -x8
    G[..., :3, 1] = -z8
    G[..., :3, 2] = -y8
    G[..., :3, 3] = p8 + radius * x8
    G[..., 3, 3] = 1.0
    return G


def grasp_transform(theta0: float, w1: float, w2: float, w3: float,
                    radius: float) -> np.ndarray:
    """Eq. 1 (corrected, see the module docstring): the needle's pose ``G_TN`` (4, 4) in
    the gripper frame for insertion ``theta0`` (m), angles ``w1, w2, w3`` (rad) and needle
    ``radius`` (m). The jaw point ``(0, 0, -theta0)`` in T is the arc point ``phi = w3``."""
    if not (math.isfinite(radius) and radius > 0):
        raise NeedleError(f"grasp: needle radius must be > 0 m, got {radius}")
    vals = (theta0, w1, w2, w3)
    if not all(math.isfinite(v) for v in vals):
        raise NeedleError(f"grasp: non-finite parameter in {vals}")
    return _grasp_transforms(theta0, w1, w2, w3, radius)


@dataclass(frozen=True)
class GraspParameters:
    """The four grasp parameters of eq. 1: ``theta0`` (m), ``w1, w2, w3`` (rad)."""

    theta0: float
    w1: float
    w2: float
    w3: float

    @property
    def phi(self) -> float:
        """Arc angle of the grasp point, ``w3`` wrapped to ``[0, 2 pi)`` (rad)."""
        return self.w3 % (2 * math.pi)

    def transform(self, radius: float) -> np.ndarray:
        """``G_TN`` (4, 4) for a needle of ``radius`` (m)."""
        return grasp_transform(self.theta0, self.w1, self.w2, self.w3, radius)


@dataclass(frozen=True)
class GraspFit:
    """:func:`grasp_parameters`'s answer: the parameters and how far ``G_TN`` is from
    being a grasp of eq. 1: ``offset`` (m), the grasp point's distance from the gripper
    axis; ``tilt`` (rad), the rotation left once ``w1, w2, w3`` are taken out (the wire not
    square to the gripper axis)."""

    params: GraspParameters
    offset: float
    tilt: float


def grasp_point_angle(G_TN: np.ndarray, needle: Needle, depth: float = 0.0) -> float:
    """Arc angle ``phi`` (rad, in ``[0, needle.arc]``) of the needle point nearest the jaw
    point ``(0, 0, -depth)`` in T (T's origin by default; pass ``theta0`` for the point
    actually held)."""
    G_NT = invert(_checked(G_TN))
    q = G_NT[:3, :3] @ np.array([0.0, 0.0, -depth]) + G_NT[:3, 3]
    phi = math.atan2(q[1], q[0]) % (2 * math.pi)
    if phi <= needle.arc:
        return phi
    # Past the tip: the nearest wire point is one of the ends.
    d_base = float(np.linalg.norm(q - needle.base))
    d_tip = float(np.linalg.norm(q - needle.tip))
    return 0.0 if d_base <= d_tip else needle.arc


def _checked(T: np.ndarray, what: str = "G_TN") -> np.ndarray:
    try:
        return as_transform(T, what=what)
    except GeometryError as exc:
        raise NeedleError(str(exc)) from exc


def grasp_parameters(G_TN: np.ndarray, radius: float) -> GraspFit:
    """Inverse of :func:`grasp_transform`: the parameters of a grasp ``G_TN`` (e.g. a
    tracked needle pose seen from the gripper, ``G_PT^-1 G_PN``).

    The grasp point is the arc point nearest the gripper axis (``x_T = y_T = 0``); where the
    needle's circle meets the axis twice, the one nearest the jaw tip on the jaw side
    (``z_T <= 0``). Its arc angle is ``w3``, its depth ``theta0``; ``w1, w2`` come from the
    rotation that remains. :class:`GraspFit` says how far ``G_TN`` is from an eq. 1 grasp.
    """
    G = _checked(G_TN)
    if not (math.isfinite(radius) and radius > 0):
        raise NeedleError(f"grasp: needle radius must be > 0 m, got {radius}")
    R, c = G[:3, :3], G[:3, 3]
    u, v = radius * R[:, 0], radius * R[:, 1]

    def residual(phi: np.ndarray) -> np.ndarray:
        return (c[:, None] + np.outer(u, np.cos(phi)) + np.outer(v, np.sin(phi)))

    grid = np.linspace(0.0, 2 * math.pi, 720, endpoint=False)
    q = residual(grid)
    f = q[0] ** 2 + q[1] ** 2
    starts = grid[(f <= np.roll(f, 1)) & (f <= np.roll(f, -1))]
    # Gauss-Newton on (q_x, q_y): exact crossings converge to full precision, where a
    # scalar search on their squared norm stalls at sqrt(eps).
    phis = starts.copy()
    for _ in range(30):
        q = residual(phis)
        dq = np.outer(-u, np.sin(phis)) + np.outer(v, np.cos(phis))
        num = q[0] * dq[0] + q[1] * dq[1]
        den = dq[0] ** 2 + dq[1] ** 2
        phis = phis - np.where(den > 1e-30, num / np.maximum(den, 1e-30), 0.0)
    q = residual(phis)
    dist = np.hypot(q[0], q[1])
    depth = -q[2]
    near = dist <= dist.min() + 1e-9
    jaw = near & (depth >= -1e-9)
    pick = np.flatnonzero(jaw)
    k = pick[np.argmin(depth[pick])] if pick.size else int(np.argmin(dist))
    phi = float(phis[k] % (2 * math.pi))
    theta0 = float(depth[k])
    # What is left after the w3 part is taken out is Rot_z(w1) Rot_y(w2).
    M = R @ _grasp_transforms(0.0, 0.0, 0.0, phi, radius)[:3, :3].T
    w1 = math.atan2(-M[0, 1], M[1, 1])
    s1, c1 = math.sin(w1), math.cos(w1)
    w2 = math.atan2(c1 * M[0, 2] + s1 * M[1, 2], M[2, 2])
    fit = _grasp_transforms(0.0, w1, w2, phi, radius)[:3, :3]
    return GraspFit(GraspParameters(theta0, w1, w2, phi), float(dist[k]),
                    rotation_angle(fit, R))


@dataclass(frozen=True)
class GraspSettings:
    """Grasp selection settings. Lengths m, angles rad.

    The grasp point is kept ``swage_margin`` and ``tip_margin`` (arc length) from the
    needle's ends. Candidates: ``theta0_values`` x ``w1_values`` x ``w2_steps`` angles over
    a full turn x ``phi_steps`` grasp points over the usable band. During the whole drive
    the gripper tip and the shaft segment ``shaft_length`` behind it stay ``clearance``
    above the tissue, and the shaft's angle above the tissue plane stays at least
    ``min_shaft_elevation``; at entry it is at least ``approach_elevation``, so that
    :meth:`Drive.approach_pose` along the gripper axis lifts the needle. ``theta0`` must
    not exceed ``jaw_length``. ``swing_weight`` prices a radian of shaft swing against a
    radian of shaft elevation in the score.
    """

    swage_margin: float = 0.002
    tip_margin: float = 0.004
    theta0_values: tuple[float, ...] = (0.001,)
    w1_values: tuple[float, ...] = (0.0,)
    w2_steps: int = 24
    phi_steps: int = 9
    clearance: float = 0.002
    shaft_length: float = 0.02
    jaw_length: float = 0.008
    min_shaft_elevation: float = 0.0
    approach_elevation: float = math.radians(10.0)
    swing_weight: float = 0.25

    def __post_init__(self) -> None:
        for name in ("swage_margin", "tip_margin", "clearance", "shaft_length",
                     "jaw_length", "swing_weight"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise NeedleError(f"grasp settings: {name} must be >= 0, got {v}")
        if self.jaw_length > self.shaft_length:
            raise NeedleError(f"grasp settings: jaw_length {self.jaw_length} m exceeds the "
                              f"checked shaft_length {self.shaft_length} m")
        if not self.theta0_values or not self.w1_values:
            raise NeedleError("grasp settings: theta0_values and w1_values need a value")
        for t in self.theta0_values:
            if not (math.isfinite(t) and 0 <= t <= self.jaw_length):
                raise NeedleError(f"grasp settings: theta0 {t} m outside the jaws "
                                  f"[0, {self.jaw_length}] m")
        if not all(math.isfinite(w) for w in self.w1_values):
            raise NeedleError(f"grasp settings: non-finite w1 in {self.w1_values}")
        if self.w2_steps < 1 or self.phi_steps < 1:
            raise NeedleError(f"grasp settings: w2_steps and phi_steps must be >= 1, got "
                              f"{self.w2_steps}, {self.phi_steps}")
        for name in ("min_shaft_elevation", "approach_elevation"):
            v = getattr(self, name)
            if not (math.isfinite(v) and abs(v) <= math.pi / 2):
                raise NeedleError(f"grasp settings: {name} must be in [-pi/2, pi/2], "
                                  f"got {v}")


@dataclass(frozen=True)
class GraspChoice:
    """The chosen grasp and its figures over the drive.

    ``params`` and ``G_TN`` (4, 4); ``phi`` the grasp's arc angle (rad); ``score``;
    ``min_tip_clearance``, ``min_shaft_clearance`` (m, lowest height above the tissue of
    the gripper tip and of the checked shaft end); ``min_shaft_elevation`` (rad, lowest
    angle of the shaft above the tissue plane); ``shaft_swing`` (rad, largest angle of the
    shaft axis from its direction at entry); ``candidates`` tried, ``feasible`` passing
    the geometric checks, ``reach_checked`` sent to ``reachable``.
    """

    params: GraspParameters
    G_TN: np.ndarray = field(repr=False)
    phi: float
    score: float
    min_tip_clearance: float
    min_shaft_clearance: float
    min_shaft_elevation: float
    shaft_swing: float
    candidates: int
    feasible: int
    reach_checked: int


def grasp_band(needle: Needle, settings: GraspSettings) -> tuple[float, float]:
    """Arc angles ``(lo, hi)`` (rad) the grasp point may take: the needle less the swage
    and tip margins. Refused if the margins leave nothing."""
    lo = settings.swage_margin / needle.radius
    hi = needle.arc - settings.tip_margin / needle.radius
    if lo > hi:
        raise NeedleError(
            f"grasp: margins of {settings.swage_margin * 1e3:.2f} mm (swage) and "
            f"{settings.tip_margin * 1e3:.2f} mm (tip) leave nothing of a "
            f"{needle.length * 1e3:.2f} mm needle to grasp")
    return lo, hi


def _out_of_tissue_to(drive: Drive) -> float:
    """The largest arc angle (rad) of a needle point still out of the tissue at the end
    of ``drive``: the grasp point sits at circle angle ``alpha + phi``, and the tissue
    begins at ``pi + alpha0``."""
    return math.pi + drive.geometry.alpha0 - float(drive.alphas[-1])


def grasp_candidates(needle: Needle, drive: Drive, settings: GraspSettings) -> np.ndarray:
    """Candidate parameters (k, 4) as ``theta0, w1, w2, w3`` rows: the settings' grid with
    ``w3 = phi`` over the grasp band cut to the part of the needle still out of the tissue
    at the end of the drive (a grasp beyond it would be dragged into the tissue)."""
    lo, hi = grasp_band(needle, settings)
    g = drive.geometry
    out_to = _out_of_tissue_to(drive)
    if min(hi, out_to) < lo:
        raise NeedleError(
            f"grasp: the grasp band [{math.degrees(lo):.1f}, {math.degrees(hi):.1f}] deg "
            f"misses the part of the needle out of the tissue for the whole drive "
            f"[0, {math.degrees(out_to):.1f}] deg (depth {g.depth * 1e3:.2f} mm)")
    hi = min(hi, out_to)
    phis = np.linspace(lo, hi, settings.phi_steps) if settings.phi_steps > 1 else \
        np.array([0.5 * (lo + hi)])
    w2s = np.linspace(-math.pi, math.pi, settings.w2_steps, endpoint=False)
    return np.array(list(product(settings.theta0_values, settings.w1_values, w2s, phis)),
                    dtype=float)


def _drive_figures(G_ST: np.ndarray, s: GraspSettings) -> tuple[np.ndarray, ...]:
    """Per grasp, over the drive's gripper poses in S ``G_ST`` (k, n, 4, 4): the lowest
    gripper tip and shaft end (m above the tissue), the lowest shaft elevation and the
    largest shaft swing (rad), and whether the clearance and elevation rules hold."""
    tip_y = G_ST[..., 1, 3]
    z_T = G_ST[..., :3, 2]
    end_y = tip_y - s.shaft_length * z_T[..., 1]
    elevation = np.arcsin(np.clip(-z_T[..., 1], -1.0, 1.0))   # shaft above the tissue plane
    swing = np.arccos(np.clip(np.einsum("kni,ki->kn", z_T, z_T[:, 0]), -1.0, 1.0))
    min_tip, min_end = tip_y.min(axis=1), end_y.min(axis=1)
    min_elev, max_swing = elevation.min(axis=1), swing.max(axis=1)
    clear_ok = (min_tip >= s.clearance) & (min_end >= s.clearance)
    elev_ok = ((min_elev >= s.min_shaft_elevation - 1e-9)
               & (elevation[:, 0] >= s.approach_elevation - 1e-9))
    return min_tip, min_end, min_elev, max_swing, clear_ok, elev_ok


def check_drive_grasp(needle: Needle, drive: Drive, G_TN: np.ndarray,
                      settings: GraspSettings | None = None) -> GraspChoice:
    """The figures of one given grasp ``G_TN`` (4, 4; e.g. the grasp a hand-off actually
    produced, seen by the tracker) over ``drive``, checked by :func:`select_grasp`'s rules:
    the grasp point inside the band and out of the tissue for the whole drive, the
    gripper and shaft clear of the tissue, the shaft's elevation. Refused
    (:class:`NeedleError` naming the rule) when a rule fails: a drive on it would push
    the jaws into the tissue or drag the grasp under the surface."""
    s = settings or GraspSettings()
    G_TN = _checked(G_TN)
    fit = grasp_parameters(G_TN, needle.radius)
    phi = grasp_point_angle(G_TN, needle, fit.params.theta0)
    lo, hi = grasp_band(needle, s)
    out_to = _out_of_tissue_to(drive)
    if not lo - 1e-9 <= phi <= min(hi, out_to) + 1e-9:
        raise NeedleError(
            f"grasp: the jaws hold the needle at {math.degrees(phi):.1f} deg of arc, outside "
            f"[{math.degrees(lo):.1f}, {math.degrees(min(hi, out_to)):.1f}] deg (away from "
            "swage and tip, and out of the tissue for the whole drive)")
    G_ST = (drive.G_SN @ invert(G_TN))[None]
    min_tip, min_end, min_elev, max_swing, clear_ok, elev_ok = _drive_figures(G_ST, s)
    if not clear_ok[0]:
        raise NeedleError(
            f"grasp: with this grasp the gripper comes within "
            f"{min(min_tip[0], min_end[0]) * 1e3:.2f} mm of the tissue during the drive "
            f"({s.clearance * 1e3:.2f} mm needed)")
    if not elev_ok[0]:
        raise NeedleError(
            f"grasp: with this grasp the shaft falls to {math.degrees(min_elev[0]):.1f} deg "
            f"above the tissue (needs {math.degrees(s.min_shaft_elevation):.1f} deg, and "
            f"{math.degrees(s.approach_elevation):.1f} deg at entry)")
    score = float(min_elev[0] - s.swing_weight * max_swing[0])
    return GraspChoice(fit.params, G_TN.copy(), phi, score, float(min_tip[0]),
                       float(min_end[0]), float(min_elev[0]), float(max_swing[0]), 1, 1, 0)


def select_grasp(needle: Needle, drive: Drive, settings: GraspSettings | None = None,
                 reachable: Callable[[np.ndarray], bool] | None = None) -> GraspChoice:
    """Choose the driving grasp for ``drive`` (the rule is in the module docstring).

    ``reachable(G_PT) -> bool`` (optional) judges one gripper pose in P (4, 4); it is
    asked, best-scoring grasp first, about every pose of a grasp until one passes them
    all. Refused (:class:`NeedleError`, saying which rule excluded the candidates) if no
    candidate is feasible or the needle does not match the drive's geometry.
    """
    s = settings or GraspSettings()
    g = drive.geometry
    if abs(needle.radius - g.radius) > 1e-9 or abs(needle.arc - g.arc) > 1e-9:
        raise NeedleError(f"grasp: needle (r {needle.radius} m, arc {needle.arc} rad) is "
                          f"not the drive's (r {g.radius} m, arc {g.arc} rad)")
    cand = grasp_candidates(needle, drive, s)
    G_TN = _grasp_transforms(cand[:, 0], cand[:, 1], cand[:, 2], cand[:, 3], needle.radius)
    G_ST = drive.G_SN[None] @ invert(G_TN)[:, None]          # (k, n, 4, 4)
    min_tip, min_end, min_elev, max_swing, clear_ok, elev_ok = _drive_figures(G_ST, s)
    ok = clear_ok & elev_ok
    if not ok.any():
        best = float(np.minimum(min_tip, min_end).max())
        raise NeedleError(
            f"grasp: none of {len(cand)} candidates is feasible: {int((~clear_ok).sum())} "
            f"bring the gripper within {s.clearance * 1e3:.2f} mm of the tissue (best "
            f"lowest point {best * 1e3:.2f} mm), {int((clear_ok & ~elev_ok).sum())} more "
            f"lower the shaft below {math.degrees(s.min_shaft_elevation):.1f} deg or enter "
            f"with it below {math.degrees(s.approach_elevation):.1f} deg")
    score = min_elev - s.swing_weight * max_swing
    lowest = np.minimum(min_tip, min_end)
    # Best score first; among equal scores (the grid is symmetric) the most clearance.
    order = [int(i) for i in np.lexsort((-lowest, -np.round(score, 9))) if ok[i]]
    checked = 0
    chosen = None
    for i in order:
        if reachable is None:
            chosen = i
            break
        checked += 1
        G_PT = drive.G_PS @ G_ST[i]
        if all(bool(reachable(T)) for T in G_PT):
            chosen = i
            break
    if chosen is None:
        raise NeedleError(f"grasp: reachable() refused a pose of each of the {len(order)} "
                          f"grasps that clear the tissue ({len(cand)} candidates)")
    p = GraspParameters(*(float(v) for v in cand[chosen]))
    return GraspChoice(p, G_TN[chosen], p.phi, float(score[chosen]),
                       float(min_tip[chosen]), float(min_end[chosen]),
                       float(min_elev[chosen]), float(max_swing[chosen]),
                       len(cand), len(order), checked)


@dataclass(frozen=True)
class SurfaceGraspSettings:
    """Grasps of a needle lying on or standing out of a surface (pick-up, hand-off,
    regrasp). Lengths m, angles rad.

    ``theta0``: how deep the wire sits in the jaws (eq. 1). ``w1_values``: the wire's turn
    about the gripper axis; ``+-pi/2`` hold it along ``x_T``, between jaws that close
    along ``y_T`` (the simulated cell's and most needle drivers'). ``w2_steps``: gripper
    angles about the wire over a full turn. ``min_elevation``: the shaft's lowest angle
    above the surface plane; ``min_tip_height``: the jaw tip's lowest height above it
    (negative: the closed jaws may press a soft surface that much, as they must to take
    a wire lying flat on it).
    """

    theta0: float = 0.001
    w1_values: tuple[float, ...] = (math.pi / 2, -math.pi / 2)
    w2_steps: int = 24
    min_elevation: float = math.radians(30.0)
    min_tip_height: float = -0.0006

    def __post_init__(self) -> None:
        if not (math.isfinite(self.theta0) and self.theta0 >= 0):
            raise NeedleError(f"surface grasp: theta0 must be >= 0 m, got {self.theta0}")
        if not self.w1_values or not all(math.isfinite(w) for w in self.w1_values):
            raise NeedleError(f"surface grasp: w1_values needs finite values, got "
                              f"{self.w1_values}")
        if self.w2_steps < 1:
            raise NeedleError(f"surface grasp: w2_steps must be >= 1, got {self.w2_steps}")
        if not (math.isfinite(self.min_elevation) and abs(self.min_elevation) <= math.pi / 2):
            raise NeedleError(f"surface grasp: min_elevation must be in [-pi/2, pi/2], got "
                              f"{self.min_elevation}")
        if not math.isfinite(self.min_tip_height):
            raise NeedleError("surface grasp: min_tip_height must be finite")


@dataclass(frozen=True)
class SurfaceGrasp:
    """One grasp of a needle at a known pose: ``params`` (eq. 1), ``G_TN`` (4, 4),
    ``T_ref_T`` (4, 4) the gripper pose that realises it (frame of the needle's pose),
    ``elevation`` (rad) the shaft's angle above the surface, ``tip_height`` (m) the jaw
    tip's height above it."""

    params: GraspParameters
    G_TN: np.ndarray = field(repr=False)
    T_ref_T: np.ndarray = field(repr=False)
    elevation: float
    tip_height: float


def surface_grasps(needle: Needle, T_ref_N: np.ndarray, phi: float,
                   surface_point: np.ndarray, surface_normal: np.ndarray,
                   settings: SurfaceGraspSettings | None = None) -> list[SurfaceGrasp]:
    """Grasps of the needle at pose ``T_ref_N`` (4, 4, m) at arc angle ``phi`` (rad) from
    the free side of a surface (``surface_point`` (3,) on it, ``surface_normal`` (3,)
    toward the free side, both in the frame of ``T_ref_N``), steepest shaft first.

    The family is eq. 1 with ``theta0`` and ``w1`` from the settings, ``w3 = phi`` and
    ``w2`` around the wire: the wire square across the jaws, the gripper anywhere around
    it. Kept: shaft at least ``min_elevation`` above the surface, jaw tip no lower than
    ``min_tip_height``. Reachability is the caller's (it knows the arm). Empty when none
    is kept. Refused (:class:`NeedleError`): ``phi`` off the needle, a zero normal.
    """
    s = settings or SurfaceGraspSettings()
    if not (math.isfinite(phi) and 0.0 <= phi <= needle.arc):
        raise NeedleError(f"surface grasp: phi {phi} rad is off the needle [0, "
                          f"{needle.arc:.4f}] rad")
    T = _checked(T_ref_N, "T_ref_N")
    n = np.asarray(surface_normal, dtype=float).reshape(3)
    norm = float(np.linalg.norm(n))
    if not (math.isfinite(norm) and norm > 1e-9):
        raise NeedleError(f"surface grasp: the surface normal is degenerate (norm {norm:.3g})")
    n = n / norm
    p0 = np.asarray(surface_point, dtype=float).reshape(3)
    w2 = np.linspace(-math.pi, math.pi, s.w2_steps, endpoint=False)
    cand = np.array(list(product((s.theta0,), s.w1_values, w2, (phi,))), dtype=float)
    G = _grasp_transforms(cand[:, 0], cand[:, 1], cand[:, 2], cand[:, 3], needle.radius)
    T_ref_T = T[None] @ invert(G)
    elevation = np.arcsin(np.clip(-(T_ref_T[:, :3, 2] @ n), -1.0, 1.0))
    tip_height = (T_ref_T[:, :3, 3] - p0) @ n
    keep = (elevation >= s.min_elevation - 1e-12) & (tip_height >= s.min_tip_height)
    order = [int(i) for i in np.argsort(-elevation, kind="stable") if keep[i]]
    return [SurfaceGrasp(GraspParameters(*(float(v) for v in cand[i])), G[i], T_ref_T[i],
                         float(elevation[i]), float(tip_height[i])) for i in order]
