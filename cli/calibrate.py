"""``oralnav calibrate KIND``: calibrations from recorded samples.

    oralnav calibrate pivot --matrices FILE [--method algebraic|sphere|ransac] [--json]
                            [--out FILE --cell ID --unit mm|m]
    oralnav calibrate hand-eye --robot T_B_tcp.txt --marker T_C_RM.txt [--method M]
    oralnav calibrate endoscope-opener --opener T_C_OM.txt --board-camera T_C_CB.txt
                                       --board-endoscope T_En_CB.txt
    oralnav calibrate effector-zero --marker T_C_RM.txt --flange T_B_J6.txt
                                    --hand-eye FILE (--tip p_C_SI.txt | --pointer T_C_SI.txt
                                    --pivot FILE)
    oralnav calibrate effector-marker --opener T_C_OM.txt --effector-marker T_En_EM.txt
                                      --robot-marker T_C_RM.txt --hand-eye FILE
                                      --endoscope-opener FILE --effector-zero FILE
    (each also [--unit m|mm] [--out FILE --cell ID] [--json])
    oralnav calibrate camera --images DIR --fields F [--board NAME] [--model M] [--rig-out R]
                             [--rig-format toml|opencv|ros|kalibr] [--min-views N] [--reject RULE]
    oralnav calibrate stereo --left DIR --right DIR --fields F [--board NAME] [--rig-out R]
                             [--rig-format toml|opencv|ros|kalibr] [--min-views N] [--reject RULE]
    (both also [--min-views N] [--reject RULE]; the board: any target of the fields file)
    oralnav calibrate capture-views --rig RIG --out DIR [--views N]     (simulated images)
    oralnav calibrate capture --out DIR [--samples N] [--corner-noise PX]   (simulated cell)
    oralnav calibrate chain --samples DIR --out DIR --cell ID
    oralnav calibrate temporal --url URL | --samples DIR   (cli/temporal.py)

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
    load_calibration,
    samples_digest,
    save_calibration,
)
from oralnav.config.loader import atomic_write_bytes, atomic_write_text
from oralnav.control.calibration.chain import (
    AveragedPose,
    calibrate_effector_marker,
    calibrate_effector_zero,
    calibrate_endoscope_opener,
)
from oralnav.control.calibration.handeye import HAND_EYE_METHODS, calibrate_hand_eye
from oralnav.control.calibration.pivot import METHODS as PIVOT_METHODS
from oralnav.control.calibration.pivot import (
    PivotError,
    pivot_calibration,
    validate_tracking_matrices,
)
from oralnav.control.navigation.chains import extraoral_T_B_E0


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


def read_points(path: str | Path, what: str) -> tuple[np.ndarray, bytes]:
    """Points from a text file, N rows of 3 numbers: ``((N, 3) array, the file's bytes)``."""
    path = Path(path)
    try:
        raw = path.read_bytes()
        a = np.loadtxt(path, dtype=float, ndmin=2)
    except FileNotFoundError:
        raise SampleFileError(f"{path}: {what}: file not found") from None
    except ValueError as exc:
        raise SampleFileError(f"{path}: {what}: not a table of numbers ({exc})") from None
    if a.size == 0 or a.shape[1] != 3:
        raise SampleFileError(f"{path}: {what}: expected N rows of 3 numbers (x y z), got "
                              f"shape {a.shape}")
    return a, raw


def _scaled(T: np.ndarray, unit: str) -> np.ndarray:
    """Stacked transforms with their translations converted from ``unit`` to metres."""
    T = T.copy()
    T[:, :3, 3] *= LENGTH_UNITS[unit]
    return T


def _samples(args: argparse.Namespace, named: dict[str, str], unit: str | None = None
             ) -> tuple[dict[str, np.ndarray], SampleInfo]:
    """Read the stacked-matrix files ``named`` (option -> path), all with one count, in
    metres; returns the arrays and the provenance (count, hash over every file, names)."""
    unit = unit or args.unit
    arrays, raws, count = {}, [], None
    for option, path in named.items():
        T, raw = read_matrices(path, option)
        T = validate_tracking_matrices(T, f"{path}: {option}", min_poses=1)
        if count is not None and len(T) != count:
            raise SampleFileError(f"{path}: {option}: {len(T)} samples, but "
                                  f"{next(iter(named.values()))} has {count}: the files must "
                                  "hold the same instants, row for row")
        count = len(T)
        arrays[option] = _scaled(T, unit)
        raws.append(raw)
    return arrays, SampleInfo(int(count or 0), samples_digest(raws),
                              ", ".join(str(p) for p in named.values()))


def _emit_result(args: argparse.Namespace, doc: dict[str, Any], text: str) -> None:
    if args.json:
        print(json.dumps(doc))
    else:
        print(text)


def _averaged(args: argparse.Namespace, kind: str, key: str, res: AveragedPose,
              info: SampleInfo, method: str) -> int:
    """Write and print a chain calibration averaged over samples."""
    cal = Calibration(kind=kind, cell=args.cell or "", method=method, values={key: res.T},
                      samples=info, residuals=res.report())
    path = _write(args, cal)
    if res.n_used < res.n_samples:
        _progress(f"left out {res.n_samples - res.n_used} disagreeing sample(s): "
                  f"{np.flatnonzero(~res.used).tolist()}")
    _emit_result(args, {"kind": kind, key: res.T.tolist(), **res.report(), "out": path},
                 f"{key} from {res.n_used} of {res.n_samples} samples: spread "
                 f"{res.translation_spread_mm:.3f} mm / {res.rotation_spread_deg:.3f} deg "
                 f"(standard error {res.translation_sem_mm:.3f} mm / "
                 f"{res.rotation_sem_deg:.3f} deg)\n{_matrix(res.T)}")
    return 0


def _matrix(T: np.ndarray) -> str:
    return "\n".join("  [" + ", ".join(f"{v: .6f}" for v in row) + "]" for row in T)


def _load(path: str, kind: str, cell: str | None) -> Calibration:
    return load_calibration(path, kind=kind, cell=cell)


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


# -- hand-eye -------------------------------------------------------------------------
def cmd_hand_eye(args: argparse.Namespace) -> int:
    _needs_cell(args)
    a, info = _samples(args, {"--robot": args.robot, "--marker": args.marker})
    T_B_tcp, T_C_RM = a["--robot"], a["--marker"]
    _progress(f"hand-eye calibration from {len(T_B_tcp)} poses (start: {args.method})")
    res = calibrate_hand_eye(T_B_tcp, T_C_RM, method=args.method)
    if len(res.downweighted):
        _progress(f"suspect poses (down-weighted): {list(map(int, res.downweighted))}")
    cal = Calibration(
        kind="hand_eye", cell=args.cell or "", method=f"refined from {res.start_method}",
        values={"T_B_C": res.T_B_C, "T_tcp_RM": res.T_tcp_RM}, samples=info,
        residuals={"rms_mm": res.rms_mm, "rms_deg": res.rms_deg,
                   "per_pose_mm": res.residuals_mm.tolist(),
                   "per_pose_deg": res.residuals_deg.tolist(),
                   "start_rms_mm": res.start_rms_mm, "start_rms_deg": res.start_rms_deg},
        quality={"sigma_T_B_C_mm": res.sigma_T_B_C_mm, "sigma_T_B_C_deg": res.sigma_T_B_C_deg,
                 "downweighted": [float(i) for i in res.downweighted]})
    path = _write(args, cal)
    _emit_result(args, {"kind": "hand_eye", "T_B_C": res.T_B_C.tolist(),
                        "T_tcp_RM": res.T_tcp_RM.tolist(), "rms_mm": res.rms_mm,
                        "rms_deg": res.rms_deg, "sigma_T_B_C_mm": res.sigma_T_B_C_mm,
                        "sigma_T_B_C_deg": res.sigma_T_B_C_deg,
                        "per_pose_mm": res.residuals_mm.tolist(),
                        "per_pose_deg": res.residuals_deg.tolist(),
                        "start_method": res.start_method, "out": path},
                 f"T_B_C (camera in base) from {res.n_poses} poses, refined from "
                 f"{res.start_method}: residual RMS {res.rms_mm:.3f} mm / {res.rms_deg:.3f} deg, "
                 f"1-sigma {res.sigma_T_B_C_mm:.3f} mm / {res.sigma_T_B_C_deg:.4f} deg\n"
                 f"{_matrix(res.T_B_C)}\nper pose (mm): "
                 + " ".join(f"{v:.3f}" for v in res.residuals_mm))
    return 0


# -- endoscope to opener, end-effector zero and marker ----------------------------------
def cmd_endoscope_opener(args: argparse.Namespace) -> int:
    _needs_cell(args)
    a, info = _samples(args, {"--opener": args.opener, "--board-camera": args.board_camera,
                              "--board-endoscope": args.board_endoscope})
    res = calibrate_endoscope_opener(a["--opener"], a["--board-camera"], a["--board-endoscope"])
    return _averaged(args, "endoscope_opener", "T_OM_En", res, info, "eq. 2, SE(3) mean")


def cmd_effector_zero(args: argparse.Namespace) -> int:
    _needs_cell(args)
    a, info = _samples(args, {"--marker": args.marker, "--flange": args.flange})
    he = _load(args.hand_eye, "hand_eye", args.cell)
    if args.tip:
        p, raw = read_points(args.tip, "--tip")
        p = p * LENGTH_UNITS[args.unit]
    else:
        if not (args.pointer and args.pivot):
            raise SampleFileError("give the tip positions (--tip) or the pointer's poses and "
                                  "its pivot calibration (--pointer and --pivot)")
        ptr, raw = read_matrices(args.pointer, "--pointer")
        ptr = _scaled(validate_tracking_matrices(ptr, f"{args.pointer}: --pointer"), args.unit)
        tip = _load(args.pivot, "pivot", args.cell)["tip_offset"]
        p = ptr[:, :3, :3] @ tip + ptr[:, :3, 3]
    info = SampleInfo(info.count, samples_digest([info.sha256.encode(), raw]), info.source)
    res = calibrate_effector_zero(a["--marker"], p, he["T_B_C"], a["--flange"])
    return _averaged(args, "effector_zero", "T_RM_E0", res, info, "eqs. 3-4, SE(3) mean")


def cmd_effector_marker(args: argparse.Namespace) -> int:
    _needs_cell(args)
    a, info = _samples(args, {"--opener": args.opener, "--effector-marker": args.effector_marker,
                              "--robot-marker": args.robot_marker})
    he = _load(args.hand_eye, "hand_eye", args.cell)
    eo = _load(args.endoscope_opener, "endoscope_opener", args.cell)
    ez = _load(args.effector_zero, "effector_zero", args.cell)
    T_RM_E0 = ez["T_RM_E0"]
    T_B_E0 = np.stack([extraoral_T_B_E0(he["T_B_C"], T, T_RM_E0[:3, :3], T_RM_E0[:3, 3])
                       for T in a["--robot-marker"]])
    res = calibrate_effector_marker(he["T_B_C"], a["--opener"], eo["T_OM_En"],
                                    a["--effector-marker"], T_B_E0)
    return _averaged(args, "effector_marker", "T_EM_E", res, info, "eq. 7, SE(3) mean")


# -- camera intrinsics and stereo from images -----------------------------------------
def _board(args: argparse.Namespace):
    """The calibration target ``--board`` of ``--fields`` (any family)."""
    from oralnav.config.fields import load_targets

    fields = load_targets(args.fields)
    if args.board not in fields:
        raise SampleFileError(f"{args.fields}: no field {args.board!r}; it has {sorted(fields)}")
    return fields[args.board]


def _images(folder: str | Path, what: str) -> list[Path]:
    folder = Path(folder)
    if not folder.is_dir():
        raise SampleFileError(f"{folder}: {what}: not a folder of images")
    files = sorted(p for p in folder.iterdir()
                   if p.suffix.lower() in (".png", ".tif", ".tiff", ".bmp", ".jpg", ".jpeg"))
    if not files:
        raise SampleFileError(f"{folder}: {what}: no images (png, tif, bmp, jpg)")
    return files


def _detect(files: list[Path], board, what: str) -> tuple[list, tuple[int, int], bytes]:
    """Detect ``board`` in every image: (views, (width, height), the images' digest)."""
    import cv2

    from oralnav.control.calibration.targets import detect_target

    views, size, raws = [], None, []
    for k, f in enumerate(files):
        raw = f.read_bytes()
        img = cv2.imdecode(np.frombuffer(raw, np.uint8), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise SampleFileError(f"{f}: {what}: not a readable image")
        if size is None:
            size = (img.shape[1], img.shape[0])
        elif size != (img.shape[1], img.shape[0]):
            raise SampleFileError(f"{f}: {what}: {img.shape[1]}x{img.shape[0]} px, but "
                                  f"{files[0].name} is {size[0]}x{size[1]}: one camera, one size")
        views.append(detect_target(img, board))
        raws.append(raw)
        if (k + 1) % 10 == 0 or k + 1 == len(files):
            _progress(f"{what}: detected the board in {sum(v is not None for v in views)} of "
                      f"{k + 1} images")
    assert size is not None
    return views, size, samples_digest(raws).encode()


def _fit_options(args: argparse.Namespace) -> dict[str, Any]:
    """``--min-views`` and ``--reject`` as keyword arguments of the calibrations (a bad
    rule is a CalibrationError: exit 2 with the rule's syntax)."""
    from oralnav.control.calibration.cameras import RejectRule

    out: dict[str, Any] = {"reject": RejectRule.parse(args.reject)}
    if args.min_views is not None:
        out["min_views"] = args.min_views
    return out


#: --rig-out's format from the file's suffix where the suffix says it (YAML is ambiguous:
#: OpenCV, ROS and Kalibr all write it)
RIG_SUFFIX_FORMATS = {".toml": "toml", ".xml": "opencv", ".json": "opencv"}


def _rig_out_format(args: argparse.Namespace) -> str | None:
    """The format ``--rig-out`` is written in: ``--rig-format``, else the suffix's
    (:data:`RIG_SUFFIX_FORMATS`). Checked before any calibration runs, so a name that does
    not say its format costs nothing (a SampleFileError: exit 2)."""
    if not args.rig_out:
        if args.rig_format:
            raise SampleFileError("--rig-format needs --rig-out FILE")
        return None
    if args.rig_format:
        return args.rig_format
    fmt = RIG_SUFFIX_FORMATS.get(Path(args.rig_out).suffix.lower())
    if fmt is None:
        raise SampleFileError(f"--rig-out {args.rig_out}: say which format with --rig-format "
                              "toml|opencv|ros|kalibr (.toml is ours, .xml and .json are "
                              "OpenCV's; a .yaml may be OpenCV's, ROS's or Kalibr's)")
    return fmt


def _with_files(rows: list[dict], files: list[Path]) -> list[dict]:
    """The per-view table's rows with each view's image name."""
    return [{"file": f.name, **r} for r, f in zip(rows, files, strict=True)]


def _table(rows: list[dict], columns: dict[str, str]) -> str:
    """The per-view table as text: index, image, the error columns (px), status and why."""
    width = max([5] + [len(r["file"]) for r in rows])
    head = f"  view  {'image':<{width}}" + "".join(f"  {c:>8}" for c in columns.values())
    lines = [head + "  status"]
    for r in rows:
        errs = "".join(f"  {'-' if r[k] is None else format(r[k], '.3f'):>8}" for k in columns)
        why = f": {r['why']}" if r["why"] else ""
        lines.append(f"  {r['view']:>4}  {r['file']:<{width}}{errs}  {r['status']}{why}")
    return "\n".join(lines)


def _camera_text(name: str, res, rows: list[dict]) -> str:
    limit = ("" if res.reject == "none" else f", limit {res.limit_px:.3f} px")
    return (f"{name}: {res.model} model from {len(res.used)} of {len(rows)} views, RMS "
            f"{res.rms:.3f} px; fx {res.K[0, 0]:.2f} fy {res.K[1, 1]:.2f} cx {res.K[0, 2]:.2f} "
            f"cy {res.K[1, 2]:.2f}\noutlier rule {res.reject}{limit}\n"
            + _table(rows, {"rms_px": "RMS px"}))


def cmd_camera(args: argparse.Namespace) -> int:
    from oralnav.control.calibration.cameras import calibrate_camera
    from oralnav.control.vision.camera import Rig

    _needs_cell(args)
    args.rig_out_format = _rig_out_format(args)
    opts = _fit_options(args)
    board = _board(args)
    files = _images(args.images, "--images")
    views, size, digest = _detect(files, board, "--images")
    res = calibrate_camera(views, board, size, model=args.model, **opts)
    if res.model == "fisheye":
        raise SampleFileError("the rig format holds OpenCV's standard and rational models; a "
                              "fisheye fit cannot be written (use --model rational)")
    rig = Rig(args.name, {args.name: res.camera_model(args.name, np.eye(4))})
    doc = res.to_dict()
    doc["views"] = _with_files(doc["views"], files)
    return _rig_result(args, "camera", rig, doc, len(files), digest,
                       _camera_text(args.name, res, doc["views"]) + "\n"
                       + res.coverage.describe())


def cmd_stereo(args: argparse.Namespace) -> int:
    from oralnav.control.calibration.cameras import calibrate_camera, calibrate_stereo

    _needs_cell(args)
    args.rig_out_format = _rig_out_format(args)
    opts = _fit_options(args)
    board = _board(args)
    names = args.names.split(",")
    if len(names) != 2 or not all(names):
        raise SampleFileError(f"--names: expected two camera names, e.g. left,right; got "
                              f"{args.names!r}")
    lf, rf = _images(args.left, "--left"), _images(args.right, "--right")
    if [p.name for p in lf] != [p.name for p in rf]:
        raise SampleFileError(f"{args.left} and {args.right}: the image names differ; a "
                              "stereo pair must share its name in both folders")
    lv, lsize, ld = _detect(lf, board, "--left")
    rv, rsize, rd = _detect(rf, board, "--right")
    cams = [calibrate_camera(v, board, sz, model=args.model, **opts)
            for v, sz in ((lv, lsize), (rv, rsize))]
    left, right = (c.camera_model(n, np.eye(4)) for c, n in zip(cams, names, strict=True))
    res = calibrate_stereo(lv, rv, board, left, right, refine_intrinsics=args.refine, **opts)
    doc = res.to_dict()
    doc["views"] = _with_files(doc["views"], lf)
    doc["intrinsics"] = {}
    texts = []
    for n, c in zip(names, cams, strict=True):
        d = c.to_dict()
        d["views"] = _with_files(d["views"], lf)
        doc["intrinsics"][n] = d
        texts.append(_camera_text(n, c, d["views"]))
    limit = "" if res.reject == "none" else f", limit {res.limit_px:.3f} px over both images"
    return _rig_result(args, "stereo", res.rig(), doc, len(lf), samples_digest([ld, rd]).encode(),
                       "\n".join(texts) + "\n"
                       f"{names[1]} in {names[0]}: baseline {res.baseline * 1e3:.3f} mm, RMS "
                       f"{res.rms:.3f} px, epipolar RMS {res.epipolar_rms_px:.3f} px, from "
                       f"{len(res.used)} of {len(lf)} pairs\n{_matrix(res.T_left_right)}\n"
                       f"outlier rule {res.reject}{limit}\n"
                       + _table(doc["views"], {"rms_left_px": names[0] + " px",
                                               "rms_right_px": names[1] + " px"}))


def _fit_quality(args: argparse.Namespace, kind: str, doc: dict) -> dict[str, Any]:
    """What the calibration file keeps of how the fit chose its views: the views used,
    the outlier rule with its limit (px; absent with ``none``) and the fewest views it
    accepted, so that a file can be fitted again the same way."""
    from oralnav.control.calibration.cameras import MIN_STEREO_VIEWS, MIN_VIEWS

    quality: dict[str, Any] = {
        "used_views": [float(i) for i in doc.get("used", [])],
        "outlier_rule": doc["reject"],
        "min_views": float(args.min_views if args.min_views is not None
                           else MIN_STEREO_VIEWS if kind == "stereo" else MIN_VIEWS)}
    if doc.get("limit_px") is not None:
        quality["outlier_limit_px"] = float(doc["limit_px"])
    return quality


def _rig_result(args: argparse.Namespace, kind: str, rig, doc: dict, n: int, digest: bytes,
                text: str) -> int:
    from oralnav.config.rig import save_rig_as

    # a view without the board has no error: written as -1 (TOML has no NaN)
    per_view = np.array([[-1.0 if e is None else e for e in np.atleast_1d(row)]
                         for row in doc["per_view_rms_px"]], dtype=float)
    cal = Calibration(kind=kind, cell=args.cell or "", method=f"opencv {doc.get('model', kind)}",
                      values={"rig": rig},
                      samples=SampleInfo(n, digest.decode(), str(getattr(args, "images", "")
                                                                  or f"{args.left}, {args.right}")),
                      residuals={"rms_px": float(doc["rms_px"]),
                                 "per_view_rms_px": per_view.ravel().tolist()},
                      quality=_fit_quality(args, kind, doc))
    if args.rig_out:  # first: a format that cannot hold the rig refuses before any write
        save_rig_as(rig, args.rig_out, args.rig_out_format)
        _progress(f"wrote rig file {args.rig_out} ({args.rig_out_format})")
    path = _write(args, cal)
    doc.update({"kind": kind, "out": path, "rig_out": args.rig_out,
                "rig_format": args.rig_out_format})
    _emit_result(args, doc, text)
    return 0


def cmd_capture_views(args: argparse.Namespace) -> int:
    import cv2

    from oralnav.config.loader import dump_toml
    from oralnav.config.rig import load_rig
    from oralnav.sim.world.calibration_views import render_calibration_views

    rig = load_rig(args.rig)
    names = args.cameras.split(",") if args.cameras else list(rig.names)
    out = Path(args.out)
    for n in names:
        (out / n).mkdir(parents=True, exist_ok=True)

    def save(k: int, images) -> None:
        for cam, img in images.items():
            ok, buf = cv2.imencode(".png", img)
            if not ok:
                raise RuntimeError(f"PNG encoding failed for camera {cam!r}")
            atomic_write_bytes(out / cam / f"view_{k:03d}.png", buf.tobytes())

    views = render_calibration_views(
        rig, n=args.views, cameras=names, seed=args.seed, on_frame=save,
        progress=lambda d, t: _progress(f"view {d}/{t} rendered") if d % 5 == 0 or d == t
        else None)
    b = views.board
    atomic_write_text(out / "board.toml", "# the calibration board shown in the views\n"
                      + dump_toml({"fields": {"board": {
                          "family": "charuco", "dictionary": b.dictionary,
                          "squares": list(b.squares), "square": b.square, "marker": b.marker,
                          "first_id": b.first_id, "surface": {"kind": "plane"}}}}))
    doc = {"out": str(out), "cameras": names, "views": len(views),
           "fields": str(out / "board.toml"), "board": "board"}
    _emit_result(args, doc, f"rendered {len(views)} views of the board through "
                 f"{', '.join(names)} into {out} (board in {out / 'board.toml'})")
    return 0


# -- simulated capture and the whole chain -------------------------------------------
#: What ``capture`` writes: folder -> files (stacked 4x4 matrices, metres; the pivot's
#: pointer poses in millimetres, the pointer format of ``calibrate pivot``).
CAPTURE_FILES = {
    "hand_eye": ("T_B_tcp.txt", "T_C_RM.txt"),
    "endoscope_opener": ("T_C_OM.txt", "T_C_CB.txt", "T_En_CB.txt"),
    "pivot": ("T_C_SI_mm.txt",),
    "effector_zero": ("T_C_RM.txt", "T_C_SI.txt", "T_B_J6.txt"),
    "effector_marker": ("T_C_OM.txt", "T_En_EM.txt", "T_C_RM.txt"),
}


def _save_stack(path: Path, T: np.ndarray) -> None:
    atomic_write_text(path, "".join(
        " ".join(f"{v:.12g}" for v in row) + "\n" for row in np.asarray(T).reshape(-1, 4)))


def cmd_capture(args: argparse.Namespace) -> int:
    from oralnav.config.daemon import load_config
    from oralnav.sim.world.calibration_chain import ChainSimulator

    cfg = load_config(args.config)
    if cfg.cell is None:
        raise SampleFileError(f"{cfg.path}: [cell] sim_cell: capture needs the simulated cell")
    if args.samples < 3:
        raise SampleFileError("--samples must be at least 3")
    out = Path(args.out)
    sim = ChainSimulator(cfg.cell, args.corner_noise, np.random.default_rng(args.seed))
    n = args.samples
    steps = {
        "hand_eye": lambda: sim.hand_eye_samples(n),
        "endoscope_opener": lambda: sim.endoscope_opener_samples(n),
        "pivot": lambda: (sim.pivot_samples(10 * n)[0] * _mm(),),
        "effector_zero": lambda: sim.effector_zero_samples(n),
        "effector_marker": lambda: sim.effector_marker_samples(n),
    }
    written: dict[str, list[str]] = {}
    for k, (kind, make) in enumerate(steps.items(), 1):
        _progress(f"[{k}/{len(steps)}] {kind}: the simulated arm moves through its poses")
        arrays = make()
        folder = out / kind
        folder.mkdir(parents=True, exist_ok=True)
        for name, T in zip(CAPTURE_FILES[kind], arrays, strict=True):
            _save_stack(folder / name, T)
        written[kind] = [str(folder / f) for f in CAPTURE_FILES[kind]]
    doc = {"out": str(out), "cell": cfg.cell.source, "samples": n,
           "corner_noise_px": args.corner_noise, "seed": args.seed, "files": written}
    atomic_write_text(out / "capture.json", json.dumps(doc, indent=1) + "\n")
    _emit_result(args, doc, f"captured {n} samples per calibration ({10 * n} pivot poses) at "
                 f"{args.corner_noise} px corner noise into {out}")
    return 0


def _mm() -> np.ndarray:
    """Scale for stacked 4x4 matrices: translations to millimetres, rotations untouched."""
    s = np.ones((4, 4))
    s[:3, 3] = 1e3
    return s


def chain_commands(samples: Path, out: Path, cell: str) -> list[list[str]]:
    """The ``oralnav calibrate`` command lines that calibrate the whole chain, in order,
    from a ``capture`` folder into ``out`` (one calibration file per kind)."""
    s = {k: [str(samples / k / f) for f in files] for k, files in CAPTURE_FILES.items()}
    o = {k: str(out / f"{k}.toml") for k in CAPTURE_FILES}
    tail = ["--cell", cell]
    return [
        ["hand-eye", "--robot", s["hand_eye"][0], "--marker", s["hand_eye"][1],
         "--out", o["hand_eye"], *tail],
        ["endoscope-opener", "--opener", s["endoscope_opener"][0], "--board-camera",
         s["endoscope_opener"][1], "--board-endoscope", s["endoscope_opener"][2],
         "--out", o["endoscope_opener"], *tail],
        ["pivot", "--matrices", s["pivot"][0], "--unit", "mm", "--out", o["pivot"], *tail],
        ["effector-zero", "--marker", s["effector_zero"][0], "--pointer", s["effector_zero"][1],
         "--pivot", o["pivot"], "--flange", s["effector_zero"][2], "--hand-eye", o["hand_eye"],
         "--out", o["effector_zero"], *tail],
        ["effector-marker", "--opener", s["effector_marker"][0], "--effector-marker",
         s["effector_marker"][1], "--robot-marker", s["effector_marker"][2],
         "--hand-eye", o["hand_eye"], "--endoscope-opener", o["endoscope_opener"],
         "--effector-zero", o["effector_zero"], "--out", o["effector_marker"], *tail],
    ]


def _check_capture(samples: Path) -> None:
    """``samples`` must be a folder ``capture`` wrote: the message names the folder, as
    the user gave it to --samples, and what is missing, not the steps' own options."""
    if not samples.is_dir():
        what = "not a folder" if samples.exists() else "no such folder"
        raise SampleFileError(f"{samples}: --samples: {what} (give the --out folder of "
                              "oralnav calibrate capture)")
    missing = [f"{k}/{f}" for k, files in CAPTURE_FILES.items() for f in files
               if not (samples / k / f).is_file()]
    if missing:
        raise SampleFileError(f"{samples}: --samples: not a complete capture folder; missing "
                              f"{', '.join(missing)} (oralnav calibrate capture writes them)")


def cmd_chain(args: argparse.Namespace) -> int:
    _check_capture(Path(args.samples))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    parser = argparse.ArgumentParser(prog="oralnav calibrate")
    add_parser(parser.add_subparsers(dest="group"), nested=True)
    files = {}
    for k, argv in enumerate(chain_commands(Path(args.samples), out, args.cell), 1):
        _progress(f"[{k}/5] oralnav calibrate {' '.join(argv)}")
        step = parser.parse_args(argv)
        step.json = False
        # each step prints its own summary; --json keeps stdout to the one final object
        if args.json:
            import contextlib
            import io
            with contextlib.redirect_stdout(io.StringIO()) as buf:
                step.func(step)
            _progress(buf.getvalue().rstrip())
        else:
            step.func(step)
        files[argv[0]] = step.out
    _emit_result(args, {"out": str(out), "cell": args.cell, "files": files},
                 f"wrote {len(files)} calibration files into {out}")
    return 0


def add_parser(sub: argparse._SubParsersAction, nested: bool = False) -> None:
    """Register ``oralnav calibrate ...`` on the top-level subparsers."""
    cal = sub if nested else sub.add_parser(
        "calibrate", help="calibrations from recorded samples (docs/calibration.md)"
    ).add_subparsers(dest="cmd", required=True)

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

    def unit(p: argparse.ArgumentParser) -> None:
        p.add_argument("--unit", default="m", choices=sorted(LENGTH_UNITS),
                       help="length unit of the sample files (default m)")

    he = cal.add_parser("hand-eye", help="the stereo camera in the robot base (T_B_C) and the "
                        "robot marker on the TCP, from robot motions")
    he.add_argument("--robot", required=True, help="stacked 4x4 TCP poses T_B_tcp from the arm")
    he.add_argument("--marker", required=True,
                    help="stacked 4x4 robot-marker poses T_C_RM seen at those TCP poses")
    he.add_argument("--method", default="auto", choices=["auto", *HAND_EYE_METHODS],
                    help="closed-form start before the joint refinement (auto: the best)")
    unit(he)
    common(he)
    he.set_defaults(func=cmd_hand_eye)

    eo = cal.add_parser("endoscope-opener", help="the endoscope on the opener (T_OM_En, "
                        "eqs. 1-2) from a board both cameras see")
    eo.add_argument("--opener", required=True, help="stacked T_C_OM (stereo camera)")
    eo.add_argument("--board-camera", required=True, help="stacked T_C_CB (stereo camera)")
    eo.add_argument("--board-endoscope", required=True, help="stacked T_En_CB (endoscope)")
    unit(eo)
    common(eo)
    eo.set_defaults(func=cmd_endoscope_opener)

    ez = cal.add_parser("effector-zero", help="the end-effector zero frame on the robot "
                        "marker (T_RM_E0, eqs. 3-4) from pointer touches")
    ez.add_argument("--marker", required=True, help="stacked T_C_RM at each touch")
    ez.add_argument("--flange", required=True, help="stacked T_B_J6 (arm flange) at each touch")
    ez.add_argument("--hand-eye", required=True, help="hand_eye calibration file")
    ez.add_argument("--tip", help="the pointer tip at each touch, N rows of x y z (camera)")
    ez.add_argument("--pointer", help="instead of --tip: stacked pointer poses T_C_SI ...")
    ez.add_argument("--pivot", help="... and the pointer's pivot calibration file")
    unit(ez)
    common(ez)
    ez.set_defaults(func=cmd_effector_zero)

    em = cal.add_parser("effector-marker", help="the end-effector in its marker's frame "
                        "(T_EM_E, eq. 7), wrist at zero inside the mouth")
    em.add_argument("--opener", required=True, help="stacked T_C_OM")
    em.add_argument("--effector-marker", required=True, help="stacked T_En_EM (endoscope)")
    em.add_argument("--robot-marker", required=True, help="stacked T_C_RM (for eq. 5)")
    em.add_argument("--hand-eye", required=True, help="hand_eye calibration file")
    em.add_argument("--endoscope-opener", required=True,
                    help="endoscope_opener calibration file")
    em.add_argument("--effector-zero", required=True, help="effector_zero calibration file")
    unit(em)
    common(em)
    em.set_defaults(func=cmd_effector_marker)
    def board(p: argparse.ArgumentParser) -> None:
        p.add_argument("--fields", required=True, help="marker-field TOML describing the board")
        p.add_argument("--board", default="board", help="the board's name in --fields")
        p.add_argument("--model", default="standard", choices=["radtan", "standard", "rational"],
                       help="distortion model: standard (5 coefficients), radtan (4, k3 held "
                            "at 0: what Kalibr's camchain holds) or rational (8, for strong "
                            "distortion such as the endoscope's)")
        p.add_argument("--rig-out", help="also write the result as a rig file (a folder for a "
                                         "ROS stereo pair)")
        p.add_argument("--rig-format", choices=["toml", "opencv", "ros", "kalibr"],
                       help="--rig-out's format: ours (toml), OpenCV FileStorage, ROS "
                            "camera_info or Kalibr camchain (default: from the suffix, "
                            ".toml ours, .xml/.json OpenCV's)")
        p.add_argument("--min-views", type=int, default=None,
                       help="fewest usable views a fit accepts, also the floor of outlier "
                            "rejection (default 6 per camera, 5 stereo pairs)")
        p.add_argument("--reject", default="default", metavar="RULE",
                       help="outlier views: none, or terms NAME:VALUE joined by commas, a "
                            "view dropped above the largest: mad:K (median + K robust "
                            "sigmas), median:F (F x median), floor:P (median + P px), px:P "
                            "(P px); default mad:4,median:2,floor:0.25 (docs/calibration.md)")
        common(p)

    cm = cal.add_parser("camera", help="one camera's intrinsics from images of a flat target "
                        "(ChArUco, chessboard, circle grid, ArUco grid)")
    cm.add_argument("--images", required=True, help="folder of the camera's board images")
    cm.add_argument("--name", default="camera", help="the camera's name in the rig")
    board(cm)
    cm.set_defaults(func=cmd_camera)

    st = cal.add_parser("stereo", help="both cameras' intrinsics and the right camera in the "
                        "left from synchronised images of a flat target")
    st.add_argument("--left", required=True, help="folder of the left camera's images")
    st.add_argument("--right", required=True, help="folder of the right camera's images "
                    "(same file names: a pair per name)")
    st.add_argument("--names", default="left,right", help="the cameras' names in the rig")
    st.add_argument("--refine", action="store_true",
                    help="refine the intrinsics in the stereo fit too")
    board(st)
    st.set_defaults(func=cmd_stereo)
    if nested:
        return

    cv = cal.add_parser("capture-views", help="render ChArUco board views through a rig's "
                        "simulated cameras (PNG per camera and view, and the board's fields file)")
    cv.add_argument("--rig", required=True, help="rig TOML (its cameras are the truth)")
    cv.add_argument("--cameras", help="comma-separated cameras (default: all)")
    cv.add_argument("--out", required=True, help="folder: one subfolder of PNGs per camera")
    cv.add_argument("--views", type=int, default=20)
    cv.add_argument("--seed", type=int, default=0)
    cv.add_argument("--json", action="store_true", help="print one JSON object")
    cv.set_defaults(func=cmd_capture_views)

    cp = cal.add_parser("capture", help="record every chain calibration's samples on the "
                        "simulated cell (the arm moves itself through the poses)")
    cp.add_argument("--config", default=None, help="daemon configuration with [cell] sim_cell "
                    "(default: the shipped sim.toml)")
    cp.add_argument("--out", required=True, help="folder for the sample files")
    cp.add_argument("--samples", type=int, default=15, help="samples per calibration "
                    "(the pivot records 10x as many poses; default 15)")
    cp.add_argument("--corner-noise", type=float, default=0.15,
                    help="marker-corner noise, px (default 0.15, the tracker's residual)")
    cp.add_argument("--seed", type=int, default=0)
    cp.add_argument("--json", action="store_true", help="print one JSON object")
    cp.set_defaults(func=cmd_capture)

    ch = cal.add_parser("chain", help="run the five chain calibrations in order on a capture "
                        "folder, writing one file per kind")
    ch.add_argument("--samples", required=True, help="a folder written by capture")
    ch.add_argument("--out", required=True, help="folder for the calibration files")
    ch.add_argument("--cell", required=True, help="the cell the calibrations belong to")
    ch.add_argument("--json", action="store_true", help="print one JSON object")
    ch.set_defaults(func=cmd_chain)

    from oralnav.cli import temporal  # its own module: it talks to the daemon
    temporal.add_parser(cal)
