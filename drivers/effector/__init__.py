"""End-effectors: the :class:`EndEffector` contract (a tendon-driven wrist), its kinematics
and a lazy name -> backend registry.

::

    from oralnav.drivers.effector import open_effector

    async with open_effector("sim", clock=clock) as wrist:
        wrist.command([0.0, 0.2, -0.1, 0.3])   # roll, pitch, yaw, jaw (rad)

``open_effector`` builds the device (no I/O); ``start()`` (or ``async with``) connects it.
"""

from __future__ import annotations

from typing import Any

from ..registry import backend_class
from .base import EffectorState, EndEffector
from .kinematics import JOINTS, EffectorCommandError, WristKinematics

__all__ = [
    "BACKENDS",
    "JOINTS",
    "EffectorCommandError",
    "EffectorState",
    "EndEffector",
    "WristKinematics",
    "effector_class",
    "open_effector",
]

#: Backend name -> ``"module:Class"``; the module is imported on first use.
BACKENDS: dict[str, str] = {
    "canopen": "oralnav.drivers.effector.canopen_drive:CanopenDriveEffector",
    "modbus": "oralnav.drivers.effector.modbus_drive:ModbusDriveEffector",
    "sim": "oralnav.drivers.effector.sim:SimEffector",
}


def effector_class(backend: str) -> type[EndEffector]:
    """Import and return the :class:`EndEffector` subclass registered as ``backend``.

    Raises:
        DriverInitError: unknown name, or the backend's module (or its SDK) cannot be imported.
    """
    return backend_class("end-effector", BACKENDS, backend, EndEffector)


def open_effector(backend: str, **kwargs: Any) -> EndEffector:
    """Build (not start) an end-effector of the named backend with its own arguments."""
    return effector_class(backend)(**kwargs)
