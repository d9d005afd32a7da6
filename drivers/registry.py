"""Lazy backend registries shared by every device kind (camera, arm, effector, inputs).

Each kind keeps a table ``{backend name: "module:Class"}``, in the style of python-can's
interface table. :func:`backend_class` imports a backend's module only when that backend is
asked for, so a machine without one vendor SDK can still use every other backend, and checks
that what it found implements the kind's base class.
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping
from typing import TypeVar

from .errors import DriverInitError

__all__ = ["backend_class"]

BaseT = TypeVar("BaseT")


def backend_class(
    kind: str, backends: Mapping[str, str], name: str, base: type[BaseT]
) -> type[BaseT]:
    """Import and return the class registered as ``name`` in ``backends``.

    Args:
        kind: what the table holds, for messages ("camera", "arm", ...).
        backends: backend name -> ``"package.module:Class"``.
        name: the backend asked for.
        base: the kind's base class; the registered class must subclass it.

    Raises:
        DriverInitError: ``name`` is not in the table (the message lists the known names),
            the entry is malformed, its module cannot be imported (the SDK is missing or fails
            to load; the cause is chained), or the attribute is not a ``base`` subclass.
    """
    try:
        target = backends[name]
    except (KeyError, TypeError):  # TypeError: an unhashable name
        known = ", ".join(sorted(backends)) or "none"
        raise DriverInitError(f"unknown {kind} backend {name!r} (known: {known})") from None
    module_name, sep, class_name = target.partition(":")
    if not sep or not module_name or not class_name:
        raise DriverInitError(
            f"{kind} backend {name!r}: entry {target!r} is not of the form 'module:Class'"
        )
    try:
        module = importlib.import_module(module_name)
    except Exception as exc:  # an SDK can fail to load with any error (OSError, ...)
        raise DriverInitError(
            f"{kind} backend {name!r} is not available: cannot import {module_name} "
            f"({type(exc).__name__}: {exc})"
        ) from exc
    cls = getattr(module, class_name, None)
    if not (isinstance(cls, type) and issubclass(cls, base)):
        raise DriverInitError(
            f"{kind} backend {name!r}: {target} is not a {base.__name__} subclass"
        )
    return cls
