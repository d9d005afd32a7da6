"""Shared-memory records between the daemon and its control-loop process.

The 500 Hz control loop runs in a process of its own (docs/control_loop.md shows why: a
thread behind the GIL missed its period by up to 2-3 ms while tracking ran). The two
processes exchange a few fixed-size records, each a numpy structured scalar in a
``multiprocessing.shared_memory`` block: two copies of the record and a sequence number.

- One writer per record (a lock serialises the writer's threads). The sequence is odd while
  a write is under way and even when none is; ``sequence // 2`` records are complete, the
  latest in copy ``(sequence // 2) % 2``, and a write fills the other copy.
- A reader copies the latest complete record and keeps it if the writer did not start on
  that same copy meanwhile (two writes later); otherwise it reads again.

So neither side waits on the other. A single copy under a plain sequence lock made the
reader wait out a write the daemon had begun: a writer thread that lost the GIL mid-write
held the 2 ms loop for 27 ms here and 57-130 ms on a loaded CI machine, and the deadline
watchdog stopped the arm.

Records hold numbers only (poses as 4x4 float64 in metres, times in seconds on the
daemon's clock, flags as bools, reasons as fixed-size UTF-8 bytes).
"""

from __future__ import annotations

import threading
from multiprocessing import shared_memory
from typing import Any

import numpy as np

from oralnav.realtime.errors import RealtimeError

#: Bytes kept for a reason string (UTF-8, truncated at a character boundary).
REASON_BYTES = 240


class ShmError(RealtimeError, RuntimeError):
    """A shared record cannot be created, attached or read."""


class SharedRecord:
    """One structured record of ``dtype`` in shared memory, with a sequence lock.

    Create it in the daemon (``SharedRecord(dtype)``), pass ``.name`` to the child process
    and attach there (``SharedRecord(dtype, name=...)``). The creator unlinks the block in
    ``close()``; an attached side only closes its mapping.
    """

    def __init__(self, dtype: np.dtype, name: str | None = None) -> None:
        self.dtype = np.dtype(dtype)
        size = 8 + 2 * self.dtype.itemsize  # uint64 sequence, then two copies
        self._owner = name is None
        try:
            self._shm = shared_memory.SharedMemory(name=name, create=self._owner, size=size)
        except (FileNotFoundError, OSError, ValueError) as exc:
            raise ShmError(f"shared record {name or '(new)'}: {exc}") from exc
        buf = self._shm.buf
        self._seq = np.ndarray((1,), dtype=np.uint64, buffer=buf, offset=0)
        self._rec = np.ndarray((2,), dtype=self.dtype, buffer=buf, offset=8)
        self._lock = threading.Lock()
        self._mine: np.void | None = None  # the writer's copy of its latest record
        if self._owner:
            self._seq[0] = 0
            self._rec[:] = np.zeros((), dtype=self.dtype)

    @property
    def name(self) -> str:
        return self._shm.name

    def write(self, **values: Any) -> None:
        """Set the named fields (the others keep their values) as one update. Never waits
        on a reader."""
        with self._lock:
            # first write from this side: start from what is there; a value that does not
            # convert leaves both the shared record and this side's copy as they were
            mine = (self.read() if self._mine is None else self._mine).copy()
            for key, value in values.items():
                mine[key] = value
            self._mine = mine
            done = int(self._seq[0]) // 2
            self._seq[0] = np.uint64(2 * done + 1)       # odd: filling the other copy
            self._rec[(done + 1) % 2] = mine
            self._seq[0] = np.uint64(2 * done + 2)       # even: that copy is the latest

    def read(self, retries: int = 10_000) -> np.void:
        """A consistent copy of the latest complete record. Never waits on the writer: it
        retries only when the writer got two writes ahead during the copy."""
        for _ in range(retries):
            done = int(self._seq[0]) // 2
            copy = self._rec[done % 2].copy()
            # the writer starts on this copy again at sequence 2 * done + 3
            if int(self._seq[0]) < 2 * done + 3:
                return copy
        raise ShmError(f"shared record {self.name}: no consistent read in {retries} tries "
                       "(is its writer writing without pause?)")

    @property
    def sequence(self) -> int:
        """Completed writes so far times two (changes on every write)."""
        return int(self._seq[0])

    def close(self) -> None:
        """Release the mapping (and the block, on the creating side). Idempotent."""
        shm, self._shm = getattr(self, "_shm", None), None
        if shm is None:
            return
        # numpy views must go before the mapping can close
        del self._seq, self._rec
        _release(shm, self._owner)


class SharedRing:
    """The last ``slots`` entries of ``dtype`` appended by one writer, in shared memory:
    the arm's measured TCP history, which the daemon reads to place each camera frame's
    capture instant on the arm's trajectory.

    Layout: a uint64 count of completed appends, then ``slots`` entries, each a uint64
    sequence before its record. Append ``k`` (0-based) goes to slot ``k % slots``: the
    slot's sequence is set to ``2k + 1`` (odd: being written), the record copied, the
    sequence set to ``2k + 2``, then the count to ``k + 1``. A reader copies every slot
    and keeps those whose sequence was ``2k + 2`` both before and after its copy, for the
    ``k`` it expects there: so a torn or overwritten slot is left out, never returned.
    Appends write one slot, never the whole ring, and neither side waits on the other.

    Create it on one side (``SharedRing(dtype, slots)``) and attach on the other with
    ``name=``; the creator unlinks the block in ``close()``.
    """

    def __init__(self, dtype: np.dtype, slots: int, name: str | None = None) -> None:
        if isinstance(slots, bool) or not isinstance(slots, int) or slots < 2:
            raise ShmError(f"a shared ring needs slots >= 2 (an integer), got {slots!r}")
        self.dtype = np.dtype(dtype)
        self.slots = slots
        self._entry = np.dtype([("seq", "u8"), ("rec", self.dtype)])
        self._owner = name is None
        size = 8 + slots * self._entry.itemsize
        try:
            self._shm = shared_memory.SharedMemory(name=name, create=self._owner, size=size)
        except (FileNotFoundError, OSError, ValueError) as exc:
            raise ShmError(f"shared ring {name or '(new)'}: {exc}") from exc
        buf = self._shm.buf
        self._count = np.ndarray((1,), dtype=np.uint64, buffer=buf, offset=0)
        self._ring = np.ndarray((slots,), dtype=self._entry, buffer=buf, offset=8)
        self._lock = threading.Lock()
        if self._owner:
            self._count[0] = 0
            self._ring["seq"] = 0

    @property
    def name(self) -> str:
        return self._shm.name

    @property
    def count(self) -> int:
        """Appends completed so far."""
        return int(self._count[0])

    def append(self, **values: Any) -> None:
        """Add one entry (fields not given are zero); the oldest drops out. Never waits on
        a reader."""
        with self._lock:
            k = int(self._count[0])
            slot = self._ring[k % self.slots]
            rec = np.zeros((), dtype=self.dtype)
            for key, value in values.items():
                rec[key] = value
            self._ring["seq"][k % self.slots] = np.uint64(2 * k + 1)
            slot["rec"] = rec
            self._ring["seq"][k % self.slots] = np.uint64(2 * k + 2)
            self._count[0] = np.uint64(k + 1)

    def read(self) -> np.ndarray:
        """The entries still in the ring, oldest first, as a structured array of
        ``dtype`` (a copy); slots being overwritten during the copy are left out."""
        count = int(self._count[0])
        n = min(count, self.slots)
        if n == 0:
            return np.zeros(0, dtype=self.dtype)
        ks = np.arange(count - n, count, dtype=np.int64)
        idx = ks % self.slots
        before = self._ring["seq"][idx].copy()
        recs = self._ring["rec"][idx].copy()
        after = self._ring["seq"][idx]
        want = (2 * ks + 2).astype(np.uint64)
        ok = (before == want) & (after == want)
        return recs[ok]

    def close(self) -> None:
        """Release the mapping (and the block, on the creating side). Idempotent."""
        shm, self._shm = getattr(self, "_shm", None), None
        if shm is None:
            return
        del self._count, self._ring  # numpy views first, as for SharedRecord
        _release(shm, self._owner)


def _release(shm: shared_memory.SharedMemory, owner: bool) -> None:
    """Close a block's mapping; unlink the block too on the side that created it."""
    shm.close()
    if owner:
        try:
            shm.unlink()
        except FileNotFoundError:
            pass


def encode_reason(text: str) -> bytes:
    """``text`` as at most :data:`REASON_BYTES` bytes of UTF-8, cut at a character."""
    raw = text.encode("utf-8")[:REASON_BYTES]
    return raw.decode("utf-8", errors="ignore").encode("utf-8")


def decode_reason(raw: bytes | np.bytes_) -> str:
    return bytes(raw).rstrip(b"\0").decode("utf-8", errors="replace")
