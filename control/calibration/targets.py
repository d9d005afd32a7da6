"""Flat calibration targets besides the tracked ChArUco fields, and finding them in images.

A target is a flat pattern of points whose positions are known: chessboard inner corners,
circle centres, ArUco marker corners, or the chessboard corners of a ChArUco board printed
with a dictionary of one's own. Each point has an id (its row in :attr:`Target.corners`),
so a detection is the same ``(ids, px)`` view that a tracked field's detection gives and
:mod:`oralnav.control.calibration.cameras` fits either alike. Tracked ChArUco fields
(:class:`~oralnav.control.vision.markers.MarkerField`) keep the tracker's own detector
(:func:`detect_target` sends them there); these targets are for calibration only.

Frames and units: the target frame has z = 0 on the printed face, metres; pixels have the
centre of the top-left pixel at (0, 0), as OpenCV's detectors give them.

- ``chessboard``: ``inner_corners`` (nx, ny) of squares of side ``square``; corner ``j`` at
  ``(j % nx, j // nx) * square``, OpenCV's order (row by row).
- ``circles``: a symmetric grid of ``grid`` (cols, rows) circle centres ``spacing`` apart;
  centre ``j`` at ``(j % cols, j // cols) * spacing``.
- ``asymmetric_circles``: OpenCV's asymmetric grid, ``grid`` (cols, rows); centre ``j`` of
  row ``r = j // cols``, column ``c = j % cols`` at ``((2 c + r % 2) * spacing, r * spacing)``
  (OpenCV's calibration sample's layout, ``spacing`` its square size).
- ``aruco_grid``: OpenCV's ``GridBoard``; point ``4 k + i`` is corner ``i`` (OpenCV's
  clockwise order from top left) of the board's ``k``-th marker, at the board's own
  object points.
- ``charuco`` with a custom dictionary: OpenCV's ``CharucoBoard`` and its corner ids, the
  field frame of :mod:`oralnav.control.vision.markers`.

A chessboard and a symmetric circle grid have the same points after a half turn, and a
detector may number them from either end; stereo calibration needs both cameras to number
one view alike. A chessboard whose ``nx + ny`` is odd (OpenCV's 9 x 6) tells its ends
apart by colour: the square between its first four corners and the one between its last
four differ, and detections are numbered from the end whose square is dark. Other chessboards
and symmetric circle grids are numbered so that their first row runs rightward in the
image, which two cameras side by side agree on unless the rows stand near vertical. A
square pattern (nx = ny) also looks the same after a quarter turn; for stereo, use one
with nx != ny and, for a chessboard, nx + ny odd.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import ClassVar

import cv2
import numpy as np

from oralnav.control.errors import MarkerFieldError
from oralnav.control.vision.detection import FieldCorners, check_image, detect_fields
from oralnav.control.vision.markers import MarkerField, PlaneSurface, aruco_dictionary

__all__ = ["ArucoGrid", "CharucoTarget", "Chessboard", "CircleGrid", "Target", "detect_target"]

#: cornerSubPix's stop rule for chessboard corners.
_SUBPIX = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.001)


class Target:
    """What every flat target shares: a name, a family, its points and a detector.

    Subclasses give ``name``, :attr:`pitch` and ``_flat()`` (N x 2, m) and ``detect``.
    """

    name: str
    family: ClassVar[str]
    #: Calibration needs a flat target; :mod:`~oralnav.control.calibration.cameras`
    #: checks tracked fields' surfaces, and every target here is flat.
    surface: ClassVar[PlaneSurface] = PlaneSurface()

    def _flat(self) -> np.ndarray:
        raise NotImplementedError

    @property
    def pitch(self) -> float:
        """The pattern's smallest point spacing (m): what "spread out" is measured in."""
        raise NotImplementedError

    @cached_property
    def corners(self) -> np.ndarray:
        """Position (N x 3, target frame, m) of each point, row = id."""
        xy = np.asarray(self._flat(), dtype=float).reshape(-1, 2)
        return np.c_[xy, np.zeros(len(xy))]

    @cached_property
    def corner_ids(self) -> np.ndarray:
        return np.arange(len(self.corners))

    @cached_property
    def corner_index(self) -> dict[int, int]:
        """Point id -> row in :attr:`corners` (the identity: ids are rows)."""
        return {int(i): int(i) for i in self.corner_ids}

    @property
    def corner_count(self) -> int:
        return len(self.corners)

    def detect(self, image: np.ndarray) -> FieldCorners | None:
        """The target's points found in ``image`` (mono8), or ``None``."""
        raise NotImplementedError


def _positive(where: str, **lengths: float) -> None:
    for key, v in lengths.items():
        if not (np.isfinite(v) and v > 0):
            raise MarkerFieldError(f"{where}: {key} must be a positive length (m), got {v}")


def _grid(where: str, key: str, value: tuple[int, int], least: int) -> tuple[int, int]:
    nx, ny = (int(v) for v in value)
    if (nx, ny) != tuple(value) or nx < least or ny < least:
        raise MarkerFieldError(f"{where}: {key} must be two whole numbers >= {least}, "
                               f"got {value}")
    return nx, ny


def _rightward(px: np.ndarray, cols: int) -> np.ndarray:
    """``px`` (a grid's points, row by row, ``cols`` a row) reversed when its first row
    runs leftward in the image: reversing a row-major grid's order is its half turn."""
    return px[::-1].copy() if px[cols - 1, 0] < px[0, 0] else px


def _dark_first(img: np.ndarray, px: np.ndarray, size: tuple[int, int],
                step: float) -> np.ndarray:
    """Chessboard corners ``px`` (row by row, ``size`` = (nx, ny), nx + ny odd) reversed
    when the square between the first four corners is the lighter of the two end squares
    (module docstring)."""
    nx, ny = size
    g = px.reshape(ny, nx, 2)
    # The squares between the corner grid's first and last four corners: whole on every
    # board, where the outer squares may be trimmed (OpenCV's own sample board is).
    ends = [g[:2, :2].reshape(-1, 2).mean(axis=0), g[-2:, -2:].reshape(-1, 2).mean(axis=0)]
    k = max(3, int(0.3 * step)) | 1
    level = [float(cv2.getRectSubPix(img, (k, k), (float(x), float(y))).mean())
             for x, y in ends]
    return px[::-1].copy() if level[0] > level[1] else px


@dataclass(frozen=True, eq=False)
class Chessboard(Target):
    """A plain chessboard: ``inner_corners`` (nx, ny) inner corners, ``square`` (m) apart."""

    name: str
    inner_corners: tuple[int, int]
    square: float
    family: ClassVar[str] = "chessboard"

    def __post_init__(self) -> None:
        where = f"target {self.name!r}"
        # OpenCV's chessboard detectors need more than two corners each way
        object.__setattr__(self, "inner_corners",
                           _grid(where, "inner_corners", self.inner_corners, 3))
        _positive(where, square=self.square)

    @property
    def pitch(self) -> float:
        return float(self.square)

    def _flat(self) -> np.ndarray:
        nx, ny = self.inner_corners
        j = np.arange(nx * ny)
        return np.stack([j % nx, j // nx], axis=1) * float(self.square)

    def detect(self, image: np.ndarray) -> FieldCorners | None:
        """OpenCV's classic detector (``findChessboardCorners``), its sector-based one
        (``findChessboardCornersSB``) for images the first misses, then ``cornerSubPix``
        over a window scaled to the corner spacing."""
        img = check_image(image)
        size = self.inner_corners
        ok, px = cv2.findChessboardCorners(
            img, size, flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
        if not ok:
            ok, px = cv2.findChessboardCornersSB(
                img, size, flags=cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE)
            if not ok:
                return None
        grid = np.asarray(px, dtype=np.float32).reshape(size[1], size[0], 2)
        step = min(float(np.linalg.norm(np.diff(grid, axis=a), axis=2).min()) for a in (0, 1))
        # A half-window of 0.3 corner spacings: the fixed 11 px of OpenCV's stereo sample
        # reaches the next corner on its own left02/right02 (22 and 19 px apart) and puts
        # those views at 1.2 px RMS; 0.3 keeps every view of that sample under 0.25 px and,
        # on rendered boards, halves the error of the sector-based detector's own corners.
        half = int(np.clip(0.3 * step, 2, 11))
        px = cv2.cornerSubPix(img, grid.reshape(-1, 1, 2), (half, half), (-1, -1), _SUBPIX)
        px = np.asarray(px, dtype=float).reshape(-1, 2)
        px = (_dark_first(img, px, size, step) if sum(size) % 2
              else _rightward(px, size[0]))
        return FieldCorners(self.corner_ids.copy(), px)


@dataclass(frozen=True, eq=False)
class CircleGrid(Target):
    """A grid of dark circles on a light ground, ``grid`` (cols, rows) centres, ``spacing``
    (m) as in the module docstring; ``asymmetric`` for OpenCV's staggered grid."""

    name: str
    grid: tuple[int, int]
    spacing: float
    asymmetric: bool = False

    def __post_init__(self) -> None:
        where = f"target {self.name!r}"
        object.__setattr__(self, "grid", _grid(where, "grid", self.grid, 2))
        _positive(where, spacing=self.spacing)
        if self.grid[0] * self.grid[1] < 4:
            raise MarkerFieldError(f"{where}: a grid of {self.grid} has too few circles "
                                   "(at least 4)")

    @property
    def family(self) -> str:  # type: ignore[override]
        return "asymmetric_circles" if self.asymmetric else "circles"

    @property
    def pitch(self) -> float:
        return float(self.spacing)

    def _flat(self) -> np.ndarray:
        cols, rows = self.grid
        j = np.arange(cols * rows)
        c, r = j % cols, j // cols
        x = 2 * c + r % 2 if self.asymmetric else c
        return np.stack([x, r], axis=1) * float(self.spacing)

    def detect(self, image: np.ndarray) -> FieldCorners | None:
        img = check_image(image)
        params = cv2.SimpleBlobDetector_Params()
        # OpenCV's default caps a blob at 5000 px^2 (a circle of 80 px): too small for a
        # grid filling a high-resolution image
        params.maxArea = max(params.maxArea, 0.25 * img.size / (self.grid[0] * self.grid[1]))
        flags = (cv2.CALIB_CB_ASYMMETRIC_GRID if self.asymmetric
                 else cv2.CALIB_CB_SYMMETRIC_GRID)
        ok, px = cv2.findCirclesGrid(img, self.grid, flags=flags,
                                     blobDetector=cv2.SimpleBlobDetector_create(params))
        if not ok or px is None:
            return None
        px = np.asarray(px, dtype=float).reshape(-1, 2)
        if not self.asymmetric:
            px = _rightward(px, self.grid[0])
        return FieldCorners(self.corner_ids.copy(), px)


def _dictionary(where: str, name: str, custom: cv2.aruco.Dictionary | None,
                first_id: int, count: int) -> cv2.aruco.Dictionary:
    """The target's dictionary (``custom``, or OpenCV's predefined ``name``), checked to
    hold ids ``first_id .. first_id + count - 1``."""
    dic = custom if custom is not None else aruco_dictionary(name)
    size = int(dic.bytesList.shape[0])
    if int(first_id) != first_id or first_id < 0 or first_id + count > size:
        raise MarkerFieldError(f"{where}: ids {first_id}..{first_id + count - 1} overflow "
                               f"{name}, which has ids 0..{size - 1}")
    return dic


def _subpix_detector(dic: cv2.aruco.Dictionary) -> cv2.aruco.ArucoDetector:
    params = cv2.aruco.DetectorParameters()
    # marker corners straight from the contour fit are a fraction of a pixel off; the
    # calibration is only as good as its corners
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    return cv2.aruco.ArucoDetector(dic, params)


@dataclass(frozen=True, eq=False)
class ArucoGrid(Target):
    """OpenCV's ArUco ``GridBoard``: ``markers`` (nx, ny) markers of side ``marker`` (m),
    ``separation`` (m) apart, ids ``first_id ..`` of ``dictionary`` (an OpenCV name, or
    the label of ``custom``, a dictionary read from a file)."""

    name: str
    markers: tuple[int, int]
    marker: float
    separation: float
    dictionary: str
    first_id: int = 0
    custom: cv2.aruco.Dictionary | None = None
    family: ClassVar[str] = "aruco_grid"

    def __post_init__(self) -> None:
        where = f"target {self.name!r}"
        nx, ny = _grid(where, "markers", self.markers, 1)
        object.__setattr__(self, "markers", (nx, ny))
        if nx * ny < 2:
            raise MarkerFieldError(f"{where}: a grid board needs at least 2 markers")
        _positive(where, marker=self.marker, separation=self.separation)
        _dictionary(where, self.dictionary, self.custom, self.first_id, nx * ny)

    @property
    def pitch(self) -> float:
        return float(self.marker)

    @cached_property
    def board(self) -> cv2.aruco.GridBoard:
        """OpenCV's board (metres), for detection and drawing."""
        n = self.markers[0] * self.markers[1]
        dic = _dictionary(f"target {self.name!r}", self.dictionary, self.custom,
                          self.first_id, n)
        return cv2.aruco.GridBoard(self.markers, float(self.marker), float(self.separation),
                                   dic, np.arange(self.first_id, self.first_id + n))

    def _flat(self) -> np.ndarray:
        return np.asarray(self.board.getObjPoints(), dtype=float).reshape(-1, 3)[:, :2]

    def detect(self, image: np.ndarray) -> FieldCorners | None:
        """``ArucoDetector`` (sub-pixel corners), then the board's ``matchImagePoints``."""
        img = check_image(image)
        quads, ids, _ = _subpix_detector(self.board.getDictionary()).detectMarkers(img)
        if ids is None or len(ids) == 0:
            return None
        ids = np.asarray(ids).reshape(-1)
        # a marker seen twice cannot say which is right; neither is kept
        seen, counts = np.unique(ids, return_counts=True)
        keep = np.isin(ids, seen[counts == 1])
        quads = [q for q, k in zip(quads, keep, strict=True) if k]
        ids = ids[keep]
        if not len(ids):
            return None
        obj, px = self.board.matchImagePoints(quads, ids.reshape(-1, 1))
        if obj is None or not len(obj):
            return None
        # matchImagePoints gives object points; their rows in the board model are the ids
        rows = {tuple(p): k for k, p in enumerate(self.corners.astype(np.float32))}
        pid = np.array([rows[tuple(p)] for p in np.asarray(obj, np.float32).reshape(-1, 3)])
        return FieldCorners(pid, np.asarray(px, dtype=float).reshape(-1, 2),
                            np.sort(ids).astype(int))


@dataclass(frozen=True, eq=False)
class CharucoTarget(Target):
    """A flat ChArUco board printed with a dictionary of one's own (``custom``, read from
    the file ``dictionary`` names): OpenCV's ``CharucoBoard`` and ``CharucoDetector``.
    Corner ids and frame are those of :class:`~oralnav.control.vision.markers.MarkerField`.
    """

    name: str
    squares: tuple[int, int]
    square: float
    marker: float
    dictionary: str
    custom: cv2.aruco.Dictionary
    first_id: int = 0
    family: ClassVar[str] = "charuco"

    def __post_init__(self) -> None:
        where = f"target {self.name!r}"
        nx, ny = _grid(where, "squares", self.squares, 2)
        object.__setattr__(self, "squares", (nx, ny))
        _positive(where, square=self.square, marker=self.marker)
        if self.marker >= self.square:
            raise MarkerFieldError(f"{where}: marker ({self.marker}) must be smaller than "
                                   f"square ({self.square})")
        _dictionary(where, self.dictionary, self.custom, self.first_id, nx * ny // 2)

    @property
    def pitch(self) -> float:
        return float(self.square)

    @cached_property
    def board(self) -> cv2.aruco.CharucoBoard:
        n = self.squares[0] * self.squares[1] // 2
        return cv2.aruco.CharucoBoard(self.squares, float(self.square), float(self.marker),
                                      self.custom, np.arange(self.first_id, self.first_id + n))

    def _flat(self) -> np.ndarray:
        return np.asarray(self.board.getChessboardCorners(), dtype=float).reshape(-1, 3)[:, :2]

    def detect(self, image: np.ndarray) -> FieldCorners | None:
        img = check_image(image)
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        det = cv2.aruco.CharucoDetector(self.board, cv2.aruco.CharucoParameters(), params)
        px, ids, _, marker_ids = det.detectBoard(img)
        if ids is None or not len(ids):
            return None
        markers = (np.zeros(0, int) if marker_ids is None
                   else np.sort(np.asarray(marker_ids).reshape(-1)).astype(int))
        return FieldCorners(np.asarray(ids).reshape(-1).astype(int),
                            np.asarray(px, dtype=float).reshape(-1, 2), markers)


def detect_target(image: np.ndarray, target: MarkerField | Target) -> FieldCorners | None:
    """``target``'s points in ``image`` (mono8): a tracked ChArUco field through the
    tracker's own detector, any other target through its OpenCV detector."""
    if isinstance(target, MarkerField):
        return detect_fields(image, [target]).get(target.name)
    if isinstance(target, Target):
        return target.detect(image)
    raise MarkerFieldError(f"not a calibration target: {type(target).__name__}")
