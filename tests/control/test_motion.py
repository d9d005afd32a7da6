"""Issue 4, control loop: the fast geodesic step of ``control.motion`` agrees with SciPy's
Slerp and never exceeds its distance or angle bound."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

from oralnav.control.motion import geodesic, rotation_exp, rotation_log, step_toward


def _pose(rng: np.random.Generator, angle: float | None = None) -> np.ndarray:
    T = np.eye(4)
    if angle is None:
        T[:3, :3] = Rotation.random(random_state=rng).as_matrix()
    else:
        axis = rng.normal(size=3)
        T[:3, :3] = Rotation.from_rotvec(axis / np.linalg.norm(axis) * angle).as_matrix()
    T[:3, 3] = rng.uniform(-0.3, 0.3, 3)
    return T


@pytest.mark.parametrize("angle", [0.0, 1e-9, 1e-5, 0.3, 2.0, np.pi - 1e-3, np.pi - 1e-6])
def test_log_and_exp_match_scipy_over_the_whole_range(angle: float) -> None:
    """Rotation log/exp agree with SciPy's rotation vectors, including near 0 and near pi
    where the closed forms divide by zero."""
    rng = np.random.default_rng(7)
    for _ in range(20):
        axis = rng.normal(size=3)
        v = axis / np.linalg.norm(axis) * angle
        R = Rotation.from_rotvec(v).as_matrix()
        np.testing.assert_allclose(rotation_exp(v), R, atol=1e-12)
        back = rotation_log(R)
        # near pi, v and -v are the same rotation: compare the rotations themselves
        np.testing.assert_allclose(Rotation.from_rotvec(back).as_matrix(), R, atol=1e-9)
        assert abs(np.linalg.norm(back) - angle) < 1e-6


def test_step_matches_slerp_and_respects_both_bounds() -> None:
    """Each step is the Slerp pose at the same fraction, moves at most max_distance and
    turns at most max_angle, and the last step lands exactly on the goal."""
    rng = np.random.default_rng(3)
    for _ in range(200):
        Ta, Tb = _pose(rng), _pose(rng)
        max_d, max_a = rng.uniform(1e-4, 0.05), rng.uniform(1e-4, 0.5)
        T, s = step_toward(Ta, Tb, max_d, max_a)
        assert np.linalg.norm(T[:3, 3] - Ta[:3, 3]) <= max_d + 1e-12
        turn = Rotation.from_matrix(T[:3, :3] @ Ta[:3, :3].T).magnitude()
        assert turn <= max_a + 1e-9
        slerp = Slerp([0.0, 1.0], Rotation.from_matrix([Ta[:3, :3], Tb[:3, :3]]))
        np.testing.assert_allclose(T[:3, :3], slerp(s).as_matrix(), atol=1e-9)
        np.testing.assert_allclose(T[:3, 3], Ta[:3, 3] + s * (Tb[:3, 3] - Ta[:3, 3]),
                                   atol=1e-12)
    Ta, Tb = _pose(rng), _pose(rng)
    T = Ta
    for _ in range(10_000):
        T, s = step_toward(T, Tb, 0.01, 0.05)
        if s >= 1.0:
            break
    assert np.array_equal(T, Tb)


@pytest.mark.parametrize("angle", [0.0, 1e-8, 0.02, 1.0, 3.0, np.pi - 1e-5, None])
def test_geodesic_is_slerp_at_every_fraction(angle: float | None) -> None:
    """Issue 36 item 3 (the planners' paths without SciPy's per-call cost): the
    rotations along ``geodesic`` are SciPy's Slerp between the same two, at every
    fraction, for turns from none to nearly a half turn; the path ends on the goal."""
    rng = np.random.default_rng(11)
    f = np.linspace(0.0, 1.0, 17)
    for _ in range(20):
        R0 = _pose(rng)[:3, :3]
        R1 = R0 @ _pose(rng, angle)[:3, :3]
        slerp = Slerp([0.0, 1.0], Rotation.from_matrix([R0, R1]))(f).as_matrix()
        got = geodesic(R0, R1, f)
        np.testing.assert_allclose(got, slerp, atol=1e-9)
        np.testing.assert_allclose(got[-1], R1, atol=1e-9)
