"""Video4Linux2 cameras (the endoscope, UVC cameras) through OpenCV; backend ``"v4l2"``.

OpenCV's V4L2 backend (``cv2.VideoCapture(path, cv2.CAP_V4L2)``) opens and streams the
device; the driver sets the pixel format (FOURCC), size, frame rate and exposure, reads in a
worker thread, and delivers mono8 (or BGR) :class:`CameraFrame` objects stamped with the
V4L2 buffer time (``CLOCK_MONOTONIC``, the clock of ``time.monotonic()``) when the device
gives one, else the time the frame was returned.

When OpenCV cannot open or stream the device, the driver finds out why and says so in the
:class:`DriverInitError`: the path does not exist (listing the video devices there are), is
not a character device, is a character device that is not V4L2, is a V4L2 node without video
capture (a UVC camera's metadata node), cannot be opened (permissions, busy) or is in use by
another process (listing the processes that hold it open, when ``/proc`` shows them).

A read that fails raises :class:`DriverIOError` naming the device and drops the capture;
the next ``read()`` opens the device again (one attempt per read, at least
``reopen_interval`` s apart), so a replugged endoscope comes back under a stable
``/dev/v4l/by-id/...`` path.
"""

from __future__ import annotations

import errno
import fcntl
import logging
import math
import os
import stat
import struct
import threading
import time
from pathlib import Path
from typing import Any

import anyio
import anyio.to_thread
import cv2
import numpy as np

from oralnav.checks import NumberMessages, positive_number

from ..errors import DriverInitError, DriverIOError, DriverTimeoutError
from ..lifecycle import LifecycleState
from .base import Camera, CameraFrame

__all__ = ["V4L2Camera", "device_holders", "diagnose_device", "video_devices"]

log = logging.getLogger(__name__)

# struct v4l2_capability: driver[16] card[32] bus_info[32] version capabilities device_caps
# reserved[3]; VIDIOC_QUERYCAP = _IOR('V', 0, struct v4l2_capability).
_CAPABILITY = struct.Struct("=16s32s32sIII12x")
_VIDIOC_QUERYCAP = (2 << 30) | (_CAPABILITY.size << 16) | (ord("V") << 8) | 0
_CAP_VIDEO_CAPTURE = 0x00000001
_CAP_VIDEO_CAPTURE_MPLANE = 0x00001000
_CAP_DEVICE_CAPS = 0x80000000
# V4L2 exposure_time_absolute counts 100 us; OpenCV's V4L2 auto-exposure values.
_EXPOSURE_UNIT_US = 100.0
_AUTO_EXPOSURE_MANUAL = 1
_AUTO_EXPOSURE_AUTO = 3
# Wording of a refused positive setting (ints and floats only: a setting given as a string
# is a configuration mistake, not something to parse).
_POSITIVE = NumberMessages.uniform("{what} must be a finite number > 0, got {value!r}")


def video_devices() -> list[str]:
    """The ``/dev/video*`` nodes of this machine, in numeric order."""
    nodes = []
    for path in Path("/dev").glob("video*"):
        suffix = path.name[len("video"):]
        if suffix.isdigit():
            nodes.append((int(suffix), str(path)))
    return [p for _, p in sorted(nodes)]


def device_holders(path: str) -> list[str]:
    """Other processes holding ``path`` open, as ``"pid (name)"`` (those /proc shows)."""
    try:
        target = os.path.realpath(path)
        device = os.stat(target).st_rdev
    except OSError:
        return []
    found = []
    me = os.getpid()
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit() or int(proc.name) == me:
            continue
        try:
            for fd in (proc / "fd").iterdir():
                try:
                    st = os.stat(fd)
                except OSError:
                    continue
                if stat.S_ISCHR(st.st_mode) and st.st_rdev == device:
                    name = (proc / "comm").read_text().strip()
                    found.append(f"{proc.name} ({name})")
                    break
        except OSError:  # gone, or not ours to look at
            continue
    return found


def diagnose_device(path: str) -> str:
    """Why ``path`` cannot be a V4L2 capture device, as a phrase (``"... does not exist"``);
    ``""`` when it looks like one (then OpenCV's failure is something else). Blocking."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        nodes = video_devices()
        return (f"{path} does not exist (video devices here: "
                f"{', '.join(nodes) if nodes else 'none'})")
    except OSError as exc:
        return f"{path} cannot be examined ({exc.strerror})"
    if not stat.S_ISCHR(st.st_mode):
        kind = ("a directory" if stat.S_ISDIR(st.st_mode)
                else "a regular file" if stat.S_ISREG(st.st_mode)
                else "a FIFO" if stat.S_ISFIFO(st.st_mode)
                else "a socket" if stat.S_ISSOCK(st.st_mode)
                else "a block device" if stat.S_ISBLK(st.st_mode) else "not a device")
        return f"{path} is not a character device ({kind})"
    try:
        fd = os.open(path, os.O_RDWR | os.O_NONBLOCK)
    except OSError as exc:
        if exc.errno in (errno.EACCES, errno.EPERM):
            return (f"{path}: permission denied (is the user in the group owning it, "
                    "usually 'video'?)")
        if exc.errno == errno.EBUSY:
            return _busy(path)
        return f"{path} cannot be opened ({exc.strerror})"
    try:
        buf = bytearray(_CAPABILITY.size)
        try:
            fcntl.ioctl(fd, _VIDIOC_QUERYCAP, buf)
        except OSError as exc:
            if exc.errno in (errno.ENOTTY, errno.EINVAL):
                return (f"{path} is a character device ({os.major(st.st_rdev)}:"
                        f"{os.minor(st.st_rdev)}) but not a V4L2 device")
            return f"{path}: V4L2 query failed ({exc.strerror})"
    finally:
        os.close(fd)
    driver, card, _, _, caps, device_caps = _CAPABILITY.unpack(buf)
    if caps & _CAP_DEVICE_CAPS:
        caps = device_caps
    card_name = card.split(b"\0", 1)[0].decode("utf-8", "replace")
    if not caps & (_CAP_VIDEO_CAPTURE | _CAP_VIDEO_CAPTURE_MPLANE):
        return (f"{path} ({card_name}) is a V4L2 node without video capture (a metadata or "
                "output node; the camera's image node is usually the other one)")
    return ""


def _busy(path: str) -> str:
    holders = device_holders(path)
    return f"{path} is busy" + (f" (in use by {', '.join(holders)})" if holders else
                                " (in use by another program?)")


class V4L2Camera(Camera):
    """A V4L2 camera read through OpenCV's V4L2 backend (see the module docs).

    Args:
        device: ``/dev/videoN`` path (or a stable ``/dev/v4l/by-id/...`` link), or the
            index ``N``.
        name: camera name put in every frame; default: the path's file name.
        fourcc: pixel format to ask for, four characters (``"MJPG"``, ``"YUYV"``,
            ``"GREY"``); default: the device's.
        size: ``(width, height)`` px to ask for; default: the device's.
        fps: frame rate to ask for (Hz); default: the device's. Devices round it; the rate
            granted is in ``applied``.
        exposure_us: manual exposure, microseconds (V4L2 counts 100 us steps); switches
            auto exposure off. ``None`` keeps the device's setting.
        auto_exposure: ``True`` switches auto exposure on, ``False`` off; ``None`` (the
            default) leaves it, unless ``exposure_us`` is given.
        mono: deliver (H, W) uint8 mono8 images; ``False`` delivers (H, W, 3) uint8 BGR.
        buffers: V4L2 buffer count (OpenCV's ``CAP_PROP_BUFFERSIZE``); default OpenCV's.
        timeout: s a read may take before it counts as timed out.
        reopen_interval: s between attempts to reopen the device after a failed read.

    ``start()`` refuses (``DriverInitError``) a size or FOURCC the device does not grant.
    """

    def __init__(
        self,
        device: int | str = 0,
        *,
        name: str | None = None,
        fourcc: str | None = None,
        size: tuple[int, int] | None = None,
        fps: float | None = None,
        exposure_us: float | None = None,
        auto_exposure: bool | None = None,
        mono: bool = True,
        buffers: int | None = None,
        timeout: float = 2.0,
        reopen_interval: float = 1.0,
    ) -> None:
        if isinstance(device, bool) or not (
                (isinstance(device, int) and device >= 0)
                or (isinstance(device, str) and device.strip())):
            raise DriverInitError(f"v4l2 device must be a /dev/videoN path or an index >= 0, "
                                  f"got {device!r}")
        self.path = f"/dev/video{device}" if isinstance(device, int) else device.strip()
        super().__init__(name if name is not None else (Path(self.path).name or "v4l2"))
        what = f"camera {self.name!r} ({self.path})"
        if fourcc is not None and (not isinstance(fourcc, str) or len(fourcc) != 4
                                   or not fourcc.isascii()):
            raise DriverInitError(f"{what}: fourcc must be four ASCII characters such as "
                                  f"'MJPG' or 'YUYV', got {fourcc!r}")
        self.fourcc = fourcc
        if size is not None and (
                not isinstance(size, tuple | list) or len(size) != 2
                or not all(isinstance(v, int) and not isinstance(v, bool) and v > 0
                           for v in size)):
            raise DriverInitError(f"{what}: size must be (width, height) px > 0, got {size!r}")
        self.size_request = None if size is None else (int(size[0]), int(size[1]))
        self.fps = (None if fps is None else positive_number(
            fps, f"{what}: fps", DriverInitError, numbers_only=True, messages=_POSITIVE))
        self.exposure_us = (None if exposure_us is None else positive_number(
            exposure_us, f"{what}: exposure_us", DriverInitError, numbers_only=True,
            messages=_POSITIVE))
        if auto_exposure is not None and not isinstance(auto_exposure, bool):
            raise DriverInitError(f"{what}: auto_exposure must be True, False or None, "
                                  f"got {auto_exposure!r}")
        if auto_exposure and exposure_us is not None:
            raise DriverInitError(f"{what}: exposure_us and auto_exposure=True exclude each "
                                  "other")
        self.auto_exposure = auto_exposure
        self.mono = bool(mono)
        if buffers is not None and (isinstance(buffers, bool) or not isinstance(buffers, int)
                                    or buffers < 1):
            raise DriverInitError(f"{what}: buffers must be an integer >= 1, got {buffers!r}")
        self.buffers = buffers
        self.timeout = positive_number(timeout, f"{what}: timeout", DriverInitError,
                                       numbers_only=True, messages=_POSITIVE)
        self.reopen_interval = positive_number(reopen_interval, f"{what}: reopen_interval",
                                               DriverInitError, numbers_only=True,
                                               messages=_POSITIVE)
        self.applied: dict[str, Any] = {}
        self._cap: Any = None
        self._lock = threading.Lock()  # the capture object
        self._read_lock: anyio.Lock | None = None
        self._life = LifecycleState()  # changed under _lock
        self._counter = 0
        self._last_stamp = -math.inf
        self._lost: str | None = None
        self._next_open = 0.0
        self.reopens = 0

    def _label(self) -> str:
        return f"camera {self.name!r} ({self.path})"

    # -- lifecycle --------------------------------------------------------------------------

    async def start(self) -> None:
        with self._lock:
            self._life.begin_start(f"{self._label()}: start() called twice or after close() "
                                   "(build a new camera)")
        self._read_lock = anyio.Lock()
        cap, size = await anyio.to_thread.run_sync(self._open, DriverInitError)
        with self._lock:
            if not self._life.finish_start():
                cap.release()
                raise DriverInitError(f"{self._label()}: closed during start()")
            self._cap, self._size = cap, size

    async def close(self) -> None:
        with self._lock:
            if not self._life.close():
                return
        with anyio.CancelScope(shield=True):
            await anyio.to_thread.run_sync(self._release)

    def _release(self) -> None:
        with self._lock:
            cap, self._cap = self._cap, None
        if cap is not None:
            cap.release()

    def _open(self, error: type[DriverInitError] | type[DriverIOError]) -> tuple[Any, tuple]:
        """Open and configure the device, grab one frame; (capture, (width, height))."""
        cap = cv2.VideoCapture(self.path, cv2.CAP_V4L2)
        try:
            if not cap.isOpened():
                why = diagnose_device(self.path) or self._unexplained("cannot open it")
                raise error(f"{self._label()}: {why}")
            self._configure(cap, error)
            ok, image = cap.read()
            if not ok or image is None:
                why = diagnose_device(self.path) or self._unexplained("gets no frame")
                raise error(f"{self._label()}: opened but cannot capture: {why}")
            size = (int(image.shape[1]), int(image.shape[0]))
            if self.size_request is not None and size != self.size_request:
                raise error(f"{self._label()}: asked for {self.size_request[0]}x"
                            f"{self.size_request[1]}, the device delivers {size[0]}x{size[1]}")
            self.applied["size"] = size
            opened, cap = cap, None
            return opened, size
        finally:
            if cap is not None:
                cap.release()

    def _unexplained(self, what: str) -> str:
        """Why OpenCV failed on a path that looks like a capture device."""
        if device_holders(self.path):
            return _busy(self.path)
        return f"OpenCV's V4L2 backend {what} (busy, or a format it cannot use?)"

    def _configure(self, cap: Any, error: type[DriverInitError] | type[DriverIOError]) -> None:
        if self.fourcc is not None:
            cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter.fourcc(*self.fourcc))
            got = _fourcc_text(cap.get(cv2.CAP_PROP_FOURCC))
            if got != self.fourcc:
                raise error(f"{self._label()}: the device refuses FOURCC {self.fourcc!r} "
                            f"(it keeps {got!r})")
        if self.size_request is not None:
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, self.size_request[0])
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, self.size_request[1])
        if self.fps is not None:
            cap.set(cv2.CAP_PROP_FPS, self.fps)
        if self.buffers is not None:
            cap.set(cv2.CAP_PROP_BUFFERSIZE, self.buffers)
        cap.set(cv2.CAP_PROP_READ_TIMEOUT_MSEC, self.timeout * 1000.0)  # where supported
        if self.exposure_us is not None or self.auto_exposure is False:
            cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, _AUTO_EXPOSURE_MANUAL)
        elif self.auto_exposure:
            cap.set(cv2.CAP_PROP_AUTO_EXPOSURE, _AUTO_EXPOSURE_AUTO)
        if self.exposure_us is not None:
            if not cap.set(cv2.CAP_PROP_EXPOSURE, self.exposure_us / _EXPOSURE_UNIT_US):
                raise error(f"{self._label()}: the device refuses exposure "
                            f"{self.exposure_us:g} us")
        self.applied.update(
            fourcc=_fourcc_text(cap.get(cv2.CAP_PROP_FOURCC)),
            fps=float(cap.get(cv2.CAP_PROP_FPS)),
            exposure_us=float(cap.get(cv2.CAP_PROP_EXPOSURE)) * _EXPOSURE_UNIT_US,
            auto_exposure=float(cap.get(cv2.CAP_PROP_AUTO_EXPOSURE)),
        )

    # -- reading ----------------------------------------------------------------------------

    async def read(self) -> CameraFrame:
        self._check_state()
        assert self._read_lock is not None
        async with self._read_lock:
            self._check_state()
            if self._lost is not None:
                await self._reopen()
            t0 = time.monotonic()
            result = await anyio.to_thread.run_sync(self._grab)
            self._check_state(during=True)
            if result is None:
                waited = time.monotonic() - t0
                why = await anyio.to_thread.run_sync(diagnose_device, self.path)
                self._drop(why or "read failed")
                if not why and waited >= self.timeout:
                    raise DriverTimeoutError(f"{self._label()}: no frame for {waited:.2f} s; "
                                             "the next read() reopens the device")
                raise DriverIOError(f"{self._label()}: read failed"
                                    + (f": {why}" if why else "")
                                    + "; the next read() reopens the device")
            image, stamp_ms = result
            return self._frame(image, stamp_ms)

    def _check_state(self, during: bool = False) -> None:
        if not self._life.running:  # the label only for the message
            self._life.check(self._label(), during="read()" if during else None)

    def _grab(self) -> tuple[np.ndarray, float] | None:
        with self._lock:
            cap = self._cap
            if cap is None:
                return None
            ok, image = cap.read()
            if not ok or image is None:
                return None
            return image, float(cap.get(cv2.CAP_PROP_POS_MSEC))

    def _frame(self, image: np.ndarray, stamp_ms: float) -> CameraFrame:
        if self.mono and image.ndim == 3:
            image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        elif not self.mono and image.ndim == 2:
            image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
        size = (int(image.shape[1]), int(image.shape[0]))
        if size != self._size:
            raise DriverIOError(f"{self._label()}: frame size {size} differs from the camera "
                                f"size {self._size}")
        now = time.monotonic()
        stamp = stamp_ms * 1e-3
        if not (math.isfinite(stamp) and now - 5.0 <= stamp <= now):
            stamp = now  # the device's buffer time is not on CLOCK_MONOTONIC
        stamp = max(stamp, self._last_stamp)
        self._last_stamp = stamp
        frame = CameraFrame(image=image, timestamp=stamp, counter=self._counter,
                            camera=self.name)
        self._counter += 1
        return frame

    def _drop(self, why: str) -> None:
        with self._lock:
            cap, self._cap = self._cap, None
        if cap is not None:
            cap.release()
        self._lost = why
        self._next_open = time.monotonic() + self.reopen_interval
        log.warning("%s: %s; the device will be reopened", self._label(), why)

    async def _reopen(self) -> None:
        delay = self._next_open - time.monotonic()
        if delay > 0:
            await anyio.sleep(delay)
        self._check_state()
        try:
            cap, size = await anyio.to_thread.run_sync(self._open, DriverIOError)
        except DriverIOError:
            self._next_open = time.monotonic() + self.reopen_interval
            raise
        with self._lock:
            if self._life.closed:
                cap.release()
                raise DriverIOError(f"{self._label()}: closed during read()")
            if size != self._size:
                cap.release()
                self._next_open = time.monotonic() + self.reopen_interval
                raise DriverIOError(f"{self._label()}: came back with size {size}, "
                                    f"not {self._size}")
            self._cap = cap
        self._lost = None
        self.reopens += 1
        log.warning("%s: reopened", self._label())

    def __repr__(self) -> str:
        return f"V4L2Camera({self.path!r}, name={self.name!r})"


def _fourcc_text(value: float) -> str:
    code = int(value)
    return "".join(chr((code >> (8 * i)) & 0xFF) for i in range(4))
