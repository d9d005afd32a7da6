"""Issue 8, tendon drive over Modbus: the ``modbus`` end-effector backend (pymodbus client)
against an emulated drive unit that is a real pymodbus server, over Modbus TCP on loopback
and over RTU on real tty devices (a pty null-modem). Commands reach the motors through the
coupling and the pretension; a Modbus exception and an axis fault are named faults; a hung
or vanished drive is a lost link, reopened when the drive returns; the drive's host watchdog
stops the axes when the PC goes quiet."""

from __future__ import annotations

import logging
import math
import time

import anyio
import numpy as np
import pytest

from oralnav.drivers.effector import effector_class, open_effector
from oralnav.drivers.effector.kinematics import WristKinematics
from oralnav.drivers.effector.modbus_drive import (
    ModbusDriveEffector,
    decode_int32,
    encode_int32,
)
from oralnav.drivers.errors import DriverInitError, DriverIOError
from oralnav.sim.peers.modbus_drive import HOST_WATCHDOG_ERROR, ModbusDriveServer
from oralnav.sim.peers.null_modem import NullModem

WAIT = 3.0
CPR = 4096 / (2 * math.pi)  # counts per motor rad (a 12-bit encoder)


@pytest.fixture(autouse=True)
def _quiet_pymodbus():
    # pymodbus logs every refused connection at ERROR while the driver retries
    logger = logging.getLogger("pymodbus")
    level = logger.level
    logger.setLevel(logging.CRITICAL)
    yield
    logger.setLevel(level)


async def _until(pred, timeout: float = WAIT) -> None:
    t0 = time.monotonic()
    while not pred():
        assert time.monotonic() - t0 < timeout, "condition not reached in time"
        await anyio.sleep(0.005)


def test_int32_registers_round_trip_high_word_first():
    """issue 8 Modbus: INT32 positions travel as two registers, high word first."""
    assert encode_int32(np.array([1, -1, 70000])) == [0, 1, 0xFFFF, 0xFFFF, 1, 4464]
    values = np.array([0, 123456, -98765, 2**31 - 1, -(2**31)])
    assert decode_int32(encode_int32(values)).tolist() == values.tolist()


@pytest.mark.parametrize("kwargs, why", [
    ({"transport": "udp", "host": "x"}, "transport must be"),
    ({"transport": "tcp"}, "needs host"),
    ({"transport": "rtu"}, "needs serial_port"),
    ({"host": "x", "port": 70000}, "port must be"),
    ({"host": "x", "device_id": 0}, "device_id"),
    ({"host": "x", "watchdog_ms": -1}, "watchdog_ms"),
    ({"host": "x", "counts_per_rad": 0}, "counts_per_rad"),
    ({"host": "x", "pretension": [0, 0, float("nan"), 0]}, "pretension"),
    ({"host": "x", "rate_hz": 0}, "rate_hz"),
])
def test_bad_settings_are_init_errors(kwargs, why):
    """issue 8 Modbus (bad input): a malformed setting is a DriverInitError naming it."""
    with pytest.raises(DriverInitError, match=why):
        ModbusDriveEffector(**kwargs)


def test_registered_as_modbus():
    """issue 8 Modbus: the backend is found by name in the end-effector registry."""
    assert effector_class("modbus") is ModbusDriveEffector


async def test_commands_reach_the_motors_through_coupling_and_pretension():
    """issue 8 Modbus (TCP): a joint command becomes motor counts through the coupling
    matrix and the pretension; the drive follows with its lag; the reading comes back as the
    commanded joints."""
    kin = WristKinematics()
    pre = np.array([0.05, 0.10, 0.0, -0.02])
    with ModbusDriveServer() as drive:
        async with open_effector("modbus", host="127.0.0.1", port=drive.port, kinematics=kin,
                                 pretension=pre, counts_per_rad=CPR) as eff:
            st = eff.state()
            assert st.connected and st.fault is None
            # the drive starts at 0 counts: that is minus the pretension in motor angle
            np.testing.assert_allclose(st.motors, -pre, atol=1 / CPR)
            q = np.array([0.3, 0.2, -0.1, 0.4])
            eff.command(q)
            want = np.rint((kin.joints_to_motors(q) + pre) * CPR)
            await _until(lambda: np.abs(drive.positions() - want).max() <= 2)
            await _until(lambda: np.abs(eff.state().joints - q).max() < 3e-3)
            assert eff.exchanges > 5


async def test_rtu_on_a_serial_line():
    """issue 8 Modbus (RTU): the same drive over RTU framing on real tty devices (two
    ptys wired as a null-modem), with a unit id other than 1."""
    with NullModem() as cable, ModbusDriveServer(serial_port=cable.ends[0], framer="rtu",
                                                 device_id=7) as drive:
        async with open_effector("modbus", transport="rtu", serial_port=cable.ends[1],
                                 device_id=7, rate_hz=100, silence_timeout=0.3) as eff:
            q = np.array([-0.2, 0.1, 0.3, 0.2])
            eff.command(q)
            await _until(lambda: np.abs(eff.state().joints - q).max() < 3e-3)
            assert drive.requests > 10


async def test_a_modbus_exception_is_a_named_fault_while_it_lasts():
    """issue 8 Modbus (bad input): a drive answering with a Modbus exception is a fault
    naming the code, the drive and the transaction; commands are refused; when the drive
    answers normally the fault clears."""
    with ModbusDriveServer() as drive:
        async with open_effector("modbus", host="127.0.0.1", port=drive.port) as eff:
            drive.inject_exception(4)
            await _until(lambda: eff.state().fault is not None)
            fault = eff.state().fault
            assert "Modbus exception 4 (server device failure)" in fault
            assert f"127.0.0.1:{drive.port}" in fault
            with pytest.raises(DriverIOError, match="Modbus exception 4"):
                eff.command(np.zeros(4))
            assert eff.state().connected  # the link is fine; the drive refuses
            drive.inject_exception(None)
            await _until(lambda: eff.state().fault is None)
            eff.command(np.zeros(4))


async def test_an_axis_fault_holds_until_the_fault_reset():
    """issue 8 Modbus: an axis fault (over-current) is reported with its error code and
    kept by the drive; commands are refused; reset_fault() runs the reset sequence and the
    wrist obeys again, from where it is."""
    with ModbusDriveServer() as drive:
        async with open_effector("modbus", host="127.0.0.1", port=drive.port) as eff:
            drive.fault_axis(2, 0x2310)
            await _until(lambda: eff.state().fault is not None)
            assert eff.state().fault == "axis 2 error 0x2310"
            with pytest.raises(DriverIOError, match="axis 2 error 0x2310"):
                eff.command(np.zeros(4))
            await anyio.sleep(0.05)
            assert eff.state().fault is not None  # the drive keeps it
            eff.reset_fault()
            await _until(lambda: eff.state().fault is None)
            q = np.array([0.0, 0.1, 0.1, 0.1])
            eff.command(q)
            await _until(lambda: np.abs(eff.state().joints - q).max() < 3e-3)


async def test_a_hung_drive_is_a_lost_link():
    """issue 8 Modbus: a drive whose stack answers but whose cycle counter stopped is a
    lost link (not connected, the fault says hung), also across reconnect attempts."""
    with ModbusDriveServer() as drive:
        async with open_effector("modbus", host="127.0.0.1", port=drive.port,
                                 reconnect_backoff=(0.02, 0.05)) as eff:
            drive.hang()
            await _until(lambda: not eff.state().connected)
            assert "cycle counter stuck" in eff.state().fault
            await anyio.sleep(0.3)  # reconnect attempts must not read it as alive
            assert not eff.state().connected
            drive.hang(False)
            await _until(lambda: eff.state().connected)


async def test_a_vanished_drive_is_reconnected_and_its_watchdog_stopped_it():
    """issue 8 Modbus (bad input): the drive unit goes away: not connected, commands
    refused, stop() does not raise; while the PC could not write, the drive's host watchdog
    faulted the axes (0x8130); when the drive returns the link is reopened and the fault is
    shown until the operator's reset."""
    with ModbusDriveServer() as drive:
        port = drive.port
        async with open_effector("modbus", host="127.0.0.1", port=port, watchdog_ms=50,
                                 reconnect_backoff=(0.02, 0.1)) as eff:
            drive.stop()
            await _until(lambda: not eff.state().connected)
            assert f"127.0.0.1:{port}" in eff.state().fault
            with pytest.raises(DriverIOError, match="disconnected"):
                eff.command(np.zeros(4))
            eff.stop()
            await anyio.sleep(0.1)
            drive.start()
            await _until(lambda: eff.state().connected)
            assert eff.reconnects == 1
            assert f"error 0x{HOST_WATCHDOG_ERROR:04X}" in eff.state().fault
            eff.reset_fault()
            await _until(lambda: eff.state().fault is None)


async def test_a_wrong_address_is_a_fault_not_a_crash():
    """issue 8 Modbus (bad input): nothing listening at the configured address: start()
    returns after connect_timeout with the wrist disconnected and the address named."""
    with ModbusDriveServer() as drive:
        port = drive.port
    eff = open_effector("modbus", host="127.0.0.1", port=port, connect_timeout=0.2)
    async with eff:
        st = eff.state()
        assert not st.connected and f"127.0.0.1:{port}" in st.fault
        with pytest.raises(DriverIOError):
            eff.command(np.zeros(4))
