"""The control loop: at a fixed rate, read the newest goal, check safety, servo the arm.

``ControlLoop.step(now)`` is one period, with no waiting and no I/O of its own (the drivers
do theirs, non-blocking). It runs in one of two ways:

- ``ControlProcess``: a process of its own that owns the arm and end-effector drivers and
  calls ``step`` on the wall clock at the configured rate; the daemon talks to it only
  through three shared records (``realtime/shm.py``). This is the production path: a thread
  in the daemon's process missed its 2 ms period by up to 2-3 ms while tracking ran (GIL;
  ``oralnav bench control`` charts both, docs/control_loop.md has the figures).
- in-process, on a virtual clock: tests and the deterministic simulation call ``step``
  themselves, advancing the simulated drivers between calls.

Per period the loop (1) reads the arm and wrist state; (2) trips the latched stop on a stop
request from the daemon, a disconnected or protective-stopped arm, a silent or faulted
driver, a stale fixture frame while guiding, or repeated deadline misses; (3) when
stopped, commands nothing at all; otherwise steps the servo setpoint toward the goal with
the speed limits and sends it, or, when holding (asked to, or because the goal was
computed from poses older than ``stale_pose``), only kicks the arm's watchdog. In GUIDE
mode the setpoint comes from the admittance inside the virtual fixture
(``control/guidance/guided_motion.py``), and the rod's collision alarm on the surrogate
model, or a TCP outside the fixture at the start, trips the stop too. It records each new
measured TCP in the arm history and each goal's capture-to-command latency, both for the
daemon. The plan arrives through ``set_guide`` (in the control process,
from the plan channel, ``realtime/plan_channel.py``), which refuses a new plan while a
guided motion runs; any latched stop ends the guided motion, so that a reset never
resumes it. The status record reports the guidance: active or not, the plan messages
taken and refused, the rod's clearance and where the head is on the planned axis.
"""

from __future__ import annotations

import inspect
import logging
import math
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from oralnav.control.errors import ControlError
from oralnav.control.guidance.guided_motion import GuidedMotion, GuideStep
from oralnav.drivers.arm import Arm, ArmState
from oralnav.drivers.effector import EffectorState, EndEffector
from oralnav.realtime.shm import SharedRecord, SharedRing, decode_reason, encode_reason
from oralnav.safety.limits import SpeedLimiter, WorkspaceBox
from oralnav.safety.watchdogs import DeadlineWatchdog, DriverSilenceWatchdog, StalePoseWatchdog

log = logging.getLogger(__name__)

#: Control modes the daemon may ask for. GUIDE: admittance inside the planned virtual
#: fixture (``ControlLoop.set_guide``), the operator's push measured by the arm's force
#: sensor; the goal is unused and ``T_B_F`` places the patient's model frame.
HOLD, MOVE, GUIDE = 0, 1, 2

#: A period off its nominal length by more than this counts as a miss in the status.
MISS_S = 0.001
#: Period-error histogram: bins of 25 us up to 5 ms, then one overflow bin.
HIST_BIN_S = 25e-6
HIST_BINS = 200

#: The daemon -> loop record: the goal (base frame) and what the loop may do with it.
NAV_DTYPE = np.dtype([
    ("t_pose", "f8"),              # capture time (s, daemon clock) of the pose behind goal
    ("goal", "f8", (4, 4)),        # T_B_tcp goal, m
    ("mode", "i4"),                # HOLD, MOVE or GUIDE
    ("near_point", "f8", (3,)),    # the patient (opener origin), base frame, m
    ("near_valid", "?"),           # near_point is known: slow down near it
    ("wrist_goal", "f8", (4,)),    # roll, pitch, yaw, jaw (rad)
    ("wrist_valid", "?"),
    ("T_B_F", "f8", (4, 4)),       # GUIDE: the surrogate model's frame in the base, m
])

#: The daemon -> loop commands. Counters, so a request is never lost between two reads.
CMD_DTYPE = np.dtype([
    ("stop_count", "i8"),
    ("stop_reason", f"S{240}"),
    ("clear_count", "i8"),         # bumped by the daemon after an authenticated reset
    ("stops_cleared", "i8"),       # stop_count when that reset was made: it ends those
    ("shutdown", "?"),
    ("recover_count", "i8"),       # bumped by the daemon for an operator's device recovery
    ("recover_device", "S16"),     # "effector" or "arm"
])

#: The loop -> daemon arm history: one entry per new measured TCP (the arm's own
#: timestamp, mapped by its driver onto the daemon's monotonic clock: RTDE's controller
#: time on the UR), so the daemon can place a camera frame's capture instant on the
#: arm's trajectory (docs/navigation.md, "Time").
ARM_SAMPLE_DTYPE = np.dtype([
    ("t", "f8"),                   # s, when the arm measured this pose
    ("T_B_tcp", "f8", (4, 4)),     # measured TCP, m
])
#: Entries kept: 4 s at 500 Hz, well beyond a frame's capture-to-tracked delay.
ARM_HISTORY_SLOTS = 2048
#: The loop -> daemon capture-to-command latency: one entry per goal (MOVE) or fixture
#: frame (GUIDE), when the first servo command computed from it is sent.
LATENCY_DTYPE = np.dtype([
    ("t_capture", "f8"),           # s: the capture instant of the poses behind the goal
    ("t_command", "f8"),           # s: when the first servo command toward it was sent
])
#: Entries kept: the last 512 goals (17 s at 30 frames/s).
LATENCY_SLOTS = 512

#: The loop -> daemon status.
STATUS_DTYPE = np.dtype([
    ("t", "f8"),                   # loop clock at the last period (s)
    ("periods", "i8"),
    ("T_B_tcp", "f8", (4, 4)),     # measured TCP, m
    ("t_arm", "f8"),               # when the arm measured T_B_tcp (s, its timestamp)
    ("tcp_speed", "f8", (6,)),     # m/s, rad/s
    ("setpoint", "f8", (4, 4)),    # last servo setpoint sent, m
    ("arm_connected", "?"),
    ("protective_stop", "?"),
    ("emergency_stop", "?"),
    ("wrist", "f8", (4,)),
    ("t_wrist", "f8"),
    ("latched", "?"),
    ("stop_time", "f8"),
    ("stop_reason", f"S{240}"),
    ("stop_count_seen", "i8"),
    ("clear_count_seen", "i8"),
    ("motion_commands", "i8"),
    ("goal_stale", "?"),           # held this period: the MOVE goal is older than stale_pose
    ("t_last_motion", "f8"),
    ("misses", "i8"),
    ("err_last", "f8"),            # |period - nominal| of the last period (s)
    ("err_max", "f8"),
    ("hist", "i8", (HIST_BINS + 1,)),
    # guided insertion (GUIDE mode; docs/control_loop.md, "Guided insertion")
    ("guide_active", "?"),         # this period ran the admittance (GUIDE, started, no stop)
    ("guide_planned", "?"),        # a plan is installed
    ("guide_seq", "i8"),           # the last plan message taken (ControlPort.set_guide)
    ("guide_refused_seq", "i8"),   # the last plan message refused (0: none)
    ("guide_rod_distance", "f8"),  # m: the rod's certified clearance at the measured TCP
    ("guide_to_target", "f8"),     # m: measured head to the target along the axis (> 0 out)
    ("guide_lateral", "f8"),       # m: measured head's distance from the planned axis
    # the wrist's drive (docs/drivers.md) and device recovery (docs/safety.md)
    ("wrist_connected", "?"),
    ("wrist_fault", f"S{240}"),
    ("arm_fault", f"S{240}"),      # why the arm cannot obey (a start failure, a lost link)
    ("recover_count_seen", "i8"),
])


@dataclass(frozen=True)
class LoopSettings:
    """What the loop needs from the configuration (SI units; ``[control]`` and
    ``[safety]`` of the daemon file, docs/safety.md)."""

    rate_hz: float = 500.0
    stale_pose: float = 0.1              # s: a MOVE goal older than this is held, a GUIDE
                                         # frame older than this stops the arm
    driver_silence: float = 0.1          # s: a driver state older than this stops the arm
    deadline_misses: int = 5             # consecutive late periods that stop the arm
    max_period_lateness: float = 0.01    # s: one period this late stops the arm
    max_wrist_speed: float = 1.0         # rad/s per joint
    # m, base frame: a goal or a measured TCP outside stops the arm
    workspace_min: tuple[float, float, float] = (-0.85, -0.85, 0.0)
    workspace_max: tuple[float, float, float] = (0.85, 0.85, 1.0)

    @property
    def period(self) -> float:
        return 1.0 / self.rate_hz

    @classmethod
    def from_config(cls, control: Any, safety: Any) -> LoopSettings:
        """From the daemon file's ``[control]`` and ``[safety]`` sections."""
        return cls(rate_hz=control.rate_hz, stale_pose=safety.stale_pose,
                   driver_silence=safety.driver_silence,
                   deadline_misses=safety.deadline_misses,
                   max_period_lateness=safety.max_period_lateness,
                   workspace_min=tuple(safety.workspace_min),
                   workspace_max=tuple(safety.workspace_max))


class ControlLoop:
    """One control period at a time; see the module docstring.

    ``arm`` and ``effector`` follow the driver contracts (``oralnav.drivers.arm.Arm``,
    ``oralnav.drivers.effector.EndEffector``); ``effector`` may be None.
    ``limiter`` (a :class:`~oralnav.safety.limits.SpeedLimiter`) steps the setpoint.
    """

    def __init__(self, arm: Arm, effector: EndEffector | None, settings: LoopSettings,
                 nav: SharedRecord, cmd: SharedRecord, status: SharedRecord,
                 limiter: SpeedLimiter, clock: Callable[[], float] | None = None,
                 history: SharedRing | None = None,
                 latency: SharedRing | None = None) -> None:
        self.arm, self.effector, self.s = arm, effector, settings
        # the measured TCP's history (ARM_SAMPLE_DTYPE), when the daemon reads one
        self.history = history
        # capture-to-command latencies (LATENCY_DTYPE), when the daemon reads them
        self.latency = latency
        self._t_capture_used = -math.inf  # the capture instant of the last goal servoed
        self._t_history = -math.inf  # the arm timestamp last appended
        # the real clock, to time each period's work; None (virtual clock): work is instant
        self._clock = clock
        self.nav, self.cmd, self.status = nav, cmd, status
        self.limiter = limiter
        self._setpoint: np.ndarray | None = None
        self._latched = False
        self._stop_seen = int(cmd.read()["stop_count"])
        self._clear_seen = int(cmd.read()["clear_count"])
        self._recover_seen = int(cmd.read()["recover_count"])
        #: device -> why it did not start (written by the control process's start retries)
        self.start_errors: dict[str, str] = {}
        self._deadline = DeadlineWatchdog(settings.period, settings.deadline_misses,
                                          settings.max_period_lateness)
        self._silence = DriverSilenceWatchdog(settings.driver_silence)
        self._stale = StalePoseWatchdog(settings.stale_pose)
        self._workspace = WorkspaceBox(settings.workspace_min, settings.workspace_max)
        self._last_now: float | None = None
        self._hist = np.zeros(HIST_BINS + 1, dtype=np.int64)
        self._periods = self._misses = self._motion = 0
        self._err_max = 0.0
        self._t_motion = 0.0
        self._stop_time = 0.0
        self._stop_reason = ""
        self._guide: GuidedMotion | None = None  # for GUIDE mode (set_guide)
        self.last_guide: GuideStep | None = None  # the last step, for status and tests
        self._guide_active = False
        self._guide_seq = 0
        self._guide_refused = 0
        self._guide_metrics = (math.nan, math.nan, math.nan)  # rod distance, axial, radial
        self._goal_stale = False  # this period held on a MOVE goal older than stale_pose

    @property
    def guide_running(self) -> bool:
        """A guided motion is under way: a plan started, no stop latched, and GUIDE is
        still what the daemon asks for (read fresh: a HOLD written just now counts)."""
        return (self._guide is not None and self._guide.started and not self._latched
                and int(self.nav.read()["mode"]) == GUIDE)

    def set_guide(self, guide: GuidedMotion | None, seq: int | None = None) -> bool:
        """Install the plan's :class:`~oralnav.control.guidance.guided_motion.GuidedMotion` (None:
        remove it); it starts from the measured TCP on the first GUIDE period. ``seq``
        numbers the request for the status record (default: the next number).

        Refused (False; the running motion and its plan are kept, ``guide_refused_seq``
        reports ``seq``) while a guided motion runs (:attr:`guide_running`): a plan never
        changes under the operator's hand. The daemon ends the motion (HOLD) first.
        """
        seq = self._guide_seq + 1 if seq is None else int(seq)
        if self.guide_running:
            self.refuse_guide(seq, "a guided motion is running")
            return False
        if self._guide is not None:
            self._guide.finish()
        self._guide = guide
        self._guide_seq = seq
        self.last_guide = None
        self._guide_metrics = (math.nan, math.nan, math.nan)
        return True

    def refuse_guide(self, seq: int, why: str) -> None:
        """Report plan message ``seq`` as refused (unreadable, or refused by
        :meth:`set_guide`); nothing else changes."""
        self._guide_refused = int(seq)
        log.warning("plan %d refused: %s", seq, why)

    # -- one period ------------------------------------------------------------------
    def step(self, now: float, lateness: float = 0.0) -> None:
        """One period at ``now`` (s, loop clock), which started ``lateness`` s after its
        scheduled time (the runner knows; in-process callers on a virtual clock pass 0)."""
        s = self.s
        err = 0.0
        if self._last_now is not None:
            err = abs((now - self._last_now) - s.period)
            b = min(int(err / HIST_BIN_S), HIST_BINS)
            self._hist[b] += 1
            self._err_max = max(self._err_max, err)
            self._misses += err > MISS_S
        self._last_now = now
        self._periods += 1
        arm = self.arm.state()
        wrist = self.effector.state() if self.effector is not None else None
        nav = self.nav.read()
        cmd = self.cmd.read()

        if int(cmd["clear_count"]) != self._clear_seen:
            self._clear_seen = int(cmd["clear_count"])
            # a stop requested before the reset, and not yet seen, is over with it: on a
            # late period both arrive together and must not latch the loop again
            self._stop_seen = max(self._stop_seen, int(cmd["stops_cleared"]))
            self._unlatch(arm)
        if int(cmd["recover_count"]) != self._recover_seen:
            self._recover_seen = int(cmd["recover_count"])
            self._recover(cmd["recover_device"].decode("ascii", "replace"))
        reason = self._trip_reason(now, arm, wrist, nav, cmd)
        if reason is not None and not self._latched:
            self._latch(now, reason)
        self._guide_active = False
        self._goal_stale = False
        if not self._latched:
            self._command(now, arm, nav)
        self._record(arm)
        self._publish(now, arm, wrist, err)
        # finished how long after this period's end (its deadline); <= 0 is on time
        self._deadline.period_done(self._clock_after(now) - (now - lateness + s.period), now)

    def _trip_reason(self, now: float, arm: ArmState, wrist: EffectorState | None, nav: np.void,
                     cmd: np.void) -> str | None:
        if int(cmd["stop_count"]) != self._stop_seen:
            self._stop_seen = int(cmd["stop_count"])
            return f"stop requested: {decode_reason(cmd['stop_reason'])}"
        if not arm.connected:
            return "arm disconnected"
        if arm.emergency_stop:
            return "arm emergency stop"
        if arm.protective_stop:
            return "arm protective stop"
        self._silence.heartbeat("arm", arm.timestamp)
        if wrist is not None:
            if not wrist.connected:
                return "end-effector disconnected"
            if wrist.fault:
                return f"end-effector fault: {wrist.fault}"
            self._silence.heartbeat("end-effector", wrist.timestamp)
        trips = self._silence.check(now) + self._deadline.check(now)
        outside = self._workspace_reason("TCP", arm.T_B_tcp)
        if outside is None and int(nav["mode"]) == MOVE:
            outside = self._workspace_reason("goal", np.array(nav["goal"]))
        if outside is not None:  # never steer toward, or stay moving, outside the box
            return outside
        if int(nav["mode"]) == GUIDE and self._guide is None:
            return "guided motion requested without a plan"
        if int(nav["mode"]) == GUIDE:  # the operator's push follows a stale fixture: stop
            self._stale.fresh("goal", float(nav["t_pose"]))
            trips += self._stale.check(now)
        else:  # MOVE holds on a stale goal instead (_command); HOLD needs no pose
            self._stale.disarm("goal")
        return "; ".join(f"{t.name}: {t.reason}" for t in trips) if trips else None

    def _workspace_reason(self, what: str, T: np.ndarray) -> str | None:
        bad = self._workspace.violations(T[:3, 3])
        if not bad:
            return None
        return f"workspace: {what} outside the box (" + ", ".join(
            f"{axis} {d * 1e3:+.1f} mm" for axis, d in bad) + ")"

    def _clock_after(self, now: float) -> float:
        return self._clock() if self._clock is not None else now

    def _latch(self, now: float, reason: str) -> None:
        """Stop everything once; from here on the loop commands nothing until cleared."""
        self._latched = True
        self._stop_time, self._stop_reason = now, reason
        if self._guide is not None:
            # a guided motion never resumes by itself after a reset: the next GUIDE
            # period starts afresh from the measured TCP
            self._guide.finish()
        log.warning("control loop stop: %s", reason)
        for dev in (self.arm, self.effector):
            if dev is None:
                continue
            try:
                dev.stop()
            except Exception:  # stop() must not raise, but the loop must outlive it
                log.exception("stop() of %r raised", dev)

    def _recover(self, device: str) -> None:
        """An operator asked to recover a device from its fault: the wrist's drive runs its
        fault reset (``reset_fault``), the arm its controller's recovery (``recover``). Only
        while the stop is latched; both only start the work (their own threads do it), so
        the period is not held up."""
        if not self._latched:
            log.warning("recovery of %s ignored: the stop is not latched", device)
            return
        dev = {"effector": self.effector, "arm": self.arm}.get(device)
        action = {"effector": "reset_fault", "arm": "recover"}.get(device, "")
        fn = getattr(dev, action, None)
        if fn is None:
            log.warning("recovery of %s: the %s driver has no %s()", device, device, action)
            return
        log.warning("recovering %s (%s) at the operator's request", device, action)
        try:
            pending = fn()
        except Exception:  # a driver error must not end the loop; the status shows the fault
            log.exception("recovering %s failed", device)
            return
        if inspect.isawaitable(pending):
            # an async recovery (the UR arm's dashboard sequence takes seconds): its own
            # thread and event loop, never this period's
            threading.Thread(target=_await_recovery, args=(device, pending),
                             name=f"recover-{device}", daemon=True).start()

    def _unlatch(self, arm: ArmState) -> None:
        """The daemon cleared the stop after an authenticated reset: resume from where
        the arm now is (never from the old setpoint)."""
        self._latched = False
        self._deadline = DeadlineWatchdog(self.s.period, self.s.deadline_misses,
                                          self.s.max_period_lateness)
        self._setpoint = np.array(arm.T_B_tcp, dtype=float)

    def _command(self, now: float, arm: ArmState, nav: np.void) -> None:
        s = self.s
        if self._setpoint is None:
            self._setpoint = np.array(arm.T_B_tcp, dtype=float)
        mode = int(nav["mode"])
        if mode == GUIDE:
            goal = self._guide_goal(now, arm, nav)
            if goal is None:
                return
        else:
            if self._guide is not None:
                self._guide.finish()    # the next GUIDE period starts from the measured TCP
            # a MOVE goal computed from poses older than stale_pose is not followed: the
            # arm holds where it is until a fresh one comes (slow sight, slow motion);
            # poses that stop coming are the daemon's pose_timeout, a latched stop
            self._goal_stale = mode == MOVE and now - float(nav["t_pose"]) > s.stale_pose
            if mode != MOVE or self._goal_stale:
                self._setpoint = np.array(arm.T_B_tcp, dtype=float)
                self.arm.kick()
                return
            goal = np.array(nav["goal"])
        near = np.array(nav["near_point"]) if bool(nav["near_valid"]) else None
        self._setpoint = self.limiter.step(self._setpoint, goal, s.period, near=near)
        self.arm.servo(self._setpoint, s.period)
        t_capture = float(nav["t_pose"])
        if self.latency is not None and t_capture != self._t_capture_used:
            # the first command from this capture: its latency, on the real clock
            self._t_capture_used = t_capture
            self.latency.append(t_capture=t_capture, t_command=self._clock_after(now))
        if self.effector is not None and bool(nav["wrist_valid"]):
            q = np.array(self.effector.state().joints, dtype=float)
            step = np.clip(np.array(nav["wrist_goal"]) - q, -s.max_wrist_speed * s.period,
                           s.max_wrist_speed * s.period)
            self.effector.command(q + step)
        self._motion += 1
        self._t_motion = now

    def _guide_goal(self, now: float, arm: ArmState, nav: np.void) -> np.ndarray | None:
        """The admittance's setpoint for this period, or None after latching the stop (a
        TCP outside the fixture at the start, bad sensor data, or the rod alarm)."""
        T_B_F = np.array(nav["T_B_F"])
        try:
            if not self._guide.started:
                self._guide.start(arm.T_B_tcp, T_B_F)
            step = self._guide.step(arm.tcp_force, T_B_F, arm.T_B_tcp, self.s.period)
        except ControlError as exc:
            self._latch(now, f"guided motion: {exc}")
            return None
        self.last_guide = step
        # where the measured head is on the planned axis, in F (for the operator)
        fx = self._guide.plan.fixture
        p_F = T_B_F[:3, :3].T @ (arm.T_B_tcp[:3, 3] - T_B_F[:3, 3])
        self._guide_metrics = (step.rod_distance, fx.axial(p_F), fx.radial(p_F))
        if step.alarm is not None:
            self._latch(now, step.alarm)
            return None
        self._guide_active = True
        return step.setpoint

    def _arm_fault(self, arm: ArmState) -> str:
        """Why the arm cannot obey, in words ("" when it can or nobody knows): a start that
        failed, else the driver's own ``fault`` (a lost link, a stop), while not ready."""
        if arm.ready:
            return ""
        if not arm.connected and "arm" in self.start_errors:
            return self.start_errors["arm"]
        return getattr(self.arm, "fault", None) or ""

    def _record(self, arm: ArmState) -> None:
        """Append the arm's measured TCP to the history when it is a new measurement (a
        UR reports at its own rate; a repeated timestamp is the same sample)."""
        if self.history is None or not arm.connected or arm.timestamp <= self._t_history:
            return
        self._t_history = arm.timestamp
        self.history.append(t=arm.timestamp, T_B_tcp=arm.T_B_tcp)

    def _publish(self, now: float, arm: ArmState, wrist: EffectorState | None,
                 err: float) -> None:
        self.status.write(
            t=now, periods=self._periods, T_B_tcp=arm.T_B_tcp, t_arm=arm.timestamp,
            tcp_speed=arm.tcp_speed,
            setpoint=self._setpoint if self._setpoint is not None else arm.T_B_tcp,
            arm_connected=arm.connected, protective_stop=arm.protective_stop,
            emergency_stop=arm.emergency_stop,
            wrist=wrist.joints if wrist is not None else np.zeros(4),
            t_wrist=wrist.timestamp if wrist is not None else 0.0,
            latched=self._latched, stop_time=self._stop_time,
            stop_reason=encode_reason(self._stop_reason),
            stop_count_seen=self._stop_seen, clear_count_seen=self._clear_seen,
            motion_commands=self._motion, t_last_motion=self._t_motion,
            goal_stale=self._goal_stale,
            misses=self._misses, err_last=err, err_max=self._err_max, hist=self._hist,
            guide_active=self._guide_active, guide_planned=self._guide is not None,
            guide_seq=self._guide_seq, guide_refused_seq=self._guide_refused,
            guide_rod_distance=self._guide_metrics[0],
            guide_to_target=self._guide_metrics[1], guide_lateral=self._guide_metrics[2],
            wrist_connected=wrist.connected if wrist is not None else False,
            wrist_fault=encode_reason(wrist.fault or "") if wrist is not None else b"",
            recover_count_seen=self._recover_seen,
            arm_fault=encode_reason(self._arm_fault(arm)))


def _await_recovery(device: str, pending: Any) -> None:
    """Run an async device recovery to its end in this (worker) thread; log the outcome."""
    import anyio

    async def wait() -> None:
        await pending

    try:
        anyio.run(wait)
    except Exception:
        log.exception("recovering %s failed", device)
    else:
        log.warning("recovery of %s done", device)


#: s: the last stretch before a deadline spent spinning rather than asleep. With the timer
#: slack at 1 ns (:func:`tighten_timing`) a sleeping SCHED_FIFO loop wakes 25 us late at the
#: median and 80 us at the 99th percentile on a 2-core VM with both cores busy; 50 us of
#: spin brings that to 4 and 26 us for 3 % of a core (200 us: 3 and 5 us for 10 %).
SPIN_S = 5e-5
#: s: the GIL switch interval in the control process (Python's default is 5 ms). A helper
#: thread of a driver (the Modbus drive's, the UR driver's command and reader threads)
#: holding the GIL when the loop wakes keeps it until it blocks or this much has passed:
#: at 5 ms, up to two and a half periods of a 500 Hz loop. (A run of late periods ending
#: 5.3 ms late was seen under load; that this was the cause is not shown.)
SWITCH_INTERVAL_S = 2e-4


def tighten_timing() -> str:
    """For the calling (control) process: timer slack 1 ns (the kernel otherwise delays
    each wake-up by up to 50 us to batch timers) and a short GIL switch interval
    (:data:`SWITCH_INTERVAL_S`); says what was set."""
    import ctypes
    import sys

    sys.setswitchinterval(SWITCH_INTERVAL_S)
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        ok = libc.prctl(29, 1, 0, 0, 0) == 0  # PR_SET_TIMERSLACK, 1 ns
    except (OSError, AttributeError):
        ok = False
    return (f"GIL switch interval {SWITCH_INTERVAL_S * 1e6:.0f} us, "
            + ("timer slack 1 ns" if ok else "timer slack unchanged (prctl refused)"))


def run_at_rate(step: Callable[[float, float], None], rate_hz: float,
                should_stop: Callable[[], bool], clock: Callable[[], float] = time.monotonic,
                spin_s: float = SPIN_S) -> None:
    """Call ``step(now, lateness)`` every ``1 / rate_hz`` s of ``clock`` until
    ``should_stop()``; ``lateness`` is how long after its scheduled time the call starts.

    Sleeps to within ``spin_s`` of each deadline, then yields in a short spin (see
    :data:`SPIN_S`). Deadlines stay on the original grid; a period overrun by more than a
    whole period skips ahead rather than bursting.
    """
    period = 1.0 / rate_hz
    t_next = clock() + period
    while not should_stop():
        while True:
            rem = t_next - clock()
            if rem <= 0:
                break
            time.sleep(rem - spin_s if rem > spin_s else 0)
        now = clock()
        step(now, now - t_next)
        t_next += period
        if now - t_next > period:
            t_next = now + period


def try_realtime(priority: int) -> str:
    """Ask for SCHED_FIFO at ``priority`` for the calling process; say what happened."""
    if priority <= 0:
        return "normal scheduling (realtime_priority = 0)"
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        return f"SCHED_FIFO priority {priority}"
    except (PermissionError, OSError, AttributeError) as exc:
        return f"normal scheduling (SCHED_FIFO {priority} refused: {exc})"
