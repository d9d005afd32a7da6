"""The needle procedure's motions, looks and hand-offs (issue 7, "What to build" item 7):
wrist limits on a path, the tracker kept through the drive and the hand-off, the pulled
needle shown to the cameras, carries that keep clear of the tissue. Each test's docstring
names the requirement it checks.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from oralnav.control.geometry import rotation_angle
from oralnav.control.needle.procedure import (
    ProcedureSettings,
    back_off,
)

from .cells import _passes_to_the_regrasp, _ports, _procedure


def test_a_path_from_a_wrist_near_its_limit_may_bend_it_as_far_as_it_stands():
    """Issue 7, the regrasp's reach: on trial 87 (ports chosen for the suture) the drive
    ends, as planned with no margin, with the driver's wrist yawed within the plans'
    reach_margin of its limit (-79 deg of +-80). Held to the full margin, every path
    from there failed at its first pose and the regrasp refused out of reach. A path
    leaving a pose may bend the wrist as far as it stands (the margin the pose itself
    keeps, by bisection), the goals keep the full margin: the regrasp passes (truth)."""
    settings = ProcedureSettings()
    cell, proc = _procedure(87, settings=settings, **_ports(settings))
    for step in ("NG", "NH", "ND"):
        r = proc.run(step)
        assert r.ok and r.truth_ok, r
    seen = []
    leaving = proc._leaving_margin
    proc._leaving_margin = lambda arm, here: (seen.append((arm, here)), leaving(arm, here))[1]
    r = proc.run("NR")
    assert r.ok and r.truth_ok, r
    # the driver, backed off the needle, leaves from within the margin's band
    arm, here = seen[0]
    assert arm == proc.driver and cell.reachable(arm, here, 0.0)[0]
    assert not cell.reachable(arm, here, settings.reach_margin)[0]
    leave = leaving(arm, here)
    assert 0.0 < leave < settings.reach_margin
    assert cell.reachable(arm, here, leave)[0]
    assert not cell.reachable(arm, here, leave + 0.01 * settings.reach_margin)[0]
    other = next(a for a in proc.arms if a != arm)       # parked, well inside its range
    assert leaving(other, cell.gripper_pose(other)) == settings.reach_margin


def test_the_driven_tip_seen_end_on_does_not_make_the_tracker_slip():
    """Issue 7, tracking at the drive's end: on trial 120 (ports chosen for the suture)
    the emerging tip points within 8-11 deg of both cameras' lines of sight, so its end
    in the images is the disc of its cut (4 px of spread) and says little of how far
    the wire reaches. Weighed as a side-on end, the images alone put the needle
    1.9 mm and 12 deg from the truth, claimed 0.6 deg sure, the tracker took that as a
    slip in the jaws, and the regrasp refused (not converged). With the end's weight
    cut by its spread (RefineSettings.end_spread_px), the drive and the regrasp pass
    (truth)."""
    cell, proc = _procedure(120, settings=ProcedureSettings(),
                            **_ports(ProcedureSettings()))
    for step in ("NG", "NH", "ND", "NR"):
        r = proc.run(step)
        assert r.ok and r.truth_ok, r


def test_a_tip_standing_over_the_pads_edge_does_not_make_the_tracker_slip():
    """Issue 7, tracking at the drive's end: on trial 82 the emerging tip stands 7-9 px
    beyond the pad's edge in both views, where the wire fades into the step from tissue
    to dark. Its end was read on the edge, the images alone slid the needle 18 deg along
    its arc, the tracker took that as a slip in the jaws, and the regrasp refused (not
    converged). With the edge band neither searched nor read as an end
    (RefineSettings.edge_band_px, the procedure's surface outline), the drive and the
    regrasp pass (truth) and the needle in the tissue is tracked within 3 deg."""
    _passes_to_the_regrasp(82, blind=True)


def test_the_pulled_needle_is_moved_toward_the_views_middle_to_be_seen():
    """Issue 7, the pull's look: where no turn or rise of the pulled needle lets both
    cameras see it (edge-on, off the tissue or out of view: session 20's trials 49, 113
    and 153, whose tracks were then lost), it is moved toward where the reference camera
    looks on the tissue (show_shifts). On trial 49 (ports chosen for the suture), with
    the views refused within 5 mm (in the tissue's plane) of where the pull leaves the
    needle: without the shifts no show pose exists; with them the one found moves the
    needle 10 or 20 mm toward the view's middle. Unrefused, NP passes (truth)."""
    settings = ProcedureSettings()
    cell, proc = _procedure(49, settings=settings, **_ports(settings))
    for step in ("NG", "NH", "ND", "NR"):
        r = proc.run(step)
        assert r.ok and r.truth_ok, r
    arm = proc.holder
    pull = proc._pull[0]
    for k, T in enumerate(pull.G_PT):
        proc._move(arm, T, f"pull pose {k + 1}")
    T_N = pull.G_CN[-1]
    n = proc.normal

    def in_plane(d):
        return d - float(d @ n) * n

    view_each = proc._view_each

    def refused_near(poses, tools, **kw):
        why = view_each(poses, tools, **kw)
        return lambda k: ("not seen there"
                          if np.linalg.norm(in_plane(poses[k][:3, 3] - T_N[:3, 3])) < 0.005
                          else why(k))
    proc._view_each = refused_near
    proc.s = replace(settings, show_shifts=(0.0,))
    assert proc._show_pose(arm, T_N, proc.G_TN) is None
    proc.s = settings
    shown = proc._show_pose(arm, T_N, proc.G_TN)
    assert shown is not None
    moved = in_plane((shown[0] @ proc.G_TN)[:3, 3] - T_N[:3, 3])
    toward = in_plane(proc.views.aim(proc.incision.mean(axis=0)) - T_N[:3, 3])
    assert np.linalg.norm(moved) == pytest.approx(0.010, abs=1e-6) \
        or np.linalg.norm(moved) == pytest.approx(min(0.020, np.linalg.norm(toward)), abs=1e-6)
    assert moved @ toward / (np.linalg.norm(moved) * np.linalg.norm(toward)) > 0.999
    cell, proc = _procedure(49, settings=settings, **_ports(settings))
    for step in ("NG", "NH", "ND", "NR", "NP"):
        r = proc.run(step)
        assert r.ok and r.truth_ok, r


def test_the_pulled_needle_is_turned_to_the_cameras_before_the_look():
    """Issue 7, the pull (NP) shows the regrasp's hold: on trial 2 (ports chosen for
    the suture) the pull leaves the needle standing square to the tissue, which the
    cameras see nearly face-on, so they see the needle edge-on (beyond the 60 deg the
    views measure well; on session 17's trial 18, 81 deg and partly over the dark
    beyond the pad, where the look found half its arc and lost it). NP turns it to
    where both cameras see it (the planner's view rule) before the look: the look then
    sees it there (truth), and the needle is out of the tissue in the jaws."""
    cell, proc = _procedure(2, settings=ProcedureSettings(),
                            **_ports(ProcedureSettings()))
    for step in ("NG", "NH", "ND", "NR"):
        r = proc.run(step)
        assert r.ok and r.truth_ok, r
    assert proc._pull is not None
    pulled = proc._pull[0].G_CN[-1]
    assert proc._view(pulled) == "edge-on to the camera"
    seen = []
    followed = proc._followed
    proc._followed = lambda *a: (seen.append(cell.truth().T_ref_needle), followed(*a))[1]
    np_ = proc.run("NP")
    assert np_.ok and np_.truth_ok, np_
    assert np_.figures["show_turn_deg"] > 0
    tools = [cell.true_gripper_pose(g) for g in cell.grippers]
    assert proc._view(seen[0], tools) == ""


def test_a_needle_near_the_pads_edge_is_lifted_less():
    """Issue 7, the pick-up (NG): on trial 37 the needle lies near the pad's edge, and
    lifted the full 10 mm it would stand against the dark beyond the edge in a view
    (the thin-feature measurement needs the tissue behind it); the pick-up then lifts
    it 5 mm (`lift_low`) rather than refusing, and the picker holds it (truth)."""
    cell, proc = _procedure(37, settings=ProcedureSettings())
    ng = proc.run("NG")
    assert ng.ok and ng.truth_ok, ng
    assert ng.figures["lift_mm"] == 5.0
    _, high = _procedure(37, settings=ProcedureSettings(lift_low=0.010))
    refused = high.run("NG")
    assert refused.refused and "not against the tissue" in refused.detail, refused


def test_a_carry_that_would_sweep_the_needle_through_the_tissue_goes_over_it():
    """Issue 7, the drive enters where planned (the truth's entry is the tip's first
    crossing of the surface): on trial 16 the straight path from the hand-off to the
    drive's approach turns the needle about the jaws and would sweep its tip through the
    tissue away from the planned entry; the approach goes over the tissue instead, and
    the truth's entry and exit are the planned ones."""
    cell, proc = _procedure(16, settings=ProcedureSettings())
    for step in ("NG", "NH"):
        assert proc.run(step).ok
    moves = []
    move = proc._move
    proc._move = lambda arm, T, what: (moves.append(what), move(arm, T, what))[1]
    nd = proc.run("ND")
    assert nd.ok and nd.truth_ok, nd
    assert any(w.startswith("drive approach (over the tissue") for w in moves), moves


def test_the_initialisation_compares_both_twins():
    """Issue 7, base and tip told apart: on trial 17 the wrong twin's fit
    slides its tip on along the thread and its base back inside the wire, where the
    wire beyond the base reads as thread (+10 DN, above the 8 DN a decision needs); the
    initialisation fits the other twin too and keeps the one the thread favours more,
    the true one (+28 DN)."""
    cell, proc = _procedure(17, settings=ProcedureSettings())
    tr = proc._look(init=True)
    assert tr.converged, tr.reason
    T = cell.truth().T_ref_needle
    assert math.degrees(rotation_angle(tr.pose[:3, :3], T[:3, :3])) < 5.0
    assert tr.swage > 20.0


def test_the_hand_off_check_moves_square_to_the_line_of_sight():
    """Issue 7, the hand-off's hold check (seeds 6, 21, 32 failed it while held): the
    views measure depth along the line of sight to about a millimetre, across it to a
    tenth, so the check motion goes across it, hold_check long."""
    cell, proc = _procedure(0, settings=ProcedureSettings())
    for step in ("NG", "NH"):
        assert proc.run(step).ok
    arm = proc.holder
    assert arm is not None and proc.track is not None
    T_N = proc.track.pose
    T0 = cell.gripper_pose(arm)
    goal = proc._check_motion(arm, T_N)
    step = goal[:3, 3] - T0[:3, 3]
    assert np.allclose(goal[:3, :3], T0[:3, :3])
    assert np.linalg.norm(step) == pytest.approx(proc.s.hold_check)
    ray = T_N[:3, 3] - proc.cams[0].T_ref_cam[:3, 3]
    assert abs(step @ ray) / (np.linalg.norm(step) * np.linalg.norm(ray)) < 1e-6
    assert step @ proc.normal >= -1e-9         # never toward the tissue


def test_a_hand_off_keeps_the_needles_ends_the_thread_decided():
    """Issue 7, tracking through the hand-off: on trial 21 the thread, seen at +25 DN
    while the first arm held the needle, hides behind the second arm's jaws once they
    close, and the wrong twin then reads +15 DN. The track stays on the ends it decided
    (it turned end for end here, and ND then saw the driving grasp at 154 deg of arc
    instead of 26)."""
    cell, proc = _procedure(21, settings=ProcedureSettings())
    assert proc.run("NG").ok
    proc.run("NH")
    T = cell.truth().T_ref_needle
    T_track = proc.tracker.last.pose
    assert rotation_angle(T_track[:3, :3].T @ T[:3, :3]) < math.radians(10.0)


@pytest.mark.parametrize("held", [True, False])
def test_the_hold_check_judges_the_follow_across_the_line_of_sight(held):
    """Issue 7, the hand-off's hold check (15 of the 17 `grasp_missed` of the 200
    trials were held: their tracks were 1-3.6 mm off in depth, over the 3-D
    tolerance). The tracked needle 2.5 mm off along the line of sight still followed
    the jaws' 3 mm move across it when held; a needle let go, seen 2.5 mm off in depth
    where it was, did not."""
    from types import SimpleNamespace

    from oralnav.control.geometry import invert
    from oralnav.control.needle.procedure import StepFailed, translation

    cell, proc = _procedure(0)
    arm = proc.arms[0]
    before = cell.truth().T_ref_needle
    ray = before[:3, 3] - proc.cams[0].T_ref_cam[:3, 3]
    ray /= np.linalg.norm(ray)
    across = np.cross(ray, proc.normal)
    across /= np.linalg.norm(across)
    move = translation(proc.s.hold_check * across)
    T0 = invert(move) @ cell.gripper_pose(arm)          # the jaws came 3 mm across
    where = (move if held else np.eye(4)) @ before
    seen = translation(0.0025 * ray + 0.0002 * proc.normal) @ where
    proc._look = lambda *a, **k: SimpleNamespace(converged=True, pose=seen, refined=None,
                                                 reason="")
    if held:
        assert np.array_equal(proc._followed(arm, before, T0, "test", 0.001), seen)
    else:
        with pytest.raises(StepFailed) as err:
            proc._followed(arm, before, T0, "test", 0.001)
        assert err.value.cause == "grasp_missed"


def test_a_held_needle_is_tracked_through_the_hand_off_in_the_narrow_window():
    """Issue 7, tracking accuracy where shafts cross the wire (trial 69): the tracked
    pose after the hand-off's check, started from the pose carried with the jaws, is
    refined in the narrow window first. The wide capture rounds reached a crossing
    shaft and left the held needle 3.6 mm and 14.5 deg off; the drive planned on that
    grasp was refused (`grasp_unfit`)."""
    cell, proc = _procedure(69, settings=ProcedureSettings())
    for step in ("NG", "NH"):
        assert proc.run(step).ok
    assert proc.track is not None
    T = cell.truth().T_ref_needle
    assert np.linalg.norm(proc.track.pose[:3, 3] - T[:3, 3]) < 0.001
    assert rotation_angle(proc.track.pose[:3, :3], T[:3, :3]) < math.radians(3.0)


def test_a_tip_over_the_incision_does_not_slide_the_hand_off_grasp():
    """Issue 7, the hand-off: on trial 132, carried to the hand-off pose, the needle's
    tip lies over the incision line in both views, whose pixels the features ignore.
    The tip's end was read where the wire enters the mask, 6-7 px short, the fit slid
    7 deg along the arc, the driver grasped 6 deg (1.4 mm) off its planned point, and
    the drive refused a grasp 0.3 deg inside the swage margin (grasp_unfit). With the
    incision mask blind to the refinement like the pad's edge band
    (NeedleTracker.set_ignored), the grasp made lies within 1.5 deg of the plan and the
    drive passes (truth)."""
    cell, proc = _procedure(132, settings=ProcedureSettings(),
                            **_ports(ProcedureSettings()))
    assert proc.tracker.blind is not None
    for k, m in enumerate(proc._masks):
        assert m.any() and proc.tracker.blind[k][m].all()
    for step in ("NG", "NH", "ND"):
        r = proc.run(step)
        assert r.ok and r.truth_ok, r
        if step == "NH":
            assert abs(r.figures["grasp_phi_deg"] - r.figures["planned_phi_deg"]) < 1.5, r


def test_the_pick_up_counts_only_hand_offs_the_holder_can_carry_the_needle_to():
    """Issue 7, the pick-up's plan: the hand-off poses a pick-up grasp leads to
    (handoff_meetings) count only where the holder, lifted, can carry the needle on the
    straight path NH moves it on, as NH and port selection (port_pair) check. On trial
    162 the pick-up counted three meetings whose paths all bent the holder's wrist past
    its limits midway, and NH refused (out of reach); counted with their paths, the
    pick-up takes another grasp and the hand-off passes (truth)."""
    cell, proc = _procedure(162, settings=ProcedureSettings(),
                            **_ports(ProcedureSettings()))
    r = proc.run("NG")
    assert r.ok and r.truth_ok, r
    A = proc.picker
    T_N = proc.track.pose
    why: dict[str, int] = {}
    found = proc._meetings(proc._grasp_seen(A, T_N), proc._handoff_candidates(),
                           cell.gripper_pose(A), why, 3)
    assert found, why
    r = proc.run("NH")
    assert r.ok and r.truth_ok, r


def test_a_held_needle_is_not_turned_end_for_end_by_a_fit_from_the_swarm():
    """Issue 7, tracking on the drive's approach: on trial 178 the filter's estimate lay
    on the other twin, and its fit, refined without the motion prior (which cannot reach
    across a half turn), read as agreeing with it; with the slide undetermined it
    replaced the belief the jaws carried, and the drive was tracked end for end (the
    regrasp then found the needle 20 mm from the plan: exit_missed). A fit a half turn
    from a belief now ranks as contradicting it: the drive is tracked within 3 deg and
    the regrasp passes (truth)."""
    _passes_to_the_regrasp(178)


def test_the_hand_off_is_planned_with_the_drivers_path_to_it():
    """Issue 7, the hand-off: a meeting counts only where the driver also gets from
    where it waits to the hand-off's approach and in to its grasp on straight paths
    (NeedleProcedure._driver_path, the moves NH makes), and NH checks that path at the
    limits before moving. On trial 134 the driver's move from its park to the approach
    stopped at its wrist's pitch limit after 68 of 77 increments (move_stopped); with
    the path planned, NH passes (truth). The path ends at the approach, then the
    grasp."""
    cell, proc = _procedure(134, settings=ProcedureSettings(),
                            **_ports(ProcedureSettings()))
    for step in ("NG", "NH"):
        r = proc.run(step)
        assert r.ok and r.truth_ok, r
    T0 = proc.park[proc.driver]
    T_B = cell.gripper_pose(proc.driver)
    path = proc._driver_path(T0, T_B)
    assert np.allclose(path[-1], T_B)
    k = next(i for i, T in enumerate(path)
             if np.allclose(T, back_off(T_B, proc.s.approach)))
    assert 0 < k < len(path) - 1


@pytest.mark.parametrize("attempts", [1, 2])
def test_an_unconverged_global_initialisation_is_started_again(attempts):
    """Issue 36 (generalising): the pick-up's first look, a global initialisation of the
    particle filter, finds the needle's basin with some chance; one that ends unconverged
    (here made so) is started again on fresh frames and particles, up to
    ``init_attempts`` in all, and the look gives the first converged track; with one
    attempt the look stays unconverged."""
    cell, proc = _procedure(2, settings=replace(ProcedureSettings(), init_attempts=attempts))
    starts, update = [], proc.tracker.update
    initialize = proc.tracker.initialize

    def counted(*a, **k):
        starts.append(1)
        return initialize(*a, **k)

    def first_lost(*a, **k):
        tr = update(*a, **k)
        return replace(tr, converged=False, reason="test") if len(starts) == 1 else tr
    proc.tracker.initialize, proc.tracker.update = counted, first_lost
    tr = proc._look(init=True, static=False)
    assert len(starts) == attempts
    assert tr.converged == (attempts == 2)
    if tr.converged:
        T = cell.truth().T_ref_needle
        assert np.linalg.norm(tr.pose[:3, 3] - T[:3, 3]) < 0.5e-3
