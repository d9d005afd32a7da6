"""Scene renderer: what the stereo camera and the endoscope see, with exact ground truth.

Model no more than a scene needs: each object (a marker field on a plane or a cylinder, a
rod) is ray-cast only inside its own projected bounding box; everything else is the
precomputed background. Per object and camera:

1. the undistorted viewing ray of every sub-pixel sample comes from a per-camera ray map
   (the camera model inverted once, exactly, at the pixel centres; sub-pixel rays are
   bilinear in that smooth map);
2. rays are intersected with the surface in the object's frame and, for fields, turned
   into flat-sheet coordinates;
3. the sheet texture is sampled bilinearly from a mip level whose texel is about one
   sample wide (square edges lie exactly on texel boundaries at every level, so bilinear
   sampling puts each edge where it is), then ``supersample``^2 samples are box-averaged
   into a pixel value and a coverage;
4. objects are composited far to near by mean depth (objects do not interpenetrate).

Illumination gradient, Gaussian blur, motion blur (sub-exposure poses averaged) and read +
shot noise follow. Noise comes from OpenCV's RNG seeded from (scene seed, frame, camera),
so the same scene, seed and frame give the same bytes. Everything before the noise is a
function of the poses and jaw gaps alone, so a renderer asked to (``keep_clean``) keeps
each camera's last few noise-free signals with their ground truth: a scene rendered again
unmoved (a procedure looking several times at a still needle) then costs only the noise.
It is off by default, where a render stands in for a camera's capture time (the daemon's
simulated cell, the render benchmark).

Ground truth per camera: each field's pose and the exact projection of every visible
chessboard corner (in the image, printed face toward the camera, not under a blot, not
hidden by a nearer object), with its obliquity.

Needle-driving objects (seed 002): tissue pads, needles and grippers. A pad is a plane
patch like a field's (a light level with a dark incision line). Needles (a torus segment
drawn as mitred chord pieces of the wire, with an optional suture thread drawn the same
way) and grippers (box jaws and a cylinder shaft, the jaw gap overridable per render) are
ray-cast piece by piece, each piece inside its own small box, into one sample-level
z-buffer per camera (``_object_layer``), in which the pads take part as occluders. A needle
lying on a pad, a needle between the jaws, or a needle half inside the tissue is thus
resolved per sample, before the box filter, rather than per object. The layer is then one
object to the far-to-near compositing, after every pad. Ground truth per camera and needle:
its pose, the projection of K arc points and whether each is visible.
"""

from __future__ import annotations

import copy
import math
import time
import weakref
from collections import OrderedDict
from collections.abc import Mapping
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from oralnav.control.geometry import transform_points
from oralnav.control.vision.camera import CameraModel
from oralnav.control.vision.markers import CylinderSurface, MarkerField, PlaneSurface
from oralnav.sim.errors import SimError
from oralnav.sim.world.scene import Gripper, Imaging, NeedleObject, Placement, Rod, Scene, TissuePad

#: Finest texture: pixels per chessboard square. Coarser mip levels halve it down to 4.
MAX_TEXELS_PER_SQUARE = 512
MIN_TEXELS_PER_SQUARE = 4

#: Arc points per needle in the ground truth (:class:`NeedleTruth`), base to tip.
NEEDLE_TRUTH_POINTS = 64
#: Bound on the sagitta of the needle's chord pieces: this fraction of the wire radius, and
#: this fraction of a pixel at the needle's nearest point (see ``_needle_pieces``).
SAGITTA_WIRE = 0.1
SAGITTA_PX = 0.05
#: Needle and gripper parts nearer than this to the camera plane (m) are not drawn.
NEAR = 1e-3


class RenderError(SimError, ValueError):
    """A scene cannot be rendered as asked (unknown placement, a points-only field...)."""


@dataclass
class FieldTruth:
    """Ground truth of one field in one camera.

    ``corner_ids`` (N,) are OpenCV chessboard corner ids, ``corners_px`` (N x 2) their exact
    pixel positions, ``obliquity`` (N,) the angle (rad) between the viewing ray and the
    printed face's normal at each corner.
    """

    T_cam_field: np.ndarray
    corner_ids: np.ndarray
    corners_px: np.ndarray
    obliquity: np.ndarray

    def to_json(self) -> dict:
        return {"T_cam_field": self.T_cam_field.tolist(),
                "corner_ids": self.corner_ids.tolist(),
                "corners_px": self.corners_px.tolist(),
                "obliquity_deg": np.degrees(self.obliquity).round(4).tolist()}


@dataclass
class NeedleTruth:
    """Ground truth of one needle in one camera.

    ``phi`` (K,) are the arc angles (rad, base 0 to tip ``arc``) of K points equally spaced
    along the needle's centreline (``Needle.points(K)``, frame N), ``points_px`` (K x 2)
    their exact projections through the camera model (distortion included; NaN behind the
    camera), ``visible`` (K,) whether each is seen: in the image, in front of the camera and
    not hidden by a nearer object (a pad, a gripper, another needle, a field or a rod; the
    needle's own wire does not hide its centreline).
    """

    T_cam_needle: np.ndarray
    phi: np.ndarray
    points_px: np.ndarray
    visible: np.ndarray

    @property
    def visible_fraction(self) -> float:
        """Share of the K arc points that are visible (0..1)."""
        return float(self.visible.mean()) if len(self.visible) else 0.0

    def to_json(self) -> dict:
        return {"T_cam_needle": self.T_cam_needle.tolist(),
                "phi_rad": self.phi.tolist(),
                "points_px": [[float(u), float(v)] if np.isfinite(u) and np.isfinite(v)
                              else None for u, v in self.points_px],
                "visible": [bool(b) for b in self.visible],
                "visible_fraction": round(self.visible_fraction, 6)}


@dataclass
class Frame:
    """One rendered frame: an image per camera, ground truth, and how long each took (s).

    ``truth`` holds the fields' truth per camera; ``needle_truth`` the needles' (per camera,
    every needle of the scene). ``T_ref_needle``, ``T_ref_pad`` and ``T_ref_tool`` are the
    poses the needles, pads and grippers were rendered at (reference frame), ``opening``
    the jaw gap (m) each gripper was rendered with.
    """

    images: dict[str, np.ndarray]
    T_ref_field: dict[str, np.ndarray]
    truth: dict[str, dict[str, FieldTruth]]
    frame: int
    seed: int
    render_s: dict[str, float] = field(default_factory=dict)
    needle_truth: dict[str, dict[str, NeedleTruth]] = field(default_factory=dict)
    T_ref_needle: dict[str, np.ndarray] = field(default_factory=dict)
    T_ref_pad: dict[str, np.ndarray] = field(default_factory=dict)
    T_ref_tool: dict[str, np.ndarray] = field(default_factory=dict)
    opening: dict[str, float] = field(default_factory=dict)

    def truth_json(self, reference: str, image_files: Mapping[str, str] | None = None) -> dict:
        """The ``truth.json`` document (see docs/formats.md). Scenes with needles, pads or
        grippers add ``needles``, ``pads``, ``grippers`` and each camera's ``needles``
        (docs/simulator.md)."""
        cams = {}
        for cam, fields in self.truth.items():
            entry: dict = {"size": [int(self.images[cam].shape[1]),
                                    int(self.images[cam].shape[0])]}
            if image_files and cam in image_files:
                entry["image"] = image_files[cam]
            entry["fields"] = {name: t.to_json() for name, t in fields.items()}
            if self.T_ref_needle:
                entry["needles"] = {name: t.to_json()
                                    for name, t in self.needle_truth.get(cam, {}).items()}
            cams[cam] = entry
        doc = {"units": {"length": "m", "pixel": "px, centre of top-left pixel at (0, 0)"},
               "reference": reference, "frame": self.frame, "seed": self.seed,
               "fields": {n: {"T_ref_field": T.tolist()} for n, T in self.T_ref_field.items()}}
        for key, poses, pose_key in (("needles", self.T_ref_needle, "T_ref_needle"),
                                     ("pads", self.T_ref_pad, "T_ref_pad"),
                                     ("grippers", self.T_ref_tool, "T_ref_tool")):
            if poses:
                doc[key] = {n: {pose_key: T.tolist()} for n, T in poses.items()}
        doc["cameras"] = cams
        return doc


@dataclass
class _Patch:
    x0: int
    y0: int
    value: np.ndarray      # premultiplied level (DN * coverage), h x w float32
    alpha: np.ndarray      # coverage 0..1, h x w float32
    depth: float           # metres along the optical axis, for ordering
    owner: int


@dataclass
class _Job:
    """Pieces of one object ray-cast in one pass: ``kind`` names the caster, ``boxes``
    (m x 4) are the pieces' pixel boxes, ``par`` the caster's parameters (those named in
    ``per_piece`` have one row per piece), and ``axis`` (m x k x 3, camera frame) points
    within ``margin`` (m) of which each piece lies (which pieces may reach under a pad)."""

    code: int
    kind: str
    boxes: np.ndarray
    par: dict
    axis: np.ndarray
    margin: float
    per_piece: tuple[str, ...] = ()
    material: int = -1     # index into the layer's materials; -1: the object's own (code)


def _batches(jobs: list[_Job]) -> list[_Job]:
    """Jobs as cast: many small pieces in one gathered pass (the Python overhead of one
    pass per piece would dominate), large or few pieces one by one (padding them all to
    the largest box would waste samples)."""
    out = []
    for job in jobs:
        b = job.boxes
        if len(b) <= 4 or ((b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])).max() > 4096:
            for k in range(len(b)):
                par = {n: (v[k:k + 1] if n in job.per_piece else v)
                       for n, v in job.par.items()}
                out.append(_Job(job.code, job.kind, b[k:k + 1], par, job.axis[k:k + 1],
                                job.margin, material=job.material))
        else:
            out.append(job)
    return out


@dataclass
class _Layer:
    """The needles' and grippers' sample-level z-buffer over one box of one camera.

    Sample (i, j) of the canvas sits at pixel ``(x0 - 0.5 + (j + 0.5) / s, y0 - 0.5 +
    (i + 0.5) / s)``. ``inv`` is 1 / depth (1/m, depth along the optical axis) of the
    nearest surface, 0 where there is none; ``own`` the code of the object it belongs to
    (0 none, then the needles and grippers: ``codes``). ``pads`` are the pads drawn in
    this view, which hide what lies under them.
    """

    x0: int
    y0: int
    s: int
    inv: np.ndarray
    own: np.ndarray
    codes: dict[str, int]
    patch: _Patch | None
    pads: list = field(default_factory=list)


#: Ray maps by camera model (identity; models are frozen): renderers of the same rig, such
#: as a new one per randomised trial, share the ~0.2 s inversion of a 640x480 model.
_RAY_MAPS: weakref.WeakKeyDictionary[CameraModel, np.ndarray] = weakref.WeakKeyDictionary()


class _CameraState:
    """Per-camera precomputation: the ray map, the illumination and the background."""

    def __init__(self, cam: CameraModel, imaging: Imaging) -> None:
        self.cam = cam
        w, h = cam.size
        u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
        rays = _RAY_MAPS.get(cam)
        if rays is None:
            if cam.has_distortion:
                rays = cam.ray_map()
                if np.isnan(rays).any():
                    bad = int(np.isnan(rays).any(axis=-1).sum())
                    raise RenderError(f"camera {cam.name!r}: the distortion model does not "
                                      f"invert at {bad} pixels; check its dist coefficients")
            else:
                K = cam.K
                rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]], axis=-1)
            rays = _RAY_MAPS[cam] = np.ascontiguousarray(rays, dtype=np.float32)
        self.rays = rays   # shared by every renderer of this camera model; never written
        gx, gy = imaging.illumination_gradient
        illum = 1.0 + gx * (u / w - 0.5) + gy * (v / h - 0.5)
        self.illumination = np.clip(illum, 0.0, None).astype(np.float32)
        self.background = (imaging.background * self.illumination).astype(np.float32)

    def sub_rays_xy(self, x0: int, y0: int, x1: int, y1: int, s: int
                    ) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`sub_rays` as two one-channel arrays (x, y), which OpenCV's arithmetic
        takes without copying."""
        if s == 1:
            return cv2.split(np.ascontiguousarray(self.rays[y0:y1, x0:x1]))
        h, w = self.rays.shape[:2]
        px0, py0, px1, py1 = max(x0 - 1, 0), max(y0 - 1, 0), min(x1 + 1, w), min(y1 + 1, h)
        size = ((px1 - px0) * s, (py1 - py0) * s)
        ox, oy = (x0 - px0) * s, (y0 - py0) * s
        return tuple(cv2.resize(c, size, interpolation=cv2.INTER_LINEAR)
                     [oy:oy + (y1 - y0) * s, ox:ox + (x1 - x0) * s]
                     for c in cv2.split(np.ascontiguousarray(self.rays[py0:py1, px0:px1])))

    def sub_rays(self, x0: int, y0: int, x1: int, y1: int, s: int) -> np.ndarray:
        """Normalised rays of the s x s samples of every pixel in [x0, x1) x [y0, y1).

        Sample i of pixel u sits at ``u + (i + 0.5) / s - 0.5``; resizing the 1-pixel-padded
        crop by s with bilinear interpolation lands exactly on those positions.
        """
        if s == 1:
            return self.rays[y0:y1, x0:x1]
        h, w = self.rays.shape[:2]
        px0, py0, px1, py1 = max(x0 - 1, 0), max(y0 - 1, 0), min(x1 + 1, w), min(y1 + 1, h)
        crop = self.rays[py0:py1, px0:px1]
        big = cv2.resize(crop, ((px1 - px0) * s, (py1 - py0) * s),
                         interpolation=cv2.INTER_LINEAR)
        ox, oy = (x0 - px0) * s, (y0 - py0) * s
        return big[oy:oy + (y1 - y0) * s, ox:ox + (x1 - x0) * s]


class _Texture:
    """Mip levels of one field's flat sheet; level k has 2**k texels per square."""

    def __init__(self, fld: MarkerField) -> None:
        self.field = fld
        levels: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        img = fld.board_image(MAX_TEXELS_PER_SQUARE)
        pps = MAX_TEXELS_PER_SQUARE
        while pps >= MIN_TEXELS_PER_SQUARE:
            levels[pps] = (img, np.full_like(img, 255))
            # Area-halving keeps square edges on texel boundaries (pps stays a power of 2).
            img = cv2.resize(img, (img.shape[1] // 2, img.shape[0] // 2),
                             interpolation=cv2.INTER_AREA)
            pps //= 2
        self.levels = levels

    def level_for(self, samples_per_square: float) -> int:
        """Finest level whose texel is not smaller than a sample."""
        pps = MIN_TEXELS_PER_SQUARE
        while pps * 2 <= min(samples_per_square, MAX_TEXELS_PER_SQUARE):
            pps *= 2
        return pps


def _pose_at(T: np.ndarray, v: np.ndarray, w: np.ndarray, tau: float) -> np.ndarray:
    """Pose ``tau`` seconds from ``T`` under constant velocity (reference frame)."""
    if tau == 0.0:
        return T
    out = T.copy()
    out[:3, :3] = Rotation.from_rotvec(w * tau).as_matrix() @ T[:3, :3]
    out[:3, 3] = T[:3, 3] + v * tau
    return out


def _ring(u: np.ndarray, radius: float) -> np.ndarray:
    """16 points (16, 3) on the circle of ``radius`` about the unit axis ``u`` through the
    origin: a cylinder's cross-section, for its bounding box."""
    e1 = np.cross(u, [1.0, 0.0, 0.0])
    if np.linalg.norm(e1) < 0.1:
        e1 = np.cross(u, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(u, e1)
    ang = np.linspace(0, 2 * np.pi, 16, endpoint=False)
    return radius * (np.cos(ang)[:, None] * e1 + np.sin(ang)[:, None] * e2)


class SceneRenderer:
    """Renders a :class:`~oralnav.sim.world.scene.Scene` into images with ground truth.

    The constructor only records the scene; per-camera ray maps and textures are built on
    first use and kept. With ``keep_clean`` > 0 so are that many recent noise-free renders
    per camera, keyed by every pose and jaw gap: a state rendered again gets only fresh
    noise, and the same bytes and truth as a full render.
    ``render`` is thread-safe to call from one worker thread at a time.
    """

    def __init__(self, scene: Scene, needle_points: int = NEEDLE_TRUTH_POINTS,
                 keep_clean: int = 0) -> None:
        self.scene = scene
        if keep_clean < 0:
            raise RenderError(f"keep_clean must be >= 0 renders, got {keep_clean}")
        self.keep_clean = int(keep_clean)
        self._cams: dict[str, _CameraState] = {}
        self._tex: dict[str, _Texture] = {}
        # per camera: state key -> (noise-free signal, field truth, needle truth)
        self._clean: dict[str, OrderedDict[bytes, tuple]] = {}
        for p in scene.placements:
            if not p.field.renderable:
                raise RenderError(
                    f"placement {p.name!r}: field {p.field.name!r} has a points surface, "
                    "which is known only at its corners and cannot be rendered")
        names = {p.name for p in scene.placements}
        for b in scene.blots:
            if b.placement not in names:
                raise RenderError(f"blot {b.name!r}: unknown placement {b.placement!r}")
        posed = [p.name for p in scene.placements] + [
            o.name for o in (*scene.needles, *scene.pads, *scene.grippers)]
        twice = sorted({n for n in posed if posed.count(n) > 1})
        if twice:
            raise RenderError(f"placements, needles, pads and grippers share one name space "
                              f"(render poses are keyed by name); repeated: {twice}")
        _check_objects(scene)
        if needle_points < 2:
            raise RenderError(f"needle_points must be >= 2, got {needle_points}")
        self.needle_points = int(needle_points)

    # -- cached state -----------------------------------------------------------------
    def _camera(self, name: str) -> _CameraState:
        st = self._cams.get(name)
        if st is None:
            st = self._cams[name] = _CameraState(self.scene.rig[name], self.scene.imaging)
        return st

    def _texture(self, fld: MarkerField) -> _Texture:
        tex = self._tex.get(fld.name)
        if tex is None:
            tex = self._tex[fld.name] = _Texture(fld)
        return tex

    def prepare(self) -> None:
        """Build every camera's ray map and every texture now (otherwise on first render)."""
        for name in self.scene.rig.names:
            self._camera(name)
        for p in self.scene.placements:
            self._texture(p.field)

    # -- public -----------------------------------------------------------------------
    def render(self, poses: Mapping[str, np.ndarray] | None = None, frame: int = 0,
               cameras: tuple[str, ...] | None = None,
               openings: Mapping[str, float] | None = None) -> Frame:
        """Render every camera (or ``cameras``) of the rig.

        ``poses`` overrides placements' ``T_ref_field``, needles' ``T_ref_needle``, pads'
        ``T_ref_pad`` and grippers' ``T_ref_tool`` by name (the simulated cell moves them
        this way); ``openings`` overrides grippers' jaw gap ``opening`` (m) by name (the
        cell opens and closes the jaws this way); ``frame`` selects the noise draw.
        """
        sc = self.scene
        poses = dict(poses or {})
        objects = sc.object_poses()
        unknown = set(poses) - {p.name for p in sc.placements} - set(objects)
        if unknown:
            raise RenderError(f"poses given for unknown placements or objects "
                              f"{sorted(unknown)}")
        openings = dict(openings or {})
        names_g = {g.name for g in sc.grippers}
        if set(openings) - names_g:
            raise RenderError(f"openings given for unknown grippers "
                              f"{sorted(set(openings) - names_g)}; the scene has "
                              f"{sorted(names_g)}")
        for n, o in openings.items():
            try:
                openings[n] = float(o)
            except (TypeError, ValueError):
                openings[n] = math.nan
            if not (math.isfinite(openings[n]) and openings[n] >= 0):
                raise RenderError(f"opening of gripper {n!r} must be a finite gap >= 0 m, "
                                  f"got {o!r}")
        grippers = tuple(replace(g, opening=openings[g.name]) if g.name in openings else g
                         for g in sc.grippers)
        T_ref = {p.name: np.asarray(poses.get(p.name, p.T_ref_field), dtype=float)
                 for p in sc.placements}
        T_obj = {n: np.asarray(poses.get(n, T), dtype=float) for n, T in objects.items()}
        for n, T in T_obj.items():
            if T.shape != (4, 4) or not np.all(np.isfinite(T)):
                raise RenderError(f"pose of {n!r} must be a finite 4x4 transform")
        images, truth, needle_truth, times = {}, {}, {}, {}
        names = cameras or tuple(sc.rig.names)
        key = _state_key(T_ref, T_obj, grippers) if self.keep_clean else b""
        for cam_name in names:
            t0 = time.perf_counter()
            # the noise draw belongs to the camera, whichever cameras this call renders
            ci = sc.rig.names.index(sc.rig[cam_name].name)
            img, tr, ntr = self._render_camera(cam_name, T_ref, T_obj, frame, ci, grippers,
                                               key)
            images[cam_name], truth[cam_name] = img, tr
            if sc.needles:
                needle_truth[cam_name] = ntr
            times[cam_name] = time.perf_counter() - t0
        return Frame(images=images, T_ref_field=T_ref, truth=truth, frame=frame,
                     seed=sc.seed, render_s=times, needle_truth=needle_truth,
                     T_ref_needle={n.name: T_obj[n.name] for n in sc.needles},
                     T_ref_pad={p.name: T_obj[p.name] for p in sc.pads},
                     T_ref_tool={g.name: T_obj[g.name] for g in sc.grippers},
                     opening={g.name: g.opening for g in grippers})

    # -- one camera -------------------------------------------------------------------
    def _render_camera(self, cam_name: str, T_ref: dict[str, np.ndarray],
                       T_obj: dict[str, np.ndarray], frame: int, cam_index: int,
                       grippers: tuple[Gripper, ...], key: bytes
                       ) -> tuple[np.ndarray, dict[str, FieldTruth], dict[str, NeedleTruth]]:
        """One camera's image (noise of ``frame`` on the noise-free signal of the state
        ``key``, rendered or kept from an earlier call) and its ground truth."""
        kept = self._clean.setdefault(cam_name, OrderedDict())
        hit = kept.get(key) if self.keep_clean else None
        if hit is None:
            signal, truth, needle_truth = self._render_clean(cam_name, T_ref, T_obj, grippers)
            if self.keep_clean:
                kept[key] = (signal.copy(), copy.deepcopy(truth), copy.deepcopy(needle_truth))
                while len(kept) > self.keep_clean:
                    kept.popitem(last=False)
        else:
            kept.move_to_end(key)
            # copies: a caller may keep or change a frame's truth; the kept one must not
            signal, truth, needle_truth = (hit[0].copy(), copy.deepcopy(hit[1]),
                                           copy.deepcopy(hit[2]))
        if self.scene.imaging.noisy:
            self._add_noise(signal, frame, cam_index)
        np.maximum(signal, 0.0, out=signal)  # convertScaleAbs would mirror negatives
        image = cv2.convertScaleAbs(signal)  # rounds and saturates to 0..255
        return image, truth, needle_truth

    def _render_clean(self, cam_name: str, T_ref: dict[str, np.ndarray],
                      T_obj: dict[str, np.ndarray], grippers: tuple[Gripper, ...]
                      ) -> tuple[np.ndarray, dict[str, FieldTruth], dict[str, NeedleTruth]]:
        """One camera's noise-free signal (float, before clipping) and its ground truth."""
        st = self._camera(cam_name)
        cam = st.cam
        im = self.scene.imaging
        T_cam_ref = cam.T_cam_ref
        patches: list[_Patch] = []
        for k, pl in enumerate(self.scene.placements):
            patch = self._field_patch(st, pl, T_cam_ref, T_ref[pl.name], owner=k + 1)
            if patch is not None:
                patches.append(patch)
        n_fields = len(self.scene.placements)
        for k, rod in enumerate(self.scene.rods):
            patches += self._rod_patches(st, rod, T_cam_ref, owner=n_fields + k + 1)
        next_owner = n_fields + len(self.scene.rods) + 1
        pads = []  # the pads drawn in this view, which also occlude in the object layer
        for pad in self.scene.pads:
            T = T_cam_ref @ T_obj[pad.name]
            patch = self._pad_patch(st, pad, T, owner=next_owner)
            next_owner += 1
            if patch is not None:
                patches.append(patch)
                pads.append((pad, T, patch))
        layer = None
        if self.scene.needles or self.scene.grippers:
            layer = self._object_layer(st, T_cam_ref, T_obj, pads, grippers,
                                       owner=next_owner)
        if layer is not None and layer.patch is not None:
            # The layer is resolved against the pads per sample, so it goes over all of
            # them; against fields and rods it is ordered by its mean depth, as they are.
            if pads:
                layer.patch.depth = min(layer.patch.depth,
                                        min(p.depth for _, _, p in pads) - 1e-9)
            patches.append(layer.patch)

        signal = st.background.copy()
        owner = np.zeros(signal.shape, np.uint8)
        # pixels that an object composited after the layer covers (needle visibility)
        late = np.zeros(signal.shape, bool) if self.scene.needles else None
        after_layer = False
        for p in sorted(patches, key=lambda p: -p.depth):
            h, w = p.alpha.shape
            sl = (slice(p.y0, p.y0 + h), slice(p.x0, p.x0 + w))
            illum = st.illumination[sl]
            sig = signal[sl]
            sig *= 1.0 - p.alpha
            sig += p.value * illum
            owner[sl][p.alpha > 0.5] = p.owner
            if late is not None:
                if after_layer:
                    late[sl] |= p.alpha > 0.5
                after_layer |= layer is not None and p is layer.patch
        if im.blur_sigma_px > 0 and patches:
            self._blur(signal, patches, im.blur_sigma_px)
        truth = {}
        for k, pl in enumerate(self.scene.placements):
            tr = self._field_truth(cam, pl, T_cam_ref @ T_ref[pl.name], owner, k + 1)
            if tr is not None:
                truth[pl.name] = tr
        needle_truth = {nd.name: self._needle_truth(cam, nd, T_cam_ref @ T_obj[nd.name],
                                                    layer, late)
                        for nd in self.scene.needles}
        return signal, truth, needle_truth

    def _blur(self, signal: np.ndarray, patches: list[_Patch], sigma: float) -> None:
        """Gaussian blur inside the union box of all objects (the background is smooth)."""
        pad = int(math.ceil(4 * sigma)) + 1
        h, w = signal.shape
        x0 = max(min(p.x0 for p in patches) - pad, 0)
        y0 = max(min(p.y0 for p in patches) - pad, 0)
        x1 = min(max(p.x0 + p.alpha.shape[1] for p in patches) + pad, w)
        y1 = min(max(p.y0 + p.alpha.shape[0] for p in patches) + pad, h)
        roi = signal[y0:y1, x0:x1]
        roi[...] = cv2.GaussianBlur(roi, (0, 0), sigma, borderType=cv2.BORDER_REPLICATE)

    def _add_noise(self, signal: np.ndarray, frame: int, cam_index: int) -> None:
        im = self.scene.imaging
        seed = self.scene.seed
        seq = np.random.SeedSequence([seed & 0xFFFFFFFF, seed >> 32, frame, cam_index])
        cv2.setRNGSeed(int(seq.generate_state(1)[0] & 0x7FFFFFFF))
        noise = np.empty_like(signal)
        cv2.randn(noise, 0.0, 1.0)
        if im.shot_noise_gain > 0:
            var = cv2.addWeighted(signal, im.shot_noise_gain, signal, 0.0,
                                  im.read_noise_dn ** 2)
            np.maximum(var, 0.0, out=var)
            cv2.multiply(noise, cv2.sqrt(var), dst=noise)
            cv2.add(signal, noise, dst=signal)
        else:
            cv2.scaleAdd(noise, im.read_noise_dn, signal, dst=signal)

    # -- bounding boxes ---------------------------------------------------------------
    def _bbox(self, cam: CameraModel, pts_cam: np.ndarray, pad: int
              ) -> tuple[int, int, int, int] | None:
        pts_cam = pts_cam[pts_cam[:, 2] > 1e-4]
        if len(pts_cam) == 0:
            return None
        uv = cam.project(pts_cam)
        uv = uv[np.isfinite(uv).all(axis=1)]
        if len(uv) == 0:
            return None
        x0 = max(int(math.floor(uv[:, 0].min())) - pad, 0)
        y0 = max(int(math.floor(uv[:, 1].min())) - pad, 0)
        x1 = min(int(math.ceil(uv[:, 0].max())) + pad + 1, cam.width)
        y1 = min(int(math.ceil(uv[:, 1].max())) + pad + 1, cam.height)
        if x1 <= x0 or y1 <= y0:
            return None
        return x0, y0, x1, y1

    @staticmethod
    def _hull_points(fld: MarkerField) -> np.ndarray:
        """Points (field frame) whose projections bound the field's image footprint."""
        W, H = fld.sheet_size
        s = fld.surface
        if isinstance(s, CylinderSurface):
            phi = np.linspace(-np.pi, np.pi, 73)
            y = np.linspace(0.0, H, 9)
            P, Y = np.meshgrid(phi, y)
            xc = 0.5 * W
            return np.stack([xc + s.radius * np.sin(P), Y, s.radius * (1 - np.cos(P))],
                            axis=-1).reshape(-1, 3)
        t = np.linspace(0.0, 1.0, 33)
        edge = np.concatenate([np.stack([t * W, 0 * t], 1), np.stack([t * W, 0 * t + H], 1),
                               np.stack([0 * t, t * H], 1), np.stack([0 * t + W, t * H], 1)])
        return fld.sheet_to_field(edge)

    # -- fields -----------------------------------------------------------------------
    def _field_patch(self, st: _CameraState, pl: Placement, T_cam_ref: np.ndarray,
                     T_ref_field: np.ndarray, owner: int) -> _Patch | None:
        im = self.scene.imaging
        fld = pl.field
        n = max(1, im.motion_samples)
        moving = n > 1 and (np.any(pl.velocity) or np.any(pl.angular_velocity))
        taus = [((k + 0.5) / n - 0.5) * im.exposure for k in range(n)] if moving else [0.0]
        poses = [T_cam_ref @ _pose_at(T_ref_field, pl.velocity, pl.angular_velocity, tau)
                 for tau in taus]
        hull = self._hull_points(fld)
        boxes = [self._bbox(st.cam, transform_points(T, hull), pad=2) for T in poses]
        boxes = [b for b in boxes if b is not None]
        if not boxes:
            return None
        x0, y0 = min(b[0] for b in boxes), min(b[1] for b in boxes)
        x1, y1 = max(b[2] for b in boxes), max(b[3] for b in boxes)
        s = im.supersample
        rays = st.sub_rays(x0, y0, x1, y1, s)
        blots = [b for b in self.scene.blots if b.placement == pl.name]
        val_sum = alpha_sum = None
        for T in poses:
            val, alpha = self._shade_field(fld, T, rays, blots, st.cam)
            val_sum = val if val_sum is None else val_sum + val
            alpha_sum = alpha if alpha_sum is None else alpha_sum + alpha
        if len(poses) > 1:
            val_sum /= len(poses)
            alpha_sum /= len(poses)
        if not np.any(alpha_sum):
            return None
        size = (x1 - x0, y1 - y0)
        if s > 1:
            val_sum = cv2.resize(val_sum, size, interpolation=cv2.INTER_AREA)
            alpha_sum = cv2.resize(alpha_sum, size, interpolation=cv2.INTER_AREA)
        depth = float(transform_points(poses[len(poses) // 2], fld.corners)[:, 2].mean())
        return _Patch(x0, y0, val_sum, alpha_sum, depth, owner)

    def _shade_field(self, fld: MarkerField, T_cam_field: np.ndarray, rays: np.ndarray,
                     blots: list, cam: CameraModel) -> tuple[np.ndarray, np.ndarray]:
        """Premultiplied level and coverage of every sample (unit illumination)."""
        im = self.scene.imaging
        tex = self._texture(fld)
        depth = float(np.linalg.norm(T_cam_field[:3, 3])) or 1.0
        pps = tex.level_for(cam.K[0, 0] * im.supersample * fld.square / depth)
        scale = pps / fld.square
        maps, body = self._texel_maps(fld, T_cam_field, rays, scale)
        if maps is None:
            return (np.zeros(rays.shape[:2], np.float32),) * 2
        # The print (0 black .. 255 white) and the sheet's coverage (255 on the sheet) are
        # sampled alike; outside the sheet both read 0, so bilinear sampling anti-aliases
        # the sheet edge too and the print comes out premultiplied by the coverage.
        # (Two one-channel remaps are ~3x faster than one two-channel remap.)
        print_img, cover_img = tex.levels[pps]
        print_ = cv2.remap(print_img, maps, None, cv2.INTER_LINEAR,
                           borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        cover = cv2.remap(cover_img, maps, None, cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        val = cv2.addWeighted(cover, im.black / 255.0, print_, (im.white - im.black) / 255.0,
                              0.0, dtype=cv2.CV_32F)
        alpha = cover.astype(np.float32)
        alpha *= 1.0 / 255.0
        for blot in blots:
            cx, cy = (c * scale - 0.5 for c in blot.center)
            r = blot.radius * scale
            mx, my = maps[..., 0], maps[..., 1]
            inside = (mx - cx) ** 2 + (my - cy) ** 2 <= r * r
            val[inside] = blot.level * alpha[inside]
        if body is not None:
            bare = body * (1.0 - alpha)
            val += im.body * bare
            alpha += bare
        return val, alpha

    @staticmethod
    def _texel_maps(fld: MarkerField, T_cam_field: np.ndarray, rays: np.ndarray,
                    scale: float) -> tuple[np.ndarray | None, np.ndarray | None]:
        """Texel coordinates (h x w x 2, float32) where each sample's ray meets the sheet,
        and for a cylinder the mask (float32 0/1) of samples that hit its body at all.

        Samples that miss are sent far outside the texture. ``scale`` is texels per metre.
        """
        W, H = fld.sheet_size
        surf = fld.surface
        R = T_cam_field[:3, :3]
        o = -R.T @ T_cam_field[:3, 3]          # camera centre in the field frame
        if isinstance(surf, PlaneSurface):
            if o[2] >= 0:  # camera behind the printed face: the sheet is not seen
                return None, None
            # The plane z = 0 is a homography of the normalised image: for a ray
            # d = R^T [x, y, 1], the hit is o - (o_z / d_z) d. Fold in texel scaling.
            Rt = R.T
            Hm = np.array([[o[0] * Rt[2] - o[2] * Rt[0]],
                           [o[1] * Rt[2] - o[2] * Rt[1]],
                           [Rt[2]]]).reshape(3, 3)
            A = np.array([[scale, 0.0, -0.5], [0.0, scale, -0.5], [0.0, 0.0, 1.0]])
            maps = cv2.perspectiveTransform(np.ascontiguousarray(rays), A @ Hm)
            # rays meeting the plane behind the camera (d_z <= 0) see nothing
            dz = Rt[2, 0] * rays[..., 0] + Rt[2, 1] * rays[..., 1] + Rt[2, 2]
            maps[dz <= 0] = -10.0
            return maps, None
        R32 = R.astype(np.float32)
        x, y = rays[..., 0], rays[..., 1]
        dx = R32[0, 0] * x + R32[1, 0] * y + R32[2, 0]
        dy = R32[0, 1] * x + R32[1, 1] * y + R32[2, 1]
        dz = R32[0, 2] * x + R32[1, 2] * y + R32[2, 2]
        r = np.float32(surf.radius)
        xc = np.float32(0.5 * W)
        ox, oy, oz = (np.float32(v) for v in (o[0] - xc, o[1], o[2] - surf.radius))
        a = dx * dx + dz * dz
        b = 2.0 * (dx * ox + dz * oz)
        c = ox * ox + oz * oz - r * r
        disc = b * b - 4.0 * a * c
        with np.errstate(invalid="ignore", divide="ignore"):
            lam = (-b - np.sqrt(disc)) / (2.0 * a)
        Y = oy + lam * dy
        body = (disc > 0) & (lam > 0) & (Y >= 0) & (Y <= H)
        # phi measured from the sheet's centre line, printed face outward
        phi = np.arctan2(ox + lam * dx, -(oz + lam * dz))
        maps = np.empty(rays.shape, np.float32)
        maps[..., 0] = (xc + r * phi) * scale - 0.5
        maps[..., 1] = Y * scale - 0.5
        maps[~body] = -10.0
        return maps, body.astype(np.float32)

    def _field_truth(self, cam: CameraModel, pl: Placement, T_cam_field: np.ndarray,
                     owner: np.ndarray, owner_id: int) -> FieldTruth | None:
        fld = pl.field
        pc = transform_points(T_cam_field, fld.corners)
        uv = cam.project(pc)
        normals = fld.sheet_normals(fld.corners_flat) @ T_cam_field[:3, :3].T
        view = pc / np.linalg.norm(pc, axis=1, keepdims=True)
        cos_obl = -(normals * view).sum(axis=1)
        ok = cam.in_image(uv) & (cos_obl > 0) & (pc[:, 2] > 0)
        for blot in self.scene.blots:
            if blot.placement == pl.name:
                d2 = ((fld.corners_flat - np.asarray(blot.center)) ** 2).sum(axis=1)
                ok &= d2 > blot.radius ** 2
        idx = np.flatnonzero(ok)
        if len(idx):
            ui = np.clip(np.rint(uv[idx, 0]).astype(int), 0, cam.width - 1)
            vi = np.clip(np.rint(uv[idx, 1]).astype(int), 0, cam.height - 1)
            idx = idx[owner[vi, ui] == owner_id]
        if len(idx) == 0:
            return None
        return FieldTruth(T_cam_field=T_cam_field, corner_ids=fld.corner_ids[idx].copy(),
                          corners_px=uv[idx], obliquity=np.arccos(np.clip(cos_obl[idx], -1, 1)))

    # -- rods -------------------------------------------------------------------------
    def _rod_patches(self, st: _CameraState, rod: Rod, T_cam_ref: np.ndarray,
                     owner: int) -> list[_Patch]:
        """A rod as short pieces, each ray-cast only inside its own small box (a long
        diagonal rod's single box would be mostly empty)."""
        p0 = transform_points(T_cam_ref, rod.p0[None])[0]
        p1 = transform_points(T_cam_ref, rod.p1[None])[0]
        length = float(np.linalg.norm(p1 - p0))
        if length == 0:
            return []
        ends = self._bbox(st.cam, np.stack([p0, p1]), pad=0)
        span = 0 if ends is None else max(ends[2] - ends[0], ends[3] - ends[1])
        n = max(1, min(64, span // 48))
        out = []
        for k in range(n):
            patch = self._rod_piece(st, rod, p0, p1, k / n, (k + 1) / n, owner)
            if patch is not None:
                out.append(patch)
        return out

    def _rod_piece(self, st: _CameraState, rod: Rod, p0: np.ndarray, p1: np.ndarray,
                   f0: float, f1: float, owner: int) -> _Patch | None:
        """Part [f0, f1] (fractions of the length) of the rod from p0 to p1 (camera frame)."""
        axis = p1 - p0
        length = float(np.linalg.norm(axis))
        u = axis / length
        ring = _ring(u, rod.radius)
        along = np.linspace(f0, f1, 5)[:, None, None] * axis
        box = self._bbox(st.cam, (p0 + along + ring[None]).reshape(-1, 3), pad=2)
        if box is None:
            return None
        x0, y0, x1, y1 = box
        s = self.scene.imaging.supersample
        rays = st.sub_rays(x0, y0, x1, y1, s)
        x, y = rays[..., 0], rays[..., 1]
        # ray d = [x, y, 1]; the cylinder is |perp(lam d - p0)| = r about axis u
        uf = u.astype(np.float32)
        du = uf[0] * x + uf[1] * y + uf[2]
        m_perp = (p0 - (p0 @ u) * u).astype(np.float32)
        dpx, dpy, dpz = x - du * uf[0], y - du * uf[1], 1.0 - du * uf[2]
        a = dpx * dpx + dpy * dpy + dpz * dpz
        b = -2.0 * (dpx * m_perp[0] + dpy * m_perp[1] + dpz * m_perp[2])
        c = np.float32(m_perp @ m_perp - rod.radius ** 2)
        disc = b * b - 4.0 * a * c
        with np.errstate(invalid="ignore", divide="ignore"):
            root = np.sqrt(disc)
            lam = (-b - root) / (2.0 * a)
        along_s = lam * du - np.float32(p0 @ u)
        hit = (disc > 0) & (lam > 0) & (along_s >= f0 * length) & (along_s < f1 * length)
        if not hit.any():
            return None
        # Lit from the camera: brightest where the surface faces the viewer. The normal's
        # cosine to the ray is sqrt(disc) / (2 r sqrt(a) |d|) for this quadratic.
        with np.errstate(invalid="ignore", divide="ignore"):
            facing = root / (2.0 * rod.radius * np.sqrt(a * (x * x + y * y + 1.0)))
        val = np.where(hit, rod.level * (0.55 + 0.45 * np.clip(facing, 0, 1)), 0.0)
        val = val.astype(np.float32)
        alpha = hit.astype(np.float32)
        if s > 1:
            size = (x1 - x0, y1 - y0)
            val = cv2.resize(val, size, interpolation=cv2.INTER_AREA)
            alpha = cv2.resize(alpha, size, interpolation=cv2.INTER_AREA)
        mid = p0 + 0.5 * (f0 + f1) * axis
        return _Patch(x0, y0, val, alpha, float(mid[2]), owner)

    # -- tissue pads ------------------------------------------------------------------
    def _pad_patch(self, st: _CameraState, pad: TissuePad, T_cam_pad: np.ndarray,
                   owner: int) -> _Patch | None:
        """The pad as a plane patch: its level inside its rectangle, the incision's level
        inside the incision's stroke; seen only from its +z side.

        The pad is uniform away from its outline and its incision, where supersampling
        changes nothing. So pixels are classified at their centres, and only short pieces
        along the four edges and along the stroke (boxes as rods' pieces have) are
        supersampled: the same image as supersampling the whole box, at a fraction of the
        cost for a pad that fills much of the view.
        """
        cam = st.cam
        o = -T_cam_pad[:3, :3].T @ T_cam_pad[:3, 3]   # camera centre in the pad frame
        if o[2] <= 0:
            return None
        sx, sy = pad.size
        corners = np.array([[-sx, -sy, 0], [sx, -sy, 0], [sx, sy, 0], [-sx, sy, 0]]) / 2
        t = np.linspace(0.0, 1.0, 33)[:, None]
        outline = np.concatenate([corners[k] + t * (corners[(k + 1) % 4] - corners[k])
                                  for k in range(4)])
        box = self._bbox(cam, transform_points(T_cam_pad, outline), pad=2)
        if box is None:
            return None
        x0, y0, x1, y1 = box
        s = self.scene.imaging.supersample
        cc = transform_points(T_cam_pad, corners)
        if cc[:, 2].min() <= NEAR:
            # the pad reaches behind the camera: supersample it all, by plane coordinates
            x, y = st.sub_rays_xy(x0, y0, x1, y1, s)
            cover = _pad_hits(pad, T_cam_pad, cv2.merge([x, y]))[0].astype(np.float32)
            alpha = cover if s == 1 else cv2.resize(cover, (x1 - x0, y1 - y0),
                                                    interpolation=cv2.INTER_AREA)
            edges = None
        else:
            # A ray meets the rectangle iff it lies inside the four planes through the
            # camera centre and its edges: four affine maps of the normalised image.
            edges = []
            for k in range(4):
                n = np.cross(cc[k], cc[(k + 1) % 4])
                edges.append(n / (np.linalg.norm(n) * np.sign(n @ cc.mean(axis=0))))
            px, py = cv2.split(np.ascontiguousarray(st.rays[y0:y1, x0:x1]))
            alpha = _inside(px, py, edges).astype(np.float32)
            if s > 1:
                for bx in self._stroke_boxes(cam, T_cam_pad, [(corners[k, :2],
                                             corners[(k + 1) % 4, :2], 0.0) for k in range(4)]):
                    bx0, by0, bx1, by1 = _clip_box(bx, box)
                    if bx1 > bx0:
                        x, y = st.sub_rays_xy(bx0, by0, bx1, by1, s)
                        alpha[by0 - y0:by1 - y0, bx0 - x0:bx1 - x0] = cv2.resize(
                            _inside(x, y, edges).astype(np.float32), (bx1 - bx0, by1 - by0),
                            interpolation=cv2.INTER_AREA)
        if not alpha.any():
            return None
        val = alpha * np.float32(pad.level)
        half = 0.5 * pad.incision_width
        for bx in self._stroke_boxes(cam, T_cam_pad, [(*pad.incision, half)]):
            bx0, by0, bx1, by1 = _clip_box(bx, box)
            if bx1 <= bx0:
                continue
            x, y = st.sub_rays_xy(bx0, by0, bx1, by1, s)
            hx, hy = _plane_xy(T_cam_pad, x, y)
            cover = (_inside(x, y, edges) if edges is not None
                     else (np.abs(hx) <= 0.5 * sx) & (np.abs(hy) <= 0.5 * sy))
            # boxes overlap; each tests the whole stroke, so overlaps agree
            v = np.where(_near_segment(hx, hy, pad.incision, half),
                         np.float32(pad.incision_level), np.float32(pad.level)) * cover
            if s > 1:
                v = cv2.resize(v, (bx1 - bx0, by1 - by0), interpolation=cv2.INTER_AREA)
            val[by0 - y0:by1 - y0, bx0 - x0:bx1 - x0] = v
        return _Patch(x0, y0, val, alpha, float(cc[:, 2].mean()), owner)

    def _stroke_boxes(self, cam: CameraModel, T_cam_pad: np.ndarray, strokes: list
                      ) -> np.ndarray:
        """Pixel boxes (m x 4) of short pieces (about 32 px) of straight strokes on the
        pad: ``strokes`` is a list of (a, b, half_width), ends in pad x, y (m). Each box
        holds its piece's stroke plus 2 px; together they cover every pixel the strokes
        (or, for width 0, the lines) touch."""
        out = []
        for a, b, h in strokes:
            a, b = np.asarray(a, float), np.asarray(b, float)
            ends = transform_points(T_cam_pad, np.array([[*a, 0.0], [*b, 0.0]]))
            n = 1
            if ends[:, 2].min() > NEAR:
                uv = cam.project(ends)
                n = int(min(max(math.ceil(np.linalg.norm(uv[1] - uv[0]) / 32.0), 1), 256))
            f = np.linspace(0.0, 1.0, n + 1)
            along = a + f[:, None] * (b - a)
            off = np.array([[dx, dy] for dx in (-h, h) for dy in (-h, h)])
            pts = np.concatenate([along[:-1, None] + off, along[1:, None] + off], axis=1)
            pts = np.concatenate([pts, np.zeros(pts.shape[:2] + (1,))], axis=2)
            out.append(self._piece_boxes(cam, transform_points(T_cam_pad, pts.reshape(-1, 3))
                                         .reshape(n, -1, 3)))
        boxes = np.concatenate(out)
        return boxes[(boxes[:, 2] > boxes[:, 0]) & (boxes[:, 3] > boxes[:, 1])]

    # -- needles and grippers: one sample-level z-buffer ------------------------------
    def _object_layer(self, st: _CameraState, T_cam_ref: np.ndarray,
                      T_obj: dict[str, np.ndarray],
                      pads: list[tuple[TissuePad, np.ndarray, _Patch]],
                      grippers: tuple[Gripper, ...], owner: int) -> _Layer:
        """Ray-cast every needle and gripper piece, each inside its own small box, into one
        z-buffer of supersamples; a sample whose ray meets a drawn pad before the piece is
        dropped (the pad, drawn beneath the layer, shows there).

        Why a z-buffer: these objects touch and interleave. A needle lies on a pad (an
        oblique pad's mean depth can be nearer than the needle on it), the jaws clamp the
        wire from both sides (one jaw in front of it, one behind, both overlapping it in
        the image), a driven needle is half inside the tissue. Ordering whole objects, or
        pieces, by one depth gets each of these wrong somewhere; a depth test per
        supersample gets them right, and edges stay anti-aliased because the test comes
        before the box filter. Only these objects share the buffer (it spans the union of
        their boxes); fields and rods keep the cheaper per-object order. Pads are planes
        and need no buffer: a piece's hit samples are tested against them, and only for
        pieces that reach below a pad's surface (nothing above a plane seen from its
        front can be hidden by it).
        """
        cam = st.cam
        s = self.scene.imaging.supersample
        codes: dict[str, int] = {}
        materials = [(0.0, 0.0, 1.0, True)]   # (level, specular, shininess, rod) by code
        jobs: list[_Job] = []
        for nd in self.scene.needles:
            codes[nd.name] = code = len(materials)
            materials.append((nd.level, nd.specular, nd.shininess, False))
            jobs += self._needle_pieces(cam, nd, T_cam_ref @ T_obj[nd.name], code)
        for g in grippers:
            codes[g.name] = code = len(materials)
            materials.append((g.level, 0.0, 1.0, True))
            jobs += self._gripper_pieces(cam, g, T_cam_ref @ T_obj[g.name], code)
        for nd in self.scene.needles:
            if nd.thread_length > 0:
                # The thread is part of its needle (its code: it does not hide the needle's
                # centreline in the truth) drawn in its own material, matt like a rod.
                materials.append((nd.thread_level, 0.0, 1.0, True))
                jobs += self._thread_pieces(cam, nd, T_cam_ref @ T_obj[nd.name],
                                            codes[nd.name], len(materials) - 1)
        jobs = [j for j in jobs if len(j.boxes)]
        if not jobs:
            return _Layer(0, 0, s, np.zeros((0, 0), np.float32), np.zeros((0, 0), np.int16),
                          codes, None, pads)
        allb = np.concatenate([j.boxes for j in jobs])
        x0, y0 = int(allb[:, 0].min()), int(allb[:, 1].min())
        x1, y1 = int(allb[:, 2].max()), int(allb[:, 3].max())
        shape = ((y1 - y0) * s, (x1 - x0) * s)
        inv = np.zeros(shape, np.float32)
        val = np.zeros(shape, np.float32)
        own = np.zeros(shape, np.int16)
        drawn = False
        for job in _batches(jobs):
            boxes = job.boxes
            if len(boxes) == 1:   # one piece: its own rays
                r = st.sub_rays(*(int(v) for v in boxes[0]), s)
                xs, ys, valid = r[None, ..., 0], r[None, ..., 1], True
            else:                 # many small pieces: one pass over their gathered rays
                jx0, jy0 = int(boxes[:, 0].min()), int(boxes[:, 1].min())
                r = st.sub_rays(jx0, jy0, int(boxes[:, 2].max()), int(boxes[:, 3].max()), s)
                xs, ys, valid = _gather(r, (boxes - [jx0, jy0, jx0, jy0]) * s)
            hit, lam, c = _CASTERS[job.kind](xs, ys, **job.par)
            hit &= valid & (lam > NEAR)
            under = np.zeros(len(boxes), bool)
            for _, T, _ in pads:
                height = (job.axis - T[:3, 3]) @ T[:3, 2]   # above the pad's plane (m)
                under |= height.min(axis=1) - job.margin < -1e-9
            if under.any():
                # samples whose ray meets a pad before the piece: under the tissue
                at = np.nonzero(hit & under[:, None, None])
                hidden = np.zeros(len(at[0]), bool)
                for pad, T, _ in pads:
                    hidden |= _pad_in_front(pad, T, xs[at], ys[at], lam[at])
                hit[tuple(a[hidden] for a in at)] = False
            linv = np.divide(np.float32(1.0), lam, out=np.zeros(lam.shape, np.float32),
                             where=hit)
            shade = _shade(materials[job.code if job.material < 0 else job.material], c)
            sb = (boxes - [x0, y0, x0, y0]) * s
            for k in range(len(sb)):
                bx0, by0, bx1, by1 = (int(v) for v in sb[k])
                sl = (slice(by0, by1), slice(bx0, bx1))
                li = linv[k, :by1 - by0, :bx1 - bx0]
                m = li > inv[sl]
                if m.any():
                    np.copyto(inv[sl], li, where=m)
                    np.copyto(val[sl], shade[k, :by1 - by0, :bx1 - bx0], where=m)
                    own[sl][m] = job.code
                    drawn = True
        if not drawn:
            return _Layer(x0, y0, s, inv, own, codes, None, pads)
        # ordered against fields and rods by the mean depth of the pieces' axes
        depth = float(np.mean(np.concatenate([j.axis[..., 2].ravel() for j in jobs])))
        value = val   # the shaded level where an object is, 0 elsewhere: premultiplied
        alpha = (own > 0).astype(np.float32)
        if s > 1:
            size = (x1 - x0, y1 - y0)
            value = cv2.resize(value, size, interpolation=cv2.INTER_AREA)
            alpha = cv2.resize(alpha, size, interpolation=cv2.INTER_AREA)
        return _Layer(x0, y0, s, inv, own, codes, _Patch(x0, y0, value, alpha, depth, owner),
                      pads)

    def _piece_boxes(self, cam: CameraModel, pts: np.ndarray) -> np.ndarray:
        """Pixel boxes (m x 4: x0, y0, x1, y1, clipped to the image) of m point groups
        (m x k x 3, camera frame), padded by 2 px; empty boxes come out with x1 <= x0."""
        m, k = pts.shape[:2]
        uv = cam.project(pts.reshape(-1, 3)).reshape(m, k, 2)
        lo = np.floor(uv.min(axis=1)) - 2
        hi = np.ceil(uv.max(axis=1)) + 3
        behind = ~np.isfinite(lo).all(axis=1) | ~np.isfinite(hi).all(axis=1)
        lo[behind] = 0.0   # a piece reaching behind the camera is not drawn
        hi[behind] = 0.0
        x0 = np.clip(lo[:, 0], 0, cam.width)
        y0 = np.clip(lo[:, 1], 0, cam.height)
        x1 = np.clip(hi[:, 0], 0, cam.width)
        y1 = np.clip(hi[:, 1], 0, cam.height)
        return np.stack([x0, y0, x1, y1], axis=1).astype(np.int64)

    def _needle_pieces(self, cam: CameraModel, nd: NeedleObject, T: np.ndarray,
                       code: int) -> list[_Job]:
        """The wire as mitred chord pieces of the arc, plus flat caps at base and tip.

        Chord bound: pieces span ``dphi`` with sagitta ``s = R_v (1 - cos(dphi / 2))`` no
        larger than a tenth of the wire radius and 0.05 px at the needle's nearest point
        (``SAGITTA_WIRE``, ``SAGITTA_PX``); the vertices sit on a circle of radius ``R_v =
        R + s / 2``, so the drawn axis is within +-s/2 of the true arc everywhere. For the
        CT-1 needle (R 13 mm, wire 1 mm) face-on 10 cm from a 520 px focal length camera
        this is 41 pieces, s = 0.0096 mm (0.05 px; the pixel bound is the tighter one
        there, the wire bound is 0.05 mm). Each piece is the wire's
        cylinder about its chord, cut by the planes bisecting the angles at its ends
        (mitre joints: adjacent pieces meet exactly, without gaps or overlaps).
        """
        needle = nd.needle
        x, y = np.eye(3)[0], np.eye(3)[1]
        return self._tube_pieces(cam, T, np.zeros(3), x, y, needle.radius, needle.arc,
                                 0.5 * needle.wire_diameter, code, caps=(True, True))

    def _thread_pieces(self, cam: CameraModel, nd: NeedleObject, T: np.ndarray, code: int,
                       material: int) -> list[_Job]:
        """The suture thread (``NeedleObject.thread_arc``, frame N) as mitred chord pieces
        of its arc, the needle's own construction and chord bound at the thread's radius;
        a flat cap at its free end only (its start is inside the swage)."""
        centre, e1, e2, angle = nd.thread_arc()
        jobs = self._tube_pieces(cam, T, centre, e1, e2, nd.thread_bend_radius, angle,
                                 0.5 * nd.thread_diameter, code, caps=(False, True))
        return [replace(j, material=material) for j in jobs]

    def _tube_pieces(self, cam: CameraModel, T: np.ndarray, centre: np.ndarray,
                     e1: np.ndarray, e2: np.ndarray, R: float, arc: float, r: float,
                     code: int, caps: tuple[bool, bool]) -> list[_Job]:
        """A wire of radius ``r`` swept along the circular arc ``centre + R (cos a e1 +
        sin a e2)``, ``a`` in [0, ``arc``] (frame of ``T``, the pose in the camera), as
        mitred chord pieces (see :meth:`_needle_pieces` for the bound), with flat caps at
        the start and the end where ``caps`` says."""
        def circle(radius: float, a: np.ndarray) -> np.ndarray:
            return (centre + radius * np.cos(a)[:, None] * e1
                    + radius * np.sin(a)[:, None] * e2)

        coarse = transform_points(T, circle(R, np.linspace(0.0, arc, 33)))
        if coarse[:, 2].max() <= NEAR + r:
            return []
        f = float(max(cam.K[0, 0], cam.K[1, 1]))
        zmin = max(float(coarse[:, 2].min()) - r, NEAR)
        sag = min(SAGITTA_WIRE * r, SAGITTA_PX * zmin / f)
        Rv = R + 0.5 * sag
        dphi = 2.0 * math.acos(1.0 - sag / Rv)
        n = int(min(max(math.ceil(arc / dphi), 1), 2048))
        phi = np.linspace(0.0, arc, n + 1)
        V = transform_points(T, circle(Rv, phi))
        seg = V[1:] - V[:-1]
        U = seg / np.linalg.norm(seg, axis=1, keepdims=True)
        Bn = np.empty_like(V)                      # mitre plane normals at the vertices
        Bn[0], Bn[-1] = U[0], U[-1]
        mid = U[:-1] + U[1:]
        Bn[1:-1] = mid / np.linalg.norm(mid, axis=1, keepdims=True)
        cube = r * np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)])
        pts = np.concatenate([V[:-1, None] + cube, V[1:, None] + cube], axis=1)
        boxes = self._piece_boxes(cam, pts)
        ok = ((V[:-1, 2] > NEAR + r) & (V[1:, 2] > NEAR + r)
              & (boxes[:, 2] > boxes[:, 0]) & (boxes[:, 3] > boxes[:, 1]))
        idx = np.flatnonzero(ok)
        axis = np.stack([V[:-1], V[1:]], axis=1)
        out = [_Job(code, "cylinder", boxes[idx], dict(
            P0=V[idx], U=U[idx], r=r, N0=Bn[idx], c0=(Bn[idx] * V[idx]).sum(1),
            N1=Bn[idx + 1], c1=(Bn[idx + 1] * V[idx + 1]).sum(1)), axis[idx], r,
            ("P0", "U", "N0", "c0", "N1", "c1"))]
        for k, vi, cap in ((0, 0, caps[0]), (n - 1, n, caps[1])):   # flat end caps
            if cap and ok[k]:
                out.append(_Job(code, "disc", boxes[k:k + 1],
                                dict(C=V[vi:vi + 1], N=U[k:k + 1], r=r), axis[k:k + 1], r))
        return out

    def _gripper_pieces(self, cam: CameraModel, g: Gripper, T: np.ndarray,
                        code: int) -> list[_Job]:
        """The two jaws (boxes in frame T) and the shaft (cylinder pieces, split as rods
        are, with a flat cap at the jaw end)."""
        out = []
        half = 0.5 * g.jaw_width
        R, t = T[:3, :3], T[:3, 3]
        corners = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], float)
        for side in (1.0, -1.0):
            ya, yb = side * 0.5 * g.opening, side * (0.5 * g.opening + g.jaw_thickness)
            lo = np.array([-half, min(ya, yb), -g.jaw_length])
            hi = np.array([half, max(ya, yb), 0.0])
            pts = transform_points(T, lo + corners * (hi - lo))
            box = self._piece_boxes(cam, pts[None])
            if box[0, 2] > box[0, 0] and box[0, 3] > box[0, 1]:
                out.append(_Job(code, "box", box, dict(R=R, t=t, lo=lo, hi=hi),
                                pts[None], 0.0))
        p1 = transform_points(T, np.array([[0.0, 0.0, -g.jaw_length]]))[0]
        p0 = transform_points(T, np.array([[0.0, 0.0, -g.jaw_length - g.shaft_length]]))[0]
        # A shaft running back past the camera plane (an instrument entering from behind
        # the endoscope) is cut where its ring would reach the near plane: a piece reaching
        # behind the camera has no box and would drop the whole shaft.
        z_cut = NEAR + g.shaft_radius + 1e-6
        if p1[2] <= z_cut:
            return out
        if p0[2] < z_cut:
            p0 = p1 + (p0 - p1) * ((p1[2] - z_cut) / (p1[2] - p0[2]))
        axis = p1 - p0
        u = axis / np.linalg.norm(axis)
        ends = self._bbox(cam, np.stack([p0, p1]), pad=0)
        if ends is None:
            return out
        n = max(1, min(64, max(ends[2] - ends[0], ends[3] - ends[1]) // 48))
        ring = _ring(u, g.shaft_radius)
        f = np.linspace(0.0, 1.0, n + 1)
        along = f[:-1, None] + (f[1:] - f[:-1])[:, None] * np.linspace(0, 1, 5)[None]
        pts = (p0 + along[..., None, None] * axis + ring).reshape(n, -1, 3)
        boxes = self._piece_boxes(cam, pts)
        ok = (boxes[:, 2] > boxes[:, 0]) & (boxes[:, 3] > boxes[:, 1])
        idx = np.flatnonzero(ok)
        c, L = float(u @ p0), float(np.linalg.norm(axis))
        ends_k = np.stack([p0 + f[:-1, None] * axis, p0 + f[1:, None] * axis], axis=1)
        out.append(_Job(code, "cylinder", boxes[idx], dict(
            P0=np.repeat(p0[None], len(idx), axis=0), U=np.repeat(u[None], len(idx), axis=0),
            r=g.shaft_radius, N0=None, c0=c + f[idx] * L, N1=None, c1=c + f[idx + 1] * L),
            ends_k[idx], g.shaft_radius, ("P0", "U", "c0", "c1")))
        if ok[-1]:
            out.append(_Job(code, "disc", boxes[-1:], dict(C=p1[None], N=u[None],
                                                           r=g.shaft_radius),
                            ends_k[-1:], g.shaft_radius))
        return out

    def _needle_truth(self, cam: CameraModel, nd: NeedleObject, T_cam_needle: np.ndarray,
                      layer: _Layer | None, late: np.ndarray | None) -> NeedleTruth:
        """Projection of K arc points and their visibility: the supersample nearest each
        point's projection must not belong to another object nearer than the point (the
        wire's own surface does not count), the ray to the point must not meet a pad
        first, and no field or rod drawn over the layer may cover the point's pixel by
        more than half."""
        K = self.needle_points
        phi = np.linspace(0.0, nd.needle.arc, K)
        pc = transform_points(T_cam_needle, nd.needle.points(K))
        uv = cam.project(pc)
        vis = cam.in_image(uv) & (pc[:, 2] > NEAR)
        idx = np.flatnonzero(vis)
        if len(idx) and layer is not None and layer.own.size:
            s = layer.s
            hgt, wid = layer.own.shape
            j = np.floor((uv[idx, 0] - layer.x0 + 0.5) * s).astype(int)
            i = np.floor((uv[idx, 1] - layer.y0 + 0.5) * s).astype(int)
            inb = (i >= 0) & (i < hgt) & (j >= 0) & (j < wid)
            ii, jj = np.clip(i, 0, hgt - 1), np.clip(j, 0, wid - 1)
            own = layer.own[ii, jj]
            other = inb & (own != 0) & (own != layer.codes[nd.name])
            nearer = layer.inv[ii, jj] > 1.0 / pc[idx, 2]
            vis[idx[other & nearer]] = False
        idx = np.flatnonzero(vis)
        if len(idx) and layer is not None:
            x, y, z = pc[idx, 0] / pc[idx, 2], pc[idx, 1] / pc[idx, 2], pc[idx, 2]
            for pad, T, _ in layer.pads:
                vis[idx[_pad_in_front(pad, T, x, y, z)]] = False
        idx = np.flatnonzero(vis)
        if len(idx) and late is not None:
            ui = np.clip(np.rint(uv[idx, 0]).astype(int), 0, cam.width - 1)
            vi = np.clip(np.rint(uv[idx, 1]).astype(int), 0, cam.height - 1)
            vis[idx[late[vi, ui]]] = False
        return NeedleTruth(T_cam_needle=T_cam_needle, phi=phi, points_px=uv, visible=vis)


# -- ray casting of needle and gripper pieces -------------------------------------------
# Rays are d = (x, y, 1) in the camera frame (x, y: undistorted normalised coordinates,
# arrays m x H x W, one slab per piece), so a hit at ``lam`` d has depth ``lam`` along the
# optical axis. Each caster returns (hit, lam, cos): cos is the cosine between the surface
# normal and the ray, from which the layer shades the samples it keeps (``_shade``);
# parameters come per piece (leading axis m) unless scalar.

def _state_key(T_ref: Mapping[str, np.ndarray], T_obj: Mapping[str, np.ndarray],
               grippers: tuple[Gripper, ...]) -> bytes:
    """What a camera's noise-free render depends on beyond the (fixed) scene: every
    placement's and object's pose and every jaw gap, as exact bytes."""
    parts = [np.ascontiguousarray(T, dtype=float).tobytes()
             for poses in (T_ref, T_obj) for _, T in sorted(poses.items())]
    parts.append(np.array([g.opening for g in grippers], dtype=float).tobytes())
    return b"".join(parts)


def _col(a: np.ndarray | float) -> np.ndarray:
    """Per-piece values (m,) as float32 (m, 1, 1), for broadcasting over a piece's slab."""
    return np.asarray(a, np.float32).reshape(-1, 1, 1)


def _shade(material: tuple[float, float, float, bool], cos: np.ndarray) -> np.ndarray:
    """Level (DN, unit illumination) of samples whose normal makes ``cos`` with the ray.

    ``material`` = (level, specular, shininess, rod). Lit from the camera: a dim base
    ``level (0.5 + 0.5 cos)`` plus a Blinn-Phong highlight; with the light at the camera the
    half vector is the viewing direction, so the highlight is ``specular cos**shininess``.
    ``rod``: the rods' shading, ``level (0.55 + 0.45 cos)``.
    """
    level, specular, shininess, rod = material
    cos = np.clip(cos, 0.0, 1.0)
    if rod:
        return np.float32(level) * (0.55 + 0.45 * cos)
    out = np.float32(level) * (0.5 + 0.5 * cos)
    if specular > 0:
        out += np.float32(specular) * cos ** np.float32(shininess)
    return out


def _cast_cylinder(x: np.ndarray, y: np.ndarray, *, P0, U, r, N0, c0, N1, c1):
    """Front surface of the cylinder of radius ``r`` about the line through ``P0`` along
    unit ``U``, kept between the planes ``N0 . X >= c0`` and ``N1 . X < c1`` (``N0 = N1 =
    None``: both planes across the axis, normal ``U``).

    With ``m = P0 - (P0 . U) U`` (the axis's offset from the camera, across the axis) and
    ``w = m x U``, ``|lam d_perp - m|^2 = r^2`` has ``lam = (d . m - sqrt(q)) / a`` with
    ``a = |d|^2 - (d . U)^2`` and ``q = r^2 a - (d . w)^2`` (Lagrange's identity: no
    cancellation between two large terms, which float32 could not afford at 0.1 m for a
    0.5 mm wire). The normal's cosine to the ray is ``sqrt(q) / (r |d|)``.
    """
    P0, U = np.asarray(P0, float), np.asarray(U, float)
    M = P0 - (P0 * U).sum(1, keepdims=True) * U
    W = np.cross(M, U)
    dd = x * x + y * y + 1.0
    du = _col(U[:, 0]) * x + _col(U[:, 1]) * y + _col(U[:, 2])
    dm = _col(M[:, 0]) * x + _col(M[:, 1]) * y + _col(M[:, 2])
    dw = _col(W[:, 0]) * x + _col(W[:, 1]) * y + _col(W[:, 2])
    a = dd - du * du
    q = np.float32(r * r) * a - dw * dw
    with np.errstate(invalid="ignore", divide="ignore"):
        sq = np.sqrt(q)
        lam = (dm - sq) / a
        cos = sq / (np.float32(r) * np.sqrt(dd))
    if N0 is None:     # planes across the axis (a rod's pieces): N0 = N1 = U
        e0 = e1 = du
    else:
        N0, N1 = np.asarray(N0, float), np.asarray(N1, float)
        e0 = _col(N0[:, 0]) * x + _col(N0[:, 1]) * y + _col(N0[:, 2])
        e1 = _col(N1[:, 0]) * x + _col(N1[:, 1]) * y + _col(N1[:, 2])
    hit = (q > 0) & (lam * e0 >= _col(c0)) & (lam * e1 < _col(c1))
    return hit, lam, cos


def _cast_disc(x: np.ndarray, y: np.ndarray, *, C, N, r):
    """Flat disc of radius ``r`` centred at ``C`` with unit normal ``N`` (an end cap)."""
    C, N = np.asarray(C, float), np.asarray(N, float)
    dn = _col(N[:, 0]) * x + _col(N[:, 1]) * y + _col(N[:, 2])
    with np.errstate(invalid="ignore", divide="ignore"):
        lam = _col((C * N).sum(1)) / dn
        cos = np.abs(dn) / np.sqrt(x * x + y * y + 1.0)
    ex, ey, ez = lam * x - _col(C[:, 0]), lam * y - _col(C[:, 1]), lam - _col(C[:, 2])
    hit = ex * ex + ey * ey + ez * ez <= np.float32(r * r)
    return hit, lam, cos


def _cast_box(x: np.ndarray, y: np.ndarray, *, R, t, lo, hi):
    """Axis-aligned box [lo, hi] of the frame whose pose in the camera is (R, t): the slab
    method in that frame; the cosine is the hit face's normal's to the ray."""
    o = -R.T @ t                                   # camera centre in the box's frame
    near = np.full(x.shape, -np.inf, np.float32)
    far = np.full(x.shape, np.inf, np.float32)
    cos = np.zeros(x.shape, np.float32)
    with np.errstate(invalid="ignore", divide="ignore"):
        for i in range(3):
            di = np.float32(R[0, i]) * x + np.float32(R[1, i]) * y + np.float32(R[2, i])
            inv_d = 1.0 / di
            t1 = np.float32(lo[i] - o[i]) * inv_d
            t2 = np.float32(hi[i] - o[i]) * inv_d
            tmin, tmax = np.minimum(t1, t2), np.maximum(t1, t2)
            entered = tmin > near
            near = np.where(entered, tmin, near)
            cos = np.where(entered, np.abs(di), cos)
            far = np.minimum(far, tmax)
        cos = cos / np.sqrt(x * x + y * y + 1.0)
    hit = (near <= far) & (near > 0)
    return hit, near, cos


_CASTERS = {"cylinder": _cast_cylinder, "disc": _cast_disc, "box": _cast_box}


def _gather(rays: np.ndarray, boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rays (x, y) of m sample boxes (m x 4, sample indices into ``rays``), padded to
    one size (m x H x W), and the mask of each box's own samples."""
    h = boxes[:, 3] - boxes[:, 1]
    w = boxes[:, 2] - boxes[:, 0]
    H, W = int(h.max()), int(w.max())
    iy = np.minimum(boxes[:, 1, None] + np.arange(H), rays.shape[0] - 1)
    ix = np.minimum(boxes[:, 0, None] + np.arange(W), rays.shape[1] - 1)
    g = rays[iy[:, :, None], ix[:, None, :]]
    valid = ((np.arange(H)[None, :, None] < h[:, None, None])
             & (np.arange(W)[None, None, :] < w[:, None, None]))
    return g[..., 0], g[..., 1], valid


def _pad_hits(pad: TissuePad, T_cam_pad: np.ndarray, rays: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where the rays (h x w x 2, contiguous float32) meet the pad's plane, in pad
    coordinates (x, y, m), and the mask of rays that hit the pad's rectangle in front of
    the camera. The plane is a homography of the normalised image (as for a field)."""
    R = T_cam_pad[:3, :3]
    o = -R.T @ T_cam_pad[:3, 3]
    Rt = R.T
    Hm = np.array([o[0] * Rt[2] - o[2] * Rt[0], o[1] * Rt[2] - o[2] * Rt[1], Rt[2]])
    xy = cv2.perspectiveTransform(np.ascontiguousarray(rays), Hm)
    hx, hy = xy[..., 0], xy[..., 1]
    dz = (np.float32(Rt[2, 0]) * rays[..., 0] + np.float32(Rt[2, 1]) * rays[..., 1]
          + np.float32(Rt[2, 2]))
    sx, sy = pad.size
    inside = (dz < 0) & (np.abs(hx) <= 0.5 * sx) & (np.abs(hy) <= 0.5 * sy)
    return inside, hx, hy


def _pad_in_front(pad: TissuePad, T_cam_pad: np.ndarray, x: np.ndarray, y: np.ndarray,
                  lam: np.ndarray) -> np.ndarray:
    """Mask of the rays d = (x, y, 1) (1-D) that meet the pad's rectangle at a depth
    between 0 and ``lam`` (m): what lies at ``lam`` on them is hidden by the pad."""
    R, t = T_cam_pad[:3, :3], T_cam_pad[:3, 3]
    n = R[:, 2]
    x, y = x.astype(float), y.astype(float)
    with np.errstate(divide="ignore", invalid="ignore"):
        lp = float(n @ t) / (n[0] * x + n[1] * y + n[2])
    ex, ey, ez = lp * x - t[0], lp * y - t[1], lp - t[2]
    px = R[0, 0] * ex + R[1, 0] * ey + R[2, 0] * ez
    py = R[0, 1] * ex + R[1, 1] * ey + R[2, 1] * ez
    sx, sy = pad.size
    return ((lp > 0) & (lp < lam) & (np.abs(px) <= 0.5 * sx) & (np.abs(py) <= 0.5 * sy))


def _inside(x: np.ndarray, y: np.ndarray, edges: list[np.ndarray]) -> np.ndarray:
    """Mask of rays d = (x, y, 1) on the inner side of every plane through the camera
    centre with normal ``edges[k]`` (a convex polygon's cone)."""
    m = None
    for n in edges:
        e = cv2.addWeighted(x, float(n[0]), y, float(n[1]), float(n[2]))
        m = e if m is None else np.minimum(m, e, out=m)
    return m >= 0


def _clip_box(b: np.ndarray, box: tuple[int, int, int, int]) -> tuple[int, int, int, int]:
    """Box ``b`` clipped to ``box``; empty (x1 <= x0) if they do not meet."""
    x0, y0 = max(int(b[0]), box[0]), max(int(b[1]), box[1])
    x1, y1 = min(int(b[2]), box[2]), min(int(b[3]), box[3])
    return (x0, y0, x1, y1) if (x1 > x0 and y1 > y0) else (0, 0, 0, 0)


def _plane_xy(T_cam_pad: np.ndarray, x: np.ndarray, y: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray]:
    """Pad-frame (x, y) where the rays d = (x, y, 1) meet the pad's plane z = 0 (a
    homography of the normalised image, as for a field)."""
    Rt = T_cam_pad[:3, :3].T
    o = -Rt @ T_cam_pad[:3, 3]
    H = np.array([o[0] * Rt[2] - o[2] * Rt[0], o[1] * Rt[2] - o[2] * Rt[1], Rt[2]])
    w = cv2.addWeighted(x, float(H[2, 0]), y, float(H[2, 1]), float(H[2, 2]))
    hx = cv2.addWeighted(x, float(H[0, 0]), y, float(H[0, 1]), float(H[0, 2]))
    hy = cv2.addWeighted(x, float(H[1, 0]), y, float(H[1, 1]), float(H[1, 2]))
    with np.errstate(divide="ignore", invalid="ignore"):
        return hx / w, hy / w


def _near_segment(x: np.ndarray, y: np.ndarray, seg, half_width: float) -> np.ndarray:
    """Mask of points (x, y) within ``half_width`` of the segment ``seg`` ((x0, y0),
    (x1, y1)): a stroke with round ends."""
    (ax, ay), (bx, by) = seg
    ex, ey = bx - ax, by - ay
    L2 = ex * ex + ey * ey
    px, py = x - np.float32(ax), y - np.float32(ay)
    if L2 > 0:
        t = np.clip((px * np.float32(ex) + py * np.float32(ey)) * np.float32(1.0 / L2),
                    0.0, 1.0)
        px = px - t * np.float32(ex)
        py = py - t * np.float32(ey)
    return px * px + py * py <= np.float32(half_width * half_width)


def _check_objects(scene: Scene) -> None:
    """Refuse needle-driving objects the renderer cannot draw (RenderError)."""
    def positive(what: str, **values: float) -> None:
        bad = {k: v for k, v in values.items() if not (math.isfinite(v) and v > 0)}
        if bad:
            raise RenderError(f"{what}: must be finite and > 0: {bad}")

    for nd in scene.needles:
        positive(f"needle {nd.name!r}", shininess=nd.shininess)
        if not (nd.specular >= 0 and nd.level >= 0):
            raise RenderError(f"needle {nd.name!r}: level and specular must be >= 0")
        if not (math.isfinite(nd.thread_length) and nd.thread_length >= 0):
            raise RenderError(f"needle {nd.name!r}: thread_length must be >= 0 m (0: no "
                              f"thread), got {nd.thread_length}")
        if nd.thread_length > 0:
            positive(f"needle {nd.name!r}", thread_diameter=nd.thread_diameter,
                     thread_bend_radius=nd.thread_bend_radius)
            if not nd.thread_level >= 0:
                raise RenderError(f"needle {nd.name!r}: thread_level must be >= 0")
            if not (math.isfinite(nd.thread_tilt) and abs(nd.thread_tilt) <= math.pi / 2):
                raise RenderError(f"needle {nd.name!r}: thread_tilt must be within +-pi/2 "
                                  f"rad, got {nd.thread_tilt}")
    for pad in scene.pads:
        positive(f"pad {pad.name!r}", size_x=pad.size[0], size_y=pad.size[1],
                 incision_width=pad.incision_width)
    for g in scene.grippers:
        positive(f"gripper {g.name!r}", jaw_length=g.jaw_length, jaw_width=g.jaw_width,
                 jaw_thickness=g.jaw_thickness, shaft_radius=g.shaft_radius,
                 shaft_length=g.shaft_length)
        if not (math.isfinite(g.opening) and g.opening >= 0):
            raise RenderError(f"gripper {g.name!r}: opening must be >= 0, got {g.opening}")
