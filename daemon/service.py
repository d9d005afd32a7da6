"""``oralnavd`` as a service: build everything from the configuration, run the task group,
and stop the robot before anything else on SIGTERM / SIGINT.

Task group (one anyio event loop; blocking work runs in the control process or in worker
threads):

- ``supervise``: the safety supervisor (``DaemonCore.supervise``, 50 Hz); beside the
  group, the loop's heartbeat watch (``daemon/heartbeat.py``) polls in a thread of its own;
- ``serve``: the operator REST API (uvicorn on this loop, 127.0.0.1 unless configured);
- ``systemd``: READY / WATCHDOG / STOPPING notifications when systemd runs the daemon;
- ``signals``: SIGTERM / SIGINT -> latched stop -> wait for the loop to confirm (at most
  ``STOP_CONFIRM_S``) -> leave the task group.

- ``capture``: the cameras (or the simulated cell's renderer) read, tracked and published
  into the pose store, each round followed by a navigation step (``build_navigation``).
- ``igtl``: with ``[igtl]``, the OpenIGTLink server for 3D Slicer (``daemon/igtl.py``):
  poses out, suture targets in; its sockets in a thread of their own.
- ``recorder``: the session recorder's poll (``daemon/recording.py``, 10 Hz): safety
  transitions and arm samples for a running recording; its writer is a thread of its own.

The control loop runs in its own process (``ControlProcess``); its drivers are built there.
"""

from __future__ import annotations

import logging
import os
import shutil
import signal
import ssl
import sys
import tempfile
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

import anyio
import anyio.to_thread
import numpy as np

from oralnav.config.daemon import DaemonConfig
from oralnav.config.errors import ConfigError
from oralnav.config.loader import resolve_file
from oralnav.daemon.api import bind_api, build_app, serve
from oralnav.daemon.api_gate import AuthLimits, FailureLimiter
from oralnav.daemon.audit import AuditLog
from oralnav.daemon.auth import TokenStore
from oralnav.daemon.core import DaemonCore
from oralnav.daemon.heartbeat import LoopHeartbeat
from oralnav.daemon.live_views import LiveViews
from oralnav.drivers.io import open_inputs
from oralnav.realtime.control_loop import LoopSettings
from oralnav.realtime.control_process import ControlProcess, DriverSpec, ProcessSpec
from oralnav.safety.limits import SpeedLimiter
from oralnav.safety.watchdogs import WatchdogSet

log = logging.getLogger(__name__)

#: How long SIGTERM waits for the control loop to confirm the stop before exiting anyway.
STOP_CONFIRM_S = 0.5


def _log(msg: str) -> None:
    print(f"oralnavd: {msg}", file=sys.stderr, flush=True)


def load_tokens(cfg: DaemonConfig, cleanup: list[Callable[[], None]] | None = None
                ) -> tuple[TokenStore, dict[str, str]]:
    """The configured tokens file, or, without one, fresh demo tokens written (0600) to the
    runtime directory, whose path is printed so the operator can read them. Returns the
    store and the clear demo tokens (empty with a configured file). What must be removed
    when the daemon stops (the demo tokens' temporary folder, when it made one) is added
    to ``cleanup``."""
    api = cfg.settings.api
    if api.tokens_file:
        path = resolve_file(cfg.path, "api.tokens_file", api.tokens_file)
        return TokenStore.from_file(path), {}
    runtime = os.environ.get("RUNTIME_DIRECTORY", "").split(":")[0]
    if runtime:  # systemd's RuntimeDirectory= is removed by systemd when the unit stops
        folder = Path(runtime)
    else:
        folder = Path(tempfile.mkdtemp(prefix="oralnavd-"))
        if cleanup is not None:  # demo tokens must not outlive the daemon that issued them
            cleanup.append(partial(shutil.rmtree, folder, ignore_errors=True))
    path = folder / "tokens.toml"
    clear = TokenStore.generate(path)
    secrets_file = folder / "tokens.txt"
    fd = os.open(secrets_file, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        for name, token in clear.items():
            f.write(f"{name} {token}\n")
    _log(f"no [api] tokens_file: generated demo tokens (operator, observer) in "
         f"{secrets_file}")
    return TokenStore.from_file(path), clear


def build_control(cfg: DaemonConfig, home: np.ndarray | None = None) -> ControlProcess:
    """The control process for ``cfg``'s cell: the simulated arm and wrist for the sim
    cell; for a hardware cell the ``[arm]`` and ``[effector]`` backends (docs/formats.md)."""
    s = cfg.settings
    if s.arm.backend == "sim":
        # the simulated arm's watchdog outwaits the loop's own deadline watchdog, so a
        # stalled loop is stopped by the loop, with its reason, and the arm's watchdog
        # stays the backstop
        arm_opts: dict[str, Any] = {
            "max_speed": s.safety.max_speed,
            "watchdog_timeout": max(0.05, 2.0 * s.safety.max_period_lateness)}
        if home is not None:
            arm_opts["home"] = home
    else:
        arm_opts = s.arm.driver_options()
    effector_opts = s.effector.driver_options(cfg.path.parent)
    return ControlProcess(ProcessSpec(
        arm=DriverSpec(s.arm.backend, arm_opts),
        effector=DriverSpec(s.effector.backend, effector_opts),
        settings=LoopSettings.from_config(s.control, s.safety),
        limiter=SpeedLimiter.from_settings(s.safety),
        realtime_priority=s.control.realtime_priority, cpu=s.control.cpu))


async def run_service(cfg: DaemonConfig, api_port: int | None = None, *,
                      on_ready: Callable[..., Any] | None = None,
                      record: Any = None) -> int:
    """Run the daemon until SIGTERM / SIGINT (or until the coroutine that
    ``on_ready(core, port, tokens, nav)`` returns, if any, finishes). Returns the exit
    status. ``record``: ``RecordingOptions`` to record the session from the start
    (``oralnavd --record``)."""
    s = cfg.settings
    # the API's port first: one taken by another daemon is one clear error before the
    # control process, the cameras or the renderer start (ConfigError: exit 2)
    port_wanted = api_port or s.api.port
    tls = tls_files(cfg)
    try:
        api_sock = bind_api(s.api.host, port_wanted, allow_remote=s.api.allow_remote)
    except OSError as exc:
        raise ConfigError(cfg.path, "api.port", f"{exc.strerror or exc} (another oralnavd "
                          "running? choose another port with --api-port)") from None
    if s.api.allow_remote and tls is None:
        log.warning("the operator API on %s:%d faces the network over plain HTTP: tokens "
                    "and commands travel in clear; set [api] tls_cert and tls_key",
                    s.api.host, port_wanted)
    cleanup: list[Callable[[], None]] = [api_sock.close]
    try:
        return await _run(cfg, api_port, api_sock, tls, cleanup, on_ready, record=record)
    finally:
        for fn in reversed(cleanup):
            fn()


def tls_files(cfg: DaemonConfig) -> tuple[str, str] | None:
    """``[api] tls_cert`` and ``tls_key`` as paths, loaded once here so that a bad pair is
    one clear error at start (ConfigError naming the keys), not a traceback from uvicorn."""
    api = cfg.settings.api
    if api.tls_cert is None or api.tls_key is None:
        return None
    cert = resolve_file(cfg.path, "api.tls_cert", api.tls_cert)
    key = resolve_file(cfg.path, "api.tls_key", api.tls_key)
    try:
        ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER).load_cert_chain(cert, key)
    except (ssl.SSLError, OSError) as exc:
        raise ConfigError(cfg.path, "api.tls_cert", f"{cert} with {key}: not a certificate "
                          f"and its private key in PEM ({exc})") from None
    return str(cert), str(key)


async def _run(cfg: DaemonConfig, api_port: int | None, api_sock: Any,
               tls: tuple[str, str] | None, cleanup: list[Callable[[], None]],
               on_ready: Callable[..., Any] | None, record: Any = None) -> int:
    """:func:`run_service` once the API's socket is bound."""
    from oralnav.daemon.systemd import Notifier, watchdog_task

    s = cfg.settings
    tokens, clear = load_tokens(cfg, cleanup)
    audit = AuditLog.from_config(s.api).open()
    control = build_control(cfg, cfg.cell.home_T_B_tcp if cfg.cell is not None else None)
    inputs = open_inputs(s.inputs.backend, **s.inputs.driver_options())
    notifier = Notifier()
    core = DaemonCore(control, WatchdogSet.from_settings(s.safety, 1.0 / s.control.rate_hz),
                      inputs=inputs)
    core.audit = audit  # its incomplete and pending records show in GET /status
    igtl = igtl_server(cfg, core, cleanup)  # bound now: a taken port fails at start
    views = LiveViews(s.api.views_max_hz, clock=core.clock)
    app = build_app(core, tokens, audit, telemetry_hz=s.api.telemetry_hz,
                    auth_limiter=FailureLimiter(AuthLimits.from_config(s.api)), views=views)
    capture, nav, cell = build_navigation(cfg, core)
    capture.taps.append(views.tap)  # the console's live views see every tracked round
    recorder = attach_recorder(cfg, core, capture, audit, record)
    if cfg.cell is not None:  # the cell file's planned targets, offered in the console
        core.set_planned(dict(cfg.cell.targets_OM))
    if cell is not None:
        # before the control loop starts: preparing is seconds of work on every core
        _log("preparing the simulated cell (camera ray maps, textures)...")
        await anyio.to_thread.run_sync(cell.prepare)
    keep_off_control_cpu(s.control.cpu)
    await control.start()
    # a thread that wants the GIL waits up to the switch interval (5 ms by default) for
    # the holder to let go: at 1 ms the heartbeat watch keeps its few-period promise
    # whatever Python work the event loop or the tracking threads are doing
    sys.setswitchinterval(min(sys.getswitchinterval(), 0.001))
    heartbeat = LoopHeartbeat(core, clock=core.clock,
                              priority=max(0, s.control.realtime_priority - 1))
    core.heartbeat = heartbeat
    try:
        heartbeat.start()  # a hung loop is seen within a few periods, whatever this loop does
        await inputs.start()
        async with anyio.create_task_group() as tg:
            await tg.start(core.supervise)
            await tg.start(capture.run)
            tg.start_soon(recorder.run)
            if igtl is not None:
                await tg.start(igtl.run)
                _log(f"serving OpenIGTLink (3D Slicer) on {igtl.host}:{igtl.port}: poses at "
                     f"{igtl.rate_hz:g} Hz, suture targets "
                     + ("in" if igtl.accept_targets else "not accepted"))
            port = await tg.start(partial(serve, allow_remote=s.api.allow_remote,
                                          sock=api_sock, tls=tls), app,
                                  s.api.host, api_port or s.api.port)
            scheme = "https" if tls else "http"
            _log(f"serving the operator API on {scheme}://{s.api.host}:{port} "
                 f"(console at /, OpenAPI at /docs); audit log {audit.path}")
            # fed only while the control process is alive and its loop beats
            tg.start_soon(watchdog_task, notifier, core.health)
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
                job = on_ready(core, port, clear, nav)
                if job is not None:
                    await job
                    await stop_robot(core, "job finished")
                    tg.cancel_scope.cancel()
    finally:
        notifier.stopping(status="stopping: robot stopped, shutting the control loop down")
        with anyio.CancelScope(shield=True):
            # before the control process goes: the last transitions and arm samples
            await anyio.to_thread.run_sync(recorder.close)
            heartbeat.close()
            await control.close()
            await inputs.close()
        audit.close()
    _log("stopped")
    return 0


def igtl_server(cfg: DaemonConfig, core: DaemonCore,
                cleanup: list[Callable[[], None]]) -> Any:
    """The OpenIGTLink server ``[igtl]`` asks for (``daemon/igtl.py``), its port bound and
    its closing added to ``cleanup``; None when the section is absent or not enabled. A
    port that cannot be bound is a ConfigError naming ``[igtl] port``."""
    section = cfg.settings.igtl
    if section is None or not section.enabled:
        return None
    from oralnav.daemon.igtl import IgtlServer

    server = IgtlServer.from_config(core, section)
    try:
        server.bind()
    except OSError as exc:
        raise ConfigError(cfg.path, "igtl.port", f"{section.host}:{section.port}: "
                          f"{exc.strerror or exc} (another OpenIGTLink server running, "
                          "3D Slicer's own server connector among them?)") from None
    cleanup.append(server.sockets.close)
    return server


def build_navigation(cfg: DaemonConfig, core: DaemonCore) -> tuple[Any, Any, Any]:
    """The capture pipeline and the navigation listening to it, the same for every cell,
    and the simulated cell (None on a hardware cell). On the simulated cell its renderer
    is the one source and its ground truth observes what is reached; on a hardware cell
    the configured cameras are the sources, and a hardware-in-the-loop cell's peers
    (``[cell] truth``) observe. The navigation's refusal guards ``POST /procedure/start``,
    and its hand-eye places the opener for guided insertion."""
    from oralnav.daemon.capture_task import (
        CapturePipeline,
        hardware_sources,
        sim_sources,
        stereo_offset,
    )
    from oralnav.daemon.navigation_task import NavigationTask, nav_calibration
    from oralnav.daemon.temporal_session import ROBOT_POSE, TemporalSession

    s = cfg.settings
    observers: list[Callable[..., Any]] = []
    cell = None
    simulated = s.cell.backend == "sim"
    if simulated and cfg.cell is not None:
        from oralnav.daemon.sim_cell import ArmProbe, SimTruth
        from oralnav.sim.world.cell import SimCell

        probe = ArmProbe(core, cfg.cell.home_T_B_tcp)
        cell = SimCell(cfg.cell, probe, probe.wrist, probe.sample_time)
        cc = cfg.cell
        roles = {role: cell.config.stereo_scene.placement(getattr(cc, role)).field
                 for role in ("robot", "opener", "effector")}
        # the renderer stamps each frame with the arm's own instant: no offset unless a
        # temporal calibration file says otherwise
        offset = cfg.stereo_time_offset() or 0.0
        sources = sim_sources(cell, cell.stereo_rig, cell.endoscope_rig, roles, offset)
        observers.append(SimTruth(cell))
    else:
        offset = stereo_offset(cfg)
        sources = hardware_sources(cfg, offset)
    if s.cell.truth:  # a hardware-in-the-loop cell of protocol peers: they know the truth
        from oralnav.daemon.sim_cell import PeerTruth

        observers.append(PeerTruth(s.cell.truth))
    missing = cfg.missing_calibrations()
    try:
        # only the simulated cell may stand in its truth for a missing calibration file
        calibration = nav_calibration(cfg.calibrations, cfg.cell if simulated else None)
        why = ""
    except KeyError as exc:
        calibration, why = None, str(exc.args[0])
    if cell is not None:
        _log("navigation calibration: " + (
            f"files of cell {s.calibration.cell!r}" if s.calibration and not missing else
            f"the simulated cell's truth for {', '.join(missing)}"))
    capture = CapturePipeline(core, sources)
    nav = NavigationTask(core, calibration=calibration, entry_T_OM_E0=cfg.entry_T_OM_E0(),
                         settings=s.navigation, tracked=capture.pose_names(),
                         progress=_log, observers=observers, no_calibration=why)
    capture.listeners.append(nav.on_tracked)
    temporal = TemporalSession(core, applied_offset=offset,
                               tracked=ROBOT_POSE in capture.pose_names())
    capture.listeners.append(temporal.on_tracked)
    core.temporal_session = temporal
    core.start_checks.append(nav.refusal)
    if calibration is not None:
        # guided insertion places the tracked opener in the base with the same hand-eye
        core.set_hand_eye(calibration.T_B_C)
    refusal = nav.refusal()
    if refusal:
        _log(f"navigation unavailable on this cell: {refusal}")
    return capture, nav, cell


def attach_recorder(cfg: DaemonConfig, core: DaemonCore, capture: Any, audit: AuditLog,
                    record: Any = None) -> Any:
    """The session recorder (``daemon/recording.py``) attached to the capture pipeline
    (a tap), the audit log (an observer) and the core (``/recording``); recording at once
    with ``record`` (``RecordingOptions``). A recording that cannot start is logged: the
    daemon runs without it."""
    from oralnav.daemon.recording import RecordingError, SessionRecorder

    recorder = SessionRecorder(core, capture.sources, config_path=cfg.path)
    capture.taps.append(recorder.tap)
    audit.observers.append(recorder.on_audit)
    core.recorder = recorder
    if record is not None:
        try:
            recorder.start(record, "oralnavd --record")
            _log(f"recording the session to {record.path}")
        except RecordingError as exc:
            _log(f"not recording: {exc}")
    return recorder


def keep_off_control_cpu(cpu: int | None) -> None:
    """With ``[control] cpu`` set, run the daemon (tracking, rendering, API) on the other
    CPUs, so the control process has its core to itself (it pins itself to ``cpu``)."""
    if cpu is None or not hasattr(os, "sched_setaffinity"):
        return
    others = os.sched_getaffinity(0) - {cpu}
    if others:
        os.sched_setaffinity(0, others)
        _log(f"daemon on CPU(s) {sorted(others)}, control loop on CPU {cpu}")


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
