"""What a benchmark ran on, for its JSON: CPU count and model, Python, library versions,
and the commit it ran."""

from __future__ import annotations

import os
import platform
from pathlib import Path
from typing import Any


def cpu_model() -> str:
    """The CPU's model name (Linux ``/proc/cpuinfo``), else what ``platform`` says."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def describe(**versions: Any) -> dict[str, Any]:
    """``cpus``, ``cpu`` and ``python``, then ``versions`` (name -> version or setting)
    as given."""
    return {"cpus": os.cpu_count(), "cpu": cpu_model(), "python": platform.python_version(),
            **versions}


def commit(where: Path | None = None) -> str:
    """The git commit of the installed oralnav source (or of the checkout holding
    ``where``), or ``"unknown (oralnav <version>)"``
    outside a git checkout. With uncommitted changes to tracked files it is
    ``<commit>+dirty.<digest>``, the digest (12 hex digits) that of the changes themselves:
    two trees with different edits on one commit are two builds (a resumed report or a
    cluster's workers must not mix their results)."""
    import hashlib
    import subprocess

    from oralnav import __version__

    here = where or Path(__file__).resolve().parent

    def git(*args: str) -> bytes:
        return subprocess.run(["git", "-C", str(here), *args], check=True,
                              capture_output=True, timeout=10).stdout

    try:
        head = git("rev-parse", "HEAD").decode().strip()
        changes = git("diff", "HEAD", "--no-ext-diff", "--binary")
    except (OSError, subprocess.SubprocessError):
        return f"unknown (oralnav {__version__})"
    if not changes.strip():
        return head
    return f"{head}+dirty.{hashlib.sha1(changes).hexdigest()[:12]}"
