"""Safety inputs (e-stop, foot pedal): the :class:`SafetyInputs` contract and a lazy
name -> backend registry. Inputs read fail-safe: a disconnected e-stop reads pressed.

::

    from oralnav.drivers.io import open_inputs

    async with open_inputs("sim", clock=clock) as inputs:
        if inputs.state().estop_pressed: ...

``open_inputs`` builds the device (no I/O); ``start()`` (or ``async with``) connects it.
"""

from __future__ import annotations

from typing import Any

from ..registry import backend_class
from .base import InputState, SafetyInputs

__all__ = ["BACKENDS", "InputState", "SafetyInputs", "inputs_class", "open_inputs"]

#: Backend name -> ``"module:Class"``; the module is imported on first use.
BACKENDS: dict[str, str] = {
    "serial": "oralnav.drivers.io.serial_link:SerialInputs",
    "sim": "oralnav.drivers.io.sim:SimInputs",
}


def inputs_class(backend: str) -> type[SafetyInputs]:
    """Import and return the :class:`SafetyInputs` subclass registered as ``backend``.

    Raises:
        DriverInitError: unknown name, or the backend's module (or its SDK) cannot be imported.
    """
    return backend_class("inputs", BACKENDS, backend, SafetyInputs)


def open_inputs(backend: str, **kwargs: Any) -> SafetyInputs:
    """Build (not start) safety inputs of the named backend with their own arguments."""
    return inputs_class(backend)(**kwargs)
