"""The tendon drive over Modbus TCP or RTU (``pymodbus``); backend ``"modbus"``.

For drive units that speak Modbus rather than CANopen. The register map (one device id, four
axes; docs/formats.md, "Modbus tendon-drive registers") is the drive unit's:

Holding registers (written by us, FC16 in one transaction per cycle):

==========  ==========================================================================
0..3        control word per axis: bit 0 enable, bit 1 fault reset (acts on 0 -> 1),
            bit 2 halt
4..11       target position per axis, INT32 counts, high word first
12          host watchdog, ms (0: off): the drive faults every axis (0x8130) when no
            write reaches it for this long, so a dead PC stops the wrist
==========  ==========================================================================

Input registers (read, FC04, one transaction per cycle):

==========  ==========================================================================
0..3        status word per axis: bit 0 enabled, bit 1 fault, bit 2 target reached
4..11       actual position per axis, INT32 counts, high word first
12..15      error code per axis (CiA 402 codes; 0: none)
16          drive cycle counter, +1 per drive cycle, wrapping; a counter that stops
            while the drive still answers is a hung drive
==========  ==========================================================================

A Modbus exception answer (illegal address, device failure, ...) is a drive fault that lasts
while the drive answers with exceptions; an axis's fault bit is the drive's own fault, which
it keeps until :meth:`~.motor_drive.MotorDriveEffector.reset_fault`. A timeout, a closed
connection or a stuck cycle counter is a lost link, reopened with back-off.
"""

from __future__ import annotations

import logging
import math
import struct
import time
from typing import Any, Literal

import numpy as np

from ..errors import DriverInitError, DriverIOError
from .motor_drive import DriveReading, MotorDriveEffector

__all__ = ["EXCEPTIONS", "HR_CONTROL", "HR_TARGET", "HR_WATCHDOG", "IR_COUNT",
           "ModbusDriveEffector", "decode_int32", "encode_int32"]

log = logging.getLogger(__name__)

HR_CONTROL, HR_TARGET, HR_WATCHDOG = 0, 4, 12
IR_STATUS, IR_POSITION, IR_ERROR, IR_CYCLE, IR_COUNT = 0, 4, 12, 16, 17
CW_ENABLE, CW_FAULT_RESET, CW_HALT = 0x1, 0x2, 0x4
SW_ENABLED, SW_FAULT, SW_REACHED = 0x1, 0x2, 0x4
#: Modbus exception codes, in words (Modbus application protocol v1.1b3, section 7).
EXCEPTIONS = {1: "illegal function", 2: "illegal data address", 3: "illegal data value",
              4: "server device failure", 5: "acknowledge", 6: "server device busy",
              8: "memory parity error", 10: "gateway path unavailable",
              11: "gateway target device failed to respond"}


def encode_int32(values: np.ndarray) -> list[int]:
    """INT32 values -> registers, high word first."""
    out: list[int] = []
    for v in values:
        hi, lo = struct.unpack(">HH", struct.pack(">i", int(v)))
        out += [hi, lo]
    return out


def decode_int32(registers: list[int]) -> np.ndarray:
    """Registers (pairs, high word first) -> INT32 values."""
    return np.array([struct.unpack(">i", struct.pack(">HH", registers[i], registers[i + 1]))[0]
                     for i in range(0, len(registers), 2)], dtype=np.int64)


class ModbusDriveEffector(MotorDriveEffector):
    """The wrist on a Modbus drive unit (see the module docstring).

    Args:
        transport: ``"tcp"`` (Modbus TCP) or ``"rtu"`` (RTU framing on a serial line, or on
            TCP through a serial gateway with ``host``).
        host, port: the drive's (or gateway's) address for TCP (port default 502).
        serial_port, baudrate, parity, stopbits: the serial line for RTU without ``host``.
        device_id: the drive's Modbus unit id (1..247).
        timeout: s per transaction before the link counts as lost (default: half the
            silence timeout).
        watchdog_ms: the drive's host watchdog (register 12), 0 to leave it off.
        **options: :class:`~.motor_drive.MotorDriveEffector`'s (kinematics, counts_per_rad,
            pretension, rate_hz, silence_timeout, connect_timeout, reconnect_backoff, clock,
            name).
    """

    def __init__(self, *, transport: Literal["tcp", "rtu"] = "tcp", host: str | None = None,
                 port: int = 502, serial_port: str | None = None, baudrate: int = 115200,
                 parity: Literal["N", "E", "O"] = "N", stopbits: int = 1, device_id: int = 1,
                 timeout: float | None = None, watchdog_ms: int = 100,
                 **options: Any) -> None:
        super().__init__(**options)
        where = f"effector {self.name!r}"
        if transport not in ("tcp", "rtu"):
            raise DriverInitError(f"{where}: transport must be 'tcp' or 'rtu', "
                                  f"got {transport!r}")
        if transport == "tcp" and not host:
            raise DriverInitError(f"{where}: Modbus TCP needs host")
        if transport == "rtu" and not (host or serial_port):
            raise DriverInitError(f"{where}: Modbus RTU needs serial_port (or host for a "
                                  "TCP gateway)")
        if isinstance(port, bool) or not isinstance(port, int) or not 1 <= port <= 65535:
            raise DriverInitError(f"{where}: port must be 1..65535, got {port!r}")
        if isinstance(device_id, bool) or not isinstance(device_id, int) \
                or not 1 <= device_id <= 247:
            raise DriverInitError(f"{where}: device_id must be 1..247, got {device_id!r}")
        if isinstance(watchdog_ms, bool) or not isinstance(watchdog_ms, int) \
                or not 0 <= watchdog_ms <= 65535:
            raise DriverInitError(f"{where}: watchdog_ms must be 0..65535, got {watchdog_ms!r}")
        # half the silence limit by default: a drive that does not answer is named before
        # the wrist as a whole reads silent
        t = self.silence_timeout / 2 if timeout is None else timeout
        if not (isinstance(t, int | float) and math.isfinite(t) and t > 0):
            raise DriverInitError(f"{where}: timeout must be > 0 s, got {timeout!r}")
        self.transport, self.host, self.port = transport, host, port
        self.serial_port, self.baudrate = serial_port, baudrate
        self.parity, self.stopbits = parity, stopbits
        self.device_id, self.timeout, self.watchdog_ms = device_id, float(t), watchdog_ms
        self._client: Any = None
        self._control = [0, 0, 0, 0]
        self._last_counts: np.ndarray | None = None
        self._cycle: tuple[int, float] | None = None  # counter, when it last changed

    @property
    def address(self) -> str:
        """Where the drive is, for messages."""
        if self.host:
            return f"{self.transport.upper()} {self.host}:{self.port} unit {self.device_id}"
        return f"RTU {self.serial_port} unit {self.device_id}"

    # -- hooks ------------------------------------------------------------------------------
    def _open(self) -> None:
        from pymodbus.client import ModbusSerialClient, ModbusTcpClient
        from pymodbus.framer import FramerType

        if self.host:
            framer = FramerType.SOCKET if self.transport == "tcp" else FramerType.RTU
            client = ModbusTcpClient(self.host, port=self.port, framer=framer,
                                     timeout=self.timeout, retries=0)
        else:
            client = ModbusSerialClient(self.serial_port, framer=FramerType.RTU,
                                        baudrate=self.baudrate, parity=self.parity,
                                        stopbits=self.stopbits, timeout=self.timeout,
                                        retries=0)
        self._client = client
        if not client.connect():
            raise DriverIOError(f"cannot connect to the Modbus drive at {self.address}")
        self._cycle = None
        counts, fault, _ = self._read_inputs()
        if fault is not None:
            raise DriverIOError(f"Modbus drive at {self.address} refused the first read: "
                                f"{fault}")
        # a hung drive's stack may still answer: its cycle counter must advance
        first = self._cycle
        deadline = time.monotonic() + self.silence_timeout
        while self._cycle == first:
            if time.monotonic() > deadline:
                raise DriverIOError(f"Modbus drive at {self.address}: cycle counter stuck at "
                                    f"{first[0]} (drive hung)")
            time.sleep(0.002)
            counts, fault, _ = self._read_inputs()
        self._last_counts = counts
        # hold where the drive is, then enable: never move on connecting
        self._control = [CW_ENABLE] * 4
        self._write(HR_CONTROL, self._control + encode_int32(counts) + [self.watchdog_ms])

    def _exchange(self, target: np.ndarray | None) -> DriveReading:
        if target is None:
            fault = self._write(HR_CONTROL, self._control)
        else:
            fault = self._write(HR_CONTROL, self._control + encode_int32(target))
        counts, read_fault, status = self._read_inputs()
        fault = fault or read_fault
        if counts is None:  # the read was refused: report the fault at the last position
            counts = self._last_counts
        self._last_counts = counts
        return DriveReading(counts=counts, fault=fault or status)

    def _reset_fault(self) -> None:
        for value in ([CW_FAULT_RESET] * 4, [CW_ENABLE] * 4):
            fault = self._write(HR_CONTROL, value)
            if fault is not None:
                raise DriverIOError(f"fault reset refused: {fault}")
        counts, fault, _ = self._read_inputs()
        if counts is not None:  # hold where the drive now is
            self._write(HR_TARGET, encode_int32(counts))

    def _close_link(self) -> None:
        client, self._client = self._client, None
        if client is None:
            return
        try:
            if client.connected:
                client.write_registers(HR_CONTROL, [CW_HALT] * 4, device_id=self.device_id)
        except Exception:  # the drive may be gone; its host watchdog then stops it
            log.debug("effector %r: halting on close", self.name, exc_info=True)
        client.close()

    # -- transactions -----------------------------------------------------------------------
    def _call(self, what: str, fn: Any, *args: Any, **kwargs: Any) -> Any:
        from pymodbus.exceptions import ModbusException

        if self._client is None:
            raise DriverIOError(f"Modbus drive at {self.address}: not connected")
        try:
            return fn(*args, device_id=self.device_id, **kwargs)
        except ModbusException as exc:
            raise DriverIOError(f"Modbus drive at {self.address}: {what} failed: "
                                f"{exc}") from exc
        except OSError as exc:
            raise DriverIOError(f"Modbus drive at {self.address}: {what}: {exc}") from exc

    def _refused(self, what: str, response: Any) -> str | None:
        if not response.isError():
            return None
        code = getattr(response, "exception_code", None)
        if code is None:
            raise DriverIOError(f"Modbus drive at {self.address}: {what}: {response}")
        return (f"Modbus exception {code} ({EXCEPTIONS.get(code, 'unknown')}) from "
                f"{self.address} on {what}")

    def _write(self, address: int, values: list[int]) -> str | None:
        what = f"writing holding registers {address}..{address + len(values) - 1}"
        return self._refused(what, self._call(what, self._client.write_registers, address,
                                              values))

    def _read_inputs(self) -> tuple[np.ndarray | None, str | None, str | None]:
        """(counts, Modbus exception, axis faults) from the input registers."""
        what = f"reading input registers 0..{IR_COUNT - 1}"
        rr = self._call(what, self._client.read_input_registers, 0, count=IR_COUNT)
        refused = self._refused(what, rr)
        if refused is not None:
            return None, refused, None
        regs = list(rr.registers)
        if len(regs) != IR_COUNT:
            raise DriverIOError(f"Modbus drive at {self.address}: {what}: got {len(regs)} "
                                "registers")
        self._check_cycle(regs[IR_CYCLE])
        status, errors = regs[IR_STATUS:IR_STATUS + 4], regs[IR_ERROR:IR_ERROR + 4]
        faults = [f"axis {i} error 0x{errors[i]:04X}" for i in range(4)
                  if status[i] & SW_FAULT]
        axis_fault = ", ".join(faults) if faults else None
        return decode_int32(regs[IR_POSITION:IR_POSITION + 8]), None, axis_fault

    def _check_cycle(self, counter: int) -> None:
        now = time.monotonic()
        if self._cycle is None or counter != self._cycle[0]:
            self._cycle = (counter, now)
        elif now - self._cycle[1] > self.silence_timeout:
            raise DriverIOError(f"Modbus drive at {self.address}: cycle counter stuck at "
                                f"{counter} for {now - self._cycle[1]:.3f} s (drive hung)")
