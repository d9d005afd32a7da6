"""GigE Vision and USB3 Vision cameras through Aravis 0.8 (PyGObject); backend ``"aravis"``.

The camera is found by Aravis's discovery (:func:`discover`) or opened directly by its IP
address, configured (region, pixel format, frame rate, exposure, gain, trigger, packet size),
and streamed into a pool of ``buffers`` buffers that Aravis's own stream thread fills. Every
SDK call runs in a worker thread (``anyio.to_thread``), never on the event loop, and a read
waits for a buffer in short slices so that ``close()`` and cancellation are served quickly.

Frames are :class:`AravisFrame` objects: a :class:`CameraFrame` (``timestamp`` is the
host's arrival time of the frame mapped onto ``time.monotonic()``) plus the camera's own
``device_timestamp`` (s, camera clock), its ``frame_id`` (the GigE Vision block id or USB3
Vision frame id, unwrapped past the 16-bit wrap of GigE Vision 1.x), the number of frames
lost just before it (``lost_before``) and the link ``epoch`` (+1 per reconnect or counter
reset). The stereo pairing (:mod:`.stereo`) pairs on ``frame_id`` when the cameras share a
trigger.

Faults. A frame that arrives incomplete (missing packets) is dropped and counted; frames the
camera sent that never arrived show as gaps in ``frame_id`` and are counted in
``lost_frames``. When no frame comes within ``timeout``:

- free-running (``trigger="off"``): ``read()`` raises :class:`DriverTimeoutError` and the link
  is treated as lost;
- triggered: the driver asks the camera whether it is still there and still armed. A
  camera that answers raises :class:`DriverTimeoutError` (no trigger came); one that does
  not answer (GigE Vision gives up after about 2.5 s of retries) or that has lost its trigger
  setting (it restarted) is lost and ``read()`` raises :class:`DriverIOError`.

A lost link is re-established by the following ``read()`` calls, automatically
(``reconnect=True``): each waits for the back-off delay, asks whether the camera is back (a
unicast GigE Vision discovery to its address, 0.25 s; failing that, or for USB3 Vision,
Aravis's discovery by device id, about 1 s) and, once it answers, reopens and reconfigures
it. A failed attempt raises :class:`DriverIOError` naming the camera and why, and doubles
the delay up to ``reconnect_backoff[1]``. The objects of the lost link are released only
once the camera answers again (releasing them while it is away costs Aravis several seconds
of retries), or at ``close()``.
"""

from __future__ import annotations

import ipaddress
import logging
import math
import socket
import struct
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import anyio
import anyio.to_thread
import cv2
import gi
import numpy as np

gi.require_version("Aravis", "0.8")
from gi.repository import Aravis, GLib  # noqa: E402  (needs require_version first)

from oralnav.checks import NumberMessages, finite_number, positive_number  # noqa: E402

from ..clock import DeviceClockMap, PtpClockMap  # noqa: E402
from ..errors import (  # noqa: E402
    ClockError,
    DriverError,
    DriverInitError,
    DriverIOError,
    DriverTimeoutError,
)
from ..lifecycle import LifecycleState  # noqa: E402
from .base import Camera, CameraFrame  # noqa: E402

__all__ = [
    "PIXEL_FORMATS",
    "AravisCamera",
    "AravisDevice",
    "AravisFrame",
    "convert_image",
    "discover",
    "find_cameras",
    "gige_answer",
    "gige_controlled",
]

log = logging.getLogger(__name__)

# Pixel formats the driver converts, by GenICam name: bits per pixel of the mono formats,
# the Bayer tile's top-left 2x2 (OpenCV's RGGB-style names), and the packed colour ones.
_MONO_BITS = {"Mono8": 8, "Mono10": 10, "Mono12": 12, "Mono14": 14, "Mono16": 16}
_BAYER_TILE = {"BayerRG8": "RGGB", "BayerGR8": "GRBG", "BayerGB8": "GBRG", "BayerBG8": "BGGR"}
_COLOUR = ("RGB8", "BGR8")
#: GenICam pixel formats the driver turns into mono8 or BGR8 images.
PIXEL_FORMATS = (*_MONO_BITS, *_BAYER_TILE, *_COLOUR)

# Longest single wait for a buffer (s): a read polls in slices this long so that close()
# and cancellation never wait for a whole frame timeout.
_POP_SLICE_S = 0.05
# GigE Vision 1.x block ids are 16 bits and skip 0: ..., 65534, 65535, 1, 2, ...
_GV_ID_WRAP = 65535
# A backwards step of a GigE id counts as a wrap only from this close to the top to this
# close to the bottom; any other backwards step is a counter reset (camera restarted).
_GV_WRAP_MARGIN = 4096

# Aravis keeps one process-wide device list; discovery and opening go through it.
_SDK_LOCK = threading.Lock()

# Wording of the refused settings, one per check (ints and floats only: a setting given as a
# string is a configuration mistake, not something to parse).
_POSITIVE = NumberMessages.uniform("{what} must be a finite number > 0, got {value!r}")
_FINITE = NumberMessages.uniform("{what} must be a finite number, got {value!r}")

# GigE Vision control protocol (GVCP): unicast discovery (the serial number's offset in its
# acknowledge's payload) and register reads.
_GVCP_PORT = 3956
_GVCP_KEY = 0x42
_GVCP_ACK_REQUIRED = 0x01
_GVCP_DISCOVERY_CMD = 0x0002
_GVCP_DISCOVERY_ACK = 0x0003
_GVCP_SERIAL_AT = 0xD8
_GVCP_READREG_CMD = 0x0080
_GVCP_READREG_ACK = 0x0081
_GVCP_CCP_REGISTER = 0x0A00  # control channel privilege: 0 when nobody controls the camera


@dataclass(frozen=True)
class AravisDevice:
    """One camera as Aravis's discovery reports it."""

    device_id: str
    vendor: str
    model: str
    serial: str
    address: str
    physical_id: str
    protocol: str

    def describe(self) -> str:
        return (f"{self.device_id} ({self.vendor} {self.model}, serial {self.serial}, "
                f"{self.protocol} {self.address})")

    def matches(self, spec: str) -> bool:
        """Whether ``spec`` names this camera: device id, serial, address or MAC."""
        names = (self.device_id, self.serial, self.address)
        return spec in names or (bool(self.physical_id)
                                 and spec.lower() == self.physical_id.lower())


@dataclass(frozen=True, eq=False)
class AravisFrame(CameraFrame):
    """A :class:`CameraFrame` with what the camera itself says about the frame.

    Attributes:
        device_timestamp: capture time on the camera's clock, seconds (Aravis converts
            GigE Vision ticks to nanoseconds); not comparable between cameras unless their
            clocks are synchronised (PTP).
        frame_id: the camera's frame id, unwrapped past the 16-bit GigE Vision wrap; after a
            reconnect or a counter reset it goes on from the last value + 1.
        lost_before: frames the camera numbered but that were not delivered (never arrived,
            arrived incomplete, or found no free buffer) just before this one.
        epoch: 0 for the first link; +1 at each reconnect or counter reset, when
            ``frame_id`` offsets between cameras must be learnt again.
        pixel_format: the camera's pixel format the image was converted from.
    """

    device_timestamp: float
    frame_id: int
    lost_before: int
    epoch: int
    pixel_format: str


def discover() -> list[AravisDevice]:
    """Cameras Aravis finds (GigE Vision broadcast discovery and USB3 Vision); blocking,
    about 1 s (the GigE Vision discovery timeout)."""
    with _SDK_LOCK:
        return _discover_unlocked()


def _discover_unlocked() -> list[AravisDevice]:
    Aravis.update_device_list()
    return [
        AravisDevice(
            device_id=Aravis.get_device_id(i) or "",
            vendor=Aravis.get_device_vendor(i) or "",
            model=Aravis.get_device_model(i) or "",
            serial=Aravis.get_device_serial_nbr(i) or "",
            address=Aravis.get_device_address(i) or "",
            physical_id=Aravis.get_device_physical_id(i) or "",
            protocol=Aravis.get_device_protocol(i) or "",
        )
        for i in range(Aravis.get_n_devices())
    ]


def _gvcp(address: str, command: int, payload: bytes, ack: int, timeout: float) -> bytes | None:
    """One GVCP request to ``address``; the acknowledge's payload, or ``None`` when nothing
    (successful) answers within ``timeout`` s. Blocking."""
    request_id = int(time.monotonic_ns() % 0xFFFF) + 1
    packet = struct.pack(">BBHHH", _GVCP_KEY, _GVCP_ACK_REQUIRED, command, len(payload),
                         request_id) + payload
    deadline = time.monotonic() + timeout
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        try:
            sock.sendto(packet, (address, _GVCP_PORT))
            while (left := deadline - time.monotonic()) > 0:
                sock.settimeout(left)
                data, _ = sock.recvfrom(2048)
                if len(data) < 8:
                    continue
                status, answer, _, ack_id = struct.unpack(">HHHH", data[:8])
                if status == 0 and answer == ack and ack_id == request_id:
                    return data[8:]
        except OSError:  # timeout, unreachable network, refused
            return None
    return None


def gige_answer(address: str, timeout: float = 0.25) -> str | None:
    """Ask the GigE Vision camera at ``address`` who it is (a unicast GVCP discovery, which
    every GigE Vision device answers without being opened). Returns its serial number, or
    ``None`` when nothing answers within ``timeout`` s. Blocking."""
    reply = _gvcp(address, _GVCP_DISCOVERY_CMD, b"", _GVCP_DISCOVERY_ACK, timeout)
    if reply is None or len(reply) < _GVCP_SERIAL_AT + 16:
        return None
    serial = reply[_GVCP_SERIAL_AT:_GVCP_SERIAL_AT + 16].split(b"\0", 1)[0]
    return serial.decode("ascii", "replace")


def gige_controlled(address: str, timeout: float = 0.25) -> bool | None:
    """Whether an application controls the GigE Vision camera at ``address`` (its control
    channel privilege register is set; reading it needs no control); ``None`` if it does
    not answer. Blocking."""
    reply = _gvcp(address, _GVCP_READREG_CMD, struct.pack(">I", _GVCP_CCP_REGISTER),
                  _GVCP_READREG_ACK, timeout)
    if reply is None or len(reply) < 4:
        return None
    return struct.unpack(">I", reply[:4])[0] != 0


async def find_cameras() -> list[AravisDevice]:
    """:func:`discover` in a worker thread."""
    return await anyio.to_thread.run_sync(discover)


def _listing(devices: Sequence[AravisDevice]) -> str:
    if not devices:
        return "Aravis found no camera"
    return "cameras found: " + "; ".join(d.describe() for d in devices)


def _gerror(exc: BaseException) -> str:
    return getattr(exc, "message", None) or str(exc)


def _is_ip(text: str) -> bool:
    try:
        ipaddress.IPv4Address(text)
    except ValueError:
        return False
    return True


def convert_image(data: bytes, width: int, height: int, pixel_format: str, *,
                  mono: bool = True, x_padding: int = 0) -> np.ndarray:
    """Turn one buffer's bytes into (H, W) uint8 (``mono``) or (H, W, 3) uint8 BGR.

    Mono10..Mono16 (unpacked, little-endian 16-bit words) keep their 8 high bits; Bayer
    formats are demosaiced; ``x_padding`` bytes ending each row are skipped.

    Raises:
        ValueError: an unsupported format, or too few bytes for the image.
    """
    if pixel_format in _MONO_BITS:
        bits = _MONO_BITS[pixel_format]
        channels, itemsize = 1, (1 if bits == 8 else 2)
    elif pixel_format in _BAYER_TILE:
        channels, itemsize = 1, 1
    elif pixel_format in _COLOUR:
        channels, itemsize = 3, 1
    else:
        raise ValueError(f"pixel format {pixel_format!r} is not one of {', '.join(PIXEL_FORMATS)}")
    row = width * channels * itemsize
    stride = row + x_padding
    need = stride * (height - 1) + row
    if len(data) < need:
        raise ValueError(f"{pixel_format} {width}x{height}: buffer holds {len(data)} bytes, "
                         f"need {need}")
    raw = np.frombuffer(data, np.uint8, count=need)
    if x_padding:
        raw = np.lib.stride_tricks.as_strided(raw, (height, row), (stride, 1))
    raw = raw.reshape(height, row)
    if pixel_format in _MONO_BITS:
        if itemsize == 1:
            gray = raw.copy()
        else:
            words = np.ascontiguousarray(raw).view("<u2")
            gray = (words >> (bits - 8)).astype(np.uint8)
        return gray if mono else cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)
    if pixel_format in _BAYER_TILE:
        tile = _BAYER_TILE[pixel_format]
        code = getattr(cv2, f"COLOR_Bayer{tile}2{'GRAY' if mono else 'BGR'}")
        return cv2.cvtColor(np.ascontiguousarray(raw), code)
    pixels = np.ascontiguousarray(raw).reshape(height, width, 3)
    if pixel_format == "RGB8":
        return cv2.cvtColor(pixels, cv2.COLOR_RGB2GRAY if mono else cv2.COLOR_RGB2BGR)
    return cv2.cvtColor(pixels, cv2.COLOR_BGR2GRAY) if mono else pixels.copy()


@dataclass
class _Raw:
    """One buffer's content, taken in the worker thread."""

    image: np.ndarray
    frame_id: int
    device_ns: int
    system_ns: int


class _Link:
    """The SDK objects of one connection: the camera (and its device) and its stream."""

    def __init__(self, camera: Any, stream: Any, device: AravisDevice | None, target: str,
                 gv: bool, pixel_format: str, size: tuple[int, int]) -> None:
        self.camera = camera
        self.stream = stream
        self.device = device
        self.target = target
        self.gv = gv
        self.pixel_format = pixel_format
        self.size = size

    def release(self, stop: bool) -> None:
        """Stop the acquisition (if ``stop``) and drop the SDK objects. Blocking: Aravis
        retries its last register writes for seconds on a camera that has gone."""
        camera, stream = self.camera, self.stream
        self.camera = self.stream = None
        if camera is not None and stop:
            try:
                camera.stop_acquisition()
            except GLib.Error as exc:
                log.debug("stop_acquisition on release: %s", _gerror(exc))
        # The stream first: its teardown writes to the camera through the device.
        del stream
        if camera is not None and stop and self.gv:
            # Give up control now, not whenever the last reference to the device goes.
            device = camera.get_device()
            if device.is_controller():
                try:
                    device.leave_control()
                except GLib.Error as exc:
                    log.debug("leave_control on release: %s", _gerror(exc))
            del device
        del camera


class AravisCamera(Camera):
    """A GigE Vision or USB3 Vision camera through Aravis (see the module docs).

    Args:
        camera_id: which camera: an IPv4 address (opened directly, no discovery), or the
            device id :func:`discover` lists, a serial number or a MAC address (found by
            discovery); ``None``: the first camera discovery finds.
        name: camera name put in every frame; default ``camera_id`` or ``"aravis"``.
        pixel_format: GenICam pixel format the camera sends, one of :data:`PIXEL_FORMATS`.
        mono: deliver (H, W) uint8 mono8 images; ``False`` delivers (H, W, 3) uint8 BGR.
        region: ``(x, y, width, height)`` px on the sensor; default: the camera's own.
        exposure_us: exposure time, microseconds (auto exposure is switched off).
        gain: gain in the camera's unit (dB on most SFNC cameras; auto gain switched off).
        frame_rate: Hz, for free-running; also the upper bound of triggered frames on
            cameras that honour it. ``None`` keeps the camera's.
        trigger: ``"off"`` (free-running), ``"software"``, or a hardware trigger source
            of the camera (``"Line0"``, ``"Line1"``...) for frame-start triggers.
        trigger_activation: for hardware triggers, e.g. ``"RisingEdge"``; default: the
            camera's.
        auto_trigger: with ``trigger="software"``, ``read()`` fires the trigger itself when
            no triggered frame is pending; ``False`` leaves firing to
            :meth:`software_trigger`.
        buffers: size of the buffer pool (frames the camera can get ahead of the reader).
        timeout: s ``read()`` waits for a frame (see the module docs for what follows).
        packet_size: GigE Vision stream packet size, bytes (jumbo frames: up to ~9000);
            default: the camera's.
        reconnect: re-establish a lost link on the following reads.
        reconnect_backoff: (first, max) s between reconnect attempts, doubling.
        timestamps: what ``CameraFrame.timestamp`` is: ``"arrival"``, when the frame
            arrived on this computer (default), or ``"device"``, the camera's own frame
            timestamp mapped onto ``time.monotonic()`` (:class:`~..clock.DeviceClockMap`):
            the capture instant plus the shortest transfer delay, free of each frame's
            transfer jitter; or ``"ptp"``, the camera's timestamp as PTP (IEEE 1588) time,
            TAI, mapped with this computer's own clocks (:class:`~..clock.PtpClockMap`):
            the capture instant itself, when both are synchronised to one grandmaster. A
            device clock that goes back or jumps, or a PTP time that does not match the
            arrival, is a :class:`~..errors.ClockError` from ``read()``, never a frame
            placed wrongly.

    After ``start()``: ``device`` (the :class:`AravisDevice` opened), ``applied`` (the
    settings read back from the camera) and the counters ``delivered``, ``lost_frames``,
    ``incomplete_frames``, ``underruns``, ``timeouts`` and ``reconnects``.
    """

    def __init__(
        self,
        camera_id: str | None = None,
        *,
        name: str | None = None,
        pixel_format: str = "Mono8",
        mono: bool = True,
        region: tuple[int, int, int, int] | None = None,
        exposure_us: float | None = None,
        gain: float | None = None,
        frame_rate: float | None = None,
        trigger: str = "off",
        trigger_activation: str | None = None,
        auto_trigger: bool = True,
        buffers: int = 8,
        timeout: float = 1.0,
        packet_size: int | None = None,
        reconnect: bool = True,
        reconnect_backoff: tuple[float, float] = (0.2, 5.0),
        timestamps: str = "arrival",
    ) -> None:
        if camera_id is not None and (not isinstance(camera_id, str) or not camera_id.strip()):
            raise DriverInitError(f"aravis camera_id must be a non-empty string or None, "
                                  f"got {camera_id!r}")
        super().__init__(name if name is not None else (camera_id or "aravis"))
        self.camera_id = camera_id.strip() if camera_id else None
        what = f"camera {self.name!r}"
        if pixel_format not in PIXEL_FORMATS:
            raise DriverInitError(f"{what}: pixel_format {pixel_format!r} is not supported; "
                                  f"use one of {', '.join(PIXEL_FORMATS)}")
        self.pixel_format = pixel_format
        self.mono = bool(mono)
        if region is not None:
            if (not isinstance(region, Sequence) or len(region) != 4
                    or not all(isinstance(v, int | np.integer) and not isinstance(v, bool)
                               for v in region)
                    or min(region[:2]) < 0 or min(region[2:]) <= 0):
                raise DriverInitError(f"{what}: region must be (x, y, width, height) px with "
                                      f"x, y >= 0 and width, height > 0, got {region!r}")
            region = tuple(int(v) for v in region)
        self.region = region
        self.exposure_us = (None if exposure_us is None else positive_number(
            exposure_us, f"{what}: exposure_us", DriverInitError, numbers_only=True,
            messages=_POSITIVE))
        self.gain = (None if gain is None else finite_number(
            gain, f"{what}: gain", DriverInitError, numbers_only=True, messages=_FINITE))
        self.frame_rate = (None if frame_rate is None else positive_number(
            frame_rate, f"{what}: frame_rate", DriverInitError, numbers_only=True,
            messages=_POSITIVE))
        if not isinstance(trigger, str) or not trigger:
            raise DriverInitError(f"{what}: trigger must be 'off', 'software' or a trigger "
                                  f"source name such as 'Line0', got {trigger!r}")
        self.trigger = trigger.lower() if trigger.lower() in ("off", "software") else trigger
        if trigger_activation is not None and (
                not isinstance(trigger_activation, str) or not trigger_activation):
            raise DriverInitError(f"{what}: trigger_activation must be a name such as "
                                  f"'RisingEdge', got {trigger_activation!r}")
        if trigger_activation is not None and self.trigger in ("off", "software"):
            raise DriverInitError(f"{what}: trigger_activation applies to hardware triggers "
                                  f"only (trigger={self.trigger!r})")
        self.trigger_activation = trigger_activation
        self.auto_trigger = bool(auto_trigger)
        if isinstance(buffers, bool) or not isinstance(buffers, int) or buffers < 1:
            raise DriverInitError(f"{what}: buffers must be an integer >= 1, got {buffers!r}")
        self.buffers = buffers
        self.timeout = positive_number(timeout, f"{what}: timeout", DriverInitError,
                                       numbers_only=True, messages=_POSITIVE)
        if packet_size is not None and (isinstance(packet_size, bool)
                                        or not isinstance(packet_size, int)
                                        or not 576 <= packet_size <= 16384):
            raise DriverInitError(f"{what}: packet_size must be an integer in 576..16384 "
                                  f"bytes, got {packet_size!r}")
        self.packet_size = packet_size
        self.reconnect = bool(reconnect)
        try:
            lo, hi = (float(v) for v in reconnect_backoff)
        except (TypeError, ValueError):
            lo = hi = math.nan
        if not (0 < lo <= hi and math.isfinite(hi)):
            raise DriverInitError(f"{what}: reconnect_backoff must be (first, max) s with "
                                  f"0 < first <= max, got {reconnect_backoff!r}")
        self.reconnect_backoff = (lo, hi)
        if timestamps not in ("arrival", "device", "ptp"):
            raise DriverInitError(f"{what}: timestamps must be 'arrival', 'device' or "
                                  f"'ptp', got {timestamps!r}")
        self.timestamps = timestamps
        self._clock_map = PtpClockMap() if timestamps == "ptp" else DeviceClockMap()

        self._lock = threading.Lock()  # the SDK objects below
        self._life = LifecycleState()  # changed under _lock
        self._read_lock: anyio.Lock | None = None
        self._link: _Link | None = None
        self._stale: list[_Link] = []  # links lost, released once the camera answers again
        self._device: AravisDevice | None = None
        self.applied: dict[str, Any] = {}
        # reading state (touched by the one reader under _read_lock)
        self._counter = 0
        self._pending = 0  # software triggers fired whose frame has not come yet
        self._last_raw: int | None = None  # raw id of the last frame of this link
        self._frame_id: int | None = None  # unwrapped id of the last frame delivered
        self._epoch = 0
        self._last_stamp = -math.inf
        self._lost: str | None = None
        self._attempts = 0
        self._backoff = lo
        self._next_attempt = 0.0
        self.lost_frames = 0
        self.incomplete_frames = 0
        self.timeouts = 0
        self.reconnects = 0

    # -- properties -------------------------------------------------------------------------

    @property
    def device(self) -> AravisDevice | None:
        """The camera opened (``None`` before ``start()``). Opened by address, its
        ``device_id`` is the camera's DeviceID feature rather than discovery's id."""
        return self._device

    @property
    def delivered(self) -> int:
        """Frames ``read()`` has returned."""
        return self._counter

    @property
    def connected(self) -> bool:
        """Started, not closed, and the link not lost."""
        return self._life.running and self._lost is None

    @property
    def underruns(self) -> int:
        """Aravis's underrun count on the current link: data it discarded because no buffer
        was free (it counts packets; the frames lost that way count in ``lost_frames``)."""
        with self._lock:
            link = self._link
            if link is None or link.stream is None:
                return 0
            return int(link.stream.get_info_uint64_by_name("n_underruns"))

    def _label(self) -> str:
        if self._device is not None:
            where = f"{self._device.device_id} at {self._device.address}"
        else:
            where = self.camera_id or "first camera found"
        return f"camera {self.name!r} ({where})"

    # -- lifecycle --------------------------------------------------------------------------

    async def start(self) -> None:
        with self._lock:
            self._life.begin_start(f"{self._label()}: start() called twice or after close() "
                                   "(build a new camera)")
        self._read_lock = anyio.Lock()
        await anyio.to_thread.run_sync(self._connect, False)
        with self._lock:
            closed = not self._life.finish_start()
        if closed:
            await anyio.to_thread.run_sync(self._release_all)
            raise DriverInitError(f"{self._label()}: closed during start()")
        log.info("%s: streaming %s %dx%d", self._label(), self.pixel_format, *self.size)

    async def close(self) -> None:
        with self._lock:
            if not self._life.close():
                return
        with anyio.CancelScope(shield=True):
            await anyio.to_thread.run_sync(self._release_all)

    def _release_all(self) -> None:
        with self._lock:
            links = ([self._link] if self._link is not None else []) + self._stale
            live = self._link
            self._link, self._stale = None, []
        for link in links:
            link.release(stop=link is live)

    # -- reading ----------------------------------------------------------------------------

    async def read(self) -> AravisFrame:
        self._check_state()
        assert self._read_lock is not None
        async with self._read_lock:
            self._check_state()
            if self._lost is not None:
                await self._recover()
            if self.trigger == "software" and self.auto_trigger and self._pending == 0:
                await anyio.to_thread.run_sync(self._fire)
            deadline = time.monotonic() + self.timeout
            while (remaining := deadline - time.monotonic()) > 0:
                raw = await anyio.to_thread.run_sync(self._pop, min(remaining, _POP_SLICE_S))
                self._check_state(during=True)
                if raw is not None:
                    return self._frame(raw)
            await self._timed_out()
        raise AssertionError("unreachable")  # _timed_out always raises

    async def software_trigger(self) -> None:
        """Fire one software trigger (``trigger="software"``); its frame comes by ``read()``.

        Raises:
            DriverIOError: not a software-triggered camera, not started, closed or lost.
        """
        if self.trigger != "software":
            raise DriverIOError(f"{self._label()}: software_trigger() needs trigger='software' "
                                f"(it is {self.trigger!r})")
        self._check_state()
        if self._lost is not None:
            raise DriverIOError(f"{self._label()}: link lost ({self._lost}); read() reconnects")
        await anyio.to_thread.run_sync(self._fire)

    def _check_state(self, during: bool = False) -> None:
        if not self._life.running:  # the label only for the message
            self._life.check(self._label(), during="read()" if during else None)

    def _fire(self) -> None:
        with self._lock:
            link = self._link
            if link is None or link.camera is None:
                raise DriverIOError(f"{self._label()}: closed")
            try:
                link.camera.software_trigger()
            except GLib.Error as exc:
                why = f"software trigger failed: {_gerror(exc)}"
                self._mark_lost_locked(why)
                raise DriverIOError(f"{self._label()}: {why}; {self._next_step()}") from None
            self._pending += 1

    def _pop(self, timeout_s: float) -> _Raw | None:
        with self._lock:
            link = self._link
            if link is None or link.stream is None:
                return None
            buffer = link.stream.timeout_pop_buffer(max(1, int(timeout_s * 1e6)))
            if buffer is None:
                return None
            try:
                if (buffer.get_status() != Aravis.BufferStatus.SUCCESS
                        or buffer.get_payload_type() != Aravis.BufferPayloadType.IMAGE):
                    self.incomplete_frames += 1
                    log.debug("%s: frame %d dropped (%s)", self._label(),
                              buffer.get_frame_id(), buffer.get_status().value_nick)
                    return None
                width, height = buffer.get_image_width(), buffer.get_image_height()
                x_padding = buffer.get_image_padding()[0]
                try:
                    image = convert_image(buffer.get_data(), width, height, link.pixel_format,
                                          mono=self.mono, x_padding=x_padding)
                except ValueError as exc:
                    self.incomplete_frames += 1
                    log.warning("%s: frame %d dropped: %s", self._label(),
                                buffer.get_frame_id(), exc)
                    return None
                return _Raw(image, int(buffer.get_frame_id()), int(buffer.get_timestamp()),
                            int(buffer.get_system_timestamp()))
            finally:
                link.stream.push_buffer(buffer)

    def _frame(self, raw: _Raw) -> AravisFrame:
        link = self._link
        gv = link.gv if link is not None else True
        lost = 0
        if self._frame_id is None:
            frame_id = raw.frame_id
        elif self._last_raw is None:  # first frame of a new link
            frame_id = self._frame_id + 1
            self._epoch += 1
            self._clock_map.reset()  # a new link: the camera may have restarted its clock
        else:
            step = raw.frame_id - self._last_raw
            if step <= 0 and gv and self._last_raw > _GV_ID_WRAP - _GV_WRAP_MARGIN \
                    and raw.frame_id < _GV_WRAP_MARGIN:
                step = max(1, raw.frame_id + _GV_ID_WRAP - self._last_raw)
            if step <= 0:  # the camera's counter went back: it restarted
                log.warning("%s: frame id went from %d to %d; counter reset", self._label(),
                            self._last_raw, raw.frame_id)
                self._epoch += 1
                self._clock_map.reset()  # a restarted camera restarted its clock too
                step = 1
            else:
                lost = step - 1
            frame_id = self._frame_id + step
        self._last_raw, self._frame_id = raw.frame_id, frame_id
        self.lost_frames += lost
        self._pending = max(0, self._pending - 1)
        # Arrival time: Aravis stamps the host's real-time clock (ns); map it onto
        # time.monotonic() and keep the stamps non-decreasing and not in the future.
        now = time.monotonic()
        stamp = raw.system_ns * 1e-9 - (time.time() - now)
        if not (now - 60.0 <= stamp <= now):  # the wall clock was stepped
            stamp = now
        if self.timestamps in ("device", "ptp"):
            try:
                stamp = self._clock_map.map(raw.device_ns * 1e-9, stamp)
            except ClockError as exc:
                raise ClockError(f"{self._label()}: {exc}") from None
        stamp = max(stamp, self._last_stamp)
        self._last_stamp = stamp
        frame = AravisFrame(image=raw.image, timestamp=stamp, counter=self._counter,
                            camera=self.name, device_timestamp=raw.device_ns * 1e-9,
                            frame_id=frame_id, lost_before=lost, epoch=self._epoch,
                            pixel_format=link.pixel_format if link else self.pixel_format)
        self._counter += 1
        return frame

    async def _timed_out(self) -> None:
        self.timeouts += 1
        self._pending = 0
        waited = f"no frame for {self.timeout:.2f} s"
        if self.trigger == "off":
            with self._lock:
                self._mark_lost_locked(waited)
            raise DriverTimeoutError(f"{self._label()}: {waited} while free-running; "
                                     f"{self._next_step()}")
        why = await anyio.to_thread.run_sync(self._probe)
        if why is not None:
            raise DriverIOError(f"{self._label()}: lost ({why}); {self._next_step()}")
        raise DriverTimeoutError(f"{self._label()}: {waited} (trigger {self.trigger}: no "
                                 "trigger came, or its frame was lost)")

    def _probe(self) -> str | None:
        """Whether the triggered camera still answers and is still armed; the reason if not
        (then the link is marked lost)."""
        with self._lock:
            link = self._link
            if link is None or link.camera is None:
                return None
            try:
                mode = link.camera.get_string("TriggerMode")
            except GLib.Error as exc:
                why = f"the camera does not answer: {_gerror(exc)}"
            else:
                if mode == "On":
                    return None
                why = f"the camera's TriggerMode is {mode!r} (it restarted?)"
            self._mark_lost_locked(why)
            return why

    def _mark_lost_locked(self, why: str) -> None:
        if self._link is not None:
            self._stale.append(self._link)
            self._link = None
        if self._lost is None:
            self._lost = why
            self._attempts = 0
            self._backoff = self.reconnect_backoff[0]
            self._next_attempt = time.monotonic() + self._backoff
            log.warning("%s: link lost (%s)", self._label(), why)

    def _next_step(self) -> str:
        if self.reconnect:
            return "the next read() reconnects"
        return "reconnect is off: close() and build a new camera"

    async def _recover(self) -> None:
        why = self._lost
        if not self.reconnect:
            raise DriverIOError(f"{self._label()}: lost ({why}); {self._next_step()}")
        delay = self._next_attempt - time.monotonic()
        if delay > 0:
            await anyio.sleep(delay)
        self._check_state()
        self._attempts += 1
        try:
            await anyio.to_thread.run_sync(self._connect, True)
        except DriverError as exc:
            self._backoff = min(self._backoff * 2, self.reconnect_backoff[1])
            self._next_attempt = time.monotonic() + self._backoff
            raise DriverIOError(f"{self._label()}: lost ({why}); reconnect attempt "
                                f"{self._attempts} failed: {exc}") from exc
        self._lost = None
        self._last_raw = None
        self._pending = 0
        self.reconnects += 1
        log.warning("%s: reconnected after %d attempt(s)", self._label(), self._attempts)

    # -- opening (worker thread) -----------------------------------------------------------------

    def _connect(self, reconnecting: bool) -> None:
        """Find, open, configure and start the camera; store the link. Raises
        DriverInitError (start) or DriverIOError (reconnect) naming what failed."""
        error = DriverIOError if reconnecting else DriverInitError
        device, target = self._relocate() if reconnecting else self._locate()
        # The camera answers: free the lost link first (quick now), so that the camera
        # accepts the new one as its controller.
        with self._lock:
            stale, self._stale = self._stale, []
        for old in stale:
            old.release(stop=True)
        link = self._open(device, target, error)
        with self._lock:
            if self._life.closed:
                self._stale.append(link)
                return
            if reconnecting and self._size is not None and link.size != self._size:
                self._stale.append(link)
                raise error(f"{self._label()}: came back with size {link.size}, "
                            f"not {self._size}")
            self._link = link
            self._device = link.device
            self._size = link.size

    def _locate(self) -> tuple[AravisDevice | None, str]:
        """For start(): (discovered device or None, what to open: an address, or the
        device id of a USB3 Vision camera)."""
        spec = self.camera_id
        if spec is not None and _is_ip(spec):
            if gige_answer(spec, timeout=0.5) is None:
                raise DriverInitError(f"camera {self.name!r}: no GigE Vision camera answers "
                                      f"at {spec}; {_listing(discover())}")
            return None, spec  # opened directly, without discovery
        devices = discover()
        if spec is None:
            if not devices:
                raise DriverInitError(f"camera {self.name!r}: {_listing(devices)} (GigE "
                                      "Vision discovery on every interface, and USB3 Vision)")
            return devices[0], _target(devices[0])
        for device in devices:
            if device.matches(spec):
                return device, _target(device)
        raise DriverInitError(f"camera {self.name!r}: no camera {spec!r}; "
                              f"{_listing(devices)}")

    def _relocate(self) -> tuple[AravisDevice | None, str]:
        """For a reconnect: find the camera opened before, without opening anything."""
        device = self._device
        assert device is not None
        if device.protocol == "GigEVision" and device.address:
            serial = gige_answer(device.address)
            if serial is not None and (serial == device.serial or not device.serial):
                return device, device.address
            if self.camera_id is not None and _is_ip(self.camera_id):
                raise DriverIOError(f"no answer from {device.address}" + (
                    "" if serial is None else f" (a camera with serial {serial} answers)"))
        # moved to another address, or a USB3 camera: look for its device id
        for found in discover():
            if found.device_id == device.device_id:
                return found, _target(found)
        raise DriverIOError(f"{device.device_id} not found by discovery")

    def _open(self, device: AravisDevice | None, target: str,
              error: type[DriverError]) -> _Link:
        # On failure the error leaves as a fresh exception: the original's traceback would
        # keep the camera alive, to be finalised later on whatever thread drops it (Aravis
        # then writes to the camera, blocking for seconds if someone else controls it).
        camera = stream = None
        failure: DriverError | None = None
        try:
            if (device is None or device.protocol == "GigEVision") and _is_ip(target) \
                    and gige_controlled(target):
                # Aravis would spend seconds trying to take control, then open it read-only
                raise error(f"camera {self.name!r}: {target} is controlled by another "
                            "application; close that first")
            with _SDK_LOCK:
                camera = Aravis.Camera.new(target)
            gv = bool(camera.is_gv_device())
            if gv and not camera.get_device().is_controller():
                raise error(f"camera {self.name!r}: {target} is controlled by another "
                            "application (Aravis could open it only read-only); close that "
                            "first")
            if device is None:
                device = AravisDevice(
                    device_id=camera.get_device_id() or "", vendor=camera.get_vendor_name() or "",
                    model=camera.get_model_name() or "",
                    serial=camera.get_device_serial_number() or "", address=target,
                    physical_id="", protocol="GigEVision" if gv else "USB3Vision")
            self._configure(camera, target, error)
            if gv and self.packet_size is not None:
                camera.gv_set_packet_size(self.packet_size)
            payload = camera.get_payload()
            stream = camera.create_stream(None, None)
            if stream is None:
                raise error(f"camera {self.name!r}: {target}: cannot create a stream")
            for _ in range(self.buffers):
                stream.push_buffer(Aravis.Buffer.new_allocate(payload))
            camera.set_acquisition_mode(Aravis.AcquisitionMode.CONTINUOUS)
            camera.start_acquisition()
            region = camera.get_region()
            link = _Link(camera, stream, device, target, gv, self.pixel_format,
                         (int(region.width), int(region.height)))
            camera = stream = None
            return link
        except DriverError as exc:
            failure = type(exc)(str(exc))
        except GLib.Error as exc:
            failure = error(f"camera {self.name!r}: cannot open {target}: {_gerror(exc)}"
                            if camera is None else f"camera {self.name!r}: {target}: "
                            f"{_gerror(exc)}")
        finally:
            if camera is not None:  # failed halfway: release what was opened, here
                _Link(camera, stream, None, target, True, "", (0, 0)).release(stop=False)
                camera = stream = None
        raise failure

    def _configure(self, camera: Any, target: str, error: type[DriverError]) -> None:
        what = f"camera {self.name!r} ({target})"

        def check(ok: bool, message: str) -> None:
            if not ok:
                raise error(f"{what}: {message}")

        def within(key: str, value: float, bounds: Any, unit: str) -> None:
            lo, hi = float(bounds.min), float(bounds.max)
            check(lo <= value <= hi, f"{key} {value:g} {unit} is outside the camera's range "
                                     f"{lo:g}..{hi:g} {unit}")

        def apply(key: str, call: Any, *args: Any) -> None:
            try:
                call(*args)
            except GLib.Error as exc:
                raise error(f"{what}: cannot set {key} {args!r}: {_gerror(exc)}") from None

        if self.region is not None:
            x, y, w, h = self.region
            sensor = camera.get_sensor_size()
            check(x + w <= sensor.width and y + h <= sensor.height,
                  f"region {self.region} does not fit the sensor "
                  f"{sensor.width}x{sensor.height}")
            apply("region", camera.set_region, x, y, w, h)
            got = camera.get_region()
            check((got.x, got.y, got.width, got.height) == self.region,
                  f"region {self.region} not accepted: the camera set "
                  f"{(got.x, got.y, got.width, got.height)} (check the width/height/offset "
                  "increments)")
        available = list(camera.dup_available_pixel_formats_as_strings() or [])
        check(self.pixel_format in available,
              f"pixel_format {self.pixel_format!r} is not offered; the camera offers "
              f"{', '.join(available) or 'none'} (the driver converts "
              f"{', '.join(PIXEL_FORMATS)})")
        apply("pixel_format", camera.set_pixel_format_from_string, self.pixel_format)
        if self.frame_rate is not None:
            # before the trigger: Aravis's set_frame_rate switches frame-start triggers off
            check(camera.is_frame_rate_available(), "frame_rate is not settable on it")
            within("frame_rate", self.frame_rate, camera.get_frame_rate_bounds(), "Hz")
            apply("frame_rate", camera.set_frame_rate, self.frame_rate)
        if self.exposure_us is not None:
            check(camera.is_exposure_time_available(), "exposure is not settable on it")
            if camera.is_exposure_auto_available():
                apply("exposure auto", camera.set_exposure_time_auto, Aravis.Auto.OFF)
            within("exposure_us", self.exposure_us, camera.get_exposure_time_bounds(), "us")
            apply("exposure_us", camera.set_exposure_time, self.exposure_us)
        if self.gain is not None:
            check(camera.is_gain_available(), "gain is not settable on it")
            if camera.is_gain_auto_available():
                apply("gain auto", camera.set_gain_auto, Aravis.Auto.OFF)
            within("gain", self.gain, camera.get_gain_bounds(), "")
            apply("gain", camera.set_gain, self.gain)
        if self.trigger == "off":
            apply("trigger", camera.clear_triggers)
        elif self.trigger == "software":
            check(camera.is_software_trigger_supported(),
                  "it has no software trigger (TriggerSoftware)")
            apply("trigger", camera.set_trigger, "Software")
        else:
            sources = list(camera.dup_available_trigger_sources() or [])
            check(self.trigger in sources,
                  f"trigger source {self.trigger!r} is not offered; the camera offers "
                  f"{', '.join(sources) or 'none'}")
            apply("trigger", camera.set_trigger, self.trigger)
            if self.trigger_activation is not None:
                kinds = list(camera.dup_available_enumerations_as_strings(
                    "TriggerActivation") or [])
                check(self.trigger_activation in kinds,
                      f"trigger_activation {self.trigger_activation!r} is not offered; the "
                      f"camera offers {', '.join(kinds) or 'none'}")
                apply("trigger_activation", camera.set_string, "TriggerActivation",
                      self.trigger_activation)
        region = camera.get_region()
        self.applied = {
            "pixel_format": camera.get_pixel_format_as_string(),
            "region": (region.x, region.y, region.width, region.height),
            "exposure_us": (camera.get_exposure_time()
                            if camera.is_exposure_time_available() else None),
            "gain": camera.get_gain() if camera.is_gain_available() else None,
            "frame_rate": camera.get_frame_rate() if camera.is_frame_rate_available() else None,
            "trigger": (self.trigger if self.trigger == "off"
                        else camera.get_trigger_source()),
        }


def _target(device: AravisDevice) -> str:
    # GigE cameras are opened by address: Aravis then picks the interface that routes to
    # them (discovery answers may come back through another interface).
    if device.protocol == "GigEVision" and device.address:
        return device.address
    return device.device_id
