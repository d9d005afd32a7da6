"""Issue 4, the service: ``oralnavd`` serves the simulated cell's REST API on loopback,
and SIGTERM stops the robot first and then exits cleanly (status 0, control process gone,
audit log intact)."""

from __future__ import annotations

import contextlib
import functools
import logging
import os
import re
import signal
import socket
import ssl
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from ..drivers.test_camera_aravis import ARAVIS_MISSING
from ..helpers import machine_stops_only

# alone (./dev.sh test runs these after the parallel suite, with the machine to itself):
# each runs a whole daemon whose 500 Hz loop, at normal scheduling beside the suite's
# workers on 2 cores, fell 100 periods behind in a row (deadline:misses) in clean-clone
# runs on a slow day: the main job, and the hardware cell on its protocol peers
pytestmark = pytest.mark.alone


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def sim_config(folder: Path, changes: dict[str, str]) -> Path:
    """A copy of the embedded sim configuration in ``folder``, its relative paths made
    absolute, with each line ``changes`` names (``"rate_hz = 500.0"``) replaced by its
    value (the line must be there once)."""
    config_dir = Path(__file__).resolve().parents[2] / "config"
    text = (config_dir / "sim.toml").read_text()

    def absolute(m: re.Match) -> str:
        path = config_dir / m.group(2)
        return f'{m.group(1)}"{path}"' if path.exists() else m.group(0)

    text = re.sub(r'^(\w+ = )"([^"]+)"', absolute, text, flags=re.M)
    for old, new in changes.items():
        lines = [ln for ln in text.splitlines() if ln.split("#")[0].strip() == old]
        assert len(lines) == 1, f"{old!r} is not one line of config/sim.toml"
        text = text.replace(lines[0], new)
    path = folder / "sim.toml"
    path.write_text(text)
    return path


def start_oralnavd(folder: Path, port: int, log: Path | None = None,
                   config: Path | None = None) -> subprocess.Popen:
    """``oralnavd`` on ``config`` (default: the embedded sim configuration), its API on
    ``port``, its state and demo tokens in ``folder``; its output piped (read it when it
    has ended), or written to ``log`` for a daemon that runs longer than a pipe's buffer
    holds."""
    env = dict(os.environ, STATE_DIRECTORY=str(folder), RUNTIME_DIRECTORY=str(folder))
    out = subprocess.PIPE if log is None else open(log, "w")  # noqa: SIM115
    args = ["--api-port", str(port)] + (["--config", str(config)] if config else [])
    try:
        return subprocess.Popen([sys.executable, "-m", "oralnav.daemon.main", *args],
                                env=env, cwd=folder, stdout=out, stderr=out, text=True)
    finally:
        if log is not None:
            out.close()  # the child holds its own descriptor


def _wait_for_api(proc: subprocess.Popen, base: str, folder: Path) -> dict[str, str]:
    """Wait (at most 60 s) for the daemon's /health; its demo tokens by name."""
    deadline = time.monotonic() + 60
    while True:
        assert proc.poll() is None, proc.stderr.read() if proc.stderr else "oralnavd exited"
        try:
            if httpx.get(f"{base}/health", timeout=0.5).status_code == 200:
                break
        except httpx.TransportError:
            pass
        assert time.monotonic() < deadline, "the API never came up"
        time.sleep(0.1)
    return dict(line.split() for line in (folder / "tokens.txt").read_text().splitlines())


def _hardware_cell(folder: Path, devices: str, cameras: str = "") -> Path:
    """A hardware-cell configuration in ``folder``: the shipped rig and fields, safety
    limits for a busy test machine, then ``devices`` and ``cameras`` (TOML tables)."""
    config_dir = Path(__file__).resolve().parents[2] / "config"
    path = folder / "cell.toml"
    path.write_text(f"""
name = "hardware-test"
[cell]
backend = "hardware"
rig = "{config_dir}/rigs/stereo.toml"
fields = "{config_dir}/fields/cell.toml"
[safety]
driver_silence = 0.5
# the busy-machine tolerances of config/sim.toml (why there): with 10 late periods in a
# row the 500 Hz loop, at normal scheduling beside the suite's workers, faulted on
# deadline:misses in a clean-clone run while this test waited for READY
max_period_lateness = 0.1
deadline_misses = 100
# the simulated GigE cameras send 10 frames/s, rendered on the same 2 loaded cores: a
# 0.2 s stall (the default) is two frames late, which a busy test run reaches
camera_stall = 1.0
""" + devices + cameras)
    return path


def _stereo_cameras(addresses: list[str]) -> str:
    """``[cameras.left]`` and ``[cameras.right]`` on simulated GigE cameras at
    ``addresses``, full sensor size (the rig's calibration) at 10 Hz."""
    return "".join(f'[cameras.{name}]\nbackend = "aravis"\ncamera_id = "{address}"\n'
                   'region = [0, 0, 1920, 1200]\nframe_rate = 10.0\n'
                   for name, address in zip(("left", "right"), addresses, strict=True))


def _start_daemon(config: Path, folder: Path) -> tuple[subprocess.Popen, str]:
    """oralnavd on ``config`` with its state in ``folder``; the process and its API URL."""
    port = _free_port()
    env = dict(os.environ, STATE_DIRECTORY=str(folder), RUNTIME_DIRECTORY=str(folder))
    proc = subprocess.Popen([sys.executable, "-m", "oralnav.daemon.main", "--config",
                             str(config), "--api-port", str(port)], env=env, cwd=folder,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    return proc, f"http://127.0.0.1:{port}"


class _Api:
    """The daemon's REST API seen from a test: the status polled until a condition holds,
    and operator commands."""

    def __init__(self, base: str, tokens: dict[str, str]) -> None:
        self.base = base
        self.observer = {"Authorization": f"Bearer {tokens['observer']}"}
        self.operator = {"Authorization": f"Bearer {tokens['operator']}"}

    def status(self) -> dict:
        return httpx.get(f"{self.base}/status", headers=self.observer, timeout=2).json()

    def until(self, pred, what: str, timeout: float = 20.0) -> dict:
        """Poll /status until ``pred(status)``; the last status."""
        deadline = time.monotonic() + timeout
        while not pred(st := self.status()):
            assert time.monotonic() < deadline, (what, st["safety"]["state"],
                                                 st["safety"]["reasons"],
                                                 st["safety"]["history"][-4:], st["rates_hz"])
            time.sleep(0.05)
        return st

    def post(self, path: str) -> int:
        """An operator's POST; its HTTP status."""
        return httpx.post(f"{self.base}{path}", headers=self.operator, timeout=5).status_code

    def ready(self, resets: int = 2) -> dict:
        """Poll /status until READY; the status. A FAULT on the machine's stops alone (a
        loop stall, camera stalls: tests/helpers.py MACHINE_STOPS, seen in two clean-clone
        runs as the cell came up) is reset, as an operator would, at most ``resets``
        times; any other state fails as :meth:`until` does."""
        for _ in range(resets + 1):
            st = self.until(lambda s: s["safety"]["state"] == "READY" or (
                s["safety"]["state"] == "FAULT"
                and machine_stops_only(s["safety"]["reasons"])), "READY")
            if st["safety"]["state"] == "READY":
                return st
            logging.getLogger(__name__).warning("the cell faulted on the machine's stops; "
                                                "reset: %s", st["safety"]["reasons"])
            self.reset_when_allowed()
        return self.until(lambda s: s["safety"]["state"] == "READY", "READY")

    def reset_when_allowed(self, timeout: float = 20.0) -> None:
        """POST /reset until the daemon accepts it (the fault conditions have cleared)."""
        deadline = time.monotonic() + timeout
        while self.post("/reset") != 200:
            assert time.monotonic() < deadline, self.status()["safety"]
            time.sleep(0.2)


def test_sigterm_stops_the_robot_then_exits_cleanly(tmp_path: Path) -> None:
    """Start oralnavd on the embedded sim configuration, check /health and an operator
    command over HTTP, then SIGTERM: the daemon latches the stop, the control loop confirms
    it, and the process exits 0 within a few seconds."""
    port = _free_port()
    proc = start_oralnavd(tmp_path, port)
    try:
        base = f"http://127.0.0.1:{port}"
        tokens = _wait_for_api(proc, base, tmp_path)
        head = {"Authorization": f"Bearer {tokens['operator']}"}
        st = httpx.get(f"{base}/status", headers=head, timeout=2).json()
        assert st["control_loop"]["running"] is True
        r = httpx.post(f"{base}/estop", headers=head, json={"reason": "test"}, timeout=2)
        assert r.status_code == 200
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, err
    assert re.search(r"SIGTERM: stopping the robot first", err), err
    assert "stopped" in err
    audit = (tmp_path / "oralnav-audit.jsonl").read_text().splitlines()
    assert any('"/estop"' in line for line in audit)


def test_main_job_visits_every_target(tmp_path: Path) -> None:
    """The main job (`oralnavd --demo`): the daemon runs the two-stage navigation on the
    simulated cell while the demo plays the operator over REST; every suture target is
    reached with a TRE under 0.2 mm against ground truth, and it exits 0. The same run
    records the session (issue 33 item 4: `--record`, every 10th round's frames, cheap on
    CPU): the file is complete, nothing was dropped, and its rounds replay bit for bit. A
    run stopped by the machine alone (a loop stall, camera stalls: tests/helpers.py
    MACHINE_STOPS) is run once more; any other stop fails at once."""
    import json as _json

    from oralnav.cli.replay import replay

    def main_job(folder: Path) -> tuple[Path, subprocess.CompletedProcess, dict]:
        folder.mkdir()
        env = dict(os.environ, STATE_DIRECTORY=str(folder), RUNTIME_DIRECTORY=str(folder))
        proc = subprocess.run([sys.executable, "-m", "oralnav.daemon.main", "--demo",
                               "--json", "--api-port", str(_free_port()), "--record",
                               "demo.mcap", "--record-every", "10", "--record-compression",
                               "none"], env=env, cwd=folder, capture_output=True, text=True,
                              timeout=300)
        try:
            return folder, proc, _json.loads(proc.stdout)
        except ValueError:
            return folder, proc, {}

    folder, proc, doc = main_job(tmp_path / "first")
    if proc.returncode != 0 and machine_stops_only(doc.get("demo", {}).get("reasons")):
        logging.getLogger(__name__).warning("main job stopped by the machine; run again "
                                            "once: %s", doc["demo"]["reasons"])
        folder, proc, doc = main_job(tmp_path / "second")
    assert proc.returncode == 0, proc.stderr[-3000:]
    demo = doc["demo"]
    assert demo["done"] is True
    assert set(demo["tre_mm"]) == {"stitch_1", "stitch_2", "stitch_3", "stitch_4"}
    assert max(demo["tre_mm"].values()) < 0.2
    assert demo["rates_hz"]["tracking cell"] > 1.0
    rec = doc["recording"]
    assert rec["state"] == "stopped" and rec["path"] == str(folder / "demo.mcap"), rec
    assert rec["frames"]["dropped"] == 0 and rec["frames"]["written"] >= 3
    out = replay(folder / "demo.mcap")
    assert out["all_identical"] and out["poses"] >= 3 and not out["truncated"], out
    assert out["poses_recorded"] >= 2 * rec["rounds"]  # every pose of every round, kept


def test_daemon_runs_a_hardware_cell_on_protocol_peers(tmp_path: Path) -> None:
    """Issue 8 (done when: the daemon runs with the fake devices in place of the simulated
    ones): oralnavd on the [cell] backend = "hardware" configuration that
    oralnav.cli.peers writes for its peers drives the UR arm through ur_rtde against the
    fake UR controller, the wrist over Modbus TCP against the emulated
    drive unit, reads the serial e-stop box and the stereo pair from two simulated GigE
    cameras through Aravis; /status shows them connected, stereo pairs tracked and the cell
    READY; a protective stop faults the cell until the operator's POST /recover/arm (the
    dashboard recovery) and a reset; the box's e-stop latches ESTOP; SIGTERM exits
    cleanly."""
    import logging

    from oralnav.cli.peers import HardwarePeers

    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)
    with HardwarePeers(tmp_path, ur_host=f"127.84.{os.getpid() % 250}.1",
                       cameras="pattern" if ARAVIS_MISSING is None else "none") as peers:
        ur, box = peers.ur, peers.box
        cams = peers.camera_addresses
        config = peers.write_config()
        proc, base = _start_daemon(config, tmp_path)
        try:
            api = _Api(base, _wait_for_api(proc, base, tmp_path))
            st = api.ready()
            loop = st["control_loop"]
            assert loop["arm_connected"] and loop["wrist_connected"], loop
            assert loop["wrist_fault"] is None and st["inputs"]["connected"]
            if cams:  # stereo pairs arrive and are tracked (the fakes show no markers)
                api.until(lambda s: s["rates_hz"].get("tracking stereo", 0.0) > 0.0,
                          "stereo pairs tracked")
            # a protective stop: FAULT; reset refused until the operator's dashboard recovery
            ur.inject_protective_stop()
            api.until(lambda s: s["safety"]["state"] == "FAULT", "FAULT", timeout=10)
            assert api.post("/reset") == 409
            time.sleep(0.7)  # the controller's unlock delay (0.5 s for the peers)
            assert api.post("/recover/arm") == 200
            api.reset_when_allowed()
            api.until(lambda s: s["safety"]["state"] == "READY", "READY after the reset")
            box.press_estop()
            st = api.until(lambda s: s["safety"]["state"] == "ESTOP", "ESTOP", timeout=10)
            assert "emergency stop pressed" in str(st["safety"]["reasons"])
            assert st["inputs"]["estop_pressed"] and st["inputs"]["fault"] is None
            proc.send_signal(signal.SIGTERM)
            out, err = proc.communicate(timeout=30)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
    assert proc.returncode == 0, err[-3000:]


def test_an_unreachable_arm_and_camera_fault_the_cell_and_recover(tmp_path: Path) -> None:
    """Issue 8 (bad input: a wrong IP, recovery when the device returns): oralnavd on a
    hardware cell whose UR controller and stereo cameras are not there yet comes up and
    serves; the cell is in FAULT naming the arm and the cameras (the status says which
    controller address did not answer); once the controller and
    the cameras appear, the arm connects and pairs are tracked, and an operator reset
    brings the cell to READY."""
    from oralnav.sim.peers.ur import FakeURControllerProcess

    ur_host = f"127.84.{os.getpid() % 250}.2"
    with contextlib.ExitStack() as stack:
        cams, addresses = "", []
        if ARAVIS_MISSING is None:
            from oralnav.sim.peers.gige_fake import (
                FakeGvCamera,
                NoLoopbackAddress,
                loopback_address,
            )

            try:  # two cameras need two loopback addresses (aliases: root and iproute2)
                addresses = [stack.enter_context(loopback_address()) for _ in range(2)]
                cams = _stereo_cameras(addresses)
            except NoLoopbackAddress:
                addresses = []
        config = _hardware_cell(tmp_path, f"""
[arm]
backend = "ur"
[arm.ur]
host = "{ur_host}"
watchdog_timeout = 0.25
connect_timeout = 0.5
""", cams)
        proc, base = _start_daemon(config, tmp_path)
        try:
            api = _Api(base, _wait_for_api(proc, base, tmp_path))
            until = functools.partial(api.until, timeout=30.0)
            st = until(lambda s: s["safety"]["state"] == "FAULT", "FAULT")
            assert not st["control_loop"]["arm_connected"]
            st = until(lambda s: s["control_loop"]["arm_fault"], "why the arm is not there")
            assert ur_host in st["control_loop"]["arm_fault"], st["control_loop"]
            why = str(st["safety"]["reasons"])
            assert "arm" in why, why
            if cams:
                st = until(lambda s: "camera stereo" in str(s["safety"]["reasons"]),
                           "the cameras' fault")
                for address in addresses:
                    fake = FakeGvCamera(address, f"OX{address.split('.')[-1]:0>6}")
                    stack.callback(fake.close)
                    fake.start()
            stack.enter_context(FakeURControllerProcess(ur_host))
            until(lambda s: s["control_loop"]["arm_connected"], "the arm connected")
            if cams:
                until(lambda s: s["rates_hz"].get("tracking stereo", 0.0) > 0.0,
                      "stereo pairs tracked")
            api.reset_when_allowed()
            until(lambda s: s["safety"]["state"] == "READY", "READY")
            proc.send_signal(signal.SIGTERM)
            out, err = proc.communicate(timeout=30)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
    assert proc.returncode == 0, err[-3000:]
    assert f"{ur_host}" in err  # the log names the controller it could not reach


def test_https_and_demo_tokens_removed_at_exit(tmp_path: Path) -> None:
    """issue 30: with [api] tls_cert and tls_key the daemon serves HTTPS (a client that
    trusts the certificate reads /health); demo tokens generated into a temporary folder
    (no $RUNTIME_DIRECTORY) are removed when the daemon stops."""
    subprocess.run(["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "1",
                    "-subj", "/CN=127.0.0.1", "-addext", "subjectAltName=IP:127.0.0.1",
                    "-keyout", str(tmp_path / "key.pem"), "-out", str(tmp_path / "cert.pem")],
                   check=True, capture_output=True)
    config = _hardware_cell(tmp_path, '[api]\ntls_cert = "cert.pem"\ntls_key = "key.pem"\n'
                                      f'audit_log = "{tmp_path}/audit.jsonl"\n')
    temp = tmp_path / "tmp"
    temp.mkdir()
    port = _free_port()
    env = {k: v for k, v in os.environ.items() if k != "RUNTIME_DIRECTORY"}
    env["TMPDIR"] = str(temp)
    proc = subprocess.Popen([sys.executable, "-m", "oralnav.daemon.main", "--config",
                             str(config), "--api-port", str(port)], env=env, cwd=tmp_path,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        trust = ssl.create_default_context(cafile=str(tmp_path / "cert.pem"))
        while True:
            assert proc.poll() is None, proc.stderr.read()
            try:
                r = httpx.get(f"https://127.0.0.1:{port}/health", timeout=0.5, verify=trust)
                break
            except httpx.TransportError:
                assert time.monotonic() < deadline, "the API never came up"
                time.sleep(0.1)
        assert r.status_code == 200 and r.json()["ok"] is True
        with pytest.raises(httpx.TransportError):  # plain HTTP is not served
            httpx.get(f"http://127.0.0.1:{port}/health", timeout=2)
        (folder,) = list(temp.glob("oralnavd-*"))
        assert (folder / "tokens.txt").is_file()
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, err
    assert "https://127.0.0.1" in err
    assert list(temp.iterdir()) == [], "demo tokens left behind"
