"""The telemetry websocket's stream (``/telemetry``, built in ``daemon/api.py``): a
snapshot of ``ops.telemetry()`` at the configured rate, and what the client subscribed to
(:data:`TOPICS`): the status, the poses, the views' news and the camera frames themselves
as binary messages (``daemon/live_views.py`` gives their layout). Whatever the number of
clients, a frame is encoded once (``LiveViews``), and a client gets only the newest frame
of each camera at the rate it asked for: a slow client skips frames, never queues them.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
from dataclasses import dataclass, field
from typing import Any, Protocol

import anyio
from fastapi import WebSocket
from starlette.websockets import WebSocketDisconnect, WebSocketState

from oralnav.daemon.live_views import (
    MAX_QUALITY,
    MAX_WIDTH,
    MIN_QUALITY,
    MIN_WIDTH,
    LiveViews,
    NoFrame,
)
from oralnav.daemon.schemas import jsonable

__all__ = ["FRAMES_DEFAULT", "FRAMES_MAX_FPS", "STATUS_PERIOD_S", "TOPICS", "stream"]

log = logging.getLogger(__name__)


class TelemetrySource(Protocol):
    """What the stream reads (``DaemonCore`` through the API's ``Operations``)."""

    def telemetry(self) -> dict[str, Any]: ...

    def status(self) -> dict[str, Any]: ...

    def poses(self) -> dict[str, Any]: ...


#: what a telemetry client may subscribe to besides the snapshot: ``status`` (the whole
#: GET /status document, at most every STATUS_PERIOD_S and at once on a safety state
#: change), ``poses`` (GET /poses, with every snapshot), ``views`` (GET /views's
#: cameras, with the snapshot that follows a new frame: a client learns of each frame
#: without polling) and ``frames`` (each camera's new frames themselves, as binary
#: messages: ``daemon/live_views.py``; at the ``"frames"`` options' rate and width)
TOPICS = frozenset({"status", "poses", "views", "frames"})
#: s, the least time between two ``status`` documents on one connection
STATUS_PERIOD_S = 0.2
#: bytes: a longer client message is refused (a subscription is a few dozen bytes)
MAX_CLIENT_MESSAGE = 4096
#: the ``frames`` topic's default options and the bounds of its rate (frames/s per camera)
FRAMES_DEFAULT = {"fps": 5.0, "width": 640, "quality": 70}
FRAMES_MAX_FPS = 30.0


@dataclass
class _Subscription:
    """What one telemetry client asked for (:data:`TOPICS`) and, with ``frames``, each
    camera's least period (s) between two frames, their width (px) and JPEG quality."""

    topics: set[str] = field(default_factory=set)
    frame_period: float = 1.0 / FRAMES_DEFAULT["fps"]
    frame_width: int = int(FRAMES_DEFAULT["width"])
    frame_quality: int = int(FRAMES_DEFAULT["quality"])

    def take(self, other: _Subscription) -> None:
        """Become ``other``: a client's new subscription replaces its last, in place (the
        frame push reads this object)."""
        self.__dict__.update(other.__dict__)


def _frame_options(opts: Any) -> tuple[dict[str, float] | None, str | None]:
    """The ``"frames"`` options ``{"fps": f, "width": w, "quality": q}`` (each optional)
    merged with :data:`FRAMES_DEFAULT`, or (None, why they are refused)."""
    if opts is None:
        return dict(FRAMES_DEFAULT), None
    if not isinstance(opts, dict) or set(opts) - set(FRAMES_DEFAULT):
        return None, 'expected "frames": {"fps": f, "width": w, "quality": q}'
    out = {**FRAMES_DEFAULT, **opts}
    bounds = {"fps": (0.1, FRAMES_MAX_FPS), "width": (MIN_WIDTH, MAX_WIDTH),
              "quality": (MIN_QUALITY, MAX_QUALITY)}
    for key, (lo, hi) in bounds.items():
        v = out[key]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not lo <= v <= hi:
            return None, f"frames {key} must be a number in [{lo:g}, {hi:g}], got {v!r}"
        if key != "fps" and v != int(v):
            return None, f"frames {key} must be a whole number, got {v!r}"
    return out, None


def _subscription(text: str | None) -> tuple[_Subscription | None, str | None]:
    """A client message ``{"subscribe": [topic, ...], "frames": {...}}`` (the options
    only with the ``frames`` topic) as (subscription, None), or (None, why it is
    refused)."""
    if text is None or len(text) > MAX_CLIENT_MESSAGE:
        return None, f"send text of at most {MAX_CLIENT_MESSAGE} bytes"
    try:
        doc = json.loads(text)
    except ValueError:
        return None, "not JSON; send {\"subscribe\": [\"status\", \"poses\"]}"
    topics = doc.get("subscribe") if isinstance(doc, dict) else None
    if not isinstance(topics, list) or not all(isinstance(t, str) for t in topics):
        return None, "expected {\"subscribe\": [topic, ...]}"
    unknown = sorted(set(topics) - TOPICS)
    if unknown:
        return None, f"unknown topic(s) {', '.join(unknown)} (known: {', '.join(sorted(TOPICS))})"
    extra = sorted(set(doc) - {"subscribe", "frames"})
    if extra:
        return None, f"unknown key(s) {', '.join(extra)} (known: subscribe, frames)"
    if "frames" in doc and "frames" not in topics:
        return None, 'the "frames" options need the frames topic'
    opts, why = _frame_options(doc.get("frames"))
    if opts is None:
        return None, why
    return _Subscription(set(topics), 1.0 / opts["fps"], int(opts["width"]),
                         int(opts["quality"])), None


async def _push_frames(ws: WebSocket, sub: _Subscription, views: LiveViews) -> None:
    """While ``sub`` has the ``frames`` topic, send each camera's new frames as binary
    messages, at most one per camera every ``sub.frame_period`` s: woken by the capture
    pipeline's rounds, the newest frame only (a frame in between is skipped, never
    queued), encoded once for every client (``LiveViews``)."""
    sent: dict[str, int] = {}       # camera -> the counter this client was last sent
    last: dict[str, float] = {}     # camera -> when (s, anyio clock)
    seen = -1
    while True:
        if "frames" not in sub.topics:
            sent.clear()  # a new subscription starts with every camera's frame
            await anyio.sleep(0.2)
            continue
        seen = views.generation
        due = math.inf
        for cam, counter in views.counters().items():
            now = anyio.current_time()
            if sent.get(cam) == counter:
                continue
            if now < last.get(cam, -math.inf) + sub.frame_period:
                due = min(due, last[cam] + sub.frame_period)
                continue
            try:
                msg, shown = await anyio.to_thread.run_sync(
                    views.frame_message, cam, sub.frame_width, sub.frame_quality)
            except NoFrame:
                continue
            if shown == sent.get(cam):
                # the encoder, rate-limited, handed back the frame this client has: ask
                # again once it may encode the newer one, and never send a frame twice
                due = min(due, now + 1.0 / views.max_hz)
                continue
            await ws.send_bytes(msg)
            sent[cam], last[cam] = shown, now
        if due < math.inf:  # a camera waits for its period: the newest frame then
            await anyio.sleep_until(due)
        else:  # the next round (at most 0.5 s: a changed subscription is seen)
            with anyio.move_on_after(0.5):
                await views.wait_newer(seen)


async def stream(ws: WebSocket, ops: TelemetrySource, period: float,
                  views: LiveViews | None = None) -> None:
    """Send ``ops.telemetry()`` every ``period`` seconds until the client disconnects,
    with what it subscribed to (:data:`TOPICS`; a refused message is answered
    ``{"error": ...}`` and changes nothing)."""
    sub = _Subscription()
    sent_frames: dict[str, int] = {}  # views: the counters this client was last sent
    async with anyio.create_task_group() as tg:
        async def watch() -> None:
            # reading is also how a disconnect is seen at once
            while True:
                msg = await ws.receive()
                if msg["type"] == "websocket.disconnect":
                    break
                wanted, why = _subscription(msg.get("text"))
                if wanted is None:
                    await ws.send_text(json.dumps({"error": why}))
                else:
                    sub.take(wanted)
            tg.cancel_scope.cancel()

        tg.start_soon(watch)
        if views is not None:
            tg.start_soon(_push_frames, ws, sub, views)
        deadline = anyio.current_time()
        last_status, last_state = -math.inf, None
        try:
            while True:
                try:
                    doc = ops.telemetry()
                    now = anyio.current_time()
                    if "status" in sub.topics and (now - last_status >= STATUS_PERIOD_S
                                               or doc.get("state") != last_state):
                        doc = {**doc, "status": ops.status()}
                        last_status, last_state = now, doc.get("state")
                    if "poses" in sub.topics:
                        doc = {**doc, "poses": ops.poses()}
                    if "views" in sub.topics and views is not None:
                        frames = views.counters()
                        if frames != sent_frames:
                            doc = {**doc, "views": views.cameras()}
                            sent_frames = frames
                    text = json.dumps(jsonable(doc), allow_nan=False)
                except Exception as exc:
                    log.exception("telemetry snapshot failed")
                    await ws.close(code=1011, reason=f"telemetry failed: {type(exc).__name__}")
                    break
                await ws.send_text(text)
                # fixed rate without drift; after a stall, skip rather than burst
                deadline = max(deadline + period, anyio.current_time())
                await anyio.sleep_until(deadline)
        except WebSocketDisconnect:
            pass
        tg.cancel_scope.cancel()
    if ws.application_state == WebSocketState.CONNECTED and \
            ws.client_state == WebSocketState.CONNECTED:
        with contextlib.suppress(Exception):
            await ws.close()
