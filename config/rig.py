"""The rig file: cameras, their intrinsics and their poses in the reference frame.

See docs/formats.md. Lengths in metres, intrinsics in pixels. Our TOML is the default;
:func:`load_rig` also reads OpenCV, ROS and Kalibr camera files and :func:`save_rig_as`
writes them (config/camera_files/).
"""

from __future__ import annotations

import functools
import tomllib
from importlib import resources
from pathlib import Path
from typing import Annotated

import numpy as np
from pydantic import Field, field_validator

from oralnav.control.geometry import as_transform
from oralnav.control.vision.camera import DIST_LENGTHS, CameraModel, Rig

from .camera_files import FORMATS, Names, Size, detect_format, load_camera_file, save_camera_file
from .loader import Float, Int, Strict, atomic_write_text, build, dump_toml, read_toml, validate

Matrix = list[list[Float]]
Pixels = Annotated[Int, Field(gt=0, le=65535)]


class CameraEntry(Strict):
    size: tuple[Pixels, Pixels]
    K: Matrix
    dist: list[Float] = Field(default_factory=lambda: [0.0] * 5)
    T_ref_cam: Matrix = Field(default_factory=lambda: np.eye(4).tolist())

    # The camera model checks these too; checking them here names the offending key.
    @field_validator("K")
    @classmethod
    def _k_shape(cls, v: Matrix) -> Matrix:
        if len(v) != 3 or any(len(r) != 3 for r in v):
            raise ValueError("K must be a 3x3 matrix")
        if v[0][0] <= 0 or v[1][1] <= 0:
            raise ValueError("K focal lengths fx = K[0][0] and fy = K[1][1] must be positive")
        if v[0][1] != 0 or v[1][0] != 0 or list(v[2]) != [0.0, 0.0, 1.0]:
            raise ValueError("K must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (no skew)")
        return v

    @field_validator("dist")
    @classmethod
    def _dist_length(cls, v: list[float]) -> list[float]:
        if len(v) not in DIST_LENGTHS:
            raise ValueError(f"dist must have {', '.join(map(str, DIST_LENGTHS))} entries "
                             f"(OpenCV order k1 k2 p1 p2 [k3 ...]), got {len(v)}")
        return v

    @field_validator("T_ref_cam")
    @classmethod
    def _t_rigid(cls, v: Matrix) -> Matrix:
        if len(v) != 4 or any(len(r) != 4 for r in v):
            raise ValueError("T_ref_cam must be a 4x4 matrix")
        try:
            as_transform(v, what="T_ref_cam")
        except ValueError as exc:  # the key is already in the message's location
            raise ValueError(str(exc).removeprefix("T_ref_cam: ")) from None
        return v


class RigFile(Strict):
    reference: str
    cameras: dict[str, CameraEntry] = Field(min_length=1)


def rig_from_dict(data: dict, path: str | Path) -> Rig:
    """Validate a parsed rig document and build the :class:`Rig`."""
    doc = validate(RigFile, data, path)
    cams = {}
    for name, e in doc.cameras.items():
        cams[name] = build(path, f"cameras.{name}", lambda n=name, e=e: CameraModel(
            n, e.size, np.array(e.K), np.array(e.dist), np.array(e.T_ref_cam)))
    return build(path, "reference", lambda: Rig(doc.reference, cams))


def load_rig(path: str | Path, *, names: Names = None, size: Size = None) -> Rig:
    """Read and validate a rig file; raises ``ConfigError`` naming file and key.

    A ``.toml`` file is our rig format; any other file (or a ROS pair's folder) is judged
    from its content: our TOML, or an OpenCV, ROS or Kalibr camera file
    (:func:`oralnav.config.camera_files.load_camera_file`, which ``names`` and ``size``
    go to: the cameras' names in file order, and the image size where the file lacks it).
    """
    fmt = detect_format(path)
    if fmt != "toml":
        return load_camera_file(path, names=names, size=size, fmt=fmt)
    if names is not None or size is not None:
        raise ValueError(f"{path}: a rig TOML names and sizes its cameras itself; names and "
                         "size are for OpenCV, ROS and Kalibr files")
    return rig_from_dict(read_toml(path), path)


#: The shipped stereo endoscope that the randomised needle trials are seen by (seed 002's
#: cell; :func:`oralnav.sim.world.needle_trials.trial_scene` takes it as ``rig``).
TRIAL_RIG_FILE = Path(str(resources.files("oralnav.config").joinpath(
    "rigs/stereo_endoscope.toml")))


@functools.lru_cache(maxsize=4)
def _shared_rig(path: str) -> Rig:
    return load_rig(path)


def trial_rig(path: str | Path = TRIAL_RIG_FILE) -> Rig:
    """The needle trials' rig, read once per file and process: every trial cell shares one
    :class:`Rig`, so their renderers share its cameras' ray maps (sim/world/render.py)."""
    return _shared_rig(str(Path(path).resolve()))


def rig_to_dict(rig: Rig) -> dict:
    return {"reference": rig.reference,
            "cameras": {n: {"size": list(c.size), "K": c.K.tolist(), "dist": c.dist.tolist(),
                            "T_ref_cam": c.T_ref_cam.tolist()} for n, c in rig.cameras.items()}}


def save_rig(rig: Rig, path: str | Path) -> None:
    """Write ``rig`` atomically in the rig format (the old file stays on any error).

    Raises ``ConfigError`` naming ``path`` when the rig cannot be written as a valid rig
    file (a non-finite value, a camera the format cannot hold); ``OSError`` on I/O failure.
    """
    text = build(path, "", lambda: "# oralnav rig: lengths in metres, intrinsics in pixels\n"
                 + dump_toml(rig_to_dict(rig)))
    # Re-read what we are about to write: a file we cannot load back is never written.
    rig_from_dict(build(path, "", lambda: tomllib.loads(text)), path)
    atomic_write_text(path, text)


def save_rig_as(rig: Rig, path: str | Path, fmt: str = "toml") -> None:
    """Write ``rig`` atomically as ``fmt``, one of :data:`FORMATS`:

    - ``"toml"``: our rig file (:func:`save_rig`);
    - ``"opencv"``: an OpenCV FileStorage file, YAML, XML or JSON by ``path``'s suffix
      (``.yml``/``.yaml``, ``.xml``, ``.json``); one or two cameras;
    - ``"ros"``: ROS camera_info YAML; one camera: ``path`` is the ``.yaml`` file; a stereo
      pair: ``path`` is a folder (created if missing) that gets ``left.yaml`` (the
      reference) and ``right.yaml``;
    - ``"kalibr"``: a Kalibr camchain ``.yaml``, any number of cameras.

    Every format but ours needs the rig's reference to be one of its cameras. Raises
    ``ConfigError`` naming ``path`` when the format cannot hold the rig (the message says
    what), ``ValueError`` on an unknown ``fmt``, ``OSError`` on I/O failure. Every file is
    read back before it is written.
    """
    if fmt not in FORMATS:
        raise ValueError(f"fmt must be one of {', '.join(FORMATS)}, got {fmt!r}")
    if fmt == "toml":
        save_rig(rig, path)
    else:
        save_camera_file(rig, path, fmt)
