"""The append-only audit log of operator commands (JSON lines).

One line per command (every POST, every telemetry websocket connect), including those
refused by authentication (401/403), validation (400/422) or state (409)::

    {"time": "2025-01-31T09:12:03.481Z", "who": "alice", "role": "operator",
     "client": "127.0.0.1:51234", "method": "POST", "path": "/procedure/start",
     "body": "", "status": 200, "result": "ok"}

``time`` is wall-clock UTC (ISO 8601, milliseconds); ``who``/``role`` are ``null`` when the
caller was not authenticated; ``body`` is a bounded summary of the request body (never the
bearer token: tokens travel in a header or in the websocket query, which is not logged).

Durability: the file is opened with ``O_APPEND`` (never truncated or rewritten, a torn last
line from a crash is closed with a newline before the next record), each record is one
``write`` followed by ``fsync``; commands are rare, so the cost is irrelevant.

Refusal when the log fails: before a command runs the API calls :meth:`AuditLog.check`;
it fails while the log is closed, while earlier records are still waiting to be written,
or when the disk has less than ``min_free_bytes`` left, and the API then answers 503
without running the command. A record that cannot be written (the disk failed between the
check and the write) is kept in memory, logged at ERROR level (so it reaches the system
journal) and retried by the next :meth:`check`; until it lands every further command is
refused. The e-stop is the one exception: it always runs (see docs/api.md).
"""

from __future__ import annotations

import json
import logging
import os
import threading
from collections import deque
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

#: longest ``body`` summary kept in a record, characters
BODY_SUMMARY_CHARS = 512
#: records kept in memory while the file cannot be written; older ones are only in the
#: system journal after that (they were logged at ERROR level when they failed)
MAX_PENDING = 1000


class AuditError(Exception):
    """The audit log cannot take a record; the message says why."""


def resolve_audit_path(ref: str | Path, environ: dict[str, str] | None = None) -> Path:
    """Where ``[api] audit_log`` points: absolute as written; a relative path goes under
    ``$STATE_DIRECTORY`` (systemd's ``StateDirectory=``, e.g. /var/lib/oralnav) when set,
    else under the working directory. It is state, so never next to the config file."""
    env = os.environ if environ is None else environ
    ref = Path(ref).expanduser()
    if ref.is_absolute():
        return ref
    # systemd may list several folders separated by ':'; the first is ours
    state = env.get("STATE_DIRECTORY", "").split(":")[0]
    return (Path(state) if state else Path.cwd()) / ref


def summarize_body(body: bytes | str | None, limit: int = BODY_SUMMARY_CHARS) -> str:
    """A one-line summary of a request body of at most about ``limit`` characters: compact
    JSON when it parses, else the text with undecodable bytes replaced."""
    if not body:
        return ""
    text = body.decode("utf-8", "replace") if isinstance(body, bytes) else body
    try:
        text = json.dumps(json.loads(text), separators=(",", ":"), ensure_ascii=False)
    except (ValueError, RecursionError):  # not JSON, or nested past the parser's depth
        text = " ".join(text.split())  # keep it on one line
    if len(text) > limit:
        text = f"{text[:limit]}...(+{len(text) - limit} chars)"
    return text


def utc_now_iso() -> str:
    """The wall-clock time as ISO 8601 UTC with milliseconds (``...T09:12:03.481Z``)."""
    return datetime.now(UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


class AuditLog:
    """Append-only JSON-lines audit log; thread-safe (records are written under a lock).

    The constructor does no I/O: :meth:`open` (or ``with``) opens the file, creating it with
    mode 0600. Writes block on ``fsync``; call :meth:`check` and :meth:`record` from a
    worker thread when the event loop must not stall.
    """

    def __init__(self, path: str | Path, *, min_free_bytes: int = 1 << 20) -> None:
        self.path = Path(path)
        self.min_free_bytes = min_free_bytes
        self._fd: int | None = None
        self._lock = threading.Lock()
        self._pending: deque[bytes] = deque(maxlen=MAX_PENDING)
        self._torn = False  # the file ends inside a line (crash or short write)

    # -- lifecycle --------------------------------------------------------------------
    def open(self) -> AuditLog:
        """Open the file for appending (idempotent); raises :class:`AuditError`."""
        with self._lock:
            if self._fd is not None:
                return self
            try:
                fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_CLOEXEC,
                             0o600)
            except OSError as exc:
                raise AuditError(f"cannot open audit log {str(self.path)!r}: "
                                 f"{exc.strerror or exc}") from None
            self._torn = _ends_inside_line(self.path)
            self._fd = fd
        return self

    def close(self) -> None:
        """Close the file (idempotent); pending records stay pending."""
        with self._lock:
            fd, self._fd = self._fd, None
            if fd is not None:
                os.close(fd)

    def __enter__(self) -> AuditLog:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def is_open(self) -> bool:
        return self._fd is not None

    @property
    def pending(self) -> int:
        """Records that failed to write and wait for the next :meth:`check`."""
        return len(self._pending)

    # -- records ----------------------------------------------------------------------
    def check(self) -> None:
        """Raise :class:`AuditError` unless the next record can be expected to land: the
        file is open, earlier failed records are written now, and the disk has room."""
        with self._lock:
            if self._fd is None:
                raise AuditError(f"audit log {str(self.path)!r} is not open")
            while self._pending:
                try:
                    self._append(self._pending[0])
                except OSError as exc:
                    raise AuditError(f"audit log {str(self.path)!r} cannot be written "
                                     f"({exc.strerror or exc}); {len(self._pending)} "
                                     "record(s) waiting") from None
                self._pending.popleft()
            try:
                st = os.fstatvfs(self._fd)
            except OSError:  # pragma: no cover - some file systems cannot say
                return
            free = st.f_bavail * st.f_frsize
            if free < self.min_free_bytes:
                raise AuditError(f"audit log {str(self.path)!r}: only {free} bytes free on "
                                 f"its disk (at least {self.min_free_bytes} needed)")

    def record(self, *, who: str | None, role: str | None, method: str, path: str,
               status: int, result: str, body: bytes | str | None = None,
               client: str | None = None) -> dict[str, Any]:
        """Append one record and fsync it; returns the record.

        Raises :class:`AuditError` when it cannot be written; the record is then kept for
        a retry by :meth:`check` and logged at ERROR level so that it is not lost.
        """
        rec = {"time": utc_now_iso(), "who": who, "role": role, "client": client,
               "method": method, "path": path, "body": summarize_body(body),
               "status": int(status), "result": str(result)}
        line = (json.dumps(rec, ensure_ascii=False, separators=(",", ":")) + "\n").encode()
        with self._lock:
            try:
                if self._fd is None:
                    raise OSError(f"audit log {str(self.path)!r} is not open")
                if self._pending:  # keep the file in order: older records first
                    raise OSError(f"{len(self._pending)} earlier record(s) still waiting")
                self._append(line)
            except OSError as exc:
                self._pending.append(line)
                reason = exc.strerror or str(exc)
                log.error("audit record not written (%s), kept for retry: %s",
                          reason, line.decode().rstrip())
                raise AuditError(f"audit log {str(self.path)!r} cannot be written: "
                                 f"{reason}") from None
        return rec

    def _append(self, line: bytes) -> None:
        # caller holds the lock; one write per record so concurrent writers (even other
        # processes, thanks to O_APPEND) never interleave inside a line
        assert self._fd is not None
        data = (b"\n" + line) if self._torn else line
        written = 0
        try:
            while written < len(data):
                written += os.write(self._fd, data[written:])
        finally:
            if written:  # a short write leaves the file inside a line: close it next time
                self._torn = not data[:written].endswith(b"\n")
        # a failed fsync retries the record: a duplicate line beats a lost one
        os.fsync(self._fd)


def _ends_inside_line(path: Path) -> bool:
    """True when ``path`` is non-empty and does not end with a newline (a torn record)."""
    try:
        with open(path, "rb") as f:
            f.seek(0, os.SEEK_END)
            if f.tell() == 0:
                return False
            f.seek(-1, os.SEEK_END)
            return f.read(1) != b"\n"
    except OSError:
        return False
