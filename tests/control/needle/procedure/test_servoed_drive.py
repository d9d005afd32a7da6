"""The drive servoed on the tracked needle (issue 36 item 1): through an arm's kinematic
error it puts the needle where the plan does, and a servo guard stops the arm where it
is, naming the cause, before any further motion.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from oralnav.control.needle.procedure import ProcedureSettings
from oralnav.control.needle.servo import ServoSettings

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
    """Issue 36, bad input: the tracker loses the needle at the servo's third look of
    the drive; the drive fails with ``servo_lost`` naming the pose, and the driver has
    not moved since that look (no command on a lost track)."""
    cell, proc = _to_the_drive(2, SERVOED)
    look = proc._look
    calls, poses = [], []

    def losing(*a, **k):
        tr = look(*a, **k)
        calls.append(1)
        poses.append(cell.gripper_pose(proc.driver))
        # ND looks at the start and after the approach, then the servo's: its third
        # is the fifth look of ND
        return replace(tr, converged=False, reason="test: lost") if len(calls) == 5 else tr
    proc._look = losing
    r = proc.run("ND")
    assert not r.ok and r.cause == "servo_lost", r
    assert "drive pose" in r.detail and "test: lost" in r.detail
    assert len(calls) == 5
    np.testing.assert_array_equal(cell.gripper_pose(proc.driver), poses[-1])
