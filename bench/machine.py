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


def commit() -> str:
    """The git commit of the installed oralnav source (``+dirty`` with uncommitted changes),
    or ``"unknown (oralnav <version>)"`` outside a git checkout."""
    import subprocess

    from oralnav import __version__

    here = Path(__file__).resolve().parent
    try:
        head = subprocess.run(["git", "-C", str(here), "rev-parse", "HEAD"], check=True,
                              capture_output=True, text=True, timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(here), "status", "--porcelain",
                                "--untracked-files=no"], check=True, capture_output=True,
                               text=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return f"unknown (oralnav {__version__})"
    return head + ("+dirty" if dirty else "")
