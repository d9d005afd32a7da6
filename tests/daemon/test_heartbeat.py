"""Issue 30, serious 3: a hung control process does not go unseen. The daemon watches the
loop's heartbeat on its own clock, in a thread of its own, and latches FAULT within a few
periods of silence; the stop is commanded, the daemon reports itself unhealthy (the
systemd watchdog is starved) while the loop is silent, and after the process resumes the
cell resets to READY."""

from __future__ import annotations

import os
import signal
import time

import anyio
import pytest

from oralnav.daemon.heartbeat import LoopHeartbeat
from oralnav.daemon.systemd import ask_health
from oralnav.drivers.io.sim import SimInputs
from oralnav.realtime.control_loop import HOLD
from tests.daemon.core_rig import control_process, daemon_core, supervise_until

#: how late past its limit the watch may latch on a loaded 2-core CI machine (s)
SLACK_S = 0.05


@pytest.fixture
async def cell():
    proc = control_process()
    await proc.start()
    inputs = SimInputs()
    await inputs.start()
    core = daemon_core(proc, inputs)
    hb = LoopHeartbeat(core)
    core.heartbeat = hb
    try:
        hb.start()
        await supervise_until(core, lambda: core.supervisor.state.value == "READY")
        yield core, proc, hb
    finally:
        hb.close()
        if proc.alive:
            os.kill(proc._proc.pid, signal.SIGCONT)
        await inputs.close()
        await proc.close()


async def test_a_stopped_control_process_faults_within_its_limit_and_recovers(cell) -> None:
    """SIGSTOP of the control child: FAULT (deadline:stalled, naming the silence) within
    period + max_period_lateness (+ slack) of its last period, though the process is
    alive; the stop is commanded and HOLD written; health is False with the reason (what
    the systemd watchdog asks) until SIGCONT; then the loop obeys the stop, health returns
    and a reset brings READY."""
    core, proc, hb = cell
    deadline = core.watchdogs.deadline
    limit = deadline.period + deadline.max_lateness
    stops_before = int(proc.cmd.read()["stop_count"])
    pid = proc._proc.pid
    os.kill(pid, signal.SIGSTOP)
    try:
        t_last = float(proc.read_status()["t"])  # the loop's last period (monotonic)
        while core.supervisor.state.value != "FAULT":
            assert time.monotonic() - t_last < 2.0, "no FAULT while the loop is stopped"
            await anyio.sleep(0.001)
        latched_at = core.supervisor.history[-1].time
        assert core.supervisor.history[-1].who == "deadline:stalled"
        assert "silent" in core.supervisor.history[-1].reason
        assert latched_at - t_last < limit + SLACK_S, (latched_at - t_last, limit)
        assert proc.alive  # alive, yet seen as hung
        ok, why = core.health()
        assert not ok and "silent" in why
        # the systemd watchdog withholds pings (the reason names the silence so far, which
        # has grown by the time it is asked again: compare its words, not its number)
        ok, asked = ask_health(core.health)
        assert not ok and asked.startswith("control loop silent for "), asked
        assert int(proc.cmd.read()["stop_count"]) == stops_before + 1
        assert int(proc.nav.read()["mode"]) == HOLD
        assert hb.last_trip is not None and hb.last_trip["quiet_s"] > limit
        await anyio.sleep(0.2)
        core.supervise_once(time.monotonic())
        assert "silent" in (core.supervisor.not_ready_reason or "")
    finally:
        os.kill(pid, signal.SIGCONT)
    await supervise_until(core, lambda: bool(proc.read_status()["latched"]))
    assert "stop requested" in proc.read_status()["stop_reason"].decode()
    await supervise_until(core, lambda: core.health()[0])
    core.reset("dr.smith")
    await supervise_until(core, lambda: core.supervisor.state.value == "READY")
