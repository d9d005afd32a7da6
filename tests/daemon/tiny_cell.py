"""What the recording and replay tests share: a tiny stereo cell (two 320x240 cameras, one
ChArUco field moving a little every frame, rendered with noise in milliseconds) tracked by
the daemon's own capture pipeline into a real daemon core, with the control loop stepped
in-process on a virtual clock, so that the arm's history fills as on the daemon."""

from __future__ import annotations

import functools
from typing import Any

import numpy as np

from oralnav.config.daemon import load_config
from oralnav.control.geometry import transform_from_euler
from oralnav.control.vision.camera import CameraModel, Rig
from oralnav.control.vision.markers import MarkerField, PlaneSurface
from oralnav.control.vision.tracker import Tracker
from oralnav.daemon.capture_task import CapturePipeline, Source, View
from oralnav.daemon.core import DaemonCore
from oralnav.drivers.arm.sim import SimArm
from oralnav.drivers.camera.base import CameraFrame
from oralnav.drivers.clock import VirtualClock
from oralnav.drivers.effector.sim import SimEffector
from oralnav.realtime.control_loop import LoopSettings
from oralnav.realtime.control_process import InProcessControl
from oralnav.safety.limits import SpeedLimiter
from oralnav.safety.watchdogs import WatchdogSet
from oralnav.sim.world.render import SceneRenderer
from oralnav.sim.world.scene import Imaging, Placement, Scene

#: Seconds between two rounds (virtual).
ROUND_S = 0.1
#: Control periods stepped per round (the arm's history gets a sample each).
STEPS = 5


def tiny_rig() -> Rig:
    K = np.array([[420.0, 0.0, 160.0], [0.0, 420.0, 120.0], [0.0, 0.0, 1.0]])
    T_right = np.eye(4)
    T_right[0, 3] = 0.06
    return Rig("left", {"left": CameraModel("left", (320, 240), K, np.zeros(5)),
                        "right": CameraModel("right", (320, 240), K,
                                             np.array([0.01, -0.02, 0.0, 0.0, 0.0]), T_right)})


def field_pose(i: int) -> np.ndarray:
    """The field's pose in frame ``i``: 1 mm and half a degree a frame."""
    return transform_from_euler([-0.04 + 0.001 * i, -0.03 + 0.0005 * i, 0.25],
                                [5.0 + 0.5 * i, -10.0, 5.0 + 0.3 * i])


@functools.cache
def renderer() -> tuple[SceneRenderer, MarkerField]:
    field = MarkerField("robot", "DICT_4X4_50", (5, 4), 0.02, 0.015, 0, PlaneSurface())
    scene = Scene(tiny_rig(), (Placement("robot", field, field_pose(0)),),
                  imaging=Imaging(supersample=1, read_noise_dn=1.0, blur_sigma_px=0.7), seed=3)
    r = SceneRenderer(scene)
    r.prepare()
    return r, field


@functools.cache
def images(i: int) -> dict[str, np.ndarray]:
    r, _ = renderer()
    return r.render({"robot": field_pose(i)}, frame=i).images


class TinyCell:
    """The core, the in-process control loop and a capture pipeline whose one source
    (``tiny``) is a stereo view of the field, published as ``T_C_RM``."""

    def __init__(self) -> None:
        cfg = load_config()
        s = cfg.settings
        self.clock = VirtualClock(100.0)
        settings = LoopSettings.from_config(s.control, s.safety)
        self.period = settings.period
        self.arm, self.wrist = SimArm(clock=self.clock), SimEffector(clock=self.clock)
        self.control = InProcessControl(self.arm, self.wrist, settings,
                                        SpeedLimiter.from_settings(s.safety))
        self.core = DaemonCore(self.control, WatchdogSet.from_settings(s.safety, self.period),
                               clock=self.clock.now)
        _, field = renderer()
        view = View(Tracker(tiny_rig(), [field], method="nvgba", mode="predict"), "C",
                    {"robot": "RM"})
        self.source = Source("tiny", lambda: None, [view])
        self.pipeline = CapturePipeline(self.core, [self.source])
        self.i = 0
        self.counters = 0

    async def rounds(self, n: int) -> list[Any]:
        """Track the next ``n`` frames as the pipeline does; the rounds published."""
        out = []
        for _ in range(n):
            for _ in range(STEPS):
                self.clock.advance(ROUND_S / STEPS)
                self.control.step(self.clock.now())
            now = self.clock.now()
            frames = {cam: CameraFrame(img, now, self.i, cam)
                      for cam, img in images(self.i).items()}
            out.append(await self.pipeline.process(self.source, frames))
            self.i += 1
        return out

    async def start(self) -> TinyCell:
        await self.arm.start()
        await self.wrist.start()
        return self

    async def close(self) -> None:
        await self.wrist.close()
        await self.arm.close()
        await self.control.close()
