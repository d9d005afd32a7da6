"""The scene file: what the simulator renders (see docs/formats.md).

A scene names a rig file and a fields file (paths relative to the scene file), places
fields in the rig's reference frame, adds occluders and sets the imaging model.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import numpy as np
from pydantic import Field, field_validator, model_validator

from oralnav.control.geometry import as_transform, transform_from_euler
from oralnav.sim.scene import Blot, Imaging, Placement, Rod, Scene

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


class SceneFile(Strict):
    rig: str
    fields: str
    seed: Annotated[Int, Field(ge=0, lt=2**63)] = 0
    imaging: ImagingEntry = ImagingEntry()
    placements: dict[str, PlacementEntry] = Field(min_length=1)
    rods: dict[str, RodEntry] = Field(default_factory=dict)
    blots: dict[str, BlotEntry] = Field(default_factory=dict)


def load_scene(path: str | Path) -> Scene:
    """Read a scene file and the rig and fields files it names; all validated."""
    path = Path(path)
    doc = validate(SceneFile, read_toml(path), path)
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
    imaging = Imaging(**doc.imaging.model_dump())
    return Scene(rig=rig, placements=tuple(placements), rods=rods, blots=blots,
                 imaging=imaging, seed=doc.seed, source=str(path))
