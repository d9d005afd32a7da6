"""Issue 35, item 1 (seed 000's experiments): each runs on tiny sizes, pairs the paper's
figures with ours, writes its charts, and computes its verdict from its targets."""

from __future__ import annotations

import numpy as np
import pytest

from oralnav.bench.report import seed000
from oralnav.bench.report.context import Context

TINY = {"table1_frames": 3, "fig9_frames": 4, "fig11_frames": 3, "fig11_step_deg": 45,
        "table2_trials": 2, "fig13_frames": 4}


@pytest.fixture
def ctx(tmp_path, monkeypatch):
    monkeypatch.setattr(seed000, "QUICK", TINY)
    return Context(quick=True, charts=tmp_path, workers=1)  # no pool beside the suite


def _check(section, ctx):
    d = section.as_dict()
    assert d["rows"] and d["verdict"] in ("met", "missed", "not measured", "shown")
    for name in d["charts"]:
        assert (ctx.charts / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    return d


@pytest.mark.parametrize("exp", seed000.EXPERIMENTS, ids=lambda e: e.key)
def test_experiment_pairs_paper_with_ours(exp, ctx):
    """Every seed-000 experiment gives rows with the paper's figure where the paper has one
    and ours measured (no missing figure on the simulated cell), and a chart."""
    d = _check(exp.run(ctx), ctx)
    assert any(r["paper"] is not None for r in d["rows"])
    assert all(r["verdict"] != "not measured" for r in d["rows"]), d["rows"]
    assert d["charts"]


def test_fig13_verdict_follows_the_measured_time(ctx, monkeypatch):
    """Fig. 13's rows are computed from the timings: a daemon tracker at 20 FPS misses the
    paper's 25.17, one at 50 FPS meets it; an acquisition over 40 ms misses issue 3's
    target (stage timings given, so the rule alone is checked)."""
    from oralnav.bench import navigation

    def timings(ms_full: float, ms_predict: float):
        def fake(frames, opencv_frames, methods):
            part = {"recognition": 1.0, "pose": 1.0, "roi": 0.1}
            return {"results": {
                "nvgba/full": {"median_ms": ms_full, "breakdown_ms": part},
                "nvgba/roi": {"median_ms": 20.0, "breakdown_ms": part},
                "nvgba/predict": {"median_ms": ms_predict, "breakdown_ms": part}}}
        return fake

    monkeypatch.setattr(navigation, "speed_accuracy", timings(58.0, 50.0))
    monkeypatch.setattr(seed000, "_chart_fig13", lambda ctx, key, res: "x.png")
    rows = {r.figure: r for r in seed000.fig13(ctx).rows}
    fps = rows["frames per second, the daemon's default"]
    assert fps.ours == pytest.approx(20.0) and fps.verdict == "missed"
    assert rows["without ROI: total per stereo frame, median"].verdict == "missed"
    monkeypatch.setattr(navigation, "speed_accuracy", timings(30.0, 20.0))
    rows = {r.figure: r for r in seed000.fig13(ctx).rows}
    assert rows["frames per second, the daemon's default"].verdict == "met"
    assert rows["without ROI: total per stereo frame, median"].verdict == "met"


def test_head_motion_is_slow_and_bounded():
    """Fig. 9's head motion: within +-10 deg and +-25 mm of the start, and under 1 mm and
    0.5 deg a frame at 30 Hz (a patient's head, not a jump the ROI could not follow)."""
    T0 = np.eye(4)
    T0[:3, 3] = [0.0, 0.0, 0.215]
    prev = seed000.head_motion(T0, 0)
    for k in range(200):
        T = seed000.head_motion(T0, k)
        ang = np.degrees(np.arccos(np.clip((np.trace(T0[:3, :3].T @ T[:3, :3]) - 1) / 2, -1, 1)))
        assert ang <= 10.5 and np.linalg.norm(T[:3, 3] - T0[:3, 3]) <= 0.025
        step = np.degrees(np.arccos(np.clip((np.trace(prev[:3, :3].T @ T[:3, :3]) - 1) / 2,
                                            -1, 1)))
        assert step <= 0.5 and np.linalg.norm(T[:3, 3] - prev[:3, 3]) <= 0.001
        prev = T
