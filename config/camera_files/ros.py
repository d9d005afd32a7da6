"""ROS ``camera_info`` YAML: one file per camera; a stereo pair is two files (or their
folder) whose rectification matrices and right projection matrix give the extrinsics."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from oralnav.control.geometry import invert
from oralnav.control.vision.camera import CameraModel, Rig

from ..errors import ConfigError
from ..loader import atomic_write_text
from .checks import (
    _FISHEYE,
    Names,
    Size,
    _camera,
    _check_size,
    _distortion,
    _finite,
    _intrinsics,
    _keys_found,
    _names,
    _numbers,
    _pixels,
    _read_text,
    _rig,
    _rotation,
    _yaml_doc,
)
from .detect import ROS_PAIR, _yaml_kind
from .writing import _fit_distortion, _flow, _ordered

_ROS_KEYS = ("image_width", "image_height", "camera_name", "camera_matrix", "distortion_model",
             "distortion_coefficients", "rectification_matrix", "projection_matrix")
# ROS's distortion models the rig holds, with the lengths each may have.
_ROS_MODELS = {"plumb_bob": (4, 5), "rational_polynomial": (8,)}


def _ros_matrix(path: Path, doc: Mapping, key: str, rows: int, cols: int | None) -> np.ndarray:
    """A ``{rows, cols, data}`` matrix of the expected shape (``cols`` None: any)."""
    m = doc[key]
    if not isinstance(m, dict) or set(m) != {"rows", "cols", "data"}:
        raise ConfigError(path, key, "must be a mapping of rows, cols and data, got "
                                     f"{m!r}")
    r, c = m["rows"], m["cols"]
    for k, v in (("rows", r), ("cols", c)):
        if isinstance(v, bool) or not isinstance(v, int):
            raise ConfigError(path, f"{key}.{k}", f"must be a whole number, got {v!r}")
    if r != rows or (cols is not None and c != cols):
        raise ConfigError(path, key, f"must be {rows}x{cols if cols is not None else 'N'}, "
                                     f"got {r}x{c}")
    data = _numbers(path, f"{key}.data", m["data"])
    if data.size != r * c:
        raise ConfigError(path, f"{key}.data", f"must have rows x cols = {r * c} numbers, "
                                               f"got {data.size}")
    return data.reshape(r, c)


def _ros_camera(path: Path, doc: Any) -> tuple[str | None, tuple[int, int], np.ndarray,
                                                np.ndarray, np.ndarray | None,
                                                np.ndarray | None]:
    """(camera_name, size, K, dist, rectification or None, projection or None)."""
    if _yaml_kind(doc) != "ros":
        raise ConfigError(path, "", "not a ROS camera_info YAML (image_width, image_height, "
                                    f"camera_matrix, ...){_keys_found(doc)}")
    unknown = [k for k in doc if k not in _ROS_KEYS]
    if unknown:
        raise ConfigError(path, str(unknown[0]), "unknown key: a ROS camera_info YAML holds "
                                                 f"{', '.join(_ROS_KEYS)}")
    for k in ("image_width", "image_height", "camera_matrix", "distortion_coefficients"):
        if k not in doc:
            raise ConfigError(path, k, "missing")
    size = (_pixels(path, "image_width", doc["image_width"]),
            _pixels(path, "image_height", doc["image_height"]))
    name = doc.get("camera_name")
    if name is not None and (not isinstance(name, str) or not name):
        raise ConfigError(path, "camera_name", f"must be a non-empty string, got {name!r}")
    K = _intrinsics(path, "camera_matrix", _ros_matrix(path, doc, "camera_matrix", 3, 3))
    # camera_calibration_parsers reads a file without distortion_model as plumb_bob.
    model = doc.get("distortion_model", "plumb_bob")
    if model in _FISHEYE:
        raise ConfigError(path, "distortion_model", f"{model!r} is a fisheye model, which "
                          "the rig cannot hold (plumb_bob or rational_polynomial only)")
    if model not in _ROS_MODELS:
        raise ConfigError(path, "distortion_model", f"{model!r} is not a model the rig holds: "
                          f"{' or '.join(_ROS_MODELS)}")
    d = _ros_matrix(path, doc, "distortion_coefficients", 1, None)
    d = _distortion(path, "distortion_coefficients", d, _ROS_MODELS[model], model)
    R = P = None
    if "rectification_matrix" in doc:
        # Older camera_calibration prints the rectification with 6 decimals (about float32
        # precision), which can miss the 1e-6 check: re-orthonormalised within 1e-5.
        R = _rotation(path, "rectification_matrix",
                      _ros_matrix(path, doc, "rectification_matrix", 3, 3), coarse=True)[:3, :3]
    if "projection_matrix" in doc:
        P = _finite(path, "projection_matrix", _ros_matrix(path, doc, "projection_matrix", 3, 4))
    return name, size, K, d, R, P


def _ros_paths(paths: str | Path | Sequence[str | Path]) -> list[Path]:
    if isinstance(paths, str | Path):
        p = Path(paths)
        return [p / n for n in ROS_PAIR] if p.is_dir() else [p]
    out = [Path(p) for p in paths]
    if len(out) not in (1, 2):
        raise ValueError(f"a ROS rig is one camera_info file or a stereo pair (two), got "
                         f"{len(out)}")
    return out


def load_ros(paths: str | Path | Sequence[str | Path], *, names: Names = None,
             size: Size = None) -> Rig:
    """A rig from ROS camera_info YAML: one file (one camera, the reference), a stereo pair
    as two files (left, the reference, first), or a folder holding ``left.yaml`` and
    ``right.yaml``.

    The pair's extrinsics come from the rectification matrices R_l, R_r (camera to
    rectified frame) and the right projection matrix's ``Tx = -fx' B`` and ``Ty``: points
    of the left camera map into the right one by ``R_r^T [I | (Tx/fx', Ty/fy', 0)] R_l``.
    ``names`` defaults to each file's ``camera_name``, else ``camera`` or ``left``,
    ``right``; ``size``, if given, must match the files' image size.
    """
    plist = _ros_paths(paths)
    return _ros_rig([(p, _yaml_doc(p, _read_text(p))) for p in plist], names, size)


def _ros_rig(docs: Sequence[tuple[Path, Any]], names: Names, size: Size) -> Rig:
    cams = [(p, *_ros_camera(p, doc)) for p, doc in docs]
    default = ["camera"] if len(cams) == 1 else ["left", "right"]
    found = _names(cams[0][0], names, len(cams), [c[1] for c in cams], default)
    for p, _, wh, *_ in cams:
        _check_size(p, "image_width", wh, size)
    if len(cams) == 1:
        p, _, wh, K, d, _, _ = cams[0]
        return _rig(p, [_camera(p, "camera_matrix", found[0], wh, K, d)])
    (pl, _, whl, Kl, dl, Rl, Pl), (pr, _, whr, Kr, dr, Rr, Pr) = cams
    for p, R, P in ((pl, Rl, Pl), (pr, Rr, Pr)):
        if R is None or P is None:
            raise ConfigError(p, "rectification_matrix" if R is None else "projection_matrix",
                              "missing: a stereo pair's extrinsics come from the "
                              "rectification and projection matrices")
    if np.any(Pl[:, 3] != 0):
        raise ConfigError(pl, "projection_matrix", f"its last column {Pl[:, 3].tolist()} is "
                          "not zero: the first file of a pair must be the left (reference) "
                          "camera")
    if Pr[2, 3] != 0:
        raise ConfigError(pr, "projection_matrix", f"Tz = P[2][3] = {Pr[2, 3]!r} must be 0 in "
                          "a rectified pair")
    if not np.allclose(Pl[:2, :2], Pr[:2, :2], rtol=1e-9, atol=0.0) or Pr[0, 0] <= 0 \
            or Pr[1, 1] <= 0:
        raise ConfigError(pr, "projection_matrix", f"fx' fy' {Pr[0, 0]!r} {Pr[1, 1]!r} differ "
                          f"from the left's {Pl[0, 0]!r} {Pl[1, 1]!r}: not one rectified pair")
    T_rr_rl = np.eye(4)
    T_rr_rl[:3, 3] = (Pr[0, 3] / Pr[0, 0], Pr[1, 3] / Pr[1, 1], 0.0)
    T_rl_l, T_rr_r = np.eye(4), np.eye(4)
    T_rl_l[:3, :3], T_rr_r[:3, :3] = Rl, Rr
    T_r_l = invert(T_rr_r) @ T_rr_rl @ T_rl_l
    return _rig(pl, [_camera(pl, "camera_matrix", found[0], whl, Kl, dl),
                     _camera(pr, "projection_matrix", found[1], whr, Kr, dr, invert(T_r_l))])


def _ros_doc(c: CameraModel, dist: np.ndarray, R: np.ndarray, P: np.ndarray) -> dict:
    return {"image_width": c.width, "image_height": c.height, "camera_name": c.name,
            "camera_matrix": {"rows": 3, "cols": 3, "data": c.K.ravel()},
            "distortion_model": "plumb_bob" if dist.size == 5 else "rational_polynomial",
            "distortion_coefficients": {"rows": 1, "cols": int(dist.size), "data": dist},
            "rectification_matrix": {"rows": 3, "cols": 3, "data": R.ravel()},
            "projection_matrix": {"rows": 3, "cols": 4, "data": P.ravel()}}


def ros_texts(rig: Rig, path: str | Path) -> dict[Path, str]:
    """``rig`` as ROS camera_info YAML, by the file each text goes to: one camera -> ``path``
    itself (a ``.yaml`` file; R = I, P = [K | 0]); two -> ``path`` is a folder and the texts
    go to ``left.yaml`` (the reference) and ``right.yaml``, with R and P from
    ``cv2.stereoRectify`` (CALIB_ZERO_DISPARITY, alpha 0, as camera_calibration does)."""
    path = Path(path)
    cams = _ordered(rig, path, "ROS camera_info", 2)
    dists = [_fit_distortion(path, c, (5, 8), "ROS's plumb_bob (5) or rational_polynomial "
                                              "(8)") for c in cams]
    if len(cams) == 1:
        if path.suffix.lower() not in (".yaml", ".yml"):
            raise ConfigError(path, "", "a one-camera ROS file is a .yaml file: name it so")
        (c,), (d,) = cams, dists
        P = np.hstack([c.K, np.zeros((3, 1))])
        return {path: _flow(_ros_doc(c, d, np.eye(3), P), sort=False)}
    if path.suffix:
        raise ConfigError(path, "", f"a ROS stereo pair is written to a folder as "
                                    f"{' and '.join(ROS_PAIR)}: give a folder, not a file")
    c1, c2 = cams
    T_c2_c1 = invert(c2.T_ref_cam)
    R1, R2, P1, P2, _, _, _ = cv2.stereoRectify(
        c1.K, c1.dist, c2.K, c2.dist, c1.size, T_c2_c1[:3, :3],
        T_c2_c1[:3, 3].reshape(3, 1),
        flags=cv2.CALIB_ZERO_DISPARITY, alpha=0)
    return {path / ROS_PAIR[0]: _flow(_ros_doc(c1, dists[0], R1, P1), sort=False),
            path / ROS_PAIR[1]: _flow(_ros_doc(c2, dists[1], R2, P2), sort=False)}


def save_ros(rig: Rig, path: str | Path) -> None:
    """Write ``rig`` as ROS camera_info YAML (:func:`ros_texts` says where). The texts are
    read back before anything is written; each file is written atomically, but a pair is
    two files, so a crash between them can leave a new ``left.yaml`` beside the old
    ``right.yaml``. A pair's folder is created if it does not exist (its parent must)."""
    texts = ros_texts(rig, path)
    _ros_rig([(p, _yaml_doc(p, t)) for p, t in texts.items()], None, None)
    folder = Path(path)
    if len(texts) == 2 and not folder.is_dir():
        if not folder.parent.is_dir():
            raise FileNotFoundError(f"cannot write {str(folder)!r}: folder "
                                    f"{str(folder.parent)!r} does not exist")
        folder.mkdir()
    for p, text in texts.items():
        atomic_write_text(p, text)
