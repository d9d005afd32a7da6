"""The fake controller in a child process, and the command line that runs one.

``ur_rtde``'s Python constructors (``RTDEControlInterface(...)``,
``RTDEReceiveInterface(...)``) do all their network I/O while holding the GIL, so a fake
controller on threads of the *same* interpreter can never answer them. Tests therefore run
the fake with :class:`FakeURControllerProcess`, which starts a
:class:`~oralnav.sim.peers.ur.controller.FakeURController` in a child process
(``python -m oralnav.sim.peers.ur --rpc``) and forwards method calls to it over two pipes.
"""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any

from oralnav.drivers.arm.ur_protocol import DASHBOARD_PORT
from oralnav.sim.peers.ur.controller import FakeURController

__all__ = ["FakeURControllerProcess", "main"]


def _serve(recv: Connection, send: Connection) -> None:
    """Child process: build a controller from the first message, then answer method calls
    until told to stop (or until the parent goes away)."""
    try:
        kwargs = recv.recv()
        ctrl = FakeURController(**kwargs)
        ctrl.start()
    except BaseException as exc:
        send.send(("err", exc))
        return
    send.send(("ok", None))
    try:
        while True:
            try:
                name, args, kw = recv.recv()
            except (EOFError, OSError):
                break
            if name == "__stop__":
                break
            try:
                if name.startswith("_") or not callable(getattr(ctrl, name, None)):
                    raise AttributeError(f"FakeURController has no method {name!r}")
                send.send(("ok", getattr(ctrl, name)(*args, **kw)))
            except BaseException as exc:
                send.send(("err", exc))
    finally:
        ctrl.stop()
        try:
            send.send(("ok", None))
        except OSError:
            pass


class FakeURControllerProcess:
    """A :class:`FakeURController` in a child process; its public methods are called through.

    ``FakeURControllerProcess(host="127.0.0.1", **kwargs)`` takes the controller's arguments.
    ``start()`` returns once the ports listen (``OSError`` if one is taken); ``stop()`` ends
    the process. A context manager. ``fake.pose()``, ``fake.inject_protective_stop()`` ...
    run in the child and return its result (numpy arrays and records are copied back). The
    child is ``python -m oralnav.sim.peers.ur --rpc``, talking over two pipes.
    """

    def __init__(self, host: str = "127.0.0.1", *, timeout: float = 20.0,
                 **kwargs: Any) -> None:
        self.host = host
        self.timeout = float(timeout)
        self._kwargs = dict(kwargs, host=host)
        self._proc: subprocess.Popen | None = None
        self._send: Connection | None = None
        self._recv: Connection | None = None
        self._call_lock = threading.Lock()

    def start(self) -> None:
        """Start the child and wait until its controller listens (``OSError`` if a port is
        taken, ``TimeoutError`` after ``timeout`` s)."""
        if self._proc is not None:
            raise RuntimeError("FakeURControllerProcess already started")
        to_child_r, to_child_w = os.pipe()
        to_parent_r, to_parent_w = os.pipe()
        try:
            proc = subprocess.Popen(
                [sys.executable, "-m", "oralnav.sim.peers.ur", "--rpc",
                 str(to_child_r), str(to_parent_w)],
                pass_fds=(to_child_r, to_parent_w), stdin=subprocess.DEVNULL)
        finally:
            os.close(to_child_r)
            os.close(to_parent_w)
        send = Connection(to_child_w, readable=False)
        recv = Connection(to_parent_r, writable=False)
        try:
            send.send(self._kwargs)
            if not recv.poll(self.timeout):
                raise TimeoutError("fake UR controller process did not start")
            status, value = recv.recv()
            if status != "ok":
                raise value
        except BaseException:
            proc.kill()
            proc.wait()
            send.close()
            recv.close()
            raise
        self._proc, self._send, self._recv = proc, send, recv

    def stop(self) -> None:
        """End the child process. Idempotent."""
        proc, send, recv = self._proc, self._send, self._recv
        if proc is None or send is None or recv is None:
            return
        self._proc = self._send = self._recv = None
        try:
            with self._call_lock:
                send.send(("__stop__", (), {}))
                if recv.poll(10.0):
                    recv.recv()
        except (OSError, EOFError):
            pass
        try:
            proc.wait(5.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        send.close()
        recv.close()

    def __enter__(self) -> FakeURControllerProcess:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def call(self, name: str, *args: Any, **kwargs: Any) -> Any:
        """Call ``FakeURController.<name>(*args, **kwargs)`` in the child."""
        with self._call_lock:
            send, recv = self._send, self._recv
            if send is None or recv is None:
                raise RuntimeError("fake UR controller process not started")
            send.send((name, args, kwargs))
            if not recv.poll(self.timeout):
                raise TimeoutError(f"fake UR controller: {name}() did not answer")
            status, value = recv.recv()
        if status != "ok":
            raise value
        return value

    def __getattr__(self, name: str) -> Callable[..., Any]:
        if name.startswith("_"):
            raise AttributeError(name)
        if not callable(getattr(FakeURController, name, None)):
            raise AttributeError(f"FakeURController has no method {name!r}")

        def method(*args: Any, **kwargs: Any) -> Any:
            return self.call(name, *args, **kwargs)

        method.__name__ = name
        return method


def main(argv: list[str] | None = None) -> None:
    """``python -m oralnav.sim.peers.ur [--host H] [--series e|cb3]``: serve until
    interrupted."""
    import argparse

    parser = argparse.ArgumentParser(description="A fake UR controller for ur_rtde clients.")
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--series", choices=("e", "cb3"), default="e")
    parser.add_argument("--dashboard-port", type=int, default=DASHBOARD_PORT)
    parser.add_argument("--rpc", nargs=2, type=int, metavar=("READ_FD", "WRITE_FD"),
                        help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.rpc:
        # The child of FakeURControllerProcess. What it sends back (CommandRecord ...) is
        # defined in the package's modules, never in __main__, so it unpickles in the parent.
        _serve(Connection(args.rpc[0], writable=False), Connection(args.rpc[1], readable=False))
        return
    logging.basicConfig(level=logging.INFO)
    ctrl = FakeURController(args.host, series=args.series, dashboard_port=args.dashboard_port)
    ctrl.start()
    print(f"fake UR controller ({args.series}-series, {ctrl.frequency:g} Hz) on {args.host}: "
          f"RTDE {ctrl.rtde_port}, dashboard {ctrl.dashboard_port}, scripts "
          f"{', '.join(map(str, ctrl.script_ports))}; Ctrl-C stops it", flush=True)
    try:
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        pass
    finally:
        ctrl.stop()
