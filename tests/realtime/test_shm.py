"""Issue 4, control process: the shared records between the daemon and the control loop.
A read always returns one whole record, and neither side waits on the other: a writer that
stalls mid-write (a daemon thread that lost the GIL) leaves the loop reading the last
complete record at once."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from oralnav.realtime.shm import (
    SharedRecord,
    SharedRing,
    ShmError,
    decode_reason,
    encode_reason,
)

PAIR = np.dtype([("a", "f8"), ("b", "f8"), ("big", "f8", (64,)), ("n", "i8")])


@pytest.fixture
def rec():
    r = SharedRecord(PAIR)
    yield r
    r.close()


def test_fields_not_written_keep_their_values_across_sides(rec: SharedRecord) -> None:
    """A write sets only the named fields; an attached side reads what the creator wrote,
    and its own first write starts from that record."""
    rec.write(a=1.0, b=-1.0, n=7)
    other = SharedRecord(PAIR, name=rec.name)
    try:
        got = other.read()
        assert (got["a"], got["b"], got["n"]) == (1.0, -1.0, 7)
        rec.write(a=2.0)
        got = other.read()
        assert (got["a"], got["b"], got["n"]) == (2.0, -1.0, 7)
        assert rec.sequence == 4
    finally:
        other.close()


def test_a_reader_never_waits_on_a_writer_stalled_mid_write(rec: SharedRecord) -> None:
    """With the sequence left odd (a write begun and not finished), read returns the last
    complete record at once instead of spinning until the writer resumes."""
    rec.write(a=1.0, b=-1.0)           # one record complete: it is in copy 1
    rec._seq[0] += np.uint64(1)        # a writer that began the next write and stalled
    rec._rec[0]["a"] = 99.0            # ... half-way through filling the other copy
    t0 = time.perf_counter()
    got = rec.read()
    assert time.perf_counter() - t0 < 0.001
    assert (got["a"], got["b"]) == (1.0, -1.0)


def test_concurrent_reads_see_only_whole_records(rec: SharedRecord) -> None:
    """A writer thread updating every field together as fast as it can: each record a
    reader in another thread copies is whole (a == -b == every element of big == n), and
    the records it sees never go back in time."""
    stop = threading.Event()

    def writer() -> None:
        k = 0
        while not stop.is_set():
            k += 1
            rec.write(a=float(k), b=-float(k), big=np.full(64, float(k)), n=k)

    t = threading.Thread(target=writer)
    t.start()
    try:
        last, reads, t_end = 0, 0, time.monotonic() + 0.3
        while time.monotonic() < t_end:
            got = rec.read()
            n = int(got["n"])
            assert got["a"] == n and got["b"] == -n and np.all(got["big"] == n)
            assert n >= last
            last, reads = n, reads + 1
        assert reads > 100 and last > 100
    finally:
        stop.set()
        t.join()


def test_a_writer_that_never_pauses_is_reported_not_waited_on(rec: SharedRecord) -> None:
    """If every try finds the writer two writes ahead, read gives up with an error that
    names the record instead of returning a torn copy."""
    rec.write(a=1.0)
    seq = rec._seq

    class Ahead:  # the sequence moves by two writes between every pair of looks
        def __init__(self) -> None:
            self.v = int(seq[0])

        def __getitem__(self, i: int) -> np.uint64:
            self.v += 4
            return np.uint64(self.v)

    rec._seq = Ahead()
    try:
        with pytest.raises(ShmError, match=rec.name):
            rec.read(retries=50)
    finally:
        rec._seq = seq


def test_reasons_are_cut_at_a_character_boundary() -> None:
    """A reason longer than the field keeps whole UTF-8 characters only."""
    raw = encode_reason("é" * 200)
    assert len(raw) <= 240 and decode_reason(raw) == "é" * (len(raw) // 2)


def test_a_write_that_does_not_convert_changes_nothing(rec: SharedRecord) -> None:
    """Bad input loses nothing: a write whose value does not fit its field raises, and
    neither the shared record nor the writer's next write carries its other fields."""
    rec.write(a=1.0, n=1)
    with pytest.raises(ValueError):
        rec.write(a=5.0, big=np.zeros(3))          # 3 values for a 64-value field
    got = rec.read()
    assert (got["a"], got["n"]) == (1.0, 1) and rec.sequence == 2
    rec.write(n=2)
    got = rec.read()
    assert (got["a"], got["n"]) == (1.0, 2)


# -- the arm history ring (issue 32: navigation places each frame on the arm's trajectory) --

SAMPLE = np.dtype([("t", "f8"), ("x", "f8", (3,))])


def test_ring_keeps_the_newest_entries_oldest_first_on_both_sides() -> None:
    """Issue 32: the ring holds the last ``slots`` appends, oldest first, and a side that
    attached by name reads the same; fields not given are zero."""
    ring = SharedRing(SAMPLE, 4)
    other = SharedRing(SAMPLE, 4, name=ring.name)
    try:
        assert len(ring.read()) == 0
        for k in range(6):
            ring.append(t=float(k), x=[k, 2 * k, 3 * k])
        got = other.read()
        assert got["t"].tolist() == [2.0, 3.0, 4.0, 5.0]
        assert got["x"][-1].tolist() == [5.0, 10.0, 15.0]
        ring.append(t=6.0)
        assert other.read()["x"][-1].tolist() == [0.0, 0.0, 0.0]
        assert ring.count == other.count == 7
    finally:
        other.close()
        ring.close()


def test_ring_leaves_out_a_slot_being_written() -> None:
    """Issue 32: a slot whose writer is mid-copy (its sequence odd, or of another append)
    is left out of a read, never returned torn."""
    ring = SharedRing(SAMPLE, 4)
    try:
        for k in range(4):
            ring.append(t=float(k))
        ring._ring["seq"][1] += 1  # as if the writer had begun overwriting slot 1
        assert ring.read()["t"].tolist() == [0.0, 2.0, 3.0]
    finally:
        ring.close()


def test_ring_refuses_a_useless_size() -> None:
    """Issue 32 (bad input): fewer than two slots is a named error."""
    with pytest.raises(ShmError, match="slots >= 2"):
        SharedRing(SAMPLE, 1)


def test_ring_reads_whole_entries_while_a_writer_appends() -> None:
    """Issue 32: reads racing a writer thread return only whole, increasing entries."""
    ring = SharedRing(SAMPLE, 64)
    stop = threading.Event()

    def writer() -> None:
        k = 0
        while not stop.is_set():
            ring.append(t=float(k), x=[k, k, k])
            k += 1

    th = threading.Thread(target=writer)
    th.start()
    try:
        for _ in range(2000):
            got = ring.read()
            assert np.all(np.diff(got["t"]) > 0)
            assert np.all(got["x"] == got["t"][:, None])
    finally:
        stop.set()
        th.join()
        ring.close()
