"""Issue 35, item 1 and "bad input": the report's run writes a self-contained index.html
and a strict report.json, turns a failing experiment into its section while the rest is
written, resumes an interrupted run, and refuses an output folder holding anything else
unless forced."""

from __future__ import annotations

import json
import math

import pytest

from oralnav.bench.report.charts import plt, save
from oralnav.bench.report.context import Context, Experiment
from oralnav.bench.report.run import ReportError, Settings, run_report
from oralnav.bench.report.section import Row, Section, Target

CALLS: list[str] = []


def _ok(ctx: Context) -> Section:
    CALLS.append("ok")
    p = plt()
    fig, ax = p.subplots()
    ax.plot([0, 1], [0, 1])
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    name = save(fig, ctx.chart("t/ok", "line"))
    row = Row("a", "mm", 1.0, 0.5, Target("<=", 1.0, "paper"))
    return Section("t/ok", "fine", "a setup", [row], [name],
                   data={"nan": math.nan, "list": [1.0, math.inf]})


def _boom(ctx: Context) -> Section:
    CALLS.append("boom")
    raise RuntimeError("the renderer broke")


def _stop(ctx: Context) -> Section:
    CALLS.append("stop")
    raise KeyboardInterrupt


OK = Experiment("t/ok", "fine", _ok, (1.0, 2.0))
BOOM = Experiment("t/boom", "breaks", _boom, (1.0, 2.0))
STOP = Experiment("t/stop", "interrupted", _stop, (1.0, 2.0))


@pytest.fixture(autouse=True)
def _clear():
    CALLS.clear()


def test_report_written_with_a_failed_section(tmp_path):
    """A failing experiment's section names its error; the others are still written; the
    page embeds its charts (opens offline) and report.json is strict JSON."""
    lines: list[str] = []
    doc = run_report(tmp_path / "r", [BOOM, OK], Settings(quick=True), say=lines.append)
    assert doc["complete"] and CALLS == ["boom", "ok"]
    e = doc["experiments"]
    assert e["t/boom"]["verdict"] == "failed" and "the renderer broke" in e["t/boom"]["error"]
    assert e["t/ok"]["verdict"] == "met" and e["t/ok"]["paper"] == {"a": 1.0}
    text = (tmp_path / "r" / "report.json").read_text()
    back = json.loads(text, parse_constant=lambda c: pytest.fail(f"non-JSON constant {c}"))
    assert back["experiments"]["t/ok"]["data"] == {"nan": None, "list": [1.0, None]}
    assert back["commit"] and back["machine"]["cpus"] and back["settings"]["quick"] is True
    page = (tmp_path / "r" / "index.html").read_text()
    assert "data:image/png;base64," in page and "the renderer broke" in page
    assert "src='http" not in page and "<script" not in page
    assert any("min left" in line for line in lines)


def test_interrupted_run_resumes(tmp_path):
    """Ctrl-C keeps what finished; the same settings resume without rerunning it; other
    settings are refused (their figures would not be comparable)."""
    out = tmp_path / "r"
    with pytest.raises(KeyboardInterrupt):
        run_report(out, [OK, STOP], Settings(quick=True))
    doc = json.loads((out / "report.json").read_text())
    assert doc["complete"] is False and list(doc["experiments"]) == ["t/ok"]
    assert "not run yet" in (out / "index.html").read_text()
    with pytest.raises(ReportError, match="cannot resume"):
        run_report(out, [OK, BOOM], Settings(quick=False))
    CALLS.clear()
    doc = run_report(out, [OK, BOOM], Settings(quick=True))
    assert CALLS == ["boom"] and doc["complete"]
    assert set(doc["experiments"]) == {"t/ok", "t/boom"}


def test_existing_folder_refused_unless_forced(tmp_path):
    """A finished report or a folder of other files is not written over without --force;
    --force replaces only the report's own files."""
    out = tmp_path / "r"
    run_report(out, [OK], Settings(quick=True))
    with pytest.raises(ReportError, match="finished report.*--force"):
        run_report(out, [OK], Settings(quick=True))
    (out / "notes.txt").write_text("mine")
    run_report(out, [OK], Settings(quick=True), force=True)
    assert (out / "notes.txt").read_text() == "mine"
    other = tmp_path / "other"
    other.mkdir()
    (other / "x.txt").write_text("x")
    with pytest.raises(ReportError, match="holds no report"):
        run_report(other, [OK], Settings(quick=True))
