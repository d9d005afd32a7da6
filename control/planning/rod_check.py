"""Certified rod clearance on a surrogate model (seed 004 §4.1, made conservative).

The paper's queries (eqs. 10-13, :mod:`oralnav.control.planning.placement`) read the clearance
along rays from the slice origin, only at the slices a line crosses, and interpolate
between slices. Against the exact mesh that calls rods safe that are not: the radial
clearance exceeds the Euclidean one beside an oblique wall, and a tooth between two
slices is seen by neither (``oralnav bench planning`` counts them). This module answers
the same question with a lower bound that holds for the mesh itself, provided the model
carries a :class:`~oralnav.control.planning.fpsm.Certificate` (curves fitted to slab envelopes):

- **In the plane**: a grid per slice of the Euclidean distance from each node to the
  curve (exact to the curve's dense polygon, capped at ``cap``), minus the slice's
  excursion and the polygon's chord error. At a point, the best of the four surrounding
  nodes' ``value - |node - point|`` is a lower bound (the distance is 1-Lipschitz).
- **Across slices**: slice ``j``'s curve is clear over its whole cell, so a ball of
  radius ``R`` about ``p`` is clear wherever, for every cell ``j`` it reaches (``dz_j`` away
  in z), ``c_j(p)^2 + dz_j^2 >= R^2``; behind the model's back end lies tissue, beyond
  the last cell nothing is known. The largest such ``R`` (the *slab bound*, up to
  ``cap``) is a lower bound of ``d(p)``, the distance from ``p`` to all that may be tissue.
- **Fast grid**: ``d`` is 1-Lipschitz, so any node ``n`` gives ``d(p) >= B(n) - |p - n|``
  for its slab bound ``B(n)``. :class:`RodCheck` stores ``B`` on a 3-D grid (the distance
  grids' nodes in x, y, ``FAST_DZ`` apart in z from ``z_lo`` to ``z_hi``; rounded down to
  ``cap / 255`` steps, one byte a node): the nearest node bounds ``d`` anywhere with one
  read and a square root (off the grid too, only more loosely). It never exceeds the slab
  bound at ``p`` itself: the nearest node is one of the four whose values that reads,
  and ``sqrt(c^2 + dz^2)`` drops by at most ``|p - n|`` when ``c`` drops by the distance
  across and ``dz`` by the distance along z.
- **Along the axis**: sphere tracing. From a sample with ball radius ``R`` the next
  sample is ``R - r - need`` further (at least ``tol``), and between two samples ``l``
  apart the distance is at least ``(R_a + R_b - l) / 2`` (for any lower bounds ``R_a``,
  ``R_b`` of ``d``); the rod's bound is the least of these, minus ``r``. A sample takes
  the fast grid's bound alone where that clears ``r + need`` by more than ``2 tol`` and
  would not lower the rod's bound; elsewhere it takes the slab bound (a rod's first
  sample, and one after a sample that lowered the bound, go straight to it: they all but
  always need it). So the decision at
  ``need`` is made on the slab bound, sampled as finely near the threshold as without
  the fast grid, and so is every sample that sets the bound: the value is as tight as
  the slab bound makes it, and only the samples where the clearance grows again (off a
  wall, out of a narrow) cost a single read. The result is a certified lower bound of
  the rod's clearance (axis distance to tissue minus ``r``).

The axis is checked from its start to where it leaves the model's front (``z_hi``):
beyond it, outside the mouth, the model knows nothing and checks nothing, as eq. 13
does. Compiled with numba: the grids are built once per model. A batched query traces
:data:`LANES` rods at once, one sample of each in turn (their samples do not depend on
one another, so the CPU overlaps their memory reads), in one kernel that hands no array
to a helper (numba's reference counting of array arguments costs more than a sample);
it takes a fraction of a microsecond per rod (``oralnav bench planning`` measures it
against python-fcl on the mesh).

Pure math, no I/O. Lengths in metres, Center frame.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from oralnav.control.errors import PlanningError
from oralnav.control.planning import polar_curve as pc
from oralnav.control.planning.fpsm import FPSM, slice_cells

TWO_PI = 2.0 * math.pi

#: Grid spacing of the distance grids (m) and the cap of the stored distances (m).
GRID = 5e-4
CAP = 0.012
#: Vertices of the dense polygon the grids measure to (0.25 deg apart).
VERTICES = 1440
#: Smallest sphere-tracing step (m): the bound is this close to the sampled minimum.
TOL = 1e-4
#: Node spacing of the fast grid along z (m); across, it is ``grid``. 0.5 or 2 mm changed
#: the batched query by under 5 % (most samples that matter compute the slab bound).
FAST_DZ = 1e-3
#: Rods traced at once by a batched query: 1, 2, 4, 8 lanes took 270, 170, 155, 150 ns a
#: rod (r = 2 mm rods in the example mouth, this 2-core machine).
LANES = 4

_NEG = -1.0   # stored for grid nodes outside the curve: "tissue" (any negative works)
_LEVELS = 255  # fast-grid steps: a node stores floor(B / (cap / 255)), uint8

# Layout of the float64 parameter vector the kernels read (RodCheck._meta): scalars,
# then the M cells' (start, end) and the cell-lookup table.
(_X0, _Y0, _H, _IH, _NX, _NY, _ZLO, _ZHI, _CAP, _TOL, _BAND, _M, _FZ0, _FHZ, _FIHZ,
 _FNZ, _FQ, _IJQ, _NJ) = range(19)
_HEAD = 19
# Lane state of _trace: axis start and direction, the current and next sample (m along
# the axis), the end, ball radius at the current sample, running bound, radius, fast-path
# floor, mode (2: the next sample is the rod's first, 1: the last sample lowered the
# bound, 0: it did not), rod index (-1: free lane).
(_TX, _TY, _TZ, _UX, _UY, _UZ, _S, _S2, _B, _R, _LOW, _RAD, _FLOOR, _MODE,
 _ROD) = range(15)


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


@numba.njit(cache=True, nogil=True)
def _fast_grid(grids: np.ndarray, cells: np.ndarray, z_lo: float, cap: float, z0: float,
               dz: float, nz: int, q: float) -> np.ndarray:
    """The fast grid (nz, ny, nx), uint8: at each distance-grid node and ``z0 + k dz`` (m),
    the slab bound (m) in steps of ``q`` (m), rounded down; 0 at or behind the back end."""
    M, ny, nx = grids.shape
    z_end = cells[M - 1, 1]
    out = np.zeros((nz, ny, nx), dtype=np.uint8)
    dzk = np.empty(M)
    for kz in range(nz):
        z = z0 + kz * dz
        if not (z > z_lo and z < z_end):
            continue
        b0 = min(cap, z - z_lo, z_end - z)
        for k in range(M):
            dzk[k] = max(cells[k, 0] - z, z - cells[k, 1], 0.0)
        for iy in range(ny):
            for ix in range(nx):
                best = b0
                for k in range(M):
                    if dzk[k] < b0:        # cells farther than b0 cannot lower the bound
                        # at the node the in-plane bound is the node's own value
                        c = max(float(grids[k, iy, ix]), 0.0)
                        best = min(best, math.sqrt(c * c + dzk[k] * dzk[k]))
                level = min(int(best / q), _LEVELS)
                if level * q > best:       # the division rounded up: one step down
                    level -= 1
                out[kz, iy, ix] = level
    return out


# inlined where called from compiled code (_rod): numba counts the references of a
# call's array arguments, which costs more than the query of one rod
@numba.njit(cache=True, nogil=True, inline="always")
def _trace(grids: np.ndarray, fast: np.ndarray, meta: np.ndarray, T: np.ndarray,
           E: np.ndarray, radii: np.ndarray, r0: float, need: float) -> np.ndarray:
    """Certified clearances (m, (K,)) of the rods on the axes ``T`` -> ``E`` (K, 3), m, of
    radii ``radii`` (K,) or, when that is empty, ``r0`` (m); ``inf`` for an axis wholly
    beyond the front, NaN for a non-finite one. Each rod is traced up to the front
    ``z_hi``; sampling is fine only where the clearance nears ``need`` (module doc).
    :data:`LANES` rods are traced at once, one sample each in turn, so that their memory
    reads overlap. TypeError (the caller converts and retries) unless T and E are both
    (K, 3) and ``radii`` is empty or (K,)."""
    if (T.shape[1] != 3 or E.shape[0] != T.shape[0] or E.shape[1] != 3
            or radii.shape[0] not in (0, T.shape[0])):
        raise TypeError("rod starts and ends must both be (K, 3), radii (K,) or none")
    x0, y0, h, ih = meta[_X0], meta[_Y0], meta[_H], meta[_IH]
    nx, ny, M = int(meta[_NX]), int(meta[_NY]), int(meta[_M])
    z_lo, z_hi, cap, tol, band = meta[_ZLO], meta[_ZHI], meta[_CAP], meta[_TOL], meta[_BAND]
    fz0, fhz, fihz, fnz, fq = meta[_FZ0], meta[_FHZ], meta[_FIHZ], int(meta[_FNZ]), meta[_FQ]
    ijq, nj = meta[_IJQ], int(meta[_NJ])
    CB = _HEAD                  # cell k spans meta[CB + 2k] .. meta[CB + 2k + 1]
    JT = _HEAD + 2 * M          # first cell that can hold z in each lookup bin
    z_end = meta[CB + 2 * M - 1]
    xm, ym, zm = nx - 1.0, ny - 1.0, fnz - 1.0
    K = T.shape[0]
    out = np.empty(K)
    per_rod = radii.shape[0] > 0
    W = min(LANES, K)
    st = np.empty((max(W, 1), 15))
    for w in range(W):
        st[w, _ROD] = -1.0
    nxt = 0
    live = 0
    while True:
        for w in range(W):                 # give each free lane the next rod
            while st[w, _ROD] < 0.0 and nxt < K:
                i = nxt
                nxt += 1
                r = radii[i] if per_rod else r0
                tx, ty, tz = T[i, 0], T[i, 1], T[i, 2]
                vx, vy, vz = E[i, 0] - tx, E[i, 1] - ty, E[i, 2] - tz
                L = math.sqrt(vx * vx + vy * vy + vz * vz)
                chk = tx + ty + tz + L + r
                if chk - chk != 0.0:       # a NaN or infinite input (or length): no answer
                    out[i] = math.nan
                    continue
                ux = uy = uz = 0.0
                if L > 0.0:
                    ux, uy, uz = vx / L, vy / L, vz / L
                # the axis part at or below the front plane
                a, b = 0.0, L
                if uz > 0.0:
                    b = min(L, (z_hi - tz) / uz)
                elif uz < 0.0:
                    a = max(0.0, (z_hi - tz) / uz)
                elif tz > z_hi:
                    out[i] = math.inf
                    continue
                if b < a:
                    out[i] = math.inf
                    continue
                st[w, _TX], st[w, _TY], st[w, _TZ] = tx, ty, tz
                st[w, _UX], st[w, _UY], st[w, _UZ] = ux, uy, uz
                st[w, _S], st[w, _S2], st[w, _B] = a, a, b
                st[w, _R], st[w, _LOW], st[w, _RAD] = 0.0, math.inf, r
                st[w, _FLOOR], st[w, _MODE], st[w, _ROD] = r + need + band, 2.0, i
                live += 1
        if live == 0:
            break
        for w in range(W):
            if st[w, _ROD] < 0.0:
                continue
            s, s2, b, r = st[w, _S], st[w, _S2], st[w, _B], st[w, _RAD]
            x = st[w, _TX] + s2 * st[w, _UX]
            y = st[w, _TY] + s2 * st[w, _UY]
            z = st[w, _TZ] + s2 * st[w, _UZ]
            # the fast bound from the nearest node (clamped: the bound holds from any
            # node); not read on a rod's first sample or after a sample that lowered the
            # rod's bound, where the slab bound is all but sure to be needed
            R2 = -1.0
            if st[w, _MODE] == 0.0:
                px, py, pz = (x - x0) * ih, (y - y0) * ih, (z - fz0) * fihz
                px = min(px, xm) if px > 0.0 else 0.0
                py = min(py, ym) if py > 0.0 else 0.0
                pz = min(pz, zm) if pz > 0.0 else 0.0
                kx, ky, kz = int(px + 0.5), int(py + 0.5), int(pz + 0.5)
                dx, dy, dz = (px - kx) * h, (py - ky) * h, (pz - kz) * fhz
                R2 = fast[kz, ky, kx] * fq - math.sqrt(dx * dx + dy * dy + dz * dz)
            # the slab bound (never below the fast one) near the threshold, or where
            # this sample lowers the rod's bound (its value)
            if (st[w, _MODE] != 0.0 or R2 < st[w, _FLOOR]
                    or min(R2, 0.5 * (st[w, _R] + R2 - (s2 - s))) < st[w, _LOW]):
                best = 0.0                 # at or behind the back end, or past the cells
                if z > z_lo and z < z_end:
                    best = min(cap, z - z_lo, z_end - z)
                    j = int(meta[JT + min(int((z - z_lo) * ijq), nj - 1)])
                    while z > meta[CB + 2 * j + 1] and j < M - 1:
                        j += 1
                    px, py = (x - x0) * ih, (y - y0) * ih
                    ix, iy = int(math.floor(px)), int(math.floor(py))
                    if ix < 0 or iy < 0 or ix + 1 >= nx or iy + 1 >= ny:
                        # off the grids: tissue in every plane, from the point's own cell
                        best = min(best, max(meta[CB + 2 * j] - z, 0.0))
                    else:
                        # the four nodes' value - |node - point|, the same in every slice
                        ax, ay = px - ix, py - iy
                        bx, by = 1.0 - ax, 1.0 - ay
                        d00 = h * math.sqrt(ax * ax + ay * ay)
                        d01 = h * math.sqrt(bx * bx + ay * ay)
                        d10 = h * math.sqrt(ax * ax + by * by)
                        d11 = h * math.sqrt(bx * bx + by * by)
                        # cells j, j - 1, ... down, then j + 1, ... up, each run until a
                        # cell is farther than the best ball; a node outside the curve
                        # (< 0) leaves c = 0: the ball reaches tissue dz away
                        k = j
                        while k >= 0:
                            dz = max(meta[CB + 2 * k] - z, z - meta[CB + 2 * k + 1], 0.0)
                            if dz >= best:
                                break
                            c = max(0.0, grids[k, iy, ix] - d00, grids[k, iy, ix + 1] - d01,
                                    grids[k, iy + 1, ix] - d10,
                                    grids[k, iy + 1, ix + 1] - d11)
                            best = min(best, math.sqrt(c * c + dz * dz))
                            k -= 1
                        k = j + 1
                        while k < M:
                            dz = max(meta[CB + 2 * k] - z, z - meta[CB + 2 * k + 1], 0.0)
                            if dz >= best:
                                break
                            c = max(0.0, grids[k, iy, ix] - d00, grids[k, iy, ix + 1] - d01,
                                    grids[k, iy + 1, ix] - d10,
                                    grids[k, iy + 1, ix + 1] - d11)
                            best = min(best, math.sqrt(c * c + dz * dz))
                            k += 1
                R2 = best
            low = st[w, _LOW]
            if st[w, _MODE] == 2.0:
                low = R2
                st[w, _MODE] = 1.0
            else:
                lower = min(low, 0.5 * (st[w, _R] + R2 - (s2 - s)), R2)
                st[w, _MODE] = 1.0 if lower < low else 0.0
                low = lower
                s = s2
            # below need: not certified, and the rest of the axis cannot raise the bound
            if low - r < need or not s < b:
                out[int(st[w, _ROD])] = low - r
                st[w, _ROD] = -1.0
                live -= 1
                continue
            step = R2 - r - need
            if not step > tol:
                step = tol
            st[w, _S], st[w, _R], st[w, _LOW] = s, R2, low
            st[w, _S2] = min(s + step, b)
    return out


_NO_RADII = np.empty(0)


@numba.njit(cache=True, nogil=True)
def _rod(grids: np.ndarray, fast: np.ndarray, meta: np.ndarray, T: np.ndarray,
         E: np.ndarray, r: float, need: float) -> float:
    """:func:`_trace` for one rod: T and E (3,) (m), radius ``r`` (m)."""
    if T.shape[0] != 3 or E.shape[0] != 3:
        raise TypeError("a rod end must be (3,)")
    return _trace(grids, fast, meta, T.reshape((1, 3)), E.reshape((1, 3)), meta[:0], r,
                  need)[0]


# The signatures the query kernels take; other argument types (a list, another dtype, a
# strided or read-only view) are refused at once with TypeError (RodCheck then converts
# and retries) rather than compiled mid-period in the control loop.
_SIGNATURES = (
    (_trace, "float64[::1](float32[:, :, ::1], uint8[:, :, ::1], float64[::1], "
             "float64[:, ::1], float64[:, ::1], float64[::1], float64, float64)"),
    (_rod, "float64(float32[:, :, ::1], uint8[:, :, ::1], float64[::1], float64[::1], "
           "float64[::1], float64, float64)"))


def _load_kernels() -> None:
    """Compile (or load from numba's cache) the query kernels for their one signature
    each, and refuse other types from then on (once per process)."""
    for kernel, signature in _SIGNATURES:
        if not kernel.signatures:
            kernel.compile(signature)
            kernel.disable_compile()


def _point(v: object) -> np.ndarray:
    """The first three values (m) of ``v`` as a new float64 (3,) array."""
    a = np.array(v, dtype=float).reshape(-1)
    if a.size < 3:
        raise PlanningError(f"a point needs 3 coordinates (m), got {a.size}")
    return np.ascontiguousarray(a[:3])


class RodCheck:
    """Certified rod and point clearances on one certified model (see the module doc).

    Building computes one distance grid per slice (``grid`` m apart, distances capped at
    ``cap`` m, float32) and the fast grid from them (one byte a node: 1.2 MB for the
    example mouth): a few hundred milliseconds, once per model. Queries are compiled;
    the first check built in a process loads them.
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
        # every slice's grid has the same nodes: x, y = -extent + i grid
        self.x0 = self.y0 = -extent
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
        # the fast grid: z from the back end to the front, where the traces stop
        nz = int(math.ceil((self.z_hi - self.z_lo) / FAST_DZ)) + 1
        q = self.cap / _LEVELS
        self.fast = _fast_grid(self.grids, self.cells, self.z_lo, self.cap, self.z_lo,
                               FAST_DZ, nz, q)
        # the slab bound is computed where the fast one clears r + need by less than this
        # (m): more than tol, so that a sample passed on the fast bound alone steps on by
        # more than tol and its gap bound, (R_next + r + need) / 2, does not depend on it
        self.band = 2.0 * self.tol
        # cell lookup: bins of half the narrowest cell up to the last cell's start, each
        # holding the first cell that ends at or after the bin's start (at most 4096)
        span = max(float(self.cells[-1, 0]) - self.z_lo, 0.0)
        width = float(np.min(self.cells[:, 1] - self.cells[:, 0]))
        jq = max(width / 2.0, span / 4096.0, 1e-9)
        nj = int(span / jq) + 2
        table = np.searchsorted(self.cells[:, 1], self.z_lo + np.arange(nj) * jq, "left")
        head = np.zeros(_HEAD)
        head[[_X0, _Y0, _H, _IH, _NX, _NY, _ZLO, _ZHI, _CAP, _TOL, _BAND, _M, _FZ0, _FHZ,
              _FIHZ, _FNZ, _FQ, _IJQ, _NJ]] = (
            self.x0, self.y0, self.h, 1.0 / self.h, n, n, self.z_lo, self.z_hi, self.cap,
            self.tol, self.band, M, self.z_lo, FAST_DZ, 1.0 / FAST_DZ, nz, q, 1.0 / jq, nj)
        self._meta = np.concatenate([head, self.cells.ravel(),
                                     np.minimum(table, M - 1).astype(float)])
        _load_kernels()

    def __setstate__(self, state: dict) -> None:
        # unpickled (a guided plan reaching the control process): the kernels refuse
        # other argument types there too
        self.__dict__.update(state)
        _load_kernels()

    def clearances(self, T: np.ndarray, E: np.ndarray, r: float | np.ndarray,
                   need: float = 0.0) -> np.ndarray:
        """Certified clearance (m) of K rods of radius ``r`` (m, scalar or (K,)) on the
        axes ``T`` -> ``E`` (K, 3): a lower bound of each axis's distance to tissue minus
        ``r``, within ``tol`` of the sampled minimum where it nears ``need`` (m; coarser
        above). Positive: the rod is clear. ``inf``: the axis lies beyond the front.
        A value below ``need`` only says so: the search stops at the first sample that
        shows it (a colliding rod costs no more than a clear one). NaN for a rod with a
        non-finite coordinate or radius."""
        try:    # float64 (K, 3) arrays go straight in (the planner's batches)
            if type(r) is np.ndarray:
                return _trace(self.grids, self.fast, self._meta, T, E, r, 0.0, need)
            return _trace(self.grids, self.fast, self._meta, T, E, _NO_RADII, r, need)
        except TypeError:
            pass
        # anything else: new float64 (K, 3) arrays (C-ordered and writable, as typed)
        T = np.array(T, dtype=float, order="C").reshape(-1, 3)
        E = np.array(E, dtype=float, order="C").reshape(-1, 3)
        if T.shape != E.shape:
            raise PlanningError(f"rod starts and ends differ in shape: {T.shape}, {E.shape}")
        ra = np.asarray(r, dtype=float)
        if ra.ndim == 0:
            return _trace(self.grids, self.fast, self._meta, T, E, _NO_RADII, float(ra),
                          float(need))
        radii = np.array(np.broadcast_to(ra, (T.shape[0],)))     # a writable copy
        return _trace(self.grids, self.fast, self._meta, T, E, radii, 0.0, float(need))

    def clearance(self, T: np.ndarray, E: np.ndarray, r: float, need: float = 0.0) -> float:
        """:meth:`clearances` for one rod (T, E: (3,), m), without the batching."""
        try:    # float64 (3,) arrays go straight in (a call per control period)
            return _rod(self.grids, self.fast, self._meta, T, E, r, need)
        except TypeError:
            return _rod(self.grids, self.fast, self._meta, _point(T), _point(E), float(r),
                        float(need))

    def ball(self, p: np.ndarray) -> float:
        """Certified distance (m, up to ``cap``) from point ``p`` (3,) to tissue: the slab
        bound at ``p`` (module doc)."""
        q = _point(p)
        # a rod of length 0 and radius 0 asked for an infinite clearance: its one sample,
        # a first one, takes the slab bound; with no front, a point past it is answered
        meta = self._meta.copy()
        meta[_ZHI] = math.inf
        return _rod(self.grids, self.fast, meta, q, q, 0.0, math.inf)


def warm_up() -> None:
    """Load (or compile) the kernels now, on a tiny analytic model: a process that will
    run the rod alarm in its control loop calls this before the loop starts, so the first
    guided period does not stall on numba's cache."""
    rc = RodCheck(FPSM.cylinder(0.01, 0.0, 0.02, 3, 3), grid=1e-3)
    rc.clearances(np.zeros((1, 3)) + [0, 0, 0.005], np.zeros((1, 3)) + [0, 0, 0.015], 0.001)
    rc.clearance(np.array([0, 0, 0.005]), np.array([0, 0, 0.015]), 0.001)
