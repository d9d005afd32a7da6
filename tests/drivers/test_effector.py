"""Issue 4 drivers: wrist kinematics, the end-effector contract and the simulated wrist."""

from __future__ import annotations

import logging
import math

import numpy as np
import pytest

from oralnav.drivers.clock import VirtualClock
from oralnav.drivers.effector import (
    JOINTS,
    EffectorCommandError,
    WristKinematics,
    open_effector,
)
from oralnav.drivers.effector.kinematics import DEFAULT_COUPLING
from oralnav.drivers.effector.sim import SimEffector
from oralnav.drivers.errors import DriverInitError, DriverIOError

H = 0.002


def test_joints_motors_round_trip_through_the_coupling():
    """issue 4 drivers: motors_to_joints(joints_to_motors(q)) == q over the joint range, and
    the motor angles are C q + m0."""
    offset = [0.1, -0.2, 0.3, 0.0]
    kin = WristKinematics(motor_offset=offset)
    rng = np.random.default_rng(4)
    for _ in range(200):
        q = rng.uniform(kin.joint_min, kin.joint_max)
        m = kin.joints_to_motors(q)
        assert np.allclose(m, DEFAULT_COUPLING @ q + offset)
        assert np.allclose(kin.motors_to_joints(m), q, atol=1e-12)


def test_default_coupling_routes_yaw_and_jaw_tendons_over_the_pitch_pulley():
    """issue 4 drivers: in the example coupling, pitching alone turns the pitch, yaw and jaw
    motors (the yaw and jaw tendons wrap the pitch pulley); yaw or jaw alone turn one motor."""
    kin = WristKinematics()
    pitch_only = kin.joints_to_motors([0.0, 0.5, 0.0, 0.0])
    assert np.allclose(pitch_only, [0.0, 0.6, 0.3, 0.3])
    assert np.allclose(kin.joints_to_motors([0.0, 0.0, 0.5, 0.0]), [0, 0, 0.5, 0])
    assert np.allclose(kin.joints_to_motors([0.0, 0.0, 0.0, 0.5]), [0, 0, 0, 0.5])
    assert JOINTS == ("roll", "pitch", "yaw", "jaw")


def test_limits_are_checked_with_errors_naming_joint_and_limit():
    """issue 4 drivers: check_joints refuses a joint outside its limits, or a pose whose motor
    angles leave the motor travel, naming the joint (or motor), the value and the limit."""
    kin = WristKinematics()
    assert np.array_equal(kin.check_joints(kin.joint_max), kin.joint_max)  # limits included
    with pytest.raises(EffectorCommandError,
                       match=r"joint 'pitch' = 1\.6000 rad \(91\.7 deg\) is above its upper "
                             r"limit 1\.3963 rad \(80\.0 deg\)"):
        kin.check_joints([0.0, 1.6, 0.0, 0.0])
    with pytest.raises(EffectorCommandError, match="joint 'jaw' .* below its lower limit 0.0000"):
        kin.check_joints([0.0, 0.0, 0.0, -0.1])
    tight = WristKinematics(motor_min=[-4, -4, -1.0, -4], motor_max=[4, 4, 1.0, 4])
    with pytest.raises(EffectorCommandError, match="motor 'yaw' .* above its upper limit 1.0"):
        tight.check_joints([0.0, 1.0, 0.8, 0.0])  # yaw motor = 0.6 * 1.0 + 0.8 = 1.4
    for bad, why in [([0, 0, 0], r"shape \(4,\)"), ([0, math.nan, 0, 0], "non-finite"),
                     ("x", "4 numbers")]:
        with pytest.raises(EffectorCommandError, match=why):
            kin.check_joints(bad)
    with pytest.raises(EffectorCommandError, match="motor 'roll'"):
        kin.check_motors([7.0, 0, 0, 0])
    assert issubclass(EffectorCommandError, DriverIOError)
    assert issubclass(EffectorCommandError, ValueError)


def test_coupling_must_be_invertible_and_limits_well_formed():
    """issue 4 drivers: a singular or ill-conditioned coupling, or an empty joint or motor
    range, is refused at construction with DriverInitError."""
    singular = DEFAULT_COUPLING.copy()
    singular[3] = singular[2]  # yaw and jaw motors driven identically: jaw is unobservable
    with pytest.raises(DriverInitError, match="singular or ill-conditioned"):
        WristKinematics(coupling=singular)
    with pytest.raises(DriverInitError, match="singular or ill-conditioned"):
        WristKinematics(coupling=np.diag([1.0, 1.0, 1.0, 1e-9]))
    with pytest.raises(DriverInitError, match="4x4"):
        WristKinematics(coupling=np.eye(3))
    with pytest.raises(DriverInitError, match="joint 'yaw': joint_min 0.5 must be below"):
        WristKinematics(joint_min=[-1, -1, 0.5, 0], joint_max=[1, 1, 0.5, 1])
    with pytest.raises(DriverInitError, match="motor_max"):
        WristKinematics(motor_max=[1, 1, 1])
    kin = WristKinematics()
    with pytest.raises(ValueError):
        kin.coupling[0, 0] = 2.0  # immutable


async def test_sim_wrist_moves_within_its_joint_speed_limit():
    """issue 4 drivers: the sim wrist moves every joint toward the command at no more than
    max_joint_speed, reaches it, and reports motors consistent with its joints."""
    clock = VirtualClock()
    speeds = np.array([3.0, 1.0, 1.5, 2.0])
    wrist = SimEffector(clock=clock, max_joint_speed=speeds)
    target = np.array([1.0, -0.6, 0.9, 0.8])
    async with wrist:
        wrist.command(target)
        prev = wrist.state()
        for _ in range(600):
            clock.advance(H)
            wrist.advance(H)
            s = wrist.state()
            assert (np.abs(s.joints - prev.joints) <= speeds * H + 1e-12).all()
            assert np.allclose(s.motors, wrist.kinematics.joints_to_motors(s.joints))
            prev = s
        assert np.allclose(s.joints, target) and s.timestamp == clock.now()
        assert s.connected and s.fault is None
        # The slowest joint (pitch, 0.6 rad at 1 rad/s) needed 0.6 s: 300 periods.
        assert np.isclose(s.joints[1], target[1])


async def test_out_of_limit_commands_are_refused_not_clamped():
    """issue 4 drivers: a command outside the limits raises and leaves the wrist where it was
    going; nothing is clamped."""
    clock = VirtualClock()
    wrist = SimEffector(clock=clock)
    async with wrist:
        with pytest.raises(EffectorCommandError, match="joint 'roll'"):
            wrist.command([4.0, 0.0, 0.0, 0.0])
        for _ in range(10):
            clock.advance(H)
            wrist.advance(H)
        assert not wrist.state().joints.any()
        assert wrist.command_log == []  # never reached the device


async def test_stop_holds_position_and_never_raises(caplog):
    """issue 4 drivers: stop() holds the current joints; it never raises (not started,
    disconnected, closed, a failing backend)."""
    clock = VirtualClock()
    wrist = SimEffector(clock=clock, max_joint_speed=1.0)
    wrist.stop()
    async with wrist:
        wrist.command([0.0, 0.5, 0.0, 0.0])
        for _ in range(50):
            clock.advance(H)
            wrist.advance(H)
        wrist.stop()
        held = wrist.state().joints.copy()
        for _ in range(50):
            clock.advance(H)
            wrist.advance(H)
        assert np.array_equal(wrist.state().joints, held) and 0 < held[1] < 0.5
        wrist.inject_disconnect()
        with caplog.at_level(logging.WARNING):
            wrist.stop()
        assert "while disconnected" in caplog.text
        with pytest.raises(DriverIOError, match="disconnected"):
            wrist.command(held)

        def broken() -> None:
            raise RuntimeError("bus off")

        wrist._stop = broken  # type: ignore[method-assign]
        wrist.stop()
        assert "bus off" in caplog.text
    wrist.stop()
    assert [c.kind for c in wrist.command_log] == ["stop", "command", "stop", "stop", "command"]


async def test_fault_and_silence_injections():
    """issue 4 drivers: an injected fault is reported, makes the wrist hold and refuse
    commands; silence stops the state timestamp; clear() ends both."""
    clock = VirtualClock()
    wrist = SimEffector(clock=clock)
    async with wrist:
        wrist.command([0.0, 0.0, 0.0, 0.5])
        clock.advance(H)
        wrist.advance(H)
        wrist.inject_fault("tendon slack on motor 3")
        s = wrist.state()
        assert s.fault == "tendon slack on motor 3"
        with pytest.raises(DriverIOError, match="tendon slack"):
            wrist.command([0.0, 0.0, 0.0, 0.5])
        clock.advance(H)
        wrist.advance(H)
        assert np.array_equal(wrist.state().joints, s.joints)  # holds
        wrist.inject_silence()
        for _ in range(5):
            clock.advance(H)
            wrist.advance(H)
        assert wrist.state().timestamp == s.timestamp + H < clock.now()
        wrist.clear()
        wrist.command([0.0, 0.0, 0.0, 0.5])
        clock.advance(H)
        wrist.advance(H)
        s = wrist.state()
        assert s.fault is None and s.timestamp == clock.now() and s.joints[3] > 2 * H


async def test_lifecycle_and_registry():
    """issue 4 drivers: open_effector('sim') builds an unstarted wrist; commands need start()
    and fail after close(); close() is idempotent; bad construction is refused."""
    wrist = open_effector("sim", clock=VirtualClock())
    with pytest.raises(DriverIOError, match="not started"):
        wrist.command(np.zeros(4))
    assert not wrist.state().connected
    await wrist.start()
    with pytest.raises(DriverInitError, match="twice"):
        await wrist.start()
    wrist.command(np.zeros(4))
    await wrist.close()
    await wrist.close()
    with pytest.raises(DriverIOError, match="closed"):
        wrist.command(np.zeros(4))
    for bad in ([1.0, 0.0, 1.0, 1.0], [1.0, 2.0], "fast"):
        with pytest.raises(DriverInitError, match="max_joint_speed"):
            SimEffector(max_joint_speed=bad)
    with pytest.raises(DriverInitError, match="initial"):
        SimEffector(initial=[0.0, 3.0, 0.0, 0.0])
