"""The paper's two-stage navigation (section III.C) as a goal generator, with no I/O.

Stages:

1. ``approach`` (extra-oral): the stereo camera sees the robot marker; eq. 5 gives the
   end-effector zero frame ``T_B_E0``. The goal is the intra-oral entry pose, held in the
   opener frame (``T_OM_E0_entry``) and followed in the base through the opener marker.
2. ``adjust`` (intra-oral): the endoscope on the opener sees the end-effector marker; eq. 6
   gives ``T_B_E``, and the end-effector is brought onto the entry pose precisely.
3. ``targets``: each suture target, registered in the opener frame and followed in the
   base (eq. 8), is visited in turn with the end-effector's orientation kept.
4. ``done``.

Each ``update`` takes the newest poses (and the TCP pose at their capture time) and
returns the TCP goal that would put the measured frame on its goal: the visual correction
``T_B_tcp_goal = T_B_X_goal @ inv(T_B_X_meas) @ T_B_tcp``, which cancels calibration and
kinematic errors between the TCP and X as the loop converges (X = E0, then E).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from oralnav.control.geometry import compose, invert
from oralnav.control.motion import rotation_log
from oralnav.control.navigation.chains import extraoral_T_B_E0, intraoral_T_B_E, targets_in_base

STAGES = ("approach", "adjust", "targets", "done")


@dataclass(frozen=True)
class NavCalibration:
    """The calibrations the chains need (4x4, m): camera in base (hand-eye), end-effector
    zero on the robot marker (eqs. 3-4), endoscope on the opener (eq. 2), end-effector on
    its marker (eq. 7)."""

    T_B_C: np.ndarray
    T_RM_E0: np.ndarray
    T_OM_En: np.ndarray
    T_EM_E: np.ndarray


@dataclass
class NavStep:
    """What ``update`` decided: the TCP goal (None: hold), the stage, the remaining error
    of the steered frame (m, rad), and the target just reached (name) if any."""

    goal: np.ndarray | None
    stage: str
    error_m: float = float("nan")
    error_rad: float = float("nan")
    reached: str | None = None
    target: str | None = None


@dataclass
class TwoStageNavigator:
    """See the module docstring. ``targets_OM``: name -> (3,) point in ``OM`` (m), visited
    in order. A frame is on its goal within ``tol_m`` and ``tol_rad`` for ``settle``
    consecutive updates."""

    calib: NavCalibration
    T_OM_E0_entry: np.ndarray
    targets_OM: Mapping[str, np.ndarray]
    tol_m: float = 0.2e-3
    tol_rad: float = np.radians(0.2)
    settle: int = 3
    stage: str = "approach"
    _order: list[str] = field(default_factory=list)
    _index: int = 0
    _ok: int = 0
    _R_B_E: np.ndarray | None = None

    def __post_init__(self) -> None:
        self._order = list(self.targets_OM)

    @property
    def current_target(self) -> str | None:
        return self._order[self._index] if self._index < len(self._order) else None

    @property
    def remaining(self) -> list[str]:
        """The targets still to visit, the current one first."""
        return self._order[self._index:]

    def select(self, name: str) -> None:
        """Make ``name`` the current target (the surgeon's choice): it is visited next,
        then the targets not yet visited in their order. A visited target may be chosen
        again. Before the targets stage it is the first one visited. ``KeyError`` for a
        name that is not a target; nothing changes after ``"done"``."""
        if name not in self.targets_OM:
            raise KeyError(f"no suture target {name!r} (targets: "
                           f"{', '.join(self.targets_OM)})")
        if self.stage == "done":
            return
        rest = [t for t in self._order[self._index:] if t != name]
        self._order = self._order[:self._index] + [name] + rest
        self._ok = 0  # settling on the previous target counts nothing toward this one

    def update(self, T_C_RM: np.ndarray | None, T_C_OM: np.ndarray | None,
               T_En_EM: np.ndarray | None, T_B_tcp: np.ndarray) -> NavStep:
        """One navigation step from the poses of one capture (None: not seen) and the TCP
        pose (base, m) at that capture."""
        c = self.calib
        if self.stage == "done" or T_C_OM is None:
            return NavStep(None, self.stage)
        T_B_OM = compose(c.T_B_C, T_C_OM)
        if self.stage == "approach":
            if T_C_RM is None:
                return NavStep(None, self.stage)
            meas = extraoral_T_B_E0(c.T_B_C, T_C_RM, c.T_RM_E0[:3, :3], c.T_RM_E0[:3, 3])
            goal = T_B_OM @ self.T_OM_E0_entry
            return self._steer(meas, goal, T_B_tcp, next_stage="adjust")
        if T_En_EM is None:
            return NavStep(None, self.stage)
        meas = intraoral_T_B_E(c.T_B_C, T_C_OM, c.T_OM_En, T_En_EM, c.T_EM_E)
        if self.stage == "adjust":
            goal = T_B_OM @ self.T_OM_E0_entry  # the wrist is at zero: E = E0
            step = self._steer(meas, goal, T_B_tcp, next_stage="targets")
            if step.stage == "targets":
                self._R_B_E = goal[:3, :3].copy()
            return step
        name = self.current_target
        goal = np.eye(4)
        goal[:3, :3] = self._R_B_E if self._R_B_E is not None else meas[:3, :3]
        T_OM_tar = np.eye(4)
        T_OM_tar[:3, 3] = self.targets_OM[name]
        goal[:3, 3] = targets_in_base(c.T_B_C, T_C_OM, T_OM_tar)[:3, 3]
        step = self._steer(meas, goal, T_B_tcp, next_stage=None)
        step.target = name
        if step.reached:
            self._index += 1
            if self._index >= len(self._order):
                self.stage = "done"
            step.stage = self.stage
        return step

    def _steer(self, meas: np.ndarray, goal: np.ndarray, T_B_tcp: np.ndarray,
               next_stage: str | None) -> NavStep:
        err = invert(meas) @ goal
        e_m = float(np.linalg.norm(goal[:3, 3] - meas[:3, 3]))
        e_r = float(np.linalg.norm(rotation_log(err[:3, :3])))
        tcp_goal = goal @ invert(meas) @ T_B_tcp
        self._ok = self._ok + 1 if (e_m <= self.tol_m and e_r <= self.tol_rad) else 0
        step = NavStep(tcp_goal, self.stage, e_m, e_r)
        if self._ok >= self.settle:
            self._ok = 0
            if next_stage is not None:
                self.stage = next_stage
                step.stage = next_stage
            else:
                step.reached = self.current_target
        return step
