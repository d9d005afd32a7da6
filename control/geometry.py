"""Rigid-body geometry on SE(3), built on ``scipy.spatial.transform.Rotation``.

Convention (see docs/conventions.md): ``T_a_b`` is the 4x4 homogeneous pose of frame b
expressed in frame a; it maps points from b to a, so ``T_a_c = T_a_b @ T_b_c``.
Lengths are metres, angles radians. Twists are ordered ``[rho (3), omega (3)]``: ``rho``
the translational part (metres), ``omega`` the rotation vector (radians).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from oralnav.checks import TransformMessages, rigid_transform
from oralnav.control.errors import GeometryError

#: Tolerance on ``R^T R - I`` (max abs entry) and on ``det R - 1`` for a proper rotation.
ROTATION_TOL = 1e-6

# as_transform's wording since before oralnav.checks; a non-numeric T raises numpy's own
# TypeError/ValueError, as it always did.
_TRANSFORM_MESSAGES = TransformMessages(
    not_numbers=None,
    shape="{what}: expected a 4x4 transform, got shape {shape}",
    non_finite="{what}: transform has non-finite entries",
    bottom_row="{what}: bottom row must be [0, 0, 0, 1], got {row}",
    rotation="{what}: not a proper rotation (|R^T R - I| = {ortho:.2e}, det = {det:.6f})",
)


def as_rotation_matrix(R: np.ndarray | Sequence, *, tol: float = ROTATION_TOL,
                       what: str = "rotation") -> np.ndarray:
    """Return ``R`` as a float 3x3 proper rotation, or raise :class:`GeometryError`.

    ``what`` names the value in the error message (e.g. ``"T_ref_cam"``).
    """
    R = np.asarray(R, dtype=float)
    if R.shape != (3, 3):
        raise GeometryError(f"{what}: expected a 3x3 rotation, got shape {R.shape}")
    if not np.all(np.isfinite(R)):
        raise GeometryError(f"{what}: rotation has non-finite entries")
    ortho = np.max(np.abs(R.T @ R - np.eye(3)))
    det = np.linalg.det(R)
    if ortho > tol or abs(det - 1.0) > tol:
        raise GeometryError(
            f"{what}: not a proper rotation (|R^T R - I| = {ortho:.2e}, det = {det:.6f})")
    return R


def as_transform(T: np.ndarray | Sequence, *, tol: float = ROTATION_TOL,
                 what: str = "transform") -> np.ndarray:
    """Return ``T`` as a float 4x4 rigid transform, or raise :class:`GeometryError`.

    Checks the shape, finiteness, the bottom row ``[0, 0, 0, 1]`` and that the upper-left
    3x3 block is a proper rotation within ``tol`` (``det`` within ``tol`` of 1 too).
    Not a copy when ``T`` already is a float array.
    """
    return rigid_transform(T, what, GeometryError, tol=tol, det_tol=tol,
                           messages=_TRANSFORM_MESSAGES)


def make_transform(R: np.ndarray | Rotation | None = None,
                   t: np.ndarray | Sequence | None = None) -> np.ndarray:
    """Build a 4x4 transform from a rotation (matrix or ``Rotation``) and a translation (m)."""
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R.as_matrix() if isinstance(R, Rotation) else as_rotation_matrix(R)
    if t is not None:
        T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


def nearest_rigid(T: np.ndarray) -> np.ndarray:
    """``T`` with its 3x3 block replaced by the nearest rotation (SVD projection): for
    measured poses whose rotation has drifted a few 1e-7 from orthonormal, before they
    enter chains that check rigidity strictly."""
    U, _, Vt = np.linalg.svd(T[:3, :3])
    R = U @ Vt
    if np.linalg.det(R) < 0:  # a reflection is no pose: flip the weakest axis
        U[:, -1] = -U[:, -1]
        R = U @ Vt
    out = np.array(T, dtype=float)
    out[:3, :3] = R
    out[3] = [0.0, 0.0, 0.0, 1.0]
    return out


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform (``T_b_a`` from ``T_a_b``), exact for rigid matrices."""
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    out = np.zeros_like(T, dtype=float)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


def compose(*Ts: np.ndarray) -> np.ndarray:
    """Chain transforms left to right: ``compose(T_a_b, T_b_c) == T_a_c``."""
    if not Ts:
        return np.eye(4)
    out = np.asarray(Ts[0], dtype=float)
    for T in Ts[1:]:
        out = out @ T
    return out


def transform_points(T_a_b: np.ndarray, p_b: np.ndarray) -> np.ndarray:
    """Map points ``p_b`` (N x 3, frame b) into frame a; returns N x 3."""
    p_b = np.asarray(p_b, dtype=float)
    return p_b @ T_a_b[:3, :3].T + T_a_b[:3, 3]


def _left_jacobian(omega: np.ndarray) -> np.ndarray:
    """SO(3) left Jacobian ``J(omega)``; maps ``rho`` to the translation of ``exp``."""
    theta = np.linalg.norm(omega)
    W = _hat(omega)
    if theta < 1e-8:
        return np.eye(3) + 0.5 * W + W @ W / 6.0
    # (1 - cos t) / t^2 written as 2 sin^2(t/2) / t^2: the plain form cancels
    # catastrophically for small t (about 1e-9 m lost per metre of rho at t = 1e-8 rad).
    # (t - sin t) / t^3 also cancels, but it multiplies W @ W ~ t^2, so the error stays ~1e-16.
    sinc_half = np.sin(0.5 * theta) / (0.5 * theta)
    a = 0.5 * sinc_half * sinc_half
    b = (theta - np.sin(theta)) / theta**3
    return np.eye(3) + a * W + b * (W @ W)


def _left_jacobian_inv(omega: np.ndarray) -> np.ndarray:
    theta = np.linalg.norm(omega)
    W = _hat(omega)
    if theta < 1e-8:
        return np.eye(3) - 0.5 * W + W @ W / 12.0
    half = 0.5 * theta
    coef = (1.0 - half * np.cos(half) / np.sin(half)) / theta**2
    return np.eye(3) - 0.5 * W + coef * (W @ W)


def _hat(v: np.ndarray) -> np.ndarray:
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def exp(xi: np.ndarray | Sequence) -> np.ndarray:
    """SE(3) exponential: twist ``[rho, omega]`` (m, rad) -> 4x4 transform."""
    xi = np.asarray(xi, dtype=float).reshape(6)
    rho, omega = xi[:3], xi[3:]
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(omega).as_matrix()
    T[:3, 3] = _left_jacobian(omega) @ rho
    return T


def log(T: np.ndarray) -> np.ndarray:
    """SE(3) logarithm: 4x4 transform -> twist ``[rho, omega]`` (m, rad); inverse of :func:`exp`."""
    omega = Rotation.from_matrix(T[:3, :3]).as_rotvec()
    rho = _left_jacobian_inv(omega) @ T[:3, 3]
    return np.concatenate([rho, omega])


def rotation_angle(R_a: np.ndarray, R_b: np.ndarray | None = None) -> float:
    """Angle (rad) of the relative rotation ``R_a^T R_b`` (or of ``R_a`` alone); in [0, pi]."""
    R = R_a if R_b is None else R_a.T @ R_b
    return float(Rotation.from_matrix(R).magnitude())


def pose_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """Translation error (m) and rotation error (rad) of ``T_est`` against ``T_true``.

    Both transforms map the same child frame into the same parent frame; the translation
    error is the distance between their origins in the parent frame.
    """
    dt = float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3]))
    return dt, rotation_angle(T_true[:3, :3], T_est[:3, :3])


def average_poses(Ts: Sequence[np.ndarray] | np.ndarray,
                  weights: Sequence[float] | np.ndarray | None = None) -> np.ndarray:
    """Weighted mean of rigid transforms.

    Rotations are averaged with ``Rotation.mean`` (the chordal L2 mean, which is the right
    estimate for tightly clustered samples such as repeated calibration views);
    translations arithmetically. Raises :class:`GeometryError` on an empty set.
    """
    Ts = np.asarray(Ts, dtype=float)
    if Ts.ndim != 3 or Ts.shape[1:] != (4, 4) or len(Ts) == 0:
        raise GeometryError(f"average_poses: expected N x 4 x 4 with N >= 1, got {Ts.shape}")
    w = np.ones(len(Ts)) if weights is None else np.asarray(weights, dtype=float)
    if w.shape != (len(Ts),) or np.any(w < 0) or not np.any(w > 0):
        raise GeometryError("average_poses: weights must be N non-negative values, not all 0")
    R = Rotation.from_matrix(Ts[:, :3, :3]).mean(weights=w)
    t = (w[:, None] * Ts[:, :3, 3]).sum(axis=0) / w.sum()
    return make_transform(R, t)


def transform_from_euler(translation: Sequence[float],
                         euler_xyz_deg: Sequence[float]) -> np.ndarray:
    """4x4 transform from a translation (m) and extrinsic x-y-z Euler angles in degrees."""
    return make_transform(Rotation.from_euler("xyz", euler_xyz_deg, degrees=True), translation)
