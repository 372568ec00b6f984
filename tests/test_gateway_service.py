"""The gateway service with real transports (Mosquitto, Zenoh) and a stand-in WSN.

The sensor network is replaced by two callables (what the gateway injects is
recorded; what the collection tree would deliver is fed through ``on_event``),
so these tests pin the transport side independently of the protocol. The
end-to-end tests with a real fleet are in test_gateway_e2e.py.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import Callable
from pathlib import Path

import pytest
import zenoh
from mosquitto import Collector, Mosquitto, mosquitto_fixture, pub  # noqa: F401

from awaremw.gateway.events import Inject
from awaremw.gateway.mqtt import MqttSettings
from awaremw.gateway.service import GatewayService, GatewaySettings, deployment_definitions
from awaremw.protocol.events import Delivered as FakeDelivered  # what a root emits
from awaremw.protocol.events import ItemAdopted
from awaremw.protocol.frames import (
    ChannelDef,
    DataRecord,
    GroupReport,
    GroupStatus,
    ItemKind,
)
from awaremw.runtime.zenoh_session import SessionSettings, free_tcp_endpoint, open_session

GROUP = json.dumps({"conditions": [{"attr": "temperature", "op": ">", "value": 45}]})
CHANNEL = json.dumps({"attr": "temperature", "group_type": 1, "period_s": 2, "agg": "avg"})

# Each malformed payload of the contract's list: (topic, payload, expected code).
MALFORMED: list[tuple[str, bytes, str]] = [
    (
        "aware/def/group/1",
        b'{"conditions": [{"attr": "pressure", "op": ">", "value": 1}]}',
        "unknown_attribute",
    ),
    (
        "aware/def/group/1",
        b'{"conditions": [{"attr": "x", "op": "=>", "value": 1}]}',
        "bad_operator",
    ),
    ("aware/def/channel/1", b'{"attr": "x", "period_s": 0.001}', "period_out_of_range"),
    ("aware/def/channel/999", CHANNEL.encode(), "channel_id_out_of_range"),
    ("aware/def/group/300", GROUP.encode(), "group_type_out_of_range"),
    ("aware/def/group/1", b'{"conditions": "temperature > 45"}', "wrong_type"),
    ("aware/def/channel/1", b'{"attr": "x", "period_s": ', "invalid_json"),
    ("aware/def/channel/1", b"\xc3\x28", "invalid_utf8"),
    ("aware/def/channel/1", b" " * 5000 + b"{}", "payload_too_large"),
    ("aware/cmd/led", b'{"target": {"robot": 1}}', "unknown_target"),
    ("aware/cmd/led", json.dumps({"args": {"text": "x" * 80}}).encode(), "does_not_fit_mtu"),
    ("aware/def/widget/1", b"{}", "unknown_topic"),
]


class FakeWsn:
    def __init__(self) -> None:
        self.injected: list[tuple[int, Inject]] = []
        self.t = 100.0

    def inject(self, node: int, inj: Inject) -> None:
        self.injected.append((node, inj))

    def now(self) -> float:
        return self.t


async def until(cond: Callable[[], bool], event: asyncio.Event, timeout: float = 10.0) -> None:
    async def loop() -> None:
        while not cond():
            event.clear()
            await event.wait()

    await asyncio.wait_for(loop(), timeout)


def service(mosq: Mosquitto, state: Path, wsn: FakeWsn, **kw: object) -> GatewayService:
    svc = GatewayService(
        [0, 5],
        settings=GatewaySettings(state_dir=state),
        mqtt=MqttSettings.from_url(mosq.url("gateway"), reconnect_min_s=0.05),
        **kw,  # type: ignore[arg-type]
    )
    svc.bind(wsn.inject, wsn.now)
    return svc


@pytest.mark.mosquitto
async def test_mqtt_definitions_data_groups_and_refusals(
    mosquitto: Mosquitto, tmp_path: Path
) -> None:
    wsn = FakeWsn()
    async with service(mosquitto, tmp_path, wsn) as svc:
        assert svc.mqtt is not None
        await asyncio.wait_for(svc.mqtt.connected.wait(), 10)
        assert pub(mosquitto, "operator", "aware/def/group/1", GROUP).returncode == 0
        assert pub(mosquitto, "operator", "aware/def/channel/1", CHANNEL).returncode == 0
        await until(lambda: len(wsn.injected) == 4, svc.handled)
        assert [(n, i.kind, i.item_id, i.version) for n, i in wsn.injected] == [
            (0, ItemKind.GROUP_TYPE, 1, 1),
            (5, ItemKind.GROUP_TYPE, 1, 1),
            (0, ItemKind.CHANNEL, 1, 1),
            (5, ItemKind.CHANNEL, 1, 1),
        ]
        assert wsn.injected[2][1].body == ChannelDef(0, 1, 0xFFFF, 2000, 0)

        # Every malformed payload: a specific refusal on aware/errors, nothing injected.
        async with Collector(mosquitto.url("viewer"), "aware/errors") as errors:
            for topic, payload, _ in MALFORMED:
                r = pub(mosquitto, "operator", topic, payload, retain=topic.startswith("aware/def"))
                assert r.returncode == 0, r
            await errors.wait_for(lambda ms: len(ms) >= len(MALFORMED))
            got = [json.loads(p) for p in errors.payloads()]
        assert [(e["topic"], e["code"]) for e in got] == [(t, c) for t, _, c in MALFORMED]
        assert all(e["error"] for e in got)
        assert len(wsn.injected) == 4
        assert svc.bridge.definitions()["def/channel/1"]["period_s"] == 2.0

        # WSN -> IP: records (once, even if two roots deliver them) and group state.
        async with Collector(mosquitto.url("viewer"), "aware/#") as viewer:
            rec = DataRecord(1, 1, 513, 7, 0, 47.25, 3, 12)
            svc.on_event(0, FakeDelivered(12, rec, 2, 101.5), 101.5)
            svc.on_event(5, FakeDelivered(12, rec, 3, 101.6), 101.6)
            svc.on_event(0, FakeDelivered(12, GroupReport(1, 513, 12, 3, 3), 2, 102.0), 102.0)
            await viewer.wait_for(lambda ms: any(t == "aware/groups/1/513" for t, *_ in ms))
            svc.on_event(
                0, FakeDelivered(12, GroupReport(1, 513, 12, 3, 0, GroupStatus.GONE), 2, 103), 103
            )
            await viewer.wait_for(
                lambda ms: any(t == "aware/groups/1/513" and not p for t, p, _ in ms)
            )
            data = [(t, json.loads(p)) for t, p, _ in viewer.messages if t.startswith("aware/data")]
            assert data == [
                (
                    "aware/data/1/1/513",
                    {
                        "value": 47.25,
                        "count": 3,
                        "agg": "avg",
                        "epoch": 7,
                        "leader": 12,
                        "t": 101.5,
                        "attr": "temperature",
                        "unit": "°C",
                    },
                )
            ]
            groups = [(p, r) for t, p, r in viewer.messages if t == "aware/groups/1/513"]
            assert json.loads(groups[0][0])["leader"] == 12
            assert groups[-1] == (b"", False)  # cleared (live message; retained now empty)

            # A merge: a client sees which group 514 merged into before it is cleared.
            svc.on_event(0, FakeDelivered(14, GroupReport(1, 514, 14, 1, 2), 2, 104.0), 104.0)
            gone = GroupReport(1, 514, 14, 1, 0, GroupStatus.GONE, 600)
            svc.on_event(0, FakeDelivered(14, gone, 2, 105.0), 105.0)
            await viewer.wait_for(
                lambda ms: any(t == "aware/groups/1/514" and b"merged_into" in p for t, p, _ in ms)
            )
            wsn.t = 105.0 + svc.bridge.report_period_s  # one report period later: cleared
            await viewer.wait_for(
                lambda ms: any(t == "aware/groups/1/514" and not p for t, p, _ in ms)
            )
            merged = [p for t, p, _ in viewer.messages if t == "aware/groups/1/514"]
            # (the ALIVE state may be coalesced away: retained topics keep their latest)
            assert json.loads(merged[-2])["merged_into"] == 600
            assert merged[-1] == b""


@pytest.mark.mosquitto
async def test_restart_keeps_versions_and_reinjects(mosquitto: Mosquitto, tmp_path: Path) -> None:
    wsn = FakeWsn()
    async with service(mosquitto, tmp_path, wsn) as svc:
        pub(mosquitto, "operator", "aware/def/channel/1", CHANNEL)
        await until(lambda: len(wsn.injected) == 2, svc.handled)
        changed = CHANNEL.replace('"period_s": 2', '"period_s": 3')
        pub(mosquitto, "operator", "aware/def/channel/1", changed)
        await until(lambda: len(wsn.injected) == 4, svc.handled)
        assert wsn.injected[-1][1].version == 2

    # Restart: the stored state is injected at once (same versions); the broker's
    # retained copy (the gateway's own, with its version: One truth) is recognised,
    # not applied again.
    wsn2 = FakeWsn()
    async with service(mosquitto, tmp_path, wsn2) as svc:
        assert [(n, i.item_id, i.version) for n, i in wsn2.injected] == [(0, 1, 2), (5, 1, 2)]
        assert svc.mqtt is not None
        await until(lambda: svc.bridge.stats.unchanged >= 1, svc.handled)
        assert len(wsn2.injected) == 2
        # A definition published after the restart takes effect, with version 3.
        pub(mosquitto, "operator", "aware/def/channel/1", CHANNEL)
        await until(lambda: len(wsn2.injected) == 4, svc.handled)
        assert wsn2.injected[-1][1].version == 3


@pytest.mark.zenoh
async def test_zenoh_hbn_api(tmp_path: Path) -> None:
    ep = free_tcp_endpoint()
    gw = open_session(SessionSettings(listen=(ep,)))
    dev = open_session(SessionSettings(connect=(ep,)))
    wsn = FakeWsn()
    svc = GatewayService([0], settings=GatewaySettings(state_dir=tmp_path), zenoh_session=gw)
    svc.bind(wsn.inject, wsn.now)
    try:
        async with svc:
            errors: list[bytes] = []
            loop = asyncio.get_running_loop()
            got_error = asyncio.Event()

            def on_err(s: zenoh.Sample) -> None:
                errors.append(s.payload.to_bytes())
                loop.call_soon_threadsafe(got_error.set)

            sub = dev.declare_subscriber("aware/hbn/errors", on_err)
            # Routes take a moment: put until the gateway has the definition.
            for _ in range(100):
                dev.put("aware/hbn/def/group/1", GROUP)
                try:
                    await until(lambda: len(wsn.injected) >= 1, svc.handled, timeout=0.1)
                    break
                except TimeoutError:
                    continue
            dev.put("aware/hbn/def/channel/1", CHANNEL)
            await until(lambda: len(wsn.injected) == 2, svc.handled)
            assert [i.kind for _, i in wsn.injected] == [ItemKind.GROUP_TYPE, ItemKind.CHANNEL]
            dev.put("aware/hbn/def/channel/2", b'{"attr": "nope", "period_s": 1}')
            await asyncio.wait_for(got_error.wait(), 10)
            err = json.loads(errors[0])
            assert (err["topic"], err["code"]) == ("aware/hbn/def/channel/2", "unknown_attribute")
            replies = await asyncio.to_thread(
                lambda: {
                    str(r.ok.key_expr): json.loads(r.ok.payload.to_bytes())
                    for r in dev.get("aware/hbn/def/**", timeout=5)
                    if r.ok is not None
                }
            )
            assert set(replies) == {"aware/hbn/def/group/1", "aware/hbn/def/channel/1"}
            assert replies["aware/hbn/def/channel/1"]["version"] == 1
            dev.delete("aware/hbn/def/channel/1")
            await until(lambda: len(wsn.injected) == 3, svc.handled)
            assert wsn.injected[-1][1] == Inject(ItemKind.CHANNEL, 1, 2, None)
            sub.undeclare()  # type: ignore[no-untyped-call]
    finally:
        dev.close()  # type: ignore[no-untyped-call]
        gw.close()  # type: ignore[no-untyped-call]


def test_deployment_definitions_are_validated_like_mqtt() -> None:
    defs = deployment_definitions(
        [
            {
                "type": 1,
                "conditions": [{"attr": "rssi:100", "op": ">", "value": -89.0}],
                "hysteresis": 3.0,
            }
        ],
        [
            {
                "id": 1,
                "attr": "temperature",
                "group_type": 1,
                "group_id": "*",
                "period_s": 2.0,
                "agg": "avg",
            },
            {"id": 2, "attr": "bogus", "period_s": 2.0},
        ],
    )
    assert [r for r, _ in defs] == ["def/group/1", "def/channel/1", "def/channel/2"]
    wsn = FakeWsn()
    svc = GatewayService([0])
    svc.bind(wsn.inject, wsn.now)
    outs = svc.define_initial(defs)
    assert [o.accepted for o in outs] == [True, True, False]
    assert outs[2].error is not None and outs[2].error.code == "unknown_attribute"


def test_versions_in_force_are_learned_from_the_network() -> None:
    """A gateway that lost its store learns the versions its mote hears."""
    wsn = FakeWsn()
    held = {(ItemKind.CHANNEL, 1): ChannelDef(0, 1, 0xFFFF, 4000, 0)}
    svc = GatewayService([0])
    svc.bind(wsn.inject, wsn.now, lambda node, kind, i: held.get((kind, i)))
    svc.on_event(0, ItemAdopted(ItemKind.CHANNEL, 1, 7, False, 3), 5.0)
    svc.on_event(0, ItemAdopted(ItemKind.CHANNEL, 1, 2, False, 3), 5.0)  # older: ignored
    svc.on_event(0, ItemAdopted(ItemKind.GROUP_TYPE, 4, 3, True, 3), 5.0)  # a tombstone
    svc.on_event(0, ItemAdopted(ItemKind.CHANNEL, 2, 9, False, None), 5.0)  # ours: not learned
    assert svc.bridge.stats.learned == 2
    assert svc.bridge.definitions() == {
        "def/channel/1": {"attr": "temperature", "group_type": 1, "group_id": "*",
                          "period_s": 4.0, "agg": "avg", "version": 7},
    }  # fmt: skip
    # The same body again: nothing new. Another one: version 8, which the motes accept.
    same = json.dumps({"attr": "temperature", "group_type": 1, "period_s": 4})
    assert svc.handle("def/channel/1", same.encode()).inject is None
    out = svc.handle("def/channel/1", CHANNEL.encode())
    assert out.inject is not None and out.inject.version == 8
    out = svc.handle("def/group/4", GROUP.encode())
    assert out.inject is not None and out.inject.version == 4


def test_a_definition_the_network_ignored_is_reasserted_above_its_version() -> None:
    """Restarted without its store, the gateway numbers from 1; when its mote hears
    that the network holds version 5 of something else, its own newer definition
    goes out again as version 6."""
    wsn = FakeWsn()
    net_body = ChannelDef(0, 1, 0xFFFF, 4000, 0)
    svc = GatewayService([0])
    svc.bind(wsn.inject, wsn.now, lambda node, kind, i: net_body)
    out = svc.handle("def/channel/1", CHANNEL.encode())
    assert out.inject is not None and out.inject.version == 1  # the motes ignore it
    svc.on_event(0, ItemAdopted(ItemKind.CHANNEL, 1, 5, False, 3), 5.0)
    last = wsn.injected[-1][1]
    assert (last.version, last.body) == (6, ChannelDef(0, 1, 0xFFFF, 2000, 0))
    assert svc.bridge.stats.reasserted == 1
    assert svc.bridge.definitions()["def/channel/1"]["version"] == 6
