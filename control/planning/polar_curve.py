"""Closed polar curves of piecewise cubics: one slice of the surrogate model (seed 004, §3.1).

A slice boundary is ``rho(theta)``, ``0 <= theta < 2 pi``, made of ``N`` cubic segments
joined at the knots ``theta_k = 2 pi k / N``. The knot values ``p_k`` (the paper's control
points ``rho_{k+1}``, metres) are the only parameters: eq. 2 fixes each knot's derivative
to the central difference of its neighbours, ``(p_{k+1} - p_{k-1}) N / (4 pi)``, with the
index taken cyclically. That makes every segment a cubic Hermite piece whose end slopes are
known linear combinations of the ``p``, i.e. a closed Catmull-Rom spline in ``theta``; so
``rho(theta)`` is *linear* in ``p``: ``rho(theta) = B(theta) @ p`` with four non-zero
weights per row. The weights sum to one, so shrinking the curve by ``r`` (eq. 12) is
``p - r``.

The paper writes each segment in absolute ``theta`` (eq. 1) and finds its ``4 N``
coefficients from the linear system of eqs. 3-5; :func:`segment_coefficients` does exactly
that and the tests check it against the local Hermite form used everywhere else (the
absolute powers of ``theta`` up to ``(2 pi)^3`` make that system badly conditioned for
large ``N``, which is why the fast path avoids it). The area of eq. 6 is a quadratic form
``S = p^T G p / 2`` (:func:`area_matrix`); :func:`area_eq6` evaluates the paper's closed form
from the absolute coefficients, for the check.

Pure math: numpy arrays in, arrays out. Angles in radians, radii in metres (or any one
length unit: every function here is homogeneous in it).
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from oralnav.control.errors import PlanningError

TWO_PI = 2.0 * math.pi

#: Rows: the weights of ``p[k-1], p[k], p[k+1], p[k+2]`` on segment ``k``; columns: the
#: coefficients of ``1, t, t^2, t^3`` in the local parameter ``t = theta / h - k`` in
#: [0, 1), ``h = 2 pi / N``. Cubic Hermite with end slopes ``h v_k = (p[k+1] - p[k-1]) / 2``.
_WEIGHTS = np.array([
    [0.0, -0.5, 1.0, -0.5],
    [1.0, 0.0, -2.5, 1.5],
    [0.0, 0.5, 2.0, -1.5],
    [0.0, 0.0, -0.5, 0.5],
])


def check_points(n: int) -> int:
    """``n`` control points per curve, refused below 3 (no closed cubic spline)."""
    if int(n) != n or n < 3:
        raise PlanningError(f"a closed curve needs at least 3 control points, got {n}")
    return int(n)


def basis(theta: np.ndarray, n: int) -> np.ndarray:
    """The ``(len(theta), n)`` matrix ``B`` with ``rho(theta) = B @ p``.

    ``theta`` (rad) may be any real angles; they are wrapped into [0, 2 pi).
    """
    n = check_points(n)
    theta = np.mod(np.asarray(theta, dtype=float).ravel(), TWO_PI)
    u = theta * (n / TWO_PI)
    k = np.minimum(np.floor(u).astype(int), n - 1)
    t = u - k
    w = np.stack([np.ones_like(t), t, t * t, t * t * t], axis=1) @ _WEIGHTS.T  # (K, 4)
    out = np.zeros((theta.size, n))
    rows = np.arange(theta.size)
    for j, shift in enumerate((-1, 0, 1, 2)):
        np.add.at(out, (rows, (k + shift) % n), w[:, j])  # add: for n = 3 two taps coincide
    return out


def evaluate(p: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """``rho(theta)`` for control points ``p`` of shape (..., N); angles broadcast against
    the leading axes, e.g. ``p`` (M, N) with ``theta`` (M, K) gives (M, K).

    The per-point path for queries on many slices at once (collision detection): gathers
    the four taps of each angle's segment instead of building a dense basis.
    """
    p = np.asarray(p, dtype=float)
    n = p.shape[-1]
    theta = np.mod(np.asarray(theta, dtype=float), TWO_PI)
    u = theta * (n / TWO_PI)
    k = np.minimum(np.floor(u).astype(int), n - 1)
    t = u - k
    t2 = t * t
    t3 = t2 * t
    w = _WEIGHTS
    out = np.zeros(np.broadcast_shapes(p.shape[:-1], theta.shape))
    for j, shift in enumerate((-1, 0, 1, 2)):
        wj = w[j, 0] + w[j, 1] * t + w[j, 2] * t2 + w[j, 3] * t3
        out = out + wj * np.take_along_axis(p, (k + shift) % n, axis=-1)
    return out


@lru_cache(maxsize=64)
def _gram(n: int) -> np.ndarray:
    # W_ab = int_0^1 w_a(t) w_b(t) dt = C H C^T with the Hilbert matrix H_ij = 1/(i+j+1)
    H = 1.0 / (np.arange(4)[:, None] + np.arange(4)[None, :] + 1.0)
    W = _WEIGHTS @ H @ _WEIGHTS.T
    h = TWO_PI / n
    G = np.zeros((n, n))
    for k in range(n):
        idx = [(k + s) % n for s in (-1, 0, 1, 2)]
        for a in range(4):
            for b in range(4):
                G[idx[a], idx[b]] += h * W[a, b]
    G.setflags(write=False)
    return G


def area_matrix(n: int) -> np.ndarray:
    """Symmetric ``G`` (N, N) with the enclosed area ``S = p^T G p / 2`` (eq. 6) and its
    gradient ``dS/dp = G p``. Read-only and cached per ``n``."""
    return _gram(check_points(n))


def area(p: np.ndarray) -> np.ndarray:
    """Enclosed area of each curve (m^2 for p in m): ``p`` (..., N) -> (...)."""
    p = np.asarray(p, dtype=float)
    G = area_matrix(p.shape[-1])
    return 0.5 * np.einsum("...i,ij,...j->...", p, G, p)


def segment_coefficients(p: np.ndarray) -> np.ndarray:
    """The paper's coefficients ``(a_i, b_i, c_i, d_i)`` of eq. 1, in absolute ``theta``,
    found by solving ``M a = b`` (eqs. 3-5): value and slope at both ends of each segment.

    Returns (N, 4). The paper prints ``b_rho`` and ``b_v`` of eq. 4 with their indices
    garbled; the right-hand side here is what eq. 2 states (segment ``i`` runs from knot
    value ``p_i`` to ``p_{i+1}`` with the central-difference slopes).
    """
    p = np.asarray(p, dtype=float).ravel()
    n = check_points(p.size)
    h = TWO_PI / n
    v = (np.roll(p, -1) - np.roll(p, 1)) * n / (2.0 * TWO_PI)  # eq. 2: N (p+ - p-) / (4 pi)
    M = np.zeros((4 * n, 4 * n))
    rhs = np.zeros(4 * n)
    for i in range(n):
        for end, th in enumerate((i * h, (i + 1) * h)):
            r = 4 * i + end
            M[r, 4 * i:4 * i + 4] = (1.0, th, th * th, th ** 3)          # P_i, eq. 5
            M[r + 2, 4 * i:4 * i + 4] = (0.0, 1.0, 2.0 * th, 3.0 * th * th)  # Q_i
            rhs[r] = p[(i + end) % n]
            rhs[r + 2] = v[(i + end) % n]
    return np.linalg.solve(M, rhs).reshape(n, 4)


def area_eq6(coeffs: np.ndarray) -> float:
    """The area of eq. 6 in the paper's closed form, from :func:`segment_coefficients`."""
    coeffs = np.asarray(coeffs, dtype=float)
    n = coeffs.shape[0]
    total = 0.0
    for i, (a, b, c, d) in enumerate(coeffs):
        def prim(th: float, a=a, b=b, c=c, d=d) -> float:
            return (a * a * th + a * b * th ** 2 + (2 * a * c + b * b) / 3 * th ** 3
                    + (a * d + b * c) / 2 * th ** 4 + (2 * b * d + c * c) / 5 * th ** 5
                    + c * d / 3 * th ** 6 + d * d / 7 * th ** 7)
        total += prim(TWO_PI * (i + 1) / n) - prim(TWO_PI * i / n)
    return 0.5 * total
