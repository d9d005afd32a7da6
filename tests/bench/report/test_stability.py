"""Issue 35, item 1 ("stability where methods fail"): the navigation sweeps mark each
method's breaking point and the needle tracker's loss boundary is found and marked, on
tiny sweeps run in this process (``workers=1``). Each test's docstring names the
requirement it checks."""

from __future__ import annotations

import json

import pytest

from oralnav.bench.report import stability
from oralnav.bench.report.context import Context

PNG = b"\x89PNG\r\n\x1a\n"


@pytest.fixture
def ctx(tmp_path):
    return Context(quick=True, charts=tmp_path, workers=1)


def test_navigation_breaking_points_are_marked(ctx, monkeypatch):
    """Issue 35 stability (navigation): at 80 deg from the cameras no method finds the
    sheet, so every method breaks there (holds to 0 deg) and the chart marks that value
    for each; a fifth of the sheet stained (a one-point sweep) breaks none (holds to
    20 %, "no break"). The rows have no paper figure and no target, so the verdict is
    "shown"."""
    monkeypatch.setitem(stability.NAV_SWEEPS, "quick", {"view_angle_deg": (0, 80),
                                                       "occluded_fraction": (0.2,)})
    monkeypatch.setitem(stability.NAV_FRAMES, "quick", 1)
    sec = stability.run_navigation(ctx)
    d = sec.as_dict()
    methods = d["data"]["methods"]
    rows = {r["figure"]: r for r in d["rows"]}
    assert len(rows) == 2 * len(methods)
    for m in methods:
        angle = rows[f"viewing angle: {m} holds to"]
        assert angle["ours"] == 0 and "breaks at 80 deg" in angle["note"]
        stain = rows[f"sheet occluded: {m} holds to"]
        assert stain["ours"] == pytest.approx(20.0) and "no break" in stain["note"]
        assert angle["paper"] is None and angle["target"] is None
    breaks = {(s, m): v for s, sw in d["data"]["sweeps"].items()
              for m, v in sw["breaks_at"].items() if v is not None}
    assert breaks == {("view_angle_deg", m): 80 for m in methods}
    assert {(k["sweep"], k["method"]): k["value"] for k in d["data"]["chart_marks"]} == breaks
    assert d["verdict"] == "shown"
    assert (ctx.charts / d["charts"][0]).read_bytes()[:8] == PNG
    json.dumps(d)


def test_needle_tracker_loss_boundary_is_found_and_marked(ctx, monkeypatch):
    """Issue 35 stability (the needle tracker's loss boundary): with the wire 4 DN from
    the pad the tracker has nothing to follow, so the low-contrast sweep finds it lost
    there; each nuisance's rows give the last value that holds (from the sweep's own
    boundary) and the chart marks every boundary found."""
    monkeypatch.setitem(stability.TRACKER_SIZES, "quick", {
        "seeds": 1, "frames": 2,
        "values": {"jaw_occlusion": (2.5, 20.0), "edge_on": (0.0, 90.0),
                   "low_contrast": (60.0, 4.0)}})
    sec = stability.run_needle_tracker(ctx)
    d = sec.as_dict()
    where = d["data"]["where"]
    assert where["low_contrast"]["lost"]["fails_from"] == 4.0
    rows = {r["figure"]: r for r in d["rows"]}
    for name, label in (("jaw_occlusion", "jaw width"),
                        ("edge_on", "needle normal to viewing ray"),
                        ("low_contrast", "wire contrast against the pad")):
        assert rows[f"{label}: needle kept up to"]["ours"] == where[name]["lost"]["holds_to"]
        assert rows[f"{label}: target met up to"]["ours"] == where[name]["target"]["holds_to"]
    drawn = {(k["nuisance"], k["what"]): k["value"] for k in d["data"]["chart_marks"]}
    found = {(n, w): where[n][w]["fails_from"] for n in where for w in ("lost", "target")
             if where[n][w]["fails_from"] is not None}
    assert drawn == found and ("low_contrast", "lost") in drawn
    assert d["data"]["seeds"] == [stability.TRACKER_SEED]
    assert (ctx.charts / d["charts"][0]).read_bytes()[:8] == PNG
    json.dumps(d)
