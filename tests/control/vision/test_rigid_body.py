"""Unit tests of ``oralnav.control.vision.rigid_body`` (ArUco rigid bodies as tracked objects).

Each test's docstring names the requirement it checks ("rigid bodies: ..."). Poses are
checked on synthetic corners projected through a distorted camera, so an exact fit must
come back to 1e-6 (m, rad).
"""

from __future__ import annotations

import threading

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from oralnav.control.errors import ControlError, MarkerFieldError
from oralnav.control.geometry import invert, make_transform, pose_error
from oralnav.control.vision.camera import CameraModel
from oralnav.control.vision.rigid_body import (
    T_TAG_OPENCV_MARKER,
    BodyPose,
    RigidBody,
    cached_detector,
    default_detector_parameters,
    detect_tag_list,
    detect_tags,
    estimate_body_pose,
    single_tag_body,
    unique_tags,
)

SIDE = 0.0145  # m, the peer's reference tags
PITCH = 0.0175


def _square(centre, side=SIDE, R=None) -> np.ndarray:
    """A square tag in OpenCV order (x right, y down on the print), optionally rotated."""
    h = side / 2
    c = np.array([[-h, -h, 0.0], [h, -h, 0.0], [h, h, 0.0], [-h, h, 0.0]])
    if R is not None:
        c = c @ R.T
    return c + np.asarray(centre, dtype=float)


def _planar_body(n=(3, 4), first=10, dictionary="DICT_ARUCO_ORIGINAL") -> RigidBody:
    tags = {}
    for j in range(n[1]):
        for i in range(n[0]):
            tags[first + j * n[0] + i] = _square((i * PITCH, j * PITCH, 0.0))
    return RigidBody("plate", dictionary, tags)


def _cube_body() -> RigidBody:
    """Tags on three faces of a 30 mm cube: a non-planar body."""
    a = 0.015
    faces = {
        1: (Rotation.identity(), (0.0, 0.0, -a)),
        2: (Rotation.from_euler("y", 90, degrees=True), (-a, 0.0, 0.0)),
        3: (Rotation.from_euler("x", -90, degrees=True), (0.0, -a, 0.0)),
    }
    tags = {}
    for k, (rot, centre) in faces.items():
        for m, off in enumerate(((-0.006, 0.0, 0.0), (0.006, 0.0, 0.0))):
            tags[10 * k + m] = rot.apply(_square(off, side=0.01)) + np.asarray(centre)
    return RigidBody("cube", "DICT_4X4_50", tags)


@pytest.fixture(scope="module")
def camera() -> CameraModel:
    K = np.array([[1100.0, 0.0, 640.0], [0.0, 1090.0, 480.0], [0.0, 0.0, 1.0]])
    return CameraModel("left", (1280, 960), K, np.array([-0.12, 0.08, 0.001, -0.0015, -0.01]))


# Bodies face the camera: a tag's z points away from a camera that sees its printed face.
T_TRUE = make_transform(Rotation.from_euler("xyz", [20.0, 15.0, -30.0], degrees=True),
                        [0.012, -0.02, 0.31])


def _observe(body: RigidBody, camera: CameraModel, T=T_TRUE, ids=None) -> dict:
    ids = body.ids if ids is None else ids
    return {t: camera.project_from(T, body.tags[t]) for t in ids}


def _assert_pose(pose: BodyPose | None, T=T_TRUE, tol=1e-6) -> None:
    assert pose is not None
    dt, dr = pose_error(pose.T_cam_body, T)
    assert dt < tol and dr < tol, (dt, dr)


# -- pose ---------------------------------------------------------------------------------------
def test_planar_body_pose_recovered(camera):
    """rigid bodies: a planar multi-tag body's pose comes back to 1e-6 m / rad from exact
    corners through a distorted camera, with all tags used and quality 1."""
    body = _planar_body()
    pose = estimate_body_pose(body, _observe(body, camera), camera)
    _assert_pose(pose)
    assert pose.tags_used == pose.tags_seen == body.ids
    assert pose.quality == 1.0
    assert pose.reproj_rms_px < 1e-6
    assert pose.body == "plate" and pose.camera == "left"
    assert pose.tags_rejected == ()


def test_non_planar_body_pose_recovered(camera):
    """rigid bodies: tags on three faces of a cube (non-planar) give the pose to 1e-6."""
    body = _cube_body()
    # the cube's (1, 1, 1) diagonal along the optical axis: all three faces in view
    diag, _ = Rotation.align_vectors([[0.0, 0.0, 1.0]], [np.ones(3) / np.sqrt(3)])
    T = make_transform(Rotation.from_euler("z", 25, degrees=True) * diag, [-0.01, 0.015, 0.25])
    pose = estimate_body_pose(body, _observe(body, camera, T), camera)
    _assert_pose(pose, T)


@pytest.mark.parametrize("rotvec", [(0.0, 0.0, 0.0), (0.5, -0.3, 0.2), (-0.2, 0.9, 2.5)])
def test_single_tag_pose_recovered(camera, rotvec):
    """rigid bodies: one visible tag (IPPE_SQUARE, both mirror solutions polished by LM)
    gives its exact pose, including a tag off the body origin and tilted."""
    body = _planar_body()
    T = make_transform(Rotation.from_rotvec(rotvec), [0.01, 0.0, 0.2])
    pose = estimate_body_pose(body, _observe(body, camera, T, ids=[15]), camera)
    _assert_pose(pose, T)
    assert pose.tags_used == (15,)
    assert pose.quality == pytest.approx(1 / 12)


def test_single_rectangular_tag_pose_recovered(camera):
    """rigid bodies: a lone tag that is not square (a scaled print) still converges: the
    square only seeds LM, which fits the real corners."""
    rect = _square((0.0, 0.0, 0.0)) * np.array([1.6, 1.0, 1.0])
    body = RigidBody("rect", "DICT_4X4_50", {7: rect})
    pose = estimate_body_pose(body, _observe(body, camera), camera)
    _assert_pose(pose)


def test_quality_is_visible_over_total(camera):
    """rigid bodies: quality is visible tags / body tags, like the peer tracker (11 of 12
    gives 0.91667); tags of other bodies are ignored."""
    body = _planar_body()
    seen = _observe(body, camera, ids=body.ids[1:])
    seen[999] = np.array([[1.0, 1.0], [50.0, 1.0], [50.0, 50.0], [1.0, 50.0]])
    pose = estimate_body_pose(body, seen, camera)
    _assert_pose(pose)
    assert pose.quality == pytest.approx(11 / 12)
    assert 999 not in pose.tags_seen


def test_single_tag_body_matches_opencv_marker_frame(camera):
    """rigid bodies: single_tag_body follows the field convention (y down, z away), and
    T_TAG_OPENCV_MARKER turns it into OpenCV's single-marker frame (y up, z to camera)."""
    s = 0.05
    body = single_tag_body(0, s, "DICT_4X4_50")
    assert body.name == "DICT_4X4_50:0"
    opencv = np.array([[-s / 2, s / 2, 0], [s / 2, s / 2, 0], [s / 2, -s / 2, 0],
                       [-s / 2, -s / 2, 0]])
    marker_in_tag = opencv @ T_TAG_OPENCV_MARKER[:3, :3].T
    np.testing.assert_allclose(marker_in_tag, body.tags[0], atol=1e-15)
    # a tag facing the camera: the OpenCV marker frame then has z toward the camera
    T = make_transform(Rotation.from_euler("x", 10, degrees=True), [0.0, 0.0, 0.2])
    pose = estimate_body_pose(body, _observe(body, camera, T), camera)
    T_cam_marker = pose.T_cam_body @ T_TAG_OPENCV_MARKER
    assert T_cam_marker[2, 2] < -0.9  # marker z points back at the camera
    np.testing.assert_allclose(T_cam_marker @ invert(T_TAG_OPENCV_MARKER), pose.T_cam_body)


# -- wrong and duplicate tags ----------------------------------------------------------------------
def test_wrong_tag_is_left_out(camera):
    """rigid bodies: a tag whose corners sit elsewhere (a misread id) is rejected by the
    tag consensus; the pose from the others stays exact."""
    body = _planar_body()
    seen = _observe(body, camera)
    seen[12] = seen[12] + np.array([80.0, -45.0])
    pose = estimate_body_pose(body, seen, camera)
    _assert_pose(pose)
    assert 12 not in pose.tags_used
    assert pose.tags_rejected == (12,)
    assert pose.quality == 1.0  # it was seen; it just disagreed


def test_several_wrong_tags_are_left_out(camera):
    """rigid bodies: three wrong tags out of twelve (one moved far, one slightly, one
    seen where another tag is, turned a quarter) are all rejected; the pose stays exact."""
    body = _planar_body()
    seen = _observe(body, camera)
    seen[10] = seen[10] + np.array([-150.0, 30.0])
    seen[16] = seen[16] + np.array([12.0, 0.0])
    seen[21] = _observe(body, camera)[20][[1, 2, 3, 0]]  # right place, turned a quarter
    pose = estimate_body_pose(body, seen, camera)
    _assert_pose(pose)
    assert pose.tags_rejected == (10, 16, 21)


def test_two_disagreeing_tags_give_no_pose(camera):
    """rigid bodies: with two tags that disagree there is no way to tell the right one,
    so no pose is returned rather than one from the wrong tag."""
    body = _planar_body()
    seen = _observe(body, camera, ids=[10, 11])
    seen[11] = seen[11] + np.array([0.0, 120.0])
    assert estimate_body_pose(body, seen, camera) is None


def test_duplicate_ids_dropped(camera):
    """rigid bodies: a tag id seen twice in one image (the same tag twice) is dropped, never
    used silently: the pose comes from the other tags, and a body seen only through the
    duplicated id gets no pose."""
    body = _planar_body()
    good = _observe(body, camera)
    pairs = list(good.items()) + [(13, good[13] + np.array([200.0, 10.0]))]
    pose = estimate_body_pose(body, pairs, camera)
    _assert_pose(pose)
    assert 13 not in pose.tags_seen and 13 not in pose.tags_used
    assert pose.quality == pytest.approx(11 / 12)
    only = [(13, good[13]), (13, good[13] + np.array([200.0, 10.0]))]
    assert estimate_body_pose(body, only, camera) is None
    assert unique_tags(only) == {}


def test_no_or_degenerate_tags_give_no_pose(camera):
    """rigid bodies: no tag of the body, or only degenerate image quads (collinear or
    coincident corners), give None."""
    body = _planar_body()
    assert estimate_body_pose(body, {}, camera) is None
    assert estimate_body_pose(body, [], camera) is None
    assert estimate_body_pose(body, {500: np.ones((4, 2))}, camera) is None
    line = np.array([[10.0, 10.0], [20.0, 20.0], [30.0, 30.0], [40.0, 40.0]])
    assert estimate_body_pose(body, {10: line}, camera) is None
    assert estimate_body_pose(body, {10: line, 11: np.full((4, 2), 5.0)}, camera) is None


@pytest.mark.parametrize("corners, reason", [
    (np.zeros((3, 2)), "expected 4 corners"),
    (np.array([[0.0, 0], [1, 0], [1, np.nan], [0, 1]]), "non-finite"),
    ("abcd", "must be numbers"),
])
def test_malformed_detections_rejected(camera, corners, reason):
    """rigid bodies: malformed detections (wrong shape, NaN, not numbers) raise
    MarkerFieldError naming the tag."""
    with pytest.raises(MarkerFieldError, match=reason):
        estimate_body_pose(_planar_body(), {10: corners}, camera)


def test_opencv_shaped_detections_accepted(camera):
    """rigid bodies: corners in OpenCV's (1, 4, 2) float32 layout are taken as they come."""
    body = _planar_body()
    seen = {t: c.reshape(1, 4, 2).astype(np.float32) for t, c in _observe(body, camera).items()}
    pose = estimate_body_pose(body, seen, camera)
    _assert_pose(pose, tol=1e-4)  # float32 pixels


# -- the body ----------------------------------------------------------------------------------
@pytest.mark.parametrize("tags, reason", [
    ({1: np.full((4, 3), np.nan)}, "non-finite"),
    ({1: np.zeros((3, 3))}, "4 x 3"),
    ({1: np.zeros((4, 3))}, "degenerate"),
    ({1: [[0, 0, 0], [0.01, 0, 0], [0.02, 0, 0], [0.03, 0, 0]]}, "degenerate"),
    ({1: _square((0, 0, 0))[[0, 2, 1, 3]]}, "crossed"),
    ({1: [[0, 0, 0], [0.01, 0, 0], [0.002, 0.002, 0], [0, 0.01, 0]]}, "one direction"),
    ([(1, _square((0, 0, 0))), (1, _square((0.02, 0, 0)))], "given twice"),
    ({50: _square((0, 0, 0))}, "outside DICT_4X4_50"),
    ({-1: _square((0, 0, 0))}, "outside DICT_4X4_50"),
    ({1.0: _square((0, 0, 0))}, "integer"),
    ({True: _square((0, 0, 0))}, "integer"),
    ({}, "at least one tag"),
    (42, "mapping"),
])
def test_bad_body_rejected(tags, reason):
    """rigid bodies: a body with non-finite, misshapen, degenerate or crossed tags, a
    repeated id, an id outside its dictionary or no tag raises MarkerFieldError."""
    with pytest.raises(MarkerFieldError, match=reason):
        RigidBody("b", "DICT_4X4_50", tags)


def test_bad_body_name_or_dictionary_rejected():
    """rigid bodies: an empty name or an unknown dictionary is a MarkerFieldError (a
    ControlError and a ValueError)."""
    with pytest.raises(MarkerFieldError, match="name"):
        RigidBody("", "DICT_4X4_50", {1: _square((0, 0, 0))})
    with pytest.raises(MarkerFieldError, match="unknown ArUco dictionary"):
        RigidBody("b", "DICT_NOPE", {1: _square((0, 0, 0))})
    with pytest.raises(ControlError):
        single_tag_body(0, -0.01, "DICT_4X4_50")
    assert issubclass(MarkerFieldError, ValueError)


def test_body_is_frozen_and_sorted():
    """rigid bodies: a body is immutable (mapping and arrays read-only), ids sorted, and
    corners() stacks the requested tags in order."""
    body = RigidBody("b", "DICT_4X4_50", {5: _square((0.02, 0, 0)), 2: _square((0, 0, 0))})
    assert body.ids == (2, 5) and len(body) == 2
    with pytest.raises(TypeError):
        body.tags[3] = _square((0, 0, 0))  # type: ignore[index]
    with pytest.raises(ValueError):
        body.tags[2][0, 0] = 1.0
    np.testing.assert_array_equal(body.corners([5, 2])[:4], body.tags[5])
    assert body.corners([]).shape == (0, 3)


# -- detection ----------------------------------------------------------------------------------
def _marker_image(placements, dictionary="DICT_4X4_50", px=80, size=(480, 360)) -> np.ndarray:
    img = np.full((size[1], size[0]), 255, np.uint8)
    dic = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary))
    for tid, (x, y) in placements:
        img[y:y + px, x:x + px] = cv2.aruco.generateImageMarker(dic, tid, px)
    return img


def test_detect_tags_corners_and_order():
    """rigid bodies: detect_tags returns id -> (4, 2) float64 px in OpenCV order (top-left
    first, clockwise), within half a pixel of the printed corners, for mono8 and BGR."""
    img = _marker_image([(3, (40, 60)), (7, (240, 150))])
    for image in (img, cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)):
        tags = detect_tags(image, "DICT_4X4_50")
        assert sorted(tags) == [3, 7]
        c = tags[3]
        assert c.shape == (4, 2) and c.dtype == np.float64
        expect = np.array([[39.5, 59.5], [119.5, 59.5], [119.5, 139.5], [39.5, 139.5]])
        np.testing.assert_allclose(c, expect, atol=0.5)


def test_detect_tags_drops_duplicates():
    """rigid bodies: the same tag twice in one image is left out by detect_tags (both
    copies) but listed twice by detect_tag_list."""
    img = _marker_image([(3, (40, 60)), (3, (240, 150)), (9, (40, 220))])
    assert sorted(t for t, _ in detect_tag_list(img, "DICT_4X4_50")) == [3, 3, 9]
    assert sorted(detect_tags(img, "DICT_4X4_50")) == [9]


def test_detector_cached_per_dictionary_and_params_honoured():
    """rigid bodies: one detector per dictionary is kept (per thread); explicit parameters
    build their own and are honoured; the default refines corners to sub-pixel."""
    assert cached_detector("DICT_4X4_50") is cached_detector("DICT_4X4_50")
    assert cached_detector("DICT_4X4_50") is not cached_detector("DICT_ARUCO_ORIGINAL")
    other = []
    t = threading.Thread(target=lambda: other.append(cached_detector("DICT_4X4_50")))
    t.start()
    t.join()
    assert other[0] is not cached_detector("DICT_4X4_50")
    p = default_detector_parameters()
    assert p.cornerRefinementMethod == cv2.aruco.CORNER_REFINE_SUBPIX
    img = _marker_image([(3, (40, 60))])
    p.minMarkerPerimeterRate = 0.9  # larger than the marker: nothing found
    assert detect_tags(img, "DICT_4X4_50", p) == {}
    assert sorted(detect_tags(img, "DICT_4X4_50")) == [3]


@pytest.mark.parametrize("image", [np.zeros((10, 10), np.float32), np.zeros((4, 4, 2), np.uint8),
                                   [[0, 1], [1, 0]]])
def test_detect_tags_bad_image(image):
    """rigid bodies: an image that is not mono8 / BGR / BGRA uint8 is a MarkerFieldError."""
    with pytest.raises(MarkerFieldError, match="image"):
        detect_tags(image, "DICT_4X4_50")


def test_detect_then_pose_on_rendered_tag():
    """rigid bodies: detection and pose chain on a rendered tag: the pose of a fronto-parallel
    tag 80 px wide seen by an ideal camera matches its placement within 1 mm."""
    img = _marker_image([(5, (200, 140))])
    cam = CameraModel("c", (480, 360), np.array([[400.0, 0, 239.5], [0, 400.0, 179.5],
                                                  [0, 0, 1]]))
    side = 0.02
    body = single_tag_body(5, side, "DICT_4X4_50")
    pose = estimate_body_pose(body, detect_tags(img, "DICT_4X4_50"), cam)
    assert pose is not None
    z = 400.0 * side / 80.0
    centre_px = np.array([239.5, 179.5])
    expect = np.array([(*(((200 - 0.5 + 40) - centre_px[0]) * z / 400.0,
                          ((140 - 0.5 + 40) - centre_px[1]) * z / 400.0), z)])
    np.testing.assert_allclose(pose.T_cam_body[:3, 3], expect.ravel(), atol=1e-3)
    np.testing.assert_allclose(pose.T_cam_body[:3, :3], np.eye(3), atol=0.05)
