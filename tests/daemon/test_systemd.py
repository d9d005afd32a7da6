"""systemd integration (``oralnav.daemon.systemd``) and the shipped unit file.

Requirement (issue 4, systemd): sd_notify spoken directly on ``$NOTIFY_SOCKET`` (a path or
an ``@`` abstract name), READY/WATCHDOG/STOPPING/STATUS/RELOADING datagrams; a no-op
outside systemd; a failed notification never raises; ``$WATCHDOG_USEC`` honoured only for
the pid in ``$WATCHDOG_PID``; the watchdog task pings at half the interval only while the
daemon is healthy; ``config/oralnavd.service`` is a hardened ``Type=notify`` unit.
"""

from __future__ import annotations

import logging
import os
import re
import socket
import tempfile
import time
import uuid
from collections.abc import Iterator
from functools import partial
from importlib import resources
from pathlib import Path

import anyio
import pytest

from oralnav.daemon import systemd
from oralnav.daemon.systemd import Notifier, watchdog_interval, watchdog_task

UNIT = Path(__file__).resolve().parents[2] / "config" / "oralnavd.service"


# -- helpers ---------------------------------------------------------------------------


@pytest.fixture
def sock_dir(tmp_path: Path) -> Iterator[Path]:
    """A folder for a socket: tmp_path unless its path is too long for sun_path."""
    if len(str(tmp_path / "notify.sock")) < 100:
        yield tmp_path
        return
    with tempfile.TemporaryDirectory(prefix="sd") as short:
        yield Path(short)


@pytest.fixture
def receiver(sock_dir: Path, monkeypatch) -> Iterator[socket.socket]:
    """A datagram socket bound to a path, named by NOTIFY_SOCKET (systemd's side)."""
    path = sock_dir / "notify.sock"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(path))
    sock.setblocking(False)
    monkeypatch.setenv("NOTIFY_SOCKET", str(path))
    monkeypatch.delenv("WATCHDOG_USEC", raising=False)
    monkeypatch.delenv("WATCHDOG_PID", raising=False)
    yield sock
    sock.close()


def drain(sock: socket.socket) -> list[str]:
    """Every datagram waiting on ``sock``, decoded."""
    out = []
    while True:
        try:
            out.append(sock.recv(4096).decode())
        except BlockingIOError:
            return out


def fields(datagram: str) -> dict[str, str]:
    return dict(line.split("=", 1) for line in datagram.split("\n"))


# -- Notifier --------------------------------------------------------------------------


def test_ready_reaches_notify_socket(receiver):
    """issue 4 systemd: READY=1 (with its STATUS=) reaches the NOTIFY_SOCKET path as one
    datagram."""
    with Notifier() as n:
        assert n.enabled
        assert n.ready(status="tracking 3 fields, API on 127.0.0.1:8750") is True
    (msg,) = drain(receiver)
    assert fields(msg) == {"READY": "1", "STATUS": "tracking 3 fields, API on 127.0.0.1:8750"}


def test_abstract_namespace_socket(monkeypatch):
    """issue 4 systemd: NOTIFY_SOCKET starting with '@' names the abstract namespace."""
    name = f"oralnav-test-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind("\0" + name)
        sock.setblocking(False)
        monkeypatch.setenv("NOTIFY_SOCKET", "@" + name)
        with Notifier() as n:
            assert n.enabled and n.socket_name == "@" + name
            assert n.watchdog()
        assert drain(sock) == ["WATCHDOG=1"]


def test_each_notification_sends_its_assignment(receiver):
    """issue 4 systemd: WATCHDOG=1, STOPPING=1, STATUS=, RELOADING=1 (+MONOTONIC_USEC) and
    EXTEND_TIMEOUT_USEC arrive as systemd expects them."""
    with Notifier() as n:
        assert n.watchdog() and n.stopping(status="arm stopped") and n.status("running")
        before = time.clock_gettime_ns(time.CLOCK_MONOTONIC) // 1000
        assert n.reloading() and n.extend_timeout(2.5)
    got = [fields(m) for m in drain(receiver)]
    assert got[0] == {"WATCHDOG": "1"}
    assert got[1] == {"STOPPING": "1", "STATUS": "arm stopped"}
    assert got[2] == {"STATUS": "running"}
    assert got[3]["RELOADING"] == "1" and int(got[3]["MONOTONIC_USEC"]) >= before
    assert got[4] == {"EXTEND_TIMEOUT_USEC": "2500000"}


def test_status_text_cannot_break_the_protocol(receiver):
    """issue 4 systemd: a STATUS= text with newlines stays one assignment (no injected
    READY=1) and is bounded."""
    with Notifier() as n:
        n.status("fault\nREADY=1")
        n.status("x" * 10_000)
    first, second = drain(receiver)
    assert first == "STATUS=fault READY=1"
    assert len(second) == len("STATUS=") + systemd.STATUS_MAX_CHARS


def test_noop_without_notify_socket(monkeypatch):
    """issue 4 systemd: outside systemd (no NOTIFY_SOCKET) every call is a no-op that says
    so: enabled is False and nothing is sent or raised."""
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    n = Notifier()
    assert not n.enabled and n.socket_name == ""
    assert not any([n.ready("x"), n.watchdog(), n.stopping(), n.status("x"), n.reloading(),
                    n.extend_timeout(1)])
    assert n.failures == 0 and repr(n) == "Notifier(disabled)"
    assert not Notifier(environ={}).enabled


@pytest.mark.parametrize("value", ["vsock:2:1234", "relative/path", "@"])
def test_unusable_notify_socket_value_disables(value, caplog):
    """issue 4 systemd: a NOTIFY_SOCKET that is neither a path nor an @name disables
    notifications with a warning, not an error."""
    with caplog.at_level(logging.WARNING, logger=systemd.__name__):
        n = Notifier(environ={"NOTIFY_SOCKET": value})
    assert not n.enabled and not n.ready()
    assert "notifications are off" in caplog.text


def test_broken_socket_path_does_not_raise_and_logs_once(tmp_path, caplog):
    """issue 4 systemd: a notify failure (no socket at the path) never raises; the first
    is logged as a warning, the rest are ignored."""
    n = Notifier(environ={"NOTIFY_SOCKET": str(tmp_path / "gone.sock")})
    assert n.enabled
    with caplog.at_level(logging.DEBUG, logger=systemd.__name__):
        results = [n.ready(), n.watchdog(), n.status("x"), n.stopping()]
    assert results == [False] * 4 and n.failures == 4
    warnings = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1 and "gone.sock" in warnings[0].getMessage()


def test_systemd_going_away_midway_does_not_raise(receiver, caplog):
    """issue 4 systemd: the socket disappearing after a good send (systemd or journald
    restarting) costs notifications, never an exception; sends recover when it returns."""
    path = receiver.getsockname()
    n = Notifier()
    assert n.ready()
    receiver.close()
    os.unlink(path)
    with caplog.at_level(logging.WARNING, logger=systemd.__name__):
        assert not n.watchdog() and not n.watchdog()
    assert n.failures == 2
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as again:
        again.bind(path)
        again.setblocking(False)
        assert n.watchdog()
        assert drain(again) == ["WATCHDOG=1"]
    n.close()
    n.close()  # idempotent
    assert not n.enabled and not n.watchdog()


def test_full_receive_queue_never_blocks(receiver):
    """issue 4 systemd: when systemd does not read (queue full), a send fails at once
    instead of stalling the event loop."""
    n = Notifier()
    t0 = time.monotonic()
    results = [n.watchdog() for _ in range(2000)]
    assert time.monotonic() - t0 < 1.0
    assert results[0] and not all(results)
    n.close()


# -- watchdog_interval -----------------------------------------------------------------


def test_watchdog_interval_from_watchdog_usec():
    """issue 4 systemd: WATCHDOG_USEC (microseconds) becomes seconds; absent, zero or
    malformed means no watchdog."""
    assert watchdog_interval({"WATCHDOG_USEC": "5000000"}) == 5.0
    assert watchdog_interval({"WATCHDOG_USEC": "40000"}) == pytest.approx(0.04)
    for env in ({}, {"WATCHDOG_USEC": ""}, {"WATCHDOG_USEC": "0"},
                {"WATCHDOG_USEC": "-5"}, {"WATCHDOG_USEC": "5s"}):
        assert watchdog_interval(env) is None, env


def test_watchdog_interval_honours_watchdog_pid(monkeypatch):
    """issue 4 systemd: WATCHDOG_PID limits the request to the pid it names (the control
    process inherits the variables and must not take them as its own)."""
    me = os.getpid()
    assert watchdog_interval({"WATCHDOG_USEC": "1000000", "WATCHDOG_PID": str(me)}) == 1.0
    assert watchdog_interval({"WATCHDOG_USEC": "1000000", "WATCHDOG_PID": str(me + 1)}) is None
    assert watchdog_interval({"WATCHDOG_USEC": "1000000", "WATCHDOG_PID": "7"}, pid=7) == 1.0
    assert watchdog_interval({"WATCHDOG_USEC": "1000000", "WATCHDOG_PID": "abc"}) is None
    monkeypatch.setenv("WATCHDOG_USEC", "2000000")
    monkeypatch.setenv("WATCHDOG_PID", str(me))
    assert watchdog_interval() == 2.0  # os.environ by default


# -- watchdog_task ---------------------------------------------------------------------


async def test_watchdog_task_returns_at_once_without_watchdog(receiver):
    """issue 4 systemd: with no WATCHDOG_USEC (or a disabled notifier) the task reports
    None and returns at once, sending nothing."""
    with Notifier() as n:
        with anyio.fail_after(1):
            async with anyio.create_task_group() as tg:
                assert await tg.start(watchdog_task, n, lambda: True) is None
        with anyio.fail_after(1):
            async with anyio.create_task_group() as tg:
                off = Notifier(environ={})
                task = partial(watchdog_task, interval=1.0)
                assert await tg.start(task, off, lambda: True) is None
    assert drain(receiver) == []


async def test_watchdog_task_pings_at_half_the_interval(receiver, monkeypatch):
    """issue 4 systemd: WATCHDOG_USEC=40 ms -> WATCHDOG=1 every 20 ms while healthy."""
    monkeypatch.setenv("WATCHDOG_USEC", "40000")
    with Notifier() as n:
        async with anyio.create_task_group() as tg:
            period = await tg.start(watchdog_task, n, lambda: True)
            assert period == pytest.approx(0.02)
            await anyio.sleep(0.2)
            tg.cancel_scope.cancel()
    pings = drain(receiver)
    assert set(pings) == {"WATCHDOG=1"}
    assert 6 <= len(pings) <= 13, len(pings)  # 0.2 s / 20 ms + the first, with slack


async def test_watchdog_task_withholds_pings_while_unhealthy(receiver, monkeypatch, caplog):
    """issue 4 systemd: pings stop while healthy() is False (so systemd restarts a wedged
    daemon), the loss is logged once, and pings resume when health returns."""
    monkeypatch.setenv("WATCHDOG_USEC", "40000")
    state = {"ok": True}
    with Notifier() as n, caplog.at_level(logging.WARNING, logger=systemd.__name__):
        async with anyio.create_task_group() as tg:
            await tg.start(watchdog_task, n, lambda: state["ok"])
            await anyio.sleep(0.08)
            state["ok"] = False
            await anyio.sleep(0.03)  # a tick already past its health check may still ping
            assert len(drain(receiver)) >= 2
            await anyio.sleep(0.15)
            assert drain(receiver) == []
            state["ok"] = True
            await anyio.sleep(0.1)
            assert len(drain(receiver)) >= 2
            tg.cancel_scope.cancel()
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1 and "withholding watchdog pings" in errors[0].getMessage()
    assert "resumed" in caplog.text


async def test_health_check_that_raises_counts_as_unhealthy(receiver, caplog):
    """issue 4 systemd: a health check that raises withholds the ping (and names the
    error) instead of crashing the daemon's task group."""

    def broken() -> bool:
        raise RuntimeError("status record unreadable")

    with Notifier() as n, caplog.at_level(logging.ERROR, logger=systemd.__name__):
        async with anyio.create_task_group() as tg:
            assert await tg.start(partial(watchdog_task, interval=0.04), n, broken) == 0.02
            await anyio.sleep(0.08)
            tg.cancel_scope.cancel()
    assert drain(receiver) == []
    assert "status record unreadable" in caplog.text


# -- the unit file ---------------------------------------------------------------------


def parse_unit(text: str) -> dict[str, list[tuple[str, str, str]]]:
    """A systemd unit as {section: [(key, value, comment line above), ...]}; repeated keys
    are kept in order (configparser would merge them)."""
    sections: dict[str, list[tuple[str, str, str]]] = {}
    current = None
    comment = ""
    for raw in text.splitlines():
        line = raw.strip()
        if not line:
            comment = ""
        elif line[0] in "#;":
            comment = line
        elif line.startswith("["):
            current = sections.setdefault(line.strip("[]"), [])
            comment = ""
        else:
            assert current is not None, f"directive outside a section: {raw!r}"
            key, sep, value = line.partition("=")
            assert sep, f"not a KEY=VALUE line: {raw!r}"
            current.append((key.strip(), value.strip(), comment))
            comment = ""
    return sections


def _seconds(span: str) -> float:
    units = {"ms": 1e-3, "s": 1.0, "min": 60.0}
    m = re.fullmatch(r"(\d+(?:\.\d+)?)(ms|s|min)?", span)
    assert m, span
    return float(m.group(1)) * units[m.group(2) or "s"]


@pytest.fixture(scope="module")
def unit() -> dict[str, list[tuple[str, str, str]]]:
    return parse_unit(UNIT.read_text())


def _get(unit, section: str, key: str) -> list[str]:
    return [v for k, v, _ in unit[section] if k == key]


def test_unit_file_has_the_key_directives(unit):
    """issue 4 systemd: the unit is Type=notify with the watchdog, restarts on failure,
    mixed kill mode, the state directory and the main hardening directives."""
    want = {
        "Type": "notify", "NotifyAccess": "main", "WatchdogSec": "5s",
        "Restart": "on-failure", "KillMode": "mixed", "NoNewPrivileges": "yes",
        "ProtectSystem": "strict", "ProtectHome": "yes", "PrivateTmp": "yes",
        "StateDirectory": "oralnav", "RuntimeDirectory": "oralnav",
        "CapabilityBoundingSet": "", "AmbientCapabilities": "",
        "MemoryDenyWriteExecute": "yes",
    }
    for key, value in want.items():
        assert _get(unit, "Service", key) == [value], key
    assert set(unit) == {"Unit", "Service", "Install"}
    exec_start = _get(unit, "Service", "ExecStart")[0].split()
    assert exec_start[0] == "/opt/oralnav/venv/bin/oralnavd"
    assert exec_start[exec_start.index("--config") + 1].startswith("/etc/oralnav/")
    assert _get(unit, "Service", "SystemCallFilter")[0] == "@system-service"
    assert int(_get(unit, "Service", "LimitRTPRIO")[0]) > 0
    assert _get(unit, "Service", "User") and _get(unit, "Service", "Group")


def test_unit_file_timings_and_families(unit):
    """issue 4 systemd: the stop timeout leaves the daemon time to stop the arm and its
    control process (5 s + 1 s) first; the address families keep AF_UNIX (the notify
    socket), TCP for the UR arm and AF_CAN for the tendon drive."""
    assert _seconds(_get(unit, "Service", "TimeoutStopSec")[0]) >= 10
    assert _seconds(_get(unit, "Service", "RestartSec")[0]) >= 1
    families = set(_get(unit, "Service", "RestrictAddressFamilies")[0].split())
    assert {"AF_UNIX", "AF_INET", "AF_INET6", "AF_CAN"} <= families
    assert "yes" not in _get(unit, "Service", "RestrictRealtime")  # SCHED_FIFO is needed


def test_every_unit_directive_has_a_comment(unit):
    """issue 4 systemd: every directive of the unit is preceded by a comment saying why."""
    bare = [(s, k) for s, entries in unit.items() for k, _, c in entries if not c]
    assert bare == []


def test_unit_file_is_package_data():
    """issue 4 systemd: the unit ships inside the package (config/*.service)."""
    shipped = resources.files("oralnav.config").joinpath("oralnavd.service")
    assert shipped.is_file()
    assert "Type=notify" in shipped.read_text()
