"""The needle procedure's actions on its cell, which the steps are made of: look (track
the needle on fresh frames), move and carry an arm within its reach and clear of the
tissue, and check by a look that a held needle followed the jaws. Reference frame, m,
rad."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from oralnav.control.geometry import invert
from oralnav.control.needle.features import NeedleFeatures, feature_maps
from oralnav.control.needle.model import Needle
from oralnav.control.needle.procedure.cell import NeedleCellPort
from oralnav.control.needle.procedure.poses import _path, translation
from oralnav.control.needle.procedure.results import StepFailed, _refuse
from oralnav.control.needle.procedure.settings import ProcedureSettings
from oralnav.control.needle.procedure.views import ViewRule
from oralnav.control.needle.tracker import NeedleTrack, NeedleTracker, ToolCylinder
from oralnav.control.vision.camera import CameraModel


class CellActions:
    """The actions of :class:`~oralnav.control.needle.procedure.steps.NeedleProcedure` on
    its cell, its base: the procedure's constructor sets the attributes declared here
    (see there); the state they change is the tracker's and :attr:`track`."""

    cell: NeedleCellPort
    s: ProcedureSettings
    needle: Needle
    incision: np.ndarray
    normal: np.ndarray
    arms: tuple[str, ...]
    cams: list[CameraModel]
    tracker: NeedleTracker
    views: ViewRule
    track: NeedleTrack | None
    _wire_px: list[float]
    _masks: list[np.ndarray]
    _depth_range: tuple[float, float]

    # -- tracking -------------------------------------------------------------------------
    def _features(self) -> list[NeedleFeatures]:
        """The cell's views now, reduced to what the tracker reads."""
        return self._features_of(self.cell.images())

    def _features_of(self, imgs: dict[str, np.ndarray]) -> list[NeedleFeatures]:
        """``imgs`` (by camera name) reduced to what the tracker reads."""
        return [feature_maps(imgs[cam.name], w, ignore=m)
                for cam, w, m in zip(self.cams, self._wire_px, self._masks, strict=True)]

    def _look(self, delta: np.ndarray | None = None, *, static: bool = True,
              init: bool = False, trusted: bool = True, kinematic: bool = True
              ) -> NeedleTrack:
        """Track on fresh frames: a global initialisation (``init``), or ``updates``
        updates, the first predicted with the gripper's motion ``delta`` (a held needle),
        the others with no motion (``static``: held or in the tissue, the grasped noise)
        or Brownian motion (free). ``trusted=False``: the first motion is what a check
        tests, or the jaws closed since the last look (the tracker carries only the
        slide, :meth:`.NeedleTracker.predict`). ``kinematic=False``: ``delta`` is the
        needle's motion as a servo's model predicts it, not the arm's reported one."""
        s = self.s
        still = np.eye(4) if static else None
        # the grippers where they are now hide part of the needle
        self.tracker.set_tools([part for a in self.arms
                                for part in self._tool_parts(self.cell.gripper_pose(a))])
        if init:
            # the global localisation lands in the needle's basin with some chance: one
            # that ends unconverged is started again on fresh frames and particles (on
            # development seeds 200-399, a second start converged, on the true pose, in 5
            # of the 7 pick-ups refused as not converged)
            for _ in range(s.init_attempts):
                tr = self.tracker.initialize(self._features(), self._depth_range)
                for _ in range(s.init_updates):
                    self.tracker.predict(still)
                    tr = self.tracker.update(self._features())
                if tr.converged:
                    break
        else:
            tr = None
            for k in range(s.updates):
                self.tracker.predict(delta if k == 0 and delta is not None else still,
                                     trusted=trusted or k > 0,
                                     kinematic=kinematic or k > 0)
                tr = self.tracker.update(self._features())
        assert tr is not None
        self.track = tr
        return tr

    def _converged(self, what: str, **look: Any) -> np.ndarray:
        """Look; the tracked ``T_ref_N``, or a refusal naming why the tracker has not
        converged."""
        tr = self._look(**look)
        if not tr.converged:
            raise _refuse("not_converged", f"{what}: the needle tracker has not converged "
                                           f"({tr.reason})")
        return tr.pose

    def _grasp_seen(self, arm: str, T_ref_N: np.ndarray) -> np.ndarray:
        """The grasp ``G_TN`` as the tracker sees it: ``inv(T_ref_T) T_ref_N``."""
        return invert(self.cell.gripper_pose(arm)) @ T_ref_N

    # -- motion ---------------------------------------------------------------------------
    def _move(self, arm: str, T: np.ndarray, what: str) -> None:
        self._act(what, self.cell.move, arm, T)

    def _jaws(self, arm: str, close: bool, what: str) -> None:
        """Close (``close``) or open ``arm``'s jaws. A cell that refuses (a stop came while
        the step ran: the daemon's cell asks its safety state first) fails the step with
        ``move_stopped``, as an arm that stopped short does."""
        self._act(what, self.cell.close if close else self.cell.open, arm)

    @staticmethod
    def _act(what: str, action: Callable[..., Any], *args: Any) -> None:
        """``action(*args)`` on the cell; the cell's own error (an arm stopped short, a
        refused motion) fails the step with ``move_stopped`` and ``what``."""
        try:
            action(*args)
        except Exception as exc:   # the cell's own error type
            raise StepFailed("move_stopped", f"{what}: {exc}") from None

    def _reach(self, arm: str, poses: Sequence[np.ndarray], margin: float | None = None
               ) -> tuple[bool, str]:
        """Whether ``arm`` reaches every pose, and the limit that refuses one. Plans keep
        the wrist ``reach_margin`` inside its limits (``margin``, rad, by default); a
        check of what is about to run on the grasp actually made passes 0."""
        m = self.s.reach_margin if margin is None else margin
        poses = list(poses)
        if len(poses) > 1:
            # one batched check settles most paths (each pose alone cost ~0.1 ms, a
            # quarter of a trial's time); the poses it doubts are asked one by one, in
            # order, so the answer and the limit named are the first refusing pose's
            ok_all = self.cell.reachable_all(arm, np.stack(poses), m)
            if ok_all.all():
                return True, ""
            poses = [poses[i] for i in range(int(np.argmin(ok_all)), len(poses))
                     if not ok_all[i]]
        for T in poses:
            ok, why = self.cell.reachable(arm, T, m)
            if not ok:
                return False, why
        return True, ""

    def _leaving_margin(self, arm: str, here: np.ndarray) -> float:
        """The wrist margin (rad) for the path of ``arm`` leaving ``here``: the plans'
        ``reach_margin``, or less where the arm already stands nearer a limit (the drive
        and the back-off run on what the wrist reaches, with no margin): such a path may
        bend the wrist as far as it stands, not further, while its goal keeps the full
        margin. Held to the full margin, every path from the drive's end failed its first
        pose on 8 of session 20's 14 regrasps refused out of reach."""
        m = self.s.reach_margin
        if self.cell.reachable(arm, here, m)[0]:
            return m
        lo, hi = 0.0, m
        for _ in range(10):           # bisection to m / 1024 (under 0.01 deg)
            mid = 0.5 * (lo + hi)
            if self.cell.reachable(arm, here, mid)[0]:
                lo = mid
            else:
                hi = mid
        return lo

    def _lowest(self, poses: Sequence[np.ndarray], G_TN: np.ndarray) -> float:
        """The lowest height (m) over the tissue plane of the needle held at ``G_TN`` by
        a gripper at any of ``poses`` (its ``T_ref_T``)."""
        if len(poses) == 0:
            return math.inf
        pts = self.needle.points(48)
        base = self.incision.mean(axis=0)
        P = np.stack(list(poses)) @ G_TN
        # every point's height at every pose, (R p + t - base) . n = p . R^T n + (t - base) . n
        h = pts @ (P[:, :3, :3].transpose(0, 2, 1) @ self.normal).T \
            + ((P[:, :3, 3] - base) @ self.normal)[None, :]
        return float(h.min())

    def _carry(self, arm: str, goal: np.ndarray, G_TN: np.ndarray, what: str) -> None:
        """Move ``arm``, holding the needle at ``G_TN``, to ``goal`` without the needle
        touching the tissue on the way: the straight path turns the needle about the
        jaws, and its far end can sweep down through the surface (an unplanned puncture,
        away from the planned entry). Where it would, the needle goes over: up along the
        normal, across, and straight down to ``goal``, the first rise of ``carry_rises``
        whose whole path keeps it ``carry_clearance`` clear (at ``goal`` itself it may be
        lower, since a straight descent ends there); refused when none does."""
        s = self.s
        T0 = self.cell.gripper_pose(arm)
        floor = min(s.carry_clearance, self._lowest([goal], G_TN))
        if self._lowest(_path(T0, goal, 32), G_TN) >= floor:
            self._move(arm, goal, what)
            return
        last = "no rise keeps the needle off the tissue"
        for h in s.carry_rises:
            rise = translation(h * self.normal)
            for legs in ([rise @ goal, goal], [rise @ T0, rise @ goal, goal]):
                path, start = [], T0
                for T in legs:
                    path += _path(start, T, 32)
                    start = T
                if self._lowest(path, G_TN) < floor:
                    continue
                ok, why = self._reach(arm, path)
                if not ok:
                    last = why
                    continue
                for k, T in enumerate(legs):
                    self._move(arm, T, f"{what} (over the tissue, leg {k + 1} of {len(legs)})")
                return
        raise _refuse("unsafe_path", f"{what}: the straight path would sweep the needle "
                                     f"through the tissue, and no path over it is reachable "
                                     f"({last})")

    def _verify_hold(self, arm: str, T_goal: np.ndarray, what: str) -> np.ndarray:
        """Move ``arm`` (which should hold the needle) to ``T_goal`` and look: the needle
        must have moved with the jaws (:meth:`_hold_reference`, :meth:`_followed`).
        Returns the tracked ``T_ref_N``."""
        before = self._hold_reference()
        T0 = self.cell.gripper_pose(arm)
        self._move(arm, T_goal, f"{what}: the check motion")
        return self._followed(arm, before, T0, what, self.s.hold_tolerance)

    def _check_motion(self, arm: str, T_N: np.ndarray) -> np.ndarray:
        """The goal of a ``hold_check`` motion of ``arm`` holding the needle at ``T_N``:
        square to the reference camera's line of sight to the needle, which the views
        measure to a tenth of a millimetre, where along it (depth) they measure only to
        about a millimetre. First the way that lifts most off the tissue, then sideways
        along it, and last along the normal; the first whose goal the arm reaches and
        from where the cameras see the needle."""
        T = self.cell.gripper_pose(arm)
        v = self._sight(T_N)
        up = self.normal - float(self.normal @ v) * v
        side = np.cross(v, self.normal)
        if np.linalg.norm(side) < 1e-9:
            # looking straight along the normal: any way square to the sight lifts none
            side = np.cross(v, np.eye(3)[int(np.argmin(np.abs(v)))])
            up = np.cross(side, v)
        ways = [w / np.linalg.norm(w) for w in (up, side, -side)] + [self.normal]
        for w in ways:
            move = translation(self.s.hold_check * w)
            if (self._reach(arm, [move @ T], 0.0)[0]
                    and not self._view(move @ T_N, [move @ T])):
                return move @ T
        return translation(self.s.hold_check * self.normal) @ T

    def _hold_reference(self) -> np.ndarray:
        """Where the needle lies in jaws that just closed: closing centres the wire
        between them (it moves the needle by up to half the open gap), so a fresh look,
        when it converges, rather than the pose the grasp was aimed on."""
        assert self.track is not None
        before = self.track.pose
        tr = self._look(trusted=False)
        return tr.pose if tr.converged else before

    def _followed(self, arm: str, before: np.ndarray, T0: np.ndarray, what: str,
                  tolerance: float) -> np.ndarray:
        """Look after ``arm`` moved from ``T0``: the needle, at ``before`` when the jaws
        closed, must lie where the jaws' motion took it (within ``tolerance``, m, or
        ``follow_ratio`` of its distance from where it was, whichever is larger) and
        nearer there than where it was. Returns the tracked ``T_ref_N``."""
        delta = self.cell.gripper_pose(arm) @ invert(T0)
        # the images must show the hold: the motion is not assumed
        tr = self._look(delta, trusted=False)
        moved = delta @ before
        if not tr.converged:
            # not where the jaws took it: perhaps where it was (the jaws let it go)
            stayed = self._look(invert(delta), trusted=False)
            if not stayed.converged:
                off = self._left_behind(stayed, moved, before, tolerance)
                if off is not None:
                    raise StepFailed("grasp_missed",
                                      f"{what}: the needle did not follow the jaws: the look "
                                      f"places it {off * 1e3:.2f} mm from where it was, though "
                                      f"it did not converge ({stayed.reason})")
                raise StepFailed("lost_track", f"{what}: the tracker lost the needle after "
                                                f"the check motion ({tr.reason})")
            tr = stayed
        # held and let go are told apart by how far apart they put the needle: over
        # the whole arc, which needs the slide along it measured by these views (where
        # the jaws and the tissue hide the ends, the slide is the motion model's, which
        # assumed the hold, and proves nothing); or, where the two differ off the
        # needle's own circle (the centre or the plane moved), whatever the slide: the
        # views fix the slide only at the needle's ends, an end misread by the jaws, the
        # tissue or an edge-on view slides the track by degrees, and a grasp that
        # slipped along the arc still holds (the steps re-read the grasp after the
        # check). Third, the centre's motion square to the reference camera's line of
        # sight, which the views measure to tenths of a millimetre where the depth is
        # good to a millimetre or two (at the hand-off the depth error alone, 1-3.6 mm,
        # put 15 of 17 truly held needles of the 200 trials over the 3-D tolerances; the
        # check motion is made square to the sight for this). The needle followed if any
        # shows it: a needle let go stays where it was by all
        ref = tr.refined
        measures = []
        if ref is not None and ref.sigma_slide_seen <= self.s.max_sigma_angle:
            measures.append(self._arc_distance)
        if self._slide_free_distance(moved, before) > 2.0 * tolerance:
            measures.append(self._slide_free_distance)
        across = self._across_sight(before)
        if across(moved, before) > 2.0 * tolerance:
            measures.append(across)
        if not measures:
            raise StepFailed("hold_unseen", f"{what}: the check motion turned the needle "
                                             "along its own arc, and the views do not show "
                                             "its ends: whether it followed is unseen")
        verdicts = []
        for dist in measures:
            off, stay = (dist(tr.pose, T) for T in (moved, before))
            allowed = max(tolerance, self.s.follow_ratio * stay)
            verdicts.append((off <= allowed and off < stay, off, allowed, stay))
        if not any(v[0] for v in verdicts):
            _, off, allowed, stay = verdicts[0]
            raise StepFailed("grasp_missed",
                              f"{what}: the needle did not follow the jaws ({off * 1e3:.2f} mm "
                              f"from where it would be if held, {allowed * 1e3:.2f} mm "
                              f"allowed; {stay * 1e3:.2f} mm from where it was)")
        return tr.pose

    def _left_behind(self, tr: NeedleTrack, moved: np.ndarray, before: np.ndarray,
                     tolerance: float) -> float | None:
        """Whether a look that did not converge still shows the needle left where it was
        (its slide-free distance from ``before``, m) rather than where the jaws took it
        (``moved``): the fit passed, its position and its plane's tilt are certain, and
        what failed is the slide along the arc (the views read no end: the tip in the
        pad's edge band, the base's thread) or the filter's score. ``None`` when it does
        not show that. It can only tell a miss, never a hold: a needle that followed
        must be placed whole."""
        ref = tr.refined
        if ref is None or not ref.ok or ref.cov is None \
                or ref.sigma_position > self.s.max_sigma_position:
            return None
        # the tilt's uncertainty: the rotation's less the turn about N's z (the slide)
        tilt = math.sqrt(max(float(np.linalg.eigvalsh(ref.cov[:2, :2]).max()), 0.0))
        if tilt > self.s.max_sigma_angle:
            return None
        stay = self._slide_free_distance(ref.pose, before)
        if stay <= tolerance < 0.5 * self._slide_free_distance(ref.pose, moved):
            return stay
        return None

    def _arc_distance(self, T_a: np.ndarray, T_b: np.ndarray) -> float:
        """RMS distance (m) between the needle's arc points at two poses."""
        p = self.needle.points(24)
        d = (p @ T_a[:3, :3].T + T_a[:3, 3]) - (p @ T_b[:3, :3].T + T_b[:3, 3])
        return float(np.sqrt(np.mean(np.sum(d * d, axis=1))))

    def _slide_free_distance(self, T_a: np.ndarray, T_b: np.ndarray) -> float:
        """How far apart two needle poses are whatever their slide along the arc (m):
        the centres' distance and the planes' tilt (taken at the radius)."""
        tilt = math.acos(max(-1.0, min(1.0, float(T_a[:3, 2] @ T_b[:3, 2]))))
        return math.hypot(float(np.linalg.norm(T_a[:3, 3] - T_b[:3, 3])),
                          self.needle.radius * tilt)

    def _sight(self, T_ref_N: np.ndarray) -> np.ndarray:
        """The reference camera's line of sight to the needle's centre at ``T_ref_N``
        (unit, reference frame): the views measure depth along it to about a
        millimetre, across it to a tenth."""
        return self.views.sight(T_ref_N)

    def _across_sight(self, T_ref_N: np.ndarray) -> Callable[[np.ndarray, np.ndarray], float]:
        """A distance (m) between two needle poses: their centres' distance square to
        the reference camera's line of sight to the needle at ``T_ref_N`` (what the views
        measure best; slide and tilt do not enter)."""
        v = self._sight(T_ref_N)

        def distance(T_a: np.ndarray, T_b: np.ndarray) -> float:
            d = T_a[:3, 3] - T_b[:3, 3]
            return float(np.linalg.norm(d - float(d @ v) * v))
        return distance

    def _view(self, T_ref_N: np.ndarray, tools: Sequence[np.ndarray] = (),
              incision: bool = False, strict: bool = False) -> str:
        """Why the cameras would not see the needle well at ``T_ref_N`` (:class:`ViewRule`;
        "" when they would)."""
        return self.views.why_not(T_ref_N, tools, incision, strict)

    def _view_each(self, T_ref_N: Sequence[np.ndarray], tools: Sequence[Sequence[np.ndarray]],
                   incision: bool = False, strict: bool = False) -> Callable[[int], str]:
        """:meth:`_view` of candidate ``k`` of ``T_ref_N`` (with ``tools[k]``) as a
        function of ``k``, worked out in batches (:meth:`ViewRule.why_not_each`)."""
        return self.views.why_not_each(T_ref_N, tools, incision, strict)

    def _tool_parts(self, T_ref_T: np.ndarray) -> tuple[ToolCylinder, ToolCylinder]:
        return self.views.tool_parts(T_ref_T)
