"""Issue 36 item 2: the needle Monte Carlo's seed ranges. Changes are developed on seeds
0-999, success is reported on the validation range from 1,000,000 (400 trials), and each
run says which range its seeds lie in, with the 95 % interval of its overall success.
The trials are stand-ins here (the procedure's own tests run it)."""

from __future__ import annotations

import json
import math

import pytest

from oralnav.bench import needle


def test_seed_ranges_are_named():
    """A range within 0-999 is development, one from 1,000,000 validation, one reaching
    into the development seeds and past them mixed, and any other held out."""
    assert needle.seed_split(0, 199) == "development"
    assert needle.seed_split(990, 999) == "development"
    assert needle.seed_split(990, 1009) == "mixed"
    assert needle.seed_split(1_000_000, 1_000_399) == "validation"
    assert needle.seed_split(10_000, 10_199) == "held out"


@pytest.fixture
def stand_in(monkeypatch):
    """Trials that succeed on even seeds and fail NG on odd ones; seeds run recorded."""
    seen: list[int] = []

    def trial(seed: int) -> dict:
        seen.append(seed)
        ok = seed % 2 == 0
        steps = {s: ok for s in ("NG", "NH", "ND", "NR", "NP")}
        failure = None if ok else {"step": "NG", "cause": "refused_not_converged",
                                   "detail": "stand-in", "truth": ""}
        if not ok:
            steps.update({s: None for s in ("NH", "ND", "NR", "NP")})
        return {"seed": seed, "steps": steps, "failure": failure, "seconds": 0.1,
                "results": []}

    monkeypatch.setattr(needle, "run_trial", trial)
    return seen


def test_validation_runs_400_trials_from_the_validation_seed(stand_in, tmp_path, capsys):
    """`main(validation=True)` runs VALIDATION_TRIALS trials from VALIDATION_SEED, and
    needle.json says the split and the Wilson interval of the overall success (200 of 400:
    45.1-54.9 %)."""
    doc = needle.main(tmp_path, validation=True, workers=1)
    assert stand_in == list(range(1_000_000, 1_000_400))
    saved = json.loads((tmp_path / "needle.json").read_text())
    assert saved["split"] == doc["split"] == "validation"
    assert saved["overall"] == pytest.approx(0.5)
    lo, hi = saved["overall_interval"]
    assert lo == pytest.approx(0.4510, abs=5e-4) and hi == pytest.approx(0.5490, abs=5e-4)
    assert "validation seeds 1000000-1000399" in capsys.readouterr().err


def test_a_development_run_says_so(stand_in, tmp_path, capsys):
    """A run on seeds 0-3 is named development, on stderr and in needle.json."""
    doc = needle.main(tmp_path, trials=4, seed=0, workers=1)
    assert stand_in == [0, 1, 2, 3] and doc["split"] == "development"
    assert "development seeds 0-3" in capsys.readouterr().err


def test_an_arm_error_reaches_every_trial_and_is_recorded(monkeypatch, tmp_path, capsys):
    """Issue 36, trials with arm errors: ``arm_error`` (mm, deg) reaches each trial (here on
    a two-process pool, so the trial function with it must cross to the workers), the
    summary and stderr say it, and a stored record of other settings is run again rather
    than kept."""
    store = tmp_path / "store"
    store.mkdir()
    (store / "0.json").write_text(json.dumps({"seed": 0, "steps": {}, "failure": None,
                                              "seconds": 0.1, "results": []}))
    monkeypatch.setattr(needle, "run_trial", _recording_trial)
    doc = needle.run(2, 0, workers=2, progress=False, store=store, arm_error=(2.0, 1.0))
    assert doc["arm_error"] == {"mm": 2.0, "deg": 1.0}
    assert [r["arm_error"] for r in doc["records"]] == [{"mm": 2.0, "deg": 1.0}] * 2
    kept = needle.run(2, 0, workers=1, progress=False, store=store, arm_error=(2.0, 1.0))
    assert [r["seconds"] for r in kept["records"]] == [r["seconds"] for r in doc["records"]]
    with pytest.raises(ValueError, match="finite values >= 0"):
        needle.run(1, 0, workers=1, progress=False, arm_error=(-1.0, 0.0))
    needle.main(tmp_path, trials=1, seed=0, workers=1, arm_error=(2.0, 1.0))
    assert "with 2 mm / 1 deg arm errors" in capsys.readouterr().err


def _recording_trial(seed: int, arm_error=None, servo: bool = False,
                     stream: bool = False) -> dict:
    """A stand-in trial (module level: it crosses to pool workers) that records the arm
    error and the servo setting it was given, the way run_trial does."""
    import os

    steps = dict.fromkeys(("NG", "NH", "ND", "NR", "NP"), True)
    rec = {"seed": seed, "steps": steps, "failure": None, "seconds": float(os.getpid()),
           "results": []}
    if arm_error is not None:
        rec["arm_error"] = {"mm": arm_error[0], "deg": arm_error[1]}
    if servo:
        rec["servo"] = True
    if stream:
        rec["stream"] = True
        rec["results"] = [{"step": "ND", "figures": {
            "servo_rate_hz": 10.0 + seed, "servo_latency_ms": [40.0, 50.0 + seed],
            "servo_command_ms": [1.0, 1.0],
            "servo_prepare_ms": [10.0, 12.0], "servo_track_ms": [20.0, 30.0]}}]
    return rec


def test_a_servoed_run_reaches_every_trial_and_is_recorded(monkeypatch, tmp_path, capsys):
    """Issue 36 item 1 (open-loop and servoed side by side): ``servo`` reaches each trial
    on a two-process pool, the summary, the records and stderr say it, and records of an
    open-loop run are run again rather than kept, and the other way round."""
    store = tmp_path / "store"
    monkeypatch.setattr(needle, "run_trial", _recording_trial)
    open_loop = needle.run(2, 0, workers=2, progress=False, store=store)
    assert open_loop["servo"] is False and all("servo" not in r for r in open_loop["records"])
    doc = needle.run(2, 0, workers=2, progress=False, store=store, servo=True)
    assert doc["servo"] is True and [r.get("servo") for r in doc["records"]] == [True, True]
    kept = needle.run(2, 0, workers=1, progress=False, store=store, servo=True)
    assert [r["seconds"] for r in kept["records"]] == [r["seconds"] for r in doc["records"]]
    again = needle.run(2, 0, workers=1, progress=False, store=store)
    assert all("servo" not in r for r in again["records"])
    needle.main(tmp_path, trials=1, seed=0, workers=1, servo=True)
    assert "the drive servoed" in capsys.readouterr().err


def test_a_streamed_run_is_recorded_and_sums_up_its_rate_and_latency(monkeypatch, tmp_path,
                                                                     capsys):
    """Issue 36 item 1 (the servo fed by a tracking task): ``stream`` reaches each trial
    with the servo, records say it and only streamed records are kept for a streamed
    run; the summary pools every command's latency and every frame's work, and the rate
    the slower stage allows (they overlap); stderr prints them."""
    store = tmp_path / "store"
    monkeypatch.setattr(needle, "run_trial", _recording_trial)
    looks = needle.run(2, 0, workers=1, progress=False, store=store, servo=True)
    assert "stream" not in looks
    doc = needle.run(2, 0, workers=2, progress=False, store=store, servo=True, stream=True)
    assert [r.get("stream") for r in doc["records"]] == [True, True]
    st = doc["stream"]
    assert st["commands"] == 4 and st["drives"] == 2
    assert st["rate_hz"] == {"p50": 10.5, "min": 10.0}
    assert st["latency_ms"]["max"] == 51.0
    assert st["frame_ms"]["tracking"]["p50"] == 25.0
    assert st["tracking_capacity_hz"] == 40.0        # 1000 / the slower stage's 25 ms
    needle.main(tmp_path, trials=1, seed=0, workers=1, servo=True, stream=True)
    err = capsys.readouterr().err
    assert "from a tracking task" in err and "streamed servo:" in err


def _difficulty_trial(seed: int, arm_error=None, servo: bool = False,
                      difficulty: float = 1.0, stream: bool = False) -> dict:
    """A stand-in trial: the open-loop procedure fails the drive above difficulty 1 (the
    first failure undetected on even seeds), the servoed one never; both record what
    they were given, as run_trial does."""
    ok = servo or difficulty <= 1.0
    steps = {s: ok for s in ("NG", "NH", "ND", "NR", "NP")}
    failure = None
    if not ok:
        steps.update(ND=False, NR=None, NP=None)
        failure = {"step": "ND", "cause": "undetected" if seed % 2 == 0 else "exit_missed",
                   "detail": "stand-in", "truth": ""}
    rec = {"seed": seed, "steps": steps, "failure": failure, "seconds": 0.1, "results": []}
    if servo:
        rec["servo"] = True
    if stream:
        rec["stream"] = True
    if difficulty != 1.0:
        rec["difficulty"] = difficulty
    if arm_error is not None:
        rec["arm_error"] = {"mm": arm_error[0], "deg": arm_error[1]}
    return rec


def test_the_difficulty_sweep_runs_both_procedures_at_each_level(monkeypatch, tmp_path,
                                                                  capsys):
    """Issue 36 item 4: the sweep runs every seed at every difficulty (sorted, repeats
    dropped) open-loop and servoed, with the arm error given to each; the document
    gives per procedure and level the success, its Wilson interval (4 of 4: 51.0-100 %),
    the undetected failures and the causes; main writes needle_difficulty.json and a PNG
    chart and prints a line a level."""
    monkeypatch.setattr(needle, "run_trial", _difficulty_trial)
    doc = needle.main(tmp_path, trials=4, seed=10, workers=1, difficulty=[2.0, 0.0, 1.0, 2.0],
                      arm_error=(1.0, 0.5))
    assert doc["levels"] == [0.0, 1.0, 2.0] and doc["split"] == "development"
    assert len(doc["records"]) == 3 * 2 * 4
    assert {(r.get("difficulty", 1.0), r.get("servo", False), r["seed"])
            for r in doc["records"]} == {(d, m, s) for d in (0.0, 1.0, 2.0)
                                         for m in (False, True) for s in range(10, 14)}
    assert all(r["arm_error"] == {"mm": 1.0, "deg": 0.5} for r in doc["records"])
    open_loop, servoed = doc["modes"]["open_loop"], doc["modes"]["servoed"]
    assert [p["overall"] for p in open_loop] == [1.0, 1.0, 0.0]
    assert [p["overall"] for p in servoed] == [1.0, 1.0, 1.0]
    assert open_loop[2]["undetected"] == 2 and open_loop[2]["failure_causes"] == {
        "ND undetected": 2, "ND exit_missed": 2}
    lo, hi = servoed[0]["overall_interval"]
    assert lo == pytest.approx(0.510, abs=5e-3) and hi == pytest.approx(1.0)
    saved = json.loads((tmp_path / "needle_difficulty.json").read_text())
    assert saved["modes"] == doc["modes"]
    assert (tmp_path / "needle_difficulty.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    err = capsys.readouterr().err
    assert "difficulty 2: open-loop 0.0 %" in err and "servoed 100.0 %" in err
    assert doc["stream"] is False and not any(r.get("stream") for r in doc["records"])
    streamed = needle.main(tmp_path, trials=1, seed=10, workers=1, difficulty=[0.0, 2.0],
                           stream=True)
    assert streamed["stream"] is True
    assert {r.get("servo", False): r.get("stream", False) for r in streamed["records"]} == {
        False: False, True: True}
    assert "servoed from a tracking task" in capsys.readouterr().err


def test_bad_difficulties_are_refused_before_any_trial(monkeypatch):
    """A difficulty outside 0..2 or not finite, or a sweep of one level, is a ValueError
    naming it, and no trial runs."""
    ran = []
    monkeypatch.setattr(needle, "run_trial", lambda *a, **k: ran.append(a))
    for bad in ([0.0, 2.5], [math.nan, 1.0]):
        with pytest.raises(ValueError, match="difficulty must be within 0..2"):
            needle.sweep(bad, 2, 0, workers=1, progress=False)
    with pytest.raises(ValueError, match="at least two"):
        needle.sweep([1.0, 1.0], 2, 0, workers=1, progress=False)
    with pytest.raises(ValueError, match="within 0..2"):
        needle.run(1, 0, workers=1, progress=False, difficulty=-1.0)
    assert ran == []
