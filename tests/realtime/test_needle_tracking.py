"""The needle tracking task (issue 36, item 1: "the tracker runs in the daemon's task
structure ... with its own watchdog"): frames come in capture order with their arrival
times, capture overlaps tracking, and a stalled stream or a dead tracker reaches the step
as a named ``ServoStop`` within its timeout, never as an old frame.
"""

from __future__ import annotations

import threading
import time

import pytest

from oralnav.control.needle.servo import ServoStop
from oralnav.realtime.needle_tracking import NeedleTrackingTask, start_tracking


def _task(capture_s: float = 0.0, track_s: float = 0.0, stall_after: int | None = None,
          fail_at: int | None = None):
    """A task on stand-ins: ``capture`` numbers its frames and sleeps ``capture_s``
    (blocking for good from frame ``stall_after`` on), ``track`` sleeps ``track_s`` and
    returns (meta, previous meta), raising at frame ``fail_at`` once ``release`` is set
    (so the test has taken the frames before it)."""
    count = {"n": 0}
    release = threading.Event()

    def capture():
        count["n"] += 1
        if stall_after is not None and count["n"] > stall_after:
            release.wait()
        time.sleep(capture_s)
        return f"image {count['n']}", count["n"]

    def track(payload, meta, previous):
        assert payload == f"prepared image {meta}"
        if meta == fail_at:
            release.wait(5.0)
            raise RuntimeError("test: the tracker broke")
        time.sleep(track_s)
        return (meta, previous)

    task = start_tracking(capture, lambda images: f"prepared {images}", track)
    return task, release


def test_frames_come_newest_first_in_capture_order_with_their_times():
    """Each ``next(after)`` is a frame newer than ``after``; its track saw the frame
    tracked before it as the previous one (no frame tracked twice or out of order), and
    its arrival stamp precedes its publication."""
    task, _ = _task(0.002, 0.002)
    try:
        seq, seen = 0, []
        for _ in range(10):
            fr = task.next(seq, timeout=2.0)
            assert fr.seq > seq
            assert fr.stamp <= fr.tracked_at
            seen.append(fr)
            seq = fr.seq
    finally:
        task.stop()
    metas = [fr.track[0] for fr in seen]
    assert metas == sorted(metas) and len(set(metas)) == len(metas)
    for fr in seen:
        meta, previous = fr.track
        assert previous == (None if meta == 1 else meta - 1)
    assert len(task.track_s) >= 10 and all(w > 0 for w in task.track_s)
    assert len(task.prepare_s) >= len(task.track_s)


def test_capture_overlaps_tracking():
    """The grabber captures the next frame while the tracker works on the last: with 40
    ms each, frames are tracked about every 40 ms, not every 80."""
    task, _ = _task(0.04, 0.04)
    try:
        fr = task.next(0, timeout=2.0)
        t0, first = time.monotonic(), fr.seq
        for _ in range(8):
            fr = task.next(fr.seq, timeout=2.0)
        per_frame = (time.monotonic() - t0) / (fr.seq - first)
    finally:
        task.stop()
    assert per_frame < 0.065, per_frame


def test_a_stalled_stream_is_stale_within_the_timeout():
    """Issue 36, bad input: a frame stream that stalls. After frame 3 the capture blocks;
    the step's wait for a newer frame ends at its timeout with ``stale``, naming the
    last frame and its age, instead of handing the old frame again."""
    task, release = _task(stall_after=3)
    try:
        seq = 0
        while seq < 3:
            seq = task.next(seq, timeout=2.0).seq
        t0 = time.monotonic()
        with pytest.raises(ServoStop) as err:
            task.next(seq, timeout=0.2)
        waited = time.monotonic() - t0
    finally:
        release.set()
        task.stop()
    assert err.value.cause == "stale"
    assert "frame 3" in err.value.detail and "ms ago" in err.value.detail, err.value.detail
    assert 0.19 <= waited < 1.0, waited


def test_a_tracker_that_raises_ends_the_task_named():
    """An error in the tracking thread ends the task: the step's next wait raises
    ``tracker_failed`` with the error's type and message at once (not after the
    timeout), and stop() still returns."""
    task, release = _task(fail_at=2)
    fr = task.next(0, timeout=2.0)
    release.set()
    t0 = time.monotonic()
    with pytest.raises(ServoStop) as err:
        task.next(fr.seq, timeout=5.0)
    assert time.monotonic() - t0 < 1.0
    assert err.value.cause == "tracker_failed"
    assert "RuntimeError: test: the tracker broke" in err.value.detail
    assert task.stop().seq == 1
    assert task.stop().seq == 1        # twice is harmless


def test_stop_joins_both_threads_and_a_stopped_task_hands_out_nothing():
    task = NeedleTrackingTask(lambda: ("i", 1), lambda images: images,
                              lambda p, m, prev: m, name="test-tracking").start()
    task.next(0, timeout=2.0)
    task.stop()
    assert not any(t.name.startswith("test-tracking") for t in threading.enumerate())
    with pytest.raises(ServoStop) as err:
        task.next(10**9, timeout=0.5)
    assert err.value.cause == "stale" and "stopped" in err.value.detail
