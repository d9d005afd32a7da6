"""Issue 32, items 3-5 and the target "the hardware-in-the-loop demo runs in CI as one
end-to-end test": ``oralnav sim peers`` with rendered cameras (the simulated cell's stereo
pair and endoscope drawn where the fake UR controller has the arm and the Modbus drive
unit has the wrist, streamed over GigE Vision and read through Aravis), and ``oralnavd
--config DIR/cell.toml --demo --json`` on the configuration it writes: the main job
through ur_rtde, pymodbus, pyserial and Aravis, its TRE measured against the peers'
truth. ``oralnav bench hil`` runs the same on repeat."""

from __future__ import annotations

import logging
import os
import sys
from pathlib import Path

import pytest

from oralnav.bench.busy_demo import free_port, run_once

from ..drivers.test_camera_aravis import GI_MISSING

pytestmark = pytest.mark.skipif(GI_MISSING is not None, reason=str(GI_MISSING))

#: s: the demo's own limit is 240 s; on an idle 2-core machine it takes 50-80 s
RUN_LIMIT_S = 300.0


def test_the_main_job_reaches_every_target_on_the_hardware_in_the_loop_cell(
        tmp_path: Path) -> None:
    """The hardware-peer demo registers the four suture targets, runs the approach, the
    intra-oral adjustment and the targets, and ends READY with each TRE <= 0.1 mm against
    the peers' truth; its JSON carries the capture-to-command latency with its delivery
    and tracking stages, and the tracking rate."""
    from oralnav.cli.peers import HardwarePeers
    from oralnav.sim.peers.gige_fake import NoLoopbackAddress

    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    peers = HardwarePeers(tmp_path / "cell", ur_host=f"127.84.{os.getpid() % 250}.9",
                          cameras="rendered")
    try:
        peers.__enter__()
    except NoLoopbackAddress as exc:
        pytest.skip(f"no loopback address for three cameras: {exc}")
    try:
        assert peers.rendered is not None, "the rendered cameras did not start"
        assert set(peers.rendered.addresses) == {"left", "right", "endoscope"}
        rec = run_once(tmp_path / "run", [
            sys.executable, "-m", "oralnav.daemon.main", "--config",
            str(peers.write_config()), "--demo", "--json", "--api-port", str(free_port())],
            timeout=RUN_LIMIT_S)
    finally:
        peers.__exit__(None, None, None)
    log = (tmp_path / "run" / "stderr.txt").read_text()[-3000:]
    assert rec["passed"], f"{rec.get('why')}\n{log}"
    assert rec["state"] == "READY"
    tre = rec["tre_mm"]
    assert set(tre) == {"stitch_1", "stitch_2", "stitch_3", "stitch_4"}, tre
    assert all(v is not None and v <= 0.1 for v in tre.values()), tre
    lat = rec["latency_ms"]
    assert 0 < lat["p50"] <= lat["p99"]
    assert set(lat["stages"]) == {"delivery", "tracking"}
    assert rec["tracking_hz"] > 0
