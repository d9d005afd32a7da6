"""The suture needle's geometry: a circular arc of wire (seed 002, §III).

Needle frame ``N`` (seed 002, Fig. 3): the origin at the arc's centre, ``x`` toward the
needle's base (the swage, where the suture is attached), ``y`` toward its body, ``z = x × y``
normal to the needle's plane. A point of the arc at angle ``phi`` (rad, measured from ``x``
toward ``y``) is ``radius (cos phi, sin phi, 0)``: the base at ``phi = 0``, the tip at
``phi = arc`` (pi for the semicircular needles of the paper, e.g. Ethicon's CT-1, 26 mm
across, radius 13 mm).

Pure math, no I/O. Lengths in metres, angles in radians.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from oralnav.control.errors import NeedleError


@dataclass(frozen=True)
class Needle:
    """A circular needle: arc ``radius`` (m), ``wire_diameter`` (m) and the ``arc`` angle
    (rad, base to tip; pi for a semicircle)."""

    radius: float = 0.013
    wire_diameter: float = 0.001
    arc: float = math.pi

    def __post_init__(self) -> None:
        if not (math.isfinite(self.radius) and self.radius > 0):
            raise NeedleError(f"needle radius must be > 0 m, got {self.radius}")
        if not (math.isfinite(self.wire_diameter)
                and 0 < self.wire_diameter < self.radius):
            raise NeedleError(f"needle wire diameter must be > 0 and below the radius "
                              f"({self.radius} m), got {self.wire_diameter}")
        if not (math.isfinite(self.arc) and 0 < self.arc <= 2 * math.pi):
            raise NeedleError(f"needle arc must be in (0, 2 pi] rad, got {self.arc}")

    @property
    def length(self) -> float:
        """Arc length of the wire, base to tip (m)."""
        return self.radius * self.arc

    def point(self, phi: float | np.ndarray) -> np.ndarray:
        """Arc point(s) at angle(s) ``phi`` (rad) in frame N (m): (3,) or (..., 3)."""
        phi = np.asarray(phi, dtype=float)
        return self.radius * np.stack([np.cos(phi), np.sin(phi), np.zeros_like(phi)],
                                      axis=-1)

    def tangent(self, phi: float | np.ndarray) -> np.ndarray:
        """Unit tangent(s) at ``phi`` in frame N, pointing from the base toward the tip."""
        phi = np.asarray(phi, dtype=float)
        return np.stack([-np.sin(phi), np.cos(phi), np.zeros_like(phi)], axis=-1)

    def points(self, n: int) -> np.ndarray:
        """``n`` >= 2 points (n, 3) equally spaced along the arc, base first, tip last
        (frame N, m)."""
        if n < 2:
            raise NeedleError(f"an arc needs at least 2 sample points, got {n}")
        return self.point(np.linspace(0.0, self.arc, n))

    @property
    def base(self) -> np.ndarray:
        """The swage end (m, frame N)."""
        return self.point(0.0)

    @property
    def tip(self) -> np.ndarray:
        """The needle point (m, frame N)."""
        return self.point(self.arc)
