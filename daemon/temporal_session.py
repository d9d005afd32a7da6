"""The temporal calibration run by the daemon: the arm's excitation, the record, the fit.

``POST /calibration/temporal`` starts it (``oralnav calibrate temporal`` does, and polls
``GET /calibration/temporal``). From READY, with the robot marker in the stereo camera's
view, the session:

1. takes the safety state to RUNNING (the activity ``"temporal calibration"``: every stop,
   pause, abort and watchdog applies as to a procedure; the navigation ignores it) and
   watches the robot marker's pose, so that losing it stops the robot;
2. at each supervision tick sends the loop a MOVE goal: the start pose translated by the
   excitation (``control/calibration/temporal.py`` :func:`excitation`, a few millimetres,
   the orientation held), stamped now (an open-loop path, not derived from a frame);
3. records each tracked robot-marker position with its published stamp (a listener of the
   capture pipeline), and the arm's measured TCP history (the control loop's ring, read at
   every tick, so a run longer than the ring keeps every sample);
4. after the excitation and half a second of rest, holds, ends the activity (READY) and
   fits the offset in a worker thread (:func:`estimate_time_offset`).

The published stamps already have the applied offset subtracted, so the fit measures what
is left; the result is the applied offset plus it: the offset to write. Any stop, pause or
abort ends the run as failed, with why. No file is written here: the client writes the
calibration file (atomically, as every calibration command does) and the daemon applies it
when it next loads its configuration.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass
from typing import Any

import numpy as np

from oralnav.control.calibration.temporal import TemporalFit, estimate_time_offset, excitation
from oralnav.control.errors import CalibrationError
from oralnav.safety.errors import StateError
from oralnav.safety.states import SafetyState

__all__ = ["ACTIVITY", "REST_S", "ROBOT_POSE", "Excitation", "TemporalSession"]

log = logging.getLogger(__name__)

#: The safety supervisor's activity while the excitation runs (``DaemonCore.activity``).
ACTIVITY = "temporal calibration"
#: The pose the fit follows: the robot marker in the stereo camera.
ROBOT_POSE = "T_C_RM"
#: Rest (s) after the excitation before the record ends, so the last frames are placed.
REST_S = 0.5


@dataclass(frozen=True)
class Excitation:
    """The excitation asked for: peak ``amplitude`` (m), ``period`` (s), ``duration`` (s),
    and the offsets searched, ``+-search`` (s)."""

    amplitude: float = 0.005
    period: float = 4.0
    duration: float = 24.0
    search: float = 0.2


class TemporalSession:
    """See the module docstring.

    Args:
        core: the daemon core (safety state, goal, poses, the arm's history).
        applied_offset: the stereo camera's offset the pipeline already subtracts (s).
        tracked: whether a camera of this cell tracks the robot marker (``T_C_RM``).
    """

    def __init__(self, core: Any, *, applied_offset: float, tracked: bool) -> None:
        self.core = core
        self.applied_offset = float(applied_offset)
        self.tracked = tracked
        self._lock = threading.Lock()
        self.phase = "idle"            # idle | moving | solving | done | failed
        self.excitation: Excitation | None = None
        self.by: str | None = None
        self.error: str | None = None
        self.fit: TemporalFit | None = None
        self._t0 = 0.0
        self._T0 = np.eye(4)
        self._near: np.ndarray | None = None
        self._frames: list[tuple[float, np.ndarray]] = []
        self._arm_t: list[np.ndarray] = []
        self._arm_p: list[np.ndarray] = []
        self._arm_last = -np.inf
        self._solver: threading.Thread | None = None

    # -- start ---------------------------------------------------------------------------
    def refusal(self) -> str:
        """Why a run cannot start now ("" when it can)."""
        core = self.core
        if not self.tracked:
            return ("cannot calibrate time: no camera of this cell tracks the robot marker "
                    f"({ROBOT_POSE}; the stereo rig with the robot field)")
        if self.phase in ("moving", "solving"):
            return f"a temporal calibration is already running (started by {self.by})"
        state = core.supervisor.state
        if state is not SafetyState.READY:
            return f"cannot calibrate time in {state.value}: the robot must be READY"
        if core.guide_session.running:
            return "cannot calibrate time: a guided insertion is running"
        rec = core.pose(ROBOT_POSE)
        # in view: a pose newer than the lost-pose limit (the excitation is open loop, so
        # a slow camera's older poses still record the motion)
        limit = core.watchdogs.poses.limit
        if rec is None or core.clock() - rec["stamp"] > limit:
            return (f"cannot calibrate time: the robot marker ({ROBOT_POSE}) is not in view "
                    f"(no pose within {limit:g} s)")
        if core.control.read_status() is None:
            return "cannot calibrate time: the control loop has not reported the arm yet"
        return ""

    def start(self, who: str, plan: Excitation) -> dict[str, Any]:
        """Start the excitation ``plan`` from the arm's current pose; StateError, nothing
        moved, when refused. Returns :meth:`report`."""
        core = self.core
        try:  # a plan the excitation refuses (too short) moves nothing
            excitation(0.0, plan.amplitude, plan.period, plan.duration)
        except CalibrationError as exc:
            raise StateError(f"cannot calibrate time: {exc}") from None
        with self._lock:
            why = self.refusal()
            if why:
                raise StateError(why)
            now = core.clock()
            st = core.control.read_status()
            self._T0 = np.array(st["T_B_tcp"], dtype=float)
            self._near = self._opener_in_base()
            self._frames, self._arm_t, self._arm_p = [], [], []
            self._arm_last = -np.inf
            # named before RUNNING: the navigation must never steer it
            core.start_activity(ACTIVITY, now, who, "temporal calibration started")
            self.excitation, self.by, self.error, self.fit = plan, who, None, None
            self._t0 = now
            self.phase = "moving"
        core.watch_poses({ROBOT_POSE})  # a lost robot marker stops the robot
        log.info("temporal calibration started by %s: %.1f mm, %.1f s period, %.0f s", who,
                 plan.amplitude * 1e3, plan.period, plan.duration)
        return self.report()

    def _opener_in_base(self) -> np.ndarray | None:
        """The tracked opener in the base (m), for the loop's near-patient speed limit;
        None without a hand-eye calibration or an opener pose."""
        T_B_C, rec = self.core.T_B_C, self.core.pose("T_C_OM")
        if T_B_C is None or rec is None:
            return None
        return (T_B_C @ rec["T"])[:3, 3]

    # -- the run -------------------------------------------------------------------------
    def tick(self, now: float) -> None:
        """One supervision tick (``now``: s): the goal of the excitation at ``now``, the
        arm's new samples; the end of the run when it is over or interrupted."""
        core = self.core
        with self._lock:
            if self.phase != "moving":
                return
            self._collect()
            state = core.supervisor.state
            if state is not SafetyState.RUNNING or core.activity != ACTIVITY:
                self._fail(now, f"interrupted ({state.value})")
                return
            plan = self.excitation
            s = now - self._t0
            if s >= plan.duration + REST_S:
                core.hold()
                core.supervisor.abort(now, "temporal calibration", "excitation complete")
                core.watch_poses(set())
                self.phase = "solving"
                self._solver = threading.Thread(target=self._solve, name="temporal fit",
                                                daemon=True)
                self._solver.start()
                return
            goal = self._T0.copy()
            goal[:3, 3] += excitation(min(s, plan.duration), plan.amplitude, plan.period,
                                      plan.duration)
            if not core.set_goal(goal, now, near_point=self._near, wrist=np.zeros(4)):
                self._fail(now, "the safety state refused motion")

    def _collect(self) -> None:
        """Append the arm's samples newer than the last kept (call with the lock held)."""
        h = self.core.control.read_arm_history()
        if not len(h):
            return
        new = h["t"] > self._arm_last
        if new.any():
            self._arm_t.append(np.array(h["t"][new], dtype=float))
            self._arm_p.append(np.array(h["T_B_tcp"][new][:, :3, 3], dtype=float))
            self._arm_last = float(h["t"][new][-1])

    def _fail(self, now: float, why: str) -> None:
        """End the run as failed (lock held): HOLD, and no procedure left to resume."""
        core = self.core
        self.phase, self.error = "failed", why
        core.hold()
        core.watch_poses(set())
        try:  # RUNNING/PAUSED -> READY, or drop what a latched stop interrupted
            core.supervisor.abort(now, "temporal calibration", f"temporal calibration {why}")
        except StateError:
            pass
        log.warning("temporal calibration failed: %s", why)

    async def on_tracked(self, rnd: Any) -> None:
        """A capture-pipeline listener: keep the round's robot-marker position."""
        stamp = rnd.poses.get(ROBOT_POSE)
        if stamp is None or self.phase != "moving":
            return
        rec = self.core.pose(ROBOT_POSE)
        if rec is not None and rec["stamp"] == stamp:
            with self._lock:
                self._frames.append((float(stamp), np.array(rec["T"][:3, 3], dtype=float)))

    def _solve(self) -> None:
        """The fit, in a worker thread (a few hundred ms of numpy)."""
        plan = self.excitation
        with self._lock:
            frames = list(self._frames)
            t_arm = np.concatenate(self._arm_t) if self._arm_t else np.zeros(0)
            p_arm = np.concatenate(self._arm_p) if self._arm_p else np.zeros((0, 3))
        try:
            fit = estimate_time_offset(np.array([f[0] for f in frames]),
                                       np.array([f[1] for f in frames]).reshape(-1, 3),
                                       t_arm, p_arm, search_s=plan.search)
        except CalibrationError as exc:
            with self._lock:
                self.phase, self.error = "failed", str(exc)
            log.warning("temporal calibration failed: %s", exc)
            return
        with self._lock:
            self.fit, self.phase = fit, "done"
        log.info("temporal calibration: stereo timestamps %+.2f ms (+- %.2f ms) late "
                 "against the arm, %.2f ms applied", (self.applied_offset + fit.offset_s)
                 * 1e3, fit.sigma_s * 1e3, self.applied_offset * 1e3)

    def wait(self, timeout: float | None = None) -> None:
        """Wait for the fit to end (tests, the virtual-clock cell)."""
        if self._solver is not None:
            self._solver.join(timeout)

    # -- report --------------------------------------------------------------------------
    def report(self, samples: bool = False) -> dict[str, Any]:
        """``GET /calibration/temporal``: the phase, the progress and, once done, the
        offset to write (``offset_s``: the applied one plus what the fit found); with
        ``samples``, the record itself (stamps s, positions m) for the calibration file's
        digest and for a fit offline."""
        with self._lock:
            plan = self.excitation
            doc: dict[str, Any] = {
                "phase": self.phase, "started_by": self.by, "error": self.error,
                "applied_offset_s": self.applied_offset,
                "excitation": None if plan is None else {
                    "amplitude_mm": plan.amplitude * 1e3, "period_s": plan.period,
                    "duration_s": plan.duration, "search_ms": plan.search * 1e3},
                "elapsed_s": (self.core.clock() - self._t0) if self.phase == "moving"
                else None,
                "frames": len(self._frames),
                "arm_samples": int(sum(len(a) for a in self._arm_t)),
                "result": None}
            if self.fit is not None:
                doc["result"] = {"offset_s": self.applied_offset + self.fit.offset_s,
                                 "sigma_s": self.fit.sigma_s, **self.fit.as_dict()}
            if samples:
                doc["samples"] = {
                    "t_cam": [f[0] for f in self._frames],
                    "p_C": [f[1].tolist() for f in self._frames],
                    "t_arm": np.concatenate(self._arm_t).tolist() if self._arm_t else [],
                    "p_B": np.concatenate(self._arm_p).tolist() if self._arm_p else []}
        return doc
