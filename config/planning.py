"""Planning files: the placement scene (TOML) and the surrogate-model file (JSON).

A placement scene (docs/formats.md, "Planning scene") names the oral-cavity model (a
cylinder, a saved FPSM file or a mesh to fit), the implant hole, the instrument, the
objective and the PSO settings; file keys carry their units (``_mm``, ``_deg``), the
objects built from them are SI. An FPSM file holds a fitted model with its build report
and the mesh it came from; it is written atomically and checked again before it replaces
anything.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import Field, model_validator

from oralnav.control.errors import PlanningError
from oralnav.control.planning.fpsm import FPSM, METHODS, BuildReport, FitSettings, build_fpsm
from oralnav.control.planning.placement import EQUATIONS, Hole, PlacementSettings
from oralnav.control.planning.pso import PSOSettings

from .errors import ConfigError
from .loader import Float, Int, Strict, atomic_write_text, build, read_toml, resolve_file, validate

#: The FPSM file's format tag and version.
FPSM_FORMAT = "oralnav-fpsm"
FPSM_VERSION = 1

Range = tuple[Float, Float]
Vec3 = tuple[Float, Float, Float]
Pos = Annotated[Float, Field(gt=0)]


class ModelEntry(Strict):
    """``[model]``: what stands for the oral cavity."""

    kind: Literal["cylinder", "fpsm", "mesh", "oral_cavity"]
    # cylinder
    radius_mm: Pos | None = None
    z_range_mm: Range | None = None          # cylinder, or a mesh's slice range
    # fpsm / mesh
    file: str | None = None
    units: Literal["auto", "m", "mm"] = "auto"
    slices: Annotated[Int, Field(ge=2, le=200)] = 15
    points: Annotated[Int, Field(ge=3, le=100)] = 15
    samples: Annotated[Int, Field(ge=3, le=10000)] = 150
    method: str = "slp"
    margin_mm: Annotated[Float, Field(ge=0, le=5)] = 0.0
    # envelope: fit each curve to the nearest tissue over its slice's cell, which lets the
    # placement be certified against the mesh; plane: the paper's plane cuts
    boundary: Literal["envelope", "plane"] = "envelope"
    reach_mm: Annotated[Float, Field(ge=0, le=100)] = 10.0
    # oral_cavity: the parametric mouth of oralnav.sim.world.oral_cavity (tests and demos)
    width_mm: Annotated[Float, Field(ge=20, le=300)] = 55.0
    height_mm: Annotated[Float, Field(ge=20, le=300)] = 45.0
    depth_mm: Annotated[Float, Field(ge=20, le=300)] = 90.0
    teeth: bool = True
    missing_teeth: tuple[str, ...] = ()

    @model_validator(mode="after")
    def _kind_keys(self) -> ModelEntry:
        if self.kind == "cylinder":
            if self.radius_mm is None or self.z_range_mm is None:
                raise ValueError("a cylinder model needs radius_mm and z_range_mm")
            if self.file is not None:
                raise ValueError("a cylinder model takes no file")
        elif self.kind == "oral_cavity":
            if self.file is not None:
                raise ValueError("an oral_cavity model is generated: it takes no file")
        elif self.file is None:
            raise ValueError(f"a {self.kind} model needs file")
        if self.z_range_mm is not None and not self.z_range_mm[1] > self.z_range_mm[0]:
            raise ValueError("z_range_mm must be [low, high] with high > low")
        if self.method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}")
        return self


class HoleEntry(Strict):
    position_mm: Vec3
    axis: Vec3


class ToolEntry(Strict):
    rod_radius_mm: Annotated[Float, Field(ge=0, le=50)] = 6.0
    implant_length_mm: Annotated[Float, Field(gt=0, le=100)] = 31.0
    min_clearance_mm: Annotated[Float, Field(ge=0, le=20)] = 0.5


class ObjectiveEntry(Strict):
    equation: Int = 14
    lambda_avg: Annotated[Float, Field(ge=0)] = 0.5
    lambda_min: Annotated[Float, Field(gt=0)] = 0.5
    shrink_line2: bool = True
    max_hole_depth_mm: Annotated[Float, Field(gt=0)] = 20.0

    @model_validator(mode="after")
    def _eq(self) -> ObjectiveEntry:
        if self.equation not in EQUATIONS:
            raise ValueError(f"equation must be one of {EQUATIONS}")
        return self


class SearchEntry(Strict):
    d_T_range_mm: Range = (0.0, 120.0)
    theta_T_range_deg: Range = (-90.0, 90.0)

    @model_validator(mode="after")
    def _ranges(self) -> SearchEntry:
        for name in ("d_T_range_mm", "theta_T_range_deg"):
            lo, hi = getattr(self, name)
            if not hi > lo:
                raise ValueError(f"{name} must be [low, high] with high > low")
        return self


class PSOEntry(Strict):
    particles: Annotated[Int, Field(ge=2, le=10000)] = 30
    c0: Annotated[Float, Field(ge=0, lt=1.5)] = 0.7
    c1: Annotated[Float, Field(ge=0)] = 0.3
    c2: Annotated[Float, Field(ge=0)] = 0.4
    patience: Annotated[Int, Field(ge=1)] = 40
    max_iterations: Annotated[Int, Field(ge=1)] = 1000
    seed: Int = 0


class PlanningSceneFile(Strict):
    model: ModelEntry
    hole: HoleEntry
    tool: ToolEntry = ToolEntry()
    objective: ObjectiveEntry = ObjectiveEntry()
    search: SearchEntry = SearchEntry()
    pso: PSOEntry = PSOEntry()


@dataclass(frozen=True)
class PlanningScene:
    """A loaded placement scene: SI objects ready for
    :func:`oralnav.control.planning.placement.place`.
    ``build`` is the fit report when the model was fitted from a mesh at load."""

    path: Path
    model: FPSM
    hole: Hole
    settings: PlacementSettings
    source: str
    build: BuildReport | None = None
    mesh: Any = None


def load_planning_scene(path: str | Path) -> PlanningScene:
    """Read and check a placement scene; a mesh model is fitted here (about a second)."""
    path = Path(path)
    f = validate(PlanningSceneFile, read_toml(path), path)
    m = f.model
    report = mesh = None
    if m.kind == "cylinder":
        lo, hi = m.z_range_mm
        model = build(path, "model", lambda: FPSM.cylinder(
            m.radius_mm * 1e-3, lo * 1e-3, hi * 1e-3, m.slices, m.points))
        source = f"cylinder r = {m.radius_mm:g} mm"
    elif m.kind == "fpsm":
        target = resolve_file(path, "model.file", m.file)
        model = load_fpsm(target)[0]
        source = str(target)
    else:
        if m.kind == "mesh":
            from .mesh import load_mesh

            target = resolve_file(path, "model.file", m.file)
            mesh = load_mesh(target, units=m.units).mesh
            source = str(target)
        else:
            from oralnav.sim.world.oral_cavity import oral_cavity_mesh

            mesh = build(path, "model", lambda: oral_cavity_mesh(
                m.width_mm * 1e-3, m.height_mm * 1e-3, m.depth_mm * 1e-3, teeth=m.teeth,
                missing=tuple(m.missing_teeth)))
            source = (f"parametric oral cavity {m.width_mm:g} x {m.height_mm:g} x "
                      f"{m.depth_mm:g} mm")
        z = None if m.z_range_mm is None else (m.z_range_mm[0] * 1e-3, m.z_range_mm[1] * 1e-3)
        model, report = build(path, "model", lambda: build_fpsm(
            mesh, m.slices, m.points, m.samples, z,
            FitSettings(method=m.method, margin=m.margin_mm * 1e-3), m.boundary,
            m.reach_mm * 1e-3))
    o, s, t, p = f.objective, f.search, f.tool, f.pso
    settings = build(path, "pso", lambda: PlacementSettings(
        rod_radius=t.rod_radius_mm * 1e-3, implant_length=t.implant_length_mm * 1e-3,
        min_clearance=t.min_clearance_mm * 1e-3,
        lambda_avg=o.lambda_avg, lambda_min=o.lambda_min, equation=o.equation,
        shrink_line2=o.shrink_line2,
        d_range=(s.d_T_range_mm[0] * 1e-3, s.d_T_range_mm[1] * 1e-3),
        theta_range=(math.radians(s.theta_T_range_deg[0]),
                     math.radians(s.theta_T_range_deg[1])),
        max_hole_depth=o.max_hole_depth_mm * 1e-3,
        pso=PSOSettings(particles=p.particles, c0=p.c0, c1=p.c1, c2=p.c2,
                        patience=p.patience, max_iterations=p.max_iterations, seed=p.seed)))
    hole = build(path, "hole", lambda: Hole([v * 1e-3 for v in f.hole.position_mm],
                                             f.hole.axis))
    return PlanningScene(path, model, hole, settings, source, report, mesh)


# -- FPSM files ---------------------------------------------------------------------------

def fpsm_to_dict(model: FPSM, report: BuildReport | None = None,
                 mesh_file: str | Path | None = None) -> dict[str, Any]:
    doc: dict[str, Any] = {"format": FPSM_FORMAT, "version": FPSM_VERSION,
                           "created": datetime.now(UTC).isoformat(timespec="seconds"),
                           **model.to_dict()}
    if report is not None:
        doc["build"] = report.to_dict()
    if mesh_file is not None:
        data = Path(mesh_file).read_bytes()
        doc["mesh"] = {"file": str(mesh_file), "sha256": hashlib.sha256(data).hexdigest()}
    return doc


def fpsm_from_dict(doc: Any, path: str | Path) -> FPSM:
    if not isinstance(doc, dict):
        raise ConfigError(path, "", "not an FPSM file (expected a JSON object)")
    if doc.get("format") != FPSM_FORMAT:
        raise ConfigError(path, "format", f"expected {FPSM_FORMAT!r}, got {doc.get('format')!r}")
    if doc.get("version") != FPSM_VERSION:
        raise ConfigError(path, "version", f"unsupported version {doc.get('version')!r} "
                                           f"(this build reads {FPSM_VERSION})")
    if doc.get("units") != "m" or doc.get("frame") != "Center":
        raise ConfigError(path, "units", "an FPSM file must be in metres in the Center frame")
    try:
        return FPSM.from_dict(doc)
    except PlanningError as exc:
        raise ConfigError(path, "rho", str(exc)) from None


def load_fpsm(path: str | Path) -> tuple[FPSM, dict[str, Any]]:
    """Read an FPSM file: the model and the whole document (build report, mesh hash)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(path, "", "file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(path, "", f"cannot read: {exc}") from None
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ConfigError(path, "", f"not valid JSON: {exc}") from None
    return fpsm_from_dict(doc, path), doc


def save_fpsm(model: FPSM, path: str | Path, report: BuildReport | None = None,
              mesh_file: str | Path | None = None) -> Path:
    """Write ``model`` to ``path`` atomically, after reading the text back through the
    loader: a model the loader would refuse never replaces a good file."""
    path = Path(path)
    text = json.dumps(fpsm_to_dict(model, report, mesh_file), indent=1) + "\n"
    fpsm_from_dict(json.loads(text), path)
    atomic_write_text(path, text)
    return path
