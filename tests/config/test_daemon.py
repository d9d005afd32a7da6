"""Tests of ``oralnav.config.daemon``: the daemon configuration and the shipped defaults.

Each test's docstring names the requirement it checks (Issue 2: configuration).
"""

from __future__ import annotations

from functools import partial
from pathlib import Path

import pytest
from pydantic import ValidationError

from oralnav.config.daemon import (
    ISO_REDUCED_SPEED,
    DaemonConfig,
    default_config_path,
    load_config,
)
from oralnav.config.errors import ConfigError
from tests.config.helpers import edit, expect_config_error, write_file

CONFIG = Path(__file__).resolve().parents[2] / "config"
SIM = CONFIG / "sim.toml"
HARDWARE = CONFIG / "hardware.example.toml"

GOOD = f"""\
name = "test-cell"

[cell]
backend = "sim"
rig = "{CONFIG}/rigs/stereo.toml"
endoscope_rig = "{CONFIG}/rigs/endoscope.toml"
fields = "{CONFIG}/fields/cell.toml"
scene = "{CONFIG}/examples/stereo_cell.toml"

[control]
rate_hz = 500.0

[safety]
max_speed = 0.25
near_patient_speed = 0.05
stale_pose = 0.1

[api]
host = "127.0.0.1"
port = 8750
"""


def _edit(old: str, new: str, text: str = GOOD) -> str:
    return edit(old, new, text)


#: GOOD as a hardware cell (the simulated cell drives only simulated devices)
HW = _edit('backend = "sim"', 'backend = "hardware"')


_write = write_file
_expect = partial(expect_config_error, load_config)


# -- shipped files -------------------------------------------------------------------------
def test_default_config_is_the_embedded_sim_toml():
    """Issue 2 (every shipped file loads): load_config() with no path loads the embedded
    simulation default, config/sim.toml, and every file it names."""
    cfg = load_config()
    assert isinstance(cfg, DaemonConfig)
    assert cfg.path == default_config_path()
    assert cfg.path.name == "sim.toml"
    assert cfg.path.read_bytes() == SIM.read_bytes()
    s = cfg.settings
    assert s.name == "oralnav-sim" and s.cell.backend == "sim"
    assert cfg.rig.names == ("left", "right")
    assert cfg.endoscope_rig is not None and cfg.endoscope_rig.names == ("endoscope",)
    assert sorted(cfg.fields) == ["effector", "opener", "robot"]
    assert cfg.scene_path is not None and cfg.scene_path.name == "stereo_cell.toml"
    assert cfg.scene is not None and cfg.scene.source == str(cfg.scene_path)
    assert s.safety.max_speed <= ISO_REDUCED_SPEED
    assert s.safety.near_patient_speed <= s.safety.max_speed
    assert (s.api.host, s.api.port, s.control.rate_hz) == ("127.0.0.1", 8750, 500.0)


def test_hardware_template_loads_from_any_cwd(tmp_path, monkeypatch):
    """Issue 2 (every shipped file loads): config/hardware.example.toml loads, its paths
    resolved against its own folder whatever the working directory."""
    monkeypatch.chdir(tmp_path)
    cfg = load_config(HARDWARE)
    s = cfg.settings
    assert s.cell.backend == "hardware" and s.cell.scene is None
    assert cfg.scene_path is None and cfg.scene is None
    assert cfg.rig.names == ("left", "right") and cfg.endoscope_rig is not None
    assert (s.safety.max_speed, s.safety.near_patient_speed) == (0.20, 0.03)


def test_relative_config_path_from_repository_cwd(monkeypatch):
    """Issue 2 (every shipped file loads): load_config("config/hardware.example.toml") as the
    issue writes it works from the repository root."""
    monkeypatch.chdir(CONFIG.parent)
    cfg = load_config("config/hardware.example.toml")
    assert cfg.settings.cell.backend == "hardware"


def test_settings_are_frozen():
    """Issue 2 (configuration): validated once at start, then frozen."""
    cfg = load_config()
    with pytest.raises(ValidationError, match="frozen"):
        cfg.settings.safety.max_speed = 1.0
    with pytest.raises(AttributeError):
        cfg.rig = None


def test_good_config_template_loads_with_defaults(tmp_path):
    """Issue 2 (bad input tests are meaningful): the template the broken cases edit loads;
    omitted sections take their defaults."""
    cfg = load_config(_write(tmp_path, "c.toml", GOOD))
    assert cfg.settings.name == "test-cell"
    text = GOOD.split("[control]")[0]
    cfg = load_config(_write(tmp_path, "bare.toml", text))
    s = cfg.settings
    assert (s.control.rate_hz, s.safety.max_speed, s.safety.near_patient_speed,
            s.api.port) == (500.0, 0.25, 0.05, 8750)


@pytest.mark.parametrize("speed", ["0.25", "0.05"])
def test_speed_bounds_are_inclusive(tmp_path, speed):
    """Issue 2 (safety bounds): max_speed may equal the ISO 10218 reduced speed and
    near_patient_speed may equal max_speed."""
    text = _edit("max_speed = 0.25", f"max_speed = {speed}")
    cfg = load_config(_write(tmp_path, "c.toml", text))
    assert cfg.settings.safety.max_speed == float(speed)
    assert cfg.settings.safety.near_patient_speed == 0.05


def test_hardware_backend_needs_no_scene(tmp_path):
    """Issue 2 (configuration): only the sim backend needs a scene."""
    text = _edit('backend = "sim"', 'backend = "hardware"')
    text = _edit(f'scene = "{CONFIG}/examples/stereo_cell.toml"\n', "", text)
    assert load_config(_write(tmp_path, "c.toml", text)).scene_path is None


def test_serial_inputs_section_gives_the_driver_its_options(tmp_path):
    """Issue 8 (configuration): [inputs] backend = "serial" passes port, baudrate and the
    heartbeat settings to the serial backend; the default is the simulated buttons."""
    assert load_config(_write(tmp_path, "a.toml", GOOD)).settings.inputs.backend == "sim"
    text = GOOD + '\n[inputs]\nbackend = "serial"\nport = "/dev/ttyUSB0"\nbaudrate = 57600\n'
    ins = load_config(_write(tmp_path, "b.toml", text)).settings.inputs
    assert ins.driver_options() == {"port": "/dev/ttyUSB0", "baudrate": 57600,
                                    "heartbeat_timeout": 0.1, "recover_lines": 3,
                                    "connect_timeout": 2.0}


def test_effector_section_gives_the_drive_backend_its_options(tmp_path):
    """Issue 8 (configuration): [effector] with [effector.canopen] gives the CANopen backend
    the configured coupling, pretension, limits and bus settings; the default is the
    simulated wrist."""
    assert load_config(_write(tmp_path, "a.toml", GOOD)).settings.effector.backend == "sim"
    text = HW + """
[effector]
backend = "canopen"
coupling = [[1.0, 0, 0, 0], [0, 1.5, 0, 0], [0, 0.5, 1.0, 0], [0, 0.5, 0, 1.0]]
pretension = [0.0, 0.1, 0.05, 0.05]
motor_min = [-10, -10, -10, -10]
motor_max = [10, 10, 10, 10]

[effector.canopen]
channel = "can1"
node_ids = [11, 12, 13, 14]
mode = "pp"
"""
    cfg = load_config(_write(tmp_path, "b.toml", text))
    opts = cfg.settings.effector.driver_options(cfg.path.parent)
    assert opts["kinematics"].coupling[1, 1] == 1.5
    assert opts["pretension"] == [0.0, 0.1, 0.05, 0.05]
    assert (opts["channel"], opts["node_ids"], opts["mode"]) == ("can1", (11, 12, 13, 14), "pp")
    from oralnav.drivers.effector import open_effector

    eff = open_effector("canopen", **opts)  # the backend accepts them as they are
    assert eff.node_ids == (11, 12, 13, 14)


# -- bad input -----------------------------------------------------------------------------
BROKEN = {
    # name: (file text, expected "[section] key" text, expected reason texts)
    "max_speed_above_iso": (_edit("max_speed = 0.25", "max_speed = 0.3"),
                            "[safety] max_speed:", ("exceeds the ISO 10218 reduced speed",
                                                    "0.25 m/s")),
    "near_speed_above_iso": (_edit("near_patient_speed = 0.05", "near_patient_speed = 0.26"),
                             "[safety] near_patient_speed:", ("ISO 10218",)),
    "near_above_max": (_edit("max_speed = 0.25", "max_speed = 0.04"),
                       "[safety] near_patient_speed:", ("must not exceed max_speed",)),
    "max_speed_zero": (_edit("max_speed = 0.25", "max_speed = 0.0"), "[safety] max_speed:",
                       ("greater than 0",)),
    "max_speed_string": (_edit("max_speed = 0.25", 'max_speed = "0.2"'),
                         "[safety] max_speed:", ("valid number",)),
    "stale_pose_bound": (_edit("stale_pose = 0.1", "stale_pose = 2.0"),
                         "[safety] stale_pose:", ("less than or equal to 1",)),
    "sim_without_scene": (_edit(f'scene = "{CONFIG}/examples/stereo_cell.toml"\n', ""),
                          "[cell] scene:", ("sim backend needs scene",)),
    "backend_unknown": (_edit('backend = "sim"', 'backend = "real"'), "[cell] backend:",
                        ("'sim' or 'hardware'",)),
    "missing_rig": (_edit(f'rig = "{CONFIG}/rigs/stereo.toml"\n', ""), "[cell] rig:",
                    ("Field required",)),
    "missing_cell": (GOOD.split("[cell]")[0], ": cell:", ("Field required",)),
    "unknown_key": (_edit("stale_pose = 0.1", "stale_pose = 0.1\nmax_force = 5.0"),
                    "[safety] max_force:", ("unknown key",)),
    "unknown_section": (GOOD + "\n[robot]\nip = \"10.0.0.2\"\n", ": robot:", ("unknown key",)),
    "port_string": (_edit("port = 8750", 'port = "8750"'), "[api] port:", ("valid integer",)),
    "port_bound": (_edit("port = 8750", "port = 70000"), "[api] port:",
                   ("less than or equal to 65535",)),
    "rate_bound": (_edit("rate_hz = 500.0", "rate_hz = 5000.0"), "[control] rate_hz:",
                   ("less than or equal to 1000",)),
    "syntax": (_edit("[safety]", "[safety"), "not valid TOML", ("line 13",)),
    "rig_file_missing": (_edit(f"{CONFIG}/rigs/stereo.toml", "rigs/none.toml"), "[cell] rig:",
                         ("file not found", "none.toml")),
    "endoscope_rig_missing": (_edit(f"{CONFIG}/rigs/endoscope.toml", "none.toml"),
                              "[cell] endoscope_rig:", ("file not found",)),
    "fields_file_missing": (_edit(f"{CONFIG}/fields/cell.toml", "none.toml"), "[cell] fields:",
                            ("file not found",)),
    "scene_file_missing": (_edit(f"{CONFIG}/examples/stereo_cell.toml", "none.toml"),
                           "[cell] scene:", ("file not found",)),
    "serial_inputs_without_port": (GOOD + '\n[inputs]\nbackend = "serial"\n',
                                   "[inputs] port:", ("serial backend needs port",)),
    "inputs_backend_unknown": (GOOD + '\n[inputs]\nbackend = "usb"\n', "[inputs] backend:",
                               ("'sim' or 'serial'",)),
    "effector_canopen_without_section": (HW + '\n[effector]\nbackend = "canopen"\n',
                                         ": effector:", ("needs an [effector.canopen]",)),
    "effector_singular_coupling": (GOOD + "\n[effector]\ncoupling = [[1, 0, 0, 0], "
                                   "[0, 1, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]]\n",
                                   ": effector:", ("condition number",)),
    "effector_pretension_degrees": (GOOD + "\n[effector]\npretension = [5, 5, 5, 5]\n",
                                    ": effector:", ("degrees?",)),
    "effector_modbus_tcp_without_host": (
        HW + '\n[effector]\nbackend = "modbus"\n[effector.modbus]\nport = 502\n',
        "[effector] modbus", ("Modbus TCP needs host",)),
    "effector_canopen_host_id_clash": (
        HW + '\n[effector]\nbackend = "canopen"\n[effector.canopen]\nhost_node_id = 3\n',
        "[effector] canopen", ("is a drive's node id",)),
    "effector_eds_missing": (
        HW + '\n[effector]\nbackend = "canopen"\n[effector.canopen]\neds = "none.eds"\n',
        "[effector.canopen] eds:", ("file not found",)),
    "arm_ur_without_section": (_edit('backend = "sim"', 'backend = "hardware"')
                               + '\n[arm]\nbackend = "ur"\n', ": arm:",
                               ("needs an [arm.ur]",)),
    "arm_ur_lookahead_bound": (_edit('backend = "sim"', 'backend = "hardware"')
                               + '\n[arm]\nbackend = "ur"\n[arm.ur]\nhost = "10.0.0.2"\n'
                               "lookahead_time = 0.5\n", "[arm.ur] lookahead_time:",
                               ("less than or equal to 0.2",)),
    "sim_cell_with_real_arm": (GOOD + '\n[arm]\nbackend = "ur"\n[arm.ur]\nhost = "x"\n',
                               ": the simulated cell", ("drives the simulated arm",
                                                 "[arm] backend = 'ur'")),
    "camera_not_in_the_rigs": (HW + '\n[cameras.middle]\nbackend = "v4l2"\n'
                               'device = "/dev/video0"\n', "[cameras] middle:",
                               ("no camera 'middle' in the rigs", "left, right",
                                'role = "monitor"')),
    "monitor_camera_with_a_rig_name": (HW + '\n[cameras.left]\nbackend = "v4l2"\n'
                                       'device = "/dev/video0"\nrole = "monitor"\n',
                                       "[cameras.left] role:",
                                       ("a camera of the rigs",)),
    "camera_option_unknown": (HW + '\n[cameras.endoscope]\nbackend = "v4l2"\n'
                              'device = "/dev/video0"\nzoom = 3\n', "[cameras] endoscope:",
                              ("the v4l2 backend does not take", "zoom")),
    "camera_backend_unknown": (HW + '\n[cameras.left]\nbackend = "gige"\n',
                               "[cameras.left] backend:", ("'aravis', 'v4l2' or 'replay'",)),
    "sim_cell_with_cameras": (GOOD + '\n[cameras.left]\nbackend = "replay"\npath = "x"\n',
                              ": the simulated cell", ("[cameras.left]",)),
    "inputs_heartbeat_bound": (GOOD + '\n[inputs]\nbackend = "serial"\nport = "/dev/x"\n'
                               "heartbeat_timeout = 5.0\n", "[inputs] heartbeat_timeout:",
                               ("less than or equal to 1",)),
}


@pytest.mark.parametrize("case", list(BROKEN))
def test_broken_daemon_config_is_one_clear_error(tmp_path, case):
    """Issue 2 (bad input): a broken daemon configuration (speeds above the ISO 10218
    reduced speed of 0.25 m/s, near_patient_speed above max_speed, the sim backend without
    a scene, wrong types, unknown keys, bounds, missing files) gives one ConfigError naming
    the file, the section and key, and the reason, and starts nothing."""
    text, where, reasons = BROKEN[case]
    _expect(_write(tmp_path, f"{case}.toml", text), where, *reasons)


def test_broken_scene_is_caught_at_start(tmp_path):
    """Issue 2 (never half-starts): load_config validates the scene the sim backend will
    render, so a broken scene fails the configuration check, naming the scene file and key,
    before the daemon starts anything."""
    scene = _write(tmp_path, "scene.toml", (CONFIG / "examples" / "stereo_cell.toml")
                   .read_text().replace('field = "opener"', 'field = "jaw"')
                   .replace('"../', f'"{CONFIG}/'))
    path = _write(tmp_path, "c.toml", _edit(f"{CONFIG}/examples/stereo_cell.toml", str(scene)))
    with pytest.raises(ConfigError) as ei:
        load_config(path)
    assert str(ei.value).startswith(f"{scene}: [placements.opener] field: unknown field 'jaw'")


def test_broken_rig_is_reported_against_the_rig_file(tmp_path):
    """Issue 2 (bad input): an error in the rig the configuration names is reported against
    the rig file and its key."""
    rig = _write(tmp_path, "rig.toml", (CONFIG / "rigs" / "stereo.toml").read_text()
                 .replace("[[2395.0, 0.0,", "[[2395.0, 0.5,"))
    path = _write(tmp_path, "c.toml", _edit(f"{CONFIG}/rigs/stereo.toml", str(rig)))
    with pytest.raises(ConfigError) as ei:
        load_config(path)
    assert str(ei.value).startswith(f"{rig}: [cameras.right] K: ")
    assert "no skew" in str(ei.value)


def test_missing_config_file(tmp_path):
    """Issue 2 (bad input): a missing configuration file is a ConfigError naming it."""
    with pytest.raises(ConfigError) as ei:
        load_config(tmp_path / "oralnav.toml")
    assert str(ei.value) == f"{tmp_path / 'oralnav.toml'}: file not found"


# -- [calibration] (issue 5 item 6) ---------------------------------------------------------
def _calibration_files(folder: Path, cell: str = "test-cell") -> dict[str, Path]:
    import numpy as np

    from oralnav.config.calibration import Calibration, SampleInfo, save_calibration

    out = {}
    for kind, key in (("hand_eye", None), ("endoscope_opener", "T_OM_En"),
                      ("effector_zero", "T_RM_E0"), ("effector_marker", "T_EM_E")):
        values = {"T_B_C": np.eye(4), "T_tcp_RM": np.eye(4)} if key is None \
            else {key: np.eye(4)}
        out[kind] = save_calibration(Calibration(kind, cell, "test", values,
                                                 SampleInfo(3, "0" * 64)),
                                     folder / f"{kind}.toml")
    return out


def test_calibration_files_load_by_path_from_the_configuration(tmp_path):
    """Issue 5 item 6: the daemon loads each calibration file named in [calibration],
    checked against the section's cell."""
    files = _calibration_files(tmp_path)
    text = GOOD + '\n[calibration]\ncell = "test-cell"\n' + "".join(
        f'{k} = "{p}"\n' for k, p in files.items())
    cfg = load_config(_write(tmp_path, "oralnav.toml", text))
    assert sorted(cfg.calibrations) == sorted(files)
    assert cfg.missing_calibrations() == []
    assert load_config(_write(tmp_path, "oralnav.toml", GOOD)).missing_calibrations() == [
        "hand_eye", "endoscope_opener", "effector_zero", "effector_marker"]


def test_calibration_of_another_cell_is_refused_at_load(tmp_path):
    """Issue 5, bad input: a calibration file from another cell stops the daemon at load,
    naming that file and its cell key."""
    files = _calibration_files(tmp_path, cell="other-cell")
    text = GOOD + f'\n[calibration]\ncell = "test-cell"\nhand_eye = "{files["hand_eye"]}"\n'
    with pytest.raises(ConfigError, match="another cell") as exc:
        load_config(_write(tmp_path, "oralnav.toml", text))
    assert exc.value.file == str(files["hand_eye"]) and exc.value.key == "cell"


def test_calibration_file_of_the_wrong_kind_is_refused(tmp_path):
    files = _calibration_files(tmp_path)
    text = GOOD + f'\n[calibration]\ncell = "test-cell"\nhand_eye = "{files["effector_zero"]}"\n'
    with pytest.raises(ConfigError, match="'effector_zero' calibration; a 'hand_eye' one"):
        load_config(_write(tmp_path, "oralnav.toml", text))


def test_calibration_entry_pointing_at_a_non_toml_file_names_the_entry(tmp_path):
    """issue 30: a [calibration] entry that points at a file that is not TOML is refused
    naming the configuration file, the [calibration] key that referred to it, and the
    file itself."""
    notes = _write(tmp_path, "hand_eye.txt", "1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    path = _write(tmp_path, "oralnav.toml", GOOD + f'\n[calibration]\ncell = "test-cell"\n'
                                                   f'hand_eye = "{notes}"\n')
    msg = _expect(path, "[calibration] hand_eye:", str(notes), "not valid TOML")
    assert msg.startswith(f"{path}: [calibration] hand_eye: {notes}: "), msg


# -- issue 30: truncated files and files of another kind -----------------------------------
def test_config_cut_short_is_called_truncated(tmp_path):
    """issue 30: a daemon configuration cut in the middle says the file looks truncated:
    cut inside a statement (the TOML parse fails at its end), or cut before its [cell]
    section (it parses, and [cell] is missing)."""
    cut = GOOD[:GOOD.index('fields = "') + 12]  # inside the fields string
    _expect(_write(tmp_path, "cut.toml", cut), "not valid TOML", "truncated")
    head = GOOD[:GOOD.index("[cell]")]
    _expect(_write(tmp_path, "head.toml", head), ": cell:",
            "no [cell] section", "cut short", "another kind of file")


@pytest.mark.parametrize("name, what, where", [
    ("examples/sim_cell.toml", "a cell file", "[cell] sim_cell"),
    ("examples/stereo_cell.toml", "a scene file", "[cell] scene"),
    ("rigs/stereo.toml", "a rig file", "[cell] rig"),
    ("fields/cell.toml", "a marker-fields file", "[cell] fields"),
    ("calibration/hand_eye.toml", "a calibration file", "[calibration]"),
    ("examples/oral_cavity_case.toml", "a planning scene", "oralnav plan place"),
])
def test_another_kind_of_file_given_as_configuration_says_what_it_is(name, what, where):
    """issue 30: `oralnavd --config config/examples/sim_cell.toml` (or a scene, rig, fields,
    calibration or planning file) says what kind of file it is and where it belongs,
    in one line, instead of listing its keys as unknown ones."""
    msg = _expect(CONFIG / name, "not a daemon configuration", what, where)
    assert "unknown key" not in msg


@pytest.mark.parametrize("api, where", [
    ({}, None),
    ({"audit_max_bytes": 1 << 20, "audit_keep": 2, "auth_failure_burst": 3,
      "auth_failure_refill_s": 1.5, "auth_lockout_s": 5.0, "auth_lockout_max_s": 5.0}, None),
    ({"audit_max_bytes": 1000}, "[api] audit_max_bytes"),
    ({"audit_keep": 0}, "[api] audit_keep"),
    ({"audit_keep": 1.5}, "[api] audit_keep"),
    ({"auth_failure_burst": 0}, "[api] auth_failure_burst"),
    ({"auth_failure_refill_s": 0.0}, "[api] auth_failure_refill_s"),
    ({"auth_lockout_s": 0.5}, "[api] auth_lockout_s"),
    ({"auth_lockout_s": 120.0, "auth_lockout_max_s": 60.0}, "[api] auth_lockout_max_s"),
])
def test_api_audit_rotation_and_lockout_keys(tmp_path, api, where):
    """issue 30: [api] audit_max_bytes (>= 64 KiB) and audit_keep (>= 1) bound the audit
    log; auth_failure_burst, auth_failure_refill_s, auth_lockout_s and auth_lockout_max_s
    (never shorter than auth_lockout_s) set the lockout of failed authentication; each
    error names the key."""
    from oralnav.config.daemon import ApiSection
    from oralnav.config.loader import validate

    path = tmp_path / "d.toml"
    if where is None:
        sec = validate(ApiSection, api, path, "api")
        assert sec.audit_max_bytes == api.get("audit_max_bytes", 64 << 20)
        assert sec.audit_keep == api.get("audit_keep", 5)
        return
    with pytest.raises(ConfigError) as ei:
        validate(ApiSection, api, path, "api")
    assert str(ei.value).startswith(f"{path}: {where}:"), str(ei.value)
