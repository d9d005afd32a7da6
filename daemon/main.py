"""``oralnavd``: the navigation and control daemon.

It loads and validates the configuration and every file it names, then serves the cell:
the control loop in its own process, the safety supervisor and the operator REST API in
one anyio task group (``daemon/service.py``), until SIGTERM, which stops the robot first.
``--check`` only validates. ``--demo`` on the simulated cell renders what the stereo camera
and the endoscope see, tracks the fields and checks OpenCV's stock ChArUco detector
against the ground truth (the two-stage navigation job replaces it with issue 4's next
part).

    oralnavd [--config FILE] [--check] [--demo] [--api-port N] [--json]
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from oralnav import __version__
from oralnav.config.daemon import DaemonConfig, load_config
from oralnav.config.errors import ConfigError
from oralnav.control.errors import ControlError


def _log(msg: str) -> None:
    print(f"oralnavd: {msg}", file=sys.stderr, flush=True)


def detection_report(image: np.ndarray, field, truth) -> dict[str, Any]:
    """Run OpenCV's ChArUco detector + cornerSubPix on ``image`` for ``field`` and compare
    the corners with the renderer's ground truth (pixels)."""
    detector = cv2.aruco.CharucoDetector(field.board)
    corners, ids, _, _ = detector.detectBoard(image)
    if ids is None or len(ids) == 0:
        return {"truth": len(truth.corner_ids), "found": 0}
    pts = cv2.cornerSubPix(image, corners.astype(np.float32), (4, 4), (-1, -1),
                           (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 50, 1e-4))
    index = {int(c): k for k, c in enumerate(truth.corner_ids)}
    errs = [float(np.linalg.norm(p - truth.corners_px[index[int(i)]]))
            for p, i in zip(pts.reshape(-1, 2), ids.ravel(), strict=True) if int(i) in index]
    wrong = int(sum(int(i) not in index for i in ids.ravel()))
    return {"truth": len(truth.corner_ids), "found": len(errs), "wrong_ids": wrong,
            "mean_err_px": round(float(np.mean(errs)), 4) if errs else None,
            "max_err_px": round(float(np.max(errs)), 4) if errs else None}


def demo(cfg: DaemonConfig) -> dict[str, Any]:
    """Render the simulated cell's views and report detection against ground truth."""
    from oralnav.config.scene import load_scene
    from oralnav.sim.render import SceneRenderer

    scenes = [cfg.scene]  # loaded and validated with the configuration
    endo = cfg.scene_path.parent / "endoscope_view.toml" if cfg.scene_path else None
    if endo is not None and endo.is_file() and cfg.endoscope_rig is not None:
        scenes.append(load_scene(endo))
    report: dict[str, Any] = {}
    tracking: dict[str, Any] = {}
    for scene in scenes:
        renderer = SceneRenderer(scene)
        _log(f"preparing {Path(scene.source).name} (camera ray maps, textures)...")
        renderer.prepare()
        frame = renderer.render()
        tracking[Path(scene.source).stem] = tracking_report(scene, renderer)
        for cam, img in frame.images.items():
            entry = {"render_ms": round(frame.render_s[cam] * 1e3, 1), "fields": {}}
            for name, truth in frame.truth[cam].items():
                field = scene.placement(name).field
                entry["fields"][name] = detection_report(img, field, truth)
            report[cam] = entry
            _log(f"{cam}: rendered in {entry['render_ms']} ms")
    return {"detection": report, "tracking": tracking}


def tracking_report(scene, renderer, frames: int = 5) -> dict[str, Any]:
    """Track the scene's fields over a few frames (only the noise changes) with NVG-BA and
    report, per field, the pose error against ground truth and the time per frame."""
    from oralnav.control.geometry import pose_error
    from oralnav.control.tracker import Tracker

    tracker = Tracker(scene.rig, [p.field for p in scene.placements], method="nvgba")
    fields: dict[str, Any] = {}
    times = []
    for k in range(frames):
        f = renderer.render(frame=k)
        est = tracker.track(f.images)
        times.append(tracker.last_timing.total)
        for p in scene.placements:
            e = est.get(p.field.name)
            if e is None:
                fields.setdefault(p.name, []).append(None)
                continue
            te, re = pose_error(e.T_ref_field, f.T_ref_field[p.name])
            fields.setdefault(p.name, []).append((te * 1e3, float(np.degrees(re)), e.corners))
    out: dict[str, Any] = {"frames": frames, "first_ms": round(times[0], 1),
                           "steady_ms": round(float(np.median(times[1:])), 1), "fields": {}}
    for name, rows in fields.items():
        ok = [r for r in rows if r is not None]
        out["fields"][name] = {
            "found": len(ok),
            "max_err_mm": round(max(r[0] for r in ok), 4) if ok else None,
            "max_err_deg": round(max(r[1] for r in ok), 4) if ok else None,
            "corners": int(np.median([r[2] for r in ok])) if ok else 0}
    return out


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="oralnavd", description="oralnav navigation daemon")
    p.add_argument("--version", action="version", version=f"oralnavd {__version__}")
    p.add_argument("--config", help="configuration TOML (default: the embedded sim.toml)")
    p.add_argument("--check", action="store_true", help="validate the configuration and exit")
    p.add_argument("--demo", action="store_true",
                   help="simulated cell: render the views and check detection against truth")
    p.add_argument("--api-port", type=int, help="override [api] port")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    return p


def run(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        cfg = load_config(args.config)
        if args.api_port is not None and not 1 <= args.api_port <= 65535:
            raise ConfigError("--api-port", "", f"must be 1..65535, got {args.api_port}")
    except (ConfigError, ControlError) as exc:
        print(f"oralnavd: error: {exc}", file=sys.stderr)
        if args.json:
            print(json.dumps({"error": str(exc), "exit": 2}))
        return 2
    s = cfg.settings
    port = args.api_port or s.api.port
    _log(f"configuration {cfg.path} is valid: {s.cell.backend} cell, "
         f"cameras {', '.join(cfg.rig.names)}, fields {', '.join(sorted(cfg.fields))}, "
         f"control at {s.control.rate_hz:g} Hz, API on {s.api.host}:{port}")
    doc: dict[str, Any] = {"config": str(cfg.path), "valid": True, "backend": s.cell.backend,
                           "api": {"host": s.api.host, "port": port}}
    if args.demo:
        if s.cell.backend != "sim":
            _log("--demo needs the sim backend")
            return 2
        t0 = time.perf_counter()
        doc["demo"] = demo(cfg)
        doc["demo_s"] = round(time.perf_counter() - t0, 2)
    if args.json:
        print(json.dumps(doc))
    elif "demo" in doc:
        print(f"simulated cell ({cfg.path.name}): NVG-BA tracking against ground truth")
        for scene, t in doc["demo"]["tracking"].items():
            print(f"  {scene}: {t['frames']} frames, first {t['first_ms']} ms, then "
                  f"{t['steady_ms']} ms per frame")
            for name, r in t["fields"].items():
                err = (f"max error {r['max_err_mm']} mm, {r['max_err_deg']} deg"
                       if r["found"] else "not found")
                print(f"    {name:9s} found {r['found']}/{t['frames']}, {r['corners']:3d} "
                      f"corners, {err}")
        print("OpenCV's stock ChArUco detector on the first frame, against ground truth")
        for cam, e in doc["demo"]["detection"].items():
            print(f"  {cam} (render {e['render_ms']} ms)")
            for name, r in e["fields"].items():
                err = (f"mean {r['mean_err_px']} px, max {r['max_err_px']} px"
                       if r.get("mean_err_px") is not None else "no corners")
                print(f"    {name:9s} {r['found']:3d}/{r['truth']:3d} corners, {err}")
        print("run `oralnavd` without --demo to serve the cell (control loop, safety, "
              "REST API); see docs/control_loop.md and docs/api.md")
    elif not args.check:
        import anyio

        from .service import run_service
        logging.basicConfig(level=logging.INFO, format="oralnavd: %(name)s: %(message)s")
        return anyio.run(run_service, cfg, args.api_port)
    return 0


def main() -> None:
    sys.exit(run())


if __name__ == "__main__":
    main()
