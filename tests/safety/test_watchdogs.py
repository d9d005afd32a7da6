"""Tests of ``oralnav.safety.watchdogs``.

Each test's docstring names the requirement it checks (Issue 4: safety). Times are
virtual; limits are chosen exactly representable in binary (0.125 s...) so that "exactly
at the limit" is exact and the boundary tests test the comparison, not rounding.
"""

from __future__ import annotations

import math
import threading

import pytest

from oralnav.config.daemon import SafetySection
from oralnav.safety.errors import InputError
from oralnav.safety.watchdogs import (
    CameraStallWatchdog,
    CovarianceWatchdog,
    DeadlineWatchdog,
    DriverSilenceWatchdog,
    StalePoseWatchdog,
    Trip,
    WatchdogSet,
)

UP = math.inf


def after(t: float) -> float:
    """The next float after ``t``: the smallest time past a limit."""
    return math.nextafter(t, UP)


# -- stale pose ----------------------------------------------------------------------------
def test_stale_pose_trips_just_past_the_limit():
    """Issue 4 safety (stale pose watchdog): a pose exactly stale_pose old is fresh; one a
    hair older trips, naming the source and the age and limit in the reason."""
    w = StalePoseWatchdog(0.125)
    w.fresh("opener", 10.0)
    assert w.check(10.125) == []
    (trip,) = w.check(after(10.125))
    assert trip.name == "stale_pose:opener"
    assert trip.limit == 0.125 and trip.value > 0.125
    (trip,) = w.check(10.259)
    assert trip.reason == "pose of 'opener' is 0.259 s old (limit 0.125 s)"


def test_stale_pose_per_source_and_fresh_pose_clears():
    """Issue 4 safety (stale pose watchdog): each named source has its own age; a fresh
    pose clears the trip; an older stamp arriving late does not age the source."""
    w = StalePoseWatchdog(0.1)
    w.fresh("opener", 1.0)
    w.fresh("effector", 1.05)
    assert [t.name for t in w.check(1.12)] == ["stale_pose:opener"]
    w.fresh("opener", 1.11)
    w.fresh("opener", 0.5)  # out of order: ignored
    assert w.check(1.12) == []
    assert w.next_deadline() == pytest.approx(1.15)


def test_watchdogs_are_disarmed_until_the_first_feed():
    """Issue 4 safety (arming): a watchdog watches a source from its first feed only; a
    source that never delivered is not a trip (the daemon's "never started" check), and
    disarm stops watching it."""
    w = StalePoseWatchdog(0.1)
    assert w.check(1e6) == [] and w.armed == () and w.next_deadline() is None
    w.fresh("opener", 0.0)
    assert w.armed == ("opener",)
    assert len(w.check(1.0)) == 1
    w.disarm("opener")
    assert w.check(1.0) == []
    c = CameraStallWatchdog(0.2)
    assert c.check(1e6) == []
    d = DeadlineWatchdog(0.002, 3, 0.01)
    assert d.check(1e6) == [] and d.next_deadline() is None


# -- driver silence ------------------------------------------------------------------------
def test_driver_silence_boundary_and_reason():
    """Issue 4 safety (silent driver watchdog): a driver exactly driver_silence quiet is
    fine; a hair longer trips with the figure in the reason."""
    w = DriverSilenceWatchdog(0.0625)
    w.heartbeat("arm", 2.0)
    w.heartbeat("effector", 2.5)
    assert w.check(2.0625) == []
    (trip,) = w.check(after(2.0625))
    assert trip.name == "driver_silence:arm"
    (trip, _) = w.check(2.6)
    assert trip.reason == "driver 'arm' silent for 0.600 s (limit 0.062 s)"


# -- camera stall --------------------------------------------------------------------------
def test_camera_stall_boundary_and_reason():
    """Issue 4 safety (stalled camera watchdog): a counter unchanged for exactly
    camera_stall is fine, a hair longer trips; repeated frames with the same counter do
    not count as progress; the reason names the counter and the time."""
    w = CameraStallWatchdog(0.25)
    w.frame("left", 41, 0.0)
    w.frame("left", 42, 1.0)
    for t in (1.1, 1.2, 1.25):
        w.frame("left", 42, t)  # the same frame again
    assert w.check(1.25) == []
    (trip,) = w.check(after(1.25))
    assert trip.name == "camera_stall:left"
    (trip,) = w.check(1.5)
    assert trip.reason == "camera 'left' frame counter stuck at 42 for 0.500 s (limit 0.250 s)"
    w.frame("left", 43, 1.5)
    assert w.check(1.5) == []


def test_camera_counter_restart_counts_as_progress():
    """Issue 4 safety (stalled camera watchdog): a counter that goes back (camera reopened)
    is progress, not a stall; a camera that stops calling in at all trips too."""
    w = CameraStallWatchdog(0.25)
    w.frame("left", 1000, 0.0)
    w.frame("left", 0, 0.2)
    assert w.check(0.4) == []
    assert len(w.check(0.5)) == 1  # nothing since 0.2
    with pytest.raises(InputError, match="integer"):
        w.frame("left", 1.5, 0.6)  # type: ignore[arg-type]


# -- deadline ------------------------------------------------------------------------------
def test_deadline_trips_after_n_consecutive_late_periods():
    """Issue 4 safety (deadline-miss logic): N-1 consecutive late periods do not trip; the
    N-th does, with the count and lateness in the reason; an on-time period resets the
    count."""
    w = DeadlineWatchdog(period=0.002, misses=3, max_lateness=0.01)
    t = 0.0
    for _ in range(5):  # late, late, on time: never three in a row
        for lateness in (0.0005, 0.0005, 0.0):
            t += 0.002
            w.period_done(lateness, t)
    assert w.check(t) == [] and w.consecutive_misses == 0
    for _ in range(2):
        t += 0.002
        w.period_done(0.0005, t)
    assert w.check(t) == [] and w.consecutive_misses == 2
    t += 0.002
    w.period_done(0.00075, t)
    (trip,) = w.check(t)
    assert trip.name == "deadline:misses"
    assert trip.reason == ("3 consecutive control periods late (limit 3), the last "
                           "0.750 ms late")
    assert w.check(t) == []  # an event: reported once...
    t += 0.002
    w.period_done(0.0005, t)
    assert [x.name for x in w.check(t)] == ["deadline:misses"]  # ...and again while late


def test_deadline_on_time_means_lateness_not_above_zero():
    """Issue 4 safety (deadline-miss logic): a period finishing exactly at its deadline
    (lateness 0) is on time; any positive lateness is late."""
    w = DeadlineWatchdog(period=0.002, misses=1, max_lateness=0.01)
    w.period_done(0.0, 1.0)
    assert w.check(1.0) == []
    w.period_done(5e-324, 1.002)
    assert [t.name for t in w.check(1.002)] == ["deadline:misses"]


def test_deadline_hard_bound_trips_at_once():
    """Issue 4 safety (deadline-miss logic): one period later than max_lateness trips at
    once (exactly max_lateness does not), and the trip survives until the next check even
    if on-time periods follow."""
    w = DeadlineWatchdog(period=0.002, misses=5, max_lateness=0.0078125)
    w.period_done(0.0078125, 1.0)
    assert w.check(1.0) == []
    w.period_done(after(0.0078125), 1.01)
    w.period_done(0.02, 1.03)
    w.period_done(0.0, 1.032)  # on time again before anyone checked
    (trip,) = w.check(1.032)
    assert trip.name == "deadline:hard" and trip.value == 0.02  # the worst is kept
    assert trip.reason == "control period finished 20.000 ms late (limit 7.812 ms)"


def test_deadline_stalled_loop_is_found_by_the_clock():
    """Issue 4 safety (deadline-miss logic): a hung control loop feeds nothing; check
    trips once no period has completed for period + max_lateness (not before)."""
    w = DeadlineWatchdog(period=0.001953125, misses=5, max_lateness=0.0078125)
    w.period_done(0.0, 4.0)
    limit = 4.0 + 0.001953125 + 0.0078125
    assert w.next_deadline() == limit
    assert w.check(limit) == []
    (trip,) = w.check(after(limit))
    assert trip.name == "deadline:stalled"
    (trip,) = w.check(4.5)
    assert trip.reason.startswith("control loop completed no period for 500.000 ms")


# -- covariance ----------------------------------------------------------------------------
def test_covariance_boundary_and_reason():
    """Issue 4 safety (pose covariance watchdog): a sigma equal to its bound is fine, a
    hair above trips, per quantity, with the figure in mm or deg; a good pose clears."""
    w = CovarianceWatchdog(max_position_sigma=0.0009765625, max_rotation_sigma_deg=0.5)
    w.pose("opener", 0.0009765625, 0.5)
    assert w.check(0.0) == []
    w.pose("opener", after(0.0009765625), 0.5)
    assert [t.name for t in w.check(0.0)] == ["position_sigma:opener"]
    w.pose("opener", 0.0002, after(0.5))
    assert [t.name for t in w.check(0.0)] == ["rotation_sigma:opener"]
    w.pose("opener", 0.0015, 0.75)
    pos, rot = w.check(0.0)
    assert pos.reason == "pose of 'opener' has a position sigma of 1.500 mm (limit 0.977 mm)"
    assert rot.reason == "pose of 'opener' has a rotation sigma of 0.750 deg (limit 0.500 deg)"
    w.pose("opener", 0.0001, 0.1)
    assert w.check(0.0) == []


def test_covariance_nan_trips_and_negative_is_refused():
    """Issue 4 safety (pose covariance watchdog): an unknown (NaN) sigma trips; a negative
    one is malformed input."""
    w = CovarianceWatchdog(0.001, 1.0)
    w.pose("effector", math.nan, 0.1)
    assert [t.name for t in w.check(0.0)] == ["position_sigma:effector"]
    with pytest.raises(InputError, match="must not be negative"):
        w.pose("effector", -0.001, 0.1)


# -- the set, validation, threads ----------------------------------------------------------
def test_watchdog_set_from_settings_checks_all():
    """Issue 4 safety (WatchdogSet): built from the [safety] defaults and the control
    period, check(now) gathers the trips of every watchdog; next_deadline is the earliest."""
    s = SafetySection()
    ws = WatchdogSet.from_settings(s, period=1 / 500)
    assert ws.poses.limit == s.pose_timeout and ws.cameras.limit == s.camera_stall
    assert ws.stale_pose == s.stale_pose
    assert ws.deadline.misses == s.deadline_misses
    assert ws.next_deadline() is None
    ws.poses.fresh("opener", 0.0)
    ws.cameras.frame("left", 1, 0.0)
    ws.drivers.heartbeat("arm", 0.0)
    ws.deadline.period_done(0.0, 0.0)
    ws.covariance.pose("opener", 0.01, 0.1)
    assert ws.next_deadline() == pytest.approx(0.002 + s.max_period_lateness)
    names = sorted(t.name for t in ws.check(1.0))
    assert names == ["camera_stall:left", "deadline:stalled", "driver_silence:arm",
                     "position_sigma:opener", "stale_pose:opener"]
    assert all(isinstance(t, Trip) for t in ws.check(1.0))


@pytest.mark.parametrize(("make", "match"), [
    (lambda: StalePoseWatchdog(0.0), "positive"),
    (lambda: StalePoseWatchdog(math.nan), "finite"),
    (lambda: DeadlineWatchdog(0.002, 0, 0.01), "integer >= 1"),
    (lambda: DeadlineWatchdog(-0.002, 3, 0.01), "positive"),
    (lambda: CovarianceWatchdog(0.001, "x"), "number"),
    (lambda: StalePoseWatchdog(0.1).fresh("", 1.0), "non-empty name"),
    (lambda: StalePoseWatchdog(0.1).fresh("a", math.inf), "finite"),
    (lambda: StalePoseWatchdog(0.1).check(math.nan), "finite"),
])
def test_bad_input_is_a_clear_error(make, match):
    """Issue 4 safety (clear errors): bad limits, names, stamps and times raise InputError
    saying what is wrong."""
    with pytest.raises(InputError, match=match):
        make()


def test_feeds_and_checks_from_two_threads():
    """Issue 4 safety (thread-safe): a control thread feeding while another thread checks
    never trips on fresh data nor raises."""
    w = StalePoseWatchdog(0.5)
    d = DeadlineWatchdog(0.002, 3, 0.01)
    stop = threading.Event()
    errors: list[BaseException] = []

    def feed() -> None:
        try:
            for k in range(20000):
                w.fresh(f"s{k % 4}", k * 1e-4)
                d.period_done(0.0, k * 1e-4)
        except BaseException as exc:  # pragma: no cover - reported below
            errors.append(exc)
        finally:
            stop.set()

    t = threading.Thread(target=feed)
    t.start()
    trips = []
    while not stop.is_set():
        trips += w.check(0.0) + d.check(0.0)
    t.join()
    assert errors == [] and trips == []
