"""Pose of a marker field from its corners in one or more cameras: PnP, BA and NVG-BA.

The navigation paper (seed 000, section III.D) estimates a coarse pose by PnP, then refines
it by bundle adjustment over every camera that sees the field (eqs. 15-16), and in NVG-BA
weights each corner by how squarely the camera sees it (eqs. 9-14, 17).

**Eq. 14 as printed is inverted.** It sets the weight to ``arccos(n . z)``, the obliquity
itself, so a corner seen face-on would get weight 0 and a grazing one the most, which
contradicts the sentence before it ("the more perpendicular the crosspoint is to the camera
plane, the larger its corresponding weight"). The default here follows the text: weights that
fall with obliquity (``cos``, ``cos2``); ``paper`` keeps the printed formula so the
benchmark can chart the variants. Obliquity is measured against the line of sight to the
corner, which is what foreshortens it; the paper's camera z axis differs from it by at most
the half field of view (``axis`` uses the z axis with the ``cos`` weight).

Parametrisation and covariance: the pose ``T_ref_field`` is updated as
``R <- Rot(dtheta) R``, ``t <- t + dt`` with ``[dt (m), dtheta (rad)]`` in the reference
frame, so the 6x6 covariance is that of the field origin's position and of a rotation vector
in the reference frame. It is ``s^2 (J^T W J)^-1`` at the solution, with ``s^2`` the weighted
residual variance pooled with a prior corner noise (a 4-corner tag has 2 residual degrees of
freedom, too few to know its own noise); tag corners add a shift shared by every tag edge,
which no residual shows; and a planar set seen by one camera adds its other, mirrored pose
(issue 34 item 6; :func:`_covariance`, docs/tracking.md).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal, Protocol

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from oralnav.control.vision.camera import CameraModel
from oralnav.control.vision.markers import MarkerField


class CornerModel(Protocol):
    """What plain BA (``weighting="none"``) reads of a model: its corners (N x 3, model
    frame, m). A :class:`MarkerField` is one; so is a rigid body's tag-corner table."""

    @property
    def corners(self) -> np.ndarray: ...


Weighting = Literal["none", "cos", "cos2", "axis", "paper"]
WEIGHTINGS: tuple[str, ...] = ("none", "cos", "cos2", "axis", "paper")
#: The weighting NVG-BA uses unless told otherwise (see docs/tracking.md for the choice).
DEFAULT_WEIGHTING: Weighting = "cos2"

#: Smallest residual standard deviation (px) used for the covariance.
MIN_SIGMA_PX = 0.05
#: Levenberg-Marquardt stop from IPPE's other pose to the other minimum of a planar set's
#: fit: 30 steps, or a step under 1e-10 (rad, and m over the normalised plane).
_AMBIGUITY_LM = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 1e-10)
#: Residuals above this many robust sigmas (and above ``MIN_OUTLIER_PX``) are outliers.
OUTLIER_SIGMAS = 4.0
MIN_OUTLIER_PX = 1.0
#: A coplanar corner set whose image is thinner than this (width / length of its spread)
#: is seen edge-on and refused (see ``_degenerate``).
MIN_EDGE_ON_SPREAD = 0.06


@dataclass(frozen=True)
class CornerNoise:
    """What a fit's covariance assumes of its corners' image errors (px, per image axis).

    Attributes:
        sigma_px: the independent error of one corner coordinate expected before the
            fit's residuals are seen (the prior of :func:`pixel_variance`).
        dof: how many residual degrees of freedom that prior is worth.
        edge_sigma_px: standard deviation of a shift along their normals shared by every
            tag edge in one image (0 for corners that are not tag corners). Such a shift
            leaves no residual (a tag shrunk by it fits as a farther tag), so it adds to
            the covariance whatever the fit's residuals.
        small_side_px: tags whose image side is shorter than this (px) have corners
            worse by ``small_side_px / side``: their shift grows by that factor and their
            corner noise by its square (0: no such growth).

    With ``edge_sigma_px`` or ``small_side_px`` set, rows ``4k .. 4k + 3`` of the model
    are tag ``k``'s corners in detection order (round the tag).
    """

    sigma_px: float
    dof: int = 4
    edge_sigma_px: float = 0.0
    small_side_px: float = 0.0

    @property
    def tags(self) -> bool:
        """True for tag corners (the model's rows come four to a tag)."""
        return self.edge_sigma_px > 0 or self.small_side_px > 0


#: Chessboard corners of a marker field (saddle points refined by
#: :func:`~oralnav.control.vision.detection.refine_corners`). Over 128 renders of 6-9 corner
#: fields (2026-11-27, 640 x 480, 0.4-1.5 px blur, 1-3 DN noise, 0-50 deg tilt) their error
#: against the truth was 0.05 px median, 0.03-0.05 px RMS in most views and up to 0.2 px in
#: blurred, tilted ones; unlike a tag's corners they show no shared shift.
FIELD_CORNERS = CornerNoise(sigma_px=0.05)


@dataclass
class Observation:
    """One camera's corners of one field.

    Attributes:
        camera: the camera (its ``T_ref_cam`` places it in the rig).
        rows: rows into ``field.corners`` (N,).
        px: measured pixels (N x 2).
    """

    camera: CameraModel
    rows: np.ndarray
    px: np.ndarray
    _xy: np.ndarray | None = field(default=None, repr=False)

    @property
    def xy(self) -> np.ndarray:
        """Undistorted normalised coordinates of :attr:`px` (N x 2), cached."""
        if self._xy is None:
            self._xy = self.camera.undistort_normalized(self.px)
        return self._xy


@dataclass(frozen=True)
class PoseEstimate:
    """A field's pose in the rig reference frame, from one frame's images.

    Attributes:
        T_ref_field: 4x4 pose of the field in the rig's reference frame (m).
        corners: number of corner observations used (summed over cameras).
        reproj_rms_px: RMS reprojection error of those observations (px).
        covariance: 6x6 covariance of ``[dt (m), dtheta (rad)]``, reference frame.
        cameras: names of the cameras whose corners were used.
        per_camera: camera name -> (rows into field.corners, px) of the inliers.
        method: ``"pnp"``, ``"ba"``, ``"nvgba"`` or ``"opencv"``.
    """

    T_ref_field: np.ndarray
    corners: int
    reproj_rms_px: float
    covariance: np.ndarray
    cameras: tuple[str, ...]
    per_camera: dict[str, tuple[np.ndarray, np.ndarray]]
    method: str

    @property
    def position_sigma_m(self) -> float:
        """Largest standard deviation of the field origin along any axis (m)."""
        return float(np.sqrt(max(np.max(np.linalg.eigvalsh(self.covariance[:3, :3])), 0.0)))

    @property
    def rotation_sigma_deg(self) -> float:
        """Largest standard deviation of the rotation about any axis (deg)."""
        var = float(np.max(np.linalg.eigvalsh(self.covariance[3:, 3:])))
        return float(np.degrees(np.sqrt(max(var, 0.0))))

    def within(self, max_rms_px: float, max_position_sigma_mm: float,
               max_rotation_sigma_deg: float, min_corners: int = 4) -> bool:
        """True for a finite fit within these reprojection and covariance limits: the
        gate a caller applies before reporting the pose (a wrong pose is worse than none).
        """
        return bool(self.corners >= min_corners and np.isfinite(self.reproj_rms_px)
                    and self.reproj_rms_px <= max_rms_px
                    and np.all(np.isfinite(self.covariance))
                    and self.position_sigma_m * 1e3 <= max_position_sigma_mm
                    and self.rotation_sigma_deg <= max_rotation_sigma_deg)


# -- NVG-BA normals and weights (eqs. 9-14) ----------------------------------------------
def corner_normals(fld: MarkerField) -> np.ndarray:
    """Unit normal (N x 3, field frame) of each known corner, from its model neighbours.

    Eqs. 9-13: the normal is the eigenvector of least eigenvalue of the scatter matrix of
    the neighbourhood, centred on its mean. The corner itself joins its 8-connected
    neighbours (an edge corner has as few as 3); where those are too few or on a line, the
    nearest model corners widen it. Signs are oriented to the printed face
    where that is known (plane and cylinder); weights use ``|cos|`` so it does not matter.
    """
    P = fld.corners
    out = np.zeros_like(P)
    for j, nb in enumerate(fld.neighbours):
        normal = _least_scatter_axis(P[np.concatenate([[j], nb])])
        if normal is None:
            # Too few or collinear neighbours (a model missing the next row): widen to the
            # nearest corners in the model until they span a surface patch.
            order = np.argsort(np.linalg.norm(P - P[j], axis=1))
            for k in range(9, len(P) + 8, 8):
                normal = _least_scatter_axis(P[order[:k]])
                if normal is not None:
                    break
        out[j] = (0.0, 0.0, -1.0) if normal is None else normal
    if fld.renderable:
        face = fld.sheet_normals(fld.corners_flat)
        out *= np.sign(np.sum(out * face, axis=1, keepdims=True) + 1e-300)
    return out


def _least_scatter_axis(pts: np.ndarray) -> np.ndarray | None:
    """Eigenvector of least eigenvalue of the points' centred scatter (eqs. 10-13), or None
    when it is not defined: fewer than 3 points, or points (nearly) on a line."""
    if len(pts) < 3:
        return None
    Q = pts - pts.mean(axis=0)
    vals, vecs = np.linalg.eigh(Q.T @ Q)
    if vals[1] <= 1e-4 * vals[2]:
        return None
    return vecs[:, 0]


def obliquity_weights(T_ref_field: np.ndarray, normals: np.ndarray, points: np.ndarray,
                      camera: CameraModel, weighting: Weighting) -> np.ndarray:
    """Per-corner weight for one camera under pose ``T_ref_field`` (eq. 14 and variants).

    ``normals`` and ``points`` are the corners' rows of :func:`corner_normals` and
    ``field.corners``. ``"none"`` gives ones (plain BA).
    """
    n = len(points)
    if weighting == "none":
        return np.ones(n)
    T_cam_field = camera.T_cam_ref @ T_ref_field
    n_cam = normals @ T_cam_field[:3, :3].T
    if weighting == "axis":
        cos = np.abs(n_cam[:, 2])
    else:
        p_cam = points @ T_cam_field[:3, :3].T + T_cam_field[:3, 3]
        ray = p_cam / np.linalg.norm(p_cam, axis=1, keepdims=True)
        cos = np.abs(np.sum(n_cam * ray, axis=1))
    cos = np.clip(cos, 0.0, 1.0)
    if weighting in ("cos", "axis"):
        w = cos
    elif weighting == "cos2":
        w = cos ** 2
    elif weighting == "paper":
        w = np.arccos(cos)  # as printed: grows with obliquity
    else:
        raise ValueError(f"unknown weighting {weighting!r}; expected one of {WEIGHTINGS}")
    return np.maximum(w, 1e-3)


# -- coarse PnP ---------------------------------------------------------------------------
def _degenerate(points: np.ndarray, px: np.ndarray) -> bool:
    """True when the corners cannot fix a pose: too few, (nearly) collinear in the model
    or in the image, or coplanar in the model and seen nearly edge-on.

    The last case is a planar set (one row of a cylinder field is a planar arc) whose plane
    nearly contains the camera centre: its image is a thin band, and PnP finds a mirrored
    pose about the line of sight that fits the band to under a pixel (21 mm and 168 deg off
    in the test, at a spread ratio of 0.035). The limit is ``MIN_EDGE_ON_SPREAD``: a whole
    10 x 7 plane field reaches it only at about 85 deg of obliquity, where no corner is
    usable anyway, and two rows of one at about 70 deg.
    """
    if len(points) < 4:
        return True
    sv3, sv2 = _spread(points), _spread(px)
    if _collinear(sv3) or _collinear(sv2):
        return True
    return bool(sv3[2] < 1e-3 * sv3[0] and sv2[1] < MIN_EDGE_ON_SPREAD * sv2[0])


def _spread(arr: np.ndarray) -> np.ndarray:
    """Singular values of the centred points (largest first)."""
    return np.linalg.svd(arr - arr.mean(axis=0), compute_uv=False)


def _collinear(sv: np.ndarray) -> bool:
    """True for a spread (:func:`_spread`) of points on one spot or (nearly) one line."""
    return bool(sv[0] <= 0 or sv[1] < 1e-3 * sv[0])


def _degenerate_set(points: np.ndarray, xy: np.ndarray, cam_idx: np.ndarray) -> bool:
    """:func:`_degenerate` for observations stacked over cameras: the image tests apply
    to a single camera only, since two cameras triangulate what one sees edge-on."""
    if len(np.unique(cam_idx)) == 1:
        return _degenerate(points, xy)
    return len(points) < 4 or _collinear(_spread(points))


def pnp_camera(points: np.ndarray, px: np.ndarray, camera: CameraModel,
               ransac_px: float = 3.0) -> tuple[np.ndarray, np.ndarray] | None:
    """Pose of the field in one camera (``T_cam_field``) by RANSAC PnP, and the inlier mask.

    RANSAC runs AP3P on minimal sets only to find the inliers; SQPnP then solves all of
    them and Levenberg-Marquardt refines, and the inliers are re-read from that pose.
    RANSAC with SQPnP inside (OpenCV 5.0) was measured failing on planar fields turned
    50-70 deg away: 12 of 54 exact corners kept at 50 deg, a pose 127 deg off at 60 and
    an exception at 70 (OpenCV issue 27098 reports wrong planar RANSAC poses since 4.7).
    Returns ``None`` for a degenerate corner set or when fewer than 4 inliers remain.
    """
    if _degenerate(points, px):
        return None
    obj = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 1, 3)
    img = np.ascontiguousarray(px, dtype=np.float64).reshape(-1, 1, 2)
    try:
        ok, rvec, tvec, inl = cv2.solvePnPRansac(
            obj, img, camera.K, camera.dist, iterationsCount=100,
            reprojectionError=ransac_px, confidence=0.999, flags=cv2.SOLVEPNP_AP3P)
        if not ok or inl is None or len(inl) < 4:
            return None
        mask = np.zeros(len(points), dtype=bool)
        mask[inl.ravel()] = True
        if _degenerate(points[mask], px[mask]):
            return None
        for _ in range(2):
            ok, rvec, tvec = cv2.solvePnP(obj[mask], img[mask], camera.K, camera.dist,
                                          flags=cv2.SOLVEPNP_SQPNP)
            if not ok:
                return None
            rvec, tvec = cv2.solvePnPRefineLM(obj[mask], img[mask], camera.K, camera.dist,
                                              rvec, tvec)
            uv, _ = cv2.projectPoints(obj, rvec, tvec, camera.K, camera.dist)
            again = np.linalg.norm(uv.reshape(-1, 2) - px, axis=1) < ransac_px
            if again.sum() < 4 or np.array_equal(again, mask):
                break
            mask = again
    except cv2.error:
        return None
    if mask.sum() < 4:
        return None
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rvec.ravel()).as_matrix()
    T[:3, 3] = tvec.ravel()
    if T[2, 3] <= 0 or not np.all(np.isfinite(T)):
        return None
    return T, mask


def coarse_pose(fld: MarkerField, observations: Sequence[Observation],
                ransac_px: float = 3.0) -> np.ndarray | None:
    """``T_ref_field`` from the camera whose RANSAC PnP keeps the most corners, or None."""
    best: tuple[int, np.ndarray] | None = None
    for ob in observations:
        res = pnp_camera(fld.corners[ob.rows], ob.px, ob.camera, ransac_px)
        if res is None:
            continue
        T_cam_field, mask = res
        n = int(mask.sum())
        if best is None or n > best[0]:
            best = (n, ob.camera.T_ref_cam @ T_cam_field)
    return None if best is None else best[1]


# -- bundle adjustment (eqs. 15-17) -------------------------------------------------------
def _residuals(T: np.ndarray, X: np.ndarray, obs_xy: np.ndarray, R_cr: np.ndarray,
               t_cr: np.ndarray, f: np.ndarray, with_jacobian: bool):
    """Scaled normalised-plane residuals (2N,) and their Jacobian (2N x 6) for all rows.

    Rows are stacked over cameras; ``R_cr, t_cr`` (N x 3 x 3, N x 3) take reference-frame
    points into each row's camera and ``f`` (N,) is that camera's focal length, so residuals
    are close to pixels.
    """
    RX = X @ T[:3, :3].T
    p_ref = RX + T[:3, 3]
    p_cam = (R_cr @ p_ref[:, :, None])[:, :, 0] + t_cr
    z = p_cam[:, 2]
    zs = np.where(z > 1e-9, z, 1e-9)
    x = p_cam[:, :2] / zs[:, None]
    r = (f[:, None] * (x - obs_xy)).ravel()
    if not with_jacobian:
        return r, None, z
    # d(residual)/d(p_cam) = f / z * [[1, 0, -x], [0, 1, -y]]; chained through R_cr.
    g = (f / zs)[:, None]
    A0 = g * (R_cr[:, 0, :] - x[:, 0:1] * R_cr[:, 2, :])  # n x 3, d(r_x)/d(p_ref)
    A1 = g * (R_cr[:, 1, :] - x[:, 1:2] * R_cr[:, 2, :])
    # d(p_ref)/d(dtheta) = -[RX]x, and a^T (-[v]x) = v x a, row by row.
    J = np.empty((len(X), 2, 6))
    J[:, 0, :3] = A0
    J[:, 1, :3] = A1
    _cross_into(RX, A0, J[:, 0, 3:])
    _cross_into(RX, A1, J[:, 1, 3:])
    return r, J.reshape(-1, 6), z


def _cross_into(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:
    """Row-wise ``a x b`` (N x 3) written into ``out``: ``np.cross``'s axis handling costs
    more than the product itself on the few rows of a tag."""
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]


def _stack(fld: CornerModel, obs: Sequence[Observation]):
    """Rows of all observations stacked: model points (N x 3), normalised measurements
    (N x 2), camera index (N,), and per row the camera's R_cam_ref, t_cam_ref and focal."""
    X = np.concatenate([fld.corners[o.rows] for o in obs])
    xy = np.concatenate([o.xy for o in obs])
    cam_idx = np.concatenate([np.full(len(o.rows), k) for k, o in enumerate(obs)])
    R_cr = np.stack([o.camera.T_cam_ref[:3, :3] for o in obs])[cam_idx]
    t_cr = np.stack([o.camera.T_cam_ref[:3, 3] for o in obs])[cam_idx]
    f = np.array([0.5 * (o.camera.K[0, 0] + o.camera.K[1, 1]) for o in obs])[cam_idx]
    return X, xy, cam_idx, R_cr, t_cr, f


def bundle_adjust(fld: MarkerField | CornerModel, observations: Sequence[Observation],
                  T0: np.ndarray, weighting: Weighting = "none",
                  normals: np.ndarray | None = None, iterations: int = 12,
                  reject_outliers: bool = True, method: str = "ba",
                  noise: CornerNoise = FIELD_CORNERS) -> PoseEstimate | None:
    """Refine ``T0`` (``T_ref_field``) over every observation; eqs. 15-17.

    Weighted least squares on the normalised image plane (scaled by the focal length) with
    an analytic Jacobian (see :func:`_solve`). Weights, when asked for, come
    from the coarse pose (as in the paper) and stay fixed. Observations with residuals over
    ``OUTLIER_SIGMAS`` robust sigmas are dropped once and the fit repeated. Returns None when
    fewer than 4 corners or a degenerate set remain. NVG-BA weights without ``normals``
    need a :class:`MarkerField` (its corner neighbourhoods); plain BA takes any model.
    ``noise`` describes the corners for the covariance (:func:`_covariance`); a planar set
    seen by one camera may come back in the other pose that fits it, when that one fits
    better (:func:`_planar_ambiguity`).
    """
    obs = [o for o in observations if len(o.rows) > 0]
    if not obs:
        return None
    X, xy, cam_idx, R_cr, t_cr, f = _stack(fld, obs)
    if weighting != "none":
        if normals is None:
            normals = corner_normals(fld)
        w = np.concatenate([
            obliquity_weights(T0, normals[o.rows], fld.corners[o.rows], o.camera, weighting)
            for o in obs])
    else:
        w = np.ones(len(X))
    keep = np.all(np.isfinite(xy), axis=1)
    T = T0.copy()
    for _pass in range(2 if reject_outliers else 1):
        if keep.sum() < 4 or _degenerate_set(X[keep], xy[keep], cam_idx[keep]):
            return None
        T = _solve(T, X[keep], xy[keep], R_cr[keep], t_cr[keep], f[keep],
                          w[keep], iterations)
        if T is None:
            return None
        if not reject_outliers or _pass == 1:
            break
        r, _, _ = _residuals(T, X, np.where(np.isfinite(xy), xy, 0), R_cr, t_cr, f, False)
        err = np.linalg.norm(r.reshape(-1, 2), axis=1)
        sigma = 1.4826 * np.median(err[keep]) / 1.1774  # per-axis sigma from 2-D radii
        bad = err > max(MIN_OUTLIER_PX, OUTLIER_SIGMAS * sigma)
        if not np.any(bad & keep):
            break
        keep &= ~bad
    rows = np.concatenate([o.rows for o in obs])
    args = (X[keep], xy[keep], R_cr[keep], t_cr[keep], f[keep])
    found = _covariance(T, *args, w[keep], cam_idx[keep], rows[keep], noise)
    if found is not None and found[0] is not T:
        # the other planar pose fits better: polish it with this fit's own weights
        polished = _solve(found[0], *args, w[keep], iterations)
        if polished is not None:
            found = _covariance(polished, *args, w[keep], cam_idx[keep], rows[keep], noise,
                                may_swap=False) or found
    if found is None:
        return None
    T, cov = found
    return _estimate(fld, obs, T, keep, cam_idx, cov, method)


def _solve(T0: np.ndarray, X, xy, R_cr, t_cr, f, w, iterations: int) -> np.ndarray | None:
    """Weighted least squares over ``[dt, dtheta]`` from ``T0``: scipy's Levenberg-Marquardt
    (MINPACK) with our analytic Jacobian. A hand-written Gauss-Newton loop timed against it
    on the same 128 opener corners (2026-11-22) took 1.0 ms to its 0.7 ms for the same pose,
    so the library solver stays."""
    sw = np.sqrt(np.repeat(w, 2))

    def pose_of(x: np.ndarray) -> np.ndarray:
        T = T0.copy()
        T[:3, :3] = Rotation.from_rotvec(x[3:]).as_matrix() @ T0[:3, :3]
        T[:3, 3] = T0[:3, 3] + x[:3]
        return T

    def fun(x: np.ndarray) -> np.ndarray:
        return sw * _residuals(pose_of(x), X, xy, R_cr, t_cr, f, False)[0]

    def jac(x: np.ndarray) -> np.ndarray:
        return sw[:, None] * _residuals(pose_of(x), X, xy, R_cr, t_cr, f, True)[1]

    try:
        sol = least_squares(fun, np.zeros(6), jac=jac, method="lm", x_scale="jac",
                            max_nfev=20 * iterations, xtol=1e-10, ftol=1e-12)
    except (ValueError, np.linalg.LinAlgError):
        return None
    T = pose_of(sol.x)
    if not np.all(np.isfinite(T)):
        return None
    _, _, z = _residuals(T, X, xy, R_cr, t_cr, f, False)
    return T if np.all(z > 0) else None


def _estimate(fld: CornerModel, obs: Sequence[Observation], T: np.ndarray, keep: np.ndarray,
              cam_idx: np.ndarray, cov: np.ndarray, method: str) -> PoseEstimate:
    per_camera: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    sq = []
    for k, o in enumerate(obs):
        sel = keep[cam_idx == k]
        if not np.any(sel):
            continue
        rows, px = o.rows[sel], o.px[sel]
        per_camera[o.camera.name] = (rows, px)
        uv = o.camera.project_from(o.camera.T_cam_ref @ T, fld.corners[rows])
        sq.append(np.sum((uv - px) ** 2, axis=1))
    err = np.concatenate(sq)
    return PoseEstimate(T_ref_field=T, corners=int(len(err)),
                        reproj_rms_px=float(np.sqrt(np.mean(err))), covariance=cov,
                        cameras=tuple(per_camera), per_camera=per_camera, method=method)


# -- covariance -----------------------------------------------------------------------------
def pixel_variance(ssr: float, n_residuals: int, noise: CornerNoise = FIELD_CORNERS,
                   prior_scale: float = 1.0) -> float:
    """Variance (px^2) of one corner coordinate, the scale of a fit's covariance.

    ``ssr`` is the weighted sum of squared residuals (px^2) of ``n_residuals`` image
    coordinates fitted by the 6 pose parameters. Their own estimate ``ssr / (n - 6)`` is
    pooled with the prior variance ``prior_scale * noise.sigma_px^2``, worth ``noise.dof``
    residuals (the conjugate update of a Gaussian's variance), and the pooled value is
    widened by ``nu / (nu - 2)`` for ``nu`` degrees of freedom in all: the pose error is
    then Student-t, and that is its variance. A 4-corner tag (2 residual degrees of
    freedom) thus leans on the prior, a 100-corner field on its residuals. Never below
    ``MIN_SIGMA_PX`` squared.
    """
    nu = noise.dof + max(int(n_residuals) - 6, 0)
    s2 = (noise.dof * prior_scale * noise.sigma_px ** 2 + max(float(ssr), 0.0)) / nu
    return max(s2 * nu / (nu - 2), MIN_SIGMA_PX ** 2)


def _covariance(T: np.ndarray, X: np.ndarray, xy: np.ndarray, R_cr: np.ndarray,
                t_cr: np.ndarray, f: np.ndarray, w: np.ndarray, cam_idx: np.ndarray,
                rows: np.ndarray, noise: CornerNoise, may_swap: bool = True
                ) -> tuple[np.ndarray, np.ndarray] | None:
    """The pose and its 6x6 covariance of ``[dt (m), dtheta (rad)]`` (reference frame) for
    the fit ``T`` to these stacked rows (as :func:`_residuals`; ``w`` per-row weights,
    ``rows`` into the model).

    ``s^2 (J^T W J)^-1`` with ``s^2`` from :func:`pixel_variance`; plus, for tag corners,
    the shared edge shift (:func:`_tag_terms`); then, where one camera sees a planar set,
    the other pose that fits it (:func:`_planar_ambiguity`), which replaces ``T`` when it
    fits better and ``may_swap``. None when singular.
    """
    r, J, z = _residuals(T, X, xy, R_cr, t_cr, f, True)
    if np.any(z <= 0):
        return None
    w2 = np.repeat(w / np.mean(w), 2)
    ssr = float(np.sum(w2 * r * r))
    prior_scale, shifts = _tag_terms(xy, f, cam_idx, rows, noise)
    s2 = pixel_variance(ssr, len(r), noise, prior_scale)
    try:
        H_inv = np.linalg.inv(J.T @ (J * w2[:, None]))
    except np.linalg.LinAlgError:
        return None
    cov = s2 * H_inv + _shift_covariance(shifts, J, w2, H_inv)
    if not np.all(np.isfinite(cov)):
        return None
    if cam_idx.min() == cam_idx.max() and _coplanar(X):
        return _planar_ambiguity(T, cov, ssr, s2, X, xy, R_cr, t_cr, f, w2, shifts,
                                 may_swap)
    return T, cov


def _tag_terms(xy: np.ndarray, f: np.ndarray, cam_idx: np.ndarray, rows: np.ndarray,
               noise: CornerNoise) -> tuple[float, list[np.ndarray]]:
    """For tag corners (``noise.tags``): the factor on the prior corner variance, and per
    camera the displacement (N x 2, px) of every row under the shared edge shift at one
    standard deviation. ``(1.0, [])`` for other corners.

    Sub-pixel refinement of a tag's corner (an L-shaped corner, unlike a chessboard's
    saddle) pulls it into the tag as blur rounds the corner, by about the same amount at
    every corner of every tag in one image: each edge moves along its normal, so each
    corner moves along its bisector, farther at acute corners. The fit absorbs most of
    that into depth, where no residual shows it. Displacements are found on the measured
    quadrilaterals (``f * xy``, rows ``4k .. 4k + 3`` round tag ``k``); a tag of side ``L``
    under ``noise.small_side_px`` shifts ``small_side_px / L`` times as far and adds that
    ratio to the fourth power to the prior's mean variance factor.
    """
    if not noise.tags:
        return 1.0, []
    # tags: rows 4k .. 4k + 3 of one camera; a tag missing a corner has no closed outline
    key = cam_idx.astype(np.int64) * (int(rows.max()) // 4 + 1) + rows // 4
    n = len(rows)
    if n % 4 == 0 and np.array_equal(rows.reshape(-1, 4) - rows[::4, None], _IN_ORDER) \
            and not np.any(rows[::4] % 4) and np.array_equal(key[::4], key[3::4]):
        idx = np.arange(n).reshape(-1, 4)  # four to a tag, in order (a body's rows)
    else:
        order = np.lexsort((rows % 4, key))
        ks = key[order]
        starts = np.nonzero(np.r_[True, ks[1:] != ks[:-1]])[0]
        sizes = np.diff(np.r_[starts, len(ks)])
        idx = order[(starts[sizes == 4][:, None] + np.arange(4)).ravel()].reshape(-1, 4)
    if len(idx) == 0:
        return 1.0, []
    quads = f[idx, None] * xy[idx]                          # tags x 4 x 2, undistorted px
    side = np.mean(np.linalg.norm(quads[:, _NEXT] - quads, axis=2), axis=1)
    gain = np.maximum(1.0, noise.small_side_px / np.maximum(side, 1e-9))
    prior_scale = float(np.mean(gain ** 4))
    if noise.edge_sigma_px <= 0:
        return prior_scale, []
    moved = (noise.edge_sigma_px * gain)[:, None, None] * _corner_shift(quads)
    shifts = []
    tag_cam = cam_idx[idx[:, 0]]
    for cam in np.unique(tag_cam):
        v = np.zeros((n, 2))
        mine = tag_cam == cam
        v[idx[mine].ravel()] = moved[mine].reshape(-1, 2)
        shifts.append(v)
    return prior_scale, shifts


def _shift_covariance(shifts: list[np.ndarray], J: np.ndarray, w2: np.ndarray,
                      H_inv: np.ndarray) -> np.ndarray:
    """Pose covariance (6x6) of independent row displacements at one standard deviation
    each (:func:`_tag_terms`), through the weighted least-squares solution
    ``H^-1 J^T W``."""
    out = np.zeros((6, 6))
    for v in shifts:
        g = H_inv @ (J.T @ (w2 * v.ravel()))
        out += np.outer(g, g)
    return out


_NEXT = np.array([1, 2, 3, 0])  # the next and the previous corner round a tag
_PREV = np.array([3, 0, 1, 2])
_IN_ORDER = np.arange(4)[None, :]


def _corner_shift(quads: np.ndarray) -> np.ndarray:
    """Displacement (T x 4 x 2) of each corner of ``quads`` (T x 4 x 2, corners in order
    round each) when every edge moves 1 outward along its normal: the point 1 out from
    both of its edges, ``(n1 + n2) / (1 + n1 . n2)`` for the outward unit normals of the
    two (zero for a degenerate quadrilateral)."""
    d = quads[:, _NEXT] - quads                             # edge k from corner k to k + 1
    d /= np.maximum(np.linalg.norm(d, axis=2, keepdims=True), 1e-12)
    # (dy, -dx) points out of a quadrilateral of positive shoelace area (image axes)
    area = np.sum(quads[..., 0] * quads[:, _NEXT, 1] - quads[:, _NEXT, 0] * quads[..., 1],
                  axis=1)
    n = np.sign(area)[:, None, None] * np.stack([d[..., 1], -d[..., 0]], axis=2)
    n1, n2 = n[:, _PREV], n                                 # corner k: edges k - 1 and k
    den = 1.0 + np.sum(n1 * n2, axis=2, keepdims=True)
    return np.where(den > 1e-9, (n1 + n2) / np.maximum(den, 1e-9), 0.0)


def _coplanar(X: np.ndarray) -> bool:
    """True for model points on one plane (the test of :func:`_degenerate`)."""
    sv = _spread(X)
    return bool(sv[2] < 1e-3 * sv[0])


def _planar_ambiguity(T: np.ndarray, cov: np.ndarray, ssr: float, s2: float, X: np.ndarray,
                      xy: np.ndarray, R_cr: np.ndarray, t_cr: np.ndarray, f: np.ndarray,
                      w2: np.ndarray, shifts: list[np.ndarray], may_swap: bool = True
                      ) -> tuple[np.ndarray, np.ndarray]:
    """The pose and covariance of a planar set seen by one camera, given the other pose
    that fits it.

    A plane seen by one camera fits two poses, mirror images about the line of sight;
    when it is small in the image or seen nearly face-on both fit its corners to within
    their noise (IPPE returns both). The other minimum is reached from IPPE's other pose by
    Levenberg-Marquardt; ``shifts`` are the tag-edge displacements of the fit
    (:func:`_tag_terms`). With ``p`` its posterior weight against ``T`` (Laplace: the
    excess of its residuals over ``2 s2`` and its covariance volume), the covariance is
    the second moment of the two-pose mixture about the reported pose:
    ``(1 - p) cov + p (cov_alt + d d^T)``, ``d`` the step to the other pose. Where that
    pose fits clearly worse, ``p`` vanishes and ``T, cov`` come back unchanged; where its
    residuals are smaller (a fit that settled in the wrong minimum) and ``may_swap``, it
    is the one reported.
    """
    R_cam = R_cr[0] @ T[:3, :3]
    obj = np.ascontiguousarray(X, dtype=np.float64).reshape(-1, 1, 3)
    img = np.ascontiguousarray(xy, dtype=np.float64).reshape(-1, 1, 2)
    try:
        n, rvecs, tvecs, _ = cv2.solvePnPGeneric(obj, img, np.eye(3), None,
                                                 flags=cv2.SOLVEPNP_IPPE)
    except cv2.error:
        return T, cov
    if n < 2:
        return T, cov
    # of IPPE's two poses, the one that turns farther from the fit (the smaller trace of
    # the turn between them) seeds the other minimum, which OpenCV's Levenberg-Marquardt
    # reaches on the same normalised coordinates (unweighted: the weights of one camera's
    # planar set barely differ)
    k = int(np.argmin([np.sum(cv2.Rodrigues(rv)[0] * R_cam) for rv in rvecs[:n]]))
    try:
        rvec, tvec = cv2.solvePnPRefineLM(obj, img, np.eye(3), None, rvecs[k].copy(),
                                          tvecs[k].copy(), _AMBIGUITY_LM)
    except cv2.error:
        return T, cov
    # T_ref_field of that pose: T_ref_cam @ T_cam_field, with T_ref_cam = inv(R_cr, t_cr)
    T_alt = np.eye(4)
    T_alt[:3, :3] = R_cr[0].T @ cv2.Rodrigues(rvec)[0]
    T_alt[:3, 3] = R_cr[0].T @ (tvec.ravel() - t_cr[0])
    r, J, z = _residuals(T_alt, X, xy, R_cr, t_cr, f, True)
    if np.any(z <= 0) or not np.all(np.isfinite(r)):
        return T, cov
    try:
        H_inv = np.linalg.inv(J.T @ (J * w2[:, None]))
    except np.linalg.LinAlgError:
        return T, cov
    # both poses fit the same corners, so the same image quadrilaterals shift
    cov_alt = s2 * H_inv + _shift_covariance(shifts, J, w2, H_inv)
    ssr_alt = float(np.sum(w2 * r * r))
    log_odds = (ssr - ssr_alt) / (2.0 * s2) + 0.5 * (np.linalg.slogdet(cov_alt)[1]
                                                     - np.linalg.slogdet(cov)[1])
    if not np.isfinite(log_odds):
        return T, cov
    if may_swap and ssr_alt < ssr:  # the other pose fits better: report it
        T, T_alt, cov, cov_alt, log_odds = T_alt, T, cov_alt, cov, -log_odds
    if log_odds < -40.0:  # the other pose is e^-40 as likely: nothing to add
        return T, cov
    p = 1.0 / (1.0 + np.exp(-min(log_odds, 40.0)))
    d = np.concatenate([T_alt[:3, 3] - T[:3, 3],
                        cv2.Rodrigues(T_alt[:3, :3] @ T[:3, :3].T)[0].ravel()])
    out = (1.0 - p) * cov + p * (cov_alt + np.outer(d, d))
    return (T, out) if np.all(np.isfinite(out)) else (T, cov)


def estimate_pose(fld: MarkerField, observations: Sequence[Observation],
                  method: Literal["pnp", "ba", "nvgba"] = "nvgba",
                  weighting: Weighting = DEFAULT_WEIGHTING,
                  normals: np.ndarray | None = None, T_guess: np.ndarray | None = None
                  ) -> PoseEstimate | None:
    """The whole chain for one field: coarse PnP, then BA or NVG-BA over all cameras.

    ``pnp`` stops after the coarse pose (refined over the best camera only, with the same
    robust loop so its figures are comparable). ``T_guess`` replaces the coarse PnP when a
    trusted prior exists (predictive tracking), which saves its cost; each frame's estimate
    still depends only on that frame's corners.
    """
    T0 = T_guess if T_guess is not None else coarse_pose(fld, observations)
    if T0 is None:
        return None
    if method == "pnp":
        best = max(observations, key=lambda o: len(o.rows))
        return bundle_adjust(fld, [best], T0, "none", method="pnp")
    if method == "ba":
        return bundle_adjust(fld, observations, T0, "none", method="ba")
    if method == "nvgba":
        return bundle_adjust(fld, observations, T0, weighting, normals, method="nvgba")
    raise ValueError(f"unknown method {method!r}; expected 'pnp', 'ba' or 'nvgba'")


def pose_covariance(fld: CornerModel, observations: Sequence[Observation], T: np.ndarray,
                    noise: CornerNoise = FIELD_CORNERS) -> np.ndarray | None:
    """6x6 covariance of ``[dt, dtheta]`` (reference frame) of an unweighted fit at ``T``,
    for poses found by other means (the OpenCV baseline): that of :func:`bundle_adjust`,
    about ``T`` even where the other planar pose fits better; None when singular."""
    obs = [o for o in observations if len(o.rows) > 0]
    if not obs:
        return None
    X, xy, cam_idx, R_cr, t_cr, f = _stack(fld, obs)
    ok = np.all(np.isfinite(xy), axis=1)
    if ok.sum() < 4:
        return None
    rows = np.concatenate([o.rows for o in obs])
    found = _covariance(T, X[ok], xy[ok], R_cr[ok], t_cr[ok], f[ok], np.ones(int(ok.sum())),
                        cam_idx[ok], rows[ok], noise, may_swap=False)
    if found is None:
        return None
    return found[1]
