"""A fleet's watch over its event loop: a core or hook that raises inside a
loop callback is a local bug; the guard records it, marks the fleet failed and
lets :meth:`LoopGuard.raise_errors` re-raise it as :class:`FleetError`."""

from __future__ import annotations

import asyncio
from typing import Any


class FleetError(RuntimeError):
    """A local bug surfaced inside the fleet's event loop (a core or hook raised)."""


MAX_ERRORS = 16  # the first one is raised; a few more are kept for the log


class LoopGuard:
    """The loop's exception handler while a fleet runs (chained to the previous one)."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.errors: list[BaseException] = []
        self.failed_event = asyncio.Event()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._old_handler: Any = None
        self._closed = False

    @property
    def failed(self) -> bool:
        return self.failed_event.is_set()

    def install(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        self._old_handler = loop.get_exception_handler()
        loop.set_exception_handler(self._handle)

    def uninstall(self) -> None:
        self._closed = True
        loop = self._loop
        if loop is not None and loop.get_exception_handler() == self._handle:
            loop.set_exception_handler(self._old_handler)
        # else another fleet chained its handler on top of ours: ours stays in the
        # chain but, closed, only forwards.

    def raise_errors(self) -> None:
        if self.errors:
            e = self.errors[0]
            raise FleetError(f"fleet {self.name}: {type(e).__name__}: {e}") from e

    def _handle(self, loop: asyncio.AbstractEventLoop, ctx: dict[str, Any]) -> None:
        exc = ctx.get("exception")
        if isinstance(exc, Exception) and not self._closed:
            # A core or hook raised in a loop callback: our bug. Stop and report.
            if len(self.errors) < MAX_ERRORS:
                self.errors.append(exc)
            self.failed_event.set()
        if self._old_handler is not None:
            self._old_handler(loop, ctx)
        else:
            loop.default_exception_handler(ctx)
