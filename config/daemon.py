"""The daemon's configuration (``oralnavd --config FILE``); see docs/formats.md.

Validated once at start, then frozen. ``config/sim.toml`` (shipped inside the package) is
the default: the simulated cell. ``config/hardware.example.toml`` is the template for a
real robot PC.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field, ValidationInfo, field_validator

from oralnav.control.camera import Rig
from oralnav.control.markers import MarkerField
from oralnav.sim.scene import Scene

from .fields import load_fields
from .loader import Float, Int, Strict, read_toml, resolve_file, validate
from .rig import load_rig
from .scene import load_scene

#: ISO 10218 reduced speed: no configured Cartesian speed may exceed it (m/s).
ISO_REDUCED_SPEED = 0.25


class CellSection(Strict):
    backend: Literal["sim", "hardware"] = "sim"
    rig: str
    endoscope_rig: str | None = None
    fields: str
    # validate_default: the check below must also run when scene is left out
    scene: str | None = Field(None, validate_default=True)

    @field_validator("scene")
    @classmethod
    def _scene_for_sim(cls, v: str | None, info: ValidationInfo) -> str | None:
        if info.data.get("backend") == "sim" and not v:
            raise ValueError("the sim backend needs scene (a scene file to simulate)")
        return v


class ControlSection(Strict):
    rate_hz: Annotated[Float, Field(ge=10, le=1000)] = 500.0


def _iso_speed(v: float) -> float:
    if v > ISO_REDUCED_SPEED:
        raise ValueError(f"{v} m/s exceeds the ISO 10218 reduced speed, "
                         f"{ISO_REDUCED_SPEED} m/s")
    return v


class SafetySection(Strict):
    max_speed: Annotated[Float, Field(gt=0)] = ISO_REDUCED_SPEED
    near_patient_speed: Annotated[Float, Field(gt=0)] = 0.05
    stale_pose: Annotated[Float, Field(gt=0, le=1.0)] = 0.1

    _check_iso = field_validator("max_speed", "near_patient_speed")(_iso_speed)

    @field_validator("near_patient_speed")
    @classmethod
    def _near_is_slower(cls, v: float, info: ValidationInfo) -> float:
        # info.data lacks max_speed when max_speed itself failed; that error is reported
        top = info.data.get("max_speed")
        if top is not None and v > top:
            raise ValueError(f"near_patient_speed ({v} m/s) must not exceed max_speed "
                             f"({top} m/s)")
        return v


class ApiSection(Strict):
    host: str = "127.0.0.1"
    port: Annotated[Int, Field(ge=1, le=65535)] = 8750


class DaemonFile(Strict):
    name: str = "oralnav"
    cell: CellSection
    control: ControlSection = ControlSection()
    safety: SafetySection = SafetySection()
    api: ApiSection = ApiSection()


@dataclass(frozen=True)
class DaemonConfig:
    """A validated daemon configuration with its referenced files loaded."""

    path: Path
    settings: DaemonFile
    rig: Rig
    endoscope_rig: Rig | None
    fields: dict[str, MarkerField]
    scene_path: Path | None
    #: the loaded scene file, when the configuration names one (validated at start too)
    scene: Scene | None = None


def default_config_path() -> Path:
    """The embedded simulation default, ``config/sim.toml``."""
    return Path(str(resources.files("oralnav.config").joinpath("sim.toml")))


def load_config(path: str | Path | None = None) -> DaemonConfig:
    """Load and validate a daemon configuration and every file it names.

    Nothing is started here; any problem raises :class:`ConfigError` naming the file and
    key before the daemon touches hardware.
    """
    path = Path(path) if path is not None else default_config_path()
    doc = validate(DaemonFile, read_toml(path), path)
    cell = doc.cell
    rig = load_rig(resolve_file(path, "cell.rig", cell.rig))
    endo = (load_rig(resolve_file(path, "cell.endoscope_rig", cell.endoscope_rig))
            if cell.endoscope_rig else None)
    fields = load_fields(resolve_file(path, "cell.fields", cell.fields))
    scene_path = resolve_file(path, "cell.scene", cell.scene) if cell.scene else None
    scene = load_scene(scene_path) if scene_path is not None else None
    return DaemonConfig(path=path, settings=doc, rig=rig, endoscope_rig=endo, fields=fields,
                        scene_path=scene_path, scene=scene)
