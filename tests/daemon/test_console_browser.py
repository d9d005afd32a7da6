"""Issue 33, items 1 and 2: the surgeon's web console in a real headless browser (Debian's
``chromium`` driven through its ``chromedriver`` by Selenium; nothing is downloaded) on a
running simulated daemon (``oralnavd`` as a process, the sim cell with a CB3 arm's 125 Hz
loop).

One browser session plays the surgeon: an observer token is refused an operator action
with a clear message; the operator signs in, sees the camera views update with the
tracked fields, registers the planned targets, selects one, starts the procedure, loses
the page mid-procedure (the procedure goes on; the console reconnects and shows the
truth), and stops it with the e-stop: the console and the API both say ESTOP. A stop on
the control loop's deadline alone (the shared 2-core machine stalling the loop under the
whole suite) is recovered from the console, Reset then Resume, at most twice; any other
stop fails the test. Screenshots
at 1280x800 mid-procedure and at a tablet viewport are saved under
``$ORALNAV_ARTIFACTS`` (default ``test-artifacts/``) as the test's artefacts.

Without chromium, chromedriver or selenium the test is skipped saying which is missing;
``./dev.sh test`` installs them (``.ci/run`` runs it).
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import time
from pathlib import Path

import httpx
import pytest

from .test_service import _free_port, _wait_for_api, sim_config, start_oralnavd

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
CHROMEDRIVER = shutil.which("chromedriver")
try:
    import selenium  # noqa: F401
    SELENIUM = True
except ImportError:  # pragma: no cover - the test extra installs it
    SELENIUM = False

_MISSING = [what for what, ok in (("the Debian package chromium", CHROMIUM),
                                  ("the Debian package chromium-driver", CHROMEDRIVER),
                                  ("the Python package selenium", SELENIUM)) if not ok]
pytestmark = pytest.mark.skipif(
    bool(_MISSING), reason=f"no browser to test the console: {', '.join(_MISSING)} "
                           "missing (./dev.sh test installs them)")

ROOT = Path(__file__).resolve().parents[2]
ARTIFACTS = Path(os.environ.get("ORALNAV_ARTIFACTS", ROOT / "test-artifacts"))
#: s: the longest wait for anything the console should show
WAIT_S = 30.0
#: s: the longest wait for a stage of the procedure (the busy-demo benchmark saw whole
#: procedures of 55 s with every core busy)
SLOW_WAIT_S = 120.0


@pytest.fixture
def daemon(tmp_path: Path):
    """``oralnavd`` on the embedded simulated cell: (base URL, demo tokens)."""
    port = _free_port()
    # its log in a file: a pipe nobody reads during the test would stall it when full
    proc = start_oralnavd(tmp_path, port, log=tmp_path / "oralnavd.log",
                          config=sim_config(tmp_path, CB3_CELL))
    try:
        base = f"http://127.0.0.1:{port}"
        yield base, _wait_for_api(proc, base, tmp_path)
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.communicate(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate()


# The simulated cell as a CB3 arm's (125 Hz) rather than an e-Series (500 Hz): this test is
# of the console, and CI's machine gives the loop normal scheduling (no SCHED_FIFO there).
# At normal priority the scheduler favours a process by how little CPU it has used, so a
# loop that wakes a quarter as often is picked promptly when it wakes: with three busy
# processes beside the daemon and the browser on 2 cores, the 500 Hz loop stalled past its
# 100 ms limit before the procedure started (deadline:stalled, 103 ms) in one of two runs
# here, the 125 Hz loop in neither; the whole procedure passed both times.
CB3_CELL = {"rate_hz = 500.0": "rate_hz = 125.0"}


@pytest.fixture
def browser():
    from oralnav.bench.console import headless_chromium

    driver = headless_chromium()
    try:
        yield driver
    finally:
        driver.quit()


def _wait(what: str, check, timeout: float = WAIT_S):
    """Poll ``check()`` until it returns something truthy; fail naming ``what``."""
    deadline = time.monotonic() + timeout
    while True:
        got = check()
        if got:
            return got
        assert time.monotonic() < deadline, f"the console never showed {what}"
        time.sleep(0.1)


# alone: beside the parallel suite on 2 cores the daemon did not reach READY within the
# 30 s wait in two clean-clone runs on 2026-11-27 (it takes 26 s in all by itself)
@pytest.mark.alone
def test_a_surgeon_runs_and_stops_the_procedure_from_the_console(daemon, browser) -> None:
    """Done when (issue 33): a person can run the procedure and stop it from the console
    alone; the screenshot shows the console mid-procedure. Bad input: an observer's click
    on an operator action is refused clearly; a page lost mid-procedure does not stop it,
    and the console comes back showing the truth."""
    from selenium.webdriver.common.by import By

    base, tokens = daemon
    d = browser
    by_id = lambda i: d.find_element(By.ID, i)  # noqa: E731
    ARTIFACTS.mkdir(parents=True, exist_ok=True)

    def sign_in(token: str) -> None:
        by_id("token").clear()
        by_id("token").send_keys(token)
        by_id("login").find_element(By.TAG_NAME, "button").click()
        _wait("the signed-in page", lambda: by_id("main").is_displayed())

    def notice() -> str:
        return by_id("notice").text if by_id("notice").is_displayed() else ""

    d.get(base + "/")
    assert by_id("estop").is_displayed()  # visible before anyone signs in
    by_id("token").send_keys("not-a-token")
    by_id("login").find_element(By.TAG_NAME, "button").click()
    _wait("the refusal of an unknown token", lambda: "unknown token" in by_id("login-error").text)

    # an observer sees, and is refused an operator's action with the reason
    sign_in(tokens["observer"])
    _wait("the state READY", lambda: by_id("state").text == "READY")
    by_id("planned").click()
    _wait("the observer's refusal",
          lambda: "refused" in notice() and "operator token is needed" in notice())
    head = {"Authorization": f"Bearer {tokens['operator']}"}
    assert httpx.get(f"{base}/targets", headers=head).json()["targets"] == []  # nothing done
    by_id("signout").click()

    sign_in(tokens["operator"])
    # the live views: the stereo pair and the endoscope, updating, fields drawn
    left = _wait("the left view", lambda: d.find_elements(
        By.CSS_SELECTOR, "figure.view[data-camera=left][data-counter]"))[0]
    first = int(left.get_attribute("data-counter"))
    _wait("the left view updating", lambda: int(left.get_attribute("data-counter")) > first)
    cams = {e.get_attribute("data-camera") for e in d.find_elements(By.CSS_SELECTOR,
                                                                    "figure.view")}
    assert cams == {"left", "right", "endoscope"}
    assert "opener" in left.text and "robot" in left.text  # the fields tracked in it

    # the planned targets, one selected, then the start
    by_id("planned").click()
    rows = _wait("the registered targets", lambda: d.find_elements(
        By.CSS_SELECTOR, "#targets li[data-name]"))
    assert [r.get_attribute("data-name") for r in rows] == [
        "stitch_1", "stitch_2", "stitch_3", "stitch_4"]
    rows[2].find_element(By.CSS_SELECTOR, "input[type=radio]").click()
    by_id("select").click()
    _wait("the selection done", lambda: "Select stitch_3: done" in notice())
    assert httpx.get(f"{base}/status", headers=head).json()["selected_target"] == "stitch_3"
    d.find_element(By.CSS_SELECTOR, "button[data-post='/procedure/start']").click()
    _wait("RUNNING", lambda: by_id("state").text == "RUNNING")

    stalls: list[str] = []

    def recover_from_a_loop_stall(st: dict) -> bool:
        """A stop on the control loop's deadline alone is recovered from the console as
        an operator would: Reset, then Resume (the procedure goes on where it stood). The
        loop runs at normal priority on a shared 2-core machine, which with the whole
        suite and a browser on it stalled the loop past its limit (108 ms), a stop the
        product rightly makes; this test is of the console. At most twice; any other
        stop fails the test."""
        sf = st["safety"]
        if sf["state"] != "FAULT" or len(stalls) >= 2 or not sf["reasons"] or not all(
                c["source"] == "control loop" and c["reason"].startswith("deadline")
                for c in sf["reasons"]):
            return False
        stalls.append(sf["reasons"][0]["reason"])
        d.find_element(By.CSS_SELECTOR, "button[data-post='/reset']").click()
        _wait("READY after the reset", lambda: by_id("state").text == "READY")
        d.find_element(By.CSS_SELECTOR, "button[data-post='/procedure/resume']").click()
        _wait("RUNNING again", lambda: by_id("state").text == "RUNNING")
        return True

    def stage(*names: str) -> bool:
        """The console shows one of ``names``; a stop of the procedure fails at once
        (but for a loop stall, recovered)."""
        if by_id("state").text in ("FAULT", "ESTOP", "READY"):
            st = httpx.get(f"{base}/status", headers=head).json()
            if recover_from_a_loop_stall(st):
                return False
            why = "; ".join(f"{c['source']}: {c['reason']}" for c in st["safety"]["reasons"])
            raise AssertionError(f"the procedure stopped ({st['safety']['state']}: {why}; "
                                 f"stalls recovered before: {stalls}): {st['procedure']}")
        return by_id("stage").text in names

    # mid-procedure: the page goes away; the daemon goes on without it. (The stages take
    # as long as tracking makes them: longer on a busy machine, hence the longer waits.)
    _wait("the intra-oral stages", lambda: stage("adjust", "targets"), SLOW_WAIT_S)
    d.get("about:blank")
    time.sleep(1.0)
    st = httpx.get(f"{base}/status", headers=head).json()
    d.get(base + "/")  # the token is kept for the tab: no new sign-in
    _wait("the console back, live", lambda: by_id("link").text == "live")
    if st["safety"]["state"] != "RUNNING":
        assert recover_from_a_loop_stall(st), st["safety"]
    _wait("the truth after reconnecting", lambda: by_id("state").text == "RUNNING")
    # the surgeon's choice is the first target visited
    _wait("the selected target steered to", lambda: stage("targets")
          and by_id("target").text == "stitch_3", SLOW_WAIT_S)
    _wait("the views updating again", lambda: d.find_elements(
        By.CSS_SELECTOR, "figure.view[data-camera=left][data-counter]"))
    time.sleep(0.5)  # one more view round, for the picture
    d.save_screenshot(str(ARTIFACTS / "console-mid-procedure-1280x800.png"))

    by_id("estop").click()
    _wait("ESTOP", lambda: by_id("state").text == "ESTOP")
    assert httpx.get(f"{base}/status", headers=head).json()["safety"]["state"] == "ESTOP"
    assert "console e-stop" in by_id("why").text or "E-stop: done" in notice()

    # a tablet: the e-stop still in sight, one column
    d.set_window_size(820, 1180)
    time.sleep(0.3)
    rect = by_id("estop").rect
    assert by_id("estop").is_displayed() and rect["x"] + rect["width"] <= 820
    d.save_screenshot(str(ARTIFACTS / "console-estop-tablet-820x1180.png"))
    if stalls:
        print(f"control-loop stalls recovered from the console: {stalls}")
