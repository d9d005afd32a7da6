"""The latched stop: an idempotent, synchronous fan-out to every registered stop handler.

Once triggered the stop stays latched until :meth:`LatchedStop.clear`, which only
:meth:`oralnav.safety.states.SafetySupervisor.reset` calls. Triggering never awaits and
never raises: each handler runs in its own try/except, so one failing handler (a driver
whose socket is gone) cannot keep the others (the end-effector, the brake output) from
being told to stop.

Re-trigger policy: the first trigger of a latch calls every handler, and so does an
escalating trigger (``escalate=True``: the supervisor passes it when FAULT becomes
ESTOP). Other triggers while latched record their reason and call again only the
handlers that have not yet returned normally during this latch: a failed stop command is
retried at the next trip, a successful one is not repeated at the watchdog's rate.
Handlers must be idempotent all the same: escalation, concurrent triggers and a handler
added while latched may call one more than once.
Time is passed in (``now``, seconds, monotonic or virtual); nothing here reads a clock.
"""

from __future__ import annotations

import inspect
import logging
import math
import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from .errors import InputError, StateError

log = logging.getLogger(__name__)

#: A stop handler: called with no argument, or with the :class:`StopRecord` that latched.
StopHandler = Callable[[], Any] | Callable[["StopRecord"], Any]


@dataclass(frozen=True)
class StopRecord:
    """One trigger of the stop: when (s), by whom or what, and why."""

    time: float
    source: str
    reason: str

    def as_dict(self) -> dict[str, Any]:
        # NaN is not JSON; a time that could not be read is reported as null
        t = self.time if math.isfinite(self.time) else None
        return {"time": t, "source": self.source, "reason": self.reason}


class _Handler:
    """A registered handler and its bookkeeping for the current latch."""

    __slots__ = ("fn", "name", "takes_record", "done", "running", "failures")

    def __init__(self, fn: StopHandler, name: str, takes_record: bool) -> None:
        self.fn = fn
        self.name = name
        self.takes_record = takes_record
        self.done = False      # returned normally during the current latch
        self.running = False   # being called right now (by some thread)
        self.failures = 0      # failed calls during the current latch


def _takes_record(fn: StopHandler) -> bool:
    """Whether ``fn`` accepts one positional argument; decided once, at registration."""
    try:
        sig = inspect.signature(fn)
    except (TypeError, ValueError):  # some builtins have no signature: call them bare
        return False
    try:
        sig.bind(None)
        return True
    except TypeError:
        pass
    try:
        sig.bind()
        return False
    except TypeError:
        raise InputError(f"stop handler {fn!r} must take no argument or one StopRecord"
                         ) from None


class LatchedStop:
    """A latched, idempotent stop fan-out. Thread-safe; handlers run outside the lock so a
    handler may read this object (or trigger it again) without deadlocking."""

    def __init__(self, *, max_records: int = 64) -> None:
        if max_records < 1:
            raise InputError(f"max_records must be at least 1, got {max_records}")
        self._lock = threading.Lock()
        self._handlers: list[_Handler] = []
        self._latched = False
        self._first: StopRecord | None = None
        # bounded: a watchdog that keeps tripping while latched must not grow memory
        self._records: deque[StopRecord] = deque(maxlen=max_records)
        self._triggers = 0

    # -- registration ---------------------------------------------------------------------
    def add_handler(self, handler: StopHandler, name: str | None = None) -> None:
        """Register ``handler`` (no argument, or one :class:`StopRecord`).

        Added while latched, it is called at once: whatever it stops must be stopped too.
        """
        if not callable(handler):
            raise InputError(f"stop handler {handler!r} is not callable")
        h = _Handler(handler, name or getattr(handler, "__qualname__", repr(handler)),
                     _takes_record(handler))
        with self._lock:
            self._handlers.append(h)
            run = self._latched
            if run:
                h.running = True
            record = self._first
        if run and record is not None:
            self._run([h], record)

    def remove_handler(self, handler: StopHandler) -> bool:
        """Unregister ``handler``; False if it was not registered."""
        with self._lock:
            for i, h in enumerate(self._handlers):
                if h.fn is handler:
                    del self._handlers[i]
                    return True
        return False

    # -- the stop path --------------------------------------------------------------------
    def trigger(self, now: float, source: str, reason: str, *,
                escalate: bool = False) -> bool:
        """Latch the stop and fan out to the handlers; True when this call latched it.

        Never raises and never blocks on other triggers (only on the short bookkeeping
        lock); see the module docstring for which handlers a re-trigger calls
        (``escalate``: all of them again).
        """
        try:
            record = StopRecord(float(now), str(source), str(reason))
        except Exception:  # a malformed argument must still stop the robot
            record = StopRecord(math.nan, repr(source), repr(reason))
        with self._lock:
            first = not self._latched
            if first:
                self._latched = True
                self._first = record
            if first or escalate:
                for h in self._handlers:
                    h.done = False
                    h.failures = 0
            self._records.append(record)
            self._triggers += 1
            # a handler already running in another thread is not entered twice
            run = [h for h in self._handlers if not h.done and not h.running]
            for h in run:
                h.running = True
        if first:
            log.warning("STOP latched by %s: %s", record.source, record.reason)
        self._run(run, record)
        return first

    def _run(self, handlers: list[_Handler], record: StopRecord) -> None:
        deferred: BaseException | None = None
        for h in handlers:
            ok = False
            try:
                if h.takes_record:
                    h.fn(record)  # type: ignore[call-arg]
                else:
                    h.fn()  # type: ignore[call-arg]
                ok = True
            except Exception:
                # the first failure per latch with its traceback; repeats (one per
                # re-trigger, possibly at the control rate) without
                if h.failures == 0:
                    log.exception("stop handler %s failed (the others still run)", h.name)
                else:
                    log.debug("stop handler %s failed again", h.name, exc_info=True)
            except BaseException as exc:  # KeyboardInterrupt, SystemExit: after the others
                deferred = deferred or exc
            finally:
                with self._lock:
                    h.running = False
                    if ok:
                        h.done = True
                    else:
                        h.failures += 1
        if deferred is not None:
            # only interpreter-exit signals get here; every handler has been called
            raise deferred

    # -- state ----------------------------------------------------------------------------
    @property
    def latched(self) -> bool:
        """True from the first trigger until :meth:`clear`. Read without the lock: one
        attribute read is atomic, and the control loop must never wait here."""
        return self._latched

    @property
    def first(self) -> StopRecord | None:
        """The trigger that latched the stop, or None when not latched."""
        with self._lock:
            return self._first

    @property
    def records(self) -> tuple[StopRecord, ...]:
        """Every trigger of the current latch (the latest ``max_records``), oldest first."""
        with self._lock:
            return tuple(self._records)

    @property
    def unconfirmed(self) -> tuple[str, ...]:
        """Names of handlers that have not returned normally during the current latch; empty
        when not latched."""
        with self._lock:
            if not self._latched:
                return ()
            return tuple(h.name for h in self._handlers if not h.done)

    def clear(self, now: float, who: str) -> bool:
        """Release the latch; False if it was not latched. Called by the supervisor's
        ``reset`` only, once the cause has cleared; ``who`` (the operator) is required."""
        if not isinstance(who, str) or not who.strip():
            raise StateError("clearing the latched stop needs the operator's name (who)")
        with self._lock:
            was = self._latched
            self._latched = False
            self._first = None
            self._records.clear()
            for h in self._handlers:
                h.done = False
                h.failures = 0
        if was:
            log.warning("STOP cleared by %s at t=%.3f", who, now)
        return was

    def snapshot(self) -> dict[str, Any]:
        """JSON-able state for GET /status."""
        with self._lock:
            return {
                "latched": self._latched,
                "first": self._first.as_dict() if self._first else None,
                "records": [r.as_dict() for r in self._records],
                "triggers": self._triggers,
                "handlers": [h.name for h in self._handlers],
                "unconfirmed": ([h.name for h in self._handlers if not h.done]
                                if self._latched else []),
            }
