"""Recorded poses against replayed ones: the figures ``oralnav replay`` reports
(docs/recording.md, "Replay"). Pure: it is handed poses and counts them, it reads nothing.

A pose is *identical* when the replayed 4x4 transform has the recorded one's bits, all 16
float64 of them (``-0.0`` and ``0.0`` differ). Every other pose adds its translation
difference (mm, in the frame it was published in) and rotation difference (deg, the
angle of ``R_rec^T R_rep``) to the maxima. A field recorded but not found by the replay is
*missing*; one found but not recorded is *extra*.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from oralnav.control.geometry import pose_error

__all__ = ["PoseComparison"]


@dataclass
class PoseComparison:
    """Counts and maxima over every pose compared; see the module docstring."""

    poses: int = 0
    identical: int = 0
    missing: int = 0
    extra: int = 0
    max_translation_diff_mm: float = 0.0
    max_rotation_diff_deg: float = 0.0
    worst: dict[str, Any] | None = None
    per_pose: dict[str, dict[str, int]] = field(default_factory=dict)

    def add(self, where: str, pose: str, recorded: Sequence[float] | np.ndarray | None,
            replayed: np.ndarray | None) -> bool:
        """One pose ``pose`` of round ``where`` (a label for the report): the recorded
        transform (16 floats or 4x4, None when not recorded) against the replayed one
        (None when the replay did not find it). True when identical."""
        counts = self.per_pose.setdefault(pose, {"poses": 0, "identical": 0})
        if recorded is None:
            if replayed is not None:
                self.extra += 1
            return False
        self.poses += 1
        counts["poses"] += 1
        if replayed is None:
            self.missing += 1
            return False
        rec = np.asarray(recorded, dtype=np.float64).reshape(4, 4)
        rep = np.asarray(replayed, dtype=np.float64).reshape(4, 4)
        if rec.tobytes() == rep.tobytes():
            self.identical += 1
            counts["identical"] += 1
            return True
        dt, dr = pose_error(rec, rep)
        dt_mm, dr_deg = float(dt) * 1e3, math.degrees(float(dr))
        if dt_mm > self.max_translation_diff_mm or dr_deg > self.max_rotation_diff_deg:
            self.worst = {"round": where, "pose": pose, "translation_diff_mm": dt_mm,
                          "rotation_diff_deg": dr_deg}
        self.max_translation_diff_mm = max(self.max_translation_diff_mm, dt_mm)
        self.max_rotation_diff_deg = max(self.max_rotation_diff_deg, dr_deg)
        return False

    @property
    def all_identical(self) -> bool:
        """Every recorded pose replayed bit for bit, and nothing more found."""
        return self.identical == self.poses and not self.missing and not self.extra

    def summary(self) -> dict[str, Any]:
        """The report's pose figures (JSON-able)."""
        return {"poses": self.poses, "identical": self.identical,
                "differing": self.poses - self.identical - self.missing,
                "missing": self.missing, "extra": self.extra,
                "max_translation_diff_mm": self.max_translation_diff_mm,
                "max_rotation_diff_deg": self.max_rotation_diff_deg,
                "worst": self.worst, "per_pose": dict(sorted(self.per_pose.items()))}
