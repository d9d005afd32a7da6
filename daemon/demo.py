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


def _say(msg: str) -> None:
    print(f"oralnavd demo: {msg}", file=sys.stderr, flush=True)


async def play_operator(core: Any, port: int, clear: dict[str, str], nav: Any,
                        result: dict[str, Any]) -> None:
    """Drive one procedure through the API; fill ``result``."""
    if nav is None:
        raise RuntimeError("--demo needs [cell] sim_cell in the configuration")
    if "operator" not in clear:
        raise RuntimeError("--demo needs the generated demo tokens: leave [api] tokens_file "
                           "unset")
    head = {"Authorization": f"Bearer {clear['operator']}"}
    t0 = time.monotonic()
    async with httpx.AsyncClient(base_url=f"http://127.0.0.1:{port}", headers=head,
                                 timeout=5.0) as api:
        while (await api.get("/status")).json()["safety"]["state"] != "READY":
            if time.monotonic() - t0 > 30:
                raise RuntimeError("the cell did not become READY within 30 s")
            await anyio.sleep(0.1)
        targets = [{"name": n, "p_OM": [float(x) for x in p]}
                   for n, p in nav.cell.config.targets_OM.items()]
        r = await api.post("/targets", json={"targets": targets})
        r.raise_for_status()
        _say(f"registered {len(targets)} suture targets in the opener frame")
        r = await api.post("/procedure/start")
        r.raise_for_status()
        _say("procedure started")
        start = time.monotonic()
        last = ""
        while True:
            st = (await api.get("/status")).json()
            proc, state = st.get("procedure", {}), st["safety"]["state"]
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
            control_loop=st.get("control_loop", {}),
            reasons=st["safety"].get("reasons"))
    tre = list(result["tre_mm"].values())
    if tre:
        result["tre_mean_mm"] = float(np.mean(tre))
        result["tre_max_mm"] = float(np.max(tre))


def print_result(result: dict[str, Any]) -> None:
    """The main job's summary on stdout."""
    done = "done" if result.get("done") else "NOT done"
    print(f"two-stage navigation on the simulated cell: {done} in "
          f"{result.get('duration_s', 0):.1f} s (final state {result.get('state')})")
    for name, tre in result.get("tre_mm", {}).items():
        print(f"  {name:10s} TRE {tre:.3f} mm (end-effector against the target, ground truth)")
    if "tre_mean_mm" in result:
        print(f"  mean TRE {result['tre_mean_mm']:.3f} mm, max {result['tre_max_mm']:.3f} mm")
    loop = result.get("control_loop", {})
    rates = result.get("rates_hz", {})
    print(f"  tracking {rates.get('tracking', 0):.1f} frames/s (stereo pair + endoscope, "
          f"rendered and tracked on this machine); control loop {loop.get('periods', 0)} "
          f"periods, p99 period error {loop.get('period_error_p99_ms') or 0.0:.3f} ms")
    if not result.get("done"):
        print(f"  stopped because: {result.get('reasons')}")
