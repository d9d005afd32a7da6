"""Issue 33 item 1 ("the monitor camera"): a camera configured with ``role = "monitor"``
is read on a hardware cell as a source without views: its frames reach the pipeline's taps
(the console's views, the recorder) and nothing else; it is never tracked, and its frames
never feed the camera-stall watch (its stall stops nothing)."""

from __future__ import annotations

import anyio
import cv2
import numpy as np

from oralnav.config.daemon import load_config
from oralnav.daemon.capture_task import CapturePipeline, hardware_sources
from oralnav.daemon.live_views import LiveViews
from tests.config.helpers import write_file
from tests.config.test_daemon import HW


class _Core:
    """What the pipeline asks of the core; a frame fed to the stall watch is a failure."""

    def __init__(self) -> None:
        self.clock = lambda: 0.0
        self.fed: list[str] = []

    def camera_frame(self, name: str, counter: int) -> None:
        self.fed.append(name)


def test_a_monitor_camera_is_shown_never_tracked_nor_watched(tmp_path):
    """The monitor camera is its own source with no views; a round of it reaches the
    taps (the live views show it) without touching the stall watch or the pose store."""
    frames = tmp_path / "monitor"
    frames.mkdir()
    for i in range(2):
        cv2.imwrite(str(frames / f"f{i}.png"), np.full((48, 64), 40 * i, np.uint8))
    cfg = load_config(write_file(tmp_path, "c.toml", HW + f"""
[cameras.monitor]
backend = "replay"
path = "{frames}"
role = "monitor"
"""))
    (source,) = [s for s in hardware_sources(cfg) if s.name == "monitor"]
    assert source.views == [] and source.pose_names() == set()
    core = _Core()
    views = LiveViews()
    pipe = CapturePipeline(core, [source], taps=[views.tap])

    async def one_round():
        stream = source.make()
        await stream.start()
        try:
            return await pipe.process(source, await stream.read())
        finally:
            await stream.close()

    rnd = anyio.run(one_round)
    assert rnd is not None and rnd.poses == {} and core.fed == []
    (cam,) = views.cameras()
    assert (cam["name"], cam["source"], cam["width"], cam["counter"], cam["fields"]) == \
        ("monitor", "monitor", 64, 0, [])
