"""The needle grasp G_TN (seed 002 §III.C, eq. 1) and the choice of a driving grasp."""

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from oralnav.control.errors import NeedleError
from oralnav.control.needle.drive import SutureGeometry, plan_drive, tissue_frame
from oralnav.control.needle.grasp import (
    R0,
    R_N8N,
    GraspSettings,
    eq1_as_printed,
    grasp_candidates,
    grasp_parameters,
    grasp_point_angle,
    grasp_transform,
    select_grasp,
)
from oralnav.control.needle.model import Needle

CT1 = Needle(radius=0.013)
R = CT1.radius


def _rot(axis, angle):
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler(axis, angle).as_matrix()
    return T


def _trans(x, y, z):
    T = np.eye(4)
    T[:3, 3] = x, y, z
    return T


def _random_params(rng, k=20):
    return [(rng.uniform(0, 0.005), *rng.uniform(-math.pi, math.pi, 3)) for _ in range(k)]


def test_eq1_printed_rotation_is_proper():
    """Eq. 1 as printed: R is a rotation (orthonormal, det +1) for random angles and is
    Rot_z(w1) Rot_y(w2) R0 Rot_y(w3)."""
    rng = np.random.default_rng(0)
    for _, w1, w2, w3 in _random_params(rng):
        Rp, _ = eq1_as_printed(0.0, w1, w2, w3, R)
        assert np.allclose(Rp.T @ Rp, np.eye(3), atol=1e-14)
        assert np.linalg.det(Rp) == pytest.approx(1.0)
        comp = (_rot("z", w1) @ _rot("y", w2))[:3, :3] @ R0 @ _rot("y", w3)[:3, :3]
        assert np.allclose(Rp, comp, atol=1e-14)


def test_eq1_printed_frame_and_theta0_row():
    """Eq. 1 as printed (the documented discrepancy): its frame N8 has its origin on the
    needle circle, centred at (r, 0, 0) in N8's x-z plane, so T's origin lies on that
    circle for any w1, w2, w3; its theta0 moves N8 along -x_T, not -z_T."""
    rng = np.random.default_rng(1)
    for t0, w1, w2, w3 in _random_params(rng):
        Rp, p = eq1_as_printed(0.0, w1, w2, w3, R)
        o = -Rp.T @ p                                  # T's origin in N8
        assert abs(o[1]) < 1e-15
        assert np.linalg.norm(o - [R, 0, 0]) == pytest.approx(R)
        _, p_t = eq1_as_printed(t0, w1, w2, w3, R)
        assert np.allclose(p_t - p, [-t0, 0, 0])


def test_eq1_is_rigid_and_jaw_point_on_arc():
    """Eq. 1 (corrected): G_TN is a rigid transform for random parameters; the jaw point
    (0, 0, -theta0) in T lies on the needle's arc at phi = w3, so at theta0 = 0 T's origin
    is on the arc, and theta0 moves that arc point along -z_T."""
    rng = np.random.default_rng(2)
    for t0, w1, w2, w3 in _random_params(rng):
        G = grasp_transform(t0, w1, w2, w3, R)
        assert np.allclose(G[:3, :3].T @ G[:3, :3], np.eye(3), atol=1e-14)
        assert np.linalg.det(G[:3, :3]) == pytest.approx(1.0)
        assert np.allclose(G[3], [0, 0, 0, 1])
        assert np.allclose(G @ np.append(CT1.point(w3), 1), [0, 0, -t0, 1], atol=1e-15)
        G0 = grasp_transform(0.0, w1, w2, w3, R)
        assert np.allclose(G0 @ np.append(CT1.point(w3), 1), [0, 0, 0, 1], atol=1e-15)
        assert np.allclose(G[:3, 3] - G0[:3, 3], [0, 0, -t0])
        assert np.allclose(G[:3, :3], G0[:3, :3])


def test_eq1_equals_composition():
    """Eq. 1 (corrected) is Trans(0, 0, -theta0) Rot_z(w1) Rot_y(w2) G0 Rot_zN(-w3), and
    its rotation is the printed R followed by the fixed change of axes N8 -> N."""
    G0 = np.array([[0, 0, 1, 0], [0, -1, 0, 0], [1, 0, 0, -R], [0, 0, 0, 1.0]])
    rng = np.random.default_rng(3)
    for t0, w1, w2, w3 in _random_params(rng):
        comp = _trans(0, 0, -t0) @ _rot("z", w1) @ _rot("y", w2) @ G0 @ _rot("z", -w3)
        G = grasp_transform(t0, w1, w2, w3, R)
        assert np.allclose(G, comp, atol=1e-15)
        assert np.allclose(G[:3, :3], eq1_as_printed(t0, w1, w2, w3, R)[0] @ R_N8N)


def test_w3_alone_moves_grasp_along_arc():
    """Eq. 1: w3 turns the needle about its own centre (the centre stays put in T) and
    w1, w2 leave the grasped arc point unchanged."""
    c = grasp_transform(0.001, 0.3, -0.8, 0.2, R)[:3, 3]
    for w3 in (0.5, 1.5, 2.5):
        assert np.allclose(grasp_transform(0.001, 0.3, -0.8, w3, R)[:3, 3], c)
    for w1, w2 in ((0.0, 0.0), (1.0, 2.0), (-2.5, 0.7)):
        G = grasp_transform(0.0, w1, w2, 1.1, R)
        assert grasp_point_angle(G, CT1) == pytest.approx(1.1)


def test_grasp_point_angle():
    """grasp_point_angle: the arc angle nearest the jaw point; clamped to the nearer end
    when the jaw point is off the needle's arc."""
    G = grasp_transform(0.002, 0.4, 1.0, 2.0, R)
    assert grasp_point_angle(G, CT1, depth=0.002) == pytest.approx(2.0)
    assert grasp_point_angle(grasp_transform(0, 0, 0, -0.3, R), CT1) == 0.0
    assert grasp_point_angle(grasp_transform(0, 0, 0, math.pi + 0.3, R), CT1) == CT1.arc


def test_grasp_parameters_round_trip():
    """grasp_parameters inverts eq. 1 (corrected) for random parameters, including the
    plane-containing-the-shaft case w2 = 0 where the circle crosses the gripper axis
    twice (the jaw side's nearest crossing is the grasp)."""
    rng = np.random.default_rng(4)
    params = _random_params(rng) + [(0.001, 0.3, 0.0, 0.9), (0.001, 0.3, math.pi, 0.9)]
    for t0, w1, w2, w3 in params:
        G = grasp_transform(t0, w1, w2, w3, R)
        fit = grasp_parameters(G, R)
        assert fit.offset < 1e-12 and fit.tilt < 1e-9
        assert fit.params.theta0 == pytest.approx(t0, abs=1e-12)
        assert fit.params.phi == pytest.approx(w3 % (2 * math.pi))
        assert np.allclose(fit.params.transform(R), G, atol=1e-12)


def test_grasp_parameters_reports_off_axis_grasp():
    """grasp_parameters: a pose that no eq. 1 grasp gives (needle shifted sideways in the
    jaws) is reported by its offset from the gripper axis."""
    G = _trans(0.0015, 0, 0) @ grasp_transform(0.001, 0.2, 1.0, 0.8, R)
    fit = grasp_parameters(G, R)
    assert 0.0005 < fit.offset <= 0.0015 + 1e-12


@pytest.mark.parametrize("args", [(0, 0, 0, 0, 0.0), (0, 0, math.nan, 0, R),
                                  (math.inf, 0, 0, 0, R)])
def test_grasp_transform_bad_input_refused(args):
    """Bad input: a zero radius or non-finite parameter."""
    with pytest.raises(NeedleError):
        grasp_transform(*args)


def _drive(depth=0.006, n=40):
    G_CS = tissue_frame([-0.02, 0.0, 0.12], [0.02, 0.0, 0.12], [0.0, 0.2, -1.0])
    G_PC = _trans(0.1, -0.05, 0.3) @ _rot("x", 2.8)
    return plan_drive(G_PC, G_CS, SutureGeometry.for_needle(CT1, depth), n)


@pytest.mark.parametrize("depth", [0.003, 0.006, 0.010])
def test_select_grasp_keeps_gripper_out_of_tissue(depth):
    """select_grasp: the chosen grasp lies in the arc band and, over the whole drive
    (eq. 3 poses mapped back to S independently), keeps the gripper tip and its shaft
    segment the clearance above the tissue and enters with the shaft rising."""
    s = GraspSettings()
    drive = _drive(depth)
    c = select_grasp(CT1, drive, s)
    assert s.swage_margin / R - 1e-12 <= c.phi <= CT1.arc - s.tip_margin / R
    G_PT = drive.with_grasp(c.G_TN).G_PT
    G_SP = np.linalg.inv(drive.G_PS)
    lowest = math.inf
    for T in G_PT:
        T_S = G_SP @ T
        for sl in np.linspace(0, s.shaft_length, 5):
            lowest = min(lowest, (T_S @ [0, 0, -sl, 1])[1])
    assert lowest >= s.clearance - 1e-12
    assert lowest == pytest.approx(min(c.min_tip_clearance, c.min_shaft_clearance))
    assert -(G_SP @ G_PT[0])[1, 2] >= math.sin(s.approach_elevation) - 1e-12
    drive.with_grasp(c.G_TN).approach_pose(0.005)    # the seed's approach along z works


def test_select_grasp_honours_reachable():
    """select_grasp: a reachable() that rejects one mid-drive pose of the unconstrained
    choice gives another grasp, all of whose poses it accepts."""
    drive = _drive()
    best = select_grasp(CT1, drive)
    mid = drive.with_grasp(best.G_TN).G_PT[len(drive.alphas) // 2]

    def reachable(T):
        return not np.allclose(T, mid, atol=1e-9)

    c = select_grasp(CT1, drive, reachable=reachable)
    assert not np.allclose(c.G_TN, best.G_TN)
    assert all(reachable(T) for T in drive.with_grasp(c.G_TN).G_PT)
    assert c.reach_checked >= 2 and c.score <= best.score + 1e-9


def test_select_grasp_feasible_set_matches_independent_check():
    """select_grasp: the candidates it counts feasible are exactly those whose gripper tip
    and shaft end (eq. 3 poses mapped to S) stay the clearance above the tissue over the
    whole drive, here with the elevation rules off so that the shaft check binds."""
    s = GraspSettings(min_shaft_elevation=-math.pi / 2, approach_elevation=-math.pi / 2,
                      shaft_length=0.012, jaw_length=0.005)
    drive = _drive(0.006, n=25)
    c = select_grasp(CT1, drive, s)
    G_SP = np.linalg.inv(drive.G_PS)
    feasible = 0
    for t0, w1, w2, w3 in grasp_candidates(CT1, drive, s):
        G_PT = drive.with_grasp(grasp_transform(t0, w1, w2, w3, R)).G_PT
        ys = [(G_SP @ T @ [0, 0, -sl, 1])[1] for T in G_PT for sl in (0.0, s.shaft_length)]
        feasible += min(ys) >= s.clearance
    assert c.feasible == feasible
    assert 0 < feasible < c.candidates


def test_select_grasp_refuses_unreachable():
    """select_grasp refuses when reachable() rejects every pose."""
    with pytest.raises(NeedleError, match="reachable"):
        select_grasp(CT1, _drive(), reachable=lambda T: False)


def test_select_grasp_refuses_margins_excluding_arc():
    """select_grasp refuses when the swage and tip margins leave no arc to grasp."""
    s = GraspSettings(swage_margin=0.02, tip_margin=0.021)
    with pytest.raises(NeedleError, match="leave nothing"):
        select_grasp(CT1, _drive(), s)


def test_select_grasp_refuses_band_inside_tissue():
    """select_grasp refuses when the only allowed grasp points end the drive in the
    tissue (swage margin beyond the arc that stays out)."""
    s = GraspSettings(swage_margin=0.018)
    with pytest.raises(NeedleError, match="out of the tissue"):
        select_grasp(CT1, _drive(0.006), s)


def test_select_grasp_refuses_impossible_clearance():
    """select_grasp refuses when no candidate keeps the gripper the clearance above the
    tissue for the whole drive."""
    with pytest.raises(NeedleError, match="within 20.00 mm"):
        select_grasp(CT1, _drive(), GraspSettings(clearance=0.02))


def test_select_grasp_refuses_other_needle():
    """select_grasp refuses a needle whose radius is not the drive's."""
    with pytest.raises(NeedleError, match="not the drive's"):
        select_grasp(Needle(radius=0.011), _drive())


@pytest.mark.parametrize("kw", [{"clearance": -0.001}, {"theta0_values": (0.02,)},
                                {"jaw_length": 0.05}, {"w2_steps": 0},
                                {"approach_elevation": 2.0}, {"w1_values": ()}])
def test_bad_grasp_settings_refused(kw):
    """Bad input: grasp settings out of their bounds."""
    with pytest.raises(NeedleError):
        GraspSettings(**kw)
