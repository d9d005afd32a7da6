"""What a simulated scene holds: a camera rig, marker fields placed in it, occluders, the
needle-driving objects (needles, tissue pads, grippers) and the imaging settings. Built
from a scene TOML file by ``oralnav.config.scene``.

All poses are in the rig's reference frame (``T_ref_field``, ``T_ref_needle``...), lengths
in metres, angles in radians, image levels in digital numbers (DN, 0..255 for mono8).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from oralnav.control.needle.model import Needle
from oralnav.control.vision.camera import Rig
from oralnav.control.vision.markers import MarkerField


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
class NeedleObject:
    """A suture needle: a metallic torus segment, the wire (radius ``needle.wire_diameter``
    / 2) swept along ``needle``'s arc (frame N of ``oralnav.control.needle.model``: origin at the
    arc centre, x toward the base, y toward the body, z the arc's normal).

    ``T_ref_needle`` is the pose of N in the reference frame. Shading, lit from the camera
    (the endoscope's light is coaxial): ``level * (0.5 + 0.5 c) + specular * c**shininess``
    DN, where ``c`` is the cosine between the surface normal and the viewing ray (a dim
    metallic base plus a Blinn-Phong highlight, which for a light at the camera peaks
    where the normal faces the camera: bright streaks along the wire).

    Suture thread (``thread_length`` > 0; 0 = none): a dark strand of ``thread_diameter``
    (m) attached at the swage, the cue that tells base from tip (the arc's outline alone
    cannot, see ``control/needle/tracker.py``). Its shape is fixed in frame N, so it moves
    rigidly with the needle (:meth:`thread_points`). Drawn at ``thread_level`` DN with the
    rods' matt shading.
    """

    name: str
    needle: Needle
    T_ref_needle: np.ndarray
    level: float = 70.0
    specular: float = 180.0
    shininess: float = 20.0
    thread_length: float = 0.0
    thread_diameter: float = 0.0004
    thread_level: float = 45.0
    thread_bend_radius: float = 0.025
    thread_tilt: float = 0.0

    def thread_arc(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """The thread as a circular arc in frame N: ``(centre, e1, e2, angle)`` with its
        points ``centre + thread_bend_radius (cos a e1 + sin a e2)`` for ``a`` in ``[0,
        angle]`` (rad), ``a = 0`` at the base.

        Shape (a deterministic stand-in for a limp strand): the thread leaves the base
        along ``-tangent(0)`` (straight on from the arc, away from the body, N's ``-y``)
        and bends in the needle's plane with the fixed radius ``thread_bend_radius``, away
        from the arc's centre (toward N's ``+x``), so it never crosses the needle; ``angle
        = thread_length / thread_bend_radius``. ``thread_tilt`` (rad) turns that plane
        about N's x axis (through the base: the line from the arc's centre to it), its
        start bending ``thread_tilt`` out of the needle's plane toward N's ``+z``: a needle
        that rests on its ends, turned ``lift`` about its chord, has its thread lying on
        the surface with ``thread_tilt = lift``. No gravity, no contact otherwise: it goes
        where the pose puts it (into a pad, which hides that part).
        """
        rho = self.thread_bend_radius
        out = np.array([1.0, 0.0, 0.0])          # away from the arc's centre at the base
        centre = self.needle.base + rho * out
        start = -self.needle.tangent(0.0)
        c, s = math.cos(self.thread_tilt), math.sin(self.thread_tilt)
        # the start direction turned about x by -thread_tilt (N's y and z parts)
        start = np.array([start[0], c * start[1] + s * start[2], -s * start[1] + c * start[2]])
        return centre, -out, start, self.thread_length / rho

    def thread_points(self, n: int = 32) -> np.ndarray:
        """``n`` >= 2 points (n, 3) equally spaced along the thread's centreline, from the
        base to the free end, in frame N (m). Empty (0, 3) without a thread."""
        if self.thread_length <= 0:
            return np.zeros((0, 3))
        centre, e1, e2, angle = self.thread_arc()
        a = np.linspace(0.0, angle, max(int(n), 2))[:, None]
        return centre + self.thread_bend_radius * (np.cos(a) * e1 + np.sin(a) * e2)


@dataclass(frozen=True, eq=False)
class TissuePad:
    """A flat, light suturing pad with a dark straight incision line drawn on it.

    The pad's surface is the z = 0 plane of its frame (``T_ref_pad``), +z out of the
    tissue; it spans ``size`` = (x, y) extents (m) centred on the frame origin and is seen
    only from its +z side. The incision runs from ``incision[0]`` to ``incision[1]`` (pad
    x, y, m) with width ``incision_width`` (m, round ends), drawn at ``incision_level``.
    """

    name: str
    T_ref_pad: np.ndarray
    size: tuple[float, float] = (0.06, 0.04)
    level: float = 170.0
    incision: tuple[tuple[float, float], tuple[float, float]] = ((-0.025, 0.0), (0.025, 0.0))
    incision_width: float = 0.0008
    incision_level: float = 35.0


@dataclass(frozen=True, eq=False)
class Gripper:
    """A needle gripper (the paper's frame T, seed 002 Fig. 3): origin at the tip, y
    perpendicular to the jaws, z along the gripper toward the tip.

    Two jaws, boxes ``jaw_width`` (along x) by ``jaw_thickness`` (along y) by
    ``jaw_length`` (z from ``-jaw_length`` to 0), whose inner faces lie at y = +-opening/2
    (``opening`` = the needle's wire diameter holds it); and a shaft, a cylinder of
    ``shaft_radius`` along -z from ``z = -jaw_length`` for ``shaft_length``. Lengths in m.
    """

    name: str
    T_ref_tool: np.ndarray
    jaw_length: float = 0.010
    jaw_width: float = 0.0025
    jaw_thickness: float = 0.0012
    opening: float = 0.001
    shaft_radius: float = 0.003
    shaft_length: float = 0.05
    level: float = 110.0


@dataclass(frozen=True, eq=False)
class Scene:
    """A complete scene: the rig, the placed fields, occluders, the needle-driving objects,
    imaging and the seed."""

    rig: Rig
    placements: tuple[Placement, ...]
    rods: tuple[Rod, ...] = ()
    blots: tuple[Blot, ...] = ()
    imaging: Imaging = Imaging()
    seed: int = 0
    source: str = ""
    needles: tuple[NeedleObject, ...] = ()
    pads: tuple[TissuePad, ...] = ()
    grippers: tuple[Gripper, ...] = ()

    def placement(self, name: str) -> Placement:
        for p in self.placements:
            if p.name == name:
                return p
        raise KeyError(f"scene has no placement {name!r}; it has "
                       f"{[p.name for p in self.placements]}")

    def object_poses(self) -> dict[str, np.ndarray]:
        """The pose of every needle, pad and gripper in the reference frame, by name
        (``T_ref_needle``, ``T_ref_pad``, ``T_ref_tool``)."""
        out: dict[str, np.ndarray] = {}
        for n in self.needles:
            out[n.name] = n.T_ref_needle
        for p in self.pads:
            out[p.name] = p.T_ref_pad
        for g in self.grippers:
            out[g.name] = g.T_ref_tool
        return out
