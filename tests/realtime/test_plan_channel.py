"""Issue 6, item 5: the plan channel that carries a GuidePlan to the control process. The
loop's end never blocks and costs about a microsecond per period when empty (measured
here; the target is under 1 % of a 2 ms period); a plan larger than the pipe arrives
whole over several periods, none of which reads more than a chunk; a frame that does
not unpickle is reported, never installed; the daemon's end never blocks either: what
the pipe cannot take waits in its outbox, and a second plan is refused meanwhile."""

from __future__ import annotations

import mmap
import os
import resource
import time

import numpy as np
import pytest

from oralnav.control.guidance.guided_motion import GuidedMotion, GuidePlan
from oralnav.daemon.guidance import plan_insertion
from oralnav.realtime import plan_channel
from oralnav.realtime.plan_channel import (
    HEADER,
    READ_CHUNK,
    ChannelError,
    PlanInbox,
    PlanSender,
    decode,
    encode,
)
from tests.daemon.guide_cell import T_OM_F, small_scene


@pytest.fixture(scope="module")
def plan(tmp_path_factory) -> GuidePlan:
    return plan_insertion(small_scene(tmp_path_factory.mktemp("scene")), T_OM_F, "test",
                          7).plan


@pytest.fixture
def channel():
    r, w = os.pipe()
    inbox, sender = PlanInbox(r), PlanSender(w)
    yield inbox, sender
    inbox.close()
    sender.close()


def _deliver(inbox: PlanInbox, sender: PlanSender) -> tuple[tuple, list[float]]:
    """Poll as the loop does, flushing as the daemon's tick does, until a frame is whole;
    the message and each poll's cost (s)."""
    costs: list[float] = []
    out = None
    while out is None:
        t0 = time.perf_counter()
        out = inbox.poll()
        costs.append(time.perf_counter() - t0)
        sender.flush()
        assert len(costs) < 10_000
    return out, costs


def test_plan_crosses_whole(channel, plan):
    """A sent plan comes out equal (pose, model, fixture) with its number, once, over as
    many periods as it has chunks (this plan is about 180 kB with its rod check);
    None (clear the plan) crosses too; an empty pipe gives None."""
    inbox, sender = channel
    assert inbox.poll() is None
    frame = encode(1, plan)
    sender.send(frame)
    (seq, got), costs = _deliver(inbox, sender)
    assert seq == 1 and isinstance(got, GuidePlan)
    assert len(costs) >= len(frame) // READ_CHUNK          # at most a chunk per period
    assert np.array_equal(got.T_F_tool, plan.T_F_tool)
    assert np.array_equal(got.model.rho, plan.model.rho)
    assert np.array_equal(got.fixture.target, plan.fixture.target)
    GuidedMotion(got)  # usable as it arrives
    assert inbox.poll() is None and sender.pending == 0
    sender.send(encode(2, None))
    assert inbox.poll() == (2, None)


def test_unreadable_frame_is_reported_not_installed(channel):
    """A payload that does not unpickle comes out as an exception with its number (the
    loop refuses that number); the channel goes on working."""
    inbox, sender = channel
    payload = b"not a pickle"
    sender.send(HEADER.pack(3, len(payload)) + payload)
    seq, got = inbox.poll()
    assert seq == 3 and isinstance(got, Exception)
    sender.send(encode(4, None))
    assert inbox.poll() == (4, None)


@pytest.mark.parametrize("payload, why", [
    (b"\x01", "too short for its table"),
    (b"\x00\x00\x00\x00", "names 0 sections"),
    (b"\x05\x00\x00\x00" + bytes(8), "names 5 sections"),
    (b"\x01\x00\x00\x00" + (1000).to_bytes(8, "little") + bytes(20), "section 0"),
])
def test_a_payload_whose_table_does_not_fit_is_named(payload, why):
    """A payload whose section table is short, empty or points past its end is refused
    with what does not fit (the loop then reports it as an unreadable plan)."""
    with pytest.raises(ValueError, match=why):
        decode(memoryview(payload))


def test_arrays_come_back_as_writable_views_of_the_frame():
    """The plan's contiguous arrays travel out of band: they come back equal, writable
    and aligned, viewing the frame's own memory (no copy); a non-contiguous one comes back
    equal too (pickled in band)."""
    grid = np.arange(24, dtype=np.float32).reshape(2, 3, 4)
    sliced = np.arange(20.0).reshape(4, 5)[:, ::2]
    frame = bytearray(encode(5, {"grid": grid, "sliced": sliced, "name": "p"}))
    got = decode(memoryview(frame)[HEADER.size:])
    assert np.array_equal(got["grid"], grid) and np.array_equal(got["sliced"], sliced)
    assert got["name"] == "p" and got["grid"].flags.writeable and got["grid"].flags.aligned
    assert np.shares_memory(got["grid"], np.frombuffer(frame, np.uint8))
    got["grid"][0, 0, 0] = -1.0
    assert grid[0, 0, 0] == 0.0


def test_sender_never_blocks(channel, monkeypatch):
    """With nobody reading, a frame larger than the pipe is written in part and the rest
    kept (no waiting); another frame is refused while that one is under way; a frame over
    MAX_FRAME is refused before anything is written."""
    inbox, sender = channel
    big = encode(1, b"x" * (2 * sender.capacity))
    t0 = time.perf_counter()
    sender.send(big)
    assert 0 < sender.pending < len(big)
    with pytest.raises(ChannelError, match="busy"):
        sender.send(encode(2, None))
    assert sender.flush() is False
    assert time.perf_counter() - t0 < 0.05
    (seq, got), _ = _deliver(inbox, sender)
    assert seq == 1 and got == b"x" * (2 * sender.capacity)
    monkeypatch.setattr(plan_channel, "MAX_FRAME", 1000)
    with pytest.raises(ChannelError, match="more than the control channel takes"):
        sender.send(encode(3, b"y" * 2000))
    assert sender.pending == 0 and inbox.poll() is None


def test_completing_a_frame_takes_no_fresh_memory(channel, plan):
    """The cause of a slow completing period, counted rather than timed: the period that
    completes a 2.4 MB plan page-faults no more than one chunk's pages (an in-band pickle
    gave its arrays fresh memory: 457 faults, 1.3-1.6 ms on this VM), and the period that
    reads the header faults in none of the payload (a zero-filled buffer took them all)."""
    inbox, sender = channel
    sender.send(encode(1, (plan, np.ones((11, 205, 205), np.float32))))
    faults, out = [], None
    while out is None:
        before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        out = inbox.poll()
        faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
        sender.flush()
    assert len(faults) > 30 and max(faults) <= 2 * READ_CHUNK // mmap.PAGESIZE, faults


@pytest.mark.alone  # a timing bound: 1.07 ms against 1 ms beside the parallel suite
def test_poll_costs_about_a_microsecond_per_period(channel, plan):
    """Per-period cost of the loop's end: an empty poll (every period but those that
    bring a plan) averages well under 10 us (measured 0.4 us: 0.02 % of a 2 ms
    period); while a plan arrives each period reads at most one chunk (about 10 us), and
    the period that completes it unpickles it and builds the GuidedMotion in well under
    1 ms (measured 0.15 ms for this plan and 0.24 ms for a 2.4 MB one, the size of the
    paper's cylinder case with its rod check; 1.1 ms on CI's VM before the arrays came
    out of band)."""
    inbox, sender = channel
    for _ in range(1000):
        inbox.poll()
    n = 20000
    t0 = time.perf_counter()
    for _ in range(n):
        inbox.poll()
    empty = (time.perf_counter() - t0) / n
    chunk: list[float] = []
    figures = []
    # the plan, and the plan padded to 2 MB with a float32 grid as the rod check holds
    for payload in (plan, (plan, np.ones((11, 205, 205), np.float32))):
        frame = encode(1, payload)
        last = []
        for _ in range(5):
            sender.send(frame)
            (_, got), costs = _deliver(inbox, sender)
            t0 = time.perf_counter()
            GuidedMotion(got if isinstance(got, GuidePlan) else got[0])
            last.append(costs[-1] + time.perf_counter() - t0)
            chunk.extend(costs[:-1])
        figures.append(f"{len(frame) / 1e3:.0f} kB in {len(costs)} periods, the last "
                       f"{np.median(last) * 1e3:.2f} ms")
        assert np.median(last) < 1e-3
    print(f"plan channel: empty poll {empty * 1e6:.2f} us per period; "
          f"{'; '.join(figures)} (unpickle and GuidedMotion); {np.median(chunk) * 1e6:.0f} "
          f"us per chunk (max {max(chunk) * 1e6:.0f})")
    assert empty < 10e-6
    assert np.median(chunk) < 0.1e-3
