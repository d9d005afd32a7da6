"""Issue 8, contract tests: every end-effector backend, simulated and real, keeps the same
promises: refused commands before start and after close; commands within the limits are
followed and out-of-limit ones refused (not clamped); stop() holds and never raises; a lost
link reads disconnected and refuses commands until it returns; a device fault is named and
refuses commands until cleared. The Modbus backend runs against the emulated drive unit (a
pymodbus server on loopback), the CANopen one against emulated CiA 402 drives on python-can's
virtual bus."""

from __future__ import annotations

import logging
import threading
import time
import uuid
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass

import anyio
import numpy as np
import pytest

from oralnav.drivers.effector import EffectorCommandError, EndEffector, open_effector
from oralnav.drivers.errors import DriverIOError
from oralnav.sim.peers.cia402_drive import EmulatedCia402Drives
from oralnav.sim.peers.modbus_drive import ModbusDriveServer

WAIT = 3.0


@dataclass
class Harness:
    """A backend's wrist and the hands that break and mend it."""

    effector: EndEffector
    link_down: Callable[[], None]
    link_up: Callable[[], None]
    fault: Callable[[], None]
    clear_fault: Callable[[], None]


async def _sim() -> AsyncIterator[Harness]:
    eff = open_effector("sim", max_joint_speed=5.0)
    done = threading.Event()

    def advance() -> None:  # the simulated cell's part: move the wrist in time
        while not done.wait(0.005):
            eff.advance(0.005)

    mover = threading.Thread(target=advance, daemon=True)
    mover.start()
    try:
        yield Harness(eff, eff.inject_disconnect, eff.clear,
                      lambda: eff.inject_fault("over-current"), eff.clear)
    finally:
        done.set()
        mover.join(1.0)


async def _modbus() -> AsyncIterator[Harness]:
    with ModbusDriveServer() as drive:
        eff = open_effector("modbus", host="127.0.0.1", port=drive.port,
                            reconnect_backoff=(0.02, 0.1))
        yield Harness(eff, drive.stop, drive.start, lambda: drive.fault_axis(1),
                      eff.reset_fault)


async def _canopen() -> AsyncIterator[Harness]:
    channel = f"oralnav-{uuid.uuid4().hex[:8]}"
    drives = EmulatedCia402Drives(channel)
    drives.start()
    try:
        eff = open_effector("canopen", interface="virtual", channel=channel,
                            reconnect_backoff=(0.02, 0.1))
        yield Harness(eff, drives.stop, drives.start, lambda: drives.inject_fault(2),
                      eff.reset_fault)
    finally:
        drives.stop()


@pytest.fixture(params=["sim", "modbus", "canopen"])
async def harness(request) -> AsyncIterator[Harness]:
    logger = logging.getLogger("pymodbus")
    level = logger.level
    logger.setLevel(logging.CRITICAL)  # refused reconnections are expected here
    gen = {"sim": _sim, "modbus": _modbus, "canopen": _canopen}[request.param]()
    h = await gen.__anext__()
    try:
        yield h
    finally:
        await h.effector.close()
        await gen.aclose()
        logger.setLevel(level)


async def _until(pred, timeout: float = WAIT) -> None:
    t0 = time.monotonic()
    while not pred():
        assert time.monotonic() - t0 < timeout, "condition not reached in time"
        await anyio.sleep(0.005)


def _near(eff: EndEffector, q: np.ndarray, tol: float = 3e-3) -> bool:
    return bool(np.abs(eff.state().joints - q).max() < tol)


async def test_refused_before_start_and_after_close(harness: Harness):
    """issue 8 contract: commands are refused (DriverIOError) before start() and after
    close(); close() is idempotent and leaves the wrist disconnected."""
    eff = harness.effector
    with pytest.raises(DriverIOError):
        eff.command(np.zeros(4))
    assert not eff.state().connected
    await eff.start()
    await _until(lambda: eff.state().connected)
    assert eff.state().fault is None
    await eff.close()
    await eff.close()
    assert not eff.state().connected
    with pytest.raises(DriverIOError):
        eff.command(np.zeros(4))


async def test_follows_within_limits_and_refuses_beyond(harness: Harness):
    """issue 8 contract: a target within the limits is reached; one beyond a joint limit is
    refused with EffectorCommandError and changes nothing."""
    eff = harness.effector
    await eff.start()
    q = np.array([0.2, -0.15, 0.1, 0.3])
    eff.command(q)
    await _until(lambda: _near(eff, q))
    with pytest.raises(EffectorCommandError, match="pitch"):
        eff.command(np.array([0.0, 2.0, 0.0, 0.3]))
    await anyio.sleep(0.05)
    assert _near(eff, q)


async def test_stop_holds_where_the_wrist_is(harness: Harness):
    """issue 8 contract: stop() during a motion holds the wrist near where it was."""
    eff = harness.effector
    await eff.start()
    eff.command(np.array([1.5, 0.0, 0.0, 0.0]))
    await _until(lambda: eff.state().joints[0] > 0.2)
    eff.stop()
    await anyio.sleep(0.1)
    held = eff.state().joints.copy()
    await anyio.sleep(0.1)
    np.testing.assert_allclose(eff.state().joints, held, atol=3e-3)
    assert held[0] < 1.4


async def test_a_lost_link_refuses_commands_and_recovers(harness: Harness):
    """issue 8 contract: a lost link reads disconnected; commands raise DriverIOError and
    stop() does not raise; when the link returns the wrist reads connected again."""
    eff = harness.effector
    await eff.start()
    harness.link_down()
    await _until(lambda: not eff.state().connected)
    with pytest.raises(DriverIOError):
        eff.command(np.zeros(4))
    eff.stop()
    harness.link_up()
    await _until(lambda: eff.state().connected)


async def test_a_device_fault_is_named_and_refuses_until_cleared(harness: Harness):
    """issue 8 contract: a device fault shows in state().fault and refuses commands; once
    cleared the wrist obeys again."""
    eff = harness.effector
    await eff.start()
    harness.fault()
    await _until(lambda: eff.state().fault is not None)
    with pytest.raises(DriverIOError, match="fault"):
        eff.command(np.zeros(4))
    harness.clear_fault()
    await _until(lambda: eff.state().fault is None)
    q = np.array([0.0, 0.1, 0.0, 0.1])
    eff.command(q)
    await _until(lambda: _near(eff, q))
