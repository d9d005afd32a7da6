"""Automatic placement of the feeding target on the surrogate model (seed 004, §4).

Frames (Center frame of the model, metres): the implant hole ``{Hole}`` sits at ``t_ch`` on
the tissue with its z axis ``D_hz`` along the hole's axis, pointing into the cavity, and
its x axis parallel to the Center YZ plane (eqs. 15-17). The tool frame ``{Tool}`` is the
hole frame moved ``d_T`` along that axis and turned ``theta_T`` about it (eq. 18). The
instrument is a contra-angle: its rod leaves the head along the tool x axis. ``line1`` is
the rod's axis at the target, starting ``r`` out along tool x; ``line2`` the same line
``d12`` (the implant length) back toward the hole, where the rod ends up once the implant
is in: feeding sweeps the rod from one to the other (eq. 19).

Safety of a line (eq. 13) samples the model where the line crosses each slice (``m``
points) and at its start ``T``; eq. 14 weighs the square roots of both lines' values and
PSO (eq. 20, :mod:`oralnav.control.planning.pso`) minimises it over ``d_T`` and ``theta_T``.
Eqs. 21 and 22 are the paper's linear and squared variants, kept to chart their failures.

Two choices differ from the paper's text, and both are charted (``oralnav bench planning``):

- The paper computes line2 on the *unshrunk* model ("line2 is not a rod"). But line2 is
  where the rod is when the implant is home, so it needs the rod's clearance as much as
  line1 does; and only the symmetric treatment gives the paper's own cylinder answer
  (Table 2: d_T = 65.5 mm; line1 shrunk and line2 not gives 62.5 mm). ``shrink_line2``
  defaults to True.
- Eq. 22 squares ``f_safe``, which would score a collision (f < 0) like clearance. The
  variant here keeps the sign, ``sgn(f) f^2``, so it still fails only as the paper says.

The search scores placements with the paper's queries. When the model carries a
certificate, placements whose lines (as rods of the rod radius from their start out
through the model's front) are not certified ``min_clearance`` clear of the tissue
(:mod:`oralnav.control.planning.rod_check`, a bound that holds for the mesh itself) are penalised
during the search, and ``collision_free`` needs both lines certified. A model without a
certificate is searched as the paper does and its placement says ``certified=False``.

Objective values use distances in millimetres, as the paper's do (its Fig. 17 optimum is
-2.611), so they compare with its figures; every other length here is in metres.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numba
import numpy as np

from oralnav.control.errors import PlanningError
from oralnav.control.planning.fpsm import FPSM
from oralnav.control.planning.pso import PSOSettings, minimize_pso
from oralnav.control.planning.rod_check import RodCheck

#: Objective equations of the paper: 14 (adopted), 21 (linear), 22 (squared).
EQUATIONS = (14, 21, 22)


@dataclass(frozen=True)
class Hole:
    """The implant hole in the Center frame: ``position`` (m) and ``axis`` (unit, into
    the cavity)."""

    position: np.ndarray
    axis: np.ndarray

    def __post_init__(self) -> None:
        p = np.asarray(self.position, dtype=float).reshape(-1)
        a = np.asarray(self.axis, dtype=float).reshape(-1)
        if p.shape != (3,) or a.shape != (3,) or not (np.all(np.isfinite(p))
                                                      and np.all(np.isfinite(a))):
            raise PlanningError("hole position and axis must be finite 3-vectors")
        n = float(np.linalg.norm(a))
        if n < 1e-9:
            raise PlanningError("hole axis is zero")
        a = a / n
        if math.hypot(a[1], a[2]) < 1e-9:
            raise PlanningError("hole axis is parallel to the Center x axis: eq. 16 defines no "
                                "hole x axis for it")
        object.__setattr__(self, "position", p)
        object.__setattr__(self, "axis", a)


def hole_frame(hole: Hole) -> np.ndarray:
    """``T_C_hole`` (eqs. 15-17): z along the hole axis, x in the Center YZ plane with a
    non-negative z component. Eq. 16 divides by ``D_hz^(y)``; for ``D_hz^(y) = 0`` its
    limit is taken, ``x = (0, -sgn(D_hz^(z)), 0)``."""
    dz = hole.axis
    den = math.hypot(dz[1], dz[2])
    sy = 1.0 if dz[1] >= 0 else -1.0
    dx = np.array([0.0, -sy * dz[2] / den, abs(dz[1]) / den])
    T = np.eye(4)
    T[:3, 0] = dx
    T[:3, 1] = np.cross(dz, dx)
    T[:3, 2] = dz
    T[:3, 3] = hole.position
    return T


def tool_pose(T_ch: np.ndarray, d_T: float, theta_T: float) -> np.ndarray:
    """``T_C_tool = T_C_hole @ T_hole_tool`` (eq. 18)."""
    c, s = math.cos(theta_T), math.sin(theta_T)
    T_ht = np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, d_T], [0, 0, 0, 1.0]])
    return T_ch @ T_ht


def feed_lines(T_ch: np.ndarray, d_T: np.ndarray, theta_T: np.ndarray, rod_radius: float,
               implant_length: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eq. 19 for K placements at once: start points ``P1``, ``P2`` (K, 3) and the common
    unit direction ``D`` (K, 3), Center frame, metres."""
    d_T = np.asarray(d_T, dtype=float).reshape(-1)
    th = np.asarray(theta_T, dtype=float).reshape(-1)
    R = T_ch[:3, :3]
    t = T_ch[:3, 3]
    x_tool = np.stack([np.cos(th), np.sin(th), np.zeros_like(th)], axis=1) @ R.T
    base = t + d_T[:, None] * R[:, 2]
    P1 = base + rod_radius * x_tool
    P2 = P1 - implant_length * R[:, 2]
    return P1, P2, x_tool


def line_safe_distances(model: FPSM, P: np.ndarray, D: np.ndarray,
                        shrink: float | np.ndarray = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Safe distances (m) along K lines starting at ``P`` (K, 3) in direction ``D``:
    column 0 is the start ``T`` (eq. 11), columns 1..M the crossings ``Q`` with each slice
    ahead of the start (eq. 10), NaN where a line does not cross that slice. ``shrink``
    (m, scalar or per line) is eq. 12's rod radius. Returns the (K, M + 1) distances and
    the crossing counts ``m`` (K,)."""
    P = np.asarray(P, dtype=float).reshape(-1, 3)
    D = np.asarray(D, dtype=float).reshape(-1, 3)
    shrink = np.broadcast_to(np.asarray(shrink, dtype=float), (P.shape[0],))
    dT, dQ, ok = _line_parts(model, P, D, shrink)
    out = np.concatenate([dT[:, None], np.where(ok, dQ, np.nan)], axis=1)
    return out, ok.sum(axis=1)


def _line_parts(model: FPSM, P: np.ndarray, D: np.ndarray,
                shrink: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The start's distance (K,), every slice's distance (K, M) and which slices the line
    crosses ahead of its start (K, M). All points of all lines go through one model
    query: this is the inner loop of the placement search."""
    z = model.z
    K, M = P.shape[0], z.size
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (z - P[:, 2:3]) / D[:, 2:3]
    ok = t > 0                          # NaN and -inf compare False
    ok &= np.isfinite(t)
    t[~ok] = 0.0
    # the start: its two neighbouring slices (eq. 11); the crossings: their own slice.
    # Every (line, slice) pair is queried, crossing or not, and masked afterwards: one
    # dense numpy pass is cheaper than gathering the crossings.
    zc = np.clip(P[:, 2], z[0], z[-1])
    j0 = np.clip(np.searchsorted(z, zc, side="right") - 1, 0, M - 2)
    sl = np.concatenate([j0, j0 + 1, np.tile(np.arange(M), K)])
    x = np.concatenate([P[:, 0], P[:, 0], (P[:, 0:1] + t * D[:, 0:1]).ravel()])
    y = np.concatenate([P[:, 1], P[:, 1], (P[:, 1:2] + t * D[:, 1:2]).ravel()])
    d = model.radius_at(sl, np.arctan2(y, x)) - np.hypot(x, y)
    d1, d2 = d[:K], d[K:2 * K]
    w = (zc - z[j0]) / (z[j0 + 1] - z[j0])
    dT = d1 + (d2 - d1) * w - shrink
    beyond = np.abs(P[:, 2] - zc)      # outside the model: never positive (FPSM.safe_distance)
    dT = np.where(beyond > 0, np.minimum(dT, 0.0) - beyond, dT)
    return dT, d[2 * K:].reshape(K, M) - shrink[:, None], ok


@numba.njit(cache=True, inline="always")
def _slice_distance(coef: np.ndarray, j: int, x: float, y: float) -> float:
    """Eq. 10 on slice ``j``: ``rho_j(theta) - |(x, y)|`` (m), no shrink; ``coef`` is the
    model's (M, N, 4) Hermite power coefficients (:meth:`FPSM.radius_at`'s)."""
    n = coef.shape[1]
    th = math.atan2(y, x)
    if th < 0.0:
        th += 2.0 * math.pi
    u = th * (n / (2.0 * math.pi))
    k = min(int(u), n - 1)
    t = u - k
    c = coef[j, k]
    return ((c[3] * t + c[2]) * t + c[1]) * t + c[0] - math.hypot(x, y)


@numba.njit(cache=True, inline="always")
def _line_f(coef: np.ndarray, z: np.ndarray, px: float, py: float, pz: float, dx: float,
            dy: float, dz: float, shrink: float, lam_avg: float, lam_min: float
            ) -> tuple[float, int]:
    """Eq. 13 of one line (m) and its crossing count: :func:`_line_parts` and
    :meth:`PlacementProblem.line_values` for a single line, compiled."""
    M = z.size
    # the start (eq. 11): between its two neighbouring slices; outside the slice range
    # never positive (FPSM.safe_distance)
    zc = min(max(pz, z[0]), z[M - 1])
    j0 = 0
    while j0 < M - 2 and z[j0 + 1] <= zc:
        j0 += 1
    d1 = _slice_distance(coef, j0, px, py)
    d2 = _slice_distance(coef, j0 + 1, px, py)
    w = (zc - z[j0]) / (z[j0 + 1] - z[j0])
    dT = d1 + (d2 - d1) * w - shrink
    beyond = abs(pz - zc)
    if beyond > 0.0:
        dT = min(dT, 0.0) - beyond
    dmin, total, m = dT, dT, 0
    if dz != 0.0:
        for j in range(M):
            t = (z[j] - pz) / dz
            if t > 0.0 and math.isfinite(t):       # the crossings ahead of the start
                d = _slice_distance(coef, j, px + t * dx, py + t * dy) - shrink
                total += d
                m += 1
                if d < dmin:
                    dmin = d
    if dmin > 0.0:
        return lam_avg * total / (m + 1) + lam_min * dmin, m
    return lam_min * dmin, m


@numba.njit(cache=True, nogil=True)
def _objective(coef: np.ndarray, z: np.ndarray, T_ch: np.ndarray, x: np.ndarray,
               rod_radius: float, implant_length: float, shrink2: float, lam_avg: float,
               lam_min: float, equation: int) -> np.ndarray:
    """:meth:`PlacementProblem.evaluate` compiled: eq. 19's lines for each placement
    ``x`` (K, 2), eq. 13 on both, eq. 14 (21, 22) of the pair, in the paper's mm."""
    out = np.empty(x.shape[0])
    for i in range(x.shape[0]):
        d_T, th = x[i, 0], x[i, 1]
        c, s = math.cos(th), math.sin(th)
        # x_tool = R @ (cos th, sin th, 0); P1 = t + d_T R_z + r x_tool; P2 = P1 - l R_z
        vx = T_ch[0, 0] * c + T_ch[0, 1] * s
        vy = T_ch[1, 0] * c + T_ch[1, 1] * s
        vz = T_ch[2, 0] * c + T_ch[2, 1] * s
        p1x = T_ch[0, 3] + d_T * T_ch[0, 2] + rod_radius * vx
        p1y = T_ch[1, 3] + d_T * T_ch[1, 2] + rod_radius * vy
        p1z = T_ch[2, 3] + d_T * T_ch[2, 2] + rod_radius * vz
        f1, m1 = _line_f(coef, z, p1x, p1y, p1z, vx, vy, vz, rod_radius, lam_avg, lam_min)
        f2, m2 = _line_f(coef, z, p1x - implant_length * T_ch[0, 2],
                         p1y - implant_length * T_ch[1, 2], p1z - implant_length * T_ch[2, 2],
                         vx, vy, vz, shrink2, lam_avg, lam_min)
        a, b = f1 * 1e3, f2 * 1e3
        if equation == 14:
            a = math.copysign(math.sqrt(abs(a)), a)
            b = math.copysign(math.sqrt(abs(b)), b)
        elif equation == 22:
            a = math.copysign(a * a, a)
            b = math.copysign(b * b, b)
        out[i] = -((m1 + 1) * a + (m2 + 1) * b) / (m1 + m2 + 2)
    return out


def f_safe(d: np.ndarray, lambda_avg: float = 0.5, lambda_min: float = 0.5) -> np.ndarray:
    """Eq. 13 on the (K, m + 1) distances of :func:`line_safe_distances` (NaN ignored):
    the weighted mean plus the weighted minimum while the line is clear, only the minimum
    term once it collides (d_min <= 0)."""
    valid = ~np.isnan(d)
    dmin = np.min(np.where(valid, d, np.inf), axis=1)
    avg = np.sum(np.where(valid, d, 0.0), axis=1) / valid.sum(axis=1)
    return np.where(dmin > 0, lambda_avg * avg + lambda_min * dmin, lambda_min * dmin)


@dataclass(frozen=True)
class PlacementSettings:
    """The instrument, the objective and the search box. Lengths m, angles rad."""

    rod_radius: float = 0.006
    implant_length: float = 0.031
    lambda_avg: float = 0.5
    lambda_min: float = 0.5
    equation: int = 14
    shrink_line2: bool = True
    d_range: tuple[float, float] = (0.0, 0.12)
    theta_range: tuple[float, float] = (-math.pi / 2, math.pi / 2)
    max_hole_depth: float = 0.02   # a hole farther than this outside the model is refused
    # certified rod clearance both lines must keep (certified models only): room for the
    # guided insertion's tracking and fixture deviations before its alarm trips
    min_clearance: float = 0.0005
    pso: PSOSettings = field(default_factory=PSOSettings)

    def __post_init__(self) -> None:
        if self.equation not in EQUATIONS:
            raise PlanningError(f"objective equation must be one of {EQUATIONS}, "
                                f"got {self.equation}")
        if not (self.rod_radius >= 0 and self.implant_length > 0):
            raise PlanningError(f"rod radius must be >= 0 and implant length > 0, got "
                                f"{self.rod_radius} m and {self.implant_length} m")
        if not (self.min_clearance >= 0 and math.isfinite(self.min_clearance)):
            raise PlanningError(f"min_clearance must be >= 0 m, got {self.min_clearance}")
        if not (self.lambda_avg >= 0 and self.lambda_min > 0):
            raise PlanningError("lambda_avg must be >= 0 and lambda_min > 0")
        for name in ("d_range", "theta_range"):
            lo, hi = getattr(self, name)
            if not hi > lo:
                raise PlanningError(f"{name} must have upper > lower, got {lo}..{hi}")


def _signed_root(f: np.ndarray) -> np.ndarray:
    return np.sign(f) * np.sqrt(np.abs(f))


class PlacementProblem:
    """Eq. 14 (or 21, 22) as a function of ``x = (d_T, theta_T)`` for one model and hole.

    Construction checks the hole against the model (:class:`PlanningError` when it lies
    outside). :meth:`evaluate` scores K placements at once.
    """

    def __init__(self, model: FPSM, hole: Hole, settings: PlacementSettings | None = None):
        self.model, self.hole = model, hole
        self.s = settings or PlacementSettings()
        z = model.z
        hz = hole.position[2]
        if not z[0] <= hz <= z[-1]:
            raise PlanningError(
                f"the hole (z = {hz * 1e3:.1f} mm) is outside the model, whose slices span "
                f"z = {z[0] * 1e3:.1f}..{z[-1] * 1e3:.1f} mm")
        depth = -float(model.safe_distance(hole.position))
        if depth > self.s.max_hole_depth:
            raise PlanningError(
                f"the hole lies {depth * 1e3:.1f} mm outside the model's surface (more than "
                f"{self.s.max_hole_depth * 1e3:.1f} mm): it is not on this patient's cavity")
        self.T_ch = hole_frame(hole)

    def lines(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        x = np.atleast_2d(np.asarray(x, dtype=float))
        return feed_lines(self.T_ch, x[:, 0], x[:, 1], self.s.rod_radius,
                          self.s.implant_length)

    def line_values(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                  np.ndarray]:
        """``f_safe`` of line1 and line2 (m) and their crossing counts ``m1``, ``m2``."""
        s = self.s
        P1, P2, D = self.lines(x)
        K = P1.shape[0]
        shrink = np.concatenate([np.full(K, s.rod_radius),
                                 np.full(K, s.rod_radius if s.shrink_line2 else 0.0)])
        dT, dQ, ok = _line_parts(self.model, np.concatenate([P1, P2]), np.concatenate([D, D]),
                                 shrink)
        # eq. 13 without NaN bookkeeping: the start always counts, crossings where ok
        m = ok.sum(axis=1)
        dmin = np.minimum(dT, np.min(np.where(ok, dQ, np.inf), axis=1))
        avg = (dT + np.sum(np.where(ok, dQ, 0.0), axis=1)) / (m + 1)
        f = np.where(dmin > 0, s.lambda_avg * avg + s.lambda_min * dmin, s.lambda_min * dmin)
        return f[:K], f[K:], m[:K], m[K:]

    def evaluate(self, x: np.ndarray) -> np.ndarray:
        """The objective (smaller is safer) for K placements ``x`` (K, 2), compiled (the
        search's inner loop; :meth:`evaluate_numpy` is the same in numpy)."""
        s = self.s
        x = np.ascontiguousarray(np.atleast_2d(np.asarray(x, dtype=float)))
        return _objective(self.model.coefficients, self.model.z, self.T_ch, x, s.rod_radius,
                          s.implant_length, s.rod_radius if s.shrink_line2 else 0.0,
                          s.lambda_avg, s.lambda_min, s.equation)

    def evaluate_numpy(self, x: np.ndarray) -> np.ndarray:
        """:meth:`evaluate` from :meth:`line_values` in numpy: the reference the compiled
        objective is tested and benchmarked against."""
        f1, f2, m1, m2 = self.line_values(x)
        a, b = f1 * 1e3, f2 * 1e3       # the paper's millimetres
        if self.s.equation == 14:
            a, b = _signed_root(a), _signed_root(b)
        elif self.s.equation == 22:
            a, b = np.sign(a) * a * a, np.sign(b) * b * b
        return -((m1 + 1) * a + (m2 + 1) * b) / (m1 + m2 + 2)

    def grid(self, n_d: int = 121, n_theta: int = 121) -> tuple[np.ndarray, np.ndarray,
                                                                 np.ndarray]:
        """The objective on a dense grid over the search box: ``d`` (n_d,), ``theta``
        (n_theta,), values (n_theta, n_d). For contour charts and the optimality check."""
        d = np.linspace(*self.s.d_range, n_d)
        th = np.linspace(*self.s.theta_range, n_theta)
        D, TH = np.meshgrid(d, th)
        vals = self.evaluate(np.stack([D.ravel(), TH.ravel()], axis=1))
        return d, th, vals.reshape(TH.shape)


@dataclass(frozen=True)
class Placement:
    """The planned feeding target. ``collision_free`` is False when no placement clears the
    model: then ``d_T``/``theta_T`` are the least bad found and must not be used."""

    d_T: float                     # m
    theta_T: float                 # rad
    objective: float
    iterations: int
    evaluations: int
    time_ms: float
    collision_free: bool
    f_safe_line1: float            # m
    f_safe_line2: float            # m
    T_C_tool: np.ndarray           # the tool frame at the target
    history: np.ndarray = field(repr=False)
    certified: bool = False        # the lines' clearances below hold for the mesh itself
    clearance_line1: float = math.nan   # certified rod clearance (m); NaN: no certificate
    clearance_line2: float = math.nan
    reason: str = ""               # why it is not collision-free, for the operator

    def to_dict(self) -> dict:
        """The ``oralnav plan place --json`` object (SI units)."""
        return {"d_T": self.d_T, "theta_T": self.theta_T, "objective": self.objective,
                "iterations": self.iterations, "time_ms": self.time_ms,
                "collision_free": self.collision_free}


#: How far (m) a line is followed when certified: it is clipped where it leaves the
#: model's front, so any length past the mouth does.
LINE_LENGTH = 1.0

#: Added to the objective of a placement that is not certified clear, plus its shortfall
#: in mm: worse than any certified one (objectives are a few sqrt(mm)).
UNCERTIFIED_PENALTY = 1000.0


def certify_lines(check: RodCheck, problem: PlacementProblem, x: np.ndarray,
                  need: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Certified clearances (m) of line1 and line2 for K placements ``x`` (K, 2), as rods
    of the rod radius (line2 of ``rod_radius`` only when ``shrink_line2``, as in the
    search). A value below ``need`` (m) says only that the line is not certified that
    clear (:meth:`~oralnav.control.planning.rod_check.RodCheck.clearances`)."""
    s = problem.s
    P1, P2, D = problem.lines(x)
    K = P1.shape[0]
    T = np.concatenate([P1, P2])
    E = T + LINE_LENGTH * np.concatenate([D, D])
    r = np.concatenate([np.full(K, s.rod_radius),
                        np.full(K, s.rod_radius if s.shrink_line2 else 0.0)])
    c = check.clearances(T, E, r, need)
    return c[:K], c[K:]


def uncertified_penalty(check: RodCheck, problem: PlacementProblem
                         ) -> Callable[[np.ndarray], np.ndarray]:
    def penalty(x: np.ndarray) -> np.ndarray:
        need = problem.s.min_clearance
        c1, c2 = certify_lines(check, problem, x, need)
        short = need - np.minimum(c1, c2)
        return np.where(short <= 0, 0.0, UNCERTIFIED_PENALTY + short * 1e3)
    return penalty


def place(model: FPSM, hole: Hole, settings: PlacementSettings | None = None,
          check: RodCheck | None = None) -> Placement:
    """Optimise ``(d_T, theta_T)`` by PSO on the chosen objective (eq. 14 by default).

    When the model carries a certificate, placements whose lines are not certified clear
    (:func:`certify_lines`) are penalised during the search (lazily, see
    :func:`~oralnav.control.planning.pso.minimize_pso`) and the result must be certified to count
    as collision-free. ``check``: a prebuilt :class:`~oralnav.control.planning.rod_check.RodCheck`
    of ``model``, built here otherwise (a few hundred ms); ``time_ms`` is the search."""
    problem = PlacementProblem(model, hole, settings)
    s = problem.s
    lo = np.array([s.d_range[0], s.theta_range[0]])
    hi = np.array([s.d_range[1], s.theta_range[1]])
    certified = model.certificate is not None
    penalty = None
    if certified:
        check = check if check is not None else RodCheck(model)
        penalty = uncertified_penalty(check, problem)
    t0 = time.perf_counter()
    res = minimize_pso(problem.evaluate, lo, hi, s.pso, penalty=penalty)
    ms = (time.perf_counter() - t0) * 1e3
    f1, f2, _, _ = problem.line_values(res.x[None])
    ok = bool(f1[0] > 0 and f2[0] > 0)
    reason = "" if ok else (f"no placement clears the surrogate model: f_safe of line1 "
                            f"{f1[0] * 1e3:.2f} mm, line2 {f2[0] * 1e3:.2f} mm")
    c1 = c2 = math.nan
    if certified:
        cc1, cc2 = certify_lines(check, problem, res.x[None], s.min_clearance)
        c1, c2 = float(cc1[0]), float(cc2[0])
        if ok and not min(c1, c2) >= s.min_clearance:
            ok = False
            reason = (f"no placement found keeps the certified {s.min_clearance * 1e3:.2f} mm "
                      f"from the tissue (the best clears the surrogate's rays; certified rod "
                      f"clearance of line1 {c1 * 1e3:.2f} mm, line2 {c2 * 1e3:.2f} mm)")
    return Placement(d_T=float(res.x[0]), theta_T=float(res.x[1]), objective=float(res.value),
                     iterations=res.iterations, evaluations=res.evaluations, time_ms=ms,
                     collision_free=ok, f_safe_line1=float(f1[0]), f_safe_line2=float(f2[0]),
                     T_C_tool=tool_pose(problem.T_ch, float(res.x[0]), float(res.x[1])),
                     history=res.history, certified=certified, clearance_line1=c1,
                     clearance_line2=c2, reason=reason)
