"""Issue 8 stereo synchronisation: pairing the frames of two cameras by trigger counter or
by timestamp, dropping (and counting) the frames that cannot pair.

The pairing logic is tested on hand-built frames; the reader (StereoCamera) on replayed
recordings and on two of Aravis's simulated GigE Vision cameras, each on its own loopback
address (see test_camera_aravis.py; skipped, with the reason, where they cannot run)."""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import anyio
import cv2
import numpy as np
import pytest

from oralnav.drivers.camera.base import CameraFrame
from oralnav.drivers.camera.replay import ReplayCamera
from oralnav.drivers.camera.stereo import FramePairer, StereoCamera, trigger_counter
from oralnav.drivers.errors import DriverInitError, DriverIOError
from tests.drivers.test_camera_aravis import ARAVIS_MISSING, running_fakes

IMAGE = np.zeros((2, 2), np.uint8)


@dataclass(frozen=True, eq=False)
class IdFrame(CameraFrame):
    """A frame with a camera frame id and link epoch, like the Aravis backend's."""

    frame_id: int
    epoch: int = 0


def frame(camera: str, t: float, counter: int = 0, frame_id: int | None = None,
          epoch: int = 0) -> CameraFrame:
    if frame_id is None:
        return CameraFrame(IMAGE, t, counter, camera)
    return IdFrame(IMAGE, t, counter, camera, frame_id, epoch)


def feed(pairer: FramePairer, frames: list[CameraFrame]) -> list[tuple[float, float]]:
    """Push frames in order; the pairs' (left, right) timestamps."""
    pairs = []
    for f in frames:
        pair = pairer.push(f)
        if pair is not None:
            assert list(pair) == list(pairer.names)
            pairs.append((pair["L"].timestamp, pair["R"].timestamp))
    return pairs


# -- pairing logic ------------------------------------------------------------------------


def test_timestamp_pairing_pairs_within_tolerance_and_drops_the_rest():
    """issue 8 stereo: by timestamp, frames within the tolerance pair whatever order they
    come in; a frame whose partner was lost is dropped and counted for its camera."""
    pairer = FramePairer(("L", "R"), tolerance=0.004)
    period = 1 / 30
    left = [frame("L", i * period, i) for i in range(8)]
    right = [frame("R", i * period + 0.002 * (-1) ** i, i) for i in range(8) if i != 3]
    # right runs one frame ahead of left, then behind
    order = left[:2] + right[:4] + left[2:6] + right[4:] + left[6:]
    pairs = feed(pairer, order)
    assert [round(lt / period) for lt, _ in pairs] == [0, 1, 2, 4, 5, 6, 7]
    assert all(abs(lt - rt) <= 0.004 for lt, rt in pairs)
    assert pairer.paired == 7 and pairer.dropped == {"L": 1, "R": 0}
    assert pairer.pending("L") == pairer.pending("R") == 0


def test_timestamp_pairing_takes_the_closest_frame_and_bounds_the_wait():
    """issue 8 stereo: a frame pairs with the closest frame of the other camera within the
    tolerance (the others are dropped); a camera that goes silent leaves at most
    max_pending frames of the other waiting, older ones dropped."""
    pairer = FramePairer(("L", "R"), tolerance=0.02)
    assert feed(pairer, [frame("R", 0.990), frame("R", 1.004), frame("R", 1.015),
                         frame("L", 1.006)]) == [(1.006, 1.004)]
    assert pairer.dropped == {"L": 0, "R": 1} and pairer.pending("R") == 1
    pairer = FramePairer(("L", "R"), tolerance=0.001, max_pending=3)
    feed(pairer, [frame("L", float(i)) for i in range(10)])
    assert pairer.pending("L") == 3 and pairer.dropped == {"L": 7, "R": 0}
    assert pairer.waiting_for() == "R"
    pairer.clear()
    assert pairer.pending("L") == 0 and pairer.dropped["L"] == 10
    with pytest.raises(DriverIOError, match="unknown camera 'X'"):
        pairer.push(frame("X", 0.0))


def test_counter_pairing_learns_the_offset_and_drops_frames_lost_in_transfer():
    """issue 8 stereo: by counter, the offset between the cameras' frame ids is learnt from
    the first timestamp match (across the 16-bit wrap's unwrapped ids); then frames pair on
    ids, and frames lost in transfer on either side (gaps in the ids) drop their partner
    exactly, whatever the arrival jitter within the tolerance."""
    pairer = FramePairer(("L", "R"), by="counter", tolerance=0.008)
    rng = np.random.default_rng(1)
    frames = []
    for k in range(40):
        t = 10.0 + k / 60
        if k not in (7, 20):
            frames.append(frame("L", t + 0.001, k, frame_id=500 + k))
        if k not in (12, 13):
            jitter = 0.0 if k == 0 else float(rng.uniform(-0.006, 0.006))
            frames.append(frame("R", t + jitter, k, frame_id=65530 + k))
    frames.sort(key=lambda f: f.timestamp)
    pairs = []
    for f in frames:
        pair = pairer.push(f)
        if pair:
            pairs.append(pair)
    assert pairer.offset == 500 - 65530
    assert all(p["L"].frame_id - p["R"].frame_id == pairer.offset for p in pairs)
    assert len(pairs) == 36 and pairer.dropped == {"L": 2, "R": 2}
    assert [trigger_counter(p["L"]) - 500 for p in pairs][:8] == [0, 1, 2, 3, 4, 5, 6, 8]


def test_counter_pairing_notices_a_missed_trigger():
    """issue 8 stereo: a camera that misses a trigger numbers its next exposure as the one
    it missed; the counter match is then a period off in time, so the offset is learnt
    again and pairing goes on right (the unpartnered frame dropped)."""
    pairer = FramePairer(("L", "R"), by="counter", tolerance=0.005)
    frames = []
    r_id = 70
    for k in range(10):
        t = k / 30
        frames.append(frame("L", t, k, frame_id=k))
        if k != 5:  # R never exposed on trigger 5
            frames.append(frame("R", t + 0.001, k, frame_id=r_id))
            r_id += 1
    pairs = feed(pairer, sorted(frames, key=lambda f: f.timestamp))
    assert len(pairs) == 9 and all(abs(lt - rt) <= 0.005 for lt, rt in pairs)
    assert pairer.dropped == {"L": 1, "R": 0} and pairer.offset == -69


def test_counter_pairing_relearns_after_a_reconnect_and_uses_a_given_offset():
    """issue 8 stereo: when a camera's epoch changes (reconnected) the counter offset is
    learnt again; a given counter_offset is used from the first frame; frames without a
    frame id pair on their delivered counter."""
    pairer = FramePairer(("L", "R"), by="counter", tolerance=0.002)
    feed(pairer, [frame("L", 1.0, frame_id=10), frame("R", 1.0, frame_id=20),
                  frame("L", 2.0, frame_id=11), frame("R", 2.0, frame_id=21)])
    assert pairer.offset == -10 and pairer.paired == 2
    # R reconnects: its ids go on from 22 but it missed two triggers (t=3, 4)
    pairs = feed(pairer, [frame("L", 3.0, frame_id=12), frame("L", 4.0, frame_id=13),
                          frame("R", 5.0, frame_id=22, epoch=1), frame("L", 5.0, frame_id=14),
                          frame("L", 6.0, frame_id=15), frame("R", 6.0, frame_id=23, epoch=1)])
    assert pairs == [(5.0, 5.0), (6.0, 6.0)] and pairer.offset == -8
    assert pairer.dropped == {"L": 2, "R": 0}
    fixed = FramePairer(("L", "R"), by="counter", counter_offset=2)
    pairs = feed(fixed, [frame("L", 0.0, 2), frame("R", 0.5, 0), frame("L", 0.1, 3),
                         frame("R", 0.9, 1)])
    assert pairs == [(0.0, 0.5), (0.1, 0.9)] and fixed.dropped == {"L": 0, "R": 0}


def test_pairer_arguments_are_checked():
    """issue 8 stereo: bad pairing arguments raise DriverInitError naming them."""
    for kwargs, why in [({"names": ("a", "a")}, "two different camera names"),
                        ({"by": "phase"}, "by must be"),
                        ({"tolerance": -1.0}, "tolerance must be"),
                        ({"counter_offset": 1.5}, "counter_offset must be"),
                        ({"max_pending": 0}, "max_pending must be")]:
        args = {"names": ("a", "b"), **kwargs}
        with pytest.raises(DriverInitError, match=why):
            FramePairer(**args)


# -- the reader, on recordings --------------------------------------------------------------


def _recording(path: Path, stamps: list[float]) -> Path:
    path.mkdir()
    rows = []
    for i, t in enumerate(stamps):
        cv2.imwrite(str(path / f"f{i}.png"), np.full((6, 8), i, np.uint8))
        rows.append(f"f{i}.png,{t!r}\n")
    (path / "timestamps.csv").write_text("file,timestamp\n" + "".join(rows))
    return path


async def test_stereo_camera_pairs_recordings_and_reports_drops(tmp_path, caplog):
    """issue 8 stereo: StereoCamera reads two cameras as pairs; a frame missing on one side
    drops its partner, counted per camera (and logged); cameras that never overlap end in
    DriverIOError naming the pairing, not in an endless read."""
    left = _recording(tmp_path / "left", [0.0, 0.1, 0.2, 0.3, 0.4, 0.5])
    right = _recording(tmp_path / "right", [0.001, 0.099, 0.302, 0.401, 0.5, 0.6])
    rig = StereoCamera(ReplayCamera(left, name="left"), ReplayCamera(right, name="right"),
                       tolerance=0.005)
    pairs = []
    with caplog.at_level(logging.WARNING, logger="oralnav.drivers.camera.stereo"):
        async with rig:
            for _ in range(5):
                pairs.append(await rig.read())
    assert [(p["left"].counter, p["right"].counter) for p in pairs] == [
        (0, 0), (1, 1), (3, 2), (4, 3), (5, 4)]
    assert rig.paired == 5 and rig.dropped == {"left": 1, "right": 0}
    assert "dropped frame 2 of 'left'" in caplog.text
    far = _recording(tmp_path / "far", [5.0 + 0.1 * i for i in range(6)])
    rig = StereoCamera(ReplayCamera(left, name="left", loop=True),
                       ReplayCamera(far, name="right", loop=True), max_unpaired=8)
    async with rig:
        with pytest.raises(DriverIOError, match="no pair in 8 frames .*by timestamp"):
            await rig.read()
    with pytest.raises(DriverInitError, match="stereo cameras must be Camera"):
        StereoCamera(ReplayCamera(left), object())  # type: ignore[arg-type]


async def test_a_failed_start_closes_both(tmp_path):
    """issue 8 stereo: when one camera fails to start, both are closed."""
    left = ReplayCamera(_recording(tmp_path / "left", [0.0, 0.1]), name="left")
    right = ReplayCamera(tmp_path / "missing", name="right")
    with pytest.raises(DriverInitError):
        async with StereoCamera(left, right):
            pass
    with pytest.raises(DriverIOError, match="closed"):
        await left.read()


# -- two simulated GigE Vision cameras ------------------------------------------------------


needs_aravis = pytest.mark.skipif(ARAVIS_MISSING is not None, reason=str(ARAVIS_MISSING))


@needs_aravis
async def test_two_fake_cameras_pair_by_trigger_counter():
    """issue 8 stereo: two simulated GigE cameras, software-triggered together, pair on
    their frame ids with the offset learnt (left numbered 3 ahead); a frame lost on one side
    leaves its partner unpaired, dropped and counted. (The fake serves software triggers in
    40 ms slots of the wall clock, and a busy machine delays it further: rounds are spaced,
    and the tolerance wide, to match.)"""
    from oralnav.drivers.camera.aravis import AravisCamera

    with running_fakes() as make:
        fake_l, fake_r = make(), make()
        options = {"region": (0, 0, 32, 24), "frame_rate": 1000.0, "trigger": "software",
                   "auto_trigger": False, "timeout": 1.0}
        left = AravisCamera(fake_l.address, name="left", **options)
        right = AravisCamera(fake_r.address, name="right", **options)
        async with StereoCamera(left, right, by="counter", tolerance=0.2) as rig:
            # the fake's first triggered frame can come late: take it out of the test, and
            # run left's ids 3 ahead of right's
            for cam, n in ((left, 4), (right, 1)):
                for _ in range(n):
                    await cam.software_trigger()
                    await cam.read()

            async def fire() -> None:
                await left.software_trigger()
                await right.software_trigger()
                await anyio.sleep(0.25)

            pairs = []
            for k in range(6):
                if k in (2, 4):  # a frame of one camera lost on its way to the rig
                    await fire()
                    await (left if k == 2 else right).read()
                await fire()
                pairs.append(await rig.read())
        assert rig.pairer.offset == 3
        assert all(p["left"].frame_id - p["right"].frame_id == 3 for p in pairs)
        assert np.all(np.diff([p["right"].frame_id for p in pairs]) >= 1)
        assert rig.paired == 6 and rig.dropped == {"left": 1, "right": 1}


@needs_aravis
async def test_two_free_running_fake_cameras_pair_by_timestamp():
    """issue 8 stereo: two free-running simulated GigE cameras at one rate pair by
    timestamp within half a frame period, on the device clock (the fakes stamp frames with
    this computer's clock, as PTP-synchronised cameras share one): after the frames the
    left camera sent before the right one started, nearly every frame pairs (a fake stalled
    by a busy machine skips a few); every frame read is paired, dropped or still waiting."""
    from oralnav.drivers.camera.aravis import AravisCamera

    with running_fakes() as make:
        fake_l, fake_r = make(), make()
        options = {"region": (0, 0, 32, 24), "frame_rate": 50.0, "timeout": 0.5,
                   "buffers": 32}
        left = AravisCamera(fake_l.address, name="left", **options)
        right = AravisCamera(fake_r.address, name="right", **options)
        async with StereoCamera(left, right, tolerance=0.01, clock="device") as rig:
            pairs = [await rig.read() for _ in range(5)]
            settled = sum(rig.dropped.values())
            pairs += [await rig.read() for _ in range(25)]
            read = {name: cam.delivered for name, cam in rig.cameras.items()}
            for name in read:
                assert read[name] == (rig.paired + rig.dropped[name]
                                      + rig.pairer.pending(name))
    gaps = [abs(p["left"].device_timestamp - p["right"].device_timestamp) for p in pairs]
    assert max(gaps) <= 0.01 and rig.paired == 30
    assert sum(rig.dropped.values()) - settled <= 10
