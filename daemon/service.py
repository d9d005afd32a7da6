"""``oralnavd`` as a service: build everything from the configuration, run the task group,
and stop the robot before anything else on SIGTERM / SIGINT.

Task group (one anyio event loop; blocking work runs in the control process or in worker
threads):

- ``supervise``: the safety supervisor (``DaemonCore.supervise``, 200 Hz);
- ``serve``: the operator REST API (uvicorn on this loop, 127.0.0.1 unless configured);
- ``systemd``: READY / WATCHDOG / STOPPING notifications when systemd runs the daemon;
- ``signals``: SIGTERM / SIGINT -> latched stop -> wait for the loop to confirm (at most
  ``STOP_CONFIRM_S``) -> leave the task group.

The control loop runs in its own process (``ControlProcess``); its drivers are built there.
Camera capture and tracking join this group with the simulated cell (issue 4, next part).
"""

from __future__ import annotations

import logging
import os
import signal
import sys
import tempfile
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

import anyio
import numpy as np

from oralnav.config.daemon import DaemonConfig
from oralnav.config.loader import resolve_file
from oralnav.drivers.io import open_inputs
from oralnav.safety.limits import SpeedLimiter
from oralnav.safety.watchdogs import WatchdogSet

from .api import build_app, serve
from .audit import AuditLog, resolve_audit_path
from .auth import TokenStore
from .control_loop import LoopSettings
from .control_process import ControlProcess, DriverSpec, ProcessSpec
from .core import DaemonCore

log = logging.getLogger(__name__)

#: How long SIGTERM waits for the control loop to confirm the stop before exiting anyway.
STOP_CONFIRM_S = 0.5


def _log(msg: str) -> None:
    print(f"oralnavd: {msg}", file=sys.stderr, flush=True)


def load_tokens(cfg: DaemonConfig) -> TokenStore:
    """The configured tokens file, or, without one, fresh demo tokens written (0600) to the
    runtime directory, whose path is printed so the operator can read them."""
    api = cfg.settings.api
    if api.tokens_file:
        return TokenStore.from_file(resolve_file(cfg.path, "api.tokens_file", api.tokens_file))
    runtime = os.environ.get("RUNTIME_DIRECTORY", "").split(":")[0]
    folder = Path(runtime) if runtime else Path(tempfile.mkdtemp(prefix="oralnavd-"))
    path = folder / "tokens.toml"
    clear = TokenStore.generate(path)
    secrets_file = folder / "tokens.txt"
    fd = os.open(secrets_file, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        for name, token in clear.items():
            f.write(f"{name} {token}\n")
    _log(f"no [api] tokens_file: generated demo tokens (operator, observer) in "
         f"{secrets_file}")
    return TokenStore.from_file(path)


def build_control(cfg: DaemonConfig, home: np.ndarray | None = None) -> ControlProcess:
    """The control process for ``cfg``'s cell (sim drivers for the sim backend)."""
    s = cfg.settings
    if s.cell.backend != "sim":
        raise NotImplementedError("hardware drivers come with the hardware issue; "
                                  "use [cell] backend = \"sim\"")
    arm_opts: dict[str, Any] = {"max_speed": s.safety.max_speed}
    if home is not None:
        arm_opts["home"] = home
    return ControlProcess(ProcessSpec(
        arm=DriverSpec("sim", arm_opts), effector=DriverSpec("sim"),
        settings=LoopSettings.from_config(s.control, s.safety),
        limiter=SpeedLimiter.from_settings(s.safety),
        realtime_priority=s.control.realtime_priority, cpu=s.control.cpu))


async def run_service(cfg: DaemonConfig, api_port: int | None = None, *,
                      on_ready: Callable[[DaemonCore, int], Any] | None = None) -> int:
    """Run the daemon until SIGTERM / SIGINT (or until ``on_ready``'s coroutine, if it
    returns one, finishes). Returns the exit status."""
    from .systemd import Notifier, watchdog_task

    s = cfg.settings
    tokens = load_tokens(cfg)
    audit = AuditLog(resolve_audit_path(s.api.audit_log)).open()
    control = build_control(cfg)
    inputs = open_inputs("sim")
    notifier = Notifier()
    await control.start()
    await inputs.start()
    core = DaemonCore(control, WatchdogSet.from_settings(s.safety, 1.0 / s.control.rate_hz),
                      inputs=inputs)
    app = build_app(core, tokens, audit, telemetry_hz=s.api.telemetry_hz)
    try:
        async with anyio.create_task_group() as tg:
            await tg.start(core.supervise)
            port = await tg.start(partial(serve, allow_remote=s.api.allow_remote), app,
                                  s.api.host, api_port or s.api.port)
            _log(f"serving the operator API on http://{s.api.host}:{port} "
                 f"(OpenAPI at /docs); audit log {audit.path}")
            tg.start_soon(watchdog_task, notifier, lambda: control.alive)
            notifier.ready(status=f"API on {s.api.host}:{port}")

            async def on_signal() -> None:
                with anyio.open_signal_receiver(signal.SIGTERM, signal.SIGINT) as signals:
                    async for signum in signals:
                        name = signal.Signals(signum).name
                        _log(f"{name}: stopping the robot first")
                        await stop_robot(core, f"{name} received")
                        tg.cancel_scope.cancel()
                        return

            tg.start_soon(on_signal)
            if on_ready is not None:
                job = on_ready(core, port)
                if job is not None:
                    await job
                    await stop_robot(core, "job finished")
                    tg.cancel_scope.cancel()
    finally:
        notifier.stopping(status="stopping: robot stopped, shutting the control loop down")
        with anyio.CancelScope(shield=True):
            await control.close()
            await inputs.close()
        audit.close()
    _log("stopped")
    return 0


async def stop_robot(core: DaemonCore, reason: str) -> bool:
    """Latch the stop and wait (at most ``STOP_CONFIRM_S``) until the control loop reports
    it; True when confirmed."""
    now = core.clock()
    core.supervisor.stop.trigger(now, "daemon", reason)
    with anyio.move_on_after(STOP_CONFIRM_S):
        while True:
            st = core.control.read_status()
            if st is None or bool(st["latched"]) or not core.control.alive:
                return True
            await anyio.sleep(0.002)
    log.error("the control loop did not confirm the stop within %.1f s", STOP_CONFIRM_S)
    return False
