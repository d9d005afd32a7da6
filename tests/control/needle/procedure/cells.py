"""Shared by the needle procedure's tests: the shipped trial rig, fast settings, a
procedure on a trial cell, and snapshots of the cell's true poses."""

from __future__ import annotations

import math

import numpy as np

from oralnav.config.rig import trial_rig
from oralnav.control.geometry import rotation_angle
from oralnav.control.needle.procedure import (
    NeedleProcedure,
    ProcedureSettings,
    port_drives,
    port_pair,
)
from oralnav.sim.world.needle_cell import NeedleCell
from oralnav.sim.world.needle_trials import CT1, trial_cell
from oralnav.sim.world.needle_truth import check_truth

#: The shipped stereo endoscope the trials are seen by.
RIG = trial_rig()

FAST = ProcedureSettings(particles=1500)


def _ports(settings: ProcedureSettings) -> dict:
    """The trial's ports chosen for the suture with ``settings``' rules, as the bench's."""
    return {"drivable": port_drives(CT1, settings), "workable": port_pair(CT1, settings)}


def _procedure(seed: int = 0, settings: ProcedureSettings = FAST, **cell_options):
    cell, info = trial_cell(seed, rig=RIG, **cell_options)
    proc = NeedleProcedure(cell, info.incision, info.surface_normal, settings,
                           surface_outline=info.surface_outline, truth_check=check_truth)
    return cell, proc


def _snapshot(cell: NeedleCell) -> list[np.ndarray]:
    return [cell.truth().T_ref_needle] + [cell.true_gripper_pose(g) for g in cell.grippers]


def _unmoved(cell: NeedleCell, before: list[np.ndarray]) -> bool:
    return all(np.array_equal(a, b) for a, b in zip(before, _snapshot(cell), strict=True))


def _passes_to_the_regrasp(seed: int, blind: bool = False) -> None:
    """Trial ``seed`` (its ports chosen for the suture) passes NG to NR (truth), the
    needle in the tissue after ND tracked within 3 deg; ``blind``: the tracker has its
    blind pixels."""
    cell, proc = _procedure(seed, settings=ProcedureSettings(),
                            **_ports(ProcedureSettings()))
    assert not blind or proc.tracker.blind is not None
    for step in ("NG", "NH", "ND", "NR"):
        r = proc.run(step)
        assert r.ok and r.truth_ok, r
        if step == "ND":
            T_t = cell.truth().T_ref_needle
            assert math.degrees(rotation_angle(proc.track.pose[:3, :3], T_t[:3, :3])) < 3.0
