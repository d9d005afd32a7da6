"""The needle procedure's steps checked against the simulated cell's ground truth
(:class:`~oralnav.sim.world.needle_cell.CellTruth`): what the Monte Carlo bench and the
daemon's simulated cell count as a success, never what the procedure acts on.

Pass :func:`check_truth` as the procedure's ``truth_check``
(:class:`~oralnav.control.needle.procedure.NeedleProcedure`); after every step it fills
:attr:`~oralnav.control.needle.procedure.StepResult.truth_ok` and ``truth_detail``, and
adds the tracker's error against the true needle pose to the step's figures (mm, deg).
Reference frame, metres.
"""

from __future__ import annotations

import math

import numpy as np

from oralnav.control.geometry import rotation_angle
from oralnav.control.needle.procedure import NeedleProcedure, StepResult
from oralnav.sim.world.needle_cell import CellTruth

__all__ = ["check_truth", "placement_truth", "pose_error"]


def pose_error(T: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """Centre distance (mm) and rotation angle (deg) between two needle poses."""
    return (float(np.linalg.norm(T[:3, 3] - T_true[:3, 3])) * 1e3,
            math.degrees(rotation_angle(T[:3, :3], T_true[:3, :3])))


def check_truth(proc: NeedleProcedure, res: StepResult) -> None:
    """Fill ``res.truth_ok`` from the cell's ground truth, when it has one: NG, the picker
    holds the needle; NH, the driver alone; ND, :func:`placement_truth`; NR, the
    regrasping arm holds it in the tissue; NP, it is out of the tissue and held. A step
    the procedure did not see succeed is never a truth success."""
    truth_fn = getattr(proc.cell, "truth", None)
    if truth_fn is None:
        return
    t = truth_fn()
    if proc.track is not None:
        e_pos, e_ang = pose_error(proc.track.pose, t.T_ref_needle)
        res.figures["track_error_mm"] = round(e_pos, 3)
        res.figures["track_error_deg"] = round(e_ang, 2)
    held = set(t.held_by)
    step = res.step
    if step == "NG":
        ok = proc.picker is not None and proc.picker in held
        why = f"held by {sorted(held)}"
    elif step == "NH":
        ok = proc.driver is not None and held == {proc.driver}
        why = f"held by {sorted(held)}"
    elif step == "ND":
        ok, why = placement_truth(proc, t)
    elif step == "NR":
        arm = proc.holder
        ok = arm is not None and arm in held and t.in_tissue
        why = f"held by {sorted(held)}, in tissue {t.in_tissue}"
    else:
        ok = t.out_of_tissue_after_pull and bool(held)
        why = f"out of the tissue {t.out_of_tissue_after_pull}, held by {sorted(held)}"
    res.truth_ok = bool(ok and res.ok)
    res.truth_detail = why


def placement_truth(proc: NeedleProcedure, t: CellTruth) -> tuple[bool, str]:
    """ND against truth: the tip went in and came out within the placement tolerance
    of the planned entry and exit."""
    if proc.geometry is None or t.entry is None or t.exit is None:
        return False, (f"entry {'none' if t.entry is None else 'made'}, exit "
                       f"{'none' if t.exit is None else 'made'}")
    entry, exit_ = proc.planned_crossings()
    e_in = float(np.linalg.norm(t.entry - entry))
    e_out = float(np.linalg.norm(t.exit - exit_))
    tol = proc.s.placement_tolerance
    return (e_in <= tol and e_out <= tol,
            f"entry {e_in * 1e3:.2f} mm, exit {e_out * 1e3:.2f} mm from the plan "
            f"(tolerance {tol * 1e3:.1f} mm)")
