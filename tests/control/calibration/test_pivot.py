"""Pivot calibration (issue 5 item 3): the algebraic, sphere and RANSAC solvers recover a
simulated pointer's tip, and degenerate or malformed pose sets are refused clearly."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from oralnav.control.calibration.pivot import PivotError, pivot_calibration
from oralnav.control.geometry import make_transform

TIP_MM = np.array([2.0, -3.0, 160.0])        # a 160 mm pointer, tip slightly off its axis
PIVOT_MM = np.array([120.0, -40.0, 900.0])   # the divot, in the tracker frame


def _pivoting(n: int, noise_mm: float, seed: int, spread_deg: float = 25.0) -> np.ndarray:
    """Tool poses (mm) whose tip sits in the divot: t = p_W - R p_tool, plus tracker noise
    on the tool origin (isotropic, ``noise_mm`` per axis)."""
    rng = np.random.default_rng(seed)
    rv = rng.uniform(-1, 1, size=(n, 3)) * np.radians(spread_deg)
    base = Rotation.from_euler("x", 180, degrees=True)  # tool pointing down into the divot
    R = (Rotation.from_rotvec(rv) * base).as_matrix()
    t = PIVOT_MM - R @ TIP_MM + rng.normal(0.0, noise_mm, size=(n, 3))
    return np.stack([make_transform(Ri, ti) for Ri, ti in zip(R, t, strict=True)])


@pytest.mark.parametrize("method", ["algebraic", "sphere", "ransac"])
def test_noise_free_poses_give_the_exact_tip(method):
    """Every solver recovers the tip and the pivot exactly from noise-free poses."""
    res = pivot_calibration(_pivoting(50, 0.0, 1), method, ransac_threshold=0.01)
    np.testing.assert_allclose(res.tip_offset, TIP_MM, atol=1e-6)
    np.testing.assert_allclose(res.pivot_point, PIVOT_MM, atol=1e-6)
    assert res.rms < 1e-6


# The sphere fit uses only the tool origins, not the orientations, so its centre is less
# well determined along the pointer's mean axis (a +-25 deg cap of a 160 mm sphere): it gets
# 0.02-0.2 mm where the one-step fit gets 0.01-0.04 mm on the same poses (8 seeds).
@pytest.mark.parametrize("method, tol_mm", [("algebraic", 0.1), ("ransac", 0.1),
                                            ("sphere", 0.3)])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_tip_within_a_tenth_of_a_millimetre_at_tracker_noise(method, tol_mm, seed):
    """Target: pivot tip within 0.1 mm at 0.1 mm tracker noise (300 poses, +-25 deg) for
    the algebraic and RANSAC solvers; the orientation-blind sphere fit within 0.3 mm."""
    res = pivot_calibration(_pivoting(300, 0.1, seed), method, ransac_threshold=0.5,
                            seed=seed)
    assert np.linalg.norm(res.tip_offset - TIP_MM) < tol_mm
    assert np.linalg.norm(res.pivot_point - PIVOT_MM) < tol_mm
    # the 3D RMS of isotropic 0.1 mm noise is about sqrt(3) * 0.1 mm
    assert 0.12 < res.rms < 0.2
    assert res.rms_per_component == pytest.approx(res.rms / np.sqrt(3))


def test_ransac_drops_gross_outliers_the_algebraic_fit_absorbs():
    """RANSAC's consensus excludes poses with a slipped tip; the one-step fit is pulled."""
    T = _pivoting(200, 0.1, 7)
    rng = np.random.default_rng(8)
    slip = rng.normal(size=(30, 3))
    # the tip slipped out of the divot: 3-6 mm in random directions
    T[:30, :3, 3] += slip / np.linalg.norm(slip, axis=1)[:, None] * rng.uniform(3, 6, (30, 1))
    alg = pivot_calibration(T, "algebraic")
    ran = pivot_calibration(T, "ransac", ransac_threshold=1.0, ransac_iterations=30)
    assert not ran.inliers[:30].any() and ran.inliers[30:].all()
    assert np.linalg.norm(ran.tip_offset - TIP_MM) < 0.1
    assert np.linalg.norm(alg.tip_offset - TIP_MM) > 3 * np.linalg.norm(ran.tip_offset - TIP_MM)
    assert ran.rms < alg.rms


def test_single_pose_is_rank_deficient():
    """Bad input: one pose cannot determine six unknowns; the error says rank deficient."""
    with pytest.raises(PivotError, match="rank deficient"):
        pivot_calibration(_pivoting(1, 0.0, 0))


def test_rotation_about_one_axis_is_rank_deficient():
    """Bad input: pivoting about a single axis leaves the tip unobservable along it."""
    angles = np.radians(np.linspace(-30, 30, 40))
    R = Rotation.from_rotvec(angles[:, None] * [0.0, 0.0, 1.0]).as_matrix()
    T = np.stack([make_transform(Ri, PIVOT_MM - Ri @ TIP_MM) for Ri in R])
    with pytest.raises(PivotError, match="rank deficient"):
        pivot_calibration(T)


def test_too_little_rotation_is_refused():
    """Bad input: a tool barely turned (within 2 deg) is refused, naming the spread."""
    with pytest.raises(PivotError, match="turned at most"):
        pivot_calibration(_pivoting(100, 0.0, 3, spread_deg=1.0))


@pytest.mark.parametrize("bad, match", [
    (np.zeros((10, 3, 4)), "stacked 4x4"),
    (np.full((5, 4, 4), np.nan), "non-finite"),
])
def test_malformed_matrices_are_refused(bad, match):
    """Bad input: wrong shapes and NaNs name what is wrong."""
    with pytest.raises(PivotError, match=match):
        pivot_calibration(bad)


def test_non_rigid_matrix_is_named_by_index():
    """Bad input: a scaled rotation is not rigid; the message gives the matrix index."""
    T = _pivoting(20, 0.0, 4)
    T[7, :3, :3] *= 1.01
    with pytest.raises(PivotError, match="matrix 7 is not rigid"):
        pivot_calibration(T)


def test_unknown_method_is_refused():
    with pytest.raises(PivotError, match="unknown pivot method"):
        pivot_calibration(_pivoting(20, 0.0, 4), "lsq")


def test_ransac_without_consensus_says_so():
    """RANSAC with a threshold far below the noise finds no consensus and says what to do."""
    with pytest.raises(PivotError, match="no consensus"):
        pivot_calibration(_pivoting(100, 1.0, 5), "ransac", ransac_threshold=0.01)
