"""The OpenIGTLink server's message rate and latency on loopback (issue 33, item 3).

``oralnav bench igtl --out DIR [--seconds S] [--json]`` runs the daemon's OpenIGTLink
server (``daemon/igtl.py``, on a core of its own without a control loop: the tool passes
it in, the benchmarks never import the daemon) and reads it with pyigtl's own client, as
3D Slicer would, in three runs of ``seconds`` each, :data:`POSES` poses each:

- ``fresh`` at 30 Hz and at 120 Hz (the ``rate_hz`` bound): every pose is published again
  each millisecond, so the server always sends one at most a millisecond old; the age at
  receipt is the server's and the socket's part (pose store -> tick -> pack -> loopback ->
  the client's thread);
- ``camera`` at 30 Hz: the poses are published at :data:`CAMERA_HZ`, a little off the
  server's 30 Hz as a camera's own clock is, so the phase between them sweeps a whole
  period; the age at receipt adds the wait for the next tick (up to one period), what a
  Slicer user sees.

Per run: messages received per second per pose (each counted once by its stamp), and the
age at receipt (p50, p99, max, ms): the client's wall clock at receipt less the message's
timestamp (the capture stamp on the epoch), so the figure also checks the stamp
conversion. The receipt is seen by polling pyigtl's client every 0.2 ms (up to that much
late). Writes ``igtl.json`` into DIR; progress goes to stderr.
"""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Callable
from contextlib import AbstractContextManager
from importlib.metadata import version
from pathlib import Path
from typing import Any

import numpy as np
import pyigtl

from oralnav.bench.machine import describe

__all__ = ["main"]

#: Poses published in each run (the cell's four tracked ones)
POSES = ("T_C_RM", "T_C_OM", "T_C_EM", "T_En_EM")
#: How often ``fresh`` runs publish (s)
FRESH_PERIOD_S = 0.001
#: The ``camera`` run's publication rate (Hz): off 30 Hz so that the phase sweeps
CAMERA_HZ = 29.3
#: How often the client is polled (s)
POLL_S = 0.0002


def _say(msg: str) -> None:
    print(f"bench igtl: {msg}", file=sys.stderr, flush=True)


def _run(serve: Callable[..., AbstractContextManager[Any]], rate_hz: float,
         publish_period: float, seconds: float) -> dict[str, Any]:
    """One run: publish every ``publish_period`` s for ``seconds`` s, read everything."""
    with serve(rate_hz=rate_hz) as server:
        core = server.core
        client = pyigtl.OpenIGTLinkClient("127.0.0.1", server.port)
        try:
            t0 = time.monotonic()
            while not client.is_connected():
                if time.monotonic() - t0 > 5.0:
                    raise RuntimeError("pyigtl's client did not connect within 5 s")
                time.sleep(0.001)
            T = np.eye(4)
            stamps: dict[str, set[float]] = {}
            ages: list[float] = []
            next_pub = start = time.monotonic()
            end = start + seconds
            k = 0
            while (now := time.monotonic()) < end:
                if now >= next_pub:
                    k += 1
                    T[0, 3] = k * 1e-6          # a new pose each time, as tracking gives
                    stamp = core.clock()
                    for pose in POSES:
                        core.publish_pose(pose, T, stamp, frame=pose.split("_")[1])
                    next_pub += publish_period
                for msg in client.get_latest_messages():
                    received = time.time()
                    seen = stamps.setdefault(msg.device_name, set())
                    if msg.timestamp not in seen:
                        seen.add(msg.timestamp)
                        ages.append(received - msg.timestamp)
                time.sleep(POLL_S)
            duration = time.monotonic() - start
        finally:
            client.stop()
    a = np.array(ages) * 1e3
    per_pose = [len(v) / duration for v in stamps.values()]
    return {"rate_hz": rate_hz, "publish_hz": round(1.0 / publish_period, 3),
            "seconds": round(duration, 3), "poses": len(stamps),
            "messages_per_s_per_pose": round(float(np.mean(per_pose)), 2) if per_pose else 0.0,
            "messages": len(a),
            "age_ms": {"p50": round(float(np.percentile(a, 50)), 3),
                       "p99": round(float(np.percentile(a, 99)), 3),
                       "max": round(float(a.max()), 3)} if len(a) else None}


def main(out: Path, serve: Callable[..., AbstractContextManager[Any]],
         seconds: float = 5.0) -> dict[str, Any]:
    """Run the three runs; write and return ``igtl.json``'s content. ``serve(rate_hz=)``
    runs a server and yields it (``.port``, ``.core.publish_pose``, ``.core.clock``:
    ``oralnav.daemon.igtl.standalone_server``, which the tool passes)."""
    if not seconds > 0:
        raise ValueError(f"seconds must be positive, got {seconds}")
    out.mkdir(parents=True, exist_ok=True)
    runs = {}
    for name, rate, period in (("fresh_30hz", 30.0, FRESH_PERIOD_S),
                               ("fresh_120hz", 120.0, FRESH_PERIOD_S),
                               ("camera_30hz", 30.0, 1.0 / CAMERA_HZ)):
        _say(f"{name}: {seconds:g} s")
        runs[name] = _run(serve, rate, period, seconds)
        _say(f"{name}: {json.dumps(runs[name])}")
    doc = {"machine": describe(pyigtl=version("pyigtl")), "runs": runs}
    (out / "igtl.json").write_text(json.dumps(doc, indent=2) + "\n")
    return doc
