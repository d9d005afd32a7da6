"""Simulated wrist: each joint moves toward its commanded angle at a bounded speed.

The simulated cell (or a test) advances the clock and calls :meth:`SimEffector.advance`.
Motor angles follow from the joints through the kinematics. Injections for tests:
:meth:`SimEffector.inject_silence` (the reported state stops updating),
:meth:`SimEffector.inject_fault` (the device holds and refuses commands),
:meth:`SimEffector.inject_disconnect`, and :meth:`SimEffector.clear` (ends them all).
"""

from __future__ import annotations

import collections
import logging
import math
import threading
from typing import NamedTuple

import numpy as np

from ..clock import Clock, WallClock
from ..errors import DriverInitError, DriverIOError
from ..lifecycle import LifecycleState
from .base import EffectorState, EndEffector
from .kinematics import JOINTS, WristKinematics

__all__ = ["CommandRecord", "SimEffector"]

log = logging.getLogger(__name__)


class CommandRecord(NamedTuple):
    """One ``command``/``stop`` call: clock time (s) and kind (refused calls included)."""

    time: float
    kind: str


class SimEffector(EndEffector):
    """A simulated tendon-driven wrist.

    Args:
        kinematics: coupling and limits (default: the example :class:`WristKinematics`).
        clock: timestamps (default: the wall clock).
        max_joint_speed: rad/s, one value for all joints or (4,) per joint.
        initial: (4,) starting joints, rad, within limits (default: zero, moved into the
            limits where zero is outside them).
        name: for messages and logs.
        log_size: entries kept in :attr:`command_log`.
    """

    def __init__(
        self,
        kinematics: WristKinematics | None = None,
        clock: Clock | None = None,
        max_joint_speed: float | np.ndarray = 2.0,
        initial: np.ndarray | None = None,
        name: str = "effector",
        log_size: int = 10_000,
    ) -> None:
        kin = WristKinematics() if kinematics is None else kinematics
        if not isinstance(kin, WristKinematics):
            raise DriverInitError(f"kinematics must be a WristKinematics, got {kin!r}")
        super().__init__(kin, name)
        self.clock: Clock = WallClock() if clock is None else clock
        if not callable(getattr(self.clock, "now", None)):
            raise DriverInitError(f"clock must have now() -> seconds, got {clock!r}")
        try:
            speed = np.broadcast_to(np.asarray(max_joint_speed, dtype=float), (4,)).copy()
        except (TypeError, ValueError):
            speed = np.full(4, np.nan)
        if not (np.isfinite(speed).all() and (speed > 0).all()):
            raise DriverInitError(
                f"max_joint_speed must be finite rad/s > 0 (one or {len(JOINTS)}), "
                f"got {max_joint_speed!r}"
            )
        self.max_joint_speed = speed
        if initial is None:
            initial = np.clip(np.zeros(4), kin.joint_min, kin.joint_max)
        try:
            q0 = kin.check_joints(initial)
        except ValueError as exc:
            raise DriverInitError(f"effector {name!r}: initial: {exc}") from None
        if isinstance(log_size, bool) or not isinstance(log_size, int) or log_size < 1:
            raise DriverInitError(f"log_size must be an integer >= 1, got {log_size!r}")

        self._lock = threading.Lock()
        self._q = q0
        self._target = q0.copy()
        self._life = LifecycleState()  # changed under _lock
        self._connected = False
        self._fault: str | None = None
        self._silent = False
        self._snap_time = float(self.clock.now())
        self._snap_q = q0.copy()
        self._log: collections.deque[CommandRecord] = collections.deque(maxlen=log_size)

    async def start(self) -> None:
        with self._lock:
            self._life.start(
                f"effector {self.name!r}: start() called twice (build a new one after close)"
            )
            self._connected = True
            self._snap_time = float(self.clock.now())

    async def close(self) -> None:
        self.stop()
        with self._lock:
            self._life.close()
            self._connected = False

    def state(self) -> EffectorState:
        with self._lock:
            return EffectorState(
                timestamp=self._snap_time,
                joints=self._snap_q,
                motors=self.kinematics.joints_to_motors(self._snap_q),
                connected=self._connected,
                fault=self._fault,
            )

    @property
    def command_log(self) -> list[CommandRecord]:
        """Every ``command``/``stop`` call (refused ones too), oldest first."""
        with self._lock:
            return list(self._log)

    def _command(self, q: np.ndarray) -> None:
        with self._lock:
            self._log.append(CommandRecord(float(self.clock.now()), "command"))
            reason = self._refusal()
            if reason is not None:
                raise DriverIOError(f"effector {self.name!r}: command refused: {reason}")
            self._target = q.copy()

    def _stop(self) -> None:
        with self._lock:
            self._log.append(CommandRecord(float(self.clock.now()), "stop"))
            unreachable = self._life.running and not self._connected
            if not unreachable:
                self._target = self._q.copy()
        if unreachable:  # logged outside the lock: a log handler may do slow I/O
            log.warning("effector %r: stop() while disconnected", self.name)

    def _refusal(self) -> str | None:
        reason = self._life.refusal()  # "not started" or "closed"
        if reason is not None:
            return reason
        if not self._connected:
            return "disconnected"
        if self._fault is not None:
            return f"device fault: {self._fault}"
        return None

    def advance(self, dt: float) -> None:
        """Move every joint toward its target by at most ``max_joint_speed * dt`` (the caller
        advances the clock); the reported state gets the clock's time unless silenced."""
        dt = float(dt)
        if not math.isfinite(dt) or dt < 0.0:
            raise ValueError(f"dt must be a finite number of seconds >= 0, got {dt!r}")
        with self._lock:
            step = self.max_joint_speed * dt
            self._q = self._q + np.clip(self._target - self._q, -step, step)
            if not self._silent:
                self._snap_q = self._q.copy()
                self._snap_time = float(self.clock.now())

    # -- injections ---------------------------------------------------------------------------

    def inject_silence(self) -> None:
        """The device goes silent: ``state()`` keeps returning the last snapshot."""
        with self._lock:
            self._silent = True

    def inject_fault(self, message: str) -> None:
        """The device reports a fault: it holds its position and refuses commands."""
        with self._lock:
            self._fault = str(message) or "fault"
            self._target = self._q.copy()

    def inject_disconnect(self) -> None:
        """The link drops: commands are refused, the wrist holds its last target."""
        with self._lock:
            self._connected = False

    def clear(self) -> None:
        """End every injection (silence, fault, disconnect while started)."""
        with self._lock:
            self._silent = False
            self._fault = None
            if self._life.running:
                self._connected = True
