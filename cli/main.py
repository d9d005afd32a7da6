"""``oralnav``: the command-line tools.

    oralnav sim render SCENE.toml --out DIR [--frames N] [--seed N] [--json]
    oralnav sim peers --out DIR [--no-cameras] [--json]
    oralnav sim aruco --out DIR [--frames N] [--json]        (cli/examples.py)
    oralnav sim pivot --out FILE [--poses N] [--outliers N] [--json]
    oralnav markers print FIELD [--fields FILE] --dpi N --out F.png [--no-label] [--json]
    oralnav config check [FILE] [--json]
    oralnav track --rig RIG --fields FIELDS --image NAME=PATH [...] [--method M] [--json]
    oralnav track --rig RIG --fields FIELDS --replay NAME=SOURCE [...] [--mode M] [--json]
    oralnav track --calibration NAME=calibration.txt [--fields FIELDS] [--body NAME=PATH ...]
                  [--tag NAME=DICT:ID:SIDE_MM ...] --replay NAME=VIDEO [--frames N] [--json]
    oralnav calibrate pivot --matrices FILE [--method M] [--json] [--out F --cell ID]
    oralnav plan mouth --out FILE.stl [--width-mm W] [--no-teeth] [--json]
    oralnav plan fpsm --mesh FILE --slices M --points N --out FPSM.json [--json]
    oralnav plan place --scene FILE [--figures DIR] [--json]
    oralnav replay FILE.mcap [--json]
    oralnav bench navigation|control|calibration|planning [--quick] --out DIR
    oralnav bench needle [--trials N] [--seed S | --validation] [--workers W] [--arm-error MM DEG]
                         [--servo] [--stream] [--scheduler ADDRESS] [--quick] [--tracking]
                         --out DIR [--json]
    oralnav bench faults [--quick] --out DIR [--json]
    oralnav bench busy-demo --out DIR [--runs N] [--busy N] [--json]
    oralnav bench console --out DIR [--seconds S] [--fps F] [--rounds N] [--json]
    oralnav bench hil --out DIR [--runs N] [--camera-latency S] [--camera-clock-offset S]
    oralnav bench igtl --out DIR [--seconds S] [--json]
    oralnav bench needle-stream --out DIR [--seed S] [--trials N] [--fps F ...] [--json]
    oralnav report --out DIR [--quick] [--force] [--only KEY ...] [--scheduler ADDRESS]
                                                             (cli/report.py)

Every ``--json`` prints exactly one JSON object on stdout; progress and logs go to stderr.
Exit status: 0 done, 2 bad input (the message names the file and key), 1 anything else.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Sequence
from dataclasses import replace
from importlib import resources
from pathlib import Path
from typing import Any

import cv2

from oralnav import __version__
from oralnav.cli import calibrate, examples, plan, replay, report, temporal
from oralnav.cli.extras import missing_extra, require_bench_extra
from oralnav.cli.sheets import SheetError, render_sheet, write_png
from oralnav.config.daemon import load_config
from oralnav.config.errors import ConfigError
from oralnav.config.fields import load_fields
from oralnav.config.loader import atomic_write_bytes, atomic_write_text
from oralnav.config.scene import load_scene
from oralnav.control.errors import ControlError
from oralnav.sim.world.render import RenderError, SceneRenderer


class UsageError(Exception):
    """Bad command-line input that argparse cannot catch (exit status 2)."""


def _default_fields() -> Path:
    """The marker fields shipped with the simulated cell, used when no --fields is given."""
    return Path(str(resources.files("oralnav.config").joinpath("fields/cell.toml")))


def _progress(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def _emit(args: argparse.Namespace, doc: dict[str, Any], text: str) -> None:
    if args.json:
        print(json.dumps(doc))
    else:
        print(text)


# -- oralnav sim render ---------------------------------------------------------------
def cmd_sim_render(args: argparse.Namespace) -> int:

    scene = load_scene(args.scene)
    if args.seed is not None:
        scene = replace(scene, seed=args.seed)
    if args.frames < 1:
        raise UsageError("--frames must be at least 1")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    renderer = SceneRenderer(scene)
    t0 = time.perf_counter()
    renderer.prepare()
    prep = time.perf_counter() - t0
    frames = []
    for k in range(args.frames):
        frame = renderer.render(frame=k)
        folder = out if args.frames == 1 else out / f"frame_{k:04d}"
        folder.mkdir(exist_ok=True)
        files = {}
        for cam, img in frame.images.items():
            name = f"{cam}.png"
            ok, buf = cv2.imencode(".png", img)
            if not ok:
                raise RuntimeError(f"PNG encoding failed for camera {cam!r}")
            atomic_write_bytes(folder / name, buf.tobytes())
            files[cam] = name
        truth = frame.truth_json(scene.rig.reference, files)
        atomic_write_text(folder / "truth.json", json.dumps(truth, indent=1) + "\n")
        frames.append({"folder": str(folder), "render_ms": {c: round(s * 1e3, 2) for c, s in
                                                            frame.render_s.items()},
                       "visible_corners": {c: {f: len(t.corner_ids) for f, t in fl.items()}
                                           for c, fl in frame.truth.items()}})
        _progress(f"frame {k + 1}/{args.frames}: " + ", ".join(
            f"{c} {s * 1e3:.1f} ms" for c, s in frame.render_s.items()))
    doc = {"scene": str(args.scene), "out": str(out), "seed": scene.seed,
           "prepare_s": round(prep, 3), "frames": frames}
    lines = [f"rendered {args.frames} frame(s) of {args.scene} into {out} (seed {scene.seed})"]
    for cam, fl in frames[-1]["visible_corners"].items():
        lines.append(f"  {cam}: " + (", ".join(f"{f} {n} corners" for f, n in fl.items())
                                     or "no field visible"))
    _emit(args, doc, "\n".join(lines))
    return 0


# -- oralnav markers print ------------------------------------------------------------
# -- oralnav sim peers ----------------------------------------------------------------
_PEER_KEYS = """keys (then Enter): e e-stop press/release, p pedal press/release,
  s protective stop on the arm, f fault on drive axis 1, q quit"""


def cmd_sim_peers(args: argparse.Namespace) -> int:
    """Run a hardware cell of protocol peers until q, end of input or Ctrl-C."""
    import signal

    def leave(signum: int, frame: object) -> None:
        signal.signal(signal.SIGTERM, signal.SIG_IGN)  # one is enough: clean up in peace
        raise KeyboardInterrupt  # unwinds through the peers' clean-up

    signal.signal(signal.SIGTERM, leave)
    _progress("starting the peers: fake UR controller, Modbus drive unit, serial e-stop "
              "box" + {"none": "", "pattern": ", simulated GigE cameras (test pattern)",
                       "rendered": ", the simulated cell's cameras (rendering their "
                                   "maps takes a few seconds)"}[args.cameras] + "...")
    try:
        _run_peers(args)
    except KeyboardInterrupt:  # a signal while starting or stopping: cleaned up already
        pass
    _progress("peers stopped")
    return 0


def _run_peers(args: argparse.Namespace) -> None:
    import signal

    from oralnav.cli.peers import HardwarePeers

    if args.frame_rate is not None and not 0.1 <= args.frame_rate <= 1000:
        raise UsageError(f"--frame-rate must be 0.1..1000 Hz, got {args.frame_rate}")
    if not 0.0 <= args.camera_latency <= 1.0:
        raise UsageError(f"--camera-latency must be 0..1 s, got {args.camera_latency}")
    with HardwarePeers(args.out, cameras=args.cameras, frame_rate=args.frame_rate,
                       camera_latency=args.camera_latency,
                       camera_clock_offset=args.camera_clock_offset) as peers:
        path = peers.write_config()
        cams = (peers.rendered.addresses if peers.rendered is not None
                else dict(zip(("left", "right"), peers.camera_addresses, strict=False)))
        doc = {"config": str(path), "ur_host": peers.ur.host, "modbus_port": peers.drive.port,
               "estop": str(peers.box.link), "cameras": cams,
               "truth": peers.truth.url if peers.truth is not None else None}
        _emit(args, doc, f"peers running; configuration {path}\n"
                         f"  run: oralnavd --config {path}\n{_PEER_KEYS}")
        sys.stdout.flush()
        try:
            for line in sys.stdin:
                key = line.strip().lower()[:1]
                if key == "q":
                    break
                if key == "e":
                    (peers.box.release_estop if peers.box.estop else peers.box.press_estop)()
                    _progress(f"e-stop {'pressed' if peers.box.estop else 'released'}")
                elif key == "p":
                    (peers.box.release_pedal if peers.box.pedal else peers.box.press_pedal)()
                    _progress(f"pedal {'pressed' if peers.box.pedal else 'released'}")
                elif key == "s":
                    peers.ur.inject_protective_stop()
                    _progress("protective stop (POST /recover/arm, then /reset)")
                elif key == "f":
                    peers.drive.fault_axis(1)
                    _progress("drive axis 1 faulted (POST /recover/effector, then /reset)")
                elif key:
                    _progress(_PEER_KEYS)
            else:  # end of input (not a terminal): run until SIGINT or SIGTERM
                while True:
                    signal.pause()
        except KeyboardInterrupt:
            pass


def cmd_markers_print(args: argparse.Namespace) -> int:
    fields_path = Path(args.fields) if args.fields else _default_fields()
    fields = load_fields(fields_path)
    if args.field not in fields:
        raise UsageError(f"{fields_path}: no field {args.field!r}; it has {sorted(fields)}")
    fld = fields[args.field]
    sheet = render_sheet(fld, args.dpi, label=not args.no_label)
    write_png(args.out, sheet.image, args.dpi)
    w_mm, h_mm = (round(v * 1e3, 6) for v in fld.sheet_size)
    doc = {"field": fld.name, "out": str(args.out), "dpi": args.dpi,
           "image_px": [int(sheet.image.shape[1]), int(sheet.image.shape[0])],
           "board_mm": [w_mm, h_mm], "board_origin_px": list(sheet.board_origin_px),
           "ids": [int(fld.first_id), int(fld.first_id + fld.marker_count - 1)]}
    _emit(args, doc, f"wrote {args.out}: field {fld.name!r}, board {w_mm:g} x {h_mm:g} mm at "
                     f"{args.dpi:g} dpi; print at 100 % (actual size) and check the scale bar")
    return 0


# -- oralnav config check -------------------------------------------------------------
def cmd_config_check(args: argparse.Namespace) -> int:
    cfg = load_config(args.file)
    s = cfg.settings
    doc = {"config": str(cfg.path), "name": s.name, "backend": s.cell.backend,
           "cameras": list(cfg.rig.names),
           "endoscope": list(cfg.endoscope_rig.names) if cfg.endoscope_rig else [],
           "fields": sorted(cfg.fields), "rate_hz": s.control.rate_hz,
           "api": f"{s.api.host}:{s.api.port}",
           "calibrations": {k: {"file": c.source, "method": c.method, "created": c.created}
                            for k, c in cfg.calibrations.items()},
           "calibrations_missing": cfg.missing_calibrations()}
    cals = (f"; calibrations of cell {s.calibration.cell!r}: {', '.join(cfg.calibrations)}"
            if cfg.calibrations and s.calibration else "; no calibration files")
    if doc["calibrations_missing"]:
        cals += f" (missing: {', '.join(doc['calibrations_missing'])})"
    _emit(args, doc, f"{cfg.path}: valid ({s.cell.backend} cell, cameras "
                     f"{', '.join(doc['cameras'] + doc['endoscope'])}, fields "
                     f"{', '.join(doc['fields'])}{cals})")
    return 0


# -- oralnav track --------------------------------------------------------------------
def _named_paths(items: Sequence[str], option: str, what: str = "camera") -> dict[str, Path]:
    out: dict[str, Path] = {}
    for item in items:
        name, sep, path = item.partition("=")
        if not sep or not name or not path:
            raise UsageError(f"{option} expects NAME=PATH, got {item!r}")
        if name in out:
            raise UsageError(f"{option}: {what} {name!r} given twice")
        out[name] = Path(path)
    return out


def _calibration_rig(items: Sequence[str], images: dict[str, Any] | None,
                     sources: dict[str, Path] | None):
    """A one-camera rig from ``--calibration NAME=FILE``: a scikit-surgery calibration.txt,
    or a one-camera OpenCV FileStorage, ROS camera_info or Kalibr camchain file (judged
    from its content). The camera is the reference frame, named NAME; its image size is
    that of its first image, and a file that holds a size must agree with it."""
    from dataclasses import replace

    from oralnav.config.camera_files import detect_format, load_camera_file, sniff_format
    from oralnav.config.rigid_bodies import load_calibration_txt
    from oralnav.control.vision.camera import Rig
    from oralnav.drivers.camera.replay import read_frame
    from oralnav.drivers.errors import DriverError

    cal = _named_paths(items, "--calibration")
    if len(cal) != 1:
        raise UsageError("--calibration builds a one-camera rig: give it once "
                         "(use --rig RIG for several cameras)")
    ((name, path),) = cal.items()
    option = "--image" if images is not None else "--replay"
    given = images if images is not None else sources
    if not given or name not in given:
        raise UsageError(f"--calibration names camera {name!r}, but no {option} "
                         f"{name}=... is given")
    if images is not None:
        h, w = images[name].shape[:2]
    else:
        try:
            h, w = read_frame(given[name], 0).shape[:2]
        except DriverError as exc:
            raise UsageError(str(exc)) from exc
    fmt = "folder" if path.is_dir() else sniff_format(path)
    if fmt is None and path.suffix.lower() in (".yaml", ".yml", ".xml", ".json"):
        detect_format(path)  # raises: none of the formats, with what was expected
    if fmt is None:  # none of the ecosystem's formats: scikit-surgery's text
        return Rig(name, {name: load_calibration_txt(path, (w, h), name=name)})
    if fmt not in ("opencv", "ros", "kalibr"):
        raise UsageError(f"--calibration {name}={path}: a {'rig TOML' if fmt == 'toml' else fmt}"
                         " is not a one-camera calibration file; give it as --rig")
    rig = load_camera_file(path, size=(w, h), fmt=fmt)
    if len(rig.cameras) != 1:
        raise UsageError(f"--calibration {name}={path}: the file holds {len(rig.cameras)} "
                         "cameras; --calibration builds a one-camera rig (use --rig FILE)")
    (cam,) = rig.cameras.values()
    return Rig(name, {name: replace(cam, name=name)})


def _tag_bodies(items: Sequence[str]) -> list:
    """One-tag bodies from ``--tag NAME=DICT:ID:SIDE_MM``."""
    from oralnav.control.errors import MarkerFieldError
    from oralnav.control.vision.rigid_body import single_tag_body

    out = []
    for item in items:
        name, sep, spec = item.partition("=")
        parts = spec.split(":")
        if not sep or not name or len(parts) != 3:
            raise UsageError(f"--tag expects NAME=DICT:ID:SIDE_MM (e.g. "
                             f"tag=DICT_4X4_50:0:50), got {item!r}")
        dictionary, tag_id, side = parts
        try:
            tid, side_mm = int(tag_id), float(side)
        except ValueError:
            raise UsageError(f"--tag {item!r}: ID must be a whole number and SIDE_MM a "
                             "length in millimetres") from None
        try:
            out.append(single_tag_body(tid, side_mm * 1e-3, dictionary, name=name))
        except MarkerFieldError as exc:
            raise UsageError(f"--tag {item!r}: {exc}") from None
    return out


def _read_mono(path: Path, camera: str) -> Any:
    if not path.is_file():
        raise UsageError(f"camera {camera!r}: no image file {path}")
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise UsageError(f"camera {camera!r}: {path} is not a readable image")
    return img


def _estimate_doc(est) -> dict[str, Any]:
    doc = {"T_ref_field": [[round(float(v), 9) for v in row] for row in est.T_ref_field],
           "corners": est.corners, "reproj_rms_px": round(est.reproj_rms_px, 4),
           "cameras": list(est.cameras),
           "position_sigma_mm": round(est.position_sigma_m * 1e3, 5)}
    if hasattr(est, "tags_seen"):  # a rigid body's BodyEstimate
        doc.update(method=est.method, tags_seen=list(est.tags_seen),
                   tags_used=list(est.tags_used), quality=round(est.quality, 5))
    return doc


def _frame_doc(tracker, est: dict[str, Any]) -> dict[str, Any]:
    """One frame's estimates: marker fields under "fields", rigid bodies under "bodies"
    (same keys, plus method, tags_seen, tags_used, quality), and the timing in ms."""
    t = tracker.last_timing
    return {"fields": {n: _estimate_doc(e) for n, e in est.items() if n in tracker.fields},
            "bodies": {n: _estimate_doc(e) for n, e in est.items() if n in tracker.bodies},
            "timing_ms": {k: round(v, 3) for k, v in t.as_dict().items() if k != "stages"}}


def _found(est: dict[str, Any]) -> str:
    return ", ".join(f"{n} {len(e.tags_used)} tag(s)" if hasattr(e, "tags_used")
                     else f"{n} {e.corners} corners" for n, e in est.items()) or "nothing found"


def cmd_track(args: argparse.Namespace) -> int:
    from oralnav.config.rig import load_rig
    from oralnav.config.rigid_bodies import load_rigid_bodies
    from oralnav.control.vision.tracker import Tracker

    if bool(args.image) == bool(args.replay):
        raise UsageError("give either --image NAME=PATH (one frame) or --replay NAME=SOURCE")
    if bool(args.rig) == bool(args.calibration):
        raise UsageError("give either --rig RIG or --calibration NAME=FILE (one camera)")
    images = sources = None
    if args.image:
        images = {c: _read_mono(p, c) for c, p in _named_paths(args.image, "--image").items()}
    else:
        sources = _named_paths(args.replay, "--replay")
    rig = load_rig(args.rig) if args.rig else _calibration_rig(args.calibration, images,
                                                                sources)
    fields = list(load_fields(args.fields).values()) if args.fields else []
    bodies = load_rigid_bodies(
        _named_paths(args.body, "--body", "body").items(), args.body_dictionary)
    bodies += _tag_bodies(args.tag)
    if not fields and not bodies:
        raise UsageError("nothing to track: give --fields FIELDS, --body NAME=PATH or "
                         "--tag NAME=DICT:ID:SIDE_MM")
    tracker = Tracker(rig, fields, method=args.method, mode=args.mode, bodies=bodies)
    if images is not None:
        est = tracker.track(images)
        t = tracker.last_timing
        lines = [f"{n}: {e.corners} corners, rms {e.reproj_rms_px:.3f} px, t = "
                 + " ".join(f"{v * 1e3:.3f}" for v in e.T_ref_field[:3, 3]) + " mm"
                 for n, e in est.items()] or ["nothing found"]
        _emit(args, _frame_doc(tracker, est), "\n".join(lines + [f"total {t.total:.1f} ms"]))
        return 0
    return _track_replay(args, tracker, sources)


def _track_replay(args: argparse.Namespace, tracker, sources: dict[str, Path]) -> int:
    from oralnav.drivers.camera.replay import frame_count, read_frame
    from oralnav.drivers.errors import DriverError

    try:
        counts = {c: frame_count(p) for c, p in sources.items()}
    except DriverError as exc:
        raise UsageError(str(exc)) from exc
    n = min(counts.values())
    if args.frames is not None:
        n = min(n, args.frames)
    frames = []
    for k in range(n):
        try:
            images = {c: read_frame(p, k) for c, p in sources.items()}
        except DriverError as exc:
            raise UsageError(str(exc)) from exc
        est = tracker.track(images)
        frames.append({"frame": k, **_frame_doc(tracker, est),
                       "stages": dict(tracker.last_timing.stages)})
        if not args.json or (k + 1) % 25 == 0:
            _progress(f"frame {k + 1}/{n}: {_found(est)}")
    times = [f["timing_ms"]["total"] for f in frames]
    doc = {"frames": frames, "timing_ms": {
        "median": round(float(sorted(times)[len(times) // 2]), 3) if times else None}}
    _emit(args, doc, f"tracked {n} frame(s); median {doc['timing_ms']['median']} ms per frame")
    return 0


# -- oralnav bench --------------------------------------------------------------------
def cmd_bench(args: argparse.Namespace) -> int:
    require_bench_extra()
    from oralnav.bench import calibration, control, navigation, planning

    bench = {"navigation": navigation, "control": control, "calibration": calibration,
             "planning": planning}[args.cmd]
    bench.main(Path(args.out), quick=args.quick)
    return 0


def cmd_bench_needle(args: argparse.Namespace) -> int:
    require_bench_extra()
    from oralnav.bench import needle

    if args.trials is not None and args.trials < 1:
        raise UsageError(f"--trials must be at least 1, got {args.trials}")
    if args.workers is not None and args.workers < 1:
        raise UsageError(f"--workers must be at least 1, got {args.workers}")
    try:
        arm_error = needle.arm_error_checked(args.arm_error)
    except ValueError:
        raise UsageError(f"--arm-error takes two finite values >= 0 (mm, deg), got "
                         f"{' '.join(f'{v:g}' for v in args.arm_error)}") from None
    if args.validation and (args.seed is not None or args.quick):
        raise UsageError("--validation runs the validation seeds from "
                         f"{needle.VALIDATION_SEED}: give it without --seed or --quick")
    levels = args.difficulty or [1.0]
    try:
        levels = [needle.difficulty_checked(d) for d in levels]
    except ValueError as exc:
        raise UsageError(f"--difficulty: {exc}") from None
    sweeping = len(levels) > 1
    if sweeping and (args.servo or args.tracking):
        raise UsageError("a --difficulty sweep runs each difficulty open-loop and servoed "
                         "(--stream: servoed from the tracking task), and charts no "
                         "tracking: give it without --servo or --tracking")
    from oralnav.bench.executor import SchedulerError

    try:
        doc = needle.main(Path(args.out), quick=args.quick, trials=args.trials,
                          seed=args.seed or 0, workers=args.workers,
                          scheduler=args.scheduler, validation=args.validation,
                          arm_error=arm_error, servo=args.servo or args.stream,
                          difficulty=levels, stream=args.stream)
    except SchedulerError as exc:
        raise UsageError(str(exc)) from None
    if sweeping:
        points = {name: [round(p["overall"], 4) for p in pts]
                  for name, pts in doc["modes"].items()}
        _emit(args, {"levels": doc["levels"], "trials": doc["trials"], "overall": points},
              f"sweep over difficulties {', '.join(f'{d:g}' for d in doc['levels'])}: "
              + "; ".join(f"{name.replace('_', '-')} "
                          + ", ".join(f"{100 * v:.0f} %" for v in vals)
                          for name, vals in points.items())
              + f" (details in {Path(args.out) / 'needle_difficulty.json'})")
        return 0
    s = needle.summary(doc)
    _emit(args, s, f"{s['trials']} trials on {doc['split']} seeds: "
                   f"overall {100 * s['overall']:.1f} %; "
                   + ", ".join(f"{k} {100 * v:.1f} %" for k, v in s["steps"].items())
                   + f" (details in {Path(args.out) / 'needle.json'})")
    if args.tracking:
        from oralnav.bench import needle_tracking

        # the speed/accuracy chart goes to the same folder; its summary to stderr
        needle_tracking.main(Path(args.out), quick=args.quick, seed=args.seed or 0)
    return 0


def cmd_bench_hil(args: argparse.Namespace) -> int:
    """``oralnav bench hil``: exit 0 when every run passed, 1 otherwise."""
    from oralnav.bench import hil

    if args.runs < 1:
        raise UsageError(f"--runs must be at least 1, got {args.runs}")
    if not 0.0 <= args.camera_latency <= 1.0:
        raise UsageError(f"--camera-latency must be 0..1 s, got {args.camera_latency}")
    from functools import partial

    from oralnav.cli.peers import HardwarePeers

    doc = hil.main(Path(args.out), partial(HardwarePeers, cameras="rendered"),
                   runs=args.runs, camera_latency=args.camera_latency,
                   camera_clock_offset=args.camera_clock_offset)
    s = {k: v for k, v in doc.items() if k != "results"}
    if args.json:
        print(json.dumps(s))
    else:
        print(f"main job on the hardware-in-the-loop cell: {doc['passed']}/{doc['runs']} "
              f"passed; TRE max {s['tre_max_mm']} mm over {s['tre_measured']} targets; "
              f"latency p99 {s['latency_p99_ms']} ms; slowest tracking "
              f"{s['tracking_hz_min']} frames/s")
    return 0 if doc["passed"] == doc["runs"] else 1


def cmd_bench_console(args: argparse.Namespace) -> int:
    """``oralnav bench console``: exit 0 when the tracking rate with a console open on
    another machine is within 5 % of the rate without one (issue 33), 1 otherwise."""
    from oralnav.bench import console

    if args.seconds < 2 or args.rounds < 1:
        raise UsageError(f"--seconds must be at least 2 and --rounds at least 1, got "
                         f"{args.seconds:g} and {args.rounds}")
    doc = console.main(Path(args.out), seconds=args.seconds, fps=args.fps,
                       rounds=args.rounds)
    s = {k: v for k, v in doc.items() if k != "windows"}
    if args.json:
        print(json.dumps(s))
    else:
        print(f"tracking {s['tracking_hz_closed']:.2f} rounds/s with the console closed "
              f"(daemon {s['daemon_cores_closed']:.2f} cores)")
        for mode, where in (("browser", "open in a browser on this machine"),
                            ("remote", "open on another machine (its traffic only)")):
            m, fps = s[mode], s[mode]["console_fps_per_view"]
            lo, hi = m["tracking_change_pct_range"]
            print(f"  {m['tracking_hz']:.2f} rounds/s {where}: {m['tracking_change_pct']:+.1f}"
                  f" % (median against the closed windows either side; range {lo:+.1f} .. "
                  f"{hi:+.1f} %; daemon {m['daemon_cores']:.2f} cores); "
                  f"{'-' if fps is None else f'{fps:.2f}'} frames/s per view shown "
                  f"(setting {s['fps_setting']})")
        print(f"  (the remote console's client itself used {s['remote']['client_cores']:.3f} "
              "cores of this machine)")
    return 0 if s["remote"]["tracking_change_pct"] >= -5.0 else 1


def cmd_bench_busy_demo(args: argparse.Namespace) -> int:
    """``oralnav bench busy-demo``: exit 0 when every run passed, 1 otherwise."""
    from oralnav.bench import busy_demo

    if args.runs < 1:
        raise UsageError(f"--runs must be at least 1, got {args.runs}")
    if args.busy is not None and args.busy < 0:
        raise UsageError(f"--busy must be 0 or more, got {args.busy}")
    doc = busy_demo.main(Path(args.out), runs=args.runs, busy=args.busy)
    s = {k: v for k, v in doc.items() if k != "results"}
    if args.json:
        print(json.dumps(s))
    else:
        def fmt(v: float | None, digits: int) -> str:
            return "-" if v is None else f"{v:.{digits}f}"

        print(f"main job on a busy machine ({doc['busy']} busy processes, {doc['cpus']} "
              f"CPUs): {doc['passed']}/{doc['runs']} passed; duration median "
              f"{fmt(s['duration_s']['median'], 1)} s, max {fmt(s['duration_s']['max'], 1)} "
              f"s; TRE max {fmt(s['tre_max_mm'], 3)} mm; slowest tracking "
              f"{fmt(s['tracking_hz_min'], 2)} frames/s")
        for why in s["failures"]:
            print(f"  failed: {why}")
    return 0 if doc["passed"] == doc["runs"] else 1


def cmd_bench_faults(args: argparse.Namespace) -> int:
    require_bench_extra()
    from oralnav.bench import faults

    s = faults.summary(faults.main(Path(args.out), quick=args.quick))
    _emit(args, s, "fault campaign: " + ", ".join(
        f"{k} {'met' if v['met'] else 'NOT met' if v['met'] is False else 'undecided'}"
        for k, v in s["targets"].items()) + f" (details in {s['json']})")
    return 0


def _stream_line(r: dict[str, Any]) -> str:
    """One played-back rate of ``oralnav bench needle-stream`` in words."""
    at = "as taken" if not r["fps"] else f"{r['fps']:g} fps"
    return (f"{at} {r['rate_hz']['p50']} Hz, arrival to step p50 {r['latency_ms']['p50']}"
            f" / p99 {r['latency_ms']['p99']} ms")


def cmd_bench_needle_stream(args: argparse.Namespace) -> int:
    """``oralnav bench needle-stream``: the streamed drive servo's rate and latency with
    the recorded frames played at camera rate (bench/needle_stream.py)."""
    from oralnav.bench import needle_stream

    if args.trials < 1:
        raise UsageError(f"--trials must be at least 1, got {args.trials}")
    if any(not (math.isfinite(f) and f >= 0) for f in args.fps):
        raise UsageError(f"--fps takes frame rates >= 0 (0: as fast as tracked), got "
                         f"{' '.join(f'{f:g}' for f in args.fps)}")
    try:
        doc = needle_stream.main(Path(args.out), seed=args.seed, trials=args.trials,
                                 fps=args.fps)
    except RuntimeError as exc:
        raise UsageError(str(exc)) from None
    summary = {k: {"rate_hz": r["rate_hz"], "latency_ms": r["latency_ms"],
                   "skipped": r["skipped"]} for k, r in doc["replay"].items()}
    _emit(args, {"drives": doc["drives"], "replay": summary, "command_ms": doc["command_ms"],
                 "closed_loop_rate_hz": doc["closed_loop"]["rate_hz"], "met": doc["met"]},
          f"{doc['drives']} streamed drives; closed-loop (renderer-paced) "
          f"{doc['closed_loop']['rate_hz']['p50']} Hz; played back: "
          + "; ".join(_stream_line(r) for r in doc["replay"].values())
          + f"; command p50 {(doc['command_ms'] or {}).get('p50')} ms; "
          f"30 Hz target {'met' if doc['met'] else 'not met'}")
    return 0


def cmd_bench_igtl(args: argparse.Namespace) -> int:
    """``oralnav bench igtl``: the OpenIGTLink server's message rate and pose age on
    loopback, read with pyigtl's client (bench/igtl.py)."""
    from oralnav.bench import igtl
    from oralnav.daemon.igtl import standalone_server

    if not args.seconds > 0:
        raise UsageError(f"--seconds must be positive, got {args.seconds:g}")
    doc = igtl.main(Path(args.out), standalone_server, seconds=args.seconds)
    if args.json:
        print(json.dumps(doc["runs"]))
    else:
        for name, r in doc["runs"].items():
            age = r["age_ms"] or {}
            print(f"{name}: {r['messages_per_s_per_pose']:.1f} messages/s per pose "
                  f"({r['poses']} poses, server at {r['rate_hz']:g} Hz); age at receipt "
                  f"p50 {age.get('p50', '-')} ms, p99 {age.get('p99', '-')} ms")
    return 0


class _Parser(argparse.ArgumentParser):
    """An argument parser whose subcommands refuse arguments they do not know themselves.

    argparse's subcommands leave unknown arguments to the top-level parser, which then
    prints the top-level usage; the subcommand's own usage is what helps. The subcommand
    parsers are of the parent's class, so every level refuses its own unknown arguments.
    """

    def parse_known_args(self, args: Sequence[str] | None = None,
                         namespace: argparse.Namespace | None = None
                         ) -> tuple[argparse.Namespace, list[str]]:
        ns, extras = super().parse_known_args(args, namespace)
        if extras:
            self.error(f"unrecognized arguments: {' '.join(extras)}")
        return ns, extras


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="oralnav", description="oralnav tools")
    p.add_argument("--version", action="version", version=f"oralnav {__version__}")
    sub = p.add_subparsers(dest="group", required=True)

    sim = sub.add_parser("sim", help="scene simulator").add_subparsers(dest="cmd", required=True)
    r = sim.add_parser("render", help="render a scene file to PNGs with ground truth")
    r.add_argument("scene", help="scene TOML file (see docs/formats.md)")
    r.add_argument("--out", required=True, help="output folder (created if missing)")
    r.add_argument("--frames", type=int, default=1, help="frames to render (noise differs)")
    r.add_argument("--seed", type=int, default=None, help="override the scene's seed")
    r.add_argument("--json", action="store_true", help="print one JSON object")
    r.set_defaults(func=cmd_sim_render)

    pe = sim.add_parser("peers", help="run a hardware cell of protocol peers (fake UR "
                        "controller, Modbus drive, serial e-stop box, GigE cameras) and "
                        "write its configuration")
    pe.add_argument("--out", required=True, help="folder for cell.toml and the e-stop link")
    pe.add_argument("--cameras", choices=("rendered", "pattern", "none"), default="rendered",
                    help="rendered (default): the simulated cell's stereo pair and endoscope "
                         "showing the arm and wrist where the peers have them, with the "
                         "cell's calibration and ground truth; pattern: Aravis's test "
                         "pattern only; none")
    pe.add_argument("--no-cameras", action="store_const", dest="cameras", const="none",
                    help="the same as --cameras none")
    pe.add_argument("--frame-rate", type=float, default=None,
                    help="camera frame rate, Hz (default 1.5 rendered, 10 pattern)")
    pe.add_argument("--camera-latency", type=float, default=0.0,
                    help="s from a rendered frame's capture to its transfer (0..1)")
    pe.add_argument("--camera-clock-offset", type=float, default=0.0,
                    help="s, the error of the rendered cameras' PTP timestamps (positive: "
                         "late), what oralnav calibrate temporal finds")
    pe.add_argument("--json", action="store_true", help="print one JSON object")
    pe.set_defaults(func=cmd_sim_peers)
    examples.add_parsers(sim)

    mk = sub.add_parser("markers", help="marker fields").add_subparsers(dest="cmd",
                                                                        required=True)
    pr = mk.add_parser("print", help="write a printable sheet of a field at true scale")
    pr.add_argument("field", help="field name in the fields file")
    pr.add_argument("--fields", help="marker-field TOML (default: the shipped cell fields)")
    pr.add_argument("--dpi", type=float, required=True, help="printer resolution, dots/inch")
    pr.add_argument("--out", required=True, help="PNG file to write")
    pr.add_argument("--no-label", action="store_true", help="board and quiet zone only")
    pr.add_argument("--json", action="store_true", help="print one JSON object")
    pr.set_defaults(func=cmd_markers_print)

    cf = sub.add_parser("config", help="daemon configuration").add_subparsers(dest="cmd",
                                                                             required=True)
    ck = cf.add_parser("check", help="validate a daemon configuration and its files")
    ck.add_argument("file", nargs="?", default=None, help="config TOML (default: sim.toml)")
    ck.add_argument("--json", action="store_true", help="print one JSON object")
    ck.set_defaults(func=cmd_config_check)

    tk = sub.add_parser("track", help="estimate marker-field and rigid-body poses in images "
                                      "or recordings")
    tk.add_argument("--rig", help="rig TOML (cameras, reference frame)")
    tk.add_argument("--calibration", action="append", default=[], metavar="NAME=FILE",
                    help="instead of --rig: one camera from a scikit-surgery calibration.txt "
                         "(3 lines of K, 1 of distortion; pixels), the reference frame; its "
                         "image size is that of its first image")
    tk.add_argument("--fields", help="marker-field TOML (optional with --body or --tag)")
    tk.add_argument("--body", action="append", default=[], metavar="NAME=PATH",
                    help="an ArUco rigid body: a scikit-surgery tag table (tag id, centre, "
                         "4 corners; millimetres) of --body-dictionary tags (repeat per body)")
    tk.add_argument("--body-dictionary", default="DICT_ARUCO_ORIGINAL", metavar="DICT",
                    help="OpenCV dictionary of the --body tables' tags "
                         "(default DICT_ARUCO_ORIGINAL, the peer's)")
    tk.add_argument("--tag", action="append", default=[], metavar="NAME=DICT:ID:SIDE_MM",
                    help="a one-tag body, e.g. tag=DICT_4X4_50:0:50; its frame is at the tag "
                         "centre, x right and y down on the print, z away from the camera")
    tk.add_argument("--image", action="append", default=[], metavar="NAME=PATH",
                    help="one camera's image of a single frame (repeat per camera)")
    tk.add_argument("--replay", action="append", default=[], metavar="NAME=SOURCE",
                    help="one camera's recording: a video file or an image folder")
    tk.add_argument("--frames", type=int, default=None, help="replay at most N frames")
    tk.add_argument("--method", default="nvgba", choices=["nvgba", "ba", "pnp", "opencv"])
    tk.add_argument("--mode", default="predict", choices=["predict", "roi", "full"],
                    help="search stage cap for replays (a single frame always searches "
                         "whole images)")
    tk.add_argument("--json", action="store_true", help="print one JSON object")
    tk.set_defaults(func=cmd_track)

    calibrate.add_parser(sub)
    plan.add_parser(sub)
    replay.add_parser(sub)
    report.add_parser(sub)

    bn = sub.add_parser("bench", help="benchmarks").add_subparsers(dest="cmd", required=True)
    nv = bn.add_parser("navigation", help="speed/accuracy charts of the tracker (minutes)")
    nv.add_argument("--quick", action="store_true", help="fewer frames (about 2-3 minutes)")
    nv.add_argument("--out", required=True, help="folder for navigation.json and charts")
    nv.set_defaults(func=cmd_bench)
    cl = bn.add_parser("control", help="control-loop period jitter, thread against process, "
                                       "with tracking at full rate (minutes)")
    cl.add_argument("--quick", action="store_true", help="8 s per run instead of 60 s")
    cl.add_argument("--out", required=True, help="folder for control.json and its chart")
    cl.set_defaults(func=cmd_bench)
    cb = bn.add_parser("calibration", help="TRE of the calibrated chain against the number "
                                           "of samples and the corner noise (minutes)")
    cb.add_argument("--quick", action="store_true", help="8 trials a point instead of 30")
    cb.add_argument("--out", required=True, help="folder for calibration.json and its chart")
    cb.set_defaults(func=cmd_bench)
    pl = bn.add_parser("planning", help="surrogate-model fit, its answers against the exact "
                                        "mesh and the placement search, next to the paper's "
                                        "figures (about a minute)")
    pl.add_argument("--quick", action="store_true", help="fewer repeats, rods and seeds "
                                                         "(about 30 s)")
    pl.add_argument("--out", required=True, help="folder for planning.json and its charts")
    pl.set_defaults(func=cmd_bench)
    nd = bn.add_parser("needle", help="needle grasp, hand-off, drive, regrasp and pull on "
                                      "randomised simulated cells: success per step, "
                                      "failures by cause (about 5 s a trial per core)")
    nd.add_argument("--trials", type=int, default=None,
                    help="number of trials (default 200; 10 with --quick)")
    nd.add_argument("--seed", type=int, default=None,
                    help="first trial's seed (default 0; seeds 0-999 are for development)")
    nd.add_argument("--validation", action="store_true",
                    help="the validation Monte Carlo: 400 trials (or --trials) on seeds from "
                         "1,000,000, which no change is tuned on (docs/needle.md)")
    nd.add_argument("--workers", type=int, default=None,
                    help="processes (default: one per CPU)")
    nd.add_argument("--scheduler", default=None, metavar="ADDRESS",
                    help="run the trials on a Dask cluster: its scheduler's address "
                         "(tcp://host:8786), or 'local' for a LocalCluster of --workers "
                         "here (needs oralnav[cluster]; default: a local process pool)")
    nd.add_argument("--arm-error", type=float, nargs=2, default=None, metavar=("MM", "DEG"),
                    help="give each arm a kinematic error: its tool MM and DEG away from "
                         "where it reports it (a random direction and axis per arm and "
                         "trial, drawn apart from the layout; default: none)")
    nd.add_argument("--servo", action="store_true",
                    help="servo the drive on the needle tracked during it (the procedure's "
                         "drive_servo; default: open-loop, as planned)")
    nd.add_argument("--stream", action="store_true",
                    help="servo the drive from a tracking task that tracks every frame "
                         "while the arm moves, correcting on each (implies --servo, or in "
                         "a sweep is its servoed procedure; needle.json's 'stream' gives "
                         "the rate and latency)")
    nd.add_argument("--difficulty", type=float, nargs="+", default=None, metavar="D",
                    help="the trials' difficulty, 0..2 (default 1: the usual trials; up "
                         "to 1 it scales the imaging nuisances, above 1 it also tilts the "
                         "pad further and lifts the needle). Several values: the sweep, "
                         "each run open-loop and servoed, 40 trials a point (4 with "
                         "--quick): needle_difficulty.json and .png")
    nd.add_argument("--quick", action="store_true", help="fewer trials")
    nd.add_argument("--out", required=True, help="folder for needle.json (and charts)")
    nd.add_argument("--json", action="store_true",
                    help='print {"trials", "overall", "steps"} as one JSON object')
    nd.add_argument("--tracking", action="store_true",
                    help="also chart tracking speed against accuracy (particles 100..10000) "
                         "and where the tracker loses the needle: needle_tracking.json "
                         "(about 15 min; 2 with --quick)")
    nd.set_defaults(func=cmd_bench_needle)
    fa = bn.add_parser("faults", help="fault campaign on the running daemon: kill -9 of the "
                                      "daemon and of its control process, SIGSTOP, hostile "
                                      "bodies, reset cycles, a soak with RSS (about 40 min; "
                                      "3-6 with --quick)")
    fa.add_argument("--quick", action="store_true", help="3 kill rounds, 10 reset cycles, "
                                                         "a 60 s soak")
    fa.add_argument("--out", required=True, help="folder for faults.json and faults.png")
    fa.add_argument("--json", action="store_true", help="print the targets as one JSON object")
    fa.set_defaults(func=cmd_bench_faults)
    hl = bn.add_parser("hil", help="the main job on the hardware-in-the-loop cell (protocol "
                                   "peers, rendered GigE cameras): TRE against the peers' "
                                   "truth, latency, tracking rate (minutes a run)")
    hl.add_argument("--runs", type=int, default=1, help="demo runs, each on fresh peers")
    hl.add_argument("--camera-latency", type=float, default=0.0,
                    help="s from a rendered frame's capture to its transfer (0..1)")
    hl.add_argument("--camera-clock-offset", type=float, default=0.0,
                    help="s, the error of the cameras' PTP timestamps (positive: late)")
    hl.add_argument("--out", required=True, help="folder for hil.json and each run's log")
    hl.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    hl.set_defaults(func=cmd_bench_hil)
    ns = bn.add_parser("needle-stream", help="the streamed drive servo's rate and "
                                             "latency: drives recorded, their frames played "
                                             "back at camera rate (about 3 minutes)")
    ns.add_argument("--seed", type=int, default=100, help="first development seed (100)")
    ns.add_argument("--trials", type=int, default=5, help="drives to record (5)")
    ns.add_argument("--fps", type=float, nargs="+", default=[30.0, 60.0, 0.0],
                    help="camera rates to play the frames at (0: as fast as tracked; "
                         "default 30 60 0)")
    ns.add_argument("--out", required=True, help="folder for needle_stream.json")
    ns.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    ns.set_defaults(func=cmd_bench_needle_stream)
    ig = bn.add_parser("igtl", help="the OpenIGTLink server (3D Slicer): messages per "
                                    "second and pose age at receipt on loopback (about "
                                    "15 s)")
    ig.add_argument("--seconds", type=float, default=5.0, help="s per run (3 runs)")
    ig.add_argument("--out", required=True, help="folder for igtl.json")
    ig.add_argument("--json", action="store_true", help="print the runs as one JSON object")
    ig.set_defaults(func=cmd_bench_igtl)
    bd = bn.add_parser("busy-demo", help="the main job (oralnavd --demo) run again and again "
                                         "while other processes keep every core busy "
                                         "(about 40 s a run on 2 cores)")
    bd.add_argument("--runs", type=int, default=10, help="demo runs (default 10)")
    bd.add_argument("--busy", type=int, default=None,
                    help="busy processes (default: one per CPU)")
    bd.add_argument("--out", required=True, help="folder for busy_demo.json and each run's log")
    bd.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    bd.set_defaults(func=cmd_bench_busy_demo)
    co = bn.add_parser("console", help="the tracking rate with the web console open and "
                                       "closed, and the console's frame rate (headless "
                                       "chromium; about 8 minutes)")
    co.add_argument("--seconds", type=float, default=15.0, help="s per window (default 15)")
    co.add_argument("--fps", type=int, default=10, choices=(1, 2, 5, 10),
                    help="the console's frames-per-second setting (default 10, its highest)")
    co.add_argument("--rounds", type=int, default=6,
                    help="(closed, browser, closed, remote) window rounds (default 6)")
    co.add_argument("--out", required=True, help="folder for console.json and the log")
    co.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    co.set_defaults(func=cmd_bench_console)
    return p


def run(argv: Sequence[str] | None = None) -> int:
    """Parse ``argv`` and run the command; returns the exit status."""
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except ModuleNotFoundError as exc:
        extra = missing_extra(exc)
        if extra is None:
            raise
        _fail(args, extra, 2)
        return 2
    except (ConfigError, ControlError, RenderError, SheetError, UsageError,
            calibrate.SampleFileError, temporal.RecordError, replay.ReplayFileError,
            examples.ExampleError,
            FileNotFoundError) as exc:
        _fail(args, str(exc), 2)
        return 2
    except (OSError, RuntimeError, ValueError) as exc:
        _fail(args, f"{type(exc).__name__}: {exc}", 1)
        return 1


def _fail(args: argparse.Namespace, msg: str, code: int) -> None:
    print(f"oralnav: error: {msg}", file=sys.stderr)
    if getattr(args, "json", False):
        print(json.dumps({"error": msg, "exit": code}))


def main() -> None:
    sys.exit(run())
