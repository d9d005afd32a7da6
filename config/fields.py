"""The marker-field file: ChArUco fields and the surfaces they are stuck on, and flat
calibration targets (chessboards, circle grids, ArUco grid boards, ChArUco boards of a
custom dictionary).

See docs/formats.md. Lengths in metres. :func:`load_fields` gives the fields the tracker
follows and refuses a file holding a calibration-only target; :func:`load_targets` gives
every entry, for ``oralnav calibrate camera`` and ``stereo``.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated, Literal

import cv2
import numpy as np
from pydantic import Field, field_validator, model_validator

from oralnav.control.calibration.targets import (
    ArucoGrid,
    CharucoTarget,
    Chessboard,
    CircleGrid,
    Target,
)
from oralnav.control.vision.markers import (
    CylinderSurface,
    MarkerField,
    PlaneSurface,
    PointsSurface,
    aruco_dictionary,
)

from .errors import ConfigError
from .loader import (
    Float,
    Int,
    Strict,
    build,
    dump_toml,
    load_file,
    read_toml,
    resolve_file,
    validate,
)

Length = Annotated[Float, Field(gt=0, le=1.0)]
Count = Annotated[Int, Field(ge=2, le=200)]
Family = Literal["charuco", "chessboard", "circles", "asymmetric_circles", "aruco_grid"]

#: The keys each family takes besides ``family`` (the schema holds them all; a key of
#: another family is reported on itself), and those it needs. A ChArUco or ArUco-grid
#: entry also needs ``dictionary`` or ``dictionary_file``.
KEYS: dict[str, tuple[str, ...]] = {
    "charuco": ("dictionary", "dictionary_file", "squares", "square", "marker", "first_id",
                "surface"),
    "chessboard": ("inner_corners", "square"),
    "circles": ("grid", "spacing"),
    "asymmetric_circles": ("grid", "spacing"),
    "aruco_grid": ("dictionary", "dictionary_file", "markers", "marker", "separation",
                   "first_id"),
}
REQUIRED: dict[str, tuple[str, ...]] = {
    "charuco": ("squares", "square", "marker"),
    "chessboard": ("inner_corners", "square"),
    "circles": ("grid", "spacing"),
    "asymmetric_circles": ("grid", "spacing"),
    "aruco_grid": ("markers", "marker", "separation"),
}


class SurfaceEntry(Strict):
    kind: Literal["plane", "cylinder", "points"] = "plane"
    radius: Length | None = None
    file: str | None = None

    @model_validator(mode="after")
    def _keys_for_kind(self) -> SurfaceEntry:
        if self.kind == "cylinder" and self.radius is None:
            raise ValueError("a cylinder surface needs radius (metres)")
        if self.kind != "cylinder" and self.radius is not None:
            raise ValueError(f"radius applies to cylinders only, not to a {self.kind}")
        if self.kind == "points" and not self.file:
            raise ValueError("a points surface needs file (a CSV: corner_id,x,y,z)")
        if self.kind != "points" and self.file is not None:
            raise ValueError(f"file applies to points surfaces only, not to a {self.kind}")
        return self


class FieldEntry(Strict):
    """One ``[fields.NAME]`` entry, every family's keys; :func:`_check_keys` then checks
    which the family takes and needs."""

    family: Family = "charuco"
    dictionary: str | None = None
    dictionary_file: str | None = None
    squares: tuple[Count, Count] | None = None
    square: Length | None = None
    marker: Length | None = None
    first_id: Annotated[Int, Field(ge=0)] = 0
    surface: SurfaceEntry = SurfaceEntry()
    # OpenCV's chessboard detectors need at least 3 inner corners each way
    inner_corners: tuple[Annotated[Int, Field(ge=3, le=200)],
                         Annotated[Int, Field(ge=3, le=200)]] | None = None
    grid: tuple[Count, Count] | None = None
    spacing: Length | None = None
    markers: tuple[Annotated[Int, Field(ge=1, le=100)],
                   Annotated[Int, Field(ge=1, le=100)]] | None = None
    separation: Length | None = None

    @field_validator("dictionary")
    @classmethod
    def _known_dictionary(cls, v: str | None) -> str | None:
        if v is not None:
            aruco_dictionary(v)  # a MarkerFieldError (a ValueError) names OpenCV's ones
        return v


class FieldsFile(Strict):
    fields: dict[str, FieldEntry] = Field(min_length=1)


def read_corner_table(path: Path) -> dict[int, tuple[float, float, float]]:
    """Read a ``corner_id,x,y,z`` CSV (field frame, metres)."""
    try:
        # utf-8-sig: spreadsheets often start a CSV with a byte-order mark
        with path.open(newline="", encoding="utf-8-sig") as f:
            rows = list(csv.reader(f))
    except OSError as exc:
        raise ConfigError(path, "", f"cannot read corner table: {exc.strerror or exc}") from None
    except (UnicodeDecodeError, csv.Error) as exc:
        raise ConfigError(path, "", f"not a UTF-8 CSV corner table: {exc}") from None
    if not rows or [c.strip() for c in rows[0]] != ["corner_id", "x", "y", "z"]:
        raise ConfigError(path, "", "first line must be the header corner_id,x,y,z")
    out: dict[int, tuple[float, float, float]] = {}
    for n, row in enumerate(rows[1:], start=2):
        if not row or all(not c.strip() for c in row):
            continue
        try:
            cid = int(row[0])
            xyz = tuple(float(v) for v in row[1:])
        except ValueError:
            raise ConfigError(path, f"line {n}", f"not an id and three numbers: {row}") from None
        if len(xyz) != 3:
            raise ConfigError(path, f"line {n}", f"expected 4 columns, got {len(row)}")
        if not all(math.isfinite(v) for v in xyz):
            raise ConfigError(path, f"line {n}", f"corner {cid}: x, y, z must be finite: {row}")
        if cid in out:
            raise ConfigError(path, f"line {n}", f"corner {cid} listed twice")
        out[cid] = xyz  # type: ignore[assignment]
    return out


def read_dictionary(path: str | Path) -> cv2.aruco.Dictionary:
    """An ArUco dictionary from OpenCV's dictionary file (YAML, XML or JSON, as
    ``cv2.aruco.Dictionary.writeDictionary`` writes it and ``readDictionary`` reads it):
    ``nmarkers``, ``markersize`` (bits per side), optional ``maxCorrectionBits``, and
    ``marker_0`` .. ``marker_<nmarkers-1>``, each marker's bits row by row as a string of
    ``0`` and ``1``. Checked here first: OpenCV's reader takes a string of the wrong length
    without a word."""
    path = Path(path)
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as exc:
        # the Python binding wraps a parser's cv2.error in a SystemError
        exc = exc.__cause__ or exc
        why = str(exc).strip().splitlines()[-1] if str(exc).strip() else repr(exc)
        raise ConfigError(path, "", f"not an OpenCV dictionary file (YAML, XML or JSON): "
                                    f"{why}") from None
    try:
        if not fs.isOpened():
            raise ConfigError(path, "", "cannot open it as an OpenCV dictionary file "
                                        "(YAML, XML or JSON)")
        root = fs.root()

        def whole(key: str, least: int, most: int, default: int | None = None) -> int:
            node = root.getNode(key)
            if node.empty() or node.isNone():
                if default is not None:
                    return default
                raise ConfigError(path, key, "missing: an OpenCV dictionary file gives "
                                             "nmarkers, markersize and marker_0 ..")
            if not node.isInt() or not least <= int(node.real()) <= most:
                raise ConfigError(path, key, f"must be a whole number {least}..{most}")
            return int(node.real())

        n = whole("nmarkers", 1, 100_000)
        side = whole("markersize", 2, 16)
        whole("maxCorrectionBits", 0, side * side, default=0)
        for i in range(n):
            node = root.getNode(f"marker_{i}")
            bits = node.string() if node.isString() else None
            if bits is None or len(bits) != side * side or set(bits) - {"0", "1"}:
                raise ConfigError(path, f"marker_{i}", f"must be a string of {side * side} "
                                  f"bits (0 or 1), a {side}x{side} marker row by row")
        dic = cv2.aruco.Dictionary()
        if not dic.readDictionary(root):
            raise ConfigError(path, "", "OpenCV's readDictionary refused it")
    finally:
        fs.release()
    return dic


def _check_keys(path: str | Path, name: str, e: FieldEntry) -> None:
    """The keys the entry's family takes and needs, each problem named at its key."""
    key = f"fields.{name}"
    takes = KEYS[e.family]
    for k in FieldEntry.model_fields:
        if k in e.model_fields_set and k != "family" and k not in takes:
            raise ConfigError(path, f"{key}.{k}", f"does not apply to a {e.family} entry, "
                                                  f"which takes {', '.join(takes)}")
    for k in REQUIRED[e.family]:
        if getattr(e, k) is None:
            raise ConfigError(path, f"{key}.{k}", f"Field required (a {e.family} entry "
                                                  f"needs {', '.join(REQUIRED[e.family])})")
    if "dictionary" in takes:
        if e.dictionary is None and e.dictionary_file is None:
            raise ConfigError(path, f"{key}.dictionary",
                              "Field required: give dictionary (an OpenCV predefined "
                              "dictionary's name) or dictionary_file (a dictionary file)")
        if e.dictionary is not None and e.dictionary_file is not None:
            raise ConfigError(path, f"{key}.dictionary_file",
                              "give dictionary or dictionary_file, not both")


def _dictionary(path: str | Path, name: str, e: FieldEntry
                ) -> tuple[str, cv2.aruco.Dictionary | None]:
    """The entry's dictionary: its label (an OpenCV name, or the file as written) and the
    dictionary read from ``dictionary_file`` (``None`` for a predefined one)."""
    if e.dictionary_file is None:
        return str(e.dictionary), None
    return e.dictionary_file, load_file(path, f"fields.{name}.dictionary_file",
                                        e.dictionary_file, read_dictionary)


def _check_ids(path: str | Path, name: str, e: FieldEntry, label: str,
               custom: cv2.aruco.Dictionary | None, count: int, what: str) -> None:
    size = (custom if custom is not None else aruco_dictionary(label)).bytesList.shape[0]
    if e.first_id + count > size:
        raise ConfigError(path, f"fields.{name}.first_id",
                          f"{what} has {count} markers, so ids {e.first_id}.."
                          f"{e.first_id + count - 1} overflow {label}, which has ids "
                          f"0..{size - 1}; first_id must be at most {size - count}")


def _check_entry(path: str | Path, name: str, e: FieldEntry, label: str,
                 custom: cv2.aruco.Dictionary | None) -> None:
    """A ChArUco entry's cross-key checks, each reported at the key to change.
    ``MarkerField`` repeats them; doing them here first names ``[fields.NAME] KEY`` rather
    than the field."""
    key = f"fields.{name}"
    nx, ny = e.squares
    if e.marker >= e.square:
        raise ConfigError(path, f"{key}.marker",
                          f"marker side ({e.marker} m) must be smaller than square ({e.square} m)")
    _check_ids(path, name, e, label, custom, nx * ny // 2, f"a {nx}x{ny} board")
    width = nx * e.square
    if e.surface.kind == "cylinder" and width / e.surface.radius > 2 * np.pi:
        raise ConfigError(path, f"{key}.surface.radius",
                          f"radius {e.surface.radius} m is too small for the sheet: a {width:g} m "
                          f"wide sheet would wrap {np.degrees(width / e.surface.radius):.0f} deg "
                          f"(at most 360); radius must be >= {width / (2 * np.pi):.6f} m")


def _points_surface(path: str | Path, name: str, e: FieldEntry) -> PointsSurface:
    key = f"fields.{name}.surface.file"
    table = resolve_file(path, key, e.surface.file)
    points = read_corner_table(table)
    nx, ny = e.squares
    n = (nx - 1) * (ny - 1)
    bad = sorted(i for i in points if not 0 <= i < n)
    if bad:
        raise ConfigError(path, key, f"{table.name}: corner ids {bad[:5]} are outside 0..{n - 1} "
                                     f"of a {nx}x{ny} board")
    if len(points) < 4:
        raise ConfigError(path, key, f"{table.name}: a points surface needs at least 4 corners, "
                                     f"got {len(points)}")
    return PointsSurface(points=points, source=str(table))


def _entries(data: dict, path: str | Path) -> dict[str, FieldEntry]:
    doc = validate(FieldsFile, data, path)
    for name, e in doc.fields.items():
        _check_keys(path, name, e)
    return doc.fields


def _field(path: str | Path, name: str, e: FieldEntry) -> MarkerField:
    """A ChArUco entry of a predefined dictionary as the tracker's field."""
    _check_entry(path, name, e, str(e.dictionary), None)
    s = e.surface
    if s.kind == "cylinder":
        surface = CylinderSurface(radius=s.radius)
    elif s.kind == "points":
        surface = _points_surface(path, name, e)
    else:
        surface = PlaneSurface()
    return build(path, f"fields.{name}", lambda: MarkerField(
        name=name, dictionary=e.dictionary, squares=e.squares, square=e.square,
        marker=e.marker, first_id=e.first_id, surface=surface))


def _target(path: str | Path, name: str, e: FieldEntry) -> MarkerField | Target:
    """Any entry as a calibration target: a ChArUco field of a predefined dictionary stays
    the tracker's field (found by the tracker's own detector)."""
    key = f"fields.{name}"
    if e.family == "chessboard":
        return build(path, f"{key}.inner_corners",
                     lambda: Chessboard(name, e.inner_corners, e.square))
    if e.family in ("circles", "asymmetric_circles"):
        return build(path, f"{key}.grid", lambda: CircleGrid(
            name, e.grid, e.spacing, asymmetric=e.family == "asymmetric_circles"))
    label, custom = _dictionary(path, name, e)
    if e.family == "aruco_grid":
        nx, ny = e.markers
        _check_ids(path, name, e, label, custom, nx * ny, f"a {nx}x{ny} grid")
        return build(path, f"{key}.markers", lambda: ArucoGrid(
            name, e.markers, e.marker, e.separation, label, e.first_id, custom))
    if custom is None:
        return _field(path, name, e)
    _check_entry(path, name, e, label, custom)
    if e.surface.kind != "plane":
        raise ConfigError(path, f"{key}.surface.kind",
                          "a board of a dictionary file is a calibration target and must be "
                          "flat (plane)")
    return build(path, key, lambda: CharucoTarget(name, e.squares, e.square, e.marker, label,
                                                  custom, e.first_id))


def _check_shared_ids(path: str | Path, fields: dict[str, MarkerField]) -> None:
    """Two fields printing the same marker ids from one dictionary cannot be told apart."""
    names = list(fields)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            fa, fb = fields[a], fields[b]
            if fa.dictionary == fb.dictionary:
                lo = max(fa.first_id, fb.first_id)
                hi = min(fa.first_id + fa.marker_count, fb.first_id + fb.marker_count) - 1
                if lo <= hi:
                    raise ConfigError(path, f"fields.{b}.first_id",
                                      f"marker ids {lo}..{hi} of {fa.dictionary} are also used "
                                      f"by field {a!r}; fields must not share ids")


def fields_from_dict(data: dict, path: str | Path) -> dict[str, MarkerField]:
    """Validate a parsed fields document and build the :class:`MarkerField` objects the
    tracker follows; an entry that is a calibration target only is refused."""
    entries = _entries(data, path)
    for name, e in entries.items():
        if e.family != "charuco":
            raise ConfigError(path, f"fields.{name}.family",
                              f"a {e.family} entry is a calibration target only (oralnav "
                              "calibrate camera and stereo); the tracker follows charuco "
                              "fields")
        if e.dictionary_file is not None:
            raise ConfigError(path, f"fields.{name}.dictionary_file",
                              "a dictionary file serves calibration only (oralnav calibrate "
                              "camera and stereo); a tracked field names one of OpenCV's "
                              "predefined dictionaries")
    fields = {name: _field(path, name, e) for name, e in entries.items()}
    _check_shared_ids(path, fields)
    return fields


def load_fields(path: str | Path) -> dict[str, MarkerField]:
    """Read and validate a marker-field file for tracking; raises ``ConfigError`` naming
    file and key (also for an entry that is a calibration target only)."""
    return fields_from_dict(read_toml(path), path)


def targets_from_dict(data: dict, path: str | Path) -> dict[str, MarkerField | Target]:
    """Validate a parsed fields document and build every entry as a calibration target
    (ChArUco fields of a predefined dictionary as :class:`MarkerField`)."""
    entries = _entries(data, path)
    out = {name: _target(path, name, e) for name, e in entries.items()}
    _check_shared_ids(path, {n: f for n, f in out.items() if isinstance(f, MarkerField)})
    return out


def load_targets(path: str | Path) -> dict[str, MarkerField | Target]:
    """Read and validate a marker-field file for calibration: every family; raises
    ``ConfigError`` naming file and key."""
    return targets_from_dict(read_toml(path), path)


def fields_to_files(fields: Sequence[MarkerField], name: str = "fields.toml") -> dict[str, str]:
    """``fields`` written as a marker-field file ``name`` and the corner tables its points
    surfaces name (``<field>.corners.csv`` beside it): file name -> text, in the field
    order given. :func:`load_fields` reads them back as equal fields: every float is
    written with the digits that round-trip it exactly (a session recording rebuilds its
    trackers from these files, docs/recording.md)."""
    doc: dict[str, dict] = {}
    files: dict[str, str] = {}
    for f in fields:
        s = f.surface
        entry: dict = {"family": f.family, "dictionary": f.dictionary,
                       "squares": list(f.squares), "square": float(f.square),
                       "marker": float(f.marker), "first_id": int(f.first_id)}
        if isinstance(s, CylinderSurface):
            entry["surface"] = {"kind": "cylinder", "radius": float(s.radius)}
        elif isinstance(s, PointsSurface):
            table = f"{f.name}.corners.csv"
            entry["surface"] = {"kind": "points", "file": table}
            rows = [f"{int(i)},{float(x)!r},{float(y)!r},{float(z)!r}"
                    for i, (x, y, z) in sorted(s.points.items())]
            files[table] = "corner_id,x,y,z\n" + "\n".join(rows) + "\n"
        else:
            entry["surface"] = {"kind": "plane"}
        doc[f.name] = entry
    files = {name: "# oralnav marker fields: lengths in metres\n"
             + dump_toml({"fields": doc}), **files}
    return files
