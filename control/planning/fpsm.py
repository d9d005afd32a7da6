"""The finite-parameter surrogate model (FPSM) of the oral cavity (seed 004, §3 and §4.1).

Frame: the model's ``Center`` frame, metres. Its Z axis runs through the cavity and out of
the mouth; ``M`` slices are the planes ``z = z_j`` and each holds one closed polar curve
(:mod:`oralnav.control.planning.polar_curve`) centred on the Z axis. Inside a curve is free space;
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

from oralnav.control.errors import PlanningError
from oralnav.control.planning import polar_curve as pc

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
    # a segment along its ray (the projection of an edge in a plane through Z, common
    # in the slab envelopes) makes den ~ 0 and t garbage: its first point is the nearer end
    radial = np.abs(den) <= 1e-9 * np.hypot(eo[:, 0], eo[:, 1])
    if np.any(radial):
        near = np.minimum(np.hypot(ao[:, 0], ao[:, 1]),
                          np.hypot(ao[:, 0] + eo[:, 0], ao[:, 1] + eo[:, 1]))
        t = np.where(radial, near, t)
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


def envelope_segments(mesh: Any, lo: float, hi: float) -> np.ndarray:
    """The outline of the mesh's part within ``lo <= z <= hi`` (m), projected on the XY
    plane: (S, 2, 2) segments whose first hit along any ray from the Z axis is the nearest
    tissue over the whole slab, not only in one plane.

    A triangle clipped to the slab is convex; its projection's edges are its own edges
    clipped to the slab plus its cuts by the two planes, so those are all the segments
    needed. Raises :class:`PlanningError` when tissue crosses the Z axis inside the slab
    (a triangle over the axis, e.g. a cap): no ray from the axis starts in free space.
    """
    V = np.asarray(mesh.vertices, dtype=float)
    F = np.asarray(mesh.faces)
    E = np.asarray(mesh.edges_unique)
    a, b = V[E[:, 0]], V[E[:, 1]]
    keep = (np.maximum(a[:, 2], b[:, 2]) >= lo) & (np.minimum(a[:, 2], b[:, 2]) <= hi)
    a, b = a[keep], b[keep]
    e = b - a
    with np.errstate(divide="ignore", invalid="ignore"):
        t_lo = (lo - a[:, 2]) / e[:, 2]
        t_hi = (hi - a[:, 2]) / e[:, 2]
    flat = e[:, 2] == 0            # an edge in a plane z = const inside the slab: all of it
    t0 = np.where(flat, 0.0, np.clip(np.minimum(t_lo, t_hi), 0.0, 1.0))
    t1 = np.where(flat, 1.0, np.clip(np.maximum(t_lo, t_hi), 0.0, 1.0))
    clipped = np.stack([(a + t0[:, None] * e)[:, :2], (a + t1[:, None] * e)[:, :2]], axis=1)
    # tissue over the axis: a triangle whose projection holds the origin with its height
    # there inside the slab
    T = V[F]
    z_lo_f, z_hi_f = T[:, :, 2].min(axis=1), T[:, :, 2].max(axis=1)
    T = T[(z_hi_f >= lo) & (z_lo_f <= hi)]
    p0, p1, p2 = T[:, 0], T[:, 1], T[:, 2]
    u, v = p1[:, :2] - p0[:, :2], p2[:, :2] - p0[:, :2]
    o = -p0[:, :2]                          # the origin relative to p0
    d = u[:, 0] * v[:, 1] - v[:, 0] * u[:, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        w1 = (o[:, 0] * v[:, 1] - v[:, 0] * o[:, 1]) / d
        w2 = (u[:, 0] * o[:, 1] - o[:, 0] * u[:, 1]) / d
        w0 = 1.0 - w1 - w2
        over = (np.abs(d) > 0) & (w0 >= 0) & (w1 >= 0) & (w2 >= 0)
        zc = w0 * p0[:, 2] + w1 * p1[:, 2] + w2 * p2[:, 2]
    if np.any(over & (zc >= lo) & (zc <= hi)):
        zz = float(zc[over & (zc >= lo) & (zc <= hi)][0])
        raise PlanningError(
            f"tissue crosses the Z axis at z = {zz * 1e3:.1f} mm, inside the slab "
            f"{lo * 1e3:.1f}..{hi * 1e3:.1f} mm of a slice: move the Z axis inside the cavity "
            "or narrow the slice range")
    cuts = cut_segments(mesh, np.array([lo, hi]))
    return np.concatenate([clipped] + cuts)


def slice_cells(z: np.ndarray, z_lo: float, z_hi: float, reach: float) -> np.ndarray:
    """The slab (M, 2) each slice's curve must stay clear over, m: from half-way to the
    previous slice to half-way to the next; the first starts at ``z_lo`` (behind it the
    model assumes tissue), the last reaches ``reach`` beyond ``z_hi`` (so that a ball of
    radius up to ``reach`` centred in the model is covered)."""
    z = np.asarray(z, dtype=float)
    mid = 0.5 * (z[1:] + z[:-1])
    return np.stack([np.concatenate([[z_lo], mid]), np.concatenate([mid, [z_hi + reach]])],
                    axis=1)


def envelope_boundaries(mesh: Any, cells: np.ndarray, n_rays: int,
                        segments: list[np.ndarray] | None = None
                        ) -> tuple[np.ndarray, list[np.ndarray]]:
    """Boundary radii (M, n_rays), m: per slice, the distance from the Z axis to the
    nearest tissue anywhere in its cell (:func:`slice_cells`), and the cells' segments
    (reusable for another ray count)."""
    segs = segments if segments is not None else [
        envelope_segments(mesh, float(lo), float(hi)) for lo, hi in cells]
    mid = 0.5 * (np.asarray(cells)[:, 0] + np.asarray(cells)[:, 1])
    return slice_boundaries(None, mid, n_rays, segments=segs), segs


def excursion(model_rho: np.ndarray, dense: np.ndarray, segments: list[np.ndarray]
              ) -> np.ndarray:
    """Per slice, how far (m, >= 0) the fitted curve reaches past tissue: on the dense
    rays' hits and at every segment end point of the slice's outline (where a tooth's
    corner can sit between two rays)."""
    n = model_rho.shape[1]
    Bd = pc.basis(_sample_angles(dense.shape[1]), n)
    out = np.maximum(0.0, np.max(model_rho @ Bd.T - dense, axis=1))
    for j, seg in enumerate(segments):
        pts = np.asarray(seg, dtype=float).reshape(-1, 2)
        if pts.size == 0:
            continue
        th = np.arctan2(pts[:, 1], pts[:, 0])
        rho = pc.basis(np.mod(th, TWO_PI), n) @ model_rho[j]
        out[j] = max(out[j], float(np.max(rho - np.hypot(pts[:, 0], pts[:, 1]))))
    return out


# -- the model --------------------------------------------------------------------------

@dataclass(frozen=True)
class Certificate:
    """What a model built on slab envelopes guarantees (:mod:`oralnav.control.planning.rod_check`
    relies on it): slice ``j``'s curve, pulled in by ``excursion[j]`` (m), is clear of
    tissue over its whole cell of :func:`slice_cells`; behind ``z_lo`` lies tissue; the
    last cell reaches ``reach`` beyond ``z_hi``. Lengths m."""

    z_lo: float
    z_hi: float
    reach: float
    excursion: tuple[float, ...]

    def __post_init__(self) -> None:
        vals = (self.z_lo, self.z_hi, *self.excursion)
        if not (all(math.isfinite(v) for v in vals) and self.z_hi > self.z_lo
                and self.reach >= 0 and min(self.excursion, default=0.0) >= 0):
            raise PlanningError("model certificate needs finite z_lo < z_hi, reach >= 0 and "
                                "excursions >= 0 (m)")

    def to_dict(self) -> dict[str, Any]:
        return {"z_lo": self.z_lo, "z_hi": self.z_hi,
                "reach": self.reach if math.isfinite(self.reach) else "inf",
                "excursion": list(self.excursion)}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Certificate:
        try:
            return cls(float(d["z_lo"]), float(d["z_hi"]), float(d["reach"]),
                       tuple(float(v) for v in d["excursion"]))
        except KeyError as exc:
            raise PlanningError(f"model certificate lacks {exc.args[0]!r}") from None
        except (TypeError, ValueError) as exc:
            raise PlanningError(f"model certificate is malformed: {exc}") from None


@dataclass(frozen=True, eq=False)
class FPSM:
    """Slices ``z`` (M,) ascending, metres, and control radii ``rho`` (M, N), metres, in
    the Center frame. Immutable; build with :func:`build_fpsm` or :meth:`cylinder`.
    ``certificate`` is set when the curves were fitted to slab envelopes (or the model is
    analytic): only then can :mod:`oralnav.control.planning.rod_check` certify a rod."""

    z: np.ndarray
    rho: np.ndarray
    certificate: Certificate | None = None
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
        c = self.certificate
        if c is not None and (len(c.excursion) != z.size or not c.z_lo <= z[0]
                              or not z[-1] <= c.z_hi):
            raise PlanningError("model certificate does not match its slices (one excursion "
                                "a slice, z_lo <= first slice, last slice <= z_hi)")
        z.setflags(write=False)
        rho = rho.copy()
        rho.setflags(write=False)
        object.__setattr__(self, "z", z)
        object.__setattr__(self, "rho", rho)
        taps = np.stack([np.roll(rho, -s, axis=1) for s in (-1, 0, 1, 2)], axis=2)
        # per slice and segment, the coefficients of 1, t, t^2, t^3 (M, N, 4)
        coef = taps @ pc._WEIGHTS
        coef.setflags(write=False)
        object.__setattr__(self, "_coef", coef)

    @classmethod
    def cylinder(cls, radius: float, z_min: float, z_max: float, slices: int,
                 points: int = 15) -> FPSM:
        """A circular cylinder of ``radius`` (m) around Z between ``z_min`` and ``z_max``:
        every curve constant (the spline reproduces constants exactly)."""
        if not (radius > 0 and z_max > z_min):
            raise PlanningError(f"cylinder needs radius > 0 and z_max > z_min, got radius "
                                f"{radius}, z {z_min}..{z_max}")
        # analytic: nothing between or beyond the slices but the same wall, so it certifies
        return cls(np.linspace(z_min, z_max, slices), np.full((slices, points), radius),
                   Certificate(z_min, z_max, math.inf, (0.0,) * slices))

    @property
    def slices(self) -> int:
        return self.z.size

    @property
    def coefficients(self) -> np.ndarray:
        """(M, N, 4) read-only: per slice and segment ``k``, the coefficients of 1, t, t^2,
        t^3 of ``rho`` in ``t = theta N / 2 pi - k`` (m), for compiled queries."""
        return self._coef

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
        d: dict[str, Any] = {"frame": "Center", "units": "m", "z": self.z.tolist(),
                             "rho": self.rho.tolist()}
        if self.certificate is not None:
            d["certificate"] = self.certificate.to_dict()
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> FPSM:
        try:
            cert = d.get("certificate")
            return cls(np.asarray(d["z"], dtype=float), np.asarray(d["rho"], dtype=float),
                       None if cert is None else Certificate.from_dict(cert))
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
    plane_area: float = math.nan   # the plane cut's visible region (same rule as boundary_area)

    @property
    def coverage_plane(self) -> float:
        """Area over the plane cut's area: the paper's coverage for envelope-fitted curves."""
        return self.area / self.plane_area


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
    boundary: str = "plane"

    @property
    def total_s(self) -> float:
        return self.preassign_s + self.fit_s

    @property
    def coverage(self) -> float:
        """Total curve area over total visible boundary area."""
        return (sum(r.area for r in self.per_slice)
                / sum(r.boundary_area for r in self.per_slice))

    @property
    def coverage_plane(self) -> float:
        """Total curve area over total plane-cut area (equals :attr:`coverage` for plane
        fits)."""
        return (sum(r.area for r in self.per_slice)
                / sum(r.plane_area for r in self.per_slice))

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
                "iterations": self.iterations, "boundary": self.boundary,
                "coverage": self.coverage, "coverage_plane": self.coverage_plane,
                "penetrating_samples": self.penetrating_samples,
                "penetration_max_m": self.penetration_max,
                "per_slice": [dict(vars(r), coverage_plane=r.coverage_plane)
                              for r in self.per_slice]}


def slice_heights(z_min: float, z_max: float, slices: int) -> np.ndarray:
    """``slices`` planes evenly through [z_min, z_max] (m), at the centres of equal
    intervals so that none sits on a cap of the mesh."""
    if slices < 2:
        raise PlanningError(f"a surrogate model needs at least 2 slices, got {slices}")
    if not z_max > z_min:
        raise PlanningError(f"slice range is empty: z {z_min * 1e3:.1f}..{z_max * 1e3:.1f} mm")
    return z_min + (np.arange(slices) + 0.5) * (z_max - z_min) / slices


def report_slices(model: FPSM, dense: np.ndarray, samples: np.ndarray,
                  plane: np.ndarray | None = None) -> list[SliceReport]:
    """Coverage and penetration of each slice against its boundary radii on the dense
    rays ``dense`` (M, R) and on the sampling rays ``samples`` (M, Z); ``plane`` (M, R),
    the plane cuts' radii on the dense rays, when the boundary is not the plane's."""
    plane = dense if plane is None else plane
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
            penetration_max=float(max(0.0, np.max(curve_d[j] - dense[j]))),
            plane_area=float(0.5 * np.mean(plane[j] ** 2) * TWO_PI)))
    return out


#: Boundary kinds of :func:`build_fpsm`.
BOUNDARIES = ("envelope", "plane")

#: Default reach of the last cell beyond the model's front end (m): covers rods of up to
#: this radius leaving the model there.
REACH = 0.01


def build_fpsm(mesh: Any, slices: int = 15, points: int = 15, samples: int = 150,
               z_range: tuple[float, float] | None = None,
               settings: FitSettings | None = None, boundary: str = "envelope",
               reach: float = REACH) -> tuple[FPSM, BuildReport]:
    """Build a model of ``mesh`` (trimesh, Center frame, metres): ``slices`` planes across
    ``z_range`` (default: the mesh's z extent), ``points`` control points and ``samples``
    sampling rays per slice. Returns the model and its :class:`BuildReport`; the timings
    cover the pre-assignment and the fit, not the coverage report.

    ``boundary="plane"`` fits each curve to its plane's cut, as the paper does (§3.2).
    ``"envelope"`` (default) fits it to the nearest tissue over its whole cell
    (:func:`slice_cells`), so that the model, pulled in by the measured excursion, holds
    no tissue anywhere between the slices either, and carries a :class:`Certificate`.
    Coverage is reported against the fitted boundary and against the plane cuts."""
    s = settings or FitSettings()
    if samples < 3:
        raise PlanningError(f"samples must be >= 3, got {samples}")
    if boundary not in BOUNDARIES:
        raise PlanningError(f"unknown boundary {boundary!r}; one of {BOUNDARIES}")
    if not (reach >= 0 and math.isfinite(reach)):
        raise PlanningError(f"reach must be finite and >= 0 m, got {reach}")
    if mesh is None or len(getattr(mesh, "faces", ())) == 0:
        raise PlanningError("the mesh is empty: no triangles to fit the surrogate model to")
    lo, hi = (float(mesh.bounds[0][2]), float(mesh.bounds[1][2])) if z_range is None \
        else (float(z_range[0]), float(z_range[1]))
    z = slice_heights(lo, hi, slices)
    t0 = time.perf_counter()
    plane_segs = cut_segments(mesh, z)
    if boundary == "plane":
        segs = plane_segs
        b_samples = slice_boundaries(mesh, z, samples, segments=segs)
    else:
        cells = slice_cells(z, lo, hi, reach)
        # the back wall at z_lo is assumed anyway (tissue behind); a cap lying in that
        # plane must not count as tissue over the axis
        cells[0, 0] = max(cells[0, 0], lo + 1e-7)
        b_samples, segs = envelope_boundaries(mesh, cells, samples)
    t1 = time.perf_counter()
    fit = fit_slices(b_samples, points, s)
    dense = slice_boundaries(mesh, z, DENSE_RAYS, segments=segs)
    cert = None
    if boundary == "envelope":
        exc = excursion(fit.rho, dense, segs)
        cert = Certificate(lo, hi, reach, tuple(float(v) for v in exc))
    model = FPSM(z, fit.rho, cert)
    plane = dense if boundary == "plane" else slice_boundaries(mesh, z, DENSE_RAYS,
                                                                segments=plane_segs)
    report = BuildReport(method=s.method, slices=slices, points=points, samples=samples,
                         preassign_s=t1 - t0, fit_s=fit.seconds, iterations=fit.iterations,
                         per_slice=tuple(report_slices(model, dense, b_samples, plane)),
                         boundary=boundary)
    return model, report
