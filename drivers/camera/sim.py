"""Simulated cameras: images come from a frame source handed over at construction.

The simulated cell (built by the daemon, never imported here) renders every camera of the
rig at one instant. It is given to the cameras as a :class:`FrameSource`. Rendering is
blocking CPU work, so each capture runs in a worker thread (``anyio.to_thread``), never on
the event loop.

- :class:`SimCamera`: one camera (a :class:`Camera`, registered as backend ``"sim"``).
- :class:`SimCameraSet`: several cameras captured together, like ``ReplayRig``: each
  ``read()`` returns ``{name: CameraFrame}`` rendered at one instant, with one timestamp and
  counters in step.

The cameras do not pace themselves: each ``read()`` captures once, at whatever instant the
source renders (a cell on a virtual clock renders its current time). ``freeze()`` simulates
a stalled camera: ``read()`` then waits, delivering nothing, until ``unfreeze()`` or
``close()``. A stalled camera therefore looks like a stalled real one: no new counter, no new
timestamp, and a reader blocked in ``read()``, so a watchdog on the age of the last frame
trips however the reader is written (returning the same frame again would hide the stall
from a watchdog that only checks that reads return).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Mapping, Sequence
from typing import Protocol, runtime_checkable

import anyio
import anyio.to_thread
import numpy as np

from ..errors import DriverError, DriverInitError, DriverIOError
from ..lifecycle import LifecycleState
from .base import Camera, CameraFrame, FrameStream

__all__ = ["FrameSource", "SimCamera", "SimCameraSet"]

# How often a read on a frozen camera looks again (wall seconds). Polling a flag, rather than
# waiting on an event, lets freeze() and unfreeze() be called from any thread.
_FROZEN_POLL_S = 0.002


@runtime_checkable
class FrameSource(Protocol):
    """What renders the simulated images (the simulated cell provides it)."""

    def capture(self, cameras: Sequence[str]) -> tuple[dict[str, np.ndarray], float]:
        """Render the named cameras at one instant; blocking.

        Returns:
            ``({name: image}, timestamp)``: one image per named camera, (H, W) uint8 mono8
            (or (H, W, 3) uint8 BGR), all showing the same instant, and that instant in
            seconds. Return fresh arrays: the frames keep them.
        """
        ...


def _check_size(size: object, what: str) -> tuple[int, int]:
    if (
        not isinstance(size, Sequence)
        or len(size) != 2
        or not all(isinstance(v, int | np.integer) and not isinstance(v, bool) for v in size)
        or min(size) <= 0  # type: ignore[type-var]
    ):
        raise DriverInitError(f"{what} must be (width, height) in pixels > 0, got {size!r}")
    return int(size[0]), int(size[1])  # type: ignore[index]


class _Capture:
    """The shared engine: names, sizes, one counter, capture in a thread, freeze."""

    def __init__(
        self,
        names: Sequence[str],
        source: FrameSource,
        sizes: Mapping[str, tuple[int, int]] | None,
    ) -> None:
        if isinstance(names, str) or not names:
            raise DriverInitError(f"need a non-empty sequence of camera names, got {names!r}")
        for name in names:
            if not isinstance(name, str) or not name:
                raise DriverInitError(f"camera names must be non-empty strings, got {name!r}")
        if len(set(names)) != len(names):
            raise DriverInitError(f"camera names must be unique, got {list(names)!r}")
        if not callable(getattr(source, "capture", None)):
            raise DriverInitError(
                f"source must have a capture(cameras) method (a FrameSource), got {source!r}"
            )
        self.names = tuple(names)
        self.source = source
        self.sizes: dict[str, tuple[int, int]] = {}
        if sizes is not None:
            unknown = set(sizes) - set(self.names)
            if unknown:
                raise DriverInitError(f"size given for unknown camera(s) {sorted(unknown)}")
            self.sizes = {n: _check_size(s, f"camera {n!r}: size") for n, s in sizes.items()}
        self._lock = threading.Lock()
        self._life = LifecycleState()  # changed under _lock
        self._counter = 0
        self._frozen = False

    @property
    def label(self) -> str:
        return ", ".join(repr(n) for n in self.names)

    async def start(self) -> None:
        with self._lock:
            self._life.begin_start(
                f"camera {self.label}: start() called twice (build a new camera after close)"
            )
        if len(self.sizes) < len(self.names):
            # One probe capture, discarded: its instant is already past when read() comes.
            try:
                images, _ = await self._capture()
            except DriverIOError as exc:
                raise DriverInitError(f"cannot start: {exc}") from exc
            for name in self.names:
                self.sizes.setdefault(name, _image_size(images[name]))
        with self._lock:
            self._life.finish_start()  # False when close() came during the probe: stays closed

    async def read(self) -> dict[str, CameraFrame]:
        while True:
            with self._lock:
                if not self._life.running:
                    raise DriverIOError(
                        f"camera {self.label}: read() after close()" if self._life.closed
                        else f"camera {self.label}: read() needs start() first and no close()"
                    )
                frozen = self._frozen
            if not frozen:
                break
            await anyio.sleep(_FROZEN_POLL_S)
        images, timestamp = await self._capture()
        frames: dict[str, CameraFrame] = {}
        with self._lock:
            if not self._life.running:
                raise DriverIOError(f"camera {self.label}: closed during read()")
            for name in self.names:
                size = _image_size(images[name])
                if size != self.sizes[name]:
                    raise DriverIOError(
                        f"camera {name!r}: frame size {size} differs from the camera size "
                        f"{self.sizes[name]}"
                    )
                frames[name] = CameraFrame(images[name], timestamp, self._counter, name)
            self._counter += 1
        return frames

    async def _capture(self) -> tuple[dict[str, np.ndarray], float]:
        try:
            result = await anyio.to_thread.run_sync(self.source.capture, self.names)
        except DriverError:
            raise
        except Exception as exc:  # a renderer error is a failed capture, not a crash
            raise DriverIOError(
                f"camera {self.label}: capture failed ({type(exc).__name__}: {exc})"
            ) from exc
        return _check_result(result, self.names)

    def close(self) -> None:
        with self._lock:
            self._life.close()

    def freeze(self) -> None:
        with self._lock:
            self._frozen = True

    def unfreeze(self) -> None:
        with self._lock:
            self._frozen = False

    @property
    def frozen(self) -> bool:
        with self._lock:
            return self._frozen


def _image_size(image: np.ndarray) -> tuple[int, int]:
    return int(image.shape[1]), int(image.shape[0])


def _check_result(
    result: object, names: Sequence[str]
) -> tuple[dict[str, np.ndarray], float]:
    if not (isinstance(result, tuple) and len(result) == 2 and isinstance(result[0], Mapping)):
        raise DriverIOError(
            f"frame source must return ({{name: image}}, timestamp), got {type(result).__name__}"
        )
    images, timestamp = result
    try:
        timestamp = float(timestamp)
    except (TypeError, ValueError):
        timestamp = math.nan
    if not math.isfinite(timestamp):
        raise DriverIOError(
            f"frame source returned timestamp {result[1]!r}; need finite seconds"
        )
    out: dict[str, np.ndarray] = {}
    for name in names:
        image = images.get(name)
        if image is None:
            raise DriverIOError(f"camera {name!r}: the frame source returned no image for it")
        if not (
            isinstance(image, np.ndarray)
            and image.dtype == np.uint8
            and (image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3))
            and image.size > 0
        ):
            raise DriverIOError(
                f"camera {name!r}: the frame source returned "
                f"{getattr(image, 'shape', type(image).__name__)} "
                f"{getattr(image, 'dtype', '')}; need (H, W) or (H, W, 3) uint8"
            )
        out[name] = image
    return out, timestamp


class SimCamera(Camera):
    """One simulated camera fed by ``source``.

    Args:
        name: the camera's name, passed to ``source.capture([name])``.
        source: the :class:`FrameSource` (the simulated cell).
        size: ``(width, height)`` px if known; otherwise ``start()`` learns it from one probe
            capture. A frame of another size makes ``read()`` raise ``DriverIOError``.

    Frames carry the source's timestamp (seconds, the cell's clock) and a counter from 0.
    """

    def __init__(
        self, name: str, source: FrameSource, size: tuple[int, int] | None = None
    ) -> None:
        super().__init__(name)
        sizes = None if size is None else {name: size}
        self._engine = _Capture([name], source, sizes)

    async def start(self) -> None:
        await self._engine.start()
        self._size = self._engine.sizes[self.name]

    async def read(self) -> CameraFrame:
        return (await self._engine.read())[self.name]

    async def close(self) -> None:
        self._engine.close()

    def freeze(self) -> None:
        """Stall the camera: ``read()`` waits until :meth:`unfreeze` or ``close()``."""
        self._engine.freeze()

    def unfreeze(self) -> None:
        """End a :meth:`freeze`; the next frame is a fresh capture."""
        self._engine.unfreeze()

    @property
    def frozen(self) -> bool:
        return self._engine.frozen


class SimCameraSet(FrameStream[dict[str, CameraFrame]]):
    """Several simulated cameras captured together (a synchronised stereo rig, say).

    ``read()`` makes one ``source.capture(names)`` call and returns ``{name: CameraFrame}``
    in the order of ``names``: every frame has the same timestamp and the same counter.

    Args:
        names: camera names, unique.
        source: the :class:`FrameSource`.
        sizes: ``{name: (width, height)}`` for some or all cameras; the rest are learnt by one
            probe capture at ``start()``.
    """

    def __init__(
        self,
        names: Sequence[str],
        source: FrameSource,
        sizes: Mapping[str, tuple[int, int]] | None = None,
    ) -> None:
        self._engine = _Capture(names, source, sizes)

    @property
    def names(self) -> tuple[str, ...]:
        return self._engine.names

    @property
    def sizes(self) -> dict[str, tuple[int, int]]:
        """``{name: (width, height)}`` px, complete once ``start()`` has returned."""
        if len(self._engine.sizes) < len(self._engine.names):
            raise DriverError(f"cameras {self._engine.label}: sizes are known after start()")
        return dict(self._engine.sizes)

    async def start(self) -> None:
        await self._engine.start()

    async def read(self) -> dict[str, CameraFrame]:
        return await self._engine.read()

    async def close(self) -> None:
        self._engine.close()

    def freeze(self) -> None:
        """Stall every camera of the set: ``read()`` waits until :meth:`unfreeze`/``close()``."""
        self._engine.freeze()

    def unfreeze(self) -> None:
        self._engine.unfreeze()

    @property
    def frozen(self) -> bool:
        return self._engine.frozen

    def __repr__(self) -> str:
        return f"SimCameraSet(names={list(self.names)!r})"
