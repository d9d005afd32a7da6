"""Bearer tokens of the operator API: who may look and who may command.

Two roles, ordered ``observer`` < ``operator``: an observer reads status, poses, targets and
telemetry; an operator may also change state (e-stop, reset, procedure, targets). Only the
SHA-256 of each token is stored, in a TOML tokens file::

    [tokens.alice]
    role = "operator"
    sha256 = "9f86d081884c7d659a2feaa0c55ad015a3bf4f1b2b0b822cd15d6c15b0f00a08"

    [tokens.wall-display]
    role = "observer"
    sha256 = "..."

``sha256`` is the lowercase hex digest of the UTF-8 token (``hash_token``). A token is
checked against every stored digest with :func:`hmac.compare_digest`, so a guess learns
nothing from the timing.
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field, StringConstraints, field_validator

from oralnav.config.errors import ConfigError
from oralnav.config.loader import Strict, atomic_write_bytes, read_toml, toml_key, validate

Role = Literal["observer", "operator"]

#: role -> rank; a principal may do what any role of equal or lower rank may do
ROLE_RANK: dict[str, int] = {"observer": 0, "operator": 1}

#: longer presented tokens are refused unhashed (generated ones are 43 characters)
MAX_TOKEN_CHARS = 512

_Hex = Annotated[str, StringConstraints(pattern=r"^[0-9a-fA-F]{64}$")]
_Name = Annotated[str, StringConstraints(pattern=r"^[A-Za-z0-9_.-]{1,64}$")]


@dataclass(frozen=True)
class Principal:
    """An authenticated caller: the token's name in the tokens file and its role."""

    name: str
    role: Role

    def allows(self, required: Role) -> bool:
        """True when this principal's role is ``required`` or above it."""
        return ROLE_RANK[self.role] >= ROLE_RANK[required]


class _TokenEntry(Strict):
    role: Role
    sha256: _Hex

    @field_validator("sha256")
    @classmethod
    def _lower(cls, v: str) -> str:
        return v.lower()


class _TokensFile(Strict):
    tokens: dict[_Name, _TokenEntry] = Field(min_length=1)


def hash_token(token: str) -> str:
    """The lowercase hex SHA-256 of a clear token, as the tokens file stores it."""
    return hashlib.sha256(token.encode("utf-8")).hexdigest()


class TokenStore:
    """The known token digests and their principals; immutable once built."""

    def __init__(self, entries: dict[str, tuple[Role, str]]) -> None:
        """``entries``: token name -> (role, lowercase hex SHA-256 of the token)."""
        self._entries = tuple(
            (Principal(name, role), bytes.fromhex(digest))
            for name, (role, digest) in entries.items())

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(p.name for p, _ in self._entries)

    @classmethod
    def from_file(cls, path: str | Path) -> TokenStore:
        """Load a tokens file; any problem raises :class:`ConfigError` naming file and key.

        A file that others may write is refused: anyone who can add a line there could
        give themselves the operator role.
        """
        path = Path(path)
        doc = validate(_TokensFile, read_toml(path), path)
        try:
            mode = path.stat().st_mode
        except OSError as exc:  # pragma: no cover - read_toml just read it
            raise ConfigError(path, "", f"cannot stat: {exc.strerror or exc}") from None
        if mode & 0o022:
            raise ConfigError(path, "", f"group or others may write it (mode {mode & 0o777:o}); "
                                        "chmod 600 it")
        seen: dict[str, str] = {}
        for name, entry in doc.tokens.items():
            if entry.sha256 in seen:
                # the same token under two names would make the audit log ambiguous
                raise ConfigError(path, f"tokens.{name}.sha256",
                                  f"same token as tokens.{seen[entry.sha256]}")
            seen[entry.sha256] = name
        return cls({n: (e.role, e.sha256) for n, e in doc.tokens.items()})

    @classmethod
    def generate(cls, path: str | Path) -> dict[str, str]:
        """Create fresh random ``operator`` and ``observer`` tokens, write their digests to
        ``path`` (atomically, mode 0600, replacing an earlier file) and return the clear
        tokens by name. Only the caller ever sees the clear tokens; load the store with
        :meth:`from_file`."""
        tokens = {role: secrets.token_urlsafe(32) for role in ("operator", "observer")}
        text = "# oralnav API tokens: SHA-256 digests only (docs/api.md)\n"
        for name, token in tokens.items():
            text += (f"\n[tokens.{toml_key(name)}]\nrole = \"{name}\"\n"
                     f"sha256 = \"{hash_token(token)}\"\n")
        # mode 0600: only the daemon's user may read even the digests
        atomic_write_bytes(path, text.encode("utf-8"), mode=0o600)
        return tokens

    def authenticate(self, token: str | None) -> Principal | None:
        """The principal of a clear bearer token, or ``None`` when it is unknown."""
        if not token or len(token) > MAX_TOKEN_CHARS:
            return None
        digest = hashlib.sha256(token.encode("utf-8", "surrogateescape")).digest()
        found = None
        for principal, stored in self._entries:
            # no early exit: every entry costs the same, match or not
            if hmac.compare_digest(digest, stored):
                found = principal
        return found
