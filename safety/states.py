"""The safety state machine: IDLE, READY, RUNNING, PAUSED, FAULT, ESTOP (docs/safety.md).

Rules the code below keeps:

- Requests that make the robot move or release a latch (``start``, ``resume``, ``reset``)
  are strict: refused with :class:`StateError` naming the current state and why, changing
  nothing, and they need the authenticated operator's name (``who``).
- Requests and reports that make it safer never fail: ``fault`` and ``estop`` never raise,
  ``pause`` while already paused and the health reports (``mark_ready``,
  ``mark_not_ready``) are no-ops where they do not apply.
- FAULT and ESTOP are latched; entering either fires the :class:`LatchedStop`
  synchronously, before the call returns. ESTOP outranks FAULT: a fault while in ESTOP
  is recorded but leaves the state ESTOP; an e-stop while in FAULT moves to ESTOP.
- ``reset`` (FAULT/ESTOP -> IDLE) only when the e-stop input is released and the faults
  have cleared, as the caller (the daemon, which reads the inputs and watchdogs) reports.
- A latch during a procedure (RUNNING or PAUSED) interrupts it: the procedure is kept,
  never continued by itself. After the reset (and READY) the operator ``resume``s it from
  where it stood or ``abort``s it; ``start`` is refused until one of the two is chosen.

Time is passed in (``now``, seconds, monotonic or virtual); nothing here reads a clock.
"""

from __future__ import annotations

import logging
import math
import threading
from collections import deque
from dataclasses import dataclass
from enum import StrEnum
from typing import Any

from .errors import InputError, StateError
from .stop import LatchedStop

log = logging.getLogger(__name__)


class SafetyState(StrEnum):
    """The daemon's safety state; the value is what GET /status reports."""

    IDLE = "IDLE"        # up, not ready: drivers not connected or no fresh poses
    READY = "READY"      # healthy, may move on command
    RUNNING = "RUNNING"  # a procedure is executing
    PAUSED = "PAUSED"    # procedure held, robot holding still
    FAULT = "FAULT"      # a watchdog or limit tripped; latched
    ESTOP = "ESTOP"      # emergency stop (input or REST); latched


#: States that only ``reset`` leaves.
LATCHED = frozenset({SafetyState.FAULT, SafetyState.ESTOP})


@dataclass(frozen=True)
class Transition:
    """One state change: when (s), from, to, who asked (operator) or what caused it
    (watchdog, input), and why."""

    time: float
    from_state: SafetyState
    to_state: SafetyState
    who: str
    reason: str

    def as_dict(self) -> dict[str, Any]:
        return {"time": _json_time(self.time), "from": self.from_state.value,
                "to": self.to_state.value, "who": self.who, "reason": self.reason}


@dataclass(frozen=True)
class Cause:
    """An active reason for a latched state: ``kind`` is ``"fault"`` or ``"estop"``."""

    time: float
    kind: str
    source: str
    reason: str

    def as_dict(self) -> dict[str, Any]:
        return {"time": _json_time(self.time), "kind": self.kind, "source": self.source,
                "reason": self.reason}

    def __str__(self) -> str:
        return f"{self.source}: {self.reason}"


def _json_time(t: float) -> float | None:
    return t if math.isfinite(t) else None


def _check_now(now: float) -> float:
    try:
        t = float(now)
    except (TypeError, ValueError):
        raise InputError(f"now must be a time in seconds, got {now!r}") from None
    if not math.isfinite(t):
        raise InputError(f"now must be finite, got {now!r}")
    return t


def _safe_float(now: object) -> float:
    # for the stop path: never raise, a bad time becomes NaN
    try:
        return float(now)  # type: ignore[arg-type]
    except Exception:
        return math.nan


def _safe_str(x: object, default: str) -> str:
    # for the stop path: never raise, whatever __str__ does
    try:
        return str(x) or default
    except Exception:
        return default


def _unnamed(who: object) -> str:
    # for requests that make the robot safer: a missing name is recorded, not refused
    return (who.strip() if isinstance(who, str) else "") or "(unnamed)"


def _operator(who: object, action: str) -> str:
    if not isinstance(who, str) or not who.strip():
        raise StateError(f"{action} needs the authenticated operator's name (who)")
    return who.strip()


class SafetySupervisor:
    """The safety state machine. Thread-safe: the control loop (its own thread) and the
    event loop call in concurrently.

    ``state`` and ``motion_allowed`` are read without the lock (one attribute read each),
    so the 500 Hz loop never waits on a stop handler. Everything else takes a re-entrant
    lock: the latched stop fires inside it, so no request can slip between entering FAULT
    and the stop being commanded, and a handler that reads :meth:`snapshot` in the same
    thread does not deadlock. Stop handlers must therefore be quick and never block.
    """

    def __init__(self, stop: LatchedStop | None = None, *, history: int = 256,
                 max_causes: int = 32) -> None:
        if history < 1 or max_causes < 1:
            raise InputError("history and max_causes must be at least 1")
        self._lock = threading.RLock()
        self._stop = stop if stop is not None else LatchedStop()
        self._state = SafetyState.IDLE
        self._since = math.nan          # time of the last transition (none yet)
        self._not_ready: str | None = "starting"
        self._operator: str | None = None  # who started the current procedure
        # a procedure a latch interrupted: who started it, when and why it was stopped
        self._interrupted: dict[str, Any] | None = None
        # keyed by (kind, source): the first reason of each source is the cause; repeats
        # (a watchdog tripping every check while latched) only count
        self._causes: dict[tuple[str, str], Cause] = {}
        self._max_causes = max_causes
        self._dropped_causes = 0
        self._history: deque[Transition] = deque(maxlen=history)

    # -- reading --------------------------------------------------------------------------
    @property
    def state(self) -> SafetyState:
        return self._state

    @property
    def motion_allowed(self) -> bool:
        """True only in RUNNING with the stop not latched; the control loop checks this
        every period before commanding anything but a hold."""
        return self._state is SafetyState.RUNNING and not self._stop.latched

    @property
    def stop(self) -> LatchedStop:
        """The latched stop; register the drivers' stop handlers here."""
        return self._stop

    @property
    def reasons(self) -> tuple[Cause, ...]:
        """The active causes of FAULT/ESTOP, oldest first (empty otherwise)."""
        with self._lock:
            return tuple(self._causes.values())

    @property
    def interrupted(self) -> dict[str, Any] | None:
        """The procedure a latched stop interrupted (``by``: who started it, ``time``,
        ``reason``), until it is resumed or aborted; None otherwise."""
        with self._lock:
            return dict(self._interrupted) if self._interrupted is not None else None

    @property
    def not_ready_reason(self) -> str | None:
        """Why the last health report said not ready; None when it said healthy."""
        return self._not_ready

    @property
    def history(self) -> tuple[Transition, ...]:
        """The latest transitions, oldest first (bounded)."""
        with self._lock:
            return tuple(self._history)

    def snapshot(self, history: int = 20) -> dict[str, Any]:
        """JSON-able state for GET /status, with the latest ``history`` transitions."""
        with self._lock:
            hist = list(self._history)[-history:] if history > 0 else []
            return {
                "state": self._state.value,
                "motion_allowed": self.motion_allowed,
                "since": _json_time(self._since),
                "operator": self._operator,
                "interrupted": (dict(self._interrupted) if self._interrupted is not None
                                else None),
                "not_ready_reason": self._not_ready,
                "reasons": [c.as_dict() for c in self._causes.values()],
                "dropped_reasons": self._dropped_causes,
                "stop": self._stop.snapshot(),
                "history": [t.as_dict() for t in hist],
            }

    # -- internals ------------------------------------------------------------------------
    def _go(self, now: float, to: SafetyState, who: str, reason: str) -> None:
        # caller holds the lock
        self._history.append(Transition(now, self._state, to, who, reason))
        log.info("safety %s -> %s (%s: %s)", self._state.value, to.value, who, reason)
        self._state = to
        self._since = now

    def _why_not(self, action: str) -> str:
        """Why the current state refuses ``action``, to follow "while in STATE"."""
        s = self._state
        if s in LATCHED:
            return f" ({self._causes_text()}); reset first"
        if s is SafetyState.IDLE and (action == "start" or (
                action == "resume" and self._interrupted is not None)):
            return f" (not ready: {self._not_ready or 'waiting for a health report'})"
        if s is SafetyState.RUNNING:
            if action == "resume":
                return ": the procedure is running, not paused"
            return f": a procedure is running (started by {self._operator})"
        if s is SafetyState.PAUSED:
            return f": a procedure is paused (started by {self._operator}); resume or abort"
        return ": no procedure is running"

    def _causes_text(self, most: int = 3) -> str:
        causes = list(self._causes.values())
        text = "; ".join(str(c) for c in causes[:most]) or "no reason recorded"
        if len(causes) > most:
            text += f"; and {len(causes) - most} more"
        return text

    def _refuse(self, action: str) -> StateError:
        return StateError(f"cannot {action} while in {self._state.value}"
                          f"{self._why_not(action)}")

    def _add_cause(self, now: float, kind: str, source: str, reason: str) -> None:
        key = (kind, source)
        if key in self._causes:
            return
        if len(self._causes) >= self._max_causes:
            self._dropped_causes += 1  # bounded; the stop keeps the latest records
            return
        self._causes[key] = Cause(now, kind, source, reason)

    # -- health reports (never raise) -----------------------------------------------------
    def mark_ready(self, now: float) -> bool:
        """Health report: drivers connected and poses fresh. IDLE -> READY; elsewhere it
        only notes the health (a latched state still needs ``reset``). True on a change."""
        now = _check_now(now)
        with self._lock:
            self._not_ready = None
            if self._state is SafetyState.IDLE:
                self._go(now, SafetyState.READY, "health", "drivers connected, poses fresh")
                return True
            return False

    def mark_not_ready(self, now: float, reason: str) -> bool:
        """Health report: not ready, because ``reason``. READY -> IDLE; in RUNNING or
        PAUSED a procedure cannot go on without health, so it faults (source "health").
        True on a change."""
        now = _check_now(now)
        reason = str(reason) or "not ready"
        with self._lock:
            self._not_ready = reason
            if self._state is SafetyState.READY:
                self._go(now, SafetyState.IDLE, "health", reason)
                return True
            if self._state in (SafetyState.RUNNING, SafetyState.PAUSED):
                return self.fault(now, "health", reason)
            return False

    # -- operator requests ----------------------------------------------------------------
    def start(self, now: float, who: str, reason: str = "procedure started") -> None:
        """READY -> RUNNING, on ``who``'s request."""
        now = _check_now(now)
        with self._lock:
            if self._state is not SafetyState.READY:
                raise self._refuse("start")
            who = _operator(who, "start")
            if self._interrupted is not None:
                raise StateError(
                    "cannot start: the procedure started by "
                    f"{self._interrupted['by']} was interrupted by a stop "
                    f"({self._interrupted['reason']}); resume or abort it first")
            if self._stop.latched:  # defensive: the stop was triggered behind our back
                raise StateError("cannot start while the latched stop is latched "
                                 f"({self._stop.first}); reset first")
            self._operator = who
            self._go(now, SafetyState.RUNNING, who, reason)

    def pause(self, now: float, who: str, reason: str = "paused") -> bool:
        """RUNNING -> PAUSED (robot holds still); a no-op when already PAUSED. True on a
        change. An empty ``who`` is recorded as "(unnamed)": a hold is never refused for
        a missing name."""
        now = _check_now(now)
        with self._lock:
            if self._state is SafetyState.PAUSED:
                return False
            if self._state is not SafetyState.RUNNING:
                raise self._refuse("pause")
            self._go(now, SafetyState.PAUSED, _unnamed(who), reason)
            return True

    def resume(self, now: float, who: str, reason: str = "resumed") -> None:
        """PAUSED -> RUNNING, on ``who``'s request; or READY -> RUNNING when a latched
        stop interrupted the procedure (:attr:`interrupted`) and the cell was reset: it
        goes on from where it stood."""
        now = _check_now(now)
        with self._lock:
            paused = self._state is SafetyState.PAUSED
            if not paused and not (self._state is SafetyState.READY
                                   and self._interrupted is not None):
                raise self._refuse("resume")
            who = _operator(who, "resume")
            if self._stop.latched:
                raise StateError("cannot resume while the latched stop is latched "
                                 f"({self._stop.first}); reset first")
            if not paused:
                self._operator = who
                reason = (f"{reason}: procedure interrupted by "
                          f"{self._interrupted['reason']}" if self._interrupted else reason)
            self._interrupted = None
            self._go(now, SafetyState.RUNNING, who, reason)

    def abort(self, now: float, who: str, reason: str = "procedure aborted") -> None:
        """RUNNING or PAUSED -> READY: the procedure ends, the robot holds. A procedure a
        latched stop interrupted (:attr:`interrupted`) is dropped in any state, which
        stays as it is (a latch still needs its reset)."""
        now = _check_now(now)
        with self._lock:
            if self._state not in (SafetyState.RUNNING, SafetyState.PAUSED):
                if self._interrupted is None:
                    raise self._refuse("abort")
                was = self._interrupted
                self._interrupted = None
                self._history.append(Transition(now, self._state, self._state,
                                                _unnamed(who), f"{reason} (interrupted by "
                                                f"{was['reason']})"))
                log.info("interrupted procedure aborted by %s", _unnamed(who))
                return
            self._operator = None
            self._interrupted = None
            self._go(now, SafetyState.READY, _unnamed(who), reason)

    # -- latching (never raise) -----------------------------------------------------------
    def fault(self, now: float, source: str, reason: str) -> bool:
        """A watchdog or limit tripped: any state -> FAULT, except ESTOP which outranks it
        (the cause is recorded all the same). Fires the latched stop before returning.
        Never raises. True when the state changed."""
        return self._latch(now, SafetyState.FAULT, "fault", source, reason)

    def estop(self, now: float, source: str, reason: str) -> bool:
        """Emergency stop (input or REST): any state -> ESTOP. Fires the latched stop
        before returning. Never raises. True when the state changed."""
        return self._latch(now, SafetyState.ESTOP, "estop", source, reason)

    def _latch(self, now: float, to: SafetyState, kind: str, source: str,
               reason: str) -> bool:
        t = _safe_float(now)
        source, reason = _safe_str(source, "unknown"), _safe_str(reason, "unspecified")
        with self._lock:
            changed = False
            try:
                # ESTOP outranks FAULT: a fault never leaves ESTOP
                if self._state in (SafetyState.RUNNING, SafetyState.PAUSED):
                    self._interrupted = {"by": self._operator, "time": _json_time(t),
                                         "reason": f"{source}: {reason}"}
                    self._operator = None
                if self._state is not to and self._state is not SafetyState.ESTOP:
                    self._go(t, to, source, reason)
                    changed = True
                self._add_cause(t, kind, source, reason)
            except Exception:  # bookkeeping must not keep the robot moving
                log.exception("safety bookkeeping failed while latching %s", to.value)
                if self._state is not SafetyState.ESTOP:
                    self._state = to
            # inside the lock: a reset cannot slip in before the stop is commanded. A state
            # change while latched (FAULT -> ESTOP) tells every handler again
            try:
                self._stop.trigger(t, source, reason, escalate=changed)
            except Exception:  # LatchedStop.trigger never raises; belt and braces
                log.exception("latched stop raised")
            return changed

    def reset(self, now: float, who: str, *, estop_released: bool,
              faults_cleared: bool) -> None:
        """FAULT or ESTOP -> IDLE, clearing the latched stop and the causes.

        ``estop_released``: the e-stop input reads released. ``faults_cleared``: no
        watchdog or limit condition is present now. Both must be True (the caller reads
        them just before), and ``who`` names the operator. READY follows on the next
        healthy report.
        """
        now = _check_now(now)
        with self._lock:
            if self._state not in LATCHED:
                raise StateError(f"cannot reset while in {self._state.value}: "
                                 "nothing is latched")
            who = _operator(who, "reset")
            if estop_released is not True:
                raise StateError(f"cannot reset while in {self._state.value}: the e-stop "
                                 "input is still pressed; release it first")
            if faults_cleared is not True:
                raise StateError(f"cannot reset while in {self._state.value}: the fault "
                                 f"condition has not cleared ({self._causes_text()})")
            self._stop.clear(now, who)
            causes = "; ".join(str(c) for c in self._causes.values())
            self._causes.clear()
            self._dropped_causes = 0
            self._operator = None
            self._go(now, SafetyState.IDLE, who, f"reset (was: {causes or 'no cause'})")
