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
from ..helpers import machine_stops_only

# alone: ./dev.sh test runs it after the parallel suite, with the machine to itself
pytestmark = [pytest.mark.skipif(GI_MISSING is not None, reason=str(GI_MISSING)),
              pytest.mark.alone]

#: s: the demo's own limit is 240 s; on an idle 2-core machine it takes 50-80 s
RUN_LIMIT_S = 300.0


def _demo(folder: Path) -> dict:
    """The peers with rendered cameras started in ``folder``, the demo run on their
    configuration, the peers stopped; the run's record (``bench.busy_demo.run_once``)."""
    from oralnav.cli.peers import HardwarePeers
    from oralnav.sim.peers.gige_fake import NoLoopbackAddress

    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    peers = HardwarePeers(folder / "cell", ur_host=f"127.84.{os.getpid() % 250}.9",
                          cameras="rendered")
    try:
        peers.__enter__()
    except NoLoopbackAddress as exc:
        pytest.skip(f"no loopback address for three cameras: {exc}")
    try:
        assert peers.rendered is not None, "the rendered cameras did not start"
        assert set(peers.rendered.addresses) == {"left", "right", "endoscope"}
        rec = run_once(folder / "run", [
            sys.executable, "-m", "oralnav.daemon.main", "--config",
            str(peers.write_config()), "--demo", "--json", "--api-port", str(free_port())],
            timeout=RUN_LIMIT_S)
    finally:
        peers.__exit__(None, None, None)
    rec["log"] = (folder / "run" / "stderr.txt").read_text()[-3000:]
    return rec


def _machine_stops_only(rec: dict) -> bool:
    """Whether a failed run stopped on the machine's stops alone (the renderer, three
    2-Mpixel views in the peers' process, starved; the loop stalled): environmental
    stops the daemon is right to take (tests/helpers.py ``MACHINE_STOPS``)."""
    return not rec["passed"] and machine_stops_only(rec.get("reasons"))


def test_the_main_job_reaches_every_target_on_the_hardware_in_the_loop_cell(
        tmp_path: Path) -> None:
    """The hardware-peer demo registers the four suture targets, runs the approach, the
    intra-oral adjustment and the targets, and ends READY with each TRE <= 0.1 mm against
    the peers' truth; its JSON carries the capture-to-command latency with its delivery
    and tracking stages, and the tracking rate. Marked ``alone``: ./dev.sh test runs it
    after the parallel suite (beside another worker on 2 cores its renderer starved: 2 of
    3 full runs failed on camera stalls). A run stopped by camera stalls or the loop's
    deadlines alone (the machine starved it) is run again, once; any other stop fails at
    once."""
    rec = _demo(tmp_path / "first")
    if _machine_stops_only(rec):  # once, and only for these environmental stops
        logging.getLogger(__name__).warning("HIL demo stopped on a starved machine (camera "
                                            "stalls or loop deadlines); run again once: %s",
                                            rec["why"])
        rec = _demo(tmp_path / "second")
    assert rec["passed"], f"{rec.get('why')}\n{rec['log']}"
    assert rec["state"] == "READY"
    tre = rec["tre_mm"]
    assert set(tre) == {"stitch_1", "stitch_2", "stitch_3", "stitch_4"}, tre
    assert all(v is not None and v <= 0.1 for v in tre.values()), tre
    lat = rec["latency_ms"]
    assert 0 < lat["p50"] <= lat["p99"]
    assert set(lat["stages"]) == {"delivery", "tracking"}
    assert rec["tracking_hz"] > 0


def test_only_a_stop_on_a_starved_machine_is_run_again():
    """The retry's rule: camera stalls and the loop's deadlines alone (the machine
    starved the daemon) qualify; any other reason among them (a lost pose, an e-stop), a
    passed run, or a run without the daemon's reasons do not."""
    stall = {"kind": "fault", "source": "camera_stall:left"}
    late = {"kind": "fault", "source": "deadline:stalled"}
    loop = {"kind": "fault", "source": "control loop",
            "reason": "deadline:stalled: control loop completed no period for 114 ms"}
    gone = {"kind": "fault", "source": "control loop", "reason": "arm disconnected"}
    assert _machine_stops_only({"passed": False, "reasons": [loop, late]})
    assert not _machine_stops_only({"passed": False, "reasons": [loop, gone]})
    other = {"kind": "fault", "source": "pose_timeout:opener"}
    assert _machine_stops_only({"passed": False, "reasons": [stall, dict(stall)]})
    assert _machine_stops_only({"passed": False, "reasons": [late, stall]})
    assert not _machine_stops_only({"passed": False, "reasons": [stall, other]})
    assert not _machine_stops_only({"passed": False, "reasons": [late, other]})
    assert not _machine_stops_only({"passed": True, "reasons": [stall]})
    assert not _machine_stops_only({"passed": False, "why": "no JSON result on stdout"})
