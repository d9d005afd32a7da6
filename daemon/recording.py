"""The session recorder: what the daemon saw and did, written to one MCAP file per
recording, so that a session can be looked at in Foxglove and its tracking re-run
(``oralnav replay``). docs/recording.md lists the channels.

Where each thing comes from:

- :meth:`SessionRecorder.tap`, a tap of the capture pipeline (``daemon/capture_task.py``):
  every tracked round's poses (a ``foxglove.FrameTransform`` per published pose and one
  ``/oralnav/rounds`` record with each estimate bit-exact) and, every ``every``-th round,
  its frames;
- :meth:`SessionRecorder.poll`, 10 times a second on the event loop
  (:meth:`SessionRecorder.run`): the safety transitions (``SafetySupervisor.history``) and
  the arm's TCP as the control loop measured it (its 4 s history ring, every sample);
- :meth:`SessionRecorder.on_audit`, an observer of the audit log (``daemon/audit.py``):
  every audit record, and each operator command once its outcome is known.

None of these writes: they append to two queues that one writer thread empties. Frames go
to a bounded queue (``queue_rounds`` rounds): when the writer is behind (a slow disk) a new
round's frames are dropped, counted and reported (``GET /recording``, the log every
``DROP_LOG_S``, the ``/oralnav/recorder`` channel, the file's final summary). Everything
else (poses, rounds, TCP, safety, commands, audit) goes to an unbounded queue the writer
always empties first: it is small (a few kB a second) and is never dropped; its length
and high-water mark are in the status. So tracking, the event loop and the control
process (another process) never wait on the disk.

A write that fails (a full disk: ENOSPC, a read-only one: EROFS, EACCES) ends the
recording: the state becomes ``failed`` with the error naming the file, the error is
logged, what reached the disk stays readable (``oralnav replay`` reads a cut file up to its
last whole chunk), and the daemon and the robot go on. The file is written in place, not
through a temporary name: a recording cut by a crash keeps everything up to its last
chunk.
"""

from __future__ import annotations

import errno as errno_mod
import logging
import math
import os
import socket
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import anyio
import anyio.abc
import numpy as np

from oralnav import __version__
from oralnav.daemon import recording_format as fmt
from oralnav.daemon.audit import resolve_audit_path
from oralnav.daemon.errors import DaemonError
from oralnav.safety.errors import StateError

__all__ = ["RecordingError", "RecordingOptions", "SessionRecorder"]

log = logging.getLogger(__name__)

#: How often (s) the recorder looks at the safety state and the arm's history.
POLL_S = 0.1
#: Seconds between two log messages about dropped frames.
DROP_LOG_S = 5.0
#: Records waiting past this many are logged as a disk falling far behind (never dropped).
RECORDS_WARN = 20_000
#: How long (s) a stop waits for the writer to write what is queued and close the file.
STOP_WAIT_S = 30.0
#: MCAP chunk size (bytes): images of a few MB make chunks of one image each.
CHUNK_BYTES = 1 << 20
#: Command intents kept while their outcome is awaited (commands are rare; a few hang).
MAX_INTENTS = 256


class RecordingError(DaemonError, ValueError):
    """A recording that cannot start: bad options, or a file that cannot be created (the
    message names the file and the error; the API answers 422)."""


@dataclass(frozen=True)
class RecordingOptions:
    """How to record (docs/recording.md): ``path`` (``.mcap``; a relative path goes where
    a relative audit log goes, :func:`~oralnav.daemon.audit.resolve_audit_path`), the frames of
    every ``every``-th round, encoded as ``images`` (``raw``, ``png``, ``jpeg`` with
    ``jpeg_quality``, or ``none``), chunks compressed with ``compression``, at most
    ``queue_rounds`` rounds of frames waiting for the disk, and whether an existing file
    may be replaced (``overwrite``: ``oralnavd --record`` may, the API may not)."""

    path: Path
    every: int = 1
    images: str = "raw"
    compression: str = "none"
    jpeg_quality: int = 90
    queue_rounds: int = 8
    overwrite: bool = False

    def __post_init__(self) -> None:
        path = resolve_audit_path(self.path)
        if path.suffix.lower() != ".mcap":
            raise RecordingError(f"recording {str(path)!r}: the file must end in .mcap")
        object.__setattr__(self, "path", path)
        if isinstance(self.every, bool) or not isinstance(self.every, int) or \
                not 1 <= self.every <= 10_000:
            raise RecordingError(f"every must be a whole number of rounds 1..10000, got "
                                 f"{self.every!r}")
        if self.images not in fmt.IMAGE_ENCODINGS:
            raise RecordingError(f"images must be one of {', '.join(fmt.IMAGE_ENCODINGS)}, "
                                 f"got {self.images!r}")
        if self.compression not in fmt.COMPRESSIONS:
            raise RecordingError(f"compression must be one of {', '.join(fmt.COMPRESSIONS)}"
                                 f", got {self.compression!r}")
        if not 1 <= int(self.jpeg_quality) <= 100:
            raise RecordingError(f"jpeg_quality must be 1..100, got {self.jpeg_quality!r}")
        if not 1 <= int(self.queue_rounds) <= 1024:
            raise RecordingError(f"queue_rounds must be 1..1024, got {self.queue_rounds!r}")

    def as_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["path"] = str(self.path)
        return d


def _utc_iso(ns: int | None = None) -> str:
    t = datetime.fromtimestamp((time.time_ns() if ns is None else ns) / 1e9, UTC)
    return t.isoformat(timespec="milliseconds").replace("+00:00", "Z")


def _os_error(path: Path, exc: BaseException) -> str:
    """``exc`` as a sentence naming the file and the errno (``... (ENOSPC)``)."""
    if isinstance(exc, OSError) and exc.errno is not None:
        name = errno_mod.errorcode.get(exc.errno, str(exc.errno))
        return f"{path}: {exc.strerror or exc} ({name})"
    return f"{path}: {type(exc).__name__}: {exc}"


class _Session:
    """One recording: its options, its file and writer thread, its queues and counts.
    Every attribute the tap, the poll and the status read is guarded by ``lock``."""

    def __init__(self, options: RecordingOptions, who: str, lock: threading.Condition,
                 begin: Callable[[Any], None]) -> None:
        self.options = options
        self.who = who
        self.cond = lock
        self.begin = begin                  # writes the header, metadata, attachments
        self.state = "recording"
        self.error: str | None = None
        self.records: deque[tuple] = deque()
        self.frames: deque[tuple[str, int, Mapping[str, Any]]] = deque()
        self.stop_requested = False
        self.stopped_by: str | None = None
        self.started_utc = _utc_iso()
        self.t0 = time.monotonic()
        self.t_end: float | None = None
        self.rounds = 0                     # tracked rounds seen while recording
        self.seen: dict[str, int] = {}      # source -> rounds seen while recording
        self.frames_queued = 0              # camera frames accepted into the queue
        self.frames_written = 0
        self.frames_dropped = 0             # writer behind: the queue was full
        self.frames_decimated = 0           # left out by ``every``
        self.rounds_dropped = 0
        self.records_written = 0
        self.records_max = 0                # high-water mark of the records queue
        self.bytes = 0
        self.write_busy_s = 0.0             # writer time spent encoding and writing
        self.size: int | None = None        # the file's size once closed
        self.thread: threading.Thread | None = None

    def push(self, item: tuple) -> None:
        """A record for the writer; the caller holds the lock."""
        self.records.append(item)
        n = len(self.records)
        if n > self.records_max:
            self.records_max = n
            if n == RECORDS_WARN:
                log.warning("recording %s: %d records waiting for the disk (none is "
                            "dropped)", self.options.path, n)
        self.cond.notify()

    @property
    def active(self) -> bool:
        return self.state == "recording" and not self.stop_requested


class SessionRecorder:
    """See the module docstring. ``core``: the daemon core (its clock, supervisor and
    control port); ``sources``: the capture pipeline's sources, whose views the file
    describes; ``config_path``: the configuration file to attach (None: none)."""

    def __init__(self, core: Any, sources: Sequence[Any], *,
                 config_path: str | os.PathLike[str] | None = None) -> None:
        self.core = core
        self.sources = list(sources)
        self.config_path = None if config_path is None else Path(config_path)
        self._cond = threading.Condition()
        self._session: _Session | None = None
        self._last: _Session | None = None  # the latest session, for the status
        # which view of which source each View is (the rounds name views by index)
        self._views = {id(v): (s.name, i) for s in self.sources for i, v in enumerate(s.views)}
        self._rounds: dict[str, int] = {}     # source -> rounds tracked since the start
        # (source, view) -> the last two rounds it tracked: the replay of a recording that
        # starts mid-session continues the trackers' prediction from them
        self._recent: dict[tuple[str, int], deque] = {}
        self._first: set[str] = set()         # sources whose first round is still to come
        self._last_transition: Any = None
        self._last_arm_t = -math.inf
        self._dropped_logged = (0, -math.inf)  # (count, monotonic time) last logged
        self._intents: dict[str, dict[str, Any]] = {}  # audit id -> intent, until its outcome

    # -- taps and observers (cheap, never block, never raise) ---------------------------
    def tap(self, rnd: Any) -> None:
        """A tracked round (``capture_task.CapturedRound``), on the event loop."""
        number = self._rounds[rnd.source] = self._rounds.get(rnd.source, 0) + 1
        views = [(self._views.get(id(view), (rnd.source, -1))[1], view, stamp, found)
                 for view, stamp, found in rnd.views]
        try:
            self._record(rnd, number, views)
        finally:  # after _record: its "before" rounds are the ones before this one
            for index, view, stamp, found in views:
                self._recent.setdefault((rnd.source, index), deque(maxlen=2)).append(
                    (number, view, stamp, found))

    def _record(self, rnd: Any, number: int, views: list[tuple[int, Any, float, Any]]
                ) -> None:
        """Queue round ``number`` for the file, when recording."""
        with self._cond:
            s = self._session
            if s is None or not s.active:
                return
            if rnd.source in self._first:
                self._first.discard(rnd.source)
                self._push_before(s, rnd.source, number)
            n = s.seen[rnd.source] = s.seen.get(rnd.source, 0) + 1
            s.rounds += 1
            opts = s.options
            if opts.images == "none":
                images = "off"
            elif (n - 1) % opts.every:
                images = "decimated"
                s.frames_decimated += len(rnd.frames)
            elif len(s.frames) >= opts.queue_rounds:
                images = "dropped"
                s.frames_dropped += len(rnd.frames)
                s.rounds_dropped += 1
            else:
                images = "queued"
                s.frames.append((rnd.source, number, rnd.frames))
                s.frames_queued += len(rnd.frames)
            meta = {cam: (f.timestamp, f.counter) for cam, f in rnd.frames.items()}
            t = _mean([f.timestamp for f in rnd.frames.values()])
            s.push(("round", rnd.source, number, meta, views, images, t))
            for _, view, stamp, found in views:
                for fname, est in found.items():
                    suffix = view.suffixes.get(fname, fname)
                    s.push(("tf", fmt.pose_topic(f"T_{view.frame}_{suffix}"),
                            est.T_ref_field, stamp, view.frame,
                            fmt.child_frame(view.frame, suffix)))

    def _push_before(self, s: _Session, source: str, number: int) -> None:
        """The rounds before the first recorded one of ``source`` that its views last
        tracked in, as ``before`` records (lock held)."""
        earlier: dict[int, list] = {}
        for (src, index), recent in self._recent.items():
            if src != source:
                continue
            for n, view, stamp, found in recent:
                if n < number:
                    earlier.setdefault(n, []).append((index, view, stamp, found))
        for n in sorted(earlier):
            views = earlier[n]
            s.push(("round", source, n, {}, views, "before", min(v[2] for v in views)))

    def on_audit(self, record: Mapping[str, Any]) -> None:
        """An audit record as the audit log made it (any thread). Intents are kept until
        their outcome, recording or not: the command that starts a recording has its
        intent written before, its outcome after."""
        rec = dict(record)
        rid = str(rec.get("id"))
        with self._cond:
            intent = None
            if rec.get("phase") == "intent":
                self._intents[rid] = rec
                while len(self._intents) > MAX_INTENTS:  # outcomes that never came
                    self._intents.pop(next(iter(self._intents)))
            elif rec.get("phase") == "outcome":
                intent = self._intents.pop(rid, None)
            s = self._session
            if s is None or not s.active:
                return
            s.push(("audit", rec, self.core.clock(), intent))

    # -- the poll task (event loop) -------------------------------------------------------
    async def run(self, *, task_status: anyio.abc.TaskStatus[None] =
                  anyio.TASK_STATUS_IGNORED) -> None:
        """Poll every ``POLL_S`` until cancelled."""
        task_status.started()
        while True:
            self.poll()
            await anyio.sleep(POLL_S)

    def poll(self) -> None:
        """Queue the safety transitions and arm samples that are new since the last
        poll, and report frames dropped since the last report."""
        history = self.core.supervisor.history
        with self._cond:
            s = self._session
            active = s is not None and s.active
        new = _after(history, self._last_transition)
        if history:
            self._last_transition = history[-1]
        samples = None
        if active:
            try:
                arm = self.core.control.read_arm_history()
            except Exception as exc:  # a control process going away: no more samples
                log.debug("recording: arm history unreadable: %s", exc)
                arm = None
            if arm is not None and len(arm):
                samples = arm[arm["t"] > self._last_arm_t]
                if len(samples):
                    self._last_arm_t = float(samples["t"][-1])
        with self._cond:
            s = self._session
            if s is None or not s.active:
                return
            now = self.core.clock()
            for tr in new:
                s.push(("json", fmt.SAFETY_TOPIC, fmt.transition_record(tr),
                        tr.time if math.isfinite(tr.time) else now))
            if samples is not None and len(samples):
                s.push(("tcp", samples))
            dropped = s.frames_dropped
            if dropped > self._dropped_logged[0]:
                s.push(("json", fmt.RECORDER_TOPIC, {
                    "event": "frames dropped", "frames_dropped": dropped,
                    "detail": "the writer was behind: the frame queue was full"}, now))
                if time.monotonic() - self._dropped_logged[1] >= DROP_LOG_S:
                    log.warning("recording %s: %d frames dropped so far (the disk is slower "
                                "than the cameras; poses are all kept)", s.options.path,
                                dropped)
                    self._dropped_logged = (dropped, time.monotonic())
                else:
                    self._dropped_logged = (dropped, self._dropped_logged[1])

    # -- operations (API, oralnavd --record) ----------------------------------------------
    def start(self, options: RecordingOptions, who: str) -> dict[str, Any]:
        """Start recording to ``options.path``; the status. :class:`StateError` while a
        recording runs; :class:`RecordingError` when the file cannot be created (the
        status then says ``failed`` with the same error)."""
        with self._cond:
            if self._session is not None:
                raise StateError(f"already recording to {self._session.options.path}; "
                                 "POST /recording/stop first")
        views, files = self._views_and_files()
        config_text = None
        if self.config_path is not None:
            try:
                config_text = self.config_path.read_bytes()
            except OSError as exc:  # provenance only: the views carry what replay needs
                log.warning("recording: the configuration %s is not attached: %s",
                            self.config_path, exc.strerror or exc)
        path = options.path
        mode = "wb" if options.overwrite else "xb"
        try:
            fh = open(path, mode)  # noqa: SIM115 - the writer thread closes it
        except OSError as exc:
            why = "the file exists (choose another name)" if isinstance(exc, FileExistsError) \
                else _os_error(path, exc)
            err = f"cannot record to {path}: {why}"
            with self._cond:
                failed = _Session(options, who, self._cond, lambda w: None)
                failed.state, failed.error, failed.t_end = "failed", err, time.monotonic()
                self._last = failed
            log.error("%s", err)
            raise RecordingError(err) from None

        def begin(writer: Any) -> None:
            self._begin(writer, session, views, files, config_text)

        with self._cond:
            if self._session is not None:  # another start won the race: undo ours
                fh.close()
                if not options.overwrite:
                    path.unlink(missing_ok=True)
                raise StateError(f"already recording to {self._session.options.path}")
            session = _Session(options, who, self._cond, begin)
            self._session = self._last = session
            self._first = {s.name for s in self.sources}
            # only what happens from now on: transitions and arm samples already seen
            # belong to no recording
            history = self.core.supervisor.history
            self._last_transition = history[-1] if history else None
            self._last_arm_t = self.core.clock() - POLL_S
            T_B_C = getattr(self.core, "T_B_C", None)
            if T_B_C is not None:
                session.push(("tf", fmt.HAND_EYE_TOPIC, np.array(T_B_C, dtype=float),
                              self.core.clock(), "B", "C"))
            session.push(("json", fmt.SAFETY_TOPIC, {
                "time": self.core.clock(), "from": None,
                "to": self.core.supervisor.state.value, "who": "recorder",
                "reason": "the state when the recording started"}, self.core.clock()))
            session.thread = threading.Thread(target=self._write, args=(session, fh),
                                              name="recorder", daemon=True)
            session.thread.start()
        log.info("recording to %s (images %s every %d round(s), %s chunks) by %s", path,
                 options.images, options.every, options.compression, who)
        return self.status()

    def stop(self, who: str, wait_s: float = STOP_WAIT_S) -> dict[str, Any]:
        """End the recording: the writer writes what is queued, the summary and the index,
        and closes the file (waited for up to ``wait_s``). Never refused: without a
        recording it only returns the status."""
        with self._cond:
            s = self._session
            if s is None:
                return self.status()
            if not s.stop_requested:
                s.stop_requested = True
                s.stopped_by = who
                if s.state == "recording":
                    s.state = "stopping"
            s.cond.notify_all()
            thread = s.thread
        if thread is not None:
            thread.join(wait_s)
            if thread.is_alive():
                log.error("recording %s: the writer is still busy after %.0f s; it goes on "
                          "in the background", s.options.path, wait_s)
        return self.status()

    def close(self) -> None:
        """The daemon is stopping: record the last transitions, then stop (blocking)."""
        try:
            self.poll()
        except Exception:  # the core going down: what is queued still gets written
            log.exception("recording: last poll failed")
        self.stop("daemon stopping")

    def status(self) -> dict[str, Any]:
        """``GET /recording``: the state (``idle``, ``recording``, ``stopping``,
        ``stopped``, ``failed``) and the latest recording's figures."""
        with self._cond:
            s = self._last
            if s is None:
                return {"state": "idle", "path": None, "error": None}
            end = s.t_end if s.t_end is not None else time.monotonic()
            duration = max(end - s.t0, 0.0)
            return {
                "state": s.state, "path": str(s.options.path), "error": s.error,
                "options": s.options.as_dict(), "by": s.who, "stopped_by": s.stopped_by,
                "started_utc": s.started_utc, "duration_s": round(duration, 3),
                "rounds": s.rounds,
                "frames": {"written": s.frames_written,
                           "queued": sum(len(f[2]) for f in s.frames),
                           "dropped": s.frames_dropped, "decimated": s.frames_decimated,
                           "rounds_dropped": s.rounds_dropped},
                "records": {"written": s.records_written, "queued": len(s.records),
                            "max_queued": s.records_max},
                "bytes": s.size if s.size is not None else s.bytes,
                # the file's growth over the recording, and the writer's own pace while it
                # works (encoding, compressing, writing): how much faster than the cameras
                # the disk path is
                "mb_per_s": round(s.bytes / duration / 1e6, 3) if duration > 0 else None,
                "writer_mb_per_s": round(s.bytes / s.write_busy_s / 1e6, 3)
                if s.write_busy_s > 0 else None,
                "writer_busy": round(s.write_busy_s / duration, 3) if duration > 0 else None,
            }

    # -- internals -----------------------------------------------------------------------
    def _views_and_files(self) -> tuple[list[dict[str, Any]], dict[str, bytes]]:
        views: list[dict[str, Any]] = []
        files: dict[str, bytes] = {}
        for s in self.sources:
            for i, v in enumerate(s.views):
                entry, more = fmt.view_entry(s.name, i, v)
                views.append(entry)
                files.update(more)
        return views, files

    def _clock_offset(self) -> tuple[int, int]:
        """(UTC minus the daemon's clock, ns; the uncertainty, ns): the clock read on
        both sides of the wall clock."""
        a = fmt.to_ns(self.core.clock())
        utc = time.time_ns()
        b = fmt.to_ns(self.core.clock())
        return utc - (a + b) // 2, (b - a + 1) // 2

    def _begin(self, writer: Any, s: _Session, views: list[dict[str, Any]],
               files: Mapping[str, bytes], config_text: bytes | None) -> None:
        """The file's first records: metadata (session, clock, views) and attachments."""
        offset, uncertainty = self._clock_offset()
        now = time.time_ns()
        writer.add_metadata(fmt.SESSION_METADATA, {
            "oralnav_version": __version__, "started_utc": s.started_utc,
            "host": socket.gethostname(), "by": s.who,
            "options": fmt.json_bytes(s.options.as_dict()).decode(),
            "sources": fmt.json_bytes([{"name": src.name, "cameras": sorted(
                {c for v in src.views for c in v.tracker.rig.names})}
                for src in self.sources]).decode(),
            "config": str(self.config_path) if self.config_path else ""})
        writer.add_metadata(fmt.CLOCK_METADATA, {
            "clock": "daemon monotonic (CLOCK_MONOTONIC): frame capture instants, pose "
                     "stamps, events; integer nanoseconds",
            "utc_minus_clock_ns": str(offset), "uncertainty_ns": str(uncertainty),
            "measured_utc": _utc_iso(now)})
        writer.add_metadata(fmt.VIEWS_METADATA, {"views": fmt.json_bytes(views).decode()})
        for name, data in files.items():
            writer.add_attachment(now, now, name, "application/toml" if name.endswith(
                ".toml") else "text/csv", data)
        if config_text is not None:
            writer.add_attachment(now, now, fmt.CONFIG_ATTACHMENT, "application/toml",
                                  config_text)

    def _write(self, s: _Session, fh: Any) -> None:
        """The writer thread: the file from its header to its footer."""
        writer = None
        try:
            writer = _McapFile(fh, s.options.compression)
            s.begin(writer.raw)
            while True:
                with s.cond:
                    while not s.records and not s.frames and not s.stop_requested:
                        s.cond.wait()
                    records = list(s.records)
                    s.records.clear()
                    # every record waiting first, then one round of frames: the small
                    # path always goes ahead, and never starves the frames
                    frames = s.frames.popleft() if s.frames else None
                    done = s.stop_requested and not records and not frames and not s.frames
                t0 = time.perf_counter()
                for item in records:
                    writer.record(item)
                if frames is not None:
                    writer.frames(frames, s.options)
                busy = time.perf_counter() - t0
                with s.cond:
                    s.records_written += len(records)
                    if frames is not None:
                        s.frames_written += len(frames[2])
                    s.bytes = writer.tell()
                    s.write_busy_s += busy
                if done:
                    break
            self._finish(s, writer)
        except Exception as exc:
            self._fail(s, writer, fh, exc)
        else:
            with s.cond:
                s.state = "stopped"
                s.t_end = time.monotonic()
                self._session = None
                self._first = set()
            log.info("recording %s stopped by %s: %d rounds, %d frames written, %d dropped, "
                     "%.1f MB", s.options.path, s.stopped_by, s.rounds, s.frames_written,
                     s.frames_dropped, (s.size or 0) / 1e6)

    def _finish(self, s: _Session, writer: _McapFile) -> None:
        offset, uncertainty = self._clock_offset()
        with s.cond:
            summary = {
                "ended_utc": _utc_iso(), "stopped_by": s.stopped_by or "",
                "rounds": str(s.rounds), "frames_written": str(s.frames_written),
                "frames_dropped": str(s.frames_dropped),
                "frames_decimated": str(s.frames_decimated),
                "rounds_dropped": str(s.rounds_dropped),
                "records_written": str(s.records_written),
                "records_max_queued": str(s.records_max),
                "duration_s": f"{time.monotonic() - s.t0:.3f}",
                "utc_minus_clock_ns_at_end": str(offset),
                "uncertainty_ns_at_end": str(uncertainty)}
        writer.raw.add_metadata(fmt.SUMMARY_METADATA, summary)
        writer.raw.finish()
        size = writer.tell()
        writer.close()
        with s.cond:
            s.size = size
            s.bytes = size

    def _fail(self, s: _Session, writer: _McapFile | None, fh: Any,
              exc: BaseException) -> None:
        """A write failed: end the recording, keep what is on disk, say why."""
        err = f"recording stopped: cannot write {_os_error(s.options.path, exc)}"
        if isinstance(exc, OSError):
            log.error("%s; what was written before stays readable (oralnav replay reads "
                      "it up to its last whole chunk)", err)
        else:
            log.exception("%s", err)
        with s.cond:
            s.state = "failed"
            s.error = err
            s.t_end = time.monotonic()
            lost = sum(len(f[2]) for f in s.frames)
            s.frames_dropped += lost
            s.frames.clear()
            s.records.clear()
            self._session = None
            self._first = set()
        # the index and summary may still fit (a disk that had room for them): try once
        for step in ((writer.raw.finish,) if writer is not None else ()) + (fh.close,):
            try:
                step()
            except Exception as again:
                log.debug("recording %s: %s", s.options.path, again)
        try:
            s.size = os.path.getsize(s.options.path)
        except OSError:
            s.size = None


class _McapFile:
    """The writer thread's MCAP writer: the ``mcap`` library's, its channels registered
    on first use (Protobuf schemas through ``mcap-protobuf-support``)."""

    def __init__(self, fh: Any, compression: str) -> None:
        from mcap.writer import CompressionType, Writer

        self.fh = fh
        kind = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4,
                "none": CompressionType.NONE}[compression]
        self.raw = Writer(fh, chunk_size=CHUNK_BYTES, compression=kind)
        self.raw.start(profile="", library=f"oralnav {__version__}")
        self._channels: dict[str, int] = {}
        self._schemas: dict[str, int] = {}

    def tell(self) -> int:
        try:
            return int(self.fh.tell())
        except (OSError, ValueError):
            return 0

    def close(self) -> None:
        self.fh.close()

    def _channel(self, topic: str, message: Any = None) -> int:
        cid = self._channels.get(topic)
        if cid is not None:
            return cid
        if message is None:  # a JSON channel
            name, schema = fmt.JSON_CHANNELS[topic]
            sid = self._schemas.get(name)
            if sid is None:
                sid = self._schemas[name] = self.raw.register_schema(name, "jsonschema",
                                                                     schema)
            cid = self.raw.register_channel(topic, "json", sid)
        else:
            from mcap_protobuf.schema import register_schema

            name = type(message).DESCRIPTOR.full_name
            sid = self._schemas.get(name)
            if sid is None:
                sid = self._schemas[name] = register_schema(self.raw, type(message))
            cid = self.raw.register_channel(topic, "protobuf", sid)
        self._channels[topic] = cid
        return cid

    def _add(self, topic: str, data: bytes, t: float, message: Any = None,
             sequence: int = 0) -> None:
        ns = max(fmt.to_ns(t), 0)
        self.raw.add_message(self._channel(topic, message), log_time=ns, data=data,
                             publish_time=ns, sequence=sequence & 0xFFFFFFFF)

    def _json(self, topic: str, obj: Any, t: float, sequence: int = 0) -> None:
        self._add(topic, fmt.json_bytes(obj), t, sequence=sequence)

    def _proto(self, topic: str, msg: Any, t: float, sequence: int = 0) -> None:
        self._add(topic, msg.SerializeToString(), t, msg, sequence)

    def record(self, item: tuple) -> None:
        kind = item[0]
        if kind == "round":
            _, source, number, meta, views, images, t = item
            frames = {cam: _FrameMeta(*m) for cam, m in meta.items()}
            entries = [(index, view.frame, stamp, {
                fname: fmt.pose_entry(f"T_{view.frame}_{view.suffixes.get(fname, fname)}",
                                      est) for fname, est in found.items()})
                for index, view, stamp, found in views]
            self._json(fmt.ROUNDS_TOPIC, fmt.round_record(source, number, frames, entries,
                                                          images), t, number)
        elif kind == "tf":
            _, topic, T, stamp, parent, child = item
            self._proto(topic, fmt.frame_transform(T, stamp, parent, child), stamp)
        elif kind == "tcp":
            samples = item[1]
            quats = fmt.quaternions(samples["T_B_tcp"])
            for t, T, q in zip(samples["t"], samples["T_B_tcp"], quats, strict=True):
                self._proto(fmt.TCP_TOPIC, fmt.frame_transform(T, float(t), "B", "tcp", q),
                            float(t))
        elif kind == "json":
            _, topic, obj, t = item
            self._json(topic, obj, t)
        elif kind == "audit":
            _, rec, t, intent = item
            self._json(fmt.AUDIT_TOPIC, rec, t)
            # an operator command, once its outcome is known
            if rec.get("method") == "POST" and rec.get("phase") in ("outcome", "single"):
                self._json(fmt.COMMANDS_TOPIC, fmt.command_record(rec, intent), t)
        else:  # pragma: no cover - the recorder makes only the kinds above
            raise ValueError(f"unknown record kind {kind!r}")

    def frames(self, item: tuple[str, int, Mapping[str, Any]], opts: RecordingOptions) -> None:
        _, number, frames = item
        for cam, f in frames.items():
            msg = fmt.image_message(f.image, f.timestamp, cam, opts.images, opts.jpeg_quality)
            self._proto(fmt.image_topic(cam), msg, f.timestamp, number)


@dataclass(frozen=True)
class _FrameMeta:
    timestamp: float
    counter: int


def _mean(xs: Sequence[float]) -> float:
    return float(np.mean(xs)) if xs else 0.0


def _after(history: Sequence[Any], last: Any) -> list[Any]:
    """The transitions of ``history`` after ``last`` (by identity); all of them when
    ``last`` has left the bounded history (or was None)."""
    if last is None:
        return list(history)
    for i in range(len(history) - 1, -1, -1):
        if history[i] is last:
            return list(history[i + 1:])
    return list(history)
