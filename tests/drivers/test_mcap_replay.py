"""The MCAP camera backend (``oralnav.drivers.camera.mcap_replay``, issue 33 item 4): the
images of an MCAP file (Foxglove RawImage or CompressedImage) played as cameras, rounds
made of the images that share a sequence number, a cut file played up to the cut, a file
that is not MCAP refused at start."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from mcap_protobuf.writer import Writer

from oralnav.drivers.camera import open_camera
from oralnav.drivers.camera.mcap_replay import McapRig
from oralnav.drivers.errors import DriverInitError, EndOfStream

ROUNDS = 5


def _image(i: int, cam: int) -> np.ndarray:
    rng = np.random.default_rng(10 * i + cam)
    return rng.integers(0, 256, (24, 32), dtype=np.uint8)


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    """Two cameras, ``a`` raw and ``b`` PNG, ROUNDS rounds (sequence 10, 11, ...), camera
    b's image of the third round missing; small chunks so a cut lands in the data."""
    path = tmp_path_factory.mktemp("mcap") / "cams.mcap"
    with open(path, "wb") as f, Writer(f, chunk_size=512) as w:
        for i in range(ROUNDS):
            t = 100 + i * 0.1
            ns = int(t * 1e9)
            a = _image(i, 0)
            raw = RawImage(width=32, height=24, encoding="mono8", step=32, data=a.tobytes(),
                           frame_id="a")
            raw.timestamp.FromNanoseconds(ns)
            w.write_message("/a", raw, log_time=ns, publish_time=ns, sequence=10 + i)
            if i == 2:
                continue
            ok, png = cv2.imencode(".png", _image(i, 1))
            comp = CompressedImage(data=png.tobytes(), format="png", frame_id="b")
            comp.timestamp.FromNanoseconds(ns + 1000)
            w.write_message("/b", comp, log_time=ns, publish_time=ns, sequence=10 + i)
    return path


async def test_rounds_come_in_step_with_exact_pixels_and_stamps(recording):
    """A rig of two topics gives each complete round's images, pixel for pixel, stamped
    with their own timestamps, its sequence number after each read; the round missing an
    image is skipped and counted; the end is EndOfStream."""
    async with McapRig(recording, {"a": "/a", "b": "/b"}) as rig:
        assert rig.sizes == {"a": (32, 24), "b": (32, 24)}
        seen = []
        while True:
            try:
                frames = await rig.read()
            except EndOfStream:
                break
            i = rig.sequence - 10
            seen.append(i)
            assert np.array_equal(frames["a"].image, _image(i, 0))
            assert np.array_equal(frames["b"].image, _image(i, 1))
            assert frames["a"].timestamp == pytest.approx(100 + i * 0.1, abs=1e-9)
            assert frames["b"].timestamp - frames["a"].timestamp == pytest.approx(1e-6)
            assert frames["a"].counter == len(seen) - 1
        assert seen == [0, 1, 3, 4] and rig.incomplete == 1 and rig.truncated is None


async def test_one_topic_as_a_camera_from_the_registry(recording):
    """``open_camera("mcap", path=..., topic=...)`` plays one topic as a Camera."""
    cam = open_camera("mcap", path=recording, topic="/a", name="left")
    async with cam:
        assert cam.size == (32, 24)
        frames = [f async for f in cam]
    assert [f.camera for f in frames] == ["left"] * ROUNDS
    assert np.array_equal(frames[4].image, _image(4, 0))


async def test_a_cut_file_plays_to_the_cut_and_junk_is_refused(recording, tmp_path):
    """A file cut in its data plays the rounds before the cut and then ends, saying what
    was wrong (``truncated``); a file that is not MCAP is a DriverInitError naming it."""
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(recording.read_bytes()[:recording.stat().st_size * 2 // 3])
    async with McapRig(cut, {"a": "/a"}) as rig:
        n = 0
        with pytest.raises(EndOfStream, match="unreadable after that"):
            while True:
                await rig.read()
                n += 1
        assert 1 <= n < ROUNDS and rig.truncated
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"\x00" * 100)
    with pytest.raises(DriverInitError, match=f"{junk}: not an MCAP file"):
        async with McapRig(junk, {"a": "/a"}):
            pass
