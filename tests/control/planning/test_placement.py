"""Placement of the feeding target (seed 004, §4: eqs. 13-22) and the paper's cylinder
case (Fig. 19, Table 2)."""

import math
from dataclasses import replace

import numpy as np
import pytest

from oralnav.control.errors import PlanningError
from oralnav.control.planning.fpsm import FPSM
from oralnav.control.planning.placement import (
    EQUATIONS,
    Hole,
    PlacementProblem,
    PlacementSettings,
    f_safe,
    hole_frame,
    line_safe_distances,
    place,
)
from oralnav.control.planning.pso import PSOSettings

CYL = FPSM.cylinder(0.05, 0.0, 0.1, 11, 15)
HOLE = Hole([0.0, -0.05, 0.05], [0.0, 1.0, 0.0])


def _place(equation=14, shrink_line2=True, seed=0, model=CYL, hole=HOLE, **kw):
    return place(model, hole, PlacementSettings(equation=equation, shrink_line2=shrink_line2,
                                                pso=PSOSettings(seed=seed), **kw))


def test_hole_frame_eq16():
    """Eqs. 15-17: z along the hole axis, x in the Center YZ plane with x_z >= 0, and a
    right-handed frame; the paper's axis (0, 1, 0) gives x = (0, 0, 1)."""
    T = hole_frame(HOLE)
    assert np.allclose(T[:3, 0], [0, 0, 1]) and np.allclose(T[:3, 2], [0, 1, 0])
    rng = np.random.default_rng(0)
    for _ in range(20):
        a = rng.normal(size=3)
        T = hole_frame(Hole([0, 0, 0], a))
        R = T[:3, :3]
        assert np.allclose(R.T @ R, np.eye(3)) and np.linalg.det(R) == pytest.approx(1)
        assert np.allclose(R[:, 2], a / np.linalg.norm(a))
        assert abs(R[0, 0]) < 1e-12 and R[2, 0] >= 0


def test_hole_frame_limit_and_refusals():
    """Eq. 16 at D_hz^(y) = 0 takes its limit; an axis along Center x or zero is refused."""
    T = hole_frame(Hole([0, 0, 0], [0.6, 0.0, 0.8]))
    assert np.allclose(T[:3, 0], [0, -1, 0])
    with pytest.raises(PlanningError, match="parallel to the Center x axis"):
        Hole([0, 0, 0], [1, 0, 0])
    with pytest.raises(PlanningError, match="zero"):
        Hole([0, 0, 0], [0, 0, 0])


def test_line_distances_in_a_cylinder():
    """Eqs. 10-12 on a line parallel to Z at 15.5 mm from the axis: every crossing ahead of
    the start is sampled and each is R - r - 15.5 mm."""
    d, m = line_safe_distances(CYL, [[0.0, 0.0155, 0.056]], [[0.0, 0.0, 1.0]], 0.006)
    assert m[0] == 5                      # slices at 60, 70, 80, 90, 100 mm
    vals = d[0][~np.isnan(d[0])]
    assert vals.size == 6 and np.allclose(vals, 0.05 - 0.006 - 0.0155)


def test_f_safe_eq13():
    """Eq. 13: weighted mean plus weighted minimum when clear, minimum only on collision."""
    d = np.array([[0.01, 0.02, 0.03, np.nan], [0.01, -0.002, 0.03, 0.04]])
    f = f_safe(d, 0.5, 0.5)
    assert f[0] == pytest.approx(0.5 * 0.02 + 0.5 * 0.01)
    assert f[1] == pytest.approx(0.5 * -0.002)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_cylinder_case_eq14(seed):
    """Table 2: eq. 14 gives d_T = 65.5 mm and theta_T = 0 on the 50 mm cylinder."""
    p = _place(seed=seed)
    assert p.d_T == pytest.approx(0.0655, abs=1e-5)
    assert p.theta_T == pytest.approx(0.0, abs=1e-4)
    assert p.collision_free and p.iterations > 40


def test_cylinder_case_eq21_is_flat_along_d():
    """Table 2's failure of eq. 21: at theta_T = 0 its value does not change with d_T while
    the two lines straddle the axis (50-81 mm), so the swarm stops anywhere in it."""
    prob = PlacementProblem(CYL, HOLE, PlacementSettings(equation=21))
    d = np.linspace(0.0505, 0.0805, 31)
    vals = prob.evaluate(np.stack([d, np.zeros_like(d)], axis=1))
    assert np.ptp(vals) < 1e-9
    found = {round(_place(21, seed=s).d_T, 4) for s in range(4)}
    assert len(found) > 1


def test_cylinder_case_eq22_converges_to_an_end():
    """Table 2's failure of eq. 22: it drives one line onto the cylinder's axis (81 mm in the
    paper; with both lines shrunk, 50 mm is the mirror optimum), never to 65.5 mm."""
    for seed in range(3):
        p = _place(22, seed=seed)
        assert min(abs(p.d_T - 0.081), abs(p.d_T - 0.050)) < 1e-4
    p = _place(22, shrink_line2=False)
    assert p.d_T == pytest.approx(0.081, abs=1e-4)


def test_paper_literal_line2_moves_the_optimum():
    """The paper's text (line2 on the unshrunk model) gives 62.5 mm in its own cylinder
    case, not its Table 2 answer: why line2 is shrunk by default."""
    assert _place(14, shrink_line2=False).d_T == pytest.approx(0.0625, abs=1e-5)


@pytest.mark.parametrize("equation", EQUATIONS)
@pytest.mark.parametrize("shrink_line2", [True, False])
def test_compiled_objective_matches_numpy(equation, shrink_line2):
    """The compiled objective the search runs is eqs. 13-14 (21, 22) as the numpy
    reference computes them: placements across and beyond the box, lines starting
    outside the slice range, lines parallel to the slices (no crossings)."""
    tilted = Hole([0.01, -0.04, 0.03], [0.2, 0.9, -0.3])
    rng = np.random.default_rng(3)
    x = np.column_stack([rng.uniform(-0.05, 0.2, 500), rng.uniform(-4, 4, 500)])
    x = np.vstack([x, [[0.05, math.pi / 2], [0.05, -math.pi / 2], [0.0, 0.0]]])
    for hole in (HOLE, tilted):
        prob = PlacementProblem(CYL, hole, PlacementSettings(equation=equation,
                                                             shrink_line2=shrink_line2))
        fast, ref = prob.evaluate(x), prob.evaluate_numpy(x)
        assert np.all(np.isfinite(fast))
        np.testing.assert_allclose(fast, ref, rtol=1e-12, atol=1e-12)


def test_pso_reaches_the_grid_optimum():
    """PSO's answer is at least as good as a dense grid's best."""
    prob = PlacementProblem(CYL, HOLE, PlacementSettings())
    d, th, F = prob.grid(241, 181)
    assert _place().objective <= F.min() + 1e-8   # within the stopping tolerance


def test_reproducible_with_a_seed():
    """Same seed, same placement."""
    a, b = _place(seed=7), _place(seed=7)
    assert (a.d_T, a.theta_T, a.iterations) == (b.d_T, b.theta_T, b.iterations)


def test_no_safe_placement_is_reported():
    """Bad input: a rod that cannot fit gives an explicit collision_free = False."""
    narrow = FPSM.cylinder(0.005, 0.0, 0.1, 11, 15)
    p = _place(model=narrow, hole=Hole([0, -0.005, 0.05], [0, 1, 0]))
    assert not p.collision_free
    assert p.to_dict()["collision_free"] is False


def test_hole_outside_the_model_is_refused():
    """Bad input: a hole beyond the slices or far outside the surface."""
    with pytest.raises(PlanningError, match="outside the model, whose slices span"):
        _place(hole=Hole([0, -0.05, 0.15], [0, 1, 0]))
    with pytest.raises(PlanningError, match="outside the model's surface"):
        _place(hole=Hole([0, -0.09, 0.05], [0, 1, 0]))


def test_settings_refused():
    """Bad input: unknown objective, empty search box."""
    with pytest.raises(PlanningError, match="equation"):
        PlacementSettings(equation=13)
    with pytest.raises(PlanningError, match="d_range"):
        PlacementSettings(d_range=(0.1, 0.0))


def test_tool_pose_puts_the_rod_on_line1():
    """Eq. 18-19: the returned tool frame's x axis is line1's direction and its origin is
    d_T along the hole axis."""
    p = _place()
    T = p.T_C_tool
    assert np.allclose(T[:3, 3], HOLE.position + p.d_T * HOLE.axis, atol=1e-12)
    c = math.cos(p.theta_T)
    assert np.dot(T[:3, 0], [0, 0, 1]) == pytest.approx(c)


def test_placement_time_is_small():
    """Target: placement <= 20 ms (measured in the bench; here a loose guard for a loaded
    CI machine)."""
    s = replace(PlacementSettings(), pso=PSOSettings(seed=0))
    place(CYL, HOLE, s)
    t = min(place(CYL, HOLE, s).time_ms for _ in range(3))
    assert t < 60.0


def test_cylinder_case_is_certified():
    """The paper's cylinder answer (65.5 mm) holds under certification: both lines are
    certified at least min_clearance clear, and the certified value is a lower bound of
    the exact clearance (the lines run along z 15.5 mm from the axis of the 50 mm
    cylinder: 50 - 15.5 - 6 = 28.5 mm, of which the check's 12 mm cap sees part)."""
    p = _place()
    assert p.certified and p.collision_free
    assert p.d_T == pytest.approx(0.0655, abs=2e-4)
    P1, P2, D = PlacementProblem(CYL, HOLE, PlacementSettings()).lines(
        np.array([[p.d_T, p.theta_T]]))
    for P, c in ((P1[0], p.clearance_line1), (P2[0], p.clearance_line2)):
        assert abs(D[0, 2]) == pytest.approx(1.0)           # along z: the distance is radial
        exact = 0.05 - math.hypot(P[0], P[1]) - 0.006
        assert 0.0005 <= c <= exact


@pytest.fixture(scope="module")
def mouth_scene():
    from importlib import resources
    from pathlib import Path

    from oralnav.config.planning import load_planning_scene
    from oralnav.control.planning.rod_check import RodCheck

    path = Path(str(resources.files("oralnav.config").joinpath(
        "examples/oral_cavity_case.toml")))
    scene = load_planning_scene(path)
    return scene, RodCheck(scene.model)


def _exact_line_clearances(scene, p):
    from oralnav.bench.planning import MeshOracle

    oracle = MeshOracle(scene.mesh)
    prob = PlacementProblem(scene.model, scene.hole, scene.settings)
    P1, P2, D = prob.lines(np.array([[p.d_T, p.theta_T]]))
    z_hi = scene.model.certificate.z_hi
    out = []
    for P in (P1[0], P2[0]):
        E = P + (z_hi - P[2]) / D[0, 2] * D[0]
        out.append(oracle.clearance(P, E) - scene.settings.rod_radius)
    return out


def test_mouth_placement_is_clear_of_the_mesh(mouth_scene):
    """Bad input / safety: in the parametric mouth the placement reported collision-free
    is clear of the mesh itself (python-fcl), by at least its certified clearance."""
    scene, check = mouth_scene
    p = place(scene.model, scene.hole, scene.settings, check)
    assert p.collision_free and p.certified
    assert min(p.clearance_line1, p.clearance_line2) >= scene.settings.min_clearance
    e1, e2 = _exact_line_clearances(scene, p)
    assert e1 >= p.clearance_line1 and e2 >= p.clearance_line2


def test_paper_search_alone_reports_a_colliding_placement(mouth_scene):
    """Why certification exists: with a 4 mm rod the paper's criterion (eq. 13 > 0 on both
    lines) accepts a placement that python-fcl finds cutting the mesh; the certified
    search reports no safe placement instead."""
    scene, check = mouth_scene
    s = replace(scene.settings, rod_radius=0.004)
    uncertified = FPSM(scene.model.z, scene.model.rho)      # same curves, no certificate
    paper = place(uncertified, scene.hole, s)
    assert paper.collision_free and not paper.certified
    scene4 = replace(scene, settings=s)
    assert min(_exact_line_clearances(scene4, paper)) < 0
    p = place(scene.model, scene.hole, s, check)
    assert not p.collision_free and "certified" in p.reason
