"""Run a scenario in real time: fleets over Zenoh, the gateway, MQTT.

The product's main mode, as a robot would meet it. In one process (so that
the experiment can also observe the motes' events for the metrics):

* three Zenoh sessions on loopback, multicast scouting off, explicit
  endpoints: the **field** (the sensing motes; listens on a free port), the
  **robot** (its mote) and the **gateway** (its mote); the latter two connect
  to the field, so every frame between the robot, the field and the gateway
  travels over Zenoh;
* the gateway service on the gateway mote (:func:`attach_to_fleet`), bridged
  to an MQTT broker: the embedded one (amqtt) unless a URL is given;
* the robot's client (:class:`~awaremw.experiments.client.RobotClient`),
  which at ``define_at_s`` publishes the scenario's group and channel
  definitions over MQTT and collects the records it receives.

All fleets share one time origin and speed factor. Records count as arrived
when the MQTT subscriber receives them (at the fleet's emulated time of that
moment), not when the gateway mote does.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

from awaremw.experiments.client import GroupSeen, Received, RobotClient, definition_payloads
from awaremw.experiments.metrics import Recorder, RunResult
from awaremw.experiments.scenario import Scenario
from awaremw.gateway.mqtt import MqttSettings
from awaremw.nodes import KindsFactory, app_of
from awaremw.protocol.attributes import rssi_attribute
from awaremw.protocol.core import MoteCore
from awaremw.protocol.events import EventHook, MoteEvent
from awaremw.protocol.mote import AwareMote
from awaremw.runtime.deployment import Deployment, NodeSpec
from awaremw.runtime.zenoh_session import SessionSettings, free_tcp_endpoint

log = logging.getLogger(__name__)


@dataclass
class LiveState:
    """What a view may show while a real-time run goes on (updated in place)."""

    records: list[Received] = field(default_factory=list)
    groups: dict[tuple[int, int], GroupSeen] = field(default_factory=dict)
    errors: list[str] = field(default_factory=list)


Tick = Callable[[float, "RealtimeRun"], None]


@dataclass(frozen=True, slots=True)
class RealtimeSettings:
    """How a real-time run goes: speed factor, MQTT broker and prefix, sampling."""

    speed: float = 1.0
    mqtt: str | None = None  # broker URL; None: start the embedded broker
    # The broker at ``mqtt`` was started empty for this run (the demo's embedded
    # one): every retained definition on it is this run's, even one published
    # before the gateway subscribed (a dashboard's first click).
    fresh_broker: bool = False
    robot_mqtt: str | None = None  # the client's own account (default: mqtt's)
    prefix: str = "aware"
    sample_dt: float = 0.5  # emulated seconds between ticks (RSSI samples, views)
    # A secrets directory (`awaremw keys init`): an embedded router with its access
    # rules; the motes and the gateway connect to it with their roles; the radio is
    # authenticated with its network key and the gateway's motes sign their items.
    secrets: str | None = None
    # A capture of the radio (awaremw.radio.capture): every fleet's medium taps it.
    pcap: str | None = None
    # (host, port) of the metrics endpoint (/metrics, /healthz, /readyz;
    # docs/monitoring.md): the gateway's figures and every fleet's, together.
    metrics: tuple[str, int] | None = None

    def __post_init__(self) -> None:
        if not self.speed > 0:
            raise ValueError(f"speed must be > 0, got {self.speed}")


@dataclass(frozen=True, slots=True)
class RunHooks:
    """What the caller (a view, the demo) wants to hear about while the run goes on."""

    on_tick: Tick | None = None  # every sample_dt, with the run
    on_record: Callable[[Received], None] | None = None  # a record reached the robot
    on_event: EventHook | None = None  # every mote event


class RealtimeRun:
    """Set up, run and tear down one real-time run of a scenario."""

    def __init__(
        self,
        sc: Scenario,
        settings: RealtimeSettings | None = None,
        *,
        recorder: Recorder | None = None,
        hooks: RunHooks | None = None,
    ) -> None:
        self.sc = sc
        self.settings = s = settings or RealtimeSettings()
        self.speed = s.speed
        self.prefix = s.prefix
        self.recorder = recorder or Recorder(record_sources=("mqtt",))
        self.hooks = hooks or RunHooks()
        self.secrets = s.secrets
        self.live = LiveState()
        self.fleets: list[object] = []
        self.client: RobotClient | None = None
        self.broker_url: str | None = None

    # ------------------------------------------------------------------ helpers

    def _factory(self, name: str = "field") -> KindsFactory:
        """The core factory of one fleet: with secrets, the radio secured and, for
        the gateway's fleet only, the signing key (its motes sign the items)."""
        if self.secrets is None:
            return KindsFactory(self.sc.world)
        from awaremw.security.material import load_radio_security, load_signing_key

        security = load_radio_security(self.secrets)
        key = None
        if name == "gateway":
            key = load_signing_key(self.secrets, security.gateway_public_key)
        return KindsFactory(self.sc.world, security=security, signing_key=key)

    def _session_settings(self, name: str, endpoint: str) -> SessionSettings | None:
        if self.secrets is None:
            return None
        from awaremw.security.zenoh_acl import role_settings

        return role_settings(Path(self.secrets), "gateway" if name == "gateway" else "fleet",
                             [endpoint])  # fmt: skip

    def now(self) -> float:
        from awaremw.runtime.fleet import Fleet

        f = self.fleets[0]
        assert isinstance(f, Fleet)
        return f.now()

    def cores(self) -> dict[int, MoteCore]:
        from awaremw.runtime.fleet import Fleet

        out: dict[int, MoteCore] = {}
        for f in self.fleets:
            assert isinstance(f, Fleet)
            out.update(f.cores)
        return out

    def forwarders(self) -> set[int]:
        """Motes that acknowledged unicasts so far (data was routed through them)."""
        from awaremw.runtime.fleet import Fleet

        out: set[int] = set()
        for f in self.fleets:
            assert isinstance(f, Fleet)
            out.update(n for n, c in f.counters().items() if c.acks_tx > 0)
        return out

    def traffic(self) -> dict[int, tuple[int, int, float]]:
        from awaremw.runtime.fleet import Fleet

        d = self.sc.deployment
        out: dict[int, tuple[int, int, float]] = {}
        for f in self.fleets:
            assert isinstance(f, Fleet)
            for n, c in f.counters().items():
                txp = d.tx_power_of(d.node(n))
                out[n] = (c.frames_tx, c.frames_rx, c.energy_mj(d.preset, txp))
        return out

    def _sample(self, now: float) -> None:
        rob = self.sc.robot
        if rob is None:
            return
        attr = rssi_attribute(rob)
        cores = self.cores()
        for n in self.sc.get("rssi_motes", []):
            core = cores.get(int(n))
            if isinstance(core, AwareMote):
                self.recorder.on_rssi(int(n), now, core.ctx.read(attr, now))

    def _got_record(self, r: Received) -> None:
        now = self.now()
        self.live.records.append(r)
        self.recorder.on_record(now, r.record, "mqtt")
        if self.hooks.on_record is not None:
            self.hooks.on_record(r)

    def _got_group(self, g: GroupSeen) -> None:
        if g.state is None:
            self.live.groups.pop((g.group_type, g.group_id), None)
        else:
            self.live.groups[(g.group_type, g.group_id)] = g

    # ------------------------------------------------------------------ the run

    async def run(self, duration: float | None = None) -> RunResult:
        from awaremw.gateway.broker import EmbeddedBroker
        from awaremw.gateway.service import GatewaySettings, attach_to_fleet
        from awaremw.ops.metrics import show_gateway, starting_endpoint
        from awaremw.runtime.fleet import Fleet, FleetSettings
        from awaremw.runtime.fleet.stats import FleetSnapshot, merge_snapshots

        sc = self.sc
        d = sc.deployment
        end = sc.duration if duration is None else duration
        started = time.monotonic()
        async with contextlib.AsyncExitStack() as stack:
            url = self.settings.mqtt
            fresh = self.settings.fresh_broker or url is None
            if url is None:
                broker = await stack.enter_async_context(EmbeddedBroker())
                url = broker.url
            self.broker_url = url
            gw_mqtt = MqttSettings.from_url(url, client_id=f"awaremw-gw-{id(self):x}",
                                            prefix=self.prefix)  # fmt: skip
            ops = None
            if self.settings.metrics is not None:  # up first: not ready until the gateway is
                ops = await stack.enter_async_context(starting_endpoint(self.settings.metrics))
                print(f"metrics: {ops.url}/metrics (/healthz, /readyz)", flush=True)
            endpoint = free_tcp_endpoint()
            if self.secrets is not None:
                from awaremw.runtime.router import EmbeddedRouter
                from awaremw.security.zenoh_acl import router_config_path

                router = EmbeddedRouter(
                    [endpoint], config_file=str(router_config_path(Path(self.secrets)))
                )
                await asyncio.to_thread(router.start)
                stack.callback(router.close)
            groups: tuple[tuple[str, Callable[[NodeSpec], bool], list[str], list[str]], ...] = (
                ("field", lambda s: s.kind not in ("robot", "gateway"), [endpoint], []),
                ("robot", lambda s: s.kind == "robot", [], [endpoint]),
                ("gateway", lambda s: s.kind == "gateway", [], [endpoint]),
            )
            fleets: list[Fleet] = []
            for name, flt, listen, connect in groups:
                if not any(flt(s) for s in d.nodes):
                    continue
                factory = self._factory(name)
                settings = FleetSettings(
                    name=name,
                    speed=self.speed,
                    listen=tuple(listen),
                    connect=tuple(connect),
                    autostart=False,
                    control=False,
                    session=self._session_settings(name, endpoint),
                    security=factory.security,
                    figures=ops is not None,
                )
                f = Fleet(d, factory, settings, node_filter=flt)
                await stack.enter_async_context(f)
                f.on_event(self.recorder.on_event)
                if self.hooks.on_event is not None:
                    f.on_event(self.hooks.on_event)
                fleets.append(f)
            self.fleets = list(fleets)
            gw_fleet = next(f for f in fleets if f.name == "gateway")
            # A run starts from its scenario, never from what a broker retained before
            # it: on a broker it did not start, of the retained definitions it takes
            # only its own (they may be retained before the gateway subscribes).
            own = None if fresh else frozenset(definition_payloads(sc.group_json, sc.channel_json))
            gw_settings = GatewaySettings(prefix=self.prefix, retained_only=own)
            svc = attach_to_fleet(gw_fleet, settings=gw_settings, mqtt=gw_mqtt, hbn=True)
            await stack.enter_async_context(svc)
            if ops is not None:  # the gateway's figures and every fleet's, merged

                def merged() -> FleetSnapshot:
                    return merge_snapshots(f.stats.snapshot(window=False) for f in fleets)

                show_gateway(ops, svc, merged, motes_ready=True)
            for f in fleets:
                for n, r in f.runners.items():
                    app = app_of(r.core)
                    if app is not None:
                        app.energy = _energy_probe(f, d, n)
            capture = None
            if self.settings.pcap is not None:
                from awaremw.radio.capture import Capture

                capture = Capture.to_file(self.settings.pcap)
                stack.callback(capture.close)
                for f in fleets:
                    f.medium.tap = capture
            # Let the Zenoh peers find each other before time 0.
            await asyncio.sleep(0.3)
            start_wall = time.time() + 0.1
            if capture is not None:
                capture.epoch = start_wall
            for f in fleets:
                f.start(start_wall)
            client_settings = (
                MqttSettings.from_url(self.settings.robot_mqtt, prefix=self.prefix)
                if self.settings.robot_mqtt is not None
                else gw_mqtt
            )
            client_settings = replace(client_settings, client_id=f"awaremw-robot-{id(self):x}")
            self.client = RobotClient(
                client_settings, sc.group_json, sc.channel_json,
                on_record=self._got_record, on_group=self._got_group,
                on_error=self.live.errors.append,
            )  # fmt: skip
            tasks = [
                asyncio.create_task(self._client_task(fleets[0]), name="robot-client"),
                asyncio.create_task(self._ticker(fleets[0], end), name="ticker"),
            ]
            try:
                await fleets[0].run(end)
                for f in fleets:
                    f.raise_errors()
            finally:
                if self.client is not None:
                    self.client.stop()
                # The client leaves cleanly (disconnect) before the broker stops.
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(asyncio.shield(tasks[0]), timeout=2.0)
                for t in tasks:
                    t.cancel()
                for t in tasks:
                    with contextlib.suppress(asyncio.CancelledError):
                        await t
            traffic = self.traffic()
        log.info("real-time run of %s: %.1f s wall", sc.name, time.monotonic() - started)
        return RunResult(sc, self.recorder, end, traffic, mode="realtime", speed=self.speed)

    async def _client_task(self, fleet: object) -> None:
        from awaremw.runtime.fleet import Fleet

        assert isinstance(fleet, Fleet) and self.client is not None
        await fleet.wait_until(self.sc.define_at)
        try:
            await self.client.run()
        except Exception as e:  # the broker went away: the run goes on, report it
            log.error("robot client stopped: %s", e)
            self.live.errors.append(f"robot client: {e}")

    async def _ticker(self, fleet: object, end: float) -> None:
        from awaremw.runtime.fleet import Fleet

        assert isinstance(fleet, Fleet)
        t = 0.0
        while t <= end:
            await fleet.wait_until(t)
            now = fleet.now()
            self._sample(now)
            if self.hooks.on_tick is not None:
                self.hooks.on_tick(now, self)
            t += self.settings.sample_dt


def _energy_probe(fleet: object, d: Deployment, node: int) -> Callable[[], float]:
    from awaremw.runtime.fleet import Fleet

    assert isinstance(fleet, Fleet)
    txp = d.tx_power_of(d.node(node))

    def probe() -> float:
        c = fleet.counters().get(node)
        return 0.0 if c is None else c.energy_mj(d.preset, txp) / 1000.0

    return probe


def run_realtime(
    sc: Scenario,
    speed: float = 1.0,
    duration: float | None = None,
    mqtt: str | None = None,
    plain: bool = True,
    robot_mqtt: str | None = None,
    secrets: str | None = None,
    pcap: str | None = None,
) -> RunResult:
    """Blocking helper for the CLI: one real-time run, shown live on a terminal
    (``plain`` False and stdout a TTY) or as status log lines."""
    import sys

    from awaremw.experiments.snapshot import snapshot_of
    from awaremw.view.live import LiveView, PlainLog, View, describe

    view: View = LiveView() if not plain and sys.stdout.isatty() else PlainLog(every=10.0)

    def tick(now: float, run: RealtimeRun) -> None:
        view.update(
            snapshot_of(sc, run.recorder, now, run.live, run.traffic(), forwarders=run.forwarders())
        )

    def event(node: int, ev: MoteEvent, t: float) -> None:
        line = describe(node, ev, t)
        if line is not None:
            view.log(t, line)

    rt = RealtimeRun(
        sc,
        RealtimeSettings(speed=speed, mqtt=mqtt, robot_mqtt=robot_mqtt, secrets=secrets, pcap=pcap),
        hooks=RunHooks(on_tick=tick, on_event=event),
    )
    view.start()
    try:
        return asyncio.run(rt.run(duration))
    finally:
        view.stop()
