"""Needle tracking by particle filter (seed 002, §III.B): the thin-feature map, the
projected-arc measurement, the motion model, resampling and the refusals."""

import math

import cv2
import numpy as np
import pytest

from oralnav.control.camera import CameraModel
from oralnav.control.errors import NeedleError
from oralnav.control.geometry import transform_from_euler
from oralnav.control.needle import Needle
from oralnav.control.needle_features import feature_distance
from oralnav.control.needle_tracker import FilterSettings, NeedleFilter

CAM = CameraModel("endoscope", (320, 240), np.array([[300.0, 0, 160], [0, 300.0, 120],
                                                     [0, 0, 1]]))
NEEDLE = Needle()
T_TRUE = transform_from_euler([0.002, -0.001, 0.1], [20, -15, 30])


def _image(T=T_TRUE, noise=0.0, seed=0):
    rng = np.random.default_rng(seed)
    img = np.full((CAM.height, CAM.width), 150.0)
    img += rng.normal(0.0, noise, img.shape) if noise else 0.0
    img = np.clip(img, 0, 255).astype(np.uint8)
    uv = CAM.project_from(T, NEEDLE.points(200))
    cv2.polylines(img, [np.round(uv * 16).astype(np.int32)], False, 60, 2, cv2.LINE_AA, 4)
    return img


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
