"""One truth on both transports: the gateway's store is the only source of the
definitions in force; MQTT retains each one with its version and a Zenoh ``get``
answers the same bytes, whichever transport made the change, across deletions and
restarts (docs/gateway.md, "One truth"). Real parts: a gateway mote on a Zenoh
session on loopback, the embedded broker and Mosquitto, aiomqtt clients."""

from __future__ import annotations

import asyncio
import json
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import zenoh
from mosquitto import Mosquitto, mosquitto_fixture  # noqa: F401

from awaremw.cli.client import publish
from awaremw.gateway.bridge import MAX_VERSION_JUMP, GatewayBridge
from awaremw.gateway.broker import EmbeddedBroker
from awaremw.gateway.hbn import wait_for_gateway
from awaremw.gateway.inbox import Inbox, Incoming
from awaremw.gateway.mqtt import MqttSettings
from awaremw.gateway.schema import is_copy
from awaremw.gateway.service import GatewayService, GatewaySettings, attach_to_fleet
from awaremw.gateway.store import VersionStore
from awaremw.nodes import KindsFactory, kind_names
from awaremw.runtime.deployment import load
from awaremw.runtime.fleet import Fleet, FleetSettings
from awaremw.runtime.zenoh_session import SessionSettings, free_tcp_endpoint, open_session

pytestmark = pytest.mark.zenoh

AGREE_WITHIN_S = 5.0  # the bound every step must meet (measured: see docs/gateway.md)
ABSENT_AFTER_S = 0.5  # no retained message within this after the SUBACK: none is held


def group(value: float) -> bytes:
    return json.dumps({"conditions": [{"attr": "temperature", "op": ">", "value": value}]}).encode()


def channel(period: float) -> bytes:
    return json.dumps({"attr": "temperature", "group_type": 1, "period_s": period}).encode()


def copy(body: bytes, version: int) -> bytes:
    return json.dumps({**json.loads(body), "version": version}).encode()


def test_the_store_answers_each_copy_by_its_version() -> None:
    """The pure rules (docs/gateway.md, "One truth"), on the bridge alone."""
    b = GatewayBridge(VersionStore())
    rel = "def/group/1"

    def version() -> int:
        item = b.definitions().get(rel)
        return -1 if item is None else int(item["version"])

    assert b.handle(rel, group(10), source=rel).accepted and version() == 1
    assert b.handle(rel, group(20), source=rel).accepted and version() == 2
    # The store's own copy: nothing to do; its bytes are what both transports show.
    ours = b.definition_payload(rel)
    assert ours is not None and json.loads(ours)["version"] == 2
    assert not b.handle(rel, ours, source=rel).accepted and version() == 2
    # An older copy is stale: it changes nothing, whatever its body.
    assert not b.handle(rel, copy(group(10), 1), source=rel).accepted
    assert version() == 2 and b.stats.stale == 1
    # A newer copy of the same body: stale as well (the store's number stands).
    assert not b.handle(rel, copy(group(20), 9), source=rel).accepted and version() == 2
    # The store's version with another body: an edit, the next version.
    assert b.handle(rel, copy(group(30), 2), source=rel).accepted and version() == 3
    # A newer copy with another body: taken in under its own version...
    out = b.handle(rel, copy(group(40), 7), source=rel)
    assert out.inject is not None and out.inject.version == 7 and version() == 7
    # ... but not so far ahead that the radio's u32 circle would read it as older.
    far = b.handle(rel, copy(group(50), 7 + MAX_VERSION_JUMP + 1), source=rel)
    assert far.error is not None and far.error.code == "bad_value" and version() == 7
    for bad, code in ((0, "bad_value"), (-3, "bad_value"), ("7", "wrong_type")):
        doc = {**json.loads(group(60)), "version": bad}
        refused = b.handle(rel, json.dumps(doc).encode(), source=rel)
        assert refused.error is not None and refused.error.code == code, bad
    assert version() == 7
    # Deleted: no payload on either transport, and a stale copy does not bring it back.
    assert b.handle(rel, b"", source=rel).accepted and b.definition_payload(rel) == b""
    assert not b.handle(rel, copy(group(40), 7), source=rel).accepted
    assert b.definition_payload(rel) == b""
    assert b.definition_payload("def/group/999") is None  # names no definition


@dataclass
class Brokers:
    """The URLs a broker gives the gateway and a client that defines."""

    gateway: str
    operator: str
    viewer: str
    restart: Any  # () -> None: the broker again, its retained messages gone


@pytest.fixture(params=["embedded", pytest.param("mosquitto", marks=pytest.mark.mosquitto)])
def broker(request: pytest.FixtureRequest) -> str:
    return str(request.param)


@asynccontextmanager
async def brokers(kind: str, request: pytest.FixtureRequest) -> AsyncIterator[Brokers]:
    if kind == "mosquitto":
        m: Mosquitto = request.getfixturevalue("mosquitto")

        def restart_mosquitto() -> None:
            m.kill()  # persistence off: the retained messages go with it
            m.start()

        yield Brokers(m.url("gateway"), m.url("operator"), m.url("viewer"), restart_mosquitto)
        return
    b = EmbeddedBroker(anonymous=True)
    await b.start()
    holder = {"b": b}

    async def restart_embedded() -> None:
        await holder["b"].stop()
        fresh = EmbeddedBroker(port=b.port, anonymous=True)  # in memory: nothing retained
        await fresh.start()
        holder["b"] = fresh

    try:
        yield Brokers(b.url, b.url, b.url, restart_embedded)
    finally:
        await holder["b"].stop()


async def retained(url: str, topic: str) -> bytes:
    """What a new subscriber gets retained on ``topic`` (b"": nothing)."""
    s = MqttSettings.from_url(url)
    async with s.client(f"truth-{time.monotonic_ns()}", timeout=10) as c:
        await c.subscribe(topic, qos=1)
        try:
            async with asyncio.timeout(ABSENT_AFTER_S):
                async for m in c.messages:
                    if m.retain and isinstance(m.payload, bytes):
                        return m.payload
        except TimeoutError:
            pass
    return b""


def answered(dev: zenoh.Session, key: str) -> bytes:
    """What a Zenoh ``get`` answers on ``key`` (b"": no answer)."""
    replies = [r.ok.payload.to_bytes() for r in dev.get(key, timeout=5.0) if r.ok is not None]
    assert len(replies) <= 1, replies
    return replies[0] if replies else b""


@dataclass
class Views:
    viewer: str
    dev: zenoh.Session
    latencies: list[float]

    async def agree(self, rel: str, want: dict[str, Any] | None) -> dict[str, Any] | None:
        """Wait until MQTT retained and Zenoh ``get`` show the same bytes on ``rel``,
        and they are ``want`` (a subset of the document, with its version) or nothing."""
        start = time.monotonic()
        last: tuple[bytes, bytes] = (b"", b"")
        while time.monotonic() - start < AGREE_WITHIN_S:
            mq = await retained(self.viewer, f"aware/{rel}")
            zn = await asyncio.to_thread(answered, self.dev, f"aware/hbn/{rel}")
            last = (mq, zn)
            if mq == zn and _matches(mq, want):
                self.latencies.append(time.monotonic() - start)
                return None if not mq else json.loads(mq)  # type: ignore[no-any-return]
        raise AssertionError(f"{rel}: MQTT {last[0]!r} and Zenoh {last[1]!r}, wanted {want}")


def _matches(payload: bytes, want: dict[str, Any] | None) -> bool:
    if want is None:
        return payload == b""
    if not payload:
        return False
    doc = json.loads(payload)
    return all(doc.get(k) == v for k, v in want.items())


@asynccontextmanager
async def gateway(
    b: Brokers, state: Path, latencies: list[float]
) -> AsyncIterator[tuple[GatewayService, Views]]:
    """A gateway (its mote on a Zenoh session listening on loopback, its store in
    ``state``) and a device session connected to it, once the gateway answers."""
    dep = load("grid_small", kind_names())
    ep = free_tcp_endpoint()
    fleet = Fleet(
        dep,
        KindsFactory(),
        FleetSettings(name="gateway", listen=(ep,), control=False),
        node_filter=lambda s: s.kind == "gateway",
    )
    async with fleet:
        svc = attach_to_fleet(
            fleet,
            settings=GatewaySettings(state_dir=state),
            mqtt=MqttSettings.from_url(b.gateway, reconnect_min_s=0.05),
        )
        async with svc:
            assert svc.mqtt is not None
            await asyncio.wait_for(svc.mqtt.connected.wait(), 10)
            dev = open_session(SessionSettings(connect=(ep,)))
            try:
                await asyncio.to_thread(wait_for_gateway, dev)
                yield svc, Views(b.viewer, dev, latencies)
            finally:
                dev.close()  # type: ignore[no-untyped-call]


async def define(url: str, rel: str, payload: bytes) -> int | None:
    """Through the client verbs' path: publish retained, wait for the gateway's take."""
    answer = await publish(MqttSettings.from_url(url), rel, payload, retain=True, wait=5.0)
    assert answer.error is None, answer.error
    return answer.version


async def test_mqtt_and_zenoh_show_one_truth(
    broker: str, request: pytest.FixtureRequest, tmp_path: Path
) -> None:
    latencies: list[float] = []
    async with brokers(broker, request) as b:
        async with gateway(b, tmp_path, latencies) as (svc, views):
            # MQTT, then Zenoh: a new MQTT subscriber gets the Zenoh version, retained.
            assert await define(b.operator, "def/group/1", group(15)) == 1
            await views.agree("def/group/1", {"version": 1, "conditions": [
                {"attr": "temperature", "op": ">", "value": 15.0}]})  # fmt: skip
            views.dev.put("aware/hbn/def/group/1", group(45))
            doc = await views.agree("def/group/1", {"version": 2})
            assert doc is not None and doc["conditions"][0]["value"] == 45.0
            # Zenoh, then MQTT.
            views.dev.put("aware/hbn/def/channel/1", channel(2.0))
            await views.agree("def/channel/1", {"version": 1, "period_s": 2.0})
            assert await define(b.operator, "def/channel/1", channel(4.0)) == 2
            await views.agree("def/channel/1", {"version": 2, "period_s": 4.0})
            # The same definition again makes no version, and MQTT still shows the store's.
            assert await define(b.operator, "def/channel/1", channel(4.0)) == 2
            await views.agree("def/channel/1", {"version": 2, "period_s": 4.0})
            # A delete each way: neither transport shows the definition any more.
            views.dev.delete("aware/hbn/def/group/1")
            await views.agree("def/group/1", None)
            assert await define(b.operator, "def/channel/1", b"") is None
            await views.agree("def/channel/1", None)
            # Something to carry over the restarts: group 2 at version 2.
            await define(b.operator, "def/group/2", group(20))
            views.dev.put("aware/hbn/def/group/2", group(25))
            await views.agree("def/group/2", {"version": 2})
            stale = await retained(b.viewer, "aware/def/group/1")
            assert stale == b""
            old_copy = json.dumps({**json.loads(group(20)), "version": 1}).encode()

        # While the gateway is away: a stale copy of group 2 (version 1) is retained
        # over the store's version 2, and a new channel is defined on MQTT.
        async with MqttSettings.from_url(b.operator).client("truth-writer", timeout=10) as c:
            await c.publish("aware/def/group/2", old_copy, qos=1, retain=True)
            await c.publish("aware/def/channel/3", channel(3.0), qos=1, retain=True)
        assert await retained(b.viewer, "aware/def/group/2") == old_copy

        async with gateway(b, tmp_path, latencies) as (svc, views):
            await views.agree("def/group/2", {"version": 2, "conditions": [
                {"attr": "temperature", "op": ">", "value": 25.0}]})  # fmt: skip
            await views.agree("def/channel/3", {"version": 1, "period_s": 3.0})
            await views.agree("def/group/1", None)
            await views.agree("def/channel/1", None)
            assert svc.bridge.stats.stale >= 1

        # The broker loses every retained message while the gateway is away: the
        # gateway republishes the store's at start.
        restarted = b.restart()
        if asyncio.iscoroutine(restarted):
            await restarted
        assert await retained(b.viewer, "aware/def/group/2") == b""
        async with gateway(b, tmp_path, latencies) as (svc, views):
            await views.agree("def/group/2", {"version": 2})
            await views.agree("def/channel/3", {"version": 1})
            await views.agree("def/group/1", None)
    print(
        f"\none truth ({broker}): {len(latencies)} checks, agreed within "
        f"median {sorted(latencies)[len(latencies) // 2] * 1000:.0f} ms, "
        f"max {max(latencies) * 1000:.0f} ms"
    )


def test_a_copy_never_takes_the_place_of_a_clients_waiting_definition() -> None:
    """In a burst the gateway hears its own older republications among the client's
    definitions: the inbox keeps the client's newest, whatever copy comes after it."""
    inbox = Inbox(is_copy=lambda m: is_copy(m.payload))
    topic = "aware/def/group/1"

    def put(payload: bytes) -> None:
        assert inbox.put(Incoming("def/group/1", payload, topic)) is None

    put(group(10))
    put(copy(group(5), 4))  # our echo of an older version: the client's stays
    assert inbox.stats.copies == 1
    put(group(20))  # the client's newer one replaces its older one
    put(copy(group(20), 6))  # a copy after it: ignored again
    m = inbox.pop()
    assert m is not None and m.payload == group(20) and inbox.pop() is None
    put(copy(group(20), 6))  # alone, a copy waits like any definition
    put(copy(group(30), 7))  # and a newer copy replaces an older one
    m = inbox.pop()
    assert m is not None and json.loads(m.payload)["version"] == 7
    assert not is_copy(b"\xff") and not is_copy(b'"version"')
