"""Issue 32, item 3: the hardware-in-the-loop cameras give each frame the truth of the
capture it shows. A frame's PTP stamp reads back microseconds either side of its capture
instant; the capture it belongs to is found within ``STAMP_TOLERANCE_S``, never the one a
frame period before (that mistake gave a reached target the previous frame's truth)."""

from __future__ import annotations

from oralnav.sim.hil.cameras import STAMP_TOLERANCE_S, capture_at

#: capture instants of a 10 Hz camera (s, host monotonic)
INSTANTS = [10.0, 10.1, 10.2, 10.3]


def test_a_stamp_just_before_its_capture_gets_that_capture() -> None:
    """A stamp 20 us before the capture at 10.2 s is that capture, not the one at 10.1 s;
    one exactly on it or just after it is that capture too."""
    assert capture_at(INSTANTS, 10.2 - 20e-6) == 2
    assert capture_at(INSTANTS, 10.2) == 2
    assert capture_at(INSTANTS, 10.2 + 20e-6) == 2


def test_between_captures_the_earlier_one_answers() -> None:
    """An instant between two captures, farther than the tolerance from the next, is the
    earlier capture's (the newest at or before it); past the last, the last."""
    assert STAMP_TOLERANCE_S < 0.05
    assert capture_at(INSTANTS, 10.15) == 1
    assert capture_at(INSTANTS, 10.2 - 2 * STAMP_TOLERANCE_S) == 1
    assert capture_at(INSTANTS, 99.0) == 3


def test_an_instant_before_every_capture_has_none() -> None:
    """Before the oldest capture (beyond the tolerance) there is no capture: None, which
    truth_at turns into a named error and the TRE observer into no figure."""
    assert capture_at(INSTANTS, 9.9) is None
    assert capture_at(INSTANTS, 10.0 - 2 * STAMP_TOLERANCE_S) is None
    assert capture_at([], 10.0) is None
