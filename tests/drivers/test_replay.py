"""Tests of the camera base, the backend registry and the replay backend.

Each test's docstring names the requirement it checks (drivers: camera base + replay).
The peer videos come from ../shared/peer-data (scikit-surgeryarucotracker's data/); those
tests are skipped, with the reason, only where that folder is absent.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import anyio
import cv2
import numpy as np
import pytest

from oralnav.drivers.camera import BACKENDS, Camera, CameraFrame, camera_class, open_camera
from oralnav.drivers.camera.replay import (
    DEFAULT_FPS,
    ReplayCamera,
    ReplayRig,
    frame_count,
    read_frame,
)
from oralnav.drivers.errors import (
    DriverError,
    DriverInitError,
    DriverIOError,
    DriverTimeoutError,
    EndOfStream,
)
from tests.helpers import ARUCO_DATA as ARUCO
from tests.helpers import needs_aruco_data

#: name -> (decodable frames, frames per second in the file)
PEER_VIDEOS = {"output.avi": (10, 10.0), "multipattern.avi": (10, 30.0), "12markers.avi": (1, 30.0)}

W, H = 32, 24


def _image(i: int, colour: bool = False) -> np.ndarray:
    """A small frame whose pixels encode its index (so order mix-ups show)."""
    img = np.full((H, W), 10 * i % 256, np.uint8)
    img[0, 0] = i
    if colour:
        return np.dstack([img, np.full_like(img, 200), np.full_like(img, 50)])
    return img


def _folder(path: Path, n: int, *, stamps: list[float] | None = None, colour: bool = False,
            names: list[str] | None = None) -> Path:
    """Write frames ``frame_<i>.png`` (unpadded, to exercise natural order), optional csv."""
    path.mkdir(parents=True, exist_ok=True)
    names = names or [f"frame_{i}.png" for i in range(n)]
    for i, name in enumerate(names):
        assert cv2.imwrite(str(path / name), _image(i, colour))
    if stamps is not None:
        rows = "".join(f"{name},{t!r}\n" for name, t in zip(names, stamps, strict=True))
        (path / "timestamps.csv").write_text("file,timestamp\n" + rows)
    return path


def _direct_frames(path: Path) -> list[np.ndarray]:
    """Every frame as plain cv2.VideoCapture gives it (BGR), read sequentially."""
    cap = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        frames.append(frame)
    cap.release()
    return frames


async def _read_all(cam: Camera) -> list[CameraFrame]:
    return [frame async for frame in cam]


# -- peer videos ---------------------------------------------------------------------------


@needs_aruco_data
@pytest.mark.parametrize("name", sorted(PEER_VIDEOS))
async def test_peer_videos_play_every_frame_as_mono8(name):
    """A real video plays all its decodable frames as 640x480 mono8, stamped i / file fps,
    counted from 0, then ends with EndOfStream."""
    count, fps = PEER_VIDEOS[name]
    async with ReplayCamera(ARUCO / name) as cam:
        assert cam.size == (640, 480)
        assert cam.frame_count == count
        assert cam.fps == fps
        frames = await _read_all(cam)
        with pytest.raises(EndOfStream):
            await cam.read()
    assert len(frames) == count
    for i, frame in enumerate(frames):
        assert frame.image.dtype == np.uint8 and frame.image.shape == (480, 640)
        assert frame.counter == i
        assert frame.camera == Path(name).stem
        assert frame.timestamp == pytest.approx(i / fps)


@needs_aruco_data
@pytest.mark.parametrize("name", sorted(PEER_VIDEOS))
def test_peer_frame_count_helper(name):
    """frame_count() counts decodable frames, not the container header (multipattern.avi's
    header claims 11 frames; 10 decode)."""
    assert frame_count(ARUCO / name) == PEER_VIDEOS[name][0]


@needs_aruco_data
async def test_output_avi_frame_1_equals_videocapture():
    """Frame index 1 of output.avi equals what cv2.VideoCapture gives directly: BGR as is,
    mono as its BGR2GRAY conversion; read_frame and the camera agree."""
    direct = _direct_frames(ARUCO / "output.avi")
    assert len(direct) == 10
    expected_mono = cv2.cvtColor(direct[1], cv2.COLOR_BGR2GRAY)
    np.testing.assert_array_equal(read_frame(ARUCO / "output.avi", 1, mono=False), direct[1])
    mono = read_frame(ARUCO / "output.avi", 1)
    assert mono.dtype == np.uint8 and mono.shape == (480, 640)
    np.testing.assert_array_equal(mono, expected_mono)
    async with ReplayCamera(ARUCO / "output.avi") as cam:
        await cam.read()
        second = await cam.read()
    assert cam.index == 1
    np.testing.assert_array_equal(second.image, expected_mono)


@needs_aruco_data
async def test_video_random_access_start_frame_and_loop_match_sequential_decoding():
    """start_frame, read_frame(index) and loop passes deliver exactly the frames a sequential
    VideoCapture decodes, including the last frame of a file whose header overcounts."""
    path = ARUCO / "multipattern.avi"
    direct = _direct_frames(path)
    for index in (9, 0, 5):
        np.testing.assert_array_equal(read_frame(path, index, mono=False), direct[index])
    async with ReplayCamera(path, start_frame=7, loop=True, mono=False) as cam:
        got = [await cam.read() for _ in range(5)]
    assert [f.counter for f in got] == [0, 1, 2, 3, 4]
    for frame, index in zip(got, [7, 8, 9, 7, 8], strict=True):
        np.testing.assert_array_equal(frame.image, direct[index])
    # second pass: one recording length (9/30 - 7/30 + 1/30 s) later
    assert got[3].timestamp == pytest.approx(got[0].timestamp + 3 / 30)


@needs_aruco_data
async def test_single_frame_h264_video_loops():
    """A one-frame video (12markers.avi) loops: same image, counter and timestamp advance."""
    async with ReplayCamera(ARUCO / "12markers.avi", loop=True) as cam:
        frames = [await cam.read() for _ in range(3)]
    assert [f.counter for f in frames] == [0, 1, 2]
    assert [f.timestamp for f in frames] == pytest.approx([0, 1 / 30, 2 / 30])
    for frame in frames[1:]:
        np.testing.assert_array_equal(frame.image, frames[0].image)


@needs_aruco_data
async def test_fps_argument_overrides_video_rate():
    """The fps argument sets a video's timestamps (i / fps) instead of the file's rate."""
    async with ReplayCamera(ARUCO / "output.avi", fps=50) as cam:
        stamps = [(await cam.read()).timestamp for _ in range(3)]
    assert stamps == pytest.approx([0.0, 0.02, 0.04])


# -- image folders ---------------------------------------------------------------------------


async def test_folder_without_timestamps_plays_in_natural_order_at_default_fps(tmp_path):
    """A folder without timestamps.csv plays in natural name order (frame_2 before frame_10),
    stamped i / 25 s (the default fps), mono8."""
    folder = _folder(tmp_path / "cam", 12)
    async with ReplayCamera(folder) as cam:
        assert cam.size == (W, H) and cam.frame_count == 12 and cam.fps == DEFAULT_FPS
        frames = await _read_all(cam)
    assert [int(f.image[0, 0]) for f in frames] == list(range(12))
    assert [f.timestamp for f in frames] == pytest.approx([i / 25 for i in range(12)])
    assert all(f.image.dtype == np.uint8 and f.image.shape == (H, W) for f in frames)
    assert frames[0].camera == "cam"


async def test_folder_with_timestamps_csv_uses_recorded_times_and_row_order(tmp_path):
    """With timestamps.csv the rows give play order and each frame's capture time (s)."""
    folder = tmp_path / "rec"
    names = ["b.png", "a.png", "c.png"]
    _folder(folder, 3, names=names, stamps=[100.0, 100.04, 100.1])
    async with ReplayCamera(folder, name="left", fps=5) as cam:
        assert cam.timestamps == pytest.approx([100.0, 100.04, 100.1])
        assert cam.fps == pytest.approx(1 / 0.05)  # median interval; csv wins over fps
        frames = await _read_all(cam)
    assert [f.timestamp for f in frames] == [100.0, 100.04, 100.1]
    assert [int(f.image[0, 0]) for f in frames] == [0, 1, 2]  # written in row order
    assert {f.camera for f in frames} == {"left"}


async def test_colour_folder_mono_and_bgr(tmp_path):
    """mono=True converts colour images to mono8; mono=False returns (H, W, 3) uint8 BGR."""
    folder = _folder(tmp_path / "c", 2, colour=True)
    async with ReplayCamera(folder, mono=False) as cam:
        bgr = (await cam.read()).image
    np.testing.assert_array_equal(bgr, _image(0, colour=True))
    async with ReplayCamera(folder) as cam:
        mono = (await cam.read()).image
    np.testing.assert_array_equal(mono, cv2.cvtColor(_image(0, colour=True), cv2.COLOR_BGR2GRAY))
    np.testing.assert_array_equal(read_frame(folder, 1, mono=False), _image(1, colour=True))


async def test_loop_restarts_and_keeps_timestamps_increasing(tmp_path):
    """loop=True restarts at start_frame; timestamps grow by one recording length per pass
    (last - first + median interval) and the counter keeps counting."""
    folder = _folder(tmp_path / "l", 4, stamps=[0.0, 0.1, 0.2, 0.3])
    async with ReplayCamera(folder, loop=True, start_frame=1) as cam:
        frames = [await cam.read() for _ in range(7)]
        assert cam.index == 1
    assert [int(f.image[0, 0]) for f in frames] == [1, 2, 3, 1, 2, 3, 1]
    assert [f.counter for f in frames] == list(range(7))
    assert [f.timestamp for f in frames] == pytest.approx(
        [0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7])


async def test_realtime_paces_frames_to_recorded_intervals(tmp_path):
    """realtime=True delivers frames at their recorded pace (first at once); the default
    delivers them as fast as they decode."""
    folder = _folder(tmp_path / "rt", 4, stamps=[5.0, 5.02, 5.04, 5.06])
    async with ReplayCamera(folder, realtime=True) as cam:
        await cam.read()
        t0 = time.monotonic()
        await _read_all(cam)
        paced = time.monotonic() - t0
    assert 0.055 <= paced < 0.5
    async with ReplayCamera(folder) as cam:
        t0 = time.monotonic()
        await _read_all(cam)
        fast = time.monotonic() - t0
    assert fast < paced


async def test_end_of_stream_is_final_and_a_driver_io_error(tmp_path):
    """Without loop, read() after the last frame raises EndOfStream (a DriverIOError), again
    on every later call; async iteration simply stops."""
    folder = _folder(tmp_path / "e", 2)
    async with ReplayCamera(folder) as cam:
        assert len(await _read_all(cam)) == 2
        for _ in range(2):
            with pytest.raises(EndOfStream, match="end of recording") as info:
                await cam.read()
        assert isinstance(info.value, DriverIOError) and isinstance(info.value, DriverError)


# -- bad inputs -------------------------------------------------------------------------------


async def test_missing_path_fails_at_start_not_in_constructor(tmp_path):
    """The constructor does no I/O; start() raises DriverInitError naming the missing path."""
    missing = tmp_path / "nope"
    cam = ReplayCamera(missing)
    with pytest.raises(DriverInitError, match="nope: no such file or folder"):
        await cam.start()
    await cam.close()
    with pytest.raises(DriverInitError, match="nope"):
        read_frame(missing, 0)


async def test_empty_folder_fails_at_start(tmp_path):
    """A folder without images gives DriverInitError naming the folder."""
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "notes.txt").write_text("no images here")
    with pytest.raises(DriverInitError, match="empty: folder holds no images"):
        async with ReplayCamera(tmp_path / "empty"):
            pass


async def test_corrupt_first_image_fails_at_start_and_later_one_at_read(tmp_path):
    """A corrupt image gives an error naming the file: DriverInitError at start() when it is
    the first frame, DriverIOError at read() later, after which replay goes on."""
    folder = _folder(tmp_path / "bad", 3)
    (folder / "frame_1.png").write_bytes(b"\x89PNG\r\n\x1a\n not really a png")
    async with ReplayCamera(folder) as cam:
        assert int((await cam.read()).image[0, 0]) == 0
        with pytest.raises(DriverIOError, match="frame_1.png: cannot decode"):
            await cam.read()
        assert int((await cam.read()).image[0, 0]) == 2
    with pytest.raises(DriverInitError, match="frame_1.png: cannot decode"):
        async with ReplayCamera(folder, start_frame=1):
            pass


async def test_corrupt_video_and_single_image_fail_at_start(tmp_path):
    """An unreadable video file and a lone image file give DriverInitError naming the path."""
    bad = tmp_path / "broken.avi"
    bad.write_bytes(b"RIFF garbage, no video here")
    with pytest.raises(DriverInitError, match="broken.avi: cannot open as a video"):
        async with ReplayCamera(bad):
            pass
    single = _folder(tmp_path / "one", 1) / "frame_0.png"
    with pytest.raises(DriverInitError, match="frame_0.png: a single image"):
        async with ReplayCamera(single):
            pass


async def test_image_of_other_size_fails_at_read(tmp_path):
    """A frame whose size differs from the first gives DriverIOError naming file and sizes."""
    folder = _folder(tmp_path / "sz", 2)
    cv2.imwrite(str(folder / "frame_1.png"), np.zeros((H + 1, W), np.uint8))
    async with ReplayCamera(folder) as cam:
        await cam.read()
        with pytest.raises(DriverIOError, match=f"frame_1.png: image is {W}x{H + 1}"):
            await cam.read()


@pytest.mark.parametrize(
    ("csv_text", "message"),
    [
        ("file,timestamp\nframe_0.png,0.0\nframe_1.png,abc\n",
         r"timestamps.csv line 3: timestamp must be a finite number of seconds, got 'abc'"),
        ("file,timestamp\nframe_0.png,0.5\nframe_1.png,0.5\n",
         r"timestamps.csv line 3: timestamp 0.5 is not after"),
        ("file,timestamp\nframe_0.png,0\nframe_1.png,1\nghost.png,2\n",
         r"timestamps.csv line 4: ghost.png is not in the folder"),
        ("file,timestamp\nframe_0.png,0\nframe_0.png,1\n",
         r"timestamps.csv line 3: frame_0.png is already listed on line 2"),
        ("file,time\nframe_0.png,0\n", r"timestamps.csv line 1: header must name"),
        ("file,timestamp\nframe_0.png,0\nframe_1.png\n",
         r"timestamps.csv line 3: expected 2 fields, got 1"),
        ("file,timestamp\nframe_0.png,0\n", r"timestamps.csv: images in the folder are not "
                                            r"listed: frame_1.png"),
        ("file,timestamp\n", r"timestamps.csv: lists no frames"),
    ],
    ids=["not-a-number", "not-increasing", "missing-file", "duplicate", "header",
         "short-row", "unlisted-image", "no-rows"],
)
async def test_bad_timestamps_csv_names_file_and_line(tmp_path, csv_text, message):
    """A malformed timestamps.csv fails at start() with DriverInitError naming it and the
    offending line."""
    folder = _folder(tmp_path / "ts", 2)
    (folder / "timestamps.csv").write_text(csv_text)
    with pytest.raises(DriverInitError, match=message):
        async with ReplayCamera(folder):
            pass


@pytest.mark.parametrize(
    "kwargs",
    [{"start_frame": -1}, {"start_frame": 1.5}, {"fps": 0}, {"fps": float("nan")},
     {"name": ""}],
)
def test_bad_arguments_fail_in_constructor(tmp_path, kwargs):
    """Bad constructor arguments raise DriverInitError at once (without touching the path)."""
    with pytest.raises(DriverInitError):
        ReplayCamera(tmp_path / "does-not-matter", **kwargs)


async def test_start_frame_out_of_range_fails_at_start(tmp_path):
    """start_frame past the end gives DriverInitError stating the frame count."""
    folder = _folder(tmp_path / "s", 3)
    with pytest.raises(DriverInitError, match="frame index 3 is out of range .*3 frames"):
        async with ReplayCamera(folder, start_frame=3):
            pass
    with pytest.raises(DriverInitError, match="frame index 7 is out of range"):
        read_frame(folder, 7)


# -- lifecycle ---------------------------------------------------------------------------------


async def test_lifecycle_close_idempotent_and_misuse_errors(tmp_path, no_leaked_tasks):
    """close() is idempotent (before start too); read before start / after close raises
    DriverIOError; size is known only after start; a closed camera cannot restart; no thread
    or task outlives the camera (checked by the conftest fixtures)."""
    folder = _folder(tmp_path / "lc", 2)
    never_started = ReplayCamera(folder)
    await never_started.close()
    await never_started.close()

    cam = ReplayCamera(folder)
    with pytest.raises(DriverError, match="size is known only after start"):
        _ = cam.size
    with pytest.raises(DriverIOError, match="not started"):
        await cam.read()
    await cam.start()
    with pytest.raises(DriverInitError, match="twice"):
        await cam.start()
    assert cam.size == (W, H)
    await cam.read()
    await cam.close()
    await cam.close()
    with pytest.raises(DriverIOError, match="closed"):
        await cam.read()
    with pytest.raises(DriverInitError):
        await cam.start()


async def test_close_waits_for_concurrent_read_and_later_reads_fail(tmp_path):
    """close() while a frame decodes in a worker thread waits for that read, which returns its
    frame; reads queued behind it then fail cleanly with DriverIOError."""
    folder = _folder(tmp_path / "cc", 5)
    results: list[object] = []
    decoding = threading.Event()
    async with ReplayCamera(folder) as cam:
        await cam.read()  # the frame start() decoded; the next ones go to a worker thread
        recording = cam._recording  # white box: make the decode slow and observable
        plain_read = recording.read

        def slow_read(index: int) -> np.ndarray:
            decoding.set()
            time.sleep(0.05)
            return plain_read(index)

        recording.read = slow_read

        async def reader():
            try:
                results.append(await cam.read())
            except DriverIOError as exc:
                results.append(exc)

        async with anyio.create_task_group() as group:
            for _ in range(3):
                group.start_soon(reader)
            while not decoding.is_set():
                await anyio.sleep(0.001)
            await cam.close()
    assert len(results) == 3
    assert isinstance(results[0], CameraFrame) and int(results[0].image[0, 0]) == 1
    assert all(isinstance(r, DriverIOError) and "closed" in str(r) for r in results[1:])


def test_camera_frame_is_frozen_and_errors_form_one_hierarchy():
    """CameraFrame is immutable; every driver error is a DriverError (timeout also a
    TimeoutError)."""
    frame = CameraFrame(image=np.zeros((2, 2), np.uint8), timestamp=1.0, counter=0, camera="x")
    with pytest.raises(AttributeError):
        frame.counter = 1  # type: ignore[misc]
    for cls in (DriverInitError, DriverIOError, DriverTimeoutError, EndOfStream):
        assert issubclass(cls, DriverError)
    assert issubclass(DriverTimeoutError, TimeoutError)


# -- registry -----------------------------------------------------------------------------------


async def test_registry_opens_replay_lazily(tmp_path):
    """open_camera('replay', ...) builds an unstarted ReplayCamera from its 'module:Class'
    entry; it works as an async context manager."""
    assert BACKENDS["replay"] == "oralnav.drivers.camera.replay:ReplayCamera"
    assert camera_class("replay") is ReplayCamera
    cam = open_camera("replay", path=_folder(tmp_path / "r", 1), name="left")
    assert isinstance(cam, ReplayCamera) and isinstance(cam, Camera) and cam.name == "left"
    async with cam:
        assert (await cam.read()).camera == "left"


def test_registry_errors(monkeypatch):
    """Unknown names and unimportable or wrong backends raise DriverInitError naming them."""
    with pytest.raises(DriverInitError, match=r"unknown camera backend 'gige' \(known: .*replay"):
        open_camera("gige")
    monkeypatch.setitem(BACKENDS, "ghost", "oralnav.drivers.camera.no_such_module:Ghost")
    with pytest.raises(DriverInitError, match="'ghost' is not available"):
        camera_class("ghost")
    monkeypatch.setitem(BACKENDS, "wrong", "oralnav.drivers.camera.base:CameraFrame")
    with pytest.raises(DriverInitError, match="not a Camera subclass"):
        camera_class("wrong")


# -- rig ------------------------------------------------------------------------------------------


async def test_rig_groups_frames_per_index(tmp_path):
    """ReplayRig plays named sources in step: each read() returns {name: frame} with one
    recording index; it ends with EndOfStream (async iteration stops)."""
    left = _folder(tmp_path / "a", 3, stamps=[0.0, 0.1, 0.2])
    right = _folder(tmp_path / "b", 3, stamps=[0.001, 0.101, 0.201])
    async with ReplayRig({"left": left, "right": right}) as rig:
        assert rig.frame_count == 3
        groups = [group async for group in rig]
        with pytest.raises(EndOfStream):
            await rig.read()
    assert len(groups) == 3
    for i, group in enumerate(groups):
        assert list(group) == ["left", "right"]
        assert {name: f.camera for name, f in group.items()} == {"left": "left", "right": "right"}
        assert {f.counter for f in group.values()} == {i}
        assert {int(f.image[0, 0]) for f in group.values()} == {i}
    assert groups[2]["right"].timestamp == pytest.approx(0.201)


async def test_rig_rejects_sources_of_different_length(tmp_path):
    """Sources with different frame counts fail at start() naming each count; all closed."""
    rig = ReplayRig({"left": _folder(tmp_path / "a", 2), "right": _folder(tmp_path / "b", 3)})
    with pytest.raises(DriverInitError, match="differ in frame count: left .*: 2, right .*: 3"):
        async with rig:
            pass
    with pytest.raises(DriverIOError, match="closed"):
        await rig.cameras["left"].read()
