"""The operator REST API (``oralnav.daemon.api``) against a fake daemon core.

Requirement (issue 4, REST API): observer reads, operator commands; 401/403 before anything
else; StateError -> 409, bad values -> 4xx with a reason, and in every refusal nothing in
the core changes; every command is audited and refused (503) when it cannot be; live
telemetry over a websocket; ``serve()`` runs uvicorn on the daemon's own anyio loop.
"""

from __future__ import annotations

import contextlib
import json
import signal
import socket
import threading
import time
from collections.abc import AsyncIterator
from typing import Any

import anyio
import httpx
import numpy as np
import pytest
import websockets

from oralnav.daemon import audit as audit_mod
from oralnav.daemon.api import build_app, serve
from oralnav.daemon.api_gate import BODY_LIMITS, DEFAULT_LIMIT
from oralnav.daemon.audit import AuditLog
from oralnav.daemon.auth import TokenStore
from oralnav.daemon.guidance import GuidePlanError
from oralnav.daemon.schemas import SutureTarget, jsonable
from oralnav.safety.errors import LimitError, StateError


class FakeOps:
    """A tiny state machine standing in for the daemon core; ``calls`` logs every
    state-changing call that reached it."""

    def __init__(self) -> None:
        self.state = "IDLE"
        self.target_list: list[SutureTarget] = [SutureTarget(name="t0", p_OM=(0.01, 0, 0))]
        self.calls: list[tuple] = []
        self.ticks = 0

    healthy: tuple[bool, str | None] = (True, None)

    def health(self) -> tuple[bool, str | None]:
        return self.healthy

    def status(self) -> dict[str, Any]:
        return {"state": self.state, "reasons": [], "rate_hz": np.float64(500.0)}

    def poses(self) -> dict[str, Any]:
        return {"T_C_OM": np.eye(4), "t": 12.5, "stale": float("nan")}

    def telemetry(self) -> dict[str, Any]:
        self.ticks += 1
        return {"tick": self.ticks, "state": self.state, "p": np.zeros(3), "err": float("inf")}

    def estop(self, who: str, reason: str) -> None:
        self.calls.append(("estop", who, reason))
        self.state = "ESTOP"

    def reset(self, who: str) -> None:
        if self.state != "ESTOP":
            raise StateError(f"nothing to reset: state is {self.state}")
        self.calls.append(("reset", who))
        self.state = "IDLE"

    def recover(self, device: str, who: str) -> None:
        if self.state != "ESTOP":
            raise StateError(f"cannot recover the {device} in {self.state}")
        self.calls.append(("recover", device, who))

    def procedure(self, action: str, who: str) -> None:
        allowed = {"start": "IDLE", "pause": "RUNNING", "resume": "PAUSED", "abort": "RUNNING"}
        if self.state != allowed[action]:
            raise StateError(f"cannot {action} while {self.state}")
        self.calls.append(("procedure", action, who))
        self.state = {"start": "RUNNING", "pause": "PAUSED", "resume": "RUNNING",
                      "abort": "IDLE"}[action]

    def targets(self) -> list[SutureTarget]:
        return list(self.target_list)

    def planned_targets(self) -> list[SutureTarget]:
        return [SutureTarget(name="planned_1", p_OM=(0.02, 0.0, 0.0))]

    def select_target(self, name: str, who: str) -> None:
        if name not in {t.name for t in self.target_list}:
            raise StateError(f"cannot select {name!r}: no such suture target")
        self.calls.append(("select_target", name, who))

    def set_targets(self, targets: list[SutureTarget], who: str) -> None:
        if self.state == "RUNNING":
            raise StateError("targets cannot change while RUNNING")
        if any(t.name.startswith("limit") for t in targets):
            raise LimitError("t1 lies outside the virtual fixture workspace")
        if any(t.name.startswith("boom") for t in targets):
            raise RuntimeError("core bug")
        self.calls.append(("set_targets", who))
        self.target_list = list(targets)

    # guided insertion: "bad" scenes fail validation, "unsafe" ones have no safe placement
    plan: dict[str, Any] | None = None
    guiding = False
    plan_thread: threading.Thread | None = None

    def plan_guide(self, scene: str, T_OM_F: Any, who: str,
                   seed: int | None = None) -> dict[str, Any]:
        self.plan_thread = threading.current_thread()
        if "bad" in scene:
            raise GuidePlanError(f"planning scene: {scene}: [hole] axis: field required")
        if "unsafe" in scene:
            raise StateError(f"no collision-free placement in {scene}: nothing was armed")
        if self.guiding:
            raise StateError("cannot plan while a guided insertion is running")
        self.calls.append(("plan_guide", scene, who, seed))
        self.plan = {"scene": scene, "T_OM_F": np.asarray(T_OM_F),
                     "placement": {"d_T": 0.0655, "collision_free": True},
                     "fixture": {"frame": "F", "target": np.array([0.0, 0.0155, 0.05]),
                                 "direction": np.array([0.0, 0.0, 1.0])}}
        return self.plan

    def start_guide(self, who: str) -> None:
        if self.plan is None:
            raise StateError("no insertion plan: POST /guide/plan first")
        if self.state != "IDLE" or self.guiding:
            raise StateError(f"cannot start guidance while {self.state}")
        self.calls.append(("start_guide", who))
        self.guiding = True

    def stop_guide(self, who: str) -> None:
        self.calls.append(("stop_guide", who))
        self.guiding, self.plan = False, None

    def guide(self) -> dict[str, Any]:
        return {"phase": "active" if self.guiding else "idle", "plan": self.plan,
                "rod_distance_m": float("nan")}

    # needle procedure: a cell must be loaded; steps in order; "NR" is always refused
    needle_trial: int | None = None
    needle_done: list[str] = []

    def needle(self) -> dict[str, Any]:
        return {"cell": self.needle_trial, "done": list(self.needle_done)}

    def needle_cell(self, trial: int, difficulty: float, who: str,
                    servo: str = "off") -> dict[str, Any]:
        self.plan_thread = threading.current_thread()
        self.calls.append(("needle_cell", trial, difficulty, who, servo))
        self.needle_trial, self.needle_done = trial, []
        return self.needle()

    def needle_step(self, step: str, who: str) -> dict[str, Any]:
        if self.needle_trial is None:
            raise StateError("no needle cell: POST /needle/cell first")
        if step == "NR":
            raise StateError("needle step NR refused: the needle tracker has not converged")
        self.calls.append(("needle_step", step, who))
        self.needle_done.append(step)
        return {"result": {"step": step, "ok": True}, "next": None}


    # temporal calibration: refused unless IDLE (standing in for READY)
    temporal_runs: list[dict] = []

    def start_temporal(self, body: Any, who: str) -> dict[str, Any]:
        if self.state != "IDLE":
            raise StateError(f"cannot calibrate time in {self.state}")
        self.calls.append(("start_temporal", body.model_dump(), who))
        self.temporal_runs = [body.model_dump()]
        return {"phase": "moving"}

    def temporal(self, samples: bool = False) -> dict[str, Any]:
        doc = {"phase": "moving" if self.temporal_runs else "idle", "result": None}
        if samples:
            doc["samples"] = {"t_cam": [], "p_C": [], "t_arm": [], "p_B": []}
        return doc

    # session recording (issue 33 item 4): the recorder's own tests are test_recording.py
    recording_state = "idle"

    def recording(self) -> dict[str, Any]:
        return {"state": self.recording_state, "path": None, "error": None}

    def start_recording(self, body: Any, who: str) -> dict[str, Any]:
        if self.recording_state == "recording":
            raise StateError("already recording")
        self.calls.append(("start_recording", body.path, who))
        self.recording_state = "recording"
        return self.recording()

    def stop_recording(self, who: str) -> dict[str, Any]:
        self.calls.append(("stop_recording", who))
        self.recording_state = "stopped"
        return self.recording()


POSTS = ["/estop", "/reset", "/procedure/start", "/procedure/pause", "/procedure/resume",
         "/procedure/abort", "/targets", "/guide/plan", "/guide/start", "/guide/stop",
         "/needle/cell", "/needle/NG", "/recover/effector", "/calibration/temporal",
         "/targets/select", "/recording/start", "/recording/stop"]
GOOD_TARGETS = {"targets": [{"name": "s1", "p_OM": [0.01, 0.02, 0.0]},
                            {"name": "s2", "p_OM": [0.0, -0.01, 0.005], "n_OM": [0, 0, 2]}]}
EYE4 = np.eye(4).tolist()
GOOD_PLAN = {"scene": "config/examples/cylinder_case.toml", "T_OM_F": EYE4, "seed": 3}


@pytest.fixture
def rig(tmp_path):
    """A fake core, generated tokens, an open audit log and an app over them."""
    clear = TokenStore.generate(tmp_path / "tokens.toml")
    store = TokenStore.from_file(tmp_path / "tokens.toml")
    audit = AuditLog(tmp_path / "audit.jsonl").open()
    ops = FakeOps()
    app = build_app(ops, store, audit, telemetry_hz=50.0)

    class Rig:
        pass

    r = Rig()
    r.ops, r.audit, r.app, r.path = ops, audit, app, tmp_path / "audit.jsonl"
    r.op = {"Authorization": f"Bearer {clear['operator']}"}
    r.obs = {"Authorization": f"Bearer {clear['observer']}"}
    r.tokens = clear
    yield r
    audit.close()


@pytest.fixture
async def client(rig):
    transport = httpx.ASGITransport(app=rig.app)
    async with httpx.AsyncClient(transport=transport, base_url="http://oralnav") as c:
        yield c


def audit_lines(rig) -> list[dict]:
    return [json.loads(x) for x in rig.path.read_text().splitlines()]


def audit_results(rig) -> list[dict]:
    """The records that say how a request ended: outcomes and single records, each
    checked against its intent when it has one (issue 30: write-ahead)."""
    recs = audit_lines(rig)
    intents = {x["id"]: x for x in recs if x["phase"] == "intent"}
    out = []
    for x in recs:
        if x["phase"] == "outcome":
            intent = intents.pop(x["id"])
            assert recs.index(intent) < recs.index(x)
            assert (intent["who"], intent["method"], intent["path"]) == \
                (x["who"], x["method"], x["path"])
            out.append({**x, "body": intent["body"]})
        elif x["phase"] == "single":
            out.append(x)
    assert not intents, f"intents without an outcome: {intents}"
    return out


def body_for(path: str) -> dict | None:
    return {"/targets": GOOD_TARGETS, "/guide/plan": GOOD_PLAN,
            "/needle/cell": {"trial": 3}, "/calibration/temporal": {},
            "/targets/select": {"name": "t0"},
            "/recording/start": {"path": "session.mcap"}}.get(path)


# -- roles -------------------------------------------------------------------------------
async def test_health_needs_no_token(client):
    """issue 4 REST: GET /health answers {"ok": true} without a token."""
    r = await client.get("/health")
    assert r.status_code == 200 and r.json()["ok"] is True


@pytest.mark.parametrize("path", ["/status", "/poses", "/targets", "/guide", "/needle",
                                  "/calibration/temporal", "/recording"])
async def test_reads_need_a_valid_token(client, rig, path):
    """issue 4 REST: GETs answer 401 with WWW-Authenticate: Bearer without a token or with
    an unknown one, and 200 for an observer."""
    for headers in ({}, {"Authorization": "Bearer nope"}, {"Authorization": "Basic abc"}):
        r = await client.get(path, headers=headers)
        assert r.status_code == 401 and r.headers["www-authenticate"].startswith("Bearer")
        assert r.json()["detail"]
    assert (await client.get(path, headers=rig.obs)).status_code == 200
    assert (await client.get(path, headers=rig.op)).status_code == 200  # operator >= observer


async def test_reads_return_plain_json(client, rig):
    """issue 4 REST: status, poses and targets come back as plain JSON (numpy arrays as
    lists, NaN as null)."""
    assert (await client.get("/status", headers=rig.obs)).json() == \
        {"state": "IDLE", "reasons": [], "rate_hz": 500.0}
    poses = (await client.get("/poses", headers=rig.obs)).json()
    assert poses["T_C_OM"][3] == [0.0, 0.0, 0.0, 1.0] and poses["stale"] is None
    assert (await client.get("/targets", headers=rig.obs)).json() == \
        {"targets": [{"name": "t0", "p_OM": [0.01, 0.0, 0.0], "n_OM": None}]}


def test_every_post_route_is_covered(rig):
    """issue 4 REST: the role tests below cover every POST route the app has."""
    posts = {r.path for r in rig.app.routes if "POST" in getattr(r, "methods", ())}
    assert posts == {"/estop", "/reset", "/procedure/{action}", "/targets", "/guide/plan",
                     "/guide/start", "/guide/stop", "/needle/cell", "/needle/{step}",
                     "/recover/{device}", "/calibration/temporal", "/targets/select",
                     "/recording/start", "/recording/stop"}


@pytest.mark.parametrize("path", POSTS)
async def test_observer_gets_403_on_every_state_change(client, rig, path):
    """issue 4 REST: an observer gets 403 on every state-changing endpoint; nothing in the
    core is called, and the refusal is audited."""
    r = await client.post(path, headers=rig.obs, json=body_for(path))
    assert r.status_code == 403 and "operator" in r.json()["detail"]
    assert rig.ops.calls == [] and rig.ops.state == "IDLE"
    (rec,) = audit_lines(rig)
    assert (rec["status"], rec["who"], rec["role"], rec["path"]) == \
        (403, "observer", "observer", path)


@pytest.mark.parametrize("path", POSTS)
async def test_401_comes_before_body_checks(client, rig, path):
    """issue 4 REST: without a valid token every POST is 401, even with a malformed or
    invalid body (a stranger learns nothing about validation); nothing is called."""
    for headers in ({}, {"Authorization": "Bearer wrong"}):
        for content in (b"{not json", b'{"bogus": 1}'):
            r = await client.post(path, headers={**headers, "content-type": "application/json"},
                                  content=content)
            assert r.status_code == 401, (headers, content, r.text)
            assert r.headers["www-authenticate"].startswith("Bearer")
    r = await client.post(path, headers=rig.obs | {"content-type": "application/json"},
                          content=b"{not json")
    assert r.status_code == 403
    assert rig.ops.calls == []
    assert [x["status"] for x in audit_lines(rig)] == [401, 401, 401, 401, 403]


# -- the gate: authentication before the body, bounded bodies (issue 30) -----------------
async def _asgi_post(app, path: str, headers: dict[str, str], chunks: list[bytes]):
    """POST straight through ASGI; returns (status, JSON body, chunks the app read)."""
    read = []
    pending = list(chunks)

    async def receive():
        if not pending:
            return {"type": "http.disconnect"}
        chunk = pending.pop(0)
        read.append(chunk)
        return {"type": "http.request", "body": chunk, "more_body": bool(pending)}

    sent = []

    async def send(message):
        sent.append(message)

    scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1",
             "method": "POST", "scheme": "http", "path": path, "raw_path": path.encode(),
             "query_string": b"", "root_path": "", "client": ("127.0.0.1", 5555),
             "server": ("127.0.0.1", 8750),
             "headers": [(k.lower().encode(), v.encode()) for k, v in headers.items()]}
    await app(scope, receive, send)
    start = next(m for m in sent if m["type"] == "http.response.start")
    body = b"".join(m.get("body", b"") for m in sent if m["type"] == "http.response.body")
    return start["status"], json.loads(body), read


async def test_a_stranger_is_refused_before_a_byte_of_the_body_is_read(rig):
    """issue 30, serious 1: a POST without a valid token is 401 (an observer's 403) from
    its headers alone: the gate never reads the body, however large it says it is, and the
    refusal is audited."""
    huge = str(47 * 1024 * 1024)
    for headers, status in (({}, 401), ({"Authorization": "Bearer nope"}, 401),
                            (rig.obs, 403)):
        code, doc, read = await _asgi_post(
            rig.app, "/targets", {**headers, "content-length": huge,
                                  "content-type": "application/json"},
            [b"{" * 65536] * 4)
        assert (code, read) == (status, []), doc
    assert [x["status"] for x in audit_lines(rig)] == [401, 401, 403]
    assert rig.ops.calls == []


async def test_bodies_past_their_endpoints_limit_are_413(rig):
    """issue 30, serious 1: an operator's body larger than its endpoint accepts is 413,
    at once from Content-Length (nothing read) or, streamed without one, as soon as the
    bytes pass the limit; the core is never called and the refusal is audited."""
    limit = BODY_LIMITS["/targets"]
    code, doc, read = await _asgi_post(rig.app, "/targets",
                                       {**rig.op, "content-length": str(limit + 1)},
                                       [b" " * 1024] * 80)
    assert (code, read) == (413, []) and f"{limit} bytes" in doc["detail"]
    code, doc, read = await _asgi_post(rig.app, "/targets", rig.op, [b" " * 16384] * 40)
    assert code == 413 and len(read) == limit // 16384 + 1
    code, doc, read = await _asgi_post(rig.app, "/reset", rig.op, [b" " * 5000])
    assert code == 413 and f"{DEFAULT_LIMIT} bytes" in doc["detail"]
    assert rig.ops.calls == []
    assert [x["status"] for x in audit_lines(rig)] == [413, 413, 413]
    # a full-size legitimate body still goes through, and quickly
    targets = {"targets": [{"name": f"target-{k:03d}", "p_OM": [0.0123456789] * 3,
                            "n_OM": [0.0, 0.0, 1.0]} for k in range(64)]}
    raw = json.dumps(targets, indent=2).encode()
    assert len(raw) < limit
    t0 = time.perf_counter()
    code, doc, _ = await _asgi_post(rig.app, "/targets",
                                    {**rig.op, "content-type": "application/json"}, [raw])
    assert code == 200, doc
    assert time.perf_counter() - t0 < 0.25  # about 5 ms here; bounded by the limit


@pytest.mark.parametrize("content", [b"[" * 1000 + b"]" * 1000, b'{"targets": "\xff\xfe"}',
                                     b'{"targets": [\xc3\x28]}'])
async def test_unparseable_bodies_are_audited_and_need_a_token(client, rig, content):
    """issue 30: a body nested 1000 deep or not UTF-8 is 401 without a token and 400 with
    one, naming what is wrong; both are audited (docs/api.md: every command is)."""
    content = content.decode("unicode_escape").encode("latin-1")
    hdr = {"content-type": "application/json"}
    assert (await client.post("/targets", headers=hdr, content=content)).status_code == 401
    r = await client.post("/targets", headers=rig.op | hdr, content=content)
    assert r.status_code in (400, 422), r.text
    assert "JSON" in r.json()["detail"] or r.status_code == 422
    assert [x["status"] for x in audit_lines(rig)] == [401, r.status_code]
    assert rig.ops.calls == []


async def test_health_says_why_the_daemon_is_not_healthy(client, rig):
    """issue 30: GET /health is 503 with the reason while the core reports the control
    process dead or its loop silent (what the systemd watchdog asks too)."""
    rig.ops.healthy = (False, "control process is not running")
    r = await client.get("/health")
    assert r.status_code == 503
    assert r.json()["ok"] is False and r.json()["reason"] == "control process is not running"


async def test_a_huge_unauthenticated_post_does_not_stall_the_served_loop(rig):
    """issue 30, serious 1 (target): over real HTTP, a 47 MB POST /targets without a
    token is refused within 1 s while GET /health, polled all along, never waits more
    than 100 ms (on a loaded CI machine: 250 ms)."""
    one = b'{"name": "s1", "p_OM": [0.01, 0, 0]}'
    body = b'{"targets": [' + b", ".join([one] * 1_300_000) + b"]}"  # the body
    assert len(body) > 47e6
    gaps: list[float] = []
    with anyio.fail_after(20):
        async with anyio.create_task_group() as tg:
            port = await tg.start(serve, rig.app, "127.0.0.1", 0)
            done = anyio.Event()

            async def poll() -> None:
                async with httpx.AsyncClient() as c:
                    await c.get(f"http://127.0.0.1:{port}/health")  # connect, warm up
                    while not done.is_set():
                        t0 = time.perf_counter()
                        assert (await c.get(f"http://127.0.0.1:{port}/health")).status_code \
                            == 200
                        gaps.append(time.perf_counter() - t0)
                        await anyio.sleep(0.01)

            tg.start_soon(poll)
            await anyio.sleep(0.3)
            # a raw client that streams the body while it listens, as an attacker would:
            # the time is the server's, to its first byte of answer
            stream = await anyio.connect_tcp("127.0.0.1", port)
            head = (f"POST /targets HTTP/1.1\r\nHost: oralnav\r\nContent-Type: "
                    f"application/json\r\nContent-Length: {len(body)}\r\n\r\n").encode()
            t0 = time.perf_counter()
            answer = b""

            async def push() -> None:
                try:
                    await stream.send(head)
                    for k in range(0, len(body), 1 << 16):
                        await stream.send(body[k:k + (1 << 16)])
                except (anyio.BrokenResourceError, anyio.ClosedResourceError, OSError):
                    pass  # the server answered and closed: nothing more is read

            async with anyio.create_task_group() as client:
                client.start_soon(push)
                with contextlib.suppress(anyio.EndOfStream, anyio.BrokenResourceError,
                                         OSError):
                    answer = await stream.receive()
                refused_s = time.perf_counter() - t0
                client.cancel_scope.cancel()
            await stream.aclose()
            await anyio.sleep(0.1)
            done.set()
            tg.cancel_scope.cancel()
    print(f"47 MB unauthenticated POST: refused in {refused_s * 1e3:.0f} ms, longest "
          f"/health wait {max(gaps) * 1e3:.0f} ms over {len(gaps)} polls")
    # the server answers and closes with the body unread: its kernel may reset the
    # connection before the client reads the answer (then b""); the audit log below
    # says what the server answered either way
    assert answer == b"" or answer.startswith(b"HTTP/1.1 401"), answer[:200]
    assert answer == b"" or b"connection: close" in answer.lower()
    assert refused_s < 1.0
    assert max(gaps) < 0.25, max(gaps)
    assert [x["status"] for x in audit_lines(rig)] == [401]


async def test_operator_drives_the_procedure(client, rig):
    """issue 4 REST: an operator can set targets, start, pause, resume, abort, e-stop and
    reset; each call reaches the core with the token's name and is audited."""
    steps = [("/targets", GOOD_TARGETS), ("/procedure/start", None), ("/procedure/pause", None),
             ("/procedure/resume", None), ("/procedure/abort", None),
             ("/estop", {"reason": "test stop"}), ("/reset", None)]
    for path, body in steps:
        r = await client.post(path, headers=rig.op, json=body)
        assert r.status_code == 200, r.text
        assert r.json()["ok"] is True and r.json()["audited"] is True
    assert rig.ops.calls == [
        ("set_targets", "operator"), ("procedure", "start", "operator"),
        ("procedure", "pause", "operator"), ("procedure", "resume", "operator"),
        ("procedure", "abort", "operator"), ("estop", "operator", "test stop"),
        ("reset", "operator")]
    recs = audit_results(rig)
    assert [(x["path"], x["status"], x["who"]) for x in recs] == \
        [(p, 200, "operator") for p, _ in steps]
    assert recs[0]["body"].startswith('{"targets":[{"name":"s1"')
    # issue 30: every command but the e-stop wrote its intent before it ran
    assert [x["phase"] for x in audit_lines(rig)] == \
        ["intent", "outcome"] * 5 + ["single"] + ["intent", "outcome"]


async def test_estop_body_is_optional(client, rig):
    """issue 4 REST: POST /estop works without a body (default reason) and rejects unknown
    keys in one."""
    assert (await client.post("/estop", headers=rig.op)).status_code == 200
    assert rig.ops.calls == [("estop", "operator", "operator e-stop")]
    r = await client.post("/estop", headers=rig.op, json={"reason": "x", "force": True})
    assert r.status_code == 422 and "force" in r.json()["detail"]
    assert len(rig.ops.calls) == 1


# -- state and value errors ------------------------------------------------------------
async def test_state_error_is_409_and_changes_nothing(client, rig):
    """issue 4 REST: a StateError from the core is 409 {"detail": reason}; the fake's
    state and targets stay as they were, and the refusal is audited."""
    r = await client.post("/reset", headers=rig.op)
    assert r.status_code == 409 and r.json() == {"detail": "nothing to reset: state is IDLE"}
    r = await client.post("/procedure/pause", headers=rig.op)
    assert r.status_code == 409 and "cannot pause while IDLE" in r.json()["detail"]
    rig.ops.state = "RUNNING"
    before = rig.ops.targets()
    r = await client.post("/targets", headers=rig.op, json=GOOD_TARGETS)
    assert r.status_code == 409 and "RUNNING" in r.json()["detail"]
    assert rig.ops.targets() == before and rig.ops.calls == [] and rig.ops.state == "RUNNING"
    recs = audit_results(rig)
    assert [x["status"] for x in recs] == [409, 409, 409]
    assert recs[2]["result"] == "targets cannot change while RUNNING"


async def test_limit_error_is_422_and_core_bug_is_500(client, rig):
    """issue 4 REST: a LimitError (ValueError) from the core is 422 with its reason; any
    other exception is 500 naming it; both are audited."""
    body = {"targets": [{"name": "limit1", "p_OM": [0.0, 0.0, 0.01]}]}
    r = await client.post("/targets", headers=rig.op, json=body)
    assert r.status_code == 422 and "virtual fixture" in r.json()["detail"]
    body = {"targets": [{"name": "boom", "p_OM": [0.0, 0.0, 0.01]}]}
    r = await client.post("/targets", headers=rig.op, json=body)
    assert r.status_code == 500 and "RuntimeError: core bug" in r.json()["detail"]
    assert [x["status"] for x in audit_results(rig)] == [422, 500]


def _target(**kw) -> dict:
    t = {"name": "s1", "p_OM": [0.01, 0.0, 0.0]}
    t.update(kw)
    return t


BAD_TARGETS = {
    # standard JSON has no NaN: clients send the non-standard literal, a string, or 1e999
    "NaN literal": (b'{"targets": [{"name": "a", "p_OM": [NaN, 0, 0]}]}', "p_OM[0]"),
    "Infinity literal": (b'{"targets": [{"name": "a", "p_OM": [0, -Infinity, 0]}]}',
                         "p_OM[1]"),
    "1e999": (b'{"targets": [{"name": "a", "p_OM": [0, 0, 1e999]}]}', "p_OM[2]"),
    "string NaN": ({"targets": [_target(p_OM=["NaN", 0, 0])]}, "p_OM[0]"),
    "string number": ({"targets": [_target(p_OM=["0.01", 0, 0])]}, "p_OM[0]"),
    "boolean": ({"targets": [_target(p_OM=[True, 0, 0])]}, "p_OM[0]"),
    "millimetres": ({"targets": [_target(p_OM=[12.0, 3.0, 0.0])]}, "0.2 m"),
    "just out of range": ({"targets": [_target(p_OM=[0.15, 0.15, 0.0])]}, "p_OM"),
    "two coordinates": ({"targets": [_target(p_OM=[0.0, 0.0])]}, "p_OM"),
    "four coordinates": ({"targets": [_target(p_OM=[0.0, 0.0, 0.0, 0.0])]}, "p_OM"),
    "zero normal": ({"targets": [_target(n_OM=[0, 0, 0])]}, "non-zero"),
    "tiny normal": ({"targets": [_target(n_OM=[1e-9, 0, 0])]}, "n_OM"),
    "NaN normal": (b'{"targets": [{"name": "a", "p_OM": [0,0,0], "n_OM": [NaN,0,1]}]}',
                   "n_OM[0]"),
    "duplicate names": ({"targets": [_target(), _target()]}, "repeated: s1"),
    "unknown target key": ({"targets": [_target(depth=0.01)]}, "targets[0].depth"),
    "unknown top key": ({"targets": [], "replace": True}, "replace: unknown key"),
    "too many": ({"targets": [_target(name=f"t{i}") for i in range(65)]}, "64"),
    "bad name": ({"targets": [_target(name="a b")]}, "name"),
    "empty name": ({"targets": [_target(name="")]}, "name"),
    "long name": ({"targets": [_target(name="x" * 65)]}, "name"),
    "missing p_OM": ({"targets": [{"name": "a"}]}, "p_OM: Field required"),
    "missing targets": ({}, "targets: Field required"),
    "not an object": ([1, 2], "body"),
    "malformed JSON": (b'{"targets": [', "not valid JSON"),
}


@pytest.mark.parametrize("case", list(BAD_TARGETS))
async def test_bad_targets_are_refused_with_a_reason(client, rig, case):
    """issue 4 REST: non-finite, out-of-range, mis-shaped, duplicate, unknown-key, too many
    targets or malformed JSON are answered 4xx with a reason naming the field; the core is
    never called and its targets are unchanged; the refusal is audited."""
    body, reason = BAD_TARGETS[case]
    before = rig.ops.targets()
    if isinstance(body, bytes):
        r = await client.post("/targets", headers=rig.op | {"content-type": "application/json"},
                              content=body)
    else:
        r = await client.post("/targets", headers=rig.op, json=body)
    assert r.status_code == (400 if case == "malformed JSON" else 422), r.text
    detail = r.json()["detail"]
    assert isinstance(detail, str) and reason in detail, detail
    assert rig.ops.calls == [] and rig.ops.targets() == before
    (rec,) = audit_lines(rig)
    assert rec["status"] == r.status_code and rec["result"] == detail
    assert rec["who"] == "operator" and rec["body"]


async def test_targets_are_normalised_and_stored(client, rig):
    """issue 4 REST: accepted targets reach the core as SutureTarget with a unit n_OM."""
    r = await client.post("/targets", headers=rig.op, json=GOOD_TARGETS)
    assert r.status_code == 200
    s1, s2 = rig.ops.targets()
    assert s1.n_OM is None and s2.n_OM == (0.0, 0.0, 1.0)
    r = await client.get("/targets", headers=rig.obs)
    assert r.json()["targets"][1]["p_OM"] == [0.0, -0.01, 0.005]


async def test_unknown_procedure_action_is_422(client, rig):
    """issue 4 REST: POST /procedure/<other> is 422 naming the allowed actions; nothing
    runs."""
    r = await client.post("/procedure/launch", headers=rig.op)
    assert r.status_code == 422 and "'start'" in r.json()["detail"]
    assert rig.ops.calls == []


# -- guided insertion ------------------------------------------------------------------
async def test_guide_plan_start_stop_over_rest(client, rig):
    """issue 6, item 5: POST /guide/plan answers the placement and the fixture's target
    and direction (planning runs in a worker thread, off the event loop); GET /guide
    (observer) shows the plan; start and stop reach the core with the operator's name;
    a new plan while guiding is 409 and keeps the running one; every command is
    audited."""
    r = await client.post("/guide/plan", headers=rig.op, json=GOOD_PLAN)
    assert r.status_code == 200, r.text
    doc = r.json()
    assert doc["ok"] is True and doc["command"] == "guide plan" and doc["by"] == "operator"
    assert doc["placement"] == {"d_T": 0.0655, "collision_free": True}
    assert doc["fixture"]["target"] == [0.0, 0.0155, 0.05]
    assert doc["fixture"]["direction"] == [0.0, 0.0, 1.0]
    assert rig.ops.plan_thread is not threading.main_thread()
    assert rig.ops.calls == [("plan_guide", GOOD_PLAN["scene"], "operator", 3)]
    g = (await client.get("/guide", headers=rig.obs)).json()
    assert g["phase"] == "idle" and g["plan"]["T_OM_F"] == EYE4
    assert g["rod_distance_m"] is None                      # NaN -> null
    assert (await client.post("/guide/start", headers=rig.op)).status_code == 200
    assert (await client.get("/guide", headers=rig.obs)).json()["phase"] == "active"
    r = await client.post("/guide/plan", headers=rig.op, json=GOOD_PLAN | {"seed": 4})
    assert r.status_code == 409 and "running" in r.json()["detail"]
    assert rig.ops.plan["scene"] == GOOD_PLAN["scene"]
    assert (await client.post("/guide/stop", headers=rig.op)).status_code == 200
    assert rig.ops.calls[1:] == [("start_guide", "operator"), ("stop_guide", "operator")]
    assert (await client.get("/guide", headers=rig.obs)).json()["plan"] is None
    recs = audit_results(rig)
    assert [(x["path"], x["status"]) for x in recs] == [
        ("/guide/plan", 200), ("/guide/start", 200), ("/guide/plan", 409),
        ("/guide/stop", 200)]
    assert '"scene":"config/examples/cylinder_case.toml"' in recs[0]["body"]


BAD_PLANS = {
    "no registration": ({"scene": "s.toml"}, "T_OM_F"),
    "3x3 registration": ({"scene": "s.toml", "T_OM_F": np.eye(3).tolist()}, "T_OM_F"),
    "NaN in registration": (b'{"scene": "s.toml", "T_OM_F": [[NaN, 0, 0, 0], [0, 1, 0, 0], '
                            b'[0, 0, 1, 0], [0, 0, 0, 1]]}', "T_OM_F[0][0]"),
    "string number": ({"scene": "s.toml", "T_OM_F": [["1", 0, 0, 0]] + EYE4[1:]},
                      "T_OM_F[0][0]"),
    "negative seed": ({"scene": "s.toml", "T_OM_F": EYE4, "seed": -1}, "seed"),
    "float seed": ({"scene": "s.toml", "T_OM_F": EYE4, "seed": 1.5}, "seed"),
    "empty scene": ({"scene": "", "T_OM_F": EYE4}, "scene"),
    "unknown key": ({"scene": "s.toml", "T_OM_F": EYE4, "equation": 22}, "equation"),
}


@pytest.mark.parametrize("case", sorted(BAD_PLANS))
async def test_bad_guide_plan_bodies_are_422(client, rig, case):
    """issue 6, item 5: a malformed POST /guide/plan body is 422 naming where; the core is
    not called and the previous plan stays."""
    body, where = BAD_PLANS[case]
    kw = {"content": body, "headers": rig.op | {"content-type": "application/json"}} \
        if isinstance(body, bytes) else {"json": body, "headers": rig.op}
    r = await client.post("/guide/plan", **kw)
    assert r.status_code == 422, r.text
    assert any(e["where"].startswith(where) for e in r.json()["errors"]), r.json()
    assert rig.ops.calls == [] and rig.ops.plan is None
    assert audit_lines(rig)[-1]["status"] == 422


async def test_guide_refusals_from_the_core(client, rig):
    """issue 6, item 5: a bad scene (GuidePlanError) is 422 with the loader's message; no
    collision-free placement is 409; start without a plan is 409; none changes the
    plan the core holds."""
    r = await client.post("/guide/plan", headers=rig.op, json=GOOD_PLAN | {"scene": "bad.toml"})
    assert r.status_code == 422 and "[hole] axis" in r.json()["detail"]
    r = await client.post("/guide/start", headers=rig.op)
    assert r.status_code == 409 and "POST /guide/plan" in r.json()["detail"]
    assert (await client.post("/guide/plan", headers=rig.op, json=GOOD_PLAN)).status_code == 200
    r = await client.post("/guide/plan", headers=rig.op,
                          json=GOOD_PLAN | {"scene": "unsafe.toml"})
    assert r.status_code == 409 and "collision-free" in r.json()["detail"]
    assert rig.ops.plan["scene"] == GOOD_PLAN["scene"]
    assert [x["status"] for x in audit_results(rig)] == [422, 409, 200, 409]


# -- audit ---------------------------------------------------------------------------------
async def test_every_command_is_audited_and_earlier_lines_stay(client, rig):
    """issue 4 audit: each command, accepted or refused (401, 403, 422, 409), adds exactly
    one line, after the lines already in the file, which stay unchanged. issue 30: a
    command that reaches the core (409, 200) adds two, its intent and its outcome."""
    rig.audit.close()
    rig.path.write_text('{"earlier": "run"}\n')
    rig.audit.open()
    await client.post("/procedure/start")                                      # 401
    await client.post("/procedure/start", headers=rig.obs)                     # 403
    await client.post("/targets", headers=rig.op, json={"targets": [{}]})      # 422
    await client.post("/reset", headers=rig.op)                                # 409
    await client.post("/procedure/start", headers=rig.op)                      # 200
    await client.get("/status", headers=rig.obs)                               # not a command
    lines = rig.path.read_text().splitlines()
    assert lines[0] == '{"earlier": "run"}'
    recs = [json.loads(x) for x in lines[1:]]
    assert [x["status"] for x in recs] == [401, 403, 422, None, 409, None, 200]
    assert [x["phase"] for x in recs] == ["single"] * 3 + ["intent", "outcome"] * 2
    assert recs[0]["who"] is None and recs[0]["client"]
    assert all(x["method"] == "POST" for x in recs)


@pytest.mark.parametrize("broken", ["closed", "disk full"])
async def test_audit_failure_refuses_commands_with_503(client, rig, broken):
    """issue 4 audit: when the audit log cannot be written every command except the e-stop
    is refused with 503 and the core is not called; the e-stop still runs (safety first)
    and says it was not audited."""
    if broken == "closed":
        rig.audit.close()
    else:
        rig.audit.min_free_bytes = 1 << 62
    for path in POSTS:
        if path == "/estop":
            continue
        r = await client.post(path, headers=rig.op, json=body_for(path))
        assert r.status_code == 503 and "audit log" in r.json()["detail"], r.text
    assert rig.ops.calls == [] and rig.ops.state == "IDLE"
    r = await client.post("/estop", headers=rig.op)
    if broken == "closed":
        assert r.json()["audited"] is False and r.headers["x-audit"] == "failed"
    assert r.status_code == 200 and rig.ops.state == "ESTOP"


async def test_record_lost_after_running_blocks_until_written(client, rig, monkeypatch):
    """issue 4 audit: if the record of a command that ran cannot be written, the reply says
    so (X-Audit: failed), later commands get 503 without reaching the core until the
    record is written, and then the log holds every record in order. issue 30: the
    intent landed, the outcome did not."""
    real = audit_mod.os.write
    writes = {"n": 0}

    def full(fd, data):
        writes["n"] += 1
        if writes["n"] == 1:  # the intent lands; from its outcome on the disk is full
            return real(fd, data)
        raise OSError(28, "No space left on device")

    await client.post("/estop", headers=rig.op)
    monkeypatch.setattr(audit_mod.os, "write", full)
    r = await client.post("/reset", headers=rig.op)
    assert r.status_code == 200 and r.headers["x-audit"] == "failed"
    assert r.json()["audited"] is False
    r = await client.post("/procedure/start", headers=rig.op)
    assert r.status_code == 503
    assert rig.ops.calls == [("estop", "operator", "operator e-stop"), ("reset", "operator")]
    monkeypatch.setattr(audit_mod.os, "write", real)
    r = await client.post("/procedure/start", headers=rig.op)
    assert r.status_code == 200
    assert [(x["path"], x["status"]) for x in audit_results(rig)] == [
        ("/estop", 200), ("/reset", 200), ("/procedure/start", 503), ("/procedure/start", 200)]


async def test_the_intent_is_durable_before_the_command_runs(client, rig, monkeypatch):
    """issue 30, write-ahead: when the core runs a command its intent is already in the
    file (so a crash while it runs leaves a trace); a command whose intent cannot be written
    does not run (503, completed by an outcome carrying the intent's id); the e-stop runs
    first and leaves a single record."""
    seen: list[list[tuple[str, str]]] = []
    real = rig.ops.procedure

    def procedure(action: str, who: str) -> None:
        seen.append([(x["phase"], x["path"]) for x in audit_lines(rig)])
        real(action, who)

    monkeypatch.setattr(rig.ops, "procedure", procedure)
    assert (await client.post("/procedure/start", headers=rig.op)).status_code == 200
    assert seen == [[("intent", "/procedure/start")]]

    real_fsync, fsyncs = audit_mod.os.fsync, []

    def fsync_fails_once(fd):  # the intent's bytes are written, its fsync fails
        fsyncs.append(fd)
        if len(fsyncs) == 1:
            raise OSError(5, "Input/output error")
        real_fsync(fd)

    monkeypatch.setattr(audit_mod.os, "fsync", fsync_fails_once)
    r = await client.post("/procedure/pause", headers=rig.op)
    assert r.status_code == 503 and "Input/output error" in r.json()["detail"]
    assert len(seen) == 1 and rig.ops.state == "RUNNING"
    r = await client.post("/estop", headers=rig.op)
    assert r.status_code == 200 and rig.ops.state == "ESTOP"
    recs = audit_lines(rig)
    assert [(x["phase"], x["path"], x["status"]) for x in recs[2:]] == [
        ("intent", "/procedure/pause", None), ("outcome", "/procedure/pause", 503),
        ("single", "/estop", 200)]
    assert recs[2]["id"] == recs[3]["id"]


# -- OpenAPI -------------------------------------------------------------------------------
async def test_openapi_declares_the_bearer_scheme(client):
    """issue 4 REST: /openapi.json declares HTTP bearer auth and the endpoints; /docs is
    served."""
    spec = (await client.get("/openapi.json")).json()
    schemes = spec["components"]["securitySchemes"]
    assert {"type": "http", "scheme": "bearer"}.items() <= next(iter(schemes.values())).items()
    assert {"/health", "/status", "/poses", "/targets", "/estop", "/reset",
            "/procedure/{action}"} <= set(spec["paths"])
    assert spec["paths"]["/reset"]["post"]["security"]
    assert (await client.get("/docs")).status_code == 200


async def test_docs_load_nothing_from_outside_the_daemon(client):
    """Issue 33 item 6: /docs works on an offline operator station: Swagger UI's script,
    style and icon come from the daemon itself (the package ``fastapi-swagger`` ships
    them), and the page names no other host."""
    page = (await client.get("/docs")).text
    assert "://" not in page.replace("http://oralnav", "")
    for asset in ("swagger-ui-bundle.js", "swagger-ui.css", "favicon-32x32.png"):
        assert f"/docs/assets/{asset}" in page
        r = await client.get(f"/docs/assets/{asset}")
        assert r.status_code == 200 and len(r.content) > 500, asset
    assert (await client.get("/redoc")).status_code == 404  # it would load from a CDN


def test_jsonable_makes_plain_json():
    """issue 4 REST: core values (numpy, models, NaN) become standard JSON."""
    out = jsonable({"a": np.arange(3), "b": np.float32(1.5), "c": float("nan"), 1: (True,),
                    "t": SutureTarget(name="x", p_OM=(0, 0, 0))})
    assert json.dumps(out, allow_nan=False)
    assert out == {"a": [0, 1, 2], "b": 1.5, "c": None, "1": [True],
                   "t": {"name": "x", "p_OM": [0.0, 0.0, 0.0], "n_OM": None}}
    with pytest.raises(TypeError):
        jsonable(object())


# -- websocket telemetry -------------------------------------------------------------------
@contextlib.asynccontextmanager
async def running(app) -> AsyncIterator[int]:
    """The app served by the real serve() on 127.0.0.1 (a free port) for the block."""
    async with anyio.create_task_group() as tg:
        port = await tg.start(serve, app, "127.0.0.1", 0)
        try:
            yield port
        finally:
            tg.cancel_scope.cancel()


async def _ws_messages(rig, query: str = "", headers: dict | None = None,
                       n: int = 3) -> list[dict]:
    """``n`` telemetry messages; a refused handshake raises websockets.InvalidStatus."""
    refused = None
    async with running(rig.app) as port:
        try:
            async with websockets.connect(f"ws://127.0.0.1:{port}/telemetry{query}",
                                          additional_headers=headers) as ws:
                return [json.loads(await ws.recv()) for _ in range(n)]
        except websockets.InvalidStatus as exc:
            refused = exc  # raised outside the task group, not wrapped in a group
    raise refused


@pytest.mark.parametrize("how", ["header", "query"])
async def test_telemetry_streams_snapshots(rig, how):
    """issue 4 REST: WS /telemetry accepts an observer token in the Authorization header or
    ?token= (browsers), sends ops.telemetry() as standard JSON repeatedly, and the connect
    is audited without the token."""
    if how == "header":
        msgs = await _ws_messages(rig, headers=rig.obs)
    else:
        msgs = await _ws_messages(rig, f"?token={rig.tokens['observer']}")
    assert [m["tick"] for m in msgs] == [1, 2, 3]
    assert msgs[0] == {"tick": 1, "state": "IDLE", "p": [0.0, 0.0, 0.0], "err": None}
    (rec,) = audit_lines(rig)
    assert (rec["method"], rec["path"], rec["status"], rec["who"]) == \
        ("WS", "/telemetry", 101, "observer")
    assert rig.tokens["observer"] not in rig.path.read_text()


@pytest.mark.parametrize("how", ["none", "bad header", "bad query", "audit closed"])
async def test_telemetry_refusals(rig, how):
    """issue 4 REST: WS /telemetry without a valid token is refused at the handshake with
    HTTP 401 (503 when the connect cannot be audited); nothing is streamed, and the
    refusal is audited where the log works."""
    query, headers = "", None
    if how == "bad header":
        headers = {"Authorization": "Bearer nope"}
    elif how == "bad query":
        query = "?token=nope"
    elif how == "audit closed":
        headers = rig.obs
        rig.audit.close()
    with pytest.raises(websockets.InvalidStatus) as ei:
        await _ws_messages(rig, query, headers)
    want = 503 if how == "audit closed" else 401
    assert ei.value.response.status_code == want
    assert rig.ops.ticks == 0
    if want == 401:
        assert ei.value.response.headers["WWW-Authenticate"].startswith("Bearer")
        (rec,) = audit_lines(rig)
        assert (rec["method"], rec["status"], rec["who"]) == ("WS", 401, None)


async def test_telemetry_failure_closes_with_1011(rig, caplog):
    """issue 4 REST: if the core cannot give a snapshot the stream ends with close code
    1011 (internal error) naming the failure, and the error is logged."""
    def broken() -> dict:
        raise RuntimeError("no poses yet")

    rig.ops.telemetry = broken
    async with running(rig.app) as port:
        async with websockets.connect(f"ws://127.0.0.1:{port}/telemetry",
                                      additional_headers=rig.obs) as ws:
            with pytest.raises(websockets.ConnectionClosedError) as ei:
                await ws.recv()
    assert ei.value.rcvd.code == 1011 and "RuntimeError" in ei.value.rcvd.reason
    assert "telemetry snapshot failed" in caplog.text


async def test_telemetry_rate_is_configurable(rig):
    """issue 4 REST: snapshots come at telemetry_hz (here 50 Hz: 10 take about 0.2 s)."""
    async with running(rig.app) as port:
        async with websockets.connect(f"ws://127.0.0.1:{port}/telemetry",
                                      additional_headers=rig.obs) as ws:
            await ws.recv()
            t0 = time.monotonic()
            for _ in range(10):
                await ws.recv()
            dt = time.monotonic() - t0
    assert 0.15 < dt < 1.0, dt  # loose above: a loaded CI machine may lag


# -- serve() -------------------------------------------------------------------------------
async def test_serve_runs_on_the_daemon_loop_and_stops_on_cancel(rig):
    """issue 4 REST: serve() runs uvicorn inside an anyio task group on 127.0.0.1 port 0,
    reports the real port only once it is listening, installs no signal handlers, answers
    GET /health and a websocket over loopback, and on cancellation closes the websocket and
    stops listening before the task group exits."""
    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    with anyio.fail_after(10):
        async with anyio.create_task_group() as tg:
            port = await tg.start(serve, rig.app, "127.0.0.1", 0)
            assert port > 0
            assert {s: signal.getsignal(s) for s in before} == before
            async with httpx.AsyncClient() as c:
                r = await c.get(f"http://127.0.0.1:{port}/health")
            assert r.status_code == 200 and r.json()["ok"] is True
            ws = await websockets.connect(f"ws://127.0.0.1:{port}/telemetry",
                                          additional_headers=rig.obs)
            assert json.loads(await ws.recv())["tick"] >= 1
            tg.cancel_scope.cancel()
        # the server closed the stream (1012: service restart) on its way down
        with pytest.raises(websockets.ConnectionClosed) as ei:
            while True:
                await ws.recv()
        assert ei.value.rcvd is not None and ei.value.rcvd.code == 1012
        await ws.close()
    assert {s: signal.getsignal(s) for s in before} == before
    with socket.socket() as s, pytest.raises(ConnectionRefusedError):
        s.connect(("127.0.0.1", port))


@pytest.mark.parametrize("host", ["0.0.0.0", "::", "192.168.1.10", "robot.local"])
async def test_serve_refuses_remote_hosts_unless_allowed(rig, host):
    """issue 4 REST: serve() refuses a non-loopback host unless allow_remote (the daemon
    binds 127.0.0.1 unless configured otherwise)."""
    async with anyio.create_task_group() as tg:
        with pytest.raises(ValueError, match="allow_remote"):
            await tg.start(serve, rig.app, host, 0)


async def test_serve_reports_a_busy_port(rig):
    """issue 4 REST: a port already in use raises OSError naming host and port."""
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        async with anyio.create_task_group() as tg:
            with pytest.raises(OSError, match=f"127.0.0.1:{port}"):
                await tg.start(serve, rig.app, "127.0.0.1", port)


# -- configuration ---------------------------------------------------------------------------
@pytest.mark.parametrize("api, where", [
    ({}, None),
    ({"host": "::1", "port": 8751, "telemetry_hz": 5.0}, None),
    ({"host": "0.0.0.0", "allow_remote": True, "tokens_file": "tokens.toml"}, None),
    ({"tls_cert": "cert.pem", "tls_key": "key.pem"}, None),
    ({"host": "0.0.0.0", "allow_remote": True}, "[api] tokens_file: allow_remote = true "
                                                "needs a tokens_file"),
    ({"tls_cert": "cert.pem"}, "[api] tls_key: HTTPS needs both"),
    ({"tls_key": "key.pem"}, "[api] tls_key: HTTPS needs both"),
    ({"host": "0.0.0.0"}, "[api] host: '0.0.0.0' is not a loopback address"),
    ({"host": "robot.local"}, "[api] host"),
    ({"host": "0.0.0.0", "allow_remote": "yes"}, "[api] allow_remote"),
    ({"telemetry_hz": 0.0}, "[api] telemetry_hz"),
    ({"telemetry_hz": 1000.0}, "[api] telemetry_hz"),
    ({"tokens_file": ""}, "[api] tokens_file"),
    ({"bind": "127.0.0.1"}, "[api] bind: unknown key"),
])
def test_api_section_binds_loopback_unless_allowed(tmp_path, api, where):
    """issue 4 config: [api] accepts tokens_file, audit_log, telemetry_hz (1..100 Hz) and
    allow_remote; a non-loopback host is an error naming [api] host unless allow_remote.
    issue 30: allow_remote refuses the demo tokens (a tokens_file is needed), and HTTPS
    needs both tls_cert and tls_key."""
    from oralnav.config.daemon import ApiSection
    from oralnav.config.errors import ConfigError
    from oralnav.config.loader import validate

    path = tmp_path / "d.toml"
    if where is None:
        sec = validate(ApiSection, api, path, "api")
        assert sec.audit_log == "oralnav-audit.jsonl"
        assert sec.tokens_file == api.get("tokens_file")
        return
    with pytest.raises(ConfigError) as ei:
        validate(ApiSection, api, path, "api")
    assert str(ei.value).startswith(f"{path}: {where}"), str(ei.value)


# -- needle procedure --------------------------------------------------------------------
async def test_needle_cell_and_steps_over_rest(client, rig):
    """issue 7, item 7: POST /needle/cell loads a cell (in a worker thread), POST
    /needle/{step} runs a step and answers its result, GET /needle reads the state; a
    refused step is 409 with the core's reason; a step name that is not one of the five
    is 422 and reaches nothing, as is a servo mode other than off, looks, stream (issue
    36); every command is audited."""
    r = await client.post("/needle/NG", headers=rig.op)
    assert r.status_code == 409 and "POST /needle/cell" in r.json()["detail"]
    r = await client.post("/needle/cell", headers=rig.op, json={"trial": 7, "difficulty": 0.5})
    assert r.status_code == 200, r.text
    assert rig.ops.plan_thread is not threading.main_thread()
    r = await client.post("/needle/NG", headers=rig.op)
    assert r.status_code == 200 and r.json()["result"] == {"step": "NG", "ok": True}
    r = await client.post("/needle/NR", headers=rig.op)
    assert r.status_code == 409 and "not converged" in r.json()["detail"]
    for bad in ("/needle/ng", "/needle/XX"):
        assert (await client.post(bad, headers=rig.op)).status_code == 422
    for body in ({"trial": -1}, {"trial": "3"}, {"trial": 1, "difficulty": 2.5},
                 {"trial": 1, "extra": 0}, {"trial": 1, "servo": "fast"}):
        r = await client.post("/needle/cell", headers=rig.op, json=body)
        assert r.status_code == 422, body
    assert (await client.get("/needle", headers=rig.obs)).json() == {"cell": 7, "done": ["NG"]}
    assert rig.ops.calls == [("needle_cell", 7, 0.5, "operator", "off"),
                             ("needle_step", "NG", "operator")]
    r = await client.post("/needle/cell", headers=rig.op, json={"trial": 7, "servo": "stream"})
    assert r.status_code == 200 and rig.ops.calls[-1] == ("needle_cell", 7, 1.0, "operator",
                                                          "stream")
    statuses = [(x["path"], x["status"]) for x in audit_lines(rig)]
    assert ("/needle/NR", 409) in statuses and ("/needle/XX", 422) in statuses


async def test_temporal_calibration_endpoint(client, rig):
    """issue 32, "Time": POST /calibration/temporal starts the excitation with the body's
    figures (defaults where left out; out-of-range values 422 naming the field, nothing
    called); GET reports the phase, with the record on ?samples=true; a refusal is 409."""
    r = await client.post("/calibration/temporal", headers=rig.op, json={"amplitude_mm": 3})
    assert r.status_code == 200 and r.json()["phase"] == "moving"
    assert rig.ops.calls[-1] == ("start_temporal", {"amplitude_mm": 3.0, "period_s": 4.0,
                                                    "duration_s": 24.0, "search_ms": 200.0},
                                 "operator")
    n = len(rig.ops.calls)
    for bad in ({"amplitude_mm": 50}, {"period_s": 0.1}, {"duration_s": 1000},
                {"amplitude_mm": "5"}, {"speed": 1}):
        r = await client.post("/calibration/temporal", headers=rig.op, json=bad)
        assert r.status_code == 422, bad
        assert next(iter(bad)) in json.dumps(r.json()), r.json()
    assert len(rig.ops.calls) == n
    doc = (await client.get("/calibration/temporal", headers=rig.obs)).json()
    assert doc["phase"] == "moving" and "samples" not in doc
    doc = (await client.get("/calibration/temporal?samples=true", headers=rig.obs)).json()
    assert set(doc["samples"]) == {"t_cam", "p_C", "t_arm", "p_B"}
    rig.ops.state = "RUNNING"
    r = await client.post("/calibration/temporal", headers=rig.op, json={})
    assert r.status_code == 409 and "RUNNING" in r.json()["detail"]
