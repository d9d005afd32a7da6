"""Tests of ``oralnav.config.cell``: the cell file of the simulated surgical cell.

Only loading is tested here (no image is rendered; tests/sim/world/test_cell.py renders). Each
test's docstring names the requirement it checks (issue 4 sim cell: the cell file).
"""

from __future__ import annotations

import tomllib
from functools import partial
from pathlib import Path

import numpy as np
import pytest

from oralnav.config.cell import load_cell_config, load_sim_cell
from oralnav.config.errors import ConfigError
from oralnav.config.scene import load_scene
from oralnav.sim.world.cell import CellConfig, CellGeometry, SimCell
from tests.config.helpers import edit, expect_config_error, write_file

EXAMPLES = Path(__file__).resolve().parents[2] / "config" / "examples"
CELL = EXAMPLES / "sim_cell.toml"
STEREO = EXAMPLES / "stereo_cell.toml"
ENDOSCOPE = EXAMPLES / "endoscope_view.toml"

# The shipped file with absolute scene paths, so it can be edited and written anywhere.
GOOD = edit('stereo_scene = "stereo_cell.toml"', f'stereo_scene = "{STEREO}"',
            edit('endoscope_scene = "endoscope_view.toml"', f'endoscope_scene = "{ENDOSCOPE}"',
                 CELL.read_text()))

_expect = partial(expect_config_error, load_cell_config)


def _write(tmp_path: Path, text: str) -> Path:
    return write_file(tmp_path, "cell.toml", text)


def test_shipped_cell_loads_from_any_folder(tmp_path, monkeypatch):
    """Issue 4 sim cell (the cell file): config/examples/sim_cell.toml loads from any
    working directory; its scene paths are relative to it and their rigs are reused."""
    monkeypatch.chdir(tmp_path)
    cfg = load_cell_config(CELL)
    assert isinstance(cfg, CellConfig) and cfg.source == str(CELL)
    assert cfg.stereo_scene.rig.reference == "left"
    assert cfg.endoscope_scene.rig.reference == "endoscope"
    assert (cfg.robot, cfg.effector, cfg.opener) == ("robot", "effector", "opener")
    assert 3 <= len(cfg.targets_OM) <= 5


def test_loader_round_trip():
    """Issue 4 sim cell (loader round trip): every number of the file reaches the config
    unchanged (transforms, wrist link, poses, mouth box, targets)."""
    raw = tomllib.loads(CELL.read_text())
    cfg = load_cell_config(CELL)
    for key, value in raw["geometry"].items():
        assert np.array_equal(getattr(cfg.geometry, key), np.array(value)), key
    for key, value in raw["poses"].items():
        assert np.array_equal(getattr(cfg, key), np.array(value)), key
    assert np.array_equal(cfg.geometry.mouth_min, raw["mouth"]["min"])
    assert np.array_equal(cfg.geometry.mouth_max, raw["mouth"]["max"])
    assert {n: list(p) for n, p in cfg.targets_OM.items()} == {
        n: t["p_OM"] for n, t in raw["targets"].items()}
    assert not cfg.geometry.T_B_C.flags.writeable  # frozen once validated


def test_derived_numbers_round_trip():
    """Issue 4 sim cell (derived numbers round-trip within 1e-9): re-deriving T_tcp_RM,
    T_tcp_E0, T_B_OM and T_OM_En from the chosen values and the two scene files gives the
    file's numbers."""
    cfg = load_cell_config(CELL)
    g = cfg.geometry
    stereo, endo = load_scene(STEREO), load_scene(ENDOSCOPE)
    derived = CellGeometry.from_views(
        T_B_C=g.T_B_C, T_E_EM=g.T_E_EM, wrist_link=g.wrist_link, mouth_min=g.mouth_min,
        mouth_max=g.mouth_max, home_T_B_tcp=cfg.home_T_B_tcp,
        intraoral_T_B_tcp=cfg.intraoral_T_B_tcp,
        T_C_RM=stereo.placement("robot").T_ref_field,
        T_C_EM=stereo.placement("effector").T_ref_field,
        T_C_OM=stereo.placement("opener").T_ref_field,
        T_En_EM=endo.placement("effector").T_ref_field)
    for key in ("T_tcp_RM", "T_tcp_E0", "T_B_OM", "T_OM_En"):
        np.testing.assert_allclose(getattr(g, key), getattr(derived, key), rtol=0, atol=1e-9,
                                   err_msg=key)


def test_load_sim_cell_builds_without_rendering():
    """Issue 4 sim cell (config builds it from files): load_sim_cell gives a SimCell with
    the stereo and endoscope cameras, and reads no state before a capture."""
    def never():
        raise AssertionError("the constructor must not read the state")

    cell = load_sim_cell(CELL, never, never, never)
    assert isinstance(cell, SimCell)
    assert cell.camera_names == ("left", "right", "endoscope")
    assert [f.name for f in cell.fields] == ["robot", "effector", "opener"]


# -- clear errors ---------------------------------------------------------------------------
BAD = {
    "unknown_top_key": (GOOD + 'colour = "blue"\n', "colour", "unknown key"),
    "unknown_geometry_key": (edit("wrist_link = 0.008", "wrist_link = 0.008\nT_B_X = 1", GOOD),
                             "[geometry] T_B_X", "unknown key"),
    "not_a_rotation": (edit("T_B_C = [[0.0, 0.0, -1.0, 0.59]", "T_B_C = [[0.0, 0.1, -1.0, 0.59]",
                            GOOD), "[geometry] T_B_C", "not a proper rotation"),
    "not_4x4": (edit("T_B_OM = [[0.0, 0.0, -1.0, 0.375],", "T_B_OM = [", GOOD),
                "[geometry] T_B_OM", "4x4"),
    "bottom_row": (edit("[0.0, 0.0, 0.0, 1.0]]\nwrist_link", "[0.0, 0.0, 0.1, 1.0]]\nwrist_link",
                        GOOD), "[geometry] T_tcp_E0", "bottom row"),
    "pose_not_rigid": (edit("home_T_B_tcp = [[1.0,", "home_T_B_tcp = [[2.0,", GOOD),
                       "[poses] home_T_B_tcp", "not a proper rotation"),
    "missing_mouth": (edit("min = [0.070, -0.010, -0.040]\nmax = [0.120, 0.060, 0.040]\n", "",
                           GOOD).replace("[mouth]", ""), "mouth", "Field required"),
    "string_number": (edit("wrist_link = 0.008", 'wrist_link = "0.008"', GOOD),
                      "[geometry] wrist_link", "valid number"),
    "negative_link": (edit("wrist_link = 0.008", "wrist_link = -0.008", GOOD),
                      "[geometry] wrist_link", "greater than or equal to 0"),
    "mouth_inverted": (edit("max = [0.120,", "max = [0.060,", GOOD), "[mouth] max",
                       "x: 0.06 <= 0.07"),
    "target_outside": (edit("p_OM = [0.102, 0.035, 0.010]", "p_OM = [0.202, 0.035, 0.010]",
                            GOOD), "[targets.stitch_4] p_OM", "outside the mouth box"),
    "stereo_scene_missing": (edit(str(STEREO), "nowhere.toml", GOOD), "stereo_scene",
                             "file not found"),
    "endoscope_scene_missing": (edit(str(ENDOSCOPE), "nowhere.toml", GOOD), "endoscope_scene",
                                "file not found"),
    "unknown_placement": (edit('opener = "opener"', 'opener = "mouth"', GOOD),
                          "[placements] opener", "has no placement 'mouth'"),
}


@pytest.mark.parametrize("case", BAD, ids=list(BAD))
def test_bad_files_are_rejected_naming_file_and_key(case, tmp_path):
    """Issue 4 sim cell (clear errors): an unknown key, a bad transform, a missing scene
    file and the other mistakes each give one ConfigError naming the file and the key."""
    text, where, reason = BAD[case]
    _expect(_write(tmp_path, text), where, reason)


def test_endoscope_scene_without_the_effector_is_rejected(tmp_path):
    """Issue 4 sim cell (clear errors): an endoscope scene that does not place the
    effector field is reported on the cell file's [placements] effector."""
    scene = write_file(tmp_path, "endo.toml", edit(
        "[placements.effector]", "[placements.other]",
        ENDOSCOPE.read_text().replace('"../', f'"{ENDOSCOPE.parent.parent}/')))
    cell = _write(tmp_path, edit(str(ENDOSCOPE), str(scene), GOOD))
    _expect(cell, "[placements] effector", "the endoscope scene")


def test_rigs_sharing_a_camera_name_are_rejected(tmp_path):
    """Issue 4 sim cell (clear errors): the stereo rig named again as the endoscope's is
    reported on endoscope_scene (capture could not tell the cameras apart)."""
    cell = _write(tmp_path, edit(str(ENDOSCOPE), str(STEREO), GOOD))
    _expect(cell, "endoscope_scene", "in both rigs")


def test_a_broken_scene_is_reported_in_its_own_file(tmp_path):
    """Issue 4 sim cell (clear errors): a broken scene file named by the cell is reported
    against the scene file and its key."""
    scene = write_file(tmp_path, "stereo.toml", edit(
        "seed = 1", "seed = -1",
        STEREO.read_text().replace('"../', f'"{STEREO.parent.parent}/')))
    cell = _write(tmp_path, edit(str(STEREO), str(scene), GOOD))
    with pytest.raises(ConfigError) as ei:
        load_cell_config(cell)
    assert ei.value.file == str(scene) and ei.value.key == "seed"
