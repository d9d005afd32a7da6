"""A simulated serial e-stop / foot-pedal box on a pseudo-terminal, the protocol peer of the
``serial`` safety-input backend (``oralnav.drivers.io.serial_link``).

The box owns the master side of a pty pair and streams ``$OSIO`` status lines at ``rate_hz``
from a thread; the driver opens the slave side with pyserial exactly as it opens a USB serial
adapter. ``link`` (optional) is a symlink the box keeps pointing at its current slave, as
udev keeps ``/dev/serial/by-id/...`` pointing at a replugged adapter, so a driver configured
with the link finds the box again after :meth:`SerialBox.unplug` and :meth:`SerialBox.plug`.

Faults to inject: :meth:`silence` (the box stops writing), :meth:`garble` (raw bytes on the
line), :meth:`repeat` (the box repeats its last line: a stuck sequence number) and
:meth:`unplug` (the pty closes; the slave path vanishes).
"""

from __future__ import annotations

import os
import threading
import tty
from pathlib import Path

from oralnav.drivers.io.serial_link import encode_line

__all__ = ["SerialBox"]


class SerialBox:
    """A fake safety-input box; a context manager that plugs it in and unplugs it.

    Args:
        rate_hz: status lines per second.
        link: a symlink kept pointing at the current pty slave (None: use :attr:`path`).
    """

    def __init__(self, rate_hz: float = 100.0, link: str | Path | None = None) -> None:
        if not rate_hz > 0:
            raise ValueError(f"rate_hz must be > 0, got {rate_hz!r}")
        self.period = 1.0 / float(rate_hz)
        self.link = Path(link) if link is not None else None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._master: int | None = None
        self._slave: int | None = None
        self.path: str | None = None  # the current slave device
        self.estop = False
        self.pedal = False
        self.seq = 0
        self.silent = False
        self.stuck = False
        self.sent = 0

    # -- plugging ------------------------------------------------------------------------
    def plug(self) -> str:
        """Open a fresh pty pair and start streaming; returns the path a driver opens."""
        if self._thread is not None:
            raise RuntimeError("the box is already plugged in")
        master, slave = os.openpty()
        tty.setraw(slave)  # no echo, no line editing: bytes pass as a USB adapter passes them
        # a full queue (no reader yet) drops lines, as a UART overruns; never blocks the box
        os.set_blocking(master, False)
        self._master, self._slave = master, slave
        self.path = os.ttyname(slave)
        if self.link is not None:
            tmp = self.link.with_name(self.link.name + ".new")
            tmp.unlink(missing_ok=True)
            tmp.symlink_to(self.path)
            os.replace(tmp, self.link)
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="serial-box", daemon=True)
        self._thread.start()
        return str(self.link) if self.link is not None else self.path

    def unplug(self) -> None:
        """Stop and close the pty (the driver's reads fail; the slave path vanishes)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
            self._thread = None
        for fd in (self._master, self._slave):
            if fd is not None:
                os.close(fd)
        self._master = self._slave = None
        if self.link is not None:
            self.link.unlink(missing_ok=True)

    def __enter__(self) -> SerialBox:
        self.plug()
        return self

    def __exit__(self, *exc: object) -> None:
        self.unplug()

    # -- what the box reports ------------------------------------------------------------
    def press_estop(self) -> None:
        self.estop = True

    def release_estop(self) -> None:
        self.estop = False

    def press_pedal(self) -> None:
        self.pedal = True

    def release_pedal(self) -> None:
        self.pedal = False

    def silence(self) -> None:
        """Stop writing (the box hangs; the port stays open)."""
        self.silent = True

    def repeat(self) -> None:
        """Keep writing the last line unchanged (a stuck sequence number)."""
        self.stuck = True

    def resume(self) -> None:
        """End :meth:`silence` and :meth:`repeat`."""
        self.silent = self.stuck = False

    def garble(self, data: bytes) -> None:
        """Write raw bytes on the line now, between status lines."""
        with self._lock:
            if self._master is None:
                raise RuntimeError("the box is unplugged")
            os.write(self._master, data)

    def _run(self) -> None:
        while not self._stop.wait(self.period):
            if self.silent:
                continue
            with self._lock:
                if not self.stuck:
                    self.seq = (self.seq + 1) % 65536
                try:
                    os.write(self._master, encode_line(self.seq, self.estop, self.pedal))
                except BlockingIOError:
                    continue
                except OSError:
                    return
                self.sent += 1
