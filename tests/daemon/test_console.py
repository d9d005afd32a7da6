"""Issue 33, items 1 and 6: what the console needs of the operator API, against the fake
core of ``test_api.py``: the page and its files without a token (nothing secret in them)
under a strict content policy; ``/session``, ``/views``, a view's JPEG, the planned
targets and the target selection with the usual roles, refusals and audit; and the
telemetry websocket's subscriptions to the status, the poses and the frames."""

from __future__ import annotations

import json
import struct

import anyio
import cv2
import httpx
import numpy as np
import pytest
import websockets

from oralnav.daemon.api import build_app
from oralnav.daemon.auth import TokenStore
from oralnav.daemon.live_views import LiveViews

from .test_api import _ws_messages, audit_lines, rig, running  # noqa: F401  (fixtures)
from .test_live_views import _pose, _round
from .test_live_views import _rig as _camera_rig


@pytest.fixture
def views_rig(rig):  # noqa: F811  (the fixture of test_api)
    """``rig`` with live views that have seen one round of two cameras."""
    views = LiveViews(max_hz=50.0)
    views.tap(_round(7, _camera_rig(), _pose()))
    rig.views = views
    tokens = TokenStore.from_file(rig.path.parent / "tokens.toml")
    rig.app = build_app(rig.ops, tokens, rig.audit, telemetry_hz=50.0, views=views)
    return rig


@pytest.fixture
async def vclient(views_rig):
    transport = httpx.ASGITransport(app=views_rig.app)
    async with httpx.AsyncClient(transport=transport, base_url="http://oralnav") as c:
        yield c


async def test_the_page_and_its_files_are_served_without_a_token_under_a_strict_policy(
        vclient):
    """Item 1: the console at / (plain HTML, its script and style from the daemon only)."""
    r = await vclient.get("/")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
    csp = r.headers["content-security-policy"]
    assert "default-src 'self'" in csp and "frame-ancestors 'none'" in csp
    assert 'src="/console/console.js"' in r.text and "E-STOP" in r.text
    for name, kind in (("console.js", "javascript"), ("console.css", "text/css")):
        f = await vclient.get(f"/console/{name}")
        assert f.status_code == 200 and kind in f.headers["content-type"]
    assert (await vclient.get("/console/nope.js")).status_code == 404


async def test_session_says_who_the_token_is(vclient, views_rig):
    """Item 1 "the same token roles as the API": the console learns the role it has."""
    r = await vclient.get("/session", headers=views_rig.obs)
    assert r.json() == {"name": "observer", "role": "observer"}
    assert (await vclient.get("/session")).status_code == 401


async def test_views_list_the_cameras_with_their_overlays(vclient, views_rig):
    """Item 1: the views with size, counter and the fields found in them."""
    doc = (await vclient.get("/views", headers=views_rig.obs)).json()
    assert doc["max_hz"] == 50.0
    left = doc["cameras"][0]
    assert (left["name"], left["width"], left["height"], left["counter"]) == \
        ("left", 640, 480, 7)
    assert left["fields"][0]["name"] == "opener" and len(left["fields"][0]["axes"]) == 4
    assert (await vclient.get("/views")).status_code == 401


async def test_a_view_is_a_jpeg_with_its_counter_and_capture_instant(vclient, views_rig):
    """Item 1: a camera's newest frame, downscaled; an unknown camera is 404 naming the
    known ones; sizes out of bounds are 422; an observer may watch."""
    r = await vclient.get("/views/left/image?width=320", headers=views_rig.obs)
    assert r.status_code == 200 and r.headers["content-type"] == "image/jpeg"
    assert r.content[:2] == b"\xff\xd8" and r.headers["x-frame-counter"] == "7"
    assert float(r.headers["x-capture-time"]) == 107.0
    assert r.headers["cache-control"] == "no-store"
    r = await vclient.get("/views/nope/image", headers=views_rig.obs)
    assert r.status_code == 404 and "left, right" in r.json()["detail"]
    r = await vclient.get("/views/left/image?width=5000", headers=views_rig.obs)
    assert r.status_code == 422 and "width" in r.json()["detail"]
    assert (await vclient.get("/views/left/image")).status_code == 401


async def test_without_views_the_list_is_empty(rig):  # noqa: F811
    """A daemon built without live views answers an empty list, and 404 for an image."""
    transport = httpx.ASGITransport(app=rig.app)
    async with httpx.AsyncClient(transport=transport, base_url="http://oralnav") as c:
        assert (await c.get("/views", headers=rig.obs)).json() == \
            {"cameras": [], "max_hz": None}
        assert (await c.get("/views/left/image", headers=rig.obs)).status_code == 404


async def test_the_surgeon_selects_the_current_target(vclient, views_rig):
    """Item 1 (the seed's "select the current suture target"): an operator command,
    audited; an unknown name is 409 and changes nothing; an observer is 403."""
    r = await vclient.post("/targets/select", headers=views_rig.op, json={"name": "t0"})
    assert r.status_code == 200, r.text
    assert views_rig.ops.calls == [("select_target", "t0", "operator")]
    r = await vclient.post("/targets/select", headers=views_rig.op, json={"name": "t9"})
    assert r.status_code == 409 and "no such suture target" in r.json()["detail"]
    r = await vclient.post("/targets/select", headers=views_rig.obs, json={"name": "t0"})
    assert r.status_code == 403
    r = await vclient.post("/targets/select", headers=views_rig.op, json={"name": "a b"})
    assert r.status_code == 422
    assert len(views_rig.ops.calls) == 1
    paths = [(x["path"], x["status"]) for x in audit_lines(views_rig)
             if x["phase"] != "intent"]
    assert paths == [("/targets/select", 200), ("/targets/select", 409),
                     ("/targets/select", 403), ("/targets/select", 422)]


async def test_planned_targets_are_offered_not_registered(vclient, views_rig):
    """Item 1: the cell file's targets, for the console's "Register planned"."""
    doc = (await vclient.get("/targets/planned", headers=views_rig.obs)).json()
    assert [t["name"] for t in doc["targets"]] == ["planned_1"]
    assert views_rig.ops.calls == []


async def test_telemetry_subscribes_to_status_and_poses(views_rig):
    """Item 6: a client subscribes to the status and the poses instead of polling; a
    malformed or unknown subscription is answered with an error and changes nothing."""
    async with running(views_rig.app) as port:
        url = f"ws://127.0.0.1:{port}/telemetry?token={views_rig.tokens['observer']}"
        async with websockets.connect(url) as ws:
            first = json.loads(await ws.recv())
            assert "status" not in first and "poses" not in first
            await ws.send("not json")
            await ws.send(json.dumps({"subscribe": ["status", "bogus"]}))
            await ws.send(json.dumps({"subscribe": ["status", "poses"]}))
            errors, got = [], None
            for _ in range(40):
                msg = json.loads(await ws.recv())
                if "error" in msg:
                    errors.append(msg["error"])
                elif "status" in msg and "poses" in msg:
                    got = msg
                    break
            assert got is not None, errors
            assert got["status"]["state"] == "IDLE" and got["poses"]["T_C_OM"][3][3] == 1.0
            assert any("not JSON" in e for e in errors)
            assert any("unknown topic(s) bogus" in e for e in errors)
            await ws.send("x" * 5000)
            for _ in range(40):
                msg = json.loads(await ws.recv())
                if "error" in msg:
                    assert "at most 4096 bytes" in msg["error"]
                    break
            else:
                pytest.fail("an oversized message was not answered")


async def test_telemetry_says_when_a_view_has_a_new_frame(views_rig):
    """Item 1 "never slowing tracking": a console subscribed to ``views`` learns of each
    new frame from the snapshot that follows it, once, instead of polling /views."""
    async with running(views_rig.app) as port:
        url = f"ws://127.0.0.1:{port}/telemetry?token={views_rig.tokens['observer']}"
        async with websockets.connect(url) as ws:
            await ws.send(json.dumps({"subscribe": ["views"]}))
            counters = []
            for _ in range(30):
                msg = json.loads(await ws.recv())
                if "views" in msg:
                    counters.append([c["counter"] for c in msg["views"]])
                    if len(counters) == 1:  # a new frame after the first announcement
                        views_rig.views.tap(_round(8, _camera_rig(), _pose()))
            assert counters == [[7, 7], [8, 8]], counters


def _frame(msg: bytes) -> tuple[dict, bytes]:
    (n,) = struct.unpack(">I", msg[:4])
    return json.loads(msg[4:4 + n]), msg[4 + n:]


async def test_telemetry_pushes_each_new_frame_as_a_binary_message(views_rig):
    """Item 1 "live views ... over the existing websocket ... never slowing tracking": a
    client subscribed to ``frames`` gets each camera's newest frame once, as a binary
    message (header with the overlay, then the JPEG at the width asked), no request per
    frame; a new round brings the next frames; bad frame options are refused by name."""
    views_rig.views.max_hz = 60.0
    async with running(views_rig.app) as port:
        url = f"ws://127.0.0.1:{port}/telemetry?token={views_rig.tokens['observer']}"
        async with websockets.connect(url) as ws:
            await ws.send(json.dumps({"subscribe": ["frames"], "frames": {"fps": 0}}))
            await ws.send(json.dumps({"subscribe": ["status"], "frames": {"fps": 5}}))
            await ws.send(json.dumps({"subscribe": ["frames"], "frames": {"size": 5}}))
            await ws.send(json.dumps({"subscribe": ["frames"],
                                      "frames": {"fps": 30, "width": 320}}))
            errors, frames = [], []
            for _ in range(200):
                msg = await ws.recv()
                if isinstance(msg, str):
                    doc = json.loads(msg)
                    errors.extend([doc["error"]] if "error" in doc else [])
                    continue
                head, jpeg = _frame(msg)
                img = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_UNCHANGED)
                assert img.shape == (240, 320) and head["fields"][0]["name"] == "opener"
                frames.append((head["camera"], head["counter"]))
                if len(frames) == 2:
                    views_rig.views.tap(_round(8, _camera_rig(), _pose()))
                if len(frames) == 4:
                    break
            assert sorted(frames[:2]) == [("left", 7), ("right", 7)], frames
            assert sorted(frames[2:]) == [("left", 8), ("right", 8)], frames
            assert any("frames fps must be a number in [0.1, 30]" in e for e in errors)
            assert any("need the frames topic" in e for e in errors)
            assert any("expected \"frames\"" in e for e in errors), errors


async def test_a_rate_limited_encoder_never_sends_a_frame_twice(views_rig):
    """Item 1 ("each camera's newest frame once"): a round that comes while the encoder
    may not yet encode again (its 1 / max_hz) brings its frames once the encoder may, and
    never the previous frames a second time (a loaded machine showed it: left 8, then
    right 7 again)."""
    views_rig.views.max_hz = 2.0  # an encode every 0.5 s at most
    async with running(views_rig.app) as port:
        url = f"ws://127.0.0.1:{port}/telemetry?token={views_rig.tokens['observer']}"
        async with websockets.connect(url) as ws:
            await ws.send(json.dumps({"subscribe": ["frames"],
                                      "frames": {"fps": 30, "width": 320}}))
            frames = []
            with anyio.fail_after(10):
                while len(frames) < 4:
                    msg = await ws.recv()
                    if isinstance(msg, str):
                        continue
                    head, _ = _frame(msg)
                    frames.append((head["camera"], head["counter"]))
                    if len(frames) == 2:  # at once: within the encoder's 0.5 s
                        views_rig.views.tap(_round(8, _camera_rig(), _pose()))
    assert sorted(frames[:2]) == [("left", 7), ("right", 7)], frames
    assert sorted(frames[2:]) == [("left", 8), ("right", 8)], frames
