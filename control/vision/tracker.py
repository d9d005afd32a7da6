"""Frame-to-frame tracking of every marker field seen by a camera set.

:class:`Tracker` turns one set of synchronous images (``{camera name: mono8 image}``) into
field poses in the rig's reference frame. Consecutive calls form a video: what the tracker
keeps between them decides only *where it looks*, never the pose itself, which comes from
the current frame's corners alone (as in the paper, section III.C).

Search stages, per field (docs/tracking.md):

- ``full``: find and decode markers over the whole image (acquisition, or a lost field);
- ``roi``: the same inside the box where the last pose puts the field (eqs. 18-19), grown by
  a motion margin;
- ``predict``: project every model corner through the constant-velocity prediction of the
  pose, refine them in place with ``cornerSubPix``, and check the identity by reading the
  markers' bit cells where the pose puts them (a lock one square off reads wrong bits).

``mode`` caps the stage: ``"full"`` always searches the whole image, ``"roi"`` uses boxes,
``"predict"`` (default) tracks corners and falls back to boxes, then to the whole image.

ArUco rigid bodies (:mod:`.rigid_body`, tags with known 3D corners) are tracked beside the
fields: each frame, OpenCV's ArUco detector searches whole images once per body dictionary,
and :func:`.rigid_body.estimate_body` poses each body over every camera that sees it. They
keep no video state, and their estimates join the fields' under the bodies' names.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Literal

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from oralnav.control.errors import MarkerFieldError
from oralnav.control.geometry import invert
from oralnav.control.vision.camera import CameraModel, Rig
from oralnav.control.vision.detection import (
    BoardLayout,
    DetectionError,
    FieldCorners,
    QuadParams,
    check_image,
    decoder_for,
    detect_fields,
    refine_corners,
)
from oralnav.control.vision.markers import MarkerField
from oralnav.control.vision.pose import (
    DEFAULT_WEIGHTING,
    Observation,
    PoseEstimate,
    Weighting,
    corner_normals,
    estimate_pose,
    pose_covariance,
)
from oralnav.control.vision.rigid_body import (
    BodyEstimate,
    RigidBody,
    confusable_tags,
    correction_bits,
    detect_tag_list,
    estimate_body,
)

Method = Literal["nvgba", "ba", "pnp", "opencv"]
Mode = Literal["full", "roi", "predict"]
METHODS: tuple[str, ...] = ("nvgba", "ba", "pnp", "opencv")
MODES: tuple[str, ...] = ("full", "roi", "predict")


@dataclass(frozen=True)
class TrackerSettings:
    """Tuning of the tracker; the defaults suit the shipped cell.

    Attributes:
        max_rms_px: an estimate whose reprojection RMS exceeds this is not reported.
        min_corners: fewest corner observations for a reported pose.
        roi_margin: ROI growth on each side, as a fraction of the predicted box size.
        roi_margin_px: plus this many pixels on each side.
        verify_score: fraction of a marker's bit cells that must read as expected.
        verify_fraction: fraction of checked markers that must pass in predictive tracking.
        max_position_sigma_mm: an estimate whose covariance gives the field origin a
            standard deviation over this along any axis is not reported (an ill-posed fit:
            a mirrored pose of a thin corner set had 1.3 mm).
        max_rotation_sigma_deg: likewise for the rotation's standard deviation (0.8 deg
            there; the 16 mm end-effector field has 0.07 deg).
        max_obliquity_deg: predictive tracking skips corners seen more obliquely than this
            (angle between the surface normal and the line of sight); their refined
            positions are biased (0.5-0.8 px at 63 deg on the shipped cylinders).
        quads: settings of the marker search.
        body_max_rms_px: a rigid body's estimate whose reprojection RMS exceeds this is not
            reported (the peer's real bodies fit to 0.6-1.1 px: printed-tag model errors).
        body_max_position_sigma_mm, body_max_rotation_sigma_deg: the covariance gate for
            bodies. Looser than the fields': one 50 mm tag at 210 mm reports 0.7-1.5 mm and
            0.5-2.0 deg (peer output.avi, the covariance of ``pose.pixel_variance`` with the
            tags' corner noise), the peer's 12-tag reference 0.9 mm and 0.4 deg.
        body_max_tag_error_px, body_max_tag_error_rel: a body's tag agrees with the others
            when its RMS reprojection error is at most the larger of these (px, fraction of
            its side in pixels); see :func:`.rigid_body.estimate_body_pose`.
    """

    max_rms_px: float = 1.0
    min_corners: int = 6
    roi_margin: float = 0.25
    roi_margin_px: int = 24
    verify_score: float = 0.9
    verify_fraction: float = 0.6
    max_position_sigma_mm: float = 0.5
    max_rotation_sigma_deg: float = 0.5
    max_obliquity_deg: float = 60.0
    quads: QuadParams = QuadParams()
    body_max_rms_px: float = 2.0
    body_max_position_sigma_mm: float = 5.0
    body_max_rotation_sigma_deg: float = 5.0
    body_max_tag_error_px: float = 4.0
    body_max_tag_error_rel: float = 0.1


@dataclass
class _FieldModel:
    """Per-field constants the tracker precomputes (all in the field frame, metres)."""

    field: MarkerField
    layout: BoardLayout
    normals: np.ndarray          # eqs. 9-13 normals, for NVG-BA weights
    face_normals: np.ndarray     # exact surface normals where known, else ``normals``
    step_rows: np.ndarray        # (N, 2): row of the x and the y grid neighbour, or -1
    marker_quads: np.ndarray     # (M, 4, 3) marker corners on the surface
    marker_ids: np.ndarray       # (M,)
    marker_normals: np.ndarray   # (M, 3) surface normal at each marker's centre
    signed: bool                 # normals point out of the printed face (else sign unknown)

    @classmethod
    def of(cls, fld: MarkerField) -> _FieldModel:
        layout = BoardLayout.of(fld)
        nx = fld.squares[0] - 1
        step = np.full((len(fld.corner_ids), 2), -1, dtype=int)
        for r, cid in enumerate(fld.corner_ids):
            cx, cy = int(cid) % nx, int(cid) // nx
            for k, (dx, dy) in enumerate(((1, 0), (0, 1))):
                x2, y2 = cx + dx, cy + dy
                if x2 >= nx or y2 >= fld.squares[1] - 1:
                    x2, y2 = cx - dx, cy - dy
                step[r, k] = fld.corner_index.get(y2 * nx + x2, -1) if x2 >= 0 and y2 >= 0 else -1
        if fld.renderable:
            quads3 = fld.sheet_to_field(layout.marker_flat)
        else:
            quads3 = _interpolate_points_field(fld, layout.marker_flat)
        normals = corner_normals(fld)
        if fld.renderable:
            face = fld.sheet_normals(fld.corners_flat)
            m_normals = fld.sheet_normals(layout.marker_flat.mean(axis=1))
        else:
            face = normals
            centres = quads3.mean(axis=1)
            nearest = np.argmin(np.linalg.norm(
                centres[:, None, :] - fld.corners[None, :, :], axis=2), axis=1)
            m_normals = normals[nearest]
        return cls(fld, layout, normals, face, step, quads3, fld.marker_ids, m_normals,
                   fld.renderable)

    def facing_cos(self, normals_cam: np.ndarray, p_cam: np.ndarray) -> np.ndarray:
        """Cosine between each surface normal and the direction to the camera (camera
        frame); negative for a surface turned away, where the normals' sign is known."""
        ray = p_cam / np.linalg.norm(p_cam, axis=1, keepdims=True)
        cos = -np.sum(normals_cam * ray, axis=1)
        return cos if self.signed else np.abs(cos)


def _interpolate_points_field(fld: MarkerField, flat: np.ndarray) -> np.ndarray:
    """3D positions of flat-sheet points on a points field: an affine map fitted to the six
    nearest known corners of each point (the model is only known at its corners)."""
    out = np.empty(flat.shape[:-1] + (3,))
    known_flat, known = fld.corners_flat, fld.corners
    pts = flat.reshape(-1, 2)
    res = out.reshape(-1, 3)
    for i, p in enumerate(pts):
        near = np.argsort(np.linalg.norm(known_flat - p, axis=1))[:6]
        A = np.concatenate([known_flat[near], np.ones((len(near), 1))], axis=1)
        coef, *_ = np.linalg.lstsq(A, known[near], rcond=None)
        res[i] = np.append(p, 1.0) @ coef
    return out


def _check_bodies(bodies: Sequence[RigidBody], fields: Sequence[MarkerField]
                  ) -> dict[str, RigidBody]:
    """The bodies by name, once checked against the fields and each other: distinct names,
    and no tag that OpenCV's detector (with the error correction it applies to the body's
    dictionary) could read as a field marker or as another body's tag."""
    out: dict[str, RigidBody] = {}
    field_names = {f.name for f in fields}
    for b in bodies:
        if not isinstance(b, RigidBody):
            raise MarkerFieldError(f"bodies must be RigidBody objects, got {type(b).__name__}")
        if b.name in field_names:
            raise MarkerFieldError(f"rigid body {b.name!r} has the name of a marker field; "
                                   "names must be unique across fields and bodies")
        if b.name in out:
            raise MarkerFieldError(f"rigid body name {b.name!r} is given twice")
        bits = correction_bits(b.dictionary)
        for f in fields:
            pairs = confusable_tags(b.dictionary, b.ids, f.dictionary, f.marker_ids, bits)
            if pairs:
                t, m = pairs[0]
                raise MarkerFieldError(
                    f"rigid body {b.name!r}: tag {t} of {b.dictionary} reads as marker {m} "
                    f"of field {f.name!r} ({f.dictionary}); {len(pairs)} such tag(s): use "
                    "another dictionary or other ids for the body")
        for other in out.values():
            pairs = confusable_tags(b.dictionary, b.ids, other.dictionary, other.ids,
                                    max(bits, correction_bits(other.dictionary)))
            if pairs:
                t, m = pairs[0]
                raise MarkerFieldError(
                    f"rigid bodies {b.name!r} and {other.name!r} share tags: {b.dictionary} "
                    f"{t} reads as {other.dictionary} {m}")
        out[b.name] = b
    return out


@dataclass
class _FieldState:
    T: np.ndarray | None = None          # last reported T_ref_field
    T_prev: np.ndarray | None = None     # the one before (constant-velocity prediction)


@dataclass
class FrameTiming:
    """Where one :meth:`Tracker.track` call spent its time (milliseconds).

    ``recognition`` covers marker search, decoding, corner refinement and identity checks;
    ``pose`` PnP and (NVG-)BA; ``roi`` the prediction of boxes and corners from last poses.
    """

    total: float = 0.0
    recognition: float = 0.0
    pose: float = 0.0
    roi: float = 0.0
    stages: dict[str, str] = field(default_factory=dict)

    def as_dict(self) -> dict:
        return {"total": self.total, "recognition": self.recognition, "pose": self.pose,
                "roi": self.roi, "stages": dict(self.stages)}


class Tracker:
    """Tracks marker fields over a rig's cameras; see the module docstring.

    Args:
        rig: the cameras (names, intrinsics, poses in the reference frame).
        fields: the marker fields to look for (unique names, disjoint id blocks).
        method: ``"nvgba"`` (default), ``"ba"``, ``"pnp"`` or ``"opencv"`` (OpenCV's stock
            ``CharucoDetector`` + ``solvePnP`` per camera, the baseline).
        mode: ``"predict"`` (default), ``"roi"`` or ``"full"``.
        weighting: NVG-BA obliquity weighting (see :mod:`.pose`).
        settings: thresholds and search settings.
        bodies: ArUco rigid bodies to track as well (``method``, ``mode`` and ``weighting``
            do not apply to them). Their names must differ from the fields' and from each
            other's, and no body tag may be one that a detector could read as a field
            marker or another body's tag (:func:`.rigid_body.confusable_tags`), so bodies
            use other dictionaries or ids than the fields. At least one field or body.

    Raises:
        ValueError: a bad method, mode or name; :class:`MarkerFieldError` (a ValueError)
            for bodies whose names or tags collide with the fields' or each other's.
    """

    def __init__(self, rig: Rig, fields: Sequence[MarkerField], method: Method = "nvgba",
                 mode: Mode = "predict", weighting: Weighting = DEFAULT_WEIGHTING,
                 settings: TrackerSettings = TrackerSettings(),
                 bodies: Sequence[RigidBody] = ()):
        if method not in METHODS:
            raise ValueError(f"unknown method {method!r}; expected one of {', '.join(METHODS)}")
        if mode not in MODES:
            raise ValueError(f"unknown mode {mode!r}; expected one of {', '.join(MODES)}")
        names = [f.name for f in fields]
        if len(set(names)) != len(names):
            raise ValueError(f"field names must be unique, got {names}")
        bodies = list(bodies)
        if not fields and not bodies:
            raise ValueError("a tracker needs at least one marker field or rigid body")
        self.bodies: dict[str, RigidBody] = _check_bodies(bodies, fields)
        self.rig = rig
        self.fields = {f.name: f for f in fields}
        self.method: Method = method
        self.mode: Mode = mode
        self.weighting: Weighting = weighting
        self.settings = settings
        self._models = {f.name: _FieldModel.of(f) for f in fields}
        self._layouts = {n: m.layout for n, m in self._models.items()}
        self._state = {n: _FieldState() for n in self.fields}
        self._opencv: dict[str, cv2.aruco.CharucoDetector] = {}
        for d in {f.dictionary for f in fields}:
            decoder_for(d)  # build code tables now, not in the first frame
        self._body_dictionaries = sorted({b.dictionary for b in bodies})
        self.last_timing = FrameTiming()

    def reset(self) -> None:
        """Forget every field's last pose: the next frame searches whole images."""
        self._state = {n: _FieldState() for n in self.fields}

    def restore(self, last: Mapping[str, np.ndarray],
                before: Mapping[str, np.ndarray]) -> None:
        """Remember what :meth:`track` would after a frame that found ``last`` following
        one that found ``before`` (field -> ``T_ref_field``, 4x4; a field absent was not
        found). A replay that skips frames (a decimated recording) or starts mid-video
        then predicts exactly as the live tracker did, from the poses it reported."""
        state = {}
        for name in self.fields:
            T, T_prev = last.get(name), before.get(name)
            # a field lost in the last frame is searched afresh, whatever came before
            state[name] = _FieldState() if T is None else _FieldState(
                np.array(T, dtype=float).reshape(4, 4),
                None if T_prev is None else np.array(T_prev, dtype=float).reshape(4, 4))
        self._state = state

    # -- the frame ---------------------------------------------------------------------
    def _check_images(self, images: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        if not isinstance(images, Mapping) or not images:
            raise DetectionError("track() needs a non-empty mapping camera name -> image")
        out = {}
        for name, img in images.items():
            if name not in self.rig.cameras:
                raise DetectionError(
                    f"unknown camera {name!r}; the rig has {', '.join(self.rig.names)}")
            out[name] = check_image(img, self.rig[name].size, what=f"camera {name!r}")
        return out

    def track(self, images: Mapping[str, np.ndarray]) -> dict[str, PoseEstimate]:
        """Estimate every field and body visible in ``images`` (``{camera name: mono8
        image}``).

        Returns ``{field or body name: PoseEstimate}`` (a body's is a
        :class:`.rigid_body.BodyEstimate`); those not found are absent. Raises
        :class:`DetectionError` for an unknown camera or an image of the wrong size/dtype.
        """
        t0 = time.perf_counter()
        imgs = self._check_images(images)
        timing = FrameTiming()
        if self.method == "opencv":
            out = self._track_opencv(imgs, timing)
        else:
            out = self._track_own(imgs, timing)
        for name in self.fields:
            st = self._state[name]
            est = out.get(name)
            if est is None:
                st.T = st.T_prev = None
            else:
                st.T_prev, st.T = st.T, est.T_ref_field
        if self.bodies:
            out.update(self._track_bodies(imgs, timing))
        timing.total = (time.perf_counter() - t0) * 1e3
        self.last_timing = timing
        return out

    def _predicted_pose(self, name: str) -> np.ndarray | None:
        st = self._state[name]
        if st.T is None:
            return None
        if st.T_prev is None:
            return st.T
        # Constant velocity in the reference frame (the last motion T T_prev^-1 once more),
        # its rotation made a proper one again through Rotation (the nearest rotation).
        # Each estimate starts from this prediction and keeps its deviation from a
        # rotation (BA turns it by a rotation), so the bare product fed its rounding back
        # and grew it 2.4 times a frame: past 1e-9 off orthonormal after 20 frames, 1e-2
        # after 40 (issue 30).
        T = st.T @ invert(st.T_prev) @ st.T
        T[:3, :3] = Rotation.from_matrix(T[:3, :3]).as_matrix()
        return T

    def _accept(self, est: PoseEstimate | None) -> PoseEstimate | None:
        s = self.settings
        if est is None or not est.within(s.max_rms_px, s.max_position_sigma_mm,
                                         s.max_rotation_sigma_deg, s.min_corners):
            return None
        return est

    def _track_own(self, imgs: dict[str, np.ndarray], timing: FrameTiming
                   ) -> dict[str, PoseEstimate]:
        out: dict[str, PoseEstimate] = {}
        need_full: list[str] = []
        for name, model in self._models.items():
            T_pred = self._predicted_pose(name)
            if T_pred is None or self.mode == "full":
                need_full.append(name)
                continue
            est = None
            if self.mode == "predict":
                est = self._predict_field(model, T_pred, imgs, timing)
                if est is not None:
                    timing.stages[name] = "predict"
            if est is None:
                est = self._roi_field(model, T_pred, imgs, timing)
                if est is not None:
                    timing.stages[name] = "roi"
            if est is None:
                need_full.append(name)
            else:
                out[name] = est
        if need_full:
            flds = [self.fields[n] for n in need_full]
            t = time.perf_counter()
            found = {cam: detect_fields(img, flds, self.settings.quads, layouts=self._layouts)
                     for cam, img in imgs.items()}
            timing.recognition += (time.perf_counter() - t) * 1e3
            for name in need_full:
                est = self._estimate(name, {c: f[name] for c, f in found.items() if name in f},
                                     None, timing)
                if est is not None:
                    out[name] = est
                    timing.stages[name] = "full"
        return out

    def _estimate(self, name: str, corners: Mapping[str, FieldCorners],
                  T_guess: np.ndarray | None, timing: FrameTiming) -> PoseEstimate | None:
        fld = self.fields[name]
        obs = []
        for cam, fc in corners.items():
            rows = np.array([fld.corner_index.get(int(i), -1) for i in fc.ids], dtype=int)
            ok = rows >= 0  # a points field may not model every printed corner
            if np.any(ok):
                obs.append(Observation(self.rig[cam], rows[ok], fc.px[ok]))
        if not obs:
            return None
        t = time.perf_counter()
        method = self.method if self.method != "opencv" else "pnp"
        est = estimate_pose(fld, obs, method, self.weighting, self._models[name].normals,
                            T_guess=T_guess)
        if est is not None:
            est = self._without_grazing(self._models[name], est, method)
        timing.pose += (time.perf_counter() - t) * 1e3
        return self._accept(est)

    def _without_grazing(self, model: _FieldModel, est: PoseEstimate, method: str
                         ) -> PoseEstimate:
        """Refit ``est`` without the corners it shows more oblique than
        ``max_obliquity_deg``, when enough squarely seen corners remain.

        Refined corners at grazing angles are biased (0.2-0.8 px at 60-65 deg on the
        shipped cylinders) and NVG-BA's weights only damp them; predictive tracking never
        looks at them, and this gives the full-frame and ROI paths the same corner policy.
        A field seen only at grazing angles keeps them, weighted, rather than vanishing.
        """
        s = self.settings
        cos_min = np.cos(np.radians(s.max_obliquity_deg))
        obs, dropped = [], 0
        for cam_name, (rows, px) in est.per_camera.items():
            cam = self.rig[cam_name]
            T_cam_field = cam.T_cam_ref @ est.T_ref_field
            p_cam = model.field.corners[rows] @ T_cam_field[:3, :3].T + T_cam_field[:3, 3]
            ok = model.facing_cos(model.face_normals[rows] @ T_cam_field[:3, :3].T,
                                  p_cam) > cos_min
            dropped += int(np.sum(~ok))
            if np.any(ok):
                obs.append(Observation(cam, rows[ok], px[ok]))
        if dropped == 0 or sum(len(o.rows) for o in obs) < max(s.min_corners, 8):
            return est
        refit = estimate_pose(model.field, obs, method, self.weighting, model.normals,
                              T_guess=est.T_ref_field)
        return est if refit is None else refit

    # -- rigid bodies ----------------------------------------------------------------------
    def _track_bodies(self, imgs: dict[str, np.ndarray], timing: FrameTiming
                      ) -> dict[str, BodyEstimate]:
        """Every body in whole images: one detector pass per dictionary and camera, then a
        pose per body over the cameras (:func:`.rigid_body.estimate_body`)."""
        s = self.settings
        t = time.perf_counter()
        found = {d: {cam: detect_tag_list(img, d) for cam, img in imgs.items()}
                 for d in self._body_dictionaries}
        t1 = time.perf_counter()
        timing.recognition += (t1 - t) * 1e3
        out: dict[str, BodyEstimate] = {}
        for name, body in self.bodies.items():
            est = self._accept_body(estimate_body(
                body, found[body.dictionary], self.rig,
                max_tag_error_px=s.body_max_tag_error_px,
                max_tag_error_rel=s.body_max_tag_error_rel))
            if est is not None:
                out[name] = est
                timing.stages[name] = "full"
        timing.pose += (time.perf_counter() - t1) * 1e3
        return out

    def _accept_body(self, est: BodyEstimate | None) -> BodyEstimate | None:
        """The fields' rules with the bodies' limits (no corner minimum: one tag has 4)."""
        s = self.settings
        if est is None or not est.within(s.body_max_rms_px, s.body_max_position_sigma_mm,
                                         s.body_max_rotation_sigma_deg):
            return None
        return est

    # -- ROI (eqs. 18-19) -----------------------------------------------------------------
    def roi_boxes(self, name: str, T_ref_field: np.ndarray) -> dict[str, tuple[int, int, int, int]]:
        """Eqs. 18-19: the box (x0, y0, x1, y1) around ``name``'s projected corners in each
        camera, grown by the motion margin and clipped to the image; cameras where the field
        falls outside the image are absent."""
        fld = self.fields[name]
        s = self.settings
        boxes = {}
        for cam_name in self.rig.names:
            cam = self.rig[cam_name]
            uv = cam.project_from(cam.T_cam_ref @ T_ref_field, fld.corners)
            uv = uv[np.all(np.isfinite(uv), axis=1)]
            if len(uv) == 0:
                continue
            lo, hi = uv.min(axis=0), uv.max(axis=0)
            # eq. 19's corner box, then the margin: the corners sit a square inside the
            # markers' outer edge, and the field moves between frames.
            grow = s.roi_margin * (hi - lo) + s.roi_margin_px
            x0, y0 = np.floor(lo - grow).astype(int)
            x1, y1 = np.ceil(hi + grow).astype(int) + 1
            x0, y0 = max(x0, 0), max(y0, 0)
            x1, y1 = min(x1, cam.width), min(y1, cam.height)
            if x1 - x0 >= 16 and y1 - y0 >= 16:
                boxes[cam_name] = (int(x0), int(y0), int(x1), int(y1))
        return boxes

    def _roi_field(self, model: _FieldModel, T_pred: np.ndarray, imgs: dict[str, np.ndarray],
                   timing: FrameTiming) -> PoseEstimate | None:
        name = model.field.name
        t = time.perf_counter()
        boxes = {c: b for c, b in self.roi_boxes(name, T_pred).items() if c in imgs}
        t1 = time.perf_counter()
        timing.roi += (t1 - t) * 1e3
        found = {}
        for cam, box in boxes.items():
            res = detect_fields(imgs[cam], [model.field], self.settings.quads, roi=box,
                                layouts=self._layouts)
            if name in res:
                found[cam] = res[name]
        timing.recognition += (time.perf_counter() - t1) * 1e3
        if not found:
            return None
        return self._estimate(name, found, None, timing)

    # -- predictive corner tracking -----------------------------------------------------
    def _predict_field(self, model: _FieldModel, T_pred: np.ndarray,
                       imgs: dict[str, np.ndarray], timing: FrameTiming) -> PoseEstimate | None:
        fld = model.field
        s = self.settings
        cos_min = np.cos(np.radians(s.max_obliquity_deg))
        corners: dict[str, FieldCorners] = {}
        checked = passed = 0
        for cam_name, img in imgs.items():
            t = time.perf_counter()
            cam = self.rig[cam_name]
            T_cam_field = cam.T_cam_ref @ T_pred
            R, tv = T_cam_field[:3, :3], T_cam_field[:3, 3]
            p_cam = fld.corners @ R.T + tv
            uv = cam.project(p_cam)
            facing = model.facing_cos(model.face_normals @ R.T, p_cam) > cos_min
            vis = facing & np.all(np.isfinite(uv), axis=1) & cam.in_image(uv, margin=4)
            if vis.sum() < s.min_corners:
                timing.roi += (time.perf_counter() - t) * 1e3
                continue
            step = model.step_rows
            sq = np.full(len(uv), np.inf)
            for k in range(2):
                ok = step[:, k] >= 0
                d = np.linalg.norm(uv[step[ok, k]] - uv[ok], axis=1)
                sq[ok] = np.minimum(sq[ok], d)
            vis &= np.isfinite(sq) & (sq >= 6.0)
            rows = np.nonzero(vis)[0]
            t1 = time.perf_counter()
            timing.roi += (t1 - t) * 1e3
            px, ok = refine_corners(img, uv[rows], sq[rows])
            # Identity: the bits of the markers the pose puts in view must read right.
            mq_cam = model.marker_quads.reshape(-1, 3) @ R.T + tv
            mq = cam.project(mq_cam).reshape(-1, 4, 2)
            side = np.linalg.norm(mq - np.roll(mq, 1, axis=1), axis=2).min(axis=1)
            centres = mq_cam.reshape(-1, 4, 3).mean(axis=1)
            mvis = np.isfinite(side) & (side > 12.0)
            mvis &= model.facing_cos(model.marker_normals @ R.T, centres) > cos_min
            mvis &= np.all(cam.in_image(mq.reshape(-1, 2), margin=2).reshape(-1, 4), axis=1)
            if np.any(mvis):
                scores = decoder_for(fld.dictionary).match_scores(
                    img, mq[mvis], model.marker_ids[mvis])
                checked += len(scores)
                passed += int(np.sum(scores >= s.verify_score))
            timing.recognition += (time.perf_counter() - t1) * 1e3
            if ok.sum() >= s.min_corners:
                corners[cam_name] = FieldCorners(fld.corner_ids[rows[ok]], px[ok])
        if not corners or checked == 0 or passed < s.verify_fraction * checked:
            return None
        return self._estimate(fld.name, corners, T_pred, timing)

    # -- the OpenCV baseline ------------------------------------------------------------
    def _opencv_detector(self, fld: MarkerField) -> cv2.aruco.CharucoDetector:
        det = self._opencv.get(fld.name)
        if det is None:
            det = self._opencv[fld.name] = cv2.aruco.CharucoDetector(fld.board)
        return det

    def _track_opencv(self, imgs: dict[str, np.ndarray], timing: FrameTiming
                      ) -> dict[str, PoseEstimate]:
        """OpenCV's stock ChArUco detector and ``solvePnP`` (iterative) per camera; the
        field's pose comes from the camera that sees the most corners. In ``roi`` and
        ``predict`` modes the detector runs on the predicted boxes (the stock pipeline has
        no corner tracker)."""
        out: dict[str, PoseEstimate] = {}
        for name, fld in self.fields.items():
            T_pred = self._predicted_pose(name) if self.mode != "full" else None
            t = time.perf_counter()
            boxes = (self.roi_boxes(name, T_pred) if T_pred is not None else
                     {c: (0, 0, self.rig[c].width, self.rig[c].height) for c in imgs})
            t1 = time.perf_counter()
            timing.roi += (t1 - t) * 1e3
            best: tuple[int, str, np.ndarray, np.ndarray] | None = None
            for cam_name, (x0, y0, x1, y1) in boxes.items():
                if cam_name not in imgs:
                    continue
                crop = imgs[cam_name][y0:y1, x0:x1]
                ch_corners, ch_ids, _, _ = self._opencv_detector(fld).detectBoard(crop)
                if ch_ids is None or len(ch_ids) < 4:
                    continue
                px = ch_corners.reshape(-1, 2).astype(float) + (x0, y0)
                rows = np.array([fld.corner_index.get(int(i), -1) for i in ch_ids.ravel()])
                px, rows = px[rows >= 0], rows[rows >= 0]
                if best is None or len(rows) > best[0]:
                    best = (len(rows), cam_name, rows, px)
            timing.recognition += (time.perf_counter() - t1) * 1e3
            if best is None:
                continue
            t2 = time.perf_counter()
            _, cam_name, rows, px = best
            cam = self.rig[cam_name]
            est = self._opencv_pose(fld, cam, rows, px)
            timing.pose += (time.perf_counter() - t2) * 1e3
            est = self._accept(est)
            if est is not None:
                out[name] = est
                timing.stages[name] = "full" if T_pred is None else "roi"
        return out

    @staticmethod
    def _opencv_pose(fld: MarkerField, cam: CameraModel, rows: np.ndarray, px: np.ndarray
                     ) -> PoseEstimate | None:
        obj = fld.corners[rows]
        if len(rows) < 4:
            return None
        try:
            ok, rvec, tvec = cv2.solvePnP(obj, px.reshape(-1, 1, 2), cam.K, cam.dist,
                                          flags=cv2.SOLVEPNP_ITERATIVE)
        except cv2.error:
            return None
        if not ok:
            return None
        T_cam = np.eye(4)
        T_cam[:3, :3] = Rotation.from_rotvec(rvec.ravel()).as_matrix()
        T_cam[:3, 3] = tvec.ravel()
        if T_cam[2, 3] <= 0 or not np.all(np.isfinite(T_cam)):
            return None  # a mirrored solution behind the camera
        T = cam.T_ref_cam @ T_cam
        ob = Observation(cam, rows, px)
        cov = pose_covariance(fld, [ob], T)
        if cov is None:
            return None
        uv = cam.project_from(T_cam, obj)
        rms = float(np.sqrt(np.mean(np.sum((uv - px) ** 2, axis=1))))
        return PoseEstimate(T, len(rows), rms, cov, (cam.name,), {cam.name: (rows, px)},
                            "opencv")
