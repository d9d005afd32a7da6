"""A guided-insertion cell for the daemon tests: the cylinder planning case placed in the
robot base through a camera, an opener and a registration, and an operator's hand that the
control process's simulated arm feels (``SimArm(force_source=...)``).

Frames (docs/control_loop.md, "Guided insertion"): ``T_B_F = T_B_C @ T_C_OM @ T_OM_F``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from oralnav.control.guidance.virtual_fixture import VirtualFixture
from oralnav.sim.world.hand import ScriptedHand

#: The paper's cylinder case (a 1.9 MB plan with its rod check; about 2 s to plan).
CYLINDER = Path(str(resources.files("oralnav.config").joinpath(
    "examples/cylinder_case.toml")))

#: A small cylinder case for the daemon tests: 20 mm radius, 6 slices, a 2 mm rod, the
#: hole on the wall at z = 20 mm. It plans in about 0.2 s (most of it the certified rod
#: check) to d_T = 25 mm, theta_T = 0: the rod runs up the cylinder's axis region, out of
#: the front at z = 50 mm.
SMALL_SCENE = """\
[model]
kind = "cylinder"
radius_mm = 20.0
z_range_mm = [0.0, 50.0]
slices = 6
points = 15

[hole]
position_mm = [0.0, -20.0, 20.0]
axis = [0.0, 1.0, 0.0]

[tool]
rod_radius_mm = 2.0
implant_length_mm = 10.0

[search]
d_T_range_mm = [0.0, 40.0]
"""


def small_scene(folder: Path) -> Path:
    """Write :data:`SMALL_SCENE` into ``folder``; its path."""
    path = Path(folder) / "small_cylinder.toml"
    path.write_text(SMALL_SCENE)
    return path


def rigid(rotvec: tuple[float, float, float], t: tuple[float, float, float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


#: The camera in the base, the model on the opener (the registration), the model in the
#: base (0.45 m out, in reach; its z axis, out of the mouth, tilted toward the robot).
T_B_C = rigid((2.2, 0.3, -0.2), (0.3, -0.7, 0.9))
T_OM_F = rigid((0.15, -0.1, 0.05), (0.01, -0.03, -0.09))
T_B_F = rigid((0.0, -0.6, 0.5), (0.45, 0.05, 0.12))
#: What the stereo camera reports for the opener (the test plays the tracker).
T_C_OM = np.linalg.inv(T_B_C) @ T_B_F @ np.linalg.inv(T_OM_F)


def start_pose(T_F_tool: np.ndarray, fx: VirtualFixture, out: float = 0.02) -> np.ndarray:
    """``T_B_tcp`` on the fixture's axis, ``out`` m beyond the cylinder's mouth, with the
    planned tool orientation: where the operator has brought the instrument."""
    T_F = np.array(T_F_tool, dtype=float)
    T_F[:3, 3] = fx.target + (fx.cylinder_length + out) * fx.direction
    return T_B_F @ T_F


@dataclass
class BaseFrameHand:
    """The scripted hand of :mod:`oralnav.sim.world.hand` as a sim-arm ``force_source``: its
    force (frame ``F``) at the measured TCP, turned into the base frame. Its script
    starts at the first call. Picklable, so it reaches the control process."""

    hand: ScriptedHand
    T_B_F: np.ndarray
    _t0: float | None = field(default=None, repr=False)

    def __call__(self, t: float, T_B_tcp: np.ndarray) -> np.ndarray:
        if self._t0 is None:
            self._t0 = t
        R, o = self.T_B_F[:3, :3], self.T_B_F[:3, 3]
        p_F = R.T @ (T_B_tcp[:3, 3] - o)
        return R @ self.hand.force(max(t - self._t0, 0.0), p_F)
