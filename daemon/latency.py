"""Where a frame's capture-to-command latency goes: the daemon's record of each tracked
round's capture instant, when its frames reached the tracking task, and when its poses
were published.

The control loop measures the whole latency (a goal's capture instant to the first servo
command computed from it, ``realtime/control_loop.py``). This splits the part before the
goal by stage, for each view of a tracked round (the stereo pair, the endoscope: each has
its own capture instant):

- ``delivery``: capture to the frames' arrival in the daemon's capture task (exposure,
  read-out, transfer, the driver's queue; on the hardware-in-the-loop cell also the
  rendering, because the renderer is the camera there);
- ``tracking``: arrival to the poses published (detection and refinement of every view).

What is left of the whole (published to the first servo command) is the navigation's
step and the wait for the control loop's next period. All instants are the daemon's
monotonic clock, in seconds; the summaries are in milliseconds.
"""

from __future__ import annotations

import threading
from collections import deque
from typing import Any

import numpy as np

__all__ = ["STAGE_VIEWS", "StageTimes", "percentiles_ms"]

#: Views kept (per daemon, every source together): about the loop's 512 goals.
STAGE_VIEWS = 512


def percentiles_ms(seconds: np.ndarray) -> dict[str, Any] | None:
    """``{"n", "p50", "p99", "max"}`` in ms of durations given in s; None when empty."""
    if len(seconds) == 0:
        return None
    ms = np.asarray(seconds, dtype=float) * 1e3
    return {"n": int(ms.size), "p50": float(np.percentile(ms, 50)),
            "p99": float(np.percentile(ms, 99)), "max": float(ms.max())}


class StageTimes:
    """The last :data:`STAGE_VIEWS` tracked views' stage instants (module docstring);
    safe to record from the capture tasks while the status reads."""

    def __init__(self, keep: int = STAGE_VIEWS) -> None:
        self._lock = threading.Lock()
        self._views: deque[tuple[float, float, float]] = deque(maxlen=keep)

    def record(self, captured: float, arrived: float, published: float) -> None:
        """One view of a round: its capture instant, its frames' arrival in the capture
        task and its poses' publication (s, daemon monotonic clock)."""
        with self._lock:
            self._views.append((float(captured), float(arrived), float(published)))

    def summary(self) -> dict[str, Any] | None:
        """``{"delivery": {...}, "tracking": {...}}``, each :func:`percentiles_ms` over
        the views kept; None before the first."""
        with self._lock:
            views = np.array(self._views, dtype=float).reshape(-1, 3)
        if len(views) == 0:
            return None
        return {"delivery": percentiles_ms(views[:, 1] - views[:, 0]),
                "tracking": percentiles_ms(views[:, 2] - views[:, 1])}
