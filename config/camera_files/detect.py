"""Which format a rig or camera file is in: judged from its content (a ``.toml`` file is
ours without reading it), with an error that says what was expected and what was found."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path
from typing import Any

import yaml

from ..errors import ConfigError
from .checks import _keys_found, _one_line, _read_text

#: Every rig file format :func:`oralnav.config.rig.save_rig_as` writes.
FORMATS = ("toml", "opencv", "ros", "kalibr")
#: The files of a ROS stereo pair in a folder, left (the reference) first: the names ROS's
#: camera_calibration gives them in its calibrationdata.tar.gz.
ROS_PAIR = ("left.yaml", "right.yaml")
#: What a rig file may be, for error messages.
EXPECTED = ("a rig TOML, an OpenCV FileStorage file (YAML with !!opencv-matrix matrices, XML "
            "or JSON), a ROS camera_info YAML (image_width, camera_matrix, ...) or a Kalibr "
            "camchain YAML (cam0, cam1, ...)")

_KALIBR_CAM = re.compile(r"cam(\d+)")


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
