"""The daemon's core: safety state, the control process, poses and targets, and what the
REST API asks of them (:class:`~oralnav.daemon.api.Operations`).

``DaemonCore.supervise`` is the supervisor task of the anyio task group. At
``SUPERVISE_HZ`` it reads the control process's status record, the safety inputs and the
daemon-side watchdogs (camera stall, stale poses, pose covariance), and moves the safety
state machine: a stop the loop latched on its own becomes FAULT with the loop's reason, a
pressed e-stop becomes ESTOP, health decides IDLE <-> READY. Every entry into FAULT or
ESTOP fires the latched stop, whose handler tells the control loop to stop at its next
period (``ControlProcess.request_stop``: a shared-memory write, it never blocks).

The core is what the tracking and procedure tasks report to (``publish_pose``,
``set_goal``): it is the one place that knows the state and the newest poses.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from typing import Any

import anyio
import numpy as np

from oralnav.safety.errors import StateError
from oralnav.safety.states import SafetyState, SafetySupervisor
from oralnav.safety.stop import LatchedStop
from oralnav.safety.watchdogs import WatchdogSet

from .api import ProcedureAction, SutureTarget, jsonable
from .control_loop import HIST_BIN_S
from .control_process import ControlProcess
from .shm import decode_reason

log = logging.getLogger(__name__)

#: How often the supervisor task looks at everything (Hz).
SUPERVISE_HZ = 50.0


class DaemonCore:
    """See the module docstring. ``clock`` is the daemon's monotonic clock (s), the one the
    control process and the pose timestamps use."""

    def __init__(self, control: ControlProcess, watchdogs: WatchdogSet, *,
                 inputs: Any = None, clock: Callable[[], float] = time.monotonic) -> None:
        self.control = control
        self.watchdogs = watchdogs
        self.inputs = inputs
        self.clock = clock
        self.supervisor = SafetySupervisor(LatchedStop())
        self.supervisor.stop.add_handler(self._stop_robot, name="control loop")
        self._lock = threading.Lock()
        self._targets: list[SutureTarget] = []
        self._poses: dict[str, dict[str, Any]] = {}
        self._rates: dict[str, float] = {}
        self._watched: set[str] = set()   # poses whose staleness trips (what steers now)
        self._started = clock()
        #: what a running procedure reports (phase, progress), shown in /status
        self.procedure_info: dict[str, Any] = {}

    # -- the latched stop's handler (sync, never blocks) ---------------------------------
    def _stop_robot(self, record: Any) -> None:
        self.control.request_stop(f"{record.source}: {record.reason}")

    # -- reports from the other tasks ----------------------------------------------------
    def publish_pose(self, name: str, T: np.ndarray, stamp: float, *, frame: str,
                     corners: int = 0, sigma_m: float = math.nan,
                     sigma_deg: float = math.nan) -> None:
        """A fresh pose ``T`` (4x4, m) of ``name`` in ``frame``, captured at ``stamp``."""
        with self._lock:
            self._poses[name] = {"T": np.array(T, dtype=float), "stamp": float(stamp),
                                 "frame": frame, "corners": int(corners),
                                 "sigma_mm": sigma_m * 1e3, "sigma_deg": sigma_deg}
        if name in self._watched:
            self.watchdogs.poses.fresh(name, stamp)
        if math.isfinite(sigma_m) and math.isfinite(sigma_deg):
            self.watchdogs.covariance.pose(name, sigma_m, sigma_deg)

    def watch_poses(self, names: set[str]) -> None:
        """Only these poses' staleness trips from now on (those the current stage steers
        by: a field hidden on purpose, like the effector inside the mouth, is no fault)."""
        with self._lock:
            dropped = self._watched - names
            self._watched = set(names)
        for name in dropped:
            self.watchdogs.poses.disarm(name)

    def camera_frame(self, name: str, counter: int) -> None:
        self.watchdogs.cameras.frame(name, counter, self.clock())

    def set_rate(self, name: str, hz: float) -> None:
        with self._lock:
            self._rates[name] = float(hz)

    def pose(self, name: str) -> dict[str, Any] | None:
        with self._lock:
            p = self._poses.get(name)
            return None if p is None else dict(p)

    # -- supervisor task -----------------------------------------------------------------
    def supervise_once(self, now: float) -> None:
        """One look at everything; see the module docstring."""
        sup = self.supervisor
        st = self.control.read_status()
        if not self.control.alive:
            sup.fault(now, "control", "control process is not running")
        elif (st is not None and bool(st["latched"]) and not sup.stop.latched
              and int(st["clear_count_seen"]) == self.control.clears):
            # latched on its own (not by our stop), and not merely a period behind a reset
            sup.fault(now, "control loop", decode_reason(st["stop_reason"]))
        if self.inputs is not None:
            ins = self.inputs.state()
            if ins.estop_pressed:
                sup.estop(now, "e-stop input", "emergency stop pressed"
                          if ins.connected else "e-stop input disconnected (reads pressed)")
        for trip in self.watchdogs.check(now):
            sup.fault(now, trip.name, trip.reason)
        problem = self._health(st)
        if problem is None:
            sup.mark_ready(now)
        else:
            sup.mark_not_ready(now, problem)

    def _health(self, st: np.void | None) -> str | None:
        if st is None or not self.control.alive:
            return "control loop not running"
        if not bool(st["arm_connected"]):
            return "arm not connected"
        if bool(st["protective_stop"]) or bool(st["emergency_stop"]):
            return "arm stopped by its controller"
        return None

    async def supervise(self, *, task_status: anyio.abc.TaskStatus[None] =
                        anyio.TASK_STATUS_IGNORED) -> None:
        task_status.started()
        period = 1.0 / SUPERVISE_HZ
        while True:
            self.supervise_once(self.clock())
            await anyio.sleep(period)

    # -- Operations (REST) ---------------------------------------------------------------
    def status(self) -> dict[str, Any]:
        sup = self.supervisor.snapshot()
        st = self.control.read_status()
        loop: dict[str, Any] = {"running": self.control.alive}
        if st is not None:
            hist = np.array(st["hist"])
            n = int(hist.sum())
            p99 = None
            if n:
                b = int(np.searchsorted(np.cumsum(hist) / n, 0.99))
                p99 = (b + 1) * HIST_BIN_S * 1e3
            loop.update(periods=int(st["periods"]), latched=bool(st["latched"]),
                        stop_reason=decode_reason(st["stop_reason"]) or None,
                        period_error_p99_ms=p99, period_error_max_ms=float(st["err_max"]) * 1e3,
                        periods_off_1ms=int(st["misses"]),
                        arm_connected=bool(st["arm_connected"]),
                        motion_commands=int(st["motion_commands"]))
        with self._lock:
            rates = dict(self._rates)
        return jsonable({"safety": sup, "control_loop": loop, "rates_hz": rates,
                         "uptime_s": self.clock() - self._started,
                         "procedure": dict(self.procedure_info)})

    def poses(self) -> dict[str, Any]:
        now = self.clock()
        out: dict[str, Any] = {}
        with self._lock:
            items = list(self._poses.items())
        for name, p in items:
            out[name] = {"frame": p["frame"], "T": p["T"].tolist(),
                         "age_s": now - p["stamp"], "corners": p["corners"],
                         "sigma_mm": p["sigma_mm"], "sigma_deg": p["sigma_deg"]}
        st = self.control.read_status()
        if st is not None:
            out["tcp"] = {"frame": "B", "T": np.array(st["T_B_tcp"]).tolist(),
                          "age_s": now - float(st["t"])}
        return jsonable(out)

    def telemetry(self) -> dict[str, Any]:
        st = self.control.read_status()
        doc: dict[str, Any] = {"t": self.clock(), "state": self.supervisor.state.value}
        if st is not None:
            doc.update(tcp=np.array(st["T_B_tcp"])[:3, 3].tolist(),
                       tcp_speed=np.array(st["tcp_speed"]).tolist(),
                       wrist=np.array(st["wrist"]).tolist(), latched=bool(st["latched"]))
        return jsonable(doc)

    def estop(self, who: str, reason: str) -> None:
        self.supervisor.estop(self.clock(), f"operator {who}", reason or "REST e-stop")

    def reset(self, who: str) -> None:
        now = self.clock()
        released = True
        if self.inputs is not None:
            released = not self.inputs.state().estop_pressed
        st = self.control.read_status()
        trips = self.watchdogs.check(now)
        problem = self._health(st)
        cleared = not trips and problem is None
        if not cleared:
            why = "; ".join([t.reason for t in trips] + ([problem] if problem else []))
            if self.supervisor.state in (SafetyState.FAULT, SafetyState.ESTOP) and released:
                raise StateError(f"cannot reset: the fault condition is still present ({why})")
        self.supervisor.reset(now, who, estop_released=released, faults_cleared=cleared)
        self.control.clear_stop()
        log.info("reset by %s", who)

    def procedure(self, action: ProcedureAction, who: str) -> None:
        now = self.clock()
        sup = self.supervisor
        if action == "start":
            if not self._targets:
                raise StateError("cannot start: no suture targets registered (POST /targets)")
            sup.start(now, who)
        elif action == "pause":
            sup.pause(now, who)
            self.hold()
        elif action == "resume":
            sup.resume(now, who)
        elif action == "abort":
            sup.abort(now, who)
            self.hold()
        else:  # the API validates the action; this guards direct callers
            raise StateError(f"unknown procedure action {action!r}")

    def targets(self) -> list[SutureTarget]:
        with self._lock:
            return list(self._targets)

    def set_targets(self, targets: list[SutureTarget], who: str) -> None:
        if self.supervisor.state in (SafetyState.RUNNING, SafetyState.PAUSED):
            raise StateError(f"cannot change targets while {self.supervisor.state.value}; "
                             "abort the procedure first")
        with self._lock:
            self._targets = list(targets)
        log.info("%d suture target(s) set by %s", len(targets), who)

    # -- motion (procedure task) ---------------------------------------------------------
    def set_goal(self, T_B_tcp: np.ndarray, t_pose: float, *,
                 near_point: np.ndarray | None = None,
                 wrist: np.ndarray | None = None) -> bool:
        """Ask the loop to move toward ``T_B_tcp`` (m, base frame), computed from poses
        captured at ``t_pose``. Refused (False, the loop holds) unless RUNNING."""
        if not self.supervisor.motion_allowed:
            self.hold()
            return False
        self.control.set_goal(T_B_tcp, t_pose, move=True, near_point=near_point, wrist=wrist)
        return True

    def hold(self) -> None:
        st = self.control.read_status()
        T = np.array(st["T_B_tcp"]) if st is not None else np.eye(4)
        self.control.set_goal(T, self.clock(), move=False)
