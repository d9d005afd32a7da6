"""The script ports (secondary 30002, real-time 30003) of the fake controller, and ur_rtde's
control script, emulated.

A port takes URScript programs (``def name(): ... end`` or ``sec``) and sends nothing back.
A program starts ``script_start_delay`` s after it arrives (replacing a running one) if the
robot is running with no safety stop. ur_rtde's control script is recognised and
*emulated*: every controller cycle it reads the command register
``input_int_register_<off>`` and the argument registers ``input_double_register_<off>...``,
acts, and answers on ``output_int_register_<off>`` (1: ready for a command, 2: done with
it), as the real script does. Emulated commands: servoL (24), speedL (10), servoStop (16),
speedStop (15), stopL (33), stopJ (34), setWatchdog (35, ``rtde_set_watchdog(..., "stop")``),
triggerProtectiveStop (31) and stopScript (255); any other command is recorded and answered
"done" without effect. Other programs are recorded and end at once.
"""

from __future__ import annotations

import collections
import re
from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np

from oralnav.drivers.arm.ur_protocol import RobotMode, SafetyMode
from oralnav.sim.peers.ur.kinematics import TcpPoint
from oralnav.sim.peers.ur.server import Conn

__all__ = ["CommandRecord", "ControlScript", "ScriptConn"]

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


class ScriptConn(Conn):
    """A client of a script port: complete programs go to the controller."""

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


class ControlScript:
    """The program state of :class:`~oralnav.sim.peers.ur.controller.FakeURController` and
    the emulated control script that reads its RTDE input registers."""

    script_start_delay: float  # s
    _tcp: TcpPoint
    _robot_mode: int
    _safety_mode: int
    _estop_kind: int
    _inputs: dict[str, Any]
    _input_time: dict[str, float]  # controller s of the last package setting each input
    _out_int: list[int]
    _program_name: str | None
    _program_text: str | None
    _program_is_rtde: bool
    _running: bool
    _pending_start: float | None
    _off: int
    _executing: bool
    _busy_stop: bool
    _servoing: bool
    _speeding: bool
    _watchdog: tuple[str, float, float] | None
    _commands: collections.deque[CommandRecord]
    _programs: collections.deque[tuple[float, int, str, str]]
    _now: Callable[[], float]
    _event: Callable[..., None]
    _protective_stop: Callable[[str], None]

    # -- inputs and the script's registers ---------------------------------------------------------

    def _in_int(self, i: int) -> int:
        """``input_int_register_<i>`` as last received."""
        return int(self._inputs.get(f"input_int_register_{i}", 0))

    def _in_double(self, i: int) -> float:
        """``input_double_register_<i>`` as last received."""
        return float(self._inputs.get(f"input_double_register_{i}", 0.0))

    def _apply_inputs(self, values: dict[str, Any]) -> None:
        """Take one decoded input package; record a command when it sets the command
        register."""
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
        """The arguments of ``cmd`` from the argument registers, for the record."""
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
        """Stop the program when the watched register went unwritten for a watchdog
        period."""
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
        """A program can start: brakes released, safety normal, no e-stop."""
        return (self._robot_mode == RobotMode.RUNNING and self._safety_mode == SafetyMode.NORMAL
                and not self._estop_kind)

    def _program_received(self, name: str, text: str, port: int) -> None:
        """A complete program arrived on script port ``port``: schedule its start."""
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
        """Start the received program if the robot is ready (else record the refusal)."""
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
        """End the program (pending or running) and brake the TCP."""
        if not self._running and self._pending_start is None:
            return
        self._pending_start = None
        self._running = False
        self._busy_stop = False
        self._servoing = self._speeding = False
        self._watchdog = None
        self._tcp.stop()
        self._event("program_stopped", why=why)
