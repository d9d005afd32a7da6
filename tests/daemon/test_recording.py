"""Issue 33 item 4, session recording (``oralnav.daemon.recording``): one MCAP file per
recording with Foxglove's schemas, what replay needs inside it, frames dropped (and
counted) when the writer is behind while every pose is kept, and disks that refuse
writes ending the recording, never the daemon. The frames are the tiny cell's
(``tests/daemon/tiny_cell.py``): real renders tracked by the daemon's own pipeline.
Each test's docstring names the requirement it checks (the issue's numbered points)."""

from __future__ import annotations

import errno
import json
import os
import time
from pathlib import Path

import cv2
import httpx
import numpy as np
import pytest
from mcap.decoder import DecoderFactory as McapDecoderFactory
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from oralnav.cli.replay import replay_async
from oralnav.config.rig import load_rig
from oralnav.daemon import recording as recording_mod
from oralnav.daemon import recording_format as fmt
from oralnav.daemon.recording import (
    RecordingError,
    RecordingOptions,
    SessionRecorder,
)
from oralnav.safety.errors import StateError
from tests.daemon.tiny_cell import TinyCell, images, tiny_rig

ROUNDS = 6


async def _recorded(tmp_path: Path, name: str = "s.mcap", before: int = 0,
                    rounds: int = ROUNDS, **options) -> tuple[Path, TinyCell, dict]:
    """A tiny cell tracked for ``before`` rounds, then recorded for ``rounds``; the file,
    the (closed) cell and the recorder's final status."""
    c = await TinyCell().start()
    try:
        rec = SessionRecorder(c.core, c.pipeline.sources)
        c.pipeline.taps.append(rec.tap)
        await c.rounds(before)
        path = tmp_path / name
        rec.start(RecordingOptions(path, **options), "test")
        for _ in range(rounds):
            await c.rounds(1)
            rec.poll()
        status = rec.stop("test")
    finally:
        await c.close()
    return path, c, status


class _Json(McapDecoderFactory):
    """The JSON channels' messages as dicts."""

    def decoder_for(self, message_encoding, schema):
        return json.loads if message_encoding == "json" else None


def _read(path: Path) -> dict:
    """Everything in the file, through ``mcap``'s own reader and Protobuf decoders."""
    with open(path, "rb") as f:
        r = make_reader(f, decoder_factories=[DecoderFactory(), _Json()])
        summary = r.get_summary()
        out = {"schemas": {s.name: s.encoding for s in summary.schemas.values()},
               "channels": {c.topic: (c.message_encoding, summary.schemas[c.schema_id].name)
                            for c in summary.channels.values()},
               "counts": {summary.channels[i].topic: n for i, n in
                          summary.statistics.channel_message_counts.items()},
               "metadata": {m.name: dict(m.metadata) for m in r.iter_metadata()},
               "attachments": {a.name: bytes(a.data) for a in r.iter_attachments()},
               "messages": {}}
        for _, ch, msg, dec in r.iter_decoded_messages(log_time_order=False):
            out["messages"].setdefault(ch.topic, []).append((msg, dec))
    return out


async def test_the_file_holds_foxglove_schemas_and_what_replay_needs(tmp_path):
    """Items 1-2: read back with mcap's reader, poses are ``foxglove.FrameTransform``
    (each at its capture instant in ns, the translation exact), the arm's TCP too, frames
    ``foxglove.RawImage`` (lossless: the tracked pixels) or, asked for, PNG in
    ``foxglove.CompressedImage``; rounds and safety are JSON channels; the metadata names
    the clock and its UTC offset; the rig and fields travel as files that load back equal."""
    path, c, status = await _recorded(tmp_path)
    assert status["state"] == "stopped" and status["error"] is None
    doc = _read(path)
    assert doc["schemas"]["foxglove.FrameTransform"] == "protobuf"
    assert doc["schemas"]["foxglove.RawImage"] == "protobuf"
    assert doc["channels"]["/poses/T_C_RM"] == ("protobuf", "foxglove.FrameTransform")
    assert doc["channels"]["/arm/tcp"] == ("protobuf", "foxglove.FrameTransform")
    assert doc["channels"]["/cameras/left/image"] == ("protobuf", "foxglove.RawImage")
    assert doc["channels"]["/oralnav/rounds"] == ("json", "oralnav.TrackedRound")
    assert doc["channels"]["/oralnav/safety"] == ("json", "oralnav.SafetyTransition")
    assert doc["counts"]["/poses/T_C_RM"] == ROUNDS
    assert doc["counts"]["/cameras/right/image"] == ROUNDS
    assert doc["counts"]["/arm/tcp"] >= ROUNDS * 4  # every control period's sample
    rounds = [json.loads(m.data) for m, _ in doc["messages"]["/oralnav/rounds"]]
    for (msg, tf), r in zip(doc["messages"]["/poses/T_C_RM"], rounds, strict=True):
        entry = r["views"][0]["found"]["robot"]
        assert msg.log_time == fmt.to_ns(r["views"][0]["stamp"])
        assert (tf.parent_frame_id, tf.child_frame_id) == ("C", "RM")
        T = np.array(entry["T"]).reshape(4, 4)
        assert [tf.translation.x, tf.translation.y, tf.translation.z] == T[:3, 3].tolist()
    msg, raw = doc["messages"]["/cameras/left/image"][2]
    assert (raw.encoding, raw.width, raw.height, raw.frame_id) == ("mono8", 320, 240, "left")
    assert raw.data == images(2)["left"].tobytes()  # lossless
    assert msg.sequence == rounds[2]["round"]
    clock = doc["metadata"]["oralnav.clock"]
    assert "monotonic" in clock["clock"] and int(clock["utc_minus_clock_ns"]) > 0
    assert set(doc["metadata"]) >= {"oralnav.session", "oralnav.views", "oralnav.summary"}
    views = json.loads(doc["metadata"]["oralnav.views"]["views"])
    assert views[0]["tracker"]["method"] == "nvgba" and views[0]["tracker"]["mode"] == "predict"
    rig_file = tmp_path / "rig.toml"
    rig_file.write_bytes(doc["attachments"][views[0]["rig"]])
    back, rig = load_rig(rig_file), tiny_rig()
    for name in rig.names:
        assert back[name].K.tobytes() == rig[name].K.tobytes()
        assert back[name].dist.tobytes() == rig[name].dist.tobytes()
    assert doc["metadata"]["oralnav.summary"]["frames_dropped"] == "0"

    png, _, _ = await _recorded(tmp_path, "png.mcap", rounds=2, images="png")
    doc = _read(png)
    assert doc["channels"]["/cameras/left/image"] == ("protobuf", "foxglove.CompressedImage")
    _, comp = doc["messages"]["/cameras/left/image"][1]
    assert comp.format == "png"
    decoded = cv2.imdecode(np.frombuffer(comp.data, np.uint8), cv2.IMREAD_UNCHANGED)
    assert np.array_equal(decoded, images(1)["left"])


async def test_every_recorded_pose_replays_bit_for_bit(tmp_path):
    """Items 3 and 5: a short recording of real tracked frames, replayed with trackers
    rebuilt from the file, gives every pose bit for bit; so does one started mid-session
    and keeping every third round's frames only (the replay continues each tracker's
    prediction from the recorded poses of the rounds it has no frames of)."""
    path, _, _ = await _recorded(tmp_path)
    doc = await replay_async(path)
    assert doc["rounds"] == ROUNDS and doc["frames"] == 2 * ROUNDS
    assert doc["poses"] == ROUNDS and doc["identical"] == ROUNDS and doc["all_identical"]
    assert doc["max_translation_diff_mm"] == 0.0 and not doc["truncated"]

    path, _, status = await _recorded(tmp_path, "mid.mcap", before=3, rounds=7, every=3)
    assert status["frames"]["decimated"] == 2 * 4
    doc = await replay_async(path)
    assert doc["rounds"] == 3 and doc["poses"] == 3 and doc["identical"] == 3, doc
    assert doc["reseeded"] == 3 and doc["recorded_rounds"] == {"decimated": 4, "queued": 3}
    assert doc["poses_recorded"] == 7


async def test_a_slow_writer_drops_frames_counts_them_and_keeps_every_pose(tmp_path,
                                                                          monkeypatch):
    """Item 2: while the writer is slow (a slow disk: 0.3 s a round of frames) the tap
    still returns at once; frames that find the queue full are dropped and counted (the
    status, the recorder channel, the file's summary), every pose and round is written,
    and the replay of the rounds kept is still bit for bit."""
    slow = recording_mod._McapFile.frames

    def frames(self, item, opts):
        time.sleep(0.3)
        slow(self, item, opts)

    monkeypatch.setattr(recording_mod._McapFile, "frames", frames)
    c = await TinyCell().start()
    try:
        rec = SessionRecorder(c.core, c.pipeline.sources)
        taps: list[float] = []

        def timed(rnd):
            t0 = time.perf_counter()
            rec.tap(rnd)
            taps.append(time.perf_counter() - t0)

        c.pipeline.taps.append(timed)
        path = tmp_path / "slow.mcap"
        rec.start(RecordingOptions(path, queue_rounds=1), "test")
        await c.rounds(8)
        rec.poll()
        during = rec.status()
        status = rec.stop("test")
    finally:
        await c.close()
    assert max(taps) < 0.05  # never waits for the writer
    assert during["state"] == "recording" and during["frames"]["dropped"] > 0
    dropped = status["frames"]["dropped"]
    assert dropped >= 2 and dropped % 2 == 0  # whole rounds: both cameras
    assert status["frames"]["written"] + dropped == 16
    doc = _read(path)
    assert doc["counts"]["/poses/T_C_RM"] == 8 and doc["counts"]["/oralnav/rounds"] == 8
    assert doc["counts"]["/cameras/left/image"] == status["frames"]["written"] // 2
    assert doc["metadata"]["oralnav.summary"]["frames_dropped"] == str(dropped)
    events = [json.loads(m.data) for m, _ in doc["messages"]["/oralnav/recorder"]]
    assert events[-1]["event"] == "frames dropped" and events[-1]["frames_dropped"] > 0
    rounds = [json.loads(m.data) for m, _ in doc["messages"]["/oralnav/rounds"]]
    assert sum(r["images"] == "dropped" for r in rounds) * 2 == dropped
    out = await replay_async(path)
    assert out["frames_dropped"] == dropped and out["all_identical"]
    assert out["poses"] == out["identical"] == status["frames"]["written"] // 2


def _unwritable(tmp_path: Path, monkeypatch) -> tuple[Path, str]:
    """A folder this process cannot create files in, and the errno name expected: a
    read-only folder (EACCES), or, for root (whom permissions do not stop), the recorder's
    open failing as a read-only file system does (EROFS)."""
    folder = tmp_path / "ro"
    folder.mkdir()
    folder.chmod(0o500)
    if not os.access(folder, os.W_OK):
        return folder, "EACCES"

    def read_only(path, mode="r", *args, **kwargs):
        raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(path))

    monkeypatch.setattr(recording_mod, "open", read_only, raising=False)
    return folder, "EROFS"


async def test_a_read_only_folder_is_a_clear_error_and_the_core_keeps_tracking(
        tmp_path, monkeypatch):
    """Item 2: a recording asked into a folder that refuses files fails at once with an
    error naming the file and the errno (RecordingError, the API's 422), the status says
    ``failed`` with it, and the core goes on publishing poses round after round."""
    folder, name = _unwritable(tmp_path, monkeypatch)
    c = await TinyCell().start()
    try:
        rec = SessionRecorder(c.core, c.pipeline.sources)
        c.pipeline.taps.append(rec.tap)
        await c.rounds(1)
        target = folder / "x.mcap"
        with pytest.raises(RecordingError, match=f"{target}.*{name}"):
            rec.start(RecordingOptions(target), "test")
        st = rec.status()
        assert st["state"] == "failed" and name in st["error"] and str(target) in st["error"]
        before = c.core.pose("T_C_RM")["stamp"]
        rounds = await c.rounds(2)
        assert all(r is not None and "T_C_RM" in r.poses for r in rounds)
        assert c.core.pose("T_C_RM")["stamp"] > before
        assert c.core.supervisor.state.value != "FAULT"
        ok = tmp_path / "ok.mcap"  # a writable place still records afterwards
        monkeypatch.undo()
        folder.chmod(0o700)
        rec.start(RecordingOptions(ok), "test")
        await c.rounds(1)
        assert rec.stop("test")["state"] == "stopped"
    finally:
        await c.close()


class _FillingFile:
    """A real file on a disk that fills after ``room`` bytes: writes beyond fail with
    ENOSPC, having written what fitted (as a full disk does)."""

    def __init__(self, path, mode, room: int) -> None:
        self.f = open(path, mode)  # noqa: SIM115 - closed by close()
        self.room = room

    def write(self, data) -> int:
        data = bytes(data)
        if len(data) > self.room:
            self.f.write(data[:self.room])
            self.f.flush()
            self.room = 0
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        self.room -= len(data)
        return self.f.write(data)

    def tell(self) -> int:
        return self.f.tell()

    def flush(self) -> None:
        self.f.flush()

    def close(self) -> None:
        self.f.close()


async def test_a_full_disk_ends_the_recording_keeps_it_readable_and_never_the_daemon(
        tmp_path, monkeypatch):
    """Item 2: a disk that fills mid-recording (ENOSPC) ends the recording with the error
    naming the file in the status, the core keeps tracking, and what reached the disk
    replays as a truncated recording, bit for bit as far as it goes."""
    monkeypatch.setattr(recording_mod, "CHUNK_BYTES", 64 * 1024)  # a chunk per image
    monkeypatch.setattr(recording_mod, "open",
                        lambda p, m: _FillingFile(p, m, room=400_000), raising=False)
    c = await TinyCell().start()
    try:
        rec = SessionRecorder(c.core, c.pipeline.sources)
        c.pipeline.taps.append(rec.tap)
        path = tmp_path / "full.mcap"
        rec.start(RecordingOptions(path), "test")
        for _ in range(12):
            await c.rounds(1)
            rec.poll()
            if rec.status()["state"] == "failed":
                break
            time.sleep(0.05)  # the writer writes
        deadline = time.monotonic() + 10
        while rec.status()["state"] != "failed" and time.monotonic() < deadline:
            time.sleep(0.02)
        st = rec.status()
        assert st["state"] == "failed", st
        assert "ENOSPC" in st["error"] and str(path) in st["error"]
        rounds = await c.rounds(3)  # tracking never noticed
        assert all(r is not None and "T_C_RM" in r.poses for r in rounds)
        assert rec.stop("test")["state"] == "failed"  # stop is never refused
    finally:
        await c.close()
    doc = await replay_async(path)
    assert doc["truncated"] and doc["rounds"] >= 1
    assert doc["identical"] == doc["poses"] == doc["rounds"]


async def test_recording_endpoints_roles_audit_and_the_command_channel(tmp_path):
    """Item 1: GET /recording for observers, POST /recording/start and /stop for
    operators only (403), audited like every command; a second start is 409, a path that
    is no .mcap file 422; the file holds the operator's commands with their outcome, the
    audit records and the e-stop's safety transition."""
    from oralnav.config.daemon import load_config
    from oralnav.daemon.api import build_app
    from oralnav.daemon.audit import AuditLog
    from oralnav.daemon.auth import TokenStore
    from oralnav.daemon.service import attach_recorder

    clear = TokenStore.generate(tmp_path / "tokens.toml")
    tokens = TokenStore.from_file(tmp_path / "tokens.toml")
    audit = AuditLog(tmp_path / "audit.jsonl").open()
    c = await TinyCell().start()
    try:
        rec = attach_recorder(load_config(), c.core, c.pipeline, audit)
        app = build_app(c.core, tokens, audit)
        op = {"Authorization": f"Bearer {clear['operator']}"}
        ob = {"Authorization": f"Bearer {clear['observer']}"}
        path = tmp_path / "api.mcap"
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://oralnav") as cl:
            r = await cl.get("/recording", headers=ob)
            assert r.status_code == 200 and r.json()["state"] == "idle"
            r = await cl.post("/recording/start", json={"path": str(path)}, headers=ob)
            assert r.status_code == 403
            r = await cl.post("/recording/start", json={"path": str(tmp_path / "a.txt")},
                              headers=op)
            assert r.status_code == 422 and ".mcap" in r.text
            r = await cl.post("/recording/start", json={"path": str(path), "every": 2},
                              headers=op)
            assert r.status_code == 200, r.text
            assert r.json()["state"] == "recording" and r.json()["audited"] is True
            r = await cl.post("/recording/start", json={"path": str(path)}, headers=op)
            assert r.status_code == 409 and "already recording" in r.text
            await c.rounds(3)
            assert (await cl.post("/estop", json={"reason": "test"}, headers=op)).status_code \
                == 200
            rec.poll()
            r = await cl.post("/recording/stop", headers=op)
            assert r.status_code == 200 and r.json()["state"] == "stopped", r.text
            assert r.json()["frames"]["written"] == 4 and r.json()["frames"]["decimated"] == 2
    finally:
        await c.close()
        audit.close()
    doc = _read(path)
    commands = [json.loads(m.data) for m, _ in doc["messages"]["/oralnav/commands"]]
    assert [(x["path"], x["status"]) for x in commands] == [
        ("/recording/start", 200), ("/recording/start", 409), ("/estop", 200)]
    assert json.loads(commands[0]["body"])["every"] == 2  # the intent's body
    assert commands[2]["who"] == "operator" and commands[2]["role"] == "operator"
    audit_recs = [json.loads(m.data) for m, _ in doc["messages"]["/oralnav/audit"]]
    assert {a["phase"] for a in audit_recs} >= {"intent", "outcome", "single"}
    safety = [json.loads(m.data) for m, _ in doc["messages"]["/oralnav/safety"]]
    assert safety[0]["who"] == "recorder"  # the state when recording began
    assert any(t["to"] == "ESTOP" for t in safety)
    logged = (tmp_path / "audit.jsonl").read_text()
    assert '"path":"/recording/start"' in logged and '"path":"/recording/stop"' in logged


def test_options_are_checked_before_anything_is_opened(tmp_path):
    """Item 1: a recording must be an ``.mcap`` file; decimation, encodings and the queue
    are bounded; each refusal names the option."""
    for bad, match in ((dict(path=tmp_path / "x.txt"), r"\.mcap"),
                       (dict(path=tmp_path / "x.mcap", every=0), "every"),
                       (dict(path=tmp_path / "x.mcap", images="gif"), "images"),
                       (dict(path=tmp_path / "x.mcap", compression="xz"), "compression"),
                       (dict(path=tmp_path / "x.mcap", queue_rounds=0), "queue_rounds")):
        with pytest.raises(RecordingError, match=match):
            RecordingOptions(**bad)
    assert not list(tmp_path.iterdir())


async def test_a_second_start_is_refused_and_an_existing_file_is_kept(tmp_path):
    """Item 1: while recording, a start is a StateError (409) naming the file; the API
    never replaces an existing file (``oralnavd --record`` may: ``overwrite``)."""
    c = await TinyCell().start()
    try:
        rec = SessionRecorder(c.core, c.pipeline.sources)
        kept = tmp_path / "kept.mcap"
        kept.write_bytes(b"precious")
        with pytest.raises(RecordingError, match="exists"):
            rec.start(RecordingOptions(kept), "test")
        assert kept.read_bytes() == b"precious"
        rec.start(RecordingOptions(tmp_path / "a.mcap"), "test")
        with pytest.raises(StateError, match="a.mcap"):
            rec.start(RecordingOptions(tmp_path / "b.mcap"), "test")
        rec.stop("test")
        assert rec.stop("again")["state"] == "stopped"  # never refused
    finally:
        await c.close()


def test_oralnavd_record_refuses_a_bad_path_before_anything_starts(tmp_path, capsys):
    """Item 1: ``oralnavd --record`` checks its file with the configuration: a folder it
    cannot make, a name that is no ``.mcap`` or a bad decimation is exit 2 naming
    ``--record``; a good one passes ``--check`` without creating the file (its folder is
    made, as for every output on the command line)."""
    from oralnav.daemon.main import run

    (tmp_path / "file").write_text("")
    assert run(["--check", "--record", str(tmp_path / "file" / "x.mcap")]) == 2
    assert "--record" in (err := capsys.readouterr().err) and "cannot create folder" in err
    assert run(["--check", "--record", str(tmp_path / "new" / "x.mcap")]) == 0
    assert (tmp_path / "new").is_dir() and not (tmp_path / "new" / "x.mcap").exists()
    capsys.readouterr()
    assert run(["--check", "--record", str(tmp_path / "x.txt")]) == 2
    assert ".mcap" in capsys.readouterr().err
    assert run(["--check", "--record", str(tmp_path / "x.mcap"), "--record-every", "0"]) == 2
    assert "every" in capsys.readouterr().err
    assert run(["--check", "--record", str(tmp_path / "x.mcap")]) == 0
    assert not (tmp_path / "x.mcap").exists()
