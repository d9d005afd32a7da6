"""The fake controller's arm: the TCP as a point with an orientation (no joints).

Poses are ``[x, y, z, rx, ry, rz]`` in the robot base frame (m, rotation vector, rad), as
RTDE's ``actual_TCP_pose``; twists are ``[vx, vy, vz, wx, wy, wz]`` in the base frame (m/s,
rad/s), as ``actual_TCP_speed``. The point follows servo targets (first order, time constant
the servoL lookahead, braking in time), ramps to speed twists and decelerates for stops,
within speed and acceleration limits.
"""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = ["TcpPoint", "as_pose6"]


def as_pose6(pose: Iterable[float] | np.ndarray) -> np.ndarray:
    """``pose`` (6 values, or a 4x4 ``T_B_tcp`` with metres) as ``[x, y, z, rx, ry, rz]``."""
    h = np.asarray(pose, dtype=float)
    return (np.concatenate([h[:3, 3], Rotation.from_matrix(h[:3, :3]).as_rotvec()])
            if h.shape == (4, 4) else h.reshape(6))


def _clip_norm(v: np.ndarray, limit: float) -> np.ndarray:
    """``v`` scaled down to norm ``limit`` when longer."""
    n = float(np.linalg.norm(v))
    return v * (limit / n) if n > limit else v


class TcpPoint:
    """The TCP as a point with an orientation, moved by servo targets, twists and stops.

    ``p`` (m) and ``R`` (base <- TCP) are the pose, ``v`` (m/s) and ``w`` (rad/s) the twist,
    all in the base frame. ``mode`` is what moves it: ``hold`` (at rest), ``servo``,
    ``speed`` or ``stop`` (decelerating). Limits: ``vmax`` m/s, ``wmax`` rad/s, ``amax``
    m/s^2, ``alphamax`` rad/s^2.
    """

    def __init__(self, pose6: Iterable[float], max_speed: float, max_angular_speed: float,
                 max_accel: float, max_angular_accel: float) -> None:
        pose6 = np.asarray(list(pose6), dtype=float)
        self.p = pose6[:3].copy()
        self.R = Rotation.from_rotvec(pose6[3:])
        self.v = np.zeros(3)
        self.w = np.zeros(3)
        self.vmax, self.wmax = max_speed, max_angular_speed
        self.amax, self.alphamax = max_accel, max_angular_accel
        self.mode = "hold"
        self.target_p = self.p.copy()
        self.target_R = self.R
        self.tau = 0.1
        self.cmd_v = np.zeros(3)
        self.cmd_w = np.zeros(3)
        self.accel = max_accel
        self.angular_accel = max_angular_accel

    def pose6(self) -> tuple[float, ...]:
        """The pose ``[x, y, z, rx, ry, rz]`` (m, rad)."""
        return (*self.p.tolist(), *self.R.as_rotvec().tolist())

    def target6(self) -> tuple[float, ...]:
        """The servo target while servoing, else the pose (RTDE's ``target_TCP_pose``)."""
        if self.mode == "servo":
            return (*self.target_p.tolist(), *self.target_R.as_rotvec().tolist())
        return self.pose6()

    def twist(self) -> tuple[float, ...]:
        """The twist ``[vx, vy, vz, wx, wy, wz]`` (m/s, rad/s)."""
        return (*self.v.tolist(), *self.w.tolist())

    def set_pose(self, pose6: Iterable[float]) -> None:
        """Put the TCP at ``pose6`` (m, rad), at rest."""
        pose6 = np.asarray(list(pose6), dtype=float)
        self.p = pose6[:3].copy()
        self.R = Rotation.from_rotvec(pose6[3:])
        self.v, self.w, self.mode = np.zeros(3), np.zeros(3), "hold"

    def servo(self, pose6: np.ndarray, lookahead_time: float) -> None:
        """Follow ``pose6`` (m, rad) with time constant ``lookahead_time`` (s, clamped to
        ur_rtde's 0.03 ... 0.2). A non-finite target is ignored."""
        if not np.isfinite(pose6).all():
            return
        self.mode = "servo"
        self.target_p = pose6[:3].copy()
        self.target_R = Rotation.from_rotvec(pose6[3:])
        self.tau = min(max(float(lookahead_time), 0.03), 0.2) if math.isfinite(
            lookahead_time) else 0.1

    def speed(self, twist: np.ndarray, accel: float) -> None:
        """Ramp to ``twist`` (m/s, rad/s; clipped to the limits) at ``accel`` (m/s^2, also
        used as rad/s^2). A non-finite twist is ignored."""
        if not np.isfinite(twist).all():
            return
        self.mode = "speed"
        self.cmd_v = _clip_norm(twist[:3], self.vmax)
        self.cmd_w = _clip_norm(twist[3:], self.wmax)
        accel = float(accel) if math.isfinite(accel) and accel > 0 else self.amax
        self.accel = min(accel, self.amax)
        self.angular_accel = min(accel, self.alphamax)

    def stop(self, decel: float | None = None) -> None:
        """Decelerate to a stand-still at ``decel`` (m/s^2; default the limit)."""
        if self.mode == "hold":
            return
        decel = self.amax if decel is None or not math.isfinite(decel) or decel <= 0 else decel
        self.mode = "stop"
        self.accel = float(decel)
        self.angular_accel = float(decel) * self.alphamax / self.amax

    @property
    def stopped(self) -> bool:
        """At rest (``hold``)."""
        return self.mode == "hold"

    def step(self, h: float) -> None:
        """Advance by ``h`` s."""
        if self.mode == "hold":
            return
        a, alpha = self.amax, self.alphamax
        if self.mode == "servo":
            e = self.target_p - self.p
            d = float(np.linalg.norm(e))
            speed = min(self.vmax, d / max(self.tau, h), math.sqrt(a * d))
            v_set = e * (speed / d) if d > 0 else e
            e_r = (self.target_R * self.R.inv()).as_rotvec()
            d_r = float(np.linalg.norm(e_r))
            w_speed = min(self.wmax, d_r / max(self.tau, h), math.sqrt(alpha * d_r))
            w_set = e_r * (w_speed / d_r) if d_r > 0 else e_r
        elif self.mode == "speed":
            v_set, w_set = self.cmd_v, self.cmd_w
            a, alpha = self.accel, self.angular_accel
        else:  # "stop"
            v_set, w_set = np.zeros(3), np.zeros(3)
            a, alpha = self.accel, self.angular_accel
        self.v = self.v + _clip_norm(v_set - self.v, a * h)
        self.w = self.w + _clip_norm(w_set - self.w, alpha * h)
        self.p = self.p + self.v * h
        if np.any(self.w):
            self.R = Rotation.from_rotvec(self.w * h) * self.R
        if self.mode == "stop" and not np.any(self.v) and not np.any(self.w):
            self.mode = "hold"
