"""Issue 33 item 4, ``oralnav replay`` (``oralnav.cli.replay``): a session recording
replayed through the MCAP camera backend with the daemon's trackers, every pose compared
bit for bit; ``--json`` prints one object; a truncated file replays what is readable and
says so; a file that is not a recording is a clear error (exit 2). Each test's docstring
names the requirement it checks."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import anyio
import numpy as np
import pytest
from mcap.reader import make_reader

from oralnav.cli.main import run
from oralnav.control.vision.tracker import Tracker
from oralnav.daemon.recording import RecordingOptions, SessionRecorder
from oralnav.daemon.replay_compare import PoseComparison
from tests.daemon.tiny_cell import TinyCell

ROUNDS = 8


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    """A recording of the tiny cell: 8 rounds, small chunks (one image each) so that a
    cut lands inside the data."""
    from oralnav.daemon import recording as recording_mod

    path = tmp_path_factory.mktemp("replay") / "session.mcap"

    async def record() -> None:
        c = await TinyCell().start()
        try:
            rec = SessionRecorder(c.core, c.pipeline.sources)
            c.pipeline.taps.append(rec.tap)
            await c.rounds(1)
            rec.start(RecordingOptions(path), "test")
            await c.rounds(ROUNDS)
            rec.stop("test")
        finally:
            await c.close()

    chunk = recording_mod.CHUNK_BYTES
    recording_mod.CHUNK_BYTES = 64 * 1024
    try:
        anyio.run(record)
    finally:
        recording_mod.CHUNK_BYTES = chunk
    return path


def _json(capsys) -> dict:
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1, out
    return json.loads(out[0])


def test_json_reports_every_pose_identical(recording, capsys):
    """Item 3: ``oralnav replay FILE --json`` prints one object with frames, poses,
    identical and the largest differences; every pose is identical bit for bit (exit 0)."""
    assert run(["replay", str(recording), "--json"]) == 0
    doc = _json(capsys)
    assert {"frames", "poses", "identical", "max_translation_diff_mm",
            "max_rotation_diff_deg"} <= set(doc)
    assert doc["frames"] == 2 * ROUNDS and doc["rounds"] == ROUNDS
    assert doc["poses"] == doc["identical"] == ROUNDS
    assert doc["max_translation_diff_mm"] == 0.0 and doc["max_rotation_diff_deg"] == 0.0
    assert doc["frames_dropped"] == 0 and doc["truncated"] is False
    assert run(["replay", str(recording)]) == 0
    assert f"{ROUNDS} of {ROUNDS} poses identical bit for bit" in capsys.readouterr().out


def test_a_different_pose_is_reported_with_its_difference(recording, capsys, monkeypatch):
    """Item 3: a replay whose poses differ (here the tracker is made to report 1 um off)
    counts them, reports the largest translation and rotation differences and exits 1."""
    track = Tracker.track

    def off(self, images):
        out = track(self, images)
        for name, est in out.items():
            T = est.T_ref_field.copy()  # a copy: what the tracker keeps stays its own
            T[0, 3] += 1e-6
            out[name] = dataclasses.replace(est, T_ref_field=T)
        return out

    monkeypatch.setattr(Tracker, "track", off)
    assert run(["replay", str(recording), "--json"]) == 1
    doc = _json(capsys)
    assert doc["identical"] == 0 and doc["differing"] == ROUNDS
    assert doc["max_translation_diff_mm"] == pytest.approx(1e-3, rel=1e-6)
    assert doc["worst"]["pose"] == "T_C_RM"


def test_a_truncated_file_replays_what_is_readable_and_says_so(recording, tmp_path, capsys):
    """Item 3: a file cut in the middle of a chunk (a crash, a full disk) replays the
    rounds before the cut, bit for bit, and the report and stderr say it was truncated."""
    with open(recording, "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    mid = chunks[len(chunks) // 2]
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(recording.read_bytes()[:mid.chunk_start_offset + mid.chunk_length // 2])
    assert run(["replay", str(cut), "--json"]) == 0
    out = capsys.readouterr()
    doc = json.loads(out.out)
    assert doc["truncated"] is True and "cut short" in doc["truncation"]
    assert 1 <= doc["rounds"] < ROUNDS and doc["identical"] == doc["poses"] == doc["rounds"]
    assert f"warning: {cut} is truncated" in out.err


def test_a_file_that_is_no_recording_is_a_clear_error(tmp_path, capsys):
    """Item 3: a file that is not MCAP, a missing file, and an MCAP file without a
    session's description each exit 2 with one line naming the file and what is wrong."""
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"PK\x03\x04 this is a zip, not a recording" * 10)
    assert run(["replay", str(junk), "--json"]) == 2
    doc = _json(capsys)
    assert doc["exit"] == 2 and str(junk) in doc["error"] and "not an MCAP file" in doc["error"]
    assert run(["replay", str(tmp_path / "none.mcap")]) == 2
    assert "none.mcap: cannot open" in capsys.readouterr().err
    from mcap.writer import Writer

    other = tmp_path / "other.mcap"
    with open(other, "wb") as f:
        w = Writer(f)
        w.start()
        w.finish()
    assert run(["replay", str(other)]) == 2
    err = capsys.readouterr().err
    assert str(other) in err and "not a session recording" in err


def test_identical_means_every_bit():
    """Item 3: the comparison counts a pose identical only when all 16 float64 are the
    recorded bits (-0.0 is not 0.0); a missing or extra field is counted apart."""
    T = np.eye(4)
    T[:3, 3] = [0.1, -0.0, 0.3]
    cmp = PoseComparison()
    assert cmp.add("r1", "T_C_RM", T.reshape(-1).tolist(), T.copy())
    U = T.copy()
    U[1, 3] = 0.0
    assert not cmp.add("r2", "T_C_RM", T.reshape(-1).tolist(), U)
    cmp.add("r3", "T_C_OM", T, None)
    cmp.add("r3", "T_C_EM", None, T)
    s = cmp.summary()
    assert (s["poses"], s["identical"], s["differing"], s["missing"], s["extra"]) == \
        (3, 1, 1, 1, 1)
    assert s["max_translation_diff_mm"] == 0.0 and not cmp.all_identical
