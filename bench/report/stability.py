"""Stability where methods fail (issue 35): the navigation sweeps with each method's breaking
point, and the needle tracker's loss boundary.

- ``stability/navigation``: :func:`oralnav.bench.navigation.sweeps` (viewing angle,
  cylinder radius, read noise, blur, occlusion; every point a trial on ``ctx``'s engine),
  per method the last value it holds to and where it breaks (a frame without pose or a
  median error over ``BREAK_MM``).
- ``stability/needle_tracker``: :func:`oralnav.bench.needle_tracking.failures` (jaw
  occlusion, edge-on angle, low contrast at 3000 particles; every trial on ``ctx``'s
  engine), where the tracker loses the needle and where it misses its target.

Neither paper runs such sweeps, so the rows have no paper figure and no target (no issue
sets one); their verdicts are "shown". Sizes are module constants so tests can shrink
them.
"""

from __future__ import annotations

import math
from typing import Any

from oralnav.bench.report.charts import legend_outside, mark_minority, plt, save
from oralnav.bench.report.context import Context, Experiment
from oralnav.bench.report.section import Row, Section

__all__ = ["EXPERIMENTS", "NAV_FRAMES", "TRACKER_SEED", "TRACKER_SIZES"]

#: Rendered frames per navigation sweep point (as ``oralnav bench navigation``: 2 quick,
#: 5 full).
NAV_FRAMES = {"quick": 2, "full": 5}
#: The sweeps' values: quick, every sweep's ends and the values around where methods
#: broke in full runs, sparser between (19 points of 29: on the shared 2-core machine a
#: point of 2 frames takes 3-9 s); full (``None``): every value of ``navigation.SWEEPS``.
NAV_SWEEPS: dict[str, dict[str, tuple[float, ...]] | None] = {
    "quick": {"view_angle_deg": (0, 50, 70, 75, 80), "cylinder_radius_mm": (30, 12, 6),
              "read_noise_dn": (0, 8, 16), "blur_sigma_px": (1.0, 2.0, 3.0, 4.0),
              "occluded_fraction": (0.0, 0.4, 0.6, 0.8)},
    "full": None}
#: The nuisance sweeps' first trial seed: held out like the needle Monte Carlo's (the
#: tracker was developed on seeds 0-29).
TRACKER_SEED = 10000
#: Needle-tracker nuisance sweeps: trials per value, frames per trial (one
#: initialisation, then updates), and the values (``None``: the bench's quick or full
#: values).
TRACKER_SIZES: dict[str, dict[str, Any]] = {
    "quick": {"seeds": 3, "frames": 3, "values": None},
    "full": {"seeds": 10, "frames": 6, "values": None}}

#: How each navigation sweep reads: axis label, unit and scale of its values for the rows
#: and charts, and whether the nuisance grows as the value falls.
_NAV_AXES: dict[str, tuple[str, str, float, bool]] = {
    "view_angle_deg": ("viewing angle", "deg", 1.0, False),
    "cylinder_radius_mm": ("cylinder radius", "mm", 1.0, True),
    "read_noise_dn": ("read noise", "DN", 1.0, False),
    "blur_sigma_px": ("lens blur sigma", "px", 1.0, False),
    "occluded_fraction": ("sheet occluded", "%", 100.0, False)}
_COLOURS = {"opencv": "tab:red", "pnp": "tab:orange", "ba": "tab:blue", "nvgba": "tab:green"}


def _nav_axis(sweep: str) -> tuple[str, str, float, bool]:
    return _NAV_AXES.get(sweep, (sweep.replace("_", " "), "", 1.0, False))


# -- stability/navigation ---------------------------------------------------------------

def run_navigation(ctx: Context) -> Section:
    """The navigation sweeps with each method's breaking point (module docstring)."""
    from oralnav.bench import navigation as nav
    from oralnav.bench.needle_tracking import _plain as plain

    frames = NAV_FRAMES["quick" if ctx.quick else "full"]
    values = NAV_SWEEPS["quick" if ctx.quick else "full"] or nav.SWEEPS
    ctx.say(f"navigation sweeps: {sum(len(v) for v in values.values())} points of "
            f"{frames} frames")
    doc = nav.sweeps(frames, scheduler=ctx.scheduler, workers=ctx.workers, values=values)
    rows = []
    for sweep in values:
        label, unit, scale, _ = _nav_axis(sweep)
        sw = doc[sweep]
        last = sw["rows"][-1]["value"]
        for m in nav.METHODS:
            holds, breaks = sw["holds_to"][m], sw["breaks_at"][m]
            if breaks is None:
                note = f"no break within the sweep (to {scale * last:g} {unit})"
            elif holds is None:
                note = f"broken from the sweep's first value, {scale * breaks:g} {unit}"
            else:
                note = f"breaks at {scale * breaks:g} {unit}"
            rows.append(Row(f"{label}: {m} holds to", unit, None,
                            None if holds is None else scale * holds, note=note))
    chart, marks = _chart_navigation(ctx, doc, values, nav.METHODS, nav.BREAK_MM)
    setup = (
        "Paper (seed 000): the opener's and the robot's ChArUco fields tracked by BA and "
        "NVG-BA in good and bad poses; it sweeps no nuisance to a method's failure. Ours: "
        "one field at a time rendered by the simulator's stereo cell (two 1920x1200 "
        "cameras, 1 px blur, read and shot noise) while one nuisance grows: the robot's "
        "flat sheet turned from the cameras, an 8 x 6 sheet on ever thinner cylinders, "
        "more read noise, more lens blur, a stain over a growing share of the sheet. "
        f"{frames} frames a point; every method (OpenCV's stock detector and PnP, our "
        "detection with PnP, BA, NVG-BA) on the same frames, from scratch each frame. A "
        f"method breaks at the first value where a frame gives no pose or its median "
        f"error exceeds {nav.BREAK_MM:g} mm; 'holds to' is the value before that.")
    data = {"frames": frames, "break_mm": nav.BREAK_MM, "methods": list(nav.METHODS),
            "sweeps": {s: doc[s] for s in values}, "chart_marks": marks}
    return Section("stability/navigation", "Stability: navigation methods where they break",
                   setup, rows, [chart], plain(data))


def _chart_navigation(ctx: Context, doc: dict[str, Any], values: dict[str, Any],
                      methods: tuple[str, ...], break_mm: float
                      ) -> tuple[str, list[dict[str, Any]]]:
    """A column per sweep: median error (mm, log) above, detection rate (%) below, a
    dotted vertical line where each method breaks (and a triangle of its colour on top,
    so that methods breaking at the same value stay told apart). Returns the file name
    and the marks drawn."""
    from oralnav.bench.needle_tracking import _plain_log_axis

    pyplot = plt()
    names = list(values)
    fig, axes = pyplot.subplots(2, len(names), figsize=(3.6 * len(names) + 1.5, 6.4),
                                squeeze=False)
    marks: list[dict[str, Any]] = []
    for j, sweep in enumerate(names):
        label, unit, scale, falls = _nav_axis(sweep)
        top, bottom = axes[0, j], axes[1, j]
        rows = doc[sweep]["rows"]
        xs = [scale * r["value"] for r in rows]
        for k, m in enumerate(methods):
            err = [r[m]["median_mm"] if r[m]["median_mm"] is not None else math.nan
                   for r in rows]
            rate = [100 * r[m]["detection_rate"] for r in rows]
            top.plot(xs, err, "o-", color=_COLOURS.get(m), label=m, ms=4)
            bottom.plot(xs, rate, "o-", color=_COLOURS.get(m), label=m, ms=4)
            # a median over fewer than half the frames: ringed
            mark_minority(top, xs, err, [0 < r[m]["detection_rate"] < 0.5 for r in rows])
            b = doc[sweep]["breaks_at"][m]
            if b is not None:
                for ax in (top, bottom):
                    ax.axvline(scale * b, color=_COLOURS.get(m), ls=":", lw=1.2)
                # above the axes, one row per method
                top.plot([scale * b], [1.04 + 0.07 * k], "v", color=_COLOURS.get(m), ms=6,
                         transform=top.get_xaxis_transform(), clip_on=False)
                marks.append({"sweep": sweep, "method": m, "value": b})
        top.axhline(break_mm, color="0.5", ls="--", lw=0.8)
        top.set_yscale("log")
        _plain_log_axis(top.yaxis)
        top.set_ylabel("median pose error (mm)")
        top.set_title(label, fontsize=10, pad=8 + 5 * len(methods))
        bottom.set_ylabel("frames with a pose (%)")
        bottom.set_ylim(-5, 105)
        for ax in (top, bottom):
            ax.set_xlabel(f"{label} ({unit})" if unit else label)
            ax.grid(alpha=0.3, which="both")
            if falls:
                ax.invert_xaxis()   # growing nuisance to the right, as in the others
    # the legend once, outside the last column: methods, the break line, minority ring
    last = axes[0, -1]
    last.plot([], [], ls=":", color="0.3", marker="v",
              label="where the method breaks (line and mark in its colour)")
    last.plot([], [], ls="--", color="0.5", label=f"break threshold {break_mm:g} mm")
    legend_outside(last)
    fig.suptitle("Navigation: where each method breaks (dotted lines)", fontsize=11)
    fig.tight_layout()
    return save(fig, ctx.chart("stability/navigation", "sweeps")), marks


# -- stability/needle_tracker -----------------------------------------------------------

#: Per nuisance: the point's value key, axis label, unit, whether the nuisance grows as
#: the value falls.
_NUISANCES: dict[str, tuple[str, str, str, bool]] = {
    "jaw_occlusion": ("jaw_width_mm", "jaw width", "mm", False),
    "edge_on": ("normal_to_ray_deg", "needle normal to viewing ray", "deg", False),
    "low_contrast": ("contrast_dn", "wire contrast against the pad", "DN", True)}


def run_needle_tracker(ctx: Context) -> Section:
    """The needle tracker's loss boundary under three nuisances (module docstring)."""
    from oralnav.bench import needle_tracking as nt
    from oralnav.bench.needle_tracking import _plain as plain

    size = TRACKER_SIZES["quick" if ctx.quick else "full"]
    values = size["values"] or (nt.QUICK_NUISANCES if ctx.quick else nt.NUISANCES)
    ctx.say(f"needle tracker nuisances: {size['seeds']} trials of {size['frames']} frames "
            f"per value, {sum(len(v) for v in values.values())} values")
    doc = nt.failures(TRACKER_SEED, size["seeds"], size["frames"], values,
                      scheduler=ctx.scheduler, workers=ctx.workers)
    rows = []
    for name, (key, label, unit, _) in _NUISANCES.items():
        w = doc[f"{name}_where"]
        pts = doc[name]
        end = pts[-1][key] if pts else None
        for what, rule, fig in (
                ("lost", "median centre error > 1 mm or median outline angle > 5 deg",
                 "needle kept up to"),
                ("target", "median error > 0.5 mm or 2 deg, or under half converged",
                 "target met up to")):
            holds, fails = w[what]["holds_to"], w[what]["fails_from"]
            if fails is None:
                note = f"holds over the whole sweep (to {end:g} {unit})"
            elif holds is None:
                note = f"fails from the sweep's first value, {fails:g} {unit} ({rule})"
            else:
                note = f"fails from {fails:g} {unit} ({rule})"
            rows.append(Row(f"{label}: {fig}", unit, None, holds, note=note))
    chart, marks = _chart_tracker(ctx, doc)
    seeds = doc["seeds"]
    setup = (
        "Paper (seed 002): the tracker runs on the dVRK's endoscope images; its failures "
        "were tracking errors, with no sweep of what causes them. Ours: the needle "
        "tracker at 3000 particles, stereo, under one growing nuisance at a time: the "
        "held, moving needle with ever wider jaws hiding more of the wire; a free, still "
        "needle 20 mm off the pad turned from face-on to edge-on; the needle drawn as a "
        "flat grey wire ever closer to the pad's level. "
        f"{size['seeds']} trials a value on held-out seeds {seeds[0]}-{seeds[-1]} (edge-on: "
        f"{', '.join(map(str, doc['edge_on_seeds']))}, those whose needle stays in view at "
        f"every angle), {size['frames'] - 1} updates each. The needle is lost where the "
        "median centre error exceeds 1 mm or the median outline angle (base/tip twin "
        "forgiven) 5 deg; the target is missed where the median error exceeds 0.5 mm or "
        "2 deg or fewer than half the updates are converged.")
    data = {"seeds": seeds, "edge_on_seeds": doc["edge_on_seeds"],
            "frames_per_trial": size["frames"], "particles": doc["particles"],
            "values": {k: list(v) for k, v in values.items()},
            "where": {n: doc[f"{n}_where"] for n in _NUISANCES},
            "points": {n: [{k: v for k, v in p.items() if k != "runs"} for p in doc[n]]
                       for n in _NUISANCES},
            "seconds": doc.get("seconds"), "chart_marks": marks}
    return Section("stability/needle_tracker", "Stability: where the needle tracker loses "
                   "the needle", setup, rows, [chart], plain(data))


#: The tracker's boundaries as the chart draws them: which, colour, legend text, style.
_BOUNDARIES = (("lost", "C3", "needle lost from here"),
               ("target", "orange", "target missed from here"))
#: The target's line wide and under the lost one, so both show where they coincide.
_BOUNDARY_STYLE: dict[str, dict[str, Any]] = {"lost": {"lw": 1.2, "ls": "-", "zorder": 3},
                                              "target": {"lw": 3.0, "ls": "-",
                                                         "alpha": 0.6, "zorder": 2}}


def _chart_tracker(ctx: Context, doc: dict[str, Any]) -> tuple[str, list[dict[str, Any]]]:
    """A column per nuisance: median position error (mm, log), median orientation error
    (deg, log, twin counted and forgiven), converged share (%); a red line where the
    needle is lost and an orange one where the target is first missed. Returns the file
    name and the marks drawn."""
    from oralnav.bench.needle_tracking import TARGET, WRONG_DEG, WRONG_MM, _plain_log_axis

    pyplot = plt()
    fig, axes = pyplot.subplots(3, 3, figsize=(14, 9), squeeze=False)
    marks: list[dict[str, Any]] = []
    for j, (name, (key, label, unit, falls)) in enumerate(_NUISANCES.items()):
        pts = [p for p in doc[name] if p["updates"]]
        n_seeds = len(doc["edge_on_seeds"] if name == "edge_on" else doc["seeds"])
        xs = [p[key] for p in pts]
        # a point from fewer than half of the trials asked for (the rest not buildable)
        minority = [p["trials"] < n_seeds / 2 for p in pts]
        a_mm, a_deg, a_conv = axes[0, j], axes[1, j], axes[2, j]
        ys = [p["position_mm_median"] for p in pts]
        a_mm.plot(xs, ys, "o-", color="C0", label="position error, median")
        mark_minority(a_mm, xs, ys, minority)
        a_mm.axhline(TARGET["position_mm"], color="C0", ls="--", lw=0.8,
                     label=f"target {TARGET['position_mm']:g} mm")
        a_mm.axhline(WRONG_MM, color="C3", ls="--", lw=0.8, label=f"lost: {WRONG_MM:g} mm")
        ys = [p["angle_deg_median"] for p in pts]
        a_deg.plot(xs, ys, "s-", color="C1", label="orientation error, median")
        mark_minority(a_deg, xs, ys, minority)
        a_deg.plot(xs, [p["outline_angle_deg_median"] for p in pts], "s:", color="C2",
                   label="outline angle, median (twin forgiven)")
        a_deg.axhline(TARGET["angle_deg"], color="C1", ls="--", lw=0.8,
                      label=f"target {TARGET['angle_deg']:g} deg")
        a_deg.axhline(WRONG_DEG, color="C3", ls="--", lw=0.8,
                      label=f"lost: outline {WRONG_DEG:g} deg")
        ys = [100 * p["converged_share"] for p in pts]
        a_conv.plot(xs, ys, "^-", color="C4", label="updates converged")
        mark_minority(a_conv, xs, ys, minority)
        a_conv.set_ylim(-5, 105)
        where = doc[f"{name}_where"]
        for what, colour, _text in _BOUNDARIES:
            x = where[what]["fails_from"]
            if x is None:
                continue
            for ax in (a_mm, a_deg, a_conv):
                ax.axvline(x, color=colour, **_BOUNDARY_STYLE[what])
            marks.append({"nuisance": name, "what": what, "value": x})
        for ax in (a_mm, a_deg):
            ax.set_yscale("log")
            _plain_log_axis(ax.yaxis)
        a_mm.set_ylabel("median position error (mm)")
        a_deg.set_ylabel("median orientation error (deg)")
        a_conv.set_ylabel("updates converged (%)")
        a_mm.set_title(label, fontsize=10)
        for ax in (a_mm, a_deg, a_conv):
            ax.set_xlabel(f"{label} ({unit})")
            ax.grid(alpha=0.3, which="both")
            if falls:
                ax.invert_xaxis()   # growing nuisance to the right
    # the boundary lines' legend entries on the last row, whichever columns have them
    for _what, colour, text in _BOUNDARIES:
        axes[2, -1].plot([], [], color=colour, label=text, **_BOUNDARY_STYLE[_what])
    for ax in axes[:, -1]:
        legend_outside(ax)
    fig.suptitle(f"Needle tracker ({doc['particles']} particles, stereo): where it loses "
                 "the needle", fontsize=11)
    fig.tight_layout()
    return save(fig, ctx.chart("stability/needle_tracker", "nuisances")), marks


#: Estimates (s) on the 2-core development machine, 2 workers, load average 2-3: quick
#: measured 2026-11-27 (19 navigation points 78 s, 30 tracker trials 29 s); full from
#: the quick per-point times (29 points of 5 frames; 240 tracker trials of 6 frames).
EXPERIMENTS: tuple[Experiment, ...] = (
    Experiment("stability/navigation", "Stability: navigation methods where they break",
               run_navigation, estimate_s=(80.0, 140.0)),
    Experiment("stability/needle_tracker", "Stability: where the needle tracker loses the "
               "needle", run_needle_tracker, estimate_s=(30.0, 280.0)),
)
