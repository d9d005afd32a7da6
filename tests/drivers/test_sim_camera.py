"""Issue 4 drivers: simulated cameras fed by a frame source (SimCamera, SimCameraSet)."""

from __future__ import annotations

import threading
import time

import anyio
import numpy as np
import pytest

from oralnav.drivers.camera import Camera, open_camera
from oralnav.drivers.camera.sim import FrameSource, SimCamera, SimCameraSet
from oralnav.drivers.errors import DriverError, DriverInitError, DriverIOError


class FakeSource:
    """Renders each camera as a constant image (value = capture index), 0.1 s apart."""

    def __init__(self, sizes: dict[str, tuple[int, int]], delay: float = 0.0) -> None:
        self.sizes = dict(sizes)
        self.delay = delay
        self.calls: list[tuple[str, ...]] = []
        self.threads: set[int] = set()

    def capture(self, cameras):
        self.threads.add(threading.get_ident())
        if self.delay:
            time.sleep(self.delay)  # blocking render
        index = len(self.calls)
        self.calls.append(tuple(cameras))
        images = {}
        for name in cameras:
            w, h = self.sizes[name]
            images[name] = np.full((h, w), index % 256, np.uint8)
        return images, 100.0 + 0.1 * index


async def test_set_delivers_synchronised_frames_with_counters_in_step():
    """issue 4 drivers: each SimCameraSet read is one capture: every camera's frame has the
    same timestamp and counter, counters run 0, 1, 2...; sizes come from a probe at start."""
    source = FakeSource({"left": (8, 6), "right": (10, 4)})
    assert isinstance(source, FrameSource)
    rig = SimCameraSet(["left", "right"], source)
    with pytest.raises(DriverError, match="after start"):
        _ = rig.sizes
    assert source.calls == []  # the constructor does no I/O
    async with rig:
        assert rig.sizes == {"left": (8, 6), "right": (10, 4)}
        for counter in range(3):
            frames = await rig.read()
            assert list(frames) == ["left", "right"]
            assert {f.counter for f in frames.values()} == {counter}
            assert {f.timestamp for f in frames.values()} == {100.0 + 0.1 * (counter + 1)}
            assert frames["right"].image.shape == (4, 10) and frames["left"].camera == "left"
            assert int(frames["left"].image[0, 0]) == counter + 1  # probe was capture 0
    assert source.calls == [("left", "right")] * 4


async def test_known_sizes_skip_the_probe_and_mismatches_are_io_errors():
    """issue 4 drivers: with sizes given, start() captures nothing; a frame of another size,
    a missing camera, a bad timestamp or a failing source raise DriverIOError."""
    source = FakeSource({"left": (8, 6)})
    async with SimCameraSet(["left"], source, sizes={"left": (8, 6)}) as rig:
        assert source.calls == []
        assert (await rig.read())["left"].counter == 0
        source.sizes["left"] = (9, 6)
        with pytest.raises(DriverIOError, match=r"'left': frame size \(9, 6\) differs"):
            await rig.read()

    class Broken:
        def __init__(self, result):
            self.result = result

        def capture(self, cameras):
            if isinstance(self.result, Exception):
                raise self.result
            return self.result

    image = np.zeros((6, 8), np.uint8)
    for result, why in [
        (({}, 1.0), "returned no image for it"),
        (({"left": image}, float("nan")), "finite seconds"),
        (({"left": image.astype(float)}, 1.0), "uint8"),
        ([image], "must return"),
        (RuntimeError("scene lost"), "capture failed .*scene lost"),
    ]:
        cam = SimCamera("left", Broken(result), size=(8, 6))
        async with cam:
            with pytest.raises(DriverIOError, match=why):
                await cam.read()


async def test_capture_runs_in_a_worker_thread():
    """issue 4 drivers: the blocking render runs off the event loop: the loop keeps running
    other tasks while a capture sleeps."""
    source = FakeSource({"c": (4, 4)}, delay=0.05)
    ticks = 0

    async def ticker() -> None:
        nonlocal ticks
        while True:
            ticks += 1
            await anyio.sleep(0.005)

    async with SimCamera("c", source, size=(4, 4)) as cam:
        async with anyio.create_task_group() as group:
            group.start_soon(ticker)
            await cam.read()
            group.cancel_scope.cancel()
    assert threading.get_ident() not in source.threads
    assert ticks >= 5


async def test_single_camera_through_the_registry():
    """issue 4 drivers: open_camera('sim', name=..., source=...) is a Camera whose size is
    known after start and whose counter starts at 0."""
    source = FakeSource({"endo": (16, 12)})
    cam = open_camera("sim", name="endo", source=source)
    assert isinstance(cam, SimCamera) and isinstance(cam, Camera)
    with pytest.raises(DriverError, match="after start"):
        _ = cam.size
    async with cam:
        assert cam.size == (16, 12)
        frames = [await cam.read() for _ in range(3)]
    assert [f.counter for f in frames] == [0, 1, 2]
    assert [f.timestamp for f in frames] == pytest.approx([100.1, 100.2, 100.3])
    assert source.calls == [("endo",)] * 4


async def test_freeze_stalls_reads_until_unfrozen_or_closed():
    """issue 4 drivers: a frozen sim camera delivers nothing (read waits), so a watchdog on
    the age of the last frame trips; unfreeze() resumes with the next counter and a fresh
    timestamp; close() ends a waiting read with DriverIOError."""
    source = FakeSource({"left": (4, 4), "right": (4, 4)})
    rig = SimCameraSet(["left", "right"], source)
    async with rig:
        last = await rig.read()
        rig.freeze()
        assert rig.frozen
        calls = len(source.calls)
        with anyio.move_on_after(0.05) as scope:
            await rig.read()
        assert scope.cancelled_caught  # no frame in 50 ms: stale to any watchdog
        assert len(source.calls) == calls  # nothing rendered while frozen
        rig.unfreeze()
        frames = await rig.read()
        assert frames["left"].counter == last["left"].counter + 1
        assert frames["left"].timestamp > last["left"].timestamp

        rig.freeze()
        outcome: list[BaseException] = []

        async def reader() -> None:
            try:
                await rig.read()
            except DriverIOError as exc:
                outcome.append(exc)

        async with anyio.create_task_group() as group:
            group.start_soon(reader)
            await anyio.sleep(0.02)
            await rig.close()
        assert len(outcome) == 1 and "close" in str(outcome[0])


async def test_lifecycle_errors():
    """issue 4 drivers: reads need start() and fail after close(); start() twice is refused;
    bad names, sizes or sources are refused at construction; a failing probe fails start()."""
    source = FakeSource({"a": (4, 4)})
    cam = SimCamera("a", source)
    with pytest.raises(DriverIOError, match="start"):
        await cam.read()
    async with cam:
        with pytest.raises(DriverInitError, match="twice"):
            await cam.start()
    await cam.close()
    with pytest.raises(DriverIOError, match="after close"):
        await cam.read()
    for names, why in [([], "non-empty"), (["a", "a"], "unique"), ("ab", "sequence"),
                       ([""], "non-empty strings")]:
        with pytest.raises(DriverInitError, match=why):
            SimCameraSet(names, source)
    with pytest.raises(DriverInitError, match="capture"):
        SimCameraSet(["a"], object())  # type: ignore[arg-type]
    with pytest.raises(DriverInitError, match="width, height"):
        SimCamera("a", source, size=(0, 4))
    with pytest.raises(DriverInitError, match="unknown camera"):
        SimCameraSet(["a"], source, sizes={"b": (4, 4)})
    with pytest.raises(DriverInitError, match="cannot start: camera 'zz'"):
        async with SimCamera("zz", source):
            pass
