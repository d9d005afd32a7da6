"""The fake controller's socket loop: one thread, one selector for every socket, and the
controller cycle on its clock.

:class:`Conn` is one accepted connection with its buffers (the protocol modules subclass it:
``rtde``, ``dashboard``, ``script``); :class:`ServerLoop` is the part of
:class:`~oralnav.sim.peers.ur.controller.FakeURController` that listens, accepts, reads,
writes and closes, runs the controller cycle every ``period`` s (late cycles caught up, at
most 25 at a time, and counted as overruns) and runs other threads' socket changes on the
loop (:meth:`ServerLoop._in_loop`). Every listening socket sets ``SO_REUSEADDR``, so a fake
restarts at once on the same address.
"""

from __future__ import annotations

import logging
import queue
import selectors
import socket
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from oralnav.sim.peers.ur.controller import FakeURController

__all__ = ["Conn", "ServerLoop"]

log = logging.getLogger(__name__)


class Conn:
    """One accepted TCP connection with its outgoing buffer (sockets are non-blocking)."""

    kind = "?"
    MAX_BACKLOG = 1 << 20  # bytes of unsent data before data packages are dropped

    def __init__(self, ctrl: FakeURController, sock: socket.socket, peer: Any) -> None:
        self.ctrl, self.sock, self.peer = ctrl, sock, peer
        self.inbuf = bytearray()
        self.outbuf = bytearray()
        self.closed = False

    def fileno(self) -> int:
        """The socket's descriptor (for the selector)."""
        return self.sock.fileno()

    def send(self, data: bytes, droppable: bool = False) -> None:
        """Queue ``data`` and write what the socket takes; ``droppable`` data is discarded
        while more than ``MAX_BACKLOG`` bytes wait (a client that stopped reading)."""
        if self.closed or (droppable and len(self.outbuf) > self.MAX_BACKLOG):
            return
        self.outbuf += data
        self.flush()

    def flush(self) -> None:
        """Write queued data until the socket would block."""
        while self.outbuf and not self.closed:
            try:
                n = self.sock.send(self.outbuf)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                self.ctrl._drop(self)
                return
            del self.outbuf[:n]
        self.ctrl._want_write(self, bool(self.outbuf))

    def on_readable(self) -> None:
        """Read what arrived and hand it to :meth:`handle`; EOF or an error drops it."""
        try:
            data = self.sock.recv(65536)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            data = b""
        if not data:
            self.ctrl._drop(self)
            return
        self.inbuf += data
        self.handle()

    def on_accept(self) -> None:
        """Called once the loop has registered a new connection: what the server sends
        first (nothing by default)."""

    def handle(self) -> None:
        """Consume what ``inbuf`` holds (the protocol's part)."""
        raise NotImplementedError


class ServerLoop:
    """The socket loop of :class:`~oralnav.sim.peers.ur.controller.FakeURController`.

    The state below is created by ``FakeURController.__init__``; ``_lock`` guards the
    controller state, which the loop touches only while holding it.
    """

    host: str
    period: float  # s, one controller cycle
    _lock: threading.RLock
    _sel: selectors.BaseSelector | None
    _thread: threading.Thread | None
    _listeners: list[socket.socket]
    _conns: set[Conn]
    _actions: queue.Queue[tuple[Callable[[], Any], threading.Event, list]]
    _wake_r: socket.socket | None
    _wake_w: socket.socket | None
    _stopping: bool
    _overruns: int
    # Provided by the controller.
    _servers: Callable[[], list[tuple[int, type[Conn]]]]
    _cycle: Callable[[int], None]
    _event: Callable[..., None]

    # -- lifecycle --------------------------------------------------------------------------------

    def start(self) -> None:
        """Bind the ports and start the controller thread (raises ``OSError`` when a port is
        taken)."""
        if self._thread is not None:
            raise RuntimeError("FakeURController already started")
        self._sel = selectors.DefaultSelector()
        self._wake_r, self._wake_w = socket.socketpair()
        self._wake_r.setblocking(False)
        self._sel.register(self._wake_r, selectors.EVENT_READ, None)
        self._stopping = False
        try:
            self._listen()
        except OSError:
            self._close_all()
            raise
        self._thread = threading.Thread(target=self._run, name="fake-ur-controller", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Close every socket and stop the thread. Idempotent."""
        thread = self._thread
        if thread is None:
            return
        self._stopping = True
        self._wake()
        thread.join(5.0)
        self._thread = None
        self._close_all()

    def _listen(self) -> None:
        assert self._sel is not None
        for port, cls in self._servers():
            srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                srv.bind((self.host, port))
                srv.listen(8)
            except OSError as exc:
                srv.close()
                raise OSError(exc.errno, f"fake UR controller cannot listen on "
                                         f"{self.host}:{port}: {exc.strerror}") from None
            srv.setblocking(False)
            self._listeners.append(srv)
            self._sel.register(srv, selectors.EVENT_READ, cls)

    def _unlisten(self) -> None:
        for srv in self._listeners:
            if self._sel is not None:
                try:
                    self._sel.unregister(srv)
                except (KeyError, ValueError):
                    pass
            srv.close()
        self._listeners.clear()

    def _close_all(self) -> None:
        with self._lock:
            for conn in list(self._conns):
                self._drop(conn)
            self._unlisten()
            for s in (self._wake_r, self._wake_w):
                if s is not None:
                    s.close()
            self._wake_r = self._wake_w = None
            if self._sel is not None:
                self._sel.close()
                self._sel = None

    def _wake(self) -> None:
        w = self._wake_w
        if w is not None:
            try:
                w.send(b"x")
            except OSError:
                pass

    def _in_loop(self, fn: Callable[[], Any], timeout: float = 5.0) -> Any:
        """Run ``fn`` on the controller thread (socket changes) and return its result."""
        if self._thread is None or threading.current_thread() is self._thread:
            with self._lock:
                return fn()
        done, box = threading.Event(), []
        self._actions.put((fn, done, box))
        self._wake()
        if not done.wait(timeout):
            raise TimeoutError("fake UR controller thread did not answer")
        if box and isinstance(box[0], BaseException):
            raise box[0]
        return box[0] if box else None

    # -- the controller thread ---------------------------------------------------------------------

    def _run(self) -> None:
        sel = self._sel
        assert sel is not None
        next_tick = time.monotonic() + self.period
        while not self._stopping:
            timeout = max(0.0, next_tick - time.monotonic())
            try:
                events = sel.select(timeout)
            except (OSError, ValueError):
                events = []
            with self._lock:
                for key, mask in events:
                    self._dispatch(key, mask)
                self._run_actions()
                now = time.monotonic()
                if now >= next_tick:
                    n = int((now - next_tick) / self.period) + 1
                    if n > 1:
                        self._overruns += 1
                    try:
                        self._cycle(n)
                    except Exception:  # a bug here must not kill the controller
                        log.exception("fake UR controller: cycle failed")
                    next_tick += n * self.period

    def _run_actions(self) -> None:
        while True:
            try:
                fn, done, box = self._actions.get_nowait()
            except queue.Empty:
                return
            try:
                box.append(fn())
            except BaseException as exc:  # handed back to the caller
                box.append(exc)
            done.set()

    def _dispatch(self, key: selectors.SelectorKey, mask: int) -> None:
        obj = key.data
        if obj is None:  # the wake-up pipe
            try:
                while key.fileobj.recv(4096):  # type: ignore[union-attr]
                    pass
            except (BlockingIOError, OSError):
                pass
            return
        if isinstance(obj, type):  # a listening socket: obj is the connection class
            try:
                sock, peer = key.fileobj.accept()  # type: ignore[union-attr]
            except (BlockingIOError, OSError):
                return
            sock.setblocking(False)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            conn = obj(self, sock, peer)
            self._conns.add(conn)
            assert self._sel is not None
            self._sel.register(sock, selectors.EVENT_READ, conn)
            self._event("connect", kind=conn.kind, port=sock.getsockname()[1])
            conn.on_accept()
            return
        if mask & selectors.EVENT_WRITE:
            obj.flush()
        if mask & selectors.EVENT_READ and not obj.closed:
            obj.on_readable()

    def _want_write(self, conn: Conn, want: bool) -> None:
        if conn.closed or self._sel is None:
            return
        events = selectors.EVENT_READ | (selectors.EVENT_WRITE if want else 0)
        try:
            if self._sel.get_key(conn.sock).events != events:
                self._sel.modify(conn.sock, events, conn)
        except (KeyError, ValueError):
            pass

    def _drop(self, conn: Conn) -> None:
        if conn.closed:
            return
        conn.closed = True
        self._conns.discard(conn)
        if self._sel is not None:
            try:
                self._sel.unregister(conn.sock)
            except (KeyError, ValueError):
                pass
        try:
            conn.sock.close()
        except OSError:
            pass
        self._event("disconnect", kind=conn.kind)
