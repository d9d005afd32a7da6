"""Calibration accuracy budget (issue 5 item 8): the whole chain calibrated in simulation
from noisy samples, then eq. 21's TRE at the cell's suture targets.

    oralnav bench calibration [--quick] --out DIR      (or: python -m bench calibration)

For every trial, :func:`oralnav.sim.world.calibration_chain.calibrate_chain` measures every
sample of the chain (hand-eye, endoscope to opener, pointer pivot, end-effector zero,
end-effector marker) through the project's pose estimator at one marker-corner noise
(``sim/world/measure.py``: exact corners plus Gaussian pixel noise), calibrates in the paper's
order, and :func:`~oralnav.sim.world.calibration_chain.chain_tre` registers the targets with the
pointer and measures where the navigated end-effector really ends up. Trials differ only
in their noise draws. Two sweeps:

- TRE against the number of samples per calibration (the pivot takes 10x as many poses),
  at the realistic corner noise (0.15 px: the tracker's residual on the rendered cell);
- TRE against the corner noise, at the default sample count.

Each point reports the median, the 90th percentile and the mean of the trials' TRE, and
the median error of each calibration against the truth, so the budget shows which link
dominates. The paper's hardware TRE is 0.69 mm (Table II); the target here is <= 0.3 mm at
realistic noise. Writes ``calibration.json`` and ``calibration_tre.png``.
"""

from __future__ import annotations

import json
import os
import platform
import sys
import time
from functools import lru_cache
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from oralnav.bench.executor import TrialRunner
from oralnav.config.cell import load_cell_config
from oralnav.control.errors import CalibrationError
from oralnav.control.geometry import invert, pose_error
from oralnav.sim.world.calibration_chain import (
    POINTER_TIP,
    ChainSimulator,
    MeasurementLost,
    calibrate_chain,
    chain_tre,
)

#: Marker-corner noise (px) taken as realistic: the tracker's reprojection RMS on the
#: rendered cell is 0.12 px (bench/navigation.py, issue 3), rounded up.
REALISTIC_PX = 0.15
#: Samples per calibration used by the noise sweep and recommended in docs/calibration.md.
DEFAULT_SAMPLES = 15
TRE_TARGET_MM = 0.3


def _cell_file() -> Path:
    return Path(str(resources.files("oralnav.config").joinpath("examples/sim_cell.toml")))


def _errors(cal, cfg) -> dict[str, tuple[float, float]]:
    """Each calibration's error against the truth: (mm, deg)."""
    g = cfg.geometry

    def e(T, T_true) -> tuple[float, float]:
        dt, dr = pose_error(T, T_true)
        return dt * 1e3, float(np.degrees(dr))

    return {"hand_eye": e(cal.T_B_C, g.T_B_C),
            "endoscope_opener": e(cal.T_OM_En, g.T_OM_En),
            "effector_zero": e(cal.T_RM_E0, invert(g.T_tcp_RM) @ g.T_tcp_E0),
            "effector_marker": e(cal.T_EM_E, invert(g.T_E_EM)),
            "pivot_tip": (float(np.linalg.norm(cal.pivot.tip_offset - POINTER_TIP)) * 1e3, 0.0)}


def calibration_trial(item: tuple[str, int, float, int, int]) -> dict[str, Any]:
    """One trial: the chain calibrated from ``n`` samples at ``sigma_px`` and its TRE.
    ``item = (cell file, n, sigma_px, seed, k)``; the noise draws are a function of
    ``(seed, n, k, sigma_px)`` alone, so a trial gives the same result on any engine
    (bench/executor.py). Returns ``{"tre_mm", "errors", "seconds"}`` or, when the
    calibration was refused, ``{"failure"}`` (its reason's first clause)."""
    path, n, sigma_px, seed, k = item
    cfg = _config(path)
    sim = ChainSimulator(cfg, sigma_px, np.random.default_rng([seed, n, k, int(sigma_px * 1e4)]))
    t0 = time.perf_counter()
    try:
        cal = calibrate_chain(sim, n)
        tre = chain_tre(sim, cal)[0] * 1e3
    except (CalibrationError, MeasurementLost) as exc:
        # a refused calibration is an outcome to count, not a crash: the operator would
        # be told to recapture
        return {"failure": str(exc).split(":")[0]}
    return {"tre_mm": tre, "errors": _errors(cal, cfg), "seconds": time.perf_counter() - t0}


@lru_cache(maxsize=4)
def _config(path: str) -> Any:
    """The cell file, read once per process (each worker of a pool reads its own)."""
    return load_cell_config(Path(path))


def run_point(n: int, sigma_px: float, trials: int, seed: int, *,
              runner: TrialRunner | None = None, cell: Path | None = None) -> dict[str, Any]:
    """``trials`` independent chain calibrations at ``n`` samples and ``sigma_px`` of the
    cell file ``cell`` (default the shipped simulated cell), run on ``runner`` (default
    this process)."""
    path = str(cell or _cell_file())
    items = [(path, n, sigma_px, seed, k) for k in range(trials)]
    results = (runner.map(calibration_trial, items) if runner is not None
               else [calibration_trial(i) for i in items])
    tre = [r["tre_mm"] for r in results if "tre_mm" in r]
    errs = [r["errors"] for r in results if "tre_mm" in r]
    secs = [r["seconds"] for r in results if "tre_mm" in r]
    failures: dict[str, int] = {}
    for r in results:
        if "failure" in r:
            failures[r["failure"]] = failures.get(r["failure"], 0) + 1
    if not tre:
        return {"samples": n, "sigma_px": sigma_px, "trials": trials, "failed": trials,
                "failures": failures, "tre_mm": None, "calibration_errors": None}
    tre_a = np.array(tre)
    per = {name: {"median_mm": float(np.median([e[name][0] for e in errs])),
                  "median_deg": float(np.median([e[name][1] for e in errs]))}
           for name in errs[0]}
    return {"samples": n, "sigma_px": sigma_px, "trials": trials,
            "failed": trials - len(tre), "failures": failures,
            "tre_mm": {"median": float(np.median(tre_a)), "p90": float(np.percentile(tre_a, 90)),
                       "mean": float(tre_a.mean()), "max": float(tre_a.max()),
                       "all": tre_a.round(4).tolist()},
            "calibration_errors": per, "calibrate_s_median": float(np.median(secs))}


def _say(point: dict[str, Any], what: str) -> None:
    p = point["tre_mm"]
    tre = "no calibration succeeded" if p is None else \
        f"TRE median {p['median']:.3f} mm, p90 {p['p90']:.3f} mm"
    fails = f"; {point['failed']} of {point['trials']} refused {point['failures']}" \
        if point["failed"] else ""
    print(f"{what}: {tre}{fails}", file=sys.stderr, flush=True)


def _chart(doc: dict[str, Any], out: Path) -> None:
    from matplotlib.ticker import FixedLocator, NullLocator

    from oralnav.bench.report.charts import legend_outside, mark_minority, plt

    p = plt()
    fig, axes = p.subplots(1, 2, figsize=(12, 4.4), layout="constrained")
    for ax, key, xkey, xlabel in ((axes[0], "by_samples", "samples",
                                   "samples per calibration (pivot: x10 poses)"),
                                  (axes[1], "by_noise", "sigma_px",
                                   "marker-corner noise, per axis (px)")):
        pts = [q for q in doc[key] if q["tre_mm"] is not None]
        x = [q[xkey] for q in pts]
        med = [q["tre_mm"]["median"] for q in pts]
        ax.plot(x, med, "o-", label="TRE median")
        ax.plot(x, [q["tre_mm"]["p90"] for q in pts], "s--", label="TRE 90th percentile")
        for name in ("hand_eye", "endoscope_opener", "effector_marker"):
            ax.plot(x, [q["calibration_errors"][name]["median_mm"] for q in pts], ":",
                    label=f"{name.replace('_', ' ')} error (median)")
        # a point whose calibrations were mostly refused pools a few lucky trials
        mark_minority(ax, x, med, [q["failed"] > q["trials"] / 2 for q in pts])
        ax.axhline(TRE_TARGET_MM, color="r", lw=0.8, label=f"target {TRE_TARGET_MM} mm")
        ax.set_xlabel(xlabel)
        ax.set_ylabel("error (mm)")
        ax.grid(alpha=0.3)
        # ticks at the measured points only, written plainly (log axes otherwise crowd)
        ax.xaxis.set_major_locator(FixedLocator(x))
        ax.xaxis.set_minor_locator(NullLocator())
        ax.set_xticks(x, [f"{v:g}" for v in x])
    axes[0].set_title(f"TRE vs samples at {doc['realistic_px']} px")
    axes[1].set_title(f"TRE vs corner noise at {doc['default_samples']} samples")
    axes[1].set_xscale("log")
    axes[1].set_yscale("log")
    axes[1].xaxis.set_minor_locator(NullLocator())
    legend_outside(axes[1])
    fig.savefig(out / "calibration_tre.png", dpi=110)
    p.close(fig)


def main(out: Path, quick: bool = False, workers: int | None = None) -> dict[str, Any]:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    trials = 8 if quick else 30
    counts = (3, 5, 10, 15, 30) if quick else (3, 5, 8, 10, 15, 20, 30, 50)
    # beyond about 0.5 px the tracker's 1 px reprojection gate starts refusing poses; the
    # failures are counted per point
    noises = (0.05, 0.15, 0.3, 0.6) if quick else (0.05, 0.1, 0.15, 0.2, 0.3, 0.45, 0.6, 0.8)
    t0 = time.perf_counter()
    doc: dict[str, Any] = {
        "bench": "calibration", "quick": quick, "cell": str(_cell_file()),
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
        "realistic_px": REALISTIC_PX, "default_samples": DEFAULT_SAMPLES, "trials": trials,
        "by_samples": [], "by_noise": []}
    # each point's trials are independent: one local process pool runs them all
    with TrialRunner(workers=workers) as runner:
        doc["engine"] = runner.name
        for n in counts:
            doc["by_samples"].append(run_point(n, REALISTIC_PX, trials, seed=1, runner=runner))
            _say(doc["by_samples"][-1], f"{n:3d} samples at {REALISTIC_PX} px")
        for s in noises:
            doc["by_noise"].append(run_point(DEFAULT_SAMPLES, s, trials, seed=2,
                                             runner=runner))
            _say(doc["by_noise"][-1], f"{s:5.2f} px at {DEFAULT_SAMPLES} samples")
    at = next(p for p in doc["by_noise"] if p["sigma_px"] == REALISTIC_PX)
    tre = at["tre_mm"]
    # no TRE (every calibration refused) is a missed target, never a met one
    doc["targets"] = {"tre_mm_median": tre and tre["median"], "tre_mm_p90": tre and tre["p90"],
                      "tre_target_mm": TRE_TARGET_MM,
                      "met": bool(tre) and tre["p90"] <= TRE_TARGET_MM,
                      "paper_hardware_tre_mm": 0.69}
    doc["elapsed_s"] = time.perf_counter() - t0
    (out / "calibration.json").write_text(json.dumps(doc, indent=1) + "\n")
    _chart(doc, out)
    t = doc["targets"]
    tre = ("no calibration succeeded" if t["tre_mm_p90"] is None else
           f"median {t['tre_mm_median']:.3f} mm, p90 {t['tre_mm_p90']:.3f} mm")
    print(f"TRE at {REALISTIC_PX} px, {DEFAULT_SAMPLES} samples: {tre} "
          f"(target {TRE_TARGET_MM} mm, met: {t['met']}); "
          f"{doc['elapsed_s']:.0f} s; wrote {out}/calibration.json and calibration_tre.png",
          file=sys.stderr)
    return doc
