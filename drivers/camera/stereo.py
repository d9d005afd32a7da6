"""Stereo synchronisation: pair the frames of two cameras that capture independently.

Two cameras on a shared hardware trigger expose on the same pulses, but each numbers and
stamps its frames on its own, and each can lose frames on its own link. Two free-running
cameras do not even expose together. :class:`FramePairer` matches their frames:

- ``by="timestamp"``: frames whose ``timestamp`` (host arrival time, s, one clock for both
  cameras; or, with ``clock="device"``, the cameras' own ``device_timestamp`` when their
  clocks are synchronised) differ by at most ``tolerance`` s pair; each frame pairs with
  the closest frame of the other camera within the tolerance.
- ``by="counter"``: frames pair when their trigger counters agree: a frame's counter is its
  ``frame_id`` (the camera's own frame number, :class:`~.aravis.AravisFrame`), or its
  ``counter`` for cameras that have none. The cameras number from different starts, so the
  offset between them is ``counter_offset`` if given, else learnt from the first pair that
  matches by timestamp, and learnt again when a camera's ``epoch`` changes (it reconnected or
  restarted its counter). Once learnt, frames lost in transfer (a gap in one camera's
  numbers) never shift the pairing. A counter match whose timestamps differ by more than
  ``tolerance`` means a camera missed a trigger (it numbers exposures, not pulses): the
  offset is learnt again.

A frame that can no longer pair (the other camera's frames have moved past it, or more than
``max_pending`` frames wait for a partner) is dropped and counted per camera in ``dropped``;
``paired`` counts the pairs. Frames of each camera must come in capture order.

:class:`StereoCamera` reads two :class:`Camera` objects through a pairer and returns
``{left_name: frame, right_name: frame}`` per ``read()``, like ``ReplayRig`` and
``SimCameraSet``. It reads whichever camera has no frame waiting for a partner, so it needs
no background task; each camera's driver buffers what arrives meanwhile.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from collections.abc import Callable
from typing import Literal

import anyio

from ..errors import DriverError, DriverInitError, DriverIOError
from .base import Camera, CameraFrame, FrameStream

__all__ = ["FramePairer", "StereoCamera", "trigger_counter"]

log = logging.getLogger(__name__)

PairBy = Literal["timestamp", "counter"]
Clock = Literal["host", "device"]


def trigger_counter(frame: CameraFrame) -> int:
    """The frame's trigger counter: the camera's ``frame_id`` when it has one, else the
    driver's delivered-frame ``counter``."""
    frame_id = getattr(frame, "frame_id", None)
    return int(frame.counter if frame_id is None else frame_id)


class FramePairer:
    """Pairs the frames of two cameras pushed to it one at a time (no I/O; see the module).

    Args:
        names: the two camera names, ``(left, right)``; frames carry them in ``camera``.
        by: ``"timestamp"`` or ``"counter"``.
        tolerance: s; the most two paired timestamps may differ (``by="timestamp"``, and
            for learning the counter offset).
        counter_offset: left counter minus right counter for frames of the same trigger;
            ``None`` learns it.
        max_pending: frames of one camera kept waiting for a partner; older ones are dropped.
        counter_of: the trigger counter of a frame (default :func:`trigger_counter`).
        clock: which time pairs: ``"host"``, the frames' ``timestamp`` (arrival on this
            computer, one clock for every camera), or ``"device"``, their
            ``device_timestamp`` (only for cameras whose clocks are synchronised, by PTP
            say; it leaves out the transfer delay).
    """

    def __init__(
        self,
        names: tuple[str, str],
        *,
        by: PairBy = "timestamp",
        tolerance: float = 0.005,
        counter_offset: int | None = None,
        max_pending: int = 16,
        counter_of: Callable[[CameraFrame], int] = trigger_counter,
        clock: Clock = "host",
    ) -> None:
        if (not isinstance(names, tuple | list) or len(names) != 2
                or not all(isinstance(n, str) and n for n in names) or names[0] == names[1]):
            raise DriverInitError(f"stereo pairing needs two different camera names, "
                                  f"got {names!r}")
        if by not in ("timestamp", "counter"):
            raise DriverInitError(f"stereo pairing by must be 'timestamp' or 'counter', "
                                  f"got {by!r}")
        if (isinstance(tolerance, bool) or not isinstance(tolerance, int | float)
                or not math.isfinite(tolerance) or tolerance < 0):
            raise DriverInitError(f"stereo pairing tolerance must be a finite number >= 0 s, "
                                  f"got {tolerance!r}")
        if counter_offset is not None and (isinstance(counter_offset, bool)
                                           or not isinstance(counter_offset, int)):
            raise DriverInitError(f"counter_offset must be an integer or None, "
                                  f"got {counter_offset!r}")
        if isinstance(max_pending, bool) or not isinstance(max_pending, int) or max_pending < 1:
            raise DriverInitError(f"max_pending must be an integer >= 1, got {max_pending!r}")
        if clock not in ("host", "device"):
            raise DriverInitError(f"stereo pairing clock must be 'host' or 'device', "
                                  f"got {clock!r}")
        self.clock: Clock = clock
        self.names = (names[0], names[1])
        self.by: PairBy = by
        self.tolerance = float(tolerance)
        self.fixed_offset = counter_offset
        self.offset: int | None = counter_offset
        self.max_pending = max_pending
        self.counter_of = counter_of
        self._queues: dict[str, deque[CameraFrame]] = {n: deque() for n in self.names}
        self._epochs: dict[str, int | None] = dict.fromkeys(self.names)
        self._last: dict[str, CameraFrame | None] = dict.fromkeys(self.names)
        self._turn = 0
        self.paired = 0
        self.dropped: dict[str, int] = dict.fromkeys(self.names, 0)

    # -- queries ----------------------------------------------------------------------------

    def pending(self, name: str) -> int:
        """Frames of camera ``name`` waiting for a partner."""
        return len(self._queues[name])

    def last(self, name: str) -> CameraFrame | None:
        """The last frame of camera ``name`` pushed."""
        return self._last[name]

    def waiting_for(self) -> str:
        """The camera to read next: one with no frame waiting for a partner (at most one
        camera has frames waiting); when neither has, the cameras take turns."""
        left, right = self.names
        if self._queues[left] and not self._queues[right]:
            return right
        if self._queues[right] and not self._queues[left]:
            return left
        name = self.names[self._turn]
        self._turn ^= 1
        return name

    @property
    def by_counter(self) -> bool:
        """Pairing on counters now (``by="counter"`` and the offset known)."""
        return self.by == "counter" and self.offset is not None

    # -- pairing ----------------------------------------------------------------------------

    def push(self, frame: CameraFrame) -> dict[str, CameraFrame] | None:
        """Add one frame; return ``{left: frame, right: frame}`` when it completes a pair."""
        name = frame.camera
        if name not in self._queues:
            raise DriverIOError(f"stereo pairing of {self.names}: frame of unknown camera "
                                f"{name!r}")
        self._check_order(name, frame)
        return self._place(frame)

    def _place(self, frame: CameraFrame) -> dict[str, CameraFrame] | None:
        name = frame.camera
        other = self.names[1] if name == self.names[0] else self.names[0]
        mine, theirs = self._queues[name], self._queues[other]
        key = self._key(frame)
        tol = self._tolerance()
        # Frames of the other camera too old to pair with this one can pair with no later
        # frame of this camera either.
        while theirs and self._key(theirs[0]) < key - tol:
            self._drop(theirs.popleft(), "no partner")
        candidates = []
        for i, waiting in enumerate(theirs):
            gap = abs(self._key(waiting) - key)
            if gap > tol:
                break
            candidates.append((gap, i))
        if candidates:
            _, best = min(candidates)
            skew = abs(self.time_of(theirs[best]) - self.time_of(frame))
            if self.by_counter and self.fixed_offset is None and skew > self.tolerance:
                # same trigger count, different moments: a camera missed a trigger
                log.warning("stereo %s/%s: counters match but times differ by %.6f s; a "
                            "camera missed a trigger: learning the counter offset again",
                            *self.names, skew)
                self.offset = None
                return self._place(frame)
            for _ in range(best):
                self._drop(theirs.popleft(), "a closer frame paired")
            partner = theirs.popleft()
            return self._pair(frame, partner)
        if theirs:  # the other camera is already past this frame
            self._drop(frame, "no partner")
            return None
        mine.append(frame)
        while len(mine) > self.max_pending:
            self._drop(mine.popleft(), f"more than {self.max_pending} frames waiting")
        return None

    def clear(self) -> None:
        """Drop (and count) every frame waiting for a partner."""
        for queue in self._queues.values():
            while queue:
                self._drop(queue.popleft(), "cleared")

    def _pair(self, frame: CameraFrame, partner: CameraFrame) -> dict[str, CameraFrame]:
        left, right = self.names
        pair = {frame.camera: frame, partner.camera: partner}
        if self.by == "counter" and self.offset is None:
            self.offset = self.counter_of(pair[left]) - self.counter_of(pair[right])
            log.info("stereo %s/%s: counter offset %d learnt from times %.6f/%.6f",
                     left, right, self.offset, self.time_of(pair[left]), self.time_of(pair[right]))
        self.paired += 1
        return {left: pair[left], right: pair[right]}

    def time_of(self, frame: CameraFrame) -> float:
        """The time this pairer pairs ``frame`` on (see ``clock``), s."""
        if self.clock == "host":
            return frame.timestamp
        stamp = getattr(frame, "device_timestamp", None)
        if stamp is None:
            raise DriverIOError(f"stereo pairing on the device clock: frame {frame.counter} "
                                f"of {frame.camera!r} has no device_timestamp")
        return float(stamp)

    def _key(self, frame: CameraFrame) -> float:
        if not self.by_counter:
            return self.time_of(frame)
        counter = self.counter_of(frame)
        assert self.offset is not None
        return float(counter - self.offset if frame.camera == self.names[0] else counter)

    def _tolerance(self) -> float:
        return 0.0 if self.by_counter else self.tolerance

    def _check_order(self, name: str, frame: CameraFrame) -> None:
        """Relearn the counter offset when a camera's numbering restarts; keep each camera's
        queue in capture order."""
        epoch = getattr(frame, "epoch", None)
        last = self._last[name]
        restarted = epoch is not None and self._epochs[name] is not None \
            and epoch != self._epochs[name]
        if last is None:
            went_back = False
        elif self.by == "counter":
            went_back = self.counter_of(frame) <= self.counter_of(last)
        else:
            went_back = self.time_of(frame) < self.time_of(last)
        self._epochs[name] = epoch
        self._last[name] = frame
        if restarted or went_back:
            why = ("its time went back" if self.by == "timestamp" and not restarted
                   else "camera restarted its numbering")
            while self._queues[name]:
                self._drop(self._queues[name].popleft(), why)
            if self.by == "counter" and self.fixed_offset is None and self.offset is not None:
                log.info("stereo %s/%s: camera %r restarted its numbering; learning the "
                         "counter offset again", *self.names, name)
                self.offset = None
                # the other camera's waiting frames are keyed by counter: drop them too
                other = self.names[1] if name == self.names[0] else self.names[0]
                while self._queues[other]:
                    self._drop(self._queues[other].popleft(), "offset relearnt")

    def _drop(self, frame: CameraFrame, why: str) -> None:
        self.dropped[frame.camera] += 1
        level = logging.WARNING if self.dropped[frame.camera] == 1 else logging.DEBUG
        log.log(level, "stereo %s/%s: dropped frame %d of %r (t=%.6f): %s (%d dropped so far)",
                *self.names, frame.counter, frame.camera, frame.timestamp, why,
                self.dropped[frame.camera])


class StereoCamera(FrameStream[dict[str, CameraFrame]]):
    """Two cameras read as synchronised pairs (see the module docs).

    Args:
        left, right: the cameras (built, not started); their names must differ.
        by, tolerance, counter_offset, max_pending, clock: as for :class:`FramePairer`.
        max_unpaired: frames read in a row without a pair after which ``read()`` gives up
            with :class:`DriverIOError` (the cameras do not overlap: wrong tolerance, one
            camera not triggered...).

    ``start()`` starts both (and closes both if either fails); ``close()`` closes both. An
    error of either camera's ``read()`` propagates; frames waiting for a partner are kept.
    """

    def __init__(
        self,
        left: Camera,
        right: Camera,
        *,
        by: PairBy = "timestamp",
        tolerance: float = 0.005,
        counter_offset: int | None = None,
        max_pending: int = 16,
        max_unpaired: int = 64,
        clock: Clock = "host",
    ) -> None:
        for cam in (left, right):
            if not isinstance(cam, Camera):
                raise DriverInitError(f"stereo cameras must be Camera objects, got {cam!r}")
        if isinstance(max_unpaired, bool) or not isinstance(max_unpaired, int) \
                or max_unpaired < 1:
            raise DriverInitError(f"max_unpaired must be an integer >= 1, got {max_unpaired!r}")
        self.pairer = FramePairer((left.name, right.name), by=by, tolerance=tolerance,
                                  counter_offset=counter_offset, max_pending=max_pending,
                                  clock=clock)
        self.cameras: dict[str, Camera] = {left.name: left, right.name: right}
        self.max_unpaired = max_unpaired
        self.name = f"{left.name}+{right.name}"
        self._lock: anyio.Lock | None = None

    @property
    def paired(self) -> int:
        return self.pairer.paired

    @property
    def dropped(self) -> dict[str, int]:
        """Unpaired frames dropped, per camera."""
        return dict(self.pairer.dropped)

    async def start(self) -> None:
        self._lock = anyio.Lock()
        try:
            for camera in self.cameras.values():
                await camera.start()
        except BaseException:
            await self.close()
            raise

    async def read(self) -> dict[str, CameraFrame]:
        if self._lock is None:
            raise DriverIOError(f"stereo {self.name}: not started")
        async with self._lock:
            for _ in range(self.max_unpaired):
                name = self.pairer.waiting_for()
                pair = self.pairer.push(await self.cameras[name].read())
                if pair is not None:
                    return pair
            last = {n: self.pairer.last(n) for n in self.cameras}
            stamps = ", ".join(f"{n} t={self.pairer.time_of(f):.6f}" if f else f"{n} nothing"
                               for n, f in last.items())
            raise DriverIOError(
                f"stereo {self.name}: no pair in {self.max_unpaired} frames "
                f"(pairing by {self.pairer.by}, tolerance {self.pairer.tolerance:g} s; last "
                f"frames: {stamps}; dropped {self.pairer.dropped})")

    async def close(self) -> None:
        errors: list[DriverError] = []
        for camera in self.cameras.values():
            try:
                await camera.close()
            except DriverError as exc:  # close the other one all the same
                errors.append(exc)
        if errors:
            raise errors[0]

    def __repr__(self) -> str:
        left, right = self.cameras.values()
        return f"StereoCamera({left!r}, {right!r}, by={self.pairer.by!r})"
