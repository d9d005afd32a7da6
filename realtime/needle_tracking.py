"""The needle tracker as a task of its own (issue 36, item 1): while a servoed motion runs,
one thread captures the views and another tracks them, frame after frame, and the step
that moves the arm takes the newest tracked frame when it wants one, instead of stopping
the arm to look.

Two threads, a pipeline one frame deep: the *grabber* captures a frame (``capture``: the
views) and reduces it to what the tracker reads (``prepare``) as soon as the last one was
taken by the *tracker*,
which predicts and updates the particle filter on it (``track``) and publishes it. So
capture and tracking overlap on the two cores, and the tracker always works on the
newest views but one. The callables are the procedure's
(:mod:`oralnav.control.needle.procedure.feed` says what each does); this module only
runs them, times them and guards the hand-over.

The watchdog is the step's wait: :meth:`NeedleTrackingTask.next` gives up after its
timeout (a stalled stream: ``stale``), and an error in either thread ends the task and is
raised to the step as ``tracker_failed`` with its type and message, so a servoed motion
never goes on on an old pose or a dead tracker. Clock: ``time.monotonic`` (s).
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

from oralnav.control.needle.procedure.feed import Capture, Prepare, Track, TrackedFrame
from oralnav.control.needle.servo import ServoStop

log = logging.getLogger(__name__)

__all__ = ["NeedleTrackingTask", "start_tracking"]


class NeedleTrackingTask:
    """Runs ``capture`` and ``track`` (see the module docstring) until :meth:`stop`.
    Implements :class:`~oralnav.control.needle.procedure.feed.TrackingFeed`.
    ``prepare_s`` and ``track_s``: the seconds each frame's ``prepare`` and ``track``
    took, in order: the daemon's own work on a frame (the capture itself is the camera's,
    here the renderer's). The two run at once, so a camera-fed task keeps up with frames
    as fast as the slower of the two."""

    def __init__(self, capture: Capture, prepare: Prepare, track: Track,
                 name: str = "needle-tracking") -> None:
        self._capture = capture
        self._prepare = prepare
        self._track = track
        self._cond = threading.Condition()
        # captured and prepared, not yet tracked: (seq, stamp, payload, meta)
        self._slot: tuple[int, float, Any, Any] | None = None
        self._latest: TrackedFrame | None = None
        self._error: BaseException | None = None
        self._stopping = False
        self._seq = 0
        self.prepare_s: list[float] = []
        self.track_s: list[float] = []
        self._threads = [threading.Thread(target=self._guarded, args=(loop,),
                                          name=f"{name}-{what}", daemon=True)
                         for what, loop in (("grab", self._grab), ("track", self._follow))]

    def start(self) -> NeedleTrackingTask:
        for t in self._threads:
            t.start()
        return self

    def _guarded(self, loop: Any) -> None:
        try:
            loop()
        except BaseException as exc:   # noqa: BLE001 - any error ends the task, named
            log.exception("needle tracking task failed")
            with self._cond:
                self._error = exc
                self._stopping = True
                self._cond.notify_all()

    def _grab(self) -> None:
        while True:
            with self._cond:
                # one frame ahead of the tracker: capture once the last one was taken
                while self._slot is not None and not self._stopping:
                    self._cond.wait()
                if self._stopping:
                    return
            images, meta = self._capture()
            # the frame's time is when its views arrived (a camera's, or the renderer's
            # stand-in for one): what the daemon does with them from here is its latency
            stamp = time.monotonic()
            payload = self._prepare(images)
            self.prepare_s.append(time.monotonic() - stamp)
            with self._cond:
                self._seq += 1
                self._slot = (self._seq, stamp, payload, meta)
                self._cond.notify_all()

    def _follow(self) -> None:
        previous: Any = None
        while True:
            with self._cond:
                while self._slot is None and not self._stopping:
                    self._cond.wait()
                if self._stopping:
                    return
                seq, stamp, payload, meta = self._slot
                self._slot = None
                self._cond.notify_all()
            t0 = time.monotonic()
            track = self._track(payload, meta, previous)
            done = time.monotonic()
            self.track_s.append(done - t0)
            previous = meta
            with self._cond:
                self._latest = TrackedFrame(seq, stamp, done, meta, track)
                self._cond.notify_all()

    def next(self, after: int, timeout: float) -> TrackedFrame:
        """See :meth:`~oralnav.control.needle.procedure.feed.TrackingFeed.next`."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                if self._error is not None:
                    raise ServoStop("tracker_failed", f"the tracking task stopped: "
                                    f"{type(self._error).__name__}: {self._error}")
                if self._latest is not None and self._latest.seq > after:
                    return self._latest
                if self._stopping:
                    raise ServoStop("stale", "the tracking task was stopped")
                left = deadline - time.monotonic()
                if left <= 0:
                    last = ("none tracked yet" if self._latest is None else
                            f"the last, frame {self._latest.seq}, captured "
                            f"{(time.monotonic() - self._latest.stamp) * 1e3:.0f} ms ago")
                    raise ServoStop("stale", f"no tracked frame newer than frame {after} "
                                             f"within {timeout * 1e3:.0f} ms ({last})")
                self._cond.wait(left)

    def stop(self) -> TrackedFrame | None:
        """See :meth:`~oralnav.control.needle.procedure.feed.TrackingFeed.stop`."""
        with self._cond:
            self._stopping = True
            self._cond.notify_all()
        for t in self._threads:
            if t.ident is not None and t is not threading.current_thread():
                t.join()
        return self._latest


def start_tracking(capture: Capture, prepare: Prepare, track: Track) -> NeedleTrackingTask:
    """A :data:`~oralnav.control.needle.procedure.feed.FeedFactory`: the task, started."""
    return NeedleTrackingTask(capture, prepare, track).start()
