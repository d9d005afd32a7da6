"""``oralnavd`` (daemon/main.py): ``--check`` checks everything a start reads, and a start
that meets bad input says so in one line with exit status 2."""

from __future__ import annotations

import os
import socket
from pathlib import Path

import pytest

from oralnav.config.errors import ConfigError
from oralnav.daemon import main
from oralnav.daemon.auth import hash_token

CONFIG = Path(__file__).resolve().parents[2] / "config"

#: a hardware cell with no devices configured: loads in milliseconds, starts nothing
CELL = f"""\
[cell]
backend = "hardware"
rig = "{CONFIG}/rigs/stereo.toml"
fields = "{CONFIG}/fields/cell.toml"
"""

DIGEST = hash_token("s3cret")
TOKENS = f'[tokens.alice]\nrole = "operator"\nsha256 = "{DIGEST}"\n'

#: name: (tokens file text or None for no file, its mode, texts the error line must hold)
BAD_TOKENS = {
    "mode_0666": (TOKENS, 0o666, ("tokens.toml", "[api] tokens_file", "mode 666")),
    "bad_hex": (TOKENS.replace(DIGEST, "xyz"), 0o600, ("tokens.toml", "[tokens.alice] sha256")),
    "no_tokens": ("# no tokens yet\n", 0o600, ("tokens.toml", "tokens", "no [tokens] section")),
    "unknown_key": (TOKENS + "colour = 1\n", 0o600,
                    ("tokens.toml", "[tokens.alice] colour", "unknown key")),
    "bad_role": (TOKENS.replace('"operator"', '"admin"'), 0o600,
                 ("tokens.toml", "[tokens.alice] role", "'observer' or 'operator'")),
    "truncated": (TOKENS[:-20], 0o600, ("[api] tokens_file", "tokens.toml", "truncated")),
    "missing": (None, 0o600, ("[api] tokens_file", "file not found", "tokens.toml")),
}


def _config(folder: Path, api: str) -> Path:
    path = folder / "oralnav.toml"
    path.write_text(CELL + "\n[api]\n" + api)
    return path


def _with_tokens(folder: Path, text: str | None, mode: int) -> Path:
    if text is not None:
        tokens = folder / "tokens.toml"
        tokens.write_text(text)
        os.chmod(tokens, mode)
    return _config(folder, f'tokens_file = "tokens.toml"\naudit_log = "{folder}/audit.jsonl"\n')


def _one_error_line(capsys) -> str:
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith("oralnavd: error: "), err
    return lines[0]


@pytest.mark.parametrize("case", list(BAD_TOKENS))
def test_check_refuses_a_bad_tokens_file(tmp_path, capsys, case):
    """issue 30: `oralnavd --check` loads the tokens file as a start does, so a tokens file
    with mode 0666, bad hex, no tokens, an unknown key, a bad role, cut short, or missing
    exits 2 with one line naming the file and key, and a real start refuses it the same
    way before it says "configuration is valid"."""
    text, mode, parts = BAD_TOKENS[case]
    path = _with_tokens(tmp_path, text, mode)
    for argv in (["--check", "--config", str(path)], ["--config", str(path)]):
        assert main.run(argv) == 2
        line = _one_error_line(capsys)
        for part in parts:
            assert part in line, line
    assert not (tmp_path / "audit.jsonl").exists()  # the start stopped before opening it


def test_check_accepts_a_good_tokens_file(tmp_path, capsys):
    """issue 30: a good tokens file (mode 0600) passes --check."""
    assert main.run(["--check", "--config", str(_with_tokens(tmp_path, TOKENS, 0o600))]) == 0
    assert "is valid" in capsys.readouterr().err


def test_check_refuses_an_audit_log_whose_folder_is_missing(tmp_path, capsys):
    """issue 30: --check checks that the audit log can be opened at start: its folder must
    exist (the daemon creates the log, not its folder); named by [api] audit_log."""
    path = _config(tmp_path, f'audit_log = "{tmp_path}/no/such/audit.jsonl"\n')
    assert main.run(["--check", "--config", str(path)]) == 2
    line = _one_error_line(capsys)
    assert f"{path}: [api] audit_log:" in line and "does not exist" in line, line


def test_start_turns_a_config_error_while_loading_tokens_into_one_line(tmp_path, capsys,
                                                                       monkeypatch):
    """issue 30: a ConfigError raised while the service loads the tokens (a file changed
    between the check and the start) ends the start with one line and exit 2, no
    traceback."""
    from oralnav.daemon import service

    def broken(cfg, cleanup=None):
        raise ConfigError(tmp_path / "tokens.toml", "tokens.alice.role", "changed under us")

    monkeypatch.setattr(service, "load_tokens", broken)
    assert main.run(["--config", str(_with_tokens(tmp_path, TOKENS, 0o600)),
                     "--api-port", str(_free_port())]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert err.strip().splitlines()[-1] == (f"oralnavd: error: {tmp_path / 'tokens.toml'}: "
                                            "[tokens.alice] role: changed under us")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_a_port_in_use_is_one_line_before_anything_starts(tmp_path, capsys):
    """issue 30: the API's port already in use ends the start with one line naming [api]
    port and the address, exit 2, before the control process, the audit log or anything
    else is started (no ExceptionGroup traceback after a READY cell)."""
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        path = _with_tokens(tmp_path, TOKENS, 0o600)
        assert main.run(["--config", str(path), "--api-port", str(port)]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "READY" not in err, err
    last = err.strip().splitlines()[-1]
    assert last.startswith(f"oralnavd: error: {path}: [api] port: cannot bind the API to "
                           f"127.0.0.1:{port}"), last
    assert not (tmp_path / "audit.jsonl").exists()
