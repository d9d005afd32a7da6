"""The gate in front of the operator API: who may send a body, and how large it may be.

FastAPI reads and parses a request's body before an endpoint's dependencies run, so a
bearer-token dependency alone lets a stranger make the daemon read, parse and validate a
body of any size on the event loop that the safety supervisor, the tracking and the
systemd watchdog share (issue 30: a 47 MB POST stalled ``/health`` for seconds). The gate
is a plain ASGI middleware that runs before FastAPI sees the request:

1. every POST is authenticated from its headers alone: a missing or unknown token is 401,
   an observer's token 403, answered without reading a byte of the body;
2. a body larger than its endpoint's limit (:data:`BODY_LIMITS`, bytes) is 413: at once
   when ``Content-Length`` says so, else as soon as the streamed bytes pass the limit;
3. the body is then read here (bounded) and handed on, so FastAPI's parsing and
   validation only ever see a body of a few kilobytes (about a millisecond of work at the
   largest; docs/api.md).

Each refusal is audited like any other command. Reads (GET) and the telemetry websocket
pass through: they carry no body, and their endpoints check the token themselves.
Starlette's own ``RequestBodyLimitMiddleware`` limits sizes too, but it answers before
authentication, in plain text, and unaudited.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable

from starlette.requests import Request
from starlette.responses import JSONResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from .auth import Principal, Role, TokenStore

#: the largest body (bytes) each POST endpoint accepts; others get :data:`DEFAULT_LIMIT`.
#: /targets: 64 targets of about 200 bytes each, with room for pretty-printing
BODY_LIMITS: dict[str, int] = {"/targets": 64 * 1024, "/guide/plan": 16 * 1024}
#: every other POST: an e-stop reason (500 characters), a needle cell, or nothing
DEFAULT_LIMIT = 4 * 1024
#: methods that carry a body and change state: the operator role is needed
COMMAND_METHODS = frozenset({"POST", "PUT", "PATCH", "DELETE"})


class Refused(Exception):
    """A request refused before it reaches the core (401/403)."""

    def __init__(self, status: int, detail: str, headers: dict[str, str] | None = None,
                 principal: Principal | None = None) -> None:
        super().__init__(detail)
        self.status, self.detail, self.headers, self.principal = status, detail, headers, principal


def bearer_from_header(value: str | None) -> str | None:
    """The token of an ``Authorization: Bearer <token>`` header value, or None."""
    scheme, _, token = (value or "").partition(" ")
    return (token.strip() or None) if scheme.lower() == "bearer" else None


def authorize(tokens: TokenStore, token: str | None, required: Role) -> Principal:
    """The principal of ``token`` if it has ``required``; raises :class:`Refused`."""
    if token is None:
        raise Refused(401, "missing bearer token (Authorization: Bearer <token>)",
                      {"WWW-Authenticate": 'Bearer realm="oralnav"'})
    principal = tokens.authenticate(token)
    if principal is None:
        raise Refused(401, "unknown bearer token",
                      {"WWW-Authenticate": 'Bearer realm="oralnav", error="invalid_token"'})
    if not principal.allows(required):
        raise Refused(403, f"needs the {required} role; token {principal.name!r} has "
                           f"{principal.role}", principal=principal)
    return principal


def body_limit(path: str) -> int:
    """The largest body (bytes) a POST to ``path`` may carry."""
    return BODY_LIMITS.get(path, DEFAULT_LIMIT)


#: ``record(request, principal, status, result, body)``: one audit record; False when it
#: could not be written
Recorder = Callable[[Request, Principal | None, int, str, bytes], Awaitable[bool]]


class _TooLarge(Exception):
    pass


class RequestGate:
    """ASGI middleware: authentication and body limits before the app (module docstring).
    ``record`` writes the audit record of a refusal (``build_app``'s recorder)."""

    def __init__(self, app: ASGIApp, tokens: TokenStore, record: Recorder) -> None:
        self.app = app
        self.tokens = tokens
        self.record = record

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] not in COMMAND_METHODS:
            await self.app(scope, receive, send)
            return
        request = Request(scope)
        path = scope["path"]
        try:
            principal = authorize(
                self.tokens, bearer_from_header(request.headers.get("authorization")),
                "operator")
        except Refused as exc:
            await self._refuse(request, scope, receive, send, exc.status, exc.detail,
                               exc.principal, exc.headers)
            return
        limit = body_limit(path)
        declared = _content_length(request)
        if declared is not None and declared > limit:
            await self._refuse(request, scope, receive, send, 413,
                               f"request body of {declared} bytes is larger than the "
                               f"{limit} bytes POST {path} accepts", principal)
            return
        try:
            body = await _read_body(receive, limit)
        except _TooLarge:
            await self._refuse(request, scope, receive, send, 413,
                               f"request body is larger than the {limit} bytes POST {path} "
                               "accepts", principal)
            return
        except _Disconnected:
            return  # the client went away before sending its body: nothing to answer
        await self.app(scope, _replay(body, receive), send)

    async def _refuse(self, request: Request, scope: Scope, receive: Receive, send: Send,
                      status: int, detail: str, principal: Principal | None,
                      headers: dict[str, str] | None = None) -> None:
        audited = await self.record(request, principal, status, detail, b"")
        headers = dict(headers or {})
        if not audited:
            headers["X-Audit"] = "failed"
        if status == 413:
            # the unread rest of the body makes the connection unusable: say so
            headers["Connection"] = "close"
        await JSONResponse({"detail": detail}, status, headers=headers)(scope, receive, send)


class _Disconnected(Exception):
    pass


def _content_length(request: Request) -> int | None:
    raw = request.headers.get("content-length")
    try:
        return int(raw) if raw is not None else None
    except ValueError:
        return None  # h11 refuses a malformed length before we see it


async def _read_body(receive: Receive, limit: int) -> bytes:
    """The whole body, refusing (``_TooLarge``) as soon as it passes ``limit`` bytes."""
    chunks: list[bytes] = []
    size = 0
    while True:
        message = await receive()
        if message["type"] == "http.disconnect":
            raise _Disconnected
        chunk = message.get("body", b"")
        size += len(chunk)
        if size > limit:
            raise _TooLarge
        chunks.append(chunk)
        if not message.get("more_body", False):
            return b"".join(chunks)


def _replay(body: bytes, receive: Receive) -> Receive:
    """A ``receive`` that gives ``body`` once, then whatever the server sends next (a
    disconnect)."""
    sent = False

    async def replay() -> Message:
        nonlocal sent
        if not sent:
            sent = True
            return {"type": "http.request", "body": body, "more_body": False}
        return await receive()

    return replay
