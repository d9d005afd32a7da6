"""Issue 8, serial I/O in the daemon: the core reading a serial e-stop box (the simulated box
on a real pty). A pressed e-stop, garbage on the line, a silent box and an unplugged box
each latch ESTOP with a reason that names the cause; the status shows the input's fault;
reset is refused until the box reads released again, and then succeeds."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from oralnav.daemon.core import DaemonCore
from oralnav.drivers.io import open_inputs
from oralnav.safety.errors import StateError
from oralnav.sim.peers.serial_box import SerialBox
from tests.daemon.core_rig import control_process, daemon_core, supervise_until


@pytest.fixture
async def cell(tmp_path: Path):
    proc = control_process()
    link = tmp_path / "osio"
    box = SerialBox(rate_hz=200, link=link)
    box.plug()
    inputs = open_inputs("serial", port=str(link), heartbeat_timeout=0.05,
                         reopen_backoff=(0.02, 0.1))
    await proc.start()
    await inputs.start()
    core = daemon_core(proc, inputs)
    try:
        yield core, box, inputs
    finally:
        await inputs.close()
        await proc.close()
        box.unplug()


def _state(core: DaemonCore) -> str:
    return core.supervisor.state.value


async def _reset_when_released(core: DaemonCore, box: SerialBox) -> None:
    await supervise_until(core, lambda: core.status()["inputs"]["connected"]
                           and not core.status()["inputs"]["estop_pressed"])
    core.reset("operator")
    await supervise_until(core, lambda: _state(core) == "READY")


async def test_serial_estop_faults_latch_and_recover(cell) -> None:
    """issue 8 serial (bad input): the box's e-stop, garbage, silence and unplugging each
    latch ESTOP naming the cause (status shows it), never crash the daemon, and the stop
    can be reset once the box reads released again."""
    core, box, inputs = cell
    await supervise_until(core, lambda: _state(core) == "READY")
    assert core.status()["inputs"]["fault"] is None

    box.press_estop()
    await supervise_until(core, lambda: _state(core) == "ESTOP")
    assert "emergency stop pressed" in json.dumps(core.status()["safety"])
    await supervise_until(core, lambda: bool(core.control.read_status()["latched"]))
    with pytest.raises(StateError, match="e-stop"):
        core.reset("operator")
    box.release_estop()
    await _reset_when_released(core, box)

    causes = [
        (lambda: box.garble(b"\x07\x07 garbage \xff\n"), "garbage on serial line"),
        (box.silence, "silent for"),
        (box.unplug, str(box.link)),
    ]
    for make, why in causes:
        make()
        await supervise_until(core, lambda: _state(core) == "ESTOP")
        status = core.status()
        assert why in json.dumps(status["safety"]), (why, status["safety"])
        assert status["inputs"]["estop_pressed"] and not status["inputs"]["connected"]
        if why == "silent for":
            box.resume()
        elif why == str(box.link):
            with pytest.raises(StateError):
                core.reset("operator")  # the box is gone: the input reads pressed
            box.plug()
        await _reset_when_released(core, box)
    await supervise_until(core, lambda: not bool(core.control.read_status()["latched"]))
