"""Issue 8, serial I/O: the e-stop and foot pedal read from a serial box through pyserial,
tested through a real pty pair against the simulated box (``oralnav.sim.peers.serial_box``). A
silent line, garbage, a stuck sequence number and an unplugged box are each a named fault
that reads the e-stop pressed; the input recovers by itself when the box speaks again."""

from __future__ import annotations

import re
import time
from pathlib import Path

import anyio
import pytest

from oralnav.drivers.errors import DriverInitError
from oralnav.drivers.io import inputs_class, open_inputs
from oralnav.drivers.io.serial_link import MAX_LINE, SerialInputs, encode_line, parse_line
from oralnav.sim.peers.serial_box import SerialBox

#: generous: the suite runs on a loaded 2-core machine
WAIT = 3.0


async def _until(pred, timeout: float = WAIT) -> None:
    t0 = time.monotonic()
    while not pred():
        assert time.monotonic() - t0 < timeout, "condition not reached in time"
        await anyio.sleep(0.005)


def test_lines_match_the_documented_format():
    """issue 8 serial: the status line format of docs/formats.md, checked against golden
    lines written out by hand (CRC-16/CCITT-FALSE, whose check value for b"123456789" is
    0x29B1)."""
    assert encode_line(12, False, True) == b"$OSIO,12,0,1*3841\n"
    assert encode_line(12, True, False) == b"$OSIO,12,1,0*1F50\n"
    assert encode_line(0, False, False) == b"$OSIO,0,0,0*E629\n"
    line = parse_line(b"$OSIO,12,1,0*1F50\r")
    assert (line.seq, line.estop_pressed, line.pedal_pressed) == (12, True, False)


@pytest.mark.parametrize("raw, why", [
    (b"$OSIO,12,0,1*1F50", "bad CRC 1F50"),       # e-stop and pedal swapped in transit
    (b"OSIO,12,0,1*3841", "not a \\$OSIO line"),
    (b"$OSIO,12,0,1*38G1", "not four hex digits"),
    (b"\x00\xff\xfe", "not a \\$OSIO line"),
    (b"", "not a \\$OSIO line"),
])
def test_malformed_lines_are_refused_by_name(raw, why):
    """issue 8 serial (bad input): garbage, a wrong CRC (digits swapped) or a missing start
    is refused with a message saying what is wrong."""
    with pytest.raises(ValueError, match=why):
        parse_line(raw)


@pytest.mark.parametrize("body, why", [
    (b"OSIO,12,0", "expected \\$OSIO,<seq>"),
    (b"XXIO,12,0,1", "expected \\$OSIO,<seq>"),
    (b"OSIO,70000,0,1", "seq b'70000' is not in"),
    (b"OSIO,-1,0,1", "seq b'-1' is not in"),
    (b"OSIO,1,2,1", "must be 0 or 1"),
])
def test_well_framed_but_wrong_fields_are_refused(body, why):
    """issue 8 serial (bad input): a line with a good CRC but wrong fields is refused."""
    import binascii

    raw = b"$%s*%04X" % (body, binascii.crc_hqx(body, 0xFFFF))
    with pytest.raises(ValueError, match=why):
        parse_line(raw)


@pytest.mark.parametrize("kwargs, why", [
    ({"port": ""}, "port must be a device path"),
    ({"port": "/dev/x", "baudrate": 0}, "baudrate"),
    ({"port": "/dev/x", "heartbeat_timeout": float("nan")}, "heartbeat_timeout"),
    ({"port": "/dev/x", "recover_lines": 0}, "recover_lines"),
    ({"port": "/dev/x", "reopen_backoff": (2.0, 1.0)}, "reopen_backoff"),
])
def test_bad_arguments_raise_init_errors(kwargs, why):
    """issue 8 serial: a malformed setting is a DriverInitError naming it, before any I/O."""
    with pytest.raises(DriverInitError, match=why):
        SerialInputs(**kwargs)


def test_registered_as_serial():
    """issue 8 serial: the backend is found by name in the inputs registry."""
    assert inputs_class("serial") is SerialInputs


async def test_reads_the_box_and_follows_its_buttons():
    """issue 8 serial: after start() the input is connected and reads what the box reports;
    timestamps advance with each line; no line is lost or bad on a clean link."""
    with SerialBox(rate_hz=200) as box:
        async with open_inputs("serial", port=box.path) as ins:
            st = ins.state()
            assert st.connected and st.fault is None
            assert not st.estop_pressed and not st.pedal_pressed
            box.press_pedal()
            await _until(lambda: ins.state().pedal_pressed)
            box.press_estop()
            await _until(lambda: ins.state().estop_pressed)
            t0 = ins.state().timestamp
            await _until(lambda: ins.state().timestamp > t0)
            box.release_estop()
            box.release_pedal()
            await _until(lambda: not ins.state().estop_pressed
                         and not ins.state().pedal_pressed)
            assert ins.state().connected
            assert ins.lines >= 3 and ins.bad_lines == 0


async def test_a_silent_line_is_a_fault_and_recovers():
    """issue 8 serial: a box that stops writing is a fault within the heartbeat timeout (the
    e-stop reads pressed, the reason names the silence); when it speaks again the input
    reads again after recover_lines good lines."""
    with SerialBox(rate_hz=200) as box:
        async with SerialInputs(box.path, heartbeat_timeout=0.05) as ins:
            box.silence()
            await _until(lambda: not ins.state().connected)
            st = ins.state()
            assert st.estop_pressed and not st.pedal_pressed
            assert "silent" in st.fault and box.path in st.fault
            box.resume()
            await _until(lambda: ins.state().connected)
            assert not ins.state().estop_pressed


async def test_a_stuck_sequence_number_is_silence():
    """issue 8 serial: a box repeating its last line (seq not advancing) gives no
    heartbeat."""
    with SerialBox(rate_hz=200) as box:
        async with SerialInputs(box.path, heartbeat_timeout=0.05) as ins:
            box.repeat()
            sent = box.sent
            await _until(lambda: not ins.state().connected)
            assert box.sent > sent  # the box kept writing
            assert "silent" in ins.state().fault
            box.resume()
            await _until(lambda: ins.state().connected)


@pytest.mark.parametrize("junk, why", [
    (b"\x00\xff noise\n", "not a \\$OSIO line"),
    (b"$OSIO,5,0,1*1F50\n", "bad CRC"),
    (b"A" * (MAX_LINE + 10), "without a newline"),
])
async def test_garbage_is_a_named_fault_then_recovers(junk, why):
    """issue 8 serial (bad input): garbage on the line faults the input (the fault quotes
    what was wrong and stays in last_fault); after recover_lines good lines it reads again;
    the driver does not crash."""
    with SerialBox(rate_hz=100) as box:
        async with SerialInputs(box.path, recover_lines=3) as ins:
            assert ins.last_fault is None
            box.garble(junk)
            await _until(lambda: ins.bad_lines >= 1)
            assert ins.last_fault.startswith(f"garbage on serial line {box.path}")
            assert re.search(why, ins.last_fault)
            await _until(lambda: ins.state().connected)
            assert ins.bad_lines == 1


async def test_garbage_blocks_the_input_until_good_lines_follow():
    """issue 8 serial (bad input): with a slow box, the fault after garbage lasts until
    recover_lines good lines have arrived."""
    with SerialBox(rate_hz=20) as box:
        async with SerialInputs(box.path, recover_lines=5, heartbeat_timeout=0.2) as ins:
            lines = ins.lines
            box.garble(b"#$%&\n")
            await _until(lambda: ins.bad_lines == 1)
            st = ins.state()
            assert not st.connected and st.estop_pressed and "garbage" in st.fault
            await _until(lambda: ins.state().connected)
            assert ins.lines >= lines + 5


async def test_an_unplugged_box_is_reopened_under_its_link(tmp_path: Path):
    """issue 8 serial: unplugging the box is a fault naming the port; plugged in again (a
    new pty behind the same udev-like link) it is reopened and reads again."""
    link = tmp_path / "osio"
    with SerialBox(rate_hz=200, link=link) as box:
        async with SerialInputs(str(link), reopen_backoff=(0.02, 0.1)) as ins:
            box.press_estop()
            await _until(lambda: ins.state().estop_pressed)
            box.unplug()
            await _until(lambda: not ins.state().connected)
            assert str(link) in ins.state().fault
            assert ins.state().estop_pressed
            box.release_estop()
            box.plug()
            await _until(lambda: ins.state().connected)
            assert not ins.state().estop_pressed
            assert ins.reopens == 1


async def test_a_missing_box_at_start_is_a_fault_not_a_crash(tmp_path: Path):
    """issue 8 serial (bad input): a box not plugged in at start: start() returns after
    connect_timeout with the input in fault (e-stop pressed, the path named); the box
    plugged in later is found."""
    link = tmp_path / "osio"
    ins = SerialInputs(str(link), connect_timeout=0.1, reopen_backoff=(0.02, 0.1))
    async with ins:
        st = ins.state()
        assert not st.connected and st.estop_pressed and str(link) in st.fault
        with SerialBox(rate_hz=200, link=link):
            await _until(lambda: ins.state().connected)
    st = ins.state()
    assert not st.connected and st.estop_pressed and st.fault == "closed"


async def test_fail_safe_before_start_and_after_close():
    """issue 8 serial: not started and closed read fail-safe; close() is idempotent and
    safe before start(); start() twice is refused."""
    ins = SerialInputs("/dev/does-not-exist")
    await ins.close()
    ins = SerialInputs("/dev/does-not-exist", connect_timeout=0.05)
    st = ins.state()
    assert st.estop_pressed and not st.connected and st.fault == "not started"
    with SerialBox() as box:
        ins = SerialInputs(box.path)
        await ins.start()
        with pytest.raises(DriverInitError, match="twice"):
            await ins.start()
        await ins.close()
        await ins.close()
        assert ins.state().estop_pressed and not ins.state().connected
