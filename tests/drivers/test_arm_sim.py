"""Issue 4 drivers: the arm contract and the simulated arm (SimArm)."""

from __future__ import annotations

import logging
import math
import threading

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from oralnav.drivers.arm import ArmCommandError, ArmState
from oralnav.drivers.arm.sim import DEFAULT_HOME, SimArm
from oralnav.drivers.clock import VirtualClock
from oralnav.drivers.errors import DriverInitError, DriverIOError

H = 0.002  # control period, s (500 Hz)
EPS = 1e-9


def make_arm(**kwargs) -> tuple[SimArm, VirtualClock]:
    clock = VirtualClock()
    return SimArm(clock=clock, **kwargs), clock


def tick(arm: SimArm, clock: VirtualClock, dt: float = H) -> ArmState:
    clock.advance(dt)
    arm.advance(dt)
    return arm.state()


def pose(offset=(0.0, 0.0, 0.0), rotvec=(0.0, 0.0, 0.0), base=DEFAULT_HOME) -> np.ndarray:
    T = base.copy()
    T[:3, 3] += offset
    T[:3, :3] = (Rotation.from_rotvec(rotvec) * Rotation.from_matrix(base[:3, :3])).as_matrix()
    return T


def angle_between(R1: np.ndarray, R2: np.ndarray) -> float:
    return float(np.linalg.norm((Rotation.from_matrix(R1) * Rotation.from_matrix(R2).inv())
                                .as_rotvec()))


async def test_servo_sequence_respects_speed_and_acceleration_limits():
    """issue 4 drivers: over a servo sequence with far, switching targets, the sim arm never
    exceeds its linear and angular speed and acceleration limits (checked on the reported
    twist and on the pose itself)."""
    arm, clock = make_arm(max_speed=0.25, max_angular_speed=1.0, max_accel=1.0,
                          max_angular_accel=4.0)
    targets = [pose((0.15, 0.05, -0.1), (0.8, 0.0, 0.3)), pose((-0.1, 0.1, 0.05), (-0.5, 0.4, 0)),
               pose((0.0, -0.12, 0.0), (0.0, 0.0, -1.2)), pose()]
    async with arm:
        prev = arm.state()
        peak = np.zeros(2)
        for k in range(4 * 200):  # each target for 0.4 s, switched mid-motion
            arm.servo(targets[k // 200], H)
            s = tick(arm, clock)
            v, w = np.linalg.norm(s.tcp_speed[:3]), np.linalg.norm(s.tcp_speed[3:])
            assert v <= 0.25 + EPS and w <= 1.0 + EPS
            dv = np.linalg.norm(s.tcp_speed[:3] - prev.tcp_speed[:3]) / H
            dw = np.linalg.norm(s.tcp_speed[3:] - prev.tcp_speed[3:]) / H
            assert dv <= 1.0 + 1e-6 and dw <= 4.0 + 1e-6
            step = np.linalg.norm(s.T_B_tcp[:3, 3] - prev.T_B_tcp[:3, 3])
            assert step <= 0.25 * H + EPS
            assert angle_between(s.T_B_tcp[:3, :3], prev.T_B_tcp[:3, :3]) <= 1.0 * H + 1e-7
            peak = np.maximum(peak, [v, w])
            prev = s
        assert peak[0] > 0.24 and peak[1] > 0.99  # the limits were actually reached


async def test_servo_reaches_the_target_and_settles():
    """issue 4 drivers: servoing to a fixed target reaches it (position and orientation) and
    the arm comes to rest there."""
    arm, clock = make_arm()
    target = pose((0.05, -0.03, 0.02), (0.1, -0.2, 0.3))
    async with arm:
        for _ in range(600):
            arm.servo(target, H)
            s = tick(arm, clock)
        assert np.linalg.norm(s.T_B_tcp[:3, 3] - target[:3, 3]) < 1e-6
        assert angle_between(s.T_B_tcp[:3, :3], target[:3, :3]) < 1e-6
        assert np.linalg.norm(s.tcp_speed) < 1e-6
        assert s.ready and s.connected and s.timestamp == pytest.approx(clock.now())


async def test_speed_ramps_to_clamped_twist_and_stop_decelerates_then_holds():
    """issue 4 drivers: speed() ramps at the asked acceleration to the twist (clamped to the
    speed limit); stop() decelerates within max_accel to a stand-still and the arm then stays
    still."""
    arm, clock = make_arm(max_speed=0.25, max_accel=1.0)
    async with arm:
        arm.speed([0.0, 0.0, 0.5, 0.0, 0.0, 0.0], 0.5)  # 0.5 m/s asked, 0.25 m/s allowed
        for _ in range(50):
            arm.kick()
            s = tick(arm, clock)
        assert s.tcp_speed[2] == pytest.approx(0.5 * 50 * H)  # ramping at 0.5 m/s^2
        for _ in range(500):
            arm.kick()
            s = tick(arm, clock)
        assert np.allclose(s.tcp_speed, [0, 0, 0.25, 0, 0, 0])
        arm.stop()
        speeds = []
        for _ in range(200):
            s = tick(arm, clock)
            speeds.append(np.linalg.norm(s.tcp_speed))
        decel = -np.diff([0.25, *speeds]) / H
        assert (decel >= -EPS).all() and (decel <= 1.0 + 1e-6).all()
        assert speeds[-1] == 0.0
        assert speeds.index(0.0) == pytest.approx(0.25 / 1.0 / H, abs=1)  # v / a
        still = s.T_B_tcp.copy()
        for _ in range(100):
            s = tick(arm, clock)
        assert np.array_equal(s.T_B_tcp, still) and not s.tcp_speed.any()
        arm.stop()  # idempotent
        assert np.array_equal(tick(arm, clock).T_B_tcp, still)


async def test_watchdog_stops_an_arm_that_is_not_kicked():
    """issue 4 drivers: a moving arm that gets neither a command nor a kick within
    watchdog_timeout stops itself; regular kicks keep it going."""
    arm, clock = make_arm(watchdog_timeout=0.05)
    async with arm:
        arm.speed([0.1, 0, 0, 0, 0, 0], 1.0)
        for _ in range(100):  # 0.2 s of kicks every period
            arm.kick()
            tick(arm, clock)
        assert arm.watchdog_trips == 0 and arm.state().tcp_speed[0] == pytest.approx(0.1)
        t_last = clock.now()
        while clock.now() - t_last <= 0.05 + EPS:
            s = tick(arm, clock)
        # The deadline has just passed: it is braking now and then stands still.
        for _ in range(100):
            s = tick(arm, clock)
        assert arm.watchdog_trips == 1 and not s.tcp_speed.any()
        # The watchdog is not a latch: a new command moves the arm again.
        arm.speed([0.1, 0, 0, 0, 0, 0], 1.0)
        assert tick(arm, clock).tcp_speed[0] > 0


async def test_watchdog_acts_when_it_expires_even_if_the_host_stalled():
    """issue 30 (hung control process): the simulated arm's watchdog stops it
    watchdog_timeout after the last command, as a controller on its own machine would, even
    when its host stalls for seconds and then advances it in one go: the arm ends where a
    host that had kept running (advancing period by period) leaves it."""
    results = []
    for stalled in (False, True):
        arm, clock = make_arm(watchdog_timeout=0.05)
        async with arm:
            arm.speed([0.1, 0, 0, 0, 0, 0], 1.0)
            for _ in range(100):
                arm.kick()
                tick(arm, clock)
            x0 = arm.state().T_B_tcp[0, 3]
            if stalled:  # the process was stopped for 3 s, then resumed
                s = tick(arm, clock, 3.0)
            else:
                for _ in range(1500):
                    s = tick(arm, clock)
            assert arm.watchdog_trips == 1 and not s.tcp_speed.any()
            results.append(s.T_B_tcp[0, 3] - x0)
    # 0.05 s at 0.1 m/s, then braking: millimetres, not the 0.3 m of 3 s at speed
    assert 0.004 < results[0] < 0.02
    assert results[1] == pytest.approx(results[0], abs=2e-4)


async def test_watchdog_keeps_running_while_disconnected():
    """issue 4 drivers: when the link drops the arm goes on with its last command only until
    its watchdog stops it."""
    arm, clock = make_arm(watchdog_timeout=0.05)
    async with arm:
        arm.speed([0, 0.1, 0, 0, 0, 0], 1.0)
        for _ in range(100):
            arm.kick()
            tick(arm, clock)
        arm.inject_disconnect()
        with pytest.raises(DriverIOError, match="disconnected"):
            arm.kick()
        for _ in range(200):
            s = tick(arm, clock)
        assert not s.tcp_speed.any() and arm.watchdog_trips == 1 and not s.connected


@pytest.mark.parametrize("fault", ["protective", "emergency", "disconnect"])
async def test_motion_is_refused_while_the_arm_cannot_obey(fault):
    """issue 4 drivers: servo and speed raise DriverIOError after a protective stop, an
    emergency stop or a disconnect (the caller never believes it moves); a protective or
    emergency stop also brakes the arm; once cleared, commands work again."""
    arm, clock = make_arm()
    async with arm:
        arm.speed([0.1, 0, 0, 0, 0, 0], 1.0)
        for _ in range(50):
            arm.kick()
            tick(arm, clock)
        inject, clear, words = {
            "protective": (arm.inject_protective_stop, arm.clear_protective_stop,
                           "in protective stop"),
            "emergency": (arm.inject_emergency_stop, arm.clear_emergency_stop,
                          "in emergency stop"),
            "disconnect": (arm.inject_disconnect, arm.reconnect, "disconnected"),
        }[fault]
        inject()
        s = arm.state()
        assert not s.ready
        assert s.protective_stop == (fault == "protective")
        assert s.emergency_stop == (fault == "emergency")
        assert s.connected == (fault != "disconnect")
        with pytest.raises(DriverIOError, match=f"servo refused: arm {words}"):
            arm.servo(s.T_B_tcp, H)
        with pytest.raises(DriverIOError, match=f"speed refused: arm {words}"):
            arm.speed(np.zeros(6), 1.0)
        if fault != "disconnect":
            for _ in range(10):
                arm.kick()  # the link is up: kicking is fine, but it does not move the arm
                s = tick(arm, clock)
            assert s.tcp_speed[0] < 0.1 - 10 * H * 1.0 + 1e-9  # braking at max_accel
        clear()
        assert arm.state().ready
        arm.servo(arm.state().T_B_tcp, H)


async def test_motion_is_refused_outside_start_and_close():
    """issue 4 drivers: servo before start() or after close() raises DriverIOError; close()
    stops the arm and is idempotent; start() twice is refused."""
    arm, clock = make_arm()
    with pytest.raises(DriverIOError, match="not started"):
        arm.servo(DEFAULT_HOME, H)
    await arm.start()
    with pytest.raises(DriverInitError, match="twice"):
        await arm.start()
    arm.speed([0.1, 0, 0, 0, 0, 0], 1.0)
    tick(arm, clock)
    await arm.close()
    await arm.close()
    with pytest.raises(DriverIOError, match="closed"):
        arm.servo(DEFAULT_HOME, H)
    # Refused calls are logged too; each close() stopped the arm first.
    assert [c.kind for c in arm.command_log] == ["servo", "speed", "stop", "stop", "servo"]
    for _ in range(100):
        s = tick(arm, clock)
    assert not s.tcp_speed.any() and not s.connected and not s.ready


async def test_stop_never_raises(caplog):
    """issue 4 drivers: stop() never raises: not started, disconnected, closed, or with a
    backend whose stop fails (the failure is logged)."""
    arm, clock = make_arm()
    arm.stop()
    await arm.start()
    arm.inject_disconnect()
    with caplog.at_level(logging.WARNING):
        arm.stop()
    assert "while disconnected" in caplog.text
    arm.reconnect()

    def broken() -> None:
        raise RuntimeError("socket gone")

    arm._stop = broken  # type: ignore[method-assign]
    with caplog.at_level(logging.ERROR):
        arm.stop()
    assert "socket gone" in caplog.text
    await arm.close()  # close() stops first; even a failing stop does not stop close()
    arm.stop()


async def test_command_log_records_every_motion_call_with_clock_time():
    """issue 4 drivers: command_log holds (clock time, kind) for every servo/speed/stop call,
    refused ones included, bounded in size; it lets a test assert that no motion command
    came after a stop."""
    arm, clock = make_arm(log_size=5)
    async with arm:
        arm.servo(DEFAULT_HOME, H)
        tick(arm, clock)
        arm.speed(np.zeros(6), 1.0)
        tick(arm, clock)
        t_stop = clock.now()
        arm.stop()
        tick(arm, clock)
        kick_time = clock.now()
        arm.kick()  # not a motion command: not logged
        assert [(c.time, c.kind) for c in arm.command_log] == [
            (pytest.approx(0.0), "servo"), (pytest.approx(H), "speed"),
            (pytest.approx(t_stop), "stop")]
        assert not [c for c in arm.command_log if c.time > t_stop and c.kind != "stop"]
        assert kick_time > t_stop
        arm.inject_protective_stop()
        with pytest.raises(DriverIOError):
            arm.servo(DEFAULT_HOME, H)
        assert arm.command_log[-1].kind == "servo"  # refused, still logged
        for _ in range(5):
            arm.stop()
        assert len(arm.command_log) == 5 and {c.kind for c in arm.command_log} == {"stop"}
        t, kind = arm.command_log[0]
        assert kind == "stop"


async def test_freeze_makes_a_silent_driver():
    """issue 4 drivers: after freeze() the state timestamp (and pose) stop advancing while
    the clock and the arm go on; unfreeze() resumes."""
    arm, clock = make_arm()
    async with arm:
        arm.speed([0.05, 0, 0, 0, 0, 0], 1.0)
        tick(arm, clock)
        arm.freeze()
        frozen = arm.state()
        for _ in range(10):
            arm.kick()
            s = tick(arm, clock)
        assert s.timestamp == frozen.timestamp < clock.now()
        assert np.array_equal(s.T_B_tcp, frozen.T_B_tcp)
        arm.unfreeze()
        s = tick(arm, clock)
        assert s.timestamp == clock.now() and s.T_B_tcp[0, 3] > frozen.T_B_tcp[0, 3]


def test_inputs_are_validated_with_messages_naming_the_argument():
    """issue 4 drivers: malformed poses, periods, twists and accelerations are refused with
    ArmCommandError (a DriverIOError and a ValueError) naming the argument; bad constructor
    arguments raise DriverInitError."""
    arm, _ = make_arm()
    skew = DEFAULT_HOME.copy()
    skew[0, 1] = 0.3
    nan = DEFAULT_HOME.copy()
    nan[0, 3] = math.nan
    bottom = DEFAULT_HOME.copy()
    bottom[3, 0] = 1.0
    mirror = DEFAULT_HOME @ np.diag([1.0, 1.0, -1.0, 1.0])
    for bad, why in [(skew, "proper rotation"), (nan, "non-finite"), (bottom, "bottom row"),
                     (mirror, "proper rotation"), (np.eye(3), r"shape \(4, 4\)"),
                     ("abc", "4x4")]:
        with pytest.raises(ArmCommandError, match=f"T_B_tcp .*{why}"):
            arm.servo(bad, H)
    for dt in (0.0, -H, math.nan, None):
        with pytest.raises(ArmCommandError, match="dt must be"):
            arm.servo(DEFAULT_HOME, dt)  # type: ignore[arg-type]
    with pytest.raises(ArmCommandError, match="twist has non-finite"):
        arm.speed([0, 0, math.inf, 0, 0, 0], 1.0)
    with pytest.raises(ArmCommandError, match=r"twist must have shape \(6,\)"):
        arm.speed([0, 0, 0], 1.0)
    with pytest.raises(ArmCommandError, match="accel must be"):
        arm.speed(np.zeros(6), 0.0)
    assert issubclass(ArmCommandError, DriverIOError) and issubclass(ArmCommandError, ValueError)
    assert arm.command_log == []  # malformed calls never reach the backend
    with pytest.raises(DriverInitError, match="max_speed"):
        SimArm(max_speed=-1.0)
    with pytest.raises(DriverInitError, match="home"):
        SimArm(home=skew)


def test_state_is_a_frozen_read_only_snapshot():
    """issue 4 drivers: ArmState is immutable and its arrays are read-only copies."""
    arm, _ = make_arm()
    s = arm.state()
    with pytest.raises(AttributeError):
        s.ready = True  # type: ignore[misc]
    with pytest.raises(ValueError):
        s.T_B_tcp[0, 3] = 1.0
    assert s.T_B_tcp.shape == (4, 4) and s.tcp_speed.shape == (6,)
    assert np.array_equal(s.T_B_tcp, DEFAULT_HOME)


async def test_control_thread_and_simulation_can_share_the_arm():
    """issue 4 drivers: a control thread servoing and kicking while another thread advances
    the simulation and reads states: no errors, every state well formed, target reached."""
    # The simulation runs on virtual time faster than the OS schedules the control thread,
    # so the watchdog is set long here; it has its own tests.
    arm, clock = make_arm(watchdog_timeout=100.0)
    target = pose((0.02, 0.0, 0.0))
    errors: list[BaseException] = []
    done = threading.Event()
    servoed = threading.Event()

    def control() -> None:
        try:
            while not done.is_set():
                arm.servo(target, H)
                servoed.set()
                arm.kick()
                s = arm.state()
                assert s.T_B_tcp.shape == (4, 4) and np.isfinite(s.tcp_speed).all()
        except BaseException as exc:  # reported to the test thread
            errors.append(exc)
            servoed.set()

    async with arm:
        thread = threading.Thread(target=control)
        thread.start()
        try:
            assert servoed.wait(5.0)
            for _ in range(1000):
                s = tick(arm, clock)
                if np.linalg.norm(s.T_B_tcp[:3, 3] - target[:3, 3]) < 1e-6:
                    break
        finally:
            done.set()
            thread.join()
        assert not errors
        assert np.linalg.norm(arm.state().T_B_tcp[:3, 3] - target[:3, 3]) < 1e-6


def _push_along_x(t: float, T_B_tcp: np.ndarray) -> np.ndarray:
    """A force source for the test below: 2 N per second of clock time, along base x,
    and the TCP's height as the torque about z (so the pose it is given shows)."""
    return np.array([2.0 * t, 0.0, 0.0, 0.0, 0.0, T_B_tcp[2, 3]])


async def test_force_source_feeds_the_force_sensor(caplog):
    """issue 6, item 5 (GUIDE on the control process): the ``force_source`` option is what
    the force sensor reads after each advance, given the clock time and the new TCP pose;
    a bad value (wrong size, non-finite, an exception) reads as zero and is logged; the
    option must be callable."""
    arm, clock = make_arm(force_source=_push_along_x)
    async with arm:
        assert np.all(arm.state().tcp_force == 0.0)        # nothing before an advance
        clock.advance(0.5)
        arm.advance(0.5)
        f = arm.state().tcp_force
        assert f[0] == pytest.approx(2.0 * clock.now()) and f[5] == pytest.approx(0.3)
        for bad in (lambda t, T: [1.0, 2.0], lambda t, T: [math.nan, 0.0, 0.0],
                    lambda t, T: 1 / 0):
            arm._force_source = bad
            with caplog.at_level(logging.ERROR):
                tick(arm, clock)
            assert np.all(arm.state().tcp_force == 0.0)
        assert "force_source" in caplog.text
    with pytest.raises(DriverInitError, match="force_source"):
        SimArm(force_source=3.0)
