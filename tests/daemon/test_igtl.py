"""Issue 33 item 3: the OpenIGTLink server for 3D Slicer (``daemon/igtl.py``), with pyigtl's
own client as the peer on loopback: poses out (names, mm, epoch stamps, new ones only),
suture targets in (validated, refused while RUNNING, audited), hostile input dropped per
connection while the server goes on, and the ``[igtl]`` section."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import socket
import struct
import time
from collections.abc import Iterator

import numpy as np
import pyigtl
import pytest
from scipy.spatial.transform import Rotation

from oralnav.config.daemon import IgtlSection, load_config
from oralnav.config.errors import ConfigError
from oralnav.config.loader import validate
from oralnav.daemon.audit import AuditLog
from oralnav.daemon.core import DaemonCore
from oralnav.daemon.igtl import (
    DEVICE_NAME_BYTES,
    FRAME_NAMES,
    IgtlServer,
    device_name,
    epoch_offset,
    running,
    targets_from_points,
    to_igtl_matrix,
)
from oralnav.daemon.igtl_sockets import REPLY_DEVICE, IgtlSockets
from oralnav.daemon.schemas import SutureTarget
from oralnav.realtime.control_loop import STATUS_DTYPE
from oralnav.safety.states import SafetyState
from oralnav.safety.watchdogs import WatchdogSet

WAIT_S = 3.0   # longest wait for anything on loopback (it takes milliseconds)


class _Control:
    """The control port as the server and the core read it: a status record holding the
    arm's TCP (base frame, m) measured at ``t_arm``; goals and stops are ignored."""

    alive = True

    def __init__(self) -> None:
        self.status = np.zeros((), dtype=STATUS_DTYPE)
        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler("xyz", [180, 0, 30], degrees=True).as_matrix()
        T[:3, 3] = [0.41, -0.12, 0.305]
        self.status["T_B_tcp"] = T
        self.status["t_arm"] = self.status["t"] = time.monotonic()

    def read_status(self) -> np.void:
        return self.status[()].copy()

    def set_goal(self, *args: object, **kwargs: object) -> None:
        pass

    def request_stop(self, reason: str) -> None:
        pass


@dataclasses.dataclass
class Rig:
    core: DaemonCore
    server: IgtlServer
    audit: AuditLog

    def records(self) -> list[dict]:
        return [json.loads(line) for line in self.audit.path.read_text().splitlines()]


@pytest.fixture(scope="module")
def core_and_audit(tmp_path_factory) -> Iterator[tuple[DaemonCore, AuditLog]]:
    """One core and audit log for the module (building the core loads the configuration)."""
    cfg = load_config()
    core = DaemonCore(_Control(), WatchdogSet.from_settings(cfg.settings.safety, 0.002))
    audit = AuditLog(tmp_path_factory.mktemp("igtl") / "audit.jsonl").open()
    core.audit = audit
    yield core, audit
    audit.close()


@pytest.fixture
def fresh(core_and_audit) -> Iterator[Rig]:
    """The module's core READY with no targets, and a server (port 0, 100 Hz) on an event
    loop of its own. The server is per test (it starts in milliseconds): its loop's
    worker threads (the audit's fsync) end with it, as the leaked-thread check wants."""
    core, audit = core_and_audit
    sup, now = core.supervisor, core.clock()
    if sup.state in (SafetyState.RUNNING, SafetyState.PAUSED):
        sup.abort(now, "test")
    sup.mark_ready(now)
    core.set_targets([], "test")
    server = IgtlServer(core, "127.0.0.1", 0, rate_hz=100.0)
    with running(server):
        yield Rig(core, server, audit)


@contextlib.contextmanager
def client(port: int) -> Iterator[pyigtl.OpenIGTLinkClient]:
    c = pyigtl.OpenIGTLinkClient("127.0.0.1", port)
    try:
        t0 = time.monotonic()
        while not c.is_connected():
            assert time.monotonic() - t0 < WAIT_S, "pyigtl's client did not connect"
            time.sleep(0.005)
        yield c
    finally:
        c.stop()


def _rigid(rx: float, ry: float, rz: float, t: list[float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [rx, ry, rz], degrees=True).as_matrix()
    T[:3, 3] = t
    return T


def _send_points(c: pyigtl.OpenIGTLinkClient, device: str, names: list[str],
                 xyz_mm: list[list[float]]) -> str:
    """Send a POINT list and return the server's answer (the STRING's text)."""
    c.send_message(pyigtl.PointMessage(positions=xyz_mm, names=names, device_name=device),
                   wait=True)
    reply = c.wait_for_message(REPLY_DEVICE, timeout=WAIT_S)
    assert reply is not None, "no reply to the POINT message"
    return reply.string


def _closed_by_server(sock: socket.socket) -> bool:
    """Whether the server closes ``sock`` (reading past what it sends first)."""
    sock.settimeout(WAIT_S)
    try:
        while sock.recv(65536):
            pass
    except TimeoutError:
        return False
    except ConnectionResetError:
        pass
    return True


# -- pure helpers -----------------------------------------------------------------------
def test_names_follow_the_plus_convention_and_fit_a_header():
    """Item 3.1: each pose ``T_<to>_<from>`` is sent as ``<from>To<to>`` from the one frame
    table; every name the daemon publishes fits the header's 20 bytes; a frame not in the
    table keeps its code; what is not a pose name, or too long, has no name."""
    assert device_name("T_C_RM") == "RobotToCamera"
    assert device_name("T_C_OM") == "OpenerToCamera"
    assert device_name("T_C_EM") == "EffectorToCamera"
    assert device_name("T_En_EM") == "EffectorToEndoscope"
    assert device_name("T_B_tcp") == "TcpToRobotBase"
    for to in ("C", "En", "B"):
        for frm in FRAME_NAMES:
            name = device_name(f"T_{to}_{frm}")
            assert name is not None and len(name.encode()) <= DEVICE_NAME_BYTES
    assert device_name("T_C_XY") == "XYToCamera"
    assert device_name("T_C_" + "Q" * 20) is None
    assert device_name("opener") is None and device_name("T_C") is None


def test_matrices_go_out_in_millimetres_and_stamps_on_the_epoch():
    """Item 3.1: a pose in metres becomes a float32 matrix with its translation in mm
    (rotation untouched); the clock offset maps a monotonic stamp onto the wall clock."""
    T = _rigid(10, 20, 30, [0.1, -0.02, 0.3])
    M = to_igtl_matrix(T)
    assert M.dtype == np.float32
    np.testing.assert_allclose(M[:3, 3], [100.0, -20.0, 300.0], rtol=1e-6)
    np.testing.assert_allclose(M[:3, :3], T[:3, :3], atol=1e-7)
    assert T[0, 3] == 0.1   # the pose itself is not changed
    mono = iter(np.arange(100.0, 101.0, 0.01))
    assert epoch_offset(lambda: float(next(mono)), lambda: 1.7e9) == pytest.approx(
        1.7e9 - 100.005)
    assert abs(time.monotonic() + epoch_offset(time.monotonic) - time.time()) < 0.01


def test_points_become_targets_with_the_api_checks():
    """Item 3.2: POINT positions (mm, OM) become suture targets in metres; NaN, a point
    beyond the opener's reach, a name the API refuses, repeated names and too many
    points are refused, each naming the point."""
    got = targets_from_points(["F-1", "F_2"], [(10.0, -5.0, 2.5), (0.0, 0.0, 199.0)])
    assert got == [SutureTarget(name="F-1", p_OM=(0.01, -0.005, 0.0025)),
                   SutureTarget(name="F_2", p_OM=(0.0, 0.0, 0.199))]
    cases = [
        (["a", "b"], [(1, 2, 3), (math.nan, 0, 0)], "point 1 'b': position [nan, 0.0, 0.0]"),
        (["a"], [(0, 0, 250.0)], "point 0 'a': 250.0 mm from the opener marker's origin"),
        (["F 1"], [(1, 2, 3)], "point 0 'F 1': name: String should match pattern"),
        ([""], [(1, 2, 3)], "point 0 '': name"),
        (["a", "a"], [(1, 2, 3), (4, 5, 6)], "target names must be unique; repeated: a"),
        ([f"p{i}" for i in range(65)], [(1, 2, 3)] * 65, "65 points; at most 64"),
    ]
    for names, xyz, words in cases:
        with pytest.raises(ValueError, match=None) as ei:
            targets_from_points(names, xyz)
        assert words in str(ei.value), str(ei.value)


# -- poses out ------------------------------------------------------------------------
def test_poses_stream_as_the_core_shows_them(fresh: Rig):
    """Item 3.1: every published pose and the arm's TCP arrive under their names, equal to
    GET /poses (translation in mm) to float32 precision, stamped with their capture
    instant on the epoch."""
    core, server = fresh.core, fresh.server
    now = core.clock()
    published = {"T_C_RM": _rigid(5, -10, 90, [0.05, 0.10, 0.45]),
                 "T_C_OM": _rigid(-30, 15, 0, [-0.02, 0.03, 0.38]),
                 "T_C_EM": _rigid(170, 5, -45, [0.01, -0.04, 0.41]),
                 "T_En_EM": _rigid(0, 80, 10, [0.001, 0.002, 0.03])}
    for i, (name, T) in enumerate(published.items()):
        core.publish_pose(name, T, now - 0.01 * i, frame=name.split("_")[1])
    shown = core.poses()
    expected = {n: (np.array(shown[n]["T"]), now - 0.01 * i)
                for i, n in enumerate(published)}
    st = core.control.read_status()
    expected["T_B_tcp"] = (np.array(shown["tcp"]["T"]), float(st["t_arm"]))
    with client(server.port) as c:
        for pose, (T, stamp) in expected.items():
            msg = c.wait_for_message(device_name(pose), timeout=WAIT_S)
            assert msg is not None, f"{device_name(pose)} not received"
            T_mm = T.copy()
            T_mm[:3, 3] *= 1e3
            np.testing.assert_allclose(msg.matrix, T_mm, rtol=1e-6, atol=1e-6,
                                       err_msg=pose)
            assert msg.timestamp == pytest.approx(stamp + server.offset, abs=1e-6), pose


def test_only_new_poses_are_sent(fresh: Rig):
    """Item 3.1: a pose goes out once per capture stamp: nothing is re-sent while it does
    not change; the next publication goes out with its own stamp."""
    core, server = fresh.core, fresh.server
    T = _rigid(0, 0, 0, [0.0, 0.0, 0.3])

    def received(c: pyigtl.OpenIGTLinkClient, stamp: float) -> None:
        # the module's core may hold an older opener pose: it goes out first, once
        t0 = time.monotonic()
        while True:
            msg = c.wait_for_message("OpenerToCamera", timeout=WAIT_S)
            assert msg is not None and time.monotonic() - t0 < WAIT_S
            if msg.timestamp == pytest.approx(stamp + server.offset, abs=1e-6):
                return

    stamp = core.clock()
    core.publish_pose("T_C_OM", T, stamp, frame="C")
    with client(server.port) as c:
        received(c, stamp)
        time.sleep(10 / server.rate_hz)   # ten ticks: nothing again
        assert c.wait_for_message("OpenerToCamera", timeout=0) is None
        stamp = core.clock()
        core.publish_pose("T_C_OM", T, stamp, frame="C")
        received(c, stamp)


# -- targets in ---------------------------------------------------------------------
def test_points_set_targets_and_are_audited(fresh: Rig):
    """Item 3.2: a POINT list (mm, OM) becomes the suture targets as POST /targets sets
    them, is answered ``ok``, and leaves a write-ahead intent and its outcome in the
    audit log (method IGTL, path igtl:POINT/<device>, who igtl, the client address)."""
    core = fresh.core
    with client(fresh.server.port) as c:
        answer = _send_points(c, "F", ["F-1", "F-2"], [[12.5, -3.0, 40.0], [0.0, 8.0, 41.0]])
    assert answer == "ok: 2 suture target(s) set from POINT 'F'"
    got = core.targets()
    assert [t.name for t in got] == ["F-1", "F-2"]
    np.testing.assert_allclose(got[0].p_OM, [0.0125, -0.003, 0.040], rtol=1e-6)
    intent, outcome = fresh.records()[-2:]
    assert intent["phase"] == "intent" and outcome["phase"] == "outcome"
    assert intent["id"] == outcome["id"]
    for rec in (intent, outcome):
        assert rec["method"] == "IGTL" and rec["path"] == "igtl:POINT/F"
        assert rec["who"] == "igtl" and rec["client"].startswith("127.0.0.1:")
    assert '"F-1"' in intent["body"] and outcome["status"] == 200


def test_points_refused_while_running(fresh: Rig):
    """Item 3.2: while RUNNING the targets stay as they are; the sender is told why (409)
    and the refusal is audited."""
    core = fresh.core
    core.set_targets([SutureTarget(name="kept", p_OM=(0.0, 0.0, 0.05))], "test")
    core.supervisor.start(core.clock(), "test")
    with client(fresh.server.port) as c:
        answer = _send_points(c, "F", ["F-1"], [[1.0, 2.0, 3.0]])
    assert answer.startswith("refused (409): cannot change targets while RUNNING"), answer
    assert [t.name for t in core.targets()] == ["kept"]
    outcome = fresh.records()[-1]
    assert outcome["status"] == 409 and outcome["path"] == "igtl:POINT/F"


def test_nan_and_far_points_are_refused(fresh: Rig):
    """Item 3.3: a POINT list with NaN, or a point far outside the opener, is refused
    (422) naming the point; the targets and the connection stay."""
    core = fresh.core
    with client(fresh.server.port) as c:
        nan = _send_points(c, "F", ["a", "b"], [[1.0, 2.0, 3.0], [math.nan, 0.0, 0.0]])
        far = _send_points(c, "F", ["a"], [[0.0, 0.0, 350.0]])
        assert core.targets() == []
        ok = _send_points(c, "F", ["a"], [[0.0, 0.0, 35.0]])
    assert nan.startswith("refused (422): point 1 'b'"), nan
    assert far.startswith("refused (422): point 0 'a': 350.0 mm"), far
    assert ok.startswith("ok: 1 suture target(s)")
    statuses = [r["status"] for r in fresh.records()[-4:]]
    assert statuses == [422, 422, None, 200]   # the last command: intent, outcome


# -- hostile input ------------------------------------------------------------------
def test_hostile_input_closes_only_that_connection(fresh: Rig, caplog):
    """Item 3.3: garbage bytes, a header declaring a huge body, a wrong CRC and a client
    that goes away mid-message each close (only) that connection with a logged reason;
    a client afterwards still gets the poses and sets targets."""
    server = fresh.server
    head = struct.Struct(">H12s20sIIQQ")
    hostile = {
        "garbage": b"\xff\xfe" * 64,
        "HTTP": b"GET / HTTP/1.1\r\nHost: x\r\n\r\n" + b"x" * 40,
        "huge body": head.pack(1, b"POINT", b"F", 0, 0, 1 << 40, 0),
        "CRC": head.pack(1, b"POINT", b"F", 0, 0, 4, 12345) + b"abcd",
    }
    with caplog.at_level("INFO", logger="oralnav.daemon.igtl"):
        for what, data in hostile.items():
            with socket.create_connection(("127.0.0.1", server.port), timeout=WAIT_S) as s:
                s.sendall(data)
                assert _closed_by_server(s), f"{what}: connection left open"
        with socket.create_connection(("127.0.0.1", server.port), timeout=WAIT_S) as s:
            s.sendall(head.pack(1, b"POINT", b"F", 0, 0, 136, 0)[:30])   # and leaves
    text = caplog.text
    assert "not an OpenIGTLink stream?" in text
    assert "declares a body of 1099511627776 bytes, more than the 65536 accepted" in text
    assert "CRC mismatch" in text
    fresh.core.publish_pose("T_C_OM", np.eye(4), fresh.core.clock(), frame="C")
    with client(server.port) as c:
        assert c.wait_for_message("OpenerToCamera", timeout=WAIT_S) is not None
        assert _send_points(c, "G", ["g"], [[1.0, 1.0, 1.0]]).startswith("ok:")
    assert [t.name for t in fresh.core.targets()] == ["g"]


def test_a_framed_but_malformed_point_body_is_refused_and_the_stream_goes_on(fresh: Rig):
    """Item 3.3: a POINT whose body is not whole points (valid frame and CRC) is refused
    (400) and audited; the same connection then sets targets."""
    good = pyigtl.PointMessage(positions=[[1.0, 2.0, 3.0]], names=["a"],
                               device_name="F").pack()
    body = good[58:-10]            # a point cut short; the header says so, with its CRC
    bad = good[:42] + struct.pack(">QQ", len(body), pyigtl.messages.CRC64(body)) + body
    with client(fresh.server.port) as c:
        c.socket.sendall(bad)      # pyigtl's own client socket: framed, CRC right
        reply = c.wait_for_message(REPLY_DEVICE, timeout=WAIT_S)
        assert reply is not None and reply.string.startswith(
            "refused (400): malformed POINT message: ValueError: 126 bytes"), reply.string
        assert _send_points(c, "F", ["a"], [[1.0, 2.0, 3.0]]).startswith("ok:")
    assert fresh.records()[-3]["status"] == 400


def test_a_stalled_message_and_a_client_that_does_not_read_are_dropped(caplog):
    """Item 3.3: the socket thread on its own: a message begun and never finished is
    dropped after the stall time, a client that reads nothing past its outbox bound; the
    server still accepts clients and sends."""
    sockets = IgtlSockets("127.0.0.1", 0, stall_s=0.2, max_outbox=4096)
    sockets.start()
    try:
        with caplog.at_level("WARNING", logger="oralnav.daemon.igtl"):
            with socket.create_connection(("127.0.0.1", sockets.port)) as s:
                s.sendall(b"\x00\x01POINT")
                assert _closed_by_server(s)
            with socket.socket() as s:
                s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # a small window
                s.connect(("127.0.0.1", sockets.port))
                t0 = time.monotonic()
                while sockets.clients == 0:
                    assert time.monotonic() - t0 < WAIT_S
                    time.sleep(0.005)
                big = [(f"P{i % 4}", np.eye(4, dtype=np.float32), 1.7e9) for i in range(200)]
                for _ in range(200):
                    sockets.broadcast(big)
                    if "not reading" in caplog.text:
                        break
                    time.sleep(0.01)
        assert "still unfinished" in caplog.text
        assert "not reading" in caplog.text
        t0 = time.monotonic()
        while sockets.queued:   # what is still queued would swamp the next client's outbox
            assert time.monotonic() - t0 < WAIT_S
            time.sleep(0.005)
        with client(sockets.port) as c:
            sockets.broadcast([("X", np.eye(4, dtype=np.float32), 1.7e9)])
            assert c.wait_for_message("X", timeout=WAIT_S) is not None
    finally:
        sockets.close()


# -- configuration and wiring ---------------------------------------------------------
def test_igtl_section_defaults_and_loopback_rule(tmp_path):
    """Item 3: ``[igtl]`` defaults to 127.0.0.1:18944 at 30 Hz accepting targets; a
    remote host needs allow_remote; the rate is bounded; each error names the key."""
    path = tmp_path / "d.toml"
    sec = validate(IgtlSection, {}, path, "igtl")
    assert (sec.enabled, sec.host, sec.port, sec.rate_hz, sec.accept_targets) == (
        True, "127.0.0.1", 18944, 30.0, True)
    assert validate(IgtlSection, {"host": "0.0.0.0", "allow_remote": True}, path,
                    "igtl").host == "0.0.0.0"
    for bad, where in [({"host": "0.0.0.0"}, "host"), ({"rate_hz": 500.0}, "rate_hz"),
                       ({"port": 0}, "port"), ({"enabled": "yes"}, "enabled")]:
        with pytest.raises(ConfigError) as ei:
            validate(IgtlSection, bad, path, "igtl")
        assert str(ei.value).startswith(f"{path}: [igtl] {where}:"), str(ei.value)
    assert load_config().settings.igtl is None   # absent: off


def test_the_service_binds_the_configured_port_or_says_why(fresh: Rig):
    """Item 3: the service builds the server only when ``[igtl]`` is present and enabled,
    binds it before anything starts, and a taken port is a ConfigError naming
    ``[igtl] port``."""
    from oralnav.daemon.service import igtl_server

    cfg = load_config()

    def with_igtl(**kw):
        return dataclasses.replace(cfg, settings=cfg.settings.model_copy(
            update={"igtl": IgtlSection(**kw) if kw else None}))

    cleanup: list = []
    assert igtl_server(with_igtl(), fresh.core, cleanup) is None
    assert igtl_server(with_igtl(enabled=False, port=1), fresh.core, cleanup) is None
    with pytest.raises(ConfigError) as ei:
        igtl_server(with_igtl(port=fresh.server.port), fresh.core, cleanup)
    assert "[igtl] port" in str(ei.value) and "in use" in str(ei.value), str(ei.value)
    assert cleanup == []


def test_the_benchmark_runs_and_reports_rate_and_age(tmp_path, capsys):
    """Item 3 figures: ``oralnav bench igtl`` (short runs) writes igtl.json and prints per
    run the messages per second per pose near the server's rate and the age at receipt
    (fresh poses: milliseconds; camera-like: up to a period more)."""
    from oralnav.cli.main import run

    assert run(["bench", "igtl", "--out", str(tmp_path), "--seconds", "0.4", "--json"]) == 0
    runs = json.loads(capsys.readouterr().out)
    assert json.loads((tmp_path / "igtl.json").read_text())["runs"] == runs
    assert set(runs) == {"fresh_30hz", "fresh_120hz", "camera_30hz"}
    for r in runs.values():
        assert r["poses"] == 4
        assert 0.5 * r["rate_hz"] < r["messages_per_s_per_pose"] <= 1.1 * r["rate_hz"], r
        assert 0.0 < r["age_ms"]["p50"] <= r["age_ms"]["p99"] <= r["age_ms"]["max"]
    assert runs["fresh_30hz"]["age_ms"]["p50"] < 20.0
