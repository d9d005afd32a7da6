"""The simulated cell's cameras as GigE Vision cameras on loopback, showing the arm and
the wrist where their protocol peers actually are.

:class:`CellCameras` builds a :class:`~oralnav.sim.world.cell.SimCell` whose arm pose is
read from the fake UR controller and whose wrist joints from the drive unit (callables
given by the caller), and one :class:`~oralnav.sim.peers.gige_render.RenderedGvCamera` per
camera of the cell's rigs (the stereo pair and the endoscope). Cameras at one frame rate
tick together; at each tick the first camera to ask renders every view of one capture of
the cell (one arm pose, one instant) and the others take their view of that same capture,
as cameras on a shared trigger would. Each capture's ground truth is kept
(:meth:`CellCameras.truth_at`) for the truth service.

The capture instant is the instant the arm pose describes: the host's clock at the
controller cycle that computed it (``arm_sample``), the instant the arm's own RTDE package
for that pose goes out. (Stamping the moment of reading instead would make every frame up
to one controller period late: 4 ms on average on a 125 Hz CB3, which a temporal
calibration would measure as camera delay.)
"""

from __future__ import annotations

import bisect
import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

import cv2
import numpy as np

from oralnav.sim.errors import SimError
from oralnav.sim.peers.gige_render import RenderedGvCamera
from oralnav.sim.world.cell import CellConfig, SimCell

__all__ = ["STAMP_TOLERANCE_S", "CellCameras", "capture_at"]

#: s: how far a frame's stamp, read back from the cameras' timestamps, may lie from its
#: capture instant (two host clocks read at render and at arrival: microseconds)
STAMP_TOLERANCE_S = 1e-3

log = logging.getLogger(__name__)


def capture_at(instants: list[float], t: float,
               tolerance: float = STAMP_TOLERANCE_S) -> int | None:
    """The index of the newest capture at or before ``t`` among ``instants`` (s,
    increasing), or None when all are later. A frame's stamp comes back from the cameras'
    PTP time within microseconds of its capture, either side, so a capture up to
    ``tolerance`` after ``t`` is the one ``t`` stamps, never the one before it (a frame
    period earlier, whose truth would be a whole frame's motion off)."""
    i = bisect.bisect_right(instants, t + tolerance)
    return None if i == 0 else i - 1


class _Capture:
    """One capture of the cell: every view, its instant, the cameras that took it."""

    def __init__(self, images: dict[str, np.ndarray], t: float) -> None:
        self.images, self.t = images, t
        self.taken: set[str] = set()


class CellCameras:
    """See the module docstring.

    Args:
        config: the cell (its scenes name the rigs, fields and imaging).
        arm_sample: the arm's newest ``T_B_tcp`` (4x4, m) and the instant it describes
            (s, ``time.monotonic()``), read from its peer.
        wrist_joints: the wrist's joints now ``[roll, pitch, yaw, jaw]`` (rad).
        frame_rate: Hz of every camera until a driver sets its own.
        latency_s: s from capture to the first packet (each camera).
        clock_offset_s: the cameras' clock minus the host's monotonic clock, s (with
            ``ptp``: the error of their PTP timestamps).
        ptp: the cameras are PTP-synchronised to this host (their timestamps are TAI).
        keep: captures whose truth is kept.
    """

    def __init__(self, config: CellConfig,
                 arm_sample: Callable[[], tuple[np.ndarray, float]],
                 wrist_joints: Callable[[], np.ndarray], *, frame_rate: float = 5.0,
                 latency_s: float = 0.0, clock_offset_s: float = 0.0,
                 ptp: bool = False, keep: int = 512) -> None:
        self._arm_sample = arm_sample
        self._T = np.eye(4)
        self.cell = SimCell(config, self._pose, wrist_joints, self._sample)
        self.names = self.cell.camera_names
        self.frame_rate, self.latency_s = float(frame_rate), float(latency_s)
        self.clock_offset_s = float(clock_offset_s)
        self.ptp = bool(ptp)
        self._lock = threading.Lock()
        self._latest: _Capture | None = None
        self._truths: deque[tuple[float, dict[str, Any]]] = deque(maxlen=keep)
        self.cameras: dict[str, RenderedGvCamera] = {}
        #: how long each of the last captures took to render (s), for diagnosis
        self.render_s: deque[float] = deque(maxlen=256)

    # -- the arm pose of one capture ------------------------------------------------------
    def _sample(self) -> float:
        """The cell's clock, read first at each capture: reads the arm pose and returns
        the instant it describes."""
        T, t = self._arm_sample()
        self._T = np.array(T, dtype=float)
        return float(t)

    def _pose(self) -> np.ndarray:
        return self._T

    # -- the cameras ----------------------------------------------------------------------
    def start(self) -> None:
        """Build the renderer's maps, render one capture (the cameras' first frame must
        not wait on the renderer's set-up) and start a camera per view."""
        # OpenCV's parallel loops wait for every one of their threads; on cores shared
        # with the daemon one descheduled worker holds a whole render up (a capture took
        # 1.2-2 s on 2 cores, 0.33 s at the median single-threaded). This is the peers'
        # process: the setting is theirs alone.
        cv2.setNumThreads(1)
        self.cell.prepare()
        self._view(self.names[0])
        # the warm-up capture is never sent: a camera's first frame must be fresh (a
        # frame seconds old would read as a camera clock that jumped)
        self._latest.taken.update(self.names)
        try:
            for name in self.names:
                rig = (self.cell.stereo_rig if name in self.cell.stereo_rig.names
                       else self.cell.endoscope_rig)
                cam = RenderedGvCamera(lambda n=name: self._view(n), size=tuple(rig[name].size),
                                       latency_s=self.latency_s,
                                       clock_offset_s=self.clock_offset_s,
                                       frame_rate=self.frame_rate, ptp=self.ptp)
                cam.start()
                self.cameras[name] = cam
        except BaseException:
            self.close()
            raise

    def close(self) -> None:
        for cam in self.cameras.values():
            cam.close()

    def __enter__(self) -> CellCameras:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def addresses(self) -> dict[str, str]:
        """Camera name -> the loopback address it binds."""
        return {n: c.address for n, c in self.cameras.items() if c.address}

    def _view(self, name: str) -> tuple[np.ndarray, float]:
        """Camera ``name``'s image of the newest capture it has not taken yet, rendering a
        new capture of every view when it has taken the newest (module docstring)."""
        with self._lock:  # the others wait for the capture they will take too
            cap = self._latest
            if cap is None or name in cap.taken:
                t0 = time.monotonic()
                images, t = self.cell.capture(self.names)
                self.render_s.append(time.monotonic() - t0)
                truth = self.cell.truth()
                cap = self._latest = _Capture(images, t)
                self._truths.append((t, truth))
            cap.taken.add(name)
            return cap.images[name], cap.t

    # -- ground truth ---------------------------------------------------------------------
    def truth_at(self, t: float | None = None) -> dict[str, Any]:
        """The truth of the newest capture at or before ``t`` (s, host monotonic, give or
        take :data:`STAMP_TOLERANCE_S`; None: the newest): ``time``, ``T_B_tcp``,
        ``T_B_E`` (4x4, m), ``q`` and ``targets_B`` (name -> (3,) m). Raises
        :class:`SimError` when there is none."""
        with self._lock:
            items = list(self._truths)
        if not items:
            raise SimError("no capture yet")
        if t is None:
            when, truth = items[-1]
        else:
            i = capture_at([w for w, _ in items], t)
            if i is None:
                raise SimError(f"no capture kept at or before {t:.6f} s (the oldest is "
                               f"{items[0][0]:.6f} s)")
            when, truth = items[i]
        return {"time": when, "T_B_tcp": truth["T_B_tcp"], "T_B_E": truth["T_B_E"],
                "q": truth["q"], "targets_B": self.cell.targets_B()}
