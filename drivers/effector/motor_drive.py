"""The tendon-driven wrist on an external motor drive, reached over a fieldbus: what the
CANopen and Modbus backends share.

A cycle thread exchanges the motor targets and readings with the drive every ``1/rate_hz``
s; :meth:`~MotorDriveEffector.command`, :meth:`~MotorDriveEffector.stop` and
:meth:`~MotorDriveEffector.state` only touch what that thread stores, so the 500 Hz control
loop never waits on the bus. Backends implement four hooks, all called from the thread:
``_open`` (connect, configure and enable the drive), ``_exchange`` (write the targets, read
the positions and the drive's fault), ``_close_link`` and ``_reset_fault``.

Units. Drive positions are integer encoder counts; motor angles are rad (the kinematics'
``m``). ``counts = round((m + pretension) * counts_per_rad)`` per motor: the **pretension**
(rad, per motor, from the configuration) is the extra motor angle that keeps each tendon taut
at the joints' zero; it is added to every target and taken off every reading, so joints and
motors above it are those of :class:`~.kinematics.WristKinematics`.

Faults. A link that cannot be opened or is lost, a bus that stays silent for
``silence_timeout`` s, or a drive reporting a fault (an EMCY, a fault bit, a Modbus exception)
shows in :attr:`EffectorState.fault` (``connected`` False for the first two); the control loop
latches its stop on either. A lost link is reopened with back-off. The fault shown is what
the drive reports now: a drive latches its own faults (a CiA 402 drive stays in FAULT) until
:meth:`~MotorDriveEffector.reset_fault` runs its reset sequence (an operator's decision, never
automatic); a refused transaction (a Modbus exception) shows for as long as it lasts.
"""

from __future__ import annotations

import abc
import logging
import math
import threading
import time
from dataclasses import dataclass

import anyio
import anyio.to_thread
import numpy as np

from ..clock import Clock, WallClock
from ..errors import DriverError, DriverInitError, DriverIOError
from ..lifecycle import LifecycleState
from .base import EffectorState, EndEffector
from .kinematics import WristKinematics

__all__ = ["DriveReading", "MotorDriveEffector"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DriveReading:
    """What one exchange with the drive returned.

    Attributes:
        counts: (4,) motor positions, encoder counts (int64).
        fault: the drive's fault, in words (None when healthy).
    """

    counts: np.ndarray
    fault: str | None = None


def _per_motor(value: object, what: str, name: str, *, positive: bool) -> np.ndarray:
    try:
        arr = np.broadcast_to(np.asarray(value, dtype=float), (4,)).copy()
    except (TypeError, ValueError):
        arr = np.full(4, np.nan)
    if not np.isfinite(arr).all() or (positive and not (arr > 0).all()):
        rule = "finite and > 0" if positive else "finite"
        raise DriverInitError(f"effector {name!r}: {what} must be one or 4 {rule} numbers, "
                              f"got {value!r}")
    return arr


class MotorDriveEffector(EndEffector):
    """Base of the fieldbus wrists (see the module docstring).

    Args:
        kinematics: coupling and joint/motor limits (default: the example kinematics).
        counts_per_rad: encoder counts per motor radian, one or (4,).
        pretension: rad per motor added to targets and taken off readings, one or (4,).
        rate_hz: exchanges per second.
        silence_timeout: s without a successful exchange after which the link is lost.
        connect_timeout: s ``start()`` waits for the first reading; a drive that has not
            answered by then leaves the wrist disconnected (a fault) and the thread retries.
        reconnect_backoff: (first, max) s between attempts to reopen the link, doubling.
        clock: timestamps (default: the wall clock).
        name: for messages and logs.
    """

    def __init__(self, kinematics: WristKinematics | None = None, *,
                 counts_per_rad: float | np.ndarray = 4096 / (2 * math.pi),
                 pretension: float | np.ndarray = 0.0, rate_hz: float = 200.0,
                 silence_timeout: float = 0.1, connect_timeout: float = 2.0,
                 reconnect_backoff: tuple[float, float] = (0.1, 2.0),
                 clock: Clock | None = None, name: str = "effector") -> None:
        kin = WristKinematics() if kinematics is None else kinematics
        if not isinstance(kin, WristKinematics):
            raise DriverInitError(f"kinematics must be a WristKinematics, got {kin!r}")
        super().__init__(kin, name)
        self.counts_per_rad = _per_motor(counts_per_rad, "counts_per_rad", name, positive=True)
        self.pretension = _per_motor(pretension, "pretension (rad)", name, positive=False)
        for key, v in (("rate_hz", rate_hz), ("silence_timeout", silence_timeout),
                       ("connect_timeout", connect_timeout)):
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
                raise DriverInitError(f"effector {name!r}: {key} must be > 0, got {v!r}")
        lo, hi = reconnect_backoff
        if not (0 < lo <= hi and math.isfinite(hi)):
            raise DriverInitError(f"effector {name!r}: reconnect_backoff must be "
                                  f"0 < first <= max, got {reconnect_backoff!r}")
        self.period = 1.0 / float(rate_hz)
        self.silence_timeout = float(silence_timeout)
        self.connect_timeout = float(connect_timeout)
        self._backoff = (float(lo), float(hi))
        self.clock: Clock = WallClock() if clock is None else clock
        self._lock = threading.Lock()
        self._quit = threading.Event()
        self._reset_wanted = threading.Event()
        self._thread: threading.Thread | None = None
        self._life = LifecycleState()  # changed under _lock; _quit tells the thread
        self._link = False                          # the thread holds an open link
        self._target: np.ndarray | None = None      # counts to send; None: hold
        self._counts: np.ndarray | None = None      # the latest reading
        self._time: float | None = None             # clock time of the latest reading
        self._link_fault: str | None = None         # why the link is down
        self._drive_fault: str | None = None        # the drive's fault, as last read
        self.exchanges = 0
        self.reconnects = 0

    # -- units -----------------------------------------------------------------------------
    def motors_to_counts(self, m: np.ndarray) -> np.ndarray:
        """Motor angles (rad) -> drive counts, pretension included."""
        return np.rint((np.asarray(m, float) + self.pretension) * self.counts_per_rad
                       ).astype(np.int64)

    def counts_to_motors(self, counts: np.ndarray) -> np.ndarray:
        """Drive counts -> motor angles (rad), pretension taken off."""
        return np.asarray(counts, float) / self.counts_per_rad - self.pretension

    # -- the contract ----------------------------------------------------------------------
    def state(self) -> EffectorState:
        now = float(self.clock.now())
        with self._lock:
            counts, t = self._counts, self._time
            connected = self._life.running and self._link \
                and counts is not None
            fault = self._drive_fault
            if connected and t is not None and now - t > self.silence_timeout:
                connected = False
                fault = (f"drive silent for {now - t:.3f} s "
                         f"(limit {self.silence_timeout:.3f} s)")
            elif not connected:  # why the link is down comes first
                fault = self._link_fault or fault or "not connected"
        motors = (self.counts_to_motors(counts) if counts is not None
                  else np.zeros(4) + np.nan)
        joints = (self.kinematics.motors_to_joints(motors) if counts is not None
                  else np.zeros(4) + np.nan)
        return EffectorState(timestamp=t if t is not None else 0.0, joints=joints,
                             motors=motors, connected=connected, fault=fault)

    def _command(self, q: np.ndarray) -> None:
        counts = self.motors_to_counts(self.kinematics.joints_to_motors(q))
        with self._lock:
            reason = self._refusal()
            if reason is not None:
                raise DriverIOError(f"effector {self.name!r}: command refused: {reason}")
            self._target = counts

    def _stop(self) -> None:
        with self._lock:
            self._target = None if self._counts is None else self._counts.copy()

    def _refusal(self) -> str | None:
        reason = self._life.refusal()  # "not started" or "closed"
        if reason is not None:
            return reason
        if not self._link or self._counts is None:
            return f"disconnected ({self._link_fault or 'no reading yet'})"
        if self._drive_fault is not None:
            return f"drive fault: {self._drive_fault}"
        return None

    def reset_fault(self) -> None:
        """Ask the thread to clear the drive's fault (its fault-reset sequence) and hold the
        current position. The operator's decision; the fault clears only if the drive's
        does."""
        self._reset_wanted.set()

    async def start(self) -> None:
        with self._lock:
            # running at once: the thread reports the link's faults from here on
            self._life.start(f"effector {self.name!r}: start() called twice "
                             "(build a new one after close)")
        self._thread = threading.Thread(target=self._run, name=f"drive-{self.name}",
                                        daemon=True)
        self._thread.start()
        await anyio.to_thread.run_sync(self._wait_first_reading)
        st = self.state()
        if not st.connected:
            log.warning("effector %r not connected after %.1f s: %s", self.name,
                        self.connect_timeout, st.fault)

    def _wait_first_reading(self) -> None:
        deadline = time.monotonic() + self.connect_timeout
        while time.monotonic() < deadline and not self._quit.is_set():
            with self._lock:
                if self._counts is not None and self._link:
                    return
            time.sleep(0.005)

    async def close(self) -> None:
        self.stop()
        if self._thread is not None and self._link:
            await anyio.sleep(2 * self.period)  # let the hold reach the drive
        with self._lock:
            self._life.close()
        self._quit.set()
        thread, self._thread = self._thread, None
        if thread is not None:
                await anyio.to_thread.run_sync(thread.join, 5.0)

    # -- the cycle thread ------------------------------------------------------------------
    def _run(self) -> None:
        delay = self._backoff[0]
        opened_once = False
        while not self._quit.is_set():
            if not self._link:
                try:
                    self._open()
                except DriverError as exc:
                    self._lose(str(exc))
                    self._quit.wait(delay)
                    delay = min(2 * delay, self._backoff[1])
                    continue
                with self._lock:
                    self._link, self._link_fault = True, None
                    self._target = None  # after (re)connecting, hold where the drive is
                self.reconnects += opened_once
                opened_once, delay = True, self._backoff[0]
            t0 = time.monotonic()
            if self._reset_wanted.is_set():
                self._reset_wanted.clear()
                try:
                    self._reset_fault()
                except DriverError as exc:
                    log.warning("effector %r: fault reset failed: %s", self.name, exc)
                else:
                    with self._lock:
                        self._target = None  # hold where the drive is
            with self._lock:
                target = None if self._target is None else self._target.copy()
            try:
                reading = self._exchange(target)
            except DriverError as exc:
                self._lose(str(exc))
                continue
            now = float(self.clock.now())
            with self._lock:
                self._counts = np.asarray(reading.counts, dtype=np.int64).copy()
                self._time = now
                changed = reading.fault != self._drive_fault
                self._drive_fault = reading.fault
                if reading.fault is not None:
                    self._target = None  # a faulted drive holds; so does what we send
                if self._target is None:
                    self._target = self._counts.copy()
            if changed and reading.fault:
                log.warning("effector %r: drive fault: %s", self.name, reading.fault)
            elif changed:
                log.info("effector %r: drive fault cleared", self.name)
            self.exchanges += 1
            self._quit.wait(max(0.0, self.period - (time.monotonic() - t0)))
        self._close_quietly()

    def _lose(self, why: str) -> None:
        with self._lock:
            was = self._link
            self._link, self._link_fault = False, why
        if was:
            log.warning("effector %r: link lost: %s", self.name, why)
        self._close_quietly()

    def _close_quietly(self) -> None:
        try:
            self._close_link()
        except Exception:  # the link is gone either way
            log.debug("effector %r: closing the link", self.name, exc_info=True)

    # -- backend hooks (cycle thread only) -------------------------------------------------
    @abc.abstractmethod
    def _open(self) -> None:
        """Connect, configure and enable the drive; raise DriverError naming what failed."""

    @abc.abstractmethod
    def _exchange(self, target: np.ndarray | None) -> DriveReading:
        """Send ``target`` counts (None: hold the current position) and read the drive;
        raise DriverIOError when the link is lost (a drive fault is a reading, not an
        exception)."""

    @abc.abstractmethod
    def _close_link(self) -> None:
        """Disable the drive if reachable and close the link; idempotent."""

    @abc.abstractmethod
    def _reset_fault(self) -> None:
        """Run the drive's fault-reset sequence and re-enable it."""

