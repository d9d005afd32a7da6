"""The procedure's view rule asked about many poses at once (issue 36 item 3, per-trial
cost): the batched answers (:meth:`ViewRule.why_not_all`, :meth:`ViewRule.why_not_each`)
are the rule's, pose for pose, for every kind of refusal.
"""

from __future__ import annotations

import numpy as np

from oralnav.control.needle.procedure.views import _turned_and_raised
from oralnav.control.needle.refine import ToolCylinder

from .cells import _procedure


def _reference(views, T_ref_N: np.ndarray, tools, incision: bool, strict: bool) -> str:
    """The view rule written out for one pose, each gripper part's occlusion asked alone
    (:meth:`ToolCylinder.hides`): the oracle the batches are held to."""
    s = views.s
    pts = views.needle.points(48) @ T_ref_N[:3, :3].T + T_ref_N[:3, 3]
    facing = abs(float(T_ref_N[:3, 2] @ views.sight(T_ref_N)))
    if facing < np.cos(s.max_view_angle - (s.strict_view_angle if strict else 0.0)):
        return "edge-on to the camera"
    least = min(1.0, s.min_visible + (s.strict_visible if strict else 0.0))
    m = s.view_margin_px
    for cam, masked in zip(views.cams, views.masks, strict=True):
        uv = cam.project_from(cam.T_cam_ref, pts)
        if not (np.all(np.isfinite(uv)) and np.all(uv >= m)
                and np.all(uv[:, 0] <= cam.width - 1 - m)
                and np.all(uv[:, 1] <= cam.height - 1 - m)):
            return "out of view"
        hidden = np.zeros(len(pts), dtype=bool)
        for T in tools:
            tip, z = T[:3, 3], T[:3, 2]
            heel = tip - s.jaw_length * z
            for part in (ToolCylinder(tip, heel, s.jaw_radius),
                         ToolCylinder(heel, tip - s.tool_length * z, s.tool_radius)):
                hidden |= part.hides(cam, uv)
        if 1.0 - hidden.mean() < least:
            return "hidden by the grippers"
        if incision:
            px = np.round(uv).astype(int)
            hidden |= masked[px[:, 1], px[:, 0]]
            if 1.0 - hidden.mean() < least:
                return "hidden by the incision line"
        hidden |= ~views.backdrop(cam, pts)
        if 1.0 - hidden.mean() < least:
            return "hidden or not against the tissue"
    return ""


def test_batched_view_answers_are_the_rules_pose_for_pose():
    """Issue 36 item 3: hand-off-like candidates about trial 3's needle (turned, raised,
    shifted across the view, some out of it, some over the incision), each with both
    grippers or with one moved over the needle, get from one batch, and from the lazy
    batches the planners use, the answer the rule gives for that pose alone, for each
    strictness; the candidates draw every kind of refusal."""
    cell, proc = _procedure(3)
    views = proc.views
    T_N = cell.truth().T_ref_needle
    grips = [cell.gripper_pose(g) for g in cell.grippers]
    poses, tools = [], []
    on_line = proc.incision.mean(axis=0) - T_N[:3, 3]      # the needle over the incision
    for shift in (0.0, 0.02 * np.array([1.0, 0.5, 0.0]), 0.06 * np.array([1.0, 0.5, 0.0]),
                  on_line):
        shifted = T_N.copy()
        shifted[:3, 3] += shift
        for k, (T, _, _) in enumerate(_turned_and_raised(shifted, views.normal, (0.0, 0.01))):
            if k % 7:
                continue
            over = grips[0].copy()
            over[:3, 3] = T[:3, 3] + 0.01 * views.normal     # a gripper just above it
            poses.append(T)
            tools.append(np.stack([grips[0], grips[1]] if k % 2 else [over, grips[1]]))
    poses, tools = np.stack(poses), np.stack(tools)
    kinds = set()
    for strict, incision in ((True, True), (False, True), (False, False)):
        want = [_reference(views, T, tl, incision, strict)
                for T, tl in zip(poses, tools, strict=True)]
        kinds |= set(want)
        assert views.why_not_all(poses, tools, incision, strict) == want
        lazy = views.why_not_each(list(poses), list(tools), incision, strict, first=3)
        assert [lazy(k) for k in range(0, len(poses), 2)] == want[::2]
        assert [views.why_not(T, tl, incision, strict)
                for T, tl in zip(poses[:12], tools[:12], strict=True)] == want[:12]
    assert kinds == {"", "edge-on to the camera", "out of view", "hidden by the grippers",
                     "hidden by the incision line", "hidden or not against the tissue"}, kinds
    assert views.why_not_all(poses[:0], tools[:0]) == []
