"""Issue 4 drivers: safety inputs (e-stop, foot pedal) and their fail-safe reading."""

from __future__ import annotations

import pytest

from oralnav.drivers.clock import VirtualClock
from oralnav.drivers.errors import DriverInitError
from oralnav.drivers.io import InputState, SafetyInputs, open_inputs
from oralnav.drivers.io.sim import SimInputs


async def test_buttons_are_read_with_clock_time():
    """issue 4 drivers: the sim e-stop and pedal read what was pressed, stamped with the
    clock's time."""
    clock = VirtualClock(5.0)
    async with SimInputs(clock=clock) as inputs:
        assert inputs.state() == InputState(5.0, False, False, True)
        inputs.press_pedal()
        clock.advance(0.1)
        assert inputs.state() == InputState(5.1, False, True, True)
        inputs.press_estop()
        inputs.release_pedal()
        assert inputs.state() == InputState(5.1, True, False, True)
        inputs.release_estop()
        assert not inputs.state().estop_pressed


async def test_a_disconnected_input_reads_fail_safe():
    """issue 4 drivers: an input that is not connected (not started, link lost, closed) reads
    the e-stop as pressed and the pedal as released, whatever the buttons say."""
    clock = VirtualClock()
    inputs = SimInputs(clock=clock)
    inputs.press_pedal()
    assert inputs.state() == InputState(0.0, True, False, False)  # not started yet
    await inputs.start()
    assert inputs.state() == InputState(0.0, False, True, True)
    inputs.inject_disconnect()
    assert inputs.state() == InputState(0.0, True, False, False)
    inputs.clear()
    assert inputs.state().pedal_pressed and not inputs.state().estop_pressed
    await inputs.close()
    await inputs.close()
    assert inputs.state() == InputState(0.0, True, False, False)


def test_fail_safe_is_applied_by_the_base_class():
    """issue 4 drivers: SafetyInputs.state() makes any backend fail-safe, even one whose raw
    reading says 'released' while disconnected."""

    class Careless(SafetyInputs):
        def _read(self) -> InputState:
            return InputState(1.0, estop_pressed=False, pedal_pressed=True, connected=False)

        async def start(self) -> None:
            pass

        async def close(self) -> None:
            pass

    assert Careless().state() == InputState(1.0, True, False, False)


async def test_silence_freezes_the_reading():
    """issue 4 drivers: a silent input repeats its last reading (timestamp included) so a
    staleness watchdog can see it; clear() brings it back."""
    clock = VirtualClock()
    async with open_inputs("sim", clock=clock) as inputs:
        assert isinstance(inputs, SimInputs)
        inputs.inject_silence()
        clock.advance(1.0)
        inputs.press_estop()
        assert inputs.state() == InputState(0.0, False, False, True)
        inputs.clear()
        assert inputs.state() == InputState(1.0, True, False, True)
        with pytest.raises(DriverInitError, match="twice"):
            await inputs.start()
