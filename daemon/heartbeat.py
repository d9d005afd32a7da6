"""The control loop's heartbeat, watched from the daemon on the daemon's own clock.

A control process that hangs (SIGSTOP, a stuck driver call, a kernel that stops
scheduling it) is still *alive*: ``ControlProcess.alive`` says yes and its status record
keeps its last values. Only the heartbeat tells: ``ControlPort.heartbeat()`` changes with
every period the loop completes. :class:`LoopHeartbeat` polls it in a thread of its own
(every ``poll_s``, about a microsecond a look), so that neither a busy event loop nor a
slow request delays the verdict, and feeds each change to the daemon's
:class:`~oralnav.safety.watchdogs.DeadlineWatchdog` (``WatchdogSet.deadline``). When no
period has completed for ``period + max_period_lateness`` (the same silence after which
the loop's own deadline watchdog would stop the arm) it latches FAULT
(``deadline:stalled``) at once from this thread: the latched stop's handlers ask the loop
to stop and write HOLD, which a hung loop reads when it runs again. Until then the arm is
stopped by its own controller: the UR's RTDE watchdog, or the simulated arm's watchdog
(docs/safety.md, "A hung control process"). While the loop is silent the core reports the
daemon unhealthy, so the systemd watchdog is starved and ``GET /health`` says why.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections.abc import Callable
from typing import Any

log = logging.getLogger(__name__)

#: How often the heartbeat is looked at (s).
POLL_S = 0.001


class LoopHeartbeat:
    """Watches ``control.heartbeat()`` and latches FAULT through ``core.supervisor`` when
    the loop falls silent. ``core`` is the :class:`~oralnav.daemon.core.DaemonCore`; its
    ``watchdogs.deadline`` holds the limit. Constructing does nothing; :meth:`start` runs
    the thread and :meth:`close` (idempotent) ends it. :meth:`observe` is the one look,
    thread-safe, also called by the supervisor's tick."""

    def __init__(self, core: Any, *, poll_s: float = POLL_S,
                 clock: Callable[[], float] = time.monotonic, priority: int = 0) -> None:
        """``priority``: SCHED_FIFO priority for the watch thread (0: normal scheduling),
        e.g. one below the control loop's ``[control] realtime_priority``, so that a busy
        host delays the watch no more than the loop it watches."""
        if not poll_s > 0:
            raise ValueError(f"poll_s must be > 0 s, got {poll_s!r}")
        self.core = core
        self.poll_s = poll_s
        self.clock = clock
        self.priority = int(priority)
        self._lock = threading.Lock()
        self._beat: int | None = None
        self._silent = False           # the current silence has been latched already
        #: the last silence latched: {"beats": n, "quiet_s": silence when latched}
        self.last_trip: dict[str, float] | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def observe(self, now: float) -> bool:
        """One look at ``now`` (s, daemon clock); False while the loop is silent past its
        limit (FAULT is latched once per silence)."""
        deadline = self.core.watchdogs.deadline
        beat = self.core.control.heartbeat()
        with self._lock:
            if beat and beat != self._beat:
                # a period completed since the last look: on this clock, now at the latest
                self._beat = beat
                self._silent = False
                deadline.period_done(0.0, now)
                return True
            if not deadline.stalled(now):
                return True
            first = not self._silent
            self._silent = True
            quiet = deadline.quiet(now) or 0.0
            if first:
                self.last_trip = {"beats": float(beat), "quiet_s": quiet}
        if first:
            limit = deadline.period + deadline.max_lateness
            self.core.supervisor.fault(
                now, "deadline:stalled",
                f"control loop silent: no period completed for {quiet * 1e3:.1f} ms "
                f"(limit {limit * 1e3:.1f} ms); the process is alive but not running")
            log.error("control loop silent for %.1f ms: FAULT latched, stop commanded",
                      quiet * 1e3)
        return False

    def start(self) -> None:
        """Run the watch in its own daemon thread (idempotent)."""
        if self._thread is not None:
            return
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="loop-heartbeat", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        if self.priority > 0:
            try:  # Linux schedules threads by their own id
                os.sched_setscheduler(threading.get_native_id(), os.SCHED_FIFO,
                                      os.sched_param(self.priority))
                log.info("heartbeat watch at SCHED_FIFO priority %d", self.priority)
            except (OSError, AttributeError) as exc:
                log.warning("heartbeat watch: SCHED_FIFO %d refused (%s); normal "
                            "scheduling", self.priority, exc)
        while not self._stop.wait(self.poll_s):
            try:
                self.observe(self.clock())
            except Exception:  # the watch must outlive a bad read; the tick looks too
                log.exception("heartbeat check failed")

    def close(self) -> None:
        """End the thread (idempotent)."""
        thread, self._thread = self._thread, None
        if thread is not None:
            self._stop.set()
            thread.join(timeout=1.0)

    def __enter__(self) -> LoopHeartbeat:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
