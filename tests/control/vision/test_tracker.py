"""Tests of ``oralnav.control.vision.tracker``: every method and search stage on the shipped cell.

Each test's docstring names the requirement it checks (navigation paper, section III.C-E:
recognition, coarse pose, (NVG-)BA, dynamic ROI eqs. 18-19). Images come from the shipped
``stereo_cell`` scene, rendered once per module (seeded noise, blur, illumination).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from oralnav.config.scene import load_scene
from oralnav.config.tracker import load_tracker
from oralnav.control.geometry import pose_error
from oralnav.control.vision.detection import DetectionError
from oralnav.control.vision.pose import PoseEstimate
from oralnav.control.vision.tracker import METHODS, FrameTiming, Tracker
from oralnav.sim.world.render import SceneRenderer

ROOT = Path(__file__).resolve().parents[3]
RIG_FILE = ROOT / "config" / "rigs" / "stereo.toml"
FIELDS_FILE = ROOT / "config" / "fields" / "cell.toml"
CELL = ROOT / "config" / "examples" / "stereo_cell.toml"
FIELDS = ("robot", "effector", "opener")
FAR = np.array([[1.0, 0, 0, 5.0], [0, 1.0, 0, 5.0], [0, 0, 1.0, 1.0], [0, 0, 0, 1.0]])


@pytest.fixture(scope="module")
def cell():
    """The shipped stereo cell: scene, prepared renderer and three static frames (the
    noise differs from frame to frame)."""
    scene = load_scene(CELL)
    renderer = SceneRenderer(scene)
    renderer.prepare()
    frames = [renderer.render(frame=i) for i in range(3)]
    return scene, renderer, frames


def _tracker(scene, **kw) -> Tracker:
    return Tracker(scene.rig, [p.field for p in scene.placements], **kw)


def _err(est: PoseEstimate, T_true: np.ndarray) -> tuple[float, float]:
    """Translation (mm) and rotation (deg) errors."""
    dt, dr = pose_error(est.T_ref_field, T_true)
    return dt * 1e3, float(np.degrees(dr))


# -- construction ---------------------------------------------------------------------------
def test_from_files_with_the_shipped_rig_and_fields():
    """Tracker construction: load_tracker reads the shipped rig and marker-field files
    (cameras left/right, fields robot/effector/opener) and passes method and options on;
    unknown methods or modes, duplicate field names and an empty field list are refused."""
    tr = load_tracker(RIG_FILE, FIELDS_FILE, method="ba", mode="roi", weighting="axis")
    assert set(tr.fields) == set(FIELDS)
    assert tuple(tr.rig.names) == ("left", "right")
    assert (tr.method, tr.mode, tr.weighting) == ("ba", "roi", "axis")
    assert load_tracker(str(RIG_FILE), str(FIELDS_FILE)).method == "nvgba"
    assert isinstance(tr.last_timing, FrameTiming)
    fields = list(tr.fields.values())
    with pytest.raises(ValueError, match="unknown method 'lsq'"):
        Tracker(tr.rig, fields, method="lsq")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="unknown mode 'fast'"):
        Tracker(tr.rig, fields, mode="fast")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="unique"):
        Tracker(tr.rig, fields + fields[:1])
    with pytest.raises(ValueError, match="at least one marker field"):
        Tracker(tr.rig, [])


# -- accuracy -------------------------------------------------------------------------------
# (translation mm, rotation deg) bounds per method on robot and opener; pnp uses one camera.
BOUNDS = {"nvgba": (0.1, 0.1), "ba": (0.1, 0.1), "pnp": (0.5, 0.5)}


@pytest.mark.parametrize("mode", ["predict", "full"])
@pytest.mark.parametrize("method", list(BOUNDS))
def test_every_method_finds_every_field_accurately(cell, method, mode):
    """Tracking accuracy: on three frames of the shipped cell every method finds all three
    fields; NVG-BA and BA put the robot and opener fields within 0.1 mm and 0.1 deg of
    the truth and the end-effector within 0.1 mm (its rotation: see the xfail test
    below); single-camera PnP within 0.5 mm and 0.5 deg."""
    scene, _, frames = cell
    tr = _tracker(scene, method=method, mode=mode)
    t_max, r_max = BOUNDS[method]
    for fr in frames:
        out = tr.track(fr.images)
        assert set(out) == set(FIELDS), (method, mode, fr.frame, set(out))
        for name, est in out.items():
            dt, dr = _err(est, fr.T_ref_field[name])
            assert est.method == method
            assert dt <= t_max, (name, fr.frame, dt)
            if name == "effector":
                assert dr <= 0.5, (name, fr.frame, dr)
            else:
                assert dr <= r_max, (name, fr.frame, dr)


@pytest.mark.xfail(strict=True, reason=(
    "the end-effector field (8x5 squares of 2 mm round a 6 mm radius, 185 mm away) comes "
    "out 0.08-0.15 deg off about its cylinder axis from full-image detection (median "
    "0.09 deg over 6 frames), 1-2 sigma of its own covariance (~0.07 deg): the corners "
    "beyond 60 deg obliquity are now dropped (that halved the error), the rest still carry "
    "0.1-0.2 px of refinement bias on so strong a curvature"))
@pytest.mark.parametrize("method", ["nvgba", "ba"])
def test_effector_rotation_within_a_tenth_of_a_degree(cell, method):
    """Tracking accuracy: NVG-BA and BA put the end-effector field within 0.1 deg of the
    truth on every frame, from full-image detection."""
    scene, _, frames = cell
    tr = _tracker(scene, method=method, mode="full")
    worst = max(_err(tr.track(fr.images)["effector"], fr.T_ref_field["effector"])[1]
                for fr in frames)
    assert worst <= 0.1, worst


@pytest.fixture(scope="module")
def opencv_frame0(cell):
    """The OpenCV baseline on frame 0 (about a second: run once)."""
    scene, _, frames = cell
    tr = _tracker(scene, method="opencv", mode="full")
    return tr.track(frames[0].images), tr.last_timing


def test_opencv_baseline_on_plane_and_opener(cell, opencv_frame0):
    """Tracking baseline (OpenCV CharucoDetector + solvePnP per camera): the robot and
    opener fields, when reported, are within 0.5 mm of the truth with a finite RMS, and
    the baseline reports at least one field."""
    _, _, frames = cell
    out, timing = opencv_frame0
    assert out
    for name in ("robot", "opener"):
        if name in out:
            est = out[name]
            assert est.method == "opencv" and len(est.cameras) == 1
            assert np.isfinite(est.reproj_rms_px)
            assert _err(est, frames[0].T_ref_field[name])[0] <= 0.5
            assert timing.stages[name] == "full"


def test_opencv_baseline_reports_only_right_poses(cell, opencv_frame0):
    """Tracking baseline: the OpenCV baseline may miss fields, but every field it reports
    is within 0.5 mm of the truth, with a finite reprojection RMS."""
    _, _, frames = cell
    out, _ = opencv_frame0
    for name, est in out.items():
        assert np.isfinite(est.reproj_rms_px), name
        assert _err(est, frames[0].T_ref_field[name])[0] <= 0.5, name


def test_estimates_carry_a_usable_covariance(cell):
    """Pose estimate contents: a 6x6 symmetric positive-definite covariance, at least 6
    corners, an RMS under the acceptance gate, both cameras and per-camera inliers that
    index the field's corners."""
    scene, _, frames = cell
    tr = _tracker(scene)
    out = tr.track(frames[0].images)
    for name, est in out.items():
        fld = tr.fields[name]
        C = est.covariance
        assert C.shape == (6, 6)
        np.testing.assert_allclose(C, C.T, rtol=1e-9, atol=1e-30)
        assert np.all(np.linalg.eigvalsh(C) > 0)
        assert est.corners >= 6
        assert 0 < est.reproj_rms_px <= tr.settings.max_rms_px
        assert set(est.cameras) == {"left", "right"}
        assert sum(len(r) for r, _ in est.per_camera.values()) == est.corners
        for rows, px in est.per_camera.values():
            assert np.all((rows >= 0) & (rows < len(fld.corners))) and px.shape == (len(rows), 2)
        # the truth lies within a few sigma of the estimate (0.1 mm at most anyway)
        assert 0 < est.position_sigma_m < 1e-4


def test_covariance_gate_withholds_loose_poses(cell):
    """Bad input / safety gate: an estimate whose covariance is looser than the settings'
    position or rotation limit is withheld (absent), not reported; the same frame's fields
    are reported under the defaults, whose limits (0.5 mm, 0.5 deg) sit far above them."""
    from dataclasses import replace

    scene, _, frames = cell
    tr = _tracker(scene, mode="full")
    out = tr.track(frames[0].images)
    assert set(out) == set(FIELDS)
    sigma_mm = {n: e.position_sigma_m * 1e3 for n, e in out.items()}
    assert max(sigma_mm.values()) < 0.2 * tr.settings.max_position_sigma_mm
    # a limit between the fields' sigmas drops exactly the looser ones
    cut = float(np.median(list(sigma_mm.values())))
    strict = _tracker(scene, mode="full",
                      settings=replace(tr.settings, max_position_sigma_mm=cut))
    assert set(strict.track(frames[0].images)) == {n for n, s in sigma_mm.items() if s <= cut}
    tight_rot = _tracker(scene, mode="full",
                         settings=replace(tr.settings, max_rotation_sigma_deg=1e-4))
    assert tight_rot.track(frames[0].images) == {}


# -- search stages --------------------------------------------------------------------------
@pytest.mark.parametrize("mode, steady", [("predict", "predict"), ("roi", "roi"),
                                          ("full", "full")])
def test_stages_move_from_full_to_the_mode_and_reset(cell, mode, steady):
    """Search stages: the first frame searches whole images ('full'); later frames of a
    tracked field use the mode's stage ('predict' corner tracking, 'roi' boxes of eqs.
    18-19); reset() forgets the poses and the next frame is 'full' again. The timing
    splits the frame's time into recognition, pose and ROI work."""
    scene, _, frames = cell
    tr = _tracker(scene, mode=mode)
    stages = []
    for fr in frames:
        tr.track(fr.images)
        stages.append(dict(tr.last_timing.stages))
    assert stages[0] == dict.fromkeys(FIELDS, "full")
    assert stages[1] == stages[2] == dict.fromkeys(FIELDS, steady)
    t = tr.last_timing
    assert t.total > 0 and t.recognition > 0 and t.pose > 0
    assert t.recognition + t.pose + t.roi <= t.total * 1.05
    assert set(t.as_dict()) == {"total", "recognition", "pose", "roi", "stages"}
    tr.reset()
    tr.track(frames[0].images)
    assert tr.last_timing.stages == dict.fromkeys(FIELDS, "full")


def test_field_out_of_view_is_absent_not_stale(cell):
    """Tracking: a field that leaves the view is absent from the result (no stale pose),
    the others still track; when it comes back it is found by a whole-image search."""
    scene, renderer, frames = cell
    tr = _tracker(scene)
    tr.track(frames[0].images)
    tr.track(frames[1].images)
    for k in (2, 3):
        fr = renderer.render(poses={"robot": FAR}, frame=k)
        assert "robot" not in fr.truth["left"] and "robot" not in fr.truth["right"]
        out = tr.track(fr.images)
        assert set(out) == {"effector", "opener"}
        assert "robot" not in tr.last_timing.stages
        for name, est in out.items():
            assert _err(est, fr.T_ref_field[name])[0] <= 0.1
    out = tr.track(frames[2].images)
    assert set(out) == set(FIELDS)
    assert tr.last_timing.stages["robot"] == "full"
    assert _err(out["robot"], frames[2].T_ref_field["robot"])[0] <= 0.1


def _about_axis(T: np.ndarray, fld, angle: float) -> np.ndarray:
    """``T`` turned by ``angle`` about the field's cylinder axis (parallel to field y
    through (xc, *, radius)): the sheet slides along itself."""
    c = np.array([0.5 * fld.sheet_size[0], 0.0, fld.surface.radius])
    M = np.eye(4)
    M[:3, :3] = Rotation.from_rotvec([0.0, angle, 0.0]).as_matrix()
    M[:3, 3] = c - M[:3, :3] @ c
    return T @ M


def _moved(scene, case: str) -> tuple[str, np.ndarray]:
    if case == "opener-x":
        name = "opener"
        T = scene.placement(name).T_ref_field.copy()
        fld = scene.placement(name).field
        step = np.eye(4)
        step[0, 3] = fld.square
        return name, T @ step
    if case == "opener-arc":
        fld = scene.placement("opener").field
        return "opener", _about_axis(scene.placement("opener").T_ref_field, fld,
                                     fld.square / fld.surface.radius)
    fld = scene.placement("robot").field
    step = np.eye(4)
    step[0, 3] = fld.square
    return "robot", scene.placement("robot").T_ref_field @ step


@pytest.mark.parametrize("mode", ["predict", "roi"])
@pytest.mark.parametrize("case", ["opener-x", "opener-arc", "robot-x"])
def test_one_square_jump_is_not_a_false_lock(cell, case, mode):
    """Identity check of predictive tracking: after two static frames, the field jumps by
    exactly one square (along its x axis, or for the opener cylinder also round its axis,
    where the corner grid maps onto itself): the corners near the prediction are a
    square off, so a lock on them would be a one-square error. The reported pose is the
    new one (within 0.2 mm, 0.2 deg), not the old one."""
    scene, renderer, frames = cell
    tr = _tracker(scene, mode=mode)
    tr.track(frames[0].images)
    tr.track(frames[1].images)
    name, T_new = _moved(scene, case)
    fr = renderer.render(poses={name: T_new}, frame=5)
    out = tr.track(fr.images)
    assert name in out
    dt, dr = _err(out[name], T_new)
    assert dt <= 0.2 and dr <= 0.2, (case, dt, dr)
    assert _err(out[name], frames[1].T_ref_field[name])[0] > 2.0  # it did move
    assert tr.last_timing.stages[name] != "predict"


def test_constant_velocity_motion_keeps_predicting(cell):
    """Predictive tracking: a field moving at constant velocity (0.4 mm and 0.3 deg per
    frame) is tracked by the constant-velocity prediction ('predict' stage) within
    0.1 mm from the third frame on."""
    scene, renderer, _ = cell
    tr = _tracker(scene)
    T0 = scene.placement("opener").T_ref_field
    for k in range(5):
        T = T0.copy()
        T[:3, :3] = Rotation.from_euler("x", 0.3 * k, degrees=True).as_matrix() @ T0[:3, :3]
        T[:3, 3] += np.array([0.4e-3, -0.2e-3, 0.1e-3]) * k
        fr = renderer.render(poses={"opener": T}, frame=10 + k)
        out = tr.track(fr.images)
        assert _err(out["opener"], T)[0] <= 0.1
        if k >= 2:
            assert tr.last_timing.stages["opener"] == "predict"


def _swayed(T: np.ndarray, s: float) -> np.ndarray:
    """``T`` turned by ``s`` times (0.5, 0.3, -0.4) deg and moved by ``s`` times
    (0.6, -0.4, 0.3) mm, in the reference frame."""
    out = T.copy()
    out[:3, :3] = Rotation.from_rotvec(np.radians([0.5, 0.3, -0.4]) * s).as_matrix() @ T[:3, :3]
    out[:3, 3] += np.array([0.6e-3, -0.4e-3, 0.3e-3]) * s
    return out


def test_predictive_tracking_reports_rigid_poses(cell):
    """issue 30: every published pose is rigid to 1e-9. All three fields sway smoothly
    (8 rendered poses, played three times: 24 frames, each field on the 'predict' stage
    from the third frame on); every reported T_ref_field has ||R^T R - I|| < 1e-9 and
    det R = 1 within 1e-9. Each estimate starts from the constant-velocity prediction, so
    a prediction that is not a rotation (a matrix product fed back frame after frame) is
    inherited and grows: it passed 1e-9 after about 20 frames."""
    scene, renderer, _ = cell
    period = 8
    frames = [renderer.render(poses={n: _swayed(scene.placement(n).T_ref_field,
                                                0.15 * np.sin(2 * np.pi * k / period))
                                     for n in FIELDS}, frame=20 + k)
              for k in range(period)]
    tr = _tracker(scene)
    for k in range(3 * period):
        fr = frames[k % period]
        out = tr.track(fr.images)
        assert set(out) == set(FIELDS), k
        for name, est in out.items():
            R = est.T_ref_field[:3, :3]
            ortho, det = float(np.linalg.norm(R.T @ R - np.eye(3))), float(np.linalg.det(R))
            assert ortho < 1e-9 and abs(det - 1.0) < 1e-9, (k, name, ortho, det)
            assert np.array_equal(est.T_ref_field[3], [0.0, 0.0, 0.0, 1.0]), (k, name)
            assert _err(est, fr.T_ref_field[name])[0] <= 0.1, (k, name)
        if k >= 2:
            assert tr.last_timing.stages == dict.fromkeys(FIELDS, "predict"), k


# -- bad input and failure ------------------------------------------------------------------
def test_bad_images_raise_detection_error(cell):
    """Tracking bad input: an unknown camera name, an image of the wrong size or dtype,
    an empty mapping or a non-mapping raise DetectionError with a message that names the
    camera and the problem; the tracker's state is untouched."""
    scene, _, frames = cell
    tr = _tracker(scene)
    images = frames[0].images
    tr.track(images)
    with pytest.raises(DetectionError, match=r"unknown camera 'middle'; the rig has left, right"):
        tr.track({"middle": images["left"]})
    with pytest.raises(DetectionError,
                       match=r"camera 'right': image is 960x600, the camera is 1920x1200"):
        tr.track({"left": images["left"], "right": images["right"][::2, ::2]})
    with pytest.raises(DetectionError, match=r"camera 'left': expected dtype uint8"):
        tr.track({"left": images["left"].astype(np.float32)})
    with pytest.raises(DetectionError, match=r"camera 'left': expected a 2-D mono image"):
        tr.track({"left": np.dstack([images["left"]] * 3)})
    with pytest.raises(DetectionError, match="non-empty mapping"):
        tr.track({})
    with pytest.raises(DetectionError, match="non-empty mapping"):
        tr.track([images["left"]])  # type: ignore[arg-type]
    tr.track(frames[1].images)
    assert tr.last_timing.stages == dict.fromkeys(FIELDS, "predict")


def test_one_camera_alone_is_enough(cell):
    """Tracking: images from a subset of the rig's cameras are accepted; every field is
    still found from the one camera, within 0.1 mm for robot and opener."""
    scene, _, frames = cell
    tr = _tracker(scene, method="ba")
    out = tr.track({"left": frames[0].images["left"]})
    assert set(out) == set(FIELDS)
    for name, est in out.items():
        assert est.cameras == ("left",)
        if name != "effector":
            assert _err(est, frames[0].T_ref_field[name])[0] <= 0.1


@pytest.fixture(scope="module")
def noise_images(cell):
    scene, _, _ = cell
    rng = np.random.default_rng(12)
    return {c: rng.integers(0, 256, scene.rig[c].size[::-1], dtype=np.uint8)
            for c in scene.rig.names}


@pytest.mark.parametrize("method", METHODS)
def test_pure_noise_gives_no_pose(cell, noise_images, method):
    """Stability where methods fail: an image of pure noise gives no pose for every
    method, from a fresh tracker."""
    scene, _, _ = cell
    assert _tracker(scene, method=method).track(noise_images) == {}


def test_noise_after_tracking_gives_no_pose(cell, noise_images):
    """Stability where methods fail: a tracker locked on the cell that is then fed pure
    noise reports nothing (the predicted corners and boxes find no field), and finds the
    fields again afterwards."""
    scene, _, frames = cell
    tr = _tracker(scene)
    tr.track(frames[0].images)
    tr.track(frames[1].images)
    assert tr.track(noise_images) == {}
    out = tr.track(frames[2].images)
    assert set(out) == set(FIELDS)
    assert tr.last_timing.stages == dict.fromkeys(FIELDS, "full")


# -- dynamic ROI (eqs. 18-19) ---------------------------------------------------------------
def test_roi_boxes_contain_the_projected_corners(cell):
    """Eqs. 18-19: the box of a field in each camera, from its pose, contains every
    visible corner of the ground truth, lies inside the image, and is no larger than the
    projected corners' box grown by the motion margin."""
    scene, _, frames = cell
    tr = _tracker(scene)
    s = tr.settings
    fr = frames[0]
    for name in FIELDS:
        boxes = tr.roi_boxes(name, fr.T_ref_field[name])
        assert set(boxes) == {"left", "right"}
        for cam_name, (x0, y0, x1, y1) in boxes.items():
            cam = scene.rig[cam_name]
            assert 0 <= x0 < x1 <= cam.width and 0 <= y0 < y1 <= cam.height
            assert all(isinstance(v, int) for v in (x0, y0, x1, y1))
            uv = fr.truth[cam_name][name].corners_px
            assert np.all((uv[:, 0] >= x0) & (uv[:, 0] < x1 - 1)
                          & (uv[:, 1] >= y0) & (uv[:, 1] < y1 - 1))
            # eq. 18 over every model corner, eq. 19's box, then the margin
            allc = cam.project_from(cam.T_cam_ref @ fr.T_ref_field[name],
                                    tr.fields[name].corners)
            lo, hi = allc.min(axis=0), allc.max(axis=0)
            grow = s.roi_margin * (hi - lo) + s.roi_margin_px
            assert x0 >= np.floor(lo[0] - grow[0]) and y0 >= np.floor(lo[1] - grow[1])
            assert x1 <= np.ceil(hi[0] + grow[0]) + 1 and y1 <= np.ceil(hi[1] + grow[1]) + 1


def test_roi_boxes_clip_at_the_border_and_skip_unseen_cameras(cell):
    """Eqs. 18-19: a field partly outside an image gets a box clipped to the image; a
    field outside a camera's view (or behind it) gets no box there."""
    scene, _, _ = cell
    tr = _tracker(scene)
    T = scene.placement("robot").T_ref_field.copy()
    cam = scene.rig["left"]
    # slide the robot field left until its corners straddle the left image border
    T[0, 3] -= 0.055
    uv = cam.project_from(cam.T_cam_ref @ T, tr.fields["robot"].corners)
    assert uv[:, 0].min() < 0 < uv[:, 0].max()
    boxes = tr.roi_boxes("robot", T)
    x0, y0, x1, y1 = boxes["left"]
    assert x0 == 0 and x1 > 0 and 0 <= y0 < y1 <= cam.height
    assert tr.roi_boxes("robot", FAR) == {}
    behind = scene.placement("robot").T_ref_field.copy()
    behind[2, 3] = -0.2
    assert tr.roi_boxes("robot", behind) == {}
