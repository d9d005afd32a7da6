"""RTDE (TCP 30004) on the fake controller: the output and input fields it offers, the
connection that speaks the protocol, and the values its output packages carry.

Protocol versions 1 and 2: version negotiation, the controller version, output and input
recipe setup (each field answered with its RTDE type; unknown or refused fields with
``NOT_FOUND`` / ``IN_USE``), start / pause, output data packages at the controller rate
decimated to each client's frequency (``round(rate / frequency)`` cycles), and input data
packages decoded by the client's own input recipes into the input registers. Text messages
are ignored.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from typing import Any

from oralnav.drivers.arm.ur_protocol import (
    RTDE_DATA_PACKAGE,
    RTDE_GET_URCONTROL_VERSION,
    RTDE_HEADER,
    RTDE_NOT_FOUND,
    RTDE_PAUSE,
    RTDE_REQUEST_PROTOCOL_VERSION,
    RTDE_SETUP_INPUTS,
    RTDE_SETUP_OUTPUTS,
    RTDE_START,
    RTDE_TEXT_MESSAGE,
    SAFETY_BIT_ESTOP,
    SAFETY_BIT_NORMAL,
    SAFETY_BIT_PROTECTIVE,
    SAFETY_BIT_ROBOT_ESTOP,
    SAFETY_BIT_SYSTEM_ESTOP,
    RobotMode,
    RuntimeState,
    SafetyMode,
)
from oralnav.sim.peers.ur.kinematics import TcpPoint
from oralnav.sim.peers.ur.server import Conn

__all__ = ["INPUT_FIELDS", "OUTPUT_FIELDS", "RTDEConn", "RTDEOutputs"]

#: RTDE type name -> struct format of one value (big endian, no padding).
_FORMATS = {
    "BOOL": "?",
    "UINT8": "B",
    "UINT32": "I",
    "UINT64": "Q",
    "INT32": "i",
    "DOUBLE": "d",
    "VECTOR3D": "3d",
    "VECTOR6D": "6d",
    "VECTOR6INT32": "6i",
    "VECTOR6UINT32": "6I",
}
_COUNTS = {"VECTOR3D": 3, "VECTOR6D": 6, "VECTOR6INT32": 6, "VECTOR6UINT32": 6}


def _output_fields() -> dict[str, str]:
    """The standard output fields (RTDE guide, output table) -> RTDE type."""
    fields = {name: "VECTOR6D" for name in (
        "target_q", "target_qd", "target_qdd", "target_current", "target_moment", "actual_q",
        "actual_qd", "actual_current", "joint_control_output", "actual_TCP_pose",
        "actual_TCP_speed", "actual_TCP_force", "target_TCP_pose", "target_TCP_speed",
        "joint_temperatures", "actual_joint_voltage", "ft_raw_wrench", "payload_inertia",
        "actual_current_window", "actual_current_as_torque", "actual_joint_torques",
    )}
    fields.update({name: "DOUBLE" for name in (
        "timestamp", "actual_execution_time", "speed_scaling", "target_speed_fraction",
        "actual_momentum", "actual_main_voltage", "actual_robot_voltage", "actual_robot_current",
        "standard_analog_input0", "standard_analog_input1", "standard_analog_output0",
        "standard_analog_output1", "io_current", "tool_analog_input0", "tool_analog_input1",
        "tool_output_current", "tool_temperature", "payload", "speed_scaling_combined",
    )})
    fields.update({name: "VECTOR3D" for name in (
        "actual_tool_accelerometer", "elbow_position", "elbow_velocity", "payload_cog",
    )})
    fields.update({name: "UINT64" for name in (
        "actual_digital_input_bits", "actual_digital_output_bits",
    )})
    fields.update({name: "INT32" for name in (
        "robot_mode", "safety_mode", "safety_status", "tool_output_voltage",
    )})
    fields.update({name: "UINT32" for name in (
        "runtime_state", "robot_status_bits", "safety_status_bits", "analog_io_types",
        "tool_mode", "tool_analog_input_types", "output_bit_registers0_to_31",
        "output_bit_registers32_to_63", "input_bit_registers0_to_31",
        "input_bit_registers32_to_63",
    )})
    fields.update({"joint_mode": "VECTOR6INT32", "tool_output_mode": "UINT8"})
    for i in range(48):
        fields[f"output_int_register_{i}"] = "INT32"
        fields[f"output_double_register_{i}"] = "DOUBLE"
        fields[f"input_int_register_{i}"] = "INT32"
        fields[f"input_double_register_{i}"] = "DOUBLE"
    for i in range(64, 128):
        fields[f"output_bit_register_{i}"] = "BOOL"
        fields[f"input_bit_register_{i}"] = "BOOL"
    return fields


def _input_fields() -> dict[str, str]:
    """The standard input fields (RTDE guide, input table) -> RTDE type."""
    fields = {
        "speed_slider_mask": "UINT32", "speed_slider_fraction": "DOUBLE",
        "standard_digital_output_mask": "UINT8", "standard_digital_output": "UINT8",
        "configurable_digital_output_mask": "UINT8", "configurable_digital_output": "UINT8",
        "tool_digital_output_mask": "UINT8", "tool_digital_output": "UINT8",
        "standard_analog_output_mask": "UINT8", "standard_analog_output_type": "UINT8",
        "standard_analog_output_0": "DOUBLE", "standard_analog_output_1": "DOUBLE",
        "input_bit_registers0_to_31": "UINT32", "input_bit_registers32_to_63": "UINT32",
        "external_force_torque": "VECTOR6D",
    }
    for i in range(48):
        fields[f"input_int_register_{i}"] = "INT32"
        fields[f"input_double_register_{i}"] = "DOUBLE"
    for i in range(64, 128):
        fields[f"input_bit_register_{i}"] = "BOOL"
    return fields


#: Output field name -> RTDE type (``DOUBLE``, ``VECTOR6D`` ...).
OUTPUT_FIELDS = _output_fields()
#: Input field name -> RTDE type.
INPUT_FIELDS = _input_fields()


def _zero(rtde_type: str) -> Any:
    """What a field of ``rtde_type`` reads when the fake does not fill it."""
    n = _COUNTS.get(rtde_type)
    if n is None:
        return False if rtde_type == "BOOL" else 0
    return (0.0,) * n if rtde_type.endswith("D") else (0,) * n


class RTDEConn(Conn):
    """One RTDE client: its protocol version, output recipe and input recipes."""

    kind = "rtde"

    def __init__(self, *args: Any) -> None:
        super().__init__(*args)
        self.protocol = 1
        self.out_names: list[str] = []
        self.out_struct: struct.Struct | None = None
        self.out_every = 1
        self.out_recipe = 0
        self.in_recipes: dict[int, tuple[list[str], struct.Struct]] = {}
        self.started = False

    def handle(self) -> None:
        while len(self.inbuf) >= 3:
            size, kind = RTDE_HEADER.unpack_from(self.inbuf)
            if size < 3:  # garbage: a real controller would drop the client
                self.ctrl._drop(self)
                return
            if len(self.inbuf) < size:
                return
            payload = bytes(self.inbuf[3:size])
            del self.inbuf[:size]
            self.message(kind, payload)
            if self.closed:
                return

    def reply(self, kind: int, payload: bytes = b"") -> None:
        """Answer a request of type ``kind``."""
        self.send(RTDE_HEADER.pack(3 + len(payload), kind) + payload)

    def message(self, kind: int, payload: bytes) -> None:
        """Act on one message (``payload`` without the header)."""
        ctrl = self.ctrl
        if kind == RTDE_REQUEST_PROTOCOL_VERSION:
            version = struct.unpack(">H", payload[:2])[0] if len(payload) >= 2 else 0
            ok = version in (1, 2)
            if ok:
                self.protocol = version
            self.reply(kind, struct.pack(">B", ok))
        elif kind == RTDE_GET_URCONTROL_VERSION:
            self.reply(kind, struct.pack(">IIII", *ctrl.version))
        elif kind == RTDE_SETUP_OUTPUTS:
            if self.protocol >= 2:
                frequency = struct.unpack(">d", payload[:8])[0] if len(payload) >= 8 else 0.0
                names_raw = payload[8:]
            else:
                frequency, names_raw = ctrl.frequency, payload
            names = [n for n in names_raw.decode("ascii", "replace").split(",") if n]
            types = [ctrl._field_answer(n, OUTPUT_FIELDS) for n in names]
            ok = bool(names) and all(t in _FORMATS for t in types) and frequency > 0
            if ok and not self.started:
                self.out_names = names
                self.out_struct = struct.Struct(">B" + "".join(_FORMATS[t] for t in types))
                self.out_every = max(1, round(ctrl.frequency / min(frequency, ctrl.frequency)))
                self.out_recipe = 1
            ctrl._event("rtde_setup_outputs", names=names, frequency=frequency, accepted=ok)
            self.reply(kind, struct.pack(">B", 1 if ok else 0) + ",".join(types).encode())
        elif kind == RTDE_SETUP_INPUTS:
            names = [n for n in payload.decode("ascii", "replace").split(",") if n]
            types = [ctrl._field_answer(n, INPUT_FIELDS) for n in names]
            ok = bool(names) and all(t in _FORMATS for t in types)
            recipe = 0
            if ok:
                recipe = len(self.in_recipes) + 1
                fmt = ">B" + "".join(_FORMATS[t] for t in types)
                self.in_recipes[recipe] = (names, struct.Struct(fmt))
            else:
                ctrl._event("rtde_setup_inputs_refused", names=names, types=types)
            self.reply(kind, struct.pack(">B", recipe) + ",".join(types).encode())
        elif kind == RTDE_START:
            ok = self.out_struct is not None
            self.reply(kind, struct.pack(">B", ok))
            self.started = ok
        elif kind == RTDE_PAUSE:
            self.started = False
            self.reply(kind, struct.pack(">B", 1))
        elif kind == RTDE_DATA_PACKAGE:
            self.input_package(payload)
        elif kind == RTDE_TEXT_MESSAGE:
            pass
        else:
            ctrl._event("rtde_unknown_package", kind=kind)

    def input_package(self, payload: bytes) -> None:
        """Decode an input data package by its recipe into the controller's inputs."""
        if not payload:
            return
        recipe = self.in_recipes.get(payload[0])
        if recipe is None:
            self.ctrl._event("rtde_unknown_input_recipe", recipe=payload[0])
            return
        names, fmt = recipe
        if len(payload) != fmt.size:
            self.ctrl._event("rtde_bad_input_package", recipe=payload[0], size=len(payload),
                             expected=fmt.size)
            return
        flat = fmt.unpack(payload)[1:]
        values: dict[str, Any] = {}
        i = 0
        for name in names:
            n = _COUNTS.get(INPUT_FIELDS[name], 1)
            values[name] = flat[i] if n == 1 else tuple(flat[i:i + n])
            i += n
        self.ctrl._apply_inputs(values)

    def data_package(self, values: dict[str, Any]) -> None:
        """Send one output package: the recipe's fields from ``values``, the rest from the
        controller (dropped while the client is behind)."""
        assert self.out_struct is not None
        flat: list[Any] = [self.out_recipe]
        for name in self.out_names:
            value = values.get(name)
            if value is None:
                value = self.ctrl._output_value(name)
            if isinstance(value, tuple):
                flat.extend(value)
            else:
                flat.append(value)
        body = self.out_struct.pack(*flat)
        self.send(RTDE_HEADER.pack(3 + len(body), RTDE_DATA_PACKAGE) + body, droppable=True)


class RTDEOutputs:
    """What the RTDE outputs of :class:`~oralnav.sim.peers.ur.controller.FakeURController`
    read, and how its recipe fields are answered."""

    _tcp: TcpPoint
    _wrench: tuple[float, ...]
    _robot_mode: int
    _safety_mode: int
    _estop_kind: int
    _running: bool
    _refused: dict[str, str]
    _inputs: dict[str, Any]
    _out_int: list[int]
    _out_double: list[float]
    _now: Callable[[], float]

    def _safety_bits(self) -> int:
        """``safety_status_bits`` for the current safety mode and e-stop."""
        mode = self._safety_mode
        bits = 0
        if mode == SafetyMode.NORMAL:
            bits |= 1 << SAFETY_BIT_NORMAL
        if mode == SafetyMode.PROTECTIVE_STOP:
            bits |= 1 << SAFETY_BIT_PROTECTIVE
        if self._estop_kind == SafetyMode.SYSTEM_EMERGENCY_STOP:
            bits |= (1 << SAFETY_BIT_SYSTEM_ESTOP) | (1 << SAFETY_BIT_ESTOP)
        if self._estop_kind == SafetyMode.ROBOT_EMERGENCY_STOP:
            bits |= (1 << SAFETY_BIT_ROBOT_ESTOP) | (1 << SAFETY_BIT_ESTOP)
        return bits

    def _robot_bits(self) -> int:
        """``robot_status_bits``: bit 0 powered, bit 1 program running."""
        powered = self._robot_mode in (RobotMode.POWER_ON, RobotMode.IDLE, RobotMode.RUNNING)
        return int(powered) | (int(self._running) << 1)

    def _outputs(self) -> dict[str, Any]:
        """This cycle's values of the fields the fake fills (pose in m and rad, twist in m/s
        and rad/s, wrench in N and N m, all in the base frame)."""
        pose = self._tcp.pose6()
        twist = self._tcp.twist()
        return {
            "timestamp": self._now(),
            "actual_TCP_pose": pose,
            "target_TCP_pose": self._tcp.target6(),
            "actual_TCP_speed": twist,
            "target_TCP_speed": twist,
            "actual_TCP_force": self._wrench,
            "robot_mode": self._robot_mode,
            "safety_mode": self._safety_mode,
            "safety_status": self._safety_mode,
            "safety_status_bits": self._safety_bits(),
            "robot_status_bits": self._robot_bits(),
            "runtime_state": RuntimeState.PLAYING if self._running else RuntimeState.STOPPED,
        }

    def _output_value(self, name: str) -> Any:
        """The value of an output field :meth:`_outputs` does not fill."""
        if name.startswith("output_int_register_"):
            return self._out_int[int(name.rsplit("_", 1)[1])]
        if name.startswith("output_double_register_"):
            return self._out_double[int(name.rsplit("_", 1)[1])]
        if name.startswith("input_"):
            return self._inputs.get(name, _zero(OUTPUT_FIELDS[name]))
        if name in ("speed_scaling", "target_speed_fraction", "speed_scaling_combined"):
            return 1.0
        if name in ("actual_main_voltage", "actual_robot_voltage"):
            return 48.0
        if name == "joint_mode":
            return (253,) * 6 if self._robot_mode == RobotMode.RUNNING else (236,) * 6
        if name == "actual_execution_time":
            return 0.3
        return _zero(OUTPUT_FIELDS[name])

    def _field_answer(self, name: str, table: dict[str, str]) -> str:
        """The type a recipe setup answers for ``name`` (refused: ``NOT_FOUND`` / ``IN_USE``)."""
        refused = self._refused.get(name)
        if refused is not None:
            return refused
        return table.get(name, RTDE_NOT_FOUND)
