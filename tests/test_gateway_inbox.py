"""The last definition wins: the gateway's inbox (coalescing, bounds, reports) and
the MQTT bridge's reconcile after a burst, against a real Mosquitto.

The full-size attacks (20,000 redefinitions over MQTT, 50,000 over Zenoh, checked
on every mote) are ``benchmarks/abuse.py``; docs/robustness.md has the figures.
"""

from __future__ import annotations

import asyncio
import json
import random
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

import aiomqtt
import pytest
import zenoh
from mosquitto import Collector, Mosquitto, mosquitto_fixture  # noqa: F401

from awaremw.gateway.events import ErrorReport, Inject, Publish
from awaremw.gateway.hbn import HbnApi
from awaremw.gateway.inbox import OVERFLOW, Inbox, Incoming, overflow_report
from awaremw.gateway.mqtt import MqttBridge, MqttSettings
from awaremw.gateway.service import GatewayService, GatewaySettings
from awaremw.protocol.frames import ItemKind
from awaremw.runtime.zenoh_session import SessionSettings, free_tcp_endpoint, open_session


def msg(rel: str, payload: bytes = b"{}", retained: bool = False) -> Incoming:
    return Incoming(rel, payload, f"aware/{rel}", retained)


def drain(box: Inbox) -> list[Incoming]:
    out = []
    while (m := box.pop()) is not None:
        out.append(m)
    return out


def test_the_newest_definition_replaces_the_waiting_one_in_its_place() -> None:
    box = Inbox()
    for m in (
        msg("def/channel/1", b"a"),
        msg("def/group/1", b"g"),
        msg("cmd/led", b"c1"),
        msg("def/channel/1", b"b"),  # supersedes "a", keeps its place before the group
        msg("cmd/led", b"c2"),  # commands are events: both kept, in order
        msg("def/channel/1", b""),  # a deletion is a value too: the newest wins
    ):
        assert box.put(m) is None
    got = [(m.rel, m.payload) for m in drain(box)]
    assert got == [("def/channel/1", b""), ("def/group/1", b"g"), ("cmd/led", b"c1"),
                   ("cmd/led", b"c2")]  # fmt: skip
    assert box.stats.as_dict() == {"taken": 6, "coalesced": 2, "copies": 0, "dropped": 0,
                                   "handed": 4, "peak": 4}  # fmt: skip


def test_an_invalid_definition_keeps_its_place_to_be_refused_in_its_turn() -> None:
    box = Inbox(max_commands=2, valid=lambda m: m.payload != b"bad")
    for m in (
        msg("def/channel/1", b"bad"),
        msg("def/group/1", b"g"),
        msg("def/channel/1", b"good"),  # does not replace the bad one: waits behind it
        msg("def/channel/1", b"better"),  # replaces "good" (valid)
        msg("def/channel/1", b"bad"),
        msg("def/channel/1", b"best"),
    ):
        assert box.put(m) is None
    got = [(m.rel, m.payload) for m in drain(box)]
    assert got == [("def/channel/1", b"bad"), ("def/group/1", b"g"),
                   ("def/channel/1", b"bad"), ("def/channel/1", b"best")]  # fmt: skip
    # Kept invalid ones count with the commands (events): bounded too.
    for _ in range(2):
        assert box.put(msg("def/channel/2", b"bad")) is None
    assert box.put(msg("def/channel/2", b"bad")) is None  # the topic's newest: a value
    last = msg("def/channel/2", b"x")
    assert box.put(last) is last and box.stats.dropped == 1


def test_bounds_refuse_and_return_what_does_not_fit() -> None:
    box = Inbox(max_definitions=2, max_commands=2)
    for i in range(2):
        assert box.put(msg(f"def/channel/{i}")) is None
        assert box.put(msg(f"cmd/c{i}")) is None
    third = msg("def/channel/9")
    assert box.put(third) is third  # a third topic does not fit...
    assert box.put(msg("def/channel/0", b"new")) is None  # ...a newer value of one waiting does
    cmd = msg("cmd/c9")
    assert box.put(cmd) is cmd
    assert box.stats.dropped == 2 and len(box) == 4
    box.pop()  # a definition left: room for another
    assert box.put(third) is None and box.put(cmd) is cmd
    r = json.loads(overflow_report(third, "the MQTT inbox", refetched=True).to_json())
    assert r["code"] == OVERFLOW and r["topic"] == "aware/def/channel/9"
    assert "retained value is read again" in r["error"]
    r = json.loads(overflow_report(cmd, "the Zenoh HBN inbox", refetched=False).to_json())
    assert "send the command again" in r["error"]


def test_random_bursts_end_on_the_last_value_of_every_topic() -> None:
    for seed in range(5):
        rng = random.Random(seed)
        box = Inbox(max_definitions=8)
        last: dict[str, bytes] = {}
        applied: dict[str, bytes] = {}
        for i in range(5000):
            topic = f"def/channel/{rng.randrange(8)}"
            last[topic] = payload = str(i).encode()
            assert box.put(msg(topic, payload)) is None  # 8 topics fit 8 slots
            if rng.random() < 0.1:  # the gateway handles now and then
                for m in drain(box):
                    applied[m.rel] = m.payload
        for m in drain(box):
            applied[m.rel] = m.payload
        assert applied == last
        assert box.stats.coalesced > 0 and box.stats.dropped == 0


# --------------------------------------------------------------------------- Mosquitto


@asynccontextmanager
async def running(bridge: MqttBridge) -> AsyncIterator[None]:
    task = asyncio.create_task(bridge.run())
    try:
        await asyncio.wait_for(bridge.connected.wait(), 10)
        yield
    finally:
        bridge.stop()
        await asyncio.wait_for(task, 10)


async def until(cond: object, timeout: float) -> None:
    assert callable(cond)
    deadline = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < deadline, "timed out"
        await asyncio.sleep(0.05)


@pytest.mark.mosquitto
async def test_a_burst_ends_on_the_broker_retained_values_even_with_losses(
    mosquitto: Mosquitto,
) -> None:
    """2,000 retained redefinitions of 8 channels as fast as the broker takes them;
    the gateway handles slowly (3 ms each, a stand-in for its store) and loses every
    live message of channel 8 (a stand-in for a broker that drops some). After the
    burst the bridge re-reads the retained definitions: every channel ends on the
    broker's value."""
    state: dict[str, bytes] = {}
    handled = [0]

    def gateway(rel: str, payload: bytes, retained: bool, topic: str) -> None:
        handled[0] += 1
        time.sleep(0.003)  # the cost of handling one definition, not a synchronisation
        if rel == "def/channel/8" and not retained:
            return  # lost on the way
        state[rel] = payload

    settings = MqttSettings.from_url(mosquitto.url("gateway"), reconnect_min_s=0.05)
    bridge = MqttBridge(settings, gateway)
    rng = random.Random(1)
    last: dict[str, bytes] = {}
    async with running(bridge), aiomqtt.Client(
        "127.0.0.1", mosquitto.port, username="operator", password="operator-pw"
    ) as op:  # fmt: skip
        op.pending_calls_threshold = 250
        pending = []
        for i in range(2000):
            rel = f"def/channel/{1 + rng.randrange(8)}"
            doc = {"attr": "temperature", "period_s": round(1 + rng.random() * 4, 1),
                   "agg": rng.choice(["avg", "min", "max"]), "n": i}  # fmt: skip
            last[rel] = payload = json.dumps(doc).encode()
            pending.append(op.publish(f"aware/{rel}", payload, qos=1, retain=True))
            if len(pending) == 200:
                await asyncio.gather(*pending)
                pending.clear()
        await asyncio.gather(*pending)
        t_last = time.monotonic()
        await until(lambda: state == last, 10)
        took = time.monotonic() - t_last
    st = bridge.inbox.stats
    print(f"converged {took:.2f} s after the last; handled {handled[0]} of 2000; {st}")
    assert bridge.stats.reconciles >= 1
    assert st.coalesced > 0 and handled[0] < 2000 + 8 * (bridge.stats.reconciles + 1)
    assert st.dropped == 0


@pytest.mark.mosquitto
async def test_commands_the_gateway_cannot_take_are_each_reported(mosquitto: Mosquitto) -> None:
    got: list[str] = []

    def gateway(rel: str, payload: bytes, retained: bool, topic: str) -> None:
        time.sleep(0.005)  # a slow gateway
        got.append(payload.decode())

    settings = MqttSettings.from_url(mosquitto.url("gateway"), max_incoming=5)
    bridge = MqttBridge(settings, gateway)
    n = 200
    async with (
        Collector(mosquitto.url("viewer"), "aware/errors") as errors,
        running(bridge),
        aiomqtt.Client("127.0.0.1", mosquitto.port, username="operator",
                       password="operator-pw") as op,
    ):  # fmt: skip
        await asyncio.gather(
            *(op.publish("aware/cmd/led", json.dumps({"n": i}), qos=1) for i in range(n))
        )
        await until(
            lambda: len(got) + bridge.inbox.stats.dropped == n and not len(bridge.inbox), 20
        )
        dropped = bridge.inbox.stats.dropped
        await errors.wait_for(lambda ms: len(ms) >= dropped)
    reports = [json.loads(p) for p in errors.payloads("aware/errors")]
    assert all(r["code"] == OVERFLOW and r["topic"] == "aware/cmd/led" for r in reports)
    # Each refused command is reported (a report may come twice: QoS 1 after a
    # stop that swallowed its acknowledgement, counted in ``resent``) ...
    reported = {json.loads(r["payload"])["n"] for r in reports}
    assert dropped > 0 and len(reported) == dropped
    assert len(reports) - len(reported) <= bridge.stats.resent
    # ... and every command is either handled or reported, never both.
    handled = [json.loads(p)["n"] for p in got]
    assert sorted(handled + sorted(reported)) == list(range(n))


# --------------------------------------------------------------------------- Zenoh


def overflow(reports: list[bytes]) -> list[dict[str, str]]:
    """The overflow reports among what arrived on the errors key (probes left out)."""
    docs = [json.loads(r) for r in reports]
    return [d for d in docs if d["code"] == OVERFLOW]


@pytest.mark.zenoh
async def test_zenoh_bursts_end_on_the_last_put_and_overflow_is_reported() -> None:
    """5,000 puts on 4 definition keys and 300 commands while the gateway handles
    slowly: each key ends on its last put; each command is handled or reported on
    ``aware/hbn/errors``."""
    ep = free_tcp_endpoint()
    gw = open_session(SessionSettings(listen=(ep,)))
    dev = open_session(SessionSettings(connect=(ep,)))
    state: dict[str, bytes] = {}
    commands: list[int] = []

    def gateway(rel: str, payload: bytes, retained: bool, key: str, size: int) -> None:
        time.sleep(0.002)  # the cost of handling one message, not a synchronisation
        if rel.startswith("cmd/"):
            commands.append(json.loads(payload)["n"])
        else:
            state[rel] = payload

    api = HbnApi(gw, gateway, inbox=Inbox(max_commands=5))
    reports: list[bytes] = []
    loop = asyncio.get_running_loop()
    sub = dev.declare_subscriber(
        "aware/hbn/errors",
        lambda s: loop.call_soon_threadsafe(reports.append, s.payload.to_bytes()),
    )
    api.start()
    try:
        # Routes up: a probe put reaches the gateway.
        async def probe() -> bool:
            dev.put("aware/hbn/def/channel/0", b"probe")
            await asyncio.sleep(0.1)
            return "def/channel/0" in state

        deadline = time.monotonic() + 10
        while not await probe():
            assert time.monotonic() < deadline, "no route to the gateway"
        # ... and one from the gateway's errors to our subscriber.
        while not reports:
            assert time.monotonic() < deadline, "no route from the gateway"
            api.publish_error(ErrorReport("probe", "probe", "probe", ""))
            await asyncio.sleep(0.05)
        rng = random.Random(2)
        last: dict[str, bytes] = {"def/channel/0": b"probe"}

        def burst() -> None:
            block = zenoh.CongestionControl.BLOCK
            for i in range(5000):
                rel = f"def/channel/{1 + rng.randrange(4)}"
                last[rel] = str(i).encode()
                dev.put(f"aware/hbn/{rel}", last[rel], congestion_control=block)
            for n in range(300):
                dev.put("aware/hbn/cmd/led", json.dumps({"n": n}), congestion_control=block)

        await asyncio.to_thread(burst)
        await until(lambda: state == last and len(commands) + api.dropped == 300, 20)
        await until(lambda: len(overflow(reports)) >= api.dropped, 10)
    finally:
        api.close()
        sub.undeclare()  # type: ignore[no-untyped-call]
        dev.close()  # type: ignore[no-untyped-call]
        gw.close()  # type: ignore[no-untyped-call]
    st = api.inbox.stats
    assert st.coalesced > 0 and st.dropped > 0
    docs = overflow(reports)
    reported = [json.loads(d["payload"])["n"] for d in docs]
    assert sorted(commands + reported) == list(range(300))


@pytest.mark.mosquitto
async def test_a_bad_definition_superseded_at_once_is_still_refused_with_its_code(
    mosquitto: Mosquitto,
) -> None:
    """200 x (a bad channel definition, then a good one) on one topic, as fast as the
    broker takes them: the gateway applies the last good one, and each bad one is
    refused on ``aware/errors`` with its code -- also those a good one superseded in
    the inbox before they were handled."""
    injected: list[Inject] = []
    svc = GatewayService(
        [0], mqtt=MqttSettings.from_url(mosquitto.url("gateway")), settings=GatewaySettings()
    )
    svc.bind(lambda node, inj: injected.append(inj), lambda: 0.0)
    n = 200
    async with Collector(mosquitto.url("viewer"), "aware/errors") as errors, svc:
        assert svc.mqtt is not None
        await asyncio.wait_for(svc.mqtt.connected.wait(), 10)
        async with aiomqtt.Client(
            "127.0.0.1", mosquitto.port, username="operator", password="operator-pw"
        ) as op:  # fmt: skip
            op.pending_calls_threshold = 2 * n + 10
            await asyncio.gather(
                *(
                    op.publish("aware/def/channel/1", payload, qos=1, retain=True)
                    for i in range(n)
                    for payload in (
                        json.dumps({"attr": "temperature", "period_s": 0}),
                        json.dumps({"attr": "temperature", "period_s": 1 + i}),
                    )
                )
            )
        await errors.wait_for(lambda ms: len(ms) >= n, timeout=20)
        await until(lambda: svc.bridge.definitions().get("def/channel/1", {}).get("period_s")
                    == float(n), 10)  # fmt: skip
    codes = [json.loads(p)["code"] for p in errors.payloads("aware/errors")]
    assert codes.count("period_out_of_range") >= n
    assert svc.mqtt.inbox.stats.coalesced > 0, svc.mqtt.inbox.stats  # some were superseded
    assert svc.bridge.stats.refused_by_code["period_out_of_range"] == n


@pytest.mark.mosquitto
async def test_the_gateways_own_clearing_heard_back_is_not_a_clients_deletion(
    mosquitto: Mosquitto,
) -> None:
    """The gateway clears a refused definition off the broker (an empty retained
    message, when nothing is defined there) and hears that clearing back live: it is
    its own echo. Taken for a client's deletion, it replaced or deleted the
    definition a client sent meanwhile (the burst test above lost its last
    definition so, on a loaded machine). A client's deletion after it is the
    client's."""
    rel, bad = "def/channel/1", json.dumps({"attr": "temperature", "period_s": 0}).encode()
    good = json.dumps({"attr": "temperature", "period_s": 2}).encode()
    got: list[tuple[str, bytes, bool]] = []

    def gateway(rel: str, payload: bytes, retained: bool, topic: str) -> None:
        got.append((rel, payload, retained))
        if payload == bad:  # refused, with nothing defined there: cleared
            bridge.publish(Publish(rel, b"", retain=True))

    bridge = MqttBridge(MqttSettings.from_url(mosquitto.url("gateway")), gateway)
    async with running(bridge), aiomqtt.Client(
        "127.0.0.1", mosquitto.port, username="operator", password="operator-pw"
    ) as op:  # fmt: skip
        await asyncio.wait_for(bridge.subscribed.wait(), 10)
        await op.publish(f"aware/{rel}", bad, qos=1, retain=True)
        await until(lambda: bridge.stats.echoes or (rel, b"", False) in got, 10)
        await op.publish(f"aware/{rel}", good, qos=1, retain=True)
        await until(lambda: len(got) >= 2, 10)
        await op.publish(f"aware/{rel}", b"", qos=1, retain=True)  # the client deletes it
        await until(lambda: len(got) >= 3, 10)
    assert got == [(rel, bad, False), (rel, good, False), (rel, b"", False)]
    assert bridge.stats.echoes == 1


async def test_a_burst_goes_on_the_radio_as_its_newest_version_paced() -> None:
    """100 redefinitions of a channel in one go: the gateway mote gets the first at
    once and the newest at the end of the gap, not 100 versions; commands at once."""
    injected: list[Inject] = []
    svc = GatewayService([0], settings=GatewaySettings(hbn=False))
    svc.bind(lambda node, inj: injected.append(inj), lambda: 0.0)
    async with svc:
        for i in range(100):
            doc = {"attr": "temperature", "period_s": 1 + i}
            assert svc.handle("def/channel/1", json.dumps(doc).encode()).accepted
        assert svc.handle("cmd/led", json.dumps({"target": "all", "args": {}}).encode()).accepted
        assert [i.kind for i in injected] == [ItemKind.CHANNEL, ItemKind.COMMAND]
        latest = svc.bridge.item(ItemKind.CHANNEL, 1)
        assert latest is not None and latest.version == 100
        await until(lambda: len(injected) == 3, 5)
        assert injected[-1] == Inject(ItemKind.CHANNEL, 1, 100, latest.body)
