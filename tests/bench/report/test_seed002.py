"""Issue 35, item 1 (seed 002's experiments) and its needle target: the needle Monte Carlo
runs on held-out seeds with 95 % intervals, failures by cause and computed verdicts; the
tracker's rate is paired with the paper's 3 FPS and held to issue 7's targets. Each test's
docstring names the requirement it checks.

The Monte Carlo's trials are replaced by a stand-in that records the seeds it is given (a
real trial takes 20-35 s here; ``bench/needle.py``'s trials have their own tests), run in
this process (``workers=1``). The tracker runs for real on one tiny trial."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import pytest

from oralnav.bench import needle
from oralnav.bench.report import seed002
from oralnav.bench.report.context import Context
from oralnav.control.needle.procedure import STEPS

PNG = b"\x89PNG\r\n\x1a\n"


def _record(seed: int, fail_at: str | None, cause: str = "grasp_missed") -> dict:
    """A trial record as ``needle.run_trial`` gives it: the steps up to ``fail_at``
    succeeded, ``fail_at`` failed, the later ones were not run."""
    steps: dict[str, bool | None] = {}
    failure = None
    for st in STEPS:
        if failure is not None:
            steps[st] = None
        elif st == fail_at:
            steps[st] = False
            failure = {"step": st, "cause": cause, "detail": f"stand-in {cause}",
                       "truth": ""}
        else:
            steps[st] = True
    return {"seed": seed, "steps": steps, "failure": failure, "seconds": 1.5, "results": []}


@pytest.fixture
def trials(monkeypatch):
    """A stand-in trial: 1000001 fails at NR (exit missed), 1000002 and 1000003 at NG
    (refused), every other seed succeeds; the seeds it ran are recorded."""
    seen: list[int] = []
    fails = {1000001: ("NR", "exit_missed"), 1000002: ("NG", "refused_not_converged"),
             1000003: ("NG", "refused_not_converged")}

    def fake(seed: int) -> dict:
        seen.append(seed)
        step, cause = fails.get(seed, (None, ""))
        return _record(seed, step, cause)

    monkeypatch.setattr(needle, "run_trial", fake)
    monkeypatch.setitem(seed002.NEEDLE_TRIALS, "quick", 4)
    return seen


@pytest.fixture
def ctx(tmp_path):
    return Context(quick=True, charts=tmp_path, workers=1)


def _rows(section) -> dict[str, dict]:
    return {r["figure"]: r for r in section.as_dict()["rows"]}


def test_needle_tables_run_on_held_out_seeds_with_intervals(trials, ctx):
    """Issue 35 needle target and issue 36's split: the trials are the validation seeds
    from 1,000,000 up, none of the development seeds 0-999, and the section says so;
    every rate has its 95 % Wilson interval (1 of 4 overall: 4.6-69.9 %); failures are
    listed by cause; a step reached by fewer than half the trials is flagged as a
    minority figure; the chart is written."""
    sec = seed002.run_tables(ctx)
    assert trials and sorted(trials) == [1000000, 1000001, 1000002, 1000003]
    assert min(trials) > seed002.DEVELOPED_ON[1]
    d = sec.as_dict()
    assert d["data"]["seeds"] == [1000000, 1000003] and d["data"]["developed_on"] == [0, 999]
    assert "validation seeds 1000000-1000003" in d["setup"] and "0-999" in d["setup"]
    lo, hi = d["data"]["intervals"]["overall"]["overall"]
    assert lo == pytest.approx(0.0456, abs=5e-4) and hi == pytest.approx(0.6994, abs=5e-4)
    rows = _rows(sec)
    overall = rows["overall success (Table II)"]
    assert overall["ours"] == pytest.approx(25.0) and overall["paper"] == pytest.approx(70.0)
    assert "95 % interval 4.6-69.9 %" in overall["note"]
    assert rows["NG success (Table II, of all trials)"]["ours"] == pytest.approx(50.0)
    assert rows["NR success (Table II, of the trials reaching it)"]["ours"] == pytest.approx(50.0)
    assert rows["failures: NG refused_not_converged"]["ours"] == 2
    assert rows["failures: NR exit_missed"]["ours"] == 1
    assert rows["failed trials"]["ours"] == 3
    # NP was reached by 1 trial of 4, NH by 2 (not fewer than half)
    assert rows["NP success (Table II, of the trials reaching it)"]["minority"]
    assert not rows["NH success (Table II, of the trials reaching it)"]["minority"]
    assert rows["time per trial (median)"]["ours"] == pytest.approx(1.5)
    assert d["charts"] and (ctx.charts / d["charts"][0]).read_bytes()[:8] == PNG
    json.dumps(d)


def test_needle_tables_verdicts_are_computed(trials, ctx, monkeypatch):
    """Issue 35 "honest verdicts": the overall rate is held to issue 7's 90 % and, in the
    full report, the trial count to issue 35's 400: with every trial a success the rate is
    met; a full run of 4 trials misses the count (so the section), a quick run only shows
    it; with 1 of 4 a success the rate is missed too."""
    monkeypatch.setattr(needle, "run_trial", lambda seed: _record(seed, None))
    rows = _rows(good := seed002.run_tables(ctx))
    assert rows["overall success (Table II)"]["verdict"] == "met"
    assert rows["overall success (Table II)"]["target"] == {
        "op": ">=", "value": 90.0, "source": "issue 7"}
    assert rows["trials"]["verdict"] == "shown" and good.as_dict()["verdict"] == "met"
    monkeypatch.setitem(seed002.NEEDLE_TRIALS, "full", 4)
    full = seed002.run_tables(replace(ctx, quick=False))
    assert _rows(full)["trials"]["verdict"] == "missed"
    assert full.as_dict()["verdict"] == "missed"
    monkeypatch.setattr(needle, "run_trial",
                        lambda seed: _record(seed, None if seed == 1000000 else "NH"))
    bad = _rows(seed002.run_tables(ctx))
    assert bad["overall success (Table II)"]["verdict"] == "missed"


def test_needle_tables_refuse_the_development_seeds(trials, ctx, monkeypatch):
    """Issue 35 needle target, issue 36's split: a seed range that overlaps the
    development seeds 0-999 is refused before any trial runs."""
    monkeypatch.setattr(seed002, "NEEDLE_SEED", 998)
    with pytest.raises(ValueError, match="0-999"):
        seed002.run_tables(ctx)
    assert trials == []


def test_tracker_rate_pairs_the_paper_fps_with_ours(ctx, monkeypatch):
    """Issue 35 item 1 (the tracker's rate at 3000 particles against the paper's 3 FPS):
    one real trial of 2 updates at 100 and 3000 particles; the rate row carries the paper's
    3 and issue 7's >= 30 target, its verdict follows the measured rate, the accuracy rows
    are held to 0.5 mm and 2 deg, and the chart is written."""
    monkeypatch.setitem(seed002.TRACKER_SIZES, "quick", {
        "seeds": 1, "frames": 3, "particles": (100, 3000), "single_camera": None})
    # in this process: a pool forked after the tracker's OpenMP threads started aborts,
    # and other tests in this process may have started them
    monkeypatch.setattr(seed002, "RATE_WORKERS", 1)
    sec = seed002.run_tracker_rate(ctx)
    rows = _rows(sec)
    rate = rows["tracking updates per second, 3000 particles (predict + update)"]
    assert rate["paper"] == 3.0 and rate["target"]["value"] == 30.0
    assert rate["ours"] is not None and math.isfinite(rate["ours"]) and rate["ours"] > 0
    assert rate["verdict"] == ("met" if rate["ours"] >= 30.0 else "missed")
    pos = rows["position error, 3000 particles (median)"]
    assert pos["target"]["op"] == "<=" and pos["target"]["value"] == 0.5
    assert pos["verdict"] == ("met" if pos["ours"] <= 0.5 else "missed")
    assert rows["orientation error, 3000 particles (median)"]["target"]["value"] == 2.0
    d = sec.as_dict()
    assert [r["particles"] for r in d["data"]["sweep"]] == [100, 3000]
    assert d["data"]["seeds"] == [1000000]
    assert (ctx.charts / d["charts"][0]).read_bytes()[:8] == PNG
    json.dumps(d)


def test_an_interrupted_monte_carlo_resumes_its_trials(tmp_path, ctx, monkeypatch):
    """Issue 35 "bad input" (an interrupted run: what finished is kept; rerunning
    resumes): the report's needle Monte Carlo keeps each finished trial; stopped at its
    third trial, the rerun runs only the trials that had not finished, and the tables
    count every trial once."""
    from oralnav.bench.report.run import Settings, run_report

    seen: list[int] = []

    def stops_at_10002(seed: int) -> dict:
        if seed == 1000002:
            raise KeyboardInterrupt
        seen.append(seed)
        return _record(seed, None)

    monkeypatch.setattr(needle, "run_trial", stops_at_10002)
    exp = next(e for e in seed002.EXPERIMENTS if e.key == "002/tables")
    with pytest.raises(KeyboardInterrupt):
        run_report(tmp_path / "r", [exp], Settings(quick=True, workers=1))
    assert seen == [1000000, 1000001]
    assert sorted(p.name for p in (tmp_path / "r" / "trials" / "002_tables").iterdir()) == [
        "1000000.json", "1000001.json"]

    def fine(seed: int) -> dict:
        seen.append(seed)
        return _record(seed, None)

    monkeypatch.setattr(needle, "run_trial", fine)
    seen.clear()
    doc = run_report(tmp_path / "r", [exp], Settings(quick=True, workers=1))
    n = seed002.NEEDLE_TRIALS["quick"]
    assert seen == list(range(1000002, 1000000 + n))
    ours = doc["experiments"]["002/tables"]["ours"]
    assert ours["trials"] == n and ours["overall success (Table II)"] == 100.0
