"""What a benchmark ran on, for its JSON: CPU count and model, Python, library versions."""

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
