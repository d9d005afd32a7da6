"""Unit tests of ``oralnav.control.geometry`` (SE(3) helpers).

Each test's docstring names the requirement it checks (Issue 2, item 1: geometry).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import expm
from scipy.spatial.transform import Rotation

from oralnav.control import geometry as g
from oralnav.control.errors import ControlError, GeometryError


def _random_transform(rng: np.random.Generator, scale: float = 0.5) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    T[:3, 3] = rng.uniform(-scale, scale, 3)
    return T


def _twist_matrix(xi: np.ndarray) -> np.ndarray:
    """4x4 matrix of twist ``[rho, omega]`` in se(3), for an independent ``expm`` reference."""
    rho, (x, y, z) = xi[:3], xi[3:]
    return np.array([[0.0, -z, y, rho[0]],
                     [z, 0.0, -x, rho[1]],
                     [-y, x, 0.0, rho[2]],
                     [0.0, 0.0, 0.0, 0.0]])


def _twists(rng: np.random.Generator, angles: list[float], per_angle: int) -> list[np.ndarray]:
    out = []
    for theta in angles:
        for _ in range(per_angle):
            axis = rng.normal(size=3)
            axis /= np.linalg.norm(axis)
            out.append(np.concatenate([rng.uniform(-0.5, 0.5, 3), theta * axis]))
    return out


SMALL_ANGLES = [0.0, 1e-12, 1e-9, 1e-8, 2e-8, 1e-7, 1e-6, 1e-5, 1e-3]
GENERIC_ANGLES = [0.1, 0.7, 1.5, 2.5]
NEAR_PI_ANGLES = [np.pi - 1e-3, np.pi - 1e-6, np.pi - 1e-9]


# -- exp / log -------------------------------------------------------------------------
def test_exp_matches_matrix_exponential():
    """Issue 2 item 1: exp of a twist equals scipy's expm of its se(3) matrix (1e-12),
    including near-zero rotations, where naive (1 - cos t)/t^2 loses precision."""
    rng = np.random.default_rng(11)
    for xi in _twists(rng, SMALL_ANGLES + GENERIC_ANGLES, 20):
        T = g.exp(xi)
        np.testing.assert_allclose(T, expm(_twist_matrix(xi)), rtol=0, atol=1e-12)
        np.testing.assert_array_equal(T[3], [0.0, 0.0, 0.0, 1.0])


@pytest.mark.parametrize("angles", [SMALL_ANGLES, GENERIC_ANGLES, NEAR_PI_ANGLES],
                         ids=["near-zero", "generic", "near-pi"])
def test_log_exp_round_trip(angles):
    """Issue 2 item 1: log(exp(xi)) == xi and exp(log(T)) == T for random twists, including
    near-zero and near-pi rotation angles (1e-12)."""
    rng = np.random.default_rng(12)
    for xi in _twists(rng, angles, 40):
        T = g.exp(xi)
        xi_back = g.log(T)
        np.testing.assert_allclose(xi_back, xi, rtol=0, atol=1e-12)
        np.testing.assert_allclose(g.exp(xi_back), T, rtol=0, atol=1e-12)


def test_log_at_exactly_pi_returns_an_equivalent_twist():
    """Issue 2 item 1: at a rotation of exactly pi (axis sign ambiguous), exp(log(T)) == T."""
    rng = np.random.default_rng(13)
    for xi in _twists(rng, [np.pi], 20):
        T = g.exp(xi)
        xi_back = g.log(T)
        assert np.linalg.norm(xi_back[3:]) == pytest.approx(np.pi, abs=1e-12)
        np.testing.assert_allclose(g.exp(xi_back), T, rtol=0, atol=1e-12)


def test_log_of_random_transforms_round_trips():
    """Issue 2 item 1: exp(log(T)) == T for random rigid transforms (uniform rotations)."""
    rng = np.random.default_rng(14)
    for _ in range(200):
        T = _random_transform(rng)
        xi = g.log(T)
        assert np.linalg.norm(xi[3:]) <= np.pi + 1e-12
        np.testing.assert_allclose(g.exp(xi), T, rtol=0, atol=1e-12)


def test_exp_of_pure_translation_and_pure_rotation():
    """Issue 2 item 1: exp([rho, 0]) is a translation by rho; exp([0, omega]) is the rotation
    vector omega with no translation."""
    T = g.exp([0.1, -0.2, 0.3, 0.0, 0.0, 0.0])
    np.testing.assert_allclose(T, g.make_transform(t=[0.1, -0.2, 0.3]), atol=1e-15)
    T = g.exp([0.0, 0.0, 0.0, 0.0, 0.0, np.pi / 2])
    np.testing.assert_allclose(T[:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-15)
    np.testing.assert_allclose(T[:3, 3], 0.0, atol=1e-15)


# -- invert / compose --------------------------------------------------------------------
def test_invert_times_transform_is_identity():
    """Issue 2 item 1: invert(T) @ T == I and T @ invert(T) == I for random rigid transforms."""
    rng = np.random.default_rng(21)
    for _ in range(100):
        T = _random_transform(rng, scale=2.0)
        np.testing.assert_allclose(g.invert(T) @ T, np.eye(4), rtol=0, atol=1e-14)
        np.testing.assert_allclose(T @ g.invert(T), np.eye(4), rtol=0, atol=1e-14)


def test_invert_batched_matches_single():
    """Issue 2 item 1: invert on an N x 4 x 4 stack inverts each transform."""
    rng = np.random.default_rng(22)
    Ts = np.stack([_random_transform(rng) for _ in range(7)])
    inv = g.invert(Ts)
    assert inv.shape == (7, 4, 4)
    for T, Ti in zip(Ts, inv, strict=True):
        np.testing.assert_allclose(Ti, np.linalg.inv(T), rtol=0, atol=1e-13)


def test_compose_order_convention_on_points():
    """Issue 2 item 1: compose order is T_a_c = T_a_b @ T_b_c; mapping points c -> b -> a
    equals mapping them with compose(T_a_b, T_b_c), and the reverse order differs."""
    rng = np.random.default_rng(23)
    T_a_b = _random_transform(rng)
    T_b_c = _random_transform(rng)
    p_c = rng.uniform(-0.1, 0.1, (20, 3))
    p_b = g.transform_points(T_b_c, p_c)
    p_a = g.transform_points(T_a_b, p_b)
    T_a_c = g.compose(T_a_b, T_b_c)
    np.testing.assert_allclose(T_a_c, T_a_b @ T_b_c, atol=1e-15)
    np.testing.assert_allclose(g.transform_points(T_a_c, p_c), p_a, rtol=0, atol=1e-14)
    wrong = g.transform_points(g.compose(T_b_c, T_a_b), p_c)
    assert np.max(np.abs(wrong - p_a)) > 1e-3
    # and invert maps back: T_c_a takes frame-a points to frame c.
    np.testing.assert_allclose(g.transform_points(g.invert(T_a_c), p_a), p_c, atol=1e-14)


def test_compose_chains_three_and_empty_is_identity():
    """Issue 2 item 1: compose(T_a_b, T_b_c, T_c_d) == T_a_b @ T_b_c @ T_c_d; compose() == I."""
    rng = np.random.default_rng(24)
    Ts = [_random_transform(rng) for _ in range(3)]
    np.testing.assert_allclose(g.compose(*Ts), Ts[0] @ Ts[1] @ Ts[2], atol=1e-14)
    np.testing.assert_array_equal(g.compose(), np.eye(4))


def test_transform_points_known_case():
    """Issue 2 item 1: transform_points applies R then t (frame b -> a) on a hand case."""
    T_a_b = g.make_transform(Rotation.from_euler("z", 90, degrees=True), [1.0, 2.0, 3.0])
    p_a = g.transform_points(T_a_b, [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(p_a, [[1.0, 3.0, 3.0], [1.0, 2.0, 4.0]], atol=1e-15)


def test_transform_from_euler_is_extrinsic_xyz_in_degrees():
    """Issue 2 item 1: transform_from_euler uses extrinsic x-y-z angles in degrees,
    R = Rz @ Ry @ Rx, and the translation in metres."""
    def rx(a):
        c, s = np.cos(a), np.sin(a)
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])

    def ry(a):
        c, s = np.cos(a), np.sin(a)
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])

    def rz(a):
        c, s = np.cos(a), np.sin(a)
        return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])

    T = g.transform_from_euler([0.01, -0.02, 0.3], [10.0, -20.0, 30.0])
    R = rz(np.radians(30.0)) @ ry(np.radians(-20.0)) @ rx(np.radians(10.0))
    np.testing.assert_allclose(T[:3, :3], R, atol=1e-15)
    np.testing.assert_allclose(T[:3, 3], [0.01, -0.02, 0.3], atol=0)
    np.testing.assert_array_equal(T[3], [0.0, 0.0, 0.0, 1.0])


# -- pose_error / average_poses ----------------------------------------------------------
def test_pose_error_known_case():
    """Issue 2 item 1: pose_error of a pose offset by (3, -4, 0) mm and rotated 10 deg is
    (0.005 m, radians(10))."""
    T_true = g.transform_from_euler([0.1, 0.2, 0.3], [5.0, -40.0, 70.0])
    T_est = T_true.copy()
    T_est[:3, 3] += [0.003, -0.004, 0.0]
    T_est[:3, :3] = T_est[:3, :3] @ Rotation.from_rotvec([0.0, np.radians(10.0), 0.0]).as_matrix()
    dt, dr = g.pose_error(T_est, T_true)
    assert dt == pytest.approx(0.005, abs=1e-15)
    assert dr == pytest.approx(np.radians(10.0), abs=1e-12)
    assert g.pose_error(T_true, T_true) == pytest.approx((0.0, 0.0), abs=1e-12)
    # symmetric in its arguments
    assert g.pose_error(T_true, T_est) == pytest.approx((dt, dr), abs=1e-12)


def test_pose_error_rotation_is_in_zero_pi():
    """Issue 2 item 1: the rotation error of a 190 deg relative rotation is 170 deg."""
    T = g.transform_from_euler([0, 0, 0], [0.0, 0.0, 190.0])
    _, dr = g.pose_error(T, np.eye(4))
    assert dr == pytest.approx(np.radians(170.0), abs=1e-12)


def test_average_poses_recovers_pose_from_noisy_samples():
    """Issue 2 item 1: the mean of 400 samples with 1 mm / 0.5 deg noise recovers the true
    pose within 0.2 mm and 0.05 deg."""
    rng = np.random.default_rng(31)
    T_true = g.transform_from_euler([0.05, -0.1, 0.4], [20.0, 160.0, -75.0])
    samples = []
    for _ in range(400):
        dR = Rotation.from_rotvec(rng.normal(0.0, np.radians(0.5), 3)).as_matrix()
        T = T_true.copy()
        T[:3, :3] = T_true[:3, :3] @ dR
        T[:3, 3] += rng.normal(0.0, 0.001, 3)
        samples.append(T)
    T_mean = g.average_poses(samples)
    dt, dr = g.pose_error(T_mean, T_true)
    assert dt < 2e-4
    assert dr < np.radians(0.05)
    g.as_transform(T_mean)  # a proper rigid transform
    # a single sample is worse than the mean, so the test can tell averaging from picking one
    assert g.pose_error(samples[0], T_true)[1] > dr


def test_average_poses_weights():
    """Issue 2 item 1: average_poses honours weights: zero-weight samples are ignored,
    translations are the weighted mean, and same-axis rotations average in between."""
    T0 = g.transform_from_euler([0.0, 0.0, 0.0], [0.0, 0.0, 0.0])
    T1 = g.transform_from_euler([0.4, 0.0, 0.0], [0.0, 0.0, 20.0])
    outlier = g.transform_from_euler([5.0, 5.0, 5.0], [90.0, 0.0, 0.0])
    T = g.average_poses([T0, T1, outlier], weights=[3.0, 1.0, 0.0])
    np.testing.assert_allclose(T[:3, 3], [0.1, 0.0, 0.0], atol=1e-15)
    rotvec = Rotation.from_matrix(T[:3, :3]).as_rotvec()
    np.testing.assert_allclose(rotvec[:2], 0.0, atol=1e-12)
    # chordal mean about one axis: between the samples, nearer the heavier one
    assert 0.0 < np.degrees(rotvec[2]) < 10.0
    np.testing.assert_allclose(g.average_poses([T0, T1], weights=[0.0, 2.0]), T1, atol=1e-12)
    np.testing.assert_allclose(g.average_poses([T1]), T1, atol=1e-12)
    # unweighted mean of two same-axis rotations is their midpoint
    T = g.average_poses([T0, T1])
    assert np.degrees(Rotation.from_matrix(T[:3, :3]).magnitude()) == pytest.approx(10.0)


@pytest.mark.parametrize("Ts, weights", [
    (np.zeros((0, 4, 4)), None),
    (np.zeros((2, 3, 3)), None),
    ([np.eye(4), np.eye(4)], [1.0, -1.0]),
    ([np.eye(4), np.eye(4)], [0.0, 0.0]),
    ([np.eye(4), np.eye(4)], [1.0]),
], ids=["empty", "not-4x4", "negative-weight", "all-zero-weights", "weight-count"])
def test_average_poses_rejects_bad_input(Ts, weights):
    """Issue 2 item 1: average_poses raises GeometryError on empty/malformed sets or weights."""
    with pytest.raises(GeometryError, match="average_poses"):
        g.average_poses(Ts, weights)


# -- validation --------------------------------------------------------------------------
def test_as_transform_accepts_rigid_transform():
    """Issue 2 item 1: as_transform returns a valid rigid transform (from nested lists too)
    as a float 4x4 array."""
    T = g.transform_from_euler([0.1, 0.2, 0.3], [10.0, 20.0, 30.0])
    out = g.as_transform(T.tolist(), what="T_B_C")
    assert out.dtype == float and out.shape == (4, 4)
    np.testing.assert_array_equal(out, T)


def _bad_transforms() -> dict[str, object]:
    good = g.transform_from_euler([0.1, 0.2, 0.3], [10.0, 20.0, 30.0])
    nan = good.copy()
    nan[1, 3] = np.nan
    inf = good.copy()
    inf[0, 0] = np.inf
    bottom = good.copy()
    bottom[3] = [0.0, 0.0, 0.1, 1.0]
    bottom_scale = good.copy()
    bottom_scale[3, 3] = 2.0
    scaled = good.copy()
    scaled[:3, :3] *= 1.01
    reflection = good.copy()
    reflection[:3, :3] = reflection[:3, :3] @ np.diag([1.0, 1.0, -1.0])
    sheared = good.copy()
    sheared[0, 1] += 1e-3
    return {
        "shape-3x3": np.eye(3),
        "shape-3x4": good[:3],
        "shape-16": good.reshape(16),
        "nan": nan,
        "inf": inf,
        "bottom-row": bottom,
        "bottom-row-scale": bottom_scale,
        "scaled": scaled,
        "reflection": reflection,
        "sheared": sheared,
    }


@pytest.mark.parametrize("case", list(_bad_transforms()))
def test_as_transform_rejects_and_names_the_value(case):
    """Issue 2 item 1: as_transform rejects wrong shape, NaN/inf, a bad bottom row and a 3x3
    block that is not a proper rotation (scaled, reflected det -1, sheared) with a
    GeometryError (a ValueError and ControlError) whose message names ``what``."""
    T = _bad_transforms()[case]
    with pytest.raises(GeometryError, match="T_opener_marker") as info:
        g.as_transform(T, what="T_opener_marker")
    assert isinstance(info.value, ValueError)
    assert isinstance(info.value, ControlError)


def test_as_transform_reflection_message_reports_determinant():
    """Issue 2 item 1: a reflection (det -1) is rejected as not a proper rotation."""
    T = np.diag([1.0, 1.0, -1.0, 1.0])
    with pytest.raises(GeometryError, match=r"T_x: not a proper rotation.*det = -1"):
        g.as_transform(T, what="T_x")


def test_as_transform_tolerance():
    """Issue 2 item 1: rotation checks use ``tol``: a 1e-9 perturbation passes by default,
    a 1e-4 one fails, and passes again with a looser tol."""
    T = np.eye(4)
    T[0, 0] += 1e-9
    g.as_transform(T)
    T[0, 0] = 1.0 + 1e-4
    with pytest.raises(GeometryError):
        g.as_transform(T)
    g.as_transform(T, tol=1e-3)


@pytest.mark.parametrize("R", [
    np.eye(4), np.full((3, 3), np.nan), 2.0 * np.eye(3), np.diag([1.0, -1.0, 1.0]),
], ids=["shape", "nan", "scaled", "reflection"])
def test_as_rotation_matrix_rejects_and_names_the_value(R):
    """Issue 2 item 1: as_rotation_matrix rejects a wrong shape, NaN, a scaled matrix and a
    reflection with a GeometryError naming ``what``."""
    with pytest.raises(GeometryError, match="R_B_E"):
        g.as_rotation_matrix(R, what="R_B_E")


def test_make_transform_validates_rotation():
    """Issue 2 item 1: make_transform rejects a non-rotation matrix and accepts a Rotation."""
    with pytest.raises(GeometryError):
        g.make_transform(2.0 * np.eye(3))
    R = Rotation.from_euler("x", 30, degrees=True)
    T = g.make_transform(R, [1.0, 2.0, 3.0])
    np.testing.assert_allclose(T[:3, :3], R.as_matrix(), atol=0)
    np.testing.assert_array_equal(T[:3, 3], [1.0, 2.0, 3.0])


def test_nearest_rigid_repairs_drift_and_keeps_rigid_poses() -> None:
    """Issue 4 navigation: a measured pose whose rotation drifted 1e-6 from orthonormal is
    projected onto the nearest rotation (then passes the strict chain checks); an exact
    pose comes back unchanged."""
    from oralnav.control.geometry import as_transform, nearest_rigid, transform_from_euler

    T = transform_from_euler([0.1, -0.2, 0.3], [10.0, 20.0, 30.0])
    np.testing.assert_allclose(nearest_rigid(T), T, atol=1e-15)
    bad = T.copy()
    bad[:3, :3] *= 1 + 3e-6
    bad[0, 1] += 2e-6
    with pytest.raises(ValueError):
        as_transform(bad)
    fixed = as_transform(nearest_rigid(bad))
    np.testing.assert_allclose(fixed[:3, :3].T @ fixed[:3, :3], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(fixed, T, atol=1e-5)
