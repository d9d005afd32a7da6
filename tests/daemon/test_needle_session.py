"""Issue 7 item 7 and the brief's "the robot stops rather than guesses": a needle step the
daemon runs is stopped by the safety state while it runs, not only before it starts. A
stop halts the arm within one motion increment (1 mm, 2 deg); the step fails with
``move_stopped`` naming the safety state, and nothing moves after it."""

from __future__ import annotations

import numpy as np

from oralnav.daemon.needle_session import NeedleSession

STOP = "the safety state is ESTOP: reset first"


def test_a_stop_during_a_step_halts_the_arm_where_it_is() -> None:
    """NG on trial 0: motion is allowed for the first 25 asks (the step's own check, then
    the pick-up approach's increments), then refused. The step fails with move_stopped and
    the reason; the grippers' true poses are those of the moment the stop came."""
    asks = {"n": 0}
    at_stop: dict[str, np.ndarray] = {}

    def refused() -> str:
        asks["n"] += 1
        if asks["n"] <= 25:
            return ""
        if not at_stop:
            cell = session._proc.cell
            at_stop.update({g: cell.true_gripper_pose(g) for g in cell.grippers})
        return STOP

    session = NeedleSession(refused)
    session.load_trial(0, 1.0, "test")
    out = session.run_step("NG", "test")
    res = out["result"]
    assert not res["ok"] and res["cause"] == "move_stopped", res
    assert STOP in res["detail"] and "pick-up" in res["detail"]
    assert at_stop and asks["n"] == 26  # refused once: nothing asked to move after it
    cell = session._proc.cell
    for g, T in at_stop.items():
        assert np.array_equal(cell.true_gripper_pose(g), T)
    assert session.status()["running"] is None


def test_every_increment_of_a_step_asks_whether_it_may_move() -> None:
    """With motion allowed throughout, NG on trial 0 succeeds as it does outside the
    daemon, and the session asked before each of the many increments (not once a step)."""
    asks = {"n": 0}

    def refused() -> str:
        asks["n"] += 1
        return ""

    session = NeedleSession(refused)
    session.load_trial(0, 1.0, "test")
    res = session.run_step("NG", "test")["result"]
    assert res["ok"] and res["truth_ok"], res
    assert asks["n"] > 20


def test_a_stop_during_a_streamed_drive_halts_the_arm_and_ends_the_tracking_task() -> None:
    """Issue 36 item 1 ("the tracker runs in the daemon's task structure"): on a cell
    loaded with ``servo="stream"``, the drive takes its frames from the needle tracking
    task's threads. A stop that comes mid-drive halts the driver within one increment
    (move_stopped, naming the state), the task's threads end with the step, and the
    step's figures are lost with it, not the arm's position."""
    import threading

    stopped = {"now": False}
    at_stop: dict[str, np.ndarray] = {}

    def refused() -> str:
        if not stopped["now"]:
            return ""
        if not at_stop:
            cell = session._proc.cell
            at_stop.update({g: cell.true_gripper_pose(g) for g in cell.grippers})
        return STOP

    session = NeedleSession(refused)
    session.load_trial(102, 1.0, "test", servo="stream")
    assert session.status()["cell"]["servo"] == "stream"
    for step in ("NG", "NH"):
        assert session.run_step(step, "test")["result"]["ok"]
    proc = session._proc
    take = proc._features_of
    frames = {"n": 0}

    def counting(images):
        frames["n"] += 1
        if frames["n"] == 6:           # the stop comes while the streamed drive runs
            stopped["now"] = True
        return take(images)
    proc._features_of = counting
    res = session.run_step("ND", "test")["result"]
    assert not res["ok"] and res["cause"] == "move_stopped", res
    assert STOP in res["detail"] and "drive pose" in res["detail"], res["detail"]
    cell = proc.cell
    for g, T in at_stop.items():
        assert np.array_equal(cell.true_gripper_pose(g), T)
    assert not [t for t in threading.enumerate() if t.name.startswith("needle-tracking")]


def test_a_bad_servo_mode_is_refused_and_keeps_the_cell() -> None:
    session = NeedleSession(lambda: "")
    session.load_trial(0, 1.0, "test")
    try:
        session.load_trial(0, 1.0, "test", servo="fast")
    except ValueError as exc:
        assert "servo must be one of off, looks, stream" in str(exc)
    else:
        raise AssertionError("servo='fast' was accepted")
    assert session.status()["cell"]["servo"] == "off"
