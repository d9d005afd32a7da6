"""A null-modem cable between two pseudo-terminals: bytes written to one end's device are
read at the other's, as between two USB serial adapters wired together. Lets a serial
protocol stack (a Modbus RTU master and slave, say) talk over real tty devices in tests.
"""

from __future__ import annotations

import os
import select
import threading
import tty

__all__ = ["NullModem"]


class NullModem:
    """Two pty pairs bridged by a thread; :attr:`ends` are the two device paths."""

    def __init__(self) -> None:
        self._fds: list[tuple[int, int]] = []
        for _ in range(2):
            master, slave = os.openpty()
            tty.setraw(slave)
            self._fds.append((master, slave))
        self.ends = (os.ttyname(self._fds[0][1]), os.ttyname(self._fds[1][1]))
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._pump, name="null-modem", daemon=True)
        self._thread.start()

    def _pump(self) -> None:
        a, b = self._fds[0][0], self._fds[1][0]
        peer = {a: b, b: a}
        while not self._stop.is_set():
            ready, _, _ = select.select([a, b], [], [], 0.05)
            for fd in ready:
                try:
                    data = os.read(fd, 4096)
                except OSError:  # an end closed: nothing to carry
                    continue
                if data:
                    os.write(peer[fd], data)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        for master, slave in self._fds:
            os.close(master)
            os.close(slave)

    def __enter__(self) -> NullModem:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
