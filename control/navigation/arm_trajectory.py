"""The arm's measured trajectory, and its pose at a camera frame's capture instant.

Eq. 5 of the navigation seed chains a tracked camera pose with the arm's TCP pose; eqs. 6
and 8 correct the TCP goal by the same product. Taken at different instants, the product is
wrong by the arm's speed times the time between them (20 mm/s for 30 ms is 0.6 mm, six
times the target accuracy). So navigation asks for the TCP pose *at* each frame's capture
instant: linear in position and geodesic in rotation between the two measured samples
around it. No I/O: the daemon reads the samples from the control loop's history
(``realtime/control_loop.py``, ``ARM_SAMPLE_DTYPE``).

An instant the samples cannot place is a :class:`TimingError` naming why, never a guess:
before the oldest sample (the frame is older than the history), after the newest (the arm
has not reported that instant yet; the caller may wait for it), or inside a gap between two
samples longer than ``max_gap`` (the arm was silent; interpolating across would invent a
path). Timestamps that do not increase are refused too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from oralnav.control.errors import ControlError
from oralnav.control.motion import rotation_exp, rotation_log

__all__ = ["ArmTrajectory", "TimingError"]


class TimingError(ControlError):
    """A pose cannot be placed in time: the instant lies outside the arm's history or in
    a gap of it, or the history's timestamps do not increase. ``kind`` says which:
    ``"older"``, ``"newer"``, ``"gap"``, ``"empty"`` or ``"order"``."""

    def __init__(self, kind: str, message: str) -> None:
        super().__init__(message)
        self.kind = kind


@dataclass(frozen=True, eq=False)
class ArmTrajectory:
    """Measured TCP samples, oldest first: times ``t`` (N,) in s and poses ``T`` (N, 4, 4)
    in the base frame, m. ``max_gap`` (s): the longest interval between two samples that
    :meth:`at` interpolates across."""

    t: np.ndarray
    T: np.ndarray
    max_gap: float

    def __post_init__(self) -> None:
        t = np.asarray(self.t, dtype=float).reshape(-1)
        T = np.asarray(self.T, dtype=float).reshape(-1, 4, 4)
        if len(t) != len(T):
            raise ValueError(f"{len(t)} sample times for {len(T)} poses")
        if not math.isfinite(self.max_gap) or self.max_gap <= 0:
            raise ValueError(f"max_gap must be a finite number of seconds > 0, got "
                             f"{self.max_gap!r}")
        if not np.all(np.isfinite(t)):
            raise TimingError("order", "the arm history has non-finite timestamps")
        back = np.flatnonzero(np.diff(t) <= 0)
        if len(back):
            i = int(back[0])
            raise TimingError("order", f"the arm's timestamps do not increase: sample {i + 1} "
                              f"at {t[i + 1]:.6f} s follows {t[i]:.6f} s (a clock that "
                              "jumped back)")
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "T", T)

    @classmethod
    def from_samples(cls, samples: np.ndarray, max_gap: float) -> ArmTrajectory:
        """From a structured array with fields ``t`` and ``T_B_tcp`` (the control loop's
        history record)."""
        return cls(np.asarray(samples["t"]), np.asarray(samples["T_B_tcp"]), max_gap)

    def __len__(self) -> int:
        return len(self.t)

    @property
    def newest(self) -> float:
        """The newest sample's time (s); -inf when empty."""
        return float(self.t[-1]) if len(self.t) else -math.inf

    def at(self, when: float) -> np.ndarray:
        """The TCP pose (4x4, base, m) at ``when`` (s, the samples' clock). Raises
        :class:`TimingError` where the samples cannot place it (module docstring)."""
        t = self.t
        if not len(t):
            raise TimingError("empty", "no arm pose measured yet")
        if when < t[0]:
            raise TimingError("older", f"the frame is {(t[0] - when) * 1e3:.1f} ms older than "
                              f"the arm history ({(t[-1] - t[0]) * 1e3:.0f} ms kept)")
        if when > t[-1]:
            raise TimingError("newer", f"the arm has not reported the frame's instant yet "
                              f"(its newest pose is {(when - t[-1]) * 1e3:.1f} ms older)")
        i = int(np.searchsorted(t, when, side="right"))
        if i >= len(t):  # exactly the newest sample
            return self.T[-1].copy()
        t0, t1 = float(t[i - 1]), float(t[i])
        if t1 - t0 > self.max_gap:
            raise TimingError("gap", f"the arm history has a gap of {(t1 - t0) * 1e3:.1f} ms "
                              f"at the frame's instant (at most {self.max_gap * 1e3:.1f} ms "
                              "is interpolated)")
        a = (when - t0) / (t1 - t0)
        T0, T1 = self.T[i - 1], self.T[i]
        out = np.eye(4)
        R0 = T0[:3, :3]
        out[:3, :3] = R0 @ rotation_exp(a * rotation_log(R0.T @ T1[:3, :3]))
        out[:3, 3] = (1.0 - a) * T0[:3, 3] + a * T1[:3, 3]
        return out
