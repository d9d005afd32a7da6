"""Safety inputs from a serial e-stop / foot-pedal box (``pyserial``); backend ``"serial"``.

The box streams one status line per period (20-100 Hz is typical) in this ASCII format
(docs/formats.md, "Serial safety-input lines")::

    $OSIO,<seq>,<estop>,<pedal>*<CRC>\\n

- ``seq``: decimal 0..65535, +1 per line, wrapping to 0. A line whose ``seq`` does not
  advance is no heartbeat (firmware stuck in a loop that repeats its last line).
- ``estop``, ``pedal``: ``1`` pressed, ``0`` released.
- ``CRC``: four hex digits, the CRC-16/CCITT-FALSE (polynomial 0x1021, initial 0xFFFF;
  ``binascii.crc_hqx(body, 0xFFFF)``) of every byte between ``$`` and ``*``. Unlike NMEA's
  XOR checksum it catches the e-stop and pedal digits swapped. A trailing ``\\r`` is
  accepted.

Fail-safe reading (on top of the base class's rule): the input reads **connected** only
while (a) the port is open, (b) the last advancing line is at most ``heartbeat_timeout`` s
old, and (c) at least ``recover_lines`` good lines have arrived in a row since the last
fault. A silent line, a line that does not parse (garbage, a bad checksum, a line longer than
``MAX_LINE`` bytes) and a lost port are each a fault, named in ``InputState.fault``; the
e-stop then reads pressed, which latches the daemon's stop. The driver keeps reading and
reopens a lost port with back-off, so the input recovers on its own when the box returns;
clearing the latched stop stays the operator's decision.
"""

from __future__ import annotations

import binascii
import logging
import math
import threading
import time
from dataclasses import dataclass

import anyio.to_thread
import serial

from ..clock import Clock, WallClock
from ..errors import DriverInitError
from ..lifecycle import LifecycleState
from .base import InputState, SafetyInputs

__all__ = ["MAX_LINE", "SerialInputs", "StatusLine", "encode_line", "parse_line"]

log = logging.getLogger(__name__)

#: Longest accepted line, bytes, newline excluded; more without a newline is garbage.
MAX_LINE = 64
_TAG = b"OSIO"
_SEQ_MOD = 65536


@dataclass(frozen=True)
class StatusLine:
    """One decoded status line of the box."""

    seq: int
    estop_pressed: bool
    pedal_pressed: bool


def _checksum(body: bytes) -> int:
    return binascii.crc_hqx(body, 0xFFFF)


def encode_line(seq: int, estop_pressed: bool, pedal_pressed: bool) -> bytes:
    """The status line for these values, newline included (what the box sends)."""
    if not 0 <= seq < _SEQ_MOD:
        raise ValueError(f"seq must be in 0..{_SEQ_MOD - 1}, got {seq}")
    body = b"%s,%d,%d,%d" % (_TAG, seq, int(bool(estop_pressed)), int(bool(pedal_pressed)))
    return b"$%s*%04X\n" % (body, _checksum(body))


def parse_line(line: bytes) -> StatusLine:
    """Decode one line (without its ``\\n``; a trailing ``\\r`` is stripped).

    Raises:
        ValueError: the line is not a status line; the message says what is wrong.
    """
    line = line.rstrip(b"\r")
    if not line.startswith(b"$") or len(line) < 6 or line[-5:-4] != b"*":
        raise ValueError(f"not a $OSIO line: {line[:40]!r}")
    body, cs_text = line[1:-5], line[-4:]
    try:
        cs = int(cs_text, 16)
    except ValueError:
        raise ValueError(f"CRC {cs_text!r} is not four hex digits") from None
    if cs != _checksum(body):
        raise ValueError(f"bad CRC {cs_text.decode('ascii', 'replace')} "
                         f"(computed {_checksum(body):04X}) in {line[:40]!r}")
    parts = body.split(b",")
    if len(parts) != 4 or parts[0] != _TAG:
        raise ValueError(f"expected $OSIO,<seq>,<estop>,<pedal>, got {line[:40]!r}")
    if not parts[1].isdigit() or int(parts[1]) >= _SEQ_MOD:
        raise ValueError(f"seq {parts[1][:8]!r} is not in 0..{_SEQ_MOD - 1}")
    flags = parts[2:]
    if any(f not in (b"0", b"1") for f in flags):
        raise ValueError(f"estop/pedal must be 0 or 1, got {b','.join(flags)[:16]!r}")
    return StatusLine(int(parts[1]), flags[0] == b"1", flags[1] == b"1")


class SerialInputs(SafetyInputs):
    """E-stop and foot pedal read from a serial status stream (see the module docstring).

    Args:
        port: the device path; prefer a stable udev name (``/dev/serial/by-id/...``), which
            also lets a replugged box come back under the same path.
        baudrate: line speed (8N1).
        heartbeat_timeout: s without an advancing line after which the input is silent.
        recover_lines: good lines in a row needed to read connected again after a fault.
        connect_timeout: s ``start()`` waits for the first good lines; the input then reads
            as it is (a fault if the box has not spoken) and keeps trying in the background.
        reopen_backoff: (first, max) s between attempts to reopen a lost port, doubling.
        clock: timestamps (default: the wall clock).
        name: for messages and logs.
    """

    def __init__(self, port: str, *, baudrate: int = 115200, heartbeat_timeout: float = 0.1,
                 recover_lines: int = 3, connect_timeout: float = 2.0,
                 reopen_backoff: tuple[float, float] = (0.1, 2.0), clock: Clock | None = None,
                 name: str = "inputs") -> None:
        super().__init__(name)
        if not isinstance(port, str) or not port:
            raise DriverInitError(f"inputs {name!r}: port must be a device path, got {port!r}")
        if isinstance(baudrate, bool) or not isinstance(baudrate, int) or baudrate <= 0:
            raise DriverInitError(f"inputs {name!r}: baudrate must be a positive integer, "
                                  f"got {baudrate!r}")
        for key, v in (("heartbeat_timeout", heartbeat_timeout),
                       ("connect_timeout", connect_timeout)):
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
                raise DriverInitError(f"inputs {name!r}: {key} must be > 0 s, got {v!r}")
        if isinstance(recover_lines, bool) or not isinstance(recover_lines, int) \
                or recover_lines < 1:
            raise DriverInitError(f"inputs {name!r}: recover_lines must be an integer >= 1, "
                                  f"got {recover_lines!r}")
        lo, hi = reopen_backoff
        if not (0 < lo <= hi and math.isfinite(hi)):
            raise DriverInitError(f"inputs {name!r}: reopen_backoff must be 0 < first <= max, "
                                  f"got {reopen_backoff!r}")
        self.clock: Clock = WallClock() if clock is None else clock
        self.port, self.baudrate = port, baudrate
        self.heartbeat_timeout = float(heartbeat_timeout)
        self.recover_lines = recover_lines
        self.connect_timeout = float(connect_timeout)
        self._backoff = (float(lo), float(hi))
        self._lock = threading.Lock()
        self._wake = threading.Event()  # set by close(): the reader thread leaves
        self._thread: threading.Thread | None = None
        self._ser: serial.Serial | None = None
        self._life = LifecycleState()  # changed under _lock; _wake tells the thread
        # what the reader thread learnt (under _lock)
        self._open = False
        self._last: StatusLine | None = None
        self._last_time: float | None = None  # clock time of the last advancing line
        self._streak = 0                       # good lines since the last fault
        self._fault: str | None = None         # the last fault, until recovered
        self._last_fault: str | None = None    # the last fault, kept
        self.lines = 0          # good lines received
        self.bad_lines = 0      # lines that did not parse
        self.lost_lines = 0     # seq gaps (lines the box sent that never arrived)
        self.reopens = 0        # times a lost port was opened again

    # -- lifecycle ---------------------------------------------------------------------
    async def start(self) -> None:
        with self._lock:
            # running at once: the reader thread reports the link's faults from here on
            self._life.start(
                f"inputs {self.name!r}: start() called twice (build new ones after close)")
        try:
            self._open_port()
        except serial.SerialException as exc:
            # a box that is not plugged in yet is a fault the reader keeps trying to clear
            self._set_fault(str(exc))  # pyserial names the port
        self._thread = threading.Thread(target=self._run, name=f"serial-{self.name}",
                                        daemon=True)
        self._thread.start()
        await anyio.to_thread.run_sync(self._wait_connected)
        st = self._read()
        if not st.connected:
            log.warning("inputs %r on %s not connected after %.1f s: %s", self.name, self.port,
                        self.connect_timeout, st.fault)

    def _wait_connected(self) -> None:
        deadline = time.monotonic() + self.connect_timeout
        while time.monotonic() < deadline and not self._wake.is_set():
            if self._read().connected:
                return
            time.sleep(0.005)

    async def close(self) -> None:
        with self._lock:
            self._life.close()
        self._wake.set()
        thread, self._thread = self._thread, None
        if thread is not None:
                await anyio.to_thread.run_sync(thread.join, 2.0)
        self._close_port()

    # -- reading -------------------------------------------------------------------------
    def _read(self) -> InputState:
        now = float(self.clock.now())
        with self._lock:
            last, t, fault = self._last, self._last_time, self._fault
            connected = (self._open and self._life.running and last is not None
                         and self._streak >= self.recover_lines)
            if connected and t is not None and now - t > self.heartbeat_timeout:
                connected = False
                fault = (f"serial line {self.port} silent for {now - t:.3f} s "
                         f"(heartbeat limit {self.heartbeat_timeout:.3f} s)")
            if not self._life.running:
                fault = self._life.refusal()  # "not started" or "closed"
            if not connected and fault is None:
                fault = self._waiting(last)
        return InputState(
            timestamp=t if t is not None else now,
            estop_pressed=last.estop_pressed if last is not None else True,
            pedal_pressed=last.pedal_pressed if last is not None else False,
            connected=connected,
            fault=None if connected else fault,
        )

    def _waiting(self, last: StatusLine | None) -> str:
        """Why a reading without a fault is not connected yet (under ``_lock``)."""
        if last is None:
            return f"no status line from {self.port} yet"
        return (f"{self.port} recovering ({self._streak} of {self.recover_lines} good lines "
                f"in a row)")

    # -- the reader thread ---------------------------------------------------------------
    def _open_port(self) -> None:
        ser = serial.Serial(self.port, self.baudrate, timeout=0.02, exclusive=True)
        with self._lock:
            self._ser, self._open = ser, True
            self._streak = 0

    def _close_port(self) -> None:
        with self._lock:
            ser, self._ser, self._open = self._ser, None, False
        if ser is not None:
            try:
                ser.close()
            except Exception:  # closing a vanished device may fail; nothing to keep
                log.debug("closing %s", self.port, exc_info=True)

    @property
    def last_fault(self) -> str | None:
        """The latest fault the reader met, kept after the input recovered (None: none)."""
        with self._lock:
            return self._last_fault

    def _set_fault(self, why: str) -> None:
        with self._lock:
            new = why != self._fault
            self._fault, self._last_fault, self._streak = why, why, 0
        if new:
            log.warning("inputs %r: %s", self.name, why)

    def _run(self) -> None:
        buf = b""
        delay = self._backoff[0]
        while not self._wake.is_set():
            ser = self._ser
            if ser is None:
                try:
                    self._open_port()
                except serial.SerialException as exc:
                    self._set_fault(str(exc))  # pyserial names the port
                    self._wake.wait(delay)
                    delay = min(2 * delay, self._backoff[1])
                    continue
                self.reopens += 1
                delay, buf = self._backoff[0], b""
                log.info("inputs %r: reopened %s", self.name, self.port)
                continue
            try:
                chunk = ser.read(max(1, ser.in_waiting))
            except (serial.SerialException, OSError, TypeError) as exc:
                # TypeError: pyserial reading a port closed under it
                if self._wake.is_set():
                    break
                self._set_fault(f"lost {self.port}: {exc}")
                self._close_port()
                continue
            if not chunk:
                continue
            buf += chunk
            *lines, buf = buf.split(b"\n")
            for line in lines:
                self._take(line)
            if len(buf) > MAX_LINE:
                self._bad(f"{len(buf)} bytes without a newline: {buf[:24]!r}...")
                buf = b""

    def _take(self, raw: bytes) -> None:
        if len(raw) > MAX_LINE:
            self._bad(f"line of {len(raw)} bytes (max {MAX_LINE}): {raw[:24]!r}...")
            return
        try:
            line = parse_line(raw)
        except ValueError as exc:
            self._bad(str(exc))
            return
        now = float(self.clock.now())
        with self._lock:
            prev = self._last
            if prev is not None:
                step = (line.seq - prev.seq) % _SEQ_MOD
                if step == 0:  # repeats are no heartbeat: the silence check will trip
                    return
                self.lost_lines += step - 1
            gap = None if self._last_time is None else now - self._last_time
            if gap is not None and gap > self.heartbeat_timeout:
                # the line was silent: note it, and recover as after any other fault
                self._streak = 0
                self._last_fault = (f"serial line {self.port} silent for {gap:.3f} s "
                                    f"(heartbeat limit {self.heartbeat_timeout:.3f} s)")
            self._last, self._last_time = line, now
            self.lines += 1
            self._streak += 1
            if self._streak >= self.recover_lines and self._fault is not None:
                log.info("inputs %r: %s reads again (%s cleared)", self.name, self.port,
                         self._fault)
                self._fault = None

    def _bad(self, why: str) -> None:
        with self._lock:
            self.bad_lines += 1
        self._set_fault(f"garbage on serial line {self.port}: {why}")
