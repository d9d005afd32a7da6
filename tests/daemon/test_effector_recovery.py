"""Issue 8, the wrist's drive in the daemon: the control process driving the ``modbus``
end-effector against the emulated drive unit (a pymodbus server in this process, reached
over loopback TCP). A drive fault latches the stop with the drive's own words; the reset is
refused while the fault is present; the operator's device recovery (POST /recover/effector)
runs the drive's fault reset, and then the reset succeeds."""

from __future__ import annotations

import json
import logging

import pytest

from oralnav.drivers.io.sim import SimInputs
from oralnav.realtime.control_process import DriverSpec
from oralnav.safety.errors import StateError
from oralnav.sim.peers.modbus_drive import ModbusDriveServer
from tests.daemon.core_rig import control_process, daemon_core, supervise_until

WAIT = 5.0  # s: the drive's fault reset goes over Modbus from another process


@pytest.fixture
async def cell():
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    with ModbusDriveServer() as drive:
        # the drive's host watchdog at 1 s, as the protocol-peer cell has it: at the
        # driver's default 100 ms, a control process at normal scheduling on a loaded
        # 2-core machine let it expire at start-up (0x8130 on every axis), which is not
        # the fault this test injects
        proc = control_process(DriverSpec("modbus", {"host": "127.0.0.1", "port": drive.port,
                                                     "silence_timeout": 0.2,
                                                     "watchdog_ms": 1000}),
                               driver_silence=0.3)
        await proc.start()
        inputs = SimInputs()
        await inputs.start()
        core = daemon_core(proc, inputs)
        try:
            yield core, drive
        finally:
            await inputs.close()
            await proc.close()


async def test_a_drive_fault_latches_and_the_operator_recovers_it(cell) -> None:
    """issue 8 (bad input, a drive fault): the fault latches the stop naming the axis and
    its error code; reset is refused while it is present; recovery is refused unless the
    stop is latched; POST /recover/effector clears it, then the reset returns to READY."""
    core, drive = cell
    await supervise_until(core, lambda: core.supervisor.state.value == "READY", WAIT)
    with pytest.raises(StateError, match="only while the stop is latched"):
        core.recover("effector", "alice")

    drive.fault_axis(1, 0x2310)
    await supervise_until(core, lambda: core.supervisor.state.value == "FAULT", WAIT)
    status = core.status()
    assert "end-effector fault: axis 1 error 0x2310" in json.dumps(status["safety"])
    assert status["control_loop"]["wrist_fault"] == "axis 1 error 0x2310"
    with pytest.raises(StateError, match="end-effector: axis 1 error 0x2310"):
        core.reset("alice")

    core.recover("effector", "alice")
    await supervise_until(core, lambda: core.status()["control_loop"]["wrist_fault"] is None, WAIT)
    core.reset("alice")
    await supervise_until(core, lambda: core.supervisor.state.value == "READY", WAIT)
