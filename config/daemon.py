"""The daemon's configuration (``oralnavd --config FILE``); see docs/formats.md.

Validated once at start, then frozen. ``config/sim.toml`` (shipped inside the package) is
the default: the simulated cell. ``config/hardware.example.toml`` is the template for a
real robot PC.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import partial
from importlib import resources
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field, ValidationInfo, field_validator, model_validator

from oralnav.control.geometry import invert
from oralnav.control.vision.camera import Rig
from oralnav.control.vision.markers import MarkerField
from oralnav.sim.world.cell import CellConfig
from oralnav.sim.world.scene import Scene

from .calibration import Calibration, load_calibration
from .cell import CellFile, Matrix, load_cell_config, rigid_matrix
from .errors import ConfigError
from .fields import FieldsFile, load_fields
from .hardware import ArmSection, CameraSection, EffectorSection, StereoSection
from .loader import Float, Int, Strict, load_file, read_toml, resolve_file, validate
from .rig import RigFile, load_rig
from .scene import SceneFile, load_scene

#: ISO 10218 reduced speed: no configured Cartesian speed may exceed it (m/s).
ISO_REDUCED_SPEED = 0.25


class CellSection(Strict):
    backend: Literal["sim", "hardware"] = "sim"
    rig: str
    endoscope_rig: str | None = None
    fields: str
    # validate_default: the check below must also run when scene is left out
    scene: str | None = Field(None, validate_default=True)
    # the moving simulated cell (docs/formats.md, "Cell file"): what oralnavd's sim
    # cameras render from the sim arm's state; on a hardware-in-the-loop cell of protocol
    # peers, the cell the peers render (its suture targets are what --demo registers)
    sim_cell: str | None = None
    # the ground truth of a hardware-in-the-loop cell (oralnav sim peers): its loopback
    # URL, GET ?t=<s>; the daemon measures each reached target's TRE against it. Never on
    # a real cell: it has no truth
    truth: str | None = None

    @field_validator("truth")
    @classmethod
    def _loopback_truth(cls, v: str | None) -> str | None:
        if v is not None and not v.startswith(("http://127.0.0.1:", "http://localhost:")):
            raise ValueError(f"must be a loopback http URL (http://127.0.0.1:PORT/truth), "
                             f"got {v!r}")
        return v

    @field_validator("scene")
    @classmethod
    def _scene_for_sim(cls, v: str | None, info: ValidationInfo) -> str | None:
        if info.data.get("backend") == "sim" and not v:
            raise ValueError("the sim backend needs scene (a scene file to simulate)")
        return v


class ControlSection(Strict):
    """The control loop (docs/control_loop.md)."""

    rate_hz: Annotated[Float, Field(ge=10, le=1000)] = 500.0
    # SCHED_FIFO priority for the control process (0: normal scheduling); needs
    # LimitRTPRIO in the service unit or root
    realtime_priority: Annotated[Int, Field(ge=0, le=99)] = 0
    # pin the control process to this CPU (None: let the kernel place it)
    cpu: Annotated[Int, Field(ge=0, le=1023)] | None = None


def _iso_speed(v: float) -> float:
    if v > ISO_REDUCED_SPEED:
        raise ValueError(f"{v} m/s exceeds the ISO 10218 reduced speed, "
                         f"{ISO_REDUCED_SPEED} m/s")
    return v


class SafetySection(Strict):
    """Watchdogs and limits (docs/safety.md). SI units unless the key names another;
    positions and the workspace are in the robot base frame."""

    max_speed: Annotated[Float, Field(gt=0)] = ISO_REDUCED_SPEED
    near_patient_speed: Annotated[Float, Field(gt=0)] = 0.05
    # s: a goal computed from poses older than this is not followed (the arm holds until
    # a fresh one); a guided insertion's opener pose older than this stops the arm
    stale_pose: Annotated[Float, Field(gt=0, le=1.0)] = 0.1
    # s: a pose the current stage steers by that has not come for this long is lost: a
    # latched stop (FAULT). Slow poses only slow the motion ([navigation] max_step)
    pose_timeout: Annotated[Float, Field(gt=0, le=10.0)] = 0.5
    # rad/s; the ISO speed bounds the TCP's linear speed only, so rotation has its own
    max_angular_speed: Annotated[Float, Field(gt=0, le=3.14159)] = 0.5
    near_patient_angular_speed: Annotated[Float, Field(gt=0, le=3.14159)] = 0.2
    # m: within this distance of the opener or a target the near-patient speeds apply
    near_patient_distance: Annotated[Float, Field(gt=0, le=0.5)] = 0.1
    # s a camera's frame counter may stay unchanged
    camera_stall: Annotated[Float, Field(gt=0, le=2.0)] = 0.2
    # s a driver may go without a heartbeat or state message
    driver_silence: Annotated[Float, Field(gt=0, le=1.0)] = 0.1
    # consecutive late control periods that trip; one period later than
    # max_period_lateness (s) trips at once, as does a loop completing none for that long
    deadline_misses: Annotated[Int, Field(ge=1, le=1000)] = 5
    max_period_lateness: Annotated[Float, Field(gt=0, le=0.1)] = 0.01
    # 1-sigma pose uncertainty that trips (m, deg); the tracker's own gate withholds
    # poses above 0.5 mm / 0.5 deg, so these only catch what slips past it
    max_position_sigma: Annotated[Float, Field(gt=0, le=0.01)] = 0.001
    max_rotation_sigma_deg: Annotated[Float, Field(gt=0, le=10.0)] = 1.0
    # m, base frame: a UR5e's reach (0.85 m) above its mounting plane; set the real
    # cell's box in its configuration
    workspace_min: tuple[Float, Float, Float] = (-0.85, -0.85, 0.0)
    workspace_max: tuple[Float, Float, Float] = (0.85, 0.85, 1.0)

    _check_iso = field_validator("max_speed", "near_patient_speed")(_iso_speed)

    @field_validator("pose_timeout")
    @classmethod
    def _lost_after_stale(cls, v: float, info: ValidationInfo) -> float:
        stale = info.data.get("stale_pose")
        if stale is not None and v < stale:
            raise ValueError(f"pose_timeout ({v} s) must be at least stale_pose ({stale} s): "
                             "a pose is lost only after it went stale")
        return v

    @field_validator("near_patient_angular_speed")
    @classmethod
    def _near_turns_slower(cls, v: float, info: ValidationInfo) -> float:
        top = info.data.get("max_angular_speed")
        if top is not None and v > top:
            raise ValueError(f"near_patient_angular_speed ({v} rad/s) must not exceed "
                             f"max_angular_speed ({top} rad/s)")
        return v

    @field_validator("workspace_min", "workspace_max")
    @classmethod
    def _within_reach(cls, v: tuple[float, float, float]) -> tuple[float, float, float]:
        # 2 m is beyond any arm this daemon drives: a larger figure is a unit slip (mm)
        for axis, x in zip("xyz", v, strict=True):
            if abs(x) > 2.0:
                raise ValueError(f"{axis} = {x} m is beyond 2 m from the base "
                                 "(metres expected)")
        return v

    @field_validator("workspace_max")
    @classmethod
    def _max_above_min(cls, v: tuple[float, float, float],
                       info: ValidationInfo) -> tuple[float, float, float]:
        lo = info.data.get("workspace_min")
        if lo is not None:
            bad = [f"{a}: {h} <= {m}" for a, m, h in zip("xyz", lo, v, strict=True)
                   if not h > m]
            if bad:
                raise ValueError("workspace_max must exceed workspace_min on every axis ("
                                 + ", ".join(bad) + ")")
        return v

    @field_validator("near_patient_speed")
    @classmethod
    def _near_is_slower(cls, v: float, info: ValidationInfo) -> float:
        # info.data lacks max_speed when max_speed itself failed; that error is reported
        top = info.data.get("max_speed")
        if top is not None and v > top:
            raise ValueError(f"near_patient_speed ({v} m/s) must not exceed max_speed "
                             f"({top} m/s)")
        return v


def _loopback_unless_allowed(host: str, info: ValidationInfo, server: str) -> str:
    """``host`` when it is a loopback address or the section sets ``allow_remote = true``
    (declared before ``host``, so that ``info.data`` has it); ValueError naming
    ``server`` otherwise."""
    if not ApiSection.is_loopback(host) and info.data.get("allow_remote") is not True:
        raise ValueError(f"{host!r} is not a loopback address; {server} binds remote "
                         "interfaces only with allow_remote = true")
    return host


class ApiSection(Strict):
    """The operator REST API (docs/api.md).

    ``tokens_file`` is relative to this configuration file; ``None`` makes the daemon
    generate demo tokens at start. ``audit_log`` is state, not configuration: a relative
    path is resolved against ``$STATE_DIRECTORY`` (set by systemd's ``StateDirectory=``),
    else the user's state folder (``$XDG_STATE_HOME/oralnav`` or
    ``~/.local/state/oralnav``), never against the (possibly read-only, packaged) config
    folder nor the working directory; see ``oralnav.daemon.audit.resolve_audit_path``.
    """

    # declared before host so that host's check below sees it
    allow_remote: bool = Field(False, strict=True)
    # validate_default: a default host must pass the loopback check too
    host: str = Field("127.0.0.1", min_length=1, validate_default=True)
    port: Annotated[Int, Field(ge=1, le=65535)] = 8750
    tokens_file: str | None = Field(None, min_length=1, validate_default=True)
    audit_log: str = Field("oralnav-audit.jsonl", min_length=1)
    telemetry_hz: Annotated[Float, Field(ge=1, le=100)] = 20.0
    # the console's live views: JPEGs encoded per camera and second at most, whatever the
    # number of consoles (docs/console.md: the cost it bounds)
    views_max_hz: Annotated[Float, Field(gt=0, le=60)] = 10.0
    # HTTPS: PEM certificate (chain) and private key, relative to this file; both or none
    tls_cert: str | None = Field(None, min_length=1)
    tls_key: str | None = Field(None, min_length=1, validate_default=True)
    # the audit log is rotated before a record would take it past audit_max_bytes, and
    # audit_keep rotated files are kept (docs/api.md "Audit log"; oralnav.daemon.audit)
    audit_max_bytes: Annotated[Int, Field(ge=64 * 1024, le=1 << 40)] = 64 << 20
    audit_keep: Annotated[Int, Field(ge=1, le=1000)] = 5
    # failed authentication per client address (docs/api.md "Rate limits and lockout";
    # the defaults are oralnav.daemon.api_gate's constants): a burst of failures locks the
    # address out for auth_lockout_s, doubling on repeats up to auth_lockout_max_s; one
    # failure is forgiven every auth_failure_refill_s
    auth_failure_burst: Annotated[Int, Field(ge=1, le=1000)] = 10
    auth_failure_refill_s: Annotated[Float, Field(ge=0.1, le=3600)] = 6.0
    auth_lockout_s: Annotated[Float, Field(ge=1, le=86400)] = 60.0
    auth_lockout_max_s: Annotated[Float, Field(ge=1, le=86400)] = 900.0

    @field_validator("tokens_file")
    @classmethod
    def _remote_needs_real_tokens(cls, v: str | None, info: ValidationInfo) -> str | None:
        # demo tokens are written to a local file for whoever runs the daemon; a port
        # that faces the network must be guarded by tokens someone issued on purpose
        if v is None and info.data.get("allow_remote") is True:
            raise ValueError("allow_remote = true needs a tokens_file: the demo tokens "
                             "generated at start are refused on a network-facing port")
        return v

    @field_validator("tls_key")
    @classmethod
    def _tls_pair(cls, v: str | None, info: ValidationInfo) -> str | None:
        if (v is None) != (info.data.get("tls_cert") is None):
            raise ValueError("HTTPS needs both tls_cert and tls_key"
                             + (" (tls_key is missing)" if v is None else
                                " (tls_cert is missing)"))
        return v

    @field_validator("auth_lockout_max_s")
    @classmethod
    def _lockout_bound(cls, v: float, info: ValidationInfo) -> float:
        first = info.data.get("auth_lockout_s")
        if first is not None and v < first:
            raise ValueError(f"{v:g} s is shorter than auth_lockout_s ({first:g} s): "
                             "repeated lockouts only grow")
        return v

    @staticmethod
    def is_loopback(host: str) -> bool:
        """True for ``localhost`` and loopback IP literals (127.0.0.0/8, ::1); a host name
        is not resolved (no I/O while validating), so any other name counts as remote."""
        import ipaddress  # local: only this class of the module needs it

        if host.lower() == "localhost":
            return True
        try:
            return ipaddress.ip_address(host.strip("[]")).is_loopback
        except ValueError:
            return False

    @field_validator("host")
    @classmethod
    def _loopback_unless_allowed(cls, v: str, info: ValidationInfo) -> str:
        # a surgical robot's command port must not face the network by accident
        return _loopback_unless_allowed(v, info, "the operator API")


class IgtlSection(Strict):
    """The OpenIGTLink server for 3D Slicer (docs/api.md, "OpenIGTLink (3D Slicer)"):
    tracked poses and the arm's TCP out as TRANSFORM messages at ``rate_hz`` (Hz), suture
    targets in as POINT lists (unless ``accept_targets = false``). The section's absence
    turns it off, as does ``enabled = false``. Like ``[api]``, it binds a loopback address
    unless ``allow_remote = true``: it has no authentication of its own."""

    enabled: bool = Field(True, strict=True)
    # declared before host so that host's check below sees it
    allow_remote: bool = Field(False, strict=True)
    # validate_default: a default host must pass the loopback check too
    host: str = Field("127.0.0.1", min_length=1, validate_default=True)
    port: Annotated[Int, Field(ge=1, le=65535)] = 18944
    # poses sent per second at most (each new pose once); Slicer renders at 30-60 Hz
    rate_hz: Annotated[Float, Field(ge=1, le=120)] = 30.0
    accept_targets: bool = Field(True, strict=True)

    @field_validator("host")
    @classmethod
    def _loopback_unless_allowed(cls, v: str, info: ValidationInfo) -> str:
        # anyone who reaches this port may set suture targets: never the network by accident
        return _loopback_unless_allowed(v, info, "the OpenIGTLink server")


class InputsSection(Strict):
    """The e-stop and foot pedal (docs/drivers.md, "Serial safety inputs"). ``sim``: the
    simulated buttons (pressed over REST in the demo); ``serial``: a box streaming ``$OSIO``
    status lines on ``port``."""

    backend: Literal["sim", "serial"] = "sim"
    # validate_default: the check below must also run when port is left out
    port: str | None = Field(None, min_length=1, validate_default=True)
    baudrate: Annotated[Int, Field(ge=1200, le=4_000_000)] = 115200
    # s without a status line after which the input is silent (reads e-stop pressed)
    heartbeat_timeout: Annotated[Float, Field(gt=0, le=1.0)] = 0.1
    # good lines in a row before a faulted input reads again
    recover_lines: Annotated[Int, Field(ge=1, le=100)] = 3
    # s start waits for the box before the daemon goes on (with the input in fault)
    connect_timeout: Annotated[Float, Field(gt=0, le=30.0)] = 2.0

    @field_validator("port")
    @classmethod
    def _port_for_serial(cls, v: str | None, info: ValidationInfo) -> str | None:
        if info.data.get("backend") == "serial" and not v:
            raise ValueError("the serial backend needs port (the box's device path)")
        return v

    def driver_options(self) -> dict[str, object]:
        """Keyword arguments of the backend's constructor."""
        if self.backend == "sim":
            return {}
        return {"port": self.port, "baudrate": self.baudrate,
                "heartbeat_timeout": self.heartbeat_timeout,
                "recover_lines": self.recover_lines, "connect_timeout": self.connect_timeout}


class CalibrationSection(Strict):
    """The cell's calibration files (docs/calibration.md), relative to this file. Each is
    checked on load: its kind, its cell (must be ``cell``), rigid transforms, units."""

    # the cell these calibrations belong to; a file of another cell is refused
    cell: str = Field(min_length=1)
    hand_eye: str | None = None            # T_B_C, T_tcp_RM
    endoscope_opener: str | None = None    # T_OM_En (eqs. 1-2)
    effector_zero: str | None = None       # T_RM_E0 (eqs. 3-4)
    effector_marker: str | None = None     # T_EM_E (eq. 7)
    pivot: str | None = None               # the registration pointer's tip ([28])
    temporal: str | None = None            # the stereo camera's time offset (s)


class NavigationSection(Strict):
    """The two-stage navigation (docs/navigation.md). Lengths in m, angles in degrees."""

    # The intra-oral entry pose: the end-effector zero frame E0 in the opener marker's
    # frame OM (4x4, m), where the approach (eq. 5) ends and the adjustment (eq. 6) aims.
    # A plan's choice, so the configuration gives it; on the simulated cell it defaults
    # to the cell file's intra-oral pose.
    entry_T_OM_E0: Matrix | None = None
    # The most the TCP goal may lead the arm per tracked frame (m, deg): motion is
    # bounded by how often poses come, so slow tracking is slow, safe motion.
    max_step: Annotated[Float, Field(gt=0, le=0.05)] = 0.005
    max_turn_deg: Annotated[Float, Field(gt=0, le=30.0)] = 2.0
    # s: the longest silence of the arm's measured TCP that a frame's capture instant
    # may be interpolated across (a longer one: the frame is not chained, FAULT)
    arm_history_gap: Annotated[Float, Field(gt=0, le=0.5)] = 0.05

    _check = field_validator("entry_T_OM_E0")(rigid_matrix)


#: The calibration kinds the navigation chain needs (eqs. 5-8).
NAVIGATION_CALIBRATIONS = ("hand_eye", "endoscope_opener", "effector_zero", "effector_marker")


class DaemonFile(Strict):
    name: str = "oralnav"
    cell: CellSection
    calibration: CalibrationSection | None = None
    navigation: NavigationSection = NavigationSection()
    control: ControlSection = ControlSection()
    safety: SafetySection = SafetySection()
    inputs: InputsSection = InputsSection()
    arm: ArmSection = ArmSection()
    effector: EffectorSection = EffectorSection()
    cameras: dict[str, CameraSection] = Field(default_factory=dict)
    stereo: StereoSection = StereoSection()
    api: ApiSection = ApiSection()
    igtl: IgtlSection | None = None   # absent: no OpenIGTLink server

    @model_validator(mode="after")
    def _sim_cell_drives_sim_devices(self) -> DaemonFile:
        # the simulated cell renders its cameras from the simulated arm and wrist
        if self.cell.backend == "sim":
            real = [f"[{k}] backend = {b!r}" for k, b in
                    (("arm", self.arm.backend), ("effector", self.effector.backend))
                    if b != "sim"] + [f"[cameras.{n}]" for n in self.cameras]
            if real:
                raise ValueError("the simulated cell ([cell] backend = \"sim\") drives the "
                                 "simulated arm, wrist and cameras; " + ", ".join(real)
                                 + " needs [cell] backend = \"hardware\"")
        return self


@dataclass(frozen=True)
class DaemonConfig:
    """A validated daemon configuration with its referenced files loaded."""

    path: Path
    settings: DaemonFile
    rig: Rig
    endoscope_rig: Rig | None
    fields: dict[str, MarkerField]
    scene_path: Path | None
    #: the loaded scene file, when the configuration names one (validated at start too)
    scene: Scene | None = None
    #: the loaded cell file ([cell] sim_cell), when the configuration names one
    cell: CellConfig | None = None
    #: the loaded calibration files ([calibration]), kind -> Calibration
    calibrations: dict[str, Calibration] = field(default_factory=dict)

    def missing_calibrations(self) -> list[str]:
        """The navigation chain's calibration kinds the configuration does not name."""
        return [k for k in NAVIGATION_CALIBRATIONS if k not in self.calibrations]

    def stereo_time_offset(self) -> float | None:
        """How late the stereo camera's timestamps are against the arm's clock (s): the
        temporal calibration's ``offset_s``, or None when the configuration names none."""
        cal = self.calibrations.get("temporal")
        return None if cal is None else float(cal["offset_s"])

    def entry_T_OM_E0(self) -> np.ndarray | None:
        """The intra-oral entry pose ``T_OM_E0`` (4x4, m): ``[navigation] entry_T_OM_E0``,
        else, on the simulated cell, the cell file's intra-oral TCP pose taken to the
        opener; None when neither is given (navigation then refuses to start)."""
        given = self.settings.navigation.entry_T_OM_E0
        if given is not None:
            return np.array(given, dtype=float)
        if self.cell is None:
            return None
        g = self.cell.geometry
        return invert(g.T_B_OM) @ self.cell.intraoral_T_B_tcp @ g.T_tcp_E0


def _check_cameras(path: Path, doc: DaemonFile, rig: Rig, endo: Rig | None) -> None:
    """Each ``[cameras.<name>]`` names a camera of the rigs (a monitor camera: one no rig
    names), and its driver accepts its options (the constructor checks them and does no
    I/O)."""
    from oralnav.drivers.camera import camera_class
    from oralnav.drivers.errors import DriverInitError

    known = list(rig.names) + (list(endo.names) if endo is not None else [])
    for name, cam in doc.cameras.items():
        if cam.role == "monitor" and name in known:
            raise ConfigError(path, f"cameras.{name}.role", f"{name!r} is a camera of the "
                              "rigs, tracked: a monitor camera takes a name no rig uses")
        if cam.role == "tracking" and name not in known:
            raise ConfigError(path, f"cameras.{name}", f"no camera {name!r} in the rigs "
                              f"(cameras: {', '.join(known)}); a camera that only shows the "
                              "operative area takes role = \"monitor\"")
        try:
            camera_class(cam.backend)(name=name, **cam.driver_options())
        except DriverInitError as exc:
            raise ConfigError(path, f"cameras.{name}", str(exc)) from None
        except TypeError as exc:  # an option the backend does not take
            raise ConfigError(path, f"cameras.{name}", f"an option the {cam.backend} backend "
                              f"does not take (docs/cameras.md): {exc}") from None


def _other_kinds() -> list[tuple[str, set[str], set[str], str]]:
    """The project's other TOML files, for telling one given as a daemon configuration:
    (what it is, its top-level keys, those it requires, where it belongs instead)."""
    from .calibration import _File as CalibrationFile
    from .planning import PlanningSceneFile

    def keys(model: type[Strict]) -> tuple[set[str], set[str]]:
        fields = model.model_fields
        return set(fields), {k for k, f in fields.items() if f.is_required()}

    return [
        ('a cell file (docs/formats.md, "Cell file")', *keys(CellFile),
         'name it in a daemon configuration\'s [cell] sim_cell (as config/sim.toml does) and '
         'run oralnavd --config on that'),
        ("a scene file", *keys(SceneFile),
         "name it in a daemon configuration's [cell] scene, or render it with "
         "oralnav sim render"),
        ("a rig file", *keys(RigFile), "name it in a daemon configuration's [cell] rig"),
        ("a marker-fields file", *keys(FieldsFile),
         "name it in a daemon configuration's [cell] fields"),
        ("a calibration file", *keys(CalibrationFile),
         "name it in a daemon configuration's [calibration] section under its kind"),
        ("a planning scene", *keys(PlanningSceneFile),
         "use it with oralnav plan place --scene"),
        ("a tokens file (docs/api.md)", {"tokens"}, {"tokens"},
         "name it in a daemon configuration's [api] tokens_file"),
    ]


def _check_kind(path: Path, data: dict[str, Any]) -> None:
    """Refuse, with one line that says so, another kind of project file given as a daemon
    configuration (a cell, scene, rig, fields, calibration, planning or tokens file),
    rather than listing its keys as unknown ones."""
    top = set(data)
    if isinstance(data.get("cell"), dict) or not top - set(DaemonFile.model_fields):
        return  # a daemon configuration, if a broken one: validate says what is wrong
    # the kind whose keys hold all of the file's and most of whose required keys it has;
    # of equals the narrower (a fields file's one key is also a scene's)
    best = max(((len(req & top), -len(known), what, hint)
                for what, known, req, hint in _other_kinds()
                if top <= known and req & top), default=None)
    if best is not None:
        _, _, what, hint = best
        raise ConfigError(path, "", f"this looks like {what}, not a daemon configuration "
                          f"(top-level keys {', '.join(sorted(top))}; no [cell] section): "
                          f"{hint}")


def default_config_path() -> Path:
    """The embedded simulation default, ``config/sim.toml``."""
    return Path(str(resources.files("oralnav.config").joinpath("sim.toml")))


def load_config(path: str | Path | None = None) -> DaemonConfig:
    """Load and validate a daemon configuration and every file it names.

    Nothing is started here; any problem raises :class:`ConfigError` naming the file and
    key before the daemon touches hardware.
    """
    path = Path(path) if path is not None else default_config_path()
    data = read_toml(path)
    _check_kind(path, data)
    doc = validate(DaemonFile, data, path)
    cell = doc.cell
    rig = load_file(path, "cell.rig", cell.rig, load_rig)
    endo = (load_file(path, "cell.endoscope_rig", cell.endoscope_rig, load_rig)
            if cell.endoscope_rig else None)
    fields = load_file(path, "cell.fields", cell.fields, load_fields)
    scene_path = resolve_file(path, "cell.scene", cell.scene) if cell.scene else None
    scene = (load_file(path, "cell.scene", scene_path, load_scene)
             if scene_path is not None else None)
    cell_cfg = (load_file(path, "cell.sim_cell", cell.sim_cell, load_cell_config)
                if cell.sim_cell else None)
    _check_cameras(path, doc, rig, endo)
    for key in ("tls_cert", "tls_key"):
        ref = getattr(doc.api, key)
        if ref is not None:
            resolve_file(path, f"api.{key}", ref)
    if doc.effector.canopen is not None and doc.effector.canopen.eds:
        resolve_file(path, "effector.canopen.eds", doc.effector.canopen.eds)  # must exist
    cals: dict[str, Calibration] = {}
    if doc.calibration is not None:
        c = doc.calibration
        for kind in (*NAVIGATION_CALIBRATIONS, "pivot", "temporal"):
            ref = getattr(c, kind)
            if ref:
                cals[kind] = load_file(path, f"calibration.{kind}", ref, partial(
                    load_calibration, kind=kind, cell=c.cell))
    return DaemonConfig(path=path, settings=doc, rig=rig, endoscope_rig=endo, fields=fields,
                        scene_path=scene_path, scene=scene, cell=cell_cfg, calibrations=cals)
