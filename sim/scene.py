"""What a simulated scene holds: a camera rig, marker fields placed in it, occluders and
the imaging settings. Built from a scene TOML file by ``oralnav.config.scene``.

All poses are in the rig's reference frame (``T_ref_field``), lengths in metres, angles
in radians, image levels in digital numbers (DN, 0..255 for mono8).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from oralnav.control.camera import Rig
from oralnav.control.markers import MarkerField


@dataclass(frozen=True)
class Imaging:
    """How pixels are formed; defaults give a clean, noise-free, unblurred image.

    Attributes:
        supersample: samples per pixel side (anti-aliasing by box filtering, 1..4).
        background: level of the empty scene at unit illumination (DN).
        white, black: levels of the sheet's white and black print at unit illumination (DN).
        body: level of an opener cylinder's bare surface where the sheet does not cover it.
        illumination_gradient: relative illumination change across the image width and
            height, (gx, gy): the illumination is ``1 + gx (u/W - 0.5) + gy (v/H - 0.5)``.
        blur_sigma_px: Gaussian optical blur (standard deviation, pixels); 0 for none.
        read_noise_dn: standard deviation of the signal-independent read noise (DN).
        shot_noise_gain: DN per photo-electron; shot-noise variance is ``gain * signal``.
        motion_samples: sub-exposure poses averaged for motion blur (1 = none).
        exposure: exposure time (s) over which velocities blur the image.
    """

    supersample: int = 2
    background: float = 40.0
    white: float = 220.0
    black: float = 20.0
    body: float = 150.0
    illumination_gradient: tuple[float, float] = (0.0, 0.0)
    blur_sigma_px: float = 0.0
    read_noise_dn: float = 0.0
    shot_noise_gain: float = 0.0
    motion_samples: int = 1
    exposure: float = 0.01

    @property
    def noisy(self) -> bool:
        return self.read_noise_dn > 0 or self.shot_noise_gain > 0


@dataclass(frozen=True, eq=False)
class Placement:
    """A marker field placed in the scene.

    ``velocity`` (m/s) and ``angular_velocity`` (rad/s, rotation vector rate) are in the
    reference frame and only matter for motion blur; the pose is the mid-exposure pose.
    """

    name: str
    field: MarkerField
    T_ref_field: np.ndarray
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    angular_velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))


@dataclass(frozen=True, eq=False)
class Rod:
    """An opaque straight rod (an instrument shaft) from ``p0`` to ``p1`` (reference frame,
    m) with ``radius`` (m), drawn at ``level`` DN."""

    name: str
    p0: np.ndarray
    p1: np.ndarray
    radius: float
    level: float = 90.0


@dataclass(frozen=True, eq=False)
class Blot:
    """A disc of ``radius`` (m) covering part of a field's printed face (blood, a stain),
    centred at ``center`` on the flat sheet (field x, y, m), drawn at ``level`` DN."""

    name: str
    placement: str
    center: tuple[float, float]
    radius: float
    level: float = 60.0


@dataclass(frozen=True, eq=False)
class Scene:
    """A complete scene: the rig, the placed fields, occluders, imaging and the seed."""

    rig: Rig
    placements: tuple[Placement, ...]
    rods: tuple[Rod, ...] = ()
    blots: tuple[Blot, ...] = ()
    imaging: Imaging = Imaging()
    seed: int = 0
    source: str = ""

    def placement(self, name: str) -> Placement:
        for p in self.placements:
            if p.name == name:
                return p
        raise KeyError(f"scene has no placement {name!r}; it has "
                       f"{[p.name for p in self.placements]}")
