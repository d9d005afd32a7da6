"""Temporal calibration: how late a camera's timestamps are against the arm's clock.

Eq. 5 of the navigation seed chains a tracked robot-marker pose with the TCP pose. The
daemon takes the TCP pose at the frame's capture instant from the arm's measured history
(``control/navigation/arm_trajectory.py``), so a camera whose timestamps are late by
``delta`` (a stamp taken on arrival, a device clock mapped with the transport delay, an
exposure time nobody subtracted) chains each frame with the arm pose ``delta`` later: wrong
by speed x ``delta``.

The arm translates through a small excitation (:func:`excitation`: a smooth 3-D Lissajous
path, the orientation held), so the robot marker moves exactly as the TCP does, seen from
the camera through an unknown fixed rigid transform. For a candidate offset ``delta`` the
arm's positions at ``t_cam - delta`` (linear interpolation of its history) are fitted onto
the tracked marker positions by the best rotation and translation (Kabsch, through
``scipy.spatial.transform.Rotation.align_vectors``); :func:`estimate_time_offset` finds the
``delta`` with the least residual: a 1 ms grid over the search window, then a bounded
scalar refinement. No hand-eye calibration is needed (the fit finds the rotation), so the
offset can be measured before or after it.

Its uncertainty is the Gauss-Newton one: ``sigma^2 = s^2 / sum |R v_i|^2``, with ``s^2`` the
residual variance per coordinate and ``v_i`` the arm's velocity at each frame's instant: a
faster excitation and more frames give a sharper offset. Frames whose residual is far above
the others' (a mis-tracked pose) are left out once, and the fit redone.

Sign: ``offset_s > 0`` means the camera's stamps are *late*; the capture instant on the
arm's clock is ``stamp - offset_s``. Units: seconds and metres inside; the result also
reports ms and mm where named.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize_scalar
from scipy.spatial.transform import Rotation

from oralnav.control.errors import CalibrationError

__all__ = ["MIN_FRAMES", "TemporalFit", "estimate_time_offset", "excitation"]

#: Fewest tracked frames a fit accepts (each gives 3 equations; 7 unknowns).
MIN_FRAMES = 20
#: RMS arm speed (m/s) below which the offset is not observable.
MIN_SPEED = 1e-3
#: A frame whose residual exceeds this many robust sigmas (and 3x the median) is left out.
OUTLIER_SIGMAS = 5.0


@dataclass(frozen=True)
class TemporalFit:
    """The estimated offset and how well it is known.

    Attributes:
        offset_s: how late the camera's stamps are against the arm's clock (s).
        sigma_s: its one-sigma uncertainty (s).
        rms_m: RMS distance between the tracked marker positions and the fitted arm
            positions at the offset (m).
        frames: frames used; ``rejected``: frames left out as outliers.
        speed_rms: RMS arm speed at the frames' instants (m/s).
        R_C_B: the fitted rotation from the arm's base to the camera frame (3x3).
        search_s: the half-width of the window searched (s).
    """

    offset_s: float
    sigma_s: float
    rms_m: float
    frames: int
    rejected: int
    speed_rms: float
    R_C_B: np.ndarray
    search_s: float

    def as_dict(self) -> dict[str, float | int]:
        """JSON-able figures in ms and mm."""
        return {"offset_ms": self.offset_s * 1e3, "sigma_ms": self.sigma_s * 1e3,
                "rms_mm": self.rms_m * 1e3, "frames": self.frames, "rejected": self.rejected,
                "speed_rms_mm_s": self.speed_rms * 1e3, "search_ms": self.search_s * 1e3}


def excitation(t: np.ndarray | float, amplitude: float, period: float, duration: float
               ) -> np.ndarray:
    """The excitation's TCP displacement (m, base frame) at times ``t`` (s from its start):
    ``(..., 3)``. Three sines of 1, 2 and 3 cycles per ``period`` on x, y, z (a Lissajous
    path that is not planar, so the fit's rotation is determined), of peak ``amplitude``
    (m; z half of it), faded in and out over one ``period`` with a raised cosine so the
    path starts and ends at rest, at zero displacement. Zero outside ``[0, duration]``."""
    if not (amplitude > 0 and period > 0 and duration >= 2 * period):
        raise CalibrationError(f"excitation: need amplitude > 0, period > 0 and duration >= "
                               f"2 periods; got {amplitude!r} m, {period!r} s, {duration!r} s")
    t = np.asarray(t, dtype=float)
    ramp = np.clip(np.minimum(t, duration - t) / period, 0.0, 1.0)
    env = 0.5 - 0.5 * np.cos(np.pi * ramp)
    w = 2 * np.pi / period
    d = np.stack([np.sin(w * t), np.sin(2 * w * t + 0.5), 0.5 * np.sin(3 * w * t + 1.0)],
                 axis=-1)
    return amplitude * env[..., None] * d


def _interp(t: np.ndarray, t_arm: np.ndarray, p_B: np.ndarray) -> np.ndarray:
    return np.stack([np.interp(t, t_arm, p_B[:, k]) for k in range(3)], axis=-1)


def _fit(delta: float, t_cam: np.ndarray, p_C: np.ndarray, t_arm: np.ndarray,
         p_B: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """(sum of squared residuals m^2, residuals (N, 3), R_C_B) at offset ``delta``."""
    q = _interp(t_cam - delta, t_arm, p_B)
    qc, pc = q - q.mean(axis=0), p_C - p_C.mean(axis=0)
    rot, _ = Rotation.align_vectors(pc, qc)
    r = pc - rot.apply(qc)
    return float(np.sum(r * r)), r, rot.as_matrix()


def _search(t_cam: np.ndarray, p_C: np.ndarray, t_arm: np.ndarray, p_B: np.ndarray,
            search_s: float, step_s: float) -> float:
    grid = np.arange(-search_s, search_s + step_s / 2, step_s)
    cost = np.array([_fit(d, t_cam, p_C, t_arm, p_B)[0] for d in grid])
    k = int(np.argmin(cost))
    if k == 0 or k == len(grid) - 1:
        raise CalibrationError(
            f"temporal calibration: the best offset is at the edge of the search window "
            f"(+-{search_s * 1e3:.0f} ms); the true offset is larger, or the marker does not "
            "follow the arm (another field tracked, the wrong camera)")
    lo, hi = grid[k] - step_s, grid[k] + step_s
    res = minimize_scalar(lambda d: _fit(d, t_cam, p_C, t_arm, p_B)[0], bounds=(lo, hi),
                          method="bounded", options={"xatol": 1e-6})
    return float(res.x)


def estimate_time_offset(t_cam: np.ndarray, p_C: np.ndarray, t_arm: np.ndarray,
                         p_B: np.ndarray, *, search_s: float = 0.2,
                         step_s: float = 1e-3) -> TemporalFit:
    """The camera's time offset against the arm (see the module docstring).

    Args:
        t_cam: (N,) the tracked frames' stamps (s, the daemon's clock, as published).
        p_C: (N, 3) the robot marker's origin in the camera frame at each (m).
        t_arm: (M,) the arm's measured TCP stamps (s, increasing).
        p_B: (M, 3) the measured TCP positions (m, base frame).
        search_s: offsets searched, ``[-search_s, search_s]`` (s).
        step_s: the grid's step (s) before refinement; finer than the excitation's
            shortest half-period.

    Raises:
        CalibrationError: naming what is wrong: shapes or values, too few frames inside
            the arm history, an arm that barely moved, a best offset at the window's edge.
    """
    t_cam = np.asarray(t_cam, dtype=float)
    p_C = np.asarray(p_C, dtype=float)
    t_arm = np.asarray(t_arm, dtype=float)
    p_B = np.asarray(p_B, dtype=float)
    if t_cam.ndim != 1 or p_C.shape != (len(t_cam), 3):
        raise CalibrationError(f"temporal calibration: frames: need N stamps and (N, 3) "
                               f"positions, got {t_cam.shape} and {p_C.shape}")
    if t_arm.ndim != 1 or p_B.shape != (len(t_arm), 3) or len(t_arm) < 2:
        raise CalibrationError(f"temporal calibration: arm history: need M >= 2 stamps and "
                               f"(M, 3) positions, got {t_arm.shape} and {p_B.shape}")
    for name, a in (("frame stamps", t_cam), ("marker positions", p_C),
                    ("arm stamps", t_arm), ("arm positions", p_B)):
        if not np.all(np.isfinite(a)):
            raise CalibrationError(f"temporal calibration: {name} hold NaN or infinity")
    if np.any(np.diff(t_arm) <= 0):
        raise CalibrationError("temporal calibration: the arm's stamps do not increase")
    if not (search_s > 0 and 0 < step_s < search_s):
        raise CalibrationError(f"temporal calibration: need 0 < step < search window, got "
                               f"{step_s!r} s and {search_s!r} s")
    # only frames the arm history places for every offset searched
    inside = (t_cam - search_s >= t_arm[0]) & (t_cam + search_s <= t_arm[-1])
    if inside.sum() < MIN_FRAMES:
        raise CalibrationError(
            f"temporal calibration: {int(inside.sum())} of {len(t_cam)} frames lie inside "
            f"the arm's history (+-{search_s * 1e3:.0f} ms); need {MIN_FRAMES}")
    t_cam, p_C = t_cam[inside], p_C[inside]
    v_all = np.gradient(p_B, t_arm, axis=0)
    speed = float(np.sqrt(np.mean(np.sum(_interp(t_cam, t_arm, v_all) ** 2, axis=1))))
    if speed < MIN_SPEED:
        raise CalibrationError(
            f"temporal calibration: the arm moved at {speed * 1e3:.2f} mm/s RMS while "
            f"tracked; need at least {MIN_SPEED * 1e3:g} mm/s for the offset to show")
    keep = np.ones(len(t_cam), dtype=bool)
    delta = _search(t_cam, p_C, t_arm, p_B, search_s, step_s)
    # one pass without the frames far off the rest (a mis-tracked pose), then refit
    _, r, _ = _fit(delta, t_cam, p_C, t_arm, p_B)
    dist = np.linalg.norm(r, axis=1)
    med = float(np.median(dist))
    mad = float(np.median(np.abs(dist - med))) * 1.4826
    keep = dist <= max(med + OUTLIER_SIGMAS * mad, 3.0 * med)
    if keep.sum() < MIN_FRAMES:
        raise CalibrationError(f"temporal calibration: only {int(keep.sum())} frames agree "
                               f"with the arm's path; need {MIN_FRAMES}")
    if not keep.all():
        delta = _search(t_cam[keep], p_C[keep], t_arm, p_B, search_s, step_s)
    tc, pc = t_cam[keep], p_C[keep]
    sse, r, R = _fit(delta, tc, pc, t_arm, p_B)
    n = len(tc)
    s2 = sse / max(3 * n - 7, 1)   # 3 rotation, 3 translation, 1 offset
    J = _interp(tc - delta, t_arm, v_all) @ R.T   # d residual / d offset
    sigma = math.sqrt(s2 / float(np.sum(J * J)))
    return TemporalFit(offset_s=delta, sigma_s=sigma, rms_m=math.sqrt(sse / n), frames=n,
                       rejected=int((~keep).sum()), speed_rms=speed, R_C_B=R,
                       search_s=search_s)
