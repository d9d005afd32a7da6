"""Needle tracking: speed against accuracy, and where the tracker loses the needle (issue 7).

    python -m oralnav.bench.needle_tracking [OUT] [--quick]
    (``python -m bench`` and ``oralnav bench`` once wired in)

The tracker is seed 002's (``control/needle/tracker.py``): the particle filter, then the
sub-pixel refinement on the wire's centreline, with the suture thread telling base from
tip. Scenes are the simulator's randomised trial cells (``sim/world/needle_trials.py``: the
640 x 480 stereo endoscope, a threaded CT-1 needle on a tilted pad 80-120 mm away, random
light, blur and noise). Every tracker setting runs on the same rendered frames.

1. **Particles sweep** (100 .. 10 000 particles) on a *held, moving* needle. Per trial
   seed, a gripper of the cell (``NeedleCell``) moves from its park pose onto the wire
   (square across its jaws), closes, lifts the needle 4 mm off the pad and then moves it
   steadily, 0.5 mm and 1 degree a frame (a fixed screw about the jaws' tip, drawn per
   seed so the needle stays above the pad, in both views and within the arm's reach). Of
   the feasible grasps (either arm, 0.25-0.75 of the arc from the swage) the one whose
   gripper hides the least of the needle is used, as a grasp planner would choose. The
   tracker initialises on the first frame and then follows with ``predict(delta)``,
   ``delta`` the gripper's reported incremental motion ``T_new @ inv(T_old)`` (reference
   frame). Per setting: update time (predict + update; feature maps are timed apart, they
   do not depend on the particles), initialisation time, position error (needle centre,
   mm) and orientation error (deg) against the truth on every update, the share of
   updates the tracker calls converged. At 3000 particles also: the left channel alone
   ("in the endoscope view"), and the same trials' needle free and still on the pad as
   drawn (Brownian ``predict()``), for comparison with the held one.
2. **Where it loses the needle**, at 3000 particles, one nuisance swept at a time:
   - jaw occlusion: the held, moving needle of (1) with the jaws made wider (``Gripper.
     jaw_width``), so they hide more of the wire; the hidden share is the renderer's
     (arc points not visible in the left view);
   - edge-on: a free, still needle held in the air 20 mm in front of its trial pose
     (nothing else near it), first face-on to the left camera, then turned about an
     in-plane axis (drawn per seed) until its normal is at 90 degrees to the viewing ray;
   - low contrast: the trial's needle on the pad drawn as a flat grey wire (no highlight)
     ``C`` DN darker than the pad, ``C`` from 100 down to 4 DN; the contrast actually in
     the left image (the pad beside the wire minus the wire's centreline) is measured too.
   Each sweep states where the needle is *lost* (the median centre error over 1 mm or the
   median outline angle, the base/tip twin forgiven, over 5 deg) and where the *target is
   missed* (the median error, a twin counted as the 180 degrees it is, over 0.5 mm or
   2 deg, or fewer than half the updates converged).

A track that says it has converged yet is more than 1 mm or 5 degrees off is counted
apart (``converged_wrong_share``): that is what a step would wrongly move on.

Writes ``needle_tracking.json`` and the charts ``needle_tracking_*.png``; progress on
stderr. Lengths in the JSON are mm, angles deg, times ms unless a key says otherwise.
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from oralnav.bench.machine import describe
from oralnav.config.rig import trial_rig
from oralnav.control.geometry import invert, make_transform, transform_points
from oralnav.control.needle.features import NeedleFeatures, feature_maps
from oralnav.control.needle.model import Needle
from oralnav.control.needle.tracker import FilterSettings, NeedleTracker
from oralnav.control.vision.camera import CameraModel
from oralnav.sim.world.needle_cell import ArmReach, CellError, NeedleCell
from oralnav.sim.world.needle_trials import TrialInfo, trial_scene
from oralnav.sim.world.render import SceneRenderer
from oralnav.sim.world.scene import Scene

PARTICLES = (100, 300, 1000, 3000, 10000)
#: A converged update this far off is counted as converged yet wrong (mm, deg).
WRONG_MM, WRONG_DEG = 1.0, 5.0
TARGET = {"particles": 3000, "updates_per_s": 30.0, "position_mm": 0.5, "angle_deg": 2.0}
#: The tracker's search depth at initialisation (m, along the left camera's rays): the
#: trial pads lie 80-120 mm away.
DEPTH_RANGE = (0.06, 0.16)
#: Nominal working distance for the wire's width in pixels (the feature window).
WORKING_DISTANCE = 0.1
#: Held-needle motion per frame (m, rad) and the lift off the pad before tracking (m).
STEP_M = 0.0005
STEP_RAD = math.radians(1.0)
LIFT_M = 0.004
#: Depth of the wire in the jaws (m, along -z of the gripper) at the grasp.
GRASP_DEPTH = 0.0015
#: Where on the arc to grasp (share of the arc from the swage), in order of preference.
GRASP_SHARES = (0.35, 0.5, 0.65, 0.25, 0.75)
#: Clearances the planned motion keeps: the arc above the pad (m) and inside the images
#: (px).
PAD_CLEARANCE = 0.001
VIEW_MARGIN_PX = 10.0
#: Edge-on sweep: how far the needle is brought toward the camera, off the pad (m).
EDGE_ON_LIFT = 0.020

#: Nuisance values, in order of growing nuisance: jaw width (mm; 2.5 is the trial
#: grippers'), angle between the needle's normal and the viewing ray (deg), wire contrast
#: against the pad (DN).
NUISANCES: dict[str, tuple[float, ...]] = {
    "jaw_occlusion": (2.5, 5.0, 7.5, 10.0, 12.5, 15.0, 20.0),
    "edge_on": (0.0, 30.0, 50.0, 60.0, 70.0, 75.0, 80.0, 85.0, 90.0),
    "low_contrast": (100.0, 60.0, 40.0, 25.0, 16.0, 12.0, 8.0, 4.0)}
QUICK_NUISANCES: dict[str, tuple[float, ...]] = {
    "jaw_occlusion": (2.5, 10.0, 20.0),
    "edge_on": (0.0, 60.0, 80.0, 90.0),
    "low_contrast": (60.0, 16.0, 8.0)}


def _say(msg: str) -> None:
    print(f"bench needle_tracking: {msg}", file=sys.stderr, flush=True)


# -- clips: rendered frames reduced to features, with the truth ---------------------------

@dataclass
class Clip:
    """One trial's frames, as the tracker reads them, with the truth.

    ``features[k]``: one :class:`NeedleFeatures` per camera (``cameras`` order) of frame
    ``k``; ``truth[k]``: the needle's true ``T_ref_N``; ``delta[k]``: the gripper's
    reported incremental motion into frame ``k`` (reference frame; ``None`` for a free
    needle and for frame 0); ``feature_ms[k]``: the feature maps' time for the frame (all
    cameras); ``visible[k]``: the share of arc points visible in the left view;
    ``contrast_dn``: the pad-minus-wire level measured in the left image (median over the
    arc, first frame).
    """

    seed: int
    cameras: tuple[CameraModel, ...]
    needle: Needle
    features: list[list[NeedleFeatures]] = field(default_factory=list)
    truth: list[np.ndarray] = field(default_factory=list)
    delta: list[np.ndarray | None] = field(default_factory=list)
    feature_ms: list[float] = field(default_factory=list)
    visible: list[float] = field(default_factory=list)
    contrast_dn: float = math.nan
    notes: dict[str, Any] = field(default_factory=dict)


def _incision_masks(cams: Sequence[CameraModel], info: TrialInfo) -> list[np.ndarray]:
    """The incision drawn as a 16 px band in each view: the operator gives the suture line,
    so the tracker may ignore it (a long dark line the filter would otherwise score)."""
    out = []
    for cam in cams:
        uv = cam.project_from(cam.T_cam_ref, np.asarray(info.incision))
        m = np.zeros((cam.height, cam.width), np.uint8)
        cv2.line(m, tuple(int(x) for x in np.round(uv[0])),
                 tuple(int(x) for x in np.round(uv[1])), 1, 16)
        out.append(m.astype(bool))
    return out


def _add_frame(clip: Clip, images: dict[str, np.ndarray], masks: Sequence[np.ndarray],
               truth: np.ndarray, delta: np.ndarray | None, visible: float) -> None:
    t0 = time.perf_counter()
    feats = []
    for cam, mask in zip(clip.cameras, masks, strict=True):
        wire_px = cam.K[0, 0] * clip.needle.wire_diameter / WORKING_DISTANCE
        feats.append(feature_maps(images[cam.name], wire_px, ignore=mask))
    clip.feature_ms.append((time.perf_counter() - t0) * 1e3)
    clip.features.append(feats)
    clip.truth.append(np.array(truth, dtype=float))
    clip.delta.append(None if delta is None else np.array(delta, dtype=float))
    clip.visible.append(float(visible))


def _wire_contrast(image: np.ndarray, cam: CameraModel, needle: Needle,
                   T_ref_N: np.ndarray) -> float:
    """Median over the arc of (pad beside the wire) - (wire's centreline) in ``image`` (DN):
    the level 2.5 wire widths to either side along the projected normal, averaged, minus
    the centreline's. Positive for a wire darker than its surroundings."""
    pts = transform_points(cam.T_cam_ref @ T_ref_N, needle.points(60))
    uv = cam.project(pts)
    tan = np.gradient(uv, axis=0)
    nrm = np.stack([-tan[:, 1], tan[:, 0]], axis=1)
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-9)
    off = 2.5 * cam.K[0, 0] * needle.wire_diameter / pts[:, 2:3]
    img = image.astype(np.float32)

    def at(p: np.ndarray) -> np.ndarray:
        return cv2.remap(img, p[:, 0].astype(np.float32).reshape(1, -1),
                         p[:, 1].astype(np.float32).reshape(1, -1), cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REPLICATE)[0]

    ok = cam.in_image(uv, 3 + float(off.max()))
    if not ok.any():
        return math.nan
    beside = 0.5 * (at(uv + off * nrm) + at(uv - off * nrm))
    return float(np.median((beside - at(uv))[ok]))


def still_clip(seed: int, scene: Scene, info: TrialInfo, frames: int) -> Clip:
    """A free needle that does not move: ``frames`` renders of ``scene`` (new noise each)."""
    renderer = SceneRenderer(scene, keep_clean=1)  # the same state each frame
    cams = tuple(scene.rig[c] for c in scene.rig.names)
    nd = scene.needles[0]
    clip = Clip(seed, cams, nd.needle)
    masks = _incision_masks(cams, info)
    for k in range(frames):
        fr = renderer.render(frame=k)
        _add_frame(clip, fr.images, masks, nd.T_ref_needle, None,
                   fr.needle_truth[cams[0].name][nd.name].visible_fraction)
        if k == 0:
            clip.contrast_dn = _wire_contrast(fr.images[cams[0].name], cams[0], nd.needle,
                                              nd.T_ref_needle)
    return clip


# -- the held, moving needle -------------------------------------------------------------

def _grasp_pose(T_ref_N: np.ndarray, needle: Needle, share: float, rcm: np.ndarray
                ) -> np.ndarray:
    """The gripper pose ``T_ref_tool`` that holds the wire at ``share`` of the arc: the
    wire along the jaws' x (square across them, as the cell's jaws clamp it), ``GRASP_
    DEPTH`` inside the jaws, the gripper's z as near the shaft's line from the RCM as a
    z square to the wire allows (the wrist bends the rest)."""
    phi = share * needle.arc
    p = transform_points(T_ref_N, needle.point(phi)[None])[0]
    t = T_ref_N[:3, :3] @ needle.tangent(phi)
    d = p - rcm
    d /= np.linalg.norm(d)
    z = d - (d @ t) * t
    z /= np.linalg.norm(z)
    R = np.column_stack([t, np.cross(z, t), z])
    return make_transform(R, p + GRASP_DEPTH * z)


def _path_reachable(reach: ArmReach, T0: np.ndarray, T1: np.ndarray, n: int = 24) -> bool:
    """Whether the straight-line / slerp path from ``T0`` to ``T1`` stays in reach (what
    ``NeedleCell.move`` checks per increment; sampled here so a refused move is rare)."""
    rots = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([T0[:3, :3], T1[:3, :3]])))
    for s in np.linspace(0.0, 1.0, n):
        T = make_transform(rots(s).as_matrix(), (1 - s) * T0[:3, 3] + s * T1[:3, 3])
        if not reach.reachable(T)[0]:
            return False
    return True


def _about(T: np.ndarray, centre: np.ndarray, R: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """``T`` turned by ``R`` about ``centre`` (reference frame), then shifted."""
    M = make_transform(R, centre - R @ centre + shift)
    return M @ T


def _plan_motion(cell: NeedleCell, name: str, T_tool0: np.ndarray, T_tool_N: np.ndarray,
                 frames: int, rng: np.random.Generator) -> list[np.ndarray] | None:
    """Gripper poses for ``frames`` steady frames: each frame turns the gripper by
    ``STEP_RAD`` about a fixed axis through its tip and moves it ``STEP_M`` along a fixed
    direction in the pad's plane (both drawn); the first draw that keeps the arc above the
    pad, in both views and the gripper in reach wins. ``None`` if none of 40 does."""
    pad = cell.pad
    n_pad = pad.T_ref_pad[:3, 2]
    T_pad_ref = invert(pad.T_ref_pad)
    arc = cell.needle.points(40)
    reach = cell.arm_reach(name)
    cams = [cell.rig[c] for c in cell.cameras]
    for _ in range(40):
        axis = Rotation.random(random_state=rng).apply([0.0, 0.0, 1.0])
        v = rng.normal(size=3)
        v -= (v @ n_pad) * n_pad
        v *= STEP_M / np.linalg.norm(v)
        R = Rotation.from_rotvec(STEP_RAD * axis).as_matrix()
        poses, T, ok = [], T_tool0, True
        for _ in range(frames):
            T = _about(T, T[:3, 3], R, v)
            pts = transform_points(T @ T_tool_N, arc)
            if (transform_points(T_pad_ref, pts)[:, 2].min() < PAD_CLEARANCE
                    or not reach.reachable(T)[0]):
                ok = False
                break
            for cam in cams:
                pc = transform_points(cam.T_cam_ref, pts)
                if not np.all(cam.in_image(cam.project(pc), VIEW_MARGIN_PX)):
                    ok = False
            if not ok:
                break
            poses.append(T)
        if ok:
            return poses
    return None


def held_clip(seed: int, frames: int, jaw_width: float | None = None) -> Clip | None:
    """Trial ``seed`` with the needle grasped, lifted and moved (see the module docstring):
    ``frames`` frames, the first before any motion. ``jaw_width`` (m) widens both
    grippers' jaws. Of the grasps (arm and point of the arc) that reach, hold and can move
    the needle as planned, the one that leaves the most of the arc visible in the worse
    view wins (a gripper's shaft, 6 mm thick and near the endoscope, can hide half the
    needle), ties going to the earlier in ``GRASP_SHARES``. ``None`` if none does."""
    scene, reach, info = trial_scene(seed, rig=trial_rig())
    if jaw_width is not None:
        scene = replace(scene, grippers=tuple(replace(g, jaw_width=jaw_width)
                                              for g in scene.grippers))
    rng = np.random.default_rng([seed, 7])
    T_N0 = scene.needles[0].T_ref_needle
    needle = scene.needles[0].needle
    n_pad = scene.pads[0].T_ref_pad[:3, 2]
    best: tuple[float, NeedleCell, str, float, list[np.ndarray]] | None = None
    for share in GRASP_SHARES:
        for g in scene.grippers:
            name = g.name
            T_grasp = _grasp_pose(T_N0, needle, share, reach[name].rcm)
            T_lift = T_grasp.copy()
            T_lift[:3, 3] += LIFT_M * n_pad
            if not (_path_reachable(reach[name], g.T_ref_tool, T_grasp)
                    and _path_reachable(reach[name], T_grasp, T_lift)):
                continue
            cell = NeedleCell(scene, reach)
            try:
                cell.move(name, T_grasp)
                if not cell.close(name):
                    continue
                cell.move(name, T_lift)
            except CellError:
                continue
            T_tool_N = cell.truth().T_tool_needle[name]
            plan = _plan_motion(cell, name, cell.gripper_pose(name), T_tool_N, frames - 1,
                                rng)
            if plan is None:
                continue
            cell.images()
            vis = min(t["needle"].visible_fraction
                      for t in cell.last_frame.needle_truth.values())
            if best is None or vis > best[0]:
                best = (vis, cell, name, share, plan)
    if best is None:
        return None
    _, cell, name, share, plan = best
    cams = tuple(cell.rig[c] for c in cell.cameras)
    clip = Clip(seed, cams, needle, notes={"arm": name, "grasp_share": share,
                                           "jaw_width_mm": 1e3 * cell.gripper(name).jaw_width})
    masks = _incision_masks(cams, info)
    for k in range(frames):
        delta = None
        if k:
            before = cell.gripper_pose(name)
            cell.move(name, plan[k - 1])
            delta = cell.gripper_pose(name) @ invert(before)
        images = cell.images()
        vis = cell.last_frame.needle_truth[cams[0].name]["needle"].visible_fraction
        _add_frame(clip, images, masks, cell.truth().T_ref_needle, delta, vis)
        if k == 0:
            clip.contrast_dn = _wire_contrast(images[cams[0].name], cams[0], needle,
                                              cell.truth().T_ref_needle)
    return clip


# -- the nuisance scenes ------------------------------------------------------------------

def edge_on_scene(seed: int, angle_deg: float) -> tuple[Scene, TrialInfo] | None:
    """Trial ``seed``'s needle brought ``EDGE_ON_LIFT`` toward the left camera along its
    viewing ray (clear of the pad), grippers removed, its normal at ``angle_deg`` to the
    viewing ray to its centre: face-on first, turned about an in-plane axis drawn per seed.
    ``None`` if the arc would leave a view or touch the pad."""
    scene, _, info = trial_scene(seed, rig=trial_rig())
    nd = scene.needles[0]
    cam = scene.rig[scene.rig.names[0]]
    c0 = nd.T_ref_needle[:3, 3]
    eye = cam.T_ref_cam[:3, 3]
    ray = (c0 - eye) / np.linalg.norm(c0 - eye)
    centre = c0 - EDGE_ON_LIFT * ray
    z = -ray                                            # face-on: the normal to the camera
    x = nd.T_ref_needle[:3, 0] - (nd.T_ref_needle[:3, 0] @ z) * z
    x /= np.linalg.norm(x)
    R_face = np.column_stack([x, np.cross(z, x), z])
    beta = np.random.default_rng([seed, 11]).uniform(0.0, math.pi)
    axis = R_face @ np.array([math.cos(beta), math.sin(beta), 0.0])
    R = Rotation.from_rotvec(math.radians(angle_deg) * axis).as_matrix() @ R_face
    T = make_transform(R, centre)
    pts = transform_points(T, nd.needle.points(40))
    pad = scene.pads[0]
    if transform_points(invert(pad.T_ref_pad), pts)[:, 2].min() < PAD_CLEARANCE:
        return None
    for name in scene.rig.names:
        c = scene.rig[name]
        if not np.all(c.in_image(c.project(transform_points(c.T_cam_ref, pts)),
                                 VIEW_MARGIN_PX)):
            return None
    return replace(scene, needles=(replace(nd, T_ref_needle=T),), grippers=()), info


def low_contrast_scene(seed: int, contrast_dn: float) -> tuple[Scene, TrialInfo]:
    """Trial ``seed`` with its needle drawn as a flat grey wire ``contrast_dn`` below the
    pad's level: no shaded base (level 0) and a "highlight" that does not fall off
    (specular ``pad - C`` with shininess 1e-6, so ``cos**1e-6 ~ 1``). The metallic shading
    keeps dark rims at half the base level whatever the level, so it cannot go below some
    20 DN of contrast on this pad."""
    scene, _, info = trial_scene(seed, rig=trial_rig())
    nd = scene.needles[0]
    level = max(scene.pads[0].level - contrast_dn, 0.0)
    nd = replace(nd, level=0.0, specular=level, shininess=1e-6)
    return replace(scene, needles=(nd,)), info


# -- tracking a clip ---------------------------------------------------------------------

def _flip(needle: Needle) -> np.ndarray:
    """The half turn about the arc's bisector (frame N) that swaps base and tip."""
    b = needle.arc / 2
    a = np.array([math.cos(b), math.sin(b), 0.0])
    return 2.0 * np.outer(a, a) - np.eye(3)


def _angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """The angle (deg) of the rotation between ``Ra`` and ``Rb`` (scipy's, not an arccos of
    the trace, which loses precision near zero)."""
    return math.degrees(float(Rotation.from_matrix(Ra.T @ Rb).magnitude()))


def pose_errors(T: np.ndarray, T_true: np.ndarray, needle: Needle, cam: CameraModel
                ) -> dict[str, float]:
    """``T`` against the truth: centre distance (mm), rotation angle (deg), the same angle
    for the nearer of ``T`` and its base/tip twin (the outline's error, deg; the twin
    shares the centre), the RMS distance of 16 arc points (mm), their mean distance in
    ``cam``'s image (px), and ``twin``: whether the twin is the nearer."""
    pts = needle.points(16)
    a, b = transform_points(T, pts), transform_points(T_true, pts)
    uv_a = cam.project(transform_points(cam.T_cam_ref, a))
    uv_b = cam.project(transform_points(cam.T_cam_ref, b))
    ang = _angle_deg(T[:3, :3], T_true[:3, :3])
    ang_twin = _angle_deg(T[:3, :3] @ _flip(needle), T_true[:3, :3])
    return {"position_mm": 1e3 * float(np.linalg.norm(T[:3, 3] - T_true[:3, 3])),
            "angle_deg": ang, "outline_angle_deg": min(ang, ang_twin),
            "arc_rms_mm": 1e3 * float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=1)))),
            "image_px": float(np.mean(np.linalg.norm(uv_a - uv_b, axis=1))),
            "twin": bool(ang_twin < ang)}


def track_clip(clip: Clip, particles: int, cameras: Sequence[int] | None = None
               ) -> dict[str, Any]:
    """Initialise on frame 0, then predict + update on every later frame. Returns the
    initialisation time (ms), each update's wall and CPU time (ms), errors, converged flag
    and reason (why not, when not)."""
    idx = list(range(len(clip.cameras))) if cameras is None else list(cameras)
    cams = [clip.cameras[i] for i in idx]
    tr = NeedleTracker(clip.needle, cams, FilterSettings(particles=particles, seed=clip.seed))
    t0 = time.perf_counter()
    track = tr.initialize([clip.features[0][i] for i in idx], DEPTH_RANGE)
    init_ms = (time.perf_counter() - t0) * 1e3
    out: dict[str, Any] = {"seed": clip.seed, "init_ms": init_ms,
                           "init": {**pose_errors(track.pose, clip.truth[0], clip.needle,
                                                  clip.cameras[0]),
                                    "converged": track.converged},
                           "updates": []}
    for k in range(1, len(clip.features)):
        feats = [clip.features[k][i] for i in idx]
        t0, c0 = time.perf_counter(), time.process_time()
        tr.predict(clip.delta[k])
        track = tr.update(feats)
        ms = (time.perf_counter() - t0) * 1e3
        # the process's CPU time (all its threads) as well: on a shared machine the wall
        # time grows with the neighbours' load, the CPU time much less
        cpu_ms = (time.process_time() - c0) * 1e3
        out["updates"].append({"ms": ms, "cpu_ms": cpu_ms, "converged": bool(track.converged),
                               "reason": track.reason,
                               **pose_errors(track.pose, clip.truth[k], clip.needle,
                                             clip.cameras[0])})
    return out


# -- summaries ----------------------------------------------------------------------------

def _pct(x: Sequence[float], q: float) -> float | None:
    a = np.asarray(x, dtype=float)
    return float(np.percentile(a, q)) if a.size else None


def _reason_kind(reason: str) -> str:
    """The tracker's reason cut to its kind (the figures in it vary)."""
    return reason.split("(")[0].strip() or "converged"


def summarise(runs: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Statistics over every update of ``runs`` (the tracks of one setting)."""
    ups = [u for r in runs for u in r["updates"]]
    conv = [u for u in ups if u["converged"]]
    # converged yet wrong: what a step would move on
    wrong = [u for u in conv if u["position_mm"] > WRONG_MM or u["angle_deg"] > WRONG_DEG]
    ms = [u["ms"] for u in ups]
    med = _pct(ms, 50)
    reasons: dict[str, int] = {}
    for u in ups:
        k = _reason_kind(u["reason"])
        reasons[k] = reasons.get(k, 0) + 1
    return {
        "trials": len(runs), "updates": len(ups),
        "update_ms_median": med, "update_ms_p90": _pct(ms, 90),
        # the fastest tenth: near the cost on an idle machine when neighbours load it
        "update_ms_p10": _pct(ms, 10),
        "update_cpu_ms_median": _pct([u["cpu_ms"] for u in ups], 50),
        "updates_per_s": None if not med else 1e3 / med,
        "init_ms_median": _pct([r["init_ms"] for r in runs], 50),
        "position_mm_median": _pct([u["position_mm"] for u in ups], 50),
        "position_mm_p90": _pct([u["position_mm"] for u in ups], 90),
        "angle_deg_median": _pct([u["angle_deg"] for u in ups], 50),
        "angle_deg_p90": _pct([u["angle_deg"] for u in ups], 90),
        "outline_angle_deg_median": _pct([u["outline_angle_deg"] for u in ups], 50),
        "arc_rms_mm_median": _pct([u["arc_rms_mm"] for u in ups], 50),
        "image_px_median": _pct([u["image_px"] for u in ups], 50),
        "converged_share": len(conv) / len(ups) if ups else None,
        "converged_wrong_share": len(wrong) / len(ups) if ups else None,
        "converged_position_mm_median": _pct([u["position_mm"] for u in conv], 50),
        "converged_angle_deg_median": _pct([u["angle_deg"] for u in conv], 50),
        "twin_share": float(np.mean([u["twin"] for u in ups])) if ups else None,
        "reasons": reasons,
    }


def _lost(s: dict[str, Any]) -> bool:
    """The tracker has lost the needle at a point: the median centre error or the median
    outline angle (base/tip twin forgiven) is grossly off (``WRONG_MM``, ``WRONG_DEG``),
    not merely over the target."""
    if not s["updates"]:
        return True
    return s["position_mm_median"] > WRONG_MM or s["outline_angle_deg_median"] > WRONG_DEG


def _fails(s: dict[str, Any]) -> bool:
    """A point misses the target: the median error (twin counted as the error it is) is
    over the target, or fewer than half its updates are converged."""
    if not s["updates"]:
        return True
    return (s["position_mm_median"] > TARGET["position_mm"]
            or s["angle_deg_median"] > TARGET["angle_deg"] or s["converged_share"] < 0.5)


def _where(points: Sequence[dict[str, Any]], key: str, bad: Callable[[dict[str, Any]], bool]
           ) -> dict[str, Any]:
    """The last value of the sweep (in order of growing nuisance) that still passes before
    the first that does not, by ``bad``."""
    holds, fails = None, None
    for p in points:
        if bad(p):
            fails = p[key]
            break
        holds = p[key]
    return {"holds_to": holds, "fails_from": fails}


def _say_point(what: str, s: dict[str, Any]) -> None:
    if not s["updates"]:
        _say(f"{what}: no trial")
        return
    _say(f"{what}: {s['update_ms_median']:.1f} ms/update ({s['updates_per_s']:.0f}/s), "
         f"{s['position_mm_median']:.2f} mm / {s['angle_deg_median']:.2f} deg median "
         f"(p90 {s['position_mm_p90']:.2f} mm / {s['angle_deg_p90']:.1f} deg), converged "
         f"{100 * s['converged_share']:.0f} % of {s['updates']}")


# -- the sections -------------------------------------------------------------------------

def particle_sweep(seeds: Sequence[int], frames: int, particles: Sequence[int] = PARTICLES,
                   single_camera: int | None = TARGET["particles"]) -> dict[str, Any]:
    """Section 1: every particle count on the same held, moving clips; at
    ``single_camera`` particles also the left view alone and the same trials' needle left
    free and still on the pad. Returns the sweep rows (``sweep``), ``single_camera``,
    ``free_needle`` and what the clips were (``clips``: skipped seeds, feature-map time,
    visibility, grasps)."""
    runs: dict[int, list[dict[str, Any]]] = {p: [] for p in particles}
    single: list[dict[str, Any]] = []
    free: list[dict[str, Any]] = []
    feat_ms: list[float] = []
    feat_ms_left: list[float] = []
    skipped, visible, notes = [], [], []
    warmed = False
    for seed in seeds:
        clip = held_clip(seed, frames)
        if clip is None:
            skipped.append(seed)
            _say(f"seed {seed}: no feasible grasp and motion, skipped")
            continue
        if not warmed:      # compile / load the numba kernels outside the timings
            track_clip(clip, min(particles))
            warmed = True
        feat_ms += clip.feature_ms[1:]
        feat_ms_left += [f / len(clip.cameras) for f in clip.feature_ms[1:]]
        visible += clip.visible
        notes.append({"seed": seed, **clip.notes})
        for p in particles:
            runs[p].append(track_clip(clip, p))
        if single_camera:
            single.append(track_clip(clip, single_camera, cameras=[0]))
            # the same trial untouched: the needle free and still on the pad, grippers
            # parked clear of it (the trial as drawn), for comparison with the held one
            scene, _, tinfo = trial_scene(seed, rig=trial_rig())
            free.append(track_clip(still_clip(seed, scene, tinfo, frames), single_camera))
        last = runs[particles[-1]][-1]["updates"][-1] if runs[particles[-1]] else None
        _say(f"seed {seed} done ({clip.notes['arm']} arm at {clip.notes['grasp_share']:.2f} "
             f"of the arc; {particles[-1]} particles: "
             f"{last['position_mm']:.2f} mm / {last['angle_deg']:.2f} deg last)"
             if last else f"seed {seed} done")
    rows = []
    for p in particles:
        s = {"particles": p, "cameras": "stereo", **summarise(runs[p]), "runs": runs[p]}
        _say_point(f"{p:5d} particles, stereo", s)
        rows.append(s)
    one = still = None
    if single_camera:
        one = {"particles": single_camera, "cameras": "left", **summarise(single),
               "runs": single}
        _say_point(f"{single_camera} particles, left view only", one)
        still = {"particles": single_camera, "cameras": "stereo", **summarise(free),
                 "runs": free}
        _say_point(f"{single_camera} particles, free needle still on the pad", still)
    info = {"seeds": list(seeds), "skipped_seeds": skipped, "frames_per_trial": frames,
            "feature_ms_median_stereo": _pct(feat_ms, 50),
            "feature_ms_median_per_camera": _pct(feat_ms_left, 50),
            "visible_share_median": _pct(visible, 50),
            "visible_share_min": float(min(visible)) if visible else None,
            "grasps": notes}
    return {"sweep": rows, "single_camera": one, "free_needle": still, "clips": info}


def nuisance_clip(name: str, seed: int, value: float, frames: int) -> Clip | None:
    """Trial ``seed``'s clip of ``frames`` frames under nuisance ``name`` at ``value``
    (jaw width mm, normal-to-ray angle deg, contrast DN; see the module docstring);
    ``None`` where the trial cannot be built so (no grasp, the needle out of view)."""
    if name == "jaw_occlusion":
        return held_clip(seed, frames, jaw_width=value * 1e-3)
    if name == "edge_on":
        made = edge_on_scene(seed, value)
        return None if made is None else still_clip(seed, *made, frames)
    if name == "low_contrast":
        return still_clip(seed, *low_contrast_scene(seed, value), frames)
    raise ValueError(f"unknown nuisance {name!r}; have {list(NUISANCES)}")


def nuisance_trial(item: tuple[str, float, int, int, int]) -> dict[str, Any] | None:
    """One trial of a nuisance sweep, ``(name, value, seed, frames, particles)``: the
    track of :func:`nuisance_clip` (``track_clip``'s record) with the clip's visible
    shares and measured contrast, or ``None`` where the clip cannot be built. A pure
    function of its item, so it runs on any engine of ``bench/executor.py``; BLAS is held
    to one thread in it, as in :func:`run`."""
    from threadpoolctl import threadpool_limits

    name, value, seed, frames, particles = item
    with threadpool_limits(limits=1, user_api="blas"):
        clip = nuisance_clip(name, seed, value, frames)
        if clip is None:
            return None
        return {"run": track_clip(clip, particles), "visible": clip.visible,
                "contrast_dn": clip.contrast_dn}


def _point(value: float, seeds: Sequence[int], trials: Sequence[dict[str, Any] | None]
           ) -> dict[str, Any]:
    """One nuisance value's summary from its trials (``None``: the seed was skipped)."""
    runs = [t["run"] for t in trials if t is not None]
    vis = [v for t in trials if t is not None for v in t["visible"]]
    contrast = [t["contrast_dn"] for t in trials
                if t is not None and math.isfinite(t["contrast_dn"])]
    return {"value": value, **summarise(runs),
            "skipped_seeds": [s for s, t in zip(seeds, trials, strict=True) if t is None],
            "visible_share_median": _pct(vis, 50), "contrast_dn_median": _pct(contrast, 50),
            "runs": runs}


def _edge_on_seeds(start: int, n: int, angles: Sequence[float]) -> list[int]:
    """The first ``n`` seeds from ``start`` whose needle, brought off the pad, stays in
    both views and off the pad at every angle of the sweep, so that every angle is
    measured on the same trials."""
    out, seed = [], start
    while len(out) < n and seed < start + 20 * n:
        if all(edge_on_scene(seed, a) is not None for a in angles):
            out.append(seed)
        seed += 1
    return out


#: Per nuisance: its value's key in the points and its unit.
_NUISANCE_KEYS = {"jaw_occlusion": ("jaw_width_mm", "mm"),
                  "edge_on": ("normal_to_ray_deg", "deg"),
                  "low_contrast": ("contrast_dn", "DN")}


def failures(start: int, n: int, frames: int, values: dict[str, Sequence[float]],
             particles: int = TARGET["particles"], scheduler: str | None = None,
             workers: int | None = None) -> dict[str, Any]:
    """Section 2: the three nuisance sweeps, each over ``values[name]`` in order of growing
    nuisance, on ``n`` trials from seed ``start`` (edge-on: the first ``n`` that fit at
    every angle). Every (value, seed) is a trial on the engine ``scheduler`` names
    (``bench/executor.py``; default a local process pool of ``workers``): the errors do
    not depend on where a trial ran, its update times do (they are not what this section
    reports)."""
    from oralnav.bench.executor import TrialRunner

    seeds = list(range(start, start + n))
    edge_seeds = _edge_on_seeds(start, n, values["edge_on"])
    used = {"jaw_occlusion": seeds, "edge_on": edge_seeds, "low_contrast": seeds}
    items = [(name, v, seed, frames, particles)
             for name in _NUISANCE_KEYS for v in values[name] for seed in used[name]]
    t0 = time.perf_counter()

    def said(i: int, _trial: Any, done: int, total: int) -> None:
        name, v, seed = items[i][:3]
        _say(f"{name} {v:g} seed {seed} ({done}/{total}), "
             f"{time.perf_counter() - t0:.0f} s")

    with TrialRunner(scheduler, workers) as runner:
        trials = runner.map(nuisance_trial, items, on_result=said) if items else []
    out: dict[str, Any] = {"particles": particles, "seeds": seeds,
                           "edge_on_seeds": edge_seeds, "frames_per_trial": frames}
    for name, (key, unit) in _NUISANCE_KEYS.items():
        pts = []
        for v in values[name]:
            got = [t for it, t in zip(items, trials, strict=True)
                   if it[0] == name and it[1] == v]
            p = _point(v, used[name], got)
            _say_point(f"{name} {v:g}", p)
            p[key] = p.pop("value")
            pts.append(p)
        out[name] = pts
        out[f"{name}_where"] = {"unit": unit, "lost": _where(pts, key, _lost),
                                "target": _where(pts, key, _fails)}
        _say(f"[{name}: {out[f'{name}_where']}]")
    out["seconds"] = time.perf_counter() - t0
    return out


# -- charts -------------------------------------------------------------------------------

def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _plain_log_axis(axis: Any) -> None:
    """Plain numbers on a log axis: the decades and the 2s and 5s between them (matplotlib
    would write 2x10^-1)."""
    from matplotlib.ticker import FormatStrFormatter, FuncFormatter

    def minor(v: float, _pos: int) -> str:
        lead = round(v / 10 ** math.floor(math.log10(v) + 1e-9))
        return f"{v:g}" if lead in (2, 5) else ""

    axis.set_major_formatter(FormatStrFormatter("%g"))
    axis.set_minor_formatter(FuncFormatter(minor))


def _chart_sweep(doc: dict[str, Any], out: Path) -> list[str]:
    plt = _plt()
    rows = [r for r in doc["sweep"] if r["updates"]]
    P = [r["particles"] for r in rows]
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4.4))
    a1.plot(P, [r["position_mm_median"] for r in rows], "o-", color="C0",
            label="position median (mm)")
    a1.plot(P, [r["position_mm_p90"] for r in rows], "o:", color="C0",
            label="position p90 (mm)")
    a1.plot(P, [r["angle_deg_median"] for r in rows], "s-", color="C1",
            label="angle median (deg)")
    a1.plot(P, [r["outline_angle_deg_median"] for r in rows], "s--", color="C2",
            label="outline angle median (deg, twin forgiven)")
    a1.axhline(TARGET["position_mm"], color="C0", lw=0.8, ls="--")
    a1.axhline(TARGET["angle_deg"], color="C1", lw=0.8, ls="--")
    a1.set_xscale("log")
    a1.set_yscale("log")
    _plain_log_axis(a1.xaxis)
    _plain_log_axis(a1.yaxis)
    a1.set_xlabel("particles")
    a1.set_ylabel("error against truth (mm, deg)")
    a1.set_title("needle error (stereo, held needle moving)", fontsize=10)
    a1.grid(alpha=0.3, which="both")
    a1.legend(fontsize=7)
    a2.plot(P, [r["updates_per_s"] for r in rows], "o-", label="updates/s (median time)")
    a2.plot(P, [1e3 / r["update_ms_p10"] for r in rows], "o:",
            label="updates/s (fastest tenth)")
    a2.axhline(TARGET["updates_per_s"], color="r", lw=0.8, label="target 30/s")
    a2b = a2.twinx()
    a2b.plot(P, [100 * r["converged_share"] for r in rows], "^--", color="C3",
             label="converged %")
    a2b.plot(P, [100 * r["converged_wrong_share"] for r in rows], "v:", color="C4",
             label="converged yet > 1 mm / 5 deg off %")
    a2b.set_ylim(0, 105)
    a2b.set_ylabel("share of updates (%)")
    a2.set_xscale("log")
    _plain_log_axis(a2.xaxis)
    a2.set_ylim(bottom=0)
    a2.set_xlabel("particles")
    a2.set_ylabel("tracking updates per second")
    load = doc["machine"].get("load_average_start", [math.nan])[0]
    a2.set_title(f"speed, feature maps not included ({doc['machine']['cpus']} cores, "
                 f"load {load:.1f} at start)", fontsize=10)
    a2.grid(alpha=0.3, which="both")
    h1, l1 = a2.get_legend_handles_labels()
    h2, l2 = a2b.get_legend_handles_labels()
    a2.legend(h1 + h2, l1 + l2, fontsize=7)
    fig.tight_layout()
    p1 = out / "needle_tracking_particles.png"
    fig.savefig(p1, dpi=110)
    plt.close(fig)

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.4))
    for ax, key, label, target in (
            (axes[0], "position_mm_median", "median position error (mm)",
             TARGET["position_mm"]),
            (axes[1], "angle_deg_median", "median orientation error (deg)",
             TARGET["angle_deg"])):
        for r in rows:
            ax.plot(r[key], r["updates_per_s"], "o", color="C0")
            ax.annotate(f"{r['particles']}", (r[key], r["updates_per_s"]),
                        textcoords="offset points", xytext=(5, 4), fontsize=8)
        for extra, mark, colour, name in (("single_camera", "s", "C1", "left view only"),
                                          ("free_needle", "D", "C2", "free needle, still")):
            r = doc.get(extra)
            if r and r["updates"]:
                ax.plot(r[key], r["updates_per_s"], mark, color=colour,
                        label=f"{name}, {r['particles']}")
        ax.plot([], [], "o", color="C0", label="held needle moving, stereo")
        ax.axhline(TARGET["updates_per_s"], color="r", lw=0.8)
        ax.axvline(target, color="r", lw=0.8)
        ax.set_xscale("log")
        _plain_log_axis(ax.xaxis)
        ax.set_xlabel(label)
        ax.set_ylabel("tracking updates per second (median)")
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7)
    fig.suptitle("speed against accuracy (labels: particles; red: the targets)", fontsize=10)
    fig.tight_layout()
    p2 = out / "needle_tracking_speed_accuracy.png"
    fig.savefig(p2, dpi=110)
    plt.close(fig)
    return [p1.name, p2.name]


def _chart_failures(doc: dict[str, Any], out: Path) -> str:
    plt = _plt()
    f = doc["failures"]
    fig, axes = plt.subplots(1, 3, figsize=(16, 4.6))
    for ax, name, key, label in (
            (axes[0], "jaw_occlusion", "jaw_width_mm", "jaw width (mm)"),
            (axes[1], "edge_on", "normal_to_ray_deg",
             "angle between needle normal and viewing ray (deg)"),
            (axes[2], "low_contrast", "contrast_dn", "wire contrast against the pad (DN)")):
        pts = [p for p in f[name] if p["updates"]]
        x = [p[key] for p in pts]
        ax.plot(x, [p["position_mm_median"] for p in pts], "o-", label="position median (mm)")
        ax.plot(x, [p["angle_deg_median"] for p in pts], "s-", label="angle median (deg)")
        ax.plot(x, [p["outline_angle_deg_median"] for p in pts], "s:",
                label="outline angle median (deg, twin forgiven)")
        ax.axhline(TARGET["position_mm"], color="C0", lw=0.8, ls="--")
        ax.axhline(TARGET["angle_deg"], color="C1", lw=0.8, ls="--")
        ax.set_yscale("log")
        _plain_log_axis(ax.yaxis)
        ax.set_xlabel(label)
        ax.set_ylabel("error (mm, deg)")
        ax.grid(alpha=0.3, which="both")
        axb = ax.twinx()
        axb.plot(x, [100 * p["converged_share"] for p in pts], "^--", color="C3",
                 label="converged %")
        if name == "jaw_occlusion":
            axb.plot(x, [100 * (1 - p["visible_share_median"]) for p in pts], "v:",
                     color="C4", label="arc hidden in the left view %")
        axb.set_ylim(0, 105)
        axb.set_ylabel("%")
        if name == "low_contrast":
            ax.invert_xaxis()       # growing nuisance to the right, as in the others
        w = f[f"{name}_where"]
        ax.set_title(f"{name.replace('_', ' ')}: outline lost from {w['lost']['fails_from']}"
                     f", target missed from {w['target']['fails_from']} {w['unit']}",
                     fontsize=9)
        h1, l1 = ax.get_legend_handles_labels()
        h2, l2 = axb.get_legend_handles_labels()
        ax.legend(h1 + h2, l1 + l2, fontsize=6, loc="upper left", framealpha=0.8)
    fig.suptitle(f"where the tracker loses the needle ({f['particles']} particles, stereo; "
                 f"{len(f['seeds'])} trials a point)", fontsize=10)
    fig.tight_layout()
    p = out / "needle_tracking_failures.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    return p.name


# -- the run ------------------------------------------------------------------------------

def _blas_threads() -> list[str]:
    from threadpoolctl import threadpool_info

    return [f"{i['internal_api']} {Path(i['filepath']).name}: {i['num_threads']} thread(s)"
            for i in threadpool_info() if i.get("user_api") == "blas"]


def _machine() -> dict[str, Any]:
    import numba

    return describe(numpy=np.__version__, opencv=cv2.__version__, numba=numba.__version__,
                    numba_threads=numba.get_num_threads())


def _plain(x: Any) -> Any:
    """The JSON form: numpy made plain, non-finite floats as null, floats to 5 significant
    digits (the per-update records run to thousands)."""
    if isinstance(x, dict):
        return {k: _plain(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_plain(v) for v in x]
    if isinstance(x, np.ndarray):
        return _plain(x.tolist())
    if isinstance(x, np.generic):
        return _plain(x.item())
    if isinstance(x, float):
        return float(f"{x:.5g}") if math.isfinite(x) else None
    return x


def run(out: Path, *, quick: bool, seed: int, sweep_seeds: int, sweep_frames: int,
        particles: Sequence[int], failure_seeds: int, failure_frames: int,
        nuisances: dict[str, Sequence[float]], scheduler: str | None = None,
        workers: int | None = 1) -> dict[str, Any]:
    """The bench with explicit sizes (``main`` picks them; the smoke test shrinks them).
    ``nuisances``: the values of each nuisance sweep, by section name. The nuisance
    trials run on the engine ``scheduler``/``workers`` name (``bench/executor.py``); by
    default in this process, as before: the particles sweep has by then started the
    tracker's OpenMP threads here, and a process pool forked after that aborts.

    BLAS is held to one thread while it runs (threadpoolctl; restored after): the
    refinement's small solves gain nothing from BLAS threads, and on the shared 2-core
    machine spinning BLAS workers beside a busy neighbour slow everything down. The
    filter's kernel is numba's and keeps its threads."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        return _run(Path(out), quick=quick, seed=seed, sweep_seeds=sweep_seeds,
                    sweep_frames=sweep_frames, particles=particles,
                    failure_seeds=failure_seeds, failure_frames=failure_frames,
                    nuisances=nuisances, scheduler=scheduler, workers=workers)


def _run(out: Path, *, quick: bool, seed: int, sweep_seeds: int, sweep_frames: int,
         particles: Sequence[int], failure_seeds: int, failure_frames: int,
         nuisances: dict[str, Sequence[float]], scheduler: str | None,
         workers: int | None) -> dict[str, Any]:
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    pinned = _blas_threads()
    doc: dict[str, Any] = {
        "bench": "needle_tracking", "quick": quick, "seed": seed,
        "command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]),
        "machine": {**_machine(), "blas_threads_pinned": pinned,
                    "load_average_start": list(os.getloadavg())},
        "scenes": "sim.needle_trials trial cells (640x480 stereo endoscope, threaded CT-1 "
                  "needle, tilted pad 80-120 mm away); see the module docstring",
        "motion": {"step_mm": STEP_M * 1e3, "step_deg": math.degrees(STEP_RAD),
                   "lift_mm": LIFT_M * 1e3, "grasp_shares": list(GRASP_SHARES)},
        "depth_range_m": list(DEPTH_RANGE)}
    t0 = time.perf_counter()
    sec = particle_sweep(range(seed, seed + sweep_seeds), sweep_frames, particles)
    rows, info = sec["sweep"], sec["clips"]
    doc["sweep"], doc["single_camera"] = rows, sec["single_camera"]
    doc["free_needle"], doc["sweep_clips"] = sec["free_needle"], info
    doc["section_s"] = {"sweep": time.perf_counter() - t0}
    doc["machine"]["load_average_after_sweep"] = list(os.getloadavg())
    t0 = time.perf_counter()
    doc["failures"] = failures(seed, failure_seeds, failure_frames, nuisances,
                               scheduler=scheduler, workers=workers)
    doc["section_s"]["failures"] = time.perf_counter() - t0
    at = next((r for r in rows if r["particles"] == TARGET["particles"]), None)
    if at is not None and at["updates"]:
        doc["target"] = {
            **TARGET, "measured_updates_per_s": at["updates_per_s"],
            "measured_position_mm_median": at["position_mm_median"],
            "measured_angle_deg_median": at["angle_deg_median"],
            "measured_with_feature_maps_per_s": 1e3 / (at["update_ms_median"]
                                                       + info["feature_ms_median_stereo"]),
            "met_speed": at["updates_per_s"] >= TARGET["updates_per_s"],
            "met_accuracy": (at["position_mm_median"] <= TARGET["position_mm"]
                             and at["angle_deg_median"] <= TARGET["angle_deg"])}
    else:
        doc["target"] = {**TARGET, "measured": None}
    doc["charts"] = [*_chart_sweep(doc, out), _chart_failures(doc, out)]
    doc["elapsed_s"] = time.perf_counter() - t_start
    # other processes share this machine's cores: the load says how quiet it was
    doc["machine"]["load_average_end"] = list(os.getloadavg())
    (out / "needle_tracking.json").write_text(json.dumps(_plain(doc), indent=1) + "\n")
    t = doc["target"]
    if "measured_updates_per_s" in t:
        def word(met: bool) -> str:
            return "met" if met else "MISSED"

        _say(f"{TARGET['particles']} particles: {t['measured_updates_per_s']:.0f} updates/s "
             f"(target {TARGET['updates_per_s']:.0f}: {word(t['met_speed'])}), median "
             f"{t['measured_position_mm_median']:.2f} mm / "
             f"{t['measured_angle_deg_median']:.2f} deg (target {TARGET['position_mm']} mm / "
             f"{TARGET['angle_deg']} deg: {word(t['met_accuracy'])})")
    else:
        _say(f"{TARGET['particles']} particles were not run: the targets are not measured")
    _say(f"{doc['elapsed_s']:.0f} s; wrote {out}/needle_tracking.json and "
         f"{len(doc['charts'])} charts")
    return doc


def main(out: Path, quick: bool = False, seed: int = 0) -> dict[str, Any]:
    """Quick: 6 trials of 6 frames for the sweep, 5 trials of 4 frames per nuisance
    value (under a minute idle, about 2 minutes under load); full: 30 trials of 11
    frames, 10 trials of 6 frames (7-8 minutes)."""
    if quick:
        return run(out, quick=True, seed=seed, sweep_seeds=6, sweep_frames=6,
                   particles=PARTICLES, failure_seeds=5, failure_frames=4,
                   nuisances=QUICK_NUISANCES)
    return run(out, quick=False, seed=seed, sweep_seeds=30, sweep_frames=11,
               particles=PARTICLES, failure_seeds=10, failure_frames=6, nuisances=NUISANCES)


if __name__ == "__main__":
    import argparse

    ap = argparse.ArgumentParser(prog="python -m oralnav.bench.needle_tracking")
    ap.add_argument("out", nargs="?", default=str(Path(__file__).parent / "out"))
    ap.add_argument("--quick", action="store_true", help="fewer trials (about 2 minutes)")
    ap.add_argument("--seed", type=int, default=0, help="first trial seed")
    args = ap.parse_args()
    main(Path(args.out), quick=args.quick, seed=args.seed)
