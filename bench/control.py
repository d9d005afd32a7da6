"""Control-loop timing: thread or process, with tracking at full rate (issue 4).

``oralnav bench control [--quick] --out DIR`` runs the real ``ControlLoop`` on simulated
drivers at the configured rate for a while, in each of two placements:

- ``thread``: a thread of the process that also tracks (what one would write first);
- ``process``: the ``ControlProcess`` child that ``oralnavd`` uses, with normal
  scheduling, and ``process-fifo``: the same with SCHED_FIFO 50 (``[control]
  realtime_priority``, as ``config/sim.toml`` sets it);

- ``process-ur``: the process with the real ``ur`` arm backend (issue 8): ur_rtde in the
  driver's own child, over RTDE to the fake UR controller, as on a real cell;

each once idle and once while the main thread tracks the simulated cell's three fields
back-to-back with NVG-BA on two 1920x1200 images (heavier than camera rate). The loop
servoes toward goals that the main thread moves every tracked frame. It writes
``control.json`` (every period-error histogram, p50/p99/p99.9/max, misses) and
``control_loop.png``. Target: p99 |period - 2 ms| <= 1 ms at 500 Hz under tracking.
"""

from __future__ import annotations

import json
import os
import platform
import sys
import threading
import time
from pathlib import Path
from typing import Any

import anyio
import numpy as np

from oralnav.realtime.control_loop import (
    CMD_DTYPE,
    HIST_BIN_S,
    HIST_BINS,
    NAV_DTYPE,
    STATUS_DTYPE,
    ControlLoop,
    LoopSettings,
    run_at_rate,
)
from oralnav.realtime.control_process import ControlProcess, DriverSpec, ProcessSpec
from oralnav.realtime.shm import SharedRecord

P99_TARGET_MS = 1.0
#: SCHED_FIFO priority of the "process-fifo" runs (what config/sim.toml asks for).
RT_PRIORITY = 50


def _fifo_granted() -> str:
    """Whether this machine grants SCHED_FIFO (the loop falls back to normal otherwise)."""
    import os as _os

    from oralnav.realtime.control_loop import try_realtime
    pid = _os.fork()
    if pid == 0:  # try in a throwaway child so this process keeps its scheduling
        _os._exit(0 if try_realtime(RT_PRIORITY).startswith("SCHED_FIFO") else 1)
    _, code = _os.waitpid(pid, 0)
    return f"SCHED_FIFO {RT_PRIORITY}" if code == 0 else "normal (SCHED_FIFO refused)"


def _log(msg: str) -> None:
    print(f"bench control: {msg}", file=sys.stderr, flush=True)


def _home() -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = [0.0, 0.0, 0.3]
    return T


def _goal(k: int) -> np.ndarray:
    """Goals 2 cm apart, alternating, so the loop is always servoing."""
    T = _home()
    T[0, 3] += 0.02 * (k % 2)
    return T


class _Tracking:
    """Back-to-back NVG-BA tracking of the simulated cell on the calling thread."""

    def __init__(self) -> None:
        from oralnav.bench.navigation import cell_scene, trajectory
        from oralnav.control.vision.tracker import Tracker
        from oralnav.sim.world.render import SceneRenderer

        scene = cell_scene()
        renderer = SceneRenderer(scene)
        renderer.prepare()
        self.frames = [renderer.render(trajectory(scene, k), frame=k).images for k in range(8)]
        self.tracker = Tracker(scene.rig, [p.field for p in scene.placements], method="nvgba",
                               mode="predict")
        self.count = 0

    def run(self, seconds: float, on_frame) -> float:
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < seconds:
            self.tracker.track(self.frames[self.count % len(self.frames)])
            self.count += 1
            on_frame(self.count)
        return self.count / (time.perf_counter() - t0)


def _summary(hist: np.ndarray, err_max: float, misses: int) -> dict[str, Any]:
    n = int(hist.sum())
    cdf = np.cumsum(hist) / max(n, 1)

    def pct(q: float) -> float:
        b = int(np.searchsorted(cdf, q))
        return (b + 1) * HIST_BIN_S * 1e3 if b < HIST_BINS else err_max * 1e3

    return {"periods": n, "p50_ms": pct(0.50), "p99_ms": pct(0.99), "p999_ms": pct(0.999),
            "max_ms": err_max * 1e3, "misses_over_1ms": int(misses),
            "hist_bin_ms": HIST_BIN_S * 1e3, "hist": hist.tolist()}


def _limiter():
    from oralnav.safety.limits import SpeedLimiter
    return SpeedLimiter(max_speed=0.25, max_angular_speed=0.5)


def _drivers() -> tuple[DriverSpec, DriverSpec]:
    return (DriverSpec("sim", {"home": _home()}), DriverSpec("sim"))


def run_thread(seconds: float, settings: LoopSettings, tracking: _Tracking | None
               ) -> dict[str, Any]:
    from oralnav.drivers.arm import open_arm
    from oralnav.drivers.clock import WallClock
    from oralnav.drivers.effector import open_effector

    clock = WallClock()
    arm_spec, eff_spec = _drivers()
    arm = open_arm("sim", clock=clock, **arm_spec.options)
    eff = open_effector("sim", clock=clock)
    anyio.run(arm.start)
    anyio.run(eff.start)
    nav, cmd, status = (SharedRecord(d) for d in (NAV_DTYPE, CMD_DTYPE, STATUS_DTYPE))
    try:
        nav.write(goal=_goal(0), t_pose=clock.now(), mode=1)
        loop = ControlLoop(arm, eff, settings, nav, cmd, status, _limiter(), clock=clock.now)
        done = threading.Event()
        last = [clock.now()]

        def step(now: float, lateness: float) -> None:
            arm.advance(now - last[0])
            eff.advance(now - last[0])
            last[0] = now
            loop.step(now, lateness)

        th = threading.Thread(target=run_at_rate, args=(step, settings.rate_hz, done.is_set),
                              kwargs={"clock": clock.now}, daemon=True)
        th.start()
        fps = _load(seconds, tracking, lambda k: nav.write(goal=_goal(k), t_pose=clock.now()))
        done.set()
        th.join()
        st = status.read()
        out = _summary(np.array(st["hist"]), float(st["err_max"]), int(st["misses"]))
        out.update(latched=bool(st["latched"]), tracking_fps=fps)
        return out
    finally:
        for r in (nav, cmd, status):
            r.close()
        anyio.run(arm.close)
        anyio.run(eff.close)


def run_process(seconds: float, settings: LoopSettings, tracking: _Tracking | None,
                realtime_priority: int = 0, arm: DriverSpec | None = None) -> dict[str, Any]:
    arm_spec, eff_spec = _drivers()
    arm_spec = arm or arm_spec
    proc = ControlProcess(ProcessSpec(arm=arm_spec, effector=eff_spec, settings=settings,
                                      limiter=_limiter(),
                                      realtime_priority=realtime_priority))

    async def body() -> dict[str, Any]:
        await proc.start()
        try:
            proc.set_goal(_goal(0), time.monotonic(), move=True)
            fps = _load(seconds, tracking,
                        lambda k: proc.set_goal(_goal(k), time.monotonic(), move=True))
            st = proc.read_status()
            out = _summary(np.array(st["hist"]), float(st["err_max"]), int(st["misses"]))
            out.update(latched=bool(st["latched"]), tracking_fps=fps)
            return out
        finally:
            await proc.close()

    return anyio.run(body)


def run_process_ur(seconds: float, settings: LoopSettings,
                   tracking: _Tracking | None) -> dict[str, Any]:
    """The process placement with the ``ur`` arm backend: every servo goes through the
    driver's pipe to its ur_rtde child and over RTDE to the fake UR controller (a third
    process, 500 Hz), as on a real cell."""
    from oralnav.sim.peers.ur import FakeURControllerProcess

    home = [*_home()[:3, 3], 0.0, 0.0, 0.0]  # x y z (m), rotation vector (rad)
    with FakeURControllerProcess(f"127.85.{os.getpid() % 250}.1", home=home) as fake:
        return run_process(seconds, settings, tracking,
                           arm=DriverSpec("ur", {"host": fake.host, "watchdog_timeout": 0.25}))


def _load(seconds: float, tracking: _Tracking | None, on_frame) -> float | None:
    if tracking is None:
        k = 0
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < seconds:
            time.sleep(0.033)
            k += 1
            on_frame(k)
        return None
    return tracking.run(seconds, on_frame)


def charts(doc: dict[str, Any], out: Path) -> list[str]:
    from oralnav.bench.report.charts import legend_outside
    from oralnav.bench.report.charts import plt as pyplot

    plt = pyplot()
    fig, ax = plt.subplots(figsize=(9, 4.5), layout="constrained")
    for key, r in doc["runs"].items():
        h = np.array(r["hist"], dtype=float)
        edges = np.arange(len(h) + 1) * r["hist_bin_ms"]
        frac = h / max(h.sum(), 1)
        ax.step(edges[:-1], np.maximum(frac, 1e-7), where="post",
                label=f"{key}: p99 {r['p99_ms']:.3f} ms")
    ax.axvline(P99_TARGET_MS, color="k", ls="--", lw=0.8, label="1 ms")
    ax.set_yscale("log")
    ax.set_xlabel("|period - nominal| (ms); last bin: beyond 5 ms")
    ax.set_ylabel("fraction of periods")
    ax.set_title(f"control loop at {doc['rate_hz']:g} Hz on {doc['machine']['cpus']} cores")
    legend_outside(ax)  # the tails the chart is for sit where an inside legend would go
    fig.savefig(out / "control_loop.png", dpi=110)
    plt.close(fig)
    return ["control_loop.png"]


def main(out: Path, quick: bool = False) -> dict[str, Any]:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    seconds = 8.0 if quick else 60.0
    settings = LoopSettings(rate_hz=500.0)
    _log("rendering the cell for the tracking load...")
    tracking = _Tracking()
    doc: dict[str, Any] = {
        "bench": "control", "quick": quick, "rate_hz": settings.rate_hz, "seconds": seconds,
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
        "runs": {}}
    placements = (("thread", run_thread), ("process", run_process),
                  ("process-fifo", lambda *a: run_process(*a, realtime_priority=RT_PRIORITY)),
                  ("process-ur", run_process_ur))
    for placement, fn in placements:
        for loaded in (False, True):
            key = f"{placement}/{'tracking' if loaded else 'idle'}"
            _log(f"{key}: {seconds:g} s...")
            r = fn(seconds, settings, tracking if loaded else None)
            doc["runs"][key] = r
            _log(f"  p50 {r['p50_ms']:.3f} ms, p99 {r['p99_ms']:.3f} ms, "
                 f"max {r['max_ms']:.3f} ms, {r['misses_over_1ms']} periods off by > 1 ms"
                 + (f", tracking {r['tracking_fps']:.0f} frames/s" if loaded else "")
                 + ("; the loop LATCHED A STOP" if r.get("latched") else ""))
    target_run = doc["runs"]["process-fifo/tracking"]
    p99 = target_run["p99_ms"]
    verdict = verdict_of(p99, bool(target_run.get("latched")))
    doc["targets"] = {"p99_ms_under_tracking": p99, "p99_ms_target": P99_TARGET_MS,
                      "met": verdict == "met", "verdict": verdict,
                      "latched_runs": [k for k, r in doc["runs"].items() if r.get("latched")],
                      "scheduling": _fifo_granted(),
                      "p99_ms_under_tracking_normal_scheduling":
                          doc["runs"]["process/tracking"]["p99_ms"],
                      "p99_ms_under_tracking_ur_backend":
                          doc["runs"]["process-ur/tracking"]["p99_ms"]}
    doc["charts"] = charts(doc, out)
    (out / "control.json").write_text(json.dumps(doc, indent=1) + "\n")
    _log(f"wrote {out / 'control.json'}: process ({doc['targets']['scheduling']}) p99 "
         f"{p99:.3f} ms under tracking (target <= {P99_TARGET_MS} ms): {verdict}"
         + (f"; runs that latched a stop: {', '.join(doc['targets']['latched_runs'])}"
            if doc["targets"]["latched_runs"] else ""))
    return doc


def verdict_of(p99_ms: float, latched: bool) -> str:
    """The target's verdict from what the run measured: ``met`` only when its p99 is
    within the target and its loop never latched a stop (a stopped loop's periods are
    not the servo's: timing after a stop says nothing of control under load)."""
    if latched:
        return "missed: the loop latched a stop during the run"
    if not np.isfinite(p99_ms) or p99_ms > P99_TARGET_MS:
        return f"missed: p99 {p99_ms:.3f} ms > {P99_TARGET_MS} ms"
    return "met"
