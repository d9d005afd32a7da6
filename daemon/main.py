"""``oralnavd``: the navigation and control daemon.

It loads and validates the configuration and every file it names, then serves the cell:
the control loop in its own process, the safety supervisor and the operator REST API in
one anyio task group (``daemon/service.py``), until SIGTERM, which stops the robot first.
``--check`` only validates, everything a start reads (the configuration and its files,
the tokens file, the audit log's folder; :func:`check_start_files`). ``--demo`` is the
main job: on the simulated cell it plays the operator over the REST API (register the
suture targets, start) while the daemon runs the paper's two-stage navigation, then
prints the reached TRE and the measured rates. ``--record FILE.mcap`` records the
session from the start (docs/recording.md; ``--record-every``, ``--record-images``,
``--record-compression``), the demo's too.

    oralnavd [--config FILE] [--check] [--demo] [--api-port N] [--record FILE.mcap] [--json]
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from oralnav import __version__
from oralnav.config.daemon import DaemonConfig, load_config
from oralnav.config.errors import ConfigError
from oralnav.config.loader import load_file
from oralnav.control.errors import ControlError


def _log(msg: str) -> None:
    print(f"oralnavd: {msg}", file=sys.stderr, flush=True)


def check_start_files(cfg: DaemonConfig) -> None:
    """Check what a start reads or writes beyond the configuration ``load_config`` has
    loaded: the tokens file (loaded as the API will load it), the audit log (its folder
    must exist and the file be writable: the log is opened, and its folder created only when
    it is the default user state folder, ``daemon/audit.py`` ``state_dir``) and,
    without a tokens file, ``$RUNTIME_DIRECTORY`` for the demo tokens. Raises
    :class:`ConfigError` naming the configuration file and key, or the tokens file and key.
    """
    from oralnav.daemon.audit import ensure_user_state_dir, resolve_audit_path
    from oralnav.daemon.auth import TokenStore

    api = cfg.settings.api
    if api.tokens_file:
        load_file(cfg.path, "api.tokens_file", api.tokens_file, TokenStore.from_file)
    log = resolve_audit_path(api.audit_log)
    try:
        ensure_user_state_dir(log)  # the default folder is ours to make; others are not
    except OSError as exc:
        raise ConfigError(cfg.path, "api.audit_log", f"{log}: cannot create the state "
                          f"folder {log.parent}: {exc.strerror or exc}") from None
    if log.exists():
        if not log.is_file() or not os.access(log, os.W_OK):
            raise ConfigError(cfg.path, "api.audit_log",
                              f"{log}: not a file this user may append to")
    elif not log.parent.is_dir():
        raise ConfigError(cfg.path, "api.audit_log", f"{log}: folder {log.parent} does not "
                          "exist (the daemon creates the log, not its folder)")
    elif not os.access(log.parent, os.W_OK | os.X_OK):
        raise ConfigError(cfg.path, "api.audit_log", f"{log}: this user may not create "
                          f"files in {log.parent}")
    runtime = os.environ.get("RUNTIME_DIRECTORY", "").split(":")[0]
    if not api.tokens_file and runtime and not os.access(runtime, os.W_OK | os.X_OK):
        raise ConfigError(cfg.path, "api.tokens_file", "not set, so demo tokens go to "
                          f"$RUNTIME_DIRECTORY {runtime}, which this user may not write")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="oralnavd", description="oralnav navigation daemon")
    p.add_argument("--version", action="version", version=f"oralnavd {__version__}")
    p.add_argument("--config", help="configuration TOML (default: the embedded sim.toml)")
    p.add_argument("--check", action="store_true", help="validate the configuration and exit")
    p.add_argument("--demo", action="store_true",
                   help="the main job: play the operator on the simulated cell (targets, "
                        "start, two-stage navigation) and report TRE and rates")
    p.add_argument("--api-port", type=int, help="override [api] port")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.add_argument("--record", metavar="FILE.mcap",
                   help="record the session to an MCAP file (poses, frames, safety, commands; "
                        "docs/recording.md); replaced if it exists")
    p.add_argument("--record-every", type=int, default=1, metavar="N",
                   help="record the frames of every N-th tracked round (default 1: all)")
    p.add_argument("--record-images", choices=("raw", "png", "jpeg", "none"), default="raw",
                   help="how frames are recorded (default raw: lossless, cheapest CPU)")
    p.add_argument("--record-compression", choices=("zstd", "lz4", "none"), default="none",
                   help="MCAP chunk compression (default none: zstd halves the file for "
                        "several times the writer's CPU)")
    return p


def recording_options(args: argparse.Namespace) -> Any:
    """``--record`` and its options as ``RecordingOptions`` (None without ``--record``);
    ConfigError naming the option when they are wrong or the file's folder cannot be
    made or written: a bad path is refused before anything starts."""
    if not args.record:
        return None
    from oralnav.daemon.recording import RecordingError, RecordingOptions

    try:
        # a path on the command line is the shell's: relative to the working directory
        opts = RecordingOptions(Path(args.record).absolute(), every=args.record_every,
                                images=args.record_images,
                                compression=args.record_compression, overwrite=True)
    except RecordingError as exc:
        raise ConfigError("--record", "", str(exc)) from None
    folder = opts.path.parent
    try:  # an output on the command line gets its folder, as every oralnav output does
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError("--record", "", f"{opts.path}: cannot create folder {folder}: "
                          f"{exc.strerror or exc}") from None
    if not os.access(folder, os.W_OK | os.X_OK) or (
            opts.path.exists() and not os.access(opts.path, os.W_OK)):
        raise ConfigError("--record", "", f"{opts.path}: this user may not write it")
    return opts


def run(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        cfg = load_config(args.config)
        check_start_files(cfg)
        record = recording_options(args)
        if args.api_port is not None and not 1 <= args.api_port <= 65535:
            raise ConfigError("--api-port", "", f"must be 1..65535, got {args.api_port}")
    except (ConfigError, ControlError) as exc:
        print(f"oralnavd: error: {exc}", file=sys.stderr)
        if args.json:
            print(json.dumps({"error": str(exc), "exit": 2}))
        return 2
    s = cfg.settings
    port = args.api_port or s.api.port
    _log(f"configuration {cfg.path} is valid: {s.cell.backend} cell, "
         f"cameras {', '.join(cfg.rig.names)}, fields {', '.join(sorted(cfg.fields))}, "
         f"control at {s.control.rate_hz:g} Hz, API on {s.api.host}:{port}")
    doc: dict[str, Any] = {"config": str(cfg.path), "valid": True, "backend": s.cell.backend,
                           "api": {"host": s.api.host, "port": port}}
    if args.demo:
        if cfg.cell is None:
            _log("--demo needs [cell] sim_cell: the cell whose suture targets it registers "
                 "(the simulated cell, or the one a cell of protocol peers renders)")
            return 2
        import anyio

        from oralnav.daemon.demo import demo_summary, play_operator, print_result
        from oralnav.daemon.service import run_service
        logging.basicConfig(level=logging.WARNING, format="oralnavd: %(name)s: %(message)s")
        result: dict[str, Any] = {}
        cores: list[Any] = []  # the core, for the recording's figures after the run
        t0 = time.perf_counter()
        try:
            rc = anyio.run(lambda: run_service(
                cfg, args.api_port, record=record,
                on_ready=lambda core, p, clear, nav: cores.append(core) or play_operator(
                    p, clear, dict(cfg.cell.targets_OM), result)))
        except Exception as exc:  # the job's own failure (an ExceptionGroup from the tasks)
            leaves = exc.exceptions if isinstance(exc, ExceptionGroup) else (exc,)
            _log("demo failed: " + "; ".join(str(e) for e in leaves))
            result.setdefault("error", "; ".join(str(e) for e in leaves))
            rc = 1
        doc["demo"] = result
        doc["demo_s"] = round(time.perf_counter() - t0, 2)
        doc.update(demo_summary(result))
        if record is not None and cores and cores[0].recorder is not None:
            rec = doc["recording"] = cores[0].recorder.status()
            _log(f"recording {rec['path']}: {rec['state']}, {rec['rounds']} rounds, "
                 f"{rec['frames']['written']} frames written, {rec['frames']['dropped']} "
                 f"dropped, {(rec['bytes'] or 0) / 1e6:.1f} MB at {rec['mb_per_s']} MB/s"
                 + (f"; {rec['error']}" if rec["error"] else ""))
        if args.json:
            print(json.dumps(doc))
        else:
            print_result(result, s.cell.backend)
        return rc if result.get("done") else 1
    if args.check:
        if args.json:
            print(json.dumps(doc))
        return 0
    import anyio

    from oralnav.daemon.audit import AuditError
    from oralnav.daemon.service import run_service
    logging.basicConfig(level=logging.INFO, format="oralnavd: %(name)s: %(message)s")
    try:
        return anyio.run(lambda: run_service(cfg, args.api_port, record=record))
    except (ConfigError, AuditError) as exc:
        # a file changed since the check above (tokens, audit log): one line, bad input
        print(f"oralnavd: error: {exc}", file=sys.stderr)
        return 2


def main() -> None:
    sys.exit(run())


if __name__ == "__main__":
    main()
