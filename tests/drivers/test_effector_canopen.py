"""Issue 8, tendon drive over CANopen CiA 402: the ``canopen`` end-effector backend
(``canopen`` on python-can) against four emulated CiA 402 drives (``canopen`` LocalNodes on
python-can's virtual bus: state machine driven by the controlword, position following with
a lag, faults injectable). Checked: the SDO configuration (mode, PDO mapping, heartbeats),
cyclic synchronous and profile position, EMCY faults and the fault reset, a lost heartbeat
and a silent node as a lost link, and a drive that faults when its master's heartbeat
stops."""

from __future__ import annotations

import struct
import time
import uuid

import anyio
import canopen
import numpy as np
import pytest

from oralnav.drivers.effector import effector_class, open_effector
from oralnav.drivers.effector.canopen_drive import CanopenDriveEffector
from oralnav.drivers.effector.cia402 import minimal_od, state_of
from oralnav.drivers.effector.kinematics import WristKinematics
from oralnav.drivers.errors import DriverInitError, DriverIOError
from oralnav.sim.peers.cia402_drive import EmulatedCia402Drives

WAIT = 3.0
CPR = 4096 / (2 * np.pi)


def _channel() -> str:
    return f"oralnav-{uuid.uuid4().hex[:8]}"  # a virtual bus of this test's own


async def _until(pred, timeout: float = WAIT) -> None:
    t0 = time.monotonic()
    while not pred():
        assert time.monotonic() - t0 < timeout, "condition not reached in time"
        await anyio.sleep(0.005)


def _open(channel: str, **kw):
    return open_effector("canopen", interface="virtual", channel=channel,
                         reconnect_backoff=(0.02, 0.1), **kw)


@pytest.mark.parametrize("kwargs, why", [
    ({"node_ids": (1, 2, 3)}, "4 distinct ids"),
    ({"node_ids": (1, 1, 2, 3)}, "4 distinct ids"),
    ({"node_ids": (1, 2, 3, 200)}, "4 distinct ids"),
    ({"mode": "velocity"}, "mode must be"),
    ({"host_node_id": 2}, "host_node_id"),
    ({"heartbeat_ms": 0}, "heartbeat_ms"),
    ({"sdo_timeout": -1}, "sdo_timeout"),
])
def test_bad_settings_are_init_errors(kwargs, why):
    """issue 8 CANopen (bad input): a malformed setting is a DriverInitError naming it."""
    with pytest.raises(DriverInitError, match=why):
        CanopenDriveEffector(**kwargs)


def test_registered_as_canopen():
    """issue 8 CANopen: the backend is found by name in the end-effector registry."""
    assert effector_class("canopen") is CanopenDriveEffector


async def test_csp_configures_the_drives_and_follows_through_the_coupling():
    """issue 8 CANopen (cyclic synchronous position): connecting writes mode 8, the
    heartbeats and the PDO mapping by SDO (read back from the drives), enables every drive,
    and a joint command reaches the motors through the coupling and pretension."""
    ch, kin = _channel(), WristKinematics()
    pre = np.array([0.0, 0.05, -0.05, 0.1])
    with EmulatedCia402Drives(ch) as drives:
        async with _open(ch, kinematics=kin, pretension=pre, counts_per_rad=CPR) as eff:
            assert eff.state().connected and eff.state().fault is None
            for nid in (1, 2, 3, 4):
                node = drives.drives[nid].node
                assert drives.state(nid) == "OPERATION ENABLED"
                assert struct.unpack("<b", node.get_data(0x6060, 0))[0] == 8
                assert [v.index for v in node.tpdo[1]] == [0x6041, 0x6064]
                assert [v.index for v in node.rpdo[1]] == [0x6040, 0x607A]
                assert drives.drives[nid].consumer == (0x7F, 0.06)  # watches this PC
            q = np.array([0.3, -0.2, 0.1, 0.5])
            eff.command(q)
            want = np.rint((kin.joints_to_motors(q) + pre) * CPR)
            await _until(lambda: np.abs(drives.axes.counts() - want).max() <= 2)
            await _until(lambda: np.abs(eff.state().joints - q).max() < 3e-3)
            assert drives.syncs > 10


async def test_profile_position_takes_each_target_on_the_setpoint_handshake():
    """issue 8 CANopen (profile position): mode 1, and new targets are taken on the
    new-setpoint bit's rising edge, also when they change every cycle."""
    ch = _channel()
    with EmulatedCia402Drives(ch) as drives:
        async with _open(ch, mode="pp") as eff:
            node = drives.drives[1].node
            assert struct.unpack("<b", node.get_data(0x6060, 0))[0] == 1
            for k in range(1, 21):  # a ramp: a new target every few cycles
                eff.command(np.array([0.02 * k, 0.0, 0.0, 0.01 * k]))
                await anyio.sleep(0.005)
            q = np.array([0.4, 0.0, 0.0, 0.2])
            await _until(lambda: np.abs(eff.state().joints - q).max() < 3e-3)


async def test_an_emcy_fault_is_named_and_cleared_by_the_fault_reset():
    """issue 8 CANopen (bad input): a drive that answers with an EMCY goes to FAULT; the
    wrist's fault names the node and the EMCY code, commands are refused; reset_fault()
    resets and re-enables it, and the wrist obeys again."""
    ch = _channel()
    with EmulatedCia402Drives(ch) as drives:
        async with _open(ch) as eff:
            drives.inject_fault(3, 0x2310)
            await _until(lambda: eff.state().fault is not None
                         and "EMCY" in eff.state().fault)
            assert eff.state().fault == "node 3 FAULT: EMCY 0x2310 (continuous over-current)"
            with pytest.raises(DriverIOError, match="node 3 FAULT"):
                eff.command(np.zeros(4))
            eff.reset_fault()
            await _until(lambda: eff.state().fault is None)
            assert drives.state(3) == "OPERATION ENABLED"
            q = np.array([0.1, 0.1, 0.1, 0.1])
            eff.command(q)
            await _until(lambda: np.abs(eff.state().joints - q).max() < 3e-3)


async def test_a_lost_heartbeat_is_a_lost_link_and_recovers():
    """issue 8 CANopen (heartbeat consumer): a drive whose heartbeat stops while its PDOs
    go on is a lost link naming the node; reconnecting reconfigures it (its heartbeat
    restarts) and the wrist reads again."""
    ch = _channel()
    with EmulatedCia402Drives(ch) as drives:
        async with _open(ch, heartbeat_ms=10) as eff:
            drives.stop_heartbeat(2)
            await _until(lambda: not eff.state().connected
                         and "heartbeat lost" in (eff.state().fault or ""))
            assert "node 2" in eff.state().fault
            await _until(lambda: eff.state().connected)
            assert eff.reconnects >= 1


async def test_a_silent_node_is_a_lost_link_until_it_returns():
    """issue 8 CANopen: a node that stops answering (unplugged) is a lost link naming it;
    commands are refused; when it answers again the link is reopened."""
    ch = _channel()
    with EmulatedCia402Drives(ch) as drives:
        async with _open(ch) as eff:
            drives.mute(4)
            await _until(lambda: not eff.state().connected and "[4]" in eff.state().fault)
            with pytest.raises(DriverIOError, match="disconnected"):
                eff.command(np.zeros(4))
            eff.stop()
            drives.unmute(4)
            await _until(lambda: eff.state().connected)


async def test_an_empty_bus_and_a_wrong_device_are_named_faults():
    """issue 8 CANopen (bad input): no drive on the bus: start() returns with the wrist
    disconnected and the silent node named; a node whose device type is not CiA 402 is
    refused by name."""
    ch = _channel()
    eff = _open(ch, connect_timeout=0.3, sdo_timeout=0.05)
    async with eff:
        st = eff.state()
        assert not st.connected and "node 1" in st.fault and "does not answer SDO" in st.fault
    ch = _channel()
    with EmulatedCia402Drives(ch) as drives:
        drives.drives[1].node.set_data(0x1000, 0, struct.pack("<I", 0x00000191))
        eff = _open(ch, connect_timeout=0.3)
        async with eff:
            st = eff.state()
            assert not st.connected and "node 1" in st.fault
            assert "not a CiA 402 drive (device type 0x00000191)" in st.fault


async def test_a_drive_faults_when_its_master_goes_quiet():
    """issue 8 CANopen (heartbeat consumer on the drive): a drive configured to watch its
    master's heartbeat faults with 0x8130 and sends an EMCY once the heartbeat stops, even
    without SYNCs (a dead PC sends nothing)."""
    ch = _channel()
    with EmulatedCia402Drives(ch, node_ids=(5, 6, 7, 8)) as drives:
        net = canopen.Network()
        net.connect(interface="virtual", channel=ch)
        try:
            node = canopen.RemoteNode(5, minimal_od(5))
            net.add_node(node)
            node.sdo[0x6060].raw = 8
            node.sdo[0x1016][1].raw = (0x60 << 16) | 30  # watch node 0x60, 30 ms
            beat = net.send_periodic(0x700 + 0x60, [0x05], 0.01)
            node.nmt.state = "OPERATIONAL"
            for cw in (0x06, 0x07, 0x0F):
                node.sdo[0x6040].raw = cw
                net.sync.transmit()
                await anyio.sleep(0.02)
            assert state_of(node.sdo[0x6041].raw) == "OPERATION ENABLED"
            beat.stop()  # the master dies
            await _until(lambda: drives.state(5) == "FAULT")
            assert (5, 0x8130) in drives.emcys
            assert drives.state(6) == "SWITCH ON DISABLED"  # not configured: untouched
        finally:
            net.disconnect()
