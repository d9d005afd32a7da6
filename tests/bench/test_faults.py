"""The fault campaign's pure parts (issue 30), without a daemon: matching acknowledged
commands with the audit log in both record formats, the RSS trend, the /health gaps and
the configuration the campaign writes."""

from __future__ import annotations

import json
import os
import stat
import tomllib
from pathlib import Path

import pytest

from oralnav.bench.faults import (
    answer_gaps,
    audited_commands,
    large_targets_body,
    match_acks,
    parse_audit,
    rss_trend,
    write_daemon_config,
    write_tokens,
)

SIM = Path(__file__).resolve().parents[2] / "config" / "sim.toml"


def _single(path: str, status: int) -> str:
    return json.dumps({"time": "2026-01-01T00:00:00.000Z", "who": "bench", "method": "POST",
                       "path": path, "body": "", "status": status, "result": "ok"})


def test_single_records_match_in_order_and_a_lost_one_is_missing() -> None:
    """Every command answered 200 must have a record with its path and status 200, in the
    order of the answers; refusals and a torn last line do not count for it."""
    text = "\n".join([_single("/targets", 200), _single("/procedure/start", 409),
                      _single("/estop", 200), _single("/reset", 200)]) + '\n{"time": "2026-'
    records, torn = parse_audit(text)
    assert (len(records), torn) == (4, 1)
    cmds = audited_commands(records)
    assert match_acks(["/targets", "/estop", "/reset"], cmds)["missing"] == []
    # an acknowledged start has no 200 record: missing; order matters too
    m = match_acks(["/targets", "/procedure/start", "/estop"], cmds)
    assert m["missing"] == [{"index": 1, "path": "/procedure/start"}]
    assert match_acks(["/reset", "/estop"], cmds)["audited"] == 1


def test_write_ahead_intent_and_outcome_records_count_as_audited() -> None:
    """The write-ahead format: an intent with an id and the path, later its outcome with the
    status naming the intent's id. An intent without an outcome is no finished command."""
    lines = [{"phase": "intent", "id": 7, "path": "/targets", "method": "POST"},
             {"phase": "intent", "id": 8, "path": "/estop", "method": "POST"},
             {"phase": "outcome", "id": 7, "status": 200, "result": "ok"},
             {"kind": "outcome", "intent": 8, "outcome": {"status": 200}},
             {"phase": "intent", "id": 9, "path": "/reset", "method": "POST"}]
    records, torn = parse_audit("\n".join(json.dumps(x) for x in lines))
    assert torn == 0
    assert audited_commands(records) == [("/targets", 200), ("/estop", 200)]
    m = match_acks(["/targets", "/estop", "/reset"], audited_commands(records))
    assert m["missing"] == [{"index": 2, "path": "/reset"}]


def test_rss_trend_tells_a_warm_up_from_a_leak() -> None:
    """Growth during warm-up then flat is bounded; steady growth after it is not; too few
    samples after warm-up decide nothing."""
    t = [5.0 * k for k in range(120)]  # 10 minutes
    flat = [600.0 + min(tk, 180.0) * 0.7 for tk in t]  # +126 MiB in 3 min, then flat
    r = rss_trend(t, flat, warmup_s=180.0)
    assert r["warmup"]["growth_mib"] == pytest.approx(0.7 * 175, rel=1e-6)
    assert r["after_warmup"]["slope_mib_per_min"] == pytest.approx(0.0, abs=1e-9)
    assert r["bounded"] is True
    leak = [600.0 + tk / 60.0 * 2.0 for tk in t]  # 2 MiB/min throughout
    r = rss_trend(t, leak, warmup_s=180.0)
    assert r["after_warmup"]["slope_mib_per_min"] == pytest.approx(2.0, rel=1e-6)
    assert r["bounded"] is False
    assert rss_trend([0.0, 10.0], [1.0, 2.0], warmup_s=180.0)["bounded"] is None


def test_health_gaps_include_a_request_that_never_came_back() -> None:
    """The gap after the last answer runs to the window's end: a stall is never hidden."""
    gaps = answer_gaps([1.01, 1.02, 1.03, 5.0], 1.0, 1.5)
    assert max(gaps) == pytest.approx(0.47)
    assert sum(gaps) == pytest.approx(0.5)


def test_large_body_is_issue_30s() -> None:
    body = large_targets_body(10_000)
    doc = json.loads(body)
    assert len(body) >= 10_000 and doc["targets"][0] == {"name": "s0", "p_OM": [0.01, 0, 0]}


def test_config_points_at_the_sim_files_and_sets_the_robot_pc_lateness(tmp_path) -> None:
    """The written configuration names the embedded cell's files absolutely, its own tokens
    file (0600, not group/world writable) and audit log, a loopback port, and the robot PC's
    max_period_lateness when asked."""
    tokens = tmp_path / "tokens.toml"
    token = write_tokens(tokens)
    assert len(token) > 20 and not stat.S_IMODE(os.stat(tokens).st_mode) & 0o077
    cfg = write_daemon_config(tmp_path / "d.toml", port=18999, tokens_file=tokens,
                              audit_log=tmp_path / "audit.jsonl", lateness=0.01, base=SIM)
    doc = tomllib.loads(cfg.read_text())
    base = tomllib.loads(SIM.read_text())
    assert doc["api"] == {**base.get("api", {}), "host": "127.0.0.1", "port": 18999,
                          "tokens_file": str(tokens.resolve()),
                          "audit_log": str((tmp_path / "audit.jsonl").resolve())}
    assert doc["safety"]["max_period_lateness"] == 0.01
    assert Path(doc["cell"]["rig"]).is_absolute() and Path(doc["cell"]["rig"]).is_file()
    assert doc["cell"]["backend"] == base["cell"]["backend"]
