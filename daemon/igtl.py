"""The OpenIGTLink server for 3D Slicer (docs/api.md, "OpenIGTLink (3D Slicer)").

Out: every pose of the pose store (``T_C_RM``, ``T_C_OM``, ``T_C_EM``, ``T_En_EM``, ...)
and the arm's TCP (``T_B_tcp``, from the control loop's status) as TRANSFORM messages,
named in PLUS's ``FromToTo`` convention from :data:`FRAME_NAMES` (``T_C_OM`` ->
``OpenerToCamera``), translation in millimetres (Slicer's unit; our poses are in metres),
stamped with the pose's capture instant as seconds since the Unix epoch.

Rate: at ``[igtl] rate_hz`` the event loop looks at the pose store and sends each pose
that is **new since the last look** (its capture stamp changed), the newest only when
several came in between. Why not every pose at every tick: a pose that stopped updating
(a field hidden) then freezes in Slicer instead of being re-sent as if it were live, and
nothing is sent twice with one stamp. A client that connects gets the newest of each
pose at once, so it never waits for the next tracked frame to see the scene.

In: POINT messages (a markups fiducial list sent by OpenIGTLinkIF): the points, in mm in
the opener-marker frame ``OM``, become the suture targets exactly as ``POST /targets``
sets them (the same :class:`~oralnav.daemon.schemas.TargetsBody` validation, then
``DaemonCore.set_targets``, which refuses while RUNNING or PAUSED), audited in the API's
audit log (method ``IGTL``, path ``igtl:POINT/<device>``, who ``igtl``, the peer's
address as ``client``; write-ahead like an API command). Every POINT is answered with a
STRING message named :data:`REPLY_DEVICE` to the client that sent it: ``ok: ...`` or
``refused (<status>): <why>`` (pyigtl has no STATUS message; Slicer shows a STRING as a
text node).

Threads: the sockets are :class:`~oralnav.daemon.igtl_sockets.IgtlSockets`' own thread
(why not pyigtl's server: that module's docstring). The event loop samples the poses
and hands the thread ready values (``broadcast``, ``reply``); the thread hands received
POINT lists to the event loop through an anyio memory stream
(``anyio.from_thread.run_sync`` with the loop's token), where they are validated,
audited (fsync in a worker thread) and applied.
"""

from __future__ import annotations

import contextlib
import functools
import json
import logging
import math
import time
from collections.abc import Callable, Iterator, Sequence
from typing import TYPE_CHECKING, Any

import anyio
import anyio.from_thread
import anyio.lowlevel
import anyio.to_thread
import numpy as np
from pydantic import ValidationError

from oralnav.daemon.audit import AuditError
from oralnav.daemon.igtl_sockets import IgtlSockets, PointRequest
from oralnav.daemon.schemas import MAX_TARGET_RADIUS, MAX_TARGETS, SutureTarget, TargetsBody
from oralnav.safety.errors import StateError

if TYPE_CHECKING:
    from oralnav.config.daemon import IgtlSection
    from oralnav.daemon.core import DaemonCore

log = logging.getLogger(__name__)

#: OpenIGTLink's registered port (the OpenIGTLinkIF connector's default)
DEFAULT_PORT = 18944
#: The IGTL name of each of our frames (docs/conventions.md). A pose ``T_<to>_<from>``
#: is sent as ``<from>To<to>`` (PLUS's convention): ``T_C_OM`` -> ``OpenerToCamera``. The
#: marker fields are named after the part they sit on (PLUS names a tool by its marker's
#: frame): ``Robot`` is the robot marker RM, not the base. A frame not listed keeps its
#: code (``T_C_XY`` -> ``XYToCamera``).
FRAME_NAMES: dict[str, str] = {
    "C": "Camera",        # the stereo camera (the tracker)
    "En": "Endoscope",
    "B": "RobotBase",
    "RM": "Robot",        # robot marker (field on the arm)
    "OM": "Opener",       # opener marker (field on the mouth opener)
    "EM": "Effector",     # end-effector marker (field on the end-effector)
    "tcp": "Tcp",         # the arm's tool centre point
}
#: The arm's TCP in the base, from the control loop's status (not the pose store)
TCP_POSE = "T_B_tcp"
#: Longest device name an OpenIGTLink header holds (bytes; longer ones are cut)
DEVICE_NAME_BYTES = 20
#: POINT lists waiting for the event loop; more are refused ("busy")
MAX_QUEUED_REQUESTS = 16


# -- pure helpers (no sockets) ------------------------------------------------------------
def device_name(pose: str) -> str | None:
    """The IGTL device name of pose ``pose`` (``T_<to>_<from>``, our convention) by
    :data:`FRAME_NAMES`; None when the name is not of that form or the result would not
    fit an IGTL header (:data:`DEVICE_NAME_BYTES`)."""
    parts = pose.split("_")
    if len(parts) != 3 or parts[0] != "T" or not parts[1] or not parts[2]:
        return None
    to, frm = parts[1], parts[2]
    name = f"{FRAME_NAMES.get(frm, frm)}To{FRAME_NAMES.get(to, to)}"
    return name if len(name.encode()) <= DEVICE_NAME_BYTES else None


def to_igtl_matrix(T: np.ndarray) -> np.ndarray:
    """A 4x4 pose in metres as an IGTL TRANSFORM matrix: float32, translation in mm."""
    M = np.array(T, dtype=np.float64, copy=True).reshape(4, 4)
    M[:3, 3] *= 1e3
    return M.astype(np.float32)


def epoch_offset(clock: Callable[[], float], wall: Callable[[], float] = time.time) -> float:
    """Seconds to add to a stamp of ``clock`` (the daemon's monotonic clock) to get seconds
    since the Unix epoch: the wall clock read between two ``clock`` reads, of the tightest
    of five tries. Taken once when the server starts: a later step of the wall clock (NTP)
    does not move the stamps sent, which keep the monotonic clock's order."""
    best = (math.inf, 0.0)
    for _ in range(5):
        a = clock()
        w = wall()
        b = clock()
        if b - a < best[0]:
            best = (b - a, w - 0.5 * (a + b))
    return best[1]


def targets_from_points(names: Sequence[str],
                        positions_mm: Sequence[Sequence[float]]) -> list[SutureTarget]:
    """Suture targets from a POINT list: ``names`` and ``positions_mm`` (mm, in the
    opener-marker frame ``OM``), checked as ``POST /targets`` checks its body (at most
    ``MAX_TARGETS``, names of ``[A-Za-z0-9_.-]`` and unique, finite positions at most
    ``MAX_TARGET_RADIUS`` from the ``OM`` origin). Raises ValueError naming each point
    that is wrong (by index and name) and why, in mm."""
    if len(names) != len(positions_mm):
        raise ValueError(f"{len(names)} names for {len(positions_mm)} positions")
    if len(names) > MAX_TARGETS:
        raise ValueError(f"{len(names)} points; at most {MAX_TARGETS} suture targets")
    wrong: list[str] = []
    for i, (name, p) in enumerate(zip(names, positions_mm, strict=True)):
        xyz = [float(v) for v in p]
        if len(xyz) != 3 or not all(math.isfinite(v) for v in xyz):
            wrong.append(f"point {i} {name!r}: position {xyz} mm is not three finite numbers")
            continue
        r_mm = math.hypot(*xyz)
        if r_mm > MAX_TARGET_RADIUS * 1e3:
            wrong.append(f"point {i} {name!r}: {r_mm:.1f} mm from the opener marker's origin, "
                         f"farther than {MAX_TARGET_RADIUS * 1e3:.0f} mm (positions are read "
                         "in mm in the opener marker frame OM)")
    if wrong:
        raise ValueError("; ".join(wrong))
    items = [{"name": n, "p_OM": tuple(float(v) * 1e-3 for v in p)}
             for n, p in zip(names, positions_mm, strict=True)]
    try:
        return list(TargetsBody.model_validate({"targets": items}).targets)
    except ValidationError as exc:
        raise ValueError(_describe(exc, names)) from None


def _describe(exc: ValidationError, names: Sequence[str]) -> str:
    """Pydantic's errors about a targets body, each naming the point (index and name)."""
    out = []
    for e in exc.errors():
        loc = tuple(e.get("loc", ()))
        msg = str(e.get("msg", "invalid"))
        if e.get("type") == "value_error":
            msg = str(e.get("ctx", {}).get("error", msg))   # the validator's own words
        if len(loc) >= 2 and loc[0] == "targets" and isinstance(loc[1], int):
            i = loc[1]
            what = "name" if "name" in loc[2:] else ".".join(str(p) for p in loc[2:])
            who = f"point {i} {names[i]!r}" if i < len(names) else f"point {i}"
            out.append(f"{who}: {what}: {msg}" if what else f"{who}: {msg}")
        else:
            out.append(f"points: {msg}")
    return "; ".join(out) or str(exc)


# -- the server on the event loop -----------------------------------------------------
class IgtlServer:
    """The OpenIGTLink server of the daemon (see the module docstring): ``core``'s poses
    out at ``rate_hz`` (Hz), suture targets in (refused unless ``accept_targets``).
    :meth:`bind` opens the port (no thread yet), :meth:`run` is the task of the daemon's
    task group."""

    def __init__(self, core: DaemonCore, host: str = "127.0.0.1", port: int = DEFAULT_PORT,
                 *, rate_hz: float = 30.0, accept_targets: bool = True) -> None:
        if not (math.isfinite(rate_hz) and rate_hz > 0):
            raise ValueError(f"igtl rate_hz must be a positive number, got {rate_hz!r}")
        self.core = core
        self.rate_hz = float(rate_hz)
        self.accept_targets = bool(accept_targets)
        self.sockets = IgtlSockets(host, port)
        #: seconds added to a stamp of ``core.clock`` to get the epoch (set by :meth:`run`)
        self.offset = epoch_offset(core.clock)
        self._sent: dict[str, float] = {}     # pose -> the capture stamp last sent
        self._unnamed: set[str] = set()        # poses without an IGTL name (warned once)

    @classmethod
    def from_config(cls, core: DaemonCore, section: IgtlSection) -> IgtlServer:
        """The server ``[igtl]`` describes (docs/formats.md)."""
        return cls(core, section.host, section.port, rate_hz=section.rate_hz,
                   accept_targets=section.accept_targets)

    @property
    def host(self) -> str:
        return self.sockets.host

    @property
    def port(self) -> int:
        return self.sockets.port

    def bind(self) -> int:
        """Open the port; returns it. Raises OSError (taken, or not an address here)."""
        return self.sockets.bind()

    async def run(self, *, task_status: anyio.abc.TaskStatus[int] =
                  anyio.TASK_STATUS_IGNORED) -> None:
        """Serve until cancelled; ``task_status.started(port)`` once clients may connect."""
        self.bind()
        self.offset = epoch_offset(self.core.clock)
        send, receive = anyio.create_memory_object_stream[PointRequest](MAX_QUEUED_REQUESTS)
        token = anyio.lowlevel.current_token()

        def on_points(req: PointRequest) -> None:  # in the socket thread
            try:
                anyio.from_thread.run_sync(send.send_nowait, req, token=token)
            except anyio.WouldBlock:
                self.sockets.reply(req.conn, f"refused (503): {MAX_QUEUED_REQUESTS} POINT "
                                             "lists are waiting already; send it again")
            except (anyio.ClosedResourceError, anyio.BrokenResourceError, RuntimeError):
                pass   # the server is stopping

        self.sockets.on_points = on_points
        self.sockets.start()
        try:
            async with send, receive, anyio.create_task_group() as tg:
                tg.start_soon(self._stream)
                tg.start_soon(self._commands, receive)
                task_status.started(self.port)
        finally:
            with anyio.CancelScope(shield=True):
                await anyio.to_thread.run_sync(self.sockets.close)

    # -- out: poses ------------------------------------------------------------------
    def sample(self) -> list[tuple[str, np.ndarray, float]]:
        """The poses new since the last call, as ``(device, matrix, epoch stamp)``:
        each of the pose store's poses whose capture stamp changed, and the arm's TCP
        whose measurement instant changed (``t_arm`` of the loop's status)."""
        core = self.core
        out: list[tuple[str, np.ndarray, float]] = []
        for pose in core.pose_store.snapshot(0.0):
            rec = core.pose_store.pose(pose)
            if rec is not None:
                self._add(out, pose, rec["T"], rec["stamp"])
        st = core.control.read_status()
        if st is not None:
            t = float(st["t_arm"]) or float(st["t"])   # t_arm is 0 before a measurement
            if t > 0.0:
                self._add(out, TCP_POSE, np.array(st["T_B_tcp"]), t)
        return out

    def _add(self, out: list[tuple[str, np.ndarray, float]], pose: str, T: np.ndarray,
             stamp: float) -> None:
        if self._sent.get(pose) == stamp:
            return
        name = device_name(pose)
        if name is None:
            if pose not in self._unnamed:
                self._unnamed.add(pose)
                log.warning("igtl: pose %r has no OpenIGTLink name of at most %d bytes "
                            "(FRAME_NAMES in daemon/igtl.py); not sent", pose,
                            DEVICE_NAME_BYTES)
            return
        self._sent[pose] = stamp
        out.append((name, to_igtl_matrix(T), stamp + self.offset))

    async def _stream(self) -> None:
        period = 1.0 / self.rate_hz
        due = time.monotonic()
        while True:
            try:
                self.sockets.broadcast(self.sample())
            except Exception:   # a bad pose never ends the stream (or the daemon)
                log.exception("igtl: sampling the poses failed")
            due += period
            now = time.monotonic()
            if due < now - period:   # fell behind (a busy loop): no burst to catch up
                due = now
            await anyio.sleep(max(0.0, due - now))

    # -- in: suture targets ------------------------------------------------------------
    async def _commands(self, receive: Any) -> None:
        async for req in receive:
            try:
                await self.apply_points(req)
            except Exception as exc:   # answered, logged; the server goes on
                log.exception("igtl: POINT %r from %s failed", req.device, req.client)
                self.sockets.reply(req.conn, f"refused (500): internal error: "
                                             f"{type(exc).__name__}: {exc}")

    async def apply_points(self, req: PointRequest) -> tuple[int, str]:
        """Validate, audit and apply one POINT list, and answer its sender; returns the
        audit status and result (200 ok, 400 malformed, 403 targets not accepted, 409
        refused by the state, 422 invalid points, 503 the audit log failed)."""
        path = f"igtl:POINT/{req.device}"
        body = json.dumps({"points": [{"name": n, "xyz_mm": list(p)} for n, p in
                                      zip(req.names, req.positions_mm, strict=True)]})
        audit = self.core.audit
        if req.error is not None:
            status, result = 400, f"malformed POINT message: {req.error}"
        elif not self.accept_targets:
            status, result = 403, "suture targets over OpenIGTLink are off ([igtl] " \
                                  "accept_targets = false)"
        else:
            try:
                targets = targets_from_points(req.names, req.positions_mm)
            except ValueError as exc:
                status, result = 422, str(exc)
            else:
                return await self._set(req, path, body, targets)
        await self._record(path, req, status, result, body)
        return self._answer(req, status, result, audit is not None)

    async def _set(self, req: PointRequest, path: str, body: str,
                   targets: list[SutureTarget]) -> tuple[int, str]:
        audit = self.core.audit
        intent: str | None = None
        if audit is not None:   # write-ahead, as the API: no record, no command
            try:
                intent = await anyio.to_thread.run_sync(functools.partial(
                    audit.intent, who="igtl", role=None, method="IGTL", path=path,
                    body=body, client=req.client))
            except AuditError as exc:
                result = f"command refused: the audit log cannot be written ({exc})"
                await self._record(path, req, 503, result, "" if exc.record_id else body,
                                   outcome_of=exc.record_id)
                return self._answer(req, 503, result, False)
        try:
            self.core.set_targets(targets, f"igtl {req.client}")
            status, result = 200, "ok"
        except StateError as exc:
            status, result = 409, str(exc) or "not allowed in the current state"
        except ValueError as exc:
            status, result = 422, str(exc) or "invalid value"
        audited = await self._record(path, req, status, result, "" if intent else body,
                                     outcome_of=intent)
        if status == 200:
            result = f"{len(targets)} suture target(s) set from POINT {req.device!r}"
        return self._answer(req, status, result, audited)

    async def _record(self, path: str, req: PointRequest, status: int, result: str,
                      body: str, outcome_of: str | None = None) -> bool:
        """One audit record (fsync in a worker thread); False when not written (it is
        then kept for retry and journaled by the audit log) or there is no log."""
        audit = self.core.audit
        if audit is None:
            return False
        try:
            await anyio.to_thread.run_sync(functools.partial(
                audit.record, who="igtl", role=None, method="IGTL", path=path,
                status=status, result=result, body=body, client=req.client,
                outcome_of=outcome_of))
        except AuditError:
            return False
        return True

    def _answer(self, req: PointRequest, status: int, result: str,
                audited: bool) -> tuple[int, str]:
        note = "" if audited else " (not audited)"
        if status == 200:
            log.info("igtl: %s from %s%s", result, req.client, note)
            self.sockets.reply(req.conn, f"ok: {result}{note}")
        else:
            log.warning("igtl: POINT %r from %s refused (%d): %s%s", req.device, req.client,
                        status, result, note)
            self.sockets.reply(req.conn, f"refused ({status}): {result}{note}")
        return status, result


@contextlib.contextmanager
def running(server: IgtlServer) -> Iterator[IgtlServer]:
    """Run ``server`` on an event loop of its own in a thread until the block ends (tests,
    ``oralnav bench igtl``); the daemon runs :meth:`IgtlServer.run` in its task group."""
    from anyio.from_thread import start_blocking_portal

    with start_blocking_portal() as portal:
        future, _ = portal.start_task(server.run, name="igtl")
        try:
            yield server
        finally:
            future.cancel()
            with contextlib.suppress(BaseException):
                future.exception(timeout=5.0)


class _NoLoop:
    """A control port with no control loop behind it (no TCP to send, goals ignored)."""

    alive = False

    def read_status(self) -> None:
        return None

    def set_goal(self, *args: Any, **kwargs: Any) -> None:
        pass

    def request_stop(self, reason: str) -> None:
        pass


@contextlib.contextmanager
def standalone_server(rate_hz: float = 30.0, port: int = 0) -> Iterator[IgtlServer]:
    """A server on 127.0.0.1 (``port`` 0: any free one) over a core of its own with the
    default safety settings and no control loop, run by :func:`running`: what ``oralnav
    bench igtl`` measures. Poses go in through ``server.core.publish_pose``."""
    from oralnav.config.daemon import SafetySection
    from oralnav.daemon.core import DaemonCore
    from oralnav.safety.watchdogs import WatchdogSet

    core = DaemonCore(_NoLoop(), WatchdogSet.from_settings(SafetySection(), 0.002))
    with running(IgtlServer(core, "127.0.0.1", port, rate_hz=rate_hz)) as server:
        yield server
