"""Replay backend: plays a recorded video file or a folder of images as a camera.

A recording is either

- a video file, anything OpenCV's ``cv2.VideoCapture`` reads (``.avi``, ``.mp4``...); frame
  ``i`` is stamped ``i / fps`` seconds, with ``fps`` the ``fps`` argument if given, else the
  file's own frame rate, else 25; or
- a folder of images (``.png .jpg .jpeg .tif .tiff .pgm .ppm .pnm .pbm .bmp .webp``), played
  in natural name order (``f2.png`` before ``f10.png``), each frame stamped ``i / fps``; or,
  when the folder holds a ``timestamps.csv`` (header ``file,timestamp``, seconds), in the
  order of its rows, each stamped with its recorded time. See ``docs/drivers.md``.

Frames are mono8 (``mono=True``, the default) or 8-bit BGR (``mono=False``). Decoding runs in
a worker thread, never on the event loop. Without ``realtime`` frames come as fast as they
decode; with it, ``read()`` waits so that frames come at their recorded pace (a slow reader
gets every frame late, none is skipped). With ``loop`` the recording restarts at
``start_frame`` after its last frame, and timestamps keep increasing by one recording length
(last minus first timestamp, plus one frame interval) per pass; without it ``read()`` raises
:class:`EndOfStream`.
"""

from __future__ import annotations

import csv
import logging
import math
import os
import re
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import anyio
import anyio.to_thread
import cv2
import numpy as np

from ..errors import DriverError, DriverInitError, DriverIOError, EndOfStream
from ..lifecycle import LifecycleState
from .base import Camera, CameraFrame, FrameStream

__all__ = [
    "DEFAULT_FPS",
    "IMAGE_SUFFIXES",
    "TIMESTAMPS_FILE",
    "EndOfStream",
    "ReplayCamera",
    "ReplayRig",
    "frame_count",
    "read_frame",
]

log = logging.getLogger(__name__)

#: File suffixes (lower case) that make a file in a replay folder a frame.
IMAGE_SUFFIXES = frozenset(
    {".png", ".jpg", ".jpeg", ".tif", ".tiff", ".pgm", ".ppm", ".pnm", ".pbm", ".bmp", ".webp"}
)
#: Name of the optional per-folder capture-time table.
TIMESTAMPS_FILE = "timestamps.csv"
#: Frame rate (Hz) used when neither the recording nor the caller gives one.
DEFAULT_FPS = 25.0

# Forward distance (frames) up to which a video is advanced by grabbing rather than seeking:
# grabbing is exact for every codec, seeking relies on the container's index.
_MAX_GRAB_AHEAD = 64


def _natural_key(name: str) -> tuple[list[Any], str]:
    # re.split with a capture group puts the digit runs at odd positions, so the key's items
    # have the same type at the same position and always compare.
    parts = re.split(r"(\d+)", name)
    return [int(p) if i % 2 else p.lower() for i, p in enumerate(parts)], name


def _check_index(value: Any, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 0:
        raise DriverInitError(f"{what} must be an integer >= 0, got {value!r}")
    return int(value)


class _Recording:
    """Blocking access to one recording; call from one thread at a time (a worker thread)."""

    def __init__(self, path: Path, mono: bool) -> None:
        self.path = path
        self.mono = mono
        self.files: list[Path] = []  # folder frames, in play order
        self.timestamps: np.ndarray | None = None  # recorded capture times, folder + csv only
        self.file_fps: float | None = None  # a video's own frame rate, when it gives one
        self.count = 0
        self.size: tuple[int, int] | None = None
        self._cap: cv2.VideoCapture | None = None
        self._next = 0  # index the video capture decodes next

    # -- lifecycle ------------------------------------------------------------------------

    def open(self, first: int) -> np.ndarray:
        """Check the recording, count its frames and return frame ``first`` (decoded).

        Raises:
            DriverInitError: missing path, unreadable or empty recording, bad timestamps.csv,
                ``first`` out of range, or frame ``first`` cannot be decoded.
        """
        try:
            if self.path.is_dir():
                self._open_folder()
            elif self.path.is_file():
                if self.path.suffix.lower() in IMAGE_SUFFIXES:
                    raise DriverInitError(
                        f"{self.path}: a single image is not a recording; give the folder "
                        "that holds the frames"
                    )
                self._open_video()
            else:
                raise DriverInitError(f"{self.path}: no such file or folder")
            if first >= self.count:
                raise DriverInitError(
                    f"{self.path}: frame index {first} is out of range "
                    f"(the recording has {self.count} frames)"
                )
            try:
                return self.read(first)
            except DriverIOError as exc:
                raise DriverInitError(str(exc)) from exc
        except BaseException:
            self.close()
            raise

    def close(self) -> None:
        cap, self._cap = self._cap, None
        if cap is not None:
            cap.release()

    def read(self, index: int) -> np.ndarray:
        """Decode frame ``index`` (0 <= index < count) as mono8 or BGR8."""
        image = self._read_video(index) if self._cap is not None else self._read_file(index)
        if self.mono and image.ndim == 3:
            image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        height, width = image.shape[:2]
        if self.size is None:
            self.size = (width, height)
        elif (width, height) != self.size:
            where = self.files[index] if self.files else f"{self.path} frame {index}"
            raise DriverIOError(
                f"{where}: image is {width}x{height}, the recording's frames are "
                f"{self.size[0]}x{self.size[1]}"
            )
        return image

    # -- image folders --------------------------------------------------------------------

    def _open_folder(self) -> None:
        try:
            images = sorted(
                (e.name for e in os.scandir(self.path)
                 if e.is_file() and Path(e.name).suffix.lower() in IMAGE_SUFFIXES),
                key=_natural_key,
            )
        except OSError as exc:
            raise DriverInitError(f"{self.path}: cannot list folder ({exc})") from exc
        table = self.path / TIMESTAMPS_FILE
        if table.exists():
            names, stamps = _read_timestamps(table)
            listed = set(names)
            unlisted = [n for n in images if n not in listed]
            if unlisted:
                more = f" and {len(unlisted) - 5} more" if len(unlisted) > 5 else ""
                raise DriverInitError(
                    f"{table}: images in the folder are not listed: "
                    f"{', '.join(unlisted[:5])}{more}"
                )
            self.timestamps = stamps
        else:
            names = images
        if not names:
            suffixes = " ".join(sorted(IMAGE_SUFFIXES))
            raise DriverInitError(f"{self.path}: folder holds no images ({suffixes})")
        self.files = [self.path / n for n in names]
        self.count = len(self.files)

    def _read_file(self, index: int) -> np.ndarray:
        file = self.files[index]
        flags = cv2.IMREAD_GRAYSCALE if self.mono else cv2.IMREAD_COLOR
        image = cv2.imread(os.fspath(file), flags)
        if image is None:
            raise DriverIOError(f"{file}: cannot decode image (missing, corrupt or unsupported)")
        return image

    # -- video files ----------------------------------------------------------------------

    def _open_video(self) -> None:
        self._reopen()
        fps = self._cap.get(cv2.CAP_PROP_FPS)
        self.file_fps = float(fps) if math.isfinite(fps) and fps > 0 else None
        self.count = self._count_frames()
        if self.count == 0:
            raise DriverInitError(f"{self.path}: video holds no decodable frame")

    def _reopen(self) -> None:
        self.close()
        name = os.fspath(self.path)
        # FFmpeg first: CAP_ANY may hand a name to the image-sequence backend instead.
        cap = cv2.VideoCapture(name, cv2.CAP_FFMPEG)
        if not cap.isOpened():
            cap.release()
            cap = cv2.VideoCapture(name)
        if not cap.isOpened():
            cap.release()
            raise DriverInitError(
                f"{self.path}: cannot open as a video (corrupt, or a format OpenCV cannot read)"
            )
        self._cap = cap
        self._next = 0

    def _count_frames(self) -> int:
        # Container headers can be wrong (multipattern.avi claims 11 frames and holds 10, a
        # truncated file keeps its header): trust the header only if its last frame decodes
        # and nothing follows it, otherwise count by decoding. Seeking after a failed read is
        # unreliable for some codecs, so every probe starts from a fresh capture.
        claimed = int(self._cap.get(cv2.CAP_PROP_FRAME_COUNT))
        if claimed > 0:
            if claimed > 1:
                self._cap.set(cv2.CAP_PROP_POS_FRAMES, claimed - 1)
            if self._cap.grab() and not self._cap.grab():
                self._reopen()
                return claimed
            self._reopen()
        count = 0
        while self._cap.grab():
            count += 1
        self._reopen()
        if claimed > 0 and count != claimed:
            log.info("%s: header claims %d frames, %d decode", self.path, claimed, count)
        return count

    def _read_video(self, index: int) -> np.ndarray:
        cap = self._cap
        if index != self._next:
            if 0 <= self._next < index <= self._next + _MAX_GRAB_AHEAD:
                while self._next < index:
                    if not cap.grab():
                        raise DriverIOError(f"{self.path}: frame {self._next} cannot be decoded")
                    self._next += 1
            else:
                self._reopen()
                cap = self._cap
                if index > 0:
                    cap.set(cv2.CAP_PROP_POS_FRAMES, index)
                self._next = index
        ok, image = cap.read()
        if not ok or image is None:
            self._next = -1  # position unknown: the next read reopens
            raise DriverIOError(f"{self.path}: frame {index} cannot be decoded")
        self._next = index + 1
        return image


def _read_timestamps(table: Path) -> tuple[list[str], np.ndarray]:
    """Parse ``timestamps.csv``: columns ``file`` and ``timestamp`` (seconds), any order."""
    names: list[str] = []
    stamps: list[float] = []
    seen: dict[str, int] = {}
    try:
        with table.open(newline="", encoding="utf-8-sig") as fh:
            reader = csv.reader(fh)
            header = next(reader, None)
            columns = [c.strip() for c in header] if header else []
            if "file" not in columns or "timestamp" not in columns:
                raise DriverInitError(
                    f"{table} line 1: header must name the columns file,timestamp, "
                    f"got {','.join(columns) or 'nothing'!r}"
                )
            i_file, i_time = columns.index("file"), columns.index("timestamp")
            for row in reader:
                line = reader.line_num
                if not any(cell.strip() for cell in row):
                    continue  # blank line
                if len(row) != len(columns):
                    raise DriverInitError(
                        f"{table} line {line}: expected {len(columns)} fields, got {len(row)}"
                    )
                name, text = row[i_file].strip(), row[i_time].strip()
                if not name or Path(name).name != name or name in (".", ".."):
                    raise DriverInitError(
                        f"{table} line {line}: file must be a file name in the folder, "
                        f"got {name!r}"
                    )
                if name in seen:
                    raise DriverInitError(
                        f"{table} line {line}: {name} is already listed on line {seen[name]}"
                    )
                try:
                    stamp = float(text)
                except ValueError:
                    stamp = math.nan
                if not math.isfinite(stamp):
                    raise DriverInitError(
                        f"{table} line {line}: timestamp must be a finite number of seconds, "
                        f"got {text!r}"
                    )
                if stamps and stamp <= stamps[-1]:
                    raise DriverInitError(
                        f"{table} line {line}: timestamp {text} is not after the previous "
                        f"one ({stamps[-1]!r}); timestamps must increase strictly"
                    )
                if not (table.parent / name).is_file():
                    raise DriverInitError(f"{table} line {line}: {name} is not in the folder")
                seen[name] = line
                names.append(name)
                stamps.append(stamp)
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise DriverInitError(f"{table}: cannot read ({exc})") from exc
    if not names:
        raise DriverInitError(f"{table}: lists no frames")
    return names, np.asarray(stamps, dtype=np.float64)


class ReplayCamera(Camera):
    """A camera that plays a recording (video file or image folder); see the module docs.

    Args:
        path: video file, or folder of images with an optional ``timestamps.csv``.
        name: camera name put in every frame; default: the file's stem or the folder's name.
        loop: restart at ``start_frame`` after the last frame instead of ending.
        realtime: pace ``read()`` to the recorded timestamps (the first frame comes at once).
        mono: deliver mono8 (H, W) uint8 images; ``False`` delivers BGR (H, W, 3) uint8.
        start_frame: recording index of the first frame delivered.
        fps: frame rate (Hz) for recordings without timestamps; overrides a video's own.

    Frame timestamps are the recorded capture times in seconds (not the replay clock); the
    frame counter counts delivered frames from 0. ``index`` is the recording index of the
    frame ``read()`` returned last.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        name: str | None = None,
        loop: bool = False,
        realtime: bool = False,
        mono: bool = True,
        start_frame: int = 0,
        fps: float | None = None,
    ) -> None:
        try:
            self.path = Path(path)
        except TypeError:
            raise DriverInitError(f"replay path must be a path, got {path!r}") from None
        super().__init__((self.path.stem or "replay") if name is None else name)
        self.loop = bool(loop)
        self.realtime = bool(realtime)
        self.mono = bool(mono)
        self.start_frame = _check_index(start_frame, "start_frame")
        if fps is not None and (isinstance(fps, bool) or not isinstance(fps, int | float)
                                or not math.isfinite(fps) or fps <= 0):
            raise DriverInitError(f"fps must be a finite number > 0, got {fps!r}")
        self._fps_arg = None if fps is None else float(fps)
        self._recording: _Recording | None = None
        self._lock: anyio.Lock | None = None
        self._life = LifecycleState()  # one event loop: no lock needed
        self._timestamps = np.empty(0)
        self._period = 0.0  # timestamp advance per loop pass, seconds
        self._fps = DEFAULT_FPS
        self._first: tuple[int, np.ndarray] | None = None  # frame decoded by start()
        self._next = 0
        self._passes = 0
        self._counter = 0
        self._index: int | None = None
        self._clock0: float | None = None  # time.monotonic() of the first realtime frame
        self._stamp0 = 0.0

    # -- properties (valid after start) -------------------------------------------------

    @property
    def frame_count(self) -> int:
        """Number of frames in the recording (not just from ``start_frame``)."""
        return self._started_recording().count

    @property
    def fps(self) -> float:
        """Nominal frame rate in Hz (from timestamps.csv, the ``fps`` argument or the video)."""
        self._started_recording()
        return self._fps

    @property
    def timestamps(self) -> np.ndarray:
        """(frame_count,) recorded capture time of every frame, seconds (first loop pass)."""
        self._started_recording()
        return self._timestamps.copy()

    @property
    def index(self) -> int | None:
        """Recording index of the frame ``read()`` returned last; ``None`` before the first."""
        return self._index

    # -- lifecycle --------------------------------------------------------------------------

    async def start(self) -> None:
        self._life.begin_start(f"camera {self.name!r}: start() called twice or after close()")
        self._lock = anyio.Lock()
        recording = self._recording = _Recording(self.path, self.mono)
        first = await anyio.to_thread.run_sync(recording.open, self.start_frame)
        self._first = (self.start_frame, first)
        self._size = recording.size
        if recording.timestamps is not None:
            stamps = recording.timestamps
            steps = np.diff(stamps)
            self._fps = float(1.0 / np.median(steps)) if steps.size else (
                self._fps_arg or DEFAULT_FPS)
        else:
            self._fps = self._fps_arg or recording.file_fps or DEFAULT_FPS
            stamps = np.arange(recording.count, dtype=np.float64) / self._fps
        self._timestamps = stamps
        step = float(np.median(np.diff(stamps))) if stamps.size > 1 else 1.0 / self._fps
        self._period = float(stamps[-1] - stamps[self.start_frame]) + step
        self._next = self.start_frame
        # False when close() came during the awaits above: it released the recording, and
        # the camera stays closed
        self._life.finish_start()

    async def read(self) -> CameraFrame:
        lock = self._require_started()
        async with lock:
            recording = self._started_recording()  # close() may have run while we waited
            if self._next >= recording.count:
                if not self.loop:
                    raise EndOfStream(
                        f"camera {self.name!r}: end of recording {self.path} "
                        f"({recording.count} frames)"
                    )
                self._next = self.start_frame
                self._passes += 1
            index = self._next
            first, self._first = self._first, None
            if first is not None and first[0] == index:
                image = first[1]
            else:
                try:
                    image = await anyio.to_thread.run_sync(recording.read, index)
                except DriverIOError:
                    self._next = index + 1  # the error names the frame; the next read goes on
                    raise
            stamp = float(self._timestamps[index]) + self._passes * self._period
            if self.realtime:
                await self._pace(stamp)
            frame = CameraFrame(image=image, timestamp=stamp, counter=self._counter,
                                camera=self.name)
            self._next = index + 1
            self._counter += 1
            self._index = index
            return frame

    async def close(self) -> None:
        if not self._life.close():
            return
        recording, self._recording = self._recording, None
        self._first = None
        if recording is None:
            return
        # Shielded: a cancelled caller must still release the file; the lock lets a decode
        # that is running in a worker thread finish before the capture goes away.
        with anyio.CancelScope(shield=True):
            async with self._lock:
                recording.close()

    # -- helpers ----------------------------------------------------------------------------

    async def _pace(self, stamp: float) -> None:
        now = time.monotonic()
        if self._clock0 is None:
            self._clock0, self._stamp0 = now, stamp
            return
        delay = self._clock0 + (stamp - self._stamp0) - now
        if delay > 0:
            await anyio.sleep(delay)

    def _require_started(self) -> anyio.Lock:
        self._started_recording()
        assert self._lock is not None
        return self._lock

    def _started_recording(self) -> _Recording:
        if not self._life.running:  # the label only for the message
            self._life.check(f"camera {self.name!r}")
        assert self._recording is not None  # running: start() opened it, only close() drops it
        return self._recording

    def __repr__(self) -> str:
        return f"ReplayCamera({os.fspath(self.path)!r}, name={self.name!r})"


class ReplayRig(FrameStream[dict[str, CameraFrame]]):
    """Several recordings replayed in step, e.g. ``{"left": dir_a, "right": dir_b}``.

    Every source must hold the same number of frames. ``read()`` returns one frame per
    camera, all with the same recording index, as ``{name: CameraFrame}``; the options
    (``loop``, ``realtime``, ``mono``, ``start_frame``, ``fps``) apply to every camera.
    """

    def __init__(self, sources: Mapping[str, str | os.PathLike[str]], **options: Any) -> None:
        if not sources:
            raise DriverInitError("a replay rig needs at least one source")
        self.cameras: dict[str, ReplayCamera] = {
            name: ReplayCamera(path, name=name, **options) for name, path in sources.items()
        }

    @property
    def frame_count(self) -> int:
        """Frames per source (all equal)."""
        return next(iter(self.cameras.values())).frame_count

    async def start(self) -> None:
        try:
            for camera in self.cameras.values():
                await camera.start()
        except BaseException:
            await self.close()
            raise
        counts = {name: cam.frame_count for name, cam in self.cameras.items()}
        if len(set(counts.values())) > 1:
            listing = ", ".join(f"{n} ({c.path}): {counts[n]}" for n, c in self.cameras.items())
            await self.close()
            raise DriverInitError(f"replay rig sources differ in frame count: {listing}")

    async def read(self) -> dict[str, CameraFrame]:
        frames: dict[str, CameraFrame] = {}

        async def read_one(name: str, camera: ReplayCamera) -> None:
            frames[name] = await camera.read()

        try:
            async with anyio.create_task_group() as group:
                for name, camera in self.cameras.items():
                    group.start_soon(read_one, name, camera)
        except ExceptionGroup as group_error:
            # All sources end together; hand callers one plain driver error, not a group.
            errors = _leaves(group_error)
            driver_errors = [e for e in errors if isinstance(e, DriverError)]
            if len(driver_errors) == len(errors):
                raise driver_errors[0] from None
            raise
        return {name: frames[name] for name in self.cameras}

    async def close(self) -> None:
        for camera in self.cameras.values():
            await camera.close()


def _leaves(group: BaseExceptionGroup) -> list[BaseException]:
    out: list[BaseException] = []
    for exc in group.exceptions:
        out.extend(_leaves(exc) if isinstance(exc, BaseExceptionGroup) else [exc])
    return out


def read_frame(path: str | os.PathLike[str], index: int, mono: bool = True) -> np.ndarray:
    """Decode one frame of a recording, synchronously (for tests and CLI tools).

    Returns (H, W) uint8 when ``mono``, else (H, W, 3) uint8 BGR.

    Raises:
        DriverInitError: the path is missing or unreadable, or ``index`` is out of range.
    """
    recording = _Recording(Path(path), bool(mono))
    try:
        return recording.open(_check_index(index, "index"))
    finally:
        recording.close()


def frame_count(path: str | os.PathLike[str]) -> int:
    """Number of frames in a recording (decodable frames of a video), synchronously.

    Raises:
        DriverInitError: the path is missing or unreadable.
    """
    recording = _Recording(Path(path), True)
    try:
        recording.open(0)
        return recording.count
    finally:
        recording.close()
