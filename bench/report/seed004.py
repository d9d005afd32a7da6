"""Seed 004's experiments (preoperative planning) in simulation, each beside the paper's
figures: Table 1 / Fig. 15 (one slice's fit against the number of control points N), the
surrogate model's build time (§5.1, 33.6 s in C++), the Fig. 17 placement and its time
(0.299 s) and the cylinder case of Figs. 19-20 / Table 2 (the objectives of eqs. 14, 21
and 22).

The measurements are :mod:`oralnav.bench.planning`'s (``oralnav bench planning``), run here
at the report's sizes; the charts of the slices and the contours are
:mod:`oralnav.bench.plan_figures`'. The mouth is the parametric oral cavity of
``config/examples/oral_cavity_case.toml``, the cylinder the paper's case of
``config/examples/cylinder_case.toml``.

Units: lengths in mm, angles in degrees, coverage in % (curve area over the boundary's
area seen from the slice origin), fit and build times in s, placement times in ms; the
placement objective in the paper's units (eq. 14: mm^0.5, eq. 21: mm, eq. 22: mm^2;
smaller is safer). Every time is the median of repeats, with BLAS held to one thread.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, replace
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np

from oralnav.bench import planning
from oralnav.bench.plan_figures import OBJECTIVE_UNITS, objective_contour
from oralnav.bench.report.charts import legend_outside, plt, save
from oralnav.bench.report.context import Context, Experiment
from oralnav.bench.report.section import Row, Section, Target
from oralnav.config.planning import PlanningScene, load_planning_scene
from oralnav.control.planning.placement import PlacementProblem, place
from oralnav.control.planning.rod_check import RodCheck

__all__ = ["EXPERIMENTS", "FULL", "QUICK", "Sizes"]


@dataclass(frozen=True)
class Sizes:
    """How much each experiment measures.

    Attributes:
        table1_points: the N of Table 1 (the paper's 3..20).
        table1_fits: (fit variant of ``planning.FITS``, fits a time is the median of); the
            first is ours, the rest run as baselines.
        build_sizes: (slices, points) of the full models; must hold (15, 15).
        build_methods: fit variants of the full models; must hold "slp".
        build_repeats: builds each time is the median of.
        place_seeds: PSO seeds on the mouth (the time is their median).
        reference_grid: (d_T, theta_T) cells of the reference optimum's grid.
        table2_seeds: PSO seeds per objective on the cylinder.
        table2_grid: (d_T, theta_T) cells where each objective's minimum is found.
        contour_cells: cells a side of each contour chart.
    """

    table1_points: tuple[int, ...]
    table1_fits: tuple[tuple[str, int], ...]
    build_sizes: tuple[tuple[int, int], ...]
    build_methods: tuple[str, ...]
    build_repeats: int
    place_seeds: int
    reference_grid: tuple[int, int]
    table2_seeds: int
    table2_grid: tuple[int, int]
    contour_cells: int


#: ``--quick``: the paper's method only as Table 1's baseline (one fit a point: it costs
#: 20-60 ms a slice against slp's 5 ms), the full models by slp alone.
QUICK = Sizes(table1_points=tuple(range(3, 21)), table1_fits=(("slp", 3), ("paper", 1)),
              build_sizes=((10, 10), (15, 15), (15, 20)), build_methods=("slp",),
              build_repeats=3, place_seeds=20, reference_grid=(401, 361),
              table2_seeds=10, table2_grid=(241, 181), contour_cells=161)
FULL = Sizes(table1_points=tuple(range(3, 21)),
             table1_fits=(("slp", 5), ("lbfgs", 5), ("paper", 5), ("paper_table1", 5)),
             build_sizes=planning.BUILD_SIZES, build_methods=planning.BUILD_METHODS,
             build_repeats=3, place_seeds=50, reference_grid=(401, 361),
             table2_seeds=20, table2_grid=(241, 181), contour_cells=201)

#: Issue 6: "an order of magnitude or two faster at equal or better coverage and safety"
#: than the paper; Table 1's time per slice is held to a tenth of the paper's.
SPEEDUP_TARGET = 10.0
#: Issue 6: eq. 14 must give the cylinder's d_T = 65.5 mm and theta_T = 0; the tolerance
#: (ours) is well below the 0.5 mm x 1 degree grid the minimum is checked on.
TABLE2_TOL_MM = 0.1
TABLE2_TOL_DEG = 0.1
#: Eq. 21's documented failure: a minimum flat in d_T, at least this wide (mm) on the grid.
EQ21_FLAT_MM = 1.0
#: Eq. 22's documented failure: its minimum at least this far (mm) from eq. 14's 65.5 mm
#: (the paper's lands 15.5 mm away, at 81 mm).
EQ22_AWAY_MM = 5.0
#: The paper's Fig. 17 answer on its scan (d_T mm, theta_T deg, objective, PSO iterations).
PAPER_FIG17 = {"d_T_mm": 38.206, "theta_T_deg": -4.005, "objective": -2.611059,
               "iterations": 76}
#: Table 1's variants as the rows name them, and as the chart's legend does.
ROW_LABELS = {"lbfgs": "lbfgs (ours, smooth penalty)",
              "paper": "paper's eqs. 7-9 run here (C++ settings)",
              "paper_table1": "paper's eqs. 7-9 run here (Table-1 settings)"}
FIT_LABELS = {"slp": "ours: slp", "lbfgs": "ours: lbfgs",
              "paper": "paper's eqs. 7-9 here, C++ settings (lambda 3e4, alpha 0.1 mm)",
              "paper_table1": "paper's eqs. 7-9 here, Table-1 settings (lambda 2e4, "
                              "alpha 1.0 mm)"}
_STYLE = {"slp": ("o-", "tab:blue"), "lbfgs": ("s-", "tab:green"),
          "paper": ("^-", "tab:red"), "paper_table1": ("v--", "tab:orange")}


def _sizes(ctx: Context) -> Sizes:
    return QUICK if ctx.quick else FULL


@cache
def _scene(name: str) -> PlanningScene:
    """A shipped planning scene, loaded once a process (the mouth's mesh and certified
    model take about 2 s)."""
    return load_planning_scene(planning._example(name))


@contextmanager
def _one_blas_thread() -> Iterator[list[str]]:
    """BLAS held to one thread while timing, as ``oralnav bench planning`` does (on a
    shared 2-core machine its spinning workers slow the small fits 3-30x), and given back
    afterwards, so the report's other experiments keep their own setting."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        yield [f"{i['internal_api']}: {i['num_threads']} thread(s)"
               for i in planning._blas_info()]


def _machine(blas: list[str], load_start: tuple[float, ...]) -> dict[str, Any]:
    """What the times were measured under: the BLAS setting and the load average (other
    processes share this machine's cores) at the start and the end."""
    return {"blas": blas, "load_average_start": list(load_start),
            "load_average_end": list(os.getloadavg())}


def _pct(x: float) -> float:
    return float(x) * 100.0


# -- 004/table1: one slice against N -----------------------------------------------------

def table1(ctx: Context) -> Section:
    """Table 1 / Fig. 15: coverage (%) and time per slice (s) against N."""
    key = "004/table1"
    z = _sizes(ctx)
    ours = z.table1_fits[0][0]
    load0 = os.getloadavg()
    with _one_blas_thread() as blas:
        ctx.say("loading the parametric mouth")
        mouth = _scene("oral_cavity_case.toml")
        parts = []
        for method, repeats in z.table1_fits:
            ctx.say(f"table 1: {method} fits, N = {z.table1_points[0]}.."
                    f"{z.table1_points[-1]}, median of {repeats}")
            parts.append(planning.table1(mouth.mesh, ctx.quick, points=z.table1_points,
                                         fits={method: planning.FITS[method]},
                                         repeats=repeats, say=ctx.say))
    summary = [s for p in parts for s in p["summary"]]
    by = {(s["method"], s["points"]): s for s in summary}
    ns = list(z.table1_points)

    rows: list[Row] = []
    for n in ns:
        s = by[(ours, n)]
        paper_cov, paper_s = planning.PAPER_TABLE1[n]
        rows.append(Row(f"N = {n}: coverage", "%", paper_cov, _pct(s["coverage_mean"]),
                        note=f"{ours}, mean of {len(planning.TABLE1_SLICES)} slices"))
        rows.append(Row(f"N = {n}: time per slice", "s", paper_s, s["time_s_per_slice"],
                        Target("<=", paper_s / SPEEDUP_TARGET,
                               f"issue 6: {SPEEDUP_TARGET:g}x faster than the paper")))
    paper_mean = float(np.mean([planning.PAPER_TABLE1[n][0] for n in ns]))
    span = f"N = {ns[0]}..{ns[-1]}"
    for method, _ in z.table1_fits:
        ss = [by[(method, n)] for n in ns]
        mean_cov = _pct(np.mean([s["coverage_mean"] for s in ss]))
        pen = int(sum(s["penetrating_samples"] for s in ss))
        label = ROW_LABELS.get(method, method)
        if method == ours:
            rows.append(Row(f"coverage, mean over {span}", "%", round(paper_mean, 2), mean_cov,
                            Target(">=", round(paper_mean, 2),
                                   "issue 6: equal or better coverage than the paper"),
                            note=f"{ours}; the paper's on its own boundary (Fig. 7a)"))
            rows.append(Row(f"penetrating samples, all N and slices ({ours})", "samples",
                            None, pen, Target("<=", 0, "issue 6: no penetration")))
        else:
            rows.append(Row(f"{label}: coverage, mean over {span}", "%", round(paper_mean, 2),
                            mean_cov, note="run here, for comparison"))
            rows.append(Row(f"{label}: time per slice, mean over {span}", "s",
                            float(np.mean([planning.PAPER_TABLE1[n][1] for n in ns])),
                            float(np.mean([s["time_s_per_slice"] for s in ss])),
                            note="run here, for comparison"))
            rows.append(Row(f"{label}: penetrating samples, all N and slices", "samples",
                            None, pen, note="run here, for comparison"))

    ctx.say("table 1: chart")
    chart = _chart_table1(ctx.chart(key, "coverage_time"), summary,
                          [m for m, _ in z.table1_fits], ns)
    slices = ", ".join(f"{name} (z = {zz * 1e3:.1f} mm)" for name, zz in planning.TABLE1_SLICES)
    setup = (
        "The paper fits one complex boundary of its scan (its Fig. 7a) with N = 3..20 "
        "control points by its eqs. 7-9 (normalised gradient descent, numerical derivatives; "
        f"MATLAB R2017b, lambda 20000, alpha 1.0, Z = {planning.SAMPLES} samples) on an "
        "i5-10200H, and reports coverage and time per slice. The scan is not public: here "
        f"three slices of a parametric mouth ({slices}) are fitted at the same Z by ours, "
        f"{ours} (sequential LP, hard constraints), and, as baselines run in this process, "
        f"{', '.join(FIT_LABELS[m] for m, _ in z.table1_fits[1:]) or 'none'}. Coverage is "
        "the curve's area over the boundary's area seen from the slice origin (1440 rays), "
        "averaged over the three slices; each time is the median of "
        f"{', '.join(f'{r} ({m})' for m, r in z.table1_fits)} fits of one slice. The "
        "boundaries differ, so the coverage rows compare shapes of like difficulty, not the "
        "same shape; the time target is issue 6's order of magnitude over the paper.")
    data = {"slices": parts[0]["slices"], "samples": planning.SAMPLES,
            "repeats": {m: r for m, r in z.table1_fits},
            "settings": {k: v for p in parts for k, v in p["settings"].items()},
            "summary": summary, "per_slice": [r for p in parts for r in p["rows"]],
            "paper": {str(n): {"coverage_pct": c, "time_s": t}
                      for n, (c, t) in planning.PAPER_TABLE1.items()},
            "machine": _machine(blas, load0)}
    return Section(key, TITLES[key], setup, rows, [chart], planning._plain(data))


def _chart_table1(path: Path, summary: list[dict[str, Any]], methods: list[str],
                  ns: list[int]) -> str:
    """Coverage (%) and time per slice (s, log) against N, one axis each, every variant run
    and the paper's Table 1."""
    from matplotlib.ticker import MaxNLocator

    pyplot = plt()
    fig, (ax, at) = pyplot.subplots(2, 1, figsize=(8.6, 7.0), sharex=True)
    for method in methods:
        ss = sorted((s for s in summary if s["method"] == method), key=lambda s: s["points"])
        x = np.array([s["points"] for s in ss])
        cov = np.array([_pct(s["coverage_mean"]) for s in ss])
        mk, col = _STYLE.get(method, ("o-", "tab:gray"))
        # the Table-1 settings run away (coverage in the thousands of %): such points sit
        # on the top edge, hollow, so the axis keeps the others readable
        off = cov > 105.0
        ax.plot(x, np.where(off, np.nan, cov), mk, ms=4, color=col, label=FIT_LABELS[method])
        if off.any():
            ax.plot(x[off], np.full(int(off.sum()), 104.0), mk[0], ms=6, mfc="none",
                    color=col, ls="none",
                    label=f"{ROW_LABELS.get(method, method)}: coverage > 105 % (runs away)")
        at.plot(x, [s["time_s_per_slice"] for s in ss], mk, ms=4, color=col,
                label=FIT_LABELS[method])
    ax.plot(ns, [planning.PAPER_TABLE1[n][0] for n in ns], "k:", marker="x", ms=6,
            label="paper Table 1 (its Fig. 7a boundary, MATLAB)")
    at.plot(ns, [planning.PAPER_TABLE1[n][1] for n in ns], "k:", marker="x", ms=6,
            label="paper Table 1 (MATLAB, i5-10200H)")
    at.plot(ns, [planning.PAPER_TABLE1[n][1] / SPEEDUP_TARGET for n in ns], ":",
            color="tab:purple", label=f"target: paper / {SPEEDUP_TARGET:g} (issue 6)")
    ax.set_ylim(0, 106)
    ax.set_ylabel("coverage, mean of 3 slices (%)")
    at.set_yscale("log")
    at.set_ylabel("time per slice (s)")
    at.set_xlabel("control points N (count)")
    at.xaxis.set_major_locator(MaxNLocator(integer=True))
    for a in (ax, at):
        a.grid(alpha=0.3, which="both")
        legend_outside(a)
    ax.set_title("Table 1 / Fig. 15: one slice's fit against the control points")
    return save(fig, path)


# -- 004/build: the full model -----------------------------------------------------------

def build(ctx: Context) -> Section:
    """The FPSM's build: time (s), coverage (%), penetrating samples, against §5.1's 33.6 s."""
    key = "004/build"
    z = _sizes(ctx)
    load0 = os.getloadavg()
    charts_of = {m: ctx.chart(key, f"slices_{m}") for m in ("slp", "paper")
                 if m in z.build_methods}
    with _one_blas_thread() as blas:
        ctx.say("loading the parametric mouth")
        mouth = _scene("oral_cavity_case.toml")
        ctx.say(f"building {', '.join(f'{s} x {p}' for s, p in z.build_sizes)} by "
                f"{', '.join(z.build_methods)}, median of {z.build_repeats}")
        full = planning.full_model(mouth.mesh, ctx.quick, ctx.charts, sizes=z.build_sizes,
                                   methods=z.build_methods, repeats=z.build_repeats,
                                   slice_charts=charts_of, say=ctx.say)
    ctx.say("build: charts")
    charts = [planning.chart_build(full, ctx.chart(key, "time_coverage")).name]
    charts += [p.name for p in charts_of.values()]

    def get(s: int, p: int, m: str) -> dict[str, Any] | None:
        return next((r for r in full["rows"] if (r["slices"], r["points"], r["method"])
                     == (s, p, m)), None)

    paper15 = planning.PAPER_BUILD_S["15 slices (x15 per §5.1, x20 per §5.3)"]
    paper10 = planning.PAPER_BUILD_S["10x10"]
    ours = get(15, 15, "slp")
    assert ours is not None            # full_model raises without it
    issue = "issue 6"
    rows = [
        Row("15 x 15 build time (slp)", "s", paper15, ours["total_s"],
            Target("<=", planning.BUILD_TARGET_S, issue),
            note="paper: C++, 15 slices (15 points per its §5.1, 20 per §5.3); ours: "
                 "pre-assignment + fit"),
        Row("15 x 15 coverage (slp)", "%", None, _pct(ours["coverage"]),
            Target(">=", _pct(planning.COVERAGE_TARGET), issue),
            note=f"worst slice {_pct(ours['coverage_worst_slice']):.1f} %; the paper gives "
                 "no figure"),
        Row("15 x 15 penetrating samples (slp)", "samples", None,
            ours["penetrating_samples"], Target("<=", 0, issue),
            note=f"deepest excursion between samples {ours['penetration_max_mm']:.2f} mm"),
        Row("speed-up over the paper's 33.6 s (15 x 15 slp)", "x", None,
            paper15 / ours["total_s"]),
    ]
    for (s, p), paper_s, note in (((10, 10), paper10, "paper: C++"),
                                  ((15, 20), paper15, "paper: C++, §5.3's 15 x 20")):
        r = get(s, p, "slp")
        if r is not None:
            rows.append(Row(f"{s} x {p} build time (slp)", "s", paper_s, r["total_s"],
                            note=note))
            rows.append(Row(f"{s} x {p} coverage (slp)", "%", None, _pct(r["coverage"])))
    for m in z.build_methods:
        r = get(15, 15, m)
        if m == "slp" or r is None:
            continue
        name = "paper's eqs. 7-9 here" if m == "paper" else m
        rows.append(Row(f"15 x 15 build time ({name})", "s", paper15, r["total_s"],
                        note="run here, for comparison"))
        rows.append(Row(f"15 x 15 coverage ({name})", "%", None, _pct(r["coverage"]),
                        note="run here, for comparison"))
        rows.append(Row(f"15 x 15 penetrating samples ({name})", "samples", None,
                        r["penetrating_samples"], note="run here, for comparison"))
    env = full["envelope"]
    rows += [
        Row("certified 15 x 15 (slab envelopes): build + rod-check grids", "s", None,
            env["total_s"] + env["rod_check_build_s"],
            Target("<=", planning.BUILD_TARGET_S, issue),
            note="the planner's model: each curve clear of all tissue in its slab"),
        Row("certified 15 x 15: coverage of its envelopes", "%", None, _pct(env["coverage"]),
            Target(">=", _pct(planning.COVERAGE_TARGET), issue)),
        Row("certified 15 x 15: coverage of the plane cuts", "%", None,
            _pct(env["coverage_plane"]),
            note="below the envelopes' by construction: an envelope is the cut less the "
                 "tissue reaching in anywhere in the slab"),
        Row("certified 15 x 15: penetrating samples", "samples", None,
            env["penetrating_samples"], Target("<=", 0, issue)),
    ]
    setup = (
        "The paper's C++ solver builds the surrogate model (FPSM) of its scanned mouth, "
        "15 slices (15 control points by its §5.1, 20 by §5.3) at Z = 150 samples, lambda "
        "30000, alpha 0.1, 1000 iterations, in 33.613 s, and 10 x 10 in 12.227 s, on an "
        "i5-10200H; it reports no coverage for the whole model. Here the parametric mouth "
        "(55 x 45 x 90 mm, full arches but the lower left first molar) is built at "
        f"{', '.join(f'{s} x {p}' for s, p in z.build_sizes)} by "
        f"{', '.join(z.build_methods)}, from the mesh (pre-assignment: the plane cuts) to "
        "the fitted curves, each time the median of "
        f"{z.build_repeats} builds; coverage is over all slices on 1440 rays a slice, and a "
        "penetrating sample is a sampling ray whose curve point lies outside the tissue "
        "boundary. The planner's own model, fitted to slab envelopes and certified by the "
        "rod check, is built too. Targets: issue 6 (15 x 15 in <= 1 s at >= 90 % coverage, "
        "no penetrating sample).")
    data = {**full, "paper_s": planning.PAPER_BUILD_S,
            "target": {**full["target"], "build_s": planning.BUILD_TARGET_S,
                       "coverage": planning.COVERAGE_TARGET},
            "machine": _machine(blas, load0)}
    return Section(key, TITLES[key], setup, rows, charts, planning._plain(data))


# -- 004/fig17: the placement on the mouth -----------------------------------------------

def fig17(ctx: Context) -> Section:
    """The Fig. 17 placement: PSO time (ms) against the paper's 0.299 s, the answer (d_T
    mm, theta_T deg, objective mm^0.5) and its gap to a dense-grid optimum."""
    key = "004/fig17"
    z = _sizes(ctx)
    load0 = os.getloadavg()
    contour = ctx.chart(key, "contour")
    with _one_blas_thread() as blas:
        ctx.say("loading the parametric mouth")
        mouth = _scene("oral_cavity_case.toml")
        ctx.say(f"placing by PSO, {z.place_seeds} seeds, against a "
                f"{z.reference_grid[0]} x {z.reference_grid[1]} grid optimum")
        res = planning.pso({"oral_cavity": mouth}, ctx.quick, ctx.charts,
                           particles=(mouth.settings.pso.particles,), inertias=(),
                           seeds=z.place_seeds, reference_grid=z.reference_grid,
                           contours={"oral_cavity": contour}, say=ctx.say)
    case = res["cases"]["oral_cavity"]
    runs = case["by_particles"][0]
    default = case["default"]
    ref = case["reference"]
    unit = OBJECTIVE_UNITS[mouth.settings.equation]
    free = _pct(runs["collision_free"])
    rows = [
        Row(f"placement time (PSO, {runs['particles']} particles), median", "ms",
            planning.PAPER_PSO_S * 1e3, runs["time_ms"]["median"],
            Target("<=", planning.PLACE_TARGET_MS, "issue 6"),
            note=f"{runs['runs']} seeds; paper: C++, one run"),
        Row("placement time, 90th percentile", "ms", None, runs["time_ms"]["p90"]),
        Row("PSO iterations, median", "iterations", PAPER_FIG17["iterations"],
            runs["iterations"]["median"],
            note="stop: best unchanged 40 iterations (the paper's rule)"),
        Row("d_T", "mm", PAPER_FIG17["d_T_mm"], default["d_T_mm"],
            note="seed 0; another mouth, hole and rod than the paper's"),
        Row("theta_T", "deg", PAPER_FIG17["theta_T_deg"], default["theta_T_deg"],
            note="seed 0"),
        Row(f"objective at the placement (eq. {mouth.settings.equation})", unit,
            PAPER_FIG17["objective"], default["objective"], note="seed 0"),
        Row("gap to the reference optimum, median", unit, None, runs["gap"]["median"],
            note=f"reference {ref['objective']:.4f} at d_T {ref['d_T_mm']:.2f} mm, "
                 f"theta_T {ref['theta_T_deg']:.2f} deg (grid + Nelder-Mead)"),
        Row(f"seeds within {planning.GAP_OK:g} of the reference", "%", None,
            _pct(runs["within_gap_ok"])),
        Row("collision-free placements (certified)", "% of seeds",
            "collision-free (Fig. 17)", free,
            Target(">=", 100.0, "paper Fig. 17: the placement clears the tissue")),
    ]
    h = mouth.hole
    setup = (
        "The paper places its implanting instrument in its scanned mouth (hole at t_ch = "
        "(-10, -25, 50) mm, axis +y; rod radius 6 mm, implant 31 mm) by PSO over d_T and "
        "theta_T on eq. 14 (30 particles, c1 0.3, c2 0.4, lambda_avg = lambda_min = 0.5, "
        "stop when the best is unchanged 40 iterations): 0.299 s in C++ after 76 iterations, "
        "d_T = 38.206 mm, theta_T = -4.005 deg, objective -2.611 (Figs. 17-18, with the "
        "objective's contour). Here the parametric mouth's hole is at ("
        f"{', '.join(f'{v * 1e3:.2f}' for v in h.position)}) mm on the lower left molar "
        f"gap, with a {mouth.settings.rod_radius * 1e3:.0f} mm rod and a "
        f"{mouth.settings.implant_length * 1e3:.0f} mm implant (a 4 mm rod has no placement "
        "in this mouth), the same PSO settings (inertia c0 "
        f"{mouth.settings.pso.c0:g}, which the paper does not give) and the planner's "
        "certification: placements whose lines are not certified "
        f"{mouth.settings.min_clearance * 1e3:.1f} mm clear of the mesh are penalised. The "
        f"time is the solver's, the median over {runs['runs']} seeds; the reference optimum "
        f"is a {z.reference_grid[0]} x {z.reference_grid[1]} grid of the same objective "
        "polished by Nelder-Mead. The geometry differs from the paper's, so d_T, theta_T "
        "and the objective are shown, not held to its figures.")
    data = {"case": case, "target_ms": planning.PLACE_TARGET_MS,
            "paper": {**PAPER_FIG17, "time_s": planning.PAPER_PSO_S},
            "machine": _machine(blas, load0)}
    return Section(key, TITLES[key], setup, rows, [contour.name], planning._plain(data))


# -- 004/fig19_20: the cylinder and the objective variants -------------------------------

def fig19_20(ctx: Context) -> Section:
    """Table 2 / Figs. 19-20: the cylinder case's d_T (mm) and theta_T (deg) by eqs. 14,
    21 and 22, and each objective's contour."""
    key = "004/fig19_20"
    z = _sizes(ctx)
    load0 = os.getloadavg()
    with _one_blas_thread() as blas:
        cyl = _scene("cylinder_case.toml")
        ctx.say(f"table 2: eqs. 14, 21, 22 on the cylinder, {z.table2_seeds} seeds each")
        t2 = planning.table2(cyl, ctx.quick, seeds=z.table2_seeds, grid=z.table2_grid,
                             say=ctx.say)
        ctx.say("table 2: contours")
        check = RodCheck(cyl.model) if cyl.model.certificate is not None else None
        charts = []
        for eq in (14, 21, 22):
            s = replace(cyl.settings, equation=eq, shrink_line2=True)
            answer = place(cyl.model, cyl.hole, s, check)
            path = objective_contour(PlacementProblem(cyl.model, cyl.hole, s), answer,
                                     ctx.chart(key, f"contour_eq{eq}"), n=z.contour_cells,
                                     title=f"cylinder case, eq. {eq} (Fig. 20)")
            charts.append(path.name)

    def row(eq: int, shrunk: bool = True) -> dict[str, Any]:
        return next(r for r in t2["rows"]
                    if r["equation"] == eq and r["shrink_line2"] == shrunk)

    issue = "issue 6"
    r14, r21, r22 = row(14), row(21), row(22)
    mid = planning.PAPER_TABLE2[14][0]
    flat = r21["grid_min_d_T_mm"]
    rows = [
        Row("eq. 14: d_T", "mm", mid, r14["d_T_mm"], note="seed 0"),
        Row("eq. 14: |d_T - 65.5 mm|", "mm", 0.0, abs(r14["d_T_mm"] - mid),
            Target("<=", TABLE2_TOL_MM, f"{issue}: eq. 14 gives d_T = 65.5 mm")),
        Row("eq. 14: |theta_T|", "deg", planning.PAPER_TABLE2[14][1],
            abs(r14["theta_T_deg"]),
            Target("<=", TABLE2_TOL_DEG, f"{issue}: eq. 14 gives theta_T = 0")),
        Row("eq. 14: d_T over seeds, max - min", "mm", None,
            r14["d_T_mm_over_seeds"]["max"] - r14["d_T_mm_over_seeds"]["min"],
            note=f"{t2['seeds']} seeds"),
        Row("eq. 14, line2 not shrunk (the paper's text): d_T", "mm", None,
            row(14, False)["d_T_mm"],
            note="line1 shrunk by the rod radius, line2 not: 3 mm off the middle"),
        Row("eq. 21: d_T", "mm", planning.PAPER_TABLE2[21][0], r21["d_T_mm"],
            note="seed 0; any point of the flat minimum"),
        Row("eq. 21: theta_T", "deg", planning.PAPER_TABLE2[21][1], r21["theta_T_deg"]),
        Row("eq. 21: width in d_T of the flat minimum", "mm", "flat in d_T (Fig. 20)",
            max(flat) - min(flat),
            Target(">=", EQ21_FLAT_MM, f"{issue}: eq. 21's documented failure"),
            note=f"grid cells tying for the minimum: d_T {min(flat):g}..{max(flat):g} mm"),
        Row("eq. 22: d_T", "mm", planning.PAPER_TABLE2[22][0], r22["d_T_mm"],
            note="seed 0; by seed it lands on 81 mm or its mirror at 50 mm"),
        Row("eq. 22: theta_T", "deg", planning.PAPER_TABLE2[22][1], r22["theta_T_deg"]),
        Row("eq. 22: |d_T - 65.5 mm|", "mm", abs(planning.PAPER_TABLE2[22][0] - mid),
            abs(r22["d_T_mm"] - mid),
            Target(">=", EQ22_AWAY_MM, f"{issue}: eq. 22's documented failure")),
    ]
    setup = (
        "The paper's Fig. 19 checks its objective on a cylinder standing for the mouth: "
        "radius 50 mm, slices along its axis from 0 to 100 mm, the implant hole on its wall "
        "at (0, -50, 50) mm with its axis toward the cylinder's, the instrument and PSO of "
        "the Fig. 17 test (rod radius 6 mm, implant 31 mm, 30 particles). The right answer "
        "is d_T = 31 + (100 - 31) / 2 = 65.5 mm, theta_T = 0: eq. 14 (signed square roots "
        "of the two lines' safety) finds it, eq. 21 (linear) is flat in d_T and lands "
        "anywhere (55.304 mm), eq. 22 (squared) lands at 81 mm (Table 2, contours in Fig. "
        "20). Here the same case (config/examples/cylinder_case.toml) is placed by each "
        f"objective with {t2['seeds']} PSO seeds (seed 0 in the table), each minimum is "
        f"found on a {z.table2_grid[0]} x {z.table2_grid[1]} grid (0.5 mm x 1 deg), and "
        "line2 (where the rod ends once the implant is in) is shrunk by the rod radius as "
        "line1 is; the paper's text leaves it unshrunk, shown in its own row. Eq. 22 here "
        "keeps the sign of f_safe (sgn(f) f^2) so a collision still scores as one. The "
        "contours are over the search box (d_T 0..120 mm, theta_T -90..90 deg) with the PSO's "
        "answer and the grid minimum marked.")
    data = {**t2, "paper": {str(k): {"d_T_mm": d, "theta_T_deg": t}
                            for k, (d, t) in planning.PAPER_TABLE2.items()},
            "tolerance": {"d_T_mm": TABLE2_TOL_MM, "theta_T_deg": TABLE2_TOL_DEG,
                          "eq21_flat_mm": EQ21_FLAT_MM, "eq22_away_mm": EQ22_AWAY_MM},
            "objective_units": {str(k): v for k, v in OBJECTIVE_UNITS.items()},
            "machine": _machine(blas, load0)}
    return Section(key, TITLES[key], setup, rows, charts, planning._plain(data))


TITLES = {
    "004/table1": "Table 1 / Fig. 15: one slice's fit against the control points",
    "004/build": "§5.1: the surrogate model's build time",
    "004/fig17": "Fig. 17: the placement and its time",
    "004/fig19_20": "Figs. 19-20 / Table 2: the cylinder and the objective variants",
}

_RUNS: dict[str, Callable[[Context], Section]] = {
    "004/table1": table1, "004/build": build, "004/fig17": fig17, "004/fig19_20": fig19_20}

#: (quick, full) seconds measured on the 2-core development machine while other work
#: shared it (load average 2.5 quick, 4 full): quick 12 + 8.5 + 3 + 8 s, full 102 + 53 +
#: 5 + 12 s; table 1's includes loading the mouth (about 2 s, once a process).
_ESTIMATES = {"004/table1": (15.0, 55.0), "004/build": (10.0, 30.0),
              "004/fig17": (4.0, 4.0), "004/fig19_20": (9.0, 9.0)}

EXPERIMENTS: tuple[Experiment, ...] = tuple(
    Experiment(k, TITLES[k], _RUNS[k], _ESTIMATES[k]) for k in _RUNS)
