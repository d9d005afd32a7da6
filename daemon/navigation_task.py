"""The two-stage navigation as a listener of the capture pipeline, the same on every cell.

After each tracked round (``daemon/capture_task.py``) that completes a capture of the pose
the current stage steers by (``T_C_RM`` while approaching, ``T_En_EM`` inside the mouth)
and of the opener's (see "Pairing"), and while the procedure runs,
:class:`NavigationTask` turns the pose store's newest poses into the control loop's goal
through the two-stage navigator (``control/navigation/navigator.py``).
It reads only the pose store, the arm's measured history (the control loop's), the
configuration and the calibration files: no simulator object.

- **Time.** The navigator chains a tracked pose with the TCP pose (eqs. 5, 6, 8), so it is
  given the TCP pose *at that pose's capture instant*, interpolated in the arm's measured
  history (``control/navigation/arm_trajectory.py``). A frame the history cannot place
  (older than it, inside a gap, or not reported by the arm within ``ARM_WAIT_S``) is a
  FAULT naming why, never a pose chained across instants that do not match.
- **Pairing.** Each capture of the pose the stage steers by makes one step, with the
  opener pose of the same capture when another source tracks it (inside the mouth the
  effector is seen by the endoscope, the opener by the stereo pair): a step waits for the
  opener's round of that capture or later, one opener round at most. Stepping at once
  on the opener of the previous capture would make the goal a frame period older (on the
  hardware-in-the-loop cell the endoscope's single view is tracked before the stereo
  pair's two, and such goals went past ``stale_pose`` under load: the arm held).
- **Slow sight slows the robot.** The goal sent to the loop leads the arm's newest
  measured TCP by at most ``[navigation] max_step`` and ``max_turn_deg`` per tracked
  frame, so the arm moves at most that far on what one frame showed: slow tracking is
  slow motion; only poses that stop coming (the stale-pose watchdog) stop the robot.
- **Refusal.** :meth:`NavigationTask.refusal` says why a procedure cannot run on this
  cell (no navigation calibration, no entry pose, a stage whose poses no camera tracks);
  the core refuses ``POST /procedure/start`` with it (409).
- **Observers.** ``on_reached(target, stamp) -> TRE in mm or None`` callbacks measure what
  was reached, in a worker thread; only simulated cells attach them (``daemon/sim_cell.py``:
  the simulated cell's ground truth, or a hardware-in-the-loop cell's peers').
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import anyio
import numpy as np

from oralnav.config.calibration import Calibration
from oralnav.config.daemon import NAVIGATION_CALIBRATIONS, NavigationSection
from oralnav.control.geometry import invert
from oralnav.control.motion import step_toward
from oralnav.control.navigation.arm_trajectory import ArmTrajectory, TimingError
from oralnav.control.navigation.navigator import NavCalibration, TwoStageNavigator
from oralnav.daemon.capture_task import TrackedRound
from oralnav.daemon.core import DaemonCore
from oralnav.safety.states import SafetyState
from oralnav.sim.world.cell import CellConfig

__all__ = ["ARM_WAIT_S", "STEERING_POSES", "NavigationTask", "nav_calibration",
           "sim_calibration"]

log = logging.getLogger(__name__)

#: The poses each navigation stage steers by: their staleness stops the robot.
STEERING_POSES = {"approach": {"T_C_RM", "T_C_OM"}, "adjust": {"T_C_OM", "T_En_EM"},
                  "targets": {"T_C_OM", "T_En_EM"}}
#: The pose whose fresh capture makes a navigation step, by stage (the one that moves).
MOVING_POSE = {"approach": "T_C_RM", "adjust": "T_En_EM", "targets": "T_En_EM"}
#: The opener's pose: every stage's goal is in its frame (the head is taken as still).
OPENER_POSE = "T_C_OM"
#: s: two poses this close in capture instant are of one capture (cameras on a shared
#: trigger are stamped microseconds apart; frames of free-running cameras are not)
SAME_CAPTURE_S = 1e-3
#: Every pose some stage needs; a cell that tracks none of one refuses to start.
NEEDED_POSES = ("T_C_RM", "T_C_OM", "T_En_EM")
#: How long (s) a step waits for the arm to report a frame's capture instant: the arm
#: reports every period (2-8 ms), so a longer wait means its reports stopped.
ARM_WAIT_S = 0.1

#: ``(target name, capture instant s) -> TRE mm or None``: a measurement of what was
#: reached (the simulated cell's ground truth).
ReachedObserver = Callable[[str, float], float | None]


def sim_calibration(cell: CellConfig) -> NavCalibration:
    """The simulated cell's true geometry as a calibration: what a perfect calibration
    would measure. Used only for kinds the configuration names no file for."""
    g = cell.geometry
    return NavCalibration(T_B_C=g.T_B_C, T_RM_E0=invert(g.T_tcp_RM) @ g.T_tcp_E0,
                          T_OM_En=g.T_OM_En, T_EM_E=invert(g.T_E_EM))


def nav_calibration(calibrations: Mapping[str, Calibration], cell: CellConfig | None = None
                    ) -> NavCalibration:
    """The navigation chain's calibration from the configuration's files (kind ->
    :class:`Calibration`); on the simulated cell (its cell file), a kind without a file
    falls back to the cell's truth (the service logs which). Raises ``KeyError`` naming
    the missing kinds otherwise."""
    missing = [k for k in NAVIGATION_CALIBRATIONS if k not in calibrations]
    if missing and cell is None:
        raise KeyError(f"no calibration file for {', '.join(missing)} ([calibration] in the "
                       "configuration; docs/calibration.md)")
    truth = sim_calibration(cell) if cell is not None else None

    def pick(kind: str, key: str, attr: str) -> np.ndarray:
        cal = calibrations.get(kind)
        return np.array(cal[key]) if cal is not None else getattr(truth, attr)

    return NavCalibration(T_B_C=pick("hand_eye", "T_B_C", "T_B_C"),
                          T_RM_E0=pick("effector_zero", "T_RM_E0", "T_RM_E0"),
                          T_OM_En=pick("endoscope_opener", "T_OM_En", "T_OM_En"),
                          T_EM_E=pick("effector_marker", "T_EM_E", "T_EM_E"))


class NavigationTask:
    """See the module docstring.

    Args:
        core: the daemon core (pose store, arm history, safety state, goal).
        calibration: the navigation chain's calibration, or None when the cell has none
            (then every start is refused, saying so).
        entry_T_OM_E0: the intra-oral entry pose (4x4, m, opener frame), or None (refused).
        settings: ``[navigation]`` (per-frame step, arm-history gap).
        tracked: every pose the cell's cameras can publish (the pipeline's).
        progress: where stage changes and reached targets are said.
        observers: measurements of what was reached (only the simulated cell's).
        no_calibration: why ``calibration`` is None, for the refusal.
    """

    def __init__(self, core: DaemonCore, *, calibration: NavCalibration | None,
                 entry_T_OM_E0: np.ndarray | None, settings: NavigationSection,
                 tracked: set[str], progress: Callable[[str], None] | None = None,
                 observers: Sequence[ReachedObserver] = (), no_calibration: str = "") -> None:
        self.core = core
        self.calibration = calibration
        self.entry = None if entry_T_OM_E0 is None else np.array(entry_T_OM_E0, dtype=float)
        self.settings = settings
        self.tracked = set(tracked)
        self.progress = progress or (lambda msg: log.info("%s", msg))
        self.observers = list(observers)
        self.no_calibration = no_calibration
        self.navigator: TwoStageNavigator | None = None
        self.tre_mm: dict[str, float] = {}
        #: the core's selection count last applied to the navigator (``select_target``)
        self._selections = 0
        #: the moving pose last stepped on: (name, capture instant s); each capture of
        #: it makes one step (the navigator's settle count is in frames)
        self._stepped: tuple[str, float] | None = None

    # -- what the cell can do ------------------------------------------------------------
    def refusal(self) -> str:
        """Why a procedure cannot run on this cell ("" when it can)."""
        if self.calibration is None:
            return f"cannot start: no navigation calibration ({self.no_calibration})"
        if self.entry is None:
            return ("cannot start: no intra-oral entry pose ([navigation] entry_T_OM_E0 in "
                    "the configuration)")
        if not self.tracked:
            return "cannot start: no camera is configured to track the cell ([cameras.*])"
        lost = [p for p in NEEDED_POSES if p not in self.tracked]
        if lost:
            return ("cannot start: no camera tracks " + ", ".join(lost) + " (the approach "
                    "needs the stereo rig with the robot and opener fields, the intra-oral "
                    "stages the endoscope with the effector field)")
        return ""

    # -- one tracked round ---------------------------------------------------------------
    async def on_tracked(self, rnd: TrackedRound) -> None:
        """A listener of the capture pipeline: one navigation step when ``rnd`` carries
        the pose the current stage steers by and the procedure runs."""
        core = self.core
        if core.activity not in (None, "procedure"):
            return  # RUNNING moves the arm for something else (a temporal calibration)
        try:
            await self._step(rnd)
        finally:
            stage = self.navigator.stage if self.navigator is not None else None
            # an interrupted procedure keeps its navigator, but steers nothing until resumed
            steering = core.supervisor.state in (SafetyState.RUNNING, SafetyState.PAUSED)
            core.watch_poses(STEERING_POSES.get(stage, set()) if steering else set())

    async def _step(self, rnd: TrackedRound) -> None:
        core = self.core
        state = core.supervisor.state
        if state is not SafetyState.RUNNING:
            if state is not SafetyState.PAUSED and core.supervisor.interrupted is None:
                # a new start begins a new procedure; one a stop interrupted is kept, to
                # be resumed from its current target (or aborted) after the reset
                self.navigator = None
            return
        if self.calibration is None or self.entry is None:  # start was refused; belt
            core.supervisor.fault(core.clock(), "navigation", self.refusal())
            return
        if self.navigator is None:
            targets = {t.name: np.array(t.p_OM) for t in core.targets()}
            self.navigator = TwoStageNavigator(self.calibration, self.entry, targets)
            self._selections = 0  # a selection made before the start applies to this one
            self.tre_mm = {}
            core.procedure_info.clear()
            self.progress("stage approach: extra-oral, robot marker (eq. 5)")
        nav = self.navigator
        self._apply_selection(nav)
        moving = MOVING_POSE.get(nav.stage)
        rec = core.pose(moving) if moving is not None else None
        opener = core.pose(OPENER_POSE)
        if rec is None or opener is None or not self._paired(rnd, moving, rec, opener):
            return
        stamp = rec["stamp"]
        if stamp - opener["stamp"] > core.watchdogs.stale_pose:
            # the head is taken as still only within stale_pose: an older opener pose
            # steers nothing (the last goal goes stale and the arm holds; pose_timeout
            # stops it if the opener does not come back)
            return
        self._stepped = (moving, stamp)
        poses = {n: self._pose(n) for n in NEEDED_POSES}
        poses[moving], poses[OPENER_POSE] = rec["T"], opener["T"]
        T_B_tcp = await self._arm_at(stamp)
        if T_B_tcp is None:
            return
        before = nav.stage
        step = nav.update(poses["T_C_RM"] if moving == "T_C_RM" else None, poses["T_C_OM"],
                          poses["T_En_EM"] if moving == "T_En_EM" else None, T_B_tcp)
        info = core.procedure_info
        info.update(stage=step.stage, error_mm=step.error_m * 1e3,
                    error_deg=math.degrees(step.error_rad), target=step.target,
                    remaining=nav.remaining, tre_mm=dict(self.tre_mm))
        if step.reached:
            await self._reached(step.reached, stamp)
        if step.stage != before:
            self.progress({"adjust": "stage adjust: intra-oral, endoscope (eq. 6)",
                           "targets": "stage targets: suture targets followed in the base "
                                      "(eq. 8)",
                           "done": "all targets visited"}.get(step.stage, step.stage))
        if step.stage == "done":
            core.hold()
            info["done"] = True
            core.supervisor.abort(core.clock(), "navigator", "procedure complete")
            return
        if step.goal is not None and poses["T_C_OM"] is not None:
            goal = self._bounded(step.goal)
            near = (self.calibration.T_B_C @ poses["T_C_OM"])[:3, 3]  # the tracked opener
            # the goal is as old as the oldest pose behind it
            core.set_goal(goal, min(stamp, opener["stamp"]), near_point=near,
                          wrist=np.zeros(4))

    def _apply_selection(self, nav: TwoStageNavigator) -> None:
        """The surgeon's newest target choice, once: the navigator goes there next."""
        core = self.core
        if core.selections == self._selections or core.selected_target is None:
            return
        self._selections = core.selections
        if core.selected_target in nav.targets_OM:
            nav.select(core.selected_target)
            core.procedure_info["target"] = nav.current_target
            self.progress(f"target {core.selected_target} selected: visited next")

    def _paired(self, rnd: TrackedRound, moving: str, rec: Mapping[str, Any],
                opener: Mapping[str, Any]) -> bool:
        """Whether to step now on the newest ``moving`` pose (its store record ``rec``)
        after round ``rnd`` (module docstring, "Pairing"): not stepped on yet, and either
        the opener pose is of its capture or later, or ``rnd`` brought the opener (the
        wait is one opener round at most)."""
        if moving not in rnd.poses and OPENER_POSE not in rnd.poses:
            return False  # this round shows nothing the stage steers by
        if self._stepped == (moving, rec["stamp"]):
            return False
        return (opener["stamp"] >= rec["stamp"] - SAME_CAPTURE_S
                or OPENER_POSE in rnd.poses)

    def _pose(self, name: str) -> np.ndarray | None:
        """The store's newest ``name`` (4x4, m), or None."""
        rec = self.core.pose(name)
        return None if rec is None else rec["T"]

    async def _arm_at(self, stamp: float) -> np.ndarray | None:
        """The measured TCP at ``stamp`` (4x4, base, m), waiting up to ``ARM_WAIT_S`` for
        the arm to report that instant; None after a FAULT naming why it cannot be had."""
        core = self.core
        gap = self.settings.arm_history_gap
        with anyio.move_on_after(ARM_WAIT_S):
            while True:
                try:
                    return core.arm_trajectory(gap).at(stamp)
                except TimingError as exc:
                    if exc.kind not in ("newer", "empty"):
                        core.supervisor.fault(core.clock(), "navigation timing", str(exc))
                        return None
                    why = str(exc)
                await anyio.sleep(0.002)
        core.supervisor.fault(core.clock(), "navigation timing",
                              f"{why}, after waiting {ARM_WAIT_S * 1e3:.0f} ms")
        return None

    def _bounded(self, goal: np.ndarray) -> np.ndarray:
        """``goal`` moved toward from the arm's newest measured TCP by at most the
        per-frame step and turn (``[navigation] max_step``, ``max_turn_deg``)."""
        traj: ArmTrajectory = self.core.arm_trajectory(self.settings.arm_history_gap)
        now = traj.T[-1]
        s = self.settings
        out, _ = step_toward(now, goal, s.max_step, math.radians(s.max_turn_deg))
        return out

    async def _reached(self, target: str, stamp: float) -> None:
        for observe in self.observers:
            # in a worker thread: a peer's truth service may take a while to answer, and
            # the event loop also runs the supervisor
            tre = await anyio.to_thread.run_sync(observe, target, stamp)
            if tre is not None:
                self.tre_mm[target] = tre
                self.core.procedure_info["tre_mm"] = dict(self.tre_mm)
                self.progress(f"reached {target}: TRE {tre:.3f} mm against ground truth")
                return
        self.progress(f"reached {target}")
