"""Unit tests of ``oralnav.control.vision.markers`` (ChArUco marker fields).

Each test's docstring names the requirement it checks (Issue 2, item 3: markers).
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from oralnav.control.errors import ControlError, MarkerFieldError
from oralnav.control.vision.markers import (
    CylinderSurface,
    MarkerField,
    PlaneSurface,
    PointsSurface,
    aruco_dictionary,
)

SQUARE = 0.003
MARKER = 0.0022


def _field(squares=(12, 9), surface=None, first_id=0, dictionary="DICT_4X4_1000",
           square=SQUARE, marker=MARKER, name="opener") -> MarkerField:
    return MarkerField(name, dictionary, squares, square, marker, first_id,
                       PlaneSurface() if surface is None else surface)


# -- plane field -----------------------------------------------------------------------------
@pytest.mark.parametrize("squares", [(12, 9), (5, 5), (3, 2), (4, 7)])
def test_plane_corners_match_opencv_board(squares):
    """Issue 2 item 3: a plane field's corner ids and 3D corners match OpenCV's
    CharucoBoard.getChessboardCorners() (OpenCV's ids are the row index)."""
    f = _field(squares)
    ref = np.asarray(f.board.getChessboardCorners(), dtype=float)
    nx, ny = squares
    assert f.corner_count == (nx - 1) * (ny - 1) == len(ref)
    np.testing.assert_array_equal(f.corner_ids, np.arange(len(ref)))
    # OpenCV stores float32 (about 2 nm at 3 cm); the field keeps exact float64 positions
    np.testing.assert_allclose(f.corners, ref, rtol=0, atol=1e-8)
    np.testing.assert_allclose(f.corners_flat, ref[:, :2], rtol=0, atol=1e-8)
    j = np.arange(len(ref))
    exact = np.column_stack([(j % (nx - 1) + 1) * SQUARE, (j // (nx - 1) + 1) * SQUARE])
    np.testing.assert_allclose(f.corners_flat, exact, rtol=0, atol=1e-15)
    assert f.corner_index == {i: i for i in range(len(ref))}
    assert f.renderable


@pytest.mark.parametrize("squares, first_id", [((12, 9), 0), ((5, 5), 100), ((3, 2), 997)])
def test_marker_ids_run_from_first_id(squares, first_id):
    """Issue 2 item 3: the board's ArUco ids run consecutively from first_id, one marker in
    every other square (floor(nx * ny / 2))."""
    f = _field(squares, first_id=first_id)
    nx, ny = squares
    assert f.marker_count == nx * ny // 2 == len(f.board.getIds())
    np.testing.assert_array_equal(np.asarray(f.board.getIds()).ravel(), f.marker_ids)
    np.testing.assert_array_equal(f.marker_ids, np.arange(first_id, first_id + nx * ny // 2))


def test_detected_corner_ids_and_positions_match_field_model():
    """Issue 2 item 3: detecting the field's own board image with OpenCV's CharucoDetector
    gives every corner, with OpenCV's ids, exactly where the field model puts it (squares on
    pixel boundaries: corner (x, y) at pixel (x, y) * px/square - 0.5, up to the 0.5 px
    convention shift of OpenCV 4.x), also for first_id > 0."""
    f = _field((12, 9), first_id=300)
    pps = 20
    img = f.board_image(pps)
    corners, ids, _, marker_ids = cv2.aruco.CharucoDetector(f.board).detectBoard(img)
    assert marker_ids is not None and ids is not None
    assert sorted(np.asarray(marker_ids).ravel()) == list(f.marker_ids)
    ids = np.asarray(ids).ravel()
    assert sorted(ids) == list(f.corner_ids)
    model = f.corners[[f.corner_index[int(i)] for i in ids], :2] * (pps / SQUARE)
    offset = corners.reshape(-1, 2) - model
    # One common offset for every corner: -0.5 px with OpenCV 5 (pixel centres at integers,
    # the camera model's convention); OpenCV 4.x reports corners 0.5 px further (+0.0).
    common = np.median(offset, axis=0)
    assert any(np.allclose(common, c, atol=0.02) for c in (-0.5, 0.0)), common
    np.testing.assert_allclose(offset, np.broadcast_to(common, offset.shape), rtol=0, atol=0.05)


# -- cylinder field --------------------------------------------------------------------------
def test_cylinder_corners_follow_wrap_formula():
    """Issue 2 item 3: cylinder corners follow the guide's wrap formula: with xc the sheet's x
    centre and phi = (x - xc) / r, (x, y, 0) -> (xc + r sin phi, y, r (1 - cos phi))."""
    r = 0.012
    f = _field((12, 9), CylinderSurface(r))
    j = np.arange(11 * 8)
    flat = np.column_stack([(j % 11 + 1) * SQUARE, (j // 11 + 1) * SQUARE])
    np.testing.assert_allclose(flat, np.asarray(f.board.getChessboardCorners())[:, :2],
                               atol=1e-8)
    xc = 12 * SQUARE / 2
    phi = (flat[:, 0] - xc) / r
    expected = np.column_stack([xc + r * np.sin(phi), flat[:, 1], r * (1 - np.cos(phi))])
    np.testing.assert_allclose(f.corners, expected, rtol=0, atol=1e-12)
    np.testing.assert_allclose(f.corners_flat, flat, rtol=0, atol=1e-12)
    # wrapped, not flat: the outer corners leave the z = 0 plane by millimetres
    assert f.corners[:, 2].max() > 1e-3
    np.testing.assert_array_equal(f.corner_ids, np.arange(88))


@pytest.mark.parametrize("r", [0.006, 0.012, 0.05])
def test_cylinder_points_lie_at_radius_from_axis(r):
    """Issue 2 item 3: wrapped points (corners and arbitrary sheet points) lie at distance
    radius from the cylinder axis x = xc, z = radius (parallel to field y)."""
    rng = np.random.default_rng(3)
    f = _field((12, 9), CylinderSurface(r))
    w, h = f.sheet_size
    xy = np.vstack([f.corners_flat, rng.uniform([0, 0], [w, h], (200, 2))])
    p = f.sheet_to_field(xy)
    d = np.hypot(p[:, 0] - w / 2, p[:, 2] - r)
    np.testing.assert_allclose(d, r, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(p[:, 1], xy[:, 1])


def test_cylinder_preserves_flat_sheet_arc_length():
    """Issue 2 item 3: wrapping preserves flat-sheet lengths: the arc length along a wrapped
    row equals the flat sheet width, adjacent corners along x are a chord of arc `square`,
    and along y they stay `square` apart."""
    r = 0.008
    f = _field((12, 9), CylinderSurface(r))
    w, h = f.sheet_size
    x = np.linspace(0.0, w, 20001)
    row = f.sheet_to_field(np.column_stack([x, np.full_like(x, 0.4 * h)]))
    arc = np.sum(np.linalg.norm(np.diff(row, axis=0), axis=1))
    assert arc == pytest.approx(w, rel=1e-8)
    # the straight-line width is shorter: the sheet really is bent
    assert np.linalg.norm(row[-1] - row[0]) < 0.9 * w
    c = f.corners.reshape(8, 11, 3)  # rows of corners (along y), 11 corners along x
    chord = np.linalg.norm(np.diff(c, axis=1), axis=2)
    np.testing.assert_allclose(chord, 2 * r * np.sin(SQUARE / (2 * r)), rtol=0, atol=1e-14)
    np.testing.assert_allclose(np.linalg.norm(np.diff(c, axis=0), axis=2), SQUARE, atol=1e-15)


def test_cylinder_sheet_normals_unit_outward_and_minus_z_at_centre():
    """Issue 2 item 3: cylinder sheet_normals are unit, point to -z at phi = 0 (x = xc),
    point away from the axis (printed face outward) and are normal to the surface."""
    r = 0.012
    f = _field((12, 9), CylinderSurface(r))
    w, h = f.sheet_size
    rng = np.random.default_rng(5)
    xy = rng.uniform([0, 0], [w, h], (300, 2))
    n = f.sheet_normals(xy)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-15)
    np.testing.assert_allclose(f.sheet_normals([[w / 2, 0.3 * h]]), [[0.0, 0.0, -1.0]],
                               atol=1e-15)
    p = f.sheet_to_field(xy)
    radial = p - np.column_stack([np.full(len(p), w / 2), p[:, 1], np.full(len(p), r)])
    np.testing.assert_allclose(np.sum(n * radial, axis=1), r, atol=1e-12)
    eps = 1e-6  # central differences: tangents to ~(eps / r)^2
    tx = (f.sheet_to_field(xy + [eps, 0.0]) - f.sheet_to_field(xy - [eps, 0.0])) / (2 * eps)
    ty = (f.sheet_to_field(xy + [0.0, eps]) - f.sheet_to_field(xy - [0.0, eps])) / (2 * eps)
    np.testing.assert_allclose(np.linalg.norm(tx, axis=1), 1.0, atol=1e-8)
    np.testing.assert_allclose(np.sum(n * tx, axis=1), 0.0, atol=1e-8)
    np.testing.assert_allclose(np.sum(n * ty, axis=1), 0.0, atol=1e-8)


def test_plane_sheet_normals_point_to_minus_z():
    """Issue 2 item 3: plane sheet_normals are the unit vector -z everywhere."""
    f = _field((5, 4))
    n = f.sheet_normals(np.array([[0.0, 0.0], [0.01, 0.005], [0.015, 0.012]]))
    np.testing.assert_array_equal(n, np.tile([0.0, 0.0, -1.0], (3, 1)))


# -- validation ------------------------------------------------------------------------------
def test_unknown_dictionary_lists_known_names():
    """Issue 2 item 3: an unknown dictionary name raises MarkerFieldError (a ValueError)
    listing OpenCV's known dictionary names."""
    for name in ["DICT_4X4_1001", "4X4_1000", "CORNER_REFINE_SUBPIX", ""]:
        with pytest.raises(MarkerFieldError, match="DICT_4X4_1000") as info:
            aruco_dictionary(name)
        msg = str(info.value)
        assert repr(name) in msg
        assert "DICT_6X6_250" in msg and "DICT_ARUCO_ORIGINAL" in msg
        assert isinstance(info.value, ValueError) and isinstance(info.value, ControlError)
    with pytest.raises(MarkerFieldError, match="DICT_5X5_100"):
        _field(dictionary="DICT_5X5_1OO")


def test_known_dictionary_is_opencv_predefined():
    """Issue 2 item 3: aruco_dictionary returns OpenCV's predefined dictionary of that name."""
    d = aruco_dictionary("DICT_5X5_250")
    ref = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_5X5_250)
    assert d.markerSize == 5
    np.testing.assert_array_equal(d.bytesList, ref.bytesList)


def test_ids_overflowing_dictionary_error():
    """Issue 2 item 3: ids overflowing the dictionary (first_id 990 on a 12x9 board, 54
    markers, with DICT_4X4_1000) raise MarkerFieldError; 946 (ids up to 999) fits."""
    with pytest.raises(MarkerFieldError, match=r"990\.\.1043.*DICT_4X4_1000.*0\.\.999"):
        _field((12, 9), first_id=990)
    with pytest.raises(MarkerFieldError, match="overflow"):
        _field((12, 9), first_id=947)
    assert _field((12, 9), first_id=946).marker_ids[-1] == 999
    with pytest.raises(MarkerFieldError, match="overflow"):
        _field((12, 9), first_id=-1)
    with pytest.raises(MarkerFieldError, match="overflow DICT_4X4_50"):
        _field((12, 9), dictionary="DICT_4X4_50")


def test_cylinder_radius_too_small_errors():
    """Issue 2 item 3: a cylinder whose circumference is shorter than the sheet width (the
    sheet would wrap more than 360 deg) raises MarkerFieldError; a non-positive radius too."""
    width = 12 * SQUARE
    r_min = width / (2 * np.pi)
    with pytest.raises(MarkerFieldError, match="too small"):
        _field((12, 9), CylinderSurface(0.99 * r_min))
    _field((12, 9), CylinderSurface(1.01 * r_min))
    for r in [0.0, -0.01, float("nan")]:
        with pytest.raises(MarkerFieldError, match="radius"):
            _field((12, 9), CylinderSurface(r))


@pytest.mark.parametrize("marker", [SQUARE, 1.5 * SQUARE, 0.0, -0.001, float("nan")])
def test_marker_not_smaller_than_square_errors(marker):
    """Issue 2 item 3: a marker side >= the square side (or non-positive) raises
    MarkerFieldError."""
    with pytest.raises(MarkerFieldError, match="marker"):
        _field(marker=marker)


@pytest.mark.parametrize("kwargs", [
    {"squares": (1, 9)}, {"squares": (12, 1)}, {"square": 0.0}, {"square": float("inf")},
], ids=["nx<2", "ny<2", "square0", "square-inf"])
def test_bad_board_geometry_errors(kwargs):
    """Issue 2 item 3: fewer than 2 squares per side or a non-positive square side raise
    MarkerFieldError."""
    with pytest.raises(MarkerFieldError):
        _field(**kwargs)


def test_family_must_be_charuco():
    """Issue 2 item 3: only the charuco family is accepted."""
    with pytest.raises(MarkerFieldError, match="family"):
        MarkerField("x", "DICT_4X4_50", (5, 4), SQUARE, MARKER, family="aruco")


# -- points field ----------------------------------------------------------------------------
def test_points_surface_keeps_only_given_ids():
    """Issue 2 item 3: a points surface with a subset of corners keeps only those ids, in
    ascending order, with their given 3D positions and flat positions."""
    rng = np.random.default_rng(8)
    plane = _field((5, 4))
    ids = [11, 0, 5, 6, 2, 9]
    pts = {i: tuple(plane.corners[i] + rng.normal(0, 1e-4, 3)) for i in ids}
    f = _field((5, 4), PointsSurface(pts, source="opener_corners.csv"))
    np.testing.assert_array_equal(f.corner_ids, sorted(ids))
    np.testing.assert_allclose(f.corners, [pts[i] for i in sorted(ids)], atol=0)
    np.testing.assert_allclose(f.corners_flat, plane.corners_flat[sorted(ids)], atol=0)
    assert f.corner_index == {c: k for k, c in enumerate(sorted(ids))}
    assert not f.renderable
    with pytest.raises(MarkerFieldError, match="points"):
        f.sheet_to_field(np.zeros((1, 2)))
    with pytest.raises(MarkerFieldError, match="points"):
        f.sheet_normals(np.zeros((1, 2)))


@pytest.mark.parametrize("bad_id", [12, 100, -1])
def test_points_surface_out_of_range_id_errors(bad_id):
    """Issue 2 item 3: a points surface with a corner id outside the board (0..11 on 5x4)
    raises MarkerFieldError naming the id."""
    pts = {i: (0.0, 0.0, 0.0) for i in range(6)}
    pts[bad_id] = (0.0, 0.0, 0.0)
    with pytest.raises(MarkerFieldError, match=rf"\[{bad_id}\].*0\.\.11"):
        _field((5, 4), PointsSurface(pts))


def test_points_surface_needs_four_finite_points():
    """Issue 2 item 3: a points surface needs at least 4 corners with finite x, y, z."""
    with pytest.raises(MarkerFieldError, match="at least 4"):
        _field((5, 4), PointsSurface({i: (0.0, 0.0, 0.0) for i in range(3)}))
    pts = {i: (0.0, 0.0, 0.0) for i in range(5)}
    pts[2] = (0.0, np.nan, 0.0)
    with pytest.raises(MarkerFieldError, match="finite"):
        _field((5, 4), PointsSurface(pts))


# -- neighbours ------------------------------------------------------------------------------
def _brute_neighbours(f: MarkerField) -> list[set[int]]:
    """Rows whose flat positions are within one diagonal step (8-connected grid)."""
    flat = f.corners_flat
    d = np.linalg.norm(flat[:, None] - flat[None], axis=2)
    near = (d > 0) & (d < 1.5 * f.square)
    return [set(np.flatnonzero(row)) for row in near]


def test_neighbours_counts_and_symmetry():
    """Issue 2 item 3: on a 12x9 board (11x8 corners) an interior corner has 8 neighbours, a
    grid corner 3, an edge corner 5; neighbours are symmetric and equal the 8-connected grid
    neighbours."""
    f = _field((12, 9))
    nb = f.neighbours
    assert len(nb) == 88
    counts = {0: 3, 10: 3, 77: 3, 87: 3, 5: 5, 11: 5, 21: 5, 82: 5, 12: 8, 40: 8, 75: 8}
    for cid, n in counts.items():
        assert len(nb[f.corner_index[cid]]) == n, cid
    assert sorted(len(x) for x in nb).count(3) == 4
    for k, rows in enumerate(nb):
        assert k not in rows
        for j in rows:
            assert k in nb[j]
    assert [set(x) for x in nb] == _brute_neighbours(f)
    assert set(nb[f.corner_index[0]]) == {f.corner_index[c] for c in (1, 11, 12)}


def test_neighbours_on_points_field_only_known():
    """Issue 2 item 3: on a points field, neighbours index rows of known corners only and
    stay symmetric."""
    plane = _field((5, 4))
    ids = [0, 1, 4, 5, 6, 10, 11]
    f = _field((5, 4), PointsSurface({i: tuple(plane.corners[i]) for i in ids}))
    nb = f.neighbours
    assert len(nb) == len(ids)
    assert [set(x) for x in nb] == _brute_neighbours(f)
    by_id = {int(f.corner_ids[k]): {int(f.corner_ids[j]) for j in rows}
             for k, rows in enumerate(nb)}
    assert by_id[0] == {1, 4, 5}
    assert by_id[5] == {0, 1, 4, 6, 10}
    assert by_id[11] == {6, 10}


# -- board image -----------------------------------------------------------------------------
def _marker_squares(f: MarkerField) -> set[tuple[int, int]]:
    centres = [np.asarray(o, dtype=float).mean(axis=0) for o in f.board.getObjPoints()]
    return {(int(c[0] // f.square), int(c[1] // f.square)) for c in centres}


@pytest.mark.parametrize("squares", [(12, 9), (5, 5)])
@pytest.mark.parametrize("pps", [8, 13, 20, 40, 43])
def test_board_image_size_and_square_alignment(squares, pps):
    """Issue 2 item 3: board_image is exactly nx*pps wide and ny*pps high, mono8, and its
    squares align with pixel boundaries: the top-left square block is uniform, every square
    without a marker is uniformly black, every marker square has a white outer ring and its
    marker centred in the square."""
    f = _field(squares)
    nx, ny = squares
    img = f.board_image(pps)
    assert img.shape == (ny * pps, nx * pps)
    assert img.dtype == np.uint8
    top_left = img[:pps, :pps]
    assert np.all(top_left == top_left[0, 0])
    marked = _marker_squares(f)
    assert len(marked) == f.marker_count
    for i in range(nx):
        for j in range(ny):
            block = img[j * pps:(j + 1) * pps, i * pps:(i + 1) * pps]
            if (i, j) not in marked:
                assert np.all(block == 0), (i, j)
                continue
            ring = np.concatenate([block[0], block[-1], block[:, 0], block[:, -1]])
            assert np.all(ring == 255), (i, j)
            dark = np.argwhere(block == 0)
            lo, hi = dark.min(axis=0), dark.max(axis=0)
            # the marker (black border) is centred in the square
            np.testing.assert_array_equal(lo, pps - 1 - hi)


def test_board_image_too_small_errors():
    """Issue 2 item 3: a px_per_square too small to draw the markers raises MarkerFieldError
    (not a bare cv2.error)."""
    f = _field((12, 9))
    for pps in [2, 3, 7]:
        with pytest.raises(MarkerFieldError, match="px_per_square"):
            f.board_image(pps)
    with pytest.raises(MarkerFieldError, match="border_bits"):
        f.board_image(20, border_bits=0)
