"""Simulated arm: the TCP as a Cartesian point mass with speed and acceleration limits.

Translation and rotation are limited separately: ``max_speed`` (m/s) and ``max_accel``
(m/s^2) bound the norm of the linear velocity and of its rate of change, and
``max_angular_speed`` (rad/s) and ``max_angular_accel`` (rad/s^2) those of the angular
velocity. The orientation is a ``scipy.spatial.transform.Rotation``; the angular velocity is
expressed in the base frame, so ``R(t + h) = exp(w h) R(t)``.

Nothing moves on its own: the simulated cell (or a test) advances the clock and calls
:meth:`SimArm.advance`. Commands behave like their ur-rtde models:

- ``servo(T, dt)`` sets a target pose. The TCP heads for it at the speed that would cover the
  remaining distance in ``dt``, capped by the speed limit and by a braking speed
  ``sqrt(a d)`` (braking at half the acceleration limit, which leaves room for the
  discrete-time integration not to overshoot).
- ``speed(twist, accel)`` ramps to a twist (clamped to the speed limits, as the arm's own
  limits would) at ``accel`` (capped at ``max_accel``; the angular ramp uses the same fraction
  of ``max_angular_accel``) and keeps it.
- ``stop()`` ramps both velocities to zero at the acceleration limits, then holds the pose.
- The watchdog: when a servo or speed motion has received neither a motion command nor a
  ``kick()`` for ``watchdog_timeout`` seconds (driver clock), the arm stops as on ``stop()``.

``stop()`` does not latch: a later ``servo``/``speed`` moves again (the latched stop lives in
the safety layer). Fault injections for tests: :meth:`inject_protective_stop`,
:meth:`inject_emergency_stop`, :meth:`inject_disconnect` (the arm goes on with its last
command until its watchdog stops it, as a real one would), :meth:`reconnect`,
:meth:`clear_protective_stop`, :meth:`clear_emergency_stop`, and :meth:`freeze` (the reported
state stops updating: a silent driver).

The force sensor reads what :meth:`SimArm.apply_wrench` last set, or, with the
``force_source`` option, what that callable returns for the state each :meth:`advance`
reaches: a scripted operator's hand inside a process the test cannot reach into (the
control process builds its own drivers).
"""

from __future__ import annotations

import collections
import logging
import math
import threading
from collections.abc import Callable
from typing import NamedTuple

import numpy as np
from scipy.spatial.transform import Rotation

from ..clock import Clock, WallClock
from ..errors import DriverInitError, DriverIOError
from ..lifecycle import LifecycleState
from .base import Arm, ArmCommandError, ArmState, check_pose

__all__ = ["DEFAULT_HOME", "CommandRecord", "SimArm"]

log = logging.getLogger(__name__)

#: Default TCP pose in the base frame: 0.4 m forward, 0.3 m up, tool z pointing down.
DEFAULT_HOME = np.array(
    [
        [1.0, 0.0, 0.0, 0.4],
        [0.0, -1.0, 0.0, 0.0],
        [0.0, 0.0, -1.0, 0.3],
        [0.0, 0.0, 0.0, 1.0],
    ]
)


class CommandRecord(NamedTuple):
    """One ``servo``/``speed``/``stop`` call: clock time (s) and kind. Calls that were
    refused are recorded too: the log says what the caller asked for."""

    time: float
    kind: str


def _limit(value: float, what: str, unit: str) -> float:
    try:
        out = float(value)
    except (TypeError, ValueError):
        out = math.nan
    if isinstance(value, bool) or not math.isfinite(out) or out <= 0.0:
        raise DriverInitError(f"{what} must be a finite number of {unit} > 0, got {value!r}")
    return out


def _clip_norm(v: np.ndarray, limit: float) -> np.ndarray:
    n = float(np.linalg.norm(v))
    return v * (limit / n) if n > limit else v


def _approach_speed(distance: float, limit: float, accel: float, horizon: float) -> float:
    # The smallest of: the speed limit, a speed that still brakes in time (at accel / 2),
    # and the speed that covers the distance in one horizon (so it never overshoots a step).
    return min(limit, math.sqrt(accel * distance), distance / horizon)


class SimArm(Arm):
    """A simulated UR-like arm; see the module docstring for the dynamics.

    Args:
        name: for messages and logs.
        clock: timestamps and the watchdog; a :class:`VirtualClock` in simulation
            (default: the wall clock).
        home: (4, 4) initial ``T_B_tcp``, metres.
        max_speed: m/s; max_angular_speed: rad/s; max_accel: m/s^2;
        max_angular_accel: rad/s^2.
        watchdog_timeout: seconds without a motion command or kick before the arm stops.
        max_step: longest integration step, seconds; ``advance`` subdivides longer periods.
        log_size: entries kept in :attr:`command_log` (oldest dropped).
        force_source: optional ``f(t, T_B_tcp) -> wrench``, called at the end of each
            :meth:`advance` with the clock time (s) and the new TCP pose (4x4, m); its
            3 or 6 values (N, N m, base frame) become the force sensor's reading, as
            :meth:`apply_wrench` would set them. Must be picklable to reach a control
            process. A value that is not 3 or 6 finite numbers reads as zero (logged).
    """

    def __init__(
        self,
        name: str = "arm",
        clock: Clock | None = None,
        home: np.ndarray | None = None,
        max_speed: float = 0.25,
        max_angular_speed: float = 1.0,
        max_accel: float = 1.0,
        max_angular_accel: float = 4.0,
        watchdog_timeout: float = 0.05,
        max_step: float = 0.002,
        log_size: int = 10_000,
        force_source: Callable[[float, np.ndarray], np.ndarray] | None = None,
    ) -> None:
        super().__init__(name)
        self.clock: Clock = WallClock() if clock is None else clock
        if not callable(getattr(self.clock, "now", None)):
            raise DriverInitError(f"clock must have now() -> seconds, got {clock!r}")
        try:
            home_T = check_pose(DEFAULT_HOME if home is None else home, "home")
        except ArmCommandError as exc:
            raise DriverInitError(f"arm {name!r}: {exc}") from None
        self.max_speed = _limit(max_speed, "max_speed", "m/s")
        self.max_angular_speed = _limit(max_angular_speed, "max_angular_speed", "rad/s")
        self.max_accel = _limit(max_accel, "max_accel", "m/s^2")
        self.max_angular_accel = _limit(max_angular_accel, "max_angular_accel", "rad/s^2")
        self.watchdog_timeout = _limit(watchdog_timeout, "watchdog_timeout", "seconds")
        self.max_step = _limit(max_step, "max_step", "seconds")
        if isinstance(log_size, bool) or not isinstance(log_size, int) or log_size < 1:
            raise DriverInitError(f"log_size must be an integer >= 1, got {log_size!r}")
        if force_source is not None and not callable(force_source):
            raise DriverInitError(f"force_source must be callable, got {force_source!r}")
        self._force_source = force_source

        self._lock = threading.Lock()
        # Physical state (base frame).
        self._p = home_T[:3, 3].copy()
        self._R = Rotation.from_matrix(home_T[:3, :3])
        self._v = np.zeros(3)
        self._w = np.zeros(3)
        # Motion mode: "hold" | "servo" | "speed" | "stop", and its set points.
        self._mode = "hold"
        self._target_p = self._p.copy()
        self._target_R = self._R
        self._horizon = self.max_step
        self._cmd_v = np.zeros(3)
        self._cmd_w = np.zeros(3)
        self._cmd_accel = self.max_accel
        self._cmd_angular_accel = self.max_angular_accel
        self._last_feed = -math.inf  # last motion command or kick, clock seconds
        # Link and controller flags.
        self._life = LifecycleState()  # changed under _lock
        self._connected = False
        self._protective = False
        self._estop = False
        self._frozen = False
        # What state() reports: updated by advance() unless frozen.
        self._snap_time = float(self.clock.now())
        self._snap_T = home_T
        self._snap_twist = np.zeros(6)
        self._wrench = np.zeros(6)  # what the simulated force sensor reads (apply_wrench)
        self._log: collections.deque[CommandRecord] = collections.deque(maxlen=log_size)
        self.watchdog_trips = 0  # times the watchdog stopped the arm

    # -- lifecycle ----------------------------------------------------------------------------

    async def start(self) -> None:
        with self._lock:
            self._life.start(
                f"arm {self.name!r}: start() called twice (build a new arm after close)"
            )
            self._connected = True
            self._snap_time = float(self.clock.now())

    async def close(self) -> None:
        self.stop()
        with self._lock:
            self._life.close()
            self._connected = False

    # -- state --------------------------------------------------------------------------------

    def state(self) -> ArmState:
        with self._lock:
            return ArmState(
                timestamp=self._snap_time,
                T_B_tcp=self._snap_T,
                tcp_speed=self._snap_twist,
                connected=self._connected,
                protective_stop=self._protective,
                emergency_stop=self._estop,
                ready=self._refusal() is None,
                tcp_force=self._wrench,
            )

    @property
    def command_log(self) -> list[CommandRecord]:
        """Every ``servo``/``speed``/``stop`` call, oldest first (bounded by ``log_size``)."""
        with self._lock:
            return list(self._log)

    def _refusal(self) -> str | None:
        # Why a motion command cannot be obeyed now, or None. Call under the lock.
        reason = self._life.refusal()  # "not started" or "closed"
        if reason is not None:
            return reason
        if not self._connected:
            return "disconnected"
        if self._estop:
            return "in emergency stop"
        if self._protective:
            return "in protective stop"
        return None

    # -- commands -----------------------------------------------------------------------------

    def _servo(self, T_B_tcp: np.ndarray, dt: float) -> None:
        with self._lock:
            now = float(self.clock.now())
            self._log.append(CommandRecord(now, "servo"))
            self._check_ready("servo")
            self._mode = "servo"
            self._target_p = T_B_tcp[:3, 3].copy()
            self._target_R = Rotation.from_matrix(T_B_tcp[:3, :3])
            self._horizon = dt
            self._last_feed = now

    def _speed(self, twist: np.ndarray, accel: float) -> None:
        with self._lock:
            now = float(self.clock.now())
            self._log.append(CommandRecord(now, "speed"))
            self._check_ready("speed")
            self._mode = "speed"
            self._cmd_v = _clip_norm(twist[:3], self.max_speed)
            self._cmd_w = _clip_norm(twist[3:], self.max_angular_speed)
            fraction = min(accel, self.max_accel) / self.max_accel
            self._cmd_accel = fraction * self.max_accel
            self._cmd_angular_accel = fraction * self.max_angular_accel
            self._last_feed = now

    def _stop(self) -> None:
        with self._lock:
            self._log.append(CommandRecord(float(self.clock.now()), "stop"))
            unreachable = self._life.running and not self._connected
            if not unreachable and self._mode != "hold":
                self._mode = "stop"
        if unreachable:
            # Nothing reaches the arm; its watchdog stops it. Not an exception: stop() is on
            # the latched-stop path.
            log.warning("arm %r: stop() while disconnected; the watchdog stops it", self.name)

    def kick(self) -> None:
        with self._lock:
            # A stopped (protective / emergency) arm can still be kicked: the link is up.
            if not self._life.running or not self._connected:
                raise DriverIOError(f"arm {self.name!r}: kick() failed: arm {self._refusal()}")
            self._last_feed = float(self.clock.now())

    def _check_ready(self, what: str) -> None:
        reason = self._refusal()
        if reason is not None:
            raise DriverIOError(f"arm {self.name!r}: {what} refused: arm {reason}")

    # -- simulation -----------------------------------------------------------------------------

    def advance(self, dt: float) -> None:
        """Integrate the TCP over ``dt`` seconds, the interval that ends at the clock's
        current time (the caller advances the clock).

        The watchdog acts at the instant it expires, as a controller on its own machine
        would, not when the caller comes back: when the interval spans
        ``last command + watchdog_timeout``, the motion runs up to that instant and the
        rest of ``dt`` brakes. So a host that stalls (its process stopped for seconds, then
        resumed with one long ``advance``) sees the arm that the real controller's watchdog
        would have left. Integrates in steps of at most ``max_step``; the reported state
        gets the clock's time unless frozen.
        """
        dt = float(dt)
        if not math.isfinite(dt) or dt < 0.0:
            raise ValueError(f"dt must be a finite number of seconds >= 0, got {dt!r}")
        with self._lock:
            now = float(self.clock.now())
            silence = now - self._last_feed
            tripped = self._mode in ("servo", "speed") and silence > self.watchdog_timeout
            # seconds of the interval before the watchdog expired (all of it if it did not)
            before = min(dt, max(0.0, dt - (silence - self.watchdog_timeout))) if tripped \
                else dt
        if tripped:  # logged outside the lock: a log handler may do slow I/O
            log.warning(
                "arm %r: watchdog: no command for %.3f s > %.3f s; stopping",
                self.name, silence, self.watchdog_timeout,
            )
        self._integrate(before)
        if tripped:
            with self._lock:
                if self._mode in ("servo", "speed"):
                    self._mode = "stop"
                    self.watchdog_trips += 1
            self._integrate(dt - before)
        with self._lock:
            if not self._frozen:
                T = np.eye(4)
                T[:3, :3] = self._R.as_matrix()
                T[:3, 3] = self._p
                self._snap_T = T
                self._snap_twist = np.concatenate([self._v, self._w])
                self._snap_time = now
            T_now = self._snap_T
        if self._force_source is not None:  # called outside the lock: it is user code
            self._read_force_source(now, T_now)

    def _integrate(self, dt: float) -> None:
        """Move over ``dt`` s in the current mode, in steps of at most ``max_step``."""
        steps = max(1, math.ceil(dt / self.max_step - 1e-9)) if dt > 0.0 else 0
        for _ in range(steps):
            # The lock is taken per step, so a stop() never waits for a long advance().
            with self._lock:
                self._step(dt / steps)

    def _read_force_source(self, now: float, T_B_tcp: np.ndarray) -> None:
        try:
            w = np.asarray(self._force_source(now, T_B_tcp.copy()), dtype=float).reshape(-1)
        except Exception:
            log.exception("arm %r: force_source raised; the sensor reads zero", self.name)
            w = np.zeros(6)
        if w.size == 3:
            w = np.concatenate([w, np.zeros(3)])
        if w.shape != (6,) or not np.all(np.isfinite(w)):
            log.error("arm %r: force_source gave %r, not 3 or 6 finite numbers; the sensor "
                      "reads zero", self.name, w)
            w = np.zeros(6)
        with self._lock:
            self._wrench = w

    def _step(self, h: float) -> None:
        # One semi-implicit Euler step: velocities move toward their set points within the
        # acceleration limits, then the pose moves with the new velocities.
        a, alpha = self.max_accel, self.max_angular_accel
        if self._mode == "hold":
            return
        if self._mode == "servo":
            horizon = max(self._horizon, h)
            e = self._target_p - self._p
            d = float(np.linalg.norm(e))
            v_set = e * (_approach_speed(d, self.max_speed, a, horizon) / d) if d > 0 else e
            e_r = (self._target_R * self._R.inv()).as_rotvec()
            d_r = float(np.linalg.norm(e_r))
            w_set = (
                e_r * (_approach_speed(d_r, self.max_angular_speed, alpha, horizon) / d_r)
                if d_r > 0
                else e_r
            )
        elif self._mode == "speed":
            v_set, w_set = self._cmd_v, self._cmd_w
            a, alpha = self._cmd_accel, self._cmd_angular_accel
        else:  # "stop"
            v_set, w_set = np.zeros(3), np.zeros(3)
        self._v = self._v + _clip_norm(v_set - self._v, a * h)
        self._w = self._w + _clip_norm(w_set - self._w, alpha * h)
        self._p = self._p + self._v * h
        if np.any(self._w):
            self._R = Rotation.from_rotvec(self._w * h) * self._R
        if self._mode == "stop" and not np.any(self._v) and not np.any(self._w):
            self._mode = "hold"

    # -- fault injection (tests, simulated cell) ----------------------------------------------

    def apply_wrench(self, wrench: np.ndarray) -> None:
        """Set what the simulated TCP force sensor reads (base frame, N and N m): the
        operator's push, e.g. from :class:`oralnav.sim.world.hand.ScriptedHand`. It does not
        move the arm by itself; the admittance controller turns it into motion."""
        w = np.asarray(wrench, dtype=float).reshape(-1)
        if w.size == 3:
            w = np.concatenate([w, np.zeros(3)])
        if w.shape != (6,) or not np.all(np.isfinite(w)):
            raise ArmCommandError(f"arm {self.name!r}: a wrench is 3 or 6 finite numbers, "
                                  f"got {wrench!r}")
        with self._lock:
            self._wrench = w

    def inject_protective_stop(self) -> None:
        """The arm enters a protective stop: it brakes, and refuses motion until cleared."""
        with self._lock:
            self._protective = True
            if self._mode != "hold":
                self._mode = "stop"

    def clear_protective_stop(self) -> None:
        with self._lock:
            self._protective = False

    def inject_emergency_stop(self) -> None:
        """The arm's own e-stop opens: it brakes, and refuses motion until cleared."""
        with self._lock:
            self._estop = True
            if self._mode != "hold":
                self._mode = "stop"

    def clear_emergency_stop(self) -> None:
        with self._lock:
            self._estop = False

    def inject_disconnect(self) -> None:
        """The link drops: commands are refused; the arm keeps its last command until its
        watchdog stops it."""
        with self._lock:
            self._connected = False

    def reconnect(self) -> None:
        """The link is back (only while started and not closed)."""
        with self._lock:
            if self._life.running:
                self._connected = True

    def freeze(self) -> None:
        """The driver goes silent: ``state()`` keeps returning the last snapshot."""
        with self._lock:
            self._frozen = True

    def unfreeze(self) -> None:
        with self._lock:
            self._frozen = False
