"""A scripted operator's hand: the force sensor's stand-in in simulation.

``ScriptedHand.force(t, p)`` is the force (N, fixture frame ``F``) a surgeon's hand puts on
the instrument at time ``t`` (s, from the start of the script) when the tool point is at
``p`` (m, frame ``F``). It is a pure function of ``(t, p)`` and the settings (the random
pushes are drawn from the seed and the index of their time slot, not from a running
generator), so a simulation run is reproducible whatever the order or rate of the calls.

The script, in three phases:

- ``push`` (``0 <= t < push_duration``): ``push_force`` newtons along the axis toward the
  target, plus a centring pull toward the axis, ``centering`` N/m times the tool's
  radial offset, capped at ``push_force`` (a hand steering the tool onto the axis while
  it feeds it in; at the target it keeps pressing against the end stop);
- ``pull`` (the next ``pull_duration`` s): ``pull_force`` newtons straight out along the
  entry direction (the tool withdrawn);
- ``release`` (afterwards): no force at all, the hand let go.

During ``push`` and ``pull`` a lateral disturbance tries to take the tool off the axis,
perpendicular to it (the worst case for the fixture): a sinusoid of
``lateral_amplitude`` N at ``lateral_frequency`` Hz along a fixed lateral direction, plus
piecewise-constant random pushes, a new one every ``random_interval`` s, uniform in a
lateral disc of radius ``random_amplitude`` N. ``noise_std`` adds Gaussian sensor noise
(N per axis, every phase, drawn per ``noise_period`` time slot).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from oralnav.control.guidance.virtual_fixture import VirtualFixture

__all__ = ["ScriptedHand", "PUSH", "PULL", "RELEASE"]

PUSH, PULL, RELEASE = "push", "pull", "release"

def _slot(t: float, period: float) -> int:
    """Index of the time slot of ``t`` (s, >= 0) on a grid of ``period`` s."""
    if not (t >= 0.0 and math.isfinite(t)):
        raise ValueError(f"time t (s) must be >= 0 and finite, got {t!r}")
    return math.floor(t / period)


def _lateral_basis(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors perpendicular to ``d`` and to each other (deterministic)."""
    helper = np.eye(3)[int(np.argmin(np.abs(d)))]
    e1 = np.cross(d, helper)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(d, e1)


@dataclass(frozen=True, eq=False)
class ScriptedHand:
    """A deterministic simulated operator for a :class:`VirtualFixture`; see the module
    docstring. Forces in N, times in s, frequencies in Hz, all in the fixture's frame."""

    fixture: VirtualFixture
    push_force: float = 4.0
    centering: float = 500.0
    push_duration: float = 4.0
    pull_force: float = 3.0
    pull_duration: float = 1.0
    lateral_amplitude: float = 0.0
    lateral_frequency: float = 1.5
    random_amplitude: float = 0.0
    random_interval: float = 0.25
    noise_std: float = 0.0
    noise_period: float = 0.002
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("push_force", "centering", "push_duration", "pull_force", "pull_duration",
                     "lateral_amplitude", "lateral_frequency", "random_amplitude",
                     "noise_std"):
            v = float(getattr(self, name))
            if not math.isfinite(v) or v < 0.0:
                raise ValueError(f"ScriptedHand.{name} must be >= 0 and finite, got {v!r}")
        for name in ("random_interval", "noise_period"):
            v = float(getattr(self, name))
            if not math.isfinite(v) or v <= 0.0:
                raise ValueError(f"ScriptedHand.{name} must be positive and finite, "
                                 f"got {v!r}")
        e1, e2 = _lateral_basis(np.asarray(self.fixture.direction, dtype=float))
        object.__setattr__(self, "_e1", e1)
        object.__setattr__(self, "_e2", e2)

    @property
    def duration(self) -> float:
        """End of the pull phase (s); from then on the hand is released."""
        return self.push_duration + self.pull_duration

    @property
    def lateral_directions(self) -> tuple[np.ndarray, np.ndarray]:
        """The two unit lateral directions (frame ``F``); the sinusoid acts along the
        first."""
        return self._e1.copy(), self._e2.copy()  # type: ignore[attr-defined]

    def phase(self, t: float) -> str:
        """``"push"``, ``"pull"`` or ``"release"`` at time ``t`` (s)."""
        if t < self.push_duration:
            return PUSH
        if t < self.duration:
            return PULL
        return RELEASE

    def disturbance(self, t: float) -> np.ndarray:
        """The lateral disturbance (3,), N, at time ``t`` (s): sinusoid plus the random
        push of ``t``'s slot; perpendicular to the axis."""
        e1, e2 = self._e1, self._e2  # type: ignore[attr-defined]
        f = self.lateral_amplitude * math.sin(2.0 * math.pi * self.lateral_frequency * t) * e1
        if self.random_amplitude > 0.0:
            slot = _slot(t, self.random_interval)
            u, ang = np.random.default_rng((self.seed, 1, slot)).random(2)
            rad = self.random_amplitude * math.sqrt(u)  # uniform in the disc
            ang *= 2.0 * math.pi
            f = f + rad * (math.cos(ang) * e1 + math.sin(ang) * e2)
        return f

    def force(self, t: float, p: ArrayLike) -> np.ndarray:
        """The hand's force (3,), N, frame ``F``, at time ``t`` (s) with the tool point at
        ``p`` (3,), m, frame ``F``."""
        t = float(t)
        if not (t >= 0.0 and math.isfinite(t)):
            raise ValueError(f"time t (s) must be >= 0 and finite, got {t!r}")
        d = np.asarray(self.fixture.direction, dtype=float)
        ph = self.phase(t)
        if ph == PUSH:
            w = np.asarray(p, dtype=float) - np.asarray(self.fixture.target, dtype=float)
            radial = w - (w @ d) * d
            off = float(np.linalg.norm(radial))
            f = -self.push_force * d + self.disturbance(t)
            if off > 0.0:  # toward the axis, capped
                f = f - (min(self.centering * off, self.push_force) / off) * radial
        elif ph == PULL:
            f = self.pull_force * d + self.disturbance(t)
        else:
            f = np.zeros(3)
        if self.noise_std > 0.0:
            slot = _slot(t, self.noise_period)
            f = f + np.random.default_rng((self.seed, 2, slot)).normal(0.0, self.noise_std, 3)
        return f

    __call__ = force
