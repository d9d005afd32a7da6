"""`oralnav track`: poses from image files or recordings, the JSON contract of issue 3, and
bad input (exit 2 with a message naming what is wrong); ArUco rigid bodies, peer
calibrations and the peer videos (those tests are skipped, with the reason, where
../shared/peer-data is absent)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from oralnav.cli import main as cli
from oralnav.config.rig import load_rig
from oralnav.control.geometry import make_transform, pose_error
from oralnav.control.vision.camera import CameraModel
from oralnav.control.vision.rigid_body import (
    T_TAG_OPENCV_MARKER,
    RigidBody,
    detect_tag_list,
    single_tag_body,
)
from tests.helpers import ARUCO_DATA, PEER_TAG0_MM, mm_to_m, needs_aruco_data, render_tags

ROOT = Path(__file__).resolve().parents[2]
RIG = ROOT / "config" / "rigs" / "stereo.toml"
FIELDS = ROOT / "config" / "fields" / "cell.toml"
SCENE = ROOT / "config" / "examples" / "stereo_cell.toml"


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    out = tmp_path_factory.mktemp("cell")
    assert cli.run(["sim", "render", str(SCENE), "--out", str(out), "--frames", "2"]) == 0
    return out


def _one_json(capsys) -> dict:
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 1, lines
    return json.loads(lines[0])


def _args(*extra: str) -> list[str]:
    return ["track", "--rig", str(RIG), "--fields", str(FIELDS), *extra]


def test_track_json_contract_and_accuracy(rendered, capsys):
    """Issue 3 CLI: `--image NAME=PATH` per camera prints {"fields": {NAME: {T_ref_field,
    corners, reproj_rms_px}}, "timing_ms": {"total"}}, and the poses match the truth."""
    f0 = rendered / "frame_0000"
    assert cli.run(_args("--image", f"left={f0 / 'left.png'}", "--image",
                         f"right={f0 / 'right.png'}", "--json")) == 0
    doc = _one_json(capsys)
    truth = json.loads((f0 / "truth.json").read_text())
    assert set(doc["fields"]) == {"robot", "effector", "opener"}
    assert doc["timing_ms"]["total"] > 0
    for name, est in doc["fields"].items():
        assert est["corners"] >= 6 and 0 < est["reproj_rms_px"] < 1.0
        T_true = np.asarray(truth["fields"][name]["T_ref_field"])
        te, re = pose_error(np.asarray(est["T_ref_field"]), T_true)
        # The effector field is 16 x 10 mm: one frame fixes its rotation to a few tenths
        # of a degree (0.25 deg over 10 mm is 0.04 mm at its edge).
        max_deg = 0.5 if name == "effector" else 0.1
        assert te < 1e-4 and np.degrees(re) < max_deg, (name, te, np.degrees(re))


def test_track_replays_an_image_folder(rendered, tmp_path, capsys):
    """Issue 3: the tracker runs on recorded data through the replay source."""
    for cam in ("left", "right"):
        d = tmp_path / cam
        d.mkdir()
        for k in range(2):
            img = cv2.imread(str(rendered / f"frame_{k:04d}" / f"{cam}.png"), cv2.IMREAD_GRAYSCALE)
            cv2.imwrite(str(d / f"{k:03d}.png"), img)
    assert cli.run(_args("--replay", f"left={tmp_path / 'left'}",
                         "--replay", f"right={tmp_path / 'right'}", "--json")) == 0
    doc = _one_json(capsys)
    assert len(doc["frames"]) == 2
    assert set(doc["frames"][1]["fields"]) == {"robot", "effector", "opener"}
    assert set(doc["frames"][1]["stages"].values()) <= {"predict", "roi"}


@pytest.mark.parametrize("extra, needle", [
    (["--image", "left=/nonexistent/left.png"], "no image file"),
    (["--image", "middle=IMG"], "unknown camera 'middle'"),
    (["--image", "left"], "NAME=PATH"),
    ([], "either --image"),
])
def test_track_bad_input_exits_2(rendered, tmp_path, capsys, extra, needle):
    """Issue 3 bad input: a missing file, an unknown camera, a malformed option: exit 2 and
    a message naming the problem, one JSON object with --json."""
    extra = [e.replace("IMG", str(rendered / "frame_0000" / "left.png")) for e in extra]
    assert cli.run(_args(*extra, "--json")) == 2
    doc = _one_json(capsys)
    assert needle in doc["error"]


def test_track_corrupt_or_wrong_size_image(rendered, tmp_path, capsys):
    """Issue 3 bad input: a corrupt file and an image of the wrong size are refused."""
    bad = tmp_path / "corrupt.png"
    bad.write_bytes(b"\x89PNG\r\n\x1a\nnot really")
    assert cli.run(_args("--image", f"left={bad}", "--json")) == 2
    assert "not a readable image" in _one_json(capsys)["error"]
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), np.zeros((100, 120), np.uint8))
    assert cli.run(_args("--image", f"left={small}", "--json")) == 2
    assert "120x100" in _one_json(capsys)["error"]


# -- rigid bodies, calibrations and the peer videos ------------------------------------------
# Bodies are reported under "bodies", beside "fields", with the same keys plus method,
# tags_seen, tags_used and quality; see docs/tracking.md.
T_REF_PLATE = make_transform(Rotation.from_euler("xyz", [10.0, -20.0, 5.0], degrees=True),
                             [-0.085, 0.02, 0.26])


def _plate(side: float = 0.010, pitch: float = 0.013) -> RigidBody:
    """Six DICT_ARUCO_ORIGINAL tags (the peer's reference ids) in a 3 x 2 grid."""
    h = side / 2
    sq = np.array([[-h, -h, 0.0], [h, -h, 0.0], [h, h, 0.0], [-h, h, 0.0]])
    ids = (11, 100, 109, 304, 308, 560)
    return RigidBody("plate", "DICT_ARUCO_ORIGINAL",
                     {t: sq + (k % 3 * pitch, k // 3 * pitch, 0.0) for k, t in enumerate(ids)})


def _write_table(body: RigidBody, path: Path) -> Path:
    """The body as a peer tag table: id, centre, 4 corners, millimetres."""
    rows = [f"{t} " + " ".join(f"{v * 1e3:.4f}" for v in np.vstack([c.mean(axis=0), c]).ravel())
            for t, c in body.tags.items()]
    path.write_text("\n".join(rows) + "\n")
    return path


def _write_calibration(path: Path, K: np.ndarray, dist: np.ndarray) -> Path:
    path.write_text("\n".join(" ".join(f"{v:.6f}" for v in row) for row in K) + "\n"
                    + " ".join(f"{v:.6f}" for v in dist) + "\n")
    return path


def test_track_fields_and_bodies_together(rendered, tmp_path, capsys):
    """Issue 3 CLI + rigid bodies: `--body NAME=PATH` (a peer tag table in mm) beside
    `--fields`: a body of DICT_ARUCO_ORIGINAL tags pasted into the rendered stereo cell is
    reported under "bodies" (T_ref_field in metres, rig reference frame, corners, RMS,
    method "aruco", tags seen) within 0.5 mm and 0.5 degrees, and the fields keep their
    accuracy under "fields"."""
    rig = load_rig(RIG)
    f0 = rendered / "frame_0000"
    plate = _plate()
    args = ["track", "--rig", str(RIG), "--fields", str(FIELDS),
            "--body", f"plate={_write_table(plate, tmp_path / 'plate.txt')}", "--json"]
    for cam in rig.names:
        img = cv2.imread(str(f0 / f"{cam}.png"), cv2.IMREAD_GRAYSCALE)
        img = render_tags(rig[cam], plate, rig[cam].T_cam_ref @ T_REF_PLATE, image=img)
        cv2.imwrite(str(tmp_path / f"{cam}.png"), img)
        args += ["--image", f"{cam}={tmp_path / f'{cam}.png'}"]
    assert cli.run(args) == 0
    doc = _one_json(capsys)
    assert set(doc) == {"fields", "bodies", "timing_ms"} and doc["timing_ms"]["total"] > 0
    assert set(doc["fields"]) == {"robot", "effector", "opener"}
    truth = json.loads((f0 / "truth.json").read_text())
    for name, est in doc["fields"].items():
        te, re = pose_error(np.asarray(est["T_ref_field"]),
                            np.asarray(truth["fields"][name]["T_ref_field"]))
        max_deg = 0.5 if name == "effector" else 0.1
        assert te < 1e-4 and np.degrees(re) < max_deg, (name, te, np.degrees(re))
    body = doc["bodies"]["plate"]
    assert body["method"] == "aruco" and body["cameras"] == ["left", "right"]
    assert body["tags_seen"] == body["tags_used"] == list(plate.ids)
    assert body["corners"] == 48 and 0 < body["reproj_rms_px"] < 1.0
    te, re = pose_error(np.asarray(body["T_ref_field"]), T_REF_PLATE)
    assert te < 5e-4 and np.degrees(re) < 0.5, (te, np.degrees(re))


def test_track_single_tag_with_a_calibration_file(tmp_path, capsys):
    """Issue 3 CLI: `--calibration CAMERA=calibration.txt` builds a one-camera rig (the
    camera is the reference frame; the image gives the size), `--tag NAME=DICT:ID:SIDE_MM`
    a one-tag body, and `--fields` is optional: the 40 mm tag's pose comes back in metres
    within 1 mm and 1 degree, under "bodies", with "fields" empty."""
    K = np.array([[800.0, 0.0, 319.5], [0.0, 800.0, 239.5], [0.0, 0.0, 1.0]])
    dist = np.array([0.1, 0.0, 0.0, 0.0, 0.0])
    cal = _write_calibration(tmp_path / "calibration.txt", K, dist)
    cam = CameraModel("cam", (640, 480), K, dist)
    T = make_transform(Rotation.from_euler("xyz", [15.0, 10.0, 30.0], degrees=True),
                       [0.01, -0.005, 0.25])
    img = render_tags(cam, single_tag_body(7, 0.040, "DICT_4X4_50"), T)
    cv2.imwrite(str(tmp_path / "cam.png"), img)
    assert cli.run(["track", "--calibration", f"cam={cal}", "--tag", "t=DICT_4X4_50:7:40",
                    "--image", f"cam={tmp_path / 'cam.png'}", "--json"]) == 0
    doc = _one_json(capsys)
    assert doc["fields"] == {} and set(doc["bodies"]) == {"t"}
    est = doc["bodies"]["t"]
    assert est["corners"] == 4 and est["tags_seen"] == [7] and est["cameras"] == ["cam"]
    te, re = pose_error(np.asarray(est["T_ref_field"]), T)
    assert te < 1e-3 and np.degrees(re) < 1.0, (te, np.degrees(re))


def test_track_replay_frames_keep_the_json_contract(tmp_path, capsys):
    """Issue 3 CLI JSON contract on replays: every frame carries "fields", "bodies" and
    "timing_ms": {"total": ...} (a dict, as for a single frame), plus "stages"."""
    K = np.array([[800.0, 0.0, 319.5], [0.0, 800.0, 239.5], [0.0, 0.0, 1.0]])
    cal = _write_calibration(tmp_path / "calibration.txt", K, np.zeros(5))
    cam = CameraModel("cam", (640, 480), K)
    rec = tmp_path / "rec"
    rec.mkdir()
    tag = single_tag_body(7, 0.040, "DICT_4X4_50")
    for k in range(2):
        T = make_transform(Rotation.from_euler("y", 10 * k, degrees=True), [0.0, 0.0, 0.25])
        cv2.imwrite(str(rec / f"{k}.png"), render_tags(cam, tag, T))
    assert cli.run(["track", "--calibration", f"cam={cal}", "--tag", "t=DICT_4X4_50:7:40",
                    "--replay", f"cam={rec}", "--json"]) == 0
    doc = _one_json(capsys)
    assert len(doc["frames"]) == 2 and doc["timing_ms"]["median"] > 0
    for k, frame in enumerate(doc["frames"]):
        assert frame["frame"] == k and frame["fields"] == {}
        assert frame["timing_ms"]["total"] > 0 and frame["stages"] == {"t": "full"}
        assert abs(frame["bodies"]["t"]["T_ref_field"][2][3] - 0.25) < 1e-3


@needs_aruco_data
def test_track_peer_output_video(capsys):
    """Issue 3 replay on the peer videos: `oralnav track --calibration cam=calibration.txt
    --tag tag=DICT_4X4_50:0:50 --replay cam=output.avi --frames 3 --json` prints the tag's
    pose in each of the 3 frames; frame index 1 lies within 1 mm and 3 degrees of the
    peer's regression pose (OpenCV single-marker frame = ours @ T_TAG_OPENCV_MARKER)."""
    assert cli.run(["track", "--calibration", f"cam={ARUCO_DATA / 'calibration.txt'}",
                    "--tag", "tag=DICT_4X4_50:0:50",
                    "--replay", f"cam={ARUCO_DATA / 'output.avi'}", "--frames", "3",
                    "--json"]) == 0
    doc = _one_json(capsys)
    assert [f["frame"] for f in doc["frames"]] == [0, 1, 2]
    assert all(f["bodies"]["tag"]["tags_seen"] == [0] for f in doc["frames"])
    T = np.asarray(doc["frames"][1]["bodies"]["tag"]["T_ref_field"]) @ T_TAG_OPENCV_MARKER
    te, re = pose_error(T, mm_to_m(PEER_TAG0_MM))
    assert te < 1e-3 and np.degrees(re) < 3.0, (te * 1e3, np.degrees(re))
    assert abs(T[2, 3] - 0.210) <= 1e-3


@needs_aruco_data
def test_track_peer_multipattern_bodies(capsys):
    """Issue 3 replay on the peer videos: multipattern.avi with `--body reference=...
    --body pointer=...` (DICT_ARUCO_ORIGINAL, the default --body-dictionary) reports, in
    frame 0, 11 of the 12 reference tags and 5 of the 6 pointer tags (the peer's
    qualities), without the video's DICT_4X4_50 tag 0."""
    assert cli.run(["track", "--calibration", f"cam={ARUCO_DATA / 'calibration.txt'}",
                    "--body", f"reference={ARUCO_DATA / 'reference.txt'}",
                    "--body", f"pointer={ARUCO_DATA / 'pointer.txt'}",
                    "--replay", f"cam={ARUCO_DATA / 'multipattern.avi'}", "--frames", "1",
                    "--json"]) == 0
    bodies = _one_json(capsys)["frames"][0]["bodies"]
    assert set(bodies) == {"reference", "pointer"}
    assert (len(bodies["reference"]["tags_seen"]), len(bodies["pointer"]["tags_seen"])) == (11, 5)
    assert bodies["reference"]["quality"] == pytest.approx(0.91667, abs=1e-5)
    assert bodies["pointer"]["quality"] == pytest.approx(0.83333, abs=1e-5)
    assert 0 not in bodies["reference"]["tags_seen"] + bodies["pointer"]["tags_seen"]


@pytest.mark.parametrize("extra, needle", [
    (["--tag", "t=DICT_4X4_50:0"], "NAME=DICT:ID:SIDE_MM"),
    (["--tag", "t=DICT_4X4_50:x:50"], "ID must be a whole number"),
    (["--tag", "t=DICT_NOPE:0:50"], "unknown ArUco dictionary 'DICT_NOPE'"),
    (["--tag", "t=DICT_4X4_50:50:50"], "outside DICT_4X4_50"),
    (["--tag", "t=DICT_4X4_50:0:-5"], "positive length"),
    (["--tag", "t=DICT_4X4_50:40:5", "--tag", "t=DICT_4X4_50:41:5"], "'t' is given twice"),
    (["--body", "b=/nonexistent/b.txt"], "file not found"),
    (["--body", "b"], "NAME=PATH"),
    ([], "nothing to track"),
    (["--calibration", "cam=CAL", "--tag", "t=DICT_4X4_50:40:5"], "either --rig"),
])
def test_track_body_bad_input_exits_2(rendered, extra, needle, capsys):
    """Issue 3 bad input for bodies: malformed --tag / --body, unknown dictionaries, ids
    outside them, missing tables, nothing to track, --rig with --calibration: exit 2 and a
    message naming the problem (one JSON object with --json)."""
    extra = [e.replace("CAL", str(ROOT / "missing.txt")) for e in extra]
    img = rendered / "frame_0000" / "left.png"
    assert cli.run(["track", "--rig", str(RIG), "--image", f"left={img}", *extra,
                    "--json"]) == 2
    assert needle in _one_json(capsys)["error"]


def test_track_body_collisions_exit_2(rendered, tmp_path, capsys):
    """Issue 3 bad input for bodies: a body named like a field, a tag that the fields'
    markers would be read as (DICT_4X4_50 id 3 is the robot field's marker 3, and the
    cell image really shows it), and a --calibration for a camera that has no image:
    exit 2, naming what collides."""
    img = rendered / "frame_0000" / "left.png"
    base = ["track", "--rig", str(RIG), "--fields", str(FIELDS), "--image", f"left={img}"]
    assert cli.run([*base, "--tag", "opener=DICT_4X4_50:40:5", "--json"]) == 2
    assert "'opener' has the name of a marker field" in _one_json(capsys)["error"]
    assert cli.run([*base, "--tag", "t=DICT_4X4_50:3:5", "--json"]) == 2
    assert "reads as marker 3 of field 'robot'" in _one_json(capsys)["error"]
    seen = {t for t, _ in detect_tag_list(cv2.imread(str(img), cv2.IMREAD_GRAYSCALE),
                                           "DICT_4X4_50")}
    assert 3 in seen  # the refusal is not hypothetical
    cal = _write_calibration(tmp_path / "c.txt", np.eye(3) * [800, 800, 1], np.zeros(5))
    assert cli.run(["track", "--calibration", f"right={cal}", "--tag", "t=DICT_4X4_50:0:5",
                    "--image", f"left={img}", "--json"]) == 2
    assert "names camera 'right'" in _one_json(capsys)["error"]
