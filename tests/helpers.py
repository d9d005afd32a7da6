"""Helpers shared across the test packages: where the peer data lives, the figures the
peers assert, synthetic images of ArUco rigid bodies, and the deadline settings of tests
that spawn a real control process.

The peer data (``shared/peer-data/README.md``) sits beside the checkout, at
``../shared/peer-data``. Tests that need it carry :data:`needs_aruco_data`, so they are
skipped, with the reason, only where that folder is absent.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from oralnav.control.vision.camera import CameraModel
from oralnav.control.vision.rigid_body import RigidBody

ROOT = Path(__file__).resolve().parents[1]
PEER_DATA = ROOT.parent / "shared" / "peer-data"
#: scikit-surgeryarucotracker's data/: output.avi, multipattern.avi, 12markers.avi,
#: calibration.txt and the rigid-body tables.
ARUCO_DATA = PEER_DATA / "sksurgery-arucotracker"
needs_aruco_data = pytest.mark.skipif(
    not ARUCO_DATA.is_dir(),
    reason=f"peer data folder {ARUCO_DATA} is absent (CI has it at ../shared/peer-data)",
)

#: scikit-surgerycore's pivot-calibration matrices: all_matrices.txt (1151 poses, mm) and
#: single_rank_deficient.txt (one pose).
PIVOT_DATA = PEER_DATA / "sksurgery-pivot"
needs_pivot_data = pytest.mark.skipif(
    not PIVOT_DATA.is_dir(),
    reason=f"peer data folder {PIVOT_DATA} is absent (CI has it at ../shared/peer-data)",
)

#: The peer's regression pose of tag DICT_4X4_50:0 (50 mm) in output.avi frame index 1
#: (camera frame, OpenCV single-marker convention: z toward the camera), millimetres.
PEER_TAG0_MM = np.array([
    [0.99928828, -0.02261964, 0.03018762, 17.609988],
    [-0.02280416, -0.99972323, 0.00578211, 25.085676],
    [0.03004847, -0.00646639, -0.99952753, 210.36779],
    [0.0, 0.0, 0.0, 1.0]])

#: The peer's regression pose of ``reference`` in multipattern.avi frame 0 with
#: calibration.txt (its tests test_with_tool_desc_and_calib / test_tool_desc_and_float64),
#: millimetres, checked there within 5 mm over a 500 mm cube.
PEER_REFERENCE_MM = np.array([
    [-0.84701057, 0.51884094, -0.11565978, -82.2903442],
    [-0.48733129, -0.67100208, 0.55880625, 48.5032501],
    [0.21232361, 0.52967943, 0.82119327, 243.992401],
    [0.0, 0.0, 0.0, 1.0]])


def mm_to_m(T_mm: np.ndarray) -> np.ndarray:
    """A 4x4 pose with its translation in millimetres, in metres."""
    T = np.array(T_mm, dtype=float)
    T[:3, 3] *= 1e-3
    return T


def render_tags(camera: CameraModel, body: RigidBody, T_cam_body: np.ndarray, *,
                image: np.ndarray | None = None, background: int = 200,
                supersample: int = 4, noise_px: float = 0.0, seed: int = 0) -> np.ndarray:
    """A mono8 image (``camera.size``) of ``body``'s tags, printed black on white with a
    one-cell white margin, seen at ``T_cam_body`` (m) through ``camera``.

    Each tag's outer black border lands on its projected body corners (OpenCV order);
    tags behind the camera or turned away are not drawn. Tags are drawn through
    homographies into a pinhole image ``supersample`` times larger, area-averaged, then
    resampled through the camera's distortion around the tags. ``image`` (mono8, camera
    size) is drawn on instead of a ``background`` grey; ``noise_px`` adds Gaussian noise
    (grey levels, seeded).
    """
    w, h = camera.size
    s = supersample
    pinhole = CameraModel("pinhole", camera.size, camera.K)
    layer = np.zeros((h * s, w * s), np.uint8)
    cover = np.zeros((h * s, w * s), np.uint8)
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, body.dictionary))
    cells = dictionary.markerSize + 2
    cell = 24  # source pixels per bit cell
    drawn = []  # distorted image corners of the tags drawn
    for tid, corners in body.tags.items():
        p_cam = corners @ T_cam_body[:3, :3].T + T_cam_body[:3, 3]
        normal = np.cross(p_cam[1] - p_cam[0], p_cam[3] - p_cam[0])  # tag z, away from print
        if np.any(p_cam[:, 2] <= 0) or normal @ p_cam.mean(axis=0) <= 0:
            continue  # behind the camera, or its printed face turned away
        drawn.append(camera.project(p_cam))
        marker = cv2.aruco.generateImageMarker(dictionary, tid, cells * cell)
        printed = cv2.copyMakeBorder(marker, cell, cell, cell, cell, cv2.BORDER_CONSTANT,
                                     value=255)
        lo, hi = cell - 0.5, cell + cells * cell - 0.5
        src = np.array([[lo, lo], [hi, lo], [hi, hi], [lo, hi]], np.float32)
        dst = (s * (pinhole.project(p_cam) + 0.5) - 0.5).astype(np.float32)
        H = cv2.getPerspectiveTransform(src, dst)
        for what, into in ((printed, layer), (np.full_like(printed, 255), cover)):
            cv2.warpPerspective(what, H, (w * s, h * s), dst=into, flags=cv2.INTER_LINEAR,
                                borderMode=cv2.BORDER_TRANSPARENT)
    out = (np.full((h, w), background, np.float32) if image is None
           else image.astype(np.float32))
    if drawn:
        tags = cv2.resize(layer, (w, h), interpolation=cv2.INTER_AREA).astype(np.float32)
        alpha = cv2.resize(cover, (w, h), interpolation=cv2.INTER_AREA).astype(np.float32)
        alpha /= 255
        # Each pixel of the tags' (distorted) region samples the pinhole image where its
        # ray lands; the margin covers the one-cell white border and bent edges.
        uv = np.concatenate(drawn)
        pad = 0.25 * float(np.max(uv.max(axis=0) - uv.min(axis=0))) + 8
        x0, y0 = np.maximum(np.floor(uv.min(axis=0) - pad), 0).astype(int)
        x1, y1 = np.minimum(np.ceil(uv.max(axis=0) + pad) + 1, (w, h)).astype(int)
        if x1 > x0 and y1 > y0:
            v, u = np.mgrid[y0:y1, x0:x1].astype(float)
            xy = camera.undistort_normalized(np.stack([u.ravel(), v.ravel()], axis=1))
            xy = np.nan_to_num(xy, nan=-1e3).reshape(y1 - y0, x1 - x0, 2)
            K = camera.K
            map_u = (K[0, 0] * xy[..., 0] + K[0, 2]).astype(np.float32)
            map_v = (K[1, 1] * xy[..., 1] + K[1, 2]).astype(np.float32)
            t = cv2.remap(tags, map_u, map_v, cv2.INTER_LINEAR, borderValue=0)
            a = cv2.remap(alpha, map_u, map_v, cv2.INTER_LINEAR, borderValue=0)
            region = out[y0:y1, x0:x1]
            out[y0:y1, x0:x1] = region * (1 - a) + t * a
    if noise_px > 0:
        out += np.random.default_rng(seed).normal(0.0, noise_px, out.shape)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


#: Deadline settings for tests that spawn a real control process to check something other
#: than its deadlines (REST flows, stop and reset): the test machine is shared and not
#: real-time, and a normal-priority child there was seen 16-57 ms late under load, which
#: the product's 10 ms limit rightly turns into a stop. The deadline watchdog itself is
#: tested on a virtual clock (tests/realtime/test_control_loop.py, tests/safety).
LOADED_MACHINE = {"max_period_lateness": 0.5, "deadline_misses": 1000}

#: The stops a starved machine causes, which the daemon is right to take: camera stalls
#: (a renderer starved of the 2 cores) and the control loop's deadlines (a clean-clone run
#: here, alone and with SCHED_FIFO, saw the loop complete no period for 108.7 ms: whole
#: processes stop for about 100 ms now and then, cause not found; docs/control_loop.md).
MACHINE_STOPS = ("camera_stall:", "deadline:")


def machine_stops_only(reasons: object) -> bool:
    """Whether the daemon's stop ``reasons`` (its /status safety reasons, each a dict
    with a ``source``) are all :data:`MACHINE_STOPS`: an end-to-end run stopped by those
    alone may be run once more; any other reason fails it."""
    def machine(e: object) -> bool:
        # a watchdog names itself as the source (deadline:stalled, camera_stall:left); the
        # loop's own stop is the source "control loop" with the trip as its reason
        if not isinstance(e, dict):
            return False
        source, reason = str(e.get("source", "")), str(e.get("reason", ""))
        return source.startswith(MACHINE_STOPS) or (source == "control loop"
                                                    and reason.startswith("deadline:"))

    return isinstance(reasons, list) and bool(reasons) and all(map(machine, reasons))


def draw_visible_runs(img: np.ndarray, uv: np.ndarray, keep: np.ndarray, value: int,
                      thickness: int) -> None:
    """Draw the polyline ``uv`` (N, 2 px) on ``img`` in place, anti-aliased at 1/16 px,
    only along its runs of consecutive points where ``keep`` (N,) is True: a needle cut
    by the tissue plane shows as separate pieces."""
    for run in np.split(np.arange(len(uv)), np.nonzero(np.diff(keep))[0] + 1):
        if keep[run[0]] and run.size > 1:
            cv2.polylines(img, [np.round(uv[run] * 16).astype(np.int32)], False, value,
                          thickness, cv2.LINE_AA, 4)
