"""Needle drive and pull along the needle's own arc (seed 002, §III.E-F, eqs. 2-4).

Frames (seed 002, Figs. 4 and 7). The seed writes ``G_AB`` for what the guide calls
``T_A_B``: the 4x4 pose of frame B in frame A. Here:

- ``S``, the tissue frame (:func:`tissue_frame`): origin on the incision line, ``z`` along
  the incision (start to end), ``y`` the tissue surface normal pointing out of the tissue,
  ``x = y × z`` across the incision. The tissue is modelled as the plane ``y = 0``.
- ``N``, the needle frame of :mod:`.needle`: origin at the arc's centre, ``x`` toward the
  base (swage), ``y`` toward the body, the arc at angles ``phi`` in ``[0, arc]``.
- ``T``, the gripper (:mod:`.needle_grasp`), ``C`` the camera, ``P`` the robot base.

Eq. 2: ``G_SN(alpha) = [R_z(alpha), (0, h, 0)]``: the needle lies in the plane ``z_S = 0``
(across the incision) with its centre at height ``h = r - d`` above the tissue, where ``d``
is the suture depth. Turning ``alpha`` rotates the needle about its own centre, so every
wire point stays on one circle and the wire follows the hole the tip cut (the seed's
argument for the least tissue tear). A needle point at arc angle ``phi`` sits at angle
``alpha + phi`` on that circle in S. The circle is under the tissue for angles in
``(pi + alpha0, 2 pi - alpha0)`` with ``alpha0 = arcsin(h / r)`` (eq. 4); the entry ``g``
is at angle ``pi + alpha0``, the exit ``f`` at ``2 pi - alpha0``.

Eq. 4 gives ``alpha0 <= alpha <= pi - alpha0``: the tip (``phi = pi``) goes from ``g`` to
``f``. That holds for the seed's semicircular needles only. For an arc of any length the
same condition (tip from ``g`` to ``f``) is ``pi + alpha0 - arc <= alpha <= 2 pi - alpha0 -
arc`` (:attr:`SutureGeometry.alpha_start`, :attr:`SutureGeometry.alpha_end`), which is eq. 4
when ``arc = pi``. The drive is possible only if ``pi - 2 alpha0 < arc <= pi + 2 alpha0``:
a shorter arc ends with its base in the tissue (nothing left to hold), a longer one starts
with its base already below the surface beyond the exit.

Eq. 3: ``G_PT(alpha) = G_PC G_CS G_SN(alpha) G_TN^-1``.

§III.F, pull: after the drive the needle is regrasped near its tip (pose from the tracker)
and turned further about its own centre until the swage has left the tissue, then lifted
along the tissue normal.

Pure math, no I/O. Metres and radians.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from oralnav.control.errors import GeometryError, NeedleError
from oralnav.control.geometry import as_transform, invert, make_transform
from oralnav.control.needle.model import Needle

#: Shortest incision accepted by :func:`tissue_frame` (m); below it the direction is noise.
MIN_INCISION = 1e-4


def _unit(v: np.ndarray, what: str, min_norm: float = 1e-12) -> np.ndarray:
    v = np.asarray(v, dtype=float).reshape(3)
    n = float(np.linalg.norm(v))
    if not math.isfinite(n) or n < min_norm:
        raise NeedleError(f"{what} is degenerate (norm {n:.3g})")
    return v / n


def _checked(T: np.ndarray, what: str) -> np.ndarray:
    try:
        return as_transform(T, what=what)
    except GeometryError as exc:
        raise NeedleError(str(exc)) from exc


def tissue_frame(p_start: np.ndarray, p_end: np.ndarray, normal: np.ndarray,
                 suture_point: np.ndarray | None = None,
                 viewpoint: np.ndarray | tuple[float, float, float] | None = (0.0, 0.0, 0.0),
                 min_angle: float = math.radians(10.0)) -> np.ndarray:
    """Tissue frame S from the incision, as ``T_C_S`` in the frame of the inputs (m).

    ``p_start``, ``p_end``: the incision's end points (3,); ``normal``: the tissue surface
    normal (3,), any length. ``z_S`` runs from start to end; ``y_S`` is the normal made
    perpendicular to the incision (a fitted plane and a detected line rarely agree
    exactly) and turned to face ``viewpoint`` (the camera centre, the origin of the camera
    frame by default; ``None`` keeps the normal's sign as given); ``x_S = y_S × z_S``.
    The origin is the point of the incision segment nearest ``suture_point`` (default the
    midpoint). Refused (:class:`NeedleError`): non-finite input, an incision shorter than
    :data:`MIN_INCISION`, a zero normal, a normal within ``min_angle`` (rad) of the
    incision, a suture point beyond the segment's ends.
    """
    a = np.asarray(p_start, dtype=float).reshape(3)
    b = np.asarray(p_end, dtype=float).reshape(3)
    n = np.asarray(normal, dtype=float).reshape(3)
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b)) and np.all(np.isfinite(n))):
        raise NeedleError("tissue frame: non-finite incision end or normal")
    length = float(np.linalg.norm(b - a))
    if length < MIN_INCISION:
        raise NeedleError(f"tissue frame: incision {length:.3g} m long, below "
                          f"{MIN_INCISION} m; its direction is undefined")
    z = (b - a) / length
    n = _unit(n, "tissue frame: surface normal")
    # sin of the angle between normal and incision: small means the normal says nothing
    # about which way is out of the tissue across the incision.
    sin_angle = float(np.linalg.norm(np.cross(n, z)))
    if sin_angle < math.sin(min_angle):
        raise NeedleError(f"tissue frame: normal {math.degrees(math.asin(min(sin_angle, 1))):.2f}"
                          f" deg from the incision (needs >= {math.degrees(min_angle):.1f} deg)")
    y = n - (n @ z) * z
    y /= np.linalg.norm(y)
    if suture_point is None:
        origin = 0.5 * (a + b)
    else:
        s = np.asarray(suture_point, dtype=float).reshape(3)
        if not np.all(np.isfinite(s)):
            raise NeedleError("tissue frame: non-finite suture point")
        u = float((s - a) @ z) / length
        if not -1e-9 <= u <= 1 + 1e-9:
            raise NeedleError(f"tissue frame: suture point lies {u * length:.4g} m along an "
                              f"incision {length:.4g} m long, outside it")
        origin = a + min(max(u, 0.0), 1.0) * length * z
    if viewpoint is not None:
        toward = np.asarray(viewpoint, dtype=float).reshape(3) - origin
        if float(toward @ y) < 0.0:
            y = -y
    x = np.cross(y, z)
    return make_transform(np.column_stack([x, y, z]), origin)


@dataclass(frozen=True)
class SutureGeometry:
    """The planar suture of seed 002 Fig. 7: needle ``radius`` r (m), suture ``depth`` d
    (m, chosen by the surgeon), needle ``arc`` (rad, pi for the seed's semicircles).

    Refused (:class:`NeedleError`): a depth not in ``(0, r)`` (eq. 4's ``arcsin(h / r)``
    needs ``0 < h <= r``, and ``h = r`` is a bite of zero depth), and an arc that cannot
    carry the tip from entry to exit with its base still out of the tissue (see the module
    docstring: ``pi - 2 alpha0 < arc <= pi + 2 alpha0``).
    """

    radius: float
    depth: float
    arc: float = math.pi

    def __post_init__(self) -> None:
        r, d = self.radius, self.depth
        if not (math.isfinite(r) and r > 0):
            raise NeedleError(f"suture: needle radius must be > 0 m, got {r}")
        if not math.isfinite(d):
            raise NeedleError(f"suture: depth must be finite, got {d}")
        h = r - d
        if h > r:
            raise NeedleError(f"suture: centre height h = r - d = {h:.4g} m exceeds the radius "
                              f"{r:.4g} m (depth {d:.4g} m <= 0); eq. 4's arcsin(h/r) is "
                              "undefined")
        if d <= 0:
            raise NeedleError(f"suture: depth must be > 0 m, got {d:.4g} m")
        if d >= r:
            raise NeedleError(f"suture: depth {d:.4g} m must be below the needle radius "
                              f"{r:.4g} m: the needle centre would sit at or under the tissue "
                              f"(h = {h:.4g} m)")
        if not (math.isfinite(self.arc) and 0 < self.arc <= 2 * math.pi):
            raise NeedleError(f"suture: needle arc must be in (0, 2 pi], got {self.arc}")
        a0 = self.alpha0
        if self.arc <= math.pi - 2 * a0:
            raise NeedleError(
                f"suture: a {math.degrees(self.arc):.1f} deg needle cannot span a "
                f"{d * 1e3:.2f} mm deep bite with radius {r * 1e3:.2f} mm: the submerged arc "
                f"is {math.degrees(math.pi - 2 * a0):.1f} deg, so the base would be in the "
                "tissue when the tip reaches the exit")
        if self.arc > math.pi + 2 * a0 + 1e-12:
            raise NeedleError(
                f"suture: a {math.degrees(self.arc):.1f} deg needle is longer than "
                f"{math.degrees(math.pi + 2 * a0):.1f} deg for a {d * 1e3:.2f} mm bite: its base "
                "would be under the tissue beyond the exit before the tip enters")

    @classmethod
    def for_needle(cls, needle: Needle, depth: float) -> SutureGeometry:
        """The suture of ``needle`` (its radius and arc) at ``depth`` (m)."""
        return cls(needle.radius, depth, needle.arc)

    @property
    def h(self) -> float:
        """Height of the needle centre above the tissue, ``r - d`` (m; eq. 4)."""
        return self.radius - self.depth

    @property
    def alpha0(self) -> float:
        """``arcsin(h / r)`` (rad; eq. 4)."""
        return math.asin(self.h / self.radius)

    @property
    def half_width(self) -> float:
        """Half the bite width, ``sqrt(r^2 - h^2)`` (m): ``|x|`` of ``g`` and ``f``."""
        return math.sqrt(max(self.radius**2 - self.h**2, 0.0))

    @property
    def entry(self) -> np.ndarray:
        """Entry point ``g`` in S (m): ``(-sqrt(r^2 - h^2), 0, 0)``."""
        return np.array([-self.half_width, 0.0, 0.0])

    @property
    def exit(self) -> np.ndarray:
        """Exit point ``f`` in S (m): ``(+sqrt(r^2 - h^2), 0, 0)``."""
        return np.array([self.half_width, 0.0, 0.0])

    @property
    def alpha_start(self) -> float:
        """``alpha`` at which the tip is at the entry ``g`` (rad): ``alpha0`` for a
        semicircle (eq. 4), ``pi + alpha0 - arc`` in general."""
        return math.pi + self.alpha0 - self.arc

    @property
    def alpha_end(self) -> float:
        """``alpha`` at which the tip is at the exit ``f`` (rad): ``pi - alpha0`` for a
        semicircle (eq. 4), ``2 pi - alpha0 - arc`` in general."""
        return 2 * math.pi - self.alpha0 - self.arc

    @property
    def alpha_swage_out(self) -> float:
        """``alpha`` at which the base (swage) reaches the exit ``f`` (rad): the end of the
        pull's rotation, ``2 pi - alpha0``."""
        return 2 * math.pi - self.alpha0

    @property
    def spare_arc(self) -> float:
        """Arc (rad) of the needle still out of the tissue on the base side when the tip
        reaches the exit, ``arc - (pi - 2 alpha0)``: where the driving grasp must sit."""
        return self.arc - (math.pi - 2 * self.alpha0)


def G_SN(alpha: float | np.ndarray, h: float) -> np.ndarray:
    """Eq. 2: the needle's pose in the tissue frame, ``[R_z(alpha), (0, h, 0)]``.

    ``alpha`` (rad) scalar -> (4, 4); array (n,) -> (n, 4, 4). ``h`` the centre height (m).
    """
    a = np.asarray(alpha, dtype=float)
    c, s = np.cos(a), np.sin(a)
    T = np.zeros(a.shape + (4, 4))
    T[..., 0, 0], T[..., 0, 1] = c, -s
    T[..., 1, 0], T[..., 1, 1] = s, c
    T[..., 2, 2] = 1.0
    T[..., 1, 3] = h
    T[..., 3, 3] = 1.0
    return T


@dataclass(frozen=True)
class Drive:
    """A planned drive: the needle's motion in S and, once a grasp is chosen, the gripper's.

    ``alphas`` (n,) rad, increasing; ``G_SN`` (n, 4, 4) needle poses in S (eq. 2);
    ``G_PS`` (4, 4) the tissue frame in the robot base P (``G_PC G_CS``); ``G_TN`` the
    grasp (4, 4) or ``None``; ``G_PT`` (n, 4, 4) gripper poses in P (eq. 3) when a grasp
    is set. :func:`oralnav.control.needle.grasp.select_grasp` reads a grasp-free drive.
    """

    geometry: SutureGeometry
    alphas: np.ndarray
    G_SN: np.ndarray
    G_PS: np.ndarray
    G_TN: np.ndarray | None = None
    G_PT: np.ndarray | None = field(default=None, repr=False)

    def gripper_poses(self, G_TN: np.ndarray) -> np.ndarray:
        """Eq. 3 for grasp ``G_TN``: gripper poses ``G_PT`` (n, 4, 4) along the drive."""
        G_NT = invert(_checked(G_TN, "G_TN"))
        return self.G_PS @ self.G_SN @ G_NT

    def gripper_in_tissue(self, G_TN: np.ndarray) -> np.ndarray:
        """``G_ST = G_SN(alpha) G_TN^-1`` (n, 4, 4): the gripper in S along the drive."""
        return self.G_SN @ invert(_checked(G_TN, "G_TN"))

    def with_grasp(self, G_TN: np.ndarray) -> Drive:
        """This drive with the grasp set and its gripper poses computed."""
        G_TN = _checked(G_TN, "G_TN").copy()
        return Drive(self.geometry, self.alphas, self.G_SN, self.G_PS, G_TN,
                     self.gripper_poses(G_TN))

    def approach_pose(self, offset: float,
                      along: Literal["gripper", "tangent"] = "gripper") -> np.ndarray:
        """Gripper pose ``G_PT`` (4, 4) ``offset`` (m) before the first drive pose.

        ``"gripper"``: backed off along the gripper's ``-z`` (the seed approaches "along the
        z-axis of the end-effector"); ``"tangent"``: backed off along the needle tip's
        tangent at the entry, so the tip slides in along the arc's own direction. Refused
        if no grasp is set, ``offset < 0``, or (``"gripper"``) the gripper does not point
        into the tissue at entry, so backing off along ``-z`` would not lift the tip.
        """
        if self.G_TN is None:
            raise NeedleError("approach: the drive has no grasp (use Drive.with_grasp)")
        if not (math.isfinite(offset) and offset >= 0):
            raise NeedleError(f"approach: offset must be >= 0 m, got {offset}")
        G_ST0 = self.G_SN[0] @ invert(self.G_TN)
        if along == "gripper":
            z_T = G_ST0[:3, 2]
            if z_T[1] >= -1e-9:
                raise NeedleError(
                    f"approach: the gripper's z axis points {math.degrees(math.asin(z_T[1])):.1f}"
                    " deg away from the tissue at entry; backing off along -z would not lift "
                    "the needle (approach along the tangent, or choose another grasp)")
            step = make_transform(t=[0.0, 0.0, -offset])
            return self.G_PS @ G_ST0 @ step
        if along == "tangent":
            arc = self.geometry.arc
            R = self.G_SN[0][:3, :3]
            d = R @ np.array([-math.sin(arc), math.cos(arc), 0.0])  # tip tangent, into tissue
            return self.G_PS @ make_transform(t=-offset * d) @ G_ST0
        raise NeedleError(f"approach: 'along' must be 'gripper' or 'tangent', got {along!r}")


def plan_drive(G_PC: np.ndarray, G_CS: np.ndarray, geometry: SutureGeometry, n: int,
               G_TN: np.ndarray | None = None, overshoot: float = 0.0) -> Drive:
    """Plan the drive: ``n`` >= 2 angles from the tip at the entry to the tip at the exit.

    ``overshoot`` (m of arc, >= 0) turns the needle further, so the tip stands that far out
    of the exit for the regrasp (§III.F needs a tip to hold; eq. 4 stops with the tip at
    the exit, ``overshoot = 0``). Refused if the overshoot would pull the base into the
    tissue. ``G_TN`` optional: the grasp, whose gripper poses (eq. 3) are then filled in.
    """
    if n < 2:
        raise NeedleError(f"drive: needs at least 2 poses, got {n}")
    if not (math.isfinite(overshoot) and overshoot >= 0):
        raise NeedleError(f"drive: overshoot must be >= 0 m, got {overshoot}")
    extra = overshoot / geometry.radius
    if extra >= geometry.spare_arc:
        raise NeedleError(
            f"drive: an overshoot of {overshoot * 1e3:.2f} mm ({math.degrees(extra):.1f} deg) "
            f"would put the base in the tissue; only {math.degrees(geometry.spare_arc):.1f} "
            "deg of arc is spare at the exit")
    G_PS = _checked(G_PC, "G_PC") @ _checked(G_CS, "G_CS")
    alphas = np.linspace(geometry.alpha_start, geometry.alpha_end + extra, n)
    drive = Drive(geometry, alphas, G_SN(alphas, geometry.h), G_PS)
    return drive if G_TN is None else drive.with_grasp(G_TN)


def drive_poses(G_PC: np.ndarray, G_CS: np.ndarray, G_TN: np.ndarray,
                geometry: SutureGeometry, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 3 over eq. 4's range: ``(alphas (n,), G_PT (n, 4, 4))``, gripper poses in P.

    ``G_PT = G_PC G_CS G_SN(alpha) G_TN^-1`` for ``n`` angles from ``alpha_start``
    (``alpha0`` for a semicircle) to ``alpha_end`` (``pi - alpha0``).
    """
    drive = plan_drive(G_PC, G_CS, geometry, n)
    return drive.alphas, drive.gripper_poses(G_TN)


def regrasp_pose(G_PC: np.ndarray, G_CN: np.ndarray, G_TN: np.ndarray,
                 approach: float = 0.0) -> np.ndarray:
    """Gripper pose ``G_PT`` (4, 4) that grasps the tracked needle ``G_CN`` with grasp
    ``G_TN`` (§III.F), backed off ``approach`` (m) along the gripper's ``-z`` (0: the grasp
    itself). Build ``G_TN`` near the tip with
    :func:`oralnav.control.needle.grasp.grasp_transform` (``w3`` = the tip's arc angle minus
    a margin)."""
    if not (math.isfinite(approach) and approach >= 0):
        raise NeedleError(f"regrasp: approach must be >= 0 m, got {approach}")
    G_PT = _checked(G_PC, "G_PC") @ _checked(G_CN, "G_CN") @ invert(_checked(G_TN, "G_TN"))
    return G_PT @ make_transform(t=[0.0, 0.0, -approach])


@dataclass(frozen=True)
class Pull:
    """The pull (§III.F): ``betas`` (n,) rad, the needle's extra turn about its own centre
    from the tracked pose (the lift steps repeat the last value); ``G_CN``
    (n + n_lift, 4, 4) needle poses in C; ``G_PT`` (n + n_lift, 4, 4) gripper poses in P;
    ``n_turn`` (= n) the number of leading poses that turn (the rest lift)."""

    betas: np.ndarray
    G_CN: np.ndarray
    G_PT: np.ndarray
    n_turn: int


def swage_exit_turn(G_SN_tracked: np.ndarray, needle: Needle) -> float:
    """Turn ``beta`` >= 0 (rad) about the needle's own axis, tip first, after which the
    needle at ``G_SN_tracked`` (its pose in S) has its base (swage) come up through the
    tissue plane ``y_S = 0``: the last wire point to leave the tissue.

    0 if no wire point is under the tissue. Refused if the base never surfaces as the
    needle turns (a tracked pose the pull cannot follow).
    """
    R, c = G_SN_tracked[:3, :3], G_SN_tracked[:3, 3]
    wire_y = (needle.points(64) @ R.T + c)[:, 1]
    if wire_y.min() >= 0.0:
        return 0.0
    r = needle.radius
    # The base at turn beta is c + r R (cos beta, sin beta, 0); its height is
    # c_y + r (a cos beta + b sin beta) = c_y + r m cos(beta - psi).
    a, b = R[1, 0], R[1, 1]
    m = math.hypot(a, b)
    if m * r <= abs(c[1]):
        raise NeedleError(f"pull: the tracked needle's base never surfaces while it turns "
                          f"(centre {c[1] * 1e3:.2f} mm above the tissue, needle plane "
                          f"{math.degrees(math.acos(min(m, 1.0))):.1f} deg off the normal)")
    psi = math.atan2(b, a)
    # The height rises through zero where cos(beta - psi) = -c_y / (r m) with
    # sin(beta - psi) < 0. A base still above the tissue (not yet in) first goes down
    # through the entry; the first upward crossing is its exit either way.
    delta = math.acos(max(-1.0, min(1.0, -c[1] / (r * m))))
    return (psi - delta) % (2 * math.pi)


def pull_poses(G_PC: np.ndarray, G_CS: np.ndarray, G_CN: np.ndarray, G_TN: np.ndarray,
               needle: Needle, n: int, swage_clearance: float = 0.002, lift: float = 0.01,
               n_lift: int = 5) -> Pull:
    """Pull (§III.F) from the tracked needle pose ``G_CN`` held by grasp ``G_TN``.

    The needle turns about its own centre and axis (``G_CN Rot_z(beta)``, the drive's
    motion continued, so the wire follows its track out of the tissue) until its base is
    ``swage_clearance`` (m of arc) past the tissue surface (no turn if no wire is in the
    tissue), in ``n`` >= 2 poses, then
    rises ``lift`` (m) along the tissue normal ``y_S`` in ``n_lift`` further poses. The
    turn is computed from the tracked pose, not the plan, so a needle that slipped or a
    tissue that moved is followed. Gripper poses ``G_PT = G_PC G_CN(beta) G_TN^-1``.
    ``G_CN`` must name base and tip correctly: the tracker cannot tell them apart from the
    outline (:mod:`.needle_tracker`), and a swapped pose would turn the needle backward.
    """
    if n < 2 or n_lift < 0:
        raise NeedleError(f"pull: needs n >= 2 turn poses and n_lift >= 0, got {n}, {n_lift}")
    for name, v in (("swage_clearance", swage_clearance), ("lift", lift)):
        if not (math.isfinite(v) and v >= 0):
            raise NeedleError(f"pull: {name} must be >= 0, got {v}")
    G_CS = _checked(G_CS, "G_CS")
    G_CN = _checked(G_CN, "G_CN")
    G_NT = invert(_checked(G_TN, "G_TN"))
    G_PC = _checked(G_PC, "G_PC")
    beta_end = swage_exit_turn(invert(G_CS) @ G_CN, needle)
    if beta_end > 0:
        beta_end += swage_clearance / needle.radius
    betas = np.linspace(0.0, beta_end, n)
    turn = G_CN @ G_SN(betas, 0.0)
    up = G_CS[:3, 1]
    steps = np.linspace(0.0, lift, n_lift + 1)[1:]
    lifted = np.repeat(turn[-1][None], n_lift, axis=0)
    lifted[:, :3, 3] += steps[:, None] * up
    poses_N = np.concatenate([turn, lifted])
    all_betas = np.concatenate([betas, np.full(n_lift, beta_end)])
    return Pull(all_betas, poses_N, G_PC @ poses_N @ G_NT, n)
