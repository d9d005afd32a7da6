"""Issue 33, item 6: every command of README.md's "Tools" section runs as written, in
order, in a folder holding nothing but a copy of the shipped `config/` (a fresh clone's
files), and writes only under `out/`. The lines are read from the README itself, so the
README cannot drift from the tools again. Lines that need a running daemon or its
recording, run until stopped, or are benchmarks (minutes) are only parsed."""

from __future__ import annotations

import contextlib
import io
import json
import shlex
import shutil

import pytest

from oralnav.cli import main as cli
from tests.helpers import ROOT

README = ROOT / "README.md"
TOOL = ".venv/bin/oralnav"
#: Command prefixes parsed but not run, and why.
NOT_RUN = {
    ("bench",): "a benchmark (minutes)",
    # the quick report is 5 minutes on two cores; tests/bench/report runs each of its
    # experiments at test sizes, and tests/cli/test_report.py the command
    ("report",): "the papers' experiments (minutes)",
    ("sim", "peers"): "runs protocol peers until stopped",
    ("calibrate", "temporal"): "needs a running daemon",
    ("replay",): "reads a daemon's recording",
}
#: The lines whose inputs the README once left to the reader (issue 33 item 6): each must
#: stay in the README and run.
MUST_RUN = [("sim", "aruco"), ("sim", "pivot"), ("calibrate", "pivot"), ("plan", "mouth"),
            ("plan", "fpsm"), ("track", "--calibration")]


def tools_lines() -> list[list[str]]:
    """The shell lines of the README's Tools code block, continuations joined, comments
    dropped, each split as the shell would."""
    text = README.read_text()
    section = text.split("\n## Tools\n", 1)[1].split("\n## ", 1)[0]
    block = section.split("```sh\n", 1)[1].split("\n```", 1)[0]
    return [shlex.split(line, comments=True)
            for line in block.replace("\\\n", " ").splitlines() if line.strip()]


def _skip_reason(args: list[str]) -> str | None:
    for prefix, why in NOT_RUN.items():
        if tuple(args[:len(prefix)]) == prefix:
            return why
    return None


def test_the_tools_block_is_found():
    """issue 33 item 6: the parser finds the Tools block and the tool lines the README
    must keep runnable."""
    lines = [argv[1:] for argv in tools_lines() if argv[0] == TOOL]
    for want in MUST_RUN:
        assert any(tuple(a[:len(want)]) == want for a in lines), want


def test_every_tools_line_runs_on_a_fresh_clone(tmp_path, monkeypatch):
    """issue 33 item 6: each `oralnav` line of the Tools section, run in order (in this
    process, to save start-ups) in a folder with only `config/`, exits 0; a `--json` line
    prints exactly one JSON object; the ArUco bodies and the pointer tip come out; nothing
    is written outside `out/`. Lines it does not run still parse."""
    shutil.copytree(ROOT / "config", tmp_path / "config",
                    ignore=shutil.ignore_patterns("__pycache__", "*.py"))
    monkeypatch.chdir(tmp_path)
    parser = cli.build_parser()
    docs: dict[tuple[str, ...], dict] = {}
    ran = []
    for argv in tools_lines():
        if argv[0] != TOOL:
            continue  # oralnavd (the daemon) and ./dev.sh (the benchmarks)
        args = argv[1:]
        if _skip_reason(args):
            parser.parse_args(args)  # an option renamed since is still caught
            continue
        out, err = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            rc = cli.run(args)
        assert rc == 0, f"{shlex.join(argv)} -> {rc}\n{err.getvalue()[-2000:]}"
        if "--json" in args:
            lines = out.getvalue().strip().splitlines()
            assert len(lines) == 1, (args, lines)
            docs[tuple(args[:2])] = json.loads(lines[0])
        ran.append(args)
    for want in MUST_RUN:
        assert any(tuple(a[:len(want)]) == want for a in ran), want
    assert sorted(p.name for p in tmp_path.iterdir()) == ["config", "out"]
    aruco = docs[("track", "--calibration")]["frames"]
    assert len(aruco) == 3 and all(set(f["bodies"]) == {"reference", "tag"} for f in aruco)
    tip = docs[("calibrate", "pivot")]["tip_offset"]
    assert tip == pytest.approx([15.0, 70.0, 5.0], abs=0.3)  # what sim pivot states
