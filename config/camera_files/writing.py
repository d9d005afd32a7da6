"""What the camera-file writers share: the cameras in the order a file holds them, their
distortion at a length the format takes, and YAML written as ROS and Kalibr write it."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from oralnav.control.vision.camera import CameraModel, Rig

from ..errors import ConfigError


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
