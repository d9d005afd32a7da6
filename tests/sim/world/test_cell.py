"""Tests of ``oralnav.sim.world.cell``: the moving simulated cell the sim cameras render from.

One cell is shared by the module (ray maps take seconds per camera); each test sets the
state it needs. Each test's docstring names the requirement it checks (issue 4 sim cell).
"""

from __future__ import annotations

import threading
from pathlib import Path

import numpy as np
import pytest

from oralnav.config.cell import load_cell_config
from oralnav.config.scene import load_scene
from oralnav.control.geometry import invert, pose_error, transform_from_euler
from oralnav.control.vision.tracker import Tracker
from oralnav.sim.world.cell import CellError, SimCell, wrist_transform

EXAMPLES = Path(__file__).resolve().parents[3] / "config" / "examples"
CELL = EXAMPLES / "sim_cell.toml"
STEREO = load_scene(EXAMPLES / "stereo_cell.toml")
ENDOSCOPE = load_scene(EXAMPLES / "endoscope_view.toml")


class State:
    """The arm, wrist and clock the cell reads; counts the reads."""

    def __init__(self, T_B_tcp: np.ndarray) -> None:
        self.T, self.q, self.t = T_B_tcp, np.zeros(4), 10.0
        self.reads = {"arm": 0, "wrist": 0, "clock": 0}

    def arm(self) -> np.ndarray:
        self.reads["arm"] += 1
        return self.T

    def wrist(self) -> np.ndarray:
        self.reads["wrist"] += 1
        return self.q

    def clock(self) -> float:
        self.reads["clock"] += 1
        return self.t


@pytest.fixture(scope="module")
def config():
    return load_cell_config(CELL)


@pytest.fixture(scope="module")
def shared(config):
    state = State(config.home_T_B_tcp)
    cell = SimCell(config, state.arm, state.wrist, state.clock)
    cell.prepare()
    return cell, state


@pytest.fixture
def cell(shared, config):
    """The shared cell, reset to home with the wrist at zero."""
    c, state = shared
    state.T, state.q, state.t = config.home_T_B_tcp, np.zeros(4), 10.0
    return c, state


def _close(a: np.ndarray, b: np.ndarray, tol: float = 1e-9) -> None:
    np.testing.assert_allclose(a, b, rtol=0, atol=tol)


def test_home_stereo_view_matches_stereo_cell_toml(cell):
    """Issue 4 sim cell: the stereo view at the home pose matches stereo_cell.toml (T_C_RM,
    T_C_EM at q = 0, T_C_OM), every field is rendered in both cameras, EM is outside the
    mouth."""
    c, _ = cell
    c.capture(("left", "right"))
    truth = c.truth()
    assert not truth["effector_in_mouth"]
    for key, name in (("T_C_RM", "robot"), ("T_C_EM", "effector"), ("T_C_OM", "opener")):
        _close(truth[key], STEREO.placement(name).T_ref_field)
        _close(truth["cameras"]["left"][name].T_cam_field, truth[key])
        assert len(truth["cameras"]["right"][name].corner_ids) >= 12, name


def test_intraoral_view_matches_endoscope_view_toml(cell, config):
    """Issue 4 sim cell: at the intra-oral pose EM is inside the mouth, absent from the
    stereo truth and present in the endoscope truth where endoscope_view.toml places it."""
    c, state = cell
    state.T = config.intraoral_T_B_tcp
    c.capture(c.camera_names)
    truth = c.truth()
    assert truth["effector_in_mouth"]
    assert "T_C_EM" not in truth
    for cam in ("left", "right"):
        assert set(truth["cameras"][cam]) == {"robot", "opener"}, cam
    _close(truth["T_En_EM"], ENDOSCOPE.placement("effector").T_ref_field)
    assert len(truth["cameras"]["endoscope"]["effector"].corner_ids) >= 12
    # the endoscope on the opener sits in the mouth too
    assert c.geometry.in_mouth(truth["T_B_En"][:3, 3])


def test_moving_the_arm_moves_RM_and_EM_not_OM(cell):
    """Issue 4 sim cell: moving the arm moves the robot and effector fields rigidly with
    the TCP and leaves the opener (the still head) in place."""
    c, state = cell
    c.capture(("left",))
    before = c.truth()
    move = transform_from_euler([0.004, -0.006, 0.003], [2.0, -3.0, 4.0])
    state.T = move @ state.T
    c.capture(("left",))
    after = c.truth()
    for key in ("T_B_RM", "T_B_EM", "T_B_E0", "T_B_E"):
        _close(after[key], move @ before[key])
        assert pose_error(after[key], before[key])[0] > 1e-3, key
    for key in ("T_B_OM", "T_C_OM", "T_B_En"):
        _close(after[key], before[key], 0.0)
    _close(after["T_C_RM"], invert(after["T_B_C"]) @ after["T_B_RM"])
    _close(after["cameras"]["left"]["robot"].T_cam_field, after["T_C_RM"])
    _close(after["cameras"]["left"]["opener"].T_cam_field, before["T_C_OM"])


def test_wrist_joints_move_EM_relative_to_RM(cell):
    """Issue 4 sim cell: wrist joints (roll, pitch, yaw) move EM relative to RM through
    T_E0_E(q); the jaw does not move the frame; q = 0 is the zero frame."""
    c, state = cell
    link = c.geometry.wrist_link

    def T_RM_EM() -> np.ndarray:
        c.capture(())  # no camera: the truth alone
        t = c.truth()
        return invert(t["T_B_RM"]) @ t["T_B_EM"]

    rest = T_RM_EM()
    _close(wrist_transform(np.zeros(4), link), np.eye(4), 0.0)
    for q in ([0.3, 0, 0, 0], [0, 0.3, 0, 0], [0, 0, 0.3, 0], [0.2, -0.4, 0.5, 0]):
        state.q = np.array(q)
        assert pose_error(T_RM_EM(), rest)[1] > 0.1, q
        t = c.truth()
        _close(invert(t["T_B_E0"]) @ t["T_B_E"], wrist_transform(q, link))
    state.q = np.array([0.0, 0.0, 0.0, 0.8])
    _close(T_RM_EM(), rest)
    # the axes: roll and yaw turn about E's own origin, pitch swings it on a link-radius arc
    for q, dist in (([0.5, 0, 0, 0], 0.0), ([0, 0, 0.5, 0], 0.0),
                    ([0, np.pi / 2, 0, 0], np.sqrt(2) * link)):
        assert np.linalg.norm(wrist_transform(q, link)[:3, 3]) == pytest.approx(dist, abs=1e-12)
    R = wrist_transform([0, 0, 0.5, 0], link)[:3, :3]
    _close(R @ [0, 1, 0], [0, 1, 0])  # yaw is about y


def test_targets_lie_in_the_mouth_within_reach(cell, config):
    """Issue 4 sim cell: the 3-5 suture targets lie in the mouth box, within a few cm of
    the end-effector at the intra-oral pose; targets_B follows eq. 8 (T_B_OM p_OM)."""
    c, _ = cell
    g = c.geometry
    assert 3 <= len(config.targets_OM) <= 5
    E_B = g.poses(config.intraoral_T_B_tcp, np.zeros(4))["T_B_E"][:3, 3]
    targets_B = c.targets_B()
    assert set(targets_B) == set(config.targets_OM)
    for name, p_OM in config.targets_OM.items():
        assert np.all(p_OM >= g.mouth_min) and np.all(p_OM <= g.mouth_max), name
        _close(targets_B[name], g.T_B_OM[:3, :3] @ p_OM + g.T_B_OM[:3, 3])
        assert g.in_mouth(targets_B[name])
        assert np.linalg.norm(targets_B[name] - E_B) < 0.03, name


def test_capture_sizes_one_instant_and_counter(cell):
    """Issue 4 sim cell (FrameSource): capture returns fresh uint8 images of the rigs'
    sizes in the order asked, one timestamp from the clock, one read of the state per
    capture, and a frame counter for the noise draw."""
    c, state = cell
    state.t = 123.25
    reads = dict(state.reads)
    frame = c.frame
    images, t = c.capture(["endoscope", "left", "right"])
    assert t == 123.25 and c.truth()["time"] == 123.25
    assert list(images) == ["endoscope", "left", "right"]
    for name, img in images.items():
        rig = c.endoscope_rig if name == "endoscope" else c.stereo_rig
        w, h = rig[name].size
        assert img.shape == (h, w) and img.dtype == np.uint8, name
    assert {k: v - reads[k] for k, v in state.reads.items()} == {"arm": 1, "wrist": 1,
                                                                  "clock": 1}
    assert c.truth()["frame"] == frame and c.frame == frame + 1
    again, _ = c.capture(["left"])
    assert again["left"] is not images["left"]
    assert not np.array_equal(again["left"], images["left"])  # the next noise draw
    with pytest.raises(CellError, match="unknown camera"):
        c.capture(["left", "nose"])


def test_truth_needs_a_capture_and_captures_serialise(config):
    """Issue 4 sim cell: truth() describes the last capture (none yet is an error),
    captures from several threads are serialised (each counts one frame), and a malformed
    arm pose or joint vector is refused."""
    state = State(config.home_T_B_tcp)
    c = SimCell(config, state.arm, state.wrist, state.clock)
    with pytest.raises(CellError, match="no capture yet"):
        c.truth()
    errors: list[BaseException] = []

    def worker() -> None:
        try:
            for _ in range(20):
                c.capture(())
        except BaseException as exc:  # reported by the assertion below
            errors.append(exc)

    threads = [threading.Thread(target=worker) for _ in range(4)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert not errors and c.frame == 80 and c.truth()["frame"] == 79
    state.T = np.eye(3)
    with pytest.raises(CellError, match="arm_pose"):
        c.capture(())
    state.T, state.q = config.home_T_B_tcp, np.zeros(3)
    with pytest.raises(CellError, match="wrist_joints"):
        c.capture(())


def test_tracker_recovers_T_C_RM(cell):
    """Issue 4 sim cell (end to end): Tracker (NVG-BA) on one stereo capture at home
    recovers T_C_RM within 0.1 mm."""
    c, _ = cell
    images, _ = c.capture(c.stereo_rig.names)
    truth = c.truth()
    est = Tracker(c.stereo_rig, list(c.fields), method="nvgba").track(images)
    dt, dr = pose_error(est["robot"].T_ref_field, truth["T_C_RM"])
    assert dt < 1e-4 and np.degrees(dr) < 0.1, (dt, np.degrees(dr))
