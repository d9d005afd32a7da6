"""The main job on the hardware-in-the-loop cell (issue 32, item 4).

``oralnav bench hil --out DIR [--runs N] [--camera-latency S] [--camera-clock-offset S]
[--json]`` starts the protocol peers with rendered cameras (``oralnav sim peers``: the fake
UR controller, the Modbus drive unit, the serial e-stop box, the simulated cell's stereo
pair and endoscope as GigE cameras, its ground truth on loopback) and runs ``oralnavd
--config DIR/cell.toml --demo --json`` on them ``runs`` times, each on fresh peers. Each
run's record: passed (exit 0, every target reached), each target's TRE against the peers'
truth, the capture-to-command latency (p50, p99) and its delivery and tracking stages,
the slowest tracking rate, the duration and, for a failure, the demo's reason. It writes
``hil.json`` into DIR and each run's daemon log into ``DIR/run_<k>``; progress goes to
stderr.
"""

from __future__ import annotations

import json
import logging
import sys
from collections.abc import Callable
from contextlib import AbstractContextManager
from pathlib import Path
from typing import Any

from oralnav.bench.busy_demo import free_port, run_once

__all__ = ["main"]


def _say(msg: str) -> None:
    print(f"bench hil: {msg}", file=sys.stderr, flush=True)


def _worst_p99(runs: list[dict[str, Any]], stage: str | None = None) -> float | None:
    """The largest p99 (ms) over ``runs`` of the whole latency, or of one of its
    ``stages``; None where no run measured it."""
    p99s = []
    for r in runs:
        lat = r.get("latency_ms") or {}
        if stage is not None:
            lat = (lat.get("stages") or {}).get(stage) or {}
        if lat.get("p99") is not None:
            p99s.append(lat["p99"])
    return max(p99s, default=None)


def main(out: Path, make_peers: Callable[..., AbstractContextManager[Any]], runs: int = 1,
         camera_latency: float = 0.0, camera_clock_offset: float = 0.0) -> dict[str, Any]:
    """Run the campaign; write and return ``hil.json``'s content. ``make_peers(folder,
    camera_latency=, camera_clock_offset=)`` gives the peers with rendered cameras
    (``oralnav.cli.peers.HardwarePeers``, which the tool passes: the benchmarks never
    import the tools)."""
    if runs < 1:
        raise ValueError(f"runs must be at least 1, got {runs}")
    out = out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    results = []
    for k in range(runs):
        folder = out / f"run_{k}"
        _say(f"run {k + 1}/{runs}: starting the peers (rendering maps takes seconds)")
        with make_peers(folder, camera_latency=camera_latency,
                        camera_clock_offset=camera_clock_offset) as peers:
            if peers.rendered is None:
                raise RuntimeError("the rendered cameras did not start (Aravis and a "
                                   "loopback address per camera are needed)")
            config = peers.write_config()
            rec = run_once(folder, [sys.executable, "-m", "oralnav.daemon.main", "--config",
                                    str(config), "--demo", "--json", "--api-port",
                                    str(free_port())])
        results.append(rec)
        _say(f"run {k + 1}/{runs}: " + ("passed" if rec["passed"] else "FAILED")
             + (f" in {rec['duration_s']:.1f} s" if rec.get("duration_s") else "")
             + (f"; TRE {rec.get('tre_mm')}" if rec.get("tre_mm") else "")
             + (f" ({rec['why']})" if not rec["passed"] else ""))
    passed = [r for r in results if r["passed"]]
    tre = [v for r in passed for v in (r.get("tre_mm") or {}).values() if v is not None]
    doc = {"runs": runs, "camera_latency_s": camera_latency,
           "camera_clock_offset_s": camera_clock_offset, "passed": len(passed),
           "tre_max_mm": max(tre) if tre else None, "tre_measured": len(tre),
           "latency_p99_ms": _worst_p99(passed),
           # where the latency goes (daemon/latency.py): capture to arrival, then tracking
           "delivery_p99_ms": _worst_p99(passed, "delivery"),
           "tracking_p99_ms": _worst_p99(passed, "tracking"),
           "tracking_hz_min": min((r["tracking_hz"] for r in passed
                                   if r.get("tracking_hz") is not None), default=None),
           "results": results}
    (out / "hil.json").write_text(json.dumps(doc, indent=1))
    return doc
