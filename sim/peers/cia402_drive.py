"""Emulated CiA 402 drives on a CAN bus: the protocol peer of the ``canopen`` end-effector
backend. Each motor axis is a ``canopen`` :class:`~canopen.LocalNode` (SDO server, NMT slave,
heartbeat producer, EMCY producer) on a python-can bus, by default the ``virtual`` interface
that connects buses of the same channel name inside one process.

What a drive does here:

- its PDO mapping is whatever the master wrote by SDO; it is read when the node goes
  OPERATIONAL, and the RPDO is read and the TPDO sent on every SYNC;
- the CiA 402 state machine follows the controlword (shutdown, switch on, enable operation,
  disable voltage, quick stop, fault reset on bit 7's rising edge);
- the axis follows its target with a lag (:class:`~oralnav.sim.peers.drive_model.DriveAxes`): every
  SYNC in cyclic synchronous position (mode 8); on the new-setpoint bit's rising edge in
  profile position (mode 1), acknowledged in statusword bit 12;
- a heartbeat consumer (0x1016:1) watches the master: its heartbeat missing while the drive
  is enabled is fault 0x8130;
- a fault (injected, or the heartbeat) disables the axis, sends an EMCY and shows FAULT
  until the master's fault reset.

Injections: :meth:`EmulatedCia402Drives.inject_fault`, :meth:`~EmulatedCia402Drives.mute`
(a node stops answering: no TPDO, no heartbeat, as if unplugged) and
:meth:`~EmulatedCia402Drives.unmute`.
"""

from __future__ import annotations

import logging
import struct
import threading
import time
from dataclasses import dataclass, field

import canopen

from oralnav.drivers.effector.cia402 import (
    CW_FAULT_RESET,
    CW_NEW_SETPOINT,
    MODES,
    SW_SETPOINT_ACK,
    SW_TARGET_REACHED,
    minimal_od,
)
from oralnav.sim.peers.drive_model import DriveAxes

__all__ = ["EmulatedCia402Drives"]

log = logging.getLogger(__name__)

_SW = {"SWITCH ON DISABLED": 0x40, "READY TO SWITCH ON": 0x21, "SWITCHED ON": 0x23,
       "OPERATION ENABLED": 0x27, "QUICK STOP ACTIVE": 0x07, "FAULT": 0x08}
_REMOTE = 0x0200  # statusword bit 9: the drive takes commands over the bus


@dataclass
class _Drive:
    node: canopen.LocalNode
    axis: int
    state: str = "SWITCH ON DISABLED"
    last_cw: int = 0
    muted: bool = False
    mapped: bool = False
    master_seen: float | None = None  # when the master's heartbeat last came
    consumer: tuple[int, float] | None = None  # (producer id, timeout s)
    rpdo: dict[int, int] = field(default_factory=dict)


class EmulatedCia402Drives:
    """Four (or ``len(node_ids)``) emulated CiA 402 drives on one bus.

    Args:
        channel: the python-can channel (a name for the ``virtual`` interface).
        node_ids: one node per motor axis, in motor order.
        interface: python-can interface.
        axes: the motors (default: :class:`DriveAxes` with 10 ms lag).
    """

    def __init__(self, channel: str, node_ids: tuple[int, ...] = (1, 2, 3, 4), *,
                 interface: str = "virtual", axes: DriveAxes | None = None) -> None:
        self.channel, self.interface = channel, interface
        self.axes = DriveAxes(len(node_ids)) if axes is None else axes
        self.node_ids = tuple(node_ids)
        self.network: canopen.Network | None = None
        self.drives: dict[int, _Drive] = {}
        self._lock = threading.RLock()
        self.syncs = 0
        self.emcys: list[tuple[int, int]] = []  # (node id, code) sent

    # -- life -------------------------------------------------------------------------------
    def start(self) -> None:
        """Connect to the bus, boot every node (PRE-OPERATIONAL, boot-up message)."""
        net = canopen.Network()
        net.connect(interface=self.interface, channel=self.channel)
        self.network = net
        for i, nid in enumerate(self.node_ids):
            node = canopen.LocalNode(nid, minimal_od(nid))
            net.add_node(node)
            d = _Drive(node, i)
            self.drives[nid] = d
            node.nmt.state = "PRE-OPERATIONAL"
            net.send_message(0x700 + nid, bytes([0]))  # boot-up
        net.subscribe(0x80, self._on_sync)
        self._quit = threading.Event()
        self._ticker = threading.Thread(target=self._tick, name="cia402-drives", daemon=True)
        self._ticker.start()

    def _tick(self) -> None:
        """The drives' own clock (10 ms): the heartbeat consumers run without SYNCs, so a
        master that dies (no SYNC, no heartbeat) still faults the drives."""
        while not self._quit.wait(0.01):
            now = time.monotonic()
            with self._lock:
                self.axes.advance(now)
                for d in self.drives.values():
                    if not d.muted:
                        self._watch_master(d, now)

    def stop(self) -> None:
        """Leave the bus (every node goes silent)."""
        net, self.network = self.network, None
        if net is None:
            return
        self._quit.set()
        self._ticker.join(2.0)
        for d in self.drives.values():
            d.node.nmt.stop_heartbeat()
        net.disconnect()
        self.drives.clear()

    def __enter__(self) -> EmulatedCia402Drives:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- injections -------------------------------------------------------------------------
    def inject_fault(self, node_id: int, code: int = 0x2310) -> None:
        """Fault one drive: FAULT state, axis disabled, EMCY ``code`` sent."""
        with self._lock:
            self._fault(self.drives[node_id], code)

    def mute(self, node_id: int) -> None:
        """The node stops answering (no TPDO, no heartbeat), as if unplugged."""
        with self._lock:
            d = self.drives[node_id]
            d.muted = True
            d.node.nmt.stop_heartbeat()

    def unmute(self, node_id: int) -> None:
        with self._lock:
            d = self.drives[node_id]
            d.muted = False
            hb = self._u16(d.node, 0x1017)
            if hb:
                d.node.nmt.start_heartbeat(hb)

    def stop_heartbeat(self, node_id: int) -> None:
        """The node stops its heartbeat but goes on with its PDOs."""
        with self._lock:
            self.drives[node_id].node.nmt.stop_heartbeat()

    def state(self, node_id: int) -> str:
        """The node's CiA 402 state."""
        return self.drives[node_id].state

    # -- the drive --------------------------------------------------------------------------
    @staticmethod
    def _u16(node: canopen.LocalNode, index: int) -> int:
        try:
            return struct.unpack("<H", node.get_data(index, 0))[0]
        except Exception:  # never written and no default: off
            return 0

    def _on_master_heartbeat(self, can_id: int, data: bytearray, timestamp: float) -> None:
        now = time.monotonic()
        with self._lock:
            for d in self.drives.values():
                if d.consumer is not None and 0x700 + d.consumer[0] == can_id:
                    d.master_seen = now

    def _on_sync(self, can_id: int, data: bytearray, timestamp: float) -> None:
        now = time.monotonic()
        with self._lock:
            self.syncs += 1
            self.axes.advance(now)
            for d in self.drives.values():
                if d.muted or d.node.nmt.state != "OPERATIONAL":
                    d.mapped = False
                    continue
                if not d.mapped:
                    self._map(d, now)
                self._watch_master(d, now)
                self._step(d)
                self._send_tpdo(d)

    def _map(self, d: _Drive, now: float) -> None:
        """Read the PDO configuration the master wrote (the node just went OPERATIONAL)."""
        d.node.rpdo.read(from_od=False)
        d.node.tpdo.read(from_od=False)
        for m in d.node.rpdo.map.values():
            if m.enabled and m.cob_id not in d.rpdo:
                d.rpdo[m.cob_id] = 1
                self.network.subscribe(m.cob_id, m.on_message)
        d.mapped = True
        try:
            value = struct.unpack("<I", d.node.get_data(0x1016, 1))[0]
        except Exception:
            value = 0
        producer, ms = (value >> 16) & 0x7F, value & 0xFFFF
        if ms:
            d.consumer = (producer, ms / 1000.0)
            d.master_seen = now
            self.network.subscribe(0x700 + producer, self._on_master_heartbeat)

    def _watch_master(self, d: _Drive, now: float) -> None:
        if d.consumer is None or d.master_seen is None or d.state == "FAULT":
            return
        if now - d.master_seen > d.consumer[1] and d.state == "OPERATION ENABLED":
            self._fault(d, 0x8130)

    def _received(self, d: _Drive, index: int) -> int | None:
        for m in d.node.rpdo.map.values():
            if not (m.enabled and m.is_received):
                continue
            for var in m:
                if var.index == index:
                    return int(var.raw)
        return None

    def _step(self, d: _Drive) -> None:
        ax = self.axes
        cw = self._received(d, 0x6040)
        if cw is None:  # no RPDO carries it: the controlword written by SDO
            cw = struct.unpack("<H", d.node.get_data(0x6040, 0))[0]
        prev, d.last_cw = d.last_cw, cw
        s = d.state
        if s == "FAULT":
            if cw & CW_FAULT_RESET and not prev & CW_FAULT_RESET:
                ax.fault[d.axis] = 0
                s = "SWITCH ON DISABLED"
        elif not cw & 0x02:                       # disable voltage
            s = "SWITCH ON DISABLED"
        elif cw & 0x86 == 0x02 and s in ("OPERATION ENABLED", "QUICK STOP ACTIVE"):
            s = "QUICK STOP ACTIVE"               # quick stop (bit 2 low)
        elif cw & 0x87 == 0x06:                   # shutdown
            s = "READY TO SWITCH ON"
        elif cw & 0x8F == 0x07 and s in ("READY TO SWITCH ON", "OPERATION ENABLED"):
            s = "SWITCHED ON"
        elif cw & 0x8F == 0x0F and s in ("READY TO SWITCH ON", "SWITCHED ON",
                                          "OPERATION ENABLED"):
            s = "OPERATION ENABLED"
        was_enabled = d.state == "OPERATION ENABLED"
        d.state = s
        enabled = s == "OPERATION ENABLED"
        ax.enabled[d.axis] = enabled
        if enabled and not was_enabled:
            ax.target[d.axis] = ax.position[d.axis]  # enabling never jumps
        if not enabled:
            return
        target = self._received(d, 0x607A)
        mode = struct.unpack("<b", d.node.get_data(0x6060, 0))[0]
        if target is None:
            return
        if mode == MODES["csp"]:
            ax.target[d.axis] = float(target)
        elif mode == MODES["pp"] and cw & CW_NEW_SETPOINT and not prev & CW_NEW_SETPOINT:
            ax.target[d.axis] = float(target)

    def _send_tpdo(self, d: _Drive) -> None:
        ax = self.axes
        sw = _SW.get(d.state, 0) | _REMOTE
        if ax.reached()[d.axis]:
            sw |= SW_TARGET_REACHED
        if d.last_cw & CW_NEW_SETPOINT:
            sw |= SW_SETPOINT_ACK
        values = {0x6041: sw, 0x6064: int(ax.counts()[d.axis])}
        d.node.set_data(0x6041, 0, struct.pack("<H", sw))
        d.node.set_data(0x6064, 0, struct.pack("<i", values[0x6064]))
        for m in d.node.tpdo.map.values():
            if not m.enabled:
                continue
            for var in m:
                if var.index in values:
                    var.raw = values[var.index]
            m.transmit()

    def _fault(self, d: _Drive, code: int) -> None:
        if d.state == "FAULT":
            return
        d.state = "FAULT"
        self.axes.set_fault(d.axis, code)
        d.node.set_data(0x603F, 0, struct.pack("<H", code))
        self.emcys.append((d.node.id, code))
        if self.network is not None and not d.muted:
            d.node.emcy.send(code, 0x01)
