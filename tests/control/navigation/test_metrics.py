"""Unit tests of ``oralnav.control.navigation.metrics`` (navigation seed, section IV).

Expected values are computed by hand (or with plain numpy on 1-D data) in each test.
Each test's docstring names the requirement it checks.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from oralnav.control.errors import ControlError, GeometryError
from oralnav.control.geometry import make_transform, pose_error
from oralnav.control.navigation import metrics as m

R0 = Rotation.from_euler("xyz", [40.0, -75.0, 160.0], degrees=True)


def _poses(rotations: Rotation, translations: np.ndarray | None = None) -> np.ndarray:
    n = len(rotations)
    t = np.zeros((n, 3)) if translations is None else translations
    return np.stack([make_transform(rotations[i], t[i]) for i in range(n)])


# -- jitter (eq. 20) --------------------------------------------------------------------
def test_translation_jitter_matches_hand_values():
    """Eq. 20 translation: per-axis sample STD (n - 1) and MAD from the median, in mm."""
    x_mm = np.array([1.0, 2.0, 4.0, 10.0, 3.0])
    # mean 4, deviations -3 -2 0 6 -1: sum of squares 50, / 4 -> STD sqrt(12.5).
    # median 3, |deviations| 2 1 1 7 0 -> MAD 1.
    t = np.stack([x_mm, 2 * x_mm, np.full(5, 7.0)], axis=1) / 1000.0
    s = m.jitter_stats(_poses(Rotation.from_quat(np.tile([0, 0, 0, 1.0], (5, 1))), t))
    np.testing.assert_allclose(s.std_mm, [np.sqrt(12.5), 2 * np.sqrt(12.5), 0.0], atol=1e-12)
    np.testing.assert_allclose(s.mad_mm, [1.0, 2.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(s.std_mm, np.std(t * 1000, axis=0, ddof=1), atol=1e-12)
    assert s.n == 5 and s.std_deg == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize("side", ["body", "space"])
def test_rotation_jitter_about_one_axis_is_eq20_of_the_angle(side):
    """Eq. 20 rotation: jitter about one axis gives STD/MAD of the angle, whatever R0 is."""
    a_deg = np.array([0.1, -0.05, 0.02, 0.3, 0.0])
    # STD: numpy with n - 1. MAD: median 0.02, |dev| .08 .07 0 .28 .02 -> 0.07.
    jitter = Rotation.from_euler("z", a_deg[:, None], degrees=True)
    R = R0 * jitter if side == "body" else jitter * R0
    s = m.jitter_stats(_poses(R))
    assert s.std_deg == pytest.approx(np.std(a_deg, ddof=1), abs=1e-9)
    assert s.mad_deg == pytest.approx(0.07, abs=1e-9)


def test_rotation_jitter_counts_direction_not_only_size():
    """Eq. 20 rotation (choice documented in jitter_stats): 0.1 deg about +-x, +-y, +-z
    gives STD sqrt(6 * 0.1^2 / 5) and MAD 0.1, where the STD of the angles would be 0."""
    rotvecs = np.radians(0.1) * np.concatenate([np.eye(3), -np.eye(3)])
    s = m.jitter_stats(_poses(R0 * Rotation.from_rotvec(rotvecs)))
    assert s.std_deg == pytest.approx(np.sqrt(6 * 0.01 / 5), abs=1e-9)
    assert s.mad_deg == pytest.approx(0.1, abs=1e-9)


def test_rotation_jitter_independent_of_absolute_orientation():
    """Eq. 20 rotation: the figure does not depend on the frame the poses are reported in."""
    rng = np.random.default_rng(3)
    R = Rotation.from_rotvec(rng.normal(scale=np.radians(0.2), size=(31, 3)))
    a = m.jitter_stats(_poses(R))
    b = m.jitter_stats(_poses(R0 * R))
    c = m.jitter_stats(_poses(R * R0))
    for s in (b, c):
        assert s.std_deg == pytest.approx(a.std_deg, rel=1e-6)
        assert s.mad_deg == pytest.approx(a.mad_deg, rel=1e-6)


def test_rotation_mad_is_robust_to_an_outlier():
    """Eq. 20 MAD: one 20 deg outlier inflates the STD but barely moves the MAD."""
    rotvecs = np.radians(0.1) * np.concatenate([np.eye(3), -np.eye(3), np.eye(3)[:2]])
    rotvecs = np.concatenate([rotvecs, [np.radians([20.0, 0.0, 0.0])]])
    s = m.jitter_stats(_poses(R0 * Rotation.from_rotvec(rotvecs)))
    assert s.std_deg > 5.0
    assert s.mad_deg < 0.15


def test_jitter_stats_is_frozen_and_json_ready():
    """JitterStats: frozen, read-only arrays, as_dict survives json.dumps with units in keys."""
    t = np.array([[0.0, 0.0, 0.0], [0.001, 0.0, 0.0]])
    s = m.jitter_stats(_poses(Rotation.identity(2), t))
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.n = 3  # type: ignore[misc]
    with pytest.raises(ValueError):
        s.std_mm[0] = 1.0
    d = json.loads(json.dumps(s.as_dict()))
    assert d["n"] == 2 and set(d) == {"n", "std_mm", "mad_mm", "std_deg", "mad_deg"}
    assert d["std_mm"][0] == pytest.approx(np.sqrt(0.5))


def test_jitter_rejects_bad_input():
    """Eq. 20 inputs: n < 2, a wrong shape or a non-rigid pose raise clear errors."""
    with pytest.raises(m.MetricsError, match="at least 2"):
        m.jitter_stats(np.eye(4)[None])
    with pytest.raises(m.MetricsError, match=r"\(N, 4, 4\)"):
        m.jitter_stats(np.eye(4))
    with pytest.raises(m.MetricsError, match=r"\(N, 4, 4\)"):
        m.jitter_stats(np.zeros((0, 4, 4)))
    bad = np.stack([np.eye(4)] * 3)
    bad[2, :3, :3] *= 1.01  # scaled, not a rotation
    with pytest.raises(GeometryError, match=r"poses\[2\]"):
        m.jitter_stats(bad)


# -- TRE (eq. 21) -----------------------------------------------------------------------
def test_tre_of_known_offsets():
    """Eq. 21: a constant 0.3/0.4/0 offset gives 0.5; error norms 1, 2, 2 give sqrt(3)."""
    rng = np.random.default_rng(0)
    p = rng.uniform(-50, 50, (7, 3))
    assert m.tre(p, p + [0.3, 0.4, 0.0]) == pytest.approx(0.5, abs=1e-12)
    q = np.zeros((3, 3))
    assert m.tre(q, [[1.0, 0, 0], [0, 2.0, 0], [0, 0, -2.0]]) == pytest.approx(np.sqrt(3.0))
    assert m.tre(p, p) == 0.0


def test_tre_rejects_bad_input():
    """Eq. 21 inputs: mismatched or wrong shapes, no points and NaN raise MetricsError."""
    with pytest.raises(m.MetricsError, match="pair up"):
        m.tre(np.zeros((3, 3)), np.zeros((4, 3)))
    with pytest.raises(m.MetricsError, match=r"\(N, 3\)"):
        m.tre(np.zeros((3, 2)), np.zeros((3, 2)))
    with pytest.raises(m.MetricsError, match="at least one"):
        m.tre(np.zeros((0, 3)), np.zeros((0, 3)))
    with pytest.raises(m.MetricsError, match="p_measured.*non-finite"):
        m.tre(np.zeros((1, 3)), [[0.0, np.nan, 0.0]])


# -- AAE (section IV.D) -----------------------------------------------------------------
def test_absolute_angular_error_wraps_around():
    """IV.D AAE: |measured - truth| in degrees, wrapped so it never exceeds 180."""
    measured = [10.0, 179.0, -170.0, 190.0, 0.0, -30.5, 725.0]
    truth = [10.0, -179.0, 170.0, -170.0, 180.0, -30.0, 0.0]
    np.testing.assert_allclose(m.absolute_angular_error(measured, truth),
                               [0.0, 2.0, 20.0, 0.0, 180.0, 0.5, 5.0], atol=1e-12)


def test_absolute_angular_error_broadcasts_and_rejects_bad_input():
    """IV.D AAE: N frames against one gadget angle broadcast; mismatches and NaN raise."""
    np.testing.assert_allclose(m.absolute_angular_error([9.0, 11.5, 10.0], 10.0),
                               [1.0, 1.5, 0.0])
    with pytest.raises(m.MetricsError, match="broadcast"):
        m.absolute_angular_error([1.0, 2.0], [1.0, 2.0, 3.0])
    with pytest.raises(m.MetricsError, match="measured_deg"):
        m.absolute_angular_error([np.inf], 0.0)


# -- pose errors and summaries (benchmarks, IV.C) -------------------------------------------
def test_pose_errors_match_geometry_pose_error():
    """IV.C pose errors: (N,) mm and degrees, equal to geometry.pose_error per pose."""
    rng = np.random.default_rng(4)
    T_true = _poses(Rotation.random(6, random_state=rng), rng.uniform(-0.5, 0.5, (6, 3)))
    d = _poses(Rotation.from_rotvec(rng.normal(scale=0.05, size=(6, 3))),
               rng.normal(scale=0.002, size=(6, 3)))
    T_est = T_true @ d
    trans_mm, rot_deg = m.pose_errors(T_est, T_true)
    assert trans_mm.shape == rot_deg.shape == (6,)
    for i in range(6):
        dt, dr = pose_error(T_est[i], T_true[i])
        assert trans_mm[i] == pytest.approx(dt * 1000.0, abs=1e-9)
        assert rot_deg[i] == pytest.approx(np.degrees(dr), abs=1e-9)
    # A known error: 1 mm along x and 2 deg about z.
    one = make_transform(Rotation.from_euler("z", 2.0, degrees=True), [0.001, 0.0, 0.0])
    t, r = m.pose_errors(one[None], np.eye(4)[None])
    assert t[0] == pytest.approx(1.0) and r[0] == pytest.approx(2.0)


def test_pose_errors_reject_mismatched_stacks():
    """IV.C pose errors: stacks must pair up; non-rigid poses raise GeometryError."""
    with pytest.raises(m.MetricsError, match="pair up"):
        m.pose_errors(np.stack([np.eye(4)] * 2), np.stack([np.eye(4)] * 3))
    with pytest.raises(GeometryError, match=r"T_true\[0\]"):
        m.pose_errors(np.eye(4)[None], np.zeros((1, 4, 4)))


def test_error_summary_hand_values():
    """Benchmark summary: median, mean, p95 (linear) and max of each error series."""
    s = m.error_summary([1.0, 2.0, 3.0, 4.0, 100.0], [0.5, 0.1, 0.2, 0.3, 0.4])
    # p95 sits at index 0.95 * 4 = 3.8: 4 + 0.8 * (100 - 4) = 80.8.
    assert s["n"] == 5
    assert s["translation_mm"] == pytest.approx(
        {"median": 3.0, "mean": 22.0, "p95": 80.8, "max": 100.0})
    assert s["rotation_deg"] == pytest.approx(
        {"median": 0.3, "mean": 0.3, "p95": 0.48, "max": 0.5})
    json.dumps(s)
    with pytest.raises(m.MetricsError, match="equally long"):
        m.error_summary([1.0], [1.0, 2.0])
    with pytest.raises(ControlError):
        m.error_summary([], [])
