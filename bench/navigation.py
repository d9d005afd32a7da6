"""Navigation benchmark (issue 3): speed against accuracy, the paper's Table I in
simulation, stability where methods fail, and the Fig. 13 time breakdown.

    oralnav bench navigation [--quick] --out DIR      (or: python -m bench navigation)

Every figure comes from simulated sequences with exact ground truth, rendered from the
shipped cell (``config/examples/stereo_cell.toml``: two 1920x1200 cameras, robot plane,
end-effector cylinder r = 6 mm, opener cylinder r = 12 mm, 1 px lens blur, read + shot
noise). All methods run in this process on the same frames:

- ``opencv``: OpenCV's stock ``CharucoDetector`` + ``solvePnP`` per camera (the baseline);
- ``pnp``: our detection, RANSAC PnP refined on the best camera;
- ``ba``: our detection, bundle adjustment over both cameras (eqs. 15-16);
- ``nvgba``: BA with obliquity weights (eqs. 9-17, weights falling with obliquity).

Writes ``navigation.json`` (every figure) and PNG charts into the output folder.
"""

from __future__ import annotations

import json
import os
import platform
import sys
import time
from collections.abc import Sequence
from dataclasses import replace
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from oralnav.config.scene import load_scene
from oralnav.control.geometry import make_transform, pose_error, transform_from_euler
from oralnav.control.navigation.metrics import error_summary, jitter_stats
from oralnav.control.vision.detection import detect_fields
from oralnav.control.vision.markers import CylinderSurface, MarkerField
from oralnav.control.vision.pose import (
    DEFAULT_WEIGHTING,
    WEIGHTINGS,
    Observation,
    corner_normals,
    estimate_pose,
)
from oralnav.control.vision.tracker import METHODS, MODES, Tracker
from oralnav.sim.world.render import SceneRenderer
from oralnav.sim.world.scene import Blot, Scene

#: Camera rate of the simulated sequences (Hz): motion between frames follows from it.
RATE_HZ = 30.0
#: A method "breaks" where it gives no pose or an error above this (mm).
BREAK_MM = 1.0


def _log(msg: str) -> None:
    print(f"bench navigation: {msg}", file=sys.stderr, flush=True)


def cell_scene() -> Scene:
    path = resources.files("oralnav.config").joinpath("examples/stereo_cell.toml")
    return load_scene(Path(str(path)))


def trajectory(scene: Scene, k: int) -> dict[str, np.ndarray]:
    """Poses of every placement at frame ``k``: slow drifts of a few mm and degrees, like
    a patient breathing and an arm holding position (reference frame)."""
    t = k / RATE_HZ
    out = {}
    for i, p in enumerate(scene.placements):
        ph = 1.3 * i
        d = 0.003 * np.array([np.sin(2 * np.pi * 0.25 * t + ph), np.sin(2 * np.pi * 0.17 * t + ph),
                              0.5 * np.sin(2 * np.pi * 0.11 * t + ph)])
        rot = np.radians(2.0) * np.array([np.sin(2 * np.pi * 0.13 * t + ph),
                                          np.cos(2 * np.pi * 0.19 * t + ph) - 1, 0.0])
        T = p.T_ref_field.copy()
        c = T[:3, :3] @ p.field.corners.mean(axis=0) + T[:3, 3]  # turn about the field centre
        R = Rotation.from_rotvec(rot).as_matrix()
        T[:3, :3] = R @ T[:3, :3]
        T[:3, 3] = R @ (T[:3, 3] - c) + c + d
        out[p.name] = T
    return out


def _errors(est: dict, truth: dict[str, np.ndarray]) -> list[tuple[str, float, float]]:
    out = []
    for name, e in est.items():
        te, re = pose_error(e.T_ref_field, truth[name])
        out.append((name, te * 1e3, float(np.degrees(re))))
    return out


# -- 1 + 4: speed against accuracy, and the time breakdown ------------------------------
def speed_accuracy(frames: int, opencv_frames: int,
                   methods: Sequence[str] = METHODS) -> dict[str, Any]:
    """Every method of ``methods`` in every mode on the same rendered frames of the moving
    cell: time per stereo pair by stage (ms) and pose error against the truth."""
    scene = cell_scene()
    renderer = SceneRenderer(scene)
    renderer.prepare()
    n = max(frames, opencv_frames if "opencv" in methods else 0)
    _log(f"speed/accuracy: rendering {n} stereo frames of the moving cell...")
    seq = [renderer.render(poses=trajectory(scene, k), frame=k) for k in range(n)]
    fields = [p.field for p in scene.placements]
    results: dict[str, Any] = {}
    for method in methods:
        for mode in MODES:
            count = opencv_frames if method == "opencv" else frames
            tr = Tracker(scene.rig, fields, method=method, mode=mode)
            tr.track(seq[0].images)  # warm-up: acquisition and first-call costs
            tr.reset()
            times, parts, errs, found, stages = [], [], [], 0, {}
            per_field: dict[str, list[tuple[float, float]]] = {}
            for f in seq[:count]:
                est = tr.track(f.images)
                t = tr.last_timing
                times.append(t.total)
                parts.append((t.recognition, t.pose, t.roi))
                for name, te, re in _errors(est, f.T_ref_field):
                    errs.append((te, re))
                    per_field.setdefault(name, []).append((te, re))
                found += len(est)
                for s in t.stages.values():
                    stages[s] = stages.get(s, 0) + 1
            errs_a = np.array(errs) if errs else np.zeros((0, 2))
            steady = times[2:] if len(times) > 4 else times
            key = f"{method}/{mode}"
            results[key] = {
                "method": method, "mode": mode, "frames": count,
                "first_frame_ms": times[0],
                "median_ms": float(np.median(steady)),
                "p90_ms": float(np.percentile(steady, 90)),
                "breakdown_ms": dict(zip(("recognition", "pose", "roi"),
                                         np.median(np.array(parts[2:] or parts), axis=0).tolist(),
                                         strict=True)),
                "detection_rate": found / (count * len(fields)),
                "stages": stages,
                "errors": error_summary(errs_a[:, 0], errs_a[:, 1]) if len(errs_a) else None,
                "errors_by_field": {
                    name: error_summary(np.array(v)[:, 0], np.array(v)[:, 1])
                    for name, v in per_field.items()},
            }
            r = results[key]
            e = r["errors"]
            _log(f"  {key:16s} {r['median_ms']:8.1f} ms/pair  found {r['detection_rate']:.0%}  "
                 + (f"median {e['translation_mm']['median']:.4f} mm "
                    f"{e['rotation_deg']['median']:.4f} deg" if e else "no pose"))
    # Full-frame (re)acquisition: our pipeline on every frame with no history.
    return {"rate_hz": RATE_HZ, "fields": [f.name for f in fields], "results": results}


#: Table I's suture targets in the opener field's frame (m): 30-50 mm from its origin,
#: where the suture sites lie relative to the opener's marker.
TABLE_ONE_TARGETS = np.array([[0.0, 0.030, -0.010], [0.020, 0.040, -0.015],
                              [-0.020, 0.045, -0.020]])


# -- 2: Table I ---------------------------------------------------------------------------
def table_one(frames: int) -> dict[str, Any]:
    """Jitter of the opener's pose over ``frames`` static frames (only the noise changes),
    BA against NVG-BA and its weighting variants, on the same detected corners."""
    base = cell_scene()
    opener = base.placement("opener")
    # "Good": the sheet faces the cameras at 215 mm. "Bad": turned 55 deg about the
    # cylinder axis and pushed to 300 mm, so half the sheet curves away to grazing.
    good = opener.T_ref_field
    bad = opener.T_ref_field @ transform_from_euler([0, 0, 0], [0, 55, 0])
    bad[:3, 3] = [0.030, -0.020, 0.300]
    out: dict[str, Any] = {"frames": frames}
    fld = opener.field
    normals = corner_normals(fld)
    for label, T in (("good", good), ("bad", bad)):
        scene = replace(base, placements=(replace(opener, T_ref_field=T),))
        renderer = SceneRenderer(scene)
        renderer.prepare()
        _log(f"table I: {label} pose, {frames} frames...")
        poses: dict[str, list[np.ndarray]] = {}
        errs: dict[str, list[tuple[float, float]]] = {}
        corners = []
        for k in range(frames):
            f = renderer.render(frame=k)
            obs = []
            for cam, img in f.images.items():
                found = detect_fields(img, [fld])
                if fld.name in found:
                    fc = found[fld.name]
                    obs.append(Observation(scene.rig[cam],
                                           np.array([fld.corner_index[int(i)] for i in fc.ids]),
                                           fc.px))
            corners.append(sum(len(o.rows) for o in obs))
            variants = [("ba", "none")] + [("nvgba", w) for w in WEIGHTINGS if w != "none"]
            for method, w in variants:
                est = estimate_pose(fld, obs, method, w, normals) if obs else None
                key = method if method == "ba" else f"nvgba-{w}"
                if est is None:
                    continue
                poses.setdefault(key, []).append(est.T_ref_field)
                te, re = pose_error(est.T_ref_field, T)
                errs.setdefault(key, []).append((te * 1e3, float(np.degrees(re))))
        entry: dict[str, Any] = {"median_corners": float(np.median(corners)), "variants": {}}
        for key, ps in poses.items():
            e = np.array(errs[key])
            P = np.array(ps)
            # Suture targets fixed in the opener frame, followed in the reference frame
            # (eq. 8): their jitter adds the rotation's, times the lever arm.
            tgt = np.einsum("nij,kj->nki", P[:, :3, :3], TABLE_ONE_TARGETS) + P[:, None, :3, 3]
            tgt_std = np.linalg.norm(np.std(tgt, axis=0, ddof=1), axis=1) * 1e3
            entry["variants"][key] = {"found": len(ps), **jitter_stats(P).as_dict(),
                                      "target_std_mm": float(np.mean(tgt_std)),
                                      "errors": error_summary(e[:, 0], e[:, 1])}
        out[label] = entry
        ba = entry["variants"].get("ba")
        for key, nv in entry["variants"].items():
            if key == "ba" or not ba:
                continue
            red = {axis: 1 - nv["std_mm"][i] / ba["std_mm"][i] for i, axis in enumerate("XYZ")}
            red["Rot"] = 1 - nv["std_deg"] / ba["std_deg"]
            red["xyz"] = 1 - np.linalg.norm(nv["std_mm"]) / np.linalg.norm(ba["std_mm"])
            red["targets"] = 1 - nv["target_std_mm"] / ba["target_std_mm"]
            nv["std_reduction_vs_ba"] = red
        nv = entry["variants"].get(f"nvgba-{DEFAULT_WEIGHTING}")
        if ba and nv:
            entry["std_reduction"] = nv["std_reduction_vs_ba"]
            r = entry["std_reduction"]
            _log(f"  {label}: BA STD |xyz| {np.linalg.norm(ba['std_mm']):.4f} mm "
                 f"{ba['std_deg']:.4f} deg, targets {ba['target_std_mm']:.4f} mm; "
                 f"NVG-BA({DEFAULT_WEIGHTING}) cuts X {r['X']:+.0%} Y {r['Y']:+.0%} "
                 f"Z {r['Z']:+.0%} Rot {r['Rot']:+.0%} targets {r['targets']:+.0%}")
    return out


# -- 3: stability sweeps ------------------------------------------------------------------
def _single_field_scene(base: Scene, fld: MarkerField, T: np.ndarray, **imaging) -> Scene:
    from oralnav.sim.world.scene import Placement

    return replace(base, placements=(Placement("target", fld, T),),
                   imaging=replace(base.imaging, **imaging), rods=(), blots=())


#: The stability sweeps: each nuisance's values in order of growing nuisance (the unit is
#: in the name; the cylinder's radius shrinks as the nuisance grows).
SWEEPS: dict[str, tuple[float, ...]] = {
    "view_angle_deg": (0, 30, 50, 60, 70, 75, 80),
    "cylinder_radius_mm": (30, 20, 12, 10, 8, 6),
    "read_noise_dn": (0, 2, 4, 8, 12, 16),
    "blur_sigma_px": (0.5, 1.0, 2.0, 3.0, 4.0),
    "occluded_fraction": (0.0, 0.2, 0.4, 0.6, 0.8)}


def sweep_scene(sweep: str, value: float) -> Scene:
    """The one-field scene of sweep ``sweep`` (a key of :data:`SWEEPS`) at ``value``: the
    robot's sheet turned ``value`` deg from the cameras, an opener-style 8 x 6 sheet on a
    cylinder of radius ``value`` mm, the robot's sheet face-on with read noise ``value``
    DN or lens blur ``value`` px, or with a stain over ``value`` of its area."""
    base = cell_scene()
    robot = base.placement("robot").field
    T_front = transform_from_euler([0.0, 0.0, 0.22], [0, 0, 0])
    T_face = T_front @ make_transform(t=[-0.025, -0.0175, 0])
    if sweep == "view_angle_deg":
        return _single_field_scene(base, robot, transform_from_euler(
            [-0.025, -0.0175, 0.22], [0, value, 0]))
    if sweep == "cylinder_radius_mm":
        opener = base.placement("opener").field
        f = MarkerField("target", opener.dictionary, (8, 6), 0.003, 0.0022, opener.first_id,
                        CylinderSurface(value * 1e-3))
        return _single_field_scene(base, f, transform_from_euler([-0.012, -0.009, 0.20],
                                                                 [0, 0, 0]))
    if sweep == "read_noise_dn":
        return _single_field_scene(base, robot, T_face, read_noise_dn=value)
    if sweep == "blur_sigma_px":
        return _single_field_scene(base, robot, T_face, blur_sigma_px=value)
    if sweep == "occluded_fraction":
        sc = _single_field_scene(base, robot, T_face)
        if value > 0:
            w, h = robot.sheet_size
            rad = float(np.sqrt(value * w * h / np.pi))
            sc = replace(sc, blots=(Blot("stain", "target", (0.5 * w, 0.5 * h), rad),))
        return sc
    raise ValueError(f"unknown sweep {sweep!r}; have {list(SWEEPS)}")


def sweep_point(item: tuple[str, float, int]) -> dict[str, Any]:
    """One point of a sweep, ``(sweep, value, frames)``: every method on the same
    ``frames`` renders of :func:`sweep_scene`; per method its detection rate (share of
    frames with a pose) and median errors (mm, deg; ``None`` without a pose). A pure
    function of its item, so it runs on any engine of ``bench/executor.py``."""
    sweep, value, frames = item
    scene = sweep_scene(sweep, value)
    renderer = SceneRenderer(scene)
    renderer.prepare()
    imgs = [renderer.render(frame=k) for k in range(frames)]
    fld = scene.placements[0].field
    row: dict[str, Any] = {"value": value}
    for method in METHODS:
        tr = Tracker(scene.rig, [fld], method=method, mode="full")
        errs = []
        for f in imgs:
            est = tr.track(f.images)
            if fld.name in est:  # estimates by field name, truth by placement
                te, re = pose_error(est[fld.name].T_ref_field, f.T_ref_field["target"])
                errs.append((te * 1e3, np.degrees(re)))
        e = np.array(errs) if errs else np.zeros((0, 2))
        row[method] = {"detection_rate": len(errs) / frames,
                       "median_mm": float(np.median(e[:, 0])) if len(e) else None,
                       "median_deg": float(np.median(e[:, 1])) if len(e) else None}
    return row


def _broken(r: dict[str, Any]) -> bool:
    """A method's figures at a point break it: a frame without pose, or an error over
    ``BREAK_MM``."""
    return r["detection_rate"] < 1.0 or (r["median_mm"] or 0) > BREAK_MM


def sweeps(frames: int, scheduler: str | None = None, workers: int | None = None,
           values: dict[str, tuple[float, ...]] | None = None) -> dict[str, Any]:
    """The stability sweeps (``values``, default :data:`SWEEPS`), ``frames`` frames a
    point, each point a trial on the engine ``scheduler`` names (``bench/executor.py``;
    default a local process pool of ``workers``). Per sweep its rows and, per method,
    ``breaks_at`` (the first value that breaks it, ``None`` if none does) and
    ``holds_to`` (the last value before that; the sweep's end if it never breaks,
    ``None`` if it breaks at the first)."""
    from oralnav.bench.executor import TrialRunner

    values = SWEEPS if values is None else values
    items = [(sweep, v, frames) for sweep, vs in values.items() for v in vs]

    def said(i: int, row: dict[str, Any], done: int, total: int) -> None:
        sweep = items[i][0]
        _log(f"  {sweep} {row['value']} ({done}/{total}): " + ", ".join(
            f"{m} {row[m]['detection_rate']:.0%}"
            + (f" {row[m]['median_mm']:.3f} mm" if row[m]["median_mm"] is not None else "")
            for m in METHODS))

    with TrialRunner(scheduler, workers) as runner:
        _log(f"sweeps: {len(items)} points of {frames} frames on {runner.name}")
        results = runner.map(sweep_point, items, on_result=said)
    out: dict[str, Any] = {"frames": frames, "break_mm": BREAK_MM}
    for sweep in values:
        rows = [r for (s, _, _), r in zip(items, results, strict=True) if s == sweep]
        breaks, holds = {}, {}
        for m in METHODS:
            bad = [k for k, r in enumerate(rows) if _broken(r[m])]
            breaks[m] = rows[bad[0]]["value"] if bad else None
            last = (bad[0] if bad else len(rows)) - 1
            holds[m] = rows[last]["value"] if last >= 0 else None
        out[sweep] = {"rows": rows, "breaks_at": breaks, "holds_to": holds}
    return out


# -- charts -------------------------------------------------------------------------------
def chart_table_one(t1: dict[str, Any], path: Path) -> None:
    """Table I's jitter (``table_one``'s result) as bars per estimator, one quantity per
    axis: translation STD (mm) above, rotation STD (deg) below; good pose left, bad
    right."""
    from oralnav.bench.report.charts import legend_outside, plt, save

    fig, axes = plt().subplots(2, 2, figsize=(12, 6.5), layout="constrained")
    for col, label in enumerate(("good", "bad")):
        var = t1[label]["variants"]
        names = list(var)
        w = 0.8 / max(len(names), 1)
        for i, n in enumerate(names):
            axes[0, col].bar(np.arange(3) + i * w, var[n]["std_mm"], width=w, label=n)
            axes[1, col].bar([i * w], [var[n]["std_deg"]], width=w, label=n)
        axes[0, col].set_xticks(np.arange(3) + 0.4 - w / 2, ["X", "Y", "Z"])
        axes[0, col].set_ylabel("translation STD (mm)")
        axes[0, col].set_title(f"{label} opener pose: STD over {t1['frames']} frames")
        axes[1, col].set_xticks([i * w for i in range(len(names))], names, rotation=25)
        axes[1, col].set_ylabel("rotation STD (deg)")
    legend_outside(axes[0, 1])
    save(fig, path)


def charts(doc: dict[str, Any], out: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    written = []
    colours = {"opencv": "tab:red", "pnp": "tab:orange", "ba": "tab:blue", "nvgba": "tab:green"}
    markers = {"full": "s", "roi": "^", "predict": "o"}
    sa = doc["speed_accuracy"]["results"]
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5))
    for r in sa.values():
        if not r["errors"]:
            continue
        for ax, key, unit in ((axes[0], "translation_mm", "mm"), (axes[1], "rotation_deg", "deg")):
            ax.scatter(r["median_ms"], r["errors"][key]["median"], c=colours[r["method"]],
                       marker=markers[r["mode"]], s=60, label=f"{r['method']} / {r['mode']}")
            ax.set_xscale("log")
            ax.set_xlabel("median ms per stereo pair (2 x 1920x1200)")
            ax.set_ylabel(f"median pose error ({unit})")
            ax.grid(True, which="both", alpha=0.3)
    axes[0].axvline(10, ls="--", c="grey", lw=0.8)
    axes[0].legend(fontsize=7, ncol=2)
    fig.suptitle("Speed against accuracy (three fields, moving cell)")
    fig.tight_layout()
    fig.savefig(out / "speed_accuracy.png", dpi=110)
    plt.close(fig)
    written.append("speed_accuracy.png")

    fig, ax = plt.subplots(figsize=(9, 4.5))
    keys = [k for k in sa if sa[k]["method"] in ("nvgba", "opencv")]
    bottom = np.zeros(len(keys))
    for part, col in (("recognition", "tab:blue"), ("pose", "tab:orange"), ("roi", "tab:green")):
        vals = np.array([sa[k]["breakdown_ms"][part] for k in keys])
        ax.bar(keys, vals, bottom=bottom, label=part, color=col)
        bottom += vals
    ax.set_yscale("log")
    ax.set_ylabel("median ms per stereo pair")
    ax.set_title("Time per frame: recognition, pose estimation, ROI (cf. paper Fig. 13)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out / "time_breakdown.png", dpi=110)
    plt.close(fig)
    written.append("time_breakdown.png")

    chart_table_one(doc["table_one"], out / "table_one.png")
    written.append("table_one.png")

    sw = doc["sweeps"]
    names = [k for k in sw if isinstance(sw[k], dict) and "rows" in sw[k]]
    fig, axes = plt.subplots(2, len(names), figsize=(4 * len(names), 7), squeeze=False)
    for j, name in enumerate(names):
        rows = sw[name]["rows"]
        xs = [r["value"] for r in rows]
        for m in METHODS:
            err = [r[m]["median_mm"] if r[m]["median_mm"] is not None else np.nan for r in rows]
            axes[0, j].plot(xs, err, "o-", c=colours[m], label=m)
            axes[1, j].plot(xs, [r[m]["detection_rate"] for r in rows], "o-", c=colours[m])
            b = sw[name]["breaks_at"][m]
            if b is not None:
                axes[0, j].axvline(b, c=colours[m], ls=":", lw=1)
        axes[0, j].set_yscale("log")
        axes[0, j].axhline(BREAK_MM, c="grey", ls="--", lw=0.8)
        axes[0, j].set_title(name)
        axes[0, j].set_ylabel("median error (mm)")
        axes[1, j].set_ylabel("detection rate")
        axes[1, j].set_xlabel(name)
        axes[1, j].set_ylim(-0.05, 1.05)
    axes[0, 0].legend(fontsize=7)
    fig.suptitle("Stability where methods fail (dotted: where each breaks)")
    fig.tight_layout()
    fig.savefig(out / "stability.png", dpi=100)
    plt.close(fig)
    written.append("stability.png")
    return written


def main(out: Path, quick: bool = False) -> dict[str, Any]:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    frames, opencv_frames, jitter_frames, sweep_frames = (
        (20, 6, 40, 2) if quick else (60, 20, 200, 5))
    doc: dict[str, Any] = {
        "bench": "navigation", "quick": quick,
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                    "processor": platform.processor() or platform.machine()},
        "speed_accuracy": speed_accuracy(frames, opencv_frames),
        "table_one": table_one(jitter_frames),
        "sweeps": sweeps(sweep_frames),
    }
    sa = doc["speed_accuracy"]["results"]
    ours = sa["nvgba/predict"]
    base = sa["opencv/full"]
    doc["targets"] = {
        "steady_pair_ms": ours["median_ms"],
        "steady_pair_ms_target": 10.0,
        "speedup_over_opencv": base["median_ms"] / ours["median_ms"],
        "speedup_target": 3.0,
        "acquisition_pair_ms": sa["nvgba/full"]["median_ms"],
        "acquisition_pair_ms_target": 40.0,
        "median_error_mm": ours["errors"]["translation_mm"]["median"],
        "median_error_deg": ours["errors"]["rotation_deg"]["median"],
        "median_error_by_field": {
            name: {"mm": e["translation_mm"]["median"], "deg": e["rotation_deg"]["median"]}
            for name, e in ours["errors_by_field"].items()},
        "opencv_median_error_mm": base["errors"]["translation_mm"]["median"]
        if base["errors"] else None,
        "bad_pose_std_reduction": doc["table_one"]["bad"].get("std_reduction"),
        "bad_pose_std_reduction_target": 0.30,
    }
    doc["verdicts"] = verdicts(doc["targets"])
    doc["charts"] = charts(doc, out)
    doc["elapsed_s"] = time.perf_counter() - t0
    (out / "navigation.json").write_text(json.dumps(doc, indent=1, default=_jsonable) + "\n")
    _log("targets: " + json.dumps(doc["targets"], default=_jsonable))
    for name, v in doc["verdicts"].items():
        _log(f"  {name}: {v}")
    _log(f"wrote {out / 'navigation.json'} and {', '.join(doc['charts'])} "
         f"in {doc['elapsed_s']:.0f} s")
    return doc


def verdicts(t: dict[str, Any]) -> dict[str, str]:
    """Each of issue 3's targets marked from what the run measured (report/section.py's
    rules: a missing figure is ``not measured``, never met)."""
    from oralnav.bench.report.section import Row, Target

    cut = t["bad_pose_std_reduction"]
    rows = [Row("steady_pair_ms", "ms", None, t["steady_pair_ms"],
                Target("<=", t["steady_pair_ms_target"], "issue 3")),
            Row("acquisition_pair_ms", "ms", None, t["acquisition_pair_ms"],
                Target("<=", t["acquisition_pair_ms_target"], "issue 3")),
            Row("speedup_over_opencv", "x", None, t["speedup_over_opencv"],
                Target(">=", t["speedup_target"], "issue 3")),
            Row("bad_pose_std_reduction", "share", None, cut and cut["xyz"],
                Target(">=", t["bad_pose_std_reduction_target"], "issue 3"))]
    return {r.figure: r.verdict for r in rows}


def _jsonable(o: Any) -> Any:
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")
