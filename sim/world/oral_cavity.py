"""A parametric oral cavity held open by an opener: a test and demo stand-in for a scan.

No public oral-cavity mesh ships in a package, so planning tests and demos (the surrogate
model of the planning seed, section 3) run on this one. It models what a scene needs and
no more: the soft-tissue wall as one tube around the Z axis (palate dome on top, cheeks at
the sides, a tongue bulge on the floor that rises toward the back, the whole narrowing a
little toward the pharynx) and, optionally, the dental arches as rounded-box crowns that
stand 5-9 mm proud of the wall, the obstacles an instrument rod meets entering the mouth.

Frame ("Center", metres): Z runs along the cavity from the back (pharynx, ``z = 0``) to the
mouth opening (``z = depth``), pointing out of the mouth; y points up (cranial, toward the
palate); x = y cross z (lateral). Polar angles ``theta`` in a plane z = const are measured
from +x toward +y. The Z axis lies in free space for every z in (0, depth): every ray
from it in a plane z = const hits the wall or a tooth, and no tooth reaches into a central
corridor around it. Face normals point out of the tissue, into the free air.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import trimesh

__all__ = ["CORRIDOR_FRACTION", "Tooth", "dental_arches", "oral_cavity_mesh", "wall_radius"]

#: Teeth stay at least this fraction of ``min(width, height) / 2`` away from the Z axis, so
#: slice origins (on the axis) are always in free space.
CORRIDOR_FRACTION = 0.3

# Shape of the wall, as fractions. The front ring (z = depth) is the opener's ellipse,
# width x height; the back ring is _BACK_SCALE of it. The pinch narrows the diagonals
# (where the alveolar ridges are), which leaves a dome on top and cheeks at the sides.
# The tongue takes up to _TONGUE of the floor's radius at the back, none at the front.
_BACK_SCALE = 0.8
_PINCH = 0.06
_TONGUE = 0.5
_TONGUE_SIGMA = 0.55  # rad: half-width of the tongue bulge around the floor's centre line

# Dental arches of the reference mouth (width 55 mm, depth 90 mm); x scales with width and
# z with depth, crown sizes and protrusions stay in millimetres (teeth do not scale with
# how wide the opener holds the mouth). Side rows, front to back: 2 premolars, 3 molars;
# (mesio-distal length, bucco-lingual width, protrusion), metres.
_SIDE_TEETH = ((0.007, 0.008, 0.006), (0.007, 0.008, 0.006), (0.010, 0.009, 0.007),
               (0.010, 0.009, 0.007), (0.0095, 0.009, 0.0065))
_SIDE_FIRST_Z = 0.018  # front of the first premolar, measured back from z = depth
_SIDE_GAP = 0.001
_SIDE_X = 0.5  # fraction of width / 2 at which the side rows stand
# Incisors across the front: x centres (fraction of width / 2), mesio-distal length,
# labio-lingual thickness, protrusion; the row's centre is _INCISOR_Z behind the opening.
_INCISOR_X = (-0.38, -0.127, 0.127, 0.38)
_INCISOR_SIZE = (0.0065, 0.006, 0.008)
_INCISOR_Z = 0.008
_ROOT = 0.0015  # crowns reach this far past the wall, so no gap opens between them
_ROUNDING = 6.0  # superellipsoid exponent of a crown: a box with rounded edges


def wall_radius(theta: np.ndarray | float, z: np.ndarray | float, width: float = 0.055,
                height: float = 0.045, depth: float = 0.09) -> np.ndarray:
    """Radius of the tube wall from the Z axis, metres (vectorised, broadcasting).

    ``theta`` is the polar angle in a plane z = const (radians, from +x toward +y), ``z``
    the plane's height on the Z axis (metres, clipped to [0, depth]). At ``z = depth`` the
    wall reaches exactly ``width / 2`` at theta = 0 and pi and ``height / 2`` at theta =
    +-pi/2; everywhere else it lies inside that ellipse.
    """
    theta, z = np.broadcast_arrays(np.asarray(theta, dtype=float), np.asarray(z, dtype=float))
    u = np.clip(z / depth, 0.0, 1.0)  # 0 at the pharynx, 1 at the opening
    a, b = 0.5 * width, 0.5 * height
    c, s = np.cos(theta), np.sin(theta)
    ellipse = a * b / np.sqrt((b * c) ** 2 + (a * s) ** 2)
    pinch = 1.0 - _PINCH * np.sin(2.0 * theta) ** 2
    from_floor = np.mod(theta + 0.5 * np.pi + np.pi, 2.0 * np.pi) - np.pi
    tongue = _TONGUE * (1.0 - u) ** 1.5 * np.exp(-((from_floor / _TONGUE_SIGMA) ** 2))
    taper = _BACK_SCALE + (1.0 - _BACK_SCALE) * u
    return taper * ellipse * pinch * (1.0 - tongue)


@dataclass(frozen=True)
class Tooth:
    """One crown as an axis-aligned rounded box in the Center frame (metres).

    ``center`` (3,) and ``half_extents`` (3,) of its box; ``tip`` (3,) the centre of the
    face that points into the cavity (the occlusal or incisal edge); ``upper`` whether it
    hangs from the upper jaw (then it points -y).
    """

    name: str
    center: tuple[float, float, float]
    half_extents: tuple[float, float, float]
    tip: tuple[float, float, float]
    upper: bool


def _wall_y(x: np.ndarray, z: float, upper: bool, width: float, height: float,
            depth: float) -> np.ndarray:
    """Height y of the upper (or lower) wall above x at z: the polar wall read as y(x)."""
    t = np.linspace(0.01, np.pi - 0.01, 2001)
    theta = t if upper else -t
    r = wall_radius(theta, z, width, height, depth)
    xs, ys = r * np.cos(theta), r * np.sin(theta)
    order = np.argsort(xs)
    return np.interp(x, xs[order], ys[order])


def dental_arches(width: float = 0.055, height: float = 0.045,
                  depth: float = 0.09) -> tuple[Tooth, ...]:
    """The crowns of :func:`oral_cavity_mesh`: per jaw 4 incisors and 5 teeth per side.

    Crowns point vertically (upper ones down, lower ones up) as in a mouth held open; each
    reaches from ``_ROOT`` inside the wall to its protrusion (5-9 mm, measured at its centre)
    into the cavity, but never into the central corridor (see :data:`CORRIDOR_FRACTION`).
    Raises ``ValueError`` when the mouth is too small for crowns of at least 2 mm.
    """
    corridor = CORRIDOR_FRACTION * 0.5 * min(width, height)
    a = 0.5 * width
    # positions scale with the mouth; crowns only shrink (to fit a small one), never grow
    xs, zs = width / 0.055, depth / 0.09
    boxes: list[tuple[str, float, float, float, float, float]] = []
    # (name, x centre, x half-size, z centre, z half-size, protrusion): the footprint
    for k, x in enumerate(_INCISOR_X):
        length, thick, protrusion = _INCISOR_SIZE
        boxes.append((f"incisor{k + 1}", x * a, 0.5 * length * min(xs, 1.0),
                      depth - _INCISOR_Z * zs, 0.5 * thick * min(zs, 1.0), protrusion))
    for side, sign in (("right", -1.0), ("left", 1.0)):
        z_front = depth - _SIDE_FIRST_Z * zs
        for k, (length, wide, protrusion) in enumerate(_SIDE_TEETH):
            slot = (length + _SIDE_GAP) * zs
            name = f"premolar{k + 1}" if k < 2 else f"molar{k - 1}"
            boxes.append((f"{side}_{name}", sign * _SIDE_X * a, 0.5 * wide * min(xs, 1.0),
                          z_front - 0.5 * slot, 0.5 * length * min(zs, 1.0), protrusion))
            z_front -= slot
    teeth = []
    for upper in (True, False):
        sy = 1.0 if upper else -1.0
        for name, xc, hx, zc, hz, protrusion in boxes:
            # wall height over the footprint: the crown's root covers its highest point
            xs = np.array([xc - hx, xc, xc + hx])
            walls = np.concatenate([_wall_y(xs, zz, upper, width, height, depth)
                                    for zz in (zc - hz, zc, zc + hz)])
            root = sy * min(np.max(sy * walls) + _ROOT, 0.5 * height)
            centre_wall = _wall_y(np.array([xc]), zc, upper, width, height, depth)[0]
            tip = sy * max(sy * centre_wall - protrusion, corridor)
            if sy * (root - tip) < 0.002:
                raise ValueError(f"mouth {width * 1e3:.0f} x {height * 1e3:.0f} mm is too "
                                 "small for teeth; pass teeth=False")
            jaw = "upper" if upper else "lower"
            teeth.append(Tooth(name=f"{jaw}_{name}",
                               center=(xc, 0.5 * (root + tip), zc),
                               half_extents=(hx, 0.5 * abs(root - tip), hz),
                               tip=(xc, tip, zc), upper=upper))
    return tuple(teeth)


@functools.lru_cache(maxsize=8)
def _unit_sphere(count: int) -> tuple[np.ndarray, np.ndarray]:
    # a UV sphere's rings and meridians line up with the box's edges after the push-out
    sphere = trimesh.creation.uv_sphere(count=[count, count])
    return np.asarray(sphere.vertices, dtype=float), np.asarray(sphere.faces, dtype=np.int64)


def _rounded_box(center: np.ndarray, half: np.ndarray,
                 count: int) -> tuple[np.ndarray, np.ndarray]:
    """A closed rounded box: a UV sphere pushed out radially onto a superellipsoid, so it
    keeps the sphere's clean, watertight topology. Normals point outward."""
    d, faces = _unit_sphere(count)
    scale = np.sum(np.abs(d) ** _ROUNDING, axis=1) ** (-1.0 / _ROUNDING)
    return center + d * scale[:, None] * half, faces


def _tube(width: float, height: float, depth: float, n_theta: int, n_z: int,
          closed_front: bool) -> tuple[np.ndarray, np.ndarray]:
    theta = np.arange(n_theta) * (2.0 * np.pi / n_theta)
    z = np.linspace(0.0, depth, n_z)
    r = wall_radius(theta[None, :], z[:, None], width, height, depth)  # (n_z, n_theta)
    ring = np.stack([r * np.cos(theta), r * np.sin(theta),
                     np.broadcast_to(z[:, None], r.shape)], axis=-1).reshape(-1, 3)
    idx = np.arange(n_z * n_theta).reshape(n_z, n_theta)
    p0, p1 = idx[:-1], np.roll(idx[:-1], -1, axis=1)  # ring k: theta_i and theta_{i+1}
    q0, q1 = idx[1:], np.roll(idx[1:], -1, axis=1)    # ring k + 1
    # wound so that normals point toward the axis: out of the tissue, into the air
    faces = [np.stack([p0, q0, p1], -1).reshape(-1, 3), np.stack([p1, q0, q1], -1).reshape(-1, 3)]
    verts = [ring, np.array([[0.0, 0.0, 0.0]])]
    back = n_z * n_theta
    faces.append(np.stack([np.full(n_theta, back), idx[0], np.roll(idx[0], -1)], -1))
    if closed_front:
        verts.append(np.array([[0.0, 0.0, depth]]))
        faces.append(np.stack([np.full(n_theta, back + 1), np.roll(idx[-1], -1), idx[-1]], -1))
    return np.concatenate(verts), np.concatenate(faces)


def oral_cavity_mesh(width: float = 0.055, height: float = 0.045, depth: float = 0.09,
                     teeth: bool = True, closed_front: bool = False,
                     resolution: float = 1.0, missing: tuple[str, ...] = ()
                     ) -> trimesh.Trimesh:
    """A plausible oral cavity held open by an opener, as a triangle mesh in the Center
    frame (see the module docstring), metres.

    Args:
        width: lateral size of the mouth opening (x, cheek to cheek), metres.
        height: vertical size of the mouth opening (y, floor to palate), metres.
        depth: length of the cavity along Z, from the pharynx (z = 0) to the opening
            (z = depth), metres.
        teeth: add the dental arches, 28 crowns, each a separate closed component.
        closed_front: cap the opening too, so the whole mesh is watertight; by default the
            front is open (one boundary loop at z = depth), as a scan of an open mouth is.
        resolution: scales the face count (about 29 000 faces at 1.0, linear in it).
        missing: names of crowns to leave out (:func:`dental_arches`, e.g.
            ``"lower_left_molar1"``): the gap where an implant goes.

    The wall is a tube whose vertices lie exactly on :func:`wall_radius`, capped at the
    back; the bounding box is ``[-width/2, width/2] x [-height/2, height/2] x [0, depth]``.
    Deterministic. Raises ``ValueError`` for sizes outside 20-300 mm or a resolution that
    is not positive.
    """
    for name, v in (("width", width), ("height", height), ("depth", depth)):
        if not (np.isfinite(v) and 0.02 <= v <= 0.3):
            raise ValueError(f"{name} must be 0.02-0.3 m (an oral cavity), got {v!r}")
    if not (np.isfinite(resolution) and resolution > 0.0):
        raise ValueError(f"resolution must be positive, got {resolution!r}")
    # 2 n_theta (n_z - 1) tube faces; n_theta a multiple of 4 puts vertices at the extremes
    n_theta = max(4 * round(40.0 * np.sqrt(resolution)), 16)
    n_z = max(round(64.0 * np.sqrt(resolution)), 4)
    verts, faces = _tube(width, height, depth, n_theta, n_z, closed_front)
    parts_v, parts_f, offset = [verts], [faces], len(verts)
    if teeth:
        count = max(round(10.0 * np.sqrt(resolution)), 4)  # 320 faces a crown at 1.0
        crowns = dental_arches(width, height, depth)
        unknown = set(missing) - {t.name for t in crowns}
        if unknown:
            raise ValueError(f"no tooth named {sorted(unknown)}; the crowns are "
                             f"{', '.join(t.name for t in crowns)}")
        for tooth in crowns:
            if tooth.name in missing:
                continue
            v, f = _rounded_box(np.array(tooth.center), np.array(tooth.half_extents), count)
            parts_v.append(v)
            parts_f.append(f + offset)
            offset += len(v)
    return trimesh.Trimesh(np.concatenate(parts_v), np.concatenate(parts_f), process=False)
