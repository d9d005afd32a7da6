"""Issue 33, item 1: the console's live views (``oralnav.daemon.live_views``): the tap only
keeps references (tracking never waits on a console), JPEGs are downscaled and encoded at
most ``max_hz`` times a second per camera whatever the polling, and the overlay puts each
tracked field where its estimated pose projects."""

from __future__ import annotations

import json
import struct
import time
from types import SimpleNamespace

import anyio
import cv2
import numpy as np
import pytest

from oralnav.control.vision.camera import CameraModel, Rig
from oralnav.daemon.capture_task import CapturedRound
from oralnav.daemon.live_views import AXIS_M, LiveViews, NoFrame

K = np.array([[800.0, 0, 320], [0, 800.0, 240], [0, 0, 1]])


def _rig() -> Rig:
    T_ref_right = np.eye(4)
    T_ref_right[0, 3] = 0.1  # the right camera 10 cm along x
    return Rig("left", {"left": CameraModel("left", (640, 480), K, np.zeros(5)),
                        "right": CameraModel("right", (640, 480), K, np.zeros(5),
                                             T_ref_right)})


def _round(counter: int, rig: Rig, T_ref_field: np.ndarray) -> CapturedRound:
    """A round of both cameras in which field ``opener`` was found at ``T_ref_field``,
    its inlier corners being a 4-point square around the projected origin."""
    frames, per_camera = {}, {}
    for cam in rig.names:
        img = np.full((480, 640), counter % 256, np.uint8)
        frames[cam] = SimpleNamespace(image=img, timestamp=100.0 + counter, counter=counter,
                                      camera=cam)
        T_cam_field = np.linalg.inv(rig[cam].T_ref_cam) @ T_ref_field
        o = rig[cam].project_from(T_cam_field, np.zeros((1, 3)))[0]
        square = o + np.array([[-20, -20], [20, -20], [20, 20], [-20, 20], [0, 0]])
        per_camera[cam] = (np.arange(5), square)
    est = SimpleNamespace(T_ref_field=T_ref_field, per_camera=per_camera, corners=10)
    view = SimpleNamespace(tracker=SimpleNamespace(rig=rig), frame="C",
                           suffixes={"opener": "OM"})
    return CapturedRound("stereo", frames, [(view, 100.0 + counter, {"opener": est})],
                         {"T_C_OM": 100.0 + counter})


def _pose(z: float = 0.5) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = (0.02, -0.01, z)
    return T


def test_the_tap_keeps_references_and_costs_microseconds():
    """Item 1 "never slowing tracking": the tap copies no pixels and returns at once."""
    views, rig = LiveViews(), _rig()
    rnd = _round(1, rig, _pose())
    t0 = time.perf_counter()
    for _ in range(1000):
        views.tap(rnd)
    per_tap = (time.perf_counter() - t0) / 1000
    assert per_tap < 200e-6, f"{per_tap * 1e6:.0f} us per tap"
    assert views._latest["left"].frame.image is rnd.frames["left"].image  # no copy


def test_overlay_projects_the_estimated_pose_in_each_camera():
    """Item 1 "the tracked fields drawn over the views": the axes' origin is the field
    origin projected through that camera's model (the right camera sees it shifted), the
    hull encloses the inlier corners, and the axes are AXIS_M long in the field."""
    views, rig = LiveViews(), _rig()
    T = _pose()
    views.tap(_round(1, rig, T))
    for cam in ("left", "right"):
        (f,) = views.overlay(cam)
        T_cam = np.linalg.inv(rig[cam].T_ref_cam) @ T
        o = rig[cam].project_from(T_cam, np.zeros((1, 3)))[0]
        x = rig[cam].project_from(T_cam, np.array([[AXIS_M, 0, 0]]))[0]
        assert f["name"] == "opener" and f["corners"] == 5
        assert np.allclose(f["axes"][0], o, atol=0.06)
        assert np.allclose(f["axes"][1], x, atol=0.06)
        assert len(f["hull"]) == 4  # the centre corner is inside
        assert cv2.pointPolygonTest(np.array(f["hull"], np.float32), o.astype(float),
                                    False) > 0
    left, right = views.overlay("left")[0], views.overlay("right")[0]
    assert left["axes"][0][0] - right["axes"][0][0] == pytest.approx(800 * 0.1 / 0.5, abs=0.2)


def test_jpeg_is_downscaled_and_encoded_at_most_max_hz_per_camera():
    """Item 1 "at a rate the operator can set, never slowing tracking": a console
    polling faster than ``max_hz`` gets the previous JPEG again (no encode), whatever
    size it asks; a new frame after 1/max_hz is encoded; the image is downscaled to the
    width asked; a frame already encoded at a size is served from the cache."""
    now = [0.0]
    views, rig = LiveViews(max_hz=5.0, clock=lambda: now[0]), _rig()
    views.tap(_round(1, rig, _pose()))
    data, counter, stamp = views.jpeg("left", width=320)
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    assert img.shape == (240, 320) and counter == 1 and stamp == 101.0
    views.tap(_round(2, rig, _pose()))
    again, counter, _ = views.jpeg("left", width=320)  # within 0.2 s: the same bytes
    assert again is data and counter == 1 and views.encodes == 1
    time.sleep(0.21)
    small, counter, _ = views.jpeg("left", width=320)
    assert counter == 2 and views.encodes == 2
    # another console's size within the period: the newest JPEG (the browser scales it),
    # so consoles of several sizes cannot multiply the encodes
    assert views.jpeg("left", width=480)[0] is small and views.encodes == 2
    time.sleep(0.21)
    big, _, _ = views.jpeg("left", width=1920)  # never upscaled
    assert cv2.imdecode(np.frombuffer(big, np.uint8), 0).shape == (480, 640)
    assert views.jpeg("left", width=320)[0] is small  # that frame at that size: kept
    assert views.encodes == 3


def test_unknown_camera_and_bad_sizes_are_clear_errors():
    """Bad input: an unknown camera names the ones with frames; width and quality out
    of bounds are ValueErrors naming the bounds."""
    views = LiveViews()
    with pytest.raises(NoFrame, match="none yet"):
        views.jpeg("left")
    views.tap(_round(1, _rig(), _pose()))
    with pytest.raises(NoFrame, match=r"'nope'.*left, right"):
        views.overlay("nope")
    with pytest.raises(ValueError, match="width must be 64..1920"):
        views.jpeg("left", width=10)
    with pytest.raises(ValueError, match="quality"):
        views.jpeg("left", quality=100)
    with pytest.raises(ValueError, match="max_hz"):
        LiveViews(max_hz=0)
    assert [c["name"] for c in views.cameras()] == ["left", "right"]


def test_a_frame_message_carries_its_own_overlay_and_jpeg():
    """Item 1 "the tracked fields drawn over the views": a pushed frame is one binary
    message, header then JPEG, and the header's overlay and counter are those of the frame
    in that JPEG (not of a newer one tapped since), made once for every console."""
    views, rig = LiveViews(max_hz=5.0), _rig()
    views.tap(_round(3, rig, _pose()))
    msg, counter = views.frame_message("right", width=320)
    (n,) = struct.unpack(">I", msg[:4])
    head = json.loads(msg[4:4 + n])
    img = cv2.imdecode(np.frombuffer(msg[4 + n:], np.uint8), cv2.IMREAD_UNCHANGED)
    assert counter == 3 and head["camera"] == "right" and head["counter"] == 3
    assert (head["width"], head["height"]) == (640, 480) and img.shape == (240, 320)
    assert head["stamp"] == 103.0 and head["fields"] == views.overlay("right")
    views.tap(_round(4, rig, _pose(0.6)))  # within 1/max_hz: the frame 3 message again
    again, counter = views.frame_message("right", width=320)
    assert again is msg and counter == 3 and views.encodes == 1
    assert views.overlay("right") != head["fields"]  # frame 4's overlay is elsewhere


async def test_wait_newer_wakes_on_the_next_round():
    """The frame push waits for rounds instead of polling: ``wait_newer`` returns at once
    when a round came after the generation seen, else at the next tap."""
    views, rig = LiveViews(), _rig()
    assert await views.wait_newer(-1) == 0
    woke = []

    async def waiter() -> None:
        woke.append(await views.wait_newer(0))

    async with anyio.create_task_group() as tg:
        tg.start_soon(waiter)
        await anyio.sleep(0.05)
        assert woke == []
        views.tap(_round(1, rig, _pose()))
    assert woke == [1]
