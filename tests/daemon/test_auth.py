"""Bearer tokens of the operator API (``oralnav.daemon.auth``).

Requirement (issue 4, REST API): two roles, observer < operator; the tokens file keeps only
SHA-256 digests; generated demo tokens are written atomically with mode 0600; a broken
tokens file is a ConfigError naming the file and key.
"""

from __future__ import annotations

import hashlib
import os
import stat
from pathlib import Path

import pytest

from oralnav.config.errors import ConfigError
from oralnav.daemon import auth
from oralnav.daemon.auth import Principal, TokenStore, hash_token

DIGEST = "a" * 64


def _write(tmp_path: Path, text: str, mode: int = 0o600) -> Path:
    path = tmp_path / "tokens.toml"
    path.write_text(text)
    path.chmod(mode)
    return path


def _entry(name: str, role: str = "operator", digest: str = DIGEST) -> str:
    return f'[tokens.{name}]\nrole = "{role}"\nsha256 = "{digest}"\n'


def test_generate_writes_only_digests_with_mode_0600(tmp_path):
    """issue 4 auth: generate() makes a fresh operator and an observer token, stores only
    their SHA-256 digests (file mode 0600) and returns the clear tokens."""
    path = tmp_path / "tokens.toml"
    clear = TokenStore.generate(path)
    assert set(clear) == {"operator", "observer"}
    assert clear["operator"] != clear["observer"] and len(clear["operator"]) >= 32
    text = path.read_text()
    for token in clear.values():
        assert token not in text
        assert hash_token(token) in text
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert [p.name for p in tmp_path.iterdir()] == ["tokens.toml"]  # no temporary left
    again = TokenStore.generate(path)  # replaces the file, still private, new tokens
    assert again["operator"] != clear["operator"]
    assert stat.S_IMODE(path.stat().st_mode) == 0o600


def test_generated_tokens_authenticate_with_their_roles(tmp_path):
    """issue 4 auth: authenticate() maps each clear token to its principal and refuses
    unknown, empty and oversized tokens."""
    path = tmp_path / "tokens.toml"
    clear = TokenStore.generate(path)
    store = TokenStore.from_file(path)
    assert store.authenticate(clear["operator"]) == Principal("operator", "operator")
    assert store.authenticate(clear["observer"]) == Principal("observer", "observer")
    for bad in (None, "", clear["operator"] + "x", clear["operator"][:-1], "x" * 10_000):
        assert store.authenticate(bad) is None


def test_roles_are_ordered_observer_below_operator():
    """issue 4 auth: operator may do all an observer may, not the reverse."""
    op, ob = Principal("a", "operator"), Principal("b", "observer")
    assert op.allows("operator") and op.allows("observer")
    assert ob.allows("observer") and not ob.allows("operator")


def test_every_entry_is_compared_in_constant_time(tmp_path, monkeypatch):
    """issue 4 auth: tokens are compared with hmac.compare_digest against every entry, with
    no early exit on a match."""
    path = _write(tmp_path, _entry("a", digest=hash_token("tok-a"))
                  + _entry("b", "observer", hash_token("tok-b"))
                  + _entry("c", digest=hash_token("tok-c")))
    store = TokenStore.from_file(path)
    calls = []
    real = auth.hmac.compare_digest

    def spy(a, b):
        calls.append(1)
        return real(a, b)

    monkeypatch.setattr(auth.hmac, "compare_digest", spy)
    assert store.authenticate("tok-a") == Principal("a", "operator")
    assert len(calls) == 3


def test_hash_token_is_sha256_hex_and_file_digests_are_case_insensitive(tmp_path):
    """issue 4 auth: the file's sha256 is the hex SHA-256 of the UTF-8 token; uppercase hex
    is accepted."""
    assert hash_token("s3cret") == hashlib.sha256(b"s3cret").hexdigest()
    path = _write(tmp_path, _entry("alice", digest=hash_token("s3cret").upper()))
    assert TokenStore.from_file(path).authenticate("s3cret") == Principal("alice", "operator")


@pytest.mark.parametrize("text, where, reason", [
    (_entry("a", role="admin"), "[tokens.a] role", "'observer' or 'operator'"),
    (_entry("a", digest="abc"), "[tokens.a] sha256", "should match pattern"),
    (_entry("a") + 'token = "clear"\n', "[tokens.a] token", "unknown key"),
    ("[tokens]\n", "tokens", "at least 1"),
    ("title = 'x'\n", "title", "unknown key"),
    (_entry("a") + _entry("b", "observer"), "[tokens.b] sha256", "same token as tokens.a"),
    ("[tokens.a\n", "", "not valid TOML"),
])
def test_bad_tokens_file_names_file_and_key(tmp_path, text, where, reason):
    """issue 4 auth: a broken tokens file raises ConfigError naming the file, the key and
    what is wrong."""
    path = _write(tmp_path, text)
    with pytest.raises(ConfigError) as ei:
        TokenStore.from_file(path)
    msg = str(ei.value)
    assert msg.startswith(f"{path}: ") and where in msg and reason in msg, msg


def test_missing_or_writable_by_others_tokens_file_is_refused(tmp_path):
    """issue 4 auth: a missing tokens file, or one that group/others may write (anyone could
    add an operator), is a ConfigError naming the file."""
    with pytest.raises(ConfigError, match="file not found"):
        TokenStore.from_file(tmp_path / "nope.toml")
    path = _write(tmp_path, _entry("a"), mode=0o666)
    with pytest.raises(ConfigError, match="chmod 600"):
        TokenStore.from_file(path)


def test_generate_into_a_missing_folder_fails_and_leaves_nothing(tmp_path):
    """issue 4 auth: generate() into a folder that does not exist raises and writes
    nothing (atomic write)."""
    with pytest.raises(FileNotFoundError, match="does not exist"):
        TokenStore.generate(tmp_path / "no" / "tokens.toml")
    assert not os.listdir(tmp_path)
