"""Issue 8, backend 4: the UR arm through ur-rtde (URArm), against the fake UR controller.

Every test runs the real ur_rtde client (RTDEReceiveInterface, RTDEControlInterface,
DashboardClient) on loopback against :class:`oralnav.sim.peers.ur.FakeURController`,
which runs in a child process (ur_rtde's constructors hold the GIL). ur_rtde fixes the
ports (30004, 30003, 29999), so each fake gets its own loopback address.
"""

from __future__ import annotations

import itertools
import math
import os
import time

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from oralnav.drivers.arm import open_arm
from oralnav.drivers.arm.ur import URArm
from oralnav.drivers.errors import DriverInitError, DriverIOError
from oralnav.sim.peers.ur import FakeURControllerProcess

H = 0.002  # control period, s (500 Hz)
HOME = [0.35, -0.12, 0.28, 2.9, 0.4, -0.3]  # m, rotation vector: a tilted tool
_hosts = itertools.count(1)


def next_host() -> str:
    """A fresh loopback address per fake (127.0.0.0/8 is all loopback on Linux)."""
    return f"127.83.{os.getpid() % 250}.{next(_hosts) % 250 + 1}"


@pytest.fixture
def fake():
    ctrl = FakeURControllerProcess(next_host(), home=HOME)
    ctrl.start()
    yield ctrl
    ctrl.stop()


def make_arm(fake, **kwargs) -> URArm:
    # Watchdog and staleness a little looser than on a robot PC: the machine running the tests
    # may be busy. Tests about them set their own.
    opts = dict(host=fake.host, lookahead_time=0.05, gain=500.0, watchdog_timeout=0.25,
                stale_timeout=0.5, connect_timeout=1.0, reconnect_backoff=(0.1, 0.4))
    opts.update(kwargs)
    return URArm(**opts)


def wait_for(predicate, timeout: float, what: str, period: float = 0.005):
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(period)


def run_loop(arm: URArm, seconds: float, target=None, twist=None, accel: float = 0.5,
             kick: bool = True) -> None:
    """The 500 Hz control loop, roughly: a set point and a kick every cycle."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        if target is not None:
            arm.servo(target, H)
        if twist is not None:
            arm.speed(np.asarray(twist, dtype=float), accel)
        if kick:
            arm.kick()
        arm.state()
        time.sleep(H)


def offset_pose(T: np.ndarray, dp) -> np.ndarray:
    out = T.copy()
    out[:3, 3] += dp
    return out


# -- connecting ------------------------------------------------------------------------------


@pytest.mark.parametrize("series, rate", [("e", 500.0), ("cb3", 125.0)])
async def test_connect_reads_pose_force_and_timestamps_at_the_controller_rate(series, rate):
    """issue 8 UR: start() connects RTDEReceive/RTDEControl to the controller at its rate
    (500 Hz e-Series, 125 Hz CB3, frequency=None); state() is connected and ready with the
    fake's TCP pose (rotation vector -> 4x4) and wrench, and timestamps on the driver clock
    advance by one controller period per package."""
    with FakeURControllerProcess(next_host(), home=HOME, series=series) as fake:
        fake.apply_wrench([1.0, -2.0, 3.0, 0.1, 0.2, 0.3])
        async with make_arm(fake) as arm:
            s = wait_for(lambda: (st := arm.state()).tcp_force[2] == 3.0 and st, 1.0, "force")
            assert s.connected and s.ready and not s.protective_stop and not s.emergency_stop
            np.testing.assert_allclose(s.T_B_tcp, fake.pose_matrix(), atol=1e-9)
            np.testing.assert_allclose(s.T_B_tcp[:3, :3],
                                       Rotation.from_rotvec(HOME[3:]).as_matrix(), atol=1e-9)
            np.testing.assert_allclose(s.tcp_force, [1.0, -2.0, 3.0, 0.1, 0.2, 0.3])
            stamps = []
            end = time.monotonic() + 0.3
            while time.monotonic() < end:
                stamps.append(arm.state().timestamp)
                time.sleep(0.0005)
            steps = np.diff(np.unique(stamps)) * rate  # in controller periods
            assert len(steps) > 0.3 * rate * 0.25  # packages seen (a busy machine skips some)
            # stamped by the controller's clock: one period apart from package to package
            # (polls a busy machine misses, and the driver-clock mapping's corrections, make
            # the other steps)
            assert np.mean(np.abs(steps - 1.0) < 1e-3) > 0.25, np.round(steps, 3)
            assert abs(stamps[-1] - time.monotonic()) < 0.05  # mapped onto the driver clock
            assert arm.diagnostics()["program_running"]
            assert fake.status()["connections"].count("rtde") == 2


async def test_registry_builds_the_ur_backend_and_rejects_bad_options():
    """issue 8 UR: open_arm("ur", ...) builds a URArm (no I/O); bad options are a
    DriverInitError naming the option (ur_rtde's servoL ranges for lookahead and gain)."""
    arm = open_arm("ur", name="left", host="10.0.0.7")
    assert isinstance(arm, URArm) and arm.name == "left" and arm.host == "10.0.0.7"
    await arm.close()  # safe before start
    await arm.close()
    for bad, what in [(dict(host=""), "host"), (dict(lookahead_time=0.5), "lookahead_time"),
                      (dict(gain=50), "gain"), (dict(watchdog_timeout=0), "watchdog_timeout"),
                      (dict(frequency=1000), "frequency"),
                      (dict(reconnect_backoff=(2, 1)), "reconnect_backoff")]:
        kwargs = dict(host="10.0.0.7") | bad
        with pytest.raises(DriverInitError, match=what):
            URArm(**kwargs)


async def test_wrong_host_or_port_fails_fast_naming_host_and_port():
    """issue 8 UR: a controller address nothing answers on (nothing listening, or an
    unroutable address) gives a DriverInitError naming host and port within a few seconds;
    a controller whose dashboard server is not on 29999 (ur_rtde's fixed port) names that
    port. The arm can be closed afterwards."""
    silent = next_host()
    arm = URArm(host=silent, connect_timeout=0.5)
    t0 = time.monotonic()
    with pytest.raises(DriverInitError, match=rf"{silent}:29999 \(dashboard server\)"):
        await arm.start()
    assert time.monotonic() - t0 < 3.0
    await arm.close()

    arm = URArm(host="192.0.2.1", connect_timeout=0.5)  # TEST-NET-1: never routed
    t0 = time.monotonic()
    with pytest.raises(DriverInitError, match=r"192\.0\.2\.1:29999"):
        await arm.start()
    assert time.monotonic() - t0 < 3.0

    with FakeURControllerProcess(next_host(), dashboard_port=29998) as fake:
        arm = make_arm(fake)
        with pytest.raises(DriverInitError, match=rf"{fake.host}:29999 \(dashboard server\)"):
            await arm.start()
        await arm.close()


async def test_refused_recipe_names_the_field_and_start_recovers():
    """issue 8 UR: an RTDE output field the controller answers NOT_FOUND, or an input
    register it answers IN_USE, fails start() with a DriverInitError naming the field; no
    crash, and start() succeeds once the controller accepts the recipe again."""
    with FakeURControllerProcess(next_host()) as fake:
        arm = make_arm(fake)
        fake.refuse_field("actual_TCP_force")
        with pytest.raises(DriverInitError, match=r"actual_TCP_force NOT_FOUND"):
            await arm.start()
        fake.accept_all_fields()
        fake.refuse_field("input_int_register_0", "IN_USE")
        with pytest.raises(DriverInitError, match=r"input_int_register_0 IN_USE"):
            await arm.start()
        fake.accept_all_fields()
        await arm.start()
        assert arm.state().ready
        await arm.close()


# -- motion ----------------------------------------------------------------------------------


async def test_servo_moves_toward_the_target_with_the_configured_lookahead_and_gain(fake):
    """issue 8 UR: servo() at 500 Hz drives servoL: the fake's TCP moves to the target and
    the state follows; the controller received servoL with the pose (rotation vector), the
    period as time, and lookahead_time / gain from the constructor; the watchdog was armed
    (setWatchdog at 1 / watchdog_timeout Hz) before the first servoL."""
    async with make_arm(fake, lookahead_time=0.07, gain=800.0) as arm:
        start = arm.state().T_B_tcp
        target = offset_pose(start, [0.02, -0.01, 0.005])
        run_loop(arm, 0.5, target=target)
        np.testing.assert_allclose(fake.pose_matrix()[:3, 3], target[:3, 3], atol=1e-3)
        wait_for(lambda: np.allclose(arm.state().T_B_tcp, fake.pose_matrix(), atol=1e-4), 0.5,
                 "state to follow")
        servos = fake.commands("servoL")
        assert len(servos) > 50
        last = servos[-1].args
        np.testing.assert_allclose(last["target"][:3], target[:3, 3], atol=1e-12)
        np.testing.assert_allclose(Rotation.from_rotvec(last["target"][3:]).as_matrix(),
                                   target[:3, :3], atol=1e-9)
        assert (last["time"], last["lookahead_time"], last["gain"]) == (H, 0.07, 800.0)
        names = [c.name for c in fake.commands()]
        assert names.index("setWatchdog") < names.index("servoL")
        assert fake.commands("setWatchdog")[0].args["min_frequency"] == pytest.approx(4.0)


async def test_speed_moves_at_the_twist_and_stop_halts(fake):
    """issue 8 UR: speed() drives speedL: the TCP reaches the twist and moves at it; stop()
    returns at once and the controller decelerates to a stand-still (speedStop with at least
    stop_decel); a later servo() switches mode (the fake saw the stop first)."""
    async with make_arm(fake, stop_decel=4.0) as arm:
        p0 = fake.pose()[:3]
        twist = [0.0, 0.04, -0.02, 0.0, 0.0, 0.1]
        run_loop(arm, 0.4, twist=twist, accel=1.0)
        np.testing.assert_allclose(fake.tcp_speed(), twist, atol=1e-9)
        assert fake.pose()[1] - p0[1] > 0.04 * 0.25
        t0 = time.perf_counter()
        arm.stop()
        assert time.perf_counter() - t0 < 0.005  # never blocks
        run_loop(arm, 0.1)  # kicks only
        assert fake.motion() == "hold"
        np.testing.assert_allclose(fake.tcp_speed(), 0.0, atol=1e-12)
        stop = fake.commands("speedStop")[-1]
        assert stop.args["deceleration"] >= 4.0
        target = arm.state().T_B_tcp
        run_loop(arm, 0.05, target=target)
        assert fake.commands("servoL")
        assert fake.program_running()


async def test_watchdog_kicks_keep_the_arm_going_and_silence_stops_it(fake):
    """issue 8 UR: the RTDE input watchdog: with a kick every cycle (and no new command) the
    control program keeps running and the arm keeps its twist for many watchdog periods;
    when the kicks stop for longer than watchdog_timeout the controller (as the real script's
    rtde_set_watchdog(..., "stop")) stops the program and the arm; the driver then reads not
    ready and refuses commands until recover()."""
    async with make_arm(fake, watchdog_timeout=0.1) as arm:
        run_loop(arm, 0.05, twist=[0.03, 0.0, 0.0, 0.0, 0.0, 0.0], accel=1.0)
        run_loop(arm, 0.6)  # 6 watchdog periods of kicks only
        assert fake.program_running()
        assert fake.tcp_speed()[0] == pytest.approx(0.03)
        assert fake.command_counts()["no_cmd"] >= 12
        time.sleep(0.3)  # the control loop stalls
        trips = fake.events("watchdog_tripped")
        assert len(trips) == 1 and trips[0][2]["variable"] == "input_int_register_0"
        wait_for(lambda: fake.motion() == "hold", 0.5, "the arm to stop")
        s = wait_for(lambda: (st := arm.state()).connected and not st.ready and st, 0.5,
                     "not ready")
        assert not s.protective_stop
        with pytest.raises(DriverIOError, match="control program stopped"):
            arm.servo(s.T_B_tcp, H)
        arm.kick()  # the link is up: a kick is no error
        await arm.recover()
        run_loop(arm, 0.05, target=arm.state().T_B_tcp)
        assert fake.watchdog() is not None and arm.state().ready


# -- safety stops and recovery ---------------------------------------------------------------


async def test_protective_stop_shows_refuses_commands_and_recovery_waits_for_the_request(fake):
    """issue 8 UR: a protective stop in the controller shows in state() (protective_stop,
    not ready) and motion commands raise DriverIOError; stop() and kick() do not raise. The
    driver never touches the dashboard by itself: only recover() unlocks the stop and
    restarts the control program, after which servo works and re-arms the watchdog."""
    async with make_arm(fake) as arm:
        run_loop(arm, 0.1, target=offset_pose(arm.state().T_B_tcp, [0.01, 0, 0]))
        programs = len(fake.programs())
        fake.inject_protective_stop()
        s = wait_for(lambda: (st := arm.state()).protective_stop and st, 0.5, "protective")
        assert s.connected and not s.ready and not s.emergency_stop
        assert arm.fault == "in protective stop"
        with pytest.raises(DriverIOError, match="servo refused: arm in protective stop"):
            arm.servo(s.T_B_tcp, H)
        with pytest.raises(DriverIOError, match="speed refused: arm in protective stop"):
            arm.speed(np.zeros(6), 1.0)
        arm.stop()
        arm.kick()
        time.sleep(0.3)
        assert not [c for c, _ in fake.dashboard_log() if "unlock" in c]  # never automatic
        assert len(fake.programs()) == programs and arm.state().protective_stop
        await arm.recover()
        log = [c for c, _ in fake.dashboard_log()]
        assert "unlock protective stop" in log
        assert len(fake.programs()) == programs + 1  # the control script uploaded again
        s = arm.state()
        assert s.ready and not s.protective_stop
        before = len(fake.commands("setWatchdog"))
        run_loop(arm, 0.05, target=s.T_B_tcp)
        assert len(fake.commands("setWatchdog")) == before + 1


async def test_emergency_stop_shows_refuses_commands_and_recovers_after_release(fake):
    """issue 8 UR: an emergency stop shows in state() (emergency_stop, not ready) and
    commands raise; recover() refuses while the e-stop is pressed; once it is released,
    recover() powers on, releases the brakes and restarts the program."""
    async with make_arm(fake) as arm:
        fake.inject_emergency_stop()
        s = wait_for(lambda: (st := arm.state()).emergency_stop and st, 0.5, "e-stop")
        assert s.connected and not s.ready
        with pytest.raises(DriverIOError, match="arm in emergency stop"):
            arm.servo(s.T_B_tcp, H)
        arm.stop()
        with pytest.raises(DriverIOError, match="emergency stop is still pressed"):
            await arm.recover()
        fake.release_emergency_stop()
        wait_for(lambda: not arm.state().emergency_stop, 0.5, "release")
        assert not arm.state().ready  # powered off
        await arm.recover()
        log = [c for c, _ in fake.dashboard_log()]
        assert log.index("power on") < log.index("brake release")
        assert arm.state().ready
        run_loop(arm, 0.05, target=offset_pose(arm.state().T_B_tcp, [0.0, 0.0, 0.01]))
        assert fake.program_running()


async def test_start_during_a_protective_stop_connects_then_recovers_on_request():
    """issue 8 UR: a robot already in protective stop at start(): the driver connects and
    reads the stop (no control script uploaded, ready False) instead of failing; recover()
    unlocks it and opens the control interface."""
    with FakeURControllerProcess(next_host(), home=HOME) as fake:
        fake.inject_protective_stop()
        async with make_arm(fake) as arm:
            s = arm.state()
            assert s.connected and s.protective_stop and not s.ready
            assert not fake.programs()
            assert "protective stop" in arm.fault
            await arm.recover()
            assert arm.state().ready and len(fake.programs()) == 1


# -- losing the controller -------------------------------------------------------------------


async def test_controller_vanishes_then_returns_and_the_driver_reconnects(fake):
    """issue 8 UR: the controller vanishes (connections closed, nothing listening): state()
    reads disconnected at once, servo/speed/kick raise DriverIOError, stop() only logs; the
    arm's own watchdog stops it. When the controller returns the driver reconnects with
    back-off (the control script is uploaded again) and re-arms the watchdog with the next
    motion command."""
    async with make_arm(fake) as arm:
        T = arm.state().T_B_tcp
        run_loop(arm, 0.1, target=offset_pose(T, [0.0, 0.01, 0.0]))
        programs = len(fake.programs())
        fake.vanish()
        s = wait_for(lambda: (st := arm.state()) and not st.connected and st, 0.5,
                     "disconnected")
        assert not s.ready
        with pytest.raises(DriverIOError, match="servo refused: arm disconnected"):
            arm.servo(T, H)
        with pytest.raises(DriverIOError, match="disconnected"):
            arm.speed(np.zeros(6), 1.0)
        with pytest.raises(DriverIOError, match="kick"):
            arm.kick()
        arm.stop()  # logs, never raises
        assert "disconnected" in arm.fault
        wait_for(lambda: fake.events("watchdog_tripped"), 0.5, "the controller's watchdog")
        time.sleep(0.4)  # a few failed reconnection attempts
        fake.come_back()
        s = wait_for(lambda: arm.reconnects == 1 and (st := arm.state()).ready and st, 5.0,
                     "reconnected and ready")
        assert s.connected
        assert len(fake.programs()) == programs + 1
        assert fake.watchdog() is None  # the new program is not armed yet ...
        run_loop(arm, 0.05, target=offset_pose(T, [0.0, 0.0, 0.0]))
        assert fake.watchdog() == {"variable": "input_int_register_0", "min_frequency": 4.0}
        assert fake.program_running()


async def test_a_recipe_refused_while_reconnecting_is_named_and_retried(fake):
    """issue 8 UR: the controller comes back refusing an RTDE field: each reconnection
    attempt fails naming the field (arm.fault), with back-off, without a crash; once the
    controller accepts the recipe again the driver reconnects."""
    async with make_arm(fake) as arm:
        fake.refuse_field("safety_status_bits")
        fake.kill_connections()
        wait_for(lambda: "safety_status_bits NOT_FOUND" in (arm.fault or ""), 3.0,
                 "the refusal named")
        assert not arm.state().connected
        with pytest.raises(DriverIOError, match="disconnected"):
            arm.servo(arm.state().T_B_tcp, H)
        fake.accept_all_fields()
        wait_for(lambda: arm.state().ready, 5.0, "reconnected")
        assert arm.reconnects == 1 and arm.fault is None


async def test_killed_connections_are_reopened(fake):
    """issue 8 UR: the controller drops every connection but stays up: the driver tears
    ur_rtde down (its own half-working auto-reconnect included) and reconnects; the arm is
    ready again."""
    async with make_arm(fake) as arm:
        run_loop(arm, 0.05, target=arm.state().T_B_tcp)
        fake.kill_connections()
        wait_for(lambda: arm.reconnects >= 1 and arm.state().ready, 5.0, "reconnected")
        run_loop(arm, 0.05, target=arm.state().T_B_tcp)
        assert fake.program_running() and arm.state().ready


async def test_a_silent_controller_reads_disconnected_until_data_flows_again(fake):
    """issue 8 UR: a controller that keeps its connections but stops sending (hung): the
    timestamps stop, and after stale_timeout the arm reads disconnected and refuses
    commands; when data flows again it reads connected (no reconnection needed)."""
    async with make_arm(fake, stale_timeout=0.1, link_timeout=5.0) as arm:
        fake.freeze()
        t_frozen = arm.state().timestamp
        s = wait_for(lambda: (st := arm.state()) and not st.connected and st, 1.0, "stale")
        assert s.timestamp == pytest.approx(t_frozen, abs=0.01)
        with pytest.raises(DriverIOError, match="disconnected"):
            arm.servo(s.T_B_tcp, H)
        fake.unfreeze()
        wait_for(lambda: arm.state().connected, 1.0, "fresh data")
        assert arm.reconnects == 0


async def test_calls_from_the_control_thread_do_not_wait_for_the_controller(fake):
    """issue 8 UR: servo/kick/state stay fast while the command thread waits for a stop
    to complete (ur_rtde's stops block until the script reports done)."""
    async with make_arm(fake, stop_decel=1.0, watchdog_timeout=0.5) as arm:
        run_loop(arm, 0.3, twist=[0.1, 0.0, 0.0, 0.0, 0.0, 0.0], accel=2.0)
        arm.stop()  # ~0.1 s of braking, spent in the command thread
        worst = 0.0
        for _ in range(20):
            t0 = time.perf_counter()
            arm.kick()
            s = arm.state()
            worst = max(worst, time.perf_counter() - t0)
            time.sleep(H)
        assert worst < 0.01
        assert math.isfinite(s.timestamp)
        wait_for(lambda: fake.motion() == "hold", 1.0, "stand-still")
