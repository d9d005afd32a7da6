"""Issue 33, item 6: `oralnav sim aruco` and `oralnav sim pivot` write the inputs of the
README's `track` (ArUco bodies) and `calibrate pivot` lines, so those run on a fresh clone:
each writes files its reader takes, with a truth the reader's answer matches, and bad
options exit 2 naming the option."""

from __future__ import annotations

import contextlib
import io
import json

import numpy as np
import pytest

from oralnav.cli import main as cli
from oralnav.config.rigid_bodies import load_calibration_txt, load_rigid_body
from oralnav.control.geometry import pose_error
from oralnav.drivers.camera.replay import frame_count
from oralnav.sim.world.aruco_video import CAMERA, REFERENCE_PLATE, TAG_SPEC, field_body
from tests.helpers import ROOT


def _json(capsys) -> dict:
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1, out
    return json.loads(out[0])


@pytest.fixture(scope="module")
def aruco(tmp_path_factory):
    """`sim aruco --frames 3`, run once: (its JSON answer, the folder)."""
    out = tmp_path_factory.mktemp("aruco")
    buf = io.StringIO()  # a module fixture cannot use capsys
    with contextlib.redirect_stdout(buf):
        assert cli.run(["sim", "aruco", "--out", str(out), "--frames", "3", "--json"]) == 0
    return json.loads(buf.getvalue()), out


def test_sim_aruco_writes_the_files_track_reads(aruco):
    """issue 33 item 6: `sim aruco` writes a replayable video.avi (the frames asked), a
    calibration.txt and a reference.txt that read back as the rendered camera and body,
    and a truth.json with every body's pose per frame."""
    doc, out = aruco
    assert doc["video"] == str(out / "video.avi") and doc["frames"] == 3
    assert frame_count(out / "video.avi") == 3
    cam = load_calibration_txt(out / "calibration.txt", CAMERA.size, name="cam")
    np.testing.assert_allclose(cam.K, CAMERA.K)
    np.testing.assert_allclose(cam.dist, CAMERA.dist)
    body = load_rigid_body(out / "reference.txt")
    expected = field_body(REFERENCE_PLATE)
    assert body.ids == expected.ids and body.dictionary == expected.dictionary
    for tid in body.ids:
        np.testing.assert_allclose(body.tags[tid], expected.tags[tid], atol=1e-9)
    truth = json.loads((out / "truth.json").read_text())
    assert [f["frame"] for f in truth["frames"]] == [0, 1, 2]
    assert set(truth["frames"][0]["T_cam_body"]) == {"reference", "tag"}
    assert doc["tag"] == TAG_SPEC == "tag=DICT_4X4_50:0:50"


def test_track_finds_the_sim_aruco_bodies_at_their_true_poses(aruco, capsys):
    """issue 33 item 6: `track --calibration --tag --body --replay` on what `sim aruco`
    wrote gives both bodies in every frame, within 3 mm and 1 deg of truth.json (one 50 mm
    tag at 0.33 m is good to about 1 mm in depth)."""
    doc, out = aruco
    assert cli.run(doc["track"][1:] + ["--json"]) == 0
    frames = _json(capsys)["frames"]
    truth = json.loads((out / "truth.json").read_text())["frames"]
    assert len(frames) == 3
    for got, want in zip(frames, truth, strict=True):
        assert set(got["bodies"]) == {"reference", "tag"}
        assert len(got["bodies"]["reference"]["tags_used"]) >= 10
        for name, est in got["bodies"].items():
            te, re = pose_error(np.asarray(est["T_ref_field"]),
                                np.asarray(want["T_cam_body"][name]))
            assert te < 3e-3 and np.degrees(re) < 1.0, (name, te, np.degrees(re))


@pytest.mark.parametrize("option, value", [("--frames", "0"), ("--fps", "0")])
def test_sim_aruco_bad_option_exits_2_naming_it(tmp_path, capsys, option, value):
    """issue 33 item 6: a frame count or rate out of range exits 2, the message names the
    option, and nothing is written."""
    assert cli.run(["sim", "aruco", "--out", str(tmp_path / "a"), option, value,
                    "--json"]) == 2
    doc = _json(capsys)
    assert doc["exit"] == 2 and doc["error"].startswith(f"{option} must be")
    assert not (tmp_path / "a").exists()


def test_sim_pivot_poses_give_back_the_stated_tip(tmp_path, capsys):
    """issue 33 item 6: `sim pivot` writes poses `calibrate pivot` reads (its comment header
    included) and states the true tip; RANSAC leaves out the outliers and recovers the tip
    within the residual RMS of the poses it kept."""
    poses = tmp_path / "out" / "pivot.txt"
    assert cli.run(["sim", "pivot", "--poses", "60", "--outliers", "6", "--out", str(poses),
                    "--json"]) == 0
    truth = _json(capsys)
    assert truth["out"] == str(poses) and len(truth["outliers"]) == 6
    np.testing.assert_allclose(truth["tip_offset"], [15.0, 70.0, 5.0])
    assert poses.read_text().startswith("# oralnav sim pivot: 60 poses")
    assert cli.run(["calibrate", "pivot", "--matrices", str(poses), "--method", "ransac",
                    "--json"]) == 0
    got = _json(capsys)
    err = np.linalg.norm(np.subtract(got["tip_offset"], truth["tip_offset"]))
    assert err < got["rms"] < 0.5, (err, got["rms"])
    assert np.linalg.norm(np.subtract(got["pivot_point"], truth["pivot_point"])) < got["rms"]


@pytest.mark.parametrize("args, option", [
    (["--poses", "5"], "--poses"),
    (["--outliers", "80"], "--outliers"),
    (["--corner-noise", "-1"], "--corner-noise"),
    (["--spread-deg", "1"], "--spread-deg"),
    (["--config", str(ROOT / "config" / "hardware.example.toml")], "--config"),
])
def test_sim_pivot_bad_option_exits_2_naming_it(tmp_path, capsys, args, option):
    """issue 33 item 6: out-of-range counts, noise or tilt, more outliers than RANSAC can
    leave out, or a configuration without a simulated cell exit 2 naming the option, and
    no file is written."""
    out = tmp_path / "pivot.txt"
    assert cli.run(["sim", "pivot", "--out", str(out), *args, "--json"]) == 2
    doc = _json(capsys)
    assert doc["exit"] == 2 and doc["error"].startswith(option), doc
    assert not out.exists()
