"""The finite-parameter surrogate model (FPSM) of the oral cavity (seed 004, §3 and §4.1).

Frame: the model's ``Center`` frame, metres. Its Z axis runs through the cavity and out of
the mouth; ``M`` slices are the planes ``z = z_j`` and each holds one closed polar curve
(:mod:`oralnav.control.polar_curve`) centred on the Z axis. Inside a curve is free space;
the tissue is outside.

Building a model (§3.2-3.3) has two steps:

1. **Pre-assignment**: :func:`slice_boundaries` cuts the mesh with every slice plane
   (trimesh), keeps per sampling ray only the cut segments whose angular span covers it,
   and returns, for each slice and each of the ``Z`` sampling angles, the distance from
   the slice origin to the first tissue hit. This is the paper's container of triangles
   "aligned with the sampling points" reduced to what the penetration test reads.
2. **Fit**: each curve is made as large as it can be without a sampling point passing its
   ray's boundary radius. :func:`fit_slices` offers the paper's method and two better ones:

   - ``"paper"``: eq. 7's ``F = -S + lambda f_pene^2`` minimised by eq. 8's normalised
     gradient descent with eq. 9's central differences, slice by slice; the baseline.
   - ``"lbfgs"``: the same trade-off with a smooth penalty on the penetration *depth*
     (``f_pene`` counts samples, so its gradient is zero almost everywhere) and the
     analytic gradient, all slices in one L-BFGS-B problem, then the curve shrunk by its
     worst penetrating sample so that none is left.
   - ``"slp"`` (default): maximise the area under the hard constraints ``rho(theta_z) <=
     boundary_z`` by sequential linear programming. ``rho`` is linear in the control
     points and the area is a convex quadratic, so each linearisation is a lower bound and
     every step (one HiGHS LP over all slices) increases the area while staying feasible.
     No penalty weight to tune and no penetrating sample by construction.

Coverage of a slice (:class:`SliceReport`) is the curve's area over the area of the tissue
boundary as seen from the slice origin (``0.5 * int r_b(theta)^2 dtheta`` on a dense ray
set: the largest star-shaped region a polar curve can fill). Penetration is measured on
that dense set as well, so it also catches bulges between the sampling rays.

Queries (§4.1): :meth:`FPSM.safe_distance` is eq. 10 on a slice and eq. 11 between
slices, with eq. 12's shrink by a rod radius.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.sparse as sp
from scipy.optimize import linprog, minimize

from . import polar_curve as pc
from .errors import PlanningError

TWO_PI = 2.0 * math.pi

#: Fit methods of :func:`fit_slices`.
METHODS = ("slp", "lbfgs", "paper")

#: Dense rays per slice for coverage and penetration reports (0.25 deg apart).
DENSE_RAYS = 1440


# -- pre-assignment: mesh -> boundary radii ---------------------------------------------

def cut_segments(mesh: Any, z: np.ndarray) -> list[np.ndarray]:
    """The mesh cut by each plane ``z = z_j``: a list of (S_j, 2, 2) arrays of 2D segments
    (x, y in metres, Center frame). ``mesh`` is a ``trimesh.Trimesh`` in the Center frame.
    """
    import trimesh  # heavy import, needed only when a model is built

    out = []
    for zj in np.asarray(z, dtype=float):
        seg = trimesh.intersections.mesh_plane(mesh, (0.0, 0.0, 1.0), (0.0, 0.0, float(zj)))
        out.append(np.asarray(seg, dtype=float).reshape(-1, 2, 3)[:, :, :2])
    return out


def ray_radii(segments: np.ndarray, n_rays: int) -> np.ndarray:
    """Distance (m) from the origin to the nearest segment along each of ``n_rays`` rays at
    angles ``2 pi i / n_rays``; ``inf`` where a ray hits nothing.

    ``segments`` is (S, 2, 2). Each segment is tested only against the rays inside its
    angular span (the pre-assignment), so the cost is O(S + hits), not O(S * n_rays).
    """
    seg = np.asarray(segments, dtype=float).reshape(-1, 2, 2)
    out = np.full(n_rays, np.inf)
    if seg.shape[0] == 0:
        return out
    a, b = seg[:, 0], seg[:, 1]
    e = b - a
    ang_a = np.arctan2(a[:, 1], a[:, 0])
    span = np.arctan2(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0], np.einsum("ij,ij->i", a, b))
    lo = np.minimum(ang_a, ang_a + span) * (n_rays / TWO_PI)
    hi = np.maximum(ang_a, ang_a + span) * (n_rays / TWO_PI)
    first = np.ceil(lo - 1e-9).astype(int)
    count = np.floor(hi + 1e-9).astype(int) - first + 1
    keep = count > 0
    if not np.any(keep):
        return out
    first, count = first[keep], count[keep]
    a, e = a[keep], e[keep]
    owner = np.repeat(np.arange(first.size), count)
    step = np.arange(owner.size) - np.repeat(np.cumsum(count) - count, count)
    ray = first[owner] + step
    ang = ray * (TWO_PI / n_rays)
    u = np.stack([np.cos(ang), np.sin(ang)], axis=1)
    ao, eo = a[owner], e[owner]
    den = u[:, 0] * eo[:, 1] - u[:, 1] * eo[:, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (ao[:, 0] * eo[:, 1] - ao[:, 1] * eo[:, 0]) / den
    ok = np.isfinite(t) & (t > 0)
    np.minimum.at(out, np.mod(ray[ok], n_rays), t[ok])
    return out


def slice_boundaries(mesh: Any, z: np.ndarray, n_rays: int,
                     segments: list[np.ndarray] | None = None) -> np.ndarray:
    """Boundary radii (M, n_rays) in metres: per slice ``z_j`` and per ray angle
    ``2 pi i / n_rays``, the distance from ``(0, 0, z_j)`` to the first tissue hit.

    Raises :class:`PlanningError` when a slice has a ray that hits nothing (the mesh does
    not enclose that slice's origin), naming the slice and the open angles.
    """
    z = np.asarray(z, dtype=float)
    segs = cut_segments(mesh, z) if segments is None else segments
    out = np.empty((z.size, n_rays))
    for j, s in enumerate(segs):
        r = ray_radii(s, n_rays)
        bad = ~np.isfinite(r)
        if np.any(bad):
            deg = np.flatnonzero(bad) * 360.0 / n_rays
            raise PlanningError(
                f"the mesh does not enclose the origin of slice {j} (z = {z[j] * 1e3:.1f} mm):"
                f" {bad.sum()} of {n_rays} rays from the Z axis hit nothing (e.g. at "
                f"{', '.join(f'{d:.1f}' for d in deg[:4])} deg); move the Z axis inside the"
                " cavity or narrow the slice range")
        out[j] = r
    return out


# -- the model --------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class FPSM:
    """Slices ``z`` (M,) ascending, metres, and control radii ``rho`` (M, N), metres, in
    the Center frame. Immutable; build with :func:`build_fpsm` or :meth:`cylinder`."""

    z: np.ndarray
    rho: np.ndarray
    _coef: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        z = np.asarray(self.z, dtype=float).ravel()
        rho = np.asarray(self.rho, dtype=float)
        if z.size < 2:
            raise PlanningError(f"a surrogate model needs at least 2 slices, got {z.size}")
        if rho.ndim != 2 or rho.shape[0] != z.size:
            raise PlanningError(f"rho must be (slices, points) = ({z.size}, N), "
                                f"got shape {rho.shape}")
        pc.check_points(rho.shape[1])
        if not (np.all(np.isfinite(z)) and np.all(np.isfinite(rho))):
            raise PlanningError("surrogate model has non-finite slice heights or radii")
        if np.any(np.diff(z) <= 0):
            raise PlanningError("surrogate model slice heights must be strictly ascending")
        if np.any(rho < 0):
            raise PlanningError("surrogate model has negative control radii")
        z.setflags(write=False)
        rho = rho.copy()
        rho.setflags(write=False)
        object.__setattr__(self, "z", z)
        object.__setattr__(self, "rho", rho)
        taps = np.stack([np.roll(rho, -s, axis=1) for s in (-1, 0, 1, 2)], axis=2)
        # per slice and segment, the coefficients of 1, t, t^2, t^3 (M, N, 4)
        object.__setattr__(self, "_coef", taps @ pc._WEIGHTS)

    @classmethod
    def cylinder(cls, radius: float, z_min: float, z_max: float, slices: int,
                 points: int = 15) -> FPSM:
        """A circular cylinder of ``radius`` (m) around Z between ``z_min`` and ``z_max``:
        every curve constant (the spline reproduces constants exactly)."""
        if not (radius > 0 and z_max > z_min):
            raise PlanningError(f"cylinder needs radius > 0 and z_max > z_min, got radius "
                                f"{radius}, z {z_min}..{z_max}")
        return cls(np.linspace(z_min, z_max, slices), np.full((slices, points), radius))

    @property
    def slices(self) -> int:
        return self.z.size

    @property
    def points(self) -> int:
        return self.rho.shape[1]

    def radius(self, j: int | np.ndarray, theta: np.ndarray, shrink: float = 0.0) -> np.ndarray:
        """``rho_j(theta) - shrink`` (m): slice index/indices ``j`` broadcast with
        ``theta`` (rad)."""
        j = np.asarray(j)
        th = np.asarray(theta, dtype=float)
        shape = np.broadcast_shapes(j.shape, th.shape)
        jj = np.broadcast_to(j, shape).reshape(-1)
        tt = np.broadcast_to(th, shape).reshape(-1)
        return self.radius_at(jj, tt).reshape(shape) - shrink

    def radius_at(self, j: np.ndarray, theta: np.ndarray) -> np.ndarray:
        """``rho_j(theta)`` (m) for flat, equally long integer ``j`` and ``theta`` (rad):
        :meth:`radius` without the broadcasting, for hot loops."""
        # one gather of the segment's power coefficients, then Horner: the hot path of
        # every collision query, so no per-call basis assembly
        n = self.points
        u = np.mod(theta, TWO_PI) * (n / TWO_PI)
        k = np.minimum(u.astype(int), n - 1)
        t = u - k
        c = self._coef[j, k]
        return ((c[:, 3] * t + c[:, 2]) * t + c[:, 1]) * t + c[:, 0]

    def slice_safe_distance(self, j: np.ndarray, xy: np.ndarray,
                            shrink: float = 0.0) -> np.ndarray:
        """Eq. 10 on slice(s) ``j``: ``rho_j(theta_P) - shrink - |P_xy|`` (m) for points
        ``xy`` (..., 2); positive inside the (shrunk) curve."""
        xy = np.asarray(xy, dtype=float)
        theta = np.arctan2(xy[..., 1], xy[..., 0])
        return self.radius(j, theta, shrink) - np.hypot(xy[..., 0], xy[..., 1])

    def safe_distance(self, points: np.ndarray, shrink: float = 0.0) -> np.ndarray:
        """Safe distance (m) of points (..., 3), Center frame: eq. 10 on a slice, eq. 11's
        linear interpolation between the two slices around the point.

        Outside the slice range the model knows nothing, so the answer is never positive
        there: the nearest slice's distance capped at zero, minus how far beyond it the
        point is (continuous, and it steers an optimiser back into the model).
        """
        P = np.asarray(points, dtype=float)
        shape = P.shape[:-1]
        P = P.reshape(-1, 3)
        z = self.z
        zc = np.clip(P[:, 2], z[0], z[-1])
        j = np.clip(np.searchsorted(z, zc, side="right") - 1, 0, z.size - 2)
        d1 = self.slice_safe_distance(j, P[:, :2], shrink)
        d2 = self.slice_safe_distance(j + 1, P[:, :2], shrink)
        w = (zc - z[j]) / (z[j + 1] - z[j])
        d = d1 + (d2 - d1) * w
        beyond = np.abs(P[:, 2] - zc)
        d = np.where(beyond > 0, np.minimum(d, 0.0) - beyond, d)
        return d.reshape(shape)

    def to_dict(self) -> dict[str, Any]:
        """Plain-data form (the FPSM file's model part, docs/formats.md)."""
        return {"frame": "Center", "units": "m", "z": self.z.tolist(),
                "rho": self.rho.tolist()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> FPSM:
        try:
            return cls(np.asarray(d["z"], dtype=float), np.asarray(d["rho"], dtype=float))
        except KeyError as exc:
            raise PlanningError(f"surrogate model lacks {exc.args[0]!r}") from None
        except (TypeError, ValueError) as exc:
            if isinstance(exc, PlanningError):
                raise
            raise PlanningError(f"surrogate model is malformed: {exc}") from None


# -- the fit ----------------------------------------------------------------------------

@dataclass(frozen=True)
class FitSettings:
    """Settings of :func:`fit_slices`. ``margin`` (m) is kept between every sampling point
    and its boundary; the paper's settings (§5.1) are the ``paper_*`` defaults, in the
    paper's millimetre units since its penalty weight is relative to areas in mm^2."""

    method: str = "slp"
    margin: float = 0.0
    max_iterations: int = 50           # slp / lbfgs outer steps
    tolerance: float = 1e-7            # relative area gain that ends the slp iterations
    lbfgs_weight: float = 1e6          # penalty weight on squared depth (m^2 -> m^2 area)
    paper_lambda: float = 30000.0      # lambda_pene of eq. 7 (area in mm^2)
    paper_alpha_mm: float = 0.1        # alpha of eq. 8 (mm)
    paper_delta_mm: float = 0.01       # delta rho of eq. 9 (mm)
    paper_iterations: int = 1000

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise PlanningError(f"unknown fit method {self.method!r}; one of {METHODS}")
        if not (self.margin >= 0 and math.isfinite(self.margin)):
            raise PlanningError(f"fit margin must be >= 0 m, got {self.margin}")
        for name in ("max_iterations", "paper_iterations"):
            if getattr(self, name) < 1:
                raise PlanningError(f"{name} must be >= 1")
        for name in ("tolerance", "lbfgs_weight", "paper_lambda", "paper_alpha_mm",
                     "paper_delta_mm"):
            if not getattr(self, name) > 0:
                raise PlanningError(f"{name} must be > 0")


@dataclass(frozen=True)
class FitResult:
    rho: np.ndarray        # (M, N) control radii, m
    iterations: int        # outer iterations (slp LPs, lbfgs iterations, paper steps summed)
    seconds: float


def _sample_angles(n_samples: int) -> np.ndarray:
    return np.arange(n_samples) * (TWO_PI / n_samples)


def fit_slices(boundary: np.ndarray, n_points: int,
               settings: FitSettings | None = None) -> FitResult:
    """Fit one curve of ``n_points`` control points per row of ``boundary`` (M, Z): the
    boundary radii (m) at the ``Z`` sampling angles ``2 pi z / Z``. See the module doc."""
    s = settings or FitSettings()
    b = np.asarray(boundary, dtype=float)
    if b.ndim != 2 or not np.all(np.isfinite(b)) or np.any(b <= 0):
        raise PlanningError("boundary radii must be a finite, positive (slices, samples) array")
    n = pc.check_points(n_points)
    if b.shape[1] < n:
        raise PlanningError(f"{b.shape[1]} sampling points cannot pin {n} control points;"
                            " use at least as many samples as points")
    cap = b - s.margin
    if np.any(cap <= 0):
        raise PlanningError(f"fit margin {s.margin * 1e3:.2f} mm exceeds a boundary radius "
                            f"({b.min() * 1e3:.2f} mm)")
    B = pc.basis(_sample_angles(b.shape[1]), n)
    t0 = time.perf_counter()
    if s.method == "slp":
        rho, it = _fit_slp(B, cap, s)
    elif s.method == "lbfgs":
        rho, it = _fit_lbfgs(B, cap, s)
    else:
        rho, it = _fit_paper(B, cap, s)
    return FitResult(rho, it, time.perf_counter() - t0)


def _fit_slp(B: np.ndarray, cap: np.ndarray, s: FitSettings) -> tuple[np.ndarray, int]:
    m, n = cap.shape[0], B.shape[1]
    G = pc.area_matrix(n)
    A = sp.kron(sp.identity(m, format="csr"), sp.csr_matrix(B), format="csr")
    bub = cap.ravel()
    bounds = [(0.0, float(2.0 * cap.max()))] * (m * n)
    rho = np.repeat(cap.min(axis=1)[:, None], n, axis=1)   # a feasible circle per slice
    S = pc.area(rho).sum()
    it = 0
    while it < s.max_iterations:
        it += 1
        grad = rho @ G                                      # dS/dp per slice
        res = linprog(-grad.ravel(), A_ub=A, b_ub=bub, bounds=bounds, method="highs")
        if res.status != 0:
            raise PlanningError(f"surrogate fit: the linear program failed ({res.message})")
        new = np.clip(res.x.reshape(m, n), 0.0, None)
        S_new = pc.area(new).sum()
        if S_new <= S * (1.0 + s.tolerance):
            if S_new > S:
                rho = new
            break
        rho, S = new, S_new
    # the LP honours the constraints to its feasibility tolerance (~1e-9 m); remove that
    over = (rho @ B.T - cap).max(axis=1)
    rho = rho - np.clip(over, 0.0, None)[:, None]
    return rho, it


def _fit_lbfgs(B: np.ndarray, cap: np.ndarray, s: FitSettings) -> tuple[np.ndarray, int]:
    m, n = cap.shape[0], B.shape[1]
    G = pc.area_matrix(n)
    lam = s.lbfgs_weight
    scale = float(cap.mean())          # work in units of the mean radius: well scaled

    def f(x: np.ndarray) -> tuple[float, np.ndarray]:
        P = x.reshape(m, n)
        excess = P @ B.T - cap / scale
        pos = np.clip(excess, 0.0, None)
        val = -0.5 * np.einsum("ij,jk,ik->", P, G, P) + lam * np.sum(pos * pos)
        grad = -(P @ G) + 2.0 * lam * (pos @ B)
        return float(val), grad.ravel()

    x0 = np.repeat((cap.min(axis=1) / scale)[:, None], n, axis=1).ravel()
    res = minimize(f, x0, jac=True, method="L-BFGS-B",
                   bounds=[(0.0, 2.0 * float(cap.max()) / scale)] * (m * n),
                   options={"maxiter": 200 * s.max_iterations, "gtol": 1e-10})
    rho = res.x.reshape(m, n) * scale
    over = (rho @ B.T - cap).max(axis=1)             # the penalty allows slight excess
    rho = np.clip(rho - np.clip(over, 0.0, None)[:, None], 0.0, None)
    return rho, int(res.nit)


def _fit_paper(B: np.ndarray, cap: np.ndarray, s: FitSettings) -> tuple[np.ndarray, int]:
    """Eqs. 7-9 as the paper states them, slice by slice, in millimetres."""
    m, n = cap.shape[0], B.shape[1]
    G = pc.area_matrix(n)
    capmm = cap * 1e3
    z = cap.shape[1]
    lam, alpha, delta = s.paper_lambda, s.paper_alpha_mm, s.paper_delta_mm
    out = np.empty((m, n))
    total = 0
    # +/- delta on each coordinate: the 2N probes of eq. 9, evaluated together
    probes = np.concatenate([np.eye(n), -np.eye(n)]) * delta

    def F(P: np.ndarray, c: np.ndarray) -> np.ndarray:
        S = 0.5 * np.einsum("ij,jk,ik->i", P, G, P)
        pene = np.count_nonzero(P @ B.T > c, axis=1) / z
        return -S + lam * pene * pene

    for j in range(m):
        c = capmm[j]
        rho = np.full(n, c.min())                # the inscribed circle, as the slp fit
        best, best_F = rho.copy(), F(rho[None], c)[0]
        for _ in range(s.paper_iterations):
            vals = F(rho[None] + probes, c)
            g = (vals[:n] - vals[n:]) / (2.0 * delta)
            norm = np.linalg.norm(g)
            total += 1
            if norm == 0:
                break
            rho = rho - alpha * g / norm
            Fr = F(rho[None], c)[0]
            if Fr < best_F:
                best, best_F = rho.copy(), Fr
        out[j] = best
    return out * 1e-3, total


# -- building and reporting ---------------------------------------------------------------

@dataclass(frozen=True)
class SliceReport:
    """One slice of a built model. Areas m^2, lengths m."""

    z: float
    area: float
    boundary_area: float           # visible region from the slice origin, dense rays
    coverage: float                # area / boundary_area
    penetrating_samples: int       # sampling points beyond their boundary radius
    penetration_max: float         # deepest excursion beyond the boundary on dense rays (m)


@dataclass(frozen=True)
class BuildReport:
    method: str
    slices: int
    points: int
    samples: int
    preassign_s: float
    fit_s: float
    iterations: int
    per_slice: tuple[SliceReport, ...] = field(default_factory=tuple)

    @property
    def total_s(self) -> float:
        return self.preassign_s + self.fit_s

    @property
    def coverage(self) -> float:
        """Total curve area over total visible boundary area."""
        return (sum(r.area for r in self.per_slice)
                / sum(r.boundary_area for r in self.per_slice))

    @property
    def penetrating_samples(self) -> int:
        return sum(r.penetrating_samples for r in self.per_slice)

    @property
    def penetration_max(self) -> float:
        return max(r.penetration_max for r in self.per_slice)

    def to_dict(self) -> dict[str, Any]:
        return {"method": self.method, "slices": self.slices, "points": self.points,
                "samples": self.samples, "preassign_s": self.preassign_s,
                "fit_s": self.fit_s, "total_s": self.total_s,
                "iterations": self.iterations, "coverage": self.coverage,
                "penetrating_samples": self.penetrating_samples,
                "penetration_max_m": self.penetration_max,
                "per_slice": [vars(r) for r in self.per_slice]}


def slice_heights(z_min: float, z_max: float, slices: int) -> np.ndarray:
    """``slices`` planes evenly through [z_min, z_max] (m), at the centres of equal
    intervals so that none sits on a cap of the mesh."""
    if slices < 2:
        raise PlanningError(f"a surrogate model needs at least 2 slices, got {slices}")
    if not z_max > z_min:
        raise PlanningError(f"slice range is empty: z {z_min * 1e3:.1f}..{z_max * 1e3:.1f} mm")
    return z_min + (np.arange(slices) + 0.5) * (z_max - z_min) / slices


def report_slices(model: FPSM, dense: np.ndarray, samples: np.ndarray) -> list[SliceReport]:
    """Coverage and penetration of each slice against its boundary radii on the dense
    rays ``dense`` (M, R) and on the sampling rays ``samples`` (M, Z)."""
    out = []
    R = dense.shape[1]
    Bd = pc.basis(_sample_angles(R), model.points)
    Bs = pc.basis(_sample_angles(samples.shape[1]), model.points)
    curve_d = model.rho @ Bd.T
    curve_s = model.rho @ Bs.T
    for j in range(model.slices):
        # both areas by the same rule on the same rays, so their ratio is unbiased
        a_b = 0.5 * np.mean(dense[j] ** 2) * TWO_PI
        a_c = float(pc.area(model.rho[j]))
        out.append(SliceReport(
            z=float(model.z[j]), area=a_c, boundary_area=float(a_b),
            coverage=float(a_c / a_b),
            penetrating_samples=int(np.count_nonzero(curve_s[j] > samples[j] + 1e-12)),
            penetration_max=float(max(0.0, np.max(curve_d[j] - dense[j])))))
    return out


def build_fpsm(mesh: Any, slices: int = 15, points: int = 15, samples: int = 150,
               z_range: tuple[float, float] | None = None,
               settings: FitSettings | None = None) -> tuple[FPSM, BuildReport]:
    """Build a model of ``mesh`` (trimesh, Center frame, metres): ``slices`` planes across
    ``z_range`` (default: the mesh's z extent), ``points`` control points and ``samples``
    sampling rays per slice. Returns the model and its :class:`BuildReport`; the timings
    cover the pre-assignment and the fit, not the coverage report."""
    s = settings or FitSettings()
    if samples < 3:
        raise PlanningError(f"samples must be >= 3, got {samples}")
    if mesh is None or len(getattr(mesh, "faces", ())) == 0:
        raise PlanningError("the mesh is empty: no triangles to fit the surrogate model to")
    lo, hi = (float(mesh.bounds[0][2]), float(mesh.bounds[1][2])) if z_range is None \
        else (float(z_range[0]), float(z_range[1]))
    z = slice_heights(lo, hi, slices)
    t0 = time.perf_counter()
    segs = cut_segments(mesh, z)
    boundary = slice_boundaries(mesh, z, samples, segments=segs)
    t1 = time.perf_counter()
    fit = fit_slices(boundary, points, s)
    model = FPSM(z, fit.rho)
    dense = slice_boundaries(mesh, z, DENSE_RAYS, segments=segs)
    report = BuildReport(method=s.method, slices=slices, points=points, samples=samples,
                         preassign_s=t1 - t0, fit_s=fit.seconds, iterations=fit.iterations,
                         per_slice=tuple(report_slices(model, dense, boundary)))
    return model, report
