"""The parametric oral cavity (planning stand-in for a scan): a clean manifold tube with
the stated size, the Z axis in free space, teeth that are real obstacles, deterministic."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from oralnav.config.mesh import check_mesh
from oralnav.sim.world.oral_cavity import (
    CORRIDOR_FRACTION,
    dental_arches,
    oral_cavity_mesh,
    wall_radius,
)

W, H, D = 0.055, 0.045, 0.09
# planes between the tube's rings, from near the pharynx to near the opening
ZS = (0.004, 0.0231, 0.0412, 0.0598, 0.0705, 0.0821, 0.0877)


@pytest.fixture(scope="module")
def cavity() -> trimesh.Trimesh:
    return oral_cavity_mesh()


@pytest.fixture(scope="module")
def bare() -> trimesh.Trimesh:
    return oral_cavity_mesh(teeth=False)


def _edge_counts(mesh: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray]:
    return np.unique(np.sort(mesh.edges, axis=1), axis=0, return_counts=True)


def free_radius(mesh: trimesh.Trimesh, z: float, angles: np.ndarray) -> np.ndarray:
    """Distance from (0, 0, z) along each in-plane ray (angle from +x toward +y) to the
    first surface it meets; inf where it meets none. Exact on the mesh's section."""
    seg = trimesh.intersections.mesh_plane(mesh, [0.0, 0.0, 1.0], [0.0, 0.0, z])[:, :, :2]
    p, e = seg[:, 0], seg[:, 1] - seg[:, 0]
    d = np.stack([np.cos(angles), np.sin(angles)], axis=1)

    def cross(a, b):
        return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]

    den = cross(d[:, None, :], e[None])  # (rays, segments)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = cross(p[None], e[None]) / den
        t = cross(p[None], d[:, None, :]) / den
    hit = (np.abs(den) > 1e-15) & (s > 0) & (t >= -1e-9) & (t <= 1 + 1e-9)
    return np.where(hit, s, np.inf).min(axis=1)


def test_default_mesh_is_a_clean_manifold(cavity):
    """Every edge has exactly two faces except the open front's loop; about 30 000 faces
    (the paper's mesh size); check_mesh accepts it with nothing to repair."""
    edges, counts = _edge_counts(cavity)
    assert set(np.unique(counts)) == {1, 2}
    boundary = edges[counts == 1]
    np.testing.assert_allclose(cavity.vertices[boundary.ravel(), 2], D, atol=1e-12)
    assert 20_000 <= len(cavity.faces) <= 40_000
    report = check_mesh(cavity.copy(), "generated")
    assert report.removed_degenerate == 0 and report.merged_vertices == 0
    assert report.components == 1 + 28 and report.faces == len(cavity.faces)


@pytest.mark.parametrize("size", [(W, H, D), (0.045, 0.05, 0.07), (0.02, 0.02, 0.02),
                                  (0.3, 0.3, 0.3)])
def test_bounded_by_the_stated_size(size):
    """The bounding box is [-w/2, w/2] x [-h/2, h/2] x [0, depth], teeth included."""
    w, h, d = size
    for teeth in (False, True):
        mesh = oral_cavity_mesh(w, h, d, teeth=teeth)
        np.testing.assert_allclose(mesh.bounds, [[-w / 2, -h / 2, 0.0], [w / 2, h / 2, d]],
                                   atol=1e-12)


@pytest.mark.parametrize("teeth", [False, True])
def test_watertight_iff_closed_front(teeth):
    """Open front: one boundary loop, every tooth closed; closed_front: watertight."""
    open_mesh = oral_cavity_mesh(teeth=teeth)
    closed = oral_cavity_mesh(teeth=teeth, closed_front=True)
    assert not open_mesh.is_watertight and closed.is_watertight
    assert set(np.unique(_edge_counts(closed)[1])) == {2}
    # the open mesh's boundary is the front ring only, so every tooth is watertight
    edges, counts = _edge_counts(open_mesh)
    assert np.all(open_mesh.vertices[edges[counts == 1].ravel(), 2] == D)
    assert closed.body_count == (29 if teeth else 1)
    if teeth:
        for tooth in trimesh.Trimesh(closed.vertices, closed.faces).split(
                only_watertight=False)[1:]:
            assert tooth.is_watertight and tooth.volume > 0


@pytest.mark.parametrize("teeth", [False, True])
def test_every_ray_from_the_z_axis_hits_the_mesh(teeth, cavity, bare):
    """Slice origins on the Z axis are in free space: every in-plane ray hits the mesh,
    no closer than the central corridor."""
    mesh = cavity if teeth else bare
    angles = np.linspace(0.0, 2.0 * np.pi, 360, endpoint=False) + 0.001
    corridor = CORRIDOR_FRACTION * 0.5 * min(W, H)
    for z in ZS:
        r = free_radius(mesh, z, angles)
        assert np.all(np.isfinite(r)), z
        assert r.min() >= min(corridor, 0.9 * wall_radius(angles, z).min()), z


def test_teeth_stay_out_of_the_corridor():
    """No tooth vertex comes closer to the Z axis than the corridor."""
    for w, h, d in ((W, H, D), (0.04, 0.035, 0.07), (0.07, 0.06, 0.12), (0.02, 0.02, 0.02)):
        mesh = oral_cavity_mesh(w, h, d)
        tube = oral_cavity_mesh(w, h, d, teeth=False)
        teeth = mesh.vertices[len(tube.vertices):]  # the crowns follow the tube
        assert np.linalg.norm(teeth[:, :2], axis=1).min() >= CORRIDOR_FRACTION * min(w, h) / 2


def test_wall_vertices_lie_on_wall_radius(bare):
    """The tube's vertices are exactly on wall_radius; between them the section stays
    within 0.3 mm of it."""
    v = bare.vertices
    r = np.linalg.norm(v[:, :2], axis=1)
    on_axis = r == 0.0
    assert on_axis.sum() == 1  # the back cap's centre
    np.testing.assert_allclose(r[~on_axis], wall_radius(np.arctan2(v[~on_axis, 1],
                                                                   v[~on_axis, 0]),
                                                        v[~on_axis, 2]), rtol=1e-12)
    angles = np.linspace(0.0, 2.0 * np.pi, 500, endpoint=False)
    for z in ZS:
        np.testing.assert_allclose(free_radius(bare, z, angles), wall_radius(angles, z),
                                   atol=3e-4)


def test_wall_radius_shape():
    """wall_radius broadcasts; the palate is above the tongue, the back narrower than the
    front, the tongue rises toward the back, the opening is the width x height ellipse."""
    th = np.array([0.0, np.pi / 2, np.pi, -np.pi / 2])
    np.testing.assert_allclose(wall_radius(th, D), [W / 2, H / 2, W / 2, H / 2])
    assert wall_radius(th[:, None], np.array([0.0, D / 2, D])).shape == (4, 3)
    floor = wall_radius(-np.pi / 2, np.array([0.0, 0.03, 0.06, D]))
    assert np.all(np.diff(floor) > 0)  # the floor drops toward the opening
    assert wall_radius(np.pi / 2, 0.0) > wall_radius(-np.pi / 2, 0.0)
    assert wall_radius(0.0, 0.0) < wall_radius(0.0, D)


def test_teeth_reduce_the_free_radius_where_they_stand(cavity, bare):
    """Each crown stands 5-9 mm proud of the wall: toward its tip, the free radius with
    teeth is at least 4 mm shorter than the wall's, and the ray stops at the tip."""
    for tooth in dental_arches():
        x, y, z = tooth.tip
        angle = np.array([np.arctan2(y, x)])
        with_teeth = free_radius(cavity, z, angle)[0]
        without = free_radius(bare, z, angle)[0]
        assert without - with_teeth >= 0.004, tooth.name
        assert with_teeth == pytest.approx(np.hypot(x, y), abs=5e-4), tooth.name


def test_some_sections_are_not_star_shaped(cavity):
    """Beside every side crown there is free air the axis cannot see (the vestibule between
    crown and cheek): those sections are not star-shaped about the slice origin."""
    side = [t for t in dental_arches() if "incisor" not in t.name]
    assert len(side) == 20
    for tooth in side:
        cx, _, cz = tooth.center
        hx = tooth.half_extents[0]
        up = 1.0 if tooth.upper else -1.0
        # points 0.5 mm outside the crown's cheek-side face, 1-3 mm from its tip rootward
        x = cx + np.sign(cx) * (hx + 0.0005)
        y = tooth.tip[1] + up * np.array([0.001, 0.002, 0.003])
        angle, dist = np.arctan2(y, x), np.hypot(x, y)
        free = dist < wall_radius(angle, cz)  # inside the wall, beside the crown: free air
        hidden = free_radius(cavity, cz, angle) < dist - 1e-4
        assert np.any(free & hidden), tooth.name


def test_resolution_scales_the_face_count():
    """resolution scales the face count about linearly."""
    base = len(oral_cavity_mesh().faces)
    for res in (0.25, 0.5, 2.0):
        ratio = len(oral_cavity_mesh(resolution=res).faces) / base
        assert 0.75 * res <= ratio <= 1.25 * res, res


def test_deterministic():
    """Two calls give the same mesh, bit for bit."""
    a, b = oral_cavity_mesh(), oral_cavity_mesh()
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.faces, b.faces)


def test_normals_point_into_the_free_air(bare, cavity):
    """Wall normals point toward the axis (out of the tissue), crowns' outward."""
    c, n = bare.triangles_center, bare.face_normals
    side = c[:, 2] > 0.0
    assert np.all(np.sum(n[side, :2] * c[side, :2], axis=1) < 0.0)
    assert np.all(n[~side, 2] > 0.99)  # the back cap faces the opening
    teeth = cavity.faces[len(bare.faces):]
    assert trimesh.Trimesh(cavity.vertices, teeth).volume > 0


@pytest.mark.parametrize("kwargs", [{"width": 0.0}, {"height": float("nan")},
                                    {"depth": 1.0}, {"resolution": 0.0}])
def test_bad_parameters_are_refused(kwargs):
    """Sizes outside 20-300 mm, non-finite values and a non-positive resolution raise."""
    with pytest.raises(ValueError, match=next(iter(kwargs))):
        oral_cavity_mesh(**kwargs)
