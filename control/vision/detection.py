"""Finding marker-field corners in an image: ArUco quads, their ids, chessboard corners.

The pipeline, written for speed on a small CPU (see docs/tracking.md):

1. **Quads** are found on a (possibly) reduced copy of the image: adaptive threshold,
   contours, 4-vertex convex polygons (:func:`find_quads`).
2. **Decoding** samples each quad's bit grid from the full-resolution image, all quads in
   one ``cv2.remap`` call, and looks the code up in a table of every id and rotation of the
   dictionary (:class:`MarkerDecoder`). Only exact codes are accepted: dense dictionaries
   such as ``DICT_4X4_1000`` leave no room for error correction.
3. **Chessboard corners** around each decoded marker are predicted through the marker's
   homography and refined at full resolution with ``cv2.cornerSubPix``
   (:func:`refine_corners`), with a window sized to the local square so that it stays
   inside the four squares that meet at the corner. A refinement that gave up, and a point
   that is not a chessboard corner of the expected colouring or whose neighbourhood is not
   point-symmetric (:func:`x_junction_ok`), are dropped rather than reported: at grazing
   angles the marker quads are a few pixels wide and a poor prediction is common there, and
   an occluder's edge across the refinement window pulls the corner off.

Pixel convention: the centre of the top-left pixel is (0, 0), as in :mod:`.camera`.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from functools import lru_cache

import cv2
import numpy as np

from oralnav.control.errors import ControlError
from oralnav.control.vision.markers import MarkerField, aruco_dictionary


class DetectionError(ControlError, ValueError):
    """An image or a detection request is unusable (wrong dtype, shape, empty ROI)."""


#: Subpixel refinement stops after this many iterations or a move below ``_SUBPIX_EPS`` px.
_SUBPIX_ITERS = 30
_SUBPIX_EPS = 0.005


@dataclass(frozen=True)
class Quad:
    """A decoded ArUco marker in one image.

    Attributes:
        marker_id: dictionary id.
        corners: 4 x 2 pixels (full resolution), in the marker's own corner order
            (top-left, top-right, bottom-right, bottom-left of the printed marker).
    """

    marker_id: int
    corners: np.ndarray


@dataclass
class FieldCorners:
    """Chessboard corners of one field found in one image.

    Attributes:
        ids: board corner ids (N,), OpenCV's numbering.
        px: refined pixel positions (N x 2).
        markers: ids of the markers that located them (empty when tracked from a pose).
    """

    ids: np.ndarray
    px: np.ndarray
    markers: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))

    def __len__(self) -> int:
        return len(self.ids)


def check_image(image: np.ndarray, size: tuple[int, int] | None = None,
                what: str = "image") -> np.ndarray:
    """Return ``image`` as a C-contiguous mono8 array, or raise :class:`DetectionError`.

    ``size`` is the expected ``(width, height)``.
    """
    if not isinstance(image, np.ndarray):
        raise DetectionError(f"{what}: expected a numpy array, got {type(image).__name__}")
    if image.dtype != np.uint8:
        raise DetectionError(f"{what}: expected dtype uint8 (mono8), got {image.dtype}")
    if image.ndim != 2:
        raise DetectionError(f"{what}: expected a 2-D mono image, got shape {image.shape}")
    if size is not None and (image.shape[1], image.shape[0]) != tuple(size):
        raise DetectionError(
            f"{what}: image is {image.shape[1]}x{image.shape[0]}, the camera is "
            f"{size[0]}x{size[1]}")
    return np.ascontiguousarray(image)


# -- quads ------------------------------------------------------------------------------
@dataclass(frozen=True)
class QuadParams:
    """Candidate-quad search settings (pixels of the full-resolution image).

    Attributes:
        scale: the image is reduced by this factor (1 or 0.5) before thresholding.
        block: adaptive-threshold block size at the reduced scale (odd).
        offset: adaptive-threshold constant (grey levels).
        min_side: smallest quad side kept, full-resolution pixels.
        max_side: largest quad side kept, full-resolution pixels.
        approx: polygon approximation tolerance as a fraction of the contour length.
    """

    scale: float = 1.0
    block: int = 7
    offset: float = 7.0
    min_side: float = 8.0
    max_side: float = 400.0
    approx: float = 0.05


def find_quads(image: np.ndarray, params: QuadParams = QuadParams(),
               roi: tuple[int, int, int, int] | None = None) -> np.ndarray:
    """Dark convex quadrilaterals in ``image`` (Q x 4 x 2 full-resolution pixels).

    ``roi`` = (x0, y0, x1, y1), pixel bounds (exclusive end), restricts the search.
    Corners come clockwise on screen (x right, y down).
    """
    x0, y0 = 0, 0
    sub = image
    if roi is not None:
        x0, y0, x1, y1 = roi
        sub = image[y0:y1, x0:x1]
    if sub.shape[0] < 8 or sub.shape[1] < 8:
        return np.zeros((0, 4, 2))
    s = params.scale
    small = sub if s == 1.0 else cv2.resize(sub, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
    binary = cv2.adaptiveThreshold(small, 255, cv2.ADAPTIVE_THRESH_MEAN_C,
                                   cv2.THRESH_BINARY_INV, params.block, params.offset)
    contours, _ = cv2.findContours(binary, cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    min_len = 4 * params.min_side * s
    max_len = 4 * params.max_side * s
    quads = []
    for c in contours:
        n = len(c)
        if n < min_len or n > max_len:
            continue
        poly = cv2.approxPolyDP(c, params.approx * n, True)
        if len(poly) == 4 and cv2.isContourConvex(poly):
            quads.append(poly.reshape(4, 2))
    if not quads:
        return np.zeros((0, 4, 2))
    q = np.asarray(quads, dtype=float)
    side = np.linalg.norm(q - q[:, [3, 0, 1, 2]], axis=2).min(axis=1)
    q = q[side >= params.min_side * s]
    # Clockwise on screen: positive signed area with y down.
    x, y = q[..., 0], q[..., 1]
    area = np.sum(x * np.roll(y, -1, axis=1) - np.roll(x, -1, axis=1) * y, axis=1)
    q[area < 0] = q[area < 0][:, ::-1]
    # Contour pixels lie on the dark side of the edge: half a reduced pixel outward.
    centre = q.mean(axis=1, keepdims=True)
    d = q - centre
    q = q + 0.5 * d / np.maximum(np.linalg.norm(d, axis=2, keepdims=True), 1e-9)
    q = (q + 0.5) / s - 0.5  # reduced-pixel centres to full-resolution pixel centres
    q[..., 0] += x0
    q[..., 1] += y0
    # Drop near-duplicates (the inner and outer contour of one border): keep the outer.
    return _unique_quads(q)


def _unique_quads(q: np.ndarray) -> np.ndarray:
    if len(q) < 2:
        return q
    centres = q.mean(axis=1)
    sides = np.linalg.norm(q - np.roll(q, 1, axis=1), axis=2).mean(axis=1)
    dist = np.linalg.norm(centres[:, None] - centres[None, :], axis=2)
    # i duplicates a larger quad j (the inner and outer contour of one marker border) when
    # their centres are closer than a quarter of j's side and j is at most 1.6 times bigger;
    # a marker inside a much larger dark frame is not a duplicate.
    larger = (sides[None, :] > sides[:, None]) | ((sides[None, :] == sides[:, None])
                                                   & (np.arange(len(q))[None, :]
                                                      < np.arange(len(q))[:, None]))
    similar = sides[None, :] <= 1.6 * sides[:, None]
    dup = np.any(larger & similar & (dist < 0.25 * sides[None, :]), axis=1)
    return q[~dup]


# -- decoding ---------------------------------------------------------------------------
class MarkerDecoder:
    """Reads ArUco ids from quads by sampling the bit grid at full resolution.

    Built once per dictionary (the code table covers every id and its four rotations).
    """

    def __init__(self, dictionary: str, border_bits: int = 1):
        self.dictionary = dictionary
        dic = aruco_dictionary(dictionary)
        self.bits = int(dic.markerSize)
        self.border = int(border_bits)
        self.cells = self.bits + 2 * self.border
        self.table: dict[int, tuple[int, int]] = {}
        n = dic.bytesList.shape[0]
        weights = 1 << np.arange(self.bits * self.bits, dtype=np.int64)[::-1]
        codes = np.empty((n, 4), dtype=np.int64)
        for i in range(n):
            img = cv2.aruco.generateImageMarker(dic, i, self.cells, borderBits=self.border)
            inner = (img[self.border:-self.border, self.border:-self.border] > 127)
            for k in range(4):
                codes[i, k] = int(np.sum(np.rot90(inner, k).ravel() * weights))
        for i in range(n):
            for k in range(4):
                # A code that two ids (or two rotations) share is ambiguous: never accept it.
                c = int(codes[i, k])
                self.table[c] = (-1, -1) if c in self.table else (i, k)
        self._weights = weights
        self._codes = codes
        ring = np.ones((self.cells, self.cells), dtype=bool)
        ring[self.border:-self.border, self.border:-self.border] = False
        self._ring = ring.ravel()
        # Expected white cells of every id, border included (n x cells^2).
        self._expect = np.zeros((n, self.cells * self.cells), dtype=bool)
        self._expect[:, ~self._ring] = (codes[:, :1] & weights[None, :]) > 0
        # Sample 3 x 3 points inside each cell, away from its edges.
        g = (np.arange(self.cells)[:, None] + np.array([0.3, 0.5, 0.7])[None, :]).ravel()
        gx, gy = np.meshgrid(g / self.cells, g / self.cells)
        self._unit = np.stack([gx.ravel(), gy.ravel()], axis=1)  # (9 c^2) x 2

    def code_of(self, marker_id: int) -> int:
        """Integer code of ``marker_id`` in its canonical orientation."""
        return int(self._codes[marker_id, 0])

    def cell_means(self, image: np.ndarray, quads: np.ndarray) -> np.ndarray:
        """Mean grey level of each bit cell (Q x cells^2), quads as Q x 4 x 2 pixels."""
        Q = len(quads)
        H = square_to_quad(np.asarray(quads, dtype=float))  # Q x 3 x 3
        u = np.concatenate([self._unit, np.ones((len(self._unit), 1))], axis=1)
        p = H @ u.T  # Q x 3 x K
        pts = (p[:, :2] / p[:, 2:3]).transpose(0, 2, 1).astype(np.float32)
        sampled = cv2.remap(image, pts[..., 0], pts[..., 1], cv2.INTER_LINEAR,
                            borderMode=cv2.BORDER_CONSTANT, borderValue=0).astype(float)
        c = self.cells
        return sampled.reshape(Q, c, 3, c, 3).transpose(0, 1, 3, 2, 4).reshape(Q, c * c, 9).mean(-1)

    def decode(self, image: np.ndarray, quads: np.ndarray,
               allowed: Iterable[range] | None = None) -> list[Quad]:
        """Decode quads (Q x 4 x 2 px, clockwise) into markers; unreadable ones are dropped.

        ``allowed`` restricts the ids accepted (ranges of ids, e.g. the fields' id blocks).
        """
        if len(quads) == 0:
            return []
        cells = self.cell_means(image, quads)
        border = cells[:, self._ring]
        inner = cells[:, ~self._ring]
        black = np.median(border, axis=1)
        white = inner.max(axis=1)
        thr = 0.5 * (black + white)
        bits = inner > thr[:, None]
        codes = bits.astype(np.int64) @ self._weights
        good = (white - black >= 12.0) & (np.count_nonzero(border > thr[:, None], axis=1) <= 2)
        out: list[Quad] = []
        for i in np.nonzero(good)[0]:
            marker_id, rot = self.table.get(int(codes[i]), (-1, -1))
            if marker_id < 0:
                continue
            if allowed is not None and not any(marker_id in r for r in allowed):
                continue
            # np.rot90(canonical, k) was seen: the canonical top-left is at index (4 - k) % 4.
            start = (4 - rot) % 4
            out.append(Quad(int(marker_id), np.roll(quads[i], -start, axis=0)))
        return out

    def match_scores(self, image: np.ndarray, quads: np.ndarray,
                     marker_ids: Sequence[int]) -> np.ndarray:
        """Fraction of bit cells (border included) that read as expected, per quad.

        Quads here come from a predicted pose, already in the marker's corner order; this is
        the identity check of predictive tracking. A quad without contrast scores 0.
        """
        if len(quads) == 0:
            return np.zeros(0)
        m = self.cell_means(image, quads)
        expect = self._expect[np.asarray(marker_ids, dtype=int)]
        n_hi = expect.sum(axis=1)
        n_lo = expect.shape[1] - n_hi
        hi = np.sum(m * expect, axis=1) / np.maximum(n_hi, 1)
        lo = np.sum(m * ~expect, axis=1) / np.maximum(n_lo, 1)
        scores = np.mean((m > 0.5 * (lo + hi)[:, None]) == expect, axis=1)
        scores[(hi - lo < 12.0) | (n_hi == 0)] = 0.0
        return scores


def square_to_quad(quads: np.ndarray) -> np.ndarray:
    """Homographies (Q x 3 x 3) taking the unit square's corners (0,0), (1,0), (1,1), (0,1)
    to each quad's four corners (Q x 4 x 2), in closed form (vectorised, no solver)."""
    x0, y0 = quads[:, 0, 0], quads[:, 0, 1]
    x1, y1 = quads[:, 1, 0], quads[:, 1, 1]
    x2, y2 = quads[:, 2, 0], quads[:, 2, 1]
    x3, y3 = quads[:, 3, 0], quads[:, 3, 1]
    dx1, dx2, dx3 = x1 - x2, x3 - x2, x0 - x1 + x2 - x3
    dy1, dy2, dy3 = y1 - y2, y3 - y2, y0 - y1 + y2 - y3
    den = dx1 * dy2 - dx2 * dy1
    den = np.where(np.abs(den) > 1e-12, den, 1e-12)
    g = (dx3 * dy2 - dx2 * dy3) / den
    h = (dx1 * dy3 - dx3 * dy1) / den
    H = np.empty((len(quads), 3, 3))
    H[:, 0] = np.stack([x1 - x0 + g * x1, x3 - x0 + h * x3, x0], axis=1)
    H[:, 1] = np.stack([y1 - y0 + g * y1, y3 - y0 + h * y3, y0], axis=1)
    H[:, 2] = np.stack([g, h, np.ones_like(g)], axis=1)
    return H


@lru_cache(maxsize=16)
def decoder_for(dictionary: str) -> MarkerDecoder:
    """A shared :class:`MarkerDecoder` per dictionary name (its table takes ~10 ms to build)."""
    return MarkerDecoder(dictionary)


# -- chessboard corners -----------------------------------------------------------------
@dataclass(frozen=True)
class BoardLayout:
    """Where each marker of a field sits on the flat sheet, and which corners surround it.

    Attributes:
        marker_flat: marker index -> its 4 corners on the flat sheet (M x 4 x 2, m).
        marker_corner_ids: marker index -> the board corner ids at its square's four
            corners (M x 4), -1 where the square corner is on the sheet's outer edge.
    """

    marker_flat: np.ndarray
    marker_corner_ids: np.ndarray
    corner_flat: np.ndarray  # all board corners (corner_count x 2, m)

    @classmethod
    def of(cls, fld: MarkerField) -> BoardLayout:
        s = fld.square
        nx, ny = fld.squares
        flat = np.asarray(fld.board.getObjPoints(), dtype=float)[:, :, :2]
        ids = np.full((len(flat), 4), -1, dtype=int)
        for m, quad in enumerate(flat):
            col, row = (int(v) for v in np.floor(quad.mean(axis=0) / s))
            for k, (gx, gy) in enumerate(((col, row), (col + 1, row), (col + 1, row + 1),
                                          (col, row + 1))):
                if 1 <= gx <= nx - 1 and 1 <= gy <= ny - 1:
                    ids[m, k] = (gy - 1) * (nx - 1) + (gx - 1)
        j = np.arange(fld.corner_count)
        corner_flat = np.stack([(j % (nx - 1) + 1) * s, (j // (nx - 1) + 1) * s], axis=1)
        return cls(flat, ids, corner_flat)


@dataclass
class CornerPrediction:
    """Chessboard corners predicted from decoded markers (see :func:`predict_corners`).

    Attributes:
        ids: corner ids (N,).
        px: predicted pixels (N x 2).
        square_px: local square side, pixels (N,): the root of the square's image area.
        markers: ids of the markers used.
        axes: image vectors of one square along the sheet's x and y at each corner
            (N x 2 x 2, pixels; ``axes[i, 0]`` is x).
        light_diagonal: +1 where the squares toward +x+y and -x-y of the corner are the
            light ones (those that hold markers), -1 where the other two are (N,).
    """

    ids: np.ndarray
    px: np.ndarray
    square_px: np.ndarray
    markers: np.ndarray
    axes: np.ndarray
    light_diagonal: np.ndarray

    @classmethod
    def empty(cls) -> CornerPrediction:
        """No corner."""
        return cls(np.zeros(0, dtype=int), np.zeros((0, 2)), np.zeros(0),
                   np.zeros(0, dtype=int), np.zeros((0, 2, 2)), np.zeros(0))


def predict_corners(fld: MarkerField, layout: BoardLayout, quads: Sequence[Quad]
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Chessboard corners around decoded markers of ``fld``, through each marker's homography.

    Returns ``(ids, px, square_px, markers)``: corner ids (N,), predicted pixels (N x 2), the
    local square side in pixels (N,), and the ids of the markers used. A corner predicted by
    two markers takes the mean; corners whose predictions disagree by more than a quarter
    square are dropped (one of the markers is misread or misplaced). :func:`predict_board`
    gives the same with each corner's square axes and colouring.
    """
    pr = predict_board(fld, layout, quads)
    return pr.ids, pr.px, pr.square_px, pr.markers


def predict_board(fld: MarkerField, layout: BoardLayout, quads: Sequence[Quad]
                  ) -> CornerPrediction:
    """:func:`predict_corners`, with the local square axes and colouring of each corner."""
    m = np.array([q.marker_id - fld.first_id for q in quads], dtype=int)
    keep = (m >= 0) & (m < len(layout.marker_flat))
    if not np.any(keep):
        return CornerPrediction.empty()
    m = m[keep]
    img = np.stack([q.corners for q, k in zip(quads, keep, strict=True) if k])
    # Sheet -> image homography of each marker: sheet to the marker's unit square, then
    # the unit square to the image quad.
    flat = layout.marker_flat[m]                      # Q x 4 x 2 (TL, TR, BR, BL)
    side = flat[:, 1, 0] - flat[:, 0, 0]
    A = np.zeros((len(m), 3, 3))
    A[:, 0, 0] = A[:, 1, 1] = 1.0 / side
    A[:, 0, 2] = -flat[:, 0, 0] / side
    A[:, 1, 2] = -flat[:, 0, 1] / side
    A[:, 2, 2] = 1.0
    H = square_to_quad(img) @ A
    col_row = np.floor(flat.mean(axis=1) / fld.square)
    sq = (col_row[:, None, :] + np.array([[0, 0], [1, 0], [1, 1], [0, 1]])) * fld.square
    p = H @ np.concatenate([sq, np.ones((len(m), 4, 1))], axis=2).transpose(0, 2, 1)
    valid = np.all(p[:, 2] > 0, axis=1)
    w = np.where(p[:, 2:3] > 0, p[:, 2:3], 1.0)                    # Q x 1 x 4
    px = (p[:, :2] / w).transpose(0, 2, 1)                         # Q x 4 x 2
    # Jacobian of the homography at each square corner, times one square: the image of a
    # step of one square along the sheet's x and y there (Q x 4 x 2 x 2, [..., :, 0] is x).
    w_corner = w.transpose(0, 2, 1)[..., None]                    # Q x 4 x 1 x 1
    J = (H[:, None, :2, :2] - px[..., None] * H[:, None, 2:3, :2]) / w_corner * fld.square
    x, y = px[..., 0], px[..., 1]
    area = 0.5 * np.abs(np.sum(x * np.roll(y, -1, axis=1) - np.roll(x, -1, axis=1) * y, axis=1))
    ids = layout.marker_corner_ids[m]
    use = (ids >= 0) & valid[:, None]
    cid = ids[use]
    cpx = px[use]
    cJ = J[use]
    # The marker's own (light) square lies toward +x+y of its corner 0 and -x-y of corner 2.
    clight = np.broadcast_to(np.array([1.0, -1.0, 1.0, -1.0]), ids.shape)[use]
    cside = np.repeat(np.sqrt(area)[:, None], 4, axis=1)[use]
    if len(cid) == 0:
        return CornerPrediction.empty()
    uniq, inv, counts = np.unique(cid, return_inverse=True, return_counts=True)
    mean_px = np.zeros((len(uniq), 2))
    np.add.at(mean_px, inv, cpx)
    mean_px /= counts[:, None]
    mean_J = np.zeros((len(uniq), 2, 2))
    np.add.at(mean_J, inv, cJ)
    mean_J /= counts[:, None, None]
    light = np.zeros(len(uniq))
    light[inv] = clight  # every marker around a corner agrees: it is a chessboard
    mean_side = np.bincount(inv, cside) / counts
    spread = np.zeros(len(uniq))
    np.maximum.at(spread, inv, np.linalg.norm(cpx - mean_px[inv], axis=1))
    ok = spread <= 0.25 * mean_side
    used = np.unique(m[valid] + fld.first_id)
    return CornerPrediction(uniq[ok], mean_px[ok], mean_side[ok], used,
                            mean_J[ok].transpose(0, 2, 1), light[ok])


def subpix_window(square_px: np.ndarray) -> np.ndarray:
    """Half-size (px) of the cornerSubPix window for corners with a local square of
    ``square_px`` pixels, between 2 and 6 px.

    The markers stand about 0.13 square from the corner in the white squares; a window
    reaching past them pulls the corner toward their edges (measured on simulated cylinder
    fields: median error 0.05 px at 0.13 square, 0.12 px at 0.2, 0.15 px at 0.25)."""
    return np.clip(np.round(0.13 * np.asarray(square_px)), 2, 6).astype(int)


def refine_corners(image: np.ndarray, px: np.ndarray, square_px: np.ndarray,
                   max_move: float = 0.35) -> tuple[np.ndarray, np.ndarray]:
    """Refine predicted chessboard corners at full resolution.

    Returns ``(px, ok)``: refined pixels (N x 2) and a mask of corners that stayed inside
    the image, moved less than ``max_move`` squares (a larger move means the prediction
    was not near a corner, or the window slid to another one), and converged.
    ``cornerSubPix`` hands back the starting point unchanged when its iterations wander
    further than the window's half-size from it; that is a failure, not a corner.
    """
    px = np.asarray(px, dtype=float).reshape(-1, 2)
    out = px.copy()
    if len(px) == 0:
        return out, np.zeros(0, dtype=bool)
    h, w = image.shape
    win = subpix_window(square_px)
    inside = ((px[:, 0] >= win + 1) & (px[:, 0] <= w - win - 2)
              & (px[:, 1] >= win + 1) & (px[:, 1] <= h - win - 2))
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, _SUBPIX_ITERS, _SUBPIX_EPS)
    gave_up = np.zeros(len(px), dtype=bool)
    for half in np.unique(win[inside]):
        sel = inside & (win == half)
        start = px[sel].astype(np.float32).reshape(-1, 1, 2)
        pts = start.copy()
        cv2.cornerSubPix(image, pts, (int(half), int(half)), (-1, -1), crit)
        gave_up[sel] = np.all(pts == start, axis=(1, 2))
        out[sel] = pts.reshape(-1, 2)
    move = np.linalg.norm(out - px, axis=1)
    ok = (inside & ~gave_up & (move < max_move * np.asarray(square_px))
          & np.all(np.isfinite(out), axis=1))
    return out, ok


#: X-junction check: sample distances along the square's diagonals (fractions of a square).
#: The markers start 0.13 square from the corner inside the light squares, so the samples
#: stay in the plain margin around the corner.
_XJ_STEPS = (0.05, 0.09)
#: Point-symmetry ring, 16 directions at 22.5 deg steps in the sheet's frame, halfway
#: between the square axes so that none runs along a square's edge. Radii are multiples of
#: the ``cornerSubPix`` half-window, so that the ring covers the pixels the refinement used
#: (an edge there pulls the corner). On the outer ring every direction is sampled; on the
#: inner one only the 8 directions 34 deg or more from the edges: printed corners are not
#: perfect X-junctions (ink spread, squares a fraction of a pixel out of line), and on a
#: sharp photograph two samples 1 px from an edge then differ by up to half the contrast.
_XJ_RING_DIRECTIONS = 16
_XJ_RING_OUTER = 1.5
_XJ_RING_INNER = 1.0


def _sample_coefficients() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Coefficients (2 x K) of the two square axes for the diagonal samples (light
    diagonal's four, then the dark one's) and for half of the ring's directions, and the
    indices of those directions that lie mid-way in a square's sector."""
    st = np.array(_XJ_STEPS)
    plus = np.stack([st, st])      # along a0 + a1
    minus = np.stack([st, -st])    # along a0 - a1
    diag = np.concatenate([plus, -plus, minus, -minus], axis=1)
    half = _XJ_RING_DIRECTIONS // 2
    theta = (np.arange(half) + 0.5) * (2 * np.pi / _XJ_RING_DIRECTIONS)
    per_sector = _XJ_RING_DIRECTIONS // 4
    k = np.arange(half) % per_sector
    mid = np.flatnonzero((k > 0) & (k < per_sector - 1))
    return diag, np.stack([np.cos(theta), np.sin(theta)]), mid


_XJ_DIAG, _XJ_RING, _XJ_RING_MID = _sample_coefficients()


def x_junction_scores(image: np.ndarray, px: np.ndarray, axes: np.ndarray,
                      light_diagonal: np.ndarray, square_px: np.ndarray | None = None
                      ) -> tuple[np.ndarray, np.ndarray]:
    """How much each point looks like the chessboard corner it is meant to be.

    ``px`` (N x 2) are corner pixels, ``axes`` (N x 2 x 2) the image vectors of one square
    along the sheet's x and y there, ``light_diagonal`` (N,) +1 where the squares toward
    +x+y and -x-y are the light ones, ``square_px`` (N,) the local square side in pixels
    (default: the root of the area ``axes`` span). Returns ``(contrast, asymmetry)``, grey
    levels (N,):

    - ``contrast``: samples a little way into each of the four squares along their
      diagonals; the light pair's mean minus the dark pair's mean (negative for the wrong
      colouring, i.e. a corner one square off);
    - ``asymmetry``: the largest difference between two samples point-symmetric about the
      point, on a ring of 16 directions at 1.5 times the ``cornerSubPix`` half-window,
      and of the 8 of them mid-way between the square edges at 1 times. A chessboard
      corner is point-symmetric under any blur (the two light squares face each other, so
      do the dark ones and the markers' borders); an occluder's edge or texture in the
      window is not, and neither is a corner that the refinement left off its true place.
    """
    px = np.asarray(px, dtype=float).reshape(-1, 2)
    n = len(px)
    if n == 0:
        return np.zeros(0), np.zeros(0)
    axes = np.asarray(axes, dtype=float).reshape(n, 2, 2)
    if square_px is None:
        square_px = np.sqrt(np.abs(np.linalg.det(axes)))
    # x and y apart (N x K each): numpy is slow on a trailing axis of length 2, and the
    # check runs on every corner of every frame.
    ax, ay = axes[:, :, 0], axes[:, :, 1]
    ux, uy = ax @ _XJ_RING, ay @ _XJ_RING
    scale = subpix_window(square_px)[:, None] / np.maximum(np.hypot(ux, uy), 1e-12)
    ux *= scale
    uy *= scale
    ox, oy = _XJ_RING_OUTER * ux, _XJ_RING_OUTER * uy
    ix, iy = _XJ_RING_INNER * ux[:, _XJ_RING_MID], _XJ_RING_INNER * uy[:, _XJ_RING_MID]
    mx = np.concatenate([ax @ _XJ_DIAG, ox, ix, -ox, -ix], axis=1)
    my = np.concatenate([ay @ _XJ_DIAG, oy, iy, -oy, -iy], axis=1)
    mx += px[:, :1]
    my += px[:, 1:]
    # One remap for every sample of every corner: the diagonals, the ring, its reflection.
    v = cv2.remap(image, mx.astype(np.float32), my.astype(np.float32), cv2.INTER_LINEAR,
                  borderMode=cv2.BORDER_REPLICATE).astype(float)
    k = _XJ_DIAG.shape[1]
    m = _XJ_RING.shape[1] + len(_XJ_RING_MID)
    contrast = (v[:, :k // 2].mean(axis=1) - v[:, k // 2:k].mean(axis=1)) * light_diagonal
    asymmetry = np.abs(v[:, k:k + m] - v[:, k + m:]).max(axis=1)
    return contrast, asymmetry


def x_junction_ok(image: np.ndarray, px: np.ndarray, axes: np.ndarray,
                  light_diagonal: np.ndarray, among: np.ndarray | None = None,
                  min_contrast: float = 12.0, min_relative: float = 0.4,
                  max_asymmetry: float = 0.35, asymmetry_floor: float = 6.0,
                  square_px: np.ndarray | None = None) -> np.ndarray:
    """Mask of points that are chessboard corners with the expected colouring
    (see :func:`x_junction_scores`).

    ``cornerSubPix`` can stop on an edge or on a marker's corner when the prediction was
    poor (the marker quads are a few pixels wide at grazing angles), or where something
    covers the corner or crosses its window; such points are not reported. A point passes
    when:

    - the light diagonal is lighter by ``min_contrast`` grey levels or more (no corner,
      or a corner one square off, fails);
    - that contrast is at least ``min_relative`` of the median over the field's points
      (``among``, a mask; default all): a marker's corner, or a corner with one square
      covered, has three squares of one shade and about half the contrast;
    - the neighbourhood is point-symmetric about it: no two reflected ring samples differ
      by more than ``max_asymmetry`` of the contrast plus ``asymmetry_floor`` grey levels
      (for noise). An occluder's edge through or near the corner, at any angle, breaks
      the symmetry; so does texture over it (mostly: a saddle of texture can pass), and a
      refinement pulled off the corner.

    ``square_px`` (N,) sizes the ring like :func:`refine_corners`' window (default: from
    ``axes``). The thresholds and what they cost are measured in docs/tracking.md,
    "Corner checks".
    """
    contrast, asym = x_junction_scores(image, px, axes, light_diagonal, square_px)
    if len(contrast) == 0:
        return np.zeros(0, dtype=bool)
    sel = np.ones(len(contrast), dtype=bool) if among is None else np.asarray(among, bool)
    typical = float(np.median(contrast[sel])) if np.any(sel) else 0.0
    return ((contrast >= max(min_contrast, min_relative * typical))
            & (asym <= max_asymmetry * contrast + asymmetry_floor))


def detect_fields(image: np.ndarray, fields: Sequence[MarkerField],
                  params: QuadParams = QuadParams(),
                  roi: tuple[int, int, int, int] | None = None,
                  layouts: dict[str, BoardLayout] | None = None) -> dict[str, FieldCorners]:
    """Find the chessboard corners of every field in ``image`` (mono8, full resolution).

    Fields sharing a dictionary are decoded together; markers outside every field's id block
    are ignored. Fields with no corner found are absent from the result.
    """
    image = check_image(image)
    quads = find_quads(image, params, roi)
    out: dict[str, FieldCorners] = {}
    by_dict: dict[str, list[MarkerField]] = {}
    for f in fields:
        by_dict.setdefault(f.dictionary, []).append(f)
    for dic, flds in by_dict.items():
        allowed = [range(f.first_id, f.first_id + f.marker_count) for f in flds]
        decoded = decoder_for(dic).decode(image, quads, allowed)
        for f in flds:
            mine = [q for q in decoded if f.first_id <= q.marker_id < f.first_id + f.marker_count]
            if not mine:
                continue
            layout = (layouts or {}).get(f.name) or BoardLayout.of(f)
            pr = predict_board(f, layout, mine)
            px, ok = refine_corners(image, pr.px, pr.square_px)
            ok &= x_junction_ok(image, px, pr.axes, pr.light_diagonal, among=ok,
                                square_px=pr.square_px)
            if np.any(ok):
                out[f.name] = FieldCorners(pr.ids[ok], px[ok], pr.markers)
    return out
