"""Needle tracking by particle filter (seed 002, §III.B): the thin-feature map, the
projected-arc measurement, the motion model, resampling and the refusals; the tissue
plane that hides the part of a driven needle under the surface."""

import copy
import math
from dataclasses import replace
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from oralnav.config.rig import trial_rig
from oralnav.control.errors import NeedleError
from oralnav.control.geometry import invert, transform_from_euler
from oralnav.control.needle.features import feature_distance, feature_maps
from oralnav.control.needle.model import Needle
from oralnav.control.needle.tracker import (
    FilterSettings,
    NeedleFilter,
    NeedleTracker,
    TissuePlane,
    TrackSettings,
    contested,
)
from oralnav.control.vision.camera import CameraModel
from oralnav.sim.world.needle_cell import NeedleCell
from oralnav.sim.world.needle_trials import trial_scene
from tests.helpers import draw_visible_runs

CAM = CameraModel("endoscope", (320, 240), np.array([[300.0, 0, 160], [0, 300.0, 120],
                                                     [0, 0, 1]]))
NEEDLE = Needle()
T_TRUE = transform_from_euler([0.002, -0.001, 0.1], [20, -15, 30])


def _image(T=T_TRUE, noise=0.0, seed=0, plane=None):
    """The needle drawn on a grey image; with ``plane``, only its runs above the plane."""
    rng = np.random.default_rng(seed)
    img = np.full((CAM.height, CAM.width), 150.0)
    img += rng.normal(0.0, noise, img.shape) if noise else 0.0
    img = np.clip(img, 0, 255).astype(np.uint8)
    pts = NEEDLE.points(200)
    uv = CAM.project_from(T, pts)
    keep = np.ones(len(pts), bool) if plane is None else \
        plane.height(pts @ T[:3, :3].T + T[:3, 3]) >= 0
    draw_visible_runs(img, uv, keep, 60, 2)
    return img


def _plane_in_N(T, point_N, normal_N):
    """A tissue plane given in the needle's frame N of pose ``T``."""
    return TissuePlane(T[:3, :3] @ point_N + T[:3, 3], T[:3, :3] @ normal_N)


def _filter(**kw):
    return NeedleFilter(NEEDLE, [CAM], FilterSettings(particles=200, **kw))


def test_feature_map_finds_the_wire_not_the_noise():
    """Thin features: the drawn wire is on the map (distance 0 on its projected points),
    sensor noise is not (few feature pixels away from the wire), and an ignore mask
    removes what it covers."""
    img = _image(noise=4.0)
    dm = feature_distance(img, 3.0)
    uv = CAM.project_from(T_TRUE, NEEDLE.points(40))
    on = dm[np.round(uv[:, 1]).astype(int), np.round(uv[:, 0]).astype(int)]
    assert np.median(on) < 1.0
    assert (dm < 0.5).mean() < 0.05
    everything = np.ones(img.shape, bool)
    assert np.all(feature_distance(img, 3.0, ignore=everything) > 100)


def test_true_pose_scores_best():
    """The measurement: the true pose matches fully; a pose shifted 2 mm sideways, a
    farther needle lying along part of the wire, and one tilted 15 deg about the arc's
    bisector all score lower. The tilt is the weak direction of a single view (its ends
    only foreshorten, by cos 15 deg): a margin of 0.05, not more."""
    dm = feature_distance(_image(), 2.0)
    flt = _filter()
    shifted = T_TRUE.copy()
    shifted[0, 3] += 0.002
    farther = T_TRUE.copy()
    farther[:3, 3] *= 1.3
    turned = T_TRUE @ transform_from_euler([0, 0, 0], [0, 15, 0])   # out of its plane
    poses = np.stack([T_TRUE, shifted, farther, turned])
    m = flt.scores([dm], poses[:, :3, :3], poses[:, :3, 3])[:, 0]
    assert m[0] == pytest.approx(1.0, abs=0.05)
    assert np.all(m[1:] < m[0] - 0.05)


def test_base_tip_twin_is_indistinguishable():
    """Symmetry: the half turn about the arc's bisector maps the arc onto itself, so the
    twin scores the same; the estimate reports both."""
    dm = feature_distance(_image(), 2.0)
    flt = _filter()
    twin = T_TRUE.copy()
    twin[:3, :3] = T_TRUE[:3, :3] @ flt.flip
    poses = np.stack([T_TRUE, twin])
    m = flt.scores([dm], poses[:, :3, :3], poses[:, :3, 3])[:, 0]
    assert m[0] == pytest.approx(m[1], abs=1e-9)
    assert np.allclose(NEEDLE.points(9) @ flt.flip.T, NEEDLE.points(9)[::-1], atol=1e-12)


def test_grasped_motion_moves_every_particle_with_the_gripper():
    """Motion model, grasped: with the noise off, each particle is the gripper's
    incremental motion applied to its pose."""
    flt = _filter(grasped_position_noise=0.0, grasped_rotation_noise=0.0, anneal_steps=0)
    flt.initialize([feature_distance(_image(), 2.0)], (0.08, 0.12))
    before_R, before_t = flt.R.copy(), flt.t.copy()
    D = transform_from_euler([0.001, 0.002, -0.003], [5, 0, -3])
    flt.predict(delta=D)
    assert np.allclose(flt.R, np.einsum("ij,pjk->pik", D[:3, :3], before_R))
    assert np.allclose(flt.t, before_t @ D[:3, :3].T + D[:3, 3])


def test_free_motion_is_brownian_about_the_wire():
    """Motion model, free: rotations turn about the arc's middle, so that point moves
    only by the position noise."""
    flt = _filter(rotation_noise=0.3, position_noise=0.0, anneal_steps=0)
    flt.initialize([feature_distance(_image(), 2.0)], (0.08, 0.12))
    mid = NEEDLE.point(NEEDLE.arc / 2)
    before = np.einsum("pij,j->pi", flt.R, mid) + flt.t
    flt.predict()
    after = np.einsum("pij,j->pi", flt.R, mid) + flt.t
    assert np.allclose(before, after, atol=1e-12)
    assert np.all(np.abs(np.linalg.det(flt.R) - 1) < 1e-9)


def test_low_variance_resampling_keeps_weighted_shares():
    """Resampling (seed ref. [24]): a particle of weight w appears about w P times."""
    flt = _filter()
    flt.R = np.repeat(np.eye(3)[None], 200, axis=0)
    flt.t = np.zeros((200, 3))
    flt.t[:, 0] = np.arange(200)
    w = np.zeros(200)
    w[[3, 7, 11]] = [0.5, 0.3, 0.2]
    flt._resample(w)
    ids, counts = np.unique(flt.t[:, 0].astype(int), return_counts=True)
    assert ids.tolist() == [3, 7, 11] and counts.tolist() == [100, 60, 40]


@pytest.mark.parametrize("seed", range(4))
def test_filter_finds_the_needle_outline(seed):
    """Global initialisation and a few updates find the needle on a clean image: the
    estimate's arc (or its base/tip twin) reprojects within 6 px of the true one, on
    every seed tried. A single view determines the outline, not the depth: the 3-D
    error of the arc's middle spreads over 4-13 mm across seeds here, which is why the
    accuracy target needs stereo or refinement (docs/needle.md); no 3-D bound is
    asserted."""
    dm = feature_distance(_image(), 2.0)
    flt = NeedleFilter(NEEDLE, [CAM], FilterSettings(particles=2000, seed=seed))
    est = flt.initialize([dm], (0.08, 0.12))
    for _ in range(5):
        flt.predict(scale=0.5)
        est = flt.update([dm])
    pts = NEEDLE.points(9)
    true = CAM.project_from(T_TRUE, pts)
    off = min(np.abs(CAM.project_from(T, pts) - true).max() for T in (est.pose, est.pose_alt))
    assert off < 6.0
    assert est.score > 0.8


def test_refusals():
    """Bad input: too few particles, no camera, a map of the wrong size, an image that
    is not mono8, an uninitialised filter, a blank first image."""
    with pytest.raises(NeedleError, match="particles"):
        FilterSettings(particles=2)
    with pytest.raises(NeedleError, match="at least one camera"):
        NeedleFilter(NEEDLE, [])
    flt = _filter()
    with pytest.raises(NeedleError, match="not initialised"):
        flt.predict()
    with pytest.raises(NeedleError, match="mono8"):
        feature_distance(np.zeros((10, 10), np.float32), 2.0)
    with pytest.raises(NeedleError, match="feature map is"):
        flt.scores([np.zeros((10, 10), np.float32)])
    blank = feature_distance(np.full((CAM.height, CAM.width), 150, np.uint8), 2.0)
    with pytest.raises(NeedleError, match="no thin feature"):
        flt.initialize([blank], (0.08, 0.12))
    with pytest.raises(NeedleError, match="depth range"):
        flt.initialize([blank], (0.12, 0.08))
    assert math.isfinite(flt.s.gain)


# -- the tissue plane ----------------------------------------------------------------------

R_WIRE = 0.5 * NEEDLE.wire_diameter
# the middle of the arc in the tissue: points with y_N above 0.6 r are under the surface
MIDDLE_IN = _plane_in_N(T_TRUE, np.array([0.0, 0.6 * NEEDLE.radius, 0.0]),
                        np.array([0.0, -1.0, 0.0]))


def _reference_lengths(T, plane):
    """(visible, in image) projected lengths (px) of the filter's arc by a plain
    computation: chords with both ends in the image, and of those the ones with both
    ends a wire radius or more above ``plane``."""
    pts = NEEDLE.points(FilterSettings().arc_points)
    uv = CAM.project_from(T, pts)
    inside = CAM.in_image(uv) & np.all(np.isfinite(uv), axis=1)
    vis = inside & (plane.height(pts @ T[:3, :3].T + T[:3, 3]) >= R_WIRE)
    ln = np.linalg.norm(np.diff(uv, axis=0), axis=1)
    return float(ln[vis[1:] & vis[:-1]].sum()), float(ln[inside[1:] & inside[:-1]].sum())


def test_hidden_chords_are_neither_support_nor_missing_wire():
    """Occluder semantics in the score: with the middle of the arc under the plane (and
    not drawn), a chord counts in the supported and the projected length only when both
    its ends are visible (the projected length equals a plain computation of it); the
    true pose then matches as a fully supported arc (supported / projected near 1)
    where, without the plane, the hidden half counts as missing wire. Removing the plane
    gives the plane-free scores back exactly."""
    dm = feature_distance(_image(plane=MIDDLE_IN), 2.0)
    flt = _filter()
    R, t = T_TRUE[None, :3, :3].copy(), T_TRUE[None, :3, 3].copy()
    bare = flt._raw(flt._stack([dm]), R, t)[0, 0]
    flt.set_occluder(MIDDLE_IN)
    sup, tot = flt._raw(flt._stack([dm]), R, t)[0, 0]
    visible, full = _reference_lengths(T_TRUE, MIDDLE_IN)
    assert 0.3 * full < visible < 0.7 * full            # about half the arc is hidden
    assert tot == pytest.approx(visible, rel=1e-9)
    assert bare[1] == pytest.approx(full, rel=1e-9)
    assert sup / tot > 0.95
    assert bare[0] / bare[1] < 0.75                     # the plane-free score misses it
    flt.set_occluder(None)
    assert np.array_equal(flt._raw(flt._stack([dm]), R, t)[0, 0], bare)


def test_a_sliver_of_visible_arc_scores_zero():
    """Occluder semantics, the floor: a pose showing only a tenth of its arc (less than
    ``min_visible``), even lying on the wire, and a pose entirely under the plane score
    exactly 0 (not NaN, not a high share from a few points), and an update over such
    particles stays finite."""
    # only phi >= 0.9 pi (near the tip) stands out of the tissue
    sliver = _plane_in_N(T_TRUE, np.array([-NEEDLE.radius * math.cos(0.1 * math.pi), 0, 0]),
                         np.array([-1.0, 0.0, 0.0]))
    dm = feature_distance(_image(), 2.0)
    flt = NeedleFilter(NEEDLE, [CAM], FilterSettings(particles=200), occluder=sliver)
    visible, full = _reference_lengths(T_TRUE, sliver)
    assert 0 < visible < flt.s.min_visible * full
    sunk = T_TRUE.copy()
    sunk[:3, 3] += 0.05 * T_TRUE[:3, 0]                 # the whole needle under it
    poses = np.stack([T_TRUE, sunk])
    raw = flt._raw(flt._stack([dm]), poses[:, :3, :3].copy(), poses[:, :3, 3].copy())
    assert np.array_equal(raw, np.zeros_like(raw))
    m = flt.scores([dm], poses[:, :3, :3], poses[:, :3, 3])
    assert np.array_equal(m, np.zeros_like(m))
    flt.R = np.repeat(poses[:, :3, :3], 100, axis=0)
    flt.t = np.repeat(poses[:, :3, 3], 100, axis=0)
    flt.w = np.full(200, 1.0 / 200)
    est = flt.update([dm])
    assert est.score == 0.0 and est.match == 0.0 and not est.converged
    assert np.all(np.isfinite(est.pose)) and np.all(np.isfinite(flt.w))


def test_bad_tissue_planes_are_refused():
    """Bad input: a zero or non-finite normal, a point that is not a 3-vector, a plane
    that a camera is under (a normal pointing into the tissue), and something that is
    not a TissuePlane are refused with a NeedleError; a good normal is normalised."""
    with pytest.raises(NeedleError, match="non-zero"):
        TissuePlane(np.zeros(3), np.zeros(3))
    with pytest.raises(NeedleError, match="finite"):
        TissuePlane([0.0, 0.0, math.nan], [0.0, 0.0, 1.0])
    with pytest.raises(NeedleError, match="3-vectors"):
        TissuePlane([0.0, 0.0], [0.0, 0.0, 1.0])
    plane = TissuePlane([0.0, 0.0, 0.1], [0.0, 0.0, -3.0])
    assert np.allclose(plane.normal, [0.0, 0.0, -1.0])
    with pytest.raises(ValueError):
        plane.normal[0] = 1.0                           # frozen, arrays read-only
    flt = _filter()
    with pytest.raises(NeedleError, match="under it"):
        flt.set_occluder(TissuePlane([0.0, 0.0, 0.1], [0.0, 0.0, 1.0]))
    assert flt.occluder is None
    with pytest.raises(NeedleError, match="TissuePlane"):
        flt.set_occluder((np.zeros(3), np.array([0.0, 0.0, -1.0])))
    with pytest.raises(NeedleError, match="min_visible"):
        FilterSettings(min_visible=1.0)


# -- a needle driven into the tissue pad (the simulator) -----------------------------------

DRIVEN_SEED = 2


def _driven_pose(scene, depth=0.0045, tilt_deg=30.0, turn_deg=45.0):
    """``T_ref_N`` of a needle driven through the pad: its base and tip out, the middle
    of its arc ``depth`` (m) under the surface (about 60 % of the arc hidden). The chord
    lies in the surface 12 mm to the pad's -y of its centre (away from the incision),
    turned ``turn_deg`` about the normal from across the line of sight; the needle's
    plane leans ``tilt_deg`` from the normal toward the camera, so the endoscope sees
    the arc rather than its edge."""
    tilt, turn = math.radians(tilt_deg), math.radians(turn_deg)
    T_pad = scene.pads[0].T_ref_pad
    n = T_pad[:3, 2]
    foot = T_pad[:3, :3] @ np.array([0.0, -0.012, 0.0]) + T_pad[:3, 3]
    eye = scene.rig[scene.rig.reference].T_ref_cam[:3, 3] - foot
    w = eye - (eye @ n) * n                             # toward the camera, in the surface
    w = Rotation.from_rotvec(turn * n).apply(w / np.linalg.norm(w))
    x = np.cross(w, n)
    y = -math.cos(tilt) * n + math.sin(tilt) * w        # toward the arc's middle
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, y, np.cross(x, y)])
    r = scene.needles[0].needle.radius
    T[:3, 3] = foot + (r * math.cos(tilt) - depth) * n - r * math.sin(tilt) * w
    return T


@pytest.fixture(scope="module")
def driven():
    """A trial cell's needle standing on the pad, tracked over two frames; then pushed
    6 mm along the surface normal into the pad (three frames rendered)."""
    scene, reach, info = trial_scene(DRIVEN_SEED, rig=trial_rig())
    T_in = _driven_pose(scene)
    n = scene.pads[0].T_ref_pad[:3, 2]
    push = np.eye(4)
    push[:3, 3] = -0.006 * n
    cams = [scene.rig[c] for c in scene.rig.names]

    def feats(cell):
        imgs = cell.images()
        out = []
        for cam in cams:
            uv = cam.project_from(cam.T_cam_ref, np.asarray(info.incision))
            mask = np.zeros((cam.height, cam.width), np.uint8)
            cv2.line(mask, tuple(np.round(uv[0]).astype(int)),
                     tuple(np.round(uv[1]).astype(int)), 1, 16)
            wire_px = cam.K[0, 0] * cell.needle.wire_diameter / 0.1
            out.append(feature_maps(imgs[cam.name], wire_px, ignore=mask.astype(bool)))
        return out

    above, inside = (NeedleCell(replace(scene, needles=(replace(scene.needles[0],
                                                                T_ref_needle=T),)), reach)
                     for T in (invert(push) @ T_in, T_in))
    tracker = NeedleTracker(above.needle, cams, FilterSettings(seed=DRIVEN_SEED))
    tracker.initialize(feats(above), (0.06, 0.16))
    tracker.predict()
    tracker.update(feats(above))
    T_pad = scene.pads[0].T_ref_pad
    return SimpleNamespace(tracker=tracker, push=push, frames=[feats(inside) for _ in range(3)],
                           truth=inside.truth(), plane=TissuePlane(T_pad[:3, 3], T_pad[:3, 2]))


def _follow(driven, plane):
    """The tracker follows the push, told the gripper's motion with a 0.6 mm / 2.5 deg
    error (about the needle), with or without the tissue plane; the last track."""
    tr = copy.deepcopy(driven.tracker)
    tr.set_occluder(plane)
    T = driven.truth.T_ref_needle
    error = T @ transform_from_euler([0.0004, -0.0003, 0.0003], [1.5, -1.5, 1.2]) @ invert(T)
    tr.predict(error @ driven.push)
    for f in driven.frames:
        track = tr.update(f)
        tr.predict()
    return track


def _pose_error(T, Tt):
    R = T[:3, :3].T @ Tt[:3, :3]
    return (float(np.linalg.norm(T[:3, 3] - Tt[:3, 3])),
            math.degrees(math.acos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def test_tracker_with_the_tissue_plane_follows_a_driven_needle(driven):
    """Task: a needle in tissue. With its middle ~60 % under the pad's surface, the
    tracker given the surface follows it to within 0.3 mm and 2 deg of the truth (base
    and tip told apart by the thread: no twin), with the whole visible arc found, and
    says it has converged. Measured: 0.06 mm, 1.6 deg, the angle a slide along the arc
    (the single tip end's outward blur bias: the swage end is continued by the thread)."""
    T = driven.truth.T_ref_needle
    pts = driven.tracker.needle.points(400) @ T[:3, :3].T + T[:3, 3]
    hidden = float(np.mean(driven.plane.height(pts) < 0))
    assert driven.truth.in_tissue and 0.5 < hidden < 0.7
    track = _follow(driven, driven.plane)
    dp, da = _pose_error(track.pose, driven.truth.T_ref_needle)
    assert dp < 0.3e-3 and da < 2.0, (dp, da)
    assert track.converged, track.reason
    assert track.refined.support > 0.9 and track.swage > 10.0


def test_tracker_without_the_plane_loses_a_driven_needle(driven):
    """Why the plane: on the same frames, the plane-free tracker counts the hidden arc
    as missing wire: the refinement finds about half the arc (below the 60 % it needs),
    the track is not converged, and the pose drifts millimetres away."""
    track = _follow(driven, None)
    dp, _ = _pose_error(track.pose, driven.truth.T_ref_needle)
    assert not track.converged
    assert not track.refined.ok and track.refined.support < 0.6
    assert dp > 2e-3, dp


def test_the_slide_drifts_only_with_a_motion(driven):
    """The motion prior (``TrackSettings.slide_drift``): the wire slips along its own arc
    only when something moves it (a gripper's motion, or the jaws closing: an untrusted
    look). A trusted look with nothing moved carries the slide's uncertainty unchanged;
    at the hand-off, where the jaws hide an end, one drift per look had grown it past
    what a step may move on while the pose stayed 0.3 deg from the truth. The tilt and
    position drift stay (the arm's and the model's error), an untrusted or a moving
    look widens the slide by one drift."""
    tr = copy.deepcopy(driven.tracker)
    assert tr._belief is not None
    slide, tilt = (lambda c: (c[2, 2], c[0, 0]))(tr._belief[1])
    drift = tr.s.slide_drift ** 2
    tr.predict(np.eye(4))
    c = tr._belief[1]
    assert c[2, 2] == pytest.approx(slide) and c[0, 0] == pytest.approx(tilt + tr.s.tilt_drift ** 2)
    tr.predict(np.eye(4), trusted=False)
    assert tr._belief[1][2, 2] == pytest.approx(slide + drift)
    tr.predict(driven.push)
    assert tr._belief[1][2, 2] == pytest.approx(slide + 2 * drift)


def test_an_inexact_arm_widens_the_position_by_the_motion_s_size(driven):
    """Issue 36 (the prior of a motion an arm with kinematic errors makes): with
    ``turn_drift`` and ``travel_drift`` the position's variance grows by the squares of
    ``turn_drift`` times the motion's turn (rad) and ``travel_drift`` times how far it
    takes the needle's centre (m), on top of ``position_drift``; a still look adds only
    ``position_drift``, and the defaults (exact kinematics) add only that whatever the
    motion."""
    tr = copy.deepcopy(driven.tracker)
    tr.s = replace(tr.s, turn_drift=0.002, travel_drift=0.01)
    T_b, cov = tr._belief
    turn = transform_from_euler([0.0, 0.0, 0.0], [0.0, 0.0, 30.0])
    motion = T_b @ turn @ invert(T_b) @ transform_from_euler([0.004, 0.0, 0.0], [0, 0, 0])
    tr.predict(motion)
    travel = float(np.linalg.norm(tr._belief[0][:3, 3] - T_b[:3, 3]))
    assert travel == pytest.approx(0.004)
    added = np.diag(tr._belief[1] - cov)[3:]
    want = tr.s.position_drift ** 2 + (0.002 * math.radians(30)) ** 2 + (0.01 * 0.004) ** 2
    np.testing.assert_allclose(added, want, rtol=1e-9)
    T_b, cov = tr._belief
    tr.predict(np.eye(4))
    np.testing.assert_allclose(np.diag(tr._belief[1] - cov)[3:], tr.s.position_drift ** 2)
    exact = copy.deepcopy(driven.tracker)
    T_b, cov = exact._belief
    exact.predict(motion)
    np.testing.assert_allclose(np.diag(exact._belief[1] - cov)[3:],
                               exact.s.position_drift ** 2)
    with pytest.raises(NeedleError, match="turn_drift"):
        TrackSettings(turn_drift=-1.0)


def _drifting(driven):
    """A copy of the driven tracker with arm-accuracy drifts (2 mm a radian, 1 %), the
    motion turning it 20 deg about its belief's centre, and the belief's covariance."""
    tr = copy.deepcopy(driven.tracker)
    tr.s = replace(tr.s, turn_drift=0.002, travel_drift=0.01)
    T_b, cov = tr._belief
    c = T_b[:3, 3]
    step = (transform_from_euler(c, [0.0, 0.0, 0.0])
            @ transform_from_euler([0.0, 0.0, 0.0], [0.0, 0.0, 20.0])
            @ transform_from_euler(-c, [0.0, 0.0, 0.0]))
    return tr, step, cov


def test_a_servo_s_motions_drift_by_their_share_of_a_half_turn(driven):
    """Issue 36 (the servoed drive's looks): a motion a servo's model predicts
    (``kinematic=False``) widens the slide and the tilt by its share of a half turn, so
    a turn looked at in nine steps adds what one open-loop motion adds (a drift per look
    took the slide's sigma to 3.5 deg by the regrasp); the arm's accuracy drifts do not
    apply to it."""
    tr, step, cov = _drifting(driven)
    for _ in range(9):
        tr.predict(step, kinematic=False)
    added = np.diag(tr._belief[1] - cov)
    assert added[2] == pytest.approx(tr.s.slide_drift ** 2, rel=1e-9)
    np.testing.assert_allclose(added[:2], tr.s.tilt_drift ** 2, rtol=1e-9)
    np.testing.assert_allclose(added[3:], 9 * tr.s.position_drift ** 2, rtol=1e-9)
    one = copy.deepcopy(driven.tracker)
    T_b, cov = one._belief
    one.predict(step)
    assert np.diag(one._belief[1] - cov)[2] == pytest.approx(one.s.slide_drift ** 2)


def test_a_tracking_task_s_frames_drift_by_their_share_and_by_the_arm_s_accuracy(driven):
    """Issue 36 (the streamed drive): an arm's reported motion split into frames
    (``split=True``) widens the slide and tilt by its share of a half turn, as a servo's
    predicted motion does, and the position by the arms' accuracy drifts as any reported
    motion does (a full slide drift a frame took the slide's sigma to 3.3 deg at the
    regrasp of development trials 100 and 101)."""
    tr, step, cov = _drifting(driven)
    for _ in range(9):
        tr.predict(step, split=True)
    added = np.diag(tr._belief[1] - cov)
    assert added[2] == pytest.approx(tr.s.slide_drift ** 2, rel=1e-9)
    np.testing.assert_allclose(added[:2], tr.s.tilt_drift ** 2, rtol=1e-9)
    turn = math.radians(20.0)
    position = tr.s.position_drift ** 2 + (tr.s.turn_drift * turn) ** 2
    assert np.all(added[3:] > 9 * position * 0.999), (added[3:], 9 * position)


def test_a_fixed_side_skips_the_twin_contest_only_once_decided(driven, monkeypatch):
    """Issue 36 (the streamed drive's rate): where the views show no thread (the jaws
    hide it: evidence 0 here), an update contests the decided side by refitting the
    twin; with the sides fixed (a needle in closed jaws) it does not (one refit less, 146
    ms against 34 ms an update on development trial 101), and keeps its side. A track
    not yet decided is contested even when fixed."""
    import oralnav.control.needle.tracker as tracker_module

    monkeypatch.setattr(tracker_module, "swage_evidence", lambda *a, **k: 0.0)

    def fits(fixed: bool, sided: bool) -> tuple[int, object]:
        tr = copy.deepcopy(driven.tracker)
        assert tr._sided
        tr._sided = sided
        tr.fix_side(fixed)
        tr.set_occluder(driven.plane)
        calls = []
        best = tr._best_fit

        def counted(features, starts, **k):
            calls.append(len(starts))
            return best(features, starts, **k)
        tr._best_fit = counted
        tr.predict(driven.push)
        track = tr.update(driven.frames[0])
        return len(calls), track

    n_fixed, track = fits(True, True)
    n_free, _ = fits(False, True)
    n_undecided, _ = fits(True, False)
    assert n_free == n_fixed + 1 and n_undecided == n_free, (n_fixed, n_free, n_undecided)
    _, da = _pose_error(track.pose, driven.truth.T_ref_needle)
    assert da < 5.0, da


def test_jaws_that_close_and_hide_the_wire_leave_the_belief_standing(driven):
    """The motion prior after an update that fits nothing: where the jaws just closed
    (an untrusted look, nothing moved) and hide the wire, what was known stands, its
    slide widened by one drift, for the next look to hold the slide by (trial 15's pull,
    whose tip the jaws hid). After a motion a check tests (did the needle follow?), it
    is dropped: nothing confirmed where the needle went. Blank frames stand for the
    hidden wire."""
    blank = [feature_maps(np.full((c.height, c.width), 150, np.uint8), 5.0)
             for c in driven.tracker.cameras]
    tr = copy.deepcopy(driven.tracker)
    assert tr._belief is not None
    T_b, cov = tr._belief
    tr.predict(np.eye(4), trusted=False)
    track = tr.update(blank)
    assert not track.converged and not track.refined.ok
    assert tr._belief is not None and np.allclose(tr._belief[0], T_b)
    assert tr._belief[1][2, 2] == pytest.approx(cov[2, 2] + tr.s.slide_drift ** 2)
    tr = copy.deepcopy(driven.tracker)
    tr.predict(driven.push, trusted=False)
    track = tr.update(blank)
    assert not track.refined.ok and tr._belief is None


def test_twins_that_both_read_the_thread_alike_are_contested():
    """Base/tip decision (TrackSettings.swage_contest): two twins' thread evidence
    contests the decision only when both read the thread past their own base (at least
    swage_min) within swage_contest times each other (trial 20: +8.7 and +9.3 DN); a
    reading under swage_min, or one clearly stronger (trial 17: +28 against +10),
    decides; the ratio must be at least 1."""
    s = TrackSettings()
    assert contested(8.7, 9.3, s) and contested(9.3, 8.7, s)
    assert not contested(28.0, 10.0, s)
    assert not contested(9.0, 2.5, s) and not contested(-9.0, 9.0, s)
    assert not contested(8.7, 9.3, replace(s, swage_contest=1.05))
    with pytest.raises(NeedleError, match="swage_contest"):
        TrackSettings(swage_contest=0.9)


def test_ignored_pixels_join_the_edge_band_as_blind():
    """Incision mask (NeedleTracker.set_ignored): the pixels the features ignore are
    blind to the refinement, as the surface's edge band is: ``blind`` is their union per
    camera, either alone when the other is unset, and ``None`` with neither. A mask of
    the wrong size or type, or the wrong number of them, is refused naming the camera
    or the count."""
    tr = NeedleTracker(NEEDLE, [CAM], FilterSettings(particles=200))
    assert tr.blind is None
    mask = np.zeros((CAM.height, CAM.width), bool)
    mask[100:110, :] = True
    tr.set_ignored([mask])
    assert tr.blind is not None and np.array_equal(tr.blind[0], mask)
    outline = np.array([[-0.03, -0.03, 0.1], [0.03, -0.03, 0.1], [0.03, 0.03, 0.1],
                        [-0.03, 0.03, 0.1]])
    tr.set_surface_outline(outline)
    band = tr.refiner.edge_bands(outline)[0]
    assert band.any() and not np.array_equal(band, mask)
    assert np.array_equal(tr.blind[0], band | mask)
    tr.set_ignored(None)
    assert np.array_equal(tr.blind[0], band)
    tr.set_ignored([None])
    assert np.array_equal(tr.blind[0], band)
    tr.set_surface_outline(None)
    tr.set_ignored(None)
    assert tr.blind is None
    with pytest.raises(NeedleError, match="expected 1 ignore masks"):
        tr.set_ignored([mask, mask])
    with pytest.raises(NeedleError, match="'endoscope'.*bool"):
        tr.set_ignored([mask[:10]])
    with pytest.raises(NeedleError, match="'endoscope'.*bool"):
        tr.set_ignored([mask.astype(np.uint8)])
