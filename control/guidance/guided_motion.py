"""Guided insertion along the planned axis: the virtual fixture's admittance in the robot's
control loop, with the surrogate model as a live collision alarm for the rod (seed 004,
§2.2 and §5.3).

Frames: ``F`` is the surrogate model's Center frame, fixed to the patient (the paper
describes all motion relative to the oral cavity); ``B`` the robot base. ``T_B_F`` comes
from navigation every period, so the fixture moves with the patient's head. The plan
(:class:`GuidePlan`) is the placement's tool frame ``T_F_tool`` (eq. 18): the instrument's
head enters along its rod, the rod being the tool x axis (line1 of eq. 19), until the head
reaches the tool origin. The fixture is therefore the cylinder and cones around the tool
x axis ending at the tool origin (:meth:`GuidePlan.fixture_for`), the commanded point is
the TCP (the instrument head) and the TCP's orientation is held at the planned one.

Per period (:meth:`GuidedMotion.step`): the sensor's force, rotated into ``F``, drives
the admittance (:mod:`oralnav.control.guidance.admittance`); the commanded head position goes back
to ``B`` with the planned orientation. Independently, the rod at the *measured* TCP pose
is checked against the tissue by the certified rod clearance
(:mod:`oralnav.control.planning.rod_check`; the plan's model must carry a certificate): when the
rod cannot be certified ``alarm_distance`` clear the step reports it, and the control
loop stops the arm. Only the rod's part inside the modelled cavity counts: out in front of
the mouth (beyond the model's front) nothing is checked; behind its back end is tissue.

Pure math: no I/O, no clock (the caller passes ``dt``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from oralnav.control.errors import PlanningError
from oralnav.control.guidance.admittance import (
    AdmittanceController,
    AdmittanceSettings,
    AdmittanceState,
)
from oralnav.control.guidance.virtual_fixture import VirtualFixture
from oralnav.control.planning.fpsm import FPSM
from oralnav.control.planning.placement import LINE_LENGTH
from oralnav.control.planning.rod_check import RodCheck


@dataclass(frozen=True, eq=False)
class GuidePlan:
    """A planned insertion: ``T_F_tool`` (4x4, m) from the placement, the model for the
    alarm, the rod radius and the alarm bound (m), the fixture and admittance settings."""

    T_F_tool: np.ndarray
    model: FPSM
    rod_radius: float
    alarm_distance: float = 0.0
    fixture: VirtualFixture | None = None
    admittance: AdmittanceSettings = AdmittanceSettings()
    check: RodCheck | None = None      # built from the model when not given (~0.3 s)

    def __post_init__(self) -> None:
        T = np.asarray(self.T_F_tool, dtype=float)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise PlanningError("T_F_tool must be a finite 4x4 transform")
        R = T[:3, :3]
        if np.max(np.abs(R.T @ R - np.eye(3))) > 1e-6 or np.linalg.det(R) <= 0:
            raise PlanningError("T_F_tool's rotation block is not a rotation")
        if not (self.rod_radius >= 0 and np.isfinite(self.alarm_distance)):
            raise PlanningError("rod_radius must be >= 0 and alarm_distance finite (m)")
        object.__setattr__(self, "T_F_tool", T)
        if self.model.certificate is None:
            raise PlanningError(
                "a guided insertion needs a certified surrogate model (fitted to slab "
                "envelopes): the rod alarm must hold for the tissue, not only the model")
        if self.check is None:
            object.__setattr__(self, "check", RodCheck(self.model))
        if self.fixture is None:
            object.__setattr__(self, "fixture", self.fixture_for(T, self.model))

    @staticmethod
    def fixture_for(T_F_tool: np.ndarray, model: FPSM, lateral: float = 0.0005,
                    cone_half_angle_deg: float = 20.0, cone_length: float = 0.08
                    ) -> VirtualFixture:
        """The default fixture for a plan: a cylinder of ``lateral`` radius (m) along the
        rod from the head's target out to where the rod leaves the model (the mouth), then
        one cone of ``cone_half_angle_deg`` widening over ``cone_length`` (m) outside it."""
        head = T_F_tool[:3, 3]
        out = T_F_tool[:3, 0]
        if out[2] > 1e-9:      # how far along the rod until it passes the last slice
            inside = max((model.z[-1] - head[2]) / out[2], 0.005)
        else:
            inside = 0.05
        widen = lateral + cone_length * np.tan(np.radians(cone_half_angle_deg))
        return VirtualFixture.from_axis(head, out, lateral, float(inside),
                                        cones=[(cone_length, float(widen))])


class GuideStep(NamedTuple):
    setpoint: np.ndarray            # T_B_tcp to servo to (4x4, m)
    state: AdmittanceState          # the admittance's commanded point, in F
    rod_distance: float             # certified clearance of the rod at the measured pose (m)
    alarm: str | None               # why the arm must stop, or None


class GuidedMotion:
    """The admittance-driven insertion of one plan; see the module docstring."""

    def __init__(self, plan: GuidePlan) -> None:
        self.plan = plan
        self.controller = AdmittanceController(plan.admittance, plan.fixture)
        self._R_F_tool = plan.T_F_tool[:3, :3].copy()
        self._started = False

    @property
    def started(self) -> bool:
        return self._started

    def start(self, T_B_tcp: np.ndarray, T_B_F: np.ndarray) -> AdmittanceState:
        """Begin from the measured TCP, which must already be inside the fixture (the
        controller never jumps the arm onto it: :class:`AdmittanceError` otherwise)."""
        p_F = _inv_apply(T_B_F, np.asarray(T_B_tcp, dtype=float)[:3, 3])
        st = self.controller.reset(p_F)
        self._started = True
        return st

    def finish(self) -> None:
        """End this insertion: the next :meth:`start` begins afresh from the measured TCP."""
        self._started = False

    def rod_distance(self, T_F_tcp: np.ndarray) -> float:
        """Certified clearance (m) of the rod at the TCP pose ``T_F_tcp``: the rod of the
        plan's radius along the TCP's x axis from ``r`` off its origin (eq. 19's line1),
        out to where it leaves the model's front (:mod:`oralnav.control.planning.rod_check`).
        ``inf`` while the head is out in front of the mouth; exact only down to the alarm
        bound (a value below it says only that the rod is not certified that clear)."""
        r = self.plan.rod_radius
        x = T_F_tcp[:3, 0]
        P = T_F_tcp[:3, 3] + r * x
        return self.plan.check.clearance(P, P + LINE_LENGTH * x, r, self.plan.alarm_distance)

    def step(self, force_B: np.ndarray, T_B_F: np.ndarray, T_B_tcp_measured: np.ndarray,
             dt: float) -> GuideStep:
        """One control period: force (N, base frame, 3 or 6 values: the torque is not
        used), the patient's model frame and the measured TCP in the base, ``dt`` s."""
        if not self._started:
            raise PlanningError("guided motion stepped before start()")
        T_B_F = np.asarray(T_B_F, dtype=float)
        R_B_F = T_B_F[:3, :3]
        f_F = R_B_F.T @ np.asarray(force_B, dtype=float)[:3]
        st = self.controller.step(f_F, dt)
        setpoint = np.eye(4)
        setpoint[:3, :3] = R_B_F @ self._R_F_tool
        setpoint[:3, 3] = R_B_F @ st.position + T_B_F[:3, 3]
        T_F_tcp = np.eye(4)
        Tm = np.asarray(T_B_tcp_measured, dtype=float)
        T_F_tcp[:3, :3] = R_B_F.T @ Tm[:3, :3]
        T_F_tcp[:3, 3] = R_B_F.T @ (Tm[:3, 3] - T_B_F[:3, 3])
        dmin = self.rod_distance(T_F_tcp)
        alarm = None
        if not dmin >= self.plan.alarm_distance:
            alarm = (f"rod collision alarm: the rod is not certified "
                     f"{self.plan.alarm_distance * 1e3:.2f} mm clear of the tissue "
                     f"(bound {dmin * 1e3:.2f} mm)")
        return GuideStep(setpoint, st, dmin, alarm)


def _inv_apply(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    T = np.asarray(T, dtype=float)
    return T[:3, :3].T @ (np.asarray(p, dtype=float) - T[:3, 3])
