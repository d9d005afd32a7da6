"""Corner-level measurements: what a tracker would report, without rendering images.

The renderer (``sim/world/render.py``) makes images the detector then reads; that is the whole
pipeline, at 0.1-0.5 s a view. Calibration studies need thousands of pose measurements
whose errors come from one controlled source, the marker-corner noise, so here a field's
visible chessboard corners are projected exactly through the camera model, Gaussian pixel
noise is added, and the project's own pose estimator (``control/vision/pose.py``) solves for the
pose. The pose errors then carry the estimator's real correlations (depth worse than
lateral, rotation and translation coupled) at a few milliseconds a pose.

A corner is visible when it projects into the image, lies in front of the camera and its
printed face turns toward the camera by less than the tracker's ``max_obliquity_deg``;
occlusion by other fields is not modelled (calibration views keep fields apart). Estimates
pass the tracker's gates (``TrackerSettings``) or are not reported, as in the tracker.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from oralnav.control.geometry import transform_points
from oralnav.control.vision.camera import CameraModel, Rig
from oralnav.control.vision.markers import MarkerField
from oralnav.control.vision.pose import Observation, PoseEstimate, estimate_pose
from oralnav.control.vision.tracker import TrackerSettings

__all__ = ["observe", "measure_pose", "MIN_CORNERS"]

#: The tracker's own gates: what it would refuse to report is not a measurement here either.
_GATE = TrackerSettings()
#: Fewest corners a camera must see for its observation to be used (as the tracker's gate).
MIN_CORNERS = _GATE.min_corners


def _visible(fld: MarkerField, cam: CameraModel, T_cam_field: np.ndarray,
             max_obliquity_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """Rows of ``fld.corners`` the camera sees and their exact pixels."""
    pc = transform_points(T_cam_field, fld.corners)
    uv = cam.project(pc)
    normals = fld.sheet_normals(fld.corners_flat) @ T_cam_field[:3, :3].T
    view = pc / np.linalg.norm(pc, axis=1, keepdims=True)
    cos_obl = -(normals * view).sum(axis=1)
    ok = (pc[:, 2] > 0) & (cos_obl > np.cos(np.radians(max_obliquity_deg))) \
        & cam.in_image(uv, margin=2.0)
    rows = np.flatnonzero(ok)
    return rows, uv[rows]


def observe(fld: MarkerField, T_ref_field: np.ndarray, rig: Rig, sigma_px: float,
            rng: np.random.Generator, *, cameras: Sequence[str] | None = None,
            max_obliquity_deg: float = _GATE.max_obliquity_deg) -> list[Observation]:
    """Noisy corner observations of ``fld`` at ``T_ref_field`` (rig reference frame, m).

    Each visible corner's pixel gets independent Gaussian noise of ``sigma_px`` per axis.
    Cameras seeing fewer than :data:`MIN_CORNERS` corners are left out.
    """
    out = []
    for name in cameras or rig.names:
        cam = rig[name]
        rows, uv = _visible(fld, cam, cam.T_cam_ref @ T_ref_field, max_obliquity_deg)
        if len(rows) < MIN_CORNERS:
            continue
        out.append(Observation(cam, rows, uv + rng.normal(0.0, sigma_px, uv.shape)))
    return out


def measure_pose(fld: MarkerField, T_ref_field: np.ndarray, rig: Rig, sigma_px: float,
                 rng: np.random.Generator, *, method: str = "nvgba",
                 cameras: Sequence[str] | None = None) -> PoseEstimate | None:
    """The pose the tracker would report for ``fld`` at ``T_ref_field``, or None when no
    camera sees enough corners or the estimate fails the tracker's gates (reprojection RMS,
    covariance: a few corners at one edge of one image give a pose off by centimetres, which
    the tracker refuses). ``method`` as :func:`~oralnav.control.vision.pose.estimate_pose`."""
    obs = observe(fld, T_ref_field, rig, sigma_px, rng, cameras=cameras)
    if not obs:
        return None
    est = estimate_pose(fld, obs, method=method)  # type: ignore[arg-type]
    if est is None or not est.within(_GATE.max_rms_px, _GATE.max_position_sigma_mm,
                                     _GATE.max_rotation_sigma_deg, _GATE.min_corners):
        return None
    return est
