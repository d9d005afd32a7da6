"""Build a :class:`~oralnav.control.vision.tracker.Tracker` from files: the rig, the marker
fields and the rigid bodies (docs/formats.md, docs/tracking.md).

The tracker itself never reads a file (control does no I/O); this is where its files are
read and checked, each error naming the file and key (:class:`~oralnav.config.errors.ConfigError`).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from oralnav.config.fields import load_fields
from oralnav.config.rig import load_rig
from oralnav.config.rigid_bodies import load_rigid_bodies
from oralnav.control.vision.rigid_body import RigidBody
from oralnav.control.vision.tracker import Method, Tracker

__all__ = ["load_tracker"]


def load_tracker(rig_path: str | Path, fields_path: str | Path | None = None,
                 method: Method = "nvgba", *,
                 bodies: Sequence[RigidBody | str | Path | tuple[str, str | Path]] = (),
                 body_dictionary: str = "DICT_ARUCO_ORIGINAL", **kwargs: Any) -> Tracker:
    """A tracker over the rig TOML at ``rig_path``, the marker fields of ``fields_path``
    and ``bodies``; ``kwargs`` go to :class:`Tracker` (``mode``, ``weighting``, ...).

    ``fields_path`` may be ``None`` when ``bodies`` are given. Each body is a
    :class:`RigidBody`, or a peer tag table (millimetres, read by
    :func:`oralnav.config.rigid_bodies.load_rigid_body` with tags of ``body_dictionary``):
    a path (the body is named after the file's stem) or a ``(name, path)`` pair.
    """
    rig = load_rig(rig_path)
    fields = load_fields(fields_path) if fields_path is not None else {}
    return Tracker(rig, list(fields.values()), method=method,
                   bodies=load_rigid_bodies(bodies, body_dictionary), **kwargs)
