"""ArUco rigid bodies: tags with known 3D corners, detected and posed as one object.

A rigid body is a set of ArUco tags of one dictionary whose four corners are known in the
body frame (metres). Corners are given in OpenCV's detection order: top-left, top-right,
bottom-right, bottom-left of the printed marker seen upright, so row ``k`` of a tag's
corners matches corner ``k`` of :func:`detect_tags`. The files of scikit-surgery's
arucotracker (``config.rigid_bodies``) use the same order.

:func:`single_tag_body` builds a one-tag body in the project's marker-field convention
(origin at the tag centre, x right and y down on the printed tag, z = x cross y pointing
away from a camera that sees it). OpenCV's single-marker pose (``estimatePoseSingleMarkers``,
y up, z toward the camera) is that frame turned half a turn about x:
``T_cam_marker = T_cam_body @ T_TAG_OPENCV_MARKER``.

Pose estimation (:func:`estimate_body_pose`) fits all visible tags at once: one tag is
solved by IPPE_SQUARE (both of its mirror solutions are refined and the better kept), more
by SQPnP; a tag-level consensus then drops tags that disagree with the others (a misread id,
a copy of a tag stuck elsewhere), and Levenberg-Marquardt polishes the pose on the tags that
agree. Frames: ``T_cam_body`` maps body points (m) into the camera frame (OpenCV: z along
the optical axis, x right, y down the image); pixels follow :mod:`oralnav.control.vision.camera`.

Over a rig, :func:`estimate_body` takes the camera whose tags agree best as the start, adds
the agreeing tags of the other cameras, and refines the body's ``T_ref_body`` jointly by the
bundle adjustment of :mod:`.pose`; the result is a :class:`BodyEstimate`, the
:class:`~.pose.PoseEstimate` a marker field gets, plus the tag bookkeeping.
:func:`confusable_tags` tells which tags of two dictionaries a detector could mistake for
one another (the tracker refuses bodies and fields that share tags).
"""

from __future__ import annotations

import itertools
import numbers
import threading
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from dataclasses import fields as dataclass_fields
from types import MappingProxyType

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from oralnav.control.errors import MarkerFieldError
from oralnav.control.geometry import invert, make_transform, transform_points
from oralnav.control.vision.camera import CameraModel, Rig
from oralnav.control.vision.markers import aruco_dictionary
from oralnav.control.vision.pose import CornerNoise, Observation, PoseEstimate, bundle_adjust

#: Pose of OpenCV's single-marker frame (y up, z toward the camera) in the frame of a
#: :func:`single_tag_body` tag (y down, z away): a half turn about x.
T_TAG_OPENCV_MARKER = np.diag([1.0, -1.0, -1.0, 1.0])
T_TAG_OPENCV_MARKER.flags.writeable = False

#: A tag is degenerate when its shortest side is below this (m) ...
MIN_TAG_SIDE = 1e-5
#: ... or its area is below this fraction of its mean side squared (1 for a square).
MIN_TAG_AREA_RATIO = 0.05
#: A detected tag whose image quadrilateral covers less than this (px^2) is not used.
MIN_IMAGE_AREA_PX2 = 1.0

#: Tag corners from :func:`detect_tags` (sub-pixel refined L-shaped corners), for the
#: covariance (:class:`~.pose.CornerNoise`). Measured on 113 rendered tags (2026-11-27;
#: 640 x 480, 600 px focal, 25-110 px sides, 0-55 deg tilt, 1-3 DN noise): refinement
#: pulls every edge of a tag into it, by 0.12 px at 0.3-0.7 px of blur, 0.18 px at
#: 0.7-1.1, 0.29 px at 1.1-1.5 and 0.42 px at 1.5-2 (spread 0.05-0.17 px), and beyond
#: that shift each corner coordinate is off by 0.05-0.12 px RMS on tags over 60 px
#: across; under 45 px both grow, to 0.64 px of shift and 0.4 px of scatter at 1.1-1.5 px
#: of blur. The AprilTag refinement has no such shift but 0.45 px of scatter. The values
#: below (0.1 px, a 0.2 px shift, growing under 50 px) are those of 0.4-1.5 px of blur,
#: set on 150 random renders and checked on 300 others (docs/tracking.md).
TAG_CORNERS = CornerNoise(sigma_px=0.1, dof=4, edge_sigma_px=0.2, small_side_px=50.0)

# Levenberg-Marquardt stop: the pose changes by less than ~1e-12 (rad, m) or 100 steps.
_LM_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)

TagCorners = Mapping[int, np.ndarray] | Iterable[tuple[int, np.ndarray]]


# -- the body ----------------------------------------------------------------------------------
def _as_tag_id(value: object, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise MarkerFieldError(f"{what}: tag id must be an integer, got {value!r}")
    return int(value)


def check_tag_corners(corners: object, what: str = "tag") -> np.ndarray:
    """Validate one tag's corners and return them as a read-only float (4, 3) array (m).

    Raises :class:`MarkerFieldError` (naming ``what``) unless the corners are finite and
    form a proper quadrilateral: sides of at least :data:`MIN_TAG_SIDE`, an area of at least
    :data:`MIN_TAG_AREA_RATIO` times the mean side squared, convex with one winding (four
    corners in detection order go round the tag, they do not cross it).
    """
    try:
        c = np.array(corners, dtype=float)
    except (TypeError, ValueError):
        raise MarkerFieldError(f"{what}: corners must be 4 x 3 numbers (m)") from None
    if c.shape != (4, 3):
        raise MarkerFieldError(f"{what}: corners must be 4 x 3 (m), got shape {c.shape}")
    if not np.all(np.isfinite(c)):
        raise MarkerFieldError(f"{what}: corners have non-finite entries")
    edges = np.roll(c, -1, axis=0) - c
    sides = np.linalg.norm(edges, axis=1)
    if sides.min() < MIN_TAG_SIDE:
        raise MarkerFieldError(
            f"{what}: degenerate tag, a side is {sides.min():.3g} m long "
            f"(at least {MIN_TAG_SIDE:g} m expected)")
    # vector area of the quadrilateral = half the cross product of its diagonals
    normal = 0.5 * np.cross(c[2] - c[0], c[3] - c[1])
    area = float(np.linalg.norm(normal))
    mean_side = float(sides.mean())
    if area < MIN_TAG_AREA_RATIO * mean_side**2:
        raise MarkerFieldError(
            f"{what}: degenerate tag, area {area:.3g} m^2 for sides of {mean_side:.3g} m "
            "(collinear, coincident or crossed corners)")
    turns = np.cross(edges, np.roll(edges, -1, axis=0)) @ normal
    if np.any(turns <= 0):
        raise MarkerFieldError(
            f"{what}: corners do not go round the tag in one direction (crossed or "
            "concave quadrilateral; expected OpenCV order top-left, top-right, "
            "bottom-right, bottom-left)")
    c.flags.writeable = False
    return c


def _tag_items(tags: object, what: str) -> list[tuple[object, object]]:
    if isinstance(tags, Mapping):
        return list(tags.items())
    try:
        items = [tuple(item) for item in tags]  # type: ignore[union-attr]
    except TypeError:
        raise MarkerFieldError(
            f"{what}: tags must be a mapping id -> corners or (id, corners) pairs") from None
    if any(len(item) != 2 for item in items):
        raise MarkerFieldError(f"{what}: tags must be (id, corners) pairs")
    return items


@dataclass(frozen=True, eq=False)
class RigidBody:
    """A rigid set of ArUco tags of one dictionary.

    Attributes:
        name: the body's name (``"reference"``, ``"pointer"``...).
        dictionary: OpenCV predefined dictionary name (``"DICT_ARUCO_ORIGINAL"``...).
        tags: tag id -> (4, 3) corners in the body frame (m), OpenCV corner order. A
            mapping, or (id, corners) pairs (then a repeated id is an error). Stored as a
            read-only mapping sorted by id.
    """

    name: str
    dictionary: str
    tags: Mapping[int, np.ndarray]

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise MarkerFieldError(f"rigid body name must be a non-empty string, "
                                   f"got {self.name!r}")
        where = f"rigid body {self.name!r}"
        if not isinstance(self.dictionary, str):
            raise MarkerFieldError(f"{where}: dictionary must be a name such as "
                                   f"'DICT_ARUCO_ORIGINAL', got {self.dictionary!r}")
        n_ids = int(aruco_dictionary(self.dictionary).bytesList.shape[0])
        out: dict[int, np.ndarray] = {}
        for raw_id, corners in _tag_items(self.tags, where):
            tid = _as_tag_id(raw_id, where)
            if not 0 <= tid < n_ids:
                raise MarkerFieldError(
                    f"{where}: tag id {tid} is outside {self.dictionary} (ids 0..{n_ids - 1})")
            if tid in out:
                raise MarkerFieldError(f"{where}: tag id {tid} is given twice")
            out[tid] = check_tag_corners(corners, f"{where} tag {tid}")
        if not out:
            raise MarkerFieldError(f"{where}: at least one tag is required")
        object.__setattr__(self, "tags", MappingProxyType(dict(sorted(out.items()))))

    @property
    def ids(self) -> tuple[int, ...]:
        """Tag ids, ascending."""
        return tuple(self.tags)

    def __len__(self) -> int:
        return len(self.tags)

    def corners(self, ids: Iterable[int] | None = None) -> np.ndarray:
        """Corners of the tags ``ids`` (all by default), stacked: (4 k, 3), body frame, m."""
        sel = self.ids if ids is None else tuple(ids)
        if not sel:
            return np.zeros((0, 3))
        return np.concatenate([self.tags[int(i)] for i in sel])


def single_tag_body(tag_id: int, side: float, dictionary: str,
                    name: str | None = None) -> RigidBody:
    """A body made of one square tag of ``side`` (m) centred on the body origin.

    Frame: x right and y down on the printed tag, z away from a camera that sees it (the
    convention of the project's marker fields and of scikit-surgery's ``tag_0.txt``);
    compose with :data:`T_TAG_OPENCV_MARKER` for OpenCV's single-marker frame.
    """
    if not (isinstance(side, numbers.Real) and np.isfinite(side) and side > 0):
        raise MarkerFieldError(f"tag side must be a positive length (m), got {side!r}")
    h = 0.5 * float(side)
    corners = np.array([[-h, -h, 0.0], [h, -h, 0.0], [h, h, 0.0], [-h, h, 0.0]])
    return RigidBody(name or f"{dictionary}:{tag_id}", dictionary, {tag_id: corners})


# -- detection ---------------------------------------------------------------------------------
def default_detector_parameters() -> cv2.aruco.DetectorParameters:
    """The detector parameters :func:`detect_tags` uses unless given others.

    OpenCV's defaults, plus sub-pixel corner refinement: OpenCV's default (no refinement)
    leaves corners on whole pixels, which costs a single tag's pose about a degree.
    """
    p = cv2.aruco.DetectorParameters()
    p.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    p.cornerRefinementMinAccuracy = 0.01  # px; OpenCV's 0.1 stops early
    return p


# One detector per dictionary, per thread: OpenCV does not promise that one ArucoDetector
# may run on several threads at once, and the daemon detects in worker threads.
_local = threading.local()


def cached_detector(dictionary_name: str) -> cv2.aruco.ArucoDetector:
    cache: dict[str, cv2.aruco.ArucoDetector] | None = getattr(_local, "detectors", None)
    if cache is None:
        cache = _local.detectors = {}
    det = cache.get(dictionary_name)
    if det is None:
        det = cv2.aruco.ArucoDetector(aruco_dictionary(dictionary_name),
                                      default_detector_parameters())
        cache[dictionary_name] = det
    return det


def _as_gray(image: np.ndarray) -> np.ndarray:
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8:
        raise MarkerFieldError(
            "image must be a uint8 numpy array (mono8, BGR or BGRA), got "
            f"{getattr(image, 'dtype', type(image).__name__)}")
    if image.ndim == 2:
        return image
    if image.ndim == 3 and image.shape[2] == 1:
        return image[:, :, 0]
    if image.ndim == 3 and image.shape[2] == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.ndim == 3 and image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2GRAY)
    raise MarkerFieldError(f"image must be H x W (mono8) or H x W x 3/4 (BGR/BGRA), "
                           f"got shape {image.shape}")


def detect_tag_list(image: np.ndarray, dictionary_name: str,
                    params: cv2.aruco.DetectorParameters | None = None,
                    ) -> list[tuple[int, np.ndarray]]:
    """Every tag of ``dictionary_name`` found in ``image``, repeated ids included.

    Args:
        image: mono8 (H, W) or BGR / BGRA (H, W, 3|4) uint8 image.
        dictionary_name: OpenCV predefined dictionary name.
        params: detector parameters; ``None`` uses :func:`default_detector_parameters`
            through a cached detector, others build a detector for this call.

    Returns:
        ``(id, corners)`` pairs in OpenCV's order; corners are (4, 2) float64 pixels.
    """
    gray = _as_gray(image)
    if params is None:
        det = cached_detector(dictionary_name)
    else:
        det = cv2.aruco.ArucoDetector(aruco_dictionary(dictionary_name), params)
    corners, ids, _ = det.detectMarkers(gray)
    if ids is None or len(corners) == 0:
        return []
    return [(int(i), np.asarray(c, dtype=float).reshape(4, 2))
            for i, c in zip(np.asarray(ids).reshape(-1), corners, strict=True)]


def unique_tags(detections: Iterable[tuple[int, np.ndarray]]) -> dict[int, np.ndarray]:
    """Keep the tags whose id was seen exactly once: a tag seen twice in one image cannot
    say which copy belongs to the body, so both copies are dropped rather than guessed."""
    pairs = list(detections)
    counts: dict[int, int] = {}
    for tid, _ in pairs:
        counts[int(tid)] = counts.get(int(tid), 0) + 1
    return {int(t): c for t, c in pairs if counts[int(t)] == 1}


def detect_tags(image: np.ndarray, dictionary_name: str,
                params: cv2.aruco.DetectorParameters | None = None) -> dict[int, np.ndarray]:
    """Tags of ``dictionary_name`` in ``image``: id -> (4, 2) corners (px, float64).

    Ids seen more than once are left out (see :func:`unique_tags`); use
    :func:`detect_tag_list` for every detection.
    """
    return unique_tags(detect_tag_list(image, dictionary_name, params))


# -- pose ----------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class BodyPose:
    """The pose of a rigid body seen by one camera.

    Attributes:
        body: the body's name.
        camera: the camera's name.
        T_cam_body: (4, 4) pose of the body in the camera frame (m).
        tags_used: ids of the tags the pose was fitted to, ascending.
        tags_seen: ids of the body's tags in the detections (once each), ascending.
        quality: ``len(tags_seen) / len(body)``, the peer tracker's tracking quality.
        reproj_rms_px: RMS reprojection error over the corners of ``tags_used`` (px).
    """

    body: str
    camera: str
    T_cam_body: np.ndarray
    tags_used: tuple[int, ...]
    tags_seen: tuple[int, ...]
    quality: float
    reproj_rms_px: float

    @property
    def tags_rejected(self) -> tuple[int, ...]:
        """Tags seen but left out because they disagree with the others."""
        used = set(self.tags_used)
        return tuple(t for t in self.tags_seen if t not in used)


def _image_corners(tag_corners_px: object) -> list[tuple[int, np.ndarray]]:
    out = []
    for raw_id, corners in _tag_items(tag_corners_px, "detections"):
        tid = _as_tag_id(raw_id, "detections")
        try:
            c = np.asarray(corners, dtype=float)
        except (TypeError, ValueError):
            raise MarkerFieldError(f"detections: tag {tid}: corners must be numbers") from None
        if c.size != 8:  # (4, 2), or OpenCV's (1, 4, 2)
            raise MarkerFieldError(
                f"detections: tag {tid}: expected 4 corners (4 x 2 px), got shape {c.shape}")
        c = c.reshape(4, 2)
        if not np.all(np.isfinite(c)):
            raise MarkerFieldError(f"detections: tag {tid}: corners have non-finite entries")
        out.append((tid, c))
    return out


def _image_area(c: np.ndarray) -> float:
    x, y = c[:, 0], c[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


def _pose(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    return make_transform(Rotation.from_rotvec(np.asarray(rvec, dtype=float).reshape(3)),
                          np.asarray(tvec, dtype=float).reshape(3))


def _refine(obj: np.ndarray, img: np.ndarray, cam: CameraModel,
            T: np.ndarray) -> np.ndarray | None:
    rvec = Rotation.from_matrix(T[:3, :3]).as_rotvec().reshape(3, 1)
    tvec = T[:3, 3].reshape(3, 1).copy()
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, cam.K, cam.dist, rvec, tvec, _LM_CRITERIA)
    out = _pose(rvec, tvec)
    return out if np.all(np.isfinite(out)) else None


def _solve(obj: np.ndarray, img: np.ndarray, cam: CameraModel) -> np.ndarray | None:
    """SQPnP on 8 or more points, ITERATIVE if it fails; no LM polish."""
    for flag in (cv2.SOLVEPNP_SQPNP, cv2.SOLVEPNP_ITERATIVE):
        try:
            ok, rvec, tvec = cv2.solvePnP(obj, img, cam.K, cam.dist, flags=flag)
        except cv2.error:
            continue
        if ok and np.all(np.isfinite(rvec)) and np.all(np.isfinite(tvec)):
            return _pose(rvec, tvec)
    return None


def _solve_single(obj: np.ndarray, img: np.ndarray, cam: CameraModel) -> list[np.ndarray]:
    """Both IPPE_SQUARE solutions of one tag, as poses of the body."""
    # IPPE_SQUARE wants the canonical square (-s/2, s/2), (s/2, s/2), (s/2, -s/2),
    # (-s/2, -s/2): fit that square to the tag's body corners (Kabsch through scipy), solve
    # for the square, map back. A tag that is not exactly square only seeds the LM polish.
    s = float(np.linalg.norm(np.roll(obj, -1, axis=0) - obj, axis=1).mean())
    h = 0.5 * s
    square = np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])
    centre = obj.mean(axis=0)
    rot, _ = Rotation.align_vectors(obj - centre, square)
    T_body_square = make_transform(rot, centre)
    try:
        n, rvecs, tvecs, _ = cv2.solvePnPGeneric(square, img, cam.K, cam.dist,
                                                 flags=cv2.SOLVEPNP_IPPE_SQUARE)
    except cv2.error:
        return []
    T_square_body = invert(T_body_square)
    return [_pose(r, t) @ T_square_body for r, t in zip(rvecs[:n], tvecs[:n], strict=True)]


def _tag_errors(T: np.ndarray, obj: np.ndarray, img: np.ndarray,
                cam: CameraModel) -> np.ndarray:
    """Per-tag RMS reprojection error (px) of ``T`` over consecutive groups of 4 corners;
    inf for a tag with a corner at or behind the camera."""
    p_cam = transform_points(T, obj)
    uv = cam.project(p_cam)
    d2 = np.sum((uv - img) ** 2, axis=1).reshape(-1, 4)
    err = np.sqrt(d2.mean(axis=1))
    return np.where(np.isfinite(err), err, np.inf)


def _tag_limits(tags_px: Iterable[np.ndarray], max_px: float, rel: float) -> np.ndarray:
    """Per-tag agreement limit (px): the larger of ``max_px`` and ``rel`` times the tag's
    mean side in the image."""
    side_px = np.array([np.linalg.norm(np.roll(c, -1, axis=0) - c, axis=1).mean()
                        for c in tags_px])
    return np.maximum(max_px, rel * side_px)


def _rows(idx: Iterable[int]) -> np.ndarray:
    return np.concatenate([np.arange(4 * i, 4 * i + 4) for i in idx])


def estimate_body_pose(body: RigidBody, tag_corners_px: TagCorners, camera: CameraModel,
                       *, max_tag_error_px: float = 4.0,
                       max_tag_error_rel: float = 0.1) -> BodyPose | None:
    """Pose of ``body`` in ``camera``'s frame from its detected tags.

    Args:
        body: the rigid body.
        tag_corners_px: detected tags, id -> (4, 2) corners (px, OpenCV order), as
            :func:`detect_tags` returns; or (id, corners) pairs, in which an id given
            more than once is dropped (it cannot say which copy is the body's). Tags that
            are not the body's are ignored.
        camera: the camera that took the image (its K and distortion; ``T_ref_cam`` is
            not used: the pose is in the camera frame).
        max_tag_error_px, max_tag_error_rel: with two or more tags, a tag agrees with a pose
            when its corners' RMS reprojection error is at most the larger of
            ``max_tag_error_px`` and ``max_tag_error_rel`` times its mean side in pixels
            (a near tag magnifies the body's model errors). Tags that do not agree are left
            out; when no two tags agree there is no pose.

    Returns:
        The pose, or ``None`` when no tag of the body is seen usable (fewer than one, or
        degenerate image quadrilaterals), the solvers fail, the tags disagree, or the
        body would lie behind the camera.

    Raises:
        MarkerFieldError: on malformed detections (wrong shape, non-finite corners).
    """
    pairs = _image_corners(tag_corners_px)
    seen_once = unique_tags(pairs)
    seen = sorted(t for t in seen_once if t in body.tags)
    usable = [t for t in seen if _image_area(seen_once[t]) >= MIN_IMAGE_AREA_PX2]
    if not usable:
        return None
    obj = body.corners(usable)
    img = np.concatenate([seen_once[t] for t in usable])
    k = len(usable)

    if k == 1:
        candidates = [_refine(obj, img, camera, T) for T in _solve_single(obj, img, camera)]
        scored = [(float(_tag_errors(T, obj, img, camera)[0]), i, T)
                  for i, T in enumerate(candidates) if T is not None]
        scored = [s for s in scored if np.isfinite(s[0])]
        if not scored:
            return None
        _, _, T = min(scored, key=lambda s: s[:2])
        inliers = [0]
    else:
        limit = _tag_limits([seen_once[t] for t in usable], max_tag_error_px,
                            max_tag_error_rel)
        found = _consensus(obj, img, camera, limit)
        if found is None:
            return None
        T, inliers = found

    rows = _rows(inliers)
    errs = _tag_errors(T, obj[rows], img[rows], camera)
    if not np.all(np.isfinite(errs)):
        return None
    return BodyPose(
        body=body.name,
        camera=camera.name,
        T_cam_body=T,
        tags_used=tuple(usable[i] for i in inliers),
        tags_seen=tuple(seen),
        quality=len(seen) / len(body),
        reproj_rms_px=float(np.sqrt(np.mean(errs**2))),
    )


def _consensus(obj: np.ndarray, img: np.ndarray, cam: CameraModel,
               limit: np.ndarray) -> tuple[np.ndarray, list[int]] | None:
    """Fit two or more tags, leaving out those that disagree with the rest.

    First all tags together; if one of them misses its ``limit`` (px), pairs of tags
    propose poses (RANSAC over tags, deterministic and exhaustive unless a pose that all
    tags but one agree with turns up: bodies carry few tags) and the pose that most tags
    agree with (then the lowest total error) wins. At least two tags must agree.
    """
    k = len(limit)
    everything = list(range(k))
    T = _solve(obj, img, cam)
    if T is not None:
        T = _refine(obj, img, cam, T)
    errs_all = None if T is None else _tag_errors(T, obj, img, cam)
    if errs_all is not None and np.all(errs_all <= limit):
        return T, everything

    # Pairs of the tags that fit the joint pose best go first, and the search stops at a
    # pose all tags but one agree with (the joint fit failed, so that is the best left):
    # with one wrong tag this usually takes a single solve.
    order = everything if errs_all is None else [int(i) for i in np.argsort(errs_all / limit)]
    best: tuple[int, float, list[int]] | None = None
    for pair in itertools.combinations(order, 2):
        rows = _rows(pair)
        Th = _solve(obj[rows], img[rows], cam)
        if Th is None:
            continue
        errs = _tag_errors(Th, obj, img, cam)
        agree = [i for i in everything if errs[i] <= limit[i]]
        score = (len(agree), -float(np.sum(np.minimum(errs, limit))))
        if len(agree) >= 2 and (best is None or score > best[:2]):
            best = (score[0], score[1], agree)
            if len(agree) == k - 1:
                break
    if best is None:
        return None
    inliers = best[2]
    for _ in range(3):  # refit on the agreeing tags until the set settles
        rows = _rows(inliers)
        T = _solve(obj[rows], img[rows], cam)
        T = None if T is None else _refine(obj[rows], img[rows], cam, T)
        if T is None:
            return None
        errs = _tag_errors(T, obj, img, cam)
        again = [i for i in everything if errs[i] <= limit[i]]
        if again == inliers:
            break
        if len(again) < 2:
            return None
        inliers = again
    if not np.all(_tag_errors(T, obj[_rows(inliers)], img[_rows(inliers)], cam)
                  <= limit[inliers]):
        return None
    return T, inliers


# -- over a rig --------------------------------------------------------------------------------
@dataclass(frozen=True)
class BodyEstimate(PoseEstimate):
    """A rigid body's pose in the rig's reference frame, from one frame's images.

    The :class:`~.pose.PoseEstimate` a marker field gets, with the body in the place of the
    field: ``T_ref_field`` is ``T_ref_body`` (4x4, m); ``corners`` counts the tag corners
    used, 4 per tag and camera; ``covariance`` is that of ``[dt (m), dtheta (rad)]`` in the
    reference frame, from the final Jacobian; ``per_camera`` rows index
    ``body.corners()`` (every tag in id order, 4 rows each); ``method`` is ``"aruco"``.

    Attributes:
        tags_used: ids of the tags the pose was fitted to, in any camera, ascending.
        tags_seen: ids of the body's tags detected (once in an image) by any camera.
        quality: ``len(tags_seen) / len(body)``, the peer tracker's tracking quality.
    """

    tags_used: tuple[int, ...] = ()
    tags_seen: tuple[int, ...] = ()
    quality: float = 0.0


@dataclass(frozen=True, eq=False)
class _BodyPoints:
    """A body as a :class:`.pose.CornerModel`: every tag corner ((N, 3), body frame, m)."""

    corners: np.ndarray


def estimate_body(body: RigidBody, detections: Mapping[str, TagCorners], rig: Rig, *,
                  max_tag_error_px: float = 4.0,
                  max_tag_error_rel: float = 0.1) -> BodyEstimate | None:
    """Pose of ``body`` in ``rig``'s reference frame from its tags in one or more cameras.

    Each camera's tags are posed by :func:`estimate_body_pose`. The camera that keeps the
    most tags (then the lowest RMS) gives the starting ``T_ref_body``; every other camera
    adds the tags that agree with it (the limits of :func:`estimate_body_pose`), and the
    pose is refined over all of them by :func:`.pose.bundle_adjust` (unweighted, no corner
    rejection: the tag consensus already dropped the tags that disagree), which also gives
    the covariance.

    Args:
        body: the rigid body.
        detections: camera name -> that camera's detected tags, as for
            :func:`estimate_body_pose` (other dictionaries' ids are simply not the body's).
        rig: the cameras; ``T_ref_cam`` places each in the reference frame.
        max_tag_error_px, max_tag_error_rel: the tag agreement limits.

    Returns:
        The estimate, or ``None`` when no camera gives the body a pose, or the joint
        refinement fails (degenerate corners, the body behind a camera).

    Raises:
        MarkerFieldError: on malformed detections; CameraModelError: an unknown camera.
    """
    poses: dict[str, BodyPose] = {}
    seen_px: dict[str, dict[int, np.ndarray]] = {}
    for cam_name, dets in detections.items():
        cam = rig[cam_name]
        mine = {t: c for t, c in unique_tags(_image_corners(dets)).items() if t in body.tags}
        if not mine:
            continue
        seen_px[cam_name] = mine
        pose = estimate_body_pose(body, mine, cam, max_tag_error_px=max_tag_error_px,
                                  max_tag_error_rel=max_tag_error_rel)
        if pose is not None:
            poses[cam_name] = pose
    if not poses:
        return None
    start = max(poses, key=lambda c: (len(poses[c].tags_used), -poses[c].reproj_rms_px))
    T0 = rig[start].T_ref_cam @ poses[start].T_cam_body

    index = {t: k for k, t in enumerate(body.ids)}
    obs: list[Observation] = []
    used: set[int] = set()
    for cam_name, mine in seen_px.items():
        cam = rig[cam_name]
        if cam_name == start:
            ids = list(poses[start].tags_used)
        else:
            cand = [t for t in sorted(mine) if _image_area(mine[t]) >= MIN_IMAGE_AREA_PX2]
            if not cand:
                continue
            errs = _tag_errors(cam.T_cam_ref @ T0, body.corners(cand),
                               np.concatenate([mine[t] for t in cand]), cam)
            limit = _tag_limits([mine[t] for t in cand], max_tag_error_px, max_tag_error_rel)
            ids = [t for t, e, lim in zip(cand, errs, limit, strict=True) if e <= lim]
        if not ids:
            continue
        rows = np.concatenate([4 * index[t] + np.arange(4) for t in ids])
        obs.append(Observation(cam, rows, np.concatenate([mine[t] for t in ids])))
        used.update(ids)
    est = bundle_adjust(_BodyPoints(body.corners()), obs, T0, "none",
                        reject_outliers=False, method="aruco", noise=TAG_CORNERS)
    if est is None:
        return None
    seen = sorted(set().union(*(set(m) for m in seen_px.values())))
    base = {f.name: getattr(est, f.name) for f in dataclass_fields(PoseEstimate)}
    return BodyEstimate(**base, tags_used=tuple(sorted(used)), tags_seen=tuple(seen),
                        quality=len(seen) / len(body))


# -- tags two detectors could confuse ----------------------------------------------------------
def correction_bits(dictionary: str,
                    params: cv2.aruco.DetectorParameters | None = None) -> int:
    """Bits OpenCV's detector corrects in a tag of ``dictionary`` with ``params`` (the
    :func:`detect_tags` defaults): ``int(maxCorrectionBits * errorCorrectionRate)``."""
    p = default_detector_parameters() if params is None else params
    return int(aruco_dictionary(dictionary).maxCorrectionBits * p.errorCorrectionRate)


def confusable_tags(dictionary_a: str, ids_a: Iterable[int], dictionary_b: str,
                    ids_b: Iterable[int], max_bits: int = 0) -> list[tuple[int, int]]:
    """Pairs ``(id in a, id in b)`` whose codes differ in at most ``max_bits`` bits in some
    rotation: a detector of one dictionary that corrects ``max_bits`` bits can read the
    other's tag as its own (``max_bits = 0``: the same code, as ``DICT_4X4_50`` id 3 and
    ``DICT_4X4_1000`` id 3). Dictionaries of different bit grids (4x4 and 5x5) give no
    pairs: their codes do not compare, and the detector's grid separates them.
    """
    da, db = aruco_dictionary(dictionary_a), aruco_dictionary(dictionary_b)
    a = [int(i) for i in ids_a]
    b = [int(i) for i in ids_b]
    if da.markerSize != db.markerSize or not a or not b:
        return []
    n = da.markerSize ** 2
    bits_a = np.unpackbits(da.bytesList[a, :, 0], axis=-1)[:, :n]                # (A, n)
    bits_b = np.unpackbits(db.bytesList[b].transpose(0, 2, 1), axis=-1)[..., :n]  # (B, 4, n)
    dist = (bits_a[:, None, None, :] != bits_b[None]).sum(axis=-1).min(axis=-1)  # (A, B)
    return [(a[i], b[j]) for i, j in zip(*np.nonzero(dist <= max_bits), strict=True)]
