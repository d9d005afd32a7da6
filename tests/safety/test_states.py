"""Tests of ``oralnav.safety.states``: the safety state machine.

Each test's docstring names the requirement it checks (Issue 4: safety).
"""

from __future__ import annotations

import json
import threading

import pytest

from oralnav.safety.errors import InputError, StateError
from oralnav.safety.states import SafetyState, SafetySupervisor

S = SafetyState
WHO = "dr.smith"


def in_state(state: SafetyState) -> SafetySupervisor:
    """A supervisor brought to ``state`` through legal transitions."""
    sup = SafetySupervisor()
    if state is S.IDLE:
        return sup
    if state is S.FAULT:
        sup.fault(1.0, "stale_pose:opener", "pose of 'opener' is 0.134 s old")
        return sup
    if state is S.ESTOP:
        sup.estop(1.0, "input", "e-stop pressed")
        return sup
    sup.mark_ready(1.0)
    if state in (S.RUNNING, S.PAUSED):
        sup.start(2.0, WHO)
    if state is S.PAUSED:
        sup.pause(3.0, WHO)
    assert sup.state is state
    return sup


ACTIONS = {
    "mark_ready": lambda s: s.mark_ready(10.0),
    "mark_not_ready": lambda s: s.mark_not_ready(10.0, "arm driver disconnected"),
    "start": lambda s: s.start(10.0, WHO),
    "pause": lambda s: s.pause(10.0, WHO),
    "resume": lambda s: s.resume(10.0, WHO),
    "abort": lambda s: s.abort(10.0, WHO),
    "fault": lambda s: s.fault(10.0, "driver_silence:arm", "silent for 0.2 s"),
    "estop": lambda s: s.estop(10.0, "rest", "operator pressed STOP"),
    "reset": lambda s: s.reset(10.0, WHO, estop_released=True, faults_cleared=True),
}

E = StateError
# state -> action -> resulting state, or StateError (refused, nothing changes)
TABLE = {
    S.IDLE: dict(mark_ready=S.READY, mark_not_ready=S.IDLE, start=E, pause=E, resume=E,
                 abort=E, fault=S.FAULT, estop=S.ESTOP, reset=E),
    S.READY: dict(mark_ready=S.READY, mark_not_ready=S.IDLE, start=S.RUNNING, pause=E,
                  resume=E, abort=E, fault=S.FAULT, estop=S.ESTOP, reset=E),
    S.RUNNING: dict(mark_ready=S.RUNNING, mark_not_ready=S.FAULT, start=E, pause=S.PAUSED,
                    resume=E, abort=S.READY, fault=S.FAULT, estop=S.ESTOP, reset=E),
    S.PAUSED: dict(mark_ready=S.PAUSED, mark_not_ready=S.FAULT, start=E, pause=S.PAUSED,
                   resume=S.RUNNING, abort=S.READY, fault=S.FAULT, estop=S.ESTOP, reset=E),
    S.FAULT: dict(mark_ready=S.FAULT, mark_not_ready=S.FAULT, start=E, pause=E, resume=E,
                  abort=E, fault=S.FAULT, estop=S.ESTOP, reset=S.IDLE),
    S.ESTOP: dict(mark_ready=S.ESTOP, mark_not_ready=S.ESTOP, start=E, pause=E, resume=E,
                  abort=E, fault=S.ESTOP, estop=S.ESTOP, reset=S.IDLE),
}
CASES = [(s, a) for s in TABLE for a in ACTIONS]


@pytest.mark.parametrize(("state", "action"), CASES, ids=[f"{s}-{a}" for s, a in CASES])
def test_every_transition(state, action):
    """Issue 4 safety (every transition, legal and illegal): each request in each state
    leads to the state of the table; an illegal one raises StateError naming the current
    state and changes nothing (state, history, reasons, stop)."""
    sup = in_state(state)
    expected = TABLE[state][action]
    before = sup.snapshot(history=1000)
    if expected is E:
        with pytest.raises(StateError) as ei:
            ACTIONS[action](sup)
        assert f"while in {state.value}" in str(ei.value)
        assert sup.snapshot(history=1000) == before
    else:
        ACTIONS[action](sup)
        assert sup.state is expected
        assert sup.motion_allowed == (expected is S.RUNNING)
        assert sup.stop.latched == (expected in (S.FAULT, S.ESTOP))


def test_start_refused_in_fault_names_the_cause():
    """Issue 4 safety: start is refused in FAULT with a message naming the state and the
    cause and saying to reset, and nothing changes."""
    sup = in_state(S.FAULT)
    with pytest.raises(StateError) as ei:
        sup.start(5.0, WHO)
    msg = str(ei.value)
    assert msg.startswith("cannot start while in FAULT (stale_pose:opener: pose of "
                          "'opener' is 0.134 s old)")
    assert msg.endswith("reset first")
    assert sup.state is S.FAULT and sup.stop.latched


def test_start_refused_in_idle_says_why_not_ready():
    """Issue 4 safety: start in IDLE is refused naming the not-ready reason."""
    sup = SafetySupervisor()
    sup.mark_not_ready(1.0, "no fresh pose of 'opener'")
    with pytest.raises(StateError, match=r"IDLE \(not ready: no fresh pose of 'opener'\)"):
        sup.start(2.0, WHO)


@pytest.mark.parametrize("who", ["", "   ", None])
def test_start_resume_reset_need_who(who):
    """Issue 4 safety (explicit who): start, resume and reset without the operator's name
    are refused and change nothing."""
    sup = in_state(S.READY)
    with pytest.raises(StateError, match="operator's name"):
        sup.start(5.0, who)
    assert sup.state is S.READY
    sup = in_state(S.PAUSED)
    with pytest.raises(StateError, match="operator's name"):
        sup.resume(5.0, who)
    assert sup.state is S.PAUSED
    sup = in_state(S.FAULT)
    with pytest.raises(StateError, match="operator's name"):
        sup.reset(5.0, who, estop_released=True, faults_cleared=True)
    assert sup.state is S.FAULT and sup.stop.latched


@pytest.mark.parametrize("who", ["", None])
def test_pause_and_abort_are_never_refused_for_a_missing_name(who):
    """Issue 4 safety (requests that make the robot safer never fail for want of a name):
    pause and abort without an operator name go through, recorded as "(unnamed)"."""
    sup = in_state(S.RUNNING)
    assert sup.pause(5.0, who) is True
    assert sup.history[-1].who == "(unnamed)"
    sup.abort(6.0, who)
    assert sup.state is S.READY and sup.history[-1].who == "(unnamed)"


def test_refusals_say_why():
    """Issue 4 safety (clear refusals): each refusal names the state and the reason."""
    sup = in_state(S.RUNNING)
    with pytest.raises(StateError, match="^cannot resume while in RUNNING: the procedure "
                                         "is running, not paused$"):
        sup.resume(5.0, WHO)
    with pytest.raises(StateError, match=f"^cannot start while in RUNNING: a procedure is "
                                         f"running \\(started by {WHO}\\)$"):
        sup.start(5.0, WHO)
    sup = in_state(S.READY)
    with pytest.raises(StateError, match="^cannot abort while in READY: no procedure is "
                                         "running$"):
        sup.abort(5.0, WHO)
    with pytest.raises(StateError, match="^cannot reset while in READY: nothing is "
                                         "latched$"):
        sup.reset(5.0, WHO, estop_released=True, faults_cleared=True)


def test_estop_outranks_fault():
    """Issue 4 safety (ESTOP outranks FAULT): a fault in ESTOP stays ESTOP (the cause is
    recorded); an e-stop in FAULT moves to ESTOP; the stop stays latched throughout."""
    sup = in_state(S.ESTOP)
    assert sup.fault(2.0, "camera_stall:left", "stuck") is False
    assert sup.state is S.ESTOP
    assert [(c.kind, c.source) for c in sup.reasons] == [("estop", "input"),
                                                        ("fault", "camera_stall:left")]
    sup = in_state(S.FAULT)
    assert sup.estop(2.0, "input", "e-stop pressed") is True
    assert sup.state is S.ESTOP and sup.stop.latched
    assert [h.to_state for h in sup.history] == [S.FAULT, S.ESTOP]


@pytest.mark.parametrize("state", [S.FAULT, S.ESTOP])
@pytest.mark.parametrize(("released", "cleared", "why"), [
    (False, True, "e-stop input is still pressed"),
    (True, False, "fault condition has not cleared"),
    (False, False, "e-stop input is still pressed"),
])
def test_reset_refused_until_the_cause_clears(state, released, cleared, why):
    """Issue 4 safety (reset): reset is refused while the e-stop input is pressed or the
    fault has not cleared, saying which, and nothing changes."""
    sup = in_state(state)
    before = sup.snapshot(history=1000)
    with pytest.raises(StateError, match=why):
        sup.reset(5.0, WHO, estop_released=released, faults_cleared=cleared)
    assert sup.snapshot(history=1000) == before


def test_reset_records_who_and_clears_the_latch():
    """Issue 4 safety (reset): a reset by a named operator once the cause cleared goes to
    IDLE, clears the stop and the causes, and the history records who and what it was;
    READY follows on the next healthy report."""
    sup = in_state(S.RUNNING)
    sup.fault(5.0, "deadline:misses", "5 consecutive control periods late")
    sup.reset(6.0, WHO, estop_released=True, faults_cleared=True)
    assert sup.state is S.IDLE and not sup.stop.latched and sup.reasons == ()
    last = sup.history[-1]
    assert (last.time, last.from_state, last.to_state, last.who) == (6.0, S.FAULT, S.IDLE,
                                                                     WHO)
    assert "deadline:misses" in last.reason
    sup.mark_ready(7.0)
    assert sup.state is S.READY


def test_fault_fires_the_latched_stop_synchronously():
    """Issue 4 safety: entering FAULT or ESTOP fires the latched stop before the call
    returns; the handler already sees the new state and motion is not allowed."""
    sup = in_state(S.RUNNING)
    seen = []
    sup.stop.add_handler(lambda r: seen.append((sup.state, sup.motion_allowed, r.source)))
    sup.fault(5.0, "stale_pose:opener", "old")
    assert seen == [(S.FAULT, False, "stale_pose:opener")]
    sup.fault(5.5, "stale_pose:opener", "older")  # no state change: not called again
    assert len(seen) == 1
    sup.estop(6.0, "rest", "STOP")  # an escalation: every handler is told again
    assert seen[-1] == (S.ESTOP, False, "rest")
    assert [r.source for r in sup.stop.records] == ["stale_pose:opener"] * 2 + ["rest"]


def test_handler_reading_snapshot_does_not_deadlock():
    """Issue 4 safety (nothing on the stop path blocks): a stop handler that reads the
    supervisor's snapshot in the same thread returns."""
    sup = in_state(S.READY)
    snaps = []
    sup.stop.add_handler(lambda: snaps.append(sup.snapshot()["state"]))
    sup.fault(2.0, "x", "y")
    assert snaps == ["FAULT"]


def test_fault_never_raises():
    """Issue 4 safety (fault and estop never raise): malformed arguments still latch."""
    sup = in_state(S.RUNNING)
    assert sup.fault(float("nan"), "", "") is True
    assert sup.state is S.FAULT and sup.stop.latched
    assert sup.estop(object(), None, None) is True  # type: ignore[arg-type]
    assert sup.state is S.ESTOP
    json.dumps(sup.snapshot())


def test_repeated_faults_keep_the_first_reason_per_source():
    """Issue 4 safety (active reasons): a watchdog tripping on every check while latched
    keeps its first reason as the cause; other sources add theirs."""
    sup = in_state(S.RUNNING)
    for k in range(50):
        sup.fault(5.0 + k, "stale_pose:opener", f"{k} s old")
    sup.fault(60.0, "driver_silence:arm", "silent")
    assert [str(c) for c in sup.reasons] == ["stale_pose:opener: 0 s old",
                                             "driver_silence:arm: silent"]
    assert [t.to_state for t in sup.history].count(S.FAULT) == 1


def test_history_is_bounded_and_snapshot_is_json():
    """Issue 4 safety (status): the history is a bounded deque of (time, from, to, who,
    reason); snapshot() is JSON-able and names the state, operator and reasons."""
    sup = SafetySupervisor(history=5)
    for k in range(10):
        sup.mark_ready(float(2 * k))
        sup.mark_not_ready(float(2 * k + 1), f"lost {k}")
    assert len(sup.history) == 5
    assert sup.history[-1].reason == "lost 9"
    sup.mark_ready(30.0)
    sup.start(31.0, WHO)
    snap = json.loads(json.dumps(sup.snapshot()))
    assert snap["state"] == "RUNNING" and snap["motion_allowed"] is True
    assert snap["operator"] == WHO and snap["since"] == 31.0
    assert snap["history"][-1] == {"time": 31.0, "from": "READY", "to": "RUNNING",
                                   "who": WHO, "reason": "procedure started"}
    assert snap["stop"]["latched"] is False


def test_latched_stop_behind_the_supervisor_blocks_motion():
    """Issue 4 safety (defence in depth): if the stop is triggered directly (not through
    fault/estop), motion is not allowed and start is refused until a reset."""
    sup = in_state(S.RUNNING)
    sup.stop.trigger(5.0, "direct", "wired straight to the stop")
    assert sup.state is S.RUNNING and not sup.motion_allowed
    sup.abort(6.0, WHO)
    with pytest.raises(StateError, match="latched stop is latched"):
        sup.start(7.0, WHO)


def test_bad_time_is_refused_on_requests():
    """Issue 4 safety (clear errors): a non-finite time on an operator request is an
    InputError and changes nothing."""
    sup = in_state(S.READY)
    with pytest.raises(InputError, match="finite"):
        sup.start(float("inf"), WHO)
    assert sup.state is S.READY


def test_concurrent_faults_and_requests_stay_consistent():
    """Issue 4 safety (thread-safe): a control thread faulting while the event loop
    starts, pauses and resumes ends latched in FAULT with the stop fired once per
    handler and a history whose transitions chain."""
    sup = in_state(S.READY)
    calls = []
    sup.stop.add_handler(lambda: calls.append(1))
    barrier = threading.Barrier(2)

    def operator() -> None:
        barrier.wait()
        for k in range(200):
            try:
                sup.start(float(k), WHO)
                sup.pause(float(k), WHO)
                sup.resume(float(k), WHO)
                sup.abort(float(k), WHO)
            except StateError:
                pass

    def control() -> None:
        barrier.wait()
        for k in range(200):
            if k == 100:
                sup.fault(float(k), "deadline:hard", "late")
            _ = sup.motion_allowed

    threads = [threading.Thread(target=operator), threading.Thread(target=control)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sup.state is S.FAULT and sup.stop.latched and calls == [1]
    hist = sup.history
    for a, b in zip(hist, hist[1:], strict=False):
        assert a.to_state is b.from_state


@pytest.mark.parametrize("latch", ["fault", "estop"])
@pytest.mark.parametrize("during", [S.RUNNING, S.PAUSED])
def test_a_latch_interrupts_the_procedure_which_resumes_or_aborts_after_reset(latch, during):
    """Issue 30 (reset after a stop mid-procedure): a latch during a procedure keeps it as
    interrupted, never running; after the reset and READY the operator resumes it (RUNNING)
    or aborts it (READY, dropped); start is refused meanwhile, naming both choices."""
    sup = in_state(during)
    ACTIONS[latch](sup)
    assert sup.interrupted is not None and sup.interrupted["by"] == WHO
    assert "interrupted" in json.dumps(sup.snapshot())
    assert not sup.motion_allowed
    with pytest.raises(StateError, match="reset first"):
        sup.resume(11.0, WHO)
    sup.reset(12.0, WHO, estop_released=True, faults_cleared=True)
    assert sup.state is S.IDLE
    with pytest.raises(StateError, match="not ready"):
        sup.resume(12.5, WHO)
    sup.mark_ready(13.0)
    with pytest.raises(StateError, match="resume or abort it first"):
        sup.start(14.0, WHO)
    assert sup.state is S.READY
    sup.resume(15.0, "dr.jones")
    assert sup.state is S.RUNNING and sup.motion_allowed and sup.interrupted is None
    assert sup.snapshot()["operator"] == "dr.jones"
    # a second stop, then abort instead: the procedure is dropped, READY stays
    sup.estop(16.0, "rest", "again")
    sup.reset(17.0, WHO, estop_released=True, faults_cleared=True)
    sup.mark_ready(18.0)
    sup.abort(19.0, WHO)
    assert sup.state is S.READY and sup.interrupted is None
    with pytest.raises(StateError, match="no procedure is running"):
        sup.resume(20.0, WHO)
    sup.start(21.0, WHO)
    assert sup.state is S.RUNNING


def test_an_interrupted_procedure_may_be_aborted_while_still_latched():
    """Issue 30: /procedure/abort of an interrupted procedure is accepted while FAULT is
    latched (the latch stays until its reset); a latch outside a procedure interrupts
    nothing."""
    sup = in_state(S.RUNNING)
    sup.fault(5.0, "stale_pose:goal", "old")
    sup.abort(6.0, WHO)
    assert sup.state is S.FAULT and sup.interrupted is None
    with pytest.raises(StateError, match="reset first"):
        sup.abort(7.0, WHO)
    idle = in_state(S.READY)
    idle.estop(5.0, "rest", "drill")
    assert idle.interrupted is None
