"""The navigation chain calibrated in simulation, and its target registration error.

The simulated cell (``sim/world/cell.py``) knows every true transform; :class:`ChainSimulator`
produces the samples each calibration of the navigation seed's section III.B needs, as the
tracker would measure them at a given marker-corner noise (``sim/world/measure.py``), with the
arm moving itself through the poses a real calibration would use. :func:`calibrate_chain`
runs the project's calibrations on them in the paper's order (hand-eye, endoscope to
opener, pointer pivot, end-effector zero, end-effector marker); :func:`chain_tre` then
measures eq. 21's TRE at the cell's targets. Lengths in metres unless a name says mm.

Two objects the cell file does not hold are defined here, as a real cell has them:

- a pointer (``SI``, the seed's "surgical instrument" of reference [28]): a 30 x 20 mm
  ChArUco plate on a shaft whose tip lies 60 mm from the plate's centre;
- a calibration board (``CB``, Fig. 3): a 21 x 15 mm ChArUco plate the endoscope and the
  stereo camera see together.

TRE model. The seed's eq. 21 compares "the i-th target point registered by the surgical
instrument" with "the corresponding point detected by the navigation system" after the
robot reached it; read literally, a visual servo that converged makes the two equal. What
the experiment measures is how far the end-effector really is from the real target, so
here each target is registered with the pointer (tracking noise plus the pivot
calibration's error), the servo is taken as converged (the navigation's estimate of the
end-effector, eq. 6 with the calibrated chain and one fresh endoscope measurement, equals
the registered target), and the TRE is the RMS distance between the true end-effector
origin and the true target over the targets.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from oralnav.control.calibration.chain import (
    AveragedPose,
    calibrate_effector_marker,
    calibrate_effector_zero,
    calibrate_endoscope_opener,
)
from oralnav.control.calibration.handeye import (
    HandEyeResult,
    calibrate_hand_eye,
    plan_hand_eye_poses,
)
from oralnav.control.calibration.pivot import PivotResult, pivot_calibration
from oralnav.control.geometry import invert, make_transform, transform_points
from oralnav.control.navigation.chains import extraoral_T_B_E0
from oralnav.control.vision.markers import MarkerField, PlaneSurface
from oralnav.sim.errors import SimError
from oralnav.sim.world.cell import CellConfig
from oralnav.sim.world.measure import measure_pose

__all__ = ["BOARD", "POINTER", "POINTER_TIP", "ChainCalibration", "ChainSimulator",
           "MeasurementLost", "calibrate_chain", "chain_tre"]

#: The pointer's plate; its frame is the ChArUco board frame (origin at a plate corner).
POINTER = MarkerField(name="pointer", dictionary="DICT_4X4_1000", squares=(6, 4),
                      square=0.005, marker=0.0037, first_id=300, surface=PlaneSurface())
#: The pointer's tip in its plate frame: 60 mm below the plate's centre along +y (the
#: shaft) and 5 mm behind the printed face (+z). Short, because the stereo camera stands
#: about 0.2 m from the opener and sees only about 170 x 110 mm there.
POINTER_TIP = np.array([0.015, 0.070, 0.005])
#: The endoscope-to-opener calibration board.
BOARD = MarkerField(name="board", dictionary="DICT_4X4_1000", squares=(7, 5), square=0.003,
                    marker=0.0022, first_id=400, surface=PlaneSurface())


class MeasurementLost(SimError, RuntimeError):
    """A planned sample could not be measured (the field left the view) too many times."""


def _rot(rng: np.random.Generator, deg: float) -> np.ndarray:
    """A random rotation of up to ``deg`` degrees about a random axis."""
    axis = rng.normal(size=3)
    return Rotation.from_rotvec(axis / np.linalg.norm(axis)
                                * np.radians(rng.uniform(0, deg))).as_matrix()


@dataclass
class ChainSimulator:
    """Samples of every chain calibration from the simulated cell at one corner noise.

    Args:
        config: the cell (true geometry, the stereo rig ``C`` and the endoscope rig ``En``).
        sigma_px: marker-corner noise (px, per axis) of every measurement.
        rng: the noise and pose draws.
        method: the pose estimator (``"nvgba"``, ``"ba"``...).
    """

    config: CellConfig
    sigma_px: float
    rng: np.random.Generator
    method: str = "nvgba"
    fields: dict[str, MarkerField] = field(init=False)

    def __post_init__(self) -> None:
        scene = self.config.stereo_scene
        self.fields = {role: scene.placement(getattr(self.config, role)).field
                       for role in ("robot", "effector", "opener")}
        self.g = self.config.geometry
        self.stereo = scene.rig
        self.endoscope = self.config.endoscope_scene.rig

    # -- measurement -----------------------------------------------------------------
    def _measure(self, fld: MarkerField, T_ref_field: np.ndarray, endoscope: bool = False
                 ) -> np.ndarray | None:
        rig = self.endoscope if endoscope else self.stereo
        est = measure_pose(fld, T_ref_field, rig, self.sigma_px, self.rng, method=self.method)
        return None if est is None else est.T_ref_field

    def _C(self, T_B_x: np.ndarray) -> np.ndarray:
        """A base-frame pose in the stereo camera frame (truth)."""
        return invert(self.g.T_B_C) @ T_B_x

    def _draw(self, n: int, make: Callable[[], tuple | None], what: str) -> list[tuple]:
        """``n`` samples from ``make`` (None: that draw was not measurable)."""
        out: list[tuple] = []
        tries = 0
        while len(out) < n:
            tries += 1
            if tries > 5 * n + 20:
                raise MeasurementLost(f"{what}: only {len(out)} of {n} samples measurable in "
                                      f"{tries - 1} draws; check the poses and the view")
            try:
                s = make()
            except StopIteration:  # the planned poses ran out
                raise MeasurementLost(f"{what}: only {len(out)} of {n} samples measurable "
                                      "over the planned poses; check the poses and the "
                                      "view") from None
            if s is not None:
                out.append(s)
        return out

    def _arm_poses(self, n: int, seed: int) -> np.ndarray:
        """Hand-eye style TCP poses around home, turning about the robot marker's nominal
        place on the TCP (a CAD figure on a real arm) so the marker stays in view."""
        return plan_hand_eye_poses(self.config.home_T_B_tcp, n, seed=seed,
                                   pivot_tcp=self.g.T_tcp_RM[:3, 3])

    # -- samples per calibration -----------------------------------------------------
    def hand_eye_samples(self, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """Robot at ``n`` planned poses around home: ``(T_B_tcp, measured T_C_RM)``."""
        it = iter(self._arm_poses(3 * n + 10, seed))

        def one() -> tuple | None:
            T_B_tcp = next(it)
            m = self._measure(self.fields["robot"], self._C(T_B_tcp @ self.g.T_tcp_RM))
            return None if m is None else (T_B_tcp, m)

        s = self._draw(n, one, "hand-eye")
        return np.stack([a for a, _ in s]), np.stack([b for _, b in s])

    def calibration_station(self) -> np.ndarray:
        """``T_C_OM`` of the opener (with its endoscope) on the calibration stand.

        In the mouth the endoscope's view lies below the stereo camera's image, so the
        assembly is calibrated off the patient (Fig. 3), moved across the camera's view so
        that the midpoint between the opener marker and a board 45 mm before the endoscope
        lies on the camera's optical axis; ``T_OM_En`` is a property of the assembly.
        """
        T_C_OM = self._C(self.g.T_B_OM)
        board = (T_C_OM @ self.g.T_OM_En)[:3, 3] + 0.045 * (T_C_OM @ self.g.T_OM_En)[:3, 2]
        mid = 0.5 * (T_C_OM[:3, 3] + board)
        return make_transform(None, [-mid[0], -mid[1], 0.0]) @ T_C_OM

    def endoscope_opener_samples(self, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Board in front of the endoscope, moved between samples, the opener on the
        calibration stand: ``(T_C_OM, T_C_CB, T_En_CB)`` measured at the same instants."""
        T_C_OM = self.calibration_station()
        T_C_En = T_C_OM @ self.g.T_OM_En

        def one() -> tuple | None:
            # the board's axes near the endoscope's, so its printed face (normal -z) faces
            # the lens, and the stereo camera behind the endoscope sees that face too
            c = BOARD.sheet_size
            centre = make_transform(None, [-c[0] / 2, -c[1] / 2, 0.0])
            T_En_CB = (make_transform(_rot(self.rng, 20.0),
                                      [*self.rng.uniform(-0.006, 0.006, 2),
                                       self.rng.uniform(0.035, 0.055)]) @ centre)
            om = self._measure(self.fields["opener"], T_C_OM)
            cb = self._measure(BOARD, T_C_En @ T_En_CB)
            en = self._measure(BOARD, T_En_CB, endoscope=True)
            return None if om is None or cb is None or en is None else (om, cb, en)

        s = self._draw(n, one, "endoscope to opener")
        return tuple(np.stack([x[k] for x in s]) for k in range(3))  # type: ignore[return-value]

    def _pointer_pose(self, p_B_tip: np.ndarray, tilt_deg: float) -> np.ndarray:
        """``T_B_SI`` with the tip at ``p_B_tip`` and the plate facing the stereo camera,
        tilted at random by up to ``tilt_deg``."""
        # plate facing the camera: plate z along the camera's optical axis, y (the shaft,
        # toward the tip) along the camera's +y (image down)
        R_B_plate = self.g.T_B_C[:3, :3] @ _rot(self.rng, tilt_deg)
        return make_transform(R_B_plate, p_B_tip - R_B_plate @ POINTER_TIP)

    def pivot_samples(self, n: int, spread_deg: float = 25.0) -> tuple[np.ndarray, np.ndarray]:
        """Pointer pivoting in a divot at the opener's depth, placed so the upright
        pointer's plate is at the image centre: ``(measured T_C_SI, divot p_C)``."""
        depth = self._C(self.g.T_B_OM)[2, 3]
        p_C = np.array([0.0, POINTER_TIP[1] - 0.5 * POINTER.sheet_size[1], depth])
        p_B = transform_points(self.g.T_B_C, p_C[None])[0]

        def one() -> tuple | None:
            m = self._measure(POINTER, self._C(self._pointer_pose(p_B, spread_deg)))
            return None if m is None else (m,)

        s = self._draw(n, one, "pivot")
        return np.stack([x[0] for x in s]), p_C

    def pointer_touching(self, p_B: np.ndarray) -> np.ndarray | None:
        """The pointer pose ``T_C_SI`` the tracker reports while its tip touches ``p_B``."""
        return self._measure(POINTER, self._C(self._pointer_pose(p_B, 10.0)))

    def effector_zero_samples(self, n: int, seed: int = 1
                              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Arm at ``n`` poses near home, wrist at zero, the pointer's tip on the
        end-effector origin: ``(T_C_RM, T_C_SI, T_B_J6)``."""
        poses = iter(self._arm_poses(3 * n + 10, seed))

        def one() -> tuple | None:
            T_B_tcp = next(poses)
            rm = self._measure(self.fields["robot"], self._C(T_B_tcp @ self.g.T_tcp_RM))
            si = self.pointer_touching((T_B_tcp @ self.g.T_tcp_E0)[:3, 3])
            return None if rm is None or si is None else (rm, si, T_B_tcp)

        s = self._draw(n, one, "end-effector zero")
        return tuple(np.stack([x[k] for x in s]) for k in range(3))  # type: ignore[return-value]

    def effector_marker_samples(self, n: int) -> tuple[np.ndarray, ...]:
        """Wrist at zero inside the mouth, arm near the intra-oral pose:
        ``(T_C_OM, T_En_EM, T_C_RM)``."""
        base = self.config.intraoral_T_B_tcp

        def one() -> tuple | None:
            T_B_tcp = base @ make_transform(_rot(self.rng, 4.0),
                                            self.rng.uniform(-0.002, 0.002, 3))
            T_B_E0 = T_B_tcp @ self.g.T_tcp_E0
            om = self._measure(self.fields["opener"], self._C(self.g.T_B_OM))
            em = self._measure(self.fields["effector"],
                               invert(self.g.T_B_En) @ T_B_E0 @ self.g.T_E_EM, endoscope=True)
            rm = self._measure(self.fields["robot"], self._C(T_B_tcp @ self.g.T_tcp_RM))
            return None if om is None or em is None or rm is None else (om, em, rm)

        s = self._draw(n, one, "end-effector marker")
        return tuple(np.stack([x[k] for x in s]) for k in range(3))


@dataclass(frozen=True)
class ChainCalibration:
    """Every calibration of the chain, as :func:`calibrate_chain` measured them."""

    hand_eye: HandEyeResult
    endoscope_opener: AveragedPose
    pivot: PivotResult
    effector_zero: AveragedPose
    effector_marker: AveragedPose

    @property
    def T_B_C(self) -> np.ndarray:
        return self.hand_eye.T_B_C

    @property
    def T_OM_En(self) -> np.ndarray:
        return self.endoscope_opener.T

    @property
    def T_RM_E0(self) -> np.ndarray:
        return self.effector_zero.T

    @property
    def T_EM_E(self) -> np.ndarray:
        return self.effector_marker.T


def calibrate_chain(sim: ChainSimulator, n: int, *, pivot_poses: int | None = None,
                    progress: Callable[[str], None] | None = None) -> ChainCalibration:
    """Calibrate the whole chain from ``n`` samples per calibration (pivot: ``pivot_poses``,
    default ``10 n``, as a pivot recording holds many more poses than the others)."""
    say = progress or (lambda _msg: None)
    T_B_tcp, T_C_RM = sim.hand_eye_samples(max(n, 3))
    he = calibrate_hand_eye(T_B_tcp, T_C_RM)
    say(f"hand-eye from {len(T_B_tcp)} poses")
    eo = calibrate_endoscope_opener(*sim.endoscope_opener_samples(n))
    say(f"endoscope to opener from {n} views")
    T_C_SI, _ = sim.pivot_samples(pivot_poses or 10 * n)
    pv = pivot_calibration(T_C_SI, "algebraic")
    say(f"pivot from {len(T_C_SI)} poses")
    rm, T_C_SI, T_B_J6 = sim.effector_zero_samples(n)
    p_C_SI = T_C_SI[:, :3, :3] @ pv.tip_offset + T_C_SI[:, :3, 3]
    ez = calibrate_effector_zero(rm, p_C_SI, he.T_B_C, T_B_J6)
    say(f"end-effector zero from {n} touches")
    om, em, rm2 = sim.effector_marker_samples(n)
    T_B_E0 = np.stack([extraoral_T_B_E0(he.T_B_C, r, ez.T[:3, :3], ez.T[:3, 3]) for r in rm2])
    em_cal = calibrate_effector_marker(he.T_B_C, om, eo.T, em, T_B_E0)
    say(f"end-effector marker from {n} samples")
    return ChainCalibration(he, eo, pv, ez, em_cal)


def chain_tre(sim: ChainSimulator, cal: ChainCalibration) -> tuple[float, np.ndarray]:
    """Eq. 21's TRE (m) at the cell's targets, and each target's error vector (N, 3), m.

    Per target: the pointer registers it in ``OM`` (eq. 8's preoperative half); the
    end-effector, at the intra-oral orientation, is where the navigation (eq. 6 relative
    to the opener, with the calibrated ``T_OM_En`` and ``T_EM_E`` and one endoscope
    measurement) places it on the registered target.
    """
    g = sim.g
    R_B_E = (sim.config.intraoral_T_B_tcp @ g.T_tcp_E0)[:3, :3]
    errors = []
    for name, p_OM in sim.config.targets_OM.items():
        p_B = transform_points(g.T_B_OM, p_OM[None])[0]
        # registration: the pointer on the target and the opener, seen together
        for _ in range(20):
            T_C_SI = sim.pointer_touching(p_B)
            T_C_OM = sim._measure(sim.fields["opener"], sim._C(g.T_B_OM))
            if T_C_SI is not None and T_C_OM is not None:
                break
        else:
            raise MeasurementLost(f"target {name!r}: pointer or opener not measurable")
        p_OM_reg = transform_points(invert(T_C_OM) @ T_C_SI, cal.pivot.tip_offset[None])[0]
        # navigation error at the target: estimate minus truth of the end-effector origin
        T_B_E = make_transform(R_B_E, p_B)
        T_En_EM_true = invert(g.T_B_En) @ T_B_E @ g.T_E_EM
        for _ in range(20):
            T_En_EM = sim._measure(sim.fields["effector"], T_En_EM_true, endoscope=True)
            if T_En_EM is not None:
                break
        else:
            raise MeasurementLost(f"target {name!r}: effector marker not measurable")
        p_OM_est = (cal.T_OM_En @ T_En_EM @ cal.T_EM_E)[:3, 3]
        p_OM_true = (invert(g.T_B_OM) @ T_B_E)[:3, 3]
        # the servo moves the true end-effector by (registered - estimated)
        final = p_OM_true + (p_OM_reg - p_OM_est)
        errors.append(final - p_OM)
    e = np.array(errors)
    return float(np.sqrt(np.mean(np.sum(e ** 2, axis=1)))), e
