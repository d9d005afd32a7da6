"""The needle-tracking bench (issue 7, "tracking speed against accuracy" chart and "where
the filter loses the needle"): a tiny run of ``bench/needle_tracking.py`` writes its JSON
and charts. Each test's docstring names the requirement it checks."""

from __future__ import annotations

import json
import math

import numpy as np

from oralnav.bench import needle_tracking as nt
from oralnav.config.rig import trial_rig


def test_tiny_run_writes_the_tracking_chart(tmp_path):
    """Issue 7, tracking chart: one trial, particles 100 and 300, one value per nuisance.
    The JSON has the particles sweep (time, updates per second, position and orientation
    errors, converged share), the single-camera row, the three failure sweeps and the
    target; every error is finite and every chart file exists."""
    doc = nt.run(tmp_path, quick=True, seed=0, sweep_seeds=1, sweep_frames=3,
                 particles=(100, 300), failure_seeds=1, failure_frames=2,
                 nuisances={"jaw_occlusion": (2.5,), "edge_on": (30.0,),
                            "low_contrast": (40.0,)})
    saved = json.loads((tmp_path / "needle_tracking.json").read_text())
    for key in ("bench", "machine", "sweep", "single_camera", "failures", "target",
                "charts"):
        assert key in saved, key
    assert saved["bench"] == "needle_tracking"
    assert [r["particles"] for r in saved["sweep"]] == [100, 300]
    rows = [*saved["sweep"], saved["single_camera"]]
    for name in ("jaw_occlusion", "edge_on", "low_contrast"):
        assert len(saved["failures"][name]) == 1
        assert {"lost", "target"} <= set(saved["failures"][f"{name}_where"])
        rows += saved["failures"][name]
    for r in rows:
        assert r["updates"] >= 1
        for k in ("update_ms_median", "updates_per_s", "position_mm_median",
                  "angle_deg_median", "init_ms_median", "converged_share"):
            assert r[k] is not None and math.isfinite(r[k]), (k, r[k])
        assert 0.0 <= r["converged_share"] <= 1.0
    # the nuisance measured where it is swept: hidden share, contrast in the image
    jaw = saved["failures"]["jaw_occlusion"][0]
    assert 0.5 < jaw["visible_share_median"] <= 1.0
    low = saved["failures"]["low_contrast"][0]
    assert abs(low["contrast_dn_median"] - 40.0) < 10.0
    for chart in saved["charts"]:
        assert (tmp_path / chart).stat().st_size > 0
    assert doc["sweep"][0]["particles"] == 100


def test_pose_errors_forgive_only_the_twin_in_the_outline_angle():
    """Issue 7, error measure: the error against the truth is the centre distance (mm) and
    the rotation angle (deg); the base/tip twin is 180 degrees off but its outline angle is
    0, and the image error of a pose 1 mm off is a few pixels."""
    scene, _, _ = nt.trial_scene(0, rig=trial_rig())
    nd = scene.needles[0]
    cam = scene.rig[scene.rig.names[0]]
    T = nd.T_ref_needle
    e = nt.pose_errors(T, T, nd.needle, cam)
    assert e["position_mm"] == 0.0 and e["angle_deg"] < 1e-6 and not e["twin"]
    twin = T.copy()
    twin[:3, :3] = T[:3, :3] @ nt._flip(nd.needle)
    e = nt.pose_errors(twin, T, nd.needle, cam)
    assert abs(e["angle_deg"] - 180.0) < 1e-6 and e["outline_angle_deg"] < 1e-6
    assert e["twin"] and e["position_mm"] < 1e-9
    shifted = T.copy()
    shifted[:3, 3] += np.array([0.001, 0.0, 0.0])
    e = nt.pose_errors(shifted, T, nd.needle, cam)
    assert abs(e["position_mm"] - 1.0) < 1e-9 and 2.0 < e["image_px"] < 12.0
