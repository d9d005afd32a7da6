"""Issue 32: navigation is one listener of the capture pipeline for every cell. It chains
each tracked pose with the arm pose of that pose's capture instant (interpolated in the
arm's measured history), never one of another instant; its goal leads the arm by at most
a set step per tracked frame, so slow tracking is slow, safe motion; and a cell without
what a procedure needs refuses to start it, saying why."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np
import pytest

from oralnav.config.daemon import load_config
from oralnav.control.geometry import invert
from oralnav.daemon.capture_task import TrackedRound
from oralnav.daemon.core import DaemonCore
from oralnav.daemon.navigation_task import ARM_WAIT_S
from oralnav.daemon.schemas import SutureTarget
from oralnav.daemon.service import build_navigation
from oralnav.realtime.control_loop import ARM_SAMPLE_DTYPE
from oralnav.safety.errors import StateError
from oralnav.safety.watchdogs import WatchdogSet
from tests.daemon.lockstep import CAMERA_EVERY, Lockstep, start_procedure


@pytest.fixture
async def cell():
    c = Lockstep()
    await c.start()
    try:
        yield c
    finally:
        await c.close()


def _record_goals(c: Lockstep) -> list[tuple[np.ndarray, np.ndarray]]:
    """Every goal the navigation sends, with the arm's newest measured TCP then."""
    sent: list[tuple[np.ndarray, np.ndarray]] = []
    set_goal = c.core.set_goal

    def recording(T, t_pose, **kw):
        sent.append((np.array(T), np.array(c.control.read_arm_history()["T_B_tcp"][-1])))
        return set_goal(T, t_pose, **kw)

    c.core.set_goal = recording
    return sent


async def test_the_arm_pose_of_the_capture_instant_is_chained(cell: Lockstep) -> None:
    """A round tracked 40 ms after its capture, the arm moving meanwhile: the navigator is
    given the TCP pose the cell rendered (the capture instant's, to 1e-12 m), not the
    newest, which lies more than 0.1 mm away."""
    await start_procedure(cell)
    await cell.run(3 * CAMERA_EVERY)  # moving
    given: list[np.ndarray] = []
    update = cell.nav.navigator.update

    def spy(T_C_RM, T_C_OM, T_En_EM, T_B_tcp):
        given.append(np.array(T_B_tcp))
        return update(T_C_RM, T_C_OM, T_En_EM, T_B_tcp)

    cell.nav.navigator.update = spy
    frames = await cell.cameras.read()
    rendered = np.array(cell.cell.truth()["T_B_tcp"])
    cell.camera_every = 10**9  # no round of its own meanwhile
    await cell.run(20)  # 40 ms of motion between capture and tracking
    newest = cell.control.read_arm_history()["T_B_tcp"][-1]
    await cell.capture.process(cell.source, frames)
    assert len(given) == 1
    assert np.abs(given[0] - rendered).max() < 1e-12
    assert np.linalg.norm(newest[:3, 3] - rendered[:3, 3]) > 1e-4


async def test_each_goal_leads_the_arm_by_at_most_the_step_per_frame(
        cell: Lockstep) -> None:
    """Every goal sent during the approach is within [navigation] max_step (and
    max_turn_deg) of the arm's newest measured TCP; the first ones, far from the entry
    pose, are exactly a full step ahead."""
    nav = cell.cfg.settings.navigation
    sent = _record_goals(cell)
    await start_procedure(cell)
    await cell.run(6 * CAMERA_EVERY)
    assert len(sent) >= 4
    steps = [np.linalg.norm(g[:3, 3] - now[:3, 3]) for g, now in sent]
    turns = [math.degrees(np.arccos(np.clip((np.trace(now[:3, :3].T @ g[:3, :3]) - 1) / 2,
                                            -1, 1))) for g, now in sent]
    assert max(steps) <= nav.max_step + 1e-12
    assert max(turns) <= nav.max_turn_deg + 1e-9
    assert max(steps[:2]) > 0.99 * nav.max_step or max(turns[:2]) > 0.99 * nav.max_turn_deg


async def test_slow_frames_slow_the_robot_and_do_not_stop_it() -> None:
    """Issue 32, item 6: with one tracked frame every 1.5 s (slower than stale_pose, 1 s in
    sim.toml), the procedure still visits every target with TRE < 0.1 mm and no fault;
    between two frames the TCP never moves more than max_step."""
    c = Lockstep(camera_every=750)
    await c.start()
    try:
        await start_procedure(c)
        positions = []
        for _ in range(200):  # at most 300 s of virtual time
            await c.run(c.camera_every)
            positions.append(c.arm.state().T_B_tcp[:3, 3].copy())
            if c.core.procedure_info.get("done") or c.core.supervisor.state.value != "RUNNING":
                break
        info = c.core.procedure_info
        assert info.get("done"), (info, c.core.supervisor.snapshot())
        assert max(info["tre_mm"].values()) < 0.1
        moves = np.linalg.norm(np.diff(positions, axis=0), axis=1)
        assert moves.max() <= c.cfg.settings.navigation.max_step + 1e-6
    finally:
        await c.close()


async def test_inside_the_mouth_a_step_pairs_the_effector_with_its_captures_opener(
        cell: Lockstep) -> None:
    """Issue 32 (time): the endoscope's round (the effector) and the stereo pair's (the
    opener) come from separate sources, the endoscope's first. Its step waits for the
    opener of the same capture, so the goal is as old as that capture, not a frame period
    older; each effector capture makes one step; the wait is one opener round at most."""
    await start_procedure(cell)
    await cell.run(2 * CAMERA_EVERY)
    cell.camera_every = 10**9  # only the rounds this test sends
    cell.nav.navigator.stage = "adjust"   # inside the mouth: the endoscope steers
    sent: list[float] = []
    set_goal = cell.core.set_goal

    def recording(T, t_pose, **kw):
        sent.append(t_pose)
        return set_goal(T, t_pose, **kw)

    cell.core.set_goal = recording
    T_OM = cell.core.pose("T_C_OM")["T"]
    T_EM = np.eye(4)
    T_EM[2, 3] = 0.04                      # the effector field 4 cm before the endoscope

    async def round_(name: str, pose: str, T: np.ndarray, t: float) -> None:
        frame = "En" if pose == "T_En_EM" else "C"
        cell.core.publish_pose(pose, T, t, frame=frame)
        await cell.nav.on_tracked(TrackedRound(name, {pose: t}))

    await cell.run(30)
    s1 = cell.clock.now() - 0.02          # a capture the arm history holds
    await round_("endoscope", "T_En_EM", T_EM, s1)
    assert sent == []                      # the opener of s1 is not tracked yet
    await round_("stereo", "T_C_OM", T_OM, s1)
    assert sent == [s1]                    # paired: the goal is as old as s1
    await cell.run(30)
    await round_("stereo", "T_C_OM", T_OM, cell.clock.now() - 0.02)
    assert sent == [s1]                    # no new effector capture: no new step
    await cell.run(30)
    s2 = cell.clock.now() - 0.02
    await round_("endoscope", "T_En_EM", T_EM, s2)
    late = s2 - 0.01                       # the stereo pair lags: its next round is older
    await round_("stereo", "T_C_OM", T_OM, late)
    assert sent == [s1, late]              # stepped on that round all the same
    assert cell.core.supervisor.state.value == "RUNNING"


async def test_a_frame_older_than_the_arm_history_faults(cell: Lockstep) -> None:
    """Issue 32 (bad input: a frame older than the arm history): FAULT naming the timing,
    and no goal from it."""
    await start_procedure(cell)
    await cell.run(2 * CAMERA_EVERY)
    oldest = float(cell.control.read_arm_history()["t"][0])
    sent = _record_goals(cell)
    rec = cell.core.pose("T_C_RM")
    cell.core.publish_pose("T_C_RM", rec["T"], oldest - 0.5, frame="C")
    await cell.nav.on_tracked(TrackedRound("cell", {"T_C_RM": oldest - 0.5}))
    cell.core.supervise_once(cell.clock.now())
    assert cell.core.supervisor.state.value == "FAULT"
    why = str(cell.core.supervisor.snapshot()["reasons"])
    assert "navigation timing" in why and "older than the arm history" in why
    assert sent == []


async def test_a_frame_the_arm_never_reports_faults_after_the_wait(cell: Lockstep) -> None:
    """Issue 32 (bad input: a camera clock that jumps ahead): a frame stamped later than
    anything the arm reports waits ARM_WAIT_S for the arm, then FAULT naming it."""
    await start_procedure(cell)
    await cell.run(2 * CAMERA_EVERY)
    ahead = cell.clock.now() + 0.5
    for name in ("T_C_RM", "T_C_OM"):  # the stereo pair's round: both fields, one stamp
        cell.core.publish_pose(name, cell.core.pose(name)["T"], ahead, frame="C")
    await cell.nav.on_tracked(TrackedRound("cell", {"T_C_RM": ahead, "T_C_OM": ahead}))
    cell.core.supervise_once(cell.clock.now())
    why = str(cell.core.supervisor.snapshot()["reasons"])
    assert "has not reported the frame's instant" in why
    assert f"after waiting {ARM_WAIT_S * 1e3:.0f} ms" in why


async def test_a_gap_in_the_arm_history_faults(cell: Lockstep) -> None:
    """Issue 32 (bad input: an arm history with a gap): a frame captured while the arm
    was silent longer than arm_history_gap is not chained: FAULT naming the gap."""
    await start_procedure(cell)
    await cell.run(CAMERA_EVERY)
    real = cell.control.read_arm_history

    def with_gap():
        h = real()
        keep = (h["t"] < h["t"][-1] - 0.06) | (h["t"] > h["t"][-1] - 0.01)
        return h[keep]

    cell.control.read_arm_history = with_gap
    t_gap = float(real()["t"][-1]) - 0.03
    rec = cell.core.pose("T_C_RM")
    cell.core.publish_pose("T_C_RM", rec["T"], t_gap, frame="C")
    await cell.nav.on_tracked(TrackedRound("cell", {"T_C_RM": t_gap}))
    cell.core.supervise_once(cell.clock.now())
    why = str(cell.core.supervisor.snapshot()["reasons"])
    assert "gap of" in why and "navigation timing" in why


class _NoControl:
    """A control port that is never asked for anything (the refusals come first)."""

    def read_arm_history(self):
        return np.zeros(0, dtype=ARM_SAMPLE_DTYPE)


def _hardware_config(tmp_path: Path, extra: str = "") -> Path:
    shipped = Path(load_config().path).parent
    path = tmp_path / "cell.toml"
    path.write_text(f"""
[cell]
backend = "hardware"
rig = "{shipped / 'rigs/stereo.toml'}"
fields = "{shipped / 'fields/cell.toml'}"
{extra}
""")
    return path


def _core(cfg) -> DaemonCore:
    return DaemonCore(_NoControl(), WatchdogSet.from_settings(cfg.settings.safety, 0.002))


def test_a_hardware_cell_without_calibration_refuses_to_start(tmp_path: Path) -> None:
    """Issue 32, item 7: on a hardware cell without the navigation calibration files the
    procedure start is refused (StateError: 409) with the reason, and the state stays."""
    cfg = load_config(_hardware_config(tmp_path))
    core = _core(cfg)
    capture, nav, cell = build_navigation(cfg, core)
    assert cell is None and capture.sources == []
    core.set_targets([SutureTarget(name="a", p_OM=(0.1, 0.02, 0.01))], "test")
    words = "no navigation calibration (no calibration file for hand_eye, endoscope_opener"
    with pytest.raises(StateError, match=re.escape(words)):
        core.procedure("start", "test")
    assert core.supervisor.state.value != "RUNNING"


def test_refusals_name_what_the_cell_lacks() -> None:
    """Issue 32, item 7: with the calibration, a cell without an entry pose, without
    cameras, or without an endoscope tracking the effector says which; a complete one
    has nothing to say."""
    from oralnav.daemon.navigation_task import NavigationTask, nav_calibration

    cfg = load_config()
    cal = nav_calibration(cfg.calibrations)
    full = {"T_C_RM", "T_C_OM", "T_C_EM", "T_En_EM"}

    entry_pose = cfg.entry_T_OM_E0()

    def refusal(entry=entry_pose, tracked=full) -> str:
        return NavigationTask(_core(cfg), calibration=cal, entry_T_OM_E0=entry,
                              settings=cfg.settings.navigation, tracked=tracked).refusal()

    assert refusal() == ""
    assert "no intra-oral entry pose ([navigation] entry_T_OM_E0" in refusal(entry=None)
    assert "no camera is configured" in refusal(tracked=set())
    assert "no camera tracks T_En_EM" in refusal(tracked=full - {"T_En_EM"})


def test_the_entry_pose_comes_from_the_configuration(tmp_path: Path) -> None:
    """Issue 32: [navigation] entry_T_OM_E0 is the entry pose; on the simulated cell
    without it, the cell file's intra-oral pose taken to the opener; a non-rigid one is
    refused at load naming the key."""
    cfg = load_config()
    g = cfg.cell.geometry
    np.testing.assert_allclose(cfg.entry_T_OM_E0(),
                               invert(g.T_B_OM) @ cfg.cell.intraoral_T_B_tcp @ g.T_tcp_E0)
    T = np.eye(4)
    T[:3, 3] = [0.09, 0.03, -0.02]
    given = load_config(_hardware_config(
        tmp_path, f"[navigation]\nentry_T_OM_E0 = {T.tolist()}\nmax_step = 0.002\n"))
    np.testing.assert_array_equal(given.entry_T_OM_E0(), T)
    assert given.settings.navigation.max_step == 0.002
    assert load_config(_hardware_config(tmp_path)).entry_T_OM_E0() is None
    T[0, 0] = 2.0
    from oralnav.config.errors import ConfigError
    with pytest.raises(ConfigError, match=r"\[navigation\] entry_T_OM_E0: not a proper rotation"):
        load_config(_hardware_config(tmp_path, f"[navigation]\nentry_T_OM_E0 = {T.tolist()}"))
