"""Issue 35 item 3, "honest verdicts": the control bench calls its target met only from
what it measured, and never for a run whose loop latched a stop."""

from __future__ import annotations

import math

import pytest

from oralnav.bench.control import P99_TARGET_MS, verdict_of


@pytest.mark.parametrize("p99, latched, met", [
    (0.4, False, True),
    (P99_TARGET_MS, False, True),
    (1.6, False, False),
    (0.4, True, False),       # a quiet p99 after a latched stop is no evidence
    (math.nan, False, False),  # no figure: not met
])
def test_a_target_is_met_only_when_measured_and_not_stopped(p99, latched, met):
    verdict = verdict_of(p99, latched)
    assert (verdict == "met") == met
    if latched:
        assert "latched a stop" in verdict
    elif not met:
        assert verdict.startswith("missed: p99")
