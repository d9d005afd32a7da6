"""Virtual fixture (seed 004, section 2.2): the cone segments and final cylinder around the
planned axis, their signed distance, projection, wall force and axial guidance."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from oralnav.control.errors import GeometryError, PlanningError
from oralnav.control.guidance.virtual_fixture import VirtualFixture

MM = 1e-3
# Along +z from the origin: a 1 mm x 20 mm cylinder, then a cone to 3 mm over 10 mm,
# then a cone to 13 mm over 20 mm (slope 0.5), which goes on beyond 50 mm.
CONES = [(10 * MM, 3 * MM), (20 * MM, 13 * MM)]


def _fixture(blend: float = 0.0) -> VirtualFixture:
    return VirtualFixture.from_axis([0, 0, 0], [0, 0, 2.0], 1 * MM, 20 * MM, CONES,
                                    guidance_blend=blend)


def _random_points(rng: np.random.Generator, n: int) -> np.ndarray:
    s = rng.uniform(-10 * MM, 80 * MM, n)
    r = rng.uniform(0.0, 40 * MM, n)
    a = rng.uniform(0, 2 * math.pi, n)
    return np.stack([r * np.cos(a), r * np.sin(a), s], axis=1)


def test_profile_radii_at_segment_boundaries_and_beyond() -> None:
    """Profile geometry: the cylinder radius up to its mouth, each cone's end radius at its
    end, linear in between, and the last cone goes on with its slope."""
    fx = _fixture()
    assert fx.breakpoints == pytest.approx((20 * MM, 30 * MM, 50 * MM))
    assert fx.length == pytest.approx(50 * MM)
    expected = {0.0: 1, 10 * MM: 1, 20 * MM: 1, 25 * MM: 2, 30 * MM: 3, 40 * MM: 8,
                50 * MM: 13, 60 * MM: 18, 100 * MM: 38}
    for s, r_mm in expected.items():
        assert fx.allowed_radius(s) == pytest.approx(r_mm * MM, abs=1e-15), s
    assert fx.allowed_radius(-5 * MM) == pytest.approx(1 * MM)


def test_profile_is_continuous_and_never_narrows_outward() -> None:
    """Profile continuity: no jump at any segment boundary; radii non-decreasing outward."""
    fx = _fixture()
    for b in fx.breakpoints:
        eps = 1e-9
        assert abs(fx.allowed_radius(b + eps) - fx.allowed_radius(b - eps)) < 1e-8
    s = np.linspace(0, 0.2, 2001)
    r = np.array([fx.allowed_radius(x) for x in s])
    assert np.all(np.diff(r) >= 0)


def test_cylinder_only_fixture_goes_on_as_a_cylinder() -> None:
    """Without cone segments the cylinder is the whole (open-ended) fixture."""
    fx = VirtualFixture.from_axis([0, 0, 0], [1, 0, 0], 2 * MM, 10 * MM)
    assert fx.allowed_radius(1.0) == pytest.approx(2 * MM)
    assert fx.breakpoints == pytest.approx((10 * MM,))


@pytest.mark.parametrize(("point_mm", "axial_mm", "dist_mm"), [
    ((0.5, 0, 10), 10, 0.5),             # in the cylinder, 0.5 mm from its wall
    ((0, 0, 10), 10, 1.0),               # on the axis
    ((0, 1.5, 10), 10, -0.5),            # outside the cylinder by 0.5 mm
    ((3, 4, 40), 40, 3.0),               # in the second cone (R = 8 mm), r = 5 mm
    ((0, 10, 40), 40, -2.0),             # outside the second cone by 2 mm
    ((0, 0, -2), -2, -2.0),              # past the target on the axis
    ((0.5, 0, -2), -2, -2.0),            # past the target within the cylinder radius
    ((4, 0, -3), -3, -math.hypot(3, 3)),  # past the target and off the cylinder
])
def test_signed_distance_on_hand_computed_points(point_mm, axial_mm, dist_mm) -> None:
    """Signed distance: positive radial margin inside, negative penetration outside (radial
    for s >= 0, to the target's disc behind the target); axial position signed."""
    fx = _fixture()
    p = np.array(point_mm) * MM
    assert fx.axial(p) == pytest.approx(axial_mm * MM, abs=1e-15)
    assert fx.boundary_distance(p) == pytest.approx(dist_mm * MM, abs=1e-15)
    assert fx.contains(p) == (dist_mm >= 0)


def test_queries_do_not_depend_on_where_the_axis_lies() -> None:
    """Frame: a rigidly moved fixture gives the same axial positions and distances for the
    moved points (the caller's points and the fixture share one frame)."""
    rng = np.random.default_rng(5)
    R = Rotation.random(random_state=rng).as_matrix()
    t = rng.uniform(-0.1, 0.1, 3)
    a = _fixture()
    b = VirtualFixture.from_axis(t, R @ [0, 0, 1], 1 * MM, 20 * MM, CONES)
    for p in _random_points(rng, 200):
        q = R @ p + t
        assert b.axial(q) == pytest.approx(a.axial(p), abs=1e-12)
        assert b.boundary_distance(q) == pytest.approx(a.boundary_distance(p), abs=1e-12)
        np.testing.assert_allclose(b.project(q), R @ a.project(p) + t, atol=1e-12)


def test_projection_is_inside_idempotent_and_identity_inside() -> None:
    """Projection: lands in the allowed region, never past the target, is idempotent, and
    leaves allowed points where they are; radially it keeps the direction."""
    fx = _fixture()
    rng = np.random.default_rng(1)
    for p in _random_points(rng, 500):
        q = fx.project(p)
        assert fx.boundary_distance(q) >= -1e-15
        assert fx.axial(q) >= 0.0
        np.testing.assert_allclose(fx.project(q), q, atol=1e-15)
        if fx.contains(p):
            np.testing.assert_array_equal(q, p)
        q2 = fx.project(p, margin=0.5 * MM)
        assert fx.boundary_distance(q2) >= -0.5 * MM - 1e-15
        np.testing.assert_allclose(fx.project(q2, margin=0.5 * MM), q2, atol=1e-15)
    np.testing.assert_allclose(fx.project(np.array([4, 0, -3]) * MM), [1 * MM, 0, 0],
                               atol=1e-15)
    np.testing.assert_allclose(fx.project(np.array([0, 10, 40]) * MM), [0, 8 * MM, 40 * MM],
                               atol=1e-15)


def test_in_cylinder() -> None:
    """in_cylinder: inside the final cylinder only (axially 0..L, radially <= r_cyl)."""
    fx = _fixture()
    assert fx.in_cylinder(np.array([0.5, 0, 10]) * MM)
    assert not fx.in_cylinder(np.array([1.5, 0, 10]) * MM)
    assert not fx.in_cylinder(np.array([0, 0, 25]) * MM)
    assert not fx.in_cylinder(np.array([0, 0, -1]) * MM)


def test_force_is_zero_inside_and_restoring_outside() -> None:
    """Wall force: zero inside; outside a spring (k * depth) toward the allowed region,
    including the end stop past the target; damping only against going deeper."""
    fx = _fixture()
    k, c = 1000.0, 50.0
    rng = np.random.default_rng(2)
    for p in _random_points(rng, 300):
        v = rng.normal(0, 0.05, 3)
        f = fx.fixture_force(p, v, k, c)
        depth = -fx.boundary_distance(p)
        if depth <= 0:
            np.testing.assert_array_equal(f, 0.0)
            continue
        to_region = fx.project(p) - p
        n = to_region / np.linalg.norm(to_region)
        assert np.linalg.norm(np.cross(f, n)) < 1e-9 * max(1.0, np.linalg.norm(f))
        going_deeper = max(0.0, -(v @ n))
        assert f @ n == pytest.approx(k * depth + c * going_deeper, rel=1e-9)
    # hand-computed: 2 mm out of the second cone along +y, at rest -> 2 N along -y
    np.testing.assert_allclose(fx.fixture_force(np.array([0, 10, 40]) * MM, [0, 0, 0], k, c),
                               [0, -2.0, 0], atol=1e-12)
    # end stop: 2 mm past the target -> pushed back out along +z; moving back in: no pull
    np.testing.assert_allclose(fx.fixture_force(np.array([0, 0, -2]) * MM, [0, 0, 0.1], k, c),
                               [0, 0, 2.0], atol=1e-12)
    np.testing.assert_allclose(fx.fixture_force(np.array([0, 0, -2]) * MM, [0, 0, -0.1], k, c),
                               [0, 0, 2.0 + 5.0], atol=1e-12)


def test_guidance_keeps_only_axial_motion_in_the_cylinder() -> None:
    """Guidance: in the cylinder only the axial component survives; past the blend the
    velocity is free; within the blend the lateral part is removed in proportion."""
    fx = _fixture(blend=4 * MM)
    v = np.array([0.01, -0.02, 0.03])
    np.testing.assert_allclose(fx.guidance(np.array([0.2, 0, 10]) * MM, v), [0, 0, 0.03],
                               atol=1e-15)
    np.testing.assert_allclose(fx.guidance(np.array([0, 0, 40]) * MM, v), v, atol=1e-15)
    np.testing.assert_allclose(fx.guidance(np.array([0, 0, 22]) * MM, v),
                               [0.005, -0.01, 0.03], atol=1e-15)
    assert fx.guidance_weight(10 * MM) == 1.0
    assert fx.guidance_weight(22 * MM) == pytest.approx(0.5)
    assert fx.guidance_weight(24 * MM) == 0.0
    assert _fixture().guidance_weight(20.0001 * MM) == 0.0


def test_direction_is_normalised() -> None:
    """Construction: a non-unit direction is normalised (and the arrays are read-only)."""
    fx = VirtualFixture.from_axis([1, 2, 3], [0, 3, 4], 1 * MM, 10 * MM)
    np.testing.assert_allclose(fx.direction, [0, 0.6, 0.8])
    assert not fx.direction.flags.writeable and not fx.target.flags.writeable


@pytest.mark.parametrize(("kwargs", "names"), [
    ({"direction": [0, 0, 0]}, "direction"),
    ({"direction": [0, np.nan, 1]}, "direction"),
    ({"target": [0, 0, np.inf]}, "target"),
    ({"target": [0, 0]}, "target"),
    ({"cylinder_radius": 0.0}, "cylinder_radius"),
    ({"cylinder_radius": -1e-3}, "cylinder_radius"),
    ({"cylinder_length": 0.0}, "cylinder_length"),
    ({"cylinder_length": math.nan}, "cylinder_length"),
    ({"cones": [(0.0, 3e-3)]}, "cones[0] length"),
    ({"cones": [(-0.01, 3e-3)]}, "cones[0] length"),
    ({"cones": [(0.01, 0.5e-3)]}, "cones[0] end_radius"),
    ({"cones": [(0.01, 3e-3), (0.01, 2e-3)]}, "cones[1] end_radius"),
    ({"cones": [(0.01, math.inf)]}, "cones[0] end_radius"),
    ({"cones": [(0.01,)]}, "cones[0]"),
    ({"guidance_blend": -1e-3}, "guidance_blend"),
])
def test_bad_fixtures_are_refused_with_the_parameter_named(kwargs, names) -> None:
    """Validation: zero/non-finite direction, non-finite values, non-positive lengths and
    radii, radii decreasing outward are refused with PlanningError naming the parameter."""
    args = {"target": [0, 0, 0], "direction": [0, 0, 1], "cylinder_radius": 1e-3,
            "cylinder_length": 0.02, "cones": CONES}
    args.update(kwargs)
    with pytest.raises(PlanningError, match=names.replace("[", r"\[").replace("]", r"\]")):
        VirtualFixture.from_axis(**args)


def test_bad_query_points_are_refused() -> None:
    """Queries: a point that is not a finite 3-vector raises GeometryError."""
    fx = _fixture()
    with pytest.raises(GeometryError):
        fx.boundary_distance([0, 0])
    with pytest.raises(GeometryError):
        fx.project([0, np.nan, 0])
