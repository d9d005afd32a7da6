"""The control loop in a process of its own, on the wall clock.

The daemon creates the shared records, then ``ControlProcess.start()`` spawns a child that
builds the arm and end-effector drivers itself (hardware connections belong to the
process that uses them at 500 Hz), asks for real-time scheduling, and runs
``ControlLoop.step`` at the configured rate until told to shut down. The child advances
simulated drivers by the elapsed time each period (a real arm moves on its own).

Guided-insertion plans reach the child through the plan channel (``realtime/plan_channel.py``,
a pipe the loop polls without blocking once per period): ``ControlPort.set_guide(plan)``
sends one, the child builds the :class:`~oralnav.control.guidance.guided_motion.GuidedMotion` and
installs it (``ControlLoop.set_guide``), and the status record acknowledges it
(``guide_seq``) or reports it refused (``guide_refused_seq``: a guided motion was running,
or the plan was unreadable). ``ControlPort.set_guide_frame`` then commands GUIDE with the
patient's model frame, every supervision tick, as ``set_goal`` commands MOVE.
"""

from __future__ import annotations

import gc
import logging
import multiprocessing as mp
import os
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Literal, overload

import anyio
import numpy as np

from oralnav.control.guidance.guided_motion import GuidePlan
from oralnav.drivers.arm import Arm
from oralnav.drivers.clock import Clock
from oralnav.drivers.effector import EndEffector
from oralnav.realtime.control_loop import (
    ARM_HISTORY_SLOTS,
    ARM_SAMPLE_DTYPE,
    CMD_DTYPE,
    GUIDE,
    HOLD,
    LATENCY_DTYPE,
    LATENCY_SLOTS,
    MOVE,
    NAV_DTYPE,
    STATUS_DTYPE,
    ControlLoop,
    LoopSettings,
    run_at_rate,
    tighten_timing,
    try_realtime,
)
from oralnav.realtime.plan_channel import ChannelError, PlanInbox, PlanSender, check_size, encode
from oralnav.realtime.shm import SharedRecord, SharedRing, encode_reason
from oralnav.safety.limits import SpeedLimiter

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DriverSpec:
    """A driver to build in the child: registry backend name and its arguments."""

    backend: str
    options: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class ProcessSpec:
    arm: DriverSpec
    effector: DriverSpec | None
    settings: LoopSettings
    limiter: SpeedLimiter
    realtime_priority: int = 0
    cpu: int | None = None             # pin the loop to this CPU when given


@overload
def _build(kind: Literal["arm"], spec: DriverSpec, clock: Clock) -> Arm: ...
@overload
def _build(kind: Literal["effector"], spec: DriverSpec, clock: Clock) -> EndEffector: ...
def _build(kind: str, spec: DriverSpec, clock: Clock) -> Arm | EndEffector:
    if kind == "arm":
        from oralnav.drivers.arm import open_arm as opener
    else:
        from oralnav.drivers.effector import open_effector as opener
    options = dict(spec.options)
    if spec.backend == "sim":
        options.setdefault("clock", clock)
    return opener(spec.backend, **options)


def _apply_plan(loop: ControlLoop, msg: tuple[int, Any]) -> None:
    """Install a plan that arrived on the plan channel (the child's side of
    ``ControlPort.set_guide``); an unreadable or invalid one is refused, never guessed at."""
    from oralnav.control.guidance.guided_motion import GuidedMotion, GuidePlan

    seq, plan = msg
    if plan is not None and not isinstance(plan, GuidePlan):
        what = plan if isinstance(plan, Exception) else f"a {type(plan).__name__}"
        loop.refuse_guide(seq, f"not a GuidePlan ({what})")
        return
    try:
        guide = GuidedMotion(plan) if plan is not None else None
    except Exception as exc:
        loop.refuse_guide(seq, f"{type(exc).__name__}: {exc}")
        return
    loop.set_guide(guide, seq)
    gc.freeze()  # the plan's objects join the frozen heap (settle_heap)


def _warm_guidance() -> None:
    """Before the loop runs: load numba's compiled rod check (``rod_check.warm_up``;
    compiled on a first run) and take one guided step on a small plan (the imports and
    first calls a plan needs), none of which may happen in a 2 ms period. About 0.4 s at
    start when numba's cache is warm."""
    try:
        from oralnav.control.guidance.guided_motion import GuidedMotion, GuidePlan
        from oralnav.control.planning import rod_check
        from oralnav.control.planning.fpsm import FPSM

        rod_check.warm_up()

        T = np.eye(4)   # the head 40 mm up a 20 mm cylinder, its rod (tool x) along +z
        T[:3, :3] = [[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]
        T[:3, 3] = [0.0, 0.0, 0.04]
        guide = GuidedMotion(GuidePlan(T, FPSM.cylinder(0.02, 0.0, 0.05, 3), 0.001))
        guide.start(T, np.eye(4))
        guide.step(np.zeros(3), np.eye(4), T, 0.002)
    except Exception:
        log.exception("warming up guided motion failed; a first guided period may run late")


def settle_heap() -> None:
    """Collect once and freeze what is left, so that the cyclic collector never walks the
    startup heap again. With numpy, scipy and numba loaded that heap holds about 150 000
    objects, and one full collection of them took 96 ms: a period 55 ms late in the demo
    under a loaded test run, stopped by the deadline watchdog. Objects freed by their
    reference counts still go as before."""
    gc.collect()
    gc.freeze()


#: Back-off (first, max) s between attempts to start a device that could not be reached.
START_RETRY_S = (1.0, 10.0)


def _start_or_retry(device: Arm | EndEffector, kind: str, errors: dict[str, str]) -> None:
    """Start ``device``; one that cannot be reached now (a wrong address, a controller that
    is off, a recipe it refuses) leaves the loop running with the device disconnected (the
    loop latches its stop and the status names it), and a thread keeps trying to start it
    with back-off, so the cell recovers when the device returns. ``errors[kind]`` holds why
    it has not started (the status record reports it) until it does."""
    from oralnav.drivers.errors import DriverInitError

    try:
        anyio.run(device.start)
        return
    except DriverInitError as exc:
        log.error("%r did not start: %s; retrying in the background", device, exc)
        errors[kind] = f"did not start: {exc}"

    def retry() -> None:
        delay = START_RETRY_S[0]
        while True:
            time.sleep(delay)
            try:
                anyio.run(device.start)
            except DriverInitError as exc:
                log.warning("%r still not started: %s", device, exc)
                errors[kind] = f"did not start: {exc}"
                delay = min(2 * delay, START_RETRY_S[1])
            else:
                log.warning("%r started", device)
                errors.pop(kind, None)
                return

    threading.Thread(target=retry, name=f"start-{getattr(device, 'name', 'device')}",
                     daemon=True).start()


def _child(spec: ProcessSpec, names: dict[str, str], ready: Any, plans: Any = None) -> None:
    """Entry point of the control process. ``plans``: the read end of the plan channel
    (a ``multiprocessing`` connection; its descriptor is read raw, see plan_channel)."""
    from oralnav.drivers.clock import WallClock

    logging.basicConfig(level=logging.INFO, format="oralnavd control: %(message)s")
    if spec.cpu is not None:
        try:
            os.sched_setaffinity(0, {spec.cpu})
        except OSError as exc:
            log.warning("cannot pin to CPU %s: %s", spec.cpu, exc)
    _warm_guidance()
    sched = try_realtime(spec.realtime_priority) + "; " + tighten_timing()
    nav = SharedRecord(NAV_DTYPE, names["nav"])
    cmd = SharedRecord(CMD_DTYPE, names["cmd"])
    status = SharedRecord(STATUS_DTYPE, names["status"])
    history = SharedRing(ARM_SAMPLE_DTYPE, ARM_HISTORY_SLOTS, names["history"])
    latency = SharedRing(LATENCY_DTYPE, LATENCY_SLOTS, names["latency"])
    clock = WallClock()
    inbox = None
    if plans is not None:
        inbox = PlanInbox(os.dup(plans.fileno()))
        plans.close()
    arm = _build("arm", spec.arm, clock)
    eff = _build("effector", spec.effector, clock) if spec.effector else None
    start_errors: dict[str, str] = {}
    try:
        for kind, d in (("arm", arm), ("effector", eff)):
            if d is not None:
                _start_or_retry(d, kind, start_errors)
        loop = ControlLoop(arm, eff, spec.settings, nav, cmd, status, spec.limiter,
                           clock=clock.now, history=history, latency=latency)
        loop.start_errors = start_errors
        sims = [d for d in (arm, eff) if d is not None and hasattr(d, "advance")]
        last = [clock.now()]

        def step(now: float, lateness: float) -> None:
            for d in sims:  # simulated physics: the devices move by the elapsed time
                d.advance(now - last[0])
            last[0] = now
            if inbox is not None:  # before the step: its cost counts in this period
                msg = inbox.poll()
                if msg is not None:
                    _apply_plan(loop, msg)
            loop.step(now, lateness)

        settle_heap()
        ready.set()
        cpus = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else "?"
        log.info("running at %g Hz on CPU(s) %s, %s", spec.settings.rate_hz, cpus, sched)
        parent = os.getppid()

        def should_stop() -> bool:
            # a daemon that died without shutting us down must not leave the arm servoing
            return bool(cmd.read()["shutdown"]) or os.getppid() != parent

        run_at_rate(step, spec.settings.rate_hz, should_stop, clock=clock.now)
    finally:
        for d in (arm, eff):
            if d is None:
                continue
            try:
                d.stop()
                anyio.run(d.close)
            except Exception:
                log.exception("closing %r", d)
        for r in (nav, cmd, status, history, latency):
            r.close()
        if inbox is not None:
            inbox.close()


class ControlPort:
    """The daemon's side of the control loop: the three shared records and what the core
    does with them (stop, clear, goal, status). :class:`ControlProcess` runs the loop in a
    child process; :class:`InProcessControl` steps it here, on a virtual clock."""

    def __init__(self) -> None:
        self.nav: SharedRecord | None = None
        self.cmd: SharedRecord | None = None
        self.status: SharedRecord | None = None
        self.history: SharedRing | None = None
        self.latency: SharedRing | None = None
        self._stops = 0
        self._clears = 0
        self._recovers = 0
        self._guide_sent = 0            # the last plan message's number (set_guide)
        #: size (bytes) of the last plan message, 0 where no pipe carries it
        self.guide_bytes = 0

    def _open_records(self) -> None:
        self.nav = SharedRecord(NAV_DTYPE)
        self.cmd = SharedRecord(CMD_DTYPE)
        self.status = SharedRecord(STATUS_DTYPE)
        self.history = SharedRing(ARM_SAMPLE_DTYPE, ARM_HISTORY_SLOTS)
        self.latency = SharedRing(LATENCY_DTYPE, LATENCY_SLOTS)

    def _close_records(self) -> None:
        for name in ("nav", "cmd", "status", "history", "latency"):
            rec = getattr(self, name)
            if rec is not None:
                rec.close()
                setattr(self, name, None)

    @property
    def alive(self) -> bool:
        raise NotImplementedError

    def request_stop(self, reason: str) -> None:
        """Latched-stop handler: the loop stops the arm at its next period. Never blocks."""
        if self.cmd is None:
            return
        self._stops += 1
        self.cmd.write(stop_count=self._stops, stop_reason=encode_reason(reason))

    @property
    def clears(self) -> int:
        """Clear requests sent so far; the status record's ``clear_count_seen`` reaches it
        once the loop has acted on the last one."""
        return self._clears

    def clear_stop(self) -> None:
        """After an authenticated reset: let the loop command again."""
        if self.cmd is not None:
            self._clears += 1
            self.cmd.write(clear_count=self._clears, stops_cleared=self._stops)

    def recover(self, device: str) -> None:
        """Ask the loop to recover ``device`` (``"effector"``: the drive's fault reset;
        ``"arm"``: the controller's recovery); it acts only while its stop is latched."""
        if device not in ("effector", "arm"):
            raise ValueError(f"unknown device {device!r} (effector or arm)")
        if self.cmd is not None:
            self._recovers += 1
            self.cmd.write(recover_count=self._recovers, recover_device=device.encode())

    def set_goal(self, T_B_tcp: np.ndarray, t_pose: float, *, move: bool,
                 near_point: np.ndarray | None = None, wrist: np.ndarray | None = None
                 ) -> None:
        """Publish the goal (``T_B_tcp``, m) computed from the pose captured at ``t_pose``;
        ``move`` False holds still. ``near_point``: the patient (base frame, m)."""
        if self.nav is None:
            return
        self.nav.write(goal=T_B_tcp, t_pose=t_pose, mode=MOVE if move else HOLD,
                       near_point=near_point if near_point is not None else np.zeros(3),
                       near_valid=near_point is not None,
                       wrist_goal=wrist if wrist is not None else np.zeros(4),
                       wrist_valid=wrist is not None)

    def set_guide_frame(self, T_B_F: np.ndarray, t_pose: float, *,
                        near_point: np.ndarray | None = None) -> None:
        """Command GUIDE: the loop runs the installed plan's admittance with the surrogate
        model's frame ``T_B_F`` (4x4, m, robot base) computed from the pose captured at
        ``t_pose`` (s, daemon clock; the loop's stale-pose watchdog reads it as for MOVE).
        ``near_point``: the patient (base frame, m) for the near-patient speed limit.
        Publish it every supervision tick, as ``set_goal`` is for MOVE."""
        if self.nav is None:
            return
        self.nav.write(T_B_F=T_B_F, t_pose=t_pose, mode=GUIDE,
                       near_point=near_point if near_point is not None else np.zeros(3),
                       near_valid=near_point is not None, wrist_valid=False)

    def guide_reply(self, seq: int) -> str | None:
        """What the loop did with plan message ``seq``: ``"taken"``, ``"refused"``, or
        None while it has not read it yet."""
        st = self.read_status()
        if st is None or seq <= 0:
            return None
        if int(st["guide_refused_seq"]) == seq:
            return "refused"
        if int(st["guide_seq"]) >= seq:
            return "taken"
        return None

    def guide_pending(self) -> bool:
        """A plan message is on its way that the loop has neither taken nor refused."""
        st = self.read_status()
        return st is not None and self._guide_sent > max(int(st["guide_seq"]),
                                                         int(st["guide_refused_seq"]))

    def check_guide(self, plan: GuidePlan | None) -> None:
        """Raise :class:`~oralnav.realtime.plan_channel.ChannelError` (a ``RuntimeError``)
        when ``plan`` cannot be sent (too large for the channel). Sends nothing."""

    def flush_guide(self) -> None:
        """Write more of a plan message the pipe could not take at once; never blocks.
        The daemon calls it every supervision tick."""

    def set_guide(self, plan: GuidePlan | None) -> int:
        """Send ``plan`` (a :class:`~oralnav.control.guidance.guided_motion.GuidePlan`, or None to
        remove it) to the loop; returns its message number. Never blocks: what the pipe
        does not take now goes with :meth:`flush_guide`. The loop takes it unless a guided
        motion is running there (``guide_reply``): switch to HOLD first.
        :class:`ChannelError` when the previous message is still on its way or the plan
        cannot be sent; nothing is sent then."""
        if self.guide_pending():
            raise ChannelError("the control loop has not read the previous plan message "
                               "yet; try again")
        seq = self._guide_sent + 1
        self._deliver(seq, plan)
        self._guide_sent = seq
        return seq

    def _deliver(self, seq: int, plan: GuidePlan | None) -> None:
        raise NotImplementedError

    def read_status(self) -> np.void | None:
        return None if self.status is None else self.status.read()

    def read_arm_history(self) -> np.ndarray:
        """The arm's measured TCP history, oldest first (``ARM_SAMPLE_DTYPE``: ``t`` in s
        on the arm's timestamps, ``T_B_tcp`` 4x4 m); empty before the loop's first
        sample. A copy, about 20 us for the full ring; never waits on the loop."""
        if self.history is None:
            return np.zeros(0, dtype=ARM_SAMPLE_DTYPE)
        return self.history.read()

    def read_latency(self) -> np.ndarray:
        """The last capture-to-command latencies, oldest first (``LATENCY_DTYPE``:
        ``t_capture`` and ``t_command`` in s); empty before the first goal is servoed."""
        if self.latency is None:
            return np.zeros(0, dtype=LATENCY_DTYPE)
        return self.latency.read()

    def heartbeat(self) -> int:
        """The loop's heartbeat: a number that changes with every period it completes (the
        status record's write count; the loop alone writes that record, once per period).
        0 before the records exist. About a microsecond, never waits: the daemon's
        heartbeat watch (``daemon/heartbeat.py``) polls it every millisecond."""
        return 0 if self.status is None else self.status.sequence


class ControlProcess(ControlPort):
    """Owns the shared records and the child process; see the module docstring."""

    def __init__(self, spec: ProcessSpec) -> None:
        super().__init__()
        self.spec = spec
        self._proc: mp.process.BaseProcess | None = None
        self._plans: PlanSender | None = None

    async def start(self, timeout: float = 90.0) -> None:
        """Create the records, spawn the child, and wait until its loop runs. The child
        imports numpy, scipy and numba and warms guided motion up before its first period:
        2-5 s on an idle machine, and over 20 s was seen with both cores of a 2-core
        machine busy, so the default waits generously; a child that dies says so at once."""
        self._open_records()
        ctx = mp.get_context("spawn")  # no inherited threads or locks from the daemon
        ready = ctx.Event()
        names = {"nav": self.nav.name, "cmd": self.cmd.name, "status": self.status.name,
                 "history": self.history.name, "latency": self.latency.name}
        reader, writer = ctx.Pipe(duplex=False)
        self._plans = PlanSender(os.dup(writer.fileno()))
        writer.close()
        self._proc = ctx.Process(target=_child, args=(self.spec, names, ready, reader),
                                 name="oralnavd-control", daemon=True)
        try:
            self._proc.start()
        finally:
            reader.close()  # the child has its own copy
        deadline = time.monotonic() + timeout
        # "runs" means its first period has published a status: the child signals ready
        # just before its first period, and a supervisor reading the status record before
        # that would see a disconnected arm
        while not (ready.is_set() and int(self.status.read()["periods"]) > 0):
            if not self._proc.is_alive():
                raise RuntimeError(f"control process exited during start "
                                   f"(exit code {self._proc.exitcode})")
            if time.monotonic() > deadline:
                raise TimeoutError(f"control process not running after {timeout:g} s")
            await anyio.sleep(0.01)

    @property
    def alive(self) -> bool:
        return self._proc is not None and self._proc.is_alive()

    def check_guide(self, plan: GuidePlan | None) -> None:
        check_size(len(encode(1, plan)))

    def flush_guide(self) -> None:
        if self._plans is not None:
            self._plans.flush()

    def _deliver(self, seq: int, plan: GuidePlan | None) -> None:
        if self._plans is None or not self.alive:
            raise ChannelError("the control process is not running")
        frame = encode(seq, plan)
        self._plans.send(frame)
        self.guide_bytes = len(frame)

    async def close(self, timeout: float = 5.0) -> None:
        """Shut the child down (it stops the arm first); idempotent."""
        proc, self._proc = self._proc, None
        if proc is not None:
            if self.cmd is not None:
                self.cmd.write(shutdown=True)
            deadline = time.monotonic() + timeout
            while proc.is_alive() and time.monotonic() < deadline:
                await anyio.sleep(0.01)
            if proc.is_alive():
                log.error("control process did not exit in %g s; terminating it", timeout)
                proc.terminate()
                proc.join(1.0)
        if self._plans is not None:
            self._plans.close()
            self._plans = None
        self._close_records()


class InProcessControl(ControlPort):
    """The control loop stepped in this process by its caller, on a virtual clock: the
    deterministic simulation and the tests. ``step(now)`` advances the simulated devices
    by the time since the last step, then runs one loop period."""

    def __init__(self, arm: Arm, effector: EndEffector | None, settings: LoopSettings,
                 limiter: SpeedLimiter) -> None:
        super().__init__()
        self._open_records()
        self.arm, self.effector = arm, effector
        self.loop = ControlLoop(arm, effector, settings, self.nav, self.cmd, self.status,
                                limiter, history=self.history, latency=self.latency)
        self._last: float | None = None
        self._closed = False

    @property
    def alive(self) -> bool:
        return not self._closed

    def _deliver(self, seq: int, plan: GuidePlan | None) -> None:
        # what the child does with a message, at once: same rules, no pipe
        if self._closed:
            raise ChannelError("the control loop is closed")
        _apply_plan(self.loop, (seq, plan))

    def step(self, now: float, lateness: float = 0.0) -> None:
        """One period at ``now``; ``lateness`` simulates a period that started late."""
        if self._last is not None:
            for d in (self.arm, self.effector):
                if d is not None and hasattr(d, "advance"):
                    d.advance(now - self._last)
        self._last = now
        self.loop.step(now, lateness)

    async def close(self) -> None:
        self._closed = True
        self._close_records()
