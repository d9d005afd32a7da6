"""Tests of ``oralnav.config.rigid_bodies``: scikit-surgery rigid-body tables and
``calibration.txt`` files.

Each test's docstring names the requirement it checks ("rigid-body files: ...").
"""

from __future__ import annotations

from functools import partial

import numpy as np
import pytest

from oralnav.config.errors import ConfigError
from oralnav.config.rigid_bodies import load_calibration_txt, load_rigid_body
from oralnav.control.errors import MarkerFieldError
from tests.config.helpers import edit, expect_config_error, write_file

# Two rows of the peer's reference.txt (tabs) and one written with spaces.
TABLE = (
    "860\t7.25\t7.25\t0\t0\t0\t0\t14.5\t0\t0\t14.5\t14.5\t0\t0\t14.5\t0\n"
    "759\t24.75\t7.25\t0\t17.5\t0\t0\t32\t0\t0\t32\t14.5\t0\t17.5\t14.5\t0\n"
    "# a comment line, then a blank one\n"
    "\n"
    "752 42.25 7.25 0 35 0 0 49.5 0 0 49.5 14.5 0 35 14.5 0  # trailing comment\n"
)

CALIBRATION = "560.0 0.0 320.0\n0.0 560.0 240.0\n0.0 0.0 1.0\n0.1 0.0 0.0 0.0 0.0\n"


def test_table_loads_in_metres(tmp_path):
    """rigid-body files: a peer table loads as a RigidBody in metres, named after the file,
    ids sorted, corners in file order; comments and blank lines are skipped."""
    path = write_file(tmp_path, "reference.txt", TABLE)
    body = load_rigid_body(path)
    assert body.name == "reference"
    assert body.dictionary == "DICT_ARUCO_ORIGINAL"
    assert body.ids == (752, 759, 860)
    np.testing.assert_allclose(body.tags[860], [[0, 0, 0], [0.0145, 0, 0],
                                                [0.0145, 0.0145, 0], [0, 0.0145, 0]])
    np.testing.assert_allclose(body.tags[752][2], [0.0495, 0.0145, 0.0])


def test_table_options(tmp_path):
    """rigid-body files: name, dictionary and units are honoured; a 13-column line (no
    centre, as the peer's loader allows) is accepted."""
    text = "3 0 0 0 0.01 0 0 0.01 0.01 0 0 0.01 0\n"
    path = write_file(tmp_path, "t.txt", text)
    body = load_rigid_body(path, name="probe", dictionary="DICT_4X4_50", units="m")
    assert (body.name, body.dictionary, body.ids) == ("probe", "DICT_4X4_50", (3,))
    np.testing.assert_allclose(body.tags[3][2], [0.01, 0.01, 0.0])
    short = write_file(tmp_path, "short.txt", "3 0 0 0 10 0 0 10 10 0 0 10 0\n")
    np.testing.assert_allclose(load_rigid_body(short).tags[3][1], [0.01, 0.0, 0.0])


@pytest.mark.parametrize("old, new, where, reasons", [
    ("0\t14.5\t0\n759", "0\t14.5\n759", "line 1", ("expected 16 columns", "got 15")),
    ("24.75\t7.25", "24.75\tseven", "line 2", ("column 3 is not a number", "'seven'")),
    ("24.75\t7.25", "24.75\tnan", "line 2", ("column 3 is not finite",)),
    ("759\t24.75\t7.25", "759\t26.75\t7.25", "line 2", ("tag 759: centre", "mean of its corners",
                                                       "2 mm")),
    ("759\t", "860\t", "line 2", ("tag id 860 already given on line 1",)),
    ("759\t", "75.5\t", "line 2", ("not a whole number",)),
    ("759\t", "-3\t", "line 2", ("not a whole number",)),
    ("759\t", "1024\t", "line 2", ("DICT_ARUCO_ORIGINAL (0..1023)",)),
    ("759\t24.75\t7.25\t0\t17.5\t0\t0\t32\t0\t0\t32\t14.5",
     "759\t24.75\t0\t0\t17.5\t0\t0\t32\t0\t0\t32\t0", "line 2", ("tag 759", "degenerate")),
])
def test_malformed_table_rows(tmp_path, old, new, where, reasons):
    """rigid-body files: a wrong column count, a non-number, a centre off the corners' mean,
    a repeated id, an id outside the dictionary or a degenerate tag is one ConfigError
    naming the file and the line."""
    path = write_file(tmp_path, "reference.txt", edit(old, new, TABLE))
    expect_config_error(load_rigid_body, path, where, *reasons)


def test_unreadable_or_empty_table(tmp_path):
    """rigid-body files: a missing file, a non-UTF-8 file or a file with no tag is a
    ConfigError naming the file."""
    expect_config_error(load_rigid_body, tmp_path / "nope.txt", "file not found")
    empty = write_file(tmp_path, "empty.txt", "# nothing here\n\n")
    expect_config_error(load_rigid_body, empty, "no tags")
    binary = tmp_path / "bin.txt"
    binary.write_bytes(b"\xff\xfe\x00garbage")
    expect_config_error(load_rigid_body, binary, "not UTF-8")


def test_bad_arguments_are_value_errors(tmp_path):
    """rigid-body files: an unknown unit or dictionary is the caller's error (ValueError),
    not the file's."""
    path = write_file(tmp_path, "reference.txt", TABLE)
    with pytest.raises(ValueError, match="units"):
        load_rigid_body(path, units="inch")
    with pytest.raises(MarkerFieldError, match="unknown ArUco dictionary"):
        load_rigid_body(path, dictionary="DICT_NOPE")
    # ids valid in ARUCO_ORIGINAL but not in a 50-id dictionary: the file's line is named
    expect_config_error(partial(load_rigid_body, dictionary="DICT_4X4_50"), path, "line 1",
                        "DICT_4X4_50 (0..49)")


def test_calibration_loads(tmp_path):
    """rigid-body files: the peer's calibration.txt (K, then k1 k2 p1 p2 k3) becomes a
    CameraModel of the given size with an identity T_ref_cam."""
    path = write_file(tmp_path, "calibration.txt", CALIBRATION)
    cam = load_calibration_txt(path, (640, 480), name="peer")
    assert cam.name == "peer" and cam.size == (640, 480)
    np.testing.assert_array_equal(cam.K, [[560, 0, 320], [0, 560, 240], [0, 0, 1]])
    np.testing.assert_array_equal(cam.dist, [0.1, 0, 0, 0, 0])
    np.testing.assert_array_equal(cam.T_ref_cam, np.eye(4))
    eight = write_file(tmp_path, "c8.txt", edit("0.0 0.0 0.0\n", "0.0 0.0 0.0 0 0 0\n",
                                                CALIBRATION))
    assert load_calibration_txt(eight, (640, 480)).dist.size == 8


@pytest.mark.parametrize("old, new, where, reasons", [
    ("0.1 0.0 0.0 0.0 0.0\n", "", "calibration.txt: ", ("expected 4 lines", "got 3")),
    ("0.0 560.0 240.0", "0.0 560.0", "line 2", ("a row of K needs 3 numbers", "got 2")),
    ("0.0 560.0 240.0", "0.0 x 240.0", "line 2", ("column 2 is not a number",)),
    ("0.1 0.0 0.0 0.0 0.0", "0.1 0.0 0.0", "line 4", ("distortion needs", "got 3")),
    ("560.0 0.0 320.0", "-560.0 0.0 320.0", "calibration.txt: ", ("focal lengths",)),
    ("0.1 0.0 0.0 0.0 0.0\n", "0.1 0.0 0.0 0.0 0.0\n1 2 3\n", "calibration.txt: ",
     ("expected 4 lines",)),
])
def test_malformed_calibration(tmp_path, old, new, where, reasons):
    """rigid-body files: a calibration.txt with missing or extra lines, short rows, a
    non-number, a wrong distortion length or impossible intrinsics is one ConfigError
    naming the file (and the line where there is one)."""
    path = write_file(tmp_path, "calibration.txt", edit(old, new, CALIBRATION))
    expect_config_error(partial(load_calibration_txt, size=(640, 480)), path, where, *reasons)


def test_loader_errors_are_config_errors(tmp_path):
    """rigid-body files: loader errors are ConfigError (the configuration layer's error),
    which callers catch as a whole."""
    path = write_file(tmp_path, "calibration.txt", "1 2\n")
    with pytest.raises(ConfigError):
        load_calibration_txt(path, (640, 480))


def test_written_tables_and_calibrations_read_back(tmp_path):
    """rigid-body files (issue 33 item 6): `save_rigid_body` writes a 16-column table (in
    mm, a comment line first) and `save_calibration_txt` a 4-line calibration that the
    loaders read back as the same body and camera."""
    from oralnav.config.rigid_bodies import save_calibration_txt, save_rigid_body
    from oralnav.control.vision.camera import CameraModel
    from oralnav.control.vision.rigid_body import RigidBody

    h = 0.00725
    square = np.array([[-h, -h, 0.0], [h, -h, 0.0], [h, h, 0.0], [-h, h, 0.0]])
    body = RigidBody("plate", "DICT_ARUCO_ORIGINAL",
                     {860: square, 759: square + [0.0175, 0.0, 0.001]})
    path = save_rigid_body(body, tmp_path / "plate.txt")
    lines = path.read_text().splitlines()
    assert lines[0].startswith("# rigid body 'plate'") and len(lines[1].split()) == 16
    back = load_rigid_body(path)
    assert back.ids == body.ids and back.name == "plate"
    for tid in body.ids:
        np.testing.assert_allclose(back.tags[tid], body.tags[tid], atol=1e-12)
    cam = CameraModel("cam", (640, 480), np.array([[560.0, 0, 320.5], [0, 561.0, 240.0],
                                                   [0, 0, 1]]), np.array([0.1, -0.02, 0, 0, 0]))
    cal = save_calibration_txt(cam, tmp_path / "calibration.txt")
    assert len(cal.read_text().splitlines()) == 4
    again = load_calibration_txt(cal, (640, 480))
    np.testing.assert_array_equal(again.K, cam.K)
    np.testing.assert_array_equal(again.dist, cam.dist)
