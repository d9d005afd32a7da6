"""The dashboard server (TCP 29999) of the fake controller: a greeting line, then one answer
line per command line.

Commands: ``PolyscopeVersion``, ``get serial number``, ``get robot model``, ``is in remote
control`` (true), ``robotmode``, ``safetymode``, ``safetystatus``, ``running``,
``programState``, ``get loaded program``, ``play`` (restarts the last program if the robot is
ready), ``stop``, ``pause``, ``power on``, ``power off``, ``brake release``, ``unlock
protective stop`` (refused within ``unlock_delay`` s of the stop, with the real server's
sentence), ``close safety popup``, ``close popup``, ``popup``, ``addToLog``, ``restart
safety``, ``isProgramSaved``, ``quit``; anything else gets ``could not understand: '...'``.
Answers follow the real server's wording where ur_rtde checks them
(:data:`~oralnav.drivers.arm.ur_protocol.DASHBOARD_REPLIES`).
"""

from __future__ import annotations

import collections
from collections.abc import Callable

from oralnav.drivers.arm.ur_protocol import (
    DASHBOARD_GREETING,
    DASHBOARD_REPLIES,
    DashboardCommand,
    RobotMode,
    SafetyMode,
)
from oralnav.sim.peers.ur.server import Conn

__all__ = ["DashboardConn", "DashboardServer"]


class DashboardConn(Conn):
    """A dashboard client: one command per line, one answer per line."""

    kind = "dashboard"

    def on_accept(self) -> None:
        """The greeting line."""
        self.send((DASHBOARD_GREETING + "\n").encode())

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


class DashboardServer:
    """The dashboard commands of :class:`~oralnav.sim.peers.ur.controller.FakeURController`."""

    version: tuple[int, ...]
    series: str
    serial_number: str
    unlock_delay: float  # s
    _robot_mode: int
    _safety_mode: int
    _estop_kind: int
    _protective_since: float  # controller s
    _running: bool
    _program_name: str | None
    _program_text: str | None
    _dashboard_log: collections.deque[tuple[str, str]]
    _now: Callable[[], float]
    _event: Callable[..., None]
    _robot_ready: Callable[[], bool]
    _start_program: Callable[[], None]
    _stop_program: Callable[[str], None]

    def _dashboard(self, command: str) -> str:
        """Answer one command line (without its newline) and log both."""
        answer = self._dashboard_answer(command)
        self._dashboard_log.append((command, answer))
        return answer

    def _dashboard_answer(self, command: str) -> str:
        """The answer to ``command``, acting on the controller as the real server does."""
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
        if lower == DashboardCommand.POWER_ON:
            if self._estop_kind:
                return "Failed to execute: power on"
            if self._robot_mode == RobotMode.POWER_OFF:
                self._robot_mode = RobotMode.IDLE
                self._event("power_on")
            return DASHBOARD_REPLIES[DashboardCommand.POWER_ON]
        if lower == "power off":
            self._stop_program("power off")
            self._robot_mode = RobotMode.POWER_OFF
            self._event("power_off")
            return "Powering off"
        if lower == DashboardCommand.BRAKE_RELEASE:
            if self._robot_mode == RobotMode.IDLE:
                self._robot_mode = RobotMode.RUNNING
                self._event("brake_release")
            return DASHBOARD_REPLIES[DashboardCommand.BRAKE_RELEASE]
        if lower == DashboardCommand.UNLOCK_PROTECTIVE_STOP:
            if self._safety_mode == SafetyMode.PROTECTIVE_STOP:
                if self._now() - self._protective_since < self.unlock_delay:
                    return ("Cannot unlock protective stop until 5s after occurrence. Always "
                            "inspect cause of protective stop before unlocking")
                self._safety_mode = SafetyMode.NORMAL
                self._event("protective_stop_unlocked")
            return DASHBOARD_REPLIES[DashboardCommand.UNLOCK_PROTECTIVE_STOP]
        if lower == DashboardCommand.CLOSE_SAFETY_POPUP:
            return DASHBOARD_REPLIES[DashboardCommand.CLOSE_SAFETY_POPUP]
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
