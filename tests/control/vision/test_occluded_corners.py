"""Tests of the X-junction check of ``oralnav.control.vision.detection`` against occluders
(issue 34 item 5, "a half-occluded ChArUco corner is accepted").

Requirement (docs/tracking.md, "Corner checks"): a chessboard corner is reported only
where its neighbourhood is the X-junction the field predicts. A corner that an occluder
covers, or whose refinement window an occluder's edge crosses, is dropped or, if kept,
lies within 0.5 px of its true position; corners clear of the occluder that the
refinement located (within 0.2 px) are all kept.

Synthetic views: a flat board warped by a homography, area-sampled (4 x 4 sub-pixels),
then an occluder (a half-plane with a straight edge, dark, light or textured) blended in
by its area coverage, then blur and noise. The true corners come from the homography.
Real views: OpenCV's ChArUco tutorial photographs (tests/data/opencv_charuco/README.md).
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import cv2
import numpy as np
import pytest

from oralnav.control.vision.detection import (
    detect_fields,
    refine_corners,
    subpix_window,
    x_junction_ok,
)
from oralnav.control.vision.markers import MarkerField

ROOT = Path(__file__).resolve().parents[3]
PHOTOS = ROOT / "tests" / "data" / "opencv_charuco"

SHEET = MarkerField("sheet", "DICT_4X4_1000", (6, 5), 0.004, 0.003, first_id=40)
PPS = 64        # pixels per square of the flat sheet image that is warped
SUPER = 4       # sub-pixels per pixel side for area sampling
#: the corner the occluder's edge is laid against (second row, third column of inner corners)
CHOSEN = 7


@dataclass(frozen=True)
class Geometry:
    """One synthetic view of SHEET: square side (px), in-plane turn (deg), projective
    terms of the homography (1/px), blur sigma (px) and read noise (DN)."""

    square_px: float
    turn_deg: float
    tilt: tuple[float, float]
    blur: float
    noise: float


GEOMETRIES = {
    "40px": Geometry(40.0, 12.0, (4e-4, -3e-4), 0.8, 1.5),
    "24px": Geometry(24.0, -20.0, (-6e-4, 5e-4), 1.0, 2.0),
    "14px": Geometry(14.0, 33.0, (8e-4, 0.0), 0.8, 1.5),
}


@dataclass(frozen=True)
class View:
    """An area-sampled, unblurred view (float DN), the true corner pixels (all ids), and
    the prediction the check needs: axes (N x 2 x 2), light diagonal and square side."""

    geometry: Geometry
    image: np.ndarray
    corners: np.ndarray
    axes: np.ndarray
    light: np.ndarray
    square_px: np.ndarray


@cache
def _view(name: str) -> View:
    g = GEOMETRIES[name]
    nx, ny = SHEET.squares
    w, h = int(g.square_px * nx + 60), int(g.square_px * ny + 60)
    # flat sheet pixels -> image pixels: centre the sheet, scale and turn, then tilt
    c, s = np.cos(np.radians(g.turn_deg)), np.sin(np.radians(g.turn_deg))
    k = g.square_px / PPS
    to_centre = np.array([[1, 0, -nx * PPS / 2], [0, 1, -ny * PPS / 2], [0, 0, 1.0]])
    turn = np.array([[k * c, -k * s, 0], [k * s, k * c, 0], [0, 0, 1.0]])
    tilt = np.array([[1, 0, 0], [0, 1, 0], [g.tilt[0], g.tilt[1], 1.0]])
    shift = np.array([[1, 0, w / 2], [0, 1, h / 2], [0, 0, 1.0]])
    H = shift @ tilt @ turn @ to_centre
    # Pixel centres: image pixel j is sub-pixels SUPER j .. SUPER j + SUPER - 1, centred
    # at SUPER j + (SUPER - 1) / 2.
    sub = np.array([[SUPER, 0, (SUPER - 1) / 2], [0, SUPER, (SUPER - 1) / 2], [0, 0, 1.0]])
    sheet = SHEET.board_image(PPS).astype(np.float32) / 255 * 190 + 25  # print: 25..215 DN
    fine = cv2.warpPerspective(sheet, sub @ H, (w * SUPER, h * SUPER), flags=cv2.INTER_LINEAR,
                               borderMode=cv2.BORDER_CONSTANT, borderValue=120)
    image = cv2.resize(fine, (w, h), interpolation=cv2.INTER_AREA)
    # Corner (col, row) of the sheet is at sheet pixel (col PPS - 0.5, row PPS - 0.5).
    j = np.arange(SHEET.corner_count)
    col, row = j % (nx - 1) + 1, j // (nx - 1) + 1
    flat = np.stack([col * PPS - 0.5, row * PPS - 0.5], axis=1)
    p = np.concatenate([flat, np.ones((len(flat), 1))], axis=1) @ H.T
    corners = p[:, :2] / p[:, 2:]
    # Image of one square step along the sheet's x and y: the homography's Jacobian.
    J = (H[None, :2, :2] - corners[:, :, None] * H[None, 2:3, :2]) / p[:, 2:, None] * PPS
    axes = J.transpose(0, 2, 1)
    light = np.where(sheet[(row * PPS + 2), (col * PPS + 2)] > 120, 1.0, -1.0)
    square_px = np.sqrt(np.abs(np.linalg.det(axes)))
    return View(g, image, corners, axes, light, square_px)


def _occluded(view: View, angle_deg: float, offset: float, kind: str,
              seed: int) -> tuple[np.ndarray, np.ndarray]:
    """The view with the half-plane n . (p - chosen corner) > offset covered (n at
    ``angle_deg``; offset in px, negative: the chosen corner is under it), blurred and
    noisy (mono8). Also returns each corner's signed distance to the edge (px, > 0:
    covered)."""
    h, w = view.image.shape
    n = np.array([np.cos(np.radians(angle_deg)), np.sin(np.radians(angle_deg))])
    c = view.corners[CHOSEN]
    sx = (np.arange(w * SUPER) - (SUPER - 1) / 2) / SUPER
    sy = (np.arange(h * SUPER) - (SUPER - 1) / 2) / SUPER
    inside = (n[0] * (sx[None, :] - c[0]) + n[1] * (sy[:, None] - c[1])) > offset
    cover = cv2.resize(inside.astype(np.float32), (w, h), interpolation=cv2.INTER_AREA)
    rng = np.random.default_rng(seed)
    if kind == "dark":
        occ = np.full((h, w), 8.0, np.float32)
    elif kind == "light":
        occ = np.full((h, w), 245.0, np.float32)
    else:  # texture: blotches about 3 px across, of the full grey range
        blobs = rng.uniform(0, 255, (h // 3 + 2, w // 3 + 2)).astype(np.float32)
        occ = np.clip(cv2.resize(blobs, (w, h), interpolation=cv2.INTER_CUBIC), 0, 255)
    img = cover * occ + (1 - cover) * view.image
    img = cv2.GaussianBlur(img, (0, 0), view.geometry.blur)
    img = img + rng.normal(0.0, view.geometry.noise, img.shape)
    dist = (view.corners - c) @ n - offset
    return np.clip(np.round(img), 0, 255).astype(np.uint8), dist


def _check(view: View, image: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Refine every corner from a prediction 0.5 px off (predictive tracking's case), then
    run the X-junction check as ``detect_fields`` does. Returns (kept, error px)."""
    rng = np.random.default_rng(seed)
    a = rng.uniform(0, 2 * np.pi, len(view.corners))
    start = view.corners + 0.5 * np.stack([np.cos(a), np.sin(a)], axis=1)
    px, ok = refine_corners(image, start, view.square_px)
    kept = ok & x_junction_ok(image, px, view.axes, view.light, among=ok,
                              square_px=view.square_px)
    return kept, np.linalg.norm(px - view.corners, axis=1)


def _clean(view: View, blur: float, noise: float, seed: int) -> np.ndarray:
    """The view with nothing over it, blurred and noisy (mono8)."""
    rng = np.random.default_rng(seed)
    img = cv2.GaussianBlur(view.image, (0, 0), blur) + rng.normal(0, noise, view.image.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


@pytest.mark.parametrize("name, blur, noise", [
    ("40px", 0.8, 1.5), ("40px", 2.0, 2.0), ("40px", 0.8, 6.0),
    ("24px", 1.0, 2.0), ("24px", 1.5, 2.0), ("24px", 1.0, 6.0),
    ("14px", 0.8, 1.5), ("14px", 0.8, 4.0),
])
def test_clean_views_keep_good_corners(name, blur, noise):
    """Corner checks, no false rejects: with nothing over the board, every corner that
    the refinement put within 0.2 px of the truth is kept, over ten noise draws (200
    corners per case). Only on 14 px squares with 4 DN of noise are some dropped (7 of
    200, all 0.24-0.5 px off: the ring, 2-3 px from the corner, then notices the
    refinement's error)."""
    view = _view(name)
    kept_all, err_all = [], []
    for seed in range(10):
        kept, err = _check(view, _clean(view, blur, noise, seed), seed)
        kept_all.append(kept)
        err_all.append(err)
    kept, err = np.concatenate(kept_all), np.concatenate(err_all)
    assert kept[err <= 0.2].all(), err[~kept]
    assert kept.mean() >= 0.93, (kept.sum(), len(kept), np.sort(err[~kept]))
    assert np.all(err[kept] <= 0.5), err[kept].max()


@pytest.mark.parametrize("name, blur", [("14px", 1.0), ("14px", 1.2), ("14px", 1.5),
                                        ("24px", 2.0)])
def test_blurred_small_squares_give_no_corner_off_by_more_than_half_a_pixel(name, blur):
    """Corner checks, stability where methods fail: with 14 px squares under 1-1.5 px of
    blur (24 px under 2 px), ``cornerSubPix`` (2-3 px half-window) stops up to 0.75 px
    (1 px blur) and 0.6-1.8 px (1.2-1.5 px blur) from the corners; the old check kept
    nearly all of them. What is kept now is within 0.5 px."""
    view = _view(name)
    for seed in range(3):
        kept, err = _check(view, _clean(view, blur, 2.0, seed), seed)
        assert np.all(err[kept] <= 0.5), (seed, err[kept])


OFFSETS_PX = (-2.0, -1.0, -0.5, 0.0, 0.5, 1.0, 2.0)
KINDS = ("dark", "light", "texture")


@pytest.mark.parametrize("name", list(GEOMETRIES))
def test_occluder_edge_sweep(name):
    """Corner checks under occlusion (issue 34 item 5): an occluder's straight edge laid
    against corner 7 at every 15 deg, at 0, +-0.5, +-1, +-2 px and +-0.25 square from it,
    dark, light or textured (648 views). Corner 7 with the edge through it is dropped at
    every angle and shade. Every corner that a dark or light occluder covers, or whose
    ring it reaches (within 1.5 refinement half-windows + 1 px of the edge), is dropped
    or within 0.5 px. Under texture a saddle of the texture can pass for a corner: at
    most one such corner, of the ~2,000 under or near texture per view size, is kept
    more than 0.5 px off (one, 3.3 px, at 24 px squares). Every corner 0.3 square or more
    clear of the edge that the refinement put within 0.2 px is kept."""
    view = _view(name)
    sq = view.geometry.square_px
    win = subpix_window(view.square_px)
    offsets = OFFSETS_PX + (-0.25 * sq, 0.25 * sq)
    near_n = {kind: 0 for kind in KINDS}
    near_kept = {kind: 0 for kind in KINDS}
    texture_off = []
    clear_n = clear_kept = 0
    for angle in range(0, 360, 15):
        for offset in offsets:
            for kind in KINDS:
                seed = zlib.crc32(f"{name} {angle} {offset} {kind}".encode())
                img, dist = _occluded(view, angle, offset, kind, seed)
                kept, err = _check(view, img, seed)
                near = dist > -(1.5 * win + 1.0)
                clear = dist < -0.3 * sq
                where = (angle, offset, kind)
                if offset == 0.0:
                    assert not kept[CHOSEN], (where, err[CHOSEN])
                off = near & kept & (err > 0.5)
                if kind == "texture":
                    texture_off += [(where, int(i), round(float(err[i]), 2))
                                    for i in np.flatnonzero(off)]
                else:
                    assert not off.any(), (where, np.flatnonzero(off), err[off])
                near_n[kind] += int(near.sum())
                near_kept[kind] += int((near & kept).sum())
                good = clear & (err <= 0.2)
                assert kept[good].all(), (where, np.flatnonzero(good & ~kept))
                clear_n += int(clear.sum())
                clear_kept += int((clear & kept).sum())
    assert len(texture_off) <= 1, texture_off
    # the sweep exercises both sides: many corners near the edge, many clear of it
    assert min(near_n.values()) > 600 and clear_n > 2000, (near_n, clear_n)
    print(f"{name}: near the edge kept {near_kept} of {near_n}; texture kept > 0.5 px: "
          f"{texture_off}; clear of it {clear_kept} of {clear_n} kept")


# -- OpenCV's tutorial photographs ----------------------------------------------------------
TUTORIAL = MarkerField("tutorial", "DICT_6X6_250", (5, 7), 0.04, 0.02, first_id=0)
#: OpenCV's tutorial_camera_charuco.yml: camera matrix (px) and distortion (k1 k2 p1 p2 k3)
TUTORIAL_K = np.array([[452.51072219637672, 0.0, 317.70297317353277],
                       [0.0, 456.76707935146891, 277.75155919135995], [0.0, 0.0, 1.0]])
TUTORIAL_DIST = np.array([0.12136925618707872, -1.0854664722560681, 1.1786843796668460e-04,
                          -4.6240686046485508e-04, 2.9542589406810080])
needs_photos = pytest.mark.skipif(not PHOTOS.is_dir(), reason=f"{PHOTOS} is absent")


def _photo_check(name: str) -> tuple[dict[int, float], np.ndarray]:
    """Our corners' distances (px) to the board's pose, and OpenCV's corner ids. The pose
    is solved from OpenCV's own ChArUco corners with the tutorial's calibration."""
    image = cv2.imread(str(PHOTOS / name), cv2.IMREAD_GRAYSCALE)
    assert image is not None, name
    cv_px, cv_ids, _, _ = cv2.aruco.CharucoDetector(TUTORIAL.board).detectBoard(image)
    cv_ids = cv_ids.ravel()
    ok, rvec, tvec = cv2.solvePnP(TUTORIAL.corners[cv_ids], cv_px.reshape(-1, 2),
                                  TUTORIAL_K, TUTORIAL_DIST)
    assert ok
    posed = cv2.projectPoints(TUTORIAL.corners, rvec, tvec, TUTORIAL_K,
                              TUTORIAL_DIST)[0].reshape(-1, 2)
    # the pose fits OpenCV's corners: it is the reference
    assert np.linalg.norm(posed[cv_ids] - cv_px.reshape(-1, 2), axis=1).max() < 0.45
    found = detect_fields(image, [TUTORIAL])["tutorial"]
    err = np.linalg.norm(found.px - posed[found.ids], axis=1)
    return dict(zip(found.ids.tolist(), err.tolist(), strict=True)), cv_ids


@needs_photos
def test_photo_corner_on_a_mouse_edge_is_dropped():
    """Corner checks on a real photograph (issue 34 item 5): in OpenCV's
    chocclusion_original.jpg a mouse lies over the board and its edge runs through
    corner 15, which came out 1.6 px from the board's pose (OpenCV's corners fit that pose
    within 0.27 px). It is dropped now, and so is corner 21 at the mouse's edge (half its
    contrast); the 18 corners kept are all within 0.4 px of the pose."""
    err, cv_ids = _photo_check("chocclusion_original.jpg")
    assert 15 not in err and 21 not in err, err
    assert len(err) >= 18, sorted(err)
    assert max(err.values()) <= 0.4, err


@needs_photos
def test_photo_without_occluder_keeps_every_corner():
    """Corner checks, no false rejects on real pixels: in OpenCV's choriginal.jpg (the
    same board, nothing over it; sharp, JPEG-compressed, printed corners not perfect
    X-junctions) all 24 corners are kept, each within 0.4 px of the board's pose."""
    err, cv_ids = _photo_check("choriginal.jpg")
    assert sorted(err) == list(range(TUTORIAL.corner_count)), sorted(err)
    assert max(err.values()) <= 0.4, err
