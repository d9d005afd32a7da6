"""The tendon drive over CANopen CiA 402 (``canopen`` on ``python-can``); backend
``"canopen"``.

One CiA 402 drive (a node) per motor, in the kinematics' motor order. Connecting:

1. every node is put PRE-OPERATIONAL and its device type (0x1000) checked for profile 402;
2. by SDO: the mode of operation (0x6060: cyclic synchronous position ``csp`` or profile
   position ``pp``), the heartbeat producer (0x1017) and the heartbeat consumer watching
   this PC (0x1016:1), and the PDO mapping: RPDO1 = controlword + target position, TPDO1 =
   statusword + position actual value, both on every SYNC;
3. NMT start; then RPDO + SYNC cycles step each drive's state machine to OPERATION ENABLED,
   targets held at the actual positions.

Each exchange sends RPDO1 to every node and one SYNC, and waits for every TPDO1. EMCY
messages are collected per node and name the fault; a node in FAULT is a drive fault until
:meth:`~.motor_drive.MotorDriveEffector.reset_fault` (controlword bit 7's rising edge, then
the enable sequence). A TPDO that does not come, or a heartbeat older than three producer
periods, is a lost link (reopened with back-off). This PC sends its own heartbeat, so a
drive whose master dies faults (0x8130) and stops.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from typing import Any, Literal

import numpy as np

from ..errors import DriverInitError, DriverIOError
from .cia402 import (
    CW_CHANGE_IMMEDIATELY,
    CW_FAULT_RESET,
    CW_NEW_SETPOINT,
    DEVICE_TYPE_402,
    MODES,
    controlword_toward_enabled,
    describe_emcy,
    load_od,
    state_of,
)
from .motor_drive import DriveReading, MotorDriveEffector

__all__ = ["CanopenDriveEffector"]

log = logging.getLogger(__name__)

_ENABLE_TIMEOUT = 1.0  # s for the state machines to reach OPERATION ENABLED


class _Axis:
    """What the master knows of one node (written by python-can's receive thread)."""

    def __init__(self, node: Any) -> None:
        self.node = node
        self.statusword = 0
        self.position = 0
        self.stamp = 0  # TPDOs received
        self.emcy: str | None = None
        self.setpoint: int | None = None  # last target taken in profile position
        self.raised = False  # bit 4 was raised in the last cycle


class CanopenDriveEffector(MotorDriveEffector):
    """The wrist on four CiA 402 drives (see the module docstring).

    Args:
        channel: python-can channel (``can0``; a name for the ``virtual`` interface).
        interface: python-can interface (``socketcan``, ``pcan``, ``virtual``, ...).
        bitrate: bit/s, for interfaces that set it.
        node_ids: the four drives' node ids, in motor order.
        eds: the drives' EDS file (None: the built-in CiA 402 subset,
            :func:`~.cia402.minimal_od`).
        mode: ``"csp"`` (a new target every SYNC) or ``"pp"`` (profile position: each new
            target with the new-setpoint handshake).
        heartbeat_ms: the drives' heartbeat period (0x1017).
        host_node_id, host_heartbeat_ms: this PC's heartbeat, which the drives consume
            (0x1016:1; a drive faults when it stops).
        sdo_timeout: s per SDO transfer while connecting.
        **options: :class:`~.motor_drive.MotorDriveEffector`'s.
    """

    def __init__(self, *, channel: str = "can0", interface: str = "socketcan",
                 bitrate: int = 1_000_000, node_ids: tuple[int, ...] = (1, 2, 3, 4),
                 eds: str | None = None, mode: Literal["csp", "pp"] = "csp",
                 heartbeat_ms: int = 20, host_node_id: int = 0x7F,
                 host_heartbeat_ms: int = 20, sdo_timeout: float = 0.5,
                 **options: Any) -> None:
        super().__init__(**options)
        where = f"effector {self.name!r}"
        ids = tuple(node_ids)
        if len(ids) != 4 or len(set(ids)) != 4 or not all(
                isinstance(i, int) and not isinstance(i, bool) and 1 <= i <= 127 for i in ids):
            raise DriverInitError(f"{where}: node_ids must be 4 distinct ids in 1..127, "
                                  f"got {node_ids!r}")
        if mode not in MODES:
            raise DriverInitError(f"{where}: mode must be 'csp' or 'pp', got {mode!r}")
        if not (isinstance(host_node_id, int) and 1 <= host_node_id <= 127
                and host_node_id not in ids):
            raise DriverInitError(f"{where}: host_node_id must be 1..127 and not a drive's, "
                                  f"got {host_node_id!r}")
        for key, v in (("heartbeat_ms", heartbeat_ms), ("host_heartbeat_ms", host_heartbeat_ms)):
            if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= 65535:
                raise DriverInitError(f"{where}: {key} must be 1..65535 ms, got {v!r}")
        if not (isinstance(sdo_timeout, int | float) and math.isfinite(sdo_timeout)
                and sdo_timeout > 0):
            raise DriverInitError(f"{where}: sdo_timeout must be > 0 s, got {sdo_timeout!r}")
        self.channel, self.interface, self.bitrate = channel, interface, bitrate
        self.node_ids, self.eds, self.mode = ids, eds, mode
        self.heartbeat_ms, self.host_node_id = heartbeat_ms, host_node_id
        self.host_heartbeat_ms, self.sdo_timeout = host_heartbeat_ms, float(sdo_timeout)
        self._network: Any = None
        self._axes: list[_Axis] = []
        self._heartbeat_task: Any = None
        self._rx = threading.Condition()

    @property
    def address(self) -> str:
        return f"CAN {self.interface}:{self.channel}"

    # -- hooks ------------------------------------------------------------------------------
    def _open(self) -> None:
        import canopen
        from canopen.sdo.exceptions import SdoError

        net = canopen.Network()
        self._network = net
        try:
            net.connect(interface=self.interface, channel=self.channel, bitrate=self.bitrate)
        except Exception as exc:  # python-can raises its own errors and OSError
            raise DriverIOError(f"cannot open {self.address}: {exc}") from exc
        self._axes = []
        for nid in self.node_ids:
            node = canopen.RemoteNode(nid, load_od(self.eds, nid))
            node.sdo.RESPONSE_TIMEOUT = self.sdo_timeout
            net.add_node(node)
            axis = _Axis(node)
            node.emcy.add_callback(lambda err, a=axis, n=nid: self._on_emcy(a, n, err))
            self._axes.append(axis)
        try:
            net.nmt.state = "PRE-OPERATIONAL"  # broadcast: stop any PDO traffic first
            for axis in self._axes:
                self._configure(axis)
        except SdoError as exc:
            raise DriverIOError(f"CANopen drive on {self.address}: configuring failed: "
                                f"{exc}") from exc
        self._heartbeat_task = net.send_periodic(0x700 + self.host_node_id, [0x05],
                                                 self.host_heartbeat_ms / 1000.0)
        for axis in self._axes:
            axis.node.nmt.state = "OPERATIONAL"
        self._enable()

    def _configure(self, axis: _Axis) -> None:
        node, nid = axis.node, axis.node.id
        try:
            device = node.sdo[0x1000].raw
        except Exception as exc:
            raise DriverIOError(f"node {nid} on {self.address} does not answer SDO "
                                f"({type(exc).__name__}: {exc})") from exc
        if device & 0xFFFF != DEVICE_TYPE_402 & 0xFFFF:
            raise DriverIOError(f"node {nid} on {self.address} is not a CiA 402 drive "
                                f"(device type 0x{device:08X})")
        node.sdo[0x6060].raw = MODES[self.mode]
        node.sdo[0x1017].raw = self.heartbeat_ms
        node.sdo[0x1016][1].raw = (self.host_node_id << 16) | (3 * self.host_heartbeat_ms)
        node.rpdo.read()
        node.tpdo.read()
        rx, tx = node.rpdo[1], node.tpdo[1]
        rx.clear()
        rx.add_variable(0x6040)
        rx.add_variable(0x607A)
        rx.trans_type, rx.enabled = 1, True
        tx.clear()
        tx.add_variable(0x6041)
        tx.add_variable(0x6064)
        tx.trans_type, tx.enabled = 1, True
        for other in list(node.rpdo.map.values())[1:] + list(node.tpdo.map.values())[1:]:
            other.enabled = False
        node.rpdo.save()
        node.tpdo.save()
        tx.add_callback(lambda m, a=axis: self._on_tpdo(a, m))

    def _enable(self) -> None:
        deadline = time.monotonic() + _ENABLE_TIMEOUT
        while True:
            self._cycle(controlwords=None, targets=None)
            states = [state_of(a.statusword) for a in self._axes]
            if all(s == "OPERATION ENABLED" for s in states):
                return
            if any(s == "FAULT" for s in states) and time.monotonic() > deadline:
                bad = [f"node {a.node.id}: {a.emcy or 'FAULT'}" for a in self._axes
                       if state_of(a.statusword) == "FAULT"]
                raise DriverIOError(f"drives on {self.address} stay in FAULT: "
                                    + "; ".join(bad))
            if time.monotonic() > deadline:
                raise DriverIOError(
                    f"drives on {self.address} did not reach OPERATION ENABLED in "
                    f"{_ENABLE_TIMEOUT:.1f} s: " + ", ".join(
                        f"node {a.node.id} {state_of(a.statusword)}" for a in self._axes))

    def _exchange(self, target: np.ndarray | None) -> DriveReading:
        self._cycle(controlwords=[0x0F] * 4, targets=target)
        self._check_heartbeats()
        faults = []
        for a in self._axes:
            state = state_of(a.statusword)
            if state in ("FAULT", "FAULT REACTION ACTIVE"):
                faults.append(f"node {a.node.id} FAULT" + (f": EMCY {a.emcy}" if a.emcy
                                                           else ""))
            elif state != "OPERATION ENABLED":
                faults.append(f"node {a.node.id} {state}")
        counts = np.array([a.position for a in self._axes], dtype=np.int64)
        return DriveReading(counts=counts, fault="; ".join(faults) or None)

    def _reset_fault(self) -> None:
        faulted = [state_of(a.statusword) == "FAULT" for a in self._axes]
        self._cycle(controlwords=[CW_FAULT_RESET if f else 0x0F for f in faulted], targets=None)
        for a, f in zip(self._axes, faulted, strict=True):
            if f:
                a.emcy = None
        self._enable()

    def _close_link(self) -> None:
        net, self._network = self._network, None
        if net is None:
            return
        try:
            if self._axes and net.bus is not None:
                self._cycle(controlwords=[0x06] * 4, targets=None, wait=False)  # shutdown
        except Exception:  # the bus may be gone; the drives' heartbeat consumers stop them
            log.debug("effector %r: disabling the drives on close", self.name, exc_info=True)
        if self._heartbeat_task is not None:
            try:
                self._heartbeat_task.stop()
            except Exception:
                log.debug("stopping the heartbeat", exc_info=True)
            self._heartbeat_task = None
        try:
            net.disconnect()
        except Exception:
            log.debug("effector %r: disconnecting %s", self.name, self.address, exc_info=True)

    # -- the bus cycle ----------------------------------------------------------------------
    def _cycle(self, *, controlwords: list[int] | None, targets: np.ndarray | None,
               wait: bool = True) -> None:
        """RPDO1 to every node, one SYNC, then every node's TPDO1 (half ``silence_timeout``).
        ``controlwords`` None steps each state machine toward OPERATION ENABLED; ``targets``
        None holds the actual positions."""
        net = self._network
        if net is None:
            raise DriverIOError(f"{self.address}: not connected")
        with self._rx:
            before = [a.stamp for a in self._axes]
        try:
            for i, a in enumerate(self._axes):
                cw = (controlword_toward_enabled(state_of(a.statusword)) if controlwords is None
                      else controlwords[i])
                goal = int(targets[i]) if targets is not None else a.position
                if self.mode == "pp" and cw == 0x0F:
                    # profile position: a new target rides on bit 4's rising edge, so the
                    # bit is lowered for a cycle after each raise
                    if a.raised:
                        a.raised = False
                    elif goal != a.setpoint:
                        cw |= CW_NEW_SETPOINT | CW_CHANGE_IMMEDIATELY
                        a.setpoint, a.raised = goal, True
                    else:
                        goal = a.setpoint
                rx = a.node.rpdo[1]
                rx[0x6040].raw = cw
                rx[0x607A].raw = goal
                rx.transmit()
            net.sync.transmit()
        except Exception as exc:  # python-can's CanError and OSError from the interface
            raise DriverIOError(f"{self.address}: sending failed: {exc}") from exc
        if not wait:
            return
        # half the silence limit: a node that does not answer is named before the
        # wrist as a whole reads silent
        wait_s = self.silence_timeout / 2
        deadline = time.monotonic() + wait_s
        with self._rx:
            while True:
                late = [a.node.id for a, b in zip(self._axes, before, strict=True)
                        if a.stamp == b]
                if not late:
                    return
                left = deadline - time.monotonic()
                if left <= 0:
                    raise DriverIOError(f"{self.address}: node(s) {late} sent no TPDO within "
                                        f"{wait_s:.3f} s of the SYNC")
                self._rx.wait(left)

    def _check_heartbeats(self) -> None:
        limit = 3 * self.heartbeat_ms / 1000.0
        now = time.time()  # canopen stamps heartbeats with the message's wall time
        for a in self._axes:
            t = a.node.nmt.timestamp
            if t is not None and now - t > limit:
                raise DriverIOError(f"node {a.node.id} on {self.address}: heartbeat lost "
                                    f"({now - t:.3f} s, limit {limit:.3f} s)")

    def _on_tpdo(self, axis: _Axis, m: Any) -> None:
        with self._rx:
            axis.statusword = int(m[0x6041].raw)
            axis.position = int(m[0x6064].raw)
            axis.stamp += 1
            self._rx.notify_all()

    def _on_emcy(self, axis: _Axis, node_id: int, err: Any) -> None:
        if err.code == 0:
            return  # error reset
        axis.emcy = describe_emcy(err.code)
        log.warning("effector %r: EMCY %s from node %d", self.name, axis.emcy, node_id)
