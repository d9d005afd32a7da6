"""``oralnav sim aruco`` and ``oralnav sim pivot``: example inputs for the tools, made on
the simulator, so that the README's tool lines run on a fresh clone (no peer data needed).

    oralnav sim aruco --out DIR [--frames N] [--fps F] [--seed S] [--json]
    oralnav sim pivot --out FILE [--poses N] [--corner-noise PX] [--spread-deg D]
                      [--outliers N] [--seed S] [--config FILE] [--json]

``sim aruco`` renders a short video of two ArUco rigid bodies (``sim/world/aruco_video.py``)
and writes what ``oralnav track --calibration ... --body ... --tag ... --replay ...`` reads:
``video.avi``, ``calibration.txt`` and ``reference.txt`` (the scikit-surgery formats), plus
``truth.json``, every body's true pose per frame. ``sim pivot`` records a pointer pivoting
in a divot on the simulated cell (``ChainSimulator.pivot_samples``: the tracker's pose
estimator on noisy marker corners) and writes the poses in the format ``oralnav calibrate
pivot`` reads; it prints the true tip and pivot point to check the calibration against.
Every file is written atomically.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["ExampleError", "add_parsers", "cmd_aruco", "cmd_pivot"]


class ExampleError(ValueError):
    """Bad options to a command that makes example inputs (exit status 2)."""


def _progress(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def _emit(args: argparse.Namespace, doc: dict[str, Any], text: str) -> None:
    print(json.dumps(doc) if args.json else text)


def _check_range(option: str, value: float, low: float, high: float, unit: str = "") -> None:
    def show(v: float) -> str:
        return f"{v:g}" if isinstance(v, float) else str(v)  # whole counts in full

    if not low <= value <= high:
        raise ExampleError(f"{option} must be {show(low)}..{show(high)}{unit}, got "
                           f"{show(value)}")


# -- oralnav sim aruco -------------------------------------------------------------------
#: Video codecs tried in order: FFV1 is lossless (the tracker then reads exactly what was
#: rendered), MJPG is built into OpenCV and so always there, at its best quality.
VIDEO_CODECS = ("FFV1", "MJPG")


def write_video(path: Path, images: list[np.ndarray], fps: float) -> str:
    """Write mono8 ``images`` as an AVI at ``fps`` (Hz) atomically; returns the codec.

    The video is written beside ``path`` under a temporary name (with the same suffix, from
    which OpenCV picks the container) and renamed once complete and read back whole.
    """
    import cv2

    from oralnav.drivers.camera.replay import frame_count
    from oralnav.drivers.errors import DriverError

    h, w = images[0].shape[:2]
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp{path.suffix}")
    try:
        for codec in VIDEO_CODECS:
            writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*codec), fps, (w, h),
                                     isColor=False)
            if not writer.isOpened():
                continue
            if codec == "MJPG":
                writer.set(cv2.VIDEOWRITER_PROP_QUALITY, 100)
            for img in images:
                writer.write(img)
            writer.release()
            try:
                if frame_count(tmp) == len(images):
                    os.replace(tmp, path)
                    return codec
            except DriverError:
                pass  # this codec's file does not read back: try the next one
        raise RuntimeError(f"{path}: OpenCV could not write a readable AVI with any of "
                           f"{', '.join(VIDEO_CODECS)}")
    finally:
        tmp.unlink(missing_ok=True)


def cmd_aruco(args: argparse.Namespace) -> int:
    """Render the ArUco example recording and write its calibration, tag table and truth."""
    from oralnav.config.loader import atomic_write_text
    from oralnav.config.rigid_bodies import save_calibration_txt, save_rigid_body
    from oralnav.sim.world.aruco_video import TAG_SPEC, render_tag_video

    _check_range("--frames", args.frames, 1, 1000)
    _check_range("--fps", args.fps, 0.1, 1000, " Hz")
    _check_range("--seed", args.seed, 0, 2**32 - 1)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    _progress(f"rendering {args.frames} frame(s) of two ArUco rigid bodies (seed {args.seed})")

    def progress(k: int, n: int) -> None:
        if k == n or k % 10 == 0:
            _progress(f"frame {k}/{n}")

    video = render_tag_video(args.frames, seed=args.seed, progress=progress)
    codec = write_video(out / "video.avi", video.images, args.fps)
    cal = save_calibration_txt(video.camera, out / "calibration.txt")
    ref = save_rigid_body(video.bodies["reference"], out / "reference.txt")
    cam = video.camera.name
    truth = {"units": {"length": "m"}, "reference": cam, "fps": args.fps, "seed": args.seed,
             "camera": {"name": cam, "size": list(video.camera.size)},
             "bodies": {"reference": {"file": ref.name,
                                      "dictionary": video.bodies["reference"].dictionary},
                        "tag": {"tag": TAG_SPEC}},
             "frames": [{"frame": k, "T_cam_body": {n: T.tolist() for n, T in poses.items()}}
                        for k, poses in enumerate(video.truth)]}
    atomic_write_text(out / "truth.json", json.dumps(truth, indent=1) + "\n")
    track = ["oralnav", "track", "--calibration", f"{cam}={cal}", "--tag", TAG_SPEC,
             "--body", f"reference={ref}", "--replay", f"{cam}={out / 'video.avi'}"]
    doc = {"out": str(out), "video": str(out / "video.avi"), "codec": codec,
           "frames": args.frames, "fps": args.fps, "calibration": str(cal),
           "bodies": {"reference": str(ref)}, "tag": TAG_SPEC,
           "truth": str(out / "truth.json"), "track": track}
    _emit(args, doc, f"wrote {args.frames} frame(s) ({codec}) of the reference body and "
                     f"tag {TAG_SPEC.split('=', 1)[1]} into {out}, with calibration.txt, "
                     f"reference.txt and truth.json; track them with\n  " + " ".join(track))
    return 0


# -- oralnav sim pivot -------------------------------------------------------------------
def cmd_pivot(args: argparse.Namespace) -> int:
    """Record a simulated pointer pivoting about a known tip; print that tip."""
    from oralnav.config.daemon import load_config
    from oralnav.config.loader import atomic_write_text
    from oralnav.sim.world.calibration_chain import POINTER_TIP, ChainSimulator

    _check_range("--poses", args.poses, 10, 100_000)
    _check_range("--corner-noise", args.corner_noise, 0.0, 5.0, " px")
    _check_range("--spread-deg", args.spread_deg, 5.0, 40.0, " deg")
    # RANSAC needs a clear majority of good poses to find them
    _check_range("--outliers", args.outliers, 0, args.poses // 2)
    _check_range("--seed", args.seed, 0, 2**32 - 1)
    cfg = load_config(args.config)
    if cfg.cell is None:
        raise ExampleError(f"--config {cfg.path}: not a simulated cell ([cell] sim_cell): "
                           "the pointer is simulated there")
    rng = np.random.default_rng(args.seed)
    _progress(f"pivoting the simulated pointer through {args.poses} poses "
              f"(up to {args.spread_deg:g} deg, corner noise {args.corner_noise:g} px)")
    sim = ChainSimulator(cfg.cell, args.corner_noise, rng)
    T, p_C = sim.pivot_samples(args.poses, args.spread_deg)
    T = T.copy()
    T[:, :3, 3] *= 1e3  # millimetres, as pointer tracking files are
    bad = np.sort(rng.choice(args.poses, size=args.outliers, replace=False))
    for i in bad:
        # a misread marker or a reflection: the reported origin jumps 10-40 mm
        d = rng.normal(size=3)
        T[i, :3, 3] += rng.uniform(10.0, 40.0) * d / np.linalg.norm(d)
    tip, pivot = POINTER_TIP * 1e3, p_C * 1e3
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    vec = "{:.3f} {:.3f} {:.3f}".format
    header = [f"oralnav sim pivot: {args.poses} poses T_camera_pointer (4 rows each, mm) of "
              "a pointer pivoting in a divot",
              f"true tip offset (pointer frame) {vec(*tip)} mm; true pivot point (camera "
              f"frame) {vec(*pivot)} mm",
              f"corner noise {args.corner_noise:g} px, spread {args.spread_deg:g} deg, "
              f"{args.outliers} outlier poses, seed {args.seed}"]
    rows = (" ".join(f"{v:.10g}" for v in row) for row in T.reshape(-1, 4))
    atomic_write_text(out, "".join(f"# {h}\n" for h in header)
                      + "".join(f"{r}\n" for r in rows))
    doc = {"out": str(out), "poses": args.poses, "unit": "mm", "tip_offset": tip.tolist(),
           "pivot_point": pivot.tolist(), "corner_noise_px": args.corner_noise,
           "spread_deg": args.spread_deg, "outliers": bad.tolist(), "seed": args.seed}
    _emit(args, doc, f"wrote {args.poses} pointer poses ({args.outliers} outliers) to {out}; "
                     f"true tip offset [{vec(*tip)}] mm (pointer frame), pivot point "
                     f"[{vec(*pivot)}] mm (camera frame)\n  check: oralnav calibrate pivot "
                     f"--matrices {out} --method ransac")
    return 0


def add_parsers(sim: argparse._SubParsersAction) -> None:
    """Add ``aruco`` and ``pivot`` to the ``oralnav sim`` subcommands."""
    ar = sim.add_parser("aruco", help="render a short video of ArUco rigid bodies with its "
                                      "calibration.txt, reference.txt and truth (the inputs "
                                      "of oralnav track --calibration ... --replay ...)")
    ar.add_argument("--out", required=True, help="folder for video.avi, calibration.txt, "
                                                 "reference.txt and truth.json")
    ar.add_argument("--frames", type=int, default=20, help="frames to render (20)")
    ar.add_argument("--fps", type=float, default=10.0, help="the video's frame rate, Hz (10)")
    ar.add_argument("--seed", type=int, default=0, help="image noise seed (0)")
    ar.add_argument("--json", action="store_true", help="print one JSON object")
    ar.set_defaults(func=cmd_aruco)
    pv = sim.add_parser("pivot", help="record a simulated pointer pivoting about a known tip "
                                      "(the input of oralnav calibrate pivot); prints the tip")
    pv.add_argument("--out", required=True, help="text file of stacked 4x4 poses to write (mm)")
    pv.add_argument("--poses", type=int, default=150, help="poses to record (150)")
    pv.add_argument("--corner-noise", type=float, default=0.15,
                    help="marker-corner noise, px (0.15, the tracker's residual)")
    pv.add_argument("--spread-deg", type=float, default=25.0,
                    help="largest tilt of the pointer from upright, deg (25)")
    pv.add_argument("--outliers", type=int, default=0,
                    help="poses whose position jumps 10-40 mm, as a misread marker's would "
                         "(0; what --method ransac leaves out)")
    pv.add_argument("--seed", type=int, default=0, help="seed of the poses and the noise (0)")
    pv.add_argument("--config", default=None, help="daemon configuration with [cell] sim_cell "
                                                   "(default: the shipped sim.toml)")
    pv.add_argument("--json", action="store_true", help="print one JSON object")
    pv.set_defaults(func=cmd_pivot)
