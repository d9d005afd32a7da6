"""What a session recording holds, message by message: its topics, schemas, metadata and
attachments, and the pure helpers that build each message (docs/recording.md).

No I/O here: the recorder (``daemon/recording.py``) calls these in its writer thread and
writes what they return; the replay (``cli/replay.py``) reads with the same names. The
Foxglove messages are the generated Protobuf classes of ``foxglove-schemas-protobuf``;
the JSON channels carry plain objects whose floats are written with the digits that
round-trip them (Python's ``repr``), so a pose read back is the pose published, bit for bit.

Times: every ``log_time`` and Foxglove ``timestamp`` is the daemon's monotonic clock in
integer nanoseconds (the capture instant of a frame or pose, the instant of an event);
metadata ``oralnav.clock`` gives the offset that maps it to UTC.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Mapping, Sequence
from typing import Any

import cv2
import numpy as np
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from google.protobuf.timestamp_pb2 import Timestamp
from scipy.spatial.transform import Rotation

from oralnav.config.fields import fields_to_files
from oralnav.config.loader import dump_toml
from oralnav.config.rig import rig_to_dict
from oralnav.control.vision.detection import QuadParams
from oralnav.control.vision.tracker import TrackerSettings

# -- topics -------------------------------------------------------------------------------
#: JSON: one record per tracked round (the poses found, bit-exact; which frames were kept)
ROUNDS_TOPIC = "/oralnav/rounds"
#: JSON: the safety state machine's transitions
SAFETY_TOPIC = "/oralnav/safety"
#: JSON: each operator command (POST) once its outcome is known
COMMANDS_TOPIC = "/oralnav/commands"
#: JSON: every audit record, as the audit log wrote it
AUDIT_TOPIC = "/oralnav/audit"
#: JSON: the recorder's own events (frames dropped, the recording's end)
RECORDER_TOPIC = "/oralnav/recorder"
#: foxglove.FrameTransform: the arm's measured TCP in the robot base, every loop sample
TCP_TOPIC = "/arm/tcp"
#: foxglove.FrameTransform: the stereo camera ``C`` in the robot base ``B`` (the hand-eye
#: calibration), once at the start: it joins the tracked poses to the arm in one tree
HAND_EYE_TOPIC = "/calibration/T_B_C"


def pose_topic(pose: str) -> str:
    """The FrameTransform topic of a published pose (``T_C_RM`` -> ``/poses/T_C_RM``)."""
    return f"/poses/{pose}"


def image_topic(camera: str) -> str:
    """The image topic of a camera (``left`` -> ``/cameras/left/image``)."""
    return f"/cameras/{camera}/image"


def child_frame(frame: str, suffix: str) -> str:
    """The Foxglove child frame of a field seen from ``frame``: ``RM``, ``OM``, ``EM`` in
    the stereo camera ``C``; suffixed with the frame elsewhere (``EM_En``), since a frame
    has one parent in Foxglove's transform tree and ``EM`` is seen from both."""
    return suffix if frame == "C" else f"{suffix}_{frame}"


# -- metadata and attachments -------------------------------------------------------------
#: metadata: what was recorded and how (written first)
SESSION_METADATA = "oralnav.session"
#: metadata: the clock of every time in the file and its offset to UTC
CLOCK_METADATA = "oralnav.clock"
#: metadata: the tracked views, the key ``views`` holds a JSON list (:func:`view_entry`)
VIEWS_METADATA = "oralnav.views"
#: metadata: the counts when the recording ended (written last; absent from a cut file)
SUMMARY_METADATA = "oralnav.summary"
#: attachment: the daemon's configuration file as it was read
CONFIG_ATTACHMENT = "config/daemon.toml"

#: the image encodings a recording may use: RawImage (lossless, cheap), CompressedImage
#: PNG (lossless, about 10 times the CPU of zstd chunks) or JPEG (lossy), or no images
IMAGE_ENCODINGS = ("raw", "png", "jpeg", "none")
#: the chunk compressions ``mcap`` offers
COMPRESSIONS = ("zstd", "lz4", "none")


def to_ns(t: float) -> int:
    """Seconds (float) -> integer nanoseconds."""
    return int(round(t * 1e9))


def timestamp(t: float) -> Timestamp:
    """A Protobuf ``Timestamp`` of ``t`` seconds (``t >= 0``)."""
    ns = max(to_ns(t), 0)
    return Timestamp(seconds=ns // 1_000_000_000, nanos=ns % 1_000_000_000)


def quaternions(Ts: np.ndarray) -> np.ndarray:
    """(N, 4) quaternions (x, y, z, w: Foxglove's order, SciPy's) of N 4x4 transforms'
    rotation blocks, in one call: 500 arm samples a second one by one cost 10 % of a core."""
    Ts = np.asarray(Ts, dtype=float).reshape(-1, 4, 4)
    return Rotation.from_matrix(Ts[:, :3, :3]).as_quat()


def frame_transform(T: np.ndarray, t: float, parent: str, child: str,
                    quat: np.ndarray | None = None) -> FrameTransform:
    """A ``foxglove.FrameTransform`` of the 4x4 transform ``T`` (m), ``child`` in
    ``parent``, at ``t`` (s); ``quat``: its rotation's quaternion when already known
    (:func:`quaternions`)."""
    T = np.asarray(T, dtype=float)
    msg = FrameTransform(timestamp=timestamp(t), parent_frame_id=parent, child_frame_id=child)
    x, y, z = (float(v) for v in T[:3, 3])
    msg.translation.x, msg.translation.y, msg.translation.z = x, y, z
    q = quaternions(T)[0] if quat is None else quat
    msg.rotation.x, msg.rotation.y, msg.rotation.z, msg.rotation.w = (float(v) for v in q)
    return msg


def image_message(image: np.ndarray, t: float, camera: str, encoding: str,
                  jpeg_quality: int = 90) -> RawImage | CompressedImage:
    """One camera frame as a Foxglove image at ``t`` (s), ``frame_id`` the camera:
    ``raw`` a RawImage (``mono8`` or ``bgr8``), ``png`` or ``jpeg`` a CompressedImage."""
    image = np.ascontiguousarray(image)
    if image.dtype != np.uint8 or image.ndim not in (2, 3) or \
            (image.ndim == 3 and image.shape[2] != 3):
        raise ValueError(f"camera {camera!r}: cannot record a {image.dtype} image of shape "
                         f"{image.shape} (mono8 or 3-channel BGR only)")
    if encoding == "raw":
        h, w = image.shape[:2]
        mono = image.ndim == 2
        return RawImage(timestamp=timestamp(t), frame_id=camera, width=w, height=h,
                        encoding="mono8" if mono else "bgr8", step=w * (1 if mono else 3),
                        data=image.tobytes())
    if encoding == "png":
        # level 1: the fastest; levels 3-9 shrink rendered or camera images by 3 % more
        ok, buf = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    elif encoding == "jpeg":
        ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
    else:
        raise ValueError(f"unknown image encoding {encoding!r}; expected one of "
                         f"{', '.join(IMAGE_ENCODINGS[:3])}")
    if not ok:
        raise ValueError(f"camera {camera!r}: OpenCV could not encode the image as {encoding}")
    return CompressedImage(timestamp=timestamp(t), frame_id=camera, data=buf.tobytes(),
                           format=encoding)


# -- JSON ---------------------------------------------------------------------------------
def _finite(x: Any) -> Any:
    """``x`` with non-finite floats as None (JSON has no NaN) and numpy values as Python's."""
    if isinstance(x, float | np.floating):
        return float(x) if math.isfinite(x) else None
    if isinstance(x, np.integer | np.bool_):
        return x.item()
    if isinstance(x, np.ndarray):
        return [_finite(v) for v in x.tolist()]
    if isinstance(x, Mapping):
        return {str(k): _finite(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_finite(v) for v in x]
    return x


def json_bytes(obj: Any) -> bytes:
    """``obj`` as compact UTF-8 JSON; every finite float round-trips exactly."""
    return json.dumps(_finite(obj), separators=(",", ":"), allow_nan=False,
                      ensure_ascii=False).encode()


def _schema(title: str, properties: Mapping[str, Any]) -> bytes:
    return json.dumps({"$schema": "https://json-schema.org/draft/2020-12/schema",
                       "title": title, "type": "object",
                       "properties": dict(properties)}).encode()


_NUM, _STR, _INT = {"type": "number"}, {"type": "string"}, {"type": "integer"}
_ANY_OBJ = {"type": "object"}
#: JSON channel topic -> (schema name, JSON Schema) for the recorder to register
JSON_CHANNELS: dict[str, tuple[str, bytes]] = {
    ROUNDS_TOPIC: ("oralnav.TrackedRound", _schema("one tracked round of a source", {
        "source": _STR, "round": _INT, "images": _STR, "frames": _ANY_OBJ,
        "views": {"type": "array", "items": _ANY_OBJ}})),
    SAFETY_TOPIC: ("oralnav.SafetyTransition", _schema("a safety state change", {
        "time": _NUM, "from": _STR, "to": _STR, "who": _STR, "reason": _STR})),
    COMMANDS_TOPIC: ("oralnav.OperatorCommand", _schema("an operator command's outcome", {
        "id": _STR, "who": _STR, "role": _STR, "method": _STR, "path": _STR, "body": _STR,
        "status": _INT, "result": _STR, "client": _STR})),
    AUDIT_TOPIC: ("oralnav.AuditRecord", _schema("an audit log record (docs/api.md)", {
        "time": _STR, "id": _STR, "phase": _STR, "who": _STR, "role": _STR, "method": _STR,
        "path": _STR, "body": _STR, "status": _INT, "result": _STR})),
    RECORDER_TOPIC: ("oralnav.RecorderEvent", _schema("the recorder's own events", {
        "event": _STR, "frames_dropped": _INT, "detail": _STR})),
}


def pose_entry(pose: str, est: Any) -> dict[str, Any]:
    """A tracked field's estimate as the round record keeps it: the published pose name,
    ``T`` (16 floats, row-major 4x4, m), corners, reprojection RMS (px) and spread."""
    return {"pose": pose, "T": np.asarray(est.T_ref_field, dtype=float).reshape(-1).tolist(),
            "corners": int(est.corners), "rms_px": float(est.reproj_rms_px),
            "sigma_m": float(est.position_sigma_m), "sigma_deg": float(est.rotation_sigma_deg)}


def round_record(source: str, number: int, frames: Mapping[str, Any],
                 views: Sequence[tuple[int, str, float, Mapping[str, dict[str, Any]]]],
                 images: str) -> dict[str, Any]:
    """The ``/oralnav/rounds`` record of round ``number`` of ``source``: each camera's
    frame (timestamp s, counter), and for each view that tracked (index, frame, capture
    instant s, field -> :func:`pose_entry`) what it found. ``images``: whether this
    round's frames were queued for the file (``queued``), left out by the decimation
    (``decimated``), dropped because the writer was behind (``dropped``), not recorded
    (``off``), or the round came before the recording (``before``: only its poses, which
    the replay needs to continue the trackers' prediction)."""
    return {"source": source, "round": int(number), "images": images,
            "frames": {cam: {"timestamp": float(f.timestamp), "counter": int(f.counter)}
                       for cam, f in frames.items()},
            "views": [{"view": int(i), "frame": frame, "stamp": float(stamp),
                       "found": dict(found)} for i, frame, stamp, found in views]}


def transition_record(tr: Any) -> dict[str, Any]:
    """A ``safety.states.Transition`` as the ``/oralnav/safety`` record."""
    return tr.as_dict()


def command_record(rec: Mapping[str, Any], intent: Mapping[str, Any] | None
                   ) -> dict[str, Any]:
    """An operator command's ``/oralnav/commands`` record from its audit outcome (or
    single) record ``rec`` and its intent (which holds the body), if any."""
    out = {k: rec.get(k) for k in ("id", "who", "role", "method", "path", "status",
                                   "result", "client")}
    out["body"] = (intent or rec).get("body", "")
    out["time_utc"] = rec.get("time")
    return out


# -- views: what the replay needs to build the trackers again -----------------------------
def tracker_settings_dict(settings: TrackerSettings) -> dict[str, Any]:
    """``settings`` as a JSON-able dict (:func:`tracker_settings_from_dict` inverts it)."""
    return dataclasses.asdict(settings)


def tracker_settings_from_dict(d: Mapping[str, Any]) -> TrackerSettings:
    """The settings :func:`tracker_settings_dict` wrote; ValueError naming an unknown key
    (a recording from a daemon with other settings than this one knows)."""
    names = {f.name for f in dataclasses.fields(TrackerSettings)}
    quad_names = {f.name for f in dataclasses.fields(QuadParams)}
    d = dict(d)
    quads = dict(d.pop("quads", {}))
    unknown = sorted(set(d) - names) + [f"quads.{k}" for k in sorted(set(quads) - quad_names)]
    if unknown:
        raise ValueError(f"tracker settings this version does not know: {', '.join(unknown)}")
    return TrackerSettings(**d, quads=QuadParams(**quads))


def view_entry(source: str, index: int, view: Any) -> tuple[dict[str, Any], dict[str, bytes]]:
    """A tracked view (``capture_task.View``) as the replay rebuilds it: its entry in
    ``oralnav.views`` and its files (attachment name -> bytes): the rig file and the
    marker-field file (config/rig.py, config/fields.py formats, floats exact), so that
    ``Tracker(rig, fields, method, mode, weighting, settings)`` is the daemon's."""
    tr = view.tracker
    base = f"views/{source}/{index}"
    rig_text = "# oralnav rig: lengths in metres, intrinsics in pixels\n" + \
        dump_toml(rig_to_dict(tr.rig))
    files = {f"{base}/rig.toml": rig_text.encode()}
    fields = fields_to_files(list(tr.fields.values()))
    files.update({f"{base}/{name}": text.encode() for name, text in fields.items()})
    entry = {"source": source, "view": index, "frame": view.frame,
             "suffixes": dict(view.suffixes), "time_offset": float(view.time_offset),
             "cameras": {cam: image_topic(cam) for cam in tr.rig.names},
             "tracker": {"method": tr.method, "mode": tr.mode, "weighting": tr.weighting,
                         "fields": list(tr.fields),
                         "settings": tracker_settings_dict(tr.settings)},
             "rig": f"{base}/rig.toml", "fields": f"{base}/fields.toml",
             "files": sorted(files)}
    return entry, files
