"""What the operator REST API reads and answers (docs/api.md): the request bodies, the
error answers the OpenAPI schema declares, the suture target the core keeps, and
:func:`jsonable`, which turns the core's answers into plain JSON values.

No FastAPI here: the daemon core takes its requests in these types without depending on
the HTTP layer (``daemon/api.py``) that parses them. Units: metres; frames as named on
each field (``OM``: the opener's marker field, ``F``: the model's Center frame).
"""

# no ``from __future__ import annotations``: pydantic builds each model from its field
# annotations evaluated right here, nothing left to resolve later by name
import math
from collections.abc import Mapping
from enum import Enum
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, StringConstraints, field_validator

from oralnav.config.loader import Float

#: largest distance of a suture target from the opener-marker origin (m)
MAX_TARGET_RADIUS = 0.2
#: most targets one POST /targets may set
MAX_TARGETS = 64
#: a tissue normal shorter than this cannot be normalised (dimensionless)
MIN_NORMAL_NORM = 1e-6
#: longest planning-scene path a POST /guide/plan may name (characters)
MAX_PATH_CHARS = 4096

ProcedureAction = Literal["start", "pause", "resume", "abort"]
Device = Literal["effector", "arm"]
NeedleStep = Literal["NG", "NH", "ND", "NR", "NP"]
_Vec3 = tuple[Float, Float, Float]


# -- request bodies --------------------------------------------------------------------
class _Body(BaseModel):
    # unknown keys are errors (a typo must not be silently ignored); numbers are finite
    # and real numbers (no "0.1" strings, no booleans)
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class SutureTarget(_Body):
    """A planned suture point in the opener-marker frame ``OM``.

    ``p_OM``: position (m), at most ``MAX_TARGET_RADIUS`` from the ``OM`` origin.
    ``n_OM``: optional tissue normal; any finite non-zero 3-vector, stored normalised.
    """

    name: Annotated[str, StringConstraints(min_length=1, max_length=64,
                                           pattern=r"^[A-Za-z0-9_.-]+$")]
    p_OM: _Vec3
    n_OM: _Vec3 | None = None

    @field_validator("p_OM")
    @classmethod
    def _within_reach(cls, v: tuple[float, float, float]) -> tuple[float, float, float]:
        r = math.hypot(*v)
        if r > MAX_TARGET_RADIUS:
            raise ValueError(f"|p_OM| = {r:.4g} m is farther than {MAX_TARGET_RADIUS} m from "
                             "the opener marker (metres expected, not millimetres?)")
        return v

    @field_validator("n_OM")
    @classmethod
    def _unit(cls, v: tuple[float, float, float] | None) -> tuple[float, float, float] | None:
        if v is None:
            return v
        n = math.hypot(*v)
        if not n >= MIN_NORMAL_NORM:
            raise ValueError(f"n_OM has norm {n:.3g}; a tissue normal must be non-zero")
        return (v[0] / n, v[1] / n, v[2] / n)


class TargetsBody(_Body):
    """``POST /targets``: the full list of suture targets (replaces the current one)."""

    targets: list[SutureTarget] = Field(max_length=MAX_TARGETS)

    @field_validator("targets")
    @classmethod
    def _unique(cls, v: list[SutureTarget]) -> list[SutureTarget]:
        seen: set[str] = set()
        dup = sorted({t.name for t in v if t.name in seen or seen.add(t.name)})
        if dup:
            raise ValueError(f"target names must be unique; repeated: {', '.join(dup)}")
        return v


class SelectTargetBody(_Body):
    """``POST /targets/select``: the surgeon's current suture target, by name."""

    name: Annotated[str, StringConstraints(min_length=1, max_length=64,
                                           pattern=r"^[A-Za-z0-9_.-]+$")]


class EstopBody(_Body):
    """``POST /estop`` (the body is optional)."""

    reason: str = Field("operator e-stop", max_length=500)


_Row4 = tuple[Float, Float, Float, Float]


class GuidePlanBody(_Body):
    """``POST /guide/plan``: plan a guided insertion.

    ``scene``: a planning scene TOML file (docs/formats.md, as ``oralnav plan place
    --scene`` reads it), absolute or relative to the daemon's working directory.
    ``T_OM_F``: the registration, the surrogate model's Center frame ``F`` in the opener
    marker frame ``OM`` (4x4, metres, rigid; checked by the core). ``seed``: overrides the
    scene's PSO seed.
    """

    scene: Annotated[str, StringConstraints(min_length=1, max_length=MAX_PATH_CHARS)]
    T_OM_F: tuple[_Row4, _Row4, _Row4, _Row4] = Field(
        description="rigid 4x4 transform, row by row, metres: an orthonormal rotation with "
                    "determinant +1 and the last row [0, 0, 0, 1] (anything else is 422)",
        json_schema_extra=lambda schema: schema["prefixItems"].__setitem__(
            3, {"const": [0.0, 0.0, 0.0, 1.0]}))
    seed: Annotated[int, Field(ge=0, le=2**32 - 1, strict=True)] | None = None

    @field_validator("T_OM_F")
    @classmethod
    def _rigid(cls, v: tuple[tuple[float, ...], ...]) -> tuple[tuple[float, ...], ...]:
        # the same check the planning applies (daemon/guidance.py), at the door: a 4x4
        # that is not rigid is refused naming what is wrong before anything is planned
        from oralnav.daemon.guidance import GuidePlanError, check_registration

        try:
            check_registration(v)
        except GuidePlanError as exc:
            raise ValueError(str(exc)) from None
        return v

    @field_validator("scene")
    @classmethod
    def _no_nul(cls, v: str) -> str:
        if "\0" in v:
            raise ValueError("a path cannot hold a NUL character")
        return v


class NeedleCellBody(_Body):
    """``POST /needle/cell``: load simulated needle trial ``trial`` (a seed) with imaging
    nuisances scaled by ``difficulty`` (0..2; above 1 a harder layout too:
    ``oralnav.sim.world.needle_trials.MAX_DIFFICULTY``), its drive guided by ``servo``:
    ``off`` (open-loop), ``looks`` (servoed on looks every few poses) or ``stream``
    (servoed on every frame of the needle tracking task)."""

    trial: Annotated[int, Field(ge=0, le=2**32 - 1, strict=True)]
    difficulty: Annotated[float, Field(ge=0.0, le=2.0)] = 1.0
    servo: Literal["off", "looks", "stream"] = "off"


class TemporalCalibrationBody(_Body):
    """``POST /calibration/temporal``: the arm's excitation (docs/calibration.md, "Temporal
    calibration"): peak ``amplitude_mm`` (mm; the path is a 3-D Lissajous of it, its z
    half of it), ``period_s`` (s, the slowest axis' period), ``duration_s`` (s, at least two
    periods), and the offsets searched, ``+-search_ms`` (ms)."""

    amplitude_mm: Annotated[Float, Field(gt=0.0, le=20.0)] = 5.0
    period_s: Annotated[Float, Field(ge=1.0, le=20.0)] = 4.0
    duration_s: Annotated[Float, Field(ge=2.0, le=120.0)] = 24.0
    search_ms: Annotated[Float, Field(ge=10.0, le=500.0)] = 200.0


class RecordingStartBody(_Body):
    """``POST /recording/start`` (docs/recording.md): record to ``path`` (an ``.mcap``
    file that does not exist yet; a relative one goes where a relative audit log goes, the
    daemon's state folder), the frames of every ``every``-th tracked round as ``images`` (``raw``:
    lossless RawImage; ``png``: lossless, about 10 times the CPU; ``jpeg`` at
    ``jpeg_quality``; ``none``), MCAP chunks compressed with ``compression``, at most
    ``queue_rounds`` rounds of frames waiting for the disk (beyond, frames are dropped and
    counted; poses never are)."""

    path: Annotated[str, StringConstraints(min_length=1, max_length=MAX_PATH_CHARS)]
    every: Annotated[int, Field(ge=1, le=10_000, strict=True)] = 1
    images: Literal["raw", "png", "jpeg", "none"] = "raw"
    compression: Literal["zstd", "lz4", "none"] = "none"
    jpeg_quality: Annotated[int, Field(ge=1, le=100, strict=True)] = 90
    queue_rounds: Annotated[int, Field(ge=1, le=1024, strict=True)] = 8

    @field_validator("path")
    @classmethod
    def _mcap_file(cls, v: str) -> str:
        if "\0" in v:
            raise ValueError("a path cannot hold a NUL character")
        if not v.lower().endswith(".mcap"):
            raise ValueError("the recording must be an .mcap file")
        return v


# -- error answers, as the OpenAPI schema declares them -------------------------------------
class Problem(BaseModel):
    """An error answer: ``detail`` says what was wrong, in words."""

    detail: str


class WhereWhy(BaseModel):
    """One thing wrong in a request: where (``targets[0].p_OM[1]``) and why."""

    where: str
    reason: str


class ValidationProblem(Problem):
    """A body or path that does not validate (422), or a body that is not JSON (400):
    ``detail`` joins the ``errors`` into one line."""

    errors: list[WhereWhy] = []


# -- answers as JSON ---------------------------------------------------------------------
def jsonable(x: Any) -> Any:
    """``x`` as plain JSON values: numpy arrays and scalars become lists and numbers, models
    become dicts, non-finite floats become ``null`` (standard JSON has no NaN)."""
    if x is None or isinstance(x, bool | int | str):
        return x
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, BaseModel):
        return jsonable(x.model_dump())
    if isinstance(x, Mapping):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple | set | frozenset):
        return [jsonable(v) for v in x]
    if isinstance(x, Enum):
        return jsonable(x.value)
    if hasattr(x, "tolist"):  # numpy arrays and scalars
        return jsonable(x.tolist())
    raise TypeError(f"cannot send a {type(x).__name__} as JSON")
