"""The MQTT bridge against real brokers: Mosquitto (ACL, outage) and embedded amqtt."""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

import pytest
from inbox import Inbox
from mosquitto import (  # noqa: F401
    Collector,
    Mosquitto,
    mosquitto_fixture,
    mosquitto_tls_fixture,
    pub,
)

from awaremw.gateway.broker import EmbeddedBroker
from awaremw.gateway.events import Publish
from awaremw.gateway.mqtt import BadMqttUrl, MqttBridge, MqttSettings

pytestmark = pytest.mark.mosquitto

GROUP = '{"conditions": [{"attr": "temperature", "op": ">", "value": 45}]}'


def test_url_parsing() -> None:
    s = MqttSettings.from_url("mqtt://op%40x:p%3Aw@broker.lan:1999", prefix="p")
    assert (s.host, s.port, s.username, s.password, s.tls, s.prefix) == (
        "broker.lan",
        1999,
        "op@x",
        "p:w",
        False,
        "p",
    )
    s = MqttSettings.from_url("mqtts://h")
    assert (s.port, s.tls, s.username) == (8883, True, None)
    assert MqttSettings.from_url("mqtt://h").port == 1883
    assert "pw" not in MqttSettings.from_url("mqtt://u:pw@h:1").url
    for bad in ("http://h:1", "mqtt://:1", "mqtt://h:99999", "mqtt://h:1/x", "h:1"):
        with pytest.raises(BadMqttUrl):
            MqttSettings.from_url(bad)


@asynccontextmanager
async def running(bridge: MqttBridge) -> AsyncIterator[asyncio.Task[None]]:
    task = asyncio.create_task(bridge.run())
    try:
        await asyncio.wait_for(bridge.connected.wait(), 10)
        yield task
    finally:
        bridge.stop()
        await asyncio.wait_for(task, 10)


async def test_definitions_in_data_out_status_retained(mosquitto: Mosquitto) -> None:
    # A retained definition published before the gateway connects is replayed to it.
    assert pub(mosquitto, "operator", "aware/def/group/1", GROUP).returncode == 0
    inbox = Inbox()
    bridge = MqttBridge(MqttSettings.from_url(mosquitto.url("gateway")), inbox)
    async with Collector(mosquitto.url("viewer"), "aware/#") as viewer, running(bridge):
        assert bridge.stats.protocol == "5"
        await inbox.wait(1)
        assert inbox.items[0] == ("def/group/1", GROUP.encode(), True, "aware/def/group/1")
        # A live one arrives with retained=False.
        assert pub(mosquitto, "operator", "aware/def/channel/2", "{}").returncode == 0
        assert pub(mosquitto, "operator", "aware/cmd/blink", "{}", retain=False).returncode == 0
        await inbox.wait(3)
        assert [(r, ret) for r, _, ret, _ in inbox.items[1:]] == [
            ("def/channel/2", False),
            ("cmd/blink", False),
        ]
        bridge.publish(Publish("data/2/1/513", b'{"value": 1}'))
        bridge.publish(Publish("groups/1/513", b'{"leader": 4}', retain=True))
        await viewer.wait_for(
            lambda ms: (
                {t for t, _, _ in ms}
                >= {"aware/data/2/1/513", "aware/groups/1/513", "aware/gateway/status"}
            )
        )
        assert b"online" in viewer.payloads("aware/gateway/status")
    # Stopped cleanly: status says offline (retained for newcomers).
    async with Collector(mosquitto.url("viewer"), "aware/gateway/status") as late:
        await late.wait_for(lambda ms: len(ms) >= 1)
        assert late.messages[0] == ("aware/gateway/status", b"offline", True)


async def test_only_the_operator_may_define_or_command(mosquitto: Mosquitto) -> None:
    inbox = Inbox()
    bridge = MqttBridge(MqttSettings.from_url(mosquitto.url("gateway")), inbox)
    async with running(bridge):
        r = pub(mosquitto, "viewer", "aware/def/group/1", GROUP)
        assert b"Not authorized" in r.stderr, r
        # The gateway account writes definitions only to republish what it holds
        # (docs/gateway.md, One truth); neither it nor a viewer sends commands.
        for user in ("viewer", "gateway"):
            r = pub(mosquitto, user, "aware/cmd/reset", "{}", retain=False)
            assert b"Not authorized" in r.stderr, r
        # The broker handles one client's publishes in order and had refused the
        # others before this one was sent: once the sentinel is in, nothing else is.
        assert pub(mosquitto, "operator", "aware/def/channel/9", "{}").returncode == 0
        await inbox.wait(1)
        assert [r for r, *_ in inbox.items] == ["def/channel/9"]
    # The viewer cannot publish data either; it may read it.
    r = pub(mosquitto, "viewer", "aware/data/1/1/1", "{}", retain=False)
    assert b"Not authorized" in r.stderr


async def test_broker_outage_buffers_in_order_drops_past_bound(mosquitto: Mosquitto) -> None:
    bound = 40
    settings = MqttSettings.from_url(
        mosquitto.url("gateway"), buffer_size=bound, reconnect_min_s=0.05, reconnect_max_s=0.2
    )
    bridge = MqttBridge(settings, Inbox())
    produced: list[int] = []

    def produce(n: int) -> None:
        for _ in range(n):
            i = len(produced)
            produced.append(i)
            bridge.publish(Publish(f"data/1/1/{1 + i % 3}", json.dumps({"seq": i}).encode()))

    def seqs(c: Collector) -> list[int]:
        return [json.loads(p)["seq"] for p in c.payloads("aware/data/")]

    async with running(bridge):
        sub = Collector(mosquitto.url("viewer"), "aware/data/#")
        async with sub:
            bridge.publish(Publish("groups/1/2", b'{"leader": 2}', retain=True))
            produce(25)
            await sub.wait_for(lambda ms: len(seqs(sub)) >= 25)
            mosquitto.kill()
            await asyncio.wait_for(bridge.disconnected.wait(), 10)
            # Produced while the broker is away: 30 fit in the buffer ...
            produce(30)
            assert bridge.backlog == 30
            # ... then 20 more: the 10 oldest are dropped, counted.
            produce(20)
            assert bridge.backlog == bound and bridge.stats.dropped == 10
            # Restart with the gateway locked out until our subscriber is back, so
            # that nothing the gateway delivers can miss it.
            mosquitto.lock_out("gateway")
            mosquitto.start()
            await sub.until(lambda: sub.subscribes >= 2)
            mosquitto.let_in()
            await asyncio.wait_for(bridge.connected.wait(), 10)
            await sub.wait_for(lambda ms: len(seqs(sub)) >= 25 + bound)
            got = seqs(sub)
            assert got == list(range(25)) + list(range(35, 75)), got
            assert len(got) == len(set(got))  # none twice
            assert bridge.stats.connect_failures >= 1
            # Retained group state lost with the broker was published again.
            async with Collector(mosquitto.url("viewer"), "aware/gateway/#") as g:
                await g.wait_for(lambda ms: any(t == "aware/gateway/stats" for t, *_ in ms))
                stats = json.loads(g.payloads("aware/gateway/stats")[-1])
                assert stats["dropped"] == 10 and stats["buffer_size"] == bound
            async with Collector(mosquitto.url("viewer"), "aware/groups/#") as g:
                await g.wait_for(lambda ms: len(ms) >= 1)
                assert g.messages[0] == ("aware/groups/1/2", b'{"leader": 2}', True)


async def test_embedded_broker_speaks_311_and_bridges() -> None:
    inbox = Inbox()
    async with EmbeddedBroker() as broker:
        assert broker.port > 0 and broker.public_url.startswith("mqtt://awaremw:***@127.0.0.1:")
        # Another "gateway" leaves a retained group state, a viewer watches groups.
        other = MqttBridge(MqttSettings.from_url(broker.url, client_id="other"), Inbox())
        async with (
            Collector(broker.url, "aware/groups/#", protocol="3.1.1") as groups,
            running(other),
        ):
            other.publish(Publish("groups/1/2", b'{"leader": 2}', retain=True))
            other.publish(Publish("def/group/1", GROUP.encode(), retain=True))
            await groups.wait_for(lambda ms: len(ms) >= 1)
            bridge = MqttBridge(MqttSettings.from_url(broker.url), inbox)
            async with (
                Collector(broker.url, "aware/data/#", protocol="3.1.1") as sub,
                running(bridge),
            ):
                assert bridge.stats.protocol == "3.1.1"  # amqtt refused MQTT 5
                await inbox.wait(1)
                bridge.publish(Publish("data/1/1/7", b'{"value": 3}'))
                await sub.wait_for(lambda ms: len(ms) >= 1)
                assert sub.messages == [("aware/data/1/1/7", b'{"value": 3}', False)]
                # Only what the gateway subscribed to reached it, once (unpatched
                # amqtt 0.12.1 also pushed the viewer's aware/groups/# and
                # aware/def/# once more: docs/gateway.md, the amqtt patch).
                assert {i[:3] for i in inbox.items} == {("def/group/1", GROUP.encode(), True)}


async def test_mqtts_with_a_ca_file(mosquitto_tls: Mosquitto) -> None:
    inbox = Inbox()
    ca = str(mosquitto_tls.ca_file)
    settings = MqttSettings.from_url(mosquitto_tls.tls_url("gateway"), ca_file=ca)
    assert settings.tls and settings.port == mosquitto_tls.tls_port
    bridge = MqttBridge(settings, inbox)
    async with Collector(mosquitto_tls.url("viewer"), "aware/data/#") as sub, running(bridge):
        assert bridge.stats.protocol == "5"  # the probe went through TLS too
        op = MqttBridge(
            MqttSettings.from_url(mosquitto_tls.tls_url("operator"), ca_file=ca, client_id="op"),
            Inbox(),
        )
        async with running(op):
            op.publish(Publish("def/group/1", GROUP.encode(), retain=True))
            await inbox.wait(1)
        bridge.publish(Publish("data/1/1/2", b"{}"))
        await sub.wait_for(lambda ms: len(ms) >= 1)
    # Without the CA the certificate is refused: the bridge keeps retrying.
    bad = MqttBridge(
        MqttSettings.from_url(mosquitto_tls.tls_url("gateway"), reconnect_min_s=0.01), Inbox()
    )
    task = asyncio.create_task(bad.run())
    try:

        async def refused_twice() -> None:
            while bad.stats.connect_failures < 2:
                bad.changed.clear()
                await bad.changed.wait()

        await asyncio.wait_for(refused_twice(), 10)
        assert bad.stats.connects == 0
    finally:
        bad.stop()
        await asyncio.wait_for(task, 10)
