"""The needle procedure's settings (lengths m, angles rad): the suture, the motions, the
hand-off, the views, the regrasp and the tracking, checked when built."""

from __future__ import annotations

import math
from dataclasses import dataclass

from oralnav.control.errors import NeedleError
from oralnav.control.needle.grasp import GraspSettings, SurfaceGraspSettings
from oralnav.control.needle.servo import ServoSettings


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
    initialisation, ``init_attempts`` global initialisations before the first look gives up
    (each on fresh frames and particles), ``depth_window`` (the initialisation searches the
    incision's depth plus or minus this), ``incision_mask_px`` (the incision line's width
    masked out of the features: a dark line is not the needle); ``max_sigma_position`` and
    ``max_sigma_angle``, the pose uncertainty a step may still move on (the jaws take a wire
    within about 1 mm of where they aim). ``grasp_margin``: the driving grasp is chosen this
    much (arc) further from the swage than the drive needs, and the pick-up grasp this much
    further from it than ``separation``, so that the grasps the arms actually make still
    pass. ``reach_margin`` (rad): plans keep the arms' wrist joints this far inside their
    limits, so that a grasp made a degree or two off its plan, and a path between planned
    poses, stay in reach (the moves and the checks of the grasp actually made use the limits
    themselves). ``placement_tolerance``: how far the tracked needle's entry and exit (its
    arc's crossings of the tissue surface) may lie from the plan's (ND fails otherwise), and
    in the truth check the true ones. ``drive_servo``: the drive corrected from the needle
    tracked during it (:mod:`~oralnav.control.needle.servo`, its settings; ``None``, the
    default, drives open-loop), looking after every ``servo_every`` drive poses and at the
    last until the servo says done, at most ``servo_final`` corrections there;
    ``arm_accuracy``: the arms' kinematic accuracy as their makers state it, ``(m, rad)``
    (how far off and how turned the tool may be from where an arm reports it; ``None``:
    exact), which widens the tracker's motion prior by each motion's size
    (:class:`.TrackSettings` ``turn_drift``, ``travel_drift``; the error swings round
    the RCM, ``ARM_LEVER`` away); ``servo_shown``: the servoed drive looks only where the
    plan leaves at least this share of the arc out of the tissue: the jaws hide a fifth or
    so more, and the refinement needs 60 % of what is not hidden by what it knows of;
    from 0.7 to 0.75 out of the tissue the fit found 54-58 % and the tracked centre went
    1-3 mm astray on development trials. ``stream_timeout`` (s): a drive servoed from a
    tracking task (the procedure's ``feed``) stops when no newer tracked frame comes
    within this long (a stalled stream or tracker).
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
    init_attempts: int = 2
    depth_window: float = 0.04
    incision_mask_px: int = 16
    placement_tolerance: float = 0.002
    grasp_margin: float = 0.0015
    reach_margin: float = math.radians(3.0)
    max_sigma_position: float = 0.0005
    max_sigma_angle: float = math.radians(2.5)
    seed: int = 0
    drive_servo: ServoSettings | None = None
    servo_every: int = 4
    servo_final: int = 6
    arm_accuracy: tuple[float, float] | None = None
    servo_shown: float = 0.8
    stream_timeout: float = 0.5
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
                     "strict_visible", "stream_timeout"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise NeedleError(f"needle procedure: {name} must be >= 0, got {v}")
        if not math.isfinite(self.depth):
            raise NeedleError(f"needle procedure: depth must be finite, got {self.depth}")
        if not 0.0 <= self.suture_at <= 1.0:
            raise NeedleError(f"needle procedure: suture_at must be in [0, 1], got "
                              f"{self.suture_at}")
        if self.init_attempts < 1:
            raise NeedleError(f"needle procedure: init_attempts must be >= 1, got "
                              f"{self.init_attempts}")
        if self.servo_every < 1 or self.servo_final < 0:
            raise NeedleError(f"needle procedure: servo_every must be >= 1 and servo_final "
                              f">= 0, got {self.servo_every}, {self.servo_final}")
        if self.arm_accuracy is not None and not (
                len(self.arm_accuracy) == 2
                and all(math.isfinite(v) and v >= 0 for v in self.arm_accuracy)):
            raise NeedleError(f"needle procedure: arm_accuracy must be two finite values "
                              f">= 0 (m, rad), got {self.arm_accuracy!r}")
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
