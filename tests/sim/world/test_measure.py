"""Corner-level measurements (issue 5 item 8's noise model): exact corners give the exact
pose through the project's estimator, the pose error grows with the corner noise, and a
field out of view gives no measurement."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from oralnav.config.cell import load_cell_config
from oralnav.control.geometry import invert, pose_error
from oralnav.sim.world.measure import measure_pose, observe

CFG = load_cell_config(Path(__file__).resolve().parents[3] / "config" / "examples"
                       / "sim_cell.toml")
G = CFG.geometry
RIG = CFG.stereo_scene.rig
OPENER = CFG.stereo_scene.placement(CFG.opener).field
T_C_OM = invert(G.T_B_C) @ G.T_B_OM


def test_noise_free_corners_give_the_true_pose():
    est = measure_pose(OPENER, T_C_OM, RIG, 0.0, np.random.default_rng(0))
    dt, dr = pose_error(est.T_ref_field, T_C_OM)
    assert dt < 1e-7 and dr < 1e-7
    assert set(est.cameras) == {"left", "right"}


def test_pose_error_grows_with_corner_noise():
    """RMS position error over 30 draws rises with sigma (0.05 px against 0.5 px)."""
    def rms(sigma: float) -> float:
        rng = np.random.default_rng(1)
        return float(np.sqrt(np.mean([
            pose_error(measure_pose(OPENER, T_C_OM, RIG, sigma, rng).T_ref_field, T_C_OM)[0]
            ** 2 for _ in range(30)])))
    lo, hi = rms(0.05), rms(0.5)
    assert 5 < hi / lo < 20      # linear in sigma up to the draws' scatter
    assert lo < 3e-5             # 0.05 px: about ten micrometres at 0.2 m


def test_only_facing_corners_in_the_image_are_observed():
    """The cylinder's far side is not observed; a field behind the camera not at all."""
    obs = observe(OPENER, T_C_OM, RIG, 0.0, np.random.default_rng(0))
    assert all(0 < len(o.rows) < len(OPENER.corners) for o in obs)
    behind = T_C_OM.copy()
    behind[2, 3] = -0.5
    assert measure_pose(OPENER, behind, RIG, 0.1, np.random.default_rng(0)) is None


def test_estimates_the_tracker_would_refuse_are_not_reported():
    """At 2 px corner noise the reprojection RMS exceeds the tracker's 1 px gate: None."""
    assert measure_pose(OPENER, T_C_OM, RIG, 2.0, np.random.default_rng(0)) is None
