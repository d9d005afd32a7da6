"""Pinhole camera with OpenCV's distortion model, and the camera rig.

Frames: a camera frame has z along the optical axis, x to the right and y down the image
(OpenCV). Pixel coordinates put the centre of the top-left pixel at (0, 0). Points are in
metres; pixels are float.

The projection is written out in numpy (rather than calling ``cv2.projectPoints``) so the
renderer and the estimators can project many points per call, and it is tested against
``cv2.projectPoints`` to 1e-9 px for every distortion-vector length OpenCV accepts.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from oralnav.control.errors import CameraModelError
from oralnav.control.geometry import as_transform, invert

#: Distortion-vector lengths OpenCV accepts: k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4 [tx ty]]]].
DIST_LENGTHS = (4, 5, 8, 12, 14)


# OpenCV 4.x binds the criteria overload of undistortPoints as ``undistortPointsIter``;
# OpenCV 5 dropped that name and takes ``criteria`` on ``undistortPoints`` itself (after an
# optional ``dst``, so the call below passes R, P and criteria by keyword).
_undistort_points_iter = getattr(cv2, "undistortPointsIter", cv2.undistortPoints)


def _tilt_matrix(tau_x: float, tau_y: float) -> np.ndarray:
    """OpenCV's tilted-sensor projection matrix (``computeTiltProjectionMatrix``)."""
    cx, sx = np.cos(tau_x), np.sin(tau_x)
    cy, sy = np.cos(tau_y), np.sin(tau_y)
    rot_x = np.array([[1, 0, 0], [0, cx, sx], [0, -sx, cx]])
    rot_y = np.array([[cy, 0, -sy], [0, 1, 0], [sy, 0, cy]])
    rot_xy = rot_y @ rot_x
    proj_z = np.array([[rot_xy[2, 2], 0, -rot_xy[0, 2]],
                       [0, rot_xy[2, 2], -rot_xy[1, 2]],
                       [0, 0, 1]])
    return proj_z @ rot_xy


@dataclass(frozen=True, eq=False)
class CameraModel:
    """One calibrated camera of a rig.

    Attributes:
        name: camera name in the rig (``"left"``, ``"endoscope"``...).
        size: image ``(width, height)`` in pixels.
        K: 3x3 intrinsic matrix (pixels); no skew.
        dist: OpenCV distortion coefficients, length 4, 5, 8, 12 or 14.
        T_ref_cam: 4x4 pose of this camera in the rig's reference frame (metres).
    """

    name: str
    size: tuple[int, int]
    K: np.ndarray
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))
    T_ref_cam: np.ndarray = field(default_factory=lambda: np.eye(4))

    def __post_init__(self) -> None:
        where = f"camera {self.name!r}"
        try:
            w, h = (int(v) for v in self.size)
        except (TypeError, ValueError):
            raise CameraModelError(f"{where}: size must be [width, height]") from None
        if w <= 0 or h <= 0:
            raise CameraModelError(f"{where}: size must be positive, got {self.size}")
        K = np.asarray(self.K, dtype=float)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)):
            raise CameraModelError(f"{where}: K must be a finite 3x3 matrix")
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise CameraModelError(f"{where}: K focal lengths must be positive")
        if K[0, 1] != 0 or K[1, 0] != 0 or np.any(K[2] != (0.0, 0.0, 1.0)):
            raise CameraModelError(
                f"{where}: K must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (no skew)")
        dist = np.asarray(self.dist, dtype=float).reshape(-1)
        if dist.size not in DIST_LENGTHS:
            raise CameraModelError(
                f"{where}: dist must have {', '.join(map(str, DIST_LENGTHS))} entries, "
                f"got {dist.size}")
        if not np.all(np.isfinite(dist)):
            raise CameraModelError(f"{where}: dist has non-finite entries")
        try:
            T = as_transform(self.T_ref_cam, what=f"{where} T_ref_cam")
        except ValueError as exc:
            raise CameraModelError(str(exc)) from None
        # frozen dataclass: normalised values are set once here, then never change.
        object.__setattr__(self, "size", (w, h))
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "dist", dist)
        object.__setattr__(self, "T_ref_cam", T)
        full = np.zeros(14)
        full[:dist.size] = dist
        object.__setattr__(self, "_d14", full)
        tilt = _tilt_matrix(full[12], full[13]) if dist.size == 14 else None
        object.__setattr__(self, "_tilt", tilt)
        # which distortion terms are there: a term whose coefficients are all zero adds
        # exactly 0 (or divides by exactly 1), so leaving it out changes no bit, and the
        # planners project a few points at a time, hundreds of thousands of times a trial
        object.__setattr__(self, "_rational", bool(np.any(full[5:8] != 0)))
        object.__setattr__(self, "_prism", bool(np.any(full[8:12] != 0)))
        # the inverse pose, kept (read-only): asked for on every projection from the
        # reference frame, and inverting it each time cost a planner a tenth of its time
        T_cam_ref = invert(T)
        T_cam_ref.flags.writeable = False
        object.__setattr__(self, "_T_cam_ref", T_cam_ref)

    # -- basic properties -------------------------------------------------------------
    @property
    def width(self) -> int:
        return self.size[0]

    @property
    def height(self) -> int:
        return self.size[1]

    @property
    def T_cam_ref(self) -> np.ndarray:
        """Pose of the reference frame in this camera's frame (read-only: the camera's
        own copy)."""
        return self._T_cam_ref

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.dist != 0))

    # -- projection -------------------------------------------------------------------
    def distort(self, xy: np.ndarray) -> np.ndarray:
        """Apply the distortion to normalised image coordinates (N x 2) -> (N x 2)."""
        xy = np.asarray(xy, dtype=float)
        x, y = xy[..., 0], xy[..., 1]
        k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = self._d14[:12]
        r2 = x * x + y * y
        r4 = r2 * r2
        r6 = r4 * r2
        radial = 1 + k1 * r2 + k2 * r4 + k3 * r6
        if self._rational:
            radial = radial / (1 + k4 * r2 + k5 * r4 + k6 * r6)
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        if self._prism:
            xd = xd + s1 * r2 + s2 * r4
            yd = yd + s3 * r2 + s4 * r4
        if self._tilt is not None:
            M = self._tilt
            vx = M[0, 0] * xd + M[0, 1] * yd + M[0, 2]
            vy = M[1, 0] * xd + M[1, 1] * yd + M[1, 2]
            vz = M[2, 0] * xd + M[2, 1] * yd + M[2, 2]
            inv = np.where(vz != 0, 1.0 / np.where(vz != 0, vz, 1.0), 1.0)
            xd, yd = vx * inv, vy * inv
        return np.stack([xd, yd], axis=-1)

    def normalized_to_pixels(self, xy: np.ndarray) -> np.ndarray:
        """Distort normalised coordinates (N x 2) and map them to pixels (N x 2)."""
        d = self.distort(xy)
        K = self.K
        return np.stack([K[0, 0] * d[..., 0] + K[0, 2], K[1, 1] * d[..., 1] + K[1, 2]], axis=-1)

    def project(self, p_cam: np.ndarray) -> np.ndarray:
        """Project points in this camera's frame (N x 3, metres) to pixels (N x 2).

        Points at or behind the camera plane (z <= 0) give NaN rather than a mirrored pixel.
        """
        p = np.asarray(p_cam, dtype=float)
        z = p[..., 2]
        ok = z > 0
        zs = np.where(ok, z, 1.0)
        xy = np.stack([p[..., 0] / zs, p[..., 1] / zs], axis=-1)
        uv = self.normalized_to_pixels(xy)
        uv[~ok] = np.nan
        return uv

    def project_from(self, T_cam_obj: np.ndarray, p_obj: np.ndarray) -> np.ndarray:
        """Project points given in an object frame (N x 3) through ``T_cam_obj``."""
        p = np.asarray(p_obj, dtype=float)
        return self.project(p @ T_cam_obj[:3, :3].T + T_cam_obj[:3, 3])

    # -- back-projection --------------------------------------------------------------
    def undistort_normalized(self, uv: np.ndarray, *, iterations: int = 8,
                             seed: np.ndarray | None = None) -> np.ndarray:
        """Pixels (N x 2) -> undistorted normalised coordinates (N x 2).

        OpenCV's fixed-point ``undistortPoints`` seeds the solution (unless ``seed``, a close
        guess, is given); a few Gauss-Newton steps on our own forward model then bring the
        reprojection residual to ~1e-10 px. Pixels where the model does not invert
        (residual above 1e-6 px) come back as NaN.
        """
        uv = np.asarray(uv, dtype=float).reshape(-1, 2)
        if uv.size == 0:
            return uv.copy()
        if seed is None:
            seed = _undistort_points_iter(
                uv.reshape(-1, 1, 2), self.K, self.dist, R=None, P=None,
                criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-12),
            )
        xy = np.asarray(seed, dtype=float).reshape(-1, 2)
        eps = 1e-7
        for _ in range(iterations):
            f = self.normalized_to_pixels(xy) - uv
            if np.all(np.abs(f) < 1e-9):  # the seed is usually this good already
                break
            fx = (self.normalized_to_pixels(xy + (eps, 0.0)) - uv - f) / eps
            fy = (self.normalized_to_pixels(xy + (0.0, eps)) - uv - f) / eps
            a, b, c, d = fx[:, 0], fy[:, 0], fx[:, 1], fy[:, 1]
            det = a * d - b * c
            det = np.where(np.abs(det) > 1e-300, det, np.nan)
            dx = (d * f[:, 0] - b * f[:, 1]) / det
            dy = (-c * f[:, 0] + a * f[:, 1]) / det
            xy = xy - np.stack([dx, dy], axis=-1)
        resid = np.linalg.norm(self.normalized_to_pixels(xy) - uv, axis=1)
        xy[~(resid < 1e-6)] = np.nan
        return xy

    def ray_map(self, step: int = 8) -> np.ndarray:
        """Undistorted normalised coordinates of every pixel centre (H x W x 2, float64).

        Solved exactly on a ``step``-pixel grid, spline-interpolated in between, then
        polished by two Gauss-Newton steps per pixel: the same accuracy as
        :meth:`undistort_normalized` on every pixel at a fraction of the cost.
        """
        from scipy.ndimage import map_coordinates

        w, h = self.size
        gu = np.arange(0, w + step, step, dtype=float)
        gv = np.arange(0, h + step, step, dtype=float)
        GU, GV = np.meshgrid(gu, gv)
        coarse = self.undistort_normalized(np.stack([GU.ravel(), GV.ravel()], axis=1))
        coarse = coarse.reshape(len(gv), len(gu), 2)
        v, u = np.mgrid[0:h, 0:w].astype(float)
        coords = np.stack([v.ravel() / step, u.ravel() / step])
        guess = np.stack([map_coordinates(coarse[..., k], coords, order=3, mode="nearest")
                          for k in range(2)], axis=1)
        uv = np.stack([u.ravel(), v.ravel()], axis=1)
        return self.undistort_normalized(uv, iterations=2, seed=guess).reshape(h, w, 2)

    def backproject(self, uv: np.ndarray) -> np.ndarray:
        """Pixels (N x 2) -> unit viewing rays in the camera frame (N x 3)."""
        xy = self.undistort_normalized(uv)
        rays = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
        return rays / np.linalg.norm(rays, axis=1, keepdims=True)

    def in_image(self, uv: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """Boolean mask of pixels lying inside the image, ``margin`` px from its border."""
        uv = np.asarray(uv, dtype=float)
        u, v = uv[..., 0], uv[..., 1]
        with np.errstate(invalid="ignore"):
            return ((u >= -0.5 + margin) & (u <= self.width - 0.5 - margin)
                    & (v >= -0.5 + margin) & (v <= self.height - 0.5 - margin))


@dataclass(frozen=True)
class Rig:
    """A set of cameras whose poses are given in one reference frame.

    ``reference`` names the frame in which poses are reported; when it names a camera,
    that camera's ``T_ref_cam`` is the identity.
    """

    reference: str
    cameras: Mapping[str, CameraModel]

    def __post_init__(self) -> None:
        if not self.cameras:
            raise CameraModelError("rig: at least one camera is required")
        for name, cam in self.cameras.items():
            if cam.name != name:
                raise CameraModelError(f"rig: camera stored as {name!r} is named {cam.name!r}")
        ref = self.cameras.get(self.reference)
        if ref is not None and not np.allclose(ref.T_ref_cam, np.eye(4), atol=1e-9):
            raise CameraModelError(
                f"rig: camera {self.reference!r} is the reference, so its T_ref_cam "
                "must be the identity")

    def __getitem__(self, name: str) -> CameraModel:
        try:
            return self.cameras[name]
        except KeyError:
            raise CameraModelError(
                f"unknown camera {name!r}; the rig has {sorted(self.cameras)}") from None

    @property
    def names(self) -> Sequence[str]:
        return tuple(self.cameras)
