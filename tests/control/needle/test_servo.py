"""Issue 36, item 1 (the servo's law and guards, ``oralnav.control.needle.servo``): a held
needle servoed from its tracked pose reaches its goal through an arm's kinematic error
that leaves the open-loop motion off by millimetres; each correction is bounded; and a
lost, uncertain, stale, jumping or malformed track stops the servo, naming the cause,
before anything is commanded. The arm here is a rigid-body stand-in: the reported tool
is ``E @`` the true one, the needle moves with the true tool."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from oralnav.control.errors import NeedleError
from oralnav.control.geometry import invert, make_transform, rotation_angle
from oralnav.control.needle.servo import (
    DriveServo,
    HeldNeedleServo,
    Seen,
    ServoSettings,
    ServoStop,
)

#: The needle's tip in its own frame (m): a 13 mm radius semicircle's end.
TIP = np.array([-0.013, 0.0, 0.0])
#: An arm's RCM in the reference frame (m), about where the trial cells put them.
RCM = np.array([0.055, 0.01, 0.0])


def _error(mm: float, deg: float, seed: int) -> np.ndarray:
    """A kinematic error: ``deg`` about a random axis through the RCM, then ``mm``."""
    rng = np.random.default_rng(seed)
    axis, way = rng.normal(size=3), rng.normal(size=3)
    R = Rotation.from_rotvec(math.radians(deg) * axis / np.linalg.norm(axis)).as_matrix()
    return make_transform(R, RCM - R @ RCM + mm * 1e-3 * way / np.linalg.norm(way))


class HeldArm:
    """A tool holding the needle with grasp ``G`` (tool -> needle), commanded through its
    reported pose; ``E`` maps the true tool pose to the reported one."""

    def __init__(self, E: np.ndarray) -> None:
        self.E = E
        self.T_true = make_transform(Rotation.from_euler("xyz", [170, 10, 30],
                                                         degrees=True),
                                     [0.01, 0.005, 0.1])
        self.G = make_transform(Rotation.from_euler("z", 80, degrees=True),
                                [0.0, 0.0, 0.012])

    @property
    def reported(self) -> np.ndarray:
        return self.E @ self.T_true

    @property
    def needle(self) -> np.ndarray:
        return self.T_true @ self.G

    def command(self, T_reported: np.ndarray) -> None:
        self.T_true = invert(self.E) @ T_reported


def _goal(start: np.ndarray) -> np.ndarray:
    """A drive-like goal: the needle turned 150 deg about its own z through its centre
    (the drive's arc), then 3 mm along the tissue."""
    return start @ make_transform(Rotation.from_euler("z", 150, degrees=True)) \
        @ make_transform(None, [0.0, 0.003, 0.0])


def _tip_error(T: np.ndarray, goal: np.ndarray) -> float:
    return float(np.linalg.norm((T[:3, :3] @ TIP + T[:3, 3]) - (goal[:3, :3] @ TIP
                                                                 + goal[:3, 3])))


@pytest.mark.parametrize("seed", range(1, 7))
def test_servo_reaches_the_goal_through_an_arm_error(seed):
    """With a 1 mm / 0.5 deg kinematic error in a random direction the open-loop motion
    (the grasp as the reported pose sees it, the goal commanded once) leaves the tip
    0.24-3.1 mm off (seeds 1-10); servoed from noisy tracked poses (0.03 mm, 0.05 deg)
    the tip ends within 0.15 mm and 0.3 deg, each correction within its bounds."""
    rng = np.random.default_rng(100 + seed)
    arm = HeldArm(_error(1.0, 0.5, seed))
    G_seen = invert(arm.reported) @ arm.needle        # the grasp as the procedure sees it
    goal = _goal(arm.needle)
    arm.command(goal @ invert(G_seen))                 # open loop
    open_loop = _tip_error(arm.needle, goal)
    assert open_loop > 0.0002

    s = ServoSettings()
    servo = HeldNeedleServo(goal, TIP, s)
    now = 0.0
    for _ in range(s.max_updates):
        now += 0.033
        noise = make_transform(Rotation.from_rotvec(rng.normal(0, math.radians(0.05), 3)),
                               rng.normal(0, 0.00003, 3))
        cmd = servo.update(Seen(noise @ arm.needle, now, sigma_position=0.0001,
                                sigma_angle=math.radians(0.3)), now + 0.01)
        if cmd.done:
            break
        moved = cmd.delta @ np.append(servo._point(noise @ arm.needle), 1.0)
        step = np.linalg.norm(moved[:3] - servo._point(noise @ arm.needle))
        assert step <= s.max_shift + 1e-12
        assert rotation_angle(cmd.delta[:3, :3]) <= s.max_turn + 1e-12
        arm.command(cmd.delta @ arm.reported)
    assert cmd.done, f"not done after {servo.updates} updates"
    assert _tip_error(arm.needle, goal) < 0.00015
    assert math.degrees(rotation_angle(arm.needle[:3, :3], goal[:3, :3])) < 0.3


def test_a_goal_already_reached_commands_nothing():
    """A needle seen at its goal is done at once: the identity, no correction counted."""
    goal = HeldArm(np.eye(4)).needle
    cmd = HeldNeedleServo(goal, TIP).update(Seen(goal, 1.0), 1.0)
    assert cmd.done and np.array_equal(cmd.delta, np.eye(4))


def _servo_after_one_update() -> tuple[HeldNeedleServo, np.ndarray]:
    arm = HeldArm(np.eye(4))
    servo = HeldNeedleServo(_goal(arm.needle), TIP)
    cmd = servo.update(Seen(arm.needle, 1.0), 1.0)
    arm.command(cmd.delta @ arm.reported)
    return servo, arm.needle


def test_the_tool_motion_given_is_what_the_jump_check_predicts_with():
    """The seen pose after the commanded motion passes the jump check (by default the
    last command is the tool's motion); the same pose when the caller says the tool moved
    4 mm more is a jump (the needle did not follow the tool)."""
    servo, after = _servo_after_one_update()
    assert not servo.update(Seen(after, 1.1), 1.1).done
    servo, after = _servo_after_one_update()
    more = make_transform(None, [0.004, 0.0, 0.0]) @ servo._last_delta
    with pytest.raises(ServoStop, match="jump"):
        servo.update(Seen(after, 1.1), 1.1, tool_motion=more)


@pytest.mark.parametrize("seen, now, cause", [
    (dict(converged=False, reason="the filter's estimate is not on the wire"), 1.1, "lost"),
    (dict(sigma_position=0.0005), 1.1, "uncertain"),
    (dict(sigma_angle=math.radians(3.0)), 1.1, "uncertain"),
    (dict(), 1.3, "stale"),
    (dict(twin=True), 1.1, "jump"),
    (dict(slip=0.003), 1.1, "jump"),
    (dict(nan=True), 1.1, "not_finite"),
])
def test_a_bad_track_stops_the_servo_naming_why(seen, now, cause):
    """Bad input (issue 36): the tracker not converged, a pose over its uncertainty
    bounds, a frame older than 100 ms, a twin flip (the needle seen turned 180 deg about
    its symmetry axis) or a 3 mm slip from where the tool's motion puts it, a pose with
    a NaN: each a ServoStop naming its cause, and no command."""
    servo, after = _servo_after_one_update()
    T = after.copy()
    if seen.pop("twin", False):
        T = T @ make_transform(Rotation.from_euler("y", 180, degrees=True))
    if (slip := seen.pop("slip", None)) is not None:
        T[:3, 3] += [slip, 0.0, 0.0]
    if seen.pop("nan", False):
        T[0, 3] = math.nan
    with pytest.raises(ServoStop) as err:
        servo.update(Seen(T, 1.1, **seen), now)
    assert err.value.cause == cause
    if cause == "lost":
        assert "not on the wire" in str(err.value)


def test_a_frame_used_once_is_not_used_again():
    """A frame no newer than the last one used holds (identity, nothing corrected): its
    correction is already under way."""
    arm = HeldArm(np.eye(4))
    servo = HeldNeedleServo(_goal(arm.needle), TIP)
    servo.update(Seen(arm.needle, 1.0), 1.0)
    cmd = servo.update(Seen(arm.needle, 1.0), 1.05)
    assert cmd.held and not cmd.done and np.array_equal(cmd.delta, np.eye(4))
    assert servo.updates == 1


def test_a_servo_that_makes_no_progress_stops():
    """An arm that never moves (its commands ignored): after max_updates corrections
    the servo stops (no_progress) instead of commanding forever."""
    arm = HeldArm(np.eye(4))
    servo = HeldNeedleServo(_goal(arm.needle), TIP, ServoSettings(max_updates=5))
    with pytest.raises(ServoStop, match="no_progress"):
        for k in range(10):
            servo.update(Seen(arm.needle, 1.0 + k * 0.03), 1.0 + k * 0.03,
                         tool_motion=np.eye(4))


@pytest.mark.parametrize("bad, what", [(dict(gain=0.0), "gain"), (dict(gain=1.5), "gain"),
                                       (dict(max_shift=-1.0), "max_shift"),
                                       (dict(max_age=math.nan), "max_age"),
                                       (dict(max_updates=0), "max_updates")])
def test_bad_settings_are_named(bad, what):
    """Bad input: settings out of range are refused, naming the setting."""
    with pytest.raises(NeedleError, match=what):
        ServoSettings(**bad)


def test_a_bad_goal_or_control_point_is_refused():
    """Bad input: a goal that is not a rigid transform, a control point not 3 values."""
    with pytest.raises(ServoStop, match="goal"):
        HeldNeedleServo(np.full((4, 4), np.nan))
    with pytest.raises(NeedleError, match="control point"):
        HeldNeedleServo(np.eye(4), np.zeros(2))


def test_a_tracker_answer_becomes_a_seen_frame():
    """A tracker's answer carries its pose, convergence, reason and the refinement's
    sigmas; without a refinement the sigmas are infinite, so the servo stops on it
    (uncertain) even were it marked converged."""
    from types import SimpleNamespace

    refined = SimpleNamespace(sigma_position=0.0001, sigma_angle=0.01)
    track = SimpleNamespace(pose=np.eye(4), refined=refined, converged=True, reason="",
                            short=False)
    seen = Seen.from_track(track, 2.5)
    assert (seen.stamp, seen.sigma_position, seen.sigma_angle) == (2.5, 0.0001, 0.01)
    bare = Seen.from_track(SimpleNamespace(pose=np.eye(4), refined=None, converged=True,
                                           reason="", short=False), 2.5)
    assert math.isinf(bare.sigma_position)
    with pytest.raises(ServoStop, match="uncertain"):
        HeldNeedleServo(make_transform(None, [0.0, 0.0, 0.001])).update(bare, 2.5)


# -- the drive servoed on the needle's circle (DriveServo) ---------------------------------

def _drive_goals(start: np.ndarray, n: int = 60) -> np.ndarray:
    """A drive's planned needle poses: ``start`` turned 0-180 deg about its own z through
    its centre, in ``n`` steps (the drive holds the centre still)."""
    return np.stack([start @ make_transform(Rotation.from_euler("z", a, degrees=True))
                     for a in np.linspace(0.0, 180.0, n + 1)])


def _drive(seed: int, servo: DriveServo | None, looks_until: int = 16,
           rng: np.random.Generator | None = None) -> float:
    """Drive a needle held through a 1 mm / 0.5 deg arm error along :func:`_drive_goals`,
    commanding the plan (the grasp as the reported pose sees it) times the servo's
    correction, the servo looking every 4 poses up to pose ``looks_until`` (noisy seen
    centres, 0.05 mm); the largest distance (m) of the true centre from the plan."""
    arm = HeldArm(_error(1.0, 0.5, seed))
    G_seen = invert(arm.reported) @ arm.needle
    goals = _drive_goals(arm.needle)
    worst = 0.0
    for k, goal in enumerate(goals):
        D = np.eye(4) if servo is None else servo.correction(k)
        arm.command(D @ goal @ invert(G_seen))
        worst = max(worst, float(np.linalg.norm(arm.needle[:3, 3] - goal[:3, 3])))
        if servo is not None and k % 4 == 0 and k <= looks_until:
            seen = arm.needle.copy()
            seen[:3, 3] += rng.normal(0.0, 0.00005, 3)
            servo.update(k, Seen(seen, float(k), sigma_position=0.0001,
                                 sigma_angle=math.radians(0.2)), float(k),
                         servo.predicted(k, D) @ invert(servo.predicted(k, D)), D)
    return worst


@pytest.mark.parametrize("seed", range(1, 11))
def test_drive_servo_learns_how_the_error_wanders_as_the_needle_turns(seed):
    """Issue 36, item 1 (the drive): through a 1 mm / 0.5 deg arm error the open-loop
    drive takes the needle's centre 0.19-3.2 mm off the plan somewhere on its 180 deg
    turn (seeds 1-10, the error's direction drawn per seed); servoed on looks over its
    first 48 deg only (the views lose the circle once half the arc is in the tissue),
    the rest predicted by the model of the arm's error, the true centre stays within
    0.5 mm of the plan at every pose, and within half the open-loop figure (or 0.15 mm)."""
    open_loop = _drive(seed, None)
    servo = DriveServo(_drive_goals(HeldArm(np.eye(4)).needle), ServoSettings(
        max_jump_shift=0.01))
    servoed = _drive(seed, servo, rng=np.random.default_rng(seed))
    assert servoed < 0.0005, (servoed, open_loop)
    assert servoed < max(0.5 * open_loop, 0.00015), (servoed, open_loop)
    assert servo.looks == 5 and math.isclose(math.degrees(servo.span), 48.0)


def test_drive_servo_with_one_look_only_shifts():
    """One look fixes the circle's offset there and nothing else: the correction at that
    pose cancels the seen error, the model's turning part stays near its zero prior."""
    goals = _drive_goals(HeldArm(np.eye(4)).needle)
    servo = DriveServo(goals)
    seen = goals[0].copy()
    seen[:3, 3] += [0.001, -0.0005, 0.0002]
    err = servo.update(0, Seen(seen, 1.0, sigma_position=0.0001), 1.0, np.eye(4), np.eye(4))
    assert math.isclose(err, float(np.linalg.norm([0.001, -0.0005, 0.0002])))
    np.testing.assert_allclose(servo.correction(0)[:3, 3], [-0.001, 0.0005, -0.0002],
                               atol=1e-6)
    assert servo.span == 0.0


def _drive_servo_seen(**kw) -> tuple[DriveServo, Seen]:
    goals = _drive_goals(HeldArm(np.eye(4)).needle)
    servo = DriveServo(goals)
    servo.update(0, Seen(goals[0], 1.0, sigma_position=0.0001), 1.0, np.eye(4), np.eye(4))
    args = {"pose": goals[4], "stamp": 2.0, "sigma_position": 0.0001, **kw}
    return servo, Seen(**args)


@pytest.mark.parametrize(("kw", "cause"), [
    ({"sigma_position": 0.0004}, "uncertain"),
    ({"sigma_angle": math.radians(2.0)}, "uncertain"),
    ({"converged": False, "reason": "test: off the wire"}, "lost"),
    ({"converged": False, "reason": "test: 55 % of the arc", "short": True}, "uncertain"),
    ({"stamp": 1.5}, "stale"),
    ({"stamp": math.nan}, "not_finite"),
])
def test_drive_servo_guards_stop_before_anything_is_learnt(kw, cause):
    """Issue 36, bad input: an uncertain circle or a look that shows too little of the arc
    (the caller carries on on the model), a track lost for another reason, a stale or
    malformed frame each raise their cause and leave the model as it was."""
    servo, seen = _drive_servo_seen(**kw)
    before = servo.correction(30).copy()
    with pytest.raises(ServoStop) as e:
        servo.update(4, seen, 2.0, np.eye(4), np.eye(4))
    assert e.value.cause == cause
    assert servo.looks == 1
    np.testing.assert_array_equal(servo.correction(30), before)


def test_drive_servo_stops_on_a_circle_off_the_predicted_motion():
    """A needle seen 3 mm from where the motion since the last look puts it (a slip, a
    wrong fit) is a jump: no servo on a contradicted pose; the slide along the circle is
    no jump (the jaws fix it, the views cannot see it in the tissue)."""
    goals = _drive_goals(HeldArm(np.eye(4)).needle)
    motion = goals[4] @ invert(goals[0])
    servo, _ = _drive_servo_seen()
    slid = goals[4] @ make_transform(Rotation.from_euler("z", 20, degrees=True))
    servo.update(4, Seen(slid, 2.0, sigma_position=0.0001), 2.0, motion, np.eye(4))
    servo, _ = _drive_servo_seen()
    off = goals[4].copy()
    off[:3, 3] += [0.003, 0.0, 0.0]
    with pytest.raises(ServoStop) as e:
        servo.update(4, Seen(off, 2.0, sigma_position=0.0001), 2.0, motion, np.eye(4))
    assert e.value.cause == "jump" and "3.00 mm" in str(e.value)


def test_drive_servo_takes_no_look_further_off_than_the_arms_can_be():
    """Issue 36 (the streamed drive on exact arms): a centre seen further off the plan
    than ``plausible_sigmas`` times the prior allows (with a 0.3 mm prior, 4 x 0.43 mm)
    is the tracker's error: ``implausible``, the model as it was; within it, the look is
    taken. A wider prior (inexact arms) takes the same look."""
    goals = _drive_goals(HeldArm(np.eye(4)).needle)
    far = goals[0].copy()
    far[:3, 3] += [0.003, 0.0, 0.0]
    tight = DriveServo(goals, prior_shift=0.0003)
    with pytest.raises(ServoStop) as e:
        tight.update(0, Seen(far, 1.0, sigma_position=0.0001), 1.0, np.eye(4), np.eye(4))
    assert e.value.cause == "implausible" and "3.00 mm" in str(e.value)
    assert tight.looks == 0 and np.allclose(tight.correction(10), np.eye(4))
    near = goals[0].copy()
    near[:3, 3] += [0.0015, 0.0, 0.0]
    tight.update(0, Seen(near, 1.0, sigma_position=0.0001), 1.0, np.eye(4), np.eye(4))
    wide = DriveServo(goals, prior_shift=0.0015)
    wide.update(0, Seen(far, 1.0, sigma_position=0.0001), 1.0, np.eye(4), np.eye(4))
    assert wide.looks == 1


def test_a_look_s_weight_is_its_share_of_an_independent_one():
    """Issue 36 (the streamed drive): four looks at a quarter's weight each (frames a
    pose apart sharing their error) move the model as one full look does, where four at
    full weight pull it further from the prior; a weight outside (0, 1] is refused."""
    goals = _drive_goals(HeldArm(np.eye(4)).needle)
    seen = goals[0].copy()
    seen[:3, 3] += [0.0004, 0.0, 0.0]
    look = Seen(seen, 1.0, sigma_position=0.0002)
    one, shared, full = (DriveServo(goals, prior_shift=0.0003) for _ in range(3))
    one.update(0, look, 1.0, np.eye(4), np.eye(4))
    for _ in range(4):
        shared.update(0, look, 1.0, np.eye(4), np.eye(4), weight=0.5)
        full.update(0, look, 1.0, np.eye(4), np.eye(4))
    np.testing.assert_allclose(shared.correction(0), one.correction(0), atol=1e-9)
    assert abs(full.correction(0)[0, 3]) > abs(one.correction(0)[0, 3]) + 5e-5
    with pytest.raises(NeedleError, match="weight"):
        one.update(0, look, 1.0, np.eye(4), np.eye(4), weight=0.0)


def test_drive_servo_refuses_malformed_goals():
    """Goals that are not (n, 4, 4) rigid poses, or a prior that is not a length, are
    refused naming what is wrong."""
    with pytest.raises(NeedleError, match="goals"):
        DriveServo(np.eye(4))
    with pytest.raises(ServoStop, match="drive goal 2"):
        DriveServo(np.stack([np.eye(4), np.full((4, 4), np.nan)]))
    with pytest.raises(NeedleError, match="prior_shift"):
        DriveServo(np.stack([np.eye(4)]), prior_shift=0.0)


class _Track:
    """The fields :meth:`Seen.from_track` reads."""

    def __init__(self, reason: str, held_reason: str) -> None:
        from oralnav.control.needle.refine import Refined

        self.pose = np.eye(4)
        self.converged = not reason
        self.reason, self.held_reason = reason, held_reason
        self.short = False
        self.refined = Refined(np.eye(4), 0.1, 0.9, 0.0001, math.radians(2.6), True,
                               sigma_slide=math.radians(2.6), sigma_tilt=math.radians(0.1))


def test_a_held_needle_is_judged_without_its_slide():
    """A track the tracker leaves unconverged only for its slide (2.6 deg; its plane
    0.1 deg) is usable for a needle held in the jaws, its angle sigma the plane's; one
    lost for another reason is not."""
    seen = Seen.from_track(_Track("uncertain (slide)", ""), 1.0, held=True)
    assert seen.converged and math.isclose(seen.sigma_angle, math.radians(0.1))
    free = Seen.from_track(_Track("uncertain (slide)", ""), 1.0)
    assert not free.converged and math.isclose(free.sigma_angle, math.radians(2.6))
    lost = Seen.from_track(_Track("poor fit", "poor fit"), 1.0, held=True)
    assert not lost.converged and lost.reason == "poor fit"
