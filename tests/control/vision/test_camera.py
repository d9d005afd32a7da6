"""Unit tests of ``oralnav.control.vision.camera`` (pinhole + OpenCV distortion, rig).

Each test's docstring names the requirement it checks (Issue 2, item 2: camera).
"""

from __future__ import annotations

import warnings

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from oralnav.control import geometry as g
from oralnav.control.errors import CameraModelError, ControlError
from oralnav.control.vision.camera import DIST_LENGTHS, CameraModel, Rig

SIZE = (1280, 960)
K = np.array([[1150.0, 0.0, 641.3], [0.0, 1162.5, 478.9], [0.0, 0.0, 1.0]])

#: Realistic non-zero coefficients for each OpenCV distortion length:
#: k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4 [tau_x tau_y]]]].
DISTORTIONS = {
    4: [-0.12, 0.05, 8e-4, -6e-4],
    5: [-0.21, 0.09, 1.2e-3, -8e-4, -0.02],
    8: [0.35, -0.08, 7e-4, 5e-4, 0.01, 0.52, -0.05, 0.02],
    12: [-0.18, 0.06, -9e-4, 4e-4, -0.01, 0.03, -0.01, 0.004, 1.5e-3, -4e-4, -1.1e-3, 3e-4],
    14: [-0.18, 0.06, -9e-4, 4e-4, -0.01, 0.03, -0.01, 0.004, 1.5e-3, -4e-4, -1.1e-3, 3e-4,
         0.012, -0.008],
}


def _points_in_front(rng: np.random.Generator, n: int, half_fov: float = 0.6) -> np.ndarray:
    """Random points 5 cm .. 2 m in front of the camera, within +-half_fov normalised."""
    z = rng.uniform(0.05, 2.0, n)
    xy = rng.uniform(-half_fov, half_fov, (n, 2)) * z[:, None]
    return np.column_stack([xy, z])


def _cv_project(p: np.ndarray, K: np.ndarray, dist, rvec=None, tvec=None) -> np.ndarray:
    rvec = np.zeros(3) if rvec is None else rvec
    tvec = np.zeros(3) if tvec is None else tvec
    uv, _ = cv2.projectPoints(p.reshape(-1, 1, 3), rvec, tvec, K, np.asarray(dist, float))
    return uv.reshape(-1, 2)


def _cv_undistort(uv: np.ndarray, K: np.ndarray, dist) -> np.ndarray:
    """cv2's iterative undistortion to normalised coordinates (OpenCV 4 and 5 spellings)."""
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-15)
    fn = getattr(cv2, "undistortPointsIter", cv2.undistortPoints)
    out = fn(uv.reshape(-1, 1, 2), K, np.asarray(dist, float), R=None, P=None,
             criteria=criteria)
    return out.reshape(-1, 2)


# -- projection ------------------------------------------------------------------------------
def test_dist_lengths_cover_opencv():
    """Issue 2 item 2: the distortion lengths accepted are OpenCV's 4, 5, 8, 12 and 14."""
    assert tuple(DIST_LENGTHS) == (4, 5, 8, 12, 14)
    assert sorted(DISTORTIONS) == list(DIST_LENGTHS)


@pytest.mark.parametrize("n", DIST_LENGTHS)
def test_project_matches_cv2_project_points(n):
    """Issue 2 item 2: CameraModel.project agrees with cv2.projectPoints to 1e-9 px for random
    points in front of the camera, for distortion length n with realistic non-zero
    coefficients (14: tilted sensor with small tau)."""
    rng = np.random.default_rng(100 + n)
    cam = CameraModel("left", SIZE, K, DISTORTIONS[n])
    p = _points_in_front(rng, 2000)
    uv = cam.project(p)
    ref = _cv_project(p, K, DISTORTIONS[n])
    assert uv.shape == (2000, 2)
    np.testing.assert_allclose(uv, ref, rtol=0, atol=1e-9)
    # the distortion is not negligible: the undistorted pinhole is far from it
    pinhole = p[:, :2] / p[:, 2:] * [K[0, 0], K[1, 1]] + K[:2, 2]
    assert np.max(np.abs(pinhole - ref)) > 5.0


@pytest.mark.parametrize("n", [5, 14])
def test_project_from_matches_cv2_with_pose(n):
    """Issue 2 item 2: project_from(T_cam_obj, p_obj) agrees with cv2.projectPoints given the
    same pose as rvec/tvec to 1e-9 px (T_cam_obj maps object points into the camera)."""
    rng = np.random.default_rng(7 + n)
    cam = CameraModel("left", SIZE, K, DISTORTIONS[n])
    T_cam_obj = g.transform_from_euler([0.02, -0.01, 0.5], [160.0, 10.0, -30.0])
    p_obj = rng.uniform(-0.05, 0.05, (300, 3))
    uv = cam.project_from(T_cam_obj, p_obj)
    rvec = Rotation.from_matrix(T_cam_obj[:3, :3]).as_rotvec()
    ref = _cv_project(p_obj, K, DISTORTIONS[n], rvec, T_cam_obj[:3, 3])
    np.testing.assert_allclose(uv, ref, rtol=0, atol=1e-9)


def test_project_without_distortion_is_pinhole():
    """Issue 2 item 2: with zero distortion, project is u = fx x/z + cx, v = fy y/z + cy."""
    cam = CameraModel("left", SIZE, K)
    assert not cam.has_distortion
    uv = cam.project([[0.1, -0.2, 2.0], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(uv, [[K[0, 0] * 0.05 + K[0, 2], K[1, 1] * -0.1 + K[1, 2]],
                                    [K[0, 2], K[1, 2]]], atol=1e-12)


@pytest.mark.parametrize("n", [5, 14])
def test_points_at_or_behind_camera_give_nan(n):
    """Issue 2 item 2: points with z <= 0 project to NaN (both coordinates, without a
    divide-by-zero warning), while the valid points of the same batch still agree with
    cv2.projectPoints."""
    cam = CameraModel("left", SIZE, K, DISTORTIONS[n])
    p = np.array([[0.1, 0.1, 1.0], [0.1, 0.1, 0.0], [0.0, 0.0, -1.0], [-0.1, 0.2, -1e-9],
                  [0.05, -0.02, 0.3]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no division by zero on the way to NaN
        uv = cam.project(p)
    assert np.all(np.isnan(uv[1:4]))
    assert np.all(np.isfinite(uv[[0, 4]]))
    np.testing.assert_allclose(uv[[0, 4]], _cv_project(p[[0, 4]], K, DISTORTIONS[n]),
                               rtol=0, atol=1e-9)
    single = cam.project(np.array([0.0, 0.0, -2.0]))
    assert single.shape == (2,) and np.all(np.isnan(single))


# -- back-projection -------------------------------------------------------------------------
def _pixel_grid(cam: CameraModel, nu: int = 33, nv: int = 25) -> np.ndarray:
    """A grid over the whole image, its outer rows/columns on the image border (pixel
    centres at integer coordinates, so the border is at -0.5 and size - 0.5)."""
    u = np.linspace(-0.5, cam.width - 0.5, nu)
    v = np.linspace(-0.5, cam.height - 0.5, nv)
    uu, vv = np.meshgrid(u, v)
    return np.column_stack([uu.ravel(), vv.ravel()])


MODERATE = {
    5: [-0.28, 0.11, 1.5e-3, -1.2e-3, -0.02],
    8: DISTORTIONS[8],
    14: DISTORTIONS[14],
}


@pytest.mark.parametrize("n", sorted(MODERATE))
def test_undistort_normalized_round_trips_whole_image(n):
    """Issue 2 item 2: undistort_normalized then re-distorting returns every pixel of a grid
    over the whole image, the four corners included, to <= 1e-8 px (moderate distortion)."""
    cam = CameraModel("left", SIZE, K, MODERATE[n])
    uv = _pixel_grid(cam)
    corners = np.array([[-0.5, -0.5], [cam.width - 0.5, -0.5], [-0.5, cam.height - 0.5],
                        [cam.width - 0.5, cam.height - 0.5]])
    for c in corners:
        assert np.any(np.all(uv == c, axis=1))
    xy = cam.undistort_normalized(uv)
    assert xy.shape == uv.shape
    assert np.all(np.isfinite(xy))
    err = np.linalg.norm(cam.normalized_to_pixels(xy) - uv, axis=1)
    assert err.max() <= 1e-8
    # the corners really are distorted (several pixels from the undistorted pinhole)
    pinhole = xy * [K[0, 0], K[1, 1]] + K[:2, 2]
    assert np.max(np.linalg.norm(pinhole - uv, axis=1)) > 10.0


@pytest.mark.parametrize("n", sorted(MODERATE))
def test_backproject_rays_reproject_to_pixels(n):
    """Issue 2 item 2: backproject gives unit rays in front of the camera that project back
    to the input pixels (<= 1e-8 px) across the whole image, corners included, and agree with
    cv2.undistortPoints where OpenCV's iteration converges."""
    rng = np.random.default_rng(40 + n)
    cam = CameraModel("left", SIZE, K, MODERATE[n])
    uv = np.vstack([_pixel_grid(cam, 17, 13),
                    rng.uniform([-0.5, -0.5], [cam.width - 0.5, cam.height - 0.5], (500, 2))])
    rays = cam.backproject(uv)
    assert rays.shape == (len(uv), 3)
    np.testing.assert_allclose(np.linalg.norm(rays, axis=1), 1.0, atol=1e-14)
    assert np.all(rays[:, 2] > 0)
    err = np.linalg.norm(cam.project(rays * 0.37) - uv, axis=1)
    assert err.max() <= 1e-8
    ref = _cv_undistort(uv, K, MODERATE[n])
    np.testing.assert_allclose(rays[:, :2] / rays[:, 2:], ref, rtol=0, atol=1e-4)


def test_backproject_of_projected_points_recovers_directions():
    """Issue 2 item 2: backproject(project(p)) is the unit direction of p (1e-10)."""
    rng = np.random.default_rng(50)
    cam = CameraModel("left", SIZE, K, MODERATE[5])
    p = _points_in_front(rng, 500, half_fov=0.5)
    rays = cam.backproject(cam.project(p))
    np.testing.assert_allclose(rays, p / np.linalg.norm(p, axis=1, keepdims=True),
                               rtol=0, atol=1e-10)


def test_undistort_empty_input():
    """Issue 2 item 2: undistort_normalized of no pixels returns an empty 0 x 2 array."""
    cam = CameraModel("left", SIZE, K, MODERATE[5])
    assert cam.undistort_normalized(np.zeros((0, 2))).shape == (0, 2)


def test_in_image_uses_pixel_centre_convention():
    """Issue 2 item 2: in_image accepts [-0.5, size - 0.5] (pixel centres at integers) and
    rejects NaN and outside pixels; margin shrinks the box."""
    cam = CameraModel("left", SIZE, K)
    uv = np.array([[-0.5, -0.5], [1279.5, 959.5], [-0.51, 10], [10, 959.6], [np.nan, 3],
                   [2.0, 2.0]])
    np.testing.assert_array_equal(cam.in_image(uv), [True, True, False, False, False, True])
    np.testing.assert_array_equal(cam.in_image(uv, margin=3.0),
                                  [False, False, False, False, False, False])


# -- validation ------------------------------------------------------------------------------
def _bad_K() -> dict[str, object]:
    skew = K.copy()
    skew[0, 1] = 0.5
    neg = K.copy()
    neg[0, 0] = -K[0, 0]
    zero_fy = K.copy()
    zero_fy[1, 1] = 0.0
    nan = K.copy()
    nan[0, 2] = np.nan
    last = K.copy()
    last[2, 2] = 2.0
    lower = K.copy()
    lower[1, 0] = 1.0
    return {"skew": skew, "negative-focal": neg, "zero-focal": zero_fy, "nan": nan,
            "bottom-row": last, "lower-skew": lower, "shape-3x4": np.hstack([K, np.zeros((3, 1))]),
            "shape-2x2": K[:2, :2], "flat": K.reshape(9)}


@pytest.mark.parametrize("case", list(_bad_K()))
def test_rejects_bad_K(case):
    """Issue 2 item 2: a K with skew, a non-positive focal length, the wrong shape, NaN or a
    bad last row raises CameraModelError (a ValueError) naming the camera."""
    with pytest.raises(CameraModelError, match="'endoscope'") as info:
        CameraModel("endoscope", SIZE, _bad_K()[case])
    assert isinstance(info.value, ValueError) and isinstance(info.value, ControlError)


@pytest.mark.parametrize("n", [0, 1, 3, 6, 7, 9, 13, 15])
def test_rejects_bad_dist_length(n):
    """Issue 2 item 2: a distortion vector whose length is not 4, 5, 8, 12 or 14 raises
    CameraModelError naming the camera and the length."""
    with pytest.raises(CameraModelError, match=rf"'right'.*got {n}\b"):
        CameraModel("right", SIZE, K, np.full(n, 1e-3))


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_rejects_non_finite_dist(bad):
    """Issue 2 item 2: a non-finite distortion coefficient raises CameraModelError naming
    the camera."""
    dist = np.array(DISTORTIONS[5])
    dist[2] = bad
    with pytest.raises(CameraModelError, match="'right'.*non-finite"):
        CameraModel("right", SIZE, K, dist)


def _bad_T() -> dict[str, np.ndarray]:
    good = g.transform_from_euler([0.06, 0.0, 0.0], [0.0, 5.0, 0.0])
    scaled = good.copy()
    scaled[:3, :3] *= 1.1
    reflection = good @ np.diag([-1.0, 1.0, 1.0, 1.0])
    bottom = good.copy()
    bottom[3, 0] = 0.2
    nan = good.copy()
    nan[2, 3] = np.nan
    return {"scaled": scaled, "reflection": reflection, "bottom-row": bottom, "nan": nan,
            "shape": good[:3]}


@pytest.mark.parametrize("case", list(_bad_T()))
def test_rejects_bad_T_ref_cam(case):
    """Issue 2 item 2: a T_ref_cam that is not a rigid transform raises CameraModelError
    naming the camera and T_ref_cam."""
    with pytest.raises(CameraModelError, match=r"camera 'right' T_ref_cam"):
        CameraModel("right", SIZE, K, np.zeros(5), _bad_T()[case])


@pytest.mark.parametrize("size", [(0, 960), (1280, -1), (1280,), "big", None])
def test_rejects_bad_size(size):
    """Issue 2 item 2: a non-positive or malformed image size raises CameraModelError naming
    the camera."""
    with pytest.raises(CameraModelError, match="'left'"):
        CameraModel("left", size, K)


def test_normalises_inputs():
    """Issue 2 item 2: list inputs become float arrays, size a tuple of ints, and the
    camera's T_cam_ref inverts T_ref_cam."""
    T = g.transform_from_euler([0.06, 0.001, -0.002], [0.5, -3.0, 0.2])
    cam = CameraModel("right", [1280, 960], K.tolist(), list(DISTORTIONS[4]), T.tolist())
    assert cam.size == (1280, 960) and (cam.width, cam.height) == (1280, 960)
    assert isinstance(cam.K, np.ndarray) and cam.K.dtype == float
    assert cam.dist.shape == (4,) and cam.has_distortion
    np.testing.assert_allclose(cam.T_cam_ref @ cam.T_ref_cam, np.eye(4), atol=1e-14)


# -- rig -------------------------------------------------------------------------------------
def _stereo(T_ref_left=None) -> Rig:
    left = CameraModel("left", SIZE, K, DISTORTIONS[5],
                       np.eye(4) if T_ref_left is None else T_ref_left)
    right = CameraModel("right", SIZE, K, DISTORTIONS[5],
                        g.transform_from_euler([0.06, 0.0, 0.0], [0.0, -4.0, 0.0]))
    return Rig("left", {"left": left, "right": right})


def test_rig_lookup():
    """Issue 2 item 2: a rig returns its cameras by name and lists their names."""
    rig = _stereo()
    assert rig["right"].name == "right"
    assert tuple(rig.names) == ("left", "right")


def test_rig_rejects_reference_camera_not_at_identity():
    """Issue 2 item 2: Rig rejects a reference camera whose T_ref_cam is not the identity,
    naming that camera."""
    T = g.transform_from_euler([0.001, 0.0, 0.0], [0.0, 0.0, 0.0])
    with pytest.raises(CameraModelError, match="'left'.*identity"):
        _stereo(T_ref_left=T)


def test_rig_with_non_camera_reference_frame():
    """Issue 2 item 2: a reference frame that names no camera leaves camera poses free."""
    cam = CameraModel("left", SIZE, K, T_ref_cam=g.transform_from_euler([0, 0, 1], [0, 0, 0]))
    rig = Rig("B", {"left": cam})
    assert rig["left"] is cam


def test_rig_unknown_camera_gives_clear_error():
    """Issue 2 item 2: looking up an unknown camera raises CameraModelError naming it and
    listing the rig's cameras."""
    with pytest.raises(CameraModelError, match=r"'endoscope'.*\['left', 'right'\]"):
        _stereo()["endoscope"]


def test_rig_rejects_empty_and_misnamed():
    """Issue 2 item 2: a rig needs at least one camera and each stored under its own name."""
    with pytest.raises(CameraModelError, match="at least one camera"):
        Rig("left", {})
    cam = CameraModel("left", SIZE, K)
    with pytest.raises(CameraModelError, match="'right'.*'left'"):
        Rig("left", {"right": cam})
