"""The marker-field file: ChArUco fields and the surfaces they are stuck on.

See docs/formats.md. Lengths in metres.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from oralnav.control.vision.markers import (
    CylinderSurface,
    MarkerField,
    PlaneSurface,
    PointsSurface,
    aruco_dictionary,
)

from .errors import ConfigError
from .loader import Float, Int, Strict, build, dump_toml, read_toml, resolve_file, validate

Length = Annotated[Float, Field(gt=0, le=1.0)]


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
    family: Literal["charuco"] = "charuco"
    dictionary: str
    squares: tuple[Annotated[Int, Field(ge=2, le=200)], Annotated[Int, Field(ge=2, le=200)]]
    square: Length
    marker: Length
    first_id: Annotated[Int, Field(ge=0)] = 0
    surface: SurfaceEntry = SurfaceEntry()

    @field_validator("dictionary")
    @classmethod
    def _known_dictionary(cls, v: str) -> str:
        aruco_dictionary(v)  # a MarkerFieldError (a ValueError) names OpenCV's dictionaries
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


def _check_entry(path: str | Path, name: str, e: FieldEntry) -> None:
    """The field's cross-key checks, each reported at the key to change. ``MarkerField``
    repeats them; doing them here first names ``[fields.NAME] KEY`` rather than the field."""
    key = f"fields.{name}"
    nx, ny = e.squares
    if e.marker >= e.square:
        raise ConfigError(path, f"{key}.marker",
                          f"marker side ({e.marker} m) must be smaller than square ({e.square} m)")
    count = nx * ny // 2
    size = aruco_dictionary(e.dictionary).bytesList.shape[0]
    if e.first_id + count > size:
        raise ConfigError(path, f"{key}.first_id",
                          f"a {nx}x{ny} board has {count} markers, so ids {e.first_id}.."
                          f"{e.first_id + count - 1} overflow {e.dictionary}, which has ids "
                          f"0..{size - 1}; first_id must be at most {size - count}")
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


def fields_from_dict(data: dict, path: str | Path) -> dict[str, MarkerField]:
    """Validate a parsed fields document and build its :class:`MarkerField` objects."""
    doc = validate(FieldsFile, data, path)
    fields: dict[str, MarkerField] = {}
    for name, e in doc.fields.items():
        _check_entry(path, name, e)
        s = e.surface
        if s.kind == "cylinder":
            surface = CylinderSurface(radius=s.radius)
        elif s.kind == "points":
            surface = _points_surface(path, name, e)
        else:
            surface = PlaneSurface()
        fields[name] = build(path, f"fields.{name}", lambda n=name, e=e, surface=surface:
                             MarkerField(name=n, dictionary=e.dictionary, squares=e.squares,
                                         square=e.square, marker=e.marker,
                                         first_id=e.first_id, surface=surface))
    # Two fields printing the same marker ids from one dictionary cannot be told apart.
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
    return fields


def load_fields(path: str | Path) -> dict[str, MarkerField]:
    """Read and validate a marker-field file; raises ``ConfigError`` naming file and key."""
    return fields_from_dict(read_toml(path), path)


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
