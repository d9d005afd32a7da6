"""A simulated GigE Vision camera that streams images *we* render: Aravis's ``GvFakeCamera``
run inside this process, its pixels, block ids and timestamps replaced by ours, so the
``aravis`` camera backend receives rendered frames over real GVCP/GVSP on loopback.

Which path, and why
    The camera is Aravis's own simulator (``Aravis.GvFakeCamera``, the object behind
    ``arv-fake-gv-camera-0.8``), created through PyGObject: it binds GVCP (UDP 3956) on one
    address, answers discovery and register access, and sends each frame as GVSP packets
    from a thread of its own. Per frame it calls a *fill-pattern* callback with the
    ``ArvBuffer`` about to be sent; ours writes the rendered image into that buffer and sets
    the block id and the timestamp carried by the GVSP leader.

    Two parts go through :mod:`ctypes` on ``libaravis-0.8.so.0`` (the library PyGObject has
    already loaded) instead of PyGObject, because PyGObject cannot do them:

    - ``FakeCamera.set_fill_pattern`` is annotated ``(scope call)``: PyGObject frees the
      callback's closure when ``set_fill_pattern`` returns, and the camera thread's next
      frame calls freed memory (the process dies of SIGSEGV; tried). The callback is
      therefore a ``ctypes.CFUNCTYPE`` object this class keeps alive until the camera is
      destroyed, registered with ``arv_fake_camera_set_fill_pattern`` on the C pointer of
      the ``FakeCamera`` (``__gpointer__``, checked to be an ``ArvFakeCamera`` instance).
    - ``ArvBuffer.get_data()`` hands Python a copy (and at fill time its size is the received
      size, 0). The callback gets the buffer's C pointer, reads its image width, height,
      offsets and pixel format (which the camera has already checked against the buffer's
      allocation) and writes exactly that many bytes through a numpy view of
      ``arv_buffer_get_data``'s pointer, never more.

Threads and the GIL
    The callback runs in the camera's own C thread (``arv_fake_gv_fake_camera``), which also
    answers GVCP: while the callback blocks, control requests wait (Aravis's GVCP gives a
    request 500 ms and 5 retries), so it blocks at most :data:`MAX_BLOCK_S` per frame except
    for the very first frame of an acquisition (below). ctypes takes the GIL for the
    callback; the copy into the buffer and the packet sending run without it. The callback
    calls no PyGObject, no ``logging`` and nothing that creates a ``threading`` object
    (a foreign thread calling ``threading.current_thread()`` would leave a dummy thread
    behind forever): the source is called, and every message logged, by a Python thread of
    this class.

Frames
    The simulator sends one frame at each of its frame instants: the multiples of the frame
    period (from the frame rate the driver sets) on the wall clock, or each software trigger.
    Free-running, the renderer thread calls ``source()`` ahead of each instant, early enough
    (render time, latency and its own wake-up delay, measured as it runs) for the frame to
    be ready and due at that instant: the first packet leaves never before ``capture +
    latency_s``, and the driver stamps its arrival typically 2-6 ms after that (measured on
    a 2-core VM, 1920x1200 mono8). With a latency longer than the period several
    frames are in flight, as in a camera whose exposures overlap earlier frames' transfer.
    Triggered, the frame is rendered when the trigger comes. When sending falls behind, a
    frame instant is skipped rather than every later frame going out late. Block ids go 1,
    2, ... 65535, 1 (GigE Vision 1.x ids are 16 bits and skip 0), one per frame sent; a frame
    the source fails to render is skipped and uses no id.

    The simulator sends at every instant, whatever the callback does. At an instant with no
    frame due within :data:`MAX_BLOCK_S` (a skipped render, a source slower than that), the
    callback leaves the previous frame's bytes, id and timestamp in the buffer: the packets
    repeat a block the receiver already has, and a GVSP receiver drops them (Aravis: a "late
    frame", counted as ignored packets; no frame is lost or delivered). The first frame of
    an acquisition has nothing to repeat, so that callback waits for a frame however long
    the source takes, and GVCP is not answered meanwhile: if the first render is slow (the
    renderer's lazy set-up), render once before the driver opens the camera.

Only Aravis's GigE simulator's registers are touched: ``size`` sets its sensor (and default
image) size; the driver's region, pixel format, frame rate and trigger settings reach it over
GVCP as they would a camera. Pixel formats: Mono8 carries the image exactly; Mono16 carries
it in the high byte, RGB8 in all three channels, Bayer formats as the mosaic itself.
Binning, exposure and gain are ignored.
"""

from __future__ import annotations

import atexit
import contextlib
import ctypes
import functools
import ipaddress
import logging
import math
import random
import threading
import time
import traceback
import weakref
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from oralnav.drivers.clock import tai_minus_monotonic
from oralnav.sim.errors import SimError
from oralnav.sim.peers.gige_fake import loopback_address

__all__ = [
    "LIBARAVIS",
    "MAX_BLOCK_S",
    "AravisMissing",
    "CameraSettingsError",
    "CameraStartError",
    "FrameError",
    "RenderedCameraError",
    "RenderedGvCamera",
]

log = logging.getLogger(__name__)

#: The shared library the ctypes calls go to: the one PyGObject's Aravis 0.8 uses.
LIBARAVIS = "libaravis-0.8.so.0"
_LIBGOBJECT = "libgobject-2.0.so.0"

#: Longest a frame callback keeps the camera thread (and so its GVCP answers) waiting for a
#: frame, s: half of Aravis's 500 ms GVCP timeout, so a control request is at worst retried.
MAX_BLOCK_S = 0.25
# How often the renderer thread looks at the camera's registers while it has nothing to do
# (acquisition off, triggered, enough frames ahead), s.
_POLL_S = 0.02
# The leader leaves this long after capture + latency_s: the receiver maps its real-time
# arrival stamp onto time.monotonic() with two clock reads, good to some microseconds.
_DUE_MARGIN_S = 2e-4
# Rendering starts this long (s) before the send it is for, beyond the render time or the
# latency; and the weight of each new render in the running means of their timing.
_LEAD_MARGIN_S = 1e-3
_EMA = 0.2
# A capture instant further from time.monotonic() than this is not on that clock.
_FUTURE_S = 1.0
_PAST_S = 60.0
# At most one warning a second about skipped frames; the rest go to debug.
_LOG_EVERY_S = 1.0
# GigE Vision 1.x block ids: 16 bits, 0 is invalid.
_MAX_BLOCK_ID = 65535
_MAX_SIDE = 65535
_SERIAL_LEN = 15  # ARV_GVBS_SERIAL_NUMBER_SIZE (16) less the terminating NUL
# GigE Vision bootstrap register: control channel privilege, 0 while nobody controls the
# camera (the simulator sends frames only to a controller).
_GVBS_CCP = 0x0A00

# GenICam pixel formats (PFNC values) the callback can write; others are reported.
_MONO8 = 0x01080001
_MONO16 = 0x01100007
_RGB8 = 0x02180014
_BAYER8 = (0x01080008, 0x01080009, 0x0108000A, 0x0108000B)  # GR, RG, GB, BG


class RenderedCameraError(SimError):
    """Base of what :class:`RenderedGvCamera` raises."""


class AravisMissing(RenderedCameraError, RuntimeError):
    """PyGObject's Aravis 0.8 or ``libaravis-0.8.so.0`` cannot be loaded."""


class CameraSettingsError(RenderedCameraError, ValueError):
    """A constructor argument is invalid (size, latency, clock offset, serial...)."""


class CameraStartError(RenderedCameraError, RuntimeError):
    """The simulated camera cannot start (its address has no interface, or its GVCP port is
    taken), or start() was called on a started or closed camera."""


class FrameError(RenderedCameraError, ValueError):
    """A frame the source returned cannot be sent (wrong shape or dtype, a capture instant
    not on ``time.monotonic()``...). The frame is skipped; the error is logged and kept in
    :attr:`RenderedGvCamera.last_error`."""


# -- the native side ------------------------------------------------------------------------

_FILL = ctypes.CFUNCTYPE(None, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_uint32,
                         ctypes.c_uint32, ctypes.c_uint32)


@dataclass(frozen=True)
class _Native:
    """PyGObject's Aravis module and the C functions called through ctypes."""

    aravis: Any
    lib: ctypes.CDLL
    gobject: ctypes.CDLL
    fake_camera_type: int


@functools.cache
def _load(library: str) -> _Native:
    """Aravis 0.8 through PyGObject, and ``library`` through ctypes with the prototypes used
    here; :class:`AravisMissing` naming what is missing. Cached once loaded."""
    try:
        import gi

        gi.require_version("Aravis", "0.8")
        from gi.repository import Aravis
    except (ImportError, ValueError) as exc:
        raise AravisMissing(f"PyGObject with Aravis 0.8 is not importable ({type(exc).__name__}: "
                            f"{exc}); install python3-gi / PyGObject and gir1.2-aravis-0.8") \
            from None
    try:
        lib = ctypes.CDLL(library)
        gobject = ctypes.CDLL(_LIBGOBJECT)
    except OSError as exc:
        raise AravisMissing(f"cannot load {library} or {_LIBGOBJECT} through ctypes: {exc} "
                            "(Debian package libaravis-0.8-0)") from None
    vp, u32, u64 = ctypes.c_void_p, ctypes.c_uint32, ctypes.c_uint64
    prototypes = {
        "arv_fake_camera_get_type": (ctypes.c_size_t, []),
        "arv_fake_camera_set_fill_pattern": (None, [vp, vp, vp]),
        "arv_fake_camera_read_register": (ctypes.c_int, [vp, u32, ctypes.POINTER(u32)]),
        "arv_buffer_get_data": (vp, [vp, ctypes.POINTER(ctypes.c_size_t)]),
        "arv_buffer_get_image_width": (ctypes.c_int, [vp]),
        "arv_buffer_get_image_height": (ctypes.c_int, [vp]),
        "arv_buffer_get_image_x": (ctypes.c_int, [vp]),
        "arv_buffer_get_image_y": (ctypes.c_int, [vp]),
        "arv_buffer_get_image_pixel_format": (u32, [vp]),
        "arv_buffer_set_timestamp": (None, [vp, u64]),
        "arv_buffer_set_frame_id": (None, [vp, u64]),
    }
    try:
        for name, (restype, argtypes) in prototypes.items():
            function = getattr(lib, name)
            function.restype, function.argtypes = restype, argtypes
        gobject.g_object_ref.restype, gobject.g_object_ref.argtypes = vp, [vp]
        gobject.g_object_unref.restype, gobject.g_object_unref.argtypes = None, [vp]
        gobject.g_type_check_instance_is_a.restype = ctypes.c_int
        gobject.g_type_check_instance_is_a.argtypes = [vp, ctypes.c_size_t]
    except AttributeError as exc:
        raise AravisMissing(f"{library} lacks a function this simulator needs: {exc}") from None
    return _Native(Aravis, lib, gobject, int(lib.arv_fake_camera_get_type()))


# PyCapsule_GetPointer with a prototype of our own (not set on ctypes.pythonapi's shared
# function object, which other code may use with its own).
_CAPSULE_POINTER = ctypes.PYFUNCTYPE(ctypes.c_void_p, ctypes.py_object, ctypes.c_char_p)(
    ("PyCapsule_GetPointer", ctypes.pythonapi))


def _gpointer(obj: Any) -> int:
    """The C pointer of a PyGObject wrapper (its ``__gpointer__`` capsule, unnamed)."""
    return int(_CAPSULE_POINTER(obj.__gpointer__, None) or 0)


# Cameras not closed yet: closed at interpreter exit, before the camera thread could call
# into a finalising interpreter.
_OPEN: weakref.WeakSet[RenderedGvCamera] = weakref.WeakSet()


@atexit.register
def _close_open_cameras() -> None:
    for camera in list(_OPEN):
        camera.close()


# -- frames ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Frame:
    """One rendered frame waiting to be sent."""

    image: np.ndarray  # (H, W) uint8, C-contiguous, our own copy
    capture: float  # s, time.monotonic()
    due: float  # s, time.monotonic(): not sent before
    device_ns: int  # the GVSP leader's timestamp, ns on the camera's clock


class RenderedGvCamera:
    """A GigE Vision camera on loopback that streams the images ``source`` renders.

    Args:
        source: called once per frame, from a thread of this camera; returns ``(image,
            capture)``: the (H, W) uint8 mono image (``size`` = (W, H)) and the instant it
            shows, s on the host's ``time.monotonic()`` clock (strictly increasing). An
            exception, or a result that breaks these rules (:class:`FrameError`), skips the
            frame: it is logged, counted in :attr:`frames_skipped`, kept in
            :attr:`last_error`, and streaming goes on.
        address: IPv4 address the camera binds (GVCP on UDP 3956); default: a fresh loopback
            address from :func:`oralnav.sim.peers.gige_fake.loopback_address` for the time
            the camera runs (``NoLoopbackAddress`` if none can be had).
        serial: serial number, 1-15 printable ASCII characters; default ``RX`` + 6 hex digits.
        size: ``(width, height)`` px of the sensor, and of the image before the driver sets a
            region; a region is cut out of the rendered image.
        latency_s: s from capture to the first packet leaving (exposure, readout, transfer):
            no frame leaves before ``capture + latency_s``; 0..1.
        clock_offset_s: the camera clock minus the host's ``time.monotonic()``, s: a frame's
            device timestamp is ``capture + clock_offset_s`` (ns in the GVSP leader).
        ptp: the camera's clock is PTP-synchronised to this host's, so its timestamps are
            TAI: ``capture + clock_offset_s + (CLOCK_TAI - CLOCK_MONOTONIC)`` (the offset
            is then the error of the camera's PTP timestamps).
        frame_rate: Hz, the camera's frame rate until a driver sets one (0.1..1000);
            default: the simulator's, 25 Hz.

    Use as a context manager, or ``start()`` ... ``close()``. ``close()`` is idempotent; the
    camera cannot be started again.

    Attributes:
        frames_sent: frames sent (each with a new block id).
        frames_skipped: source calls that gave no frame (raised, or :class:`FrameError`).
        blocks_resent: frame instants that repeated the previous block (no frame due).
        last_error: the last skipped frame's exception, or ``None``.
    """

    def __init__(self, source: Callable[[], tuple[np.ndarray, float]], *,
                 address: str | None = None, serial: str | None = None,
                 size: tuple[int, int] = (1920, 1200), latency_s: float = 0.0,
                 clock_offset_s: float = 0.0, frame_rate: float | None = None,
                 ptp: bool = False) -> None:
        if not callable(source):
            raise CameraSettingsError(f"source must be a callable returning (image, capture), "
                                      f"got {source!r}")
        if (not isinstance(size, tuple | list) or len(size) != 2
                or not all(isinstance(v, int | np.integer) and not isinstance(v, bool)
                           for v in size)
                or not all(1 <= v <= _MAX_SIDE for v in size)):
            raise CameraSettingsError(f"size must be (width, height) px, integers in "
                                      f"1..{_MAX_SIDE}, got {size!r}")
        if address is not None:
            try:
                address = str(ipaddress.IPv4Address(address.strip()))
            except (AttributeError, ValueError):
                # (Aravis would also take an interface name, binding its first address;
                # a driver needs the address itself.)
                raise CameraSettingsError(f"address must be an IPv4 address or None, got "
                                          f"{address!r}") from None
        if serial is None:
            serial = f"RX{random.randrange(16**6):06X}"
        if (not isinstance(serial, str) or not 1 <= len(serial) <= _SERIAL_LEN
                or not serial.isascii() or not serial.isprintable()):
            raise CameraSettingsError(f"serial must be 1..{_SERIAL_LEN} printable ASCII "
                                      f"characters, got {serial!r}")
        latency = _number(latency_s, "latency_s")
        if not 0.0 <= latency <= 1.0:
            raise CameraSettingsError(f"latency_s must be in 0..1 s, got {latency_s!r}")
        offset = _number(clock_offset_s, "clock_offset_s")
        if frame_rate is not None:
            rate = _number(frame_rate, "frame_rate")
            if not 0.1 <= rate <= 1000.0:
                raise CameraSettingsError(f"frame_rate must be in 0.1..1000 Hz, got "
                                          f"{frame_rate!r}")
            frame_rate = rate
        self.source = source
        self.serial = serial
        self.size = (int(size[0]), int(size[1]))
        self.latency_s = latency
        self.clock_offset_s = offset
        self.ptp = bool(ptp)
        self.frame_rate = frame_rate
        self._address = address

        self._cv = threading.Condition()  # guards everything down to _notices
        self._started = False
        self._closed = False
        self._stopping = False
        self._want = False  # a frame was asked of the renderer thread
        self._rendering = False
        self._ahead: deque[_Frame] = deque()  # rendered, not sent yet, oldest first
        self._notices: deque[str] = deque()  # from the camera thread, logged by ours
        self.frames_sent = 0
        self.frames_skipped = 0
        self.blocks_resent = 0
        self.last_error: BaseException | None = None
        # camera-thread state (touched by the callback only, and by close() once the
        # callback can no longer run)
        self._block_buffer: int | None = None  # ArvBuffer we hold a reference to
        self._block_id: int | None = None  # id and stamp of the frame that buffer holds
        self._block_ns = 0
        self._next_id = 1
        # renderer-thread state
        self._last_capture = -math.inf
        self._last_log = -math.inf
        self._quiet = 0  # failures not logged since the last warning
        self._instant: int | None = None  # the last frame instant rendered (period index)
        self._render_s = 0.0  # running mean of a render's duration, s
        self._capture_s = 0.0  # running mean of capture - the source's call, s
        self._late_s = 0.0  # running mean of how late a planned render starts, s
        self._planned_us: int | None = None  # when the render about to start was due

        self._native: _Native | None = None
        self._gv: Any = None
        self._fake: Any = None
        self._fake_ptr = 0
        self._fill_c: Any = None
        self._thread: threading.Thread | None = None
        self._stack = contextlib.ExitStack()

    # -- identity ---------------------------------------------------------------------------

    @property
    def address(self) -> str | None:
        """The camera's IPv4 address (``None`` before ``start()`` when none was given)."""
        return self._address

    @property
    def device_id(self) -> str:
        """The device id Aravis's discovery lists for this camera."""
        return f"Aravis-Fake-{self.serial}"

    @property
    def running(self) -> bool:
        """Started and not closed."""
        return self._started and not self._closed

    # -- lifecycle --------------------------------------------------------------------------

    def __enter__(self) -> RenderedGvCamera:
        self.start()
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def start(self) -> None:
        """Bind the camera's address and start answering GVCP. Raises
        :class:`AravisMissing`, :class:`CameraStartError`, or ``NoLoopbackAddress``."""
        with self._cv:
            if self._started or self._closed:
                raise CameraStartError(f"camera {self.serial}: start() called twice or after "
                                       "close() (build a new camera)")
            self._started = True
        try:
            self._start()
        except BaseException:
            self.close()
            raise

    def _start(self) -> None:
        native = self._native = _load(LIBARAVIS)
        aravis = native.aravis
        if self._address is None:
            self._address = self._stack.enter_context(loopback_address())
        # Aravis looks the interface up by address first, then by name ("lo" binds the
        # interface's first address, 127.0.0.1).
        gv = aravis.GvFakeCamera.new_full(self._address, self.serial, None)
        if not gv.is_running():
            del gv  # frees the sockets it did bind
            raise CameraStartError(f"camera {self.serial}: cannot serve GigE Vision on "
                                   f"{self._address} (no interface has that address, or its "
                                   "UDP port 3956 is taken)")
        self._gv = gv
        self._fake = fake = gv.get_fake_camera()
        pointer = _gpointer(fake)
        if not pointer or not native.gobject.g_type_check_instance_is_a(
                pointer, native.fake_camera_type):
            raise CameraStartError(f"camera {self.serial}: the FakeCamera's C pointer could "
                                   "not be had from PyGObject")
        self._fake_ptr = pointer
        width, height = self.size
        # A driver's region is checked against SensorWidth/SensorHeight (the GenICam file's
        # maxima for Width and Height); without a region it gets Width x Height.
        for register, value in ((aravis.FAKE_CAMERA_REGISTER_SENSOR_WIDTH, width),
                                (aravis.FAKE_CAMERA_REGISTER_SENSOR_HEIGHT, height),
                                (aravis.FAKE_CAMERA_REGISTER_WIDTH, width),
                                (aravis.FAKE_CAMERA_REGISTER_HEIGHT, height),
                                (aravis.FAKE_CAMERA_REGISTER_X_OFFSET, 0),
                                (aravis.FAKE_CAMERA_REGISTER_Y_OFFSET, 0)):
            fake.write_register(register, value)
        if self.frame_rate is not None:
            fake.write_register(aravis.FAKE_CAMERA_REGISTER_ACQUISITION_FRAME_PERIOD_US,
                                max(1, round(1e6 / self.frame_rate)))
        self._thread = threading.Thread(target=self._render_loop, daemon=True,
                                        name=f"gige-render-{self.serial}")
        self._thread.start()
        # No acquisition can have started yet (the driver needs GVCP, served from now on by
        # the camera thread): the callback is in place before the first frame.
        self._fill_c = _FILL(self._fill)
        native.lib.arv_fake_camera_set_fill_pattern(
            pointer, ctypes.cast(self._fill_c, ctypes.c_void_p), None)
        _OPEN.add(self)
        log.info("rendered GigE camera %s on %s: %dx%d, latency %.3f s, clock offset %.6f s",
                 self.device_id, self._address, width, height, self.latency_s,
                 self.clock_offset_s)

    def close(self) -> None:
        """Stop streaming, release the address; idempotent. A driver still streaming sees
        the camera vanish (no more frames, no GVCP answers)."""
        with self._cv:
            if self._closed:
                return
            self._closed = self._stopping = True
            self._cv.notify_all()  # a waiting callback returns, the renderer ends
        _OPEN.discard(self)
        native, fake = self._native, self._fake
        if fake is not None and native is not None:
            # No new frame starts once acquisition is off (the camera thread checks it before
            # each frame), so nothing is sent with the simulator's own test pattern after
            # the callback is unhooked; a driver still connected just stops receiving.
            fake.write_register(native.aravis.FAKE_CAMERA_REGISTER_ACQUISITION, 0)
            if self._fill_c is not None:
                # Takes the simulator's fill mutex: returns once a running callback has
                # returned, and the callback is never called again. ctypes releases the GIL
                # here, so that callback can finish.
                native.lib.arv_fake_camera_set_fill_pattern(self._fake_ptr, None, None)
        self._fake = None
        # The last reference: finalising the GvFakeCamera joins its thread and closes its
        # sockets (the GVCP port is free when this returns).
        self._gv = None
        if self._thread is not None:
            self._thread.join()
            self._flush_notices()
        if self._block_buffer is not None and native is not None:
            native.gobject.g_object_unref(self._block_buffer)
            self._block_buffer = None
        self._fill_c = None
        self._stack.close()

    # -- the renderer thread ----------------------------------------------------------------

    def _render_loop(self) -> None:
        """Render a frame at each of the camera's frame instants (free-running) or for each
        trigger the camera thread reports; log what that thread reports."""
        while True:
            job = self._await_job()
            if job is None:
                return
            self._flush_notices()
            if not job:
                continue
            frame: _Frame | None = None
            error: BaseException | None = None
            called = time.monotonic()
            if self._planned_us is not None:
                # How late this thread starts a render it planned (the GIL, a busy CPU).
                late = max(time.time_ns() // 1000 - self._planned_us, 0) * 1e-6
                self._late_s += _EMA * (late - self._late_s)
                self._planned_us = None
            try:
                frame = self._render()
            except Exception as exc:  # the source's own errors included: skip the frame
                error = exc
            else:
                # How long a render takes, and where in it the capture instant lies.
                self._render_s += _EMA * (time.monotonic() - called - self._render_s)
                self._capture_s += _EMA * (frame.capture - called - self._capture_s)
            with self._cv:
                self._rendering = False
                if frame is not None:
                    self._ahead.append(frame)
                else:
                    self.frames_skipped += 1
                    self.last_error = error
                self._cv.notify_all()
            if error is not None:
                self._log_skip(error)

    def _await_job(self) -> bool | None:
        """Wait until a frame is to be rendered (True), messages are to be logged (False),
        or the camera closes (None)."""
        aravis = self._native.aravis  # type: ignore[union-attr]
        with self._cv:
            while True:
                if self._stopping:
                    return None
                if self._notices:
                    return False
                # The camera thread writes these registers (GVCP) while we read them: each
                # is one aligned 32-bit word, read whole.
                acquiring = (self._register(aravis.FAKE_CAMERA_REGISTER_ACQUISITION) != 0
                             and self._register(_GVBS_CCP) != 0)
                if not acquiring:
                    # Stopped: frames rendered for that acquisition are stale.
                    self._ahead.clear()
                    self._instant = None
                    self._want = False
                    self._cv.wait(_POLL_S)
                    continue
                if self._register(aravis.FAKE_CAMERA_REGISTER_TRIGGER_MODE) == 1:
                    # Triggered: one frame per trigger, asked for by the camera thread.
                    if self._want:
                        self._want, self._rendering = False, True
                        return True
                    self._cv.wait(_POLL_S)
                    continue
                if self._instant is None and not self._want:
                    # Free-running, the first frame of an acquisition is rendered when the
                    # simulator first asks (it starts streaming up to 0.1 s after the
                    # acquisition does), so that its capture is not older than it must be.
                    self._cv.wait(_POLL_S)
                    continue
                self._want = False  # later frames follow the grid: a call only wakes us
                # The simulator sends at multiples of the frame period on the wall clock
                # (g_get_real_time, microseconds). Each frame is rendered `lead` earlier, so
                # that it is ready and due (capture + latency_s) when its send comes: the
                # first packet then leaves about latency_s after capture, as a camera's.
                period_us = self._register(
                    aravis.FAKE_CAMERA_REGISTER_ACQUISITION_FRAME_PERIOD_US) or 1_000_000
                lead_us = round(1e6 * (max(self._render_s, self.latency_s + self._capture_s)
                                       + _LEAD_MARGIN_S + 2 * self._late_s))
                now_us = time.time_ns() // 1000
                instant = (now_us + lead_us) // period_us
                if self._instant is None:
                    # At once, for the instant the simulator is sending at.
                    instant, planned = now_us // period_us, None
                elif instant > self._instant:
                    planned = instant * period_us - lead_us
                else:
                    self._cv.wait(min(((instant + 1) * period_us - lead_us - now_us) * 1e-6,
                                      _POLL_S))
                    continue
                self._instant = instant
                # At most as many frames waiting as the lead spans: one more means a send
                # came late; this instant is skipped so that sending catches up instead of
                # every later frame going out one period late.
                if len(self._ahead) >= max(1, -(-lead_us // period_us)):
                    continue
                self._planned_us, self._rendering = planned, True
                return True

    def _render(self) -> _Frame:
        result = self.source()
        if not isinstance(result, tuple) or len(result) != 2:
            raise FrameError(f"camera {self.serial}: the source must return (image, capture), "
                             f"got {type(result).__name__}")
        image, capture = result
        width, height = self.size
        if not isinstance(image, np.ndarray) or image.dtype != np.uint8 \
                or image.shape != (height, width):
            what = (f"{image.dtype} {image.shape}" if isinstance(image, np.ndarray)
                    else type(image).__name__)
            raise FrameError(f"camera {self.serial}: the source's image must be uint8 of shape "
                             f"{(height, width)} (mono8, size {width}x{height}), got {what}")
        if isinstance(capture, bool) or not isinstance(capture, int | float) \
                or not math.isfinite(capture):
            raise FrameError(f"camera {self.serial}: the capture instant must be a finite "
                             f"number (s, time.monotonic()), got {capture!r}")
        capture = float(capture)
        now = time.monotonic()
        if not now - _PAST_S <= capture <= now + _FUTURE_S:
            raise FrameError(f"camera {self.serial}: capture {capture:.6f} s is "
                             f"{capture - now:+.3f} s from time.monotonic(); it must be on "
                             "that clock and not in the future")
        if capture <= self._last_capture:
            raise FrameError(f"camera {self.serial}: capture {capture:.6f} s is not after the "
                             f"previous frame's {self._last_capture:.6f} s")
        device = capture + self.clock_offset_s
        if self.ptp:  # a camera synchronised to this host by PTP stamps TAI
            device += tai_minus_monotonic()
        device_ns = round(device * 1e9)
        if not 0 <= device_ns < 2**64:
            raise FrameError(f"camera {self.serial}: capture + clock_offset_s = "
                             f"{capture + self.clock_offset_s:.6f} s is not a valid camera "
                             "timestamp (must be >= 0)")
        self._last_capture = capture
        # Our own copy: the source may reuse its array for the next frame while this one
        # waits to be sent.
        frame = np.array(image, dtype=np.uint8, order="C", copy=True)
        return _Frame(frame, capture, capture + self.latency_s, device_ns)

    def _log_skip(self, error: BaseException) -> None:
        now = time.monotonic()
        if now - self._last_log < _LOG_EVERY_S:
            self._quiet += 1
            log.debug("camera %s: frame skipped: %s", self.serial, error)
            return
        more = f" ({self._quiet} more since the last warning)" if self._quiet else ""
        self._last_log, self._quiet = now, 0
        log.warning("camera %s: frame skipped%s: %s", self.serial, more, error,
                    exc_info=None if isinstance(error, FrameError) else error)

    def _flush_notices(self) -> None:
        with self._cv:
            notices, self._notices = list(self._notices), deque()
        for notice in notices:
            log.warning("camera %s: %s", self.serial, notice)

    # -- the camera thread ------------------------------------------------------------------
    # Called by Aravis's camera thread for every frame it sends. Nothing here may raise into
    # ctypes, log, or touch PyGObject (see the module docs).

    def _fill(self, buffer: int, _data: int, _exposure_us: int, _gain: int,
              _pixel_format: int) -> None:
        try:
            self._fill_buffer(buffer)
        except BaseException:  # a bug here: report it, send the last frame again
            self._notice(f"frame callback failed:\n{traceback.format_exc()}")
            self._repeat(buffer)

    def _fill_buffer(self, buffer: int) -> None:
        native = self._native
        assert native is not None
        lib = native.lib
        if buffer != self._block_buffer:
            # A new buffer: the simulator made one for a new acquisition (and a new receiver,
            # which takes whatever comes first as a frame). Hold a reference so that its
            # address cannot be reused while we compare with it.
            native.gobject.g_object_ref(buffer)
            if self._block_buffer is not None:
                native.gobject.g_object_unref(self._block_buffer)
            self._block_buffer, self._block_id = buffer, None
        pixel_format = int(lib.arv_buffer_get_image_pixel_format(buffer))
        if pixel_format not in (_MONO8, _MONO16, _RGB8, *_BAYER8):
            self._notice(f"pixel format 0x{pixel_format:08x} cannot be rendered (Mono8, "
                         "Mono16, RGB8, Bayer*8 can); frame not sent")
            self._repeat(buffer)
            return
        frame = self._next_frame(first=self._block_id is None)
        if frame is None:
            self._repeat(buffer)
            return
        self._write(buffer, frame.image, pixel_format)
        # Copied first, then held until due: the copy's time counts towards the latency.
        wait = frame.due + _DUE_MARGIN_S - time.monotonic()
        if wait > 0:
            time.sleep(wait)
        block_id, self._next_id = self._next_id, self._next_id % _MAX_BLOCK_ID + 1
        lib.arv_buffer_set_frame_id(buffer, block_id)
        lib.arv_buffer_set_timestamp(buffer, frame.device_ns)
        self._block_id, self._block_ns = block_id, frame.device_ns
        with self._cv:
            self.frames_sent += 1

    def _next_frame(self, first: bool) -> _Frame | None:
        """The frame to send now, or ``None`` (none due within MAX_BLOCK_S: repeat the last
        one). ``first``: nothing to repeat, so wait for a frame however long it takes."""
        deadline = time.monotonic() + MAX_BLOCK_S
        with self._cv:
            while not self._stopping:
                if self._ahead:
                    head = self._ahead[0]
                    if first or head.due <= deadline:
                        return self._ahead.popleft()
                    return None  # due later: a later frame instant sends it
                if not (self._want or self._rendering):
                    # Ask for a frame: a trigger's, or a wake-up for the renderer to notice
                    # that acquisition has started.
                    self._want = True
                    self._cv.notify_all()
                left = deadline - time.monotonic()
                if left <= 0:
                    if not first:
                        return None
                    deadline = time.monotonic() + MAX_BLOCK_S
                    self._want = False  # ask again: that render failed, or never came
                    continue
                self._cv.wait(left)
        return None

    def _register(self, address: int) -> int:
        assert self._native is not None
        value = ctypes.c_uint32()
        self._native.lib.arv_fake_camera_read_register(self._fake_ptr, address,
                                                       ctypes.byref(value))
        return int(value.value)

    def _write(self, buffer: int, image: np.ndarray, pixel_format: int) -> None:
        """The region the buffer describes, cut from ``image``, into the buffer's memory in
        its pixel format. Writes exactly width x height x bytes-per-pixel bytes: the size
        the simulator checked against the buffer's allocation before calling us."""
        lib = self._native.lib  # type: ignore[union-attr]
        width = int(lib.arv_buffer_get_image_width(buffer))
        height = int(lib.arv_buffer_get_image_height(buffer))
        x = int(lib.arv_buffer_get_image_x(buffer))
        y = int(lib.arv_buffer_get_image_y(buffer))
        bits = (pixel_format >> 16) & 0xFF
        nbytes = width * height * bits // 8
        data = lib.arv_buffer_get_data(buffer, None)
        if not data or nbytes <= 0:
            return
        memory = np.ctypeslib.as_array((ctypes.c_uint8 * nbytes).from_address(data))
        crop = image[y:y + height, x:x + width]
        if crop.shape != (height, width):  # the region reaches past the sensor: black there
            memory[:] = 0
        if pixel_format == _MONO16:
            out = memory.view("<u2").reshape(height, width)
            out[:crop.shape[0], :crop.shape[1]] = crop.astype("<u2") << 8
        elif pixel_format == _RGB8:
            out = memory.reshape(height, width, 3)
            out[:crop.shape[0], :crop.shape[1]] = crop[..., None]
        else:  # Mono8, and the Bayer mosaics of a grey scene
            out = memory.reshape(height, width)
            out[:crop.shape[0], :crop.shape[1]] = crop
        del out, memory  # no view of the simulator's memory outlives this call

    def _repeat(self, buffer: int) -> None:
        """Make the buffer a repeat of the last frame sent from it (same bytes, id and
        stamp), which the receiver drops; without one, the buffer goes out as it is."""
        if self._block_id is None or buffer != self._block_buffer:
            return
        lib = self._native.lib  # type: ignore[union-attr]
        lib.arv_buffer_set_frame_id(buffer, self._block_id)
        lib.arv_buffer_set_timestamp(buffer, self._block_ns)
        with self._cv:
            self.blocks_resent += 1

    def _notice(self, message: str) -> None:
        with self._cv:
            self._notices.append(message)
            self._cv.notify_all()


def _number(value: object, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise CameraSettingsError(f"{what} must be a finite number, got {value!r}")
    return float(value)
