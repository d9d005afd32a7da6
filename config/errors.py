"""Errors of the configuration layer: every message names the file, section and key."""

from __future__ import annotations

from pathlib import Path


class ConfigError(Exception):
    """A configuration, rig, field or scene file is unreadable or invalid.

    ``file`` is the offending file, ``key`` the dotted location inside it (``""`` for the
    file as a whole) and ``reason`` what is wrong.
    """

    def __init__(self, file: str | Path, key: str, reason: str) -> None:
        self.file = str(file)
        self.key = key
        self.reason = reason
        super().__init__(self._format())

    def _format(self) -> str:
        if not self.key:
            return f"{self.file}: {self.reason}"
        section, _, leaf = self.key.rpartition(".")
        where = f"[{section}] {leaf}" if section else leaf
        return f"{self.file}: {where}: {self.reason}"
