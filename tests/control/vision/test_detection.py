"""Unit tests of ``oralnav.control.vision.detection``: quads, ArUco decoding, chessboard corners.

Each test's docstring names the requirement it checks (the tracker's marker recognition,
navigation paper section III.C-E; ground truth from the scene renderer).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from oralnav.config.rig import load_rig
from oralnav.config.scene import load_scene
from oralnav.control.errors import ControlError
from oralnav.control.geometry import transform_from_euler
from oralnav.control.vision.detection import (
    BoardLayout,
    DetectionError,
    MarkerDecoder,
    Quad,
    QuadParams,
    check_image,
    decoder_for,
    detect_fields,
    find_quads,
    predict_board,
    predict_corners,
    refine_corners,
    square_to_quad,
    x_junction_ok,
    x_junction_scores,
)
from oralnav.control.vision.markers import CylinderSurface, MarkerField, aruco_dictionary
from oralnav.sim.world.render import SceneRenderer
from oralnav.sim.world.scene import Imaging, Placement, Scene

ROOT = Path(__file__).resolve().parents[3]
STEREO_RIG = ROOT / "config" / "rigs" / "stereo.toml"

# -- synthetic marker canvas -----------------------------------------------------------------
SIDE = 80  # marker side on the canvas, pixels (border included)
CANVAS_IDS = (3, 17, 250, 999, 512, 42, 0, 777)
#: ids for each dictionary of the round trip (DICT_6X6_250 stops at 249)
ROUND_TRIP_IDS = {"DICT_4X4_1000": CANVAS_IDS, "DICT_6X6_250": (3, 17, 249, 99, 212, 42, 0, 177)}


def _screen_corners(x0: int, y0: int, side: int) -> np.ndarray:
    """The outline of a ``side`` px square drawn from pixel (x0, y0): TL, TR, BR, BL on
    screen, pixel-centre convention (the square's edges are half a pixel outside)."""
    return np.array([[x0 - 0.5, y0 - 0.5], [x0 + side - 0.5, y0 - 0.5],
                     [x0 + side - 0.5, y0 + side - 0.5], [x0 - 0.5, y0 + side - 0.5]])


def _marker_canvas(dictionary: str, ids=CANVAS_IDS, side: int = SIDE
                   ) -> tuple[np.ndarray, dict[int, np.ndarray]]:
    """Markers of ``ids`` on a light canvas, marker n turned by n * 90 deg (np.rot90).

    Returns the canvas and each id's printed corners (TL, TR, BR, BL of the marker as
    printed, before the turn) in canvas pixels.
    """
    dic = aruco_dictionary(dictionary)
    canvas = np.full((520, 800), 200, np.uint8)
    where = {}
    for n, marker_id in enumerate(ids):
        k = n % 4
        x0, y0 = 60 + (n % 4) * 180, 80 + (n // 4) * 220
        img = cv2.aruco.generateImageMarker(dic, marker_id, side, borderBits=1)
        canvas[y0:y0 + side, x0:x0 + side] = np.rot90(img, k)
        screen = _screen_corners(x0, y0, side)
        # np.rot90 turns the print counter-clockwise on screen: printed corner i lands on
        # screen corner (i - k) mod 4.
        where[marker_id] = screen[[(i - k) % 4 for i in range(4)]]
    return canvas, where


HOMOGRAPHIES = {
    "identity": np.eye(3),
    "perspective": np.array([[0.9, 0.15, 30.0], [-0.1, 0.95, 40.0], [2e-4, -1e-4, 1.0]]),
    "turned": np.array([[0.6, -0.75, 420.0], [0.7, 0.55, 20.0], [-1.5e-4, 2e-4, 1.0]]),
}


def _warp(canvas: np.ndarray, where: dict[int, np.ndarray], H: np.ndarray
          ) -> tuple[np.ndarray, dict[int, np.ndarray]]:
    """Warp the canvas by ``H`` (canvas pixel centres -> image pixel centres), with a mild
    lens blur; the markers' printed corners go along."""
    img = cv2.warpPerspective(canvas, H, (900, 760), flags=cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_CONSTANT, borderValue=200)
    img = cv2.GaussianBlur(img, (0, 0), 0.8)
    moved = {i: cv2.perspectiveTransform(c.reshape(-1, 1, 2), H).reshape(4, 2)
             for i, c in where.items()}
    return img, moved


def _opencv_markers(image: np.ndarray, dictionary: str) -> dict[int, np.ndarray]:
    """OpenCV's own ArucoDetector with sub-pixel corner refinement: id -> 4 x 2 corners."""
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    det = cv2.aruco.ArucoDetector(aruco_dictionary(dictionary), params)
    corners, ids, _ = det.detectMarkers(image)
    assert ids is not None
    return {int(i): c.reshape(4, 2).astype(float) for i, c in zip(ids.ravel(), corners,
                                                                   strict=True)}


@pytest.mark.parametrize("dictionary", ["DICT_4X4_1000", "DICT_6X6_250"])
@pytest.mark.parametrize("hname", list(HOMOGRAPHIES))
def test_decoder_round_trip_matches_opencv(dictionary, hname):
    """Detection step 2: markers drawn at every rotation and seen through a homography
    decode to their ids, and each marker's corners come in the printed order (TL, TR, BR,
    BL): every corner lies within 1.5 px of OpenCV's ArucoDetector corner of the same
    index and of the exact outline (a wrong order would be a marker side, 50+ px, off).

    1.5 px, not 1: quad corners are contour vertices, not refined (up to 1.4 px off on a
    marker turned 40 deg in the image, where OpenCV's sub-pixel corners are 0.3 px off);
    only the chessboard corners are refined."""
    expect = ROUND_TRIP_IDS[dictionary]
    canvas, where = _marker_canvas(dictionary, expect)
    image, exact = _warp(canvas, where, HOMOGRAPHIES[hname])
    quads = find_quads(image)
    found = decoder_for(dictionary).decode(image, quads)
    ids = [q.marker_id for q in found]
    assert sorted(ids) == sorted(expect)
    ref = _opencv_markers(image, dictionary)
    for q in found:
        assert q.corners.shape == (4, 2)
        d_cv = np.linalg.norm(q.corners - ref[q.marker_id], axis=1)
        d_exact = np.linalg.norm(q.corners - exact[q.marker_id], axis=1)
        assert d_cv.max() <= 1.5, (q.marker_id, d_cv)
        assert d_exact.max() <= 1.5, (q.marker_id, d_exact)


def test_decoder_allowed_ids_and_shared_instance():
    """Detection step 2: ``allowed`` restricts the ids accepted; ``decoder_for`` builds one
    decoder per dictionary and shares it."""
    canvas, _ = _marker_canvas("DICT_4X4_1000")
    quads = find_quads(canvas)
    dec = decoder_for("DICT_4X4_1000")
    assert decoder_for("DICT_4X4_1000") is dec
    got = dec.decode(canvas, quads, allowed=[range(0, 20), range(500, 600)])
    assert sorted(q.marker_id for q in got) == [0, 3, 17, 512]
    assert dec.decode(canvas, np.zeros((0, 4, 2))) == []


def _bit_marker(bits: np.ndarray, side: int = 60) -> np.ndarray:
    """A marker image: one black border cell around ``bits`` (True = white)."""
    n = bits.shape[0]
    cells = np.zeros((n + 2, n + 2), np.uint8)
    cells[1:-1, 1:-1] = np.where(bits, 255, 0)
    return cv2.resize(cells, (side, side), interpolation=cv2.INTER_NEAREST)


def test_unknown_codes_are_rejected():
    """Detection step 2: only exact codes are accepted: a quad whose bit pattern is no id
    of the dictionary (in any rotation) decodes to nothing, next to a valid marker."""
    dec = decoder_for("DICT_4X4_1000")
    rng = np.random.default_rng(5)
    weights = 1 << np.arange(16)[::-1]
    while True:
        bits = rng.random((4, 4)) < 0.5
        codes = [int(np.sum(np.rot90(bits, k).ravel() * weights)) for k in range(4)]
        if not any(c in dec.table for c in codes) and 4 <= bits.sum() <= 12:
            break
    canvas = np.full((200, 300), 200, np.uint8)
    canvas[40:100, 40:100] = _bit_marker(bits)
    canvas[40:100, 180:240] = cv2.aruco.generateImageMarker(
        aruco_dictionary("DICT_4X4_1000"), 123, 60, borderBits=1)
    image = cv2.GaussianBlur(canvas, (0, 0), 0.7)
    quads = find_quads(image)
    centres = quads.mean(axis=1)
    # both squares are found as quads; only the real marker decodes
    assert np.any(np.linalg.norm(centres - (69.5, 69.5), axis=1) < 3)
    assert np.any(np.linalg.norm(centres - (209.5, 69.5), axis=1) < 3)
    got = dec.decode(image, quads)
    assert [q.marker_id for q in got] == [123]


def test_ambiguous_codes_are_rejected():
    """Detection step 2: a code that two ids or two rotations share is never accepted
    (DICT_ARUCO_ORIGINAL id 1023 reads the same turned by 180 deg, so its orientation, and
    with it the corner order, is unknowable); its neighbour id 1022 decodes."""
    dec = MarkerDecoder("DICT_ARUCO_ORIGINAL")
    assert dec.table[dec.code_of(1023)] == (-1, -1)
    dic = aruco_dictionary("DICT_ARUCO_ORIGINAL")
    canvas = np.full((200, 300), 200, np.uint8)
    canvas[40:110, 40:110] = cv2.aruco.generateImageMarker(dic, 1023, 70, borderBits=1)
    canvas[40:110, 180:250] = cv2.aruco.generateImageMarker(dic, 1022, 70, borderBits=1)
    image = cv2.GaussianBlur(canvas, (0, 0), 0.7)
    quads = find_quads(image)
    assert len(quads) >= 2
    assert [q.marker_id for q in dec.decode(image, quads)] == [1022]


def test_match_scores_check_identity_and_orientation():
    """Detection (identity check of predictive tracking): bit cells read where a quad is
    claimed to be score 1 for the right id in the right corner order, and less for a
    wrong id, a quad turned by one, two or three corners, or 0 on a blank area."""
    canvas, where = _marker_canvas("DICT_4X4_1000")
    image, exact = _warp(canvas, where, HOMOGRAPHIES["perspective"])
    dec = decoder_for("DICT_4X4_1000")
    ids = list(CANVAS_IDS)
    quads = np.stack([exact[i] for i in ids])
    np.testing.assert_array_equal(dec.match_scores(image, quads, ids), 1.0)
    wrong = dec.match_scores(image, quads, ids[1:] + ids[:1])
    assert np.all(wrong < 1.0) and wrong.mean() < 0.8, wrong
    for k in (1, 2, 3):
        turned = dec.match_scores(image, np.roll(quads, k, axis=1), ids)
        assert np.all(turned < 1.0) and turned.mean() < 0.8, (k, turned)
    # in the flat grey around the warped canvas: no contrast
    blank = np.array([[[820.0, 680.0], [870.0, 680.0], [870.0, 730.0], [820.0, 730.0]]])
    assert image[680:731, 820:871].std() == 0
    assert dec.match_scores(image, blank, ids[:1])[0] == 0.0
    assert dec.match_scores(image, np.zeros((0, 4, 2)), []).shape == (0,)


def test_square_to_quad_maps_unit_square_corners():
    """Detection step 2: square_to_quad's homographies take the unit square's corners
    (0,0), (1,0), (1,1), (0,1) exactly to each quad's corners, as OpenCV's
    getPerspectiveTransform does, for many quads at once."""
    rng = np.random.default_rng(1)
    base = np.array([[0.0, 0.0], [100.0, 0.0], [100.0, 100.0], [0.0, 100.0]])
    quads = base[None] + rng.uniform(-30, 30, (50, 4, 2)) + rng.uniform(0, 1000, (50, 1, 2))
    H = square_to_quad(quads)
    assert H.shape == (50, 3, 3)
    unit = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [1.0, 1.0, 1.0], [0.0, 1.0, 1.0]])
    p = H @ unit.T
    mapped = (p[:, :2] / p[:, 2:3]).transpose(0, 2, 1)
    np.testing.assert_allclose(mapped, quads, rtol=0, atol=1e-9)
    for q, h in zip(quads[:5], H[:5], strict=True):
        ref = cv2.getPerspectiveTransform(unit[:, :2].astype(np.float32),
                                          q.astype(np.float32))
        np.testing.assert_allclose(h / h[2, 2], ref / ref[2, 2], rtol=1e-4, atol=1e-4)
    # a parallelogram gives an affine map (no perspective row)
    para = np.array([[[10.0, 20.0], [60.0, 25.0], [70.0, 75.0], [20.0, 70.0]]])
    np.testing.assert_allclose(square_to_quad(para)[0, 2], (0.0, 0.0, 1.0), atol=1e-12)


def test_find_quads_roi_offsets_and_order():
    """Detection step 1: quads found inside an ROI come back in full-image pixels, equal
    to those found on the whole image; corners run clockwise on screen; an ROI under
    8 px finds nothing; a half-scale search finds the same markers within 1.5 px."""
    canvas, where = _marker_canvas("DICT_4X4_1000")
    image, _ = _warp(canvas, where, HOMOGRAPHIES["perspective"])
    full = find_quads(image)
    x, y = full[..., 0], full[..., 1]
    area = np.sum(x * np.roll(y, -1, axis=1) - np.roll(x, -1, axis=1) * y, axis=1)
    assert np.all(area > 0)  # clockwise with y down
    roi = (150, 60, 620, 420)
    part = find_quads(image, roi=roi)
    margin = 12
    inside = np.all((full[..., 0] >= roi[0] + margin) & (full[..., 0] <= roi[2] - margin)
                    & (full[..., 1] >= roi[1] + margin) & (full[..., 1] <= roi[3] - margin),
                    axis=1)
    assert inside.sum() >= 2
    for q in full[inside]:
        d = np.abs(part - q).max(axis=(1, 2))
        assert d.min() < 1e-9
    # (markers the ROI cuts may leave extra quads, but all inside the ROI)
    assert np.all((part[..., 0] >= roi[0] - 0.5) & (part[..., 0] <= roi[2] - 0.5)
                  & (part[..., 1] >= roi[1] - 0.5) & (part[..., 1] <= roi[3] - 0.5))
    assert find_quads(image, roi=(100, 100, 107, 300)).shape == (0, 4, 2)
    half = find_quads(image, QuadParams(scale=0.5, block=5))
    dec = decoder_for("DICT_4X4_1000")
    a = {q.marker_id: q.corners for q in dec.decode(image, full)}
    b = {q.marker_id: q.corners for q in dec.decode(image, half)}
    assert set(b) == set(a) == set(CANVAS_IDS)
    for i in a:
        assert np.abs(a[i] - b[i]).max() <= 1.5



def test_marker_inside_a_dark_frame_is_found():
    """Detection step 1: a marker is found whatever surrounds it; here it sits at the
    centre of a dark square frame (a window, a bracket, the dark print around a sheet).
    The frame's own quads are a different size, not duplicates of the marker's outline."""
    dic = aruco_dictionary("DICT_4X4_1000")
    canvas = np.full((400, 400), 200, np.uint8)
    canvas[50:350, 50:350] = 0
    canvas[70:330, 70:330] = 200
    canvas[170:230, 170:230] = cv2.aruco.generateImageMarker(dic, 5, 60, borderBits=1)
    image = cv2.GaussianBlur(canvas, (0, 0), 0.7)
    found = decoder_for("DICT_4X4_1000").decode(image, find_quads(image))
    assert [q.marker_id for q in found] == [5]


def test_marker_next_to_a_dark_frame_is_found():
    """Detection step 1 (control of the test above): the same marker with the frame
    opened on one side is found."""
    dic = aruco_dictionary("DICT_4X4_1000")
    canvas = np.full((400, 400), 200, np.uint8)
    canvas[50:350, 50:350] = 0
    canvas[70:330, 70:330] = 200
    canvas[50:70, :] = 200
    canvas[170:230, 170:230] = cv2.aruco.generateImageMarker(dic, 5, 60, borderBits=1)
    image = cv2.GaussianBlur(canvas, (0, 0), 0.7)
    found = decoder_for("DICT_4X4_1000").decode(image, find_quads(image))
    assert [q.marker_id for q in found] == [5]


@pytest.mark.parametrize("bad, match", [
    (np.zeros((120, 160), np.float32), "dtype uint8"),
    (np.zeros((120, 160), np.uint16), "dtype uint8"),
    (np.zeros((120, 160, 3), np.uint8), "2-D mono image"),
    (np.zeros(160, np.uint8), "2-D mono image"),
    ([[0, 1], [2, 3]], "numpy array, got list"),
    (None, "numpy array, got NoneType"),
])
def test_check_image_rejects_bad_images(bad, match):
    """Detection bad input: a non-array, a wrong dtype or a wrong number of dimensions
    raise DetectionError (a ControlError and a ValueError) naming the problem."""
    with pytest.raises(DetectionError, match=match) as info:
        check_image(bad, what="camera 'left'")
    assert "camera 'left'" in str(info.value)
    assert isinstance(info.value, ControlError) and isinstance(info.value, ValueError)
    if isinstance(bad, np.ndarray) and bad.ndim == 2:
        with pytest.raises(DetectionError):
            detect_fields(bad, [])


def test_check_image_size_and_contiguity():
    """Detection bad input: an image of the wrong size names both sizes; a valid but
    non-contiguous view comes back C-contiguous with the same pixels."""
    with pytest.raises(DetectionError, match=r"image is 160x120, the camera is 1920x1200"):
        check_image(np.zeros((120, 160), np.uint8), size=(1920, 1200))
    big = np.arange(240 * 320, dtype=np.uint32).reshape(240, 320).astype(np.uint8)
    view = big[::2, ::2]
    out = check_image(view, size=(160, 120))
    assert out.flags.c_contiguous
    np.testing.assert_array_equal(out, view)


# -- board layout and corner prediction ------------------------------------------------------
BOARD = MarkerField("board", "DICT_4X4_1000", (6, 5), 0.004, 0.003, first_id=40)


def test_board_layout_marker_corner_ids():
    """Detection step 3: the layout lists, for each marker, the board corner ids at its
    square's corners (TL, TR, BR, BL), -1 exactly on the sheet's outer edge."""
    layout = BoardLayout.of(BOARD)
    s = BOARD.square
    assert layout.marker_flat.shape == (BOARD.marker_count, 4, 2)
    np.testing.assert_allclose(layout.corner_flat, BOARD.corners_flat, atol=1e-15)
    W, H = BOARD.sheet_size
    for quad, ids in zip(layout.marker_flat, layout.marker_corner_ids, strict=True):
        col_row = np.floor(quad.mean(axis=0) / s)
        square = (col_row + np.array([[0, 0], [1, 0], [1, 1], [0, 1]])) * s
        for k in range(4):
            on_edge = (np.isclose(square[k, 0], 0) or np.isclose(square[k, 0], W)
                       or np.isclose(square[k, 1], 0) or np.isclose(square[k, 1], H))
            if on_edge:
                assert ids[k] == -1
            else:
                np.testing.assert_allclose(layout.corner_flat[ids[k]], square[k], atol=1e-12)


# A plane homography (sheet metres -> pixels) for the corner-prediction tests.
_H = np.array([[9000.0, 1500.0, 200.0], [-800.0, 8500.0, 150.0], [3.0, -2.0, 1.0]])


def _to_px(p: np.ndarray) -> np.ndarray:
    q = np.concatenate([p, np.ones(p.shape[:-1] + (1,))], axis=-1) @ _H.T
    return q[..., :2] / q[..., 2:]


def test_predict_corners_through_marker_homographies():
    """Detection step 3: on a plane, each decoded marker's homography puts the corners of
    its square exactly where they are; a corner two markers predict takes their mean, and
    a misread marker (id of another square) makes the corners it disagrees on drop out."""
    layout = BoardLayout.of(BOARD)
    quads = [Quad(int(BOARD.first_id + m), _to_px(layout.marker_flat[m]))
             for m in range(BOARD.marker_count)]
    quads.append(Quad(7, _to_px(layout.marker_flat[0])))  # another field's id: ignored
    ids, px, sq, used = predict_corners(BOARD, layout, quads)
    np.testing.assert_array_equal(ids, BOARD.corner_ids)
    # 1e-4 px: the layout takes marker outlines from OpenCV's float32 board (~1e-9 m)
    np.testing.assert_allclose(px, _to_px(BOARD.corners_flat), rtol=0, atol=1e-4)
    assert np.all((sq > 20) & (sq < 60))  # about 4 mm x ~9000 px/m
    np.testing.assert_array_equal(used, BOARD.marker_ids)
    # marker 5 claims to be marker 6: its square's corners disagree with the neighbours'
    bad = list(quads[:BOARD.marker_count])
    bad[5] = Quad(int(BOARD.first_id + 6), bad[5].corners)
    ids2, px2, _, _ = predict_corners(BOARD, layout, bad)
    assert len(ids2) < len(ids)
    exact = _to_px(BOARD.corners_flat)
    np.testing.assert_allclose(px2, exact[ids2], rtol=0, atol=1e-4)
    none = predict_corners(BOARD, layout, [Quad(7, quads[0].corners)])
    assert all(len(a) == 0 for a in none)


def test_predict_board_axes_and_colouring():
    """Detection step 3: with each predicted corner come the image vectors of one square
    along the sheet's x and y (the homography's derivative there) and which diagonal
    holds the light squares, as printed on the board image."""
    layout = BoardLayout.of(BOARD)
    quads = [Quad(int(BOARD.first_id + m), _to_px(layout.marker_flat[m]))
             for m in range(BOARD.marker_count)]
    pr = predict_board(BOARD, layout, quads)
    ids, px, sq, used = predict_corners(BOARD, layout, quads)
    np.testing.assert_array_equal(pr.ids, ids)
    np.testing.assert_array_equal(pr.px, px)
    xy = BOARD.corners_flat[pr.ids]
    h = 1e-7 * BOARD.square
    for k, step in enumerate(([h, 0.0], [0.0, h])):
        step = np.array(step)
        deriv = (_to_px(xy + step) - _to_px(xy - step)) / (2 * h) * BOARD.square
        np.testing.assert_allclose(pr.axes[:, k], deriv, rtol=1e-5, atol=1e-6)
    per_square = 100
    sheet = BOARD.board_image(per_square)
    # the square toward +x+y of each corner, sampled on the printed sheet just inside its
    # corner (its centre may hold a marker's dark bits)
    inside = ((xy / BOARD.square + 0.05) * per_square).astype(int)
    light = sheet[inside[:, 1], inside[:, 0]] > 127
    np.testing.assert_array_equal(pr.light_diagonal, np.where(light, 1.0, -1.0))

# -- rendered fields ------------------------------------------------------------------------
PLANE = MarkerField("plane", "DICT_4X4_1000", (10, 7), 0.004, 0.003, first_id=0)
CYLINDER = MarkerField("cyl", "DICT_4X4_1000", (12, 9), 0.003, 0.0022, first_id=100,
                       surface=CylinderSurface(radius=0.010))
# Same ids as PLANE, another dictionary: decoded apart.
OTHER = MarkerField("other", "DICT_6X6_250", (6, 5), 0.004, 0.003, first_id=0)
NOISY = Imaging(supersample=2, blur_sigma_px=1.0, read_noise_dn=1.2, shot_noise_gain=0.05,
                illumination_gradient=(0.15, -0.10))
FAR = transform_from_euler([5.0, 5.0, 1.0], [0, 0, 0])
SCENE_POSES = {
    "front": {"plane": ([-0.06, -0.03, 0.22], [0, 0, 0]),
              "cyl": ([0.02, -0.01, 0.20], [0, 0, 0]),
              "other": ([-0.02, 0.025, 0.21], [0, 0, 0])},
    "oblique": {"plane": ([-0.06, -0.03, 0.22], [10, -15, 5]),
                "cyl": ([0.02, -0.01, 0.20], [15, 20, 10]),
                "other": ([-0.025, 0.03, 0.23], [-20, 25, 30])},
}


@pytest.fixture(scope="module")
def renderer() -> SceneRenderer:
    rig = load_rig(STEREO_RIG)
    rig = replace(rig, cameras={"left": rig["left"]})
    placements = tuple(Placement(f.name, f, FAR) for f in (PLANE, CYLINDER, OTHER))
    r = SceneRenderer(Scene(rig=rig, placements=placements, imaging=NOISY, seed=11))
    r.prepare()
    return r


def _score(found, truth) -> tuple[np.ndarray, list[int]]:
    """Corner errors (px) against truth and the ids truth does not list as visible."""
    index = {int(c): k for k, c in enumerate(truth.corner_ids)}
    wrong = [int(i) for i in found.ids if int(i) not in index]
    err = np.array([np.linalg.norm(p - truth.corners_px[index[int(i)]])
                    for i, p in zip(found.ids, found.px, strict=True) if int(i) in index])
    return err, wrong


@pytest.mark.parametrize("pose", list(SCENE_POSES))
@pytest.mark.parametrize("frame", [0, 1])
def test_detect_fields_on_rendered_plane_and_cylinder(renderer, pose, frame):
    """Detection: on noisy renders (blur, read and shot noise, illumination gradient) a
    plane field and a 10 mm radius cylinder field in one image are found with no wrong
    corner id and a median corner error <= 0.1 px against ground truth; a third field of
    another dictionary, reusing the same ids, is found apart."""
    poses = {n: transform_from_euler(*p) for n, p in SCENE_POSES[pose].items()}
    fr = renderer.render(poses=poses, frame=frame)
    truth = fr.truth["left"]
    assert set(truth) == {"plane", "cyl", "other"}
    found = detect_fields(fr.images["left"], [PLANE, CYLINDER, OTHER])
    assert set(found) == {"plane", "cyl", "other"}
    for name, fld in (("plane", PLANE), ("cyl", CYLINDER), ("other", OTHER)):
        fc = found[name]
        err, wrong = _score(fc, truth[name])
        assert wrong == [], f"{name}: corners {wrong} are not visible in truth"
        assert np.median(err) <= 0.1, f"{name}: median {np.median(err):.3f} px"
        # a good share of the visible corners (see the xfail test below for the markers
        # find_quads loses on the flat 6x6 field)
        share = 0.9 if fld is not CYLINDER else 0.6
        assert len(fc) >= share * len(truth[name].corner_ids), (name, len(fc))
        assert fc.px.shape == (len(fc.ids), 2) and len(np.unique(fc.ids)) == len(fc.ids)
        assert np.all(np.isin(fc.markers, fld.marker_ids))


def test_every_marker_of_a_face_on_field_is_decoded(renderer):
    """Detection: on a face-on flat field every marker is decoded (OpenCV's ArucoDetector
    finds all 15 on this image), so every corner is found."""
    poses = {n: transform_from_euler(*p) for n, p in SCENE_POSES["front"].items()}
    fr = renderer.render(poses=poses)
    found = detect_fields(fr.images["left"], [OTHER])
    ref = _opencv_markers(fr.images["left"], OTHER.dictionary)
    assert set(ref) == set(OTHER.marker_ids.tolist())
    assert sorted(found["other"].markers.tolist()) == sorted(ref)
    assert len(found["other"]) == OTHER.corner_count


def test_detect_fields_only_the_fields_asked_for(renderer):
    """Detection: fields not asked for are ignored (their markers are outside every id
    block); a field out of view is absent from the result; an ROI restricts the search."""
    poses = {n: transform_from_euler(*p) for n, p in SCENE_POSES["front"].items()}
    poses["other"] = FAR
    fr = renderer.render(poses=poses)
    image = fr.images["left"]
    assert set(detect_fields(image, [CYLINDER, OTHER])) == {"cyl"}
    truth = fr.truth["left"]["plane"].corners_px
    x0, y0 = np.floor(truth.min(axis=0)).astype(int) - 60
    x1, y1 = np.ceil(truth.max(axis=0)).astype(int) + 60
    inside = detect_fields(image, [PLANE, CYLINDER], roi=(x0, y0, x1, y1))
    assert set(inside) == {"plane"}
    assert len(inside["plane"]) == PLANE.corner_count
    assert detect_fields(np.full_like(image, 40), [PLANE, CYLINDER]) == {}


def test_refine_corners_snaps_to_truth_and_flags_border(renderer):
    """Detection step 3: predictions 1 px off refine to within 0.15 px (median 0.1) of the
    true corners; predictions too close to the image border are flagged, not refined."""
    poses = {n: transform_from_euler(*p) for n, p in SCENE_POSES["front"].items()}
    fr = renderer.render(poses=poses, frame=3)
    truth = fr.truth["left"]["plane"]
    rng = np.random.default_rng(2)
    ang = rng.uniform(0, 2 * np.pi, len(truth.corners_px))
    start = truth.corners_px + np.stack([np.cos(ang), np.sin(ang)], axis=1)
    sq = np.full(len(start), 40.0)
    px, ok = refine_corners(fr.images["left"], start, sq)
    assert ok.all()
    err = np.linalg.norm(px - truth.corners_px, axis=1)
    assert np.median(err) <= 0.1 and err.max() <= 0.25, err
    edge = np.array([[2.0, 300.0], [1918.0, 600.0], [900.0, 1199.0]])
    px2, ok2 = refine_corners(fr.images["left"], edge, np.full(3, 40.0))
    assert not ok2.any()
    np.testing.assert_array_equal(px2, edge)
    empty_px, empty_ok = refine_corners(fr.images["left"], np.zeros((0, 2)), np.zeros(0))
    assert empty_px.shape == (0, 2) and empty_ok.shape == (0,)


# -- occlusion -------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def occluded() -> tuple:
    scene = load_scene(ROOT / "config" / "examples" / "stereo_occluded.toml")
    return scene, SceneRenderer(scene).render()


@pytest.mark.parametrize("camera", ["left", "right"])
def test_occluded_fields_give_correct_corners_only(occluded, camera):
    """Detection under occlusion (stereo_occluded scene: a shaft across the opener, a blot
    on the robot field, a motion-blurred end-effector): every corner reported is visible
    in ground truth and within 1 px of it (median 0.1 px); the partly covered fields are
    still found. In the right camera the shaft hides opener corner 15, and the refined
    point sits on the shaft's edge 1.9 px from it: the X-junction check drops it."""
    scene, fr = occluded
    fields = [p.field for p in scene.placements]
    found = detect_fields(fr.images[camera], fields)
    assert {"robot", "opener"} <= set(found)
    for name, fc in found.items():
        err, wrong = _score(fc, fr.truth[camera][name])
        assert wrong == [], f"{camera} {name}: hidden corners {wrong} reported"
        assert err.max() <= 1.0, f"{camera} {name}: max error {err.max():.3f} px"
        assert np.median(err) <= 0.1
    # the blot hides robot corners: none of them is reported
    blot = scene.blots[0]
    robot = scene.placement("robot").field
    under = {int(i) for i, xy in zip(robot.corner_ids, robot.corners_flat, strict=True)
             if np.hypot(*(xy - np.asarray(blot.center))) <= blot.radius}
    assert under and not under & set(found["robot"].ids.tolist())



# -- corner checks ---------------------------------------------------------------------------
CHESS_SQUARE = 24  # px


def _chessboard(n: int = 6, margin: int = 20) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A blurred n x n chessboard whose top-left square is dark. Returns the image, its
    inner corners (pixel-centre convention) and their light diagonals (+1: light toward
    +x+y)."""
    img = np.full((n * CHESS_SQUARE + 2 * margin,) * 2, 200, np.uint8)
    for r in range(n):
        for c in range(n):
            if (r + c) % 2 == 0:
                img[margin + r * CHESS_SQUARE:margin + (r + 1) * CHESS_SQUARE,
                    margin + c * CHESS_SQUARE:margin + (c + 1) * CHESS_SQUARE] = 30
    img = cv2.GaussianBlur(img, (0, 0), 1.0)
    g = margin + np.arange(1, n) * CHESS_SQUARE - 0.5
    gx, gy = np.meshgrid(g, g)
    col, row = np.meshgrid(np.arange(1, n), np.arange(1, n))
    light = np.where((col + row) % 2 == 1, 1.0, -1.0).ravel()  # square (col, row) is light
    return img, np.stack([gx.ravel(), gy.ravel()], axis=1), light


def test_refine_corners_flags_a_window_that_gave_up():
    """Detection step 3, corners sub-pixel or dropped (issue 3, stability where methods
    fail): ``cornerSubPix`` hands back its starting point unchanged when it converges
    further away than its window (3 px here); such a start, 3.5-7 px from the corner, was
    reported as refined. It is flagged now, while a start 1 px off still snaps to the
    corner."""
    img, corners, _ = _chessboard()
    c = corners[7]
    sq = np.array([float(CHESS_SQUARE)])
    for d in ([3.5, 0.5], [5.0, 0.0], [0.0, 6.0], [3.5, 3.5], [7.0, 2.0]):
        px, ok = refine_corners(img, c + np.array([d]), sq)
        assert not ok[0], (d, px)
    px, ok = refine_corners(img, c + np.array([[0.8, -0.6]]), sq)
    assert ok[0] and np.linalg.norm(px[0] - c) < 0.05


def test_x_junction_check_rejects_edges_marker_corners_and_wrong_colouring():
    """Detection step 3, corners sub-pixel or dropped (issue 3, stability where methods
    fail): refined points are kept only if they look like the chessboard corner they are
    meant to be. Every true corner passes; a point on an edge, in a square, at the corner
    of a marker-like dark patch (three squares of one shade) and a true corner with the
    colouring of its neighbour one square over (an identity one square off) all fail."""
    img, corners, light = _chessboard()
    # a dark "marker" inside the light square right of corner 7, 5 px from its corner
    c7 = corners[7]
    x0, y0 = int(c7[0] + 5.5), int(c7[1] + 5.5 - CHESS_SQUARE)
    img[y0:y0 + 12, x0:x0 + 12] = 30
    img = cv2.GaussianBlur(img, (0, 0), 0.7)
    axes = np.tile(np.eye(2) * CHESS_SQUARE, (len(corners), 1, 1))
    assert x_junction_ok(img, corners, axes, light).all()
    contrast, asym = x_junction_scores(img, corners, axes, light)
    # true corners: full contrast, point-symmetric to a few grey levels
    assert np.all(contrast > 100) and np.all(asym < 10), (contrast, asym)
    marker_corner = np.array([x0 - 0.5, y0 + 11.5])  # its bottom-left corner
    bad = np.array([c7 + [CHESS_SQUARE / 2, 0], c7 + [CHESS_SQUARE / 2] * 2, marker_corner,
                    c7])
    bad_light = np.array([light[7], light[7], -1.0, -light[7]])
    px = np.concatenate([corners, bad])
    ok = x_junction_ok(img, px, np.tile(np.eye(2) * CHESS_SQUARE, (len(px), 1, 1)),
                       np.concatenate([light, bad_light]))
    assert ok[:len(corners)].all()
    assert not ok[len(corners):].any(), ok[len(corners):]


# -- grazing views (the benchmark's viewing-angle sweep) -------------------------------------
def _turned(angle_deg: float) -> np.ndarray:
    """The robot field's pose in the benchmark's viewing-angle sweep: 220 mm ahead, turned
    ``angle_deg`` about its y axis (reference = left camera frame)."""
    return transform_from_euler([-0.025, -0.0175, 0.22], [0, angle_deg, 0])


@pytest.fixture(scope="module")
def grazing() -> tuple[SceneRenderer, MarkerField]:
    """The simulated cell's robot field (10 x 7 squares of 5 mm, DICT_4X4_1000) alone in
    the left camera, with the cell's imaging (blur, noise, illumination gradient)."""
    scene = load_scene(ROOT / "config" / "examples" / "stereo_cell.toml")
    robot = scene.placement("robot").field
    rig = replace(scene.rig, cameras={"left": scene.rig["left"]})
    sc = replace(scene, rig=rig, placements=(Placement("robot", robot, _turned(0)),),
                 rods=(), blots=())
    r = SceneRenderer(sc)
    r.prepare()
    return r, robot


@pytest.mark.parametrize("frame", [0, 1])
def test_robot_field_at_70_degrees(grazing, frame):
    """Detection, partial views and stability where methods fail (issue 3): the robot
    plane turned 70 deg from the camera (75 deg between its normal and the line of sight;
    the markers are 10-15 px wide for 40-50 px high, their bit cells under 2.5 px) is
    found with correct corner ids only, every corner within 0.5 px of the projected truth,
    and at least as many corners as OpenCV's CharucoDetector finds (6 and 12 on these
    frames; 39 and 37 of 54 here)."""
    renderer, robot = grazing
    fr = renderer.render(poses={"robot": _turned(70)}, frame=frame)
    image = fr.images["left"]
    truth = fr.truth["left"]["robot"]
    assert len(truth.corner_ids) == robot.corner_count
    found = detect_fields(image, [robot])
    assert "robot" in found
    fc = found["robot"]
    err, wrong = _score(fc, truth)
    assert wrong == []
    assert err.max() <= 0.5, f"max corner error {err.max():.3f} px"
    assert len(fc) >= 30 and len(fc.markers) >= 15, (len(fc), len(fc.markers))
    corners, ids, _, _ = cv2.aruco.CharucoDetector(robot.board).detectBoard(image)
    assert len(fc) >= (0 if ids is None else len(ids))


@pytest.mark.parametrize("angle", [50, 60, 65, 72, 75, 80])
def test_grazing_corners_are_subpixel_or_dropped(grazing, angle):
    """Detection, stability where methods fail (issue 3): from face-on to edge-on, every
    corner reported is visible in the truth and within 0.5 px of it; a corner that cannot
    be located so well is dropped. Up to 65 deg the whole field is found (>= 50 of 54
    corners). At 72 deg the markers are 8-13 px wide and some quads are several pixels
    off: one prediction landed 4.7 px from its corner, ``cornerSubPix`` gave up there and
    the point used to be reported as it was. From 75 deg (80 deg to the line of sight,
    bit cells 1-1.7 px under a 1 px blur) no marker can be read exactly, and nothing is
    reported."""
    renderer, robot = grazing
    for frame in (0, 1):
        fr = renderer.render(poses={"robot": _turned(angle)}, frame=frame)
        found = detect_fields(fr.images["left"], [robot])
        if angle <= 65:
            assert len(found["robot"]) >= 50, (frame, len(found["robot"]))
        if "robot" not in found:
            continue
        err, wrong = _score(found["robot"], fr.truth["left"]["robot"])
        assert wrong == [], (frame, wrong)
        assert err.max() <= 0.5, (frame, f"max corner error {err.max():.3f} px")
