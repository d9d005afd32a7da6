"""The simulated two-arm needle-driving cell (issue 7, "What to build" item 4:
``oralnav.sim.world.needle_cell``): grasp physics, rigid carrying, release, hand-off, reach
limits, entry/exit truth on a drive planned with ``control/needle/drive.py``, the
kinematic error of reported poses, rendering. Each test's docstring names the requirement
it checks.
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from oralnav.config.scene import load_arms, load_scene
from oralnav.control.geometry import invert, make_transform, transform_points
from oralnav.control.needle.drive import G_SN, SutureGeometry, plan_drive, tissue_frame
from oralnav.control.needle.grasp import grasp_transform
from oralnav.sim.world.needle_cell import ArmReach, CellError, NeedleCell

EXAMPLE = Path(__file__).resolve().parents[3] / "config" / "examples" / "needle_cell.toml"
LOOSE = ArmReach(rcm=np.array([0.0, 0.0, -0.2]), min_insertion=0.0, max_insertion=1.0,
                 max_wrist_pitch=math.pi, max_wrist_yaw=math.pi)


@pytest.fixture(scope="module")
def example():
    return load_scene(EXAMPLE), load_arms(EXAMPLE)


@pytest.fixture
def cell(example) -> NeedleCell:
    scene, arms = example
    return NeedleCell(scene, arms)


def _above(T_ref_needle: np.ndarray, phi: float, dy: float = 0.0, depth: float = 0.0005,
           dz: float = 0.0) -> np.ndarray:
    """A gripper pose picking up a needle that lies flat, from above: the jaws on either
    side of the wire at arc angle ``phi`` (tool y = the arc's outward radial, x = the
    wire's tangent, z = the needle's -z, into the pad), the wire ``depth`` behind the tip;
    the gripper shifted by ``dy`` along its y and ``dz`` along its z from there."""
    radial = np.array([math.cos(phi), math.sin(phi), 0.0])
    z = np.array([0.0, 0.0, -1.0])
    wire = 0.013 * radial
    T_N_T = make_transform(np.column_stack([np.cross(radial, z), radial, z]),
                           wire + (depth + dz) * z + dy * radial)
    return T_ref_needle @ T_N_T


def _pickup(cell: NeedleCell, name: str, phi: float) -> None:
    cell.move(name, _above(cell.truth().T_ref_needle, phi))
    assert cell.close(name)


# -- grasp --------------------------------------------------------------------------------
@pytest.mark.parametrize("dy", [0.0, 0.0015, -0.0019])
def test_grasp_when_the_jaws_straddle_the_wire(cell, dy):
    """Item 4, grasp physics: open jaws placed with the wire between them (off-centre by
    up to half the 4 mm gap) hold the needle when they close; the jaws centre the wire (the
    needle shifts along the gripper's y by the offset, nothing else changes), and the
    truth reports the hold and the actual grasp."""
    before = cell.truth().T_ref_needle
    cell.move("left", _above(before, 2.4, dy=dy))
    assert cell.jaw_open("left")
    assert cell.close("left") is True
    assert not cell.jaw_open("left")
    tr = cell.truth()
    assert tr.held_by == ("left",) and set(tr.T_tool_needle) == {"left"}
    T_tool = cell.true_gripper_pose("left")
    np.testing.assert_allclose(tr.T_tool_needle["left"], invert(T_tool) @ tr.T_ref_needle,
                               atol=1e-12)
    wire_T = transform_points(tr.T_tool_needle["left"], cell.needle.point(2.4)[None])[0]
    np.testing.assert_allclose(wire_T, [0.0, 0.0, -0.0005], atol=1e-7)   # centred
    shift = tr.T_ref_needle[:3, 3] - before[:3, 3]
    np.testing.assert_allclose(shift, dy * T_tool[:3, 1], atol=1e-7)
    np.testing.assert_allclose(tr.T_ref_needle[:3, :3], before[:3, :3], atol=1e-7)
    assert cell.close("left") is True                                  # idempotent


@pytest.mark.parametrize("offset", [(0.0023, 0.0), (0.0045, 0.0), (0.0, -0.0012),
                                    (0.0, 0.0112)], ids=["y_half_gap", "y_gap", "z_behind",
                                                          "z_past_jaws"])
def test_no_grasp_when_the_wire_is_not_between_the_jaws(cell, offset):
    """Item 4, grasp physics: jaws off the wire by more than half the open gap across the
    jaws, or with the wire behind the tip or beyond the jaws' length, close on nothing:
    close returns False and the needle does not move."""
    dy, dz = offset
    before = cell.truth().T_ref_needle
    cell.move("left", _above(before, 2.4, dy=dy, dz=dz))
    assert cell.close("left") is False
    assert not cell.jaw_open("left")
    tr = cell.truth()
    np.testing.assert_array_equal(tr.T_ref_needle, before)
    assert tr.held_by == () and tr.T_tool_needle == {}


def test_closing_squares_a_slightly_crooked_wire(cell):
    """Item 4, grasp physics: a wire whose tangent lies a few degrees off the jaw faces
    (turned about the gripper's axis) is turned about that axis through the grasp point
    until it lies in the faces' plane; a larger misalignment is kept."""
    for deg, squared in ((3.0, True), (20.0, False)):
        cell.open("left")
        turn = make_transform(Rotation.from_euler("z", deg, degrees=True))
        T = _above(cell.truth().T_ref_needle, 2.4) @ turn
        cell.move("left", T)
        assert cell.close("left")
        G = cell.truth().T_tool_needle["left"]
        t = G[:3, :3] @ cell.needle.tangent(2.4)
        angle = math.degrees(math.atan2(abs(t[1]), abs(t[0])))
        assert angle == pytest.approx(0.0 if squared else deg, abs=0.2)
        np.testing.assert_allclose(transform_points(G, cell.needle.point(2.4)[None])[0],
                                   [0.0, 0.0, -0.0005], atol=2e-5)


# -- carrying, release, hand-off ----------------------------------------------------------
def test_held_needle_moves_rigidly_in_small_increments(cell):
    """Item 4, move: the gripper goes along a straight line and a slerp in increments of
    at most 1 mm and 2 deg, ending exactly at the target; a held needle moves rigidly
    with it (T_tool_needle constant at every increment), and on_step sees every
    increment."""
    _pickup(cell, "left", 2.4)
    G = cell.truth().T_tool_needle["left"]
    start = cell.gripper_pose("left")
    target = start @ make_transform(Rotation.from_euler("xz", [15.0, 25.0], degrees=True),
                                    [0.002, -0.003, -0.012])
    seen = []

    def on_step(c: NeedleCell) -> None:
        seen.append((c.gripper_pose("left"), c.truth().T_tool_needle["left"]))

    cell.move("left", target, on_step=on_step)
    dist = np.linalg.norm(target[:3, 3] - start[:3, 3])
    angle = Rotation.from_matrix(start[:3, :3].T @ target[:3, :3]).magnitude()
    assert len(seen) == max(math.ceil(dist / 0.001), math.ceil(angle / math.radians(2)))
    poses = np.array([start] + [p for p, _ in seen])
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    turns = Rotation.from_matrix(poses[:-1, :3, :3]).inv() * Rotation.from_matrix(
        poses[1:, :3, :3])
    assert steps.max() <= 0.001 + 1e-12 and turns.magnitude().max() <= math.radians(2) + 1e-9
    for _, g in seen:
        np.testing.assert_allclose(g, G, atol=1e-12)
    np.testing.assert_allclose(cell.gripper_pose("left"), target, atol=1e-12)
    # the tip's path is the straight line
    off = np.cross(poses[:, :3, 3] - start[:3, 3], (target - start)[:3, 3] / dist)
    assert np.abs(off).max() < 1e-9


def test_released_needle_stays(cell):
    """Item 4, open: a released needle keeps its pose when the gripper moves away; the
    jaws are open and hold nothing."""
    _pickup(cell, "left", 2.4)
    cell.move("left", cell.gripper_pose("left") @ make_transform(t=[0.0, 0.0, -0.01]))
    here = cell.truth().T_ref_needle
    cell.open("left")
    assert cell.jaw_open("left") and cell.truth().held_by == ()
    cell.move("left", cell.gripper_pose("left") @ make_transform(t=[0.0, 0.0, -0.01]))
    np.testing.assert_array_equal(cell.truth().T_ref_needle, here)


def test_hand_off(cell):
    """Item 4, hand-off (seed 002 §III.D, Fig. 6): the first gripper lifts the needle, the
    second closes on it (both hold it), the first opens and moves away: the needle stays
    put with the second, and then follows the second."""
    _pickup(cell, "left", 2.4)
    cell.move("left", cell.gripper_pose("left") @ make_transform(t=[0.0, 0.0, -0.01]))
    lifted = cell.truth().T_ref_needle
    cell.move("right", _above(lifted, 0.7))
    assert cell.close("right")
    assert cell.truth().held_by == ("left", "right")
    cell.open("left")
    cell.move("left", cell.gripper_pose("left") @ make_transform(t=[0.0, 0.0, -0.015]))
    tr = cell.truth()
    assert tr.held_by == ("right",)
    np.testing.assert_allclose(tr.T_ref_needle, lifted, atol=1e-8)
    G = tr.T_tool_needle["right"]
    cell.move("right", cell.gripper_pose("right") @ make_transform(t=[0.003, 0.0, -0.005]))
    np.testing.assert_allclose(cell.truth().T_tool_needle["right"], G, atol=1e-12)
    assert not np.allclose(cell.truth().T_ref_needle, lifted)


def test_moving_one_of_two_holders_tears_the_needle_from_the_other(cell):
    """Item 4, move with both holding: moving one gripper tears the needle out of the
    other's jaws: that hold is released (its jaws stay closed, on nothing) and the needle
    follows the moving one."""
    _pickup(cell, "left", 2.4)
    cell.move("right", _above(cell.truth().T_ref_needle, 0.7))
    assert cell.close("right")
    G = cell.truth().T_tool_needle["right"]
    cell.move("right", cell.gripper_pose("right") @ make_transform(t=[0.0, 0.0, -0.005]))
    tr = cell.truth()
    assert tr.held_by == ("right",) and not cell.jaw_open("left")
    np.testing.assert_allclose(tr.T_tool_needle["right"], G, atol=1e-12)
    cell.images()
    assert cell.last_frame.opening == {"left": 0.0, "right": cell.needle.wire_diameter}


# -- reach ------------------------------------------------------------------------------
@pytest.mark.parametrize("limit", ["max_insertion", "min_insertion", "max_wrist"])
def test_moving_past_reach_stops_at_the_last_good_increment(cell, limit):
    """Item 4, reach: a move whose path leaves the arm's workspace raises CellError naming
    the limit; the gripper (and the needle it holds) stays at the last reachable
    increment, within one increment of the limit; reachable() names the same limit for
    the target."""
    _pickup(cell, "right", 0.7)
    reach = cell.arm_reach("right")
    start = cell.gripper_pose("right")
    shaft = reach.wrist(start).shaft
    if limit == "max_wrist":       # bend the jaws 90 deg further from the shaft
        axis = np.cross(start[:3, 2], shaft)
        target = start.copy()
        target[:3, :3] = Rotation.from_rotvec(-math.radians(90) * axis / np.linalg.norm(axis)
                                              ).as_matrix() @ start[:3, :3]
    else:
        target = start.copy()
        target[:3, 3] += (0.1 if limit == "max_insertion" else -0.1) * shaft
    ok, why = cell.reachable("right", target)
    assert not ok and why.startswith(limit)
    G = cell.truth().T_tool_needle["right"]
    with pytest.raises(CellError, match=f"move 'right'.*{limit}"):
        cell.move("right", target)
    last = cell.gripper_pose("right")
    assert cell.reachable("right", last) == (True, "")
    if limit == "max_insertion":
        assert reach.max_insertion - 0.001 <= reach.insertion(last) <= reach.max_insertion
    elif limit == "min_insertion":
        assert reach.min_insertion <= reach.insertion(last) <= reach.min_insertion + 0.001
    else:
        w = reach.wrist(last)
        worst = max(abs(w.pitch) - reach.max_wrist_pitch, abs(w.yaw) - reach.max_wrist_yaw)
        assert -math.radians(2.5) <= worst <= 0.0
    np.testing.assert_allclose(cell.truth().T_tool_needle["right"], G, atol=1e-12)


def _lnd_pose(reach: ArmReach, shaft: np.ndarray, depth: float, roll: float, pitch: float,
              yaw: float) -> np.ndarray:
    """Forward kinematics of the wrist model: the tool pose for the shaft direction
    ``shaft``, the pitch axis ``depth`` m from the RCM along it, and the three joints."""
    s = shaft / np.linalg.norm(shaft)
    a = np.cross([1.0, 0.0, 0.0], s)
    a /= np.linalg.norm(a)
    S = np.column_stack([a, np.cross(s, a), s])
    R_link = S @ Rotation.from_euler("ZY", [roll, pitch]).as_matrix()
    R = R_link @ Rotation.from_euler("X", yaw).as_matrix()
    hinge = reach.rcm + depth * s + reach.pitch_to_yaw * R_link[:, 2]
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = hinge + reach.yaw_to_tip * R[:, 2]
    return T


@pytest.mark.parametrize("joints_deg", [(0, 0, 0), (30, 40, -20), (-120, -75, 60),
                                        (170, 10, 79), (-45, 70, 70)])
def test_the_wrist_model_inverts_its_own_kinematics(joints_deg):
    """Item 4, reach (the da Vinci Large Needle Driver's wrist): for a tool pose built from
    a shaft direction and roll, pitch and yaw, with the 9.1 mm pitch-to-hinge and 9.5 mm
    hinge-to-tip links, ArmReach.wrist recovers the joints and the shaft to 1e-6."""
    reach = ArmReach(rcm=np.array([0.01, -0.02, -0.01]))
    roll, pitch, yaw = np.radians(joints_deg)
    shaft = np.array([0.3, -0.1, 1.0])
    T = _lnd_pose(reach, shaft, 0.11, roll, pitch, yaw)
    w = reach.wrist(T)
    assert (w.pitch, w.yaw) == pytest.approx((pitch, yaw), abs=1e-6)
    np.testing.assert_allclose(w.shaft, shaft / np.linalg.norm(shaft), atol=1e-6)
    assert w.bend == pytest.approx(math.acos(math.cos(pitch) * math.cos(yaw)), abs=1e-6)


def test_the_wrist_reaches_what_the_needle_driver_reaches():
    """Item 4, reach: with the Large Needle Driver's limits (pitch and yaw +-80 deg) the
    jaws bend 83 deg from the shaft with pitch and yaw at 70 deg each, but not with the
    pitch at 85 deg (refused naming max_wrist_pitch) nor the yaw at -82 deg
    (max_wrist_yaw); a pitch of 78 deg passes, but not with a 3 deg margin; an unbent
    tool pointing from the RCM has both joints at zero."""
    reach = ArmReach(rcm=np.zeros(3), max_insertion=0.3)
    shaft = np.array([0.0, 0.2, 1.0])
    ok = _lnd_pose(reach, shaft, 0.12, 0.4, math.radians(70), math.radians(70))
    assert reach.reachable(ok) == (True, "")
    assert math.degrees(reach.wrist(ok).bend) == pytest.approx(83.2, abs=0.1)
    ok_pitch, why = reach.reachable(_lnd_pose(reach, shaft, 0.12, 0.0, math.radians(85), 0.0))
    assert not ok_pitch and why.startswith("max_wrist_pitch") and "85.0 deg" in why
    ok_yaw, why = reach.reachable(_lnd_pose(reach, shaft, 0.12, 1.0, 0.2, math.radians(-82)))
    assert not ok_yaw and why.startswith("max_wrist_yaw") and "-82.0 deg" in why
    near = _lnd_pose(reach, shaft, 0.12, 0.0, math.radians(78), 0.0)
    assert reach.reachable(near) == (True, "")        # a plan's margin keeps off the limit
    ok_margin, why = reach.reachable(near, margin=math.radians(3))
    assert not ok_margin and "less a 3.0 deg margin" in why
    straight = _lnd_pose(reach, shaft, 0.12, 0.3, 0.0, 0.0)
    w = reach.wrist(straight)
    assert abs(w.pitch) < 1e-9 and abs(w.yaw) < 1e-9 and w.bend < 1e-6


def test_trial_like_park_poses_reach_the_needle(cell):
    """Item 4, reach: the example cell's arms can reach down onto the needle lying on the
    pad with the jaws across the wire (the pick-up pose is reachable by both arms)."""
    T_N = cell.truth().T_ref_needle
    for name, phi in (("left", 2.4), ("right", 0.7)):
        assert cell.reachable(name, _above(T_N, phi)) == (True, "")


# -- the drive's truth --------------------------------------------------------------------
def _drive_cell(example, depth=0.005):
    """A cell whose right gripper holds the needle at the start of a drive across the
    incision planned with control/needle/drive.py (eqs. 2-4), and that drive."""
    scene, _ = example
    pad, nd, g = scene.pads[0], scene.needles[0], scene.grippers[1]
    (a, b) = pad.incision
    ends = transform_points(pad.T_ref_pad, np.array([[*a, 0.0], [*b, 0.0]]))
    T_ref_S = tissue_frame(ends[0], ends[1], pad.T_ref_pad[:3, 2])
    geometry = SutureGeometry.for_needle(nd.needle, depth)
    # w1 = pi/2: the cell's jaws close along y (the sim's Gripper), needle_grasp's w1 = 0
    # holds the wire along y (control/needle/grasp.py's module docstring)
    G_TN = grasp_transform(0.003, math.pi / 2, 0.0, 0.35, nd.needle.radius)
    drive = plan_drive(np.eye(4), T_ref_S, geometry, 40, G_TN=G_TN, overshoot=0.003)
    sc = replace(scene, needles=(replace(nd, T_ref_needle=T_ref_S @ drive.G_SN[0]),),
                 grippers=(replace(g, T_ref_tool=drive.G_PT[0]),))
    cell = NeedleCell(sc, {g.name: LOOSE})
    assert cell.close(g.name)
    return cell, drive, T_ref_S, geometry, G_TN


def test_entry_and_exit_truth_on_a_planned_drive(example):
    """Item 4, truth: driving the needle about its own centre along the planned drive
    (eq. 3 gripper poses) records the entry where the tip went down through the pad's
    surface and the exit where it came back up: the planned entry g and exit f (eq. 4)
    within 0.05 mm; the needle is in the tissue during and after the drive, and
    out_of_tissue_after_pull only once a further turn and a lift have pulled it out."""
    cell, drive, T_ref_S, geometry, G_TN = _drive_cell(example)
    tr = cell.truth()
    assert tr.entry is None and tr.exit is None and not tr.in_tissue
    for k, T in enumerate(drive.G_PT[1:], start=1):
        cell.move("right", T)
        if k == len(drive.G_PT) // 2:
            mid = cell.truth()
            assert mid.in_tissue and mid.entry is not None and mid.exit is None
    tr = cell.truth()
    np.testing.assert_allclose(tr.entry, transform_points(T_ref_S, geometry.entry[None])[0],
                               atol=5e-5)
    np.testing.assert_allclose(tr.exit, transform_points(T_ref_S, geometry.exit[None])[0],
                               atol=5e-5)
    assert tr.in_tissue and not tr.out_of_tissue_after_pull
    # pull: turn on about the needle's centre until the swage is out, then lift
    alphas = np.linspace(drive.alphas[-1], geometry.alpha_swage_out + 0.2, 20)
    for T in T_ref_S @ G_SN(alphas, geometry.h) @ invert(G_TN):
        cell.move("right", T)
    cell.move("right", make_transform(t=0.01 * T_ref_S[:3, 1]) @ cell.gripper_pose("right"))
    tr2 = cell.truth()
    assert not tr2.in_tissue and tr2.out_of_tissue_after_pull
    np.testing.assert_array_equal(tr2.entry, tr.entry)
    np.testing.assert_array_equal(tr2.exit, tr.exit)


# -- reported poses ------------------------------------------------------------------------
def test_kinematic_error_offsets_the_reported_pose_only(example):
    """Item 4, kinematic error: a gripper's reported pose is E @ its true pose; the
    images and the truth are those of the true poses (the same bytes as a cell without the
    error), a move's target is a reported pose, and reach is judged in the reported
    frame."""
    scene, arms = example
    E = make_transform(Rotation.from_euler("xyz", [1.0, -0.5, 0.8], degrees=True),
                       [0.0015, -0.001, 0.002])
    bad = NeedleCell(scene, arms, kinematic_error={"left": E})
    good = NeedleCell(scene, arms)
    T_true = good.gripper_pose("left")
    np.testing.assert_allclose(bad.gripper_pose("left"), E @ T_true, atol=1e-15)
    np.testing.assert_array_equal(bad.gripper_pose("right"), good.gripper_pose("right"))
    np.testing.assert_array_equal(bad.true_gripper_pose("left"), T_true)
    a, b = bad.images(), good.images()
    assert all(a[c].tobytes() == b[c].tobytes() for c in bad.cameras)
    target = bad.gripper_pose("left") @ make_transform(t=[0.0, 0.0, 0.004])
    bad.move("left", target)
    np.testing.assert_allclose(bad.gripper_pose("left"), target, atol=1e-12)
    np.testing.assert_allclose(bad.true_gripper_pose("left"), invert(E) @ target, atol=1e-12)
    assert bad.reachable("left", target) == arms["left"].reachable(target)


# -- images ------------------------------------------------------------------------------
def test_images_are_new_frames_with_the_jaw_state(cell):
    """Item 4, images: every call renders every camera of the current state as a new
    frame (a new noise draw), keeps the frame and its truth as last_frame, and draws the
    jaws open, closed on the wire, or shut on nothing."""
    first = cell.images()
    assert set(first) == {"left", "right"} and first["left"].shape == (480, 640)
    assert cell.last_frame.frame == 0
    second = cell.images()
    assert cell.last_frame.frame == 1 and cell.frame == 2
    assert first["left"].tobytes() != second["left"].tobytes()
    assert cell.last_frame.opening == {"left": 0.004, "right": 0.004}
    _pickup(cell, "left", 2.4)
    cell.close("right")
    cell.images()
    assert cell.last_frame.opening == {"left": 0.001, "right": 0.0}
    np.testing.assert_array_equal(cell.last_frame.T_ref_needle["ct1"],
                                  cell.truth().T_ref_needle)
    assert cell.last_frame.needle_truth["left"]["ct1"].visible_fraction < 1.0  # jaws on it


def test_an_exposure_renders_the_state_it_was_taken_in(cell):
    """Issue 36, the streamed drive: ``expose()`` takes the state now (a new frame
    number); rendered after the cell has moved, the frame still shows that state, as a
    camera's exposure would, and ``images()`` is an exposure rendered at once."""
    before = cell.gripper_pose("left")
    render = cell.expose()
    T = before.copy()
    T[:3, 3] += [0.0, 0.0, 0.003]
    cell.move("left", T)
    render()
    assert cell.last_frame.frame == 0 and cell.frame == 1
    np.testing.assert_allclose(cell.last_frame.T_ref_tool["left"], before, atol=1e-12)
    cell.images()
    assert cell.last_frame.frame == 1
    np.testing.assert_allclose(cell.last_frame.T_ref_tool["left"], cell.gripper_pose("left"),
                               atol=1e-12)


def test_the_jaws_aligning_a_needle_on_the_pad_make_no_entry(cell):
    """The truth's entry is a bite an arm makes: jaws tilted 40 deg that close on a
    needle lying on the pad, 4.5 deg crooked, turn the wire into their faces about their
    own axis, which dips the tip 0.3 mm below the surface (no contact model); that is no
    entry (it was taken for one, 20-38 mm from the incision, on validation trials
    1000079, 1000115, 1000452). The held needle moved down through the pad afterwards
    makes one."""
    T = (_above(cell.truth().T_ref_needle, 1.2)
         @ make_transform(Rotation.from_euler("x", 40.0, degrees=True))
         @ make_transform(Rotation.from_euler("z", 4.5, degrees=True)))
    cell.move("left", T)
    assert cell.close("left")
    tip = transform_points(cell.truth().T_ref_needle, cell.needle.tip[None])
    h, over = cell._heights(tip)
    assert h[0] < -2e-4 and over[0], h
    assert cell.truth().entry is None
    n = cell._T_pad_ref[2, :3]              # the pad's normal (reference frame)
    for shift in (0.002, -0.006):           # lifted clear, then down through the pad
        T = cell.gripper_pose("left")
        T[:3, 3] += shift * n
        cell.move("left", T)
    assert cell.truth().entry is not None


def test_bad_input_is_refused(example):
    """Item 4, errors: a scene with no pad or three grippers, reach missing for a gripper,
    an unknown gripper name, or a target that is not a rigid transform give a clear
    CellError; the refused call changes nothing."""
    scene, arms = example
    with pytest.raises(CellError, match="exactly one needle and one pad"):
        NeedleCell(replace(scene, pads=()), arms)
    g3 = replace(scene.grippers[0], name="third")
    with pytest.raises(CellError, match="one or two grippers"):
        NeedleCell(replace(scene, grippers=(*scene.grippers, g3)), {**arms, "third": LOOSE})
    with pytest.raises(CellError, match="reach must be given"):
        NeedleCell(scene, {"left": arms["left"]})
    with pytest.raises(CellError, match="kinematic_error names unknown"):
        NeedleCell(scene, arms, kinematic_error={"middle": np.eye(4)})
    with pytest.raises(CellError, match="starts out of its arm's reach: max_insertion"):
        NeedleCell(scene, {**arms, "left": replace(arms["left"], max_insertion=0.05)})
    cell = NeedleCell(scene, arms)
    with pytest.raises(CellError, match="unknown gripper 'middle'"):
        cell.close("middle")
    before = cell.gripper_pose("left")
    skew = before.copy()
    skew[0, 0] += 0.1
    with pytest.raises(CellError, match="move target"):
        cell.move("left", skew)
    np.testing.assert_array_equal(cell.gripper_pose("left"), before)
    with pytest.raises(CellError, match="max_insertion"):
        ArmReach(rcm=np.zeros(3), min_insertion=0.1, max_insertion=0.05)


def test_the_quick_reach_pass_agrees_with_the_solved_wrist():
    """Item 4, reach: ArmReach.reachable settles most poses by a bound on the jaws' bend
    before solving the wrist; over 3000 random tool poses, with and without a planning
    margin, its verdict is the one the solved joints and the insertion give."""
    reach = ArmReach(rcm=np.zeros(3), max_insertion=0.3)
    rng = np.random.default_rng(17)
    for i in range(3000):
        T = np.eye(4)
        T[:3, :3] = Rotation.random(random_state=i).as_matrix()
        T[:3, 3] = rng.normal(size=3) * 0.03 + [0.0, 0.0, 0.12]
        margin = math.radians(3.0) if i % 2 else 0.0
        w = reach.wrist(T)
        solved = (abs(w.pitch) <= reach.max_wrist_pitch - margin
                  and abs(w.yaw) <= reach.max_wrist_yaw - margin
                  and reach.min_insertion <= w.insertion <= reach.max_insertion)
        assert reach.reachable(T, margin)[0] == solved, i


def test_reachable_all_answers_as_reachable_one_by_one(cell):
    """Item 4, reach, for planners asking about thousands of poses: ArmReach.reachable_all
    and NeedleCell.reachable_all give, for 3000 random tool poses at once (with and
    without a planning margin, some beyond the insertion range), the verdict of
    reachable asked pose by pose; a batch that is not N x 4 x 4 poses is refused."""
    reach = ArmReach(rcm=np.zeros(3), max_insertion=0.2)
    rng = np.random.default_rng(23)
    T = np.tile(np.eye(4), (3000, 1, 1))
    T[:, :3, :3] = Rotation.random(3000, random_state=5).as_matrix()
    T[:, :3, 3] = rng.normal(size=(3000, 3)) * 0.05 + [0.0, 0.0, 0.12]
    for margin in (0.0, math.radians(3.0)):
        one = np.array([reach.reachable(P, margin)[0] for P in T])
        assert 0.2 < one.mean() < 0.8             # both verdicts well represented
        np.testing.assert_array_equal(reach.reachable_all(T, margin), one)
    name = cell.grippers[0]
    batch = np.stack([cell.gripper_pose(name)] * 2)
    assert cell.reachable_all(name, batch).tolist() == [cell.reachable(name, batch[0])[0]] * 2
    with pytest.raises(CellError, match="N x 4 x 4"):
        cell.reachable_all(name, batch[0])
