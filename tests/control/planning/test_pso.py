"""Particle swarm optimisation (seed 004, eq. 20) and its stopping rule."""

import numpy as np
import pytest

from oralnav.control.errors import PlanningError
from oralnav.control.planning.pso import PSOSettings, minimize_pso


def sphere(x):
    return np.sum((x - np.array([0.3, -0.2])) ** 2, axis=1)


def test_finds_the_minimum_in_the_box():
    """The swarm converges on a smooth bowl's minimum."""
    r = minimize_pso(sphere, np.array([-1.0, -1.0]), np.array([1.0, 1.0]))
    assert np.allclose(r.x, [0.3, -0.2], atol=1e-4)


def test_stops_after_patience_unchanged_iterations():
    """The paper's rule: the best unchanged for ``patience`` iterations ends the search;
    the best value never gets worse."""
    r = minimize_pso(lambda x: np.zeros(len(x)), np.zeros(2), np.ones(2),
                     PSOSettings(patience=40))
    assert r.iterations == 40
    r = minimize_pso(sphere, -np.ones(2), np.ones(2))
    assert np.all(np.diff(r.history) <= 0)
    assert r.evaluations == 30 * (r.iterations + 1)


def test_stays_in_the_box():
    """Positions are clamped: a minimum outside the box is met on its wall."""
    r = minimize_pso(lambda x: x[:, 0] + x[:, 1], np.zeros(2), np.ones(2))
    assert np.allclose(r.x, [0, 0])


def test_seeded_runs_repeat():
    """Same seed, same answer; another seed, another path."""
    a = minimize_pso(sphere, -np.ones(2), np.ones(2), PSOSettings(seed=3))
    b = minimize_pso(sphere, -np.ones(2), np.ones(2), PSOSettings(seed=3))
    c = minimize_pso(sphere, -np.ones(2), np.ones(2), PSOSettings(seed=4))
    assert np.array_equal(a.history, b.history) and not np.array_equal(a.history, c.history)


def test_bad_settings_refused():
    """Bad input: one particle, a negative coefficient, an empty box."""
    with pytest.raises(PlanningError):
        PSOSettings(particles=1)
    with pytest.raises(PlanningError):
        PSOSettings(c1=-1)
    with pytest.raises(PlanningError, match="upper > lower"):
        minimize_pso(sphere, np.ones(2), np.ones(2))


def test_lazy_penalty_is_a_constraint_and_only_asked_for_candidates():
    """The penalty (a constraint too costly for the whole swarm: the certified rod check)
    is evaluated only for positions about to become a particle's best, and still steers
    the search: min x^2 + y^2 subject to x >= 0.3 ends at (0.3, 0)."""
    asked = []

    def penalty(x):
        asked.append(len(x))
        return np.where(x[:, 0] >= 0.3, 0.0, 100.0 + (0.3 - x[:, 0]))

    res = minimize_pso(lambda x: np.sum(x * x, axis=1), np.array([-1.0, -1.0]),
                       np.array([1.0, 1.0]), PSOSettings(seed=1), penalty=penalty)
    assert res.x[0] == pytest.approx(0.3, abs=1e-3) and res.value == pytest.approx(0.09, abs=1e-3)
    s = PSOSettings(seed=1)
    assert sum(asked) < 0.8 * res.evaluations and asked[0] == s.particles
