"""What the daemon-core tests share: a real control process on the simulated arm (its
wrist from the caller), the core over it with the shipped safety settings, and a wait that
runs the supervisor until a condition holds."""

from __future__ import annotations

import time

import anyio
import numpy as np

from oralnav.config.daemon import load_config
from oralnav.daemon.core import DaemonCore
from oralnav.realtime.control_loop import LoopSettings
from oralnav.realtime.control_process import ControlProcess, DriverSpec, ProcessSpec
from oralnav.safety.limits import SpeedLimiter
from oralnav.safety.watchdogs import WatchdogSet
from tests.helpers import LOADED_MACHINE


def home_pose() -> np.ndarray:
    """The simulated arm's home: 0.3 m above the base, tool aligned with it."""
    T = np.eye(4)
    T[:3, 3] = [0.0, 0.0, 0.3]
    return T


def control_process(effector: DriverSpec | None = None,
                    driver_silence: float = 0.2) -> ControlProcess:
    """A control process (not started) at 500 Hz on the simulated arm at :func:`home_pose`
    and ``effector`` (default: the simulated wrist)."""
    return ControlProcess(ProcessSpec(
        arm=DriverSpec("sim", {"home": home_pose()}),
        effector=effector if effector is not None else DriverSpec("sim"),
        settings=LoopSettings(rate_hz=500.0, stale_pose=0.5, driver_silence=driver_silence,
                              **LOADED_MACHINE),
        limiter=SpeedLimiter(0.25, 0.5)))


def daemon_core(proc: ControlProcess, inputs: object) -> DaemonCore:
    """The core over ``proc`` and ``inputs``, watchdogs from the shipped sim.toml."""
    cfg = load_config()
    return DaemonCore(proc, WatchdogSet.from_settings(cfg.settings.safety, 0.002),
                      inputs=inputs)


async def supervise_until(core: DaemonCore, pred, timeout: float = 3.0) -> None:
    """Run the supervisor every 5 ms until ``pred()``; fail after ``timeout`` s."""
    t0 = time.monotonic()
    while True:
        core.supervise_once(time.monotonic())
        if pred():
            return
        assert time.monotonic() - t0 < timeout, "condition not reached in time"
        await anyio.sleep(0.005)
