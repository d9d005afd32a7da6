"""Marker fields: ChArUco sheets on a plane, wrapped on a cylinder, or given as corner tables.

The field frame of a flat sheet is OpenCV's ``CharucoBoard`` frame: origin at the board's
outer corner, x along the first ``squares`` count, y along the second, z = x cross y
(pointing away from a camera that sees the printed face). Chessboard corner ids are
OpenCV's: corner ``j`` sits at ``((j % (nx-1) + 1) * square, (j // (nx-1) + 1) * square)``
on the flat sheet.

A cylinder field is the sheet wrapped, printed face outward, around a cylinder whose axis
is parallel to the field y axis: with ``xc`` the sheet's x centre and
``phi = (x - xc) / radius``, the flat point ``(x, y, 0)`` goes to
``(xc + radius sin phi, y, radius (1 - cos phi))``. A points field gives each corner's 3D
position directly (a reconstructed model). Lengths are metres.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from functools import cached_property
from typing import Literal

import cv2
import numpy as np

from oralnav.control.errors import MarkerFieldError


def aruco_dictionary(name: str) -> cv2.aruco.Dictionary:
    """Return OpenCV's predefined ArUco dictionary called ``name`` (e.g. ``"DICT_4X4_1000"``)."""
    value = getattr(cv2.aruco, name, None) if name.startswith("DICT_") else None
    if not isinstance(value, int):
        known = sorted(n for n in dir(cv2.aruco) if n.startswith("DICT_"))
        raise MarkerFieldError(
            f"unknown ArUco dictionary {name!r}; OpenCV has {', '.join(known)}")
    return cv2.aruco.getPredefinedDictionary(value)


@dataclass(frozen=True)
class PlaneSurface:
    """The sheet lies flat in the field's z = 0 plane."""

    kind: Literal["plane"] = "plane"


@dataclass(frozen=True)
class CylinderSurface:
    """The sheet is wrapped around a cylinder of ``radius`` (m), axis parallel to field y."""

    radius: float
    kind: Literal["cylinder"] = "cylinder"


@dataclass(frozen=True, eq=False)
class PointsSurface:
    """Each corner's 3D position in the field frame (m), keyed by chessboard corner id."""

    points: Mapping[int, tuple[float, float, float]]
    source: str = ""
    kind: Literal["points"] = "points"


Surface = PlaneSurface | CylinderSurface | PointsSurface


@dataclass(frozen=True, eq=False)
class MarkerField:
    """A self-identifying ChArUco marker field and its 3D model.

    Attributes:
        name: field name (``"opener"``, ``"robot"``, ``"effector"``...).
        dictionary: OpenCV predefined dictionary name.
        squares: squares along field x and along field y.
        square: square side (m).
        marker: ArUco marker side (m), smaller than ``square``.
        first_id: id of the field's first ArUco marker; ids run consecutively from it.
        surface: the shape the sheet takes.
    """

    name: str
    dictionary: str
    squares: tuple[int, int]
    square: float
    marker: float
    first_id: int = 0
    surface: Surface = PlaneSurface()
    family: Literal["charuco"] = "charuco"

    def __post_init__(self) -> None:
        where = f"field {self.name!r}"
        if self.family != "charuco":
            raise MarkerFieldError(f"{where}: family must be 'charuco', got {self.family!r}")
        nx, ny = (int(v) for v in self.squares)
        object.__setattr__(self, "squares", (nx, ny))
        if nx < 2 or ny < 2:
            raise MarkerFieldError(f"{where}: squares must be at least [2, 2], got {self.squares}")
        if not (np.isfinite(self.square) and self.square > 0):
            raise MarkerFieldError(f"{where}: square must be a positive length")
        if not (np.isfinite(self.marker) and 0 < self.marker < self.square):
            raise MarkerFieldError(
                f"{where}: marker ({self.marker}) must be positive and smaller than "
                f"square ({self.square})")
        dic = aruco_dictionary(self.dictionary)
        size = dic.bytesList.shape[0]
        if self.first_id < 0 or self.first_id + self.marker_count > size:
            raise MarkerFieldError(
                f"{where}: ids {self.first_id}..{self.first_id + self.marker_count - 1} "
                f"overflow {self.dictionary}, which has ids 0..{size - 1}")
        s = self.surface
        if isinstance(s, CylinderSurface):
            if not (np.isfinite(s.radius) and s.radius > 0):
                raise MarkerFieldError(f"{where}: cylinder radius must be positive")
            wrap = self.sheet_size[0] / s.radius
            if wrap > 2 * np.pi:
                raise MarkerFieldError(
                    f"{where}: cylinder radius {s.radius} m is too small for the sheet: "
                    f"a {self.sheet_size[0]} m wide sheet would wrap {np.degrees(wrap):.0f} deg "
                    f"(at most 360); radius must be >= {self.sheet_size[0] / (2 * np.pi):.6f} m")
        elif isinstance(s, PointsSurface):
            n = self.corner_count
            bad = [i for i in s.points if not 0 <= int(i) < n]
            if bad:
                raise MarkerFieldError(
                    f"{where}: corner ids {bad[:5]} are outside 0..{n - 1} of this board")
            if len(s.points) < 4:
                raise MarkerFieldError(f"{where}: a points surface needs at least 4 corners")
            pts = np.asarray(list(s.points.values()), dtype=float)
            if pts.shape[1:] != (3,) or not np.all(np.isfinite(pts)):
                raise MarkerFieldError(f"{where}: corner positions must be finite x, y, z")
        elif not isinstance(s, PlaneSurface):
            raise MarkerFieldError(f"{where}: unknown surface {s!r}")

    # -- board --------------------------------------------------------------------------
    @property
    def marker_count(self) -> int:
        """Number of ArUco markers on the board (one in every other square)."""
        return self.squares[0] * self.squares[1] // 2

    @property
    def marker_ids(self) -> np.ndarray:
        return np.arange(self.first_id, self.first_id + self.marker_count)

    @property
    def corner_count(self) -> int:
        """Number of chessboard corners of the flat board (all ids, known or not)."""
        return (self.squares[0] - 1) * (self.squares[1] - 1)

    @property
    def sheet_size(self) -> tuple[float, float]:
        """Flat sheet width (along x) and height (along y), metres."""
        return self.squares[0] * self.square, self.squares[1] * self.square

    @cached_property
    def board(self) -> cv2.aruco.CharucoBoard:
        """OpenCV's board of this field (flat, in metres), for detection and drawing."""
        return cv2.aruco.CharucoBoard(self.squares, self.square, self.marker,
                                      aruco_dictionary(self.dictionary), self.marker_ids)

    def board_image(self, px_per_square: int, border_bits: int = 1) -> np.ndarray:
        """The flat sheet as a mono8 image, ``px_per_square`` pixels per square, no margin.

        Square edges fall exactly on pixel boundaries: image pixel ``(row, col)`` covers the
        sheet area ``[col, col+1] x [row, row+1]`` times ``square / px_per_square``.
        """
        # Drawn here rather than with ``CharucoBoard.generateImage``: OpenCV 5.0 fails an ROI
        # assertion for some sizes (e.g. a 12 x 9 board at 13 px per square) and leaks a bare
        # cv2.error when the marker gets too few pixels. Each marker is centred in its square
        # with the margin rounded to whole pixels, so it sits within half a pixel of its model.
        where = f"field {self.name!r}"
        pps = int(px_per_square)
        if pps != px_per_square or pps < 4:
            raise MarkerFieldError(f"{where}: px_per_square must be an integer >= 4")
        if int(border_bits) != border_bits or border_bits < 1:
            raise MarkerFieldError(f"{where}: border_bits must be an integer >= 1")
        dic = self.board.getDictionary()
        margin = int(round(pps * (self.square - self.marker) / (2 * self.square)))
        side = pps - 2 * margin
        cells = dic.markerSize + 2 * int(border_bits)
        if side < cells:
            raise MarkerFieldError(
                f"{where}: px_per_square {pps} gives {side} px markers; a {dic.markerSize}x"
                f"{dic.markerSize} marker with {border_bits} border bits needs >= {cells} px")
        nx, ny = self.squares
        img = np.zeros((ny * pps, nx * pps), dtype=np.uint8)
        for ident, obj in zip(self.board.getIds(), self.board.getObjPoints(), strict=True):
            centre = np.asarray(obj, dtype=float).mean(axis=0)
            r0 = int(centre[1] // self.square) * pps
            c0 = int(centre[0] // self.square) * pps
            img[r0:r0 + pps, c0:c0 + pps] = 255
            img[r0 + margin:r0 + margin + side, c0 + margin:c0 + margin + side] = (
                cv2.aruco.generateImageMarker(dic, int(ident), side, borderBits=int(border_bits)))
        return img

    # -- corners ------------------------------------------------------------------------
    @cached_property
    def _flat_all(self) -> np.ndarray:
        nx, ny = self.squares
        j = np.arange(self.corner_count)
        return np.stack([(j % (nx - 1) + 1) * self.square,
                         (j // (nx - 1) + 1) * self.square], axis=1)

    @cached_property
    def corner_ids(self) -> np.ndarray:
        """Ids of the corners whose 3D position is known (all, except on a points field)."""
        if isinstance(self.surface, PointsSurface):
            return np.array(sorted(int(i) for i in self.surface.points), dtype=int)
        return np.arange(self.corner_count)

    @cached_property
    def corners_flat(self) -> np.ndarray:
        """Flat-sheet position (N x 2, m) of each corner in :attr:`corner_ids`."""
        return self._flat_all[self.corner_ids]

    @cached_property
    def corners(self) -> np.ndarray:
        """3D position (N x 3, field frame, m) of each corner in :attr:`corner_ids`."""
        if isinstance(self.surface, PointsSurface):
            pts = self.surface.points
            return np.array([pts[int(i)] for i in self.corner_ids], dtype=float)
        return self.sheet_to_field(self.corners_flat)

    @cached_property
    def corner_index(self) -> dict[int, int]:
        """Corner id -> row in :attr:`corners`."""
        return {int(c): k for k, c in enumerate(self.corner_ids)}

    @cached_property
    def neighbours(self) -> tuple[np.ndarray, ...]:
        """For each corner row, the rows of its known grid neighbours (8-connected).

        These are the model neighbours N(j) of the navigation paper's eq. 9.
        """
        nx = self.squares[0] - 1
        ny = self.squares[1] - 1
        out = []
        for cid in self.corner_ids:
            cx, cy = cid % nx, cid // nx
            rows = []
            for dy in (-1, 0, 1):
                for dx in (-1, 0, 1):
                    if (dx or dy) and 0 <= cx + dx < nx and 0 <= cy + dy < ny:
                        k = self.corner_index.get(int((cy + dy) * nx + cx + dx))
                        if k is not None:
                            rows.append(k)
            out.append(np.array(rows, dtype=int))
        return tuple(out)

    # -- surface map --------------------------------------------------------------------
    @property
    def renderable(self) -> bool:
        """Whether the sheet's shape is known everywhere (planes and cylinders)."""
        return not isinstance(self.surface, PointsSurface)

    def sheet_to_field(self, xy: np.ndarray) -> np.ndarray:
        """Map flat-sheet points (N x 2, m) to the field frame (N x 3, m)."""
        xy = np.asarray(xy, dtype=float)
        s = self.surface
        if isinstance(s, PlaneSurface):
            return np.concatenate([xy, np.zeros(xy.shape[:-1] + (1,))], axis=-1)
        if isinstance(s, CylinderSurface):
            xc = 0.5 * self.sheet_size[0]
            phi = (xy[..., 0] - xc) / s.radius
            return np.stack([xc + s.radius * np.sin(phi), xy[..., 1],
                             s.radius * (1 - np.cos(phi))], axis=-1)
        raise MarkerFieldError(
            f"field {self.name!r}: a points surface is known only at its corners")

    def sheet_normals(self, xy: np.ndarray) -> np.ndarray:
        """Outward normals (N x 3, field frame) of the printed face at flat-sheet points.

        They point toward a camera that sees the printed face, i.e. along -z on a plane.
        """
        xy = np.asarray(xy, dtype=float)
        s = self.surface
        if isinstance(s, PlaneSurface):
            n = np.zeros(xy.shape[:-1] + (3,))
            n[..., 2] = -1.0
            return n
        if isinstance(s, CylinderSurface):
            phi = (xy[..., 0] - 0.5 * self.sheet_size[0]) / s.radius
            return np.stack([np.sin(phi), np.zeros_like(phi), -np.cos(phi)], axis=-1)
        raise MarkerFieldError(
            f"field {self.name!r}: a points surface has no analytic normals")
