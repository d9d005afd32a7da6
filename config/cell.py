"""The cell file: the simulated surgical cell's geometry, poses and targets.

See docs/formats.md (cell file). A cell names a stereo scene file and an endoscope scene
file (paths relative to the cell file), whose rigs, fields and imaging it reuses, and gives
the rigid geometry that moves their fields with the arm and the wrist. Lengths in metres.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Annotated

import numpy as np
from pydantic import Field, ValidationInfo, field_validator

from oralnav.control.geometry import as_transform
from oralnav.sim.world.cell import CellConfig, CellError, CellGeometry, SimCell

from .errors import ConfigError
from .loader import Float, Strict, build, read_toml, resolve_file, validate
from .scene import load_scene

Matrix = list[list[Float]]
Vec3 = tuple[Float, Float, Float]


def rigid_matrix(v: Matrix, info: ValidationInfo) -> Matrix:
    """Field validator: a 4x4 rigid transform (bottom row [0, 0, 0, 1], rotation
    orthonormal to 1e-6)."""
    if len(v) != 4 or any(len(r) != 4 for r in v):
        raise ValueError("must be a 4x4 matrix (4 rows of 4 numbers)")
    try:
        as_transform(v, what=str(info.field_name))
    except ValueError as exc:  # the key is already in the message's location
        raise ValueError(str(exc).removeprefix(f"{info.field_name}: ")) from None
    return v


class GeometryEntry(Strict):
    T_B_C: Matrix
    T_tcp_RM: Matrix
    T_tcp_E0: Matrix
    wrist_link: Annotated[Float, Field(ge=0, le=0.1)]
    T_E_EM: Matrix
    T_B_OM: Matrix
    T_OM_En: Matrix

    _check = field_validator("T_B_C", "T_tcp_RM", "T_tcp_E0", "T_E_EM", "T_B_OM",
                             "T_OM_En")(rigid_matrix)


class PosesEntry(Strict):
    home_T_B_tcp: Matrix
    intraoral_T_B_tcp: Matrix

    _check = field_validator("home_T_B_tcp", "intraoral_T_B_tcp")(rigid_matrix)


class MouthEntry(Strict):
    min: Vec3
    max: Vec3

    @field_validator("max")
    @classmethod
    def _max_above_min(cls, v: Vec3, info: ValidationInfo) -> Vec3:
        lo = info.data.get("min")
        if lo is not None:
            bad = [f"{a}: {h} <= {m}" for a, m, h in zip("xyz", lo, v, strict=True)
                   if not h > m]
            if bad:
                raise ValueError("max must exceed min on every axis (" + ", ".join(bad) + ")")
        return v


class TargetEntry(Strict):
    p_OM: Vec3


class PlacementsEntry(Strict):
    robot: str = "robot"
    effector: str = "effector"
    opener: str = "opener"


class CellFile(Strict):
    stereo_scene: str
    endoscope_scene: str
    placements: PlacementsEntry = PlacementsEntry()
    geometry: GeometryEntry
    poses: PosesEntry
    mouth: MouthEntry
    targets: dict[str, TargetEntry] = Field(default_factory=dict)


def load_cell_config(path: str | Path) -> CellConfig:
    """Read a cell file and the two scene files it names; all validated.

    Raises ``ConfigError`` naming the file and key (a scene file's own errors name that
    file).
    """
    path = Path(path)
    doc = validate(CellFile, read_toml(path), path)
    stereo = load_scene(resolve_file(path, "stereo_scene", doc.stereo_scene))
    endoscope = load_scene(resolve_file(path, "endoscope_scene", doc.endoscope_scene))
    g = doc.geometry
    geometry = build(path, "geometry", lambda: CellGeometry(
        T_B_C=np.array(g.T_B_C), T_tcp_RM=np.array(g.T_tcp_RM),
        T_tcp_E0=np.array(g.T_tcp_E0), wrist_link=g.wrist_link, T_E_EM=np.array(g.T_E_EM),
        T_B_OM=np.array(g.T_B_OM), T_OM_En=np.array(g.T_OM_En),
        mouth_min=np.array(doc.mouth.min), mouth_max=np.array(doc.mouth.max)))
    targets = {}
    for name, t in doc.targets.items():
        p = np.array(t.p_OM)
        if not (np.all(p >= geometry.mouth_min) and np.all(p <= geometry.mouth_max)):
            raise ConfigError(path, f"targets.{name}.p_OM",
                              f"{list(t.p_OM)} is outside the mouth box [mouth] "
                              f"min {list(doc.mouth.min)} .. max {list(doc.mouth.max)}")
        targets[name] = p
    _check_placements(path, doc, stereo.placements, endoscope.placements)
    try:
        return CellConfig(geometry=geometry, stereo_scene=stereo, endoscope_scene=endoscope,
                          home_T_B_tcp=np.array(doc.poses.home_T_B_tcp),
                          intraoral_T_B_tcp=np.array(doc.poses.intraoral_T_B_tcp),
                          targets_OM=targets, robot=doc.placements.robot,
                          effector=doc.placements.effector, opener=doc.placements.opener,
                          source=str(path))
    except CellError as exc:  # the fields or camera names of the two scenes disagree
        raise ConfigError(path, "endoscope_scene", str(exc)) from None


def _check_placements(path: Path, doc: CellFile, stereo: tuple, endoscope: tuple) -> None:
    """Each named placement must be in its scene; reported on the key that names it."""
    names = {p.name for p in stereo}
    for role in ("robot", "effector", "opener"):
        name = getattr(doc.placements, role)
        if name not in names:
            raise ConfigError(path, f"placements.{role}",
                              f"the stereo scene {doc.stereo_scene!r} has no placement "
                              f"{name!r}; it has {sorted(names)}")
    names = {p.name for p in endoscope}
    if doc.placements.effector not in names:
        raise ConfigError(path, "placements.effector",
                          f"the endoscope scene {doc.endoscope_scene!r} has no placement "
                          f"{doc.placements.effector!r}; it has {sorted(names)}")


def load_sim_cell(path: str | Path, arm_pose: Callable[[], np.ndarray],
                  wrist_joints: Callable[[], np.ndarray],
                  clock: Callable[[], float]) -> SimCell:
    """Build a :class:`SimCell` from a cell file (see :class:`SimCell` for the callables)."""
    return SimCell(load_cell_config(path), arm_pose, wrist_joints, clock)
