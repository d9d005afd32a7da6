"""Chain calibrations from many samples (issue 5 items 2 and 4): eqs. 1-2 (endoscope to
opener), 3-4 (end-effector zero) and 7 (end-effector marker), averaged on SE(3) with the
spread reported, recover the simulated cell's true geometry; disagreeing samples are
rejected and degenerate input is refused with a clear error."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from oralnav.config.cell import load_cell_config
from oralnav.control.calibration.chain import (
    average_samples,
    calibrate_effector_marker,
    calibrate_effector_zero,
    calibrate_endoscope_opener,
)
from oralnav.control.errors import CalibrationError
from oralnav.control.geometry import exp, invert, pose_error, transform_from_euler

CELL = Path(__file__).resolve().parents[3] / "config" / "examples" / "sim_cell.toml"
G = load_cell_config(CELL).geometry

#: Per-sample pose noise of a tracked field: ~0.05 mm lateral, 0.15 mm along the optical
#: axis (z of the observing camera), 0.03 deg; drawn in the observing camera's frame.
SIGMA_T = np.array([0.05e-3, 0.05e-3, 0.15e-3])
SIGMA_R = np.radians(0.03)


def _err(T: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """Translation (mm) and rotation (deg) error."""
    dt, dr = pose_error(T, T_true)
    return dt * 1e3, float(np.degrees(dr))


def _noisy(T_cam_x: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """``T_cam_x`` as a tracker reports it: perturbed in the camera frame."""
    xi = np.r_[rng.normal(0, SIGMA_T), rng.normal(0, SIGMA_R, 3)]
    return exp(xi) @ T_cam_x


def _boards(n: int, rng: np.random.Generator) -> np.ndarray:
    """Board poses in OM: in front of the opener, seen by the camera and the endoscope."""
    T_OM_En = G.T_OM_En
    out = []
    for _ in range(n):
        T_En_CB = transform_from_euler([rng.uniform(-0.01, 0.01), rng.uniform(-0.01, 0.01),
                                        rng.uniform(0.04, 0.06)],
                                       rng.uniform(-20, 20, 3) + [180, 0, 0])
        out.append(T_OM_En @ T_En_CB)
    return np.stack(out)


def _opener_views(n: int, rng: np.random.Generator) -> tuple[np.ndarray, ...]:
    """``n`` noisy simultaneous views ``(T_C_OM, T_C_CB, T_En_CB)`` of boards before the
    endoscope, the opener in its place in the cell."""
    T_C_OM_true = invert(G.T_B_C) @ G.T_B_OM
    T_OM_CB = _boards(n, rng)
    return (np.stack([_noisy(T_C_OM_true, rng) for _ in T_OM_CB]),
            np.stack([_noisy(T_C_OM_true @ b, rng) for b in T_OM_CB]),
            np.stack([_noisy(invert(G.T_OM_En) @ b, rng) for b in T_OM_CB]))


def test_endoscope_to_opener_recovers_the_truth_with_its_spread():
    """Eq. 2 averaged over 20 noisy simultaneous views lands within 0.1 mm and 0.05 deg of
    the true T_OM_En; the reported spread matches the per-sample scatter."""
    res = calibrate_endoscope_opener(*_opener_views(20, np.random.default_rng(1)))
    dt_mm, dr_deg = _err(res.T, G.T_OM_En)
    assert res.n_used == 20
    assert dt_mm < 0.1 and dr_deg < 0.05, (dt_mm, dr_deg)
    assert 0.0 < res.translation_sem_mm < res.translation_spread_mm < 2.0
    assert len(res.translation_dev_mm) == 20
    # the spread comes from the stereo rotation error levered over the opener-to-board
    # distance, so it is larger than the raw position noise; the mean still is within
    assert res.report()["samples_used"] == 20


def test_a_moved_sample_is_rejected_and_reported():
    """A view where the board slipped between the cameras' exposures (2 mm) is left out."""
    T_C_OM, T_C_CB, T_En_CB = _opener_views(12, np.random.default_rng(2))
    T_C_CB[5][:3, 3] += [0.002, 0.0, 0.0]
    res = calibrate_endoscope_opener(T_C_OM, T_C_CB, T_En_CB)
    assert not res.used[5] and res.used.sum() == 11
    assert _err(res.T, G.T_OM_En)[0] < 0.15


def test_effector_zero_recovers_T_RM_E0():
    """Eqs. 3-4 over 10 arm configurations (pointer tip noise 0.1 mm) recover T_RM_E0
    within 0.1 mm and 0.05 deg; eq. 4 needs the flange from the arm and T_B_C."""
    rng = np.random.default_rng(3)
    T_RM_E0 = invert(G.T_tcp_RM) @ G.T_tcp_E0
    T_C_RM, p_C_SI, T_B_J6 = [], [], []
    for _ in range(10):
        T_B_tcp = transform_from_euler([0.4 + rng.uniform(-0.03, 0.03),
                                        rng.uniform(-0.03, 0.03), 0.3],
                                       [180 + rng.uniform(-15, 15), rng.uniform(-15, 15),
                                        rng.uniform(-30, 30)])
        T_C_RM_true = invert(G.T_B_C) @ T_B_tcp @ G.T_tcp_RM
        T_C_RM.append(_noisy(T_C_RM_true, rng))
        p_C_SI.append((T_C_RM_true @ T_RM_E0)[:3, 3] + rng.normal(0, 0.1e-3, 3))
        T_B_J6.append(T_B_tcp)
    res = calibrate_effector_zero(np.stack(T_C_RM), np.stack(p_C_SI), G.T_B_C,
                                  np.stack(T_B_J6))
    dt_mm, dr_deg = _err(res.T, T_RM_E0)
    assert dt_mm < 0.1 and dr_deg < 0.05, (dt_mm, dr_deg)


def test_effector_marker_recovers_T_EM_E():
    """Eq. 7 over 10 intra-oral samples at zero recovers T_EM_E within 0.1 mm and 0.1 deg
    given exact upstream calibrations (the chain budget in bench/calibration.py adds theirs)."""
    rng = np.random.default_rng(4)
    T_C_OM_true = invert(G.T_B_C) @ G.T_B_OM
    T_C_OM, T_En_EM, T_B_E0 = [], [], []
    base = load_cell_config(CELL).intraoral_T_B_tcp
    for _ in range(10):
        T_B_tcp = base @ transform_from_euler(rng.uniform(-0.002, 0.002, 3),
                                              rng.uniform(-5, 5, 3))
        E0 = T_B_tcp @ G.T_tcp_E0
        T_C_OM.append(_noisy(T_C_OM_true, rng))
        T_En_EM.append(_noisy(invert(G.T_B_En) @ E0 @ G.T_E_EM, rng))
        T_B_E0.append(exp(np.r_[rng.normal(0, 0.05e-3, 3), rng.normal(0, SIGMA_R, 3)]) @ E0)
    res = calibrate_effector_marker(G.T_B_C, np.stack(T_C_OM), G.T_OM_En, np.stack(T_En_EM),
                                    np.stack(T_B_E0))
    dt_mm, dr_deg = _err(res.T, invert(G.T_E_EM))
    assert dt_mm < 0.1 and dr_deg < 0.1, (dt_mm, dr_deg)


def test_too_few_samples_are_refused():
    """Bad input: two samples cannot report a spread or reject a bad one."""
    with pytest.raises(CalibrationError, match="at least 3"):
        average_samples(np.stack([np.eye(4)] * 2), "T_OM_En")


def test_samples_that_disagree_are_refused():
    """Bad input: samples split into two clusters 5 mm apart (the opener moved half-way)
    cannot be averaged; the error says something moved."""
    a = [np.eye(4)] * 4
    b = [transform_from_euler([0.005, 0, 0], [0, 0, 0])] * 4
    with pytest.raises(CalibrationError, match="did something move"):
        average_samples(np.stack(a + b), "T_OM_En")


def test_mismatched_and_non_rigid_inputs_are_named():
    """Bad input: sample counts that differ, and a non-rigid transform, name the input."""
    eye = np.stack([np.eye(4)] * 4)
    with pytest.raises(CalibrationError, match="T_C_CB: 3 samples"):
        calibrate_endoscope_opener(eye, eye[:3], eye)
    bad = eye.copy()
    bad[2, :3, :3] *= 2.0
    with pytest.raises(CalibrationError, match=r"T_En_CB\[2\]"):
        calibrate_endoscope_opener(eye, eye, bad)
    with pytest.raises(CalibrationError, match="p_C_SI"):
        calibrate_effector_zero(eye, np.full((4, 3), np.nan), np.eye(4), eye)
