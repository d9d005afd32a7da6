"""Issue 33, item 6: the example recording of `oralnav sim aruco` (its CLI and tracking
are tested in tests/cli/test_examples.py): the bodies are the plates' printed markers,
and every tag stays whole in the image, facing the camera, through the motion."""

from __future__ import annotations

import numpy as np

from oralnav.control.geometry import transform_points
from oralnav.sim.world.aruco_video import (
    CAMERA,
    REFERENCE_PLATE,
    TAG_ID,
    TAG_PLATE,
    bodies,
    body_poses,
    field_body,
    plate_poses,
)


def test_field_body_is_the_sheets_markers():
    """issue 33 item 6: a plate's body holds one tag per ArUco marker of its sheet, each a
    square of the marker's side lying on the sheet (z = 0) inside the sheet."""
    body = field_body(REFERENCE_PLATE)
    assert body.ids == tuple(range(100, 112)) and body.dictionary == "DICT_ARUCO_ORIGINAL"
    w, h = REFERENCE_PLATE.sheet_size
    for corners in body.tags.values():
        sides = np.linalg.norm(np.roll(corners, -1, axis=0) - corners, axis=1)
        np.testing.assert_allclose(sides, REFERENCE_PLATE.marker, atol=1e-7)
        assert np.all(corners[:, 2] == 0)
        assert np.all((corners[:, :2] > 0) & (corners[:, :2] < [w, h]))
    assert TAG_ID in field_body(TAG_PLATE).ids


def test_every_tag_stays_in_view_facing_the_camera():
    """issue 33 item 6: over a whole motion period every tag corner projects at least 20
    px inside the image, and each plate's printed face (-z) turns toward the camera."""
    for frame in range(0, 40, 3):
        for name, T in plate_poses(frame).items():
            fld = REFERENCE_PLATE if name == "reference" else TAG_PLATE
            uv = CAMERA.project(transform_points(T, field_body(fld).corners()))
            assert np.all(uv > 20) and np.all(uv < np.array(CAMERA.size) - 20), (name, frame)
            face = -T[:3, 2]
            assert face @ -T[:3, 3] > 0, (name, frame)


def test_the_truth_puts_each_body_on_its_plate():
    """issue 33 item 6: the one-tag body is the tag centred on its origin, and each body's
    true pose puts its tags where its plate's markers are (the rendered pixels)."""
    tag = bodies()["tag"].tags[TAG_ID]
    np.testing.assert_allclose(tag.mean(axis=0), 0.0, atol=1e-9)
    for frame in (0, 7):
        truth, plates = body_poses(frame), plate_poses(frame)
        for name, body in bodies().items():
            fld = REFERENCE_PLATE if name == "reference" else TAG_PLATE
            on_plate = field_body(fld).corners(body.ids)
            np.testing.assert_allclose(transform_points(truth[name], body.corners()),
                                       transform_points(plates[name], on_plate), atol=1e-9)
