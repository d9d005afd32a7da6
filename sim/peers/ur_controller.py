"""A fake Universal Robots controller that the real ``ur_rtde`` client can drive on loopback.

It speaks the controller's own protocols, the subset ``ur_rtde`` uses
(see ``docs/ur_rtde.md`` for the full list):

- **RTDE** (TCP ``rtde_port``, 30004): protocol version negotiation (v1 and v2), controller
  version, output and input recipe setup (each field answered with its RTDE type, unknown or
  refused fields with ``NOT_FOUND`` / ``IN_USE``), start / pause, output data packages at the
  controller rate (500 Hz e-Series, 125 Hz CB3) decimated to each client's frequency, and
  input data packages (decoded by the client's own input recipes into the input registers).
- **Dashboard server** (TCP ``dashboard_port``, 29999): the text protocol, one line per
  command and per answer (version, serial number, modes, power on/off, brake release, unlock
  protective stop, play / stop / pause, popups, ...).
- **Script ports** (TCP ``script_ports``, 30002 and 30003): URScript programs (``def
  name(): ... end``). The control script ``ur_rtde`` uploads is recognised and *emulated*:
  every controller cycle it reads the command register ``input_int_register_<off>`` and the
  argument registers ``input_double_register_<off>...``, acts, and answers on
  ``output_int_register_<off>`` (1: ready for a command, 2: done with it), as the real script
  does. Emulated commands: servoL (24), speedL (10), servoStop (16), speedStop (15), stopL
  (33), stopJ (34), setWatchdog (35, ``rtde_set_watchdog(..., "stop")``), triggerProtective
  Stop (31) and stopScript (255); any other command is recorded and answered "done" without
  effect. Other programs are recorded and "run" for one cycle.

The arm is a kinematic point: the TCP pose integrates servoL targets (a first-order follower
with time constant ``lookahead_time``) and speedL twists, within speed and acceleration
limits; stops decelerate at the commanded rate. Safety: a protective stop, an emergency stop,
the RTDE input watchdog and a stopped program halt the TCP; the first three also stop the
program (``runtime_state`` STOPPED), as on a real controller, so a client must recover
(unlock, power on, brake release) and upload its script again.

Injections for tests: :meth:`~FakeURController.inject_protective_stop`,
:meth:`~FakeURController.inject_emergency_stop` / :meth:`~FakeURController.release_emergency_stop`,
:meth:`~FakeURController.vanish` (close every connection and stop listening: the controller
is gone) / :meth:`~FakeURController.come_back`, :meth:`~FakeURController.kill_connections`,
:meth:`~FakeURController.freeze` (connections stay open, nothing is sent),
:meth:`~FakeURController.refuse_field` (a recipe field answered ``NOT_FOUND`` or ``IN_USE``),
:meth:`~FakeURController.apply_wrench`. Everything the clients send is recorded:
:meth:`~FakeURController.commands`, :meth:`~FakeURController.programs`,
:meth:`~FakeURController.dashboard_log`, :meth:`~FakeURController.events`.

Why a process. ``ur_rtde``'s Python constructors (``RTDEControlInterface(...)``,
``RTDEReceiveInterface(...)``) do all their network I/O while holding the GIL, so a fake
controller on threads of the *same* interpreter can never answer them. Tests therefore run
the fake with :class:`FakeURControllerProcess`, which starts a :class:`FakeURController` in a
child process (``spawn``) and forwards method calls to it over a pipe. The in-process
:class:`FakeURController` serves any client that does not hold the GIL (other processes,
plain sockets). ``python -m oralnav.sim.peers.ur_controller`` runs one from a shell.

Ports. ``ur_rtde`` hard-codes RTDE 30004 and the script port 30003 (only the dashboard port
is an argument of ``DashboardClient``), so a fake for ``ur_rtde`` listens on the standard
ports; give each fake its own loopback address (``127.0.0.2`` ...) to run several at once.
All listening sockets set ``SO_REUSEADDR``, so a fake can be restarted at once on the same
address.
"""

from __future__ import annotations

import collections
import importlib
import logging
import math
import os
import queue
import re
import selectors
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterable
from multiprocessing.connection import Connection
from typing import Any, NamedTuple

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = [
    "CommandRecord",
    "FakeURController",
    "FakeURControllerProcess",
    "RobotMode",
    "RuntimeState",
    "SafetyMode",
]

log = logging.getLogger(__name__)

# --- RTDE protocol ---------------------------------------------------------------------------

_REQUEST_PROTOCOL_VERSION = 86  # 'V'
_GET_URCONTROL_VERSION = 118  # 'v'
_TEXT_MESSAGE = 77  # 'M'
_DATA_PACKAGE = 85  # 'U'
_SETUP_OUTPUTS = 79  # 'O'
_SETUP_INPUTS = 73  # 'I'
_START = 83  # 'S'
_PAUSE = 80  # 'P'

_HEADER = struct.Struct(">HB")

#: RTDE type name -> struct format of one value (big endian, no padding).
_FORMATS = {
    "BOOL": "?",
    "UINT8": "B",
    "UINT32": "I",
    "UINT64": "Q",
    "INT32": "i",
    "DOUBLE": "d",
    "VECTOR3D": "3d",
    "VECTOR6D": "6d",
    "VECTOR6INT32": "6i",
    "VECTOR6UINT32": "6I",
}
_COUNTS = {"VECTOR3D": 3, "VECTOR6D": 6, "VECTOR6INT32": 6, "VECTOR6UINT32": 6}


def _output_fields() -> dict[str, str]:
    fields = {name: "VECTOR6D" for name in (
        "target_q", "target_qd", "target_qdd", "target_current", "target_moment", "actual_q",
        "actual_qd", "actual_current", "joint_control_output", "actual_TCP_pose",
        "actual_TCP_speed", "actual_TCP_force", "target_TCP_pose", "target_TCP_speed",
        "joint_temperatures", "actual_joint_voltage", "ft_raw_wrench", "payload_inertia",
        "actual_current_window", "actual_current_as_torque", "actual_joint_torques",
    )}
    fields.update({name: "DOUBLE" for name in (
        "timestamp", "actual_execution_time", "speed_scaling", "target_speed_fraction",
        "actual_momentum", "actual_main_voltage", "actual_robot_voltage", "actual_robot_current",
        "standard_analog_input0", "standard_analog_input1", "standard_analog_output0",
        "standard_analog_output1", "io_current", "tool_analog_input0", "tool_analog_input1",
        "tool_output_current", "tool_temperature", "payload", "speed_scaling_combined",
    )})
    fields.update({name: "VECTOR3D" for name in (
        "actual_tool_accelerometer", "elbow_position", "elbow_velocity", "payload_cog",
    )})
    fields.update({name: "UINT64" for name in (
        "actual_digital_input_bits", "actual_digital_output_bits",
    )})
    fields.update({name: "INT32" for name in (
        "robot_mode", "safety_mode", "safety_status", "tool_output_voltage",
    )})
    fields.update({name: "UINT32" for name in (
        "runtime_state", "robot_status_bits", "safety_status_bits", "analog_io_types",
        "tool_mode", "tool_analog_input_types", "output_bit_registers0_to_31",
        "output_bit_registers32_to_63", "input_bit_registers0_to_31",
        "input_bit_registers32_to_63",
    )})
    fields.update({"joint_mode": "VECTOR6INT32", "tool_output_mode": "UINT8"})
    for i in range(48):
        fields[f"output_int_register_{i}"] = "INT32"
        fields[f"output_double_register_{i}"] = "DOUBLE"
        fields[f"input_int_register_{i}"] = "INT32"
        fields[f"input_double_register_{i}"] = "DOUBLE"
    for i in range(64, 128):
        fields[f"output_bit_register_{i}"] = "BOOL"
        fields[f"input_bit_register_{i}"] = "BOOL"
    return fields


def _input_fields() -> dict[str, str]:
    fields = {
        "speed_slider_mask": "UINT32", "speed_slider_fraction": "DOUBLE",
        "standard_digital_output_mask": "UINT8", "standard_digital_output": "UINT8",
        "configurable_digital_output_mask": "UINT8", "configurable_digital_output": "UINT8",
        "tool_digital_output_mask": "UINT8", "tool_digital_output": "UINT8",
        "standard_analog_output_mask": "UINT8", "standard_analog_output_type": "UINT8",
        "standard_analog_output_0": "DOUBLE", "standard_analog_output_1": "DOUBLE",
        "input_bit_registers0_to_31": "UINT32", "input_bit_registers32_to_63": "UINT32",
        "external_force_torque": "VECTOR6D",
    }
    for i in range(48):
        fields[f"input_int_register_{i}"] = "INT32"
        fields[f"input_double_register_{i}"] = "DOUBLE"
    for i in range(64, 128):
        fields[f"input_bit_register_{i}"] = "BOOL"
    return fields


OUTPUT_FIELDS = _output_fields()
INPUT_FIELDS = _input_fields()


def _zero(rtde_type: str) -> Any:
    n = _COUNTS.get(rtde_type)
    if n is None:
        return False if rtde_type == "BOOL" else 0
    return (0.0,) * n if rtde_type.endswith("D") else (0,) * n


# --- controller modes (the values RTDE reports) -----------------------------------------------


class RobotMode:
    """``robot_mode`` values."""

    NO_CONTROLLER = -1
    DISCONNECTED = 0
    CONFIRM_SAFETY = 1
    BOOTING = 2
    POWER_OFF = 3
    POWER_ON = 4
    IDLE = 5
    BACKDRIVE = 6
    RUNNING = 7

    NAMES = {-1: "NO_CONTROLLER", 0: "DISCONNECTED", 1: "CONFIRM_SAFETY", 2: "BOOTING",
             3: "POWER_OFF", 4: "POWER_ON", 5: "IDLE", 6: "BACKDRIVE", 7: "RUNNING"}


class SafetyMode:
    """``safety_mode`` / ``safety_status`` values."""

    NORMAL = 1
    REDUCED = 2
    PROTECTIVE_STOP = 3
    RECOVERY = 4
    SAFEGUARD_STOP = 5
    SYSTEM_EMERGENCY_STOP = 6
    ROBOT_EMERGENCY_STOP = 7
    VIOLATION = 8
    FAULT = 9

    NAMES = {1: "NORMAL", 2: "REDUCED", 3: "PROTECTIVE_STOP", 4: "RECOVERY",
             5: "SAFEGUARD_STOP", 6: "SYSTEM_EMERGENCY_STOP", 7: "ROBOT_EMERGENCY_STOP",
             8: "VIOLATION", 9: "FAULT"}


class RuntimeState:
    """``runtime_state`` values (of the running program)."""

    STOPPING = 0
    STOPPED = 1
    PLAYING = 2
    PAUSING = 3
    PAUSED = 4
    RESUMING = 5


# safety_status_bits
_BIT_NORMAL, _BIT_PROTECTIVE, _BIT_SYSTEM_ESTOP, _BIT_ROBOT_ESTOP, _BIT_ESTOP = 0, 2, 5, 6, 7

# Command ids of ur_rtde's control script (the ones the fake knows by name).
_CMD_NAMES = {
    0: "no_cmd", 1: "moveJ", 2: "moveJ_IK", 3: "moveL", 4: "moveL_FK", 6: "forceMode",
    7: "forceModeStop", 8: "zeroFtSensor", 9: "speedJ", 10: "speedL", 11: "servoJ",
    12: "servoC", 15: "speedStop", 16: "servoStop", 17: "setPayload", 24: "servoL",
    29: "setTcp", 31: "triggerProtectiveStop", 33: "stopL", 34: "stopJ", 35: "setWatchdog",
    255: "stopScript",
}
# Commands the script runs "in real time": processed every cycle, answered "ready" at once.
_REALTIME = frozenset({6, 9, 10, 11, 24, 25, 26, 27, 38, 58, 66})
_READY, _DONE = 1, 2


class CommandRecord(NamedTuple):
    """One input package that carried a script command.

    ``time`` is the controller's clock (s, as its ``timestamp`` output), ``name`` the
    command (``servoL``, ``speedL``, ``no_cmd`` for a clear or a watchdog kick, ``cmd_<n>``
    for one the fake does not name) and ``args`` its decoded arguments.
    """

    time: float
    name: str
    args: dict


# --- the arm: a kinematic TCP -------------------------------------------------------------------


def _clip_norm(v: np.ndarray, limit: float) -> np.ndarray:
    n = float(np.linalg.norm(v))
    return v * (limit / n) if n > limit else v


class _TcpPoint:
    """The TCP as a point with an orientation, moved by servo targets, twists and stops."""

    def __init__(self, pose6: Iterable[float], max_speed: float, max_angular_speed: float,
                 max_accel: float, max_angular_accel: float) -> None:
        pose6 = np.asarray(list(pose6), dtype=float)
        self.p = pose6[:3].copy()
        self.R = Rotation.from_rotvec(pose6[3:])
        self.v = np.zeros(3)
        self.w = np.zeros(3)
        self.vmax, self.wmax = max_speed, max_angular_speed
        self.amax, self.alphamax = max_accel, max_angular_accel
        self.mode = "hold"
        self.target_p = self.p.copy()
        self.target_R = self.R
        self.tau = 0.1
        self.cmd_v = np.zeros(3)
        self.cmd_w = np.zeros(3)
        self.accel = max_accel
        self.angular_accel = max_angular_accel

    def pose6(self) -> tuple[float, ...]:
        return (*self.p.tolist(), *self.R.as_rotvec().tolist())

    def target6(self) -> tuple[float, ...]:
        if self.mode == "servo":
            return (*self.target_p.tolist(), *self.target_R.as_rotvec().tolist())
        return self.pose6()

    def twist(self) -> tuple[float, ...]:
        return (*self.v.tolist(), *self.w.tolist())

    def set_pose(self, pose6: Iterable[float]) -> None:
        pose6 = np.asarray(list(pose6), dtype=float)
        self.p = pose6[:3].copy()
        self.R = Rotation.from_rotvec(pose6[3:])
        self.v, self.w, self.mode = np.zeros(3), np.zeros(3), "hold"

    def servo(self, pose6: np.ndarray, lookahead_time: float) -> None:
        if not np.isfinite(pose6).all():
            return
        self.mode = "servo"
        self.target_p = pose6[:3].copy()
        self.target_R = Rotation.from_rotvec(pose6[3:])
        self.tau = min(max(float(lookahead_time), 0.03), 0.2) if math.isfinite(
            lookahead_time) else 0.1

    def speed(self, twist: np.ndarray, accel: float) -> None:
        if not np.isfinite(twist).all():
            return
        self.mode = "speed"
        self.cmd_v = _clip_norm(twist[:3], self.vmax)
        self.cmd_w = _clip_norm(twist[3:], self.wmax)
        accel = float(accel) if math.isfinite(accel) and accel > 0 else self.amax
        self.accel = min(accel, self.amax)
        self.angular_accel = min(accel, self.alphamax)

    def stop(self, decel: float | None = None) -> None:
        """Decelerate to a stand-still at ``decel`` (m/s^2; default the limit)."""
        if self.mode == "hold":
            return
        decel = self.amax if decel is None or not math.isfinite(decel) or decel <= 0 else decel
        self.mode = "stop"
        self.accel = float(decel)
        self.angular_accel = float(decel) * self.alphamax / self.amax

    @property
    def stopped(self) -> bool:
        return self.mode == "hold"

    def step(self, h: float) -> None:
        if self.mode == "hold":
            return
        a, alpha = self.amax, self.alphamax
        if self.mode == "servo":
            e = self.target_p - self.p
            d = float(np.linalg.norm(e))
            speed = min(self.vmax, d / max(self.tau, h), math.sqrt(a * d))
            v_set = e * (speed / d) if d > 0 else e
            e_r = (self.target_R * self.R.inv()).as_rotvec()
            d_r = float(np.linalg.norm(e_r))
            w_speed = min(self.wmax, d_r / max(self.tau, h), math.sqrt(alpha * d_r))
            w_set = e_r * (w_speed / d_r) if d_r > 0 else e_r
        elif self.mode == "speed":
            v_set, w_set = self.cmd_v, self.cmd_w
            a, alpha = self.accel, self.angular_accel
        else:  # "stop"
            v_set, w_set = np.zeros(3), np.zeros(3)
            a, alpha = self.accel, self.angular_accel
        self.v = self.v + _clip_norm(v_set - self.v, a * h)
        self.w = self.w + _clip_norm(w_set - self.w, alpha * h)
        self.p = self.p + self.v * h
        if np.any(self.w):
            self.R = Rotation.from_rotvec(self.w * h) * self.R
        if self.mode == "stop" and not np.any(self.v) and not np.any(self.w):
            self.mode = "hold"


# --- connections ------------------------------------------------------------------------------


class _Conn:
    """One accepted TCP connection with its outgoing buffer (sockets are non-blocking)."""

    kind = "?"
    MAX_BACKLOG = 1 << 20  # bytes of unsent data before data packages are dropped

    def __init__(self, ctrl: FakeURController, sock: socket.socket, peer: Any) -> None:
        self.ctrl, self.sock, self.peer = ctrl, sock, peer
        self.inbuf = bytearray()
        self.outbuf = bytearray()
        self.closed = False

    def fileno(self) -> int:
        return self.sock.fileno()

    def send(self, data: bytes, droppable: bool = False) -> None:
        if self.closed or (droppable and len(self.outbuf) > self.MAX_BACKLOG):
            return
        self.outbuf += data
        self.flush()

    def flush(self) -> None:
        while self.outbuf and not self.closed:
            try:
                n = self.sock.send(self.outbuf)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                self.ctrl._drop(self)
                return
            del self.outbuf[:n]
        self.ctrl._want_write(self, bool(self.outbuf))

    def on_readable(self) -> None:
        try:
            data = self.sock.recv(65536)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            data = b""
        if not data:
            self.ctrl._drop(self)
            return
        self.inbuf += data
        self.handle()

    def handle(self) -> None:
        raise NotImplementedError


class _RTDEConn(_Conn):
    kind = "rtde"

    def __init__(self, *args: Any) -> None:
        super().__init__(*args)
        self.protocol = 1
        self.out_names: list[str] = []
        self.out_struct: struct.Struct | None = None
        self.out_every = 1
        self.out_recipe = 0
        self.in_recipes: dict[int, tuple[list[str], struct.Struct]] = {}
        self.started = False

    def handle(self) -> None:
        while len(self.inbuf) >= 3:
            size, kind = _HEADER.unpack_from(self.inbuf)
            if size < 3:  # garbage: a real controller would drop the client
                self.ctrl._drop(self)
                return
            if len(self.inbuf) < size:
                return
            payload = bytes(self.inbuf[3:size])
            del self.inbuf[:size]
            self.message(kind, payload)
            if self.closed:
                return

    def reply(self, kind: int, payload: bytes = b"") -> None:
        self.send(_HEADER.pack(3 + len(payload), kind) + payload)

    def message(self, kind: int, payload: bytes) -> None:
        ctrl = self.ctrl
        if kind == _REQUEST_PROTOCOL_VERSION:
            version = struct.unpack(">H", payload[:2])[0] if len(payload) >= 2 else 0
            ok = version in (1, 2)
            if ok:
                self.protocol = version
            self.reply(kind, struct.pack(">B", ok))
        elif kind == _GET_URCONTROL_VERSION:
            self.reply(kind, struct.pack(">IIII", *ctrl.version))
        elif kind == _SETUP_OUTPUTS:
            if self.protocol >= 2:
                frequency = struct.unpack(">d", payload[:8])[0] if len(payload) >= 8 else 0.0
                names_raw = payload[8:]
            else:
                frequency, names_raw = ctrl.frequency, payload
            names = [n for n in names_raw.decode("ascii", "replace").split(",") if n]
            types = [ctrl._field_answer(n, OUTPUT_FIELDS) for n in names]
            ok = bool(names) and all(t in _FORMATS for t in types) and frequency > 0
            if ok and not self.started:
                self.out_names = names
                self.out_struct = struct.Struct(">B" + "".join(_FORMATS[t] for t in types))
                self.out_every = max(1, round(ctrl.frequency / min(frequency, ctrl.frequency)))
                self.out_recipe = 1
            ctrl._event("rtde_setup_outputs", names=names, frequency=frequency, accepted=ok)
            self.reply(kind, struct.pack(">B", 1 if ok else 0) + ",".join(types).encode())
        elif kind == _SETUP_INPUTS:
            names = [n for n in payload.decode("ascii", "replace").split(",") if n]
            types = [ctrl._field_answer(n, INPUT_FIELDS) for n in names]
            ok = bool(names) and all(t in _FORMATS for t in types)
            recipe = 0
            if ok:
                recipe = len(self.in_recipes) + 1
                fmt = ">B" + "".join(_FORMATS[t] for t in types)
                self.in_recipes[recipe] = (names, struct.Struct(fmt))
            else:
                ctrl._event("rtde_setup_inputs_refused", names=names, types=types)
            self.reply(kind, struct.pack(">B", recipe) + ",".join(types).encode())
        elif kind == _START:
            ok = self.out_struct is not None
            self.reply(kind, struct.pack(">B", ok))
            self.started = ok
        elif kind == _PAUSE:
            self.started = False
            self.reply(kind, struct.pack(">B", 1))
        elif kind == _DATA_PACKAGE:
            self.input_package(payload)
        elif kind == _TEXT_MESSAGE:
            pass
        else:
            ctrl._event("rtde_unknown_package", kind=kind)

    def input_package(self, payload: bytes) -> None:
        if not payload:
            return
        recipe = self.in_recipes.get(payload[0])
        if recipe is None:
            self.ctrl._event("rtde_unknown_input_recipe", recipe=payload[0])
            return
        names, fmt = recipe
        if len(payload) != fmt.size:
            self.ctrl._event("rtde_bad_input_package", recipe=payload[0], size=len(payload),
                             expected=fmt.size)
            return
        flat = fmt.unpack(payload)[1:]
        values: dict[str, Any] = {}
        i = 0
        for name in names:
            n = _COUNTS.get(INPUT_FIELDS[name], 1)
            values[name] = flat[i] if n == 1 else tuple(flat[i:i + n])
            i += n
        self.ctrl._apply_inputs(values)

    def data_package(self, values: dict[str, Any]) -> None:
        assert self.out_struct is not None
        flat: list[Any] = [self.out_recipe]
        for name in self.out_names:
            value = values.get(name)
            if value is None:
                value = self.ctrl._output_value(name)
            if isinstance(value, tuple):
                flat.extend(value)
            else:
                flat.append(value)
        body = self.out_struct.pack(*flat)
        self.send(_HEADER.pack(3 + len(body), _DATA_PACKAGE) + body, droppable=True)


class _DashboardConn(_Conn):
    kind = "dashboard"

    def handle(self) -> None:
        while b"\n" in self.inbuf:
            line, _, rest = bytes(self.inbuf).partition(b"\n")
            self.inbuf = bytearray(rest)
            command = line.decode("utf-8", "replace").strip()
            answer = self.ctrl._dashboard(command)
            self.send((answer + "\n").encode())
            if command == "quit":
                self.ctrl._drop(self)
                return


class _ScriptConn(_Conn):
    kind = "script"
    _PROGRAM = re.compile(r"^(def|sec)\s+(\w+)\s*\(\s*\)\s*:[^\n]*\n(.*?)^end[ \t]*(\n|$)",
                          re.S | re.M)

    def handle(self) -> None:
        text = self.inbuf.decode("utf-8", "replace")
        while True:
            m = self._PROGRAM.search(text)
            if m is None or (m.group(4) == "" and not text.endswith("end")):
                break
            self.ctrl._program_received(m.group(2), m.group(0), self.sock.getsockname()[1])
            text = text[m.end():]
        self.inbuf = bytearray(text.encode())


# --- the controller ---------------------------------------------------------------------------


class FakeURController:
    """A fake UR controller on ``host`` (see the module docstring).

    Args:
        host: the address to listen on (a loopback address).
        rtde_port, dashboard_port: TCP ports of the RTDE interface and the dashboard server.
        script_ports: TCP ports that accept URScript programs (secondary 30002, real-time
            30003).
        series: ``"e"`` (e-Series: 500 Hz, version 5.15) or ``"cb3"`` (125 Hz, version 3.15).
        version: (major, minor, bugfix, build) to report instead of the series' default.
        frequency: controller cycle rate, Hz (default 500 e-Series, 125 CB3).
        home: initial TCP pose, ``[x, y, z, rx, ry, rz]`` (m, rotation vector) or a 4x4.
        max_speed, max_angular_speed, max_accel, max_angular_accel: the TCP's limits (m/s,
            rad/s, m/s^2, rad/s^2).
        unlock_delay: s after a protective stop before the dashboard may unlock it (5 s on a
            real controller).
        script_start_delay: s between receiving the control script and running it.
        serial_number: what ``get serial number`` answers.
        log_size: records kept in each log.
    """

    def __init__(self, host: str = "127.0.0.1", *, rtde_port: int = 30004,
                 dashboard_port: int = 29999, script_ports: Iterable[int] = (30002, 30003),
                 series: str = "e", version: tuple[int, int, int, int] | None = None,
                 frequency: float | None = None,
                 home: Iterable[float] | np.ndarray | None = None,
                 max_speed: float = 1.0, max_angular_speed: float = 3.0,
                 max_accel: float = 10.0, max_angular_accel: float = 30.0,
                 unlock_delay: float = 0.0, script_start_delay: float = 0.02,
                 serial_number: str = "20235500042", log_size: int = 50_000) -> None:
        if series not in ("e", "cb3"):
            raise ValueError(f"series must be 'e' or 'cb3', got {series!r}")
        self.host = host
        self.rtde_port, self.dashboard_port = int(rtde_port), int(dashboard_port)
        self.script_ports = tuple(int(p) for p in script_ports)
        self.series = series
        self.version = tuple(version) if version is not None else (
            (5, 15, 0, 116283) if series == "e" else (3, 15, 8, 106339))
        self.frequency = float(frequency or (500.0 if series == "e" else 125.0))
        self.period = 1.0 / self.frequency
        self.unlock_delay = float(unlock_delay)
        self.script_start_delay = float(script_start_delay)
        self.serial_number = str(serial_number)
        if home is None:
            home6 = np.array([0.4, 0.0, 0.3, math.pi, 0.0, 0.0])  # tool z down
        else:
            h = np.asarray(home, dtype=float)
            home6 = (np.concatenate([h[:3, 3], Rotation.from_matrix(h[:3, :3]).as_rotvec()])
                     if h.shape == (4, 4) else h.reshape(6))
        self._tcp = _TcpPoint(home6, max_speed, max_angular_speed, max_accel, max_angular_accel)
        self._lock = threading.RLock()
        self._sel: selectors.BaseSelector | None = None
        self._thread: threading.Thread | None = None
        self._listeners: list[socket.socket] = []
        self._conns: set[_Conn] = set()
        self._actions: queue.Queue[tuple[Callable[[], Any], threading.Event, list]] = (
            queue.Queue())
        self._wake_r: socket.socket | None = None
        self._wake_w: socket.socket | None = None
        self._stopping = False
        self._frozen = False
        # Controller state.
        self._tick = 0
        self._overruns = 0
        self._robot_mode = RobotMode.RUNNING
        self._safety_mode = SafetyMode.NORMAL
        self._estop_kind = 0  # SafetyMode of the open e-stop, 0 when closed
        self._protective_since = -math.inf
        self._wrench = (0.0,) * 6
        self._refused: dict[str, str] = {}
        self._inputs: dict[str, Any] = {}
        self._input_time: dict[str, float] = {}
        self._out_int = [0] * 48
        self._out_double = [0.0] * 48
        # The control script (emulated) and the program state.
        self._program_name: str | None = None
        self._program_text: str | None = None
        self._program_is_rtde = False
        self._running = False
        self._pending_start: float | None = None
        self._off = 0
        self._executing = False
        self._busy_stop = False
        self._servoing = False
        self._speeding = False
        self._watchdog: tuple[str, float, float] | None = None  # (variable, min Hz, armed at)
        # Logs.
        self._commands: collections.deque[CommandRecord] = collections.deque(maxlen=log_size)
        self._events: collections.deque[tuple[float, str, dict]] = collections.deque(
            maxlen=log_size)
        self._programs: collections.deque[tuple[float, int, str, str]] = collections.deque(
            maxlen=100)
        self._dashboard_log: collections.deque[tuple[str, str]] = collections.deque(
            maxlen=log_size)

    # -- lifecycle --------------------------------------------------------------------------------

    def start(self) -> None:
        """Bind the ports and start the controller thread (raises ``OSError`` when a port is
        taken)."""
        if self._thread is not None:
            raise RuntimeError("FakeURController already started")
        self._sel = selectors.DefaultSelector()
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._sel.register(self._wake_r, selectors.EVENT_READ, None)
        self._stopping = False
        try:
            self._listen()
        except OSError:
            self._close_all()
            raise
        self._thread = threading.Thread(target=self._run, name="fake-ur-controller", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Close every socket and stop the thread. Idempotent."""
        thread = self._thread
        if thread is None:
            return
        self._stopping = True
        self._wake()
        thread.join(5.0)
        self._thread = None
        self._close_all()

    def __enter__(self) -> FakeURController:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _listen(self) -> None:
        assert self._sel is not None
        ports = [(self.rtde_port, _RTDEConn), (self.dashboard_port, _DashboardConn)]
        ports += [(p, _ScriptConn) for p in self.script_ports]
        for port, cls in ports:
            srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                srv.bind((self.host, port))
                srv.listen(8)
            except OSError as exc:
                srv.close()
                raise OSError(exc.errno, f"fake UR controller cannot listen on "
                                         f"{self.host}:{port}: {exc.strerror}") from None
            srv.setblocking(False)
            self._listeners.append(srv)
            self._sel.register(srv, selectors.EVENT_READ, cls)

    def _unlisten(self) -> None:
        for srv in self._listeners:
            if self._sel is not None:
                try:
                    self._sel.unregister(srv)
                except (KeyError, ValueError):
                    pass
            srv.close()
        self._listeners.clear()

    def _close_all(self) -> None:
        with self._lock:
            for conn in list(self._conns):
                self._drop(conn)
            self._unlisten()
            for s in (self._wake_r, self._wake_w):
                if s is not None:
                    s.close()
            self._wake_r = self._wake_w = None
            if self._sel is not None:
                self._sel.close()
                self._sel = None

    def _wake(self) -> None:
        w = self._wake_w
        if w is not None:
            try:
                w.send(b"x")
            except OSError:
                pass

    def _in_loop(self, fn: Callable[[], Any], timeout: float = 5.0) -> Any:
        """Run ``fn`` on the controller thread (socket changes) and return its result."""
        if self._thread is None or threading.current_thread() is self._thread:
            with self._lock:
                return fn()
        done, box = threading.Event(), []
        self._actions.put((fn, done, box))
        self._wake()
        if not done.wait(timeout):
            raise TimeoutError("fake UR controller thread did not answer")
        if box and isinstance(box[0], BaseException):
            raise box[0]
        return box[0] if box else None

    # -- the controller thread ---------------------------------------------------------------------

    def _run(self) -> None:
        sel = self._sel
        assert sel is not None
        next_tick = time.monotonic() + self.period
        while not self._stopping:
            timeout = max(0.0, next_tick - time.monotonic())
            try:
                events = sel.select(timeout)
            except (OSError, ValueError):
                events = []
            with self._lock:
                for key, mask in events:
                    self._dispatch(key, mask)
                self._run_actions()
                now = time.monotonic()
                if now >= next_tick:
                    n = int((now - next_tick) / self.period) + 1
                    if n > 1:
                        self._overruns += 1
                    try:
                        self._cycle(min(n, 25))
                    except Exception:  # a bug here must not kill the controller
                        log.exception("fake UR controller: cycle failed")
                    next_tick += n * self.period

    def _run_actions(self) -> None:
        while True:
            try:
                fn, done, box = self._actions.get_nowait()
            except queue.Empty:
                return
            try:
                box.append(fn())
            except BaseException as exc:  # handed back to the caller
                box.append(exc)
            done.set()

    def _dispatch(self, key: selectors.SelectorKey, mask: int) -> None:
        obj = key.data
        if obj is None:  # the wake-up pipe
            try:
                while key.fileobj.recv(4096):  # type: ignore[union-attr]
                    pass
            except (BlockingIOError, OSError):
                pass
            return
        if isinstance(obj, type):  # a listening socket: obj is the connection class
            try:
                sock, peer = key.fileobj.accept()  # type: ignore[union-attr]
            except (BlockingIOError, OSError):
                return
            sock.setblocking(False)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            conn = obj(self, sock, peer)
            self._conns.add(conn)
            assert self._sel is not None
            self._sel.register(sock, selectors.EVENT_READ, conn)
            self._event("connect", kind=conn.kind, port=sock.getsockname()[1])
            if isinstance(conn, _DashboardConn):
                conn.send(b"Connected: Universal Robots Dashboard Server\n")
            return
        if mask & selectors.EVENT_WRITE:
            obj.flush()
        if mask & selectors.EVENT_READ and not obj.closed:
            obj.on_readable()

    def _want_write(self, conn: _Conn, want: bool) -> None:
        if conn.closed or self._sel is None:
            return
        events = selectors.EVENT_READ | (selectors.EVENT_WRITE if want else 0)
        try:
            if self._sel.get_key(conn.sock).events != events:
                self._sel.modify(conn.sock, events, conn)
        except (KeyError, ValueError):
            pass

    def _drop(self, conn: _Conn) -> None:
        if conn.closed:
            return
        conn.closed = True
        self._conns.discard(conn)
        if self._sel is not None:
            try:
                self._sel.unregister(conn.sock)
            except (KeyError, ValueError):
                pass
        try:
            conn.sock.close()
        except OSError:
            pass
        self._event("disconnect", kind=conn.kind)

    # -- one controller cycle ----------------------------------------------------------------------

    def _now(self) -> float:
        return self._tick * self.period

    def _cycle(self, n: int) -> None:
        self._tick += n
        if self._pending_start is not None and self._now() >= self._pending_start:
            self._pending_start = None
            self._start_program()
        if self._running:
            self._script_cycle()
        self._check_watchdog()
        for _ in range(n):
            self._tcp.step(self.period)
        if self._frozen:
            return
        values = self._outputs()
        for conn in list(self._conns):
            if isinstance(conn, _RTDEConn) and conn.started and self._tick % conn.out_every == 0:
                conn.data_package(values)

    def _safety_bits(self) -> int:
        mode = self._safety_mode
        bits = 0
        if mode == SafetyMode.NORMAL:
            bits |= 1 << _BIT_NORMAL
        if mode == SafetyMode.PROTECTIVE_STOP:
            bits |= 1 << _BIT_PROTECTIVE
        if self._estop_kind == SafetyMode.SYSTEM_EMERGENCY_STOP:
            bits |= (1 << _BIT_SYSTEM_ESTOP) | (1 << _BIT_ESTOP)
        if self._estop_kind == SafetyMode.ROBOT_EMERGENCY_STOP:
            bits |= (1 << _BIT_ROBOT_ESTOP) | (1 << _BIT_ESTOP)
        return bits

    def _robot_bits(self) -> int:
        powered = self._robot_mode in (RobotMode.POWER_ON, RobotMode.IDLE, RobotMode.RUNNING)
        return int(powered) | (int(self._running) << 1)

    def _outputs(self) -> dict[str, Any]:
        pose = self._tcp.pose6()
        twist = self._tcp.twist()
        return {
            "timestamp": self._now(),
            "actual_TCP_pose": pose,
            "target_TCP_pose": self._tcp.target6(),
            "actual_TCP_speed": twist,
            "target_TCP_speed": twist,
            "actual_TCP_force": self._wrench,
            "robot_mode": self._robot_mode,
            "safety_mode": self._safety_mode,
            "safety_status": self._safety_mode,
            "safety_status_bits": self._safety_bits(),
            "robot_status_bits": self._robot_bits(),
            "runtime_state": RuntimeState.PLAYING if self._running else RuntimeState.STOPPED,
        }

    def _output_value(self, name: str) -> Any:
        if name.startswith("output_int_register_"):
            return self._out_int[int(name.rsplit("_", 1)[1])]
        if name.startswith("output_double_register_"):
            return self._out_double[int(name.rsplit("_", 1)[1])]
        if name.startswith("input_"):
            return self._inputs.get(name, _zero(OUTPUT_FIELDS[name]))
        if name in ("speed_scaling", "target_speed_fraction", "speed_scaling_combined"):
            return 1.0
        if name in ("actual_main_voltage", "actual_robot_voltage"):
            return 48.0
        if name == "joint_mode":
            return (253,) * 6 if self._robot_mode == RobotMode.RUNNING else (236,) * 6
        if name == "actual_execution_time":
            return 0.3
        return _zero(OUTPUT_FIELDS[name])

    def _field_answer(self, name: str, table: dict[str, str]) -> str:
        refused = self._refused.get(name)
        if refused is not None:
            return refused
        return table.get(name, "NOT_FOUND")

    def _event(self, what: str, **info: Any) -> None:
        self._events.append((self._now(), what, info))

    # -- inputs and the script's registers ---------------------------------------------------------

    def _in_int(self, i: int) -> int:
        return int(self._inputs.get(f"input_int_register_{i}", 0))

    def _in_double(self, i: int) -> float:
        return float(self._inputs.get(f"input_double_register_{i}", 0.0))

    def _apply_inputs(self, values: dict[str, Any]) -> None:
        now = self._now()
        self._inputs.update(values)
        for name in values:
            self._input_time[name] = now
        cmd_reg = f"input_int_register_{self._off}"
        if cmd_reg in values:
            cmd = int(values[cmd_reg])
            self._commands.append(CommandRecord(now, _CMD_NAMES.get(cmd, f"cmd_{cmd}"),
                                                self._command_args(cmd)))

    def _command_args(self, cmd: int) -> dict:
        o, d = self._off, self._in_double
        if cmd in (24, 11):
            return {"target": [d(o + i) for i in range(6)], "speed": d(o + 6),
                    "acceleration": d(o + 7), "time": d(o + 8), "lookahead_time": d(o + 9),
                    "gain": d(o + 10)}
        if cmd in (10, 9):
            return {"speed": [d(o + i) for i in range(6)], "acceleration": d(o + 6),
                    "time": d(o + 7)}
        if cmd in (15, 16):
            return {"deceleration": d(o)}
        if cmd in (33, 34):
            return {"deceleration": d(o), "asynchronous": bool(self._in_int(o + 1))}
        if cmd == 35:
            return {"min_frequency": d(o)}
        return {}

    def _script_cycle(self) -> None:
        """One pass of the control script's main loop (``rtde_cmd`` ... ``sync()``)."""
        o = self._off
        if self._busy_stop:  # inside a blocking stopl(): done once the TCP stands still
            if self._tcp.stopped:
                self._busy_stop = False
                self._out_int[o] = _DONE
            return
        cmd = self._in_int(o)
        if cmd in _REALTIME:
            self._process(cmd)
            self._out_int[o] = _READY
        elif cmd == 0:
            self._executing = False
            self._out_int[o] = _READY
        elif not self._executing:
            self._executing = True
            keep = self._process(cmd)
            if not keep:
                self._stop_program("stopScript")
            elif not self._busy_stop:
                self._out_int[o] = _DONE

    def _process(self, cmd: int) -> bool:
        """Act on one command; False when the script must end."""
        o, d = self._off, self._in_double
        if cmd == 24:  # servoL
            self._speeding = False
            self._servoing = True
            self._tcp.servo(np.array([d(o + i) for i in range(6)]), d(o + 9))
        elif cmd == 10:  # speedL
            self._servoing = False
            self._speeding = True
            self._tcp.speed(np.array([d(o + i) for i in range(6)]), d(o + 6))
        elif cmd in (15, 16):  # speedStop, servoStop: kill the thread, blocking stopl(a)
            if cmd == 15:
                self._speeding = False
            else:
                self._servoing = False
            self._tcp.stop(d(o))
            self._busy_stop = not self._tcp.stopped
        elif cmd in (33, 34):  # stopL / stopJ: stops moves, not the servo/speed threads
            if not (self._servoing or self._speeding):
                self._tcp.stop(d(o))
                self._busy_stop = not self._in_int(o + 1) and not self._tcp.stopped
        elif cmd == 35:  # setWatchdog -> rtde_set_watchdog(register, f, "stop")
            freq = d(o)
            var = f"input_int_register_{o}"
            if freq > 0:
                self._watchdog = (var, freq, self._now())
                self._input_time.setdefault(var, self._now())
            else:
                self._watchdog = None
            self._event("watchdog_set", variable=var, min_frequency=freq)
        elif cmd == 31:
            self._protective_stop("triggerProtectiveStop")
        elif cmd == 255:
            return False
        else:
            self._event("script_command_not_emulated", cmd=cmd,
                        name=_CMD_NAMES.get(cmd, f"cmd_{cmd}"))
        return True

    def _check_watchdog(self) -> None:
        if self._watchdog is None or not self._running:
            return
        var, freq, armed_at = self._watchdog
        last = max(self._input_time.get(var, armed_at), armed_at)
        if self._now() - last > 1.0 / freq:
            self._event("watchdog_tripped", variable=var, min_frequency=freq,
                        silence=self._now() - last)
            self._stop_program("watchdog")

    # -- programs ----------------------------------------------------------------------------------

    def _robot_ready(self) -> bool:
        return (self._robot_mode == RobotMode.RUNNING and self._safety_mode == SafetyMode.NORMAL
                and not self._estop_kind)

    def _program_received(self, name: str, text: str, port: int) -> None:
        self._programs.append((self._now(), port, name, text))
        self._event("program_received", name=name, port=port, size=len(text))
        if self._running:
            self._stop_program("replaced")
        self._program_name, self._program_text = name, text
        self._program_is_rtde = "rtde_cmd" in text and "signal_ready" in text
        m = re.search(r"global\s+reg_offset_int\s*=\s*(\d+)", text)
        self._off = int(m.group(1)) if m else 0
        self._pending_start = self._now() + self.script_start_delay

    def _start_program(self) -> None:
        if self._program_text is None:
            return
        if not self._robot_ready():
            self._event("program_refused", name=self._program_name,
                        robot_mode=RobotMode.NAMES.get(self._robot_mode),
                        safety_mode=SafetyMode.NAMES.get(self._safety_mode))
            return
        self._running = True
        self._executing = False
        self._busy_stop = False
        self._servoing = self._speeding = False
        self._watchdog = None
        self._event("program_started", name=self._program_name)
        if self._program_is_rtde:
            self._out_int[self._off] = _READY  # signal_ready()
        else:  # not the ur_rtde control script: the fake cannot run it; it ends at once
            self._stop_program("not emulated")

    def _stop_program(self, why: str) -> None:
        if not self._running and self._pending_start is None:
            return
        self._pending_start = None
        self._running = False
        self._busy_stop = False
        self._servoing = self._speeding = False
        self._watchdog = None
        self._tcp.stop()
        self._event("program_stopped", why=why)

    # -- safety ------------------------------------------------------------------------------------

    def _protective_stop(self, why: str) -> None:
        if self._estop_kind:
            return
        self._safety_mode = SafetyMode.PROTECTIVE_STOP
        self._protective_since = self._now()
        self._tcp.stop(3 * self._tcp.amax)
        self._stop_program(f"protective stop ({why})")
        self._event("protective_stop", why=why)

    # -- the dashboard server ----------------------------------------------------------------------

    def _dashboard(self, command: str) -> str:
        answer = self._dashboard_answer(command)
        self._dashboard_log.append((command, answer))
        return answer

    def _dashboard_answer(self, command: str) -> str:
        lower = command.lower()
        mode_name = RobotMode.NAMES.get(self._robot_mode, str(self._robot_mode))
        safety_name = SafetyMode.NAMES.get(self._safety_mode, str(self._safety_mode))
        if lower == "polyscopeversion":
            v = self.version
            return f"URSoftware {v[0]}.{v[1]}.{v[2]}.{v[3]} (Jan 01 2024)"
        if lower == "get serial number":
            return self.serial_number
        if lower == "get robot model":
            return "UR5" if self.series == "cb3" else "UR5e"
        if lower == "is in remote control":
            return "true"
        if lower == "robotmode":
            return f"Robotmode: {mode_name}"
        if lower == "safetymode":
            return f"Safetymode: {safety_name}"
        if lower == "safetystatus":
            return f"Safetystatus: {safety_name}"
        if lower == "running":
            return f"Program running: {'true' if self._running else 'false'}"
        if lower == "programstate":
            name = self._program_name or "<unnamed>"
            return f"{'PLAYING' if self._running else 'STOPPED'} {name}"
        if lower == "get loaded program":
            return (f"Loaded program: {self._program_name}" if self._program_name
                    else "No program loaded")
        if lower == "play":
            if self._program_text is None or not self._robot_ready():
                return "Failed to execute: play"
            self._stop_program("play")
            self._start_program()
            return "Starting program"
        if lower == "stop":
            self._stop_program("dashboard stop")
            return "Stopped"
        if lower == "pause":
            if not self._running:
                return "Failed to execute: pause"
            self._stop_program("dashboard pause")
            return "Pausing program"
        if lower == "power on":
            if self._estop_kind:
                return "Failed to execute: power on"
            if self._robot_mode == RobotMode.POWER_OFF:
                self._robot_mode = RobotMode.IDLE
                self._event("power_on")
            return "Powering on"
        if lower == "power off":
            self._stop_program("power off")
            self._robot_mode = RobotMode.POWER_OFF
            self._event("power_off")
            return "Powering off"
        if lower == "brake release":
            if self._robot_mode == RobotMode.IDLE:
                self._robot_mode = RobotMode.RUNNING
                self._event("brake_release")
            return "Brake releasing"
        if lower == "unlock protective stop":
            if self._safety_mode == SafetyMode.PROTECTIVE_STOP:
                if self._now() - self._protective_since < self.unlock_delay:
                    return ("Cannot unlock protective stop until 5s after occurrence. Always "
                            "inspect cause of protective stop before unlocking")
                self._safety_mode = SafetyMode.NORMAL
                self._event("protective_stop_unlocked")
            return "Protective stop releasing"
        if lower == "close safety popup":
            return "closing safety popup"
        if lower == "close popup":
            return "closing popup"
        if lower.startswith("popup "):
            return "showing popup"
        if lower.startswith("addtolog "):
            return "Added log message"
        if lower == "restart safety":
            return "Restarting safety"
        if lower == "isprogramsaved":
            return f"true {self._program_name or ''}".strip()
        if lower == "quit":
            return "Disconnected"
        return f"could not understand: '{command}'"

    # -- public: state -----------------------------------------------------------------------------

    def address(self) -> str:
        """The host the controller listens on."""
        return self.host

    def timestamp(self) -> float:
        """The controller's clock, s (its ``timestamp`` output)."""
        with self._lock:
            return self._now()

    def pose(self) -> np.ndarray:
        """The TCP pose ``[x, y, z, rx, ry, rz]`` (m, rotation vector)."""
        with self._lock:
            return np.array(self._tcp.pose6())

    def pose_matrix(self) -> np.ndarray:
        """The TCP pose as a 4x4 ``T_B_tcp``."""
        with self._lock:
            T = np.eye(4)
            T[:3, :3] = self._tcp.R.as_matrix()
            T[:3, 3] = self._tcp.p
            return T

    def tcp_speed(self) -> np.ndarray:
        """The TCP twist ``[vx, vy, vz, wx, wy, wz]`` (m/s, rad/s)."""
        with self._lock:
            return np.array(self._tcp.twist())

    def motion(self) -> str:
        """What moves the TCP: ``hold``, ``servo``, ``speed`` or ``stop`` (decelerating)."""
        with self._lock:
            return self._tcp.mode

    def status(self) -> dict[str, Any]:
        """Modes and flags in one snapshot."""
        with self._lock:
            return {
                "time": self._now(),
                "robot_mode": self._robot_mode,
                "safety_mode": self._safety_mode,
                "program_running": self._running,
                "program": self._program_name,
                "watchdog": None if self._watchdog is None else {
                    "variable": self._watchdog[0], "min_frequency": self._watchdog[1]},
                "motion": self._tcp.mode,
                "connections": sorted(c.kind for c in self._conns),
                "listening": bool(self._listeners),
                "frozen": self._frozen,
                "overruns": self._overruns,
            }

    def program_running(self) -> bool:
        with self._lock:
            return self._running

    def watchdog(self) -> dict[str, Any] | None:
        """The armed RTDE watchdog (``variable``, ``min_frequency``) or None."""
        with self._lock:
            return self.status()["watchdog"]

    def commands(self, name: str | None = None, since: float = -math.inf) -> list[CommandRecord]:
        """Script commands received (optionally only ``name``, from controller time
        ``since``), oldest first."""
        with self._lock:
            return [c for c in self._commands
                    if (name is None or c.name == name) and c.time >= since]

    def command_counts(self, since: float = -math.inf) -> dict[str, int]:
        with self._lock:
            return dict(collections.Counter(c.name for c in self._commands if c.time >= since))

    def events(self, what: str | None = None) -> list[tuple[float, str, dict]]:
        """What happened (connections, programs, watchdog trips, stops), oldest first."""
        with self._lock:
            return [e for e in self._events if what is None or e[1] == what]

    def programs(self) -> list[tuple[float, int, str, str]]:
        """Programs received: (controller time, port, name, text)."""
        with self._lock:
            return list(self._programs)

    def dashboard_log(self) -> list[tuple[str, str]]:
        """Dashboard commands and the answers given, oldest first."""
        with self._lock:
            return list(self._dashboard_log)

    def connections(self) -> list[str]:
        """Kinds of the open connections (``rtde``, ``dashboard``, ``script``)."""
        with self._lock:
            return sorted(c.kind for c in self._conns)

    def clear_logs(self) -> None:
        with self._lock:
            self._commands.clear()
            self._events.clear()
            self._dashboard_log.clear()

    # -- public: injections ------------------------------------------------------------------------

    def set_pose(self, pose: Iterable[float] | np.ndarray) -> None:
        """Put the TCP at ``pose`` (6 values or a 4x4), at rest."""
        h = np.asarray(pose, dtype=float)
        pose6 = (np.concatenate([h[:3, 3], Rotation.from_matrix(h[:3, :3]).as_rotvec()])
                 if h.shape == (4, 4) else h.reshape(6))
        with self._lock:
            self._tcp.set_pose(pose6)

    def apply_wrench(self, wrench: Iterable[float]) -> None:
        """What ``actual_TCP_force`` reports (N, N m, base frame)."""
        w = tuple(float(x) for x in wrench)
        if len(w) != 6:
            raise ValueError(f"a wrench is 6 numbers, got {w!r}")
        with self._lock:
            self._wrench = w

    def inject_protective_stop(self) -> None:
        """A protective stop: the TCP brakes, the program stops, ``safety_mode`` 3."""
        with self._lock:
            self._protective_stop("injected")

    def clear_protective_stop(self) -> None:
        """Clear it as from the teach pendant (the program stays stopped)."""
        with self._lock:
            if self._safety_mode == SafetyMode.PROTECTIVE_STOP:
                self._safety_mode = SafetyMode.NORMAL

    def inject_emergency_stop(self, system: bool = False) -> None:
        """The robot's (or, ``system``, the system's) e-stop opens: the TCP brakes, the
        program stops, the arm powers off."""
        with self._lock:
            kind = SafetyMode.SYSTEM_EMERGENCY_STOP if system else SafetyMode.ROBOT_EMERGENCY_STOP
            self._estop_kind = kind
            self._safety_mode = kind
            self._tcp.stop(3 * self._tcp.amax)
            self._stop_program("emergency stop")
            self._robot_mode = RobotMode.POWER_OFF
            self._event("emergency_stop", kind=SafetyMode.NAMES[kind])

    def release_emergency_stop(self) -> None:
        """The e-stop button is released: safety normal, the arm stays powered off."""
        with self._lock:
            if self._estop_kind:
                self._estop_kind = 0
                self._safety_mode = SafetyMode.NORMAL
                self._event("emergency_stop_released")

    def refuse_field(self, name: str, answer: str = "NOT_FOUND") -> None:
        """Answer the recipe field ``name`` with ``answer`` (``NOT_FOUND`` or ``IN_USE``)
        from now on."""
        if answer not in ("NOT_FOUND", "IN_USE"):
            raise ValueError(f"answer must be NOT_FOUND or IN_USE, got {answer!r}")
        with self._lock:
            self._refused[name] = answer

    def accept_all_fields(self) -> None:
        with self._lock:
            self._refused.clear()

    def kill_connections(self) -> None:
        """Close every client connection (the controller keeps listening)."""
        def kill() -> None:
            for conn in list(self._conns):
                self._drop(conn)
            self._event("connections_killed")
        self._in_loop(kill)

    def vanish(self) -> None:
        """The controller goes away: every connection closes and nothing listens. The arm
        goes on (its program keeps running until its watchdog, if armed, stops it)."""
        def gone() -> None:
            for conn in list(self._conns):
                self._drop(conn)
            self._unlisten()
            self._event("vanished")
        self._in_loop(gone)

    def come_back(self) -> None:
        """Listen again after :meth:`vanish`."""
        def back() -> None:
            if not self._listeners:
                self._listen()
                self._event("came_back")
        self._in_loop(back)

    def freeze(self) -> None:
        """Stop sending data packages (connections stay open): a hung controller."""
        with self._lock:
            self._frozen = True

    def unfreeze(self) -> None:
        with self._lock:
            self._frozen = False


# --- the controller in a child process ------------------------------------------------------------


def _serve(recv: Connection, send: Connection) -> None:
    """Child process: build a controller from the first message, then answer method calls
    until told to stop (or until the parent goes away)."""
    try:
        kwargs = recv.recv()
        ctrl = FakeURController(**kwargs)
        ctrl.start()
    except BaseException as exc:
        send.send(("err", exc))
        return
    send.send(("ok", None))
    try:
        while True:
            try:
                name, args, kw = recv.recv()
            except (EOFError, OSError):
                break
            if name == "__stop__":
                break
            try:
                if name.startswith("_") or not callable(getattr(ctrl, name, None)):
                    raise AttributeError(f"FakeURController has no method {name!r}")
                send.send(("ok", getattr(ctrl, name)(*args, **kw)))
            except BaseException as exc:
                send.send(("err", exc))
    finally:
        ctrl.stop()
        try:
            send.send(("ok", None))
        except OSError:
            pass


class FakeURControllerProcess:
    """A :class:`FakeURController` in a child process; its public methods are called through.

    ``FakeURControllerProcess(host="127.0.0.1", **kwargs)`` takes the controller's arguments.
    ``start()`` returns once the ports listen (``OSError`` if one is taken); ``stop()`` ends
    the process. A context manager. ``fake.pose()``, ``fake.inject_protective_stop()`` ...
    run in the child and return its result (numpy arrays and records are copied back). The
    child is ``python -m oralnav.sim.peers.ur_controller --rpc``, talking over two pipes.
    """

    def __init__(self, host: str = "127.0.0.1", *, timeout: float = 20.0,
                 **kwargs: Any) -> None:
        self.host = host
        self.timeout = float(timeout)
        self._kwargs = dict(kwargs, host=host)
        self._proc: subprocess.Popen | None = None
        self._send: Connection | None = None
        self._recv: Connection | None = None
        self._call_lock = threading.Lock()

    def start(self) -> None:
        if self._proc is not None:
            raise RuntimeError("FakeURControllerProcess already started")
        to_child_r, to_child_w = os.pipe()
        to_parent_r, to_parent_w = os.pipe()
        try:
            proc = subprocess.Popen(
                [sys.executable, "-m", "oralnav.sim.peers.ur_controller", "--rpc",
                 str(to_child_r), str(to_parent_w)],
                pass_fds=(to_child_r, to_parent_w), stdin=subprocess.DEVNULL)
        finally:
            os.close(to_child_r)
            os.close(to_parent_w)
        send = Connection(to_child_w, readable=False)
        recv = Connection(to_parent_r, writable=False)
        try:
            send.send(self._kwargs)
            if not recv.poll(self.timeout):
                raise TimeoutError("fake UR controller process did not start")
            status, value = recv.recv()
            if status != "ok":
                raise value
        except BaseException:
            proc.kill()
            proc.wait()
            send.close()
            recv.close()
            raise
        self._proc, self._send, self._recv = proc, send, recv

    def stop(self) -> None:
        """End the child process. Idempotent."""
        proc, send, recv = self._proc, self._send, self._recv
        if proc is None or send is None or recv is None:
            return
        self._proc = self._send = self._recv = None
        try:
            with self._call_lock:
                send.send(("__stop__", (), {}))
                if recv.poll(10.0):
                    recv.recv()
        except (OSError, EOFError):
            pass
        try:
            proc.wait(5.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        send.close()
        recv.close()

    def __enter__(self) -> FakeURControllerProcess:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def call(self, name: str, *args: Any, **kwargs: Any) -> Any:
        """Call ``FakeURController.<name>(*args, **kwargs)`` in the child."""
        with self._call_lock:
            send, recv = self._send, self._recv
            if send is None or recv is None:
                raise RuntimeError("fake UR controller process not started")
            send.send((name, args, kwargs))
            if not recv.poll(self.timeout):
                raise TimeoutError(f"fake UR controller: {name}() did not answer")
            status, value = recv.recv()
        if status != "ok":
            raise value
        return value

    def __getattr__(self, name: str) -> Callable[..., Any]:
        if name.startswith("_"):
            raise AttributeError(name)
        if not callable(getattr(FakeURController, name, None)):
            raise AttributeError(f"FakeURController has no method {name!r}")

        def method(*args: Any, **kwargs: Any) -> Any:
            return self.call(name, *args, **kwargs)

        method.__name__ = name
        return method


def main(argv: list[str] | None = None) -> None:
    """``python -m oralnav.sim.peers.ur_controller [--host H] [--series e|cb3]``: serve until
    interrupted."""
    import argparse

    parser = argparse.ArgumentParser(description="A fake UR controller for ur_rtde clients.")
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--series", choices=("e", "cb3"), default="e")
    parser.add_argument("--dashboard-port", type=int, default=29999)
    parser.add_argument("--rpc", nargs=2, type=int, metavar=("READ_FD", "WRITE_FD"),
                        help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.rpc:
        # Serve from the module under its package name (not __main__), so that what is sent
        # back (CommandRecord ...) unpickles in the parent.
        module = importlib.import_module("oralnav.sim.peers.ur_controller")
        module._serve(Connection(args.rpc[0], writable=False),
                      Connection(args.rpc[1], readable=False))
        return
    logging.basicConfig(level=logging.INFO)
    ctrl = FakeURController(args.host, series=args.series, dashboard_port=args.dashboard_port)
    ctrl.start()
    print(f"fake UR controller ({args.series}-series, {ctrl.frequency:g} Hz) on {args.host}: "
          f"RTDE {ctrl.rtde_port}, dashboard {ctrl.dashboard_port}, scripts "
          f"{', '.join(map(str, ctrl.script_ports))}; Ctrl-C stops it", flush=True)
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        pass
    finally:
        ctrl.stop()


if __name__ == "__main__":
    main()
