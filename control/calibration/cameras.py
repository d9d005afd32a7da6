"""Intrinsic and stereo calibration from detected views of a flat target.

Pure math on detections: a *view* is what a detector found in one image of a flat target
(a ChArUco field, or a chessboard, circle grid, ArUco grid or custom-dictionary ChArUco
board of :mod:`oralnav.control.calibration.targets`): the target's point ids (N,) and their
pixel positions (N x 2) (a :class:`~oralnav.control.vision.detection.FieldCorners`, or an
``(ids, px)`` pair); ``None`` stands for an image in which the target was not found, so
that index ``k`` of a left and a right list stays the same instant. OpenCV is the solver
(``calibrateCameraExtended``, ``fisheye.calibrate``, ``stereoCalibrateExtended``); this
module checks the input, rejects outlier views, detects degenerate view sets and reports
image coverage.

Frames and units: pixels with the centre of the top-left pixel at (0, 0); the board frame is
the field frame of :mod:`oralnav.control.vision.markers` or the target frame of
:mod:`oralnav.control.calibration.targets` (metres); ``T_cam_board`` is the board's
pose in the camera frame, ``T_left_right`` the right camera's pose in the left camera's
frame (metres), i.e. the right camera's ``T_ref_cam`` in a rig whose reference is the left
camera.

Fitting. Every calibration runs in two passes: the second starts from the first's
intrinsics (the rational model from a standard-model fit), because OpenCV starts each
view's pose from a homography through the starting intrinsics, and without a distortion
estimate a view in a strongly distorted image corner can settle in a local minimum.

Outlier views. Each round calibrates on the accepted views and computes every view's RMS
reprojection error e_i (a view left out has its pose solved alone under that round's
intrinsics). A :class:`RejectRule` sets the limit from the accepted views' e_i: with m
their median and s = 1.4826 * MAD (their median absolute deviation, scaled to a standard
deviation for normal data), each term of the rule gives a limit (``mad:K`` m + K s,
``median:F`` F m, ``floor:P`` m + P px, ``px:P`` P px) and a view is an outlier when its
e_i exceeds the largest of them. The default, ``mad:4,median:2,floor:0.25``, puts the
limit at ``m + max(4 s, 0.25 px, m)``: four standard deviations above the median, but
never within 0.25 px of it nor below twice the median, so a set of uniformly good views
loses nothing to the spread of its own noise (``outlier_k`` and ``outlier_floor_px`` set
its 4 and 0.25). The next round is fitted, from scratch, to the views that are not
outliers; a good view that a gross outlier's pull made look bad comes back once the
outlier is out. The rounds stop when the set of outliers no longer changes (at most
``max_rounds`` fits). The worst views are rejected first, and the accepted set never
shrinks below ``min_views``; each result says, per view, why it was dropped.

A view whose corner ids are wrong (a misread marker, a permuted list) can wreck the first
fit of a single camera so thoroughly, through free distortion coefficients, that every
view comes out tens to hundreds of px off and the rule above can no longer tell which one
is to blame; where that happens depends on the solver's rounding (the thread count, the
CPU's vector unit). Before the first fit each view's own plane-to-image homography is
therefore fitted, and the views whose RMS residual breaks the same rule (a few px for good
views under the endoscope's distortion, hundreds for permuted ids) sit out the first
round. They are sorted against that fit like any other view, so a good view the screen
suspected comes back in the next round.

Degenerate views. A focal length cannot be told apart from distance when every view shows
the board at the same orientation. The spread of the board normals in the camera frame
(largest angle between two views' normals) must reach ``min_normal_spread_deg``
(default 5 deg). It is checked on the calibrated poses; before calibrating, a cheap check
on each view's homography (through a guessed focal length) turns away sets that are
flagrantly flat (under a quarter of that), which OpenCV would otherwise solve into
nonsense.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, ClassVar, Literal

import cv2
import numpy as np

from oralnav.control.errors import CalibrationError
from oralnav.control.geometry import invert, make_transform
from oralnav.control.vision.camera import CameraModel, Rig
from oralnav.control.vision.detection import FieldCorners
from oralnav.control.vision.markers import MarkerField, PlaneSurface

from .targets import Target

__all__ = [
    "DEFAULT_REJECT",
    "MODELS",
    "CalibrationError",
    "CameraCalibration",
    "Coverage",
    "RejectRule",
    "StereoCalibration",
    "calibrate_camera",
    "calibrate_stereo",
    "image_coverage",
]

Model = Literal["radtan", "standard", "rational", "fisheye"]

#: Distortion models and the length of their coefficient vector (OpenCV order):
#: ``radtan`` k1 k2 p1 p2 (k3 held at 0: Kalibr's radtan, which cannot hold a k3);
#: ``standard`` k1 k2 p1 p2 k3; ``rational`` k1 k2 p1 p2 k3 k4 k5 k6 (``CALIB_RATIONAL_MODEL``);
#: ``fisheye`` OpenCV's equidistant fisheye model, k1 k2 k3 k4 (``cv2.fisheye``; these are
#: not pinhole coefficients and :class:`CameraModel` cannot hold them).
MODELS: Mapping[str, int] = {"radtan": 4, "standard": 5, "rational": 8, "fisheye": 4}

#: Default minimum numbers of usable views (single camera, stereo pair) and of corners in a
#: usable view.
MIN_VIEWS = 6
MIN_STEREO_VIEWS = 5
MIN_CORNERS = 8

#: How far (px) corners may lie outside the image before the image size is called wrong.
_IMAGE_SLACK_PX = 1.0

_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)


ViewLike = FieldCorners | tuple[Any, Any] | None
#: A flat calibration target: a tracked ChArUco field on a plane, or a target of
#: :mod:`oralnav.control.calibration.targets`.
Board = MarkerField | Target


# -- input ---------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class _View:
    index: int
    ids: np.ndarray      # (N,) corner ids
    obj: np.ndarray      # (N, 3) board-frame corners, m
    px: np.ndarray       # (N, 2) pixels


def _check_size(image_size: Any, what: str = "image_size") -> tuple[int, int]:
    try:
        w, h = (int(v) for v in image_size)
        ok = (w, h) == tuple(image_size)
    except (TypeError, ValueError):
        ok = False
    if not ok or w <= 0 or h <= 0:
        raise CalibrationError(f"{what} must be (width, height) in pixels, positive "
                               f"integers; got {image_size!r}")
    return w, h


def _check_board(board: Board) -> None:
    if isinstance(board, Target):
        return  # every target is flat
    if not isinstance(board, MarkerField):
        raise CalibrationError(f"board_field must be a MarkerField or a calibration Target, "
                               f"got {type(board).__name__}")
    if not isinstance(board.surface, PlaneSurface):
        raise CalibrationError(
            f"board {board.name!r} has a {board.surface.kind} surface; calibration needs a "
            "flat board (plane surface)")


def _pitch(board: Board) -> float:
    """The board's point spacing (m): a ChArUco square, a target's pitch."""
    return board.pitch if isinstance(board, Target) else float(board.square)


def _parse_view(v: ViewLike, k: int, board: Board, size: tuple[int, int],
                where: str) -> _View | None:
    """Check one view and pair its corners with the board model; ``None`` stays ``None``."""
    if v is None:
        return None
    name = f"{where}view {k}"
    if hasattr(v, "ids") and hasattr(v, "px"):
        ids_in, px_in = v.ids, v.px
    elif isinstance(v, tuple | list) and len(v) == 2:
        ids_in, px_in = v
    else:
        raise CalibrationError(f"{name}: expected corner ids and pixels (a FieldCorners or an "
                               f"(ids, px) pair), got {type(v).__name__}")
    try:
        ids_f = np.asarray(ids_in, dtype=float).reshape(-1)
        px = np.asarray(px_in, dtype=float)
    except (TypeError, ValueError):
        raise CalibrationError(f"{name}: ids and px must be numeric arrays") from None
    if px.ndim != 2 or px.shape != (len(ids_f), 2):
        raise CalibrationError(f"{name}: px must be N x 2 with N = len(ids) = {len(ids_f)}, "
                               f"got shape {px.shape}")
    if not np.all(np.isfinite(ids_f)) or np.any(ids_f != np.round(ids_f)):
        raise CalibrationError(f"{name}: corner ids must be integers")
    bad = ~np.all(np.isfinite(px), axis=1)
    if np.any(bad):
        raise CalibrationError(
            f"{name}: {int(bad.sum())} corner pixel(s) are NaN or infinite (corner ids "
            f"{ids_f[bad].astype(int)[:8].tolist()})")
    ids = ids_f.astype(int)
    off = np.array([i not in board.corner_index for i in ids], dtype=bool)
    if np.any(off):
        raise CalibrationError(
            f"{name}: corner ids {ids[off][:8].tolist()} are not on board {board.name!r} "
            f"(ids 0..{board.corner_count - 1}); wrong board_field?")
    uniq, counts = np.unique(ids, return_counts=True)
    if np.any(counts > 1):
        dup = uniq[counts > 1]
        raise CalibrationError(f"{name}: corner ids {dup[:8].tolist()} appear more than once")
    w, h = size
    s = _IMAGE_SLACK_PX
    out = ((px[:, 0] < -0.5 - s) | (px[:, 0] > w - 0.5 + s)
           | (px[:, 1] < -0.5 - s) | (px[:, 1] > h - 0.5 + s))
    if np.any(out):
        u, v_ = px[out][np.argmax(np.abs(px[out] - (w / 2, h / 2)).max(axis=1))]
        raise CalibrationError(
            f"{name}: corner at ({u:.1f}, {v_:.1f}) px lies outside the {w}x{h} image; the "
            "image size does not match the camera these views come from")
    obj = board.corners[[board.corner_index[int(i)] for i in ids]]
    return _View(k, ids, obj, px)


def _too_thin(view: _View, board: Board, min_corners: int) -> str | None:
    """Why a view cannot constrain a calibration, or None when it can."""
    n = len(view.ids)
    if n < max(3, min_corners):
        return f"{n} corners (fewer than {max(3, min_corners)})"
    xy = view.obj[:, :2] - view.obj[:, :2].mean(axis=0)
    if np.linalg.svd(xy, compute_uv=False)[1] < 0.5 * _pitch(board):
        return "its corners lie on one line of the board"
    return None


def parse_views(views: Sequence[ViewLike], board: Board, size: tuple[int, int],
                 min_corners: int | None, where: str
                 ) -> tuple[list[_View | None], dict[int, str]]:
    """Check every view; with ``min_corners``, views too thin to use become ``None`` and
    are listed (index -> reason) with those where the board was not found."""
    if isinstance(views, FieldCorners | np.ndarray) or not isinstance(views, Sequence):
        raise CalibrationError(f"{where}views must be a sequence of views (one per image), "
                               f"got {type(views).__name__}")
    parsed = [_parse_view(v, k, board, size, where) for k, v in enumerate(views)]
    skipped: dict[int, str] = {}
    for k, v in enumerate(parsed):
        if v is None:
            skipped[k] = "board not found"
        elif min_corners is not None:
            why = _too_thin(v, board, min_corners)
            if why:
                skipped[k] = why
                parsed[k] = None
    return parsed, skipped


def _not_enough(n: int, need: int, total: int, skipped: Mapping[int, str], what: str) -> str:
    msg = f"only {n} usable {what} of {total} (need at least {need})"
    if skipped:
        parts = [f"{k}: {why}" for k, why in list(skipped.items())[:6]]
        more = f", and {len(skipped) - 6} more" if len(skipped) > 6 else ""
        msg += "; skipped views " + "; ".join(parts) + more
    return msg


# -- orientation spread -------------------------------------------------------------------
def _normal_spread_deg(normals: np.ndarray) -> float:
    """Largest angle (deg) between two unit normals (V x 3), sign-agnostic."""
    c = np.abs(np.clip(normals @ normals.T, -1.0, 1.0))
    return float(np.degrees(np.arccos(c.min())))


def _homography_normals(views: Sequence[_View], K: np.ndarray) -> np.ndarray:
    """Board normals (V x 3, camera frame) from each view's plane-to-image homography
    through intrinsics ``K`` (distortion ignored): the cheap pre-check."""
    Kinv = np.linalg.inv(K)
    out = []
    for v in views:
        H, _ = cv2.findHomography(v.obj[:, :2], v.px, 0)
        if H is None:
            continue
        M = Kinv @ H
        a = M[:, 0] / np.linalg.norm(M[:, 0])
        b = M[:, 1] / np.linalg.norm(M[:, 1])
        n = np.cross(a, b)
        out.append(n / np.linalg.norm(n))
    return np.asarray(out).reshape(-1, 3)


@dataclass(frozen=True)
class RejectRule:
    """When a view's RMS error (px) makes it an outlier (module docstring): when it exceeds
    the largest limit of the terms given. A rule without terms rejects nothing.

    Attributes:
        mad: ``K`` of the limit ``m + K s`` (robust standard deviations above the median).
        median: ``F`` of the limit ``F m`` (at least 1).
        floor_px: ``P`` of the limit ``m + P`` (px above the median).
        max_px: an absolute limit (px).
    """

    mad: float | None = None
    median: float | None = None
    floor_px: float | None = None
    max_px: float | None = None

    #: The terms' names in :meth:`parse` and ``str()``, and their attributes.
    TERMS: ClassVar[Mapping[str, str]] = {"mad": "mad", "median": "median",
                                          "floor": "floor_px", "px": "max_px"}

    def __post_init__(self) -> None:
        for name, attr in self.TERMS.items():
            v = getattr(self, attr)
            if v is None:
                continue
            least = 1.0 if name == "median" else 0.0
            if isinstance(v, bool) or not isinstance(v, int | float) or not (
                    np.isfinite(v) and v >= least and (v > 0 or name == "floor")):
                raise CalibrationError(
                    f"reject rule {name}: expected a finite number "
                    f"{'>= 1' if name == 'median' else '>= 0' if name == 'floor' else '> 0'}"
                    f", got {v!r}")

    @property
    def enabled(self) -> bool:
        return any(getattr(self, a) is not None for a in self.TERMS.values())

    @classmethod
    def parse(cls, text: str) -> RejectRule:
        """A rule from its text: ``none``, or terms ``NAME:VALUE`` joined by commas
        (``median:2``, ``mad:4,median:2,floor:0.25``); ``default`` is
        :data:`DEFAULT_REJECT`."""
        t = str(text).strip().lower()
        if t == "none":
            return cls()
        if t == "default":
            return DEFAULT_REJECT
        values: dict[str, float] = {}
        for part in t.split(","):
            name, sep, value = part.strip().partition(":")
            if not sep or name not in cls.TERMS:
                raise CalibrationError(
                    f"reject rule {text!r}: {part.strip()!r} is not a term NAME:VALUE with NAME "
                    f"one of {', '.join(cls.TERMS)} (or give none, or default)")
            if cls.TERMS[name] in values:
                raise CalibrationError(f"reject rule {text!r}: {name} given twice")
            try:
                values[cls.TERMS[name]] = float(value)
            except ValueError:
                raise CalibrationError(f"reject rule {text!r}: {name}: {value!r} is not a "
                                       "number") from None
        return cls(**values)

    def __str__(self) -> str:
        terms = [f"{n}:{getattr(self, a):g}" for n, a in self.TERMS.items()
                 if getattr(self, a) is not None]
        return ",".join(terms) if terms else "none"

    def limit(self, errors: Sequence[float]) -> tuple[float, str]:
        """The limit (px) that ``errors`` (the accepted views' RMS, px) set, and the term
        that set it in words; ``(inf, "no rejection")`` for a rule without terms."""
        e = np.asarray(errors, dtype=float)
        m = float(np.median(e))
        s = 1.4826 * float(np.median(np.abs(e - m)))
        cands = []
        if self.mad is not None:
            cands.append((m + self.mad * s, f"median {m:.3f} px + {self.mad:g} x {s:.3f} px "
                                            "robust sigma"))
        if self.median is not None:
            cands.append((self.median * m, f"{self.median:g} x median {m:.3f} px"))
        if self.floor_px is not None:
            cands.append((m + self.floor_px, f"median {m:.3f} px + {self.floor_px:g} px"))
        if self.max_px is not None:
            cands.append((self.max_px, f"{self.max_px:g} px"))
        return max(cands, key=lambda c: c[0]) if cands else (np.inf, "no rejection")


#: Today's rule: ``m + max(4 s, 0.25 px, m)`` (module docstring).
DEFAULT_REJECT = RejectRule(mad=4.0, median=2.0, floor_px=0.25)


def _rule(reject: RejectRule | str | None, reject_outliers: bool, k: float,
          floor_px: float) -> RejectRule:
    """The rule a calibration runs: ``reject`` when given, else the default one with
    ``outlier_k`` and ``outlier_floor_px`` (none when ``reject_outliers`` is false)."""
    if isinstance(reject, str):
        return RejectRule.parse(reject)
    if isinstance(reject, RejectRule):
        return reject
    if reject is not None:
        raise CalibrationError(f"reject must be a RejectRule or its text, got "
                               f"{type(reject).__name__}")
    return RejectRule(mad=k, median=2.0, floor_px=floor_px) if reject_outliers else RejectRule()


def homography_screen(views: Sequence[_View], rule: RejectRule = DEFAULT_REJECT) -> list[int]:
    """Indices of views whose corners no plane-to-image homography fits (module docstring).

    The RMS residual (px) of each view's own least-squares homography is large for every
    view under strong distortion (several px at the image corners), but an order of
    magnitude larger again for a view whose corner ids are wrong; the outlier rule on these
    residuals picks out such a view before it can take part in the first fit. An absolute
    term (``px:``) of ``rule`` is left out: distortion alone puts good views above it.
    """
    rule = replace(rule, max_px=None)
    if not rule.enabled:
        return []
    res: dict[int, float] = {}
    for v in views:
        H, _ = cv2.findHomography(v.obj[:, :2], v.px, 0)
        if H is None:
            res[v.index] = np.inf
            continue
        q = cv2.perspectiveTransform(v.obj[None, :, :2].astype(float), H)[0]
        res[v.index] = _rms(q - v.px)
    limit, _ = rule.limit(list(res.values()))
    return sorted(i for i, e in res.items() if e > limit)


def _degenerate_msg(spread: float, need: float, n: int) -> str:
    return (f"degenerate views: the board normals of the {n} views lie within "
            f"{spread:.2f} deg of one another (need a spread of at least {need:g} deg); with "
            "the board at one orientation the focal length cannot be told apart from the "
            "distance. Show the board tilted 15-45 deg about different axes.")


# -- coverage -----------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Coverage:
    """Where in the image the corners of a set of views fell.

    Attributes:
        image_size: ``(width, height)`` px.
        counts: corners per cell of a coarse grid (rows x cols, int; row 0 at the image
            top, column 0 at the left).
        cell_fraction: fraction of grid cells holding at least one corner.
        hull_fraction: area of the convex hull of all corners over the image area.
    """

    image_size: tuple[int, int]
    counts: np.ndarray
    cell_fraction: float
    hull_fraction: float

    @property
    def grid(self) -> tuple[int, int]:
        """Grid ``(cols, rows)``."""
        return self.counts.shape[1], self.counts.shape[0]

    def empty_cells(self) -> list[tuple[int, int]]:
        """``(col, row)`` of every grid cell without a corner: where more views are needed."""
        rows, cols = np.nonzero(self.counts == 0)
        return [(int(c), int(r)) for r, c in zip(rows, cols, strict=True)]

    def describe(self) -> str:
        """A text map of the grid: ``.`` empty, digits 1-9 tens of corners, ``#`` 100 or more."""
        lines = [f"coverage: {100 * self.cell_fraction:.0f} % of {self.counts.size} cells, "
                 f"convex hull {100 * self.hull_fraction:.0f} % of the image"]
        for row in self.counts:
            lines.append("  " + "".join(
                "." if c == 0 else ("#" if c >= 100 else str(max(1, c // 10))) for c in row))
        return "\n".join(lines)

    def to_dict(self) -> dict:
        return {"image_size": list(self.image_size), "grid": list(self.grid),
                "counts": self.counts.tolist(), "cell_fraction": self.cell_fraction,
                "hull_fraction": self.hull_fraction, "empty_cells": self.empty_cells()}


def _coverage(points: Sequence[np.ndarray], size: tuple[int, int],
              grid: tuple[int, int]) -> Coverage:
    w, h = size
    cols, rows = (int(g) for g in grid)
    if cols < 1 or rows < 1:
        raise CalibrationError(f"coverage grid must be (cols, rows) >= 1, got {grid}")
    counts = np.zeros((rows, cols), dtype=int)
    pts = (np.concatenate([np.asarray(p, float).reshape(-1, 2) for p in points])
           if len(points) else np.zeros((0, 2)))
    if len(pts):
        c = np.clip(((pts[:, 0] + 0.5) * cols / w).astype(int), 0, cols - 1)
        r = np.clip(((pts[:, 1] + 0.5) * rows / h).astype(int), 0, rows - 1)
        np.add.at(counts, (r, c), 1)
    hull = 0.0
    if len(pts) >= 3:
        hull = float(cv2.contourArea(cv2.convexHull(pts.astype(np.float32)))) / (w * h)
    return Coverage((w, h), counts, float(np.mean(counts > 0)), hull)


def image_coverage(views: Sequence[ViewLike], image_size: tuple[int, int],
                   grid: tuple[int, int] = (8, 6)) -> Coverage:
    """Coverage of ``image_size`` by the corners of ``views`` on a ``grid`` (cols, rows);
    for an operator checking a capture before calibrating. ``None`` views are ignored."""
    size = _check_size(image_size)
    pts = []
    for k, v in enumerate(views):
        if v is None:
            continue
        px = np.asarray(v.px if hasattr(v, "px") else v[1], dtype=float)
        if px.ndim != 2 or px.shape[1] != 2 or not np.all(np.isfinite(px)):
            raise CalibrationError(f"view {k}: px must be a finite N x 2 array")
        pts.append(px)
    return _coverage(pts, size, grid)


# -- solver wrappers ----------------------------------------------------------------------
def _obj(views: Sequence[_View], fisheye: bool = False) -> list[np.ndarray]:
    # cv2.calibrateCamera wants Point3f (float32, N x 1 x 3); cv2.fisheye.calibrate fails on
    # views of different lengths unless each is a 1 x N row, and wants float64.
    if fisheye:
        return [np.ascontiguousarray(v.obj.reshape(1, -1, 3), dtype=np.float64) for v in views]
    return [np.ascontiguousarray(v.obj.reshape(-1, 1, 3), dtype=np.float32) for v in views]


def _img(views: Sequence[_View], fisheye: bool = False) -> list[np.ndarray]:
    if fisheye:
        return [np.ascontiguousarray(v.px.reshape(1, -1, 2), dtype=np.float64) for v in views]
    return [np.ascontiguousarray(v.px.reshape(-1, 1, 2), dtype=np.float32) for v in views]


def _project(model: str, K: np.ndarray, dist: np.ndarray, T: np.ndarray,
             obj: np.ndarray) -> np.ndarray:
    rvec = np.ascontiguousarray(cv2.Rodrigues(np.ascontiguousarray(T[:3, :3]))[0])
    tvec = np.ascontiguousarray(T[:3, 3].reshape(3, 1))
    o = np.ascontiguousarray(obj.reshape(-1, 1, 3), dtype=np.float64)
    if model == "fisheye":
        uv, _ = cv2.fisheye.projectPoints(o, rvec, tvec, K, dist)
    else:
        uv, _ = cv2.projectPoints(o, rvec, tvec, K, dist)
    return uv.reshape(-1, 2)


def _rms(residual: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(residual ** 2, axis=1)))) if len(residual) else np.nan


def _pose(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    return make_transform(cv2.Rodrigues(np.asarray(rvec, float).reshape(3))[0],
                          np.asarray(tvec, float).reshape(3))


def _solve_pnp(model: str, K: np.ndarray, dist: np.ndarray, v: _View) -> np.ndarray | None:
    """Board pose of a view under fixed intrinsics (for views left out of the fit)."""
    try:
        if model == "fisheye":
            ok, rvec, tvec = cv2.fisheye.solvePnP(_obj([v], True)[0], _img([v], True)[0], K,
                                                  dist)
        else:
            ok, rvec, tvec = cv2.solvePnP(_obj([v])[0], _img([v])[0], K, dist)
    except cv2.error:
        return None
    return _pose(rvec, tvec) if ok else None


def _model_flags(n_dist: int) -> int:
    """OpenCV flags enabling the coefficients of a pinhole distortion vector's length."""
    flags = cv2.CALIB_FIX_K3 if n_dist == 4 else 0
    if n_dist >= 8:
        flags |= cv2.CALIB_RATIONAL_MODEL
    if n_dist >= 12:
        flags |= cv2.CALIB_THIN_PRISM_MODEL
    if n_dist >= 14:
        flags |= cv2.CALIB_TILTED_MODEL
    return flags


@dataclass
class _Fit:
    K: np.ndarray
    dist: np.ndarray
    poses: list[np.ndarray]
    K_std: np.ndarray
    dist_std: np.ndarray


def _fit(model: str, views: Sequence[_View], size: tuple[int, int],
         K_init: np.ndarray | None, dist_init: np.ndarray | None, flags: int,
         criteria: tuple) -> _Fit:
    """One OpenCV calibration; ``K_init``/``dist_init`` (optional) start the optimisation."""
    n = MODELS[model]
    K0 = np.eye(3) if K_init is None else np.array(K_init, dtype=float)
    d0 = np.zeros(n)
    if dist_init is not None:
        d = np.asarray(dist_init, dtype=float).reshape(-1)[:n]
        d0[:len(d)] = d
    if K_init is not None:
        flags |= cv2.CALIB_USE_INTRINSIC_GUESS
    fisheye = model == "fisheye"
    try:
        if fisheye:
            flags |= cv2.CALIB_RECOMPUTE_EXTRINSIC | cv2.CALIB_FIX_SKEW
            _, K, dist, rvecs, tvecs = cv2.fisheye.calibrate(
                _obj(views, True), _img(views, True), size, K0, d0.reshape(n, 1), flags=flags,
                criteria=criteria)
            K_std = np.full(4, np.nan)
            dist_std = np.full(n, np.nan)
        else:
            flags |= _model_flags(n)
            _, K, dist, rvecs, tvecs, std_in, _, _ = cv2.calibrateCameraExtended(
                _obj(views), _img(views), size, K0, d0.reshape(n, 1), flags=flags,
                criteria=criteria)
            std_in = np.asarray(std_in, float).reshape(-1)
            K_std = std_in[:4]
            dist_std = std_in[4:4 + n]
    except cv2.error as exc:
        msg = str(exc).strip().splitlines()[-1] if str(exc).strip() else repr(exc)
        raise CalibrationError(f"OpenCV could not calibrate the {model} model on "
                               f"{len(views)} views: {msg}") from None
    K = np.asarray(K, dtype=float)
    dist = np.asarray(dist, dtype=float).reshape(-1)[:n]
    if not (np.all(np.isfinite(K)) and np.all(np.isfinite(dist))):
        raise CalibrationError(f"the {model} calibration diverged (non-finite intrinsics)")
    return _Fit(K, dist, [_pose(r, t) for r, t in zip(rvecs, tvecs, strict=True)],
                K_std, dist_std)


def _fit_staged(model: str, views: Sequence[_View], size: tuple[int, int],
                K_guess: np.ndarray | None, flags: int, criteria: tuple) -> _Fit:
    """Calibrate in two passes, the second started from the first's intrinsics.

    OpenCV starts every view's pose from a homography through the starting intrinsics.
    Under strong distortion and without a distortion estimate, a view near the image
    corner can start so far off that it settles in a local minimum (1 px RMS where its
    true pose gives 0.04 px); started again from intrinsics that model the distortion, it
    does not. The first pass fits the standard model when the rational one is asked for
    (fewer coefficients, a steadier start).
    """
    first = _fit("standard" if model == "rational" else model, views, size, K_guess, None,
                 flags, criteria)
    return _fit(model, views, size, first.K, first.dist, flags, criteria)


@dataclass
class _Robust:
    state: Any                  # the last fit
    active: list[int]           # views it was fitted to
    rejected: list[int]
    errors: dict[int, float]    # RMS error (px) of every view under it
    rounds: int
    limit: float = np.inf       # the last round's limit (px) and what set it
    how: str = "no rejection"


def robust_fit(indices: Sequence[int], fit: Callable[[list[int]], Any],
                errors: Callable[[Any, list[int]], dict[int, float]], *, rule: RejectRule,
                min_views: int, max_rounds: int, first_out: Sequence[int] = ()) -> _Robust:
    """The outlier loop of the module docstring, under ``rule`` (no term: no rejection).

    ``fit(active)`` calibrates on the active views, from scratch (a previous fit may be
    skewed by the outliers this round leaves out); ``errors(state, views)`` gives each
    view's RMS error under a fit, the pose of a view left out solved alone (``inf`` when
    it cannot be). Each round sorts every view afresh against the limit set by the views
    fitted, so a good view rejected while a gross outlier still skewed the fit comes back
    once the outlier is out. ``first_out`` are views left out of the first fit only (a
    screen's suspects): they are sorted against that fit like every other view.
    """
    reject = rule.enabled
    rejected = sorted(first_out)[:max(0, len(indices) - min_views)] if reject else []
    rounds = 0
    while True:
        rounds += 1
        active = [i for i in indices if i not in rejected]
        state = fit(active)
        if not reject:
            return _Robust(state, active, [], errors(state, active), rounds)
        err = errors(state, list(indices))
        limit, how = rule.limit([err[i] for i in active])
        worst = sorted((i for i in indices if err[i] > limit), key=lambda i: -err[i])
        worst = sorted(worst[:max(0, len(indices) - min_views)])
        if worst == rejected or rounds >= max_rounds:
            return _Robust(state, active, rejected, err, rounds, limit, how)
        rejected = worst


def _reasons(rob: _Robust, min_views: int, max_rounds: int) -> dict[int, str]:
    """Why each rejected view was dropped, and why a view above the limit was kept."""
    out: dict[int, str] = {}
    for i in rob.rejected:
        e = rob.errors.get(i, np.inf)
        if not np.isfinite(e):
            out[i] = "its board pose could not be solved under the fitted intrinsics"
        elif e > rob.limit:
            out[i] = f"{e:.3f} px > limit {rob.limit:.3f} px ({rob.how})"
        else:  # the loop stopped on max_rounds with the set still changing
            out[i] = (f"{e:.3f} px, under the last limit {rob.limit:.3f} px, but the outlier "
                      f"loop stopped at max_rounds ({max_rounds}) with it out")
    for i in rob.active:
        e = rob.errors.get(i, np.nan)
        if e > rob.limit:
            out[i] = (f"{e:.3f} px > limit {rob.limit:.3f} px ({rob.how}), kept: dropping it "
                      f"would leave fewer than min_views ({min_views})")
    return out


def _view_rows(n: int, used: Sequence[int], rejected: Sequence[int],
               skipped: Mapping[int, str], why: Mapping[int, str]) -> list[dict]:
    """One row per input view: index, status (``used``, ``dropped``, ``skipped``) and why
    (``None`` for a used view within the limit)."""
    rows = []
    for i in range(n):
        status = ("used" if i in used else "dropped" if i in rejected else "skipped")
        rows.append({"view": i, "status": status,
                     "why": skipped.get(i) if status == "skipped" else why.get(i)})
    return rows


# -- single camera ------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class CameraCalibration:
    """Result of :func:`calibrate_camera`.

    Attributes:
        model: ``"radtan"``, ``"standard"``, ``"rational"`` or ``"fisheye"`` (see :data:`MODELS`).
        image_size: ``(width, height)`` px.
        K: 3 x 3 intrinsic matrix (px).
        dist: distortion coefficients, OpenCV order, the model's full length.
        rms: RMS reprojection error over every corner of the accepted views (px).
        per_view_rms: RMS reprojection error of each input view (V,) px, under the final
            model: for rejected views too (their pose solved alone), NaN for skipped ones.
        T_cam_board: board pose in the camera frame per input view (4 x 4, m; ``None``
            for skipped views).
        used: indices of the views the final model was fitted to.
        rejected: indices of views rejected as outliers.
        skipped: index -> reason, for views not used at all (no board, too few corners).
        K_std: OpenCV's standard deviations of fx, fy, cx, cy (px); NaN for fisheye, whose
            OpenCV solver reports none.
        dist_std: standard deviations of ``dist`` (same order; NaN for fisheye).
        normal_spread_deg: largest angle between two accepted views' board normals.
        coverage: where the accepted views' corners fell in the image.
        rounds: fits run by the outlier loop (each one two OpenCV passes).
        n_corners: corners in the accepted views.
        reject: the outlier rule run (:class:`RejectRule`'s text).
        limit_px: the outlier limit of the last round (px; inf without rejection).
        why: view index -> why it was dropped (or kept above the limit).
    """

    model: str
    image_size: tuple[int, int]
    K: np.ndarray
    dist: np.ndarray
    rms: float
    per_view_rms: np.ndarray
    T_cam_board: tuple[np.ndarray | None, ...]
    used: tuple[int, ...]
    rejected: tuple[int, ...]
    skipped: Mapping[int, str]
    K_std: np.ndarray
    dist_std: np.ndarray
    normal_spread_deg: float
    coverage: Coverage
    rounds: int
    n_corners: int
    reject: str = "none"
    limit_px: float = np.inf
    why: Mapping[int, str] = field(default_factory=dict)

    def views(self) -> list[dict]:
        """The per-view table: one row per input view, ``view`` (index), ``rms_px``
        (``None`` where skipped), ``status`` (``used``, ``dropped``, ``skipped``), ``why``."""
        rows = _view_rows(len(self.per_view_rms), self.used, self.rejected, self.skipped,
                          self.why)
        for r, e in zip(rows, self.per_view_rms, strict=True):
            r["rms_px"] = None if np.isnan(e) else float(e)
        return rows

    def camera_model(self, name: str = "camera",
                     T_ref_cam: np.ndarray | None = None) -> CameraModel:
        """The result as a :class:`CameraModel` (standard and rational models only)."""
        if self.model == "fisheye":
            raise CalibrationError(
                "a fisheye calibration cannot become a CameraModel: its k1..k4 are OpenCV's "
                "fisheye coefficients, not pinhole distortion; calibrate with model='rational'")
        return CameraModel(name, self.image_size, self.K, self.dist,
                           np.eye(4) if T_ref_cam is None else T_ref_cam)

    def to_dict(self) -> dict:
        """A JSON-ready summary (lengths in metres, pixels as floats)."""
        return {"model": self.model, "image_size": list(self.image_size),
                "K": self.K.tolist(), "dist": self.dist.tolist(), "rms_px": self.rms,
                "per_view_rms_px": [None if np.isnan(e) else float(e)
                                    for e in self.per_view_rms],
                "used": list(self.used), "rejected": list(self.rejected),
                "skipped": {str(k): v for k, v in self.skipped.items()},
                "K_std": [None if np.isnan(s) else float(s) for s in self.K_std],
                "dist_std": [None if np.isnan(s) else float(s) for s in self.dist_std],
                "normal_spread_deg": self.normal_spread_deg, "rounds": self.rounds,
                "n_corners": self.n_corners, "coverage": self.coverage.to_dict(),
                "reject": self.reject,
                "limit_px": None if not np.isfinite(self.limit_px) else self.limit_px,
                "views": self.views()}


def calibrate_camera(views: Sequence[ViewLike], board_field: Board,
                     image_size: tuple[int, int], *, model: Model = "standard",
                     min_views: int = MIN_VIEWS, min_corners: int = MIN_CORNERS,
                     reject_outliers: bool = True, outlier_k: float = 4.0,
                     outlier_floor_px: float = 0.25, max_rounds: int = 5,
                     reject: RejectRule | str | None = None,
                     min_normal_spread_deg: float = 5.0,
                     K_guess: np.ndarray | None = None, flags: int = 0,
                     coverage_grid: tuple[int, int] = (8, 6),
                     criteria: tuple = _CRITERIA) -> CameraCalibration:
    """Calibrate one camera's intrinsics from views of the flat target ``board_field``.

    Args:
        views: one entry per image: the detected corners (``FieldCorners`` or
            ``(ids (N,), px (N x 2))``), or ``None`` where the board was not found.
        board_field: the target shown: a ChArUco field on a plane surface, or a
            :class:`~oralnav.control.calibration.targets.Target` (metres).
        image_size: ``(width, height)`` of the images, px.
        model: distortion model, see :data:`MODELS`.
        min_views: fewest usable views accepted (also the floor of outlier rejection).
        min_corners: views with fewer corners are skipped (and reported).
        reject_outliers, outlier_k, outlier_floor_px, max_rounds: the default outlier
            rule of the module docstring, its K and floor, and the most fits.
        reject: another outlier rule (a :class:`RejectRule` or its text, e.g.
            ``"median:3"``, ``"none"``); replaces the three above.
        min_normal_spread_deg: required spread of board orientations (module docstring).
        K_guess: initial 3 x 3 intrinsics (``CALIB_USE_INTRINSIC_GUESS``); optional.
        flags: extra OpenCV calibration flags (e.g. ``cv2.CALIB_FIX_ASPECT_RATIO``).
        coverage_grid: ``(cols, rows)`` of the coverage report.
        criteria: OpenCV termination criteria of the optimisation.

    Raises:
        CalibrationError: bad values or shapes, corners outside ``image_size``, too few
            usable views, degenerate orientations, or a solver failure.
    """
    if model not in MODELS:
        raise CalibrationError(f"model must be one of {sorted(MODELS)}, got {model!r}")
    size = _check_size(image_size)
    _check_board(board_field)
    rule = _rule(reject, reject_outliers, outlier_k, outlier_floor_px)
    if isinstance(min_views, bool) or not isinstance(min_views, int | np.integer):
        raise CalibrationError(f"min_views must be a whole number, got {min_views!r}")
    if min_views < 3:
        raise CalibrationError(f"min_views must be at least 3, got {min_views}")
    if K_guess is not None and np.asarray(K_guess).shape != (3, 3):
        raise CalibrationError(f"K_guess must be 3 x 3, got shape {np.asarray(K_guess).shape}")
    parsed, skipped = parse_views(views, board_field, size, max(4, min_corners), "")
    usable = [v for v in parsed if v is not None]
    if len(usable) < min_views:
        raise CalibrationError(_not_enough(len(usable), min_views, len(parsed), skipped,
                                           "views"))
    f0 = float(max(size)) if K_guess is None else float(np.asarray(K_guess)[0, 0])
    K0 = np.array([[f0, 0, 0.5 * (size[0] - 1)], [0, f0, 0.5 * (size[1] - 1)], [0, 0, 1]])
    pre = _normal_spread_deg(_homography_normals(usable, K0))
    if pre < 0.25 * min_normal_spread_deg:
        raise CalibrationError(_degenerate_msg(pre, min_normal_spread_deg, len(usable)))

    by_index = {v.index: v for v in usable}

    def fit_views(active: list[int]) -> tuple[_Fit, dict]:
        f = _fit_staged(model, [by_index[i] for i in active], size, K_guess, flags, criteria)
        return f, dict(zip(active, f.poses, strict=True))

    def view_errors(state: tuple[_Fit, dict], idx: list[int]) -> dict[int, float]:
        f, poses = state
        out = {}
        for i in idx:
            v = by_index[i]
            T = poses[i] if i in poses else _solve_pnp(model, f.K, f.dist, v)
            out[i] = np.inf if T is None else _rms(_project(model, f.K, f.dist, T, v.obj)
                                                    - v.px)
            if T is not None:
                poses.setdefault(i, T)
        return out

    rob = robust_fit(sorted(by_index), fit_views, view_errors, rule=rule,
                      min_views=min_views, max_rounds=max_rounds,
                      first_out=homography_screen(usable, rule))
    fit, poses = rob.state
    order = rob.active
    spread = _normal_spread_deg(np.array([poses[i][:3, 2] for i in order]))
    if spread < min_normal_spread_deg:
        raise CalibrationError(_degenerate_msg(spread, min_normal_spread_deg, len(order)))
    per_view = np.full(len(parsed), np.nan)
    T_all: list[np.ndarray | None] = [None] * len(parsed)
    for i, e in rob.errors.items():
        if np.isfinite(e):
            per_view[i], T_all[i] = e, poses[i]
    res = np.concatenate([_project(model, fit.K, fit.dist, poses[i], by_index[i].obj)
                          - by_index[i].px for i in order])
    return CameraCalibration(
        model=model, image_size=size, K=fit.K, dist=fit.dist, rms=_rms(res),
        per_view_rms=per_view, T_cam_board=tuple(T_all), used=tuple(order),
        rejected=tuple(rob.rejected), skipped=dict(skipped), K_std=fit.K_std,
        dist_std=fit.dist_std, normal_spread_deg=spread,
        coverage=_coverage([by_index[i].px for i in order], size, coverage_grid),
        rounds=rob.rounds, n_corners=len(res), reject=str(rule), limit_px=float(rob.limit),
        why=_reasons(rob, min_views, max_rounds))


# -- stereo -------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class StereoCalibration:
    """Result of :func:`calibrate_stereo`.

    Attributes:
        T_left_right: pose of the right camera in the left camera's frame (4 x 4, m).
        baseline: distance between the two camera centres (m).
        rms: RMS reprojection error over both cameras' corners of the accepted views (px).
        per_view_rms: per input view, the RMS error in the left and the right image
            (V x 2, px; NaN for skipped views; rejected views under the final model).
        used, rejected: indices of the views fitted and of those rejected as outliers.
        skipped: index -> reason for views not used (no board in one image, too few
            shared corners).
        epipolar_rms_px, epipolar_max_px: distance of the corners from their epipolar
            lines (symmetric, undistorted pixels) over the accepted views.
        left, right: the intrinsics used, as camera models (named ``left``/``right``;
            ``right.T_ref_cam`` is ``T_left_right``); refined when asked.
        T_left_board: board pose in the left camera per input view (``None`` if skipped).
        refined: whether the intrinsics were refined with the extrinsics.
        n_corners: shared corners in the accepted views.
        reject, limit_px, why: as in :class:`CameraCalibration`, on the per-view RMS
            over both images.
    """

    T_left_right: np.ndarray
    baseline: float
    rms: float
    per_view_rms: np.ndarray
    used: tuple[int, ...]
    rejected: tuple[int, ...]
    skipped: Mapping[int, str]
    epipolar_rms_px: float
    epipolar_max_px: float
    left: CameraModel
    right: CameraModel
    T_left_board: tuple[np.ndarray | None, ...]
    refined: bool
    rounds: int
    n_corners: int
    reject: str = "none"
    limit_px: float = np.inf
    why: Mapping[int, str] = field(default_factory=dict)

    def views(self) -> list[dict]:
        """The per-view table: one row per synchronized view, ``view``, ``rms_left_px``,
        ``rms_right_px`` (``None`` where skipped), ``status`` and ``why``."""
        rows = _view_rows(len(self.per_view_rms), self.used, self.rejected, self.skipped,
                          self.why)
        for r, (a, b) in zip(rows, self.per_view_rms, strict=True):
            r["rms_left_px"] = None if np.isnan(a) else float(a)
            r["rms_right_px"] = None if np.isnan(b) else float(b)
        return rows

    def rig(self, left: str = "left", right: str = "right") -> Rig:
        """A two-camera rig with the left camera as its reference."""
        cams = {left: CameraModel(left, self.left.size, self.left.K, self.left.dist),
                right: CameraModel(right, self.right.size, self.right.K, self.right.dist,
                                   self.T_left_right)}
        return Rig(left, cams)

    def to_dict(self) -> dict:
        return {"T_left_right": self.T_left_right.tolist(), "baseline_m": self.baseline,
                "rms_px": self.rms,
                "per_view_rms_px": [[None if np.isnan(e) else float(e) for e in row]
                                    for row in self.per_view_rms],
                "used": list(self.used), "rejected": list(self.rejected),
                "skipped": {str(k): v for k, v in self.skipped.items()},
                "epipolar_rms_px": self.epipolar_rms_px,
                "epipolar_max_px": self.epipolar_max_px, "refined": self.refined,
                "rounds": self.rounds, "n_corners": self.n_corners, "reject": self.reject,
                "limit_px": None if not np.isfinite(self.limit_px) else self.limit_px,
                "views": self.views(),
                "left": {"K": self.left.K.tolist(), "dist": self.left.dist.tolist()},
                "right": {"K": self.right.K.tolist(), "dist": self.right.dist.tolist()}}


def _as_camera(c: CameraCalibration | CameraModel, name: str) -> CameraModel:
    if isinstance(c, CameraCalibration):
        if c.model == "fisheye":
            raise CalibrationError(
                f"{name}: stereo calibration takes pinhole models (standard or rational); "
                "this camera was calibrated with the fisheye model")
        return c.camera_model(name)
    if isinstance(c, CameraModel):
        return CameraModel(name, c.size, c.K, c.dist)
    raise CalibrationError(f"{name} must be a CameraCalibration or a CameraModel, "
                           f"got {type(c).__name__}")


def _shared(a: _View, b: _View, board: Board) -> tuple[_View, _View]:
    common, ia, ib = np.intersect1d(a.ids, b.ids, return_indices=True)
    return (_View(a.index, common, a.obj[ia], a.px[ia]),
            _View(b.index, common, b.obj[ib], b.px[ib]))


def _epipolar(views: Sequence[tuple[_View, _View]], left: CameraModel, right: CameraModel,
              T_right_left: np.ndarray) -> np.ndarray:
    """Symmetric epipolar distances (px) of every shared corner, undistorted pixels."""
    R, t = T_right_left[:3, :3], T_right_left[:3, 3]
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    F = np.linalg.inv(right.K).T @ (tx @ R) @ np.linalg.inv(left.K)
    out = []
    for a, b in views:
        p1 = np.c_[left.undistort_normalized(a.px), np.ones(len(a.px))] @ left.K.T
        p2 = np.c_[right.undistort_normalized(b.px), np.ones(len(b.px))] @ right.K.T
        l2 = p1 @ F.T          # lines in the right image
        l1 = p2 @ F            # lines in the left image
        alg = np.abs(np.sum(p2 * l2, axis=1))
        d2 = alg / np.linalg.norm(l2[:, :2], axis=1)
        d1 = alg / np.linalg.norm(l1[:, :2], axis=1)
        out.append(np.sqrt(0.5 * (d1 ** 2 + d2 ** 2)))
    return np.concatenate(out) if out else np.zeros(0)


def _stereo_errors(K1: np.ndarray, d1: np.ndarray, K2: np.ndarray, d2: np.ndarray,
                   T_right_left: np.ndarray, T_left_board: np.ndarray,
                   pair: tuple[_View, _View]) -> tuple[float, float, float]:
    """RMS reprojection error (px) of one synchronized view: left, right, both."""
    a, b = pair
    ra = _project("standard", K1, d1, T_left_board, a.obj) - a.px
    rb = _project("standard", K2, d2, T_right_left @ T_left_board, b.obj) - b.px
    return _rms(ra), _rms(rb), _rms(np.r_[ra, rb])


def calibrate_stereo(views_left: Sequence[ViewLike], views_right: Sequence[ViewLike],
                     board_field: Board, left: CameraCalibration | CameraModel,
                     right: CameraCalibration | CameraModel, *,
                     refine_intrinsics: bool = False, min_views: int = MIN_STEREO_VIEWS,
                     min_corners: int = MIN_CORNERS, reject_outliers: bool = True,
                     outlier_k: float = 4.0, outlier_floor_px: float = 0.25,
                     max_rounds: int = 5, reject: RejectRule | str | None = None,
                     criteria: tuple = _CRITERIA) -> StereoCalibration:
    """Calibrate the pose of the right camera in the left one from synchronized views.

    Args:
        views_left, views_right: one entry per instant (the same index is the same
            instant), as in :func:`calibrate_camera`; only corners seen in both images of
            an instant are used.
        board_field: the flat target shown, as in :func:`calibrate_camera` (metres).
        left, right: the cameras' intrinsics, from :func:`calibrate_camera` (standard or
            rational model) or as :class:`CameraModel` (its ``T_ref_cam`` is ignored).
        refine_intrinsics: refine the intrinsics with the extrinsics (they start from
            ``left``/``right``); by default they stay fixed.
        min_views: fewest usable synchronized views accepted.
        min_corners: instants with fewer shared corners are skipped (and reported).
        reject_outliers, outlier_k, outlier_floor_px, max_rounds, reject: the outlier rule
            as in :func:`calibrate_camera`, on the per-view RMS over both images.
        criteria: OpenCV termination criteria.

    Raises:
        CalibrationError: mismatched view counts, bad values, too few shared views, a
            fisheye camera, or a solver failure.
    """
    L = _as_camera(left, "left")
    Rc = _as_camera(right, "right")
    _check_board(board_field)
    rule = _rule(reject, reject_outliers, outlier_k, outlier_floor_px)
    if isinstance(min_views, bool) or not isinstance(min_views, int | np.integer):
        raise CalibrationError(f"min_views must be a whole number, got {min_views!r}")
    if min_views < 2:
        raise CalibrationError(f"min_views must be at least 2, got {min_views}")
    for name, vs in (("views_left", views_left), ("views_right", views_right)):
        if isinstance(vs, FieldCorners | np.ndarray) or not isinstance(vs, Sequence):
            raise CalibrationError(f"{name} must be a sequence of views, got "
                                   f"{type(vs).__name__}")
    if len(views_left) != len(views_right):
        raise CalibrationError(
            f"views_left has {len(views_left)} views and views_right {len(views_right)}: "
            "synchronized views pair one to one (the same index is the same instant)")
    pl, _ = parse_views(views_left, board_field, L.size, None, "left ")
    pr, _ = parse_views(views_right, board_field, Rc.size, None, "right ")
    pairs: dict[int, tuple[_View, _View]] = {}
    skipped: dict[int, str] = {}
    for k, (a, b) in enumerate(zip(pl, pr, strict=True)):
        if a is None or b is None:
            skipped[k] = "board not found in " + (
                "either image" if a is None and b is None else ("left" if a is None
                                                                else "right"))
            continue
        a, b = _shared(a, b, board_field)
        why = _too_thin(a, board_field, max(4, min_corners))
        if why:
            skipped[k] = "shared " + why
            continue
        pairs[k] = (a, b)
    if len(pairs) < min_views:
        raise CalibrationError(_not_enough(len(pairs), min_views, len(pl), skipped,
                                           "synchronized views"))
    n_l, n_r = len(L.dist), len(Rc.dist)
    dl = np.zeros(max(5, n_l))
    dl[:n_l] = L.dist
    dr = np.zeros(max(5, n_r))
    dr[:n_r] = Rc.dist
    flags = _model_flags(max(len(dl), len(dr)))
    flags |= cv2.CALIB_USE_INTRINSIC_GUESS if refine_intrinsics else cv2.CALIB_FIX_INTRINSIC
    n = max(len(dl), len(dr))
    dl = np.r_[dl, np.zeros(n - len(dl))]
    dr = np.r_[dr, np.zeros(n - len(dr))]

    def fit_views(active: list[int]) -> tuple:
        va = [pairs[i][0] for i in active]
        vb = [pairs[i][1] for i in active]
        try:
            out = cv2.stereoCalibrateExtended(
                _obj(va), _img(va), _img(vb), L.K.copy(), dl.copy(), Rc.K.copy(), dr.copy(),
                L.size, np.eye(3), np.zeros((3, 1)), flags=flags, criteria=criteria)
        except cv2.error as exc:
            msg = str(exc).strip().splitlines()[-1] if str(exc).strip() else repr(exc)
            raise CalibrationError(f"OpenCV could not calibrate the stereo pair on "
                                   f"{len(active)} views: {msg}") from None
        _, K1, d1, K2, d2, R, T, _, _, rvecs, tvecs, _ = out
        T_rl = make_transform(np.asarray(R, float), np.asarray(T, float).reshape(3))
        if not np.all(np.isfinite(T_rl)):
            raise CalibrationError("the stereo calibration diverged (non-finite pose)")
        cams = (np.asarray(K1, float), np.asarray(d1, float).reshape(-1)[:n_l],
                np.asarray(K2, float), np.asarray(d2, float).reshape(-1)[:n_r])
        poses = {i: _pose(r, t) for i, r, t in zip(active, rvecs, tvecs, strict=True)}
        return cams, T_rl, poses

    def view_errors(state: tuple, idx: list[int]) -> dict[int, float]:
        (K1, d1, K2, d2), T_rl, poses = state
        out = {}
        for i in idx:
            T = poses[i] if i in poses else _solve_pnp("standard", K1, d1, pairs[i][0])
            out[i] = (np.inf if T is None
                      else _stereo_errors(K1, d1, K2, d2, T_rl, T, pairs[i])[2])
            if T is not None:
                poses.setdefault(i, T)
        return out

    rob = robust_fit(sorted(pairs), fit_views, view_errors, rule=rule,
                      min_views=min_views, max_rounds=max_rounds)
    (K1, d1, K2, d2), T_right_left, poses = rob.state
    order = rob.active
    T_left_right = invert(T_right_left)
    Lf = CameraModel("left", L.size, K1, d1)
    Rf = CameraModel("right", Rc.size, K2, d2, T_left_right)
    per_view = np.full((len(pl), 2), np.nan)
    T_all: list[np.ndarray | None] = [None] * len(pl)
    for i, e in rob.errors.items():
        if np.isfinite(e):
            T_all[i] = poses[i]
            per_view[i] = _stereo_errors(K1, d1, K2, d2, T_right_left, poses[i], pairs[i])[:2]
    res = []
    for i in order:
        a, b = pairs[i]
        res.append(_project("standard", K1, d1, poses[i], a.obj) - a.px)
        res.append(_project("standard", K2, d2, T_right_left @ poses[i], b.obj) - b.px)
    res = np.concatenate(res)
    epi = _epipolar([pairs[i] for i in order], Lf, Rf, T_right_left)
    return StereoCalibration(
        T_left_right=T_left_right, baseline=float(np.linalg.norm(T_left_right[:3, 3])),
        rms=_rms(res), per_view_rms=per_view, used=tuple(order),
        rejected=tuple(rob.rejected), skipped=skipped,
        epipolar_rms_px=float(np.sqrt(np.mean(epi ** 2))) if len(epi) else np.nan,
        epipolar_max_px=float(epi.max()) if len(epi) else np.nan, left=Lf, right=Rf,
        T_left_board=tuple(T_all), refined=bool(refine_intrinsics), rounds=rob.rounds,
        n_corners=sum(len(pairs[i][0].ids) for i in order), reject=str(rule),
        limit_px=float(rob.limit), why=_reasons(rob, min_views, max_rounds))
