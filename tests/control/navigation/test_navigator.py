"""Issue 4, two-stage navigation (control/navigation/navigator.py): with exact poses from the
simulated cell's geometry the navigator goes approach -> adjust -> targets -> done, each
TCP goal puts the steered frame on its goal, and it holds when a needed pose is missing."""

from __future__ import annotations

import numpy as np

from oralnav.config.daemon import load_config
from oralnav.control.geometry import invert
from oralnav.control.navigation.navigator import NavCalibration, TwoStageNavigator


def _setup():
    cell = load_config().cell
    g = cell.geometry
    calib = NavCalibration(T_B_C=g.T_B_C, T_RM_E0=invert(g.T_tcp_RM) @ g.T_tcp_E0,
                           T_OM_En=g.T_OM_En, T_EM_E=invert(g.T_E_EM))
    entry = invert(g.T_B_OM) @ cell.intraoral_T_B_tcp @ g.T_tcp_E0
    nav = TwoStageNavigator(calib, entry, dict(cell.targets_OM), settle=1)
    return cell, g, nav


def _observe(g, T_B_tcp):
    p = g.poses(T_B_tcp, np.zeros(4))
    T_C_B = invert(g.T_B_C)
    return (T_C_B @ p["T_B_RM"], T_C_B @ p["T_B_OM"], invert(p["T_B_En"]) @ p["T_B_EM"])


def test_stages_run_in_order_and_goals_are_exact() -> None:
    """Moving the TCP exactly to each goal walks through every stage and target, and the
    end-effector ends on each target's position in the base (eq. 8)."""
    cell, g, nav = _setup()
    T = cell.home_T_B_tcp.copy()
    stages, reached = [], []
    for _ in range(40):
        RM, OM, EM = _observe(g, T)
        step = nav.update(RM, OM, EM, T)
        stages.append(step.stage)
        if step.reached:
            p_E = g.poses(T, np.zeros(4))["T_B_E"][:3, 3]
            p_tar = g.T_B_OM[:3, :3] @ cell.targets_OM[step.reached] + g.T_B_OM[:3, 3]
            assert np.linalg.norm(p_E - p_tar) < 1e-9
            reached.append(step.reached)
        if step.stage == "done":
            break
        assert step.goal is not None
        T = step.goal
    assert reached == list(cell.targets_OM)
    order = [s for i, s in enumerate(stages) if i == 0 or s != stages[i - 1]]
    assert order == ["approach", "adjust", "targets", "done"]


def test_goal_corrects_a_tcp_calibration_error() -> None:
    """The visual correction steers by the measured frame: with the arm's reported TCP off
    by 2 mm, repeated steps still bring the truly measured end-effector zero onto the
    entry pose (to a micrometre), where trusting the arm's kinematics would be 2 mm off."""
    cell, g, nav = _setup()
    offset = np.array([0.002, 0.0, 0.0])
    T_true = cell.home_T_B_tcp.copy()
    entry_B = g.T_B_OM @ nav.T_OM_E0_entry
    for _ in range(30):
        RM, OM, EM = _observe(g, T_true)
        T_reported = T_true.copy()
        T_reported[:3, 3] += offset
        step = nav.update(RM, OM, EM, T_reported)
        if step.stage != "approach":
            break
        T_true = step.goal.copy()  # the arm puts its reported TCP at the goal
        T_true[:3, 3] -= offset
    err = np.linalg.norm((T_true @ g.T_tcp_E0)[:3, 3] - entry_B[:3, 3])
    assert err < 1e-6


def test_missing_poses_hold() -> None:
    """No opener pose, or no robot marker during the approach: no goal (the loop holds)."""
    cell, g, nav = _setup()
    RM, OM, EM = _observe(g, cell.home_T_B_tcp)
    assert nav.update(RM, None, EM, cell.home_T_B_tcp).goal is None
    assert nav.update(None, OM, EM, cell.home_T_B_tcp).goal is None


def test_a_selected_target_is_visited_next_then_the_rest_in_order() -> None:
    """Issue 33 (the seed's "select the current suture target"): a target chosen before
    or during the targets stage is the next one reached, then the targets not visited in
    their order; a visited one may be chosen again; an unknown name is a KeyError."""
    cell, g, nav = _setup()
    names = list(cell.targets_OM)
    nav.select(names[2])  # before the start: the first one visited
    T = cell.home_T_B_tcp.copy()
    reached = []
    for _ in range(60):
        RM, OM, EM = _observe(g, T)
        step = nav.update(RM, OM, EM, T)
        if step.reached:
            reached.append(step.reached)
            if len(reached) == 2:
                nav.select(names[2])  # again, though visited
        if step.stage == "done":
            break
        T = step.goal
    assert reached == [names[2], names[0], names[2], names[1], names[3]]
    try:
        nav.select("nope")
    except KeyError as exc:
        assert "no suture target 'nope'" in str(exc)
    else:
        raise AssertionError("an unknown target was accepted")
