"""The motes one fleet runs: built from a deployment's specs by the caller's
core factory, put on the medium, booted, added and killed at run time, and
their events fanned out to the registered hooks."""

from __future__ import annotations

import random
from collections.abc import Callable

from awaremw.protocol.core import MoteCore
from awaremw.protocol.events import EventHook, MoteEvent
from awaremw.radio.zenoh_medium import ZenohMedium
from awaremw.runtime.deployment import Deployment, NodeSpec
from awaremw.runtime.driver import LagStats, MoteRunner

CoreFactory = Callable[[NodeSpec, Deployment], MoteCore]
NodeFilter = Callable[[NodeSpec], bool]

HELLO_PERIOD_S = 1.0


def hello_core(spec: NodeSpec, deployment: Deployment) -> MoteCore:
    """The stand-in core: a HelloMote beaconing every second."""
    from awaremw.protocol.hello import HelloMote

    rng = random.Random(f"awaremw:{deployment.seed}:{spec.id}")
    return HelloMote(spec.id, HELLO_PERIOD_S, rng, deployment.preset.mtu)


class FleetMotes:
    """The motes of ``deployment`` that pass ``node_filter``, one
    :class:`~awaremw.runtime.driver.MoteRunner` each on one medium.

    :meth:`attach` (once the medium is open) builds them and puts those that
    boot at 0 on the air; :meth:`start` boots them at their ``boot_s``.
    """

    def __init__(
        self,
        deployment: Deployment,
        core_factory: CoreFactory,
        node_filter: NodeFilter | None = None,
        lag: LagStats | None = None,
        name: str = "main",
    ) -> None:
        self.deployment = deployment
        self.core_factory = core_factory
        self.node_filter = node_filter
        self.lag = lag
        self.name = name
        self.runners: dict[int, MoteRunner] = {}
        self.started = False
        self._boot_of: dict[int, float] = {}
        self._hooks: list[EventHook] = []
        self._medium: ZenohMedium | None = None

    @property
    def kinds(self) -> frozenset[str]:
        """The kinds a new mote may have: those this deployment runs, plus those
        the core factory names (``awaremw.nodes.KindsFactory.kinds``; the runtime
        does not import the node kinds)."""
        kinds = {s.kind for s in self.deployment.nodes}
        kinds.update(getattr(self.core_factory, "kinds", ()))
        return frozenset(kinds)

    def owns(self, spec: NodeSpec) -> bool:
        """Whether this fleet runs ``spec`` (its node filter)."""
        return self.node_filter is None or self.node_filter(spec)

    def on_event(self, hook: EventHook) -> None:
        """Register ``hook(node_id, event, now)`` for every core event (and MoteUp/Down)."""
        self._hooks.append(hook)

    # ------------------------------------------------------------------ lifecycle

    def attach(self, medium: ZenohMedium) -> None:
        """Build the motes this fleet owns on ``medium``; those booting at 0 go on
        the air now (their receivers listen before the start)."""
        self._medium = medium
        for spec in self.deployment.nodes:
            if self.owns(spec):
                r = self._make_runner(spec)
                if spec.boot_s <= 0.0:
                    r.attach()

    def start(self) -> None:
        """Boot every mote at its ``boot_s`` (the clock is anchored already)."""
        self.started = True
        for r in list(self.runners.values()):
            if not r.stopped:  # killed before the start: never boots
                r.start_at(self._boot_of.get(r.node_id, 0.0))

    def stop_all(self, reason: str = "stopped") -> None:
        for r in self.runners.values():
            r.stop(reason)

    # ------------------------------------------------------------------ at run time

    def add(self, spec: NodeSpec) -> MoteRunner:
        """Run a new mote (or a killed one again) in this process.

        It boots at ``spec.boot_s`` or now, whichever is later. ValueError if
        that id is on the air here already.
        """
        old = self.runners.get(spec.id)
        if old is not None and not old.stopped:
            raise ValueError(f"node {spec.id} is already running in fleet {self.name}")
        self.deployment.preset.check_tx_power(self.deployment.tx_power_of(spec))
        r = self._make_runner(spec)
        if self.started:
            r.start_at(spec.boot_s)
        return r

    def kill(self, node_id: int, reason: str = "killed") -> bool:
        """Switch a mote off; False if it is not running here."""
        r = self.runners.get(node_id)
        if r is None or r.stopped:
            return False
        r.stop(reason)  # on the air, or still waiting to boot
        return True

    def run_on(self, node_id: int, fn: Callable[[MoteCore, float], object]) -> None:
        """Run ``fn(core, now)`` on a running mote, then drain and re-arm its timer."""
        self.runners[node_id].run_on(fn)

    def alive(self, node_id: int) -> bool:
        r = self.runners.get(node_id)
        return r is not None and r.alive

    @property
    def cores(self) -> dict[int, MoteCore]:
        """Cores of the motes on the air."""
        return {i: r.core for i, r in self.runners.items() if r.alive}

    def on_air(self) -> int:
        return sum(1 for r in self.runners.values() if r.alive)

    def positions(self, t: float) -> dict[int, tuple[float, float]]:
        """Where each mote on the air is at ``t`` (moving motes follow their paths)."""
        return {i: r.mobility.position(t) for i, r in self.runners.items() if r.alive}

    # ------------------------------------------------------------------ inside

    def _make_runner(self, spec: NodeSpec) -> MoteRunner:
        if self._medium is None:
            raise RuntimeError(f"fleet {self.name}: motes not attached to a medium yet")
        core = self.core_factory(spec, self.deployment)
        r = MoteRunner(
            core,
            self._medium,
            spec.mobility(),
            tx_power_dbm=self.deployment.tx_power_of(spec),
            battery_mj=spec.battery_mj,
            on_event=self._dispatch,
            lag=self.lag,
        )
        self.runners[spec.id] = r
        self._boot_of[spec.id] = spec.boot_s
        return r

    def _dispatch(self, node_id: int, event: MoteEvent, now: float) -> None:
        for h in self._hooks:
            h(node_id, event, now)
