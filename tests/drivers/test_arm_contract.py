"""Issue 8, contract tests: every arm backend, simulated and real, keeps the same promises
(drivers/arm/base.py): refused motion before start and after close, with stop() never raising
and close() idempotent; once started it is connected and ready, its timestamps advance, servo
reaches a nearby pose, speed moves the TCP in the commanded direction and stop() halts it;
malformed commands are refused with ArmCommandError before they reach the backend; a
protective stop shows in the state and refuses motion until it is cleared; a lost link reads
disconnected and refuses commands until it returns.

The simulated arm runs on the wall clock, moved in time by a thread (the simulated cell's
part). The UR backend runs the real ur_rtde client against the fake UR controller in a child
process (ur_rtde's constructors hold the GIL), each fake on its own loopback address (ur_rtde
fixes the ports). Both start from the same tilted tool pose.
"""

from __future__ import annotations

import itertools
import os
import threading
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass

import anyio
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from oralnav.drivers.arm import Arm, ArmCommandError, ArmState
from oralnav.drivers.arm.sim import SimArm
from oralnav.drivers.arm.ur import URArm
from oralnav.drivers.clock import WallClock
from oralnav.drivers.errors import DriverIOError
from oralnav.sim.peers.ur import FakeURControllerProcess

H = 0.002  # control period, s (500 Hz)
WAIT = 3.0  # s for a state change to show
RECONNECT_WAIT = 8.0  # s for a returned link to read connected (UR: back-off and ur_rtde setup)
HOME6 = [0.35, -0.12, 0.28, 2.9, 0.4, -0.3]  # m, rotation vector: a tilted tool
POS_TOL = 5e-4  # m: servo arrival, both backends
ROT_TOL = 2e-3  # rad
STILL = 1e-4  # m/s: a TCP speed that is ~0
# Watchdog looser than on a robot PC (the test machine may be busy); the same for both.
WATCHDOG = 0.25


def _home_matrix() -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(HOME6[3:]).as_matrix()
    T[:3, 3] = HOME6[:3]
    return T


@dataclass
class Harness:
    """A backend's arm and the hands that stop, break and mend it."""

    backend: str
    arm: Arm
    fresh: Callable[[], Arm]  # another unstarted arm of the same backend
    protective_stop: Callable[[], None]
    clear_protective_stop: Callable[[], Awaitable[None]]  # the stop cleared, arm ready again
    link_down: Callable[[], None]
    link_up: Callable[[], None]
    device_commands: Callable[[], int]  # motion commands the arm itself has received


async def _sim() -> AsyncIterator[Harness]:
    def build() -> SimArm:
        return SimArm(clock=WallClock(), home=_home_matrix(), watchdog_timeout=WATCHDOG)

    arm = build()
    done = threading.Event()

    def advance() -> None:  # the simulated cell's part: move the arm in wall-clock time
        last = time.monotonic()
        while not done.wait(H):
            now = time.monotonic()
            arm.advance(now - last)
            last = now

    mover = threading.Thread(target=advance, daemon=True, name="sim-arm-mover")
    mover.start()

    async def clear() -> None:
        arm.clear_protective_stop()

    def received() -> int:
        return sum(1 for c in arm.command_log if c.kind in ("servo", "speed"))

    try:
        yield Harness("sim", arm, build, arm.inject_protective_stop, clear,
                      arm.inject_disconnect, arm.reconnect, received)
    finally:
        done.set()
        mover.join(1.0)


_hosts = itertools.count(1)


def _start_fake() -> FakeURControllerProcess:
    """A fake UR controller on a fresh loopback address (another test run may hold one)."""
    for _ in range(5):
        host = f"127.84.{os.getpid() % 250}.{next(_hosts) % 250 + 1}"
        fake = FakeURControllerProcess(host, home=HOME6)
        try:
            fake.start()
        except OSError:
            continue
        return fake
    raise RuntimeError("no free loopback address for the fake UR controller")


async def _ur() -> AsyncIterator[Harness]:
    fake = _start_fake()

    def build() -> URArm:
        return URArm(host=fake.host, lookahead_time=0.05, gain=500.0,
                     watchdog_timeout=WATCHDOG, stale_timeout=0.5, connect_timeout=1.0,
                     reconnect_backoff=(0.1, 0.4))

    arm = build()

    async def clear() -> None:
        fake.clear_protective_stop()  # at the pendant
        await arm.recover()  # the operator's request restarts the control program

    def received() -> int:
        counts = fake.command_counts()
        return counts.get("servoL", 0) + counts.get("speedL", 0)

    try:
        yield Harness("ur", arm, build, fake.inject_protective_stop, clear, fake.vanish,
                      fake.come_back, received)
    finally:
        fake.stop()


@pytest.fixture(params=["sim", "ur"])
async def harness(request) -> AsyncIterator[Harness]:
    gen = {"sim": _sim, "ur": _ur}[request.param]()
    h = await gen.__anext__()
    try:
        yield h
    finally:
        await h.arm.close()
        await gen.aclose()


# -- helpers ---------------------------------------------------------------------------------


async def _until(pred: Callable[[ArmState], bool], arm: Arm, what: str,
                 timeout: float = WAIT) -> ArmState:
    """Poll state() (no commands) until ``pred`` holds; the state that satisfied it."""
    deadline = time.monotonic() + timeout
    while True:
        s = arm.state()
        if pred(s):
            return s
        assert time.monotonic() < deadline, f"timed out after {timeout} s waiting for {what}"
        await anyio.sleep(0.005)


async def _control(arm: Arm, done: Callable[[ArmState], bool], what: str, *,
                   target: np.ndarray | None = None, twist: np.ndarray | None = None,
                   accel: float = 0.5, timeout: float = WAIT) -> ArmState:
    """The control loop, roughly: each period a set point (if any) and a kick, until
    ``done(state)``; the state that satisfied it."""
    deadline = time.monotonic() + timeout
    while True:
        if target is not None:
            arm.servo(target, H)
        if twist is not None:
            arm.speed(twist, accel)
        arm.kick()
        s = arm.state()
        if done(s):
            return s
        assert time.monotonic() < deadline, f"timed out after {timeout} s waiting for {what}"
        await anyio.sleep(H)


async def _kicking(arm: Arm, seconds: float) -> ArmState:
    """The control loop with nothing to command for ``seconds``: a kick each period."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        arm.kick()
        await anyio.sleep(H)
    return arm.state()


async def _started(arm: Arm) -> ArmState:
    await arm.start()
    return await _until(lambda s: s.connected and s.ready, arm, "connected and ready")


def _nearby(T: np.ndarray, dp=(0.003, -0.002, 0.004), rotvec=(0.0, 0.0, 0.02)) -> np.ndarray:
    """``T`` moved by ``dp`` (m) and turned by ``rotvec`` (rad), both in the base frame."""
    out = np.array(T, dtype=float)
    out[:3, 3] += dp
    out[:3, :3] = (Rotation.from_rotvec(rotvec) * Rotation.from_matrix(T[:3, :3])).as_matrix()
    return out


def _errors(T: np.ndarray, target: np.ndarray) -> tuple[float, float]:
    """Position (m) and orientation (rad) error of ``T`` from ``target``."""
    dp = float(np.linalg.norm(T[:3, 3] - target[:3, 3]))
    dR = Rotation.from_matrix(T[:3, :3]) * Rotation.from_matrix(target[:3, :3]).inv()
    return dp, float(np.linalg.norm(dR.as_rotvec()))


def _arrived(target: np.ndarray) -> Callable[[ArmState], bool]:
    def check(s: ArmState) -> bool:
        dp, dr = _errors(s.T_B_tcp, target)
        return dp < POS_TOL and dr < ROT_TOL

    return check


def _still(s: ArmState) -> bool:
    return float(np.linalg.norm(s.tcp_speed[:3])) < STILL and float(
        np.linalg.norm(s.tcp_speed[3:])) < 10 * STILL


def _moving(s: ArmState) -> bool:
    return float(np.linalg.norm(s.tcp_speed[:3])) > 0.005


def _assert_motion_refused(arm: Arm, T: np.ndarray) -> None:
    """servo and speed raise DriverIOError for the arm's state, not for their arguments."""
    for command in (lambda: arm.servo(T, H), lambda: arm.speed(np.zeros(6), 0.5)):
        with pytest.raises(DriverIOError) as info:
            command()
        assert not isinstance(info.value, ArmCommandError), info.value


def _assert_off(arm: Arm) -> None:
    """An arm before start() or after close(): not connected, not ready, refuses motion
    and kicks, and stop() returns quietly."""
    s = arm.state()
    assert not s.connected and not s.ready
    _assert_motion_refused(arm, _home_matrix())
    with pytest.raises(DriverIOError):
        arm.kick()
    arm.stop()
    arm.stop()


# -- the contract ----------------------------------------------------------------------------


async def test_refused_before_start_and_after_close(harness: Harness):
    """issue 8 contract: before start() and after close() state() reads not connected (and
    not ready), servo/speed/kick raise DriverIOError and stop() never raises; close() is
    idempotent, also on an arm that was never started."""
    arm = harness.arm
    _assert_off(arm)
    await _started(arm)
    await arm.close()
    await arm.close()
    _assert_off(arm)

    spare = harness.fresh()
    await spare.close()
    await spare.close()
    _assert_off(spare)


async def test_started_arm_is_connected_ready_and_its_timestamp_advances(harness: Harness):
    """issue 8 contract: after start() the arm reads connected and ready, with no stop
    active, and state().timestamp keeps advancing with time (a live arm)."""
    arm = harness.arm
    s = await _started(arm)
    assert not s.protective_stop and not s.emergency_stop
    assert s.T_B_tcp.shape == (4, 4) and s.tcp_speed.shape == (6,)
    dp, dr = _errors(s.T_B_tcp, _home_matrix())
    assert dp < 1e-6 and dr < 1e-6  # the tool pose both backends start from
    stamps = []
    t0 = time.monotonic()
    while time.monotonic() - t0 < 0.2:
        stamps.append(arm.state().timestamp)
        await anyio.sleep(0.01)
    assert all(b >= a for a, b in itertools.pairwise(stamps))  # never back
    assert stamps[-1] - stamps[0] > 0.1  # moves with the ~0.2 s that passed


async def test_servo_reaches_a_nearby_pose(harness: Harness):
    """issue 8 contract: servo() every control period (with a kick) toward a pose a few mm
    and ~1 degree away brings the TCP there (within 0.5 mm and 2 mrad), and it stays."""
    arm = harness.arm
    start = await _started(arm)
    target = _nearby(start.T_B_tcp)
    assert _errors(start.T_B_tcp, target)[0] > 0.004
    await _control(arm, _arrived(target), "the servo target", target=target)
    s = await _control(arm, _still, "the TCP to settle", target=target)
    dp, dr = _errors(s.T_B_tcp, target)
    assert dp < POS_TOL and dr < ROT_TOL


async def test_speed_moves_in_the_commanded_direction_and_stop_halts(harness: Harness):
    """issue 8 contract: speed() (with a kick each period) moves the TCP along the commanded
    twist's direction at about its speed; stop() returns at once and brings the TCP speed to
    ~0, where it holds."""
    arm = harness.arm
    start = await _started(arm)
    twist = np.array([0.02, -0.015, 0.01, 0.0, 0.0, 0.0])
    u = twist[:3] / np.linalg.norm(twist[:3])
    p0 = start.T_B_tcp[:3, 3]

    def far_along(s: ArmState) -> bool:
        return float((s.T_B_tcp[:3, 3] - p0) @ u) > 0.004

    s = await _control(arm, far_along, "4 mm along the twist", twist=twist)
    d = s.T_B_tcp[:3, 3] - p0
    assert float(d @ u) / float(np.linalg.norm(d)) > 0.99  # along the commanded direction
    v = s.tcp_speed[:3]
    assert float(v @ u) == pytest.approx(float(np.linalg.norm(twist[:3])), rel=0.05)
    assert float(np.linalg.norm(v - (v @ u) * u)) < 1e-3
    assert float(np.linalg.norm(s.tcp_speed[3:])) < 1e-3

    t0 = time.perf_counter()
    arm.stop()
    assert time.perf_counter() - t0 < 0.05  # never blocks
    s = await _control(arm, _still, "the TCP to stop")  # kicks only
    held = s.T_B_tcp[:3, 3].copy()
    s = await _kicking(arm, 0.1)
    assert _still(s)
    assert float(np.linalg.norm(s.T_B_tcp[:3, 3] - held)) < 1e-4


async def test_malformed_commands_are_refused_and_never_reach_the_backend(
        harness: Harness, monkeypatch: pytest.MonkeyPatch):
    """issue 8 contract: a non-rigid, non-finite or wrongly shaped pose, a non-finite or
    wrongly shaped twist, dt <= 0 (or NaN) and accel <= 0 raise ArmCommandError; neither the
    backend's _servo/_speed nor the arm itself sees them, and the arm stays put and ready. A
    well-formed command afterwards does reach both (so the counting would have seen one)."""
    arm = harness.arm
    start = await _started(arm)
    T = start.T_B_tcp
    calls: list[str] = []
    backend_servo, backend_speed = arm._servo, arm._speed

    def spy_servo(*args):
        calls.append("servo")
        return backend_servo(*args)

    def spy_speed(*args):
        calls.append("speed")
        return backend_speed(*args)

    monkeypatch.setattr(arm, "_servo", spy_servo)
    monkeypatch.setattr(arm, "_speed", spy_speed)
    before = harness.device_commands()

    scaled = T.copy()
    scaled[:3, :3] *= 1.01
    sheared = T.copy()
    sheared[0, 1] += 0.01
    mirrored = T.copy()
    mirrored[:3, 0] *= -1.0  # orthonormal, det -1
    bottom = T.copy()
    bottom[3, 0] = 0.1
    nan_pose = T.copy()
    nan_pose[1, 3] = np.nan
    for bad in (scaled, sheared, mirrored, bottom, nan_pose, T[:3], "pose"):
        with pytest.raises(ArmCommandError):
            arm.servo(bad, H)
    for dt in (0.0, -H, np.nan, np.inf):
        with pytest.raises(ArmCommandError, match="dt"):
            arm.servo(T, dt)
    for bad in ([np.nan, 0, 0, 0, 0, 0], [0, 0, np.inf, 0, 0, 0], [0.01, 0, 0], None):
        with pytest.raises(ArmCommandError):
            arm.speed(bad, 0.5)
    for accel in (0.0, -1.0, np.nan):
        with pytest.raises(ArmCommandError, match="accel"):
            arm.speed(np.zeros(6), accel)

    await anyio.sleep(0.1)
    assert calls == []
    assert harness.device_commands() == before
    s = arm.state()
    assert s.connected and s.ready
    assert _errors(s.T_B_tcp, T)[0] < 1e-6 and _still(s)

    arm.servo(T, H)
    assert calls == ["servo"]
    await _control(arm, lambda _: harness.device_commands() > before, "the servo to arrive")


async def test_protective_stop_refuses_motion_until_cleared(harness: Harness):
    """issue 8 contract: a protective stop during a motion shows in state().protective_stop
    with ready False, the arm brakes to a stand-still, servo/speed raise DriverIOError and
    stop() does not raise; once the stop is cleared (sim: cleared; ur: cleared at the
    pendant, then the operator's recover()) the arm is ready and servo moves it again."""
    arm = harness.arm
    await _started(arm)
    twist = np.array([0.0, 0.03, 0.0, 0.0, 0.0, 0.0])
    await _control(arm, _moving, "the TCP to move", twist=twist)
    harness.protective_stop()
    s = await _until(lambda s: s.protective_stop, arm, "the protective stop")
    assert not s.ready and s.connected and not s.emergency_stop
    _assert_motion_refused(arm, s.T_B_tcp)
    arm.stop()
    s = await _until(_still, arm, "the arm to brake")
    assert s.protective_stop and not s.ready
    _assert_motion_refused(arm, s.T_B_tcp)

    await harness.clear_protective_stop()
    s = await _until(lambda s: s.ready and not s.protective_stop, arm, "ready again")
    target = _nearby(s.T_B_tcp)
    await _control(arm, _arrived(target), "the servo target after the stop", target=target)


async def test_lost_link_refuses_commands_until_it_returns(harness: Harness):
    """issue 8 contract: a lost link reads connected False (and not ready); servo/speed/kick
    raise DriverIOError and stop() does not raise; when the link returns the arm reads
    connected and ready again and servo moves it."""
    arm = harness.arm
    start = await _started(arm)
    await _control(arm, _still, "a servo to the current pose", target=start.T_B_tcp)
    harness.link_down()
    s = await _until(lambda s: not s.connected, arm, "the link to drop")
    assert not s.ready
    _assert_motion_refused(arm, start.T_B_tcp)
    with pytest.raises(DriverIOError):
        arm.kick()
    arm.stop()
    arm.stop()

    harness.link_up()
    s = await _until(lambda s: s.connected and s.ready, arm, "the link to return",
                     timeout=RECONNECT_WAIT)
    target = _nearby(s.T_B_tcp)
    await _control(arm, _arrived(target), "the servo target after the link returned",
                   target=target)
