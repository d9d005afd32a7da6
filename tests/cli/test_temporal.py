"""`oralnav calibrate temporal` (issue 32, "Time"): against a daemon's API it starts the
excitation, follows it and writes the calibration file the daemon loads; a kept record
fits again offline to the same offset; bad records and a refusing daemon are clear
errors that write nothing."""

from __future__ import annotations

import json
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import numpy as np
import pytest

from oralnav.cli import main as cli
from oralnav.cli.temporal import record_texts, write_record
from oralnav.config.calibration import load_calibration
from oralnav.control.calibration.temporal import estimate_time_offset
from tests.control.calibration.test_temporal import _record

APPLIED = 0.005  # s, what the daemon already subtracted while recording


def _samples(offset: float) -> dict:
    t, p, ta, pa = _record(offset, seed=7)
    return {"t_cam": t.tolist(), "p_C": p.tolist(), "t_arm": ta.tolist(), "p_B": pa.tolist()}


class _Daemon:
    """A stand-in for the daemon's two endpoints on loopback: the run is "moving" for
    two looks, then "done" with the fit of the record (or refused with 409)."""

    def __init__(self, samples: dict, refuse: str = "") -> None:
        fit = estimate_time_offset(np.array(samples["t_cam"]), np.array(samples["p_C"]),
                                   np.array(samples["t_arm"]), np.array(samples["p_B"]))
        self.result = {"offset_s": APPLIED + fit.offset_s, "sigma_s": fit.sigma_s,
                       **fit.as_dict()}
        self.samples, self.refuse, self.looks, self.posts = samples, refuse, 0, []
        outer = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *a):  # quiet
                pass

            def _send(self, code: int, doc: dict) -> None:
                body = json.dumps(doc).encode()
                self.send_response(code)
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            def do_POST(self):
                n = int(self.headers.get("Content-Length", 0))
                outer.posts.append((self.headers.get("Authorization"),
                                    json.loads(self.rfile.read(n))))
                if outer.refuse:
                    self._send(409, {"detail": outer.refuse})
                else:
                    self._send(200, {"phase": "moving"})

            def do_GET(self):
                outer.looks += 1
                doc = {"phase": "moving" if outer.looks < 3 else "done", "elapsed_s": 4.0,
                       "frames": 10, "arm_samples": 100, "error": None,
                       "applied_offset_s": APPLIED, "excitation": {"period_s": 3.0},
                       "result": outer.result if outer.looks >= 3 else None}
                if "samples=true" in self.path:
                    doc["samples"] = outer.samples
                self._send(200, doc)

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}"
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)

    def __enter__(self):
        self.thread.start()
        return self

    def __exit__(self, *exc):
        self.server.shutdown()
        self.server.server_close()
        self.thread.join()


def test_runs_on_the_daemon_writes_the_file_and_the_record_fits_again(tmp_path, capsys,
                                                                        monkeypatch):
    """--url: the excitation's figures are posted with the operator token, the result
    (applied offset + what the fit found) is written as a 'temporal' calibration the
    daemon's loader accepts; --samples on the kept record gives the same offset (to 1 us:
    the record keeps 1 ns and 1 nm)."""
    monkeypatch.setattr("oralnav.cli.temporal.POLL_S", 0.01)
    with _Daemon(_samples(0.025)) as d:
        rc = cli.run(["calibrate", "temporal", "--url", d.url, "--token", "tok",
                      "--amplitude-mm", "3", "--record", str(tmp_path / "rec"),
                      "--out", str(tmp_path / "temporal.toml"), "--cell", "c1", "--json"])
    assert rc == 0
    doc = json.loads(capsys.readouterr().out)
    assert d.posts == [("Bearer tok", {"amplitude_mm": 3.0, "period_s": 4.0,
                                       "duration_s": 24.0, "search_ms": 200.0})]
    assert abs(doc["offset_ms"] - (APPLIED + 0.025) * 1e3) < 1.0
    cal = load_calibration(tmp_path / "temporal.toml", kind="temporal", cell="c1")
    assert cal["offset_s"] == pytest.approx(doc["offset_ms"] * 1e-3)
    assert cal.quality["applied_while_recording_ms"] == pytest.approx(APPLIED * 1e3)
    rc = cli.run(["calibrate", "temporal", "--samples", str(tmp_path / "rec"), "--json"])
    again = json.loads(capsys.readouterr().out)
    assert rc == 0 and again["offset_ms"] == pytest.approx(doc["offset_ms"], abs=1e-3)


def test_a_refusal_or_a_bad_record_writes_nothing(tmp_path, capsys):
    """A daemon that refuses (409) and a record that is not rows of four numbers are
    exit 2 with the reason; an existing calibration file stays as it was."""
    out = tmp_path / "temporal.toml"
    out.write_text("previous")
    with _Daemon(_samples(0.01), refuse="cannot calibrate time in FAULT") as d:
        rc = cli.run(["calibrate", "temporal", "--url", d.url, "--token", "t",
                      "--out", str(out), "--cell", "c1"])
    assert rc == 2 and "409" in capsys.readouterr().err
    rec = tmp_path / "rec"
    write_record(rec, record_texts(_samples(0.01)), {"applied_offset_s": 0.0})
    (rec / "arm.txt").write_text("1 2 3\n4 5 6\n")
    rc = cli.run(["calibrate", "temporal", "--samples", str(rec), "--out", str(out),
                  "--cell", "c1"])
    assert rc == 2 and "arm.txt" in capsys.readouterr().err
    rc = cli.run(["calibrate", "temporal", "--samples", str(tmp_path / "none"),
                  "--out", str(out), "--cell", "c1"])
    assert rc == 2 and "not found" in capsys.readouterr().err
    rc = cli.run(["calibrate", "temporal", "--url", "http://127.0.0.1:9", "--token", "t"])
    assert rc == 2 and "cannot reach" in capsys.readouterr().err
    assert out.read_text() == "previous"
