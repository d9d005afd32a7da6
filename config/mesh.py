"""Triangle meshes of the oral cavity: loading, checking and saving user meshes.

The planning layer (the surrogate model of the planning seed, section 3) is fitted to a
triangle mesh of the patient's oral cavity, given in the opener's Center frame. Scanners
and CAD tools write STL, PLY or OBJ, in metres or (more often) millimetres and without
saying which, so :func:`load_mesh` reads the three through trimesh, decides the unit from
the mesh's size when asked to (an oral cavity is 0.02-0.3 m across) and converts to
metres. :func:`check_mesh` then repairs what is harmless (duplicate vertices are merged,
zero-area faces removed, both counted in the report) and refuses what would make slicing
or distance queries wrong: no faces, non-finite vertices, non-manifold edges (more than
two faces on one edge). An open mouth is expected, so boundary edges and a mesh that is
not watertight are reported, not refused.

Errors are :class:`MeshError` (a :class:`~oralnav.config.errors.ConfigError`) naming the
file (or the in-memory mesh's ``source``) and what is wrong. :func:`save_mesh` writes
atomically, so a failed save keeps the previous file.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from .errors import ConfigError
from .loader import atomic_write_bytes

__all__ = ["FORMATS", "LENGTH_UNITS", "LoadedMesh", "MeshError", "MeshReport", "check_mesh",
           "load_mesh", "save_mesh"]

#: File extensions read and written, with trimesh's name for the format.
FORMATS = {".stl": "stl", ".ply": "ply", ".obj": "obj"}

#: Length units a mesh file may be in, with their size in metres.
LENGTH_UNITS = {"m": 1.0, "mm": 1e-3}

# An oral cavity's largest bounding-box side, metres: the range "auto" accepts, and the
# wider range an explicitly given unit must land in.
_AUTO_RANGE = (0.02, 0.3)
_PLAUSIBLE_RANGE = (0.01, 0.5)
# Binary STL layout: an 80-byte header and a uint32 triangle count, then 50 bytes a
# triangle (normal and three vertices as 12 float32, a 2-byte attribute word).
_STL_HEADER = 84
_STL_TRIANGLE = 50
# Triangles less tall than this (metres) have no area worth keeping.
_DEGENERATE_HEIGHT = 1e-9


class MeshError(ConfigError):
    """A mesh file (or in-memory mesh) cannot be used: unreadable, empty, non-finite,
    non-manifold, or of an implausible size. ``key`` is ``""`` for the file as a whole or
    the part at fault (``"units"``, ``"faces"``, ``"vertices"``, ``"edges"``)."""


@dataclass(frozen=True)
class MeshReport:
    """What :func:`check_mesh` found, after its repairs.

    ``faces`` and ``vertices`` are counts; ``watertight`` means every edge has exactly two
    faces; ``boundary_edges`` counts edges with one face (an open mouth has a loop of
    them); ``components`` counts connected parts (the wall, each tooth...);
    ``extent_m`` (3,) is the bounding box's size and ``bounds_m`` its min and max corners,
    metres; ``removed_degenerate`` counts zero-area faces removed and ``merged_vertices``
    duplicate vertices merged.
    """

    faces: int
    vertices: int
    watertight: bool
    boundary_edges: int
    components: int
    extent_m: tuple[float, float, float]
    bounds_m: tuple[tuple[float, float, float], tuple[float, float, float]]
    removed_degenerate: int = 0
    merged_vertices: int = 0

    def summary(self) -> str:
        """One line for the command line, lengths in millimetres."""
        ex = " x ".join(f"{v * 1e3:.1f}" for v in self.extent_m)
        closed = "watertight" if self.watertight else f"open ({self.boundary_edges} " \
            "boundary edges)"
        return (f"{self.faces} faces, {self.vertices} vertices, {self.components} "
                f"components, {closed}, extent {ex} mm, {self.removed_degenerate} degenerate "
                f"faces removed, {self.merged_vertices} duplicate vertices merged")


@dataclass(frozen=True, eq=False)
class LoadedMesh:
    """A mesh read by :func:`load_mesh`: ``mesh`` in metres (Center frame as the file gives
    it), the file's ``path``, the ``units`` it was read in (``"m"`` or ``"mm"``) and the
    check's ``report``."""

    mesh: trimesh.Trimesh
    path: Path
    units: str
    report: MeshReport


def _require_faces(mesh: trimesh.Trimesh, source: str | Path) -> None:
    if len(mesh.faces) == 0:
        raise MeshError(source, "faces", "the mesh has no faces (no triangles could be read)")


def _require_finite(mesh: trimesh.Trimesh, source: str | Path) -> None:
    bad = ~np.all(np.isfinite(mesh.vertices), axis=1)
    if bad.any():
        raise MeshError(source, "vertices", f"{int(bad.sum())} vertices are not finite (nan "
                        f"or inf), e.g. vertex {int(np.flatnonzero(bad)[0])}")


def _mm(p: np.ndarray) -> str:
    return "(" + ", ".join(f"{v * 1e3:.3f}" for v in p) + ") mm"


def check_mesh(mesh: trimesh.Trimesh, source: str | Path = "mesh") -> MeshReport:
    """Check ``mesh`` (metres) for planning and repair what is harmless, in place.

    Duplicate vertices are merged and zero-area faces removed (then unused vertices),
    changing ``mesh`` as trimesh's own repairs do; both are counted in the report. Raises
    :class:`MeshError` naming ``source`` when the mesh has no faces, a vertex is not
    finite, every face is degenerate, or an edge is shared by more than two faces (the
    count and one such edge's end points, in mm). On a refusal the mesh may already be
    partly repaired.
    """
    _require_faces(mesh, source)
    _require_finite(mesh, source)
    before = len(mesh.vertices)
    # position only: a scan's per-corner normals or UVs must not keep a seam open
    mesh.merge_vertices(merge_tex=True, merge_norm=True)
    merged = before - len(mesh.vertices)
    faces = np.asarray(mesh.faces)
    keep = mesh.nondegenerate_faces(height=_DEGENERATE_HEIGHT)
    keep &= (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) \
        & (faces[:, 2] != faces[:, 0])
    removed = int((~keep).sum())
    if not keep.any():
        raise MeshError(source, "faces", f"all {len(faces)} faces are degenerate (zero area)")
    if removed:
        mesh.update_faces(keep)
    mesh.remove_unreferenced_vertices()

    edges, counts = np.unique(np.sort(mesh.edges, axis=1), axis=0, return_counts=True)
    over = counts > 2
    if over.any():
        a, b = edges[np.flatnonzero(over)[0]]
        n = int(over.sum())
        raise MeshError(source, "edges", f"{n} non-manifold edge{'s' if n != 1 else ''} "
                        f"(shared by more than two faces), e.g. {_mm(mesh.vertices[a])} - "
                        f"{_mm(mesh.vertices[b])}; repair the mesh (e.g. remove duplicate "
                        "or internal faces) and export it again")
    boundary = int((counts == 1).sum())
    lo, hi = mesh.bounds
    return MeshReport(
        faces=len(mesh.faces), vertices=len(mesh.vertices), watertight=boundary == 0,
        boundary_edges=boundary, components=int(mesh.body_count),
        extent_m=tuple(float(v) for v in hi - lo),
        bounds_m=(tuple(float(v) for v in lo), tuple(float(v) for v in hi)),
        removed_degenerate=removed, merged_vertices=merged)


def _suffix(path: Path) -> str:
    ext = path.suffix.lower()
    if ext not in FORMATS:
        raise MeshError(path, "", f"unknown mesh format {path.suffix or '(no extension)'!r}; "
                        f"use one of {', '.join(FORMATS)}")
    return FORMATS[ext]


def _check_stl(path: Path, size: int) -> None:
    """Refuse an STL that trimesh would misread. A binary STL is an 80-byte header, a
    little-endian uint32 triangle count N and 50 bytes a triangle, 84 + 50 N bytes in all;
    when the size disagrees trimesh falls back to ASCII and fails on the bytes with an
    unrelated message (a missing optional package), so a cut-short file is named here."""
    with path.open("rb") as f:
        head = f.read(1024)
    # binary STLs hold NUL bytes (the count's high byte, the attribute words); ASCII ones
    # begin with "solid" and hold none
    if b"\x00" not in head:
        if head.lstrip()[:5].lower() == b"solid":
            try:
                path.read_bytes().decode("utf-8")
            except UnicodeDecodeError as exc:
                raise MeshError(path, "", f"an ASCII STL (it begins with 'solid') that is not "
                                f"UTF-8 text at byte {exc.start}") from None
        return  # not binary: trimesh reads it as ASCII (or finds no faces)
    if size < _STL_HEADER:
        raise MeshError(path, "", f"truncated binary STL: {size} bytes, fewer than its "
                        f"{_STL_HEADER}-byte header")
    n = int.from_bytes(head[80:84], "little")
    expected = _STL_HEADER + _STL_TRIANGLE * n
    if size < expected:
        raise MeshError(path, "", f"truncated binary STL: the header says {n} triangles "
                        f"({expected} bytes), the file holds {size} bytes "
                        f"({(size - _STL_HEADER) // _STL_TRIANGLE} whole triangles)")
    if size > expected:
        raise MeshError(path, "", f"binary STL of the wrong size: the header says {n} "
                        f"triangles ({expected} bytes), the file holds {size} bytes")


def _read(path: Path) -> trimesh.Trimesh:
    file_type = _suffix(path)
    if not path.exists():
        raise MeshError(path, "", "file not found")
    if not path.is_file():
        raise MeshError(path, "", "not a file")
    try:
        size = path.stat().st_size
        if size == 0:
            raise MeshError(path, "", "the file is empty")
        if file_type == "stl":
            _check_stl(path, size)
        loaded = trimesh.load(str(path), file_type=file_type, force="mesh", process=False)
    except MeshError:
        raise
    except OSError as exc:
        raise MeshError(path, "", f"cannot read: {exc.strerror or exc}") from None
    except Exception as exc:  # each format's loader raises its own kinds
        raise MeshError(path, "", f"cannot parse as {file_type.upper()}: {exc}") from None
    if isinstance(loaded, trimesh.Scene):  # force="mesh" already concatenates; be sure
        loaded = loaded.to_mesh()
    if not isinstance(loaded, trimesh.Trimesh):
        raise MeshError(path, "faces", f"the file holds a {type(loaded).__name__}, not "
                        "triangles")
    return loaded


def _units(path: Path, extent: float, units: str) -> str:
    """The unit to read a mesh of largest side ``extent`` (file units) in."""
    if units == "auto":
        for unit, scale in LENGTH_UNITS.items():
            if _AUTO_RANGE[0] <= extent * scale <= _AUTO_RANGE[1]:
                return unit
        raise MeshError(path, "units", "cannot tell the unit: the largest side of the "
                        f"mesh's bounding box is {extent:.6g} in the file's units, while an "
                        "oral cavity is 0.02-0.3 m (20-300 mm) across; check the file, or "
                        "pass units='m' or units='mm' explicitly")
    if units not in LENGTH_UNITS:
        raise MeshError(path, "units", f"unknown unit {units!r}; use 'auto', "
                        f"{', '.join(repr(u) for u in LENGTH_UNITS)}")
    size = extent * LENGTH_UNITS[units]
    if not _PLAUSIBLE_RANGE[0] <= size <= _PLAUSIBLE_RANGE[1]:
        likely = [u for u, s in LENGTH_UNITS.items()
                  if u != units and _PLAUSIBLE_RANGE[0] <= extent * s <= _PLAUSIBLE_RANGE[1]]
        hint = (f"the file is likely in {likely[0]}: pass units={likely[0]!r}" if likely
                else "no unit makes it plausible; check the file's scale")
        raise MeshError(path, "units", f"read in {units} the mesh is {size:.6g} m across, "
                        f"implausible for an oral cavity ({_PLAUSIBLE_RANGE[0]}-"
                        f"{_PLAUSIBLE_RANGE[1]} m); {hint}")
    return units


def load_mesh(path: str | Path, units: str = "auto") -> LoadedMesh:
    """Read an STL, PLY or OBJ mesh (a multi-part file is concatenated into one mesh),
    convert it to metres and check it (:func:`check_mesh`).

    ``units`` is ``"m"``, ``"mm"`` or ``"auto"``: auto reads a mesh whose largest
    bounding-box side is 0.02-0.3 as metres, 20-300 as millimetres, and refuses any other.
    An explicit unit must give 0.01-0.5 m. Raises :class:`MeshError` naming the file.
    """
    path = Path(path)
    mesh = _read(path)
    _require_faces(mesh, path)
    _require_finite(mesh, path)
    extent = float(np.max(mesh.extents))
    unit = _units(path, extent, units)
    if LENGTH_UNITS[unit] != 1.0:
        mesh.apply_scale(LENGTH_UNITS[unit])
    report = check_mesh(mesh, path)
    return LoadedMesh(mesh=mesh, path=path, units=unit, report=report)


def save_mesh(mesh: trimesh.Trimesh, path: str | Path, units: str = "m") -> Path:
    """Write ``mesh`` (metres) as STL, PLY or OBJ (from the extension) atomically, with
    coordinates in ``units`` (``"m"`` or ``"mm"``); returns the path.

    A temporary file in the same folder replaces ``path`` only once fully written, so a
    failure keeps the previous file. Raises :class:`MeshError` for an unknown extension or
    unit, a mesh without faces or with non-finite vertices, and ``OSError`` on I/O failure.
    """
    path = Path(path)
    file_type = _suffix(path)
    if units not in LENGTH_UNITS:
        raise MeshError(path, "units", f"unknown unit {units!r}; use "
                        f"{', '.join(repr(u) for u in LENGTH_UNITS)}")
    _require_faces(mesh, path)
    _require_finite(mesh, path)
    out = trimesh.Trimesh(np.asarray(mesh.vertices, dtype=float) / LENGTH_UNITS[units],
                          np.asarray(mesh.faces), process=False)
    data = out.export(file_type=file_type)
    atomic_write_bytes(path, data.encode("utf-8") if isinstance(data, str) else data)
    return path
