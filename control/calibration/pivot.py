"""Pivot calibration of a tracked pointer (the navigation seed's reference [28]; eq. 3).

A tracked tool is pivoted about a fixed point while the tracker reports its poses
``T_W_tool[i]`` (tracker/world frame ``W``). The tip offset ``p_tool`` (tool frame) and the
pivot point ``p_W`` (world frame) satisfy, for every pose,

    R_i p_tool + t_i = p_W.

Three solvers, all pure functions (no I/O), lengths in whatever unit the matrices use:

- ``algebraic``: the one-step linear least squares on the stacked system
  ``[R_i  -I] [p_tool; p_W] = -t_i`` (Yaniv's "algebraic one step").
- ``sphere``: the tool origins ``t_i`` lie on a sphere about ``p_W`` of radius
  ``|p_tool|``; fit that sphere (linear, then geometric refinement), then recover
  ``p_tool`` as the mean of ``R_i^T (p_W - t_i)``.
- ``ransac``: the algebraic solver on random 4-pose subsets; the largest consensus set
  (per-pose error below a threshold) is refitted with the algebraic solver. The defaults
  (10 subsets, 4 length units, consensus of at least a quarter of the poses) are the
  parameters scikit-surgery's own test passes (``pivot_calibration_with_ransac(m, 10, 4,
  0.25)``: iterations, error threshold, consensus fraction), so they suit millimetres.

Residuals: ``e_i = R_i p_tool + t_i - p_W`` (3,). ``rms`` is the 3D RMS ``sqrt(mean |e_i|^2)``;
``rms_per_component`` is ``sqrt(sum e_ij^2 / (3 n))`` (the scikit-surgery definition, so
``rms = sqrt(3) * rms_per_component``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from oralnav.control.errors import CalibrationError
from oralnav.control.geometry import ROTATION_TOL

__all__ = ["PivotError", "PivotResult", "pivot_calibration", "pivot_residuals",
           "validate_tracking_matrices", "METHODS"]

METHODS = ("algebraic", "sphere", "ransac")

#: Relative singular-value floor below which the pivot system counts as rank deficient.
_RANK_RTOL = 1e-9
#: Tool orientations must span at least this many degrees for a determined tip: the tip
#: offset is unobservable along any axis the tool never turns about.
MIN_ROTATION_SPREAD_DEG = 5.0


class PivotError(CalibrationError):
    """Pivot calibration refused: malformed matrices or a degenerate (rank-deficient) set."""


@dataclass(frozen=True)
class PivotResult:
    """A pivot calibration.

    Attributes:
        tip_offset: (3,) the tip in the tool frame (input units).
        pivot_point: (3,) the pivot in the tracker/world frame (input units).
        rms: 3D RMS of the residuals over the poses used.
        rms_per_component: ``rms / sqrt(3)``: the per-coordinate RMS.
        residuals: (N,) per-pose residual norms ``|R_i p_tool + t_i - p_W|`` over all poses.
        method: the solver used.
        inliers: (N,) bool, the poses the final fit used (all True but for RANSAC).
        condition: condition number of the algebraic system (large: poorly spread poses).
        rotation_spread_deg: largest angle between any tool orientation and their mean.
    """

    tip_offset: np.ndarray
    pivot_point: np.ndarray
    rms: float
    rms_per_component: float
    residuals: np.ndarray
    method: str
    inliers: np.ndarray
    condition: float
    rotation_spread_deg: float
    details: dict = field(default_factory=dict)

    @property
    def n_poses(self) -> int:
        return int(len(self.residuals))

    @property
    def n_inliers(self) -> int:
        return int(np.count_nonzero(self.inliers))


def validate_tracking_matrices(T: np.ndarray, what: str = "tracking matrices",
                               *, min_poses: int = 2) -> np.ndarray:
    """Return ``T`` as a float (N, 4, 4) stack of rigid transforms or raise :class:`PivotError`.

    The message names the first bad matrix (index) and what is wrong with it.
    """
    T = np.asarray(T, dtype=float)
    if T.ndim == 2 and T.shape == (4, 4):
        T = T[None]
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise PivotError(f"{what}: expected stacked 4x4 matrices (N, 4, 4), got shape {T.shape}")
    bad = ~np.all(np.isfinite(T), axis=(1, 2))
    if np.any(bad):
        raise PivotError(f"{what}: matrix {int(np.argmax(bad))} has non-finite entries")
    bottom = np.abs(T[:, 3] - np.array([0.0, 0.0, 0.0, 1.0])).max(axis=1)
    if np.any(bottom > 1e-9):
        i = int(np.argmax(bottom))
        raise PivotError(f"{what}: matrix {i} is not homogeneous (last row {T[i, 3].tolist()}, "
                         "expected [0, 0, 0, 1])")
    R = T[:, :3, :3]
    ortho = np.abs(R @ np.swapaxes(R, 1, 2) - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(R)
    # Tracker output is stored to ~10 significant digits (the peer data uses 10 decimals);
    # a looser tolerance than the in-memory one avoids refusing honest files.
    tol = max(ROTATION_TOL, 1e-6)
    nonrigid = (ortho > tol) | (np.abs(det - 1.0) > tol)
    if np.any(nonrigid):
        i = int(np.argmax(nonrigid))
        raise PivotError(f"{what}: matrix {i} is not rigid (|R R^T - I| = {ortho[i]:.2e}, "
                         f"det R = {det[i]:.6f}); expected a rotation and a translation")
    if len(T) < min_poses:
        raise PivotError(f"{what}: {len(T)} pose(s) given; a pivot calibration needs at least "
                         f"{min_poses} poses with the tool turned about two or more axes "
                         "(the system is rank deficient)")
    return T


def _rotation_spread_deg(R: np.ndarray) -> float:
    """Largest angle (deg) between any of the rotations ``R`` (N, 3, 3) and their chordal mean."""
    rots = Rotation.from_matrix(R)
    mean = rots.mean()
    return float(np.degrees((mean.inv() * rots).magnitude().max()))


def _system(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The stacked algebraic system ``A x = b`` with ``x = [p_tool; p_W]`` (3N x 6, 3N)."""
    n = len(T)
    A = np.empty((3 * n, 6))
    A[:, :3] = T[:, :3, :3].reshape(3 * n, 3)
    A[:, 3:] = -np.tile(np.eye(3), (n, 1))
    b = -T[:, :3, 3].reshape(3 * n)
    return A, b


def _algebraic(T: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """One-step least squares; returns ``(p_tool, p_W, condition)`` or raises on rank loss."""
    A, b = _system(T)
    # A holds rotations and identities only, so its condition number measures the spread of
    # the orientations whatever the length unit.
    x, _, rank, sv = np.linalg.lstsq(A, b, rcond=None)
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else float("inf")
    if rank < 6 or sv[-1] < _RANK_RTOL * sv[0]:
        raise PivotError(f"pivot system is rank deficient (rank {rank} of 6, condition "
                         f"{cond:.3g}) from {len(T)} pose(s): pivot the tool about at least two "
                         "axes through the tip")
    return x[:3], x[3:], cond


def pivot_residuals(T: np.ndarray, p_tool: np.ndarray, p_W: np.ndarray) -> np.ndarray:
    """Per-pose residual vectors ``R_i p_tool + t_i - p_W`` (N, 3), input units."""
    return T[:, :3, :3] @ p_tool + T[:, :3, 3] - p_W


def _sphere(T: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict]:
    """Fit a sphere to the tool origins, then the tip from the rotations."""
    t = T[:, :3, 3]
    c0 = t.mean(axis=0)
    d = t - c0
    # |t - c|^2 = r^2  <=>  2 d . c' + (r^2 - |c'|^2) = |d|^2, with c' = c - c0 (linear).
    A = np.hstack([2.0 * d, np.ones((len(t), 1))])
    sol, _, rank, sv = np.linalg.lstsq(A, (d ** 2).sum(axis=1), rcond=None)
    if rank < 4 or sv[-1] < _RANK_RTOL * sv[0]:
        raise PivotError(f"sphere fit is rank deficient (rank {rank} of 4): the tool origins "
                         "do not spread over a sphere; pivot about two or more axes")
    c = sol[:3]
    r0 = np.sqrt(max(sol[3] + c @ c, 0.0))
    # Geometric refinement: minimise the radial distances, not the algebraic residual.
    fit = least_squares(lambda p: np.linalg.norm(d - p[:3], axis=1) - p[3],
                        np.r_[c, r0], method="lm")
    centre = fit.x[:3] + c0
    p_tool = np.mean(np.einsum("nji,nj->ni", T[:, :3, :3], centre - t), axis=0)
    return p_tool, centre, {"radius": float(abs(fit.x[3]))}


def _ransac(T: np.ndarray, iterations: int, sample_size: int, threshold: float,
            min_consensus: float, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """Algebraic fits on random subsets; refit on the largest consensus set."""
    n = len(T)
    if sample_size < 3 or sample_size > n:
        raise PivotError(f"ransac: sample size must be 3..{n} (the number of poses), "
                         f"got {sample_size}")
    if not (np.isfinite(threshold) and threshold > 0):
        raise PivotError(f"ransac: threshold must be a positive length, got {threshold}")
    rng = np.random.default_rng(seed)
    best: np.ndarray | None = None
    tried = 0
    for _ in range(iterations):
        idx = rng.choice(n, size=sample_size, replace=False)
        try:
            p_tool, p_W, _ = _algebraic(T[idx])
        except PivotError:
            continue  # a degenerate subset: draw again
        tried += 1
        err = np.linalg.norm(pivot_residuals(T, p_tool, p_W), axis=1)
        inl = err < threshold
        if best is None or inl.sum() > best.sum():
            best = inl
    need = max(sample_size, int(np.ceil(min_consensus * n)))
    if best is None or best.sum() < need:
        got = 0 if best is None else int(best.sum())
        raise PivotError(f"ransac: no consensus: the best of {iterations} subsets kept {got} of "
                         f"{n} poses within {threshold} (need {need}); raise the threshold or "
                         "the iterations, or check the tracking")
    p_tool, p_W, _ = _algebraic(T[best])
    return p_tool, p_W, best, {"iterations": iterations, "subsets_solved": tried,
                               "threshold": threshold, "sample_size": sample_size}


def pivot_calibration(T_W_tool: np.ndarray, method: str = "algebraic", *,
                      ransac_iterations: int = 10, ransac_sample_size: int = 4,
                      ransac_threshold: float = 4.0, ransac_min_consensus: float = 0.25,
                      seed: int = 0,
                      min_rotation_spread_deg: float = MIN_ROTATION_SPREAD_DEG) -> PivotResult:
    """Calibrate a pointer's tip from tracked poses pivoting about a fixed point.

    Args:
        T_W_tool: (N, 4, 4) tool poses in the tracker frame (any length unit; results
            come back in it).
        method: ``"algebraic"``, ``"sphere"`` or ``"ransac"``.
        ransac_*: RANSAC's iterations, subset size, inlier threshold (input units; the
            default 4 suits millimetres) and the smallest consensus as a
            fraction of the poses. ``seed`` makes the subsets reproducible.
        min_rotation_spread_deg: refuse sets whose orientations stay within this angle of
            their mean (the tip would be set by noise).

    Raises:
        PivotError: malformed or non-rigid matrices, too few poses, too little rotation,
            a rank-deficient system, or (RANSAC) no consensus.
    """
    if method not in METHODS:
        raise PivotError(f"unknown pivot method {method!r}; use one of {list(METHODS)}")
    T = validate_tracking_matrices(T_W_tool, min_poses=3)
    spread = _rotation_spread_deg(T[:, :3, :3])
    p_tool, p_W, cond = _algebraic(T)  # refuses rank-deficient sets, whichever the method
    if spread < min_rotation_spread_deg:
        raise PivotError(f"the tool turned at most {spread:.2f} deg from its mean orientation "
                         f"over {len(T)} poses (need {min_rotation_spread_deg} deg): pivot it "
                         "further about two or more axes")
    inliers = np.ones(len(T), dtype=bool)
    details: dict = {}
    if method == "sphere":
        p_tool, p_W, details = _sphere(T)
    elif method == "ransac":
        p_tool, p_W, inliers, details = _ransac(T, ransac_iterations, ransac_sample_size,
                                                ransac_threshold, ransac_min_consensus, seed)
    e = pivot_residuals(T, p_tool, p_W)
    used = e[inliers]
    rms = float(np.sqrt(np.mean(np.sum(used ** 2, axis=1))))
    return PivotResult(tip_offset=p_tool, pivot_point=p_W, rms=rms,
                       rms_per_component=rms / np.sqrt(3.0),
                       residuals=np.linalg.norm(e, axis=1), method=method, inliers=inliers,
                       condition=cond, rotation_spread_deg=spread, details=details)
