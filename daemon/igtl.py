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

Threads: all socket work runs in one thread of its own (:class:`IgtlSockets`: one
selector, non-blocking sockets, so a slow or hostile client never blocks the others, the
event loop, the control loop or tracking). The event loop samples the poses and hands
the thread ready values (``broadcast``, ``reply``: a locked queue and a wake-up
socket); the thread hands received POINT lists to the event loop through an anyio
memory stream (``anyio.from_thread.run_sync`` with the loop's token), where they are
validated, audited (fsync in a worker thread) and applied.

Why not pyigtl's ``OpenIGTLinkServer``: it replaces the process's SIGTERM and SIGINT
handlers (and cannot be built outside the main thread), binds only 127.0.0.1 or an
interface's first address, serves one client at a time, spins on a closed connection
until a send fails, drops a header split across reads (losing the stream's framing),
hands ``recv`` whatever body size a header declares (a buffer that large, up to 2**64
bytes) and checks no CRC.
So this module keeps pyigtl for the format (``MessageBase.parse_header``, the message
classes' ``pack``/``unpack``, ``CRC64``) and runs its own socket loop: headers and bodies
are framed across reads, a declared body over :data:`MAX_BODY_BYTES`, an unknown header
version, a header that does not decode or a CRC mismatch close that connection (logged),
a stalled partial message is dropped after :data:`STALL_S`, a client that does not read
is dropped past :data:`MAX_OUTBOX_BYTES`.
"""

from __future__ import annotations

import contextlib
import functools
import json
import logging
import math
import selectors
import socket
import struct
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import anyio
import anyio.from_thread
import anyio.lowlevel
import anyio.to_thread
import numpy as np
from pydantic import ValidationError
from pyigtl.messages import CRC64, MessageBase, PointMessage, StringMessage, TransformMessage

from oralnav.daemon.audit import AuditError
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
#: The STRING message that answers each POINT message (to its sender only)
REPLY_DEVICE = "OralnavReply"
#: Longest body accepted (bytes): a POINT of MAX_TARGETS points is 64 x 136 = 8704 bytes,
#: plus a version-2 extended header and metadata. More closes the connection: a huge
#: declared size is garbage (or a volume Slicer should not send here), and reading it
#: would hold that much memory per client.
MAX_BODY_BYTES = 64 * 1024
#: Bytes waiting for a client that does not read before it is dropped (about a minute of
#: five poses at 30 Hz; a live Slicer reads at once)
MAX_OUTBOX_BYTES = 1 << 20
#: A message begun but not finished within this long drops the connection (s)
STALL_S = 5.0
#: Clients served at once; more are refused (each holds a socket and buffers)
MAX_CLIENTS = 8
#: POINT lists waiting for the event loop; more are refused ("busy")
MAX_QUEUED_REQUESTS = 16
#: Longest reply text (characters); a STRING body holds at most 65535 bytes
MAX_REPLY_CHARS = 2000
#: An OpenIGTLink header: version, type, device name, timestamp, body size, CRC (bytes)
HEADER_BYTES = MessageBase.IGTL_HEADER_SIZE
#: One point of a POINT message's content (bytes): name, group, RGBA, XYZ, diameter, owner
POINT_BYTES = 64 + 32 + 4 + 12 + 4 + 20


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


def _ascii(text: str, limit: int = MAX_REPLY_CHARS) -> str:
    # pyigtl encodes a STRING as ASCII and fails on other text (it catches the wrong
    # exception): escape what is not ASCII, and keep the reply short
    text = text.encode("ascii", "backslashreplace").decode("ascii")
    return text if len(text) <= limit else text[:limit - 3] + "..."


# -- the socket thread -------------------------------------------------------------------
@dataclass(frozen=True)
class PointRequest:
    """A POINT message as the socket thread hands it to the event loop: who sent it
    (connection id, ``host:port``), its device name, its points (names, positions in
    mm) or, for a body that did not decode, ``error``."""

    conn: int
    client: str
    device: str
    names: tuple[str, ...] = ()
    positions_mm: tuple[tuple[float, float, float], ...] = ()
    error: str | None = None


@dataclass(eq=False)
class _Conn:
    id: int
    sock: socket.socket
    client: str
    inbox: bytearray = field(default_factory=bytearray)
    outbox: bytearray = field(default_factory=bytearray)
    since: float | None = None     # when the unfinished message in ``inbox`` began (s)
    ignored: set[str] = field(default_factory=set)   # message types logged as ignored


class _Drop(Exception):
    """This connection must close; the message says why (logged)."""


class IgtlSockets:
    """OpenIGTLink's sockets in one thread: accepts clients on ``host:port``, frames and
    checks what they send (POINT lists go to ``on_points``, called in this thread),
    sends them what :meth:`broadcast` and :meth:`reply` queue. The constructor does no
    I/O; :meth:`bind` opens the port, :meth:`start` the thread, :meth:`close` ends both
    (idempotent). ``broadcast``, ``reply`` and ``close`` may be called from any thread."""

    def __init__(self, host: str, port: int, *,
                 on_points: Callable[[PointRequest], None] = lambda req: None,
                 max_body: int = MAX_BODY_BYTES, max_outbox: int = MAX_OUTBOX_BYTES,
                 stall_s: float = STALL_S, max_clients: int = MAX_CLIENTS) -> None:
        self.host, self.port = host, int(port)
        self.on_points = on_points
        self.max_body, self.max_outbox = int(max_body), int(max_outbox)
        self.stall_s, self.max_clients = float(stall_s), int(max_clients)
        self._listen: socket.socket | None = None
        self._wake_r: socket.socket | None = None
        self._wake_w: socket.socket | None = None
        self._sel: selectors.BaseSelector | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._lock = threading.Lock()    # guards the queues below
        self._sends: deque[tuple[str, np.ndarray, float]] = deque()
        self._replies: deque[tuple[int, str]] = deque()
        self._conns: dict[int, _Conn] = {}     # touched by the thread only
        self._next_id = 1
        #: the newest packed TRANSFORM of each device, for clients that connect later
        self._latest: dict[str, bytes] = {}

    # -- lifecycle (any thread) ----------------------------------------------------------
    def bind(self) -> int:
        """Open the listening socket; returns the port (the one given, or the one the
        system chose for port 0). Raises OSError (port taken, address not ours)."""
        if self._listen is not None:
            return self.port
        family = socket.AF_INET6 if ":" in self.host else socket.AF_INET
        sock = socket.socket(family, socket.SOCK_STREAM)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind((self.host.strip("[]"), self.port))
            sock.listen(self.max_clients)
            sock.setblocking(False)
        except OSError:
            sock.close()
            raise
        self._listen = sock
        self.port = sock.getsockname()[1]
        return self.port

    def start(self) -> None:
        """Serve in a thread of its own (binds first when :meth:`bind` was not called)."""
        if self._thread is not None:
            return
        self.bind()
        assert self._listen is not None
        self._stop.clear()
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)
        self._sel = selectors.DefaultSelector()
        self._sel.register(self._listen, selectors.EVENT_READ, "listen")
        self._sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        self._thread = threading.Thread(target=self._serve, name="igtl sockets", daemon=True)
        self._thread.start()

    def close(self, timeout: float = 2.0) -> None:
        """Stop the thread, close every socket (idempotent; blocks up to ``timeout`` s)."""
        self._stop.set()
        self._wake()
        if self._thread is not None:
            self._thread.join(timeout)
            if self._thread.is_alive():
                log.error("igtl: the socket thread did not stop within %.1f s", timeout)
                return
            self._thread = None
        for s in (self._listen, self._wake_r, self._wake_w):
            if s is not None:
                s.close()
        self._listen = self._wake_r = self._wake_w = None
        if self._sel is not None:
            self._sel.close()
            self._sel = None

    @property
    def clients(self) -> int:
        """Clients connected now."""
        return len(self._conns)

    @property
    def queued(self) -> int:
        """Messages handed over (:meth:`broadcast`, :meth:`reply`) that the thread has not
        taken yet."""
        with self._lock:
            return len(self._sends) + len(self._replies)

    # -- hand-off from other threads ---------------------------------------------------
    def broadcast(self, items: Sequence[tuple[str, np.ndarray, float]]) -> None:
        """Send TRANSFORM messages ``(device, matrix, epoch stamp)`` to every client
        (``matrix``: 4x4 as :func:`to_igtl_matrix` gives it; stamp: s since the epoch)."""
        if not items:
            return
        with self._lock:
            self._sends.extend(items)
        self._wake()

    def reply(self, conn: int, text: str) -> None:
        """Send ``text`` as a STRING message named :data:`REPLY_DEVICE` to connection
        ``conn`` (dropped silently when it has gone)."""
        with self._lock:
            self._replies.append((conn, text))
        self._wake()

    def _wake(self) -> None:
        w = self._wake_w
        if w is None:
            return
        with contextlib.suppress(BlockingIOError, OSError):  # full: a wake-up is pending
            w.send(b"\0")

    # -- the thread ------------------------------------------------------------------
    def _serve(self) -> None:
        assert self._sel is not None
        try:
            while not self._stop.is_set():
                try:
                    events = self._sel.select(timeout=0.5)
                    for key, mask in events:
                        if key.data == "listen":
                            self._accept()
                        elif key.data == "wake":
                            with contextlib.suppress(BlockingIOError, OSError):
                                key.fileobj.recv(4096)  # type: ignore[union-attr]
                        else:
                            self._service(key.data, mask)
                    self._take_queued()
                    self._check_stalls(time.monotonic())
                except Exception:  # never let one bad turn end the server
                    log.exception("igtl: socket loop error (the server goes on)")
                    time.sleep(0.05)
        finally:
            for c in list(self._conns.values()):
                self._close(c)

    def _accept(self) -> None:
        assert self._listen is not None and self._sel is not None
        try:
            sock, addr = self._listen.accept()
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:   # out of descriptors, ...: the listener stays
            log.error("igtl: cannot accept a client: %s", exc)
            return
        client = f"{addr[0]}:{addr[1]}"
        if len(self._conns) >= self.max_clients:
            log.warning("igtl: client %s refused: %d clients connected already (the most "
                        "served at once)", client, len(self._conns))
            sock.close()
            return
        sock.setblocking(False)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)  # poses go out at once
        c = _Conn(self._next_id, sock, client)
        self._next_id += 1
        self._conns[c.id] = c
        self._sel.register(sock, selectors.EVENT_READ, c)
        log.info("igtl: client %s connected", client)
        for data in self._latest.values():   # the scene as it stands, without waiting
            c.outbox += data
        try:
            self._flush(c)
        except _Drop as why:
            self._drop(c, str(why))

    def _service(self, c: _Conn, mask: int) -> None:
        if c.id not in self._conns:
            return
        try:
            if mask & selectors.EVENT_READ:
                self._receive(c)
            if mask & selectors.EVENT_WRITE:
                self._flush(c)
        except _Drop as why:
            self._drop(c, str(why))
        except Exception as exc:  # a bug here closes this client, never the server
            log.exception("igtl: client %s: unexpected error", c.client)
            self._drop(c, f"{type(exc).__name__}: {exc}")

    def _receive(self, c: _Conn) -> None:
        try:
            data = c.sock.recv(65536)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:
            raise _Drop(f"receive failed: {exc}") from None
        if not data:
            log.info("igtl: client %s disconnected", c.client)
            self._close(c)
            return
        c.inbox += data
        self._frame(c)

    def _frame(self, c: _Conn) -> None:
        """Take every whole message out of ``c.inbox``; raises :class:`_Drop`."""
        while len(c.inbox) >= HEADER_BYTES:
            head = bytes(c.inbox[:HEADER_BYTES])
            try:
                h = MessageBase.parse_header(head)
            except (UnicodeDecodeError, struct.error) as exc:
                raise _Drop(f"malformed header ({exc}): not an OpenIGTLink stream?") from None
            if h["header_version"] not in (1, 2):
                raise _Drop(f"header version {h['header_version']} (OpenIGTLink has 1 and "
                            "2): not an OpenIGTLink stream?")
            size = int(h["body_size"])
            if size > self.max_body:
                raise _Drop(f"{h['message_type']!r} message {h['device_name']!r} declares a "
                            f"body of {size} bytes, more than the {self.max_body} accepted")
            if len(c.inbox) < HEADER_BYTES + size:
                break
            body = bytes(c.inbox[HEADER_BYTES:HEADER_BYTES + size])
            del c.inbox[:HEADER_BYTES + size]
            c.since = None
            (crc,) = struct.unpack_from(">Q", head, HEADER_BYTES - 8)
            if CRC64(body) != crc:
                raise _Drop(f"{h['message_type']!r} message {h['device_name']!r}: CRC "
                            "mismatch (corrupted or not OpenIGTLink)")
            self._dispatch(c, h, body)
        if c.inbox and c.since is None:
            c.since = time.monotonic()

    def _dispatch(self, c: _Conn, h: dict[str, Any], body: bytes) -> None:
        kind, device = h["message_type"], h["device_name"]
        if kind != "POINT":
            if kind not in c.ignored:  # once per type and client: Slicer may stream
                c.ignored.add(kind)
                log.info("igtl: client %s sent %s %r: ignored (only POINT is taken)",
                         c.client, kind, device)
            return
        try:
            content = _content_bytes(h, body)
            if content % POINT_BYTES:
                raise ValueError(f"{content} bytes of points is not a whole number of "
                                 f"{POINT_BYTES}-byte points")
            msg = PointMessage()
            msg.unpack(h, body)
            req = PointRequest(c.id, c.client, device, tuple(msg.names),
                               tuple(tuple(float(v) for v in p) for p in msg.positions))
        except Exception as exc:  # a framed message with a bad body: refused, stream goes on
            req = PointRequest(c.id, c.client, device,
                               error=f"{type(exc).__name__}: {exc}")
        self.on_points(req)

    def _flush(self, c: _Conn) -> None:
        if c.id not in self._conns:
            return
        if c.outbox:
            try:
                sent = c.sock.send(c.outbox)
            except (BlockingIOError, InterruptedError):
                sent = 0
            except OSError as exc:
                raise _Drop(f"send failed: {exc}") from None
            del c.outbox[:sent]
        assert self._sel is not None
        want = selectors.EVENT_READ | (selectors.EVENT_WRITE if c.outbox else 0)
        if self._sel.get_key(c.sock).events != want:
            self._sel.modify(c.sock, want, c)

    def _take_queued(self) -> None:
        with self._lock:
            sends, self._sends = list(self._sends), deque()
            replies, self._replies = list(self._replies), deque()
        packed = bytearray()
        for device, matrix, stamp in sends:
            data = TransformMessage(matrix, timestamp=stamp, device_name=device).pack()
            self._latest[device] = data
            packed += data
        targets: list[tuple[_Conn, bytes]] = []
        if packed:
            blob = bytes(packed)
            targets += [(c, blob) for c in self._conns.values()]
        for conn, text in replies:
            c = self._conns.get(conn)
            if c is not None:
                targets.append((c, StringMessage(_ascii(text),
                                                 device_name=REPLY_DEVICE).pack()))
        for c, data in targets:
            if c.id not in self._conns:
                continue
            c.outbox += data
            if len(c.outbox) > self.max_outbox:
                self._drop(c, f"not reading: {len(c.outbox)} bytes waiting (more than "
                              f"{self.max_outbox})")
                continue
            try:
                self._flush(c)
            except _Drop as why:
                self._drop(c, str(why))

    def _check_stalls(self, now: float) -> None:
        for c in list(self._conns.values()):
            if c.since is not None and now - c.since > self.stall_s:
                self._drop(c, f"a message begun {now - c.since:.1f} s ago is still "
                              f"unfinished ({len(c.inbox)} bytes received)")

    def _drop(self, c: _Conn, why: str) -> None:
        log.warning("igtl: client %s dropped: %s", c.client, why)
        self._close(c)

    def _close(self, c: _Conn) -> None:
        if self._conns.pop(c.id, None) is None:
            return
        if self._sel is not None:
            with contextlib.suppress(KeyError, ValueError):
                self._sel.unregister(c.sock)
        c.sock.close()


def _content_bytes(h: dict[str, Any], body: bytes) -> int:
    """The size of a message's content (bytes): its body less the version-2 extended
    header and metadata, as pyigtl's ``unpack`` cuts it."""
    if h["header_version"] < 2:
        return len(body)
    ext, meta_head, meta_body, _ = struct.unpack_from(">HHII", body, 0)
    content = len(body) - ext - meta_head - meta_body
    if content < 0:
        raise ValueError(f"extended header and metadata ({ext + meta_head + meta_body} bytes) "
                         f"longer than the body ({len(body)} bytes)")
    return content


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
