"""Planning a guided insertion for the daemon: scene -> placement -> plan, and where the
patient's model frame is in the robot base.

Frames (docs/planning.md, docs/control_loop.md "Guided insertion"):

- ``F``: the surrogate model's Center frame, in which the scene, the placement and the
  virtual fixture live;
- ``OM``: the mouth opener's marker field, which the stereo camera tracks (``T_C_OM``);
- ``C``, ``B``: the stereo camera and the robot base; ``T_B_C`` is the hand-eye
  calibration.

So ``T_B_F = T_B_C @ T_C_OM @ T_OM_F``. The registration ``T_OM_F`` (where the model sits
on the opener, from registering the patient's scan to the opener) is not in the planning
scene, whose format is the planner's; it comes with the plan request, is checked here,
and is part of the plan the operator sees. There is no default: a guessed registration
would put the fixture beside the patient.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from oralnav.config.errors import ConfigError
from oralnav.config.planning import load_planning_scene
from oralnav.control.errors import ControlError
from oralnav.control.geometry import as_transform
from oralnav.control.guidance.guided_motion import GuidePlan
from oralnav.control.guidance.virtual_fixture import VirtualFixture
from oralnav.control.planning.placement import Placement, place
from oralnav.control.planning.rod_check import RodCheck
from oralnav.daemon.errors import DaemonError
from oralnav.safety.errors import StateError

#: The farthest the model's Center frame may sit from the opener marker's origin (m): a
#: larger registration is a unit mistake (millimetres) or not this patient.
MAX_REGISTRATION_OFFSET = 0.3


class GuidePlanError(DaemonError, ValueError):
    """The plan request is invalid: an unreadable or invalid scene, a planning error, a bad
    registration, or a plan the control channel cannot carry (REST 422)."""


class NoSafePlacement(DaemonError, StateError):
    """The placement found no collision-free feeding target (REST 409); ``placement`` holds
    the least bad one, which must never be followed."""

    def __init__(self, message: str, placement: Placement) -> None:
        super().__init__(message)
        self.placement = placement


def check_registration(T_OM_F: Any) -> np.ndarray:
    """``T_OM_F`` as a float 4x4 rigid transform (m) within :data:`MAX_REGISTRATION_OFFSET`
    of the opener; :class:`GuidePlanError` naming what is wrong otherwise."""
    try:
        T = as_transform(np.asarray(T_OM_F, dtype=float), what="T_OM_F")
    except (ControlError, TypeError, ValueError) as exc:
        raise GuidePlanError(f"T_OM_F: {exc}") from None
    d = float(np.linalg.norm(T[:3, 3]))
    if d > MAX_REGISTRATION_OFFSET:
        raise GuidePlanError(f"T_OM_F puts the model {d:.3g} m from the opener marker (at "
                             f"most {MAX_REGISTRATION_OFFSET} m; metres expected, not "
                             "millimetres?)")
    return T


def model_frame(T_B_C: np.ndarray, T_C_OM: np.ndarray, T_OM_F: np.ndarray) -> np.ndarray:
    """``T_B_F`` (4x4, m): the model's Center frame in the robot base. The tracked opener
    pose is checked, never repaired: the tracker publishes rigid poses (to about 1e-15),
    so one that is not rigid is a fault to stop on (``GeometryError``)."""
    return T_B_C @ as_transform(T_C_OM, what="T_C_OM") @ T_OM_F


def fixture_dict(fx: VirtualFixture) -> dict[str, Any]:
    """The fixture as the operator sees it, frame ``F``, metres."""
    return {"frame": "F", "target": fx.target.tolist(), "direction": fx.direction.tolist(),
            "cylinder_radius": fx.cylinder_radius, "cylinder_length": fx.cylinder_length,
            "cones": [list(c) for c in fx.cones]}


@dataclass(frozen=True, eq=False)
class GuideDraft:
    """A planned insertion the daemon holds until ``/guide/start``: the scene it came
    from, the placement, the control loop's plan and the registration ``T_OM_F`` (m)."""

    scene: Path
    source: str
    placement: Placement
    plan: GuidePlan
    T_OM_F: np.ndarray
    by: str
    seed: int | None
    planned_at: float = field(default_factory=time.time)   # wall clock, s since the epoch

    def summary(self) -> dict[str, Any]:
        """JSON-able: what ``POST /guide/plan`` answers and ``GET /guide`` shows."""
        p = self.placement
        return {"scene": str(self.scene), "model": self.source, "by": self.by,
                "seed": self.seed, "planned_at": self.planned_at,
                "placement": p.to_dict(), "T_F_tool": p.T_C_tool.tolist(),
                "fixture": fixture_dict(self.plan.fixture),
                "rod_radius": self.plan.rod_radius,
                "alarm_distance": self.plan.alarm_distance,
                "T_OM_F": self.T_OM_F.tolist()}


def plan_insertion(scene: str | Path, T_OM_F: Any, who: str,
                   seed: int | None = None) -> GuideDraft:
    """Load the planning scene, place the instrument (PSO; ``seed`` overrides the scene's),
    and build the plan with its default fixture. Blocking: a mesh scene is fitted here
    (about a second); call it from a worker thread.

    Raises :class:`GuidePlanError` for a bad scene, registration or planning input, and
    :class:`NoSafePlacement` when nothing collision-free was found.
    """
    T_OM_F = check_registration(T_OM_F)
    path = Path(scene)
    try:
        sc = load_planning_scene(path)
    except ConfigError as exc:
        raise GuidePlanError(f"planning scene: {exc}") from None
    except (ControlError, OSError) as exc:
        raise GuidePlanError(f"planning scene {path}: {exc}") from None
    settings = sc.settings
    if seed is not None:
        settings = replace(settings, pso=replace(settings.pso, seed=int(seed)))
    try:
        # one certified clearance check serves the placement and the plan's rod alarm
        # (building it is most of the planning time); an uncertified model gets none
        # here, and the plan refuses it below
        check = RodCheck(sc.model) if sc.model.certificate is not None else None
        p = place(sc.model, sc.hole, settings, check=check)
    except ControlError as exc:
        raise GuidePlanError(f"placement in {path}: {exc}") from None
    if not p.collision_free:
        raise NoSafePlacement(
            f"no collision-free placement in {path}: {p.reason} (best found: d_T = "
            f"{p.d_T * 1e3:.1f} mm, theta_T = {math.degrees(p.theta_T):.1f} deg); nothing "
            "was armed. Move the hole, widen the search or use a thinner instrument", p)
    try:
        plan = GuidePlan(p.T_C_tool, sc.model, settings.rod_radius, check=check)
    except ControlError as exc:
        raise GuidePlanError(f"plan from {path}: {exc}") from None
    return GuideDraft(path, sc.source, p, plan, T_OM_F, who, seed)
