"""OpenCV ``FileStorage`` camera files (YAML, XML or JSON): one camera as OpenCV's
calibration sample writes it, or a stereo pair as its stereo_calib sample does; read and
written through ``cv2.FileStorage``."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import cv2
import numpy as np

from oralnav.control.geometry import invert
from oralnav.control.vision.camera import Rig

from ..errors import ConfigError
from ..loader import atomic_write_text
from .checks import (
    Names,
    Size,
    _camera,
    _check_size,
    _distortion,
    _finite,
    _intrinsics,
    _names,
    _pixels,
    _read_text,
    _rig,
    _rotation,
)
from .writing import _ordered

#: OpenCV's suffixes, by which cv2.FileStorage picks the syntax it writes.
OPENCV_SUFFIXES = (".yml", ".yaml", ".xml", ".json")


class _Entry(NamedTuple):
    """One top-level FileStorage value copied out of its file: a matrix (float32: stored as
    ``dt: f``), a number, a string, a list (its strings; ``None`` for anything else), or
    ``None`` for anything else (a mapping that is no matrix, an unreadable matrix)."""

    path: Path
    value: Any
    float32: bool = False


def _cv_reason(exc: cv2.error) -> str:
    msg = str(exc).strip().splitlines()
    return msg[-1].strip() if msg else "unreadable"


def _fs_value(node: cv2.FileNode) -> tuple[Any, bool]:
    if node.isInt():
        return int(node.real()), False
    if node.isReal():
        return float(node.real()), False
    if node.isString():
        return node.string(), False
    if node.isSeq():
        return [node.at(i).string() if node.at(i).isString() else None
                for i in range(node.size())], False
    # Only an opencv-matrix is a mapping with dt and data; mat() asserts on any other.
    if node.isMap() and not node.getNode("dt").empty() and not node.getNode("data").empty():
        try:
            m = node.mat()
        except cv2.error:
            return None, False
        if isinstance(m, np.ndarray):
            return m, m.dtype == np.float32
    return None, False


def _fs_entries(text: str, path: Path) -> dict[str, _Entry]:
    try:
        fs = cv2.FileStorage(text, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    except cv2.error as exc:
        raise ConfigError(path, "", f"not a valid OpenCV FileStorage file: "
                                    f"{_cv_reason(exc)}") from None
    if not fs.isOpened():
        raise ConfigError(path, "", "not a valid OpenCV FileStorage file")
    try:
        root = fs.root()
        return {key: _Entry(path, *_fs_value(root.getNode(key))) for key in root.keys()}
    finally:
        fs.release()


def _fs_matrix(entries: Mapping[str, _Entry], key: str) -> tuple[Path, np.ndarray, bool]:
    e = entries[key]
    if not isinstance(e.value, np.ndarray):
        raise ConfigError(e.path, key, f"must be an opencv-matrix, got {e.value!r}")
    return e.path, e.value, e.float32


def _pick(entries: Mapping[str, _Entry], spellings: Sequence[str]) -> str | None:
    """The one key of ``spellings`` the files hold (``None`` if none); two is an error."""
    found = [k for k in spellings if k in entries]
    if len(found) > 1:
        e = entries[found[1]]
        raise ConfigError(e.path, found[1], f"given together with {found[0]}: they spell the "
                                            "same matrix, so which one is meant is unclear")
    return found[0] if found else None


def _fs_size(entries: Mapping[str, _Entry], first: Path, size: Size) -> tuple[int, int]:
    have = [k for k in ("image_width", "image_height") if k in entries]
    if not have:
        if size is None:
            raise ConfigError(first, "image_width", "missing, and no image size was given: "
                              "OpenCV's stereo_calib sample does not write image_width and "
                              "image_height, so pass the size of the images")
        return (int(size[0]), int(size[1]))
    if len(have) == 1:
        missing = "image_height" if have[0] == "image_width" else "image_width"
        raise ConfigError(entries[have[0]].path, missing, f"missing (given {have[0]})")
    e_w, e_h = entries["image_width"], entries["image_height"]
    found = (_pixels(e_w.path, "image_width", e_w.value),
             _pixels(e_h.path, "image_height", e_h.value))
    _check_size(e_w.path, "image_width", found, size)
    return found


def _fs_names(entries: Mapping[str, _Entry], key: str, count: int) -> list[str | None]:
    e = entries.get(key)
    if e is None:
        return [None] * count
    v = [e.value] if isinstance(e.value, str) else e.value
    if not isinstance(v, list) or len(v) != count or not all(isinstance(s, str) and s
                                                             for s in v):
        raise ConfigError(e.path, key, f"must be {count} non-empty string(s), got {e.value!r}")
    return v


def load_opencv(paths: str | Path | Sequence[str | Path], *, names: Names = None,
                size: Size = None) -> Rig:
    """A rig from OpenCV FileStorage files (YAML, XML or JSON, judged from the content).

    Args:
        paths: one file, or several whose keys are merged (stereo_calib's intrinsics.yml and
            extrinsics.yml); a key in two files is an error.
        names: the cameras' names in file order; by default the file's ``camera_name``
            (one camera) or ``camera_names`` (a pair; our writer's keys, ignored by OpenCV),
            else ``camera`` or ``left``, ``right``.
        size: image ``(width, height)`` in pixels: required when the files do not hold
            ``image_width`` and ``image_height``, checked against them when they do.

    The second camera's pose is the inverse of ``[R | T]`` (OpenCV's R, T map points of
    camera 1 into camera 2); T is read as metres (OpenCV stores it in the unit of the
    board's square size). ``R1 R2 P1 P2 Q`` are derived from the rest and not read.
    """
    plist = [Path(paths)] if isinstance(paths, str | Path) else [Path(p) for p in paths]
    if not plist:
        raise ValueError("load_opencv needs at least one file")
    entries: dict[str, _Entry] = {}
    for p in plist:
        for key, e in _fs_entries(_read_text(p), p).items():
            if key in entries:
                raise ConfigError(p, key, f"also given in {entries[key].path}")
            entries[key] = e
    return _opencv_rig(entries, plist[0], names, size)


def _opencv_rig(entries: Mapping[str, _Entry], first: Path, names: Names,
                size: Size) -> Rig:
    fish = entries.get("fisheye_model")
    if fish is not None and fish.value not in (0, 0.0):
        raise ConfigError(fish.path, "fisheye_model", f"is {fish.value!r}: OpenCV's fisheye "
                          "model, which the rig cannot hold (pinhole with OpenCV's standard "
                          "distortion only)")
    mono_k = _pick(entries, ("camera_matrix", "K"))
    stereo = [k for k in ("M1", "K1", "D1", "M2", "K2", "D2", "R", "T") if k in entries]
    if mono_k and stereo:
        raise ConfigError(entries[stereo[0]].path, stereo[0], f"given together with {mono_k}: "
                          "the file holds both a one-camera and a stereo calibration")
    if not mono_k and not stereo:
        raise ConfigError(first, "camera_matrix", "missing: an OpenCV camera file holds "
                          "camera_matrix and distortion_coefficients (one camera; or K and D) "
                          "or M1 D1 M2 D2 R T (a stereo pair; or K1, K2)")
    if mono_k:
        d_key = _need(entries, ("distortion_coefficients", "D"), first)
        wh = _fs_size(entries, first, size)
        p, K, _ = _fs_matrix(entries, mono_k)
        K = _intrinsics(p, mono_k, K)
        p, d, _ = _fs_matrix(entries, d_key)
        d = _distortion(p, d_key, d)
        (name,) = _names(first, names, 1, _fs_names(entries, "camera_name", 1), ["camera"])
        return _rig(first, [_camera(p, mono_k, name, wh, K, d)])
    keys = [_need(entries, s, first) for s in (("M1", "K1"), ("D1",), ("M2", "K2"), ("D2",),
                                                ("R",), ("T",))]
    wh = _fs_size(entries, first, size)
    mats = {k: _fs_matrix(entries, k) for k in keys}
    k1, d1, k2, d2, r_key, t_key = keys
    K1, K2 = (_intrinsics(mats[k][0], k, mats[k][1]) for k in (k1, k2))
    D1, D2 = (_distortion(mats[k][0], k, mats[k][1]) for k in (d1, d2))
    p_r, R, r32 = mats[r_key]
    # float32 ('f') matrices hold ~7 digits, about the 1e-6 check itself: re-orthonormalise
    # only those (a float64 R must pass as it is).
    T_c2_c1 = _rotation(p_r, r_key, R, coarse=r32)
    p_t, t, _ = mats[t_key]
    t = _finite(p_t, t_key, t)
    if t.size != 3 or (t.ndim == 2 and 1 not in t.shape):
        raise ConfigError(p_t, t_key, f"must be a 3-vector, got shape {t.shape}")
    T_c2_c1[:3, 3] = t.reshape(3)
    n1, n2 = _names(first, names, 2, _fs_names(entries, "camera_names", 2), ["left", "right"])
    return _rig(first, [_camera(mats[k1][0], k1, n1, wh, K1, D1),
                        _camera(p_r, r_key, n2, wh, K2, D2, invert(T_c2_c1))])


def _need(entries: Mapping[str, _Entry], spellings: Sequence[str], first: Path) -> str:
    key = _pick(entries, spellings)
    if key is None:
        raise ConfigError(first, spellings[0], "missing" + (
            f" (nor {', '.join(spellings[1:])})" if len(spellings) > 1 else "")
            + ("; OpenCV's stereo_calib writes R and T to extrinsics.yml: pass it too"
               if spellings[0] in ("R", "T") else ""))
    return key


def opencv_text(rig: Rig, path: str | Path) -> str:
    """``rig`` as OpenCV FileStorage text, in the syntax ``path``'s suffix names
    (:data:`OPENCV_SUFFIXES`): one camera as the calibration sample writes it (plus
    ``camera_name``), two as the stereo_calib sample does (``M1 D1 M2 D2 R T R1 R2 P1 P2
    Q``, plus ``image_width``, ``image_height`` and ``camera_names``)."""
    path = Path(path)
    if path.suffix.lower() not in OPENCV_SUFFIXES:
        raise ConfigError(path, "", "an OpenCV file is written as YAML (.yml, .yaml), XML "
                                    "(.xml) or JSON (.json): name it so")
    cams = _ordered(rig, path, "OpenCV", 2)
    fs = cv2.FileStorage(f"rig{path.suffix.lower()}",
                         cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)
    if len(cams) == 1:
        (c,) = cams
        fs.write("image_width", c.width)
        fs.write("image_height", c.height)
        fs.write("camera_name", c.name)
        fs.write("camera_matrix", c.K)
        fs.write("distortion_coefficients", c.dist.reshape(-1, 1))
        return fs.releaseAndGetString()
    c1, c2 = cams
    if c1.size != c2.size:
        raise ConfigError(path, f"cameras.{c2.name}.size", f"{c2.size} differs from "
                          f"{c1.name}'s {c1.size}: OpenCV's stereo files hold one image size")
    T_c2_c1 = invert(c2.T_ref_cam)
    R, T = T_c2_c1[:3, :3], T_c2_c1[:3, 3].reshape(3, 1)
    # For consumers of stereo_calib's files; the reader ignores them (derived values).
    R1, R2, P1, P2, Q, _, _ = cv2.stereoRectify(c1.K, c1.dist, c2.K, c2.dist, c1.size, R, T,
                                               flags=cv2.CALIB_ZERO_DISPARITY, alpha=0)
    fs.write("image_width", c1.width)
    fs.write("image_height", c1.height)
    fs.startWriteStruct("camera_names", cv2.FileNode_SEQ)
    for c in cams:
        fs.write("", c.name)
    fs.endWriteStruct()
    for key, value in (("M1", c1.K), ("D1", c1.dist.reshape(1, -1)), ("M2", c2.K),
                       ("D2", c2.dist.reshape(1, -1)), ("R", R), ("T", T), ("R1", R1),
                       ("R2", R2), ("P1", P1), ("P2", P2), ("Q", Q)):
        fs.write(key, np.ascontiguousarray(value, dtype=float))
    return fs.releaseAndGetString()


def save_opencv(rig: Rig, path: str | Path) -> None:
    """Write ``rig`` (one or two cameras) as an OpenCV FileStorage file, atomically; the
    text is read back first, so a file that would not load is never written."""
    text = opencv_text(rig, path)
    _opencv_rig(_fs_entries(text, Path(path)), Path(path), None, None)
    atomic_write_text(path, text)
