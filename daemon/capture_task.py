"""Capture and tracking on a hardware cell: the configured cameras (``[cameras.<name>]``)
read, tracked and published into the daemon core.

- The stereo rig's two cameras are read as pairs (``[stereo]``: by timestamp or trigger
  counter, ``oralnav.drivers.camera.stereo``); the endoscope camera, when configured, on its
  own. Each runs as a task of the daemon's group.
- Every frame feeds the camera-stall watchdog (``core.camera_frame``); every pair or frame
  is tracked in a worker thread (NVG-BA, predictive ROI) and each field found is published
  as ``T_C_<field>`` (``RM``, ``OM``, ``EM`` for the robot, opener and effector fields) or
  ``T_En_EM`` for the endoscope, stamped with the capture time; the rates go to the status.
- A camera that fails to start is a FAULT naming it, and the start is retried with
  back-off, so the cell recovers when the camera returns; one that delivers images of
  another size than its calibration is a FAULT too. The daemon keeps serving. A read
  error is logged and the read retried: the drivers reconnect by themselves, and a camera
  whose counter stops trips the camera-stall watchdog. A tracking failure is a FAULT too,
  never the daemon's end.

The two-stage navigation on a hardware cell (the capture instant's arm pose, the entry pose
in the configuration) is not wired yet; the simulated cell's ``NavigationTask`` runs it.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any

import anyio
import anyio.abc
import anyio.to_thread

from oralnav.config.daemon import DaemonConfig
from oralnav.control.vision.tracker import Tracker
from oralnav.daemon.core import DaemonCore
from oralnav.drivers.camera import Camera, open_camera
from oralnav.drivers.camera.stereo import StereoCamera
from oralnav.drivers.errors import DriverError

__all__ = ["HardwareCapture"]

log = logging.getLogger(__name__)

#: The published names of the cell's marker fields (docs/conventions.md).
FIELD_FRAMES = {"robot": "RM", "opener": "OM", "effector": "EM"}
#: Seconds between repeated read-error messages of one camera.
_LOG_EVERY_S = 5.0
#: Back-off (first, max) s between attempts to start cameras that did not start.
START_RETRY_S = (1.0, 10.0)


class HardwareCapture:
    """See the module docstring. The cameras are built in the tasks, afresh for every
    attempt to start them; their options were checked when the configuration loaded."""

    def __init__(self, core: DaemonCore, cfg: DaemonConfig) -> None:
        self.core = core
        s = cfg.settings

        def camera(name: str) -> Camera:
            c = s.cameras[name]
            return open_camera(c.backend, name=name, **c.driver_options())

        fields = list(cfg.fields.values())
        # (name, stream factory, tracker, frame): a camera starts only once, so every
        # attempt to start builds the stream afresh
        self.sources: list[tuple[str, Callable[[], Any], Tracker, str]] = []
        names = set(s.cameras)
        left, right = cfg.rig.names[0], cfg.rig.names[-1]
        if left in names and right in names and left != right:
            names -= {left, right}
            self.sources.append(("stereo", lambda: StereoCamera(
                camera(left), camera(right), by=s.stereo.by, tolerance=s.stereo.tolerance,
                clock=s.stereo.clock), Tracker(cfg.rig, fields, method="nvgba",
                                               mode="predict"), "C"))
        endo = cfg.endoscope_rig
        effector = [f for f in fields if f.name == "effector"]
        if endo is not None and effector:
            for name in sorted(names & set(endo.names)):
                names.discard(name)
                self.sources.append((name, lambda n=name: _Single(camera(n)),
                                     Tracker(endo, effector, method="nvgba", mode="predict"),
                                     "En"))
        for name in sorted(names):  # a stereo camera without its partner
            log.warning("camera %r: not part of a complete rig here; it is not read", name)
        self.frames: dict[str, int] = {}

    async def run(self, *, task_status: anyio.abc.TaskStatus[None] =
                  anyio.TASK_STATUS_IGNORED) -> None:
        async with anyio.create_task_group() as tg:
            for source in self.sources:
                tg.start_soon(self._capture, *source)
            task_status.started()

    async def _capture(self, name: str, make: Callable[[], Any], tracker: Tracker,
                       frame: str) -> None:
        core = self.core
        delay = START_RETRY_S[0]
        while True:
            stream = make()
            try:
                await stream.start()
                break
            except DriverError as exc:  # a wrong address, a camera that is off or busy
                log.error("cameras %s did not start: %s (retrying in %.0f s)", name, exc, delay)
                core.supervisor.fault(core.clock(), f"camera {name}", f"did not start: {exc}")
                await stream.close()
                await anyio.sleep(delay)  # the cell recovers when the camera returns
                delay = min(2 * delay, START_RETRY_S[1])
        wrong = [f"{cam} delivers {w}x{h} px, its calibration is {rw}x{rh}"
                 for cam, (w, h) in _sizes(stream).items()
                 for rw, rh in [tracker.rig[cam].size] if (w, h) != (rw, rh)]
        if wrong:  # a region or binning the rig was not calibrated for: nothing to track
            log.error("cameras %s: %s", name, "; ".join(wrong))
            core.supervisor.fault(core.clock(), f"camera {name}", "; ".join(wrong))
            await stream.close()
            return
        t0, last_log = time.monotonic(), -_LOG_EVERY_S
        self.frames[name] = 0
        try:
            while True:
                try:
                    frames = await stream.read()
                except DriverError as exc:  # the driver reconnects on a later read
                    if time.monotonic() - last_log > _LOG_EVERY_S:
                        log.warning("cameras %s: %s", name, exc)
                        last_log = time.monotonic()
                    await anyio.sleep(0.01)
                    continue
                for cam, f in frames.items():
                    core.camera_frame(cam, f.counter)
                images = {cam: f.image for cam, f in frames.items()}
                try:
                    found = await anyio.to_thread.run_sync(tracker.track, images)
                except Exception as exc:  # a tracking failure faults the cell, never the daemon
                    log.exception("cameras %s: tracking failed", name)
                    core.supervisor.fault(core.clock(), f"tracking {name}",
                                          f"{type(exc).__name__}: {exc}")
                    continue
                stamp = max(f.timestamp for f in frames.values())
                for field, est in found.items():
                    pose = (f"T_C_{FIELD_FRAMES.get(field, field)}" if frame == "C"
                            else f"T_En_{FIELD_FRAMES.get(field, field)}")
                    core.publish_pose(pose, est.T_ref_field, stamp, frame=frame,
                                      corners=est.corners, sigma_m=est.position_sigma_m,
                                      sigma_deg=est.rotation_sigma_deg)
                self.frames[name] += 1
                core.set_rate(f"tracking {name}",
                              self.frames[name] / max(time.monotonic() - t0, 1e-9))
        finally:
            with anyio.CancelScope(shield=True):
                try:
                    await stream.close()
                except DriverError as exc:
                    log.warning("cameras %s: closing: %s", name, exc)


def _sizes(stream: Any) -> dict[str, tuple[int, int]]:
    """The started cameras' image sizes (width, height), by name."""
    cams = stream.cameras if isinstance(stream, StereoCamera) else {
        stream.camera.name: stream.camera}
    return {name: tuple(cam.size) for name, cam in cams.items()}


class _Single:
    """One camera read as a one-entry ``{name: frame}`` stream, like the stereo pair."""

    def __init__(self, camera: Camera) -> None:
        self.camera = camera

    async def start(self) -> None:
        await self.camera.start()

    async def read(self) -> dict[str, Any]:
        f = await self.camera.read()
        return {f.camera: f}

    async def close(self) -> None:
        await self.camera.close()
