"""What the surgeon's console costs the tracking (issue 33, "Figures": console frame rate,
and the tracking rate with the console open, no drop beyond 5 %).

``oralnav bench console --out DIR [--seconds S] [--fps F] [--rounds N] [--json]`` starts
``oralnavd`` on the embedded simulated cell in a process of its own (the fault campaign's
``Daemon``: a configuration, a tokens file and the logs in DIR, a free loopback port),
waits until it is READY, then ``N`` times runs four windows of ``S`` seconds (the console
closed, open in a browser here, closed, open "on another machine") and a last closed
one, so every open window lies between two closed ones. "In a browser here": Debian's
headless chromium on this machine (Selenium through chromedriver), signed in with the
operator token, at ``F`` frames per second (the console's own setting). "On another
machine": the console's own traffic (the telemetry websocket subscribed to ``status`` and
``frames`` at ``F`` and 640 px) from a client thread here, whose CPU is measured apart.
In each window it counts the tracked rounds from the left camera's frame counter
(``GET /views`` at the window's start and end: the simulated cell renders a frame per
round), the daemon's CPU, and the frames each view showed. An open window's change is
against the mean of the closed windows either side of it: the machine drifts over a
minute by as much as the effect measured, and bracketing takes the drift out. It writes
``console.json`` into DIR and prints the summary: each kind's median change and range,
and the console's frames per second per view.
Needs the ``test`` extra (selenium) and the Debian packages chromium and chromium-driver.
"""

from __future__ import annotations

import json
import os
import shutil
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import httpx

from oralnav.bench.faults import Daemon, free_port, write_daemon_config, write_tokens

__all__ = ["headless_chromium", "main"]


def _say(msg: str) -> None:
    print(f"bench console: {msg}", file=sys.stderr, flush=True)


def headless_chromium(width: int = 1280, height: int = 800) -> Any:
    """Debian's chromium, headless at ``width`` x ``height``, driven by its chromedriver
    through Selenium (nothing downloaded from a browser vendor)."""
    from selenium import webdriver
    from selenium.webdriver.chrome.options import Options
    from selenium.webdriver.chrome.service import Service

    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    driver = shutil.which("chromedriver")
    if not chromium or not driver:
        raise RuntimeError("needs the Debian packages chromium and chromium-driver")
    opts = Options()
    opts.binary_location = chromium
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage",
                "--disable-gpu", f"--window-size={width},{height}"):
        opts.add_argument(arg)
    return webdriver.Chrome(service=Service(driver), options=opts)


def _left_counter(base: str, head: dict[str, str]) -> tuple[int, float]:
    cams = httpx.get(f"{base}/views", headers=head, timeout=2.0).json()["cameras"]
    left = next(c for c in cams if c["name"] == "left")
    return int(left["counter"]), time.monotonic()


def _cpu_s(pid: int) -> float:
    """CPU seconds (user + system) process ``pid`` has used (Linux ``/proc``)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _shown(driver: Any) -> dict[str, int]:
    from selenium.webdriver.common.by import By

    return {e.get_attribute("data-camera"): int(e.get_attribute("data-counter") or -1)
            for e in driver.find_elements(By.CSS_SELECTOR, "figure.view[data-counter]")}


class _RemoteConsole:
    """The console's traffic without a browser, as when the console runs on another
    machine (a tablet): the telemetry websocket subscribed to ``status`` and ``frames``
    at ``fps`` and 640 px, as ``console.js`` does, each frame's header read and its JPEG
    kept (not decoded: the other machine's work); in a thread, until stopped."""

    def __init__(self, base: str, token: str, fps: int) -> None:
        import threading

        self.base, self.token, self.fps = base, token, fps
        self.shown: dict[str, int] = {}
        #: s of CPU this client's thread used (its share of this machine)
        self.cpu_s = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="remote console",
                                        daemon=True)

    def start(self) -> _RemoteConsole:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)

    def _run(self) -> None:
        from websockets.sync.client import connect

        url = self.base.replace("http://", "ws://") + f"/telemetry?token={self.token}"
        with connect(url, max_size=2 ** 24) as ws:
            ws.send(json.dumps({"subscribe": ["status", "frames"],
                                "frames": {"fps": self.fps, "width": 640}}))
            cpu0 = time.thread_time()
            while not self._stop.is_set():
                self.cpu_s = time.thread_time() - cpu0
                try:
                    msg = ws.recv(timeout=0.5)
                except TimeoutError:
                    continue
                if isinstance(msg, bytes):  # a frame: header length, header, JPEG
                    n = int.from_bytes(msg[:4], "big")
                    name = json.loads(msg[4:4 + n])["camera"]
                    self.shown[name] = self.shown.get(name, 0) + 1


def _window(mode: str, base: str, head: dict[str, str], pid: int, driver: Any, token: str,
            fps: int, seconds: float) -> dict[str, Any]:
    """One window of ``seconds`` with the console ``mode`` (``closed``, ``browser`` here,
    ``remote``): the tracking rate, the daemon's CPU (its main process ``pid``: tracking,
    API; the control loop is a child), the frames each view showed, and for ``remote``
    the client's own CPU."""
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import Select

    remote = None
    if mode == "browser":
        driver.get(base + "/")  # signed in still: the tab keeps the token
        Select(driver.find_element(By.ID, "fps")).select_by_value(str(fps))
        time.sleep(2.0)  # the page up and its views flowing
        before = _shown(driver)
    else:
        driver.get("about:blank")
        time.sleep(1.0)
        if mode == "remote":
            remote = _RemoteConsole(base, token, fps).start()
            time.sleep(1.0)
            before = dict(remote.shown)
    try:
        n0, t0 = _left_counter(base, head)
        c0 = _cpu_s(pid)
        client0 = remote.cpu_s if remote is not None else 0.0
        time.sleep(seconds)
        n1, t1 = _left_counter(base, head)
        w: dict[str, Any] = {"mode": mode, "seconds": t1 - t0,
                             "tracking_hz": (n1 - n0) / (t1 - t0),
                             "daemon_cores": (_cpu_s(pid) - c0) / (t1 - t0)}
        if remote is not None:
            w["client_cores"] = (remote.cpu_s - client0) / (t1 - t0)
        if mode != "closed":
            after = _shown(driver) if remote is None else dict(remote.shown)
            w["shown_hz"] = {c: (after[c] - before.get(c, after[c])) / (t1 - t0)
                             for c in after}
    finally:
        if remote is not None:
            remote.stop()
    shown = ", ".join(f"{c} {v:.2f}" for c, v in w.get("shown_hz", {}).items())
    _say(f"console {mode}: tracking {w['tracking_hz']:.2f} rounds/s, daemon "
         f"{w['daemon_cores']:.2f} cores"
         + (f", remote client {w['client_cores']:.3f} cores" if "client_cores" in w else "")
         + (f"; frames shown per s: {shown}" if shown else ""))
    return w


def main(out: Path, *, seconds: float = 20.0, fps: int = 10, rounds: int = 2
         ) -> dict[str, Any]:
    """Run the measurement (module docstring); returns what ``console.json`` holds."""
    from selenium.webdriver.common.by import By

    out = out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    token = write_tokens(out / "tokens.toml")
    config = write_daemon_config(out / "oralnavd.toml", port=port,
                                 tokens_file=out / "tokens.toml",
                                 audit_log=out / "oralnav-audit.jsonl")
    head = {"Authorization": f"Bearer {token}"}
    windows: list[dict[str, Any]] = []
    with Daemon(config, out / "oralnavd.log", port, token) as daemon:
        daemon.wait_ready()
        _say(f"oralnavd READY on {base}; {rounds} x (closed, browser here, closed, remote) "
             f"windows of {seconds:g} s, then closed")
        driver = headless_chromium()
        try:
            driver.get(base + "/")
            driver.find_element(By.ID, "token").send_keys(token)
            driver.find_element(By.CSS_SELECTOR, "#login button").click()
            order = [m for _ in range(rounds) for m in ("closed", "browser", "closed", "remote")]
            for mode in [*order, "closed"]:
                windows.append(_window(mode, base, head, daemon.pid, driver, token, fps,
                                       seconds))
        finally:
            driver.quit()
    return _summary(out, windows, seconds=seconds, fps=fps, rounds=rounds)


def _summary(out: Path, windows: list[dict[str, Any]], *, seconds: float, fps: int,
             rounds: int) -> dict[str, Any]:
    """Each open window's change against the mean of the closed windows either side of
    it (the machine's drift over a minute is of the size measured: bracketing takes it
    out), the median change per kind and its range; writes ``console.json``."""
    def median(mode: str, key: str = "tracking_hz") -> float | None:
        vals = [w[key] for w in windows if w["mode"] == mode]
        return statistics.median(vals) if vals else None

    for i, w in enumerate(windows):
        if w["mode"] != "closed":
            ref = (windows[i - 1]["tracking_hz"] + windows[i + 1]["tracking_hz"]) / 2
            w["tracking_change_pct"] = 100.0 * (w["tracking_hz"] - ref) / ref
    doc: dict[str, Any] = {"seconds": seconds, "fps_setting": fps, "rounds": rounds,
                           "cpus": os.cpu_count(), "tracking_hz_closed": median("closed"),
                           "daemon_cores_closed": median("closed", "daemon_cores")}
    for mode in ("browser", "remote"):
        changes = [w["tracking_change_pct"] for w in windows if w["mode"] == mode]
        shown = [v for w in windows if w["mode"] == mode for v in w["shown_hz"].values()]
        doc[mode] = {"tracking_hz": median(mode),
                     "tracking_change_pct": statistics.median(changes),
                     "tracking_change_pct_range": [min(changes), max(changes)],
                     "console_fps_per_view": statistics.median(shown) if shown else None,
                     "daemon_cores": median(mode, "daemon_cores")}
    doc["remote"]["client_cores"] = median("remote", "client_cores")
    doc["windows"] = windows
    (out / "console.json").write_text(json.dumps(doc, indent=2))
    return doc
