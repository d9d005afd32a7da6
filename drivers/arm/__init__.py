"""Robot arms: the :class:`Arm` contract and a lazy name -> backend registry.

::

    from oralnav.drivers.arm import open_arm

    async with open_arm("sim", clock=clock) as arm:
        arm.servo(T_B_tcp, 0.002)

``open_arm`` builds the arm (no I/O); ``start()`` (or ``async with``) connects it.
"""

from __future__ import annotations

from typing import Any

from ..registry import backend_class
from .base import Arm, ArmCommandError, ArmState

__all__ = ["BACKENDS", "Arm", "ArmCommandError", "ArmState", "arm_class", "open_arm"]

#: Backend name -> ``"module:Class"``; the module is imported on first use.
BACKENDS: dict[str, str] = {
    "sim": "oralnav.drivers.arm.sim:SimArm",
    "ur": "oralnav.drivers.arm.ur:URArm",
}


def arm_class(backend: str) -> type[Arm]:
    """Import and return the :class:`Arm` subclass registered as ``backend``.

    Raises:
        DriverInitError: unknown name, or the backend's module (or its SDK) cannot be imported.
    """
    return backend_class("arm", BACKENDS, backend, Arm)


def open_arm(backend: str, **kwargs: Any) -> Arm:
    """Build (not start) an arm of the named backend with the backend's own arguments."""
    return arm_class(backend)(**kwargs)
