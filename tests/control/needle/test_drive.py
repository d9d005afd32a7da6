"""Needle drive and pull (seed 002 §III.E-F, eqs. 2-4): tissue frame, suture geometry,
eq. 3's gripper poses, the approach and the pull."""

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from oralnav.control.errors import NeedleError
from oralnav.control.needle.drive import (
    G_SN,
    SutureGeometry,
    drive_poses,
    plan_drive,
    pull_poses,
    regrasp_pose,
    swage_exit_turn,
    tissue_frame,
)
from oralnav.control.needle.grasp import grasp_transform
from oralnav.control.needle.model import Needle

CT1 = Needle(radius=0.013)
DEPTHS = [0.003, 0.0065, 0.010, 0.0125]


def _rigid(rng, scale=0.3):
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    T[:3, 3] = rng.uniform(-scale, scale, 3)
    return T


def _scene():
    """Camera looking down +z at a tissue 0.12 m away; the incision runs along camera x."""
    G_CS = tissue_frame([-0.02, 0.001, 0.12], [0.02, -0.001, 0.121], [0.05, 0.1, -1.0])
    return _rigid(np.random.default_rng(7)), G_CS


def _to_S(G_CS, G_C_X):
    return np.linalg.inv(G_CS) @ G_C_X


def test_tissue_frame_axes():
    """Tissue frame S: z along the incision start -> end, y the surface normal made
    perpendicular to it and facing the camera, x = y x z, origin at the midpoint."""
    a, b = np.array([0.01, 0.02, 0.10]), np.array([0.04, 0.01, 0.11])
    n = np.array([0.1, 0.2, 1.0])                     # points away from the camera
    T = tissue_frame(a, b, n)
    R = T[:3, :3]
    assert np.allclose(R.T @ R, np.eye(3)) and np.linalg.det(R) == pytest.approx(1.0)
    assert np.allclose(R[:, 2], (b - a) / np.linalg.norm(b - a))
    assert np.allclose(T[:3, 3], 0.5 * (a + b))
    y = R[:, 1]
    assert y @ (np.zeros(3) - T[:3, 3]) > 0           # flipped to face the camera
    z = R[:, 2]
    m = -n - (-n @ z) * z                             # the normal's part across the incision
    assert np.allclose(y, m / np.linalg.norm(m))
    assert np.allclose(R[:, 0], np.cross(R[:, 1], R[:, 2]))
    # kept as given when no viewpoint is named
    assert np.allclose(tissue_frame(a, b, n, viewpoint=None)[:3, 1], -y)


def test_tissue_frame_suture_point():
    """Tissue frame S: the origin is the incision point nearest the requested suture
    point."""
    a, b = np.zeros(3) + [0, 0, 0.1], np.array([0.05, 0.0, 0.1])
    T = tissue_frame(a, b, [0, 0, -1], suture_point=[0.01, 0.003, 0.099])
    assert np.allclose(T[:3, 3], [0.01, 0.0, 0.1])


@pytest.mark.parametrize("args", [
    ([0, 0, 0.1], [0, 0, 0.1], [0, 0, -1]),             # no incision
    ([0, 0, 0.1], [0.00005, 0, 0.1], [0, 0, -1]),       # shorter than MIN_INCISION
    ([0, 0, 0.1], [0.02, 0, 0.1], [0, 0, 0]),           # zero normal
    ([0, 0, 0.1], [0.02, 0, 0.1], [1, 0, 0.01]),        # normal along the incision
    ([0, 0, 0.1], [0.02, 0, 0.1], [0, math.nan, -1]),   # not finite
])
def test_tissue_frame_degenerate_refused(args):
    """Bad input: a degenerate incision or normal is refused."""
    with pytest.raises(NeedleError):
        tissue_frame(*args)


def test_tissue_frame_suture_point_off_incision_refused():
    """Bad input: a suture point beyond the incision's ends is refused."""
    with pytest.raises(NeedleError, match="outside"):
        tissue_frame([0, 0, 0.1], [0.02, 0, 0.1], [0, 0, -1], suture_point=[0.03, 0, 0.1])


@pytest.mark.parametrize("d", DEPTHS)
def test_eq4_geometry_ct1(d):
    """Eq. 4 with the CT-1 (r = 13 mm): h = r - d, alpha0 = arcsin(h/r), entry/exit at
    x = -/+ sqrt(r^2 - h^2) on the tissue plane, range [alpha0, pi - alpha0]."""
    r = CT1.radius
    g = SutureGeometry.for_needle(CT1, d)
    assert g.h == pytest.approx(r - d)
    assert g.alpha0 == pytest.approx(math.asin((r - d) / r))
    w = math.sqrt(r**2 - (r - d) ** 2)
    assert np.allclose(g.entry, [-w, 0, 0]) and np.allclose(g.exit, [w, 0, 0])
    assert g.alpha_start == pytest.approx(g.alpha0)
    assert g.alpha_end == pytest.approx(math.pi - g.alpha0)


@pytest.mark.parametrize("d", DEPTHS)
def test_eq2_tip_entry_exit_depth(d):
    """Eq. 2 with eq. 4: the tip is at g at alpha0 and at f at pi - alpha0, and the
    deepest wire point over the drive is at depth d."""
    g = SutureGeometry.for_needle(CT1, d)
    tip = lambda a: (G_SN(a, g.h) @ np.append(CT1.tip, 1.0))[:3]  # noqa: E731
    assert np.allclose(tip(g.alpha0), g.entry, atol=1e-15)
    assert np.allclose(tip(math.pi - g.alpha0), g.exit, atol=1e-15)
    alphas = np.linspace(g.alpha0, math.pi - g.alpha0, 201)
    pts = np.einsum("nij,mj->nmi", G_SN(alphas, g.h)[:, :3, :3], CT1.points(181))
    pts += G_SN(alphas, g.h)[:, None, :3, 3]
    assert pts[..., 1].min() == pytest.approx(-d, abs=1e-9)
    # every wire point stays on one circle about the centre (0, h, 0)
    assert np.allclose(np.linalg.norm(pts - [0, g.h, 0], axis=-1), CT1.radius)


@pytest.mark.parametrize("d", DEPTHS)
def test_eq2_wire_stays_in_entry_hole(d):
    """Eq. 2 (rotation about the needle centre, least tear): at every alpha of the drive
    the entry point lies on the needle's wire, and the exit point does once the tip has
    passed it."""
    g = SutureGeometry.for_needle(CT1, d)

    def on_wire(alpha, p):
        q = (np.linalg.inv(G_SN(alpha, g.h)) @ np.append(p, 1.0))[:3]
        phi = math.atan2(q[1], q[0]) % (2 * math.pi)
        return (abs(np.linalg.norm(q) - CT1.radius) < 1e-12 and abs(q[2]) < 1e-15
                and phi <= CT1.arc + 1e-9)

    for a in np.linspace(g.alpha_start, g.alpha_end, 50):
        assert on_wire(a, g.entry)
    assert on_wire(g.alpha_end, g.exit)
    assert not on_wire(0.5 * (g.alpha_start + g.alpha_end), g.exit)


def test_g_sn_is_rigid_and_vectorised():
    """Eq. 2: G_SN is a rigid transform; arrays of alpha give stacks."""
    T = G_SN(np.array([0.1, 1.2, 2.9]), 0.004)
    assert T.shape == (3, 4, 4)
    for Ti in T:
        assert np.allclose(Ti[:3, :3].T @ Ti[:3, :3], np.eye(3))
        assert np.linalg.det(Ti[:3, :3]) == pytest.approx(1.0)
        assert np.allclose(Ti[:3, 3], [0, 0.004, 0]) and np.allclose(Ti[3], [0, 0, 0, 1])


def test_general_arc_range():
    """Eq. 4 generalised: a 3/8-circle needle's tip goes from g to f over
    [pi + alpha0 - arc, 2 pi - alpha0 - arc] and its base stays out of the tissue."""
    n = Needle(radius=0.011, arc=0.75 * math.pi)
    g = SutureGeometry.for_needle(n, 0.003)
    tip = lambda a: (G_SN(a, g.h) @ np.append(n.tip, 1.0))[:3]  # noqa: E731
    base = lambda a: (G_SN(a, g.h) @ np.append(n.base, 1.0))[:3]  # noqa: E731
    assert np.allclose(tip(g.alpha_start), g.entry, atol=1e-15)
    assert np.allclose(tip(g.alpha_end), g.exit, atol=1e-15)
    assert base(g.alpha_end)[1] > 0 and base(g.alpha_start)[1] > 0


@pytest.mark.parametrize("depth", [0.013, 0.02])
def test_depth_at_or_beyond_radius_refused(depth):
    """Bad input: depth >= radius (the centre would sit at or under the tissue)."""
    with pytest.raises(NeedleError, match="below the needle radius"):
        SutureGeometry(0.013, depth)


@pytest.mark.parametrize("depth", [-0.001, -1.0])
def test_h_above_r_refused(depth):
    """Bad input: h = r - d > r (negative depth), where eq. 4's arcsin(h/r) is undefined."""
    with pytest.raises(NeedleError, match="exceeds the radius"):
        SutureGeometry(0.013, depth)


@pytest.mark.parametrize("kw", [{"radius": 0.013, "depth": 0.0},
                                {"radius": 0.0, "depth": 0.001},
                                {"radius": 0.013, "depth": math.nan}])
def test_bad_suture_numbers_refused(kw):
    """Bad input: zero depth, zero radius or a non-finite depth."""
    with pytest.raises(NeedleError):
        SutureGeometry(**kw)


def test_arc_too_short_refused():
    """Bad input: an arc no longer than the submerged arc pi - 2 alpha0 would end with its
    base in the tissue; a slightly longer one is accepted."""
    r, d = 0.013, 0.010
    a0 = math.asin((r - d) / r)
    with pytest.raises(NeedleError, match="base would be in the"):
        SutureGeometry(r, d, arc=math.pi - 2 * a0)
    assert SutureGeometry(r, d, arc=math.pi - 2 * a0 + 0.01).spare_arc == pytest.approx(0.01)


def test_arc_too_long_refused():
    """Bad input: an arc longer than pi + 2 alpha0 would start with its base under the
    tissue beyond the exit."""
    r, d = 0.013, 0.010
    a0 = math.asin((r - d) / r)
    with pytest.raises(NeedleError, match="before the tip enters"):
        SutureGeometry(r, d, arc=math.pi + 2 * a0 + 0.01)


def test_eq3_against_independent_composition():
    """Eq. 3: G_PT = G_PC G_CS G_SN(alpha) G_TN^-1, against a computation with scipy
    rotations and numpy inverses; the needle tip runs from g to f in P."""
    G_PC, G_CS = _scene()
    G_TN = grasp_transform(0.001, 0.2, -1.3, 0.3, CT1.radius)
    geom = SutureGeometry.for_needle(CT1, 0.006)
    alphas, G_PT = drive_poses(G_PC, G_CS, G_TN, geom, 7)
    assert G_PT.shape == (7, 4, 4)
    assert np.allclose(alphas, np.linspace(geom.alpha0, math.pi - geom.alpha0, 7))
    for a, T in zip(alphas, G_PT, strict=True):
        S_N = np.eye(4)
        S_N[:3, :3] = Rotation.from_rotvec([0, 0, a]).as_matrix()
        S_N[1, 3] = CT1.radius - 0.006
        assert np.allclose(T, G_PC @ G_CS @ S_N @ np.linalg.inv(G_TN), atol=1e-12)
    tip_P = lambda T: (T @ G_TN @ np.append(CT1.tip, 1))[:3]  # noqa: E731
    assert np.allclose(tip_P(G_PT[0]), (G_PC @ G_CS @ np.append(geom.entry, 1))[:3])
    assert np.allclose(tip_P(G_PT[-1]), (G_PC @ G_CS @ np.append(geom.exit, 1))[:3])


def test_overshoot_and_its_limit():
    """Drive: the overshoot leaves the tip that much arc past the exit; one that would
    pull the base into the tissue is refused."""
    geom = SutureGeometry.for_needle(CT1, 0.006)
    d = plan_drive(np.eye(4), np.eye(4), geom, 5, overshoot=0.004)
    assert d.alphas[-1] == pytest.approx(geom.alpha_end + 0.004 / CT1.radius)
    with pytest.raises(NeedleError, match="base in the tissue"):
        plan_drive(np.eye(4), np.eye(4), geom, 5, overshoot=geom.spare_arc * CT1.radius)
    with pytest.raises(NeedleError):
        plan_drive(np.eye(4), np.eye(4), geom, 1)


def test_approach_along_gripper_and_tangent():
    """Drive approach: backed off along the gripper's -z (the seed's approach) or the
    tip's tangent; either way the needle tip is lifted off the entry point."""
    G_PC, G_CS = _scene()
    geom = SutureGeometry.for_needle(CT1, 0.006)
    # a grasp whose gripper points down into the tissue at entry
    G_TN = grasp_transform(0.001, 0.0, -2.0944, 0.15, CT1.radius)
    drive = plan_drive(G_PC, G_CS, geom, 10, G_TN)
    G_PS = G_PC @ G_CS
    for along in ("gripper", "tangent"):
        A = drive.approach_pose(0.005, along)
        tip_S = (np.linalg.inv(G_PS) @ A @ G_TN @ np.append(CT1.tip, 1))[:3]
        assert np.linalg.norm(tip_S - geom.entry) == pytest.approx(0.005)
        assert tip_S[1] > 0.0
    A = drive.approach_pose(0.005, "gripper")
    assert np.allclose(np.linalg.inv(drive.G_PT[0]) @ A,
                       [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, -0.005], [0, 0, 0, 1]])


def test_approach_refused_when_gripper_points_up():
    """Drive approach: refused where backing off along -z would push the needle down."""
    geom = SutureGeometry.for_needle(CT1, 0.006)
    drive = plan_drive(np.eye(4), np.eye(4), geom, 4)
    with pytest.raises(NeedleError, match="no grasp"):
        drive.approach_pose(0.005)
    # a grasp whose gripper z axis points out of the tissue at entry
    G_TN = next(G for w2 in np.linspace(-3, 3, 13)
                if drive.gripper_in_tissue(G := grasp_transform(0.001, 0.0, w2, 0.15,
                                                                CT1.radius))[0][1, 2] > 0.1)
    with pytest.raises(NeedleError, match="would not lift"):
        drive.with_grasp(G_TN).approach_pose(0.005, "gripper")


def test_regrasp_pose():
    """§III.F regrasp: the gripper pose holds the tracked needle with the given grasp
    (G_PT G_TN = G_PC G_CN) and the approach backs off along -z_T."""
    G_PC, G_CS = _scene()
    G_CN = G_CS @ G_SN(2.6, 0.007)
    G_TN = grasp_transform(0.001, 0.0, 1.0, CT1.arc - 0.3, CT1.radius)
    T = regrasp_pose(G_PC, G_CN, G_TN)
    assert np.allclose(T @ G_TN, G_PC @ G_CN)
    A = regrasp_pose(G_PC, G_CN, G_TN, approach=0.004)
    assert np.allclose((np.linalg.inv(T) @ A)[:3, 3], [0, 0, -0.004])


def test_pull_turns_until_swage_out_then_lifts():
    """§III.F pull: from the tracked pose the needle turns about its own centre until its
    base is swage_clearance past the exit, then rises along the tissue normal; the
    gripper keeps its grasp throughout."""
    G_PC, G_CS = _scene()
    geom = SutureGeometry.for_needle(CT1, 0.006)
    a_end = geom.alpha_end + 0.005 / CT1.radius
    G_CN = G_CS @ G_SN(a_end, geom.h)
    G_TN = grasp_transform(0.001, 0.0, 1.0, CT1.arc - 0.2, CT1.radius)
    pull = pull_poses(G_PC, G_CS, G_CN, G_TN, CT1, 20, swage_clearance=0.002,
                      lift=0.01, n_lift=4)
    assert pull.n_turn == 20 and len(pull.G_PT) == 24
    turn = geom.alpha_swage_out - a_end + 0.002 / CT1.radius
    assert pull.betas[19] == pytest.approx(turn)
    centres = np.array([_to_S(G_CS, T)[:3, 3] for T in pull.G_CN[:20]])
    assert np.allclose(centres, [0, geom.h, 0])       # turns about its own centre
    base_end = (_to_S(G_CS, pull.G_CN[19]) @ np.append(CT1.base, 1))[:3]
    ang = math.atan2(base_end[1] - geom.h, base_end[0]) % (2 * math.pi)
    assert ang == pytest.approx(geom.alpha_swage_out + 0.002 / CT1.radius)
    assert base_end[1] > 0
    lifted = _to_S(G_CS, pull.G_CN[-1])[:3, 3]
    assert np.allclose(lifted, [0, geom.h + 0.01, 0])
    for T, N in zip(pull.G_PT, pull.G_CN, strict=True):
        assert np.allclose(T @ G_TN, G_PC @ N)


def test_swage_exit_turn_matches_brute_force():
    """§III.F pull: the turn at which the base comes out of the tissue, for tracked
    needles tilted out of the plane across the incision, against a numeric search: the
    first turn after which no wire point is under the tissue."""
    rng = np.random.default_rng(3)
    grid = np.linspace(0, 2 * math.pi, 2001)
    phis = np.linspace(0, CT1.arc, 200)
    for _ in range(8):
        tilt = Rotation.from_rotvec(rng.normal(0, 0.3, 3)).as_matrix()
        T = G_SN(rng.uniform(1.8, 2.6), 0.006)
        T[:3, :3] = tilt @ T[:3, :3]
        beta = swage_exit_turn(T, CT1)
        # height of every wire point at every turn: row 1 of T applied to the turned arc
        ang = grid[:, None] + phis[None, :]
        heights = T[1, 3] + CT1.radius * (T[1, 0] * np.cos(ang) + T[1, 1] * np.sin(ang))
        first_out = grid[np.argmax(heights.min(axis=1) >= -1e-6)]
        assert beta == pytest.approx(first_out, abs=2 * 2 * math.pi / 2000)
        base = T @ G_SN(beta, 0.0) @ np.append(CT1.base, 1)
        assert abs(base[1]) < 1e-12


def test_pull_without_wire_in_tissue_only_lifts():
    """§III.F pull: a needle already out of the tissue is not turned, only lifted."""
    T = G_SN(0.2, 0.02)                      # centre 20 mm up: the whole circle is out
    pull = pull_poses(np.eye(4), np.eye(4), T, np.eye(4), CT1, 3, lift=0.01, n_lift=2)
    assert np.allclose(pull.betas, 0.0)
    assert np.allclose(pull.G_CN[-1][:3, 3], [0, 0.03, 0])


def test_pull_refused_when_base_never_surfaces():
    """Bad input: a tracked needle whose circle lies wholly under the tissue cannot be
    pulled out by turning."""
    T = G_SN(2.0, -0.02)
    with pytest.raises(NeedleError, match="never surfaces"):
        pull_poses(np.eye(4), np.eye(4), T, np.eye(4), CT1, 5)
