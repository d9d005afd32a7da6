"""Calibration files (issue 5 item 6): one file per kind, written atomically with its
provenance, validated on load (kind, cell, proper rotations, finite values, known units)
with errors naming file and key; a refused write keeps the previous file."""

from __future__ import annotations

import numpy as np
import pytest

from oralnav.config.calibration import (
    Calibration,
    SampleInfo,
    load_calibration,
    samples_digest,
    save_calibration,
)
from oralnav.config.errors import ConfigError
from oralnav.config.loader import dump_toml, read_toml
from oralnav.config.rig import load_rig
from oralnav.control.geometry import transform_from_euler
from tests.helpers import ROOT

T_B_C = transform_from_euler([0.59, -0.015, 0.21], [-90.0, 0.0, -90.0])
T_TCP_RM = transform_from_euler([-0.055, 0.08, 0.045], [10.0, 20.0, 30.0])


def _hand_eye(cell: str = "cell-a") -> Calibration:
    return Calibration(kind="hand_eye", cell=cell, method="refined from shah",
                       values={"T_B_C": T_B_C, "T_tcp_RM": T_TCP_RM},
                       samples=SampleInfo(24, samples_digest([T_B_C]), "sim"),
                       residuals={"translation_rms_mm": 0.05, "per_pose_mm": [0.04, 0.06]},
                       quality={"sigma_translation_mm": 0.02})


def test_round_trip_keeps_values_and_provenance(tmp_path):
    """What is saved loads back equal, with method, date, sample count and hash."""
    path = save_calibration(_hand_eye(), tmp_path / "hand_eye.toml")
    cal = load_calibration(path, kind="hand_eye", cell="cell-a")
    np.testing.assert_allclose(cal["T_B_C"], T_B_C, atol=1e-15)
    np.testing.assert_allclose(cal["T_tcp_RM"], T_TCP_RM, atol=1e-15)
    assert cal.method == "refined from shah" and cal.samples.count == 24
    assert cal.samples.sha256 == samples_digest([T_B_C])
    assert cal.created.endswith("Z") and cal.residuals["per_pose_mm"] == [0.04, 0.06]


def test_millimetre_files_are_converted_to_metres(tmp_path):
    """A file may declare units.length = "mm"; values come back in metres."""
    path = save_calibration(_hand_eye(), tmp_path / "he.toml")
    doc = read_toml(path)
    doc["units"]["length"] = "mm"
    for k in ("T_B_C", "T_tcp_RM"):
        for row in doc["values"][k][:3]:
            row[3] *= 1000.0
    (tmp_path / "mm.toml").write_text(dump_toml(doc))
    cal = load_calibration(tmp_path / "mm.toml")
    np.testing.assert_allclose(cal["T_B_C"], T_B_C, atol=1e-12)


def test_rig_kinds_nest_a_rig(tmp_path):
    """camera and stereo calibrations hold a rig in the shared rig format."""
    rig = load_rig(ROOT / "config" / "rigs" / "stereo.toml")
    cal = Calibration(kind="stereo", cell="cell-a", method="opencv stereoCalibrate",
                      values={"rig": rig}, samples=SampleInfo(20, "0" * 64))
    back = load_calibration(save_calibration(cal, tmp_path / "stereo.toml"))
    np.testing.assert_allclose(back["rig"]["right"].T_ref_cam, rig["right"].T_ref_cam)


def _edit(tmp_path, change) -> object:
    path = save_calibration(_hand_eye(), tmp_path / "he.toml")
    doc = read_toml(path)
    change(doc)
    bad = tmp_path / "bad.toml"
    bad.write_text(dump_toml(doc).replace("12345.5", "nan"))
    return bad


@pytest.mark.parametrize("change, key, match", [
    (lambda d: d["values"]["T_B_C"][0].__setitem__(0, 1.1), "[values] T_B_C",
     "not a proper rotation"),
    (lambda d: d["values"]["T_B_C"][0].__setitem__(3, 12345.5), "[values] T_B_C",
     "non-finite"),   # 12345.5 is written as nan below (TOML writers refuse nan)
    (lambda d: d["units"].__setitem__("length", "inch"), "[units] length", "unknown length unit"),
    (lambda d: d["values"].pop("T_tcp_RM"), "[values] T_tcp_RM", "missing"),
    (lambda d: d["values"].__setitem__("T_B_X", [[1.0]]), "[values] T_B_X", "unknown key"),
    (lambda d: d["values"].__setitem__("T_B_C", [[1.0, 0.0], [0.0, 1.0]]), "[values] T_B_C",
     "4x4"),
    (lambda d: d.__setitem__("kind", "wand"), "kind", "unknown calibration kind"),
    (lambda d: d.__setitem__("format", 9), "format", "not supported"),
    (lambda d: d["samples"].__setitem__("sha256", "xyz"), "[samples] sha256", "pattern"),
])
def test_invalid_files_name_file_and_key(tmp_path, change, key, match):
    """Bad input: each defect is refused, the message naming the file and the key."""
    bad = _edit(tmp_path, change)
    with pytest.raises(ConfigError, match=match) as exc:
        load_calibration(bad)
    assert str(bad) in str(exc.value) and key in str(exc.value)


def test_file_of_another_cell_is_refused(tmp_path):
    """Bad input: a calibration from another rig is refused, naming both cells."""
    path = save_calibration(_hand_eye("cell-b"), tmp_path / "he.toml")
    with pytest.raises(ConfigError, match="'cell-b'.*'cell-a'"):
        load_calibration(path, cell="cell-a")


def test_wrong_kind_is_refused(tmp_path):
    path = save_calibration(_hand_eye(), tmp_path / "he.toml")
    with pytest.raises(ConfigError, match="'hand_eye' calibration; a 'pivot' one"):
        load_calibration(path, kind="pivot")


def test_invalid_calibration_is_never_written_and_keeps_the_old_file(tmp_path):
    """Bad input: saving a non-rigid transform raises and the previous file is unchanged."""
    path = save_calibration(_hand_eye(), tmp_path / "he.toml")
    before = path.read_bytes()
    bad = _hand_eye()
    T = T_B_C.copy()
    T[:3, :3] *= 1.05
    bad = Calibration(kind=bad.kind, cell=bad.cell, method=bad.method,
                      values={"T_B_C": T, "T_tcp_RM": T_TCP_RM}, samples=bad.samples)
    with pytest.raises(ConfigError, match="T_B_C"):
        save_calibration(bad, path)
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["he.toml"]  # no temporary left
