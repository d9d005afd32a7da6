"""RenderedGvCamera (``oralnav.sim.peers.gige_render``): a simulated GigE Vision camera that
streams images we render, checked through the real ``aravis`` camera backend over GVCP/GVSP
on loopback.

Each test renders distinctive random 1920x1200 mono8 images, one per frame, and finds the one
behind each frame the driver delivers by its device timestamp (``capture +
clock_offset_s``). The streaming tests are skipped, with the reason, where PyGObject's Aravis
0.8 is missing (the skip reason of the driver's own tests, imported from them), or where no
loopback address can be had (not root, 127.0.0.1's GVCP port taken). The cameras run at 100 Hz
with 8 KiB packets, so that each test takes a fraction of a second.
"""

from __future__ import annotations

import contextlib
import logging
import math
import time
from collections.abc import Iterator

import numpy as np
import pytest

from oralnav.sim.errors import SimError
from oralnav.sim.peers import gige_render
from oralnav.sim.peers.gige_fake import NoLoopbackAddress
from oralnav.sim.peers.gige_render import (
    AravisMissing,
    CameraSettingsError,
    CameraStartError,
    FrameError,
    RenderedGvCamera,
)
from tests.drivers.test_camera_aravis import GI_MISSING

if GI_MISSING is None:
    from oralnav.drivers.camera.aravis import AravisCamera

needs_aravis = pytest.mark.skipif(GI_MISSING is not None, reason=str(GI_MISSING))

WIDTH, HEIGHT = 1920, 1200


class RandomFrames:
    """A frame source: a fresh random image per call, captured at the call's end on
    ``time.monotonic()``; keeps what it rendered. ``fail``: call number (0-based) -> an
    exception to raise, or ``"shape"`` for a wrongly shaped image, instead of a frame."""

    def __init__(self, fail: dict[int, object] | None = None, seed: int = 8) -> None:
        self.rng = np.random.default_rng(seed)
        self.fail = fail or {}
        self.calls = 0
        self.rendered: list[tuple[float, np.ndarray]] = []  # (capture, image), kept short
        self.failed: list[np.ndarray] = []  # images of the calls that failed

    def __call__(self) -> tuple[np.ndarray, float]:
        call, self.calls = self.calls, self.calls + 1
        image = np.frombuffer(self.rng.bytes(WIDTH * HEIGHT), np.uint8).reshape(HEIGHT, WIDTH)
        what = self.fail.get(call)
        if what is not None:
            self.failed.append(image)
            if what == "shape":
                return image[:-1], time.monotonic()
            raise what  # type: ignore[misc]
        capture = time.monotonic()
        self.rendered.append((capture, image))
        del self.rendered[:-64]
        return image, capture

    def find(self, capture: float) -> tuple[float, np.ndarray]:
        """The rendered frame whose capture is nearest ``capture``."""
        return min(self.rendered, key=lambda item: abs(item[0] - capture))


@contextlib.contextmanager
def rendered(source: RandomFrames, **options) -> Iterator[RenderedGvCamera]:
    """A started RenderedGvCamera (skipping the test where no loopback address is free)."""
    camera = RenderedGvCamera(source, **options)
    try:
        camera.start()
    except NoLoopbackAddress as exc:
        pytest.skip(str(exc))
    try:
        yield camera
    finally:
        camera.close()


def driver(camera: RenderedGvCamera, **options) -> AravisCamera:
    """The aravis backend on the camera: the full sensor at 100 Hz, 8 KiB packets."""
    options = {"name": "left", "region": (0, 0, WIDTH, HEIGHT), "frame_rate": 100.0,
               "packet_size": 8192, "timeout": 2.0, **options}
    return AravisCamera(camera.address, **options)


# -- arguments ------------------------------------------------------------------------------


def test_bad_arguments_raise_named_errors(monkeypatch):
    """Bad arguments raise CameraSettingsError (a SimError and a ValueError) naming the
    argument, without I/O; a missing Aravis library makes start() raise AravisMissing
    naming it; a started or closed camera refuses start()."""
    source = RandomFrames()
    for kwargs, why in [
        ({"size": (1920,)}, r"size must be \(width, height\) px"),
        ({"size": (0, 1200)}, "size must be"),
        ({"size": (1920.0, 1200)}, "size must be"),
        ({"size": (True, 1200)}, "size must be"),
        ({"latency_s": -0.01}, r"latency_s must be in 0\.\.1 s"),
        ({"latency_s": math.nan}, "latency_s must be a finite number"),
        ({"clock_offset_s": math.inf}, "clock_offset_s must be a finite number"),
        ({"clock_offset_s": "1.0"}, "clock_offset_s must be a finite number"),
        ({"frame_rate": 5000.0}, r"frame_rate must be in 0\.1\.\.1000 Hz"),
        ({"serial": "S" * 16}, "serial must be 1..15 printable ASCII"),
        ({"serial": ""}, "serial must be"),
        ({"address": "lo"}, "address must be an IPv4 address"),
    ]:
        with pytest.raises(CameraSettingsError, match=why):
            RenderedGvCamera(source, **kwargs)
    with pytest.raises(CameraSettingsError, match="source must be a callable"):
        RenderedGvCamera(None)  # type: ignore[arg-type]
    assert issubclass(CameraSettingsError, SimError) and issubclass(CameraSettingsError,
                                                                    ValueError)
    assert issubclass(FrameError, SimError) and issubclass(AravisMissing, SimError)

    camera = RenderedGvCamera(source, serial="CAM01", address="127.0.0.1")
    assert (camera.serial, camera.device_id, camera.size) == ("CAM01", "Aravis-Fake-CAM01",
                                                              (1920, 1200))
    assert camera.address == "127.0.0.1" and not camera.running and source.calls == 0
    monkeypatch.setattr(gige_render, "LIBARAVIS", "libaravis-0.0-absent.so.0")
    with pytest.raises(AravisMissing, match="libaravis-0.0-absent.so.0|Aravis 0.8"):
        camera.start()
    assert not camera.running
    with pytest.raises(CameraStartError, match="after close"):
        camera.start()
    camera.close()  # idempotent


# -- streaming ------------------------------------------------------------------------------


@needs_aravis
async def test_frames_are_the_rendered_images_with_their_capture_time():
    """The driver receives exactly the bytes rendered (random 1920x1200 mono8, a new image
    per frame); each frame's device_timestamp is capture + clock_offset_s within 1 us; block
    ids go up by one per frame with none lost."""
    source = RandomFrames()
    offset = 4321.123456789  # s, the camera clock ahead of time.monotonic()
    with rendered(source, clock_offset_s=offset) as camera:
        async with driver(camera) as cam:
            assert cam.size == (WIDTH, HEIGHT)
            frames = [await cam.read() for _ in range(8)]
        assert camera.frames_sent >= 8 and camera.frames_skipped == 0
    assert [f.counter for f in frames] == list(range(8))
    assert np.all(np.diff([f.frame_id for f in frames]) == 1)
    assert cam.lost_frames == 0 and cam.incomplete_frames == 0
    images = set()
    for frame in frames:
        capture, image = source.find(frame.device_timestamp - offset)
        assert abs(frame.device_timestamp - (capture + offset)) <= 1e-6
        assert frame.image.shape == (HEIGHT, WIDTH) and frame.image.dtype == np.uint8
        np.testing.assert_array_equal(frame.image, image)
        images.add(capture)
    assert len(images) == len(frames)  # a different rendered image each time


@needs_aravis
async def test_ptp_stamps_read_back_as_the_capture_instant_plus_the_offset():
    """issue 32, "Time": a camera PTP-synchronised to this host (``ptp=True``) stamps TAI;
    the driver with ``timestamps="ptp"`` reads each frame back at its capture instant on
    time.monotonic() plus the camera's timestamp error (``clock_offset_s``), within 1 ms
    (the host reads two clocks), whatever the 30 ms between capture and sending."""
    source = RandomFrames()
    offset = 0.025
    with rendered(source, clock_offset_s=offset, latency_s=0.03, ptp=True) as camera:
        async with driver(camera, timestamps="ptp") as cam:
            frames = [await cam.read() for _ in range(6)]
    for frame in frames:
        capture, image = source.find(frame.timestamp - offset)
        assert abs(frame.timestamp - (capture + offset)) < 1e-3
        np.testing.assert_array_equal(frame.image, image)


@needs_aravis
async def test_no_frame_arrives_before_capture_plus_latency():
    """With latency_s=0.03 each frame's host timestamp (arrival, on time.monotonic()) is at
    least 30 ms after its capture, and not much more: the frame goes out when due."""
    source = RandomFrames()
    with rendered(source, latency_s=0.03) as camera:
        async with driver(camera) as cam:
            frames = [await cam.read() for _ in range(8)]
    delays = []
    for frame in frames:
        capture, image = source.find(frame.device_timestamp)
        assert abs(frame.device_timestamp - capture) <= 1e-6  # clock_offset_s = 0
        np.testing.assert_array_equal(frame.image, image)
        delays.append(frame.timestamp - capture)
    assert min(delays) >= 0.03, delays
    assert np.median(delays) < 0.03 + 0.05, delays  # loose: a loaded 2-core CI machine


@needs_aravis
async def test_a_frame_the_source_fails_is_skipped_and_streaming_goes_on(caplog):
    """A source that raises once, and one frame of the wrong shape (FrameError naming the
    expected shape), are skipped and logged; streaming goes on with consecutive block ids,
    no frame lost, and neither failed image is ever sent. A region the driver sets is cut
    out of the rendered image."""
    caplog.set_level(logging.DEBUG, logger=gige_render.__name__)
    source = RandomFrames(fail={2: RuntimeError("renderer hiccup"), 5: "shape"})
    region = (64, 32, 1280, 720)
    x, y, w, h = region
    with rendered(source) as camera:
        async with driver(camera, region=region) as cam:
            frames = [await cam.read() for _ in range(8)]
        assert camera.frames_skipped == 2
        assert isinstance(camera.last_error, FrameError)
        assert "must be uint8 of shape (1200, 1920)" in str(camera.last_error)
    assert np.all(np.diff([f.frame_id for f in frames]) == 1)
    assert cam.lost_frames == 0 and sum(f.lost_before for f in frames) == 0
    for frame in frames:
        _, image = source.find(frame.device_timestamp)
        np.testing.assert_array_equal(frame.image, image[y:y + h, x:x + w])
        assert not any(np.array_equal(frame.image, bad[y:y + h, x:x + w])
                       for bad in source.failed)
    skips = [r.getMessage() for r in caplog.records if "frame skipped" in r.getMessage()]
    assert len(skips) == 2
    assert "renderer hiccup" in skips[0] and "(1200, 1920)" in skips[1]
