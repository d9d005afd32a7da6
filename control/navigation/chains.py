"""Navigation chains and calibration formulas of the navigation seed (sections III.B, III.C).

Pure functions, no I/O. ``T_a_b`` is the 4x4 pose of frame b in frame a (the seed's
``T_b^a``); lengths in metres. Frames as in the seed: base ``B``, camera ``C``, endoscope
``En``, opener marker ``OM``, end-effector ``E``, robot marker ``RM``, end-effector marker
``EM``, end-effector zero ``E0``, arm flange ``J6``, calibration board ``CB``, surgical
instrument tip ``SI`` and suture/implant targets ``tar``.

Every input is validated (shape, finiteness, rigidity) and a :class:`GeometryError` names
the offending argument.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from oralnav.control.errors import GeometryError
from oralnav.control.geometry import (
    as_rotation_matrix,
    as_transform,
    compose,
    invert,
    make_transform,
    transform_points,
)


def _point(p: np.ndarray | Sequence[float], what: str) -> np.ndarray:
    """Return ``p`` as a finite float (3,) point or raise :class:`GeometryError`."""
    p = np.asarray(p, dtype=float)
    if p.shape != (3,):
        raise GeometryError(f"{what}: expected a point of shape (3,), got shape {p.shape}")
    if not np.all(np.isfinite(p)):
        raise GeometryError(f"{what}: point has non-finite entries")
    return p


def _transforms(T: np.ndarray | Sequence, what: str) -> tuple[np.ndarray, bool]:
    """Validate one 4x4 or a stack (N, 4, 4) of rigid transforms.

    Returns the stack (N, 4, 4) and whether the input was a single transform, so callers can
    hand back the shape they were given.
    """
    T = np.asarray(T, dtype=float)
    if T.shape == (4, 4):
        return as_transform(T, what=what)[None], True
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise GeometryError(f"{what}: expected a 4x4 transform or an (N, 4, 4) stack, "
                            f"got shape {T.shape}")
    for i, Ti in enumerate(T):
        as_transform(Ti, what=f"{what}[{i}]")
    return T, False


# -- calibration (section III.B) ---------------------------------------------------------
def opener_endoscope_calibration(T_C_OM: np.ndarray, T_C_CB: np.ndarray,
                                 T_En_CB: np.ndarray) -> np.ndarray:
    """Eq. 2: pose of the endoscope in the opener-marker frame, ``T_OM_En`` (4x4, m).

    ``T_C_OM`` and ``T_C_CB`` are the opener marker and the calibration board seen by the
    stereo camera, ``T_En_CB`` the same board seen by the endoscope, all at one instant.
    From eq. 1, ``T_C_OM T_OM_En T_En_CB = T_C_CB``.
    """
    T_C_OM = as_transform(T_C_OM, what="T_C_OM")
    T_C_CB = as_transform(T_C_CB, what="T_C_CB")
    T_En_CB = as_transform(T_En_CB, what="T_En_CB")
    return compose(invert(T_C_OM), T_C_CB, invert(T_En_CB))


def effector_zero_position(T_C_RM: np.ndarray, p_C_SI: np.ndarray | Sequence[float]) -> np.ndarray:
    """Eq. 3: origin of the end-effector zero frame in the robot-marker frame, ``p_RM_E0`` (3,), m.

    ``p_C_SI`` is the calibrated instrument tip (camera frame, m) held on the end-effector
    origin, so ``p_C_SI = p_C_E0``; ``T_C_RM`` is the robot marker seen at the same instant.
    """
    T_C_RM = as_transform(T_C_RM, what="T_C_RM")
    p_C_SI = _point(p_C_SI, "p_C_SI")
    return transform_points(invert(T_C_RM), p_C_SI[None])[0]


def effector_zero_rotation(R_C_RM: np.ndarray, R_B_C: np.ndarray,
                           R_B_J6: np.ndarray) -> np.ndarray:
    """Eq. 4: orientation of the end-effector zero frame in the robot-marker frame, ``R_RM_E0``.

    ``R_C_RM`` (robot marker seen by the camera), ``R_B_C`` (camera in base) and ``R_B_J6``
    (flange from the arm's kinematics) must be taken in one arm configuration. Returns 3x3.
    """
    R_C_RM = as_rotation_matrix(R_C_RM, what="R_C_RM")
    R_B_C = as_rotation_matrix(R_B_C, what="R_B_C")
    R_B_J6 = as_rotation_matrix(R_B_J6, what="R_B_J6")
    # Eq. 5's rotation block gives R_B_E0 = R_B_C R_C_RM R_RM_E0; eq. 4 sets R_B_E0 = R_B_J6,
    # i.e. it assumes the zero frame's axes are the flange's (R_J6_E0 = I). Solving gives
    # R_RM_E0 = R_C_RM^T R_B_C^T R_B_J6, which is the printed eq. 4 read in the seed's
    # notation ((R_RM^C)^-1 = R_C_RM^T, (R_C^B)^-1 = R_B_C^T): no discrepancy.
    return R_C_RM.T @ R_B_C.T @ R_B_J6


# -- navigation chains (section III.C) ---------------------------------------------------
def extraoral_T_B_E0(T_B_C: np.ndarray, T_C_RM: np.ndarray, R_RM_E0: np.ndarray,
                     p_RM_E0: np.ndarray | Sequence[float]) -> np.ndarray:
    """Eq. 5: pose of the end-effector zero frame in the base, ``T_B_E0`` (4x4, m).

    Extraoral stage: the end-effector is held at zero, so ``E0`` is fixed to the robot marker
    by the calibrated ``R_RM_E0`` (3x3, eq. 4) and ``p_RM_E0`` (3,, m, eq. 3).
    """
    T_B_C = as_transform(T_B_C, what="T_B_C")
    T_C_RM = as_transform(T_C_RM, what="T_C_RM")
    R_RM_E0 = as_rotation_matrix(R_RM_E0, what="R_RM_E0")
    p_RM_E0 = _point(p_RM_E0, "p_RM_E0")
    # Eq. 5's bracket is exactly T_C_RM @ T_RM_E0.
    return compose(T_B_C, T_C_RM, make_transform(R_RM_E0, p_RM_E0))


def intraoral_T_B_E(T_B_C: np.ndarray, T_C_OM: np.ndarray, T_OM_En: np.ndarray,
                    T_En_EM: np.ndarray, T_EM_E: np.ndarray) -> np.ndarray:
    """Eq. 6: pose of the end-effector in the base, ``T_B_E`` (4x4, m), intraoral stage.

    Camera sees the opener marker (``T_C_OM``), the endoscope fixed to the opener
    (``T_OM_En``, eq. 2) sees the end-effector marker (``T_En_EM``); ``T_EM_E`` from eq. 7.
    """
    return compose(as_transform(T_B_C, what="T_B_C"),
                   as_transform(T_C_OM, what="T_C_OM"),
                   as_transform(T_OM_En, what="T_OM_En"),
                   as_transform(T_En_EM, what="T_En_EM"),
                   as_transform(T_EM_E, what="T_EM_E"))


def effector_marker_offset(T_B_C: np.ndarray, T_C_OM: np.ndarray, T_OM_En: np.ndarray,
                           T_En_EM: np.ndarray, T_B_E0: np.ndarray) -> np.ndarray:
    """Eq. 7: pose of the end-effector in the end-effector-marker frame, ``T_EM_E`` (4x4, m).

    Valid only with the end-effector at zero (``E`` coincides with ``E0``) and all inputs taken
    at that instant; ``T_B_E0`` from eq. 5.
    """
    # The seed's text calls this T_EM^E, but its eq. 7 computes T_E^EM (pose of E in EM),
    # which is what eq. 6 needs; the equation is followed.
    T_B_EM = compose(as_transform(T_B_C, what="T_B_C"),
                     as_transform(T_C_OM, what="T_C_OM"),
                     as_transform(T_OM_En, what="T_OM_En"),
                     as_transform(T_En_EM, what="T_En_EM"))
    return compose(invert(T_B_EM), as_transform(T_B_E0, what="T_B_E0"))


def register_targets(T_C_OM: np.ndarray, T_C_tar: np.ndarray) -> np.ndarray:
    """Eq. 8, preoperative half: target poses in the opener-marker frame, ``T_OM_tar``.

    ``T_C_tar`` is one 4x4 target pose or a stack (N, 4, 4) in the camera frame (m), seen
    with the opener marker at ``T_C_OM``. Returns the same shape as ``T_C_tar``.
    """
    T_OM_C = invert(as_transform(T_C_OM, what="T_C_OM"))
    T_C_tar, single = _transforms(T_C_tar, "T_C_tar")
    out = T_OM_C @ T_C_tar
    return out[0] if single else out


def targets_in_base(T_B_C: np.ndarray, T_C_OM: np.ndarray, T_OM_tar: np.ndarray) -> np.ndarray:
    """Eq. 8: target poses in the robot base, ``T_B_tar`` (m), following the opener marker.

    ``T_OM_tar`` is one 4x4 or a stack (N, 4, 4) registered with :func:`register_targets`;
    returns the same shape.
    """
    T_B_OM = compose(as_transform(T_B_C, what="T_B_C"), as_transform(T_C_OM, what="T_C_OM"))
    T_OM_tar, single = _transforms(T_OM_tar, "T_OM_tar")
    out = T_B_OM @ T_OM_tar
    return out[0] if single else out
