"""The needle procedure as the daemon runs it over REST (issue 7, item 7): one simulated
needle cell at a time, its five steps called one by one (``POST /needle/{step}``), the
state and results read back (``GET /needle``).

The cell is the simulator's randomised trial cell (``POST /needle/cell``): no needle
hardware exists to drive yet, and the cell's ground truth gives each step its success
check (``oralnav.sim.world.needle_truth``). Steps block (they render, track and move for a
second or more): the API runs them in a worker thread, and one runs at a time. A step
refused before moving, a step out of turn (the procedure's
:class:`~oralnav.control.errors.StepOrderError`, with its message), a step while the safety
state forbids motion, and a second step while one runs are
:class:`~oralnav.safety.errors.StateError` (409) and change nothing; a step that ran
answers its result, failed or not. A stop that comes while a step runs halts the arm
within one motion increment (:class:`StoppableCell`), and the step fails
(``move_stopped``, naming the safety state).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np

from oralnav.control.errors import StepOrderError
from oralnav.control.needle.procedure import (
    NeedleProcedure,
    ProcedureSettings,
    port_drives,
    port_pair,
)
from oralnav.control.needle.servo import ServoSettings
from oralnav.realtime.needle_tracking import start_tracking
from oralnav.safety.errors import StateError

log = logging.getLogger(__name__)

#: How a loaded cell's drive is guided: open-loop, servoed on looks every few poses, or
#: servoed frame by frame from the needle tracking task.
SERVO_MODES = ("off", "looks", "stream")


class StoppableCell:
    """The needle cell as the daemon's steps move it: before every jaw action, and after
    every increment of a move (1 mm, 2 deg: ``NeedleCell.move``'s steps), it asks
    ``motion_refused()`` whether motion is still allowed. A stop that comes while a step
    runs (an e-stop, a fault: the core's latched states) ends the motion where it is,
    within one increment: the cell's ``CellError`` naming the safety state, which the step
    reports as ``move_stopped``. Everything else is the cell's own (attributes are passed
    through)."""

    def __init__(self, cell: Any, motion_refused: Callable[[], str]) -> None:
        self._cell = cell
        self._refused = motion_refused

    def __getattr__(self, name: str) -> Any:
        return getattr(self._cell, name)

    def _check(self, _cell: object = None) -> None:
        from oralnav.sim.world.cell import CellError

        why = self._refused()
        if why:
            raise CellError(f"stopped: {why}")

    def move(self, name: str, T_ref_tool_reported: np.ndarray) -> None:
        self._check()
        self._cell.move(name, T_ref_tool_reported, on_step=self._check)

    def close(self, name: str) -> bool:
        self._check()
        return bool(self._cell.close(name))

    def open(self, name: str) -> None:
        self._check()
        self._cell.open(name)


class NeedleSession:
    """See the module docstring. ``motion_refused()`` returns why motion is not allowed
    now (``""`` when it is): the core's safety state."""

    def __init__(self, motion_refused: Callable[[], str],
                 settings: ProcedureSettings | None = None) -> None:
        self._refused = motion_refused
        self._settings = settings or ProcedureSettings()
        self._lock = threading.Lock()        # one load or step at a time
        self._proc: NeedleProcedure | None = None
        self._cell_info: dict[str, Any] | None = None
        self._busy: str | None = None

    def load_trial(self, trial: int, difficulty: float, who: str,
                   servo: str = "off") -> dict[str, Any]:
        """Replace the cell by simulated trial ``trial`` (a fresh procedure at NG). A bad
        seed or difficulty is the trial's ``CellError`` (a ValueError: 422). ``servo``:
        the drive open-loop (``off``), servoed on looks every few poses (``looks``), or
        servoed frame by frame from the needle tracking task
        (:mod:`oralnav.realtime.needle_tracking`; ``stream``), whose threads run under the
        step's and end with it; a stop that comes while it runs halts the arm within one
        increment as for any step."""
        if servo not in SERVO_MODES:
            raise ValueError(f"servo must be one of {', '.join(SERVO_MODES)}, got {servo!r}")
        from oralnav.config.rig import trial_rig
        from oralnav.sim.world.needle_trials import CT1, trial_cell
        from oralnav.sim.world.needle_truth import check_truth

        if not self._lock.acquire(blocking=False):
            raise StateError(f"cannot load a cell while needle step {self._busy} runs")
        try:
            # the cell set up for the suture: ports chosen with this procedure's rules
            cell, info = trial_cell(int(trial), rig=trial_rig(), difficulty=float(difficulty),
                                    drivable=port_drives(CT1, self._settings),
                                    workable=port_pair(CT1, self._settings))
            settings = (self._settings if servo == "off" else
                        replace(self._settings,
                                drive_servo=self._settings.drive_servo or ServoSettings()))
            proc = NeedleProcedure(StoppableCell(cell, self._refused), info.incision,
                                   info.surface_normal, settings,
                                   surface_outline=info.surface_outline,
                                   truth_check=check_truth,
                                   feed=start_tracking if servo == "stream" else None)
            self._proc = proc
            self._cell_info = {"trial": int(trial), "difficulty": float(difficulty),
                               "servo": servo,
                               "loaded_by": who, "incision": info.incision.tolist(),
                               "surface_normal": info.surface_normal.tolist()}
        finally:
            self._lock.release()
        log.info("needle cell: trial %d (difficulty %.2f, servo %s) loaded by %s", trial,
                 difficulty, servo, who)
        return self.status()

    def run_step(self, step: str, who: str) -> dict[str, Any]:
        """Run one step; its result. StateError (nothing changed) when refused."""
        why = self._refused()
        if why:
            raise StateError(f"needle step {step} refused: {why}")
        if not self._lock.acquire(blocking=False):
            raise StateError(f"needle step {step} refused: step {self._busy} is running")
        try:
            proc = self._proc
            if proc is None:
                raise StateError("no needle cell: POST /needle/cell first")
            self._busy = step
            try:
                res = proc.run(step)
            except StepOrderError as exc:
                # out of turn or unknown: the daemon's 409, with the procedure's words
                raise StateError(str(exc)) from exc
        finally:
            self._busy = None
            self._lock.release()
        log.info("needle step %s by %s: %s%s", res.step, who, "ok" if res.ok else res.cause,
                 "" if res.truth_ok is None else f" (truth {res.truth_ok})")
        if res.refused:
            raise StateError(f"needle step {res.step} refused: {res.detail}")
        return {"result": res.to_json(), "next": proc.next_step}

    def status(self) -> dict[str, Any]:
        """``GET /needle``: the cell, the running step, the procedure's state."""
        proc = self._proc
        return {"cell": self._cell_info, "running": self._busy,
                "procedure": None if proc is None else proc.status()}
