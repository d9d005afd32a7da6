"""Straight-line, speed-limited motion between poses, fast enough for a 500 Hz loop.

The control loop steps its servo setpoint toward a goal every 2 ms: the translation along
the straight line, the rotation along the geodesic (constant axis), both by the same
fraction so they arrive together. SciPy's ``Rotation``/``Slerp`` do this exactly but cost
0.7 ms per step on the robot PC class of machine (object construction and array-API
dispatch on single rotations), a third of the period; ``oralnav bench control`` measures
both. Here the same geodesic is computed on plain 3x3 matrices with the Rodrigues formula
(log and exp of SO(3)) in about 25 us; ``tests/control/test_motion.py`` checks it against
SciPy's Slerp. No quaternions: only the rotation matrix and its rotation vector.
"""

from __future__ import annotations

import math

import numpy as np

#: Below this angle (rad) the log/exp series replace the closed forms (no 0/0).
_SMALL = 1e-6


def rotation_log(R: np.ndarray) -> np.ndarray:
    """Rotation vector (axis * angle, rad) of the 3x3 rotation ``R``; angle in [0, pi]."""
    c = max(-1.0, min(1.0, 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)))
    angle = math.acos(c)
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if angle < _SMALL:
        return 0.5 * w  # sin(a) ~ a: the skew part is the vector itself
    if math.pi - angle < 1e-4:
        # Near pi the skew part vanishes; read the axis off the symmetric part instead:
        # (R + R^T) / 2 - c I = (1 - c) a a^T.
        B = 0.5 * (R + R.T) - c * np.eye(3)
        k = int(np.argmax(np.diag(B)))
        axis = B[:, k] / math.sqrt(max((1.0 - c) * B[k, k], 1e-300))
        if axis @ w < 0:  # keep the sign the (small) skew part still shows
            axis = -axis
        return axis * angle
    return w * (angle / (2.0 * math.sin(angle)))


def _skew(v: np.ndarray) -> np.ndarray:
    """The cross-product matrix of the 3-vector ``v``."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def rotation_exp(v: np.ndarray) -> np.ndarray:
    """3x3 rotation of the rotation vector ``v`` (rad)."""
    angle = math.sqrt(float(v @ v))
    K = _skew(v)
    if angle < _SMALL:
        return np.eye(3) + K + 0.5 * (K @ K)
    return (np.eye(3) + (math.sin(angle) / angle) * K
            + ((1.0 - math.cos(angle)) / (angle * angle)) * (K @ K))


def geodesic(R0: np.ndarray, R1: np.ndarray, f: np.ndarray) -> np.ndarray:
    """The rotations a fraction ``f`` (n,) of the way along the geodesic from ``R0`` to
    ``R1`` (3x3 each): ``R0 exp(f log(R0^T R1))``, (n, 3, 3); what SciPy's ``Slerp``
    between the two gives, for all fractions at once on one axis (a planner checks
    paths of tens of poses thousands of times a trial, and Slerp's objects cost more
    than the path)."""
    f = np.asarray(f, dtype=float).reshape(-1)
    v = rotation_log(R0.T @ R1)
    angle = math.sqrt(float(v @ v))
    if angle < _SMALL:
        K = _skew(v)
        E = np.eye(3) + f[:, None, None] * K + (0.5 * f * f)[:, None, None] * (K @ K)
    else:
        K = _skew(v / angle)
        a = f * angle
        E = (np.eye(3) + np.sin(a)[:, None, None] * K
             + (1.0 - np.cos(a))[:, None, None] * (K @ K))
    return R0 @ E


def step_toward(T_current: np.ndarray, T_goal: np.ndarray, max_distance: float,
                max_angle: float) -> tuple[np.ndarray, float]:
    """The pose a fraction ``s`` of the way from ``T_current`` to ``T_goal`` (4x4, same
    frame, m), with ``s`` the largest value <= 1 that moves at most ``max_distance`` (m)
    and turns at most ``max_angle`` (rad). Returns the pose and ``s``.

    Translation is linear and rotation geodesic, both by ``s``; at ``s = 1`` the goal
    itself (a copy) comes back, so a setpoint that reaches its goal stays exactly on it.
    """
    dp = T_goal[:3, 3] - T_current[:3, 3]
    R_c = T_current[:3, :3]
    v = rotation_log(T_goal[:3, :3] @ R_c.T)
    dist = math.sqrt(float(dp @ dp))
    angle = math.sqrt(float(v @ v))
    s = 1.0
    if dist > 0.0:
        s = min(s, max_distance / dist)
    if angle > 0.0:
        s = min(s, max_angle / angle)
    if s >= 1.0 - 1e-9:  # within a billionth of a step: land on the goal, no sliver step
        return T_goal.copy(), 1.0
    out = np.eye(4)
    out[:3, :3] = rotation_exp(s * v) @ R_c
    out[:3, 3] = T_current[:3, 3] + s * dp
    return out, s
