"""Issue 32, items 1 and 3: the hardware-in-the-loop cell. ``oralnav sim peers`` with
rendered cameras (the simulated cell's stereo pair and endoscope, drawn where the fake UR
controller has the arm and the drive unit has the wrist, streamed over GigE Vision through
Aravis), and ``oralnavd`` on the configuration it writes: the same capture pipeline and
navigation as the simulated cell, through ur_rtde, the Modbus wrist, the serial e-stop box
and the Aravis cameras. The whole main job on it (every target, TRE against the peers'
truth) is ``oralnav bench hil``: minutes on a 2-core machine."""

from __future__ import annotations

import json
import os
import signal
import urllib.request
from pathlib import Path

import httpx
import numpy as np
import pytest

from ..drivers.test_camera_aravis import GI_MISSING
from .test_service import _Api, _start_daemon, _wait_for_api

pytestmark = pytest.mark.skipif(GI_MISSING is not None, reason=str(GI_MISSING))


def test_the_daemon_navigates_the_hardware_in_the_loop_cell(tmp_path: Path) -> None:
    """On the peers' cell the daemon comes up READY with nothing refused; the stereo pair
    and the endoscope are tracked (the robot and opener fields seen in the rendered
    images); a started procedure moves the real arm peer toward the entry pose (the
    approach error falls by 5 mm or more, the peers' truth shows the TCP moved); abort
    holds it, and SIGTERM exits cleanly."""
    import logging

    from oralnav.cli.peers import HardwarePeers
    from oralnav.sim.peers.gige_fake import NoLoopbackAddress

    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    try:
        peers = HardwarePeers(tmp_path, ur_host=f"127.84.{os.getpid() % 250}.3",
                              cameras="rendered")
        peers.__enter__()
    except NoLoopbackAddress as exc:
        pytest.skip(f"no loopback address for three cameras: {exc}")
    proc = None
    try:
        assert peers.rendered is not None, "the rendered cameras did not start"
        assert set(peers.rendered.addresses) == {"left", "right", "endoscope"}
        with urllib.request.urlopen(peers.truth.url, timeout=5) as r:
            home = np.array(json.load(r)["T_B_tcp"])
        proc, base = _start_daemon(peers.write_config(), tmp_path)
        api = _Api(base, _wait_for_api(proc, base, tmp_path))
        st = api.until(lambda s: s["safety"]["state"] == "READY", "READY", timeout=60)
        st = api.until(lambda s: s["rates_hz"].get("tracking stereo", 0) > 0
                       and s["rates_hz"].get("tracking endoscope", 0) > 0, "tracking",
                       timeout=60)
        poses = httpx.get(f"{base}/poses", headers=api.observer, timeout=5).json()
        assert {"T_C_RM", "T_C_OM"} <= set(poses), sorted(poses)
        targets = {"targets": [{"name": "a", "p_OM": [0.102, 0.02, 0.01]}]}
        assert httpx.post(f"{base}/targets", json=targets, headers=api.operator,
                          timeout=5).status_code == 200
        assert api.post("/procedure/start") == 200
        first = api.until(lambda s: s["procedure"].get("error_mm") is not None,
                          "a first approach step", timeout=60)["procedure"]["error_mm"]
        api.until(lambda s: s["procedure"].get("error_mm", first) < first - 5.0
                  or s["safety"]["state"] != "RUNNING", "the approach moving", timeout=90)
        st = api.status()
        assert st["safety"]["state"] == "RUNNING", st["safety"]["reasons"]
        with urllib.request.urlopen(peers.truth.url, timeout=5) as r:
            moved = np.array(json.load(r)["T_B_tcp"])
        assert np.linalg.norm(moved[:3, 3] - home[:3, 3]) > 0.002
        assert api.post("/procedure/abort") == 200
        api.until(lambda s: s["safety"]["state"] == "READY", "READY after abort")
        assert st["latency_ms"]["n"] >= 1
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=30)
        assert proc.returncode == 0, err[-3000:]
    finally:
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.communicate()
        peers.__exit__(None, None, None)
