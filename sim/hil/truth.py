"""The hardware-in-the-loop cell's ground truth over HTTP on loopback, for the daemon's TRE
observer (``daemon/sim_cell.py`` ``PeerTruth``) and for benchmarks.

``GET /truth?t=<s>`` answers the truth of the newest capture at or before ``t`` (s, host
monotonic clock; without ``t``: the newest) as JSON: ``time``, ``T_B_tcp`` and ``T_B_E``
(4x4 nested lists, m), ``q`` (rad) and ``targets_B`` (name -> [x, y, z], m). 404 with
``{"error": ...}`` when no capture answers; 400 for a ``t`` that is not a number. Only
127.0.0.1 is bound: it is a test harness, never part of a real cell.
"""

from __future__ import annotations

import json
import math
import threading
from collections.abc import Callable
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any
from urllib.parse import parse_qs, urlparse

import numpy as np

from oralnav.sim.errors import SimError

__all__ = ["TruthServer"]


def _jsonable(v: Any) -> Any:
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, dict):
        return {k: _jsonable(x) for k, x in v.items()}
    return v


class TruthServer:
    """Serves ``truth_at(t)`` (see the module docstring) on ``127.0.0.1:port`` (0: any free
    port) from a thread; a context manager. :attr:`url` is the endpoint."""

    def __init__(self, truth_at: Callable[[float | None], dict[str, Any]],
                 port: int = 0) -> None:
        truth = truth_at

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self) -> None:  # noqa: N802 (the http.server name)
                url = urlparse(self.path)
                if url.path != "/truth":
                    return self._send(404, {"error": f"no {url.path}; GET /truth?t=<s>"})
                raw = parse_qs(url.query).get("t", [None])[0]
                try:
                    t = None if raw is None else float(raw)
                    if t is not None and not math.isfinite(t):
                        raise ValueError(raw)
                except ValueError:
                    return self._send(400, {"error": f"t must be a finite number of seconds, "
                                                    f"got {raw!r}"})
                try:
                    self._send(200, _jsonable(truth(t)))
                except SimError as exc:
                    self._send(404, {"error": str(exc)})

            def _send(self, code: int, doc: dict[str, Any]) -> None:
                body = json.dumps(doc).encode()
                self.send_response(code)
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            def log_message(self, *args: Any) -> None:  # quiet: a harness, polled often
                pass

        self._server = ThreadingHTTPServer(("127.0.0.1", port), Handler)
        self._thread: threading.Thread | None = None

    @property
    def url(self) -> str:
        host, port = self._server.server_address[:2]
        return f"http://{host}:{port}/truth"

    def start(self) -> None:
        self._thread = threading.Thread(target=self._server.serve_forever,
                                        name="truth-server", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._server.shutdown()
        self._server.server_close()
        if self._thread is not None:
            self._thread.join()

    def __enter__(self) -> TruthServer:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
