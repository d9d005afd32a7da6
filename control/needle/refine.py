"""Sub-pixel refinement of a needle pose against the wire's centreline in every view.

The particle filter (:mod:`.needle_tracker`) is robust but coarse: its measurement reads a
binary feature map, so its precision is a fraction of the wire's width in pixels, and its
particles are spread by the motion noise. This module takes the filter's pose and polishes
it the way model-based edge trackers do ("moving edges"): the needle's arc is projected
into each camera; at every projected sample point the wire's *ridge* (a smoothed
thin-line response, :func:`.needle_features.feature_maps`) is searched along the projected
arc's normal, and its peak is located to sub-pixel precision by a parabola through the
three samples around it; Gauss-Newton on the six pose parameters then minimises the
distances, along those normals, between the projected points and the peaks, with Tukey
weights so that points on other features (the jaws, the thread, the incision) or hidden
ones do not pull. A few rounds with a shrinking search window bring the pose to the
centreline.

The result carries what a step needs to trust it: the RMS residual (px), the share of
sample points that found the wire, and the pose covariance from the normal equations
(the uncertainty the views leave, e.g. a single view's depth).

The needle's base/tip twin (:mod:`.needle_tracker`, *Symmetry*) is broken by the suture
thread at the swage: :func:`swage_evidence` compares the ridge just beyond each end.

A needle driven into tissue is partly hidden under its surface. :class:`TissuePlane` is
that surface, a known occluder: sample points under it are neither searched nor counted
as missing wire, and an end under it gives no end measurement (:meth:`PoseRefiner.refine`,
``occluder``; the particle filter reads it too).

Pure math on arrays; metres, radians, pixels. Poses are ``T_ref_N``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from oralnav.control.errors import NeedleError
from oralnav.control.geometry import rotation_angle
from oralnav.control.needle.features import NeedleFeatures
from oralnav.control.needle.model import Needle
from oralnav.control.vision.camera import CameraModel


@dataclass(frozen=True, eq=False)
class TissuePlane:
    """The tissue's surface, a plane that hides whatever lies under it (reference frame).

    ``point`` (3,): a point of the surface (m); ``normal`` (3,): its normal out of the
    tissue, toward the cameras (normalised here; any non-zero length is accepted). Both
    are stored as read-only float arrays.

    An arc sample point counts as *visible* when its centreline stands at least a wire
    radius above the plane (:meth:`visible`): then the wire's whole cross-section is out,
    so its crest and outline are the wire's. Nearer the surface the plane cuts the wire,
    and what shows is a sliver whose crest is off the axis: neither evidence of the wire
    nor a sign that it is missing. The cameras must be on the normal's side (checked by
    the tracker's parts); a point above the plane is then never hidden by it (the
    half-space above is convex). The plane is infinite: a needle past the tissue's edge
    is still taken as hidden under it.
    """

    point: np.ndarray
    normal: np.ndarray

    def __post_init__(self) -> None:
        p = np.array(self.point, dtype=float).reshape(-1)
        n = np.array(self.normal, dtype=float).reshape(-1)
        if p.shape != (3,) or n.shape != (3,):
            raise NeedleError(f"tissue plane: point and normal must be 3-vectors, got shapes "
                              f"{np.shape(self.point)} and {np.shape(self.normal)}")
        if not (np.all(np.isfinite(p)) and np.all(np.isfinite(n))):
            raise NeedleError("tissue plane: point and normal must be finite")
        ln = float(np.linalg.norm(n))
        if not ln > 1e-12:
            raise NeedleError("tissue plane: the normal must be non-zero (it points out of "
                              "the tissue, toward the cameras)")
        n = n / ln
        p.flags.writeable = False
        n.flags.writeable = False
        object.__setattr__(self, "point", p)
        object.__setattr__(self, "normal", n)

    def height(self, pts: np.ndarray) -> np.ndarray:
        """Signed distance (m) of points (..., 3, reference frame) above the surface;
        negative inside the tissue."""
        return (np.asarray(pts, dtype=float) - self.point) @ self.normal

    def visible(self, pts: np.ndarray, margin: float) -> np.ndarray:
        """Whether each centreline point (..., 3, reference frame) is out of the tissue
        by at least ``margin`` (m; the wire radius, see the class docstring)."""
        return self.height(pts) >= margin

    def check_cameras(self, cameras: Sequence[CameraModel]) -> None:
        """Refuse a plane that a camera is under (it would see the tissue's back)."""
        for cam in cameras:
            h = float(self.height(cam.T_ref_cam[:3, 3]))
            if not h > 0:
                raise NeedleError(f"tissue plane: camera {cam.name!r} is {-1e3 * h:.1f} mm "
                                  "under it; the normal must point out of the tissue, "
                                  "toward the cameras")


@dataclass(frozen=True, eq=False)
class ToolCylinder:
    """A part of an instrument that hides what lies behind it (a jaw pair, a shaft): a
    cylinder of ``radius`` (m) about the segment from ``a`` to ``b`` (3,), reference frame.

    A needle held in the jaws, or with a shaft across it, shows less wire than its model;
    the refinement must neither look for what the tool covers nor count it as missing
    (:meth:`PoseRefiner.refine`, ``tools``)."""

    a: np.ndarray
    b: np.ndarray
    radius: float

    def __post_init__(self) -> None:
        for what in ("a", "b"):
            v = np.array(getattr(self, what), dtype=float).reshape(-1)
            if v.shape != (3,) or not np.all(np.isfinite(v)):
                raise NeedleError(f"tool cylinder: {what} must be a finite 3-vector, got "
                                  f"{getattr(self, what)!r}")
            v.flags.writeable = False
            object.__setattr__(self, what, v)
        if not (math.isfinite(self.radius) and self.radius > 0):
            raise NeedleError(f"tool cylinder: radius must be > 0 m, got {self.radius}")

    def hides(self, cam: CameraModel, uv: np.ndarray, depth: np.ndarray | None = None
              ) -> np.ndarray:
        """Which image points ``uv`` (k, 2, px) of ``cam`` lie within the cylinder's image
        (cut 1 cm in front of the camera). With ``depth`` (k,), the points' distances
        along the optical axis (m), only those the cylinder's near side is in front of;
        without it depth is ignored and a point in front of the tool counts as hidden too
        (what a planner that must not overrate a view wants)."""
        return cylinders_hide(cam, self.a[None], self.b[None], np.array([self.radius]),
                              uv, depth)[0]


#: Tool parts are cut this far (m) in front of the camera plane before they are projected.
_TOOL_NEAR = 0.01


def cylinders_hide(cam: CameraModel, a: np.ndarray, b: np.ndarray, radius: np.ndarray,
                   uv: np.ndarray, depth: np.ndarray | None = None) -> np.ndarray:
    """:meth:`ToolCylinder.hides` for ``P`` cylinders at once: ends ``a``, ``b`` (P, 3,
    reference frame, m), ``radius`` (P,, m), against the image points ``uv`` of ``cam``
    (k, 2, px; or (P, k, 2), each cylinder its own points) and their ``depth`` ((k,) or
    (P, k), m, optional). (P, k) bool. One projection for all the cylinders' ends: the
    planners ask this of a few parts at a time, hundreds of thousands of times a trial."""
    uv = np.asarray(uv, dtype=float)
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    P = len(a)
    Tc = cam.T_cam_ref
    A = a @ Tc[:3, :3].T + Tc[:3, 3]
    B = b @ Tc[:3, :3].T + Tc[:3, 3]
    za, zb = A[:, 2], B[:, 2]
    gone = (za <= _TOOL_NEAR) & (zb <= _TOOL_NEAR)
    with np.errstate(divide="ignore", invalid="ignore"):
        cut = A + ((_TOOL_NEAR - za) / (zb - za))[:, None] * (B - A)
    A = np.where((za > _TOOL_NEAR)[:, None], A, cut)
    B = np.where((zb > _TOOL_NEAR)[:, None], B, cut)
    ends = cam.project(np.concatenate([A, B])).reshape(2, P, 1, 2)
    d = ends[1] - ends[0]                                        # (P, 1, 2)
    L2 = (d * d).sum(axis=-1)                                    # (P, 1)
    off = uv - ends[0]                                           # (P, k, 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.clip((off * d).sum(axis=-1) / np.where(L2 > 0, L2, 1.0), 0.0, 1.0)
        t = np.where(L2 > 0, t, 0.0)
        dist = np.linalg.norm(off - t[..., None] * d, axis=-1)
        # the image of a cylinder widens toward the camera: 1/z runs linearly along it
        inv_z = (1.0 - t) / A[:, 2:3] + t / B[:, 2:3]
        hidden = dist <= cam.K[0, 0] * np.asarray(radius, dtype=float)[:, None] * inv_z
        if depth is not None:
            hidden &= (1.0 / inv_z - np.asarray(radius, dtype=float)[:, None]
                       < np.asarray(depth, dtype=float))
    hidden &= ~gone[:, None]
    return hidden


def checked_tools(tools: Sequence[ToolCylinder]) -> tuple[ToolCylinder, ...]:
    """``tools`` as a tuple, refused (:class:`NeedleError`) when one is not a
    :class:`ToolCylinder`."""
    tools = tuple(tools)
    for tool in tools:
        if not isinstance(tool, ToolCylinder):
            raise NeedleError(f"tools must be ToolCylinder parts, got {type(tool).__name__}")
    return tools


def hidden_by(tools: Sequence[ToolCylinder], cam: CameraModel, uv: np.ndarray,
              depth: np.ndarray | None = None) -> np.ndarray:
    """Which image points ``uv`` (k, 2) of ``cam`` any of ``tools`` hides
    (:meth:`ToolCylinder.hides`; ``depth`` as there)."""
    if not tools:
        return np.zeros(len(uv), dtype=bool)
    return cylinders_hide(cam, np.stack([t.a for t in tools]), np.stack([t.b for t in tools]),
                          np.array([t.radius for t in tools]), uv, depth).any(axis=0)


def edge_band(cam: CameraModel, outline: np.ndarray, width_px: float,
              per_edge: int = 64) -> np.ndarray:
    """The pixels of ``cam``'s image within ``width_px`` of the tissue surface's edge
    (bool, image-sized): ``outline`` (k, 3, reference frame, m) is the surface's
    corners in order, each side sampled ``per_edge`` times so that lens distortion
    bends it as it bends the image. Across the edge the backdrop steps from tissue to
    what lies beyond: there the features see neither a wire darker than the tissue nor
    one brighter than the dark, and a wire crossing the band seems to stop at it."""
    o = np.asarray(outline, dtype=float)
    if o.ndim != 2 or o.shape[1] != 3 or len(o) < 3 or not np.all(np.isfinite(o)):
        raise NeedleError(f"the surface outline must be >= 3 finite 3-D points, "
                          f"got shape {o.shape}")
    if not width_px >= 0:
        raise NeedleError(f"edge band width must be >= 0 px, got {width_px}")
    f = np.linspace(0.0, 1.0, per_edge, endpoint=False)[:, None]
    ring = np.concatenate([a + f * (b - a) for a, b in zip(o, np.roll(o, -1, axis=0),
                                                           strict=True)])
    uv = cam.project_from(cam.T_cam_ref, ring)
    uv = uv[np.all(np.isfinite(uv), axis=1)]
    inside = np.zeros((cam.height, cam.width), np.uint8)
    if len(uv) >= 3:
        # sub-pixel vertices (4 fractional bits), so the band is centred on the edge
        cv2.fillPoly(inside, [np.round(uv * 16.0).astype(np.int32)], 1, shift=4)
    # distance of every pixel to the nearest pixel on the other side of the edge, less
    # the half pixel from that pixel's centre to the edge between them
    d_in = cv2.distanceTransform(inside, cv2.DIST_L2, cv2.DIST_MASK_5)
    d_out = cv2.distanceTransform(1 - inside, cv2.DIST_L2, cv2.DIST_MASK_5)
    return np.maximum(d_in, d_out) - 0.5 < width_px


def checked_masks(masks: Sequence[np.ndarray | None], cameras: Sequence[CameraModel],
                  what: str) -> list[np.ndarray | None]:
    """``masks`` as a list, one per camera (bool, image-sized, or ``None``); refused
    (:class:`NeedleError` naming ``what`` masks and the camera) otherwise."""
    masks = list(masks)
    if len(masks) != len(cameras):
        raise NeedleError(f"expected {len(cameras)} {what} masks (one per camera, or "
                          f"None), got {len(masks)}")
    for m, cam in zip(masks, cameras, strict=True):
        if m is not None and (np.asarray(m).dtype != bool
                              or np.shape(m) != (cam.height, cam.width)):
            raise NeedleError(f"camera {cam.name!r}: the {what} mask must be a bool "
                              f"{cam.height} x {cam.width} image, got "
                              f"{np.asarray(m).dtype} {np.shape(m)}")
    return masks


def _at(mask: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """``mask`` (bool image) at the pixels nearest ``uv`` (k, 2); False outside the
    image and where ``uv`` is not finite."""
    ok = np.all(np.isfinite(uv), axis=1)
    px = np.zeros((len(uv), 2), dtype=int)
    px[ok] = np.round(uv[ok]).astype(int)
    h, w = mask.shape
    ok &= (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h)
    out = np.zeros(len(uv), dtype=bool)
    out[ok] = mask[px[ok, 1], px[ok, 0]]
    return out


@dataclass(frozen=True)
class RefineSettings:
    """Refinement settings. Pixels px.

    ``search_px``: the half-width of the normal search of each round (shrinking rounds
    first capture the wire, then lock onto it); ``iterations``: Gauss-Newton steps per
    round; ``points``: arc sample points; ``min_peak``: the ridge value (DN) a peak must
    reach to count; ``tukey_px``: Tukey's constant, residuals beyond it get no weight;
    ``polish_tukey_px``: the least constant of the last round, which otherwise takes it
    from the crest residuals' spread (4.685 times their MAD scale).
    """

    points: int = 72
    search_px: tuple[float, ...] = (10.0, 6.0, 3.0, 3.0)
    step_px: float = 0.5
    iterations: int = 2
    min_peak: float = 6.0
    tukey_px: float = 2.5
    polish_tukey_px: float = 1.0  # the last round's Tukey constant is never below this
    max_rms_px: float = 0.8      # above this the refined pose is not trusted
    min_support: float = 0.6     # share of (visible) sample points that must find the wire
    end_weight: float = 6.0      # an end measurement counts as this many crest points
    margin_px: float = 10.0      # profile beyond the search window, for the crest's flanks
    max_width_ratio: float = 1.3  # crests wider than this times the median are not used
    # the ends' common outward offset (px): the half-level point of a blurred, rounded
    # end sits this far out of it; a pair further than end_bias_tol_px from it holds
    # something that is not an end (where the thread leaves the tangent, an edge)
    end_bias_px: float = 1.25
    end_bias_tol_px: float = 2.75
    # an end seen along the wire ends in the disc of its cut, whose half-extent along
    # the image tangent (its "spread", wire radius in px times the cosine between the
    # wire and the line of sight) blurs where the ridge stops: its variance grows as
    # 1 + (spread / end_spread_px)^2 (fitted on 1358 ends rendered in 20 needle trials:
    # RMS 0.95 px under 1.5 px of spread, 1.9 px at 2.5-3, 3.4 px at 4-6)
    end_spread_px: float = 1.5
    # crest points where the wire runs within this angle of the line of sight are not
    # searched: the wire's image there is its cross-section
    min_sight_angle: float = math.radians(15.0)
    # crest points and ends within this distance of the tissue surface's edge in a view
    # are not measured (:func:`edge_band`): at the true poses of 8 regrasps whose tips
    # stood over the edge, 26-61 % of the crest points within 3 px of it found the wire
    # (88-96 % at 3-6 px, all beyond 6), and every tip 5-7.5 px beyond the edge was
    # read as ending on it
    edge_band_px: float = 6.0

    def __post_init__(self) -> None:
        if self.points < 8 or not self.search_px or min(self.search_px) <= self.step_px:
            raise NeedleError("refinement needs >= 8 points and search windows wider "
                              "than the step")
        if not (self.step_px > 0 and self.iterations >= 1 and self.tukey_px > 0
                and self.polish_tukey_px > 0 and self.end_spread_px > 0
                and 0.0 <= self.min_sight_angle < 0.5 * math.pi
                and self.edge_band_px >= 0):
            raise NeedleError("step_px > 0, iterations >= 1, tukey_px > 0, "
                              "polish_tukey_px > 0, end_spread_px > 0, 0 <= "
                              "min_sight_angle < pi/2 and edge_band_px >= 0 are required")


@dataclass(frozen=True)
class Refined:
    """A refined pose ``T_ref_N`` with its quality.

    ``rms_px``: RMS of the weighted residuals over the points that found the wire;
    ``support``: the share of the sample points inside the images (and out of the
    tissue, when an occluder is given) that found it;
    ``sigma_position`` (m) and ``sigma_angle`` (rad): one standard deviation of the
    needle centre's position and of its orientation from the pose covariance (largest
    axis); ``sigma_slide`` (rad): that of the turn about the needle's own axis (the slide
    along the arc, which only the ends measure), ``sigma_slide_seen`` the same from these
    images alone (without the prior); ``sigma_tilt`` (rad): that of the needle's plane
    (the turns about the axes in it, largest; the circle's orientation without the
    slide); ``ok``: ``rms_px`` and ``support`` within
    the settings' bounds; ``cov``: the pose covariance (6x6, :func:`_perturb`'s local
    parameters, prior included; ``None`` when the normal equations are singular);
    ``prior_distance2``: the squared Mahalanobis distance of the pose from the prior
    (0 without one; large: the images moved the pose away from what was expected).
    """

    pose: np.ndarray
    rms_px: float
    support: float
    sigma_position: float
    sigma_angle: float
    ok: bool
    sigma_slide: float = math.inf
    sigma_slide_seen: float = math.inf
    cov: np.ndarray | None = None
    prior_distance2: float = 0.0
    sigma_tilt: float = math.inf


@dataclass(frozen=True, eq=False)
class PosePrior:
    """What is known of a pose before the images: ``pose`` (``T_ref_N``) and the
    information matrix ``info`` (6x6, the inverse covariance) of the local parameters
    of :func:`_perturb` (rotation vector, rad, then translation, m, both in frame N).
    A zero row leaves that parameter to the images. Made by :meth:`from_cov` (a
    tracked pose moved by a known motion) or :meth:`slide` (only the slide along the
    arc is known)."""

    pose: np.ndarray
    info: np.ndarray

    def __post_init__(self) -> None:
        T, info = np.asarray(self.pose, dtype=float), np.asarray(self.info, dtype=float)
        if not (T.shape == (4, 4) and np.all(np.isfinite(T))):
            raise NeedleError(f"pose prior: need a finite 4x4 pose, got shape {T.shape}")
        finite = info.shape == (6, 6) and bool(np.all(np.isfinite(info)))
        tol = 1e-9 * max(1.0, float(np.abs(info).max())) if finite else 0.0
        if not (finite and np.allclose(info, info.T, atol=tol)
                and np.linalg.eigvalsh(info).min() >= -tol):
            raise NeedleError("pose prior: the information matrix must be a finite, "
                              "symmetric, positive semi-definite 6x6")
        object.__setattr__(self, "pose", T)
        object.__setattr__(self, "info", info)

    @classmethod
    def from_cov(cls, pose: np.ndarray, cov: np.ndarray) -> PosePrior:
        """From a covariance (6x6, local parameters; rad^2, m^2)."""
        cov = np.asarray(cov, dtype=float)
        if not (cov.shape == (6, 6) and np.all(np.isfinite(cov))):
            raise NeedleError(f"pose prior: need a finite 6x6 covariance, got {cov.shape}")
        try:
            info = np.linalg.inv(cov)
        except np.linalg.LinAlgError:
            raise NeedleError("pose prior: the covariance is singular") from None
        return cls(pose, 0.5 * (info + info.T))

    @classmethod
    def slide(cls, pose: np.ndarray, sigma: float) -> PosePrior:
        """Only the slide along the arc (the turn about N's z) is known, to ``sigma``
        rad (a needle in closed jaws or in tissue cannot slide far)."""
        if not (sigma > 0 and math.isfinite(sigma)):
            raise NeedleError(f"pose prior: the slide's sigma must be finite and > 0 rad, "
                              f"got {sigma}")
        info = np.zeros((6, 6))
        info[2, 2] = 1.0 / (sigma * sigma)
        return cls(pose, info)

    def residual(self, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The local parameters of ``T`` from the prior pose and their Jacobian with
        respect to :func:`_perturb`'s parameters at ``T`` (rotation to first order)."""
        Rp, R = self.pose[:3, :3], T[:3, :3]
        e = np.concatenate([Rotation.from_matrix(Rp.T @ R).as_rotvec(),
                            Rp.T @ (T[:3, 3] - self.pose[:3, 3])])
        J = np.eye(6)
        J[3:, 3:] = Rp.T @ R
        return e, J


#: Forward-difference step of the refinement's Jacobian (rad, m).
_JAC_EPS = 1e-6


def _perturb(T: np.ndarray, xi: np.ndarray) -> np.ndarray:
    """``T @ exp(xi)`` with ``xi = (rotation vector, translation)`` in frame N: the
    parameters are local to the needle, so the rotation turns it about its own centre."""
    D = np.eye(4)
    D[:3, :3] = Rotation.from_rotvec(xi[:3]).as_matrix()
    D[:3, 3] = xi[3:]
    return T @ D


class PoseRefiner:
    """Refines needle poses seen by ``cameras`` (sharing the reference frame)."""

    def __init__(self, needle: Needle, cameras: Sequence[CameraModel],
                 settings: RefineSettings | None = None) -> None:
        if not cameras:
            raise NeedleError("refinement needs at least one camera")
        self.needle, self.cameras = needle, tuple(cameras)
        self.s = settings or RefineSettings()
        self.points = needle.points(self.s.points)
        # tangents in N, for the projected normal
        phi = np.linspace(0.0, needle.arc, self.s.points)
        self.tangents = np.asarray(needle.tangent(phi))
        self.T_cam_ref = [c.T_cam_ref for c in self.cameras]
        # everything a round projects, in one array (one projection per camera, not
        # five): the sample points, the points a little before and after each along the
        # arc (the image normal), the base and the tip and a point just past each (the
        # outward image tangent); each row is projected on its own, so the values are
        # those of separate calls
        K = self.s.points
        eps = 2e-4      # m along the tangent: a few pixels
        ends = np.stack([self.points[0], self.points[-1]])
        out_dir = np.stack([-self.tangents[0], self.tangents[-1]])
        self._probe = np.concatenate([self.points, self.points - eps * self.tangents,
                                      self.points + eps * self.tangents, ends,
                                      ends + eps * out_dir])
        self._cuts = np.cumsum([K, K, K, 2])
        # the Jacobian's forward-difference steps: constant, so made once
        self._steps = [_perturb(np.eye(4), _JAC_EPS * e) for e in np.eye(6)]
        self._windows: dict[float, tuple[np.ndarray, np.ndarray]] = {}

    def edge_bands(self, outline: np.ndarray) -> list[np.ndarray]:
        """Per camera, the tissue surface's edge band (:func:`edge_band`, of
        ``edge_band_px``) for :meth:`refine`'s ``blind``; ``outline`` (k, 3, reference
        frame, m): the surface's corners in order."""
        return [edge_band(cam, outline, self.s.edge_band_px) for cam in self.cameras]

    def _project(self, T: np.ndarray, pts: np.ndarray) -> list[np.ndarray]:
        return [cam.project_from(Tc @ T, pts) for cam, Tc in zip(self.cameras, self.T_cam_ref,
                                                                  strict=True)]

    @staticmethod
    def _unit(d: np.ndarray) -> np.ndarray:
        """Rows of ``d`` (M, 2) made unit; NaN where zero."""
        ln = np.linalg.norm(d, axis=1, keepdims=True)
        return d / np.where(ln > 0, ln, np.nan)

    def _geometry(self, T: np.ndarray
                  ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Per camera, at pose ``T``: the projected sample points (K, 2), the unit image
        normals of the projected arc there (K, 2), and the outward unit image tangents
        at the base and the tip (2, 2); NaN where undefined."""
        out = []
        for uv in self._project(T, self._probe):
            pts, before, after, ends, past = np.split(uv, self._cuts)
            d = self._unit(after - before)
            out.append((pts, np.stack([-d[:, 1], d[:, 0]], axis=1), self._unit(past - ends)))
        return out

    def _window(self, half: float) -> tuple[np.ndarray, np.ndarray]:
        """The crest search's sample offsets (px) for a window of ``half`` px and the
        prior over them, made once per window size."""
        w = self._windows.get(half)
        if w is None:
            s = self.s
            offs = np.arange(-half - s.margin_px, half + s.margin_px + 1e-9, s.step_px)
            # prefer the crest nearest the prediction when two features are in the window
            # (the wire and the thread, the jaws or the incision)
            prior = np.where(np.abs(offs) <= half, np.exp(-0.5 * (offs / half) ** 2), 0.0)
            w = self._windows[half] = (offs, prior)
        return w

    def _peaks(self, ridge: np.ndarray, uv: np.ndarray, n: np.ndarray, half: float,
               use: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Sub-pixel offset (px, along ``n``) of the ridge's crest near each point, and
        whether one was found (NaN offset otherwise); ``use`` (bool, per point): the
        points to search (the others, hidden, are not found and take no part in the
        crest's median width).

        The crest is the highest sample within ``half`` px (nearer ones preferred); its
        position is the midpoint of the two half-height crossings around it, each
        interpolated linearly: a wide wire's profile is flat on top, where a parabola
        through the top three samples would wander, while the flanks are steep and, for
        a symmetric profile, centred on the axis."""
        s = self.s
        offs, prior = self._window(half)
        M = offs.size
        xy = uv[:, None, :] + offs[None, :, None] * n[:, None, :]
        prof = cv2.remap(ridge, xy[..., 0].astype(np.float32), xy[..., 1].astype(np.float32),
                         cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
        prof = np.nan_to_num(prof.astype(float))
        k = np.argmax(prof * prior, axis=1)
        rows = np.arange(len(k))
        h = 0.5 * prof[rows, k]
        idx = np.arange(M)
        below = prof < h[:, None]
        lc = np.where(below & (idx < k[:, None]), idx, -1).max(axis=1)
        rc = np.where(below & (idx > k[:, None]), idx, M).min(axis=1)
        found = ((lc >= 0) & (rc < M) & (2.0 * h >= s.min_peak)
                 & np.all(np.isfinite(uv), axis=1))
        if use is not None:
            found &= use
        lc0, rc0 = np.clip(lc, 0, M - 2), np.clip(rc, 1, M - 1)
        a0, a1 = prof[rows, lc0], prof[rows, lc0 + 1]
        b0, b1 = prof[rows, rc0 - 1], prof[rows, rc0]
        xl = offs[lc0] + s.step_px * (h - a0) / np.maximum(a1 - a0, 1e-9)
        xr = offs[rc0 - 1] + s.step_px * (b0 - h) / np.maximum(b0 - b1, 1e-9)
        # a crest much wider than the wire's elsewhere is the wire merged with something
        # beside it (a pad edge, the thread, a jaw): its midpoint is pulled aside
        width = xr - xl
        if np.count_nonzero(found) >= 8:
            found &= width <= s.max_width_ratio * float(np.median(width[found])) + 1.0
        return np.where(found, 0.5 * (xl + xr), np.nan), found

    @staticmethod
    def _sight(T_cam_ref: np.ndarray, pts: np.ndarray, dirs: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
        """Per point (``pts`` with unit directions ``dirs``, (n, 3), reference frame):
        the |cosine| between the direction and the camera's line of sight to the point,
        and the point's depth in the camera (m)."""
        p = pts @ T_cam_ref[:3, :3].T + T_cam_ref[:3, 3]
        d = dirs @ T_cam_ref[:3, :3].T
        cos = np.abs(np.einsum("ij,ij->i", d, p)) / np.linalg.norm(p, axis=1)
        return cos, p[:, 2]

    def _across_sight(self, T_cam_ref: np.ndarray, pts: np.ndarray, T: np.ndarray
                      ) -> np.ndarray:
        """Per sample point (``pts``, reference frame, of the needle at ``T``): whether
        the wire there runs at least ``min_sight_angle`` off the camera's line of sight."""
        cos, _ = self._sight(T_cam_ref, pts, self.tangents @ T[:3, :3].T)
        return cos <= math.cos(self.s.min_sight_angle)

    def _end_spread(self, cam: CameraModel, T_cam_ref: np.ndarray, end_pts: np.ndarray,
                    end_dirs: np.ndarray) -> np.ndarray:
        """Per end (base, tip; points and outward unit tangents ``(2, 3)``, reference
        frame): the half-extent (px) of the wire's cut end along the image tangent, the
        wire's radius in pixels times the cosine between the wire and the line of sight.
        Near 0 for an end seen side-on; the wire's radius for one pointing at the camera,
        whose half-level point then says little about how far the wire reaches."""
        cos, depth = self._sight(T_cam_ref, end_pts, end_dirs)
        return float(cam.K[0, 0]) * 0.5 * self.needle.wire_diameter \
            / np.maximum(depth, 1e-6) * cos

    def _end(self, ridge: np.ndarray, uv: np.ndarray, t: np.ndarray, half: float) -> float:
        """Offset (px, along the outward image tangent ``t``) of the wire's end from the
        projected end point ``uv``: where the ridge falls to half its level on the wire;
        NaN when it does not fall inside the window (the end hidden or continued by the
        thread) or no wire is there."""
        s = self.s
        half = _end_half(half)
        offs = np.arange(-2.0 * half, 2.0 * half + 1e-9, s.step_px)
        xy = (uv[None, :] + offs[:, None] * t[None, :]).astype(np.float32)
        prof = cv2.remap(ridge, xy[:, 0:1], xy[:, 1:2], cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)[:, 0].astype(float)
        on = float(np.median(prof[offs < -half]))
        if not on >= 2.0 * s.min_peak:
            return math.nan
        below = np.nonzero(prof < 0.5 * on)[0]
        below = below[offs[below] > -half]
        if below.size == 0:
            return math.nan
        k = int(below[0])
        if k == 0 or np.any(prof[k:] >= 0.5 * on):
            return math.nan       # it rises again: another feature, not a clean end
        # linear interpolation between the last sample above half and the first below
        a, b = prof[k - 1], prof[k]
        return float(offs[k - 1] + s.step_px * (a - 0.5 * on) / max(a - b, 1e-9))

    @staticmethod
    def _end_clear(blind: np.ndarray | None, uv: np.ndarray, t: np.ndarray,
                   half: float) -> bool:
        """Whether the end search's window at ``uv`` (px) along the outward tangent
        ``t`` (:meth:`_end`) stays off the ``blind`` pixels (none: clear)."""
        if blind is None:
            return True
        h = _end_half(half)
        offs = np.arange(-2.0 * h, 2.0 * h + 1e-9, 1.0)
        return not np.any(_at(blind, uv[None, :] + offs[:, None] * t[None, :]))

    def _measure(self, ridges: list[np.ndarray], ends: list[np.ndarray], T: np.ndarray,
                 half: float, occluder: TissuePlane | None = None, tip_only: bool = False,
                 tools: Sequence[ToolCylinder] = (),
                 blind: Sequence[np.ndarray | None] | None = None
                 ) -> tuple[list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]],
                            int, int]:
        """Per camera, the measurements ``(point index, image direction, target pixel,
        weight)``: the ridge crest along the normal at every sample point, and the wire's
        end along the tangent at the base and the tip (weighted as ``end_weight`` points:
        sliding along itself is the one motion of an arc that its crest cannot see).
        Also the number of sample points that found the crest and of those in the
        images. Points under ``occluder``, behind one of ``tools`` or on a ``blind``
        pixel (per camera; see :meth:`refine`) in that view are not searched and not
        counted in the images; a hidden end, or one whose search reaches a blind pixel,
        gives no end measurement."""
        s = self.s
        K = self.points.shape[0]
        pts = self.points @ T[:3, :3].T + T[:3, 3]
        seen = None
        if occluder is not None:
            seen = occluder.visible(pts, 0.5 * self.needle.wire_diameter)
        # the ends' outward tangents (reference frame), for their spread in each view
        end_pts = pts[[0, K - 1]]
        end_dirs = np.stack([-self.tangents[0], self.tangents[-1]]) @ T[:3, :3].T
        out, found_n, inside = [], 0, 0
        blinds = [None] * len(self.cameras) if blind is None else blind
        for ridge, endmap, (uv, n, tg), cam, Tc, bl in zip(ridges, ends, self._geometry(T),
                                                           self.cameras, self.T_cam_ref,
                                                           blinds, strict=True):
            vis = seen
            if tools:
                hidden = hidden_by(tools, cam, uv, pts @ Tc[2, :3] + Tc[2, 3])
                vis = ~hidden if vis is None else vis & ~hidden
            if bl is not None:
                clear = ~_at(bl, uv)
                vis = clear if vis is None else vis & clear
            # a point where the wire runs nearly along the line of sight shows its
            # cross-section, a blob the crest search across the arc cannot place (the
            # base standing out of the entry toward the cameras curls into a hook a few
            # pixels wide): neither searched nor counted as missing
            crest = self._across_sight(Tc, pts, T)
            if vis is not None:
                crest &= vis
            d, found = self._peaks(ridge, uv, n, half, crest)
            found &= np.all(np.isfinite(n), axis=1)
            idx = [np.nonzero(found)[0]]
            # rows are 4 wide so the end pair (two directions, two targets) fits
            z2 = np.zeros((int(np.count_nonzero(found)), 2))
            dirs = [np.hstack([n[found], z2])]
            tgt = [np.hstack([uv[found] + d[found, None] * n[found], z2])]
            wts = [np.ones(int(np.count_nonzero(found)))]
            # the ends, as a difference: sliding along itself moves one end out and the
            # other in by the same amount, while whatever biases both ends alike (blur,
            # shading, how the ends are cut) cancels. Rows with index -1 are this pair.
            if np.all(np.isfinite(uv[[0, K - 1]])) and np.all(np.isfinite(tg)):
                # an end in the tissue: the visible wire stops at the surface, an end
                # that is not the needle's
                ob = self._end(endmap, uv[0], tg[0], half) \
                    if (vis is None or vis[0]) and not tip_only \
                    and self._end_clear(bl, uv[0], tg[0], half) else math.nan
                ot = self._end(endmap, uv[K - 1], tg[1], half) \
                    if (vis is None or vis[K - 1]) \
                    and self._end_clear(bl, uv[K - 1], tg[1], half) else math.nan
                b0 = s.end_bias_px
                # each end's variance, relative to a clean end's (see end_spread_px)
                grow = 1.0 + (self._end_spread(cam, Tc, end_pts, end_dirs)
                              / s.end_spread_px) ** 2
                weight = s.end_weight / float(np.mean(grow))
                if math.isfinite(ob) and math.isfinite(ot) \
                        and abs(0.5 * (ob + ot) - b0) > s.end_bias_tol_px:
                    # the two disagree: a pose slid along the thread finds a false "end"
                    # where the thread leaves the tangent, and as a pair it would hold
                    # the pose half-way; keep the end nearer the expected offset
                    if abs(ob - b0) > abs(ot - b0):
                        ob = math.nan
                    else:
                        ot = math.nan
                if math.isfinite(ob) != math.isfinite(ot):
                    # one end only (the thread continues the crest past the swage, an
                    # end is hidden, or it was dropped above): paired with the other end
                    # where the expected bias puts it, so it still measures the slide
                    # alone (a lone end's residual would also push the pose sideways,
                    # into the directions the crest barely sees), at half weight
                    if math.isfinite(ob):
                        ot = 2.0 * b0 - ob
                        weight = 0.5 * s.end_weight / float(grow[0])
                    else:
                        ob = 2.0 * b0 - ot
                        weight = 0.5 * s.end_weight / float(grow[1])
                if math.isfinite(ob) and math.isfinite(ot):
                    idx.append(np.array([-1]))
                    dirs.append(np.concatenate([tg[0], tg[1]])[None])
                    tgt.append(np.concatenate([uv[0] + ob * tg[0], uv[K - 1] + ot * tg[1]])[None])
                    wts.append(np.array([weight]))
            out.append((np.concatenate(idx), np.concatenate(dirs), np.concatenate(tgt),
                        np.concatenate(wts)))
            found_n += int(np.count_nonzero(found))
            inside += int(np.count_nonzero(cam.in_image(uv) & crest))
        return out, found_n, inside

    def refine(self, features: Sequence[NeedleFeatures], T: np.ndarray, *,
               occluder: TissuePlane | None = None, tip_only: bool = False,
               tools: Sequence[ToolCylinder] = (),
               prior: PosePrior | None = None,
               search_px: Sequence[float] | None = None,
               blind: Sequence[np.ndarray | None] | None = None) -> Refined:
        """Refine ``T`` (``T_ref_N``) on the cameras' features (:func:`.needle_features.
        feature_maps`, one per camera, same order): the crest on ``ridge``, the ends on
        ``ends``. ``occluder``: the tissue's surface when the needle may be in it (what
        lies under it is not looked for, and ``Refined.support`` counts only what is
        out); visibility is judged anew at each round's pose. ``tip_only``: the base's end
        is not measured (a threaded needle: the thread continues the wire past the swage,
        and where it leaves the tangent looks like an end), so the tip alone holds the
        slide along the arc. ``tools``: the instruments' parts in view (jaws, shafts),
        which hide what lies behind them in each view as the tissue does.
        ``prior``: what is known of the pose before these images (:class:`PosePrior`: a
        tracked pose moved by a known motion, or only its slide): weighed with the
        images' measurements, it keeps determined what the jaws or the tissue hide (the
        slide while both ends are hidden, the depth a short baseline barely measures).
        Ignored when the prior's pose is the other twin (turned more than 90 deg from
        ``T``). ``search_px``: the rounds' search windows in place of the settings' (a
        start already on the wire needs no wide capture rounds). ``blind``: per camera,
        the pixels whose features cannot show the wire (bool, image-sized, or ``None``:
        none), such as the tissue surface's edge band (:meth:`edge_bands`): the wire
        is neither looked for nor missed there, and no end is read across them."""
        s = self.s
        windows = tuple(s.search_px if search_px is None else search_px)
        if not windows or min(windows) <= s.step_px:
            raise NeedleError(f"search windows must be wider than the step "
                              f"({s.step_px} px), got {windows!r}")
        tools = checked_tools(tools)
        if occluder is not None:
            if not isinstance(occluder, TissuePlane):
                raise NeedleError(f"occluder must be a TissuePlane or None, got "
                                  f"{type(occluder).__name__}")
            occluder.check_cameras(self.cameras)
        if len(features) != len(self.cameras):
            raise NeedleError(f"expected {len(self.cameras)} feature sets (one per camera), "
                              f"got {len(features)}")
        for f, cam in zip(features, self.cameras, strict=True):
            for what in ("ridge", "ends"):
                if getattr(f, what).shape != (cam.height, cam.width):
                    raise NeedleError(f"camera {cam.name!r}: {what} image is "
                                      f"{getattr(f, what).shape}, the camera is "
                                      f"{cam.height} x {cam.width}")
        if blind is not None:
            blind = checked_masks(blind, self.cameras, "blind")
        ridges = [np.asarray(f.ridge, dtype=np.float32) for f in features]
        ends = [np.asarray(f.ends, dtype=np.float32) for f in features]
        T = np.asarray(T, dtype=float).copy()
        if prior is not None:
            if not isinstance(prior, PosePrior):
                raise NeedleError(f"prior must be a PosePrior or None, got "
                                  f"{type(prior).__name__}")
            if rotation_angle(prior.pose[:3, :3], T[:3, :3]) >= 0.5 * math.pi:
                prior = None
        rms, support, H = math.inf, 0.0, None
        rounds = (*windows, windows[-1])
        for n_round, half in enumerate(rounds):
            meas, found_n, inside = self._measure(ridges, ends, T, half, occluder, tip_only,
                                                  tools, blind)
            support = found_n / max(inside, 1)
            if found_n < 8:
                H = None
                break
            for _ in range(s.iterations):
                r, J, w0 = self._linearise(T, meas)
                # Tukey's constant covers the round's window: a point found 8 px out in a
                # 10 px search is the wire seen from a pose still 8 px off, not an outlier
                c = np.where(w0 > 1.0, max(s.tukey_px, 2.0 * max(half, 6.0)),
                             max(s.tukey_px, half))
                if n_round == len(rounds) - 1:
                    # the last round, on the wire: the crest points' own spread sets the
                    # constant (Tukey's 4.685 times their MAD scale). Where a shaft, the
                    # incision or the pad's edge crosses the wire, its crest bends 1-4 px
                    # toward them over a few points, and weighted at the window's
                    # constant those runs pulled a held needle 13 deg off in tilt
                    # (trial 69's hand-off), at 0.1 px elsewhere
                    crest = w0 <= 1.0
                    if np.count_nonzero(crest) >= 8:
                        mad = float(np.median(np.abs(r[crest] - np.median(r[crest]))))
                        c = np.where(crest, max(s.polish_tukey_px, 6.946 * mad), c)
                w = w0 * (1.0 - np.minimum((r / c) ** 2, 1.0)) ** 2
                if np.count_nonzero(w) < 8:
                    H = None
                    break
                H = (J * w[:, None]).T @ J
                g = (J * w[:, None]).T @ r
                rms = float(np.sqrt(np.sum(w * r * r) / max(np.sum(w), 1e-12)))
                Hs, gs = H, g
                damp = 1e-6 * np.trace(H) / 6 * np.eye(6)
                if prior is not None:
                    # the prior in the measurements' units (px^2 per unit of information
                    # at this RMS), on the local parameters from the prior's pose
                    e, Jp = prior.residual(T)
                    k = max(rms, 0.1) ** 2
                    JI = Jp.T @ prior.info
                    Hs = H + k * JI @ Jp
                    gs = g + k * JI @ e
                    # a touch of damping keeps a weak direction (a single view's depth)
                    # from running away before the next search; a direction the prior
                    # holds needs none, and damping there would only slow the prior
                    held = np.diag(prior.info) > 0
                    damp[held, held] = 0.0
                step = np.linalg.solve(Hs + damp, -gs)
                T = _perturb(T, step)
        sig_a = sig_p = sig_s = sig_seen = sig_t = math.inf
        cov = None
        d2, Jp = 0.0, None
        if prior is not None:
            e, Jp = prior.residual(T)
            d2 = float(e @ prior.info @ e)
        if H is not None:
            # the last round's normal equations; residual scale floored at 0.1 px so a
            # perfect synthetic fit does not claim a perfect pose
            info = H / max(rms, 0.1) ** 2
            try:
                sig_seen = math.sqrt(max(float(np.linalg.inv(info)[2, 2]), 0.0))
            except np.linalg.LinAlgError:
                pass
            if prior is not None:
                info = info + Jp.T @ prior.info @ Jp
            try:
                cov = np.linalg.inv(info)
                cov = 0.5 * (cov + cov.T)
                sig_a = math.sqrt(max(float(np.linalg.eigvalsh(cov[:3, :3]).max()), 0.0))
                sig_p = math.sqrt(max(float(np.linalg.eigvalsh(cov[3:, 3:]).max()), 0.0))
                sig_s = math.sqrt(max(float(cov[2, 2]), 0.0))
                sig_t = math.sqrt(max(float(np.linalg.eigvalsh(cov[:2, :2]).max()), 0.0))
            except np.linalg.LinAlgError:
                cov = None
        ok = bool(rms <= s.max_rms_px and support >= s.min_support)
        return Refined(T, rms, support, sig_p, sig_a, ok, sig_s, sig_seen, cov, d2, sig_t)

    def _linearise(self, T: np.ndarray,
                   meas: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Residuals ``dir . (uv - target)`` (px) of the measurements, their Jacobian with
        respect to the local pose parameters (forward differences) and prior weights."""
        eps = _JAC_EPS
        # the pose and its six perturbations projected in one call per camera
        Ts = [T] + [T @ D for D in self._steps]
        K = self.points.shape[0]
        pts = np.concatenate([self.points @ Ti[:3, :3].T + Ti[:3, 3] for Ti in Ts])
        proj = [cam.project_from(Tc, pts).reshape(7, K, 2)
                for cam, Tc in zip(self.cameras, self.T_cam_ref, strict=True)]
        rs, Js, ws = [], [], []
        for P, (idx, dirs, tgt, wt) in zip(proj, meas, strict=True):
            base = P[0]
            pt = idx >= 0
            i = idx[pt]
            r = np.einsum("ki,ki->k", base[i] - tgt[pt, :2], dirs[pt, :2])
            # all six columns at once: (6, k, 2) differences along the measured directions
            J = np.einsum("jki,ki->kj", (P[1:, i] - base[i]) / eps, dirs[pt, :2])
            if not np.all(pt):
                # the end pair: half the difference of the tip's and the base's offsets
                d, g = dirs[~pt][0], tgt[~pt][0]
                r = np.append(r, _pair(base, d, g))
                J = np.vstack([J, [(_pair(P[j + 1], d, g) - r[-1]) / eps
                                   for j in range(6)]])
            ok = np.isfinite(r) & np.all(np.isfinite(J), axis=1)
            rs.append(r[ok])
            Js.append(J[ok])
            ws.append(np.concatenate([wt[pt], wt[~pt]])[ok])
        return np.concatenate(rs), np.concatenate(Js), np.concatenate(ws)


def _end_half(half: float) -> float:
    """The end search's half-window (px) for a round of ``half``: it does not shrink
    with the crest's, since the half-level point sits a couple of pixels out of a flat
    end (blur), on both ends alike."""
    return max(half, 6.0)


def _pair(uv: np.ndarray, d: np.ndarray, g: np.ndarray) -> float:
    """The end pair's residual (px): half the difference of the tip's offset from its
    target along its outward direction (``d[2:]``, ``g[2:]``) and the base's
    (``d[:2]``, ``g[:2]``), for projected arc points ``uv`` (base first, tip last)."""
    return 0.5 * (float((uv[-1] - g[2:]) @ d[2:]) - float((uv[0] - g[:2]) @ d[:2]))


def swage_evidence(needle: Needle, cameras: Sequence[CameraModel],
                   ridges: Sequence[np.ndarray], T: np.ndarray, *,
                   span: tuple[float, float] = (0.002, 0.008), points: int = 12,
                   cone: float = 0.15, cone_out: float | None = None,
                   tools: Sequence[ToolCylinder] = ()) -> float:
    """How much more ridge lies beyond the base than beyond the tip (DN, mean over the
    views): the suture thread leaves the swage, nothing leaves the tip. Positive: ``T``
    has the base where the thread is; negative: the twin (base and tip swapped) is
    right; near 0: no cue (no thread visible, or both ends hidden).

    Samples ``points`` distances ``span`` (m) past each end along the arc's tangent: not
    right at the end, where a pose slid a little along the arc would read the wire; and
    as far as a few millimetres, so that a pose slid along the arc by as much (its one
    end inside the wire, the other out on the thread) reads the wire stopping short
    beyond the first end and the thread going on beyond the other. At each distance
    ``d`` the thread may have bent off the tangent: the ridge's highest value across a
    cross of half-width ``cone * d`` in the needle's plane and ``cone_out * d`` out of it
    (``cone`` unless given) is taken.
    Samples behind one of ``tools`` in a view are not read there: a jaw beside an end
    is a ridge too, and would pass for the thread. Nor are samples within a wire's width
    of the needle's own image: seen nearly edge-on, the tangent beyond an end runs back
    over the wire, which would pass for thread at that end (trial 84's approach to the
    entry: -31 DN at the true pose, and the tracker turned the needle end for end).
    """
    arc = needle.points(181)
    d = np.linspace(span[0], span[1], points)
    lat = np.linspace(-cone, cone, 5)
    out = lat if cone_out is None else np.tan(np.linspace(
        -cone_out, cone_out, 2 * max(2, math.ceil(cone_out / cone)) + 1))
    # unit offsets across the tangent at each end: in the plane (radial) and out of it
    ends = []
    for p, t in ((needle.base, -needle.tangent(0.0)), (needle.tip, needle.tangent(needle.arc))):
        radial = p / np.linalg.norm(p)
        ez = np.array([0.0, 0.0, 1.0])
        across = np.concatenate([lat[:, None] * radial, out[:, None] * ez])
        pts = p + d[:, None, None] * (t[None, None, :] + across[None, :, :])    # (n, 10, 3)
        ends.append(pts.reshape(-1, 3))
    diffs = []
    for cam, ridge in zip(cameras, ridges, strict=True):
        Tc = cam.T_cam_ref @ T
        own = cam.project_from(Tc, arc)
        own = own[np.all(np.isfinite(own), axis=1)]
        vals = []
        for pts in ends:
            uv = cam.project_from(Tc, pts).astype(np.float32)
            ok = np.all(np.isfinite(uv), axis=1) & cam.in_image(uv)
            depth = pts @ Tc[2, :3] + Tc[2, 3]
            if tools:
                ok &= ~hidden_by(tools, cam, uv, depth)
            if len(own):
                # the wire's width in pixels at each sample's depth
                width = cam.K[0, 0] * needle.wire_diameter / np.maximum(depth, 1e-9)
                near = np.min(np.linalg.norm(uv[:, None, :] - own[None, :, :], axis=2),
                              axis=1)
                ok &= ~(near < width)
            v = cv2.remap(np.asarray(ridge, np.float32), uv[:, 0:1], uv[:, 1:2],
                          cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                          borderValue=0.0)[:, 0].astype(float)
            v = np.where(ok, v, np.nan).reshape(points, -1)
            seen = np.any(np.isfinite(v), axis=1)
            if not np.any(seen):
                vals.append(math.nan)
                continue
            vals.append(float(np.mean(np.nanmax(v[seen], axis=1))))
        if all(math.isfinite(v) for v in vals):
            diffs.append(vals[0] - vals[1])
    return float(np.mean(diffs)) if diffs else 0.0
