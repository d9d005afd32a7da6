"""What the streamed drive servo needs of a tracking task (issue 36, item 1): a tracker
that runs on every frame in a task of its own while the arm moves, and hands the step
the newest tracked frame.

The procedure supplies the two halves of a frame's work as callables, and a
:data:`FeedFactory` (the realtime layer's :class:`~oralnav.realtime.needle_tracking.
NeedleTrackingTask` is one) runs them in its own threads:

- ``capture() -> (images, meta)``: grab the views now with ``meta``, what the step had
  commanded when they were taken (the drive pose, the servo's correction, the reported
  tool pose); the procedure holds its cell lock inside, so a frame shows one state;
- ``prepare(images) -> payload``: reduce the views to what the tracker reads (the frame's
  time is taken between the two: when its views arrived);
- ``track(payload, meta, previous_meta) -> NeedleTrack``: predict the needle from the
  last tracked frame's ``meta`` to this one's and update on ``payload``.

The step never waits longer than its timeout for a frame: a stream that stalls, a tracking
thread that died, are a :class:`~oralnav.control.needle.servo.ServoStop` (``stale``,
``tracker_failed``) from :meth:`TrackingFeed.next`, never a servo on an old pose. Times
are seconds of ``time.monotonic``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

from oralnav.control.needle.tracker import NeedleTrack

__all__ = ["Capture", "FeedFactory", "Prepare", "Track", "TrackedFrame", "TrackingFeed"]


@dataclass(frozen=True)
class TrackedFrame:
    """One tracked frame: ``seq`` (1, 2, ... in capture order), ``stamp`` (s,
    monotonic: when the views arrived), ``tracked_at`` (s: when its track was
    published), the capture's ``meta`` and the tracker's ``track``."""

    seq: int
    stamp: float
    tracked_at: float
    meta: Any
    track: NeedleTrack


#: ``capture() -> (images, meta)``: see the module docstring.
Capture = Callable[[], tuple[Any, Any]]
#: ``prepare(images) -> payload``.
Prepare = Callable[[Any], Any]
#: ``track(payload, meta, previous_meta) -> NeedleTrack`` (``previous_meta`` None first).
Track = Callable[[Any, Any, Any], NeedleTrack]


class TrackingFeed(Protocol):
    """A running tracking task (see the module docstring)."""

    def next(self, after: int, timeout: float) -> TrackedFrame:
        """The newest tracked frame whose ``seq`` is above ``after``, waiting up to
        ``timeout`` (s) for one; a ``ServoStop`` (``stale``: none came in time;
        ``tracker_failed``: the task's thread raised, its error named) otherwise."""
        ...

    @property
    def prepare_s(self) -> list[float]:
        """The seconds each frame's ``prepare`` took, in capture order."""
        ...

    @property
    def track_s(self) -> list[float]:
        """The seconds each tracked frame's ``track`` took, in order."""
        ...

    def stop(self) -> TrackedFrame | None:
        """Stop the task and wait for its threads; the last frame it tracked (None if
        none). Safe to call twice."""
        ...


#: ``factory(capture, prepare, track) -> TrackingFeed``, the task started.
FeedFactory = Callable[[Capture, Prepare, Track], TrackingFeed]
