"""Capture -> tracking -> navigation, one task of the daemon's task group.

Each round reads one synchronised set of frames (stereo pair and endoscope), tracks the
fields in a worker thread (stereo: robot, effector, opener; endoscope: effector), reports
the poses and frame counters to the core (watchdogs, /poses), and, while the procedure
runs, turns them into the control loop's goal through the two-stage navigator
(``control/navigation/navigator.py``). On the simulated cell it also measures what the robot reached
against ground truth: each suture target's TRE (eq. 21: the distance between where the
end-effector truly is and where the target truly is, when the navigator says "reached").
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

import anyio
import anyio.to_thread
import numpy as np

from oralnav.config.calibration import Calibration
from oralnav.config.daemon import NAVIGATION_CALIBRATIONS
from oralnav.control.geometry import invert
from oralnav.control.navigation.navigator import NavCalibration, TwoStageNavigator
from oralnav.control.vision.tracker import Tracker
from oralnav.daemon.core import DaemonCore
from oralnav.safety.states import SafetyState
from oralnav.sim.world.cell import SimCell

log = logging.getLogger(__name__)


#: The poses each navigation stage steers by: their staleness stops the robot.
STEERING_POSES = {"approach": {"T_C_RM", "T_C_OM"}, "adjust": {"T_C_OM", "T_En_EM"},
                  "targets": {"T_C_OM", "T_En_EM"}}


class ArmProbe:
    """The arm pose source the simulated cell renders from: the control loop's newest
    measured TCP, remembered so navigation uses the pose of the same instant."""

    def __init__(self, core: DaemonCore, home: np.ndarray) -> None:
        self.core = core
        self._last = np.array(home, dtype=float)
        self._lock = threading.Lock()

    def __call__(self) -> np.ndarray:
        st = self.core.control.read_status()
        with self._lock:
            if st is not None and int(st["periods"]) > 0:
                self._last = np.array(st["T_B_tcp"])
            return self._last.copy()

    def wrist(self) -> np.ndarray:
        st = self.core.control.read_status()
        return np.zeros(4) if st is None else np.array(st["wrist"])


def sim_calibration(cell: SimCell) -> NavCalibration:
    """The simulated cell's true geometry as a calibration: what a perfect calibration
    would measure. Used only for kinds the configuration names no file for."""
    g = cell.config.geometry
    return NavCalibration(T_B_C=g.T_B_C, T_RM_E0=invert(g.T_tcp_RM) @ g.T_tcp_E0,
                          T_OM_En=g.T_OM_En, T_EM_E=invert(g.T_E_EM))


def nav_calibration(calibrations: Mapping[str, Calibration], cell: SimCell | None = None
                    ) -> NavCalibration:
    """The navigation chain's calibration from the configuration's files (kind ->
    :class:`Calibration`); on the simulated cell, a kind without a file falls back to the
    cell's truth (the service logs which). Raises ``KeyError`` naming the missing kinds
    otherwise."""
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
    """See the module docstring."""

    def __init__(self, core: DaemonCore, cell: SimCell, cameras: Any, probe: ArmProbe,
                 *, calibration: NavCalibration | None = None,
                 progress: Callable[[str], None] | None = None) -> None:
        self.core, self.cell, self.cameras, self.probe = core, cell, cameras, probe
        # the configuration's calibration files, else the cell's truth
        self.calibration = calibration or sim_calibration(cell)
        self.progress = progress or (lambda msg: log.info("%s", msg))
        self.stereo = Tracker(cell.stereo_rig, list(cell.fields), method="nvgba",
                              mode="predict")
        eff = [f for f in cell.fields if f.name == cell.config.effector]
        self.endo = Tracker(cell.endoscope_rig, eff, method="nvgba", mode="predict")
        self.navigator: TwoStageNavigator | None = None
        self.tre_mm: dict[str, float] = {}
        self._frames = 0
        self._t0 = time.monotonic()

    def _new_navigator(self) -> TwoStageNavigator:
        cfg = self.cell.config
        g = cfg.geometry
        T_OM_E0_entry = invert(g.T_B_OM) @ cfg.intraoral_T_B_tcp @ g.T_tcp_E0
        targets = {t.name: np.array(t.p_OM) for t in self.core.targets()}
        return TwoStageNavigator(self.calibration, T_OM_E0_entry, targets)

    def _track(self, frames: dict[str, Any]) -> tuple[dict, dict]:
        stereo = {n: f.image for n, f in frames.items() if n in self.cell.stereo_rig.names}
        endo = {n: f.image for n, f in frames.items() if n in self.cell.endoscope_rig.names}
        return self.stereo.track(stereo), self.endo.track(endo)

    async def run(self, *, task_status: anyio.abc.TaskStatus[None] =
                  anyio.TASK_STATUS_IGNORED) -> None:
        async with self.cameras:
            task_status.started()
            while True:
                frames = await self.cameras.read()
                await self._round(frames)

    async def _round(self, frames: dict[str, Any]) -> None:
        core, cfg = self.core, self.cell.config
        stamp = next(iter(frames.values())).timestamp
        T_B_tcp = self.cell.truth()["T_B_tcp"]  # the arm pose this capture rendered
        for name, f in frames.items():
            core.camera_frame(name, f.counter)
        stereo, endo = await anyio.to_thread.run_sync(self._track, frames)
        self._frames += 1
        core.set_rate("tracking", self._frames / max(time.monotonic() - self._t0, 1e-9))
        names = {cfg.robot: "RM", cfg.opener: "OM", cfg.effector: "EM"}
        for name, est in stereo.items():
            core.publish_pose(f"T_C_{names.get(name, name)}", est.T_ref_field, stamp,
                              frame="C", corners=est.corners,
                              sigma_m=est.position_sigma_m,
                              sigma_deg=est.rotation_sigma_deg)
        for est in endo.values():
            core.publish_pose("T_En_EM", est.T_ref_field, stamp, frame="En",
                              corners=est.corners, sigma_m=est.position_sigma_m,
                              sigma_deg=est.rotation_sigma_deg)
        try:
            self._navigate(stereo, endo, T_B_tcp, stamp)
        except Exception as exc:  # a navigation failure stops the robot, not the daemon
            log.exception("navigation failed")
            core.supervisor.fault(core.clock(), "navigation", f"{type(exc).__name__}: {exc}")
        stage = self.navigator.stage if self.navigator is not None else None
        # an interrupted procedure keeps its navigator, but steers nothing until resumed
        steering = core.supervisor.state in (SafetyState.RUNNING, SafetyState.PAUSED)
        core.watch_poses(STEERING_POSES.get(stage, set()) if steering else set())

    def _navigate(self, stereo: dict, endo: dict, T_B_tcp: np.ndarray, stamp: float) -> None:
        core, cfg = self.core, self.cell.config
        if core.supervisor.state is not SafetyState.RUNNING:
            if (core.supervisor.state is not SafetyState.PAUSED
                    and core.supervisor.interrupted is None):
                # a new start begins a new procedure; one a stop interrupted is kept, to
                # be resumed from its current target (or aborted) after the reset
                self.navigator = None
            return
        if self.navigator is None:
            self.navigator = self._new_navigator()
            self.tre_mm = {}
            core.procedure_info.clear()
            self.progress("stage approach: extra-oral, robot marker (eq. 5)")

        def pose(d: dict, name: str) -> np.ndarray | None:
            e = d.get(name)
            # as tracked: rigid to about 1e-15, and the chains check it (a pose that is not
            # rigid is a navigation failure that stops the robot, never a guess)
            return None if e is None else e.T_ref_field

        nav = self.navigator
        before = nav.stage
        step = nav.update(pose(stereo, cfg.robot), pose(stereo, cfg.opener),
                          pose(endo, cfg.effector), T_B_tcp)
        info = core.procedure_info
        info.update(stage=step.stage, error_mm=step.error_m * 1e3,
                    error_deg=math.degrees(step.error_rad), target=step.target,
                    tre_mm=dict(self.tre_mm))
        if step.reached:
            truth = self.cell.truth()
            p_true = self.cell.targets_B()[step.reached]
            self.tre_mm[step.reached] = float(np.linalg.norm(truth["T_B_E"][:3, 3] - p_true)) * 1e3
            info["tre_mm"] = dict(self.tre_mm)
            self.progress(f"reached {step.reached}: TRE {self.tre_mm[step.reached]:.3f} mm "
                          "against ground truth")
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
        if step.goal is not None:
            T_B_OM = self.cell.config.geometry.T_B_OM
            core.set_goal(step.goal, stamp, near_point=T_B_OM[:3, 3], wrist=np.zeros(4))
