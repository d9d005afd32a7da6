"""Issue 8, the wrist's drive in the daemon: the control process driving the ``modbus``
end-effector against the emulated drive unit (a pymodbus server in this process, reached
over loopback TCP). A drive fault latches the stop with the drive's own words; the reset is
refused while the fault is present; the operator's device recovery (POST /recover/effector)
runs the drive's fault reset, and then the reset succeeds."""

from __future__ import annotations

import json
import logging
import time

import anyio
import numpy as np
import pytest

from oralnav.config.daemon import load_config
from oralnav.daemon.control_loop import LoopSettings
from oralnav.daemon.control_process import ControlProcess, DriverSpec, ProcessSpec
from oralnav.daemon.core import DaemonCore
from oralnav.drivers.io.sim import SimInputs
from oralnav.safety.errors import StateError
from oralnav.safety.limits import SpeedLimiter
from oralnav.safety.watchdogs import WatchdogSet
from oralnav.sim.modbus_drive import ModbusDriveServer

from ..helpers import LOADED_MACHINE


@pytest.fixture
async def cell():
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    cfg = load_config()
    home = np.eye(4)
    home[:3, 3] = [0.0, 0.0, 0.3]
    with ModbusDriveServer() as drive:
        proc = ControlProcess(ProcessSpec(
            arm=DriverSpec("sim", {"home": home}),
            effector=DriverSpec("modbus", {"host": "127.0.0.1", "port": drive.port,
                                           "silence_timeout": 0.2}),
            settings=LoopSettings(rate_hz=500.0, stale_pose=0.5, driver_silence=0.3,
                                  **LOADED_MACHINE),
            limiter=SpeedLimiter(0.25, 0.5)))
        await proc.start()
        inputs = SimInputs()
        await inputs.start()
        core = DaemonCore(proc, WatchdogSet.from_settings(cfg.settings.safety, 0.002),
                          inputs=inputs)
        try:
            yield core, drive
        finally:
            await inputs.close()
            await proc.close()


async def _supervise_until(core: DaemonCore, pred, timeout: float = 5.0) -> None:
    t0 = time.monotonic()
    while True:
        core.supervise_once(time.monotonic())
        if pred():
            return
        assert time.monotonic() - t0 < timeout, "condition not reached in time"
        await anyio.sleep(0.01)


async def test_a_drive_fault_latches_and_the_operator_recovers_it(cell) -> None:
    """issue 8 (bad input, a drive fault): the fault latches the stop naming the axis and
    its error code; reset is refused while it is present; recovery is refused unless the
    stop is latched; POST /recover/effector clears it, then the reset returns to READY."""
    core, drive = cell
    await _supervise_until(core, lambda: core.supervisor.state.value == "READY")
    with pytest.raises(StateError, match="only while the stop is latched"):
        core.recover("effector", "alice")

    drive.fault_axis(1, 0x2310)
    await _supervise_until(core, lambda: core.supervisor.state.value == "FAULT")
    status = core.status()
    assert "end-effector fault: axis 1 error 0x2310" in json.dumps(status["safety"])
    assert status["control_loop"]["wrist_fault"] == "axis 1 error 0x2310"
    with pytest.raises(StateError, match="end-effector: axis 1 error 0x2310"):
        core.reset("alice")

    core.recover("effector", "alice")
    await _supervise_until(core, lambda: core.status()["control_loop"]["wrist_fault"] is None)
    core.reset("alice")
    await _supervise_until(core, lambda: core.supervisor.state.value == "READY")
