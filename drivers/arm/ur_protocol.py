"""Universal Robots controller interface facts that both sides here rely on: the ``ur`` arm
backend (:mod:`oralnav.drivers.arm.ur`, which talks through ``ur_rtde`` and probes the ports
itself) and the fake controller its tests run against (the ``sim/peers/ur/`` package, which
imports this module; drivers never import the simulator).

What each table encodes, from UR's documentation:

- the TCP ports of the controller's interfaces ("Overview of client interfaces": dashboard
  server 29999, secondary 30002, real-time 30003, RTDE 30004);
- the RTDE message header and package types ("Real-Time Data Exchange (RTDE) Guide");
- the values of the RTDE outputs ``robot_mode``, ``safety_mode`` / ``safety_status``,
  ``safety_status_bits`` and ``runtime_state`` (the RTDE guide's output table);
- the dashboard server commands the driver's recovery sends through ``ur_rtde``'s
  ``DashboardClient``, and the answers that mean success ("Dashboard Server e-Series,
  port 29999").

The mode classes are plain ``int`` namespaces (not enums), so values stay plain integers on
the wire, in pickles and in status dictionaries.
"""

from __future__ import annotations

import struct

__all__ = [
    "DASHBOARD_GREETING",
    "DASHBOARD_PORT",
    "DASHBOARD_REPLIES",
    "REALTIME_PORT",
    "RTDE_DATA_PACKAGE",
    "RTDE_GET_URCONTROL_VERSION",
    "RTDE_HEADER",
    "RTDE_IN_USE",
    "RTDE_NOT_FOUND",
    "RTDE_PAUSE",
    "RTDE_PORT",
    "RTDE_REQUEST_PROTOCOL_VERSION",
    "RTDE_SETUP_INPUTS",
    "RTDE_SETUP_OUTPUTS",
    "RTDE_START",
    "RTDE_TEXT_MESSAGE",
    "SAFETY_BIT_ESTOP",
    "SAFETY_BIT_NORMAL",
    "SAFETY_BIT_PROTECTIVE",
    "SAFETY_BIT_ROBOT_ESTOP",
    "SAFETY_BIT_SYSTEM_ESTOP",
    "SCRIPT_PORT",
    "SECONDARY_PORT",
    "DashboardCommand",
    "RobotMode",
    "RuntimeState",
    "SafetyMode",
]

# --- ports ------------------------------------------------------------------------------------

#: RTDE interface (TCP).
RTDE_PORT = 30004
#: Dashboard server (TCP, one text line per command and per answer).
DASHBOARD_PORT = 29999
#: Secondary client interface: takes URScript programs (TCP).
SECONDARY_PORT = 30002
#: Real-time client interface: takes URScript programs (TCP).
REALTIME_PORT = 30003
#: Where ur_rtde uploads its control script (the real-time port, fixed in ur_rtde).
SCRIPT_PORT = REALTIME_PORT

# --- RTDE -------------------------------------------------------------------------------------

#: Every RTDE message starts with ``uint16 size`` (bytes, this header included) and
#: ``uint8 type``, big endian.
RTDE_HEADER = struct.Struct(">HB")

# Package types: the ASCII code of the letter the RTDE guide names each one by.
RTDE_REQUEST_PROTOCOL_VERSION = 86  # 'V'
RTDE_GET_URCONTROL_VERSION = 118  # 'v'
RTDE_TEXT_MESSAGE = 77  # 'M'
RTDE_DATA_PACKAGE = 85  # 'U'
RTDE_SETUP_OUTPUTS = 79  # 'O' (control package setup outputs)
RTDE_SETUP_INPUTS = 73  # 'I' (control package setup inputs)
RTDE_START = 83  # 'S' (control package start)
RTDE_PAUSE = 80  # 'P' (control package pause)

#: The type a recipe setup answers for a field the controller does not offer.
RTDE_NOT_FOUND = "NOT_FOUND"
#: The type a recipe setup answers for an input another client (or a fieldbus) holds.
RTDE_IN_USE = "IN_USE"

# --- controller modes (the values the RTDE outputs report) --------------------------------------


class RobotMode:
    """``robot_mode`` (RTDE output, INT32): the arm's power and brake state."""

    NO_CONTROLLER = -1
    DISCONNECTED = 0
    CONFIRM_SAFETY = 1
    BOOTING = 2
    POWER_OFF = 3
    POWER_ON = 4
    IDLE = 5  # powered, brakes engaged
    BACKDRIVE = 6
    RUNNING = 7  # powered, brakes released
    UPDATING_FIRMWARE = 8

    #: Value -> UR's name (``ROBOT_MODE_<name>``; the dashboard's ``robotmode`` answers it).
    NAMES = {-1: "NO_CONTROLLER", 0: "DISCONNECTED", 1: "CONFIRM_SAFETY", 2: "BOOTING",
             3: "POWER_OFF", 4: "POWER_ON", 5: "IDLE", 6: "BACKDRIVE", 7: "RUNNING",
             8: "UPDATING_FIRMWARE"}


class SafetyMode:
    """``safety_mode`` / ``safety_status`` (RTDE outputs, INT32): the safety system's state."""

    NORMAL = 1
    REDUCED = 2
    PROTECTIVE_STOP = 3
    RECOVERY = 4
    SAFEGUARD_STOP = 5
    SYSTEM_EMERGENCY_STOP = 6
    ROBOT_EMERGENCY_STOP = 7
    VIOLATION = 8
    FAULT = 9
    VALIDATE_JOINT_ID = 10
    UNDEFINED_SAFETY_MODE = 11
    AUTOMATIC_MODE_SAFEGUARD_STOP = 12
    SYSTEM_THREE_POSITION_ENABLING_STOP = 13

    #: Value -> UR's name (``SAFETY_MODE_<name>``; the dashboard's ``safetymode`` and
    #: ``safetystatus`` answer it).
    NAMES = {1: "NORMAL", 2: "REDUCED", 3: "PROTECTIVE_STOP", 4: "RECOVERY",
             5: "SAFEGUARD_STOP", 6: "SYSTEM_EMERGENCY_STOP", 7: "ROBOT_EMERGENCY_STOP",
             8: "VIOLATION", 9: "FAULT", 10: "VALIDATE_JOINT_ID", 11: "UNDEFINED_SAFETY_MODE",
             12: "AUTOMATIC_MODE_SAFEGUARD_STOP", 13: "SYSTEM_THREE_POSITION_ENABLING_STOP"}


class RuntimeState:
    """``runtime_state`` (RTDE output, UINT32): the state of the running program."""

    STOPPING = 0
    STOPPED = 1
    PLAYING = 2
    PAUSING = 3
    PAUSED = 4
    RESUMING = 5


# Bits of ``safety_status_bits`` (RTDE output, UINT32), the ones used here. The guide's
# order: normal, reduced, protective stopped, recovery, safeguard stopped, system emergency
# stopped, robot emergency stopped, emergency stopped, violation, fault, stopped due to safety.
SAFETY_BIT_NORMAL = 0
SAFETY_BIT_PROTECTIVE = 2
SAFETY_BIT_SYSTEM_ESTOP = 5
SAFETY_BIT_ROBOT_ESTOP = 6
SAFETY_BIT_ESTOP = 7  # set with either of the two above

# --- dashboard server -------------------------------------------------------------------------

#: The line the dashboard server sends when a client connects.
DASHBOARD_GREETING = "Connected: Universal Robots Dashboard Server"


class DashboardCommand:
    """Dashboard server commands of the driver's recovery (sent by ``ur_rtde``'s
    ``DashboardClient``; the driver names its recovery steps by them)."""

    CLOSE_SAFETY_POPUP = "close safety popup"
    UNLOCK_PROTECTIVE_STOP = "unlock protective stop"
    POWER_ON = "power on"
    BRAKE_RELEASE = "brake release"


#: Command -> the answer that means it was taken. ``DashboardClient.unlockProtectiveStop``
#: raises on any other answer (within 5 s of the stop the server refuses the unlock).
DASHBOARD_REPLIES = {
    DashboardCommand.CLOSE_SAFETY_POPUP: "closing safety popup",
    DashboardCommand.UNLOCK_PROTECTIVE_STOP: "Protective stop releasing",
    DashboardCommand.POWER_ON: "Powering on",
    DashboardCommand.BRAKE_RELEASE: "Brake releasing",
}
