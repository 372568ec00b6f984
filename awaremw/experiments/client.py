"""The robot's client: an IP device that uses the WSN over MQTT.

It does what Romeo 4R's software would: define the tracking group type and
the channels (retained ``<prefix>/def/...`` messages, the scenario's
``[[groups]]`` / ``[[channels]]`` entries as they are), then listen to
``<prefix>/data/#``, ``<prefix>/groups/#`` and ``<prefix>/errors`` and hand
every record, group state and refusal to callbacks.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import aiomqtt

from awaremw.gateway.mqtt import MqttSettings
from awaremw.gateway.schema import AGG_NAMES
from awaremw.protocol.frames import DataRecord

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class Received:
    """A data record as the client got it: topic ids plus the JSON payload."""

    wall: float  # time.monotonic() at arrival
    t: float  # emulated time the gateway stamped
    record: DataRecord
    agg: str
    attr: str | None


@dataclass(frozen=True, slots=True)
class GroupSeen:
    group_type: int
    group_id: int
    state: Mapping[str, Any] | None  # None: the group is gone


def parse_data(topic: str, payload: bytes, prefix: str = "aware") -> Received | None:
    """A ``<prefix>/data/<channel>/<type>/<group>`` message, or None if malformed."""
    parts = topic.split("/")
    if len(parts) != 5 or parts[0] != prefix or parts[1] != "data":
        return None
    try:
        ch, gt, gid = (int(p) for p in parts[2:])
        doc = json.loads(payload)
        agg = str(doc.get("agg", "avg"))
        rec = DataRecord(
            ch, gt, gid, int(doc["epoch"]), AGG_NAMES.get(agg, 0), float(doc["value"]),
            int(doc["count"]), int(doc["leader"]),
        )  # fmt: skip
        attr = doc.get("attr")
        return Received(time.monotonic(), float(doc["t"]), rec, agg, None if attr is None
                        else str(attr))  # fmt: skip
    except (ValueError, KeyError, TypeError) as e:
        log.warning("malformed data message on %s: %s", topic, e)
        return None


def definition_payloads(
    groups: Mapping[int, Mapping[str, Any]], channels: Mapping[int, Mapping[str, Any]]
) -> list[tuple[str, bytes]]:
    """The robot's definitions as MQTT messages: (topic relative to the prefix, payload)."""
    out = [(f"def/group/{t}", json.dumps(b).encode()) for t, b in groups.items()]
    out += [(f"def/channel/{c}", json.dumps(b).encode()) for c, b in channels.items()]
    return out


class RobotClient:
    """Define, then listen. ``await client.ready`` waits until definitions are out."""

    def __init__(
        self,
        settings: MqttSettings,
        groups: Mapping[int, Mapping[str, Any]],
        channels: Mapping[int, Mapping[str, Any]],
        *,
        on_record: Callable[[Received], None] | None = None,
        on_group: Callable[[GroupSeen], None] | None = None,
        on_error: Callable[[str], None] | None = None,
    ) -> None:
        self.settings = settings
        self.prefix = settings.prefix
        self.groups = dict(groups)
        self.channels = dict(channels)
        self.on_record = on_record
        self.on_group = on_group
        self.on_error = on_error
        self.received: list[Received] = []
        self.errors: list[str] = []
        self.ready = asyncio.Event()
        self._stop = asyncio.Event()

    def stop(self) -> None:
        self._stop.set()

    def definitions(self) -> list[tuple[str, bytes]]:
        """What :meth:`run` publishes (retained): (topic relative to the prefix, payload)."""
        return definition_payloads(self.groups, self.channels)

    async def run(self, define: bool = True) -> None:
        s = self.settings
        async with s.client(f"awaremw-robot-{id(self):x}") as client:
            p = self.prefix
            await client.subscribe(f"{p}/data/#", qos=1)
            await client.subscribe(f"{p}/groups/#", qos=1)
            await client.subscribe(f"{p}/errors", qos=1)
            if define:
                for rel, payload in self.definitions():
                    await client.publish(f"{p}/{rel}", payload, qos=1, retain=True)
            self.ready.set()
            reader = asyncio.create_task(self._read(client))
            try:
                await self._stop.wait()
            finally:
                reader.cancel()
                with contextlib.suppress(asyncio.CancelledError, aiomqtt.MqttError):
                    await reader

    async def _read(self, client: aiomqtt.Client) -> None:
        p = self.prefix
        async for msg in client.messages:
            topic = str(msg.topic)
            payload = msg.payload if isinstance(msg.payload, bytes) else str(msg.payload).encode()
            if topic.startswith(f"{p}/data/"):
                r = parse_data(topic, payload, p)
                if r is not None:
                    self.received.append(r)
                    if self.on_record is not None:
                        self.on_record(r)
            elif topic.startswith(f"{p}/groups/"):
                parts = topic.split("/")
                with contextlib.suppress(ValueError):
                    g = GroupSeen(int(parts[2]), int(parts[3]),
                                  json.loads(payload) if payload else None)  # fmt: skip
                    if self.on_group is not None:
                        self.on_group(g)
            elif topic == f"{p}/errors":
                text = payload.decode("utf-8", "replace")
                self.errors.append(text)
                if self.on_error is not None:
                    self.on_error(text)
