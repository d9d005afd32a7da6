"""Printable marker sheets (``oralnav markers print``): true scale, detectability, PNG dpi.

Requirement: "a surgeon's team must be able to print and stick it at true scale".
"""

from __future__ import annotations

import os
import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from oralnav.cli import sheets
from oralnav.cli.sheets import (
    SheetError,
    SheetImage,
    caption_lines,
    read_png_dpi,
    render_sheet,
    write_png,
)
from oralnav.control.vision.markers import CylinderSurface, MarkerField, PlaneSurface

INCH = 0.0254


def opener() -> MarkerField:
    return MarkerField(name="opener", dictionary="DICT_4X4_1000", squares=(12, 9),
                       square=0.003, marker=0.0022, first_id=0,
                       surface=CylinderSurface(radius=0.012))


def robot() -> MarkerField:
    return MarkerField(name="robot", dictionary="DICT_5X5_250", squares=(7, 5),
                       square=0.006, marker=0.0045, first_id=40, surface=PlaneSurface())


# -- measuring helpers ----------------------------------------------------------------------


def _edge(profile: np.ndarray, expected: float, rising: bool) -> float:
    """Sub-pixel position (edge convention) of the one black/white step near ``expected``.

    With area-averaged pixels, the black mass in a window around a step tells exactly where
    the step is: for a white-to-black step the window holds ``end - edge`` pixels of black.
    """
    a = int(np.floor(expected)) - 3
    b = a + 7
    black = 1.0 - profile[a:b].astype(float) / 255.0
    return b - black.sum() if rising else a + black.sum()


def _square_edges(sheet: SheetImage, field: MarkerField, axis: int) -> np.ndarray:
    """Measured minus expected position (px) of every visible square edge along ``axis``.

    axis 0 measures edges along x (vertical lines), 1 along y. Each line of squares is
    probed along a pixel line inside the white margin band around the markers, where the
    profile is a clean chessboard of solid black squares and blank white ones.
    Square (c, r) is black when (c + r) is even (OpenCV's ChArUco layout).
    """
    img = sheet.image if axis == 0 else sheet.image.T
    n_along, n_across = (field.squares if axis == 0 else field.squares[::-1])
    origin = sheet.board_origin_px[axis]
    origin_across = sheet.board_origin_px[1 - axis]
    ppm = sheet.px_per_metre
    band = 0.5 * (field.square - field.marker) * ppm
    assert band >= 2.0, "test needs a margin band of at least 2 px"
    errors = []
    for r in range(n_across):
        line = int(np.floor(origin_across + r * field.square * ppm + 0.5 * band))
        profile = img[line]
        for k in range(n_along + 1):
            left_black = k > 0 and (k - 1 + r) % 2 == 0
            right_black = k < n_along and (k + r) % 2 == 0
            if left_black == right_black:  # white square beside the white quiet zone
                continue
            expected = origin + k * field.square * ppm
            errors.append(_edge(profile, expected, rising=right_black) - expected)
    return np.asarray(errors)


def _outer_box(sheet: SheetImage, field: MarkerField) -> tuple[float, float, float, float]:
    """Measured (left, top, right, bottom) of the board, px, edge convention."""
    out = []
    for axis in (0, 1):
        img = sheet.image if axis == 0 else sheet.image.T
        n_along = field.squares[axis]
        origin = sheet.board_origin_px[axis]
        across = sheet.board_origin_px[1 - axis]
        ppm = sheet.px_per_metre
        band = 0.5 * (field.square - field.marker) * ppm
        # line of squares 0 starts black at k = 0; the last square of line r is black
        # when (n_along - 1 + r) is even
        r_end = 0 if (n_along - 1) % 2 == 0 else 1
        first = img[int(np.floor(across + 0.5 * band))]
        last = img[int(np.floor(across + (r_end * field.square) * ppm + 0.5 * band))]
        lo = _edge(first, origin, rising=True)
        hi = _edge(last, origin + field.sheet_size[axis] * ppm, rising=False)
        out.append((lo, hi))
    (left, right), (top, bottom) = out
    return left, top, right, bottom


# -- true scale -----------------------------------------------------------------------------


@pytest.mark.parametrize("dpi", [150.0, 333.3, 600.0, 1200.0])
def test_board_is_printed_at_true_scale(dpi: float) -> None:
    """Issue 2 item 6: printed sheet is at true scale: the board's outer box measures
    squares * square * dpi / 0.0254 px (within 1 px) and starts at board_origin_px."""
    field = opener()
    sheet = render_sheet(field, dpi)
    assert sheet.dpi == dpi
    assert sheet.px_per_metre == pytest.approx(dpi / INCH)
    left, top, right, bottom = _outer_box(sheet, field)
    want_w = field.squares[0] * field.square * dpi / INCH
    want_h = field.squares[1] * field.square * dpi / INCH
    assert abs((right - left) - want_w) < 1.0
    assert abs((bottom - top) - want_h) < 1.0
    assert abs(left - sheet.board_origin_px[0]) < 1.0
    assert abs(top - sheet.board_origin_px[1]) < 1.0
    assert sheet.board_size_px == pytest.approx((want_w, want_h))


@pytest.mark.parametrize(("make", "dpi"), [(opener, 333.3), (opener, 600.0), (robot, 254.0)])
def test_every_square_edge_is_at_its_true_position(make, dpi: float) -> None:
    """Issue 2 item 6: true scale over the whole board: every visible square edge, along x
    and along y, lies within 1 px of origin + k * square * dpi / 0.0254 (non-integer
    pixels per square included)."""
    field = make()
    sheet = render_sheet(field, dpi, label=False)
    for axis in (0, 1):
        err = _square_edges(sheet, field, axis)
        assert len(err) >= field.squares[1 - axis] * (field.squares[axis] - 1)
        assert np.abs(err).max() < 1.0, f"axis {axis}: worst edge off by {np.abs(err).max()}"


def test_pattern_matches_opencv_board_where_pixels_are_whole() -> None:
    """Issue 2 item 6: the sheet draws OpenCV's own board: where every edge falls on a pixel
    boundary (0.1 inch squares at 600 dpi) the board region equals board_image exactly."""
    for dictionary, bits in (("DICT_4X4_1000", 6), ("DICT_6X6_250", 8)):
        field = MarkerField(name="grid", dictionary=dictionary, squares=(7, 5),
                            square=0.00254 * (bits + 4) / 10, marker=0.00254 * bits / 10,
                            first_id=3)
        sheet = render_sheet(field, 600, label=False)
        ref = field.board_image((bits + 4) * 6)
        c, r = sheet.board_origin_px
        np.testing.assert_array_equal(sheet.image[r:r + ref.shape[0], c:c + ref.shape[1]], ref)


@pytest.mark.parametrize("label", [False, True])
def test_quiet_zone_is_white_and_a_square_wide(label: bool) -> None:
    """Issue 2 item 6: the board has a white quiet zone at least one square wide on every
    side (detectors need it); crop marks and caption stay outside it."""
    field = opener()
    sheet = render_sheet(field, 300, label=label)
    ppm = sheet.px_per_metre
    c, r = sheet.board_origin_px
    w, h = sheet.board_size_px
    q = field.square * ppm
    assert c >= q and r >= q
    r0, c0 = int(r - q), int(c - q)  # box of board + one square all round
    box = sheet.image[r0:int(np.ceil(r + h + q)), c0:int(np.ceil(c + w + q))]
    assert box.shape[0] >= h + 2 * q and box.shape[1] >= w + 2 * q
    mask = np.ones(box.shape, bool)
    mask[r - r0:int(np.ceil(r + h)) - r0, c - c0:int(np.ceil(c + w)) - c0] = False  # board
    assert (box[mask] == 255).all()


def test_scale_bar_measures_50_mm() -> None:
    """Issue 2 item 6: the labelled sheet carries a 50 mm scale bar with mm ticks whose end
    ticks are 50 mm apart at the sheet's dpi (within 1 px), to check a print with a ruler."""
    dpi = 300.0
    sheet = render_sheet(opener(), dpi)
    ppm_mm = dpi / INCH / 1000
    below = sheet.image[int(sheet.board_origin_px[1] + sheet.board_size_px[1] + 4 * ppm_mm):]
    dark = below < 128

    def longest_run(row: np.ndarray) -> int:
        padded = np.concatenate([[0], row.astype(np.int8), [0]])
        d = np.diff(padded)
        starts, ends = np.nonzero(d == 1)[0], np.nonzero(d == -1)[0]
        return int((ends - starts).max()) if len(starts) else 0

    runs = np.array([longest_run(row) for row in dark])
    base = int(np.argmax(runs))
    assert runs[base] == pytest.approx(50 * ppm_mm, abs=3)
    while dark[base - 1].sum() >= 0.9 * runs[base]:  # top of the (thick) base line
        base -= 1
    bar = np.nonzero(dark[base])[0]
    start = bar[0] - 2  # the "50 mm" label sits to the right of the bar: leave it out
    stop = bar[0] + runs[np.argmax(runs)] + 2
    probe = 1.0 - below[base - 2, start:stop].astype(float) / 255.0  # 2 px above: ticks
    ticks = []
    in_tick, mass, moment = False, 0.0, 0.0
    for x, v in enumerate(probe):
        if v > 0:
            in_tick, mass, moment = True, mass + v, moment + v * (x + 0.5)
        elif in_tick:
            ticks.append(moment / mass)
            in_tick, mass, moment = False, 0.0, 0.0
    assert len(ticks) == 51
    assert ticks[-1] - ticks[0] == pytest.approx(50 * ppm_mm, abs=1.0)
    assert np.diff(ticks) == pytest.approx(ppm_mm, abs=1.0)


# -- detectability --------------------------------------------------------------------------


@pytest.mark.parametrize(("make", "dpi"), [(opener, 600.0), (robot, 300.0)])
def test_sheet_is_detected_with_right_ids_and_positions(make, dpi: float) -> None:
    """Issue 2 item 6: the printed sheet is a working marker field: OpenCV's CharucoDetector
    finds most chessboard corners on the labelled sheet, with the right ids, each within
    1 px of where the board origin and true scale put it."""
    field = make()
    sheet = render_sheet(field, dpi)
    corners, ids, _, marker_ids = cv2.aruco.CharucoDetector(field.board).detectBoard(
        sheet.image)
    assert ids is not None
    ids = ids.ravel()
    assert len(ids) >= 0.9 * field.corner_count
    assert set(marker_ids.ravel()) <= set(field.marker_ids.tolist())
    assert len(set(ids.tolist())) == len(ids) and ids.max() < field.corner_count
    # corner j's flat position, mapped through the sheet; OpenCV puts pixel centres at
    # integers, hence the -0.5
    want = sheet.sheet_to_px(field.corners_flat[ids]) - 0.5
    err = np.linalg.norm(corners.reshape(-1, 2) - want, axis=1)
    assert err.max() < 1.0, f"worst corner off by {err.max():.3f} px"


# -- caption --------------------------------------------------------------------------------


def test_caption_names_field_and_mounting() -> None:
    """Issue 2 item 6: the caption states the field name, dictionary, ids, squares, square
    and marker sizes in mm, the cylinder to wrap on (radius, face outward, axis along the
    sheet's y, wrap angle) and the dpi."""
    text = "\n".join(caption_lines(opener(), 600))
    for want in ("'opener'", "DICT_4X4_1000", "ids 0..53", "12 x 9 squares",
                 "square 3.000 mm", "marker 2.200 mm",
                 "wrap on a cylinder of radius 12.000 mm", "printed face outward",
                 "axis along the sheet's y", f"{np.degrees(0.036 / 0.012):.1f} deg",
                 "600 dpi", "100 %"):
        assert want in text, want
    flat = "\n".join(caption_lines(robot(), 300))
    assert "flat" in flat and "ids 40..56" in flat and "cylinder" not in flat
    assert all(line.isascii() for line in caption_lines(opener(), 72))


def test_label_adds_caption_below_the_board() -> None:
    """Issue 2 item 6: with label the sheet grows a captioned margin under the board; the
    board itself is drawn identically with or without it."""
    field = opener()
    bare, full = render_sheet(field, 300, label=False), render_sheet(field, 300)
    assert full.image.shape[0] > bare.image.shape[0] + 100
    below = full.image[int(full.board_origin_px[1] + full.board_size_px[1]
                           + field.square * full.px_per_metre) + 1:]
    assert (below < 128).sum() > 1000  # text and scale bar
    w, h = (int(np.ceil(v)) for v in bare.board_size_px)
    (bc, br), (fc, fr) = bare.board_origin_px, full.board_origin_px
    np.testing.assert_array_equal(bare.image[br:br + h, bc:bc + w],
                                  full.image[fr:fr + h, fc:fc + w])


# -- bad input ------------------------------------------------------------------------------


@pytest.mark.parametrize("dpi", [71.9, 2400.5, 0, -300, float("nan"), float("inf"), "lots"])
def test_bad_dpi_rejected(dpi) -> None:
    """Issue 2 item 6: dpi outside [72, 2400] (or not a number) is rejected with a
    ValueError that names the value."""
    with pytest.raises(ValueError, match="dpi") as info:
        render_sheet(opener(), dpi)
    assert isinstance(info.value, SheetError)
    assert repr(dpi) in str(info.value)


def test_dpi_range_ends_accepted() -> None:
    """Issue 2 item 6: 72 and 2400 dpi are both allowed."""
    field = MarkerField(name="tiny", dictionary="DICT_4X4_50", squares=(3, 3), square=0.005,
                        marker=0.0035)
    assert render_sheet(field, 72, label=False).dpi == 72
    assert render_sheet(field, 2400, label=False).dpi == 2400


def test_oversized_board_rejected() -> None:
    """Issue 2 item 6: a board over ~20000 px per side is refused with a clear error naming
    its size and the largest usable dpi, before any memory is spent."""
    big = MarkerField(name="wall", dictionary="DICT_4X4_1000", squares=(30, 20), square=0.01,
                      marker=0.007)
    with pytest.raises(SheetError, match=r"28346 x 18898 px.*dpi <= 1693"):
        render_sheet(big, 2400)


def test_unprintably_small_bits_rejected() -> None:
    """Issue 2 item 6: a dpi at which a marker bit would be under one pixel is refused,
    naming the smallest dpi that works."""
    small = MarkerField(name="fine", dictionary="DICT_4X4_50", squares=(4, 4), square=0.001,
                        marker=0.0007)
    with pytest.raises(SheetError, match=r"0\.33 px.*dpi >= 218"):
        render_sheet(small, 72)


# -- PNG ------------------------------------------------------------------------------------


def _chunks(data: bytes) -> list[tuple[bytes, bytes, int]]:
    out, i = [], 8
    while i < len(data):
        n, kind = struct.unpack(">I4s", data[i:i + 8])
        body = data[i + 8:i + 8 + n]
        (crc,) = struct.unpack(">I", data[i + 8 + n:i + 12 + n])
        out.append((kind, body, crc))
        i += 12 + n
    return out


@pytest.mark.parametrize("dpi", [72.0, 300.0, 600.0, 1000.0 / 3])
def test_png_carries_dpi_and_pixels(tmp_path: Path, dpi: float) -> None:
    """Issue 2 item 6: the PNG's pHYs chunk (px/m, unit metre, right after IHDR, valid CRC)
    carries the dpi so printers print at true scale; read_png_dpi gets it back and
    cv2.imread decodes the same pixels."""
    image = render_sheet(opener(), 300).image
    path = tmp_path / "opener.png"
    write_png(path, image, dpi)
    assert read_png_dpi(path) == pytest.approx(dpi, abs=0.02)
    np.testing.assert_array_equal(cv2.imread(str(path), cv2.IMREAD_UNCHANGED), image)
    data = path.read_bytes()
    chunks = _chunks(data)
    assert [c[0] for c in chunks[:2]] == [b"IHDR", b"pHYs"]
    assert [c[0] for c in chunks].count(b"pHYs") == 1
    for kind, body, crc in chunks:
        assert zlib.crc32(kind + body) & 0xFFFFFFFF == crc, kind
    px, py, unit = struct.unpack(">IIB", chunks[1][1])
    assert px == py == round(dpi / INCH) and unit == 1


def test_png_colour_image_and_no_phys(tmp_path: Path) -> None:
    """Issue 2 item 6: colour images round-trip too; a PNG without pHYs reads as None and a
    file that is not a PNG is refused clearly."""
    rgb = np.dstack([np.arange(60, dtype=np.uint8).reshape(6, 10)] * 3)
    write_png(tmp_path / "c.png", rgb, 600)
    np.testing.assert_array_equal(cv2.imread(str(tmp_path / "c.png"), cv2.IMREAD_UNCHANGED),
                                  rgb)
    assert read_png_dpi(tmp_path / "c.png") == pytest.approx(600, abs=0.01)
    cv2.imwrite(str(tmp_path / "plain.png"), rgb)
    assert read_png_dpi(tmp_path / "plain.png") is None
    (tmp_path / "fake.png").write_bytes(b"GIF89a....")
    with pytest.raises(SheetError, match="not a PNG"):
        read_png_dpi(tmp_path / "fake.png")


def test_write_png_rejects_bad_input(tmp_path: Path) -> None:
    """Issue 2 item 6: bad dpi, bad images and a missing directory give clear errors and
    write nothing."""
    img = np.zeros((4, 4), np.uint8)
    with pytest.raises(SheetError, match="dpi"):
        write_png(tmp_path / "a.png", img, 10)
    with pytest.raises(SheetError, match="uint8"):
        write_png(tmp_path / "a.png", img.astype(np.float32), 300)
    with pytest.raises(FileNotFoundError, match="does not exist"):
        write_png(tmp_path / "missing" / "a.png", img, 300)
    assert list(tmp_path.iterdir()) == []


def _existing(tmp_path: Path) -> tuple[Path, bytes]:
    path = tmp_path / "sheet.png"
    write_png(path, np.full((5, 7), 200, np.uint8), 300)
    return path, path.read_bytes()


def test_failed_encode_leaves_existing_file(tmp_path: Path,
                                            monkeypatch: pytest.MonkeyPatch) -> None:
    """Issue 2 item 6 (atomic writes): an encoder failure leaves an existing file unchanged
    and no temporary file behind."""
    path, before = _existing(tmp_path)

    def boom(*args, **kwargs):
        raise RuntimeError("encoder exploded")

    monkeypatch.setattr(sheets.cv2, "imencode", boom)
    with pytest.raises(RuntimeError, match="exploded"):
        write_png(path, np.zeros((5, 7), np.uint8), 600)
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sheet.png"]


@pytest.mark.parametrize("fail", ["fsync", "replace"])
def test_failed_write_leaves_existing_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                           fail: str) -> None:
    """Issue 2 item 6 (atomic writes): a failure after the temporary file exists (fsync, or
    the final rename) leaves an existing file unchanged and removes the temporary file."""
    path, before = _existing(tmp_path)

    def boom(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(sheets.os, fail, boom)
    with pytest.raises(OSError, match="No space"):
        write_png(path, np.zeros((5, 7), np.uint8), 600)
    monkeypatch.undo()
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sheet.png"]
    assert read_png_dpi(path) == pytest.approx(300, abs=0.01)


def test_unwritable_target_leaves_it_unchanged(tmp_path: Path) -> None:
    """Issue 2 item 6 (atomic writes): a target that cannot be replaced (a directory in the
    way, or a read-only directory) raises and leaves what was there untouched."""
    in_the_way = tmp_path / "dir.png"
    in_the_way.mkdir()
    (in_the_way / "keep").write_text("x")
    with pytest.raises(OSError):
        write_png(in_the_way, np.zeros((3, 3), np.uint8), 300)
    assert (in_the_way / "keep").read_text() == "x"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dir.png"]

    if os.name == "posix" and os.geteuid() == 0:
        return  # root writes into read-only directories anyway
    path, before = _existing(tmp_path)
    tmp_path.chmod(0o500)
    try:
        with pytest.raises(PermissionError):
            write_png(path, np.zeros((5, 7), np.uint8), 600)
    finally:
        tmp_path.chmod(0o700)
    assert path.read_bytes() == before


def test_rewrite_replaces_file_and_keeps_mode(tmp_path: Path) -> None:
    """Issue 2 item 6: writing over an existing sheet replaces it whole and keeps its file
    permissions."""
    path, _ = _existing(tmp_path)
    path.chmod(0o640)
    new = np.full((2, 3), 7, np.uint8)
    write_png(path, new, 1200)
    np.testing.assert_array_equal(cv2.imread(str(path), cv2.IMREAD_UNCHANGED), new)
    assert read_png_dpi(path) == pytest.approx(1200, abs=0.01)
    assert path.stat().st_mode & 0o777 == 0o640
