"""The scripted hand, the force sensor's stand-in in simulation: deterministic, pushing to
the target, disturbing laterally, pulling back, then letting go."""

from __future__ import annotations

import math

import numpy as np
import pytest

from oralnav.control.guidance.virtual_fixture import VirtualFixture
from oralnav.sim.world.hand import PULL, PUSH, RELEASE, ScriptedHand

MM = 1e-3
D = np.array([0.0, 0.6, 0.8])
TARGET = np.array([0.01, -0.02, 0.05])


def _fixture() -> VirtualFixture:
    return VirtualFixture.from_axis(TARGET, D, 0.5 * MM, 30 * MM, [(20 * MM, 6 * MM)])


def test_push_feeds_along_the_axis_and_centres_the_tool() -> None:
    """Push phase: without disturbance, push_force along the axis toward the target plus a
    centring force toward the axis (centering x radial offset, capped at push_force)."""
    hand = ScriptedHand(_fixture(), push_force=4.0, centering=500.0)
    np.testing.assert_allclose(hand.force(0.5, TARGET + 0.03 * D), -4.0 * D, atol=1e-12)
    np.testing.assert_allclose(hand.force(0.5, TARGET), -4.0 * D, atol=1e-12)
    e1, _ = hand.lateral_directions
    np.testing.assert_allclose(hand.force(0.5, TARGET + 0.03 * D + 0.002 * e1),
                               -4.0 * D - 1.0 * e1, atol=1e-12)  # 2 mm off: 1 N back
    np.testing.assert_allclose(hand.force(0.5, TARGET + 0.03 * D + 0.02 * e1),
                               -4.0 * D - 4.0 * e1, atol=1e-12)  # capped at push_force


def test_phases_pull_back_then_release() -> None:
    """Pull-back phase: pull_force straight out along the entry direction; afterwards the
    hand is released (zero force)."""
    hand = ScriptedHand(_fixture(), push_duration=2.0, pull_force=3.0, pull_duration=1.0)
    assert [hand.phase(t) for t in (0.0, 1.99, 2.0, 2.99, 3.0, 10.0)] == \
        [PUSH, PUSH, PULL, PULL, RELEASE, RELEASE]
    np.testing.assert_allclose(hand.force(2.5, TARGET), 3.0 * D, atol=1e-12)
    np.testing.assert_array_equal(hand.force(3.5, TARGET + 0.01 * D), 0.0)
    assert hand.duration == 3.0


def test_disturbance_is_lateral_and_bounded() -> None:
    """Lateral disturbance: perpendicular to the axis, within the sinusoid's amplitude
    plus the random push's, and the sinusoid alone is A sin(2 pi f t) along a fixed
    lateral direction."""
    sine = ScriptedHand(_fixture(), lateral_amplitude=5.0, lateral_frequency=2.0)
    e1, e2 = sine.lateral_directions
    assert abs(e1 @ D) < 1e-12 and abs(e2 @ D) < 1e-12 and abs(e1 @ e2) < 1e-12
    for t in np.linspace(0, 2, 41):
        np.testing.assert_allclose(sine.disturbance(t), 5.0 * math.sin(4 * math.pi * t) * e1,
                                   atol=1e-12)
    both = ScriptedHand(_fixture(), lateral_amplitude=5.0, random_amplitude=7.0, seed=3)
    mags = []
    for t in np.linspace(0, 5, 501):
        f = both.disturbance(t)
        assert abs(f @ D) < 1e-12
        mags.append(np.linalg.norm(f))
    assert max(mags) <= 12.0 and max(mags) > 6.0


def test_deterministic_whatever_the_call_order() -> None:
    """Determinism: the force is a pure function of (t, p) and the seed; the same seed
    gives the same script in any call order, another seed another one."""
    kw = dict(lateral_amplitude=2.0, random_amplitude=6.0, noise_std=0.3)
    a = ScriptedHand(_fixture(), seed=5, **kw)
    b = ScriptedHand(_fixture(), seed=5, **kw)
    c = ScriptedHand(_fixture(), seed=6, **kw)
    p = TARGET + 0.04 * D
    ts = np.linspace(0, 6, 97)
    fa = [a.force(t, p) for t in ts]
    fb = [b.force(t, p) for t in ts[::-1]][::-1]
    np.testing.assert_array_equal(fa, fb)
    assert not np.allclose(fa, [c.force(t, p) for t in ts])
    # noise is zero-mean with the stated spread (every phase, released included)
    quiet = ScriptedHand(_fixture(), push_duration=0.0, pull_duration=0.0, noise_std=0.3)
    noise = np.array([quiet.force(t, p) for t in np.arange(2000) * 0.002])
    assert abs(noise.mean()) < 0.03 and noise.std() == pytest.approx(0.3, rel=0.1)


@pytest.mark.parametrize("kwargs", [{"push_force": -1.0}, {"random_interval": 0.0},
                                    {"noise_std": math.nan}, {"noise_period": -1.0}])
def test_bad_scripts_are_refused(kwargs) -> None:
    """Validation: negative or non-finite forces and non-positive periods are refused."""
    with pytest.raises(ValueError):
        ScriptedHand(_fixture(), **kwargs)
    with pytest.raises(ValueError):
        ScriptedHand(_fixture()).force(-1.0, TARGET)
