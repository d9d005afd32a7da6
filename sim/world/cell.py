"""The simulated surgical cell: the arm, the wrist, the opener and the views they make.

The cell turns the robot's state (the arm's TCP pose and the wrist's joints) into what the
stereo camera and the endoscope see. Frames as in the navigation seed (section III.A) and
docs/conventions.md; ``T_a_b`` is the pose of frame b in frame a, metres:

- ``B`` robot base, ``tcp`` the arm's tool centre point (what the arm reports),
- ``C`` the stereo rig's reference frame (the left camera), fixed in ``B``,
- ``RM`` robot marker, rigid on the arm's last link,
- ``E0`` end-effector zero (the wrist with every joint at 0), rigid to ``tcp``,
- ``E`` the end-effector's distal body, moved from ``E0`` by the wrist's joints,
- ``EM`` end-effector marker, rigid to ``E``,
- ``OM`` opener marker, fixed in ``B`` (the patient's head is still),
- ``En`` the endoscope, fixed on the opener.

The stereo cameras see ``RM``, ``OM`` and ``EM`` except while ``EM``'s origin is inside the
mouth box (lips and teeth occlude it); the endoscope sees ``EM``. Nothing else of the
anatomy is modelled. Configuration comes from a cell file (``oralnav.config.cell``).
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from oralnav.control.geometry import as_transform, invert, make_transform, transform_points
from oralnav.control.vision.camera import Rig
from oralnav.control.vision.markers import MarkerField
from oralnav.sim.world.render import FieldTruth, RenderError, SceneRenderer
from oralnav.sim.world.scene import Scene

__all__ = ["CellConfig", "CellError", "CellGeometry", "SimCell", "wrist_transform"]

#: How far behind the stereo cameras (m) a hidden field is parked: the renderer culls what
#: lies behind a camera, so a parked field is neither drawn nor in the truth.
_PARK_DISTANCE = 100.0
#: The endoscope sees the effector only inside the mouth and at least this far (m) in
#: front of its lens: nearer, the view would be an out-of-focus blur, and rendering a field
#: that fills the image at 2x2 supersampling costs 0.25-1 s a frame.
ENDOSCOPE_NEAR = 0.010


class CellError(RenderError):
    """The cell is inconsistent or cannot capture as asked (unknown camera, bad state)."""


def _frozen(a: np.ndarray | Sequence, what: str, shape: tuple[int, ...]) -> np.ndarray:
    out = np.array(a, dtype=float)
    if out.shape != shape or not np.all(np.isfinite(out)):
        raise CellError(f"{what}: expected finite values of shape {shape}, got {out.shape}")
    out.flags.writeable = False
    return out


def _pose(T: np.ndarray | Sequence, what: str) -> np.ndarray:
    out = np.array(as_transform(T, what=what), dtype=float)
    out.flags.writeable = False
    return out


def wrist_transform(q: np.ndarray | Sequence[float], wrist_link: float) -> np.ndarray:
    """``T_E0_E`` (4x4, m): the distal body in the zero frame at joints ``q`` (rad).

    ``q = [roll, pitch, yaw, jaw]``. Roll turns about ``E0``'s z (the shaft), then pitch
    about x through an axis ``wrist_link`` m proximal (-z) of the yaw axis, then yaw about y
    through ``E0``'s origin (the jaw hinge); the jaw opens without moving the frame. So
    ``T_E0_E(0) = I``: the zero frame is the distal body with every joint at 0.
    """
    roll, pitch, yaw = (float(v) for v in np.asarray(q, dtype=float)[:3])
    to_pitch = make_transform(None, (0.0, 0.0, -wrist_link))
    return (make_transform(Rotation.from_euler("z", roll)) @ to_pitch
            @ make_transform(Rotation.from_euler("x", pitch)) @ invert(to_pitch)
            @ make_transform(Rotation.from_euler("y", yaw)))


@dataclass(frozen=True, eq=False)
class CellGeometry:
    """The cell's rigid geometry (all 4x4 poses in metres, read-only arrays).

    Attributes:
        T_B_C: the stereo reference camera in the robot base.
        T_tcp_RM: the robot marker on the arm's last link.
        T_tcp_E0: the end-effector zero frame (wrist at q = 0) on the TCP.
        wrist_link: distance (m) between the pitch and the yaw axes along the shaft.
        T_E_EM: the end-effector marker on the distal body.
        T_B_OM: the opener marker (fixed: the head is still).
        T_OM_En: the endoscope on the opener.
        mouth_min, mouth_max: (3,) corners of the mouth box in ``OM`` (m); an ``EM`` whose
            origin lies inside (bounds included) is hidden from the stereo cameras.
    """

    T_B_C: np.ndarray
    T_tcp_RM: np.ndarray
    T_tcp_E0: np.ndarray
    wrist_link: float
    T_E_EM: np.ndarray
    T_B_OM: np.ndarray
    T_OM_En: np.ndarray
    mouth_min: np.ndarray
    mouth_max: np.ndarray

    def __post_init__(self) -> None:
        for name in ("T_B_C", "T_tcp_RM", "T_tcp_E0", "T_E_EM", "T_B_OM", "T_OM_En"):
            object.__setattr__(self, name, _pose(getattr(self, name), name))
        for name in ("mouth_min", "mouth_max"):
            object.__setattr__(self, name, _frozen(getattr(self, name), name, (3,)))
        if not np.all(self.mouth_min < self.mouth_max):
            raise CellError(f"mouth box: min {self.mouth_min.tolist()} must be below max "
                            f"{self.mouth_max.tolist()} on every axis")
        link = float(self.wrist_link)
        if not 0.0 <= link <= 0.1:
            raise CellError(f"wrist_link must be 0..0.1 m, got {self.wrist_link!r}")
        object.__setattr__(self, "wrist_link", link)

    def T_E0_E(self, q: np.ndarray | Sequence[float]) -> np.ndarray:
        """Wrist forward kinematics at joints ``q`` (rad); see :func:`wrist_transform`."""
        return wrist_transform(q, self.wrist_link)

    @property
    def T_B_En(self) -> np.ndarray:
        """The endoscope in the base (fixed)."""
        return self.T_B_OM @ self.T_OM_En

    def in_mouth(self, p_B: np.ndarray | Sequence[float]) -> bool:
        """Whether the point ``p_B`` (3,, base frame, m) lies inside the mouth box."""
        p_OM = transform_points(invert(self.T_B_OM), np.asarray(p_B, dtype=float)[None])[0]
        return bool(np.all(p_OM >= self.mouth_min) and np.all(p_OM <= self.mouth_max))

    def poses(self, T_B_tcp: np.ndarray, q: np.ndarray | Sequence[float]) -> dict[str, np.ndarray]:
        """Every frame in the base at TCP pose ``T_B_tcp`` and wrist joints ``q``.

        Returns ``{"T_B_tcp", "T_B_C", "T_B_RM", "T_B_E0", "T_B_E", "T_B_EM", "T_B_OM",
        "T_B_En"}``, fresh 4x4 arrays.
        """
        T_B_tcp = np.array(T_B_tcp, dtype=float)
        T_B_E0 = T_B_tcp @ self.T_tcp_E0
        T_B_E = T_B_E0 @ self.T_E0_E(q)
        return {"T_B_tcp": T_B_tcp, "T_B_C": self.T_B_C.copy(),
                "T_B_RM": T_B_tcp @ self.T_tcp_RM, "T_B_E0": T_B_E0, "T_B_E": T_B_E,
                "T_B_EM": T_B_E @ self.T_E_EM, "T_B_OM": self.T_B_OM.copy(),
                "T_B_En": self.T_B_En}

    @classmethod
    def from_views(cls, *, T_B_C: np.ndarray, T_E_EM: np.ndarray, wrist_link: float,
                   mouth_min: Sequence[float], mouth_max: Sequence[float],
                   home_T_B_tcp: np.ndarray, intraoral_T_B_tcp: np.ndarray,
                   T_C_RM: np.ndarray, T_C_EM: np.ndarray, T_C_OM: np.ndarray,
                   T_En_EM: np.ndarray) -> CellGeometry:
        """Derive the rest of the geometry from chosen values and two reference views.

        Chosen: the camera ``T_B_C``, the marker on the distal body ``T_E_EM``, the wrist,
        the mouth box and the two TCP poses. Views: at ``home_T_B_tcp`` with q = 0 the
        stereo camera sees ``T_C_RM``, ``T_C_EM``, ``T_C_OM``; at ``intraoral_T_B_tcp``
        with q = 0 the endoscope sees ``T_En_EM``. Solving those gives ``T_tcp_RM``,
        ``T_tcp_E0``, ``T_B_OM`` and ``T_OM_En``.
        """
        T_tcp_B = invert(as_transform(home_T_B_tcp, what="home_T_B_tcp"))
        T_B_EM_home = T_B_C @ T_C_EM
        T_tcp_E0 = T_tcp_B @ T_B_EM_home @ invert(T_E_EM)   # E = E0 at q = 0
        T_B_OM = T_B_C @ T_C_OM
        T_B_EM_in = intraoral_T_B_tcp @ T_tcp_E0 @ T_E_EM
        return cls(T_B_C=T_B_C, T_tcp_RM=T_tcp_B @ T_B_C @ T_C_RM, T_tcp_E0=T_tcp_E0,
                   wrist_link=wrist_link, T_E_EM=T_E_EM, T_B_OM=T_B_OM,
                   T_OM_En=invert(T_B_OM) @ T_B_EM_in @ invert(T_En_EM),
                   mouth_min=np.asarray(mouth_min, dtype=float),
                   mouth_max=np.asarray(mouth_max, dtype=float))


@dataclass(frozen=True, eq=False)
class CellConfig:
    """A validated cell: geometry, the two scenes it renders with, poses and targets.

    Attributes:
        geometry: the rigid geometry.
        stereo_scene: rig (reference = ``C``), fields and imaging of the stereo cameras.
        endoscope_scene: rig (reference = ``En``), fields and imaging of the endoscope.
        home_T_B_tcp, intraoral_T_B_tcp: documented TCP poses (4x4, base, m).
        targets_OM: suture targets, name -> (3,) position in ``OM`` (m).
        robot, effector, opener: the placement names of ``RM``, ``EM`` and ``OM`` in the
            scenes (the endoscope scene holds only ``effector`` of them).
        source: the file it came from, if any.
    """

    geometry: CellGeometry
    stereo_scene: Scene
    endoscope_scene: Scene
    home_T_B_tcp: np.ndarray
    intraoral_T_B_tcp: np.ndarray
    targets_OM: Mapping[str, np.ndarray] = field(default_factory=dict)
    robot: str = "robot"
    effector: str = "effector"
    opener: str = "opener"
    source: str = ""

    def __post_init__(self) -> None:
        for name in ("home_T_B_tcp", "intraoral_T_B_tcp"):
            object.__setattr__(self, name, _pose(getattr(self, name), name))
        object.__setattr__(self, "targets_OM", {
            n: _frozen(p, f"target {n!r}", (3,)) for n, p in self.targets_OM.items()})
        stereo = {p.name: p for p in self.stereo_scene.placements}
        for role in ("robot", "effector", "opener"):
            if getattr(self, role) not in stereo:
                raise CellError(f"the stereo scene has no placement {getattr(self, role)!r} "
                                f"({role}); it has {sorted(stereo)}")
        endo = {p.name: p for p in self.endoscope_scene.placements}
        if self.effector not in endo:
            raise CellError(f"the endoscope scene has no placement {self.effector!r} "
                            f"(effector); it has {sorted(endo)}")
        a, b = stereo[self.effector].field, endo[self.effector].field
        if a.name != b.name or a.corners.shape != b.corners.shape \
                or not np.allclose(a.corners, b.corners, atol=1e-12):
            raise CellError(f"the effector field differs between the scenes ({a.name!r} in "
                            f"the stereo scene, {b.name!r} in the endoscope scene)")
        clash = set(self.stereo_scene.rig.names) & set(self.endoscope_scene.rig.names)
        if clash:
            raise CellError(f"camera names {sorted(clash)} are in both rigs; they must differ")


class SimCell:
    """The moving simulated cell; a frame source for the simulated cameras.

    Args:
        config: the cell (:class:`CellConfig`, from ``oralnav.config.cell``).
        arm_pose: returns the arm's current ``T_B_tcp`` (4x4, m).
        wrist_joints: returns the wrist's current joints ``[roll, pitch, yaw, jaw]`` (rad).
        clock: returns the current time (s); each capture is stamped with it.

    The renderers are built once and kept; ray maps and textures are built on first use
    (or by :meth:`prepare`). :meth:`capture` is blocking CPU work meant for a worker
    thread; calls are serialised by a lock, so any one thread at a time may call it.
    """

    def __init__(self, config: CellConfig, arm_pose: Callable[[], np.ndarray],
                 wrist_joints: Callable[[], np.ndarray], clock: Callable[[], float]) -> None:
        self.config = config
        self.geometry = config.geometry
        self._arm_pose = arm_pose
        self._wrist_joints = wrist_joints
        self._clock = clock
        self._stereo = SceneRenderer(config.stereo_scene)
        self._endoscope = SceneRenderer(config.endoscope_scene)
        self._stereo_names = tuple(config.stereo_scene.rig.names)
        self._endoscope_names = tuple(config.endoscope_scene.rig.names)
        self._parked = self._parking_pose(config.stereo_scene.rig)
        self._parked_endo = self._parking_pose(config.endoscope_scene.rig)
        self._lock = threading.Lock()
        self._frame = 0
        self._truth: dict[str, Any] | None = None

    @staticmethod
    def _parking_pose(rig: Rig) -> np.ndarray:
        """A pose far behind every stereo camera, where a hidden field is culled."""
        axes = np.array([rig[n].T_ref_cam[:3, 2] for n in rig.names])
        d = axes.sum(axis=0)
        T = make_transform(None, -_PARK_DISTANCE * d / np.linalg.norm(d))
        for n in rig.names:
            if (rig[n].T_cam_ref @ T)[2, 3] > -0.5 * _PARK_DISTANCE:
                raise CellError(f"stereo camera {n!r} looks away from the others; the cell "
                                "cannot hide the effector field from it")
        return T

    # -- what the cell holds -----------------------------------------------------------
    @property
    def camera_names(self) -> tuple[str, ...]:
        """The stereo cameras, then the endoscope."""
        return self._stereo_names + self._endoscope_names

    @property
    def stereo_rig(self) -> Rig:
        """The stereo rig; its reference frame is ``C``."""
        return self.config.stereo_scene.rig

    @property
    def endoscope_rig(self) -> Rig:
        """The endoscope rig; its reference frame is ``En``."""
        return self.config.endoscope_scene.rig

    @property
    def fields(self) -> tuple[MarkerField, ...]:
        """The marker fields of ``RM``, ``EM`` and ``OM`` (for building trackers)."""
        scene = self.config.stereo_scene
        return tuple(scene.placement(getattr(self.config, role)).field
                     for role in ("robot", "effector", "opener"))

    @property
    def frame(self) -> int:
        """Captures so far; the next capture uses this noise draw."""
        return self._frame

    def prepare(self) -> None:
        """Build every ray map and texture now (otherwise on the first capture)."""
        with self._lock:
            self._stereo.prepare()
            self._endoscope.prepare()

    def targets_B(self) -> dict[str, np.ndarray]:
        """Suture targets in the base (eq. 8 with the true opener pose), name -> (3,) m."""
        return {n: transform_points(self.geometry.T_B_OM, p[None])[0]
                for n, p in self.config.targets_OM.items()}

    # -- capture -----------------------------------------------------------------------
    def _state(self) -> tuple[np.ndarray, np.ndarray]:
        try:
            T_B_tcp = np.array(as_transform(self._arm_pose(), what="arm_pose()"), dtype=float)
        except ValueError as exc:  # a GeometryError naming what is wrong with the pose
            raise CellError(str(exc)) from None
        q = np.array(self._wrist_joints(), dtype=float)
        if q.shape != (4,) or not np.all(np.isfinite(q)):
            raise CellError(f"wrist_joints() must give 4 finite angles [roll, pitch, yaw, "
                            f"jaw] (rad), got shape {q.shape}")
        return T_B_tcp, q

    def capture(self, cameras: Sequence[str]) -> tuple[dict[str, np.ndarray], float]:
        """Render ``cameras`` (stereo and/or endoscope names) at one instant.

        The arm pose, the wrist joints and the clock are read once, so every camera shows
        the same state. Returns ``({name: (H, W) uint8 image}, time (s))``.

        Raises:
            CellError: an unknown camera or a malformed arm pose or joint vector.
        """
        names = tuple(cameras)
        unknown = [n for n in names if n not in self.camera_names]
        if unknown:
            raise CellError(f"unknown camera(s) {unknown}; the cell has "
                            f"{list(self.camera_names)}")
        with self._lock:
            t = float(self._clock())
            T_B_tcp, q = self._state()
            poses = self.geometry.poses(T_B_tcp, q)
            cfg = self.config
            T_C_B = invert(self.geometry.T_B_C)
            T_C = {"T_C_RM": T_C_B @ poses["T_B_RM"], "T_C_OM": T_C_B @ poses["T_B_OM"],
                   "T_C_EM": T_C_B @ poses["T_B_EM"]}
            T_En_EM = invert(poses["T_B_En"]) @ poses["T_B_EM"]
            hidden = self.geometry.in_mouth(poses["T_B_EM"][:3, 3])
            frame = self._frame
            images: dict[str, np.ndarray] = {}
            seen: dict[str, dict[str, FieldTruth]] = {}
            stereo = tuple(n for n in names if n in self._stereo_names)
            if stereo:
                placed = {cfg.robot: T_C["T_C_RM"], cfg.opener: T_C["T_C_OM"],
                          cfg.effector: self._parked if hidden else T_C["T_C_EM"]}
                out = self._stereo.render(poses=placed, frame=frame, cameras=stereo)
                images.update(out.images)
                seen.update(out.truth)
            endo = tuple(n for n in names if n in self._endoscope_names)
            if endo:
                seen_by_endo = hidden and T_En_EM[2, 3] >= ENDOSCOPE_NEAR
                out = self._endoscope.render(
                    poses={cfg.effector: T_En_EM if seen_by_endo else self._parked_endo},
                    frame=frame, cameras=endo)
                images.update(out.images)
                seen.update(out.truth)
            self._frame += 1
            if hidden:
                del T_C["T_C_EM"]
            truth = {"q": q, **poses, **T_C, "T_En_EM": T_En_EM}
            for a in truth.values():
                a.flags.writeable = False  # truth() hands out the same arrays each call
            self._truth = {"time": t, "frame": frame, **truth, "effector_in_mouth": hidden,
                           "cameras": seen}
        return {n: images[n] for n in names}, t

    def truth(self) -> dict[str, Any]:
        """Ground truth of the last capture (base frame ``B``, metres, radians).

        Keys: ``time`` (s), ``frame`` (noise draw), ``q`` (4,), ``T_B_tcp``, ``T_B_C``,
        ``T_B_RM``, ``T_B_E0``, ``T_B_E``, ``T_B_EM``, ``T_B_OM``, ``T_B_En``; the stereo
        placements ``T_C_RM``, ``T_C_OM`` and ``T_C_EM`` (absent while the effector is in
        the mouth); the endoscope's ``T_En_EM``; ``effector_in_mouth``; and ``cameras``:
        ``{camera: {placement: FieldTruth}}`` for each camera rendered, with the visible
        corners.

        Raises:
            CellError: nothing has been captured yet.
        """
        with self._lock:
            if self._truth is None:
                raise CellError("no capture yet: truth() describes the last capture")
            return dict(self._truth)
