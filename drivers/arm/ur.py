"""A Universal Robots arm through ``ur_rtde`` (RTDEControlInterface / RTDEReceiveInterface).

Two RTDE connections to the controller, both at ``frequency`` (default: the controller's own
rate, 500 Hz e-Series, 125 Hz CB3): ``RTDEReceiveInterface`` streams the TCP pose, twist and
wrench, the robot and safety modes and the program state; ``RTDEControlInterface`` uploads
ur_rtde's control script and drives it through the RTDE registers (servoL, speedL,
servoStop, speedStop, the RTDE input watchdog).

**The ur_rtde host process.** Both interfaces live in a child process
(``python -m oralnav.drivers.arm.ur --ur-host``), one per connection, because ur_rtde cannot
be trusted inside the daemon: its Python constructors hold the GIL for as long as they talk
to the controller (seconds when it does not answer), each destructor sleeps 0.5 s holding the
GIL, its calls can block for seconds on a dead link, and its control interface reconnects by
itself from its receive thread in a way that leaves a thread behind which crashes the process
when the object is destroyed. The driver talks to the child over pipes; on a lost link, or a
call that does not return, it kills the child and starts a fresh one. The child streams the
receive interface's data to the driver as fixed binary records.

**Threads.** The 500 Hz control thread never waits on the controller:

- :meth:`URArm.state` returns what the child last streamed (no I/O);
- :meth:`~URArm.servo`, :meth:`~URArm.speed`, :meth:`~URArm.stop` and :meth:`~URArm.kick`
  check from that state that the arm can obey, then hand the command to the **command
  thread**, which sends it to the child and waits for ur_rtde's answer: a motion command
  replaces one not yet sent (the latest set point wins);
- the **link thread** watches the connection (the receive interface's flag, controller
  timestamps that stop advancing, the child itself) and on a loss kills the child and
  reconnects with back-off (doubling from ``reconnect_backoff[0]`` to ``[1]``);
- a **reader thread** per child takes in its records.

**Watchdog.** The control script's RTDE watchdog (``setWatchdog(1 / watchdog_timeout)``) is
armed before the first motion command after every (re)connection; from then on the controller
stops the program, and the arm, when it hears neither a command nor a :meth:`~URArm.kick` for
``watchdog_timeout`` s. Kicks are sent only when no other command went out for a couple of
controller cycles (a kick overwrites the command register, so it could hide a servo set
point the script has not read yet). The script does not hear the watchdog register while it
brakes, so :meth:`~URArm.stop` brakes at ``stop_decel`` or harder, to stand still within half
the watchdog timeout.

**Faults.** A protective stop, an emergency stop and a stopped control program (the watchdog,
the pendant) show in :meth:`~URArm.state` (``ready`` False) and :attr:`~URArm.fault`, and
refuse motion with ``DriverIOError``. Nothing is cleared automatically: :meth:`~URArm.recover`
(the operator's request) unlocks a protective stop, powers on, releases the brakes and
restarts the control program through the dashboard server. A lost controller reads
``connected`` False and refuses commands (``stop()`` only logs); when it answers again the
driver reconnects, which uploads the control script again (ur_rtde does so on connect), and
re-arms the watchdog with the next motion command.

ur_rtde fixes the ports: RTDE 30004, script 30003, dashboard 29999. Before starting a child
the driver probes them from Python with ``connect_timeout``, so a wrong address fails fast
with the host and port named.
"""

from __future__ import annotations

import importlib
import logging
import math
import os
import re
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

from ..clock import Clock, WallClock
from ..errors import DriverError, DriverInitError, DriverIOError
from ..lifecycle import LifecycleState
from .base import Arm, ArmCommandError, ArmState
from .ur_protocol import (
    DASHBOARD_PORT,
    RTDE_HEADER,
    RTDE_IN_USE,
    RTDE_NOT_FOUND,
    RTDE_PORT,
    RTDE_REQUEST_PROTOCOL_VERSION,
    RTDE_SETUP_INPUTS,
    SAFETY_BIT_ESTOP,
    SAFETY_BIT_PROTECTIVE,
    SAFETY_BIT_ROBOT_ESTOP,
    SAFETY_BIT_SYSTEM_ESTOP,
    SCRIPT_PORT,
    DashboardCommand,
    RobotMode,
    RuntimeState,
    SafetyMode,
)

__all__ = ["DASHBOARD_PORT", "RECEIVE_VARIABLES", "RTDE_PORT", "SCRIPT_PORT", "URArm"]

log = logging.getLogger(__name__)

# The ports ur_rtde uses, RTDE_PORT, SCRIPT_PORT and DASHBOARD_PORT (re-exported from
# ur_protocol), are fixed in ur_rtde, the control interface's dashboard port included.

#: What the receive interface streams.
RECEIVE_VARIABLES = (
    "timestamp", "actual_TCP_pose", "actual_TCP_speed", "actual_TCP_force", "robot_mode",
    "safety_mode", "safety_status_bits", "robot_status_bits", "runtime_state",
)

# The controller's modes in words, for messages and diagnostics ("power off", "protective
# stop"), from UR's names (ur_protocol).
_ROBOT_MODES = {v: n.lower().replace("_", " ") for v, n in RobotMode.NAMES.items()}
_SAFETY_MODES = {v: n.lower().replace("_", " ") for v, n in SafetyMode.NAMES.items()}
# this driver has always called mode 13 by its short name (its messages stay as they were)
_SAFETY_MODES[SafetyMode.SYSTEM_THREE_POSITION_ENABLING_STOP] = "three position enabling stop"
_SAFETY_OK = (SafetyMode.NORMAL, SafetyMode.REDUCED)  # the control script may run
_ESTOP_MODES = (SafetyMode.SYSTEM_EMERGENCY_STOP, SafetyMode.ROBOT_EMERGENCY_STOP)

# ur_rtde's argument ranges (rtde_control_interface.h).
_LOOKAHEAD_RANGE = (0.03, 0.2)
_GAIN_RANGE = (100.0, 2000.0)
_MAX_TOOL_ACCEL = 150.0
_SERVO_SPEED, _SERVO_ACCEL = 0.5, 0.5  # servoL's speed/acceleration: unused by ur_rtde

# A state record from the child: count, controller time, pose, twist, wrench (6 each),
# robot mode, safety mode, safety status bits, runtime state, flags.
_RECORD = struct.Struct("=Qd6d6d6diiIII")
_FLAG_RECEIVING, _FLAG_CONTROL = 1, 2


# --- pose conversions ---------------------------------------------------------------------------


def _rotvec_to_matrix(rv: np.ndarray) -> np.ndarray:
    theta = float(np.linalg.norm(rv))
    if theta < 1e-12:
        return np.eye(3)
    k = rv / theta
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(theta) * K + (1.0 - math.cos(theta)) * (K @ K)


def _matrix_to_rotvec(R: np.ndarray) -> np.ndarray:
    axis = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    cos = min(1.0, max(-1.0, (float(np.trace(R)) - 1.0) / 2.0))
    theta = math.atan2(0.5 * float(np.linalg.norm(axis)), cos)  # well-conditioned near pi
    if theta < 1e-6:
        return 0.5 * axis
    if theta < math.pi / 2:
        return axis * (theta / (2.0 * math.sin(theta)))
    # Near pi the antisymmetric part vanishes: take the axis from the symmetric part,
    # (R + R^T) / 2 = cos(theta) I + (1 - cos(theta)) k k^T.
    M = ((R + R.T) / 2.0 - cos * np.eye(3)) / (1.0 - cos)
    i = int(np.argmax(np.diag(M)))
    k = M[:, i] / math.sqrt(max(M[i, i], 1e-300))
    k /= np.linalg.norm(k)
    if float(k @ axis) < 0.0:
        k = -k
    return k * theta


def _pose6(T: np.ndarray) -> list[float]:
    return [*T[:3, 3].tolist(), *_matrix_to_rotvec(T[:3, :3]).tolist()]


def _matrix(pose6: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = _rotvec_to_matrix(np.asarray(pose6[3:6], dtype=float))
    T[:3, 3] = pose6[:3]
    return T


# --- the ur_rtde host (child process) -----------------------------------------------------------


def _robot_not_ready(robot_mode: int, safety_mode: int, bits: int) -> str | None:
    """Why the control script cannot run now (None: it can)."""
    if (bits >> SAFETY_BIT_ESTOP & 1 or bits >> SAFETY_BIT_ROBOT_ESTOP & 1
            or bits >> SAFETY_BIT_SYSTEM_ESTOP & 1):
        return "emergency stop"
    if bits >> SAFETY_BIT_PROTECTIVE & 1 or safety_mode == SafetyMode.PROTECTIVE_STOP:
        return "protective stop"
    if safety_mode not in _SAFETY_OK:
        return f"safety mode {_SAFETY_MODES.get(safety_mode, safety_mode)}"
    if robot_mode != RobotMode.RUNNING:
        return f"robot mode {_ROBOT_MODES.get(robot_mode, robot_mode)}"
    return None


class _Host:
    """Child side: ur_rtde's interfaces, a publisher of their state and a command server."""

    def __init__(self, cfg: dict[str, Any], state_fd: int) -> None:
        self.cfg = cfg
        self.state_fd = state_fd
        self.r: Any = None
        self.c: Any = None
        self.count = 0
        self.stage = "ur_rtde"

    def open(self) -> dict[str, Any]:
        import rtde_receive

        cfg = self.cfg
        self.stage = "RTDE receive interface"
        self.r = rtde_receive.RTDEReceiveInterface(
            cfg["host"], cfg["frequency"], list(RECEIVE_VARIABLES), False,
            cfg["upper_range_registers"], cfg["rt_priority"])
        why = _robot_not_ready(self.r.getRobotMode(), self.r.getSafetyMode(),
                               self.r.getSafetyStatusBits())
        if why is None:
            self.stage = "RTDE control interface"
            self.open_control()
        return {"control": self.c is not None, "why": why}

    def open_control(self) -> bool:
        import rtde_control

        cfg = self.cfg
        flags = rtde_control.RTDEControlInterface.FLAG_UPLOAD_SCRIPT
        if cfg["upper_range_registers"]:
            flags |= rtde_control.RTDEControlInterface.FLAG_UPPER_RANGE_REGISTERS
        if self.c is None:
            self.c = rtde_control.RTDEControlInterface(cfg["host"], cfg["frequency"],
                                                       int(flags), 50002, cfg["rt_priority"])
        return True

    def publish(self) -> None:
        """Stream a record whenever the controller timestamp changes (and on flag changes)."""
        r = self.r
        last_ts, last_flags = None, -1
        period = 1.0 / (self.cfg["frequency"] if self.cfg["frequency"] > 0 else 500.0)
        while True:
            connected = r.isConnected()
            flags = (_FLAG_RECEIVING if connected else 0) | (
                _FLAG_CONTROL if self.c is not None else 0)
            ts = r.getTimestamp()
            if ts != last_ts or flags != last_flags:
                pose, twist, wrench = (r.getActualTCPPose(), r.getActualTCPSpeed(),
                                       r.getActualTCPForce())
                robot_mode, safety_mode = r.getRobotMode(), r.getSafetyMode()
                bits, runtime = r.getSafetyStatusBits(), r.getRuntimeState()
                if r.getTimestamp() == ts and len(pose) == len(twist) == len(wrench) == 6:
                    self.count += 1
                    record = _RECORD.pack(self.count, ts, *pose, *twist, *wrench, robot_mode,
                                          safety_mode, bits, runtime, flags)
                    try:
                        os.write(self.state_fd, record)
                    except BlockingIOError:
                        pass  # the driver is behind: it only wants the latest anyway
                    except OSError:
                        os._exit(0)  # the driver is gone
                    last_ts, last_flags = ts, flags
                    time.sleep(period * 0.4)
                    continue
            time.sleep(0.0002 if connected else 0.01)

    def call(self, name: str, args: tuple) -> Any:
        c = self.c
        if name == "open_control":
            return self.open_control()
        if c is None:
            raise RuntimeError("no control interface")
        fn = {
            "servoL": c.servoL, "speedL": c.speedL, "servoStop": c.servoStop,
            "speedStop": c.speedStop, "kickWatchdog": c.kickWatchdog,
            "setWatchdog": c.setWatchdog, "stopScript": c.stopScript,
            "reuploadScript": c.reuploadScript,
        }.get(name)
        if fn is None:
            raise RuntimeError(f"unknown call {name!r}")
        return fn(*args)


def _host_main(cmd_fd: int, res_fd: int, state_fd: int) -> None:
    """The child: open ur_rtde from the first message's config, then serve calls. Exits with
    ``os._exit`` so that no ur_rtde destructor runs (the OS closes its sockets)."""
    cmd = Connection(cmd_fd, writable=False)
    res = Connection(res_fd, readable=False)
    os.set_blocking(state_fd, False)
    try:
        cfg = cmd.recv()
        host = _Host(cfg, state_fd)
        try:
            info = host.open()
        except Exception as exc:
            res.send(("error", host.stage, str(exc) or type(exc).__name__))
            os._exit(0)
        res.send(("ok", info))
        threading.Thread(target=host.publish, daemon=True, name="ur-host-publish").start()
        while True:
            try:
                name, args = cmd.recv()
            except (EOFError, OSError):
                break
            if name == "exit":
                break
            try:
                res.send(("ok", host.call(name, args)))
            except Exception as exc:
                res.send(("exc", f"{type(exc).__name__}: {exc}"))
    finally:
        os._exit(0)


class _HostDead(Exception):
    """The child did not answer in time or is gone."""


class _HostProcess:
    """Driver side of one child: spawn, call, read its records, kill."""

    def __init__(self, cfg: dict[str, Any], on_record: Callable[[_HostProcess, tuple], None],
                 on_exit: Callable[[_HostProcess], None], name: str) -> None:
        self.cfg = cfg
        self.name = name
        self._on_record, self._on_exit = on_record, on_exit
        self._lock = threading.Lock()
        cmd_r, cmd_w = os.pipe()
        res_r, res_w = os.pipe()
        state_r, state_w = os.pipe()
        try:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "oralnav.drivers.arm.ur", "--ur-host",
                 str(cmd_r), str(res_w), str(state_w)],
                pass_fds=(cmd_r, res_w, state_w), stdin=subprocess.DEVNULL)
        except BaseException:
            for fd in (cmd_r, cmd_w, res_r, res_w, state_r, state_w):
                os.close(fd)
            raise
        for fd in (cmd_r, res_w, state_w):
            os.close(fd)
        self._cmd = Connection(cmd_w, readable=False)
        self._res = Connection(res_r, writable=False)
        self._state_fd = state_r
        self._reader: threading.Thread | None = None
        self.dead = False

    def open(self, timeout: float, cancel: threading.Event) -> dict[str, Any]:
        """Send the config and wait for the interfaces. Raises ``_HostDead`` (no answer within
        ``timeout``, or ``cancel`` set) or ``RuntimeError(stage, text)`` (ur_rtde raised)."""
        self._cmd.send(self.cfg)
        deadline = time.monotonic() + timeout
        while not self._res.poll(0.05):
            if cancel.is_set():
                raise _HostDead("connecting cancelled by close()")
            if time.monotonic() > deadline:
                raise _HostDead(f"ur_rtde did not connect within {timeout:g} s")
        try:
            status, *rest = self._res.recv()
        except (EOFError, OSError):
            raise _HostDead("the ur_rtde host process died while connecting") from None
        if status != "ok":
            raise RuntimeError(rest[0], rest[1])
        self._reader = threading.Thread(target=self._read_records, daemon=True,
                                        name=f"ur-arm-{self.name}-reader")
        self._reader.start()
        return rest[0]

    def call(self, name: str, *args: Any, timeout: float) -> Any:
        """One ur_rtde call in the child. Raises ``_HostDead`` (no answer within ``timeout``,
        or gone) or ``RuntimeError`` (ur_rtde raised)."""
        with self._lock:
            if self.dead:
                raise _HostDead("the ur_rtde host process is gone")
            try:
                self._cmd.send((name, args))
                if not self._res.poll(timeout):
                    self.dead = True
                    raise _HostDead(f"ur_rtde {name}() did not return within {timeout:g} s")
                status, value = self._res.recv()
            except (EOFError, OSError):
                self.dead = True
                raise _HostDead("the ur_rtde host process is gone") from None
        if status != "ok":
            raise RuntimeError(value)
        return value

    def _read_records(self) -> None:
        buf = b""
        size = _RECORD.size
        while True:
            try:
                chunk = os.read(self._state_fd, 64 * size)
            except OSError:
                chunk = b""
            if not chunk:
                break
            buf += chunk
            n = len(buf) // size
            if n:
                self._on_record(self, _RECORD.unpack_from(buf, (n - 1) * size))
                buf = buf[n * size:]
        self.dead = True
        self._on_exit(self)

    def kill(self) -> None:
        """End the child at once (the OS closes its sockets; no ur_rtde destructor runs) and
        collect its reader. Idempotent."""
        self.dead = True
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait()
        with self._lock:  # a call in flight sees EOF and returns first
            self._cmd.close()
            self._res.close()
        if self._reader is not None and self._reader is not threading.current_thread():
            self._reader.join(2.0)
        try:
            os.close(self._state_fd)
        except OSError:
            pass


# --- the driver ---------------------------------------------------------------------------------


def _option(value: object, what: str, unit: str, name: str, lo: float = 0.0,
            hi: float = math.inf, lo_open: bool = True) -> float:
    try:
        out = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        out = math.nan
    low_ok = out > lo if lo_open else out >= lo
    if isinstance(value, bool) or not math.isfinite(out) or not low_ok or out > hi:
        rng = f"> {lo:g}" if lo_open else f">= {lo:g}"
        rng += f" and <= {hi:g}" if math.isfinite(hi) else ""
        raise DriverInitError(f"arm {name!r}: {what} must be a finite number of {unit} {rng}, "
                              f"got {value!r}")
    return out


class _Sample:
    """The controller's state as last streamed, decoded."""

    __slots__ = ("ctrl_time", "T", "twist", "wrench", "robot_mode", "safety_mode",
                 "safety_bits", "runtime_state", "receiving", "control")

    def __init__(self, rec: tuple) -> None:
        self.ctrl_time = rec[1]
        self.T = _matrix(np.array(rec[2:8]))
        self.twist = np.array(rec[8:14])
        self.wrench = np.array(rec[14:20])
        self.robot_mode, self.safety_mode, self.safety_bits, self.runtime_state = rec[20:24]
        self.receiving = bool(rec[24] & _FLAG_RECEIVING)
        self.control = bool(rec[24] & _FLAG_CONTROL)

    @property
    def protective(self) -> bool:
        return (bool(self.safety_bits >> SAFETY_BIT_PROTECTIVE & 1)
                or self.safety_mode == SafetyMode.PROTECTIVE_STOP)

    @property
    def estop(self) -> bool:
        bits = self.safety_bits
        return bool(bits >> SAFETY_BIT_ESTOP & 1 or bits >> SAFETY_BIT_ROBOT_ESTOP & 1
                    or bits >> SAFETY_BIT_SYSTEM_ESTOP & 1) or self.safety_mode in _ESTOP_MODES

    @property
    def not_ready(self) -> str | None:
        return _robot_not_ready(self.robot_mode, self.safety_mode, self.safety_bits)


class URArm(Arm):
    """A UR arm over ur_rtde; see the module docstring.

    Args:
        name: for messages and logs.
        host: the controller's address (IP or host name).
        frequency: RTDE rate, Hz (None: the controller's, 500 e-Series / 125 CB3).
        lookahead_time: servoL lookahead, s (0.03 ... 0.2): smoother, later tracking.
        gain: servoL proportional gain (100 ... 2000).
        watchdog_timeout: s without a command or kick before the controller stops the arm
            (the RTDE watchdog runs at ``1 / watchdog_timeout`` Hz).
        stop_decel: m/s^2 for stop() (raised when needed to stand still within half the
            watchdog timeout).
        connect_timeout: s for each port probe and each dashboard call.
        stale_timeout: s without new controller data before the arm reads disconnected.
        link_timeout: s without new data before the link is dropped and reopened.
        command_timeout: s a ur_rtde call may take (stops: plus the braking time) before the
            link is dropped and reopened.
        reconnect_backoff: (first, max) s between reconnection attempts, doubling.
        clock: the clock of ``ArmState.timestamp`` (default: the wall clock); controller
            timestamps are mapped onto it.
        upper_range_registers: use RTDE registers 24-47 (leave 0-23 to a fieldbus).
        rt_priority: ur_rtde's receive-thread real-time priority (0: its default).
    """

    def __init__(self, name: str = "arm", *, host: str, frequency: float | None = None,
                 lookahead_time: float = 0.1, gain: float = 300.0,
                 watchdog_timeout: float = 0.05, stop_decel: float = 10.0,
                 connect_timeout: float = 2.0, stale_timeout: float = 0.1,
                 link_timeout: float = 1.0, command_timeout: float = 1.0,
                 reconnect_backoff: tuple[float, float] = (0.2, 5.0),
                 clock: Clock | None = None, upper_range_registers: bool = False,
                 rt_priority: int = 0) -> None:
        super().__init__(name)
        if not isinstance(host, str) or not host.strip():
            raise DriverInitError(f"arm {name!r}: host must be the controller's address, "
                                  f"got {host!r}")
        self.host = host.strip()
        self.frequency = None if frequency is None else _option(
            frequency, "frequency", "Hz", name, hi=500.0)
        self.lookahead_time = _option(lookahead_time, "lookahead_time", "s", name,
                                      *_LOOKAHEAD_RANGE, lo_open=False)
        self.gain = _option(gain, "gain", "(servoL gain)", name, *_GAIN_RANGE, lo_open=False)
        self.watchdog_timeout = _option(watchdog_timeout, "watchdog_timeout", "s", name)
        self.stop_decel = _option(stop_decel, "stop_decel", "m/s^2", name, hi=_MAX_TOOL_ACCEL)
        self.connect_timeout = _option(connect_timeout, "connect_timeout", "s", name)
        self.stale_timeout = _option(stale_timeout, "stale_timeout", "s", name)
        self.link_timeout = _option(link_timeout, "link_timeout", "s", name)
        self.command_timeout = _option(command_timeout, "command_timeout", "s", name)
        try:
            lo, hi = (float(x) for x in reconnect_backoff)  # type: ignore[union-attr]
        except (TypeError, ValueError):
            lo = hi = math.nan
        if not (0.0 < lo <= hi) or not math.isfinite(hi):
            raise DriverInitError(f"arm {name!r}: reconnect_backoff must be (first, max) s with "
                                  f"0 < first <= max, got {reconnect_backoff!r}")
        self.reconnect_backoff = (lo, hi)
        self.clock: Clock = WallClock() if clock is None else clock
        if not callable(getattr(self.clock, "now", None)):
            raise DriverInitError(f"arm {name!r}: clock must have now() -> seconds, "
                                  f"got {clock!r}")
        self.upper_range_registers = bool(upper_range_registers)
        if isinstance(rt_priority, bool) or not isinstance(rt_priority, int) or rt_priority < 0:
            raise DriverInitError(f"arm {name!r}: rt_priority must be an integer >= 0, "
                                  f"got {rt_priority!r}")
        self.rt_priority = rt_priority

        self._lock = threading.Lock()  # everything below, shared by all threads
        self._cond = threading.Condition(self._lock)
        self._life = LifecycleState()  # changed under _lock
        self._closing = threading.Event()
        self._host: _HostProcess | None = None
        self._connecting = False  # a host is being set up: not ready yet
        self._link_thread: threading.Thread | None = None
        self._cmd_thread: threading.Thread | None = None
        self._sample: _Sample | None = None
        self._fresh_at = -math.inf  # monotonic s of the last new controller timestamp
        self._quiet_until = -math.inf  # a long call in the child: no staleness verdicts
        self._offset: float | None = None  # driver clock - controller clock
        self._offset_at = 0.0
        self._period = 1.0 / (frequency or 500.0)  # controller data period seen, s
        self._pending: tuple | None = None  # the next command (latest wins)
        self._kick = False
        self._busy = False
        self._last_sent = -math.inf
        self._motion: str | None = None  # what the control script runs: servo | speed
        self._watchdog_armed = False
        self._cmd_error: str | None = None  # the controller refused the last command
        self._link_error: str | None = None  # why the link is down
        self._control_error: str | None = None  # why there is no control interface
        self.reconnects = 0  # successful reconnections since start()

    # -- lifecycle ------------------------------------------------------------------------------

    async def start(self) -> None:
        import anyio.to_thread

        with self._lock:
            self._life.begin_start(f"arm {self.name!r}: start() called twice (build a new "
                                   f"arm after close)",
                                   after_close=f"arm {self.name!r}: start() after close()")
        try:
            await anyio.to_thread.run_sync(self._connect)
        except BaseException:
            with self._lock:
                self._life.abort_start()  # not reached: start() may be tried again
            raise
        with self._lock:
            # a close() during the connection leaves it closed; the threads then end at once
            self._life.finish_start()
            self._closing.clear()
        self._link_thread = threading.Thread(target=self._link_loop, daemon=True,
                                             name=f"ur-arm-{self.name}-link")
        self._cmd_thread = threading.Thread(target=self._command_loop, daemon=True,
                                            name=f"ur-arm-{self.name}-cmd")
        self._link_thread.start()
        self._cmd_thread.start()

    async def close(self) -> None:
        import anyio.to_thread

        with self._lock:
            if self._life.closed:
                return
            started = self._life.running
        if started:
            self.stop()
            await anyio.to_thread.run_sync(self._drain, 1.0 + self.command_timeout)
        with self._lock:
            self._life.close()
            self._closing.set()
            self._cond.notify_all()
        await anyio.to_thread.run_sync(self._shutdown)

    def _drain(self, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        with self._cond:
            while (self._pending is not None or self._busy) and time.monotonic() < deadline:
                self._cond.wait(0.01)

    def _shutdown(self) -> None:
        for thread in (self._cmd_thread, self._link_thread):
            if thread is not None:
                thread.join(self.connect_timeout + self.command_timeout + 5.0)
        with self._lock:
            host, self._host = self._host, None
        if host is not None:
            with self._lock:
                has_control = self._sample is not None and self._sample.control
            if has_control:  # leave no control program running on the controller
                try:
                    host.call("stopScript", timeout=self.command_timeout)
                except (_HostDead, RuntimeError) as exc:
                    log.warning("arm %r: ending the control script failed: %s", self.name, exc)
            host.kill()

    # -- connecting -----------------------------------------------------------------------------

    def _probe(self) -> None:
        """Check that the three ports answer, quickly and from Python, before ur_rtde (which
        waits minutes on an unreachable address) is started."""
        t = self.connect_timeout
        for port, what in ((DASHBOARD_PORT, "dashboard server"), (RTDE_PORT, "RTDE interface"),
                           (SCRIPT_PORT, "script interface")):
            if self._closing.is_set():
                raise DriverInitError(f"arm {self.name!r}: connecting cancelled by close()")
            try:
                with socket.create_connection((self.host, port), timeout=t) as s:
                    s.settimeout(t)
                    if port == DASHBOARD_PORT:
                        if not s.recv(256):
                            raise ConnectionError("closed without a greeting")
                    elif port == RTDE_PORT:
                        # request protocol version 2
                        s.sendall(struct.pack(">HBH", 5, RTDE_REQUEST_PROTOCOL_VERSION, 2))
                        kind, payload = _recv_message(s)
                        if kind != RTDE_REQUEST_PROTOCOL_VERSION or payload[:1] != b"\x01":
                            raise ConnectionError("refused RTDE protocol version 2")
            except (OSError, ConnectionError) as exc:
                reason = f"no answer within {t:g} s" if isinstance(exc, TimeoutError) else exc
                raise DriverInitError(f"arm {self.name!r}: cannot connect to the UR controller "
                                      f"at {self.host}:{port} ({what}): {reason}") from None

    def _connect(self, reconnect: bool = False) -> None:
        """Probe, start a ur_rtde host and open the interfaces (the control interface only
        when the robot can run the control script). Raises DriverInitError."""
        self._probe()
        cfg = {"host": self.host, "frequency": -1.0 if self.frequency is None else self.frequency,
               "upper_range_registers": self.upper_range_registers,
               "rt_priority": self.rt_priority}
        try:
            host = _HostProcess(cfg, self._on_record, self._on_exit, self.name)
        except OSError as exc:
            raise DriverInitError(f"arm {self.name!r}: cannot start the ur_rtde host process: "
                                  f"{exc}") from exc
        with self._lock:
            self._host = host
            self._connecting = True
            self._sample = None
            self._offset = None
            self._period = 1.0 / (self.frequency or 500.0)
            self._fresh_at = time.monotonic()
            self._link_error = None
            self._cmd_error = None
            self._motion = None
            self._watchdog_armed = False
        try:
            info = host.open(self.connect_timeout + 10.0, self._closing)
            # Wait for data that shows the outcome: with a control interface, its program
            # running (the receive stream may lag the control interface by a cycle).
            deadline = time.monotonic() + self.connect_timeout
            while True:
                s = self._sample
                if s is not None and s.control == info["control"] and (
                        not s.control or s.runtime_state == RuntimeState.PLAYING):
                    break
                if host.dead or time.monotonic() > deadline:
                    raise _HostDead(f"no data from the UR controller at {self.host}:{RTDE_PORT}"
                                    f" within {self.connect_timeout:g} s")
                time.sleep(0.002)
        except BaseException as exc:
            with self._lock:
                if self._host is host:
                    self._host = None
            host.kill()
            if isinstance(exc, RuntimeError):
                raise self._sdk_error(*exc.args) from None
            if isinstance(exc, _HostDead):
                raise DriverInitError(f"arm {self.name!r}: {exc}") from None
            raise
        with self._lock:
            self._control_error = None if info["control"] else (
                f"no control program: {info['why']} at connection; recover() starts it")
            self._connecting = False
            if reconnect:
                self.reconnects += 1
        if not info["control"]:
            log.warning("arm %r: %s", self.name, self._control_error)

    def _sdk_error(self, stage: str, text: str) -> DriverInitError:
        m = re.search(r"not found by the controller: \[([^\]]*)\]", text)
        if m:
            return DriverInitError(
                f"arm {self.name!r}: the UR controller at {self.host}:{RTDE_PORT} refused the "
                f"RTDE recipe of the {stage}: field(s) {m.group(1)} NOT_FOUND (not offered by "
                f"this PolyScope version)")
        if "already in use" in text:
            fields = self._fields_in_use()
            named = f"field(s) {', '.join(fields)} IN_USE" if fields else "input registers IN_USE"
            return DriverInitError(
                f"arm {self.name!r}: the UR controller at {self.host}:{RTDE_PORT} refused the "
                f"RTDE input recipe of the {stage}: {named} (held by another RTDE client or by "
                f"EtherNet/IP, PROFINET or MODBUS; try upper_range_registers)")
        return DriverInitError(f"arm {self.name!r}: {stage} to the UR controller at "
                               f"{self.host} failed: {text}")

    def _fields_in_use(self) -> list[str]:
        """Ask the controller which of the control script's input registers it refuses (ur_rtde
        reports "in use" without naming them)."""
        off = 24 if self.upper_range_registers else 0
        names = [f"input_int_register_{off + i}" for i in range(8)]
        names += [f"input_double_register_{off + i}" for i in range(18)]
        try:
            with socket.create_connection((self.host, RTDE_PORT),
                                          timeout=self.connect_timeout) as s:
                s.settimeout(self.connect_timeout)
                s.sendall(struct.pack(">HBH", 5, RTDE_REQUEST_PROTOCOL_VERSION, 2))
                _recv_message(s)
                body = ",".join(names).encode()
                s.sendall(RTDE_HEADER.pack(3 + len(body), RTDE_SETUP_INPUTS) + body)
                kind, payload = _recv_message(s)
        except (OSError, ConnectionError):
            return []
        if kind != RTDE_SETUP_INPUTS:
            return []
        types = payload[1:].decode("ascii", "replace").split(",")
        return [n for n, t in zip(names, types, strict=False) if t in (RTDE_IN_USE, RTDE_NOT_FOUND)]

    # -- records from the host ------------------------------------------------------------------

    def _on_record(self, host: _HostProcess, rec: tuple) -> None:
        sample = _Sample(rec)
        mono = time.monotonic()
        now = float(self.clock.now())
        with self._lock:
            if host is not self._host:
                return
            previous = self._sample
            if previous is None or sample.ctrl_time != previous.ctrl_time:
                self._fresh_at = mono
                if previous is not None and sample.ctrl_time > previous.ctrl_time:
                    self._period = min(self._period, sample.ctrl_time - previous.ctrl_time)
                # driver clock = controller clock + offset; the offset follows the smallest
                # delay seen, leaking upward slowly so that clock drift is followed.
                seen = now - sample.ctrl_time
                if self._offset is None or previous is None or (
                        sample.ctrl_time < previous.ctrl_time):
                    self._offset = seen
                else:
                    self._offset = min(self._offset + 1e-4 * (now - self._offset_at), seen)
                self._offset_at = now
            self._sample = sample

    def _on_exit(self, host: _HostProcess) -> None:
        with self._lock:
            if host is self._host and self._link_error is None:
                self._link_error = "the ur_rtde host process ended"

    # -- the link thread ------------------------------------------------------------------------

    def _link_loop(self) -> None:
        poll = min(0.02, self.stale_timeout / 2)
        delay = self.reconnect_backoff[0]
        while not self._closing.is_set():
            with self._lock:
                up = self._host is not None
            if up:
                why = self._link_problem()
                if why is not None:
                    self._drop_link(why)
                    delay = self.reconnect_backoff[0]
                    continue
                self._closing.wait(poll)
                continue
            if self._closing.wait(delay):
                break
            try:
                self._connect(reconnect=True)
            except Exception as exc:
                with self._lock:
                    self._link_error = str(exc) if isinstance(exc, DriverError) else (
                        f"reconnect failed: {type(exc).__name__}: {exc}")
                delay = min(2 * delay, self.reconnect_backoff[1])
                log.warning("arm %r: reconnect failed (next try in %.2g s): %s", self.name,
                            delay, self._link_error)
                continue
            log.warning("arm %r: reconnected to the UR controller at %s", self.name, self.host)

    def _link_problem(self) -> str | None:
        with self._lock:
            host, sample = self._host, self._sample
            silent = time.monotonic() - self._fresh_at
            quiet = time.monotonic() < self._quiet_until
            failed = self._link_error
        if host is None:
            return None
        if failed is not None:
            return failed
        if host.dead:
            return "the ur_rtde host process ended"
        if sample is not None and not sample.receiving:
            return f"RTDE connection to {self.host}:{RTDE_PORT} lost"
        if silent > self.link_timeout and not quiet:
            return f"no RTDE data from {self.host}:{RTDE_PORT} for {silent:.2f} s"
        return None

    def _drop_link(self, why: str) -> None:
        with self._lock:
            host, self._host = self._host, None
            self._link_error = why
            self._pending = None
            self._kick = False
            self._motion = None
            self._watchdog_armed = False
        log.warning("arm %r: link to the UR controller lost: %s", self.name, why)
        if host is not None:
            host.kill()

    # -- state ----------------------------------------------------------------------------------

    def state(self) -> ArmState:
        with self._lock:
            sample = self._sample
            if sample is None:
                return ArmState(timestamp=float(self.clock.now()), T_B_tcp=np.eye(4),
                                tcp_speed=np.zeros(6), connected=False, protective_stop=False,
                                emergency_stop=False, ready=False)
            return ArmState(
                timestamp=sample.ctrl_time + (self._offset or 0.0),
                T_B_tcp=sample.T,
                tcp_speed=sample.twist,
                connected=self._link_up(),
                protective_stop=sample.protective,
                emergency_stop=sample.estop,
                ready=self._refusal() is None,
                tcp_force=sample.wrench,
            )

    @property
    def fault(self) -> str | None:
        """Why the arm cannot obey now (None when ready), in words."""
        with self._lock:
            reason = self._refusal()
            if reason == "disconnected" and self._link_error:
                return f"disconnected: {self._link_error}"
            return reason

    def diagnostics(self) -> dict[str, object]:
        """Link and controller details for the status page."""
        with self._lock:
            s = self._sample
            return {
                "host": self.host,
                "connected": self._link_up(),
                "control_interface": s is not None and s.control,
                "watchdog_armed": self._watchdog_armed,
                "motion": self._motion,
                "robot_mode": None if s is None else _ROBOT_MODES.get(s.robot_mode),
                "safety_mode": None if s is None else _SAFETY_MODES.get(s.safety_mode),
                "program_running": s is not None and s.runtime_state == RuntimeState.PLAYING,
                "controller_time": None if s is None else s.ctrl_time,
                "link_error": self._link_error,
                "command_error": self._cmd_error,
                "reconnects": self.reconnects,
            }

    def _program_running(self) -> bool:
        # Our control program runs on the controller. Call under the lock.
        s = self._sample
        return s is not None and s.control and s.runtime_state == RuntimeState.PLAYING

    def _link_up(self) -> bool:
        # Call under the lock.
        s = self._sample
        return (self._host is not None and not self._connecting and s is not None
                and s.receiving
                and self._link_error is None
                and time.monotonic() - self._fresh_at <= self.stale_timeout)

    def _refusal(self) -> str | None:
        # Why a motion command cannot be obeyed now, or None. Call under the lock.
        reason = self._life.refusal()  # "not started" or "closed"
        if reason is not None:
            return reason
        s = self._sample
        if not self._link_up() or s is None:
            return "disconnected"
        if s.estop:
            return "in emergency stop"
        if s.protective:
            return "in protective stop"
        if not s.control:
            return self._control_error or "without a control interface"
        if s.robot_mode != RobotMode.RUNNING:
            return f"not running (robot mode {_ROBOT_MODES.get(s.robot_mode, '?')})"
        if s.runtime_state != RuntimeState.PLAYING:
            return ("with its control program stopped (by the RTDE watchdog, a fault or the "
                    "pendant; recover() restarts it)")
        if self._cmd_error is not None:
            return self._cmd_error
        return None

    # -- commands -------------------------------------------------------------------------------

    def _servo(self, T_B_tcp: np.ndarray, dt: float) -> None:
        self._post("servo", ("servo", _pose6(T_B_tcp), float(dt)))

    def _speed(self, twist: np.ndarray, accel: float) -> None:
        if accel > _MAX_TOOL_ACCEL:
            raise ArmCommandError(f"arm {self.name!r}: accel must be <= {_MAX_TOOL_ACCEL:g} "
                                  f"m/s^2 (ur_rtde speedL), got {accel!r}")
        self._post("speed", ("speed", twist.tolist(), float(accel)))

    def _post(self, what: str, command: tuple) -> None:
        with self._lock:
            reason = self._refusal()
            if reason is not None:
                raise DriverIOError(f"arm {self.name!r}: {what} refused: arm {reason}")
            self._pending = command
            self._cond.notify_all()

    def _stop(self) -> None:
        with self._lock:
            live = self._life.running
            reachable = self._link_up()
            # With our control program stopped the controller has stopped the arm already.
            if live and reachable and self._program_running() and self._sample is not None:
                speed = float(np.linalg.norm(self._sample.twist[:3]))
                self._pending = ("stop", speed)
                self._cond.notify_all()
        if live and not reachable:
            # Nothing reaches the arm; the controller's watchdog stops it. Not an exception:
            # stop() is on the latched-stop path.
            log.warning("arm %r: stop() while the controller is unreachable; its watchdog "
                        "stops the arm", self.name)

    def kick(self) -> None:
        with self._lock:
            if not self._life.running or not self._link_up():
                reason = self._refusal() or "disconnected"
                raise DriverIOError(f"arm {self.name!r}: kick() failed: arm {reason}")
            if self._watchdog_armed and self._program_running():
                self._kick = True
                self._cond.notify_all()

    # -- the command thread ---------------------------------------------------------------------

    def _kick_interval(self) -> float:
        # Often enough for the watchdog, never within two controller cycles of the last
        # command (the script might not have read it yet).
        return max(2.0 * self._period, self.watchdog_timeout / 5.0)

    def _command_loop(self) -> None:
        while True:
            with self._cond:
                while True:
                    if self._closing.is_set() and self._pending is None:
                        return
                    if self._pending is not None:
                        break
                    if self._kick and time.monotonic() - self._last_sent >= self._kick_interval():
                        break
                    self._cond.wait(0.002 if self._kick else 0.1)
                command, self._pending = self._pending, None
                kick, self._kick = self._kick, False
                host = self._host
                motion, armed = self._motion, self._watchdog_armed
                self._busy = True
            try:
                if host is not None:
                    self._execute(host, command, kick, motion, armed)
            finally:
                with self._cond:
                    self._busy = False
                    self._cond.notify_all()

    def _execute(self, host: _HostProcess, command: tuple | None, kick: bool,
                 motion: str | None, armed: bool) -> None:
        with self._lock:
            if host is not self._host or not self._link_up():
                return
            speed = 0.0 if self._sample is None else float(
                np.linalg.norm(self._sample.twist[:3]))
        try:
            if command is None:
                if kick:
                    self._call(host, "kickWatchdog")
                return
            kind = command[0]
            if kind == "stop":
                self._stop_motion(host, motion, command[1])
                with self._lock:
                    self._motion = None
                return
            if motion is not None and motion != kind:  # switching: end the other first
                self._stop_motion(host, motion, speed)
                with self._lock:
                    self._motion = None
            if not armed:
                if not self._call(host, "setWatchdog", 1.0 / self.watchdog_timeout):
                    return
                with self._lock:
                    self._watchdog_armed = True
            if kind == "servo":
                ok = self._call(host, "servoL", command[1], _SERVO_SPEED, _SERVO_ACCEL,
                                command[2], self.lookahead_time, self.gain)
            else:
                ok = self._call(host, "speedL", command[1], command[2], 0.0)
            if ok:
                with self._lock:
                    self._motion = kind
        except (_HostDead, RuntimeError) as exc:  # ur_rtde lost the link or hangs
            with self._lock:
                if host is self._host and self._link_error is None:
                    self._link_error = f"ur_rtde failed: {exc}"
            log.warning("arm %r: ur_rtde failed: %s", self.name, exc)

    def _stop_motion(self, host: _HostProcess, motion: str | None, speed: float) -> None:
        # Brake hard enough to stand still within half the watchdog timeout: the script does
        # not hear the watchdog register while it brakes.
        decel = min(max(self.stop_decel, speed / (0.5 * self.watchdog_timeout)),
                    _MAX_TOOL_ACCEL)
        if motion == "servo":
            self._call(host, "servoStop", decel, extra=speed / decel)
        elif motion == "speed":
            self._call(host, "speedStop", decel, extra=speed / decel)

    def _call(self, host: _HostProcess, name: str, *args: object, extra: float = 0.0) -> bool:
        ok = bool(host.call(name, *args, timeout=self.command_timeout + extra))
        with self._lock:
            self._last_sent = time.monotonic()
            if not ok and host is self._host and self._cmd_error is None:
                self._cmd_error = (f"refusing commands: the controller did not take {name} "
                                   f"(recover() restarts the control program)")
                log.warning("arm %r: %s", self.name, self._cmd_error)
        return ok

    # -- recovery (operator) --------------------------------------------------------------------

    async def recover(self, *, unlock_protective_stop: bool = True, power_on: bool = True,
                      brake_release: bool = True, restart_program: bool = True,
                      timeout: float = 10.0) -> None:
        """Bring the arm back to ``ready`` through the dashboard server: close the safety
        popup, unlock a protective stop, power on, release the brakes, then restart the
        control program (upload ur_rtde's script again); the next motion command re-arms the
        watchdog. Only on request: the driver never does this by itself.

        Raises:
            DriverIOError: not connected, the e-stop still pressed, or a step refused or not
                reached within ``timeout`` s (the message names the step and the controller's
                answer).
        """
        import anyio.to_thread

        with self._lock:
            if not self._life.running:
                raise DriverIOError(f"arm {self.name!r}: recover() needs a started arm")
        await anyio.to_thread.run_sync(self._recover, unlock_protective_stop, power_on,
                                       brake_release, restart_program, timeout)

    def _recover(self, unlock: bool, power_on: bool, brake_release: bool, restart: bool,
                 timeout: float) -> None:
        from dashboard_client import DashboardClient

        with self._lock:
            sample, connected = self._sample, self._link_up()
        if not connected or sample is None:
            raise DriverIOError(f"arm {self.name!r}: recover() refused: the UR controller at "
                                f"{self.host} is not connected")
        if sample.estop:
            raise DriverIOError(f"arm {self.name!r}: recover() refused: the emergency stop is "
                                f"still pressed (release it at the arm first)")
        log.warning("arm %r: recovery requested (unlock=%s power_on=%s brake_release=%s "
                    "restart=%s)", self.name, unlock, power_on, brake_release, restart)
        db = DashboardClient(self.host, DASHBOARD_PORT, False)
        try:
            db.connect(int(self.connect_timeout * 1000))
        except Exception as exc:
            raise DriverIOError(f"arm {self.name!r}: recover(): cannot connect to the dashboard "
                                f"server at {self.host}:{DASHBOARD_PORT}: {exc}") from exc
        try:
            self._dash(db.closeSafetyPopup, DashboardCommand.CLOSE_SAFETY_POPUP)
            if unlock and sample.protective:
                self._dash(db.unlockProtectiveStop, DashboardCommand.UNLOCK_PROTECTIVE_STOP)
                sample = self._await("the protective stop to clear", timeout,
                                     lambda s: not s.protective)
            if power_on and sample.robot_mode == RobotMode.POWER_OFF:
                self._dash(db.powerOn, DashboardCommand.POWER_ON)
                sample = self._await("power on", timeout,
                                     lambda s: s.robot_mode in (RobotMode.IDLE, RobotMode.RUNNING))
            if brake_release and sample.robot_mode == RobotMode.IDLE:
                self._dash(db.brakeRelease, DashboardCommand.BRAKE_RELEASE)
                self._await("brake release", timeout, lambda s: s.robot_mode == RobotMode.RUNNING)
        finally:
            try:
                db.disconnect()
            except Exception:
                pass
        if restart:
            self._restart_program(timeout)

    def _dash(self, fn: Callable[[], object], what: str) -> None:
        try:
            fn()
        except Exception as exc:
            raise DriverIOError(f"arm {self.name!r}: recover(): dashboard '{what}' refused by "
                                f"the UR controller at {self.host}: {exc}") from exc

    def _await(self, what: str, timeout: float, ok: Callable[[_Sample], bool]) -> _Sample:
        deadline = time.monotonic() + timeout
        while True:
            with self._lock:
                sample = self._sample
            if sample is not None and ok(sample):
                return sample
            if time.monotonic() > deadline:
                raise DriverIOError(f"arm {self.name!r}: recover(): timed out after {timeout:g} "
                                    f"s waiting for {what}")
            time.sleep(0.005)

    def _restart_program(self, timeout: float) -> None:
        with self._lock:
            host, sample = self._host, self._sample
            # Opening the control interface or uploading the script takes a while in the
            # child; its data may pause meanwhile: not a lost link.
            self._quiet_until = time.monotonic() + timeout
        if host is None or sample is None:
            raise DriverIOError(f"arm {self.name!r}: recover(): the UR controller at "
                                f"{self.host} is not connected")
        why = sample.not_ready
        if why is not None:
            raise DriverIOError(f"arm {self.name!r}: recover(): cannot start the control "
                                f"program: {why}")
        try:
            if not sample.control:
                host.call("open_control", timeout=timeout)
            elif not host.call("reuploadScript", timeout=timeout):
                raise DriverIOError(f"arm {self.name!r}: recover(): the controller did not take "
                                    f"the control script")
            self._await("the control program to run", timeout,
                        lambda s: s.control and s.runtime_state == RuntimeState.PLAYING)
        except (_HostDead, RuntimeError) as exc:
            raise DriverIOError(f"arm {self.name!r}: recover(): starting the control program "
                                f"failed: {exc}") from exc
        finally:
            with self._lock:
                self._quiet_until = -math.inf
        with self._lock:
            self._motion = None
            self._watchdog_armed = False
            self._cmd_error = None
            self._control_error = None
        log.warning("arm %r: recovered; control program running", self.name)


def _recv_message(s: socket.socket) -> tuple[int, bytes]:
    """One RTDE message (type, payload) from a blocking socket."""
    size, kind = RTDE_HEADER.unpack(_recv_exact(s, RTDE_HEADER.size))
    return kind, _recv_exact(s, size - 3)


def _recv_exact(s: socket.socket, n: int) -> bytes:
    data = b""
    while len(data) < n:
        chunk = s.recv(n - len(data))
        if not chunk:
            raise ConnectionError("closed by the controller")
        data += chunk
    return data


if __name__ == "__main__" and len(sys.argv) == 5 and sys.argv[1] == "--ur-host":
    # The ur_rtde host process, run from the module under its package name.
    importlib.import_module("oralnav.drivers.arm.ur")._host_main(
        int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]))
