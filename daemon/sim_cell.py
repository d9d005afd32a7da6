"""What only the simulated cell attaches to the daemon: the arm state its renderer draws,
and the ground-truth observer that measures each reached target's TRE.

- :class:`ArmProbe` gives the renderer (``sim/world/cell.py``) the control loop's newest
  measured TCP and wrist joints, and stamps the frame with the instant the arm measured
  that TCP: so a simulated frame's capture instant is exactly a sample of the arm's
  history, as a real camera's exposure is an instant on the arm's trajectory.
- :class:`SimTruth` is a navigation observer: when the navigator says a target is
  reached, the TRE is the distance between where the end-effector truly was at that
  capture and where the target truly is (eq. 21).
"""

from __future__ import annotations

import logging
import threading

import numpy as np

from oralnav.daemon.core import DaemonCore
from oralnav.sim.world.cell import SimCell

__all__ = ["ArmProbe", "SimTruth"]

log = logging.getLogger(__name__)


class ArmProbe:
    """The arm state the simulated cell renders. ``sample_time()`` (the cell's clock,
    read first at each capture) takes the loop's newest measured TCP and its timestamp;
    ``__call__`` (the cell's arm pose) gives that same TCP, so the image and its stamp
    describe one instant. Before the loop's first period: ``home`` at ``clock()``."""

    def __init__(self, core: DaemonCore, home: np.ndarray) -> None:
        self.core = core
        self._T = np.array(home, dtype=float)
        self._lock = threading.Lock()

    def sample_time(self) -> float:
        st = self.core.control.read_status()
        with self._lock:
            if st is None or int(st["periods"]) == 0:
                return self.core.clock()
            self._T = np.array(st["T_B_tcp"])
            return float(st["t_arm"])

    def __call__(self) -> np.ndarray:
        with self._lock:
            return self._T.copy()

    def wrist(self) -> np.ndarray:
        st = self.core.control.read_status()
        return np.zeros(4) if st is None else np.array(st["wrist"])


class SimTruth:
    """A navigation observer (``NavigationTask(observers=[...])``): the TRE (mm) of a
    reached target against the cell's ground truth, or None when the cell's last capture
    is not the one that reached (its truth would describe another instant)."""

    def __init__(self, cell: SimCell) -> None:
        self.cell = cell

    def __call__(self, target: str, stamp: float) -> float | None:
        truth = self.cell.truth()
        if truth["time"] != stamp:
            log.warning("TRE of %s not measured: the cell's last capture (%.3f s) is not "
                        "the one that reached it (%.3f s)", target, truth["time"], stamp)
            return None
        p_true = self.cell.targets_B().get(target)
        if p_true is None:  # a target the operator registered that the cell does not hold
            return None
        return float(np.linalg.norm(truth["T_B_E"][:3, 3] - p_true)) * 1e3


class PeerTruth:
    """A navigation observer for a hardware-in-the-loop cell of protocol peers (``[cell]
    truth``, ``oralnav sim peers``): the TRE (mm) of a reached target against the truth
    the peers report for the capture at or before the reaching frame's stamp. None (and a
    warning) when the peers do not answer within ``timeout`` s or do not know the target.
    A loopback request, once per target, made in a worker thread (the navigation's); the
    peers' process renders three views with the GIL mostly held, so it may take a second
    to answer on a busy machine."""

    def __init__(self, url: str, timeout: float = 5.0) -> None:
        self.url, self.timeout = url, timeout

    def __call__(self, target: str, stamp: float) -> float | None:
        import json
        import urllib.error
        import urllib.request

        try:
            with urllib.request.urlopen(f"{self.url}?t={stamp!r}",
                                        timeout=self.timeout) as r:
                truth = json.load(r)
        except (urllib.error.URLError, OSError, ValueError) as exc:
            log.warning("TRE of %s not measured: the peers' truth at %s: %s", target,
                        self.url, exc)
            return None
        p_true = truth.get("targets_B", {}).get(target)
        if p_true is None:
            log.warning("TRE of %s not measured: the peers' cell has no such target", target)
            return None
        return float(np.linalg.norm(np.array(truth["T_B_E"])[:3, 3] - np.array(p_true))) * 1e3
