"""Issue 8 Aravis camera: the GigE Vision backend against Aravis's own simulated camera.

The tests start ``arv-fake-gv-camera-0.8`` (Debian's ``aravis-tools``) as a real process and
drive it through PyGObject's Aravis 0.8, as a real GigE Vision camera: control over GVCP
(UDP 3956), frames over GVSP. Each fake camera gets a loopback address of its own, since a
camera's control port binds its address: as root, a fresh ``127.83.x.y/32`` alias is added
to ``lo`` for it and removed afterwards (no two fakes, nor two test runs, ever share a port);
without root only ``127.0.0.1`` is used, so tests needing two cameras are skipped there.

The tests are skipped, with the reason, only where PyGObject's Aravis 0.8 or the fake camera
are missing; ``./dev.sh test`` installs both (as root), so CI runs them. The helpers here
(``oralnav.sim.peers.gige_fake``: :func:`running_fakes`, :class:`FakeGvCamera`) also serve the
stereo and contract suites and the daemon's hardware-cell test.
"""

from __future__ import annotations

import contextlib
import shutil
import time
from collections.abc import Callable, Iterator

import anyio
import numpy as np
import pytest

from oralnav.drivers.camera import camera_class, open_camera
from oralnav.drivers.errors import DriverError, DriverInitError, DriverIOError, DriverTimeoutError
from oralnav.sim.peers.gige_fake import FAKE, FakeGvCamera, NoLoopbackAddress
from oralnav.sim.peers.gige_fake import running_fakes as fakes_on_loopback


def _gi_missing() -> str | None:
    try:
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis  # noqa: F401
    except (ImportError, ValueError) as exc:
        return (f"PyGObject with Aravis 0.8 is not importable ({type(exc).__name__}: {exc}); "
                "./dev.sh installs it as root (apt gir1.2-aravis-0.8, pip PyGObject<3.51)")
    return None


#: Why the Aravis backend cannot be imported here, or None.
GI_MISSING = _gi_missing()
#: Why no simulated GigE Vision camera can run here, or None.
FAKE_MISSING = (None if shutil.which(FAKE) else
                f"{FAKE} is not on PATH (Debian package aravis-tools; ./dev.sh installs it)")
#: Why the tests against simulated cameras cannot run here, or None.
ARAVIS_MISSING = GI_MISSING or FAKE_MISSING

if GI_MISSING is None:
    from oralnav.drivers.camera.aravis import (
        PIXEL_FORMATS,
        AravisCamera,
        AravisFrame,
        convert_image,
        gige_answer,
        gige_controlled,
    )


# -- fake cameras -------------------------------------------------------------------------
# (oralnav.sim.peers.gige_fake: the fake camera process and its loopback address)


@contextlib.contextmanager
def running_fakes() -> Iterator[Callable[..., FakeGvCamera]]:
    """:func:`oralnav.sim.peers.gige_fake.running_fakes`, skipping the test where no loopback
    address can be had for one more fake (not root, 127.0.0.1 taken)."""
    with fakes_on_loopback() as make:
        def make_or_skip(lost_ratio: int = 0) -> FakeGvCamera:
            try:
                return make(lost_ratio)
            except NoLoopbackAddress as exc:
                pytest.skip(str(exc))

        yield make_or_skip


@pytest.fixture
def fakes():
    if FAKE_MISSING is not None:
        pytest.skip(FAKE_MISSING)
    with running_fakes() as make:
        yield make


def small(fake: FakeGvCamera, **options) -> AravisCamera:
    """A camera on the fake, small and quick: 32x24 px at 200 Hz, quick reconnects."""
    options = {"name": "cam", "region": (0, 0, 32, 24), "frame_rate": 200.0,
               "timeout": 1.0, "reconnect_backoff": (0.05, 0.2), **options}
    return AravisCamera(fake.address, **options)


async def _until_frame(cam, deadline_s: float = 10.0):
    """Read until a frame comes (a reconnecting camera raises meanwhile)."""
    errors = []
    t_end = time.monotonic() + deadline_s
    while time.monotonic() < t_end:
        try:
            return await cam.read(), errors
        except DriverError as exc:
            errors.append(exc)
    raise AssertionError(f"no frame in {deadline_s} s: {errors[-3:]}")


pytestmark = pytest.mark.skipif(GI_MISSING is not None, reason=str(GI_MISSING))


# -- arguments, registry ------------------------------------------------------------------


async def test_constructor_checks_arguments_and_does_no_io():
    """issue 8 Aravis: bad arguments raise DriverInitError naming them; building contacts
    nothing; the backend is registered; size/read need start(); close() before start."""
    for kwargs, why in [
        ({"pixel_format": "Mono12Packed"}, "pixel_format 'Mono12Packed' is not supported"),
        ({"region": (0, 0, 0, 10)}, "region must be"),
        ({"exposure_us": -1}, "exposure_us must be a finite number > 0"),
        ({"gain": float("nan")}, "gain must be a finite number"),
        ({"frame_rate": 0}, "frame_rate must be"),
        ({"trigger": ""}, "trigger must be"),
        ({"trigger": "software", "trigger_activation": "RisingEdge"}, "hardware triggers"),
        ({"buffers": 0}, "buffers must be an integer >= 1"),
        ({"timeout": 0}, "timeout must be"),
        ({"packet_size": 100}, "packet_size must be"),
        ({"reconnect_backoff": (1.0, 0.5)}, "reconnect_backoff must be"),
        ({"camera_id": "  "}, "camera_id must be"),
    ]:
        args = {"camera_id": "192.0.2.77", **kwargs}
        with pytest.raises(DriverInitError, match=why):
            AravisCamera(**args)
    assert camera_class("aravis") is AravisCamera
    cam = open_camera("aravis", camera_id="192.0.2.77", name="left", trigger="Line1")
    assert isinstance(cam, AravisCamera) and cam.name == "left" and cam.device is None
    assert AravisCamera().name == "aravis" and AravisCamera("10.0.0.9").name == "10.0.0.9"
    with pytest.raises(DriverError, match="after start"):
        _ = cam.size
    with pytest.raises(DriverIOError, match="not started"):
        await cam.read()
    await cam.close()
    await cam.close()
    with pytest.raises(DriverIOError, match="closed"):
        await cam.read()
    with pytest.raises(DriverInitError, match="after close"):
        await cam.start()


def test_convert_image_formats():
    """issue 8 Aravis: the pixel formats the driver accepts become mono8 or BGR8: Mono16
    keeps its high bits, Bayer tiles demosaic to the right colour (GenICam BayerRG8 = red
    top-left), RGB8 swaps to BGR, row padding is skipped, short buffers are refused."""
    assert set(PIXEL_FORMATS) >= {"Mono8", "Mono16", "BayerRG8", "BayerBG8", "RGB8"}
    words = np.array([[0x0000, 0x0FFF, 0x0800], [0x0010, 0x0123, 0x0FF0]], "<u2")
    out = convert_image(words.tobytes(), 3, 2, "Mono12")
    np.testing.assert_array_equal(out, (words >> 4).astype(np.uint8))
    red = np.zeros((8, 8), np.uint8)
    tiles = {"BayerRG8": (0, 0), "BayerGR8": (0, 1), "BayerGB8": (1, 0), "BayerBG8": (1, 1)}
    for fmt, (r, c) in tiles.items():
        mosaic = red.copy()
        mosaic[r::2, c::2] = 255  # only the red sites lit
        bgr = convert_image(mosaic.tobytes(), 8, 8, fmt, mono=False)
        b, g, rr = bgr[2:6, 2:6].reshape(-1, 3).mean(axis=0)
        assert rr > 200 and g < 30 and b < 30, (fmt, b, g, rr)
        assert convert_image(mosaic.tobytes(), 8, 8, fmt).shape == (8, 8)
    rgb = np.zeros((2, 2, 3), np.uint8)
    rgb[..., 0] = 255  # red
    assert tuple(convert_image(rgb.tobytes(), 2, 2, "RGB8", mono=False)[0, 0]) == (0, 0, 255)
    padded = np.arange(2 * 5, dtype=np.uint8).reshape(2, 5)  # 3 px + 2 padding bytes
    np.testing.assert_array_equal(convert_image(padded.tobytes(), 3, 2, "Mono8", x_padding=2),
                                  padded[:, :3])
    with pytest.raises(ValueError, match="need 6"):
        convert_image(b"\0" * 5, 3, 2, "Mono8")
    with pytest.raises(ValueError, match="not one of"):
        convert_image(b"\0" * 6, 3, 2, "YUV422_8")


# -- streaming ----------------------------------------------------------------------------


async def test_frames_arrive_with_increasing_counters_ids_and_timestamps(fakes):
    """issue 8 Aravis: frames arrive from the simulated GigE camera: counter 0, 1, 2...,
    frame ids +1 across the 16-bit GigE Vision wrap, host timestamps on time.monotonic()
    and device timestamps increasing at the set frame rate; the settings read back."""
    fake = fakes()
    cam = small(fake, exposure_us=1500.0, gain=2.0)
    t0 = time.monotonic()
    async with cam:
        assert cam.size == (32, 24)
        assert cam.applied == {"pixel_format": "Mono8", "region": (0, 0, 32, 24),
                               "exposure_us": 1500.0, "gain": 2.0, "frame_rate": 200.0,
                               "trigger": "off"}
        assert cam.device.address == fake.address and cam.device.serial == fake.serial
        frames = [await cam.read() for _ in range(150)]
    t1 = time.monotonic()
    assert all(isinstance(f, AravisFrame) for f in frames)
    assert [f.counter for f in frames] == list(range(150))
    assert {f.image.shape for f in frames} == {(24, 32)} and frames[0].image.dtype == np.uint8
    assert {f.camera for f in frames} == {"cam"} and {f.epoch for f in frames} == {0}
    ids = np.array([f.frame_id for f in frames])
    steps = np.diff(ids)
    # the fake numbers from 65401: 150 frames cross 65535 -> 1, which unwraps to 65536
    assert ids[0] < 65535 < ids[-1]
    assert np.all(steps >= 1)
    assert list(steps - 1) == [f.lost_before for f in frames[1:]]
    assert cam.lost_frames == sum(f.lost_before for f in frames)
    stamps = np.array([f.timestamp for f in frames])
    assert t0 <= stamps[0] and stamps[-1] <= t1 and np.all(np.diff(stamps) >= 0)
    device = np.array([f.device_timestamp for f in frames])
    assert np.all(np.diff(device) > 0)
    period = np.median(np.diff(device) / steps)
    assert period == pytest.approx(1 / 200.0, rel=0.2)


async def test_pixel_formats_from_the_camera(fakes):
    """issue 8 Aravis: Mono16, RGB8 and BayerBG8 from the camera come out as mono8, or BGR
    with mono=False."""
    fake = fakes()
    for fmt, mono, shape in [("Mono16", True, (24, 32)), ("RGB8", False, (24, 32, 3)),
                             ("BayerBG8", True, (24, 32)), ("Mono8", False, (24, 32, 3))]:
        async with small(fake, pixel_format=fmt, mono=mono) as cam:
            frame = await cam.read()
            assert frame.image.shape == shape and frame.image.dtype == np.uint8, fmt
            assert frame.pixel_format == fmt and cam.applied["pixel_format"] == fmt


async def test_bad_settings_name_the_option_and_what_the_camera_offers(fakes):
    """issue 8 Aravis: a setting the camera cannot take fails start() with DriverInitError
    naming it and the camera's range or offer; nothing stays open."""
    fake = fakes()
    for kwargs, why in [
        ({"exposure_us": 5e7}, r"exposure_us 5e\+07 us is outside the camera's range 10\.\."),
        ({"pixel_format": "Mono12"}, "'Mono12' is not offered; the camera offers .*Mono8"),
        ({"trigger": "Line7"}, "trigger source 'Line7' is not offered; the camera offers "
                               "Line0, Software"),
        ({"region": (0, 0, 4096, 16)}, "does not fit the sensor 2048x2048"),
        ({"frame_rate": 5000.0}, "frame_rate 5000 Hz is outside"),
    ]:
        cam = small(fake, **kwargs)
        with pytest.raises(DriverInitError, match=why):
            await cam.start()
        await cam.close()
    async with small(fake) as cam:  # the camera was left free
        await cam.read()


async def test_wrong_address_or_id_lists_the_cameras_found(fakes):
    """issue 8 Aravis: an address where no camera answers, or an unknown camera id, fails
    start() with DriverInitError naming it and listing the cameras discovery found; the
    camera opens by device id and by serial number too."""
    fake = fakes()
    nobody = "127.83.0.255"  # loopback, routed to lo, nothing listens
    cam = AravisCamera(nobody, name="left")
    with pytest.raises(DriverInitError) as err:
        await cam.start()
    assert f"no GigE Vision camera answers at {nobody}" in str(err.value)
    assert fake.device_id in str(err.value) and "cameras found" in str(err.value)
    with pytest.raises(DriverInitError, match=f"no camera 'Aravis-Fake-NOPE'; .*{fake.device_id}"):
        await AravisCamera("Aravis-Fake-NOPE", name="left").start()
    assert gige_answer(fake.address) == fake.serial and gige_answer(nobody, 0.05) is None
    assert gige_controlled(fake.address) is False
    for spec in (fake.device_id, fake.serial):
        async with AravisCamera(spec, region=(0, 0, 16, 16)) as cam:
            assert cam.device.device_id == fake.device_id
            assert cam.device.address == fake.address
            assert (await cam.read()).image.shape == (16, 16)


async def test_a_camera_in_use_is_refused(fakes):
    """issue 8 Aravis: a camera another application controls fails start() with
    DriverInitError saying so (Aravis would open it read-only)."""
    fake = fakes()
    async with small(fake, name="first") as first:
        assert gige_controlled(fake.address) is True
        second = small(fake, name="second")
        with pytest.raises(DriverInitError, match="controlled by another application"):
            await second.start()
        await second.close()
        assert (await first.read()).camera == "first"


# -- triggers -----------------------------------------------------------------------------


async def test_software_and_hardware_triggers(fakes):
    """issue 8 Aravis: trigger='software' fires on read, or with auto_trigger off on
    software_trigger() only (no trigger, no frame: DriverTimeoutError from a camera that
    answers); a hardware source with no pulse times out the same way."""
    fake = fakes()
    async with small(fake, trigger="software", frame_rate=500.0) as cam:
        assert cam.applied["trigger"] == "Software"
        frames = [await cam.read() for _ in range(3)]
        assert [f.counter for f in frames] == [0, 1, 2]
        assert np.all(np.diff([f.frame_id for f in frames]) == 1)
    async with small(fake, trigger="software", auto_trigger=False, timeout=0.3) as cam:
        with pytest.raises(DriverTimeoutError, match="no trigger came"):
            await cam.read()
        await cam.software_trigger()
        assert (await cam.read()).counter == 0
        assert cam.connected and cam.timeouts == 1
    async with small(fake, trigger="Line0", timeout=0.3) as cam:
        assert cam.applied["trigger"] == "Line0"
        with pytest.raises(DriverTimeoutError, match="trigger Line0: no trigger came"):
            await cam.read()
        with pytest.raises(DriverIOError, match="needs trigger='software'"):
            await cam.software_trigger()
        assert cam.connected


# -- faults -------------------------------------------------------------------------------


async def test_lost_and_incomplete_frames_are_counted(fakes):
    """issue 8 Aravis: frames the pool had no room for show as frame-id gaps counted in
    lost_frames (and Aravis's underruns); frames with lost packets are dropped and counted
    in incomplete_frames; delivery goes on."""
    fake = fakes()
    async with small(fake, buffers=2, frame_rate=500.0) as cam:
        await cam.read()
        frames: list = []
        with anyio.fail_after(10):
            while sum(f.lost_before for f in frames) <= 10:
                # ~100 frames come in 0.2 s and 2 buffers hold them; on a loaded machine
                # the fake streams slower (4 lost was seen), so look again until it lost some
                await anyio.sleep(0.2)
                frames += [await cam.read() for _ in range(5)]
        assert cam.underruns > 0
        assert cam.lost_frames == sum(f.lost_before for f in frames) > 10
    fake.kill()  # (frees 127.0.0.1 where no alias can be added)
    lossy = fakes(lost_ratio=30)  # 3 % of the packets lost
    async with small(lossy, region=(0, 0, 512, 40)) as cam:  # 15 packets a frame
        frames = [await cam.read() for _ in range(30)]
        assert cam.incomplete_frames > 0 and cam.lost_frames > 0
        assert cam.lost_frames == sum(f.lost_before for f in frames)
        assert [f.counter for f in frames] == list(range(30))


async def test_killed_camera_is_reported_and_reconnected(fakes):
    """issue 8 Aravis: a free-running camera killed mid-stream makes read() raise
    DriverTimeoutError naming it, then DriverIOError per failed reconnect attempt (no
    crash); started again, it is reconnected by read(): counters go on, the epoch grows."""
    fake = fakes()
    async with small(fake, name="left", timeout=0.3) as cam:
        before = [await cam.read() for _ in range(3)]
        fake.kill()
        with pytest.raises(DriverTimeoutError, match=rf"camera 'left' \(.*{fake.address}\): "
                                                     "no frame for 0.30 s"):
            while True:
                await cam.read()  # frames already buffered come first
        assert not cam.connected
        with pytest.raises(DriverIOError, match=f"reconnect attempt 1 failed: no answer from "
                                                f"{fake.address}"):
            await cam.read()
        fake.start()
        frame, errors = await _until_frame(cam)
        assert all(isinstance(e, DriverIOError) for e in errors)
        assert cam.connected and cam.reconnects == 1
        assert frame.epoch == 1 and frame.counter > before[-1].counter
        assert frame.frame_id > before[-1].frame_id and frame.timestamp > before[-1].timestamp
        after = [await cam.read() for _ in range(3)]
        assert [f.counter for f in after] == [frame.counter + 1 + i for i in range(3)]


async def test_killed_triggered_camera_is_told_from_a_missing_trigger(fakes):
    """issue 8 Aravis: with a hardware trigger a silent camera is asked whether it is still
    there: killed, read() raises DriverIOError (lost, not a timeout); reconnect off, reads
    keep saying so."""
    fake = fakes()
    async with small(fake, trigger="Line0", reconnect=False, timeout=0.3) as cam:
        with pytest.raises(DriverTimeoutError):
            await cam.read()
        fake.kill()
        with pytest.raises(DriverIOError, match="lost .*does not answer.*reconnect is off"):
            await cam.read()
        with pytest.raises(DriverIOError, match="reconnect is off: close"):
            await cam.read()
        fake.start()  # so that releasing the lost link is quick


async def test_close_during_a_read_ends_it(fakes):
    """issue 8 Aravis: close() while a read waits makes that read raise DriverIOError at
    once (reads wait in short slices), and the loop stays free meanwhile."""
    fake = fakes()
    cam = small(fake, trigger="Line0", timeout=5.0)
    await cam.start()
    outcome = []

    async def reader() -> None:
        try:
            await cam.read()
        except DriverIOError as exc:
            outcome.append((str(exc), time.monotonic()))

    async with anyio.create_task_group() as group:
        group.start_soon(reader)
        await anyio.sleep(0.2)
        t_close = time.monotonic()
        await cam.close()
    assert "closed during read()" in outcome[0][0]
    assert outcome[0][1] - t_close < 0.5


# -- device timestamps mapped onto the monotonic clock (issue 32) ---------------------------

@pytest.mark.skipif(GI_MISSING is not None, reason=str(GI_MISSING))
@pytest.mark.alone  # the shortest transfer delay in 30 frames stays under 15 ms when alone
async def test_device_timestamps_are_mapped_onto_the_monotonic_clock():
    """Issue 32 (time): with timestamps="device" the frames of a camera whose clock is
    4321 s ahead of this machine's, and whose frames leave 20 ms after capture, are
    stamped at capture + 20 ms + the shortest transfer delay seen so far (under 15 ms
    here): a frame that travels slower than an earlier one does not move the stamp, so the
    lag never rises by more than the map's drift allowance (100 ppm of the time between
    arrivals) and only falls when a faster frame arrives; with the camera's clock jumping
    5 s ahead mid-stream, read() raises ClockError naming the jump, and the next frames
    are mapped afresh."""
    from oralnav.drivers.errors import ClockError
    from tests.sim.peers.test_gige_render import RandomFrames, driver, rendered

    source = RandomFrames()
    offset = 4321.0
    with rendered(source, clock_offset_s=offset, latency_s=0.02) as camera:
        async with driver(camera, timestamps="device") as cam:
            frames = [await cam.read() for _ in range(30)]
            lags = [f.timestamp - source.find(f.device_timestamp - offset)[0]
                    for f in frames]
            assert 0.02 <= min(lags) and lags[-1] < 0.02 + 0.015, lags
            # Which frame travels fastest depends on the machine's load (CI once saw the
            # first ten at 4.6 ms and a later one at 0.7 ms), so the test checks the rule,
            # not when the fastest frame came: each lag is the previous one, raised by at
            # most the drift allowance, or lower.
            # The allowance grows with the time between arrivals, which the test cannot
            # see: a frame held up to 1 s adds 100 us, still far below the millisecond
            # spread of transfer delays that the map must not pass on.
            for i in range(1, len(frames)):
                allowance = 1e-4 * (frames[i].timestamp - frames[i - 1].timestamp + 1.0)
                assert lags[i] <= lags[i - 1] + allowance, (i, lags)
            camera.clock_offset_s = offset + 5.0  # the camera's clock set forward
            with pytest.raises(ClockError, match=r"jumped by \+(4|5)\d\d\d\.\d ms"):
                for _ in range(10):
                    await cam.read()
            after = await cam.read()
            assert abs(after.timestamp - time.monotonic()) < 1.0
