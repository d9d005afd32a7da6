"""``oralnav calibrate KIND``: calibrations from recorded samples.

    oralnav calibrate pivot --matrices FILE [--method algebraic|sphere|ransac] [--json]
                            [--out FILE --cell ID --unit mm|m]

Sample files are plain text, as numpy writes them (``numpy.savetxt``): a stack of 4x4
matrices is 4N rows of 4 numbers (the scikit-surgery pivot format), a list of points N rows
of 3. Every command prints its result (``--json``: one JSON object) and, with ``--out``,
writes a calibration file (docs/formats.md, "Calibration files") atomically: a refused
calibration writes nothing and leaves an existing file as it was.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from oralnav.config.calibration import (
    LENGTH_UNITS,
    Calibration,
    SampleInfo,
    samples_digest,
    save_calibration,
)
from oralnav.control.pivot import METHODS as PIVOT_METHODS
from oralnav.control.pivot import PivotError, pivot_calibration, validate_tracking_matrices


class SampleFileError(ValueError):
    """A sample file is unreadable or of the wrong shape (exit status 2)."""


def _progress(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def read_matrices(path: str | Path, what: str) -> tuple[np.ndarray, bytes]:
    """Stacked 4x4 matrices from a text file: ``((N, 4, 4) array, the file's bytes)``."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise SampleFileError(f"{path}: {what}: file not found") from None
    except OSError as exc:
        raise SampleFileError(f"{path}: {what}: cannot read: {exc.strerror or exc}") from None
    try:
        a = np.loadtxt(path, dtype=float, ndmin=2)
    except ValueError as exc:
        raise SampleFileError(f"{path}: {what}: not a table of numbers ({exc})") from None
    if a.size == 0:
        raise SampleFileError(f"{path}: {what}: the file holds no matrices")
    if a.shape[1] != 4 or a.shape[0] % 4:
        raise SampleFileError(f"{path}: {what}: expected stacked 4x4 matrices (4N rows of 4 "
                              f"numbers), got {a.shape[0]} rows of {a.shape[1]}")
    return a.reshape(-1, 4, 4), raw


def _write(args: argparse.Namespace, cal: Calibration) -> str | None:
    if not args.out:
        return None
    path = save_calibration(cal, args.out)
    _progress(f"wrote {cal.kind} calibration to {path}")
    return str(path)


def _needs_cell(args: argparse.Namespace) -> None:
    if args.out and not args.cell:
        raise SampleFileError("--out needs --cell ID: the cell this calibration belongs to "
                              "(the daemon refuses files of another cell)")


# -- pivot ------------------------------------------------------------------------------
def cmd_pivot(args: argparse.Namespace) -> int:
    _needs_cell(args)
    T, raw = read_matrices(args.matrices, "tracking matrices")
    T = validate_tracking_matrices(T, f"{args.matrices}: tracking matrices", min_poses=1)
    _progress(f"pivot calibration ({args.method}) of {len(T)} poses from {args.matrices}")
    try:
        res = pivot_calibration(T, args.method, ransac_iterations=args.ransac_iterations,
                                ransac_threshold=args.ransac_threshold, seed=args.seed)
    except PivotError as exc:
        raise PivotError(f"{args.matrices}: {exc}") from None
    if args.method == "ransac":
        _progress(f"ransac kept {res.n_inliers} of {res.n_poses} poses")
    _progress(f"rotation spread {res.rotation_spread_deg:.1f} deg, condition "
              f"{res.condition:.1f}")
    scale = LENGTH_UNITS[args.unit]
    cal = Calibration(
        kind="pivot", cell=args.cell or "", method=args.method,
        values={"tip_offset": res.tip_offset * scale, "pivot_point": res.pivot_point * scale},
        samples=SampleInfo(len(T), samples_digest([raw]), str(args.matrices)),
        residuals={"rms_mm": res.rms * scale * 1e3,
                   "rms_per_component_mm": res.rms_per_component * scale * 1e3,
                   "per_pose_mm": (res.residuals * scale * 1e3).tolist()},
        quality={"inliers": res.n_inliers, "condition": res.condition,
                 "rotation_spread_deg": res.rotation_spread_deg})
    _write(args, cal)
    doc: dict[str, Any] = {"tip_offset": res.tip_offset.tolist(),
                           "pivot_point": res.pivot_point.tolist(), "rms": res.rms,
                           "rms_per_component": res.rms_per_component}
    if args.json:
        print(json.dumps(doc))
    else:
        f = "[{:.3f}, {:.3f}, {:.3f}]".format
        print(f"tip offset {f(*res.tip_offset)}  pivot point {f(*res.pivot_point)}  "
              f"rms {res.rms:.3f} (3D), {res.rms_per_component:.3f} per component "
              f"({args.unit}); {res.n_inliers} of {res.n_poses} poses used")
    return 0


def add_parser(sub: argparse._SubParsersAction) -> None:
    """Register ``oralnav calibrate ...`` on the top-level subparsers."""
    cal = sub.add_parser("calibrate", help="calibrations from recorded samples "
                         "(docs/calibration.md)").add_subparsers(dest="cmd", required=True)

    def common(p: argparse.ArgumentParser) -> None:
        p.add_argument("--out", help="calibration file to write (atomically)")
        p.add_argument("--cell", help="the cell the calibration belongs to (needed by --out)")
        p.add_argument("--json", action="store_true", help="print one JSON object")

    pv = cal.add_parser("pivot", help="tip of a tracked pointer pivoting about a fixed point")
    pv.add_argument("--matrices", required=True,
                    help="text file of stacked 4x4 tool poses (4N rows of 4 numbers)")
    pv.add_argument("--method", default="algebraic", choices=list(PIVOT_METHODS))
    pv.add_argument("--unit", default="mm", choices=sorted(LENGTH_UNITS),
                    help="length unit of the matrices (for --out; default mm)")
    pv.add_argument("--ransac-iterations", type=int, default=10)
    pv.add_argument("--ransac-threshold", type=float, default=4.0,
                    help="inlier distance, in the matrices' unit (default 4)")
    pv.add_argument("--seed", type=int, default=0, help="seed of RANSAC's subsets")
    common(pv)
    pv.set_defaults(func=cmd_pivot)
