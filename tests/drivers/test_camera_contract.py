"""Issue 8 camera contract: one suite every camera backend passes (docs/drivers.md, "Camera
base"): the simulated camera, the replay camera, the Aravis camera against Aravis's
simulated GigE Vision camera, and the V4L2 camera where this machine has a capture device.

Each backend is built through the registry (``open_camera``); the constructor does no I/O,
``size`` needs ``start()``, frames are (H, W) uint8 with counters from 0 and timestamps that
do not go back (live backends: on ``time.monotonic()``), ``start()`` works once, ``close()``
is idempotent and safe before ``start()``, and reads leave the event loop running."""

from __future__ import annotations

import contextlib
import math
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import anyio
import cv2
import numpy as np
import pytest

from oralnav.drivers.camera import Camera, camera_class, open_camera
from oralnav.drivers.camera.v4l2 import diagnose_device, video_devices
from oralnav.drivers.errors import DriverError, DriverInitError, DriverIOError
from tests.drivers.test_camera_aravis import ARAVIS_MISSING, running_fakes

W, H = 32, 24


@dataclass
class Harness:
    """How to build one backend's camera, and what its timestamps mean."""

    backend: str
    make: Callable[[], Camera]
    live: bool  # timestamps on time.monotonic()


class Source:
    """A frame source for the simulated camera: a short blocking render per capture."""

    def __init__(self) -> None:
        self.captures = 0

    def capture(self, cameras):
        time.sleep(0.002)
        self.captures += 1
        images = {name: np.full((H, W), self.captures % 256, np.uint8) for name in cameras}
        return images, 50.0 + 0.04 * self.captures


def _replay_folder(path: Path) -> Path:
    path.mkdir()
    for i in range(5):
        cv2.imwrite(str(path / f"frame_{i}.png"), np.full((H, W), 40 * i, np.uint8))
    return path


def _v4l2_device() -> str | None:
    for path in video_devices():
        if diagnose_device(path) == "":
            return path
    return None


@contextlib.contextmanager
def _harness(backend: str, tmp_path: Path) -> Iterator[Harness]:
    if backend == "sim":
        source = Source()
        yield Harness("sim", lambda: open_camera("sim", name="cam", source=source), False)
    elif backend == "replay":
        folder = _replay_folder(tmp_path / "rec")
        yield Harness("replay", lambda: open_camera("replay", path=folder, name="cam",
                                                    loop=True), False)
    elif backend == "aravis":
        if ARAVIS_MISSING is not None:
            pytest.skip(ARAVIS_MISSING)
        with running_fakes() as make:
            fake = make()
            yield Harness("aravis", lambda: open_camera(
                "aravis", camera_id=fake.address, name="cam", region=(0, 0, W, H),
                frame_rate=100.0), True)
    else:
        device = _v4l2_device()
        if device is None:
            pytest.skip("no V4L2 capture device on this machine (none in CI: a virtual one "
                        "needs the v4l2loopback or vivid kernel module)")
        yield Harness("v4l2", lambda: open_camera("v4l2", device=device, name="cam"), True)


@pytest.fixture(params=["sim", "replay", "aravis", "v4l2"])
def harness(request, tmp_path) -> Iterator[Harness]:
    with _harness(request.param, tmp_path) as h:
        yield h


async def test_building_does_no_io_and_size_needs_start(harness: Harness):
    """issue 8 camera contract: open_camera builds an unstarted camera of the backend's
    class; size raises DriverError and read() DriverIOError until start(); close() before
    start() is fine, twice."""
    cam = harness.make()
    assert isinstance(cam, camera_class(harness.backend)) and isinstance(cam, Camera)
    assert cam.name == "cam"
    with pytest.raises(DriverError, match="after start"):
        _ = cam.size
    with pytest.raises(DriverIOError):
        await cam.read()
    await cam.close()
    await cam.close()


async def test_frames_keep_the_contract(harness: Harness):
    """issue 8 camera contract: after start() size is (width, height); frames are (H, W)
    uint8 mono8 of that size, named after the camera, counted 0, 1, 2... with finite
    timestamps that never go back; live backends stamp time.monotonic() seconds."""
    t0 = time.monotonic()
    async with harness.make() as cam:
        width, height = cam.size
        assert isinstance(width, int) and isinstance(height, int) and width > 0 and height > 0
        frames = [await cam.read() for _ in range(6)]
    t1 = time.monotonic()
    assert [f.counter for f in frames] == list(range(6))
    for f in frames:
        assert f.camera == "cam"
        assert isinstance(f.image, np.ndarray) and f.image.dtype == np.uint8
        assert f.image.shape == (height, width)
        assert math.isfinite(f.timestamp)
    stamps = [f.timestamp for f in frames]
    assert all(b >= a for a, b in zip(stamps, stamps[1:], strict=False))
    if harness.live:
        assert t0 <= stamps[0] and stamps[-1] <= t1


async def test_start_once_and_close_ends_reading(harness: Harness):
    """issue 8 camera contract: start() twice raises DriverInitError; after close() (any
    number of times) read() raises DriverIOError and start() DriverInitError."""
    cam = harness.make()
    await cam.start()
    try:
        with pytest.raises(DriverInitError):
            await cam.start()
        assert (await cam.read()).counter == 0
    finally:
        await cam.close()
    await cam.close()
    with pytest.raises(DriverIOError):
        await cam.read()
    with pytest.raises(DriverInitError):
        await cam.start()


async def test_async_with_and_async_for(harness: Harness):
    """issue 8 camera contract: `async with` starts and closes; `async for` reads frames in
    order."""
    cam = harness.make()
    counters = []
    async with cam:
        async for frame in cam:
            counters.append(frame.counter)
            if len(counters) == 4:
                break
    assert counters == [0, 1, 2, 3]
    with pytest.raises(DriverIOError):
        await cam.read()


async def test_reads_leave_the_event_loop_running(harness: Harness):
    """issue 8 camera contract: blocking device work runs in worker threads: other tasks
    keep running while frames are read, and no thread outlives close()."""
    ticks = 0
    threads_before = set(threading.enumerate())

    async def ticker() -> None:
        nonlocal ticks
        while True:
            ticks += 1
            await anyio.sleep(0)

    async with harness.make() as cam, anyio.create_task_group() as group:
        group.start_soon(ticker)
        for _ in range(5):
            await cam.read()
        group.cancel_scope.cancel()
    assert ticks >= 5
    alive = [t for t in threading.enumerate() if t not in threads_before and t.is_alive()
             and not t.name.startswith("AnyIO worker")]
    assert not alive, alive
