"""Fault injections of the fake controller, for tests: safety stops, a vanishing, silent or
disconnecting controller, refused RTDE fields, and the TCP's pose and wrench.

- :meth:`~Injections.inject_protective_stop`: ``safety_mode`` 3, bit 2 of
  ``safety_status_bits``, the TCP brakes at 3x ``max_accel``, the program stops; cleared by
  the dashboard's ``unlock protective stop`` or :meth:`~Injections.clear_protective_stop`;
- :meth:`~Injections.inject_emergency_stop`: ``safety_mode`` 7 (6 with ``system``), bits 6
  (5) and 7, the TCP brakes, the program stops, the arm powers off; after
  :meth:`~Injections.release_emergency_stop` it needs ``power on`` and ``brake release``;
- :meth:`~Injections.vanish` / :meth:`~Injections.come_back`: every connection closes and
  nothing listens, then it listens again (the arm and its program go on meanwhile);
- :meth:`~Injections.kill_connections`; :meth:`~Injections.freeze` (connections stay open,
  nothing is sent) / :meth:`~Injections.unfreeze`;
- :meth:`~Injections.refuse_field` (a recipe field answered ``NOT_FOUND`` or ``IN_USE``) /
  :meth:`~Injections.accept_all_fields`;
- :meth:`~Injections.apply_wrench`, :meth:`~Injections.set_pose`.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np

from oralnav.drivers.arm.ur_protocol import RTDE_IN_USE, RTDE_NOT_FOUND, RobotMode, SafetyMode
from oralnav.sim.peers.ur.kinematics import TcpPoint, as_pose6
from oralnav.sim.peers.ur.server import Conn

__all__ = ["Injections"]


class Injections:
    """The public injections of :class:`~oralnav.sim.peers.ur.controller.FakeURController`
    (callable from any thread)."""

    _lock: threading.RLock
    _tcp: TcpPoint
    _wrench: tuple[float, ...]  # N, N m, base frame
    _robot_mode: int
    _safety_mode: int
    _estop_kind: int
    _refused: dict[str, str]
    _conns: set[Conn]
    _listeners: list[Any]
    _frozen: bool
    _event: Callable[..., None]
    _protective_stop: Callable[[str], None]
    _stop_program: Callable[[str], None]
    _drop: Callable[[Conn], None]
    _listen: Callable[[], None]
    _unlisten: Callable[[], None]
    _in_loop: Callable[[Callable[[], Any]], Any]

    def set_pose(self, pose: Iterable[float] | np.ndarray) -> None:
        """Put the TCP at ``pose`` (6 values or a 4x4), at rest."""
        pose6 = as_pose6(pose)
        with self._lock:
            self._tcp.set_pose(pose6)

    def apply_wrench(self, wrench: Iterable[float]) -> None:
        """What ``actual_TCP_force`` reports (N, N m, base frame)."""
        w = tuple(float(x) for x in wrench)
        if len(w) != 6:
            raise ValueError(f"a wrench is 6 numbers, got {w!r}")
        with self._lock:
            self._wrench = w

    def inject_protective_stop(self) -> None:
        """A protective stop: the TCP brakes, the program stops, ``safety_mode`` 3."""
        with self._lock:
            self._protective_stop("injected")

    def clear_protective_stop(self) -> None:
        """Clear it as from the teach pendant (the program stays stopped)."""
        with self._lock:
            if self._safety_mode == SafetyMode.PROTECTIVE_STOP:
                self._safety_mode = SafetyMode.NORMAL

    def inject_emergency_stop(self, system: bool = False) -> None:
        """The robot's (or, ``system``, the system's) e-stop opens: the TCP brakes, the
        program stops, the arm powers off."""
        with self._lock:
            kind = SafetyMode.SYSTEM_EMERGENCY_STOP if system else SafetyMode.ROBOT_EMERGENCY_STOP
            self._estop_kind = kind
            self._safety_mode = kind
            self._tcp.stop(3 * self._tcp.amax)
            self._stop_program("emergency stop")
            self._robot_mode = RobotMode.POWER_OFF
            self._event("emergency_stop", kind=SafetyMode.NAMES[kind])

    def release_emergency_stop(self) -> None:
        """The e-stop button is released: safety normal, the arm stays powered off."""
        with self._lock:
            if self._estop_kind:
                self._estop_kind = 0
                self._safety_mode = SafetyMode.NORMAL
                self._event("emergency_stop_released")

    def refuse_field(self, name: str, answer: str = RTDE_NOT_FOUND) -> None:
        """Answer the recipe field ``name`` with ``answer`` (``NOT_FOUND`` or ``IN_USE``)
        from now on."""
        if answer not in (RTDE_NOT_FOUND, RTDE_IN_USE):
            raise ValueError(f"answer must be NOT_FOUND or IN_USE, got {answer!r}")
        with self._lock:
            self._refused[name] = answer

    def accept_all_fields(self) -> None:
        """Answer every recipe field with its type again."""
        with self._lock:
            self._refused.clear()

    def kill_connections(self) -> None:
        """Close every client connection (the controller keeps listening)."""
        def kill() -> None:
            for conn in list(self._conns):
                self._drop(conn)
            self._event("connections_killed")
        self._in_loop(kill)

    def vanish(self) -> None:
        """The controller goes away: every connection closes and nothing listens. The arm
        goes on (its program keeps running until its watchdog, if armed, stops it)."""
        def gone() -> None:
            for conn in list(self._conns):
                self._drop(conn)
            self._unlisten()
            self._event("vanished")
        self._in_loop(gone)

    def come_back(self) -> None:
        """Listen again after :meth:`vanish`."""
        def back() -> None:
            if not self._listeners:
                self._listen()
                self._event("came_back")
        self._in_loop(back)

    def freeze(self) -> None:
        """Stop sending data packages (connections stay open): a hung controller."""
        with self._lock:
            self._frozen = True

    def unfreeze(self) -> None:
        """Send data packages again after :meth:`freeze`."""
        with self._lock:
            self._frozen = False
