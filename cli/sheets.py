"""Printable marker-field sheets at true scale (``oralnav markers print``).

A surgeon's team prints the sheet and sticks it on the robot, the end-effector or the mouth
opener, so the printed squares must measure exactly ``square`` metres: the navigation
model (``MarkerField.corners``) assumes it. :func:`render_sheet` draws the board at its true
size for a given printer resolution, with a white quiet zone (one square or more, which the
detectors need) and, optionally, crop marks, a caption stating the field and how to mount it,
and a ruler-checkable scale bar. :func:`write_png` stores the image with its resolution in
the PNG ``pHYs`` chunk, atomically; :func:`read_png_dpi` reads it back.

Pixel coordinates here use the *edge* convention of ``MarkerField.board_image``: pixel
``(row, col)`` covers ``[col, col + 1] x [row, row + 1]``. OpenCV's detectors report
positions with pixel *centres* at integers, i.e. ``edge coordinate - 0.5``.

How exactness is ensured: the board is never resampled from a raster. The sheet is a
piecewise-constant function on a rectilinear grid whose lines (square edges, the white
margin around each marker, the marker's bit cells) are computed in metres from the field's
geometry; only *which* cells are black is read from OpenCV's own ``board_image`` (sampled at
cell centres, at a resolution where every bit cell spans >= 8 pixels). Each output pixel is
then the exact area average of that function over the pixel (separable overlap matrices), so
every edge lies at its true sub-pixel position ``origin + x * dpi / 0.0254`` and the board
spans exactly ``squares * square`` metres at ``dpi``. The only error left is the final
rounding to 8 bits (< 1/500 px of edge position). ``tests/cli/test_sheets.py`` measures
every square edge and the detected corners against this.
"""

from __future__ import annotations

import math
import os
import struct
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from oralnav.config.loader import atomic_write_bytes
from oralnav.control.vision.markers import (
    CylinderSurface,
    MarkerField,
    PlaneSurface,
    PointsSurface,
)

__all__ = [
    "DPI_MAX",
    "DPI_MIN",
    "INCH",
    "MAX_BOARD_PX",
    "SheetError",
    "SheetImage",
    "caption_lines",
    "read_png_dpi",
    "render_sheet",
    "write_png",
]

INCH = 0.0254
"""One inch, metres."""
DPI_MIN = 72.0
DPI_MAX = 2400.0
MAX_BOARD_PX = 20000
"""Largest board side, pixels, that :func:`render_sheet` accepts."""

_BORDER_BITS = 1  # as MarkerField.board_image's default: what the detectors expect
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


class SheetError(ValueError):
    """A sheet cannot be drawn or read as asked (bad dpi, too large, not a PNG...)."""


@dataclass(frozen=True, eq=False)
class SheetImage:
    """A printable sheet.

    Attributes:
        image: the sheet, mono8, H x W (white paper = 255).
        dpi: printer resolution the sheet is drawn for, dots per inch.
        px_per_metre: ``dpi / 0.0254``.
        board_origin_px: (col, row) of the board's outer corner (the field origin) in the
            image, edge convention (pixel ``(r, c)`` covers ``[c, c+1] x [r, r+1]``).
        board_size_px: board width and height in pixels (generally not integers).
    """

    image: np.ndarray
    dpi: float
    px_per_metre: float
    board_origin_px: tuple[int, int]
    board_size_px: tuple[float, float]

    def sheet_to_px(self, xy: np.ndarray) -> np.ndarray:
        """Flat-sheet points (N x 2, m, field frame) to image points (N x 2, edge convention)."""
        xy = np.asarray(xy, dtype=float)
        return np.asarray(self.board_origin_px, dtype=float) + xy * self.px_per_metre


# -- rendering ------------------------------------------------------------------------------


def render_sheet(field: MarkerField, dpi: float, *, label: bool = True) -> SheetImage:
    """Draw ``field`` as a printable sheet at true scale for a ``dpi`` printer.

    The board spans exactly ``squares * square`` metres (``dpi / 0.0254`` pixels per metre),
    surrounded by a white quiet zone one square wide (rounded up to whole pixels). With
    ``label``, crop marks outside the quiet zone, a caption (field, dictionary, ids, sizes in
    mm, surface and how to mount it, dpi) and a 50 mm (or 10 mm) scale bar are added below.

    Raises:
        SheetError: ``dpi`` outside [72, 2400], a board wider than 20000 px, or a dpi so low
            that a marker bit would be smaller than one pixel.
    """
    dpi = _check_dpi(dpi)
    ppm = dpi / INCH
    nx, ny = field.squares
    board_w, board_h = field.sheet_size[0] * ppm, field.sheet_size[1] * ppm
    if max(board_w, board_h) > MAX_BOARD_PX:
        most = dpi * MAX_BOARD_PX / max(board_w, board_h)
        raise SheetError(
            f"field {field.name!r}: the board would be {board_w:.0f} x {board_h:.0f} px at "
            f"dpi {dpi:g}, more than {MAX_BOARD_PX} px per side; use dpi <= {math.floor(most)}")
    bits = _bits_per_side(field)
    bit_px = field.marker / bits * ppm
    if bit_px < 1.0:
        least = dpi / bit_px
        raise SheetError(
            f"field {field.name!r}: at dpi {dpi:g} a marker bit would be {bit_px:.2f} px, "
            f"too small to print; use dpi >= {math.ceil(least)}")

    quiet = _ceil(field.square * ppm)  # >= one square of white, whole pixels
    if not label:
        x0 = y0 = quiet
        width = _ceil(x0 + board_w + quiet)
        height = _ceil(y0 + board_h + quiet)
        image = np.full((height, width), 255, np.uint8)
        _draw_board(image, field, (x0, y0), ppm)
        return SheetImage(image, dpi, ppm, (x0, y0), (board_w, board_h))

    mm = ppm / 1000.0  # pixels per millimetre
    pad = math.ceil(6 * mm)  # room for crop marks outside the quiet zone
    x0 = y0 = pad + quiet
    trim = (pad, pad, x0 + board_w + quiet, y0 + board_h + quiet)  # x0, y0, x1, y1 (edges)
    font = _Font(mm)
    lines = caption_lines(field, dpi)
    text_w = max(font.width(s) for s in lines)
    avail = max(trim[2] - trim[0], text_w)
    bar_mm = 50 if 50 * mm + font.width(" mm") <= avail else 10
    bar_w = bar_mm * mm + font.width(f"{bar_mm} mm")

    width = _ceil(trim[0] + max(trim[2] - trim[0], text_w, bar_w) + pad)
    y = trim[3] + pad + font.cap  # first caption baseline
    bar_top = y + (len(lines) - 1) * font.step + font.step
    height = _ceil(bar_top + 2.5 * mm + font.step + pad)
    image = np.full((height, width), 255, np.uint8)

    _draw_board(image, field, (x0, y0), ppm)
    _draw_crop_marks(image, trim, mm)
    for k, s in enumerate(lines):
        font.put(image, s, (trim[0], y + k * font.step))
    _draw_scale_bar(image, (trim[0], bar_top), bar_mm, mm, font)
    return SheetImage(image, dpi, ppm, (x0, y0), (board_w, board_h))


def _ceil(value: float) -> int:
    """Ceiling that ignores float noise (420.00000000000006 -> 420)."""
    return math.ceil(value - 1e-7)


def _check_dpi(dpi: float) -> float:
    try:
        value = float(dpi)
    except (TypeError, ValueError):
        raise SheetError(f"dpi must be a number, got {dpi!r}") from None
    if not (math.isfinite(value) and DPI_MIN <= value <= DPI_MAX):
        raise SheetError(f"dpi must be within [{DPI_MIN:g}, {DPI_MAX:g}], got {dpi!r}")
    return value


def _bits_per_side(field: MarkerField) -> int:
    """Cells across one marker: its data bits plus the black border on each side."""
    return int(field.board.getDictionary().markerSize) + 2 * _BORDER_BITS


def _board_cells(field: MarkerField) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The board as a rectilinear grid of constant cells.

    Returns ``(xs, ys, black)``: cell edges along x and y (metres, field frame, increasing,
    from 0 to the sheet size) and a ``len(ys)-1 x len(xs)-1`` boolean array, True where the
    cell is black. Every square is split the same way: white margin, ``n`` marker bit cells,
    white margin, with the marker centred as in OpenCV's board.
    """
    nx, ny = field.squares
    sq, n = field.square, _bits_per_side(field)
    off, bit = 0.5 * (sq - field.marker), field.marker / n
    local = np.concatenate([[0.0], off + bit * np.arange(n + 1)])  # n + 2 cells per square
    xs = np.concatenate([k * sq + local for k in range(nx)] + [[nx * sq]])
    ys = np.concatenate([k * sq + local for k in range(ny)] + [[ny * sq]])

    # Which squares carry a marker (those are white; the others solid black): from the
    # board's marker corners, pure geometry.
    white = np.zeros((ny, nx), bool)
    for corners in field.board.getObjPoints():
        cx, cy = np.asarray(corners, float).reshape(-1, 3)[:, :2].mean(axis=0)
        white[int(cy // sq), int(cx // sq)] = True

    # Which bit cells are black: read at the cell centres from OpenCV's own drawing, at a
    # resolution where every bit cell spans >= 8 px (so its rounding cannot matter).
    q = max(8, math.ceil(8 * n * sq / field.marker))
    ref = field.board_image(q, border_bits=_BORDER_BITS)
    centres = off + bit * (np.arange(n) + 0.5)
    black = np.repeat(np.repeat(~white, n + 2, axis=0), n + 2, axis=1)
    for r, c in zip(*np.nonzero(white), strict=True):
        rows = np.floor((r * sq + centres) / sq * q).astype(int)
        cols = np.floor((c * sq + centres) / sq * q).astype(int)
        bits = ref[np.ix_(rows, cols)] < 128
        if not (bits[0].all() and bits[-1].all() and bits[:, 0].all() and bits[:, -1].all()):
            raise SheetError(  # OpenCV changed how it lays out boards: do not print garbage
                f"field {field.name!r}: the marker in square ({c}, {r}) has no black border "
                "where expected; cannot draw this board exactly")
        k = n + 2
        black[r * k + 1:r * k + 1 + n, c * k + 1:c * k + 1 + n] = bits
    return xs, ys, black


def _coverage(edges: np.ndarray, size: int) -> np.ndarray:
    """Overlap lengths (size x len(edges)-1, float32) of pixels [i, i+1] with cells."""
    i = np.arange(size, dtype=float)[:, None]
    lo = np.maximum(i, edges[None, :-1])
    hi = np.minimum(i + 1.0, edges[None, 1:])
    return np.clip(hi - lo, 0.0, 1.0).astype(np.float32)


def _draw_board(image: np.ndarray, field: MarkerField, origin: tuple[int, int],
                ppm: float) -> None:
    """Paint the board with its outer corner at ``origin`` (col, row), exact area coverage."""
    xs, ys, black = _board_cells(field)
    ex = origin[0] + xs * ppm
    ey = origin[1] + ys * ppm
    c0, c1 = math.floor(ex[0]), _ceil(ex[-1])
    r0, r1 = math.floor(ey[0]), _ceil(ey[-1])
    cov_x = _coverage(ex - c0, c1 - c0)                      # W x cells_x
    cov_y = _coverage(ey - r0, r1 - r0)                      # H x cells_y
    right = black.astype(np.float32) @ cov_x.T               # cells_y x W
    step = max(1, 4_000_000 // max(1, c1 - c0))              # bound the float working set
    for a in range(0, r1 - r0, step):
        frac = cov_y[a:a + step] @ right                     # black fraction of each pixel
        out = np.rint(255.0 * (1.0 - np.clip(frac, 0.0, 1.0)))
        image[r0 + a:r0 + a + len(frac), c0:c1] = np.minimum(
            image[r0 + a:r0 + a + len(frac), c0:c1], out.astype(np.uint8))


def _paint_rect(image: np.ndarray, x0: float, y0: float, x1: float, y1: float) -> None:
    """Darken the axis-aligned rectangle [x0, x1] x [y0, y1] (pixels, edge convention)
    to black, with exact area coverage at its borders."""
    c0, c1 = max(0, math.floor(x0)), min(image.shape[1], math.ceil(x1))
    r0, r1 = max(0, math.floor(y0)), min(image.shape[0], math.ceil(y1))
    if c1 <= c0 or r1 <= r0:
        return
    cx = _coverage(np.array([x0 - c0, x1 - c0]), c1 - c0)[:, 0]
    cy = _coverage(np.array([y0 - r0, y1 - r0]), r1 - r0)[:, 0]
    patch = image[r0:r1, c0:c1].astype(np.float32) * (1.0 - np.outer(cy, cx))
    image[r0:r1, c0:c1] = np.rint(patch).astype(np.uint8)


def _draw_crop_marks(image: np.ndarray, trim: Sequence[float], mm: float) -> None:
    """Short lines outside each corner of the trim box (the quiet zone's outer edge)."""
    x0, y0, x1, y1 = trim
    t = max(1.0, 0.1 * mm)
    gap, length = 1.0 * mm, 4.0 * mm
    for x, sx in ((x0, -1), (x1, 1)):
        for y, sy in ((y0, -1), (y1, 1)):
            a, b = sorted((x + sx * gap, x + sx * (gap + length)))
            _paint_rect(image, a, y - t / 2, b, y + t / 2)        # along the horizontal edge
            a, b = sorted((y + sy * gap, y + sy * (gap + length)))
            _paint_rect(image, x - t / 2, a, x + t / 2, b)        # along the vertical edge


def _draw_scale_bar(image: np.ndarray, top_left: tuple[float, float], length_mm: int,
                    mm: float, font: _Font) -> None:
    """A ruler ``length_mm`` long: a tick every mm (longer every 5 and 10), labelled in mm.

    Tick centres lie at their exact positions, so a ruler laid on the print checks the scale.
    """
    x0, top = top_left
    t = max(1.0, 0.15 * mm)
    base = top + 2.0 * mm  # bottom line of the ruler; ticks rise from it
    _paint_rect(image, x0 - t / 2, base - t / 2, x0 + length_mm * mm + t / 2, base + t / 2)
    for k in range(length_mm + 1):
        h = 2.0 if k % 10 == 0 else 1.5 if k % 5 == 0 else 1.0
        x = x0 + k * mm
        _paint_rect(image, x - t / 2, base - h * mm, x + t / 2, base)
    small = _Font(mm, cap_mm=1.5)
    for k in range(0, length_mm + 1, 10):
        s = str(k)
        small.put(image, s, (x0 + k * mm - small.width(s) / 2, base + 0.8 * mm + small.cap))
    font.put(image, f"{length_mm} mm", (x0 + length_mm * mm + 1.5 * mm, base))


class _Font:
    """Hershey simplex text sized in millimetres on the printed sheet (min ~9 px tall)."""

    face = cv2.FONT_HERSHEY_SIMPLEX

    def __init__(self, px_per_mm: float, cap_mm: float = 2.0) -> None:
        unit = cv2.getTextSize("H", self.face, 1.0, 1)[0][1]
        self.cap = max(cap_mm * px_per_mm, 9.0)  # capital height, pixels
        self.scale = self.cap / unit
        self.thick = max(1, round(self.cap / 12))
        self.step = 1.9 * self.cap  # line pitch, pixels

    def width(self, text: str) -> float:
        return float(cv2.getTextSize(text, self.face, self.scale, self.thick)[0][0])

    def put(self, image: np.ndarray, text: str, at: tuple[float, float]) -> None:
        """Write ``text`` with its baseline's left end at ``at`` (col, row)."""
        cv2.putText(image, text, (round(at[0]), round(at[1])), self.face, self.scale, 0,
                    self.thick, cv2.LINE_AA)


def _ascii(text: str) -> str:
    return text.encode("ascii", "replace").decode("ascii")


def caption_lines(field: MarkerField, dpi: float) -> list[str]:
    """The caption printed under the board, one string per line.

    ASCII only (Hershey fonts have no other glyphs); lengths in mm, angles in degrees.
    """
    nx, ny = field.squares
    w, h = (1000 * v for v in field.sheet_size)
    ids = field.marker_ids
    lines = [
        f"oralnav marker field '{_ascii(field.name)}' - ChArUco {field.dictionary}, "
        f"marker ids {ids[0]}..{ids[-1]}",
        f"{nx} x {ny} squares, square {1000 * field.square:.3f} mm, "
        f"marker {1000 * field.marker:.3f} mm, board {w:.3f} x {h:.3f} mm",
    ]
    s = field.surface
    if isinstance(s, CylinderSurface):
        wrap = math.degrees(field.sheet_size[0] / s.radius)
        lines += [
            f"surface: wrap on a cylinder of radius {1000 * s.radius:.3f} mm, "
            "printed face outward,",
            f"axis along the sheet's y (up-down here); the sheet wraps {wrap:.1f} deg",
        ]
    elif isinstance(s, PointsSurface):
        src = f" ({_ascii(Path(s.source).name)})" if s.source else ""
        lines.append(f"surface: measured corner model{src}; stick as when it was measured")
    elif isinstance(s, PlaneSurface):
        lines.append("surface: flat; stick it on a plane, printed face outward")
    lines += [
        "field frame: origin at the board's top-left outer corner, x right, y down",
        f"drawn for {dpi:g} dpi: print at 100 % (actual size, no fit-to-page); "
        "cut at the crop marks",
        "check the print: the scale bar below must measure what it says with a ruler",
    ]
    return lines


# -- PNG with pHYs ----------------------------------------------------------------------------


def _chunk(kind: bytes, data: bytes) -> bytes:
    crc = zlib.crc32(kind + data) & 0xFFFFFFFF
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", crc)


def _encode_png(image: np.ndarray, dpi: float) -> bytes:
    """PNG bytes of ``image`` with a pHYs chunk (pixels per metre, unit 1) after IHDR."""
    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise SheetError("OpenCV could not encode the image as PNG")
    png = buf.tobytes()
    if png[:8] != _PNG_SIGNATURE or png[12:16] != b"IHDR":
        raise SheetError("OpenCV produced a PNG without a leading IHDR chunk")
    ppm = round(dpi / INCH)
    phys = _chunk(b"pHYs", struct.pack(">IIB", ppm, ppm, 1))
    head_end = 8 + 12 + struct.unpack(">I", png[8:12])[0]
    rest = b"".join(c for c in _chunks_raw(png[head_end:]) if c[4:8] != b"pHYs")
    return png[:head_end] + phys + rest


def _chunks_raw(data: bytes) -> list[bytes]:
    out, i = [], 0
    while i < len(data):
        if i + 12 > len(data):
            raise SheetError("truncated PNG chunk")
        n = struct.unpack(">I", data[i:i + 4])[0]
        out.append(data[i:i + 12 + n])
        i += 12 + n
    return out


def write_png(path: str | os.PathLike[str], image: np.ndarray, dpi: float) -> None:
    """Write ``image`` (uint8, H x W or H x W x 3/4) as a PNG printed at ``dpi``.

    The resolution goes in the pHYs chunk (pixels per metre, rounded to an integer, unit =
    metre) so that printing at 100 % gives true scale. The write is atomic: the bytes go to a
    temporary file in the target directory, are fsync'ed, then renamed over ``path``; on any
    error the temporary file is removed and an existing ``path`` is left unchanged.

    Raises:
        SheetError: bad image or dpi.
        FileNotFoundError: the parent directory does not exist.
        OSError: the file cannot be written.
    """
    dpi = _check_dpi(dpi)
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.ndim not in (2, 3) or image.size == 0 or (
            image.ndim == 3 and image.shape[2] not in (1, 3, 4)):
        raise SheetError(
            f"image must be non-empty uint8 H x W or H x W x 1/3/4, got {image.dtype} "
            f"{image.shape}")
    data = _encode_png(image, dpi)  # before touching the file system
    atomic_write_bytes(path, data)


def read_png_dpi(path: str | os.PathLike[str]) -> float | None:
    """The print resolution (dpi) stored in a PNG's pHYs chunk, or None when it has none.

    None also when the chunk gives only an aspect ratio (unit 0). The value is pixels per
    metre times 0.0254, rounded to 0.01 dpi (pHYs stores whole pixels per metre).

    Raises:
        SheetError: not a PNG, a malformed chunk, or different x and y resolutions.
    """
    data = Path(path).read_bytes()
    if data[:8] != _PNG_SIGNATURE:
        raise SheetError(f"{os.fspath(path)!r} is not a PNG file")
    i = 8
    while i + 8 <= len(data):
        n, kind = struct.unpack(">I4s", data[i:i + 8])
        body = data[i + 8:i + 8 + n]
        if len(body) != n or i + 12 + n > len(data):
            raise SheetError(f"{os.fspath(path)!r}: truncated {kind!r} chunk")
        if kind == b"pHYs":
            if n != 9:
                raise SheetError(f"{os.fspath(path)!r}: pHYs chunk of {n} bytes (expected 9)")
            px, py, unit = struct.unpack(">IIB", body)
            if unit != 1:
                return None
            if px != py:
                raise SheetError(
                    f"{os.fspath(path)!r}: non-square pixels ({px} x {py} px/m); no single dpi")
            return round(px * INCH, 2)
        if kind in (b"IDAT", b"IEND"):  # pHYs must come before the image data
            return None
        i += 12 + n
    return None
