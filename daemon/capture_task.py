"""Capture -> pairing -> tracking -> the pose store: one pipeline for every cell.

A :class:`Source` is one stream of synchronised frames and the trackers that read them:

- on a hardware cell (:func:`hardware_sources`), the stereo rig's two cameras read as
  pairs (``[stereo]``: by timestamp or trigger counter, ``oralnav.drivers.camera.stereo``)
  and the endoscope camera, when configured, on its own; a monitor camera
  (``role = "monitor"``: the operative area, for the surgeon) is a source without views:
  its frames only reach the taps, it is never tracked, and its stall stops nothing;
- on the simulated cell (:func:`sim_sources`), the cell's renderer, which shows the stereo
  pair and the endoscope at one instant (``SimCameraSet``).

:class:`CapturePipeline` runs each source as a task of the daemon's group. Every frame
feeds the camera-stall watchdog (``core.camera_frame``); every set of frames is tracked in
a worker thread (NVG-BA, predictive ROI), and each field found is published into the
core's pose store as ``T_C_<field>`` (``RM``, ``OM``, ``EM`` for the robot, opener and
effector fields) or ``T_En_EM`` for the endoscope, stamped with its capture instant on the
daemon's monotonic clock (the mean of the views' timestamps). The rates go to the status.
Then the round's listeners run (navigation, :mod:`oralnav.daemon.navigation_task`) with a
:class:`TrackedRound` naming what was published: they read the store, never the frames.
Last, the round's taps see the frames themselves with what was found in them
(:class:`CapturedRound`: the console's live views, the session recorder); a tap is a plain
call that keeps references or queues them and returns at once, so nothing a tap does
(encoding, writing) ever runs on the tracking path.

Faults: a camera that fails to start is a FAULT naming it, and the start is retried with
back-off, so the cell recovers when the camera returns; one that delivers images of another
size than its calibration is a FAULT too. The daemon keeps serving. A read error is logged
and the read retried: the drivers reconnect by themselves, and a camera whose counter stops
trips the camera-stall watchdog. A camera whose clock goes back or jumps (``ClockError``,
with ``timestamps = "device"``) is a FAULT naming it: its frames cannot be placed in time.
A tracking or listener failure is a FAULT, never the daemon's end.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Awaitable, Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import anyio
import anyio.abc
import anyio.to_thread

from oralnav.config.daemon import DaemonConfig
from oralnav.control.vision.camera import Rig
from oralnav.control.vision.markers import MarkerField
from oralnav.control.vision.tracker import Tracker
from oralnav.daemon.core import DaemonCore
from oralnav.drivers.camera import Camera, open_camera
from oralnav.drivers.camera.sim import FrameSource, SimCameraSet
from oralnav.drivers.camera.stereo import StereoCamera
from oralnav.drivers.errors import ClockError, DriverError

__all__ = ["FIELD_FRAMES", "CapturePipeline", "CapturedRound", "FrameTap", "Source",
           "TrackedRound", "View", "hardware_sources", "sim_sources", "stereo_offset"]

log = logging.getLogger(__name__)

#: The published names of the cell's marker fields (docs/conventions.md).
FIELD_FRAMES = {"robot": "RM", "opener": "OM", "effector": "EM"}
#: Seconds between repeated read-error messages of one camera.
_LOG_EVERY_S = 5.0
#: Back-off (first, max) s between attempts to start cameras that did not start.
START_RETRY_S = (1.0, 10.0)


@dataclass(frozen=True)
class View:
    """One tracker of a source: the rig it tracks (its cameras are the rig's names), the
    reference frame its poses are published in (``"C"`` stereo, ``"En"`` endoscope), the
    published suffix of each field it tracks (field name -> ``RM``/``OM``/``EM``), and how
    late its cameras' timestamps are against the arm's clock (s, the temporal calibration;
    subtracted from every stamp it publishes)."""

    tracker: Tracker
    frame: str
    suffixes: Mapping[str, str]
    time_offset: float = 0.0

    def pose_names(self) -> set[str]:
        return {f"T_{self.frame}_{s}" for s in self.suffixes.values()}


@dataclass(frozen=True)
class Source:
    """A stream of synchronised frames (``make()`` builds it afresh for every attempt to
    start: a camera starts only once) and the views tracked from it."""

    name: str
    make: Callable[[], Any]
    views: Sequence[View]

    def pose_names(self) -> set[str]:
        return set().union(*(v.pose_names() for v in self.views))


@dataclass(frozen=True)
class TrackedRound:
    """What one round of a source published: its name, the capture instant (s, daemon
    monotonic clock) of each view, and the poses published, name -> capture instant."""

    source: str
    poses: Mapping[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class CapturedRound:
    """One tracked round as a tap sees it: the source's name, its frames (camera ->
    ``CameraFrame``; the arrays are shared with tracking: a tap never writes into them),
    each view's capture instant (s, daemon monotonic clock, offset applied) and what it
    found (field name -> ``PoseEstimate``: ``T_ref_field``, ``per_camera`` inlier pixels),
    and the poses published, name -> capture instant."""

    source: str
    frames: Mapping[str, Any]
    views: Sequence[tuple[View, float, Mapping[str, Any]]]
    published: Mapping[str, float]


#: A tap of the pipeline: called on the event loop after each round's listeners; it must
#: return at once (keep references, queue work for a thread) and never raise.
FrameTap = Callable[[CapturedRound], None]


def _view(rig: Rig, fields: Sequence[MarkerField], frame: str,
          suffixes: Mapping[str, str], time_offset: float = 0.0) -> View:
    tracked = [f for f in fields if f.name in suffixes]
    return View(Tracker(rig, tracked, method="nvgba", mode="predict"), frame,
                {f.name: suffixes[f.name] for f in tracked}, time_offset)


def stereo_offset(cfg: DaemonConfig) -> float:
    """The stereo camera's time offset (s) the daemon applies: the temporal calibration's,
    or 0 with a warning when the configuration names none (docs/calibration.md,
    "Temporal calibration": why a missing one is a warning, not a refusal)."""
    offset = cfg.stereo_time_offset()
    if offset is None:
        log.warning("no temporal calibration ([calibration] temporal): the stereo camera's "
                    "timestamps are taken as on the arm's clock (offset 0); run "
                    "oralnav calibrate temporal")
        return 0.0
    log.info("stereo camera timestamps corrected by the temporal calibration: %+.2f ms",
             offset * 1e3)
    return offset


def hardware_sources(cfg: DaemonConfig, stereo_offset: float = 0.0) -> list[Source]:
    """The configured cameras (``[cameras.<name>]``) as sources: the stereo pair, and each
    endoscope camera of ``[cell] endoscope_rig`` that tracks the effector field. A stereo
    camera without its partner is not read (logged). The cameras are built in the tasks;
    their options were checked when the configuration loaded. ``stereo_offset``: how late
    the stereo pair's stamps are (s; :func:`stereo_offset` reads it from the configuration)."""
    s = cfg.settings

    def camera(name: str) -> Camera:
        c = s.cameras[name]
        return open_camera(c.backend, name=name, **c.driver_options())

    fields = list(cfg.fields.values())
    suffixes = {n: FIELD_FRAMES[n] for n in cfg.fields if n in FIELD_FRAMES}
    sources: list[Source] = []
    names = set(s.cameras)
    left, right = cfg.rig.names[0], cfg.rig.names[-1]
    if left in names and right in names and left != right:
        names -= {left, right}
        sources.append(Source("stereo", lambda: StereoCamera(
            camera(left), camera(right), by=s.stereo.by, tolerance=s.stereo.tolerance,
            clock=s.stereo.clock), [_view(cfg.rig, fields, "C", suffixes, stereo_offset)]))
    for name in sorted(n for n in names if s.cameras[n].role == "monitor"):
        names.discard(name)  # shown and recorded, never tracked (no views)
        sources.append(Source(name, lambda n=name: _Single(camera(n)), []))
    endo = cfg.endoscope_rig
    if endo is not None and "effector" in cfg.fields:
        for name in sorted(names & set(endo.names)):
            names.discard(name)
            sources.append(Source(name, lambda n=name: _Single(camera(n)),
                                  [_view(endo, fields, "En", {"effector": "EM"})]))
    for name in sorted(names):
        log.warning("camera %r: not part of a complete rig here; it is not read", name)
    return sources


def sim_sources(cell: FrameSource, stereo: Rig, endoscope: Rig,
                fields: Mapping[str, MarkerField], stereo_offset: float = 0.0
                ) -> list[Source]:
    """The simulated cell as one source: its renderer shows the stereo pair and the
    endoscope at one instant. ``fields``: role (``robot``, ``opener``, ``effector``) ->
    the cell's marker field; ``stereo_offset``: the stereo view's time offset (s)."""
    names = tuple(stereo.names) + tuple(endoscope.names)
    sizes = {n: tuple(rig[n].size) for rig in (stereo, endoscope) for n in rig.names}
    suffixes = {f.name: FIELD_FRAMES[role] for role, f in fields.items()}
    effector = fields["effector"].name
    return [Source("cell", lambda: SimCameraSet(names, cell, sizes=sizes), [
        _view(stereo, list(fields.values()), "C", suffixes, stereo_offset),
        _view(endoscope, [fields["effector"]], "En", {effector: "EM"})])]


Listener = Callable[[TrackedRound], Awaitable[None]]


class CapturePipeline:
    """See the module docstring. ``listeners`` run after each round, in order."""

    def __init__(self, core: DaemonCore, sources: Sequence[Source],
                 listeners: Sequence[Listener] = (), taps: Sequence[FrameTap] = ()) -> None:
        self.core = core
        self.sources = list(sources)
        self.listeners = list(listeners)
        self.taps = list(taps)
        self.frames: dict[str, int] = {}
        self._t0: dict[str, float] = {}

    def pose_names(self) -> set[str]:
        """Every pose some source can publish (``T_C_RM``, ``T_En_EM``, ...)."""
        return set().union(*(s.pose_names() for s in self.sources))

    async def run(self, *, task_status: anyio.abc.TaskStatus[None] =
                  anyio.TASK_STATUS_IGNORED) -> None:
        async with anyio.create_task_group() as tg:
            for source in self.sources:
                tg.start_soon(self._capture, source)
            task_status.started()

    async def _start(self, source: Source) -> Any:
        """The source's stream, started; retried with back-off while it fails."""
        core = self.core
        delay = START_RETRY_S[0]
        while True:
            stream = source.make()
            try:
                await stream.start()
                return stream
            except DriverError as exc:  # a wrong address, a camera that is off or busy
                log.error("cameras %s did not start: %s (retrying in %.0f s)", source.name,
                          exc, delay)
                core.supervisor.fault(core.clock(), f"camera {source.name}",
                                      f"did not start: {exc}")
                await stream.close()
                await anyio.sleep(delay)  # the cell recovers when the camera returns
                delay = min(2 * delay, START_RETRY_S[1])

    async def _capture(self, source: Source) -> None:
        core, name = self.core, source.name
        stream = await self._start(source)
        sizes = _sizes(stream)
        wrong = [f"{cam} delivers {w}x{h} px, its calibration is {rw}x{rh}"
                 for v in source.views for cam in v.tracker.rig.names if cam in sizes
                 for (w, h), (rw, rh) in [(sizes[cam], v.tracker.rig[cam].size)]
                 if (w, h) != (rw, rh)]
        if wrong:  # a region or binning the rig was not calibrated for: nothing to track
            log.error("cameras %s: %s", name, "; ".join(wrong))
            core.supervisor.fault(core.clock(), f"camera {name}", "; ".join(wrong))
            await stream.close()
            return
        last_log = -_LOG_EVERY_S
        try:
            while True:
                try:
                    frames = await stream.read()
                except ClockError as exc:  # frames that cannot be placed in time: a fault
                    log.error("cameras %s: %s", name, exc)
                    core.supervisor.fault(core.clock(), f"camera {name}", str(exc))
                    continue
                except DriverError as exc:  # the driver reconnects on a later read
                    if time.monotonic() - last_log > _LOG_EVERY_S:
                        log.warning("cameras %s: %s", name, exc)
                        last_log = time.monotonic()
                    await anyio.sleep(0.01)
                    continue
                await self.process(source, frames)
        finally:
            with anyio.CancelScope(shield=True):
                try:
                    await stream.close()
                except DriverError as exc:
                    log.warning("cameras %s: closing: %s", name, exc)

    async def process(self, source: Source, frames: Mapping[str, Any]) -> TrackedRound | None:
        """One round: ``frames`` (``{camera: CameraFrame}``, one instant) tracked and
        published, then the listeners told. None when tracking failed (a FAULT)."""
        core, name = self.core, source.name
        if not source.views:  # a monitor camera: for the taps only (module docstring)
            self._tap(CapturedRound(name, frames, [], {}))
            return TrackedRound(name, {})
        arrived = core.clock()
        for cam, f in frames.items():
            core.camera_frame(cam, f.counter)
        try:
            found = await anyio.to_thread.run_sync(_track, source.views, frames)
        except Exception as exc:  # a tracking failure faults the cell, never the daemon
            log.exception("cameras %s: tracking failed", name)
            core.supervisor.fault(core.clock(), f"tracking {name}",
                                  f"{type(exc).__name__}: {exc}")
            return None
        published: dict[str, float] = {}
        now = core.clock()
        for view, stamp, ests in found:
            core.stage_times.record(stamp, arrived, now)
            for fname, est in ests.items():
                pose = f"T_{view.frame}_{view.suffixes.get(fname, fname)}"
                core.publish_pose(pose, est.T_ref_field, stamp, frame=view.frame,
                                  corners=est.corners, sigma_m=est.position_sigma_m,
                                  sigma_deg=est.rotation_sigma_deg)
                published[pose] = stamp
        n = self.frames[name] = self.frames.get(name, 0) + 1
        t0 = self._t0.setdefault(name, time.monotonic())
        if n > 1:  # a rate needs two rounds; the first only starts the clock
            core.set_rate(f"tracking {name}", (n - 1) / max(time.monotonic() - t0, 1e-9))
        rnd = TrackedRound(name, published)
        for listener in self.listeners:
            try:
                await listener(rnd)
            except Exception as exc:  # a failed step stops the robot, not the daemon
                log.exception("%s failed", getattr(listener, "__qualname__", listener))
                core.supervisor.fault(core.clock(), "navigation",
                                      f"{type(exc).__name__}: {exc}")
        self._tap(CapturedRound(name, frames, found, published))
        return rnd

    def _tap(self, captured: CapturedRound) -> None:
        for tap in self.taps:
            try:
                tap(captured)
            except Exception:  # a viewer or recorder never stops tracking
                log.exception("frame tap %s failed", getattr(tap, "__qualname__", tap))


def _track(views: Sequence[View], frames: Mapping[str, Any]
           ) -> list[tuple[View, float, dict[str, Any]]]:
    """Each view's fields in its cameras' frames (a worker thread): (view, capture instant
    (s, the mean of its views' timestamps), {field: estimate})."""
    out = []
    for view in views:
        mine = {n: f for n, f in frames.items() if n in view.tracker.rig.names}
        if not mine:
            continue
        stamp = sum(f.timestamp for f in mine.values()) / len(mine) - view.time_offset
        out.append((view, stamp, view.tracker.track({n: f.image for n, f in mine.items()})))
    return out


def _sizes(stream: Any) -> dict[str, tuple[int, int]]:
    """The started cameras' image sizes (width, height), by name."""
    if isinstance(stream, StereoCamera):
        return {name: tuple(cam.size) for name, cam in stream.cameras.items()}
    if isinstance(stream, _Single):
        return {stream.camera.name: tuple(stream.camera.size)}
    return {n: tuple(s) for n, s in getattr(stream, "sizes", {}).items()}


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
