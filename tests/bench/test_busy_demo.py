"""Issue 32, item 6: ``oralnav bench busy-demo`` runs the main job repeatedly beside busy
processes and reports each run: passed or why not. Checked here with a stand-in for the
demo (the real one is the benchmark itself, minutes long): results parsed, failures named,
the busy processes gone afterwards."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from oralnav.bench import busy_demo


def _fake(doc: dict, rc: int = 0) -> list[str]:
    code = f"import json, sys; print(json.dumps({doc!r})); sys.exit({rc})"
    return [sys.executable, "-c", code]


def test_runs_are_recorded_and_summarised(tmp_path: Path) -> None:
    """Two passing stand-in runs beside one busy process: both passed, the TRE and the
    tracking rate come through, busy_demo.json is written, no busy process is left."""
    demo = {"demo": {"done": True, "duration_s": 12.5, "tre_mm": {"a": 0.03, "b": 0.05},
                     "rates_hz": {"tracking cell": 1.8, "other": 9.0}, "state": "READY"}}
    doc = busy_demo.main(tmp_path, runs=2, busy=1, command=_fake(demo))
    assert doc["passed"] == 2 and doc["failed"] == 0
    assert doc["tre_max_mm"] == 0.05 and doc["tracking_hz_min"] == 1.8
    assert doc["duration_s"] == {"median": 12.5, "max": 12.5}
    assert json.loads((tmp_path / "busy_demo.json").read_text())["passed"] == 2
    left = subprocess.run(["pgrep", "-f", "x = \\(x \\* 31"], capture_output=True, text=True)
    assert left.stdout.strip() == ""


def test_a_relative_folder_is_taken_from_here(tmp_path: Path, monkeypatch) -> None:
    """The runs' folders are absolute (the demo runs inside its folder: a relative state
    folder would nest): a stand-in that writes into $STATE_DIRECTORY writes under out."""
    monkeypatch.chdir(tmp_path)
    writer = [sys.executable, "-c", "import json, os, pathlib; p = pathlib.Path("
              "os.environ['STATE_DIRECTORY']) / 'x'; p.write_text('1'); "
              "print(json.dumps({'demo': {'done': True}}))"]
    doc = busy_demo.main(Path("rel"), runs=1, busy=0, command=writer)
    assert doc["passed"] == 1 and (tmp_path / "rel" / "run_0" / "x").exists()


def test_a_failed_run_says_why(tmp_path: Path) -> None:
    """A demo that ends NOT done (exit 1) is a failure with the demo's own reason; one
    that prints nothing is a failure naming its last stderr line."""
    demo = {"demo": {"done": False, "error": "the cell did not become READY within 60 s"}}
    doc = busy_demo.main(tmp_path, runs=1, busy=0, command=_fake(demo, rc=1))
    assert doc["failed"] == 1
    assert doc["failures"] == ["the cell did not become READY within 60 s"]
    silent = [sys.executable, "-c", "import sys; sys.stderr.write('boom\\n'); sys.exit(3)"]
    doc = busy_demo.main(tmp_path, runs=1, busy=0, command=silent)
    assert doc["failures"] == ["no JSON result on stdout: boom"]


def test_bad_counts_are_refused(tmp_path: Path) -> None:
    """--runs 0 or a negative --busy is a usage error (exit 2), nothing started."""
    from oralnav.cli.main import run

    assert run(["bench", "busy-demo", "--out", str(tmp_path), "--runs", "0"]) == 2
    assert run(["bench", "busy-demo", "--out", str(tmp_path), "--busy", "-1"]) == 2
    with pytest.raises(ValueError, match="runs must be at least 1"):
        busy_demo.main(tmp_path, runs=0)
