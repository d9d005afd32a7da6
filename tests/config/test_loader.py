"""Tests of ``oralnav.config.loader`` and ``oralnav.config.errors``: reading TOML, validating
against the schemas, error locations, TOML writing and atomic writes.

Each test's docstring names the requirement it checks (Issue 2: configuration).
"""

from __future__ import annotations

import math
import os
import stat
import tomllib
from pathlib import Path
from typing import Annotated

import numpy as np
import pytest
from pydantic import Field

from oralnav.config.errors import ConfigError
from oralnav.config.loader import (
    Float,
    Int,
    Strict,
    atomic_write_text,
    build,
    dump_toml,
    load_file,
    read_toml,
    resolve,
    resolve_file,
    toml_value,
    validate,
)


class _Inner(Strict):
    size: tuple[Annotated[Int, Field(gt=0)], Annotated[Int, Field(gt=0)]]
    gain: Annotated[Float, Field(ge=0, le=1)] = 0.5


class _Doc(Strict):
    name: str
    items: dict[str, _Inner] = Field(default_factory=dict)


def _leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.endswith(".tmp"))


# -- ConfigError ---------------------------------------------------------------------------
def test_config_error_format_names_file_section_and_key():
    """Issue 2 (configuration): a ConfigError reads ``FILE: [section] key: reason``."""
    e = ConfigError("/etc/oralnav/rig.toml", "cameras.left.K", "K must be a 3x3 matrix")
    assert str(e) == "/etc/oralnav/rig.toml: [cameras.left] K: K must be a 3x3 matrix"
    assert (e.file, e.key, e.reason) == ("/etc/oralnav/rig.toml", "cameras.left.K",
                                         "K must be a 3x3 matrix")


def test_config_error_format_top_level_key_and_whole_file():
    """Issue 2 (configuration): a top-level key has no section; a whole-file problem
    (empty key) reads ``FILE: reason``."""
    assert str(ConfigError(Path("a/b.toml"), "reference", "bad")) == "a/b.toml: reference: bad"
    assert str(ConfigError("b.toml", "", "file not found")) == "b.toml: file not found"


# -- reading -------------------------------------------------------------------------------
def test_read_toml_missing_file_names_the_file(tmp_path):
    """Issue 2 (bad input): a missing file is one ConfigError naming the file."""
    path = tmp_path / "absent.toml"
    with pytest.raises(ConfigError) as ei:
        read_toml(path)
    assert str(ei.value) == f"{path}: file not found"


def test_read_toml_syntax_error_names_file_and_line(tmp_path):
    """Issue 2 (bad input): a TOML syntax error names the file and where it is."""
    path = tmp_path / "broken.toml"
    path.write_text('name = "x"\n[items.a]\nsize = [1, 2,, 3]\n')
    with pytest.raises(ConfigError) as ei:
        read_toml(path)
    msg = str(ei.value)
    assert msg.startswith(f"{path}: not valid TOML")
    assert "line 3" in msg


@pytest.mark.parametrize("text", ['name = "x"\n[items.a]\nsize = [1, 2',  # array cut
                                  'name = "x"\n[items', 'name = "x"\nsize = 1.'],
                         ids=["array", "table", "number"])
def test_read_toml_names_a_file_cut_short(tmp_path, text):
    """issue 30: a TOML file cut in the middle (the parse fails at its end, or on a last
    line without a line break) is called truncated, not only "not valid TOML"."""
    path = tmp_path / "cut.toml"
    path.write_text(text)
    with pytest.raises(ConfigError) as ei:
        read_toml(path)
    msg = str(ei.value)
    assert msg.startswith(f"{path}: not valid TOML") and "truncated" in msg, msg
    path.write_text('name = "x"\nsize = [1,, 2]\nmore = 1\n')  # an error mid-file is not
    with pytest.raises(ConfigError) as ei:
        read_toml(path)
    assert "truncated" not in str(ei.value)


def test_validate_missing_section_hints_a_cut_or_wrong_file():
    """issue 30: a required section that is missing (what a file cut short, or another kind
    of file, shows) says so; a missing plain key does not get the hint."""

    class _Sections(Strict):
        name: str
        inner: _Inner

    with pytest.raises(ConfigError) as ei:
        validate(_Sections, {"name": "x"}, "f.toml")
    assert str(ei.value) == ("f.toml: inner: Field required: the file has no [inner] "
                             "section; it may be cut short, or be another kind of file")
    with pytest.raises(ConfigError) as ei:
        validate(_Sections, {"inner": {"size": [1, 2]}}, "f.toml")
    assert str(ei.value) == "f.toml: name: Field required"


def test_load_file_names_the_key_that_referred_to_a_broken_file(tmp_path):
    """issue 30: a file named by another file's key that is broken as a whole (not TOML) is
    reported against the referring file and key too; an error at a key inside it is
    reported against that file and key as before."""
    base = tmp_path / "main.toml"
    (tmp_path / "notes.txt").write_text("just some notes\n")
    with pytest.raises(ConfigError) as ei:
        load_file(base, "refs.other", "notes.txt", read_toml)
    assert ei.value.file == str(base) and ei.value.key == "refs.other"
    assert str(ei.value).startswith(f"{base}: [refs] other: {tmp_path / 'notes.txt'}: "
                                    "not valid TOML")
    (tmp_path / "doc.toml").write_text('name = "x"\n[items.a]\nsize = [1, 0]\n')
    with pytest.raises(ConfigError) as ei:
        load_file(base, "refs.other", "doc.toml",
                  lambda p: validate(_Doc, read_toml(p), p))
    assert ei.value.file == str(tmp_path / "doc.toml") and ei.value.key == "items.a.size[1]"


def test_read_toml_not_utf8_names_the_file(tmp_path):
    """Issue 2 (bad input): a file that is not UTF-8 text is one ConfigError naming it."""
    path = tmp_path / "binary.toml"
    path.write_bytes(b'name = "\xff\xfe"\n')
    with pytest.raises(ConfigError, match="not UTF-8") as ei:
        read_toml(path)
    assert str(path) in str(ei.value)


def test_read_toml_folder_is_an_error(tmp_path):
    """Issue 2 (bad input): a folder given as a file is a ConfigError, not an OSError."""
    with pytest.raises(ConfigError, match="cannot read") as ei:
        read_toml(tmp_path)
    assert str(tmp_path) in str(ei.value)


# -- validation ----------------------------------------------------------------------------
def test_validate_unknown_key_names_file_section_and_key():
    """Issue 2 item (configuration): unknown keys are rejected naming file, section and key."""
    with pytest.raises(ConfigError) as ei:
        validate(_Doc, {"name": "x", "items": {"a": {"size": [1, 2], "gian": 0.1}}}, "f.toml")
    assert str(ei.value) == "f.toml: [items.a] gian: unknown key (check its spelling and section)"
    assert ei.value.key == "items.a.gian"


def test_validate_missing_key_names_it():
    """Issue 2 (bad input): a missing key is named with its section."""
    with pytest.raises(ConfigError) as ei:
        validate(_Doc, {"name": "x", "items": {"a": {}}}, "f.toml")
    assert str(ei.value).startswith("f.toml: [items.a] size: Field required")


def test_validate_bound_violation_names_key_bound_and_value():
    """Issue 2 (configuration): bounds are declared on the model; a value out of bounds is
    reported with the bound and the offending value."""
    with pytest.raises(ConfigError) as ei:
        validate(_Doc, {"name": "x", "items": {"a": {"size": [1, 2], "gain": 1.5}}}, "f.toml")
    msg = str(ei.value)
    assert msg.startswith("f.toml: [items.a] gain: ")
    assert "less than or equal to 1" in msg and "1.5" in msg


def test_validate_array_index_stays_on_its_key():
    """Issue 2 (configuration): an error inside an array names the key with its index
    (``[items.a] size[1]``), not a section made of the key."""
    with pytest.raises(ConfigError) as ei:
        validate(_Doc, {"name": "x", "items": {"a": {"size": [1, 0]}}}, "f.toml")
    assert str(ei.value).startswith("f.toml: [items.a] size[1]: ")
    assert "greater than 0" in str(ei.value)


@pytest.mark.parametrize("bad", ["0.5", True])
def test_validate_rejects_strings_and_booleans_as_numbers(bad):
    """Issue 2 (bad input: wrong types): a quoted number or a boolean is not a number."""
    with pytest.raises(ConfigError) as ei:
        validate(_Doc, {"name": "x", "items": {"a": {"size": [1, 2], "gain": bad}}}, "f.toml")
    assert str(ei.value).startswith("f.toml: [items.a] gain: Input should be a valid number")


@pytest.mark.parametrize("bad", [2.0, "2", False])
def test_validate_rejects_non_integers_for_integers(bad):
    """Issue 2 (bad input: wrong types): an integer key takes no float, string or bool."""
    with pytest.raises(ConfigError, match=r"\[items.a\] size\[0\]: Input should be a valid "
                                          "integer"):
        validate(_Doc, {"name": "x", "items": {"a": {"size": [bad, 2]}}}, "f.toml")


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_validate_rejects_non_finite_numbers(bad):
    """Issue 2 (configuration): TOML's nan and inf are not valid values."""
    with pytest.raises(ConfigError, match=r"\[items.a\] gain: Input should be a finite"):
        validate(_Doc, {"name": "x", "items": {"a": {"size": [1, 2], "gain": bad}}}, "f.toml")


def test_validate_int_accepted_for_float():
    """Issue 2 (configuration): an integer is a valid float (``rate_hz = 125``)."""
    doc = validate(_Doc, {"name": "x", "items": {"a": {"size": [1, 2], "gain": 1}}}, "f.toml")
    assert doc.items["a"].gain == 1.0 and isinstance(doc.items["a"].gain, float)


def test_validate_reports_every_problem_first_in_key():
    """Issue 2 (configuration): all problems are reported at once, the first in the key."""
    data = {"nme": "x", "items": {"a": {"size": [1, 2], "gain": 7}}}
    with pytest.raises(ConfigError) as ei:
        validate(_Doc, data, "f.toml")
    msg = str(ei.value)
    assert ei.value.key == "name"
    assert "\n  also nme: unknown key" in msg
    assert "\n  also items.a.gain:" in msg


def test_validated_models_are_frozen():
    """Issue 2 (configuration): validated once at start, then frozen."""
    doc = validate(_Doc, {"name": "x"}, "f.toml")
    with pytest.raises(ValueError, match="frozen"):
        doc.name = "y"


def test_build_turns_value_error_into_config_error():
    """Issue 2 (configuration): a ValueError raised while building objects from validated
    values becomes a ConfigError naming the file and key; other errors pass through."""
    def bad():
        raise ValueError("radius too small")

    with pytest.raises(ConfigError) as ei:
        build("f.toml", "fields.opener.surface.radius", bad)
    assert str(ei.value) == "f.toml: [fields.opener.surface] radius: radius too small"
    assert build("f.toml", "k", lambda: 3) == 3
    with pytest.raises(KeyError):
        build("f.toml", "k", lambda: {}["x"])


# -- paths ---------------------------------------------------------------------------------
def test_resolve_is_relative_to_the_naming_file_not_cwd(tmp_path, monkeypatch):
    """Issue 2 (configuration): paths inside a file are relative to that file's folder,
    whatever the working directory; absolute paths stay."""
    base = tmp_path / "etc" / "cfg.toml"
    monkeypatch.chdir(tmp_path)
    assert resolve(base, "rigs/r.toml") == tmp_path / "etc" / "rigs" / "r.toml"
    assert resolve("etc/cfg.toml", "r.toml") == tmp_path / "etc" / "r.toml"
    assert resolve(base, "/abs/r.toml") == Path("/abs/r.toml")


def test_resolve_file_missing_names_the_referring_file_and_key(tmp_path):
    """Issue 2 (bad input): a file named by another that does not exist is reported against
    the referring file and key, with the path looked for."""
    base = tmp_path / "cfg.toml"
    (tmp_path / "here.toml").write_text("")
    assert resolve_file(base, "cell.rig", "here.toml") == tmp_path / "here.toml"
    with pytest.raises(ConfigError) as ei:
        resolve_file(base, "cell.rig", "gone.toml")
    assert str(ei.value) == f"{base}: [cell] rig: file not found: {tmp_path / 'gone.toml'}"
    with pytest.raises(ConfigError, match="file not found"):
        resolve_file(base, "cell.rig", ".")  # a folder is not a file


# -- writing TOML --------------------------------------------------------------------------
@pytest.mark.parametrize("x", [0.1, 1 / 3, -0.0, 5e-324, 1e300, 2400.000000000001,
                               float(np.nextafter(1.0, 2.0))])
def test_toml_value_floats_round_trip_bit_exact(x):
    """Issue 2 (rig round trip): floats are written with enough digits to read back
    bit-exact, numpy scalars included."""
    for v in (x, np.float64(x)):
        back = tomllib.loads(f"v = {toml_value(v)}")["v"]
        assert np.float64(back).tobytes() == np.float64(x).tobytes()


def test_toml_value_rejects_non_finite_and_unknown_types():
    """Issue 2 (bad input: nothing written half): values TOML cannot hold are refused."""
    with pytest.raises(ValueError, match="non-finite"):
        toml_value(float("nan"))
    with pytest.raises(ValueError, match="non-finite"):
        toml_value(np.array([1.0, np.inf]))
    with pytest.raises(TypeError):
        toml_value(object())


def test_dump_toml_round_trips_nested_tables_odd_keys_and_strings():
    """Issue 2 (rig round trip): nested tables, keys that need quoting (``left cam``,
    ``a.b``), strings with quotes, backslashes and control characters and numpy values
    survive a write and a read."""
    doc = {"reference": 'le"ft\\ \n\t\x7f', "n": np.int64(3), "flag": True,
           "cameras": {"left cam": {"K": np.eye(3), "size": (4, 5)},
                       "a.b": {"dist": [0.1, -2.5e-7]}}}
    back = tomllib.loads(dump_toml(doc))
    assert back == {"reference": 'le"ft\\ \n\t\x7f', "n": 3, "flag": True,
                    "cameras": {"left cam": {"K": np.eye(3).tolist(), "size": [4, 5]},
                                "a.b": {"dist": [0.1, -2.5e-7]}}}


# -- atomic writes -------------------------------------------------------------------------
def test_atomic_write_text_writes_and_replaces(tmp_path):
    """Issue 2 (atomic writes): the new text replaces the old and no temp file remains."""
    path = tmp_path / "rig.toml"
    path.write_text("old\n")
    atomic_write_text(path, "new\n")
    assert path.read_text() == "new\n"
    assert _leftovers(tmp_path) == []


def test_atomic_write_text_failed_rename_keeps_old_file(tmp_path, monkeypatch):
    """Issue 2 (atomic writes): when the final rename fails the existing file is unchanged
    and the temporary file is removed."""
    path = tmp_path / "rig.toml"
    path.write_bytes(b"old contents\n")

    def boom(src, dst):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(OSError, match="No space"):
        atomic_write_text(path, "new contents\n")
    assert path.read_bytes() == b"old contents\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rig.toml"]


def test_atomic_write_text_failed_write_keeps_old_file(tmp_path, monkeypatch):
    """Issue 2 (atomic writes): a failure while writing (here fsync) leaves the old file and
    no temporary file."""
    path = tmp_path / "rig.toml"
    path.write_bytes(b"old\n")

    def boom(fd):
        raise OSError(5, "Input/output error")

    monkeypatch.setattr(os, "fsync", boom)
    with pytest.raises(OSError):
        atomic_write_text(path, "new\n")
    assert path.read_bytes() == b"old\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rig.toml"]


def test_atomic_write_text_missing_folder_creates_nothing(tmp_path):
    """Issue 2 (atomic writes): writing into a folder that does not exist fails clearly and
    creates nothing."""
    with pytest.raises(FileNotFoundError, match="does not exist"):
        atomic_write_text(tmp_path / "nope" / "rig.toml", "x")
    assert list(tmp_path.iterdir()) == []


def test_atomic_write_text_keeps_permissions(tmp_path):
    """Issue 2 (atomic writes): replacing a file keeps its permissions (a calibration file
    readable by the daemon's user stays readable); a new file is not private to the
    writer's temp-file mode."""
    path = tmp_path / "rig.toml"
    path.write_text("old")
    path.chmod(0o640)
    atomic_write_text(path, "new")
    assert stat.S_IMODE(path.stat().st_mode) == 0o640
    fresh = tmp_path / "fresh.toml"
    atomic_write_text(fresh, "x")
    assert stat.S_IMODE(fresh.stat().st_mode) & 0o044 == 0o044
