"""Camera files of the wider ecosystem, read into our :class:`Rig` and written from it.

Three formats (docs/formats.md, "Camera files of OpenCV, ROS and Kalibr", lists every key):

- OpenCV ``FileStorage`` (YAML, XML or JSON): one camera as OpenCV's calibration sample
  writes it (``camera_matrix``, ``distortion_coefficients``, ``image_width``,
  ``image_height``; or the plain ``K``, ``D``), or a stereo pair as its stereo_calib sample
  writes it (``M1 D1 M2 D2`` in intrinsics.yml, ``R T R1 R2 P1 P2 Q`` in extrinsics.yml;
  or ``K1``, ``K2``). Read and written through ``cv2.FileStorage``.
- ROS ``camera_info`` YAML: one file per camera; a stereo pair is two files whose
  rectification matrices and right projection matrix give the extrinsics.
- Kalibr camchain YAML: ``cam0``, ``cam1``... chained by ``T_cn_cnm1``.

Units and frames: intrinsics in pixels, translations in metres, camera frames as OpenCV's
(z along the optical axis, x right, y down), which all three formats share. Every format
gives poses relative to its first camera, so a rig read from one has its first camera as
the reference, and only a rig whose reference is one of its cameras can be written (that
camera first). What the rig cannot hold (fisheye or omnidirectional models, skew, a
distortion model or length outside OpenCV's standard one) is refused, never approximated.
Errors are :class:`ConfigError` naming the file and key.
"""

from __future__ import annotations

import math
import re
import tomllib
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import cv2
import numpy as np
import yaml

from oralnav.checks import ROTATION_TOL
from oralnav.control.geometry import as_transform, invert, nearest_rigid
from oralnav.control.vision.camera import DIST_LENGTHS, CameraModel, Rig

from .errors import ConfigError
from .loader import atomic_write_text, build

#: Every rig file format :func:`oralnav.config.rig.save_rig_as` writes.
FORMATS = ("toml", "opencv", "ros", "kalibr")
#: The files of a ROS stereo pair in a folder, left (the reference) first: the names ROS's
#: camera_calibration gives them in its calibrationdata.tar.gz.
ROS_PAIR = ("left.yaml", "right.yaml")
#: What a rig file may be, for error messages.
EXPECTED = ("a rig TOML, an OpenCV FileStorage file (YAML with !!opencv-matrix matrices, XML "
            "or JSON), a ROS camera_info YAML (image_width, camera_matrix, ...) or a Kalibr "
            "camchain YAML (cam0, cam1, ...)")
#: OpenCV's suffixes, by which cv2.FileStorage picks the syntax it writes.
OPENCV_SUFFIXES = (".yml", ".yaml", ".xml", ".json")
#: A rotation stored at float32 precision (or printed with 6 decimals) may miss the 1e-6
#: orthonormality check; within this of a rotation it is projected onto the nearest one.
FLOAT32_ROTATION_TOL = 1e-5

_KALIBR_CAM = re.compile(r"cam(\d+)")
_ROS_KEYS = ("image_width", "image_height", "camera_name", "camera_matrix", "distortion_model",
             "distortion_coefficients", "rectification_matrix", "projection_matrix")
# ROS's distortion models the rig holds, with the lengths each may have.
_ROS_MODELS = {"plumb_bob": (4, 5), "rational_polynomial": (8,)}
_FISHEYE = {"equidistant", "equi", "fisheye", "kannala_brandt"}
_KALIBR_KEYS = {"camera_model", "intrinsics", "distortion_model", "distortion_coeffs",
                "resolution", "rostopic", "T_cn_cnm1"}
# Kalibr keys that describe nothing the rig holds (view overlaps, the IMU): read past.
_KALIBR_IGNORED = {"cam_overlaps", "T_cam_imu", "timeshift_cam_imu"}

Names = Sequence[str] | None
Size = tuple[int, int] | None


# -- detection ------------------------------------------------------------------------------
def _read_text(path: Path) -> str:
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise ConfigError(path, "", "file not found") from None
    except IsADirectoryError:
        raise ConfigError(path, "", "is a folder, not a file") from None
    except OSError as exc:
        raise ConfigError(path, "", f"cannot read: {exc.strerror or exc}") from None
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        raise ConfigError(path, "", "not UTF-8 text") from None


def _is_opencv(text: str) -> bool:
    # OpenCV 4 heads its YAML with "%YAML:1.0", OpenCV 5 with "%YAML 1.2"; the matrices'
    # tag is OpenCV's own either way.
    head = text.lstrip()[:200]
    return (head.startswith("%YAML:") or "!!opencv-matrix" in text
            or (head.startswith("<?xml") and "<opencv_storage>" in text)
            or (head.startswith("{") and '"opencv-matrix"' in text))


def _yaml_kind(doc: Any) -> str | None:
    if not isinstance(doc, dict):
        return None
    if "camera_matrix" in doc and ("image_width" in doc or "distortion_coefficients" in doc):
        return "ros"
    if any(isinstance(k, str) and _KALIBR_CAM.fullmatch(k) and isinstance(v, dict)
           for k, v in doc.items()):
        return "kalibr"
    return None


def _sniff_text(text: str) -> str | None:
    if _is_opencv(text):
        return "opencv"
    try:
        kind = _yaml_kind(yaml.safe_load(text))
    except yaml.YAMLError:
        kind = None
    if kind:
        return kind
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError:
        return None
    return "toml" if "cameras" in doc or "reference" in doc else None


def sniff_format(path: str | Path) -> str | None:
    """The format of the file at ``path`` judged from its content: ``"opencv"``, ``"ros"``,
    ``"kalibr"`` or ``"toml"`` (a rig TOML), or ``None`` when it is none of them. A folder
    holding ROS's ``left.yaml`` and ``right.yaml`` is ``"ros"``.

    Raises ``ConfigError`` when the file cannot be read."""
    p = Path(path)
    if p.is_dir():
        return "ros" if all((p / n).is_file() for n in ROS_PAIR) else None
    return _sniff_text(_read_text(p))


def detect_format(path: str | Path) -> str:
    """The format of a rig or camera file, one of :data:`FORMATS`: a ``.toml`` file is ours
    without reading it, anything else is judged from its content (:func:`sniff_format`).

    Raises ``ConfigError`` naming the file and what was expected when it is none of them."""
    p = Path(path)
    if p.is_dir():
        if sniff_format(p):
            return "ros"
        raise ConfigError(p, "", f"a folder is read as a ROS stereo pair and needs "
                                 f"{' and '.join(ROS_PAIR)} in it")
    if p.suffix.lower() == ".toml":
        return "toml"
    text = _read_text(p)
    fmt = _sniff_text(text)
    if fmt:
        return fmt
    raise ConfigError(p, "", f"not a rig or camera file: expected {EXPECTED}"
                             f"{_found(text, p.suffix.lower())}")


def _keys_found(doc: Any) -> str:
    if isinstance(doc, dict) and doc:
        keys = ", ".join(str(k) for k in list(doc)[:8]) + (", ..." if len(doc) > 8 else "")
        return f"; found the top-level keys {keys}"
    return ""


def _one_line(exc: Exception) -> str:
    return " ".join(str(exc).split())


def _found(text: str, suffix: str) -> str:
    """What the file holds instead, for the error message: its top-level keys, or why it
    does not parse (as YAML for a .yaml or .yml file, else as TOML)."""
    try:
        doc, yaml_error = yaml.safe_load(text), ""
    except yaml.YAMLError as exc:
        doc, yaml_error = None, f"; as YAML: {_one_line(exc)}"
    if _keys_found(doc):
        return _keys_found(doc)
    if suffix in (".yaml", ".yml"):
        return yaml_error or (f"; found a YAML {type(doc).__name__}, not a mapping of keys"
                              if doc is not None else "; the file is empty")
    try:
        tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        return f"; as TOML: {_one_line(exc)}"
    return yaml_error


# -- checks shared by the readers -----------------------------------------------------------
def _number(path: Path, key: str, v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float | np.floating | np.integer):
        raise ConfigError(path, key, f"must be a number, got {v!r}")
    if not math.isfinite(float(v)):
        raise ConfigError(path, key, f"must be finite, got {v!r}")
    return float(v)


def _numbers(path: Path, key: str, v: Any, n: int | None = None) -> np.ndarray:
    if not isinstance(v, list):
        raise ConfigError(path, key, f"must be a list of numbers, got {v!r}")
    if n is not None and len(v) != n:
        raise ConfigError(path, key, f"must have {n} numbers, got {len(v)}")
    return np.array([_number(path, f"{key}[{i}]", x) for i, x in enumerate(v)])


def _pixels(path: Path, key: str, v: Any) -> int:
    if isinstance(v, bool) or not isinstance(v, int | np.integer) or not 0 < v <= 65535:
        raise ConfigError(path, key, f"must be a whole number of pixels in 1..65535, got {v!r}")
    return int(v)


def _finite(path: Path, key: str, m: np.ndarray) -> np.ndarray:
    m = np.asarray(m, dtype=float)
    if not np.all(np.isfinite(m)):
        raise ConfigError(path, key, f"has non-finite entries: {m.ravel().tolist()}")
    return m


def _intrinsics(path: Path, key: str, K: np.ndarray) -> np.ndarray:
    """A 3x3 pinhole matrix without skew, or ConfigError naming ``key``."""
    K = _finite(path, key, K)
    if K.shape != (3, 3):
        raise ConfigError(path, key, f"must be a 3x3 matrix, got {K.shape[0]}x"
                                     f"{K.shape[1] if K.ndim > 1 else 1}")
    if K[0, 1] != 0:
        raise ConfigError(path, key, f"has skew K[0][1] = {K[0, 1]!r}; the rig holds only "
                                     "cameras without skew")
    if K[1, 0] != 0 or list(K[2]) != [0.0, 0.0, 1.0]:
        raise ConfigError(path, key, "must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], got "
                                     f"{K.tolist()}")
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ConfigError(path, key, "focal lengths fx = K[0][0] and fy = K[1][1] must be "
                                     "positive")
    return K


def _distortion(path: Path, key: str, d: np.ndarray, lengths: Sequence[int] = DIST_LENGTHS,
                model: str = "OpenCV's") -> np.ndarray:
    d = _finite(path, key, d)
    if d.ndim == 2 and 1 not in d.shape:
        raise ConfigError(path, key, f"must be a row or a column, got {d.shape[0]}x{d.shape[1]}")
    d = d.reshape(-1)
    if d.size not in lengths:
        raise ConfigError(path, key, f"{model} distortion has {', '.join(map(str, lengths))} "
                                     f"coefficients (k1 k2 p1 p2 [k3 ...]), got {d.size}")
    return d


def _rotation(path: Path, key: str, R: np.ndarray, *, coarse: bool) -> np.ndarray:
    """``R`` as a 4x4 rigid transform (no translation). ``coarse``: the format stores it at
    float32 precision, so within :data:`FLOAT32_ROTATION_TOL` of a rotation it becomes the
    nearest rotation; otherwise it must pass the rig's 1e-6 check as it is."""
    R = _finite(path, key, R)
    if R.shape != (3, 3):
        raise ConfigError(path, key, f"must be a 3x3 rotation matrix, got shape {R.shape}")
    T = np.eye(4)
    T[:3, :3] = R
    if coarse:
        return nearest_rigid(_rigid(path, key, T, FLOAT32_ROTATION_TOL))
    return _rigid(path, key, T)


def _rigid(path: Path, key: str, T: np.ndarray, tol: float = ROTATION_TOL) -> np.ndarray:
    """``T`` checked as a rigid transform (rotation within ``tol`` of orthonormal)."""
    try:
        return as_transform(T, tol=tol, what="")
    except ValueError as exc:
        raise ConfigError(path, key, str(exc).removeprefix(": ")) from None


def _camera(path: Path, key: str, name: str, size: tuple[int, int], K: np.ndarray,
            dist: np.ndarray, T_ref_cam: np.ndarray | None = None) -> CameraModel:
    return build(path, key, lambda: CameraModel(
        name, size, K, dist, np.eye(4) if T_ref_cam is None else T_ref_cam))


def _rig(path: Path, cams: list[CameraModel]) -> Rig:
    seen: set[str] = set()
    for c in cams:
        if c.name in seen:
            raise ConfigError(path, "", f"two cameras are named {c.name!r}; pass names")
        seen.add(c.name)
    return build(path, "", lambda: Rig(cams[0].name, {c.name: c for c in cams}))


def _names(path: Path, names: Names, count: int, found: Sequence[str | None],
           default: Sequence[str]) -> list[str]:
    """Camera names in file order: ``names`` as given, else those the file holds, else
    ``default``."""
    if names is not None:
        names = list(names)
        if len(names) != count:
            raise ConfigError(path, "", f"holds {count} camera(s), but {len(names)} name(s) "
                                        f"were given: {names}")
        if not all(isinstance(n, str) and n for n in names):
            raise ValueError(f"camera names must be non-empty strings, got {names}")
        return names
    return [f if f else d for f, d in zip(found, default, strict=True)]


def _check_size(path: Path, key: str, found: tuple[int, int], size: Size) -> None:
    if size is not None and tuple(size) != found:
        raise ConfigError(path, key, f"the file is for {found[0]}x{found[1]} images, but the "
                                     f"images are {size[0]}x{size[1]}")


# -- OpenCV FileStorage ---------------------------------------------------------------------
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


# -- ROS camera_info ------------------------------------------------------------------------
def _yaml_doc(path: Path, text: str) -> Any:
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(path, "", f"not valid YAML: {_one_line(exc)}") from None


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


def _flow(doc: Mapping[str, Any], sort: bool) -> str:
    """YAML as PyYAML writes it for Kalibr and ROS: block mappings, flow lists; floats with
    every digit (repr), never a numpy type."""
    return yaml.safe_dump(_plain(doc), sort_keys=sort, default_flow_style=None, width=4096)


def _plain(v: Any) -> Any:
    if isinstance(v, Mapping):
        return {k: _plain(x) for k, x in v.items()}
    if isinstance(v, np.ndarray):
        return _plain(v.tolist())
    if isinstance(v, list | tuple):
        return [_plain(x) for x in v]
    if isinstance(v, np.floating):
        return float(v)
    if isinstance(v, np.integer):
        return int(v)
    return v


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


# -- Kalibr camchain ------------------------------------------------------------------------
def _topic_name(topic: str) -> str:
    """A camera name from its ROS image topic: ``/stereo/left/image_raw`` -> ``stereo/left``."""
    parts = [p for p in topic.split("/") if p]
    if len(parts) > 1 and parts[-1].startswith("image"):
        parts = parts[:-1]
    return "/".join(parts)


def load_kalibr(path: str | Path, *, names: Names = None, size: Size = None) -> Rig:
    """A rig from a Kalibr camchain YAML (``cam0``, ``cam1``...; pinhole cameras with the
    ``radtan`` or ``none`` distortion). Camera n's pose follows from ``T_cn_cnm1``, which
    maps points of camera n-1 into camera n: ``T_ref_cn = T_ref_cnm1 inv(T_cn_cnm1)``.

    ``names`` defaults to the cameras' ``rostopic`` without its final ``image...`` part
    (``/stereo/left/image_raw`` -> ``stereo/left``), or ``cam0``, ``cam1``... when a
    camera has none or two would share a name; ``size``, if given, must match every
    camera's ``resolution``. ``cam_overlaps``, ``T_cam_imu`` and ``timeshift_cam_imu`` are
    read past (the rig holds no IMU).
    """
    path = Path(path)
    return _kalibr_rig(path, _yaml_doc(path, _read_text(path)), names, size)


def _kalibr_rig(path: Path, doc: Any, names: Names, size: Size) -> Rig:
    if _yaml_kind(doc) != "kalibr":
        raise ConfigError(path, "", "not a Kalibr camchain YAML (cam0, cam1, ...)"
                          + _keys_found(doc))
    idx = {}
    for k in doc:
        m = _KALIBR_CAM.fullmatch(k) if isinstance(k, str) else None
        if m is None:
            raise ConfigError(path, str(k), "unknown key: a camchain holds only cam0, cam1, "
                                            "...")
        idx[int(m.group(1))] = k
    if sorted(idx) != list(range(len(idx))):
        missing = min(set(range(len(idx))) - set(idx))
        raise ConfigError(path, f"cam{missing}", "missing: cameras are numbered from cam0 "
                                                 "without gaps")
    parsed = [_kalibr_camera(path, f"cam{i}", doc[f"cam{i}"], i) for i in range(len(idx))]
    topics = [_topic_name(t) if t else None for *_, t in parsed]
    if None in topics or len(set(topics)) != len(topics) or "" in topics:
        topics = [f"cam{i}" for i in range(len(parsed))]
    found = _names(path, names, len(parsed), topics, topics)
    cams, T_ref_prev = [], np.eye(4)
    for i, (wh, K, d, T_cn_cnm1, _) in enumerate(parsed):
        _check_size(path, f"cam{i}.resolution", wh, size)
        T = np.eye(4) if i == 0 else T_ref_prev @ invert(T_cn_cnm1)
        cams.append(_camera(path, f"cam{i}", found[i], wh, K, d, T))
        T_ref_prev = T
    return _rig(path, cams)


def _kalibr_camera(path: Path, key: str, cam: Any, i: int):
    if not isinstance(cam, dict):
        raise ConfigError(path, key, f"must be a mapping, got {cam!r}")
    for k in cam:
        if k not in _KALIBR_KEYS | _KALIBR_IGNORED:
            raise ConfigError(path, f"{key}.{k}", "unknown key: a camchain camera holds "
                              f"{', '.join(sorted(_KALIBR_KEYS | _KALIBR_IGNORED))}")
    for k in ("camera_model", "intrinsics", "distortion_model", "distortion_coeffs",
              "resolution"):
        if k not in cam:
            raise ConfigError(path, f"{key}.{k}", "missing")
    model = cam["camera_model"]
    if model != "pinhole":
        raise ConfigError(path, f"{key}.camera_model", f"{model!r} cannot be held by the rig: "
                          "only Kalibr's pinhole model (omni, ds and eucm are not)")
    fu, fv, pu, pv = _numbers(path, f"{key}.intrinsics", cam["intrinsics"], 4)
    K = _intrinsics(path, f"{key}.intrinsics", np.array([[fu, 0, pu], [0, fv, pv], [0, 0, 1]]))
    dmodel = cam["distortion_model"]
    if dmodel in _FISHEYE:
        raise ConfigError(path, f"{key}.distortion_model", f"{dmodel!r} is Kalibr's fisheye "
                          "(equidistant) model, which the rig cannot hold (radtan only)")
    if dmodel not in ("radtan", "none"):
        raise ConfigError(path, f"{key}.distortion_model", f"{dmodel!r} cannot be held by the "
                          "rig: radtan (or none) only")
    n = 4 if dmodel == "radtan" else 0
    d = _numbers(path, f"{key}.distortion_coeffs", cam["distortion_coeffs"], n)
    d = d if n else np.zeros(4)  # 'none' is exactly radtan with zero coefficients
    res = cam["resolution"]
    if not isinstance(res, list) or len(res) != 2:
        raise ConfigError(path, f"{key}.resolution", f"must be [width, height], got {res!r}")
    wh = (_pixels(path, f"{key}.resolution[0]", res[0]),
          _pixels(path, f"{key}.resolution[1]", res[1]))
    T = None
    if i == 0 and "T_cn_cnm1" in cam:
        raise ConfigError(path, f"{key}.T_cn_cnm1", "cam0 is the chain's base and has no "
                                                    "T_cn_cnm1")
    if i > 0:
        if "T_cn_cnm1" not in cam:
            raise ConfigError(path, f"{key}.T_cn_cnm1", "missing: the pose of the camera "
                                                        "before it in this camera")
        rows = cam["T_cn_cnm1"]
        if not isinstance(rows, list) or len(rows) != 4:
            raise ConfigError(path, f"{key}.T_cn_cnm1", "must be 4 rows of 4 numbers")
        T = np.array([_numbers(path, f"{key}.T_cn_cnm1[{r}]", row, 4)
                      for r, row in enumerate(rows)])
        # Kalibr writes every digit (PyYAML repr), so the strict check applies as it is.
        T = _rigid(path, f"{key}.T_cn_cnm1", T)
    topic = cam.get("rostopic")
    if topic is not None and not isinstance(topic, str):
        raise ConfigError(path, f"{key}.rostopic", f"must be a string, got {topic!r}")
    return wh, K, d, T, topic


def kalibr_text(rig: Rig, path: str | Path) -> str:
    """``rig`` as a Kalibr camchain: the reference camera is ``cam0``, the others follow in
    rig order; keys sorted as Kalibr's own yaml.dump writes them. ``rostopic`` is
    ``/<name>/image_raw`` (it carries the name back); ``cam_overlaps`` is not written
    (the rig does not know which views overlap)."""
    path = Path(path)
    cams = _ordered(rig, path, "Kalibr", None)
    doc: dict[str, Any] = {}
    for i, c in enumerate(cams):
        d = _fit_distortion(path, c, (4,), "Kalibr's radtan (4)")
        cam: dict[str, Any] = {
            "camera_model": "pinhole", "distortion_coeffs": d, "distortion_model": "radtan",
            "intrinsics": [c.K[0, 0], c.K[1, 1], c.K[0, 2], c.K[1, 2]],
            "resolution": list(c.size), "rostopic": f"/{c.name}/image_raw"}
        if i:
            cam["T_cn_cnm1"] = invert(c.T_ref_cam) @ cams[i - 1].T_ref_cam
        doc[f"cam{i}"] = cam
    return _flow(doc, sort=True)


def save_kalibr(rig: Rig, path: str | Path) -> None:
    """Write ``rig`` as a Kalibr camchain YAML, atomically, after reading the text back."""
    text = kalibr_text(rig, path)
    _kalibr_rig(Path(path), _yaml_doc(Path(path), text), None, None)
    atomic_write_text(path, text)


# -- writing helpers ------------------------------------------------------------------------
def _ordered(rig: Rig, path: Path, fmt: str, most: int | None) -> list[CameraModel]:
    """The cameras to write, the reference first; refuses what ``fmt`` cannot hold."""
    if rig.reference not in rig.cameras:
        raise ConfigError(path, "reference", f"{rig.reference!r} is not one of the rig's "
                          f"cameras: {fmt} files give poses relative to their first camera, "
                          "so only a rig whose reference is a camera can be written")
    if most is not None and len(rig.cameras) > most:
        raise ConfigError(path, "cameras", f"{fmt} files hold at most {most} cameras, the rig "
                                           f"has {len(rig.cameras)}")
    return [rig.cameras[rig.reference]] + [c for n, c in rig.cameras.items()
                                           if n != rig.reference]


def _fit_distortion(path: Path, c: CameraModel, lengths: Sequence[int],
                    what: str) -> np.ndarray:
    """``c.dist`` at a length of ``lengths``: zeros appended, or trailing zeros dropped
    (both change nothing); refused when a non-zero coefficient would be lost."""
    d = c.dist
    for n in sorted(lengths):
        if n >= d.size:
            return np.concatenate([d, np.zeros(n - d.size)])
    n = max(lengths)
    if np.any(d[n:] != 0):
        raise ConfigError(path, f"cameras.{c.name}.dist", f"{d.size} coefficients with "
                          f"non-zero ones past the {n}th: {what} cannot hold them")
    return d[:n].copy()


def load_camera_file(path: str | Path | Sequence[str | Path], *, names: Names = None,
                     size: Size = None, fmt: str | None = None) -> Rig:
    """A rig from an OpenCV, ROS or Kalibr file (or a ROS pair's folder), ``fmt`` judged
    from the content unless given; several paths are OpenCV files to merge or a ROS pair.
    ``names`` and ``size`` as the format's reader takes them."""
    if not isinstance(path, str | Path):
        paths = [Path(p) for p in path]
        fmt = fmt or detect_format(paths[0])
        if fmt == "opencv":
            return load_opencv(paths, names=names, size=size)
        if fmt == "ros":
            return load_ros(paths, names=names, size=size)
        raise ConfigError(paths[0], "", f"several files are read as OpenCV or ROS files, "
                                        f"not {fmt}")
    fmt = fmt or detect_format(path)
    readers = {"opencv": load_opencv, "ros": load_ros, "kalibr": load_kalibr}
    if fmt not in readers:
        raise ConfigError(path, "", f"not an OpenCV, ROS or Kalibr camera file (a {fmt} "
                                    "file): read it with oralnav.config.rig.load_rig")
    return readers[fmt](path, names=names, size=size)


def save_camera_file(rig: Rig, path: str | Path, fmt: str) -> None:
    """Write ``rig`` as ``fmt``: ``"opencv"``, ``"ros"`` or ``"kalibr"``."""
    writers = {"opencv": save_opencv, "ros": save_ros, "kalibr": save_kalibr}
    if fmt not in writers:
        raise ValueError(f"fmt must be one of {', '.join(writers)}, got {fmt!r}")
    writers[fmt](rig, path)
