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
so the same scene, seed and frame give the same bytes.

Ground truth per camera: each field's pose and the exact projection of every visible
chessboard corner (in the image, printed face toward the camera, not under a blot, not
hidden by a nearer object), with its obliquity.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from oralnav.control.camera import CameraModel
from oralnav.control.geometry import transform_points
from oralnav.control.markers import CylinderSurface, MarkerField, PlaneSurface

from .scene import Imaging, Placement, Rod, Scene

#: Finest texture: pixels per chessboard square. Coarser mip levels halve it down to 4.
MAX_TEXELS_PER_SQUARE = 512
MIN_TEXELS_PER_SQUARE = 4


class RenderError(ValueError):
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
class Frame:
    """One rendered frame: an image per camera, ground truth, and how long each took (s)."""

    images: dict[str, np.ndarray]
    T_ref_field: dict[str, np.ndarray]
    truth: dict[str, dict[str, FieldTruth]]
    frame: int
    seed: int
    render_s: dict[str, float] = field(default_factory=dict)

    def truth_json(self, reference: str, image_files: Mapping[str, str] | None = None) -> dict:
        """The ``truth.json`` document (see docs/formats.md)."""
        cams = {}
        for cam, fields in self.truth.items():
            entry: dict = {"size": [int(self.images[cam].shape[1]),
                                    int(self.images[cam].shape[0])]}
            if image_files and cam in image_files:
                entry["image"] = image_files[cam]
            entry["fields"] = {name: t.to_json() for name, t in fields.items()}
            cams[cam] = entry
        return {"units": {"length": "m", "pixel": "px, centre of top-left pixel at (0, 0)"},
                "reference": reference, "frame": self.frame, "seed": self.seed,
                "fields": {n: {"T_ref_field": T.tolist()} for n, T in self.T_ref_field.items()},
                "cameras": cams}


@dataclass
class _Patch:
    x0: int
    y0: int
    value: np.ndarray      # premultiplied level (DN * coverage), h x w float32
    alpha: np.ndarray      # coverage 0..1, h x w float32
    depth: float           # metres along the optical axis, for ordering
    owner: int


class _CameraState:
    """Per-camera precomputation: the ray map, the illumination and the background."""

    def __init__(self, cam: CameraModel, imaging: Imaging) -> None:
        self.cam = cam
        w, h = cam.size
        u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
        if cam.has_distortion:
            rays = cam.ray_map()
            if np.isnan(rays).any():
                bad = int(np.isnan(rays).any(axis=-1).sum())
                raise RenderError(f"camera {cam.name!r}: the distortion model does not invert "
                                  f"at {bad} pixels; check its dist coefficients")
        else:
            K = cam.K
            rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]], axis=-1)
        self.rays = np.ascontiguousarray(rays, dtype=np.float32)
        gx, gy = imaging.illumination_gradient
        illum = 1.0 + gx * (u / w - 0.5) + gy * (v / h - 0.5)
        self.illumination = np.clip(illum, 0.0, None).astype(np.float32)
        self.background = (imaging.background * self.illumination).astype(np.float32)

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


class SceneRenderer:
    """Renders a :class:`~oralnav.sim.scene.Scene` into images with ground truth.

    The constructor only records the scene; per-camera ray maps and textures are built on
    first use and kept. ``render`` is thread-safe to call from one worker thread at a time.
    """

    def __init__(self, scene: Scene) -> None:
        self.scene = scene
        self._cams: dict[str, _CameraState] = {}
        self._tex: dict[str, _Texture] = {}
        for p in scene.placements:
            if not p.field.renderable:
                raise RenderError(
                    f"placement {p.name!r}: field {p.field.name!r} has a points surface, "
                    "which is known only at its corners and cannot be rendered")
        names = {p.name for p in scene.placements}
        for b in scene.blots:
            if b.placement not in names:
                raise RenderError(f"blot {b.name!r}: unknown placement {b.placement!r}")

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
               cameras: tuple[str, ...] | None = None) -> Frame:
        """Render every camera (or ``cameras``) of the rig.

        ``poses`` overrides placements' ``T_ref_field`` by placement name (the simulated
        cell moves fields this way); ``frame`` selects the noise draw.
        """
        poses = dict(poses or {})
        unknown = set(poses) - {p.name for p in self.scene.placements}
        if unknown:
            raise RenderError(f"poses given for unknown placements {sorted(unknown)}")
        T_ref = {p.name: np.asarray(poses.get(p.name, p.T_ref_field), dtype=float)
                 for p in self.scene.placements}
        images, truth, times = {}, {}, {}
        names = cameras or tuple(self.scene.rig.names)
        for cam_name in names:
            t0 = time.perf_counter()
            # the noise draw belongs to the camera, whichever cameras this call renders
            ci = self.scene.rig.names.index(self.scene.rig[cam_name].name)
            img, tr = self._render_camera(cam_name, T_ref, frame, ci)
            images[cam_name], truth[cam_name] = img, tr
            times[cam_name] = time.perf_counter() - t0
        return Frame(images=images, T_ref_field=T_ref, truth=truth, frame=frame,
                     seed=self.scene.seed, render_s=times)

    # -- one camera -------------------------------------------------------------------
    def _render_camera(self, cam_name: str, T_ref: dict[str, np.ndarray], frame: int,
                       cam_index: int) -> tuple[np.ndarray, dict[str, FieldTruth]]:
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

        signal = st.background.copy()
        owner = np.zeros(signal.shape, np.uint8)
        for p in sorted(patches, key=lambda p: -p.depth):
            h, w = p.alpha.shape
            sl = (slice(p.y0, p.y0 + h), slice(p.x0, p.x0 + w))
            illum = st.illumination[sl]
            sig = signal[sl]
            sig *= 1.0 - p.alpha
            sig += p.value * illum
            owner[sl][p.alpha > 0.5] = p.owner
        if im.blur_sigma_px > 0 and patches:
            self._blur(signal, patches, im.blur_sigma_px)
        if im.noisy:
            self._add_noise(signal, frame, cam_index)
        np.maximum(signal, 0.0, out=signal)  # convertScaleAbs would mirror negatives
        image = cv2.convertScaleAbs(signal)  # rounds and saturates to 0..255
        truth = {}
        for k, pl in enumerate(self.scene.placements):
            tr = self._field_truth(cam, pl, T_cam_ref @ T_ref[pl.name], owner, k + 1)
            if tr is not None:
                truth[pl.name] = tr
        return image, truth

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
        e1 = np.cross(u, [1.0, 0.0, 0.0])
        if np.linalg.norm(e1) < 0.1:
            e1 = np.cross(u, [0.0, 1.0, 0.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(u, e1)
        ang = np.linspace(0, 2 * np.pi, 16, endpoint=False)
        ring = rod.radius * (np.cos(ang)[:, None] * e1 + np.sin(ang)[:, None] * e2)
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
