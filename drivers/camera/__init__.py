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

from typing import Any

from ..registry import backend_class
from .base import Camera, CameraFrame

__all__ = ["BACKENDS", "Camera", "CameraFrame", "camera_class", "open_camera"]

#: Backend name -> ``"module:Class"``; the module is imported on first use.
BACKENDS: dict[str, str] = {
    "aravis": "oralnav.drivers.camera.aravis:AravisCamera",
    "mcap": "oralnav.drivers.camera.mcap_replay:McapCamera",
    "replay": "oralnav.drivers.camera.replay:ReplayCamera",
    "sim": "oralnav.drivers.camera.sim:SimCamera",
    "v4l2": "oralnav.drivers.camera.v4l2:V4L2Camera",
}


def camera_class(backend: str) -> type[Camera]:
    """Import and return the :class:`Camera` subclass registered as ``backend``.

    Raises:
        DriverInitError: unknown name, or the backend's module (or its SDK) cannot be imported.
    """
    return backend_class("camera", BACKENDS, backend, Camera)


def open_camera(backend: str, **kwargs: Any) -> Camera:
    """Build (not start) a camera of the named backend with the backend's own arguments.

    Example: ``open_camera("replay", path="rec/left", name="left", loop=True)``.
    """
    return camera_class(backend)(**kwargs)
