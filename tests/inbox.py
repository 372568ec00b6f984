"""Inbox: what a bridge hands to the gateway (MQTT or Zenoh), awaited by count."""

from __future__ import annotations

import asyncio


class Inbox:
    """Messages ``(rel, payload, retained, topic or key)``, with an event per message."""

    def __init__(self) -> None:
        self.items: list[tuple[str, bytes, bool, str]] = []
        self.changed = asyncio.Event()

    def __call__(
        self, rel: str, payload: bytes, retained: bool, where: str, size: int | None = None
    ) -> None:
        self.items.append((rel, payload, retained, where))
        self.changed.set()

    async def wait(self, n: int, timeout: float = 10.0) -> None:
        async def loop() -> None:
            while len(self.items) < n:
                self.changed.clear()
                await self.changed.wait()

        await asyncio.wait_for(loop(), timeout)
