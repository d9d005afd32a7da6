"""Issue 4, daemon core: the REST API over the real core and control process. Operators
e-stop, reset, start and pause; observers cannot; requests in the wrong state get 409 and
change nothing; a stop the control loop latches by itself, a stale pose and a pressed
e-stop input become FAULT / ESTOP, and the robot stops."""

from __future__ import annotations

import json
import time
from pathlib import Path

import anyio
import httpx
import numpy as np
import pytest

from oralnav.daemon.api import build_app
from oralnav.daemon.audit import AuditLog
from oralnav.daemon.auth import TokenStore
from oralnav.drivers.io.sim import SimInputs
from tests.daemon.core_rig import control_process, daemon_core, home_pose, supervise_until

_home = home_pose


@pytest.fixture
async def rig(tmp_path: Path):
    proc = control_process()
    await proc.start()
    inputs = SimInputs()
    await inputs.start()
    core = daemon_core(proc, inputs)
    clear = TokenStore.generate(tmp_path / "tokens.toml")
    tokens = TokenStore.from_file(tmp_path / "tokens.toml")
    audit = AuditLog(tmp_path / "audit.jsonl").open()
    app = build_app(core, tokens, audit)
    client = httpx.AsyncClient(transport=httpx.ASGITransport(app=app), base_url="http://t")
    try:
        core.supervise_once(time.monotonic())
        yield core, client, clear, inputs, tmp_path / "audit.jsonl"
    finally:
        await client.aclose()
        audit.close()
        await inputs.close()
        await proc.close()


def _auth(clear: dict[str, str], role: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {clear[role]}"}


async def _until(pred, timeout: float = 1.0) -> None:
    t0 = time.monotonic()
    while not pred():
        assert time.monotonic() - t0 < timeout, "condition not reached in time"
        await anyio.sleep(0.002)


async def test_estop_reset_and_roles_over_rest(rig) -> None:
    """An observer's e-stop is refused (403) and changes nothing; the operator's latches
    ESTOP and the control loop stops; reset returns to IDLE and then READY."""
    core, client, clear, _, audit_path = rig
    assert core.supervisor.state.value == "READY"
    r = await client.post("/estop", headers=_auth(clear, "observer"), json={"reason": "x"})
    assert r.status_code == 403 and core.supervisor.state.value == "READY"
    r = await client.post("/estop", headers=_auth(clear, "operator"), json={"reason": "drill"})
    assert r.status_code == 200, r.text
    assert core.supervisor.state.value == "ESTOP"
    await _until(lambda: bool(core.control.read_status()["latched"]))
    assert "drill" in core.control.read_status()["stop_reason"].decode()
    r = await client.post("/procedure/start", headers=_auth(clear, "operator"))
    assert r.status_code == 409 and core.supervisor.state.value == "ESTOP"
    r = await client.post("/reset", headers=_auth(clear, "operator"))
    assert r.status_code == 200, r.text
    await _until(lambda: not bool(core.control.read_status()["latched"]))
    core.supervise_once(time.monotonic())
    assert core.supervisor.state.value == "READY"
    lines = [json.loads(x) for x in audit_path.read_text().splitlines()]
    assert [x["status"] for x in lines if x["path"] == "/estop"] == [403, 200]


async def test_procedure_needs_targets_then_moves_only_while_running(rig) -> None:
    """start without targets is 409; with targets the core runs, goals move the arm, and
    after pause the loop holds (no goal is accepted)."""
    core, client, clear, _, _ = rig
    op = _auth(clear, "operator")
    r = await client.post("/procedure/start", headers=op)
    assert r.status_code == 409 and "targets" in r.json()["detail"]
    body = {"targets": [{"name": "s1", "p_OM": [0.0, 0.03, -0.01]}]}
    assert (await client.post("/targets", headers=op, json=body)).status_code == 200
    assert (await client.post("/procedure/start", headers=op)).status_code == 200
    goal = _home()
    goal[0, 3] = 0.01
    for _ in range(40):
        assert core.set_goal(goal, time.monotonic())
        await anyio.sleep(0.005)
    assert core.control.read_status()["T_B_tcp"][0, 3] > 0.001
    r = await client.post("/targets", headers=op, json=body)
    assert r.status_code == 409  # not while running
    assert (await client.post("/procedure/pause", headers=op)).status_code == 200
    assert not core.set_goal(goal, time.monotonic())
    await anyio.sleep(0.01)  # a period already under way may still have read the MOVE
    sent = int(core.control.read_status()["motion_commands"])
    await anyio.sleep(0.05)
    assert int(core.control.read_status()["motion_commands"]) == sent


async def test_loop_latch_stale_pose_and_estop_input_become_faults(rig) -> None:
    """A stop the loop latched itself becomes FAULT with its reason; a pose that the
    current stage steers by and that stops coming (pose_timeout) trips FAULT; a pressed
    e-stop input is ESTOP and blocks reset until released."""
    core, client, clear, inputs, _ = rig
    core.control.request_stop("arm protective stop (simulated)")
    await _until(lambda: bool(core.control.read_status()["latched"]))
    core.supervisor.stop.clear(time.monotonic(), "test")  # as if the loop tripped alone
    core.supervise_once(time.monotonic())
    assert core.supervisor.state.value == "FAULT"
    assert "protective stop" in json.dumps(core.status()["safety"])
    assert (await client.post("/reset", headers=_auth(clear, "operator"))).status_code == 200

    now = time.monotonic()
    core.watch_poses({"opener"})  # what the current stage steers by
    core.publish_pose("opener", _home(), now, frame="C")
    core.supervise_once(now + 0.05)
    assert core.supervisor.state.value in ("IDLE", "READY")
    # past the pose timeout (sim.toml: 5 s): the pose stopped coming
    core.supervise_once(now + core.watchdogs.poses.limit + 0.1)
    assert core.supervisor.state.value == "FAULT"
    assert "opener" in json.dumps(core.status()["safety"])

    inputs.press_estop()
    core.supervise_once(time.monotonic())
    assert core.supervisor.state.value == "ESTOP"
    r = await client.post("/reset", headers=_auth(clear, "operator"))
    assert r.status_code == 409 and "e-stop" in r.json()["detail"]


async def test_needle_steps_over_rest_on_the_core(rig) -> None:
    """issue 7, item 7: the needle steps are daemon states callable over REST: without a
    cell a step is 409; NG runs on a loaded simulated trial and answers its result with
    the truth check; a step out of turn is 409; with the e-stop latched a step is 409 and
    nothing moves."""
    core, client, clear, _, _ = rig
    op = _auth(clear, "operator")
    r = await client.post("/needle/NG", headers=op)
    assert r.status_code == 409 and "POST /needle/cell" in r.json()["detail"]
    r = await client.post("/needle/cell", headers=op, json={"trial": 0})
    assert r.status_code == 200, r.text
    assert r.json()["procedure"]["next"] == "NG"
    r = await client.post("/needle/ND", headers=op)
    assert r.status_code == 409 and "NG comes first" in r.json()["detail"]
    r = await client.post("/needle/NG", headers=op)
    assert r.status_code == 200, r.text
    res = r.json()["result"]
    assert res["ok"] and res["truth_ok"] and r.json()["next"] == "NH"
    cell = core.needle_session._proc.cell
    assert (await client.post("/estop", headers=op, json={"reason": "drill"})).status_code == 200
    before = cell.truth().T_ref_needle
    r = await client.post("/needle/NH", headers=op)
    assert r.status_code == 409 and "ESTOP" in r.json()["detail"]
    assert np.array_equal(cell.truth().T_ref_needle, before)
    doc = (await client.get("/needle", headers=_auth(clear, "observer"))).json()
    assert doc["cell"]["trial"] == 0 and doc["procedure"]["next"] == "NH"
    assert doc["procedure"]["results"]["NG"]["ok"] is True


async def test_reset_after_a_stop_mid_procedure_brings_ready_and_keeps_it(rig) -> None:
    """Issue 30, serious 2: after an e-stop during a running procedure (goals streaming to
    the loop), a reset brings READY within 1 s and READY holds (no stale-goal FAULT), in
    every cycle; the interrupted procedure resumes (the arm moves again) or aborts."""
    core, client, clear, _, _ = rig
    op = _auth(clear, "operator")
    body = {"targets": [{"name": f"s{k}", "p_OM": [0.0, 0.01 * k, -0.01]} for k in range(4)]}
    assert (await client.post("/targets", headers=op, json=body)).status_code == 200
    assert (await client.post("/procedure/start", headers=op)).status_code == 200
    goal = _home()
    for cycle in range(6):
        goal[0, 3] = 0.002 * (cycle % 2)
        for _ in range(10):  # the procedure streams goals from fresh poses
            assert core.set_goal(goal, time.monotonic())
            await anyio.sleep(0.002)
        r = await client.post("/estop", headers=op, json={"reason": f"cycle {cycle}"})
        assert r.status_code == 200
        await _until(lambda: bool(core.control.read_status()["latched"]))
        assert core.status()["safety"]["interrupted"] is not None
        t0 = time.monotonic()
        r = await client.post("/reset", headers=op)
        assert r.status_code == 200, r.text
        while core.supervisor.state.value != "READY":
            core.supervise_once(time.monotonic())
            assert time.monotonic() - t0 < 1.0, core.status()["safety"]
            await anyio.sleep(0.005)
        t_ready = time.monotonic()
        while time.monotonic() - t_ready < 0.3:  # past the loop's stale-pose limit
            core.supervise_once(time.monotonic())
            assert core.supervisor.state.value == "READY", core.status()["safety"]
            await anyio.sleep(0.01)
        r = await client.post("/procedure/start", headers=op)
        assert r.status_code == 409 and "resume or abort" in r.json()["detail"]
        r = await client.post("/procedure/resume", headers=op)
        assert r.status_code == 200, r.text
        assert core.supervisor.state.value == "RUNNING"
    sent = int(core.control.read_status()["motion_commands"])
    for _ in range(10):
        assert core.set_goal(goal, time.monotonic())
        await anyio.sleep(0.002)
    assert int(core.control.read_status()["motion_commands"]) > sent  # it moves again
    assert (await client.post("/estop", headers=op)).status_code == 200
    assert (await client.post("/procedure/abort", headers=op)).status_code == 200
    assert (await client.post("/reset", headers=op)).status_code == 200
    await supervise_until(core, lambda: core.supervisor.state.value == "READY")
    assert core.status()["safety"]["interrupted"] is None
    assert (await client.post("/procedure/start", headers=op)).status_code == 200


async def test_the_surgeon_selects_a_target_among_those_registered(rig) -> None:
    """Issue 33 item 1: POST /targets/select names the current target (shown in /status);
    a name not registered is 409 and keeps the choice; new targets without it clear it."""
    core, client, clear, _, _ = rig
    op = _auth(clear, "operator")
    r = await client.post("/targets/select", headers=op, json={"name": "s2"})
    assert r.status_code == 409 and "none, POST /targets first" in r.json()["detail"]
    body = {"targets": [{"name": f"s{k}", "p_OM": [0.0, 0.01 * k, -0.01]} for k in range(3)]}
    assert (await client.post("/targets", headers=op, json=body)).status_code == 200
    assert (await client.post("/targets/select", headers=op,
                              json={"name": "s2"})).status_code == 200
    r = await client.post("/targets/select", headers=op, json={"name": "s7"})
    assert r.status_code == 409 and "registered: s0, s1, s2" in r.json()["detail"]
    st = (await client.get("/status", headers=op)).json()
    assert st["selected_target"] == "s2" and core.selections == 1
    body["targets"] = body["targets"][:2]
    assert (await client.post("/targets", headers=op, json=body)).status_code == 200
    assert core.selected_target is None


async def test_status_gives_each_time_on_both_clocks(rig) -> None:
    """Issue 33 item 6: /status gives the daemon's monotonic seconds and, beside each, the
    same instant in UTC as the audit log writes it, so the two line up."""
    import datetime

    core, client, clear, _, audit_path = rig
    op = _auth(clear, "operator")
    assert (await client.post("/estop", headers=op, json={"reason": "t"})).status_code == 200
    st = (await client.get("/status", headers=op)).json()
    now = datetime.datetime.now(datetime.UTC)

    def parse(text: str) -> datetime.datetime:
        assert text.endswith("Z")
        return datetime.datetime.fromisoformat(text[:-1] + "+00:00")

    assert abs((parse(st["clock"]["utc"]) - now).total_seconds()) < 2.0
    estop = st["safety"]["history"][-1]
    assert estop["to"] == "ESTOP" and st["safety"]["since"] == estop["time"]
    # the transition's UTC is the status's UTC less the monotonic seconds since it
    gap = st["clock"]["monotonic_s"] - estop["time"]
    utc = parse(st["clock"]["utc"]) - datetime.timedelta(seconds=gap)
    assert abs((parse(estop["time_utc"]) - utc).total_seconds()) < 0.002
    assert st["safety"]["since_utc"] == estop["time_utc"]
    audit = [json.loads(x) for x in audit_path.read_text().splitlines()]
    assert abs((parse(audit[-1]["time"]) - parse(estop["time_utc"])).total_seconds()) < 1.0
