"""The operator REST API: status, poses, targets, e-stop, reset, procedure, guided insertion,
live telemetry and views, and the surgeon's web console at ``/``.

:func:`build_app` wraps an :class:`Operations` (the daemon core) in a FastAPI app;
:func:`serve` runs it with uvicorn inside the daemon's anyio task group. The bodies it
reads and the answers it declares are in ``daemon/schemas.py``. docs/api.md lists the
endpoints, roles, status codes and the audit log.

Rules every endpoint keeps:

- authentication first: a missing or unknown bearer token is 401 (``WWW-Authenticate:
  Bearer``), a role too low is 403, before the body is even read (``daemon/api_gate.py``:
  every POST is authenticated from its headers, and its body is bounded, 413 beyond);
- every state change is a POST and needs the ``operator`` role;
- a refused request (401/403/400/422/409/503) calls nothing in ``ops`` except the one
  that refuses it, and changes nothing;
- every command (POST, telemetry connect) is audited, refused or not: a command that runs
  writes its intent (fsynced) before it runs and its outcome after (write-ahead), a
  refusal one record; when the intent cannot be written the command is refused with 503
  (the e-stop excepted: it always runs, see :func:`build_app`);
- failed authentication is limited per client address: past a burst of 401s the address
  is locked out (429, ``Retry-After``) before any token is checked, and its refused
  requests are audited in aggregate (``daemon/api_gate.py``).
"""

# no ``from __future__ import annotations``: FastAPI must evaluate the endpoints' local
# ``Annotated`` aliases (Observer, Operator) where they are defined
import asyncio
import contextlib
import functools
import importlib.resources
import logging
import re
import socket
from collections.abc import Callable, Iterator, Mapping
from typing import Annotated, Any, Literal, Protocol

import anyio
import uvicorn
from anyio.abc import TaskStatus
from fastapi import Depends, FastAPI, Query, Request, Response, WebSocket
from fastapi.exceptions import RequestValidationError
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import JSONResponse
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from fastapi.staticfiles import StaticFiles
from pydantic import BaseModel
from starlette.exceptions import HTTPException as StarletteHTTPException

from oralnav import __version__
from oralnav.config.daemon import ApiSection
from oralnav.daemon.api_gate import (
    COMMAND_METHODS,
    FailureLimiter,
    LockoutEvent,
    RequestGate,
    count_failure,
)
from oralnav.daemon.api_gate import Refused as _Refused
from oralnav.daemon.api_gate import authorize as _authorize
from oralnav.daemon.api_gate import bearer_from_header as _bearer_from_header
from oralnav.daemon.audit import AuditError, AuditLog
from oralnav.daemon.auth import Principal, Role, TokenStore
from oralnav.daemon.console import CONSOLE_DIR, SECURITY_HEADERS, index_html
from oralnav.daemon.live_views import (
    MAX_QUALITY,
    MAX_WIDTH,
    MIN_QUALITY,
    MIN_WIDTH,
    LiveViews,
    NoFrame,
)
from oralnav.daemon.schemas import (
    Device,
    EstopBody,
    GuidePlanBody,
    NeedleCellBody,
    NeedleStep,
    Problem,
    ProcedureAction,
    RecordingStartBody,
    SelectTargetBody,
    SutureTarget,
    TargetsBody,
    TemporalCalibrationBody,
    ValidationProblem,
    jsonable,
)
from oralnav.daemon.telemetry_stream import stream as _stream
from oralnav.safety.errors import StateError

log = logging.getLogger(__name__)


# -- error answers, as each endpoint declares them in the OpenAPI schema ------------------
def _answers(**codes: tuple[type[BaseModel], str]) -> dict[int | str, dict[str, Any]]:
    return {int(code[1:]): {"model": model, "description": text}
            for code, (model, text) in codes.items()}


_TOO_MANY = (Problem, "too many failed authentications from this address: refused "
                     "until the lockout ends (Retry-After: seconds)")
_READ_ERRORS = _answers(
    _401=(Problem, "missing or unknown bearer token"),
    _409=(Problem, "not available in the current state"),
    _429=_TOO_MANY)
#: what every state-changing POST may answer besides 200 (docs/api.md)
_COMMAND_ERRORS = _answers(
    _400=(ValidationProblem, "the body is not JSON (not UTF-8, or nested too deeply)"),
    _401=(Problem, "missing or unknown bearer token (checked before the body is read)"),
    _403=(Problem, "the token lacks the operator role"),
    _409=(Problem, "not allowed in the current state; nothing changed"),
    _413=(Problem, "the body is larger than this endpoint accepts"),
    _422=(ValidationProblem, "the body or path does not validate, or the core refused a "
                             "value; nothing changed"),
    _429=_TOO_MANY,
    _503=(Problem, "the audit log cannot be written: the command did not run"))
#: the e-stop runs whatever the state and whatever the audit log
_ESTOP_ERRORS = {k: v for k, v in _COMMAND_ERRORS.items() if k not in (409, 503)}


# -- what the daemon core provides -----------------------------------------------------
class Operations(Protocol):
    """What the API needs from the daemon core. Called on the event loop; none may block.

    Methods returning ``dict`` give JSON-able values (numpy arrays and non-finite floats are
    tolerated: they are sent as lists and ``null``). Commands take ``who``, the token name
    of the operator, for the core's own log.
    """

    def health(self) -> tuple[bool, str | None]: ...  # liveness: (ok, why not)
    def status(self) -> dict[str, Any]: ...      # JSON-able: state, reasons, rates, latencies
    def poses(self) -> dict[str, Any]: ...       # JSON-able newest poses with timestamps
    def telemetry(self) -> dict[str, Any]: ...   # JSON-able live snapshot for the websocket
    def estop(self, who: str, reason: str) -> None: ...
    def reset(self, who: str) -> None: ...       # raises StateError when not allowed
    def recover(self, device: str, who: str) -> None: ...  # StateError unless latched
    def procedure(self, action: Literal["start", "pause", "resume", "abort"],
                  who: str) -> None: ...  # StateError
    def targets(self) -> list[SutureTarget]: ...
    def set_targets(self, targets: list[SutureTarget],
                    who: str) -> None: ...  # StateError (e.g. while RUNNING)
    def select_target(self, name: str, who: str) -> None: ...  # StateError: no such target
    def planned_targets(self) -> list[SutureTarget]: ...  # the cell file's, may be empty
    # guided insertion (docs/control_loop.md "Guided insertion"); plan_guide blocks (it
    # fits and places: the API calls it in a worker thread) and returns the plan summary;
    # ValueError -> 422 (bad scene or plan), StateError -> 409 (no collision-free
    # placement, or an insertion running)
    def plan_guide(self, scene: str, T_OM_F: Any, who: str,
                   seed: int | None = None) -> dict[str, Any]: ...
    def start_guide(self, who: str) -> None: ...   # StateError when not allowed
    def stop_guide(self, who: str) -> None: ...    # never refused
    def guide(self) -> dict[str, Any]: ...         # JSON-able plan summary and live status
    # needle procedure (docs/needle.md "Procedure"); needle_cell and needle_step block
    # (render, track, move: worker thread); StateError -> 409 (refused, out of turn, busy)
    def needle(self) -> dict[str, Any]: ...
    def needle_cell(self, trial: int, difficulty: float, who: str,
                    servo: str = "off") -> dict[str, Any]: ...
    def needle_step(self, step: str, who: str) -> dict[str, Any]: ...
    # temporal calibration (docs/calibration.md "Temporal calibration"): start returns the
    # run's report at once (StateError -> 409); the report gives the phase and the result
    def start_temporal(self, body: TemporalCalibrationBody, who: str) -> dict[str, Any]: ...
    def temporal(self, samples: bool = False) -> dict[str, Any]: ...
    # session recording (docs/recording.md): start creates the file (blocking: worker
    # thread) and returns the status; ValueError -> 422 (bad options, a file that cannot be
    # created), StateError -> 409 (already recording); stop waits for the writer and is
    # never refused
    def recording(self) -> dict[str, Any]: ...
    def start_recording(self, body: RecordingStartBody, who: str) -> dict[str, Any]: ...
    def stop_recording(self, who: str) -> dict[str, Any]: ...


# -- helpers -----------------------------------------------------------------------------
#: where /docs loads Swagger UI's script, style and icon from: this daemon, never a CDN
SWAGGER_ASSETS = "/docs/assets"


def _swagger_dir() -> str:
    """The folder of Swagger UI's files as the ``fastapi-swagger`` package ships them."""
    return str(importlib.resources.files("fastapi_swagger") / "resources")


def _client(conn: Request | WebSocket) -> str | None:
    return f"{conn.client.host}:{conn.client.port}" if conn.client else None


def _where(loc: tuple[Any, ...]) -> str:
    # ("body", "targets", 0, "p_OM", 1) -> "targets[0].p_OM[1]"
    out = ""
    for p in loc[1:] if loc and loc[0] in {"body", "path", "query"} else loc:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else str(p))
    return out or "body"


def _describe(errors: list[dict[str, Any]]) -> list[dict[str, str]]:
    """Pydantic's errors as ``{"where", "reason"}``, the reason naming what was sent."""
    out = []
    for e in errors:
        msg = str(e.get("msg", "invalid"))
        if e.get("type") == "value_error":
            msg = str(e.get("ctx", {}).get("error", msg))  # the validator's own words
        elif e.get("type") == "extra_forbidden":
            msg = "unknown key"
        elif e.get("type") == "json_invalid":
            loc = tuple(e.get("loc", ()))
            at = f" at character {loc[-1]}" if loc and isinstance(loc[-1], int) else ""
            out.append({"where": "body", "reason": f"not valid JSON{at}: "
                                                   f"{e.get('ctx', {}).get('error', '?')}"})
            continue
        inp = e.get("input")
        if e.get("type") not in {"missing", "extra_forbidden", "value_error"} \
                and isinstance(inp, int | float | str | bool) and len(repr(inp)) <= 40:
            msg += f" (got {inp!r})"
        out.append({"where": _where(tuple(e.get("loc", ()))), "reason": msg})
    return out


async def _body(request: Request) -> bytes:
    try:
        return await request.body()
    except RuntimeError:  # the stream was consumed elsewhere: nothing left to summarise
        return b""


# -- the app -----------------------------------------------------------------------------
def build_app(ops: Operations, tokens: TokenStore, audit: AuditLog, *,
              telemetry_hz: float = 20.0,
              auth_limiter: FailureLimiter | None = None,
              views: LiveViews | None = None) -> FastAPI:
    """The operator API over ``ops``; ``telemetry_hz`` is the websocket snapshot rate;
    ``auth_limiter`` limits failed authentication per client address (default: the
    limits of ``daemon/api_gate.py``; it is also ``app.state.auth_limiter``); ``views``:
    the cameras' newest frames for ``/views`` (none: the list is empty).

    ``audit`` must be open. The e-stop is never refused for an audit failure: refusing to
    stop a robot because a disk is full would trade safety for bookkeeping. It runs, its
    record is attempted (kept for retry and sent to the system journal on failure) and
    the answer says ``"audited": false``.
    """
    if not 0 < telemetry_hz <= 1000:
        raise ValueError(f"telemetry_hz must be in (0, 1000] Hz, got {telemetry_hz}")
    period = 1.0 / telemetry_hz
    # /docs is served below from the package's own Swagger UI files (an offline operator
    # station has no CDN); ReDoc, which only loads from a CDN, is not served
    app = FastAPI(title="oralnav operator API", version=__version__,
                  description="Status, poses, targets, e-stop and procedure control of the "
                              "oralnav suturing robot. See docs/api.md.",
                  docs_url=None, redoc_url=None)
    bearer = HTTPBearer(auto_error=False, scheme_name="bearer",
                        description="a token from the tokens file; observer reads, "
                                    "operator also commands")

    def require(role: Role) -> Callable[..., Principal]:
        def dependency(cred: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)]
                       ) -> Principal:
            return _authorize(tokens, cred.credentials if cred else None, role)
        return dependency

    Observer = Annotated[Principal, Depends(require("observer"))]
    Operator = Annotated[Principal, Depends(require("operator"))]

    async def record(conn: Request | WebSocket, principal: Principal | None, status: int,
                     result: str, body: bytes = b"", method: str | None = None,
                     outcome_of: str | None = None) -> bool:
        """One audit record from a worker thread (fsync must not stall the loop): the
        outcome of intent ``outcome_of``, else a single record. False when it could not
        be written (it is then kept for retry and journaled)."""
        try:
            await anyio.to_thread.run_sync(functools.partial(
                audit.record, who=principal.name if principal else None,
                role=principal.role if principal else None,
                method=method or getattr(conn, "method", "WS"), path=conn.url.path,
                body=body, status=status, result=result, client=_client(conn),
                outcome_of=outcome_of))
        except AuditError:
            return False  # audit.record has logged it with the record
        return True

    limiter = FailureLimiter() if auth_limiter is None else auth_limiter
    app.state.auth_limiter = limiter

    async def note_lockout(event: LockoutEvent) -> bool:
        """The audit record of a lockout's start, summary or end (one record stands for
        every request it refused; docs/api.md)."""
        try:
            await anyio.to_thread.run_sync(functools.partial(
                audit.record, who=None, role=None, method="*", path="*", status=429,
                result=event.describe(), client=event.client,
                extra={"lockout": event.kind, "refused": event.refused,
                       "lockout_s": event.seconds}))
        except AuditError:
            return False
        return True

    app.add_middleware(RequestGate, tokens=tokens, record=record, limiter=limiter,
                       note=note_lockout)

    async def audit_ready() -> str | None:
        """None when a command may run, else why the audit log refuses it."""
        try:
            await anyio.to_thread.run_sync(audit.check)
        except AuditError as exc:
            return str(exc)
        return None

    def reply(status: int, content: dict[str, Any], audited: bool,
              headers: dict[str, str] | None = None) -> JSONResponse:
        headers = dict(headers or {})
        if not audited:
            headers["X-Audit"] = "failed"
        return JSONResponse(content, status, headers=headers)

    @app.exception_handler(_Refused)
    async def _on_refused(request: Request, exc: _Refused) -> JSONResponse:
        audited = await record(request, exc.principal, exc.status, exc.detail,
                               await _body(request))
        if exc.status == 401:  # a wrong or missing token: counts towards a lockout
            await count_failure(limiter, note_lockout, request.scope)
        return reply(exc.status, {"detail": exc.detail}, audited, exc.headers)

    @app.exception_handler(RequestValidationError)
    async def _on_invalid(request: Request, exc: RequestValidationError) -> JSONResponse:
        # FastAPI parses the JSON before the dependencies run: authenticate here first so
        # that a stranger learns nothing about the body (auth always answers first)
        required: Role = "operator" if request.method == "POST" else "observer"
        try:
            principal = _authorize(
                tokens, _bearer_from_header(request.headers.get("authorization")), required)
        except _Refused as refused:
            return await _on_refused(request, refused)
        errors = _describe(list(exc.errors()))
        status = 400 if any(e.get("type") == "json_invalid" for e in exc.errors()) else 422
        detail = "; ".join(f"{e['where']}: {e['reason']}" for e in errors)
        audited = await record(request, principal, status, detail, await _body(request))
        return reply(status, {"detail": detail, "errors": errors}, audited)

    @app.exception_handler(StarletteHTTPException)
    async def _on_http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        # FastAPI's own refusals: a body it cannot parse at all (bytes that are not UTF-8,
        # JSON nested past the parser's depth), an unknown path or method. A command is
        # audited like any other (the gate authenticated it already)
        detail = str(exc.detail)
        if exc.status_code == 400 and detail == "There was an error parsing the body":
            detail = ("body is not valid JSON (bytes that are not UTF-8, or nested too "
                      "deeply to parse)")
        audited = True
        if request.method in COMMAND_METHODS:
            principal = tokens.authenticate(
                _bearer_from_header(request.headers.get("authorization")) or "")
            audited = await record(request, principal, exc.status_code, detail,
                                   await _body(request))
        return reply(exc.status_code, {"detail": detail}, audited,
                     dict(exc.headers) if exc.headers else None)

    async def command(request: Request, who: Principal, name: str, run: Callable[[], Any],
                      *, audit_first: bool = True, in_thread: bool = False) -> JSONResponse:
        """Run one state-changing command, write-ahead: its intent is written and fsynced
        (or the command is refused with 503 and does not run), then ``run()``, then its
        outcome record (same id), then the reply. ``audit_first=False`` (the e-stop):
        ``run()`` first, whatever the log, then one single record. ``in_thread``: ``run``
        blocks (planning), so it runs in a worker thread. A dict that ``run`` returns is
        added to the 200 answer."""
        body = await _body(request)
        intent: str | None = None
        if audit_first:
            try:
                intent = await anyio.to_thread.run_sync(functools.partial(
                    audit.intent, who=who.name, role=who.role, method=request.method,
                    path=request.url.path, body=body, client=_client(request)))
            except AuditError as exc:
                detail = f"command refused: the audit log cannot be written ({exc})"
                # the refusal completes the intent when part of it may be in the file
                await record(request, who, 503, detail, b"" if exc.record_id else body,
                             outcome_of=exc.record_id)
                return reply(503, {"detail": detail}, False)
        extra: Any = None
        try:
            extra = await anyio.to_thread.run_sync(run) if in_thread else run()
            status, result = 200, "ok"
        except StateError as exc:
            status, result = 409, str(exc) or "not allowed in the current state"
        except ValueError as exc:  # LimitError is a ValueError too
            status, result = 422, str(exc) or "invalid value"
        except Exception as exc:
            log.exception("%s by %s failed", name, who.name)
            status, result = 500, f"internal error: {type(exc).__name__}: {exc}"
        # the outcome names the intent; its body is in the intent already
        audited = await record(request, who, status, result, b"" if intent else body,
                               outcome_of=intent)
        content: dict[str, Any] = ({"ok": True, "command": name, "by": who.name,
                                    "audited": audited} if status == 200
                                   else {"detail": result})
        if status == 200 and isinstance(extra, Mapping):
            content = {**jsonable(extra), **content}
        return reply(status, content, audited)

    def read(fn: Callable[[], Any]) -> JSONResponse:
        try:
            return JSONResponse(jsonable(fn()))
        except StateError as exc:
            return JSONResponse({"detail": str(exc)}, 409)

    # -- endpoints -------------------------------------------------------------------
    @app.get("/health", summary="Liveness (no token needed): 503 while the control "
                                "process is dead or its loop silent",
             responses={503: {"description": "the daemon is not healthy; `reason` says why"}})
    async def health() -> JSONResponse:
        ok, why = ops.health()
        doc: dict[str, Any] = {"ok": ok, "service": "oralnav", "version": __version__}
        if not ok:
            doc["reason"] = why
        return JSONResponse(doc, 200 if ok else 503)

    @app.get("/status", responses=_READ_ERRORS,
             summary="Safety state, reasons, loop rates and latencies")
    async def get_status(_: Observer) -> JSONResponse:
        return read(ops.status)

    @app.get("/poses", responses=_READ_ERRORS,
             summary="Newest poses with their timestamps")
    async def get_poses(_: Observer) -> JSONResponse:
        return read(ops.poses)

    @app.get("/targets", responses=_READ_ERRORS,
             summary="The current suture targets")
    async def get_targets(_: Observer) -> JSONResponse:
        return read(lambda: {"targets": ops.targets()})

    @app.get("/targets/planned", responses=_READ_ERRORS,
             summary="The cell's planned suture targets (its cell file), not yet "
                     "registered: POST them to /targets to use them")
    async def get_planned_targets(_: Observer) -> JSONResponse:
        return read(lambda: {"targets": ops.planned_targets()})

    @app.get("/session", responses=_READ_ERRORS,
             summary="Who the token is: its name and role (the console's sign-in)")
    async def get_session(who: Observer) -> JSONResponse:
        return JSONResponse({"name": who.name, "role": who.role})

    @app.post("/targets/select", responses=_COMMAND_ERRORS,
              summary="Select the current suture target: a running procedure goes there "
                      "next (409 for a name not registered)")
    async def post_target_select(request: Request, who: Operator,
                                 body: SelectTargetBody) -> JSONResponse:
        return await command(request, who, f"select target {body.name}",
                             lambda: ops.select_target(body.name, who.name))

    # -- live views (daemon/live_views.py) and the console (daemon/console/) -------------
    @app.get("/views", responses=_READ_ERRORS,
             summary="The cameras with a frame: size, counter, capture instant, and the "
                     "tracked fields' overlay in their pixels")
    async def get_views(_: Observer) -> JSONResponse:
        if views is None:
            return JSONResponse({"cameras": [], "max_hz": None})
        return read(lambda: {"cameras": views.cameras(), "max_hz": views.max_hz})

    @app.get("/views/{camera}/image", response_class=Response, responses={
                 200: {"content": {"image/jpeg": {}},
                       "description": "the newest frame as JPEG; X-Frame-Counter and "
                                      "X-Capture-Time (s, daemon monotonic clock)"},
                 **_READ_ERRORS, **_answers(
                     _404=(Problem, "no such camera, or no frame from it yet"),
                     _422=(ValidationProblem, "width or quality out of bounds"))},
             summary="A camera's newest frame, downscaled JPEG (encoded at most "
                     "[api] views_max_hz times a second per camera)")
    async def get_view_image(
            _: Observer, camera: str,
            width: Annotated[int, Query(ge=MIN_WIDTH, le=MAX_WIDTH)] = 640,
            quality: Annotated[int, Query(ge=MIN_QUALITY, le=MAX_QUALITY)] = 70) -> Response:
        if views is None:
            return JSONResponse({"detail": "this daemon shows no views"}, 404)
        try:
            data, counter, stamp = await anyio.to_thread.run_sync(
                views.jpeg, camera, width, quality)
        except NoFrame as exc:
            return JSONResponse({"detail": str(exc)}, 404)
        return Response(data, media_type="image/jpeg", headers={
            "Cache-Control": "no-store", "X-Frame-Counter": str(counter),
            "X-Capture-Time": f"{stamp:.6f}"})

    @app.get("/", include_in_schema=False)
    async def console_page() -> Response:
        return Response(index_html(), media_type="text/html; charset=utf-8",
                        headers={"Cache-Control": "no-cache", **SECURITY_HEADERS})

    app.mount("/console", StaticFiles(directory=CONSOLE_DIR), name="console")

    @app.get("/docs", include_in_schema=False)
    async def swagger_ui() -> Response:
        return get_swagger_ui_html(
            openapi_url=app.openapi_url or "/openapi.json", title=f"{app.title} - Swagger UI",
            swagger_js_url=f"{SWAGGER_ASSETS}/swagger-ui-bundle.js",
            swagger_css_url=f"{SWAGGER_ASSETS}/swagger-ui.css",
            swagger_favicon_url=f"{SWAGGER_ASSETS}/favicon-32x32.png")

    app.mount(SWAGGER_ASSETS, StaticFiles(directory=_swagger_dir()), name="swagger")

    @app.post("/estop", responses=_ESTOP_ERRORS,
              summary="Latch the e-stop (always runs, even if auditing fails)")
    async def post_estop(request: Request, who: Operator,
                         body: EstopBody | None = None) -> JSONResponse:
        reason = body.reason if body else EstopBody().reason
        return await command(request, who, "estop", lambda: ops.estop(who.name, reason),
                             audit_first=False)

    @app.post("/reset", responses=_COMMAND_ERRORS,
              summary="Clear a latched stop (409 when not allowed)")
    async def post_reset(request: Request, who: Operator) -> JSONResponse:
        return await command(request, who, "reset", lambda: ops.reset(who.name))

    @app.post("/recover/{device}", responses=_COMMAND_ERRORS,
              summary="Recover a device from its fault while the stop "
              "is latched: the wrist drive's fault reset, or the arm controller's recovery "
              "(409 otherwise)")
    async def post_recover(request: Request, who: Operator, device: Device) -> JSONResponse:
        return await command(request, who, f"recover {device}",
                             lambda: ops.recover(device, who.name))

    @app.post("/procedure/{action}", responses=_COMMAND_ERRORS,
              summary="Start, pause, resume or abort the procedure")
    async def post_procedure(request: Request, who: Operator,
                             action: ProcedureAction) -> JSONResponse:
        return await command(request, who, f"procedure {action}",
                             lambda: ops.procedure(action, who.name))

    @app.post("/targets", responses=_COMMAND_ERRORS,
              summary="Replace the suture targets (409 while running)")
    async def post_targets(request: Request, who: Operator, body: TargetsBody) -> JSONResponse:
        return await command(request, who, "set targets",
                             lambda: ops.set_targets(list(body.targets), who.name))

    @app.get("/guide", responses=_READ_ERRORS,
             summary="The guided-insertion plan and live guidance status")
    async def get_guide(_: Observer) -> JSONResponse:
        return read(ops.guide)

    @app.post("/guide/plan", responses=_COMMAND_ERRORS,
              summary="Plan a guided insertion from a planning scene (422 "
                                     "bad scene, 409 no collision-free placement)")
    async def post_guide_plan(request: Request, who: Operator,
                              body: GuidePlanBody) -> JSONResponse:
        return await command(request, who, "guide plan",
                             lambda: ops.plan_guide(body.scene, body.T_OM_F, who.name,
                                                    body.seed),
                             in_thread=True)

    @app.post("/guide/start", responses=_COMMAND_ERRORS,
              summary="Start the planned guided insertion (GUIDE mode; 409 "
                                      "when not allowed)")
    async def post_guide_start(request: Request, who: Operator) -> JSONResponse:
        return await command(request, who, "guide start", lambda: ops.start_guide(who.name))

    @app.post("/guide/stop", responses=_COMMAND_ERRORS,
              summary="End guidance (HOLD) and clear the plan")
    async def post_guide_stop(request: Request, who: Operator) -> JSONResponse:
        return await command(request, who, "guide stop", lambda: ops.stop_guide(who.name))

    @app.get("/calibration/temporal", responses={**_READ_ERRORS, **_answers(
                 _422=(ValidationProblem, "the query does not validate (samples: a "
                                          "boolean)"))},
             summary="The temporal calibration's phase, progress and result "
                     "(samples=true: the record too)")
    async def get_temporal(_: Observer, samples: bool = False) -> JSONResponse:
        return read(lambda: ops.temporal(samples))

    @app.post("/calibration/temporal", responses=_COMMAND_ERRORS,
              summary="Move the arm through the temporal calibration's excitation and fit "
                      "the stereo camera's time offset (409 unless READY with the robot "
                      "marker in view)")
    async def post_temporal(request: Request, who: Operator,
                            body: TemporalCalibrationBody) -> JSONResponse:
        return await command(request, who, "temporal calibration",
                             lambda: ops.start_temporal(body, who.name))

    @app.get("/recording", responses=_READ_ERRORS,
             summary="The session recording's state, file and figures (frames written, "
                     "dropped; MB/s)")
    async def get_recording(_: Observer) -> JSONResponse:
        return read(ops.recording)

    @app.post("/recording/start", responses=_COMMAND_ERRORS,
              summary="Record the session to an MCAP file (422 for a file that cannot be "
                      "created, 409 while recording)")
    async def post_recording_start(request: Request, who: Operator,
                                   body: RecordingStartBody) -> JSONResponse:
        return await command(request, who, "recording start",
                             lambda: ops.start_recording(body, who.name), in_thread=True)

    @app.post("/recording/stop", responses=_COMMAND_ERRORS,
              summary="End the recording and close its file (never refused)")
    async def post_recording_stop(request: Request, who: Operator) -> JSONResponse:
        return await command(request, who, "recording stop",
                             lambda: ops.stop_recording(who.name), in_thread=True)

    @app.get("/needle", responses=_READ_ERRORS,
             summary="The needle cell, the procedure's next step and results")
    async def get_needle(_: Observer) -> JSONResponse:
        return read(ops.needle)

    @app.post("/needle/cell", responses=_COMMAND_ERRORS,
              summary="Load a simulated needle trial cell (a fresh procedure)")
    async def post_needle_cell(request: Request, who: Operator,
                               body: NeedleCellBody) -> JSONResponse:
        return await command(request, who, "needle cell",
                             lambda: ops.needle_cell(body.trial, body.difficulty, who.name,
                                                     body.servo),
                             in_thread=True)

    @app.post("/needle/{step}", responses=_COMMAND_ERRORS,
              summary="Run needle step NG, NH, ND, NR or NP (409 when "
                                        "refused before moving or out of turn)")
    async def post_needle_step(request: Request, who: Operator,
                               step: NeedleStep) -> JSONResponse:
        return await command(request, who, f"needle {step}",
                             lambda: ops.needle_step(step, who.name), in_thread=True)

    @app.websocket("/telemetry")
    async def telemetry(ws: WebSocket) -> None:
        """Live snapshots at ``telemetry_hz`` until the client goes. The token comes in
        the Authorization header or, for browsers (which cannot set it), ``?token=``."""
        token = (_bearer_from_header(ws.headers.get("authorization"))
                 or ws.query_params.get("token") or None)
        try:
            who = _authorize(tokens, token, "observer")
        except _Refused as exc:
            await record(ws, exc.principal, exc.status, exc.detail, method="WS")
            if exc.status == 401:
                await count_failure(limiter, note_lockout, ws.scope)
            await _deny(ws, exc.status, exc.detail, exc.headers)
            return
        why = await audit_ready()
        result = f"telemetry at {telemetry_hz:g} Hz"
        if why is not None or not await record(ws, who, 101, result, method="WS"):
            detail = f"refused: the audit log cannot be written ({why or 'write failed'})"
            await _deny(ws, 503, detail)
            return
        await ws.accept()
        await _stream(ws, ops, period, views)

    return app


async def _deny(ws: WebSocket, status: int, detail: str,
                headers: dict[str, str] | None = None) -> None:
    """Refuse a websocket handshake with a real HTTP status where the server can send one
    (ASGI denial-response extension), else by closing with 1008 (policy violation)."""
    if "websocket.http.response" in ws.scope.get("extensions", {}):
        await ws.send_denial_response(JSONResponse({"detail": detail}, status, headers=headers))
    else:  # pragma: no cover - uvicorn and the test client both support denial responses
        await ws.close(code=1008, reason=detail[:120])


# -- serving -------------------------------------------------------------------------------
_TOKEN_IN_QUERY = re.compile(r"(token=)[^&\s\"']*")


class _UvicornLogFilter(logging.Filter):
    """uvicorn logs websocket paths with their query: never let ``?token=`` reach a log.

    Also drops uvicorn's (0.54, websockets-sansio) false "returned without completing
    handshake" error, which it logs after every denial response (our refused telemetry
    connects): the telemetry endpoint always accepts or denies, so it is never true here.
    """

    def filter(self, record: logging.LogRecord) -> bool:
        msg = record.getMessage()
        if msg.startswith("ASGI callable returned without completing handshake"):
            return False
        if "token=" in msg:
            record.msg, record.args = _TOKEN_IN_QUERY.sub(r"\1<redacted>", msg), ()
        return True


_LOG_FILTER = _UvicornLogFilter()


class _Server(uvicorn.Server):
    """uvicorn without signal handlers (the daemon owns SIGINT/SIGTERM and stops the API
    by cancelling its scope) that reports when it is listening."""

    def __init__(self, config: uvicorn.Config, on_listening: Callable[[], None]) -> None:
        super().__init__(config)
        self._on_listening = on_listening
        self.shut_down = False

    @contextlib.contextmanager
    def capture_signals(self) -> Iterator[None]:
        # uvicorn.Server.serve() would replace the process's SIGINT/SIGTERM handlers
        yield

    async def startup(self, sockets: list[socket.socket] | None = None) -> None:
        await super().startup(sockets=sockets)
        if self.started:  # the listening socket accepts connections from here on
            self._on_listening()

    async def shutdown(self, sockets: list[socket.socket] | None = None) -> None:
        self.shut_down = True
        await super().shutdown(sockets=sockets)


def _bind(host: str, port: int) -> socket.socket:
    """A bound TCP socket for ``host:port`` (port 0: a free one); OSError names both."""
    try:
        family, kind, proto, _, addr = socket.getaddrinfo(
            host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)[0]
        sock = socket.socket(family, kind, proto)
    except OSError as exc:
        raise OSError(exc.errno, f"cannot bind the API to {host}:{port}: "
                                 f"{exc.strerror or exc}") from None
    try:
        # a restarted daemon must get its port back while old connections sit in TIME_WAIT
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(addr)
    except OSError as exc:
        sock.close()
        raise OSError(exc.errno, f"cannot bind the API to {host}:{port}: "
                                 f"{exc.strerror or exc}") from None
    return sock


def bind_api(host: str, port: int, *, allow_remote: bool = False) -> socket.socket:
    """The API's listening socket, bound now: the daemon binds it before it starts
    anything else, so that a port in use is one clear error and not a half-started cell.
    ``ValueError`` for a remote host without ``allow_remote``; ``OSError`` naming host and
    port when it cannot be bound."""
    if not allow_remote and not ApiSection.is_loopback(host):
        raise ValueError(f"refusing to serve the operator API on {host!r}: not a loopback "
                         "address (set [api] allow_remote = true to allow it)")
    return _bind(host, port)


async def serve(app: FastAPI, host: str, port: int, *, allow_remote: bool = False,
                grace_s: float = 2.0, sock: socket.socket | None = None,
                tls: tuple[str, str] | None = None,
                task_status: TaskStatus[int] = anyio.TASK_STATUS_IGNORED) -> None:
    """Serve ``app`` on ``host:port`` until the surrounding scope is cancelled.

    Use ``port = await tg.start(serve, app, host, port)``: it returns the port actually
    listened on (``port=0`` picks a free one) once connections are accepted. A host that is
    not loopback is refused unless ``allow_remote`` (``[api] allow_remote``). Installs no
    signal handlers. On cancellation, open connections get up to ``grace_s`` seconds to
    finish (websockets are closed with 1012) before the cancellation goes on.
    ``sock``: a socket from :func:`bind_api` (then ``host``/``port`` only name it); ``tls``:
    (certificate file, key file) to serve HTTPS. Needs anyio's asyncio backend (uvicorn
    runs on asyncio).
    """
    if not allow_remote and not ApiSection.is_loopback(host):
        if sock is not None:
            sock.close()
        raise ValueError(f"refusing to serve the operator API on {host!r}: not a loopback "
                         "address (set [api] allow_remote = true to allow it)")
    try:
        asyncio.get_running_loop()
    except RuntimeError:
        raise RuntimeError("serve() needs anyio's asyncio backend (uvicorn runs on "
                           "asyncio)") from None
    for name in ("uvicorn.error", "uvicorn.access"):
        if _LOG_FILTER not in logging.getLogger(name).filters:
            logging.getLogger(name).addFilter(_LOG_FILTER)
    if sock is None:
        sock = _bind(host, port)
    actual = int(sock.getsockname()[1])
    # log_config=None: leave the daemon's logging alone; lifespan off: the daemon's task
    # group owns start-up and shutdown; proxy_headers off: audit the real peer address
    config = uvicorn.Config(app, host=host, port=actual, lifespan="off", log_config=None,
                            access_log=False, proxy_headers=False, server_header=False,
                            timeout_graceful_shutdown=grace_s,
                            ssl_certfile=tls[0] if tls else None,
                            ssl_keyfile=tls[1] if tls else None)

    def listening() -> None:
        log.info("operator API listening on %s:%d", host, actual)
        task_status.started(actual)

    server = _Server(config, listening)
    try:
        await server.serve(sockets=[sock])
    finally:
        # uvicorn only shuts down when its own flag is set; on cancellation do it here,
        # shielded, so that connections are closed before the scope unwinds
        with anyio.CancelScope(shield=True):
            if server.started and not server.shut_down:
                server.should_exit = True
                with anyio.move_on_after(grace_s + 1.0):
                    await server.shutdown(sockets=[sock])
            for s in getattr(server, "servers", []):
                s.close()
            sock.close()
        log.info("operator API on %s:%d stopped", host, actual)
