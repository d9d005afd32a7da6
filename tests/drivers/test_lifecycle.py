"""Tests of drivers/lifecycle.py's LifecycleState, the start/close bookkeeping the driver
backends share (issue 31)."""

from __future__ import annotations

import pytest

from oralnav.drivers.errors import DriverInitError, DriverIOError
from oralnav.drivers.lifecycle import LifecycleState, Phase


def test_start_then_close():
    """issue 31 shared driver lifecycle: not started -> starting -> running -> closed; use
    is refused, naming the device and why, except while running."""
    life = LifecycleState()
    assert life.phase is Phase.NEW and not life.running and not life.closed
    assert life.refusal() == "not started"
    with pytest.raises(DriverIOError, match=r"^camera 'a': not started$"):
        life.check("camera 'a'")
    life.begin_start("twice")
    assert life.phase is Phase.STARTING and life.refusal() == "not started"
    with pytest.raises(DriverIOError, match=r"^camera 'a': not started$"):
        life.check("camera 'a'", during="read()")
    assert life.finish_start() is True
    assert life.running and life.refusal() is None
    life.check("camera 'a'")
    assert life.close() is True
    assert life.closed and not life.running and life.refusal() == "closed"
    with pytest.raises(DriverIOError, match=r"^camera 'a': closed$"):
        life.check("camera 'a'")
    with pytest.raises(DriverIOError, match=r"^camera 'a': closed during read\(\)$"):
        life.check("camera 'a'", during="read()")


def test_close_is_idempotent_and_final():
    """issue 31 shared driver lifecycle: only the first close() reports True (it releases the
    device); a closed driver never starts again, even one never started."""
    life = LifecycleState()
    assert life.close() is True
    assert life.close() is False
    with pytest.raises(DriverInitError, match="^arm 'x': start\\(\\) called twice$"):
        life.start("arm 'x': start() called twice")
    with pytest.raises(DriverInitError):
        life.begin_start("again")
    assert life.phase is Phase.CLOSED


def test_second_start_is_refused():
    """issue 31 shared driver lifecycle: start() twice, while starting or running, raises
    DriverInitError with the backend's message and leaves the phase alone."""
    life = LifecycleState()
    life.begin_start("first")
    with pytest.raises(DriverInitError, match="^second$"):
        life.begin_start("second")
    assert life.phase is Phase.STARTING
    life.finish_start()
    with pytest.raises(DriverInitError, match="^third$"):
        life.start("third")
    assert life.running


def test_close_during_start_wins():
    """issue 31 shared driver lifecycle: a close() that comes while start() awaits keeps the
    driver closed; finish_start() says so, so start() releases what it opened."""
    life = LifecycleState()
    life.begin_start("twice")
    assert life.close() is True
    assert life.finish_start() is False
    assert life.closed and life.close() is False
    assert repr(life) == "LifecycleState(CLOSED)"


def test_a_failed_start_may_be_retried_and_a_close_wins():
    """issue 31, the shared state machine: a start that failed returns to NEW, so the
    control process may start the device again (a UR controller that was off); a close()
    during the start keeps it CLOSED, and a start after close() gets its own message."""
    life = LifecycleState()
    life.begin_start("twice")
    life.abort_start()
    assert life.refusal() == "not started"
    life.begin_start("twice")            # the retry
    assert life.finish_start() and life.running
    other = LifecycleState()
    other.begin_start("twice")
    assert other.close()
    other.abort_start()
    assert other.closed
    with pytest.raises(DriverInitError, match="after close"):
        other.begin_start("twice", after_close="arm 'a': start() after close()")
