"""Aravis's simulated GigE Vision camera (``arv-fake-gv-camera-0.8``, Debian's
``aravis-tools``) as a real process on loopback: the protocol peer of the ``aravis`` camera
backend, for its tests and for running the daemon on a hardware cell without cameras.

A camera's control port (GVCP, UDP 3956) binds its address, so each fake needs a loopback
address of its own: as root, :func:`loopback_address` adds a fresh ``127.83.x.y/32`` alias to
``lo`` and removes it afterwards (no two fakes, nor two runs, ever share a port); without
root only ``127.0.0.1`` is used, so one fake at a time.
"""

from __future__ import annotations

import contextlib
import os
import random
import shutil
import signal
import socket
import subprocess
import tempfile
import time
from collections.abc import Callable, Iterator

from oralnav.sim.errors import SimError

__all__ = ["FAKE", "GVCP_PORT", "FakeGvCamera", "NoLoopbackAddress", "loopback_address",
           "running_fakes"]

FAKE = "arv-fake-gv-camera-0.8"
GVCP_PORT = 3956


class NoLoopbackAddress(SimError, RuntimeError):
    """No loopback address with a free GVCP port can be had (not root, 127.0.0.1 taken)."""


def _udp_bound(address: str, port: int) -> bool:
    """Whether a UDP socket of this network namespace is bound to address:port."""
    want = f"{socket.inet_aton(address)[::-1].hex().upper()}:{port:04X}"
    for table in ("/proc/net/udp",):
        try:
            with open(table) as fh:
                next(fh, None)
                if any(line.split()[1] == want for line in fh if len(line.split()) > 1):
                    return True
        except OSError:
            return False
    return False


def _can_alias() -> bool:
    return os.geteuid() == 0 and shutil.which("ip") is not None


@contextlib.contextmanager
def loopback_address() -> Iterator[str]:
    """A loopback address whose GVCP port is free, for one fake camera.

    As root: a fresh ``127.83.x.y/32`` alias on ``lo``, removed on exit. Otherwise
    ``127.0.0.1`` when its port 3956 is free; else :class:`NoLoopbackAddress`.
    """
    if _can_alias():
        for _ in range(20):
            address = f"127.83.{random.randint(1, 254)}.{random.randint(1, 254)}"
            if _udp_bound(address, GVCP_PORT):
                continue
            done = subprocess.run(["ip", "addr", "add", f"{address}/32", "dev", "lo"],
                                  capture_output=True, text=True)
            if done.returncode == 0:
                try:
                    yield address
                finally:
                    subprocess.run(["ip", "addr", "del", f"{address}/32", "dev", "lo"],
                                   capture_output=True)
                return
            if "File exists" not in done.stderr:
                break  # not allowed (no CAP_NET_ADMIN): fall back to 127.0.0.1
    if _udp_bound("127.0.0.1", GVCP_PORT):
        raise NoLoopbackAddress("UDP 127.0.0.1:3956 is taken (by another fake camera?) and "
                                "adding a loopback alias for this one needs root")
    yield "127.0.0.1"


class FakeGvCamera:
    """One ``arv-fake-gv-camera-0.8`` process: a GigE Vision camera on ``address``."""

    def __init__(self, address: str, serial: str, lost_ratio: int = 0) -> None:
        self.address = address
        self.serial = serial
        self.lost_ratio = lost_ratio
        self._proc: subprocess.Popen | None = None
        self._log = tempfile.TemporaryFile()

    @property
    def device_id(self) -> str:
        return f"Aravis-Fake-{self.serial}"

    @property
    def running(self) -> bool:
        return self._proc is not None and self._proc.poll() is None

    def start(self, timeout: float = 5.0) -> None:
        if self.running:
            raise RuntimeError(f"the fake camera on {self.address} is already running")
        command = [FAKE, "-i", self.address, "-s", self.serial]
        if self.lost_ratio:
            command += ["-r", str(self.lost_ratio)]
        self._proc = subprocess.Popen(command, stdin=subprocess.DEVNULL,
                                      stdout=subprocess.DEVNULL, stderr=self._log)
        deadline = time.monotonic() + timeout
        while not _udp_bound(self.address, GVCP_PORT):
            if self._proc.poll() is not None or time.monotonic() > deadline:
                self.kill()
                self._log.seek(0)
                raise RuntimeError(f"{FAKE} on {self.address} did not come up: "
                                   f"{self._log.read().decode(errors='replace').strip()}")
            time.sleep(0.01)

    def kill(self) -> None:
        """SIGKILL: the camera vanishes as if unplugged."""
        proc, self._proc = self._proc, None
        if proc is not None and proc.poll() is None:
            proc.send_signal(signal.SIGKILL)
        if proc is not None:
            proc.wait(5)

    def close(self) -> None:
        self.kill()
        self._log.close()


@contextlib.contextmanager
def running_fakes() -> Iterator[Callable[..., FakeGvCamera]]:
    """``make(lost_ratio=0) -> FakeGvCamera``: started fakes, each on its own address,
    all killed (and their addresses removed) on exit."""
    with contextlib.ExitStack() as stack:
        def make(lost_ratio: int = 0) -> FakeGvCamera:
            address = stack.enter_context(loopback_address())
            fake = FakeGvCamera(address, f"OX{random.randrange(16**6):06X}", lost_ratio)
            stack.callback(fake.close)
            fake.start()
            fakes.append(fake)
            return fake

        fakes: list[FakeGvCamera] = []
        yield make
