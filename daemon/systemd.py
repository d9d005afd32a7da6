"""systemd integration: readiness, status and watchdog notifications (sd_notify).

The daemon runs as ``Type=notify`` (``config/oralnavd.service``, docs/systemd.md). This
module speaks systemd's notification protocol itself, without libsystemd or a PyPI
package: each notification is one datagram of ``KEY=VALUE`` lines sent to the
``AF_UNIX`` datagram socket named by ``$NOTIFY_SOCKET`` (a path, or a name in the abstract
namespace when it starts with ``@``).

- :class:`Notifier` sends ``READY=1``, ``WATCHDOG=1``, ``STOPPING=1``, ``STATUS=...``,
  ``RELOADING=1`` and ``EXTEND_TIMEOUT_USEC=...``. Outside systemd it does nothing and
  says so (``enabled`` is False). It never raises into its caller and never blocks: the
  daemon must not crash or stall because systemd or journald hiccuped, so a failed send
  is logged once and then ignored.
- :func:`watchdog_interval` reads ``$WATCHDOG_USEC`` / ``$WATCHDOG_PID``.
- :func:`watchdog_task` pings ``WATCHDOG=1`` at half that interval, but only while the
  daemon reports itself healthy, so that a wedged daemon (event loop stuck, control
  process dead) stops pinging and systemd restarts it.

Standard library and anyio only: this must keep working when everything else is broken.
"""

from __future__ import annotations

import logging
import os
import socket
import threading
import time
from collections.abc import Callable, Mapping

import anyio
from anyio.abc import TaskStatus

__all__ = ["Notifier", "watchdog_interval", "watchdog_task"]

log = logging.getLogger(__name__)

#: Longest STATUS= text sent (characters); systemctl shows one line, keep datagrams small.
STATUS_MAX_CHARS = 512


def _socket_address(value: str) -> str | None:
    """The ``AF_UNIX`` address for ``$NOTIFY_SOCKET``, or None when systemd gave none we
    can use. ``@name`` is the abstract namespace (a leading NUL byte for the kernel)."""
    if value.startswith("@") and len(value) > 1:
        return "\0" + value[1:]
    if value.startswith("/"):
        return value
    # e.g. systemd >= 254's "vsock:CID:PORT" (VMs); not used on the robot PC
    return None


def _one_line(text: str) -> str:
    """A value must not break the ``KEY=VALUE`` line protocol: no newlines, bounded."""
    flat = " ".join(str(text).splitlines()).strip()
    return flat[:STATUS_MAX_CHARS]


class Notifier:
    """Sends sd_notify messages to ``$NOTIFY_SOCKET``; a no-op outside systemd.

    ``environ`` defaults to ``os.environ``, read once here (no I/O: the socket is created
    at the first send). Every method returns True when the datagram was handed to the
    kernel and False otherwise (disabled, or the send failed); none raises. Thread-safe.
    """

    def __init__(self, environ: Mapping[str, str] | None = None) -> None:
        env = os.environ if environ is None else environ
        raw = env.get("NOTIFY_SOCKET", "")
        self._socket_name = raw
        self._address = _socket_address(raw) if raw else None
        self._sock: socket.socket | None = None
        self._lock = threading.Lock()
        self._failures = 0
        self._closed = False
        if raw and self._address is None:
            log.warning("NOTIFY_SOCKET=%r is not a socket path or @abstract name; "
                        "systemd notifications are off", raw)

    @property
    def enabled(self) -> bool:
        """True when systemd asked for notifications (``$NOTIFY_SOCKET`` is usable)."""
        return self._address is not None and not self._closed

    @property
    def socket_name(self) -> str:
        """``$NOTIFY_SOCKET`` as systemd gave it ('' when not run by systemd)."""
        return self._socket_name

    @property
    def failures(self) -> int:
        """How many sends have failed so far (only the first was logged as a warning)."""
        return self._failures

    # -- the notifications -------------------------------------------------------------

    def ready(self, status: str | None = None) -> bool:
        """``READY=1``: start-up is complete (drivers up, API listening); systemd's
        ``systemctl start`` returns and units ordered after this one start now."""
        return self.notify(READY="1", STATUS=status)

    def watchdog(self) -> bool:
        """``WATCHDOG=1``: the daemon is alive and healthy; send at least every
        ``WatchdogSec / 2`` (see :func:`watchdog_task`)."""
        return self.notify(WATCHDOG="1")

    def stopping(self, status: str | None = None) -> bool:
        """``STOPPING=1``: orderly shutdown has begun (the arm has been told to stop)."""
        return self.notify(STOPPING="1", STATUS=status)

    def status(self, text: str) -> bool:
        """``STATUS=text``: one line shown by ``systemctl status``."""
        return self.notify(STATUS=text)

    def reloading(self, status: str | None = None) -> bool:
        """``RELOADING=1`` with ``MONOTONIC_USEC`` (systemd >= 253 wants the time to order
        the reload against the ``READY=1`` that must follow it)."""
        usec = time.clock_gettime_ns(time.CLOCK_MONOTONIC) // 1000
        return self.notify(RELOADING="1", MONOTONIC_USEC=str(usec), STATUS=status)

    def extend_timeout(self, seconds: float) -> bool:
        """``EXTEND_TIMEOUT_USEC``: ask for ``seconds`` more to finish starting or
        stopping (e.g. a slow camera bring-up) than ``TimeoutStartSec``/``StopSec``."""
        usec = max(0, int(seconds * 1e6))
        return self.notify(EXTEND_TIMEOUT_USEC=str(usec))

    def notify(self, **fields: str | None) -> bool:
        """Send ``KEY=VALUE`` lines (None values are left out) as one datagram."""
        if not self.enabled:
            return False
        lines = [f"{key}={_one_line(value)}" for key, value in fields.items()
                 if value is not None]
        if not lines:
            return False
        return self._send("\n".join(lines).encode("utf-8", "replace"))

    # -- plumbing ----------------------------------------------------------------------

    def _send(self, payload: bytes) -> bool:
        with self._lock:
            try:
                if self._sock is None:
                    self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
                # unconnected sendto: the path is looked up per message, so systemd
                # re-creating its socket (daemon-reexec) needs nothing from us.
                # MSG_DONTWAIT: a full receive queue drops one ping instead of stalling
                # the event loop (which would itself starve the watchdog).
                self._sock.sendto(payload, socket.MSG_DONTWAIT, self._address)
                return True
            except Exception as exc:  # any failure at all: log once, never raise
                self._failures += 1
                if self._failures == 1:
                    log.warning("systemd notification to %s failed (%s: %s); further "
                                "failures are not logged", self._socket_name,
                                type(exc).__name__, exc)
                else:
                    log.debug("systemd notification failed again: %s", exc)
                self._drop_socket()
                return False

    def _drop_socket(self) -> None:
        sock, self._sock = self._sock, None
        if sock is not None:
            try:
                sock.close()
            except OSError:
                pass

    def close(self) -> None:
        """Close the socket; later notifications are no-ops. Idempotent."""
        with self._lock:
            self._closed = True
            self._drop_socket()

    def __enter__(self) -> Notifier:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        where = self._socket_name if self.enabled else "disabled"
        return f"Notifier({where})"


def watchdog_interval(environ: Mapping[str, str] | None = None,
                      pid: int | None = None) -> float | None:
    """systemd's watchdog timeout in seconds (``WatchdogSec=``), or None when it asks for
    no watchdog pings from this process.

    ``$WATCHDOG_USEC`` holds the timeout in microseconds. ``$WATCHDOG_PID``, when set,
    names the one process that must ping; the control process inherits the daemon's
    environment, so it must not take the request as its own. Ping at half the interval
    (as sd_watchdog_enabled(3) recommends); :func:`watchdog_task` does.
    """
    env = os.environ if environ is None else environ
    raw = env.get("WATCHDOG_USEC")
    if not raw:
        return None
    try:
        usec = int(raw)
    except ValueError:
        log.warning("WATCHDOG_USEC=%r is not an integer; watchdog off", raw)
        return None
    if usec <= 0:
        return None
    owner = env.get("WATCHDOG_PID")
    if owner:
        try:
            if int(owner) != (os.getpid() if pid is None else pid):
                return None
        except ValueError:
            log.warning("WATCHDOG_PID=%r is not an integer; watchdog off", owner)
            return None
    return usec / 1e6


def ask_health(healthy: Callable[[], bool | tuple[bool, str | None]]) -> tuple[bool, str | None]:
    """``healthy()``, which may give ``(ok, why)``; an exception counts as unhealthy (and
    is the reason)."""
    try:
        answer = healthy()
    except Exception as exc:
        return False, f"health check raised {type(exc).__name__}: {exc}"
    if isinstance(answer, tuple):
        ok, why = answer
        return bool(ok), (None if ok else why)
    return bool(answer), None


async def watchdog_task(notifier: Notifier,
                        healthy: Callable[[], bool | tuple[bool, str | None]], *,
                        interval: float | None = None,
                        task_status: TaskStatus[float | None] = anyio.TASK_STATUS_IGNORED
                        ) -> None:
    """Ping ``WATCHDOG=1`` every half watchdog interval while ``healthy()`` is True.

    Start it in the daemon's task group: ``period = await tg.start(watchdog_task, n, h)``
    gives the ping period in seconds, or None when systemd asked for no watchdog (or the
    notifier is disabled), in which case the task has already returned. ``interval``
    overrides ``$WATCHDOG_USEC`` (seconds; pass it with ``functools.partial``, since
    ``tg.start`` takes positional arguments only).

    ``healthy`` must be quick and must not block (it runs on the event loop): e.g. "the
    control process is alive and its status record is fresh". While it returns False (or
    raises) no ping is sent, so systemd declares the daemon hung after ``WatchdogSec`` and
    restarts it (``Restart=on-failure``); a stuck event loop sends none either. Pings
    resume if health comes back in time. Runs until cancelled.
    """
    if interval is None:
        interval = watchdog_interval()
    if interval is None or interval <= 0 or not notifier.enabled:
        task_status.started(None)
        return
    period = interval / 2
    task_status.started(period)
    was_healthy = True
    next_at = anyio.current_time()
    while True:
        ok, why = ask_health(healthy)
        if ok:
            notifier.watchdog()
            if not was_healthy:
                log.warning("daemon healthy again: watchdog pings resumed")
        elif was_healthy:
            log.error("daemon unhealthy%s: withholding watchdog pings, systemd will "
                      "restart it within %.3g s unless health returns",
                      f" ({why})" if why else "", interval)
        was_healthy = ok
        next_at += period
        now = anyio.current_time()
        if next_at < now:  # the loop was stalled: ping on a fresh grid, do not burst
            next_at = now + period
        await anyio.sleep_until(next_at)
