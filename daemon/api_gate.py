"""The gate in front of the operator API: who is locked out, who may send a body, and how
large it may be.

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

Before all of that, failed authentication is limited per client address (issue 30: 3,000
wrong tokens at 87/s were all checked and each was audited, 129 kB/s of fsynced log).
:class:`FailureLimiter` keeps a token bucket of failures (401s, on any path) per address;
when a client has spent it, the address is locked out: every request from it is answered
429 with ``Retry-After`` from the headers alone, before any token is hashed, the right
token included, until the lockout ends; a repeated lockout lasts twice as long, up to a
bound. While locked out, requests leave no audit record each: one record when the lockout
starts, one summary with the count at most every :data:`LOCKOUT_SUMMARY_S` and when it
ends. Other addresses are never affected. Exceptions: ``GET /health`` (no token, nothing
secret) and ``POST /estop`` with a valid operator token, which still runs (stopping the
robot is always safe; an attacker behind the same proxy or NAT address must not be able
to take the e-stop away from the operator station).
"""

from __future__ import annotations

import ipaddress
import math
import time
from collections import OrderedDict
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, fields
from typing import TYPE_CHECKING, Literal

from starlette.requests import Request
from starlette.responses import JSONResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send
from starlette.websockets import WebSocket

from oralnav.daemon.auth import Principal, Role, TokenStore

if TYPE_CHECKING:
    from oralnav.config.daemon import ApiSection

#: the largest body (bytes) each POST endpoint accepts; others get :data:`DEFAULT_LIMIT`.
#: /targets: 64 targets of about 200 bytes each, with room for pretty-printing;
#: /recording/start: a path of up to 4096 characters and its options
BODY_LIMITS: dict[str, int] = {"/targets": 64 * 1024, "/guide/plan": 16 * 1024,
                               "/recording/start": 16 * 1024}
#: every other POST: an e-stop reason (500 characters), a needle cell, or nothing
DEFAULT_LIMIT = 4 * 1024
#: methods that carry a body and change state: the operator role is needed
COMMAND_METHODS = frozenset({"POST", "PUT", "PATCH", "DELETE"})

# -- failed authentication: limits (docs/api.md "Rate limits and lockout") -----------------
#: failed authentications an address may make in a burst; the one that spends the last
#: starts a lockout (``[api] auth_failure_burst``)
AUTH_FAILURE_BURST = 10
#: seconds for one failure to be forgiven (the bucket's refill): a client that keeps below
#: one failure per this many seconds is never locked out (``[api] auth_failure_refill_s``)
AUTH_FAILURE_REFILL_S = 6.0
#: the first lockout, seconds (``[api] auth_lockout_s``); each further one in a row lasts
#: twice as long as the one before ...
AUTH_LOCKOUT_S = 60.0
#: ... up to this, seconds (``[api] auth_lockout_max_s``)
AUTH_LOCKOUT_MAX_S = 900.0
#: a lockout this long (s) after the previous one ended starts again at AUTH_LOCKOUT_S
AUTH_LOCKOUT_MEMORY_S = 3600.0
#: while a lockout lasts, a summary record with the count of refused requests is written at
#: most this often (s); one more when it ends
LOCKOUT_SUMMARY_S = 60.0
#: addresses remembered at most; past it the one idle longest is forgotten (a memory bound
#: against floods from many addresses)
MAX_TRACKED_CLIENTS = 4096
#: how often (s) at most the gate looks for lockout summaries due, so that a flood from many
#: addresses does not make every request walk them all
LOCKOUT_SWEEP_S = 1.0
#: requests no lockout refuses: liveness needs no token and says nothing secret
LOCKOUT_OPEN: frozenset[tuple[str, str]] = frozenset({("GET", "/health")})
#: requests a lockout lets through with a valid operator token: the robot may always be
#: stopped (module docstring)
LOCKOUT_OPERATOR_EXEMPT: frozenset[tuple[str, str]] = frozenset({("POST", "/estop")})


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


@dataclass(frozen=True)
class AuthLimits:
    """The numbers of :class:`FailureLimiter` (module constants by default; seconds).

    ``burst`` failures in a row lock an address out; one failure is forgiven every
    ``refill_s``; the first lockout lasts ``lockout_s``, each further one twice as long
    up to ``lockout_max_s``; ``memory_s`` after a lockout ended, the next starts again at
    ``lockout_s``. ``summary_s``: the most time between a lockout's summary records.
    ``max_clients``: addresses remembered at most.
    """

    burst: int = AUTH_FAILURE_BURST
    refill_s: float = AUTH_FAILURE_REFILL_S
    lockout_s: float = AUTH_LOCKOUT_S
    lockout_max_s: float = AUTH_LOCKOUT_MAX_S
    memory_s: float = AUTH_LOCKOUT_MEMORY_S
    summary_s: float = LOCKOUT_SUMMARY_S
    max_clients: int = MAX_TRACKED_CLIENTS

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
                raise ValueError(f"AuthLimits.{f.name} must be a positive finite number, "
                                 f"got {v!r}")
        if self.burst != int(self.burst) or self.max_clients != int(self.max_clients):
            raise ValueError("AuthLimits.burst and max_clients must be whole numbers")
        if self.lockout_max_s < self.lockout_s:
            raise ValueError(f"AuthLimits.lockout_max_s ({self.lockout_max_s} s) is shorter "
                             f"than lockout_s ({self.lockout_s} s)")

    @classmethod
    def from_config(cls, api: ApiSection) -> AuthLimits:
        """The limits ``[api]`` sets (``auth_failure_burst``, ``auth_failure_refill_s``,
        ``auth_lockout_s``, ``auth_lockout_max_s``); the rest are the module's."""
        return cls(burst=api.auth_failure_burst, refill_s=api.auth_failure_refill_s,
                   lockout_s=api.auth_lockout_s, lockout_max_s=api.auth_lockout_max_s)


@dataclass(frozen=True)
class LockoutEvent:
    """Something about a lockout to audit: its ``start``, a ``summary`` while it lasts, or
    its ``end``. ``refused``: requests refused since the previous record of this lockout;
    ``seconds``: its length; ``strike``: 1 for the first lockout in a row, 2 the next..."""

    kind: Literal["start", "summary", "end"]
    client: str
    seconds: float
    strike: int
    refused: int

    def describe(self) -> str:
        """The audit record's ``result``: one sentence."""
        if self.kind == "start":
            return (f"lockout {self.strike} started: too many failed authentications from "
                    f"{self.client}; every request from it is refused (429) for "
                    f"{self.seconds:g} s")
        if self.kind == "summary":
            return (f"lockout {self.strike} of {self.client} goes on: {self.refused} "
                    "request(s) refused since the previous record")
        return (f"lockout {self.strike} of {self.client} ended ({self.seconds:g} s): "
                f"{self.refused} request(s) refused since the previous record")


@dataclass
class _Client:
    tokens: float      # failures the address may still make before a lockout
    stamp: float       # when ``tokens`` was brought up to date (s, monotonic)
    until: float = -math.inf   # the running or last lockout ends (s)
    seconds: float = 0.0       # the running or last lockout's length (s)
    strikes: int = 0           # lockouts in a row
    refused: int = 0           # requests refused since the last record
    noted: float = -math.inf   # when the last record of the lockout was made (s)


class FailureLimiter:
    """Per-address limits on failed authentication (module docstring); pure logic.

    Every method takes the time ``now`` (s, monotonic; :attr:`clock` gives it to the
    gate) and does no I/O: the caller writes the audit records of the
    :class:`LockoutEvent` values it returns. Keys are :func:`client_key` values. Not
    thread-safe: the gate calls it from the event loop only.
    """

    def __init__(self, limits: AuthLimits | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.limits = AuthLimits() if limits is None else limits
        self.clock = clock
        self._clients: OrderedDict[str, _Client] = OrderedDict()  # idle longest first
        self._locked: dict[str, _Client] = {}  # lockouts whose end is not yet recorded
        self._dropped: list[LockoutEvent] = []  # ends of lockouts forgotten for room
        self._next_sweep = -math.inf

    def __len__(self) -> int:
        return len(self._clients)

    def retry_after(self, key: str, now: float, *, count: bool = True) -> float | None:
        """Seconds until ``key``'s lockout ends, or None when it is not locked out.
        ``count``: the request is being refused (counted in the next summary)."""
        c = self._clients.get(key)
        if c is None or now >= c.until:
            return None
        if count:
            c.refused += 1
            self._clients.move_to_end(key)
        return c.until - now

    def failure(self, key: str, now: float) -> LockoutEvent | None:
        """Count one failed authentication of ``key``; the ``start`` event when it
        starts a lockout."""
        lim = self.limits
        c = self._clients.get(key)
        if c is None:
            c = self._clients[key] = _Client(tokens=float(lim.burst), stamp=now)
            self._forget_idlest()
        else:
            self._clients.move_to_end(key)
        # refill; a lockout's own time does not refill (the stamp lies at its end), so
        # the first failure after a lockout starts the next, twice as long
        c.tokens = min(float(lim.burst), c.tokens + max(0.0, now - c.stamp) / lim.refill_s)
        c.stamp = max(now, c.stamp)
        if now < c.until:  # counted while locked out (an e-stop path): nothing more
            return None
        c.tokens -= 1.0
        if c.tokens >= 1.0:
            return None
        if now - c.until > lim.memory_s:  # the last lockout is long past
            c.strikes = 0
        c.seconds = min(lim.lockout_s * 2.0 ** min(c.strikes, 60), lim.lockout_max_s)
        c.strikes += 1
        c.until = c.stamp = now + c.seconds
        c.refused, c.noted = 0, now
        self._locked[key] = c
        return LockoutEvent("start", key, c.seconds, c.strikes, 0)

    def due(self, now: float, *, force: bool = False) -> list[LockoutEvent]:
        """The summaries and ends to record now: an ended lockout's ``end`` (with the
        count since its last record), a running one's ``summary`` when requests were
        refused and :attr:`AuthLimits.summary_s` passed since its last record. Looks at
        most every :data:`LOCKOUT_SWEEP_S` unless ``force``."""
        if not force and now < self._next_sweep and not self._dropped:
            return []
        self._next_sweep = now + LOCKOUT_SWEEP_S
        out, self._dropped = self._dropped, []
        for key, c in list(self._locked.items()):
            if now >= c.until:
                out.append(LockoutEvent("end", key, c.seconds, c.strikes, c.refused))
                c.refused = 0
                del self._locked[key]
            elif c.refused and now - c.noted >= self.limits.summary_s:
                out.append(LockoutEvent("summary", key, c.seconds, c.strikes, c.refused))
                c.refused, c.noted = 0, now
        return out

    def _forget_idlest(self) -> None:
        while len(self._clients) > self.limits.max_clients:
            key, c = self._clients.popitem(last=False)
            if self._locked.pop(key, None) is not None:
                self._dropped.append(LockoutEvent("end", key, c.seconds, c.strikes,
                                                  c.refused))


def client_key(host: str | None) -> str:
    """The address a client is limited by: its IP address (an IPv4-mapped IPv6 address
    as IPv4), an IPv6 client's /64 network (one host usually holds a whole /64), or the
    host as given when it is not an IP address."""
    if not host:
        return "?"
    try:
        ip = ipaddress.ip_address(host)
    except ValueError:
        return host
    if isinstance(ip, ipaddress.IPv6Address):
        if ip.ipv4_mapped is not None:
            return str(ip.ipv4_mapped)
        return str(ipaddress.IPv6Network((ip, 64), strict=False))
    return str(ip)


def scope_client_key(scope: Scope) -> str:
    """:func:`client_key` of an ASGI connection's peer."""
    client = scope.get("client")
    return client_key(client[0] if client else None)


#: ``note(event)``: the audit record of a lockout event; False when it could not be written
Noter = Callable[[LockoutEvent], Awaitable[bool]]


async def count_failure(limiter: FailureLimiter, note: Noter, scope: Scope) -> None:
    """Count a failed authentication (401) of the connection ``scope``; record the
    lockout it starts."""
    event = limiter.failure(scope_client_key(scope), limiter.clock())
    if event is not None:
        await note(event)


def too_many_detail(retry: float) -> str:
    return (f"too many failed authentications from this address: every request from it "
            f"is refused for another {math.ceil(retry)} s")


#: ``record(request, principal, status, result, body)``: one audit record; False when it
#: could not be written
Recorder = Callable[[Request, Principal | None, int, str, bytes], Awaitable[bool]]


class _TooLarge(Exception):
    pass


class RequestGate:
    """ASGI middleware: lockouts, authentication and body limits before the app (module
    docstring). ``record`` writes the audit record of a refusal (``build_app``'s
    recorder), ``note`` that of a lockout event; ``limiter`` is shared with the app's own
    token checks (reads, telemetry), which count their failures with
    :func:`count_failure`."""

    def __init__(self, app: ASGIApp, tokens: TokenStore, record: Recorder,
                 limiter: FailureLimiter | None = None, note: Noter | None = None) -> None:
        self.app = app
        self.tokens = tokens
        self.record = record
        self.limiter = FailureLimiter() if limiter is None else limiter
        self.note = note or _no_note

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        now = self.limiter.clock()
        for event in self.limiter.due(now):
            await self.note(event)
        method = scope.get("method", "WS")
        key = scope_client_key(scope)
        request_line = (method, scope["path"])
        if request_line in LOCKOUT_OPEN:
            pass
        elif request_line not in LOCKOUT_OPERATOR_EXEMPT:
            retry = self.limiter.retry_after(key, now)
            if retry is not None:
                await _too_many(scope, receive, send, retry)
                return
        elif self.limiter.retry_after(key, now, count=False) is not None:
            # the e-stop while locked out: only a valid operator token gets through (a
            # stranger's guesses here are refused like everywhere else)
            principal = self.tokens.authenticate(
                bearer_from_header(Request(scope).headers.get("authorization")))
            if principal is None or not principal.allows("operator"):
                retry = self.limiter.retry_after(key, now)
                if retry is not None:
                    await _too_many(scope, receive, send, retry)
                    return
        if scope["type"] != "http" or method not in COMMAND_METHODS:
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
            if exc.status == 401:
                await count_failure(self.limiter, self.note, scope)
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
        # the body is left unread: close the connection after the answer, or the server
        # would go on receiving (and parsing past) the rest of it, however large
        headers["Connection"] = "close"
        await JSONResponse({"detail": detail}, status, headers=headers)(scope, receive, send)


async def _no_note(event: LockoutEvent) -> bool:
    return False


async def _too_many(scope: Scope, receive: Receive, send: Send, retry: float) -> None:
    """Answer 429 with ``Retry-After`` (whole seconds, rounded up); a websocket handshake
    gets it as a denial response where the server can send one, else a 1008 close."""
    response = JSONResponse({"detail": too_many_detail(retry)}, 429,
                            headers={"Retry-After": str(max(1, math.ceil(retry)))})
    if scope["type"] == "http":
        response.headers["Connection"] = "close"  # nothing of the body is read (_refuse)
        await response(scope, receive, send)
    elif "websocket.http.response" in scope.get("extensions", {}):
        await WebSocket(scope, receive, send).send_denial_response(response)
    else:  # pragma: no cover - uvicorn and the test client both support denial responses
        await send({"type": "websocket.close", "code": 1008,
                    "reason": "too many failed authentications"})


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
