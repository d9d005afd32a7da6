"""Issue 35, item 2: the calibration budget's trials run through the executor and give
the same TRE trial by trial in this process and on a process pool; item 3: a point with
no successful calibration has no TRE and is never counted as meeting the target."""

from __future__ import annotations

from oralnav.bench import calibration
from oralnav.bench.executor import TrialRunner


def test_trials_identical_on_every_engine():
    """Two chain calibrations of 5 samples each: the same TREs and errors here and on a
    two-process pool (each trial a function of its seed alone). Small, so that the pool
    beside the suite's workers stays brief."""
    here = calibration.run_point(5, calibration.REALISTIC_PX, 2, seed=7)
    with TrialRunner(workers=2) as pool:
        there = calibration.run_point(5, calibration.REALISTIC_PX, 2, seed=7, runner=pool)
    assert here["tre_mm"]["all"] == there["tre_mm"]["all"]
    assert here["calibration_errors"] == there["calibration_errors"]
    assert here["failed"] == 0


def test_refused_calibrations_leave_no_tre(monkeypatch):
    """Every calibration refused: the point says so (no TRE, failures counted by reason)."""
    from oralnav.control.errors import CalibrationError

    def refuse(sim, n, **kw):
        raise CalibrationError("hand-eye: poses too similar")

    monkeypatch.setattr(calibration, "calibrate_chain", refuse)
    p = calibration.run_point(5, 0.15, 2, seed=1)
    assert p["tre_mm"] is None and p["failed"] == 2
    assert p["failures"] == {"hand-eye": 2}
