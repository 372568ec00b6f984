"""End to end: a real fleet, a real gateway, real brokers (Mosquitto, amqtt) and Zenoh.

The sensor motes of ``grid_small`` (25 tmotes, 5 x 5 grid) run in one Fleet
that listens on a loopback endpoint; the gateway mote runs in a second Fleet
(its own Zenoh session, as in a separate gateway process) with the gateway
service on top, or as an ``awaremw gateway`` subprocess for the restart test.
Every temperature reading a mote takes is logged, so records can be checked
against what the motes sampled.

Group type 1 is "x > 3": every sensor mote (the gateway mote stands at x = 1),
so one group forms and its leader's records travel the collection tree.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import json
import math
import os
import signal
import statistics
import sys
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
import zenoh
from mosquitto import (  # noqa: F401
    Collector,
    Mosquitto,
    MosquittoSub,
    mosquitto_fixture,
    pub,
    require,
)

from awaremw.cli.client import publish as client_publish
from awaremw.gateway.broker import EmbeddedBroker
from awaremw.gateway.events import Publish
from awaremw.gateway.mqtt import MqttSettings
from awaremw.gateway.service import GatewayService, GatewaySettings, attach_to_fleet
from awaremw.nodes import KindsFactory, app_of, build_core, kind_names, world_of
from awaremw.protocol.attributes import TEMPERATURE
from awaremw.protocol.core import MoteCore
from awaremw.protocol.events import CommandExecuted, ItemAdopted
from awaremw.protocol.frames import ItemKind
from awaremw.runtime.deployment import Deployment, NodeSpec, load
from awaremw.runtime.fleet import Fleet, FleetSettings
from awaremw.runtime.zenoh_session import free_tcp_endpoint

pytestmark = [pytest.mark.zenoh, pytest.mark.slow]

SPEED = 4.0  # emulated seconds per wall second
ROUND_S = 4.0  # one dissemination round over the grid (Trickle tau_l = 1 s, a few hops)
GROUP = json.dumps({"conditions": [{"attr": "x", "op": ">", "value": 3}]})


def channel(period: float, attr: str = "temperature", agg: str = "avg") -> str:
    return json.dumps(
        {"attr": attr, "group_type": 1, "group_id": "*", "period_s": period, "agg": agg}
    )


@dataclass
class Emulation:
    dep: Deployment
    sensors: Fleet
    endpoint: str
    samples: list[tuple[int, float, float]] = field(default_factory=list)  # (node, t, degC)
    adopted: dict[tuple[ItemKind, int, int], dict[int, float]] = field(default_factory=dict)
    commands: list[tuple[int, CommandExecuted]] = field(default_factory=list)
    _news: asyncio.Event = field(default_factory=asyncio.Event)

    async def wait(self, cond: Callable[[], bool], timeout: float = 30.0) -> None:
        async def loop() -> None:
            while not cond():
                self._news.clear()
                await self._news.wait()

        await asyncio.wait_for(loop(), timeout)

    def now(self) -> float:
        return self.sensors.now()

    def on_event(self, node: int, ev: object, now: float) -> None:
        if isinstance(ev, CommandExecuted):
            self.commands.append((node, ev))
            self._news.set()
        if isinstance(ev, ItemAdopted):
            self.adopted.setdefault((ev.kind, ev.item_id, ev.version), {})[node] = now
            self._news.set()

    async def round_done(self, kind: ItemKind, item_id: int, version: int) -> float:
        """Emulated time by which every sensor mote held this version (one round)."""
        n = sum(1 for s in self.dep.nodes if s.kind != "gateway")

        async def wait() -> None:
            while len(self.adopted.get((kind, item_id, version), {})) < n:
                self._news.clear()
                await self._news.wait()

        await asyncio.wait_for(wait(), 30)
        return max(self.adopted[(kind, item_id, version)].values())


def logging_factory(
    dep: Deployment, samples: list[tuple[int, float, float]]
) -> Callable[[NodeSpec, Deployment], MoteCore]:
    world = world_of(dep)

    def factory(spec: NodeSpec, d: Deployment) -> MoteCore:
        core = build_core(spec, d, world)
        app = app_of(core)
        if app is not None:
            read = app.read

            def logged(attr: int, now: float) -> float | None:
                v = read(attr, now)
                if attr == TEMPERATURE and v is not None:
                    samples.append((spec.id, now, v))
                return v

            app.read = logged  # type: ignore[method-assign]
        return core

    return factory


@asynccontextmanager
async def sensor_fleet() -> AsyncIterator[Emulation]:
    # The radio before collisions (mac = "aloha", collisions = "none"), as the
    # lossless Scenario harness: these tests check records against the motes'
    # samples exactly, which needs epochs where every partial arrived; what
    # collisions do to aggregation is measured by the experiments (issue 13).
    dep = dataclasses.replace(load("grid_small", kind_names()), mac="aloha", collisions="none")
    ep = free_tcp_endpoint()
    samples: list[tuple[int, float, float]] = []
    async with Fleet(
        dep,
        logging_factory(dep, samples),
        FleetSettings(name="sensors", speed=SPEED, listen=(ep,)),
        node_filter=lambda s: s.kind != "gateway",
    ) as fleet:
        emu = Emulation(dep, fleet, ep, samples)
        fleet.on_event(emu.on_event)
        yield emu


@asynccontextmanager
async def gateway(
    emu: Emulation, mqtt: MqttSettings | None, state_dir: Path | None = None
) -> AsyncIterator[GatewayService]:
    fleet = Fleet(
        emu.dep,
        KindsFactory(),
        FleetSettings(
            name="gateway",
            speed=SPEED,
            connect=(emu.endpoint,),
            start_wall=emu.sensors.clock.start_wall,
            control=False,
        ),
        node_filter=lambda s: s.kind == "gateway",
    )
    async with fleet:
        svc = attach_to_fleet(fleet, settings=GatewaySettings(state_dir=state_dir), mqtt=mqtt)
        async with svc:
            if svc.mqtt is not None:
                await asyncio.wait_for(svc.mqtt.connected.wait(), 10)
            yield svc


def records(lines: list[tuple[str, str]], ch: int | None = None) -> list[dict[str, Any]]:
    out = []
    for topic, payload in lines:
        parts = topic.split("/")
        if len(parts) >= 5 and parts[-4] == "data" and (ch is None or int(parts[-3]) == ch):
            out.append({**json.loads(payload), "channel": int(parts[-3]), "group": int(parts[-1])})
    return out


def check_against_samples(
    recs: list[dict[str, Any]], samples: list[tuple[int, float, float]], period: float
) -> int:
    """Every record agrees with the readings of its epoch; returns how many were complete
    (every sample of the epoch aggregated) and so checked exactly."""
    complete = 0
    for r in recs:
        e = r["epoch"]
        window = [v for _, t, v in samples if e * period - 1e-6 <= t < (e + 1) * period]
        assert window, f"no mote sampled in epoch {e}: {r}"
        assert 1 <= r["count"] <= len(window), (r, len(window))
        assert min(window) - 1e-3 <= r["value"] <= max(window) + 1e-3, (r, window)
        if r["count"] == len(window):
            assert r["value"] == pytest.approx(statistics.fmean(window), rel=1e-5, abs=1e-3)
            complete += 1
    return complete


def is_period(r: dict[str, Any], period: float, late: float = 0.5) -> bool:
    """Whether a record's epoch matches ``period`` (its epoch start is just before t:
    within the epoch and ``late`` emulated seconds of delivery)."""
    return -0.5 <= r["t"] - r["epoch"] * period <= period + late


# --------------------------------------------------------------------------- Mosquitto


@pytest.mark.mosquitto
async def test_mosquitto_define_change_delete(mosquitto: Mosquitto) -> None:
    settings = MqttSettings.from_url(mosquitto.url("gateway"), reconnect_min_s=0.05)
    async with (
        sensor_fleet() as emu,
        gateway(emu, settings) as svc,
        MosquittoSub(mosquitto, "viewer", "aware/#") as sub,
    ):
        assert pub(mosquitto, "operator", "aware/def/group/1", GROUP).returncode == 0
        assert pub(mosquitto, "operator", "aware/def/channel/1", channel(1.0)).returncode == 0

        # Aggregated records on aware/data, matching what the motes sampled.
        def full(ls: list[tuple[str, str]]) -> bool:
            return sum(1 for r in records(ls, 1) if r["count"] >= 20) >= 4

        await sub.wait_for(full, timeout=40)
        recs = records(sub.lines, 1)
        assert all(r["agg"] == "avg" and r["attr"] == "temperature" for r in recs)
        assert check_against_samples(recs, emu.samples, 1.0) >= 1
        assert any(t.startswith("aware/groups/1/") for t, _ in sub.lines)

        # Malformed payloads: refused with a reason, the channel keeps running as it was.
        n_err = sum(1 for t, _ in sub.lines if t == "aware/errors")
        pub(mosquitto, "operator", "aware/def/channel/1", '{"attr": "temperature", "period_s": 0}')
        pub(mosquitto, "operator", "aware/def/channel/1", b"\xff")
        await sub.wait_for(lambda ls: sum(1 for t, _ in ls if t == "aware/errors") >= n_err + 2)
        errs = [json.loads(p) for t, p in sub.lines if t == "aware/errors"][n_err:]
        assert [e["code"] for e in errs] == ["period_out_of_range", "invalid_utf8"]
        assert svc.bridge.definitions()["def/channel/1"]["period_s"] == 1.0

        # Period 1 s -> 2 s: the records follow within one dissemination round -- from
        # the first epoch boundary after every mote holds the new version.
        pub(mosquitto, "operator", "aware/def/channel/1", channel(2.0))
        done = await emu.round_done(ItemKind.CHANNEL, 1, 2)
        await sub.wait_for(lambda ls: any(r["t"] > done + 8.0 for r in records(ls, 1)), 40)
        # Arriving after the next epoch boundary and one more epoch: new period only.
        after = [r for r in records(sub.lines, 1) if r["t"] > done + 2.0 * 2.0]
        assert after and all(is_period(r, 2.0) and not is_period(r, 1.0) for r in after), after
        first_new = min(r["epoch"] for r in records(sub.lines, 1) if is_period(r, 2.0)) * 2.0
        assert first_new <= math.floor(done / 2.0) * 2.0 + 2.0, (done, first_new)

        # Delete channel 1; channel 2 (max of x) shows that time passes and data flows.
        pub(mosquitto, "operator", "aware/def/channel/1", None)
        pub(mosquitto, "operator", "aware/def/channel/2", channel(1.0, "x", "max"))
        gone = await emu.round_done(ItemKind.CHANNEL, 1, 3)
        await sub.wait_for(lambda ls: any(r["t"] > gone + 4.0 for r in records(ls, 2)), 40)
        assert not [r for r in records(sub.lines, 1) if r["t"] > gone + 2.0 * 2.0]
        xs = [s.position[0] for s in emu.dep.nodes if s.kind != "gateway"]
        for r in records(sub.lines, 2):
            assert r["value"] in [pytest.approx(x, abs=1e-3) for x in xs]
            if r["count"] == len(xs):
                assert r["value"] == pytest.approx(max(xs), abs=1e-3)


@pytest.mark.mosquitto
async def test_broker_restart_while_data_flows(mosquitto: Mosquitto) -> None:
    settings = MqttSettings.from_url(
        mosquitto.url("gateway"), reconnect_min_s=0.05, reconnect_max_s=0.3
    )
    async with (
        sensor_fleet() as emu,
        gateway(emu, settings) as svc,
        Collector(mosquitto.url("viewer"), "aware/data/#") as sub,
    ):
        assert svc.mqtt is not None
        pub(mosquitto, "operator", "aware/def/group/1", GROUP)
        pub(mosquitto, "operator", "aware/def/channel/1", channel(1.0))

        # What the gateway publishes, in order (the reference for the subscriber).
        sent: list[tuple[str, bytes]] = []
        publish = svc.publish

        def spy(p: Publish) -> None:
            if p.topic.startswith("data/"):
                sent.append((f"aware/{p.topic}", p.payload))
            publish(p)

        svc.publish = spy  # type: ignore[method-assign]

        def got() -> list[tuple[str, bytes]]:
            return [(t, p) for t, p, _ in sub.messages]

        await sub.until(lambda: len(got()) >= 3, 40)
        mosquitto.kill()
        before_kill = len(sent)
        await asyncio.wait_for(svc.mqtt.disconnected.wait(), 10)
        # Records keep coming from the network while the broker is away.
        during = len(sent) + 3

        async def records_in() -> None:
            while len(sent) < during:
                svc.delivered.clear()
                await svc.delivered.wait()

        await asyncio.wait_for(records_in(), 20)
        assert svc.mqtt.backlog >= 3
        mosquitto.lock_out("gateway")  # until our subscriber is back (see test_gateway_mqtt)
        mosquitto.start()
        await sub.until(lambda: sub.subscribes >= 2)
        mosquitto.let_in()
        await asyncio.wait_for(svc.mqtt.connected.wait(), 10)
        target = len(sent)
        await sub.until(lambda: len(got()) >= target, 20)
        # Everything the gateway produced before, during and after the outage
        # arrives, in order. QoS 1 is at-least-once: a record in flight when the
        # broker died (published, PUBACK never back) is sent again after the
        # reconnect and counted in stats.resent -- only those may repeat, and the
        # records produced while the broker was away arrive exactly once.
        await sub.until(lambda: len(dict.fromkeys(got())) >= target, 20)
        received = got()
        assert list(dict.fromkeys(received))[:target] == sent[:target]
        repeats = len(received) - len(set(received))
        assert repeats <= svc.mqtt.stats.resent
        outage = sent[before_kill:target]
        assert len(outage) >= 3
        assert all(received.count(r) == 1 for r in outage)
        assert svc.mqtt.stats.dropped == 0


# --------------------------------------------------------------------------- gateway restart


def gateway_cmd(emu: Emulation, m: Mosquitto, state: Path) -> list[str]:
    return [
        sys.executable,
        "-m",
        "awaremw",
        "gateway",
        "grid_small",
        "--connect",
        emu.endpoint,
        "--mqtt",
        m.url("gateway"),
        "--state-dir",
        str(state),
        "--speed",
        str(SPEED),
        "--start-wall",
        repr(emu.sensors.clock.start_wall),
    ]


async def start_gateway(cmd: list[str]) -> asyncio.subprocess.Process:
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    return await asyncio.create_subprocess_exec(
        *cmd, stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.DEVNULL, env=env
    )


@pytest.mark.mosquitto
async def test_gateway_killed_and_restarted(mosquitto: Mosquitto, tmp_path: Path) -> None:
    require("mosquitto_sub")
    async with sensor_fleet() as emu, MosquittoSub(mosquitto, "viewer", "aware/#") as sub:
        cmd = gateway_cmd(emu, mosquitto, tmp_path)
        gw = await start_gateway(cmd)
        try:
            await sub.wait_for(lambda ls: ("aware/gateway/status", "online") in ls, 30)
            pub(mosquitto, "operator", "aware/def/group/1", GROUP)
            pub(mosquitto, "operator", "aware/def/channel/1", channel(1.0))
            pub(mosquitto, "operator", "aware/def/channel/1", channel(1.5))  # version 2
            await sub.wait_for(
                lambda ls: sum(1 for r in records(ls, 1) if is_period(r, 1.5)) >= 2, 40
            )
            gw.send_signal(signal.SIGKILL)
            await gw.wait()
            # The broker tells everyone through the gateway's last will.
            await sub.wait_for(
                lambda ls: (
                    ls[-1:] == [("aware/gateway/status", "offline")]
                    or ("aware/gateway/status", "offline") in ls[-3:]
                ),
                30,
            )
            gw = await start_gateway(cmd)
            n = len(sub.lines)
            await sub.wait_for(lambda ls: ("aware/gateway/status", "online") in ls[n:], 30)
            # An account without write rights is ignored...
            r = pub(mosquitto, "viewer", "aware/def/channel/1", channel(0.5))
            assert b"Not authorized" in r.stderr
            # ...a definition published after the restart takes effect (version 3 > 2:
            # the motes would ignore a gateway that numbered from 1 again).
            t0 = emu.now()
            pub(mosquitto, "operator", "aware/def/channel/1", channel(2.0))
            await sub.wait_for(
                lambda ls: (
                    sum(
                        1
                        for r in records(ls, 1)
                        if r["t"] > t0 and is_period(r, 2.0) and not is_period(r, 1.5)
                    )
                    >= 2
                ),
                40,
            )
            assert not [
                r
                for r in records(sub.lines, 1)
                if r["t"] > t0 + ROUND_S + 1 and is_period(r, 0.5) and not is_period(r, 2.0)
            ]
        finally:
            if gw.returncode is None:
                gw.terminate()
                await gw.wait()


async def test_gateway_without_its_store_learns_the_versions_in_force() -> None:
    """Restarted with its store lost, the gateway learns from its mote what the
    network holds, so a new definition still gets a version the motes accept."""
    async with sensor_fleet() as emu:
        async with gateway(emu, None) as svc:
            svc.handle("def/group/1", GROUP.encode())
            svc.handle("def/channel/1", channel(1.0).encode())
            svc.handle("def/channel/1", channel(1.5).encode())
            await emu.round_done(ItemKind.CHANNEL, 1, 2)
        async with gateway(emu, None) as svc:

            async def learned() -> None:
                while svc.bridge.stats.learned < 2:
                    svc.handled.clear()
                    await svc.handled.wait()

            await asyncio.wait_for(learned(), 30)
            assert svc.bridge.definitions()["def/channel/1"]["version"] == 2
            out = svc.handle("def/channel/1", channel(2.0).encode())
            assert out.inject is not None and out.inject.version == 3
            await emu.round_done(ItemKind.CHANNEL, 1, 3)  # every mote took it


# --------------------------------------------------------------------------- Zenoh, embedded


async def test_zenoh_hbn_define_and_receive() -> None:
    async with sensor_fleet() as emu, gateway(emu, None) as svc:
        session = emu.sensors.session  # a device on the emulation's Zenoh network
        loop = asyncio.get_running_loop()
        got: list[tuple[str, bytes]] = []
        arrived = asyncio.Event()

        def on_data(s: zenoh.Sample) -> None:
            item = (str(s.key_expr), s.payload.to_bytes())
            loop.call_soon_threadsafe(lambda: (got.append(item), arrived.set()))

        sub = session.declare_subscriber("aware/hbn/data/**", on_data)
        try:
            # Retry the puts until the gateway has them (routes come up asynchronously),
            # within a deadline: a gateway that never gets them fails the test.
            async def defined() -> None:
                while "def/channel/1" not in {k for k in svc.bridge.definitions()}:
                    session.put("aware/hbn/def/group/1", GROUP)
                    session.put("aware/hbn/def/channel/1", channel(1.0))
                    svc.handled.clear()
                    with contextlib.suppress(TimeoutError):
                        await asyncio.wait_for(svc.handled.wait(), 0.5)

            await asyncio.wait_for(defined(), 20)

            async def full() -> None:
                while sum(1 for _, p in got if json.loads(p)["count"] >= 20) < 3:
                    arrived.clear()
                    await arrived.wait()

            await asyncio.wait_for(full(), 40)
            recs = [{**json.loads(p), "channel": int(k.split("/")[-3])} for k, p in got]
            assert {k.split("/")[3] for k, _ in got} == {"1"}
            assert check_against_samples(recs, emu.samples, 1.0) >= 1
            defs = await asyncio.to_thread(
                lambda: {
                    str(r.ok.key_expr)
                    for r in session.get("aware/hbn/def/**", timeout=5)
                    if r.ok is not None
                }
            )
            assert defs == {"aware/hbn/def/group/1", "aware/hbn/def/channel/1"}
        finally:
            sub.undeclare()  # type: ignore[no-untyped-call]


async def test_embedded_broker_define_and_receive() -> None:
    async with EmbeddedBroker() as broker:
        settings = MqttSettings.from_url(broker.url)
        async with (
            sensor_fleet() as emu,
            gateway(emu, settings) as svc,
            Collector(broker.url, "aware/data/#", protocol="3.1.1") as sub,
        ):
            assert svc.mqtt is not None and svc.mqtt.stats.protocol == "3.1.1"
            s = MqttSettings.from_url(broker.url)
            await client_publish(s, "def/group/1", GROUP.encode(), retain=True)
            await client_publish(s, "def/channel/1", channel(1.0).encode(), retain=True)
            await sub.wait_for(
                lambda ms: sum(1 for _, p, _ in ms if json.loads(p)["count"] >= 20) >= 3, 40
            )
            recs = [{**json.loads(p), "channel": 1} for _, p, _ in sub.messages]
            assert check_against_samples(recs, emu.samples, 1.0) >= 1
            # A command through the same broker: the node kind's handler runs on mote 7 only.
            cmd = {"target": {"node": 7}, "args": {"color": "red", "state": "on"}}
            await client_publish(s, "cmd/led", json.dumps(cmd).encode(), retain=False)
            await emu.wait(lambda: any(n == 7 for n, _ in emu.commands))
            assert [n for n, c in emu.commands] == [7]
            app = app_of(emu.sensors.runners[7].core)
            assert app is not None and app.leds["red"] is True
