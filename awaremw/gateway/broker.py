"""Embedded MQTT broker (amqtt 0.12) for the demo: nothing to install or run.

When the gateway gets no ``--mqtt`` URL it starts this in-process broker on a
free loopback port and says where (``mqtt://127.0.0.1:PORT``). amqtt speaks
MQTT 3.1.1 only (the gateway falls back to it), allows anonymous clients here
and keeps retained messages in memory for the life of the process.
"""

from __future__ import annotations

import logging
import socket
from typing import Any

from amqtt.broker import Broker

log = logging.getLogger(__name__)


class EmbeddedBroker:
    """``async with EmbeddedBroker() as b: b.url``; ``port=0`` picks a free port."""

    def __init__(self, host: str = "127.0.0.1", port: int = 0) -> None:
        self.host = host
        self.port = port
        self._broker: Broker | None = None

    @property
    def url(self) -> str:
        return f"mqtt://{self.host}:{self.port}"

    async def start(self) -> None:
        amqtt_log = logging.getLogger("amqtt")
        if amqtt_log.level == logging.NOTSET:
            # amqtt warns about every client it refuses (the gateway's MQTT 5 probe
            # included) and about harmless protocol quirks: keep its errors only.
            amqtt_log.setLevel(logging.ERROR)
        config: dict[str, Any] = {
            "listeners": {"default": {"type": "tcp", "bind": f"{self.host}:{self.port}"}},
            # Only what the demo needs: no $SYS publisher, no per-packet logging.
            "plugins": {
                "amqtt.plugins.authentication.AnonymousAuthPlugin": {"allow_anonymous": True},
            },
        }
        broker = Broker(config)
        await broker.start()
        self._broker = broker
        if self.port == 0:
            self.port = _bound_port(broker)
        log.info("embedded MQTT broker listening on %s", self.url)

    async def stop(self) -> None:
        if self._broker is not None:
            broker, self._broker = self._broker, None
            await broker.shutdown()

    async def __aenter__(self) -> EmbeddedBroker:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()


def _bound_port(broker: Broker) -> int:
    server = broker._servers["default"].instance  # amqtt keeps the asyncio.Server here
    for sock in server.sockets:
        name = sock.getsockname()
        if sock.family in (socket.AF_INET, socket.AF_INET6):
            return int(name[1])
    raise RuntimeError("embedded broker has no bound TCP socket")
