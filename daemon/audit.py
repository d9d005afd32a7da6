"""The append-only audit log of operator commands (JSON lines), write-ahead and rotated.

Every POST, every telemetry websocket connect and every refused authentication leaves a
record, including those refused by authentication (401/403), size (413), validation
(400/422) or the audit log itself (503); the requests a lockout refuses (429) are recorded
in aggregate (``daemon/api_gate.py``). A command that runs leaves two records with one
``id``: its **intent**, written and fsynced before the command runs, and its **outcome**
after it::

    {"time": "2025-01-31T09:12:03.481Z", "id": "5f3a9c1e-17", "phase": "intent",
     "who": "alice", "role": "operator", "client": "127.0.0.1:51234", "method": "POST",
     "path": "/procedure/start", "body": "", "status": null, "result": "pending"}
    {"time": "2025-01-31T09:12:03.502Z", "id": "5f3a9c1e-17", "phase": "outcome",
     "who": "alice", ..., "body": "", "status": 200, "result": "ok"}

A record that stands alone (a refusal that ran nothing, the e-stop, which runs before its
record is written, a telemetry connect, a lockout of failed authentications) has
``"phase": "single"``. ``time`` is wall-clock UTC (ISO 8601, milliseconds); ``who``/``role``
are ``null`` when the caller was not authenticated; ``body`` is a bounded summary of the
request body (never the bearer token: tokens travel in a header or in the websocket query,
which is not logged), in the intent only (its outcome has ``""``). docs/api.md has the
whole format.

Durability: the file is opened with ``O_APPEND`` (never truncated or rewritten; a torn last
line from a crash is reported at open and closed with a newline before the next record),
each record is one ``write`` followed by ``fsync``; commands are rare, so the cost is
irrelevant. When a record would take the file past ``max_bytes`` the file is rotated first
(``audit.jsonl`` -> ``audit.jsonl.1`` -> ... -> ``audit.jsonl.<keep>``, the oldest dropped):
see :meth:`AuditLog._rotate` for why no crash during a rotation can lose a record.

Open also reads the tail of the log (:data:`TAIL_SCAN_BYTES`, into the previous file only
when the current one is shorter) for intents without an outcome: commands that may have
taken effect while the daemon stopped before it could write their outcome. They are logged
at WARNING level, counted in :attr:`AuditLog.incomplete` and closed with an outcome whose
``status`` is ``null`` (result ``unknown: ...``), so the next start does not count them again.

Refusal when the log fails: before a command runs the API writes its intent with
:meth:`AuditLog.intent`; that fails while the log is closed, while earlier records are
still waiting to be written, when the disk has less than ``min_free_bytes`` left, or when
the intent itself cannot be written, and the API then answers 503 without running the
command. A record that cannot be written (the disk failed between the intent and the
outcome) is kept in memory, logged at ERROR level (so it reaches the system journal) and
retried by the next :meth:`check`; until it lands every further command is refused. The
e-stop is the one exception: it always runs (see docs/api.md).
"""

from __future__ import annotations

import contextlib
import itertools
import json
import logging
import os
import secrets
import threading
from collections import deque
from collections.abc import Callable, Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

from oralnav.daemon.errors import DaemonError

if TYPE_CHECKING:
    from oralnav.config.daemon import ApiSection

log = logging.getLogger(__name__)

#: longest ``body`` summary kept in a record, characters
BODY_SUMMARY_CHARS = 512
#: records kept in memory while the file cannot be written; older ones are only in the
#: system journal after that (they were logged at ERROR level when they failed)
MAX_PENDING = 1000
#: the file is rotated before a record would take it past this size (bytes): 64 MiB is
#: about 250,000 records, months of commands (``[api] audit_max_bytes``)
DEFAULT_MAX_BYTES = 64 << 20
#: rotated files kept beside the current one (``[api] audit_keep``)
DEFAULT_KEEP = 5
#: smallest ``max_bytes`` accepted: a few records per file at the least
MIN_MAX_BYTES = 4096
#: how much of the log's end open() reads for intents without an outcome (bytes); the
#: commands a crash interrupted are the last few records, so a few MB is plenty
TAIL_SCAN_BYTES = 4 << 20
#: most incomplete intents named one by one in the start-up warning
MAX_NAMED_INCOMPLETE = 20
#: suffix of the empty file a rotation prepares before the current one moves away
NEW_SUFFIX = ".new"

#: the keys every record holds, in this order (docs/api.md); lockout records add a few
RECORD_KEYS = ("time", "id", "phase", "who", "role", "client", "method", "path", "body",
               "status", "result")


class AuditError(DaemonError):
    """The audit log cannot take a record; the message says why.

    ``record_id``: set when :meth:`AuditLog.intent` failed after its line may have
    reached the file (the write or its fsync failed); the refusal's record then carries
    that id as the intent's outcome.
    """

    def __init__(self, message: str, record_id: str | None = None) -> None:
        super().__init__(message)
        self.record_id = record_id


def user_state_dir(environ: Mapping[str, str] | None = None) -> Path:
    """The daemon's state folder outside systemd: ``$XDG_STATE_HOME/oralnav``, else
    ``~/.local/state/oralnav`` (the XDG base-directory rule for state that outlives a run
    but is no user document: logs, history)."""
    env = os.environ if environ is None else environ
    base = env.get("XDG_STATE_HOME", "")
    root = Path(base) if base and Path(base).is_absolute() else Path.home() / ".local/state"
    return root / "oralnav"


def state_dir(environ: Mapping[str, str] | None = None) -> Path:
    """Where the daemon keeps its state: ``$STATE_DIRECTORY`` (systemd's
    ``StateDirectory=``, e.g. /var/lib/oralnav; the first when it lists several) when set,
    else :func:`user_state_dir`."""
    env = os.environ if environ is None else environ
    state = env.get("STATE_DIRECTORY", "").split(":")[0]
    return Path(state) if state else user_state_dir(env)


def resolve_audit_path(ref: str | Path, environ: Mapping[str, str] | None = None) -> Path:
    """Where ``[api] audit_log`` points: absolute as written; a relative path goes under
    :func:`state_dir`. It is state: never next to the config file, nor wherever the daemon
    happened to be started."""
    ref = Path(ref).expanduser()
    return ref if ref.is_absolute() else state_dir(environ) / ref


def ensure_user_state_dir(path: Path, environ: Mapping[str, str] | None = None) -> None:
    """Create :func:`user_state_dir` (mode 0700, with its parents) when ``path`` lies in
    it and it does not exist yet: the default folder is the daemon's to make; any other
    folder (systemd's, or one the configuration names) must exist already."""
    folder = user_state_dir(environ)
    if folder in Path(path).parents and not folder.exists():
        folder.mkdir(mode=0o700, parents=True, exist_ok=True)


def rotated_path(path: str | Path, k: int) -> Path:
    """The ``k``-th rotated file of the audit log at ``path`` (1 is the newest)."""
    path = Path(path)
    return path.with_name(f"{path.name}.{k}")


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
    mode 0600, and checks its tail (a torn last line, intents without an outcome). Writes
    block on ``fsync``; call :meth:`intent`, :meth:`check` and :meth:`record` from a worker
    thread when the event loop must not stall.

    ``max_bytes``: the file is rotated before a record would take it past this size;
    ``keep``: rotated files kept (``path.1`` newest ... ``path.<keep>`` oldest).
    """

    def __init__(self, path: str | Path, *, min_free_bytes: int = 1 << 20,
                 max_bytes: int = DEFAULT_MAX_BYTES, keep: int = DEFAULT_KEEP) -> None:
        if max_bytes < MIN_MAX_BYTES:
            raise ValueError(f"audit log max_bytes must be at least {MIN_MAX_BYTES}, "
                             f"got {max_bytes}")
        if keep < 1:
            raise ValueError(f"audit log keep must be at least 1 rotated file, got {keep}")
        self.path = Path(path)
        self.min_free_bytes = min_free_bytes
        self.max_bytes = int(max_bytes)
        self.keep = int(keep)
        self._fd: int | None = None
        self._lock = threading.Lock()
        self._pending: deque[bytes] = deque(maxlen=MAX_PENDING)
        self._torn = False  # the file ends inside a line (crash or short write)
        self._written = 0  # bytes the last _append wrote
        # ids: a random tag per process run and a counter, so ids never repeat across
        # restarts and still sort within a run
        self._tag = secrets.token_hex(4)
        self._seq = itertools.count(1)
        self._incomplete: tuple[str, ...] = ()
        self.torn_at: int | None = None  # byte offset of the torn line found by open()
        #: called with each record (a dict) once it is written or kept for retry, and
        #: with each intent written (the session recorder, ``daemon/recording.py``); in
        #: the writer's thread, outside the log's lock: an observer must be quick
        self.observers: list[Callable[[dict[str, Any]], None]] = []

    @classmethod
    def from_config(cls, api: ApiSection, environ: dict[str, str] | None = None) -> AuditLog:
        """The log ``[api]`` describes: ``audit_log`` (:func:`resolve_audit_path`),
        ``audit_max_bytes`` and ``audit_keep``; not opened yet."""
        return cls(resolve_audit_path(api.audit_log, environ), max_bytes=api.audit_max_bytes,
                   keep=api.audit_keep)

    # -- lifecycle --------------------------------------------------------------------
    def open(self) -> AuditLog:
        """Open the file for appending (idempotent); raises :class:`AuditError`.

        Finishes a rotation a crash interrupted, reports a torn last line (WARNING, with
        its byte offset) and intents without an outcome (WARNING, :attr:`incomplete`).
        """
        with self._lock:
            if self._fd is not None:
                return self
            try:
                ensure_user_state_dir(self.path)
                self._finish_rotation()
                fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_CLOEXEC,
                             0o600)
            except OSError as exc:
                raise AuditError(f"cannot open audit log {str(self.path)!r}: "
                                 f"{exc.strerror or exc}") from None
            try:
                tails = self._read_tails()
            except OSError as exc:  # pragma: no cover - it was just opened
                os.close(fd)
                raise AuditError(f"cannot read audit log {str(self.path)!r}: "
                                 f"{exc.strerror or exc}") from None
            self._fd = fd
            self._torn, self.torn_at = False, None
            if tails:
                size, data = tails[-1][1], tails[-1][2]
                if data and not data.endswith(b"\n"):
                    self.torn_at = size - (len(data) - (data.rfind(b"\n") + 1))
                    self._torn = True
                    log.warning("audit log %s ends with a torn record (a crash or a failed "
                                "write cut it short): %d byte(s) from byte offset %d are not "
                                "a whole line; they stay as they are and the next record "
                                "starts on a new line", self.path, size - self.torn_at,
                                self.torn_at)
            incomplete = _incomplete_intents(tails)
            self._incomplete = tuple(rec["id"] for _, rec in incomplete)
        if incomplete:
            named = "; ".join(
                f"{rec['id']} {rec.get('method')} {rec.get('path')} by {rec.get('who')} at "
                f"{rec.get('time')} ({where.name})"
                for where, rec in incomplete[:MAX_NAMED_INCOMPLETE])
            more = len(incomplete) - MAX_NAMED_INCOMPLETE
            log.warning("audit log %s: %d command(s) have an intent but no outcome: the daemon "
                        "stopped while they ran, so each may or may not have taken effect: "
                        "%s%s", self.path, len(incomplete), named,
                        f"; and {more} more" if more > 0 else "")
            for _, rec in incomplete:
                # close each with an outcome of unknown status, so that the next start
                # does not count it again (appended: the intent itself stays as it is)
                with contextlib.suppress(AuditError):  # kept pending and journaled
                    self.record(who=rec.get("who"), role=rec.get("role"),
                                method=str(rec.get("method")), path=str(rec.get("path")),
                                client=rec.get("client"), status=None,
                                result="unknown: the daemon stopped before the outcome was "
                                       "written (found at start-up)",
                                outcome_of=str(rec["id"]))
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

    @property
    def incomplete(self) -> int:
        """Intents without an outcome that the last :meth:`open` found (commands that may
        or may not have taken effect before the daemon stopped)."""
        return len(self._incomplete)

    @property
    def incomplete_ids(self) -> tuple[str, ...]:
        """The ids of those intents, oldest first."""
        return self._incomplete

    # -- records ----------------------------------------------------------------------
    def check(self) -> None:
        """Raise :class:`AuditError` unless the next record can be expected to land: the
        file is open, earlier failed records are written now, and the disk has room."""
        with self._lock:
            self._check_locked()

    def intent(self, *, who: str | None, role: str | None, method: str, path: str,
               body: bytes | str | None = None, client: str | None = None) -> str:
        """Write and fsync the intent of a command about to run; returns its id, which
        its outcome (:meth:`record` with ``outcome_of``) carries.

        Raises :class:`AuditError` when the command must not run: the :meth:`check` fails
        (nothing was written), or the intent could not be written (``record_id`` is then
        set: part of it may be in the file). A failed intent is never retried: the
        command it announced does not run.
        """
        rid = self._new_id()
        line = _line(rid, "intent", who, role, client, method, path, summarize_body(body),
                     None, "pending", None)
        with self._lock:
            self._check_locked()
            self._written = 0
            try:
                self._append(line)
            except OSError as exc:
                reason = exc.strerror or str(exc)
                log.error("audit intent %s not written (%s); the command is refused: %s",
                          rid, reason, line.decode().rstrip())
                # bytes of it in the file (a short write, or a failed fsync): its refusal
                # completes it, so that no start-up counts it as a command that may have run
                raise AuditError(f"audit log {str(self.path)!r} cannot be written: "
                                 f"{reason}", record_id=rid if self._written else None
                                 ) from None
        self._notify(line)
        return rid

    def record(self, *, who: str | None, role: str | None, method: str, path: str,
               status: int | None, result: str, body: bytes | str | None = None,
               client: str | None = None, outcome_of: str | None = None,
               extra: Mapping[str, Any] | None = None) -> dict[str, Any]:
        """Append one record and fsync it; returns the record.

        ``outcome_of``: the id of the intent this record completes (``phase`` is then
        ``outcome``, else ``single``). ``extra``: further keys (lockout records); they may
        not replace the standard ones. Raises :class:`AuditError` when it cannot be
        written; the record is then kept for a retry by :meth:`check` and logged at ERROR
        level so that it is not lost.
        """
        if extra and not set(extra).isdisjoint(RECORD_KEYS):
            raise ValueError(f"extra audit keys may not replace standard ones: "
                             f"{sorted(set(extra) & set(RECORD_KEYS))}")
        rid, phase = (outcome_of, "outcome") if outcome_of else (self._new_id(), "single")
        line = _line(rid, phase, who, role, client, method, path, summarize_body(body),
                     None if status is None else int(status), str(result), extra)
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
                failed = AuditError(f"audit log {str(self.path)!r} cannot be written: "
                                    f"{reason}")
            else:
                failed = None
        self._notify(line)
        if failed is not None:
            raise failed
        return json.loads(line)

    def _notify(self, line: bytes) -> None:
        """Hand the record to the observers; one that fails is logged, never raised."""
        if not self.observers:
            return
        rec = json.loads(line)
        for observer in list(self.observers):
            try:
                observer(dict(rec))
            except Exception:
                log.exception("audit observer %r failed", observer)

    # -- internals (the caller holds the lock) -----------------------------------------
    def _new_id(self) -> str:
        return f"{self._tag}-{next(self._seq)}"

    def _check_locked(self) -> None:
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

    def _append(self, line: bytes) -> None:
        # one write per record so concurrent writers (even other processes, thanks to
        # O_APPEND) never interleave inside a line
        assert self._fd is not None
        size = os.fstat(self._fd).st_size
        if size and size + len(line) + self._torn > self.max_bytes:
            self._rotate()
        data = (b"\n" + line) if self._torn else line
        written = 0
        try:
            while written < len(data):
                written += os.write(self._fd, data[written:])
                self._written = written
        finally:
            if written:  # a short write leaves the file inside a line: close it next time
                self._torn = not data[:written].endswith(b"\n")
        # a failed fsync retries the record: a duplicate line beats a lost one
        os.fsync(self._fd)

    def _rotate(self) -> None:
        """Move the current file to ``.1`` (older ones one up) and continue in a new one.

        Why no crash loses a record: every record is fsynced before it is acknowledged;
        the old file is fsynced again here and only ever renamed, never copied; the new
        file is created empty under a temporary name and made durable (file and folder
        fsynced) *before* the old one leaves its name, so at every instant each record is
        in exactly one file under a name :meth:`open` knows. A crash after the old file
        became ``.1`` but before the new one took the name leaves ``path`` missing and
        ``path.new`` empty: :meth:`open` finishes the rotation (:meth:`_finish_rotation`).
        Records keep their order: ``.<keep>`` oldest ... ``.1``, then ``path``. A failure
        (an ``OSError``) puts the old file back, and the record that asked for the
        rotation fails like any write (kept and retried).
        """
        assert self._fd is not None
        folder = self.path.parent
        os.fsync(self._fd)
        # 1. make room: .<keep-1> -> .<keep> (the oldest is dropped), ..., .1 -> .2
        for k in range(self.keep - 1, 0, -1):
            src = rotated_path(self.path, k)
            if src.exists():
                os.replace(src, rotated_path(self.path, k + 1))
        # 2. the new file, empty and durable, before the old one moves
        new = self.path.with_name(self.path.name + NEW_SUFFIX)
        nfd = os.open(new, os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_TRUNC | os.O_CLOEXEC,
                      0o600)
        first = rotated_path(self.path, 1)
        moved = False
        try:
            os.fsync(nfd)
            _fsync_dir(folder)
            # 3. the old file becomes .1, the new one takes its name, and the folder says so
            os.replace(self.path, first)
            moved = True
            os.replace(new, self.path)
            moved = False
            _fsync_dir(folder)
        except OSError:
            os.close(nfd)
            with contextlib.suppress(OSError):
                if moved:  # put the old file back: records keep going to it
                    os.replace(first, self.path)
                new.unlink(missing_ok=True)
            raise
        old, self._fd = self._fd, nfd
        os.close(old)
        self._torn = False
        log.info("audit log %s rotated: the previous records are in %s", self.path, first)

    def _finish_rotation(self) -> None:
        """Tidy up after a rotation a crash interrupted (see :meth:`_rotate`): the empty
        ``path.new`` takes ``path``'s name when ``path`` is missing, else it is removed.
        A ``path.new`` that is not empty is not ours to remove: it is left, with a
        warning."""
        new = self.path.with_name(self.path.name + NEW_SUFFIX)
        try:
            size = new.stat().st_size
        except FileNotFoundError:
            return
        if size:
            log.warning("audit log %s: %s is not empty (%d bytes); not an interrupted "
                        "rotation of ours, left as it is", self.path, new, size)
            return
        if self.path.exists():
            new.unlink()
        else:
            os.replace(new, self.path)
            log.warning("audit log %s: finished a rotation a crash interrupted (the "
                        "previous records are in %s)", self.path, rotated_path(self.path, 1))
        _fsync_dir(self.path.parent)

    def _read_tails(self) -> list[tuple[Path, int, bytes]]:
        """The last :data:`TAIL_SCAN_BYTES` of the log as ``(file, its size, bytes)``,
        oldest file first: the current file's end, and the previous file's end only when
        the current file is shorter than the budget."""
        out: list[tuple[Path, int, bytes]] = []
        budget = TAIL_SCAN_BYTES
        for where in (self.path, rotated_path(self.path, 1)):
            try:
                with open(where, "rb") as f:
                    size = os.fstat(f.fileno()).st_size
                    start = max(0, size - budget)
                    f.seek(start)
                    data = f.read(size - start)
            except FileNotFoundError:
                break
            if start:  # began inside a line: drop the part before the first newline
                data = data[data.find(b"\n") + 1:] if b"\n" in data else b""
            out.insert(0, (where, size, data))
            budget -= size - start
            if budget <= 0:
                break
        return out


def _line(rid: str, phase: str, who: str | None, role: str | None, client: str | None,
          method: str, path: str, body: str, status: int | None, result: str,
          extra: Mapping[str, Any] | None) -> bytes:
    rec = {"time": utc_now_iso(), "id": rid, "phase": phase, "who": who, "role": role,
           "client": client, "method": method, "path": path, "body": body,
           "status": status, "result": result, **(extra or {})}
    text = json.dumps(rec, ensure_ascii=False, separators=(",", ":"))
    # json escapes the ASCII control characters but not these, which many readers
    # (Python's str.splitlines among them) take for line ends: one record, one line
    return (text.translate(_LINE_BREAKS) + "\n").encode()


#: the non-ASCII characters str.splitlines ends a line at, as JSON escapes
_LINE_BREAKS = {0x85: "\\u0085", 0x2028: "\\u2028", 0x2029: "\\u2029"}


def _incomplete_intents(tails: list[tuple[Path, int, bytes]]) -> list[tuple[Path, dict]]:
    """The intents in ``tails`` (oldest first) that no later outcome completes, with the
    file each is in. Lines that do not parse (a torn record) are skipped."""
    intents: dict[str, tuple[Path, dict]] = {}
    for where, _, data in tails:
        for raw in data.splitlines():
            # most lines stand alone: skip them without parsing
            if b'"phase":"intent"' not in raw and b'"phase":"outcome"' not in raw:
                continue
            try:
                rec = json.loads(raw)
            except ValueError:
                continue
            if not isinstance(rec, dict) or not isinstance(rec.get("id"), str):
                continue
            if rec.get("phase") == "intent":
                intents[rec["id"]] = (where, rec)
            elif rec.get("phase") == "outcome":
                intents.pop(rec["id"], None)
    return list(intents.values())


def _fsync_dir(folder: Path) -> None:
    """Make the folder's entries (a created or renamed file) durable."""
    fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
