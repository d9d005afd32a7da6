"""The append-only audit log of operator commands (``oralnav.daemon.audit``).

Requirement (issue 4, REST API): one JSON line per command with UTC time, who, role,
method, path, a bounded body summary, status and result; O_APPEND + fsync, never truncated
or rewritten, thread-safe; a log that cannot be written is reported (the API then refuses).
"""

from __future__ import annotations

import contextlib
import errno
import json
import logging
import stat
import threading
from datetime import datetime
from pathlib import Path

import pytest

from oralnav.daemon import audit as audit_mod
from oralnav.daemon.audit import (
    BODY_SUMMARY_CHARS,
    RECORD_KEYS,
    AuditError,
    AuditLog,
    resolve_audit_path,
    summarize_body,
)


def _lines(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def _rec(log: AuditLog, **kw) -> dict:
    args = dict(who="alice", role="operator", method="POST", path="/reset", status=200,
                result="ok")
    args.update(kw)
    return log.record(**args)


def test_record_is_one_json_line_with_every_field(tmp_path):
    """issue 4 audit: a record holds ISO 8601 UTC wall time, who, role, client, method,
    path, body summary, HTTP status and result, as one JSON line. issue 30: and its id and
    phase (a record that stands alone is "single")."""
    path = tmp_path / "audit.jsonl"
    with AuditLog(path) as log:
        _rec(log, body=b'{"reason":  "test"}', client="127.0.0.1:5000")
    (rec,) = _lines(path)
    assert tuple(rec) == RECORD_KEYS == ("time", "id", "phase", "who", "role", "client",
                                         "method", "path", "body", "status", "result")
    assert rec["phase"] == "single" and rec["id"]
    assert rec["time"].endswith("Z")
    t = datetime.fromisoformat(rec["time"].replace("Z", "+00:00"))
    assert t.utcoffset().total_seconds() == 0
    assert (rec["who"], rec["role"], rec["method"], rec["path"], rec["status"]) == \
        ("alice", "operator", "POST", "/reset", 200)
    assert rec["body"] == '{"reason":"test"}' and rec["client"] == "127.0.0.1:5000"
    assert stat.S_IMODE(path.stat().st_mode) == 0o600


def test_constructor_does_no_io(tmp_path):
    """issue 4 audit (lifecycle): constructing an AuditLog creates no file; open() does,
    and close() is idempotent."""
    path = tmp_path / "audit.jsonl"
    log = AuditLog(path)
    assert not path.exists() and not log.is_open
    log.open()
    log.open()
    assert path.exists() and log.is_open
    log.close()
    log.close()
    assert not log.is_open


def test_earlier_lines_are_never_lost(tmp_path):
    """issue 4 audit: opening appends (O_APPEND, no truncation): lines from earlier runs
    stay byte for byte, and a torn last line from a crash is closed, not glued to."""
    path = tmp_path / "audit.jsonl"
    path.write_text('{"old": 1}\n{"torn": ')
    with AuditLog(path) as log:
        _rec(log)
    with AuditLog(path) as log:
        _rec(log, path="/estop")
    text = path.read_text()
    assert text.startswith('{"old": 1}\n{"torn": \n')
    last = [json.loads(x) for x in text.splitlines()[2:]]
    assert [r["path"] for r in last] == ["/reset", "/estop"]


def test_body_summary_is_bounded_and_one_line():
    """issue 4 audit: the body summary is compact JSON when it parses, one line otherwise,
    and never longer than the bound (plus a short note of what was cut)."""
    assert summarize_body(b"") == "" and summarize_body(None) == ""
    assert summarize_body(b'{ "a" : [1, 2] }') == '{"a":[1,2]}'
    assert summarize_body(b"not\njson \xff") == "not json \ufffd"
    long = summarize_body(json.dumps({"k": "x" * 5000}).encode())
    assert len(long) < BODY_SUMMARY_CHARS + 30 and long.endswith("chars)")


def test_a_record_is_one_line_for_any_reader(tmp_path):
    """issue 30 (fuzzing): a body holding characters that some readers take for line ends
    (U+0085, U+2028, U+2029; Python's str.splitlines among them) is escaped, so every
    record reads as one line however the file is split, and parses back unchanged."""
    path = tmp_path / "audit.jsonl"
    text = "a\x85b\u2028c\u2029d\x1ce\x0bf"
    with AuditLog(path) as log:
        _rec(log, body=json.dumps({"k": text}, ensure_ascii=False).encode("utf-8"))
        _rec(log)
    first, second = path.read_text(encoding="utf-8").splitlines()
    assert json.loads(json.loads(first)["body"]) == {"k": text}
    assert json.loads(second)["path"] == "/reset"


def test_concurrent_writers_never_interleave(tmp_path):
    """issue 4 audit: records from many threads land whole, one per line, none lost."""
    path = tmp_path / "audit.jsonl"
    with AuditLog(path) as log:
        def work(k: int) -> None:
            for i in range(25):
                _rec(log, who=f"t{k}", result=str(i), body=b"x" * 300)

        threads = [threading.Thread(target=work, args=(k,)) for k in range(8)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    recs = _lines(path)
    assert len(recs) == 200
    for k in range(8):
        assert [r["result"] for r in recs if r["who"] == f"t{k}"] == [str(i) for i in range(25)]


def test_check_refuses_when_closed_or_disk_nearly_full(tmp_path):
    """issue 4 audit: check() raises AuditError (the API then answers 503) while the log is
    closed or its disk has less than min_free_bytes left."""
    log = AuditLog(tmp_path / "audit.jsonl", min_free_bytes=1 << 62)
    with pytest.raises(AuditError, match="not open"):
        log.check()
    with log:
        with pytest.raises(AuditError, match="bytes free"):
            log.check()
    with AuditLog(tmp_path / "audit.jsonl", min_free_bytes=0) as ok:
        ok.check()


def test_failed_record_is_kept_journaled_and_retried(tmp_path, monkeypatch, caplog):
    """issue 4 audit: a record that cannot be written raises AuditError, goes to the
    journal (ERROR log), blocks check() until it can be written, and is then written
    before newer records, so nothing is lost and the order holds."""
    path = tmp_path / "audit.jsonl"
    real_write = audit_mod.os.write

    def full(fd, data):
        raise OSError(errno.ENOSPC, "No space left on device")

    with AuditLog(path) as log:
        _rec(log, result="first")
        monkeypatch.setattr(audit_mod.os, "write", full)
        with caplog.at_level(logging.ERROR, logger=audit_mod.__name__):
            with pytest.raises(AuditError, match="No space left"):
                _rec(log, result="second")
        assert "second" in caplog.text and log.pending == 1
        with pytest.raises(AuditError, match="1 record"):
            log.check()
        with pytest.raises(AuditError):  # newer records queue behind it
            _rec(log, result="third")
        monkeypatch.setattr(audit_mod.os, "write", real_write)
        log.check()
        assert log.pending == 0
        _rec(log, result="fourth")
    assert [r["result"] for r in _lines(path)] == ["first", "second", "third", "fourth"]


def test_short_write_is_closed_by_the_next_record(tmp_path, monkeypatch):
    """issue 4 audit: a write cut short (disk full mid-line) leaves a torn line that the
    retried record starts after, on a fresh line."""
    path = tmp_path / "audit.jsonl"
    real_write = audit_mod.os.write
    calls = {"n": 0}

    def short_then_fail(fd, data):
        calls["n"] += 1
        if calls["n"] == 1:
            return real_write(fd, bytes(data[:10]))
        raise OSError(errno.ENOSPC, "No space left on device")

    with AuditLog(path) as log:
        monkeypatch.setattr(audit_mod.os, "write", short_then_fail)
        with pytest.raises(AuditError):
            _rec(log, result="cut")
        monkeypatch.setattr(audit_mod.os, "write", real_write)
        log.check()
    lines = path.read_text().splitlines()
    assert len(lines) == 2 and json.loads(lines[1])["result"] == "cut"


def test_audit_path_is_state_not_config(tmp_path, monkeypatch):
    """issue 4 audit (config), issue 33 item 6: a relative audit_log goes under
    $STATE_DIRECTORY (systemd), else the user's state folder ($XDG_STATE_HOME/oralnav,
    else ~/.local/state/oralnav), never the working directory; an absolute one is kept.
    The default folder is created (0700) when the log is opened; no other is."""
    assert resolve_audit_path("/var/log/a.jsonl", {}) == Path("/var/log/a.jsonl")
    assert resolve_audit_path("a.jsonl", {"STATE_DIRECTORY": "/var/lib/oralnav:/x"}) == \
        Path("/var/lib/oralnav/a.jsonl")
    monkeypatch.chdir(tmp_path)
    assert resolve_audit_path("a.jsonl", {"XDG_STATE_HOME": "/st"}) == \
        Path("/st/oralnav/a.jsonl")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    monkeypatch.delenv("XDG_STATE_HOME", raising=False)
    monkeypatch.delenv("STATE_DIRECTORY", raising=False)
    path = resolve_audit_path("a.jsonl")
    assert path == tmp_path / "home/.local/state/oralnav/a.jsonl"
    AuditLog(path).open().close()
    assert path.exists() and (path.parent.stat().st_mode & 0o777) == 0o700
    with pytest.raises(AuditError, match="cannot open audit log"):
        AuditLog(tmp_path / "elsewhere/a.jsonl").open()  # not ours to create


# -- issue 30: write-ahead, a torn last line, rotation ------------------------------------
def _intent(log: AuditLog, path: str = "/procedure/start") -> str:
    return log.intent(who="alice", role="operator", method="POST", path=path,
                      body=b'{"k": 1}', client="127.0.0.1:5000")


def test_intent_then_outcome_share_an_id(tmp_path):
    """issue 30, write-ahead: a command's intent is written (fsynced) before it runs, with
    status null, and its outcome after, with the same id; the body is in the intent."""
    path = tmp_path / "audit.jsonl"
    with AuditLog(path) as log:
        rid = _intent(log)
        assert [r["phase"] for r in _lines(path)] == ["intent"]  # on disk before it runs
        _rec(log, path="/procedure/start", outcome_of=rid)
        other = _intent(log)
    intent, outcome, second = _lines(path)
    assert intent["id"] == outcome["id"] == rid != second["id"] == other
    assert (intent["phase"], intent["status"], intent["body"]) == ("intent", None, '{"k":1}')
    assert (outcome["phase"], outcome["status"], outcome["result"]) == ("outcome", 200, "ok")
    assert outcome["body"] == ""


def test_an_intent_is_refused_when_the_log_is_not_ready(tmp_path, monkeypatch):
    """issue 30, write-ahead: intent() fails (so the command does not run) while the log is
    closed or its disk is nearly full (nothing written), or when the write fails (the
    error names the id when part of it may be in the file); a failed intent is never
    queued for retry, since its command never ran."""
    path = tmp_path / "audit.jsonl"
    log = AuditLog(path, min_free_bytes=1 << 62)
    with pytest.raises(AuditError, match="not open") as ei:
        _intent(log)
    assert ei.value.record_id is None
    with log:
        with pytest.raises(AuditError, match="bytes free"):
            _intent(log)
        log.min_free_bytes = 0

        def full(fd, data):
            raise OSError(errno.ENOSPC, "No space left on device")

        monkeypatch.setattr(audit_mod.os, "write", full)
        with pytest.raises(AuditError, match="No space left") as ei:
            _intent(log)
        assert ei.value.record_id is None and log.pending == 0  # not a byte landed

        def fsync_fails(fd):
            raise OSError(errno.EIO, "Input/output error")

        monkeypatch.undo()
        monkeypatch.setattr(audit_mod.os, "fsync", fsync_fails)
        with pytest.raises(AuditError, match="Input/output") as ei:
            _intent(log)
        assert ei.value.record_id and log.pending == 0


def test_an_intent_without_outcome_is_counted_and_logged_once(tmp_path, caplog):
    """issue 30, write-ahead: a crash between a command's intent and its outcome (simulated:
    the intent written, the outcome never) is found when the log is next opened: logged
    at WARNING with its id and path, counted in `incomplete`, and closed by an appended
    outcome of unknown status, so that the start after that does not count it again."""
    path = tmp_path / "audit.jsonl"
    with AuditLog(path) as log:
        done = _intent(log, "/reset")
        _rec(log, outcome_of=done)
        lost = _intent(log, "/procedure/start")
        assert log.incomplete == 0
    with caplog.at_level(logging.WARNING, logger=audit_mod.__name__):
        with AuditLog(path) as log:
            assert log.incomplete == 1 and log.incomplete_ids == (lost,)
    (warning,) = [r for r in caplog.records if r.levelno == logging.WARNING]
    assert "1 command(s) have an intent but no outcome" in warning.getMessage()
    assert lost in warning.getMessage() and "/procedure/start" in warning.getMessage()
    closing = _lines(path)[-1]
    assert (closing["id"], closing["phase"], closing["status"]) == (lost, "outcome", None)
    assert closing["result"].startswith("unknown")
    caplog.clear()
    with AuditLog(path) as log:
        assert log.incomplete == 0
    assert not caplog.records


def test_an_intent_left_in_the_previous_file_is_found(tmp_path, monkeypatch):
    """issue 30: the scan reads the previous (rotated) file's end when the current file is
    short, so an intent written just before a rotation is still found; a long current
    file is scanned only within the bounded tail (TAIL_SCAN_BYTES)."""
    path = tmp_path / "audit.jsonl"
    with AuditLog(path, max_bytes=4096) as log:
        lost = _intent(log)
        while not (tmp_path / "audit.jsonl.1").exists():
            _rec(log, body=b"x" * 200)
    with AuditLog(path, max_bytes=4096) as log:
        assert log.incomplete_ids == (lost,)
    # beyond the bounded tail an intent is not looked for (nor is the file read whole)
    monkeypatch.setattr(audit_mod, "TAIL_SCAN_BYTES", 2048)
    path2 = tmp_path / "long.jsonl"
    with AuditLog(path2) as log:
        _intent(log)
        for _ in range(20):
            _rec(log, body=b"x" * 200)
    with AuditLog(path2) as log:
        assert log.incomplete == 0


def test_a_torn_last_line_is_logged_with_its_offset(tmp_path, caplog):
    """issue 30: a last line cut by a crash mid-write is reported at open (WARNING naming
    the file and the byte offset where the torn record starts); its bytes stay as they
    are and the next record starts on a new line."""
    path = tmp_path / "audit.jsonl"
    whole = '{"old": 1}\n'
    path.write_text(whole + '{"time": "2025-01-31T09:1')
    with caplog.at_level(logging.WARNING, logger=audit_mod.__name__):
        with AuditLog(path) as log:
            assert log.torn_at == len(whole)
            _rec(log)
    (warning,) = caplog.records
    assert str(path) in warning.getMessage()
    assert f"from byte offset {len(whole)}" in warning.getMessage()
    lines = path.read_text().splitlines()
    assert lines[:2] == ['{"old": 1}', '{"time": "2025-01-31T09:1']
    assert json.loads(lines[2])["path"] == "/reset"
    caplog.clear()
    with AuditLog(path) as log:
        assert log.torn_at is None
    assert not caplog.records


def _all_records(path: Path, keep: int) -> list[dict]:
    """Every record of the log, oldest file first."""
    out = []
    for k in range(keep, 0, -1):
        p = path.with_name(f"{path.name}.{k}")
        if p.exists():
            out += _lines(p)
    return out + (_lines(path) if path.exists() else [])


def test_rotation_bounds_the_files_and_keeps_records_in_order(tmp_path):
    """issue 30: past max_bytes the file is rotated (audit.jsonl -> .1 -> ... -> .<keep>,
    the oldest dropped): no file grows past max_bytes, at most keep + 1 files exist, and
    the records in them are the newest ones, whole, in order."""
    path = tmp_path / "audit.jsonl"
    with AuditLog(path, max_bytes=4096, keep=3) as log:
        for i in range(80):
            _rec(log, result=str(i), body=b"x" * 100)
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == ["audit.jsonl", "audit.jsonl.1", "audit.jsonl.2", "audit.jsonl.3"]
    assert all(p.stat().st_size <= 4096 for p in tmp_path.iterdir())
    got = [int(r["result"]) for r in _all_records(path, 3)]
    assert got == list(range(80 - len(got), 80)) and len(got) > 30
    # with room for them all, none is dropped
    path = tmp_path / "all" / "audit.jsonl"
    path.parent.mkdir()
    with AuditLog(path, max_bytes=4096, keep=100) as log:
        for i in range(80):
            _rec(log, result=str(i), body=b"x" * 100)
    assert [int(r["result"]) for r in _all_records(path, 100)] == list(range(80))


class _Crash(BaseException):
    """The process dies here (not an OSError: no clean-up code runs)."""


def _rotation_steps(monkeypatch, crash_at: int | None) -> list[str]:
    """Count (and crash at) the steps a rotation takes: renames, folder fsyncs, the new
    file's fsync."""
    steps: list[str] = []
    real_replace, real_fsync_dir = audit_mod.os.replace, audit_mod._fsync_dir

    def step(name: str) -> None:
        steps.append(name)
        if len(steps) == crash_at:
            raise _Crash(name)

    def replace(src, dst):
        step(f"replace {Path(src).name} -> {Path(dst).name}")
        real_replace(src, dst)

    def fsync_dir(folder):
        step("fsync folder")
        real_fsync_dir(folder)

    monkeypatch.setattr(audit_mod.os, "replace", replace)
    monkeypatch.setattr(audit_mod, "_fsync_dir", fsync_dir)
    return steps


def _fill_until_rotation(log: AuditLog, acked: list[str]) -> None:
    """Write records until one asks for a rotation (which may crash); ``acked`` gets the
    result of each record written."""
    while True:
        size = log.path.stat().st_size
        name = f"r{len(acked)}"
        _rec(log, result=name, body=b"x" * 150)
        acked.append(name)
        if log.path.stat().st_size < size:
            return


@pytest.mark.parametrize("crash_at", range(1, 6))
def test_a_crash_at_any_step_of_a_rotation_loses_no_record(tmp_path, monkeypatch, crash_at):
    """issue 30: rotation never loses a record: the process is killed before each step of
    a rotation in turn (the second rotation, so that .1 -> .2 moves too); reopening
    finishes or abandons the rotation, and every record that was acknowledged is in the
    files, in order, and the log goes on."""
    path = tmp_path / "audit.jsonl"
    acked: list[str] = []
    log = AuditLog(path, max_bytes=4096, keep=20).open()
    _fill_until_rotation(log, acked)  # the first rotation, uncrashed
    steps = _rotation_steps(monkeypatch, crash_at)
    fds: list[int] = []
    real_open = audit_mod.os.open
    monkeypatch.setattr(audit_mod.os, "open",
                        lambda *a, **k: fds.append(real_open(*a, **k)) or fds[-1])
    with pytest.raises(_Crash):
        _fill_until_rotation(log, acked)
    assert len(steps) == crash_at, steps
    monkeypatch.undo()
    for fd in [log._fd, *fds]:  # the dead process's files close with it
        with contextlib.suppress(OSError):
            audit_mod.os.close(fd)
    log._fd = None
    with AuditLog(path, max_bytes=4096, keep=20) as log2:
        for i in range(60):  # enough for further rotations
            _rec(log2, result=f"after{i}")
    assert not (tmp_path / "audit.jsonl.new").exists()
    assert [r["result"] for r in _all_records(path, 20)] == \
        acked + [f"after{i}" for i in range(60)]


def test_the_steps_of_a_rotation(tmp_path, monkeypatch):
    """issue 30: a rotation makes the new file durable before the old one moves: the
    steps, in order, as the crash test above walks them."""
    path = tmp_path / "audit.jsonl"
    acked: list[str] = []
    with AuditLog(path, max_bytes=4096, keep=4) as log:
        _fill_until_rotation(log, acked)
        steps = _rotation_steps(monkeypatch, None)
        _fill_until_rotation(log, acked)
    assert steps == ["replace audit.jsonl.1 -> audit.jsonl.2", "fsync folder",
                     "replace audit.jsonl -> audit.jsonl.1",
                     "replace audit.jsonl.new -> audit.jsonl", "fsync folder"]


def test_a_failed_rotation_keeps_writing_the_old_file(tmp_path, monkeypatch, caplog):
    """issue 30: a rotation that fails (an OSError on a rename) puts the old file back; the
    record that asked for it is kept and retried like any failed write, and nothing is
    lost or reordered."""
    path = tmp_path / "audit.jsonl"
    real_replace = audit_mod.os.replace

    def replace(src, dst):
        if Path(src).name == "audit.jsonl.new":
            raise OSError(errno.EIO, "Input/output error")
        real_replace(src, dst)

    acked: list[str] = []
    with AuditLog(path, max_bytes=4096, keep=2) as log:
        monkeypatch.setattr(audit_mod.os, "replace", replace)
        with caplog.at_level(logging.ERROR, logger=audit_mod.__name__):
            with pytest.raises(AuditError, match="Input/output"):
                _fill_until_rotation(log, acked)
        assert log.pending == 1 and path.exists()
        assert not (tmp_path / "audit.jsonl.new").exists()
        monkeypatch.undo()
        log.check()
        _rec(log, result="last")
    got = [r["result"] for r in _all_records(path, 2)]
    assert got == acked + [f"r{len(acked)}", "last"]  # the failed one, then the next
