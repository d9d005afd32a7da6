"""Shared helpers of the configuration tests: edit a known-good file text, write it, and
expect exactly one ConfigError naming the file and key."""

from __future__ import annotations

import threading
from collections.abc import Callable
from pathlib import Path

import pytest

from oralnav.config.errors import ConfigError


def edit(old: str, new: str, text: str) -> str:
    """``text`` with the first ``old`` replaced by ``new`` (``old`` must be there)."""
    assert old in text, old
    return text.replace(old, new, 1)


def write_file(folder: Path, name: str, text: str) -> Path:
    path = folder / name
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def expect_config_error(load: Callable[[Path], object], path: Path, where: str,
                        *reasons: str) -> str:
    """``load(path)`` must raise one ConfigError that starts with the file, names ``where``
    and gives every reason, and must start no thread; returns the message."""
    threads = set(threading.enumerate())
    with pytest.raises(ConfigError) as ei:
        load(path)
    msg = str(ei.value)
    assert msg.startswith(f"{path}: "), msg
    assert where in msg, msg
    for r in reasons:
        assert r in msg, msg
    assert "\n" not in msg, f"one error expected, got several: {msg}"
    assert set(threading.enumerate()) == threads  # nothing was started
    return msg
