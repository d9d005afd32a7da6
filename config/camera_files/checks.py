"""What the camera-file readers share: reading a file's text, the number, pixel, matrix,
distortion and rotation checks, and the cameras and rig built from what passed them. Every
failure is a :class:`ConfigError` naming the file and key."""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from oralnav.checks import ROTATION_TOL
from oralnav.control.geometry import as_transform, nearest_rigid
from oralnav.control.vision.camera import DIST_LENGTHS, CameraModel, Rig

from ..errors import ConfigError
from ..loader import build

#: A rotation stored at float32 precision (or printed with 6 decimals) may miss the 1e-6
#: orthonormality check; within this of a rotation it is projected onto the nearest one.
FLOAT32_ROTATION_TOL = 1e-5
# Fisheye model names of ROS and Kalibr, which the rig cannot hold.
_FISHEYE = {"equidistant", "equi", "fisheye", "kannala_brandt"}

Names = Sequence[str] | None
Size = tuple[int, int] | None


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


def _keys_found(doc: Any) -> str:
    if isinstance(doc, dict) and doc:
        keys = ", ".join(str(k) for k in list(doc)[:8]) + (", ..." if len(doc) > 8 else "")
        return f"; found the top-level keys {keys}"
    return ""


def _one_line(exc: Exception) -> str:
    return " ".join(str(exc).split())


def _yaml_doc(path: Path, text: str) -> Any:
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(path, "", f"not valid YAML: {_one_line(exc)}") from None


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
