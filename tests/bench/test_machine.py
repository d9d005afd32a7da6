"""Benchmarks record the machine they ran on: CPU count and model, Python, then the
libraries each benchmark names, in that order."""

from __future__ import annotations

import os
import platform

from oralnav.bench.machine import cpu_model, describe


def test_describe_names_the_machine_then_the_given_versions() -> None:
    """The common fields come first and the benchmark's own follow as given."""
    doc = describe(numpy="1.0", threads=2)
    assert list(doc) == ["cpus", "cpu", "python", "numpy", "threads"]
    assert doc["cpus"] == os.cpu_count() and doc["python"] == platform.python_version()
    assert doc["cpu"] == cpu_model() and doc["cpu"].strip()
    assert (doc["numpy"], doc["threads"]) == ("1.0", 2)
