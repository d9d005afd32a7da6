"""The daemon's pose store: the newest tracked pose of each marker field, the tracking
rates, and which poses' staleness trips the stale-pose watchdog.

The tracking tasks publish into it (through ``DaemonCore.publish_pose``), guidance reads
the opener pose from it, and ``GET /poses`` shows it. Poses are 4x4 homogeneous transforms
in metres, each in the frame it was published in (``C``: the stereo camera), stamped
with the daemon's monotonic clock (s) at capture.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np

from oralnav.safety.watchdogs import WatchdogSet


class PoseStore:
    """See the module docstring. ``clock`` is the daemon's monotonic clock (s).
    ``pinned()`` names poses watched whatever the current stage steers by (the opener's
    while a guided insertion runs); it is asked at every re-watch, with the store's lock
    held, so it must be quick and must not take this lock."""

    def __init__(self, watchdogs: WatchdogSet, clock: Callable[[], float],
                 pinned: Callable[[], Iterable[str]] = tuple) -> None:
        self.watchdogs = watchdogs
        self.clock = clock
        self._pinned = pinned
        self._lock = threading.Lock()
        self._poses: dict[str, dict[str, Any]] = {}
        self._rates: dict[str, float] = {}
        self._watched: set[str] = set()   # poses whose staleness trips (what steers now)
        self._steering: set[str] = set()  # those the navigation stage steers by

    def publish(self, name: str, T: np.ndarray, stamp: float, *, frame: str,
                corners: int = 0, sigma_m: float = math.nan,
                sigma_deg: float = math.nan) -> None:
        """A fresh pose ``T`` (4x4, m) of ``name`` in ``frame``, captured at ``stamp`` (s);
        ``sigma_m`` and ``sigma_deg`` are its position (m) and rotation (deg) spread."""
        with self._lock:
            self._poses[name] = {"T": np.array(T, dtype=float), "stamp": float(stamp),
                                 "frame": frame, "corners": int(corners),
                                 "sigma_mm": sigma_m * 1e3, "sigma_deg": sigma_deg}
        if name in self._watched:
            self.watchdogs.poses.fresh(name, stamp)
        if math.isfinite(sigma_m) and math.isfinite(sigma_deg):
            self.watchdogs.covariance.pose(name, sigma_m, sigma_deg)

    def watch(self, names: set[str]) -> None:
        """Only these poses' staleness trips from now on (those the current stage steers
        by: a field hidden on purpose, like the effector inside the mouth, is no fault),
        and the pinned ones."""
        with self._lock:
            self._steering = set(names)
        self.rewatch()

    def rewatch(self) -> None:
        """Recompute the watched poses (steering and pinned) and disarm the dropped ones;
        called when the pinned set changes."""
        with self._lock:
            names = set(self._steering)
            names.update(self._pinned())
            dropped = self._watched - names
            self._watched = names
        # the watchdog has its own lock; holding ours over it would only delay publishers
        for name in dropped:
            self.watchdogs.poses.disarm(name)

    def camera_frame(self, name: str, counter: int) -> None:
        """Camera ``name`` delivered frame ``counter`` now (feeds the camera-stall watch)."""
        self.watchdogs.cameras.frame(name, counter, self.clock())

    def set_rate(self, name: str, hz: float) -> None:
        """The measured rate (Hz) of tracking task ``name``."""
        with self._lock:
            self._rates[name] = float(hz)

    def rates(self) -> dict[str, float]:
        """A copy of the tracking rates (Hz) by task name."""
        with self._lock:
            return dict(self._rates)

    def pose(self, name: str) -> dict[str, Any] | None:
        """A copy of the newest record of ``name`` (``T``, ``stamp``, ``frame``, ...), or
        None before its first pose."""
        with self._lock:
            p = self._poses.get(name)
            return None if p is None else dict(p)

    def snapshot(self, now: float) -> dict[str, dict[str, Any]]:
        """Every pose as ``GET /poses`` shows it: frame, ``T`` as nested lists (m), its age
        at ``now`` (s), marker corners and spread (mm, deg)."""
        out: dict[str, dict[str, Any]] = {}
        with self._lock:
            items = list(self._poses.items())
        for name, p in items:
            out[name] = {"frame": p["frame"], "T": p["T"].tolist(),
                         "age_s": now - p["stamp"], "corners": p["corners"],
                         "sigma_mm": p["sigma_mm"], "sigma_deg": p["sigma_deg"]}
        return out
