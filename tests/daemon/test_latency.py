"""Where the capture-to-command latency goes (issue 32, "Latency, measured"):
``oralnav.daemon.latency`` splits each tracked round into its delivery (capture to the
frames' arrival) and its tracking (arrival to the poses published), and the core's
``latency_ms`` shows both beside the control loop's whole figure."""

from __future__ import annotations

import numpy as np
import pytest

from oralnav.config.daemon import load_config
from oralnav.daemon.core import DaemonCore
from oralnav.daemon.latency import StageTimes, percentiles_ms
from oralnav.realtime.control_loop import LATENCY_DTYPE
from oralnav.safety.watchdogs import WatchdogSet


def test_percentiles_are_in_milliseconds_and_none_when_empty():
    """Durations in s give n, p50, p99 and max in ms; nothing measured gives None."""
    s = np.linspace(0.0, 0.1, 101)   # 0..100 ms
    out = percentiles_ms(s)
    assert out["n"] == 101
    assert out["p50"] == pytest.approx(50.0)
    assert out["p99"] == pytest.approx(99.0)
    assert out["max"] == pytest.approx(100.0)
    assert percentiles_ms(np.zeros(0)) is None


def test_each_round_splits_into_delivery_and_tracking():
    """A round captured at t, arrived at t + d and published at t + d + k reads as
    delivery d and tracking k; only the last rounds kept count."""
    times = StageTimes(keep=3)
    assert times.summary() is None
    times.record(10.0, 10.5, 10.6)      # pushed out by the three after it
    for t in (20.0, 21.0, 22.0):
        times.record(t, t + 0.040, t + 0.050)
    out = times.summary()
    assert out["delivery"]["n"] == 3
    assert out["delivery"]["max"] == pytest.approx(40.0)
    assert out["tracking"]["p50"] == pytest.approx(10.0)
    assert out["tracking"]["max"] == pytest.approx(10.0)


class _Loop:
    """The control port's latency ring as the core reads it."""

    def __init__(self, pairs: list[tuple[float, float]]) -> None:
        self.rec = np.array(pairs, dtype=float).reshape(-1, 2)

    def read_latency(self) -> np.ndarray:
        out = np.zeros(len(self.rec), dtype=LATENCY_DTYPE)
        out["t_capture"], out["t_command"] = self.rec[:, 0], self.rec[:, 1]
        return out


def _core(loop: _Loop) -> DaemonCore:
    cfg = load_config()
    return DaemonCore(loop, WatchdogSet.from_settings(cfg.settings.safety, 0.002))


def test_core_shows_the_whole_latency_and_its_stages():
    """/status's latency_ms: the loop's capture-to-command percentiles, and the tracked
    rounds' stages; tracking before any goal shows the stages with no whole figure, and
    nothing at all is None."""
    core = _core(_Loop([]))
    assert core.latency_ms() is None
    core.stage_times.record(1.0, 1.002, 1.010)
    early = core.latency_ms()
    assert early["n"] == 0 and early["p99"] is None
    assert early["stages"]["delivery"]["p50"] == pytest.approx(2.0)
    core.control = _Loop([(1.0, 1.012), (2.0, 2.014)])
    out = core.latency_ms()
    assert out["n"] == 2 and out["max"] == pytest.approx(14.0)
    assert out["stages"]["tracking"]["p50"] == pytest.approx(8.0)
