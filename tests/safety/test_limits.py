"""Tests of ``oralnav.safety.limits``: the speed limiter and the workspace box, and the
``[safety]`` settings they are built from.

Each test's docstring names the requirement it checks (Issue 4: safety).
"""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError
from scipy.spatial.transform import Rotation, Slerp

from oralnav.config.daemon import ISO_REDUCED_SPEED, SafetySection
from oralnav.safety.errors import InputError, LimitError
from oralnav.safety.limits import ISO_10218_REDUCED_SPEED, SpeedLimiter, WorkspaceBox

DT = 0.002  # s, one 500 Hz period
EPS = 1e-12  # rounding slack on a step (m or rad)


def pose(p, rotvec=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = p
    return T


def step_sizes(A: np.ndarray, B: np.ndarray) -> tuple[float, float]:
    """Translation (m) and rotation angle (rad) from pose A to pose B."""
    dp = float(np.linalg.norm(B[:3, 3] - A[:3, 3]))
    dR = Rotation.from_matrix(B[:3, :3]) * Rotation.from_matrix(A[:3, :3]).inv()
    return dp, float(dR.magnitude())


def random_pose(rng: np.random.Generator) -> np.ndarray:
    return pose(rng.uniform(-0.5, 0.5, 3), Rotation.random(random_state=rng).as_rotvec())


# -- speed limiter -------------------------------------------------------------------------
def test_iso_constants_agree():
    """Issue 4 safety (ISO 10218): the safety layer's reduced speed is the configuration's."""
    assert ISO_10218_REDUCED_SPEED == ISO_REDUCED_SPEED == 0.25


@pytest.mark.parametrize("kw", [dict(max_speed=0.26), dict(near_patient_speed=0.3)])
def test_speed_above_iso_is_refused_at_construction(kw):
    """Issue 4 safety (ISO 10218): a linear speed limit above the reduced speed 0.25 m/s
    raises LimitError when the limiter is built."""
    args = dict(max_speed=0.25, max_angular_speed=1.0) | kw
    near = args.pop("near_patient_speed", None)
    with pytest.raises(LimitError, match="ISO 10218 reduced speed"):
        SpeedLimiter(args["max_speed"], args["max_angular_speed"], near_patient_speed=near)
    SpeedLimiter(0.25, 1.0)  # exactly the reduced speed is allowed


@pytest.mark.parametrize(("args", "kw", "match"), [
    ((0.0, 1.0), {}, "max_speed"),
    ((0.1, float("nan")), {}, "max_angular_speed"),
    ((0.1, 1.0), dict(near_patient_speed=0.2), "must not exceed max_speed"),
    ((0.1, 1.0), dict(near_patient_angular_speed=2.0), "must not exceed max_angular"),
    ((0.1, 1.0), dict(near_patient_distance=-0.01), "near_patient_distance"),
])
def test_bad_limiter_settings(args, kw, match):
    """Issue 4 safety (clear errors): zero, non-finite and inconsistent limits raise
    InputError naming the setting."""
    with pytest.raises(InputError, match=match):
        SpeedLimiter(*args, **kw)


def test_random_targets_never_exceed_either_speed_and_are_reached():
    """Issue 4 safety (speed limiter, property style): over random start and target poses
    (seeded), no step exceeds the linear or the angular speed, translation stays on the
    straight line, and the target is reached exactly in the expected number of steps."""
    rng = np.random.default_rng(20240604)
    for _ in range(60):
        # random limits; the period is chosen for 1-80 steps per move to keep the run
        # short (the property does not depend on the period's size)
        v, w = rng.uniform(0.01, 0.25), rng.uniform(0.05, 3.0)
        lim = SpeedLimiter(v, w)
        A, B = random_pose(rng), random_pose(rng)
        dist, angle = step_sizes(A, B)
        dt = max(dist / v, angle / w) / rng.uniform(0.5, 80.0)
        expected = int(np.ceil(max(dist / (v * dt), angle / (w * dt)) - 1e-9))
        T, n = A, 0
        while not np.array_equal(T, B):
            nxt = lim.step(T, B, dt)
            dp, da = step_sizes(T, nxt)
            assert dp <= v * dt + EPS and da <= w * dt + EPS
            # on the segment A->B: no sideways drift
            u = (B[:3, 3] - A[:3, 3]) / dist
            off = (nxt[:3, 3] - A[:3, 3]) - u * ((nxt[:3, 3] - A[:3, 3]) @ u)
            assert np.linalg.norm(off) < 1e-9
            T, n = nxt, n + 1
            assert n <= expected + 1, "did not converge"
        assert n in (expected, expected + 1)


def test_translation_and_rotation_arrive_together():
    """Issue 4 safety (speed limiter): both move by the same fraction each period, so the
    slower one sets the pace and neither overshoots (one step short of a long move, the
    rotation is part way too)."""
    lim = SpeedLimiter(0.1, 1.0)
    A, B = pose([0, 0, 0]), pose([0.01, 0, 0], [0, 0, 0.05])
    T = lim.step(A, B, DT)  # translation-limited: 50 steps against 25
    dp, da = step_sizes(A, T)
    assert dp == pytest.approx(0.1 * DT)
    assert da == pytest.approx(0.05 * (0.1 * DT) / 0.01)  # the same 2 % of the way
    # rotation-limited
    B = pose([0.0001, 0, 0], [0, 0, 1.0])
    T = lim.step(A, B, DT)
    dp, da = step_sizes(A, T)
    assert da == pytest.approx(1.0 * DT) and dp == pytest.approx(0.0001 * DT)


def test_rotation_follows_scipy_slerp():
    """Issue 4 safety (speed limiter): the intermediate rotation is the slerp between the
    current and target rotations (scipy's Slerp), at the fraction the translation took."""
    rng = np.random.default_rng(7)
    lim = SpeedLimiter(0.05, 3.0)
    for _ in range(10):
        A, B = random_pose(rng), random_pose(rng)
        T = lim.step(A, B, DT)
        s = np.linalg.norm(T[:3, 3] - A[:3, 3]) / np.linalg.norm(B[:3, 3] - A[:3, 3])
        key = Rotation.from_matrix(np.stack([A[:3, :3], B[:3, :3]]))
        ref = Slerp([0.0, 1.0], key)(s).as_matrix()
        assert np.allclose(T[:3, :3], ref, atol=1e-12)


def test_step_within_reach_returns_the_target():
    """Issue 4 safety (speed limiter): a target within one step is returned as is; a
    target equal to the current pose stays put."""
    lim = SpeedLimiter(0.25, 0.5)
    A = pose([0.1, 0.2, 0.3], [0.1, 0, 0])
    B = pose([0.1, 0.2, 0.3 + 0.25 * DT], [0.1, 0, 0.5 * DT])
    assert np.array_equal(lim.step(A, B, DT), B)
    assert np.array_equal(lim.step(A, A, DT), A)


def test_near_patient_speed_applies_near_the_points():
    """Issue 4 safety (near-patient limit): within near_patient_distance of a given point
    (the opener, the targets) the lower speeds apply, outside the maximum ones; a step
    that would enter the zone is already slow."""
    lim = SpeedLimiter(0.25, 0.5, near_patient_speed=0.05, near_patient_angular_speed=0.1,
                       near_patient_distance=0.1)
    opener = np.array([0.5, 0.0, 0.2])
    targets = [opener, [0.0, 0.5, 0.2]]
    far = pose([0.0, 0.0, 0.2])
    goal = pose([0.5, 0.0, 0.2], [0, 0, 1.0])
    dp, _ = step_sizes(far, lim.step(far, goal, DT, near=targets))
    assert dp == pytest.approx(0.25 * DT)
    inside = pose([0.45, 0.0, 0.2])
    dp, _ = step_sizes(inside, lim.step(inside, goal, DT, near=targets))
    assert dp <= 0.05 * DT + EPS  # rotation-limited at 0.1 rad/s here
    assert lim.speeds([0.45, 0.0, 0.2], targets) == (0.05, 0.1)
    assert lim.speeds([0.0, 0.45, 0.2], targets) == (0.05, 0.1)  # the second point
    assert lim.speeds([0.3, 0.0, 0.2], targets) == (0.25, 0.5)
    # exactly at near_patient_distance counts as near, a hair beyond does not
    lim8 = SpeedLimiter(0.25, 0.5, near_patient_speed=0.05, near_patient_distance=0.125)
    assert lim8.is_near([0.375, 0.0, 0.2], [0.5, 0.0, 0.2]) is True
    assert lim8.is_near([np.nextafter(0.375, 0), 0.0, 0.2], [0.5, 0.0, 0.2]) is False
    edge = pose([0.5 - 0.1 - 0.25 * DT / 2, 0.0, 0.2])  # full step would cross in
    dp, _ = step_sizes(edge, lim.step(edge, pose(opener), DT, near=opener))
    assert dp == pytest.approx(0.05 * DT)
    # a whole approach: never faster than allowed where it is
    T = far
    while not np.array_equal(T, goal):
        nxt = lim.step(T, goal, DT, near=targets)
        dp, da = step_sizes(T, nxt)
        slow = lim.is_near(T[:3, 3], targets) or lim.is_near(nxt[:3, 3], targets)
        assert dp <= (0.05 if slow else 0.25) * DT + EPS
        assert da <= (0.1 if slow else 0.5) * DT + EPS
        T = nxt


def test_limiter_from_settings():
    """Issue 4 safety (configuration): the limiter is built from the [safety] settings."""
    s = SafetySection()
    lim = SpeedLimiter.from_settings(s)
    assert (lim.max_speed, lim.near_patient_speed, lim.max_angular_speed,
            lim.near_patient_angular_speed, lim.near_patient_distance) == (
        s.max_speed, s.near_patient_speed, s.max_angular_speed,
        s.near_patient_angular_speed, s.near_patient_distance)


@pytest.mark.parametrize(("cur", "tgt", "dt", "near", "match"), [
    (np.eye(3), np.eye(4), DT, None, r"current TCP pose .* shape \(3, 3\)"),
    (np.eye(4), np.full((4, 4), np.nan), DT, None, "target TCP pose .* non-finite"),
    (np.eye(4), np.diag([1.0, 1.0, -1.0, 1.0]), DT, None, "not a rotation"),
    (np.eye(4), np.diag([2.0, 1.0, 1.0, 1.0]), DT, None, "not a rotation"),
    (np.eye(4), np.eye(4) + np.eye(4, k=-3), DT, None, "bottom row"),
    (np.eye(4), "pose", DT, None, "4x4 transform"),
    (np.eye(4), np.eye(4), 0.0, None, "dt"),
    (np.eye(4), np.eye(4), DT, [[0.0, 0.0]], r"near-patient points .* \(N, 3\)"),
    (np.eye(4), np.eye(4), DT, [0.0, np.inf, 0.0], "near-patient points .* non-finite"),
])
def test_step_validates_inputs(cur, tgt, dt, near, match):
    """Issue 4 safety (clear errors): malformed poses (shape, NaN, reflection, scale,
    bottom row), a non-positive period and bad near points raise InputError saying what."""
    lim = SpeedLimiter(0.25, 0.5, near_patient_distance=0.1)
    with pytest.raises(InputError, match=match):
        lim.step(cur, tgt, dt, near=near)


# -- workspace -----------------------------------------------------------------------------
def test_workspace_contains_with_inclusive_bounds():
    """Issue 4 safety (workspace box): contains() takes a point or a 4x4 pose, bounds
    included."""
    box = WorkspaceBox([-0.5, -0.5, 0.0], [0.5, 0.5, 0.8])
    assert box.contains([0.5, -0.5, 0.0]) and box.contains(pose([0.0, 0.0, 0.4]))
    assert not box.contains([0.5000001, 0.0, 0.4])
    box.check(pose([0.5, 0.5, 0.8]))  # on the boundary: no error


def test_workspace_check_names_axis_and_excess():
    """Issue 4 safety (workspace box): check() raises LimitError naming every axis outside
    the box and by how much."""
    box = WorkspaceBox([-0.5, -0.5, 0.0], [0.5, 0.5, 0.8])
    with pytest.raises(LimitError) as ei:
        box.check(pose([0.62, 0.1, -0.05]))
    msg = str(ei.value)
    assert msg == ("TCP outside the workspace (base frame): x = 0.6200 m is 0.1200 m above "
                   "the maximum 0.5000 m; z = -0.0500 m is 0.0500 m below the minimum "
                   "0.0000 m")
    assert box.violations([0.0, -0.6, 0.1]) == [("y", pytest.approx(-0.1))]


@pytest.mark.parametrize(("lo", "hi", "match"), [
    ([0.0, 0.0, 0.0], [1.0, 0.0, 1.0], r"below maximum on every axis \(y: 0.0 >= 0.0\)"),
    ([0.0, 0.0], [1.0, 1.0, 1.0], r"minimum .* 3-vector"),
    ([0.0, 0.0, 0.0], [1.0, np.nan, 1.0], "non-finite"),
])
def test_workspace_bad_bounds(lo, hi, match):
    """Issue 4 safety (clear errors): a box with min not below max, a wrong shape or a NaN
    raises InputError saying which."""
    with pytest.raises(InputError, match=match):
        WorkspaceBox(lo, hi)


def test_workspace_check_validates_input():
    """Issue 4 safety (clear errors): check() of a malformed pose or point is an
    InputError, not a silent pass."""
    box = WorkspaceBox([-1, -1, -1], [1, 1, 1])
    with pytest.raises(InputError, match="3-vector"):
        box.check([0.0, 0.0])
    with pytest.raises(InputError, match="non-finite"):
        box.contains([0.0, np.nan, 0.0])
    with pytest.raises(InputError, match="not a rotation"):
        box.check(np.diag([1.0, 1.0, -1.0, 1.0]))


# -- settings ------------------------------------------------------------------------------
def test_safety_settings_defaults_build_every_object():
    """Issue 4 safety (configuration): the [safety] defaults are consistent: the box, the
    limiter and the ISO bound accept them."""
    s = SafetySection()
    box = WorkspaceBox.from_settings(s)
    assert box.contains([0.0, 0.0, 0.5])
    assert s.near_patient_angular_speed <= s.max_angular_speed


@pytest.mark.parametrize(("kw", "where", "match"), [
    (dict(workspace_min=(0.0, 0.0, 0.0), workspace_max=(1.0, 0.0, 1.0)), "workspace_max",
     "must exceed workspace_min"),
    (dict(workspace_max=(850.0, 1.0, 1.0)), "workspace_max", "metres expected"),
    (dict(near_patient_angular_speed=1.0), "near_patient_angular_speed",
     "must not exceed max_angular_speed"),
    (dict(deadline_misses=0), "deadline_misses", "greater than or equal to 1"),
    (dict(camera_stall=0.0), "camera_stall", "greater than 0"),
    (dict(max_position_sigma=0.5), "max_position_sigma", "less than or equal to 0.01"),
])
def test_safety_settings_bounds(kw, where, match):
    """Issue 4 safety (configuration bounds): the new [safety] keys declare their bounds;
    min < max of the workspace is reported on workspace_max."""
    with pytest.raises(ValidationError) as ei:
        SafetySection(**kw)
    err = ei.value.errors()[0]
    assert err["loc"][0] == where and match in str(ei.value)
