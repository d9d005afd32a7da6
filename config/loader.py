"""Reading and writing the project's TOML files.

Every file is read whole, validated by a pydantic model (unknown keys rejected, bounds
declared on the model) and only then turned into objects, so a broken file never
half-starts anything. Writes are atomic: a temporary file in the same folder, fsync,
rename, so a crash or a bad value never leaves a half-written file or loses the old one.
"""

from __future__ import annotations

import errno
import math
import os
import re
import tempfile
import tomllib
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Annotated, Any, TypeVar, get_origin

from pydantic import BaseModel, ConfigDict, ValidationError
from pydantic import Strict as _StrictType

from .errors import ConfigError

M = TypeVar("M", bound=BaseModel)
T = TypeVar("T")


#: A TOML number: an integer or a float, never a string or a boolean (lax pydantic would
#: take ``"0.3"`` or ``true`` for a number and hide a typo in the file).
Float = Annotated[float, _StrictType()]
#: A TOML integer: never a float, a string or a boolean.
Int = Annotated[int, _StrictType()]


class Strict(BaseModel):
    """Base of every file schema: unknown keys are errors, values are frozen, numbers are
    finite (TOML's ``nan`` and ``inf`` are rejected). Use :data:`Float` and :data:`Int` for
    numbers; arrays stay lax so a TOML array fills a tuple field."""

    model_config = ConfigDict(extra="forbid", frozen=True, strict=False, allow_inf_nan=False)


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
        if _cut_short(raw, exc):
            raise ConfigError(path, "", "not valid TOML: the file ends in the middle of a "
                              f"statement, so it looks truncated (cut short): {exc}") from None
        raise ConfigError(path, "", f"not valid TOML: {exc}") from None


def _cut_short(raw: bytes, exc: tomllib.TOMLDecodeError) -> bool:
    """True when a parse error is where a file cut short puts it: at the end of the
    document, or on a last line that has no line break (editors end files with one)."""
    msg = str(exc)
    if "(at end of document)" in msg:
        return True
    at = re.search(r"\(at line (\d+), column \d+\)", msg)
    return (at is not None and not raw.endswith(b"\n")
            and int(at.group(1)) == raw.count(b"\n") + 1)


def _is_section(model: type[BaseModel], name: Any) -> bool:
    """True when the top-level key ``name`` of ``model`` is a table ([name] or [name.x])."""
    info = model.model_fields.get(name) if isinstance(name, str) else None
    ann = info.annotation if info is not None else None
    return get_origin(ann) is dict or (isinstance(ann, type) and issubclass(ann, BaseModel))


def _loc(loc: Iterable[Any]) -> str:
    # pydantic adds the union member or validator name to some locations; drop them.
    # Array indices attach to their key (``size[0]``) so the key stays the last dotted part.
    out = ""
    for p in loc:
        if isinstance(p, str) and (p.startswith("function-") or p in {"tagged-union", "union"}):
            continue
        if isinstance(p, int):
            out += f"[{p}]"
        else:
            out += f".{p}" if out else str(p)
    return out


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
            if e["type"] in {"value_error", "assertion_error"}:
                # a validator's own message: drop pydantic's "Value error, " prefix
                msg = str(e.get("ctx", {}).get("error", msg))
            if e["type"] == "extra_forbidden":
                msg = "unknown key (check its spelling and section)"
            elif (e["type"] == "missing" and not prefix and len(e["loc"]) == 1
                  and _is_section(model, e["loc"][0])):
                # top-level keys precede every table in TOML, so a missing table (not a
                # missing plain key) is what a file cut short, or another kind of file, shows
                msg = (f"{msg}: the file has no [{e['loc'][0]}] section; it may be cut short, "
                       "or be another kind of file")
            elif e.get("input") is not None and e["type"] != "missing" and not isinstance(
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


def resolve_file(base_file: str | Path, key: str, ref: str | Path) -> Path:
    """:func:`resolve`, then check the file exists: a missing file is reported against the
    file and key that name it (``base_file``, ``key``), not just by its own path."""
    target = resolve(base_file, ref)
    if not target.is_file():
        raise ConfigError(base_file, key, f"file not found: {target}")
    return target


def load_file(base_file: str | Path, key: str, ref: str | Path,
              load: Callable[[Path], T]) -> T:
    """:func:`resolve_file`, then ``load`` the file. A problem with the file as a whole (not
    TOML, not UTF-8, unreadable, the wrong kind of file) is reported against ``base_file``
    and ``key`` too, so the message says which entry pointed at it; a problem at a key
    inside the file is reported against that file and key as it is."""
    target = resolve_file(base_file, key, ref)
    try:
        return load(target)
    except ConfigError as exc:
        if exc.key or Path(exc.file) != target:
            raise
        raise ConfigError(base_file, key, f"{target}: {exc.reason}") from None


def atomic_write_bytes(path: str | Path, data: bytes, mode: int | None = None) -> None:
    """Write ``data`` to ``path`` atomically: a temporary file in the same folder, fsync,
    rename, fsync of the folder. On any failure the temporary file is removed and an
    existing ``path`` is unchanged. The file gets ``mode``, or by default an existing
    file's permissions (0644 for a new one); the temporary file is 0600 until then, so a
    private ``mode`` (0600) is never readable by others, not even for an instant."""
    path = Path(path)
    if not path.parent.is_dir():
        raise FileNotFoundError(
            errno.ENOENT, f"cannot write {str(path)!r}: folder {str(path.parent)!r} does not "
            "exist", str(path.parent))
    if mode is None:
        mode = (path.stat().st_mode & 0o777) if path.is_file() else 0o644
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, mode)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    try:  # make the rename durable; not every platform can open a folder
        dfd = os.open(path.parent, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(dfd)
    except OSError:
        pass
    finally:
        os.close(dfd)


def atomic_write_text(path: str | Path, text: str) -> None:
    """Write UTF-8 ``text`` to ``path`` atomically (see :func:`atomic_write_bytes`)."""
    atomic_write_bytes(path, text.encode("utf-8"))


def toml_value(v: Any) -> str:
    """One value in TOML syntax (floats written with enough digits to round-trip)."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if not math.isfinite(v):
            raise ValueError(f"cannot write non-finite number {v} to TOML")
        return repr(float(v))  # float(): numpy's float64 repr is "np.float64(...)"
    if isinstance(v, str):
        # basic string: escape the backslash, the quote and control characters
        return '"' + "".join(
            "\\" + c if c in '\\"' else f"\\u{ord(c):04x}" if ord(c) < 0x20 or ord(c) == 0x7F
            else c for c in v) + '"'
    if hasattr(v, "tolist"):  # numpy arrays and scalars
        return toml_value(v.tolist())
    if isinstance(v, list | tuple):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def toml_key(k: str) -> str:
    """A key in TOML syntax: bare when it can be, else quoted (``"left cam"``, ``"a.b"``)."""
    return k if k and all(c.isascii() and (c.isalnum() or c in "_-") for c in k) \
        else toml_value(str(k))


def dump_toml(doc: Mapping[str, Any], _prefix: str = "") -> str:
    """Serialise nested mappings of plain values (the shapes our files use) to TOML."""
    lines: list[str] = []
    tables = []
    for k, v in doc.items():
        if isinstance(v, Mapping):
            tables.append((k, v))
        else:
            lines.append(f"{toml_key(k)} = {toml_value(v)}")
    out = "\n".join(lines)
    for k, v in tables:
        name = f"{_prefix}.{toml_key(k)}" if _prefix else toml_key(k)
        body = dump_toml(v, name)
        out += ("\n\n" if out else "") + f"[{name}]\n" + body
    return out.rstrip() + "\n" if not _prefix else out
