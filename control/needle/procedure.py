"""The visually guided needle procedure of seed 002 (§III, §IV.B): needle grasp (NG),
hand-off (NH), drive (ND), regrasp (NR) and pull (NP), driven through a needle cell.

Every step looks before it moves: the needle's pose comes from the tracker
(:class:`~oralnav.control.needle.tracker.NeedleTracker`) on the cell's stereo images, the
grippers' poses from the arms (what the robot reports; the simulated cell adds its fixed
kinematic error). A step that cannot be done safely refuses before any motion toward the
needle, with the reason (:attr:`StepResult.refused`): an undefined suture (``h > r``), a
needle or suture no arm reaches, a tracker that has not converged. A step that moved and
then saw something go wrong (a grasp whose needle does not follow the jaws, an arm that
stopped on its reach limit) fails with its cause. A step's own verdict is what it saw;
where the cell knows the truth (the simulator), each step is also checked against it
(:attr:`StepResult.truth_ok`), which is what the Monte Carlo bench counts.

The steps (docs/needle.md, "Procedure"):

- **NG**: plan the suture (tissue frame from the incision, eqs. 2-4) and choose the
  driving arm and its grasp first (:func:`~oralnav.control.needle.grasp.select_grasp`
  with the arm's reach), so that the other arm picks the needle up far enough along the
  arc from where the driver will take it; approach along the gripper axis, reach, close
  (Fig. 5), lift, and check that the needle rose with the jaws.
- **NH**: carry the needle to a hand-off pose above the suture's start, chosen so both
  arms reach their grasps and both cameras see the needle; the driver takes it with its
  driving grasp at the *tracked* pose, the first arm opens and goes back to its park pose
  (Fig. 6); the driver lifts and checks that it holds.
- **ND**: the grasp the hand-off actually produced, seen by the tracker, is checked and
  the drive planned on it (eq. 3); approach, look again, then turn the needle about its
  centre from the entry to past the exit. From there on the tracker is told the tissue's
  surface (a plane through the incision), which hides the needle's middle. The tracked
  tip must end within ``placement_tolerance`` of the plan: checked here when the tracker
  converges with the jaws still on the needle, else by NR once they have backed off.
- **NR**: release, back off, track the needle standing in the tissue, grasp the tip part
  that stands out of the exit.
- **NP**: turn the needle further along its own arc until the swage is out, then lift.

Frames: the cell's reference frame (the endoscope's left channel, ``ref``) for
everything; the robot base P is ``ref`` here (the cell reports and takes gripper poses in
it, so ``G_PC`` is the identity). Metres and radians.

Not thread-safe: one caller at a time (the daemon runs steps in a worker thread under a
lock).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from typing import Any, Protocol

import cv2
import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from oralnav.control.errors import NeedleError
from oralnav.control.geometry import invert, make_transform, rotation_angle
from oralnav.control.needle.drive import (
    Drive,
    SutureGeometry,
    plan_drive,
    pull_poses,
    tissue_frame,
)
from oralnav.control.needle.features import NeedleFeatures, feature_maps
from oralnav.control.needle.grasp import (
    GraspChoice,
    GraspSettings,
    SurfaceGrasp,
    SurfaceGraspSettings,
    check_drive_grasp,
    grasp_band,
    grasp_parameters,
    grasp_point_angle,
    select_grasp,
    surface_grasps,
)
from oralnav.control.needle.model import Needle
from oralnav.control.needle.refine import hidden_by
from oralnav.control.needle.tracker import (
    FilterSettings,
    NeedleTrack,
    NeedleTracker,
    TissuePlane,
    ToolCylinder,
    TrackSettings,
)
from oralnav.control.vision.camera import CameraModel, Rig
from oralnav.safety.errors import StateError

__all__ = ["STEPS", "NeedleCellPort", "NeedleProcedure", "ProcedureSettings", "StepResult",
           "ViewRule", "port_drives", "port_pair"]

#: The steps in their order (seed 002 §IV.B, Table I).
STEPS = ("NG", "NH", "ND", "NR", "NP")


class NeedleCellPort(Protocol):
    """What the procedure needs of a needle cell (:class:`oralnav.sim.world.needle_cell.NeedleCell`
    is one). Poses are ``T_ref_tool`` (4x4, m) as the arm reports them; ``move`` raises
    when the arm stops short (the simulated cell's ``CellError``)."""

    @property
    def rig(self) -> Rig: ...
    @property
    def cameras(self) -> tuple[str, ...]: ...
    @property
    def needle(self) -> Needle: ...
    @property
    def grippers(self) -> tuple[str, ...]: ...
    def images(self) -> dict[str, np.ndarray]: ...
    def gripper_pose(self, name: str) -> np.ndarray: ...
    def reachable(self, name: str, T_ref_tool: np.ndarray, margin: float = 0.0
                  ) -> tuple[bool, str]: ...
    def reachable_all(self, name: str, T_ref_tool: np.ndarray, margin: float = 0.0
                      ) -> np.ndarray: ...
    def move(self, name: str, T_ref_tool_reported: np.ndarray) -> None: ...
    def close(self, name: str) -> bool: ...
    def open(self, name: str) -> None: ...


@dataclass(frozen=True)
class ProcedureSettings:
    """The procedure's settings. Lengths m, angles rad.

    Suture: ``depth`` (the surgeon's d), ``suture_at`` (where along the incision, 0 its
    start, 1 its end), ``overshoot`` (arc the tip is driven past the exit, for the
    regrasp), ``drive_poses``. Motions: ``approach`` (the offset of every grasp's approach
    pose along the gripper's -z, Fig. 5), ``lift`` (the pick-up's lift; ``lift_low`` when
    no grasp's needle, lifted that far, is seen well), ``retreat`` (an
    opened gripper backs off this much), ``hold_check`` (the hand-off's check motion,
    square to the camera's line of sight where the arm reaches: the tracked needle must
    follow within ``hold_tolerance``); ``pull_tolerance``: how near where the pull took
    the jaws the needle must be seen after it (the regrasp's hold is shown by the pull),
    looked at where the pulled needle, turned about its centre, raised by one of
    ``show_heights`` and moved by one of ``show_shifts`` toward where the reference camera
    looks on the tissue, shows to the cameras (:meth:`NeedleProcedure._show_pose`: first
    where the view passes with ``strict_view_angle`` less face-on angle and
    ``strict_visible`` more of the needle in view);
    ``follow_ratio``: after a long motion a needle this share of the motion's length
    from where the jaws took it still followed them (the tolerance grows with the
    motion: the tracker's error after a turn grows with it, while a needle the jaws let
    go stays where it was, a whole motion away). ``carry_clearance``: how far above the
    tissue a held needle stays while carried; where the straight path would take it
    lower it goes over, raised by the first of ``carry_rises`` that keeps it clear.
    Hand-off: ``handoff_heights`` (the needle raised this much above its drive start pose,
    and turned about its centre as little as will do; and moved by each of
    ``handoff_shifts`` toward where the reference camera looks on the tissue, at most
    all the way: raised and turned where it starts the drive, near the incision, the
    needle is often out of view or edge-on); ``handoff_meetings``: the pick-up
    takes a grasp with at least this many hand-off poses both arms reach and both
    cameras see (else the one with the most), so that the grasp the jaws actually make,
    a few tenths of a millimetre and a few degrees off the planned one, still has one;
    ``separation`` the least arc length between the two grasps; ``view_margin_px`` how far
    inside both images the needle must be; ``min_visible`` the share of the needle no
    gripper may hide in either view, the instruments modelled as jaws (a cylinder of
    ``jaw_radius`` over ``jaw_length`` behind the tip) on a shaft (``tool_radius``, up to
    ``tool_length`` behind the tip); ``max_view_angle`` the largest
    angle between the needle's axis and the reference camera's line of sight (an
    edge-on needle leaves its tilt uncertain). Regrasp: the grasp point stays
    ``regrasp_exit_margin`` (arc) above the exit and ``regrasp_tip_margin`` from the tip.
    Tracking: ``particles``, ``updates`` per look, ``init_updates`` after the global
    initialisation, ``depth_window`` (the initialisation searches the incision's depth
    plus or minus this), ``incision_mask_px`` (the incision line's width masked out of
    the features: a dark line is not the needle); ``max_sigma_position`` and
    ``max_sigma_angle``, the pose uncertainty a step may still move on (the jaws take a
    wire within about 1 mm of where they aim). ``grasp_margin``: the driving grasp is
    chosen this much (arc) further from the swage than the drive needs, and the pick-up
    grasp this much further from it than ``separation``, so that the grasps the arms
    actually make still pass. ``reach_margin`` (rad): plans keep the arms' wrist joints
    this far inside their limits, so that a grasp made a degree or two off its plan, and
    a path between planned poses, stay in reach (the moves and the checks of the grasp
    actually made use the limits themselves). ``placement_tolerance``: how far the tracked needle's
    entry and exit (its arc's crossings of the tissue surface) may lie from the plan's
    (ND fails otherwise), and in the truth check the true ones.
    """

    depth: float = 0.005
    suture_at: float = 0.5
    overshoot: float = 0.008
    drive_poses: int = 60
    pull_poses: int = 30
    swage_clearance: float = 0.002
    pull_lift: float = 0.010
    show_heights: tuple[float, ...] = (0.0, 0.005, 0.010)
    show_shifts: tuple[float, ...] = (0.0, 0.010, 0.020)
    strict_view_angle: float = math.radians(15.0)
    strict_visible: float = 0.1
    approach: float = 0.005
    lift: float = 0.010
    lift_low: float = 0.005
    retreat: float = 0.010
    hold_check: float = 0.003
    hold_tolerance: float = 0.001
    handoff_heights: tuple[float, ...] = (0.015, 0.010, 0.020, 0.025)
    handoff_shifts: tuple[float, ...] = (0.0, 0.010, 0.020)
    handoff_meetings: int = 3
    separation: float = 0.006
    view_margin_px: float = 15.0
    min_visible: float = 0.75
    max_view_angle: float = math.radians(60.0)
    tool_radius: float = 0.003
    tool_length: float = 0.2
    jaw_radius: float = 0.0022
    jaw_length: float = 0.010
    regrasp_exit_margin: float = 0.002
    regrasp_tip_margin: float = 0.0035
    pull_tolerance: float = 0.002
    follow_ratio: float = 0.25
    carry_clearance: float = 0.001
    carry_rises: tuple[float, ...] = (0.01, 0.02, 0.03)
    regrasp_points: int = 7
    replan_shift: float = 0.0003
    replan_turn: float = math.radians(1.5)
    particles: int = 3000
    updates: int = 3
    init_updates: int = 3
    depth_window: float = 0.04
    incision_mask_px: int = 16
    placement_tolerance: float = 0.002
    grasp_margin: float = 0.0015
    reach_margin: float = math.radians(3.0)
    max_sigma_position: float = 0.0005
    max_sigma_angle: float = math.radians(2.5)
    seed: int = 0
    # jaws that close along y_T hold the wire along x_T (w1 = +-pi/2); then the needle's
    # drive turn is mostly a roll about the gripper axis only if the shaft lies near the
    # needle's axis, close to the tissue plane: the elevation floor is relaxed and the
    # clearance rule (tip and 20 mm of shaft 2 mm above the tissue) keeps it off
    drive_grasp: GraspSettings = GraspSettings(w1_values=(math.pi / 2, -math.pi / 2),
                                               w2_steps=36,
                                               min_shaft_elevation=math.radians(-15.0),
                                               approach_elevation=math.radians(5.0))
    pickup_grasp: SurfaceGraspSettings = SurfaceGraspSettings()
    # the tip part stands steeply out of the exit, and a jaw square to the wire then holds
    # the shaft low: the regrasp takes shafts down to 2 deg above the flat pad (the shaft
    # rises away from it; the pull's turn is a roll of the wrist only with the shaft
    # near the needle's axis, and at 5 deg no pull stayed in the wrist's reach on 4 of
    # 40 trials), the wire at least 1.5 mm up so the jaws' lower edge (half their
    # 2.5 mm width below it) stays off the surface; fine gripper angles, since the few
    # that fit are narrow
    regrasp: SurfaceGraspSettings = SurfaceGraspSettings(min_elevation=math.radians(2.0),
                                                         min_tip_height=0.0015,
                                                         w2_steps=72)

    def __post_init__(self) -> None:
        for name in ("overshoot", "approach", "lift", "lift_low", "retreat", "hold_check",
                     "hold_tolerance", "separation", "view_margin_px", "regrasp_exit_margin",
                     "regrasp_tip_margin", "depth_window", "placement_tolerance",
                     "swage_clearance", "pull_lift", "pull_tolerance", "follow_ratio",
                     "carry_clearance", "reach_margin", "strict_view_angle",
                     "strict_visible"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise NeedleError(f"needle procedure: {name} must be >= 0, got {v}")
        if not math.isfinite(self.depth):
            raise NeedleError(f"needle procedure: depth must be finite, got {self.depth}")
        if not 0.0 <= self.suture_at <= 1.0:
            raise NeedleError(f"needle procedure: suture_at must be in [0, 1], got "
                              f"{self.suture_at}")
        if self.drive_poses < 2 or self.pull_poses < 2 or self.updates < 1:
            raise NeedleError("needle procedure: drive_poses and pull_poses must be >= 2, "
                              "updates >= 1")
        if not self.handoff_heights:
            raise NeedleError("needle procedure: handoff_heights needs a value")
        if not self.handoff_shifts or not all(math.isfinite(d) and d >= 0
                                              for d in self.handoff_shifts):
            raise NeedleError(f"needle procedure: handoff_shifts needs values >= 0 (m), got "
                              f"{self.handoff_shifts!r}")
        if self.handoff_meetings < 1:
            raise NeedleError(f"needle procedure: handoff_meetings must be >= 1, got "
                              f"{self.handoff_meetings}")
        if not self.show_heights or not all(math.isfinite(h) and h >= 0
                                            for h in self.show_heights):
            raise NeedleError(f"needle procedure: show_heights needs values >= 0, got "
                              f"{self.show_heights!r}")
        if not self.show_shifts or not all(math.isfinite(d) and d >= 0
                                           for d in self.show_shifts):
            raise NeedleError(f"needle procedure: show_shifts needs values >= 0 (m), got "
                              f"{self.show_shifts!r}")


@dataclass
class StepResult:
    """One step's outcome.

    ``ok``: the procedure's own verdict (what it saw); ``refused``: it stopped before
    moving toward the needle; ``cause``: a short code when not ok (``refused_*`` for
    refusals, e.g. ``refused_not_converged``, ``refused_out_of_reach``,
    ``refused_bad_suture``; ``grasp_missed``, ``move_stopped``, ``lost_track`` ...),
    ``detail`` the sentence; ``figures``: what was measured (mm, deg); ``truth_ok`` /
    ``truth_detail``: the check against the cell's ground truth (``None`` without one);
    ``seconds``: wall time of the step.
    """

    step: str
    ok: bool
    refused: bool = False
    cause: str = ""
    detail: str = ""
    figures: dict[str, Any] = field(default_factory=dict)
    truth_ok: bool | None = None
    truth_detail: str = ""
    seconds: float = 0.0

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


class _StepFailed(Exception):
    """Raised inside a step: ends it with ``cause`` and the message."""

    def __init__(self, cause: str, detail: str, refused: bool = False) -> None:
        super().__init__(detail)
        self.cause, self.detail, self.refused = cause, detail, refused


def _refuse(cause: str, detail: str) -> _StepFailed:
    return _StepFailed(f"refused_{cause}", detail, refused=True)


def _translation(v: np.ndarray) -> np.ndarray:
    return make_transform(t=np.asarray(v, dtype=float))


def _back_off(T: np.ndarray, d: float, tilt: float = 0.0) -> np.ndarray:
    """``T`` moved ``d`` (m) along its own -z (out of the jaws' way), or along -z turned
    by ``tilt`` (rad) about its y: still in the plane of the jaws' faces, so open jaws
    slide off a wire that lies across them without dragging it (the wire runs along x,
    the jaws close along y)."""
    return T @ make_transform(t=[-d * math.sin(tilt), 0.0, -d * math.cos(tilt)])


#: Directions an opened gripper may back off the wire by (rad about its y, from -z):
#: straight first, then ever more aslant, up to 60 deg (the jaws still clear the wire).
_BACK_OFF_TILTS = tuple(math.radians(a) for a in (0, 20, -20, 40, -40, 60, -60))


def _turn_about(axis: np.ndarray, angle: float, point: np.ndarray) -> np.ndarray:
    """A rotation by ``angle`` about the line through ``point`` along ``axis`` (4x4)."""
    a = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    R, _ = cv2.Rodrigues(a * angle)
    T = make_transform(R)
    T[:3, 3] = point - R @ point
    return T


def _turns(step_deg: float = 30.0, axes: int = 40) -> list[np.ndarray]:
    """Rotations (3x3) of angles 0, step, ..., 180 deg about ``axes`` directions spread
    over the sphere (a Fibonacci lattice), the identity first, then by angle."""
    k = np.arange(axes) + 0.5
    z = 1.0 - 2.0 * k / axes
    az = math.pi * (1.0 + 5.0 ** 0.5) * k
    dirs = np.stack([np.sqrt(1 - z * z) * np.cos(az), np.sqrt(1 - z * z) * np.sin(az), z], 1)
    out = [np.eye(3)]
    for a in np.arange(step_deg, 180.0 + 1e-9, step_deg):
        out += [cv2.Rodrigues(d * math.radians(a))[0] for d in dirs]
    return out


#: The hand-off's candidate turns of the needle from its drive start orientation.
_HANDOFF_TURNS = _turns()


def _turned_and_raised(T_N: np.ndarray, normal: np.ndarray, heights: Sequence[float]
                       ) -> Iterator[tuple[np.ndarray, float, float]]:
    """Needle poses near ``T_N`` for a hand-off or a look: turned about the needle's
    centre by each of :data:`_HANDOFF_TURNS` (the least first) and raised along
    ``normal`` by each of ``heights`` (m). Items: ``(T_ref_N, turn (rad), height)``."""
    for turn in _HANDOFF_TURNS:
        angle = rotation_angle(turn, np.eye(3))
        for h in heights:
            T = T_N.copy()
            T[:3, :3] = turn @ T_N[:3, :3]
            T[:3, 3] += h * normal
            yield T, angle, h


#: A checked path's spacing (m, rad): the simulated cell's motion increments, so that a
#: long turn is checked where the cell will check it (a wrist limit crossed between two
#: samples 20 deg apart stops the motion half-way).
_PATH_STEP = 0.001
_PATH_TURN = math.radians(2.0)


def _path(T0: np.ndarray, T1: np.ndarray, n: int | None = None) -> list[np.ndarray]:
    """``n`` poses along the straight-line, slerp path from ``T0`` to ``T1`` (the cell's
    motion), ``T1`` last: a goal the arm reaches by a path it cannot follow is no goal.
    By default at least 8, and one per ``_PATH_STEP`` and per ``_PATH_TURN``."""
    rots = Rotation.from_matrix(np.stack([T0[:3, :3], T1[:3, :3]]))
    if n is None:
        turn = float((rots[0].inv() * rots[1]).magnitude())
        dist = float(np.linalg.norm(T1[:3, 3] - T0[:3, 3]))
        n = max(8, math.ceil(dist / _PATH_STEP), math.ceil(turn / _PATH_TURN))
    f = np.arange(1, n + 1) / n
    R = Slerp([0.0, 1.0], rots)(f).as_matrix()
    out = []
    for k in range(n):
        T = np.eye(4)
        T[:3, :3] = R[k]
        T[:3, 3] = T0[:3, 3] + f[k] * (T1[:3, 3] - T0[:3, 3])
        out.append(T)
    return out


def _pose_error(T: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """Centre distance (mm) and rotation angle (deg) between two needle poses."""
    return (float(np.linalg.norm(T[:3, 3] - T_true[:3, 3])) * 1e3,
            math.degrees(rotation_angle(T[:3, :3], T_true[:3, :3])))


def _drive_pick(s: ProcedureSettings) -> GraspSettings:
    """The drive grasp rule as the plan applies it (``grasp_margin`` more from the swage)."""
    return replace(s.drive_grasp, swage_margin=s.drive_grasp.swage_margin + s.grasp_margin)


def drive_ways(incision: np.ndarray, normal: np.ndarray, geometry: SutureGeometry,
               s: ProcedureSettings) -> list[tuple[str, np.ndarray, Drive]]:
    """The two drives of the suture at ``s.suture_at`` along ``incision`` (2, 3; reference
    frame, m) on the surface of unit ``normal``: ``("as given", G_CS, drive)`` with the
    entry on the side the incision's direction sets, then ``("reversed", ...)``, the same
    point crossed the other way (a backhand stitch for a forehand one). Raises
    :class:`NeedleError` for a degenerate incision or suture."""
    point = incision[0] + s.suture_at * (incision[1] - incision[0])
    out = []
    for ends, way in ((incision, "as given"), (incision[::-1], "reversed")):
        G_CS = tissue_frame(ends[0], ends[1], normal, suture_point=point)
        out.append((way, G_CS, plan_drive(np.eye(4), G_CS, geometry, s.drive_poses,
                                          overshoot=s.overshoot)))
    return out


def _arc_under(needle: Needle, T_N: np.ndarray, point: np.ndarray, normal: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The arc of ``needle`` at ``T_N`` in 721 points: their angles (rad), their
    positions (ref, m) and the indices of those under the surface through ``point`` with
    unit ``normal`` (out of the tissue)."""
    phis = np.linspace(0.0, needle.arc, 721)
    pts = needle.point(phis) @ T_N[:3, :3].T + T_N[:3, 3]
    under = np.nonzero((pts - point) @ normal < 0.0)[0]
    return phis, pts, under


def _tip_part(needle: Needle, T_N: np.ndarray, point: np.ndarray, normal: np.ndarray,
              s: ProcedureSettings) -> tuple[float, float, float]:
    """The tip part out of the tissue with the needle at ``T_N`` (surface as in
    :func:`_arc_under`): the regrasp may hold it from ``phi_lo`` to ``phi_hi`` (rad;
    empty when ``hi < lo``); and how far the tip stands out along the arc (mm)."""
    r, arc = needle.radius, needle.arc
    phis, _, under = _arc_under(needle, T_N, point, normal)
    cross = phis[under[-1]] if under.size else 0.0
    return (cross + s.regrasp_exit_margin / r, arc - s.regrasp_tip_margin / r,
            (arc - cross) * r * 1e3)


def _tip_grasps(needle: Needle, T_N: np.ndarray, point: np.ndarray, normal: np.ndarray,
                s: ProcedureSettings, lo: float, hi: float) -> list[SurfaceGrasp]:
    """The regrasp's candidates on the tip part ``lo``..``hi`` (rad) of the needle at
    ``T_N``, the steepest shafts first. The tip part rises steeply out of the exit, and
    a jaw square to the wire holds the shaft at most (90 deg - the wire's rise) above
    the surface: the grasps along the whole tip part (nearer the exit the wire leans
    more, further out it stands higher)."""
    grasps = [g for phi in np.linspace(lo, hi, s.regrasp_points)
              for g in surface_grasps(needle, T_N, float(phi), point, normal, s.regrasp)]
    grasps.sort(key=lambda g: -g.elevation)
    return grasps


def _pulls(needle: Needle, s: ProcedureSettings, reachable: Callable[[np.ndarray], bool],
           T_N: np.ndarray, G_CS: np.ndarray, point: np.ndarray, normal: np.ndarray) -> bool:
    """Whether an arm that reaches a pose when ``reachable(T_ref_T)`` can regrasp the tip
    of the needle standing at ``T_N`` in the tissue of frame ``G_CS`` (surface through
    ``point`` with ``normal``) and pull it out along the planned pull."""
    lo, hi, _ = _tip_part(needle, T_N, point, normal, s)
    if hi < lo:
        return False
    for g in _tip_grasps(needle, T_N, point, normal, s, lo, hi):
        if not (reachable(g.T_ref_T) and reachable(_back_off(g.T_ref_T, s.approach))):
            continue
        try:
            pull = pull_poses(np.eye(4), G_CS, T_N, g.G_TN, needle, s.pull_poses,
                              s.swage_clearance, s.pull_lift)
        except NeedleError:
            continue
        if all(reachable(T) for T in pull.G_PT):
            return True
    return False


def _driver_choice(ways: Sequence[tuple[str, np.ndarray, Drive]],
                   choose: Mapping[str, Callable[[int], GraspChoice]]
                   ) -> tuple[tuple[str, np.ndarray, Drive], str, GraspChoice]:
    """The plan's driver: of the first of ``ways`` that some arm can drive
    (``choose[arm](k)``: its driving grasp for ``ways[k]``, :func:`select_grasp`'s, or
    :class:`NeedleError`), the arm whose grasp scores best. ``(way item, arm, grasp)``;
    :class:`NeedleError` naming every arm's refusal when none drives either way."""
    why: dict[str, str] = {}
    for k, chosen in enumerate(ways):
        options = []
        for arm, pick in choose.items():
            try:
                choice = pick(k)
            except NeedleError as exc:
                why[f"{arm} ({chosen[0]})"] = str(exc)
                continue
            options.append((choice.score, arm, choice))
        if options:
            _, arm, choice = max(options, key=lambda o: o[0])
            return chosen, arm, choice
    raise NeedleError("no arm can drive this suture either way: "
                      + "; ".join(f"{a}: {w}" for a, w in why.items()))


def _pickup_phis(needle: Needle, s: ProcedureSettings, phi_B: float) -> np.ndarray:
    """The pick-up grasp's candidate points (rad along the arc) in the grasp band, clear
    of the driving grasp at ``phi_B`` by ``separation + grasp_margin``: the hand-off
    puts both jaws on the needle. Empty when the band leaves no room."""
    lo, hi = grasp_band(needle, s.drive_grasp)
    gap = (s.separation + s.grasp_margin) / needle.radius
    free = [(max(lo, phi_B + gap), hi), (lo, min(hi, phi_B - gap))]
    return np.concatenate([np.linspace(a, b, 7) for a, b in free if b >= a] or [[]])


def _shifted(T: np.ndarray, normal: np.ndarray, toward: np.ndarray,
             shifts: Sequence[float]) -> Iterator[np.ndarray]:
    """The pose ``T`` moved in the plane square to ``normal`` toward ``toward`` (3,) by
    each of ``shifts`` (m), no further than all the way there; a shift that comes out the
    same as an earlier one is not repeated."""
    d = toward - T[:3, 3]
    d -= float(d @ normal) * normal
    far = float(np.linalg.norm(d))
    done: set[float] = set()
    for shift in shifts:
        shift = min(shift, far)
        if shift in done:
            continue
        done.add(shift)
        moved = T.copy()
        if shift > 0:
            moved[:3, 3] += shift / far * d
        yield moved


def _handoff_poses(drive: Drive, G_TN_B: np.ndarray, normal: np.ndarray, s: ProcedureSettings,
                   reach_all: Callable[[np.ndarray], np.ndarray], toward: np.ndarray
                   ) -> list[tuple[np.ndarray, np.ndarray, float, float]]:
    """Needle poses for the hand-off where the driver, gripping with ``G_TN_B``, reaches
    its driving grasp and its approach (``reach_all(T (N, 4, 4)) -> (N,) bool``): the
    drive's start pose moved by each of ``handoff_shifts`` in the tissue plane toward
    ``toward`` (3,; no further than it), raised ``handoff_heights`` above the tissue and
    turned about the needle's centre, the least shift, then the least turn first.
    Items: ``(T_ref_N, driver's T_ref_T, turn (rad), height (m))``."""
    start = drive.G_PS @ drive.G_SN[0]
    items: list[tuple[np.ndarray, float, float]] = []
    for moved in _shifted(start, normal, toward, s.handoff_shifts):
        items += _turned_and_raised(moved, normal, s.handoff_heights)
    T_B = np.stack([T for T, _, _ in items]) @ invert(G_TN_B)
    ok = reach_all(T_B)
    ok[ok] &= reach_all(_back_off(T_B[ok], s.approach))
    return [(T_h, T_B[k], turn, H) for k, (T_h, turn, H) in enumerate(items) if ok[k]]


def _meetings(handoffs: Sequence[tuple], G_TN_A: np.ndarray,
              reach_all: Callable[[np.ndarray], np.ndarray], views: ViewRule, most: int,
              T_A0: np.ndarray | None = None, why: dict[str, int] | None = None,
              holder: str = "the holder",
              also: Callable[[tuple], str] | None = None) -> list[tuple]:
    """The first ``most`` of the hand-off candidates ``handoffs`` (:func:`_handoff_poses`'
    items) where the holder, gripping with ``G_TN_A``, reaches (``reach_all``; along its
    straight path from ``T_A0``, when given), the cameras see the needle past both
    grippers (``views``) and ``also(item)`` (when given) names no refusal; ``why``
    counts the refusals, naming ``holder``."""
    if not handoffs:
        return []
    why = {} if why is None else why
    T_A = np.stack([item[0] for item in handoffs]) @ invert(G_TN_A)
    there = reach_all(T_A)
    out = []
    for k, item in enumerate(handoffs):
        if not there[k]:
            refused = f"{holder} cannot hold it there"
        elif seen := views.why_not(item[0], [item[1], T_A[k]]):
            refused = f"hand-off {seen}"
        # the path last: the costliest check, for the few poses that pass the others
        elif T_A0 is not None and not reach_all(np.stack(_path(T_A0, T_A[k]))).all():
            refused = f"{holder} cannot carry it there"
        else:
            refused = also(item) if also is not None else ""
        if refused:
            why[refused] = why.get(refused, 0) + 1
            continue
        out.append(item)
        if len(out) >= most:
            break
    return out


def port_drives(needle: Needle, settings: ProcedureSettings | None = None
                ) -> Callable[[Any, np.ndarray, np.ndarray], bool]:
    """Entry port selection (seed 002's grasp rule comes from its ref. [8], Liu and
    Cavusoglu, "Needle grasp and entry port selection ..."): a check
    ``drives(reach, incision, normal) -> bool`` of whether an arm whose reach is ``reach``
    (``reach.reachable(T_ref_tool, margin) -> (ok, why)``, as the simulator's
    ``ArmReach``) can drive the planned suture either way with a grasp the plan would
    choose and then, from the same port, regrasp the tip where the planned drive leaves
    it and pull the needle out (seed 002's needle driving, its five steps; the driver
    regrasps first, :meth:`NeedleProcedure._step_nr`), for a cell set up before the
    procedure (the planner's own rules and margin, :meth:`NeedleProcedure._plan`). A
    suture the settings refuse drives from no port."""
    s = settings or ProcedureSettings()
    pick = _drive_pick(s)
    try:
        geometry = SutureGeometry.for_needle(needle, s.depth)
    except NeedleError:
        geometry = None

    def drives(reach: Any, incision: np.ndarray, normal: np.ndarray) -> bool:
        if geometry is None:
            return False

        def reachable(T: np.ndarray) -> bool:
            return bool(reach.reachable(T, s.reach_margin)[0])

        try:
            ways = drive_ways(np.asarray(incision, float), np.asarray(normal, float),
                              geometry, s)
        except NeedleError:
            return False
        point = np.mean(np.asarray(incision, float), axis=0)
        normal = np.asarray(normal, float)
        for _, G_CS, drive in ways:
            try:
                select_grasp(needle, drive, pick, reachable=reachable)
            except NeedleError:
                continue
            if _pulls(needle, s, reachable, G_CS @ drive.G_SN[-1], G_CS, point, normal):
                return True
        return False

    return drives


def port_pair(needle: Needle, settings: ProcedureSettings | None = None
              ) -> Callable[..., bool]:
    """Entry port selection for the pair of arms: a check ``workable(reaches, incision,
    normal, T_ref_needle, rig, outline) -> bool`` of whether, with each arm ``name`` at
    the port of ``reaches[name]`` (as :func:`port_drives`'s ``reach``, with
    ``reachable_all(T (N, 4, 4), margin) -> (N,) bool`` too), the plan's driver
    (:meth:`NeedleProcedure._plan`) drives the suture and pulls the needle out, and the
    other arm picks up the needle lying at ``T_ref_needle`` (reference frame, m) with a
    grasp the pick-up would make (NG: clear of the driving grasp, reached with its
    approach and its lift, the lifted needle seen) that can carry the needle from its
    lift to ``handoff_meetings`` of the hand-off poses the driver reaches (a straight
    path, as NH's), the cameras of ``rig``
    seeing the needle there past both grippers (NH; the tissue's ``outline`` (k, 3) as
    :class:`ViewRule`'s, or ``None``).

    A trial asks about many pairs of a few sites each: what one arm's site decides (its
    driving grasps, its pull, the hand-off poses it reaches and the cameras see) is
    kept for the scene last asked about."""
    s = settings or ProcedureSettings()
    pick = _drive_pick(s)
    m = s.reach_margin
    try:
        geometry = SutureGeometry.for_needle(needle, s.depth)
    except NeedleError:
        geometry = None
    memo: dict[Any, Any] = {}

    def workable(reaches: Mapping[str, Any], incision: np.ndarray, normal: np.ndarray,
                 T_ref_needle: np.ndarray, rig: Rig, outline: np.ndarray | None = None
                 ) -> bool:
        if geometry is None or len(reaches) != 2:
            return False
        incision = np.asarray(incision, float)
        normal = np.asarray(normal, float) / np.linalg.norm(normal)
        T_ref_needle = np.asarray(T_ref_needle, float)
        scene = (incision.tobytes(), normal.tobytes(), T_ref_needle.tobytes(), id(rig),
                 None if outline is None else np.asarray(outline).tobytes())
        if memo.get("scene") != scene:
            memo.clear()
            memo["scene"] = scene
            try:
                memo["ways"] = drive_ways(incision, normal, geometry, s)
            except NeedleError:
                memo["ways"] = None
            memo["views"] = ViewRule([rig[c] for c in rig.names], needle, s, normal, outline)
        ways, views = memo["ways"], memo["views"]
        if ways is None:
            return False
        point = incision.mean(axis=0)
        one = {a: (lambda T, r=r: bool(r.reachable(T, m)[0])) for a, r in reaches.items()}

        def site(a: str) -> bytes:
            return reaches[a].rcm.tobytes()

        def grasp(a: str, k: int) -> GraspChoice:
            key = ("grasp", site(a), k)
            if key not in memo:
                try:
                    memo[key] = select_grasp(needle, ways[k][2], pick, reachable=one[a])
                except NeedleError as exc:
                    memo[key] = exc
            if isinstance(memo[key], NeedleError):
                raise memo[key]
            return memo[key]

        try:
            way, B, choice = _driver_choice(ways, {a: (lambda k, a=a: grasp(a, k))
                                                   for a in reaches})
        except NeedleError:
            return False
        _, G_CS, drive = way
        key = ("driver", site(B), way[0])
        if key not in memo:
            # the driver's side: it pulls, and the hand-off poses it reaches that the
            # cameras see past its own gripper
            meet: list[tuple] = []
            if _pulls(needle, s, one[B], G_CS @ drive.G_SN[-1], G_CS, point, normal):
                meet = [item for item in _handoff_poses(
                    drive, choice.G_TN, normal, s, lambda T: reaches[B].reachable_all(T, m),
                    views.aim(point)) if not views.why_not(item[0], [item[1]])]
            memo[key] = meet
        meet = memo[key]
        if not meet:
            return False
        A = next(a for a in reaches if a != B)
        lifts = [_translation(h * normal) for h in sorted({s.lift, min(s.lift, s.lift_low)})]
        for phi in _pickup_phis(needle, s, choice.phi):
            for g in surface_grasps(needle, T_ref_needle, float(phi), point, normal,
                                    s.pickup_grasp):
                if not (one[A](g.T_ref_T) and one[A](_back_off(g.T_ref_T, s.approach))):
                    continue
                # from each lift that the arm reaches and the cameras see, as NG's and
                # NH's: the holder carries the needle there on a straight path
                for up in lifts:
                    if not one[A](up @ g.T_ref_T) \
                            or views.why_not(up @ T_ref_needle, [up @ g.T_ref_T]):
                        continue
                    if len(_meetings(meet, g.G_TN,
                                     lambda T: reaches[A].reachable_all(T, m), views,
                                     s.handoff_meetings, up @ g.T_ref_T)
                           ) >= s.handoff_meetings:
                        return True
        return False

    return workable


@dataclass(frozen=True, eq=False)
class ViewRule:
    """Whether the cameras ``cams`` (the reference camera first) would see ``needle`` well
    at a pose: the planner's view rule (the ``view_*``, ``*_visible`` and tool settings
    of ``s``), for the procedure and for port selection alike. ``normal`` (3,): the
    tissue's unit normal; ``outline`` (k, 3): its extent (reference frame, m; ``None``:
    not asked); ``masks``: per camera, the incision line's band the features ignore
    (``None``: not asked)."""

    cams: Sequence[CameraModel]
    needle: Needle
    s: ProcedureSettings
    normal: np.ndarray
    outline: np.ndarray | None = None
    masks: Sequence[np.ndarray] | None = None

    def sight(self, T_ref_N: np.ndarray) -> np.ndarray:
        """The reference camera's line of sight to the needle's centre at ``T_ref_N``
        (unit, reference frame): the views measure depth along it to about a
        millimetre, across it to a tenth."""
        v = T_ref_N[:3, 3] - self.cams[0].T_ref_cam[:3, 3]
        return v / np.linalg.norm(v)

    def aim(self, point: np.ndarray) -> np.ndarray:
        """Where the reference camera's optical axis meets the tissue plane through
        ``point`` (3,, reference frame, m): the middle of its view of the tissue; ``point``
        itself when the axis runs along the plane."""
        o, z = self.cams[0].T_ref_cam[:3, 3], self.cams[0].T_ref_cam[:3, 2]
        den = float(z @ self.normal)
        if abs(den) < 1e-9:
            return np.asarray(point, float)
        return o + float((point - o) @ self.normal) / den * z

    def why_not(self, T_ref_N: np.ndarray, tools: Sequence[np.ndarray] = (),
                incision: bool = False, strict: bool = False) -> str:
        """Why the cameras would not see the needle well at ``T_ref_N`` ("" when they
        would): every camera must see the whole needle ``view_margin_px`` inside the
        image, no more than ``1 - min_visible`` of it behind the grippers at ``tools``
        (their ``T_ref_T``), with ``incision``, in the incision line's band the
        features ignore (``incision_mask_px``), and, with an outline, off the tissue
        surface; the reference view at most ``max_view_angle`` from face-on. (The
        hand-off does not ask ``incision``: near the entry the line crosses most
        views of the needle, and the carried pose holds the parts it hides; the
        pulled needle's look, which must show the hold by the images alone, does.)
        ``strict``: with room for a pose a few millimetres and degrees off the one
        asked about, ``strict_view_angle`` less face-on angle and ``strict_visible``
        more of the needle in view."""
        s = self.s
        pts = self.needle.points(48) @ T_ref_N[:3, :3].T + T_ref_N[:3, 3]
        masks = self.masks if self.masks is not None else [None] * len(self.cams)
        facing = abs(float(T_ref_N[:3, 2] @ self.sight(T_ref_N)))
        max_angle = s.max_view_angle - (s.strict_view_angle if strict else 0.0)
        min_visible = min(1.0, s.min_visible + (s.strict_visible if strict else 0.0))
        if facing < math.cos(max_angle):
            return "edge-on to the camera"
        m = s.view_margin_px
        for cam, masked in zip(self.cams, masks, strict=True):
            uv = cam.project_from(cam.T_cam_ref, pts)
            if not (np.all(np.isfinite(uv)) and np.all(uv >= m)
                    and np.all(uv[:, 0] <= cam.width - 1 - m)
                    and np.all(uv[:, 1] <= cam.height - 1 - m)):
                return "out of view"
            hidden = np.zeros(len(pts), dtype=bool)
            for T in tools:
                hidden |= self.behind_tool(cam, uv, T)
            if 1.0 - hidden.mean() < min_visible:
                return "hidden by the grippers"
            if incision and masked is not None:
                # the features ignore the line's band (a dark line is not the wire)
                px = np.round(uv).astype(int)
                hidden |= masked[px[:, 1], px[:, 0]]
                if 1.0 - hidden.mean() < min_visible:
                    return "hidden by the incision line"
            if self.outline is not None:
                hidden |= ~self.backdrop(cam, pts)
                if 1.0 - hidden.mean() < min_visible:
                    return "hidden or not against the tissue"
        return ""

    def tool_parts(self, T_ref_T: np.ndarray) -> tuple[ToolCylinder, ToolCylinder]:
        """The gripper at ``T_ref_T`` as the parts that may hide the needle: its jaws (a
        cylinder of ``jaw_radius`` over ``jaw_length`` behind the tip) and its shaft
        (``tool_radius``, on to ``tool_length`` behind the tip)."""
        s = self.s
        tip, z = T_ref_T[:3, 3], T_ref_T[:3, 2]
        heel = tip - s.jaw_length * z
        return (ToolCylinder(tip, heel, s.jaw_radius),
                ToolCylinder(heel, tip - s.tool_length * z, s.tool_radius))

    def behind_tool(self, cam: CameraModel, uv: np.ndarray, T_ref_T: np.ndarray
                    ) -> np.ndarray:
        """Which image points ``uv`` (k, 2) the gripper at ``T_ref_T`` may hide. Depth is
        ignored, so a point in front of the tool counts as hidden too: the estimate errs
        toward refusing a view."""
        return hidden_by(self.tool_parts(T_ref_T), cam, uv)

    def backdrop(self, cam: CameraModel, pts: np.ndarray) -> np.ndarray:
        """Which of ``pts`` (k, 3, ref) ``cam`` sees against the tissue: the ray through
        the point meets the tissue plane beyond it, inside the outline (a convex polygon
        in the plane)."""
        assert self.outline is not None
        o = cam.T_ref_cam[:3, 3]
        n, p0 = self.normal, self.outline[0]
        d = pts - o
        den = d @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = ((p0 - o) @ n) / den
        beyond = np.abs(den) > 1e-12
        beyond &= lam > 1.0             # the surface must lie beyond the needle
        hit = o + np.where(beyond, lam, 0.0)[:, None] * d
        edges = np.roll(self.outline, -1, axis=0) - self.outline
        # the polygon's winding about the normal: inside is on the same side of every edge
        sign = 1.0 if float(np.cross(edges[0], edges[1]) @ n) >= 0 else -1.0
        inside = beyond
        for a, e in zip(self.outline, edges, strict=True):
            inside &= sign * (np.cross(e, hit - a) @ n) > 0
        return inside


class NeedleProcedure:
    """The five steps on one cell (see the module docstring).

    ``incision`` (2, 3): the suture line's start and end on the tissue surface, ``ref``
    frame (m): the operator's input (seed 002 finds it by vision); ``surface_normal``
    (3,): the tissue surface's normal, out of the tissue. ``surface_outline`` (k, 3),
    optional: the tissue surface's corners in order (a convex polygon, ``ref``); when
    given, the needle is only carried where both cameras see it against the tissue (the
    thin-feature measurement finds a wire darker than what lies behind it).
    ``arms``: the two grippers to use (default: the cell's). The steps run in order, each
    once: :meth:`run` refuses a step out of turn (:class:`~oralnav.safety.errors.StateError`).
    """

    def __init__(self, cell: NeedleCellPort, incision: np.ndarray, surface_normal: np.ndarray,
                 settings: ProcedureSettings | None = None,
                 arms: Sequence[str] | None = None,
                 surface_outline: np.ndarray | None = None) -> None:
        self.cell = cell
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
                                   max_sigma_angle=s.max_sigma_angle))
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
        """Run ``step`` (one of :data:`STEPS`, in order). Raises :class:`StateError` for a
        step out of turn or after a failure; otherwise returns the result, refusals and
        failures included. A refused step is not done: it may be asked again
        (:attr:`refusals` keeps the refusals); a failed one ends the procedure."""
        step = step.upper()
        if step not in STEPS:
            raise StateError(f"unknown needle step {step!r}; the steps are {list(STEPS)}")
        nxt = self.next_step
        if step != nxt:
            if nxt is None:
                failed = [k for k, r in self.results.items() if not r.ok]
                why = (f"step {failed[0]} failed ({self.results[failed[0]].detail})"
                       if failed else "all steps are done")
                raise StateError(f"needle step {step} cannot run: {why}; load a new cell")
            raise StateError(f"needle step {step} cannot run yet: {nxt} comes first")
        t0 = time.perf_counter()
        res = StepResult(step, ok=False)
        try:
            figures = getattr(self, f"_step_{step.lower()}")()
            res.ok, res.figures = True, figures
        except _StepFailed as exc:
            res.cause, res.detail, res.refused = exc.cause, exc.detail, exc.refused
        res.seconds = round(time.perf_counter() - t0, 3)
        self._check_truth(res)
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

    # -- tracking -------------------------------------------------------------------------
    def _features(self) -> list[NeedleFeatures]:
        imgs = self.cell.images()
        return [feature_maps(imgs[cam.name], w, ignore=m)
                for cam, w, m in zip(self.cams, self._wire_px, self._masks, strict=True)]

    def _look(self, delta: np.ndarray | None = None, *, static: bool = True,
              init: bool = False, trusted: bool = True) -> NeedleTrack:
        """Track on fresh frames: a global initialisation (``init``), or ``updates``
        updates, the first predicted with the gripper's motion ``delta`` (a held needle),
        the others with no motion (``static``: held or in the tissue, the grasped noise)
        or Brownian motion (free). ``trusted=False``: the first motion is what a check
        tests, or the jaws closed since the last look (the tracker carries only the
        slide, :meth:`.NeedleTracker.predict`)."""
        s = self.s
        still = np.eye(4) if static else None
        # the grippers where they are now hide part of the needle
        self.tracker.set_tools([part for a in self.arms
                                for part in self._tool_parts(self.cell.gripper_pose(a))])
        if init:
            tr = self.tracker.initialize(self._features(), self._depth_range)
            for _ in range(s.init_updates):
                self.tracker.predict(still)
                tr = self.tracker.update(self._features())
        else:
            tr = None
            for k in range(s.updates):
                self.tracker.predict(delta if k == 0 and delta is not None else still,
                                     trusted=trusted or k > 0)
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
        try:
            self.cell.move(arm, T)
        except Exception as exc:   # the cell's own error type; the arm stopped short
            raise _StepFailed("move_stopped", f"{what}: {exc}") from None

    def _reach(self, arm: str, poses: Sequence[np.ndarray], margin: float | None = None
               ) -> tuple[bool, str]:
        """Whether ``arm`` reaches every pose, and the limit that refuses one. Plans keep
        the wrist ``reach_margin`` inside its limits (``margin``, rad, by default); a
        check of what is about to run on the grasp actually made passes 0."""
        m = self.s.reach_margin if margin is None else margin
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
        pts = self.needle.points(48)
        base = self.incision.mean(axis=0)
        low = math.inf
        for T in poses:
            P = T @ G_TN
            low = min(low, float(((pts @ P[:3, :3].T + P[:3, 3] - base) @ self.normal).min()))
        return low

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
            rise = _translation(h * self.normal)
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
            move = _translation(self.s.hold_check * w)
            if (self._reach(arm, [move @ T], 0.0)[0]
                    and not self._view(move @ T_N, [move @ T])):
                return move @ T
        return _translation(self.s.hold_check * self.normal) @ T

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
                    raise _StepFailed("grasp_missed",
                                      f"{what}: the needle did not follow the jaws: the look "
                                      f"places it {off * 1e3:.2f} mm from where it was, though "
                                      f"it did not converge ({stayed.reason})")
                raise _StepFailed("lost_track", f"{what}: the tracker lost the needle after "
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
            raise _StepFailed("hold_unseen", f"{what}: the check motion turned the needle "
                                             "along its own arc, and the views do not show "
                                             "its ends: whether it followed is unseen")
        verdicts = []
        for dist in measures:
            off, stay = (dist(tr.pose, T) for T in (moved, before))
            allowed = max(tolerance, self.s.follow_ratio * stay)
            verdicts.append((off <= allowed and off < stay, off, allowed, stay))
        if not any(v[0] for v in verdicts):
            _, off, allowed, stay = verdicts[0]
            raise _StepFailed("grasp_missed",
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

    def _tool_parts(self, T_ref_T: np.ndarray) -> tuple[ToolCylinder, ToolCylinder]:
        return self.views.tool_parts(T_ref_T)

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
            pick = _drive_pick(s)
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
            up = _translation(lift * self.normal)
            for g in grasps:
                ok, _ = self._reach(arm, [g.T_ref_T, _back_off(g.T_ref_T, s.approach),
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
        self._move(arm, _back_off(g.T_ref_T, s.approach), "pick-up approach")
        self._move(arm, g.T_ref_T, "pick-up reach")
        self.cell.close(arm)
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
        approach = _back_off(T_B, self.s.approach)
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
            raise _StepFailed("lost_track", f"hand-off: the tracker lost the needle at the "
                                            f"hand-off pose ({tr.reason})")
        T_B = tr.pose @ invert(self.drive_choice.G_TN)
        ok, why = self._reach(B, self._driver_path(self.cell.gripper_pose(B), T_B), 0.0)
        if not ok:
            raise _StepFailed("out_of_reach", f"hand-off: {B!r} cannot reach the needle where "
                                              f"it was carried ({why})")
        self._move(B, _back_off(T_B, s.approach), "hand-off approach")
        self._move(B, T_B, "hand-off reach")
        self.cell.close(B)
        self.cell.open(A)
        self.holder = B
        for goal, what in ((_back_off(self.cell.gripper_pose(A), s.retreat), "back off"),
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
        T_app = self.cell.gripper_pose(B)
        for k, T in enumerate(drive.G_PT):
            self._move(B, T, f"drive pose {k + 1} of {len(drive.G_PT)}")
        self.in_tissue = True
        # from here the tissue hides the needle's middle: the tracker must not take it
        # for missing wire
        self.tracker.set_occluder(TissuePlane(self.incision.mean(axis=0), self.normal))
        tr = self._look(self.cell.gripper_pose(B) @ invert(T_app))
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
        return {"grasp_phi_deg": round(math.degrees(choice.phi), 2),
                "min_tip_clearance_mm": round(choice.min_tip_clearance * 1e3, 2),
                "tip_seen_from_plan_mm": round(float(np.linalg.norm(tip_seen - tip_plan))
                                               * 1e3, 3),
                "approach_look_converged": approach_look,
                "tracked_after_drive": tr.converged,
                "seen_in_the_jaws": ("not converged" if not tr.converged
                                     else "as planned" if seen is None else str(seen))}

    def _arc_under(self, T_N: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:func:`_arc_under` on this procedure's tissue surface."""
        return _arc_under(self.needle, T_N, self.incision.mean(axis=0), self.normal)

    def _check_exit(self, T_N: np.ndarray, what: str) -> None:
        """Fail unless the needle tracked at ``T_N`` went in and came out where the drive
        planned it (:meth:`_exit_error`)."""
        failure = self._exit_error(T_N, what)
        if failure is not None:
            raise failure

    def _exit_error(self, T_N: np.ndarray, what: str) -> _StepFailed | None:
        """Why the needle tracked at ``T_N`` does not lie where the drive put it (``None``
        when it does): its arc must cross the tissue surface, both ends above it, within
        ``placement_tolerance`` of the planned entry and exit points. That is the
        suture's bite, which the truth check judges too. The crossings do not depend on
        the needle's slide along its own circle, which the views fix only at its ends
        (seen near the pad's edge, or edge-on, an end misread by a few pixels moves the
        tip by millimetres); how far the tip went is the regrasp's concern
        (:func:`_tip_part`), and the distance of the tracked tip from the plan's end is
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
            return _StepFailed("not_in_tissue", f"{what}: none of the tracked needle lies "
                                                f"under the tissue surface ({seen} from the "
                                                "plan)")
        ends = [name for name, i in (("swage", 0), ("tip", len(pts) - 1)) if i in under]
        bad = [k for k in ("entry", "exit") if offs[k] > tol]
        if ends or bad:
            why = (f"the {' and the '.join(ends)} under the surface" if ends
                   else f"{' and '.join(bad)} off the plan")
            return _StepFailed("exit_missed",
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
        self.cell.open(B)
        self.holder = None
        self._back_off_released(B, "regrasp")
        T_N = self._converged("regrasp")
        self._check_exit(T_N, "regrasp")
        point = self.incision.mean(axis=0)
        phi_lo, phi_hi, out_mm = _tip_part(self.needle, T_N, point, self.normal, s)
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
                approach = _back_off(g.T_ref_T, s.approach)
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
            goal = _back_off(T0, self.s.retreat, tilt)
            ok, why = self._reach(arm, _path(T0, goal), 0.0)
            if ok:
                self._move(arm, goal, f"{what}: the released gripper's back-off")
                return
        raise _StepFailed("move_stopped", f"{what}: the released gripper cannot back off "
                                          f"the needle in any direction that clears the "
                                          f"jaws ({why})")

    def _regrasp(self, arm: str, g: SurfaceGrasp, pull: Any, out_mm: float
                 ) -> dict[str, Any]:
        s = self.s
        self._move(arm, _back_off(g.T_ref_T, s.approach), "regrasp approach")
        self._move(arm, g.T_ref_T, "regrasp reach")
        self.cell.close(arm)
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
            raise _StepFailed("still_in_tissue", f"pull: the tracked needle is still "
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
        for T_s, turn, _ in candidates:
            T_g = T_s @ G_NT
            if not (self._reach(arm, [T_g])[0]
                    and self._reach(arm, _path(here, T_g), leave)[0]):
                continue
            if self._lowest(_path(here, T_g, 32), G_TN) < s.carry_clearance:
                continue
            moves.append((T_s, T_g, turn))
        for strict, incision in ((True, True), (False, True), (False, False)):
            for T_s, T_g, turn in moves:
                if not self._view(T_s, [T_g, *others], incision=incision, strict=strict):
                    return T_g, turn
        return None

    # -- truth ----------------------------------------------------------------------------
    def _check_truth(self, res: StepResult) -> None:
        """Fill ``res.truth_ok`` from the cell's ground truth, when it has one."""
        truth_fn = getattr(self.cell, "truth", None)
        if truth_fn is None:
            return
        t = truth_fn()
        if self.track is not None:
            e_pos, e_ang = _pose_error(self.track.pose, t.T_ref_needle)
            res.figures["track_error_mm"] = round(e_pos, 3)
            res.figures["track_error_deg"] = round(e_ang, 2)
        held = set(t.held_by)
        step = res.step
        if step == "NG":
            ok = self.picker is not None and self.picker in held
            why = f"held by {sorted(held)}"
        elif step == "NH":
            ok = self.driver is not None and held == {self.driver}
            why = f"held by {sorted(held)}"
        elif step == "ND":
            ok, why = self._placement_truth(t)
        elif step == "NR":
            arm = self.holder
            ok = arm is not None and arm in held and t.in_tissue
            why = f"held by {sorted(held)}, in tissue {t.in_tissue}"
        else:
            ok = t.out_of_tissue_after_pull and bool(held)
            why = f"out of the tissue {t.out_of_tissue_after_pull}, held by {sorted(held)}"
        res.truth_ok = bool(ok and res.ok)
        res.truth_detail = why

    def _placement_truth(self, t: Any) -> tuple[bool, str]:
        """ND against truth: the tip went in and came out within the placement tolerance
        of the planned entry and exit."""
        if self.geometry is None or t.entry is None or t.exit is None:
            return False, (f"entry {'none' if t.entry is None else 'made'}, exit "
                           f"{'none' if t.exit is None else 'made'}")
        e_in = float(np.linalg.norm(t.entry - self._to_ref(self.geometry.entry)))
        e_out = float(np.linalg.norm(t.exit - self._to_ref(self.geometry.exit)))
        tol = self.s.placement_tolerance
        return (e_in <= tol and e_out <= tol,
                f"entry {e_in * 1e3:.2f} mm, exit {e_out * 1e3:.2f} mm from the plan "
                f"(tolerance {tol * 1e3:.1f} mm)")


def step_rates(outcomes: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Table I/II figures from per-trial outcomes (``{"steps": {step: truth_ok or None}}``):
    overall rates (a step not reached counts as failed) and individual rates (of the
    trials that reached the step)."""
    n = len(outcomes)
    overall, individual = {}, {}
    for st in STEPS:
        ok = sum(1 for o in outcomes if o["steps"].get(st) is True)
        reached = sum(1 for o in outcomes if o["steps"].get(st) is not None)
        overall[st] = ok / n if n else 0.0
        individual[st] = ok / reached if reached else None
    done = sum(1 for o in outcomes if all(o["steps"].get(st) is True for st in STEPS))
    return {"trials": n, "overall": done / n if n else 0.0, "steps": overall,
            "individual": individual}
