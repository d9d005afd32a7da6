"""The needle procedure's plan geometry (reference frame, m, rad): the suture's two drives
(as given and reversed), the driving arm and its grasp, the pick-up grasp's points, the
hand-off poses and where the two arms meet, and the tip part the regrasp may hold and
pull by."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace

import numpy as np

from oralnav.control.errors import NeedleError
from oralnav.control.geometry import invert
from oralnav.control.needle.drive import Drive, SutureGeometry, plan_drive, pull_poses, tissue_frame
from oralnav.control.needle.grasp import (
    GraspChoice,
    GraspSettings,
    SurfaceGrasp,
    grasp_band,
    surface_grasps,
)
from oralnav.control.needle.model import Needle
from oralnav.control.needle.procedure.poses import _path, back_off
from oralnav.control.needle.procedure.settings import ProcedureSettings
from oralnav.control.needle.procedure.views import ViewRule, _shifted, _turned_and_raised


def drive_pick(s: ProcedureSettings) -> GraspSettings:
    """The drive grasp rule as the plan applies it (``grasp_margin`` more from the swage)."""
    return replace(s.drive_grasp, swage_margin=s.drive_grasp.swage_margin + s.grasp_margin)


def drive_ways(incision: np.ndarray, normal: np.ndarray, geometry: SutureGeometry,
               s: ProcedureSettings) -> list[tuple[str, np.ndarray, Drive]]:
    """The two drives of the suture at ``s.suture_at`` along ``incision`` (2, 3; reference
    frame, m) on the surface of unit ``normal``: ``("as given", G_CS, drive)`` with the
    entry on the side the incision's direction sets, then ``("reversed", ...)``, the same
    point crossed the other way (a backhand stitch for a forehand one). Raises
    :class:`NeedleError` for a degenerate incision or suture."""
    point = incision[0] + s.suture_at * (incision[1] - incision[0])
    out = []
    for ends, way in ((incision, "as given"), (incision[::-1], "reversed")):
        G_CS = tissue_frame(ends[0], ends[1], normal, suture_point=point)
        out.append((way, G_CS, plan_drive(np.eye(4), G_CS, geometry, s.drive_poses,
                                          overshoot=s.overshoot)))
    return out


def _arc_under(needle: Needle, T_N: np.ndarray, point: np.ndarray, normal: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The arc of ``needle`` at ``T_N`` in 721 points: their angles (rad), their
    positions (ref, m) and the indices of those under the surface through ``point`` with
    unit ``normal`` (out of the tissue)."""
    phis = np.linspace(0.0, needle.arc, 721)
    pts = needle.point(phis) @ T_N[:3, :3].T + T_N[:3, 3]
    under = np.nonzero((pts - point) @ normal < 0.0)[0]
    return phis, pts, under


def tip_part(needle: Needle, T_N: np.ndarray, point: np.ndarray, normal: np.ndarray,
              s: ProcedureSettings) -> tuple[float, float, float]:
    """The tip part out of the tissue with the needle at ``T_N`` (surface as in
    :func:`_arc_under`): the regrasp may hold it from ``phi_lo`` to ``phi_hi`` (rad;
    empty when ``hi < lo``); and how far the tip stands out along the arc (mm)."""
    r, arc = needle.radius, needle.arc
    phis, _, under = _arc_under(needle, T_N, point, normal)
    cross = phis[under[-1]] if under.size else 0.0
    return (cross + s.regrasp_exit_margin / r, arc - s.regrasp_tip_margin / r,
            (arc - cross) * r * 1e3)


def _tip_grasps(needle: Needle, T_N: np.ndarray, point: np.ndarray, normal: np.ndarray,
                s: ProcedureSettings, lo: float, hi: float) -> list[SurfaceGrasp]:
    """The regrasp's candidates on the tip part ``lo``..``hi`` (rad) of the needle at
    ``T_N``, the steepest shafts first. The tip part rises steeply out of the exit, and
    a jaw square to the wire holds the shaft at most (90 deg - the wire's rise) above
    the surface: the grasps along the whole tip part (nearer the exit the wire leans
    more, further out it stands higher)."""
    grasps = [g for phi in np.linspace(lo, hi, s.regrasp_points)
              for g in surface_grasps(needle, T_N, float(phi), point, normal, s.regrasp)]
    grasps.sort(key=lambda g: -g.elevation)
    return grasps


def _pulls(needle: Needle, s: ProcedureSettings, reachable: Callable[[np.ndarray], bool],
           T_N: np.ndarray, G_CS: np.ndarray, point: np.ndarray, normal: np.ndarray) -> bool:
    """Whether an arm that reaches a pose when ``reachable(T_ref_T)`` can regrasp the tip
    of the needle standing at ``T_N`` in the tissue of frame ``G_CS`` (surface through
    ``point`` with ``normal``) and pull it out along the planned pull."""
    lo, hi, _ = tip_part(needle, T_N, point, normal, s)
    if hi < lo:
        return False
    for g in _tip_grasps(needle, T_N, point, normal, s, lo, hi):
        if not (reachable(g.T_ref_T) and reachable(back_off(g.T_ref_T, s.approach))):
            continue
        try:
            pull = pull_poses(np.eye(4), G_CS, T_N, g.G_TN, needle, s.pull_poses,
                              s.swage_clearance, s.pull_lift)
        except NeedleError:
            continue
        if all(reachable(T) for T in pull.G_PT):
            return True
    return False


def _driver_choice(ways: Sequence[tuple[str, np.ndarray, Drive]],
                   choose: Mapping[str, Callable[[int], GraspChoice]]
                   ) -> tuple[tuple[str, np.ndarray, Drive], str, GraspChoice]:
    """The plan's driver: of the first of ``ways`` that some arm can drive
    (``choose[arm](k)``: its driving grasp for ``ways[k]``, :func:`select_grasp`'s, or
    :class:`NeedleError`), the arm whose grasp scores best. ``(way item, arm, grasp)``;
    :class:`NeedleError` naming every arm's refusal when none drives either way."""
    why: dict[str, str] = {}
    for k, chosen in enumerate(ways):
        options = []
        for arm, pick in choose.items():
            try:
                choice = pick(k)
            except NeedleError as exc:
                why[f"{arm} ({chosen[0]})"] = str(exc)
                continue
            options.append((choice.score, arm, choice))
        if options:
            _, arm, choice = max(options, key=lambda o: o[0])
            return chosen, arm, choice
    raise NeedleError("no arm can drive this suture either way: "
                      + "; ".join(f"{a}: {w}" for a, w in why.items()))


def _pickup_phis(needle: Needle, s: ProcedureSettings, phi_B: float) -> np.ndarray:
    """The pick-up grasp's candidate points (rad along the arc) in the grasp band, clear
    of the driving grasp at ``phi_B`` by ``separation + grasp_margin``: the hand-off
    puts both jaws on the needle. Empty when the band leaves no room."""
    lo, hi = grasp_band(needle, s.drive_grasp)
    gap = (s.separation + s.grasp_margin) / needle.radius
    free = [(max(lo, phi_B + gap), hi), (lo, min(hi, phi_B - gap))]
    return np.concatenate([np.linspace(a, b, 7) for a, b in free if b >= a] or [[]])


def _handoff_poses(drive: Drive, G_TN_B: np.ndarray, normal: np.ndarray, s: ProcedureSettings,
                   reach_all: Callable[[np.ndarray], np.ndarray], toward: np.ndarray
                   ) -> list[tuple[np.ndarray, np.ndarray, float, float]]:
    """Needle poses for the hand-off where the driver, gripping with ``G_TN_B``, reaches
    its driving grasp and its approach (``reach_all(T (N, 4, 4)) -> (N,) bool``): the
    drive's start pose moved by each of ``handoff_shifts`` in the tissue plane toward
    ``toward`` (3,; no further than it), raised ``handoff_heights`` above the tissue and
    turned about the needle's centre, the least shift, then the least turn first.
    Items: ``(T_ref_N, driver's T_ref_T, turn (rad), height (m))``."""
    start = drive.G_PS @ drive.G_SN[0]
    items: list[tuple[np.ndarray, float, float]] = []
    for moved in _shifted(start, normal, toward, s.handoff_shifts):
        items += _turned_and_raised(moved, normal, s.handoff_heights)
    T_B = np.stack([T for T, _, _ in items]) @ invert(G_TN_B)
    ok = reach_all(T_B)
    ok[ok] &= reach_all(back_off(T_B[ok], s.approach))
    return [(T_h, T_B[k], turn, H) for k, (T_h, turn, H) in enumerate(items) if ok[k]]


def _meetings(handoffs: Sequence[tuple], G_TN_A: np.ndarray,
              reach_all: Callable[[np.ndarray], np.ndarray], views: ViewRule, most: int,
              T_A0: np.ndarray | None = None, why: dict[str, int] | None = None,
              holder: str = "the holder",
              also: Callable[[tuple], str] | None = None) -> list[tuple]:
    """The first ``most`` of the hand-off candidates ``handoffs`` (:func:`_handoff_poses`'
    items) where the holder, gripping with ``G_TN_A``, reaches (``reach_all``; along its
    straight path from ``T_A0``, when given), the cameras see the needle past both
    grippers (``views``) and ``also(item)`` (when given) names no refusal; ``why``
    counts the refusals, naming ``holder``."""
    if not handoffs:
        return []
    why = {} if why is None else why
    T_A = np.stack([item[0] for item in handoffs]) @ invert(G_TN_A)
    there = reach_all(T_A)
    # the view rule, the dearer check, asked in batches of the poses the holder reaches
    held = np.nonzero(there)[0]
    at = {int(k): j for j, k in enumerate(held)}
    view = views.why_not_each([handoffs[k][0] for k in held],
                              [(handoffs[k][1], T_A[k]) for k in held])
    out = []
    for k, item in enumerate(handoffs):
        if not there[k]:
            refused = f"{holder} cannot hold it there"
        elif seen := view(at[k]):
            refused = f"hand-off {seen}"
        # the path last: the costliest check, for the few poses that pass the others
        elif T_A0 is not None and not reach_all(np.stack(_path(T_A0, T_A[k]))).all():
            refused = f"{holder} cannot carry it there"
        else:
            refused = also(item) if also is not None else ""
        if refused:
            why[refused] = why.get(refused, 0) + 1
            continue
        out.append(item)
        if len(out) >= most:
            break
    return out
