"""Needle tracking by a particle filter over the needle's pose (seed 002, §III.B).

Each particle is a pose ``T_ref_N`` of the needle (frame N, :mod:`.needle`) in the rig's
reference frame. One update:

1. **Motion** (:meth:`NeedleFilter.predict`): Brownian motion while the needle is free
   (each particle perturbed by Gaussian noise in position and rotation); while it is
   grasped, every particle moved by the gripper's incremental motion first.
2. **Measurement** (:meth:`NeedleFilter.update`): each image is reduced to a thin-feature
   map (:func:`feature_distance`: pixels on thin dark or bright lines, such as the wire,
   and the distance of every pixel to the nearest of them). A particle's score in a
   camera is the mean over the needle's arc sample points, projected through the camera
   model, of ``exp(-d^2 / 2 sigma^2)`` with ``d`` the distance-map value there (0 for a
   point outside the image). The seed renders a virtual image per particle and
   correlates it with the segmented image; projecting a few dozen arc points and reading a
   distance map is the same comparison without the rendering, a few microseconds a
   particle. Cameras' scores add (stereo: both views must agree).
3. **Weights** ``exp(gain * score)``, then low-variance resampling (seed ref. [24]).

Global initialisation (:meth:`NeedleFilter.initialize`) draws particles that put one arc
point on a feature pixel of the first image at a depth inside the workspace, then anneals
on that image (updates with shrinking noise). The estimate is the weighted chordal mean of
the particles; its spread (position and angle) and score say whether the filter has
converged (:class:`NeedleEstimate`), which is what a step that would move on the estimate
must check.

**Symmetry.** A circular arc is its own image under a half turn about its bisector (the
in-plane axis at ``arc / 2``): base and tip swap and every point stays on the wire. No
outline can tell them apart; the estimate is reported in the orientation nearest the
previous one (the first time, the heavier of the two modes) and ``NeedleEstimate.pose_alt``
is the other. Telling base from tip needs a cue the outline lacks (the suture at the swage,
or the grasp that placed it).

**Tissue.** A needle driven into tissue is partly under its surface. Given that surface
(:class:`TissuePlane`, :meth:`NeedleTracker.set_occluder`), arc points under it are
expected unseen: chords touching them count neither as support nor as missing wire, and
a particle that would show less than :attr:`FilterSettings.min_visible` of its arc
scores 0 (a sliver on a feature is no evidence).

Pure math on arrays: images in, poses out; no I/O. Metres, radians, pixels.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numba
import numpy as np
from scipy.spatial.transform import Rotation

from oralnav.control.errors import NeedleError
from oralnav.control.geometry import nearest_rigid, rotation_angle
from oralnav.control.needle.features import NeedleFeatures
from oralnav.control.needle.model import Needle
from oralnav.control.needle.refine import (
    PosePrior,
    PoseRefiner,
    Refined,
    RefineSettings,
    TissuePlane,
    ToolCylinder,
    checked_masks,
    checked_tools,
    swage_evidence,
)
from oralnav.control.vision.camera import CameraModel

__all__ = ["FilterSettings", "NeedleEstimate", "NeedleFilter", "NeedleTrack", "NeedleTracker",
           "TissuePlane", "ToolCylinder", "TrackSettings", "mirror_tilt"]


@dataclass(frozen=True)
class FilterSettings:
    """Particle filter settings. Lengths m, angles rad, pixels px."""

    particles: int = 3000
    arc_points: int = 48            # arc sample points projected per particle
    sigma_px: float = 2.0           # width of a point's score about a feature pixel
    cap_px: float = 12.0            # distances beyond this score nothing
    gain: float = 40.0              # weights exp(gain * score): how sharply a frame decides
    position_noise: float = 0.0005  # Brownian motion per update, free needle (m)
    rotation_noise: float = 0.03    # Brownian motion per update, free needle (rad)
    grasped_position_noise: float = 0.0002
    grasped_rotation_noise: float = 0.01
    anneal_steps: int = 12          # updates on the first image at initialisation
    anneal_start: float = 6.0       # noise factor of the first anneal step (to 1 at the end)
    converged_position: float = 0.001   # spread below which the filter has converged (m)
    converged_angle: float = math.radians(3.0)
    converged_score: float = 0.5    # mean point score of the estimate, per camera
    min_visible: float = 0.2        # with a tissue plane: a view showing less of a
                                    # particle's arc than this share scores 0
    seed: int = 0

    def __post_init__(self) -> None:
        if self.particles < 10 or self.arc_points < 4:
            raise NeedleError(f"the needle filter needs >= 10 particles and >= 4 arc points, "
                              f"got {self.particles} and {self.arc_points}")
        if not (self.sigma_px > 0 and self.cap_px > self.sigma_px and self.gain > 0):
            raise NeedleError("sigma_px > 0, cap_px > sigma_px and gain > 0 are required")
        if min(self.position_noise, self.rotation_noise, self.grasped_position_noise,
               self.grasped_rotation_noise) < 0 or self.anneal_steps < 0:
            raise NeedleError("motion noise and anneal_steps must be >= 0")
        if not 0.0 <= self.min_visible < 1.0:
            raise NeedleError(f"min_visible must be in [0, 1), got {self.min_visible}")


@dataclass(frozen=True)
class NeedleEstimate:
    """The filter's answer after an update.

    ``pose``: ``T_ref_N`` (4x4); ``pose_alt``: the same outline with base and tip swapped.
    ``position_spread`` (m) and ``angle_spread`` (rad): weighted RMS of the particles about
    the estimate. ``score``: the share of the estimate's projected arc that lies on thin
    features, mean over the cameras (0..1).
    ``match``: its normalised correlation with the features (:meth:`NeedleFilter._match`,
    1 for the best particle's coverage). ``ess``: effective sample size before
    resampling. ``converged``: spreads, score and match within the settings' bounds: only
    then may a step move on ``pose``.
    """

    pose: np.ndarray
    pose_alt: np.ndarray
    position_spread: float
    angle_spread: float
    score: float
    match: float
    ess: float
    converged: bool
    best: np.ndarray | None = None    # the heaviest particle's pose (the swarm's mode)


# -- thin features ------------------------------------------------------------------------

# -- compiled kernels --------------------------------------------------------------------

@numba.njit(cache=True, inline="always")
def _pixel(Kc: np.ndarray, dc: np.ndarray, x: float, y: float, z: float, general: bool
           ) -> tuple[float, float]:
    """OpenCV's projection (rational radial, tangential and thin-prism terms; the tilted
    model is refused by the filter) of a camera-frame point; NaN behind the camera.
    ``general`` False: the rational denominator and thin-prism coefficients are all zero
    and are skipped (the same values: the skipped terms divide by 1 and add 0)."""
    if z <= 0.0:
        return math.nan, math.nan
    xn, yn = x / z, y / z
    r2 = xn * xn + yn * yn
    r4 = r2 * r2
    r6 = r4 * r2
    if not general:
        radial = 1.0 + dc[0] * r2 + dc[1] * r4 + dc[4] * r6
        xd = xn * radial + 2.0 * dc[2] * xn * yn + dc[3] * (r2 + 2.0 * xn * xn)
        yd = yn * radial + dc[2] * (r2 + 2.0 * yn * yn) + 2.0 * dc[3] * xn * yn
        return Kc[0, 0] * xd + Kc[0, 2], Kc[1, 1] * yd + Kc[1, 2]
    radial = (1.0 + dc[0] * r2 + dc[1] * r4 + dc[4] * r6) / \
        (1.0 + dc[5] * r2 + dc[6] * r4 + dc[7] * r6)
    xd = xn * radial + 2.0 * dc[2] * xn * yn + dc[3] * (r2 + 2.0 * xn * xn) \
        + dc[8] * r2 + dc[9] * r4
    yd = yn * radial + dc[2] * (r2 + 2.0 * yn * yn) + 2.0 * dc[3] * xn * yn \
        + dc[10] * r2 + dc[11] * r4
    return Kc[0, 0] * xd + Kc[0, 2], Kc[1, 1] * yd + Kc[1, 2]


@numba.njit(cache=True, nogil=True, inline="always")
def _score_one(p: int, out: np.ndarray, R: np.ndarray, t: np.ndarray, pts: np.ndarray,
               T_cam_ref: np.ndarray, Ks: np.ndarray, ds: np.ndarray, general_model: np.ndarray,
               maps: np.ndarray, sizes: np.ndarray, inv2s2: float, cap: float,
               plane: np.ndarray, occluded: bool, floor: float) -> None:
    """Particle ``p``'s row of :func:`_scores` (written into ``out[p]``)."""
    C, K = Ks.shape[0], pts.shape[0]
    # the particle's points' heights above the (shifted) plane: the same in every view
    if occluded:
        a0 = plane[0] * R[p, 0, 0] + plane[1] * R[p, 1, 0] + plane[2] * R[p, 2, 0]
        a1 = plane[0] * R[p, 0, 1] + plane[1] * R[p, 1, 1] + plane[2] * R[p, 2, 1]
        a2 = plane[0] * R[p, 0, 2] + plane[1] * R[p, 1, 2] + plane[2] * R[p, 2, 2]
        a3 = plane[0] * t[p, 0] + plane[1] * t[p, 1] + plane[2] * t[p, 2] + plane[3]
    else:
        a0 = a1 = a2 = a3 = 0.0
    for c in range(C):
        # T_cam_N = T_cam_ref @ T_ref_N, row by row
        A = T_cam_ref[c]
        r00 = A[0, 0] * R[p, 0, 0] + A[0, 1] * R[p, 1, 0] + A[0, 2] * R[p, 2, 0]
        r01 = A[0, 0] * R[p, 0, 1] + A[0, 1] * R[p, 1, 1] + A[0, 2] * R[p, 2, 1]
        r02 = A[0, 0] * R[p, 0, 2] + A[0, 1] * R[p, 1, 2] + A[0, 2] * R[p, 2, 2]
        r10 = A[1, 0] * R[p, 0, 0] + A[1, 1] * R[p, 1, 0] + A[1, 2] * R[p, 2, 0]
        r11 = A[1, 0] * R[p, 0, 1] + A[1, 1] * R[p, 1, 1] + A[1, 2] * R[p, 2, 1]
        r12 = A[1, 0] * R[p, 0, 2] + A[1, 1] * R[p, 1, 2] + A[1, 2] * R[p, 2, 2]
        r20 = A[2, 0] * R[p, 0, 0] + A[2, 1] * R[p, 1, 0] + A[2, 2] * R[p, 2, 0]
        r21 = A[2, 0] * R[p, 0, 1] + A[2, 1] * R[p, 1, 1] + A[2, 2] * R[p, 2, 1]
        r22 = A[2, 0] * R[p, 0, 2] + A[2, 1] * R[p, 1, 2] + A[2, 2] * R[p, 2, 2]
        m0 = A[0, 0] * t[p, 0] + A[0, 1] * t[p, 1] + A[0, 2] * t[p, 2] + A[0, 3]
        m1 = A[1, 0] * t[p, 0] + A[1, 1] * t[p, 1] + A[1, 2] * t[p, 2] + A[1, 3]
        m2 = A[2, 0] * t[p, 0] + A[2, 1] * t[p, 1] + A[2, 2] * t[p, 2] + A[2, 3]
        W, H = sizes[c, 0] - 1, sizes[c, 1] - 1
        general = general_model[c]     # the camera's rational or thin-prism terms
        sup = 0.0
        tot = 0.0
        full = 0.0          # the length in the image, hidden or not (occluded only)
        pu, pv, ps, prev_in, prev_seen = 0.0, 0.0, 0.0, False, False
        for k in range(K):
            q0, q1, q2 = pts[k, 0], pts[k, 1], pts[k, 2]
            u, v = _pixel(Ks[c], ds[c], r00 * q0 + r01 * q1 + r02 * q2 + m0,
                          r10 * q0 + r11 * q1 + r12 * q2 + m1,
                          r20 * q0 + r21 * q1 + r22 * q2 + m2, general)
            inside = u >= 0.0 and v >= 0.0 and u <= W and v <= H   # False for NaN
            sc = 0.0
            if not occluded:
                if inside:
                    d = maps[c, int(v + 0.5), int(u + 0.5)]
                    if d == 0.0:            # on a feature: exp(0), without the call
                        sc = 1.0
                    elif d < cap:
                        sc = math.exp(-d * d * inv2s2)
                    if prev_in:
                        ln = math.hypot(u - pu, v - pv)
                        sup += 0.5 * ln * (sc + ps)
                        tot += ln
                pu, pv, ps, prev_in = u, v, sc, inside
                continue
            seen = inside and a0 * q0 + a1 * q1 + a2 * q2 + a3 >= 0.0
            if seen:
                d = maps[c, int(v + 0.5), int(u + 0.5)]
                if d == 0.0:
                    sc = 1.0
                elif d < cap:
                    sc = math.exp(-d * d * inv2s2)
            if inside and prev_in:
                ln = math.hypot(u - pu, v - pv)
                full += ln
                if seen and prev_seen:
                    sup += 0.5 * ln * (sc + ps)
                    tot += ln
            pu, pv, ps, prev_in, prev_seen = u, v, sc, inside, seen
        if occluded and not tot >= floor * full:
            sup = 0.0
            tot = 0.0
        out[p, c, 0] = sup
        out[p, c, 1] = tot


@numba.njit(cache=True, nogil=True, parallel=True)
def _scores(R: np.ndarray, t: np.ndarray, pts: np.ndarray, T_cam_ref: np.ndarray,
            Ks: np.ndarray, ds: np.ndarray, general_model: np.ndarray, maps: np.ndarray,
            sizes: np.ndarray, sigma: float, cap: float, plane: np.ndarray, occluded: bool,
            floor: float) -> np.ndarray:
    """Per particle and camera (P, C, 2): the supported length ``sum l s`` and the
    projected length ``sum l`` (px) of the arc inside the image, by the trapezoid rule
    over the chords between consecutive arc points (``s`` a point's score). Particles
    ``R`` (P, 3, 3), ``t`` (P, 3) are ``T_ref_N``; ``pts`` (K, 3) arc points in N;
    ``ds`` (C, 14) distortion vectors, ``general_model`` (C,) whether a camera's rational
    or thin-prism terms are used; ``maps`` (C, H, W) distance maps (px), each camera's
    valid part ``sizes`` (C, 2) = (W, H). A chord counts only when both its ends are in
    the image.

    ``occluded``: a tissue plane hides points ``x`` (reference frame) with
    ``plane[:3] . x + plane[3] < 0`` (the plane already shifted by the visibility
    margin); a chord then counts only when both its ends are also visible. A view whose
    visible length is below ``floor`` times its length in the image (the plane ignored)
    scores (0, 0): a sliver of arc that happens to lie on a feature is no evidence."""
    out = np.zeros((R.shape[0], Ks.shape[0], 2))
    inv2s2 = 0.5 / (sigma * sigma)
    for p in numba.prange(R.shape[0]):
        _score_one(p, out, R, t, pts, T_cam_ref, Ks, ds, general_model, maps, sizes, inv2s2,
                   cap, plane, occluded, floor)
    return out


@numba.njit(cache=True, nogil=True)
def _scores_serial(R: np.ndarray, t: np.ndarray, pts: np.ndarray, T_cam_ref: np.ndarray,
                   Ks: np.ndarray, ds: np.ndarray, general_model: np.ndarray, maps: np.ndarray,
                   sizes: np.ndarray, sigma: float, cap: float, plane: np.ndarray,
                   occluded: bool, floor: float) -> np.ndarray:
    """:func:`_scores` on the calling thread, for a few poses: starting the thread team
    costs more than it saves there, and on a busy machine it waits for a free core."""
    out = np.zeros((R.shape[0], Ks.shape[0], 2))
    inv2s2 = 0.5 / (sigma * sigma)
    for p in range(R.shape[0]):
        _score_one(p, out, R, t, pts, T_cam_ref, Ks, ds, general_model, maps, sizes, inv2s2,
                   cap, plane, occluded, floor)
    return out


#: Fewer poses than this are scored on the calling thread (:func:`_scores_serial`).
_PARALLEL_MIN = 64


# -- the filter ---------------------------------------------------------------------------

class NeedleFilter:
    """A particle filter over ``T_ref_N`` seen by one or more cameras of a rig.

    ``cameras`` share the reference frame (``CameraModel.T_ref_cam``); images passed to
    :meth:`initialize` and :meth:`update` are distance maps from :func:`feature_distance`,
    one per camera in the same order. ``occluder``: the tissue's surface when the needle
    may be in it (:meth:`set_occluder`).
    """

    def __init__(self, needle: Needle, cameras: Sequence[CameraModel],
                 settings: FilterSettings | None = None, *,
                 occluder: TissuePlane | None = None) -> None:
        if not cameras:
            raise NeedleError("the needle filter needs at least one camera")
        for cam in cameras:
            if cam.dist.size == 14 and np.any(cam.dist[12:] != 0):
                raise NeedleError(f"camera {cam.name!r}: the tilted sensor model is not "
                                  "supported by the needle filter")
        self.needle, self.cameras = needle, tuple(cameras)
        self.s = settings or FilterSettings()
        self.rng = np.random.default_rng(self.s.seed)
        self.points = np.ascontiguousarray(needle.points(self.s.arc_points))
        self.T_cam_ref = np.stack([c.T_cam_ref for c in self.cameras])
        self.Ks = np.stack([c.K for c in self.cameras])
        ds = np.zeros((len(self.cameras), 14))
        for i, c in enumerate(self.cameras):
            ds[i, :c.dist.size] = c.dist
        self.ds = ds
        # rational or thin-prism terms in use (else the kernel skips them: same values)
        self.general_model = np.array([bool(np.any(d[5:12] != 0)) for d in ds])
        self.sizes = np.array([c.size for c in self.cameras], dtype=np.int64)
        # the half turn that maps the arc onto itself (base <-> tip), in frame N
        b = needle.arc / 2
        axis = np.array([math.cos(b), math.sin(b), 0.0])
        self.flip = 2.0 * np.outer(axis, axis) - np.eye(3)
        self.R = np.empty((0, 3, 3))
        self.t = np.empty((0, 3))
        self.w = np.empty(0)
        self.last: NeedleEstimate | None = None
        self.occluder: TissuePlane | None = None
        self._plane = np.zeros(4)
        self.set_occluder(occluder)

    def set_occluder(self, plane: TissuePlane | None) -> None:
        """Score the particles with ``plane`` hiding what lies under it (``None``: nothing
        hidden) from the next update on. A point is hidden unless its centreline stands
        a wire radius above the plane (:class:`.needle_refine.TissuePlane`); hidden
        chords are neither support nor missing wire, and a view that shows less than
        :attr:`FilterSettings.min_visible` of a particle's arc scores 0."""
        if plane is not None:
            if not isinstance(plane, TissuePlane):
                raise NeedleError(f"occluder must be a TissuePlane or None, got "
                                  f"{type(plane).__name__}")
            plane.check_cameras(self.cameras)
            # n . x + c >= 0 <=> x stands the wire radius above the surface or more
            self._plane = np.append(plane.normal, -float(plane.normal @ plane.point)
                                    - 0.5 * self.needle.wire_diameter)
        self.occluder = plane

    # -- maps --------------------------------------------------------------------------
    def _stack(self, maps: Sequence[np.ndarray]) -> np.ndarray:
        if len(maps) != len(self.cameras):
            raise NeedleError(f"expected {len(self.cameras)} feature maps (one per camera), "
                              f"got {len(maps)}")
        H = max(c.height for c in self.cameras)
        W = max(c.width for c in self.cameras)
        out = np.full((len(maps), H, W), np.float32(1e6), np.float32)
        for i, (m, cam) in enumerate(zip(maps, self.cameras, strict=True)):
            m = np.asarray(m, dtype=np.float32)
            if m.shape != (cam.height, cam.width):
                raise NeedleError(f"camera {cam.name!r}: feature map is {m.shape}, the camera "
                                  f"is {cam.height} x {cam.width}")
            out[i, :cam.height, :cam.width] = m
        return out

    def scores(self, maps: Sequence[np.ndarray], R: np.ndarray | None = None,
               t: np.ndarray | None = None) -> np.ndarray:
        """The match (P, C) of the particles (or of poses ``R`` (P, 3, 3), ``t`` (P, 3))
        with the images: :meth:`_match` normalised by the best of them."""
        R = self.R if R is None else np.ascontiguousarray(R, dtype=float)
        t = self.t if t is None else np.ascontiguousarray(t, dtype=float)
        raw = self._raw(self._stack(maps), R, t)
        return self._match(raw, np.maximum(raw[:, :, 0].max(axis=0), 1.0))

    def _raw(self, stacked: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
        kernel = _scores if R.shape[0] >= _PARALLEL_MIN else _scores_serial
        return kernel(R, t, self.points, self.T_cam_ref, self.Ks, self.ds, self.general_model,
                      stacked, self.sizes, self.s.sigma_px, self.s.cap_px, self._plane,
                      self.occluder is not None, self.s.min_visible)

    @staticmethod
    def _match(raw: np.ndarray, norm: np.ndarray) -> np.ndarray:
        """``supported / sqrt(projected * norm)`` per pose and camera: the normalised
        cross-correlation of a thin virtual needle with the feature image, computed on
        the projected arc. A pose whose arc lies on features only in part scores low
        (``supported < projected``), and so does one that covers only part of what the
        best covers (a smaller or farther needle lying along a piece of the true one:
        ``projected < norm``). ``norm`` (C,) is the best supported length of the swarm."""
        return raw[:, :, 0] / np.sqrt(np.maximum(raw[:, :, 1], 1e-9) * norm)

    # -- initialisation -----------------------------------------------------------------
    def initialize(self, maps: Sequence[np.ndarray], depth_range: tuple[float, float],
                   camera: int = 0) -> NeedleEstimate:
        """Global localisation on the first images: particles with one arc point on a
        feature pixel of camera ``camera`` at a depth in ``depth_range`` (m, along that
        camera's viewing ray), random orientations, then :attr:`FilterSettings.anneal_steps`
        updates on the same images with the motion noise shrinking from
        ``anneal_start`` times its value to once."""
        s = self.s
        lo, hi = depth_range
        if not 0 < lo < hi:
            raise NeedleError(f"depth range must satisfy 0 < near < far, got {depth_range}")
        cam = self.cameras[camera]
        m = np.asarray(maps[camera])
        vs, us = np.nonzero(m[:cam.height, :cam.width] < 0.5)
        if us.size == 0:
            raise NeedleError(f"camera {cam.name!r} shows no thin feature: nothing to "
                              "localise the needle on")
        P = s.particles
        pick = self.rng.integers(0, us.size, P)
        uv = np.stack([us[pick], vs[pick]], axis=1).astype(float)
        ray = cam.backproject(uv)                         # unit-z rays in the camera frame
        depth = self.rng.uniform(lo, hi, P)
        p_cam = ray * depth[:, None]
        R_cam = Rotation.random(P, random_state=self.rng).as_matrix()
        phi = self.rng.uniform(0.0, self.needle.arc, P)
        on_arc = self.needle.point(phi)                    # the point put on the pixel
        t_cam = p_cam - np.einsum("pij,pj->pi", R_cam, on_arc)
        T_ref_cam = cam.T_ref_cam
        self.R = np.ascontiguousarray(np.einsum("ij,pjk->pik", T_ref_cam[:3, :3], R_cam))
        self.t = np.ascontiguousarray(t_cam @ T_ref_cam[:3, :3].T + T_ref_cam[:3, 3])
        self.w = np.full(P, 1.0 / P)
        self.last = None
        est = self.update(maps)
        n = s.anneal_steps
        for k in range(n):
            f = s.anneal_start ** (1.0 - (k + 1) / n) if n else 1.0
            self.predict(scale=f)
            est = self.update(maps)
        return est

    # -- one step -----------------------------------------------------------------------
    def predict(self, delta: np.ndarray | None = None, scale: float = 1.0) -> None:
        """Motion update. ``delta``: the gripper's incremental motion in the reference
        frame (``T_ref_T(now) @ inv(T_ref_T(before))``) while it holds the needle: every
        particle moves with it, then the grasped noise is added; ``None``: free needle,
        Brownian motion. ``scale`` multiplies the noise (annealing)."""
        s = self.s
        P = self.R.shape[0]
        if P == 0:
            raise NeedleError("the needle filter is not initialised")
        if delta is not None:
            D = np.asarray(delta, dtype=float)
            if D.shape != (4, 4) or not np.all(np.isfinite(D)):
                raise NeedleError("gripper motion must be a finite 4x4 transform")
            self.R = np.ascontiguousarray(np.einsum("ij,pjk->pik", D[:3, :3], self.R))
            self.t = np.ascontiguousarray(self.t @ D[:3, :3].T + D[:3, 3])
            sp, sr = s.grasped_position_noise, s.grasped_rotation_noise
        else:
            sp, sr = s.position_noise, s.rotation_noise
        dR = self.rng.normal(0.0, sr * scale, (P, 3))
        dt = self.rng.normal(0.0, sp * scale, (P, 3))
        # rotate about the arc's middle, not N's origin (the centre, off the wire): a
        # rotation about the centre would swing the whole wire sideways
        mid = self.needle.point(self.needle.arc / 2)
        c = np.einsum("pij,j->pi", self.R, mid)
        self.R = np.ascontiguousarray(Rotation.from_rotvec(dR).as_matrix() @ self.R)
        self.t += dt + c - np.einsum("pij,j->pi", self.R, mid)

    def update(self, maps: Sequence[np.ndarray]) -> NeedleEstimate:
        """Measurement update on the current images, then resampling. Returns the
        estimate (also kept as :attr:`last`)."""
        s = self.s
        if self.R.shape[0] == 0:
            raise NeedleError("the needle filter is not initialised")
        stacked = self._stack(maps)
        raw = self._raw(stacked, self.R, self.t)
        norm = np.maximum(raw[:, :, 0].max(axis=0), 1.0)
        total = self._match(raw, norm).sum(axis=1)
        logw = np.log(np.maximum(self.w, 1e-300)) + s.gain * total
        logw -= logw.max()
        w = np.exp(logw)
        w /= w.sum()
        est = self._estimate(w, stacked, norm)
        self._resample(w)
        self.last = est
        return est

    def _resample(self, w: np.ndarray) -> None:
        """Low-variance (systematic) resampling: one random offset, P equal steps."""
        P = w.size
        u = (self.rng.random() + np.arange(P)) / P
        idx = np.minimum(np.searchsorted(np.cumsum(w), u), P - 1)
        self.R = np.ascontiguousarray(self.R[idx])
        self.t = np.ascontiguousarray(self.t[idx])
        self.w = np.full(P, 1.0 / P)

    def _estimate(self, w: np.ndarray, stacked: np.ndarray, norm: np.ndarray
                  ) -> NeedleEstimate:
        s = self.s
        # the reference orientation: the previous estimate's, else the best particle's
        ref = self.last.pose[:3, :3] if self.last is not None else self.R[int(np.argmax(w))]
        # bring each particle to the symmetric twin nearer the reference (same outline):
        # trace(ref^T R) grows as R nears ref
        Rf = self.R @ self.flip
        near = np.einsum("ij,pij->p", ref, self.R)
        near_f = np.einsum("ij,pij->p", ref, Rf)
        use_f = near_f > near
        Rc = np.where(use_f[:, None, None], Rf, self.R)
        # the flip is a half turn about an axis through N's origin (the arc's centre):
        # both twins share the translation
        # the chordal mean: the weighted sum of the matrices, projected onto SO(3)
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = np.einsum("p,pij->ij", w, Rc), w @ self.t
        T = nearest_rigid(T)
        Rm, tm = T[:3, :3], T[:3, 3]
        pos = float(np.sqrt(w @ np.sum((self.t - tm) ** 2, axis=1)))
        cos_a = np.clip((np.einsum("ij,pij->p", Rm, Rc) - 1.0) / 2.0, -1.0, 1.0)
        ang = float(np.sqrt(w @ np.arccos(cos_a) ** 2))
        T_alt = T.copy()
        T_alt[:3, :3] = Rm @ self.flip
        raw = self._raw(stacked, T[None, :3, :3].copy(), T[None, :3, 3].copy())
        score = float(np.mean(raw[0, :, 0] / np.maximum(raw[0, :, 1], 1e-9)))
        match = float(np.mean(self._match(raw, norm)))
        conv = (pos <= s.converged_position and ang <= s.converged_angle
                and score >= s.converged_score and match >= s.converged_score)
        k = int(np.argmax(w))
        best = np.eye(4)
        best[:3, :3], best[:3, 3] = self.R[k], self.t[k]
        return NeedleEstimate(T, T_alt, pos, ang, score, match, float(1.0 / np.sum(w * w)),
                              conv, best)


# -- the tracker: filter, then refinement -------------------------------------------------

@dataclass(frozen=True)
class TrackSettings:
    """What the tracker asks of a pose before a step may move on it: the refined fit
    within :class:`.needle_refine.RefineSettings` bounds, its one-sigma uncertainty
    under ``max_sigma_position`` (m) and ``max_sigma_angle`` (rad), and the filter's
    estimate on the wire (``min_score``). ``inject``: the share of particles reset to the
    refined pose each update (with the motion noise), which keeps the swarm on the
    precise answer; ``swage_min``: the ridge difference (DN) that decides base from tip;
    ``require_swage``: without that decision the track has not converged (a drive planned
    on the twin would push the swage first); off only for a needle without a thread. A
    continuing track (updates after a converged one, on the same twin) carries its
    decision while no update shows the thread decisively at the other end; one that
    does puts the track in doubt until fresh evidence decides again. Twins that both
    read the thread past their own base cannot both be right (their bases lie at the
    wire's opposite ends): one is slid, its base back inside the wire and its tip out
    on the thread. Where the two readings are within ``swage_contest`` times each other,
    the evidence does not decide and the better crest fit (lower RMS) does; the slid
    twin's arc follows the thread, which leaves the circle. For the same reason a carried
    decision yields only to ``swage_contest`` times the evidence it was made on.
    ``swage_cone_out`` (rad): how far out of the needle's plane the thread is looked for
    as it leaves the swage (in the plane 0.15 rad): a needle that does not lie flat on
    the tissue (resting on its ends, tilted up to 30 deg about its chord) has its limp
    thread lying on the surface, out of its plane by the tilt; looked for within 0.15
    rad, no thread was found at tilts of 12 deg or more and such pick-ups were refused
    as not told apart.

    The motion prior: a needle whose motion is known (held in closed jaws, or standing in
    tissue) is where the last refined pose, moved by that motion, puts it, give or take
    ``slide_drift`` along its arc, ``tilt_drift`` about the other axes (rad) and
    ``position_drift`` (m) per update (the jaws' hold, the tissue's give and the arm's
    kinematic error between two poses). The last update's covariance, so widened, is
    the next update's prior (:class:`.needle_refine.PosePrior`): it holds what the
    jaws or the tissue hide and what a short baseline barely measures. An arm whose
    kinematics are off moves the needle other than it reports, more the more it moves:
    ``turn_drift`` (m per rad the motion turns: the arm's error at the needle swung
    round) and ``travel_drift`` (m per m the needle's centre travels: the arm's rotation
    error) widen the position by the motion's size (0 for exact kinematics, the
    default). Where the images
    alone put the needle more than ``prior_gate`` (squared Mahalanobis distance, their
    covariance and the prior's summed) from it, the motion was not what was assumed (a
    slip): the prior is dropped and the images alone decide. A motion under test (the
    hold check) carries only the slide.
    """

    max_sigma_position: float = 0.0003
    max_sigma_angle: float = math.radians(1.5)
    min_score: float = 0.5
    inject: float = 0.2
    swage_min: float = 8.0
    swage_contest: float = 1.5
    swage_cone_out: float = 0.6
    require_swage: bool = True      # a threaded needle: base and tip must be told apart
    slide_drift: float = math.radians(1.0)
    tilt_drift: float = math.radians(0.5)
    position_drift: float = 0.0001
    prior_gate: float = 16.0
    turn_drift: float = 0.0
    travel_drift: float = 0.0

    def __post_init__(self) -> None:
        if not self.swage_contest >= 1.0:
            raise NeedleError(f"swage_contest must be >= 1 (a ratio of two twins' thread "
                              f"evidence), got {self.swage_contest}")
        for name in ("turn_drift", "travel_drift"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise NeedleError(f"{name} must be finite and >= 0, got {v}")


@dataclass(frozen=True)
class NeedleTrack:
    """One tracking update's answer.

    ``pose``: ``T_ref_N``, the refined pose when the refinement succeeded, else the
    filter's estimate; ``filter``: the filter's estimate; ``refined``: the refinement
    (``None`` when it was not run); ``swage``: the base/tip evidence
    (:func:`.needle_refine.swage_evidence` at ``pose``, positive: base as reported);
    ``converged``: only then may a step move on ``pose``; ``reason``: why not, when not.
    ``held_reason``: the same judgement for a needle whose slide along its own circle the
    closed jaws fix (the plane's orientation, ``Refined.sigma_tilt``, judged in place of
    the largest axis): empty when a step that takes the slide from the grip may move on
    the circle (centre and plane) of ``pose``. ``short``: the refinement's fit matched
    what it found (its RMS within bounds) but found too little of the arc: a view that
    hides the needle, not one that contradicts the pose.
    """

    pose: np.ndarray
    filter: NeedleEstimate
    refined: Refined | None
    swage: float
    converged: bool
    reason: str
    held_reason: str = ""
    short: bool = False


class NeedleTracker:
    """The needle tracker of seed 002 §III.B with a sub-pixel finish: the particle filter
    (:class:`NeedleFilter`) finds and follows the needle robustly; each update, its
    estimate is refined on the wire's centreline in every view (:class:`PoseRefiner`);
    the suture thread at the swage tells base from tip.

    Images go in as :class:`NeedleFeatures` (:func:`feature_maps`), one per camera.
    Once the needle is in tissue, :meth:`set_occluder` gives the tissue's surface, so
    that the part under it is not taken for missing wire.
    """

    def __init__(self, needle: Needle, cameras: Sequence[CameraModel],
                 filter_settings: FilterSettings | None = None,
                 refine_settings: RefineSettings | None = None,
                 settings: TrackSettings | None = None) -> None:
        self.filter = NeedleFilter(needle, cameras, filter_settings)
        self.refiner = PoseRefiner(needle, cameras, refine_settings)
        self.s = settings or TrackSettings()
        self.needle, self.cameras = needle, tuple(cameras)
        self.last: NeedleTrack | None = None
        # the base/tip decision carried along a continuing track: the last pose moved by
        # the motion since (``_prior``), and whether its base and tip were decided
        self._prior: np.ndarray | None = None
        self._sided = False
        # the strongest thread evidence (DN) the carried decision has had: a rigid needle
        # cannot turn end for end, so only as strong a sight of the thread at the other
        # end overturns it
        self._side_evidence = 0.0
        # the jaws hold the needle and its sides are decided: no twin contest (fix_side)
        self._side_fixed = False
        # what is known of the pose with its covariance (local parameters): the last
        # refined pose, moved and widened by each known motion since; it outlives an
        # update that fitted nothing (the jaws and the tissue hid too much), which
        # leaves the belief as it was. None: a motion was not known (Brownian). And
        # whether the next update may take it whole or only its slide (a motion under
        # test)
        self._belief: tuple[np.ndarray, np.ndarray] | None = None
        self._prior_full = False
        # whether the last motion is one a check tests (untrusted and not the identity):
        # an update that fits nothing after it leaves nothing known
        self._motion_tested = False
        self.tools: tuple[ToolCylinder, ...] = ()
        # per camera, the pixels the refinement neither searches nor reads an end on:
        # the surface's edge band and what the features ignore (``blind``, their union)
        self._edge: list[np.ndarray] | None = None
        self._ignored: list[np.ndarray] | None = None
        self.blind: list[np.ndarray] | None = None

    def set_surface_outline(self, outline: np.ndarray | None) -> None:
        """The tissue surface's corners in order (k, 3, reference frame, m; ``None``:
        not known): the refinement neither looks for the wire nor reads an end in the
        band along the surface's edge in each view (:meth:`.PoseRefiner.edge_bands`),
        where the backdrop steps from tissue to what lies beyond and the wire fades."""
        self._edge = None if outline is None else self.refiner.edge_bands(outline)
        self._blind()

    def set_ignored(self, masks: Sequence[np.ndarray | None] | None) -> None:
        """Per camera, the pixels the features ignore (bool, image-sized, or ``None``;
        e.g. the incision line, :func:`feature_maps`' ``ignore``): the wire there is
        not missing but unseen, and an end read next to them may be where the wire
        enters them (seed 132: the tip over the incision read 6-7 px short and slid
        the hand-off's fit 7 deg along the arc). Neither searched nor read as an end."""
        self._ignored = None if masks is None else [
            np.zeros((cam.height, cam.width), dtype=bool) if m is None else np.asarray(m)
            for m, cam in zip(checked_masks(masks, self.cameras, "ignore"), self.cameras,
                              strict=True)]
        self._blind()

    def _blind(self) -> None:
        parts = [p for p in (self._edge, self._ignored) if p is not None]
        self.blind = (None if not parts else
                      [np.logical_or.reduce(ms) for ms in zip(*parts, strict=True)])

    def set_tools(self, tools: Sequence[ToolCylinder]) -> None:
        """The instruments' parts in view now (jaws, shafts; reference frame): the
        refinement neither looks for nor misses the wire behind them, from the next
        update on. Give them anew whenever a gripper moved."""
        self.tools = checked_tools(tools)

    @property
    def occluder(self) -> TissuePlane | None:
        """The tissue plane in use (``None``: nothing hides the needle)."""
        return self.filter.occluder

    def fix_side(self, fixed: bool) -> None:
        """While ``fixed``, a track whose base and tip are decided keeps them without the
        twin contest (a refit of the other twin, slid both ways: three times an update's
        fits when the jaws hide the thread) and without reading the thread's evidence
        (``NeedleTrack.swage`` 0): for a needle held in closed jaws, which cannot turn it
        end for end, so the contest could only be the tracker's own error (a servo's jump
        guard catches a flip it would make). A track not yet decided is still
        contested."""
        self._side_fixed = bool(fixed)

    def set_occluder(self, plane: TissuePlane | None) -> None:
        """The tissue's surface (reference frame) hides the part of the needle under it,
        from the next update (or initialisation) on, in the filter's score and the
        refinement; ``None`` when the needle is out of the tissue again. Refuses a plane
        that a camera is under."""
        self.filter.set_occluder(plane)

    def initialize(self, features: Sequence[NeedleFeatures],
                   depth_range: tuple[float, float]) -> NeedleTrack:
        """Global localisation (:meth:`NeedleFilter.initialize`), then the finish, which
        here also tries the swarm's mode and the circle's mirror tilt of each start
        (:func:`mirror_tilt`): a swarm that found both tilts of the outline averages to
        neither, and a short stereo baseline barely separates them."""
        self.last = None
        self._prior = None
        self._belief = None
        self._sided = False
        est = self.filter.initialize([f.distance for f in features], depth_range)
        starts = [est.pose] + ([est.best] if est.best is not None else [])
        ref = self.cameras[0].T_ref_cam[:3, 3]
        starts += [mirror_tilt(T, ref) for T in starts]
        # and each slid along its own arc: the crest cannot see a slide, and a start slid
        # toward the thread can lock onto where the thread leaves the tangent as if it
        # were the end; the right slide fits the crest best (the thread bends away)
        starts += [T @ S for T in starts for S in _SLIDES]
        return self._finish(features, est, starts)

    def predict(self, delta: np.ndarray | None = None, *, trusted: bool = True,
                kinematic: bool = True, split: bool = False) -> None:
        """Motion update: :meth:`NeedleFilter.predict`; the last refined pose moves with
        the gripper too (it is the refinement's first start next update). ``delta``
        known (a held needle's gripper motion, or the identity for a needle that stays):
        that pose and its covariance, widened by the drift, are the next update's prior
        (:class:`TrackSettings`); ``trusted=False``: the motion is what a check tests
        (did the needle follow the jaws?), or the jaws just closed on the needle and may
        have shifted it: only the slide is carried. ``kinematic=False``: ``delta`` is not
        an arm's reported motion but the needle's own, predicted from what was seen (a
        servo's model of the arm's error): ``turn_drift`` and ``travel_drift`` do not
        apply, and the slide and tilt drift by the motion's share of a half turn (a servo
        looks many times along what open-loop moves in one). ``split``: an arm's reported
        motion (the kinematic drifts apply) that is one of many small ones a tracking task
        looks at frame by frame, so the slide and tilt drift by its share as for
        ``kinematic=False``."""
        self.filter.predict(delta)
        self._prior_full = trusted
        still = delta is not None and np.allclose(delta, np.eye(4), rtol=0.0, atol=1e-12)
        self._motion_tested = not trusted and delta is not None and not still
        if self.last is None:
            return
        T = self.last.pose
        self._prior = T if delta is None else np.asarray(delta, dtype=float) @ T
        if delta is None or self._belief is None:
            self._belief = None
            return
        s = self.s
        # local parameters are right-multiplied (frame N): a motion applied on the
        # left leaves their covariance as it was
        # the slide is the wire slipping in the jaws (or the tissue giving along the
        # arc): it takes a motion, or the jaws closing (an untrusted look). A trusted
        # look with nothing moved adds none, where the views do not see the ends
        # (the jaws hide one) would otherwise let it grow by one drift per look until
        # the track counts as lost while the pose is as good as before
        slide = s.slide_drift if not trusted or not still else 0.0
        tilt = s.tilt_drift
        T_b, cov = self._belief
        position = s.position_drift
        D = np.asarray(delta, dtype=float)
        if kinematic and (s.turn_drift or s.travel_drift):
            turn = rotation_angle(D[:3, :3])
            travel = float(np.linalg.norm(D[:3, :3] @ T_b[:3, 3] + D[:3, 3] - T_b[:3, 3]))
            position = math.hypot(position, s.turn_drift * turn, s.travel_drift * travel)
        if not kinematic or split:
            # a servo splits one motion into many small ones, each looked at: the wire
            # slips in the jaws (and tilts in them) as much over the whole turn as over
            # one open-loop motion, so each share adds its share of the variance (a
            # drift per look took the slide past what a step may move on after a
            # servoed drive: 3.5 deg at the regrasp, against 1.1 open-loop)
            share = math.sqrt(min(1.0, rotation_angle(D[:3, :3]) / math.pi))
            slide, tilt = slide * share, tilt * share
        drift = np.array([tilt, tilt, slide] + 3 * [position])
        self._belief = (D @ T_b, cov + np.diag(drift ** 2))

    def update(self, features: Sequence[NeedleFeatures]) -> NeedleTrack:
        """Measurement update on the current images, then the finish, started from the
        last refined pose (moved) and from the filter's estimate."""
        est = self.filter.update([f.distance for f in features])
        last = self.last
        # what is known of the pose, moved with the gripper: the belief, else the last
        # pose when it was a refined one
        moved = (self._prior is not None and last is not None and last.refined is not None
                 and last.refined.ok)
        carried = ([self._belief[0]] if self._belief is not None
                   else [self._prior] if moved else [])
        return self._finish(features, est, carried + [est.pose], narrow_first=bool(carried))

    def _finish(self, features: Sequence[NeedleFeatures], est: NeedleEstimate,
                starts: list[np.ndarray], narrow_first: bool = False) -> NeedleTrack:
        s = self.s
        ridges = [f.ridge for f in features]
        ref = self._best_fit(features, starts, first_good=len(starts) <= 2,
                             narrow_first=narrow_first)
        if ref.ok and not self._determined(ref) and self._belief is None:
            # the crest fits but no end was read, and nothing known holds the slide:
            # slid along its own arc, the fit may bring an end into the end search
            again = self._best_fit(features, [ref.pose @ S for S in _SLIDES])
            if self._determined(again):
                ref = again
        pose = ref.pose if ref.ok else est.pose
        # a continuing track keeps the base/tip decision it made on decisive evidence:
        # the thread hides behind the jaws or the tissue, or lies edge-on, for updates
        # on end, while the filter's swarm and the refinement stay on the same twin
        # (the other is a half turn away, and each update starts from the last pose)
        carried = (self._sided and self._prior is not None
                   and rotation_angle(self._prior[:3, :3].T @ pose[:3, :3]) < 0.5 * math.pi)
        # with the sides fixed (fix_side) a carried decision is not read again: the
        # thread's evidence would neither contest nor doubt it (0: no cue, unmeasured)
        swage = (0.0 if carried and self._side_fixed
                 else swage_evidence(self.needle, self.cameras, ridges, pose,
                                     cone_out=s.swage_cone_out, tools=self.tools))
        initial = self.last is None and self._prior is None     # initialize()'s finish
        if not (carried and self._side_fixed) and (
                (ref.ok and s.require_swage and (swage < s.swage_min or initial))
                or (not carried and swage < -s.swage_min)):
            # the thread does not confirm this twin, or the track starts afresh: the
            # other, fitted again (with its own tip as the end that holds the slide) and
            # from it slid both ways (the twin of a pose slid onto the thread is slid as
            # far the other way, its tip short of the true tip). The initialisation takes
            # the better of the two: the wrong twin's fit can itself slide its tip on
            # along the thread and its base back inside the wire, which beyond the base
            # then reads as thread (seed 17: +10 DN for it, +28 for the right one). A
            # carried decision yields only to decisive evidence for the other twin
            twin = pose.copy()
            twin[:3, :3] = pose[:3, :3] @ self.filter.flip
            twin_ref = ref
            if ref.ok:
                again = self._best_fit(features, [twin] + [twin @ S for S in _SLIDES])
                if again.ok:
                    twin_ref, twin = again, again.pose
            twin_swage = swage_evidence(self.needle, self.cameras, ridges, twin,
                                        cone_out=s.swage_cone_out, tools=self.tools)
            # a twin whose slide the views leave free (its tip hidden) can slide until
            # its base lies on the wire itself, which then reads as the thread: its
            # evidence overturns nothing carried
            # a carried decision yields to decisive evidence for the other twin, clearly
            # stronger (swage_contest times) than any it was carried on: with the thread
            # hidden behind the new jaws at a hand-off (seed 21), the wrong twin read
            # +15 DN where the track had read +25 on its own side before; on trial 20,
            # lifted in the jaws, the twin slid onto the thread read +9.5 DN after +9.1
            # on the right side at the first look
            if carried:
                take = (twin_swage > swage
                        and twin_swage >= max(s.swage_min,
                                              s.swage_contest * self._side_evidence)
                        and self._determined(twin_ref))
            elif contested(swage, twin_swage, s):
                # both read the thread alike (trial 20's half-circle needle, whose thread
                # reaches the pad's edge 4 mm on: +8.7 DN for the right pose, +9.3 for
                # the twin slid 14 deg onto the thread, at 0.07 and 0.11 px RMS)
                take = twin_ref.ok and twin_ref.rms_px < ref.rms_px
            else:
                take = twin_swage > swage
            if take:
                ref, pose, swage = twin_ref, twin, twin_swage
                carried = False
        if ref.ok:
            self._inject(pose)
        # the thread seen at the end the track took for the tip puts a carried decision
        # in doubt only as strongly as it was made (trial 21: -8 DN at the tip end while
        # the new jaws hid the swage, after +26 DN at the swage; the next update then
        # took the twin)
        doubted = carried and swage <= -max(s.swage_min, self._side_evidence)

        def why_not(angle: float, what: str) -> str:
            """Why a step may not move on the track, its orientation's sigma ``angle``
            (rad, ``what`` it measures) judged against the bound; empty when it may."""
            if est.score < s.min_score:
                return f"the filter's estimate is not on the wire (score {est.score:.2f})"
            if not ref.ok:
                return (f"the refined fit is poor (RMS {ref.rms_px:.2f} px, "
                        f"{100 * ref.support:.0f} % of the arc found)")
            if ref.sigma_position > s.max_sigma_position or angle > s.max_sigma_angle:
                return (f"the views leave the pose uncertain ({1e3 * ref.sigma_position:.2f}"
                        f" mm, {math.degrees(angle):.1f} deg{what})")
            if s.require_swage and doubted:
                return (f"the thread is at the end the track took for the tip (evidence "
                        f"{swage:.1f} DN): base and tip are in doubt")
            if s.require_swage and swage < s.swage_min and not carried:
                return (f"base and tip are not told apart (thread evidence {swage:.1f} DN, "
                        f"{s.swage_min:.1f} needed)")
            return ""

        reason = why_not(ref.sigma_angle, "")
        held_reason = reason and why_not(ref.sigma_tilt, " of the needle's plane")
        short = (not ref.ok and ref.rms_px <= self.refiner.s.max_rms_px
                 and est.score >= s.min_score)
        track = NeedleTrack(pose, est, ref, swage, not reason, reason, held_reason, short)
        if not reason:
            self._side_evidence = max(self._side_evidence, swage) if carried else swage
            self._sided = True
        elif s.require_swage and doubted:
            self._sided = False       # decide afresh on the next update's evidence
        self.last = track
        self._prior = None
        if ref.ok:
            # not for the twin taken without a fit of its own: the covariance is the
            # fit's, in the other twin's frame
            self._belief = (pose, ref.cov) if ref.cov is not None and ref.pose is pose \
                else None
        elif self._motion_tested:
            self._belief = None       # a motion under test that nothing confirmed
        # else: the update fitted nothing, and what was known stands; also where the
        # jaws just closed (an untrusted look with nothing moved): their hiding most of
        # the wire says nothing against it, and the slide was widened for the closing.
        # Dropped there, the pull's look had no slide to hold (trial 15: the tip hidden
        # in the jaws, the fit slid 15 deg along the thread and the track was lost)
        return track

    def _determined(self, r: Refined) -> bool:
        """Whether a refinement passed and its pose is within the uncertainty bounds."""
        s = self.s
        return (r.ok and r.sigma_position <= s.max_sigma_position
                and r.sigma_angle <= s.max_sigma_angle)

    def _best_fit(self, features: Sequence[NeedleFeatures], starts: Sequence[np.ndarray],
                  first_good: bool = False, narrow_first: bool = False) -> Refined:
        """The refinement from each start; the best: one that passes beats one that does
        not, a determined one (no end seen: the slide is free) one that is not, then the
        closer fit. ``first_good``: stop at the first start that fits well (tracking).
        ``narrow_first``: the first start is the last pose moved with the jaws, a few
        pixels off at most: it is refined first in the narrow window alone. The wide capture
        rounds reach whatever crosses the wire (a shaft, the incision, the pad's edge);
        from the true pose of trial 69's held needle they pulled the fit 13 deg off in
        tilt, at 0.21 px RMS, where the narrow window kept it within 1.4 deg at 0.12 px.
        A start that is not on the wire finds too little in the narrow window to pass,
        and the wide rounds follow."""
        s = self.s
        ref: Refined | None = None
        best: tuple[bool, bool, bool, float] | None = None
        prior = slide_only = None
        if self._belief is not None:
            T_b, cov = self._belief
            slide_only = PosePrior.slide(T_b, math.sqrt(cov[2, 2]))
            prior = PosePrior.from_cov(T_b, cov) if self._prior_full else slide_only

        def fit(T0: np.ndarray, p: PosePrior | None, narrow: bool = False) -> Refined:
            return self.refiner.refine(features, T0, occluder=self.occluder,
                                       tip_only=s.require_swage, tools=self.tools, prior=p,
                                       search_px=self.refiner.s.search_px[-1:] if narrow
                                       else None, blind=self.blind)

        tries = [(T0, False) for T0 in starts]
        if narrow_first and starts:
            tries.insert(0, (starts[0], True))
        for T0, narrow in tries:
            r = fit(T0, prior, narrow)
            consistent = True
            if prior is not None and self._prior_full and r.prior_distance2 > s.prior_gate:
                # the fit moved far from the prior: do the images alone contradict it
                # (a slip), beyond both their uncertainty and the prior's? Where they
                # leave a direction free (the slide with both ends hidden), they cannot
                # contradict it there, and the prior's fit stands
                assert self._belief is not None
                alone = fit(T0, None, narrow)
                if alone.ok and contradicts(prior, self._belief[1], alone, s.prior_gate):
                    # they decide, but a fit that agrees with the motion, from another
                    # start, goes first; the slide they do not see stays the prior's
                    r, consistent = alone, False
                    if not math.isfinite(alone.sigma_slide_seen) \
                            or alone.sigma_slide_seen > s.max_sigma_angle:
                        r = fit(T0, slide_only, narrow)
            if self._belief is not None and rotation_angle(
                    self._belief[0][:3, :3], r.pose[:3, :3]) >= 0.5 * math.pi:
                # the other twin of what the motion carried (a start from the filter's
                # swarm on it is refined without the prior, which cannot reach across
                # a half turn, and so reads as agreeing with it): base and tip are
                # decided on the thread's evidence (_finish), not by which fit the
                # images prefer (trial 178: the approach look's twin fit, its slide
                # undetermined, replaced the belief and the drive was tracked
                # end for end)
                consistent = False
            key = (r.ok, consistent, self._determined(r), -r.rms_px)
            if best is None or key > best:
                ref, best = r, key
            if first_good and consistent and r.ok \
                    and r.rms_px <= 0.5 * self.refiner.s.max_rms_px:
                break
        assert ref is not None
        return ref

    def _inject(self, pose: np.ndarray) -> None:
        """Reset a share of the particles to ``pose``, keeping the filter's twin
        reference on it (the next estimate is reported nearest the refined pose)."""
        f = self.filter
        P = f.R.shape[0]
        k = int(round(self.s.inject * P))
        if k == 0:
            return
        idx = f.rng.choice(P, k, replace=False)
        f.R[idx] = pose[:3, :3]
        f.t[idx] = pose[:3, 3]
        if f.last is not None:
            f.last = replace(f.last, pose=pose, pose_alt=pose @ _flip4(f.flip))


def contested(swage: float, twin_swage: float, s: TrackSettings) -> bool:
    """Whether two twins' thread evidence (DN) is not decisive: both read the thread
    past their own base (at least ``swage_min``), within ``swage_contest`` times each
    other."""
    lo, hi = sorted((swage, twin_swage))
    return lo >= s.swage_min and hi < s.swage_contest * lo


def contradicts(prior: PosePrior, prior_cov: np.ndarray, alone: Refined,
                 gate: float) -> bool:
    """Whether a fit of the images alone lies further than ``gate`` (squared
    Mahalanobis distance, the prior's covariance ``prior_cov`` and the fit's summed)
    from the prior: the innovation test of a Kalman filter's validation gate."""
    if alone.cov is None:
        return False
    e, J = prior.residual(alone.pose)
    S = J @ alone.cov @ J.T + prior_cov
    try:
        return float(e @ np.linalg.solve(S, e)) > gate
    except np.linalg.LinAlgError:
        return False


def arc_slide(deg: float) -> np.ndarray:
    """A turn of ``deg`` about frame N's z axis (the needle's axis through its centre):
    the arc slides along itself."""
    S = np.eye(4)
    S[:3, :3] = Rotation.from_euler("z", deg, degrees=True).as_matrix()
    return S


#: The slides tried at initialisation besides each start itself (seed 002's needle:
#: 8 deg is 1.8 mm of a 13 mm arc, about the end search's reach).
_SLIDES = tuple(arc_slide(d) for d in (-16.0, -8.0, 8.0, 16.0))


def _flip4(flip: np.ndarray) -> np.ndarray:
    F = np.eye(4)
    F[:3, :3] = flip
    return F


def mirror_tilt(T: np.ndarray, eye: np.ndarray) -> np.ndarray:
    """The other tilt of a circle's outline: the needle turned about its centre so its
    plane's normal is mirrored about the line of sight from ``eye`` (a camera centre,
    reference frame) to the centre. One view sees a circle's outline the same either way
    (the two-fold ambiguity of a circle's pose); the turn, by twice the angle between the
    normal and the line of sight about their common perpendicular, maps one onto the
    other and keeps the arc's points near their rays."""
    T = np.asarray(T, dtype=float)
    v = T[:3, 3] - np.asarray(eye, dtype=float)
    v /= np.linalg.norm(v)
    n = T[:3, 2]
    axis = np.cross(n, v)
    sn = float(np.linalg.norm(axis))
    if sn < 1e-9:
        return T.copy()       # face-on: both tilts are the same
    ang = math.atan2(sn, float(n @ v))
    # turning the normal toward the line of sight by twice their angle mirrors it
    turn = Rotation.from_rotvec(axis / sn * (2.0 * ang)).as_matrix()
    out = T.copy()
    out[:3, :3] = turn @ T[:3, :3]
    return out
