"""Issue 8, contract tests: every safety-input backend, simulated and real, keeps the same
promises: fail-safe before start, after a lost link and after close; buttons read as
pressed; a silent input's timestamp stops advancing (so no stale reading passes for a live
one). The serial backend runs against the simulated box on a real pty."""

from __future__ import annotations

import time
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass

import anyio
import pytest

from oralnav.drivers.io import SafetyInputs, open_inputs
from oralnav.sim.peers.serial_box import SerialBox

WAIT = 3.0


@dataclass
class Harness:
    """A backend's inputs and the hands that work its buttons and link."""

    inputs: SafetyInputs
    press_estop: Callable[[], None]
    release_estop: Callable[[], None]
    press_pedal: Callable[[], None]
    release_pedal: Callable[[], None]
    go_silent: Callable[[], None]
    link_down: Callable[[], None]
    link_up: Callable[[], None]


async def _sim(tmp_path) -> AsyncIterator[Harness]:
    ins = open_inputs("sim")
    yield Harness(ins, ins.press_estop, ins.release_estop, ins.press_pedal, ins.release_pedal,
                  ins.inject_silence, ins.inject_disconnect, ins.clear)


async def _serial(tmp_path) -> AsyncIterator[Harness]:
    link = tmp_path / "osio"
    box = SerialBox(rate_hz=200, link=link)
    box.plug()
    try:
        ins = open_inputs("serial", port=str(link), heartbeat_timeout=0.05,
                          reopen_backoff=(0.02, 0.1))
        yield Harness(ins, box.press_estop, box.release_estop, box.press_pedal,
                      box.release_pedal, box.silence, box.unplug, box.plug)
    finally:
        box.unplug()


@pytest.fixture(params=["sim", "serial"])
async def harness(request, tmp_path) -> AsyncIterator[Harness]:
    make = {"sim": _sim, "serial": _serial}[request.param]
    gen = make(tmp_path)
    h = await gen.__anext__()
    try:
        yield h
    finally:
        await h.inputs.close()
        await gen.aclose()


async def _until(pred, timeout: float = WAIT) -> None:
    t0 = time.monotonic()
    while not pred():
        assert time.monotonic() - t0 < timeout, "condition not reached in time"
        await anyio.sleep(0.005)


def _fail_safe(ins: SafetyInputs) -> bool:
    st = ins.state()
    return st.estop_pressed and not st.pedal_pressed and not st.connected


async def test_fail_safe_until_started_and_after_close(harness: Harness):
    """issue 8 contract: not started and closed, every backend reads e-stop pressed, pedal
    released, not connected; close() is idempotent."""
    ins = harness.inputs
    harness.press_pedal()
    assert _fail_safe(ins)
    await ins.start()
    await _until(lambda: ins.state().connected)
    st = ins.state()
    assert st.fault is None and not st.estop_pressed
    await _until(lambda: ins.state().pedal_pressed)
    await ins.close()
    await ins.close()
    assert _fail_safe(ins)


async def test_buttons_read_as_pressed(harness: Harness):
    """issue 8 contract: what the buttons do shows in state()."""
    ins = harness.inputs
    await ins.start()
    harness.press_estop()
    await _until(lambda: ins.state().estop_pressed and ins.state().connected)
    harness.release_estop()
    harness.press_pedal()
    await _until(lambda: ins.state().pedal_pressed and not ins.state().estop_pressed)
    harness.release_pedal()
    await _until(lambda: not ins.state().pedal_pressed)


async def test_a_lost_link_reads_fail_safe_and_recovers(harness: Harness):
    """issue 8 contract: a lost link reads fail-safe (the pedal held on the device reads
    released); when the link returns the input reads again."""
    ins = harness.inputs
    await ins.start()
    harness.press_pedal()
    await _until(lambda: ins.state().pedal_pressed)
    harness.link_down()
    await _until(lambda: _fail_safe(ins))
    harness.link_up()
    await _until(lambda: ins.state().connected and ins.state().pedal_pressed)


async def test_a_silent_input_stops_its_timestamp(harness: Harness):
    """issue 8 contract: a silent input's timestamp stops advancing while time goes on, so
    the reading's age shows the silence (the serial backend also faults by itself)."""
    ins = harness.inputs
    await ins.start()
    await _until(lambda: ins.state().connected)
    harness.go_silent()
    await anyio.sleep(0.02)
    t0 = ins.state().timestamp
    await anyio.sleep(0.1)
    assert ins.state().timestamp == t0
