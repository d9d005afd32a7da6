"""Issue 35, item 3 ("honest verdicts"): a report row's verdict is computed from what was
measured against its target; a missing figure is never met; a section takes the worst of
its rows' verdicts, and a failed experiment says so with its error."""

from __future__ import annotations

import math

import pytest

from oralnav.bench.report.section import Row, Section, Target, section_verdict


def test_row_verdict_follows_the_target():
    """ours <= target is met and above it missed (and the other way round for >=); no
    target is 'shown'."""
    assert Row("t", "mm", 0.69, 0.2, Target("<=", 0.3, "issue 5")).verdict == "met"
    assert Row("t", "mm", 0.69, 0.31, Target("<=", 0.3, "issue 5")).verdict == "missed"
    assert Row("f", "1/s", 25.17, 30.0, Target(">=", 25.17, "paper")).verdict == "met"
    assert Row("f", "1/s", 25.17, 20.0, Target(">=", 25.17, "paper")).verdict == "missed"
    assert Row("x", "mm", 1.0, 0.5).verdict == "shown"


@pytest.mark.parametrize("ours", [None, math.nan, math.inf])
def test_missing_figure_is_not_measured_never_met(ours):
    """A figure the run did not produce is 'not measured', even with a target it would
    trivially 'pass' (None <= 0.3 must not read as met)."""
    row = Row("t", "mm", 0.69, ours, Target("<=", 0.3, "issue 5"))
    assert row.verdict == "not measured"
    assert row.as_dict()["ours"] is None


def test_section_takes_the_worst_row_and_says_which():
    """One missed row makes the section missed, naming the figure, its value and the
    target; a missing row outranks met; an error makes it failed."""
    met = Row("a", "mm", 1.0, 0.1, Target("<=", 1.0, "paper"))
    missed = Row("b", "ms", 40.0, 58.4, Target("<=", 40.0, "issue 3"))
    gone = Row("c", "mm", None, None)
    v, line = section_verdict([met, missed, gone])
    assert v == "missed" and "b = 58.4 ms" in line and "<= 40 ms (issue 3)" in line
    assert "1 of 2 targets met" in line
    assert section_verdict([met, gone])[0] == "not measured"
    assert section_verdict([met])[0] == "met"
    assert section_verdict([Row("x", "mm", 1.0, 2.0)])[0] == "shown"
    assert section_verdict([])[0] == "not measured"
    v, line = section_verdict([met], error="RuntimeError: boom")
    assert v == "failed" and "boom" in line


def test_section_entry_pairs_paper_and_ours():
    """report.json's entry holds "paper", "ours" and "verdict" keyed by figure."""
    s = Section("000/x", "X", "setup", [Row("a", "mm", 1.56, 0.01, Target("<=", 1.56, "paper"))])
    d = s.as_dict()
    assert d["paper"] == {"a": 1.56} and d["ours"] == {"a": 0.01}
    assert d["verdict"] == "met" and d["rows"][0]["target"]["source"] == "paper"


def test_target_refuses_a_bad_operator():
    with pytest.raises(ValueError, match="op"):
        Target("<", 1.0, "paper")  # type: ignore[arg-type]
