"""The fault campaign (issue 30): the real daemon under kills, stalls, hostile bodies, resets
and a long run.

``oralnav bench faults --out DIR [--quick] [--json]`` (or ``python -m bench faults``) runs
``oralnavd`` on the simulated cell as a subprocess (a configuration written into
``DIR/faults_run`` from the embedded ``config/sim.toml``: its own tokens file, a free
loopback port and an audit log in that folder) and measures, each as one scenario of
``faults.json``:

- ``daemon_kill``: bursts of operator commands while the daemon is SIGKILLed at a random
  moment, several rounds on one audit log; every command answered 200 must have its audit
  record (the single-record format, or write-ahead intent/outcome records with ids);
- ``control_kill``: SIGKILL of the control process, the daemon's child: time to FAULT in
  ``GET /status`` and to 503 from ``GET /health``;
- ``control_stop``: SIGSTOP of the control process for a few seconds: FAULT latency from
  the loop's last period (its status record's clock, read back through ``GET /poses``),
  from the SIGSTOP and as the daemon saw it (``last_silence``), ``/health`` 503 while
  stopped, then SIGCONT and a reset to READY;
- both with the simulation's tolerant ``max_period_lateness`` (daemon A) and with the robot
  PC's 10 ms (daemon B; FAULTs its loop latches by itself on a busy machine are recorded);
- ``bodies``: a 47 MB ``POST /targets`` without a token and with one, while ``/health`` is
  polled every 10 ms (longest gap, FAULT latched or not); JSON nested 1000 deep and invalid
  UTF-8 (400, audited);
- ``reset_cycle``: procedure running, ``/estop``, ``/reset``: READY within 1 s and held,
  then ``/procedure/resume``, N cycles;
- ``soak``: ``GET /status`` at 50/s while the RSS of the daemon and of the control process
  is sampled from /proc: growth during warm-up and after it.

It writes ``faults.json`` and ``faults.png`` into DIR; progress goes to stderr. Every process
it starts runs in its own process group and is killed on the way out. Loopback only.
"""

from __future__ import annotations

import http.client
import json
import os
import random
import select
import signal
import socket
import subprocess
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterable, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

# -- targets (issue 30) ---------------------------------------------------------------------
#: an unauthenticated 47 MB body must be refused within this (s)
REFUSE_TARGET_S = 1.0
#: longest interval between two /health answers while a large body arrives (s)
HEALTH_GAP_TARGET_S = 0.1
#: FAULT after the control loop's last period with the robot PC's settings (s)
STOP_FAULT_TARGET_S = 0.020
#: after a reset: READY within this (s) ...
READY_WITHIN_S = 1.0
#: ... and still READY this long after (s)
READY_HOLD_S = 1.0
#: RSS growth after warm-up (MiB/min) below which memory counts as bounded
RSS_BOUND_MIB_PER_MIN = 0.5
#: the RSS verdict counts only with this much soak after the warm-up (s)
CONCLUSIVE_AFTER_S = 600.0
#: the robot PC's default [safety] max_period_lateness (docs/safety.md), s
ROBOT_PC_LATENESS = 0.01

#: the large body of issue 30 (bytes, at least)
LARGE_BODY_BYTES = 47_000_000
#: how long a daemon may take to reach READY (s): preparing the simulated cell takes
#: 20-30 s on the 2-core development VM
START_TIMEOUT_S = 180.0
#: one burst of commands in the daemon-kill scenario is bounded in count and time
BURST_MAX_COMMANDS = 5000
BURST_MAX_S = 10.0

#: the commands of a burst, in turn (path, body); 409s are expected and fine
BURST = (("/targets", "targets"), ("/procedure/start", None), ("/procedure/abort", None),
         ("/estop", {"reason": "fault campaign"}), ("/reset", None))


def _log(msg: str) -> None:
    print(f"bench faults: {msg}", file=sys.stderr, flush=True)


def params(quick: bool) -> dict[str, Any]:
    """The campaign's sizes: ``--quick`` for development, the full run for the figures."""
    return {"kill_rounds": 3 if quick else 5,
            "reset_cycles": 10 if quick else 100,
            "soak_s": 60.0 if quick else 1800.0,
            "soak_poll_hz": 50.0,
            "rss_every_s": 2.0 if quick else 5.0,
            "warmup_s": 30.0 if quick else 180.0,
            "stop_s": 3.0,
            "robot_pc_watch_s": 5.0 if quick else 30.0,
            "health_poll_s": 0.010}


# == pure parts (tests/bench/test_faults.py) =================================================
def parse_audit(text: str) -> tuple[list[dict[str, Any]], int]:
    """The records of an audit log's text in file order, and the count of lines that do not
    parse as a JSON object (a record torn by a crash)."""
    records: list[dict[str, Any]] = []
    torn = 0
    for line in text.splitlines():
        if not line.strip():
            continue
        try:
            rec = json.loads(line)
        except ValueError:
            torn += 1
            continue
        if isinstance(rec, dict):
            records.append(rec)
        else:
            torn += 1
    return records, torn


_KIND_KEYS = ("phase", "kind", "type", "event", "stage", "record")
_ID_KEYS = ("intent_id", "intent", "id", "seq", "ref")


def _kind(rec: dict[str, Any]) -> str | None:
    for k in _KIND_KEYS:
        v = rec.get(k)
        if isinstance(v, str):
            return v.lower()
    return None


def _status(rec: dict[str, Any]) -> int | None:
    for v in (rec.get("status"), rec.get("http_status"),
              rec["outcome"].get("status") if isinstance(rec.get("outcome"), dict) else None):
        if isinstance(v, int) and not isinstance(v, bool):
            return v
    return None


def audited_commands(records: Iterable[dict[str, Any]]) -> list[tuple[str | None, int]]:
    """``(path, status)`` of every finished command in file order.

    Two formats are read: the single record per command (``path`` and ``status`` in one
    line), and write-ahead records, an ``intent`` (with the path and an id) written before
    the command runs and an ``outcome`` (with the status, and the path or the intent's id)
    after it. An intent alone is not a finished command."""
    intents: dict[Any, dict[str, Any]] = {}
    out: list[tuple[str | None, int]] = []
    for rec in records:
        kind = _kind(rec)
        status = _status(rec)
        if kind == "intent" or (status is None and rec.get("path") is not None):
            for k in _ID_KEYS:
                if rec.get(k) is not None:
                    intents[rec[k]] = rec
                    break
            continue
        if status is None:
            continue
        path = rec.get("path")
        if path is None:
            for k in _ID_KEYS:
                ref = rec.get(k)
                if ref is not None and ref in intents:
                    path = intents[ref].get("path")
                    break
        out.append((path, status))
    return out


def unfinished_intents(records: Iterable[dict[str, Any]]) -> list[Any]:
    """Ids of write-ahead intents with no later record of the same id (the commands a
    crash interrupted before their outcome was written)."""
    open_ids: dict[Any, None] = {}
    for rec in records:
        rid = rec.get("id")
        if rid is None:
            continue
        if _kind(rec) == "intent":
            open_ids[rid] = None
        else:
            open_ids.pop(rid, None)
    return list(open_ids)


def match_acks(acks: Sequence[str], commands: Sequence[tuple[str | None, int]],
               status: int = 200) -> dict[str, Any]:
    """Match acknowledged commands (their paths, in the order their answers came) with
    audited ones in file order: an acknowledged command is audited when a record with its
    path and ``status`` follows the record matched to the one before it. Returns
    ``acknowledged``, ``audited`` and ``missing`` (index and path of each unmatched one)."""
    pos = 0
    missing: list[dict[str, Any]] = []
    for i, path in enumerate(acks):
        j = pos
        while j < len(commands) and commands[j] != (path, status):
            j += 1
        if j < len(commands):
            pos = j + 1
        else:
            missing.append({"index": i, "path": path})
    return {"acknowledged": len(acks), "audited": len(acks) - len(missing),
            "missing": missing}


def rss_trend(t_s: Sequence[float], mib: Sequence[float], warmup_s: float,
              bound_mib_per_min: float = RSS_BOUND_MIB_PER_MIN) -> dict[str, Any]:
    """Memory over time: growth and least-squares slope (MiB/min) during the warm-up
    (``t < warmup_s``, seconds from the first sample) and after it. ``bounded`` is whether
    the slope after warm-up stays within ``bound_mib_per_min`` (None with fewer than three
    samples after warm-up)."""
    import numpy as np

    t = np.asarray(t_s, dtype=float)
    m = np.asarray(mib, dtype=float)
    doc: dict[str, Any] = {"samples": int(t.size), "warmup_s": warmup_s,
                           "bound_mib_per_min": bound_mib_per_min}
    if t.size == 0:
        return {**doc, "bounded": None}
    t = t - t[0]

    def part(sel: np.ndarray) -> dict[str, Any]:
        if sel.sum() < 2:
            return {"samples": int(sel.sum()), "growth_mib": None, "slope_mib_per_min": None}
        ts, ms = t[sel], m[sel]
        slope = float(np.polyfit(ts / 60.0, ms, 1)[0]) if sel.sum() >= 3 else \
            float((ms[-1] - ms[0]) / max((ts[-1] - ts[0]) / 60.0, 1e-9))
        return {"samples": int(sel.sum()), "span_s": float(ts[-1] - ts[0]),
                "growth_mib": float(ms[-1] - ms[0]), "slope_mib_per_min": slope}

    warm = part(t < warmup_s)
    after = part(t >= warmup_s)
    bounded = (None if after["samples"] < 3
               else bool(after["slope_mib_per_min"] <= bound_mib_per_min))
    return {**doc, "first_mib": float(m[0]), "last_mib": float(m[-1]), "max_mib": float(m.max()),
            "warmup": warm, "after_warmup": after, "bounded": bounded,
            # a slope over a few minutes is noise next to a slow leak: 10 minutes at least
            "conclusive": bool(after.get("span_s", 0.0) >= CONCLUSIVE_AFTER_S)}


def answer_gaps(answers: Iterable[float], t_from: float, t_to: float) -> list[float]:
    """Intervals (s) between consecutive answer times within ``[t_from, t_to]``, the window's
    edges included: a request that never came back in the window shows as the last gap."""
    pts = [t_from, *sorted(a for a in answers if t_from <= a <= t_to), t_to]
    return [b - a for a, b in zip(pts, pts[1:], strict=False)]


def write_tokens(path: Path) -> str:
    """A tokens file (mode 0600) with one operator token, ``bench``; returns the token."""
    import hashlib
    import secrets

    token = secrets.token_urlsafe(32)
    digest = hashlib.sha256(token.encode()).hexdigest()
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(f'[tokens.bench]\nrole = "operator"\nsha256 = "{digest}"\n')
    return token


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int | float | str):
        return json.dumps(v)  # a JSON number or string is a TOML one here
    if isinstance(v, list) and not any(isinstance(x, dict) for x in v):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {v!r} as a TOML value")


def _toml(doc: dict[str, Any], prefix: str = "") -> list[str]:
    lines = [f"[{prefix}]"] if prefix else []
    lines += [f"{k} = {_toml_value(v)}" for k, v in doc.items() if not isinstance(v, dict)]
    for k, v in doc.items():
        if isinstance(v, dict):
            lines += _toml(v, f"{prefix}.{k}" if prefix else k)
    return lines


def write_daemon_config(path: Path, *, port: int, tokens_file: Path, audit_log: Path,
                        lateness: float | None = None, base: Path | None = None) -> Path:
    """A daemon configuration at ``path``: ``base`` (default: the embedded sim.toml) with
    every file it names made absolute, ``[api]`` on 127.0.0.1:``port`` with ``tokens_file``
    and ``audit_log``, and ``[safety] max_period_lateness`` set when ``lateness`` is given."""
    import tomllib

    if base is None:
        from oralnav.config.daemon import default_config_path
        base = default_config_path()
    doc = tomllib.loads(Path(base).read_text())

    def absolute(d: dict[str, Any]) -> None:
        for k, v in d.items():
            if isinstance(v, dict):
                absolute(v)
            elif isinstance(v, str) and (Path(base).parent / v).is_file():
                d[k] = str((Path(base).parent / v).resolve())

    absolute(doc)
    doc.setdefault("api", {}).update(host="127.0.0.1", port=int(port),
                                     tokens_file=str(Path(tokens_file).resolve()),
                                     audit_log=str(Path(audit_log).resolve()))
    if lateness is not None:
        doc.setdefault("safety", {})["max_period_lateness"] = float(lateness)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("# written by oralnav bench faults\n" + "\n".join(_toml(doc)) + "\n")
    return path


# == processes ===============================================================================
def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def children(pid: int) -> list[int]:
    """The pids whose parent is ``pid`` (from /proc)."""
    out = []
    for name in os.listdir("/proc"):
        if not name.isdigit():
            continue
        try:
            stat = Path(f"/proc/{name}/stat").read_text()
        except OSError:
            continue
        fields = stat.rsplit(")", 1)[-1].split()  # the name in brackets may hold spaces
        if len(fields) > 1 and int(fields[1]) == pid:
            out.append(int(name))
    return out


def rss_mib(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except (OSError, ValueError, IndexError):
        pass
    return None


class DaemonRunError(RuntimeError):
    """The campaign's oralnavd process did not do what a run needs (exited, never READY,
    no control process); not the daemon's own ``oralnav.daemon.errors.DaemonError``."""


class Daemon:
    """One ``oralnavd --config FILE`` in a process group of its own; its output goes to
    ``log``. :meth:`close` stops it (SIGTERM, then SIGKILL) and kills what is left of its
    group."""

    def __init__(self, config: Path, log: Path, port: int, token: str) -> None:
        self.config, self.log, self.port, self.token = config, log, port, token
        self.proc: subprocess.Popen[bytes] | None = None
        #: FAULTs latched (and reset) while :meth:`wait_ready` waited
        self.start_faults: list[str] = []

    @property
    def pid(self) -> int:
        assert self.proc is not None
        return self.proc.pid

    def command(self) -> list[str]:
        exe = Path(sys.executable).with_name("oralnavd")
        if exe.exists():
            return [str(exe), "--config", str(self.config)]
        return [sys.executable, "-m", "oralnav.daemon.main", "--config", str(self.config)]

    def start(self) -> Daemon:
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        with open(self.log, "ab") as out:
            self.proc = subprocess.Popen(self.command(), stdout=out, stderr=subprocess.STDOUT,
                                         stdin=subprocess.DEVNULL, env=env,
                                         start_new_session=True)
        return self

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def log_tail(self, lines: int = 8) -> str:
        try:
            return "\n".join(self.log.read_text(errors="replace").splitlines()[-lines:])
        except OSError:
            return ""

    def wait_ready(self, timeout: float = START_TIMEOUT_S) -> float:
        """Seconds until ``GET /status`` says READY; DaemonRunError if it exits or times out.
        A FAULT latched on the way (a loop that stalls by itself on a busy machine) is
        reset, as an operator would, and kept in :attr:`start_faults`."""
        t0 = time.monotonic()
        self.start_faults = []
        api = Api(self.port, self.token, timeout=2.0)
        try:
            while time.monotonic() - t0 < timeout:
                if not self.alive():
                    raise DaemonRunError(f"oralnavd exited ({self.proc.returncode}) before "
                                      f"READY:\n{self.log_tail()}")
                try:
                    code, doc = api.get("/status")
                    state = doc["safety"]["state"] if code == 200 else None
                    if state == "READY":
                        return time.monotonic() - t0
                    if state == "FAULT":
                        for c in doc["safety"].get("reasons", []):
                            why = f"{c['source']}: {c['reason']}"
                            if why not in self.start_faults:
                                self.start_faults.append(why)
                        api.post("/reset")
                except (OSError, http.client.HTTPException, KeyError, TypeError):
                    pass
                time.sleep(0.2)
        finally:
            api.close()
        raise DaemonRunError(f"oralnavd not READY within {timeout:g} s:\n{self.log_tail()}")

    def control_pid(self) -> int:
        """The control process: the daemon's child started by multiprocessing's spawn
        (``Process(name="oralnavd-control")``; its resource tracker is the other child)."""
        for pid in children(self.pid):
            try:
                cmd = Path(f"/proc/{pid}/cmdline").read_bytes()
                comm = Path(f"/proc/{pid}/comm").read_text().strip()
            except OSError:
                continue
            if comm.startswith("oralnavd-contro") or (b"spawn_main" in cmd
                                                       and b"resource_tracker" not in cmd):
                return pid
        raise DaemonRunError(f"no control process among the children of {self.pid}")

    def kill_now(self) -> None:
        """SIGKILL the daemon alone, now (from a timer thread; reaped by :meth:`kill`)."""
        try:
            os.kill(self.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass

    def kill(self) -> None:
        """SIGKILL the daemon alone, reap it, then clear what its children leave behind."""
        if self.alive():
            os.kill(self.pid, signal.SIGKILL)
        self._reap(5.0)

    def close(self) -> None:
        if self.proc is None:
            return
        if self.alive():
            os.kill(self.pid, signal.SIGTERM)
        self._reap(15.0)

    def _reap(self, wait_s: float) -> None:
        assert self.proc is not None
        try:
            self.proc.wait(timeout=wait_s)
        except subprocess.TimeoutExpired:
            os.kill(self.pid, signal.SIGKILL)
            self.proc.wait(timeout=5.0)
        # the control process leaves by itself once orphaned; give it a moment, then kill
        # whatever of the group is left (its own process group: never anything else)
        deadline = time.monotonic() + 3.0
        while time.monotonic() < deadline:
            try:
                os.killpg(self.pid, 0)
            except ProcessLookupError:
                return
            time.sleep(0.05)
        try:
            os.killpg(self.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass

    def __enter__(self) -> Daemon:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()


# == HTTP ====================================================================================
class Api:
    """A keep-alive HTTP client of the operator API on 127.0.0.1 (the standard library's)."""

    def __init__(self, port: int, token: str | None = None, timeout: float = 5.0) -> None:
        self.port, self.token, self.timeout = port, token, timeout
        self._conn: http.client.HTTPConnection | None = None

    def close(self) -> None:
        if self._conn is not None:
            self._conn.close()
            self._conn = None

    def request(self, method: str, path: str, body: Any = None, *, auth: bool = True,
                retry: bool = True) -> tuple[int, Any]:
        """``(status, JSON answer or None)``; OSError / HTTPException when no answer came
        (retried once on a fresh connection when ``retry``: never for commands whose
        answers are counted)."""
        headers = {"Authorization": f"Bearer {self.token}"} if auth and self.token else {}
        data = None
        if body is not None:
            data = body if isinstance(body, bytes) else json.dumps(body).encode()
            headers["Content-Type"] = "application/json"
        for attempt in (0, 1):
            if self._conn is None:
                self._conn = http.client.HTTPConnection("127.0.0.1", self.port,
                                                        timeout=self.timeout)
            try:
                self._conn.request(method, path, body=data, headers=headers)
                r = self._conn.getresponse()
                raw = r.read()
            except (OSError, http.client.HTTPException):
                self.close()
                if attempt or not retry:
                    raise
                continue
            try:
                return r.status, json.loads(raw) if raw else None
            except ValueError:
                return r.status, None
        raise AssertionError("unreachable")

    def get(self, path: str) -> tuple[int, Any]:
        return self.request("GET", path)

    def post(self, path: str, body: Any = None, *, retry: bool = False) -> tuple[int, Any]:
        return self.request("POST", path, body, retry=retry)

    def state(self) -> dict[str, Any]:
        code, doc = self.get("/status")
        if code != 200 or not isinstance(doc, dict):
            raise DaemonRunError(f"GET /status answered {code}: {doc}")
        return doc


class Poller(threading.Thread):
    """GET ``path`` every ``period`` s on a connection of its own; ``samples`` holds
    ``(sent, answered, status, keep(answer))`` (status None when no answer came). Bounded
    by ``max_samples``; a late answer skips periods rather than bursting."""

    def __init__(self, port: int, path: str, period: float, token: str | None = None,
                 keep: Callable[[Any], Any] | None = None, max_samples: int = 200_000) -> None:
        super().__init__(name=f"poll {path}", daemon=True)
        self.port, self.path, self.period, self.token = port, path, period, token
        self.keep, self.max_samples = keep, max_samples
        self.samples: list[tuple[float, float, int | None, Any]] = []
        self._halt = threading.Event()

    def run(self) -> None:
        api = Api(self.port, self.token, timeout=10.0)
        due = time.monotonic()
        try:
            while not self._halt.is_set() and len(self.samples) < self.max_samples:
                t0 = time.monotonic()
                try:
                    code, doc = api.request("GET", self.path, auth=self.token is not None)
                    kept = self.keep(doc) if self.keep is not None else None
                except (OSError, http.client.HTTPException):
                    code, kept = None, None
                except (KeyError, TypeError):
                    kept = None
                self.samples.append((t0, time.monotonic(), code, kept))
                due += self.period
                now = time.monotonic()
                if due < now:
                    due = now
                self._halt.wait(due - now)
        finally:
            api.close()

    def stop(self) -> None:
        self._halt.set()
        self.join(timeout=15.0)

    def first(self, pred: Callable[[tuple[float, float, int | None, Any]], bool],
              after: float) -> tuple[float, float, int | None, Any] | None:
        for s in list(self.samples):
            if s[0] >= after and pred(s):
                return s
        return None


def _state_of(doc: Any) -> str | None:
    return doc["safety"]["state"] if isinstance(doc, dict) else None


def raw_request(port: int, path: str, body: bytes,
                headers: dict[str, str] | None = None) -> tuple[bytes, int]:
    """A whole POST request as bytes (head and ``body``) and the head's length. Built before
    the timing starts: copying 47 MB holds this process's GIL for tens of milliseconds,
    which would stall the /health poller thread and count against the daemon."""
    head = (f"POST {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n"
            f"Content-Type: application/json\r\nContent-Length: {len(body)}\r\n"
            + "".join(f"{k}: {v}\r\n" for k, v in (headers or {}).items())
            + "Connection: close\r\n\r\n").encode()
    return head + body, len(head)


def send_raw(port: int, request: bytes, head_len: int,
             timeout: float = 60.0) -> dict[str, Any]:
    """Send a :func:`raw_request` over a raw socket and time the answer: seconds from the
    first byte sent to the status line (or to the connection's close), how much of the body
    went out before it, and the status (None when the connection closed without one)."""
    data = memoryview(request)
    s = socket.create_connection(("127.0.0.1", port), timeout=5.0)
    s.setblocking(False)
    sent, answer, t_answer, reset = 0, b"", None, False
    t0 = time.monotonic()
    try:
        while time.monotonic() - t0 < timeout:
            r, w, _ = select.select([s], [s] if sent < len(data) and not reset else [], [], 0.5)
            if r:
                try:
                    chunk = s.recv(65536)
                except BlockingIOError:
                    continue
                except OSError:
                    chunk = b""
                if t_answer is None:
                    t_answer = time.monotonic()
                if not chunk:
                    break
                answer += chunk
                if b"\r\n\r\n" in answer or len(answer) > 65536:
                    break
            elif w:
                try:
                    sent += s.send(data[sent:sent + 262_144])
                except BlockingIOError:
                    pass
                except OSError:  # the server closed: the answer may be waiting to be read
                    reset = True
            elif reset:
                break
    finally:
        s.close()
    status = None
    first = answer.split(b"\r\n", 1)[0].split()
    if len(first) >= 2 and first[1].isdigit():
        status = int(first[1])
    head_text, _, rest = answer.partition(b"\r\n\r\n")
    return {"status": status, "t_sent": t0,
            "answer_s": None if t_answer is None else t_answer - t0,
            "body_bytes": len(data) - head_len, "body_bytes_sent": max(0, sent - head_len),
            "closed_before_body_sent": sent < len(data),
            "answer": rest[:300].decode(errors="replace")}


def large_targets_body(min_bytes: int = LARGE_BODY_BYTES) -> bytes:
    """Issue 30's body: ``{"targets": [{"name": "sN", "p_OM": [0.01, 0, 0]}, ...]}`` of at
    least ``min_bytes``."""
    parts, size, k = [], 0, 0
    while size < min_bytes:
        item = b'{"name": "s%d", "p_OM": [0.01, 0, 0]}' % k
        parts.append(item)
        size += len(item) + 2
        k += 1
    return b'{"targets": [' + b", ".join(parts) + b"]}"


def faults_since(doc: dict[str, Any], t: float) -> list[dict[str, Any]]:
    """The transitions to FAULT in ``doc``'s history at or after ``t`` (daemon clock =
    this machine's CLOCK_MONOTONIC)."""
    return [tr for tr in doc["safety"].get("history", [])
            if tr.get("to") == "FAULT" and tr.get("time") is not None and tr["time"] >= t]


def last_period(api: Api, samples: int = 5) -> tuple[float, float] | None:
    """When the control loop's last period began (this machine's monotonic clock), while it
    is stopped or dead: ``GET /poses`` gives the status record's age (``tcp.age_s``, the
    daemon's now minus the loop's clock at its last period), so each answer bounds the
    instant between ``sent - age`` and ``answered - age``; the bounds of ``samples``
    answers are intersected. Returns (earliest, latest), or None without an answer.

    This is the loop's own time, not the moment the daemon's heartbeat watch noticed the
    period: that watch may run late on a busy machine, and its ``last_silence.quiet_s``
    then counts from its late look."""
    lo, hi = -float("inf"), float("inf")
    for _ in range(samples):
        t0 = time.monotonic()
        code, doc = api.get("/poses")
        t1 = time.monotonic()
        try:
            age = float(doc["tcp"]["age_s"])
        except (KeyError, TypeError, ValueError):
            continue
        if code == 200:
            lo, hi = max(lo, t0 - age), min(hi, t1 - age)
        time.sleep(0.01)
    return (lo, hi) if lo <= hi and lo > -float("inf") else None


def _since(t_event: float | None, bounds: tuple[float, float] | None
           ) -> tuple[float | None, float | None]:
    """(ms from the middle of ``bounds`` to ``t_event``, half the bounds' width in ms)."""
    if t_event is None or bounds is None:
        return None, None
    mid = 0.5 * (bounds[0] + bounds[1])
    return _ms(t_event - mid), _ms(0.5 * (bounds[1] - bounds[0]))


def ensure_ready(api: Api, timeout: float = 15.0) -> dict[str, Any]:
    """Bring the cell to READY (reset a latch, abort an interrupted procedure); the last
    status, DaemonRunError when it does not get there in time."""
    t0 = time.monotonic()
    doc = api.state()
    while time.monotonic() - t0 < timeout:
        sa = doc["safety"]
        if sa["state"] in ("FAULT", "ESTOP"):
            api.post("/reset")
        elif sa["state"] in ("RUNNING", "PAUSED") or sa.get("interrupted"):
            api.post("/procedure/abort")
        elif sa["state"] == "READY":
            return doc
        time.sleep(0.2)
        doc = api.state()
    raise DaemonRunError(f"not READY within {timeout:g} s: {doc['safety']['state']} "
                      f"({doc['safety'].get('reasons')})")


def _ms(s: float | None) -> float | None:
    return None if s is None else round(s * 1e3, 3)


# == scenarios ===============================================================================
def scenario_daemon_kill(work: Path, token_file: Path, token: str, rounds: int,
                         rng: random.Random, targets: list[dict[str, Any]]) -> dict[str, Any]:
    """Rounds of: start the daemon, send commands back to back, SIGKILL it at a random
    moment; all on one audit log. Every acknowledged command must be audited."""
    audit = work / "audit_kill.jsonl"
    out: dict[str, Any] = {"rounds": [], "audit_log": str(audit)}
    for k in range(rounds):
        port = free_port()
        cfg = write_daemon_config(work / "daemon_kill.toml", port=port, tokens_file=token_file,
                                  audit_log=audit)
        log = work / f"daemon_kill_{k}.log"
        offset = audit.stat().st_size if audit.exists() else 0
        d = Daemon(cfg, log, port, token)
        rnd: dict[str, Any] = {"round": k}
        try:
            d.start()
            rnd["ready_s"] = round(d.wait_ready(), 2)
            if d.start_faults:
                rnd["faults_while_starting"] = d.start_faults
            api = Api(port, token)
            kill_after = rng.uniform(0.3, 1.5)
            acks: list[str] = []
            refused: Counter[int] = Counter()
            unanswered = 0
            timer = threading.Timer(kill_after, d.kill_now)
            t0 = time.monotonic()
            timer.start()
            try:
                for i in range(BURST_MAX_COMMANDS):
                    path, body = BURST[i % len(BURST)]
                    try:
                        code, _ = api.post(path, {"targets": targets} if body == "targets"
                                           else body)
                    except (OSError, http.client.HTTPException):
                        unanswered += 1
                        break
                    if code == 200:
                        acks.append(path)
                    else:
                        refused[code] += 1
                    if time.monotonic() - t0 > BURST_MAX_S:
                        break
            finally:
                timer.cancel()
                api.close()
                d.kill()
            rnd.update(kill_after_s=round(kill_after, 3), acknowledged=len(acks),
                       refused={str(c): n for c, n in sorted(refused.items())},
                       unanswered=unanswered)
            # the restart of the next round reads this log; what it says about the audit
            # log (an incomplete record, a torn line) is kept
        except Exception as exc:
            rnd["error"] = f"{type(exc).__name__}: {exc}"
            d.close()
            out["rounds"].append(rnd)
            _log(f"  round {k + 1}: {rnd['error']}")
            continue
        end = audit.stat().st_size if audit.exists() else 0
        raw = b""
        if end < offset:  # rotated during the round: the round began in the previous file
            rnd["rotated"] = True
            with open(audit.with_name(audit.name + ".1"), "rb") as f:
                f.seek(offset)
                raw = f.read()
            offset = 0
        with open(audit, "rb") as f:
            f.seek(offset)
            raw += f.read(end - offset)
        records, torn = parse_audit(raw.decode("utf-8", "replace"))
        m = match_acks(acks, audited_commands(records))
        rnd.update(records=len(records), torn_lines=torn, missing=len(m["missing"]),
                   missing_detail=m["missing"][:10],
                   intents_without_outcome=len(unfinished_intents(records)))
        out["rounds"].append(rnd)
        _log(f"  round {k + 1}/{rounds}: killed after {kill_after:.2f} s, "
             f"{len(acks)} acknowledged, {len(m['missing'])} missing from the audit log")
    # what the restarts said about the audit log (e.g. incomplete records after a crash)
    notes = []
    for k in range(rounds):
        try:
            for line in (work / f"daemon_kill_{k}.log").read_text(errors="replace").splitlines():
                low = line.lower()
                if "audit" in low and any(w in low for w in ("incomplete", "torn", "partial",
                                                             "no outcome", "intent")):
                    notes.append(f"round {k}: {line.strip()}")
        except OSError:
            pass
    done = [r for r in out["rounds"] if "error" not in r]
    out.update(acknowledged=sum(r["acknowledged"] for r in done),
               missing=sum(r["missing"] for r in done),
               rounds_done=len(done), rounds_planned=rounds,
               torn_lines=sum(r["torn_lines"] for r in done),
               intents_without_outcome=sum(r["intents_without_outcome"] for r in done),
               restart_audit_messages=notes[:20])
    out["met"] = bool(done) and out["missing"] == 0
    return out


def scenario_control_kill(d: Daemon, api: Api) -> dict[str, Any]:
    """SIGKILL of the control process: time to FAULT (daemon's transition time and as seen
    by a fast /status poll) and to a 503 from /health."""
    ensure_ready(api)
    cpid = d.control_pid()
    # /status costs the daemon's event loop several ms an answer: polled faster, it would
    # starve the supervisor task this scenario measures. The daemon's own transition time
    # is the figure; the polls say when a client saw it.
    hp = Poller(d.port, "/health", 0.005, keep=lambda doc: (doc or {}).get("reason"))
    sp = Poller(d.port, "/status", 0.020, token=d.token, keep=_state_of)
    hp.start()
    sp.start()
    try:
        time.sleep(0.3)
        t_kill = time.monotonic()
        os.kill(cpid, signal.SIGKILL)
        deadline = t_kill + 5.0
        while time.monotonic() < deadline:
            if (sp.first(lambda s: s[3] == "FAULT", t_kill)
                    and hp.first(lambda s: s[2] == 503, t_kill)):
                break
            time.sleep(0.01)
    finally:
        hp.stop()
        sp.stop()
    doc = api.state()
    trs = faults_since(doc, t_kill)
    seen = sp.first(lambda s: s[3] == "FAULT", t_kill)
    h503 = hp.first(lambda s: s[2] == 503, t_kill)
    after_last, plus_minus = _since(trs[0]["time"] if trs else None, last_period(api))
    return {"control_pid": cpid,
            "fault_ms": _ms(trs[0]["time"] - t_kill) if trs else None,
            "fault_after_last_period_ms": after_last,
            "last_period_uncertainty_ms": plus_minus,
            "fault_reason": f"{trs[0]['who']}: {trs[0]['reason']}" if trs else None,
            "fault_seen_by_poll_ms": _ms(seen[1] - t_kill) if seen else None,
            "health_503_ms": _ms(h503[1] - t_kill) if h503 else None,
            "health_reason": h503[3] if h503 else None,
            # the last "ok" to a /health request sent after the kill (None: there was none)
            "health_last_200_ms": _ms(max((x[1] for x in hp.samples
                                           if x[0] >= t_kill and x[2] == 200),
                                          default=t_kill) - t_kill) or None,
            "state_after": doc["safety"]["state"],
            "met": bool(trs) and h503 is not None}


def scenario_control_stop(d: Daemon, api: Api, lateness: float, stop_s: float,
                          watch_s: float) -> dict[str, Any]:
    """SIGSTOP of the control process for ``stop_s``: FAULT latency from the loop's last
    period and from the SIGSTOP, /health while stopped, then SIGCONT and a reset."""
    out: dict[str, Any] = {"max_period_lateness_s": lateness, "stop_s": stop_s}
    # before the stop: does the loop fault by itself with these settings on this machine?
    t_watch = time.monotonic()
    self_faults: list[dict[str, Any]] = []
    while time.monotonic() - t_watch < watch_s:
        doc = api.state()
        for tr in faults_since(doc, t_watch):
            if tr not in self_faults:
                self_faults.append(tr)
        if doc["safety"]["state"] in ("FAULT", "ESTOP"):
            api.post("/reset")
        time.sleep(0.05)
    out["watched_before_stop_s"] = watch_s
    out["faults_by_itself"] = len(self_faults)
    out["faults_by_itself_reasons"] = [f"{t['who']}: {t['reason']}" for t in self_faults[:10]]
    try:
        before = ensure_ready(api)
        out["ready_before_stop"] = True
    except DaemonRunError as exc:
        out["ready_before_stop"] = False
        out["not_ready_reason"] = str(exc)
        before = api.state()
    trip_before = before["control_loop"].get("last_silence")
    cpid = d.control_pid()
    hp = Poller(d.port, "/health", 0.005, keep=lambda doc: (doc or {}).get("reason"))
    hp.start()
    t_stop = t_cont = None
    period_bounds = None
    try:
        time.sleep(0.3)
        t_stop = time.monotonic()
        os.kill(cpid, signal.SIGSTOP)
        time.sleep(min(0.5, stop_s / 2))
        period_bounds = last_period(api)
        while time.monotonic() - t_stop < stop_s:
            time.sleep(0.02)
    finally:
        if t_stop is not None:
            os.kill(cpid, signal.SIGCONT)
            t_cont = time.monotonic()
        hp.stop()
    doc = api.state()
    trs = faults_since(doc, t_stop)
    trip = doc["control_loop"].get("last_silence")
    fresh_trip = trip if trip and trip != trip_before else None
    h503 = hp.first(lambda s: s[2] == 503, t_stop)
    during = [s for s in hp.samples if h503 is not None and h503[1] <= s[1] <= t_cont]
    # the stall's own detection: its cause (the first per source is kept with its time),
    # also when the loop faulted by itself just before the signal and no transition to
    # FAULT followed the stall (a busy machine stalls the loop now and then)
    stall = [c for c in doc["safety"].get("reasons", [])
             if c.get("source") == "deadline:stalled" and (c.get("time") or 0.0) >= t_stop]
    t_detect = (stall[0]["time"] if stall else trs[0]["time"] if trs else None)
    if trs and trs[0].get("who") != "deadline:stalled":
        out["first_fault_not_the_stall"] = f"{trs[0]['who']}: {trs[0]['reason']}"
    after_last, plus_minus = _since(t_detect, period_bounds)
    out.update(
        fault_after_stop_ms=_ms(t_detect - t_stop) if t_detect is not None else None,
        fault_reason=(f"deadline:stalled: {stall[0]['reason']}" if stall
                      else f"{trs[0]['who']}: {trs[0]['reason']}" if trs else None),
        # from the loop's own last period (its status record's clock, via /poses)
        fault_after_last_period_ms=after_last,
        last_period_uncertainty_ms=plus_minus,
        last_period_before_stop_ms=None if period_bounds is None
        else _ms(t_stop - 0.5 * (period_bounds[0] + period_bounds[1])),
        # the daemon's own figure: silence since its heartbeat watch last saw a period
        daemon_quiet_at_fault_ms=_ms(fresh_trip["quiet_s"]) if fresh_trip else None,
        health_503_ms=_ms(h503[1] - t_stop) if h503 else None,
        # the last "ok" to a /health request sent after the SIGSTOP, before the SIGCONT
        health_last_200_ms=_ms(max((x[1] for x in hp.samples
                                    if x[0] >= t_stop and x[1] <= t_cont and x[2] == 200),
                                   default=t_stop) - t_stop) or None,
        health_reason=h503[3] if h503 else None,
        health_answers_while_stopped=len(during),
        health_ok_while_stopped=sum(1 for s in during if s[2] == 200),
        health_starved=h503 is not None and all(s[2] != 200 for s in during))
    # after SIGCONT: the loop has read the stop the daemon wrote while it was stopped
    time.sleep(0.3)
    doc = api.state()
    loop = doc["control_loop"]
    out["loop_stopped_after_cont"] = bool(loop.get("latched"))
    out["loop_stop_reason"] = loop.get("stop_reason")
    code, answer = api.post("/reset")
    t_reset = time.monotonic()
    out["reset_status"] = code
    if code != 200:
        out["reset_answer"] = answer
    ready = None
    while time.monotonic() - t_reset < 5.0:
        if api.state()["safety"]["state"] == "READY":
            ready = time.monotonic() - t_reset
            break
        time.sleep(0.02)
    out["ready_after_reset_ms"] = _ms(ready)
    latency = out["fault_after_last_period_ms"]
    if latency is None and out["fault_after_stop_ms"] is not None:
        latency = out["fault_after_stop_ms"]
    out["fault_latency_ms"] = latency
    out["met_20ms"] = latency is not None and latency <= STOP_FAULT_TARGET_S * 1e3
    return out


def _large_body_once(d: Daemon, api: Api, request: tuple[bytes, int],
                     poll_s: float) -> dict[str, Any]:
    """One large POST while /health is polled every ``poll_s``: 1 s of polling before it
    (the machine's own longest gap, for comparison), the POST, 0.5 s after."""
    hp = Poller(d.port, "/health", poll_s)
    hp.start()
    try:
        tb = time.monotonic()
        time.sleep(1.0)
        r = send_raw(d.port, *request)
        t0 = r["t_sent"]
        t1 = time.monotonic()
        time.sleep(0.5)
        t2 = time.monotonic()
    finally:
        hp.stop()
    answers = [s[1] for s in hp.samples if s[2] is not None]
    gaps = answer_gaps(answers, t0, t2)
    base = answer_gaps(answers, tb + 0.1, t0)
    inside = sorted(x for x in answers if t0 <= x <= t2)
    line = [tb + 0.1, *sorted(x for x in answers if tb + 0.1 <= x <= t2)]
    doc = api.state()
    fl = faults_since(doc, t0 - 0.05)
    worst = max(range(len(gaps)), key=gaps.__getitem__) if gaps else None
    return {"status": r["status"], "answer_ms": _ms(r["answer_s"]),
            "body_bytes": r["body_bytes"],
            "body_bytes_sent_before_answer": r["body_bytes_sent"],
            "closed_before_body_sent": r["closed_before_body_sent"],
            "answer": r["answer"], "send_s": round(t1 - t0, 3),
            "health_polls": len(inside),
            "health_not_200": sum(1 for s in hp.samples if t0 <= s[1] <= t2 and s[2] != 200),
            "health_gap_max_ms": _ms(gaps[worst]) if worst is not None else None,
            # where the longest gap ended, s after the POST began
            "health_gap_max_at_s": None if worst is None else round(
                ([*inside, t2][worst]) - t0, 3),
            "baseline_gap_max_ms": _ms(max(base)) if base else None,
            # the chart's timeline, the second before the POST included: answer time from
            # the POST (s) and the gap before it (ms)
            "health_timeline": [[round(a - t0, 4), round((a - b) * 1e3, 2)]
                                for b, a in zip(line, line[1:], strict=False)],
            "fault_latched": bool(fl),
            "fault_reasons": [f"{t['who']}: {t['reason']}" for t in fl[:5]],
            "state_after": doc["safety"]["state"]}


def scenario_bodies(d: Daemon, api: Api, audit: Path, poll_s: float,
                    reps: int = 3) -> dict[str, Any]:
    """The 47 MB body without and with a token, ``reps`` times each, while /health is
    polled; then bodies nested too deep and not UTF-8 (400, audited)."""
    body = large_targets_body()
    out: dict[str, Any] = {"large_body_bytes": len(body), "reps": reps}
    ensure_ready(api)
    for key, headers in (("large_no_token", {}),
                         ("large_with_token", {"Authorization": f"Bearer {d.token}"})):
        runs = []
        request = raw_request(d.port, "/targets", body, headers)
        for k in range(reps):
            r = _large_body_once(d, api, request, poll_s)
            runs.append(r)
            _log(f"  {key} {k + 1}/{reps}: {r['status']} after {r['answer_ms']} ms, longest "
                 f"/health gap {r['health_gap_max_ms']} ms at {r['health_gap_max_at_s']} s "
                 f"(in the 0.9 s before: {r['baseline_gap_max_ms']} ms), FAULT latched: "
                 f"{r['fault_latched']}")
            if r["fault_latched"]:
                ensure_ready(api)
        gaps = sorted(r["health_gap_max_ms"] for r in runs if r["health_gap_max_ms"] is not None)
        answers = [r["answer_ms"] for r in runs if r["answer_ms"] is not None]
        base = [r["baseline_gap_max_ms"] for r in runs if r["baseline_gap_max_ms"] is not None]
        worst = max(runs, key=lambda r: r["health_gap_max_ms"] or 0.0)
        out[key] = {"status": sorted({r["status"] for r in runs}, key=str),
                    "answer_ms_max": max(answers) if answers else None,
                    "health_gap_max_ms": gaps[-1] if gaps else None,
                    "health_gap_median_ms": gaps[len(gaps) // 2] if gaps else None,
                    "baseline_gap_max_ms": max(base) if base else None,
                    "fault_latched": any(r["fault_latched"] for r in runs),
                    "health_not_200": sum(r["health_not_200"] for r in runs),
                    "health_timeline": worst["health_timeline"],
                    "runs": [{k: v for k, v in r.items() if k != "health_timeline"}
                             for r in runs]}
    nested = b'{"targets": ' + b"[" * 1000 + b"]" * 1000 + b"}"
    bad_utf8 = b'{"targets": [{"name": "s\xff\xfe", "p_OM": [0.01, 0, 0]}]}'
    for key, raw in (("nested_1000", nested), ("invalid_utf8", bad_utf8)):
        offset = audit.stat().st_size if audit.exists() else 0
        code, answer = api.request("POST", "/targets", raw, retry=False)
        time.sleep(0.2)
        with open(audit, "rb") as f:
            f.seek(offset)
            records, _ = parse_audit(f.read().decode("utf-8", "replace"))
        audited = any(p == "/targets" and s == code for p, s in audited_commands(records))
        out[key] = {"status": code, "detail": (answer or {}).get("detail"),
                    "audited": audited}
        _log(f"  {key}: {code}, audited: {audited}")
    no, yes = out["large_no_token"], out["large_with_token"]
    out["refused_in_time"] = bool(no["status"] == [401] and no["answer_ms_max"] is not None
                                  and no["answer_ms_max"] < REFUSE_TARGET_S * 1e3)
    out["health_gap_met"] = bool(
        no["health_gap_max_ms"] is not None and yes["health_gap_max_ms"] is not None
        and max(no["health_gap_max_ms"], yes["health_gap_max_ms"])
        < HEALTH_GAP_TARGET_S * 1e3)
    # on a machine whose own gaps (no body) pass the target, the gap figure says little
    out["baseline_over_target"] = any(
        (x["baseline_gap_max_ms"] or 0.0) >= HEALTH_GAP_TARGET_S * 1e3 for x in (no, yes))
    out["met"] = bool(
        out["refused_in_time"] and out["health_gap_met"]
        and not no["fault_latched"] and not yes["fault_latched"]
        and yes["status"] == [413]
        and all(out[k]["status"] == 400 and out[k]["audited"]
                for k in ("nested_1000", "invalid_utf8")))
    return out


def scenario_reset_cycle(api: Api, targets: list[dict[str, Any]],
                         cycles: int) -> dict[str, Any]:
    """Procedure moving, /estop, /reset: READY within READY_WITHIN_S and held READY_HOLD_S,
    then /procedure/resume; ``cycles`` times."""
    ensure_ready(api)
    code, answer = api.post("/targets", {"targets": targets})
    if code != 200:
        raise DaemonRunError(f"POST /targets answered {code}: {answer}")
    rows: list[dict[str, Any]] = []
    resume_codes: Counter[int] = Counter()
    for k in range(cycles):
        row: dict[str, Any] = {"cycle": k}
        t_cycle = time.monotonic()
        doc = api.state()
        sa = doc["safety"]
        if sa["state"] != "RUNNING":
            if sa["state"] != "READY":
                try:
                    doc = ensure_ready(api, 5.0)
                except DaemonRunError as exc:
                    row["error"] = str(exc)
                    rows.append(row)
                    continue
            action = "resume" if doc["safety"].get("interrupted") else "start"
            code, answer = api.post(f"/procedure/{action}")
            row["began"] = f"{action} {code}"
            if code != 200:
                row["error"] = f"POST /procedure/{action}: {code} {answer}"
                rows.append(row)
                continue
        m0 = int(doc["control_loop"].get("motion_commands", 0))
        moved = None
        while time.monotonic() - t_cycle < 8.0:
            d2 = api.state()
            if int(d2["control_loop"].get("motion_commands", 0)) > m0 + 5:
                moved = time.monotonic() - t_cycle
                break
            if d2["safety"]["state"] != "RUNNING":
                break
            time.sleep(0.02)
        row["moved_ms"] = _ms(moved)
        row["estop"] = api.post("/estop", {"reason": "fault campaign reset cycle"})[0]
        code, answer = api.post("/reset")
        t_reset = time.monotonic()
        row["reset"] = code
        if code != 200:
            row["reset_answer"] = answer
        ready = None
        while time.monotonic() - t_reset < 3.0:
            d3 = api.state()
            if d3["safety"]["state"] == "READY":
                ready = time.monotonic() - t_reset
                break
            time.sleep(0.02)
        row["ready_ms"] = _ms(ready)
        held = None
        if ready is not None:
            held = True
            t_ready = time.monotonic()
            while time.monotonic() - t_ready < READY_HOLD_S:
                d4 = api.state()
                if d4["safety"]["state"] != "READY":
                    held = False
                    row["left_ready_for"] = d4["safety"]["state"]
                    row["reasons"] = [f"{c['source']}: {c['reason']}"
                                      for c in d4["safety"].get("reasons", [])][:3]
                    break
                time.sleep(0.05)
        else:
            d3 = api.state()
            row["state"] = d3["safety"]["state"]
            row["reasons"] = [f"{c['source']}: {c['reason']}"
                              for c in d3["safety"].get("reasons", [])][:3]
        row["held"] = held
        row["ok"] = bool(code == 200 and ready is not None and ready <= READY_WITHIN_S
                         and held)
        if row["ok"]:
            rc, ra = api.post("/procedure/resume")
            row["resume"] = rc
            resume_codes[rc] += 1
            if rc != 200:
                row["resume_answer"] = ra
        rows.append(row)
        if (k + 1) % 10 == 0 or not row["ok"]:
            _log(f"  cycle {k + 1}/{cycles}: " + ("READY and held" if row["ok"] else
                                                  f"NOT ok: {row}"))
    try:
        api.post("/procedure/abort")
    except (OSError, http.client.HTTPException):
        pass
    ready_ms = sorted(r["ready_ms"] for r in rows if r.get("ready_ms") is not None)
    ok = sum(1 for r in rows if r.get("ok"))
    return {"cycles": cycles, "ok": ok,
            "moved": sum(1 for r in rows if r.get("moved_ms") is not None),
            "ready_ms_median": ready_ms[len(ready_ms) // 2] if ready_ms else None,
            "ready_ms_max": ready_ms[-1] if ready_ms else None,
            "resume_status": {str(c): n for c, n in sorted(resume_codes.items())},
            "failures": [r for r in rows if not r.get("ok")][:10],
            "rows": rows, "met": ok == cycles}


def scenario_soak(d: Daemon, seconds: float, poll_hz: float, every_s: float,
                  warmup_s: float) -> dict[str, Any]:
    """GET /status at ``poll_hz`` for ``seconds`` while the RSS of the daemon and the
    control process is sampled every ``every_s``."""
    cpid = d.control_pid()
    sp = Poller(d.port, "/status", 1.0 / poll_hz, token=d.token, keep=_state_of,
                max_samples=int(seconds * poll_hz * 1.2) + 100)
    series: list[list[float | None]] = []
    t0 = time.monotonic()
    sp.start()
    try:
        last_note = t0
        while time.monotonic() - t0 < seconds:
            t = time.monotonic() - t0
            series.append([round(t, 2), rss_mib(d.pid), rss_mib(cpid)])
            if time.monotonic() - last_note >= 30.0:
                last_note = time.monotonic()
                _log(f"  soak {t:.0f}/{seconds:g} s: daemon {series[-1][1]:.0f} MiB, "
                     f"control {series[-1][2] or 0:.0f} MiB")
            if not d.alive():
                break
            time.sleep(max(0.0, every_s - (time.monotonic() - t0 - t)))
        series.append([round(time.monotonic() - t0, 2), rss_mib(d.pid), rss_mib(cpid)])
    finally:
        sp.stop()
    lat = sorted(s[1] - s[0] for s in sp.samples if s[2] == 200)
    states = Counter(s[3] for s in sp.samples if s[2] == 200)
    ok = [r for r in series if r[1] is not None]
    trend = rss_trend([r[0] for r in ok], [r[1] for r in ok], warmup_s)
    ctl = [r for r in series if r[2] is not None]
    ctl_trend = rss_trend([r[0] for r in ctl], [r[2] for r in ctl], warmup_s)
    return {"seconds": seconds, "polls": len(sp.samples),
            "polls_per_s": round(len(sp.samples) / max(seconds, 1e-9), 1),
            "poll_errors": sum(1 for s in sp.samples if s[2] != 200),
            "poll_ms_median": _ms(lat[len(lat) // 2]) if lat else None,
            "poll_ms_p99": _ms(lat[int(0.99 * (len(lat) - 1))]) if lat else None,
            "poll_ms_max": _ms(lat[-1]) if lat else None,
            "states": dict(states), "held_ready": set(states) == {"READY"},
            "daemon_alive": d.alive(),
            "rss_series": series, "rss_daemon": trend, "rss_control": ctl_trend,
            "met": trend["bounded"] if trend["conclusive"] else None}


# == the campaign ============================================================================
def _run(doc: dict[str, Any], name: str, fn: Callable[[], dict[str, Any]]) -> None:
    _log(f"{name}...")
    t0 = time.monotonic()
    try:
        doc["scenarios"][name] = fn()
    except Exception as exc:  # one scenario's failure is a finding, not the end of the run
        doc["scenarios"][name] = {"error": f"{type(exc).__name__}: {exc}", "met": False}
        _log(f"  {name} failed: {type(exc).__name__}: {exc}")
    doc["scenarios"][name]["wall_s"] = round(time.monotonic() - t0, 1)


def _targets_of(config: Path) -> list[dict[str, Any]]:
    """The simulated cell's suture targets, as ``oralnavd --demo`` registers them."""
    from oralnav.config.daemon import load_config

    cfg = load_config(config)
    if cfg.cell is None:
        raise DaemonRunError(f"{config}: no [cell] sim_cell, so no targets")
    return [{"name": n, "p_OM": [float(x) for x in p]} for n, p in cfg.cell.targets_OM.items()]


class _Terminated(BaseException):
    pass


def main(out: Path, quick: bool = False, seed: int = 0) -> dict[str, Any]:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    work = out / "faults_run"
    work.mkdir(exist_ok=True)
    p = params(quick)
    rng = random.Random(seed)
    from oralnav.bench.machine import describe

    doc: dict[str, Any] = {
        "bench": "faults", "quick": quick, "seed": seed,
        "date": datetime.now(UTC).isoformat(timespec="seconds"),
        "machine": describe(load_average=[round(x, 2) for x in os.getloadavg()]),
        "params": p, "work": str(work), "scenarios": {}}

    def on_term(signum: int, frame: object) -> None:
        raise _Terminated  # unwinds through every finally: the daemons are stopped

    previous = signal.signal(signal.SIGTERM, on_term) \
        if threading.current_thread() is threading.main_thread() else None
    t_all = time.monotonic()
    try:
        token_file = work / "tokens.toml"
        token = write_tokens(token_file)
        # daemon A: the simulation's settings; soak, bodies, reset cycle, stop, kill
        audit_a = work / "audit_a.jsonl"
        port = free_port()
        cfg_a = write_daemon_config(work / "daemon_a.toml", port=port, tokens_file=token_file,
                                    audit_log=audit_a)
        targets = _targets_of(cfg_a)
        a = Daemon(cfg_a, work / "daemon_a.log", port, token)
        with a:
            _log(f"starting oralnavd ({cfg_a})...")
            try:
                doc["daemon_a_ready_s"] = round(a.wait_ready(), 1)
                doc["daemon_a_faults_while_starting"] = a.start_faults
                ok = True
            except DaemonRunError as exc:
                ok = False
                for name in ("soak", "bodies", "reset_cycle", "control_stop_sim",
                             "control_kill"):
                    doc["scenarios"][name] = {"error": str(exc), "met": False}
                _log(f"  {exc}")
            if ok:
                api = Api(port, token)
                try:
                    _run(doc, "soak", lambda: scenario_soak(
                        a, p["soak_s"], p["soak_poll_hz"], p["rss_every_s"], p["warmup_s"]))
                    _run(doc, "bodies", lambda: scenario_bodies(a, api, audit_a,
                                                                p["health_poll_s"]))
                    _run(doc, "reset_cycle", lambda: scenario_reset_cycle(
                        api, targets, p["reset_cycles"]))
                    _run(doc, "control_stop_sim", lambda: scenario_control_stop(
                        a, api, _lateness(cfg_a), p["stop_s"], 0.0))
                    _run(doc, "control_kill", lambda: scenario_control_kill(a, api))
                finally:
                    api.close()
        # daemon B: the robot PC's max_period_lateness
        port = free_port()
        cfg_b = write_daemon_config(work / "daemon_b.toml", port=port, tokens_file=token_file,
                                    audit_log=work / "audit_b.jsonl",
                                    lateness=ROBOT_PC_LATENESS)
        b = Daemon(cfg_b, work / "daemon_b.log", port, token)
        with b:
            _log(f"starting oralnavd with max_period_lateness = {ROBOT_PC_LATENESS} s...")

            api_b = Api(port, token)
            try:
                def robot_pc() -> dict[str, Any]:
                    doc["daemon_b_ready_s"] = round(b.wait_ready(), 1)
                    r = scenario_control_stop(b, api_b, ROBOT_PC_LATENESS, p["stop_s"],
                                              p["robot_pc_watch_s"])
                    # faults of the loop by itself while the daemon came up (reset to go on)
                    return {"faults_while_starting": b.start_faults, **r}

                _run(doc, "control_stop_robot_pc", robot_pc)
                _run(doc, "control_kill_robot_pc", lambda: scenario_control_kill(b, api_b))
            finally:
                api_b.close()
        _run(doc, "daemon_kill", lambda: scenario_daemon_kill(
            work, token_file, token, p["kill_rounds"], rng, targets))
    except _Terminated:
        doc["interrupted"] = "SIGTERM"
        _log("SIGTERM: daemons stopped, writing what was measured")
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    doc["wall_s"] = round(time.monotonic() - t_all, 1)
    doc["targets"] = targets_summary(doc)
    try:
        doc["charts"] = charts(doc, out)
    except Exception as exc:  # a chart is no reason to lose the figures
        doc["charts"] = []
        doc["chart_error"] = f"{type(exc).__name__}: {exc}"
    (out / "faults.json").write_text(json.dumps(doc, indent=1) + "\n")
    _log(f"wrote {out / 'faults.json'} in {doc['wall_s']:.0f} s: " + ", ".join(
        f"{k} {'met' if v['met'] else 'NOT met' if v['met'] is False else 'undecided'}"
        for k, v in doc["targets"].items()))
    return doc


def _lateness(config: Path) -> float:
    import tomllib

    return float(tomllib.loads(config.read_text()).get("safety", {})
                 .get("max_period_lateness", ROBOT_PC_LATENESS))


def targets_summary(doc: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Each scenario's headline figure beside its target, and whether it was met."""
    s = doc["scenarios"]

    def get(name: str) -> dict[str, Any]:
        return s.get(name) or {"error": "not run"}

    dk, ck, bo = get("daemon_kill"), get("control_kill"), get("bodies")
    ckr = get("control_kill_robot_pc")
    sim, pc = get("control_stop_sim"), get("control_stop_robot_pc")
    rc, so = get("reset_cycle"), get("soak")
    no = bo.get("large_no_token", {})
    return {
        "daemon_kill": {"acknowledged": dk.get("acknowledged"), "missing": dk.get("missing"),
                        "rounds": dk.get("rounds_done"), "target": "0 missing",
                        "met": dk.get("met", False)},
        "control_kill": {"fault_ms": ck.get("fault_ms"), "health_503_ms": ck.get("health_503_ms"),
                         "fault_ms_robot_pc": ckr.get("fault_ms"),
                         "fault_after_last_period_ms_robot_pc":
                             ckr.get("fault_after_last_period_ms"),
                         "health_503_ms_robot_pc": ckr.get("health_503_ms"),
                         "target": "FAULT and /health 503",
                         "met": bool(ck.get("met") and ckr.get("met"))},
        "control_stop_robot_pc": {
            "fault_after_last_period_ms": pc.get("fault_after_last_period_ms"),
            "last_period_uncertainty_ms": pc.get("last_period_uncertainty_ms"),
            "daemon_quiet_at_fault_ms": pc.get("daemon_quiet_at_fault_ms"),
            "fault_after_stop_ms": pc.get("fault_after_stop_ms"),
            "faults_by_itself": pc.get("faults_by_itself"),
            "health_starved": pc.get("health_starved"),
            "target": f"<= {STOP_FAULT_TARGET_S * 1e3:g} ms", "met": pc.get("met_20ms", False)},
        "control_stop_sim": {
            "fault_after_last_period_ms": sim.get("fault_after_last_period_ms"),
            "limit_ms": None if sim.get("max_period_lateness_s") is None
            else 2.0 + sim["max_period_lateness_s"] * 1e3,
            "health_starved": sim.get("health_starved"),
            "target": "period + max_period_lateness (the sim's tolerance), /health 503",
            "met": bool(sim.get("health_starved")) and sim.get("reset_status") == 200},
        "bodies": {"no_token_status": no.get("status"),
                   "no_token_answer_ms_max": no.get("answer_ms_max"),
                   "health_gap_max_ms": no.get("health_gap_max_ms"),
                   "health_gap_max_ms_with_token": bo.get("large_with_token", {})
                   .get("health_gap_max_ms"),
                   "baseline_over_target": bo.get("baseline_over_target"),
                   "fault_latched": no.get("fault_latched"),
                   "with_token_status": bo.get("large_with_token", {}).get("status"),
                   "target": f"401 < {REFUSE_TARGET_S * 1e3:g} ms, /health gap < "
                             f"{HEALTH_GAP_TARGET_S * 1e3:g} ms, no FAULT; 413; 400 audited",
                   "met": bo.get("met", False)},
        "reset_cycle": {"ok": rc.get("ok"), "cycles": rc.get("cycles"),
                        "target": f"READY within {READY_WITHIN_S:g} s and held "
                                  f"{READY_HOLD_S:g} s in every cycle",
                        "met": rc.get("met", False)},
        "soak": {"seconds": so.get("seconds"),
                 "warmup_slope_mib_per_min": (so.get("rss_daemon") or {}).get("warmup", {})
                 .get("slope_mib_per_min"),
                 "after_warmup_slope_mib_per_min": (so.get("rss_daemon") or {})
                 .get("after_warmup", {}).get("slope_mib_per_min"),
                 "target": f"<= {RSS_BOUND_MIB_PER_MIN:g} MiB/min after warm-up",
                 "met": so.get("met")}}


def summary(doc: dict[str, Any]) -> dict[str, Any]:
    """The one JSON object ``oralnav bench faults --json`` prints."""
    return {"bench": "faults", "quick": doc["quick"], "date": doc["date"],
            "wall_s": doc.get("wall_s"), "targets": doc["targets"],
            "errors": {k: v["error"] for k, v in doc["scenarios"].items() if "error" in v},
            "json": str(Path(doc["work"]).parent / "faults.json"), "charts": doc["charts"]}


def charts(doc: dict[str, Any], out: Path) -> list[str]:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = doc["scenarios"]
    fig, (ax1, ax2, ax3) = plt.subplots(1, 3, figsize=(16, 4.8))
    soak = s.get("soak", {})
    series = soak.get("rss_series") or []
    if series:
        t = [r[0] / 60.0 for r in series]
        ax1.plot(t, [r[1] for r in series], label="oralnavd")
        ax1.plot(t, [r[2] for r in series], label="control process")
        ax1.axvline(doc["params"]["warmup_s"] / 60.0, color="k", ls=":", lw=0.8,
                    label="end of warm-up")
        slope = soak["rss_daemon"]["after_warmup"].get("slope_mib_per_min")
        ax1.set_title("RSS at 50 status polls/s" + (f": {slope:+.2f} MiB/min after warm-up"
                                                     if slope is not None else "")
                      + ("" if soak["rss_daemon"].get("conclusive") else "\n(too short a "
                         "soak to judge: 10 min after warm-up needed)"), fontsize=10)
        ax1.legend(fontsize=8)
    else:
        ax1.set_title(f"soak: {soak.get('error', 'not run')}"[:60])
    ax1.set_xlabel("minutes since the daemon was READY")
    ax1.set_ylabel("RSS (MiB)")
    bodies = s.get("bodies", {})
    for key, label in (("large_no_token", "47 MB without token"),
                       ("large_with_token", "47 MB with token")):
        tl = bodies.get(key, {}).get("health_timeline") or []
        if tl:
            ms = bodies[key].get("answer_ms_max")
            ax2.plot([x for x, _ in tl], [g for _, g in tl], marker=".", lw=0.8,
                     label=f"{label}: {'/'.join(map(str, bodies[key]['status']))} within "
                           + ("no answer" if ms is None else f"{ms:.0f} ms")
                           + f" (worst of {bodies.get('reps', 1)}; machine's own longest "
                             f"gap {bodies[key].get('baseline_gap_max_ms') or 0:.0f} ms)")
    ax2.axhline(HEALTH_GAP_TARGET_S * 1e3, color="r", ls="--", lw=0.8, label="100 ms target")
    ax2.axvline(0.0, color="k", ls=":", lw=0.8)
    top = max([g for key in ("large_no_token", "large_with_token")
               for _, g in bodies.get(key, {}).get("health_timeline") or []], default=0.0)
    ax2.set_ylim(0.0, max(170.0, 1.3 * top))
    ax2.set_xlabel("s since the POST began")
    ax2.set_ylabel("gap between /health answers (ms)")
    ax2.set_title("GET /health (every 10 ms) while a 47 MB body arrives")
    ax2.legend(fontsize=7, loc="upper right")
    bars = [("KILL\nsim", s.get("control_kill", {}).get("fault_ms")),
            ("KILL\nrobot PC", s.get("control_kill_robot_pc", {}).get("fault_ms")),
            ("STOP sim\nlast period",
             s.get("control_stop_sim", {}).get("fault_after_last_period_ms")),
            ("STOP sim\nsignal", s.get("control_stop_sim", {}).get("fault_after_stop_ms")),
            ("STOP PC\nlast period",
             s.get("control_stop_robot_pc", {}).get("fault_after_last_period_ms")),
            ("STOP PC\nsignal", s.get("control_stop_robot_pc", {}).get("fault_after_stop_ms"))]
    xs = range(len(bars))
    ax3.bar(xs, [v or 0.0 for _, v in bars], color=["C0", "C0", "C1", "C1", "C2", "C2"])
    for x, (_, v) in zip(xs, bars, strict=True):
        ax3.text(x, (v or 0.0) + 1, "n/a" if v is None else f"{v:.1f}", ha="center",
                 fontsize=8)
    ax3.axhline(STOP_FAULT_TARGET_S * 1e3, color="r", ls="--", lw=0.8,
                label="20 ms target (robot PC)")
    ax3.axhline(30.0, color="grey", ls=":", lw=0.8, label="dVRK watchdog, 30 ms")
    ax3.set_xticks(list(xs), [n for n, _ in bars], fontsize=7)
    ax3.set_ylabel("time to FAULT (ms), from the signal or the loop's last period")
    ax3.set_title("control process SIGKILLed / SIGSTOPped")
    ax3.legend(fontsize=8)
    fig.suptitle(f"oralnav fault campaign ({'quick' if doc['quick'] else 'full'}, "
                 f"{doc['date'][:10]}, {doc['machine']['cpus']} cores)")
    fig.tight_layout()
    fig.savefig(out / "faults.png", dpi=110)
    plt.close(fig)
    return ["faults.png"]
