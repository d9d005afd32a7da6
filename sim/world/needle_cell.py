"""The simulated two-arm needle-driving cell (seed 002): a stereo endoscope watching a tissue
pad, one suture needle and one or two grippers on RCM-type surgical arms.

A stateful world the needle procedure drives: it moves the grippers, opens and closes
their jaws, and asks for images; the cell keeps the needle where the jaws put it and
renders what the endoscope sees (``oralnav.sim.world.render``). Ground truth (:class:`CellTruth`)
is for success checks and benchmarks, never for control.

Frames (docs/conventions.md; ``T_a_b`` is frame b in frame a, metres): ``ref``, the
scene rig's reference (the left endoscope channel); ``T``, a gripper (origin at the jaws'
tip, ``y`` across the jaws, ``z`` along the gripper out of the tip); ``N``, the needle
(``control/needle/model.py``); the pad's frame (surface ``z = 0``, ``+z`` out of the tissue).

What is modelled, and what is not:

- **Reach.** :class:`ArmReach` is the arm's workspace: the tip's distance from the remote
  centre of motion (RCM) and the wrist's bend. It judges *reported* poses: the robot knows
  its joints; ``kinematic_error`` (a hand-eye registration error) is what separates its
  reported pose from the true one, ``T_reported = E @ T_true`` (a fixed rigid error in the
  reference frame, as a wrong ``T_ref_base`` gives).
- **Motion.** :meth:`NeedleCell.move` goes along a straight line in position and a slerp
  in rotation, in increments of at most 1 mm and 2 degrees (by default); each increment is
  checked against the reach and the motion stops at the last good one. A held needle moves
  rigidly with its gripper. No dynamics, no collisions: open jaws pass through the wire and
  the pad without pushing them, and no tissue force acts on a needle (a needle in the
  tissue is held, turned and released as in air).
- **Grasp.** Closing the jaws holds the needle when the wire passes between them (see
  :meth:`NeedleCell.close`); the jaws then centre the wire. A needle held by two grippers
  that one of them moves is torn out of the other's jaws (that hold is released, the jaws
  stay closed on nothing).
- **Release.** An opened gripper lets the needle go; it stays where it is (no gravity).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize_scalar
from scipy.spatial.transform import Rotation, Slerp

from oralnav.control.errors import GeometryError
from oralnav.control.geometry import as_transform, invert, nearest_rigid, transform_points
from oralnav.control.needle.model import Needle
from oralnav.control.vision.camera import Rig
from oralnav.sim.world.cell import CellError
from oralnav.sim.world.render import Frame, SceneRenderer
from oralnav.sim.world.scene import Gripper, NeedleObject, Scene, TissuePad

__all__ = ["ArmReach", "CellError", "CellTruth", "NeedleCell", "WristPose"]

#: Arc points tested for a grasp (about 0.1 mm apart on a CT-1 needle).
GRASP_SAMPLES = 400
#: Arc points tested for ``in_tissue``.
TISSUE_SAMPLES = 400


#: The wrist of the da Vinci Large Needle Driver (EndoWrist 400006), from the dVRK's tool
#: definition (sawIntuitiveResearchKit, share/tool/LARGE_NEEDLE_DRIVER_400006.json): roll
#: +-260 deg, wrist pitch and yaw +-80 deg each, the yaw (jaw hinge) axis 9.1 mm from the
#: pitch axis; the jaw tip 9.5 mm from the hinge (the dVRK kinematics in Berkeley's
#: FLSpegtransferHO, motion/dvrkVariables.py).
LND_WRIST_LIMIT = math.radians(80.0)
LND_PITCH_TO_YAW = 0.0091
LND_YAW_TO_TIP = 0.0095


@dataclass(frozen=True, eq=False)
class WristPose:
    """The joints an RCM arm with a pitch-yaw wrist needs for one tool pose (rad, m).

    ``roll`` about the shaft, then ``pitch`` about the wrist's first axis (square to the
    shaft), then ``yaw`` about the jaw hinge (the tool's ``x``: the jaws close along its
    ``y``); ``bend`` the angle between the tool's ``z`` and the shaft; ``shaft`` (3,) the
    shaft's unit direction, RCM to wrist; ``insertion`` the tip's distance from the RCM."""

    roll: float
    pitch: float
    yaw: float
    bend: float
    shaft: np.ndarray
    insertion: float


def _norm(v: np.ndarray) -> float:
    """The length of the 3-vector ``v``: ``np.linalg.norm``'s own arithmetic (the square
    root of ``v . v``), so the same to the bit, without its ~3 us of dispatch; the reach
    checks take a few hundred thousand a trial."""
    return math.sqrt(float(v.dot(v)))


def _shaft_frame(s: np.ndarray) -> np.ndarray:
    """A rotation whose ``z`` is the unit vector ``s`` (its roll about ``s`` arbitrary:
    the roll joint takes it up).

    The cross products are written out: planners call this hundreds of thousands of
    times a trial, and ``np.cross`` on one 3-vector cost 80 us of axis bookkeeping (the
    needle procedure's port choice spent a quarter of its time there). The arithmetic is
    ``np.cross``'s own, operation for operation, so the frames are the same to the bit."""
    s0, s1, s2 = float(s[0]), float(s[1]), float(s[2])
    if abs(s0) < 0.9:   # a = x: a x s = (0, -s2, s1)
        x = np.array([0.0 * s2 - 0.0 * s1, 0.0 * s0 - 1.0 * s2, 1.0 * s1 - 0.0 * s0])
    else:               # a = y: a x s = (s2, 0, -s0)
        x = np.array([1.0 * s2 - 0.0 * s1, 0.0 * s0 - 0.0 * s2, 0.0 * s1 - 1.0 * s0])
    x /= _norm(x)
    x0, x1, x2 = float(x[0]), float(x[1]), float(x[2])
    return np.array([[x0, s1 * x2 - s2 * x1, s0],
                     [x1, s2 * x0 - s0 * x2, s1],
                     [x2, s0 * x1 - s1 * x0, s2]])


@dataclass(frozen=True, eq=False)
class ArmReach:
    """The workspace of one RCM-type surgical arm with a two-joint wrist.

    ``rcm`` (3,): the remote centre of motion in the reference frame (m); the shaft always
    passes through it and through the wrist's pitch axis. ``min_insertion``,
    ``max_insertion``: the tool tip's distance from the RCM (m). The wrist: a roll about
    the shaft (taken as unlimited: the needle driver's +-260 deg cover any one turn of the
    procedure), a pitch within ``max_wrist_pitch`` and a yaw of the jaws about their hinge
    within ``max_wrist_yaw`` (rad); ``pitch_to_yaw`` from the pitch axis to the hinge and
    ``yaw_to_tip`` from the hinge to the tip (m). The defaults are the da Vinci Large
    Needle Driver's: the jaws bend up to 80 deg from the shaft in any direction with any
    twist, and up to 88 deg with some twists.
    """

    rcm: np.ndarray
    min_insertion: float = 0.03
    max_insertion: float = 0.20
    max_wrist_pitch: float = LND_WRIST_LIMIT
    max_wrist_yaw: float = LND_WRIST_LIMIT
    pitch_to_yaw: float = LND_PITCH_TO_YAW
    yaw_to_tip: float = LND_YAW_TO_TIP

    def __post_init__(self) -> None:
        rcm = np.array(self.rcm, dtype=float)
        if rcm.shape != (3,) or not np.all(np.isfinite(rcm)):
            raise CellError(f"arm reach: rcm must be 3 finite values (m), got {self.rcm!r}")
        rcm.flags.writeable = False
        object.__setattr__(self, "rcm", rcm)
        lo, hi = self.min_insertion, self.max_insertion
        if not (math.isfinite(lo) and math.isfinite(hi) and 0 <= lo < hi):
            raise CellError(f"arm reach: need 0 <= min_insertion < max_insertion (m), got "
                            f"{lo}, {hi}")
        for name in ("max_wrist_pitch", "max_wrist_yaw"):
            v = getattr(self, name)
            if not (math.isfinite(v) and 0 < v <= math.pi):
                raise CellError(f"arm reach: {name} must be in (0, pi] rad, got {v}")
        for name in ("pitch_to_yaw", "yaw_to_tip"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise CellError(f"arm reach: {name} must be >= 0 m, got {v}")
        if self.pitch_to_yaw + self.yaw_to_tip >= hi:
            raise CellError(f"arm reach: the wrist ({self.pitch_to_yaw + self.yaw_to_tip} m "
                            f"from pitch axis to tip) must be shorter than max_insertion {hi} m")

    def insertion(self, T_ref_tool: np.ndarray) -> float:
        """The tip's distance from the RCM (m)."""
        return _norm(np.asarray(T_ref_tool)[:3, 3] - self.rcm)

    def wrist(self, T_ref_tool: np.ndarray) -> WristPose:
        """The wrist joints that put the tool at ``T_ref_tool`` (4x4, m).

        The shaft runs from the RCM to the pitch axis, which sits ``pitch_to_yaw`` behind
        the jaw hinge along the link between them, whose direction depends on the yaw:
        found by fixed-point rounds from the RCM-to-hinge direction (each round shrinks the
        error by about ``pitch_to_yaw`` over the insertion, a few per cent here)."""
        T = np.asarray(T_ref_tool, dtype=float)
        R, tip = T[:3, :3], T[:3, 3]
        hinge = tip - self.yaw_to_tip * R[:, 2]
        s = hinge - self.rcm
        for _ in range(8):
            n = _norm(s)
            if n < 1e-9:
                raise CellError("arm reach: the wrist would sit on the RCM")
            s = s / n
            M = _shaft_frame(s).T @ R          # the tool in the shaft's frame: Rz Ry Rx
            pitch = math.asin(max(-1.0, min(1.0, -float(M[2, 0]))))
            yaw = math.atan2(float(M[2, 1]), float(M[2, 2]))
            roll = math.atan2(float(M[1, 0]), float(M[0, 0]))
            link = R @ np.array([0.0, math.sin(yaw), math.cos(yaw)])  # pitch axis -> hinge
            moved = hinge - self.pitch_to_yaw * link - self.rcm
            step = _norm(moved / max(_norm(moved), 1e-12) - s)
            s = moved
            if step < 1e-9:
                break
        s = s / _norm(s)
        bend = math.acos(max(-1.0, min(1.0, float(R[:, 2] @ s))))
        return WristPose(roll, pitch, yaw, bend, s, self.insertion(T))

    def wrist_angle(self, T_ref_tool: np.ndarray) -> float:
        """Angle (rad) between the tool's ``z`` axis and the shaft."""
        return self.wrist(T_ref_tool).bend

    def reachable_all(self, T_ref_tool: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """Whether the arm reaches each of the poses ``T_ref_tool`` (N x 4 x 4, m), as
        :meth:`reachable` would answer (N,) bool: for planners that ask about thousands
        of poses. The bounds of :meth:`reachable`'s quick pass, on all poses at once,
        settle most of them both ways (the jaws' bend from the shaft is at most
        acos(cos pitch_lim cos yaw_lim)); the rest go through :meth:`wrist`."""
        T = np.asarray(T_ref_tool, dtype=float).reshape(-1, 4, 4)
        z = T[:, :3, 2]
        L = np.linalg.norm(T[:, :3, 3] - self.rcm, axis=1)
        ok = (L >= self.min_insertion) & (L <= self.max_insertion)
        d = T[:, :3, 3] - self.yaw_to_tip * z - self.rcm
        n = np.linalg.norm(d, axis=1)
        far = n > self.pitch_to_yaw
        nf = np.where(far, n, 1.0)
        bend0 = np.arccos(np.clip(np.einsum("ij,ij->i", z, d) / nf, -1.0, 1.0))
        lean = np.arcsin(np.clip(self.pitch_to_yaw / nf, 0.0, 1.0))
        lp, ly = self.max_wrist_pitch - margin, self.max_wrist_yaw - margin
        sure = far & (bend0 + lean <= min(lp, ly, math.pi / 2))
        most = (math.acos(max(-1.0, min(1.0, math.cos(lp) * math.cos(ly))))
                if lp < math.pi / 2 and ly < math.pi / 2 else math.pi)
        never = far & (bend0 - lean > most)
        out = ok & sure
        doubt = np.nonzero(ok & ~sure & ~never)[0]
        if len(doubt):
            out[doubt] = self._joints_within(T[doubt], margin)
        return out

    def _joints_within(self, T: np.ndarray, margin: float) -> np.ndarray:
        """Whether the wrist's pitch and yaw at each of the poses ``T`` (k x 4 x 4) lie
        ``margin`` inside their limits: :meth:`wrist`'s fixed-point rounds on all the
        poses at once (each pose's rounds stop where its own would), for the poses the
        quick bounds leave in doubt, a few hundred thousand a trial. A pose whose wrist
        would sit on the RCM goes through :meth:`wrist` alone, which names it."""
        R, tip = T[:, :3, :3], T[:, :3, 3]
        hinge = tip - self.yaw_to_tip * R[:, :, 2]
        s = hinge - self.rcm
        pitch = np.zeros(len(T))
        yaw = np.zeros(len(T))
        active = np.ones(len(T), dtype=bool)
        for _ in range(8):
            n = np.sqrt(np.einsum("ij,ij->i", s, s))
            if np.any(active & (n < 1e-9)):
                return np.array([self.reachable(Ti, margin)[0] for Ti in T])
            u = s / np.where(n > 0, n, 1.0)[:, None]
            # the tool in the shaft's frame: its bottom row is the shaft's axis in R
            m = np.einsum("ij,ijk->ik", u, R)
            p_new = np.arcsin(np.clip(-m[:, 0], -1.0, 1.0))
            y_new = np.arctan2(m[:, 1], m[:, 2])
            link = np.einsum("ijk,ik->ij", R, np.stack(
                [np.zeros(len(T)), np.sin(y_new), np.cos(y_new)], axis=1))
            moved = hinge - self.pitch_to_yaw * link - self.rcm
            mn = np.sqrt(np.einsum("ij,ij->i", moved, moved))
            d = moved / np.maximum(mn, 1e-12)[:, None] - u
            step = np.sqrt(np.einsum("ij,ij->i", d, d))
            pitch = np.where(active, p_new, pitch)
            yaw = np.where(active, y_new, yaw)
            s = np.where(active[:, None], moved, s)
            active &= ~(step < 1e-9)
            if not active.any():
                break
        return ((np.abs(pitch) <= self.max_wrist_pitch - margin)
                & (np.abs(yaw) <= self.max_wrist_yaw - margin))

    def reachable(self, T_ref_tool: np.ndarray, margin: float = 0.0) -> tuple[bool, str]:
        """``(ok, reason)``: whether the arm can put its tool at ``T_ref_tool`` (4x4, m)
        with its wrist joints ``margin`` (rad) inside their limits; the reason names the
        limit that refuses it (``min_insertion``, ``max_insertion``, ``max_wrist_pitch``,
        ``max_wrist_yaw``), empty when reachable."""
        L = self.insertion(T_ref_tool)
        if L < self.min_insertion:
            return False, (f"min_insertion: the tip would be {L * 1e3:.1f} mm from the RCM, "
                           f"below {self.min_insertion * 1e3:.1f} mm")
        if L > self.max_insertion:
            return False, (f"max_insertion: the tip would be {L * 1e3:.1f} mm from the RCM, "
                           f"beyond {self.max_insertion * 1e3:.1f} mm")
        # A quick pass first: the jaws' bend from the shaft bounds both joints (for bends
        # up to 90 deg, cos bend = cos pitch cos yaw), and the shaft, which passes within
        # pitch_to_yaw of the hinge, leans at most asin(pitch_to_yaw / |hinge - RCM|) from
        # the RCM-to-hinge line; most poses a planner asks about are settled by it.
        T = np.asarray(T_ref_tool, dtype=float)
        z = T[:3, 2]
        d = T[:3, 3] - self.yaw_to_tip * z - self.rcm
        n = _norm(d)
        if n > self.pitch_to_yaw:
            bend0 = math.acos(max(-1.0, min(1.0, float(z @ d) / n)))
            if bend0 + math.asin(self.pitch_to_yaw / n) <= min(
                    self.max_wrist_pitch - margin, self.max_wrist_yaw - margin, math.pi / 2):
                return True, ""
        w = self.wrist(T)
        for name, joint, v, lim in (("max_wrist_pitch", "pitch", w.pitch, self.max_wrist_pitch),
                                    ("max_wrist_yaw", "yaw", w.yaw, self.max_wrist_yaw)):
            if abs(v) > lim - margin:
                kept = f" less a {math.degrees(margin):.1f} deg margin" if margin else ""
                return False, (f"{name}: the wrist would {joint} {math.degrees(v):.1f} deg, "
                               f"beyond +-{math.degrees(lim):.1f} deg{kept} (the jaws "
                               f"{math.degrees(w.bend):.1f} deg from the shaft)")
        return True, ""


@dataclass(frozen=True, eq=False)
class CellTruth:
    """Ground truth of the cell's state (for success checks and the bench, never control).

    ``T_ref_needle`` (4x4): the needle's pose. ``held_by``: the grippers whose closed jaws
    hold it (in the scene's gripper order). ``in_tissue``: part of the arc (centreline) is
    below the pad's surface, within the pad's extent. ``T_tool_needle``: per holding
    gripper, the actual grasp (N in T, true poses). ``entry`` (3,): where the tip first went
    down through the pad's surface while a gripper moved the needle (an arm's motion; not
    the jaws aligning it as they close), else ``None``;
    ``exit`` (3,): where the tip afterwards came back up through it, else ``None`` (both in
    the reference frame, m; crossings outside the pad's extent do not count).
    ``out_of_tissue_after_pull``: the whole arc is above the surface after having been in
    it.
    """

    T_ref_needle: np.ndarray
    held_by: tuple[str, ...]
    in_tissue: bool
    T_tool_needle: dict[str, np.ndarray]
    entry: np.ndarray | None
    exit: np.ndarray | None
    out_of_tissue_after_pull: bool


def _midline_distance(p: np.ndarray, jaw_length: float) -> np.ndarray:
    """Distance (n,) of points (n, 3, frame T) from the jaws' mid-line, the segment
    ``x = y = 0``, ``-jaw_length / 2 <= z <= 0``."""
    zc = np.clip(p[:, 2], -0.5 * jaw_length, 0.0)
    return np.sqrt(p[:, 0] ** 2 + p[:, 1] ** 2 + (p[:, 2] - zc) ** 2)


def _pose(T: np.ndarray, what: str) -> np.ndarray:
    try:
        return as_transform(T, what=what).copy()
    except GeometryError as exc:
        raise CellError(str(exc)) from None


class NeedleCell:
    """A two-arm (or one-arm) needle-driving cell seen by the scene's rig.

    ``scene`` must hold exactly one needle, one pad (whose pose stays fixed) and one or two
    grippers, each named in ``reach``. The scene's poses are the initial true poses; every
    gripper starts with open jaws, the needle free. The scene's gripper ``opening`` is the
    open jaw gap unless ``open_gap`` (m) is given. Closed jaws render with the wire's
    diameter as their gap while they hold the needle, and with 0 while they hold nothing.

    Options: ``grasp_tolerance`` (m) widens the jaws' footprint (across, ``x``, and along,
    ``z``) in the grasp test; ``kinematic_error`` (4x4 by gripper, default identity) is the
    fixed error ``E`` of the reported poses, ``T_reported = E @ T_true``;
    ``steps_per_metre`` and ``steps_per_radian`` set the motion increments (1 mm and 2
    degrees by default); ``align_max`` (rad) the largest turn about the gripper's axis by
    which closing jaws square the wire up.

    Not thread-safe: drive it from one thread.
    """

    def __init__(self, scene: Scene, reach: Mapping[str, ArmReach], *,
                 grasp_tolerance: float = 0.0002,
                 kinematic_error: Mapping[str, np.ndarray] | None = None,
                 steps_per_metre: float = 1000.0,
                 steps_per_radian: float = 1.0 / math.radians(2.0),
                 open_gap: float | None = None,
                 align_max: float = math.radians(5.0)) -> None:
        if len(scene.needles) != 1 or len(scene.pads) != 1:
            raise CellError(f"a needle cell needs exactly one needle and one pad; the scene "
                            f"has {len(scene.needles)} needles and {len(scene.pads)} pads")
        if not 1 <= len(scene.grippers) <= 2:
            raise CellError(f"a needle cell needs one or two grippers; the scene has "
                            f"{len(scene.grippers)}")
        names = tuple(g.name for g in scene.grippers)
        if set(reach) != set(names):
            raise CellError(f"reach must be given for exactly the scene's grippers {list(names)};"
                            f" got {sorted(reach)}")
        for n, r in reach.items():
            if not isinstance(r, ArmReach):
                raise CellError(f"reach[{n!r}] must be an ArmReach, got {type(r).__name__}")
        errors = dict(kinematic_error or {})
        if set(errors) - set(names):
            raise CellError(f"kinematic_error names unknown grippers "
                            f"{sorted(set(errors) - set(names))}; the scene has {list(names)}")
        for what, v in (("grasp_tolerance", grasp_tolerance), ("align_max", align_max)):
            if not (math.isfinite(v) and v >= 0):
                raise CellError(f"{what} must be >= 0, got {v}")
        for what, v in (("steps_per_metre", steps_per_metre),
                        ("steps_per_radian", steps_per_radian)):
            if not (math.isfinite(v) and v > 0):
                raise CellError(f"{what} must be > 0, got {v}")
        if open_gap is not None and not (math.isfinite(open_gap) and open_gap > 0):
            raise CellError(f"open_gap must be > 0 m, got {open_gap}")
        self._scene = scene
        # the procedure looks at still scenes several times: keep their noise-free renders
        self._renderer = SceneRenderer(scene, keep_clean=6)
        self._nd: NeedleObject = scene.needles[0]
        self._pad: TissuePad = scene.pads[0]
        self._grippers: dict[str, Gripper] = {g.name: g for g in scene.grippers}
        self._reach = dict(reach)
        self._E = {n: _pose(errors.get(n, np.eye(4)), f"kinematic_error[{n!r}]")
                   for n in names}
        self._E_inv = {n: invert(E) for n, E in self._E.items()}
        self._grasp_tol = float(grasp_tolerance)
        self._steps_m, self._steps_rad = float(steps_per_metre), float(steps_per_radian)
        self._align_max = float(align_max)
        wire = self._nd.needle.wire_diameter
        self._open_gap = {n: float(open_gap) if open_gap is not None else g.opening
                          for n, g in self._grippers.items()}
        for n, gap in self._open_gap.items():
            if gap <= wire:
                raise CellError(f"gripper {n!r}: its open jaw gap {gap * 1e3:.2f} mm does not "
                                f"clear the {wire * 1e3:.2f} mm wire (set open_gap or the "
                                "scene's opening)")
        # state: true poses, jaws, grasps (N in T, by holder, in the order they closed)
        self._T_needle = np.array(self._nd.T_ref_needle, dtype=float)
        self._T_tool = {n: np.array(g.T_ref_tool, dtype=float)
                        for n, g in self._grippers.items()}
        self._closed = dict.fromkeys(names, False)
        self._grasp: dict[str, np.ndarray] = {}
        self._entry: np.ndarray | None = None
        self._exit: np.ndarray | None = None
        self._arc_grasp = self._nd.needle.points(GRASP_SAMPLES)
        self._phi_grasp = np.linspace(0.0, self._nd.needle.arc, GRASP_SAMPLES)
        self._arc_tissue = self._nd.needle.points(TISSUE_SAMPLES)
        self._T_pad_ref = invert(self._pad.T_ref_pad)
        self._was_in = self._in_tissue(self._T_needle)
        self._frame = 0
        self.last_frame: Frame | None = None
        for n in names:
            ok, why = self.reachable(n, self.gripper_pose(n))
            if not ok:
                raise CellError(f"gripper {n!r} starts out of its arm's reach: {why}")

    # -- what the procedure may read --------------------------------------------------
    @property
    def scene(self) -> Scene:
        return self._scene

    @property
    def rig(self) -> Rig:
        return self._scene.rig

    @property
    def cameras(self) -> tuple[str, ...]:
        return tuple(self._scene.rig.names)

    @property
    def needle(self) -> Needle:
        """The needle's geometry (its pose is truth: :meth:`truth`)."""
        return self._nd.needle

    @property
    def needle_object(self) -> NeedleObject:
        """The scene's needle (shading, thread); its ``T_ref_needle`` is the initial pose."""
        return self._nd

    @property
    def pad(self) -> TissuePad:
        """The tissue pad; its pose is fixed."""
        return self._pad

    @property
    def grippers(self) -> tuple[str, ...]:
        return tuple(self._grippers)

    def gripper(self, name: str) -> Gripper:
        """The scene's gripper ``name`` (its jaw sizes; its pose is the initial one)."""
        return self._grippers[self._check_name(name)]

    def arm_reach(self, name: str) -> ArmReach:
        return self._reach[self._check_name(name)]

    @property
    def frame(self) -> int:
        """The number of :meth:`images` calls so far (the next frame's noise draw)."""
        return self._frame

    def images(self) -> dict[str, np.ndarray]:
        """Render every camera of the current state (mono8, by camera name). Each call is
        a new frame: a new noise draw. The frame, with its ground truth, is kept as
        :attr:`last_frame`."""
        return self.expose()()

    def expose(self) -> Callable[[], dict[str, np.ndarray]]:
        """The next frame's exposure: the state now (a new frame number), and a function
        that renders it as :meth:`images` does. The state is copied here, so the cell may
        move while another thread renders (a tracking task's capture: the arm does not
        wait for the renderer, as it would not wait for a camera)."""
        wire = self._nd.needle.wire_diameter
        openings = {n: (self._open_gap[n] if not self._closed[n]
                        else wire if n in self._grasp else 0.0) for n in self._grippers}
        # copies: the frame keeps its poses, the cell's state must not alias them
        poses = {self._nd.name: self._T_needle.copy(),
                 **{n: T.copy() for n, T in self._T_tool.items()}}
        number = self._frame
        self._frame += 1

        def render() -> dict[str, np.ndarray]:
            frame = self._renderer.render(poses=poses, frame=number, openings=openings)
            self.last_frame = frame
            return dict(frame.images)
        return render

    def gripper_pose(self, name: str) -> np.ndarray:
        """The robot's reported ``T_ref_tool`` (4x4, m): ``kinematic_error[name] @`` the
        true pose."""
        self._check_name(name)
        return self._E[name] @ self._T_tool[name]

    def jaw_open(self, name: str) -> bool:
        return not self._closed[self._check_name(name)]

    def reachable(self, name: str, T_ref_tool: np.ndarray, margin: float = 0.0
                  ) -> tuple[bool, str]:
        """Whether arm ``name`` can put its tool at the *reported* pose ``T_ref_tool``
        (what the planner sees) with its wrist joints ``margin`` (rad) inside their
        limits, and the limit that refuses it."""
        return self._reach[self._check_name(name)].reachable(
            _pose(T_ref_tool, "T_ref_tool"), margin)

    def reachable_all(self, name: str, T_ref_tool: np.ndarray, margin: float = 0.0
                      ) -> np.ndarray:
        """:meth:`reachable` for each of the reported poses ``T_ref_tool`` (N x 4 x 4):
        (N,) bool."""
        T = np.asarray(T_ref_tool, dtype=float)
        if T.ndim != 3 or T.shape[1:] != (4, 4) or not np.all(np.isfinite(T)):
            raise CellError(f"T_ref_tool must be finite N x 4 x 4 poses, got shape {T.shape}")
        return self._reach[self._check_name(name)].reachable_all(T, margin)

    # -- what the procedure may do ----------------------------------------------------
    def move(self, name: str, T_ref_tool_reported: np.ndarray, *,
             on_step: Callable[[NeedleCell], None] | None = None) -> None:
        """Move gripper ``name`` to the reported pose ``T_ref_tool_reported`` (4x4, m).

        Straight in position, slerp in rotation, in increments of at most
        ``1 / steps_per_metre`` m and ``1 / steps_per_radian`` rad. Each increment is
        checked against the arm's reach; the first one out of reach raises
        :class:`CellError` naming the limit, and the gripper (and a needle it holds) stays
        at the last good increment. A held needle moves rigidly with the gripper; if the
        other gripper holds it too, the move tears it out of the other's jaws (that hold
        is released; its jaws stay closed). ``on_step(cell)`` runs after each increment.
        """
        self._check_name(name)
        # re-orthonormalised: targets accepted to 1e-6 must not let the state drift
        goal = nearest_rigid(self._E_inv[name] @ _pose(T_ref_tool_reported, "move target"))
        start = self._T_tool[name]
        dp = goal[:3, 3] - start[:3, 3]
        rots = Rotation.from_matrix(np.stack([start[:3, :3], goal[:3, :3]]))
        angle = float((rots[0].inv() * rots[1]).magnitude())
        dist = float(np.linalg.norm(dp))
        n = max(1, math.ceil(dist * self._steps_m - 1e-9),
                math.ceil(angle * self._steps_rad - 1e-9))
        tear = dist > 0 or angle > 0
        s = np.arange(1, n + 1) / n
        R = Slerp([0.0, 1.0], rots)(s).as_matrix()
        reach, E = self._reach[name], self._E[name]
        for k in range(n):
            if k == n - 1:
                T = goal.copy()
            else:
                T = np.eye(4)
                T[:3, :3] = R[k]
                T[:3, 3] = start[:3, 3] + s[k] * dp
            ok, why = reach.reachable(E @ T)
            if not ok:
                done = "" if k == 0 else f" after {k} of {n} increments"
                raise CellError(f"move {name!r}: stopped{done}: {why}; the gripper stays at "
                                "its last reachable pose")
            self._T_tool[name] = T
            if name in self._grasp:
                if tear:                    # torn out of the other's jaws
                    for other in [o for o in self._grasp if o != name]:
                        del self._grasp[other]
                    tear = False
                self._set_needle(T @ self._grasp[name])
            if on_step is not None:
                on_step(self)

    def close(self, name: str) -> bool:
        """Close the jaws of ``name``; returns whether it now holds the needle (truth: a
        procedure must not decide on it, it has to look).

        The needle is grasped when the wire passes between the jaws: some arc point lies
        within the jaws' footprint, ``|x_T| <= jaw_width / 2 + wire radius`` and
        ``-jaw_length <= z_T <= 0`` (both widened by ``grasp_tolerance``), and within the
        open gap, ``|y_T| <= gap / 2``. The grasp point is the one nearest the jaws' mid-
        line (``x = y = 0``, ``z`` from ``-jaw_length / 2`` to 0). Closing centres the
        wire: the needle shifts along ``y_T`` until the wire's centre is at ``y_T = 0``,
        and if the wire's tangent there is within ``align_max`` of the jaw faces' plane
        (turning about ``z_T``), it is turned about ``z_T`` through the grasp point until
        it lies in that plane; a larger misalignment is kept (the jaws clamp the wire
        crooked). A needle already held by the other gripper moves the same way (it slips
        in the other's jaws). If the wire is not between the jaws nothing moves and the
        jaws close on nothing. Closing closed jaws changes nothing.
        """
        self._check_name(name)
        if self._closed[name]:
            return name in self._grasp
        self._closed[name] = True
        T_tool = self._T_tool[name]
        T_T_N = invert(T_tool) @ self._T_needle
        g = self._grippers[name]
        p = transform_points(T_T_N, self._arc_grasp)
        x, y, z = p[:, 0], p[:, 1], p[:, 2]
        r, tol = 0.5 * self._nd.needle.wire_diameter, self._grasp_tol
        between = ((np.abs(x) <= 0.5 * g.jaw_width + r + tol)
                   & (z >= -g.jaw_length - tol) & (z <= tol)
                   & (np.abs(y) <= 0.5 * self._open_gap[name]))
        if not between.any():
            return False
        mid = _midline_distance(p, g.jaw_length)
        k = int(np.argmin(np.where(between, mid, np.inf)))
        # refine between the neighbouring samples, so the grasp does not depend on them
        needle = self._nd.needle
        lo = self._phi_grasp[max(k - 1, 0)]
        hi = self._phi_grasp[min(k + 1, GRASP_SAMPLES - 1)]
        phi = float(minimize_scalar(
            lambda f: _midline_distance(transform_points(T_T_N, needle.point(f)[None]),
                                        g.jaw_length)[0],
            bounds=(lo, hi), method="bounded", options={"xatol": 1e-10}).x)
        q = transform_points(T_T_N, needle.point(phi)[None])[0]
        t = T_T_N[:3, :3] @ needle.tangent(phi)
        M = np.eye(4)
        M[1, 3] = -q[1]                            # centre the wire between the jaws
        q[1] = 0.0
        if abs(t[0]) > 1e-12:
            turn = math.atan(-t[1] / t[0])         # about z_T: the tangent into the x-z plane
            if abs(turn) <= self._align_max:
                c, s = math.cos(turn), math.sin(turn)
                Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
                A = np.eye(4)
                A[:3, :3] = Rz
                A[:3, 3] = q - Rz @ q              # about the axis through the grasp point
                M = A @ M
        # the jaws' own alignment of the wire is no bite: turning a needle that lies on
        # the pad about the grasp can dip its tip a fraction of a millimetre below the
        # surface (no contact model), which was taken for the suture's entry, 20-38 mm
        # from the incision (validation trials 1000079, 1000115, 1000452)
        self._set_needle(nearest_rigid(T_tool @ M @ T_T_N), crossings=False)
        self._grasp[name] = nearest_rigid(M @ T_T_N)
        for other in self._grasp:                  # the other holder's jaws slip
            if other != name:
                self._grasp[other] = nearest_rigid(invert(self._T_tool[other])
                                                   @ self._T_needle)
        return True

    def open(self, name: str) -> None:
        """Open the jaws of ``name``, releasing the needle if it held it. The needle keeps
        its pose (in the tissue it stays there; free and held by nobody it stays where it
        is: no gravity)."""
        self._check_name(name)
        self._closed[name] = False
        self._grasp.pop(name, None)

    def truth(self) -> CellTruth:
        """The ground truth of the current state."""
        held = tuple(n for n in self._grippers if n in self._grasp)
        inside = self._in_tissue(self._T_needle)
        return CellTruth(
            T_ref_needle=self._T_needle.copy(), held_by=held, in_tissue=inside,
            T_tool_needle={n: invert(self._T_tool[n]) @ self._T_needle for n in held},
            entry=None if self._entry is None else self._entry.copy(),
            exit=None if self._exit is None else self._exit.copy(),
            out_of_tissue_after_pull=self._was_in and not inside)

    def true_gripper_pose(self, name: str) -> np.ndarray:
        """The gripper's true ``T_ref_tool`` (truth, for checks only)."""
        return self._T_tool[self._check_name(name)].copy()

    # -- internals --------------------------------------------------------------------
    def _check_name(self, name: str) -> str:
        if name not in self._grippers:
            raise CellError(f"unknown gripper {name!r}; the cell has {list(self._grippers)}")
        return name

    def _heights(self, pts_ref: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Height above the pad's surface (m) of points (n, 3, reference frame), and
        whether each lies over the pad's extent."""
        p = transform_points(self._T_pad_ref, pts_ref)
        sx, sy = self._pad.size
        return p[:, 2], (np.abs(p[:, 0]) <= 0.5 * sx) & (np.abs(p[:, 1]) <= 0.5 * sy)

    def _in_tissue(self, T_ref_needle: np.ndarray) -> bool:
        h, over = self._heights(transform_points(T_ref_needle, self._arc_tissue))
        return bool(np.any((h < 0.0) & over))

    def _set_needle(self, T_new: np.ndarray, crossings: bool = True) -> None:
        """Move the needle, tracking the tip's crossings of the pad's surface (not where
        ``crossings`` is False: the jaws aligning the wire as they close)."""
        if not crossings:
            self._T_needle = T_new
            return
        tip = self._nd.needle.tip[None]
        tip0 = transform_points(self._T_needle, tip)[0]
        tip1 = transform_points(T_new, tip)[0]
        (h0, h1), _ = self._heights(np.stack([tip0, tip1]))
        down = h0 >= 0.0 > h1 and self._entry is None
        up = h0 < 0.0 <= h1 and self._entry is not None and self._exit is None
        if down or up:
            c = tip0 + (h0 / (h0 - h1)) * (tip1 - tip0)
            _, over = self._heights(c[None])
            if over[0]:
                if down:
                    self._entry = c
                else:
                    self._exit = c
        self._T_needle = T_new
        if not self._was_in:
            self._was_in = self._in_tissue(T_new)
