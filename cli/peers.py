"""A hardware cell made of protocol peers on this machine: the fake UR controller (RTDE,
dashboard, script ports), the emulated Modbus tendon-drive unit, the serial e-stop box on a
pty, and cameras. ``oralnav sim peers --out DIR`` runs them and writes ``DIR/cell.toml``, a
``[cell] backend = "hardware"`` configuration pointing at them, so ``oralnavd --config
DIR/cell.toml`` runs every real backend without the hardware (docs/drivers.md, "A cell of
protocol peers").

Cameras (``cameras=``):

- ``"rendered"`` (the hardware-in-the-loop cell): the simulated cell's stereo pair and
  endoscope as GigE cameras that show the arm where the fake UR controller has it and the
  wrist where the drive unit has it (``sim/hil/cameras.py``), with a set latency and
  camera clock offset; the cell's ground truth is served on loopback (``sim/hil/truth.py``)
  and named in ``[cell] truth``, so the daemon measures each target's TRE. The
  configuration carries the cell's calibration files, so it navigates as it is;
- ``"pattern"``: two of Aravis's own simulated cameras, streaming its test pattern
  (the protocol alone; nothing to track);
- ``"none"``.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import shutil
from importlib import resources
from pathlib import Path
from types import TracebackType
from typing import Literal

import numpy as np

__all__ = ["HardwarePeers"]

log = logging.getLogger(__name__)


def _config_file(name: str) -> Path:
    return Path(str(resources.files("oralnav.config").joinpath(name)))


class HardwarePeers:
    """The peers, started on entering and stopped on leaving (a context manager).

    Args:
        folder: where the serial box's link and ``cell.toml`` go.
        ur_host: the fake UR controller's loopback address (ur_rtde fixes its ports).
        cameras: ``"rendered"``, ``"pattern"`` or ``"none"`` (module docstring; rendered and
            pattern need Aravis, see docs/cameras.md).
        frame_rate: Hz of the cameras.
        camera_latency: s from a rendered frame's capture to its first packet.
        camera_clock_offset: s, the error of the rendered cameras' timestamps: they are
            PTP-synchronised to this host (TAI; the daemon reads them with ``timestamps =
            "ptp"``) and stamp ``capture + camera_clock_offset``.
        cell: the cell file the rendered cameras show (default: the shipped example).
    """

    def __init__(self, folder: str | Path, *, ur_host: str | None = None,
                 cameras: Literal["rendered", "pattern", "none"] = "rendered",
                 frame_rate: float | None = None, camera_latency: float = 0.0,
                 camera_clock_offset: float = 0.0, cell: str | Path | None = None) -> None:
        if cameras not in ("rendered", "pattern", "none"):
            raise ValueError(f"cameras must be 'rendered', 'pattern' or 'none', got "
                             f"{cameras!r}")
        self.folder = Path(folder)
        self.ur_host = ur_host or f"127.84.{os.getpid() % 250}.7"
        self.want_cameras = cameras
        # the renderer draws three 2-Mpixel views per capture: a few frames per second
        # (three views rendered, and tracked by the daemon, on the same cores: 1.5 Hz keeps
        # both within a 2-core machine)
        self.frame_rate = frame_rate or (1.5 if cameras == "rendered" else 10.0)
        self.camera_latency = float(camera_latency)
        self.camera_clock_offset = float(camera_clock_offset)
        self.cell_path = Path(cell) if cell is not None else _config_file(
            "examples/sim_cell.toml")
        self._stack = contextlib.ExitStack()
        self.ur = self.drive = self.box = None
        self.camera_addresses: list[str] = []
        self.rendered = None   # CellCameras, with rendered cameras
        self.truth = None      # TruthServer, with rendered cameras

    def __enter__(self) -> HardwarePeers:
        from oralnav.sim.peers.modbus_drive import ModbusDriveServer
        from oralnav.sim.peers.serial_box import SerialBox
        from oralnav.sim.peers.ur import FakeURControllerProcess

        self.folder.mkdir(parents=True, exist_ok=True)
        try:
            cell_config = None
            ur_options = {}
            if self.want_cameras == "rendered":
                from oralnav.config.cell import load_cell_config

                cell_config = load_cell_config(self.cell_path)
                ur_options["home"] = _pose6(cell_config.home_T_B_tcp)
                # a CB3-series arm (125 Hz): the arm's path (the fake controller, the
                # ur_rtde host, the control loop) then takes a quarter of the CPU that a
                # 500 Hz e-Series takes, which the renderer needs on a 2-core machine
                ur_options["series"] = "cb3"
            self.ur = self._stack.enter_context(
                FakeURControllerProcess(self.ur_host, unlock_delay=0.5, **ur_options))
            self.drive = self._stack.enter_context(ModbusDriveServer())
            self.box = self._stack.enter_context(
                SerialBox(rate_hz=100, link=self.folder / "estop"))
            if self.want_cameras == "pattern":
                self._start_cameras()
            elif self.want_cameras == "rendered":
                self._start_rendered(cell_config)
        except BaseException:
            self._stack.close()
            raise
        return self

    def _start_rendered(self, cell_config: object) -> None:
        from oralnav.sim.hil.cameras import CellCameras
        from oralnav.sim.hil.truth import TruthServer
        from oralnav.sim.peers.gige_fake import NoLoopbackAddress

        wrist = _WristReader(self.drive)
        self.rendered = CellCameras(cell_config, self.ur.pose_sample, wrist,
                                    frame_rate=self.frame_rate,
                                    latency_s=self.camera_latency,
                                    clock_offset_s=self.camera_clock_offset,
                                    ptp=True)
        try:
            self._stack.enter_context(self.rendered)
        except NoLoopbackAddress as exc:
            log.warning("no loopback address for a camera (%s): no cameras", exc)
            self.rendered = None
            return
        self.truth = self._stack.enter_context(TruthServer(self.rendered.truth_at))

    def _start_cameras(self) -> None:
        from oralnav.sim.peers.gige_fake import FAKE, NoLoopbackAddress, running_fakes

        if shutil.which(FAKE) is None:
            log.warning("%s is not installed: the cell runs without cameras", FAKE)
            return
        make = self._stack.enter_context(running_fakes())
        try:
            self.camera_addresses = [make().address, make().address]
        except NoLoopbackAddress as exc:
            log.warning("no second loopback address for a camera (%s): no cameras", exc)
            self.camera_addresses = []

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self._stack.close()


    def config_text(self) -> str:
        """The hardware-cell configuration for these peers (TOML)."""
        text = f"""# A hardware cell of protocol peers (oralnav sim peers); every device is a fake
# speaking the real protocol on this machine.
name = "oralnav-peers"

[cell]
backend = "hardware"
rig = "{_config_file('rigs/stereo.toml')}"
fields = "{_config_file('fields/cell.toml')}"
{self._cell_keys()}
{self._control_keys()}
[safety]
driver_silence = 0.5      # generous: every peer shares this machine's CPUs
max_period_lateness = 0.1
{self._slow_camera_keys()}
[inputs]
backend = "serial"
port = "{self.box.link}"
heartbeat_timeout = 0.5

[arm]
backend = "ur"

[arm.ur]
host = "{self.ur.host}"
watchdog_timeout = 0.25
{self._ur_keys()}
[effector]
backend = "modbus"
silence_timeout = 0.5

[effector.modbus]
host = "127.0.0.1"
port = {self.drive.port}
watchdog_ms = 1000        # the drive's host watchdog, generous for the same reason
"""
        for name, address in zip(("left", "right"), self.camera_addresses, strict=False):
            text += (f'\n[cameras.{name}]\nbackend = "aravis"\ncamera_id = "{address}"\n'
                     "region = [0, 0, 1920, 1200]   # the rig's calibrated size\n"
                     f"frame_rate = {self.frame_rate}\n")
        if self.camera_addresses:
            text += ('\n[stereo]\nby = "timestamp"\ntolerance = 0.01\n'
                     'clock = "device"          # the fakes stamp frames with this clock\n')
        if self.rendered is not None:
            text += self._rendered_text()
        return text

    def _cell_keys(self) -> str:
        """``[cell]`` keys of the rendered cell: the endoscope, the cell file (its targets
        for --demo) and the truth service."""
        if self.rendered is None:
            return ""
        return (f'endoscope_rig = "{_config_file("rigs/endoscope.toml")}"\n'
                f'sim_cell = "{self.cell_path.resolve()}"   # what the cameras show\n'
                f'truth = "{self.truth.url}"   # its ground truth, for the TRE\n')

    def _control_keys(self) -> str:
        """With rendered cameras the renderer shares this machine's cores with the loop:
        SCHED_FIFO for the control process, as config/sim.toml has it (refused without
        root or LimitRTPRIO: normal scheduling, logged)."""
        if self.rendered is None:
            return ""
        return ("[control]\nrealtime_priority = 50    # the renderer shares these cores\n"
                "rate_hz = 125.0           # the fake controller is a CB3-series arm\n")

    def _ur_keys(self) -> str:
        """With rendered cameras the fake controller's process shares the cores with the
        renderer and a SCHED_FIFO loop: its RTDE data can pause a few hundred ms."""
        if self.rendered is None:
            return ""
        return ("stale_timeout = 0.5       # s: the peers share this machine's cores\n"
                "link_timeout = 2.0\n\n[navigation]\n"
                "arm_history_gap = 0.2     # s: RTDE data pauses on this loaded machine\n")

    def _slow_camera_keys(self) -> str:
        """The deadline limit; with rendered cameras (a few frames/s, docs/navigation.md)
        the simulation's pose, camera and deadline limits (config/sim.toml)."""
        if self.rendered is None:
            # the peers (the fake controller at 500 Hz, its ur_rtde host, the drive) share
            # this machine's cores with the loop: 10 late periods in a row faulted the cell
            # on a slow 2-core VM with nothing else running (2026-11-27)
            return "deadline_misses = 100     # the protocol peers share these cores\n"
        return ("deadline_misses = 100     # the renderer's three views share these cores\n"
                "stale_pose = 1.0          # rendered cameras: a few frames per second\n"
                "pose_timeout = 5.0\ncamera_stall = 2.0\n")

    def _rendered_text(self) -> str:
        """The rendered cameras, the cell they show, its calibration and truth (TOML)."""
        cell = self.rendered.cell
        scene_rig = {n: cell.stereo_rig for n in cell.stereo_rig.names}
        scene_rig.update({n: cell.endoscope_rig for n in cell.endoscope_rig.names})
        text = ""
        for name, address in self.rendered.addresses.items():
            w, h = scene_rig[name][name].size
            text += (f'\n[cameras.{name}]\nbackend = "aravis"\ncamera_id = "{address}"\n'
                     f"region = [0, 0, {w}, {h}]\nframe_rate = {self.frame_rate}\n"
                     "timeout = 3.0             # s: a render can be late on a busy machine\n"
                     'timestamps = "ptp"        # the cameras are PTP-synchronised to this '
                     "host: a frame's stamp is its capture instant\n")
        # the cameras share one clock (as PTP-synchronised cameras do) and show one capture
        # of the cell: their device timestamps pair them whatever the transfer delays
        text += ('\n[stereo]\nby = "timestamp"\nclock = "device"\n'
                 "tolerance = 0.005         # both cameras show one capture of the cell\n")
        cal = _config_file("calibration")
        text += (f'\n[calibration]             # measured on the simulated cell '
                 f'(docs/calibration.md)\ncell = "sim-cell"\n'
                 f'hand_eye = "{cal / "hand_eye.toml"}"\n'
                 f'endoscope_opener = "{cal / "endoscope_opener.toml"}"\n'
                 f'effector_zero = "{cal / "effector_zero.toml"}"\n'
                 f'effector_marker = "{cal / "effector_marker.toml"}"\n')
        return text

    def write_config(self) -> Path:
        """Write ``cell.toml`` into the folder; its path."""
        from oralnav.config.loader import atomic_write_text

        path = self.folder / "cell.toml"
        atomic_write_text(path, self.config_text())
        return path


def _pose6(T: np.ndarray) -> list[float]:
    """4x4 ``T_B_tcp`` -> the controller's ``[x, y, z, rx, ry, rz]`` (m, rotation vector)."""
    from scipy.spatial.transform import Rotation

    return [*map(float, T[:3, 3]), *map(float, Rotation.from_matrix(T[:3, :3]).as_rotvec())]


class _WristReader:
    """The wrist's joints (rad) where the drive unit's axes are, through the effector
    driver's own units and kinematics (the configuration's defaults), so the rendered
    wrist is the one the daemon commands."""

    def __init__(self, drive: object) -> None:
        from oralnav.drivers.effector.kinematics import WristKinematics

        self.drive = drive
        self.kinematics = WristKinematics()
        self.counts_per_rad = 4096 / (2 * math.pi)  # MotorDriveEffector's default

    def __call__(self) -> np.ndarray:
        motors = np.asarray(self.drive.positions(), float) / self.counts_per_rad
        return self.kinematics.motors_to_joints(motors)
