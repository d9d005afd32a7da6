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

The package: :mod:`.detect` (which format a file is), :mod:`.opencv`, :mod:`.ros` and
:mod:`.kalibr` (one reader and writer each), :mod:`.checks` and :mod:`.writing` (what the
readers and the writers share); this module dispatches by format.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from oralnav.control.vision.camera import Rig

from ..errors import ConfigError
from .checks import FLOAT32_ROTATION_TOL, Names, Size
from .detect import EXPECTED, FORMATS, ROS_PAIR, detect_format, sniff_format
from .kalibr import kalibr_text, load_kalibr, save_kalibr
from .opencv import OPENCV_SUFFIXES, load_opencv, opencv_text, save_opencv
from .ros import load_ros, ros_texts, save_ros

__all__ = [
    "EXPECTED", "FLOAT32_ROTATION_TOL", "FORMATS", "OPENCV_SUFFIXES", "ROS_PAIR", "Names",
    "Size", "detect_format", "kalibr_text", "load_camera_file", "load_kalibr", "load_opencv",
    "load_ros", "opencv_text", "ros_texts", "save_camera_file", "save_kalibr", "save_opencv",
    "save_ros", "sniff_format",
]


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
