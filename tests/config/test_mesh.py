"""Oral-cavity mesh files: STL, PLY and OBJ read in metres or millimetres (told or
decided from the size), checked (refusals name the file and what is wrong, harmless
defects are repaired and counted) and saved atomically."""

from __future__ import annotations

import os

import numpy as np
import pytest
import trimesh

from oralnav.config.errors import ConfigError
from oralnav.config.mesh import (
    LoadedMesh,
    MeshError,
    MeshReport,
    check_mesh,
    load_mesh,
    save_mesh,
)
from oralnav.sim.world.oral_cavity import oral_cavity_mesh


@pytest.fixture(scope="module")
def cavity() -> trimesh.Trimesh:
    return oral_cavity_mesh(resolution=0.25)


def _box(extents=(0.05, 0.04, 0.08)) -> trimesh.Trimesh:
    return trimesh.creation.box(extents=extents)


def _refused(path, units="auto", key=None, *parts: str) -> MeshError:
    with pytest.raises(MeshError) as info:
        load_mesh(path, units=units)
    err = info.value
    assert isinstance(err, ConfigError) and str(err).startswith(str(path))
    if key is not None:
        assert err.key == key
    for part in parts:
        assert part in str(err), str(err)
    return err


@pytest.mark.parametrize("ext", ["stl", "ply", "obj"])
@pytest.mark.parametrize("units", ["m", "mm"])
def test_round_trip_with_auto_units(tmp_path, cavity, ext, units):
    """A mesh saved in m or mm as STL, PLY or OBJ loads back in metres, its unit decided
    from its size, with the same faces and shape."""
    path = save_mesh(cavity, tmp_path / f"cavity.{ext}", units=units)
    loaded = load_mesh(path)
    assert isinstance(loaded, LoadedMesh) and loaded.units == units and loaded.path == path
    mesh, report = loaded.mesh, loaded.report
    assert len(mesh.faces) == len(cavity.faces) == report.faces
    assert len(mesh.vertices) == len(cavity.vertices) == report.vertices
    np.testing.assert_allclose(mesh.bounds, cavity.bounds, atol=1e-7)  # STL is float32
    np.testing.assert_allclose(np.sort(mesh.vertices, axis=0), np.sort(cavity.vertices, axis=0),
                               atol=1e-7)
    assert report.components == 29 and not report.watertight and report.boundary_edges > 0
    np.testing.assert_allclose(report.extent_m, [0.055, 0.045, 0.09], atol=1e-7)
    np.testing.assert_allclose(report.bounds_m, cavity.bounds, atol=1e-7)


def test_explicit_units_and_watertight_report(tmp_path, cavity):
    """An explicit unit is used as given; a closed mesh is reported watertight."""
    closed = oral_cavity_mesh(resolution=0.25, closed_front=True)
    path = save_mesh(closed, tmp_path / "closed.ply", units="mm")
    loaded = load_mesh(path, units="mm")
    assert loaded.units == "mm" and loaded.report.watertight
    assert loaded.report.boundary_edges == 0
    np.testing.assert_allclose(loaded.mesh.bounds, closed.bounds, atol=1e-9)
    assert load_mesh(save_mesh(cavity, tmp_path / "m.obj"), units="m").units == "m"


def test_summary_is_one_line_in_mm(tmp_path, cavity):
    """The report's summary is one line with counts and the extent in millimetres."""
    report = load_mesh(save_mesh(cavity, tmp_path / "c.stl")).report
    line = report.summary()
    assert "\n" not in line and "55.0 x 45.0 x 90.0 mm" in line
    assert f"{report.faces} faces" in line and "29 components" in line and "open" in line


def test_scene_files_are_concatenated(tmp_path):
    """A file with several objects loads as one mesh holding all of them."""
    a, b = _box((0.03, 0.03, 0.03)), _box((0.02, 0.02, 0.02))
    b.apply_translation([0.05, 0.0, 0.0])
    path = tmp_path / "two.obj"
    path.write_text(trimesh.Scene({"a": a, "b": b}).export(file_type="obj"))
    loaded = load_mesh(path, units="m")
    assert loaded.report.components == 2 and loaded.report.faces == 24
    assert loaded.report.watertight


def test_degenerate_faces_and_duplicate_vertices_are_repaired(tmp_path):
    """Zero-area faces are removed and duplicate vertices merged, both counted; the rest
    of the mesh is kept."""
    box = _box()
    tri = box.vertices[box.faces]  # (12, 3, 3): every face with its own corners
    sliver = np.array([[[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.02, 0.0, 0.0]]])  # collinear
    soup = np.concatenate([tri, sliver]).reshape(-1, 3)
    mesh = trimesh.Trimesh(soup, np.arange(len(soup)).reshape(-1, 3), process=False)
    path = save_mesh(mesh, tmp_path / "soup.ply")
    report = load_mesh(path).report
    assert report.removed_degenerate == 1 and report.faces == 12
    assert report.merged_vertices == len(soup) - 8 - 3  # the sliver's corners are unique
    assert report.vertices == 8 and report.watertight


def test_check_mesh_names_its_source(cavity):
    """check_mesh works on an in-memory mesh and names the given source when it refuses."""
    report = check_mesh(cavity.copy(), "generated cavity")
    assert isinstance(report, MeshReport) and report.faces == len(cavity.faces)
    with pytest.raises(MeshError, match=r"^generated cavity: faces: .*no faces"):
        check_mesh(trimesh.Trimesh(), "generated cavity")


def test_refuses_a_missing_file(tmp_path):
    """A missing file is refused as such."""
    _refused(tmp_path / "nope.stl", "auto", "", "file not found")


def test_refuses_an_unknown_extension(tmp_path):
    """Only .stl, .ply and .obj are read (and written)."""
    path = tmp_path / "cavity.off"
    path.write_text("OFF\n0 0 0\n")
    _refused(path, "auto", "", "unknown mesh format '.off'", ".stl")
    with pytest.raises(MeshError, match="unknown mesh format"):
        save_mesh(_box(), tmp_path / "cavity.glb")


@pytest.mark.parametrize("ext", ["stl", "ply", "obj"])
def test_refuses_an_empty_file(tmp_path, ext):
    """An empty file is refused as empty."""
    path = tmp_path / f"empty.{ext}"
    path.write_bytes(b"")
    _refused(path, "auto", "", "empty")


def test_refuses_an_unparseable_file(tmp_path):
    """A file that is not a mesh is refused: a parse error, or no triangles read."""
    ply = tmp_path / "junk.ply"
    ply.write_bytes(b"this is not a ply file\x00\x01")
    _refused(ply, "auto", "", "cannot parse as PLY")
    stl = tmp_path / "junk.stl"
    stl.write_bytes(b"garbage")
    _refused(stl, "auto", "faces", "no faces")


def test_refuses_a_truncated_binary_stl_with_its_sizes(tmp_path, monkeypatch):
    """issue 30: a binary STL cut short (or of the wrong size) is refused saying so, with
    the triangle count its header gives and the bytes the file holds, without reaching
    trimesh's ASCII fallback (which needs the optional charset_normalizer)."""
    import sys

    monkeypatch.setitem(sys.modules, "charset_normalizer", None)  # as if not installed
    whole = save_mesh(_box(), tmp_path / "whole.stl").read_bytes()  # 12 triangles
    assert len(whole) == 84 + 50 * 12
    cut = tmp_path / "cut.stl"
    cut.write_bytes(whole[:-70])
    _refused(cut, "auto", "", "truncated binary STL", "12 triangles", "684 bytes",
             "614 bytes")
    cut.write_bytes(whole[:40])
    _refused(cut, "auto", "", "truncated binary STL", "40 bytes", "84-byte header")
    cut.write_bytes(whole + b"\0\0")
    _refused(cut, "auto", "", "wrong size", "686 bytes")
    ascii_stl = tmp_path / "ascii.stl"
    ascii_stl.write_bytes(_box().export(file_type="stl_ascii").encode() + b"\xff")
    _refused(ascii_stl, "auto", "", "ASCII STL", "not UTF-8")


def test_refuses_a_file_without_faces(tmp_path):
    """Vertices alone (a point cloud) are not a mesh."""
    path = tmp_path / "points.obj"
    path.write_text("v 0 0 0\nv 0.05 0 0\nv 0 0.05 0\n")
    _refused(path, "auto", "faces", "no faces")


def test_refuses_non_finite_vertices(tmp_path):
    """A nan or inf coordinate is refused, counted."""
    path = tmp_path / "nan.obj"
    path.write_text("v 0 0 0\nv 0.05 0 0\nv 0 nan 0\nv 0 0 inf\nf 1 2 3\nf 1 2 4\n")
    _refused(path, "auto", "vertices", "2 vertices are not finite")


def test_refuses_non_manifold_edges(tmp_path):
    """A third face on an edge is refused, counted, with the edge's end points in mm."""
    box = _box()
    a, b = box.faces[0][:2]
    extra = len(box.vertices)
    mesh = trimesh.Trimesh(np.vstack([box.vertices, [[0.0, 0.0, 0.1]]]),
                           np.vstack([box.faces, [[a, b, extra]]]), process=False)
    for ext in ("stl", "obj"):
        path = save_mesh(mesh, tmp_path / f"fin.{ext}", units="mm")
        err = _refused(path, "auto", "edges", "1 non-manifold edge ",
                       "shared by more than two faces")
        corners = {f"({', '.join(f'{v * 1e3:.3f}' for v in box.vertices[i])}) mm"
                   for i in (a, b)}
        assert all(c in str(err) for c in corners), str(err)


def test_refuses_all_degenerate_faces(tmp_path):
    """A mesh whose every face has zero area is refused."""
    path = tmp_path / "flat.obj"
    path.write_text("v 0 0 0\nv 0.02 0 0\nv 0.05 0 0\nv 0.05 0.05 0.05\n"
                    "f 1 2 3\nf 1 3 2\n")
    _refused(path, "auto", "faces", "all 2 faces are degenerate")


def test_refuses_a_mesh_1000x_too_large(tmp_path, cavity):
    """A mesh a thousand times too large is refused: auto names the extent and asks for
    an explicit unit; an explicit unit names the size in metres."""
    big = cavity.copy()
    big.apply_scale(1000.0)
    path = save_mesh(big, tmp_path / "big.stl", units="mm")  # 90 000 in the file
    _refused(path, "auto", "units", "bounding box is 90000 in the file's units",
             "pass units='m' or units='mm' explicitly")
    _refused(path, "mm", "units", "read in mm the mesh is 90 m across", "implausible")


def test_refuses_a_mesh_1000x_too_small(tmp_path, cavity):
    """A mesh a thousand times too small is refused, auto and explicit alike."""
    small = cavity.copy()
    small.apply_scale(1e-3)
    path = save_mesh(small, tmp_path / "small.stl")  # 0.00009 in the file
    _refused(path, "auto", "units", "bounding box is 9e-05 in the file's units", "explicitly")
    _refused(path, "m", "units", "9e-05 m across", "no unit makes it plausible")


def test_explicit_wrong_unit_names_the_likely_one(tmp_path, cavity):
    """A millimetre file read as metres (or the reverse) is refused with the likely unit."""
    mm = save_mesh(cavity, tmp_path / "mm.stl", units="mm")
    _refused(mm, "m", "units", "90 m across", "likely in mm: pass units='mm'")
    m = save_mesh(cavity, tmp_path / "m.stl", units="m")
    _refused(m, "mm", "units", "9e-05 m across", "likely in m: pass units='m'")
    _refused(m, "cm", "units", "unknown unit 'cm'")


def test_failed_save_keeps_the_old_file(tmp_path, cavity, monkeypatch):
    """Saves are atomic: a refused mesh or a failing write leaves the previous file as it
    was, and no temporary file behind."""
    path = save_mesh(_box(), tmp_path / "cavity.stl")
    old = path.read_bytes()
    bad = cavity.copy()
    bad.vertices[0, 0] = np.nan
    with pytest.raises(MeshError, match="not finite"):
        save_mesh(bad, path)
    assert path.read_bytes() == old

    def broken_replace(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", broken_replace)
    with pytest.raises(OSError, match="disk full"):
        save_mesh(cavity, path)
    monkeypatch.undo()
    assert path.read_bytes() == old
    assert [p.name for p in tmp_path.iterdir()] == ["cavity.stl"]
    assert len(load_mesh(path).mesh.faces) == 12
