"""Particle swarm optimisation over a box (seed 004, eq. 20), vectorised over the swarm.

``v <- c0 v + r1 c1 (x_best_i - x) + r2 c2 (x_best_glb - x)``, ``x <- x + v``, with ``r1``
and ``r2`` drawn uniformly in [0, 1) per particle and per dimension. The objective takes the
whole swarm at once, (P, D) -> (P,), so one numpy pass scores every particle. The paper's
stopping rule: the swarm's best value has not improved for ``patience`` iterations (40).

Positions are clamped to the box and a clamped velocity component is zeroed (an absorbing
wall); velocities are capped at ``v_max`` times the box size per iteration. The paper gives
c1 = 0.3 and c2 = 0.4 but no inertia c0; 0.7 here (a common choice, charted in the bench).
A seeded generator makes every run reproducible.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from oralnav.control.errors import PlanningError


@dataclass(frozen=True)
class PSOSettings:
    particles: int = 30
    c0: float = 0.7
    c1: float = 0.3
    c2: float = 0.4
    patience: int = 40
    max_iterations: int = 1000
    v_max: float = 0.2             # fraction of the box size per iteration
    tolerance: float = 1e-8        # an improvement smaller than this does not count
    seed: int = 0

    def __post_init__(self) -> None:
        if self.particles < 2:
            raise PlanningError(f"PSO needs at least 2 particles, got {self.particles}")
        if self.patience < 1 or self.max_iterations < 1:
            raise PlanningError("PSO patience and max_iterations must be >= 1")
        if not (0 <= self.c0 < 1.5 and self.c1 >= 0 and self.c2 >= 0 and self.v_max > 0):
            raise PlanningError(f"PSO coefficients out of range: c0 {self.c0}, c1 {self.c1},"
                                f" c2 {self.c2}, v_max {self.v_max}")


@dataclass(frozen=True)
class PSOResult:
    x: np.ndarray                  # best position (D,)
    value: float                   # objective there
    iterations: int
    evaluations: int
    history: np.ndarray            # best value after each iteration (iterations + 1,)


def minimize_pso(objective: Callable[[np.ndarray], np.ndarray], lower: np.ndarray,
                 upper: np.ndarray, settings: PSOSettings | None = None,
                 penalty: Callable[[np.ndarray], np.ndarray] | None = None) -> PSOResult:
    """Minimise ``objective`` over the box [lower, upper] (D,) by eq. 20.

    ``penalty`` (optional, >= 0, added to the objective) is a constraint too costly to
    evaluate for the whole swarm: it is evaluated lazily, only for positions about to
    become a particle's best, since no other position's value is ever used."""
    s = settings or PSOSettings()
    lo = np.asarray(lower, dtype=float)
    hi = np.asarray(upper, dtype=float)
    if lo.shape != hi.shape or lo.ndim != 1 or not np.all(hi > lo):
        raise PlanningError(f"PSO bounds must be 1-D with upper > lower, got {lo} .. {hi}")
    rng = np.random.default_rng(s.seed)
    span = hi - lo
    vmax = s.v_max * span
    x = lo + rng.random((s.particles, lo.size)) * span
    v = (rng.random(x.shape) - 0.5) * vmax
    f = np.asarray(objective(x), dtype=float)
    if penalty is not None:
        f = f + np.asarray(penalty(x), dtype=float)
    pbest, pval = x.copy(), f.copy()
    g = int(np.argmin(pval))
    gbest, gval = pbest[g].copy(), float(pval[g])
    history = [gval]
    still = it = 0
    evals = s.particles
    while it < s.max_iterations and still < s.patience:
        it += 1
        r1 = rng.random(x.shape)
        r2 = rng.random(x.shape)
        v = s.c0 * v + r1 * s.c1 * (pbest - x) + r2 * s.c2 * (gbest - x)
        v = np.clip(v, -vmax, vmax)
        x = x + v
        out = (x < lo) | (x > hi)
        x = np.clip(x, lo, hi)
        v[out] = 0.0
        f = np.asarray(objective(x), dtype=float)
        evals += s.particles
        better = f < pval
        if penalty is not None and np.any(better):
            f[better] += np.asarray(penalty(x[better]), dtype=float)
            better = f < pval
        pbest[better], pval[better] = x[better], f[better]
        g = int(np.argmin(pval))
        if pval[g] < gval - s.tolerance:
            gbest, gval, still = pbest[g].copy(), float(pval[g]), 0
        else:
            still += 1
        history.append(gval)
    return PSOResult(gbest, gval, it, evals, np.asarray(history))
