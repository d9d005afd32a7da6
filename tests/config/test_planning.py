"""Issue 6: the placement scene (TOML) and the surrogate-model file (JSON): every shipped
case loads, SI conversion, clear errors naming file and key, atomic FPSM writes."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from oralnav.config.errors import ConfigError
from oralnav.config.mesh import save_mesh
from oralnav.config.planning import load_fpsm, load_planning_scene, save_fpsm
from oralnav.control.planning.fpsm import FPSM
from oralnav.sim.world.oral_cavity import oral_cavity_mesh

EXAMPLES = Path(__file__).resolve().parents[2] / "config" / "examples"
CASES = sorted(EXAMPLES.glob("*_case.toml"))

CYL = """\
[model]
kind = "cylinder"
radius_mm = 50.0
z_range_mm = [0.0, 100.0]
slices = 11

[hole]
position_mm = [0.0, -50.0, 50.0]
axis = [0.0, 1.0, 0.0]
"""


def _write(tmp_path: Path, text: str, name: str = "scene.toml") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def test_cases_are_shipped():
    """The paper's cylinder case and the oral-cavity case ship in config/examples."""
    assert {p.name for p in CASES} >= {"cylinder_case.toml", "oral_cavity_case.toml"}


@pytest.mark.parametrize("path", CASES, ids=[p.stem for p in CASES])
def test_every_case_loads(path):
    """Every shipped placement scene loads into SI objects."""
    sc = load_planning_scene(path)
    assert sc.model.slices >= 2 and 0 < sc.settings.rod_radius < 0.05
    assert np.isclose(np.linalg.norm(sc.hole.axis), 1.0)


def test_cylinder_case_values_in_si():
    """The cylinder case's keys carry units; the objects are in metres and radians."""
    sc = load_planning_scene(EXAMPLES / "cylinder_case.toml")
    assert np.allclose(sc.model.rho, 0.05) and sc.model.z[-1] == pytest.approx(0.1)
    assert np.allclose(sc.hole.position, [0, -0.05, 0.05])
    assert sc.settings.rod_radius == pytest.approx(0.006)
    assert sc.settings.implant_length == pytest.approx(0.031)
    assert sc.settings.theta_range[1] == pytest.approx(math.pi / 2)
    assert sc.settings.equation == 14 and sc.settings.pso.particles == 30


@pytest.mark.parametrize("edit, key", [
    ('radius_mm = 50.0', "model"),               # cylinder without a radius
    ('kind = "cylinder"', "model.kind"),         # unknown kind
    ('axis = [0.0, 1.0, 0.0]', "hole.axis"),     # axis with two numbers
])
def test_bad_scene_names_the_key(tmp_path, edit, key):
    """Bad input: the error names the file and the offending key."""
    repl = {"radius_mm = 50.0": "", 'kind = "cylinder"': 'kind = "sphere"',
            "axis = [0.0, 1.0, 0.0]": "axis = [0.0, 1.0]"}[edit]
    p = _write(tmp_path, CYL.replace(edit, repl))
    with pytest.raises(ConfigError) as e:
        load_planning_scene(p)
    assert str(p) in str(e.value) and e.value.key.startswith(key)


def test_unknown_key_is_refused(tmp_path):
    """Bad input: a misspelt key is an error, not ignored."""
    p = _write(tmp_path, CYL + "\n[tool]\nrod_radius = 6.0\n")
    with pytest.raises(ConfigError, match="unknown key"):
        load_planning_scene(p)


def test_hole_axis_along_x_is_refused(tmp_path):
    """Bad input: eq. 16 has no hole frame for an axis along Center x."""
    p = _write(tmp_path, CYL.replace("axis = [0.0, 1.0, 0.0]", "axis = [1.0, 0.0, 0.0]"))
    with pytest.raises(ConfigError, match="parallel to the Center x axis"):
        load_planning_scene(p)


def test_mesh_model_is_fitted_at_load(tmp_path):
    """A mesh model (here in millimetres, units detected) is fitted when the scene loads,
    with its build report."""
    save_mesh(oral_cavity_mesh(resolution=0.5), tmp_path / "mouth.stl", units="mm")
    text = CYL.replace('kind = "cylinder"\nradius_mm = 50.0\nz_range_mm = [0.0, 100.0]\n'
                       'slices = 11', 'kind = "mesh"\nfile = "mouth.stl"\nslices = 6')
    text = text.replace("[0.0, -50.0, 50.0]", "[13.75, -17.3, 50.5]")
    sc = load_planning_scene(_write(tmp_path, text))
    assert sc.build is not None and sc.build.penetrating_samples == 0
    assert sc.model.slices == 6 and sc.mesh is not None


def test_missing_mesh_file_names_the_key(tmp_path):
    """Bad input: a model file that does not exist is reported against model.file."""
    text = CYL.replace('kind = "cylinder"\nradius_mm = 50.0\nz_range_mm = [0.0, 100.0]\n',
                       'kind = "mesh"\nfile = "nope.stl"\n')
    with pytest.raises(ConfigError, match="file not found") as e:
        load_planning_scene(_write(tmp_path, text))
    assert e.value.key == "model.file"


def test_fpsm_file_round_trip_and_scene_use(tmp_path):
    """An FPSM file written by save_fpsm loads back exactly and serves as a scene model."""
    m = FPSM(np.array([0.0, 0.05, 0.1]), np.full((3, 8), 0.05) + np.arange(8) * 1e-3)
    f = save_fpsm(m, tmp_path / "m.fpsm.json")
    m2, doc = load_fpsm(f)
    assert np.array_equal(m2.rho, m.rho) and doc["format"] == "oralnav-fpsm"
    text = CYL.replace('kind = "cylinder"\nradius_mm = 50.0\nz_range_mm = [0.0, 100.0]\n',
                       'kind = "fpsm"\nfile = "m.fpsm.json"\n')
    sc = load_planning_scene(_write(tmp_path, text))
    assert np.array_equal(sc.model.rho, m.rho)


def test_bad_fpsm_file_is_refused_and_nothing_replaced(tmp_path):
    """Bad input: a foreign JSON file is refused naming the key; a failed save leaves the
    previous good file as it was."""
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"format": "other"}))
    with pytest.raises(ConfigError, match="format"):
        load_fpsm(bad)
    good = save_fpsm(FPSM.cylinder(0.05, 0, 0.1, 3, 6), tmp_path / "g.json")
    before = good.read_bytes()

    class Broken(FPSM):
        def to_dict(self):
            d = super().to_dict()
            d["rho"] = [[1.0]]                  # malformed: the loader refuses it
            return d

    with pytest.raises(ConfigError):
        save_fpsm(Broken(np.array([0.0, 0.1]), np.full((2, 6), 0.05)), good)
    assert good.read_bytes() == before
