"""The embedded broker delivers what Mosquitto delivers (issue 21, item 1).

One client script runs against each broker with the same retained definitions;
what every subscriber received is compared with the other broker and with what
MQTT 3.1.1 prescribes: a subscriber gets the retained messages of its own
filters only, once each, with retain 1; messages queued for an away persistent
session come with retain 0 and no retained ones around them.
"""

from __future__ import annotations

import asyncio
import uuid
from dataclasses import dataclass
from pathlib import Path

import aiomqtt
from mosquitto import Mosquitto, mosquitto_fixture  # noqa: F401

from awaremw.gateway.broker import EmbeddedBroker
from awaremw.gateway.mqtt import MqttSettings

DEFS = {
    "aware/def/group/1": b'{"conditions": [{"attr": "temperature", "op": ">", "value": 45}]}',
    "aware/def/group/2": b'{"conditions": [{"attr": "light", "op": "<", "value": 10}]}',
    "aware/def/channel/1": b'{"attr": "temperature", "group_type": 1, "period_s": 2.0, '
    b'"agg": "avg"}',
}

Got = list[tuple[str, bytes, bool]]  # topic, payload, retain flag


@dataclass(frozen=True)
class Accounts:
    """The URLs each role uses on one broker."""

    operator: str  # writes definitions and commands, reads aware/#
    gateway: str  # writes aware/gateway/#
    viewer: str  # reads aware/gateway/#


def _client(url: str, ident: str, *, clean: bool = True) -> aiomqtt.Client:
    s = MqttSettings.from_url(url)
    return aiomqtt.Client(
        s.host, s.port, username=s.username, password=s.password, identifier=ident,
        protocol=aiomqtt.ProtocolVersion.V311, clean_session=clean,
    )  # fmt: skip


async def _until(client: aiomqtt.Client, got: Got, last: str) -> Got:
    """Collect what ``client`` receives until a message on ``last`` (the marker)."""
    async with asyncio.timeout(10):
        async for m in client.messages:
            payload = m.payload if isinstance(m.payload, bytes) else b""
            got.append((m.topic.value, payload, bool(m.retain)))
            if m.topic.value == last:
                return got
    raise AssertionError("unreachable")


async def client_script(acc: Accounts) -> dict[str, Got]:
    """The same steps on any broker; returns what each subscriber received."""
    run = uuid.uuid4().hex[:8]
    out: dict[str, Got] = {}
    async with _client(acc.operator, f"op-{run}") as op:
        for topic, payload in DEFS.items():
            await op.publish(topic, payload, qos=1, retain=True)
        # A persistent session that will be away while a command is published.
        async with _client(acc.operator, f"away-{run}", clean=False) as away:
            await away.subscribe("aware/cmd/#", qos=1)
        # A first definitions subscriber holds aware/def/# in the broker, as the
        # gateway does, while the others connect.
        async with _client(acc.operator, f"defs1-{run}") as defs1:
            await defs1.subscribe("aware/def/#", qos=1)
            await op.publish("aware/def/end", b"", qos=1)  # marker: not retained
            out["defs_first"] = await _until(defs1, [], "aware/def/end")
            # The unrelated subscriber: nothing/at/all, then the marker's topic.
            async with _client(acc.viewer, f"unrelated-{run}") as unrelated:
                await unrelated.subscribe("nothing/at/all", qos=1)
                await unrelated.subscribe("aware/gateway/end", qos=1)
                async with _client(acc.gateway, f"gw-{run}") as gw:
                    await gw.publish("aware/gateway/end", b"", qos=1)
                out["unrelated"] = await _until(unrelated, [], "aware/gateway/end")
            async with _client(acc.operator, f"defs2-{run}") as defs2:
                await defs2.subscribe("aware/def/#", qos=1)
                await op.publish("aware/def/end", b"", qos=1)
                out["defs_second"] = await _until(defs2, [], "aware/def/end")
            await op.publish("aware/cmd/led", b'{"target": "all"}', qos=1)
            async with _client(acc.operator, f"away-{run}", clean=False) as away:
                await op.publish("aware/cmd/end", b"", qos=1)
                out["away"] = await _until(away, [], "aware/cmd/end")
    return out


def _expected() -> dict[str, Got]:
    defs = sorted((t, p, True) for t, p in DEFS.items())
    return {
        "defs_first": [*defs, ("aware/def/end", b"", False)],
        "unrelated": [("aware/gateway/end", b"", False)],
        "defs_second": [*defs, ("aware/def/end", b"", False)],
        "away": [("aware/cmd/led", b'{"target": "all"}', False), ("aware/cmd/end", b"", False)],
    }


def _normalised(got: dict[str, Got]) -> dict[str, Got]:
    """Retained messages may come in any order; everything else is compared as it came."""
    return {k: sorted(m for m in v if m[2]) + [m for m in v if not m[2]] for k, v in got.items()}


async def test_embedded_and_mosquitto_deliver_the_same(mosquitto: Mosquitto) -> None:
    got_mosquitto = await client_script(
        Accounts(mosquitto.url("operator"), mosquitto.url("gateway"), mosquitto.url("viewer"))
    )
    async with EmbeddedBroker() as broker:
        got_embedded = await client_script(Accounts(broker.url, broker.url, broker.url))
    assert _normalised(got_mosquitto) == _expected()
    assert _normalised(got_embedded) == _expected()


async def test_retained_restored_from_the_state_directory_follow_the_same_rules(
    tmp_path: Path,
) -> None:
    """Definitions put back from retained.sqlite at start are delivered as those
    published in this run: to their own filters only, once each."""
    state = tmp_path / "b"
    async with EmbeddedBroker(state_dir=state) as broker, _client(broker.url, "op") as op:
        for topic, payload in DEFS.items():
            await op.publish(topic, payload, qos=1, retain=True)
    async with EmbeddedBroker(state_dir=state) as broker:
        got = await client_script(Accounts(broker.url, broker.url, broker.url))
    assert _normalised(got) == _expected()
