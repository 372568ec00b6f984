"""Run a scenario on the virtual clock (fast, deterministic).

The whole deployment runs on :class:`~awaremw.radio.virtual_medium.VirtualNetwork`
with the cores :func:`awaremw.nodes.build_core` builds (the same as the
fleet's). At ``define_at_s`` the gateway mote is given the scenario's
definitions as the gateway would inject them (versioned Drip items) and the
dissemination spreads them; records are taken where they arrive, at the
gateway mote (``Delivered``). A sampler reads, every ``sample_dt``, what the
plotted motes believe the robot's RSSI is.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from pathlib import Path

from awaremw.experiments.metrics import Recorder, RunResult
from awaremw.experiments.scenario import Scenario
from awaremw.nodes import KindsFactory, app_of
from awaremw.protocol.attributes import rssi_attribute
from awaremw.protocol.core import MoteCore, Transmission
from awaremw.protocol.events import CoreEvent
from awaremw.protocol.mote import AwareMote
from awaremw.radio.security import RadioSecurity
from awaremw.radio.virtual_medium import VirtualNetwork
from awaremw.security.material import load_gateway_keys


class ScriptedCore:
    """A MoteCore wrapper that also runs scripted actions on the mote at given
    times (the gateway's injections), inside the driver's own timer calls, so the
    driver collects what they send like any other output."""

    def __init__(self, inner: MoteCore) -> None:
        self.inner = inner
        self.node_id = inner.node_id
        self._script: list[tuple[float, Callable[[float], None]]] = []

    def at(self, t: float, action: Callable[[float], None]) -> None:
        self._script.append((t, action))
        self._script.sort(key=lambda e: e[0])

    def start(self, now: float) -> None:
        self.inner.start(now)

    def receive(self, frame: bytes, rssi_dbm: float, now: float) -> None:
        self.inner.receive(frame, rssi_dbm, now)

    def handle_timer(self, now: float) -> None:
        while self._script and self._script[0][0] <= now:
            _, action = self._script.pop(0)
            action(now)
        self.inner.handle_timer(now)

    def next_deadline(self) -> float | None:
        d = self.inner.next_deadline()
        if self._script:
            s = self._script[0][0]
            return s if d is None else min(d, s)
        return d

    def drain(self) -> list[Transmission]:
        return self.inner.drain()

    def link_result(self, tx: Transmission, acked: bool, now: float) -> None:
        self.inner.link_result(tx, acked, now)

    def events(self) -> list[CoreEvent]:
        return self.inner.events()


class VirtualRun:
    """Builds the scenario's network and runs it to ``duration``."""

    def __init__(
        self,
        scenario: Scenario,
        recorder: Recorder | None = None,
        sample_dt: float = 0.5,
        rssi_motes: list[int] | None = None,
        secrets: str | Path | None = None,
        keys: tuple[RadioSecurity, bytes] | None = None,
    ) -> None:
        self.scenario = scenario
        self.recorder = recorder or Recorder()
        d = scenario.deployment
        # With secrets (`awaremw keys init`): frames authenticated with the network
        # key, definitions signed with the gateway's key, as in a secured fleet.
        # ``keys``: those already loaded (load_gateway_keys), ``secrets``: their DIR.
        if secrets is not None and keys is not None:
            raise ValueError("VirtualRun: give secrets or keys, not both")
        if secrets is not None:
            keys = load_gateway_keys(secrets)
        security, key = (None, None) if keys is None else keys
        factory = KindsFactory(scenario.world, security=security, signing_key=key)
        self.net = VirtualNetwork(
            d.radio_model(), d.seed, mac=d.mac, collisions=d.collisions, security=security
        )
        self.net.on_event = self.recorder.on_event
        self.cores: dict[int, MoteCore] = {}
        # The gateway service injects every definition at every gateway mote.
        self.roots = tuple(s.id for s in d.of_kind("gateway")) or (scenario.gateway,)
        for spec in d.nodes:
            core = factory(spec, d)
            self.cores[spec.id] = core
            if spec.id in self.roots:
                wrapped = ScriptedCore(core)
                wrapped.at(scenario.define_at, functools.partial(self._define, spec.id))
                core = wrapped
            self.net.add(
                core,
                spec.mobility(),
                tx_power_dbm=d.tx_power_of(spec),
                start_at=spec.boot_s,
                battery_mj=spec.battery_mj,
            )
            app = app_of(self.cores[spec.id])
            if app is not None:
                app.energy = self._energy_probe(spec.id)
        self.sample_dt = sample_dt
        robot = scenario.robot
        self.rssi_motes = (
            rssi_motes if rssi_motes is not None else list(scenario.get("rssi_motes", []))
        )
        self._robot = robot
        self.on_tick: Callable[[float], None] | None = None

    def _energy_probe(self, node: int) -> Callable[[], float]:
        def probe() -> float:
            return self.net.energy_mj(node) / 1000.0  # J

        return probe

    def _define(self, root: int, now: float) -> None:
        core = self.cores[root]
        assert isinstance(core, AwareMote)
        for d in self.scenario.definitions:
            core.inject(d.kind, d.item_id, 1, d.body, now)

    def _sample(self) -> None:
        now = self.net.now
        if self._robot is not None:
            attr = rssi_attribute(self._robot)
            for n in self.rssi_motes:
                core = self.cores.get(n)
                if isinstance(core, AwareMote) and self.net.alive(n):
                    self.recorder.on_rssi(n, now, core.ctx.read(attr, now))
        if self.on_tick is not None:
            self.on_tick(now)
        self.net.call_at(now + self.sample_dt, self._sample)

    def run(self, duration: float | None = None) -> RunResult:
        end = self.scenario.duration if duration is None else duration
        self.net.call_at(0.0, self._sample)
        self.net.run_until(end)
        counters = self.net.counters
        traffic = {
            n: (c.frames_tx, c.frames_rx, self.net.energy_mj(n)) for n, c in counters.items()
        }
        return RunResult(self.scenario, self.recorder, end, traffic)
