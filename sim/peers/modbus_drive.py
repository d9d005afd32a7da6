"""An emulated Modbus tendon-drive unit: a real ``pymodbus`` server (TCP, or RTU framing on
TCP or on a serial line) whose registers are the drive's (``oralnav.drivers.effector.
modbus_drive``'s map), backed by :class:`~oralnav.sim.peers.drive_model.DriveAxes`.

The server runs on its own asyncio loop in a thread. The drive advances its axes on every
request, from the wall clock. Faults to inject: :meth:`ModbusDriveServer.inject_exception`
(every request answered with a Modbus exception), :meth:`~ModbusDriveServer.fault_axis` (an
axis error, kept until the host's fault reset), :meth:`~ModbusDriveServer.hang` (the cycle
counter stops, the stack still answers) and :meth:`~ModbusDriveServer.stop` (the unit goes
away; :meth:`~ModbusDriveServer.start` brings it back on the same address).
"""

from __future__ import annotations

import asyncio
import threading
import time
from typing import Literal

import numpy as np

from oralnav.drivers.effector.modbus_drive import (
    CW_ENABLE,
    CW_FAULT_RESET,
    CW_HALT,
    HR_CONTROL,
    HR_TARGET,
    HR_WATCHDOG,
    IR_COUNT,
    SW_ENABLED,
    SW_FAULT,
    SW_REACHED,
    decode_int32,
    encode_int32,
)
from oralnav.sim.peers.drive_model import DriveAxes

__all__ = ["HOST_WATCHDOG_ERROR", "ModbusDriveServer"]

#: CiA 402 error code the drive reports when the host watchdog expires (heartbeat error).
HOST_WATCHDOG_ERROR = 0x8130
_HR_COUNT = HR_WATCHDOG + 1


class ModbusDriveServer:
    """The emulated drive unit.

    Args:
        host, port: where to listen (TCP); port 0 picks a free one (see :attr:`port`).
        serial_port: listen on this serial device instead (RTU).
        framer: ``"socket"`` (Modbus TCP) or ``"rtu"``.
        device_id: the unit id it answers.
        axes: the motor axes (default: 4 axes, 10 ms lag).
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 0, *,
                 serial_port: str | None = None, framer: Literal["socket", "rtu"] = "socket",
                 device_id: int = 1, axes: DriveAxes | None = None) -> None:
        self.host, self.port, self.serial_port = host, port, serial_port
        self.framer, self.device_id = framer, device_id
        self.axes = DriveAxes() if axes is None else axes
        self._control = [0, 0, 0, 0]
        self._watchdog_ms = 0
        self._last_write: float | None = None
        self._exception: int | None = None
        self._hung_at: int | None = None
        self.requests = 0
        self.writes: list[list[int]] = []  # every holding-register write (last 1000)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._server = None
        self._ticker: asyncio.Task[None] | None = None

    # -- life -------------------------------------------------------------------------------
    def start(self) -> None:
        """Start serving (again); returns once the server listens."""
        if self._thread is not None:
            raise RuntimeError("the drive is already running")
        ready = threading.Event()
        failure: list[BaseException] = []
        self._thread = threading.Thread(target=self._serve, args=(ready, failure),
                                        name="modbus-drive", daemon=True)
        self._thread.start()
        if not ready.wait(10.0):
            raise RuntimeError("the emulated Modbus drive did not start in 10 s")
        if failure:
            self._thread = None
            raise failure[0]

    def stop(self) -> None:
        """Close the server and every connection (the unit vanishes)."""
        loop, thread = self._loop, self._thread
        if loop is None or thread is None:
            return
        asyncio.run_coroutine_threadsafe(self._shutdown(), loop).result(10.0)
        loop.call_soon_threadsafe(loop.stop)
        thread.join(10.0)
        self._thread = self._loop = None

    def __enter__(self) -> ModbusDriveServer:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _serve(self, ready: threading.Event, failure: list[BaseException]) -> None:
        loop = asyncio.new_event_loop()
        self._loop = loop
        try:
            loop.run_until_complete(self._open(ready, failure))
            if not failure:
                loop.run_forever()
        finally:
            loop.close()

    async def _open(self, ready: threading.Event, failure: list[BaseException]) -> None:
        from pymodbus.framer import FramerType
        from pymodbus.server import ModbusSerialServer, ModbusTcpServer
        from pymodbus.simulator import DataType, SimData, SimDevice

        device = SimDevice(
            self.device_id,
            simdata=([SimData(0, count=1, values=False, datatype=DataType.BITS)],
                     [SimData(0, count=1, values=False, datatype=DataType.BITS)],
                     [SimData(0, count=_HR_COUNT, values=0, datatype=DataType.REGISTERS)],
                     [SimData(0, count=IR_COUNT, values=0, datatype=DataType.REGISTERS)]),
            action=self._action)
        framer = FramerType.RTU if self.framer == "rtu" else FramerType.SOCKET
        try:
            if self.serial_port is not None:
                self._server = ModbusSerialServer(device, framer=framer, port=self.serial_port,
                                                  baudrate=115200)
            else:
                self._server = ModbusTcpServer(device, framer=framer,
                                               address=(self.host, self.port))
            await self._server.listen()
            self._ticker = asyncio.get_running_loop().create_task(self._tick())
            if self.serial_port is None and self.port == 0:
                self.port = self._server.transport.sockets[0].getsockname()[1]
        except BaseException as exc:  # reported to start()
            failure.append(exc)
        finally:
            ready.set()

    async def _tick(self) -> None:
        """The drive's own cycle (10 ms here): the axes move and the host watchdog runs
        whether or not the host asks anything."""
        while True:
            await asyncio.sleep(0.01)
            if self._hung_at is None:
                with self.axes.lock:
                    now = time.monotonic()
                    self.axes.advance(now)
                    self._check_watchdog(now)

    async def _shutdown(self) -> None:
        if self._ticker is not None:
            self._ticker.cancel()
            self._ticker = None
        if self._server is not None:
            await self._server.shutdown()
            self._server = None

    # -- injections -------------------------------------------------------------------------
    def inject_exception(self, code: int | None) -> None:
        """Answer every request with Modbus exception ``code`` (None: answer normally)."""
        self._exception = code

    def fault_axis(self, axis: int, code: int = 0x2310) -> None:
        """Fault one axis (default 0x2310, continuous over-current): it disables and holds
        until the host's fault reset."""
        self.axes.set_fault(axis, code)

    def hang(self, hung: bool = True) -> None:
        """The drive's cycle stops (counter and axes frozen) while its Modbus stack answers."""
        self._hung_at = self._cycle() if hung else None

    # -- the drive --------------------------------------------------------------------------
    @staticmethod
    def _cycle() -> int:
        return int(time.monotonic() * 1000.0) % 65536

    async def _action(self, function_code: int, start_address: int, address: int, count: int,
                      registers: list[int], set_values: list[int] | None) -> int | None:
        from pymodbus.constants import ExcCodes

        self.requests += 1
        if self._exception is not None:
            return ExcCodes(self._exception)
        now = time.monotonic()
        ax = self.axes
        with ax.lock:
            if self._hung_at is None:
                ax.advance(now)
                self._check_watchdog(now)
            if function_code in (6, 16) and set_values is not None:
                self._written(address, list(set_values), now)
            if function_code == 4:
                self._fill_inputs(registers)
        return None

    def _check_watchdog(self, now: float) -> None:
        if self._watchdog_ms and self._last_write is not None \
                and now - self._last_write > self._watchdog_ms / 1000.0:
            for i in range(self.axes.n):
                if self.axes.fault[i] == 0:
                    self.axes.set_fault(i, HOST_WATCHDOG_ERROR)
            self._last_write = None  # faulted once; the host's reset re-arms it

    def _written(self, address: int, values: list[int], now: float) -> None:
        full = [None] * _HR_COUNT
        full[address:address + len(values)] = values
        self.writes = (self.writes + [list(values)])[-1000:]
        self._last_write = now
        ax = self.axes
        for i in range(ax.n):
            cw = full[HR_CONTROL + i]
            if cw is None:
                continue
            if cw & CW_FAULT_RESET and not self._control[i] & CW_FAULT_RESET:
                ax.fault[i] = 0
            ax.enabled[i] = bool(cw & CW_ENABLE) and ax.fault[i] == 0
            if cw & CW_HALT:
                ax.target[i] = ax.position[i]
            self._control[i] = cw
        if all(v is not None for v in full[HR_TARGET:HR_TARGET + 8]):
            targets = decode_int32(full[HR_TARGET:HR_TARGET + 8])
            for i in range(ax.n):
                if ax.enabled[i] and not self._control[i] & CW_HALT:
                    ax.target[i] = float(targets[i])
        if full[HR_WATCHDOG] is not None:
            self._watchdog_ms = int(full[HR_WATCHDOG])

    def _fill_inputs(self, registers: list[int]) -> None:
        ax = self.axes
        reached = ax.reached()
        status = [(SW_ENABLED if ax.enabled[i] else 0) | (SW_FAULT if ax.fault[i] else 0)
                  | (SW_REACHED if reached[i] else 0) for i in range(ax.n)]
        cycle = self._hung_at if self._hung_at is not None else self._cycle()
        registers[:IR_COUNT] = (status + encode_int32(ax.counts())
                                + [int(c) & 0xFFFF for c in ax.fault] + [cycle])

    def positions(self) -> np.ndarray:
        """The axes' positions now, counts."""
        with self.axes.lock:
            self.axes.advance(time.monotonic())
            return self.axes.counts()
