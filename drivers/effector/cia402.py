"""CiA 402 (drives and motion control) pieces the CANopen backend needs: the object
dictionary subset it uses, the drive state read from the statusword and the controlword that
leads toward OPERATION ENABLED (from ``canopen``'s :class:`~canopen.profiles.p402.State402`
tables), and the EMCY codes it names.

A real drive comes with its vendor's EDS file, which holds these objects and many more; pass
it as ``eds`` to the backend. :func:`minimal_od` is the subset for drives without one at hand
and for the emulated drive (``oralnav.sim.peers.cia402_drive``).
"""

from __future__ import annotations

import canopen
from canopen import objectdictionary as odlib
from canopen.profiles.p402 import State402

__all__ = ["CW_FAULT_RESET", "CW_NEW_SETPOINT", "DEVICE_TYPE_402", "EMCY_CODES", "MODES",
           "SW_SETPOINT_ACK", "SW_TARGET_REACHED", "controlword_toward_enabled",
           "describe_emcy", "minimal_od", "state_of"]

#: 0x1000 device type of a CiA 402 servo drive (profile 402, additional info 0x0002).
DEVICE_TYPE_402 = 0x00020192
#: Modes of operation (0x6060) used here.
MODES = {"pp": 1, "csp": 8}
CW_FAULT_RESET = 0x0080
CW_NEW_SETPOINT = 0x0010        # profile position: take the target (bit 4)
CW_CHANGE_IMMEDIATELY = 0x0020  # profile position: do not queue it (bit 5)
SW_TARGET_REACHED = 0x0400      # bit 10
SW_SETPOINT_ACK = 0x1000        # bit 12 in profile position
#: EMCY error codes (CiA 301 / CiA 402) in words, for messages.
EMCY_CODES = {
    0x0000: "error reset or no error", 0x1000: "generic error",
    0x2310: "continuous over-current", 0x3210: "DC link over-voltage",
    0x3220: "DC link under-voltage", 0x4310: "drive over-temperature",
    0x5441: "enable input off", 0x7305: "incremental encoder fault",
    0x8110: "CAN overrun", 0x8130: "heartbeat or life guard error",
    0x8611: "following error", 0xFF00: "manufacturer specific",
}


def describe_emcy(code: int) -> str:
    """``0x2310 (continuous over-current)``."""
    words = EMCY_CODES.get(code) or EMCY_CODES.get(code & 0xFF00, "unknown")
    return f"0x{code:04X} ({words})"


def state_of(statusword: int) -> str:
    """The CiA 402 state the statusword shows (``State402.SW_MASK``)."""
    for name, (mask, value) in State402.SW_MASK.items():
        if statusword & mask == value:
            return name
    return "UNKNOWN"


def controlword_toward_enabled(state: str) -> int:
    """The controlword for the next step from ``state`` toward OPERATION ENABLED
    (``State402``'s path and transition tables); FAULT takes a fault reset."""
    if state in ("FAULT", "FAULT REACTION ACTIVE"):
        return CW_FAULT_RESET
    if state == "OPERATION ENABLED":
        return State402.CW_OPERATION_ENABLED
    nxt = State402.next_state_indirect(state)
    return State402.TRANSITIONTABLE.get((state, nxt), State402.CW_SHUTDOWN)


def _var(name: str, index: int, sub: int, dtype: int, access: str = "rw",
         default: int | None = 0) -> odlib.ODVariable:
    v = odlib.ODVariable(name, index, sub)
    v.data_type, v.access_type, v.default = dtype, access, default
    return v


def _record(name: str, index: int, entries: list[tuple[str, int, int, int]],
            count_access: str = "ro") -> odlib.ODRecord:
    rec = odlib.ODRecord(name, index)
    rec.add_member(_var("Highest sub-index supported", index, 0, odlib.UNSIGNED8,
                        count_access, max(e[1] for e in entries)))
    for nm, sub, dtype, default in entries:
        rec.add_member(_var(nm, index, sub, dtype, "rw", default))
    return rec


def _pdo_objects(od: odlib.ObjectDictionary, node_id: int, *, rx: bool, n: int = 2) -> None:
    com, mp, base = (0x1400, 0x1600, 0x200) if rx else (0x1800, 0x1A00, 0x180)
    kind = "RPDO" if rx else "TPDO"
    for i in range(n):
        entries = [("COB-ID", 1, odlib.UNSIGNED32, base + 0x100 * i + node_id),
                   ("Transmission type", 2, odlib.UNSIGNED8, 1)]
        if not rx:
            entries += [("Inhibit time", 3, odlib.UNSIGNED16, 0),
                        ("Event timer", 5, odlib.UNSIGNED16, 0)]
        od.add_object(_record(f"{kind} communication parameter {i + 1}", com + i, entries))
        # sub-index 0 of a mapping is the number of mapped objects, written by the master
        od.add_object(_record(f"{kind} mapping parameter {i + 1}", mp + i,
                              [(f"Mapped object {k}", k, odlib.UNSIGNED32, 0)
                               for k in range(1, 9)], count_access="rw"))
        od[mp + i][0].default = 0


def minimal_od(node_id: int) -> odlib.ObjectDictionary:
    """The CiA 301 / 402 objects the backend reads and writes, for node ``node_id``."""
    od = odlib.ObjectDictionary()
    od.node_id = node_id
    od.add_object(_var("Device type", 0x1000, 0, odlib.UNSIGNED32, "ro", DEVICE_TYPE_402))
    od.add_object(_var("Error register", 0x1001, 0, odlib.UNSIGNED8, "ro"))
    od.add_object(_record("Consumer heartbeat time", 0x1016,
                          [("Consumer heartbeat time 1", 1, odlib.UNSIGNED32, 0)]))
    od.add_object(_var("Producer heartbeat time", 0x1017, 0, odlib.UNSIGNED16))
    _pdo_objects(od, node_id, rx=True)
    _pdo_objects(od, node_id, rx=False)
    od.add_object(_var("Error code", 0x603F, 0, odlib.UNSIGNED16, "ro"))
    od.add_object(_var("Controlword", 0x6040, 0, odlib.UNSIGNED16))
    od.add_object(_var("Statusword", 0x6041, 0, odlib.UNSIGNED16, "ro"))
    od.add_object(_var("Modes of operation", 0x6060, 0, odlib.INTEGER8))
    od.add_object(_var("Modes of operation display", 0x6061, 0, odlib.INTEGER8, "ro"))
    od.add_object(_var("Position actual value", 0x6064, 0, odlib.INTEGER32, "ro"))
    od.add_object(_var("Target position", 0x607A, 0, odlib.INTEGER32))
    od.add_object(_var("Supported drive modes", 0x6502, 0, odlib.UNSIGNED32, "ro",
                       (1 << 0) | (1 << 7)))  # pp, csp
    return od


def load_od(eds: str | None, node_id: int) -> odlib.ObjectDictionary:
    """The drive's object dictionary: its EDS file, or :func:`minimal_od`."""
    if eds is None:
        return minimal_od(node_id)
    return canopen.import_od(eds, node_id)
