"""The console's live views: the newest frame of every camera the daemon reads, with the
marker fields tracked in it, as downscaled JPEG and overlay geometry.

:meth:`LiveViews.tap` is a tap of the capture pipeline (``daemon/capture_task.py``): it
only keeps a reference to each round's frames and estimates (a dict update on the event
loop), so a console never costs tracking anything on the tracking path. The work happens
when a console asks (a telemetry client subscribed to ``frames``, or
``GET /views/{camera}/image``): one frame is downscaled and encoded in a worker thread, at
most :attr:`LiveViews.max_hz` times a second per camera whatever the number of consoles or
their rate (a request in between gets the previous JPEG again), and one encode at a time,
so the views' share of the CPU is bounded (docs/console.md gives the measured cost).

Overlays are in the frame's own pixels (x right, y down, the top-left pixel's centre at
(0, 0)): for each field found in that camera, the convex hull of its inlier corners and
its origin's axes (``AXIS_M`` long, projected from the estimated pose through the rig's
camera model). The browser scales them to the size it shows.

A frame pushed over the telemetry websocket is one binary message
(:meth:`LiveViews.frame_message`): a 4-byte big-endian header length ``n``, ``n`` bytes
of UTF-8 JSON (``camera``, ``counter``, ``stamp`` (s, capture instant), ``width`` and
``height`` (px of the full frame: the overlay's pixels) and ``fields`` (the overlay)),
then the JPEG. The header travels with its own image, so an overlay is always drawn on
the frame it was found in.
"""

from __future__ import annotations

import json
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import anyio
import cv2
import numpy as np

from oralnav.control.geometry import invert

__all__ = ["AXIS_M", "LiveViews", "NoFrame"]

#: Length (m) of the field axes drawn over the views.
AXIS_M = 0.01
#: The widths (px) a client may ask for; the frame is never upscaled.
MIN_WIDTH, MAX_WIDTH = 64, 1920
#: JPEG quality bounds (OpenCV's scale, 0-100).
MIN_QUALITY, MAX_QUALITY = 10, 95
#: JPEG sizes kept per camera (consoles of different window sizes)
MAX_SIZES = 4


class NoFrame(LookupError):
    """The camera is unknown, or has delivered no frame yet; the message says which."""


@dataclass(frozen=True)
class _Latest:
    """One camera's newest frame and what the round found in it."""

    frame: Any                      # CameraFrame (image, timestamp, counter, camera)
    source: str                     # the pipeline source it came from
    arrived: float                  # s, the daemon's monotonic clock
    # (field name, estimate, the camera's model) for each field found in this camera
    found: tuple[tuple[str, Any, Any], ...]

    @cached_property
    def fields(self) -> list[dict[str, Any]]:
        """The overlay (:meth:`LiveViews.overlay`), worked out once per frame whatever the
        number of consoles."""
        return _overlay(self.found)


@dataclass
class _Encoded:
    camera: str
    latest: _Latest                 # the frame it was made of
    width: int
    quality: int
    at: float                       # s, monotonic: when it was encoded
    jpeg: bytes
    _message: bytes | None = None

    @property
    def counter(self) -> int:
        return int(self.latest.frame.counter)

    @property
    def stamp(self) -> float:
        """The frame's capture instant (s)."""
        return float(self.latest.frame.timestamp)

    @property
    def message(self) -> bytes:
        """This JPEG as a telemetry frame message (module docstring), made once."""
        if self._message is None:
            h, w = self.latest.frame.image.shape[:2]
            head = json.dumps({"camera": self.camera, "counter": self.counter,
                               "stamp": self.stamp, "width": int(w), "height": int(h),
                               "fields": self.latest.fields}).encode()
            self._message = struct.pack(">I", len(head)) + head + self.jpeg
        return self._message


class LiveViews:
    """See the module docstring. ``max_hz``: the most JPEGs encoded per camera and second
    (``[api] views_max_hz``); ``clock``: the daemon's monotonic clock (s)."""

    def __init__(self, max_hz: float = 10.0, clock: Callable[[], float] = time.monotonic
                 ) -> None:
        if not 0 < max_hz <= 60:
            raise ValueError(f"views max_hz must be in (0, 60] Hz, got {max_hz}")
        self.max_hz = float(max_hz)
        self.clock = clock
        self._latest: dict[str, _Latest] = {}
        #: camera -> (width, quality) -> the last JPEG made at that size
        self._cache: dict[str, dict[tuple[int, int], _Encoded]] = {}
        self._encode_lock = threading.Lock()  # one encode at a time, across consoles
        #: JPEGs encoded so far (the rate bound is checked on it)
        self.encodes = 0
        #: rounds tapped so far (:meth:`wait_newer` waits for it to move)
        self.generation = 0
        self._new: anyio.Event | None = None  # set by the next tap

    # -- the pipeline's side (event loop, must not block) -----------------------------------
    def tap(self, rnd: Any) -> None:
        """Keep ``rnd``'s frames (a ``CapturedRound``) as each camera's newest."""
        now = self.clock()
        found: dict[str, list[tuple[str, Any, Any]]] = {}
        for view, _stamp, ests in rnd.views:
            rig = view.tracker.rig
            for fname, est in ests.items():
                for cam in getattr(est, "per_camera", {}):
                    if cam in rig.names:
                        found.setdefault(cam, []).append((fname, est, rig[cam]))
        for cam, frame in rnd.frames.items():
            self._latest[cam] = _Latest(frame, rnd.source, now, tuple(found.get(cam, ())))
        self.generation += 1
        new, self._new = self._new, None
        if new is not None:
            new.set()

    async def wait_newer(self, seen: int) -> int:
        """Wait until a round after generation ``seen`` was tapped; returns the newest
        generation (at once if it has already moved). On the event loop."""
        while self.generation == seen:
            if self._new is None:
                self._new = anyio.Event()
            await self._new.wait()
        return self.generation

    # -- the console's side ---------------------------------------------------------------
    def cameras(self) -> list[dict[str, Any]]:
        """Each camera with a frame, in the order they first came (the sources' own: the
        stereo pair before the endoscope on the simulated cell): name, size (px), frame
        counter, capture instant and age (s), and the overlay of the fields found in it
        (:meth:`overlay`)."""
        now = self.clock()
        out = []
        for cam, latest in list(self._latest.items()):  # the order the cameras came in
            h, w = latest.frame.image.shape[:2]
            out.append({"name": cam, "source": latest.source, "width": int(w),
                        "height": int(h), "counter": int(latest.frame.counter),
                        "stamp": float(latest.frame.timestamp),
                        "age_s": now - latest.arrived, "fields": latest.fields})
        return out

    def counters(self) -> dict[str, int]:
        """Each camera's newest frame counter (cheap: whether anything is new)."""
        return {cam: int(latest.frame.counter) for cam, latest in self._latest.items()}

    def overlay(self, camera: str) -> list[dict[str, Any]]:
        """The fields found in ``camera``'s newest frame: ``name``, ``corners`` (inliers
        in this camera), ``hull`` (px polygon) and ``axes`` (px: origin, x, y, z tips)."""
        return self._get(camera).fields

    def jpeg(self, camera: str, width: int = 640, quality: int = 70
             ) -> tuple[bytes, int, float]:
        """``camera``'s newest frame as JPEG, at least ``width`` px wide (less than a
        whole downscale factor more; the frame's own width at most; aspect kept),
        and its frame counter and capture instant (s). Blocking (resize and encode): call
        it in a worker thread. A JPEG of that frame at that size and quality is encoded
        once; within ``1 / max_hz`` s of this camera's last encode, at any size, the
        newest JPEG already made of it is returned instead (perhaps of another size: the
        browser scales it), so consoles of several sizes cannot multiply the encodes.
        Raises :class:`NoFrame` and ``ValueError`` (width or quality out of bounds)."""
        enc = self._encoded(camera, width, quality)
        return enc.jpeg, enc.counter, enc.stamp

    def frame_message(self, camera: str, width: int = 640, quality: int = 70
                      ) -> tuple[bytes, int]:
        """:meth:`jpeg` as one binary telemetry message (module docstring) with its
        header, and the counter of the frame it holds (an earlier one than the newest
        within ``1 / max_hz`` s of the last encode). Blocking: in a worker thread."""
        enc = self._encoded(camera, width, quality)
        return enc.message, enc.counter

    def _encoded(self, camera: str, width: int, quality: int) -> _Encoded:
        if not MIN_WIDTH <= width <= MAX_WIDTH:
            raise ValueError(f"width must be {MIN_WIDTH}..{MAX_WIDTH} px, got {width}")
        if not MIN_QUALITY <= quality <= MAX_QUALITY:
            raise ValueError(f"quality must be {MIN_QUALITY}..{MAX_QUALITY}, got {quality}")
        self._get(camera)  # NoFrame before waiting for the lock
        with self._encode_lock:
            now = time.monotonic()
            latest = self._get(camera)
            made = self._cache.setdefault(camera, {})
            same = made.get((width, quality))
            if same is not None and same.latest is latest:
                return same
            newest = max(made.values(), key=lambda e: e.at, default=None)
            if newest is not None and now - newest.at < 1.0 / self.max_hz:
                return newest
            data = _encode(latest.frame.image, width, quality)
            self.encodes += 1
            enc = _Encoded(camera, latest, width, quality, time.monotonic(), data)
            made[(width, quality)] = enc
            if len(made) > MAX_SIZES:  # the sizes no console asked for lately go
                del made[min(made, key=lambda k: made[k].at)]
            return enc

    # -- internals ------------------------------------------------------------------------
    def _get(self, camera: str) -> _Latest:
        latest = self._latest.get(camera)
        if latest is None:
            known = ", ".join(sorted(self._latest)) or "none yet"
            raise NoFrame(f"no frame from camera {camera!r} (cameras with frames: {known})")
        return latest


def _overlay(found: tuple[tuple[str, Any, Any], ...]) -> list[dict[str, Any]]:
    """The overlay of the fields ``found`` in one frame (``_Latest.found``)."""
    out = []
    for fname, est, model in found:
        _rows, px = est.per_camera[model.name]
        px = np.asarray(px, dtype=np.float32).reshape(-1, 2)
        hull = cv2.convexHull(px).reshape(-1, 2) if len(px) >= 3 else px
        T_cam_field = invert(np.asarray(model.T_ref_cam)) @ np.asarray(est.T_ref_field)
        tips = model.project_from(T_cam_field, np.vstack([np.zeros(3), AXIS_M * np.eye(3)]))
        axes = None if not np.all(np.isfinite(tips)) else np.round(tips, 1).tolist()
        out.append({"name": fname, "corners": len(px),
                    "hull": np.round(hull.astype(float), 1).tolist(), "axes": axes})
    return out


def _encode(image: np.ndarray, width: int, quality: int) -> bytes:
    """``image`` (mono8 or BGR) downscaled by the largest whole factor that keeps it at
    least ``width`` px wide, as JPEG bytes. A whole factor is OpenCV's fast area-averaging
    path (1920 -> 640 px: 1.4 ms; to 448 px, a factor of 4.3, it took 3.1 ms on the
    development VM), and the browser scales the few pixels more itself."""
    h, w = image.shape[:2]
    k = max(1, w // width)
    if k > 1:  # INTER_AREA: the anti-aliased downscale (no moire on the fields)
        image = cv2.resize(image, (w // k, h // k), interpolation=cv2.INTER_AREA)
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:  # pragma: no cover - OpenCV encodes any 8-bit image
        raise RuntimeError("JPEG encoding failed")
    return buf.tobytes()
