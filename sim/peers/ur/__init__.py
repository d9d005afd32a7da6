"""A fake Universal Robots controller that the real ``ur_rtde`` client can drive on loopback.

It speaks the controller's own protocols, the subset ``ur_rtde`` uses
(see ``docs/ur_rtde.md`` for the full list):

- **RTDE** (TCP ``rtde_port``, 30004): protocol version negotiation (v1 and v2), controller
  version, output and input recipe setup (each field answered with its RTDE type, unknown or
  refused fields with ``NOT_FOUND`` / ``IN_USE``), start / pause, output data packages at the
  controller rate (500 Hz e-Series, 125 Hz CB3) decimated to each client's frequency, and
  input data packages (decoded by the client's own input recipes into the input registers).
- **Dashboard server** (TCP ``dashboard_port``, 29999): the text protocol, one line per
  command and per answer (version, serial number, modes, power on/off, brake release, unlock
  protective stop, play / stop / pause, popups, ...).
- **Script ports** (TCP ``script_ports``, 30002 and 30003): URScript programs (``def
  name(): ... end``). The control script ``ur_rtde`` uploads is recognised and *emulated*
  through the RTDE registers; other programs are recorded and end at once.

The arm is a kinematic point: the TCP pose integrates servoL targets (a first-order follower
with time constant ``lookahead_time``) and speedL twists, within speed and acceleration
limits; stops decelerate at the commanded rate. Everything the clients send is recorded:
``commands()``, ``programs()``, ``dashboard_log()``, ``events()``.

One module per job:

- ``controller``: :class:`FakeURController`, its state, cycle, safety stop and queries;
- ``server``: the socket loop (one thread, one selector) and the connection base class;
- ``rtde``, ``dashboard``, ``script``: the three protocols (the script module also emulates
  ur_rtde's control script and holds the program state);
- ``kinematics``: the TCP point;
- ``injections``: the faults tests inject;
- ``process``: :class:`FakeURControllerProcess`, the controller in a child process, and the
  command line (``python -m oralnav.sim.peers.ur``).

The values both this fake and the real driver rely on (ports, RTDE package types, robot and
safety modes, dashboard answers) come from :mod:`oralnav.drivers.arm.ur_protocol`.

Why a process. ``ur_rtde``'s Python constructors hold the GIL during their network I/O, so
tests run the fake with :class:`FakeURControllerProcess`; the in-process
:class:`FakeURController` serves any client that does not hold the GIL (other processes,
plain sockets).

Ports. ``ur_rtde`` hard-codes RTDE 30004 and the script port 30003 (only the dashboard port
is an argument of ``DashboardClient``), so a fake for ``ur_rtde`` listens on the standard
ports; give each fake its own loopback address (``127.0.0.2`` ...) to run several at once.
All listening sockets set ``SO_REUSEADDR``, so a fake can be restarted at once on the same
address.
"""

from __future__ import annotations

from oralnav.drivers.arm.ur_protocol import RobotMode, RuntimeState, SafetyMode
from oralnav.sim.peers.ur.controller import FakeURController
from oralnav.sim.peers.ur.process import FakeURControllerProcess
from oralnav.sim.peers.ur.rtde import INPUT_FIELDS, OUTPUT_FIELDS
from oralnav.sim.peers.ur.script import CommandRecord

__all__ = [
    "INPUT_FIELDS",
    "OUTPUT_FIELDS",
    "CommandRecord",
    "FakeURController",
    "FakeURControllerProcess",
    "RobotMode",
    "RuntimeState",
    "SafetyMode",
]
