"""The lifecycle every driver shares: ``async start()``, idempotent ``async close()``, and
``async with`` doing both (a failed ``start()`` closes what it had opened).

:class:`LifecycleState` is the bookkeeping behind it, one copy for every backend: not started
-> starting -> running, and closed from any of them, for good (a closed driver is not
restarted: build a new one). Use before ``start()`` or after ``close()`` is refused with a
:class:`~oralnav.drivers.errors.DriverIOError` naming the device and the phase.
"""

from __future__ import annotations

import enum
from types import TracebackType
from typing import Self

from .errors import DriverInitError, DriverIOError

__all__ = ["AsyncLifecycle", "LifecycleState", "Phase"]


class Phase(enum.Enum):
    """Where a driver is in its life; the value is how refusals name it."""

    NEW = "not started"
    STARTING = "starting"
    RUNNING = "running"
    CLOSED = "closed"


class LifecycleState:
    """One driver's start/close state machine: NEW -> STARTING -> RUNNING; CLOSED from any.

    Not locked: a backend whose threads share it reads and changes it under its own lock,
    together with the device state that goes with each phase. One attribute read is atomic,
    so a lock-free check (a ``read()``'s first look) sees one phase or the other.
    """

    __slots__ = ("phase",)

    def __init__(self) -> None:
        self.phase = Phase.NEW

    @property
    def running(self) -> bool:
        """``start()`` has finished and ``close()`` has not come."""
        return self.phase is Phase.RUNNING

    @property
    def closed(self) -> bool:
        return self.phase is Phase.CLOSED

    def begin_start(self, refusal: str, *, after_close: str | None = None) -> None:
        """NEW -> STARTING; ``DriverInitError(refusal)`` for a second ``start()`` or one
        after ``close()`` (``refusal`` names the device, as in ``"camera 'left': start()
        called twice or after close()"``; ``after_close``, when given, is the message for
        the second case)."""
        if self.phase is Phase.CLOSED and after_close is not None:
            raise DriverInitError(after_close)
        if self.phase is not Phase.NEW:
            raise DriverInitError(refusal)
        self.phase = Phase.STARTING

    def abort_start(self) -> None:
        """STARTING -> NEW after a ``start()`` that failed: the device may be started again
        (the control process retries an arm it could not reach). A ``close()`` that came
        meanwhile keeps it CLOSED."""
        if self.phase is Phase.STARTING:
            self.phase = Phase.NEW

    def finish_start(self) -> bool:
        """STARTING -> RUNNING. False when ``close()`` came while starting: the phase stays
        CLOSED, and the caller releases what its ``start()`` opened."""
        if self.phase is Phase.CLOSED:
            return False
        self.phase = Phase.RUNNING
        return True

    def start(self, refusal: str) -> None:
        """NEW -> RUNNING at once, for a ``start()`` with nothing to wait for; refused as
        :meth:`begin_start`."""
        self.begin_start(refusal)
        self.phase = Phase.RUNNING

    def close(self) -> bool:
        """-> CLOSED. True on the first call only: ``close()`` is idempotent, and only the
        first one releases the device."""
        if self.phase is Phase.CLOSED:
            return False
        self.phase = Phase.CLOSED
        return True

    def refusal(self) -> str | None:
        """Why the device cannot be used now: ``"not started"`` (starting included),
        ``"closed"``, or None while running."""
        if self.phase is Phase.RUNNING:
            return None
        return Phase.CLOSED.value if self.phase is Phase.CLOSED else Phase.NEW.value

    def check(self, label: str, *, during: str | None = None) -> None:
        """Return while running; else ``DriverIOError`` ``"<label>: not started"`` or
        ``"<label>: closed"``, ``"<label>: closed during <during>"`` when ``during`` names
        the operation that was under way (e.g. ``"read()"``) when ``close()`` came."""
        reason = self.refusal()
        if reason is None:
            return
        if during is not None and self.phase is Phase.CLOSED:
            reason = f"closed during {during}"
        raise DriverIOError(f"{label}: {reason}")

    def __repr__(self) -> str:
        return f"LifecycleState({self.phase.name})"


class AsyncLifecycle:
    """Mixin: ``async with device:`` starts it and always closes it."""

    async def start(self) -> None:
        raise NotImplementedError

    async def close(self) -> None:
        raise NotImplementedError

    async def __aenter__(self) -> Self:
        try:
            await self.start()
        except BaseException:
            await self.close()  # release whatever a half-done start() opened
            raise
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.close()

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={getattr(self, 'name', '?')!r})"
