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

from pydantic import Field, model_validator

from oralnav.control.camera import Rig
from oralnav.control.markers import MarkerField

from .errors import ConfigError
from .fields import load_fields
from .loader import Strict, read_toml, resolve, validate
from .rig import load_rig

#: ISO 10218 reduced speed: no configured Cartesian speed may exceed it (m/s).
ISO_REDUCED_SPEED = 0.25


class CellSection(Strict):
    backend: Literal["sim", "hardware"] = "sim"
    rig: str
    endoscope_rig: str | None = None
    fields: str
    scene: str | None = None

    @model_validator(mode="after")
    def _scene_for_sim(self) -> CellSection:
        if self.backend == "sim" and not self.scene:
            raise ValueError("the sim backend needs scene (a scene file to simulate)")
        return self


class ControlSection(Strict):
    rate_hz: Annotated[float, Field(ge=10, le=1000)] = 500.0


class SafetySection(Strict):
    max_speed: Annotated[float, Field(gt=0, le=ISO_REDUCED_SPEED)] = ISO_REDUCED_SPEED
    near_patient_speed: Annotated[float, Field(gt=0, le=ISO_REDUCED_SPEED)] = 0.05
    stale_pose: Annotated[float, Field(gt=0, le=1.0)] = 0.1

    @model_validator(mode="after")
    def _near_is_slower(self) -> SafetySection:
        if self.near_patient_speed > self.max_speed:
            raise ValueError("near_patient_speed must not exceed max_speed")
        return self


class ApiSection(Strict):
    host: str = "127.0.0.1"
    port: Annotated[int, Field(ge=1, le=65535)] = 8750


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
    rig = load_rig(resolve(path, cell.rig))
    endo = load_rig(resolve(path, cell.endoscope_rig)) if cell.endoscope_rig else None
    fields = load_fields(resolve(path, cell.fields))
    scene = resolve(path, cell.scene) if cell.scene else None
    if scene is not None and not scene.is_file():
        raise ConfigError(path, "cell.scene", f"file not found: {scene}")
    return DaemonConfig(path=path, settings=doc, rig=rig, endoscope_rig=endo, fields=fields,
                        scene_path=scene)
