"""Unit tests of ``oralnav.control.calibration.targets``: chessboards, circle grids, ArUco
grid boards and custom-dictionary ChArUco boards found in images and calibrated from.

Each test's docstring names the requirement it checks (issue 34 item 1: calibration targets
users already have; item 2: custom dictionaries). The images are rendered here with OpenCV:
each target drawn flat, then mapped through a known camera (intrinsics and distortion) at
known poses with ``cv2.remap``; the calibration must give the camera back.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from oralnav.control.calibration.cameras import calibrate_camera, calibrate_stereo
from oralnav.control.calibration.targets import (
    ArucoGrid,
    CharucoTarget,
    Chessboard,
    CircleGrid,
    Target,
    detect_target,
)
from oralnav.control.errors import MarkerFieldError
from oralnav.control.vision.camera import CameraModel
from oralnav.control.vision.markers import MarkerField

SIZE = (640, 480)
K_TRUE = np.array([[600.0, 0, 322.5], [0, 598.0, 236.0], [0, 0, 1]])
DIST_TRUE = np.array([-0.12, 0.08, 0.0005, -0.0004, 0.0])
FOCAL_REL = 5e-3        # focal lengths within 0.5 % ...
PP_PX = 2.0             # ... and the principal point within 2 px (or 3 sigma, _check_fit)


# -- rendering -----------------------------------------------------------------------------
@pytest.fixture(scope="module")
def ideal_px() -> np.ndarray:
    """For every pixel of the distorted image, where the ideal pinhole camera sees it
    (H x W x 2): one ``undistortPoints`` for every view."""
    u, v = np.meshgrid(np.arange(SIZE[0], dtype=np.float64),
                       np.arange(SIZE[1], dtype=np.float64))
    pts = np.stack([u, v], axis=-1).reshape(-1, 1, 2)
    ideal = cv2.undistortPoints(pts, K_TRUE, DIST_TRUE, R=None, P=K_TRUE, criteria=(
        cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-9))
    return ideal.reshape(SIZE[1], SIZE[0], 2)


def _pose(rx: float, ry: float, rz: float, centre_board: np.ndarray,
          at: tuple[float, float, float]) -> np.ndarray:
    """T_cam_board: the board tilted (deg) about its centre, that centre at ``at`` (m)."""
    R = Rotation.from_euler("xyz", [rx, ry, rz], degrees=True).as_matrix()
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(at) - R @ centre_board
    return T


#: Tilts (deg about x, y, z) and where the board's centre goes (x, y, z in m at ~0.5 m).
POSES = [(25, 0, 3, (0.0, 0.0, 0.50)), (-25, 0, -4, (0.02, 0.01, 0.48)),
         (0, 28, 2, (-0.03, 0.0, 0.50)), (0, -28, 6, (0.03, -0.02, 0.52)),
         (20, 20, -8, (-0.05, -0.04, 0.55)), (-20, 20, 5, (0.05, 0.04, 0.55)),
         (20, -22, 0, (0.06, -0.05, 0.58)), (-18, -20, -3, (-0.06, 0.05, 0.56)),
         (10, 5, 12, (0.0, 0.0, 0.42))]


def _render(texture: np.ndarray, board_to_tex: np.ndarray, T: np.ndarray,
            ideal: np.ndarray) -> np.ndarray:
    """The flat ``texture`` (board metres -> texture px by ``board_to_tex``, 3 x 3, texture
    pixel centres at whole numbers) seen at pose ``T`` through the distorted camera."""
    H = K_TRUE @ np.c_[T[:3, :2], T[:3, 3]] @ np.linalg.inv(board_to_tex)  # texture -> ideal
    src = cv2.perspectiveTransform(ideal.reshape(-1, 1, 2), np.linalg.inv(H))
    src = src.reshape(SIZE[1], SIZE[0], 2).astype(np.float32)
    img = cv2.remap(texture, src[..., 0], src[..., 1], cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_CONSTANT, borderValue=255)
    img = cv2.GaussianBlur(img, (0, 0), 0.6)
    noise = np.random.default_rng(int(abs(T[0, 3]) * 1e4)).normal(0, 1.0, img.shape)
    return np.clip(img + noise, 0, 255).astype(np.uint8)


def _scale(k: float, ox: float, oy: float) -> np.ndarray:
    """Board metres -> texture px: ``k`` px per metre, the board origin ``(ox, oy)`` m from
    the texture's top-left edge (a pixel centre lies half a pixel inside its edges)."""
    return np.array([[k, 0, ox * k - 0.5], [0, k, oy * k - 0.5], [0, 0, 1]])


def _chessboard_texture(t: Chessboard, pps: int = 40) -> tuple[np.ndarray, np.ndarray]:
    nx, ny = t.inner_corners
    cols, rows = nx + 1 + 2, ny + 1 + 2          # the squares and a white square around
    img = np.full((rows * pps, cols * pps), 255, np.uint8)
    for r in range(1, rows - 1):
        for c in range(1, cols - 1):
            if (r + c) % 2 == 0:
                img[r * pps:(r + 1) * pps, c * pps:(c + 1) * pps] = 0
    return img, _scale(pps / t.square, 2 * t.square, 2 * t.square)


def _circles_texture(t: CircleGrid, ppm: float = 1600.0) -> tuple[np.ndarray, np.ndarray]:
    xy = t.corners[:, :2]
    margin = 1.5 * t.spacing
    w, h = xy.max(axis=0) + 2 * margin
    img = np.full((int(h * ppm), int(w * ppm)), 255, np.uint8)
    S = _scale(ppm, margin, margin)
    shift = 4  # sub-pixel centres (1/16 px)
    for x, y in xy:
        u, v, _ = S @ (x, y, 1)
        cv2.circle(img, (int(round(u * 16)), int(round(v * 16))),
                   int(round(0.3 * t.spacing * ppm * 16)), 0, -1, cv2.LINE_AA, shift)
    return img, S


def _board_texture(board, size_m: tuple[float, float], ppm: float,
                   margin_px: int) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's own drawing of an ArUco or ChArUco board (``generateImage``) with its
    placement: the board, ``size_m`` from its origin, fills the image inside ``margin_px``
    (whole pixels at ``ppm``, so that nothing is rescaled)."""
    w, h = round(size_m[0] * ppm), round(size_m[1] * ppm)
    img = board.generateImage((w + 2 * margin_px, h + 2 * margin_px), marginSize=margin_px,
                              borderBits=1)
    return img, _scale(ppm, margin_px / ppm, margin_px / ppm)


def _views(target: Target | MarkerField, texture: np.ndarray, S: np.ndarray, ideal,
           poses=POSES):
    centre = 0.5 * (target.corners.min(axis=0) + target.corners.max(axis=0))
    out, truth = [], []
    for rx, ry, rz, at in poses:
        T = _pose(rx, ry, rz, centre, at)
        out.append(detect_target(_render(texture, S, T, ideal), target))
        truth.append(T)
    return out, truth


def _check_fit(cal) -> None:
    """fx, fy within 0.5 % and cx, cy within 2 px of the truth, or within three of
    OpenCV's own standard deviations where the target's corners allow no better."""
    got = np.r_[np.diag(cal.K)[:2], cal.K[:2, 2]]
    true = np.r_[np.diag(K_TRUE)[:2], K_TRUE[:2, 2]]
    tol = np.maximum(np.r_[FOCAL_REL * true[:2], PP_PX, PP_PX], 3 * cal.K_std)
    assert np.all(np.abs(got - true) < tol), (got, tol)


def _exact(target, views, truth) -> float:
    """Largest distance (px) of a detected point from its true projection."""
    cam = CameraModel("c", SIZE, K_TRUE, DIST_TRUE)
    worst = 0.0
    for v, T in zip(views, truth, strict=True):
        if v is not None:
            p = cam.project_from(T, target.corners[v.ids])
            worst = max(worst, float(np.abs(p - v.px).max()))
    return worst


# -- each family -----------------------------------------------------------------------------
def test_chessboard_views_give_the_camera_back(ideal_px):
    """Item 1 (chessboard): OpenCV's chessboard detector finds every corner of a 9 x 6
    inner-corner board in all nine rendered views, within 0.35 px of its true projection,
    and the views calibrate to the true focal lengths (0.5 %) and principal point (2 px)."""
    t = Chessboard("cb", (9, 6), 0.025)
    views, truth = _views(t, *_chessboard_texture(t), ideal_px)
    assert all(v is not None and len(v) == 54 for v in views)
    assert _exact(t, views, truth) < 0.35
    _check_fit(calibrate_camera(views, t, SIZE))


@pytest.mark.parametrize("asymmetric", [False, True], ids=["symmetric", "asymmetric"])
def test_circle_grid_views_give_the_camera_back(ideal_px, asymmetric):
    """Item 1 (circle grids): findCirclesGrid finds a 7 x 5 symmetric grid and OpenCV's
    4 x 11 asymmetric grid in every view, the centres within 0.5 px of the true projection
    (a circle's image centre is not quite its centre's image), and they calibrate to the
    true focal lengths (0.5 %) and principal point (2 px)."""
    t = (CircleGrid("ac", (4, 11), 0.015, asymmetric=True) if asymmetric
         else CircleGrid("c", (7, 5), 0.03))
    views, truth = _views(t, *_circles_texture(t), ideal_px)
    assert all(v is not None and len(v) == t.corner_count for v in views)
    assert _exact(t, views, truth) < 0.5
    _check_fit(calibrate_camera(views, t, SIZE))


def test_aruco_grid_views_give_the_camera_back(ideal_px):
    """Item 1 (ArUco grid): a 5 x 7 GridBoard drawn by OpenCV (generateImage) is found by
    ArucoDetector and matchImagePoints, every marker corner given its id, within 2 px of
    its true projection (a marker's outer corners, unlike a chessboard's saddle points,
    come out some tenths of a pixel inside the marker once blurred), and calibrates to the
    true intrinsics within three of OpenCV's standard deviations (about 0.5 % in focal
    length: its corners are the least precise of the families)."""
    t = ArucoGrid("g", (5, 7), 0.025, 0.006, "DICT_6X6_250", first_id=10)
    size = (5 * 0.025 + 4 * 0.006, 7 * 0.025 + 6 * 0.006)
    views, truth = _views(t, *_board_texture(t.board, size, 2000.0, 40), ideal_px)
    assert all(v is not None and len(v) == 140 for v in views)
    assert _exact(t, views, truth) < 2.0
    _check_fit(calibrate_camera(views, t, SIZE))


def _custom_dictionary() -> cv2.aruco.Dictionary:
    """A dictionary of one's own: 40 codes of 5 x 5 bits (OpenCV's extendDictionary)."""
    return cv2.aruco.extendDictionary(40, 5, randomSeed=7)


def test_custom_dictionary_charuco_views_give_the_camera_back(ideal_px):
    """Item 2 (custom dictionary): a ChArUco board printed with a dictionary of one's own
    is found through OpenCV's CharucoDetector; its corner ids and frame are those of a
    tracked ChArUco field of the same size, and it calibrates to the true intrinsics
    (focal lengths within 0.5 %, the principal point within three standard deviations)."""
    t = CharucoTarget("own", (9, 7), 0.025, 0.018, "own.yml", _custom_dictionary())
    same = MarkerField("f", "DICT_5X5_50", (9, 7), 0.025, 0.018)
    np.testing.assert_allclose(t.corners, same.corners, atol=1e-9)
    views, truth = _views(t, *_board_texture(t.board, (0.225, 0.175), 2400.0, 40), ideal_px)
    assert all(v is not None and len(v) >= 40 for v in views)
    assert _exact(t, views, truth) < 0.5
    _check_fit(calibrate_camera(views, t, SIZE))


def _stereo_chessboard(t: Chessboard, ideal, turn: float = 180.0):
    """Views of ``t`` through a left camera and one 60 mm to its right, every other view
    turned by ``turn`` deg about the board normal: (left views, right views, truth)."""
    tex, S = _chessboard_texture(t)
    centre = 0.5 * (t.corners.min(axis=0) + t.corners.max(axis=0))
    T_left_right = np.eye(4)
    T_left_right[0, 3] = 0.06
    left, right, truth = [], [], []
    for k, (rx, ry, rz, at) in enumerate(POSES):
        T = _pose(rx, ry, rz + (turn if k % 2 else 0), centre, at)
        left.append(detect_target(_render(tex, S, T, ideal), t))
        right.append(detect_target(_render(tex, S, np.linalg.inv(T_left_right) @ T, ideal), t))
        truth.append(T)
    return left, right, truth


def test_half_turned_chessboard_is_numbered_by_its_colours(ideal_px):
    """Item 1 (stereo with chessboards): a 9 x 6 board (nx + ny odd) shown the other way
    up in every other view is numbered from its dark end in both cameras, so every
    corner gets its own id (within 0.35 px of its true projection) and the stereo fit
    pairs the right corners (no view dropped, the 60 mm baseline within 0.2 mm)."""
    t = Chessboard("cb", (9, 6), 0.025)
    left, right, truth = _stereo_chessboard(t, ideal_px)
    assert _exact(t, left, truth) < 0.35
    cams = [CameraModel(n, SIZE, K_TRUE, DIST_TRUE) for n in ("left", "right")]
    st = calibrate_stereo(left, right, t, *cams)
    assert st.rejected == () and abs(st.baseline - 0.06) < 0.2e-3


def test_symmetric_chessboard_is_numbered_with_its_rows_rightward(ideal_px):
    """Item 1 (stereo with chessboards): an 8 x 6 board (nx + ny even: the same after a
    half turn, colours included) is numbered so that its first row runs rightward in
    both images, turned or not, and the stereo fit pairs the right corners."""
    t = Chessboard("cb", (8, 6), 0.025)
    left, right, _ = _stereo_chessboard(t, ideal_px)
    for v in left + right:
        assert v.px[7, 0] > v.px[0, 0]
    cams = [CameraModel(n, SIZE, K_TRUE, DIST_TRUE) for n in ("left", "right")]
    st = calibrate_stereo(left, right, t, *cams)
    assert st.rejected == () and abs(st.baseline - 0.06) < 0.2e-3


# -- bad input ---------------------------------------------------------------------------------
def test_target_not_in_the_image_is_none():
    """Item 1 (same bad-input behaviour): an image without the target gives None (the view
    is then skipped and reported), for every family."""
    blank = np.full((120, 160), 200, np.uint8)
    for t in (Chessboard("a", (4, 3), 0.01), CircleGrid("b", (4, 3), 0.01),
              CircleGrid("c", (4, 5), 0.01, asymmetric=True),
              ArucoGrid("d", (2, 2), 0.01, 0.002, "DICT_4X4_50"),
              CharucoTarget("e", (4, 3), 0.01, 0.007, "own", _custom_dictionary())):
        assert detect_target(blank, t) is None, t.family


@pytest.mark.parametrize("make,reason", [
    (lambda: Chessboard("a", (2, 6), 0.01), "inner_corners must be two whole numbers >= 3"),
    (lambda: Chessboard("a", (9, 6), -0.01), "square must be a positive length"),
    (lambda: CircleGrid("a", (2, 1), 0.01), "grid must be two whole numbers >= 2"),
    (lambda: ArucoGrid("a", (1, 1), 0.01, 0.002, "DICT_4X4_50"), "at least 2 markers"),
    (lambda: ArucoGrid("a", (5, 7), 0.01, 0.002, "DICT_4X4_50", first_id=20),
     "ids 20..54 overflow DICT_4X4_50"),
    (lambda: ArucoGrid("a", (5, 7), 0.01, 0.002, "DICT_9X9"), "unknown ArUco dictionary"),
    (lambda: CharucoTarget("a", (9, 7), 0.01, 0.01, "own", _custom_dictionary()),
     "must be smaller than square"),
    (lambda: CharucoTarget("a", (10, 9), 0.01, 0.007, "own.yml", _custom_dictionary()),
     "ids 0..44 overflow own.yml, which has ids 0..39"),
], ids=["corners", "square", "grid", "markers", "overflow", "dictionary", "marker",
        "custom_overflow"])
def test_malformed_targets_are_refused(make, reason):
    """Item 1 (bad input): a target that cannot be built is a MarkerFieldError (a
    ValueError the fields file turns into an error at its key) saying what is wrong."""
    with pytest.raises(MarkerFieldError, match=reason.replace(".", r"\.")):
        make()
