"""The camera contract every backend (replay, sim, aravis, v4l2) implements.

A camera is a source of :class:`CameraFrame` objects. Its lifecycle is the driver layer's:
the constructor checks arguments and does no I/O, ``await start()`` opens the device (after
which :attr:`Camera.size` is known), ``await read()`` returns the next frame, and
``await close()`` releases everything and may be called any number of times. Cameras are async
context managers (``async with cam:`` starts and closes) and async iterators (``async for
frame in cam:`` reads until the source ends).
"""

from __future__ import annotations

import abc
from dataclasses import dataclass
from typing import Generic, Self, TypeVar

import numpy as np

from ..errors import DriverError, DriverInitError, EndOfStream
from ..lifecycle import AsyncLifecycle


@dataclass(frozen=True, eq=False)
class CameraFrame:
    """One captured image.

    Attributes:
        image: the pixels, shape (height, width) uint8 (mono8) unless the backend says
            otherwise (e.g. (height, width, 3) uint8 BGR when asked for colour).
        timestamp: capture time in seconds. Live backends give ``time.monotonic()`` seconds;
            replay gives the recorded capture time (see the backend).
        counter: frame counter of this camera, 0 for the first frame after ``start()``,
            +1 per frame delivered.
        camera: name of the camera that produced it.
    """

    image: np.ndarray
    timestamp: float
    counter: int
    camera: str


ItemT = TypeVar("ItemT")


class FrameStream(AsyncLifecycle, Generic[ItemT]):
    """``async with`` and ``async for`` over a source with ``start()``, ``read()`` and an
    idempotent ``close()``: a camera, or a set of cameras read in step. A failed
    ``start()`` closes what it opened; iteration ends at :class:`EndOfStream`."""

    async def read(self) -> ItemT:
        raise NotImplementedError

    def __aiter__(self) -> Self:
        return self

    async def __anext__(self) -> ItemT:
        try:
            return await self.read()
        except EndOfStream:
            raise StopAsyncIteration from None


class Camera(FrameStream[CameraFrame], abc.ABC):
    """Abstract camera: ``start()``, ``read()``, idempotent ``close()``.

    Backends set ``self._size`` in ``start()``; everything else is theirs.
    """

    def __init__(self, name: str) -> None:
        if not isinstance(name, str) or not name:
            raise DriverInitError(f"camera name must be a non-empty string, got {name!r}")
        self.name = name
        self._size: tuple[int, int] | None = None

    @property
    def size(self) -> tuple[int, int]:
        """Image ``(width, height)`` in pixels; known once ``start()`` has returned."""
        if self._size is None:
            raise DriverError(f"camera {self.name!r}: size is known only after start()")
        return self._size

    @abc.abstractmethod
    async def start(self) -> None:
        """Open the device; raise :class:`DriverInitError` naming what failed."""

    @abc.abstractmethod
    async def read(self) -> CameraFrame:
        """Return the next frame.

        Raises:
            DriverIOError: the device failed, or is not started / already closed.
            DriverTimeoutError: no frame came in time.
            EndOfStream: a finite source has no more frames.
        """

    @abc.abstractmethod
    async def close(self) -> None:
        """Release the device. Idempotent; safe before ``start()`` and after a failed one."""

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r})"
