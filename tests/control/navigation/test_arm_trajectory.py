"""Issue 32 (time): navigation chains each tracked pose with the arm's TCP pose at that
pose's capture instant, interpolated in the arm's measured history; an instant the history
cannot place is a named TimingError, never a pose of another instant."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from oralnav.control.navigation.arm_trajectory import ArmTrajectory, TimingError


def _pose(t: float) -> np.ndarray:
    """A TCP moving at 20 mm/s along x and turning at 0.5 rad/s about a tilted axis."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(0.5 * t * np.array([0.0, 0.6, 0.8])).as_matrix()
    T[:3, 3] = [0.4 + 0.02 * t, 0.0, 0.3]
    return T


def _trajectory(times: np.ndarray, max_gap: float = 0.01) -> ArmTrajectory:
    return ArmTrajectory(times, np.stack([_pose(t) for t in times]), max_gap)


def test_pose_between_samples_is_the_motion_at_that_instant() -> None:
    """Between two 2 ms samples of a constant-velocity motion the interpolated pose is the
    true pose of that instant to 1e-12 m and rad (linear in position, geodesic in
    rotation); on a sample it is that sample."""
    traj = _trajectory(np.arange(0.0, 0.1, 0.002))
    for when in (0.0011, 0.0503, 0.0979, 0.098):
        T = traj.at(when)
        truth = _pose(when)
        assert np.linalg.norm(T[:3, 3] - truth[:3, 3]) < 1e-12
        assert Rotation.from_matrix(T[:3, :3].T @ truth[:3, :3]).magnitude() < 1e-12
    assert np.array_equal(traj.at(0.02), traj.T[10])


def test_newest_sample_is_an_instant_of_the_history() -> None:
    """The newest sample's own instant is placed (the boundary is inside)."""
    traj = _trajectory(np.arange(0.0, 0.01, 0.002))
    assert np.array_equal(traj.at(traj.newest), traj.T[-1])


@pytest.mark.parametrize("when, kind, words", [
    (-0.05, "older", "50.0 ms older than the arm history"),
    (0.2, "newer", "has not reported the frame's instant"),
])
def test_instants_outside_the_history_are_refused(when: float, kind: str,
                                                  words: str) -> None:
    """A frame older than the history, or newer than its newest sample, is refused with
    its kind and how far off it is."""
    traj = _trajectory(np.arange(0.0, 0.1, 0.002))
    with pytest.raises(TimingError, match=words) as err:
        traj.at(when)
    assert err.value.kind == kind


def test_a_gap_in_the_history_is_not_bridged() -> None:
    """Issue 32 (bad input: an arm history with a gap): an instant inside a silence longer
    than max_gap is refused; one beside it is still placed."""
    times = np.concatenate([np.arange(0.0, 0.02, 0.002), np.arange(0.1, 0.12, 0.002)])
    traj = _trajectory(times, max_gap=0.01)
    with pytest.raises(TimingError, match="gap of 82.0 ms") as err:
        traj.at(0.05)
    assert err.value.kind == "gap"
    traj.at(0.105)


def test_timestamps_that_go_back_are_refused() -> None:
    """Issue 32 (bad input: a clock that runs backwards): non-increasing timestamps are
    refused naming the sample; so is an empty history asked for a pose."""
    times = np.array([0.0, 0.002, 0.004, 0.003])
    with pytest.raises(TimingError, match="sample 3 at 0.003000 s follows 0.004000") as err:
        _trajectory(times)
    assert err.value.kind == "order"
    empty = ArmTrajectory(np.zeros(0), np.zeros((0, 4, 4)), 0.01)
    assert empty.newest == -math.inf
    with pytest.raises(TimingError, match="no arm pose") as err:
        empty.at(0.0)
    assert err.value.kind == "empty"


def test_bad_arguments_are_named() -> None:
    """Mismatched lengths and a non-positive max_gap are ValueErrors naming them."""
    with pytest.raises(ValueError, match="2 sample times for 1 poses"):
        ArmTrajectory(np.array([0.0, 1.0]), np.eye(4)[None], 0.01)
    with pytest.raises(ValueError, match="max_gap"):
        ArmTrajectory(np.zeros(1), np.eye(4)[None], 0.0)
