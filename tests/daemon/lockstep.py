"""What the virtual-clock procedure tests share: the daemon's core, the control loop
stepped in-process at 500 Hz of virtual time, the simulated arm, wrist and cell, and the
daemon's own capture pipeline and navigation (``build_navigation``), run in lockstep:
deterministic and faster than real time."""

from __future__ import annotations

import dataclasses
import functools

from oralnav.config.daemon import load_config
from oralnav.daemon.core import DaemonCore
from oralnav.daemon.schemas import SutureTarget
from oralnav.daemon.service import build_navigation
from oralnav.drivers.arm.sim import SimArm
from oralnav.drivers.clock import VirtualClock
from oralnav.drivers.effector.sim import SimEffector
from oralnav.drivers.io.sim import SimInputs
from oralnav.realtime.control_loop import LoopSettings
from oralnav.realtime.control_process import InProcessControl
from oralnav.safety.limits import SpeedLimiter
from oralnav.safety.watchdogs import WatchdogSet

CAMERA_EVERY = 50        # loop periods per camera frame: 10 Hz at 500 Hz
SUPERVISE_EVERY = 10     # 50 Hz


@functools.cache
def _config():
    # one frozen configuration for the module: its camera models are the same objects in
    # every test, so the renderer's ray maps (cached per camera) are built once, not per test
    return load_config()


class Lockstep:
    """The cell in lockstep; ``camera_every``: loop periods per camera frame;
    ``latency_periods``: frames reach the pipeline that many periods after they were
    rendered, stamped on arrival (a camera whose timestamps are late by that much, what
    the temporal calibration measures); ``cfg``: another configuration than config/sim.toml."""

    def __init__(self, camera_every: int = CAMERA_EVERY, latency_periods: int = 0,
                 cfg=None) -> None:
        cfg = cfg or _config()
        s = cfg.settings
        self.cfg = cfg
        self.clock = VirtualClock(100.0)
        self.arm = SimArm(clock=self.clock, home=cfg.cell.home_T_B_tcp)
        self.wrist = SimEffector(clock=self.clock)
        # config/sim.toml's limits, as oralnavd --demo uses them
        settings = LoopSettings.from_config(s.control, s.safety)
        self.period = settings.period
        self.control = InProcessControl(self.arm, self.wrist, settings,
                                        SpeedLimiter.from_settings(s.safety))
        self.inputs = SimInputs(clock=self.clock)
        self.core = DaemonCore(self.control, WatchdogSet.from_settings(s.safety, self.period),
                               inputs=self.inputs, clock=self.clock.now)
        # the daemon's own wiring: the pipeline, its one source (the renderer) and the
        # navigation listening to it, with the ground-truth observer
        self.capture, self.nav, self.cell = build_navigation(cfg, self.core)
        self.source = self.capture.sources[0]
        self.cameras = self.source.make()
        self.k = 0
        self.camera_every = camera_every
        self.latency_periods = latency_periods
        self._late: list[tuple[int, dict]] = []   # (period of arrival, frames)

    async def start(self) -> None:
        import anyio
        await anyio.to_thread.run_sync(self.cell.prepare)
        for dev in (self.arm, self.wrist, self.inputs, self.cameras):
            await dev.start()

    async def close(self) -> None:
        for dev in (self.cameras, self.inputs, self.wrist, self.arm):
            await dev.close()
        await self.control.close()

    async def run(self, periods: int, until=lambda: False, frozen=lambda: False,
                  lateness: float = 0.0) -> None:
        for _ in range(periods):
            self.clock.advance(self.period)
            self.control.step(self.clock.now(), lateness)
            self.k += 1
            if self.k % self.camera_every == 0 and not frozen():
                self._late.append((self.k + self.latency_periods, await self.cameras.read()))
            while self._late and self._late[0][0] <= self.k:
                frames = self._late.pop(0)[1]
                if self.latency_periods:
                    now = self.clock.now()
                    frames = {n: dataclasses.replace(f, timestamp=now)
                              for n, f in frames.items()}
                await self.capture.process(self.source, frames)
            if self.k % SUPERVISE_EVERY == 0:
                self.core.supervise_once(self.clock.now())
            if until():
                return


async def start_procedure(c: Lockstep) -> None:
    """Register the cell's suture targets and start the procedure from READY."""
    await c.run(SUPERVISE_EVERY)  # the loop's first periods report the arm's state
    c.core.set_targets([SutureTarget(name=n, p_OM=tuple(float(x) for x in p))
                        for n, p in c.cfg.cell.targets_OM.items()], "test")
    c.core.supervise_once(c.clock.now())
    assert c.core.supervisor.state.value == "READY"
    c.core.procedure("start", "test")
