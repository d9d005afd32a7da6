"""Tests of ``oralnav.config.camera_files`` and the rig entry points that use it
(``load_rig``, ``save_rig_as``): camera files of OpenCV, ROS and Kalibr.

Each test's docstring names the requirement it checks (Issue 34 item 2: camera files in the
formats the ecosystem uses).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from oralnav.config.camera_files import (
    detect_format,
    load_camera_file,
    load_kalibr,
    load_opencv,
    load_ros,
    sniff_format,
)
from oralnav.config.errors import ConfigError
from oralnav.config.rig import load_rig, save_rig, save_rig_as
from oralnav.control.geometry import invert
from oralnav.control.vision.camera import CameraModel, Rig

from .helpers import expect_config_error, write_file

DATA = Path(__file__).resolve().parent / "data" / "camera_files"
ROS_PAIR = DATA / "ros_stereo"
#: the same pair written by ROS's own C++ writer (camera_calibration_parsers; README there)
ROS_PARSERS_PAIR = DATA / "ros_parsers_stereo"
KALIBR = DATA / "kalibr-camchain.yaml"

# The rig the fixtures in data/camera_files hold (see the README there): 1280 x 1024 px,
# radtan distortion (k3 = 0, so every format holds it), the right camera 61 mm along x.
SIZE = (1280, 1024)
K_L = np.array([[1400.5, 0.0, 640.25], [0.0, 1399.75, 511.5], [0.0, 0.0, 1.0]])
D_L = np.array([-0.081234, 0.123456, 0.000211, -0.000312])
K_R = np.array([[1402.25, 0.0, 630.75], [0.0, 1401.5, 515.125], [0.0, 0.0, 1.0]])
D_R = np.array([-0.079876, 0.118765, -0.000123, 0.000234])
T_L_R = np.eye(4)
T_L_R[:3, :3] = Rotation.from_euler("xyz", [0.4, -1.2, 0.3], degrees=True).as_matrix()
T_L_R[:3, 3] = [0.0612, 0.0004, -0.0011]


def _stereo(names=("left", "right"), dist=(D_L, D_R)) -> Rig:
    left = CameraModel(names[0], SIZE, K_L, dist[0])
    right = CameraModel(names[1], SIZE, K_R, dist[1], T_L_R)
    return Rig(names[0], {names[0]: left, names[1]: right})


def _mono(name="endoscope", dist=(-0.28, 0.09, 0.0012, -0.0007, -0.011, 0.02, 0.001, -0.003)):
    cam = CameraModel(name, (1920, 1080), [[1050.0, 0, 961.5], [0, 1049.0, 538.25], [0, 0, 1]],
                      np.array(dist))
    return Rig(name, {name: cam})


def _padded(d: np.ndarray) -> np.ndarray:
    out = np.zeros(14)
    out[:d.size] = d
    return out


def assert_same_rig(a: Rig, b: Rig, *, tol_k=1e-12, tol_d=1e-15, tol_r=1e-12,
                    tol_t=1e-12) -> None:
    """Same reference, names in order, sizes; K, distortion (zero-padded: k1 k2 p1 p2 and
    k1 k2 p1 p2 0 are one model), rotation and translation (m) within the tolerances."""
    assert a.reference == b.reference and a.names == b.names, (a.names, b.names)
    for name in a.names:
        ca, cb = a[name], b[name]
        assert ca.size == cb.size
        np.testing.assert_allclose(ca.K, cb.K, rtol=0, atol=tol_k)
        np.testing.assert_allclose(_padded(ca.dist), _padded(cb.dist), rtol=0, atol=tol_d)
        np.testing.assert_allclose(ca.T_ref_cam[:3, :3], cb.T_ref_cam[:3, :3], rtol=0,
                                   atol=tol_r)
        np.testing.assert_allclose(ca.T_ref_cam[:3, 3], cb.T_ref_cam[:3, 3], rtol=0,
                                   atol=tol_t)


# -- round trips --------------------------------------------------------------------------
CASES = [("opencv", "rig.yml"), ("opencv", "rig.yaml"), ("opencv", "rig.xml"),
         ("opencv", "rig.json"), ("kalibr", "camchain.yaml"), ("toml", "rig.toml")]


@pytest.mark.parametrize(("fmt", "name"), CASES + [("ros", "pair")],
                         ids=[n for _, n in CASES] + ["ros-pair"])
def test_stereo_round_trip_every_format(tmp_path, fmt, name):
    """Issue 34 item 2 (round trip): ours -> theirs -> ours gives the same stereo rig within
    float precision (names, reference, sizes, K, distortion, the right camera's pose), read
    back by load_rig, which judges the format from the content."""
    rig = _stereo()
    save_rig_as(rig, tmp_path / name, fmt)
    assert detect_format(tmp_path / name) == fmt
    assert_same_rig(rig, load_rig(tmp_path / name))


@pytest.mark.parametrize(("fmt", "name"), CASES + [("ros", "cam.yaml")],
                         ids=[n for _, n in CASES] + ["ros"])
def test_mono_round_trip_every_format(tmp_path, fmt, name):
    """Issue 34 item 2 (round trip): a one-camera rig (the endoscope's 8-coefficient rational
    distortion; Kalibr: 4 radtan ones) comes back the same from every format."""
    rig = _mono(dist=D_L) if fmt == "kalibr" else _mono()
    save_rig_as(rig, tmp_path / name, fmt)
    assert_same_rig(rig, load_rig(tmp_path / name))


def test_kalibr_chains_three_cameras(tmp_path):
    """Issue 34 item 2 (round trip): Kalibr's chain of T_cn_cnm1 (camera n-1 into camera n)
    gives back every camera's pose in the reference for a three-camera rig."""
    third = np.eye(4)
    third[:3, :3] = Rotation.from_euler("zyx", [5.0, 20.0, -3.0], degrees=True).as_matrix()
    third[:3, 3] = [-0.03, 0.05, 0.01]
    rig = _stereo()
    cams = dict(rig.cameras)
    cams["top"] = CameraModel("top", (640, 480), K_R, D_R, third)
    rig = Rig("left", cams)
    save_rig_as(rig, tmp_path / "c.yaml", "kalibr")
    doc = yaml.safe_load((tmp_path / "c.yaml").read_text())
    np.testing.assert_allclose(doc["cam2"]["T_cn_cnm1"], invert(third) @ T_L_R, atol=1e-15)
    assert_same_rig(rig, load_rig(tmp_path / "c.yaml"), tol_r=1e-15, tol_t=1e-15)


def test_writers_put_the_reference_camera_first(tmp_path):
    """Issue 34 item 2 (poses relative to the first camera): a rig whose reference camera is
    not the first is written with the reference as camera 1 / cam0 / left."""
    rig = _stereo()
    swapped = Rig("left", {"right": rig["right"], "left": rig["left"]})
    save_rig_as(swapped, tmp_path / "c.yaml", "kalibr")
    assert load_rig(tmp_path / "c.yaml").names == ("left", "right")


# -- the tools' own files agree --------------------------------------------------------------
def _write_stereo_calib(folder: Path, rig: Rig, dtype=np.float64) -> tuple[Path, Path]:
    """intrinsics.yml and extrinsics.yml as OpenCV's stereo_calib sample writes them, by
    cv2.FileStorage itself (no image size in either)."""
    left, right = rig["left"], rig["right"]
    T_r_l = invert(right.T_ref_cam)
    R, T = T_r_l[:3, :3], T_r_l[:3, 3].reshape(3, 1)
    R1, R2, P1, P2, Q, _, _ = cv2.stereoRectify(left.K, left.dist, right.K, right.dist, SIZE,
                                               R, T, flags=cv2.CALIB_ZERO_DISPARITY, alpha=1)
    intr, extr = folder / "intrinsics.yml", folder / "extrinsics.yml"
    fs = cv2.FileStorage(str(intr), cv2.FILE_STORAGE_WRITE)
    for key, value in (("M1", left.K), ("D1", left.dist.reshape(1, -1)), ("M2", right.K),
                       ("D2", right.dist.reshape(1, -1))):
        fs.write(key, value)
    fs.release()
    fs = cv2.FileStorage(str(extr), cv2.FILE_STORAGE_WRITE)
    for key, value in (("R", R.astype(dtype)), ("T", T), ("R1", R1), ("R2", R2), ("P1", P1),
                       ("P2", P2), ("Q", Q)):
        fs.write(key, value)
    fs.release()
    return intr, extr


@pytest.mark.parametrize("suffix", [".yml", ".xml"])
def test_opencv_calibration_sample_file_loads(tmp_path, suffix):
    """Issue 34 item 2 (OpenCV's calibration sample): a file with every key the sample
    writes (time, board, flags and their comment, fisheye_model 0, per-view errors,
    extrinsics, 2-channel float32 image points), written by cv2.FileStorage, gives its one
    camera, named camera; the keys the rig does not hold are read past."""
    K = np.array([[800.0, 0.0, 319.5], [0.0, 800.0, 239.5], [0.0, 0.0, 1.0]])
    dist = np.array([[0.1], [-0.2], [0.001], [-0.002], [0.05]])
    path = tmp_path / f"out_camera_data{suffix}"
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("calibration_time", "Fri Nov 27 12:00:00 2026")
    for key, value in (("nr_of_frames", 25), ("image_width", 640), ("image_height", 480),
                       ("board_width", 9), ("board_height", 6), ("square_size", 0.025)):
        fs.write(key, value)
    fs.writeComment("flags: +fix_principal_point")
    fs.write("flags", 4)
    fs.write("fisheye_model", 0)
    fs.write("camera_matrix", K)
    fs.write("distortion_coefficients", dist)
    fs.write("avg_reprojection_error", 0.21)
    fs.write("per_view_reprojection_errors", np.full((25, 1), 0.2, np.float32))
    fs.write("extrinsic_parameters", np.zeros((25, 6)))
    fs.write("image_points", np.zeros((25, 54, 2), np.float32))
    fs.release()
    rig = load_rig(path)
    assert rig.names == ("camera",) and rig["camera"].size == (640, 480)
    np.testing.assert_array_equal(rig["camera"].K, K)
    np.testing.assert_array_equal(rig["camera"].dist, dist.ravel())


def test_opencv_ros_and_kalibr_files_of_one_rig_load_the_same(tmp_path):
    """Issue 34 item 2 (the tools agree): files written by OpenCV (stereo_calib's
    intrinsics.yml + extrinsics.yml, by cv2.FileStorage here), ROS (camera_calibration's
    left.yaml / right.yaml) and Kalibr (a camchain) for the same rig load to the same Rig,
    within the digits each tool prints (ROS: 8 decimals of R, 5 of P)."""
    truth = _stereo()
    names = ("left", "right")
    from_cv = load_opencv(_write_stereo_calib(tmp_path, truth), size=SIZE)
    from_ros = load_ros(ROS_PAIR, names=names)
    from_kalibr = load_kalibr(KALIBR, names=names)
    assert_same_rig(truth, from_cv)
    assert_same_rig(truth, from_kalibr, tol_r=1e-15, tol_t=1e-15)
    assert_same_rig(truth, from_ros, tol_r=3e-8, tol_t=1e-8)  # a 61 mm baseline: 0.01 um
    # judged from the content alone, by the folder or by the file
    assert_same_rig(from_ros, load_rig(ROS_PAIR, names=names))
    assert_same_rig(from_ros, load_ros([ROS_PAIR / "left.yaml", ROS_PAIR / "right.yaml"],
                                       names=names))
    assert_same_rig(from_kalibr, load_rig(KALIBR, names=names))
    # written by ROS's own library (writeCalibrationYml): full precision, flow-style lists
    assert_same_rig(truth, load_rig(ROS_PARSERS_PAIR, names=names), tol_r=3e-8, tol_t=1e-8)


def test_camera_names_come_from_the_files():
    """Issue 34 item 2 (names): without names, ROS cameras take their camera_name and Kalibr
    cameras their rostopic less its image_... part; the first camera is the reference."""
    assert load_rig(ROS_PAIR).names == ("narrow_stereo/left", "narrow_stereo/right")
    rig = load_rig(KALIBR)
    assert rig.names == ("stereo/left", "stereo/right") and rig.reference == "stereo/left"


def test_kalibr_names_fall_back_to_cam_numbers(tmp_path):
    """Issue 34 item 2 (names): Kalibr cameras without a rostopic, or two whose topics give
    one name, are named cam0, cam1."""
    doc = yaml.safe_load(KALIBR.read_text())
    for cam in doc.values():
        cam["rostopic"] = "/image_raw"
    assert load_rig(write_file(tmp_path, "a.yaml", yaml.dump(doc))).names == ("cam0", "cam1")
    doc = yaml.safe_load(KALIBR.read_text())
    del doc["cam1"]["rostopic"]
    assert load_rig(write_file(tmp_path, "b.yaml", yaml.dump(doc))).names == ("cam0", "cam1")


def test_ros_pair_rounded_to_six_decimals_is_reorthonormalised(tmp_path):
    """Issue 34 item 2 (1e-6 check): older camera_calibration prints R with 6 decimals, which
    can miss the 1e-6 orthonormality check; such a pair loads (its rotations projected onto
    the nearest ones) within the printed precision."""
    for side in ("left", "right"):
        doc = yaml.safe_load((ROS_PAIR / f"{side}.yaml").read_text())
        for key in ("rectification_matrix", "projection_matrix"):
            doc[key]["data"] = [round(v, 6) for v in doc[key]["data"]]
        write_file(tmp_path / "pair", f"{side}.yaml", yaml.dump(doc, sort_keys=False))
    rig = load_rig(tmp_path / "pair", names=("left", "right"))
    R = rig["right"].T_ref_cam[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-14)
    assert_same_rig(_stereo(), rig, tol_r=5e-6, tol_t=1e-7)


def test_float32_rotation_in_opencv_is_reorthonormalised(tmp_path):
    """Issue 34 item 2 (1e-6 check): an OpenCV R stored as float32 ('f') is projected onto
    the nearest rotation; a float64 one must pass the 1e-6 check as it is."""
    rig = load_opencv(_write_stereo_calib(tmp_path, _stereo(), np.float32), size=SIZE)
    R = rig["right"].T_ref_cam[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-14)
    assert_same_rig(_stereo(), rig, tol_r=1e-7, tol_t=1e-9)
    intr, extr = _write_stereo_calib(tmp_path, _stereo())
    T_r_l = invert(T_L_R)
    _fs_file(tmp_path, extr.name, R=np.round(T_r_l[:3, :3], 4), T=T_r_l[:3, 3].reshape(3, 1))
    expect_config_error(lambda p: load_opencv([intr, p], size=SIZE), extr, "R:",
                        "not a proper rotation")


# -- OpenCV reads what we write ------------------------------------------------------------
@pytest.mark.parametrize("suffix", [".yml", ".xml", ".json"])
def test_our_opencv_files_load_in_filestorage(tmp_path, suffix):
    """Issue 34 item 2 (OpenCV reads ours): cv2.FileStorage reads our one-camera file with the
    calibration sample's keys and our stereo file with stereo_calib's, and R, T map points
    of camera 1 into camera 2 as OpenCV's stereoCalibrate defines them."""
    mono, stereo = _mono(), _stereo()
    save_rig_as(mono, tmp_path / f"mono{suffix}", "opencv")
    fs = cv2.FileStorage(str(tmp_path / f"mono{suffix}"), cv2.FILE_STORAGE_READ)
    cam = mono["endoscope"]
    assert int(fs.getNode("image_width").real()) == 1920
    assert int(fs.getNode("image_height").real()) == 1080
    np.testing.assert_array_equal(fs.getNode("camera_matrix").mat(), cam.K)
    np.testing.assert_array_equal(fs.getNode("distortion_coefficients").mat().ravel(),
                                  cam.dist)
    fs.release()
    save_rig_as(stereo, tmp_path / f"stereo{suffix}", "opencv")
    fs = cv2.FileStorage(str(tmp_path / f"stereo{suffix}"), cv2.FILE_STORAGE_READ)
    np.testing.assert_array_equal(fs.getNode("M1").mat(), K_L)
    np.testing.assert_array_equal(fs.getNode("M2").mat(), K_R)
    np.testing.assert_array_equal(fs.getNode("D1").mat().ravel(), D_L)
    np.testing.assert_array_equal(fs.getNode("D2").mat().ravel(), D_R)
    R, T = fs.getNode("R").mat(), fs.getNode("T").mat()
    for key in ("R1", "R2", "P1", "P2", "Q"):
        assert fs.getNode(key).mat() is not None, key
    fs.release()
    p_left = np.array([0.01, -0.02, 0.15])
    p_right = invert(T_L_R)[:3, :3] @ p_left + invert(T_L_R)[:3, 3]
    np.testing.assert_allclose(R @ p_left + T.ravel(), p_right, atol=1e-15)


def test_our_ros_and_kalibr_files_have_the_tools_keys(tmp_path):
    """Issue 34 item 2 (their layout): our ROS files hold exactly camera_info's keys (K, D, R,
    P as rows/cols/data), a pair's right P has Tx = -fx' * baseline; our camchain holds
    Kalibr's keys with floats where Kalibr checks for floats."""
    save_rig_as(_stereo(), tmp_path / "pair", "ros")
    assert sorted(p.name for p in (tmp_path / "pair").iterdir()) == ["left.yaml",
                                                                      "right.yaml"]
    right = yaml.safe_load((tmp_path / "pair" / "right.yaml").read_text())
    assert list(right) == ["image_width", "image_height", "camera_name", "camera_matrix",
                           "distortion_model", "distortion_coefficients",
                           "rectification_matrix", "projection_matrix"]
    assert right["distortion_model"] == "plumb_bob"
    assert right["distortion_coefficients"] == {"rows": 1, "cols": 5,
                                                "data": [*D_R.tolist(), 0.0]}
    P = np.reshape(right["projection_matrix"]["data"], (3, 4))
    np.testing.assert_allclose(-P[0, 3] / P[0, 0], np.linalg.norm(T_L_R[:3, 3]), rtol=1e-12)
    save_rig_as(_stereo(), tmp_path / "c.yaml", "kalibr")
    doc = yaml.safe_load((tmp_path / "c.yaml").read_text())
    assert sorted(doc["cam1"]) == ["T_cn_cnm1", "camera_model", "distortion_coeffs",
                                   "distortion_model", "intrinsics", "resolution", "rostopic"]
    assert all(isinstance(v, float) for v in doc["cam0"]["intrinsics"])
    assert doc["cam0"]["resolution"] == list(SIZE)


# -- what the formats cannot hold, and bad input ---------------------------------------------
def test_writers_refuse_what_the_format_cannot_hold(tmp_path):
    """Issue 34 item 2 (never guess): writing refuses, naming the file and the key, a rig
    whose reference is no camera, more cameras than OpenCV or ROS hold, distortion the
    format cannot hold (Kalibr: a non-zero k3; ROS: a non-zero tilt) and OpenCV stereo
    cameras of two sizes; nothing is written then, and an old file stays as it was."""
    rig = _stereo()
    world = Rig("world", dict(rig.cameras))
    third = dict(rig.cameras, top=CameraModel("top", SIZE, K_L, D_L, T_L_R))
    tilt = _mono(dist=[0.1, 0.01, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0.001, 0])
    small = Rig("left", {"left": rig["left"], "right": CameraModel(
        "right", (640, 512), K_R, D_R, T_L_R)})
    old = write_file(tmp_path, "old.yaml", "keep me\n")
    cases = [(world, "kalibr", "reference", "not one of the rig's cameras"),
             (Rig("left", third), "opencv", "cameras", "at most 2"),
             (Rig("left", third), "ros", "cameras", "at most 2"),
             (_mono(dist=[0.1, 0.01, 0, 0, 0.002]), "kalibr", "dist", "radtan (4)"),
             (tilt, "ros", "dist", "rational_polynomial (8)"),
             (small, "opencv", "size", "one image size")]
    for r, fmt, key, reason in cases:
        target = old if fmt != "opencv" else tmp_path / "old.yml"
        with pytest.raises(ConfigError) as ei:
            save_rig_as(r, target, fmt)
        assert str(ei.value).startswith(f"{target}: ") and key in ei.value.key, ei.value
        assert reason in ei.value.reason, ei.value
    assert old.read_text() == "keep me\n" and not (tmp_path / "old.yml").exists()
    with pytest.raises(ConfigError, match="name it so"):
        save_rig_as(rig, tmp_path / "rig.txt", "opencv")
    with pytest.raises(ConfigError, match="give a folder"):
        save_rig_as(rig, tmp_path / "pair.yaml", "ros")
    with pytest.raises(ValueError, match="fmt must be one of"):
        save_rig_as(rig, tmp_path / "x", "matlab")


ROS_LEFT = (ROS_PAIR / "left.yaml").read_text()
KALIBR_TEXT = KALIBR.read_text()
NOT_ANY = "calibration:\n  fx: 1400.0\n  fy: 1400.0\n"


def _ros(old: str, new: str) -> str:
    assert old in ROS_LEFT, old
    return ROS_LEFT.replace(old, new, 1)


def _kalibr(old: str, new: str, after: str = "cam0:") -> str:
    head, _, tail = KALIBR_TEXT.partition(after)
    assert old in tail, old
    return head + after + tail.replace(old, new, 1)


BAD_YAML = {
    "none-of-them": (NOT_ANY, load_rig, "not a rig or camera file",
                     ("expected a rig TOML", "found the top-level keys calibration")),
    "ros-missing": (_ros("image_height: 1024\n", ""), load_rig, "image_height", ("missing",)),
    "ros-shape": (_ros("  rows: 3\n  cols: 3\n  data: [1400.5", "  rows: 3\n  cols: 4\n  data: "
                       "[1400.5"), load_rig, "camera_matrix", ("must be 3x3, got 3x4",)),
    "ros-count": (_ros("  cols: 5", "  cols: 4"), load_rig, "[distortion_coefficients] data",
                  ("rows x cols = 4 numbers, got 5",)),
    "ros-nan": (_ros("1400.5", ".nan"), load_rig, "[camera_matrix] data[0]", ("finite",)),
    "ros-fisheye": (_ros("plumb_bob", "equidistant"), load_rig, "distortion_model",
                    ("fisheye",)),
    "ros-unknown": (_ros("image_width", "binning_x: 2\nimage_width"), load_rig, "binning_x",
                    ("unknown key",)),
    "kalibr-unknown": (_kalibr("  intrinsics:", "  focal:", "cam1:"), load_rig,
                       "[cam1] focal", ("unknown key",)),
    "kalibr-no-intrinsics": (_kalibr("intrinsics", "#intrinsics", "cam1:"), load_rig,
                             "[cam1] intrinsics", ("missing",)),
    "kalibr-fisheye": (_kalibr("distortion_model: radtan", "distortion_model: equidistant"),
                       load_rig, "[cam0] distortion_model", ("fisheye",)),
    "kalibr-omni": (_kalibr("camera_model: pinhole", "camera_model: omni"), load_rig,
                    "[cam0] camera_model", ("only Kalibr's pinhole",)),
    "kalibr-nan": (_kalibr("1400.5", ".nan"), load_rig, "[cam0] intrinsics[0]", ("finite",)),
    "kalibr-shape": (_kalibr("  - [0.0, 0.0, 0.0, 1.0]\n", "", "cam1:"), load_rig,
                     "[cam1] T_cn_cnm1", ("4 rows",)),
    "kalibr-length": (_kalibr("distortion_coeffs: [", "distortion_coeffs: [0.0, "), load_rig,
                      "[cam0] distortion_coeffs", ("must have 4 numbers, got 5",)),
}


@pytest.mark.parametrize("case", list(BAD_YAML), ids=list(BAD_YAML))
def test_bad_ros_and_kalibr_files_name_file_and_key(tmp_path, case):
    """Issue 34 item 2 (bad input): a YAML that is none of the formats, a missing key, a
    wrong-shaped matrix, a NaN, a fisheye or omnidirectional camera, an unknown key: each
    is one ConfigError naming the file and the key."""
    text, load, where, reasons = BAD_YAML[case]
    path = write_file(tmp_path, "cam.yaml", text)
    expect_config_error(load, path, where, *reasons)


def _fs_file(tmp_path: Path, name: str, **values) -> Path:
    path = tmp_path / name
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for key, value in values.items():
        fs.write(key, value)
    fs.release()
    return path


def test_bad_opencv_files_name_file_and_key(tmp_path):
    """Issue 34 item 2 (bad input): OpenCV files with a missing key, a wrong-shaped matrix, a
    NaN, skew, the fisheye model, a distortion length OpenCV's model lacks, or a stereo
    file without an image size: each one ConfigError naming the file and the key."""
    good = {"image_width": 640, "image_height": 480, "camera_matrix": K_L,
            "distortion_coefficients": D_L.reshape(-1, 1)}
    skew = K_L.copy()
    skew[0, 1] = 0.5
    nan = K_L.copy()
    nan[0, 2] = np.nan
    cases = [
        ({k: v for k, v in good.items() if k != "distortion_coefficients"},
         "distortion_coefficients", "missing"),
        ({**good, "camera_matrix": np.hstack([K_L, np.zeros((3, 1))])}, "camera_matrix",
         "3x3"),
        ({**good, "camera_matrix": nan}, "camera_matrix", "non-finite"),
        ({**good, "camera_matrix": skew}, "camera_matrix", "skew"),
        ({**good, "fisheye_model": 1}, "fisheye_model", "fisheye"),
        ({**good, "distortion_coefficients": np.zeros((6, 1))}, "distortion_coefficients",
         "got 6"),
        ({k: v for k, v in good.items() if k != "image_height"}, "image_height", "missing"),
        ({"M1": K_L, "D1": D_L, "M2": K_R, "D2": D_R, "R": np.eye(3),
          "T": np.zeros((3, 1))}, "image_width", "pass the size"),
        ({"M1": K_L, "D1": D_L, "M2": K_R, "D2": D_R}, "R", "extrinsics.yml"),
        ({**good, "K": K_L}, "K", "same matrix"),
    ]
    for i, (values, where, reason) in enumerate(cases):
        path = _fs_file(tmp_path, f"c{i}.yml", **values)
        expect_config_error(load_rig, path, where + ":", reason)


def test_opencv_sizes_given_and_held_must_agree(tmp_path):
    """Issue 34 item 2 (sizes): a size passed for a file that holds one must equal it; a
    stereo_calib pair (no size) takes the size given."""
    path = _fs_file(tmp_path, "c.yml", image_width=640, image_height=480, camera_matrix=K_L,
                    distortion_coefficients=D_L)
    assert load_rig(path, size=(640, 480))["camera"].size == (640, 480)
    expect_config_error(lambda p: load_rig(p, size=(1280, 1024)), path, "image_width",
                        "640x480 images, but the images are 1280x1024")
    save_rig(_stereo(), tmp_path / "r.toml")
    with pytest.raises(ValueError, match="rig TOML names and sizes"):
        load_rig(tmp_path / "r.toml", size=SIZE)


def test_unreadable_and_unknown_files(tmp_path):
    """Issue 34 item 2 (detection): a file of another kind is reported with what was
    expected; a missing one as not found; a ROS pair needs both files; a plain text
    calibration (scikit-surgery's) is sniffed as none of the formats."""
    expect_config_error(load_rig, write_file(tmp_path, "a.yaml", "- 1\n- 2\n"),
                        "not a rig or camera file", "Kalibr camchain")
    expect_config_error(load_rig, write_file(tmp_path, "a.xml", "<?xml version='1.0'?>\n<a/>"),
                        "not a rig or camera file")
    expect_config_error(load_rig, tmp_path / "none.yml", "file not found")
    (tmp_path / "half").mkdir()
    write_file(tmp_path / "half", "left.yaml", ROS_LEFT)
    expect_config_error(load_rig, tmp_path / "half", "left.yaml and right.yaml")
    txt = write_file(tmp_path, "calibration.txt", "800 0 320\n0 800 240\n0 0 1\n0 0 0 0 0\n")
    assert sniff_format(txt) is None
    assert sniff_format(ROS_PAIR) == "ros" and sniff_format(KALIBR) == "kalibr"
    with pytest.raises(ConfigError, match="two cameras are named"):
        load_camera_file([ROS_PAIR / "left.yaml", ROS_PAIR / "right.yaml"],
                         names=("a", "a"))
