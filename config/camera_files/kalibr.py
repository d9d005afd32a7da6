"""Kalibr camchain YAML: ``cam0``, ``cam1``... pinhole cameras chained by ``T_cn_cnm1``."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from oralnav.control.geometry import invert
from oralnav.control.vision.camera import Rig

from ..errors import ConfigError
from ..loader import atomic_write_text
from .checks import (
    _FISHEYE,
    Names,
    Size,
    _camera,
    _check_size,
    _intrinsics,
    _keys_found,
    _names,
    _numbers,
    _pixels,
    _read_text,
    _rig,
    _rigid,
    _yaml_doc,
)
from .detect import _KALIBR_CAM, _yaml_kind
from .writing import _fit_distortion, _flow, _ordered

_KALIBR_KEYS = {"camera_model", "intrinsics", "distortion_model", "distortion_coeffs",
                "resolution", "rostopic", "T_cn_cnm1"}
# Kalibr keys that describe nothing the rig holds (view overlaps, the IMU): read past.
_KALIBR_IGNORED = {"cam_overlaps", "T_cam_imu", "timeshift_cam_imu"}


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
