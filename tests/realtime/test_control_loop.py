"""Issue 4, control loop: it servoes toward the goal within the speed limits, and every
fault it watches (stop request, arm disconnect, protective stop, silent or
faulted end-effector, late periods) stops the arm within two control periods of detection,
with no motion command after the stop. On the virtual clock, in-process."""

from __future__ import annotations

import threading
from collections.abc import Callable

import anyio
import numpy as np
import pytest

from oralnav.drivers.arm.sim import SimArm
from oralnav.drivers.clock import VirtualClock
from oralnav.drivers.effector.sim import SimEffector
from oralnav.realtime.control_loop import (
    ARM_SAMPLE_DTYPE,
    CMD_DTYPE,
    LATENCY_DTYPE,
    MOVE,
    NAV_DTYPE,
    STATUS_DTYPE,
    ControlLoop,
    LoopSettings,
)
from oralnav.realtime.control_process import ControlProcess, DriverSpec, ProcessSpec
from oralnav.realtime.shm import SharedRecord, SharedRing, encode_reason
from oralnav.safety.limits import SpeedLimiter
from tests.helpers import LOADED_MACHINE

SETTINGS = LoopSettings(rate_hz=500.0, stale_pose=0.1, driver_silence=0.05,
                        deadline_misses=3, max_period_lateness=0.01)
P = SETTINGS.period


def _pose(x: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = [x, 0.0, 0.3]
    return T


class Cell:
    """Sim arm and wrist, the three records and the loop, stepped on a virtual clock."""

    def __init__(self) -> None:
        self.clock = VirtualClock(10.0)
        self.arm = SimArm(clock=self.clock, home=_pose())
        self.wrist = SimEffector(clock=self.clock)
        anyio.run(self.arm.start)
        anyio.run(self.wrist.start)
        self.nav, self.cmd, self.status = (SharedRecord(d) for d in
                                           (NAV_DTYPE, CMD_DTYPE, STATUS_DTYPE))
        self.loop = ControlLoop(self.arm, self.wrist, SETTINGS, self.nav, self.cmd,
                                self.status, SpeedLimiter(0.25, 0.5))
        self.fresh_pose = True

    def goal(self, x: float) -> None:
        self.nav.write(goal=_pose(x), t_pose=self.clock.now(), mode=MOVE)

    def run(self, periods: int, each: Callable[[], None] | None = None,
            lateness: float = 0.0) -> None:
        for _ in range(periods):
            self.clock.advance(P)
            self.arm.advance(P)
            self.wrist.advance(P)
            if self.fresh_pose:
                self.nav.write(t_pose=self.clock.now())
            if each:
                each()
            self.loop.step(self.clock.now(), lateness)

    def motion_after(self, t: float) -> list:
        return [r for r in self.arm.command_log if r.time > t and r.kind in ("servo", "speed")]

    def close(self) -> None:
        for r in (self.nav, self.cmd, self.status):
            r.close()


@pytest.fixture
def cell():
    c = Cell()
    yield c
    c.close()


def test_servoes_to_the_goal_within_the_speed_limit(cell: Cell) -> None:
    """The TCP reaches a goal 5 cm away, never faster than the 0.25 m/s limit, and the
    status record reports the measured pose and the motion commands sent."""
    cell.goal(0.05)
    xs = []
    for _ in range(600):  # the sim arm lags the setpoint (1 m/s^2 acceleration)
        cell.run(1)
        xs.append(cell.arm.state().T_B_tcp[0, 3])
    speeds = np.abs(np.diff(xs)) / P
    assert speeds.max() <= 0.25 + 1e-9
    assert abs(xs[-1] - 0.05) < 1e-6
    st = cell.status.read()
    assert not st["latched"] and st["motion_commands"] == 600
    np.testing.assert_allclose(st["T_B_tcp"], cell.arm.state().T_B_tcp)


def _assert_stopped(cell: Cell, detected_at: float, reason_part: str) -> None:
    st = cell.status.read()
    assert st["latched"], "the loop did not stop"
    assert reason_part in bytes(st["stop_reason"]).decode()
    assert st["stop_time"] <= detected_at + 2 * P + 1e-9
    stops = [r for r in cell.arm.command_log if r.kind == "stop"]
    assert stops and stops[0].time <= detected_at + 2 * P + 1e-9
    assert cell.motion_after(stops[0].time) == []


def test_stop_request_stops_at_the_next_period(cell: Cell) -> None:
    """A latched stop from the daemon (shared record) stops the arm within two periods."""
    cell.goal(0.05)
    cell.run(10)
    t = cell.clock.now()
    cell.cmd.write(stop_count=1, stop_reason=encode_reason("operator e-stop"))
    cell.run(20)
    _assert_stopped(cell, t, "operator e-stop")


def test_a_stale_goal_is_held_not_followed(cell: Cell) -> None:
    """Issue 32 (slow sight slows the robot): a MOVE goal computed from poses older than
    stale_pose is not followed: the arm holds where it is (no motion command, the status
    says goal_stale), without latching; a fresh goal moves it again. Holding needs no
    pose at all. (A stale fixture frame in GUIDE still stops the arm: test_guided_loop.)"""
    cell.nav.write(goal=_pose(), t_pose=cell.clock.now(), mode=0)
    cell.fresh_pose = False
    cell.run(100)  # 0.2 s holding with an old pose
    assert not cell.status.read()["latched"]
    cell.goal(0.05)
    t_pose = cell.clock.now()
    cell.run(100)  # 0.2 s: stale after 0.1 s
    st = cell.status.read()
    assert not st["latched"] and st["goal_stale"]
    held_from = t_pose + SETTINGS.stale_pose + P
    assert cell.motion_after(held_from) == []
    x_held = cell.arm.state().T_B_tcp[0, 3]
    assert 0.0 < x_held < 0.05
    cell.fresh_pose = True
    cell.run(600)
    st = cell.status.read()
    assert not st["latched"] and not st["goal_stale"]
    assert abs(cell.arm.state().T_B_tcp[0, 3] - 0.05) < 1e-6


@pytest.mark.parametrize("fault, reason", [
    ("inject_disconnect", "disconnected"),
    ("inject_protective_stop", "protective stop"),
    ("inject_emergency_stop", "emergency stop"),
])
def test_arm_faults_stop_the_loop(cell: Cell, fault: str, reason: str) -> None:
    """An arm that drops its link, protective-stops or e-stops is seen in the next period;
    the loop sends no motion command after it."""
    cell.goal(0.05)
    cell.run(10)
    t = cell.clock.now()
    getattr(cell.arm, fault)()
    cell.run(10)
    _assert_stopped(cell, t, reason)


def test_silent_end_effector_stops_the_arm(cell: Cell) -> None:
    """An end-effector whose state stops updating for driver_silence stops the arm."""
    cell.goal(0.05)
    cell.run(10)
    t = cell.clock.now()
    cell.wrist.inject_silence()
    cell.run(60)
    _assert_stopped(cell, t + SETTINGS.driver_silence, "silent")


def test_end_effector_fault_stops_the_arm(cell: Cell) -> None:
    """A wrist reporting a fault stops the arm at once, with the wrist's message."""
    cell.goal(0.05)
    cell.run(10)
    t = cell.clock.now()
    cell.wrist.inject_fault("tendon 2 slack")
    cell.run(5)
    _assert_stopped(cell, t, "tendon 2 slack")


def test_late_periods_stop_the_arm(cell: Cell) -> None:
    """deadline_misses consecutive periods that finish after their deadline stop the arm;
    fewer do not."""
    cell.goal(0.05)
    cell.run(2, lateness=1.5 * P)
    cell.run(5)
    assert not cell.status.read()["latched"]
    t = cell.clock.now()
    cell.run(SETTINGS.deadline_misses, lateness=1.5 * P)
    cell.run(2)
    _assert_stopped(cell, t + SETTINGS.deadline_misses * P, "late")


def test_clear_resumes_from_where_the_arm_is(cell: Cell) -> None:
    """After the daemon clears a stop, the loop commands again, starting from the measured
    pose rather than the pre-stop setpoint, so nothing jumps."""
    cell.goal(0.05)
    cell.run(40)
    cell.cmd.write(stop_count=1, stop_reason=encode_reason("test"))
    cell.run(50)
    here = cell.arm.state().T_B_tcp.copy()
    cell.cmd.write(clear_count=1)
    cell.goal(0.05)
    cell.run(1)
    st = cell.status.read()
    assert not st["latched"]
    assert np.linalg.norm(st["setpoint"][:3, 3] - here[:3, 3]) <= 0.25 * P + 1e-9
    cell.run(300)
    assert abs(cell.arm.state().T_B_tcp[0, 3] - 0.05) < 1e-6


def test_a_reset_ends_the_stops_requested_before_it(cell: Cell) -> None:
    """A reset ends every stop the daemon requested before it: a late period that finds
    the daemon's own stop (sent when it latched the loop's fault) and the reset together
    resumes rather than latching again (a FAULT right after every such reset on a loaded
    machine); a stop requested after the reset still latches."""
    cell.goal(0.05)
    cell.run(10)
    cell.cmd.write(stop_count=1, stop_reason=encode_reason("arm protective stop"))
    cell.run(1)
    assert cell.status.read()["latched"]
    # the daemon's stop and then the operator's reset, before the loop's next period
    cell.cmd.write(stop_count=2, stop_reason=encode_reason("control loop: first"))
    cell.cmd.write(clear_count=1, stops_cleared=2)
    cell.run(1)
    st = cell.status.read()
    assert not st["latched"] and int(st["clear_count_seen"]) == 1
    cell.cmd.write(stop_count=3, stop_reason=encode_reason("after the reset"))
    cell.run(1)
    st = cell.status.read()
    assert st["latched"] and "after the reset" in bytes(st["stop_reason"]).decode()


async def test_control_process_runs_and_stops_on_request() -> None:
    """The spawned control process servoes the sim arm on the wall clock, stops it on a
    stop request within a few periods, sends nothing after, and exits on close."""
    proc = ControlProcess(ProcessSpec(
        arm=DriverSpec("sim", {"home": _pose()}), effector=DriverSpec("sim"),
        settings=LoopSettings(rate_hz=500.0, stale_pose=0.5, driver_silence=0.2,
                              **LOADED_MACHINE),
        limiter=SpeedLimiter(0.25, 0.5)))
    await proc.start()
    try:
        import time
        # fresh goals every 10 ms until the loop has servoed 50 periods (0.1 s at
        # 500 Hz): a loaded machine starts the process late, so the wait is not a
        # fixed time, but the loop must get there within 5 s
        deadline = time.monotonic() + 5.0
        while True:
            proc.set_goal(_pose(0.02), time.monotonic(), move=True)
            await anyio.sleep(0.01)
            st = proc.read_status()
            if st["motion_commands"] > 50 or time.monotonic() > deadline:
                break
        assert st["periods"] > 50 and st["motion_commands"] > 50 and not st["latched"]
        assert st["T_B_tcp"][0, 3] > 0.0
        t0 = time.monotonic()
        proc.request_stop("test stop")
        while not proc.read_status()["latched"]:
            assert time.monotonic() - t0 < 1.0, "no stop within 1 s"
            await anyio.sleep(0.001)
        sent = int(proc.read_status()["motion_commands"])
        await anyio.sleep(0.1)
        st = proc.read_status()
        assert int(st["motion_commands"]) == sent
        assert "test stop" in bytes(st["stop_reason"]).decode()
        assert st["stop_time"] - t0 < 0.05  # the loop saw it within a few periods
    finally:
        await proc.close()
    assert not proc.alive


def test_the_control_process_heap_is_frozen_before_the_loop_runs() -> None:
    """The loop's process collects once and freezes its startup heap, so the cyclic
    collector, which once walked about 150 000 objects in a 96 ms pause inside a 2 ms
    period, later walks only what the loop itself creates."""
    import gc

    from oralnav.realtime.control_process import settle_heap

    assert len(gc.get_objects()) > 10_000  # this test process: pytest, numpy, scipy...
    try:
        settle_heap()
        assert gc.get_freeze_count() > 10_000
        assert len(gc.get_objects()) < 1_000
    finally:
        gc.unfreeze()


def test_goal_outside_the_workspace_stops_at_once(cell: Cell) -> None:
    """A goal outside the workspace box stops the arm in the period it arrives, before any
    motion toward it; the reason names the axis and the excess."""
    cell.goal(0.01)
    cell.run(20)
    t = cell.clock.now()
    cell.goal(2.0)  # 2 m along x: far outside the default box (x <= 0.85 m)
    cell.run(5)
    _assert_stopped(cell, t, "workspace: goal outside the box (x +")


def test_device_recovery_runs_only_while_latched(cell: Cell) -> None:
    """issue 8 (device recovery): a recover request reaches the wrist's reset_fault() and
    the arm's recover() only while the stop is latched; an async recover() runs to its end
    in a thread of its own, not in the period."""
    calls: list[str] = []
    done = threading.Event()

    async def arm_recover() -> None:  # the UR arm's recovery is a coroutine
        await anyio.sleep(0.01)
        calls.append("arm")
        done.set()

    cell.wrist.reset_fault = lambda: calls.append("effector")  # type: ignore[attr-defined]
    cell.arm.recover = arm_recover  # type: ignore[attr-defined]
    cell.cmd.write(recover_count=1, recover_device=b"effector")
    cell.run(2)
    assert calls == [] and cell.status.read()["recover_count_seen"] == 1  # not latched
    cell.cmd.write(stop_count=1, stop_reason=encode_reason("test"))
    cell.run(2)
    cell.cmd.write(recover_count=2, recover_device=b"effector")
    cell.run(1)
    assert calls == ["effector"]
    cell.cmd.write(recover_count=3, recover_device=b"arm")
    cell.run(1)
    assert done.wait(2.0) and calls == ["effector", "arm"]


def test_records_each_new_arm_measurement_in_the_history() -> None:
    """Issue 32 (time): every period with a new arm measurement appends (its timestamp,
    the measured TCP) to the history ring, and the status says when the arm measured its
    TCP (``t_arm``); a repeated timestamp (an arm reporting slower than the loop) and a
    disconnected arm append nothing."""
    c = Cell()
    ring = SharedRing(ARM_SAMPLE_DTYPE, 64)
    try:
        c.loop = ControlLoop(c.arm, c.wrist, SETTINGS, c.nav, c.cmd, c.status,
                             SpeedLimiter(0.25, 0.5), history=ring)
        c.goal(0.01)
        c.run(10)
        got = ring.read()
        assert len(got) == 10 and np.all(np.diff(got["t"]) > 0)
        assert got["t"][-1] == c.arm.state().timestamp == c.status.read()["t_arm"]
        np.testing.assert_array_equal(got["T_B_tcp"][-1], c.arm.state().T_B_tcp)
        c.loop.step(c.clock.now())  # the same measurement again
        assert ring.count == 10
        c.arm.inject_disconnect()
        c.run(3)
        assert ring.count == 10
    finally:
        ring.close()
        c.close()


def test_records_capture_to_command_latency_once_per_goal() -> None:
    """Issue 32, item 5: the first servo command computed from a goal records (capture
    instant of its poses, when that command was sent); later commands toward the same
    goal add nothing, a goal from a new capture adds one; a held goal adds nothing."""
    c = Cell()
    ring = SharedRing(LATENCY_DTYPE, 16)
    try:
        c.loop = ControlLoop(c.arm, c.wrist, SETTINGS, c.nav, c.cmd, c.status,
                             SpeedLimiter(0.25, 0.5), latency=ring)
        c.fresh_pose = False
        t_capture = c.clock.now() - 0.03
        c.nav.write(goal=_pose(0.01), t_pose=t_capture, mode=MOVE)
        c.run(10)
        got = ring.read()
        assert len(got) == 1 and got["t_capture"][0] == t_capture
        assert got["t_command"][0] - t_capture == pytest.approx(0.03 + P)
        c.nav.write(goal=_pose(0.0), t_pose=c.clock.now(), mode=0)  # HOLD
        c.run(5)
        c.nav.write(goal=_pose(0.02), t_pose=c.clock.now() - 0.005, mode=MOVE)
        c.run(5)
        got = ring.read()
        assert len(got) == 2
        assert got["t_command"][1] - got["t_capture"][1] == pytest.approx(0.005 + P)
    finally:
        ring.close()
        c.close()


def test_the_control_process_tightens_its_timing():
    """Deadline misses under load (issue 32, item 6): the control process shortens the GIL
    switch interval (a driver's helper thread holding the GIL can make the loop wait up
    to 5 ms) and sets its timer slack to 1 ns; run_at_rate keeps its 2 ms grid with a
    50 us spin. Checked in a fresh interpreter, as the process sets it."""
    import subprocess
    import sys

    code = ("import ctypes, sys, time\n"
            "from oralnav.realtime.control_loop import SWITCH_INTERVAL_S, run_at_rate, "
            "tighten_timing\n"
            "print(tighten_timing())\n"
            "assert abs(sys.getswitchinterval() - SWITCH_INTERVAL_S) < 1e-6\n"
            "assert ctypes.CDLL(None).prctl(30, 0, 0, 0, 0) == 1  # PR_GET_TIMERSLACK\n"
            "late = []\n"
            "run_at_rate(lambda now, l: late.append(l), 500.0, lambda: len(late) >= 250)\n"
            "late.sort()\n"
            "print(late[len(late) // 2])\n"
            "assert late[len(late) // 2] < 1e-3\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 0, out.stderr
    assert "GIL switch interval 200 us, timer slack 1 ns" in out.stdout
