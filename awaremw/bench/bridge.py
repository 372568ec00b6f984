"""``awaremw bench bridge``: latency and throughput from the sensor network to MQTT.

Two measurements, one JSON object (``--json``):

* **end to end** (unless ``--no-fleet``): a real fleet (``--deployment``,
  default ``grid_small``) and the gateway in this process, a broker
  (``--mqtt URL``, default: the embedded amqtt broker), an MQTT subscriber on
  ``aware/data/#``. A group type that every mote joins and one channel with
  period ``--period`` are defined over MQTT; for ``--duration`` emulated
  seconds each record's *latency* is the time from the leader's sample (the
  start of the record's epoch on the shared clock: TAG-style epochs sample at
  the epoch start) to its arrival at the subscriber, and its *delivery time*
  the time from the leader's :class:`RecordProduced` event (final aggregate
  ready) to the arrival. The latency therefore includes the TAG slot schedule
  of the epoch (the leader finalises in its slot, up to one period after the
  sample), the collection tree and the bridge; the delivery time only the
  collection tree, gateway and broker.
* **bridge latency**: ``--samples`` synthetic records (default 1,000) handed
  to the gateway service at a steady ``--rate`` (records/s, default 100, a
  tenth of the bridge's throughput on a quiet machine), each timed from the hand-over (the
  gateway mote's ``Delivered`` event) to its arrival at the subscriber: the
  bridge's own latency (gateway, broker, subscriber), with enough samples for
  a p99;
* **bridge throughput**: ``--records`` synthetic records handed to the
  gateway as fast as it takes them; sustained records/s until the subscriber
  has every one of them.

Keys: ``latency_p50_ms``, ``latency_p99_ms`` (sample at the leader -> MQTT
subscriber), ``delivery_p50_ms``, ``delivery_p99_ms`` (leader's record ->
subscriber), ``latency_records`` (records measured end to end),
``bridge_p50_ms``, ``bridge_p99_ms``, ``bridge_max_ms`` (gateway hand-over ->
subscriber, paced), ``bridge_samples`` (records timed, all of them arrived),
``bridge_rate_per_s``, ``records_per_s`` (bridge throughput), ``throughput_records``,
``broker`` (``embedded`` or the URL without password), ``mqtt_protocol``,
``deployment``, ``period_s``, ``speed``. Latency keys are ``null`` with
``--no-fleet``.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import statistics
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass
from typing import Any

import aiomqtt

from awaremw.gateway.broker import EmbeddedBroker
from awaremw.gateway.mqtt import MqttSettings, mqtt_problem
from awaremw.gateway.service import GatewayService, GatewaySettings
from awaremw.protocol.events import Delivered
from awaremw.protocol.frames import DataRecord
from awaremw.security.redact import mask_url


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--mqtt", default=None, metavar="URL", help="broker (default: embedded)")
    p.add_argument(
        "--sub-mqtt",
        default=None,
        metavar="URL",
        help="the subscriber's URL if its account differs (default: --mqtt)",
    )
    p.add_argument("--prefix", default="aware", help="topic prefix (default aware)")
    p.add_argument("--records", type=int, default=5000, help="records for the throughput run")
    p.add_argument("--samples", type=int, default=1000, help="records timed by the paced run")
    p.add_argument("--rate", type=float, default=100.0, help="records/s of the paced run")
    p.add_argument("--deployment", default="grid_small", help="fleet for the end-to-end run")
    p.add_argument("--duration", type=float, default=40.0, help="emulated seconds end to end")
    p.add_argument("--period", type=float, default=1.0, help="channel period, s")
    p.add_argument("--speed", type=float, default=1.0, help="emulation speed factor")
    p.add_argument("--no-fleet", action="store_true", help="only the throughput run")


def run(args: argparse.Namespace) -> dict[str, Any]:
    return asyncio.run(_main(args))


def percentile(xs: list[float], q: float) -> float | None:
    if not xs:
        return None
    if len(xs) == 1:
        return xs[0]
    return statistics.quantiles(xs, n=100, method="inclusive")[max(0, min(98, round(q) - 1))]


@contextlib.asynccontextmanager
async def broker_url(url: str | None) -> AsyncIterator[str]:
    if url:
        yield url
        return
    async with EmbeddedBroker() as b:
        yield b.url


@dataclass
class _Arrivals:
    times: dict[str, float]
    event: asyncio.Event


async def _subscriber(url: str, topic: str, ready: asyncio.Event, out: _Arrivals) -> None:
    s = MqttSettings.from_url(url)
    async with s.client(f"awaremw-bench-sub-{id(out):x}") as c:
        await c.subscribe(topic, qos=1)
        ready.set()
        async for m in c.messages:
            now = time.monotonic()
            if not m.topic.matches(topic):
                continue  # amqtt 0.12 also sends retained messages of others' filters
            payload = m.payload if isinstance(m.payload, bytes) else b""
            with contextlib.suppress(ValueError):
                doc = json.loads(payload)
                key = f"{m.topic.value}/{doc['epoch']}"
                out.times.setdefault(key, now)
                out.event.set()


@contextlib.asynccontextmanager
async def _gateway_and_subscriber(
    url: str, sub_url: str, prefix: str, client_id: str
) -> AsyncIterator[tuple[GatewayService, _Arrivals]]:
    """A gateway service (no motes) connected to the broker at ``url``, and a
    subscriber to its data topics recording arrival times, both ready."""
    svc = GatewayService(
        [0],
        settings=GatewaySettings(prefix=prefix),
        mqtt=MqttSettings.from_url(url, client_id=client_id, persistent_session=False),
    )
    svc.bind(lambda node, inj: None, lambda: 0.0)
    arrivals = _Arrivals({}, asyncio.Event())
    ready = asyncio.Event()
    sub = asyncio.create_task(_subscriber(sub_url, f"{prefix}/data/#", ready, arrivals))
    try:
        await asyncio.wait_for(ready.wait(), 10)
        async with svc:
            assert svc.mqtt is not None
            await asyncio.wait_for(svc.mqtt.connected.wait(), 10)
            yield svc, arrivals
    finally:
        sub.cancel()
        with contextlib.suppress(asyncio.CancelledError, aiomqtt.MqttError):
            await sub


async def _throughput(url: str, sub_url: str, prefix: str, n: int) -> tuple[float, str]:
    async with _gateway_and_subscriber(url, sub_url, prefix, "awaremw-bench-gw") as (svc, arr):
        t0 = time.monotonic()
        for i in range(n):
            rec = DataRecord(1, 1, 1 + i % 16, i, 0, float(i), 1, 1)
            svc.on_event(0, Delivered(0, rec, 0, float(i)), float(i))
            if i % 200 == 199:
                await asyncio.sleep(0)  # let the sender and subscriber run
        while len(arr.times) < n:
            arr.event.clear()
            await asyncio.wait_for(arr.event.wait(), 30)
        elapsed = time.monotonic() - t0
        assert svc.mqtt is not None
        return n / elapsed, svc.mqtt.stats.protocol


async def _paced(
    url: str, sub_url: str, prefix: str, n: int, rate: float
) -> tuple[list[float], str]:
    """Bridge latencies (s) of ``n`` records handed to the gateway ``rate`` per second."""
    if n < 1 or not rate > 0:
        raise ValueError("--samples must be >= 1 and --rate > 0")
    sent: dict[str, float] = {}
    async with _gateway_and_subscriber(url, sub_url, prefix, "awaremw-bench-paced") as (svc, arr):
        t0 = time.monotonic()
        for i in range(n):
            # Group id 2 (the throughput run uses 1..16 on channel 1): channel 2 here.
            rec = DataRecord(2, 1, 2, i, 0, float(i), 1, 1)
            due = t0 + i / rate
            if (wait := due - time.monotonic()) > 0:
                await asyncio.sleep(wait)
            sent[f"{prefix}/data/2/1/2/{i}"] = time.monotonic()
            svc.on_event(0, Delivered(0, rec, 0, float(i)), float(i))
        deadline = time.monotonic() + 30.0
        while len(arr.times) < n and time.monotonic() < deadline:
            arr.event.clear()
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(arr.event.wait(), 1.0)
        if len(arr.times) < n:
            raise RuntimeError(f"bench bridge: {len(arr.times)} of {n} paced records arrived")
        assert svc.mqtt is not None
        return [arr.times[k] - sent[k] for k in sent], svc.mqtt.stats.protocol


async def _main(args: argparse.Namespace) -> dict[str, Any]:
    out: dict[str, Any] = {
        "latency_p50_ms": None,
        "latency_p99_ms": None,
        "delivery_p50_ms": None,
        "delivery_p99_ms": None,
        "latency_records": 0,
        "deployment": None if args.no_fleet else args.deployment,
        "period_s": args.period,
        "speed": args.speed,
    }
    async with broker_url(args.mqtt) as url:
        if args.mqtt is not None and (why := await mqtt_problem(url)) is not None:
            raise ValueError(why)  # one line, the password masked
        masked = mask_url(MqttSettings.from_url(url).url)
        out["broker"] = "embedded" if args.mqtt is None else masked
        sub_url = args.sub_mqtt or url
        if not args.no_fleet:
            lat, dlv = await end_to_end(
                url, sub_url, args.prefix, args.deployment, args.duration, args.period, args.speed
            )
            out["latency_records"] = len(lat)
            out["latency_p50_ms"] = _ms(percentile(lat, 50))
            out["latency_p99_ms"] = _ms(percentile(lat, 99))
            out["delivery_p50_ms"] = _ms(percentile(dlv, 50))
            out["delivery_p99_ms"] = _ms(percentile(dlv, 99))
        paced, _ = await _paced(url, sub_url, args.prefix, args.samples, args.rate)
        out["bridge_p50_ms"] = _ms(percentile(paced, 50))
        out["bridge_p99_ms"] = _ms(percentile(paced, 99))
        out["bridge_max_ms"] = _ms(max(paced))
        out["bridge_samples"] = len(paced)
        out["bridge_rate_per_s"] = args.rate
        rate, proto = await _throughput(url, sub_url, args.prefix, args.records)
        out["records_per_s"] = round(rate, 1)
        out["throughput_records"] = args.records
        out["mqtt_protocol"] = proto
    return out


async def end_to_end(
    url: str,
    sub_url: str,
    prefix: str,
    deployment: str,
    duration: float,
    period: float,
    speed: float,
    warmup: float = 10.0,
) -> tuple[list[float], list[float]]:
    """Latencies (sample -> subscriber) and delivery times (record -> subscriber), s.

    The sensor motes and the gateway mote run in two fleets of this process
    (two Zenoh sessions on loopback, as in separate processes); the group type
    is "temperature > -100" (every mote with a thermometer), the channel the
    average temperature every ``period`` seconds. Records whose epoch starts
    before ``warmup`` (tree and group forming) are not measured.
    """
    from awaremw.gateway.service import attach_to_fleet
    from awaremw.nodes import KindsFactory, kind_names
    from awaremw.protocol.events import RecordProduced
    from awaremw.runtime.deployment import load
    from awaremw.runtime.fleet import Fleet, FleetSettings
    from awaremw.runtime.zenoh_session import free_tcp_endpoint

    dep = load(deployment, kind_names())
    ep = free_tcp_endpoint()
    produced: dict[tuple[int, int, int, int], float] = {}  # -> monotonic time
    arrivals = _Arrivals({}, asyncio.Event())

    def on_event(node: int, ev: object, now: float) -> None:
        if isinstance(ev, RecordProduced):
            r = ev.record
            produced.setdefault((r.channel, r.group_type, r.group_id, r.epoch), time.monotonic())

    ready = asyncio.Event()
    sub = asyncio.create_task(_subscriber(sub_url, f"{prefix}/data/#", ready, arrivals))
    try:
        await asyncio.wait_for(ready.wait(), 10)
        factory = KindsFactory()
        sensors = Fleet(
            dep,
            factory,
            FleetSettings(name="bench-sensors", speed=speed, listen=(ep,), control=False),
            node_filter=lambda s: s.kind != "gateway",
        )
        async with sensors:
            sensors.on_event(on_event)
            gw = Fleet(
                dep,
                factory,
                FleetSettings(
                    name="bench-gateway",
                    speed=speed,
                    connect=(ep,),
                    start_wall=sensors.clock.start_wall,
                    control=False,
                ),
                node_filter=lambda s: s.kind == "gateway",
            )
            async with gw:
                svc = attach_to_fleet(
                    gw,
                    settings=GatewaySettings(prefix=prefix),
                    mqtt=MqttSettings.from_url(
                        url, client_id="awaremw-bench-e2e", persistent_session=False
                    ),
                    hbn=False,
                )
                async with svc:
                    group = {"conditions": [{"attr": "temperature", "op": ">", "value": -100}]}
                    chan = {"attr": "temperature", "group_type": 1, "period_s": period}
                    for rel, doc in (("def/group/1", group), ("def/channel/1", chan)):
                        out = svc.handle(rel, json.dumps(doc).encode())
                        if out.error is not None:
                            raise RuntimeError(f"bench definition refused: {out.error.error}")
                    await sensors.run(duration)
                    sensors.raise_errors()
                    gw.raise_errors()
            clock = sensors.clock
    finally:
        sub.cancel()
        with contextlib.suppress(asyncio.CancelledError, aiomqtt.MqttError):
            await sub
    latencies, deliveries = [], []
    for key, t_arr in arrivals.times.items():
        # key: "<prefix>/data/<channel>/<type>/<group_id>/<epoch>"
        *_, ch, gt, gid, ep_s = key.split("/")
        epoch = int(ep_s)
        if epoch * period < warmup:
            continue
        latencies.append(t_arr - clock.to_monotonic(epoch * period))
        t_prod = produced.get((int(ch), int(gt), int(gid), epoch))
        if t_prod is not None:
            deliveries.append(t_arr - t_prod)
    return latencies, deliveries


def _ms(x: float | None) -> float | None:
    return None if x is None else round(x * 1000.0, 2)
