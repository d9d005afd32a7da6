"""Configuration sections of the real cell's devices (docs/formats.md): the arm, ``[arm]``
with ``[arm.ur]``; the tendon-driven end-effector on its drive, ``[effector]`` with
``[effector.canopen]`` or ``[effector.modbus]``; the cameras, ``[cameras.<name>]``, and how
the stereo pair is matched, ``[stereo]``. Validated with the daemon configuration; each
section turns into the backend's constructor arguments with ``driver_options``.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from oralnav.drivers.effector.kinematics import (
    DEFAULT_COUPLING,
    DEFAULT_JOINT_MAX,
    DEFAULT_JOINT_MIN,
    DEFAULT_MOTOR_MAX,
    DEFAULT_MOTOR_MIN,
    WristKinematics,
)
from oralnav.drivers.errors import DriverInitError

from .loader import Float, Int, Strict

__all__ = ["ArmSection", "CameraSection", "CanopenSection", "EffectorSection", "ModbusSection",
           "StereoSection", "URSection"]

Four = tuple[Float, Float, Float, Float]


def _four(values: Any) -> tuple[float, float, float, float]:
    return tuple(float(v) for v in values)  # type: ignore[return-value]


class URSection(Strict):
    """``[arm.ur]``: a Universal Robots arm through ur-rtde (docs/ur_rtde.md)."""

    host: str = Field(min_length=1)                     # the controller's address
    # RTDE rate, Hz; None: the controller's own (500 e-Series, 125 CB3)
    frequency: Annotated[Float, Field(gt=0, le=500)] | None = None
    lookahead_time: Annotated[Float, Field(ge=0.03, le=0.2)] = 0.1   # servoL, s
    gain: Annotated[Float, Field(ge=100, le=2000)] = 300.0           # servoL
    # s without a command or kick before the controller stops the arm
    watchdog_timeout: Annotated[Float, Field(gt=0, le=1.0)] = 0.05
    stop_decel: Annotated[Float, Field(gt=0, le=40)] = 10.0          # m/s^2
    connect_timeout: Annotated[Float, Field(gt=0, le=30)] = 2.0
    # s without new controller data before the arm reads disconnected (the loop stops it)
    stale_timeout: Annotated[Float, Field(gt=0, le=2.0)] = 0.1
    # s without new data before the link is dropped and reopened
    link_timeout: Annotated[Float, Field(gt=0, le=30)] = 1.0
    upper_range_registers: bool = False   # RTDE registers 24-47, leaving 0-23 to a fieldbus


class ArmSection(Strict):
    """``[arm]``: the robot arm. ``sim`` is the simulated arm (the simulated cell always
    uses it); ``ur`` needs ``[arm.ur]``."""

    backend: Literal["sim", "ur"] = "sim"
    ur: URSection | None = None

    @model_validator(mode="after")
    def _consistent(self) -> ArmSection:
        if self.backend == "ur" and self.ur is None:
            raise ValueError('backend = "ur" needs an [arm.ur] section')
        return self

    def driver_options(self) -> dict[str, Any]:
        """The backend's constructor arguments (the sim arm's come from the daemon)."""
        if self.backend == "sim" or self.ur is None:
            return {}
        return self.ur.model_dump()


class CanopenSection(Strict):
    """``[effector.canopen]``: four CiA 402 drives on a CAN bus."""

    interface: str = Field("socketcan", min_length=1)   # python-can interface
    channel: str = Field("can0", min_length=1)
    bitrate: Annotated[Int, Field(ge=10_000, le=1_000_000)] = 1_000_000
    node_ids: tuple[Int, Int, Int, Int] = (1, 2, 3, 4)
    eds: str | None = Field(None, min_length=1)          # the drives' EDS, relative to this file
    mode: Literal["csp", "pp"] = "csp"
    heartbeat_ms: Annotated[Int, Field(ge=1, le=65535)] = 20
    host_node_id: Annotated[Int, Field(ge=1, le=127)] = 0x7F
    host_heartbeat_ms: Annotated[Int, Field(ge=1, le=65535)] = 20

    @model_validator(mode="after")
    def _ids(self) -> CanopenSection:
        ids = self.node_ids
        if len(set(ids)) != 4 or not all(1 <= i <= 127 for i in ids):
            raise ValueError(f"node_ids must be 4 distinct ids in 1..127, got {list(ids)}")
        if self.host_node_id in ids:
            raise ValueError(f"host_node_id {self.host_node_id} is a drive's node id")
        return self


class ModbusSection(Strict):
    """``[effector.modbus]``: a drive unit on Modbus TCP or RTU."""

    transport: Literal["tcp", "rtu"] = "tcp"
    host: str | None = Field(None, min_length=1)
    port: Annotated[Int, Field(ge=1, le=65535)] = 502
    serial_port: str | None = Field(None, min_length=1)
    baudrate: Annotated[Int, Field(ge=1200, le=4_000_000)] = 115200
    parity: Literal["N", "E", "O"] = "N"
    stopbits: Literal[1, 2] = 1
    device_id: Annotated[Int, Field(ge=1, le=247)] = 1
    watchdog_ms: Annotated[Int, Field(ge=0, le=65535)] = 100

    @model_validator(mode="after")
    def _where(self) -> ModbusSection:
        if self.transport == "tcp" and not self.host:
            raise ValueError("Modbus TCP needs host")
        if self.transport == "rtu" and not (self.host or self.serial_port):
            raise ValueError("Modbus RTU needs serial_port (or host for a TCP gateway)")
        return self


class EffectorSection(Strict):
    """``[effector]``: the wrist's kinematics and its drive. Angles in rad, as everywhere
    unless a key names another unit; joints ``[roll, pitch, yaw, jaw]``, motors in the same
    order. The kinematics apply to the drive backends; the simulated wrist keeps the
    example kinematics the simulated cell renders."""

    backend: Literal["sim", "canopen", "modbus"] = "sim"
    # rows are motors, columns joints: m = C q + motor_offset (docs/drivers.md)
    coupling: tuple[Four, Four, Four, Four] = tuple(
        _four(r) for r in DEFAULT_COUPLING)  # type: ignore[assignment]
    joint_min: Four = _four(DEFAULT_JOINT_MIN)
    joint_max: Four = _four(DEFAULT_JOINT_MAX)
    motor_min: Four = _four(DEFAULT_MOTOR_MIN)
    motor_max: Four = _four(DEFAULT_MOTOR_MAX)
    motor_offset: Four = (0.0, 0.0, 0.0, 0.0)
    # rad per motor: the extra angle that keeps each tendon taut at the joints' zero
    pretension: Four = (0.0, 0.0, 0.0, 0.0)
    counts_per_rad: Four = (4096 / (2 * math.pi),) * 4
    rate_hz: Annotated[Float, Field(ge=10, le=1000)] = 200.0
    silence_timeout: Annotated[Float, Field(gt=0, le=1.0)] = 0.1
    canopen: CanopenSection | None = None
    modbus: ModbusSection | None = None

    @model_validator(mode="after")
    def _consistent(self) -> EffectorSection:
        if self.backend == "canopen" and self.canopen is None:
            raise ValueError('backend = "canopen" needs an [effector.canopen] section')
        if self.backend == "modbus" and self.modbus is None:
            raise ValueError('backend = "modbus" needs an [effector.modbus] section')
        if any(c <= 0 for c in self.counts_per_rad):
            raise ValueError(f"counts_per_rad must be > 0, got {list(self.counts_per_rad)}")
        if any(abs(p) > math.pi for p in self.pretension):
            raise ValueError(f"pretension is rad per motor; {list(self.pretension)} has one "
                             "over pi (degrees?)")
        self.kinematics()  # a singular coupling or an empty range is a configuration error
        return self

    def kinematics(self) -> WristKinematics:
        """The configured coupling and limits; ValueError naming what is wrong."""
        try:
            return WristKinematics(self.coupling, self.joint_min, self.joint_max,
                                   self.motor_min, self.motor_max, self.motor_offset)
        except DriverInitError as exc:
            raise ValueError(str(exc)) from None

    def driver_options(self, config_dir: Path) -> dict[str, Any]:
        """The backend's constructor arguments (an EDS path relative to ``config_dir``)."""
        if self.backend == "sim":
            return {}
        opts: dict[str, Any] = {
            "kinematics": self.kinematics(), "pretension": list(self.pretension),
            "counts_per_rad": list(self.counts_per_rad), "rate_hz": self.rate_hz,
            "silence_timeout": self.silence_timeout}
        if self.backend == "canopen":
            bus = self.canopen.model_dump()
            if bus["eds"]:
                bus["eds"] = str(config_dir / bus["eds"])
            bus["node_ids"] = tuple(bus["node_ids"])
            return opts | bus
        return opts | self.modbus.model_dump()


class CameraSection(BaseModel):
    """``[cameras.<name>]``: one camera of the rig, ``<name>`` as the rig names it, or,
    with ``role = "monitor"``, a camera that only shows the operative area (any name no
    rig uses). ``backend`` picks the driver; every other key is that driver's own option
    (docs/cameras.md), checked by the driver when the configuration loads."""

    model_config = ConfigDict(extra="allow", frozen=True, allow_inf_nan=False)

    backend: Literal["aravis", "v4l2", "replay"]
    # "tracking": a camera of the rigs, tracked; "monitor": a camera of the operative area
    # that no rig names, read only to be shown in the console and recorded (never tracked,
    # and its stall stops nothing: navigation does not see through it)
    role: Literal["tracking", "monitor"] = "tracking"

    def driver_options(self) -> dict[str, Any]:
        """The backend's constructor arguments (lists become tuples: TOML has no tuple)."""
        return {k: tuple(v) if isinstance(v, list) else v
                for k, v in (self.model_extra or {}).items()}


class StereoSection(Strict):
    """``[stereo]``: how the stereo rig's two cameras' frames are paired
    (``oralnav.drivers.camera.stereo``)."""

    by: Literal["timestamp", "counter"] = "timestamp"
    # s: frames further apart than this are not a pair (timestamp pairing)
    tolerance: Annotated[Float, Field(gt=0, le=0.1)] = 0.005
    # whose timestamps: "host" (when the frame arrived) or "device" (the cameras' own
    # clocks, for PTP-synchronised cameras)
    clock: Literal["host", "device"] = "host"
