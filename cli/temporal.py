"""``oralnav calibrate temporal``: the stereo camera's time offset against the arm.

    oralnav calibrate temporal --url URL [--token T] [--amplitude-mm A] [--period-s P]
                               [--duration-s D] [--search-ms S] [--record DIR]
                               [--out FILE --cell ID] [--json]
    oralnav calibrate temporal --samples DIR [--search-ms S] [--out FILE --cell ID] [--json]

With ``--url`` the running daemon moves the arm through the excitation and fits the offset
(``POST /calibration/temporal``; the cell must be READY with the robot marker in view);
this command shows its progress, then writes the calibration file. ``--record DIR`` keeps
the record (``frames.txt``: stamp s and marker position m per row; ``arm.txt``: stamp s and
TCP position m; ``record.json``: the offset the daemon applied while recording, the
excitation) so that ``--samples DIR`` can fit it again offline. docs/calibration.md,
"Temporal calibration".
"""

from __future__ import annotations

import argparse
import io
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from oralnav.config.calibration import Calibration, SampleInfo, samples_digest, save_calibration
from oralnav.config.loader import atomic_write_text
from oralnav.control.calibration.temporal import estimate_time_offset

__all__ = ["RecordError", "add_parser", "cmd_temporal", "read_record", "record_texts",
           "write_record"]

#: Seconds between two looks at the daemon's progress.
POLL_S = 0.5


class RecordError(ValueError):
    """A record folder or the daemon's answer is unusable (exit status 2)."""


def _progress(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def _rows(values: list[list[float]]) -> str:
    buf = io.StringIO()
    np.savetxt(buf, np.asarray(values, dtype=float).reshape(-1, 4), fmt="%.9f")
    return buf.getvalue()


def record_texts(samples: dict[str, Any]) -> tuple[str, str]:
    """The daemon's record (``GET /calibration/temporal?samples=true``) as the text of
    ``frames.txt`` and ``arm.txt`` (a stamp and x y z per row); these bytes, in this
    order, are what the calibration file's digest covers."""
    frames = [[t, *p] for t, p in zip(samples["t_cam"], samples["p_C"], strict=True)]
    arm = [[t, *p] for t, p in zip(samples["t_arm"], samples["p_B"], strict=True)]
    return _rows(frames), _rows(arm)


def write_record(folder: Path, texts: tuple[str, str], meta: dict[str, Any]) -> list[Path]:
    """A record (:func:`record_texts`) and its ``record.json`` (``meta``) as files in
    ``folder``, each written atomically; returns the sample files."""
    folder.mkdir(parents=True, exist_ok=True)
    files = [folder / "frames.txt", folder / "arm.txt"]
    for path, text in zip(files, texts, strict=True):
        atomic_write_text(path, text)
    atomic_write_text(folder / "record.json", json.dumps(meta, indent=2) + "\n")
    return files


def read_record(folder: Path) -> tuple[np.ndarray, np.ndarray, float, bytes]:
    """``(frames (N, 4), arm (M, 4), applied offset s, digest input)`` from a record
    folder; RecordError naming the file and what is wrong."""
    out, raws = [], b""
    for name in ("frames.txt", "arm.txt"):
        path = folder / name
        try:
            raw = path.read_bytes()
            a = np.loadtxt(io.BytesIO(raw), ndmin=2)
        except FileNotFoundError:
            raise RecordError(f"{path}: not found (a folder written by --record)") from None
        except ValueError as exc:
            raise RecordError(f"{path}: not rows of numbers: {exc}") from None
        if a.shape[1:] != (4,):
            raise RecordError(f"{path}: need rows of 4 numbers (stamp s, x y z m), got "
                              f"{a.shape[1]} per row")
        out.append(a)
        raws += raw
    try:
        meta = json.loads((folder / "record.json").read_text())
        applied = float(meta["applied_offset_s"])
    except FileNotFoundError:
        raise RecordError(f"{folder / 'record.json'}: not found") from None
    except (ValueError, KeyError, TypeError) as exc:
        raise RecordError(f"{folder / 'record.json'}: no applied_offset_s ({exc})") from None
    return out[0], out[1], applied, raws


def _api(args: argparse.Namespace) -> Any:
    import httpx

    token = args.token or os.environ.get("ORALNAV_TOKEN")
    if not token:
        raise RecordError("--url needs an operator token: --token T or ORALNAV_TOKEN")
    return httpx.Client(base_url=args.url.rstrip("/"), timeout=10.0,
                        headers={"Authorization": f"Bearer {token}"})


def _answer(r: Any, what: str) -> dict[str, Any]:
    try:
        doc = r.json()
    except ValueError:
        doc = {}
    if r.status_code != 200:
        raise RecordError(f"{what}: the daemon answered {r.status_code}: "
                          f"{doc.get('detail', r.text[:200])}")
    return doc


def _run_on_daemon(args: argparse.Namespace) -> dict[str, Any]:
    """Start the run, show its progress, return the final report with the record."""
    import httpx

    try:
        return _follow(args)
    except httpx.HTTPError as exc:
        raise RecordError(f"cannot reach the daemon at {args.url}: {exc}") from None


def _follow(args: argparse.Namespace) -> dict[str, Any]:
    body = {"amplitude_mm": args.amplitude_mm, "period_s": args.period_s,
            "duration_s": args.duration_s, "search_ms": args.search_ms}
    with _api(args) as api:
        _answer(api.post("/calibration/temporal", json=body), "starting the excitation")
        _progress(f"excitation: {args.amplitude_mm:g} mm, period {args.period_s:g} s, "
                  f"{args.duration_s:g} s; keep the robot marker in view")
        last = -1
        while True:
            doc = _answer(api.get("/calibration/temporal"), "following the run")
            if doc["phase"] not in ("moving", "solving"):
                break
            el = doc.get("elapsed_s")
            shown = int(el) if el is not None else -1
            if shown != last and shown % 4 == 0:
                _progress(f"  {doc['phase']}: {el or 0:.0f}/{args.duration_s:g} s, "
                          f"{doc['frames']} frames, {doc['arm_samples']} arm samples")
                last = shown
            time.sleep(POLL_S)
        return _answer(api.get("/calibration/temporal", params={"samples": "true"}),
                       "reading the record")


def cmd_temporal(args: argparse.Namespace) -> int:
    """Fit (or have the daemon fit) the offset; print it; write it with ``--out``."""
    if args.out and not args.cell:
        raise RecordError("--out needs --cell ID: the cell this calibration belongs to "
                          "(the daemon refuses files of another cell)")
    if bool(args.url) == bool(args.samples):
        raise RecordError("give either --url URL (the daemon runs the excitation) or "
                          "--samples DIR (a record to fit again)")
    if args.url:
        doc = _run_on_daemon(args)
        if doc["phase"] != "done":
            raise RecordError(f"the temporal calibration failed: {doc.get('error')}")
        folder = Path(args.record) if args.record else None
        meta = {"applied_offset_s": doc["applied_offset_s"], "excitation": doc["excitation"],
                "daemon": args.url}
        texts = record_texts(doc["samples"])
        if folder is not None:
            write_record(folder, texts, meta)
            _progress(f"wrote the record to {folder}")
        raws = "".join(texts).encode()  # the files' bytes, in order, as read_record reads
        res = doc["result"]
        figures = {k: res[k] for k in ("offset_ms", "sigma_ms", "rms_mm", "frames",
                                       "rejected", "speed_rms_mm_s", "search_ms")}
        offset, sigma = float(res["offset_s"]), float(res["sigma_s"])
        applied, source = float(doc["applied_offset_s"]), f"daemon at {args.url}"
    else:
        folder = Path(args.samples)
        frames, arm, applied, raws = read_record(folder)
        fit = estimate_time_offset(frames[:, 0], frames[:, 1:], arm[:, 0], arm[:, 1:],
                                   search_s=args.search_ms * 1e-3)
        figures = fit.as_dict()
        offset, sigma = applied + fit.offset_s, fit.sigma_s
        source = f"{folder / 'frames.txt'}, {folder / 'arm.txt'}"
    out = None
    if args.out:
        cal = Calibration(
            kind="temporal", cell=args.cell, method="excitation, least-squares alignment",
            values={"offset_s": offset},
            samples=SampleInfo(int(figures["frames"]), samples_digest([raws]), source),
            residuals={"rms_mm": float(figures["rms_mm"])},
            quality={"sigma_ms": sigma * 1e3, "applied_while_recording_ms": applied * 1e3,
                     "frames": int(figures["frames"]), "rejected": int(figures["rejected"]),
                     "speed_rms_mm_s": float(figures["speed_rms_mm_s"])})
        out = str(save_calibration(cal, args.out))
        _progress(f"wrote temporal calibration to {out}; the daemon applies it when it next "
                  "loads its configuration ([calibration] temporal)")
    doc_out = {"kind": "temporal", "offset_ms": offset * 1e3, "sigma_ms": sigma * 1e3,
               "applied_while_recording_ms": applied * 1e3,
               "fit": figures, "out": out}
    if args.json:
        print(json.dumps(doc_out))
    else:
        print(f"stereo camera timestamps {offset * 1e3:+.2f} ms (+- {sigma * 1e3:.2f} ms) late "
              f"against the arm ({figures['frames']} frames, RMS {figures['rms_mm']:.3f} mm, "
              f"{applied * 1e3:.2f} ms applied while recording)")
    return 0


def add_parser(cal: argparse._SubParsersAction) -> None:
    """Register ``temporal`` under ``oralnav calibrate``."""
    tp = cal.add_parser("temporal", help="the stereo camera's time offset against the arm "
                        "(the daemon moves the arm through a small excitation)")
    tp.add_argument("--url", help="the daemon's API, e.g. http://127.0.0.1:8750")
    tp.add_argument("--token", help="operator token (default: $ORALNAV_TOKEN)")
    tp.add_argument("--samples", help="instead of --url: a folder written by --record")
    tp.add_argument("--record", help="with --url: keep the record in this folder")
    tp.add_argument("--amplitude-mm", type=float, default=5.0,
                    help="peak displacement of the excitation, mm (default 5)")
    tp.add_argument("--period-s", type=float, default=4.0,
                    help="its slowest axis' period, s (default 4)")
    tp.add_argument("--duration-s", type=float, default=24.0,
                    help="its length, s (default 24)")
    tp.add_argument("--search-ms", type=float, default=200.0,
                    help="offsets searched, +- ms (default 200)")
    tp.add_argument("--out", help="calibration file to write (atomically)")
    tp.add_argument("--cell", help="the cell the calibration belongs to (needed by --out)")
    tp.add_argument("--json", action="store_true", help="print one JSON object")
    tp.set_defaults(func=cmd_temporal)
