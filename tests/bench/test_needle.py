"""Issue 36 item 2: the needle Monte Carlo's seed ranges. Changes are developed on seeds
0-999, success is reported on the validation range from 1,000,000 (400 trials), and each
run says which range its seeds lie in, with the 95 % interval of its overall success.
The trials are stand-ins here (the procedure's own tests run it)."""

from __future__ import annotations

import json

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
