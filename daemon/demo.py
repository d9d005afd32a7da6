"""``oralnavd --demo``: the main job. The daemon serves the simulated cell and this plays
the operator over the real REST API: register the cell's suture targets, start the
procedure, follow its progress, and report the reached accuracy (TRE against ground truth)
and the measured rates."""

from __future__ import annotations

import sys
import time
from typing import Any

import anyio
import httpx
import numpy as np

#: The whole procedure must finish within this (s); the daemon stops the robot otherwise.
DEMO_TIMEOUT_S = 240.0
#: The cell must be READY this long (s) after the API answers.
READY_TIMEOUT_S = 60.0


def _say(msg: str) -> None:
    print(f"oralnavd demo: {msg}", file=sys.stderr, flush=True)


async def play_operator(port: int, clear: dict[str, str],
                        targets_OM: dict[str, np.ndarray], result: dict[str, Any]) -> None:
    """Drive one procedure through the API with the suture targets ``targets_OM`` (name ->
    (3,) m, opener frame); fill ``result``."""
    if "operator" not in clear:
        raise RuntimeError("--demo needs the generated demo tokens: leave [api] tokens_file "
                           "unset")
    head = {"Authorization": f"Bearer {clear['operator']}"}
    t0 = time.monotonic()
    async with httpx.AsyncClient(base_url=f"http://127.0.0.1:{port}", headers=head,
                                 timeout=5.0) as api:
        while True:
            safety = (await api.get("/status")).json()["safety"]
            if safety["state"] == "READY":
                break
            if time.monotonic() - t0 > READY_TIMEOUT_S:
                # kept, as during the procedure: a caller tells a stop from a slow start
                result.update(state=safety["state"], reasons=safety.get("reasons"))
                why = safety.get("not_ready_reason") or safety.get("reasons")
                raise RuntimeError(f"the cell did not become READY within "
                                   f"{READY_TIMEOUT_S:g} s (state {safety['state']}: {why})")
            await anyio.sleep(0.1)
        targets = [{"name": n, "p_OM": [float(x) for x in p]}
                   for n, p in targets_OM.items()]
        r = await api.post("/targets", json={"targets": targets})
        r.raise_for_status()
        result["targets"] = [t["name"] for t in targets]
        _say(f"registered {len(targets)} suture targets in the opener frame")
        r = await api.post("/procedure/start")
        r.raise_for_status()
        _say("procedure started")
        start = time.monotonic()
        last = ""
        while True:
            st = (await api.get("/status")).json()
            proc, state = st.get("procedure", {}), st["safety"]["state"]
            # kept as it goes, so a run that fails later still says where it stood
            result.update(state=state, stage=proc.get("stage"),
                          reasons=st["safety"].get("reasons"),
                          duration_s=time.monotonic() - start)
            line = (f"{state} stage {proc.get('stage', '-')}"
                    + (f", target {proc['target']}" if proc.get("target") else "")
                    + (f", error {proc['error_mm']:.3f} mm"
                       if proc.get("error_mm") is not None else ""))
            if line != last:
                _say(line)
                last = line
            if proc.get("done") or state in ("FAULT", "ESTOP"):
                break
            if time.monotonic() - start > DEMO_TIMEOUT_S:
                await api.post("/procedure/abort")
                raise RuntimeError(f"procedure not finished in {DEMO_TIMEOUT_S:g} s")
            await anyio.sleep(0.5)
        result.update(
            state=state, done=bool(proc.get("done")), tre_mm=proc.get("tre_mm", {}),
            duration_s=time.monotonic() - start, rates_hz=st.get("rates_hz", {}),
            latency_ms=st.get("latency_ms"),
            control_loop=st.get("control_loop", {}),
            reasons=st["safety"].get("reasons"))
    tre = list(result["tre_mm"].values())
    if tre:
        result["tre_mean_mm"] = float(np.mean(tre))
        result["tre_max_mm"] = float(np.max(tre))


def demo_summary(result: dict[str, Any]) -> dict[str, Any]:
    """The main job's figures as ``--json`` prints them at the top level: ``targets``
    (name -> ``{"tre_mm"}``, None where no truth was measured), ``latency_ms`` (``p50``,
    ``p99``: capture to command; ``stages``: its ``delivery`` and ``tracking`` parts, each
    ``p50`` and ``p99``), ``tracking_hz`` (the slowest camera source's rate) and
    ``final_state``."""
    tre = result.get("tre_mm", {})
    rates = [hz for name, hz in result.get("rates_hz", {}).items()
             if name.startswith("tracking")]
    lat = result.get("latency_ms") or {}
    return {"targets": {n: {"tre_mm": tre.get(n)} for n in result.get("targets", [])},
            "latency_ms": {"p50": lat.get("p50"), "p99": lat.get("p99"),
                           "stages": {k: {"p50": v["p50"], "p99": v["p99"]}
                                      for k, v in (lat.get("stages") or {}).items() if v}},
            "tracking_hz": min(rates) if rates else None,
            "final_state": result.get("state")}


def print_result(result: dict[str, Any], backend: str = "sim") -> None:
    """The main job's summary on stdout."""
    done = "done" if result.get("done") else "NOT done"
    where = "the simulated cell" if backend == "sim" else "the hardware cell"
    print(f"two-stage navigation on {where}: {done} in "
          f"{result.get('duration_s', 0):.1f} s (final state {result.get('state')})")
    for name, tre in result.get("tre_mm", {}).items():
        print(f"  {name:10s} TRE {tre:.3f} mm (end-effector against the target, ground truth)")
    missing = [n for n in result.get("targets", []) if n not in result.get("tre_mm", {})]
    if missing and result.get("done"):
        print(f"  no ground truth for {', '.join(missing)} (a real cell has none)")
    if "tre_mean_mm" in result:
        print(f"  mean TRE {result['tre_mean_mm']:.3f} mm, max {result['tre_max_mm']:.3f} mm")
    loop = result.get("control_loop", {})
    rates = result.get("rates_hz", {})
    tracked = ", ".join(f"{name.removeprefix('tracking ')} {hz:.1f}"
                        for name, hz in rates.items() if name.startswith("tracking"))
    print(f"  tracking (frames/s, rendered and tracked on this machine): {tracked or '-'}; "
          f"control loop {loop.get('periods', 0)} periods, p99 period error "
          f"{loop.get('period_error_p99_ms') or 0.0:.3f} ms")
    lat = result.get("latency_ms") or {}
    if lat.get("p50") is not None:
        camera = ("the simulated camera's rendering" if backend == "sim"
                  else "the camera's delivery")
        print(f"  capture-to-command latency p50 {lat['p50']:.1f} ms, p99 {lat['p99']:.1f} ms "
              f"over {lat['n']} goals ({camera} included)")
    for stage, v in (lat.get("stages") or {}).items():
        if v:
            print(f"    {stage:9s} p50 {v['p50']:.1f} ms, p99 {v['p99']:.1f} ms "
                  f"over {v['n']} views")
    if not result.get("done"):
        if result.get("error"):
            print(f"  failed: {result['error']}")
        if result.get("reasons"):
            print(f"  stopped because: {result['reasons']}")
