"""Certified rod clearance on a surrogate model (seed 004 §4.1, made conservative).

The paper's queries (eqs. 10-13, :mod:`oralnav.control.placement`) read the clearance
along rays from the slice origin, only at the slices a line crosses, and interpolate
between slices. Against the exact mesh that calls rods safe that are not: the radial
clearance exceeds the Euclidean one beside an oblique wall, and a tooth between two
slices is seen by neither (``oralnav bench planning`` counts them). This module answers
the same question with a lower bound that holds for the mesh itself, provided the model
carries a :class:`~oralnav.control.fpsm.Certificate` (curves fitted to slab envelopes):

- **In the plane**: a grid per slice of the Euclidean distance from each node to the
  curve (exact to the curve's dense polygon, capped at ``cap``), minus the slice's
  excursion and the polygon's chord error. At a point, the best of the four surrounding
  nodes' ``value - |node - point|`` is a lower bound (the distance is 1-Lipschitz).
- **Across slices**: slice ``j``'s curve is clear over its whole cell, so a ball of
  radius ``R`` about ``p`` is clear wherever, for every cell ``j`` it reaches (``dz_j`` away
  in z), ``c_j(p)^2 + dz_j^2 >= R^2``; behind the model's back end lies tissue.
  :func:`_ball` gives that largest ``R``: a lower bound of the distance to tissue, and
  1-Lipschitz like the distance.
- **Along the axis**: sphere tracing. From a sample with ball radius ``R`` the next
  sample is ``R - r - need`` further (at least ``tol``), and between two samples ``l``
  apart the distance is at least ``(R_a + R_b - l) / 2``. The result is a certified lower
  bound of the rod's clearance (axis distance to tissue minus ``r``).

The axis is checked from its start to where it leaves the model's front (``z_hi``):
beyond it, outside the mouth, the model knows nothing and checks nothing, as eq. 13
does. Compiled with numba: the grids are built once per model, a query costs well
under a microsecond per rod, batched (``oralnav bench planning`` measures it against
python-fcl on the mesh).

Pure math, no I/O. Lengths in metres, Center frame.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from . import polar_curve as pc
from .errors import PlanningError
from .fpsm import FPSM, slice_cells

TWO_PI = 2.0 * math.pi

#: Grid spacing of the distance grids (m) and the cap of the stored distances (m).
GRID = 5e-4
CAP = 0.012
#: Vertices of the dense polygon the grids measure to (0.25 deg apart).
VERTICES = 1440
#: Smallest sphere-tracing step (m): the bound is this close to the sampled minimum.
TOL = 1e-4

_NEG = -1.0   # stored for grid nodes outside the curve: "tissue" (any negative works)


@numba.njit(cache=True, nogil=True)
def _grid_values(x0: float, y0: float, h: float, nx: int, ny: int, px: np.ndarray,
                 py: np.ndarray, prad: np.ndarray, cap: float) -> np.ndarray:
    """Distance from each node to the closed polygon (px, py), capped at ``cap``, for
    nodes inside it; ``_NEG`` outside. Vertices are at equal angles ``2 pi k / K`` with
    radii ``prad``; only the polygon edges within the angle a distance ``< cap`` can
    subtend are visited."""
    K = px.size
    dth = TWO_PI / K
    out = np.empty((ny, nx))
    for iy in range(ny):
        y = y0 + iy * h
        for ix in range(nx):
            x = x0 + ix * h
            s = math.hypot(x, y)
            th = math.atan2(y, x)
            if th < 0.0:
                th += TWO_PI
            u = th / dth
            k = int(u)
            if k >= K:
                k = K - 1
            t = u - k
            k1 = (k + 1) % K
            # the polygon's radius along the node's ray: on the chord k..k1
            ax, ay = px[k], py[k]
            ex, ey = px[k1] - ax, py[k1] - ay
            cx, cy = math.cos(th), math.sin(th)
            den = cx * ey - cy * ex
            r_poly = (ax * ey - ay * ex) / den if den != 0.0 else (1 - t) * prad[k] + t * prad[k1]
            radial = r_poly - s
            if radial <= 0.0:
                out[iy, ix] = _NEG
                continue
            reach = min(radial, cap)
            if reach >= s:
                lo, hi = 0, K
            else:
                half = math.asin(reach / s) / dth + 2.0
                lo = int(math.floor(u - half))
                hi = int(math.ceil(u + half)) + 1
                if hi - lo > K:
                    lo, hi = 0, K
            best = reach
            for kk in range(lo, hi):
                i0 = kk % K
                i1 = (kk + 1) % K
                ax, ay = px[i0], py[i0]
                ex, ey = px[i1] - ax, py[i1] - ay
                ee = ex * ex + ey * ey
                w = ((x - ax) * ex + (y - ay) * ey) / ee if ee > 0.0 else 0.0
                if w < 0.0:
                    w = 0.0
                elif w > 1.0:
                    w = 1.0
                d = math.hypot(x - ax - w * ex, y - ay - w * ey)
                if d < best:
                    best = d
            out[iy, ix] = best
    return out


@numba.njit(cache=True, inline="always")
def _plane(grids: np.ndarray, k: int, x0: float, y0: float, h: float, x: float,
           y: float) -> float:
    """Lower bound of the in-plane clearance at (x, y) from slice ``k``'s grid."""
    ny, nx = grids.shape[1], grids.shape[2]
    fx = (x - x0) / h
    fy = (y - y0) / h
    ix = int(math.floor(fx))
    iy = int(math.floor(fy))
    if ix < 0 or iy < 0 or ix + 1 >= nx or iy + 1 >= ny:
        return _NEG
    ax, ay = fx - ix, fy - iy                 # the point's place in its cell, in [0, 1)
    bx, by = 1.0 - ax, 1.0 - ay
    best = _NEG
    v = grids[k, iy, ix]
    if v > 0.0:
        best = max(best, v - h * math.sqrt(ax * ax + ay * ay))
    v = grids[k, iy, ix + 1]
    if v > 0.0:
        best = max(best, v - h * math.sqrt(bx * bx + ay * ay))
    v = grids[k, iy + 1, ix]
    if v > 0.0:
        best = max(best, v - h * math.sqrt(ax * ax + by * by))
    v = grids[k, iy + 1, ix + 1]
    if v > 0.0:
        best = max(best, v - h * math.sqrt(bx * bx + by * by))
    return best


@numba.njit(cache=True, nogil=True)
def _ball(grids: np.ndarray, x0: np.ndarray, y0: np.ndarray, h: float, cells: np.ndarray,
          z_lo: float, cap: float, x: float, y: float, z: float) -> float:
    """The largest radius (m) of a ball about (x, y, z) certified clear of tissue, up to
    ``cap``; 0 at or behind the model's back end."""
    M = cells.shape[0]
    if z <= z_lo or z >= cells[M - 1, 1]:
        return 0.0
    # behind the back end lies tissue; beyond the last cell nothing is known
    best = min(cap, z - z_lo, cells[M - 1, 1] - z)
    j = 0
    while j < M - 1 and z > cells[j, 1]:
        j += 1
    # cells outward from the point's own; stop once a cell is farther than the best ball
    for step in range(2):
        k = j if step == 0 else j + 1
        direction = -1 if step == 0 else 1
        while 0 <= k < M:
            if z < cells[k, 0]:
                dz = cells[k, 0] - z
            elif z > cells[k, 1]:
                dz = z - cells[k, 1]
            else:
                dz = 0.0
            if dz >= best:
                break
            c = _plane(grids, k, x0[k], y0[k], h, x, y)
            if c <= 0.0:
                best = dz
            else:
                r = math.sqrt(c * c + dz * dz)
                if r < best:
                    best = r
            k += direction
    return best


@numba.njit(cache=True, nogil=True)
def _rod(grids: np.ndarray, x0: np.ndarray, y0: np.ndarray, h: float, cells: np.ndarray,
         z_lo: float, z_hi: float, cap: float, tx: float, ty: float, tz: float, ex: float,
         ey: float, ez: float, r: float, need: float, tol: float) -> float:
    """Certified clearance (m) of the rod of radius ``r`` on the axis T -> E, over the part
    of the axis up to the model's front ``z_hi``; ``inf`` when none of it is in the model.
    Sampling is fine only where the clearance nears ``need``."""
    vx, vy, vz = ex - tx, ey - ty, ez - tz
    L = math.sqrt(vx * vx + vy * vy + vz * vz)
    if L == 0.0:
        return _ball(grids, x0, y0, h, cells, z_lo, cap, tx, ty, tz) - r if tz <= z_hi \
            else math.inf
    ux, uy, uz = vx / L, vy / L, vz / L
    # the axis part at or below the front plane
    a, b = 0.0, L
    if uz > 0.0:
        b = min(L, (z_hi - tz) / uz)
    elif uz < 0.0:
        a = max(0.0, (z_hi - tz) / uz)
    elif tz > z_hi:
        return math.inf
    if b < a:
        return math.inf
    s = a
    R = _ball(grids, x0, y0, h, cells, z_lo, cap, tx + s * ux, ty + s * uy, tz + s * uz)
    low = R
    while s < b:
        step = max(R - r - need, tol)
        s2 = min(s + step, b)
        R2 = _ball(grids, x0, y0, h, cells, z_lo, cap, tx + s2 * ux, ty + s2 * uy,
                   tz + s2 * uz)
        gap = 0.5 * (R + R2 - (s2 - s))
        if gap < low:
            low = gap
        if R2 < low:
            low = R2
        if low - r < need:
            break               # not certified; the rest cannot raise the bound
        s, R = s2, R2
    return low - r


@numba.njit(cache=True, nogil=True)
def _rods(grids: np.ndarray, x0: np.ndarray, y0: np.ndarray, h: float, cells: np.ndarray,
          z_lo: float, z_hi: float, cap: float, T: np.ndarray, E: np.ndarray, r: np.ndarray,
          need: float, tol: float) -> np.ndarray:
    out = np.empty(T.shape[0])
    for i in range(T.shape[0]):
        out[i] = _rod(grids, x0, y0, h, cells, z_lo, z_hi, cap, T[i, 0], T[i, 1], T[i, 2],
                      E[i, 0], E[i, 1], E[i, 2], r[i], need, tol)
    return out


class RodCheck:
    """Certified rod and point clearances on one certified model (see the module doc).

    Building computes one distance grid per slice (``grid`` m apart, distances capped at
    ``cap`` m): tens of milliseconds, once per model. Queries are compiled.
    """

    def __init__(self, model: FPSM, grid: float = GRID, cap: float = CAP,
                 vertices: int = VERTICES, tol: float = TOL) -> None:
        cert = model.certificate
        if cert is None:
            raise PlanningError(
                "this surrogate model has no certificate (its curves were fitted to plane "
                "cuts, or it was saved without one): rebuild it with boundary='envelope' "
                "to certify rod clearances")
        if not (grid > 0 and cap > 0 and tol > 0 and vertices >= 16):
            raise PlanningError("grid, cap and tol must be > 0 m and vertices >= 16")
        self.model, self.h, self.cap, self.tol = model, float(grid), float(cap), float(tol)
        th = np.arange(vertices) * (TWO_PI / vertices)
        B = pc.basis(th, model.points)
        rad = model.rho @ B.T                                  # (M, K)
        # chord error: the curve between two vertices strays from their chord by at most
        # what the midpoints show (the arcs are 0.25 deg: the sagitta is nanometres)
        mid = model.rho @ pc.basis(th + np.pi / vertices, model.points).T
        cx, cy = rad * np.cos(th), rad * np.sin(th)
        mx, my = mid * np.cos(th + np.pi / vertices), mid * np.sin(th + np.pi / vertices)
        ex, ey = np.roll(cx, -1, axis=1) - cx, np.roll(cy, -1, axis=1) - cy
        sag = np.abs((mx - cx) * ey - (my - cy) * ex) / np.hypot(ex, ey)
        self.chord_error = float(np.max(sag))
        exc = np.asarray(cert.excursion, dtype=float)
        M = model.slices
        extent = float(np.max(rad)) + 2 * grid
        n = int(math.ceil(2 * extent / grid)) + 1
        self.x0 = np.full(M, -extent)
        self.y0 = np.full(M, -extent)
        grids = np.empty((M, n, n))
        for j in range(M):
            g = _grid_values(-extent, -extent, grid, n, n, cx[j], cy[j], rad[j], cap)
            # pulled in by excursion and chord error; nothing left: no clearance to certify
            v = g - (exc[j] + self.chord_error)
            grids[j] = np.where((g > 0) & (v > 0), v, _NEG)
        # float32 halves the cache footprint; rounded down by 10 nm so no value grows
        self.grids = np.where(grids > 0, grids - 1e-8, _NEG).astype(np.float32)
        reach = cert.reach if math.isfinite(cert.reach) else 1e3
        self.cells = slice_cells(model.z, cert.z_lo, cert.z_hi, reach)
        self.z_lo, self.z_hi = float(cert.z_lo), float(cert.z_hi)

    def clearances(self, T: np.ndarray, E: np.ndarray, r: float | np.ndarray,
                   need: float = 0.0) -> np.ndarray:
        """Certified clearance (m) of K rods of radius ``r`` (m, scalar or (K,)) on the
        axes ``T`` -> ``E`` (K, 3): a lower bound of each axis's distance to tissue minus
        ``r``, within ``tol`` of the sampled minimum where it nears ``need`` (m; coarser
        above). Positive: the rod is clear. ``inf``: the axis lies beyond the front.
        A value below ``need`` only says so: the search stops at the first sample that
        shows it (a colliding rod costs no more than a clear one)."""
        T = np.ascontiguousarray(np.asarray(T, dtype=float).reshape(-1, 3))
        E = np.ascontiguousarray(np.asarray(E, dtype=float).reshape(-1, 3))
        if T.shape != E.shape:
            raise PlanningError(f"rod starts and ends differ in shape: {T.shape}, {E.shape}")
        rr = np.ascontiguousarray(np.broadcast_to(np.asarray(r, dtype=float), (T.shape[0],)))
        return _rods(self.grids, self.x0, self.y0, self.h, self.cells, self.z_lo, self.z_hi,
                     self.cap, T, E, rr, float(need), self.tol)

    def clearance(self, T: np.ndarray, E: np.ndarray, r: float, need: float = 0.0) -> float:
        """:meth:`clearances` for one rod, without the batching."""
        t = np.asarray(T, dtype=float)
        e = np.asarray(E, dtype=float)
        return float(_rod(self.grids, self.x0, self.y0, self.h, self.cells, self.z_lo,
                          self.z_hi, self.cap, t[0], t[1], t[2], e[0], e[1], e[2],
                          float(r), float(need), self.tol))

    def ball(self, p: np.ndarray) -> float:
        """Certified distance (m, up to ``cap``) from point ``p`` (3,) to tissue."""
        return float(_ball(self.grids, self.x0, self.y0, self.h, self.cells, self.z_lo,
                           self.cap, float(p[0]), float(p[1]), float(p[2])))


def warm_up() -> None:
    """Load (or compile) the kernels now, on a tiny analytic model: a process that will
    run the rod alarm in its control loop calls this before the loop starts, so the first
    guided period does not stall on numba's cache."""
    rc = RodCheck(FPSM.cylinder(0.01, 0.0, 0.02, 3, 3), grid=1e-3)
    rc.clearances(np.zeros((1, 3)) + [0, 0, 0.005], np.zeros((1, 3)) + [0, 0, 0.015], 0.001)
    rc.clearance(np.array([0, 0, 0.005]), np.array([0, 0, 0.015]), 0.001)
