"""Tests of ArUco rigid bodies in :class:`oralnav.control.vision.tracker.Tracker`.

Issue 3: "Also support ArUco rigid bodies (tags with known 3D corners, the format of
../shared/peer-data/sksurgery-arucotracker/reference.txt)", and "a replay camera source
... so the tracker runs on recorded data; it must read the peer videos". Each test's
docstring names the requirement it checks ("tracker bodies: ..."). Synthetic images are
drawn by ``tests.helpers.render_tags`` (through the camera's distortion); the peer-video
tests run where ../shared/peer-data exists and are skipped, with the reason, elsewhere.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from oralnav.config.fields import load_fields
from oralnav.config.rigid_bodies import load_calibration_txt, load_rigid_bodies
from oralnav.config.tracker import load_tracker
from oralnav.control.errors import MarkerFieldError
from oralnav.control.geometry import make_transform, pose_error
from oralnav.control.vision.camera import CameraModel, Rig
from oralnav.control.vision.detection import DetectionError
from oralnav.control.vision.pose import PoseEstimate
from oralnav.control.vision.rigid_body import (
    T_TAG_OPENCV_MARKER,
    BodyEstimate,
    RigidBody,
    single_tag_body,
)
from oralnav.control.vision.tracker import Tracker, TrackerSettings
from oralnav.drivers.camera.replay import ReplayRig
from tests.helpers import (
    ARUCO_DATA,
    PEER_REFERENCE_MM,
    PEER_TAG0_MM,
    mm_to_m,
    needs_aruco_data,
    render_tags,
)

ROOT = Path(__file__).resolve().parents[3]
RIG_FILE = ROOT / "config" / "rigs" / "stereo.toml"
FIELDS_FILE = ROOT / "config" / "fields" / "cell.toml"

K = np.array([[1000.0, 0.0, 511.5], [0.0, 1000.0, 383.5], [0.0, 0.0, 1.0]])
#: The right camera 80 mm to the right, turned 8 degrees toward the left one's axis.
T_REF_RIGHT = make_transform(Rotation.from_euler("y", -8, degrees=True), [0.08, 0.0, 0.0])
#: The plate 300 mm in front of the rig, tilted; its tags face the cameras.
T_REF_PLATE = make_transform(Rotation.from_euler("xyz", [20.0, -15.0, 10.0], degrees=True),
                             [0.02, -0.01, 0.3])
PLATE_IDS = (11, 100, 109, 304, 308, 560)  # tags of the peer's reference body


def _square(centre, side: float) -> np.ndarray:
    h = side / 2
    return np.array([[-h, -h, 0.0], [h, -h, 0.0], [h, h, 0.0], [-h, h, 0.0]]) + centre


def _plate(name: str = "plate", ids=PLATE_IDS, dictionary: str = "DICT_ARUCO_ORIGINAL",
           side: float = 0.015, pitch: float = 0.02) -> RigidBody:
    """Tags in a 3 x 2 grid, 15 mm sides at 20 mm pitch, body frame at the first tag."""
    return RigidBody(name, dictionary, {t: _square((k % 3 * pitch, k // 3 * pitch, 0.0), side)
                                        for k, t in enumerate(ids)})


@pytest.fixture(scope="module")
def rig() -> Rig:
    left = CameraModel("left", (1024, 768), K, np.array([-0.1, 0.05, 0.0005, -0.0005, 0.0]))
    right = CameraModel("right", (1024, 768), K, T_ref_cam=T_REF_RIGHT)
    return Rig("left", {"left": left, "right": right})


def _images(rig: Rig, body: RigidBody, T_ref_body=T_REF_PLATE, **kw) -> dict[str, np.ndarray]:
    return {n: render_tags(rig[n], body, rig[n].T_cam_ref @ T_ref_body, **kw)
            for n in rig.names}


@pytest.fixture(scope="module")
def plate_images(rig) -> dict[str, np.ndarray]:
    return _images(rig, _plate(), noise_px=2.0)


def _err(est: PoseEstimate, T_true: np.ndarray) -> tuple[float, float]:
    """Translation (mm) and rotation (deg) errors."""
    dt, dr = pose_error(est.T_ref_field, T_true)
    return dt * 1e3, float(np.degrees(dr))


# -- poses -------------------------------------------------------------------------------------
def test_body_pose_over_a_stereo_rig(rig, plate_images):
    """tracker bodies: a body appears in track()'s result under its name as a PoseEstimate
    (a BodyEstimate, method "aruco") with T_ref_field in metres in the rig's reference
    frame, corners = tag corners used in both cameras, the RMS, a 6x6 covariance, and the
    peer's tag bookkeeping; the pose is within 0.5 mm and 0.3 degrees of the truth."""
    tr = Tracker(rig, [], bodies=[_plate()])
    out = tr.track(plate_images)
    assert set(out) == {"plate"}
    est = out["plate"]
    assert isinstance(est, BodyEstimate) and isinstance(est, PoseEstimate)
    assert est.method == "aruco"
    assert est.cameras == ("left", "right")
    assert est.corners == 4 * len(PLATE_IDS) * 2
    assert est.tags_used == est.tags_seen == PLATE_IDS and est.quality == 1.0
    dt, dr = _err(est, T_REF_PLATE)
    assert dt < 0.5 and dr < 0.3, (dt, dr)
    assert 0 < est.reproj_rms_px < 0.6
    cov = est.covariance
    assert cov.shape == (6, 6) and np.allclose(cov, cov.T)
    assert np.all(np.linalg.eigvalsh(cov) > 0)
    assert tr.last_timing.stages == {"plate": "full"}
    assert tr.last_timing.total >= tr.last_timing.recognition > 0


def test_one_camera_off_the_reference(rig, plate_images):
    """tracker bodies: seen by the right camera alone, the body's pose is still given in
    the reference (left) frame: the camera's T_ref_cam (80 mm, 8 degrees) is applied."""
    est = Tracker(rig, [], bodies=[_plate()]).track({"right": plate_images["right"]})["plate"]
    assert est.cameras == ("right",) and est.corners == 4 * len(PLATE_IDS)
    dt, dr = _err(est, T_REF_PLATE)
    assert dt < 1.0 and dr < 0.5, (dt, dr)


def test_covariance_follows_the_geometry(rig, plate_images):
    """tracker bodies: the covariance comes from the final fit, so it tells good geometry
    from poor: two cameras pin the position better than one, and one 15 mm tag alone is
    far looser in rotation than six (over twice: the tag-edge shift of issue 34 item 6
    loosens the one-camera plate's rotation too, to 0.29 deg against its 0.20 deg error,
    where the residuals alone gave 0.14 deg)."""
    tag = RigidBody("tag", "DICT_ARUCO_ORIGINAL", {11: _square((0.0, 0.0, 0.0), 0.015)})
    tr = Tracker(rig, [], bodies=[_plate()])
    both = tr.track(plate_images)
    right = tr.track({"right": plate_images["right"]})
    # a second tracker: two bodies may not share tag 11
    tr_tag = Tracker(rig, [], bodies=[tag])
    both |= tr_tag.track(plate_images)
    right |= tr_tag.track({"right": plate_images["right"]})

    def rot_sigma(est):
        return float(np.sqrt(np.max(np.linalg.eigvalsh(est.covariance[3:, 3:]))))

    assert both["plate"].position_sigma_m < 0.8 * right["plate"].position_sigma_m
    assert rot_sigma(right["tag"]) > 2 * rot_sigma(right["plate"])
    dt, dr = _err(both["tag"], T_REF_PLATE)  # tag 11 sits at the plate's origin
    assert dt < 1.0 and dr < 3.0, (dt, dr)


def test_single_tag_and_mm_tables_give_metres(rig, tmp_path):
    """tracker bodies: units. A peer tag table in millimetres loads as metres (tag sides
    and poses), and the tracker reports metres: the plate written as a table gives the same
    pose as the plate built in metres, and a 30 mm single tag sits at 0.3 m, not 300."""
    plate = _plate()
    rows = [f"{t}\t" + "\t".join(f"{v * 1e3:.4f}" for v in np.vstack(
        [c.mean(axis=0), c]).ravel()) for t, c in plate.tags.items()]
    table = tmp_path / "plate_mm.txt"
    table.write_text("\n".join(rows) + "\n")
    (from_file,) = load_rigid_bodies([("plate", table)])
    np.testing.assert_allclose(from_file.corners(), plate.corners(), atol=1e-9)
    images = _images(rig, plate)
    a = Tracker(rig, [], bodies=[plate]).track(images)["plate"]
    b = Tracker(rig, [], bodies=[from_file]).track(images)["plate"]
    np.testing.assert_allclose(a.T_ref_field, b.T_ref_field, atol=1e-9)

    tag = single_tag_body(7, 0.030, "DICT_4X4_50", name="tag")
    est = Tracker(rig, [], bodies=[tag]).track(_images(rig, tag))["tag"]
    assert est.corners == 8 and abs(est.T_ref_field[2, 3] - 0.3) < 1e-3
    dt, dr = _err(est, T_REF_PLATE)
    assert dt < 1.0 and dr < 1.0, (dt, dr)


def test_from_files_with_bodies(tmp_path):
    """tracker bodies: load_tracker takes bodies as RigidBody objects, table paths
    (named after the file) or (name, path) pairs in body_dictionary, with or without a
    marker-field file."""
    row = " 7.25 7.25 0 0 0 0 14.5 0 0 14.5 14.5 0 0 14.5 0\n"
    table, other = tmp_path / "probe.txt", tmp_path / "t2.txt"
    table.write_text("1" + row)
    other.write_text("2" + row)
    tr = load_tracker(RIG_FILE, bodies=[table, ("other", other), _plate()])
    assert tr.fields == {} and list(tr.bodies) == ["probe", "other", "plate"]
    assert tr.bodies["probe"].dictionary == "DICT_ARUCO_ORIGINAL"
    np.testing.assert_allclose(tr.bodies["probe"].tags[1][2], [0.0145, 0.0145, 0.0])
    tr = load_tracker(RIG_FILE, FIELDS_FILE, method="ba",
                            bodies=[("t", table)], body_dictionary="DICT_6X6_250")
    assert set(tr.fields) == {"robot", "effector", "opener"} and tr.method == "ba"
    assert tr.bodies["t"].dictionary == "DICT_6X6_250"


# -- names and tags that would collide --------------------------------------------------------
def test_names_must_not_collide(rig):
    """tracker bodies: body names must differ from the field names and from each other
    (clear MarkerFieldError, a ValueError); a tracker needs a field or a body; bodies must
    be RigidBody objects."""
    fields = list(load_fields(FIELDS_FILE).values())
    with pytest.raises(MarkerFieldError, match="'opener' has the name of a marker field"):
        Tracker(rig, fields, bodies=[_plate("opener")])
    with pytest.raises(MarkerFieldError, match="'plate' is given twice"):
        Tracker(rig, [], bodies=[_plate(), _plate(ids=(1, 2))])
    with pytest.raises(ValueError, match="at least one marker field or rigid body"):
        Tracker(rig, [], bodies=[])
    with pytest.raises(MarkerFieldError, match="RigidBody"):
        Tracker(rig, [], bodies=["reference.txt"])  # type: ignore[list-item]


def test_body_tags_must_not_be_field_markers(rig):
    """tracker bodies: body tags must not be confused with field markers. DICT_4X4_50 is
    the start of the cell fields' DICT_4X4_1000 (the robot field's markers 0..34 read as
    DICT_4X4_50 tags 0..34), so such a body is refused, naming the field and the marker;
    ids outside the fields' blocks, and 5x5 dictionaries, are accepted. Two bodies may not
    share a tag either."""
    fields = list(load_fields(FIELDS_FILE).values())
    with pytest.raises(MarkerFieldError, match=r"tag 3 of DICT_4X4_50 reads as marker 3 "
                                               r"of field 'robot'"):
        Tracker(rig, fields, bodies=[_plate(ids=(3, 40, 41), dictionary="DICT_4X4_50")])
    with pytest.raises(MarkerFieldError, match="field 'opener'"):
        Tracker(rig, fields, bodies=[_plate(ids=(500, 201, 600), dictionary="DICT_4X4_1000")])
    ok = Tracker(rig, fields, bodies=[_plate("a", ids=(35, 40, 41), dictionary="DICT_4X4_50"),
                                      _plate("b", ids=(500, 600, 700),
                                             dictionary="DICT_4X4_1000"),
                                      _plate("c")])
    assert list(ok.bodies) == ["a", "b", "c"]
    with pytest.raises(MarkerFieldError, match="'b' and 'a' share tags"):
        Tracker(rig, [], bodies=[_plate("a"), _plate("b", ids=(1, 2, 11))])
    with pytest.raises(MarkerFieldError, match="share tags"):  # the same codes, two names
        Tracker(rig, [], bodies=[_plate("a", ids=(5, 6, 7), dictionary="DICT_4X4_50"),
                                 _plate("b", ids=(7, 60, 61), dictionary="DICT_4X4_100")])


# -- bad input: no pose rather than a wrong one -----------------------------------------------
def test_nothing_to_see_gives_no_body(rig):
    """tracker bodies, bad input: blank and pure-noise images give no body, not a pose."""
    tr = Tracker(rig, [], bodies=[_plate()])
    blank = {n: np.full((768, 1024), 200, np.uint8) for n in rig.names}
    assert tr.track(blank) == {}
    rng = np.random.default_rng(3)
    noise = {n: rng.integers(0, 256, (768, 1024), dtype=np.uint8) for n in rig.names}
    assert tr.track(noise) == {}


def test_disagreeing_tags_give_no_body(rig):
    """tracker bodies, bad input: a body's two tags that disagree with the model (the
    second stuck 10 mm off) give no pose rather than a compromise; with a third tag that
    agrees, the odd one is left out and the pose is right."""
    model = _plate(ids=(11, 100))
    moved = RigidBody("plate", model.dictionary,
                      {11: model.tags[11], 100: model.tags[100] + [0.0, 0.010, 0.0]})
    tr = Tracker(rig, [], bodies=[model])
    assert tr.track(_images(rig, moved)) == {}
    model3 = _plate(ids=(11, 100, 109))
    moved3 = RigidBody("plate", model3.dictionary, {**model3.tags,
                                                    100: model3.tags[100] + [0, 0.010, 0]})
    est = Tracker(rig, [], bodies=[model3]).track(_images(rig, moved3))["plate"]
    assert est.tags_used == (11, 109) and est.tags_seen == (11, 100, 109)
    dt, dr = _err(est, T_REF_PLATE)
    assert dt < 1.0 and dr < 1.0, (dt, dr)


def test_repeated_or_tiny_tags_give_no_body(rig):
    """tracker bodies, bad input: a single-tag body whose tag appears twice cannot say
    which copy is its own, and a tag too small to read (2 mm at 0.3 m) is not found:
    both give no pose."""
    tag = single_tag_body(7, 0.030, "DICT_4X4_50", name="tag")
    twice = RigidBody("tag", "DICT_4X4_50", {7: tag.tags[7]})
    left = rig["left"]
    img = render_tags(left, twice, left.T_cam_ref @ T_REF_PLATE)
    shifted = T_REF_PLATE.copy()
    shifted[0, 3] -= 0.06
    img = render_tags(left, twice, left.T_cam_ref @ shifted, image=img)
    tr = Tracker(rig, [], bodies=[tag])
    assert tr.track({"left": img}) == {}
    tiny = single_tag_body(7, 0.002, "DICT_4X4_50", name="tag")
    assert tr.track({"left": render_tags(left, tiny, T_REF_PLATE)}) == {}


def test_gates_withhold_poor_fits(rig, plate_images):
    """tracker bodies, bad input: the body's RMS and covariance gates apply (settings
    body_max_rms_px, body_max_position_sigma_mm, body_max_rotation_sigma_deg), and an
    image of the wrong size is a DetectionError as for fields."""
    body = [_plate()]
    assert "plate" in Tracker(rig, [], bodies=body).track(plate_images)
    for gate in ({"body_max_rms_px": 0.01}, {"body_max_position_sigma_mm": 0.001},
                 {"body_max_rotation_sigma_deg": 0.001}):
        tr = Tracker(rig, [], settings=TrackerSettings(**gate), bodies=body)
        assert tr.track(plate_images) == {}, gate
    with pytest.raises(DetectionError, match="camera 'left'"):
        Tracker(rig, [], bodies=body).track({"left": np.zeros((10, 10), np.uint8)})


# -- peer videos ---------------------------------------------------------------------------------
def _peer_rig(path: Path) -> Rig:
    import cv2

    cap = cv2.VideoCapture(str(path))
    w, h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
    cap.release()
    return Rig("cam", {"cam": load_calibration_txt(ARUCO_DATA / "calibration.txt", (w, h),
                                                   name="cam")})


@needs_aruco_data
async def test_peer_output_video_through_the_replay_source():
    """tracker bodies + replay: the tracker runs on the peer's output.avi read by the replay
    source (ReplayRig) with calibration.txt; the 50 mm DICT_4X4_50 tag 0 is found in every
    frame, and at frame index 1 it lies within 1 mm and 3 degrees of the peer's regression
    pose (OpenCV single-marker frame), at z = 210 +- 1 mm."""
    video = ARUCO_DATA / "output.avi"
    tr = Tracker(_peer_rig(video), [],
                 bodies=[single_tag_body(0, 0.050, "DICT_4X4_50", name="tag")])
    poses = []
    async with ReplayRig({"cam": video}) as replay:
        async for frames in replay:
            est = tr.track({c: f.image for c, f in frames.items()})
            assert est["tag"].tags_used == (0,) and est["tag"].corners == 4
            poses.append(est["tag"].T_ref_field)
    assert len(poses) == 10
    T_cam_marker = poses[1] @ T_TAG_OPENCV_MARKER
    dt, dr = pose_error(T_cam_marker, mm_to_m(PEER_TAG0_MM))
    assert dt < 1e-3 and np.degrees(dr) < 3.0, (dt, np.degrees(dr))
    assert abs(T_cam_marker[2, 3] - 0.210) <= 1e-3


@needs_aruco_data
def test_peer_multipattern_bodies_and_tags_seen():
    """tracker bodies: on the peer's multipattern.avi frame 0 (calibration.txt) the tracker
    sees 11 of the 12 tags of reference.txt and 5 of the 6 of pointer.txt (the peer's
    qualities 0.91667 and 0.83333), the DICT_ARUCO_ORIGINAL bodies do not take the
    DICT_4X4_50 tag 0, which a single-tag body of that dictionary finds beside them, and
    reference lies within 1 mm and 1 degree of the peer's pose."""
    from oralnav.drivers.camera.replay import read_frame

    video = ARUCO_DATA / "multipattern.avi"
    bodies = load_rigid_bodies([ARUCO_DATA / "reference.txt", ARUCO_DATA / "pointer.txt"])
    bodies.append(single_tag_body(0, 0.050, "DICT_4X4_50", name="tag0"))
    tr = Tracker(_peer_rig(video), [], bodies=bodies)
    est = tr.track({"cam": read_frame(video, 0)})
    assert set(est) == {"reference", "pointer", "tag0"}
    ref, ptr = est["reference"], est["pointer"]
    assert (len(ref.tags_seen), len(ptr.tags_seen)) == (11, 5)
    assert ref.quality == pytest.approx(0.91667, abs=1e-5)
    assert ptr.quality == pytest.approx(0.83333, abs=1e-5)
    assert ref.tags_used == ref.tags_seen and ptr.tags_used == ptr.tags_seen
    assert 0 not in ref.tags_seen + ptr.tags_seen and est["tag0"].tags_used == (0,)
    dt, dr = pose_error(ref.T_ref_field, mm_to_m(PEER_REFERENCE_MM))
    assert dt < 1e-3 and np.degrees(dr) < 1.0, (dt * 1e3, np.degrees(dr))
