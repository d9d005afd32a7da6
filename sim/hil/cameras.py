"""The simulated cell's cameras as GigE Vision cameras on loopback, showing the arm and
the wrist where their protocol peers actually are.

:class:`CellCameras` builds a :class:`~oralnav.sim.world.cell.SimCell` whose arm pose is
read from the fake UR controller and whose wrist joints from the drive unit (callables
given by the caller), and one :class:`~oralnav.sim.peers.gige_render.RenderedGvCamera` per
camera of the cell's rigs (the stereo pair and the endoscope).

One render thread captures the cell at the cameras' frame instants (multiples of the frame
period on the wall clock, the instants the cameras send at): every view of one capture, one
arm pose, one instant, as cameras on a shared trigger expose. Each camera sends its view of
a capture ``RENDER_PERIODS`` frame periods after it was taken (plus the configured
latency), so the capture-to-send delay is the same for every frame even though rendering
three 2-Mpixel views takes a varying part of those periods; a capture that is not ready by
then is skipped by every camera. A constant delay is what a real camera has (exposure,
readout, transfer), and what lets the daemon map the cameras' clock onto its own.

The capture instant is the midpoint of reading the arm pose (an RPC to the controller's
process, about a millisecond): the pose the frame shows is the arm's at that instant. Each
capture's ground truth is kept (:meth:`CellCameras.truth_at`) for the truth service.
"""

from __future__ import annotations

import bisect
import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np

from oralnav.sim.errors import SimError
from oralnav.sim.peers.gige_render import RenderedGvCamera
from oralnav.sim.world.cell import CellConfig, SimCell

__all__ = ["RENDER_PERIODS", "CellCameras"]

#: Frame periods between a capture and its frames leaving: rendering three views must fit.
RENDER_PERIODS = 2

log = logging.getLogger(__name__)


class _Capture:
    """One capture of the cell: every view, its instant, the cameras that took it."""

    def __init__(self, images: dict[str, np.ndarray], t: float) -> None:
        self.images, self.t = images, t
        self.taken: set[str] = set()


class CellCameras:
    """See the module docstring.

    Args:
        config: the cell (its scenes name the rigs, fields and imaging).
        arm_pose: the arm's ``T_B_tcp`` now (4x4, m), read from its peer.
        wrist_joints: the wrist's joints now ``[roll, pitch, yaw, jaw]`` (rad).
        frame_rate: Hz of every camera until a driver sets its own.
        latency_s: s from capture to the first packet (each camera).
        clock_offset_s: the cameras' clock minus the host's monotonic clock, s.
        keep: captures whose truth is kept.
    """

    def __init__(self, config: CellConfig, arm_pose: Callable[[], np.ndarray],
                 wrist_joints: Callable[[], np.ndarray], *, frame_rate: float = 5.0,
                 latency_s: float = 0.0, clock_offset_s: float = 0.0,
                 keep: int = 512) -> None:
        self._arm_pose = arm_pose
        self._T = np.eye(4)
        self.cell = SimCell(config, self._pose, wrist_joints, self._sample)
        self.names = self.cell.camera_names
        self.frame_rate, self.latency_s = float(frame_rate), float(latency_s)
        self.clock_offset_s = float(clock_offset_s)
        self._lock = threading.Lock()
        self._cv = threading.Condition(self._lock)
        self._latest: _Capture | None = None
        self._closing = threading.Event()
        self._thread: threading.Thread | None = None
        self._truths: deque[tuple[float, dict[str, Any]]] = deque(maxlen=keep)
        self.cameras: dict[str, RenderedGvCamera] = {}
        #: how long each of the last captures took to render (s), for diagnosis
        self.render_s: deque[float] = deque(maxlen=256)

    # -- the arm pose of one capture ------------------------------------------------------
    def _sample(self) -> float:
        """The cell's clock, read first at each capture: reads the arm pose and returns
        the instant it describes (the midpoint of the read)."""
        t0 = time.monotonic()
        self._T = np.array(self._arm_pose(), dtype=float)
        return 0.5 * (t0 + time.monotonic())

    def _pose(self) -> np.ndarray:
        return self._T

    # -- the cameras ----------------------------------------------------------------------
    def start(self) -> None:
        """Build the renderer's maps, render one capture (warming up; never sent), start
        the render thread and a camera per view."""
        self.cell.prepare()
        self._render()
        self._latest.taken.update(self.names)  # the warm-up capture is never sent
        period = 1.0 / self.frame_rate
        self._thread = threading.Thread(target=self._render_loop, name="cell-cameras",
                                        daemon=True)
        self._thread.start()
        try:
            for name in self.names:
                rig = (self.cell.stereo_rig if name in self.cell.stereo_rig.names
                       else self.cell.endoscope_rig)
                # sent RENDER_PERIODS frame instants after the capture: the capture comes a
                # few ms after its instant, so the send instant is the first one at or after
                # capture + this latency
                latency = RENDER_PERIODS * period - 0.25 * period + self.latency_s
                cam = RenderedGvCamera(lambda n=name: self._view(n), size=tuple(rig[name].size),
                                       latency_s=min(latency, 1.0),
                                       clock_offset_s=self.clock_offset_s,
                                       frame_rate=self.frame_rate)
                cam.start()
                self.cameras[name] = cam
        except BaseException:
            self.close()
            raise

    def close(self) -> None:
        self._closing.set()
        with self._cv:
            self._cv.notify_all()
        for cam in self.cameras.values():
            cam.close()
        if self._thread is not None:
            self._thread.join()

    def __enter__(self) -> CellCameras:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def addresses(self) -> dict[str, str]:
        """Camera name -> the loopback address it binds."""
        return {n: c.address for n, c in self.cameras.items() if c.address}

    def _render(self) -> None:
        """One capture of every view, made the newest (the cameras wait for it)."""
        t0 = time.monotonic()
        images, t = self.cell.capture(self.names)
        truth = self.cell.truth()
        with self._cv:
            self.render_s.append(time.monotonic() - t0)
            self._latest = _Capture(images, t)
            self._truths.append((t, truth))
            self._cv.notify_all()

    def _render_loop(self) -> None:
        """Capture at each frame instant (multiples of the period on the wall clock); an
        instant that finds the previous render still running is skipped."""
        period = 1.0 / self.frame_rate
        while not self._closing.is_set():
            now = time.time()
            if self._closing.wait(period - now % period):
                return
            try:
                self._render()
            except Exception:  # a render error skips a capture, never ends the cameras
                log.exception("rendering the cell failed; this capture is skipped")

    def _view(self, name: str) -> tuple[np.ndarray, float]:
        """Camera ``name``'s image of the newest capture it has not taken yet, waiting up
        to two frame periods for one (the camera thread's call; raising skips a frame)."""
        deadline = time.monotonic() + 2.0 / self.frame_rate
        with self._cv:
            while (self._latest is None or name in self._latest.taken) \
                    and not self._closing.is_set():
                left = deadline - time.monotonic()
                if left <= 0:
                    raise SimError(f"camera {name}: no new capture of the cell in "
                                   f"{2.0 / self.frame_rate:.2f} s (rendering too slow)")
                self._cv.wait(left)
            if self._closing.is_set():
                raise SimError("closing")
            cap = self._latest
            cap.taken.add(name)
            return cap.images[name], cap.t

    # -- ground truth ---------------------------------------------------------------------
    def truth_at(self, t: float | None = None) -> dict[str, Any]:
        """The truth of the newest capture at or before ``t`` (s, host monotonic; None:
        the newest): ``time``, ``T_B_tcp``, ``T_B_E`` (4x4, m), ``q`` and
        ``targets_B`` (name -> (3,) m). Raises :class:`SimError` when there is none."""
        with self._lock:
            items = list(self._truths)
        if not items:
            raise SimError("no capture yet")
        if t is None:
            when, truth = items[-1]
        else:
            i = bisect.bisect_right([w for w, _ in items], t)
            if i == 0:
                raise SimError(f"no capture kept at or before {t:.6f} s (the oldest is "
                               f"{items[0][0]:.6f} s)")
            when, truth = items[i - 1]
        return {"time": when, "T_B_tcp": truth["T_B_tcp"], "T_B_E": truth["T_B_E"],
                "q": truth["q"], "targets_B": self.cell.targets_B()}
