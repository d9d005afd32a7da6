"""Simulated calibration sessions (``oralnav.sim.world.calibration_views``): board poses that
cover the image, rendered and detected views, their ground truth.

Each test's docstring names the requirement it checks (the calibration views the camera
and stereo calibration are tested and benchmarked on).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from oralnav.config.rig import load_rig
from oralnav.control.geometry import invert
from oralnav.control.vision.markers import CylinderSurface, MarkerField
from oralnav.sim.world.calibration_views import (
    board_poses,
    default_board,
    default_distances,
    render_calibration_views,
)
from oralnav.sim.world.render import RenderError

ROOT = Path(__file__).resolve().parents[3]
STEREO = load_rig(ROOT / "config" / "rigs" / "stereo.toml")
ENDOSCOPE = load_rig(ROOT / "config" / "rigs" / "endoscope.toml")


@pytest.fixture(scope="module")
def endo_session():
    """Six endoscope views, with a progress record."""
    calls = []
    views = render_calibration_views(ENDOSCOPE["endoscope"], n=6, seed=4,
                                     progress=lambda done, total: calls.append((done, total)))
    return views, calls


def _tilt_deg(T_cam_board: np.ndarray, board: MarkerField) -> float:
    """Angle between the board's normal and the viewing ray to its centre (deg)."""
    centre = T_cam_board[:3, :3] @ [0.5 * board.sheet_size[0], 0.5 * board.sheet_size[1], 0]
    centre = centre + T_cam_board[:3, 3]
    c = T_cam_board[:3, 2] @ centre / np.linalg.norm(centre)
    return float(np.degrees(np.arccos(np.clip(c, -1, 1))))


def test_default_boards_suit_each_camera():
    """Default boards: a 12 x 9 board of 20 mm squares for the stereo pair, worked at about
    0.45-0.75 m, and a 16 x 12 board of 2 mm squares for the endoscope at 25-45 mm; markers
    0.6 of a square; an unknown kind is refused."""
    stereo, endo = default_board("stereo"), default_board("endoscope")
    assert stereo.squares == (12, 9) and stereo.square == pytest.approx(0.020)
    assert endo.squares == (16, 12) and endo.square == pytest.approx(0.002)
    for b in (stereo, endo):
        assert b.marker == pytest.approx(0.6 * b.square)
    near, far = default_distances(stereo, STEREO["left"])
    assert 0.40 < near < 0.5 and 0.7 < far < 0.8
    near, far = default_distances(endo, ENDOSCOPE["endoscope"])
    assert 0.02 < near < 0.03 and 0.04 < far < 0.05
    with pytest.raises(ValueError, match="kind must be one of"):
        default_board("microscope")


def test_board_poses_cover_the_image_with_varied_tilts():
    """Pose set: seeded and deterministic; the first four views of a camera put the board
    on the image's four corners, the next nine one per cell of a 3 x 3 grid; every board
    faces its camera tilted 15-45 deg from its viewing ray, about axes spread round the
    board's normal, at depths inside the working range."""
    cam = STEREO["left"]
    board = default_board("stereo")
    poses = board_poses(STEREO, board, 13, cameras=("left",), seed=7)
    again = board_poses(STEREO, board, 13, cameras=("left",), seed=7)
    other = board_poses(STEREO, board, 13, cameras=("left",), seed=8)
    assert all(np.array_equal(a, b) for a, b in zip(poses, again, strict=True))
    assert not all(np.allclose(a, b) for a, b in zip(poses, other, strict=True))
    centre_b = np.array([0.5 * board.sheet_size[0], 0.5 * board.sheet_size[1], 0.0])
    centres = np.array([cam.project_from(invert(cam.T_ref_cam) @ T, centre_b[None])[0]
                        for T in poses])
    w, h = cam.size
    assert np.allclose(centres[:4], [(0, 0), (w - 1, h - 1), (w - 1, 0), (0, h - 1)], atol=1e-6)
    # the inner targets span the central 84 % of the image (board_poses' centre_span)
    unit = (centres[4:] / (np.array([w, h]) - 1.0) - 0.5) / 0.84 + 0.5
    assert len({(int(3 * a), int(3 * b)) for a, b in unit}) == 9
    near, far = default_distances(board, cam)
    tilts, normals = [], []
    for T in poses:
        T_cam = invert(cam.T_ref_cam) @ T
        tilts.append(_tilt_deg(T_cam, board))
        normals.append(T_cam[:3, 2])
        depth = (T_cam[:3, :3] @ centre_b + T_cam[:3, 3])[2]
        assert near - 1e-9 <= depth <= far + 1e-9
    assert min(tilts) >= 15 - 1e-6 and max(tilts) <= 45 + 1e-6
    normals = np.array(normals)
    spread = np.degrees(np.arccos(np.clip(normals @ normals.T, -1, 1))).max()
    assert spread > 60


def test_board_poses_alternate_between_a_rigs_cameras():
    """Pose set of a rig: views are aimed at each camera in turn, so each camera gets its
    own corner views (board centred on its image corners)."""
    board = default_board("stereo")
    poses = board_poses(STEREO, board, 8, seed=1)
    centre_b = np.array([0.5 * board.sheet_size[0], 0.5 * board.sheet_size[1], 0.0])
    right = STEREO["right"]
    uv = right.project_from(invert(right.T_ref_cam) @ poses[1], centre_b[None])[0]
    assert np.allclose(uv, (0, 0), atol=1e-6)  # view 1 is the right camera's first corner


def test_bad_pose_requests_are_refused():
    """Bad input: an unknown camera, a curved board, an impossible tilt range, a bad
    distance range or no views raise errors that name the problem."""
    flat = default_board("stereo")
    curved = MarkerField("c", "DICT_4X4_1000", (12, 9), 0.003, 0.002,
                         surface=CylinderSurface(radius=0.02))
    with pytest.raises(Exception, match="unknown camera 'middle'"):
        board_poses(STEREO, flat, 4, cameras=("middle",))
    with pytest.raises(RenderError, match="must be flat"):
        board_poses(STEREO, curved, 4)
    with pytest.raises(RenderError, match="tilt_deg"):
        board_poses(STEREO, flat, 4, tilt_deg=(50, 30))
    with pytest.raises(RenderError, match="distance"):
        board_poses(STEREO, flat, 4, distance=(0.8, 0.5))
    with pytest.raises(RenderError, match="at least 1"):
        board_poses(STEREO, flat, 0)


def test_rendered_views_match_their_truth(endo_session):
    """Rendered session: a single camera becomes a one-camera rig; every view is rendered
    and detected with the project's detector; detected corners sit within a fraction of a
    pixel of the renderer's exact projections; each view's true board pose is reported;
    progress is reported after every view."""
    views, calls = endo_session
    cam = ENDOSCOPE["endoscope"]
    assert views.cameras == ("endoscope",) and len(views) == 6
    assert calls == [(k, 6) for k in range(1, 7)]
    assert views.render_s > 0
    errors = []
    for k, (det, tr) in enumerate(zip(views.views["endoscope"], views.truth["endoscope"],
                                      strict=True)):
        assert det is not None and tr is not None, k
        assert np.allclose(tr.T_cam_field, views.T_cam_board("endoscope")[k])
        index = {int(c): j for j, c in enumerate(tr.corner_ids)}
        # a corner counts as visible once it is in the image, but the detector needs a
        # whole marker beside it: boards hanging off the image edge lose their edge corners
        assert len(det) >= (0.6 if k < 4 else 0.8) * len(tr.corner_ids), k
        assert all(int(i) in index for i in det.ids)
        errors += [np.linalg.norm(p - tr.corners_px[index[int(i)]])
                   for i, p in zip(det.ids, det.px, strict=True)]
        assert np.all(det.px[:, 0] < cam.width) and np.all(det.px[:, 1] < cam.height)
    errors = np.array(errors)
    assert np.median(errors) < 0.1 and errors.max() < 0.5


def test_given_poses_and_seed_reproduce_a_session(endo_session):
    """Determinism: the same poses and seed render the same views (same corners, same
    pixels), so a benchmark can be rerun exactly."""
    views, _ = endo_session
    again = render_calibration_views(ENDOSCOPE["endoscope"], poses=views.T_ref_board[:2],
                                     seed=4)
    for a, b in zip(views.views["endoscope"][:2], again.views["endoscope"], strict=True):
        assert np.array_equal(a.ids, b.ids) and np.array_equal(a.px, b.px)
