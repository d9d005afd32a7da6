"""Tests of ``oralnav.config.scene``: the scene file the simulator renders.

Only loading is tested here (no image is rendered). Each test's docstring names the
requirement it checks (Issue 2: configuration).
"""

from __future__ import annotations

from functools import partial
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from oralnav.config.errors import ConfigError
from oralnav.config.scene import load_arms, load_needle_cell, load_scene
from oralnav.sim.world.scene import Scene
from tests.config.helpers import edit, expect_config_error, write_file

CONFIG = Path(__file__).resolve().parents[2] / "config"
# every example is a scene file except the cell file, which names two of them, and the
# planning cases (``*_case.toml``, tests/config/test_planning.py)
EXAMPLES = sorted(p for p in (CONFIG / "examples").glob("*.toml")
                  if p.name != "sim_cell.toml" and not p.stem.endswith("_case"))
STEREO = CONFIG / "rigs" / "stereo.toml"
CELL = CONFIG / "fields" / "cell.toml"

GOOD = f"""\
rig = "{STEREO}"
fields = "{CELL}"
seed = 4

[imaging]
supersample = 2
blur_sigma_px = 0.5

[placements.robot]
field = "robot"
translation = [-0.065, -0.045, 0.245]
euler_xyz_deg = [10.0, -15.0, 3.0]

[placements.opener]
field = "opener"
T_ref_field = [[1.0, 0.0, 0.0, 0.04], [0.0, 1.0, 0.0, -0.03],
               [0.0, 0.0, 1.0, 0.215], [0.0, 0.0, 0.0, 1.0]]

[rods.shaft]
p0 = [0.010, -0.060, 0.170]
p1 = [0.060, 0.010, 0.180]
radius = 0.0015

[blots.blood]
placement = "robot"
center = [0.020, 0.012]
radius = 0.004
"""


def _edit(old: str, new: str, text: str = GOOD) -> str:
    return edit(old, new, text)


_write = write_file
_expect = partial(expect_config_error, load_scene)


# -- shipped examples ----------------------------------------------------------------------
def test_examples_are_shipped():
    """Issue 2 (every shipped file loads): the example scenes exist (guards the
    parametrised test below against an empty glob)."""
    assert {p.name for p in EXAMPLES} >= {"stereo_cell.toml", "stereo_occluded.toml",
                                          "endoscope_view.toml", "needle_pad.toml"}


@pytest.mark.parametrize("path", EXAMPLES, ids=[p.stem for p in EXAMPLES])
def test_every_example_scene_loads(path, tmp_path, monkeypatch):
    """Issue 2 (every shipped file loads): each config/examples/*.toml loads with
    load_scene, from any working directory (its rig and fields paths are relative to it)."""
    monkeypatch.chdir(tmp_path)
    scene = load_scene(path)
    assert isinstance(scene, Scene) and scene.source == str(path)
    assert scene.placements or scene.needles or scene.pads or scene.grippers
    for p in scene.placements:
        assert p.field.renderable
        assert p.T_ref_field.shape == (4, 4)


def test_stereo_cell_values():
    """Issue 2 (scene format): stereo_cell.toml places its fields where the file says:
    translation in metres, extrinsic x-y-z Euler angles in degrees, in the rig's reference
    frame."""
    scene = load_scene(CONFIG / "examples" / "stereo_cell.toml")
    assert scene.rig.names == ("left", "right") and scene.seed == 1
    assert [p.name for p in scene.placements] == ["robot", "effector", "opener"]
    robot = scene.placement("robot")
    assert robot.field.name == "robot"
    np.testing.assert_array_equal(robot.T_ref_field[:3, 3], [-0.065, -0.045, 0.245])
    expected = Rotation.from_euler("xyz", [10.0, -15.0, 3.0], degrees=True).as_matrix()
    np.testing.assert_allclose(robot.T_ref_field[:3, :3], expected, atol=1e-15)
    assert scene.imaging.blur_sigma_px == 1.0 and scene.imaging.illumination_gradient == (
        0.15, -0.10)
    assert scene.rods == () and scene.blots == ()


def test_stereo_occluded_values():
    """Issue 2 (scene format): stereo_occluded.toml has its rod, its blot on the robot
    field, and the effector's velocities (m/s, and deg/s turned to rad/s)."""
    scene = load_scene(CONFIG / "examples" / "stereo_occluded.toml")
    (rod,) = scene.rods
    assert rod.name == "shaft" and rod.radius == 0.0015 and rod.level == 110.0
    np.testing.assert_array_equal(rod.p0, [0.010, -0.060, 0.170])
    (blot,) = scene.blots
    assert (blot.name, blot.placement, blot.center, blot.radius) == (
        "blood", "robot", (0.020, 0.012), 0.004)
    eff = scene.placement("effector")
    np.testing.assert_array_equal(eff.velocity, [0.05, 0.0, 0.0])
    np.testing.assert_allclose(eff.angular_velocity, [0.0, np.radians(20.0), 0.0])
    assert scene.imaging.motion_samples == 8 and scene.imaging.exposure == 0.008


def test_endoscope_view_uses_endoscope_rig():
    """Issue 2 (scene format): endoscope_view.toml renders the effector through the
    endoscope rig, whose own frame is the reference."""
    scene = load_scene(CONFIG / "examples" / "endoscope_view.toml")
    assert scene.rig.reference == "endoscope" and scene.rig.names == ("endoscope",)
    assert [p.name for p in scene.placements] == ["effector"]


def test_good_scene_template_loads(tmp_path):
    """Issue 2 (bad input tests are meaningful): the template the broken cases edit loads,
    with defaults for what it leaves out."""
    scene = load_scene(_write(tmp_path, "s.toml", GOOD))
    opener = scene.placement("opener")
    np.testing.assert_array_equal(opener.T_ref_field[:3, 3], [0.04, -0.03, 0.215])
    assert scene.seed == 4 and scene.imaging.blur_sigma_px == 0.5
    assert scene.imaging.white == 220.0  # default
    assert scene.blots[0].level == 60.0 and scene.rods[0].level == 90.0  # defaults
    np.testing.assert_array_equal(opener.velocity, np.zeros(3))


# -- bad input -----------------------------------------------------------------------------
BROKEN = {
    # name: (file text, expected "[section] key" text, expected reason texts)
    "syntax": (_edit('field = "robot"', "field = robot"), "not valid TOML", ("line 10",)),
    "unknown_key": (_edit("blur_sigma_px = 0.5", "blur_sigma = 0.5"), "[imaging] blur_sigma:",
                    ("unknown key",)),
    "unknown_section": (GOOD + "\n[lights.key]\nlevel = 3.0\n", ": lights:", ("unknown key",)),
    "missing_rig": (_edit(f'rig = "{STEREO}"\n', ""), ": rig:", ("Field required",)),
    "no_objects": (GOOD.split("[placements.robot]")[0], ": placements:",
                   ("a scene needs at least one object",)),
    "supersample_bound": (_edit("supersample = 2", "supersample = 5"),
                          "[imaging] supersample:", ("less than or equal to 4",)),
    "seed_negative": (_edit("seed = 4", "seed = -1"), ": seed:", ("greater than or equal",)),
    "translation_string": (_edit("[-0.065, -0.045, 0.245]", '["-0.065", -0.045, 0.245]'),
                           "[placements.robot] translation[0]:", ("valid number",)),
    "translation_two": (_edit("[-0.065, -0.045, 0.245]", "[-0.065, -0.045]"),
                        "[placements.robot] translation[2]:", ("Field required",)),
    "unknown_field": (_edit('field = "opener"', 'field = "jaw"'),
                      "[placements.opener] field:",
                      ("unknown field 'jaw'", "['effector', 'opener', 'robot']")),
    "unknown_placement": (_edit('placement = "robot"', 'placement = "robt"'),
                          "[blots.blood] placement:",
                          ("unknown placement 'robt'", "['opener', 'robot']")),
    "T_not_rotation": (_edit("[[1.0, 0.0, 0.0, 0.04]", "[[1.1, 0.0, 0.0, 0.04]"),
                       "[placements.opener] T_ref_field:", ("not a proper rotation",)),
    "T_nan": (_edit("[[1.0, 0.0, 0.0, 0.04]", "[[nan, 0.0, 0.0, 0.04]"),
              "[placements.opener] T_ref_field[0][0]:", ("finite",)),
    "both_poses": (_edit("translation = [-0.065", "T_ref_field = [[1.0, 0.0, 0.0, 0.0], "
                         "[0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]\n"
                         "translation = [-0.065"),
                   "[placements] robot:", ("either as T_ref_field", "not both or neither")),
    "no_pose": (_edit("translation = [-0.065, -0.045, 0.245]\neuler_xyz_deg = [10.0, -15.0, "
                      "3.0]\n", ""), "[placements] robot:", ("not both or neither",)),
    "euler_without_translation": (
        _edit("T_ref_field = [[1.0", 'euler_xyz_deg = [0.0, 0.0, 1.0]\nT_ref_field = [[1.0'),
        "[placements] opener:", ("euler_xyz_deg needs translation",)),
    "blot_radius_bound": (_edit("radius = 0.004", "radius = 0.0"), "[blots.blood] radius:",
                          ("greater than 0",)),
    "rig_file_missing": (_edit(f'rig = "{STEREO}"', 'rig = "no_rig.toml"'), ": rig:",
                         ("file not found", "no_rig.toml")),
    "fields_file_missing": (_edit(f'fields = "{CELL}"', 'fields = "nofields.toml"'),
                            ": fields:", ("file not found", "nofields.toml")),
}


@pytest.mark.parametrize("case", list(BROKEN))
def test_broken_scene_file_is_one_clear_error(tmp_path, case):
    """Issue 2 (bad input): a malformed scene file (syntax error, unknown or missing keys,
    wrong types, bounds, a placement naming an unknown field, a blot naming an unknown
    placement, a pose that is not rigid, a missing rig or fields file) gives one
    ConfigError naming the file, the section and key, and the reason."""
    text, where, reasons = BROKEN[case]
    _expect(_write(tmp_path, f"{case}.toml", text), where, *reasons)


def test_broken_rig_named_by_scene_names_the_rig_file(tmp_path):
    """Issue 2 (bad input): an error inside the rig a scene names is reported against the
    rig file and its key, not against the scene."""
    rig = _write(tmp_path, "rig.toml", STEREO.read_text().replace("size = [1920, 1200]",
                                                                   "size = [1920]", 1))
    path = _write(tmp_path, "s.toml", _edit(f'rig = "{STEREO}"', 'rig = "rig.toml"'))
    with pytest.raises(ConfigError) as ei:
        load_scene(path)
    assert str(ei.value).startswith(f"{rig}: [cameras.left] size")


def test_broken_fields_named_by_scene_names_the_fields_file(tmp_path):
    """Issue 2 (bad input): an error inside the fields file a scene names is reported
    against that fields file and its key."""
    fields = _write(tmp_path, "f.toml", CELL.read_text().replace("first_id = 100",
                                                                  "first_id = 20"))
    path = _write(tmp_path, "s.toml", _edit(f'fields = "{CELL}"', 'fields = "f.toml"'))
    with pytest.raises(ConfigError) as ei:
        load_scene(path)
    assert str(ei.value).startswith(f"{fields}: [fields.effector] first_id:")
    assert "must not share ids" in str(ei.value)


def test_points_field_cannot_be_placed(tmp_path):
    """Issue 2 (bad input): placing a points-surface field, which the simulator cannot
    render, names the placement's field key and why."""
    _write(tmp_path, "jaw.csv", "corner_id,x,y,z\n0,0,0,0\n1,1e-3,0,0\n2,0,1e-3,0\n"
                                "3,1e-3,1e-3,0\n")
    _write(tmp_path, "f.toml", '[fields.jaw]\ndictionary = "DICT_4X4_50"\nsquares = [4, 3]\n'
                               'square = 0.004\nmarker = 0.003\n[fields.jaw.surface]\n'
                               'kind = "points"\nfile = "jaw.csv"\n')
    path = _write(tmp_path, "s.toml", f'rig = "{STEREO}"\nfields = "f.toml"\n'
                                      '[placements.jaw]\nfield = "jaw"\n'
                                      'translation = [0.0, 0.0, 0.2]\n')
    _expect(path, "[placements.jaw] field:", "points surface", "cannot render")


# -- needles, pads and grippers (issue 7, part 1) -----------------------------------------
NEEDLE_GOOD = f"""\
rig = "{CONFIG / 'rigs' / 'endoscope.toml'}"
fields = "{CELL}"

[pads.pad]
translation = [0.0, 0.0, 0.1]
euler_xyz_deg = [200.0, 0.0, 0.0]
size = [0.06, 0.04]
incision = [[-0.025, -0.01], [0.025, -0.01]]

[needles.ct1]
radius_mm = 13.0
wire_diameter_mm = 1.0
arc_deg = 180.0
translation = [0.0, 0.0, 0.099]
euler_xyz_deg = [200.0, 0.0, 0.0]

[grippers.driver]
T_ref_tool = [[1.0, 0.0, 0.0, -0.02], [0.0, 1.0, 0.0, 0.0],
              [0.0, 0.0, 1.0, 0.09], [0.0, 0.0, 0.0, 1.0]]
jaw_length = 0.012
opening = 0.002
"""


def test_needle_pad_example_values():
    """Issue 7 part 1 (scene keys): needle_pad.toml holds a CT-1 needle (radius 13 mm,
    1 mm wire, a semicircle) lying on a pad (its centre half the wire above the pad's
    surface, its plane the pad's), the pad's 5 cm incision, and an open gripper; sizes in
    mm and degrees in the file come out in metres and radians."""
    scene = load_scene(CONFIG / "examples" / "needle_pad.toml")
    assert scene.rig.reference == "endoscope" and scene.placements == ()
    (nd,), (pad,), (g,) = scene.needles, scene.pads, scene.grippers
    assert (nd.name, pad.name, g.name) == ("ct1", "pad", "driver")
    assert nd.needle.radius == pytest.approx(0.013) and nd.needle.arc == pytest.approx(np.pi)
    assert nd.needle.wire_diameter == pytest.approx(0.001)
    T_pad_needle = np.linalg.inv(pad.T_ref_pad) @ nd.T_ref_needle
    np.testing.assert_allclose(T_pad_needle[:3, 3], [0.002, 0.006, 0.0005], atol=1e-6)
    np.testing.assert_allclose(T_pad_needle[:3, :3], np.eye(3), atol=1e-9)
    (a, b) = pad.incision
    assert np.hypot(b[0] - a[0], b[1] - a[1]) == pytest.approx(0.05)
    assert 0.08 <= pad.T_ref_pad[2, 3] <= 0.12   # about 10 cm from the endoscope
    assert g.opening == 0.003 and g.shaft_radius == 0.003


def test_needle_scene_template_loads(tmp_path):
    """Issue 7 part 1 (scene keys): the template the broken cases below edit loads, with
    defaults for what it leaves out, and a scene of needle-driving objects only needs no
    placement."""
    scene = load_scene(_write(tmp_path, "n.toml", NEEDLE_GOOD))
    (nd,), (pad,), (g,) = scene.needles, scene.pads, scene.grippers
    assert nd.level == 70.0 and nd.specular == 180.0 and nd.shininess == 20.0
    assert pad.level == 170.0 and pad.incision_width == 0.0008
    assert g.jaw_length == 0.012 and g.opening == 0.002 and g.jaw_width == 0.0025
    np.testing.assert_array_equal(g.T_ref_tool[:3, 3], [-0.02, 0.0, 0.09])


def _nedit(old: str, new: str) -> str:
    return edit(old, new, NEEDLE_GOOD)


ARM = "\n[arms.driver]\nrcm = [0.0, -0.05, -0.02]\n"


NEEDLE_BROKEN = {
    "needle_unknown_key": (_nedit("radius_mm = 13.0", "radius = 0.013"),
                           "[needles.ct1] radius:", ("unknown key",)),
    "needle_radius_zero": (_nedit("radius_mm = 13.0", "radius_mm = 0.0"),
                           "[needles.ct1] radius_mm:", ("greater than 0",)),
    "needle_wire_too_thick": (_nedit("wire_diameter_mm = 1.0", "wire_diameter_mm = 3.0")
                              .replace("radius_mm = 13.0", "radius_mm = 2.0"),
                              "[needles.ct1] wire_diameter_mm:", ("below radius_mm",)),
    "needle_arc_too_long": (_nedit("arc_deg = 180.0", "arc_deg = 400.0"),
                            "[needles.ct1] arc_deg:", ("less than or equal to 360",)),
    "needle_no_pose": (_nedit('translation = [0.0, 0.0, 0.099]\neuler_xyz_deg = [200.0, 0.0, '
                              '0.0]\n', ""), "[needles] ct1:",
                       ("T_ref_needle", "not both or neither")),
    "needle_mm_as_string": (_nedit("wire_diameter_mm = 1.0", 'wire_diameter_mm = "1.0"'),
                            "[needles.ct1] wire_diameter_mm:", ("valid number",)),
    "pad_size_one": (_nedit("size = [0.06, 0.04]", "size = [0.06]"),
                     "[pads.pad] size[1]:", ("Field required",)),
    "pad_size_negative": (_nedit("size = [0.06, 0.04]", "size = [0.06, -0.04]"),
                          "[pads.pad] size[1]:", ("greater than 0",)),
    "pad_no_incision": (_nedit("incision = [[-0.025, -0.01], [0.025, -0.01]]\n", ""),
                        "[pads.pad] incision:", ("Field required",)),
    "pad_incision_outside": (_nedit("[0.025, -0.01]]", "[0.035, -0.01]]"),
                             "[pads.pad] incision:", ("outside the pad", "0.035")),
    "pad_incision_shape": (_nedit("[[-0.025, -0.01], [0.025, -0.01]]", "[[-0.025, -0.01]]"),
                           "[pads.pad] incision[1]:", ("Field required",)),
    "gripper_negative_jaw": (_nedit("jaw_length = 0.012", "jaw_length = -0.012"),
                             "[grippers.driver] jaw_length:", ("greater than 0",)),
    "gripper_unknown_key": (_nedit("opening = 0.002", "opening_mm = 2.0"),
                            "[grippers.driver] opening_mm:", ("unknown key",)),
    "gripper_T_not_rigid": (_nedit("[0.0, 0.0, 0.0, 1.0]]", "[0.0, 0.0, 0.1, 1.0]]"),
                            "[grippers.driver] T_ref_tool:", ("bottom row",)),
    "name_clash": (_nedit("[grippers.driver]", "[grippers.ct1]"), "[grippers] ct1:",
                   ("already used in [needles]",)),
    "unknown_object_section": (NEEDLE_GOOD + "\n[sutures.s]\nlength = 0.1\n", ": sutures:",
                               ("unknown key",)),
    "thread_negative": (_nedit("arc_deg = 180.0", "arc_deg = 180.0\nthread_length_mm = -1.0"),
                        "[needles.ct1] thread_length_mm:", ("greater than or equal to 0",)),
    "thread_diameter_zero": (_nedit("arc_deg = 180.0",
                                    "arc_deg = 180.0\nthread_diameter_mm = 0.0"),
                             "[needles.ct1] thread_diameter_mm:", ("greater than 0",)),
    "thread_in_metres": (_nedit("arc_deg = 180.0", "arc_deg = 180.0\nthread_length = 0.015"),
                         "[needles.ct1] thread_length:", ("unknown key",)),
    "arm_unknown_gripper": (NEEDLE_GOOD + ARM.replace("driver", "other"), "[arms] other:",
                            ("no gripper named 'other'", "driver")),
    "arm_min_above_max": (NEEDLE_GOOD + ARM + "min_insertion = 0.2\nmax_insertion = 0.1\n",
                          "[arms] driver:", ("must be below max_insertion",)),
    "arm_rcm_short": (NEEDLE_GOOD + ARM.replace("[0.0, -0.05, -0.02]", "[0.0, -0.05]"),
                      "[arms.driver] rcm[2]:", ("Field required",)),
    "arm_wrist_in_radians": (NEEDLE_GOOD + ARM + "max_wrist_pitch = 1.3\n",
                             "[arms.driver] max_wrist_pitch:", ("unknown key",)),
    "arm_wrist_too_far": (NEEDLE_GOOD + ARM + "max_wrist_yaw_deg = 200.0\n",
                          "[arms.driver] max_wrist_yaw_deg:", ("less than or equal to 180",)),
    "arm_old_cone_key": (NEEDLE_GOOD + ARM + "max_wrist_angle_deg = 75.0\n",
                         "[arms.driver] max_wrist_angle_deg:", ("unknown key",)),
    "arm_wrist_link_negative": (NEEDLE_GOOD + ARM + "yaw_to_tip = -0.001\n",
                                "[arms.driver] yaw_to_tip:", ("greater than or equal to 0",)),
}


@pytest.mark.parametrize("case", list(NEEDLE_BROKEN))
def test_broken_needle_scene_is_one_clear_error(tmp_path, case):
    """Issue 7 part 1 (bad input): a bad needle, pad or gripper key (unknown, out of
    bounds, a wire thicker than the needle's radius, an incision off the pad, a pose given
    neither or twice or not rigid, a name used twice) gives one ConfigError naming the
    file, the section and key, and the reason."""
    text, where, reasons = NEEDLE_BROKEN[case]
    _expect(_write(tmp_path, f"{case}.toml", text), where, *reasons)


# -- the needle cell's keys: thread and arms (issue 7, "What to build" items 1 and 4) -----
def test_needle_cell_example_values():
    """Items 1 and 4 (scene keys): needle_cell.toml holds the stereo endoscope, a pad, a
    CT-1 needle with a 15 mm thread (mm in the file, metres out) lying on the pad, two open
    grippers and an [arms.*] section for each; load_needle_cell builds the cell with that
    reach, and the needle keeps every arc point 8 mm from the incision."""
    path = CONFIG / "examples" / "needle_cell.toml"
    scene = load_scene(path)
    assert scene.rig.names == ("left", "right") and scene.rig.reference == "left"
    (nd,), (pad,) = scene.needles, scene.pads
    assert [g.name for g in scene.grippers] == ["left", "right"]
    assert nd.thread_length == pytest.approx(0.015) and nd.thread_diameter == pytest.approx(
        0.0004) and nd.thread_level == 45.0
    T_pad_needle = np.linalg.inv(pad.T_ref_pad) @ nd.T_ref_needle
    np.testing.assert_allclose(T_pad_needle[:3, 3], [0.004, -0.008, 0.0005], atol=1e-6)
    np.testing.assert_allclose(T_pad_needle[:3, 2], [0.0, 0.0, 1.0], atol=1e-5)
    arc = (nd.needle.points(100) @ T_pad_needle[:3, :3].T + T_pad_needle[:3, 3])[:, :2]
    assert (arc[:, 1].max() <= pad.incision[0][1] - 0.008)
    arms = load_arms(path)
    assert set(arms) == {"left", "right"}
    np.testing.assert_array_equal(arms["left"].rcm, [-0.05, 0.0, -0.015])
    assert arms["right"].max_insertion == 0.16
    assert arms["left"].max_wrist_pitch == pytest.approx(np.radians(80.0))
    assert arms["right"].max_wrist_yaw == pytest.approx(np.radians(80.0))
    cell = load_needle_cell(path)
    assert cell.grippers == ("left", "right")
    assert cell.arm_reach("right").max_insertion == 0.16
    for g in scene.grippers:
        assert cell.jaw_open(g.name)
        np.testing.assert_array_equal(cell.gripper_pose(g.name), g.T_ref_tool)


def test_needle_thread_and_arm_defaults(tmp_path):
    """Items 1 and 4 (scene keys): a needle without thread keys has no thread (and the
    documented diameter and level); an arm section with only its rcm gets the documented
    insertion and wrist defaults."""
    scene = load_scene(_write(tmp_path, "n.toml", NEEDLE_GOOD + ARM))
    nd = scene.needles[0]
    assert nd.thread_length == 0.0 and nd.thread_diameter == pytest.approx(0.0004)
    assert nd.thread_level == 45.0
    arm = load_arms(tmp_path / "n.toml")["driver"]
    assert (arm.min_insertion, arm.max_insertion) == (0.03, 0.2)
    assert arm.max_wrist_pitch == arm.max_wrist_yaw == pytest.approx(np.radians(80.0))
    assert (arm.pitch_to_yaw, arm.yaw_to_tip) == (0.0091, 0.0095)


def test_needle_cell_needs_its_objects_and_arms(tmp_path):
    """Item 4 (building a cell from TOML): a file without an [arms.*] section for a
    gripper, with two needles, or whose gripper starts out of its arm's reach gives one
    ConfigError naming the file and the section; reach= can supply the missing arm."""
    from oralnav.sim.world.needle_cell import ArmReach

    load = partial(expect_config_error, load_needle_cell)
    path = _write(tmp_path, "no_arm.toml", NEEDLE_GOOD)
    load(path, "[arms] driver:", "no [arms.<name>] section", "['driver']")
    far = ArmReach(rcm=np.array([0.0, 0.0, -0.05]), max_insertion=0.5)
    assert load_needle_cell(path, reach={"driver": far}).grippers == ("driver",)
    two = NEEDLE_GOOD + ARM + NEEDLE_GOOD[NEEDLE_GOOD.index("[needles.ct1]"):
                                          NEEDLE_GOOD.index("[grippers")].replace("ct1", "ct2")
    load(_write(tmp_path, "two.toml", two), ": needles:", "exactly one", "got 2")
    short = NEEDLE_GOOD + ARM + "max_insertion = 0.05\n"
    load(_write(tmp_path, "short.toml", short), ": arms:", "'driver' starts out of its arm's "
         "reach", "max_insertion")
