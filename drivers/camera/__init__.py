"""Cameras: the :class:`Camera` contract and a lazy name -> backend registry.

Backends live one per module and are imported only when asked for, so a machine without a
camera SDK (Aravis, ...) can still use the others::

    from oralnav.drivers.camera import open_camera

    async with open_camera("replay", path="recording/left", name="left") as cam:
        async for frame in cam:
            ...

``open_camera`` builds the camera (no I/O); ``start()`` (or ``async with``) opens it.
"""

from __future__ import annotations

import importlib
from typing import Any

from ..errors import DriverInitError
from .base import Camera, CameraFrame

__all__ = ["BACKENDS", "Camera", "CameraFrame", "camera_class", "open_camera"]

#: Backend name -> ``"module:Class"``; the module is imported on first use.
#: Planned: "sim", "aravis", "v4l2".
BACKENDS: dict[str, str] = {
    "replay": "oralnav.drivers.camera.replay:ReplayCamera",
}


def camera_class(backend: str) -> type[Camera]:
    """Import and return the :class:`Camera` subclass registered as ``backend``.

    Raises:
        DriverInitError: unknown name, or the backend's module (or its SDK) cannot be imported.
    """
    try:
        target = BACKENDS[backend]
    except (KeyError, TypeError):
        known = ", ".join(sorted(BACKENDS))
        raise DriverInitError(f"unknown camera backend {backend!r} (known: {known})") from None
    module_name, _, class_name = target.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise DriverInitError(
            f"camera backend {backend!r} is not available: cannot import {module_name} ({exc})"
        ) from exc
    cls = getattr(module, class_name, None)
    if not (isinstance(cls, type) and issubclass(cls, Camera)):
        raise DriverInitError(
            f"camera backend {backend!r}: {target} is not a Camera subclass"
        )
    return cls


def open_camera(backend: str, **kwargs: Any) -> Camera:
    """Build (not start) a camera of the named backend with the backend's own arguments.

    Example: ``open_camera("replay", path="rec/left", name="left", loop=True)``.
    """
    return camera_class(backend)(**kwargs)
