"""The main job's report (issue 32, items 4 and 5: ``oralnav.daemon.demo``): ``--json``'s
top level carries the targets' TRE, the capture-to-command latency with its stages, the
slowest tracking rate and the final state; the text says where the latency went."""

from __future__ import annotations

from oralnav.daemon.demo import demo_summary, print_result

RESULT = {
    "targets": ["stitch_1", "stitch_2"], "tre_mm": {"stitch_1": 0.031}, "state": "READY",
    "done": True, "duration_s": 12.0,
    "rates_hz": {"tracking stereo": 4.0, "tracking endoscope": 3.0, "control": 500.0},
    "latency_ms": {"n": 40, "p50": 120.0, "p99": 180.0, "max": 190.0,
                   "stages": {"delivery": {"n": 50, "p50": 60.0, "p99": 90.0, "max": 95.0},
                              "tracking": {"n": 50, "p50": 40.0, "p99": 70.0, "max": 75.0}}},
}


def test_json_summary_names_each_target_the_latency_stages_and_the_slowest_tracking():
    """Item 4's JSON: a target without truth is null, the latency keeps p50/p99 and each
    stage's p50/p99, tracking_hz is the slowest camera source."""
    doc = demo_summary(RESULT)
    assert doc["targets"] == {"stitch_1": {"tre_mm": 0.031}, "stitch_2": {"tre_mm": None}}
    assert doc["latency_ms"] == {"p50": 120.0, "p99": 180.0,
                                 "stages": {"delivery": {"p50": 60.0, "p99": 90.0},
                                            "tracking": {"p50": 40.0, "p99": 70.0}}}
    assert doc["tracking_hz"] == 3.0 and doc["final_state"] == "READY"
    empty = demo_summary({"targets": [], "state": None})
    assert empty["latency_ms"] == {"p50": None, "p99": None, "stages": {}}
    assert empty["tracking_hz"] is None


def test_text_report_prints_the_latency_and_where_it_went(capsys):
    """The stdout report: the whole latency, then each stage's p50 and p99; before any
    goal (no whole figure) only the stages."""
    print_result(RESULT, "hardware")
    out = capsys.readouterr().out
    assert "latency p50 120.0 ms, p99 180.0 ms over 40 goals (the camera's delivery" in out
    assert "delivery  p50 60.0 ms, p99 90.0 ms over 50 views" in out
    assert "tracking  p50 40.0 ms, p99 70.0 ms" in out
    no_goal = dict(RESULT, latency_ms={"n": 0, "p50": None, "p99": None, "max": None,
                                       "stages": RESULT["latency_ms"]["stages"]})
    print_result(no_goal, "sim")
    out = capsys.readouterr().out
    assert "capture-to-command" not in out and "delivery  p50 60.0 ms" in out
