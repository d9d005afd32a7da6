"""Suite-wide fixtures: no test may leave threads or asyncio tasks behind."""

from __future__ import annotations

import asyncio
import os
import shutil
import tempfile
import threading
import time

import pytest


@pytest.fixture(autouse=True)
def no_leaked_threads(request):
    """Fail a test that leaves a thread running (drivers must close what they start). A
    test module may name, in ``LONG_LIVED_THREADS`` (a tuple of name prefixes), threads a
    library keeps for the whole process once used (Dask's, in tests/bench/test_executor.py)."""
    allowed = tuple(getattr(request.module, "LONG_LIVED_THREADS", ()))
    before = set(threading.enumerate())
    yield
    deadline = time.monotonic() + 1.0
    while True:
        leaked = [t for t in threading.enumerate() if t not in before and t.is_alive()
                  and not (allowed and t.name.startswith(allowed))]
        if not leaked or time.monotonic() > deadline:
            break
        time.sleep(0.01)
    assert not leaked, f"test left threads running: {[t.name for t in leaked]}"


@pytest.fixture
async def no_leaked_tasks():
    """Fail an async test that leaves asyncio tasks pending on its loop."""
    yield
    current = asyncio.current_task()
    for _ in range(5):  # let tasks that are finishing finish
        pending = [t for t in asyncio.all_tasks() if t is not current and not t.done()]
        if not pending:
            break
        await asyncio.sleep(0.01)
    assert not pending, f"test left asyncio tasks pending: {pending}"


def pytest_collection_modifyitems(items):
    for item in items:
        if item.get_closest_marker("asyncio") and "no_leaked_tasks" not in item.fixturenames:
            item.fixturenames.append("no_leaked_tasks")


_STATE_HOME: str | None = None


def pytest_configure(config):
    """Daemons the tests start keep their default state (the audit log) in a folder of
    this run, never in the user's ~/.local/state/oralnav (``daemon/audit.py``)."""
    global _STATE_HOME
    _STATE_HOME = tempfile.mkdtemp(prefix="oralnav-test-state-")
    os.environ["XDG_STATE_HOME"] = _STATE_HOME


def pytest_unconfigure(config):
    if _STATE_HOME:
        shutil.rmtree(_STATE_HOME, ignore_errors=True)
