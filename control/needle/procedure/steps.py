"""The needle procedure's steps NG, NH, ND, NR and NP as a state machine on one cell
(:class:`NeedleProcedure`; the package docstring describes them). Reference frame, m,
rad."""

from __future__ import annotations

import copy
import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from typing import Any

import cv2
import numpy as np

from oralnav.control.errors import NeedleError, StepOrderError
from oralnav.control.geometry import invert, rotation_angle
from oralnav.control.needle.drive import Drive, SutureGeometry, pull_poses
from oralnav.control.needle.features import NeedleFeatures
from oralnav.control.needle.grasp import (
    GraspChoice,
    SurfaceGrasp,
    check_drive_grasp,
    grasp_parameters,
    grasp_point_angle,
    select_grasp,
    surface_grasps,
)
from oralnav.control.needle.procedure.actions import CellActions
from oralnav.control.needle.procedure.cell import NeedleCellPort
from oralnav.control.needle.procedure.feed import FeedFactory
from oralnav.control.needle.procedure.planning import (
    _arc_under,
    _driver_choice,
    _handoff_poses,
    _meetings,
    _pickup_phis,
    _tip_grasps,
    drive_pick,
    drive_ways,
    tip_part,
)
from oralnav.control.needle.procedure.poses import _BACK_OFF_TILTS, _path, back_off, translation
from oralnav.control.needle.procedure.results import STEPS, StepFailed, StepResult, _refuse
from oralnav.control.needle.procedure.settings import ProcedureSettings
from oralnav.control.needle.procedure.views import ViewRule, _shifted, _turned_and_raised
from oralnav.control.needle.servo import DriveServo, Seen, ServoStop
from oralnav.control.needle.tracker import (
    FilterSettings,
    NeedleTrack,
    NeedleTracker,
    TissuePlane,
    TrackSettings,
)
from oralnav.control.vision.camera import CameraModel

#: A check of a step's result against what the procedure cannot see (the simulator's
#: ground truth): called with the procedure and the result after every step; it fills
#: ``truth_ok`` and ``truth_detail`` and may add figures.
StepCheck = Callable[["NeedleProcedure", StepResult], None]


#: How far (m) a needle's grasp as the views see it may be off (one sigma): what the
#: servoed drive's model allows besides the arms' accuracy (the tracker's sigmas at a
#: hold check, 0.1-0.2 mm, and its biases beside the jaws, up to twice that).
GRASP_SEEN = 0.0003
#: How far (m) a gripper works from its arm's RCM, at most: the lever by which the arm's
#: rotation error moves the needle (the trial cells' ports lie 100-160 mm from the pad).
ARM_LEVER = 0.16
#: How many commands a streamed frame may be behind the arm: the tracking task captures
#: the next frame while it tracks the last, so the newest frame the step takes was
#: captured up to two commands before the one it answers.
STREAM_LAG = 2


def _off_at_needle(accuracy: tuple[float, float] | None) -> float:
    """How far (m) arms of ``accuracy`` (m, rad; ``None``: exact) may put the needle off:
    their shift and their rotation over ``ARM_LEVER``."""
    shift, turn = accuracy or (0.0, 0.0)
    return shift + turn * ARM_LEVER


def _drifts(accuracy: tuple[float, float] | None) -> dict[str, float]:
    """The tracker's motion-size drifts for arms of ``accuracy`` (m, rad): a turn of the
    gripper swings the arm's error at the needle round; a travel is off by the rotation
    error's share."""
    if accuracy is None:
        return {}
    return {"turn_drift": _off_at_needle(accuracy), "travel_drift": accuracy[1]}


def _pose_name(k: int, n: int) -> str:
    """Drive pose ``k`` of ``n`` as a message names it (0: the approach)."""
    return "the approach" if k == 0 else f"drive pose {k} of {n}"


class _ServoRun:
    """A servoed drive's state between looks: the :class:`DriveServo`, the reported tool
    at the tracker's last look (``at_frame``), the last look (``looked``) and the last
    one the servo used (``used``), each ``(drive pose, applied correction)``, and the
    tallies; :meth:`take` applies the guards' rules to one look, whichever way the looks
    come (stopped to look, or streamed)."""

    def __init__(self, servo: DriveServo, at_frame: np.ndarray) -> None:
        self.servo = servo
        self.at_frame = at_frame
        self.looked: tuple[int, np.ndarray] | None = None
        self.used: tuple[int, np.ndarray] | None = None
        self.errors: list[float] = []
        self.blind = self.unused = 0
        self.lost_run = 0               # lost looks since the last one used

    def motion_to(self, k: int, D: np.ndarray, tool: np.ndarray,
                  since: tuple[int, np.ndarray] | None) -> np.ndarray:
        """The needle's motion to pose ``k`` with correction ``D`` (the reported tool then
        ``tool``) from look ``since``: as the servo's model predicts it, or, before any
        look, the reported tool's motion since :attr:`at_frame`."""
        if since is None:
            return tool @ invert(self.at_frame)
        return self.servo.predicted(k, D) @ invert(self.servo.predicted(*since))

    def take(self, k: int, seen: Seen, now: float, tool: np.ndarray, D: np.ndarray,
             where: str, weight: float = 1.0, lost_allowed: int = 0) -> bool:
        """Give the servo ``seen``, a look at pose ``k`` with correction ``D`` (the
        reported tool ``tool``), at time ``now`` (s), weighed ``weight``
        (:meth:`DriveServo.update`). False where the look is not used: uncertain, or
        implausibly far off for the arms' accuracy (the model carries on: a constant
        shift only, while its looks have spanned little of the turn), or lost before the
        servo has used any (nothing it commands rests on it; the arm goes on as planned
        until a look it can use), or one of up to ``lost_allowed`` lost looks in a row
        since the last one used (a stream's frames: see ``_drive_streamed``). Any other
        stop of the servo, and a lost track once it has started, fails the step
        (``servo_<cause>``, at ``where``)."""
        # the jump guard's motion: since the last look used (none before the first)
        motion = self.motion_to(k, D, tool, self.used)
        try:
            self.errors.append(self.servo.update(k, seen, now, motion, D, weight))
        except ServoStop as exc:
            if exc.cause in ("uncertain", "implausible"):
                self.blind += 1
                return False
            if exc.cause == "lost" and self.used is None:
                self.unused += 1
                return False
            if exc.cause == "lost" and self.lost_run < lost_allowed:
                self.lost_run += 1
                self.unused += 1
                return False
            raise StepFailed(f"servo_{exc.cause}", f"{where}: {exc.detail}"
                             + (f" ({self.lost_run + 1} frames lost in a row)"
                                if exc.cause == "lost" and lost_allowed else "")) from None
        self.used = (k, D)
        self.lost_run = 0
        return True


class NeedleProcedure(CellActions):
    """The five steps on one cell (see :mod:`oralnav.control.needle.procedure`).

    ``incision`` (2, 3): the suture line's start and end on the tissue surface, ``ref``
    frame (m): the operator's input (seed 002 finds it by vision); ``surface_normal``
    (3,): the tissue surface's normal, out of the tissue. ``surface_outline`` (k, 3),
    optional: the tissue surface's corners in order (a convex polygon, ``ref``); when
    given, the needle is only carried where both cameras see it against the tissue (the
    thin-feature measurement finds a wire darker than what lies behind it).
    ``arms``: the two grippers to use (default: the cell's). ``truth_check``, optional:
    checks each step's result against a ground truth the procedure does not see (the
    simulator's; :data:`StepCheck`), where the caller has one. ``feed``, optional: starts
    a tracking task (:data:`~oralnav.control.needle.procedure.feed.FeedFactory`, the
    realtime layer's :func:`~oralnav.realtime.needle_tracking.start_tracking`); with it a
    servoed drive (``settings.drive_servo``) tracks every frame while the arm moves and
    corrects at the tracker's rate where the views show the arc, instead of stopping to
    look every ``servo_every`` poses. The steps run in order, each
    once: :meth:`run` refuses a step out of turn (:class:`~oralnav.control.errors.StepOrderError`).
    """

    def __init__(self, cell: NeedleCellPort, incision: np.ndarray, surface_normal: np.ndarray,
                 settings: ProcedureSettings | None = None,
                 arms: Sequence[str] | None = None,
                 surface_outline: np.ndarray | None = None,
                 truth_check: StepCheck | None = None,
                 feed: FeedFactory | None = None) -> None:
        self.cell = cell
        self.truth_check = truth_check
        self.feed = feed
        self.s = s = settings or ProcedureSettings()
        inc = np.asarray(incision, dtype=float)
        n = np.asarray(surface_normal, dtype=float).reshape(3)
        if inc.shape != (2, 3) or not np.all(np.isfinite(inc)):
            raise NeedleError(f"needle procedure: the incision must be 2 finite 3-D points, "
                              f"got shape {inc.shape}")
        norm = float(np.linalg.norm(n))
        if not (math.isfinite(norm) and norm > 1e-9):
            raise NeedleError("needle procedure: the surface normal is zero or not finite")
        self.incision, self.normal = inc, n / norm
        self.outline: np.ndarray | None = None
        if surface_outline is not None:
            o = np.asarray(surface_outline, dtype=float)
            if o.ndim != 2 or o.shape[1] != 3 or len(o) < 3 or not np.all(np.isfinite(o)):
                raise NeedleError(f"needle procedure: the surface outline must be >= 3 finite "
                                  f"3-D points, got shape {o.shape}")
            self.outline = o
        self.arms = tuple(arms) if arms is not None else tuple(cell.grippers)
        if len(self.arms) != 2 or len(set(self.arms)) != 2:
            raise NeedleError(f"needle procedure: needs two distinct arms for the hand-off, "
                              f"got {list(self.arms)} (a one-arm cell cannot run NH)")
        for a in self.arms:
            if a not in cell.grippers:
                raise NeedleError(f"needle procedure: unknown arm {a!r}; the cell has "
                                  f"{list(cell.grippers)}")
        self.needle = cell.needle
        self.cams: list[CameraModel] = [cell.rig[c] for c in cell.cameras]
        self.tracker = NeedleTracker(
            self.needle, self.cams, FilterSettings(particles=s.particles, seed=s.seed),
            settings=TrackSettings(max_sigma_position=s.max_sigma_position,
                                   max_sigma_angle=s.max_sigma_angle,
                                   **_drifts(s.arm_accuracy)))
        self.park = {a: cell.gripper_pose(a) for a in self.arms}
        # the incision's depth sets the features' wire width and the search depth
        mid = inc.mean(axis=0)
        self._wire_px, self._masks = [], []
        for cam in self.cams:
            z = float((cam.T_cam_ref[:3, :3] @ mid + cam.T_cam_ref[:3, 3])[2])
            if z <= 0:
                raise NeedleError(f"needle procedure: the incision is behind camera "
                                  f"{cam.name!r}")
            self._wire_px.append(cam.K[0, 0] * self.needle.wire_diameter / z)
            uv = cam.project_from(cam.T_cam_ref, inc)
            m = np.zeros((cam.height, cam.width), np.uint8)
            if np.all(np.isfinite(uv)):
                a, b = (tuple(int(v) for v in np.round(p)) for p in uv)
                cv2.line(m, a, b, 1, int(s.incision_mask_px))
            self._masks.append(m.astype(bool))
        self.views = ViewRule(self.cams, self.needle, s, self.normal, self.outline,
                              self._masks)
        self.tracker.set_surface_outline(self.outline)
        self.tracker.set_ignored(self._masks)
        z_ref = float(mid[2])
        self._depth_range = (max(z_ref - s.depth_window, 0.01), z_ref + s.depth_window)
        # state
        self.results: dict[str, StepResult] = {}
        self.refusals: list[StepResult] = []
        self.track: NeedleTrack | None = None
        self.G_CS: np.ndarray | None = None
        self.geometry: SutureGeometry | None = None
        self.drive: Drive | None = None
        self.drive_choice: GraspChoice | None = None
        self.driver: str | None = None
        self.picker: str | None = None
        self.holder: str | None = None        # who the procedure believes holds the needle
        # the regrasp's pull plan and where the needle lay when the jaws closed (NR to NP)
        self._pull: tuple[Any, np.ndarray] | None = None
        self.G_TN: np.ndarray | None = None   # its grasp, as last seen by the tracker
        self.tip_plan: np.ndarray | None = None  # where the drive should leave the tip (ref)
        self.in_tissue = False
        # whether the driver's path to a hand-off pose is clear, by start and goal
        self._driver_paths: dict[tuple[bytes, bytes], str] = {}

    # -- public ---------------------------------------------------------------------------
    @property
    def next_step(self) -> str | None:
        """The step that may run now (``None``: all done, or a step failed)."""
        for st in STEPS:
            r = self.results.get(st)
            if r is None:
                return st
            if not r.ok:
                return None
        return None

    def run(self, step: str) -> StepResult:
        """Run ``step`` (one of :data:`STEPS`, in order). Raises :class:`StepOrderError` for a
        step out of turn or after a failure; otherwise returns the result, refusals and
        failures included. A refused step is not done: it may be asked again
        (:attr:`refusals` keeps the refusals); a failed one ends the procedure."""
        step = step.upper()
        if step not in STEPS:
            raise StepOrderError(f"unknown needle step {step!r}; the steps are {list(STEPS)}")
        nxt = self.next_step
        if step != nxt:
            if nxt is None:
                failed = [k for k, r in self.results.items() if not r.ok]
                why = (f"step {failed[0]} failed ({self.results[failed[0]].detail})"
                       if failed else "all steps are done")
                raise StepOrderError(f"needle step {step} cannot run: {why}; load a new cell")
            raise StepOrderError(f"needle step {step} cannot run yet: {nxt} comes first")
        t0 = time.perf_counter()
        res = StepResult(step, ok=False)
        try:
            figures = getattr(self, f"_step_{step.lower()}")()
            res.ok, res.figures = True, figures
        except StepFailed as exc:
            res.cause, res.detail, res.refused = exc.cause, exc.detail, exc.refused
        res.seconds = round(time.perf_counter() - t0, 3)
        if self.truth_check is not None:
            # the caller's ground truth, for its success counts: never for control
            self.truth_check(self, res)
        if res.refused:
            # nothing moved toward the needle: the step may be asked again (after the
            # operator fixed the cause, or the tracker had more frames)
            self.refusals.append(res)
        else:
            self.results[step] = res
        return res

    def run_all(self) -> list[StepResult]:
        """Run the steps in order until one fails or refuses; the results of those that
        ran."""
        out = []
        while (st := self.next_step) is not None:
            out.append(self.run(st))
            if not out[-1].ok:
                break
        return out

    def status(self) -> dict[str, Any]:
        """JSON-able: next step, results so far, the roles of the arms, the last track."""
        tr = self.track
        return {"next": self.next_step, "arms": {"picker": self.picker, "driver": self.driver,
                                                 "holder": self.holder},
                "results": {k: r.to_json() for k, r in self.results.items()},
                "last_refusal": self.refusals[-1].to_json() if self.refusals else None,
                "track": None if tr is None else {
                    "converged": tr.converged, "reason": tr.reason,
                    "T_ref_N": tr.pose.tolist(), "swage": round(tr.swage, 2)}}

    # -- planning -------------------------------------------------------------------------
    def _plan(self) -> dict[str, Any]:
        """The suture and the driving arm with its grasp (before anything moves).

        The needle crosses the incision from the side its direction sets (entry at -x_S).
        Where no arm can drive it that way, the drive runs the other way across the same
        point (the incision's ends swapped): a backhand stitch for a forehand one, the
        same suture, with the wrist turning the other way about the incision."""
        s, inc = self.s, self.incision
        try:
            self.geometry = SutureGeometry.for_needle(self.needle, s.depth)
        except NeedleError as exc:
            raise _refuse("bad_suture", str(exc)) from None
        try:
            ways = drive_ways(inc, self.normal, self.geometry, s)
        except NeedleError as exc:
            raise _refuse("bad_suture", str(exc)) from None
        try:
            pick = drive_pick(s)
            chosen, self.driver, self.drive_choice = _driver_choice(ways, {
                a: (lambda k, a=a: select_grasp(self.needle, ways[k][2], pick, reachable=(
                    lambda T: self._reach(a, [T])[0]))) for a in self.arms})
        except NeedleError as exc:
            raise _refuse("out_of_reach", str(exc)) from None
        self.picker = next(a for a in self.arms if a != self.driver)
        way, self.G_CS, self.drive = chosen
        return {"driver": self.driver, "picker": self.picker, "drive_direction": way,
                "drive_grasp_phi_deg": round(math.degrees(self.drive_choice.phi), 2),
                "entry_ref": self._to_ref(self.geometry.entry).tolist(),
                "exit_ref": self._to_ref(self.geometry.exit).tolist()}

    def _to_ref(self, p_S: np.ndarray) -> np.ndarray:
        assert self.G_CS is not None
        return self.G_CS[:3, :3] @ p_S + self.G_CS[:3, 3]

    def planned_crossings(self) -> tuple[np.ndarray, np.ndarray]:
        """The planned entry and exit points (3, each; ``ref``, m) where the suture crosses
        the tissue surface; once NG has planned it."""
        assert self.geometry is not None
        return self._to_ref(self.geometry.entry), self._to_ref(self.geometry.exit)

    # -- the steps ------------------------------------------------------------------------
    def _step_ng(self) -> dict[str, Any]:
        s = self.s
        figures = self._plan()
        T_N = self._converged("grasp", init=True, static=False)
        assert self.drive_choice is not None and self.picker is not None
        arm = self.picker
        phis = _pickup_phis(self.needle, s, self.drive_choice.phi)
        if not phis.size:
            raise _refuse("no_grasp", "no part of the needle is free for the pick-up grasp "
                                      f"{s.separation * 1e3:.1f} mm from the driving grasp")
        point = self.incision.mean(axis=0)
        why: dict[str, int] = {}
        handoffs = self._handoff_candidates()
        chosen: tuple[SurfaceGrasp, np.ndarray, int] | None = None
        # of the grasps the arm reaches and sees past, the first that also has
        # handoff_meetings hand-off poses, else the one with the most: the pick-up
        # decides how the needle sits in the holder's jaws, and so where the two arms can
        # meet. The full lift first; a needle near the pad's edge, lifted that far, may
        # stand against the dark beyond it, and a lower lift keeps it against the tissue
        grasps = [g for phi in phis for g in surface_grasps(
            self.needle, T_N, float(phi), point, self.normal, s.pickup_grasp)]
        grasps.sort(key=lambda g: -g.elevation)
        for lift in sorted({s.lift, min(s.lift, s.lift_low)}, reverse=True):
            up = translation(lift * self.normal)
            for g in grasps:
                ok, _ = self._reach(arm, [g.T_ref_T, back_off(g.T_ref_T, s.approach),
                                          up @ g.T_ref_T])
                if not ok:
                    why["out of reach"] = why.get("out of reach", 0) + 1
                    continue
                seen = self._view(up @ T_N, [up @ g.T_ref_T])
                if seen:
                    why[f"lifted needle {seen}"] = why.get(f"lifted needle {seen}", 0) + 1
                    continue
                n = len(self._meetings(g.G_TN, handoffs, up @ g.T_ref_T, why,
                                       s.handoff_meetings))
                if n and (chosen is None or n > chosen[2]):
                    chosen = (g, up, n)
                if n >= s.handoff_meetings:
                    break
            if chosen is not None and chosen[2] >= s.handoff_meetings:
                break
        if chosen is None:
            raise _refuse("out_of_reach", f"arm {arm!r} has no pick-up grasp of the tracked "
                                          f"needle that leads to a hand-off ("
                                          + ", ".join(f"{k}: {v}" for k, v in why.items())
                                          + ")")
        g, up, meetings = chosen
        self._move(arm, back_off(g.T_ref_T, s.approach), "pick-up approach")
        self._move(arm, g.T_ref_T, "pick-up reach")
        self._jaws(arm, True, "pick-up: closing the jaws")
        T_N = self._verify_hold(arm, up @ self.cell.gripper_pose(arm), "pick-up")
        self.holder, self.G_TN = arm, self._grasp_seen(arm, T_N)
        figures.update(arm=arm, grasp_phi_deg=round(math.degrees(g.params.phi), 2),
                       shaft_elevation_deg=round(math.degrees(g.elevation), 1),
                       pickup_candidates=len(grasps), handoff_meetings=meetings,
                       lift_mm=round(float(up[:3, 3] @ self.normal) * 1e3, 1))
        return figures

    def _handoff_candidates(self) -> list[tuple[np.ndarray, np.ndarray, float, float]]:
        """The hand-off poses the driver reaches (:func:`_handoff_poses`)."""
        B = self.driver
        assert self.drive is not None and self.drive_choice is not None and B is not None
        m = self.s.reach_margin
        return _handoff_poses(self.drive, self.drive_choice.G_TN, self.normal, self.s,
                              lambda T: self.cell.reachable_all(B, T, m),
                              self.views.aim(self.incision.mean(axis=0)))

    def _meetings(self, G_TN_A: np.ndarray, handoffs: Sequence[tuple],
                  T_A0: np.ndarray | None, why: dict[str, int], most: int = 1) -> list[tuple]:
        """:func:`_meetings` for the picker on this cell, its plans' margin; the driver
        must also reach the hand-off's approach and grasp from where it stands on
        :meth:`_driver_path` (it waits until the needle is there)."""
        A, B = self.picker, self.driver
        assert A is not None and B is not None
        m = self.s.reach_margin
        T_B0 = self.cell.gripper_pose(B)

        def driver_path(item: tuple) -> str:
            # the same for every pick-up grasp NG weighs: asked once per pose
            key = (T_B0.tobytes(), item[1].tobytes())
            if key not in self._driver_paths:
                ok = self.cell.reachable_all(B, np.stack(self._driver_path(T_B0, item[1])),
                                             m).all()
                self._driver_paths[key] = "" if ok else f"{B} cannot get there"
            return self._driver_paths[key]
        return _meetings(handoffs, G_TN_A, lambda T: self.cell.reachable_all(A, T, m),
                         self.views, most, T_A0, why, A, driver_path)

    def _driver_path(self, T0: np.ndarray, T_B: np.ndarray) -> list[np.ndarray]:
        """The driver's straight path from ``T0`` to the hand-off's approach, then in
        to its grasp ``T_B`` (the moves NH makes)."""
        approach = back_off(T_B, self.s.approach)
        return _path(T0, approach) + _path(approach, T_B)

    def _step_nh(self) -> dict[str, Any]:
        s = self.s
        A, B = self.picker, self.driver
        assert A is not None and B is not None and self.drive_choice is not None
        T_N = self._converged("hand-off")
        G_TN_A = self._grasp_seen(A, T_N)
        phi_A = grasp_point_angle(G_TN_A, self.needle, s.pickup_grasp.theta0)
        gap = abs(phi_A - self.drive_choice.phi) * self.needle.radius
        if gap < s.separation:
            raise _refuse("no_grasp", f"the needle sits in {A!r}'s jaws {gap * 1e3:.1f} mm "
                                      f"from the driving grasp (needs {s.separation * 1e3:.1f}"
                                      " mm): the jaws would meet")
        why: dict[str, int] = {}
        handoffs = self._handoff_candidates()
        found = self._meetings(G_TN_A, handoffs, self.cell.gripper_pose(A), why)
        if not found:
            raise _refuse("out_of_reach", f"none of {len(handoffs)} hand-off poses the driver "
                                          "reaches suits the holder and the cameras ("
                                          + ", ".join(f"{k}: {v}" for k, v in why.items())
                                          + ")")
        item = found[0]
        T_h = item[0]
        figures: dict[str, Any] = {"handoff_height_mm": round(item[3] * 1e3, 1),
                                   "handoff_turn_deg": round(math.degrees(item[2]), 1)}
        T0 = self.cell.gripper_pose(A)
        self._carry(A, T_h @ invert(G_TN_A), G_TN_A, "carry to the hand-off pose")
        delta = self.cell.gripper_pose(A) @ invert(T0)
        tr = self._look(delta)
        if not tr.converged:
            raise StepFailed("lost_track", f"hand-off: the tracker lost the needle at the "
                                            f"hand-off pose ({tr.reason})")
        T_B = tr.pose @ invert(self.drive_choice.G_TN)
        ok, why = self._reach(B, self._driver_path(self.cell.gripper_pose(B), T_B), 0.0)
        if not ok:
            raise StepFailed("out_of_reach", f"hand-off: {B!r} cannot reach the needle where "
                                              f"it was carried ({why})")
        self._move(B, back_off(T_B, s.approach), "hand-off approach")
        self._move(B, T_B, "hand-off reach")
        self._jaws(B, True, "hand-off: the driver closing its jaws")
        self._jaws(A, False, "hand-off: the picker opening its jaws")
        self.holder = B
        for goal, what in ((back_off(self.cell.gripper_pose(A), s.retreat), "back off"),
                           (self.park[A], "park")):
            try:
                self.cell.move(A, goal)
            except Exception as exc:   # an open gripper that stops short holds nothing
                figures[f"{A}_{what.replace(' ', '_')}"] = str(exc)
        T_N = self._verify_hold(B, self._check_motion(B, T_N), "hand-off")
        self.G_TN = self._grasp_seen(B, T_N)
        fit = grasp_parameters(self.G_TN, self.needle.radius)
        figures.update(grasp_phi_deg=round(math.degrees(fit.params.phi), 2),
                       planned_phi_deg=round(math.degrees(self.drive_choice.phi), 2),
                       grasp_tilt_deg=round(math.degrees(fit.tilt), 2),
                       grasp_offset_mm=round(fit.offset * 1e3, 3))
        return figures

    def _step_nd(self) -> dict[str, Any]:
        B = self.driver
        assert B is not None and self.drive is not None and self.geometry is not None
        T_N = self._converged("drive")
        drive, choice = self._drive_on(B, T_N)
        approach = self._approach(drive, B)
        T0 = self.cell.gripper_pose(B)
        assert self.G_TN is not None
        self._carry(B, approach, self.G_TN, "drive approach")
        # look again just before entering: the grasp may have slipped on the way
        tr = self._look(self.cell.gripper_pose(B) @ invert(T0))
        approach_look = tr.converged
        if tr.converged:
            # the look low over the tissue, across the masked incision, with the jaws
            # near the surface, is the worst of the procedure's: it refines the drive
            # only where it agrees with the grasp seen before the approach, which the
            # jaws carried rigidly; a larger change is more likely its error than a slip
            # (a slip the exit check after the drive still catches)
            G_new = self._grasp_seen(B, tr.pose)
            assert self.G_TN is not None
            shift = float(np.linalg.norm(G_new[:3, 3] - self.G_TN[:3, 3]))
            turn = rotation_angle(G_new[:3, :3], self.G_TN[:3, :3])
            approach_look = shift <= self.s.replan_shift and turn <= self.s.replan_turn
            if approach_look:
                drive, choice = self._drive_on(B, tr.pose)
        # else: the gripper may hide the needle here; the grasp seen before the approach
        # moved rigidly with the jaws, so the drive keeps it
        servoed, moved = self._drive_along(B, drive, self.cell.gripper_pose(B))
        self.in_tissue = True
        # from here the tissue hides the needle's middle: the tracker must not take it
        # for missing wire
        self.tracker.set_occluder(TissuePlane(self.incision.mean(axis=0), self.normal))
        tr = self._look(moved)
        tip_plan = drive.G_PS @ drive.G_SN[-1]
        tip_plan = tip_plan[:3, :3] @ self.needle.tip + tip_plan[:3, 3]
        tip_seen = tr.pose[:3, :3] @ self.needle.tip + tr.pose[:3, 3]
        # the drive is judged once the released gripper has backed off (NR, before any
        # arm reaches for the tip): with the jaws still on the needle, which hide much
        # of what the tissue leaves visible, the tracker may not converge, and when it
        # does its crossings were 2-4 mm off on 3 of 40 trials whose truth lay within
        # 0.1 mm of the plan. What it sees here is reported
        self.tip_plan = tip_plan
        seen = self._exit_error(tr.pose, "drive") if tr.converged else None
        return {**servoed, "grasp_phi_deg": round(math.degrees(choice.phi), 2),
                "min_tip_clearance_mm": round(choice.min_tip_clearance * 1e3, 2),
                "tip_seen_from_plan_mm": round(float(np.linalg.norm(tip_seen - tip_plan))
                                               * 1e3, 3),
                "approach_look_converged": approach_look,
                "tracked_after_drive": tr.converged,
                "seen_in_the_jaws": ("not converged" if not tr.converged
                                     else "as planned" if seen is None else str(seen))}

    def _drive_along(self, arm: str, drive: Drive, approach: np.ndarray
                     ) -> tuple[dict[str, Any], np.ndarray]:
        """Move ``arm``, at the drive's ``approach`` pose (reported), along the drive's
        gripper poses ``G_PT``. Open-loop (no ``drive_servo``): as planned. Servoed: the
        arm's reported poses are wrong by its kinematic error, and the arc a rotation of
        the reported tool sweeps is displaced and wanders as the tool turns; so at the
        approach and every ``servo_every`` drive poses, the needle is tracked where it
        is and :class:`DriveServo` learns from its circle the translation that keeps the
        centre on the plan, which every later pose carries; the approach's look moves
        the needle before the tip touches the tissue. One look a pose: looking again at
        the same pose until the error is gone chased the look's own bias (trial 2 of the
        procedure tests, exact arms: 0.54, 0.73, 1.62 then 4.07 mm off the plan, the
        track lost), where looks from other poses of the turn average it out. At the
        last pose, where the plan leaves it seen, up to ``servo_final`` more looks
        correct until the centre is within ``done_shift`` or two of the look's sigmas.
        Looks stop where the plan hides more than ``servo_shown`` of the arc in the
        tissue, and the drive carries on on the model's prediction; a look that
        leaves the circle uncertain, or shows too little of the arc (the fit matching
        what it finds: the jaws and the entering tip hide the rest), is not used (the
        servo never moves on it, nor stops for it: what it has not learnt, it leaves as
        planned, as open-loop does, and the regrasp's check of the bite follows
        either). Until the servo has used a look (the approach's may be lost: low over
        the tissue, across the masked incision), a lost track is not used either; once it
        has, a lost track, a stale frame, a jump, or a corrected pose out of reach stops
        the drive where it is, naming the cause. Returns the servo's figures (none
        open-loop) and the needle's motion since the tracker last looked (4x4, reference
        frame, left factor; the next look's): the arm's reported motion open-loop, the
        servo model's prediction servoed (the corrections since cancel the wander the
        reported motion does not show)."""
        s = self.s
        n = len(drive.G_PT)
        if s.drive_servo is None:
            for k, T in enumerate(drive.G_PT):
                self._move(arm, T, f"drive pose {k + 1} of {n}")
            return {}, self.cell.gripper_pose(arm) @ invert(approach)
        goals = drive.G_PS @ drive.G_SN
        # the approach is the first pose the servo steers: the needle there is the
        # drive's first pose moved as the gripper backs off from it
        poses = np.concatenate([approach[None], drive.G_PT])
        # the model's prior: how far the arms may be off at the needle, as their stated
        # accuracy says, and the seen grasp's own error besides (exact arms: the looks
        # only average the grasp's; a 3 mm prior there chased the looks' biases, 77.5 %
        # against open-loop's 85 % on development seeds 200-239)
        # streamed, each frame carries the state the step had commanded when it was
        # captured, which the model takes it at: its age delays the correction but does
        # not falsify it, so the age bound is the stream's own (a frame more than
        # STREAM_LAG commands behind is stale)
        settings = (s.drive_servo if self.feed is None
                    else replace(s.drive_servo, max_age=s.stream_timeout))
        run = _ServoRun(DriveServo(
            np.concatenate([(approach @ invert(drive.G_PT[0]) @ goals[0])[None], goals]),
            settings, prior_shift=math.hypot(_off_at_needle(s.arm_accuracy), GRASP_SEEN)),
            self.cell.gripper_pose(arm))
        servo = run.servo
        # the tip is in the tissue from the first poses on: the tracker must not take the
        # part under the surface for missing wire
        self.tracker.set_occluder(TissuePlane(self.incision.mean(axis=0), self.normal))

        def go(T: np.ndarray, what: str) -> None:
            ok, why = self._reach(arm, [T], 0.0)
            if not ok:
                raise StepFailed("out_of_reach", f"drive: {what} leaves {arm!r}'s reach "
                                                 f"({why})")
            self._move(arm, T, what)

        # where the views still see enough of the arc to fix its circle: out of the
        # tissue, by the plan
        shown = [1.0 - len(under) / len(pts)
                 for _, pts, under in map(self._arc_under, servo.goals)]
        start, streamed = 0, {}
        if self.feed is not None:
            # the poses from the approach on while the arc shows, streamed: corrected on
            # every tracked frame (the rest as below, on the model and a final look)
            guided = next((k for k, v in enumerate(shown) if v < s.servo_shown), n + 1)
            start, streamed = self._drive_streamed(arm, run, poses, min(guided, n), go)
        for k in range(start, n + 1):    # start <= n: the loop sets D
            D = servo.correction(k)
            if k:
                go(D @ poses[k], _pose_name(k, n))
            if (k % s.servo_every and k < n) or shown[k] < s.servo_shown:
                continue
            for attempt in range(1 + (s.servo_final if k == n else 0)):
                now = self.cell.gripper_pose(arm)
                # the needle's motion since the last look: as the servo's model of the
                # arm's error predicts it, once it has one
                motion = run.motion_to(k, D, now, run.looked)
                tr = self._look(motion, kinematic=run.looked is None)
                run.at_frame, run.looked = now, (k, D)
                stamp = time.monotonic()
                seen = Seen.from_track(tr, stamp, held=True)
                if not run.take(k, seen, stamp, now, D, _pose_name(k, n)):
                    break
                # done once the error is within the servo's aim, or within what the look
                # itself can tell apart (two sigmas): a further correction would chase
                # the look's noise, and each look is another chance to lose the track
                if (run.errors[-1] <= max(s.drive_servo.done_shift, 2.0 * seen.sigma_position)
                        or k != n):
                    break
                D = servo.correction(k)
                go(D @ poses[k], f"{_pose_name(k, n)}, correction {attempt + 1}")
        errors = run.errors
        return {"servo_looks": len(errors), "servo_blind_looks": run.blind,
                "servo_unused_looks": run.unused,
                "servo_span_deg": round(math.degrees(servo.span), 1),
                "servo_first_error_mm": round(errors[0] * 1e3, 3) if errors else None,
                "servo_max_error_mm": round(max(errors) * 1e3, 3) if errors else None,
                "servo_last_error_mm": round(errors[-1] * 1e3, 3) if errors else None,
                "servo_correction_mm": round(float(np.linalg.norm(
                    servo.correction(n)[:3, 3])) * 1e3, 3), **streamed}, run.motion_to(
                        n, D, self.cell.gripper_pose(arm), run.looked)

    def _drive_streamed(self, arm: str, run: _ServoRun, poses: np.ndarray, end: int,
                        go: Callable[[np.ndarray, str], None]
                        ) -> tuple[int, dict[str, Any]]:
        """The servoed drive's poses ``0 .. end - 1`` (0: the approach, where the arm is)
        corrected on every tracked frame: the tracking task (``self.feed``) captures and
        tracks the views while the arm moves, and each newer tracked frame the step takes
        is one look for the servo's model (``run``) and one command, to the next pose with
        the corrected translation; so the arm never moves more than one drive pose per
        tracked frame, and a stream that stops stops the arm (``servo_stale`` after
        ``stream_timeout``). A frame is looked at as of its capture: the pose and
        correction then in force (at most ``STREAM_LAG`` commands old: the task captures
        the next frame while it tracks the last). Returns the first pose not yet
        commanded and the figures: commands a second while streaming
        (``servo_rate_hz``), each command's time from its frame's arrival
        (``servo_latency_ms``) and from the step taking the frame (``servo_command_ms``:
        the servo's update and the move), each frame's features and tracking times
        (``servo_prepare_ms``, ``servo_track_ms``), frames tracked."""
        s = self.s
        n = len(poses) - 1
        lock = threading.Lock()            # a frame shows one commanded state, whole
        state: dict[str, Any] = {"k": 0, "D": np.eye(4)}
        base = run.at_frame                 # the reported tool at the tracker's last look

        # a cell that can expose a frame (copy its state) renders it outside the lock,
        # so the arm is not held up by the renderer; another renders under it
        expose = getattr(self.cell, "expose", None)

        def capture() -> tuple[dict[str, np.ndarray], tuple]:
            with lock:
                parts = [p for a in self.arms
                         for p in self._tool_parts(self.cell.gripper_pose(a))]
                meta = (state["k"], state["D"], self.cell.gripper_pose(arm), parts)
                if expose is None:
                    return self.cell.images(), meta
                render = expose()
            return render(), meta

        def track(feats: list[NeedleFeatures], meta: tuple, previous: tuple | None
                  ) -> NeedleTrack:
            self.tracker.set_tools(meta[3])
            # one update a frame, predicted with the arm's reported motion since the last
            # tracked frame: a drive pose or two, where the arm's error barely turns; the
            # wire slips in the jaws by the frame's share of the turn
            self.tracker.predict(meta[2] @ invert(base if previous is None else previous[2]),
                                 split=True)
            return self.tracker.update(feats)

        # the tracker as the open-loop drive would leave it, for a stream the servo could
        # use no frame of (a track gone astray, 7-13 mm off on exact-armed validation
        # trials 1000607 and 1000627, then carried the next look astray too)
        before = copy.deepcopy(self.tracker)
        # the needle is in the driver's closed jaws throughout
        self.tracker.fix_side(True)
        feed = self.feed(capture, self._features_of, track)
        seq, k = 0, 0
        latency: list[float] = []
        command: list[float] = []           # from taking a frame to its command (s)
        commands: list[float] = []
        try:
            while k < end:
                fr = feed.next(seq, s.stream_timeout)
                taken = time.monotonic()
                seq = fr.seq
                kc, Dc, tool, _ = fr.meta
                if k - kc > STREAM_LAG:
                    raise ServoStop("stale", f"the newest tracked frame was captured at "
                                             f"{_pose_name(kc, n)}, {k - kc} commands ago")
                seen = Seen.from_track(fr.track, fr.stamp, held=True)
                # a frame a pose on from the last shares most of its error (the same
                # views, the same biases): the frames of servo_every poses weigh as one
                # look (17 frames at full weight took exact-armed validation trial
                # 1000635's drive 2.3 mm off on 0.6 mm looks). And a frame that loses the
                # needle, where the next may find it again, is not a lost track: the arm
                # goes on on the model until the frames of servo_every poses in a row
                # are lost, as long as the looks servo goes without seeing (every frame
                # counted stopped 3 of 80 drives at pose 1, as the tip entered)
                run.take(kc, seen, taken, tool, Dc, _pose_name(kc, n),
                         weight=1.0 / math.sqrt(s.servo_every),
                         lost_allowed=s.servo_every - 1)
                k += 1
                if k >= end:
                    break
                D = run.servo.correction(k)
                with lock:
                    go(D @ poses[k], _pose_name(k, n))
                    state.update(k=k, D=D)
                commands.append(time.monotonic())
                latency.append(commands[-1] - fr.stamp)
                command.append(commands[-1] - taken)
        except ServoStop as exc:
            raise StepFailed(f"servo_{exc.cause}", f"{_pose_name(k, n)}: {exc.detail}"
                             ) from None
        finally:
            last = feed.stop()
            self.tracker.fix_side(False)
        if run.used is None:
            self.tracker = before
        elif last is not None:
            # the tracker's state is that of its last frame: the next look moves it on
            run.at_frame, run.looked = last.meta[2], (last.meta[0], last.meta[1])
        return k, {"servo_streamed_poses": k, "servo_frames": seq,
                   "servo_rate_hz": (round((len(commands) - 1) / (commands[-1] - commands[0]), 1)
                                     if len(commands) > 1 else None),
                   # each command's arrival-to-command time, and each frame's work (its
                   # features, its tracking: they overlap, so the slower bounds the rate a
                   # camera faster than the simulator's renderer would get)
                   "servo_latency_ms": [round(v * 1e3, 1) for v in latency],
                   "servo_command_ms": [round(v * 1e3, 2) for v in command],
                   "servo_prepare_ms": [round(v * 1e3, 1) for v in feed.prepare_s],
                   "servo_track_ms": [round(v * 1e3, 1) for v in feed.track_s]}

    def _arc_under(self, T_N: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:func:`_arc_under` on this procedure's tissue surface."""
        return _arc_under(self.needle, T_N, self.incision.mean(axis=0), self.normal)

    def _check_exit(self, T_N: np.ndarray, what: str) -> None:
        """Fail unless the needle tracked at ``T_N`` went in and came out where the drive
        planned it (:meth:`_exit_error`)."""
        failure = self._exit_error(T_N, what)
        if failure is not None:
            raise failure

    def _exit_error(self, T_N: np.ndarray, what: str) -> StepFailed | None:
        """Why the needle tracked at ``T_N`` does not lie where the drive put it (``None``
        when it does): its arc must cross the tissue surface, both ends above it, within
        ``placement_tolerance`` of the planned entry and exit points. That is the
        suture's bite, which the truth check judges too. The crossings do not depend on
        the needle's slide along its own circle, which the views fix only at its ends
        (seen near the pad's edge, or edge-on, an end misread by a few pixels moves the
        tip by millimetres); how far the tip went is the regrasp's concern
        (:func:`tip_part`), and the distance of the tracked tip from the plan's end is
        only reported."""
        assert self.tip_plan is not None and self.geometry is not None
        tol = self.s.placement_tolerance
        _, pts, under = self._arc_under(T_N)
        offs = {"tip": float(np.linalg.norm(pts[-1] - self.tip_plan))}
        if under.size:
            offs["entry"] = float(np.linalg.norm(pts[under[0]]
                                                 - self._to_ref(self.geometry.entry)))
            offs["exit"] = float(np.linalg.norm(pts[under[-1]]
                                                - self._to_ref(self.geometry.exit)))
        seen = ", ".join(f"{k} {v * 1e3:.2f} mm" for k, v in offs.items())
        if not under.size:
            return StepFailed("not_in_tissue", f"{what}: none of the tracked needle lies "
                                                f"under the tissue surface ({seen} from the "
                                                "plan)")
        ends = [name for name, i in (("swage", 0), ("tip", len(pts) - 1)) if i in under]
        bad = [k for k in ("entry", "exit") if offs[k] > tol]
        if ends or bad:
            why = (f"the {' and the '.join(ends)} under the surface" if ends
                   else f"{' and '.join(bad)} off the plan")
            return StepFailed("exit_missed",
                               f"{what}: the tracked needle does not lie where the drive "
                               f"planned it ({why}: {seen} from the plan; tolerance "
                               f"{tol * 1e3:.1f} mm)")
        return None

    def _drive_on(self, arm: str, T_N: np.ndarray) -> tuple[Drive, GraspChoice]:
        """The drive on the grasp the tracker sees, checked (eq. 3); refused when that grasp
        or a pose of its drive is not fit."""
        assert self.drive is not None
        G_TN = self._grasp_seen(arm, T_N)
        try:
            choice = check_drive_grasp(self.needle, self.drive, G_TN, self.s.drive_grasp)
        except NeedleError as exc:
            raise _refuse("grasp_unfit", f"drive: {exc}") from None
        drive = self.drive.with_grasp(G_TN)
        assert drive.G_PT is not None
        ok, why = self._reach(arm, list(drive.G_PT), 0.0)
        if not ok:
            raise _refuse("out_of_reach", f"drive: {arm!r} cannot follow the drive with the "
                                          f"grasp it holds ({why})")
        self.G_TN = G_TN
        return drive, choice

    def _approach(self, drive: Drive, arm: str) -> np.ndarray:
        """The drive's approach pose, along the needle tip's tangent or else along the
        gripper (seed 002): the gripper's axis may run nearly along the tissue, and an
        approach along it carries the tip in low over the surface, where a tip tracked a
        little high enters early (by the depth error over the approach's slope); along
        the tangent the tip comes in as the drive will move it."""
        last = ""
        for along in ("tangent", "gripper"):
            try:
                T = drive.approach_pose(self.s.approach, along=along)
            except NeedleError as exc:
                last = str(exc)
                continue
            ok, why = self._reach(arm, [T], 0.0)
            if ok:
                return T
            last = why
        raise _refuse("out_of_reach", f"drive: no approach pose for {arm!r} ({last})")

    def _step_nr(self) -> dict[str, Any]:
        s = self.s
        B = self.driver
        assert B is not None
        self._jaws(B, False, "release: opening the driver's jaws")
        self.holder = None
        self._back_off_released(B, "regrasp")
        T_N = self._converged("regrasp")
        self._check_exit(T_N, "regrasp")
        point = self.incision.mean(axis=0)
        phi_lo, phi_hi, out_mm = tip_part(self.needle, T_N, point, self.normal, s)
        if phi_hi < phi_lo:
            raise _refuse("no_grasp", f"regrasp: the tip stands {out_mm:.1f} mm out of the "
                                      f"tissue, too little to grasp")
        assert self.G_CS is not None
        grasps = _tip_grasps(self.needle, T_N, point, self.normal, s, phi_lo, phi_hi)
        order = [B] + [a for a in self.arms if a != B]
        last = ""
        for arm in order:
            here = self.cell.gripper_pose(arm)
            leave = self._leaving_margin(arm, here)
            for g in grasps:
                # the approach from where the arm is too: a straight path between two
                # poses the wrist reaches may bend it past its limits
                approach = back_off(g.T_ref_T, s.approach)
                ok, why = self._reach(arm, [g.T_ref_T, approach])
                if ok:
                    ok, why = self._reach(arm, _path(here, approach), leave)
                if ok:
                    try:
                        pull = pull_poses(np.eye(4), self.G_CS, T_N, g.G_TN, self.needle,
                                          s.pull_poses, s.swage_clearance, s.pull_lift)
                    except NeedleError as exc:
                        raise _refuse("bad_pull", f"regrasp: {exc}") from None
                    ok, why = self._reach(arm, list(pull.G_PT))
                if ok:
                    return self._regrasp(arm, g, pull, out_mm)
                last = f"{arm}: {why}"
        raise _refuse("out_of_reach", f"regrasp: no arm reaches a grasp of the tip that it "
                                      f"can pull with "
                                      f"({last or 'no grasp of the tip part clears the tissue'})")

    def _back_off_released(self, arm: str, what: str) -> None:
        """Back the opened gripper ``arm`` off the needle by ``retreat``: along its own
        -z, or where the wrist cannot follow that, aslant in the plane of the jaws' faces
        (:data:`_BACK_OFF_TILTS`), the first whose whole path the arm reaches."""
        T0 = self.cell.gripper_pose(arm)
        why = ""
        for tilt in _BACK_OFF_TILTS:
            goal = back_off(T0, self.s.retreat, tilt)
            ok, why = self._reach(arm, _path(T0, goal), 0.0)
            if ok:
                self._move(arm, goal, f"{what}: the released gripper's back-off")
                return
        raise StepFailed("move_stopped", f"{what}: the released gripper cannot back off "
                                          f"the needle in any direction that clears the "
                                          f"jaws ({why})")

    def _regrasp(self, arm: str, g: SurfaceGrasp, pull: Any, out_mm: float
                 ) -> dict[str, Any]:
        s = self.s
        self._move(arm, back_off(g.T_ref_T, s.approach), "regrasp approach")
        self._move(arm, g.T_ref_T, "regrasp reach")
        self._jaws(arm, True, "regrasp: closing the jaws")
        # whether the jaws hold the needle is shown by the pull (NP): standing in the
        # tissue, with the jaws over its tip part, the needle shows too little for a
        # small check motion to tell a hold from a miss (the jaws hide the tip, the
        # tissue most of the rest), while out of the tissue after the pull it lies in
        # full view, many millimetres from where a missed needle stays
        before = self._hold_reference()
        G_seen = self._grasp_seen(arm, before)
        self.holder, self.G_TN = arm, G_seen
        self._pull = (pull, before)
        fit = grasp_parameters(G_seen, self.needle.radius)
        return {"arm": arm, "grasp_phi_deg": round(math.degrees(g.params.phi), 2),
                "seen_phi_deg": round(math.degrees(fit.params.phi), 2),
                "tip_out_mm": round(out_mm, 2),
                "shaft_elevation_deg": round(math.degrees(g.elevation), 1)}

    def _step_np(self) -> dict[str, Any]:
        s = self.s
        arm = self.holder
        assert arm is not None and self._pull is not None
        pull, before = self._pull
        T0 = self.cell.gripper_pose(arm)
        for k, T in enumerate(pull.G_PT):
            self._move(arm, T, f"pull pose {k + 1} of {len(pull.G_PT)}")
        # the pulled needle stands square to the tissue, which the cameras look at
        # nearly face-on: edge-on to them, and often over what lies beyond the tissue;
        # turned and raised where they see it, the look can show the hold
        assert self.G_TN is not None
        shown = self._show_pose(arm, pull.G_CN[-1], self.G_TN)
        figures: dict[str, Any] = {"show_turn_deg": None}
        if shown is not None:
            T_show, turn = shown
            figures["show_turn_deg"] = round(math.degrees(turn), 1)
            if not np.allclose(T_show, self.cell.gripper_pose(arm)):   # turned or raised
                try:
                    self.cell.move(arm, T_show)
                except Exception as exc:   # stopped short at a reachable pose, needle held
                    # out of the tissue: the look judges the hold wherever it stopped
                    figures["show_stopped"] = str(exc)
        # the regrasp's proof: the needle came out with the jaws
        T_N = self._followed(arm, before, T0, "pull", s.pull_tolerance)
        lowest = float(((self.needle.points(64) @ T_N[:3, :3].T + T_N[:3, 3]
                         - self.incision.mean(axis=0)) @ self.normal).min())
        if lowest < 0.0:
            raise StepFailed("still_in_tissue", f"pull: the tracked needle is still "
                                                 f"{-lowest * 1e3:.2f} mm in the tissue")
        self.in_tissue = False
        self._pull = None
        self.tracker.set_occluder(None)
        figures.update(turn_deg=round(math.degrees(float(pull.betas[-1])), 1),
                       lowest_point_mm=round(lowest * 1e3, 2))
        return figures

    def _show_pose(self, arm: str, T_N: np.ndarray, G_TN: np.ndarray
                   ) -> tuple[np.ndarray, float] | None:
        """Where ``arm``, holding the pulled needle (at ``T_N``, ``ref``) with ``G_TN``,
        shows it to the cameras: the needle moved toward the middle of the reference
        camera's view of the tissue by one of ``show_shifts`` (the least first), turned
        about its centre as little as will do (:data:`_HANDOFF_TURNS`) and raised by one
        of ``show_heights``, reached along
        the straight path from where the arm is, the needle ``carry_clearance`` off the
        tissue all the way. The views (:meth:`_view`, past both grippers) are asked in
        tiers, the first that any candidate passes deciding: with room to spare
        (``strict``) and clear of the incision line's band, then clear of the band, then
        as the hand-off asks (the features ignore the band, and the rest of the arc may
        still show the hold). Returns the gripper's ``T_ref_T`` and the turn (rad), or
        ``None`` when no candidate does."""
        s = self.s
        here = self.cell.gripper_pose(arm)
        others = [self.cell.gripper_pose(a) for a in self.arms if a != arm]
        G_NT = invert(G_TN)
        leave = self._leaving_margin(arm, here)
        toward = self.views.aim(self.incision.mean(axis=0))
        candidates = [item for T_m in _shifted(T_N, self.normal, toward, s.show_shifts)
                      for item in _turned_and_raised(T_m, self.normal, s.show_heights)]
        moves = []
        goals = np.stack([T_s for T_s, _, _ in candidates]) @ G_NT
        there = self.cell.reachable_all(arm, goals, s.reach_margin)   # all goals at once
        for (T_s, turn, _), T_g, ok in zip(candidates, goals, there, strict=True):
            if not (ok and self._reach(arm, _path(here, T_g), leave)[0]):
                continue
            if self._lowest(_path(here, T_g, 32), G_TN) < s.carry_clearance:
                continue
            moves.append((T_s, T_g, turn))
        for strict, incision in ((True, True), (False, True), (False, False)):
            view = self._view_each([T_s for T_s, _, _ in moves],
                                   [(T_g, *others) for _, T_g, _ in moves],
                                   incision=incision, strict=strict)
            for k, (_, T_g, turn) in enumerate(moves):
                if not view(k):
                    return T_g, turn
        return None
