"""Eye-to-hand calibration: the stereo camera in the robot base and the robot marker on the TCP.

The stereo camera ``C`` stands fixed in the robot base ``B``; the robot marker ``RM`` is rigid
on the arm's tool centre point ``tcp``. For robot poses i = 1..N the arm reports ``T_B_tcp[i]``
(exact up to its repeatability) and the camera measures ``T_C_RM[i]`` (noisy), so

    T_B_C @ T_C_RM[i] = T_B_tcp[i] @ T_tcp_RM

with two unknowns, ``X = T_B_C`` and ``Z = T_tcp_RM`` (the AX = ZB, robot-world-hand-eye
problem). :func:`calibrate_hand_eye` starts from a closed-form solution (OpenCV's, or this
module's own where the installed OpenCV lacks it) and refines both unknowns together by
weighted, optionally robust, nonlinear least squares on SE(3), with the residual formed where
the measurement noise is: in the camera frame.

:func:`check_pose_set` tells whether a planned set of robot poses can calibrate at all (enough
rotation, about more than one axis); :func:`plan_hand_eye_poses` makes such a set.

Conventions as in :mod:`oralnav.control.geometry`: ``T_a_b`` is the 4x4 pose of frame b in
frame a, metres and radians inside; results also report millimetres and degrees where named.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from types import MappingProxyType
from typing import Literal

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from oralnav.control.errors import CalibrationError, GeometryError
from oralnav.control.geometry import (
    as_transform,
    average_poses,
    exp,
    invert,
    make_transform,
    nearest_rigid,
)

__all__ = [
    "HAND_EYE_METHODS",
    "LOSSES",
    "CalibrationError",
    "HandEyeResult",
    "PoseSetReport",
    "available_methods",
    "calibrate_hand_eye",
    "check_pose_set",
    "plan_hand_eye_poses",
    "start_estimate",
]


#: Closed-form starting methods. The first five solve AX = XB on relative motions
#: (``cv2.calibrateHandEye``), the last two AX = ZB on the poses themselves
#: (``cv2.calibrateRobotWorldHandEye``).
HAND_EYE_METHODS = ("tsai", "park", "horaud", "andreff", "daniilidis", "shah", "li")
_AX_XB = {"tsai": "CALIB_HAND_EYE_TSAI", "park": "CALIB_HAND_EYE_PARK",
          "horaud": "CALIB_HAND_EYE_HORAUD", "andreff": "CALIB_HAND_EYE_ANDREFF",
          "daniilidis": "CALIB_HAND_EYE_DANIILIDIS"}
_AX_ZB = {"shah": "CALIB_ROBOT_WORLD_HAND_EYE_SHAH", "li": "CALIB_ROBOT_WORLD_HAND_EYE_LI"}

#: Robust losses of the refinement, applied to each pose's whitened residual norm.
LOSSES = ("linear", "huber", "soft_l1", "cauchy")
Loss = Literal["linear", "huber", "soft_l1", "cauchy"]
Backend = Literal["auto", "opencv", "builtin"]

# Default 1-sigma noise of one T_C_RM, per camera axis. Lateral error grows as Z / f and
# stereo depth error as Z^2 / (f b), so depth is about Z / b times worse: 2.5x at the sim's
# 0.25 m with its 0.1 m baseline, ~6x at 0.6 m; 0.04 mm and 0.15 mm sit between. The tilt
# of the 50 x 35 mm patch follows from depth differences across it: a few hundredths of a
# degree. Only the ratios steer the estimate (the covariance is rescaled by the observed
# residual scatter); the absolute values set where the robust loss starts to down-weight.
SIGMA_LATERAL_M = 0.04e-3
SIGMA_DEPTH_M = 0.15e-3
SIGMA_ROTATION_RAD = float(np.deg2rad(0.03))
#: Robust loss knee, in whitened pose-residual norm (a 6-dof chi: inliers ~2.3, rarely > 4).
ROBUST_SCALE = 4.0
#: Poses whose robust weight falls below this are reported as down-weighted.
DOWNWEIGHT_BELOW = 0.5
#: Default diversity rules of :func:`check_pose_set` (degrees).
MIN_ROTATION_DEG = 5.0
MIN_AXIS_SPREAD_DEG = 15.0

_MEDIAN_CHI6 = float(np.sqrt(chi2.ppf(0.5, 6)))  # median norm of a whitened 6-vector
_GOLDEN = np.pi * (3.0 - np.sqrt(5.0))           # golden angle (rad)


# -- input validation --------------------------------------------------------------------
def _stack(T: np.ndarray | Sequence, what: str) -> np.ndarray:
    """Validate an (N, 4, 4) stack of rigid transforms; return it re-orthonormalised.

    Measured rotations that passed the rigidity check (1e-6) are projected onto SO(3) so the
    maths below never sees the drift.
    """
    try:
        T = np.array(T, dtype=float)
    except (TypeError, ValueError) as exc:
        raise CalibrationError(f"{what}: not an array of 4x4 transforms ({exc})") from None
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise CalibrationError(f"{what}: expected an (N, 4, 4) stack of transforms, "
                               f"got shape {T.shape}")
    for i, Ti in enumerate(T):
        try:
            as_transform(Ti, what=f"{what}[{i}]")
        except GeometryError as exc:
            raise CalibrationError(str(exc)) from None
    return np.stack([nearest_rigid(Ti) for Ti in T]) if len(T) else T


def _pair(T_B_tcp: np.ndarray | Sequence,
          T_C_RM: np.ndarray | Sequence) -> tuple[np.ndarray, np.ndarray]:
    A = _stack(T_B_tcp, "T_B_tcp")
    M = _stack(T_C_RM, "T_C_RM")
    if len(A) != len(M):
        raise CalibrationError(f"T_B_tcp has {len(A)} poses but T_C_RM has {len(M)}: "
                               "they must be taken in pairs, one per robot pose")
    if len(A) < 3:
        raise CalibrationError(f"{len(A)} pose pairs: hand-eye calibration needs at least 3 "
                               "(15-30 recommended)")
    return A, M


# -- pose-set diversity -----------------------------------------------------------------
@dataclass(frozen=True)
class PoseSetReport:
    """Whether a set of robot poses can calibrate hand-eye, and why not.

    Attributes:
        ok: no problem found.
        n_poses: number of poses.
        max_rotation_deg: largest rotation between any two poses (deg).
        axis_spread_deg: largest angle between the axis of a relative rotation at least
            ``min_rotation_deg`` large and the main axis of all such rotations (deg, 0..90;
            0 when there are none).
        problems: one sentence per problem, each saying what motion to add.
    """

    ok: bool
    n_poses: int
    max_rotation_deg: float
    axis_spread_deg: float
    problems: tuple[str, ...] = ()

    @property
    def message(self) -> str:
        """The problems as one line ("" when the set is fine)."""
        return "; ".join(self.problems)


#: Pose pairs used for relative motions: all of them up to this many, else a fixed sample.
MAX_PAIRS = 5000


def _pairs(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (i, j), i < j, of n poses: all, or a deterministic sample of MAX_PAIRS."""
    i, j = np.triu_indices(n, k=1)
    if len(i) > MAX_PAIRS:
        keep = np.sort(np.random.default_rng(0).choice(len(i), MAX_PAIRS, replace=False))
        i, j = i[keep], j[keep]
    return i, j


def _relative_rotations(R: np.ndarray) -> np.ndarray:
    """Rotation vectors (rad, base frame) of ``R_j R_i^T`` for the pose pairs; (P, 3)."""
    i, j = _pairs(len(R))
    return Rotation.from_matrix(R[j] @ np.swapaxes(R[i], 1, 2)).as_rotvec()


def _diversity(T_B_tcp: np.ndarray, min_rotation_deg: float,
               min_axis_spread_deg: float) -> PoseSetReport:
    n = len(T_B_tcp)
    problems: list[str] = []
    if n < 3:
        problems.append(f"{n} poses: hand-eye calibration needs at least 3 (15-30 "
                        "recommended)")
    rotvecs = _relative_rotations(T_B_tcp[:, :3, :3]) if n >= 2 else np.zeros((0, 3))
    angles = np.linalg.norm(rotvecs, axis=1)
    max_rot = float(np.rad2deg(angles.max())) if len(angles) else 0.0
    big = angles >= np.deg2rad(min_rotation_deg)
    spread = 0.0
    if n >= 2 and not np.any(big):
        problems.append(
            f"rotations too small: the largest rotation between two poses is {max_rot:.2f} "
            f"deg, below {min_rotation_deg:g} deg; tilt the tool 10-30 deg between poses, "
            "about at least two different axes")
    elif np.any(big):
        axes = rotvecs[big] / angles[big, None]
        # Hand-eye recovers the rotation about a motion axis only from a second, different
        # axis. The spread is the largest angle between an axis line (a rotation by -a about
        # n is one by a about -n) and the main axis line, the principal direction of them all.
        main = np.linalg.eigh(axes.T @ axes)[1][:, -1]
        main = main if main[np.argmax(np.abs(main))] > 0 else -main
        cos = np.clip(np.abs(axes @ main), 0.0, 1.0)
        spread = float(np.rad2deg(np.arccos(cos.min())))
        if spread < min_axis_spread_deg:
            problems.append(
                "all relative rotations are about nearly one axis (within "
                f"{spread:.1f} deg of [{main[0]:.2f}, {main[1]:.2f}, {main[2]:.2f}] in the "
                f"base frame; {min_axis_spread_deg:g} deg needed): add poses tilted by "
                "10-30 deg about an axis perpendicular to it")
    return PoseSetReport(ok=not problems, n_poses=n, max_rotation_deg=max_rot,
                         axis_spread_deg=spread, problems=tuple(problems))


def check_pose_set(T_B_tcp: np.ndarray | Sequence, *,
                   min_rotation_deg: float = MIN_ROTATION_DEG,
                   min_axis_spread_deg: float = MIN_AXIS_SPREAD_DEG) -> PoseSetReport:
    """Judge a planned or recorded set of robot poses for hand-eye calibration.

    ``T_B_tcp`` is an (N, 4, 4) stack of TCP poses in the base (m). The set is good when it
    has at least 3 poses, some pair of poses differs by at least ``min_rotation_deg``, and
    the relative rotations (``R_j R_i^T``, base frame) of such pairs do not all turn about
    one axis: some axis lies at least ``min_axis_spread_deg`` off their main axis. With one
    motion axis only, the rotation about it (and the translation along it) stay
    unobservable. Malformed input raises
    :class:`CalibrationError`; an unsuitable set does not, its report says what to add.
    """
    return _diversity(_stack(T_B_tcp, "T_B_tcp"), float(min_rotation_deg),
                      float(min_axis_spread_deg))


# -- closed-form starting points --------------------------------------------------------
def _opencv_function(method: str) -> Callable | None:
    """The cv2 solver for ``method``, or None where this OpenCV build lacks it.

    opencv-contrib-python 5.0.0.93 ships the flags but not ``calibrateHandEye`` or
    ``calibrateRobotWorldHandEye`` (opencv/opencv issue 29565, fixed upstream after it).
    """
    name = "calibrateHandEye" if method in _AX_XB else "calibrateRobotWorldHandEye"
    return getattr(cv2, name, None)


def available_methods(backend: Backend = "auto") -> tuple[str, ...]:
    """The starting methods usable with ``backend`` in this installation."""
    return tuple(m for m in HAND_EYE_METHODS
                 if (backend != "builtin" and _opencv_function(m) is not None)
                 or (backend != "opencv" and m in _BUILTIN))


def _Rt(T: np.ndarray) -> tuple[list[np.ndarray], list[np.ndarray]]:
    return [np.ascontiguousarray(Ti[:3, :3]) for Ti in T], \
           [np.ascontiguousarray(Ti[:3, 3:4]) for Ti in T]


def _opencv_start(method: str, A: np.ndarray, M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's closed form; ``A = T_B_tcp``, ``M = T_C_RM`` (N, 4, 4). Returns (X, Z)."""
    func = _opencv_function(method)
    if method in _AX_XB:
        # calibrateHandEye solves the eye-in-hand chain
        #     T_base_gripper[i] @ T_gripper_cam @ T_cam_target[i] = T_base_target (constant).
        # Ours, left-multiplied by T_tcp_B[i]:  T_tcp_B[i] @ T_B_C @ T_C_RM[i] = T_tcp_RM.
        # Term by term: "gripper2base" <- T_tcp_B[i] = inv(T_B_tcp[i]) (the arm pose
        # inverted: the camera rides on our base, so our base plays OpenCV's gripper and our
        # tcp its base), "target2cam" <- T_C_RM[i] unchanged, and "cam2gripper" comes out
        # as T_B_C. The constant "target2base" is T_tcp_RM, which OpenCV does not return:
        # it is averaged below from T_tcp_B[i] X T_C_RM[i].
        Rg, tg = _Rt(invert(A))
        Rc, tc = _Rt(M)
        R, t = func(Rg, tg, Rc, tc, method=getattr(cv2, _AX_XB[method]))
        X = make_transform(None, np.asarray(t).reshape(3))
        X[:3, :3] = np.asarray(R, dtype=float)
        X = _checked_start(X, method)
        return X, _Z_from_X(X, A, M)
    # calibrateRobotWorldHandEye solves  T_cam_world[i] @ T_world_base = T_cam_gripper @
    # T_gripper_base[i]  (its A X = Z B). Ours is  T_B_tcp[i] @ T_tcp_RM = T_B_C @ T_C_RM[i]
    # read right to left, so nothing is inverted: "world2cam" <- T_B_tcp[i] (its "cam" is our
    # base, its "world" our tcp), "base2gripper" <- T_C_RM[i] (its "gripper" is our camera,
    # its "base" our marker); out come "base2world" = T_tcp_RM and "gripper2cam" = T_B_C.
    Ra, ta = _Rt(A)
    Rb, tb = _Rt(M)
    R_z, t_z, R_x, t_x = func(Ra, ta, Rb, tb, method=getattr(cv2, _AX_ZB[method]))
    Z = make_transform(None, np.asarray(t_z).reshape(3))
    Z[:3, :3] = np.asarray(R_z, dtype=float)
    X = make_transform(None, np.asarray(t_x).reshape(3))
    X[:3, :3] = np.asarray(R_x, dtype=float)
    return _checked_start(X, method), _checked_start(Z, method)


def _checked_start(T: np.ndarray, method: str) -> np.ndarray:
    if not np.all(np.isfinite(T)):
        raise CalibrationError(f"method {method!r} returned a non-finite solution")
    return nearest_rigid(T)


def _Z_from_X(X: np.ndarray, A: np.ndarray, M: np.ndarray) -> np.ndarray:
    """``T_tcp_RM`` given ``X = T_B_C``: the mean of ``T_tcp_B[i] X T_C_RM[i]``."""
    return average_poses(invert(A) @ X @ M)


def _relative_motions(A: np.ndarray, M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Relative motions (P, 4, 4) of every pair i < j, such that ``RA X = X RB``.

    From ``T_tcp_B[i] X T_C_RM[i] = Z`` for i and j: ``RA = T_B_tcp[j] T_tcp_B[i]`` (tool
    motion, base frame), ``RB = T_C_RM[j] T_RM_C[i]`` (marker motion, camera frame).
    """
    i, j = _pairs(len(A))
    return A[j] @ invert(A[i]), M[j] @ invert(M[i])


def _translation_ax_xb(R_X: np.ndarray, RA: np.ndarray, RB: np.ndarray) -> np.ndarray:
    """Least-squares ``t_X`` of ``(R_A - I) t_X = R_X t_B - t_A`` over all motions."""
    lhs = (RA[:, :3, :3] - np.eye(3)).reshape(-1, 3)
    rhs = (RB[:, :3, 3] @ R_X.T - RA[:, :3, 3]).reshape(-1)
    return np.linalg.lstsq(lhs, rhs, rcond=None)[0]


def _nearest_rotation(R: np.ndarray) -> np.ndarray:
    """The rotation nearest (Frobenius) to a 3x3 matrix, fixing a reflection."""
    U, _, Vt = np.linalg.svd(R)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def _unvec(v: np.ndarray) -> np.ndarray:
    """3x3 matrix from its column-major vec, the one in ``vec(P Y Q) = (Q^T kron P) vec Y``."""
    return v.reshape(3, 3).T


def _builtin_tsai(A: np.ndarray, M: np.ndarray) -> np.ndarray:
    """Tsai-Lenz: rotation from the modified Rodrigues vectors of the motion pairs.

    With ``P = 2 sin(theta / 2) n`` of each motion and the Gibbs vector ``g = tan(phi / 2) u``
    of ``R_X``: ``[P_A + P_B]x g = P_B - P_A`` (linear least squares in g).
    """
    RA, RB = _relative_motions(A, M)
    a = Rotation.from_matrix(RA[:, :3, :3]).as_rotvec()
    b = Rotation.from_matrix(RB[:, :3, :3]).as_rotvec()

    def modified(v: np.ndarray) -> np.ndarray:
        th = np.linalg.norm(v, axis=1, keepdims=True)
        return np.where(th > 1e-12, 2.0 * np.sin(0.5 * th) / np.maximum(th, 1e-300), 1.0) * v

    pa, pb = modified(a), modified(b)
    s = pa + pb
    skew = np.zeros((len(s), 3, 3))
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -s[:, 2], s[:, 1], -s[:, 0]
    skew[:, 1, 0], skew[:, 2, 0], skew[:, 2, 1] = s[:, 2], -s[:, 1], s[:, 0]
    g = np.linalg.lstsq(skew.reshape(-1, 3), (pb - pa).reshape(-1), rcond=None)[0]
    ng = np.linalg.norm(g)
    rotvec = 2.0 * np.arctan(ng) * g / ng if ng > 0 else g
    R_X = Rotation.from_rotvec(rotvec).as_matrix()
    return make_transform(R_X, _translation_ax_xb(R_X, RA, RB))


def _builtin_park(A: np.ndarray, M: np.ndarray) -> np.ndarray:
    """Park-Martin: ``log R_A = R_X log R_B``, solved as an orthogonal Procrustes problem."""
    RA, RB = _relative_motions(A, M)
    a = Rotation.from_matrix(RA[:, :3, :3]).as_rotvec()
    b = Rotation.from_matrix(RB[:, :3, :3]).as_rotvec()
    R_X = Rotation.align_vectors(a, b)[0].as_matrix()
    return make_transform(R_X, _translation_ax_xb(R_X, RA, RB))


def _builtin_andreff(A: np.ndarray, M: np.ndarray) -> np.ndarray:
    """Andreff: ``(I kron R_A - R_B^T kron I) vec R_X = 0``; null space, then translation."""
    RA, RB = _relative_motions(A, M)
    I3 = np.eye(3)
    K = np.concatenate([np.kron(I3, Ra) - np.kron(Rb.T, I3)
                        for Ra, Rb in zip(RA[:, :3, :3], RB[:, :3, :3], strict=True)])
    R = _unvec(np.linalg.svd(K, full_matrices=False)[2][-1])
    R_X = _nearest_rotation(R * np.sign(np.linalg.det(R)))
    return make_transform(R_X, _translation_ax_xb(R_X, RA, RB))


def _builtin_shah(A: np.ndarray, M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Shah, on the poses themselves: ``T_B_tcp[i] Z = X T_C_RM[i]`` (X = T_B_C, Z =
    T_tcp_RM). Both rotations from the null space of the stacked Kronecker rows of
    ``R_A R_Z = R_X R_B``, then both translations by linear least squares.
    """
    I3 = np.eye(3)
    K = np.concatenate([np.hstack([np.kron(I3, Ra), -np.kron(Rb.T, I3)])
                        for Ra, Rb in zip(A[:, :3, :3], M[:, :3, :3], strict=True)])
    v = np.linalg.svd(K, full_matrices=False)[2][-1]
    Rz, Rx = _unvec(v[:9]), _unvec(v[9:])
    sign = np.sign(np.linalg.det(Rz))   # one common scale: fix its sign by Z's det
    R_Z, R_X = _nearest_rotation(sign * Rz), _nearest_rotation(sign * Rx)
    # R_A t_Z + t_A = R_X t_B + t_X
    lhs = np.concatenate([np.hstack([Ra, -I3]) for Ra in A[:, :3, :3]])
    rhs = (M[:, :3, 3] @ R_X.T - A[:, :3, 3]).reshape(-1)
    t = np.linalg.lstsq(lhs, rhs, rcond=None)[0]
    return make_transform(R_X, t[3:]), make_transform(R_Z, t[:3])


def _builtin_li(A: np.ndarray, M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Li: rotations and translations of ``T_B_tcp[i] Z = X T_C_RM[i]`` in one linear
    least-squares system, unknowns ``[vec R_Z, vec R_X, t_Z, t_X]`` (X = T_B_C, Z =
    T_tcp_RM); the translation rows fix the scale. The rotations are then projected onto
    SO(3), the translations kept.
    """
    I3 = np.eye(3)
    rows, rhs = [], []
    for Ra, ta, Rb, tb in zip(A[:, :3, :3], A[:, :3, 3], M[:, :3, :3], M[:, :3, 3],
                              strict=True):
        rows.append(np.hstack([np.kron(I3, Ra), -np.kron(Rb.T, I3), np.zeros((9, 6))]))
        rhs.append(np.zeros(9))
        # R_A t_Z - R_X t_B - t_X = -t_A, with R_X t_B = (t_B^T kron I) vec R_X
        rows.append(np.hstack([np.zeros((3, 9)), -np.kron(tb[None, :], I3), Ra, -I3]))
        rhs.append(-ta)
    sol = np.linalg.lstsq(np.concatenate(rows), np.concatenate(rhs), rcond=None)[0]
    R_Z, R_X = _nearest_rotation(_unvec(sol[:9])), _nearest_rotation(_unvec(sol[9:18]))
    return make_transform(R_X, sol[21:24]), make_transform(R_Z, sol[18:21])


def _ax_xb(solver: Callable[[np.ndarray, np.ndarray], np.ndarray]):
    def start(A: np.ndarray, M: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        X = solver(A, M)
        return X, _Z_from_X(X, A, M)
    return start


#: This module's own closed forms, used where OpenCV lacks its solvers. Horaud's and
#: Daniilidis' need quaternion algebra, which the project leaves to OpenCV and scipy.
_BUILTIN: dict[str, Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]] = {
    "tsai": _ax_xb(_builtin_tsai), "park": _ax_xb(_builtin_park),
    "andreff": _ax_xb(_builtin_andreff), "shah": _builtin_shah, "li": _builtin_li,
}


def _start(method: str, A: np.ndarray, M: np.ndarray,
           backend: Backend) -> tuple[np.ndarray, np.ndarray, str]:
    if method not in HAND_EYE_METHODS:
        raise CalibrationError(f"unknown hand-eye method {method!r}; expected 'auto' or one "
                               f"of {', '.join(HAND_EYE_METHODS)}")
    if backend not in ("auto", "opencv", "builtin"):
        raise CalibrationError(f"unknown backend {backend!r}; expected 'auto', 'opencv' or "
                               "'builtin'")
    use_cv = backend != "builtin" and _opencv_function(method) is not None
    if not use_cv and backend == "builtin" and method not in _BUILTIN:
        raise CalibrationError(f"method {method!r} has no built-in implementation; built-in "
                               f"methods: {', '.join(_BUILTIN)}")
    if not use_cv and (backend == "opencv" or method not in _BUILTIN):
        raise CalibrationError(
            f"method {method!r} needs OpenCV's calibrateHandEye/calibrateRobotWorldHandEye, "
            f"which this OpenCV ({cv2.__version__}) does not provide"
            + ("" if backend == "opencv" else
               f"; built-in methods: {', '.join(_BUILTIN)}"))
    try:
        if use_cv:
            X, Z = _opencv_start(method, A, M)
        else:
            X, Z = _BUILTIN[method](A, M)
            X, Z = _checked_start(X, method), _checked_start(Z, method)
    except cv2.error as exc:
        raise CalibrationError(f"OpenCV method {method!r} failed: {exc}") from None
    except np.linalg.LinAlgError as exc:
        raise CalibrationError(f"method {method!r} failed: {exc}") from None
    return X, Z, "opencv" if use_cv else "builtin"


def start_estimate(T_B_tcp: np.ndarray | Sequence, T_C_RM: np.ndarray | Sequence,
                   method: str, *, backend: Backend = "auto") -> tuple[np.ndarray, np.ndarray]:
    """One closed-form solution ``(T_B_C, T_tcp_RM)`` (4x4 each, m), without refinement.

    ``T_B_tcp``, ``T_C_RM``: (N, 4, 4) paired poses (m). ``backend``: "opencv" (cv2's
    solver), "builtin" (this module's: tsai, park, andreff, shah, li) or "auto" (OpenCV
    where this installation has it). Inputs are validated, not checked for diversity.
    """
    A, M = _pair(T_B_tcp, T_C_RM)
    X, Z, _ = _start(method, A, M, backend)
    return X, Z


# -- refinement -------------------------------------------------------------------------
def _rho(z: np.ndarray, loss: str) -> tuple[np.ndarray, np.ndarray]:
    """Loss ``rho(z)`` and its derivative (the IRLS weight) for squared scaled norms z."""
    if loss == "linear":
        return z, np.ones_like(z)
    if loss == "huber":
        big = z > 1.0
        sq = np.sqrt(np.where(big, z, 1.0))
        return np.where(big, 2.0 * sq - 1.0, z), np.where(big, 1.0 / sq, 1.0)
    if loss == "soft_l1":
        sq = np.sqrt(1.0 + z)
        return 2.0 * (sq - 1.0), 1.0 / sq
    return np.log1p(z), 1.0 / (1.0 + z)  # cauchy


@dataclass(frozen=True)
class _Problem:
    """The data and noise model of one refinement (internal)."""

    A: np.ndarray          # T_B_tcp (N, 4, 4)
    M: np.ndarray          # T_C_RM (N, 4, 4)
    inv_sigma: np.ndarray  # (6,) 1 / sigma of [t_x, t_y, t_z, w_x, w_y, w_z], camera frame
    weights: np.ndarray    # (N,) user weights

    def errors(self, X: np.ndarray, Z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Measured minus predicted ``T_C_RM``: translation (N, 3) m, rotation (N, 3) rad.

        Both in the camera frame: the prediction is ``T_C_B T_B_tcp[i] T_tcp_RM`` and the
        rotation error is the rotation vector of ``R_meas R_pred^T``.
        """
        # The noise lives on T_C_RM and is shaped in the camera frame (depth worse than
        # lateral), so the residual compares measured and predicted marker poses there and
        # can be whitened per camera axis, the maximum-likelihood weighting. Formed in the
        # base frame (X T_C_RM vs T_B_tcp Z) the same error is rotated by R_B_C, which would
        # mix the depth axis into all three base axes; in the marker frame it would also
        # pick up the lever of the rotation noise on the translation.
        P = invert(X) @ self.A @ Z
        dt = self.M[:, :3, 3] - P[:, :3, 3]
        dw = Rotation.from_matrix(self.M[:, :3, :3] @ np.swapaxes(P[:, :3, :3], 1, 2)).as_rotvec()
        return dt, dw

    def whitened(self, X: np.ndarray, Z: np.ndarray) -> np.ndarray:
        """Whitened, weighted residuals (N, 6) (dimensionless, ~N(0, 1) for inliers)."""
        dt, dw = self.errors(X, Z)
        return np.hstack([dt, dw]) * self.inv_sigma * np.sqrt(self.weights)[:, None]


def _apply(xi: np.ndarray, X0: np.ndarray, Z0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Left increments: ``X = exp(xi[:6]) X0`` (base frame), ``Z = exp(xi[6:]) Z0`` (tcp)."""
    return exp(xi[:6]) @ X0, exp(xi[6:]) @ Z0


def _robust_residuals(r: np.ndarray, c: float, loss: str) -> np.ndarray:
    """Rescale each pose's 6-vector so its squared norm is ``c^2 rho(|r|^2 / c^2)``.

    The loss then acts on the pose as a whole (one bad detection spoils all six components
    together), and the plain least-squares solver minimises the robust cost.
    """
    if loss == "linear":
        return r.ravel()
    d2 = np.sum(r * r, axis=1)
    z = d2 / c**2
    rho, _ = _rho(z, loss)
    scale = np.sqrt(np.where(d2 > 0, c**2 * rho / np.where(d2 > 0, d2, 1.0), 1.0))
    return (r * scale[:, None]).ravel()


def _solve(prob: _Problem, X0: np.ndarray, Z0: np.ndarray, c: float,
           loss: str) -> tuple[np.ndarray, np.ndarray]:
    def fun(xi: np.ndarray) -> np.ndarray:
        return _robust_residuals(prob.whitened(*_apply(xi, X0, Z0)), c, loss)

    sol = least_squares(fun, np.zeros(12), method="trf", x_scale="jac", xtol=1e-12,
                        ftol=1e-12, gtol=1e-12, max_nfev=200)
    return _apply(sol.x, X0, Z0)


def _scale_factor(prob: _Problem, X: np.ndarray, Z: np.ndarray) -> float:
    """How much larger than the nominal sigma the residuals are (median-based, >= 1)."""
    d = np.linalg.norm(prob.whitened(X, Z), axis=1)[prob.weights > 0]
    return max(1.0, float(np.median(d)) / _MEDIAN_CHI6)


def _covariance(prob: _Problem, X: np.ndarray, Z: np.ndarray,
                robust_w: np.ndarray, inlier: np.ndarray) -> np.ndarray:
    """Covariance (12, 12) of the left increments ``[xi_X, xi_Z]`` (m, rad) at (X, Z).

    Gauss-Newton ``s^2 (J^T W J)^-1`` with J by central differences of the whitened residuals,
    W the robust weights, and ``s^2`` the reduced chi-square of the inlier poses, so the
    figure follows the observed scatter even where the nominal sigmas are off.
    """
    h = 1e-7
    cols = []
    for k in range(12):
        e = np.zeros(12)
        e[k] = h
        cols.append((prob.whitened(*_apply(e, X, Z)) - prob.whitened(*_apply(-e, X, Z)))
                    .ravel() / (2 * h))
    J = np.stack(cols, axis=1) * np.repeat(np.sqrt(robust_w), 6)[:, None]
    r = prob.whitened(X, Z)
    use = inlier & (prob.weights > 0)
    dof = 6 * int(use.sum()) - 12
    s2 = float(np.sum(r[use] ** 2)) / dof if dof > 0 else float("nan")
    try:
        return s2 * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return np.full((12, 12), np.inf)


# -- the result -------------------------------------------------------------------------
def _frozen(a: np.ndarray) -> np.ndarray:
    out = np.array(a, dtype=float)
    out.flags.writeable = False
    return out


@dataclass(frozen=True, eq=False)
class HandEyeResult:
    """An eye-to-hand calibration.

    Attributes:
        T_B_C: the stereo camera in the robot base (4x4, m).
        T_tcp_RM: the robot marker on the TCP (4x4, m).
        n_poses: number of pose pairs used.
        residuals_mm, residuals_deg: (N,) per pose, the distance (mm) and the rotation angle
            (deg) between the measured ``T_C_RM[i]`` and the one predicted by the solution,
            ``T_C_B T_B_tcp[i] T_tcp_RM``.
        rms_mm, rms_deg: root mean square of those.
        start_method: the closed-form method the refinement started from.
        start_backend: "opencv" or "builtin" (which implementation gave the start).
        start_residuals_mm, start_residuals_deg, start_rms_mm, start_rms_deg: the same
            residual figures for the start.
        starts: every start tried, method -> (rms mm, rms deg).
        start_failures: methods that could not give a start, method -> reason.
        refined: whether the joint refinement ran.
        loss: the refinement's loss.
        robust_weights: (N,) each pose's final robust weight (1 = full, smaller = trusted
            less, 0 = left out; all 1 with the linear loss or without refinement).
        downweighted: indices of poses whose robust weight fell below 0.5: suspect poses,
            left out of the last refinement pass (their residuals are still reported).
        sigma_T_B_C_mm: 1-sigma (root of the covariance's trace) of the camera origin's
            position in the base (mm), from the Jacobian at the solution.
        sigma_T_B_C_deg: 1-sigma (root of the trace) of the camera's rotation (deg).
        sigma_T_B_C_axes_mm, sigma_T_B_C_axes_deg: (3,) the same per base axis.
        covariance: (12, 12) of the left increments ``[xi_X, xi_Z]`` (m, rad), ``X = exp(xi_X)
            T_B_C`` (base frame), ``Z = exp(xi_Z) T_tcp_RM`` (tcp frame); twist order as in
            :func:`oralnav.control.geometry.exp` ([rho, omega]).
    """

    T_B_C: np.ndarray
    T_tcp_RM: np.ndarray
    n_poses: int
    residuals_mm: np.ndarray
    residuals_deg: np.ndarray
    rms_mm: float
    rms_deg: float
    start_method: str
    start_backend: str
    start_residuals_mm: np.ndarray
    start_residuals_deg: np.ndarray
    start_rms_mm: float
    start_rms_deg: float
    refined: bool
    loss: str
    robust_weights: np.ndarray
    downweighted: tuple[int, ...]
    sigma_T_B_C_mm: float
    sigma_T_B_C_deg: float
    sigma_T_B_C_axes_mm: np.ndarray
    sigma_T_B_C_axes_deg: np.ndarray
    covariance: np.ndarray
    starts: Mapping[str, tuple[float, float]] = field(default_factory=dict)
    start_failures: Mapping[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name in ("T_B_C", "T_tcp_RM", "residuals_mm", "residuals_deg",
                     "start_residuals_mm", "start_residuals_deg", "robust_weights",
                     "sigma_T_B_C_axes_mm", "sigma_T_B_C_axes_deg", "covariance"):
            object.__setattr__(self, name, _frozen(getattr(self, name)))
        object.__setattr__(self, "starts", MappingProxyType(dict(self.starts)))
        object.__setattr__(self, "start_failures",
                           MappingProxyType(dict(self.start_failures)))


def _figures(prob: _Problem, X: np.ndarray, Z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    dt, dw = prob.errors(X, Z)
    return np.linalg.norm(dt, axis=1) * 1e3, np.rad2deg(np.linalg.norm(dw, axis=1))


def _rms(v: np.ndarray) -> float:
    return float(np.sqrt(np.mean(v * v)))


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


# -- calibration ------------------------------------------------------------------------
def calibrate_hand_eye(
    T_B_tcp: np.ndarray | Sequence,
    T_C_RM: np.ndarray | Sequence,
    *,
    method: str = "auto",
    weights: np.ndarray | Sequence[float] | None = None,
    refine: bool = True,
    loss: Loss = "huber",
    sigma_lateral_m: float = SIGMA_LATERAL_M,
    sigma_depth_m: float = SIGMA_DEPTH_M,
    sigma_rotation_rad: float = SIGMA_ROTATION_RAD,
    robust_scale: float = ROBUST_SCALE,
    backend: Backend = "auto",
    min_rotation_deg: float = MIN_ROTATION_DEG,
    min_axis_spread_deg: float = MIN_AXIS_SPREAD_DEG,
) -> HandEyeResult:
    """Calibrate ``T_B_C`` (camera in base) and ``T_tcp_RM`` (marker on the TCP) together.

    Args:
        T_B_tcp: (N, 4, 4) TCP poses reported by the arm, base frame (m); N >= 3.
        T_C_RM: (N, 4, 4) robot-marker poses measured by the stereo camera at those TCP
            poses, camera frame (m).
        method: closed-form start: one of :data:`HAND_EYE_METHODS`, or "auto" to run every
            available one and start from the lowest objective.
        weights: optional (N,) non-negative per-pose weights (relative; e.g. 0 drops a pose).
        refine: run the joint nonlinear refinement of both unknowns (else return the start).
        loss: "linear", or a robust loss applied per pose ("huber", "soft_l1", "cauchy") so
            that a bad pose cannot pull the solution.
        sigma_lateral_m, sigma_depth_m, sigma_rotation_rad: expected 1-sigma noise of one
            ``T_C_RM`` in the camera frame: translation across and along the optical axis (m)
            and rotation (rad). They weight translation against rotation and set the robust
            loss's scale (raised automatically when the residuals show more noise).
        robust_scale: the robust loss's knee, in whitened pose-residual norm.
        backend: where the start comes from, "opencv", "builtin" or "auto" (OpenCV when
            available); see :func:`start_estimate`.
        min_rotation_deg, min_axis_spread_deg: diversity rules, see :func:`check_pose_set`.

    Returns:
        A :class:`HandEyeResult`.

    Raises:
        CalibrationError: malformed or unpaired input, fewer than 3 poses, a pose set
            without enough rotation about two axes, bad weights or options, or no start.
    """
    A, M = _pair(T_B_tcp, T_C_RM)
    n = len(A)
    report = _diversity(A, float(min_rotation_deg), float(min_axis_spread_deg))
    if not report.ok:
        raise CalibrationError(f"T_B_tcp: pose set unsuitable for hand-eye calibration: "
                               f"{report.message}")
    if loss not in LOSSES:
        raise CalibrationError(f"unknown loss {loss!r}; expected one of {', '.join(LOSSES)}")
    sig = np.array([sigma_lateral_m, sigma_lateral_m, sigma_depth_m, sigma_rotation_rad],
                   dtype=float)
    if not np.all(np.isfinite(sig)) or np.any(sig <= 0):
        raise CalibrationError("sigma_lateral_m, sigma_depth_m and sigma_rotation_rad must be "
                               f"positive and finite, got {sig.tolist()}")
    if not (np.isfinite(robust_scale) and robust_scale > 0):
        raise CalibrationError(f"robust_scale must be positive, got {robust_scale!r}")
    if weights is None:
        w = np.ones(n)
    else:
        w = np.asarray(weights, dtype=float)
        if w.shape != (n,) or not np.all(np.isfinite(w)) or np.any(w < 0):
            raise CalibrationError(f"weights: expected {n} finite non-negative values, got "
                                   f"shape {w.shape}")
        if np.count_nonzero(w) < 3:
            raise CalibrationError("weights: at least 3 poses need a positive weight")
    prob = _Problem(A=A, M=M, weights=w,
                    inv_sigma=1.0 / np.array([sig[0], sig[1], sig[2]] + [sig[3]] * 3))

    def objective(X: np.ndarray, Z: np.ndarray) -> float:
        d2 = np.sum(prob.whitened(X, Z) ** 2, axis=1)
        return float(np.sum(robust_scale**2 * _rho(d2 / robust_scale**2, loss)[0]))

    methods = available_methods(backend) if method == "auto" else (method,)
    if method == "auto" and not methods:
        raise CalibrationError(f"no hand-eye method available with backend {backend!r}")
    candidates: dict[str, tuple[np.ndarray, np.ndarray, str, float]] = {}
    failures: dict[str, str] = {}
    for m in methods:
        try:
            X, Z, used = _start(m, A, M, backend)
        except CalibrationError as exc:
            if method != "auto":
                raise
            failures[m] = str(exc)
            continue
        candidates[m] = (X, Z, used, objective(X, Z))
    if not candidates:
        raise CalibrationError("every hand-eye method failed: "
                               + "; ".join(f"{k}: {v}" for k, v in failures.items()))
    start_method = min(candidates, key=lambda k: candidates[k][3])
    X0, Z0, start_backend, _ = candidates[start_method]
    starts = {}
    for m, (X, Z, _, _) in candidates.items():
        mm, deg = _figures(prob, X, Z)
        starts[m] = (_rms(mm), _rms(deg))

    X, Z = X0, Z0
    robust_w = np.ones(n)
    if refine:
        if loss == "linear":
            X, Z = _solve(prob, X0, Z0, robust_scale, loss)
        else:
            # Two passes: the robust scale follows the residual scatter (never below the
            # nominal sigmas), taken first at the start, then at the first solution.
            for _ in range(2):
                c = robust_scale * _scale_factor(prob, X, Z)
                X, Z = _solve(prob, X, Z, c, loss)
            c = robust_scale * _scale_factor(prob, X, Z)
            d2 = np.sum(prob.whitened(X, Z) ** 2, axis=1)
            robust_w = _rho(d2 / c**2, loss)[1]
            suspect = robust_w < DOWNWEIGHT_BELOW
            if np.any(suspect):
                # A non-redescending loss still lets each gross outlier pull with a constant
                # force (about c sigma); once flagged, such poses are left out of a last pass.
                prob = replace(prob, weights=np.where(suspect, 0.0, prob.weights))
                X, Z = _solve(prob, X, Z, c, loss)
                d2 = np.sum(prob.whitened(X, Z) ** 2, axis=1)
                robust_w = np.where(suspect, 0.0, _rho(d2 / c**2, loss)[1])
    inlier = robust_w >= DOWNWEIGHT_BELOW
    cov = _covariance(prob, X, Z, robust_w, inlier)
    # Position of the camera origin under X = exp(xi) X: d t = rho - [t]x omega.
    G = np.hstack([np.eye(3), -_skew(X[:3, 3])])
    cov_t = G @ cov[:6, :6] @ G.T
    cov_w = cov[3:6, 3:6]
    mm, deg = _figures(prob, X, Z)
    mm0, deg0 = _figures(prob, X0, Z0)
    return HandEyeResult(
        T_B_C=X, T_tcp_RM=Z, n_poses=n, residuals_mm=mm, residuals_deg=deg,
        rms_mm=_rms(mm), rms_deg=_rms(deg), start_method=start_method,
        start_backend=start_backend, start_residuals_mm=mm0, start_residuals_deg=deg0,
        start_rms_mm=_rms(mm0), start_rms_deg=_rms(deg0), refined=bool(refine), loss=loss,
        robust_weights=robust_w,
        downweighted=tuple(int(i) for i in np.flatnonzero(~inlier)),
        sigma_T_B_C_mm=float(np.sqrt(np.trace(cov_t)) * 1e3),
        sigma_T_B_C_deg=float(np.rad2deg(np.sqrt(np.trace(cov_w)))),
        sigma_T_B_C_axes_mm=np.sqrt(np.diag(cov_t)) * 1e3,
        sigma_T_B_C_axes_deg=np.rad2deg(np.sqrt(np.diag(cov_w))),
        covariance=cov, starts=starts, start_failures=failures)


# -- pose planning ----------------------------------------------------------------------
def plan_hand_eye_poses(T_B_center: np.ndarray | Sequence, n: int = 30, *,
                        tilt_deg: float = 30.0, spin_deg: float = 15.0,
                        radius_m: float = 0.03, pivot_tcp: np.ndarray | Sequence[float] = (
                            0.0, 0.0, 0.0), seed: int = 0) -> np.ndarray:
    """A deterministic set of ``n`` TCP poses (n, 4, 4), base frame, m, for hand-eye capture.

    Around ``T_B_center`` (4x4, base, m; e.g. the arm's home): pose k is tilted about an axis
    in the TCP's own x-y plane, at azimuths a golden angle (137.5 deg) apart, by 50-100 % of
    ``tilt_deg``, and spun about the TCP's z (the tool axis) by up to +-``spin_deg`` (small,
    so a marker beside the flange keeps facing the camera). Its position lies on a sphere of
    ``radius_m`` about the centre's (a Fibonacci lattice, shuffled). Tilt and spin turn
    about ``pivot_tcp`` (3,, TCP frame, m): put it at the marker (e.g. the nominal
    ``T_tcp_RM`` translation) and the marker stays where the sphere puts it instead of
    swinging on the lever between it and the TCP, which keeps it in the camera's view.
    ``seed`` draws the tilt sizes, spins and shuffle; the same arguments give the same
    poses. The set passes :func:`check_pose_set`, or :class:`CalibrationError` says why it
    cannot.
    """
    try:
        C = nearest_rigid(as_transform(T_B_center, what="T_B_center"))
    except GeometryError as exc:
        raise CalibrationError(str(exc)) from None
    if isinstance(n, bool) or int(n) != n or not 3 <= n <= 1000:
        raise CalibrationError(f"n: expected 3..1000 poses, got {n!r}")
    n = int(n)
    if not (np.isfinite(tilt_deg) and 0 < tilt_deg <= 45):
        raise CalibrationError(f"tilt_deg: expected 0 < tilt <= 45 deg, got {tilt_deg!r}")
    if not (np.isfinite(spin_deg) and 0 <= spin_deg <= 45):
        raise CalibrationError(f"spin_deg: expected 0..45 deg, got {spin_deg!r}")
    if not (np.isfinite(radius_m) and 0 <= radius_m <= 0.2):
        raise CalibrationError(f"radius_m: expected 0..0.2 m, got {radius_m!r}")
    # a copy: Rotation.apply refuses read-only buffers (the cell's geometry arrays are)
    pivot = np.array(pivot_tcp, dtype=float)
    if pivot.shape != (3,) or not np.all(np.isfinite(pivot)) or np.linalg.norm(pivot) > 1.0:
        raise CalibrationError(f"pivot_tcp: expected a finite (3,) point within 1 m of the "
                               f"TCP, got {pivot_tcp!r}")
    rng = np.random.default_rng(seed)
    k = np.arange(n)
    azimuth = k * _GOLDEN + rng.uniform(0.0, 2.0 * np.pi)
    tilt = np.deg2rad(tilt_deg) * rng.uniform(0.5, 1.0, n)
    spin = np.deg2rad(spin_deg) * rng.uniform(-1.0, 1.0, n)
    tilts = Rotation.from_rotvec(tilt[:, None] * np.stack(
        [np.cos(azimuth), np.sin(azimuth), np.zeros(n)], axis=1))
    spins = Rotation.from_rotvec(spin[:, None] * np.array([0.0, 0.0, 1.0]))
    local = tilts * spins                      # turns in the TCP's own frame
    z = 1.0 - 2.0 * (k + 0.5) / n
    ring = np.sqrt(1.0 - z * z)
    sphere = np.stack([ring * np.cos(k * _GOLDEN), ring * np.sin(k * _GOLDEN), z], axis=1)
    shift = radius_m * sphere[rng.permutation(n)]
    # T_B_tcp[k] = T(shift) C T(pivot) local T(-pivot): the turn keeps the pivot in place.
    moved = C[:3, 3] + shift + C[:3, :3] @ pivot
    poses = np.stack([make_transform(C[:3, :3] @ local[i].as_matrix(),
                                     moved[i] - C[:3, :3] @ local[i].apply(pivot))
                      for i in range(n)])
    report = _diversity(poses, MIN_ROTATION_DEG, MIN_AXIS_SPREAD_DEG)
    if not report.ok:
        raise CalibrationError(f"planned poses unsuitable for hand-eye: {report.message}")
    return poses
