"""``oralnav replay``: re-run tracking on a session recording and compare every pose.

    oralnav replay FILE.mcap [--json]

A recording of ``oralnavd --record`` (docs/recording.md) carries each tracked view's rig,
marker fields and tracker settings, every tracked round's poses bit-exact, and the frames
of the rounds it kept. This command builds each view's tracker as the daemon built it
(``Tracker(rig, fields, method="nvgba", mode="predict")`` from those files), plays the
frames through the MCAP camera backend (``drivers/camera/mcap_replay.py``) in the order
they were tracked, and compares each pose found with the recorded one
(``daemon/replay_compare.py``). Where the frames of the round before were not kept
(decimated, dropped, or the recording started mid-session) the tracker is first given the
recorded poses of its two previous rounds (``Tracker.restore``), so that it predicts as
the live one did.

``--json`` prints one object: ``{"frames", "rounds", "poses", "identical",
"max_translation_diff_mm", "max_rotation_diff_deg", ...}``. Exit status: 0 when every
recorded pose was replayed bit for bit, 1 when some differ, 2 for a file that is missing,
not MCAP, or no session recording. A file cut short (a crash, a full disk) is replayed as
far as it is readable, and the report says it was truncated.
"""

from __future__ import annotations

import argparse
import bisect
import json
import sys
import tempfile
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from oralnav.config.errors import ConfigError
from oralnav.config.fields import load_fields
from oralnav.config.rig import load_rig
from oralnav.control.vision.tracker import Tracker
from oralnav.daemon import recording_format as fmt
from oralnav.daemon.replay_compare import PoseComparison

__all__ = ["ReplayFileError", "Session", "add_parser", "cmd_replay", "read_session",
           "replay", "replay_async"]

#: Seconds between two progress lines on stderr.
PROGRESS_S = 2.0


class ReplayFileError(ValueError):
    """The file cannot be replayed: missing, not MCAP, or not a session recording."""


@dataclass
class ReplayView:
    """One tracked view of the recording and its rebuilt tracker."""

    source: str
    index: int
    frame: str
    suffixes: dict[str, str]
    cameras: dict[str, str]          # camera -> image topic
    tracker: Tracker
    tracked: list[int] = field(default_factory=list)  # recorded rounds it tracked in


@dataclass
class Session:
    """What one pass over the file found (everything but the images)."""

    path: Path
    metadata: dict[str, dict[str, str]]
    attachments: dict[str, bytes]
    rounds: dict[str, dict[int, dict[str, Any]]]   # source -> round -> record
    images: dict[str, int]                         # image topic -> messages
    truncated: str | None
    complete: bool                                 # the footer was read

    @property
    def summary(self) -> dict[str, str] | None:
        return self.metadata.get(fmt.SUMMARY_METADATA)


def read_session(path: str | Path) -> Session:
    """Read the file once, from its start, up to its end or to where it stops being
    readable (then ``truncated`` says why): metadata, attachments, round records, image
    counts. Raises :class:`ReplayFileError` for a missing file or one that is not MCAP."""
    from mcap.exceptions import InvalidMagic
    from mcap.records import Attachment, Channel, Footer, Message, Metadata, Schema
    from mcap.stream_reader import StreamReader

    path = Path(path)
    try:
        fh = open(path, "rb")  # noqa: SIM115 - closed below
    except OSError as exc:
        raise ReplayFileError(f"{path}: cannot open ({exc.strerror or exc})") from None
    size = path.stat().st_size
    metadata: dict[str, dict[str, str]] = {}
    attachments: dict[str, bytes] = {}
    rounds: dict[str, dict[int, dict[str, Any]]] = {}
    images: dict[str, int] = {}
    channels: dict[int, tuple[str, str]] = {}   # id -> (topic, schema name)
    schemas: dict[int, str] = {}
    truncated, complete, started = None, False, False
    with fh:
        records = StreamReader(fh, validate_crcs=True).records
        try:
            for rec in records:
                started = True
                if isinstance(rec, Schema):
                    schemas[rec.id] = rec.name
                elif isinstance(rec, Channel):
                    channels[rec.id] = (rec.topic, schemas.get(rec.schema_id, ""))
                elif isinstance(rec, Message):
                    topic, schema = channels.get(rec.channel_id, ("", ""))
                    if topic == fmt.ROUNDS_TOPIC:
                        r = json.loads(rec.data)
                        rounds.setdefault(r["source"], {})[int(r["round"])] = r
                    elif schema in ("foxglove.RawImage", "foxglove.CompressedImage"):
                        images[topic] = images.get(topic, 0) + 1
                elif isinstance(rec, Metadata):
                    metadata[rec.name] = dict(rec.metadata)
                elif isinstance(rec, Attachment):
                    attachments[rec.name] = bytes(rec.data)
                elif isinstance(rec, Footer):
                    complete = True
        except InvalidMagic as exc:
            raise ReplayFileError(f"{path}: not an MCAP file ({exc})") from None
        except Exception as exc:  # a cut chunk, a torn record, a bad CRC: stop here
            if not started:
                raise ReplayFileError(f"{path}: not an MCAP file (it ends or breaks "
                                      f"before its header: {type(exc).__name__}: {exc})"
                                      ) from None
            at = fh.tell()
            truncated = (f"unreadable from byte {at} of {size} "
                         f"({type(exc).__name__}{': ' + str(exc) if str(exc) else ''}): "
                         "the file was cut short (a crash or a full disk)")
    if not complete and truncated is None:
        truncated = f"no footer after byte {size}: the file was cut short"
    return Session(path, metadata, attachments, rounds, images, truncated, complete)


def build_views(session: Session) -> list[ReplayView]:
    """Each recorded view with its tracker, built from the recording's own files.
    :class:`ReplayFileError` when the file does not describe them."""
    meta = session.metadata.get(fmt.VIEWS_METADATA)
    if meta is None or "views" not in meta:
        raise ReplayFileError(f"{session.path}: no {fmt.VIEWS_METADATA!r} metadata: not a "
                              "session recording of oralnavd --record"
                              + (f" ({session.truncated})" if session.truncated else ""))
    out = []
    with tempfile.TemporaryDirectory(prefix="oralnav-replay-") as tmp:
        for entry in json.loads(meta["views"]):
            folder = Path(tmp) / f"{entry['source']}-{entry['view']}"
            folder.mkdir()
            for name in entry["files"]:
                data = session.attachments.get(name)
                if data is None:
                    raise ReplayFileError(f"{session.path}: attachment {name!r} of view "
                                          f"{entry['view']} of {entry['source']!r} is missing")
                (folder / Path(name).name).write_bytes(data)
            t = entry["tracker"]
            try:
                rig = load_rig(folder / Path(entry["rig"]).name)
                fields = load_fields(folder / Path(entry["fields"]).name)
                settings = fmt.tracker_settings_from_dict(t["settings"])
                tracker = Tracker(rig, [fields[n] for n in t["fields"]], method=t["method"],
                                  mode=t["mode"], weighting=t["weighting"], settings=settings)
            except (ConfigError, KeyError, ValueError) as exc:
                raise ReplayFileError(f"{session.path}: view {entry['view']} of "
                                      f"{entry['source']!r} cannot be rebuilt: {exc}") from None
            out.append(ReplayView(entry["source"], int(entry["view"]), entry["frame"],
                                  dict(entry["suffixes"]), dict(entry["cameras"]), tracker))
    for v in out:
        v.tracked = sorted(n for n, r in session.rounds.get(v.source, {}).items()
                           if any(e["view"] == v.index for e in r["views"]))
    return out


def _found(record: Mapping[str, Any], index: int) -> dict[str, Any] | None:
    """What view ``index`` found in a round record (field -> pose entry), None when it
    did not track in that round."""
    for e in record["views"]:
        if e["view"] == index:
            return e["found"]
    return None


def _previous(tracked: list[int], n: int) -> tuple[int | None, int | None]:
    """The two last rounds before ``n`` in ``tracked`` (sorted)."""
    i = bisect.bisect_left(tracked, n)
    return (tracked[i - 1] if i >= 1 else None), (tracked[i - 2] if i >= 2 else None)


async def _replay_source(session: Session, source: str, views: list[ReplayView],
                         cmp: PoseComparison, report: dict[str, Any],
                         progress: Any) -> None:
    from oralnav.drivers.camera.mcap_replay import McapRig
    from oralnav.drivers.errors import DriverError, DriverInitError, EndOfStream

    rounds = session.rounds.get(source, {})
    cameras = {cam: topic for v in views for cam, topic in v.cameras.items()}
    if not any(session.images.get(t) for t in cameras.values()):
        return  # a recording without images (images = "none"): nothing to track
    rig = McapRig(session.path, cameras)
    try:
        await rig.start()
    except DriverInitError as exc:
        report["errors"].append(f"{source}: {exc}")
        return
    last_replayed: dict[int, int] = {}   # view -> the last round the replay tracked it in
    try:
        while True:
            try:
                frames = await rig.read()
            except EndOfStream:
                break
            except DriverError as exc:  # one undecodable image: skip its round
                report["errors"].append(f"{source}: {exc}")
                continue
            n = int(rig.sequence or 0)
            record = rounds.get(n)
            if record is None:
                report["rounds_without_record"] += 1
                continue
            report["rounds"] += 1
            report["frames"] += len(frames)
            for v in views:
                found = _found(record, v.index)
                if found is None:
                    continue  # the live view did not track this round: neither do we
                prev, prev2 = _previous(v.tracked, n)
                if prev is None or last_replayed.get(v.index) != prev:
                    # the frames of its last round are not in the file: continue from the
                    # poses the live tracker reported (or from nothing before the first)
                    before = _found(rounds[prev], v.index) if prev is not None else None
                    older = _found(rounds[prev2], v.index) if prev2 is not None else None
                    if before is None:
                        v.tracker.reset()
                    else:
                        v.tracker.restore({f: e["T"] for f, e in before.items()},
                                          {f: e["T"] for f, e in (older or {}).items()})
                        report["reseeded"] += 1
                ests = v.tracker.track({cam: frames[cam].image for cam in v.cameras})
                last_replayed[v.index] = n
                for fname in sorted(set(found) | set(ests)):
                    pose = f"T_{v.frame}_{v.suffixes.get(fname, fname)}"
                    rec = found.get(fname)
                    est = ests.get(fname)
                    cmp.add(f"{source}#{n}", pose, None if rec is None else rec["T"],
                            None if est is None else est.T_ref_field)
            progress(source, n)
    finally:
        await rig.close()
    report["incomplete_rounds"] += rig.incomplete


def replay(path: str | Path, progress: Any = None) -> dict[str, Any]:
    """Replay ``path``; the report (see the module docstring). :class:`ReplayFileError`
    for a file that cannot be replayed at all. ``progress(text)``: told every
    ``PROGRESS_S`` how far it got. Runs its own event loop (:func:`replay_async` inside
    one)."""
    import anyio

    return anyio.run(replay_async, path, progress)


async def replay_async(path: str | Path, progress: Any = None) -> dict[str, Any]:
    """:func:`replay` on the running event loop."""
    session = read_session(path)
    views = build_views(session)
    cmp = PoseComparison()
    report: dict[str, Any] = {"rounds": 0, "frames": 0, "reseeded": 0,
                              "rounds_without_record": 0, "incomplete_rounds": 0,
                              "errors": []}
    by_source: dict[str, list[ReplayView]] = {}
    for v in views:
        by_source.setdefault(v.source, []).append(v)
    queued = sum(1 for rs in session.rounds.values() for r in rs.values()
                 if r["images"] == "queued")
    last = [time.monotonic()]

    def tick(source: str, n: int) -> None:
        if progress is not None and time.monotonic() - last[0] >= PROGRESS_S:
            last[0] = time.monotonic()
            progress(f"{source}: round {n}, {report['rounds']} of {queued} rounds with "
                     f"frames replayed")

    for source, vs in by_source.items():
        await _replay_source(session, source, vs, cmp, report, tick)
    kinds: dict[str, int] = {}
    for rs in session.rounds.values():
        for r in rs.values():
            kinds[r["images"]] = kinds.get(r["images"], 0) + 1
    summary = session.summary or {}
    doc = {"file": str(session.path), "frames": report["frames"], "rounds": report["rounds"],
           **cmp.summary(), "all_identical": cmp.all_identical,
           "reseeded": report["reseeded"],
           "recorded_rounds": {k: v for k, v in sorted(kinds.items()) if k != "before"},
           "frames_dropped": int(summary["frames_dropped"]) if "frames_dropped" in summary
           else None,
           "rounds_missing_frames": max(queued - report["rounds"], 0),
           "incomplete_rounds": report["incomplete_rounds"],
           "truncated": session.truncated is not None, "truncation": session.truncated,
           "errors": report["errors"]}
    # the poses are what a round record holds, even in rounds whose frames were not kept
    doc["poses_recorded"] = sum(len(e["found"]) for rs in session.rounds.values()
                                for r in rs.values() if r["images"] != "before"
                                for e in r["views"])
    return doc


def add_parser(sub: argparse._SubParsersAction) -> None:
    rp = sub.add_parser("replay", help="re-run tracking on a session recording (oralnavd "
                                       "--record) and compare every pose")
    rp.add_argument("file", help="the MCAP file")
    rp.add_argument("--json", action="store_true", help="print one JSON object")
    rp.set_defaults(func=cmd_replay)


def cmd_replay(args: argparse.Namespace) -> int:
    def progress(msg: str) -> None:
        print(f"oralnav replay: {msg}", file=sys.stderr, flush=True)

    t0 = time.perf_counter()
    doc = replay(args.file, progress)
    doc["replay_s"] = round(time.perf_counter() - t0, 2)
    if doc["truncated"]:
        progress(f"warning: {doc['file']} is truncated ({doc['truncation']}); replayed "
                 "what comes before")
    for err in doc["errors"]:
        progress(f"warning: {err}")
    if args.json:
        print(json.dumps(doc))
    else:
        print(f"{doc['file']}: {doc['rounds']} rounds, {doc['frames']} frames replayed; "
              f"{doc['identical']} of {doc['poses']} poses identical bit for bit"
              f" ({doc['missing']} missing, {doc['extra']} extra)")
        if doc["identical"] != doc["poses"]:
            print(f"  largest difference: {doc['max_translation_diff_mm']:.6f} mm, "
                  f"{doc['max_rotation_diff_deg']:.6f} deg ({doc['worst']})")
        if doc["frames_dropped"]:
            print(f"  {doc['frames_dropped']} frames were dropped while recording")
        if doc["truncated"]:
            print(f"  truncated: {doc['truncation']}")
    return 0 if doc["all_identical"] else 1
