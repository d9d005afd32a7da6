"""Guided insertion as the daemon runs it (GUIDE mode, docs/control_loop.md "Guided
insertion"): the plan it holds, the insertion's phase, and the plan's way to and from
the control loop.

:meth:`GuideSession.plan` plans from a planning scene and keeps the plan;
:meth:`~GuideSession.start` sends it to the control loop (refused unless the safety state
allows it, with a fresh opener pose and the instrument inside the fixture); each
supervision tick (:meth:`~GuideSession.tick`) then commands GUIDE with the patient's model
frame ``T_B_F = T_B_C @ T_C_OM @ T_OM_F`` (4x4, m, robot base ``B``) from the newest
tracked opener pose; :meth:`~GuideSession.stop`, any latched stop
(:meth:`~GuideSession.on_stop`), or a loop that stops on its own end it (HOLD).

The session knows nothing of the safety state machine: the core passes in why a start is
refused and why a running insertion must end, as it passes the needle session
``motion_refused``. One re-entrant lock guards the state: ``plan`` commits from a worker
thread, the tick runs on the supervision task, the stop handler wherever a stop latches.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable
from typing import Any

import numpy as np

from oralnav.control.errors import ControlError
from oralnav.control.geometry import as_transform, invert
from oralnav.daemon.guidance import GuideDraft, GuidePlanError, model_frame, plan_insertion
from oralnav.daemon.poses import PoseStore
from oralnav.realtime.control_process import ControlPort
from oralnav.realtime.plan_channel import ChannelError
from oralnav.realtime.shm import decode_reason
from oralnav.safety.errors import StateError
from oralnav.safety.watchdogs import WatchdogSet

log = logging.getLogger(__name__)

#: The tracked pose guidance steers by: the opener's marker field in the stereo camera.
GUIDE_POSE = "T_C_OM"
#: How long the control loop may take to install a plan after ``start`` (s) before the
#: start is abandoned, plus :data:`GUIDE_ARM_S_PER_BYTE` per byte of the plan (the loop
#: reads 64 KiB per period, 32 MB/s at 500 Hz: a 2 MB plan takes about 70 ms).
GUIDE_ARM_TIMEOUT = 1.0
GUIDE_ARM_S_PER_BYTE = 1 / 8e6


class GuideSession:
    """See the module docstring. ``clock`` is the daemon's monotonic clock (s); ``hold()``
    tells the loop to hold where it is. ``start_refused()`` is the whole refusal message
    when the safety state forbids a start (``""`` when it allows one); ``run_refused()``
    why a running insertion must end (``""`` while it may go on). Both are called with the
    session's lock held: they must not block."""

    def __init__(self, control: ControlPort, watchdogs: WatchdogSet, poses: PoseStore, *,
                 clock: Callable[[], float], hold: Callable[[], None],
                 start_refused: Callable[[], str], run_refused: Callable[[], str]) -> None:
        self.control = control
        self.watchdogs = watchdogs
        self.poses = poses
        self.clock = clock
        self._hold = hold
        self._start_refused = start_refused
        self._run_refused = run_refused
        #: the stereo camera in the robot base (4x4, m), or None before the calibration
        self.T_B_C: np.ndarray | None = None
        self._lock = threading.RLock()
        self._draft: GuideDraft | None = None
        self._phase = "idle"               # "idle", "arming" (plan sent), "active"
        self._seq = 0                      # the plan message of this insertion
        self._deadline = 0.0               # when arming is abandoned (s)
        self._since: float | None = None
        self._by: str | None = None
        self._last_end: dict[str, Any] | None = None   # why the last insertion ended
        self._clear = False                # the loop still holds a plan to remove

    @property
    def running(self) -> bool:
        """Whether an insertion is arming or active. Read without the lock, for checks
        that only need a recent answer (the next tick acts on the locked one)."""
        return self._phase != "idle"

    def set_hand_eye(self, T_B_C: np.ndarray) -> None:
        """The stereo camera in the robot base (4x4, m): the hand-eye calibration that
        places the tracked opener, hence the patient's model, in the base."""
        try:
            self.T_B_C = as_transform(np.asarray(T_B_C, dtype=float), what="T_B_C")
        except ControlError as exc:
            raise ValueError(f"hand-eye calibration: {exc}") from None

    # -- the plan ------------------------------------------------------------------------
    def plan(self, scene: str, T_OM_F: Any, who: str,
             seed: int | None = None) -> dict[str, Any]:
        """Plan from the planning scene file ``scene`` with the registration ``T_OM_F``
        (4x4, m) and keep the plan; returns its summary. Blocking (worker thread) and
        atomic; ``DaemonCore.plan_guide`` lists the refusals."""
        self._refuse_while_guiding("plan")
        draft = plan_insertion(scene, T_OM_F, who, seed)
        try:
            self.control.check_guide(draft.plan)
        except ChannelError as exc:
            raise GuidePlanError(str(exc)) from None
        with self._lock:
            self._refuse_while_guiding("plan")  # again: it may have started meanwhile
            self._draft = draft
        p = draft.placement
        log.info("insertion planned by %s from %s: d_T %.1f mm, theta_T %.1f deg", who,
                 scene, p.d_T * 1e3, math.degrees(p.theta_T))
        return draft.summary()

    def _refuse_while_guiding(self, what: str) -> None:
        with self._lock:
            if self._phase != "idle":
                raise StateError(f"cannot {what} while a guided insertion is running "
                                 f"(started by {self._by}); POST /guide/stop first")

    # -- start, stop, status -------------------------------------------------------------
    def start(self, who: str) -> None:
        """Send the plan to the control loop; GUIDE follows once the loop has installed it
        (the tick switches). StateError, nothing changed, when refused; see
        ``DaemonCore.start_guide``."""
        now = self.clock()
        with self._lock:
            if self._phase != "idle":
                raise StateError(f"a guided insertion is already running (started by "
                                 f"{self._by})")
            draft = self._draft
            if draft is None:
                raise StateError("no insertion plan: POST /guide/plan first")
            why = self._start_refused()
            if why:
                raise StateError(why)
            st = self.control.read_status()
            if st is None or not self.control.alive or bool(st["latched"]):
                raise StateError("cannot start guidance: the control loop is not running "
                                 "or is stopped")
            T_B_F, stamp = self._model_frame(draft)
            age = now - stamp
            limit = self.watchdogs.stale_pose  # older, and the loop's GUIDE check stops it
            if age > limit:
                raise StateError(f"cannot start guidance: the opener pose ({GUIDE_POSE}) is "
                                 f"{age:.2f} s old (limit {limit:g} s)")
            fx = draft.plan.fixture
            T_F_B = invert(T_B_F)
            p_F = T_F_B[:3, :3] @ np.array(st["T_B_tcp"])[:3, 3] + T_F_B[:3, 3]
            if not fx.contains(p_F, margin=draft.plan.admittance.wall_tolerance):
                raise StateError(
                    f"cannot start guidance: the instrument head is outside the virtual "
                    f"fixture ({fx.axial(p_F) * 1e3:.1f} mm along the axis from the target, "
                    f"{fx.radial(p_F) * 1e3:.1f} mm from it, allowed "
                    f"{fx.allowed_radius(max(fx.axial(p_F), 0.0)) * 1e3:.1f} mm); bring it "
                    "onto the planned entry path first")
            try:
                seq = self.control.set_guide(draft.plan)
            except ChannelError as exc:
                raise StateError(f"cannot start guidance: {exc}") from None
            self._phase, self._seq = "arming", seq
            self._deadline = (now + GUIDE_ARM_TIMEOUT
                              + self.control.guide_bytes * GUIDE_ARM_S_PER_BYTE)
            self._since, self._by, self._last_end = now, who, None
            self._clear = False
        self.poses.rewatch()
        self.watchdogs.poses.fresh(GUIDE_POSE, stamp)
        log.info("guided insertion started by %s (plan message %d)", who, seq)

    def stop(self, who: str) -> None:
        """End the insertion (HOLD) and drop the plan, here and in the loop. Never
        refused: with nothing running it only drops the plan."""
        with self._lock:
            self._finish(self.clock(), f"stopped by {who}")
            self._draft = None
            if self._clear:
                self._clear_loop_plan()
        log.info("guidance stopped and plan cleared by %s", who)

    def end(self, now: float, reason: str) -> None:
        """End a running insertion at ``now`` (s) for ``reason`` (HOLD), keeping the plan;
        nothing when none runs."""
        with self._lock:
            self._finish(now, reason)

    def on_stop(self, record: Any) -> None:
        """Latched-stop handler: any stop ends the insertion at once (HOLD), so that a
        reset can never resume it. Quick and never blocking, as the stop path requires."""
        with self._lock:
            self._finish(self.clock(), f"stop: {record.source}: {record.reason}")

    def report(self) -> dict[str, Any]:
        """``GET /guide``: the plan's summary (or None), the phase and the loop's live
        figures (not yet JSON-safe: numpy values and NaN stay)."""
        with self._lock:
            draft = self._draft
        doc = self.status(self.control.read_status())
        doc["plan"] = draft.summary() if draft is not None else None
        return doc

    def status(self, st: np.void | None) -> dict[str, Any]:
        """The phase, who started it and when (s), how the last one ended, and from the
        loop's status record ``st`` its guidance figures (m)."""
        with self._lock:
            running = self._phase != "idle"
            doc: dict[str, Any] = {"phase": self._phase, "planned": self._draft is not None,
                                   "started_by": self._by if running else None,
                                   "since": self._since if running else None,
                                   "last_end": self._last_end}
        if st is not None:
            doc.update(active=bool(st["guide_active"]),
                       loop_planned=bool(st["guide_planned"]),
                       rod_distance_m=float(st["guide_rod_distance"]),
                       to_target_m=float(st["guide_to_target"]),
                       lateral_m=float(st["guide_lateral"]))
        return doc

    # -- each supervision tick -----------------------------------------------------------
    def tick(self, now: float, st: np.void | None) -> None:
        """Switch to GUIDE once the loop has the plan, then publish ``T_B_F``; end the
        insertion when anything is wrong (the robot holds). ``now``: the tick's time (s);
        ``st``: the loop's status record read by this tick."""
        with self._lock:
            self.control.flush_guide()
            if self._clear:
                self._clear_loop_plan()
            phase = self._phase
            if phase == "idle":
                return
            why = self._run_refused() or _loop_trouble(self.control, st) or None
            if why is None and phase == "arming":
                reply = self.control.guide_reply(self._seq)
                if reply == "refused":
                    why = "the control loop refused the plan (see its log)"
                elif reply is None:
                    if now > self._deadline:
                        why = ("the control loop did not take the plan in time (it "
                               "stops rather than guide without one)")
                    else:
                        return
                else:
                    self._phase = "active"
            if why is None:
                try:
                    T_B_F, stamp = self._model_frame(self._draft)
                except (StateError, ControlError) as exc:  # no opener pose, or a bad one
                    why = str(exc)
            if why is not None:
                self._finish(now, why)
                return
            # the pose's capture time, not now: a stale opener pose trips the loop's
            # stale-pose watchdog exactly as a stale goal does in MOVE
            self.control.set_guide_frame(T_B_F, stamp, near_point=T_B_F[:3, 3])

    def _model_frame(self, draft: GuideDraft) -> tuple[np.ndarray, float]:
        """``T_B_F`` (4x4, m) from the newest opener pose, and that pose's capture time
        (s)."""
        if self.T_B_C is None:
            raise StateError("cannot guide: no hand-eye calibration (T_B_C) to place the "
                             "patient in the robot base")
        p = self.poses.pose(GUIDE_POSE)
        if p is None:
            raise StateError(f"cannot guide: no pose of the mouth opener ({GUIDE_POSE}) "
                             "yet; it must be tracked")
        return model_frame(self.T_B_C, p["T"], draft.T_OM_F), p["stamp"]

    def _finish(self, now: float, reason: str) -> None:
        """Hold, and remove the plan from the loop (call with the lock held). The plan
        stays unless ``stop`` drops it: after a reset the operator may start again,
        through every check of ``start``."""
        if self._phase == "idle":
            return
        self._phase = "idle"
        self._last_end = {"time": now, "reason": reason, "by": self._by}
        self._by = None
        self._hold()
        self._clear = True
        self._clear_loop_plan()
        self.poses.rewatch()
        log.warning("guided insertion ended: %s", reason)

    def _clear_loop_plan(self) -> None:
        """Ask the loop to drop its plan; retried at the next tick while the channel is
        busy. Never blocks (a non-blocking pipe write)."""
        try:
            self.control.set_guide(None)
        except ChannelError:
            return
        self._clear = False


def _loop_trouble(control: ControlPort, st: np.void | None) -> str:
    """Why the control loop cannot guide now, from its status record ``st`` ("" when it
    can): not running, or latched on a stop."""
    if st is None or not control.alive:
        return "the control loop is not running"
    if bool(st["latched"]):
        return f"the control loop stopped: {decode_reason(st['stop_reason'])}"
    return ""
