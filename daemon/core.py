"""The daemon's core: safety state, the control process, poses and targets, and what the
REST API asks of them (``Operations`` in ``daemon/api.py``).

``DaemonCore.supervise`` is the supervisor task of the anyio task group. At
``SUPERVISE_HZ`` it reads the control process's status record, the safety inputs and the
daemon-side watchdogs (camera stall, stale poses, pose covariance), and moves the safety
state machine: a stop the loop latched on its own becomes FAULT with the loop's reason, a
pressed e-stop becomes ESTOP, health decides IDLE <-> READY. Every entry into FAULT or
ESTOP fires the latched stop, whose handler tells the control loop to stop at its next
period (``ControlProcess.request_stop``: a shared-memory write, it never blocks).

The core is what the tracking and procedure tasks report to (``publish_pose``,
``set_goal``): it is the one place that knows the state and the newest poses.

Guided insertion (GUIDE mode, docs/control_loop.md "Guided insertion"): ``plan_guide``
plans one from a planning scene and keeps it; ``start_guide`` sends the plan to the control
loop (refused unless READY, with a fresh opener pose and the instrument inside the
fixture); each supervision tick then commands GUIDE with the patient's model frame
``T_B_F = T_B_C @ T_C_OM @ T_OM_F`` from the newest tracked opener pose; ``stop_guide``,
any latched stop, or a loop that stops on its own end it (HOLD).

The core is the facade over its pieces: the poses live in a
:class:`~oralnav.daemon.poses.PoseStore`, guided insertion in a
:class:`~oralnav.daemon.guide_session.GuideSession`, the needle procedure in a
:class:`~oralnav.daemon.needle_session.NeedleSession`. The core owns the safety state and
hands each piece what it must know of it.
"""

from __future__ import annotations

import datetime
import logging
import math
import threading
import time
from collections.abc import Callable
from typing import Any

import anyio
import numpy as np

from oralnav.control.navigation.arm_trajectory import ArmTrajectory
from oralnav.daemon.guide_session import GUIDE_POSE, GuideSession
from oralnav.daemon.latency import StageTimes, percentiles_ms
from oralnav.daemon.needle_session import NeedleSession
from oralnav.daemon.poses import PoseStore
from oralnav.daemon.schemas import ProcedureAction, SutureTarget, jsonable
from oralnav.realtime.control_loop import HIST_BIN_S
from oralnav.realtime.control_process import ControlPort
from oralnav.realtime.shm import decode_reason
from oralnav.safety.errors import StateError
from oralnav.safety.states import LATCHED, SafetyState, SafetySupervisor
from oralnav.safety.stop import LatchedStop
from oralnav.safety.watchdogs import WatchdogSet

log = logging.getLogger(__name__)

#: How often the supervisor task looks at everything (Hz).
SUPERVISE_HZ = 50.0


def _iso_utc(unix_s: float) -> str:
    """``unix_s`` (s since the epoch) as ISO 8601 UTC to the millisecond, as the audit log
    writes its times."""
    return datetime.datetime.fromtimestamp(unix_s, datetime.UTC).isoformat(
        timespec="milliseconds").replace("+00:00", "Z")


def _add_utc(safety: dict[str, Any], now: float, wall: float) -> None:
    """Beside each monotonic time of a safety snapshot (``since``, each reason's and
    transition's ``time``, s on the daemon's clock), the same instant in UTC (``*_utc``),
    so that /status lines up with the audit log. ``now`` and ``wall``: one instant on both
    clocks."""
    def utc(t: Any) -> str | None:
        return _iso_utc(wall - (now - t)) if isinstance(t, int | float) and \
            math.isfinite(t) else None

    safety["since_utc"] = utc(safety.get("since"))
    for rec in (*safety.get("reasons", ()), *safety.get("history", ())):
        rec["time_utc"] = utc(rec.get("time"))


class DaemonCore:
    """See the module docstring. ``clock`` is the daemon's monotonic clock (s), the one the
    control process and the pose timestamps use."""

    def __init__(self, control: ControlPort, watchdogs: WatchdogSet, *,
                 inputs: Any = None, clock: Callable[[], float] = time.monotonic,
                 T_B_C: np.ndarray | None = None) -> None:
        self.control = control
        self.watchdogs = watchdogs
        self.inputs = inputs
        self.clock = clock
        self.supervisor = SafetySupervisor(LatchedStop())
        self.supervisor.stop.add_handler(self._stop_robot, name="control loop")
        self._lock = threading.Lock()     # guards the targets
        self._targets: list[SutureTarget] = []
        #: the surgeon's current suture target (``select_target``) and how many selections
        #: were made: the navigation applies each new one once (``daemon/navigation_task.py``)
        self.selected_target: str | None = None
        self.selections = 0
        #: the cell's planned suture targets (its cell file), offered to the operator
        self._planned: list[SutureTarget] = []
        #: the newest tracked poses, the tracking rates and which poses are watched
        self.pose_store = PoseStore(watchdogs, clock, pinned=self._pinned_poses)
        #: each tracked round's capture, arrival and publication (``daemon/latency.py``)
        self.stage_times = StageTimes()
        self._started = clock()
        #: what a running procedure reports (phase, progress), shown in /status
        self.procedure_info: dict[str, Any] = {}
        #: guided insertion: the plan, the phase, the plan's way to and from the loop
        self.guide_session = GuideSession(control, watchdogs, self.pose_store, clock=clock,
                                          hold=self.hold,
                                          start_refused=self._guide_start_refused,
                                          run_refused=self._guide_run_refused)
        if T_B_C is not None:
            self.set_hand_eye(T_B_C)
        # after the control loop's handler: the loop is told to stop before guidance ends
        self.supervisor.stop.add_handler(self.guide_session.on_stop, name="guidance")
        self.needle_session = NeedleSession(self._needle_refused)
        #: the control loop's heartbeat watch (``daemon/heartbeat.py``), when the service
        #: runs one; the supervision tick looks at it too
        self.heartbeat: Any = None
        #: the operator audit log (``daemon/audit.py``), when the service has one: its
        #: commands without a recorded outcome and records waiting show in the status
        self.audit: Any = None
        #: what must hold for a procedure to start: each says why not ("" when it may);
        #: the service adds the navigation's (no calibration, no cameras, ...)
        self.start_checks: list[Callable[[], str]] = []
        #: what RUNNING runs: ``"procedure"`` (the navigation steers) or ``"temporal
        #: calibration"`` (``daemon/temporal_session.py`` moves the arm); set on each start
        self.activity: str | None = None
        #: the temporal calibration (``TemporalSession``) when the service built one; each
        #: supervision tick drives its excitation
        self.temporal_session: Any = None
        #: the session recorder (``daemon/recording.py``) when the service attached one;
        #: ``/recording`` delegates to it
        self.recorder: Any = None

    # -- the latched stop's handler (sync, never blocks) ---------------------------------
    def _stop_robot(self, record: Any) -> None:
        # a latched stop ends every motion mode and goal: the loop is told to stop, and
        # the goal record says HOLD, so that nothing resumes by itself after the reset
        # (a MOVE goal left behind would trip the loop's stale-pose watchdog at once)
        self.control.request_stop(f"{record.source}: {record.reason}")
        self.hold()

    # -- reports from the other tasks ----------------------------------------------------
    def publish_pose(self, name: str, T: np.ndarray, stamp: float, *, frame: str,
                     corners: int = 0, sigma_m: float = math.nan,
                     sigma_deg: float = math.nan) -> None:
        """A fresh pose ``T`` (4x4, m) of ``name`` in ``frame``, captured at ``stamp``."""
        self.pose_store.publish(name, T, stamp, frame=frame, corners=corners,
                                sigma_m=sigma_m, sigma_deg=sigma_deg)

    def watch_poses(self, names: set[str]) -> None:
        """Only these poses' staleness trips from now on (those the current stage steers
        by: a field hidden on purpose, like the effector inside the mouth, is no fault),
        and the opener's while a guided insertion runs."""
        self.pose_store.watch(names)

    def _pinned_poses(self) -> set[str]:
        # the opener's staleness trips while an insertion steers by it, whatever the stage
        return {GUIDE_POSE} if self.guide_session.running else set()

    def camera_frame(self, name: str, counter: int) -> None:
        """Camera ``name`` delivered frame ``counter`` now (the camera-stall watch)."""
        self.pose_store.camera_frame(name, counter)

    def set_rate(self, name: str, hz: float) -> None:
        """The measured rate (Hz) of tracking task ``name``, shown in /status."""
        self.pose_store.set_rate(name, hz)

    def pose(self, name: str) -> dict[str, Any] | None:
        """A copy of the newest pose record of ``name`` (``T`` 4x4 in m, ``stamp`` in s,
        ``frame``, ...), or None before its first pose."""
        return self.pose_store.pose(name)

    def arm_trajectory(self, max_gap: float) -> ArmTrajectory:
        """The arm's measured TCP history as the control loop recorded it (base frame,
        m; times on the daemon's monotonic clock), interpolated across gaps of at most
        ``max_gap`` s. Raises ``TimingError`` when its timestamps do not increase."""
        return ArmTrajectory.from_samples(self.control.read_arm_history(), max_gap)

    # -- supervisor task -----------------------------------------------------------------
    def supervise_once(self, now: float) -> None:
        """One look at everything; see the module docstring."""
        sup = self.supervisor
        if self.heartbeat is not None:
            self.heartbeat.observe(now)
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
                sup.estop(now, "e-stop input", "emergency stop pressed" if ins.connected else
                          f"e-stop input not connected, reads pressed: {ins.fault}"
                          if ins.fault else "e-stop input disconnected (reads pressed)")
        for trip in self.watchdogs.check(now):
            sup.fault(now, trip.name, trip.reason)
        problem = self._health(st, now)
        if problem is None:
            sup.mark_ready(now)
        else:
            sup.mark_not_ready(now, problem)
        self.guide_session.tick(now, st)
        if self.temporal_session is not None:
            self.temporal_session.tick(now)

    def _health(self, st: np.void | None, now: float) -> str | None:
        if st is None or not self.control.alive:
            return "control loop not running"
        silent = self._loop_silence(now)
        if silent is not None:
            return silent
        if not bool(st["arm_connected"]):
            why = decode_reason(st["arm_fault"])
            return f"arm not connected ({why})" if why else "arm not connected"
        if bool(st["protective_stop"]) or bool(st["emergency_stop"]):
            return "arm stopped by its controller"
        wrist_fault = decode_reason(st["wrist_fault"])
        if wrist_fault:  # a drive's fault or lost link (POST /recover/effector resets one)
            return f"end-effector: {wrist_fault}"
        return None

    def _loop_silence(self, now: float) -> str | None:
        """Why the loop counts as silent (its heartbeat stalled), or None."""
        deadline = self.watchdogs.deadline
        if self.heartbeat is None or not deadline.stalled(now):
            return None
        return (f"control loop silent for {(deadline.quiet(now) or 0.0) * 1e3:.0f} ms "
                "(process alive, no period completed)")

    def health(self) -> tuple[bool, str | None]:
        """Liveness of the daemon as a whole, for ``GET /health`` and the systemd
        watchdog: False (with why) while the control process is dead or its loop silent.
        A latched stop is no failure of the daemon: that is the safety state's business."""
        if not self.control.alive:
            return False, "control process is not running"
        silent = self._loop_silence(self.clock())
        return (False, silent) if silent is not None else (True, None)

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
                        arm_fault=decode_reason(st["arm_fault"]) or None,
                        wrist_connected=bool(st["wrist_connected"]),
                        wrist_fault=decode_reason(st["wrist_fault"]) or None,
                        motion_commands=int(st["motion_commands"]))
        if self.heartbeat is not None:  # the daemon's own view of the loop's heartbeat
            quiet = self.watchdogs.deadline.quiet(self.clock())
            loop.update(quiet_ms=None if quiet is None else quiet * 1e3,
                        last_silence=self.heartbeat.last_trip)
        rates = self.pose_store.rates()
        inputs = None
        if self.inputs is not None:
            ins = self.inputs.state()
            inputs = {"connected": ins.connected, "estop_pressed": ins.estop_pressed,
                      "pedal_pressed": ins.pedal_pressed, "fault": ins.fault,
                      "age_s": self.clock() - ins.timestamp}
        audit = None
        if self.audit is not None:
            audit = {"path": str(self.audit.path), "incomplete": self.audit.incomplete,
                     "pending": self.audit.pending}
        moving = self.supervisor.state in (SafetyState.RUNNING, SafetyState.PAUSED)
        now, wall = self.clock(), time.time()
        _add_utc(sup, now, wall)
        return jsonable({"safety": sup,
                         "clock": {"monotonic_s": now, "utc": _iso_utc(wall)},
                         "control_loop": loop, "inputs": inputs,
                         "activity": self.activity if moving else None,
                         "audit": audit, "latency_ms": self.latency_ms(),
                         "rates_hz": rates,
                         "uptime_s": self.clock() - self._started,
                         "procedure": dict(self.procedure_info),
                         "selected_target": self.selected_target,
                         "guidance": self.guide_session.status(st)})

    def latency_ms(self) -> dict[str, Any] | None:
        """Capture-to-command latency over the last goals the loop servoed (up to 512):
        from a frame's capture instant to the first servo command computed from it, in
        ms: ``{"n", "p50", "p99", "max"}`` (None each before the first goal), and
        ``stages``: the tracked rounds' ``delivery`` and ``tracking`` parts
        (``daemon/latency.py``). None before anything was tracked or servoed."""
        rec = getattr(self.control, "read_latency", None)
        lat = rec() if rec is not None else []
        whole = percentiles_ms(lat["t_command"] - lat["t_capture"]) if len(lat) else None
        stages = self.stage_times.summary()
        if whole is None and stages is None:
            return None
        out: dict[str, Any] = whole or {"n": 0, "p50": None, "p99": None, "max": None}
        out["stages"] = stages
        return out

    def poses(self) -> dict[str, Any]:
        now = self.clock()
        out: dict[str, Any] = self.pose_store.snapshot(now)
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
        doc["guidance"] = self.guide_session.status(st)
        return jsonable(doc)

    def estop(self, who: str, reason: str) -> None:
        self.supervisor.estop(self.clock(), f"operator {who}", reason or "REST e-stop")

    def recover(self, device: str, who: str) -> None:
        """An operator's request to recover ``device`` from its fault while the stop is
        latched: ``"effector"`` runs the drive's fault reset, ``"arm"`` the arm
        controller's recovery. Clearing the latch stays a separate reset."""
        state = self.supervisor.state
        if state not in (SafetyState.FAULT, SafetyState.ESTOP):
            raise StateError(f"cannot recover the {device} in {state.value}: device "
                             "recovery runs only while the stop is latched (FAULT or ESTOP)")
        log.warning("operator %s: recovering the %s", who, device)
        self.control.recover(device)

    def reset(self, who: str) -> None:
        now = self.clock()
        released = True
        if self.inputs is not None:
            released = not self.inputs.state().estop_pressed
        st = self.control.read_status()
        trips = self.watchdogs.check(now)
        problem = self._health(st, now)
        cleared = not trips and problem is None
        if not cleared:
            why = "; ".join([t.reason for t in trips] + ([problem] if problem else []))
            if self.supervisor.state in (SafetyState.FAULT, SafetyState.ESTOP) and released:
                raise StateError(f"cannot reset: the fault condition is still present ({why})")
        self.supervisor.reset(now, who, estop_released=released, faults_cleared=cleared)
        # a latch ended any insertion; never let a reset resume one
        self.guide_session.end(now, "reset")
        # HOLD again before the loop may command: a goal written in the instant the stop
        # latched must not be what it follows after the reset
        self.hold()
        self.control.clear_stop()
        log.info("reset by %s", who)

    def procedure(self, action: ProcedureAction, who: str) -> None:
        now = self.clock()
        sup = self.supervisor
        if action == "start":
            if not self._targets:
                raise StateError("cannot start: no suture targets registered (POST /targets)")
            if self.guide_session.running:
                raise StateError("cannot start the procedure: a guided insertion is running "
                                 "(POST /guide/stop first)")
            for check in self.start_checks:
                why = check()
                if why:  # never RUNNING with nothing that would move the robot
                    raise StateError(why)
            self.start_activity("procedure", now, who, "procedure started")
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

    def start_activity(self, activity: str, now: float, who: str, reason: str) -> None:
        """READY -> RUNNING for ``activity`` (``"procedure"``, ``"temporal calibration"``)
        at ``now`` (s). The activity is named before the state changes, so a task that
        steers one activity never sees RUNNING under another's name; a refused start
        (StateError) leaves it as it was."""
        before, self.activity = self.activity, activity
        try:
            self.supervisor.start(now, who, reason)
        except StateError:
            self.activity = before
            raise

    def targets(self) -> list[SutureTarget]:
        with self._lock:
            return list(self._targets)

    def set_targets(self, targets: list[SutureTarget], who: str) -> None:
        if self.supervisor.state in (SafetyState.RUNNING, SafetyState.PAUSED):
            raise StateError(f"cannot change targets while {self.supervisor.state.value}; "
                             "abort the procedure first")
        if self.supervisor.interrupted is not None:
            raise StateError("cannot change targets: a stop interrupted the procedure; "
                             "resume it or abort it first (POST /procedure/abort)")
        with self._lock:
            self._targets = list(targets)
            if self.selected_target not in {t.name for t in targets}:
                self.selected_target = None  # a choice among targets that are gone
        log.info("%d suture target(s) set by %s", len(targets), who)

    def planned_targets(self) -> list[SutureTarget]:
        """The cell's planned suture targets (``set_planned``), not registered yet."""
        return list(self._planned)

    def set_planned(self, targets_OM: dict[str, Any]) -> None:
        """The cell file's planned targets: name -> (3,) point in ``OM`` (m)."""
        self._planned = [SutureTarget(name=n, p_OM=tuple(float(x) for x in p))
                         for n, p in targets_OM.items()]

    def select_target(self, name: str, who: str) -> None:
        """The surgeon chooses the current suture target (the seed's "select the current
        suture target"): a running procedure goes there next, then on through the targets
        not yet visited; before a start it is the first one visited. Any state allows it
        (it moves nothing by itself). ``StateError`` when no target has that name."""
        with self._lock:
            names = [t.name for t in self._targets]
            if name not in names:
                raise StateError(f"cannot select {name!r}: no such suture target (registered: "
                                 f"{', '.join(names) or 'none, POST /targets first'})")
            self.selected_target = name
            self.selections += 1
        log.info("suture target %s selected by %s", name, who)

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

    # -- guided insertion (GUIDE mode): the guide session, the safety state's say ---------
    @property
    def T_B_C(self) -> np.ndarray | None:
        """The stereo camera in the robot base (4x4, m), or None before the calibration."""
        return self.guide_session.T_B_C

    @T_B_C.setter
    def T_B_C(self, T_B_C: np.ndarray | None) -> None:
        # stored as given, unchecked (a test clears it): set_hand_eye is the checked way
        self.guide_session.T_B_C = T_B_C

    def set_hand_eye(self, T_B_C: np.ndarray) -> None:
        """The stereo camera in the robot base (4x4, m): the hand-eye calibration that
        places the tracked opener, hence the patient's model, in the base."""
        self.guide_session.set_hand_eye(T_B_C)

    def plan_guide(self, scene: str, T_OM_F: Any, who: str,
                   seed: int | None = None) -> dict[str, Any]:
        """Plan an insertion from the planning scene file ``scene`` with the registration
        ``T_OM_F`` (4x4, m) and keep it for :meth:`start_guide`; returns its summary.

        Blocking (the scene may fit a mesh; placement runs the PSO): the API calls it in
        a worker thread. Atomic: any refusal leaves the previous plan in place.
        :class:`~oralnav.daemon.guidance.GuidePlanError` (422) for a bad request, scene or
        plan; :class:`~oralnav.daemon.guidance.NoSafePlacement` (409) when nothing
        collision-free exists; :class:`StateError` (409) while an insertion runs (a plan
        never changes under the operator's hand: stop it first).
        """
        return self.guide_session.plan(scene, T_OM_F, who, seed)

    def start_guide(self, who: str) -> None:
        """Send the plan to the control loop; GUIDE follows once the loop has installed it
        (within a few periods; the supervision tick switches). Refused (StateError,
        nothing changed) without a plan, unless READY (not latched, no procedure), without
        the hand-eye calibration or a fresh opener pose, or with the instrument head
        outside the virtual fixture: the loop never jumps the arm onto it."""
        self.guide_session.start(who)

    def stop_guide(self, who: str) -> None:
        """End the insertion (HOLD) and drop the plan, here and in the loop. Never
        refused: with nothing running it only drops the plan."""
        self.guide_session.stop(who)

    def guide(self) -> dict[str, Any]:
        """``GET /guide``: the plan (or None), the phase and the loop's live figures."""
        return jsonable(self.guide_session.report())

    def _guide_start_refused(self) -> str:
        """Why the safety state forbids starting an insertion, as the refusal says it (""
        when it allows one): only from READY, never latched, never beside a procedure."""
        sup = self.supervisor
        state = sup.state
        if state in LATCHED or sup.stop.latched:
            return f"cannot start guidance while in {state.value}: reset first"
        if state in (SafetyState.RUNNING, SafetyState.PAUSED):
            return f"cannot start guidance: a procedure is {state.value}; abort it first"
        if sup.interrupted is not None:
            return ("cannot start guidance: a stop interrupted the procedure; resume it or "
                    "abort it first")
        if state is not SafetyState.READY:
            return (f"cannot start guidance while in {state.value} (not ready: "
                    f"{sup.not_ready_reason or 'no health report yet'})")
        return ""

    def _guide_run_refused(self) -> str:
        """Why a running insertion must end now for the safety state ("" while it may go
        on): anything but READY, or a latched stop."""
        sup = self.supervisor
        if sup.state is not SafetyState.READY or sup.stop.latched:
            return f"safety state {sup.state.value}"
        return ""

    # -- needle procedure (simulated cell) ----------------------------------------------
    def _needle_refused(self) -> str:
        """Why a needle step may not move now ("" when it may): never with a latched stop
        or during a guided insertion."""
        sup = self.supervisor
        if sup.state in LATCHED or sup.stop.latched:
            return f"the safety state is {sup.state.value}: reset first"
        if self.guide_session.running:
            return "a guided insertion is running"
        return ""

    # -- temporal calibration (daemon/temporal_session.py) ------------------------------
    def start_temporal(self, body: Any, who: str) -> dict[str, Any]:
        """Start the temporal calibration's excitation (``TemporalCalibrationBody``);
        StateError when refused or when this cell has none."""
        from oralnav.daemon.temporal_session import Excitation

        if self.temporal_session is None:
            raise StateError("cannot calibrate time: this daemon has no capture pipeline")
        plan = Excitation(amplitude=body.amplitude_mm * 1e-3, period=body.period_s,
                          duration=body.duration_s, search=body.search_ms * 1e-3)
        return jsonable(self.temporal_session.start(who, plan))

    def temporal(self, samples: bool = False) -> dict[str, Any]:
        """``GET /calibration/temporal``: the run's report (``TemporalSession.report``)."""
        if self.temporal_session is None:
            raise StateError("this daemon has no capture pipeline: no temporal calibration")
        return jsonable(self.temporal_session.report(samples))

    def needle(self) -> dict[str, Any]:
        return jsonable(self.needle_session.status())

    def needle_cell(self, trial: int, difficulty: float, who: str,
                    servo: str = "off") -> dict[str, Any]:
        return jsonable(self.needle_session.load_trial(trial, difficulty, who, servo))

    def needle_step(self, step: str, who: str) -> dict[str, Any]:
        return jsonable(self.needle_session.run_step(step, who))

    # -- session recording (daemon/recording.py, docs/recording.md) ---------------------
    def _recorder(self) -> Any:
        if self.recorder is None:
            raise StateError("this daemon has no session recorder")
        return self.recorder

    def recording(self) -> dict[str, Any]:
        """``GET /recording``: the recorder's state and the latest recording's figures."""
        return jsonable(self._recorder().status())

    def start_recording(self, body: Any, who: str) -> dict[str, Any]:
        """Start recording (``RecordingStartBody``); blocking (it creates the file: the
        API calls it in a worker thread). StateError while a recording runs;
        ``RecordingError`` (a ValueError) for a file that cannot be created."""
        from oralnav.daemon.recording import RecordingOptions

        options = RecordingOptions(body.path, every=body.every, images=body.images,
                                   compression=body.compression,
                                   jpeg_quality=body.jpeg_quality,
                                   queue_rounds=body.queue_rounds)
        return jsonable(self._recorder().start(options, who))

    def stop_recording(self, who: str) -> dict[str, Any]:
        """End the recording and close its file (blocking: waits for the writer)."""
        return jsonable(self._recorder().stop(who))
