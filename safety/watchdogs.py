"""Watchdogs: conditions that must stop the robot, checked with ``check(now) -> [Trip]``.

Each watchdog is fed by the code that sees the data (tracker, camera task, drivers, the
control loop) and checked by the safety task; both may run in different threads, so each
holds a lock. Time is passed in (``now``, seconds, the same monotonic or virtual clock
as the stamps fed); nothing here reads a clock.

Arming: a watchdog watches a named source only from that source's first feed. A source
that never delivered cannot be stale; that is the separate "never started" condition the
daemon checks before it reports READY (``armed`` lists what is watched). Limits are
exclusive: a pose exactly ``stale_pose`` old is still fresh, one a hair older trips.

A trip is reported on every check while its condition holds; the supervisor latches the
first. The deadline watchdog's per-period trips are events, kept until the next check so
a short burst of late periods between two checks is never missed.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from functools import partial
from typing import Protocol

from oralnav.checks import finite_number, positive_number

from .errors import InputError


@dataclass(frozen=True)
class Trip:
    """A tripped watchdog: ``name`` (``kind:source``), a reason with the measured figure,
    and that figure and its limit in the watchdog's unit (s, m or deg)."""

    name: str
    reason: str
    value: float
    limit: float


class Watchdog(Protocol):
    def check(self, now: float) -> list[Trip]: ...

    def next_deadline(self) -> float | None: ...


# The safety layer's number checks: InputError, the default wording, and bools accepted as
# 1.0/0.0 as they always were here.
_finite = partial(finite_number, error=InputError, allow_bool=True)
_positive = partial(positive_number, error=InputError, allow_bool=True)


def _name(name: str) -> str:
    if not isinstance(name, str) or not name:
        raise InputError(f"a watched source needs a non-empty name, got {name!r}")
    return name


class _AgeWatchdog:
    """Per named source, the time of its latest message; trips when older than ``limit``."""

    kind = "age"

    def __init__(self, limit: float) -> None:
        self.limit = _positive(limit, f"{self.kind} limit (s)")
        self._lock = threading.Lock()
        self._last: dict[str, float] = {}

    def _feed(self, name: str, stamp: float) -> None:
        name, stamp = _name(name), _finite(stamp, "stamp (s)")
        with self._lock:
            # a late-arriving older message must not make the source look older
            self._last[name] = max(stamp, self._last.get(name, -math.inf))

    def _reason(self, name: str, age: float) -> str:
        raise NotImplementedError

    @property
    def armed(self) -> tuple[str, ...]:
        """The sources watched (fed at least once), in order of first feed."""
        with self._lock:
            return tuple(self._last)

    def disarm(self, name: str) -> None:
        """Stop watching ``name`` (a source closed on purpose); re-armed by its next feed."""
        with self._lock:
            self._last.pop(name, None)

    def check(self, now: float) -> list[Trip]:
        now = _finite(now, "now (s)")
        with self._lock:
            last = list(self._last.items())
        # the deadline (stamp + limit) is what next_deadline reports; comparing against it
        # keeps check and next_deadline consistent to the last bit
        return [Trip(f"{self.kind}:{n}", self._reason(n, now - t), now - t, self.limit)
                for n, t in last if now > t + self.limit]

    def next_deadline(self) -> float | None:
        """The earliest time a check trips if nothing is fed meanwhile; None if unarmed."""
        with self._lock:
            return min((t + self.limit for t in self._last.values()), default=None)


class StalePoseWatchdog(_AgeWatchdog):
    """Trips when a pose source has had no fresh pose for longer than ``stale_pose`` s."""

    kind = "stale_pose"

    def fresh(self, name: str, stamp: float) -> None:
        """A fresh pose of ``name`` whose image was captured at ``stamp`` (s): a pose is as
        old as the image it came from."""
        self._feed(name, stamp)

    def _reason(self, name: str, age: float) -> str:
        return f"pose of {name!r} is {age:.3f} s old (limit {self.limit:.3f} s)"


class DriverSilenceWatchdog(_AgeWatchdog):
    """Trips when a driver's latest heartbeat or state message is older than
    ``driver_silence`` s."""

    kind = "driver_silence"

    def heartbeat(self, name: str, stamp: float) -> None:
        """Driver ``name`` reported (heartbeat or state) at ``stamp`` (s)."""
        self._feed(name, stamp)

    def _reason(self, name: str, age: float) -> str:
        return f"driver {name!r} silent for {age:.3f} s (limit {self.limit:.3f} s)"


class CameraStallWatchdog:
    """Trips when a camera's frame counter has not changed for longer than
    ``camera_stall`` s (a camera that repeats its last frame, or stops delivering)."""

    kind = "camera_stall"

    def __init__(self, limit: float) -> None:
        self.limit = _positive(limit, "camera_stall limit (s)")
        self._lock = threading.Lock()
        self._cams: dict[str, tuple[int, float]] = {}  # counter, time it last changed

    def frame(self, name: str, counter: int, now: float) -> None:
        """Camera ``name`` showed frame ``counter`` at ``now`` (s). Any change counts as
        progress, a decrease too: a camera reopened after a drop restarts its count."""
        name, now = _name(name), _finite(now, "now (s)")
        if isinstance(counter, bool) or not isinstance(counter, int):
            raise InputError(f"frame counter of {name!r} must be an integer, got {counter!r}")
        with self._lock:
            prev = self._cams.get(name)
            if prev is None or prev[0] != counter:
                self._cams[name] = (counter, now)

    @property
    def armed(self) -> tuple[str, ...]:
        with self._lock:
            return tuple(self._cams)

    def disarm(self, name: str) -> None:
        with self._lock:
            self._cams.pop(name, None)

    def check(self, now: float) -> list[Trip]:
        now = _finite(now, "now (s)")
        with self._lock:
            cams = list(self._cams.items())
        return [Trip(f"{self.kind}:{n}",
                     f"camera {n!r} frame counter stuck at {c} for {now - t:.3f} s "
                     f"(limit {self.limit:.3f} s)", now - t, self.limit)
                for n, (c, t) in cams if now > t + self.limit]

    def next_deadline(self) -> float | None:
        with self._lock:
            return min((t + self.limit for _, t in self._cams.values()), default=None)


class DeadlineWatchdog:
    """The control loop's deadlines. Fed each period's lateness (s after its deadline
    that the period finished; <= 0 is on time). Trips on

    - ``misses`` consecutive late periods (``deadline:misses``): jitter of one period is
      tolerated, a loop that keeps falling behind is not;
    - one period later than ``max_lateness`` (``deadline:hard``): a single long stall;
    - no period completed for ``period + max_lateness`` since the last one
      (``deadline:stalled``): a hung loop feeds nothing, so check finds it by the clock.

    Armed by the first period fed.
    """

    def __init__(self, period: float, misses: int, max_lateness: float) -> None:
        self.period = _positive(period, "control period (s)")
        if isinstance(misses, bool) or not isinstance(misses, int) or misses < 1:
            raise InputError(f"deadline misses must be an integer >= 1, got {misses!r}")
        self.misses = misses
        self.max_lateness = _positive(max_lateness, "max period lateness (s)")
        self._lock = threading.Lock()
        self._last_done: float | None = None
        self._consecutive = 0
        # events since the last check; each kind keeps its worst (hard) or latest (misses)
        self._pending: dict[str, Trip] = {}

    def period_done(self, lateness: float, now: float) -> None:
        """A control period finished ``lateness`` s after its deadline, at ``now`` (s)."""
        lateness, now = _finite(lateness, "lateness (s)"), _finite(now, "now (s)")
        with self._lock:
            self._last_done = now
            self._consecutive = self._consecutive + 1 if lateness > 0 else 0
            if lateness > self.max_lateness:
                old = self._pending.get("hard")
                if old is None or lateness > old.value:
                    self._pending["hard"] = Trip(
                        "deadline:hard",
                        f"control period finished {lateness * 1e3:.3f} ms late "
                        f"(limit {self.max_lateness * 1e3:.3f} ms)",
                        lateness, self.max_lateness)
            if self._consecutive >= self.misses:
                self._pending["misses"] = Trip(
                    "deadline:misses",
                    f"{self._consecutive} consecutive control periods late (limit "
                    f"{self.misses}), the last {lateness * 1e3:.3f} ms late",
                    float(self._consecutive), float(self.misses))

    @property
    def consecutive_misses(self) -> int:
        with self._lock:
            return self._consecutive

    def quiet(self, now: float) -> float | None:
        """Seconds since the last period completed at ``now`` (s); None until armed."""
        now = _finite(now, "now (s)")
        with self._lock:
            return None if self._last_done is None else now - self._last_done

    def stalled(self, now: float) -> bool:
        """True when ``check(now)`` would report ``deadline:stalled``; consumes nothing."""
        q = self.quiet(now)
        return q is not None and q > self.period + self.max_lateness

    def check(self, now: float) -> list[Trip]:
        now = _finite(now, "now (s)")
        with self._lock:
            trips = list(self._pending.values())
            self._pending.clear()
            last = self._last_done
        if last is not None and now > last + self.period + self.max_lateness:
            quiet = now - last
            trips.append(Trip(
                "deadline:stalled",
                f"control loop completed no period for {quiet * 1e3:.3f} ms (period "
                f"{self.period * 1e3:.3f} ms, limit {self.max_lateness * 1e3:.3f} ms late)",
                quiet, self.period + self.max_lateness))
        return trips

    def next_deadline(self) -> float | None:
        with self._lock:
            if self._pending:
                return -math.inf  # an event is waiting: check now
            if self._last_done is None:
                return None
            return self._last_done + self.period + self.max_lateness


class CovarianceWatchdog:
    """Trips while a pose source's latest pose has a position sigma above
    ``max_position_sigma`` (m) or a rotation sigma above ``max_rotation_sigma_deg``
    (deg). A NaN sigma (accuracy unknown) trips too."""

    def __init__(self, max_position_sigma: float, max_rotation_sigma_deg: float) -> None:
        self.max_position_sigma = _positive(max_position_sigma, "max position sigma (m)")
        self.max_rotation_sigma_deg = _positive(max_rotation_sigma_deg,
                                                "max rotation sigma (deg)")
        self._lock = threading.Lock()
        self._latest: dict[str, tuple[float, float]] = {}

    def pose(self, name: str, position_sigma: float, rotation_sigma_deg: float) -> None:
        """The latest pose of ``name`` has these 1-sigma uncertainties (m, deg)."""
        name = _name(name)
        vals = []
        for v, what in ((position_sigma, "position sigma (m)"),
                        (rotation_sigma_deg, "rotation sigma (deg)")):
            try:
                f = float(v)
            except (TypeError, ValueError):
                raise InputError(f"{what} of {name!r} must be a number, got {v!r}") from None
            if f < 0:  # NaN passes: unknown accuracy is reported by check, not refused
                raise InputError(f"{what} of {name!r} must not be negative, got {v!r}")
            vals.append(f)
        with self._lock:
            self._latest[name] = (vals[0], vals[1])

    @property
    def armed(self) -> tuple[str, ...]:
        with self._lock:
            return tuple(self._latest)

    def disarm(self, name: str) -> None:
        with self._lock:
            self._latest.pop(name, None)

    def check(self, now: float) -> list[Trip]:
        _finite(now, "now (s)")
        with self._lock:
            latest = list(self._latest.items())
        trips = []
        for n, (pos, rot) in latest:
            # "not <=" so that NaN trips
            if not pos <= self.max_position_sigma:
                trips.append(Trip(
                    f"position_sigma:{n}",
                    f"pose of {n!r} has a position sigma of {pos * 1e3:.3f} mm "
                    f"(limit {self.max_position_sigma * 1e3:.3f} mm)",
                    pos, self.max_position_sigma))
            if not rot <= self.max_rotation_sigma_deg:
                trips.append(Trip(
                    f"rotation_sigma:{n}",
                    f"pose of {n!r} has a rotation sigma of {rot:.3f} deg "
                    f"(limit {self.max_rotation_sigma_deg:.3f} deg)",
                    rot, self.max_rotation_sigma_deg))
        return trips

    def next_deadline(self) -> float | None:
        return None  # trips on what is fed, not on time


class WatchdogSettings(Protocol):
    """The settings :meth:`WatchdogSet.from_settings` reads (``[safety]`` of the daemon
    configuration, ``oralnav.config.daemon.SafetySection``)."""

    stale_pose: float
    pose_timeout: float
    camera_stall: float
    driver_silence: float
    deadline_misses: int
    max_period_lateness: float
    max_position_sigma: float
    max_rotation_sigma_deg: float


class WatchdogSet:
    """The daemon's watchdogs, checked together."""

    def __init__(self, *, poses: StalePoseWatchdog, cameras: CameraStallWatchdog,
                 drivers: DriverSilenceWatchdog, deadline: DeadlineWatchdog,
                 covariance: CovarianceWatchdog, stale_pose: float | None = None) -> None:
        self.poses = poses
        #: s: the age up to which a pose may still steer (``[safety] stale_pose``; the
        #: pose watch itself trips at the longer ``pose_timeout``)
        self.stale_pose = poses.limit if stale_pose is None else float(stale_pose)
        self.cameras = cameras
        self.drivers = drivers
        self.deadline = deadline
        self.covariance = covariance

    @classmethod
    def from_settings(cls, settings: WatchdogSettings, period: float) -> WatchdogSet:
        """Build from the ``[safety]`` settings and the control period (s, 1 / rate_hz)."""
        s = settings
        # the daemon's watch is for poses that stop coming (pose_timeout); the loop holds
        # on a goal older than stale_pose by itself
        return cls(poses=StalePoseWatchdog(s.pose_timeout),
                   cameras=CameraStallWatchdog(s.camera_stall),
                   drivers=DriverSilenceWatchdog(s.driver_silence),
                   deadline=DeadlineWatchdog(period, s.deadline_misses,
                                             s.max_period_lateness),
                   covariance=CovarianceWatchdog(s.max_position_sigma,
                                                 s.max_rotation_sigma_deg),
                   stale_pose=s.stale_pose)

    def __iter__(self) -> Iterator[Watchdog]:
        return iter((self.poses, self.cameras, self.drivers, self.deadline, self.covariance))

    def check(self, now: float) -> list[Trip]:
        """Every trip of every watchdog at ``now`` (s)."""
        now = _finite(now, "now (s)")
        return [t for w in self for t in w.check(now)]

    def next_deadline(self) -> float | None:
        """The earliest time any watchdog trips if nothing is fed; None if none is armed.
        The safety task sleeps until then at the latest."""
        ds = [d for w in self if (d := w.next_deadline()) is not None]
        return min(ds, default=None)
