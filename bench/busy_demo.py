"""The main job on a busy machine (issue 32, item 6): ``oralnavd --demo`` run again and again
while other processes keep every core busy.

``oralnav bench busy-demo --out DIR [--runs 10] [--busy N] [--json]`` starts ``N`` busy
processes (default: one per CPU; each a Python loop of integer work at normal priority, in
its own process group), then runs ``python -m oralnav.daemon.main --demo --json`` ``runs``
times one after the other, each on a free loopback port with its state and demo tokens in
``DIR/run_<k>``. For each run it records the exit status, whether every target was reached,
the duration, each target's TRE, the tracking rates, and why it failed (the demo's own
words). It writes ``busy_demo.json`` into DIR and prints a summary; progress goes to
stderr. The busy processes are killed on the way out, whatever happens.

A run passes when the demo exits 0 with every target reached. The slow sight this causes
(1-2 tracked frames/s on a 2-core machine) must only slow the robot: docs/navigation.md.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

__all__ = ["BUSY_LOOP", "demo_command", "free_port", "main", "run_once", "summary"]

#: One busy process: integer work that never sleeps, for at most an hour.
BUSY_LOOP = ("import time\nend = time.monotonic() + 3600\nx = 0\n"
             "while time.monotonic() < end:\n    x = (x * 31 + 7) % 1000003\n")
#: The longest one demo run may take (s) before it counts as failed and is killed.
RUN_TIMEOUT_S = 600.0


def _say(msg: str) -> None:
    print(f"bench busy-demo: {msg}", file=sys.stderr, flush=True)


def free_port() -> int:
    """A free TCP port on 127.0.0.1 (for a daemon's API)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _start_busy(n: int) -> list[subprocess.Popen]:
    return [subprocess.Popen([sys.executable, "-c", BUSY_LOOP], start_new_session=True,
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            for _ in range(n)]


def _stop(procs: Sequence[subprocess.Popen]) -> None:
    for p in procs:
        if p.poll() is None:
            try:
                os.killpg(p.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        p.wait()


def demo_command(port: int) -> list[str]:
    """The main job as ``./dev.sh run`` runs it, on ``port``, printing one JSON object."""
    return [sys.executable, "-m", "oralnav.daemon.main", "--demo", "--json",
            "--api-port", str(port)]


def run_once(folder: Path, command: Sequence[str], timeout: float = RUN_TIMEOUT_S
             ) -> dict[str, Any]:
    """One demo run in ``folder``; its record (see the module docstring)."""
    folder = folder.resolve()  # the demo runs in it: relative paths would nest
    folder.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, STATE_DIRECTORY=str(folder), RUNTIME_DIRECTORY=str(folder))
    t0 = time.monotonic()
    try:
        done = subprocess.run(list(command), env=env, cwd=folder, capture_output=True,
                              text=True, timeout=timeout)
    except subprocess.TimeoutExpired as exc:
        (folder / "stderr.txt").write_text((exc.stderr or b"").decode(errors="replace")
                                           if isinstance(exc.stderr, bytes)
                                           else exc.stderr or "")
        return {"rc": None, "passed": False, "wall_s": time.monotonic() - t0,
                "why": f"the demo did not finish in {timeout:g} s"}
    (folder / "stderr.txt").write_text(done.stderr)
    rec: dict[str, Any] = {"rc": done.returncode, "wall_s": time.monotonic() - t0}
    try:
        doc = json.loads(done.stdout.strip().splitlines()[-1])
        demo = doc["demo"]
    except (IndexError, KeyError, ValueError):
        tail = done.stderr.strip().splitlines()[-1:] or ["(no output)"]
        rec.update(passed=False, why=f"no JSON result on stdout: {tail[0]}")
        return rec
    tre = demo.get("tre_mm") or {}
    rec.update(done=bool(demo.get("done")), duration_s=demo.get("duration_s"),
               tre_mm=tre, tre_max_mm=max(tre.values()) if tre else None,
               rates_hz={k: v for k, v in (demo.get("rates_hz") or {}).items()
                         if k.startswith("tracking")},
               state=demo.get("state"), latency_ms=doc.get("latency_ms"),
               tracking_hz=doc.get("tracking_hz"))
    rec["passed"] = done.returncode == 0 and rec["done"]
    if not rec["passed"]:
        rec["why"] = demo.get("error") or str(demo.get("reasons")) or f"exit {done.returncode}"
        rec["reasons"] = demo.get("reasons")  # the stop's reasons as the daemon gave them
    return rec


def main(out: Path, runs: int = 10, busy: int | None = None,
         command: Sequence[str] | None = None) -> dict[str, Any]:
    """Run the campaign; write and return ``busy_demo.json``'s content. ``command`` (for
    tests) replaces the demo command; ``{port}`` in it is replaced by a free port."""
    if runs < 1:
        raise ValueError(f"runs must be at least 1, got {runs}")
    if busy is None:
        busy = os.cpu_count() or 1
    if busy < 0:
        raise ValueError(f"busy must be 0 or more processes, got {busy}")
    out.mkdir(parents=True, exist_ok=True)
    _say(f"{busy} busy process(es) on {os.cpu_count()} CPU(s); {runs} demo run(s)")
    procs = _start_busy(busy)
    results = []
    try:
        for k in range(runs):
            port = free_port()
            cmd = ([c.replace("{port}", str(port)) for c in command] if command
                   else demo_command(port))
            rec = run_once(out / f"run_{k}", cmd)
            results.append(rec)
            _say(f"run {k + 1}/{runs}: " + ("passed" if rec["passed"] else "FAILED")
                 + (f" in {rec['duration_s']:.1f} s" if rec.get("duration_s") else "")
                 + (f", TRE max {rec['tre_max_mm']:.3f} mm" if rec.get("tre_max_mm") else "")
                 + (f" ({rec['why']})" if not rec["passed"] else ""))
    finally:
        _stop(procs)
    doc = {"runs": runs, "busy": busy, "cpus": os.cpu_count(), "results": results,
           **summary(results)}
    (out / "busy_demo.json").write_text(json.dumps(doc, indent=1))
    return doc


def summary(results: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Passed runs, and over them: duration (s) median and max, the largest TRE (mm), the
    slowest tracking rate seen (frames/s); the failures' reasons."""
    ok = [r for r in results if r.get("passed")]
    durations = sorted(float(r["duration_s"]) for r in ok if r.get("duration_s") is not None)
    rates = [hz for r in ok for hz in (r.get("rates_hz") or {}).values()]
    return {"passed": len(ok), "failed": len(results) - len(ok),
            "duration_s": {"median": durations[len(durations) // 2] if durations else None,
                           "max": durations[-1] if durations else None},
            "tre_max_mm": max((r["tre_max_mm"] for r in ok if r.get("tre_max_mm") is not None),
                              default=None),
            "tracking_hz_min": min(rates) if rates else None,
            "failures": [r.get("why") for r in results if not r.get("passed")]}
