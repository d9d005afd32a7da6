"""Issue 6, item 4: `oralnav plan place` prints exactly the specified JSON object and
reproduces the paper's cylinder case; `oralnav plan fpsm` builds and saves a model; both
write figures; bad input exits 2 naming the file, no safe placement exits 3."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from oralnav.cli import main as cli
from oralnav.cli.plan import NO_SAFE_PLACEMENT
from oralnav.config.mesh import save_mesh
from oralnav.config.planning import load_fpsm
from oralnav.sim.world.oral_cavity import oral_cavity_mesh

ROOT = Path(__file__).resolve().parents[2]
CYLINDER = ROOT / "config" / "examples" / "cylinder_case.toml"


def _json(capsys) -> dict:
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1, out
    return json.loads(out[0])


def test_place_cylinder_case_json(capsys):
    """The shipped cylinder case: eq. 14 gives d_T = 65.5 mm, theta_T = 0, collision-free;
    the object has exactly the specified keys, in metres and radians."""
    assert cli.run(["plan", "place", "--scene", str(CYLINDER), "--json"]) == 0
    doc = _json(capsys)
    assert set(doc) == {"d_T", "theta_T", "objective", "iterations", "time_ms",
                        "collision_free"}
    assert doc["d_T"] == pytest.approx(0.0655, abs=1e-5)
    assert doc["theta_T"] == pytest.approx(0.0, abs=1e-4)
    assert doc["collision_free"] is True and doc["iterations"] > 40


@pytest.mark.parametrize("eq, expect_mm", [(21, None), (22, (50.0, 81.0))])
def test_place_variants_show_their_failures(capsys, eq, expect_mm):
    """Eqs. 21 and 22 on the cylinder: not the 65.5 mm optimum (21 lands anywhere on its
    flat stretch, 22 on one line through the axis)."""
    assert cli.run(["plan", "place", "--scene", str(CYLINDER), "--equation", str(eq),
                    "--json"]) == 0
    d = _json(capsys)["d_T"] * 1e3
    if expect_mm:
        assert min(abs(d - e) for e in expect_mm) < 0.1
    else:
        assert 50.0 <= d <= 81.0


def test_place_writes_figures(tmp_path, capsys):
    """--figures writes the objective contour and the PSO convergence as PNG."""
    assert cli.run(["plan", "place", "--scene", str(CYLINDER), "--figures", str(tmp_path),
                    "--json"]) == 0
    _json(capsys)
    for name in ("place_objective.png", "place_convergence.png"):
        assert (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_no_safe_placement_exits_3(tmp_path, capsys):
    """Bad input: a rod wider than the cavity: collision_free false and exit status 3,
    never a placement reported as safe."""
    text = CYLINDER.read_text().replace("rod_radius_mm = 6.0", "rod_radius_mm = 45.0")
    scene = tmp_path / "fat.toml"
    scene.write_text(text)
    assert cli.run(["plan", "place", "--scene", str(scene), "--json"]) == NO_SAFE_PLACEMENT
    assert _json(capsys)["collision_free"] is False


def test_fpsm_builds_and_saves(tmp_path, capsys):
    """`plan fpsm` on a millimetre STL: the file holds the model and its report; 15 x 15
    with no penetrating sample; the slice figure is written."""
    mesh = tmp_path / "mouth.stl"
    save_mesh(oral_cavity_mesh(), mesh, units="mm")
    out = tmp_path / "m.fpsm.json"
    assert cli.run(["plan", "fpsm", "--mesh", str(mesh), "--slices", "15", "--points", "15",
                    "--out", str(out), "--figures", str(tmp_path), "--json"]) == 0
    doc = _json(capsys)
    assert doc["penetrating_samples"] == 0 and doc["coverage"] > 0.9
    model, saved = load_fpsm(out)
    assert model.rho.shape == (15, 15) and saved["mesh"]["sha256"]
    assert (tmp_path / "fpsm_slices.png").exists()


def test_fpsm_bad_mesh_exits_2_and_writes_nothing(tmp_path, capsys):
    """Bad input: a mesh that does not enclose the slice origin exits 2 naming the slice,
    and no model file appears."""
    m = oral_cavity_mesh()
    m.apply_translation([0.05, 0.0, 0.0])
    save_mesh(m, tmp_path / "off.stl")
    out = tmp_path / "m.json"
    rc = cli.run(["plan", "fpsm", "--mesh", str(tmp_path / "off.stl"), "--out", str(out),
                  "--json"])
    assert rc == 2
    doc = _json(capsys)
    assert "does not enclose the origin" in doc["error"] and not out.exists()


def test_place_bad_scene_exits_2(tmp_path, capsys):
    """Bad input: a scene with the hole outside the model exits 2 with the reason."""
    text = CYLINDER.read_text().replace("[0.0, -50.0, 50.0]", "[0.0, -50.0, 150.0]")
    scene = tmp_path / "s.toml"
    scene.write_text(text)
    assert cli.run(["plan", "place", "--scene", str(scene), "--json"]) == 2
    assert "outside the model" in _json(capsys)["error"]


@pytest.mark.parametrize("closed", [False, True])
def test_mouth_writes_the_parametric_cavity_as_stl(tmp_path, capsys, closed):
    """issue 33 item 6: `plan mouth` writes the parametric oral cavity as an STL (in mm,
    creating the folder) that trimesh loads with the model's faces and size; it is
    watertight exactly when the model is (`--closed-front`), and `--missing` leaves a
    crown out."""
    import numpy as np
    import trimesh

    out = tmp_path / "out" / "mouth.stl"
    argv = ["plan", "mouth", "--out", str(out), "--resolution", "0.25", "--json"]
    if closed:
        argv += ["--closed-front", "--missing", "lower_left_molar1"]
    assert cli.run(argv) == 0
    doc = _json(capsys)
    model = oral_cavity_mesh(resolution=0.25, closed_front=closed,
                             missing=("lower_left_molar1",) if closed else ())
    mesh = trimesh.load_mesh(out)
    assert len(mesh.faces) == len(model.faces) == doc["faces"]
    np.testing.assert_allclose(mesh.extents, [55.0, 45.0, 90.0], atol=1e-3)  # mm
    assert mesh.is_watertight == closed == doc["watertight"]
    assert doc["teeth"] == (27 if closed else 28) and doc["units"] == "mm"


@pytest.mark.parametrize("args, option", [
    (["--width-mm", "10"], "--width-mm"),
    (["--depth-mm", "400"], "--depth-mm"),
    (["--resolution", "0"], "--resolution"),
    (["--missing", "wisdom_tooth"], "--missing"),
    (["--no-teeth", "--missing", "lower_left_molar1"], "--missing"),
])
def test_mouth_bad_option_exits_2_naming_it(tmp_path, capsys, args, option):
    """issue 33 item 6: a size outside the model's 20-300 mm, a non-positive resolution
    or an unknown tooth exits 2 naming the option, and no file is written."""
    out = tmp_path / "mouth.stl"
    assert cli.run(["plan", "mouth", "--out", str(out), *args, "--json"]) == 2
    doc = _json(capsys)
    assert doc["exit"] == 2 and doc["error"].startswith(option), doc
    assert not out.exists()


def test_mouth_refuses_an_unknown_mesh_suffix(tmp_path, capsys):
    """issue 33 item 6: the suffix picks the format; another exits 2 naming --out and
    creates no folder."""
    out = tmp_path / "new" / "mouth.xyz"
    assert cli.run(["plan", "mouth", "--out", str(out), "--json"]) == 2
    assert _json(capsys)["error"].startswith("--out") and not out.parent.exists()
