"""Issue 6, item 5: guided insertion in the daemon core, on the virtual clock (the control
loop stepped in-process, the supervisor at 50 Hz). Planning is atomic: a bad scene, a bad
registration or a failed placement leaves the previous plan in place. Starting is refused
(nothing sent, the loop holding) without a plan, a hand-eye calibration or a fresh opener
pose, with the head outside the fixture, while a procedure runs or a stop is latched.
While guiding, the core publishes T_B_F from the tracked opener and refuses a new plan
and a procedure start; the loop refuses a plan change too; any stop ends guidance and a
reset never resumes it."""

from __future__ import annotations

from pathlib import Path

import anyio
import numpy as np
import pytest

from oralnav.config.daemon import load_config
from oralnav.daemon.core import GUIDE_POSE, DaemonCore
from oralnav.daemon.guidance import GuidePlanError, NoSafePlacement, plan_insertion
from oralnav.daemon.schemas import SutureTarget
from oralnav.drivers.arm.sim import SimArm
from oralnav.drivers.clock import VirtualClock
from oralnav.realtime.control_loop import GUIDE, HOLD, LoopSettings
from oralnav.realtime.control_process import InProcessControl
from oralnav.safety.errors import StateError
from oralnav.safety.limits import SpeedLimiter
from oralnav.safety.watchdogs import WatchdogSet
from oralnav.sim.world.hand import ScriptedHand
from tests.daemon.guide_cell import (
    SMALL_SCENE,
    T_B_C,
    T_B_F,
    T_C_OM,
    T_OM_F,
    BaseFrameHand,
    rigid,
    small_scene,
    start_pose,
)

SETTINGS = LoopSettings(rate_hz=500.0, stale_pose=0.1, driver_silence=0.05)
P = SETTINGS.period
SEED = 7


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    return small_scene(tmp_path_factory.mktemp("scene"))


@pytest.fixture(scope="module")
def draft(scene):
    return plan_insertion(scene, T_OM_F, "test", SEED)


class CoreCell:
    """The hand-pushed sim arm, the in-process loop and the core on one virtual clock;
    every 10th period (50 Hz) the tracker reports the opener and the supervisor ticks."""

    def __init__(self, draft, home: np.ndarray | None = None) -> None:
        fx = draft.plan.fixture
        self.clock = VirtualClock(100.0)
        hand = BaseFrameHand(ScriptedHand(fx, push_force=4.0, push_duration=60.0), T_B_F)
        self.arm = SimArm(clock=self.clock, force_source=hand, home=home if home is not None
                          else start_pose(draft.placement.T_C_tool, fx, 0.005))
        anyio.run(self.arm.start)
        self.control = InProcessControl(self.arm, None, SETTINGS, SpeedLimiter(0.25, 0.5))
        self.core = DaemonCore(self.control, WatchdogSet.from_settings(
            load_config().settings.safety, P), clock=self.clock.now, T_B_C=T_B_C)
        self.T_C_OM = T_C_OM
        self.tracking = True
        self._n = 0

    def run(self, periods: int) -> None:
        for _ in range(periods):
            self.clock.advance(P)
            self.control.step(self.clock.now())
            self._n += 1
            if self._n % 10 == 0:
                if self.tracking:
                    self.core.publish_pose(GUIDE_POSE, self.T_C_OM, self.clock.now(),
                                           frame="C")
                self.core.supervise_once(self.clock.now())

    def status(self):
        return self.control.read_status()

    def mode(self) -> int:
        return int(self.control.nav.read()["mode"])

    def tcp_F(self) -> np.ndarray:
        return (np.linalg.inv(T_B_F) @ np.array(self.status()["T_B_tcp"]))[:3, 3]


@pytest.fixture
def cell(draft):
    c = CoreCell(draft)
    c.run(20)
    assert c.core.supervisor.state.value == "READY"
    yield c
    anyio.run(c.control.close)


def test_plan_refusals_keep_the_previous_plan(cell, scene, tmp_path):
    """issue 6, item 5: plan_guide answers the placement and the fixture (frame F); a
    missing or invalid scene, a registration in millimetres, a hole outside the model
    (422) and a scene with no collision-free placement (409) are refused, each with a
    reason, and the plan held before stays, untouched."""
    core = cell.core
    doc = core.plan_guide(str(scene), T_OM_F, "alice", SEED)
    assert doc["placement"]["collision_free"] is True and doc["by"] == "alice"
    assert doc["fixture"]["frame"] == "F" and len(doc["fixture"]["direction"]) == 3
    before = core.guide()["plan"]
    assert before["planned_at"] == doc["planned_at"]
    bad = tmp_path / "bad.toml"
    bad.write_text(SMALL_SCENE.replace("[tool]", "[tool]\nrod_diameter_mm = 4.0"))
    unsafe = tmp_path / "unsafe.toml"
    unsafe.write_text(SMALL_SCENE.replace("rod_radius_mm = 2.0", "rod_radius_mm = 19.0"))
    outside = tmp_path / "outside.toml"
    outside.write_text(SMALL_SCENE.replace("-20.0, 20.0]", "-20.0, 80.0]"))
    mm = T_OM_F.copy()
    mm[:3, 3] *= 1e3
    cases = [(tmp_path / "none.toml", T_OM_F, GuidePlanError, "none.toml"),
             (bad, T_OM_F, GuidePlanError, "rod_diameter_mm"),
             (scene, mm, GuidePlanError, "millimetres"),
             (scene, rigid((0, 0, 0), (0, 0, 0))[:3], GuidePlanError, "T_OM_F"),
             (outside, T_OM_F, GuidePlanError, "outside the model"),
             (unsafe, T_OM_F, NoSafePlacement, "no collision-free placement")]
    for path, T, err, words in cases:
        with pytest.raises(err, match=words):
            core.plan_guide(str(path), T, "bob", SEED)
        assert core.guide()["plan"] == before
    assert issubclass(NoSafePlacement, StateError)          # REST 409
    assert issubclass(GuidePlanError, ValueError)           # REST 422
    assert int(cell.status()["guide_seq"]) == 0             # nothing reached the loop


def test_start_refusals_send_nothing(cell, draft, scene):
    """issue 6, item 5: start_guide is refused (StateError naming why) without a plan,
    without the hand-eye calibration, without an opener pose or with a stale one, while a
    procedure runs and while a stop is latched; each refusal sends nothing to the loop,
    which keeps holding."""
    core = cell.core
    with pytest.raises(StateError, match="no insertion plan"):
        core.start_guide("alice")
    core.plan_guide(str(scene), T_OM_F, "alice", SEED)
    core.T_B_C = None
    with pytest.raises(StateError, match="hand-eye"):
        core.start_guide("alice")
    core.set_hand_eye(T_B_C)
    fresh = CoreCell(draft)
    fresh.tracking = False
    fresh.run(20)
    fresh.core.plan_guide(str(scene), T_OM_F, "alice", SEED)
    with pytest.raises(StateError, match="no pose of the mouth opener"):
        fresh.core.start_guide("alice")
    fresh.core.publish_pose(GUIDE_POSE, T_C_OM, fresh.clock.now(), frame="C")
    fresh.run(1000)                                        # 2 s: older than stale_pose
    with pytest.raises(StateError, match="s old"):
        fresh.core.start_guide("alice")
    anyio.run(fresh.control.close)

    core.set_targets([SutureTarget(name="s1", p_OM=(0.0, 0.01, 0.0))], "alice")
    core.procedure("start", "alice")
    with pytest.raises(StateError, match="procedure is RUNNING"):
        core.start_guide("alice")
    core.procedure("abort", "alice")
    core.estop("alice", "drill")
    cell.run(10)
    with pytest.raises(StateError, match="ESTOP: reset first"):
        core.start_guide("alice")
    st = cell.status()
    assert int(st["guide_seq"]) == 0 and not bool(st["guide_planned"])
    assert cell.mode() == HOLD and core.guide()["phase"] == "idle"


def test_start_outside_the_fixture_is_refused(draft, scene):
    """issue 6, item 5: with the instrument head 10 mm off the planned axis the start is
    refused (the loop would never jump the arm onto the fixture) and nothing is sent."""
    home = start_pose(draft.placement.T_C_tool, draft.plan.fixture, 0.005)
    home[:3, 3] += T_B_F[:3, :3] @ np.array([0.01, 0.0, 0.0])
    c = CoreCell(draft, home=home)
    try:
        c.run(20)
        c.core.plan_guide(str(scene), T_OM_F, "alice", SEED)
        with pytest.raises(StateError, match="outside the virtual fixture"):
            c.core.start_guide("alice")
        assert int(c.status()["guide_seq"]) == 0 and c.mode() == HOLD
    finally:
        anyio.run(c.control.close)


def test_guidance_runs_and_stops_on_the_virtual_clock(cell, draft, scene):
    """issue 6, item 5: after start_guide the loop takes the plan and the core switches to
    GUIDE with T_B_F = T_B_C T_C_OM T_OM_F; the hand feeds the head along the axis. While
    guiding, a new plan and a procedure start are refused, and a plan sent straight to
    the loop is refused there (the running motion goes on). stop_guide holds, removes the
    plan from the loop and drops it."""
    core = cell.core
    core.plan_guide(str(scene), T_OM_F, "alice", SEED)
    core.start_guide("alice")
    assert core.guide()["phase"] == "arming" and cell.mode() == HOLD
    cell.run(20)
    g = core.guide()
    assert g["phase"] == "active" and g["active"] and cell.mode() == GUIDE
    assert np.allclose(cell.control.nav.read()["T_B_F"], T_B_F, atol=1e-9)
    fx = draft.plan.fixture
    s0 = fx.axial(cell.tcp_F())
    cell.run(250)                                          # 0.5 s
    assert s0 - fx.axial(cell.tcp_F()) > 0.01 and fx.radial(cell.tcp_F()) < 0.001
    g = core.guide()
    assert g["to_target_m"] == pytest.approx(fx.axial(cell.tcp_F()), abs=0.003)
    assert g["rod_distance_m"] > 0 and g["lateral_m"] < 0.001
    assert core.status()["guidance"]["phase"] == "active"
    assert core.telemetry()["guidance"]["active"] is True

    with pytest.raises(StateError, match="guided insertion is running"):
        core.plan_guide(str(scene), T_OM_F, "bob", 1)
    core.set_targets([SutureTarget(name="s1", p_OM=(0.0, 0.01, 0.0))], "alice")
    with pytest.raises(StateError, match="guided insertion is running"):
        core.procedure("start", "alice")
    seq = cell.control.set_guide(draft.plan)
    cell.run(2)
    assert cell.control.guide_reply(seq) == "refused" and bool(cell.status()["guide_active"])

    core.stop_guide("alice")
    assert cell.mode() == HOLD
    cell.run(10)
    st = cell.status()
    assert not bool(st["guide_active"]) and not bool(st["guide_planned"])
    sent = int(st["motion_commands"])
    cell.run(50)
    assert int(cell.status()["motion_commands"]) == sent
    assert core.guide()["plan"] is None and core.guide()["last_end"]["reason"] == \
        "stopped by alice"


def test_loop_stop_ends_guidance_and_reset_never_resumes(cell, draft, scene):
    """issue 6, item 5: the patient's model jumps 25 mm sideways (the opener moved): the
    loop's rod alarm latches the stop by itself; the core faults and ends guidance at
    once. After the reset the loop holds (no motion) until the operator starts again;
    the kept plan then restarts from the measured TCP."""
    core = cell.core
    core.plan_guide(str(scene), T_OM_F, "alice", SEED)
    core.start_guide("alice")
    cell.run(300)
    assert core.guide()["phase"] == "active"
    moved = T_B_F @ rigid((0, 0, 0), (0.0, 0.025, 0.0))     # the head now in the wall
    cell.T_C_OM = np.linalg.inv(T_B_C) @ moved @ np.linalg.inv(T_OM_F)
    cell.run(20)
    st = cell.status()
    assert bool(st["latched"]) and b"rod collision alarm" in bytes(st["stop_reason"])
    assert core.supervisor.state.value == "FAULT" and core.guide()["phase"] == "idle"
    assert cell.mode() == HOLD
    cell.T_C_OM = T_C_OM
    cell.run(10)
    core.reset("alice")
    cell.run(100)
    st = cell.status()
    assert not bool(st["latched"]) and not bool(st["guide_active"])
    sent = int(st["motion_commands"])
    cell.run(50)
    assert int(cell.status()["motion_commands"]) == sent and cell.mode() == HOLD
    assert core.supervisor.state.value == "READY"
    core.start_guide("alice")                              # the plan was kept
    cell.run(50)
    assert core.guide()["phase"] == "active" and int(cell.status()["motion_commands"]) > sent
