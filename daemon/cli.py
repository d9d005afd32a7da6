"""``oralnav``: the command-line tools.

    oralnav sim render SCENE.toml --out DIR [--frames N] [--seed N] [--json]
    oralnav markers print FIELD [--fields FILE] --dpi N --out F.png [--no-label] [--json]
    oralnav config check [FILE] [--json]

Every ``--json`` prints exactly one JSON object on stdout; progress and logs go to stderr.
Exit status: 0 done, 2 bad input (the message names the file and key), 1 anything else.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from dataclasses import replace
from importlib import resources
from pathlib import Path
from typing import Any

import cv2

from oralnav import __version__
from oralnav.config.daemon import load_config
from oralnav.config.errors import ConfigError
from oralnav.config.fields import load_fields
from oralnav.config.loader import atomic_write_bytes, atomic_write_text
from oralnav.config.scene import load_scene
from oralnav.control.errors import ControlError
from oralnav.sim.render import RenderError, SceneRenderer

from .sheets import SheetError, render_sheet, write_png


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
           "api": f"{s.api.host}:{s.api.port}"}
    _emit(args, doc, f"{cfg.path}: valid ({s.cell.backend} cell, cameras "
                     f"{', '.join(doc['cameras'] + doc['endoscope'])}, fields "
                     f"{', '.join(doc['fields'])})")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="oralnav", description="oralnav tools")
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
    return p


def run(argv: Sequence[str] | None = None) -> int:
    """Parse ``argv`` and run the command; returns the exit status."""
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (ConfigError, ControlError, RenderError, SheetError, UsageError,
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
