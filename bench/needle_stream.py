"""The streamed drive servo's rate and latency at camera rate (issue 36, item 1: "servoing
at >= 30 Hz during the motions it guides, with the added latency from frame to command
reported (p50, p99)").

    oralnav bench needle-stream --out DIR [--seed S] [--trials N] [--fps F ...] [--json]

In the simulated cell the streamed servo (``oralnav bench needle --stream``) commands once
per rendered frame, and the simulator's renderer, about 70 ms a stereo pair on this
machine's two cores, sets that pace: the closed-loop rate says more of the renderer than
of the daemon. A camera delivers frames whatever the daemon does with them. So this
benchmark

1. runs streamed drives closed-loop on the development seeds ``seed .. seed + trials - 1``
   (1 mm / 0.5 deg arm errors, as the servo's figures are measured), keeping each frame
   the tracking task captured (the views and the state the step had commanded), the
   procedure's own ``prepare`` and ``track``, and the tracker as it was when the drive's
   stream began; and reports the closed-loop figures (commands a second, arrival to
   command);
2. plays each drive's frames back to a fresh tracking task
   (:class:`~oralnav.realtime.needle_tracking.NeedleTrackingTask`), the tracker restored
   to the drive's start, as a camera at ``fps`` would deliver them: frame ``i`` arrives at
   ``i / fps``, and the grabber takes the newest frame out (older ones it had no time for
   are skipped, counted). The step's side takes each newer tracked frame as the streamed
   drive does (``next``); from it the drive commands (its servo update and move, timed
   closed-loop: ``command_ms``).

Reported per ``fps``: frames tracked a second (the servo's rate: it commands on each),
frames skipped, and each frame's time from its arrival to the step (p50, p99), to which
the command's own time adds. ``fps`` 0 plays the frames as fast as the task takes them.
Writes ``needle_stream.json``.
"""

from __future__ import annotations

import copy
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from oralnav.bench.needle import percentiles, trial_procedure

#: The rates the frames are played back at by default (frames a second; 0: as fast as
#: the task takes them).
FPS = (30.0, 60.0, 0.0)
#: The servo's rate target (Hz, issue 36).
TARGET_HZ = 30.0
ARM_ERROR = (1.0, 0.5)


def record_drive(seed: int) -> dict[str, Any] | None:
    """Trial ``seed`` (development, ``ARM_ERROR`` arms) run to the end of its streamed
    drive; its frames, callables, starting tracker and ND figures (None where the drive's
    stream never started: an earlier step failed)."""
    from oralnav.realtime.needle_tracking import start_tracking

    rec: dict[str, Any] = {"seed": seed, "frames": []}

    def recording(capture, prepare, track):
        rec.update(prepare=prepare, track=track, tracker=copy.deepcopy(proc.tracker))

        def keeping():
            images, meta = capture()
            rec["frames"].append((images, meta))
            return images, meta
        return start_tracking(keeping, prepare, track)

    _, _, proc = trial_procedure(seed, ARM_ERROR, servo=True, feed=recording)
    for step in ("NG", "NH", "ND"):
        r = proc.run(step)
        if step == "ND":
            rec["figures"] = r.figures
            rec["ok"] = r.ok
        elif not r.ok:
            return None
    rec["proc"] = proc
    return rec if rec["frames"] else None


def replay(rec: dict[str, Any], fps: float, timeout: float = 2.0) -> dict[str, Any]:
    """``rec``'s frames played to a fresh tracking task at ``fps`` (0: as fast as it takes
    them), the tracker restored to the drive's start; what the step's side saw."""
    from oralnav.control.needle.servo import ServoStop
    from oralnav.realtime.needle_tracking import NeedleTrackingTask

    frames = rec["frames"]
    proc = rec["proc"]
    proc.tracker = copy.deepcopy(rec["tracker"])   # the procedure's track reads it
    track = rec["track"]
    clock: dict[str, Any] = {"t0": None, "last": -1, "skipped": 0}
    stop = {"now": False}

    def camera() -> tuple[Any, Any]:
        now = time.monotonic()
        if clock["t0"] is None:
            clock["t0"] = now
        t0, last = clock["t0"], clock["last"]
        if fps > 0:
            i = int((now - t0) * fps)              # the newest frame out by now
            if i <= last:
                i = last + 1
                time.sleep(max(0.0, t0 + i / fps - now))
            arrived = t0 + i / fps
        else:
            i, arrived = last + 1, now
        while i >= len(frames) and not stop["now"]:
            time.sleep(0.005)                      # the stream is over: nothing new
        i = min(i, len(frames) - 1)
        clock["skipped"] += max(0, i - last - 1)
        clock["last"] = i
        images, meta = frames[i]
        return images, (i, arrived, meta)

    def tracking(payload, m, previous):
        return track(payload, m[2], None if previous is None else previous[2])

    task = NeedleTrackingTask(camera, rec["prepare"], tracking, name="needle-replay").start()
    seq, latency, taken = 0, [], []
    t_first = t_last = None
    try:
        while True:
            try:
                fr = task.next(seq, timeout)
            except ServoStop:
                break
            now = time.monotonic()
            seq = fr.seq
            i, arrived, _ = fr.meta
            latency.append(now - arrived)
            taken.append(i)
            t_first = now if t_first is None else t_first
            t_last = now
            if i >= len(frames) - 1:
                break
    finally:
        stop["now"] = True
        task.stop()
    span = (t_last - t_first) if t_first is not None and t_last is not None else 0.0
    return {"frames": len(frames), "tracked": len(taken), "skipped": clock["skipped"],
            "rate_hz": round((len(taken) - 1) / span, 1) if span > 0 else None,
            "latency_ms": [round(v * 1e3, 1) for v in latency],
            "track_ms": [round(v * 1e3, 1) for v in task.track_s],
            "prepare_ms": [round(v * 1e3, 1) for v in task.prepare_s]}


def run(seed: int = 100, trials: int = 5, fps: Sequence[float] = FPS,
        progress: bool = True) -> dict[str, Any]:
    """Record streamed drives on ``trials`` development seeds from ``seed``, replay each
    at every ``fps``; the summary document."""
    from oralnav.bench.needle import stream_figures

    t0 = time.perf_counter()
    recs = []
    for s in range(seed, seed + trials):
        rec = record_drive(s)
        if progress:
            print(f"needle-stream: trial {s}: "
                  + ("no streamed drive (an earlier step failed)" if rec is None else
                     f"{len(rec['frames'])} frames recorded, drive "
                     f"{'passed' if rec['ok'] else 'failed'}"), file=sys.stderr, flush=True)
        if rec is not None:
            recs.append(rec)
    if not recs:
        raise RuntimeError(f"needle-stream: no streamed drive on seeds {seed}.."
                           f"{seed + trials - 1}")
    closed = stream_figures([{"results": [{"step": "ND", "figures": r["figures"]}]}
                             for r in recs])
    runs = {}
    for f in fps:
        out = [replay(r, f) for r in recs]
        lat = [v for o in out for v in o["latency_ms"]]
        rates = [o["rate_hz"] for o in out if o["rate_hz"] is not None]
        runs[f"{f:g}"] = {
            "fps": f, "frames": sum(o["frames"] for o in out),
            "tracked": sum(o["tracked"] for o in out),
            "skipped": sum(o["skipped"] for o in out),
            "rate_hz": {**percentiles(rates, 50), "min": min(rates) if rates else None},
            "latency_ms": {**percentiles(lat, 50, 99), "max": max(lat) if lat else None},
            "track_ms": percentiles([v for o in out for v in o["track_ms"]], 50, 99),
            "prepare_ms": percentiles([v for o in out for v in o["prepare_ms"]], 50, 99)}
        if progress:
            r = runs[f"{f:g}"]
            print(f"needle-stream: {'as fast as taken' if not f else f'{f:g} fps'}: "
                  f"{r['rate_hz']['p50']} frames tracked/s (p50 of drives), "
                  f"{r['skipped']} of {r['frames']} skipped; arrival to the step p50 "
                  f"{r['latency_ms']['p50']} ms, p99 {r['latency_ms']['p99']} ms",
                  file=sys.stderr, flush=True)
    # the drive's own time from taking a frame to its command (closed-loop), which adds
    # to the replay's arrival-to-step time
    command = [v for r in recs for v in r["figures"].get("servo_command_ms", [])]
    at30 = runs.get(f"{TARGET_HZ:g}")
    return {"bench": "needle_stream", "seeds": [seed, seed + trials - 1],
            "split": "development", "arm_error": list(ARM_ERROR),
            "drives": len(recs), "closed_loop": closed, "replay": runs,
            "command_ms": percentiles(command, 50, 99) if command else None,
            "target_hz": TARGET_HZ,
            "met": (None if at30 is None or at30["rate_hz"]["min"] is None
                    else bool(at30["rate_hz"]["min"] >= 0.95 * TARGET_HZ)),
            "seconds": round(time.perf_counter() - t0, 1)}


def main(out: Path, seed: int = 100, trials: int = 5,
         fps: Sequence[float] = FPS) -> dict[str, Any]:
    """:func:`run`; writes ``needle_stream.json`` into ``out``."""
    doc = run(seed, trials, fps)
    out.mkdir(parents=True, exist_ok=True)
    (out / "needle_stream.json").write_text(json.dumps(doc, indent=1) + "\n")
    return doc
