"""Calibration files: one TOML file per calibration kind, with its provenance.

A calibration file records what was measured (``[values]``), how well (``[residuals]``,
``[quality]``), how (``method``), when (``created``, UTC) and from what (``[samples]``: the
number of samples and the SHA-256 of their bytes), for one cell (``cell``: files from another
cell are refused). Layout and keys per kind are in docs/formats.md ("Calibration files").

Writes are atomic and re-read before they replace anything, so a failed or invalid write
keeps the previous calibration. Loading validates everything (kind, cell, finite values,
proper rotations, known units) and converts lengths to metres; errors are
:class:`~oralnav.config.errors.ConfigError` naming the file and key.
"""

from __future__ import annotations

import hashlib
import tomllib
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field

from oralnav.control.geometry import as_transform

from .errors import ConfigError
from .loader import Float, Int, Strict, atomic_write_text, build, dump_toml, read_toml, validate

__all__ = ["FORMAT", "KINDS", "LENGTH_UNITS", "Calibration", "SampleInfo", "load_calibration",
           "samples_digest", "save_calibration"]

#: Version of the calibration file layout; bumped when a key changes meaning.
FORMAT = 1

#: Length units a file may declare, with their size in metres.
LENGTH_UNITS = {"m": 1.0, "mm": 1e-3}

_Spec = Literal["transform", "point", "scalar", "seconds", "text", "rig"]

#: Each kind's ``[values]`` keys and what they hold. Transforms are 4x4 rigid ``T_a_b``
#: (pose of b in a), points (3,); both in the file's length unit. ``seconds``: one number
#: in seconds, whatever the length unit. ``rig`` is a rig
#: document (docs/formats.md "Rig") nested in the file: lengths in metres, pixels.
KINDS: dict[str, dict[str, _Spec]] = {
    # tool tip in the tool (pointer) frame, pivot point in the tracker frame (eq. 3, [28])
    "pivot": {"tip_offset": "point", "pivot_point": "point"},
    # stereo camera in the robot base and the robot marker on the TCP (eq. 5)
    "hand_eye": {"T_B_C": "transform", "T_tcp_RM": "transform"},
    # endoscope in the opener-marker frame (eqs. 1-2)
    "endoscope_opener": {"T_OM_En": "transform"},
    # end-effector zero frame in the robot-marker frame (eqs. 3-4)
    "effector_zero": {"T_RM_E0": "transform"},
    # end-effector in the end-effector-marker frame (eq. 7)
    "effector_marker": {"T_EM_E": "transform"},
    # intrinsics (and for stereo the extrinsics) as a rig
    "camera": {"rig": "rig"},
    "stereo": {"rig": "rig"},
    # how late the stereo camera's timestamps are against the arm's clock (s; the daemon
    # subtracts it): oralnav calibrate temporal
    "temporal": {"offset_s": "seconds"},
}


class _Samples(Strict):
    count: Int = Field(ge=1)
    sha256: str = Field(pattern=r"^[0-9a-f]{64}$")
    source: str = ""


class _Units(Strict):
    length: str = "m"


class _File(Strict):
    kind: str
    format: Int
    cell: str = Field(min_length=1)
    method: str = Field(min_length=1)
    created: str = Field(min_length=1)
    units: _Units = _Units()
    samples: _Samples
    values: dict[str, Any]
    residuals: dict[str, Float | list[Float]] = Field(default_factory=dict)
    quality: dict[str, Float | Int | str | list[Float]] = Field(default_factory=dict)


@dataclass(frozen=True)
class SampleInfo:
    """Where a calibration's samples came from: how many, the SHA-256 of their bytes and an
    optional description (a file name, "simulated cell")."""

    count: int
    sha256: str
    source: str = ""


@dataclass(frozen=True, eq=False)
class Calibration:
    """One calibration, in SI units (lengths in metres).

    Attributes:
        kind: one of :data:`KINDS`.
        cell: the cell (robot, cameras, opener) it belongs to; must match the
            configuration's ``[calibration] cell`` when loaded for a daemon.
        method: the solver (e.g. ``"algebraic"``, ``"refined from shah"``).
        values: key -> value per :data:`KINDS` (4x4 or (3,) arrays in metres, a Rig...).
        residuals: name -> number or list; the name carries the unit (``rms_mm``).
        quality: name -> number, text or list (spread, condition, sigma...).
        samples: what the calibration was computed from.
        created: ISO 8601 UTC time of the calibration.
        source: the file it was loaded from, if any.
    """

    kind: str
    cell: str
    method: str
    values: Mapping[str, Any]
    samples: SampleInfo
    residuals: Mapping[str, float | list[float]] = field(default_factory=dict)
    quality: Mapping[str, Any] = field(default_factory=dict)
    created: str = ""
    source: str = ""

    def __getitem__(self, key: str) -> Any:
        return self.values[key]


def samples_digest(arrays: Iterable[np.ndarray | bytes]) -> str:
    """SHA-256 over the samples (float64 arrays in C order, or raw bytes), in order."""
    h = hashlib.sha256()
    for a in arrays:
        h.update(a if isinstance(a, bytes) else np.ascontiguousarray(a, dtype=float).tobytes())
    return h.hexdigest()


def _now() -> str:
    return datetime.now(UTC).replace(microsecond=0).isoformat().replace("+00:00", "Z")


def _value_from_file(path: Path, key: str, spec: _Spec, raw: Any, scale: float) -> Any:
    """Check one ``[values]`` entry against its spec and return it in SI."""
    if spec == "text":
        if not isinstance(raw, str):
            raise ConfigError(path, key, f"expected text, got {type(raw).__name__}")
        return raw
    if spec == "rig":
        from .rig import rig_from_dict  # the rig schema validates its own keys
        if not isinstance(raw, dict):
            raise ConfigError(path, key, "expected a rig table (reference, cameras)")
        try:
            return rig_from_dict(raw, path)
        except ConfigError as exc:
            raise ConfigError(path, f"{key}.{exc.key}" if exc.key else key, exc.reason) from None
    try:
        arr = np.array(raw, dtype=float)
    except (TypeError, ValueError):
        raise ConfigError(path, key, "expected numbers") from None
    if not np.all(np.isfinite(arr)):
        raise ConfigError(path, key, "non-finite value (nan or inf)")
    if spec in ("scalar", "seconds"):
        if arr.shape != ():
            raise ConfigError(path, key, f"expected one number, got shape {arr.shape}")
        return float(arr) * (scale if spec == "scalar" else 1.0)
    if spec == "point":
        if arr.shape != (3,):
            raise ConfigError(path, key, f"expected a point [x, y, z], got shape {arr.shape}")
        return arr * scale
    # transform
    if arr.shape != (4, 4):
        raise ConfigError(path, key, f"expected a 4x4 transform, got shape {arr.shape}")
    arr[:3, 3] *= scale
    build(path, key, lambda: as_transform(arr, what=key.rpartition(".")[2]))
    return arr


def calibration_from_dict(data: Mapping[str, Any], path: str | Path, *,
                          kind: str | None = None, cell: str | None = None) -> Calibration:
    """Validate a parsed calibration document; see :func:`load_calibration`."""
    path = Path(path)
    doc = validate(_File, data, path)
    if doc.kind not in KINDS:
        raise ConfigError(path, "kind", f"unknown calibration kind {doc.kind!r}; known: "
                          f"{sorted(KINDS)}")
    if kind is not None and doc.kind != kind:
        raise ConfigError(path, "kind", f"this is a {doc.kind!r} calibration; a {kind!r} one "
                          "is needed here")
    if doc.format != FORMAT:
        raise ConfigError(path, "format", f"calibration file format {doc.format} is not "
                          f"supported (this version reads format {FORMAT})")
    if cell is not None and doc.cell != cell:
        raise ConfigError(path, "cell", f"calibration of cell {doc.cell!r}, but this "
                          f"configuration is for cell {cell!r}: a calibration from another "
                          "cell would put the robot in the wrong place; recalibrate")
    if doc.units.length not in LENGTH_UNITS:
        raise ConfigError(path, "units.length", f"unknown length unit {doc.units.length!r}; "
                          f"use one of {sorted(LENGTH_UNITS)}")
    scale = LENGTH_UNITS[doc.units.length]
    spec = KINDS[doc.kind]
    missing = sorted(set(spec) - set(doc.values))
    if missing:
        raise ConfigError(path, f"values.{missing[0]}", f"missing (a {doc.kind} calibration "
                          f"holds {sorted(spec)})")
    extra = sorted(set(doc.values) - set(spec))
    if extra:
        raise ConfigError(path, f"values.{extra[0]}", "unknown key (check its spelling and "
                          "section)")
    values = {k: _value_from_file(path, f"values.{k}", s, doc.values[k], scale)
              for k, s in spec.items()}
    return Calibration(kind=doc.kind, cell=doc.cell, method=doc.method, values=values,
                       samples=SampleInfo(doc.samples.count, doc.samples.sha256,
                                          doc.samples.source),
                       residuals=dict(doc.residuals), quality=dict(doc.quality),
                       created=doc.created, source=str(path))


def load_calibration(path: str | Path, *, kind: str | None = None,
                     cell: str | None = None) -> Calibration:
    """Read and validate a calibration file.

    ``kind`` and ``cell``, when given, must match the file's. Raises ``ConfigError``
    naming the file and key on any problem (missing file, wrong kind or cell, a non-rigid
    transform, a non-finite value, an unknown unit or key).
    """
    return calibration_from_dict(read_toml(path), path, kind=kind, cell=cell)


def _plain(v: Any) -> Any:
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, list | tuple):
        return [_plain(x) for x in v]
    return v


def calibration_to_dict(cal: Calibration) -> dict[str, Any]:
    """The file document of ``cal`` (lengths written in metres)."""
    from .rig import rig_to_dict

    if cal.kind not in KINDS:
        raise ValueError(f"unknown calibration kind {cal.kind!r}; known: {sorted(KINDS)}")
    values = {}
    for k, spec in KINDS[cal.kind].items():
        if k not in cal.values:
            raise ValueError(f"{cal.kind} calibration: missing value {k!r}")
        v = cal.values[k]
        values[k] = rig_to_dict(v) if spec == "rig" else _plain(np.asarray(v, dtype=float)) \
            if spec in ("transform", "point", "scalar", "seconds") else v
    return {"kind": cal.kind, "format": FORMAT, "cell": cal.cell, "method": cal.method,
            "created": cal.created or _now(), "units": {"length": "m"},
            "samples": {"count": int(cal.samples.count), "sha256": cal.samples.sha256,
                        "source": cal.samples.source},
            "values": values,
            "residuals": {k: _plain(v) for k, v in cal.residuals.items()},
            "quality": {k: _plain(v) for k, v in cal.quality.items()}}


def save_calibration(cal: Calibration, path: str | Path) -> Path:
    """Write ``cal`` to ``path`` atomically; returns the path.

    The text is parsed and validated again before it replaces anything, so an invalid
    calibration (a non-rigid transform, a NaN) raises ``ConfigError`` and the previous file
    stays as it was; ``OSError`` on I/O failure, also leaving the old file intact.
    """
    path = Path(path)
    header = (f"# oralnav {cal.kind} calibration (docs/formats.md, \"Calibration files\").\n"
              "# Lengths in metres, intrinsics in pixels; residual keys carry their unit.\n")
    text = build(path, "", lambda: header + dump_toml(calibration_to_dict(cal)))
    calibration_from_dict(build(path, "", lambda: tomllib.loads(text)), path, kind=cal.kind,
                          cell=cal.cell)
    atomic_write_text(path, text)
    return path
