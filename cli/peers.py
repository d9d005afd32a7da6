"""A hardware cell made of protocol peers on this machine: the fake UR controller (RTDE,
dashboard, script ports), the emulated Modbus tendon-drive unit, the serial e-stop box on a
pty and, where Aravis is installed, two simulated GigE Vision cameras for the stereo pair.
``oralnav sim peers --out DIR`` runs them and writes ``DIR/cell.toml``, a ``[cell] backend
= "hardware"`` configuration pointing at them, so ``oralnavd --config DIR/cell.toml`` runs
every real backend without the hardware (docs/drivers.md, "A cell of protocol peers").
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
from importlib import resources
from pathlib import Path
from types import TracebackType

__all__ = ["HardwarePeers"]

log = logging.getLogger(__name__)


def _config_file(name: str) -> Path:
    return Path(str(resources.files("oralnav.config").joinpath(name)))


class HardwarePeers:
    """The peers, started on entering and stopped on leaving (a context manager).

    Args:
        folder: where the serial box's link and ``cell.toml`` go.
        ur_host: the fake UR controller's loopback address (ur_rtde fixes its ports).
        cameras: run two simulated GigE cameras (needs Aravis; see docs/cameras.md).
    """

    def __init__(self, folder: str | Path, *, ur_host: str | None = None,
                 cameras: bool = True) -> None:
        self.folder = Path(folder)
        self.ur_host = ur_host or f"127.84.{os.getpid() % 250}.7"
        self.want_cameras = cameras
        self._stack = contextlib.ExitStack()
        self.ur = self.drive = self.box = None
        self.camera_addresses: list[str] = []

    def __enter__(self) -> HardwarePeers:
        from oralnav.sim.peers.modbus_drive import ModbusDriveServer
        from oralnav.sim.peers.serial_box import SerialBox
        from oralnav.sim.peers.ur import FakeURControllerProcess

        self.folder.mkdir(parents=True, exist_ok=True)
        try:
            self.ur = self._stack.enter_context(
                FakeURControllerProcess(self.ur_host, unlock_delay=0.5))
            self.drive = self._stack.enter_context(ModbusDriveServer())
            self.box = self._stack.enter_context(
                SerialBox(rate_hz=100, link=self.folder / "estop"))
            if self.want_cameras:
                self._start_cameras()
        except BaseException:
            self._stack.close()
            raise
        return self

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

[safety]
driver_silence = 0.5      # generous: every peer shares this machine's CPUs
max_period_lateness = 0.1
deadline_misses = 10

[inputs]
backend = "serial"
port = "{self.box.link}"
heartbeat_timeout = 0.5

[arm]
backend = "ur"

[arm.ur]
host = "{self.ur.host}"
watchdog_timeout = 0.25

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
                     "frame_rate = 10.0\n")
        if self.camera_addresses:
            text += ('\n[stereo]\nby = "timestamp"\ntolerance = 0.01\n'
                     'clock = "device"          # the fakes stamp frames with this clock\n')
        return text

    def write_config(self) -> Path:
        """Write ``cell.toml`` into the folder; its path."""
        from oralnav.config.loader import atomic_write_text

        path = self.folder / "cell.toml"
        atomic_write_text(path, self.config_text())
        return path
