"""Evaluation metrics of the navigation seed (section IV): jitter, TRE, AAE and pose errors.

Pure functions, no I/O. Inputs are SI (metres, 4x4 poses ``T_a_b``) unless a name carries
another unit (``*_deg``); results are reported in millimetres and degrees, as the seed's
tables are, and the unit is in every field name.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from oralnav.checks import finite_array
from oralnav.control.errors import ControlError
from oralnav.control.geometry import as_transform

_MM_PER_M = 1000.0

# The metrics' wording for a sample with NaN or infinite values (tests match on it).
_NON_FINITE = "{what}: has non-finite values"


class MetricsError(ControlError, ValueError):
    """Input to a metric is malformed (wrong shape, too few samples, non-finite values)."""


def _pose_stack(poses: np.ndarray | Sequence[np.ndarray], what: str) -> np.ndarray:
    """Validate a stack (N, 4, 4) of rigid poses, N >= 1; each one through ``as_transform``."""
    T = np.asarray(poses, dtype=float)
    if T.ndim != 3 or T.shape[1:] != (4, 4) or len(T) == 0:
        raise MetricsError(f"{what}: expected a stack of poses (N, 4, 4) with N >= 1, "
                           f"got shape {T.shape}")
    for i, Ti in enumerate(T):
        as_transform(Ti, what=f"{what}[{i}]")
    return T


def _mad(x: np.ndarray, axis: int = 0) -> np.ndarray:
    """Median absolute deviation from the median (eq. 20), unscaled, along ``axis``."""
    return np.median(np.abs(x - np.median(x, axis=axis, keepdims=True)), axis=axis)


def _geometric_median(x: np.ndarray, *, tol: float = 1e-14, max_iter: int = 200) -> np.ndarray:
    """Point minimising the summed Euclidean distance to the rows of ``x`` (N, d); Weiszfeld.

    The multivariate median that, unlike the coordinate-wise one, does not depend on the
    axes the vectors are written in; in 1-D it is the ordinary median (for odd N).
    """
    y = x.mean(axis=0)
    for _ in range(max_iter):
        d = np.linalg.norm(x - y, axis=1)
        # Clamp: an iterate on a sample would divide by zero; the sample then dominates the
        # weights, which is right because it is (within tol) the minimiser.
        w = 1.0 / np.maximum(d, tol)
        y_next = w @ x / w.sum()
        if np.linalg.norm(y_next - y) <= tol:
            return y_next
        y = y_next
    return y


@dataclass(frozen=True, eq=False)
class JitterStats:
    """Jitter of a stationary pose stream (eq. 20), as in the seed's Table I.

    ``std_mm``/``mad_mm`` (3,): per-axis X, Y, Z of the translation, millimetres, in the frame
    the poses are given in. ``std_deg``/``mad_deg``: rotation, degrees (see
    :func:`jitter_stats`). ``n``: number of poses.
    """

    std_mm: np.ndarray
    mad_mm: np.ndarray
    std_deg: float
    mad_deg: float
    n: int

    def as_dict(self) -> dict[str, Any]:
        """Plain JSON-ready dict (lists and floats)."""
        return {"n": self.n,
                "std_mm": [float(v) for v in self.std_mm],
                "mad_mm": [float(v) for v in self.mad_mm],
                "std_deg": float(self.std_deg),
                "mad_deg": float(self.mad_deg)}


def jitter_stats(poses: np.ndarray | Sequence[np.ndarray]) -> JitterStats:
    """Eq. 20 jitter (STD with n - 1, MAD from the median) of N >= 2 poses (N, 4, 4), metres.

    Translation: per axis, eq. 20 as printed. Rotation: eq. 20 says x is the rotation vector
    but Table I reports one figure, so the vector is reduced to a scalar without changing
    the formula's meaning. Each pose's rotation vector is taken relative to the mean
    rotation (``Rotation.mean``), ``v_i = log(R_mean^T R_i)``, which keeps it away from the
    +-pi wrap and makes the result independent of the absolute orientation; then

    - ``std_deg = sqrt(sum_i |v_i - mean(v)|^2 / (n - 1))``: eq. 20 with the square read as
      the squared norm (the root of the covariance trace);
    - ``mad_deg = median_i |v_i - med(v)|`` with ``med`` the geometric median (Weiszfeld).

    Both reduce exactly to eq. 20 when the rotation jitters about one axis. The tempting
    alternative, STD/MAD of the angles ``|v_i|``, is rejected: angles are non-negative, so
    a jitter of constant size in changing directions would score zero.
    """
    T = _pose_stack(poses, "poses")
    n = len(T)
    if n < 2:
        raise MetricsError(f"poses: jitter needs at least 2 poses, got {n}")
    t_mm = T[:, :3, 3] * _MM_PER_M
    std_mm = np.std(t_mm, axis=0, ddof=1)
    mad_mm = _mad(t_mm)

    R = Rotation.from_matrix(T[:, :3, :3])
    v = (R.mean().inv() * R).as_rotvec()
    std_rad = np.sqrt(np.sum((v - v.mean(axis=0)) ** 2) / (n - 1))
    mad_rad = np.median(np.linalg.norm(v - _geometric_median(v), axis=1))
    std_mm.setflags(write=False)
    mad_mm.setflags(write=False)
    return JitterStats(std_mm=std_mm, mad_mm=mad_mm, std_deg=float(np.degrees(std_rad)),
                       mad_deg=float(np.degrees(mad_rad)), n=n)


def tre(p_registered: np.ndarray, p_measured: np.ndarray) -> float:
    """Eq. 21 target registration error: RMS distance between paired points, input units.

    ``p_registered`` (N, 3): targets registered with the instrument (``p^c``);
    ``p_measured`` (N, 3): the same targets as the navigation system reports them (``p^t``).
    """
    a = finite_array(p_registered, "p_registered", MetricsError, non_finite=_NON_FINITE)
    b = finite_array(p_measured, "p_measured", MetricsError, non_finite=_NON_FINITE)
    for what, p in (("p_registered", a), ("p_measured", b)):
        if p.ndim != 2 or p.shape[1] != 3:
            raise MetricsError(f"{what}: expected points of shape (N, 3), got {p.shape}")
    if a.shape != b.shape:
        raise MetricsError(f"p_registered and p_measured must pair up: shapes {a.shape} "
                           f"and {b.shape}")
    if len(a) == 0:
        raise MetricsError("tre: needs at least one point pair, got 0")
    return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=1))))


def absolute_angular_error(measured_deg: np.ndarray | float,
                           truth_deg: np.ndarray | float) -> np.ndarray:
    """Section IV.D absolute angular error ``|measured - truth|`` in degrees, in [0, 180].

    Elementwise with numpy broadcasting (e.g. N frames against one gadget angle). The
    difference is wrapped to [-180, 180) first; the seed does not say so, but a yaw of 179
    measured as -179 is 2 degrees off, not 358.
    """
    m = finite_array(measured_deg, "measured_deg", MetricsError, non_finite=_NON_FINITE)
    t = finite_array(truth_deg, "truth_deg", MetricsError, non_finite=_NON_FINITE)
    try:
        d = m - t
    except ValueError as exc:
        raise MetricsError(f"measured_deg {m.shape} and truth_deg {t.shape} do not "
                           f"broadcast together") from exc
    return np.abs((d + 180.0) % 360.0 - 180.0)


def pose_errors(T_est: np.ndarray, T_true: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-pose translation error (N,) in mm and rotation error (N,) in degrees.

    ``T_est``, ``T_true``: stacks (N, 4, 4) of the same child frame in the same parent frame
    (m). Same definitions as ``geometry.pose_error`` (origin distance; angle of
    ``R_true^T R_est``), vectorised over the stack for benchmarks.
    """
    A = _pose_stack(T_est, "T_est")
    B = _pose_stack(T_true, "T_true")
    if A.shape != B.shape:
        raise MetricsError(f"T_est and T_true must pair up: shapes {A.shape} and {B.shape}")
    trans_mm = np.linalg.norm(A[:, :3, 3] - B[:, :3, 3], axis=1) * _MM_PER_M
    R_rel = np.swapaxes(B[:, :3, :3], 1, 2) @ A[:, :3, :3]
    rot_deg = np.degrees(Rotation.from_matrix(R_rel).magnitude())
    return trans_mm, rot_deg


def error_summary(trans_mm: np.ndarray, rot_deg: np.ndarray) -> dict[str, Any]:
    """Median, mean, 95th percentile and max of paired errors (N,), as a JSON-ready dict.

    ``{"n": N, "translation_mm": {"median", "mean", "p95", "max"}, "rotation_deg": {...}}``;
    the percentile interpolates linearly (numpy's default).
    """
    a = finite_array(trans_mm, "trans_mm", MetricsError, non_finite=_NON_FINITE)
    b = finite_array(rot_deg, "rot_deg", MetricsError, non_finite=_NON_FINITE)
    if a.ndim != 1 or a.shape != b.shape or len(a) == 0:
        raise MetricsError(f"trans_mm and rot_deg must be 1-D, equally long and non-empty: "
                           f"shapes {a.shape} and {b.shape}")

    def stats(x: np.ndarray) -> dict[str, float]:
        return {"median": float(np.median(x)), "mean": float(np.mean(x)),
                "p95": float(np.percentile(x, 95)), "max": float(np.max(x))}

    return {"n": len(a), "translation_mm": stats(a), "rotation_deg": stats(b)}
