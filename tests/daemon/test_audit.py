"""The append-only audit log of operator commands (``oralnav.daemon.audit``).

Requirement (issue 4, REST API): one JSON line per command with UTC time, who, role,
method, path, a bounded body summary, status and result; O_APPEND + fsync, never truncated
or rewritten, thread-safe; a log that cannot be written is reported (the API then refuses).
"""

from __future__ import annotations

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
    path, body summary, HTTP status and result, as one JSON line."""
    path = tmp_path / "audit.jsonl"
    with AuditLog(path) as log:
        _rec(log, body=b'{"reason":  "test"}', client="127.0.0.1:5000")
    (rec,) = _lines(path)
    assert set(rec) == {"time", "who", "role", "client", "method", "path", "body", "status",
                        "result"}
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
    """issue 4 audit (config): a relative audit_log goes under $STATE_DIRECTORY (systemd)
    or else the working directory; an absolute one is kept."""
    assert resolve_audit_path("/var/log/a.jsonl", {}) == Path("/var/log/a.jsonl")
    assert resolve_audit_path("a.jsonl", {"STATE_DIRECTORY": "/var/lib/oralnav:/x"}) == \
        Path("/var/lib/oralnav/a.jsonl")
    monkeypatch.chdir(tmp_path)
    assert resolve_audit_path("a.jsonl", {}) == tmp_path / "a.jsonl"
