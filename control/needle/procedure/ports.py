"""Entry port selection with the needle procedure's own rules (seed 002's ref. [8]): for a
cell set up before the procedure, whether an arm at a port can drive the suture and pull
the needle out (:func:`port_drives`), and whether a pair of arms can also pick the needle
up and hand it over (:func:`port_pair`). Reference frame, m, rad."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from oralnav.control.errors import NeedleError
from oralnav.control.needle.drive import SutureGeometry
from oralnav.control.needle.grasp import GraspChoice, select_grasp, surface_grasps
from oralnav.control.needle.model import Needle
from oralnav.control.needle.procedure.planning import (
    _driver_choice,
    _handoff_poses,
    _meetings,
    _pickup_phis,
    _pulls,
    drive_pick,
    drive_ways,
)
from oralnav.control.needle.procedure.poses import back_off, translation
from oralnav.control.needle.procedure.settings import ProcedureSettings
from oralnav.control.needle.procedure.views import ViewRule
from oralnav.control.vision.camera import Rig


def port_drives(needle: Needle, settings: ProcedureSettings | None = None
                ) -> Callable[[Any, np.ndarray, np.ndarray], bool]:
    """Entry port selection (seed 002's grasp rule comes from its ref. [8], Liu and
    Cavusoglu, "Needle grasp and entry port selection ..."): a check
    ``drives(reach, incision, normal) -> bool`` of whether an arm whose reach is ``reach``
    (``reach.reachable(T_ref_tool, margin) -> (ok, why)``, as the simulator's
    ``ArmReach``) can drive the planned suture either way with a grasp the plan would
    choose and then, from the same port, regrasp the tip where the planned drive leaves
    it and pull the needle out (seed 002's needle driving, its five steps; the driver
    regrasps first, :meth:`NeedleProcedure._step_nr`), for a cell set up before the
    procedure (the planner's own rules and margin, :meth:`NeedleProcedure._plan`). A
    suture the settings refuse drives from no port."""
    s = settings or ProcedureSettings()
    pick = drive_pick(s)
    try:
        geometry = SutureGeometry.for_needle(needle, s.depth)
    except NeedleError:
        geometry = None

    def drives(reach: Any, incision: np.ndarray, normal: np.ndarray) -> bool:
        if geometry is None:
            return False

        def reachable(T: np.ndarray) -> bool:
            return bool(reach.reachable(T, s.reach_margin)[0])

        try:
            ways = drive_ways(np.asarray(incision, float), np.asarray(normal, float),
                              geometry, s)
        except NeedleError:
            return False
        point = np.mean(np.asarray(incision, float), axis=0)
        normal = np.asarray(normal, float)
        for _, G_CS, drive in ways:
            try:
                select_grasp(needle, drive, pick, reachable=reachable)
            except NeedleError:
                continue
            if _pulls(needle, s, reachable, G_CS @ drive.G_SN[-1], G_CS, point, normal):
                return True
        return False

    return drives


def port_pair(needle: Needle, settings: ProcedureSettings | None = None
              ) -> Callable[..., bool]:
    """Entry port selection for the pair of arms: a check ``workable(reaches, incision,
    normal, T_ref_needle, rig, outline) -> bool`` of whether, with each arm ``name`` at
    the port of ``reaches[name]`` (as :func:`port_drives`'s ``reach``, with
    ``reachable_all(T (N, 4, 4), margin) -> (N,) bool`` too), the plan's driver
    (:meth:`NeedleProcedure._plan`) drives the suture and pulls the needle out, and the
    other arm picks up the needle lying at ``T_ref_needle`` (reference frame, m) with a
    grasp the pick-up would make (NG: clear of the driving grasp, reached with its
    approach and its lift, the lifted needle seen) that can carry the needle from its
    lift to ``handoff_meetings`` of the hand-off poses the driver reaches (a straight
    path, as NH's), the cameras of ``rig``
    seeing the needle there past both grippers (NH; the tissue's ``outline`` (k, 3) as
    :class:`ViewRule`'s, or ``None``).

    A trial asks about many pairs of a few sites each: what one arm's site decides (its
    driving grasps, its pull, the hand-off poses it reaches and the cameras see) is
    kept for the scene last asked about."""
    s = settings or ProcedureSettings()
    pick = drive_pick(s)
    m = s.reach_margin
    try:
        geometry = SutureGeometry.for_needle(needle, s.depth)
    except NeedleError:
        geometry = None
    memo: dict[Any, Any] = {}

    def workable(reaches: Mapping[str, Any], incision: np.ndarray, normal: np.ndarray,
                 T_ref_needle: np.ndarray, rig: Rig, outline: np.ndarray | None = None
                 ) -> bool:
        if geometry is None or len(reaches) != 2:
            return False
        incision = np.asarray(incision, float)
        normal = np.asarray(normal, float) / np.linalg.norm(normal)
        T_ref_needle = np.asarray(T_ref_needle, float)
        scene = (incision.tobytes(), normal.tobytes(), T_ref_needle.tobytes(), id(rig),
                 None if outline is None else np.asarray(outline).tobytes())
        if memo.get("scene") != scene:
            memo.clear()
            memo["scene"] = scene
            try:
                memo["ways"] = drive_ways(incision, normal, geometry, s)
            except NeedleError:
                memo["ways"] = None
            memo["views"] = ViewRule([rig[c] for c in rig.names], needle, s, normal, outline)
        ways, views = memo["ways"], memo["views"]
        if ways is None:
            return False
        point = incision.mean(axis=0)
        one = {a: (lambda T, r=r: bool(r.reachable(T, m)[0])) for a, r in reaches.items()}

        def site(a: str) -> bytes:
            return reaches[a].rcm.tobytes()

        def grasp(a: str, k: int) -> GraspChoice:
            key = ("grasp", site(a), k)
            if key not in memo:
                try:
                    memo[key] = select_grasp(needle, ways[k][2], pick, reachable=one[a])
                except NeedleError as exc:
                    memo[key] = exc
            if isinstance(memo[key], NeedleError):
                raise memo[key]
            return memo[key]

        try:
            way, B, choice = _driver_choice(ways, {a: (lambda k, a=a: grasp(a, k))
                                                   for a in reaches})
        except NeedleError:
            return False
        _, G_CS, drive = way
        key = ("driver", site(B), way[0])
        if key not in memo:
            # the driver's side: it pulls, and the hand-off poses it reaches that the
            # cameras see past its own gripper
            meet: list[tuple] = []
            if _pulls(needle, s, one[B], G_CS @ drive.G_SN[-1], G_CS, point, normal):
                items = _handoff_poses(drive, choice.G_TN, normal, s,
                                       lambda T: reaches[B].reachable_all(T, m),
                                       views.aim(point))
                seen = views.why_not_all(np.stack([it[0] for it in items]),
                                         np.stack([it[1] for it in items])[:, None]
                                         ) if items else []
                meet = [it for it, why in zip(items, seen, strict=True) if not why]
            memo[key] = meet
        meet = memo[key]
        if not meet:
            return False
        A = next(a for a in reaches if a != B)
        lifts = [translation(h * normal) for h in sorted({s.lift, min(s.lift, s.lift_low)})]
        for phi in _pickup_phis(needle, s, choice.phi):
            for g in surface_grasps(needle, T_ref_needle, float(phi), point, normal,
                                    s.pickup_grasp):
                if not (one[A](g.T_ref_T) and one[A](back_off(g.T_ref_T, s.approach))):
                    continue
                # from each lift that the arm reaches and the cameras see, as NG's and
                # NH's: the holder carries the needle there on a straight path
                for up in lifts:
                    if not one[A](up @ g.T_ref_T) \
                            or views.why_not(up @ T_ref_needle, [up @ g.T_ref_T]):
                        continue
                    if len(_meetings(meet, g.G_TN,
                                     lambda T: reaches[A].reachable_all(T, m), views,
                                     s.handoff_meetings, up @ g.T_ref_T)
                           ) >= s.handoff_meetings:
                        return True
        return False

    return workable
