"""The lifecycle every driver shares: ``async start()``, idempotent ``async close()``, and
``async with`` doing both (a failed ``start()`` closes what it had opened)."""

from __future__ import annotations

from types import TracebackType
from typing import Self


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
