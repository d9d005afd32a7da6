"""The needle procedure's view rule (:class:`ViewRule`: whether the cameras would see the
needle well at a pose, past the grippers and against the tissue), and the candidate poses
the hand-off and the pulled needle's look are shown from: the needle turned about its
centre, raised off the tissue and moved toward the middle of the view. Reference frame,
m, rad."""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from oralnav.control.geometry import rotation_angle
from oralnav.control.needle.model import Needle
from oralnav.control.needle.procedure.settings import ProcedureSettings
from oralnav.control.needle.refine import hidden_by
from oralnav.control.needle.tracker import ToolCylinder
from oralnav.control.vision.camera import CameraModel


@dataclass(frozen=True, eq=False)
class ViewRule:
    """Whether the cameras ``cams`` (the reference camera first) would see ``needle`` well
    at a pose: the planner's view rule (the ``view_*``, ``*_visible`` and tool settings
    of ``s``), for the procedure and for port selection alike. ``normal`` (3,): the
    tissue's unit normal; ``outline`` (k, 3): its extent (reference frame, m; ``None``:
    not asked); ``masks``: per camera, the incision line's band the features ignore
    (``None``: not asked)."""

    cams: Sequence[CameraModel]
    needle: Needle
    s: ProcedureSettings
    normal: np.ndarray
    outline: np.ndarray | None = None
    masks: Sequence[np.ndarray] | None = None

    def sight(self, T_ref_N: np.ndarray) -> np.ndarray:
        """The reference camera's line of sight to the needle's centre at ``T_ref_N``
        (unit, reference frame): the views measure depth along it to about a
        millimetre, across it to a tenth."""
        v = T_ref_N[:3, 3] - self.cams[0].T_ref_cam[:3, 3]
        return v / np.linalg.norm(v)

    def aim(self, point: np.ndarray) -> np.ndarray:
        """Where the reference camera's optical axis meets the tissue plane through
        ``point`` (3,, reference frame, m): the middle of its view of the tissue; ``point``
        itself when the axis runs along the plane."""
        o, z = self.cams[0].T_ref_cam[:3, 3], self.cams[0].T_ref_cam[:3, 2]
        den = float(z @ self.normal)
        if abs(den) < 1e-9:
            return np.asarray(point, float)
        return o + float((point - o) @ self.normal) / den * z

    def why_not(self, T_ref_N: np.ndarray, tools: Sequence[np.ndarray] = (),
                incision: bool = False, strict: bool = False) -> str:
        """Why the cameras would not see the needle well at ``T_ref_N`` ("" when they
        would): every camera must see the whole needle ``view_margin_px`` inside the
        image, no more than ``1 - min_visible`` of it behind the grippers at ``tools``
        (their ``T_ref_T``), with ``incision``, in the incision line's band the
        features ignore (``incision_mask_px``), and, with an outline, off the tissue
        surface; the reference view at most ``max_view_angle`` from face-on. (The
        hand-off does not ask ``incision``: near the entry the line crosses most
        views of the needle, and the carried pose holds the parts it hides; the
        pulled needle's look, which must show the hold by the images alone, does.)
        ``strict``: with room for a pose a few millimetres and degrees off the one
        asked about, ``strict_view_angle`` less face-on angle and ``strict_visible``
        more of the needle in view."""
        s = self.s
        pts = self.needle.points(48) @ T_ref_N[:3, :3].T + T_ref_N[:3, 3]
        masks = self.masks if self.masks is not None else [None] * len(self.cams)
        facing = abs(float(T_ref_N[:3, 2] @ self.sight(T_ref_N)))
        max_angle = s.max_view_angle - (s.strict_view_angle if strict else 0.0)
        min_visible = min(1.0, s.min_visible + (s.strict_visible if strict else 0.0))
        if facing < math.cos(max_angle):
            return "edge-on to the camera"
        m = s.view_margin_px
        for cam, masked in zip(self.cams, masks, strict=True):
            uv = cam.project_from(cam.T_cam_ref, pts)
            if not (np.all(np.isfinite(uv)) and np.all(uv >= m)
                    and np.all(uv[:, 0] <= cam.width - 1 - m)
                    and np.all(uv[:, 1] <= cam.height - 1 - m)):
                return "out of view"
            hidden = np.zeros(len(pts), dtype=bool)
            for T in tools:
                hidden |= self.behind_tool(cam, uv, T)
            if 1.0 - hidden.mean() < min_visible:
                return "hidden by the grippers"
            if incision and masked is not None:
                # the features ignore the line's band (a dark line is not the wire)
                px = np.round(uv).astype(int)
                hidden |= masked[px[:, 1], px[:, 0]]
                if 1.0 - hidden.mean() < min_visible:
                    return "hidden by the incision line"
            if self.outline is not None:
                hidden |= ~self.backdrop(cam, pts)
                if 1.0 - hidden.mean() < min_visible:
                    return "hidden or not against the tissue"
        return ""

    def tool_parts(self, T_ref_T: np.ndarray) -> tuple[ToolCylinder, ToolCylinder]:
        """The gripper at ``T_ref_T`` as the parts that may hide the needle: its jaws (a
        cylinder of ``jaw_radius`` over ``jaw_length`` behind the tip) and its shaft
        (``tool_radius``, on to ``tool_length`` behind the tip)."""
        s = self.s
        tip, z = T_ref_T[:3, 3], T_ref_T[:3, 2]
        heel = tip - s.jaw_length * z
        return (ToolCylinder(tip, heel, s.jaw_radius),
                ToolCylinder(heel, tip - s.tool_length * z, s.tool_radius))

    def behind_tool(self, cam: CameraModel, uv: np.ndarray, T_ref_T: np.ndarray
                    ) -> np.ndarray:
        """Which image points ``uv`` (k, 2) the gripper at ``T_ref_T`` may hide. Depth is
        ignored, so a point in front of the tool counts as hidden too: the estimate errs
        toward refusing a view."""
        return hidden_by(self.tool_parts(T_ref_T), cam, uv)

    def backdrop(self, cam: CameraModel, pts: np.ndarray) -> np.ndarray:
        """Which of ``pts`` (k, 3, ref) ``cam`` sees against the tissue: the ray through
        the point meets the tissue plane beyond it, inside the outline (a convex polygon
        in the plane)."""
        assert self.outline is not None
        o = cam.T_ref_cam[:3, 3]
        n, p0 = self.normal, self.outline[0]
        d = pts - o
        den = d @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = ((p0 - o) @ n) / den
        beyond = np.abs(den) > 1e-12
        beyond &= lam > 1.0             # the surface must lie beyond the needle
        hit = o + np.where(beyond, lam, 0.0)[:, None] * d
        edges = np.roll(self.outline, -1, axis=0) - self.outline
        # the polygon's winding about the normal: inside is on the same side of every edge
        sign = 1.0 if float(np.cross(edges[0], edges[1]) @ n) >= 0 else -1.0
        inside = beyond
        for a, e in zip(self.outline, edges, strict=True):
            inside &= sign * (np.cross(e, hit - a) @ n) > 0
        return inside


def _turns(step_deg: float = 30.0, axes: int = 40) -> list[np.ndarray]:
    """Rotations (3x3) of angles 0, step, ..., 180 deg about ``axes`` directions spread
    over the sphere (a Fibonacci lattice), the identity first, then by angle."""
    k = np.arange(axes) + 0.5
    z = 1.0 - 2.0 * k / axes
    az = math.pi * (1.0 + 5.0 ** 0.5) * k
    dirs = np.stack([np.sqrt(1 - z * z) * np.cos(az), np.sqrt(1 - z * z) * np.sin(az), z], 1)
    out = [np.eye(3)]
    for a in np.arange(step_deg, 180.0 + 1e-9, step_deg):
        out += [cv2.Rodrigues(d * math.radians(a))[0] for d in dirs]
    return out


#: The hand-off's candidate turns of the needle from its drive start orientation.
_HANDOFF_TURNS = _turns()


def _turned_and_raised(T_N: np.ndarray, normal: np.ndarray, heights: Sequence[float]
                       ) -> Iterator[tuple[np.ndarray, float, float]]:
    """Needle poses near ``T_N`` for a hand-off or a look: turned about the needle's
    centre by each of :data:`_HANDOFF_TURNS` (the least first) and raised along
    ``normal`` by each of ``heights`` (m). Items: ``(T_ref_N, turn (rad), height)``."""
    for turn in _HANDOFF_TURNS:
        angle = rotation_angle(turn, np.eye(3))
        for h in heights:
            T = T_N.copy()
            T[:3, :3] = turn @ T_N[:3, :3]
            T[:3, 3] += h * normal
            yield T, angle, h


def _shifted(T: np.ndarray, normal: np.ndarray, toward: np.ndarray,
             shifts: Sequence[float]) -> Iterator[np.ndarray]:
    """The pose ``T`` moved in the plane square to ``normal`` toward ``toward`` (3,) by
    each of ``shifts`` (m), no further than all the way there; a shift that comes out the
    same as an earlier one is not repeated."""
    d = toward - T[:3, 3]
    d -= float(d @ normal) * normal
    far = float(np.linalg.norm(d))
    done: set[float] = set()
    for shift in shifts:
        shift = min(shift, far)
        if shift in done:
            continue
        done.add(shift)
        moved = T.copy()
        if shift > 0:
            moved[:3, 3] += shift / far * d
        yield moved
