"""Tests of ``oralnav.config.rig``: the rig file (cameras, intrinsics, poses).

Each test's docstring names the requirement it checks (Issue 2: configuration).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from oralnav.config.errors import ConfigError
from oralnav.config.rig import load_rig, save_rig
from oralnav.control.vision.camera import CameraModel, Rig

CONFIG = Path(__file__).resolve().parents[2] / "config"
STEREO = CONFIG / "rigs" / "stereo.toml"
ENDOSCOPE = CONFIG / "rigs" / "endoscope.toml"

GOOD = """\
reference = "left"

[cameras.left]
size = [1920, 1200]
K = [[2400.0, 0.0, 960.0], [0.0, 2400.0, 600.0], [0.0, 0.0, 1.0]]
dist = [0.0, 0.0, 0.0, 0.0, 0.0]
T_ref_cam = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]

[cameras.right]
size = [1920, 1200]
K = [[2395.0, 0.0, 955.0], [0.0, 2395.0, 604.0], [0.0, 0.0, 1.0]]
dist = [-0.075, 0.11, -0.0001, 0.0002, 0.0]
T_ref_cam = [[1.0, 0.0, 0.0, 0.1], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
"""
RIGHT_T = ("T_ref_cam = [[1.0, 0.0, 0.0, 0.1], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], "
           "[0.0, 0.0, 0.0, 1.0]]")
RIGHT_K = "K = [[2395.0, 0.0, 955.0], [0.0, 2395.0, 604.0], [0.0, 0.0, 1.0]]"
RIGHT_DIST = "dist = [-0.075, 0.11, -0.0001, 0.0002, 0.0]"


def _edit(old: str, new: str) -> str:
    assert GOOD.count(old) >= 1, old
    return GOOD.replace(old, new, 1)


def _right(old: str, new: str) -> str:
    head, tail = GOOD.split("[cameras.right]")
    assert old in tail, old
    return head + "[cameras.right]" + tail.replace(old, new, 1)


def _assert_same_rig(a: Rig, b: Rig) -> None:
    assert a.reference == b.reference
    assert list(a.cameras) == list(b.cameras)
    for name in a.cameras:
        ca, cb = a.cameras[name], b.cameras[name]
        assert ca.size == cb.size
        for attr in ("K", "dist", "T_ref_cam"):
            va, vb = getattr(ca, attr), getattr(cb, attr)
            assert va.shape == vb.shape and va.dtype == vb.dtype == np.float64
            assert va.tobytes() == vb.tobytes(), f"{name}.{attr} differs"  # bit-exact


def _tmp_names(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir())


# -- shipped rigs --------------------------------------------------------------------------
def test_shipped_stereo_rig_loads():
    """Issue 2 (every shipped file loads): config/rigs/stereo.toml gives two cameras with the
    values written in the file (right camera 100 mm along x, turned 20 deg about y)."""
    rig = load_rig(STEREO)
    assert rig.reference == "left" and rig.names == ("left", "right")
    left, right = rig["left"], rig["right"]
    assert left.size == (1920, 1200)
    np.testing.assert_array_equal(left.T_ref_cam, np.eye(4))
    np.testing.assert_array_equal(right.K, [[2395.0, 0, 955.0], [0, 2395.0, 604.0], [0, 0, 1]])
    np.testing.assert_array_equal(right.dist, [-0.075, 0.11, -0.0001, 0.0002, 0.0])
    assert right.T_ref_cam[0, 3] == 0.1
    angle = Rotation.from_matrix(right.T_ref_cam[:3, :3]).as_rotvec(degrees=True)
    np.testing.assert_allclose(angle, [0.0, -20.0, 0.0], atol=1e-9)


def test_shipped_endoscope_rig_loads_with_defaults():
    """Issue 2 (every shipped file loads): config/rigs/endoscope.toml loads; an omitted
    T_ref_cam is the identity."""
    rig = load_rig(ENDOSCOPE)
    assert rig.reference == "endoscope" and rig.names == ("endoscope",)
    cam = rig["endoscope"]
    assert cam.size == (1920, 1080)
    np.testing.assert_array_equal(cam.T_ref_cam, np.eye(4))
    assert cam.dist[0] == -0.28


def test_omitted_dist_is_zero(tmp_path):
    """Issue 2 (rig format): an omitted dist is five zeros (no distortion)."""
    path = tmp_path / "rig.toml"
    path.write_text(_edit("dist = [0.0, 0.0, 0.0, 0.0, 0.0]\n", ""))
    cam = load_rig(path)["left"]
    np.testing.assert_array_equal(cam.dist, np.zeros(5))
    assert not cam.has_distortion


# -- round trip ----------------------------------------------------------------------------
@pytest.mark.parametrize("src", [STEREO, ENDOSCOPE], ids=["stereo", "endoscope"])
def test_save_load_round_trip_shipped_rigs_bit_exact(tmp_path, src):
    """Issue 2 (rig round trip): save_rig(load_rig(p), q) then load_rig(q) gives identical
    K, dist and T_ref_cam, bit for bit; saving the reloaded rig writes the same text."""
    q = tmp_path / "rig.toml"
    original = load_rig(src)
    save_rig(original, q)
    again = load_rig(q)
    _assert_same_rig(original, again)
    q2 = tmp_path / "rig2.toml"
    save_rig(again, q2)
    assert q2.read_text() == q.read_text()


def test_save_load_round_trip_awkward_floats_bit_exact(tmp_path):
    """Issue 2 (rig round trip): values with full 17-digit mantissas, tiny and negative
    numbers, a 14-term distortion vector and a random rotation survive save and load
    bit-exact."""
    rng = np.random.default_rng(7)
    R = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = rng.normal(scale=0.1, size=3)
    K = np.array([[2400 + rng.random(), 0.0, 960 + rng.random()],
                  [0.0, 2400 + rng.random(), 600 + rng.random()], [0.0, 0.0, 1.0]])
    dist = rng.normal(scale=1e-3, size=14)
    dist[3] = -1e-300
    cams = {"ref": CameraModel("ref", (640, 480), np.diag([500.0, 500.0, 1.0]) + [[0, 0, 320.1],
                                                                              [0, 0, 240.2],
                                                                              [0, 0, 0]]),
            "aux": CameraModel("aux", (1280, 1024), K, dist, T)}
    rig = Rig("ref", cams)
    q = tmp_path / "rig.toml"
    save_rig(rig, q)
    _assert_same_rig(rig, load_rig(q))


def test_save_load_round_trip_camera_name_needing_quotes(tmp_path):
    """Issue 2 (rig round trip): a camera whose name is not a bare TOML key (a space, a dot)
    is written quoted and read back under the same name."""
    cams = {n: CameraModel(n, (100, 80), np.array([[90.0, 0, 50], [0, 90.0, 40], [0, 0, 1]]))
            for n in ("left cam", "cam.2")}
    rig = Rig("left cam", cams)
    q = tmp_path / "rig.toml"
    save_rig(rig, q)
    _assert_same_rig(rig, load_rig(q))


def test_save_replaces_existing_file(tmp_path):
    """Issue 2 (rig round trip): saving over an existing rig replaces it, leaving no temp."""
    q = tmp_path / "rig.toml"
    q.write_text("# old calibration\n")
    save_rig(load_rig(STEREO), q)
    assert load_rig(q).names == ("left", "right")
    assert _tmp_names(tmp_path) == ["rig.toml"]


def test_save_failed_rename_keeps_existing_file(tmp_path, monkeypatch):
    """Issue 2 (atomic rig write): when the rename fails, an existing file at the target is
    unchanged and no temporary file remains."""
    q = tmp_path / "rig.toml"
    q.write_text(GOOD)
    before = q.read_bytes()
    rig = load_rig(STEREO)

    def boom(src, dst):
        raise OSError(30, "Read-only file system")

    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(OSError, match="Read-only"):
        save_rig(rig, q)
    assert q.read_bytes() == before
    assert _tmp_names(tmp_path) == ["rig.toml"]


def test_save_unwritable_values_keeps_existing_file(tmp_path):
    """Issue 2 (atomic rig write, bad input): a rig whose values cannot be written (a NaN
    that crept into K after validation) is refused with a ConfigError naming the target;
    the existing file is unchanged and no temporary file remains."""
    q = tmp_path / "rig.toml"
    q.write_text(GOOD)
    before = q.read_bytes()
    rig = load_rig(STEREO)
    rig["right"].K[0, 2] = np.nan  # numpy arrays stay writable inside the frozen model
    with pytest.raises(ConfigError) as ei:
        save_rig(rig, q)
    assert str(q) in str(ei.value) and "non-finite" in str(ei.value)
    assert q.read_bytes() == before
    assert _tmp_names(tmp_path) == ["rig.toml"]


def test_save_invalid_rig_is_never_written(tmp_path):
    """Issue 2 (atomic rig write): a rig the format would not load back (here a rotation
    corrupted after validation) is refused before anything is written."""
    q = tmp_path / "rig.toml"
    rig = load_rig(STEREO)
    rig["right"].T_ref_cam[0, 0] = 2.0
    with pytest.raises(ConfigError) as ei:
        save_rig(rig, q)
    assert "[cameras.right] T_ref_cam" in str(ei.value)
    assert "rotation" in str(ei.value)
    assert list(tmp_path.iterdir()) == []


# -- bad input -----------------------------------------------------------------------------
BROKEN = {
    # name: (file text, expected "[section] key" text, expected reason text)
    "syntax": (GOOD.replace('reference = "left"', "reference = left"), "not valid TOML",
               "line 1"),
    "unknown_key": (_right(RIGHT_K, RIGHT_K + "\nfocal = 3.0"), "[cameras.right] focal:",
                    "unknown key"),
    "unknown_top": ("baseline = 0.1\n" + GOOD, ": baseline:", "unknown key"),
    "missing_K": (_right(RIGHT_K + "\n", ""), "[cameras.right] K:", "Field required"),
    "missing_size": (_edit("size = [1920, 1200]\n", ""), "[cameras.left] size:",
                     "Field required"),
    "missing_reference": (_edit('reference = "left"\n', ""), ": reference:", "Field required"),
    "no_cameras": ('reference = "left"\n[cameras]\n', ": cameras:", "at least 1"),
    "K_string": (_right("[[2395.0,", '[["2395.0",'), "[cameras.right] K[0][0]:",
                 "valid number"),
    "size_float": (_edit("size = [1920, 1200]", "size = [1920.5, 1200]"),
                   "[cameras.left] size[0]:", "valid integer"),
    "size_bool": (_edit("size = [1920, 1200]", "size = [true, 1200]"),
                  "[cameras.left] size[0]:", "valid integer"),
    "size_zero": (_edit("size = [1920, 1200]", "size = [1920, 0]"), "[cameras.left] size[1]:",
                  "greater than 0"),
    "size_three": (_edit("size = [1920, 1200]", "size = [1920, 1200, 3]"),
                   "[cameras.left] size:", "at most 2"),
    "K_2x3": (_right(RIGHT_K, "K = [[2395.0, 0.0, 955.0], [0.0, 2395.0, 604.0]]"),
              "[cameras.right] K:", "3x3"),
    "K_skew": (_right("[[2395.0, 0.0,", "[[2395.0, 1.5,"), "[cameras.right] K:", "no skew"),
    "K_negative_focal": (_right("[[2395.0,", "[[-2395.0,"), "[cameras.right] K:",
                         "must be positive"),
    "K_nan": (_right("[[2395.0,", "[[nan,"), "[cameras.right] K[0][0]:", "finite"),
    "dist_length": (_right(RIGHT_DIST, "dist = [0.1, 0.2, 0.3]"), "[cameras.right] dist:",
                    "got 3"),
    "dist_inf": (_right(RIGHT_DIST, "dist = [0.1, inf, 0.0, 0.0, 0.0]"),
                 "[cameras.right] dist[1]:", "finite"),
    "T_not_rotation": (_right("[[1.0, 0.0, 0.0, 0.1]", "[[0.9, 0.0, 0.0, 0.1]"),
                       "[cameras.right] T_ref_cam:", "not a proper rotation"),
    "T_reflection": (_right("[[1.0, 0.0, 0.0, 0.1]", "[[-1.0, 0.0, 0.0, 0.1]"),
                     "[cameras.right] T_ref_cam:", "not a proper rotation"),
    "T_bottom_row": (_right("[0.0, 0.0, 0.0, 1.0]]", "[0.0, 0.0, 0.5, 1.0]]"),
                     "[cameras.right] T_ref_cam:", "bottom row"),
    "T_3x4": (_right(RIGHT_T, "T_ref_cam = [[1.0, 0.0, 0.0, 0.1], [0.0, 1.0, 0.0, 0.0], "
                              "[0.0, 0.0, 1.0, 0.0]]"),
              "[cameras.right] T_ref_cam:", "4x4"),
    "reference_not_identity": (GOOD.replace('reference = "left"', 'reference = "right"'),
                               ": reference:", "must be the identity"),
}


@pytest.mark.parametrize("case", list(BROKEN))
def test_broken_rig_file_is_one_clear_error(tmp_path, case):
    """Issue 2 (bad input): a malformed rig file (TOML syntax error, unknown or missing
    keys, wrong types, bad shapes, a T_ref_cam whose 3x3 block is not a rotation) gives one
    ConfigError naming the file, the section and key, and the reason."""
    text, where, reason = BROKEN[case]
    path = tmp_path / f"{case}.toml"
    path.write_text(text)
    with pytest.raises(ConfigError) as ei:
        load_rig(path)
    msg = str(ei.value)
    assert msg.startswith(f"{path}: "), msg
    assert where in msg, msg
    assert reason in msg, msg
    assert "\n" not in msg, f"one error expected, got several: {msg}"


def test_good_rig_template_loads(tmp_path):
    """Issue 2 (bad input tests are meaningful): the template the broken cases edit loads."""
    path = tmp_path / "rig.toml"
    path.write_text(GOOD)
    rig = load_rig(path)
    assert rig["right"].T_ref_cam[0, 3] == 0.1


def test_missing_rig_file(tmp_path):
    """Issue 2 (bad input): a missing rig file is a ConfigError naming it."""
    with pytest.raises(ConfigError, match="file not found") as ei:
        load_rig(tmp_path / "nope.toml")
    assert "nope.toml" in str(ei.value)
