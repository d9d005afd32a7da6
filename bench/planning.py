"""Preoperative planning (seed 004, §3-5): the surrogate model's fit, its answers against
the exact mesh, and the placement search, each next to the paper's figures.

    oralnav bench planning [--quick] --out DIR      (or: python -m bench planning)

Every baseline runs in this process on the same data as our methods. The mouth is the
parametric oral cavity of ``config/examples/oral_cavity_case.toml`` (55 x 45 x 90 mm, full
arches but the lower left first molar, whose gap takes the implant); the paper's own
scan and its Fig. 7a boundary are not public. Five sections:

1. **Table 1** (one slice, N = 3..20 control points). The paper fits one complex boundary
   and reports coverage and time per slice. Here three representative slices of the mouth
   (the tongue without teeth, the molar row with the implant gap, the premolar row), Z =
   150 sampling rays, are fitted by four variants: the paper's eqs. 7-9 with its §5.1 C++
   settings (lambda 30000, alpha 0.1 mm, 1000 iterations), the same with its Table-1
   MATLAB settings (lambda 20000, alpha 1.0 mm: eq. 7's penalty is at most lambda, so once
   the area passes it the descent may run away; reported as measured), and ours, ``slp``
   (sequential LP, hard constraints) and ``lbfgs`` (smooth depth penalty, analytic
   gradient). Coverage is :class:`~oralnav.control.planning.fpsm.SliceReport`'s (curve area over the
   boundary area seen from the slice origin, on 1440 dense rays); also penetrating sampling
   points and the deepest excursion between them. Time: median of repeated fits.
2. **Full model**: 10 x 10, 15 x 15 and 15 x 20 (slices x points) built from the mesh by
   each method: pre-assignment plus fit time, coverage, penetrating samples, deepest
   excursion. Target: 15 x 15 in <= 1 s at >= 90 % coverage with no penetrating sample.
   The paper took 33.6 s in C++ (its §5.1 says 15 points, §5.3 says 20) and 12.2 s for
   10 x 10.
3. **FPSM against the mesh**: the rod query of eq. 13 (safe iff every sampled distance,
   at the start T and at each slice crossing, clears the model shrunk by the rod radius)
   against python-fcl on the full mesh: a capsule of the rod's radius over the same axis
   segment (collision: yes or no) and the axis segment's exact clearance (so a false
   'safe' rod's real penetration is ``r - clearance``). Rods start at random inside the
   cavity (checked on the exact mesh cut at T's height), point toward the opening within
   60 degrees of +z, and end at the last slice plane. The deepest false-safe penetration is
   the shrink margin the model needs; a fresh rod set is then checked with that much extra
   shrink. Each false safe is traced: the model's safe distance sampled densely along the
   whole axis either finds the contact (the miss is eq. 13's sparse sampling) or not (the
   miss is the model itself); models with 2x and 4x the slices, on the same rods, show how
   much of the margin is the slice spacing. The same rods as flat-ended cylinders are
   counted too. Times: one rod per call for both, and the FPSM's batched call per rod.
4. **PSO**: swarm size, seeds and the inertia c0 against time and the gap to a reference
   optimum (a dense grid of the objective, polished by Nelder-Mead), on the paper's
   cylinder case and on the mouth. Target: <= 20 ms per placement; the paper's 0.299 s.
5. **Table 2**: the cylinder case with eqs. 14, 21, 22, line2 shrunk or not (the paper:
   d_T = 65.5, 55.304, 81.0 mm, theta_T = 0).

Writes ``planning.json`` (machine, command, every measured row and the summaries) and the
charts ``planning_*.png``.
"""

from __future__ import annotations

import json
import math
import os
import platform
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
from scipy.optimize import minimize

from oralnav.bench.machine import describe
from oralnav.config.planning import PlanningScene, load_planning_scene
from oralnav.control.errors import PlanningError
from oralnav.control.planning import polar_curve as pc
from oralnav.control.planning.fpsm import (
    DENSE_RAYS,
    FPSM,
    FitSettings,
    build_fpsm,
    cut_segments,
    fit_slices,
    ray_radii,
    report_slices,
    slice_boundaries,
)
from oralnav.control.planning.placement import (
    PlacementProblem,
    line_safe_distances,
    place,
    uncertified_penalty,
)
from oralnav.control.planning.rod_check import RodCheck

#: The paper's Table 1: N -> (coverage %, seconds per slice); MATLAB R2017b, i5-10200H,
#: lambda_p = 20000, alpha = 1.0, one boundary (its Fig. 7a).
PAPER_TABLE1 = {3: (59.24, 0.171), 4: (71.09, 0.262), 5: (60.14, 0.215), 6: (82.31, 0.303),
                7: (79.11, 0.346), 8: (79.98, 0.459), 9: (82.63, 0.406), 10: (84.07, 0.665),
                11: (86.24, 0.653), 12: (90.30, 1.161), 13: (87.29, 1.247),
                14: (91.28, 1.255), 15: (88.23, 1.926), 16: (91.42, 1.860),
                17: (92.05, 3.098), 18: (90.92, 3.969), 19: (93.17, 4.867),
                20: (90.87, 4.911)}
#: The paper's C++ build times (s): 15 slices (15 points in §5.1, 20 in §5.3) and 10 x 10.
PAPER_BUILD_S = {"15 slices (x15 per §5.1, x20 per §5.3)": 33.613, "10x10": 12.227}
PAPER_PSO_S = 0.299
#: The paper's Table 2, cylinder case: equation -> (d_T mm, theta_T deg).
PAPER_TABLE2 = {14: (65.5, 0.0), 21: (55.304, 0.0), 22: (81.0, 0.0)}

#: Table 1's slices of the mouth: name, z (m).
TABLE1_SLICES = (("tongue, no teeth", 0.010), ("molars, implant gap", 0.0505),
                 ("premolars", 0.065))
SAMPLES = 150
#: The fit variants; "paper" has the §5.1 C++ settings (FitSettings' paper defaults).
FITS = {"slp": FitSettings(method="slp"),
        "lbfgs": FitSettings(method="lbfgs"),
        "paper": FitSettings(method="paper"),
        "paper_table1": FitSettings(method="paper", paper_lambda=20000.0, paper_alpha_mm=1.0)}
BUILD_SIZES = ((10, 10), (15, 15), (15, 20))
BUILD_METHODS = ("slp", "lbfgs", "paper")
ROD_RADII = (0.002, 0.004, 0.006)
MAX_TILT_DEG = 60.0
PARTICLES = (5, 10, 20, 30, 50, 100)
INERTIAS = (0.4, 0.5, 0.6, 0.7, 0.8)
GAP_OK = 1e-3

BUILD_TARGET_S = 1.0
COVERAGE_TARGET = 0.90
PLACE_TARGET_MS = 20.0
SPEED_RATIO_TARGET = 100.0


def _say(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def _example(name: str) -> Path:
    return Path(str(resources.files("oralnav.config").joinpath(f"examples/{name}")))


def _machine() -> dict[str, Any]:
    import fcl
    import scipy
    import trimesh

    return describe(platform=platform.platform(), numpy=np.__version__,
                    scipy=scipy.__version__, trimesh=trimesh.__version__,
                    python_fcl=getattr(fcl, "__version__", "?"))


def _stats(x: Any) -> dict[str, float] | None:
    a = np.asarray(x, dtype=float)
    if a.size == 0:
        return None
    return {"median": float(np.median(a)), "p90": float(np.percentile(a, 90)),
            "min": float(a.min()), "max": float(a.max()), "mean": float(a.mean())}


# -- 1. Table 1: one slice, N = 3..20 ---------------------------------------------------

def table1(mesh: Any, quick: bool, *, points: Sequence[int] = range(3, 21),
           fits: dict[str, FitSettings] | None = None, repeats: int | None = None,
           say: Callable[[str], None] = _say) -> dict[str, Any]:
    """Each variant of ``fits`` (default :data:`FITS`) on each slice of
    :data:`TABLE1_SLICES` for each N of ``points`` (the paper's 3..20); each time (s) the
    median of ``repeats`` fits (default 1 when ``quick``, else 5)."""
    fits = FITS if fits is None else fits
    names = [n for n, _ in TABLE1_SLICES]
    z = np.array([zz for _, zz in TABLE1_SLICES])
    segs = cut_segments(mesh, z)
    samp = slice_boundaries(mesh, z, SAMPLES, segments=segs)
    dense = slice_boundaries(mesh, z, DENSE_RAYS, segments=segs)
    repeats = (1 if quick else 5) if repeats is None else repeats
    rows, summary = [], []
    for n in points:
        for method, s in fits.items():
            rho = np.empty((z.size, n))
            secs = np.empty(z.size)
            for j in range(z.size):
                times = []
                for _ in range(repeats):
                    t0 = time.perf_counter()
                    fit = fit_slices(samp[j:j + 1], n, s)
                    times.append(time.perf_counter() - t0)
                rho[j] = fit.rho[0]
                secs[j] = float(np.median(times))
            reps = report_slices(FPSM(z, rho), dense, samp)
            for j, r in enumerate(reps):
                rows.append({"points": n, "method": method, "slice": names[j],
                             "z_mm": z[j] * 1e3, "coverage": r.coverage,
                             "penetrating_samples": r.penetrating_samples,
                             "penetration_max_mm": r.penetration_max * 1e3,
                             "time_s": float(secs[j])})
            summary.append({"points": n, "method": method,
                            "coverage_mean": float(np.mean([r.coverage for r in reps])),
                            "penetrating_samples": int(sum(r.penetrating_samples
                                                           for r in reps)),
                            "penetration_max_mm": max(r.penetration_max for r in reps) * 1e3,
                            "time_s_per_slice": float(np.mean(secs)),
                            "paper_coverage": PAPER_TABLE1[n][0] / 100.0,
                            "paper_time_s": PAPER_TABLE1[n][1]})
        line = "; ".join(f"{r['method']} {r['coverage_mean']:.1%} {r['time_s_per_slice'] * 1e3:.0f}"
                         f" ms" for r in summary[-len(fits):])
        say(f"table 1, N = {n:2d}: {line} (paper {PAPER_TABLE1[n][0]:.1f} %, "
            f"{PAPER_TABLE1[n][1]:.2f} s)")
    return {"slices": [{"name": a, "z_mm": b * 1e3} for a, b in TABLE1_SLICES],
            "samples": SAMPLES, "repeats": repeats,
            "settings": {k: {"method": v.method, "paper_lambda": v.paper_lambda,
                             "paper_alpha_mm": v.paper_alpha_mm,
                             "paper_iterations": v.paper_iterations} for k, v in fits.items()},
            "rows": rows, "summary": summary,
            "_plot": {"z": z, "dense": dense, "samp": samp}}


def _chart_table1(doc: dict[str, Any], out: Path) -> list[Path]:
    plt = _plt()
    t1 = doc["table1"]
    names = [s["name"] for s in t1["slices"]]
    ns = np.arange(3, 21)
    style = {"slp": ("o-", "tab:blue"), "lbfgs": ("s-", "tab:green"),
             "paper": ("^-", "tab:red"), "paper_table1": ("v--", "tab:orange")}
    label = {"slp": "ours: slp", "lbfgs": "ours: lbfgs",
             "paper": "paper eqs. 7-9, C++ settings (lambda 3e4, alpha 0.1)",
             "paper_table1": "paper eqs. 7-9, Table-1 settings (lambda 2e4, alpha 1.0)"}
    fig, axes = plt.subplots(2, len(names), figsize=(4.6 * len(names), 7.6), squeeze=False)
    for c, name in enumerate(names):
        ax, at = axes[0][c], axes[1][c]
        for method in FITS:
            rs = [r for r in t1["rows"] if r["slice"] == name and r["method"] == method]
            cov = np.array([r["coverage"] for r in rs])
            mk, col = style[method]
            off = cov > 1.05
            ax.plot(ns, np.where(off, np.nan, cov * 100), mk, ms=3.5, color=col,
                    label=label[method])
            if np.any(off):
                ax.plot(ns[off], np.full(off.sum(), 104.0), "^", ms=5, color=col,
                        mfc="none", label=f"{method}: coverage > 105 % (runs away)")
            at.plot(ns, [r["time_s"] for r in rs], mk, ms=3.5, color=col)
        ax.plot(ns, [PAPER_TABLE1[n][0] for n in ns], "k:", marker="x", ms=4,
                label="paper Table 1 (its Fig. 7a boundary)")
        at.plot(ns, [PAPER_TABLE1[n][1] for n in ns], "k:", marker="x", ms=4)
        ax.set_ylim(0, 106)
        ax.set_title(f"{name} (z = {t1['slices'][c]['z_mm']:.1f} mm)", fontsize=9)
        ax.set_ylabel("coverage (%)")
        at.set_yscale("log")
        at.set_ylabel("time per slice (s)")
        at.set_xlabel("control points N")
        for a in (ax, at):
            a.grid(alpha=0.3)
    axes[0][0].legend(fontsize=6.5, loc="lower right")
    fig.suptitle(f"Table 1: one slice, Z = {SAMPLES} samples (median of {t1['repeats']} fits;"
                 " paper: MATLAB, i5-10200H)", fontsize=10)
    fig.tight_layout()
    paths = [out / "planning_table1.png"]
    fig.savefig(paths[0], dpi=110)
    plt.close(fig)

    # the fitted shapes on the molar slice, as the paper's Fig. 15a
    p = t1["_plot"]
    j = 1
    th = np.linspace(0, 2 * math.pi, DENSE_RAYS, endpoint=False)
    thc = np.linspace(0, 2 * math.pi, 721)
    fig, axes = plt.subplots(1, 4, figsize=(14, 3.8))
    for ax, n in zip(axes, (5, 10, 15, 20), strict=True):
        rb = p["dense"][j] * 1e3
        ax.plot(rb * np.cos(th), rb * np.sin(th), ".", ms=0.8, color="tab:gray",
                label="boundary (dense rays)")
        for method in ("slp", "lbfgs", "paper"):
            rho = fit_slices(p["samp"][j:j + 1], n, FITS[method]).rho[0]
            r = pc.evaluate(rho, thc) * 1e3
            ax.plot(r * np.cos(thc), r * np.sin(thc), "-", lw=1.0, color=style[method][1],
                    label=label[method].split(" (")[0])
        ax.set_aspect("equal")
        ax.set_title(f"N = {n}", fontsize=9)
        ax.set_xlabel("x (mm)")
    axes[0].legend(fontsize=6.5, loc="lower left")
    fig.suptitle(f"fitted curves, {names[j]} (z = {t1['slices'][j]['z_mm']:.1f} mm)",
                 fontsize=10)
    fig.tight_layout()
    paths.append(out / "planning_table1_shapes.png")
    fig.savefig(paths[1], dpi=110)
    plt.close(fig)
    return paths


# -- 2. the full model ------------------------------------------------------------------

def full_model(mesh: Any, quick: bool, out: Path, *,
               sizes: Sequence[tuple[int, int]] = BUILD_SIZES,
               methods: Sequence[str] = BUILD_METHODS, repeats: int | None = None,
               slice_charts: dict[str, Path] | None = None,
               say: Callable[[str], None] = _say) -> dict[str, Any]:
    """:func:`build_fpsm` at each (slices, points) of ``sizes`` by each of ``methods``; each
    build (s) the median of ``repeats`` (default 1 when ``quick``, else 3). ``sizes`` must
    hold (15, 15) and ``methods`` "slp" (the target's model). ``slice_charts``: method ->
    where its 15 x 15 model's slices are drawn (default ``out/planning_fpsm_slices_*.png``
    for slp and paper)."""
    repeats = (1 if quick else 3) if repeats is None else repeats
    if slice_charts is None:
        slice_charts = {m: out / f"planning_fpsm_slices_{m}.png" for m in ("slp", "paper")}
    rows = []
    for slices, points in sizes:
        for method in methods:
            reps = []
            for _ in range(repeats):
                model, rep = build_fpsm(mesh, slices, points, SAMPLES,
                                        settings=FITS[method], boundary="plane")
                reps.append(rep)
            k = int(np.argsort([r.total_s for r in reps])[len(reps) // 2])  # the median run
            rep = reps[k]
            rows.append({"slices": slices, "points": points, "method": method,
                         "total_s": rep.total_s, "preassign_s": rep.preassign_s,
                         "fit_s": rep.fit_s,
                         "total_s_all": [r.total_s for r in reps],
                         "iterations": rep.iterations, "coverage": rep.coverage,
                         "coverage_worst_slice": min(r.coverage for r in rep.per_slice),
                         "penetrating_samples": rep.penetrating_samples,
                         "penetration_max_mm": rep.penetration_max * 1e3})
            r = rows[-1]
            say(f"full model {slices}x{points} {method:5s}: {r['total_s'] * 1e3:7.0f} ms "
                f"(pre-assignment {r['preassign_s'] * 1e3:.0f} ms), coverage "
                f"{r['coverage']:.1%} (worst slice {r['coverage_worst_slice']:.1%}), "
                f"{r['penetrating_samples']} penetrating samples, deepest "
                f"{r['penetration_max_mm']:.3f} mm")
            if (slices, points) == (15, 15) and method in slice_charts:
                from oralnav.bench.plan_figures import slice_fits

                dense = slice_boundaries(mesh, model.z, DENSE_RAYS)
                slice_fits(model, dense, slice_charts[method],
                           f"FPSM 15 x 15 ({method}): coverage {rep.coverage:.1%}, "
                           f"{rep.penetrating_samples} penetrating samples")

    for r in rows:
        r["boundary"] = "plane"
    # the planner's model: slab envelopes (certifiable), and the rod check's grids on it
    reps, checks = [], []
    for _ in range(repeats):
        model, rep = build_fpsm(mesh, 15, 15, SAMPLES, settings=FITS["slp"],
                                boundary="envelope")
        t0 = time.perf_counter()
        RodCheck(model)
        checks.append(time.perf_counter() - t0)
        reps.append(rep)
    k = int(np.argsort([r.total_s for r in reps])[len(reps) // 2])
    rep = reps[k]
    env = {"slices": 15, "points": 15, "method": "slp", "boundary": "envelope",
           "total_s": rep.total_s, "preassign_s": rep.preassign_s, "fit_s": rep.fit_s,
           "rod_check_build_s": float(np.median(checks)),
           "coverage": rep.coverage, "coverage_plane": rep.coverage_plane,
           "coverage_worst_slice": min(r.coverage for r in rep.per_slice),
           "coverage_plane_worst_slice": min(r.coverage_plane for r in rep.per_slice),
           "penetrating_samples": rep.penetrating_samples,
           "penetration_max_mm": rep.penetration_max * 1e3,
           "excursion_max_mm": max(model.certificate.excursion) * 1e3}
    say(f"full model 15x15 slp on slab envelopes: {env['total_s'] * 1e3:.0f} ms + rod-check "
        f"grids {env['rod_check_build_s'] * 1e3:.0f} ms, coverage {env['coverage']:.1%} of "
        f"the envelopes, {env['coverage_plane']:.1%} of the plane cuts, "
        f"{env['penetrating_samples']} penetrating samples, excursion "
        f"{env['excursion_max_mm']:.3f} mm")

    def get(s: int, p: int, m: str) -> dict[str, Any] | None:
        return next((r for r in rows if (r["slices"], r["points"], r["method"]) == (s, p, m)),
                    None)

    ours = get(15, 15, "slp")
    if ours is None:
        raise ValueError("full_model needs the 15 x 15 slp build (the target's model)")
    # speed ratios of whatever pairs were built (a shortened run builds fewer)
    speed: dict[str, Any] = {}
    for s, p in sizes:
        base = {m: get(s, p, m) for m in ("paper", "slp", "lbfgs")}
        if base["paper"] is not None:
            speed[f"{s}x{p}"] = {f"paper_method_over_{m}": base["paper"]["total_s"]
                                 / base[m]["total_s"]
                                 for m in ("slp", "lbfgs") if base[m] is not None}
    for (s, p), paper_s in (((15, 15), 33.613), ((15, 20), 33.613), ((10, 10), 12.227)):
        r = get(s, p, "slp")
        if r is not None:
            speed[f"paper_{paper_s:.1f}s_over_slp_{s}x{p}"] = paper_s / r["total_s"]
    target = {"method": "slp", "total_s": ours["total_s"], "coverage": ours["coverage"],
              "penetrating_samples": ours["penetrating_samples"],
              "target": f"15x15 <= {BUILD_TARGET_S} s, coverage >= {COVERAGE_TARGET:.0%}, "
                        "no penetrating sample",
              "met": bool(ours["total_s"] <= BUILD_TARGET_S
                          and ours["coverage"] >= COVERAGE_TARGET
                          and ours["penetrating_samples"] == 0)}
    target["certified_model"] = {
        **env, "met_time": bool(env["total_s"] + env["rod_check_build_s"] <= BUILD_TARGET_S),
        "met_coverage_of_envelope": bool(env["coverage"] >= COVERAGE_TARGET),
        "met_coverage_of_plane": bool(env["coverage_plane"] >= COVERAGE_TARGET)}
    return {"samples": SAMPLES, "repeats": repeats, "rows": rows, "envelope": env,
            "speedup": speed, "target": target, "paper_s": PAPER_BUILD_S}


def chart_build(full: dict[str, Any], path: Path) -> Path:
    """:func:`full_model`'s builds as time (s) against coverage (%), the paper's C++
    times and the target marked, the legend beside the axes."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(8.4, 4.8))
    col = {"slp": "tab:blue", "lbfgs": "tab:green", "paper": "tab:red"}
    shapes = iter("osD^vP")
    mk = {size: next(shapes, "o") for size in dict.fromkeys(
        (r["slices"], r["points"]) for r in full["rows"])}
    for r in full["rows"]:
        ax.plot(r["total_s"], r["coverage"] * 100, mk[(r["slices"], r["points"])],
                color=col[r["method"]], ms=8,
                mfc=col[r["method"]] if r["penetrating_samples"] == 0 else "none")
        ax.annotate(f"{r['slices']}x{r['points']}", (r["total_s"], r["coverage"] * 100),
                    textcoords="offset points", xytext=(6, -3), fontsize=7)
    for label, s in (("paper C++ 15 slices", 33.613), ("paper C++ 10x10", 12.227)):
        ax.axvline(s, color="k", ls=":", lw=0.8)
        ax.text(s, 99, label, rotation=90, fontsize=7, ha="right", va="top")
    ax.axvline(BUILD_TARGET_S, color="tab:purple", lw=0.8)
    ax.axhline(COVERAGE_TARGET * 100, color="tab:purple", lw=0.8,
               label="target: <= 1 s at >= 90 % (15x15)")
    built = {r["method"] for r in full["rows"]}
    for m, c in col.items():
        if m in built:
            ax.plot([], [], "o", color=c,
                    label=m if m != "paper" else "paper eqs. 7-9 (here)")
    ax.plot([], [], "o", color="gray", mfc="none", label="open: penetrating samples")
    ax.set_xscale("log")
    ax.set_ylim(50, 100)
    ax.set_xlabel("build time: pre-assignment + fit (s)")
    ax.set_ylabel("coverage (%)")
    ax.set_title("full model on the parametric mouth: speed against accuracy", fontsize=10)
    ax.grid(alpha=0.3, which="both")
    # beside the axes: inside, the legend covered the fast builds' points
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


# -- 3. FPSM against the exact mesh -----------------------------------------------------

class MeshOracle:
    """python-fcl on the full mesh: rod (capsule) collisions and axis clearances."""

    def __init__(self, mesh: Any):
        import fcl

        self.fcl = fcl
        t0 = time.perf_counter()
        bvh = fcl.BVHModel()
        bvh.beginModel(len(mesh.vertices), len(mesh.faces))
        bvh.addSubModel(np.asarray(mesh.vertices, dtype=float),
                        np.asarray(mesh.faces, dtype=np.int32))
        bvh.endModel()
        self.obj = fcl.CollisionObject(bvh, fcl.Transform())
        self.build_s = time.perf_counter() - t0

    @staticmethod
    def _frame(T: np.ndarray, E: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        # fcl's capsule lies along its local z, centred: rotate z onto E - T
        v = E - T
        L = float(np.linalg.norm(v))
        d = v / L
        w = np.array([-d[1], d[0], 0.0])          # z x d
        c = float(d[2])
        K = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
        R = np.eye(3) + K + K @ K / (1.0 + c)      # c > 0: rods point toward +z
        return R, 0.5 * (T + E), L

    def collides(self, T: np.ndarray, E: np.ndarray, r: float) -> bool:
        fcl = self.fcl
        R, mid, L = self._frame(T, E)
        rod = fcl.CollisionObject(fcl.Capsule(r, L), fcl.Transform(R, mid))
        return fcl.collide(rod, self.obj, fcl.CollisionRequest(), fcl.CollisionResult()) > 0

    def collides_cylinder(self, T: np.ndarray, E: np.ndarray, r: float) -> bool:
        """The same rod with flat ends (the paper's rod starts at T; the capsule's caps
        reach r behind T and beyond E)."""
        fcl = self.fcl
        R, mid, L = self._frame(T, E)
        rod = fcl.CollisionObject(fcl.Cylinder(r, L), fcl.Transform(R, mid))
        return fcl.collide(rod, self.obj, fcl.CollisionRequest(), fcl.CollisionResult()) > 0

    def clearance(self, T: np.ndarray, E: np.ndarray) -> float:
        """Exact distance (m) from the segment T-E to the mesh; 0 when it cuts it."""
        fcl = self.fcl
        R, mid, L = self._frame(T, E)
        axis = fcl.CollisionObject(fcl.Capsule(0.0, L), fcl.Transform(R, mid))
        d = fcl.distance(axis, self.obj, fcl.DistanceRequest(), fcl.DistanceResult())
        return max(float(d), 0.0)


def sample_rods(mesh: Any, model: FPSM, n: int, rng: np.random.Generator
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``n`` rod axes: starts T inside the cavity, unit directions D within
    :data:`MAX_TILT_DEG` of +z, ends E on the last slice plane."""
    z0, z1 = float(model.z[0]), float(model.z[-1])
    zs = rng.uniform(z0, z1 - 0.005, n)
    phi = rng.uniform(0.0, 2.0 * math.pi, n)
    frac = np.sqrt(rng.random(n))        # uniform over the cross-section's area
    T = np.empty((n, 3))
    for i, seg in enumerate(cut_segments(mesh, zs)):
        # the exact boundary radius along phi: turn the cut by -phi and read ray 0
        c, s = math.cos(phi[i]), math.sin(phi[i])
        rot = seg @ np.array([[c, -s], [s, c]])
        rb = float(ray_radii(rot, 4)[0])
        if not np.isfinite(rb):
            raise PlanningError(f"the mesh cut at z = {zs[i] * 1e3:.1f} mm is open at "
                                f"{math.degrees(phi[i]):.1f} deg")
        T[i] = (frac[i] * rb * c, frac[i] * rb * s, zs[i])
    cos_t = rng.uniform(math.cos(math.radians(MAX_TILT_DEG)), 1.0, n)
    sin_t = np.sqrt(1.0 - cos_t ** 2)
    az = rng.uniform(0.0, 2.0 * math.pi, n)
    D = np.stack([sin_t * np.cos(az), sin_t * np.sin(az), cos_t], axis=1)
    E = T + ((z1 - T[:, 2]) / D[:, 2])[:, None] * D
    return T, D, E


def _exact(oracle: MeshOracle, T: np.ndarray, E: np.ndarray, r: float) -> dict[str, Any]:
    """The mesh's answers for rods of radius ``r`` on the axes T-E."""
    n = len(T)
    return {"hit": np.array([oracle.collides(T[i], E[i], r) for i in range(n)]),
            "hit_flat": np.array([oracle.collides_cylinder(T[i], E[i], r) for i in range(n)]),
            "clear": np.array([oracle.clearance(T[i], E[i]) for i in range(n)])}


def _check_rods(model: FPSM, T: np.ndarray, D: np.ndarray, E: np.ndarray, r: float,
                shrink: float, exact: dict[str, Any]) -> dict[str, Any]:
    """The FPSM's answers (eq. 13's d_min > 0 with eq. 12's shrink) against ``exact``."""
    d, _ = line_safe_distances(model, T, D, shrink=shrink)
    dmin = np.nanmin(d, axis=1)
    fpsm_safe = dmin > 0
    hit, hit_cyl, clear = exact["hit"], exact["hit_flat"], exact["clear"]
    pen = r - clear                              # > 0: the rod cuts the mesh this deep
    false_safe = fpsm_safe & hit
    fs_pen = pen[false_safe]
    worst = np.argsort(-np.where(false_safe, pen, -np.inf))[:min(10, int(false_safe.sum()))]
    # why each false-safe rod was missed: the model's safe distance (eqs. 10-12) sampled
    # every 0.25 mm along the whole axis, not only at T and the slice crossings. If that
    # finds the contact, the miss is the sparse sampling of eq. 13; if not, it is the
    # model itself (the curve fit, eq. 11's interpolation between slices, and eq. 12's
    # shrink along rays from the slice origin, which is no offset of the curve by r)
    why = {"sampling": 0, "model": 0}
    for i in np.flatnonzero(false_safe):
        L = float(np.linalg.norm(E[i] - T[i]))
        u = np.linspace(0.0, 1.0, max(2, int(math.ceil(L / 2.5e-4)) + 1))
        dense = model.safe_distance(T[i] + u[:, None] * (E[i] - T[i]), shrink=shrink)
        why["sampling" if np.min(dense) <= 0 else "model"] += 1
    return {
        "rods": len(T), "rod_radius_mm": r * 1e3, "shrink_mm": shrink * 1e3,
        "model_slices": model.slices,
        "true_safe": int(np.sum(fpsm_safe & ~hit)), "true_collide": int(np.sum(~fpsm_safe & hit)),
        "false_safe": int(false_safe.sum()), "false_alarm": int(np.sum(~fpsm_safe & ~hit)),
        "exact_safe": int(np.sum(~hit)),
        "false_safe_penetration_mm": _stats(fs_pen * 1e3),
        "false_safe_missed_by": why,
        "false_safe_flat_ended_rod": int(np.sum(fpsm_safe & hit_cyl)),
        "exact_safe_flat_ended_rod": int(np.sum(~hit_cyl)),
        # the capsule test and the clearance must agree; count where they do not
        "oracle_disagreements": int(np.sum(hit != (clear < r))),
        "worst_false_safe": [{"T_mm": (T[i] * 1e3).round(3).tolist(),
                              "D": D[i].round(5).tolist(),
                              "penetration_mm": float(pen[i] * 1e3),
                              "fpsm_dmin_mm": float(dmin[i] * 1e3)} for i in worst],
        "_scatter": {"clear_minus_r_mm": (clear - r) * 1e3, "dmin_mm": dmin * 1e3,
                     "false_safe": false_safe},
    }


def _time_rods(model: FPSM, oracle: MeshOracle, T: np.ndarray, D: np.ndarray,
               E: np.ndarray, r: float, batch_repeats: int) -> dict[str, Any]:
    n = len(T)
    t_f, t_c, t_d = np.empty(n), np.empty(n), np.empty(n)
    for i in range(n):
        t0 = time.perf_counter()
        d, _ = line_safe_distances(model, T[i:i + 1], D[i:i + 1], shrink=r)
        bool(np.nanmin(d) > 0)
        t1 = time.perf_counter()
        oracle.collides(T[i], E[i], r)
        t2 = time.perf_counter()
        oracle.clearance(T[i], E[i])
        t3 = time.perf_counter()
        t_f[i], t_c[i], t_d[i] = t1 - t0, t2 - t1, t3 - t2
    batch = []
    for _ in range(batch_repeats):
        t0 = time.perf_counter()
        d, _ = line_safe_distances(model, T, D, shrink=r)
        _ = np.nanmin(d, axis=1) > 0      # the answer, as the single call computes it
        batch.append((time.perf_counter() - t0) / n)
    fpsm1 = float(np.median(t_f))
    fb = float(np.median(batch))
    coll = float(np.median(t_c))
    return {"rods": n, "fpsm_single_us": fpsm1 * 1e6, "fpsm_batched_us_per_rod": fb * 1e6,
            "fcl_collide_us": coll * 1e6, "fcl_distance_us": float(np.median(t_d)) * 1e6,
            "ratio_fcl_collide_over_fpsm_single": coll / fpsm1,
            "ratio_fcl_collide_over_fpsm_batched": coll / fb,
            "ratio_fcl_distance_over_fpsm_single": float(np.median(t_d)) / fpsm1,
            "target_ratio": SPEED_RATIO_TARGET,
            "met_single": bool(coll / fpsm1 >= SPEED_RATIO_TARGET),
            "met_batched": bool(coll / fb >= SPEED_RATIO_TARGET)}


def fpsm_vs_mesh(scene: PlanningScene, quick: bool) -> dict[str, Any]:
    """The scene's FPSM (the planner's model) against fcl on its mesh."""
    mesh, certified = scene.mesh, scene.model
    # eq. 13's query as the paper has it: curves fitted to the plane cuts
    model = build_fpsm(mesh, certified.slices, certified.points, SAMPLES,
                       settings=FitSettings(method=scene.build.method if scene.build
                                            else "slp"), boundary="plane")[0]
    n = 1000 if quick else 2000
    oracle = MeshOracle(mesh)
    _say(f"fpsm vs mesh: fcl BVH of {len(mesh.faces)} triangles built in "
         f"{oracle.build_s * 1e3:.0f} ms; {n} rods per radius")
    res: dict[str, Any] = {"model": {"slices": model.slices, "points": model.points,
                                     "method": scene.build.method if scene.build else None,
                                     "z_mm": [float(model.z[0] * 1e3),
                                              float(model.z[-1] * 1e3)]},
                           "rods_per_radius": n, "max_tilt_deg": MAX_TILT_DEG,
                           "fcl_build_s": oracle.build_s,
                           "exact": "python-fcl: capsule of radius r on the axis segment "
                                    "T..E (collide); axis clearance by fcl.distance",
                           "by_radius": [], "with_margin": [], "timing": []}
    # denser models whose planes include the 15 of the planner's (3 and 1.5 mm apart, the
    # same first and last plane): how much of the margin is the slice spacing
    res["slice_spacing_mm"] = float(model.z[1] - model.z[0]) * 1e3
    denser = {}
    for m in (2 * model.slices - 1, 4 * model.slices - 3):
        h = (model.z[-1] - model.z[0]) / (m - 1)
        lo = float(model.z[0] - h / 2)
        denser[m] = build_fpsm(mesh, m, model.points, SAMPLES, (lo, lo + m * h),
                               FitSettings(method=res["model"]["method"] or "slp"),
                               boundary="plane")[0]
    res["by_slices"] = []
    for k, r in enumerate(ROD_RADII):
        T, D, E = sample_rods(mesh, model, n, np.random.default_rng([4, k, 0]))
        exact = _exact(oracle, T, E, r)
        c = _check_rods(model, T, D, E, r, r, exact)
        res["by_radius"].append(c)
        for m, dm in denser.items():
            cm = _check_rods(dm, T, D, E, r, r, exact)
            cm["slice_spacing_mm"] = (dm.z[1] - dm.z[0]) * 1e3
            res["by_slices"].append(cm)
            pm = cm["false_safe_penetration_mm"]
            _say(f"  r = {r * 1e3:.0f} mm, {m} slices ({cm['slice_spacing_mm']:.1f} mm apart):"
                 f" {cm['false_safe']} false safe (deepest {pm['max'] if pm else 0:.3f} mm; "
                 f"missed by {cm['false_safe_missed_by']}), {cm['false_alarm']} false alarms")
        p = c["false_safe_penetration_mm"]
        _say(f"  r = {r * 1e3:.0f} mm: {c['true_safe']} true safe, {c['true_collide']} true "
             f"collide, {c['false_safe']} false safe (deepest "
             f"{p['max'] if p else 0:.3f} mm; missed by {c['false_safe_missed_by']}; "
             "flat-ended rod: "
             f"{c['false_safe_flat_ended_rod']} false safe), {c['false_alarm']} false alarms")
    margin = max((c["false_safe_penetration_mm"]["max"] for c in res["by_radius"]
                  if c["false_safe_penetration_mm"]), default=0.0) * 1e-3
    res["margin_mm"] = margin * 1e3
    res["margin_by_radius_mm"] = {
        f"{c['rod_radius_mm']:.0f}": (c["false_safe_penetration_mm"]["max"]
                                      if c["false_safe_penetration_mm"] else 0.0)
        for c in res["by_radius"]}
    for k, r in enumerate(ROD_RADII):
        # a fresh rod set: the margin is checked on rods it was not measured on
        T, D, E = sample_rods(mesh, model, n, np.random.default_rng([4, k, 1]))
        c = _check_rods(model, T, D, E, r, r + margin, _exact(oracle, T, E, r))
        res["with_margin"].append(c)
        p = c["false_safe_penetration_mm"]
        _say(f"  fresh rods, r = {r * 1e3:.0f} mm, shrink r + {margin * 1e3:.2f} mm: "
             f"{c['false_safe']} false safe (deepest {p['max'] if p else 0:.3f} mm), "
             f"{c['false_alarm']} false alarms of {c['exact_safe']} exactly safe")
        nt = 200 if quick else 500
        tm = _time_rods(model, oracle, T[:nt], D[:nt], E[:nt], r, 5 if quick else 20)
        tm["rod_radius_mm"] = r * 1e3
        res["timing"].append(tm)
        _say(f"  timing r = {r * 1e3:.0f} mm: FPSM {tm['fpsm_single_us']:.1f} us per call, "
             f"{tm['fpsm_batched_us_per_rod']:.2f} us per rod batched; fcl collide "
             f"{tm['fcl_collide_us']:.1f} us, distance {tm['fcl_distance_us']:.1f} us")
    res["certified"] = _certified_rods(certified, oracle, mesh, n, quick)
    return res


def _certified_rods(model: FPSM, oracle: MeshOracle, mesh: Any, n: int,
                    quick: bool) -> dict[str, Any]:
    """The certified rod check (:mod:`oralnav.control.planning.rod_check`) on the planner's model
    (slab envelopes) against fcl: false safes (must be none), false alarms, how far below
    the exact clearance it certifies, and its speed against fcl's, one rod a call and
    batched, on the same rods."""
    t0 = time.perf_counter()
    rc = RodCheck(model)
    out: dict[str, Any] = {"rod_check_build_s": time.perf_counter() - t0,
                           "grid_mm": rc.h * 1e3, "cap_mm": rc.cap * 1e3,
                           "tol_mm": rc.tol * 1e3, "by_radius": []}
    for k, r in enumerate(ROD_RADII):
        T, D, E = sample_rods(mesh, model, n, np.random.default_rng([4, k, 2]))
        ex = _exact(oracle, T, E, r)
        c = rc.clearances(T, E, r)
        safe = c > 0
        hit = ex["hit"]
        exact_c = ex["clear"] - r
        # how tight: the largest need (exact - slack) the check still certifies
        ok = (exact_c > 0) & (exact_c + r < rc.cap)
        tight = [float(exact_c[i] - rc.clearance(T[i], E[i], r, need=0.0))
                 for i in np.flatnonzero(ok)[:300]]
        nt = 200 if quick else 500
        t_c, t_f, t_d = [], [], []
        for i in range(nt):
            a = time.perf_counter()
            rc.clearance(T[i], E[i], r)
            b = time.perf_counter()
            oracle.collides(T[i], E[i], r)
            c2 = time.perf_counter()
            oracle.clearance(T[i], E[i])
            t_c.append(b - a)
            t_f.append(c2 - b)
            t_d.append(time.perf_counter() - c2)
        batch = []
        for _ in range(5 if quick else 20):
            a = time.perf_counter()
            rc.clearances(T[:nt], E[:nt], r)
            batch.append((time.perf_counter() - a) / nt)
        single, batched = float(np.median(t_c)), float(np.median(batch))
        coll, dist = float(np.median(t_f)), float(np.median(t_d))
        row = {"rod_radius_mm": r * 1e3, "rods": n, "exact_safe": int(np.sum(~hit)),
               "certified_safe": int(safe.sum()), "false_safe": int(np.sum(safe & hit)),
               "false_alarm": int(np.sum(~safe & ~hit)),
               "bound_over_exact_max_mm": float(np.max((c - exact_c)[safe]) * 1e3)
               if safe.any() else None,
               "slack_to_certify_mm": _stats(np.asarray(tight) * 1e3),
               "single_us": single * 1e6, "batched_us_per_rod": batched * 1e6,
               "fcl_collide_us": coll * 1e6, "fcl_distance_us": dist * 1e6,
               "ratio_fcl_collide_over_single": coll / single,
               "ratio_fcl_collide_over_batched": coll / batched,
               "ratio_fcl_distance_over_batched": dist / batched,
               "target_ratio": SPEED_RATIO_TARGET,
               "met_batched": bool(coll / batched >= SPEED_RATIO_TARGET),
               "met_single": bool(coll / single >= SPEED_RATIO_TARGET)}
        out["by_radius"].append(row)
        _say(f"  certified r = {r * 1e3:.0f} mm: {row['certified_safe']} certified of "
             f"{row['exact_safe']} exactly safe, {row['false_safe']} false safe, "
             f"{row['false_alarm']} false alarms; {row['single_us']:.2f} us a call, "
             f"{row['batched_us_per_rod']:.2f} us a rod batched; fcl collide "
             f"{row['fcl_collide_us']:.1f} us ({row['ratio_fcl_collide_over_batched']:.0f}x "
             f"batched, {row['ratio_fcl_collide_over_single']:.0f}x single)")
    out["false_safe_total"] = sum(r["false_safe"] for r in out["by_radius"])
    return out


def _chart_rods(doc: dict[str, Any], out: Path) -> Path:
    plt = _plt()
    fm = doc["fpsm_vs_mesh"]
    fig, axes = plt.subplots(1, len(fm["by_radius"]), figsize=(5 * len(fm["by_radius"]), 4.6),
                             squeeze=False)
    for ax, c in zip(axes[0], fm["by_radius"], strict=True):
        sc = c["_scatter"]
        # rods that leave through the wall reach d_min of -100 mm and more: the window
        # shows the decision boundary, outliers sit on its edge
        lo, hi = -8.0, 12.0
        x = np.clip(sc["clear_minus_r_mm"], lo, hi)
        y = np.clip(sc["dmin_mm"], lo, hi)
        fs = sc["false_safe"]
        ax.axvspan(lo, 0, ymin=(0 - lo) / (hi - lo), ymax=1, color="tab:red", alpha=0.08,
                   label="false safe: FPSM clear, mesh hit")
        ax.axhline(0, color="k", lw=0.6)
        ax.axvline(0, color="k", lw=0.6)
        ax.plot(x[~fs], y[~fs], ".", ms=2, color="tab:blue", alpha=0.5, label="rods")
        ax.plot(x[fs], y[fs], "x", ms=5, color="tab:red",
                label=f"false safe ({c['false_safe']})")
        ax.plot([lo, hi], [lo, hi], ":", color="gray", lw=0.8, label="y = x")
        ax.set_xlim(lo, hi)
        ax.set_ylim(lo, hi)
        ax.set_xlabel("exact: axis clearance - r (mm; < 0: rod cuts the mesh)")
        ax.set_ylabel("FPSM: d_min of eq. 13 (mm)")
        ax.set_title(f"r = {c['rod_radius_mm']:.0f} mm: {c['true_safe']} safe, "
                     f"{c['true_collide']} collide, {c['false_safe']} false safe, "
                     f"{c['false_alarm']} false alarm", fontsize=8)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="lower right")
    fig.suptitle(f"FPSM ({fm['model']['slices']} x {fm['model']['points']}, "
                 f"{fm['model']['method']}) against the exact mesh (python-fcl capsule); "
                 f"{fm['rods_per_radius']} rods a radius, values clipped to the window; "
                 f"margin {fm['margin_mm']:.2f} mm", fontsize=10)
    fig.tight_layout()
    path = out / "planning_fpsm_vs_mesh.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


# -- 4. PSO -----------------------------------------------------------------------------

def _constrained(problem: PlacementProblem, check: RodCheck | None
                 ) -> Callable[[np.ndarray], np.ndarray]:
    """The objective the planner minimises: eq. 14 plus, on a certified model, the
    penalty on lines not certified clear (:func:`~oralnav.control.planning.placement.place`)."""
    if check is None:
        return problem.evaluate
    penalty = uncertified_penalty(check, problem)
    return lambda x: problem.evaluate(x) + penalty(np.atleast_2d(x))


def _reference(problem: PlacementProblem, n_d: int, n_theta: int,
               check: RodCheck | None = None) -> dict[str, Any]:
    """The grid optimum of the planner's objective, polished by Nelder-Mead from the best
    cell."""
    objective = _constrained(problem, check)
    t0 = time.perf_counter()
    d = np.linspace(*problem.s.d_range, n_d)
    th = np.linspace(*problem.s.theta_range, n_theta)
    D, TH = np.meshgrid(d, th)
    F = objective(np.stack([D.ravel(), TH.ravel()], axis=1)).reshape(TH.shape)
    grid_s = time.perf_counter() - t0
    k = np.unravel_index(int(np.argmin(F)), F.shape)
    x0 = np.array([d[k[1]], th[k[0]]])
    f0 = float(F[k])
    lo = np.array([problem.s.d_range[0], problem.s.theta_range[0]])
    hi = np.array([problem.s.d_range[1], problem.s.theta_range[1]])
    step = np.array([d[1] - d[0], th[1] - th[0]])
    simplex = np.array([x0, x0 + [step[0], 0.0], x0 + [0.0, step[1]]])
    nm = minimize(lambda x: float(objective(np.clip(x, lo, hi)[None])[0]), x0,
                  method="Nelder-Mead",
                  options={"initial_simplex": simplex, "xatol": 1e-8, "fatol": 1e-12,
                           "maxiter": 2000})
    x = np.clip(nm.x, lo, hi)
    f = float(objective(x[None])[0])
    if f > f0:
        x, f = x0, f0
    return {"grid": [n_d, n_theta], "grid_s": grid_s,
            "grid_best": {"d_T_mm": x0[0] * 1e3, "theta_T_deg": math.degrees(x0[1]),
                          "objective": f0},
            "reference": {"d_T_mm": x[0] * 1e3, "theta_T_deg": math.degrees(x[1]),
                          "objective": f},
            "grid_cells_within_gap_ok": int(np.sum(F <= f + GAP_OK))}


def _time_objective(problem: PlacementProblem, particles: int) -> dict[str, float]:
    """One swarm's objective (us, median of 2000): the compiled kernel the search runs
    and the numpy reference it replaced, on the same random placements."""
    s = problem.s
    rng = np.random.default_rng(5)
    x = np.column_stack([rng.uniform(*s.d_range, particles), rng.uniform(*s.theta_range,
                                                                         particles)])
    out = {}
    for name, f in (("compiled", problem.evaluate), ("numpy", problem.evaluate_numpy)):
        f(x)
        t = []
        for _ in range(2000):
            t0 = time.perf_counter()
            f(x)
            t.append(time.perf_counter() - t0)
        out[name] = float(np.median(t)) * 1e6
    out["ratio"] = out["numpy"] / out["compiled"]
    return out


def _pso_runs(scene: PlanningScene, problem: PlacementProblem, ref: float, seeds: range,
              particles: int, c0: float, check: RodCheck | None) -> list[dict[str, Any]]:
    out = []
    for seed in seeds:
        s = replace(scene.settings, pso=replace(scene.settings.pso, particles=particles,
                                                c0=c0, seed=seed))
        t0 = time.perf_counter()
        p = place(scene.model, scene.hole, s, check)
        wall = (time.perf_counter() - t0) * 1e3
        out.append({"particles": particles, "c0": c0, "seed": seed, "time_ms": p.time_ms,
                    "wall_ms": wall, "iterations": p.iterations,
                    "evaluations": p.evaluations, "objective": p.objective,
                    "gap": p.objective - ref, "d_T_mm": p.d_T * 1e3,
                    "theta_T_deg": math.degrees(p.theta_T),
                    "collision_free": p.collision_free})
    return out


def _pso_summary(runs: list[dict[str, Any]]) -> dict[str, Any]:
    gap = np.array([r["gap"] for r in runs])
    return {"particles": runs[0]["particles"], "c0": runs[0]["c0"], "runs": len(runs),
            "time_ms": _stats([r["time_ms"] for r in runs]),
            "wall_ms": _stats([r["wall_ms"] for r in runs]),
            "iterations": _stats([r["iterations"] for r in runs]),
            "gap": _stats(gap), "within_gap_ok": float(np.mean(gap <= GAP_OK)),
            "collision_free": float(np.mean([r["collision_free"] for r in runs]))}


def pso(cases: dict[str, PlanningScene], quick: bool, out: Path, *,
        particles: Sequence[int] = PARTICLES, inertias: Sequence[float] = INERTIAS,
        seeds: int | None = None, reference_grid: tuple[int, int] = (401, 361),
        contours: dict[str, Path] | None = None,
        say: Callable[[str], None] = _say) -> dict[str, Any]:
    """PSO on each scene of ``cases``: ``seeds`` runs (default 10 when ``quick``, else 20)
    at each swarm size of ``particles`` (with the scene's c0) and each inertia c0 of
    ``inertias`` (30 particles), against a reference optimum on a ``reference_grid``
    (d_T x theta_T cells) polished by Nelder-Mead; the scene's own settings' placement
    drawn on the objective's contour at ``contours[name]`` (default
    ``out/planning_contour_<name>.png``). The swarm sizes must include 30 (the target's)."""
    from oralnav.bench.plan_figures import objective_contour

    seeds = range((10 if quick else 20) if seeds is None else seeds)
    contours = contours or {}
    res: dict[str, Any] = {"seeds": len(seeds), "gap_ok": GAP_OK, "cases": {}}
    for name, scene in cases.items():
        problem = PlacementProblem(scene.model, scene.hole, scene.settings)
        check = RodCheck(scene.model) if scene.model.certificate is not None else None
        place(scene.model, scene.hole, scene.settings, check)        # warm-up
        objective_us = _time_objective(problem, scene.settings.pso.particles)
        say(f"pso {name}: objective of {scene.settings.pso.particles} particles "
            f"{objective_us['compiled']:.1f} us compiled, {objective_us['numpy']:.1f} us "
            "numpy")
        ref = _reference(problem, *reference_grid, check)
        fref = ref["reference"]["objective"]
        say(f"pso {name}: reference optimum {fref:.6f} at d_T "
            f"{ref['reference']['d_T_mm']:.3f} mm, theta_T "
            f"{ref['reference']['theta_T_deg']:.3f} deg (grid {ref['grid_s']:.1f} s)")
        runs, by_p, by_c0 = [], [], []
        for p in particles:
            rs = _pso_runs(scene, problem, fref, seeds, p, scene.settings.pso.c0, check)
            runs += rs
            by_p.append(_pso_summary(rs))
            s = by_p[-1]
            say(f"  {p:3d} particles: {s['time_ms']['median']:.1f} ms median "
                f"({s['time_ms']['p90']:.1f} p90), {s['iterations']['median']:.0f} iterations,"
                f" gap median {s['gap']['median']:.2e} p90 {s['gap']['p90']:.2e}, "
                f"{s['within_gap_ok']:.0%} within {GAP_OK:g}")
        for c0 in inertias:
            rs = _pso_runs(scene, problem, fref, seeds, 30, c0, check)
            runs += rs
            by_c0.append(_pso_summary(rs))
            s = by_c0[-1]
            say(f"  c0 = {c0}: {s['time_ms']['median']:.1f} ms, gap p90 {s['gap']['p90']:.2e},"
                f" {s['within_gap_ok']:.0%} within {GAP_OK:g}")
        default = place(scene.model, scene.hole, scene.settings, check)
        contour = objective_contour(problem, default,
                                    contours.get(name, out / f"planning_contour_{name}.png"))
        res["cases"][name] = {
            "scene": str(scene.path), "source": scene.source, **ref,
            "default": {"particles": scene.settings.pso.particles,
                        "c0": scene.settings.pso.c0, "d_T_mm": default.d_T * 1e3,
                        "theta_T_deg": math.degrees(default.theta_T),
                        "objective": default.objective, "time_ms": default.time_ms,
                        "iterations": default.iterations,
                        "collision_free": default.collision_free,
                        "gap": default.objective - fref},
            "objective_us": objective_us,
            "by_particles": by_p, "by_c0": by_c0, "runs": runs, "contour": str(contour)}
    at30 = [next(s for s in c["by_particles"] if s["particles"] == 30)
            for c in res["cases"].values()]
    res["target"] = {"time_ms_median_30_particles": {n: s["time_ms"]["median"] for n, s in
                                                     zip(res["cases"], at30, strict=True)},
                     "target_ms": PLACE_TARGET_MS, "paper_s": PAPER_PSO_S,
                     "met": all(s["time_ms"]["median"] <= PLACE_TARGET_MS for s in at30)}
    return res


def _chart_pso(doc: dict[str, Any], out: Path) -> Path:
    plt = _plt()
    cases = doc["pso"]["cases"]
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.8))
    floor = 1e-10
    for (name, c), col in zip(cases.items(), ("tab:blue", "tab:orange"), strict=False):
        for key, mk, lab in (("by_particles", "o", "swarm size"), ("by_c0", "s", "c0 at 30")):
            ss = c[key]
            t = [s["time_ms"]["median"] for s in ss]
            for ax, g in ((axes[0], [max(s["gap"]["median"], floor) for s in ss]),
                          (axes[1], [max(s["gap"]["p90"], floor) for s in ss]),
                          (axes[2], [s["within_gap_ok"] * 100 for s in ss])):
                ax.plot(t, g, mk, color=col, ms=6, mfc=col if key == "by_particles" else "none",
                        label=f"{name}: {lab}")
                for s, ti, gi in zip(ss, t, g, strict=True):
                    tag = s["particles"] if key == "by_particles" else f"c0={s['c0']}"
                    ax.annotate(str(tag), (ti, gi), textcoords="offset points",
                                xytext=(4, 3), fontsize=6, color=col)
    for ax, what in ((axes[0], "gap to the reference, median"),
                     (axes[1], "gap to the reference, 90th percentile"),
                     (axes[2], f"runs within {GAP_OK:g} of the reference (%)")):
        ax.axvline(PLACE_TARGET_MS, color="tab:purple", lw=0.8, label="target 20 ms")
        if ax is not axes[2]:
            ax.axhline(GAP_OK, color="gray", ls=":", lw=0.8, label=f"gap {GAP_OK:g}")
            ax.set_yscale("log")
        ax.set_xlabel("PSO time, median (ms)")
        ax.set_ylabel(what)
        ax.grid(alpha=0.3, which="both")
    axes[2].set_ylim(-5, 105)
    axes[0].legend(fontsize=7)
    fig.suptitle(f"PSO: speed against accuracy ({doc['pso']['seeds']} seeds a point, gaps "
                 f"floored at {floor:g}; the paper: {PAPER_PSO_S * 1e3:.0f} ms)", fontsize=10)
    fig.tight_layout()
    path = out / "planning_pso.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


# -- 5. Table 2 -------------------------------------------------------------------------

def table2(scene: PlanningScene, quick: bool, *, seeds: int | None = None,
           grid: tuple[int, int] = (241, 181),
           say: Callable[[str], None] = _say) -> dict[str, Any]:
    """The paper's Table 2 on ``scene`` (its cylinder case): eqs. 14, 21 and 22, line2
    shrunk and not, each placed with ``seeds`` PSO seeds (default 10 when ``quick``, else
    20) and its minimum found on a ``grid`` of (d_T, theta_T) cells (0.5 mm x 1 degree by
    default)."""
    seeds = range((10 if quick else 20) if seeds is None else seeds)
    rows = []
    check = RodCheck(scene.model)
    for eq in (14, 21, 22):
        for shrink2 in (True, False):
            s = replace(scene.settings, equation=eq, shrink_line2=shrink2)
            answers = [place(scene.model, scene.hole,
                             replace(s, pso=replace(s.pso, seed=k)), check) for k in seeds]
            problem = PlacementProblem(scene.model, scene.hole, s)
            d, th, F = problem.grid(*grid)
            best = float(F.min())
            ties = np.argwhere(F <= best + 1e-9)
            p0 = answers[0]
            rows.append({"equation": eq, "shrink_line2": shrink2,
                         "d_T_mm": p0.d_T * 1e3, "theta_T_deg": math.degrees(p0.theta_T),
                         "objective": p0.objective,
                         "d_T_mm_over_seeds": _stats([a.d_T * 1e3 for a in answers]),
                         "theta_T_deg_over_seeds": _stats([math.degrees(a.theta_T)
                                                           for a in answers]),
                         "grid_min_cells": len(ties),
                         # the grid cells that tie for the minimum (eq. 21 has a plateau)
                         "grid_min_d_T_mm": sorted({round(float(d[k] * 1e3), 3)
                                                    for k in ties[:, 1]}),
                         "grid_min_theta_T_deg": sorted({round(float(np.degrees(th[k])), 3)
                                                         for k in ties[:, 0]}),
                         "paper_d_T_mm": PAPER_TABLE2[eq][0],
                         "paper_theta_T_deg": PAPER_TABLE2[eq][1]})
            r = rows[-1]
            say(f"table 2, eq. {eq}, line2 {'shrunk' if shrink2 else 'not shrunk'}: d_T "
                f"{r['d_T_mm']:.3f} mm, theta_T {r['theta_T_deg']:.3f} deg (seeds: d_T "
                f"{r['d_T_mm_over_seeds']['min']:.2f}..{r['d_T_mm_over_seeds']['max']:.2f};"
                f" grid minimum in {r['grid_min_cells']} cells at d_T "
                f"{_list(r['grid_min_d_T_mm'])} mm); paper {PAPER_TABLE2[eq][0]} mm")
    return {"scene": str(scene.path), "seeds": len(seeds), "grid": list(grid), "rows": rows}


def _list(v: list[float], most: int = 6) -> str:
    if len(v) <= most:
        return ", ".join(f"{x:g}" for x in v)
    return f"{v[0]:g}..{v[-1]:g} ({len(v)} values)"


# -- the run ----------------------------------------------------------------------------

def _pin_blas_threads(n: int = 1) -> list[str]:
    """Limit BLAS to ``n`` threads for the rest of the run (threadpoolctl); returns what it
    limited.

    The fits multiply small matrices that gain nothing from BLAS threads, and on a shared
    2-core machine OpenBLAS's spinning workers make them 3-30x slower whenever another
    process runs (lbfgs 15 x 15: 0.4 s pinned, 1.9-16 s unpinned beside a busy process).
    Every method, ours and the baselines, runs under the same setting.
    """
    from threadpoolctl import threadpool_limits

    global _BLAS_LIMIT
    _BLAS_LIMIT = threadpool_limits(limits=n, user_api="blas")
    return [f"{i['internal_api']} {Path(i['filepath']).name}: {i['num_threads']} thread(s)"
            for i in _blas_info()]


def _blas_info() -> list[dict[str, Any]]:
    from threadpoolctl import threadpool_info

    return [i for i in threadpool_info() if i.get("user_api") == "blas"]


_BLAS_LIMIT: Any = None


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _plain(x: Any) -> Any:
    """The JSON form: private plot data dropped, numpy made plain."""
    if isinstance(x, dict):
        return {k: _plain(v) for k, v in x.items() if not str(k).startswith("_")}
    if isinstance(x, list | tuple):
        return [_plain(v) for v in x]
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def main(out: Path, quick: bool = False) -> dict[str, Any]:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    pinned = _pin_blas_threads(1)
    oral = load_planning_scene(_example("oral_cavity_case.toml"))
    cyl = load_planning_scene(_example("cylinder_case.toml"))
    doc: dict[str, Any] = {
        "bench": "planning", "quick": quick,
        "command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]),
        "machine": {**_machine(), "blas_threads_pinned": pinned,
                    "load_average_start": list(os.getloadavg())},
        "mouth": oral.source, "mouth_scene": str(oral.path),
        "mouth_faces": len(oral.mesh.faces), "paper_machine": "Intel i5-10200H 2.4 GHz, "
        "16 GB, Windows 10; Table 1 in MATLAB R2017b, the rest in C++"}
    sections = (("table1", lambda: table1(oral.mesh, quick)),
                ("full_model", lambda: full_model(oral.mesh, quick, out)),
                ("fpsm_vs_mesh", lambda: fpsm_vs_mesh(oral, quick)),
                ("pso", lambda: pso({"cylinder": cyl, "oral_cavity": oral}, quick, out)),
                ("table2", lambda: table2(cyl, quick)))
    doc["section_s"] = {}
    for name, run in sections:
        t0 = time.perf_counter()
        doc[name] = run()
        doc["section_s"][name] = time.perf_counter() - t0
        _say(f"[{name}: {doc['section_s'][name]:.1f} s]")
    charts = [*_chart_table1(doc, out), chart_build(doc["full_model"], out / "planning_build.png"),
              _chart_rods(doc, out), _chart_pso(doc, out)]
    charts += [Path(c["contour"]) for c in doc["pso"]["cases"].values()]
    charts += sorted(out.glob("planning_fpsm_slices_*.png"))
    doc["charts"] = [p.name for p in charts]
    doc["elapsed_s"] = time.perf_counter() - t_start
    # other processes share this machine's cores: the load says how quiet it was
    doc["machine"]["load_average_end"] = list(os.getloadavg())
    (out / "planning.json").write_text(json.dumps(_plain(doc), indent=1) + "\n")
    b, t = doc["full_model"]["target"], doc["pso"]["target"]
    fm = doc["fpsm_vs_mesh"]
    _say(f"15x15 slp build {b['total_s'] * 1e3:.0f} ms, coverage {b['coverage']:.1%}, "
         f"{b['penetrating_samples']} penetrating samples (target met: {b['met']}); "
         f"FPSM margin {fm['margin_mm']:.2f} mm; PSO 30 particles median "
         f"{', '.join(f'{k} {v:.1f} ms' for k, v in t['time_ms_median_30_particles'].items())}"
         f"; {doc['elapsed_s']:.0f} s; wrote {out}/planning.json and {len(charts)} charts")
    return doc
