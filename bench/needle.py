"""Needle driving Monte Carlo (issue 7; seed 002 §IV, Tables I and II): the whole procedure
(NG, NH, ND, NR, NP) on randomised simulated trial cells, each step checked against the
simulator's truth, every failure classified by its cause.

    oralnav bench needle --trials N --seed S --out DIR [--json] [--workers W]
                         [--arm-error MM DEG]
    python -m bench needle [--quick]

Each trial is :func:`oralnav.sim.world.needle_trials.trial_cell` (seed ``S + k``): a stereo
endoscope, a tilted tissue pad with a drawn incision, a threaded CT-1 needle lying at
random on the pad, two parked grippers on RCM arms, random lighting, blur and noise. The
procedure is :class:`oralnav.control.needle.procedure.NeedleProcedure` with its default
settings (suture depth 5 mm at the incision's middle); it gets the incision, the tissue
normal and the pad's outline, as the seed's vision does. A step counts as a success only
if the procedure saw it succeed and the truth agrees
(:func:`oralnav.sim.world.needle_truth.check_truth`); the steps after a failed one are
not run and count as failed (the paper's rule).

Failures are classified by the first failed step and its cause: a refusal before moving
(``refused_*``: the tracker had not converged, nothing reachable, ...), a failure the
procedure saw (``grasp_missed``, ``lost_track``, ``move_stopped``, ...), or
``undetected``: the procedure believed the step done and the truth says otherwise (the
dangerous kind), unless the next step caught it before moving on it
(``caught_by_NR_exit_missed``: the drive, checked once the jaws were off the needle;
``caught_by_NP_grasp_missed``: the regrasp, whose hold the pull shows).

Writes ``needle.json``: ``{"trials", "overall", "steps": {step: overall rate}}`` (Table
II's first row, as the issue asks), the individual rates (Table II's second row), the
failure classes with their trials, the seed's figures for comparison, and one record per
trial.

``--arm-error MM DEG`` gives each arm a kinematic error of that size (the tool is ``MM``
and ``DEG`` away from where the arm reports it: ``needle_trials.arm_errors``), drawn per
trial apart from the layout, so the same seeds show what the error costs; the procedure
is told the error's size as the arms' stated accuracy (``ProcedureSettings.arm_accuracy``,
which widens the tracker's motion prior), never the errors themselves. Off by default.
"""

from __future__ import annotations

import functools
import json
import math
import os
import platform
import sys
import time
from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

#: Seed 002 §IV.C, 20 trials on the dVRK: overall (Table II's first row) and individual
#: success (second row) per step.
PAPER = {"trials": 20, "overall": 0.70,
         "steps": {"NG": 0.95, "NH": 0.90, "ND": 0.90, "NR": 0.70, "NP": 0.70},
         "individual": {"NG": 19 / 20, "NH": 18 / 19, "ND": 18 / 18, "NR": 14 / 18,
                        "NP": 14 / 14}}


#: The needle procedure's seed ranges (issue 36; docs/needle.md, "Development and
#: validation seeds"). Changes are developed and tuned on the development seeds (inclusive),
#: and success is reported on the validation range, which no change is tuned on.
DEVELOPMENT_SEEDS = (0, 999)
#: The first validation seed, and the validation Monte Carlo's size.
VALIDATION_SEED = 1_000_000
VALIDATION_TRIALS = 400
#: Confidence of the intervals reported with a success rate.
CONFIDENCE = 0.95


def seed_split(first: int, last: int) -> str:
    """Which range seeds ``first``-``last`` (inclusive) lie in: ``"development"``,
    ``"validation"``, ``"mixed"`` when they reach into the development seeds and beyond,
    or ``"held out"`` (neither: seeds no change was tuned on, outside the validation
    range)."""
    lo, hi = DEVELOPMENT_SEEDS
    if lo <= first and last <= hi:
        return "development"
    if first <= hi and last >= lo:
        return "mixed"
    return "validation" if first >= VALIDATION_SEED else "held out"


def wilson(k: int, n: int) -> tuple[float, float]:
    """The Wilson score interval (``CONFIDENCE``) of ``k`` successes in ``n`` trials, as
    fractions; ``(nan, nan)`` for no trial."""
    import math

    from scipy.stats import binomtest

    if n < 1:
        return math.nan, math.nan
    ci = binomtest(k, n).proportion_ci(confidence_level=CONFIDENCE, method="wilson")
    return float(ci.low), float(ci.high)


#: Causes by which a step reports that the one before, which believed itself done,
#: failed: NR checks the drive once the jaws are off the needle, NP shows whether the
#: regrasp holds by pulling.
_LATE_CHECKS = {"NR": ("exit_missed", "not_in_tissue"),
                "NP": ("grasp_missed", "still_in_tissue")}


def first_failure(results: Sequence[Any]) -> tuple[dict[str, bool | None], dict | None]:
    """Per step, whether it succeeded by the procedure and the truth (``None``: not
    reached), and the first failure ``{"step", "cause", "detail", "truth"}`` (``None``
    when all succeeded); ``results``: the procedure's :class:`StepResult` list."""
    from oralnav.control.needle.procedure import STEPS

    steps: dict[str, bool | None] = dict.fromkeys(STEPS)
    failure = None
    for k, r in enumerate(results):
        steps[r.step] = bool(r.ok and r.truth_ok)
        if failure is None and not steps[r.step]:
            cause = r.cause if not r.ok else "undetected"
            later = results[k + 1] if k + 1 < len(results) else None
            if r.ok and later is not None and later.cause in _LATE_CHECKS.get(later.step, ()):
                # the step's own check could not run; the next step's caught it before
                # moving on it (the drive checked after the back-off, the regrasp's
                # hold shown by the pull)
                cause = f"caught_by_{later.step}_{later.cause}"
            failure = {"step": r.step, "cause": cause,
                       "detail": r.detail if not r.ok else r.truth_detail,
                       "truth": r.truth_detail}
    return steps, failure


def arm_error_checked(arm_error: Sequence[float] | None) -> tuple[float, float] | None:
    """``arm_error`` as ``(mm, deg)`` floats; ``ValueError`` unless two finite values
    >= 0 (checked here, before any trial starts, for the tool and :func:`run` alike)."""
    if arm_error is None:
        return None
    values = tuple(float(v) for v in arm_error)
    if len(values) != 2 or not all(math.isfinite(v) and v >= 0 for v in values):
        raise ValueError(f"needle bench: the arm error must be two finite values >= 0 (mm, "
                         f"deg), got {arm_error}")
    return values[0], values[1]


def difficulty_checked(difficulty: float) -> float:
    """``difficulty`` as a float; ``ValueError`` unless finite and within 0..2
    (``needle_trials.MAX_DIFFICULTY``), checked before any trial starts."""
    from oralnav.sim.world.needle_trials import MAX_DIFFICULTY

    d = float(difficulty)
    if not (math.isfinite(d) and 0.0 <= d <= MAX_DIFFICULTY):
        raise ValueError(f"needle bench: a difficulty must be within 0..{MAX_DIFFICULTY:g}, "
                         f"got {difficulty}")
    return d


def _arm_error_json(arm_error: tuple[float, float] | None) -> dict[str, float] | None:
    """``(mm, deg)`` as the records and the summary give it."""
    return None if arm_error is None else {"mm": arm_error[0], "deg": arm_error[1]}


def run_trial(seed: int, arm_error: tuple[float, float] | None = None,
              servo: bool = False, difficulty: float = 1.0,
              stream: bool = False) -> dict[str, Any]:
    """One trial: the procedure on ``trial_cell(seed)`` at ``difficulty`` (0..2,
    ``needle_trials.MAX_DIFFICULTY``), each arm with a kinematic error of ``arm_error``
    (mm, deg) when given, the drive servoed on the tracked needle with ``servo``
    (``ProcedureSettings.drive_servo``), from a tracking task that tracks every frame
    while the arm moves with ``stream`` as well (:mod:`oralnav.realtime.needle_tracking`);
    its record (JSON-able; ``difficulty`` in it unless the default)."""
    from oralnav.realtime.needle_tracking import start_tracking

    t0 = time.perf_counter()
    _, _, proc = trial_procedure(seed, arm_error, servo, difficulty,
                                 feed=start_tracking if servo and stream else None)
    results = proc.run_all()
    steps, failure = first_failure(results)
    return {"seed": seed, "steps": steps, "failure": failure,
            **({} if arm_error is None else {"arm_error": _arm_error_json(arm_error)}),
            **({"servo": True} if servo else {}),
            **({"stream": True} if servo and stream else {}),
            **({} if difficulty == 1.0 else {"difficulty": float(difficulty)}),
            "seconds": round(time.perf_counter() - t0, 2),
            "results": [r.to_json() for r in results]}


def classify(records: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Failure classes ``(step, cause)``, most frequent first, with their trials' seeds."""
    seen: dict[tuple[str, str], list[int]] = {}
    for rec in records:
        f = rec["failure"]
        if f is not None:
            seen.setdefault((f["step"], f["cause"]), []).append(rec["seed"])
    return [{"step": st, "cause": c, "count": len(s), "seeds": s,
             "example": next(r["failure"]["detail"] for r in records
                             if r["seed"] == s[0])}
            for (st, c), s in sorted(seen.items(), key=lambda kv: -len(kv[1]))]


def _kept_trials(store: Path | None, seeds: Sequence[int],
                 arm_error: tuple[float, float] | None = None,
                 servo: bool = False, difficulty: float = 1.0, stream: bool = False
                 ) -> dict[int, dict[str, Any]]:
    """The records of ``seeds`` already in ``store`` (one ``SEED.json`` each) run with
    ``arm_error``; a file that does not read back (a write cut short), or a record of
    other settings, is left out, so its trial runs again."""
    kept: dict[int, dict[str, Any]] = {}
    if store is None:
        return kept
    for s in seeds:
        try:
            rec = json.loads((store / f"{s}.json").read_text())
        except (OSError, ValueError):
            continue
        if (isinstance(rec, dict) and rec.get("seed") == s
                and rec.get("arm_error") == _arm_error_json(arm_error)
                and rec.get("servo", False) == servo
                and rec.get("stream", False) == (servo and stream)
                and rec.get("difficulty", 1.0) == difficulty):
            kept[s] = rec
    return kept


def percentiles(values: Sequence[float], *qs: float) -> dict[str, float | None]:
    """``{"p50": ..., ...}`` of ``values`` at each of ``qs`` (percent), to 0.1; None
    each where there are no values."""
    return {f"p{q:g}": (round(float(np.percentile(values, q)), 1) if len(values) else None)
            for q in qs}


def trial_procedure(seed: int, arm_error: tuple[float, float] | None = None,
                    servo: bool = False, difficulty: float = 1.0, feed: Any = None
                    ) -> tuple[Any, Any, Any]:
    """``(cell, info, procedure)`` of trial ``seed`` as :func:`run_trial` runs it: the
    trial cell at ``difficulty`` with its ports chosen for the suture, each arm off by
    ``arm_error`` (mm, deg; the procedure told the magnitudes as the arms' accuracy,
    never the errors), the drive servoed with ``servo``, fed by ``feed`` (a
    :data:`~oralnav.control.needle.procedure.feed.FeedFactory`) where given, and the
    truth checked."""
    from oralnav.config.rig import trial_rig
    from oralnav.control.needle.procedure import (
        NeedleProcedure,
        ProcedureSettings,
        port_drives,
        port_pair,
    )
    from oralnav.control.needle.servo import ServoSettings
    from oralnav.sim.world.needle_trials import CT1, trial_cell
    from oralnav.sim.world.needle_truth import check_truth

    # the cell is set up for the suture: its ports chosen together with the procedure's
    # own rules (one arm drives and pulls, the other picks up and hands over)
    error = (None if arm_error is None
             else (arm_error[0] * 1e-3, math.radians(arm_error[1])))
    cell, info = trial_cell(seed, rig=trial_rig(), difficulty=difficulty,
                            drivable=port_drives(CT1), workable=port_pair(CT1),
                            arm_error=error)
    settings = ProcedureSettings(drive_servo=ServoSettings() if servo else None,
                                 arm_accuracy=error)
    proc = NeedleProcedure(cell, info.incision, info.surface_normal, settings,
                           surface_outline=info.surface_outline, truth_check=check_truth,
                           feed=feed)
    return cell, info, proc


def stream_figures(records: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """The streamed servo's figures over ``records`` (their ND figures): commands given,
    the per-drive command rate (Hz: p50, min; bound by the simulator's renderer), every
    command's time from its frame's arrival (ms: p50, p99, max), every frame's features
    and tracking times (ms: p50, p99), and the rate the slower of the two allows
    (``tracking_capacity_hz``: 1000 / the larger p50; they overlap in the task), which a
    camera faster than the renderer would see."""
    rates: list[float] = []
    latency: list[float] = []
    prepare: list[float] = []
    track: list[float] = []
    for r in records:
        for step in r["results"]:
            f = step.get("figures", {})
            if step["step"] == "ND" and "servo_latency_ms" in f:
                latency += f["servo_latency_ms"]
                prepare += f["servo_prepare_ms"]
                track += f["servo_track_ms"]
                if f.get("servo_rate_hz") is not None:
                    rates.append(f["servo_rate_hz"])

    work = {"features": percentiles(prepare, 50, 99), "tracking": percentiles(track, 50, 99)}
    slower = max((w["p50"] for w in work.values() if w["p50"]), default=None)
    return {"commands": len(latency), "drives": len(rates),
            "rate_hz": {**percentiles(rates, 50), "min": min(rates) if rates else None},
            "latency_ms": {**percentiles(latency, 50, 99),
                           "max": max(latency) if latency else None},
            "frame_ms": work,
            "tracking_capacity_hz": round(1e3 / slower, 1) if slower else None}


def run(trials: int, seed: int, workers: int | None = None,
        progress: bool = True, scheduler: str | None = None,
        store: Path | None = None,
        arm_error: tuple[float, float] | None = None, servo: bool = False,
        difficulty: float = 1.0, stream: bool = False) -> dict[str, Any]:
    """The Monte Carlo over ``trials`` seeds from ``seed``; the summary document. The
    trials run on the engine ``scheduler`` names (``bench/executor.py``: by default a
    local process pool of ``workers``; a trial is a pure function of its seed).
    ``store``: a folder each finished trial's record is written to as it comes in, and
    read back from on the next run, so an interrupted Monte Carlo resumes where it
    stopped (the caller keeps it to one commit: a record is the code's as much as the
    seed's). ``arm_error``: each arm's kinematic error (mm, deg), ``servo``: the drive
    servoed, ``difficulty``: the trials' (0..2), ``stream``: the servo fed by a tracking
    task, as :func:`run_trial`'s; streamed, ``stream`` in the document sums up the servo's
    rate and latency (:func:`stream_figures`)."""
    from oralnav.bench.executor import TrialRunner
    from oralnav.config.loader import atomic_write_text
    from oralnav.control.needle.procedure import step_rates

    if trials < 1:
        raise ValueError(f"needle bench: trials must be >= 1, got {trials}")
    seeds = list(range(seed, seed + trials))
    arm_error = arm_error_checked(arm_error)
    difficulty = difficulty_checked(difficulty)
    stream = servo and stream
    kept = _kept_trials(store, seeds, arm_error, servo, difficulty, stream)
    todo = [s for s in seeds if s not in kept]
    if scheduler is None:
        workers = max(1, min(workers or os.cpu_count() or 1, max(len(todo), 1)))
    if store is not None:
        store.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    if progress and kept:
        print(f"needle: {len(kept)} of {trials} trials kept from an interrupted run in "
              f"{store}", file=sys.stderr, flush=True)

    def report(_i: int, rec: dict[str, Any], done: int, total: int) -> None:
        if store is not None:
            atomic_write_text(store / f"{rec['seed']}.json", json.dumps(rec) + "\n")
        if not progress:
            return
        ok = all(rec["steps"].values())
        f = rec["failure"]
        left = (time.perf_counter() - t0) / done * (total - done)
        print(f"needle: trial {rec['seed']} ({done}/{total}) "
              f"{'ok' if ok else f['step'] + ' ' + f['cause']} {rec['seconds']:.1f} s; "
              f"about {left / 60:.1f} min left", file=sys.stderr, flush=True)

    with TrialRunner(scheduler, workers) as runner:
        if progress:
            print(f"needle: {len(todo)} trials on {runner.name}"
                  + (f", dashboard {runner.dashboard}" if runner.dashboard else ""),
                  file=sys.stderr, flush=True)
        options = {**({} if arm_error is None else {"arm_error": arm_error}),
                   **({"servo": True} if servo else {}),
                   **({"stream": True} if stream else {}),
                   **({} if difficulty == 1.0 else {"difficulty": difficulty})}
        trial = functools.partial(run_trial, **options) if options else run_trial
        fresh = runner.map(trial, todo, on_result=report) if todo else []
        engine, workers = runner.name, runner.workers
    ran = dict(zip(todo, fresh, strict=True))
    records = [kept[s] if s in kept else ran[s] for s in seeds]
    rates = step_rates(records)
    causes = Counter(r["failure"]["cause"] for r in records if r["failure"])
    succeeded = sum(all(v is True for v in r["steps"].values()) for r in records)
    return {"bench": "needle", "trials": rates["trials"], "overall": rates["overall"],
            "overall_interval": list(wilson(succeeded, len(records))),
            "split": seed_split(seeds[0], seeds[-1]),
            "arm_error": _arm_error_json(arm_error), "servo": servo,
            **({"stream": stream_figures(records)} if stream else {}),
            "difficulty": difficulty,
            "steps": rates["steps"], "individual": rates["individual"],
            "failures": classify(records), "failure_causes": dict(causes),
            "paper": PAPER, "target_overall": 0.90, "seed": seed,
            "seconds": round(time.perf_counter() - t0, 1),
            "trial_seconds_median": round(float(np.median([r["seconds"] for r in records])), 2),
            "machine": {"cpus": os.cpu_count(), "workers": workers, "engine": engine,
                        "python": platform.python_version()},
            "records": records}


#: The sweep's two procedures, in the order they are charted: the drive as planned, and
#: servoed on the tracked needle (issue 36, item 4).
MODES = (("open_loop", False), ("servoed", True))


def _sweep_trial(item: tuple[int, float, bool, tuple[float, float] | None, bool]
                 ) -> dict[str, Any]:
    """:func:`run_trial` of one sweep item ``(seed, difficulty, servo, arm_error,
    stream)`` (module level: it crosses to the pool's workers)."""
    seed, difficulty, servo, arm_error, stream = item
    return run_trial(seed, arm_error, servo=servo, difficulty=difficulty,
                     stream=servo and stream)


def _rate(records: list[dict[str, Any]]) -> dict[str, Any]:
    """One sweep point: overall success, its Wilson interval, per-step rates and the
    first failures by cause."""
    from oralnav.control.needle.procedure import step_rates

    rates = step_rates(records)
    ok = sum(all(v is True for v in r["steps"].values()) for r in records)
    return {"trials": len(records), "overall": rates["overall"],
            "overall_interval": list(wilson(ok, len(records))), "steps": rates["steps"],
            "undetected": sum(1 for r in records if r["failure"]
                              and r["failure"]["cause"] == "undetected"),
            "failure_causes": dict(Counter(f"{r['failure']['step']} {r['failure']['cause']}"
                                           for r in records if r["failure"]))}


def sweep(levels: Sequence[float], trials: int, seed: int, workers: int | None = None,
          scheduler: str | None = None, arm_error: tuple[float, float] | None = None,
          progress: bool = True, stream: bool = False) -> dict[str, Any]:
    """The difficulty sweep (issue 36, item 4): ``trials`` seeds from ``seed`` at each of
    ``levels`` (0..2, :func:`run_trial`), each run open-loop and servoed (``stream``: the
    servo fed by the tracking task), all on one engine (``scheduler``/``workers`` as
    :func:`run`); the document: per mode, per level, the success with its interval, the
    step rates and the first failures."""
    if trials < 1:
        raise ValueError(f"needle bench: trials must be >= 1, got {trials}")
    levels = sorted({difficulty_checked(d) for d in levels})
    if len(levels) < 2:
        raise ValueError("needle bench: a sweep needs at least two difficulties")
    arm_error = arm_error_checked(arm_error)
    seeds = list(range(seed, seed + trials))
    items = [(s, d, servo, arm_error, stream)
             for d in levels for _, servo in MODES for s in seeds]
    if scheduler is None:
        workers = max(1, min(workers or os.cpu_count() or 1, len(items)))
    t0 = time.perf_counter()

    def report(_i: int, rec: dict[str, Any], done: int, total: int) -> None:
        if not progress:
            return
        f = rec["failure"]
        left = (time.perf_counter() - t0) / done * (total - done)
        print(f"needle sweep: difficulty {rec.get('difficulty', 1.0):g} "
              f"{'servoed' if rec.get('servo') else 'open-loop'} trial {rec['seed']} "
              f"({done}/{total}) {'ok' if f is None else f['step'] + ' ' + f['cause']}; "
              f"about {left / 60:.1f} min left", file=sys.stderr, flush=True)

    from oralnav.bench.executor import TrialRunner

    with TrialRunner(scheduler, workers) as runner:
        if progress:
            print(f"needle sweep: {len(items)} trials ({len(levels)} difficulties x 2 "
                  f"procedures x {trials} seeds) on {runner.name}", file=sys.stderr,
                  flush=True)
        records = runner.map(_sweep_trial, items, on_result=report)
        engine, workers = runner.name, runner.workers
    by = {(d, servo): [] for d in levels for _, servo in MODES}
    for (_, d, servo, _, _), rec in zip(items, records, strict=True):
        by[(d, servo)].append(rec)
    return {"bench": "needle_difficulty", "levels": levels, "trials": trials,
            "seed": seed, "split": seed_split(seeds[0], seeds[-1]),
            "arm_error": _arm_error_json(arm_error), "stream": stream,
            "modes": {name: [{"difficulty": d, **_rate(by[(d, servo)])} for d in levels]
                      for name, servo in MODES},
            "seconds": round(time.perf_counter() - t0, 1),
            "machine": {"cpus": os.cpu_count(), "workers": workers, "engine": engine,
                        "python": platform.python_version()},
            "records": records}


def sweep_chart(doc: dict[str, Any], path: Path) -> None:
    """Success against difficulty, open-loop beside servoed, with the 95 % intervals
    (PNG at ``path``)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for (name, _), colour, nudge in zip(MODES, ("tab:grey", "tab:blue"), (-0.012, 0.012),
                                        strict=True):
        pts = doc["modes"][name]
        x = np.array([p["difficulty"] for p in pts]) + nudge
        y = np.array([100 * p["overall"] for p in pts])
        lo = y - np.array([100 * p["overall_interval"][0] for p in pts])
        hi = np.array([100 * p["overall_interval"][1] for p in pts]) - y
        ax.errorbar(x, y, yerr=[lo, hi], marker="o", capsize=3, color=colour,
                    label=name.replace("_", "-")
                    + (" (streamed)" if name == "servoed" and doc.get("stream") else ""))
    ax.axvline(1.0, color="0.8", lw=0.8, zorder=0)
    err = doc["arm_error"]
    ax.set(xlabel="difficulty (1: the default trials; above 1 the layout harder too)",
           ylabel="overall success (%)", ylim=(0, 100))
    ax.set_title(f"needle procedure, {doc['trials']} {doc['split']} trials a point"
                 + ("" if err is None
                    else f"\narm errors {err['mm']:g} mm / {err['deg']:g} deg"), fontsize=10)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def summary(doc: dict[str, Any]) -> dict[str, Any]:
    """The issue's JSON: ``{"trials", "overall", "steps"}``."""
    return {"trials": doc["trials"], "overall": doc["overall"], "steps": doc["steps"]}


def main(out: Path, quick: bool = False, trials: int | None = None, seed: int = 0,
         workers: int | None = None, scheduler: str | None = None,
         validation: bool = False,
         arm_error: tuple[float, float] | None = None, servo: bool = False,
         difficulty: Sequence[float] = (1.0,), stream: bool = False) -> dict[str, Any]:
    """Run the Monte Carlo (``quick``: 10 trials, ``validation``: ``VALIDATION_TRIALS``
    from ``VALIDATION_SEED``, else 200 unless ``trials`` is given; ``arm_error``: each
    arm's kinematic error, mm and deg; ``servo``: the drive servoed; ``difficulty``: the
    trials', 0..2) and write ``needle.json`` into ``out``. With more than one
    ``difficulty``, the sweep instead (:func:`sweep`, both procedures at each; 40 trials
    a point unless ``trials``, 4 with ``quick``): ``needle_difficulty.json`` and
    ``needle_difficulty.png``."""
    if validation:
        seed = VALIDATION_SEED
    if len(difficulty) > 1:
        return _main_sweep(out, difficulty, quick, trials, seed, workers, scheduler,
                           arm_error, stream)
    n = trials if trials is not None else (
        10 if quick else VALIDATION_TRIALS if validation else 200)
    doc = run(n, seed, workers, scheduler=scheduler, arm_error=arm_error, servo=servo,
              difficulty=difficulty[0], stream=stream)
    out.mkdir(parents=True, exist_ok=True)
    (out / "needle.json").write_text(json.dumps(doc, indent=1) + "\n")
    lo, hi = doc["overall_interval"]
    err = ("" if arm_error is None
           else f" with {arm_error[0]:g} mm / {arm_error[1]:g} deg arm errors")
    err += ", the drive servoed" if servo else ""
    err += " from a tracking task" if servo and stream else ""
    err += "" if doc["difficulty"] == 1.0 else f", difficulty {doc['difficulty']:g}"
    print(f"needle: {doc['trials']} trials on {doc['split']} seeds {seed}-{seed + n - 1}{err}, "
          f"overall {100 * doc['overall']:.1f} % ({100 * CONFIDENCE:.0f} % interval "
          f"{100 * lo:.1f}-{100 * hi:.1f} %; "
          f"seed 002: {100 * PAPER['overall']:.0f} % of {PAPER['trials']}); per step "
          + ", ".join(f"{k} {100 * v:.1f} %" for k, v in doc["steps"].items()),
          file=sys.stderr)
    for f in doc["failures"]:
        print(f"  {f['count']:4d} x {f['step']} {f['cause']}: {f['example'][:120]}",
              file=sys.stderr)
    if "stream" in doc:
        st = doc["stream"]
        print(f"  streamed servo: {st['commands']} commands, rate p50 "
              f"{st['rate_hz']['p50']} Hz; capture to command p50 {st['latency_ms']['p50']} "
              f"ms, p99 {st['latency_ms']['p99']} ms; a frame's features p50 "
              f"{st['frame_ms']['features']['p50']} ms, tracking p50 "
              f"{st['frame_ms']['tracking']['p50']} ms (at most "
              f"{st['tracking_capacity_hz']} Hz from a camera)", file=sys.stderr)
    return doc


def _main_sweep(out: Path, levels: Sequence[float], quick: bool, trials: int | None,
                seed: int, workers: int | None, scheduler: str | None,
                arm_error: tuple[float, float] | None, stream: bool = False
                ) -> dict[str, Any]:
    """:func:`main`'s sweep: run it, write its JSON and chart, print a line a point."""
    n = trials if trials is not None else (4 if quick else 40)
    doc = sweep(levels, n, seed, workers, scheduler, arm_error, stream=stream)
    out.mkdir(parents=True, exist_ok=True)
    (out / "needle_difficulty.json").write_text(json.dumps(doc, indent=1) + "\n")
    sweep_chart(doc, out / "needle_difficulty.png")
    print(f"needle sweep: {n} {doc['split']} trials a point from seed {seed}"
          + ("" if arm_error is None
             else f", {arm_error[0]:g} mm / {arm_error[1]:g} deg arm errors")
          + (", servoed from a tracking task" if stream else "")
          + f", {doc['seconds'] / 60:.1f} min", file=sys.stderr)
    for k, d in enumerate(doc["levels"]):
        a, b = (doc["modes"][name][k] for name, _ in MODES)
        print(f"  difficulty {d:g}: open-loop {100 * a['overall']:.1f} % "
              f"({100 * a['overall_interval'][0]:.1f}-{100 * a['overall_interval'][1]:.1f}), "
              f"servoed {100 * b['overall']:.1f} % "
              f"({100 * b['overall_interval'][0]:.1f}-{100 * b['overall_interval'][1]:.1f}); "
              f"undetected {a['undetected']} / {b['undetected']}", file=sys.stderr)
    return doc
