"""The fake UR controller: its state, its cycle and what tests read from it.

:class:`FakeURController` is assembled from the parts of the package: the socket loop
(:class:`~oralnav.sim.peers.ur.server.ServerLoop`), the RTDE outputs
(:class:`~oralnav.sim.peers.ur.rtde.RTDEOutputs`), the programs and the emulated control
script (:class:`~oralnav.sim.peers.ur.script.ControlScript`), the dashboard server
(:class:`~oralnav.sim.peers.ur.dashboard.DashboardServer`) and the injections
(:class:`~oralnav.sim.peers.ur.injections.Injections`). This module holds the state they
share (created in ``__init__``, guarded by ``_lock``), the controller cycle, the safety
stop they all trigger, and the public queries.

Safety: a protective stop, an emergency stop, the RTDE input watchdog and a stopped program
halt the TCP; the first three also stop the program (``runtime_state`` STOPPED), as on a
real controller, so a client must recover (unlock, power on, brake release) and upload its
script again.
"""

from __future__ import annotations

import collections
import math
import queue
import selectors
import socket
import threading
import time
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np

from oralnav.drivers.arm.ur_protocol import (
    DASHBOARD_PORT,
    REALTIME_PORT,
    RTDE_PORT,
    SECONDARY_PORT,
    RobotMode,
    SafetyMode,
)
from oralnav.sim.peers.ur.dashboard import DashboardConn, DashboardServer
from oralnav.sim.peers.ur.injections import Injections
from oralnav.sim.peers.ur.kinematics import TcpPoint, as_pose6
from oralnav.sim.peers.ur.rtde import RTDEConn, RTDEOutputs
from oralnav.sim.peers.ur.script import CommandRecord, ControlScript, ScriptConn
from oralnav.sim.peers.ur.server import Conn, ServerLoop

__all__ = ["FakeURController"]

#: The most motion steps one catch-up cycle takes (a host stall of many periods).
MAX_SUBSTEPS = 25


class FakeURController(ServerLoop, RTDEOutputs, ControlScript, DashboardServer, Injections):
    """A fake UR controller on ``host`` (see :mod:`oralnav.sim.peers.ur`).

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

    def __init__(self, host: str = "127.0.0.1", *, rtde_port: int = RTDE_PORT,
                 dashboard_port: int = DASHBOARD_PORT,
                 script_ports: Iterable[int] = (SECONDARY_PORT, REALTIME_PORT),
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
            home6 = as_pose6(home)
        self._tcp = TcpPoint(home6, max_speed, max_angular_speed, max_accel, max_angular_accel)
        self._lock = threading.RLock()
        self._sel: selectors.BaseSelector | None = None
        self._thread: threading.Thread | None = None
        self._listeners: list[socket.socket] = []
        self._conns: set[Conn] = set()
        self._actions: queue.Queue[tuple[Callable[[], Any], threading.Event, list]] = (
            queue.Queue())
        self._wake_r: socket.socket | None = None
        self._wake_w: socket.socket | None = None
        self._stopping = False
        self._frozen = False
        # Controller state.
        self._tick = 0
        self._state_host = time.monotonic()
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

    def __enter__(self) -> FakeURController:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _servers(self) -> list[tuple[int, type[Conn]]]:
        """The ports to listen on and the connection class of each, in binding order."""
        ports: list[tuple[int, type[Conn]]] = [(self.rtde_port, RTDEConn),
                                               (self.dashboard_port, DashboardConn)]
        ports += [(p, ScriptConn) for p in self.script_ports]
        return ports

    # -- one controller cycle ----------------------------------------------------------------------

    def _now(self) -> float:
        """The controller's clock, s (``timestamp``): cycles since start times the period."""
        return self._tick * self.period

    def _cycle(self, n: int) -> None:
        """Advance ``n`` controller cycles (more than one to catch up), then send each
        started RTDE client its output package when its decimation is due."""
        self._tick += n
        if self._pending_start is not None and self._now() >= self._pending_start:
            self._pending_start = None
            self._start_program()
        if self._running:
            self._script_cycle()
        self._check_watchdog()
        # the motion covers all n cycles, in at most MAX_SUBSTEPS steps: a host that stalled
        # long costs no more than 25 steps, and the clock still never loses time (a real
        # controller's timestamp is real time, which the driver maps onto its host's clock)
        steps = min(n, MAX_SUBSTEPS)
        for _ in range(steps):
            self._tcp.step(n * self.period / steps)
        # this machine's clock when the state was computed, the instant its output
        # package describes: what a renderer drawing this pose stamps its capture with
        self._state_host = time.monotonic()
        if self._frozen:
            return
        values = self._outputs()
        for conn in list(self._conns):
            if (isinstance(conn, RTDEConn) and conn.started
                    and self._tick // conn.out_every != (self._tick - n) // conn.out_every):
                conn.data_package(values)

    def _event(self, what: str, **info: Any) -> None:
        """Log ``what`` happened (with details) at the controller's time."""
        self._events.append((self._now(), what, info))

    # -- safety ------------------------------------------------------------------------------------

    def _protective_stop(self, why: str) -> None:
        """Enter a protective stop (not during an e-stop): brake at 3x the limit, stop the
        program."""
        if self._estop_kind:
            return
        self._safety_mode = SafetyMode.PROTECTIVE_STOP
        self._protective_since = self._now()
        self._tcp.stop(3 * self._tcp.amax)
        self._stop_program(f"protective stop ({why})")
        self._event("protective_stop", why=why)

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

    def pose_sample(self) -> tuple[np.ndarray, float]:
        """The TCP pose as a 4x4 ``T_B_tcp`` and the instant it describes: this machine's
        ``time.monotonic()`` (s) at the cycle that computed it, the instant its RTDE
        package goes out. A camera simulator that draws the pose stamps its capture with
        it (the newest cycle is up to one period, 8 ms on a CB3, older than the call)."""
        with self._lock:
            T = np.eye(4)
            T[:3, :3] = self._tcp.R.as_matrix()
            T[:3, 3] = self._tcp.p
            return T, self._state_host

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
        """A program (the control script) runs."""
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
        """Script commands received per name (from controller time ``since``)."""
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
        """Forget the commands, events and dashboard exchanges recorded so far."""
        with self._lock:
            self._commands.clear()
            self._events.clear()
            self._dashboard_log.clear()
