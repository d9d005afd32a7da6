"""Randomised needle-driving trials: one seeded draw -> a :class:`NeedleCell` and what was
drawn (seed 002's experiments place the needle at random on the suturing pad).

Everything comes from one ``numpy.random.Generator`` seeded with the trial's seed, in a
fixed order, so a seed always gives the same cell; rejection loops (a needle that would
lie over the incision or out of view, a parked gripper that would hide it) draw from the
same stream, so they are deterministic too.

The layout, in the stereo endoscope's reference frame (the left channel; metres):

- the pad (70 x 60 mm) 80-120 mm in front of the endoscope, its normal tilted 10-35 deg
  from the direction to the camera about a random axis, turned at random in its plane;
- the incision (the operator's suture line), 40-50 mm long, along the pad's x (within
  +-8 deg), 10-16 mm to the pad's +y side of its centre;
- a CT-1-like needle (radius 13 mm, 1 mm wire, a semicircle, a 15 mm thread) lying flat
  on the pad (its plane the pad's, normal out of the tissue, centre half the wire above
  the surface) at a random position and in-plane turn: every arc point at least 8 mm from
  the incision and 4 mm inside the pad's edges, and 20 px inside both images;
- two grippers, ``"left"`` and ``"right"``, with open 4 mm jaws, parked with their tips
  12-20 mm above the pad near the left and right edges of both views, pointing straight
  from their RCM (wrist unbent), turned at random about their axis, their jaws and shafts
  clear of the needle in both views;
- each arm's RCM 40-60 mm to its side of the pad centre, +-15 mm vertically, about
  120-150 mm from the pad centre and at least 2 mm behind the camera's plane (the
  nominal port, beside the endoscope's). Entry port selection, as in seed 002's ref.
  [8] (Liu and Cavusoglu, "Needle grasp and entry port selection ..."), when a
  ``drivable`` check is given: each arm draws 12 sites anywhere on its side of the
  endoscope, 30-90 mm to the side, +-50 mm vertically and 100-160 mm from the pad
  centre, and takes the first from which the check passes (the procedure's: the suture
  driven, the tip regrasped and the needle pulled out; the record's ``port``, and
  ``port_drives`` false when none could: the arm takes its first site, and the trial
  may fail by reach). With a ``workable`` check too, both arms' sites are drawn
  before either arm is parked and the pair is chosen together: the first pair of sites
  (fewest passed over first, at most 40 pairs) from which one arm drives and pulls and
  the other picks the needle up and hands it over (``ports_workable``); else each arm
  as above. Reach: the
  dVRK manipulator's insertion, the tip 30-240 mm from the RCM, and the wrist of a da
  Vinci Large Needle Driver (pitch and yaw +-80 deg, :class:`ArmReach`). So the whole
  pad lies within the insertion range of both arms (until session 17 the insertion
  stopped 20-30 mm beyond the farthest point of the needle, the incision and the park
  pose, a limit of our own); what an arm cannot do is set by its wrist and its port.

Imaging: background 20-50 DN, pad 150-200, needle 60-90 with a specular 120-200,
illumination gradient each in [-0.35, 0.35], blur 0.8-1.5 px, read noise 1-3 DN, shot
gain 0.03-0.1, supersample 2.

``difficulty`` (0..``MAX_DIFFICULTY`` = 2, default 1) scales the imaging nuisances (the
illumination gradient, the blur above 0.8 px, the noise above its floor) in proportion:
at 2 the gradient reaches +-0.7, the blur 2.2 px, the read noise 5 DN and the shot gain
0.17. Up to 1 it leaves the draw alone: the layout is drawn first, so a seed gives the
same layout at every difficulty up to 1. Above 1 the layout gets harder too, so its
draw differs from the default's: the pad's tilt range widens from 10-35 deg to
10-(10 + 25 x difficulty) deg (60 deg at 2), and the needle no longer lies flat: it
rests on its two ends, its plane turned about the chord between them by up to
``MAX_LIFT`` x (difficulty - 1) (30 deg at 2), the arc's middle raised off the pad.

``arm_error`` (off by default): each arm's kinematic error, the transform between where
it reports its tool and where the tool is (``NeedleCell``'s ``kinematic_error``), as a
real arm's joint offsets and registration leave it. Each arm's is a rotation of the given
angle about a random axis through its RCM, then a translation of the given length in a
random direction, drawn from a stream of its own (:func:`arm_errors`), so a seed gives the
same layout, and the same imaging, with and without it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from oralnav.control.geometry import make_transform, transform_points
from oralnav.control.needle.model import Needle
from oralnav.control.vision.camera import Rig
from oralnav.sim.world.needle_cell import ArmReach, CellError, NeedleCell
from oralnav.sim.world.scene import Gripper, Imaging, NeedleObject, Scene, TissuePad

__all__ = ["MAX_DIFFICULTY", "PairCheck", "PortCheck", "TrialInfo", "arm_errors", "trial_cell",
           "trial_scene"]

PAD_SIZE = (0.070, 0.060)
CT1 = Needle(radius=0.013, wire_diameter=0.001, arc=math.pi)
THREAD_LENGTH = 0.015
OPEN_GAP = 0.004
SHAFT_LENGTH = 0.25            # past the RCM: the renderer cuts it at the camera's plane
#: Clearances: needle from the incision (m), from the pad's edges (m), from the image
#: border (px); parked gripper silhouettes from the needle (px).
INCISION_CLEARANCE = 0.008
EDGE_CLEARANCE = 0.004
BORDER_PX = 20.0
GRIPPER_CLEARANCE_PX = 10.0
MAX_ATTEMPTS = 200
#: The arms' insertion range (m, the tip's distance from the RCM): the dVRK patient-side
#: manipulator's insertion joint runs 0-240 mm (sawIntuitiveResearchKit,
#: share/kinematic/psm.json); the first 30 mm stay in the cannula.
MIN_INSERTION = 0.030
MAX_INSERTION = 0.240
#: Port sites drawn per arm when the ports are selected for the suture.
PORT_CANDIDATES = 12
#: Where an arm's port is drawn (m): to its side of the pad centre (lateral), above or
#: below it (vertical, +-), and its distance from the pad centre; the nominal port beside
#: the endoscope's, taken as it is when no port is selected.
PORT_LATERAL = (0.040, 0.060)
PORT_VERTICAL = 0.015
PORT_DISTANCE = (0.120, 0.150)
#: Where the candidate sites are drawn when the ports are selected for the suture (m):
#: anywhere on the arm's side of the endoscope within these bounds.
SITE_LATERAL = (0.030, 0.090)
SITE_VERTICAL = 0.050
SITE_DISTANCE = (0.100, 0.160)

#: ``drivable(reach, incision, normal) -> bool``: whether an arm of :class:`ArmReach`
#: ``reach`` can carry out the planned suture across ``incision`` (2, 3) on the surface
#: of ``normal`` (3,), reference frame (m); ``oralnav.control.needle.procedure.port_drives``
#: makes the procedure's (the drive, then the regrasp of the tip and the pull).
PortCheck = Callable[[ArmReach, np.ndarray, np.ndarray], bool]
#: ``workable(reaches, incision, normal, T_ref_needle, rig, outline) -> bool``: whether
#: the two arms, ``reaches`` ({name: ArmReach}), can together carry out the suture on the
#: needle lying at ``T_ref_needle`` (4x4, reference frame, m) under the cameras of
#: ``rig``, the tissue's extent ``outline`` (4, 3): one drives and pulls, the other picks
#: the needle up and hands it over (``oralnav.control.needle.procedure.port_pair``).
PairCheck = Callable[[Mapping[str, ArmReach], np.ndarray, np.ndarray, np.ndarray, Rig,
                      np.ndarray], bool]
#: The most port pairs a trial asks ``workable`` about (of PORT_CANDIDATES squared).
PAIR_CHECKS = 40
#: The hardest trials :func:`trial_scene` draws (``difficulty``); 1 is the default.
MAX_DIFFICULTY = 2.0
#: Above difficulty 1 the needle rests lifted about its chord, its plane turned out of
#: the pad's by up to this much (rad) times ``difficulty - 1``.
MAX_LIFT = math.radians(30.0)
#: The second word of the arm errors' seed (``[seed, ARM_ERROR_STREAM]``): a stream apart
#: from the layout's, which ``seed`` alone seeds.
ARM_ERROR_STREAM = 1


@dataclass(frozen=True)
class TrialInfo:
    """What one trial drew.

    ``values``: every drawn value, JSON-able (metres, degrees where the key says so).
    ``incision`` (2, 3): the incision's start and end on the pad's surface, in the
    reference frame (m): the suture line the operator gives the procedure (seed 002).
    ``surface_normal`` (3,): the pad's unit normal out of the tissue, reference frame (the
    seed identifies the pad's surface by vision; given here as the operator's input, like
    the line). ``surface_outline`` (4, 3): the pad's corners, reference frame (m): the
    extent of the tissue surface, which the seed's fiducials mark; ``None`` when unknown.
    """

    seed: int
    difficulty: float
    values: dict[str, Any]
    incision: np.ndarray
    surface_normal: np.ndarray
    surface_outline: np.ndarray | None = None

    def to_json(self) -> dict[str, Any]:
        return {"seed": self.seed, "difficulty": self.difficulty, "values": self.values,
                "incision": self.incision.tolist(),
                "surface_normal": self.surface_normal.tolist(),
                "surface_outline": (None if self.surface_outline is None
                                    else self.surface_outline.tolist())}


def _r(v: float | np.ndarray, nd: int = 6) -> Any:
    """Rounded plain Python numbers for the JSON record."""
    a = np.round(np.asarray(v, dtype=float), nd)
    return a.tolist() if a.ndim else float(a)


def _segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance (n,) of 2-D points p (n, 2) from the segment a-b."""
    d = b - a
    t = np.clip(((p - a) @ d) / float(d @ d), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[:, None] * d), axis=1)


def _in_views(rig: Rig, pts_ref: np.ndarray, margin: float) -> bool:
    for name in rig.names:
        cam = rig[name]
        pc = transform_points(cam.T_cam_ref, pts_ref)
        if np.any(pc[:, 2] <= 0.01) or not np.all(cam.in_image(cam.project(pc), margin)):
            return False
    return True


def _gripper_clear(rig: Rig, T_ref_tool: np.ndarray, pts_ref: np.ndarray) -> bool:
    """Whether the gripper's jaws and shaft (drawn as discs along its axis, radius the
    jaws' or the shaft's, projected) stay ``GRIPPER_CLEARANCE_PX`` clear of the points in
    every view."""
    s = np.arange(0.0, 0.12, 0.001)
    axis = transform_points(T_ref_tool, np.stack([0 * s, 0 * s, -s], axis=1))
    jaw = math.hypot(0.5 * OPEN_GAP + 0.0012, 0.5 * 0.0025)
    radius = np.where(s <= 0.010, jaw, 0.003)
    for name in rig.names:
        cam = rig[name]
        ac = transform_points(cam.T_cam_ref, axis)
        keep = ac[:, 2] > 0.005
        ac, rad = ac[keep], radius[keep]
        if not len(ac):
            continue
        a_px = cam.project(ac)
        r_px = rad * cam.K[0, 0] / ac[:, 2] + GRIPPER_CLEARANCE_PX
        p_px = cam.project(transform_points(cam.T_cam_ref, pts_ref))
        d = np.linalg.norm(p_px[:, None, :] - a_px[None], axis=2)
        if np.any(d < r_px[None]):
            return False
    return True


def trial_scene(seed: int, *, rig: Rig, difficulty: float = 1.0,
                drivable: PortCheck | None = None, workable: PairCheck | None = None
                ) -> tuple[Scene, dict[str, ArmReach], TrialInfo]:
    """The scene, the arms' reach and the record of trial ``seed`` (see the module
    docstring), seen by the stereo endoscope ``rig`` (the shipped one is
    :func:`oralnav.config.rig.trial_rig`; the draw depends on it, so the same seed with the
    same rig is the same trial); :func:`trial_cell` builds the cell from them. ``drivable(reach,
    incision, normal) -> bool``: entry port selection (the module docstring); without it
    each arm takes the one port site it draws. ``workable`` (with ``drivable`` only):
    the two ports are chosen together, the first pair of sites it accepts."""
    if workable is not None and drivable is None:
        raise CellError("a workable check chooses among port sites, which only a "
                        "drivable check draws: give both")
    if not (isinstance(seed, int | np.integer) and 0 <= seed < 2**63):
        raise CellError(f"trial seed must be an integer in [0, 2^63), got {seed!r}")
    if not (math.isfinite(difficulty) and 0.0 <= difficulty <= MAX_DIFFICULTY):
        raise CellError(f"difficulty must be in [0, {MAX_DIFFICULTY:g}], got {difficulty}")
    rng = np.random.default_rng(int(seed))
    D = float(difficulty)
    u = rng.uniform
    attempts = 0
    out = None
    while out is None:
        attempts += 1
        if attempts > MAX_ATTEMPTS:  # the shipped rig needs 1-2 attempts
            raise CellError(f"trial {seed}: no valid layout in {MAX_ATTEMPTS} attempts")
        out = _draw(rig, rng, drivable, workable, max(0.0, D - 1.0))
    scene_parts, reach, values, incision, normal = out
    img = dict(background=u(20.0, 50.0), pad_level=u(150.0, 200.0),
               needle_level=u(60.0, 90.0), specular=u(120.0, 200.0),
               gradient=(D * u(-0.35, 0.35), D * u(-0.35, 0.35)),
               blur=0.8 + D * u(0.0, 0.7), read_noise=1.0 + D * u(0.0, 2.0),
               shot_gain=0.03 + D * u(0.0, 0.07))
    imaging = Imaging(supersample=2, background=img["background"],
                      illumination_gradient=img["gradient"], blur_sigma_px=img["blur"],
                      read_noise_dn=img["read_noise"], shot_noise_gain=img["shot_gain"])
    pad, needle, grippers = scene_parts
    pad = TissuePad(pad.name, pad.T_ref_pad, pad.size, img["pad_level"], pad.incision,
                    pad.incision_width, pad.incision_level)
    needle = NeedleObject(needle.name, needle.needle, needle.T_ref_needle,
                          level=img["needle_level"], specular=img["specular"],
                          shininess=needle.shininess, thread_length=needle.thread_length,
                          thread_diameter=needle.thread_diameter,
                          thread_level=needle.thread_level, thread_tilt=needle.thread_tilt)
    scene = Scene(rig=rig, placements=(), imaging=imaging, seed=int(seed),
                  source=f"needle trial {seed}", needles=(needle,), pads=(pad,),
                  grippers=grippers)
    values["imaging"] = {k: _r(v, 4) for k, v in img.items()}
    values["attempts"] = attempts
    return scene, reach, TrialInfo(int(seed), D, values, incision, normal,
                                   _outline(pad.T_ref_pad))


def _outline(T_ref_pad: np.ndarray) -> np.ndarray:
    """The pad's corners (4, 3), reference frame (m)."""
    sx, sy = PAD_SIZE
    return transform_points(T_ref_pad, np.array(
        [[-sx, -sy, 0.0], [sx, -sy, 0.0], [sx, sy, 0.0], [-sx, sy, 0.0]]) / 2)


def _unit(rng: np.random.Generator) -> np.ndarray:
    """A direction drawn uniformly on the sphere."""
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def arm_errors(seed: int, reach: Mapping[str, ArmReach], translation: float,
               rotation: float) -> dict[str, np.ndarray]:
    """Each arm's kinematic error for trial ``seed`` (``E``, 4x4, reference frame: the arm
    reports ``E @ T_true``): a rotation of ``rotation`` rad about a random axis through
    the arm's RCM, then a translation of ``translation`` m in a random direction; arms
    drawn in name order from the stream ``[seed, ARM_ERROR_STREAM]``."""
    for name, v in (("translation", translation), ("rotation", rotation)):
        if not (math.isfinite(v) and v >= 0):
            raise CellError(f"arm error: {name} must be finite and >= 0, got {v}")
    rng = np.random.default_rng([int(seed), ARM_ERROR_STREAM])
    out = {}
    for name in sorted(reach):
        R = Rotation.from_rotvec(rotation * _unit(rng)).as_matrix()
        t = translation * _unit(rng)
        rcm = np.asarray(reach[name].rcm, dtype=float)
        out[name] = make_transform(R, rcm - R @ rcm + t)
    return out


def trial_cell(seed: int, *, rig: Rig, difficulty: float = 1.0,
               drivable: PortCheck | None = None,
               workable: PairCheck | None = None,
               arm_error: tuple[float, float] | None = None,
               **options) -> tuple[NeedleCell, TrialInfo]:
    """A randomised two-arm needle cell for trial ``seed`` and what was drawn, its ports
    chosen with ``drivable`` (:func:`trial_scene`); ``arm_error``: ``(translation m,
    rotation rad)`` of each arm's kinematic error (:func:`arm_errors`; the info's values
    then hold them, under ``arm_error``); ``options`` go to :class:`NeedleCell` (e.g.
    ``kinematic_error``, which ``arm_error`` replaces: give one)."""
    scene, reach, info = trial_scene(seed, rig=rig, difficulty=difficulty, drivable=drivable,
                                     workable=workable)
    if arm_error is not None:
        if "kinematic_error" in options:
            raise CellError("give arm_error or kinematic_error, not both")
        errors = arm_errors(seed, reach, *arm_error)
        options["kinematic_error"] = errors
        info = replace(info, values={**info.values, "arm_error": {
            n: {"rotvec_deg": _r(np.degrees(Rotation.from_matrix(E[:3, :3]).as_rotvec())),
                "at_rcm_m": _r(E[:3, :3] @ reach[n].rcm + E[:3, 3] - reach[n].rcm)}
            for n, E in errors.items()}})
    return NeedleCell(scene, reach, **options), info


def _site(rng: np.random.Generator, centre: np.ndarray, side: float,
          lateral: tuple[float, float], vertical: float, distance: tuple[float, float]
          ) -> ArmReach:
    """One port site on ``side`` (-1 left, +1 right) of the pad ``centre`` (m), drawn in
    the region ``lateral``, ``vertical``, ``distance`` (see :data:`SITE_LATERAL`)."""
    u = rng.uniform
    lat = side * u(*lateral)
    ver = u(-vertical, vertical)
    dist = u(*distance)
    depth = math.sqrt(max(dist**2 - lat**2 - ver**2, 0.0))
    rcm = centre + np.array([lat, ver, -depth])
    rcm[2] = min(rcm[2], -0.002)                 # behind the camera's plane
    # the wrist: the da Vinci Large Needle Driver's (ArmReach's defaults)
    return ArmReach(rcm=rcm, min_insertion=MIN_INSERTION, max_insertion=MAX_INSERTION)


def _choose_ports(sites: dict[str, list[ArmReach]], incision: np.ndarray, normal: np.ndarray,
                  T_ref_needle: np.ndarray, rig: Rig, outline: np.ndarray,
                  drivable: PortCheck, workable: PairCheck | None
                  ) -> tuple[dict[str, int], dict[str, bool], bool | None]:
    """The two arms' ports among their candidate ``sites``: the first pair (fewest
    sites passed over first) that ``workable`` accepts, of at most :data:`PAIR_CHECKS`;
    without one, each arm's first site ``drivable`` accepts, else its first (the arm may
    still pick up and hand off; the other may drive). ``(port index, whether it
    drives, whether the pair is workable (None unasked))`` per arm."""
    n = {name: len(v) for name, v in sites.items()}
    left, right = sites
    if workable is not None:
        pairs = sorted(((i, j) for i in range(n[left]) for j in range(n[right])),
                       key=lambda p: (max(p), p[0] + p[1], p[0]))
        for i, j in pairs[:PAIR_CHECKS]:
            if workable({left: sites[left][i], right: sites[right][j]}, incision, normal,
                        T_ref_needle, rig, outline):
                ports = {left: i, right: j}
                return ports, {a: drivable(sites[a][k], incision, normal)
                               for a, k in ports.items()}, True
    ports, drives = {}, {}
    for name, cands in sites.items():
        ports[name], drives[name] = 0, False
        for k, site in enumerate(cands):
            if drivable(site, incision, normal):
                ports[name], drives[name] = k, True
                break
    return ports, drives, None if workable is None else False


def _draw(rig: Rig, rng: np.random.Generator, drivable: PortCheck | None = None,
          workable: PairCheck | None = None, harder: float = 0.0):
    """One attempt at the layout; ``None`` if a constraint fails (the caller draws
    again from the same stream). ``harder``: the difficulty above 1 (0..1), which widens
    the pad's tilt and lifts the needle (module docstring); at 0 the draw is the
    default's, number for number."""
    u = rng.uniform
    # -- the pad ------------------------------------------------------------------------
    centre = np.array([0.0025 + u(-0.004, 0.004), u(-0.004, 0.004), u(0.080, 0.120)])
    toward = -centre / np.linalg.norm(centre)             # from the pad to the camera
    tilt = u(10.0, 35.0)
    if harder > 0.0:
        tilt = 10.0 + (tilt - 10.0) * (1.0 + harder)
    tilt = math.radians(tilt)
    azimuth = u(0.0, 2 * math.pi)
    e1 = np.cross(toward, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(toward, e1)
    axis = math.cos(azimuth) * e1 + math.sin(azimuth) * e2
    normal = Rotation.from_rotvec(tilt * axis).apply(toward)
    x0 = np.array([1.0, 0.0, 0.0]) - normal[0] * normal   # camera x in the pad's plane
    x0 /= np.linalg.norm(x0)
    spin = u(0.0, 2 * math.pi)
    x_pad = Rotation.from_rotvec(spin * normal).apply(x0)
    T_ref_pad = make_transform(np.column_stack([x_pad, np.cross(normal, x_pad), normal]),
                               centre)
    # -- the incision -------------------------------------------------------------------
    length = u(0.040, 0.050)
    inc_angle = math.radians(u(-8.0, 8.0))
    inc_mid = np.array([u(-0.003, 0.003), u(0.010, 0.016)])
    half = 0.5 * length * np.array([math.cos(inc_angle), math.sin(inc_angle)])
    a, b = inc_mid - half, inc_mid + half
    sx, sy = PAD_SIZE
    if np.any(np.abs(np.stack([a, b])) > [0.5 * sx - 0.002, 0.5 * sy - 0.002]):
        return None
    incision = transform_points(T_ref_pad, np.array([[*a, 0.0], [*b, 0.0]]))
    if not _in_views(rig, incision, BORDER_PX):
        return None
    # -- the needle, lying on the pad ---------------------------------------------------
    arc = CT1.points(64)
    lift = 0.0
    for _ in range(50):
        c = np.array([u(-0.5 * sx, 0.5 * sx), u(-0.5 * sy, 0.5 * sy)])
        turn = u(0.0, 2 * math.pi)
        R_pad_needle = Rotation.from_rotvec([0.0, 0.0, turn])
        if harder > 0.0:
            # resting on its two ends (N's x axis is the chord between them): turned
            # about the chord, the arc (N's +y side) rises off the pad
            lift = u(0.0, MAX_LIFT * harder)
            R_pad_needle = R_pad_needle * Rotation.from_rotvec([lift, 0.0, 0.0])
        T_pad_needle = make_transform(R_pad_needle, [c[0], c[1], 0.5 * CT1.wire_diameter])
        on_pad = transform_points(T_pad_needle, arc)
        if np.any(np.abs(on_pad[:, :2]) > [0.5 * sx - EDGE_CLEARANCE,
                                           0.5 * sy - EDGE_CLEARANCE]):
            continue
        if _segment_distance(on_pad[:, :2], a, b).min() < INCISION_CLEARANCE:
            continue
        T_ref_needle = T_ref_pad @ T_pad_needle
        arc_ref = transform_points(T_ref_needle, arc)
        if _in_views(rig, arc_ref, BORDER_PX):
            break
    else:
        return None
    # -- the arms and their parked grippers ---------------------------------------------
    cam = rig[rig.reference]
    grippers, reach, arms = [], {}, {}
    sides = (("left", -1.0), ("right", 1.0))
    chosen = None
    if drivable is not None:
        # candidate port sites for both arms, all drawn (a fixed share of the stream),
        # before either arm is parked: the pair is chosen together
        sites = {name: [_site(rng, centre, side, SITE_LATERAL, SITE_VERTICAL, SITE_DISTANCE)
                        for _ in range(PORT_CANDIDATES)] for name, side in sides}
        chosen = _choose_ports(sites, incision, normal, T_ref_needle, rig,
                               _outline(T_ref_pad), drivable, workable)
    for name, side in sides:
        if chosen is None:          # the nominal port beside the endoscope's
            site, port, drives = (_site(rng, centre, side, PORT_LATERAL, PORT_VERTICAL,
                                        PORT_DISTANCE), 0, None)
        else:
            port, drives = chosen[0][name], chosen[1][name]
            site = sites[name][port]
        rcm = site.rcm
        for _ in range(50):
            px = (u(70.0, 120.0) if side < 0 else cam.width - u(70.0, 120.0),
                  cam.height / 2 + u(-100.0, 100.0))
            ray = cam.T_ref_cam[:3, :3] @ cam.backproject(np.array([px]))[0]
            height = u(0.012, 0.020)
            o = cam.T_ref_cam[:3, 3]
            den = float(ray @ normal)
            if abs(den) < 0.2:
                continue
            lam = float((centre + height * normal - o) @ normal) / den
            if lam <= 0.02:
                continue
            tip = o + lam * ray
            z = tip - rcm
            z /= np.linalg.norm(z)
            e = np.cross(z, [0.0, 1.0, 0.0])
            e /= np.linalg.norm(e)
            x = Rotation.from_rotvec(u(0.0, 2 * math.pi) * z).apply(e)
            T_tool = make_transform(np.column_stack([x, np.cross(z, x), z]), tip)
            if not _in_views(rig, tip[None], 30.0):
                continue
            if _gripper_clear(rig, T_tool, arc_ref):
                break
        else:
            return None
        needed = np.concatenate([arc_ref, incision, tip[None]])
        if float(np.linalg.norm(needed - rcm, axis=1).max()) > MAX_INSERTION:
            return None       # not with the shipped rig: the pad is 80-120 mm away
        reach[name] = site
        grippers.append(Gripper(name, T_tool, opening=OPEN_GAP, shaft_length=SHAFT_LENGTH))
        arms[name] = {"rcm": _r(rcm), "port": port, "port_drives": drives,
                      "rcm_from_pad_centre": _r(np.linalg.norm(rcm - centre)),
                      "max_insertion": MAX_INSERTION, "park_tip": _r(tip),
                      "park_height": _r(height), "park_px": _r(px, 2)}
    values = {
        "pad": {"centre": _r(centre), "tilt_deg": _r(math.degrees(tilt), 4),
                "tilt_azimuth_deg": _r(math.degrees(azimuth), 4),
                "in_plane_deg": _r(math.degrees(spin), 4), "size": list(PAD_SIZE),
                "T_ref_pad": _r(T_ref_pad)},
        "incision": {"length": _r(length), "angle_deg": _r(math.degrees(inc_angle), 4),
                     "mid_pad_xy": _r(inc_mid), "ends_pad_xy": [_r(a), _r(b)]},
        "needle": {"centre_pad_xy": _r(c), "turn_deg": _r(math.degrees(turn), 4),
                   **({"lift_deg": _r(math.degrees(lift), 4)} if harder > 0.0 else {}),
                   "radius": CT1.radius, "wire_diameter": CT1.wire_diameter,
                   "arc_deg": 180.0, "thread_length": THREAD_LENGTH},
        "arms": arms,
        "ports_workable": None if chosen is None else chosen[2],
    }
    pad = TissuePad("pad", T_ref_pad, PAD_SIZE,
                    incision=((float(a[0]), float(a[1])), (float(b[0]), float(b[1]))))
    # lifted about its chord, its thread lies on the pad (turned back by the lift)
    needle = NeedleObject("needle", CT1, T_ref_needle, thread_length=THREAD_LENGTH,
                          thread_tilt=lift)
    return (pad, needle, tuple(grippers)), reach, values, incision, normal
