"""Benchmarks record the machine they ran on: CPU count and model, Python, then the
libraries each benchmark names, in that order; and the build they ran, one name per tree
of source (issue 35: a resumed report or a cluster's workers never mix two builds)."""

from __future__ import annotations

import os
import platform
import subprocess
from pathlib import Path

from oralnav.bench.machine import commit, cpu_model, describe


def test_describe_names_the_machine_then_the_given_versions() -> None:
    """The common fields come first and the benchmark's own follow as given."""
    doc = describe(numpy="1.0", threads=2)
    assert list(doc) == ["cpus", "cpu", "python", "numpy", "threads"]
    assert doc["cpus"] == os.cpu_count() and doc["python"] == platform.python_version()
    assert doc["cpu"] == cpu_model() and doc["cpu"].strip()
    assert (doc["numpy"], doc["threads"]) == ("1.0", 2)


def test_the_build_names_the_commit_and_the_uncommitted_changes(tmp_path: Path) -> None:
    """A clean checkout is its commit; uncommitted edits add ``+dirty.<digest>`` of the
    edits, so two different edits on one commit are two builds, and undoing them gives
    the commit back."""
    def git(*args: str) -> str:
        return subprocess.run(["git", "-C", str(tmp_path), "-c", "user.name=t", "-c",
                               "user.email=t@t", *args], check=True, capture_output=True,
                              text=True).stdout.strip()

    git("init", "-q")
    (tmp_path / "a.py").write_text("x = 1\n")
    git("add", "a.py")
    git("commit", "-q", "-m", "one")
    head = git("rev-parse", "HEAD")
    assert commit(tmp_path) == head
    (tmp_path / "a.py").write_text("x = 2\n")
    first = commit(tmp_path)
    (tmp_path / "a.py").write_text("x = 3\n")
    second = commit(tmp_path)
    assert first.startswith(head + "+dirty.") and second.startswith(head + "+dirty.")
    assert first != second
    (tmp_path / "a.py").write_text("x = 1\n")
    assert commit(tmp_path) == head
