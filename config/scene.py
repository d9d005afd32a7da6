"""The scene file: what the simulator renders (see docs/formats.md, docs/simulator.md).

A scene names a rig file and a fields file (paths relative to the scene file), places
fields in the rig's reference frame, adds occluders and the needle-driving objects
(needles, tissue pads, grippers) and sets the imaging model. Optional ``[arms.<gripper>]``
sections give the reach of the arm carrying each gripper, for the needle-driving cell
(:func:`load_needle_cell`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Annotated, ClassVar

import numpy as np
from pydantic import Field, field_validator, model_validator

from oralnav.control.errors import NeedleError
from oralnav.control.geometry import as_transform, transform_from_euler
from oralnav.control.needle.model import Needle
from oralnav.sim.world.needle_cell import ArmReach, CellError, NeedleCell
from oralnav.sim.world.scene import (
    Blot,
    Gripper,
    Imaging,
    NeedleObject,
    Placement,
    Rod,
    Scene,
    TissuePad,
)

from .errors import ConfigError
from .fields import load_fields
from .loader import Float, Int, Strict, build, read_toml, resolve_file, validate
from .rig import load_rig

Vec3 = tuple[Float, Float, Float]
Level = Annotated[Float, Field(ge=0, le=255)]


class ImagingEntry(Strict):
    supersample: Annotated[Int, Field(ge=1, le=4)] = 2
    background: Level = 40.0
    white: Level = 220.0
    black: Level = 20.0
    body: Level = 150.0
    illumination_gradient: tuple[Annotated[Float, Field(ge=-1.5, le=1.5)],
                                 Annotated[Float, Field(ge=-1.5, le=1.5)]] = (0.0, 0.0)
    blur_sigma_px: Annotated[Float, Field(ge=0, le=20)] = 0.0
    read_noise_dn: Annotated[Float, Field(ge=0, le=50)] = 0.0
    shot_noise_gain: Annotated[Float, Field(ge=0, le=10)] = 0.0
    motion_samples: Annotated[Int, Field(ge=1, le=64)] = 1
    exposure: Annotated[Float, Field(gt=0, le=1.0)] = 0.01


class PlacementEntry(Strict):
    field: str
    T_ref_field: list[list[Float]] | None = None
    translation: Vec3 | None = None
    euler_xyz_deg: Vec3 | None = None
    velocity: Vec3 = (0.0, 0.0, 0.0)
    angular_velocity_deg_s: Vec3 = (0.0, 0.0, 0.0)

    @field_validator("T_ref_field")
    @classmethod
    def _t_rigid(cls, v: list[list[float]] | None) -> list[list[float]] | None:
        if v is not None:
            try:
                as_transform(v, what="T_ref_field")
            except ValueError as exc:  # the key is already in the message's location
                raise ValueError(str(exc).removeprefix("T_ref_field: ")) from None
        return v

    @model_validator(mode="after")
    def _one_pose(self) -> PlacementEntry:
        if (self.T_ref_field is None) == (self.translation is None):
            raise ValueError("give the pose either as T_ref_field (4x4) or as translation "
                             "(+ euler_xyz_deg), not both or neither")
        if self.euler_xyz_deg is not None and self.translation is None:
            raise ValueError("euler_xyz_deg needs translation")
        return self


class RodEntry(Strict):
    p0: Vec3
    p1: Vec3
    radius: Annotated[Float, Field(gt=0, le=0.1)]
    level: Level = 90.0


class BlotEntry(Strict):
    placement: str
    center: tuple[Float, Float]
    radius: Annotated[Float, Field(gt=0, le=0.1)]
    level: Level = 60.0


def _rigid(v: list[list[float]] | None, key: str) -> list[list[float]] | None:
    if v is not None:
        try:
            as_transform(v, what=key)
        except ValueError as exc:  # the key is already in the message's location
            raise ValueError(str(exc).removeprefix(f"{key}: ")) from None
    return v


class _Posed(Strict):
    """A pose given either as a 4x4 ``T_ref_*`` (the key named by ``POSE``) or as
    ``translation`` (m) + ``euler_xyz_deg`` (extrinsic x-y-z, deg), reference frame."""

    POSE: ClassVar[str] = ""
    translation: Vec3 | None = None
    euler_xyz_deg: Vec3 | None = None

    @model_validator(mode="after")
    def _one_pose(self) -> _Posed:
        if (getattr(self, self.POSE) is None) == (self.translation is None):
            raise ValueError(f"give the pose either as {self.POSE} (4x4) or as translation "
                             "(+ euler_xyz_deg), not both or neither")
        if self.euler_xyz_deg is not None and self.translation is None:
            raise ValueError("euler_xyz_deg needs translation")
        return self

    def pose(self, path: Path, key: str) -> np.ndarray:
        T = getattr(self, self.POSE)
        if T is not None:
            return build(path, f"{key}.{self.POSE}", lambda: as_transform(T, what=self.POSE))
        return transform_from_euler(self.translation, self.euler_xyz_deg or (0.0, 0.0, 0.0))


class NeedleEntry(_Posed):
    """A suture needle (frame N of oralnav.control.needle.model); sizes in mm, the arc in deg."""

    POSE: ClassVar[str] = "T_ref_needle"
    T_ref_needle: list[list[Float]] | None = None
    radius_mm: Annotated[Float, Field(gt=0, le=100)] = 13.0
    wire_diameter_mm: Annotated[Float, Field(gt=0, le=5)] = 1.0
    arc_deg: Annotated[Float, Field(gt=0, le=360)] = 180.0
    level: Level = 70.0
    specular: Level = 180.0
    shininess: Annotated[Float, Field(ge=1, le=1000)] = 20.0
    thread_length_mm: Annotated[Float, Field(ge=0, le=500)] = 0.0
    thread_diameter_mm: Annotated[Float, Field(gt=0, le=2)] = 0.4
    thread_level: Level = 45.0

    @field_validator("T_ref_needle")
    @classmethod
    def _t_rigid(cls, v: list[list[float]] | None) -> list[list[float]] | None:
        return _rigid(v, "T_ref_needle")


class PadEntry(_Posed):
    """A tissue pad: its surface the pad frame's z = 0 plane, +z out of the tissue."""

    POSE: ClassVar[str] = "T_ref_pad"
    T_ref_pad: list[list[Float]] | None = None
    size: tuple[Annotated[Float, Field(gt=0, le=1)], Annotated[Float, Field(gt=0, le=1)]]
    level: Level = 170.0
    incision: tuple[tuple[Float, Float], tuple[Float, Float]]
    incision_width: Annotated[Float, Field(gt=0, le=0.05)] = 0.0008
    incision_level: Level = 35.0

    @field_validator("T_ref_pad")
    @classmethod
    def _t_rigid(cls, v: list[list[float]] | None) -> list[list[float]] | None:
        return _rigid(v, "T_ref_pad")


class GripperEntry(_Posed):
    """A gripper (frame T at the tip, y across the jaws, z along the gripper)."""

    POSE: ClassVar[str] = "T_ref_tool"
    T_ref_tool: list[list[Float]] | None = None
    jaw_length: Annotated[Float, Field(gt=0, le=0.1)] = 0.010
    jaw_width: Annotated[Float, Field(gt=0, le=0.05)] = 0.0025
    jaw_thickness: Annotated[Float, Field(gt=0, le=0.05)] = 0.0012
    opening: Annotated[Float, Field(ge=0, le=0.05)] = 0.001
    shaft_radius: Annotated[Float, Field(gt=0, le=0.05)] = 0.003
    shaft_length: Annotated[Float, Field(gt=0, le=1.0)] = 0.05
    level: Level = 110.0

    @field_validator("T_ref_tool")
    @classmethod
    def _t_rigid(cls, v: list[list[float]] | None) -> list[list[float]] | None:
        return _rigid(v, "T_ref_tool")


class ArmEntry(Strict):
    """The reach of the RCM arm that carries the gripper of the same name (m, degrees)."""

    rcm: Vec3
    min_insertion: Annotated[Float, Field(ge=0, le=2)] = 0.03
    max_insertion: Annotated[Float, Field(gt=0, le=2)] = 0.20
    # the wrist of the da Vinci Large Needle Driver by default (oralnav.sim.world.needle_cell)
    max_wrist_pitch_deg: Annotated[Float, Field(gt=0, le=180)] = 80.0
    max_wrist_yaw_deg: Annotated[Float, Field(gt=0, le=180)] = 80.0
    pitch_to_yaw: Annotated[Float, Field(ge=0, le=0.1)] = 0.0091
    yaw_to_tip: Annotated[Float, Field(ge=0, le=0.1)] = 0.0095

    @model_validator(mode="after")
    def _range(self) -> ArmEntry:
        if self.min_insertion >= self.max_insertion:
            raise ValueError(f"min_insertion ({self.min_insertion}) must be below "
                             f"max_insertion ({self.max_insertion})")
        return self

    def reach(self) -> ArmReach:
        return ArmReach(rcm=np.array(self.rcm, dtype=float), min_insertion=self.min_insertion,
                        max_insertion=self.max_insertion,
                        max_wrist_pitch=math.radians(self.max_wrist_pitch_deg),
                        max_wrist_yaw=math.radians(self.max_wrist_yaw_deg),
                        pitch_to_yaw=self.pitch_to_yaw, yaw_to_tip=self.yaw_to_tip)


class SceneFile(Strict):
    rig: str
    fields: str
    seed: Annotated[Int, Field(ge=0, lt=2**63)] = 0
    imaging: ImagingEntry = ImagingEntry()
    placements: dict[str, PlacementEntry] = Field(default_factory=dict)
    rods: dict[str, RodEntry] = Field(default_factory=dict)
    blots: dict[str, BlotEntry] = Field(default_factory=dict)
    needles: dict[str, NeedleEntry] = Field(default_factory=dict)
    pads: dict[str, PadEntry] = Field(default_factory=dict)
    grippers: dict[str, GripperEntry] = Field(default_factory=dict)
    arms: dict[str, ArmEntry] = Field(default_factory=dict)


def load_scene(path: str | Path) -> Scene:
    """Read a scene file and the rig and fields files it names; all validated (the
    ``[arms.*]`` sections too, which only :func:`load_needle_cell` uses)."""
    return _load(Path(path))[0]


def load_arms(path: str | Path) -> dict[str, ArmReach]:
    """The ``[arms.<gripper>]`` sections of a scene file, validated with the scene."""
    return _load(Path(path))[1]


def load_needle_cell(path: str | Path, *, reach: Mapping[str, ArmReach] | None = None,
                     **options) -> NeedleCell:
    """A :class:`~oralnav.sim.world.needle_cell.NeedleCell` from a scene file with one needle,
    one pad, one or two grippers and an ``[arms.<gripper>]`` section for each gripper
    (``reach`` adds to or replaces them by gripper name). ``options`` go to the cell
    (``kinematic_error``, ``grasp_tolerance``...)."""
    path = Path(path)
    scene, arms = _load(path)
    for section, objects, lo, hi in (("needles", scene.needles, 1, 1),
                                      ("pads", scene.pads, 1, 1),
                                      ("grippers", scene.grippers, 1, 2)):
        if not lo <= len(objects) <= hi:
            want = "exactly one" if lo == hi else f"{lo} to {hi}"
            raise ConfigError(path, section, f"a needle cell needs {want} [{section}.<name>] "
                              f"section(s), got {len(objects)}")
    reach = {**arms, **(reach or {})}
    missing = [g.name for g in scene.grippers if g.name not in reach]
    if missing:
        raise ConfigError(path, f"arms.{missing[0]}",
                          f"no [arms.<name>] section for gripper(s) {missing}: the cell needs "
                          "each arm's reach (rcm, min_insertion, max_insertion, and "
                          "optionally its wrist)")
    try:
        return NeedleCell(scene, reach, **options)
    except CellError as exc:
        raise ConfigError(path, "arms", str(exc)) from None


def _load(path: Path) -> tuple[Scene, dict[str, ArmReach]]:
    doc = validate(SceneFile, read_toml(path), path)
    if not (doc.placements or doc.needles or doc.pads or doc.grippers):
        raise ConfigError(path, "placements", "a scene needs at least one object: a "
                          "[placements.<name>], [needles.<name>], [pads.<name>] or "
                          "[grippers.<name>] section")
    seen: dict[str, str] = {n: "placements" for n in doc.placements}
    for section in ("needles", "pads", "grippers"):
        for n in getattr(doc, section):
            if n in seen:
                raise ConfigError(path, f"{section}.{n}",
                                  f"name {n!r} is already used in [{seen[n]}]; placements, "
                                  "needles, pads and grippers need distinct names")
            seen[n] = section
    rig = load_rig(resolve_file(path, "rig", doc.rig))
    fields = load_fields(resolve_file(path, "fields", doc.fields))
    placements = []
    for name, e in doc.placements.items():
        key = f"placements.{name}"
        if e.field not in fields:
            raise ConfigError(path, f"{key}.field",
                              f"unknown field {e.field!r}; the fields file has {sorted(fields)}")
        if e.T_ref_field is not None:
            T = build(path, f"{key}.T_ref_field",
                      lambda e=e: as_transform(e.T_ref_field, what="T_ref_field"))
        else:
            T = transform_from_euler(e.translation, e.euler_xyz_deg or (0.0, 0.0, 0.0))
        if not fields[e.field].renderable:
            raise ConfigError(path, f"{key}.field",
                              f"field {e.field!r} has a points surface, which the simulator "
                              "cannot render (use a plane or a cylinder)")
        placements.append(Placement(name=name, field=fields[e.field], T_ref_field=T,
                                    velocity=np.array(e.velocity),
                                    angular_velocity=np.radians(e.angular_velocity_deg_s)))
    rods = tuple(Rod(name=n, p0=np.array(r.p0), p1=np.array(r.p1), radius=r.radius,
                     level=r.level) for n, r in doc.rods.items())
    for n, b in doc.blots.items():
        if b.placement not in doc.placements:
            raise ConfigError(path, f"blots.{n}.placement",
                              f"unknown placement {b.placement!r}; the scene has "
                              f"{sorted(doc.placements)}")
    blots = tuple(Blot(name=n, placement=b.placement, center=b.center, radius=b.radius,
                       level=b.level) for n, b in doc.blots.items())
    for n in doc.arms:
        if n not in doc.grippers:
            raise ConfigError(path, f"arms.{n}",
                              f"no gripper named {n!r}; an arm section is named after the "
                              f"gripper it carries: {sorted(doc.grippers)}")
    arms = {n: a.reach() for n, a in doc.arms.items()}
    imaging = Imaging(**doc.imaging.model_dump())
    scene = Scene(rig=rig, placements=tuple(placements), rods=rods, blots=blots,
                  imaging=imaging, seed=doc.seed, source=str(path),
                  needles=tuple(_needle(path, n, e) for n, e in doc.needles.items()),
                  pads=tuple(_pad(path, n, e) for n, e in doc.pads.items()),
                  grippers=tuple(_gripper(path, n, e) for n, e in doc.grippers.items()))
    return scene, arms


def _needle(path: Path, name: str, e: NeedleEntry) -> NeedleObject:
    key = f"needles.{name}"
    if e.wire_diameter_mm >= e.radius_mm:
        raise ConfigError(path, f"{key}.wire_diameter_mm",
                          f"must be below radius_mm ({e.radius_mm}), got {e.wire_diameter_mm}")
    try:
        needle = Needle(radius=e.radius_mm * 1e-3, wire_diameter=e.wire_diameter_mm * 1e-3,
                        arc=math.radians(e.arc_deg))
    except NeedleError as exc:  # the bounds above leave nothing for it, but say where
        raise ConfigError(path, key, str(exc)) from None
    return NeedleObject(name=name, needle=needle, T_ref_needle=e.pose(path, key),
                        level=e.level, specular=e.specular, shininess=e.shininess,
                        thread_length=e.thread_length_mm * 1e-3,
                        thread_diameter=e.thread_diameter_mm * 1e-3,
                        thread_level=e.thread_level)


def _pad(path: Path, name: str, e: PadEntry) -> TissuePad:
    key = f"pads.{name}"
    sx, sy = e.size
    for end in e.incision:
        if abs(end[0]) > sx / 2 or abs(end[1]) > sy / 2:
            raise ConfigError(path, f"{key}.incision",
                              f"end {list(end)} lies outside the pad (size {list(e.size)} m, "
                              f"centred on the pad frame's origin: |x| <= {sx / 2}, "
                              f"|y| <= {sy / 2})")
    return TissuePad(name=name, T_ref_pad=e.pose(path, key), size=e.size, level=e.level,
                     incision=e.incision, incision_width=e.incision_width,
                     incision_level=e.incision_level)


def _gripper(path: Path, name: str, e: GripperEntry) -> Gripper:
    return Gripper(name=name, T_ref_tool=e.pose(path, f"grippers.{name}"),
                   jaw_length=e.jaw_length, jaw_width=e.jaw_width,
                   jaw_thickness=e.jaw_thickness, opening=e.opening,
                   shaft_radius=e.shaft_radius, shaft_length=e.shaft_length, level=e.level)
