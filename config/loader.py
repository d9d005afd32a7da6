"""Reading and writing the project's TOML files.

Every file is read whole, validated by a pydantic model (unknown keys rejected, bounds
declared on the model) and only then turned into objects, so a broken file never
half-starts anything. Writes are atomic: a temporary file in the same folder, fsync,
rename, so a crash or a bad value never leaves a half-written file or loses the old one.
"""

from __future__ import annotations

import math
import os
import tempfile
import tomllib
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any, TypeVar

from pydantic import BaseModel, ConfigDict, ValidationError

from .errors import ConfigError

M = TypeVar("M", bound=BaseModel)
T = TypeVar("T")


class Strict(BaseModel):
    """Base of every file schema: unknown keys are errors, values are frozen."""

    model_config = ConfigDict(extra="forbid", frozen=True, strict=False)


def read_toml(path: str | Path) -> dict[str, Any]:
    """Parse a TOML file, raising :class:`ConfigError` naming the file on any failure."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise ConfigError(path, "", "file not found") from None
    except OSError as exc:
        raise ConfigError(path, "", f"cannot read: {exc.strerror or exc}") from None
    try:
        return tomllib.loads(raw.decode("utf-8"))
    except UnicodeDecodeError:
        raise ConfigError(path, "", "not UTF-8 text") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(path, "", f"not valid TOML: {exc}") from None


def _loc(loc: Iterable[Any]) -> str:
    # pydantic adds the union member or validator name to some locations; drop them
    parts = [str(p) for p in loc if not (isinstance(p, str) and (
        p.startswith("function-") or p in {"tagged-union", "union"}))]
    return ".".join(parts)


def validate(model: type[M], data: Mapping[str, Any], path: str | Path, prefix: str = "") -> M:
    """Validate ``data`` against ``model``; errors name the file and the dotted key.

    All problems are reported at once, one per line, the first in the exception's key.
    """
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        errs = exc.errors(include_url=False)
        lines = []
        for e in errs:
            key = ".".join(p for p in (prefix, _loc(e["loc"])) if p)
            msg = e["msg"]
            if e["type"] == "extra_forbidden":
                msg = "unknown key (check its spelling and section)"
            elif "input" in e and e["type"] not in {"missing"} and not isinstance(
                    e["input"], dict | list):
                msg = f"{msg} (got {e['input']!r})"
            lines.append((key, msg))
        first_key, first_msg = lines[0]
        more = "".join(f"\n  also {k or '(top level)'}: {m}" for k, m in lines[1:])
        raise ConfigError(path, first_key, first_msg + more) from None


def build(path: str | Path, key: str, fn: Callable[[], T]) -> T:
    """Run ``fn`` (which turns validated values into objects); a ``ValueError`` it raises
    becomes a :class:`ConfigError` naming ``path`` and ``key``."""
    try:
        return fn()
    except ConfigError:
        raise
    except ValueError as exc:
        raise ConfigError(path, key, str(exc)) from None


def resolve(base_file: str | Path, ref: str | Path) -> Path:
    """A path written in ``base_file``, relative to that file's folder unless absolute."""
    ref = Path(ref).expanduser()
    return ref if ref.is_absolute() else Path(base_file).resolve().parent / ref


def atomic_write_text(path: str | Path, text: str) -> None:
    """Write ``text`` to ``path`` atomically; on failure the old file is untouched."""
    path = Path(path)
    if not path.parent.is_dir():
        raise FileNotFoundError(f"{path.parent}: folder does not exist")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def toml_value(v: Any) -> str:
    """One value in TOML syntax (floats written with enough digits to round-trip)."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if not math.isfinite(v):
            raise ValueError(f"cannot write non-finite number {v} to TOML")
        return repr(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if hasattr(v, "tolist"):
        v = v.tolist()
    if isinstance(v, list | tuple):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def dump_toml(doc: Mapping[str, Any], _prefix: str = "") -> str:
    """Serialise nested mappings of plain values (the shapes our files use) to TOML."""
    lines: list[str] = []
    tables = []
    for k, v in doc.items():
        if isinstance(v, Mapping):
            tables.append((k, v))
        else:
            lines.append(f"{k} = {toml_value(v)}")
    out = "\n".join(lines)
    for k, v in tables:
        name = f"{_prefix}.{k}" if _prefix else k
        body = dump_toml(v, name)
        out += ("\n\n" if out else "") + f"[{name}]\n" + body
    return out.rstrip() + "\n" if not _prefix else out
