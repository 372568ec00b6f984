"""A rogue radio against a secured fleet and gateway over real Zenoh and Mosquitto.

The rogue is a Zenoh session on the radio keys without the network key: it
captures the fleet's frames for a while, then puts back exact replays, replays
with fresh link sequence numbers, and altered copies (a record's value, a
report's or beacon's group id, a Drip item's id) with fresh link sequence
numbers and fresh frame counters. Nothing it altered or replayed may reach
MQTT or the Zenoh HBN API, and its frames are counted as refused.

The media and runners are built here with a ``security`` argument (the fleet
launcher and the CLI take ``--secrets DIR`` elsewhere).
"""

from __future__ import annotations

import asyncio
import dataclasses
import json
import time
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from dataclasses import dataclass, field

import pytest
import zenoh
from mosquitto import Mosquitto, MosquittoSub, mosquitto_fixture, pub  # noqa: F401

from awaremw.gateway.mqtt import MqttSettings
from awaremw.gateway.service import GatewayService, _inject_core
from awaremw.nodes import build_core, kind_names, world_of
from awaremw.protocol.events import ItemAdopted
from awaremw.protocol.frames import (
    CtpData,
    DataRecord,
    DripItem,
    Frame,
    GroupReport,
    LeaderBeacon,
    decode,
    encode,
)
from awaremw.protocol.mote import AwareMote
from awaremw.protocol.signing import ItemSigner
from awaremw.radio.envelope import Kind, decode_envelope, encode_envelope
from awaremw.radio.model import RadioModel
from awaremw.radio.security import COUNTER_BYTES, RadioSecurity
from awaremw.radio.zenoh_medium import ZenohMedium
from awaremw.runtime.deployment import Deployment, load
from awaremw.runtime.driver import MoteRunner
from awaremw.runtime.zenoh_session import SessionSettings, free_tcp_endpoint, open_session
from awaremw.world.clock import EmulatedClock

pytestmark = [pytest.mark.zenoh, pytest.mark.slow, pytest.mark.mosquitto]

SPEED = 4.0
MARK_VALUE = 999.0  # a record value no mote measures
MARK_GROUP = 4321  # a group id no leader picks in this run
MARK_ITEM = 77  # an item id nobody defines
CAPTURE_MAX = 400  # envelopes the rogue keeps


@dataclass
class Secured:
    """One 'process': a session, a secured medium and its motes."""

    session: zenoh.Session
    medium: ZenohMedium
    runners: dict[int, MoteRunner] = field(default_factory=dict)


@asynccontextmanager
async def secured_process(
    dep: Deployment,
    security: RadioSecurity,
    clock: EmulatedClock,
    settings: SessionSettings,
    owns: Callable[[str], bool],
    on_event: Callable[[int, object, float], None],
    signer: ItemSigner | None = None,
) -> AsyncIterator[Secured]:
    session = await asyncio.to_thread(open_session, settings)
    medium = ZenohMedium(session, RadioModel(dep.preset, dep.seed), clock, security=security)
    medium.open()
    proc = Secured(session, medium)
    world = world_of(dep)
    try:
        for spec in dep.nodes:
            if not owns(spec.kind):
                continue
            core = build_core(spec, dep, world)
            assert isinstance(core, AwareMote)
            if core.config.is_root:
                core.dissemination.signer = signer
            proc.runners[spec.id] = MoteRunner(
                core,
                medium,
                spec.mobility(),
                tx_power_dbm=dep.tx_power_of(spec),
                on_event=on_event,
            )
        yield proc
    finally:
        for r in proc.runners.values():
            r.stop()
        medium.close()
        await asyncio.to_thread(session.close)


async def until(cond: Callable[[], bool], timeout: float) -> None:
    """Wait (polling every 50 ms) until ``cond()`` holds, or fail after ``timeout`` s."""
    end = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > end:
            raise TimeoutError("condition not reached")
        await asyncio.sleep(0.05)


def alter(frame: Frame) -> Frame | None:
    """The rogue's edit of a frame it decoded (None: nothing worth altering)."""
    if isinstance(frame, CtpData):  # a new seqno, so that no duplicate filter drops it
        seqno = (frame.seqno + 0x100) & 0xFFFF
        if isinstance(frame.payload, DataRecord):
            rec = dataclasses.replace(frame.payload, value=MARK_VALUE)
            return dataclasses.replace(frame, seqno=seqno, payload=rec)
        if isinstance(frame.payload, GroupReport):
            rep = dataclasses.replace(frame.payload, group_id=MARK_GROUP)
            return dataclasses.replace(frame, seqno=seqno, payload=rep)
    if isinstance(frame, LeaderBeacon):
        return dataclasses.replace(frame, group_id=MARK_GROUP, weight=0xFFFF)
    if isinstance(frame, DripItem):
        return dataclasses.replace(frame, item_id=MARK_ITEM, version=frame.version + 5)
    return None


def forgeries(data: bytes, mic: int) -> list[bytes]:
    """Envelopes the rogue makes of one captured frame envelope."""
    env = decode_envelope(data)
    fresh = (env.seq + 0x4000) & 0xFFFF
    out = [
        data,  # exact replay
        encode_envelope(Kind.FRAME, env.src, env.x, env.y, env.tx_power, fresh, 0, env.t,
                        env.dest, env.frame),  # replay, fresh link sequence number
    ]  # fmt: skip
    tail = env.frame[-(COUNTER_BYTES + mic) :]
    payload = env.frame[: -(COUNTER_BYTES + mic)]
    try:
        altered = alter(decode(payload))
    except ValueError:
        altered = None
    if altered is not None:
        body = encode(altered)
        counter = int.from_bytes(tail[:COUNTER_BYTES], "big") + 1000
        for frame in (
            body + tail,  # altered, the original counter and MIC
            body + counter.to_bytes(COUNTER_BYTES, "big") + tail[COUNTER_BYTES:],  # fresh counter
        ):
            out.append(
                encode_envelope(Kind.FRAME, env.src, env.x, env.y, env.tx_power,
                                (fresh + 1) & 0xFFFF, 0, env.t, env.dest, frame)
            )  # fmt: skip
    return out


def records(lines: list[tuple[str, str]]) -> list[tuple[int, int, dict[str, object]]]:
    out = []
    for topic, payload in lines:
        parts = topic.split("/")
        if len(parts) >= 5 and parts[-4] == "data" and payload:
            out.append((int(parts[-3]), int(parts[-1]), json.loads(payload)))
    return out


@pytest.mark.timeout(180)
async def test_rogue_radio_replays_and_alterations_are_refused(mosquitto: Mosquitto) -> None:
    dep = load("grid_small", kind_names())
    security, sk = RadioSecurity.throwaway()
    dep = dataclasses.replace(
        dep,
        middleware={
            **dep.middleware,
            "mtu": security.payload_mtu(dep.preset.mtu),
            "gateway_public_key": security.gateway_public_key,
        },
    )
    ep = free_tcp_endpoint()
    clock = EmulatedClock(SPEED)
    adopted: list[tuple[int, ItemAdopted]] = []

    def note(node: int, ev: object, now: float) -> None:
        if isinstance(ev, ItemAdopted):
            adopted.append((node, ev))

    captured: list[tuple[str, bytes]] = []
    hbn: list[tuple[str, bytes]] = []
    mqtt = MqttSettings.from_url(mosquitto.url("gateway"), reconnect_min_s=0.05)
    gw_holder: list[GatewayService] = []

    def gw_event(node: int, ev: object, now: float) -> None:
        note(node, ev, now)
        if gw_holder:
            gw_holder[0].on_event(node, ev, now)

    async with (
        secured_process(
            dep, security, clock, SessionSettings(listen=(ep,)),
            lambda k: k != "gateway", note,
        ) as sensors,
        secured_process(
            dep, security, clock, SessionSettings(connect=(ep,)),
            lambda k: k == "gateway", gw_event, ItemSigner(sk),
        ) as gateway,
        MosquittoSub(mosquitto, "viewer", "aware/#") as sub,
    ):  # fmt: skip
        rogue = await asyncio.to_thread(open_session, SessionSettings(connect=(ep,)))
        try:
            capturing = [False]

            def capture(s: zenoh.Sample) -> None:
                if capturing[0] and len(captured) < CAPTURE_MAX:
                    captured.append((str(s.key_expr), s.payload.to_bytes()))

            cap = rogue.declare_subscriber("aware/radio/**", capture)
            watch = rogue.declare_subscriber(
                "aware/hbn/**", lambda s: hbn.append((str(s.key_expr), s.payload.to_bytes()))
            )
            root = next(iter(gateway.runners))
            root_core = gateway.runners[root].core
            assert isinstance(root_core, AwareMote)
            svc = GatewayService(
                [root],
                config=root_core.config,
                mqtt=mqtt,
                zenoh_session=gateway.session,
                known_nodes=dep.ids,
                speed=SPEED,
            )
            svc.bind(
                lambda node, inj: gateway.runners[node].run_on(
                    lambda c, now: _inject_core(c, inj, now)
                ),
                clock.now,
                lambda node, kind, iid: (
                    it.body
                    if (it := root_core.dissemination.items.get((kind, iid))) is not None
                    else None
                ),
            )
            gw_holder.append(svc)
            clock.restart(time.time())
            for proc in (sensors, gateway):
                for r in proc.runners.values():
                    r.start()
            async with svc:
                await until(lambda: svc.mqtt is not None and svc.mqtt.connected.is_set(), 10)
                group = json.dumps({"conditions": [{"attr": "x", "op": ">", "value": 3}]})
                chan = json.dumps(
                    {"attr": "temperature", "group_type": 1, "group_id": "*",
                     "period_s": 1.0, "agg": "avg"}
                )  # fmt: skip
                assert pub(mosquitto, "operator", "aware/def/group/1", group).returncode == 0
                assert pub(mosquitto, "operator", "aware/def/channel/1", chan).returncode == 0
                # Genuine traffic first: records on MQTT, and a capture full of frames.
                await until(lambda: len(records(sub.lines)) >= 3, 60)
                capturing[0] = True
                await until(lambda: len(captured) >= CAPTURE_MAX, 30)
                cap.undeclare()  # type: ignore[no-untyped-call]
                frames = [(k, d) for k, d in captured if decode_envelope(d).kind is Kind.FRAME]
                assert len(frames) >= 100
                puts = 0
                for key, data in frames:
                    for fake in forgeries(data, security.mic_bytes):
                        rogue.put(key, fake)
                        puts += 1
                media = (sensors.medium, gateway.medium)

                def refused() -> int:
                    return sum(c.refused for m in media for c in m.counters.values())

                # Every rogue frame is heard by some mote and refused by it.
                await until(lambda: refused() >= len(frames), 30)
                n_before = len(records(sub.lines))
                await until(lambda: len(records(sub.lines)) >= n_before + 3, 30)
            watch.undeclare()  # type: ignore[no-untyped-call]
        finally:
            await asyncio.to_thread(rogue.close)

    # Nothing altered reached MQTT or the HBN API; no replayed record twice.
    recs = records(sub.lines)
    assert recs and all(r["value"] != MARK_VALUE for _, _, r in recs)
    assert not [t for t, _ in sub.lines if f"/{MARK_GROUP}" in t or f"/{MARK_ITEM}" in t]
    keys = [(ch, g, r["epoch"]) for ch, g, r in recs]
    assert len(keys) == len(set(keys)), "a record was published twice"
    assert hbn, "the HBN API published nothing"
    for key, payload in hbn:
        assert f"/{MARK_GROUP}" not in key and f"/{MARK_ITEM}" not in key, key
        assert b"999.0" not in payload, (key, payload[:120])
    # No mote (gateway included) adopted a definition the rogue made.
    assert not [a for _, a in adopted if a.item_id == MARK_ITEM]
    assert {a.source for _, a in adopted} <= {None, *dep.ids}
    # Refusals, counted per reason: replays and bad MICs; no fault anywhere.
    reasons: dict[str, int] = {}
    for m in media:
        assert m.guard is not None
        for k, v in m.guard.refused.as_dict().items():
            reasons[k] = reasons.get(k, 0) + v
        assert m.faults.total == 0, m.faults.as_dict()
    assert reasons.get("replay", 0) > 0 and reasons.get("mic", 0) > 0, reasons
    assert puts > len(frames)
