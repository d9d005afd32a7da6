"""The navigation chain's calibrations from many samples (navigation seed, section III.B).

:mod:`oralnav.control.navigation.chains` holds the seed's formulas for one instant: eq. 2
(``T_OM_En``), eqs. 3-4 (``T_RM_E0``) and eq. 7 (``T_EM_E``). A calibration repeats each
measurement in several configurations and averages the per-sample results on SE(3)
(chordal rotation mean, arithmetic translation mean), rejecting samples that disagree with
the rest, and reports the spread so the operator sees how good it is. Pure functions, no
I/O; metres and radians in, metres and degrees/millimetres in the reports as named.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from oralnav.control.errors import CalibrationError, GeometryError
from oralnav.control.geometry import as_transform, average_poses, make_transform
from oralnav.control.navigation.chains import (
    effector_marker_offset,
    effector_zero_position,
    effector_zero_rotation,
    opener_endoscope_calibration,
)

__all__ = ["AveragedPose", "average_samples", "calibrate_effector_marker",
           "calibrate_effector_zero", "calibrate_endoscope_opener"]

#: Fewest samples a chain calibration accepts: one sample has no spread to report, and
#: with two a bad one cannot be told from a good one.
MIN_SAMPLES = 3
#: Rejection needs this many samples: with fewer, the median absolute deviation is set by
#: one or two samples and would throw out good ones.
MIN_SAMPLES_TO_REJECT = 5
#: A sample farther than this many robust sigmas (1.4826 MAD) from the mean is rejected...
REJECT_SIGMAS = 4.0
#: ...provided it is also farther than these floors, so a tight cluster of good samples
#: does not lose members to round-off (0.05 mm, 0.02 deg).
REJECT_FLOOR_M = 5e-5
REJECT_FLOOR_RAD = np.radians(0.02)
#: The accepted samples must agree within these (max deviation from the mean): beyond,
#: something moved during the calibration (the opener slipped, the tip left the origin).
MAX_SPREAD_M = 2e-3
MAX_SPREAD_RAD = np.radians(1.0)


@dataclass(frozen=True)
class AveragedPose:
    """A calibrated rigid transform from repeated samples.

    Attributes:
        T: the mean transform (4x4, m) over the accepted samples.
        n_samples: samples given; ``used`` (bool per sample) marks those averaged.
        translation_dev_mm, rotation_dev_deg: each sample's deviation from ``T`` (N,).
        translation_spread_mm, rotation_spread_deg: RMS deviation of the used samples.
        translation_sem_mm, rotation_sem_deg: standard error of the mean (RMS / sqrt(n-1)).
    """

    T: np.ndarray
    n_samples: int
    used: np.ndarray
    translation_dev_mm: np.ndarray
    rotation_dev_deg: np.ndarray
    translation_spread_mm: float
    rotation_spread_deg: float
    translation_sem_mm: float
    rotation_sem_deg: float

    @property
    def n_used(self) -> int:
        return int(np.count_nonzero(self.used))

    def report(self) -> dict[str, float | int | list[float]]:
        """Figures for a calibration file's ``[residuals]`` (units in the names)."""
        return {"samples_used": self.n_used,
                "translation_spread_mm": self.translation_spread_mm,
                "rotation_spread_deg": self.rotation_spread_deg,
                "translation_sem_mm": self.translation_sem_mm,
                "rotation_sem_deg": self.rotation_sem_deg,
                "per_sample_translation_mm": self.translation_dev_mm.tolist(),
                "per_sample_rotation_deg": self.rotation_dev_deg.tolist()}


def _deviations(Ts: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-sample translation (m) and rotation (rad) distance from ``T``."""
    dt = np.linalg.norm(Ts[:, :3, 3] - T[:3, 3], axis=1)
    dr = (Rotation.from_matrix(T[:3, :3]).inv()
          * Rotation.from_matrix(Ts[:, :3, :3])).magnitude()
    return dt, dr


def _outliers(d: np.ndarray, floor: float) -> np.ndarray:
    """Deviations beyond ``REJECT_SIGMAS`` robust sigmas of the median and beyond ``floor``."""
    med = np.median(d)
    sigma = 1.4826 * np.median(np.abs(d - med))
    return (d > med + REJECT_SIGMAS * sigma) & (d > floor)


def average_samples(Ts: np.ndarray | Sequence[np.ndarray], what: str, *,
                    min_samples: int = MIN_SAMPLES, reject: bool = True,
                    max_spread_m: float = MAX_SPREAD_M,
                    max_spread_rad: float = MAX_SPREAD_RAD) -> AveragedPose:
    """Average per-sample estimates of one rigid transform, rejecting disagreeing ones.

    Args:
        Ts: (N, 4, 4) per-sample estimates (m).
        what: the transform's name, for messages (``"T_OM_En"``).
        reject: drop samples beyond ``REJECT_SIGMAS`` robust sigmas (and the floors) of the
            rest, once, then re-average (from ``MIN_SAMPLES_TO_REJECT`` samples on).
        max_spread_m, max_spread_rad: refuse when an accepted sample still lies farther
            than these from the mean.

    Raises:
        CalibrationError: fewer than ``min_samples`` (before or after rejection), or
            accepted samples that disagree beyond the spread limits.
    """
    Ts = np.asarray(Ts, dtype=float)
    if Ts.ndim != 3 or Ts.shape[1:] != (4, 4):
        raise CalibrationError(f"{what}: expected (N, 4, 4) samples, got shape {Ts.shape}")
    if len(Ts) < min_samples:
        raise CalibrationError(f"{what}: {len(Ts)} sample(s); at least {min_samples} are needed "
                               "to average and to report a spread")
    used = np.ones(len(Ts), dtype=bool)
    T = average_poses(Ts)
    if reject and len(Ts) >= MIN_SAMPLES_TO_REJECT:
        dt, dr = _deviations(Ts, T)
        used = ~(_outliers(dt, REJECT_FLOOR_M) | _outliers(dr, REJECT_FLOOR_RAD))
        if used.sum() < min_samples:
            raise CalibrationError(f"{what}: only {int(used.sum())} of {len(Ts)} samples agree; "
                                   f"at least {min_samples} must")
        T = average_poses(Ts[used])
    dt, dr = _deviations(Ts, T)
    worst_t, worst_r = dt[used].max(), dr[used].max()
    if worst_t > max_spread_m or worst_r > max_spread_rad:
        i = int(np.argmax(np.where(used, dt / max_spread_m + dr / max_spread_rad, -1.0)))
        raise CalibrationError(
            f"{what}: the samples disagree: sample {i} lies {dt[i] * 1e3:.2f} mm and "
            f"{np.degrees(dr[i]):.2f} deg from the mean (limits {max_spread_m * 1e3:.1f} mm, "
            f"{np.degrees(max_spread_rad):.1f} deg); did something move during the "
            "calibration?")
    n = int(used.sum())
    rms_t = float(np.sqrt(np.mean(dt[used] ** 2)))
    rms_r = float(np.sqrt(np.mean(dr[used] ** 2)))
    return AveragedPose(T=T, n_samples=len(Ts), used=used, translation_dev_mm=dt * 1e3,
                        rotation_dev_deg=np.degrees(dr),
                        translation_spread_mm=rms_t * 1e3,
                        rotation_spread_deg=float(np.degrees(rms_r)),
                        translation_sem_mm=rms_t * 1e3 / np.sqrt(max(n - 1, 1)),
                        rotation_sem_deg=float(np.degrees(rms_r)) / np.sqrt(max(n - 1, 1)))


def _stack(T: np.ndarray | Sequence, what: str, n: int | None = None) -> np.ndarray:
    T = np.asarray(T, dtype=float)
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise CalibrationError(f"{what}: expected (N, 4, 4) transforms, got shape {T.shape}")
    if n is not None and len(T) != n:
        raise CalibrationError(f"{what}: {len(T)} samples, but the other inputs have {n}: "
                               "every sample needs all of its measurements")
    for i, Ti in enumerate(T):
        try:
            as_transform(Ti, what=f"{what}[{i}]")
        except GeometryError as exc:
            raise CalibrationError(str(exc)) from None
    return T


def calibrate_endoscope_opener(T_C_OM: np.ndarray, T_C_CB: np.ndarray, T_En_CB: np.ndarray,
                               **kw) -> AveragedPose:
    """Eqs. 1-2 over N simultaneous views: the endoscope in the opener marker, ``T_OM_En``.

    Sample i: the stereo camera sees the opener marker ``T_C_OM[i]`` and the board
    ``T_C_CB[i]`` while the endoscope sees the same board ``T_En_CB[i]`` (all (N, 4, 4), m).
    Move the board between samples so its pose errors average out. ``kw`` goes to
    :func:`average_samples`.
    """
    a = _stack(T_C_OM, "T_C_OM")
    b = _stack(T_C_CB, "T_C_CB", len(a))
    c = _stack(T_En_CB, "T_En_CB", len(a))
    per = np.stack([opener_endoscope_calibration(*s) for s in zip(a, b, c, strict=True)])
    return average_samples(per, "T_OM_En", **kw)


def calibrate_effector_zero(T_C_RM: np.ndarray, p_C_SI: np.ndarray, T_B_C: np.ndarray,
                            T_B_J6: np.ndarray, **kw) -> AveragedPose:
    """Eqs. 3-4 over N arm configurations: the end-effector zero frame in ``RM``, ``T_RM_E0``.

    Sample i: with the end-effector at zero, a pivot-calibrated pointer's tip touches the
    end-effector origin at ``p_C_SI[i]`` ((N, 3), camera frame, m) while the camera sees
    the robot marker ``T_C_RM[i]`` and the arm reports its flange ``T_B_J6[i]``; ``T_B_C``
    is the hand-eye calibration. Eq. 4 takes the zero frame's axes as the flange's.
    """
    rm = _stack(T_C_RM, "T_C_RM")
    j6 = _stack(T_B_J6, "T_B_J6", len(rm))
    p = np.asarray(p_C_SI, dtype=float)
    if p.shape != (len(rm), 3) or not np.all(np.isfinite(p)):
        raise CalibrationError(f"p_C_SI: expected {len(rm)} finite tip positions (N, 3), got "
                               f"shape {p.shape}" + ("" if np.all(np.isfinite(p))
                                                     else " with non-finite entries"))
    try:
        T_B_C = as_transform(T_B_C, what="T_B_C")
    except GeometryError as exc:
        raise CalibrationError(str(exc)) from None
    per = np.stack([make_transform(effector_zero_rotation(rm[i, :3, :3], T_B_C[:3, :3],
                                                          j6[i, :3, :3]),
                                   effector_zero_position(rm[i], p[i]))
                    for i in range(len(rm))])
    return average_samples(per, "T_RM_E0", **kw)


def calibrate_effector_marker(T_B_C: np.ndarray, T_C_OM: np.ndarray, T_OM_En: np.ndarray,
                              T_En_EM: np.ndarray, T_B_E0: np.ndarray, **kw) -> AveragedPose:
    """Eq. 7 over N samples: the end-effector in its marker's frame, ``T_EM_E``.

    Sample i, end-effector at zero inside the mouth: the camera sees the opener
    ``T_C_OM[i]``, the endoscope the effector marker ``T_En_EM[i]``, and eq. 5 gives
    ``T_B_E0[i]`` from the robot marker at that instant. ``T_B_C`` and ``T_OM_En`` are the
    hand-eye and endoscope calibrations.
    """
    om = _stack(T_C_OM, "T_C_OM")
    em = _stack(T_En_EM, "T_En_EM", len(om))
    e0 = _stack(T_B_E0, "T_B_E0", len(om))
    try:
        T_B_C = as_transform(T_B_C, what="T_B_C")
        T_OM_En = as_transform(T_OM_En, what="T_OM_En")
    except GeometryError as exc:
        raise CalibrationError(str(exc)) from None
    per = np.stack([effector_marker_offset(T_B_C, om[i], T_OM_En, em[i], e0[i])
                    for i in range(len(om))])
    return average_samples(per, "T_EM_E", **kw)
