"""Tests of ``oralnav.safety.stop``: the latched stop fan-out.

Each test's docstring names the requirement it checks (Issue 4: safety).
"""

from __future__ import annotations

import json
import logging
import threading

import pytest

from oralnav.safety.errors import InputError, StateError
from oralnav.safety.stop import LatchedStop, StopRecord


class Recorder:
    """A stop handler that counts its calls (thread-safe) and may fail."""

    def __init__(self, fail: int = 0) -> None:
        self.calls: list[StopRecord | None] = []
        self.fail = fail  # fail this many calls first
        self._lock = threading.Lock()

    def __call__(self, record: StopRecord) -> None:
        with self._lock:
            self.calls.append(record)
            if self.fail > 0:
                self.fail -= 1
                raise RuntimeError("arm socket closed")


def test_trigger_latches_and_calls_every_handler_once():
    """Issue 4 safety (stop fan-out): the first trigger latches the stop and calls every
    handler, with no argument or with the StopRecord, as the handler takes."""
    stop = LatchedStop()
    bare: list[int] = []
    rec = Recorder()
    stop.add_handler(lambda: bare.append(1), name="brake")
    stop.add_handler(rec, name="arm")
    assert not stop.latched and stop.first is None
    assert stop.trigger(1.0, "stale_pose:opener", "pose is 0.2 s old") is True
    assert stop.latched
    assert bare == [1]
    assert rec.calls == [StopRecord(1.0, "stale_pose:opener", "pose is 0.2 s old")]
    assert stop.first == rec.calls[0]
    assert stop.unconfirmed == ()


def test_failing_handler_does_not_prevent_the_others(caplog):
    """Issue 4 safety (stop fan-out): each handler runs in its own try/except; one that
    raises is logged and every other handler is still called; trigger never raises."""
    stop = LatchedStop()
    first, bad, last = Recorder(), Recorder(fail=99), Recorder()
    stop.add_handler(first, "first")
    stop.add_handler(bad, "bad")
    stop.add_handler(last, "last")
    with caplog.at_level(logging.ERROR, logger="oralnav.safety.stop"):
        stop.trigger(0.5, "estop", "button")
    assert len(first.calls) == len(bad.calls) == len(last.calls) == 1
    assert "stop handler bad failed" in caplog.text and "arm socket closed" in caplog.text
    assert stop.unconfirmed == ("bad",)
    assert stop.snapshot()["unconfirmed"] == ["bad"]


def test_retrigger_records_reason_and_retries_only_failed_handlers():
    """Issue 4 safety (re-trigger policy): while latched, a trigger records its reason;
    handlers that already succeeded are not called again, a handler that failed is
    retried until it succeeds once."""
    stop = LatchedStop()
    ok, flaky = Recorder(), Recorder(fail=1)
    stop.add_handler(ok, "ok")
    stop.add_handler(flaky, "flaky")
    assert stop.trigger(1.0, "a", "first") is True
    assert stop.trigger(2.0, "b", "second") is False  # already latched
    assert stop.trigger(3.0, "c", "third") is False
    assert len(ok.calls) == 1
    assert len(flaky.calls) == 2  # failed once, succeeded on the retry, then left alone
    assert [r.reason for r in stop.records] == ["first", "second", "third"]
    assert stop.first.reason == "first"
    assert stop.unconfirmed == ()


def test_trigger_never_raises_on_bad_arguments():
    """Issue 4 safety (nothing on the stop path raises): malformed arguments still latch
    the stop and call the handlers."""
    stop = LatchedStop()
    rec = Recorder()
    stop.add_handler(rec)

    class Bad:
        def __float__(self):
            raise ValueError("no")

    assert stop.trigger(Bad(), None, None) is True  # type: ignore[arg-type]
    assert stop.latched and len(rec.calls) == 1
    json.dumps(stop.snapshot())  # NaN time reported as null, still JSON


def test_clear_needs_who_and_rearms():
    """Issue 4 safety (clear via reset only, with who): clear without an operator name is
    refused and changes nothing; after clear, the next trigger calls every handler again."""
    stop = LatchedStop()
    rec = Recorder()
    stop.add_handler(rec)
    stop.trigger(1.0, "x", "y")
    with pytest.raises(StateError, match="operator"):
        stop.clear(2.0, "")
    assert stop.latched
    assert stop.clear(2.0, "dr.smith") is True
    assert not stop.latched and stop.records == () and stop.first is None
    assert stop.clear(2.5, "dr.smith") is False  # idempotent
    stop.trigger(3.0, "x", "again")
    assert len(rec.calls) == 2


def test_handler_added_while_latched_is_called_at_once():
    """Issue 4 safety (latched fan-out): a handler registered while the stop is latched
    (a driver that reconnects) is told to stop at once."""
    stop = LatchedStop()
    stop.trigger(1.0, "estop", "button")
    rec = Recorder()
    stop.add_handler(rec, "late")
    assert [r.reason for r in rec.calls] == ["button"]
    assert stop.remove_handler(rec) is True and stop.remove_handler(rec) is False


def test_handler_signature_is_checked_at_registration():
    """Issue 4 safety (clear errors): a handler that takes neither zero arguments nor one
    is refused when registered, not when the stop fires."""
    stop = LatchedStop()
    with pytest.raises(InputError, match="no argument or one StopRecord"):
        stop.add_handler(lambda a, b: None)
    with pytest.raises(InputError, match="not callable"):
        stop.add_handler(42)  # type: ignore[arg-type]


def test_handler_may_read_or_retrigger_the_stop_without_deadlock():
    """Issue 4 safety (never blocks): handlers run outside the stop's lock, so a handler
    that reads the stop or triggers it again returns."""
    stop = LatchedStop()
    seen = []

    def handler(record: StopRecord) -> None:
        seen.append(stop.snapshot()["latched"])
        stop.trigger(record.time, "nested", "from a handler")

    stop.add_handler(handler)
    stop.trigger(1.0, "a", "b")
    assert seen == [True]
    assert [r.source for r in stop.records] == ["a", "nested"]


def test_concurrent_triggers_call_each_handler_exactly_once():
    """Issue 4 safety (thread-safe, idempotent): many threads triggering at once latch the
    stop once; every handler runs exactly once and every reason is recorded."""
    stop = LatchedStop(max_records=1000)
    handlers = [Recorder() for _ in range(5)]
    for i, h in enumerate(handlers):
        stop.add_handler(h, f"h{i}")
    n = 16
    barrier = threading.Barrier(n)
    firsts: list[bool] = []
    lock = threading.Lock()

    def worker(i: int) -> None:
        barrier.wait()
        for k in range(20):
            r = stop.trigger(float(k), f"t{i}", f"trip {k}")
            with lock:
                firsts.append(r)

    threads = [threading.Thread(target=worker, args=(i,)) for i in range(n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sum(firsts) == 1
    assert all(len(h.calls) == 1 for h in handlers)
    assert len(stop.records) == n * 20


def test_records_are_bounded():
    """Issue 4 safety (bounded memory): a watchdog tripping every period while latched
    keeps only the latest records; the first (the cause) is kept apart."""
    stop = LatchedStop(max_records=4)
    for k in range(100):
        stop.trigger(float(k), "w", f"trip {k}")
    assert [r.reason for r in stop.records] == [f"trip {k}" for k in range(96, 100)]
    assert stop.first.reason == "trip 0"
    assert stop.snapshot()["triggers"] == 100


def test_escalation_calls_every_handler_again():
    """Issue 4 safety (re-trigger policy): an escalating trigger (FAULT becoming ESTOP)
    calls every handler again, even those that already succeeded."""
    stop = LatchedStop()
    rec = Recorder()
    stop.add_handler(rec)
    stop.trigger(1.0, "stale_pose:opener", "old")
    stop.trigger(2.0, "stale_pose:opener", "older")
    assert len(rec.calls) == 1
    assert stop.trigger(3.0, "input", "e-stop pressed", escalate=True) is False
    assert [r.reason for r in rec.calls] == ["old", "e-stop pressed"]
