"""Text files of scikit-surgery's ArUco tracker: rigid-body tag tables and calibrations.

Rigid-body table (``reference.txt``, ``pointer.txt``, ``tag_0.txt``): one tag per line,
columns separated by whitespace::

    tag_id  centre_x centre_y centre_z  c0_x c0_y c0_z  c1_x ...  c3_x c3_y c3_z

16 numbers, lengths in millimetres, corners in OpenCV's detection order (top-left,
top-right, bottom-right, bottom-left). The centre is redundant, so it must be the mean of
the corners: a mismatch means a shifted or mistyped column. As in the peer's loader, a
13-column line (id and corners, no centre) is accepted too. Blank lines and ``#`` comments
are skipped.

Calibration (``calibration.txt``): three lines of the 3x3 intrinsic matrix K (pixels),
then one line of OpenCV distortion coefficients (k1 k2 p1 p2 k3, or any length OpenCV
accepts).

:func:`save_rigid_body` and :func:`save_calibration_txt` write both formats (atomically),
so that what the project generates reads back here and in the peer.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from oralnav.control.errors import CameraModelError, MarkerFieldError
from oralnav.control.vision.camera import DIST_LENGTHS, CameraModel
from oralnav.control.vision.markers import aruco_dictionary
from oralnav.control.vision.rigid_body import RigidBody, check_tag_corners

from .errors import ConfigError
from .loader import atomic_write_text

#: Length units a table may be written in, as metres per unit.
UNITS = {"mm": 1e-3, "cm": 1e-2, "m": 1.0}
#: The centre may sit this far from the corners' mean: this fraction of the mean side ...
CENTRE_TOL_REL = 1e-2
#: ... or this many metres, whichever is larger (rounding in the file).
CENTRE_TOL_ABS = 1e-6


def _lines(path: Path) -> list[tuple[int, list[str]]]:
    """Non-blank, comment-stripped lines of ``path`` as (line number, tokens)."""
    try:
        text = path.read_bytes().decode("utf-8-sig")
    except FileNotFoundError:
        raise ConfigError(path, "", "file not found") from None
    except OSError as exc:
        raise ConfigError(path, "", f"cannot read: {exc.strerror or exc}") from None
    except UnicodeDecodeError:
        raise ConfigError(path, "", "not UTF-8 text") from None
    out = []
    for n, line in enumerate(text.splitlines(), start=1):
        tokens = line.split("#", 1)[0].split()
        if tokens:
            out.append((n, tokens))
    return out


def _numbers(path: Path, n: int, tokens: list[str]) -> list[float]:
    values = []
    for col, tok in enumerate(tokens, start=1):
        try:
            v = float(tok)
        except ValueError:
            raise ConfigError(path, f"line {n}",
                              f"column {col} is not a number: {tok!r}") from None
        if not math.isfinite(v):
            raise ConfigError(path, f"line {n}", f"column {col} is not finite: {tok!r}")
        values.append(v)
    return values


def load_rigid_body(path: str | Path, name: str | None = None,
                    dictionary: str = "DICT_ARUCO_ORIGINAL", units: str = "mm") -> RigidBody:
    """Read a scikit-surgery rigid-body table into a :class:`RigidBody` (metres).

    Args:
        path: the table.
        name: the body's name; the file's stem by default.
        dictionary: the OpenCV dictionary its tags belong to (the file does not say).
        units: the file's length unit, ``"mm"`` (the peer's), ``"cm"`` or ``"m"``.

    Raises:
        ConfigError: naming the file and line, on an unreadable file, a line that is not
            16 (or 13) numbers, an id that is not a whole number in the dictionary, a
            centre that is not the corners' mean, a degenerate tag, a repeated id, or
            no tags at all.
        ValueError: on an unknown ``units`` or ``dictionary`` (arguments, not the file).
    """
    if units not in UNITS:
        raise ValueError(f"units must be one of {', '.join(UNITS)}, got {units!r}")
    n_ids = int(aruco_dictionary(dictionary).bytesList.shape[0])  # MarkerFieldError: ValueError
    path = Path(path)
    scale = UNITS[units]
    tags: dict[int, np.ndarray] = {}
    first_line: dict[int, int] = {}
    for n, tokens in _lines(path):
        where = f"line {n}"
        if len(tokens) not in (16, 13):
            raise ConfigError(path, where, f"expected 16 columns (tag id, centre x y z, "
                                           f"4 corners x y z), got {len(tokens)}")
        values = _numbers(path, n, tokens)
        if not values[0].is_integer() or not 0 <= values[0] < n_ids:
            raise ConfigError(path, where, f"tag id {tokens[0]!r} is not a whole number in "
                                           f"{dictionary} (0..{n_ids - 1})")
        tid = int(values[0])
        if tid in tags:
            raise ConfigError(path, where,
                              f"tag id {tid} already given on line {first_line[tid]}")
        corners = np.array(values[-12:]).reshape(4, 3) * scale
        try:
            corners = check_tag_corners(corners, f"tag {tid}")
        except MarkerFieldError as exc:
            raise ConfigError(path, where, str(exc)) from None
        if len(values) == 16:
            centre = np.array(values[1:4]) * scale
            mean = corners.mean(axis=0)
            side = float(np.linalg.norm(np.roll(corners, -1, axis=0) - corners, axis=1).mean())
            tol = max(CENTRE_TOL_ABS, CENTRE_TOL_REL * side)
            off = float(np.linalg.norm(centre - mean))
            if off > tol:
                raise ConfigError(
                    path, where,
                    f"tag {tid}: centre {tokens[1:4]} is {off / scale:.4g} {units} from the "
                    f"mean of its corners {np.round(mean / scale, 4).tolist()} (columns "
                    "shifted or mistyped?)")
        tags[tid] = corners
        first_line[tid] = n
    if not tags:
        raise ConfigError(path, "", "no tags (expected one line per tag)")
    try:
        return RigidBody(name or path.stem, dictionary, tags)
    except MarkerFieldError as exc:
        raise ConfigError(path, "", str(exc)) from None


def load_rigid_bodies(items: Iterable[RigidBody | str | Path | tuple[str, str | Path]],
                      dictionary: str = "DICT_ARUCO_ORIGINAL",
                      units: str = "mm") -> list[RigidBody]:
    """Rigid bodies from a mix of :class:`RigidBody` objects (kept as they are) and tag
    tables: a path (the body is named after the file's stem) or a ``(name, path)`` pair,
    read by :func:`load_rigid_body` with ``dictionary`` and ``units``.

    Raises:
        ConfigError: as :func:`load_rigid_body`; ValueError: an item of another kind.
    """
    out = []
    for item in items:
        if isinstance(item, RigidBody):
            out.append(item)
        elif isinstance(item, str | Path):
            out.append(load_rigid_body(item, dictionary=dictionary, units=units))
        elif (isinstance(item, tuple) and len(item) == 2 and isinstance(item[0], str)
              and isinstance(item[1], str | Path)):
            out.append(load_rigid_body(item[1], item[0], dictionary=dictionary, units=units))
        else:
            raise ValueError("a rigid body is a RigidBody, a tag-table path or a "
                             f"(name, path) pair, got {item!r}")
    return out


def load_calibration_txt(path: str | Path, size: tuple[int, int],
                         name: str = "camera") -> CameraModel:
    """Read a scikit-surgery ``calibration.txt`` into a :class:`CameraModel`.

    Args:
        path: the file: 3 lines of K (pixels), then 1 line of distortion coefficients.
        size: image ``(width, height)`` in pixels (the file does not hold it).
        name: the camera's name.

    The camera's ``T_ref_cam`` is the identity (the file holds no extrinsics).

    Raises:
        ConfigError: naming the file and line, on a wrong count of lines or numbers, a
            non-number, or intrinsics :class:`CameraModel` rejects.
    """
    path = Path(path)
    lines = _lines(path)
    if len(lines) != 4:
        raise ConfigError(path, "", f"expected 4 lines (3 of K, 1 of distortion), "
                                    f"got {len(lines)}")
    rows = []
    for n, tokens in lines[:3]:
        if len(tokens) != 3:
            raise ConfigError(path, f"line {n}", f"a row of K needs 3 numbers, got {len(tokens)}")
        rows.append(_numbers(path, n, tokens))
    n, tokens = lines[3]
    if len(tokens) not in DIST_LENGTHS:
        raise ConfigError(path, f"line {n}", f"distortion needs "
                                             f"{', '.join(map(str, DIST_LENGTHS))} numbers, "
                                             f"got {len(tokens)}")
    dist = _numbers(path, n, tokens)
    try:
        return CameraModel(name, size, np.array(rows), np.array(dist))
    except CameraModelError as exc:
        raise ConfigError(path, "", str(exc)) from None


def _row(values: Iterable[float]) -> str:
    # 10 significant digits: sub-micrometre in millimetres, exact for the shipped values
    return " ".join(f"{float(v):.10g}" for v in values)


def save_rigid_body(body: RigidBody, path: str | Path, units: str = "mm") -> Path:
    """Write ``body`` as a scikit-surgery tag table (16 columns: id, centre, 4 corners) in
    ``units`` atomically, with a comment line naming the body and its dictionary (the
    table itself does not hold it); :func:`load_rigid_body` reads it back.

    Raises ``ValueError`` for an unknown unit, ``OSError`` when the file cannot be written.
    """
    if units not in UNITS:
        raise ValueError(f"units must be one of {', '.join(UNITS)}, got {units!r}")
    scale = 1.0 / UNITS[units]
    lines = [f"# rigid body {body.name!r}: {len(body)} tags of {body.dictionary}; tag id, "
             f"centre x y z, corners 0-3 x y z ({units}; top-left, top-right, "
             "bottom-right, bottom-left)"]
    for tid, corners in body.tags.items():
        c = np.asarray(corners) * scale
        lines.append(f"{tid} " + _row([*c.mean(axis=0), *c.ravel()]))
    path = Path(path)
    atomic_write_text(path, "\n".join(lines) + "\n")
    return path


def save_calibration_txt(camera: CameraModel, path: str | Path) -> Path:
    """Write ``camera``'s intrinsics as a scikit-surgery ``calibration.txt`` atomically:
    3 lines of K, 1 of distortion (pixels). No comment line: the peer reads every line.
    The image size is not part of the format; :func:`load_calibration_txt` needs it given.
    """
    lines = [_row(row) for row in camera.K] + [_row(camera.dist)]
    path = Path(path)
    atomic_write_text(path, "\n".join(lines) + "\n")
    return path
