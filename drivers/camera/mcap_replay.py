"""MCAP replay backend: the camera images of an MCAP file played as cameras.

An MCAP file (https://mcap.dev) holds messages on topics; the images this backend plays
are Foxglove's well-known schemas, ``foxglove.RawImage`` (``mono8``, ``bgr8``, ``rgb8``)
or ``foxglove.CompressedImage`` (``png``, ``jpeg``, anything OpenCV decodes), Protobuf
encoded: what ``oralnavd --record`` writes (docs/recording.md), and what Foxglove and ROS
tools export.

- :class:`McapRig` plays several cameras in step: each ``read()`` returns one round,
  ``{camera: CameraFrame}``, made of the images that share one message ``sequence``
  number (the recorder numbers each source's tracked rounds so). A round missing one of
  the cameras' images is skipped and counted (:attr:`McapRig.incomplete`).
- :class:`McapCamera` (backend ``"mcap"``) plays one image topic.

Frames come in file order, as fast as they decode (a worker thread, never the event loop);
each is stamped with its image's ``timestamp`` (s; the message's log time when the image
has none), and counted from 0. A file that ends early (a recording cut short by a crash or
a full disk: the last chunk is incomplete) plays up to the last complete chunk, then ends
with :class:`EndOfStream` like a complete one; :attr:`McapRig.truncated` says what was
wrong. A file that is not MCAP is refused at ``start()`` (:class:`DriverInitError`).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import anyio
import anyio.to_thread
import cv2
import numpy as np
from mcap.exceptions import InvalidMagic
from mcap.records import Channel, Footer, Message, Schema
from mcap.stream_reader import StreamReader

from ..errors import DriverInitError, DriverIOError, EndOfStream
from ..lifecycle import LifecycleState
from .base import Camera, CameraFrame, FrameStream

__all__ = ["IMAGE_SCHEMAS", "McapCamera", "McapRig"]

log = logging.getLogger(__name__)

#: The image schemas this backend decodes (Protobuf encoded).
IMAGE_SCHEMAS = frozenset({"foxglove.RawImage", "foxglove.CompressedImage"})
#: RawImage encodings and their channel counts.
_RAW_CHANNELS = {"mono8": 1, "8UC1": 1, "bgr8": 3, "rgb8": 3}


class _Images:
    """Blocking, sequential access to the image messages of some topics; one worker
    thread at a time. ``topics``: topic -> camera name."""

    def __init__(self, path: Path, topics: Mapping[str, str], mono: bool) -> None:
        self.path = path
        self.topics = dict(topics)
        self.mono = mono
        self.truncated: str | None = None
        self.incomplete = 0
        self._file: Any = None
        self._records: Iterator[Any] | None = None
        self._schemas: dict[int, Schema] = {}
        self._channels: dict[int, tuple[str, str]] = {}  # channel id -> (camera, schema)
        self._pending: tuple[int, str, str, Message] | None = None
        self._done = False

    def open(self) -> None:
        try:
            self._file = open(self.path, "rb")  # noqa: SIM115 - closed by close()
        except OSError as exc:
            raise DriverInitError(f"{self.path}: cannot open ({exc.strerror or exc})") from None
        self._records = StreamReader(self._file).records
        try:
            next(self._records)  # the magic and the header
        except (InvalidMagic, StopIteration) as exc:
            self.close()
            raise DriverInitError(f"{self.path}: not an MCAP file ({exc})") from None
        except Exception as exc:  # a file shorter than its magic and header
            self.close()
            raise DriverInitError(f"{self.path}: not an MCAP file (it ends before its "
                                  f"header: {type(exc).__name__}: {exc})") from None

    def close(self) -> None:
        f, self._file = self._file, None
        self._records = None
        if f is not None:
            f.close()

    def _message(self) -> tuple[int, str, str, Message] | None:
        """The next image message of our topics: (sequence, camera, schema, message);
        None at the end of the file or where it stops being readable."""
        if self._done or self._records is None:
            return None
        while True:
            try:
                rec = next(self._records)
            except StopIteration:
                self._done = True
                return None
            except Exception as exc:  # a cut chunk, a bad CRC, a torn record: stop here
                self._done = True
                self.truncated = f"{type(exc).__name__}: {exc}" if str(exc) else \
                    type(exc).__name__
                log.warning("%s: unreadable from here on (%s): the frames before it are "
                            "played", self.path, self.truncated)
                return None
            if isinstance(rec, Schema):
                self._schemas[rec.id] = rec
            elif isinstance(rec, Channel):
                schema = self._schemas.get(rec.schema_id)
                if rec.topic in self.topics and schema is not None \
                        and schema.name in IMAGE_SCHEMAS:
                    self._channels[rec.id] = (self.topics[rec.topic], schema.name)
            elif isinstance(rec, Message):
                known = self._channels.get(rec.channel_id)
                if known is not None:
                    return rec.sequence, known[0], known[1], rec
            elif isinstance(rec, Footer):
                self._done = True
                return None

    def next_round(self) -> tuple[int, dict[str, tuple[np.ndarray, float]]] | None:
        """The next round holding every camera's image: (sequence, {camera: (image,
        timestamp s)}), decoded; None at the end."""
        group: dict[str, tuple[str, Message]] = {}
        seq = None
        while True:
            item, self._pending = self._pending or self._message(), None
            if item is None:
                if group:
                    self.incomplete += 1
                return None
            s, camera, schema, msg = item
            if group and (s != seq or camera in group):  # the next round began
                self._pending = item
                self.incomplete += 1
                group = {}
                continue
            seq = s
            group[camera] = (schema, msg)
            if len(group) == len(set(self.topics.values())):
                return s, {cam: self._decode(cam, schema, msg)
                           for cam, (schema, msg) in group.items()}

    def _decode(self, camera: str, schema: str, msg: Message) -> tuple[np.ndarray, float]:
        # the generated Foxglove classes: imported here, so that the registry's other
        # backends never load protobuf
        from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
        from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

        where = f"{self.path}: camera {camera!r} image at log time {msg.log_time} ns"
        try:
            if schema == "foxglove.RawImage":
                raw = RawImage.FromString(msg.data)
                image = self._raw(raw, where)
                stamp = raw.timestamp
            else:
                comp = CompressedImage.FromString(msg.data)
                flags = cv2.IMREAD_GRAYSCALE if self.mono else cv2.IMREAD_COLOR
                image = cv2.imdecode(np.frombuffer(comp.data, np.uint8), flags)
                if image is None:
                    raise DriverIOError(f"{where}: cannot decode its {comp.format!r} data")
                stamp = comp.timestamp
        except DriverIOError:
            raise
        except Exception as exc:  # a message that does not parse as its schema
            raise DriverIOError(f"{where}: not a valid {schema}: {exc}") from None
        t = stamp.seconds + stamp.nanos * 1e-9 if stamp.seconds or stamp.nanos \
            else msg.log_time * 1e-9
        return image, t

    def _raw(self, raw: Any, where: str) -> np.ndarray:
        channels = _RAW_CHANNELS.get(raw.encoding)
        if channels is None:
            raise DriverIOError(f"{where}: RawImage encoding {raw.encoding!r} is not one of "
                                f"{', '.join(sorted(_RAW_CHANNELS))}")
        w, h = int(raw.width), int(raw.height)
        step = int(raw.step) or w * channels
        if w <= 0 or h <= 0 or step < w * channels or len(raw.data) < step * h:
            raise DriverIOError(f"{where}: {len(raw.data)} bytes do not hold a {w}x{h} "
                                f"{raw.encoding} image of step {step}")
        rows = np.frombuffer(raw.data, np.uint8, count=step * h).reshape(h, step)
        image = rows[:, :w * channels].reshape((h, w, channels) if channels > 1 else (h, w))
        if raw.encoding == "rgb8":
            image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
        if channels == 3 and self.mono:
            image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        elif channels == 1 and not self.mono:
            image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
        # a writable copy of its own: the frame outlives the message's bytes
        return np.ascontiguousarray(image) if image.flags.writeable else image.copy()


class McapRig(FrameStream[dict[str, CameraFrame]]):
    """Several cameras of an MCAP file played in step; see the module docstring.

    Args:
        path: the MCAP file.
        cameras: camera name -> the topic of its images.
        mono: deliver mono8 (H, W) uint8 images; ``False`` delivers BGR (H, W, 3) uint8.

    After ``start()`` (which decodes the first round): :attr:`sizes` (camera -> (width,
    height)); after each ``read()``: :attr:`sequence`, the round's message sequence number.
    """

    def __init__(self, path: str | os.PathLike[str], cameras: Mapping[str, str], *,
                 mono: bool = True) -> None:
        try:
            self.path = Path(path)
        except TypeError:
            raise DriverInitError(f"MCAP replay path must be a path, got {path!r}") from None
        if not cameras:
            raise DriverInitError(f"{self.path}: an MCAP replay needs at least one camera")
        topics = {str(t): str(n) for n, t in cameras.items()}
        if len(topics) != len(cameras):
            raise DriverInitError(f"{self.path}: two cameras share one topic: {dict(cameras)}")
        self.cameras = dict(cameras)
        self.name = "+".join(self.cameras)
        self._images = _Images(self.path, topics, bool(mono))
        self._life = LifecycleState()
        self._lock: anyio.Lock | None = None
        self._first: tuple[int, dict[str, tuple[np.ndarray, float]]] | None = None
        self._counter = 0
        self.sequence: int | None = None
        self.sizes: dict[str, tuple[int, int]] = {}

    @property
    def truncated(self) -> str | None:
        """What made the file unreadable from some point on (a cut chunk, a bad record),
        once the replay got there; None while everything read was whole."""
        return self._images.truncated

    @property
    def incomplete(self) -> int:
        """Rounds skipped so far because one of the cameras' images was missing."""
        return self._images.incomplete

    async def start(self) -> None:
        self._life.begin_start(f"MCAP replay {self.name!r}: start() called twice or after "
                               "close()")
        self._lock = anyio.Lock()
        images = self._images
        try:
            await anyio.to_thread.run_sync(images.open)
            first = await anyio.to_thread.run_sync(images.next_round)
        except BaseException:
            images.close()
            raise
        if first is None:
            images.close()
            why = f" (unreadable: {images.truncated})" if images.truncated else ""
            raise DriverInitError(f"{self.path}: no round with an image of every camera "
                                  f"({', '.join(f'{n} on {t}' for n, t in self.cameras.items())})"
                                  f"{why}")
        self._first = first
        self.sizes = {cam: (img.shape[1], img.shape[0]) for cam, (img, _) in first[1].items()}
        if not self._life.finish_start():
            images.close()

    async def read(self) -> dict[str, CameraFrame]:
        if not self._life.running:
            self._life.check(f"MCAP replay {self.name!r}")
        assert self._lock is not None
        async with self._lock:
            first, self._first = self._first, None
            got = first if first is not None else \
                await anyio.to_thread.run_sync(self._images.next_round)
            if not self._life.running:
                self._life.check(f"MCAP replay {self.name!r}", during="read()")
            if got is None:
                more = f", unreadable after that: {self.truncated}" if self.truncated else ""
                raise EndOfStream(f"MCAP replay {self.name!r}: end of {self.path}{more}")
            seq, decoded = got
            self.sequence = seq
            out = {cam: CameraFrame(image=decoded[cam][0], timestamp=decoded[cam][1],
                                    counter=self._counter, camera=cam)
                   for cam in self.cameras}
            self._counter += 1
            return out

    async def close(self) -> None:
        if not self._life.close():
            return
        self._first = None
        if self._lock is None:
            return
        # shielded: a cancelled caller still releases the file, after any decode under way
        with anyio.CancelScope(shield=True):
            async with self._lock:
                self._images.close()


class McapCamera(Camera):
    """One image topic of an MCAP file played as a camera (backend ``"mcap"``).

    Args:
        path: the MCAP file.
        topic: the topic of its images (``oralnavd --record`` writes
            ``/cameras/<camera>/image``).
        name: the camera name put in every frame; default: the topic.
        mono: deliver mono8 (H, W) uint8 images; ``False`` delivers BGR (H, W, 3) uint8.
    """

    def __init__(self, path: str | os.PathLike[str], topic: str, *, name: str | None = None,
                 mono: bool = True) -> None:
        if not isinstance(topic, str) or not topic:
            raise DriverInitError(f"MCAP camera: topic must be a non-empty string, got "
                                  f"{topic!r}")
        super().__init__(topic if name is None else name)
        self.topic = topic
        self._rig = McapRig(path, {self.name: topic}, mono=mono)

    @property
    def truncated(self) -> str | None:
        """See :attr:`McapRig.truncated`."""
        return self._rig.truncated

    async def start(self) -> None:
        await self._rig.start()
        self._size = self._rig.sizes[self.name]

    async def read(self) -> CameraFrame:
        return (await self._rig.read())[self.name]

    async def close(self) -> None:
        await self._rig.close()

    def __repr__(self) -> str:
        return f"McapCamera({os.fspath(self._rig.path)!r}, topic={self.topic!r})"
