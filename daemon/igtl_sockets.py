"""OpenIGTLink's sockets for the daemon's server (``daemon/igtl.py``): one thread, one
selector, non-blocking sockets, so a slow or hostile client never blocks the others, the
event loop, the control loop or tracking.

The event loop hands the thread what to send (:meth:`IgtlSockets.broadcast`,
:meth:`IgtlSockets.reply`: a locked queue and a wake-up socket); the thread hands each
POINT list it receives to ``on_points`` (:class:`PointRequest`).

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
import logging
import selectors
import socket
import struct
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pyigtl.messages import CRC64, MessageBase, PointMessage, StringMessage, TransformMessage

__all__ = ["MAX_BODY_BYTES", "REPLY_DEVICE", "IgtlSockets", "PointRequest"]

log = logging.getLogger(__name__)

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
#: Longest reply text (characters); a STRING body holds at most 65535 bytes
MAX_REPLY_CHARS = 2000
#: An OpenIGTLink header: version, type, device name, timestamp, body size, CRC (bytes)
HEADER_BYTES = MessageBase.IGTL_HEADER_SIZE
#: One point of a POINT message's content (bytes): name, group, RGBA, XYZ, diameter, owner
POINT_BYTES = 64 + 32 + 4 + 12 + 4 + 20


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
        (``matrix``: 4x4 as ``daemon/igtl.py`` ``to_igtl_matrix`` gives it, translation
        in mm; stamp: s since the epoch)."""
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
