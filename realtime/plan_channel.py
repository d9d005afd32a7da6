"""The plan channel: guided-insertion plans from the daemon to the control process.

A :class:`~oralnav.control.guidance.guided_motion.GuidePlan` holds numpy arrays, the surrogate
model and its certified rod check (distance grids: 2 to 6 MB for the example scenes),
far more than the fixed shared records carry, and it changes rarely (once per
insertion). It travels through an OS pipe instead, one frame per plan::

    seq (uint64, little endian) | length (uint64) | payload
    payload: k (uint32) | k section sizes (uint64) | the sections, each from a 16-byte offset
    sections: the pickle of the plan (or of None), then its arrays' bytes, out of band

Neither end ever blocks:

- the daemon's end (:class:`PlanSender`) is non-blocking. A frame goes into an outbox;
  each :meth:`PlanSender.flush` writes what the pipe takes and keeps the rest for the next
  call (the daemon's supervision tick, 50 Hz). The pipe's buffer is raised to 1 MiB where
  Linux allows, so most plans go at once. One frame at a time: the next is accepted
  only once the loop has acknowledged the previous (:meth:`ControlPort.set_guide`);
- the control loop's end (:class:`PlanInbox`) is polled once per period. An empty pipe
  costs one ``poll(2)`` with a zero timeout (``tests/realtime/test_plan_channel.py``
  measures the whole call at about 1 us, under 0.1 % of a 2 ms period). When bytes are
  there it reads at most :data:`READ_CHUNK` of them (tens of microseconds), so a large
  plan arrives over a few periods rather than stalling one; the period that completes a
  frame unpickles it.

The frame's memory is what makes the completing period cheap. The payload is read into an
anonymous mapping, whose pages the kernel supplies as each chunk is first written, so the
page faults are spread over the reading periods (a zero-filled buffer would take all of
them in the header's period: 1.4 ms for a 2 MB plan here). The plan's numpy arrays are
pickled out of band (protocol 5) and come back as views of that buffer, so unpickling
allocates and copies nothing large: an in-band pickle gave each array fresh memory, and
its 457 page faults made the completing period 1.3-1.6 ms for the same plan, most of a
2 ms period.

Unpickling happens in the control process. It imports and compiles nothing there: the
child imports :mod:`oralnav.control.guidance.guided_motion` and runs one guided step on a small
plan before its loop starts (numba's compiled rod check is loaded then, not mid-period).
"""

from __future__ import annotations

import logging
import mmap
import os
import pickle
import select
import struct
from typing import Any

from oralnav.realtime.errors import RealtimeError

log = logging.getLogger(__name__)

#: Frame header: sequence number, payload length (bytes).
HEADER = struct.Struct("<QQ")
#: The payload's section count, and each section's size (bytes).
COUNT = struct.Struct("<I")
SIZE = struct.Struct("<Q")
#: Sections start on multiples of this many bytes from the payload's start (the mapping
#: is page-aligned), so the arrays viewed in place are aligned for their dtype.
ALIGN = 16
#: Most bytes the loop reads from the pipe in one period.
READ_CHUNK = 65536
#: Pipe capacity asked for (bytes); Linux's unprivileged maximum by default.
WANTED_CAPACITY = 1 << 20
#: Capacity assumed where it cannot be read (POSIX guarantees far less; Linux gives 64 KiB).
DEFAULT_CAPACITY = 65536
#: Largest plan frame accepted (bytes): at READ_CHUNK per 2 ms period, 64 MiB take 2 s.
MAX_FRAME = 64 << 20


class ChannelError(RealtimeError, RuntimeError):
    """The plan channel cannot carry a plan now (busy, broken, or the plan too large)."""


def _capacity(fd: int) -> int:
    """Raise the pipe's buffer to :data:`WANTED_CAPACITY` where possible; its size."""
    try:
        import fcntl

        try:
            fcntl.fcntl(fd, fcntl.F_SETPIPE_SZ, WANTED_CAPACITY)
        except OSError:
            pass  # over /proc/sys/fs/pipe-max-size: keep what the kernel gives
        return int(fcntl.fcntl(fd, fcntl.F_GETPIPE_SZ))
    except (ImportError, AttributeError, OSError):
        return DEFAULT_CAPACITY


def _pad(n: int) -> int:
    """Bytes that bring offset ``n`` to the next multiple of :data:`ALIGN`."""
    return -n % ALIGN


def encode(seq: int, plan: Any) -> bytes:
    """One frame: ``seq`` (>= 1) and the pickled ``plan`` (or None: clear the plan), its
    contiguous arrays' bytes out of band."""
    buffers: list[pickle.PickleBuffer] = []
    pickled = pickle.dumps(plan, protocol=5, buffer_callback=buffers.append)
    sections = [memoryview(pickled)] + [b.raw() for b in buffers]
    parts: list[bytes | memoryview] = [COUNT.pack(len(sections))]
    parts += [SIZE.pack(sec.nbytes) for sec in sections]
    at = COUNT.size + SIZE.size * len(sections)
    for sec in sections:
        parts += [bytes(_pad(at)), sec]
        at += _pad(at) + sec.nbytes
    payload = b"".join(parts)
    return HEADER.pack(seq, len(payload)) + payload


def decode(payload: memoryview) -> Any:
    """The plan in a frame's ``payload``; its out-of-band arrays are views of ``payload``
    (nothing large is copied). ``ValueError`` for a payload whose sections do not fit."""
    if payload.nbytes < COUNT.size:
        raise ValueError(f"the payload is {payload.nbytes} bytes, too short for its table")
    (k,) = COUNT.unpack_from(payload)
    at = COUNT.size + SIZE.size * k
    if k < 1 or at > payload.nbytes:
        raise ValueError(f"the payload's table names {k} sections, which do not fit in "
                         f"{payload.nbytes} bytes")
    sections = []
    for i in range(k):
        (n,) = SIZE.unpack_from(payload, COUNT.size + SIZE.size * i)
        at += _pad(at)
        if at + n > payload.nbytes:
            raise ValueError(f"section {i} ({n} bytes at {at}) runs past the payload's "
                             f"{payload.nbytes} bytes")
        sections.append(payload[at:at + n])
        at += n
    return pickle.loads(sections[0], buffers=sections[1:])


def check_size(frame_bytes: int) -> None:
    """:class:`ChannelError` for a frame over :data:`MAX_FRAME`."""
    if frame_bytes > MAX_FRAME:
        raise ChannelError(
            f"the plan is {frame_bytes / 2**20:.1f} MiB, more than the control channel "
            f"takes ({MAX_FRAME / 2**20:.0f} MiB): use a coarser surrogate model (fewer "
            "slices or points)")


class PlanSender:
    """The daemon's end: the pipe's write descriptor, non-blocking, with an outbox."""

    def __init__(self, fd: int) -> None:
        self.fd = fd
        os.set_blocking(fd, False)
        self.capacity = _capacity(fd)
        self.broken: str | None = None
        self._out = memoryview(b"")

    @property
    def pending(self) -> int:
        """Bytes of the current frame not yet in the pipe."""
        return len(self._out)

    def send(self, frame: bytes) -> None:
        """Queue one whole frame and write what the pipe takes now; :meth:`flush` writes
        the rest later. Never blocks. :class:`ChannelError` while an earlier frame is not
        yet all written, or when the channel is broken (the loop then never completes a
        frame, so it installs nothing)."""
        if self.broken is not None:
            raise ChannelError(f"the plan channel is broken ({self.broken}); restart the "
                               "daemon")
        check_size(len(frame))
        if self._out:
            raise ChannelError(f"the plan channel is busy ({len(self._out)} bytes of the "
                               "previous plan not yet written)")
        self._out = memoryview(frame)
        self.flush()

    def flush(self) -> bool:
        """Write as much of the outbox as the pipe takes, without blocking; True when it
        is empty."""
        while self._out and self.broken is None:
            try:
                n = os.write(self.fd, self._out[:self.capacity])
            except BlockingIOError:
                return False
            except OSError as exc:  # the loop's end is gone
                self.broken = f"write failed: {exc}"
                self._out = memoryview(b"")
                log.error("plan channel: %s", self.broken)
                return False
            self._out = self._out[n:]
        return not self._out

    def close(self) -> None:
        try:
            os.close(self.fd)
        except OSError:
            pass


class PlanInbox:
    """The control loop's end: the pipe's read descriptor, polled once per period. A frame's
    payload is read straight into an anonymous mapping of its size (no regrowing, no copy,
    pages faulted in as each chunk arrives), which its plan's arrays then view."""

    def __init__(self, fd: int) -> None:
        self.fd = fd
        os.set_blocking(fd, False)
        self._poll = select.poll()
        self._poll.register(fd, select.POLLIN)
        self._head = b""                       # header bytes read so far
        self._seq = 0
        self._payload: mmap.mmap | None = None  # the frame's payload, once its size is known
        self._size = 0                         # the frame's payload size (bytes)
        self._got = 0                          # payload bytes read so far
        self.closed = False                    # the daemon's end is gone (EOF)

    def poll(self) -> tuple[int, Any] | None:
        """``(seq, plan)`` once a whole frame has arrived, else None; never blocks, and
        reads at most one header and :data:`READ_CHUNK` payload bytes per call.

        ``plan`` is the unpickled object, or an exception instance when the payload could
        not be unpickled (the caller refuses that ``seq``).
        """
        if self.closed or not self._poll.poll(0):
            return None
        try:
            if self._payload is None:
                chunk = os.read(self.fd, HEADER.size - len(self._head))
                if not chunk:
                    self.closed = True
                    return None
                self._head += chunk
                if len(self._head) < HEADER.size:
                    return None
                self._seq, n = HEADER.unpack(self._head)
                # an anonymous mapping (never zero-filled here), of at least one byte
                self._head, self._payload, self._got = b"", mmap.mmap(-1, max(n, 1)), 0
                self._size = n
            want = min(READ_CHUNK, self._size - self._got)
            if want:
                with memoryview(self._payload) as view:
                    k = os.readv(self.fd, [view[self._got:self._got + want]])
                if k == 0:
                    self.closed = True
                    return None
                self._got += k
        except BlockingIOError:
            return None
        if self._got < self._size:
            return None
        payload, self._payload = self._payload, None
        try:
            return self._seq, decode(memoryview(payload)[:self._size])
        except Exception as exc:  # a bad frame is refused, never installed
            log.error("plan %d could not be read: %s: %s", self._seq, type(exc).__name__,
                      exc)
            return self._seq, exc

    def close(self) -> None:
        try:
            self._poll.unregister(self.fd)
        except (KeyError, ValueError, OSError):
            pass
        try:
            os.close(self.fd)
        except OSError:
            pass
