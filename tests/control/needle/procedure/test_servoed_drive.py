"""The drive servoed on the tracked needle (issue 36 item 1): through an arm's kinematic
error it puts the needle where the plan does, looking every few poses or fed frame by
frame by a tracking task, and a servo guard stops the arm where it is, naming the cause,
before any further motion.
"""

from __future__ import annotations

import copy
import math
import threading
from dataclasses import replace

import numpy as np
import pytest

from oralnav.control.needle.procedure import ProcedureSettings
from oralnav.control.needle.servo import ServoSettings
from oralnav.realtime.needle_tracking import start_tracking

from .cells import _ports, _procedure

SERVOED = ProcedureSettings(drive_servo=ServoSettings())
#: 1 mm and 0.5 deg between each arm's reported and true tool (``--arm-error 1 0.5``)
ARM_ERROR = (0.001, math.radians(0.5))


def _to_the_drive(seed: int, settings: ProcedureSettings, **cell_options):
    cell, proc = _procedure(seed, settings=settings, **_ports(ProcedureSettings()),
                            **cell_options)
    for step in ("NG", "NH"):
        r = proc.run(step)
        assert r.ok and r.truth_ok, r
    return cell, proc


def test_a_track_lost_mid_drive_stops_the_arm_where_it_is():
    """Issue 36, bad input: the tracker loses the needle (off the wire, not merely
    uncertain) at the servo's look after drive pose 8; the drive fails with
    ``servo_lost`` naming the pose, and the driver has not moved since that look (no
    command on a lost track)."""
    cell, proc = _to_the_drive(2, SERVOED)
    look, move = proc._look, proc._move
    moves, poses = [], []

    def moving(arm, T, what, *a, **k):
        moves.append(what)
        return move(arm, T, what, *a, **k)

    def losing(*a, **k):
        tr = look(*a, **k)
        poses.append(cell.gripper_pose(proc.driver))
        if moves and moves[-1].startswith("drive pose 8 of"):
            return replace(tr, converged=False, reason="test: lost",
                           held_reason="test: lost")
        return tr
    proc._look, proc._move = losing, moving
    r = proc.run("ND")
    assert not r.ok and r.cause == "servo_lost", r
    assert r.detail.startswith("drive pose 8 of") and "test: lost" in r.detail, r.detail
    assert moves[-1].startswith("drive pose 8 of")
    np.testing.assert_array_equal(cell.gripper_pose(proc.driver), poses[-1])


def test_the_servoed_drive_corrects_an_arm_error_before_the_tip_enters():
    """Issue 36, item 1: trial 103 with a 1 mm / 0.5 deg error on each arm, whose
    open-loop drive enters 2.9 mm off the plan (``oralnav bench needle --seed 103
    --arm-error 1 0.5``): servoed, the look at the approach finds the centre 2.4 mm off
    and correct it before the tip touches the tissue, the drive passes and the truth
    agrees, the servo having learnt from looks over the first 30 deg of the turn or more."""
    cell, proc = _to_the_drive(103, replace(SERVOED, arm_accuracy=ARM_ERROR),
                               arm_error=ARM_ERROR)
    r = proc.run("ND")
    assert r.ok and r.truth_ok, r
    f = r.figures
    assert f["servo_first_error_mm"] > 2.0 and f["servo_last_error_mm"] < 0.3, f
    assert f["servo_span_deg"] >= 30.0, f


# -- streamed: the servo fed by a tracking task (realtime/needle_tracking.py) -----------

STREAMED = replace(SERVOED, arm_accuracy=ARM_ERROR, stream_timeout=0.3)


@pytest.fixture(scope="module")
def streamed_103():
    """Trial 103 with 1 mm / 0.5 deg arm errors at the drive (NG and NH passed), its
    procedure fed by the tracking task; each test drives a copy."""
    cell, proc = _to_the_drive(103, STREAMED, arm_error=ARM_ERROR)
    proc.feed = start_tracking
    return cell, proc


def _copy(streamed):
    cell, proc = copy.deepcopy(streamed)
    proc.cell = cell
    return cell, proc


def _recording_moves(cell, proc):
    """Record the driver's reported pose after every move, and what each move was."""
    move, moves = proc._move, []

    def moving(arm, T, what, *a, **k):
        move(arm, T, what, *a, **k)
        moves.append((what, cell.gripper_pose(arm)))
    proc._move = moving
    return moves


def test_the_streamed_drive_corrects_on_every_frame(streamed_103):
    """Issue 36, item 1: streamed, trial 103's drive is corrected on each tracked frame
    where the arc shows, from the approach's 2.4 mm to within 0.3 mm, and passes (truth
    too); every command has its capture-to-command time, every tracked frame its work,
    and the arm moved one drive pose per frame used."""
    cell, proc = _copy(streamed_103)
    r = proc.run("ND")
    assert r.ok and r.truth_ok, r
    f = r.figures
    assert f["servo_first_error_mm"] > 2.0 and f["servo_last_error_mm"] < 0.3, f
    k = f["servo_streamed_poses"]
    # most frames are used (which are depends a little on the machine's pace: a frame
    # shows the state commanded up to two commands before)
    assert k >= 8 and f["servo_looks"] >= k // 2, f
    assert len(f["servo_latency_ms"]) == k - 1 and all(v > 0 for v in f["servo_latency_ms"])
    assert len(f["servo_track_ms"]) >= k and f["servo_rate_hz"] > 0, f
    assert len(f["servo_prepare_ms"]) >= len(f["servo_track_ms"]), f


def test_a_stalled_stream_stops_the_streamed_drive_where_it_is(streamed_103):
    """Issue 36, bad input: the frame stream stalls after the sixth capture. The drive
    fails with ``servo_stale`` within ``stream_timeout``, naming the pose, and the driver
    has not moved since its last command."""
    cell, proc = _copy(streamed_103)
    moves = _recording_moves(cell, proc)
    hold = threading.Event()

    def stalling(capture, prepare, track):
        count = [0]

        def stalls():
            count[0] += 1
            if count[0] > 6:
                hold.wait(5.0)
            return capture()
        return start_tracking(stalls, prepare, track)
    proc.feed = stalling
    try:
        r = proc.run("ND")
    finally:
        hold.set()
    assert not r.ok and r.cause == "servo_stale", r
    assert "drive pose" in r.detail and "within 300 ms" in r.detail, r.detail
    np.testing.assert_array_equal(cell.gripper_pose(proc.driver), moves[-1][1])


@pytest.mark.parametrize("fault, cause", [("lost", "servo_lost"), ("jump", "servo_jump"),
                                          ("one_lost", None)])
def test_a_lost_or_jumping_track_stops_the_streamed_drive(streamed_103, fault, cause):
    """Issue 36, bad input: from the eighth tracked frame on the tracker loses the
    needle, or at the eighth sees it 3 mm from where the tool's motion puts it (a slip,
    a twin). A jump fails the drive on that frame: the driver is not commanded on it (at
    most the one command in flight when it was taken). A lost track fails it once the
    frames of ``servo_every`` poses in a row are lost (4), the arm having gone on on the
    model meanwhile, as the looks servo goes between looks; a single lost frame is not a
    lost track, and the drive passes."""
    cell, proc = _copy(streamed_103)
    moves = _recording_moves(cell, proc)
    marks = []

    def faulty(capture, prepare, track):
        def tracks(payload, meta, previous):
            tr = track(payload, meta, previous)
            marks.append(len(moves))
            n = len(marks)
            if (fault == "lost" and n >= 8) or (fault == "one_lost" and n == 8):
                return replace(tr, converged=False, reason="test: lost",
                               held_reason="test: lost")
            if fault == "jump" and n == 8:
                pose = tr.pose.copy()
                pose[:3, 3] += [0.003, 0.0, 0.0]
                return replace(tr, pose=pose)
            return tr
        return start_tracking(capture, prepare, tracks)
    proc.feed = faulty
    r = proc.run("ND")
    if cause is None:
        assert r.ok and r.truth_ok and r.figures["servo_unused_looks"] >= 1, r
        return
    assert not r.ok and r.cause == cause, r
    np.testing.assert_array_equal(cell.gripper_pose(proc.driver), moves[-1][1])
    if fault == "jump":
        assert len(moves) <= marks[7] + 1, (len(moves), marks[7])
    else:
        assert "4 frames lost in a row" in r.detail, r.detail
        # three lost frames went on on the model, the fourth stopped the drive
        assert len(moves) <= marks[7] + 4, (len(moves), marks[7])
