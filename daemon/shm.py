"""Shared-memory records between the daemon and its control-loop process.

The 500 Hz control loop runs in a process of its own (docs/control_loop.md shows why: a
thread behind the GIL missed its period by up to 2-3 ms while tracking ran). The two
processes exchange a few fixed-size records, each a numpy structured scalar in a
``multiprocessing.shared_memory`` block guarded by a sequence lock:

- one writer per record; the writer makes the sequence odd, writes, makes it even again;
- a reader copies the record between two reads of the sequence and retries when the
  sequence was odd or moved, so it never sees a half-written record and never blocks the
  writer (the control loop must not wait on anything).

Records hold numbers only (poses as 4x4 float64 in metres, times in seconds on the
daemon's clock, flags as bools, reasons as fixed-size UTF-8 bytes).
"""

from __future__ import annotations

import time
from multiprocessing import shared_memory
from typing import Any

import numpy as np

#: Bytes kept for a reason string (UTF-8, truncated at a character boundary).
REASON_BYTES = 240


class ShmError(RuntimeError):
    """A shared record cannot be created, attached or read."""


class SharedRecord:
    """One structured record of ``dtype`` in shared memory, with a sequence lock.

    Create it in the daemon (``SharedRecord(dtype)``), pass ``.name`` to the child process
    and attach there (``SharedRecord(dtype, name=...)``). The creator unlinks the block in
    ``close()``; an attached side only closes its mapping.
    """

    def __init__(self, dtype: np.dtype, name: str | None = None) -> None:
        self.dtype = np.dtype(dtype)
        size = 8 + self.dtype.itemsize  # uint64 sequence, then the record
        self._owner = name is None
        try:
            self._shm = shared_memory.SharedMemory(name=name, create=self._owner, size=size)
        except (FileNotFoundError, OSError, ValueError) as exc:
            raise ShmError(f"shared record {name or '(new)'}: {exc}") from exc
        buf = self._shm.buf
        self._seq = np.ndarray((1,), dtype=np.uint64, buffer=buf, offset=0)
        self._rec = np.ndarray((1,), dtype=self.dtype, buffer=buf, offset=8)
        if self._owner:
            self._seq[0] = 0
            self._rec[0] = np.zeros((), dtype=self.dtype)

    @property
    def name(self) -> str:
        return self._shm.name

    def write(self, **values: Any) -> None:
        """Set the named fields (the others keep their values) as one update."""
        self._seq[0] += np.uint64(1)           # odd: a write is under way
        rec = self._rec[0]
        for key, value in values.items():
            rec[key] = value
        self._seq[0] += np.uint64(1)           # even: the record is whole again

    def read(self, retries: int = 10_000) -> np.void:
        """A consistent copy of the record."""
        for _ in range(retries):
            s0 = int(self._seq[0])
            if s0 & 1:
                time.sleep(0)  # the writer is mid-update; let it finish
                continue
            copy = self._rec[0].copy()
            if int(self._seq[0]) == s0:
                return copy
        raise ShmError(f"shared record {self.name}: no consistent read in {retries} tries "
                       "(is its writer stuck mid-update?)")

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
        shm.close()
        if self._owner:
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
