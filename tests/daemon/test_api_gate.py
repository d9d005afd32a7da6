"""Limits on failed authentication (``oralnav.daemon.api_gate``): the pure
:class:`FailureLimiter` with the time passed in, and the gate in front of the operator API.

Requirement (issue 30, "Also found"): 3,000 wrong tokens then the right one must not
succeed, and a flood of unauthenticated requests must not grow the fsynced audit log without
bound: per client address, a burst of failed authentications locks the address out (429
with Retry-After, from the headers alone, the right token refused too) for a window that
doubles on repeats; other addresses are never affected; while locked out the refused
requests are audited in aggregate.
"""

from __future__ import annotations

import json

import httpx
import pytest

from oralnav.daemon.api import build_app
from oralnav.daemon.api_gate import (
    AuthLimits,
    FailureLimiter,
    LockoutEvent,
    client_key,
)
from oralnav.daemon.audit import AuditLog
from oralnav.daemon.auth import TokenStore
from tests.daemon.test_api import FakeOps

LIMITS = AuthLimits(burst=5, refill_s=10.0, lockout_s=60.0, lockout_max_s=300.0,
                    memory_s=1000.0, summary_s=30.0, max_clients=100)


# -- the pure logic -------------------------------------------------------------------------
def test_a_burst_of_failures_locks_the_address_out():
    """issue 30: the burst-th failure in a row starts a lockout (a "start" event); while it
    lasts every request is refused with the seconds left; it ends after its window."""
    lim = FailureLimiter(LIMITS)
    events = [lim.failure("10.0.0.1", 100.0 + 0.01 * i) for i in range(5)]
    assert events[:4] == [None] * 4
    assert events[4] == LockoutEvent("start", "10.0.0.1", 60.0, 1, 0)
    assert lim.retry_after("10.0.0.1", 110.0) == pytest.approx(50.04)
    assert lim.retry_after("10.0.0.2", 110.0) is None  # another address: not affected
    assert lim.retry_after("10.0.0.1", 160.05) is None  # the window is over


def test_slow_failures_are_forgiven():
    """issue 30: one failure is forgiven every refill_s: a client that stays below that rate
    is never locked out (a typo now and then costs nothing)."""
    lim = FailureLimiter(LIMITS)
    assert all(lim.failure("a", 10.0 * i) is None for i in range(200))


def test_repeated_lockouts_double_up_to_the_bound_and_are_forgotten():
    """issue 30: the lockout's own time refills nothing, so the first failure after it
    starts the next lockout, twice as long, up to lockout_max_s; memory_s after the last
    one ended they start again at lockout_s."""
    lim = FailureLimiter(LIMITS)
    t = 0.0
    for _ in range(5):
        ev = lim.failure("a", t)
    lengths = [ev.seconds]
    for _ in range(4):
        t += ev.seconds  # the moment it ends
        ev = lim.failure("a", t)
        assert ev is not None and ev.kind == "start"
        lengths.append(ev.seconds)
    assert lengths == [60.0, 120.0, 240.0, 300.0, 300.0]
    assert ev.strike == 5
    t += ev.seconds + LIMITS.memory_s + 1.0  # long quiet: the bucket is full again too
    assert [lim.failure("a", t + i * 0.01) for i in range(5)][-1].seconds == 60.0


def test_summaries_are_bounded_and_the_end_counts_the_rest():
    """issue 30: while locked out the refused requests are only counted: a summary at most
    every summary_s, and the end with the count since the last record; every refused
    request is in exactly one of them."""
    lim = FailureLimiter(LIMITS)
    for i in range(5):
        lim.failure("a", i * 0.01)
    t, refused = 1.0, 0
    events: list[LockoutEvent] = []
    while t < 70.0:  # 100 requests a second for the whole lockout and beyond
        if lim.retry_after("a", t) is not None:
            refused += 1
        events += lim.due(t)
        t += 0.01
    kinds = [e.kind for e in events]
    assert kinds == ["summary", "end"], kinds  # 60 s window, 30 s summaries
    assert sum(e.refused for e in events) == refused > 5000
    assert lim.due(200.0, force=True) == []


def test_the_table_of_addresses_is_bounded():
    """issue 30: a flood from many addresses cannot grow the limiter's memory: past
    max_clients the address idle longest is forgotten (a lockout forgotten so is ended,
    and its end is still reported)."""
    lim = FailureLimiter(LIMITS)
    for i in range(5):
        lim.failure("first", i * 0.01)
    for i in range(250):
        lim.failure(f"10.1.{i // 256}.{i % 256}", 1.0)
    assert len(lim) == LIMITS.max_clients
    assert lim.retry_after("first", 2.0) is None
    assert [(e.kind, e.client) for e in lim.due(2.0)] == [("end", "first")]


def test_client_key_groups_an_ipv6_host_by_its_64():
    """issue 30: clients are limited by IP address; IPv6 by /64 (one host holds all of
    it), an IPv4-mapped address as IPv4."""
    assert client_key("192.0.2.7") == "192.0.2.7"
    assert client_key("2001:db8:1:2:aaaa::1") == client_key("2001:db8:1:2::ffff") == \
        "2001:db8:1:2::/64"
    assert client_key("::ffff:192.0.2.7") == "192.0.2.7"
    assert client_key(None) == "?" and client_key("testclient") == "testclient"


@pytest.mark.parametrize("kw, where", [
    ({"burst": 0}, "burst"), ({"refill_s": float("nan")}, "refill_s"),
    ({"lockout_s": 10.0, "lockout_max_s": 5.0}, "lockout_max_s"),
    ({"burst": 2.5}, "whole numbers")])
def test_limits_are_checked(kw, where):
    """issue 30: impossible limits are refused naming the field."""
    with pytest.raises(ValueError, match=where):
        AuthLimits(**kw)


# -- the gate -------------------------------------------------------------------------------
class Clock:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


@pytest.fixture
def gated(tmp_path):
    """The API over the fake core with a fake clock and small limits."""
    clear = TokenStore.generate(tmp_path / "tokens.toml")
    audit = AuditLog(tmp_path / "audit.jsonl").open()
    clock = Clock()
    ops = FakeOps()
    app = build_app(ops, TokenStore.from_file(tmp_path / "tokens.toml"), audit,
                    auth_limiter=FailureLimiter(LIMITS, clock=clock))

    class G:
        pass

    g = G()
    g.app, g.ops, g.clock, g.path = app, ops, clock, tmp_path / "audit.jsonl"
    g.op = {"Authorization": f"Bearer {clear['operator']}"}
    g.obs = {"Authorization": f"Bearer {clear['observer']}"}
    g.bad = {"Authorization": "Bearer not-a-token"}
    yield g
    audit.close()


def _client(app, ip: str) -> httpx.AsyncClient:
    return httpx.AsyncClient(transport=httpx.ASGITransport(app=app, client=(ip, 40000)),
                             base_url="http://oralnav")


def _records(g) -> list[dict]:
    return [json.loads(x) for x in g.path.read_text().splitlines()]


async def test_lockout_refuses_even_the_right_token_and_spares_other_clients(gated):
    """issue 30: after `burst` wrong tokens (on reads and commands alike) the address gets
    429 with Retry-After for everything, the right token included, and the core is not
    reached; another address is not affected; after the window the right token works."""
    g = gated
    async with _client(g.app, "203.0.113.9") as bad, _client(g.app, "198.51.100.4") as good:
        for i in range(LIMITS.burst):
            r = await (bad.get("/status", headers=g.bad) if i % 2
                       else bad.post("/reset", headers=g.bad))
            assert r.status_code == 401
        for call in (lambda: bad.get("/status", headers=g.obs),
                     lambda: bad.post("/reset", headers=g.op),
                     lambda: bad.post("/procedure/start", headers=g.op),
                     lambda: bad.post("/targets", headers=g.op, content=b"x" * 200_000)):
            r = await call()
            assert r.status_code == 429, r.text
            assert 0 < int(r.headers["retry-after"]) <= 60
            assert "too many failed authentications" in r.json()["detail"]
        assert g.ops.calls == []
        assert (await good.get("/status", headers=g.obs)).status_code == 200
        assert (await good.post("/procedure/start", headers=g.op)).status_code == 200
        assert (await bad.get("/health")).status_code == 200  # liveness stays open
        g.clock.t += 61.0
        assert (await bad.get("/status", headers=g.obs)).status_code == 200
        assert (await bad.post("/procedure/pause", headers=g.op)).status_code == 200
    assert g.ops.calls == [("procedure", "start", "operator"), ("procedure", "pause", "operator")]


async def test_the_estop_of_a_locked_out_address_still_runs(gated):
    """issue 30: a lockout never takes the e-stop away from a valid operator token (another
    client behind the same proxy address may be the one failing); a wrong token on it is
    refused like any other request."""
    g = gated
    async with _client(g.app, "203.0.113.9") as c:
        for _ in range(LIMITS.burst):
            await c.get("/status", headers=g.bad)
        assert (await c.post("/estop", headers=g.bad)).status_code == 429
        assert (await c.post("/estop", headers=g.obs)).status_code == 429
        r = await c.post("/estop", headers=g.op, json={"reason": "drill"})
        assert r.status_code == 200 and g.ops.state == "ESTOP"
        assert (await c.post("/reset", headers=g.op)).status_code == 429


async def test_telemetry_failures_count_and_a_locked_address_gets_429(gated):
    """issue 30: a wrong token on the telemetry websocket counts like any other failure,
    and a locked-out address's handshake is refused with an HTTP 429."""
    g = gated

    async def handshake(query: str) -> dict:
        sent: list[dict] = []
        first = True

        async def receive():
            nonlocal first
            if first:
                first = False
                return {"type": "websocket.connect"}
            return {"type": "websocket.disconnect", "code": 1000}

        async def send(message):
            sent.append(message)

        scope = {"type": "websocket", "asgi": {"version": "3.0"}, "http_version": "1.1",
                 "scheme": "ws", "path": "/telemetry", "raw_path": b"/telemetry",
                 "query_string": query.encode(), "root_path": "", "headers": [],
                 "client": ("203.0.113.9", 40000), "server": ("127.0.0.1", 8750),
                 "subprotocols": [], "extensions": {"websocket.http.response": {}}}
        await g.app(scope, receive, send)
        return next(m for m in sent if m["type"] == "websocket.http.response.start")

    for _ in range(LIMITS.burst):
        assert (await handshake("token=wrong"))["status"] == 401
    start = await handshake(f"token={g.obs['Authorization'].split()[1]}")
    assert start["status"] == 429
    assert (b"retry-after", b"60") in start["headers"]


async def test_a_flood_of_refused_requests_leaves_a_bounded_audit(gated):
    """issue 30: 500 unauthenticated requests leave `burst` records of their own, one when
    the lockout starts and one summary when it ends, which counts every request it
    refused; the audit log grows by a few records, not 500."""
    g = gated
    async with _client(g.app, "203.0.113.9") as c:
        for _ in range(500):
            assert (await c.post("/procedure/start")).status_code in (401, 429)
        g.clock.t += 61.0
        # the summary is written by the next request through the gate, whoever sends it
        async with _client(g.app, "198.51.100.4") as other:
            assert (await other.get("/status", headers=g.obs)).status_code == 200
    recs = _records(g)
    assert [r["status"] for r in recs] == [401] * LIMITS.burst + [429, 429]
    start, end = recs[-2:]
    assert (start["lockout"], end["lockout"]) == ("start", "end")
    assert start["client"] == end["client"] == "203.0.113.9"
    assert end["refused"] == 500 - LIMITS.burst and end["lockout_s"] == 60.0
    assert all(r["phase"] == "single" for r in recs)
    assert g.ops.calls == []


def test_the_configuration_sets_the_limits_and_defaults_to_the_constants(tmp_path):
    """issue 30: [api]'s defaults are the gate's and the audit log's constants, and what
    [api] sets reaches the limiter and the audit log."""
    from oralnav.config.daemon import ApiSection
    from oralnav.daemon import api_gate, audit

    assert AuthLimits.from_config(ApiSection()) == AuthLimits()
    assert (api_gate.AUTH_FAILURE_BURST, api_gate.AUTH_FAILURE_REFILL_S,
            api_gate.AUTH_LOCKOUT_S, api_gate.AUTH_LOCKOUT_MAX_S) == (10, 6.0, 60.0, 900.0)
    log = AuditLog.from_config(ApiSection(), {"STATE_DIRECTORY": str(tmp_path)})
    assert (log.path, log.max_bytes, log.keep) == \
        (tmp_path / "oralnav-audit.jsonl", audit.DEFAULT_MAX_BYTES, audit.DEFAULT_KEEP)
    api = ApiSection(audit_max_bytes=1 << 20, audit_keep=2, auth_failure_burst=3,
                     auth_lockout_s=5.0, auth_lockout_max_s=7.0)
    assert AuthLimits.from_config(api) == AuthLimits(burst=3, lockout_s=5.0,
                                                     lockout_max_s=7.0)
    log = AuditLog.from_config(api, {})
    assert (log.max_bytes, log.keep) == (1 << 20, 2)
