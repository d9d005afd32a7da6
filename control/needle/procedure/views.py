"""The needle procedure's view rule (:class:`ViewRule`: whether the cameras would see the
needle well at a pose, past the grippers and against the tissue), and the candidate poses
the hand-off and the pulled needle's look are shown from: the needle turned about its
centre, raised off the tissue and moved toward the middle of the view. Reference frame,
m, rad."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from oralnav.control.geometry import rotation_angle
from oralnav.control.needle.model import Needle
from oralnav.control.needle.procedure.settings import ProcedureSettings
from oralnav.control.needle.refine import cylinders_hide
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
        T = np.asarray(T_ref_N, dtype=float)[None]
        tl = np.asarray(list(tools), dtype=float).reshape(1, -1, 4, 4)
        return self.why_not_all(T, tl, incision, strict)[0]

    def why_not_all(self, T_ref_N: np.ndarray, tools: np.ndarray | None = None,
                    incision: bool = False, strict: bool = False) -> list[str]:
        """:meth:`why_not` for ``N`` needle poses at once (N, 4, 4), each with its own
        grippers ``tools`` (N, m, 4, 4; ``None``: none): the planners weigh hundreds of
        hand-off and look poses, and asked one at a time the view rule was a third of a
        trial's time. Each answer is the one :meth:`why_not` gives: the first refusal in
        its order (face-on, then per camera: in view, past the grippers, the incision
        line, the backdrop)."""
        s = self.s
        T = np.asarray(T_ref_N, dtype=float).reshape(-1, 4, 4)
        N = len(T)
        why = [""] * N
        if N == 0:
            return why
        tl = (np.zeros((N, 0, 4, 4)) if tools is None
              else np.asarray(tools, dtype=float).reshape(N, -1, 4, 4))
        model = self.needle.points(48)
        pts = model @ T[:, :3, :3].transpose(0, 2, 1) + T[:, None, :3, 3]   # (N, 48, 3)
        masks = self.masks if self.masks is not None else [None] * len(self.cams)
        v = T[:, :3, 3] - self.cams[0].T_ref_cam[:3, 3]
        sight = v / np.linalg.norm(v, axis=1)[:, None]
        facing = np.abs(np.einsum("ij,ij->i", T[:, :3, 2], sight))
        max_angle = s.max_view_angle - (s.strict_view_angle if strict else 0.0)
        min_visible = min(1.0, s.min_visible + (s.strict_visible if strict else 0.0))
        open_ = facing >= math.cos(max_angle)       # not refused yet
        for k in np.nonzero(~open_)[0]:
            why[k] = "edge-on to the camera"
        # the grippers' parts, per pose and tool: jaws, then shaft
        m_parts = 2 * tl.shape[1]
        ends_a, ends_b = self._part_ends(tl)                              # (N, m, 2, 3)
        pa, pb = ends_a.reshape(N, m_parts, 3), ends_b.reshape(N, m_parts, 3)
        radius = np.tile([s.jaw_radius, s.tool_radius], tl.shape[1])
        m = s.view_margin_px

        def refuse(idx: np.ndarray, bad: np.ndarray, reason: str) -> np.ndarray:
            """Give the poses ``idx[bad]`` ``reason``; the rest's positions in ``idx``."""
            for k in idx[bad]:
                why[k] = reason
            return np.nonzero(~bad)[0]

        for cam, masked in zip(self.cams, masks, strict=True):
            idx = np.nonzero(open_)[0]
            if len(idx) == 0:
                break
            uv = cam.project_from(cam.T_cam_ref, pts[idx].reshape(-1, 3)).reshape(
                len(idx), -1, 2)
            with np.errstate(invalid="ignore"):
                inside = (np.isfinite(uv).all(axis=(1, 2)) & (uv >= m).all(axis=(1, 2))
                          & (uv[..., 0] <= cam.width - 1 - m).all(axis=1)
                          & (uv[..., 1] <= cam.height - 1 - m).all(axis=1))
            keep = refuse(idx, ~inside, "out of view")
            idx, uv = idx[keep], uv[keep]
            hidden = np.zeros(uv.shape[:2], dtype=bool)
            if m_parts and len(idx):
                P = len(idx) * m_parts
                hid = cylinders_hide(cam, pa[idx].reshape(P, 3), pb[idx].reshape(P, 3),
                                     np.tile(radius, len(idx)),
                                     np.repeat(uv, m_parts, axis=0))
                hidden = hid.reshape(len(idx), m_parts, -1).any(axis=1)
            bad = 1.0 - hidden.mean(axis=1) < min_visible
            keep = refuse(idx, bad, "hidden by the grippers")
            idx, uv, hidden = idx[keep], uv[keep], hidden[keep]
            if incision and masked is not None and len(idx):
                # the features ignore the line's band (a dark line is not the wire)
                px = np.round(uv).astype(int)
                hidden = hidden | masked[px[..., 1], px[..., 0]]
                bad = 1.0 - hidden.mean(axis=1) < min_visible
                keep = refuse(idx, bad, "hidden by the incision line")
                idx, hidden = idx[keep], hidden[keep]
            if self.outline is not None and len(idx):
                back = self.backdrop(cam, pts[idx].reshape(-1, 3)).reshape(len(idx), -1)
                hidden = hidden | ~back
                bad = 1.0 - hidden.mean(axis=1) < min_visible
                refuse(idx, bad, "hidden or not against the tissue")
            open_ = np.array([w == "" for w in why])
        return why

    def why_not_each(self, T_ref_N: Sequence[np.ndarray],
                     tools: Sequence[Sequence[np.ndarray]], incision: bool = False,
                     strict: bool = False, first: int = 8) -> Callable[[int], str]:
        """:meth:`why_not` of pose ``k`` of ``T_ref_N`` (with its grippers ``tools[k]``),
        as a function of ``k``, for a planner that takes candidates in order and stops at
        the first few it can use: the answers are worked out in batches
        (:meth:`why_not_all`) of ``first`` poses from the one asked, doubling each time,
        so neither one pose at a time nor all of them."""
        known: dict[int, str] = {}
        size = [first]

        def why(k: int) -> str:
            if k not in known:
                ks = range(k, min(k + size[0], len(T_ref_N)))
                size[0] *= 2
                answers = self.why_not_all(np.stack([T_ref_N[i] for i in ks]),
                                           np.stack([np.stack(list(tools[i])) if
                                                     len(tools[i]) else np.zeros((0, 4, 4))
                                                     for i in ks]), incision, strict)
                known.update(zip(ks, answers, strict=True))
            return known[k]
        return why

    def tool_parts(self, T_ref_T: np.ndarray) -> tuple[ToolCylinder, ToolCylinder]:
        """The gripper at ``T_ref_T`` as the parts that may hide the needle: its jaws (a
        cylinder of ``jaw_radius`` over ``jaw_length`` behind the tip) and its shaft
        (``tool_radius``, on to ``tool_length`` behind the tip)."""
        a, b = self._part_ends(T_ref_T)
        return (ToolCylinder(a[0], b[0], self.s.jaw_radius),
                ToolCylinder(a[1], b[1], self.s.tool_radius))

    def _part_ends(self, T_ref_T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The ends of the jaws' and the shaft's cylinders (:meth:`tool_parts`) of the
        grippers at ``T_ref_T`` (..., 4, 4): ``a``, ``b`` (..., 2, 3), jaws first."""
        s = self.s
        tip, z = T_ref_T[..., :3, 3], T_ref_T[..., :3, 2]
        heel = tip - s.jaw_length * z
        return (np.stack([tip, heel], axis=-2),
                np.stack([heel, tip - s.tool_length * z], axis=-2))

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


#: The hand-off's candidate turns of the needle from its drive start orientation, and
#: their angles (rad).
_HANDOFF_TURNS = _turns()
_HANDOFF_ANGLES = tuple(rotation_angle(turn, np.eye(3)) for turn in _HANDOFF_TURNS)


def _turned_and_raised(T_N: np.ndarray, normal: np.ndarray, heights: Sequence[float]
                       ) -> Iterator[tuple[np.ndarray, float, float]]:
    """Needle poses near ``T_N`` for a hand-off or a look: turned about the needle's
    centre by each of :data:`_HANDOFF_TURNS` (the least first) and raised along
    ``normal`` by each of ``heights`` (m). Items: ``(T_ref_N, turn (rad), height)``."""
    for turn, angle in zip(_HANDOFF_TURNS, _HANDOFF_ANGLES, strict=True):
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
