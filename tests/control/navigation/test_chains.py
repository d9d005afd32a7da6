"""Unit tests of ``oralnav.control.navigation.chains`` (navigation seed, sections III.B and III.C).

A synthetic, self-consistent world is built from random ground-truth poses in the base frame;
every "measured" transform is derived from it, and each chain must give the truth back.
Each test's docstring names the equation it checks.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from oralnav.control.errors import ControlError, GeometryError
from oralnav.control.geometry import compose, invert, make_transform
from oralnav.control.navigation import chains

ATOL = 1e-9


def _random_transform(rng: np.random.Generator, scale: float = 0.5) -> np.ndarray:
    return make_transform(Rotation.random(random_state=rng), rng.uniform(-scale, scale, 3))


def _world(seed: int) -> SimpleNamespace:
    """Ground truth: every frame's pose in the base B, plus the rigid offsets between them.

    The end-effector is at zero (E == E0), E0 axes coincide with the flange J6 (eq. 4's
    assumption), RM is rigid on the flange, En rigid on the opener, EM rigid on the effector.
    """
    rng = np.random.default_rng(seed)
    w = SimpleNamespace()
    w.T_B_C = _random_transform(rng, 1.0)
    w.T_B_J6 = _random_transform(rng, 0.8)
    w.T_J6_RM = _random_transform(rng, 0.1)
    w.T_J6_E0 = make_transform(None, rng.uniform(-0.2, 0.2, 3))  # R_J6_E0 = I
    w.T_B_OM = _random_transform(rng, 0.8)
    w.T_OM_En = _random_transform(rng, 0.05)
    w.T_E0_EM = _random_transform(rng, 0.02)
    w.T_B_CB = _random_transform(rng, 0.8)
    w.T_B_RM = compose(w.T_B_J6, w.T_J6_RM)
    w.T_B_E0 = compose(w.T_B_J6, w.T_J6_E0)
    w.T_RM_E0 = compose(invert(w.T_B_RM), w.T_B_E0)
    w.T_B_En = compose(w.T_B_OM, w.T_OM_En)
    w.T_B_EM = compose(w.T_B_E0, w.T_E0_EM)
    w.T_EM_E = invert(w.T_E0_EM)  # effector at zero: E == E0
    # What the sensors would report (camera, endoscope) and the instrument tip on E0's origin.
    w.T_C_RM = compose(invert(w.T_B_C), w.T_B_RM)
    w.T_C_OM = compose(invert(w.T_B_C), w.T_B_OM)
    w.T_C_CB = compose(invert(w.T_B_C), w.T_B_CB)
    w.T_En_CB = compose(invert(w.T_B_En), w.T_B_CB)
    w.T_En_EM = compose(invert(w.T_B_En), w.T_B_EM)
    w.p_C_SI = compose(invert(w.T_B_C), w.T_B_E0)[:3, 3]
    return w


@pytest.fixture(params=[1, 2, 3])
def world(request) -> SimpleNamespace:
    return _world(request.param)


# -- calibration (III.B) ---------------------------------------------------------------
def test_opener_endoscope_calibration_recovers_truth(world):
    """Eq. 2: T_OM_En from the board seen by camera and endoscope equals the true offset."""
    T = chains.opener_endoscope_calibration(world.T_C_OM, world.T_C_CB, world.T_En_CB)
    np.testing.assert_allclose(T, world.T_OM_En, atol=ATOL)
    # Eq. 1 closes with the result.
    np.testing.assert_allclose(compose(world.T_C_OM, T, world.T_En_CB), world.T_C_CB, atol=ATOL)


def test_effector_zero_position_recovers_truth(world):
    """Eq. 3: the instrument tip on the effector origin gives p_RM_E0 (3,)."""
    p = chains.effector_zero_position(world.T_C_RM, world.p_C_SI)
    assert p.shape == (3,)
    np.testing.assert_allclose(p, world.T_RM_E0[:3, 3], atol=ATOL)


def test_effector_zero_rotation_recovers_truth(world):
    """Eq. 4: R_RM_E0 = R_C_RM^T R_B_C^T R_B_J6 recovers the truth when E0 axes are J6's."""
    R = chains.effector_zero_rotation(world.T_C_RM[:3, :3], world.T_B_C[:3, :3],
                                      world.T_B_J6[:3, :3])
    np.testing.assert_allclose(R, world.T_RM_E0[:3, :3], atol=ATOL)


# -- navigation chains (III.C) ----------------------------------------------------------
def test_extraoral_chain_recovers_T_B_E0(world):
    """Eq. 5: camera, robot marker and the eq. 3-4 calibration give T_B_E0."""
    p = chains.effector_zero_position(world.T_C_RM, world.p_C_SI)
    R = chains.effector_zero_rotation(world.T_C_RM[:3, :3], world.T_B_C[:3, :3],
                                      world.T_B_J6[:3, :3])
    T = chains.extraoral_T_B_E0(world.T_B_C, world.T_C_RM, R, p)
    np.testing.assert_allclose(T, world.T_B_E0, atol=ATOL)
    # Eq. 5 tracks the arm: move the flange, re-measure RM, the calibration still holds.
    T_B_J6 = compose(world.T_B_J6, _random_transform(np.random.default_rng(9), 0.1))
    T_C_RM = compose(invert(world.T_B_C), T_B_J6, world.T_J6_RM)
    np.testing.assert_allclose(chains.extraoral_T_B_E0(world.T_B_C, T_C_RM, R, p),
                               compose(T_B_J6, world.T_J6_E0), atol=ATOL)


def test_intraoral_chain_recovers_T_B_E(world):
    """Eq. 6: camera -> opener -> endoscope -> effector marker -> effector gives T_B_E."""
    T = chains.intraoral_T_B_E(world.T_B_C, world.T_C_OM, world.T_OM_En, world.T_En_EM,
                               world.T_EM_E)
    np.testing.assert_allclose(T, world.T_B_E0, atol=ATOL)  # effector at zero


def test_effector_marker_offset_then_intraoral_round_trip(world):
    """Eq. 7 then eq. 6: T_EM_E calibrated at zero makes eq. 6 track the effector as it moves."""
    T_B_E0 = chains.extraoral_T_B_E0(world.T_B_C, world.T_C_RM, world.T_RM_E0[:3, :3],
                                     world.T_RM_E0[:3, 3])
    T_EM_E = chains.effector_marker_offset(world.T_B_C, world.T_C_OM, world.T_OM_En,
                                           world.T_En_EM, T_B_E0)
    np.testing.assert_allclose(T_EM_E, world.T_EM_E, atol=ATOL)
    # At zero, eq. 6 gives eq. 5's pose back.
    np.testing.assert_allclose(
        chains.intraoral_T_B_E(world.T_B_C, world.T_C_OM, world.T_OM_En, world.T_En_EM, T_EM_E),
        T_B_E0, atol=ATOL)
    # The effector and the head move: EM stays rigid on E, En on OM.
    rng = np.random.default_rng(5)
    T_B_E = compose(world.T_B_E0, _random_transform(rng, 0.02))
    T_B_OM = compose(world.T_B_OM, _random_transform(rng, 0.02))
    T_B_EM = compose(T_B_E, invert(T_EM_E))
    T_C_OM = compose(invert(world.T_B_C), T_B_OM)
    T_En_EM = compose(invert(compose(T_B_OM, world.T_OM_En)), T_B_EM)
    np.testing.assert_allclose(
        chains.intraoral_T_B_E(world.T_B_C, T_C_OM, world.T_OM_En, T_En_EM, T_EM_E),
        T_B_E, atol=ATOL)


def test_targets_register_and_follow_the_opener(world):
    """Eq. 8: targets registered in OM follow the head into the base; stack and single."""
    rng = np.random.default_rng(7)
    T_B_tar = np.stack([_random_transform(rng, 0.05) for _ in range(5)])
    T_B_tar = compose(world.T_B_OM, T_B_tar)  # near the opener
    T_C_tar = invert(world.T_B_C) @ T_B_tar
    T_OM_tar = chains.register_targets(world.T_C_OM, T_C_tar)
    assert T_OM_tar.shape == (5, 4, 4)
    np.testing.assert_allclose(
        chains.targets_in_base(world.T_B_C, world.T_C_OM, T_OM_tar), T_B_tar, atol=ATOL)
    # Single pose in, single pose out.
    one = chains.register_targets(world.T_C_OM, T_C_tar[2])
    assert one.shape == (4, 4)
    np.testing.assert_allclose(one, T_OM_tar[2], atol=ATOL)
    # The head moves: the targets move with the opener marker.
    M = _random_transform(rng, 0.05)
    T_C_OM = compose(invert(world.T_B_C), world.T_B_OM, M)
    np.testing.assert_allclose(
        chains.targets_in_base(world.T_B_C, T_C_OM, T_OM_tar[2]),
        compose(world.T_B_OM, M, T_OM_tar[2]), atol=ATOL)


# -- input validation -------------------------------------------------------------------
def test_bad_inputs_raise_errors_naming_the_argument(world):
    """All chains: malformed inputs raise GeometryError naming the argument at fault."""
    skew = world.T_C_OM.copy()
    skew[0, 1] += 0.1  # not a rotation
    with pytest.raises(GeometryError, match="T_C_OM"):
        chains.opener_endoscope_calibration(skew, world.T_C_CB, world.T_En_CB)
    with pytest.raises(GeometryError, match="T_En_EM.*4x4"):
        chains.intraoral_T_B_E(world.T_B_C, world.T_C_OM, world.T_OM_En, np.eye(3),
                               world.T_EM_E)
    with pytest.raises(GeometryError, match="p_C_SI.*shape"):
        chains.effector_zero_position(world.T_C_RM, [0.0, 0.0])
    with pytest.raises(GeometryError, match="p_RM_E0.*non-finite"):
        chains.extraoral_T_B_E0(world.T_B_C, world.T_C_RM, np.eye(3), [0.0, np.nan, 0.0])
    with pytest.raises(GeometryError, match="R_B_J6"):
        chains.effector_zero_rotation(np.eye(3), np.eye(3), -np.eye(3))  # det -1
    with pytest.raises(GeometryError, match="T_B_E0"):
        chains.effector_marker_offset(world.T_B_C, world.T_C_OM, world.T_OM_En,
                                      world.T_En_EM, 2 * np.eye(4))
    bad = np.stack([np.eye(4), np.eye(4)])
    bad[1, 3, 0] = 1.0  # bottom row
    with pytest.raises(GeometryError, match=r"T_OM_tar\[1\]"):
        chains.targets_in_base(world.T_B_C, world.T_C_OM, bad)
    with pytest.raises(GeometryError, match="T_C_tar.*stack"):
        chains.register_targets(world.T_C_OM, np.zeros((2, 3, 4)))
    # The layer's base class catches them all.
    with pytest.raises(ControlError):
        chains.register_targets(world.T_C_OM, np.zeros((4,)))
