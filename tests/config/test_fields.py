"""Tests of ``oralnav.config.fields``: the marker-field file and points-surface CSVs.

Each test's docstring names the requirement it checks (Issue 2: configuration).
"""

from __future__ import annotations

from functools import partial
from pathlib import Path

import numpy as np
import pytest

from oralnav.config.errors import ConfigError
from oralnav.config.fields import load_fields
from oralnav.control.vision.markers import CylinderSurface, PlaneSurface, PointsSurface
from tests.config.helpers import edit, expect_config_error, write_file

CONFIG = Path(__file__).resolve().parents[2] / "config"
CELL = CONFIG / "fields" / "cell.toml"

ONE = """\
[fields.opener]
family = "charuco"
dictionary = "DICT_4X4_1000"
squares = [12, 9]
square = 0.003
marker = 0.0022
first_id = 0
[fields.opener.surface]
kind = "cylinder"
radius = 0.012
"""

SECOND = """
[fields.robot]
dictionary = "DICT_4X4_1000"
squares = [10, 7]
square = 0.005
marker = 0.0037
first_id = {first_id}
"""

POINTS = """\
[fields.jaw]
dictionary = "DICT_5X5_250"
squares = [4, 3]
square = 0.004
marker = 0.003
[fields.jaw.surface]
kind = "points"
file = "{file}"
"""


def _edit(old: str, new: str, text: str = ONE) -> str:
    return edit(old, new, text)


_write = write_file
_expect = partial(expect_config_error, load_fields)


# corner table of a 4x3 board (6 corners, ids 0..5): a gently bent sheet
TABLE = {0: (0.004, 0.004, 0.0), 1: (0.008, 0.004, 0.0005), 2: (0.012, 0.004, 0.0011),
         3: (0.004, 0.008, 0.0001), 4: (0.008, 0.008, 0.0006), 5: (0.0120000000000001, 0.008,
                                                                   -1.5e-5)}


def _csv(table=TABLE, header="corner_id,x,y,z") -> str:
    rows = [header] + [f"{i},{x!r},{y!r},{z!r}" for i, (x, y, z) in table.items()]
    return "\n".join(rows) + "\n"


# -- shipped file --------------------------------------------------------------------------
def test_shipped_cell_fields_load():
    """Issue 2 (every shipped file loads): config/fields/cell.toml gives the robot, effector
    and opener fields with the surfaces and id ranges its comments state."""
    fields = load_fields(CELL)
    assert sorted(fields) == ["effector", "opener", "robot"]
    robot, eff, opener = fields["robot"], fields["effector"], fields["opener"]
    assert isinstance(robot.surface, PlaneSurface)
    assert isinstance(eff.surface, CylinderSurface) and eff.surface.radius == 0.006
    assert isinstance(opener.surface, CylinderSurface) and opener.surface.radius == 0.012
    assert (robot.marker_ids[0], robot.marker_ids[-1]) == (0, 34)
    assert (eff.marker_ids[0], eff.marker_ids[-1]) == (100, 119)
    assert (opener.marker_ids[0], opener.marker_ids[-1]) == (200, 253)
    assert opener.squares == (12, 9) and opener.square == 0.003 and opener.marker == 0.0022
    ids = np.concatenate([f.marker_ids for f in fields.values()])
    assert len(np.unique(ids)) == len(ids)


def test_surface_defaults_to_plane_and_family_to_charuco(tmp_path):
    """Issue 2 (fields format): a field without a surface table is a plane; family defaults
    to charuco."""
    path = _write(tmp_path, "f.toml", SECOND.format(first_id=0))
    f = load_fields(path)["robot"]
    assert isinstance(f.surface, PlaneSurface) and f.family == "charuco"
    assert f.first_id == 0 and f.marker_count == 35


def test_fields_with_same_ids_in_different_dictionaries_load(tmp_path):
    """Issue 2 (shared ids): ids only clash within one dictionary; the same ids in two
    dictionaries are fine."""
    text = ONE + SECOND.format(first_id=0).replace("DICT_4X4_1000", "DICT_5X5_1000")
    fields = load_fields(_write(tmp_path, "f.toml", text))
    assert fields["opener"].marker_ids[0] == fields["robot"].marker_ids[0] == 0


def test_adjacent_id_ranges_load(tmp_path):
    """Issue 2 (shared ids): ranges that touch without overlapping (0..53, 54..88) load."""
    text = ONE + SECOND.format(first_id=54)
    fields = load_fields(_write(tmp_path, "f.toml", text))
    assert fields["robot"].marker_ids[0] == fields["opener"].marker_ids[-1] + 1


def test_ids_filling_the_dictionary_exactly_load(tmp_path):
    """Issue 2 (id overflow): the last id of the field may be the dictionary's last id."""
    f = load_fields(_write(tmp_path, "f.toml", _edit("first_id = 0", "first_id = 946")))
    assert f["opener"].marker_ids[-1] == 999


# -- bad input -----------------------------------------------------------------------------
def test_unknown_dictionary(tmp_path):
    """Issue 2 (bad input): a dictionary name OpenCV lacks is one error naming the file,
    [fields.opener] dictionary, and the names OpenCV has."""
    path = _write(tmp_path, "f.toml", _edit("DICT_4X4_1000", "DICT_4X4_5000"))
    _expect(path, "[fields.opener] dictionary:", "unknown ArUco dictionary 'DICT_4X4_5000'",
            "DICT_4X4_1000")


def test_ids_overflow_the_dictionary(tmp_path):
    """Issue 2 (bad input): ids that overflow the dictionary name [fields.opener] first_id,
    the id range and the dictionary's size."""
    path = _write(tmp_path, "f.toml", _edit("first_id = 0", "first_id = 947"))
    _expect(path, "[fields.opener] first_id:", "947..1000", "overflow DICT_4X4_1000",
            "0..999")


def test_board_too_big_for_small_dictionary(tmp_path):
    """Issue 2 (bad input): a board with more markers than the dictionary holds overflows
    even from id 0 (12x9 = 54 markers in DICT_4X4_50)."""
    path = _write(tmp_path, "f.toml", _edit("DICT_4X4_1000", "DICT_4X4_50"))
    _expect(path, "[fields.opener] first_id:", "overflow DICT_4X4_50")


def test_cylinder_radius_too_small_for_the_sheet(tmp_path):
    """Issue 2 (bad input): a cylinder radius too small for the sheet (it would wrap more
    than 360 deg) names [fields.opener.surface] radius and the smallest valid radius."""
    path = _write(tmp_path, "f.toml", _edit("radius = 0.012", "radius = 0.005"))
    _expect(path, "[fields.opener.surface] radius:", "too small for the sheet",
            "radius must be >= 0.005730")


def test_cylinder_radius_just_large_enough_loads(tmp_path):
    """Issue 2 (bounds): the radius check is a bound, not a tautology: a sheet wrapping just
    under 360 deg loads."""
    path = _write(tmp_path, "f.toml", _edit("radius = 0.012", "radius = 0.00573"))
    assert load_fields(path)["opener"].surface.radius == 0.00573


@pytest.mark.parametrize("first_id,overlap", [(0, "0..34"), (50, "50..53")])
def test_two_fields_sharing_marker_ids(tmp_path, first_id, overlap):
    """Issue 2 (bad input): two fields sharing marker ids of one dictionary name the second
    field's first_id, the shared ids and the other field."""
    path = _write(tmp_path, "f.toml", ONE + SECOND.format(first_id=first_id))
    _expect(path, "[fields.robot] first_id:", f"marker ids {overlap}", "'opener'",
            "must not share ids")


BROKEN = {
    # name: (file text, expected "[section] key" text, expected reason text)
    "syntax": (_edit('family = "charuco"', "family = charuco"), "not valid TOML", "line 2"),
    "unknown_key": (_edit("marker = 0.0022", "marker = 0.0022\nmarkr = 0.002"),
                    "[fields.opener] markr:", "unknown key"),
    "unknown_surface_key": (_edit("radius = 0.012", "radius = 0.012\nlength = 0.03"),
                            "[fields.opener.surface] length:", "unknown key"),
    "missing_dictionary": (_edit('dictionary = "DICT_4X4_1000"\n', ""),
                           "[fields.opener] dictionary:", "Field required"),
    "missing_square": (_edit("square = 0.003\n", ""), "[fields.opener] square:",
                       "Field required"),
    "no_fields": ("[fields]\n", ": fields:", "at least 1"),
    "square_string": (_edit("square = 0.003", 'square = "0.003"'), "[fields.opener] square:",
                      "valid number"),
    "square_nan": (_edit("square = 0.003", "square = nan"), "[fields.opener] square:",
                   "finite"),
    "square_too_big": (_edit("square = 0.003", "square = 3.0"), "[fields.opener] square:",
                       "less than or equal to 1"),
    "squares_float": (_edit("squares = [12, 9]", "squares = [12.0, 9]"),
                      "[fields.opener] squares[0]:", "valid integer"),
    "squares_too_few": (_edit("squares = [12, 9]", "squares = [12, 1]"),
                        "[fields.opener] squares[1]:", "greater than or equal to 2"),
    "first_id_negative": (_edit("first_id = 0", "first_id = -1"), "[fields.opener] first_id:",
                          "greater than or equal to 0"),
    "marker_not_smaller": (_edit("marker = 0.0022", "marker = 0.003"),
                           "[fields.opener] marker:", "smaller than square"),
    "family": (_edit('family = "charuco"', 'family = "apriltag"'), "[fields.opener] family:",
               "'charuco'"),
    "surface_kind": (_edit('kind = "cylinder"', 'kind = "sphere"'),
                     "[fields.opener.surface] kind:", "'plane', 'cylinder' or 'points'"),
    "cylinder_without_radius": (_edit("radius = 0.012\n", ""), "[fields.opener] surface:",
                                "cylinder surface needs radius"),
    "radius_on_plane": (_edit('kind = "cylinder"', 'kind = "plane"'),
                        "[fields.opener] surface:", "radius applies to cylinders only"),
    "points_without_file": (_edit('kind = "cylinder"\nradius = 0.012', 'kind = "points"'),
                            "[fields.opener] surface:", "points surface needs file"),
}


@pytest.mark.parametrize("case", list(BROKEN))
def test_broken_fields_file_is_one_clear_error(tmp_path, case):
    """Issue 2 (bad input): a malformed fields file (syntax error, unknown or missing keys,
    wrong types, values out of bounds, inconsistent surface keys) gives one ConfigError
    naming the file, the section and key, and the reason."""
    text, where, reason = BROKEN[case]
    _expect(_write(tmp_path, f"{case}.toml", text), where, reason)


def test_good_fields_template_loads(tmp_path):
    """Issue 2 (bad input tests are meaningful): the template the broken cases edit loads."""
    f = load_fields(_write(tmp_path, "f.toml", ONE))["opener"]
    assert f.surface.radius == 0.012 and f.marker_count == 54


# -- points surface ------------------------------------------------------------------------
def test_points_surface_loads_csv_relative_to_fields_file(tmp_path, monkeypatch):
    """Issue 2 (points surface): a corner_id,x,y,z CSV named relative to the fields file
    (not the working directory) loads into a field whose corners match the table, bit for
    bit, in corner-id order."""
    table = dict(reversed(list(TABLE.items())))  # file order must not matter
    _write(tmp_path, "cell/models/jaw.csv", _csv(table))
    path = _write(tmp_path, "cell/fields.toml", POINTS.format(file="models/jaw.csv"))
    monkeypatch.chdir(tmp_path)  # a cwd where models/jaw.csv does not exist
    f = load_fields(path)["jaw"]
    assert isinstance(f.surface, PointsSurface)
    assert f.surface.source == str((tmp_path / "cell" / "models" / "jaw.csv").resolve())
    np.testing.assert_array_equal(f.corner_ids, sorted(TABLE))
    expected = np.array([TABLE[i] for i in sorted(TABLE)])
    assert f.corners.tobytes() == expected.tobytes()
    assert not f.renderable


def test_points_surface_partial_table_and_absolute_path(tmp_path):
    """Issue 2 (points surface): a table may give only some corners (at least 4) and the
    fields file may name it by absolute path; a byte-order mark before the header and blank
    lines are accepted."""
    part = {k: TABLE[k] for k in (0, 2, 3, 5)}
    csv_path = tmp_path / "elsewhere" / "jaw.csv"
    _write(tmp_path, "elsewhere/jaw.csv", "\ufeff" + _csv(part) + "\n\n")
    f = load_fields(_write(tmp_path, "cfg/f.toml", POINTS.format(file=csv_path)))["jaw"]
    np.testing.assert_array_equal(f.corner_ids, [0, 2, 3, 5])
    np.testing.assert_array_equal(f.corners, [part[k] for k in (0, 2, 3, 5)])


def test_points_surface_csv_missing(tmp_path):
    """Issue 2 (bad input): a points surface whose CSV is missing names the fields file,
    [fields.jaw.surface] file and the path looked for."""
    path = _write(tmp_path, "f.toml", POINTS.format(file="models/jaw.csv"))
    _expect(path, "[fields.jaw.surface] file:", "file not found",
            str(tmp_path / "models" / "jaw.csv"))


CSV_BROKEN = {
    # name: (CSV text, expected location text, expected reason text)
    "header": (_csv(header="id,x,y,z"), ": ", "header corner_id,x,y,z"),
    "empty": ("", ": ", "header corner_id,x,y,z"),
    "not_a_number": (_csv().replace("0.008,0.004,0.0005", "0.008,abc,0.0005"), ": line 3:",
                     "not an id and three numbers"),
    "float_id": (_csv().replace("\n1,", "\n1.0,"), ": line 3:", "not an id and three numbers"),
    "columns": (_csv().replace(",0.0005\n", "\n"), ": line 3:", "expected 4 columns, got 3"),
    "nan": (_csv().replace(",0.0005\n", ",nan\n"), ": line 3:", "must be finite"),
    "duplicate": (_csv() + "1,0.0,0.0,0.0\n", ": line 8:", "corner 1 listed twice"),
}


@pytest.mark.parametrize("case", list(CSV_BROKEN))
def test_points_surface_csv_malformed(tmp_path, case):
    """Issue 2 (bad input): a malformed corner CSV is one ConfigError naming the CSV file,
    the line and what is wrong."""
    text, where, reason = CSV_BROKEN[case]
    csv_path = _write(tmp_path, "jaw.csv", text)
    path = _write(tmp_path, "f.toml", POINTS.format(file="jaw.csv"))
    with pytest.raises(ConfigError) as ei:
        load_fields(path)
    msg = str(ei.value)
    assert msg.startswith(f"{csv_path}{where}"), msg
    assert reason in msg, msg


def test_points_surface_csv_not_text(tmp_path):
    """Issue 2 (bad input): a corner table that is not UTF-8 text is a ConfigError naming
    it, not a UnicodeDecodeError."""
    csv_path = tmp_path / "jaw.csv"
    csv_path.write_bytes(b"corner_id,x,y,z\n0,\xff\xfe,0,0\n")
    path = _write(tmp_path, "f.toml", POINTS.format(file="jaw.csv"))
    with pytest.raises(ConfigError, match="not a UTF-8 CSV") as ei:
        load_fields(path)
    assert str(ei.value).startswith(str(csv_path))


@pytest.mark.parametrize("table,reason", [
    ({**TABLE, 6: (0.0, 0.0, 0.0)}, "corner ids [6] are outside 0..5"),
    ({k: TABLE[k] for k in (0, 1, 2)}, "at least 4 corners, got 3"),
], ids=["id_outside_board", "too_few"])
def test_points_surface_table_does_not_fit_board(tmp_path, table, reason):
    """Issue 2 (bad input): a well-formed table whose corners do not fit the board names
    the fields file, [fields.jaw.surface] file, the CSV and the problem."""
    _write(tmp_path, "jaw.csv", _csv(table))
    path = _write(tmp_path, "f.toml", POINTS.format(file="jaw.csv"))
    _expect(path, "[fields.jaw.surface] file:", "jaw.csv", reason)


def test_missing_fields_file(tmp_path):
    """Issue 2 (bad input): a missing fields file is a ConfigError naming it."""
    with pytest.raises(ConfigError, match="file not found") as ei:
        load_fields(tmp_path / "nope.toml")
    assert "nope.toml" in str(ei.value)


# -- calibration targets (issue 34) ----------------------------------------------------------
TARGETS = """\
[fields.cb]
family = "chessboard"
inner_corners = [9, 6]
square = 0.025

[fields.dots]
family = "circles"
grid = [7, 5]
spacing = 0.03

[fields.acircles]
family = "asymmetric_circles"
grid = [4, 11]
spacing = 0.015

[fields.grid]
family = "aruco_grid"
dictionary = "DICT_6X6_250"
markers = [5, 7]
marker = 0.04
separation = 0.01
first_id = 3
"""

OWN = """\
[fields.own]
family = "aruco_grid"
dictionary_file = "{file}"
markers = [5, 7]
marker = 0.033
separation = 0.0066
"""


def _dictionary_file(folder: Path, name: str = "gboriginal.yml", n: int = 40) -> Path:
    """A custom dictionary written by OpenCV itself (writeDictionary), as users have them."""
    import cv2

    dic = cv2.aruco.extendDictionary(n, 5, randomSeed=3)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / name
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    dic.writeDictionary(fs)
    fs.release()
    return path


def test_every_target_family_loads_for_calibration(tmp_path):
    """Issue 34 item 1 (fields file): chessboard, circles, asymmetric_circles and
    aruco_grid entries load as calibration targets with their sizes, point counts and
    positions (metres); a ChArUco field in the same file stays the tracker's field."""
    from oralnav.config.fields import load_targets
    from oralnav.control.calibration.targets import ArucoGrid, Chessboard, CircleGrid

    t = load_targets(_write(tmp_path, "t.toml", TARGETS + "\n" + SECOND.format(first_id=0)))
    cb, dots, ac, grid = t["cb"], t["dots"], t["acircles"], t["grid"]
    assert isinstance(cb, Chessboard) and cb.corner_count == 54
    np.testing.assert_allclose(cb.corners[10], [0.025, 0.025, 0.0])
    assert isinstance(dots, CircleGrid) and dots.family == "circles" and dots.corner_count == 35
    assert isinstance(ac, CircleGrid) and ac.family == "asymmetric_circles"
    np.testing.assert_allclose(ac.corners[5], [0.045, 0.015, 0.0])   # row 1, column 1
    assert isinstance(grid, ArucoGrid) and grid.corner_count == 140
    assert list(grid.board.getIds().ravel()[:2]) == [3, 4]
    assert t["robot"].family == "charuco" and type(t["robot"]).__name__ == "MarkerField"


def test_tracking_refuses_calibration_targets(tmp_path):
    """Issue 34 item 1 (kept apart): loading a file for tracking that holds a calibration
    target is one error at that entry's family key, saying the tracker follows charuco
    fields; the tracker's own fields load as before."""
    path = _write(tmp_path, "t.toml", SECOND.format(first_id=0) + "\n" + TARGETS)
    _expect(path, "[fields.cb] family:", "calibration target only", "charuco")


def test_custom_dictionary_file_loads_relative_to_the_fields_file(tmp_path, monkeypatch):
    """Issue 34 item 2: an aruco_grid entry's dictionary_file, OpenCV's dictionary YAML as
    writeDictionary writes it, named relative to the fields file, gives the board OpenCV's
    readDictionary gives (same codes); tracking refuses such an entry at its key."""
    import cv2

    from oralnav.config.fields import load_targets

    yml = _dictionary_file(tmp_path / "cal")
    path = _write(tmp_path, "cal/f.toml", OWN.format(file="gboriginal.yml"))
    monkeypatch.chdir(tmp_path)
    grid = load_targets(path)["own"]
    ref = cv2.aruco.Dictionary()
    fs = cv2.FileStorage(str(yml), cv2.FILE_STORAGE_READ)
    assert ref.readDictionary(fs.root())
    np.testing.assert_array_equal(grid.board.getDictionary().bytesList, ref.bytesList)
    assert grid.dictionary == "gboriginal.yml"
    charuco = OWN.replace('"aruco_grid"', '"charuco"').replace(
        "markers = [5, 7]", "squares = [9, 7]").replace("separation = 0.0066", "square = 0.045")
    tracked = _write(tmp_path, "cal/c.toml", charuco.format(file="gboriginal.yml"))
    board = load_targets(tracked)["own"]
    assert board.family == "charuco" and board.corner_count == 48
    _expect(path, "[fields.own] family:", "calibration target only")
    _expect(tracked, "[fields.own] dictionary_file:", "calibration only")


def _load_targets(path: Path):
    from oralnav.config.fields import load_targets

    return load_targets(path)


_expect_target = partial(expect_config_error, _load_targets)


@pytest.mark.parametrize("content,where,reason", [
    (None, "[fields.own] dictionary_file:", "file not found"),
    ("not: [a, dictionary\n", "[fields.own] dictionary_file:", "not an OpenCV dictionary"),
    ("%YAML:1.0\n---\nmarkersize: 5\n", "nmarkers:", "missing"),
    ("%YAML:1.0\n---\nnmarkers: 1\nmarkersize: 5\nmarker_0: \"0101\"\n", "marker_0:",
     "a string of 25 bits"),
    ("%YAML:1.0\n---\nnmarkers: 2\nmarkersize: 2\nmarker_0: \"0110\"\n", "marker_1:",
     "a string of 4 bits"),
    ("%YAML:1.0\n---\nnmarkers: 1\nmarkersize: 1.5\nmarker_0: \"0\"\n", "markersize:",
     "whole number"),
], ids=["missing", "not_yaml", "no_nmarkers", "short_marker", "missing_marker", "size"])
def test_bad_dictionary_file_is_named(tmp_path, content, where, reason):
    """Issue 34 item 2 (bad input): a missing or malformed dictionary file is one
    ConfigError naming the fields file and its dictionary_file key, or the dictionary file
    and its key, and what is wrong (OpenCV's own reader would take a short marker silently)."""
    if content is not None:
        _write(tmp_path, "own.yml", content)
    path = _write(tmp_path, "f.toml", OWN.format(file="own.yml"))
    with pytest.raises(ConfigError) as ei:
        _load_targets(path)
    msg = str(ei.value)
    assert where in msg and reason in msg, msg
    assert "own.yml" in msg and "\n" not in msg


TARGET_BROKEN = {
    # name: (file text, expected "[section] key" text, expected reason text)
    "family": (TARGETS.replace('"chessboard"', '"chessbord"'), "[fields.cb] family:",
               "'chessboard'"),
    "missing_corners": (TARGETS.replace("inner_corners = [9, 6]\n", ""),
                        "[fields.cb] inner_corners:", "Field required"),
    "corners_too_few": (TARGETS.replace("[9, 6]", "[9, 2]"), "[fields.cb] inner_corners[1]:",
                        "greater than or equal to 3"),
    "foreign_key": (TARGETS.replace("square = 0.025\n", "square = 0.025\nmarker = 0.01\n", 1),
                    "[fields.cb] marker:", "does not apply to a chessboard entry"),
    "surface_on_target": (TARGETS.replace("spacing = 0.03\n",
                                          'spacing = 0.03\nsurface = {kind = "plane"}\n'),
                          "[fields.dots] surface:", "does not apply to a circles entry"),
    "spacing_negative": (TARGETS.replace("spacing = 0.03", "spacing = -0.03"),
                         "[fields.dots] spacing:", "greater than 0"),
    "grid_no_dictionary": (TARGETS.replace('dictionary = "DICT_6X6_250"\n', ""),
                           "[fields.grid] dictionary:", "Field required"),
    "grid_both_dictionaries": (TARGETS.replace('dictionary = "DICT_6X6_250"\n',
                                               'dictionary = "DICT_6X6_250"\n'
                                               'dictionary_file = "x.yml"\n'),
                               "[fields.grid] dictionary_file:", "not both"),
    "grid_overflow": (TARGETS.replace("first_id = 3", "first_id = 220"),
                      "[fields.grid] first_id:", "overflow DICT_6X6_250"),
    "grid_one_marker": (TARGETS.replace("markers = [5, 7]", "markers = [1, 1]"),
                        "[fields.grid] markers:", "at least 2 markers"),
}


@pytest.mark.parametrize("case", list(TARGET_BROKEN))
def test_broken_target_entry_is_one_clear_error(tmp_path, case):
    """Issue 34 item 1 (bad input): a malformed calibration-target entry (unknown family,
    missing or foreign keys, bounds, dictionary problems) gives one ConfigError naming the
    file, the section and key, and the reason."""
    text, where, reason = TARGET_BROKEN[case]
    _expect_target(_write(tmp_path, f"{case}.toml", text), where, reason)
