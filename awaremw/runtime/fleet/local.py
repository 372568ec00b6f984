"""A fleet run in this process: :class:`Fleet`.

It runs the motes of a deployment (those passing ``node_filter``) as loop
timers, each a :class:`~awaremw.runtime.driver.MoteRunner` on one shared
:class:`~awaremw.radio.zenoh_medium.ZenohMedium`, over this process's one Zenoh
session. It is composed of parts with one job each:

* :class:`~awaremw.runtime.fleet.motes.FleetMotes` (``fleet.motes``): builds the
  motes from the deployment with the caller's core factory; add, kill, run_on;
* :class:`~awaremw.runtime.fleet.control.ControlService` (``fleet.control``):
  the control queryable ``<prefix>/ctl/fleet/<name>`` (``awaremw fleet-ctl
  add|kill|list|stats``; see ``docs/runtime.md``);
* :class:`~awaremw.runtime.fleet.stats.FleetStats` (``fleet.stats``): snapshots;
* :class:`~awaremw.runtime.fleet.guard.LoopGuard`: a core or hook that raises
  in the loop fails the fleet (:class:`FleetError`);

and the Fleet itself only opens, starts and closes them in order.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
import time
from collections.abc import Callable

import zenoh

from awaremw.protocol.core import MoteCore
from awaremw.protocol.events import EventHook
from awaremw.radio.capture import Capture
from awaremw.radio.counters import MoteCounters
from awaremw.radio.frame_counts import with_tap
from awaremw.radio.model import RadioModel
from awaremw.radio.zenoh_medium import MacSettings, ZenohMedium
from awaremw.runtime.deployment import Deployment
from awaremw.runtime.driver import LagStats
from awaremw.runtime.fleet.clock import ClockSync
from awaremw.runtime.fleet.control import ControlService
from awaremw.runtime.fleet.figures import FigureTaker
from awaremw.runtime.fleet.guard import LoopGuard
from awaremw.runtime.fleet.motes import CoreFactory, FleetMotes, NodeFilter
from awaremw.runtime.fleet.settings import FleetSettings
from awaremw.runtime.fleet.stats import FleetStats, WorkerResult
from awaremw.runtime.zenoh_session import SessionSettings, close_quietly, open_session
from awaremw.world.clock import EmulatedClock

log = logging.getLogger(__name__)


class Fleet:
    """The motes of ``deployment`` that pass ``node_filter``, run in this process.

    ``async with Fleet(dep, factory, FleetSettings(...)) as fleet:`` sets up and
    starts at once (emulated time 0 = ``settings.start_wall``, default now).
    A launcher's worker sets ``autostart=False``, reports ready, then calls
    :meth:`start` with the shared start time. After the block,
    :attr:`results` holds this process's :class:`WorkerResult`.

    Zenoh: pass an open ``session`` to share the process's session (it is then
    not closed here); otherwise the fleet opens one on the settings' endpoints
    (peer mode, multicast scouting off) and closes it.
    """

    def __init__(
        self,
        deployment: Deployment,
        core_factory: CoreFactory,
        settings: FleetSettings | None = None,
        *,
        node_filter: NodeFilter | None = None,
        session: zenoh.Session | None = None,
        radio_model: RadioModel | None = None,
    ) -> None:
        self.settings = s = settings or FleetSettings()
        self.deployment = deployment
        self.name = s.name
        self.speed = s.speed
        self.prefix = s.prefix
        self.model = radio_model or deployment.radio_model()
        self.clock = EmulatedClock(s.speed)
        self.lag: LagStats | None = LagStats() if s.collect_lag else None
        self.motes = FleetMotes(deployment, core_factory, node_filter, self.lag, s.name)
        self.runners = self.motes.runners  # the same dict: every mote this process ran
        self.figures: FigureTaker | None = None
        if s.figures:
            self.figures = FigureTaker(deployment, self.motes.runners, self.lag)
            self.motes.on_event(self.figures.on_event)
        self.stats = FleetStats(
            s.name, self.clock, self.lag, self.counters, self.motes.on_air, self.figures
        )
        self.control = ControlService(s.name, s.prefix, self.motes, self.stats)
        self._guard = LoopGuard(s.name)
        self.clock_sync = ClockSync(s.name, self.clock, self._rearm)
        self._session = session
        self._own_session = session is None
        self._medium: ZenohMedium | None = None
        self.endpoint = (s.listen or s.connect or ("",))[0]  # where others reach it
        self.capture: Capture | None = None  # with settings.pcap, once started
        self.results: list[WorkerResult] = []  # this process's, after the fleet closed
        self.started = False
        self._closed = False
        self._cpu0, self._wall0 = time.process_time(), time.perf_counter()
        self._lag_from: asyncio.TimerHandle | None = None

    # ------------------------------------------------------------------ views

    @property
    def session(self) -> zenoh.Session:
        if self._session is None:
            raise RuntimeError("fleet not entered")
        return self._session

    @property
    def medium(self) -> ZenohMedium:
        if self._medium is None:
            raise RuntimeError("fleet not entered")
        return self._medium

    @property
    def cores(self) -> dict[int, MoteCore]:
        """Cores of the motes on the air in this process."""
        return self.motes.cores

    def counters(self) -> dict[int, MoteCounters]:
        """Per-mote counters of every mote this process ever ran."""
        return self._medium.counters if self._medium is not None else {}

    @property
    def failed(self) -> bool:
        """True once a core or hook raised inside the loop (see :meth:`raise_errors`)."""
        return self._guard.failed

    def now(self) -> float:
        """Emulated seconds since the fleet's start."""
        return self.clock.now()

    # The three calls every user of a fleet makes, kept on the fleet itself;
    # the rest is on its parts (fleet.motes, fleet.control, fleet.stats).

    def on_event(self, hook: EventHook) -> None:
        """Register ``hook(node_id, event, now)`` for every core event (and MoteUp/Down)."""
        self.motes.on_event(hook)

    def alive(self, node_id: int) -> bool:
        return self.motes.alive(node_id)

    def run_on(self, node_id: int, fn: Callable[[MoteCore, float], object]) -> None:
        """Run ``fn(core, now)`` on a running mote, then drain and re-arm its timer."""
        self.motes.run_on(node_id, fn)

    # ------------------------------------------------------------------ lifecycle

    async def __aenter__(self) -> Fleet:
        try:
            await self._setup()
            if self.settings.autostart:
                self.start(self.settings.start_wall)
        except BaseException:
            await self.aclose()  # no half-open session or stray loop handler
            raise
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.aclose()

    async def _setup(self) -> None:
        """Open the session, the medium and the control queryable; attach the motes
        that boot at 0 and prime the receiver lists. Nothing runs yet."""
        s = self.settings
        loop = asyncio.get_running_loop()
        self._guard.install(loop)
        if self._session is None:
            endpoints = s.session or SessionSettings("peer", s.connect, s.listen)
            self._session = await asyncio.to_thread(open_session, endpoints)
        medium = ZenohMedium(
            self._session,
            self.model,
            self.clock,
            prefix=s.prefix,
            handler=s.handler,
            security=s.security,
            access=MacSettings(self.deployment.mac, self.deployment.collisions),
        )
        self._medium = medium
        medium.open()
        if s.track_links:
            medium.links = {}
        medium.on_early = self.clock_sync.on_early
        self.motes.attach(medium)
        self._prime(medium)
        self.control.bind(medium, loop)
        if s.control:
            self.control.open(self._session)
        if s.freeze_gc:
            # Setup made many long-lived objects: keep the collector off them.
            # Here, not at the start: a worker of 1,300 AwareMotes collects for
            # about 1 s, and all workers at the shared start would boot late.
            gc.collect()
            gc.freeze()
        if s.plugin is not None:
            s.plugin.setup(self)

    def _prime(self, medium: ZenohMedium) -> int:
        """Precompute receiver lists for every static deployment mote near ours."""
        dep = self.deployment
        return medium.prime(
            (n.id, n.position[0], n.position[1], dep.tx_power_of(n))
            for n in dep.nodes
            if not n.is_mobile
        )

    def start(self, start_wall: float | None = None) -> None:
        """Anchor emulated time 0 at ``start_wall`` (default now) and boot the motes."""
        if self.started:
            raise RuntimeError("fleet already started")
        self.started = True
        s = self.settings
        self.clock.restart(time.time() if start_wall is None else start_wall)
        self._cpu0, self._wall0 = time.process_time(), time.perf_counter()
        if self.figures is not None:
            self.medium.tap = with_tap(self.medium.tap, self.figures.frames)
        if s.pcap is not None:
            # The medium's own tap: every frame its motes send or hear, with receptions.
            self.capture = Capture.to_file(s.pcap, epoch=self.clock.start_wall)
            self.medium.tap = with_tap(self.medium.tap, self.capture)
        self.motes.start()
        self.clock_sync.activate()
        if self.lag is not None:
            self.lag.clear()  # samples of the set-up do not count
            if s.lag_from_s > 0:
                at = self.clock.to_monotonic(s.lag_from_s)
                self._lag_from = asyncio.get_running_loop().call_at(at, self.lag.clear)
        if s.plugin is not None:
            s.plugin.started(self)

    def _rearm(self, jump: float) -> None:
        """The clock moved ``jump`` emulated seconds forward (:class:`ClockSync`):
        every mote's timer is armed again on the new origin."""
        for r in list(self.motes.runners.values()):
            r.rearm()
        if self.lag is not None:
            self.lag.clear()  # the re-armed timers fire "late" by the jump, once

    async def aclose(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self._lag_from is not None:
            self._lag_from.cancel()
        self.results = [self._result()]
        self.motes.stop_all("stopped")
        self.control.close()
        if self._medium is not None:
            self._medium.close()
        if self._own_session and self._session is not None:
            await asyncio.to_thread(close_quietly, self._session)
        if self.capture is not None:
            self.capture.close()
        self._guard.uninstall()

    def _result(self) -> WorkerResult:
        """This process's figures; a plugin's result in ``extra["plugin"]``."""
        medium, s = self._medium, self.settings
        extra: dict[str, object] = {}
        error: str | None = None
        if medium is not None and medium.links is not None:
            extra["links"] = [(a, b, n) for (a, b), n in sorted(medium.links.items())]
        if s.plugin is not None and self.started:
            try:
                extra["plugin"] = s.plugin.result()
            except Exception as e:
                log.exception("fleet %s: plugin result failed", self.name)
                error = f"plugin result: {type(e).__name__}: {e}"
        return WorkerResult(
            name=self.name,
            motes=len(self.runners),
            counters={i: c.as_dict() for i, c in self.counters().items()},
            stats=medium.stats.as_dict() if medium else {},
            lag_ms=list(self.lag.samples) if self.lag is not None else [],
            cpu_s=time.process_time() - self._cpu0,
            wall_s=time.perf_counter() - self._wall0,
            error=error,
            extra=extra,
        )

    async def run(self, duration: float | None = None) -> None:
        """Run until emulated time ``duration`` (forever if None).

        Raises :class:`FleetError` if a core or hook raised inside the loop.
        """
        if duration is None:
            await self._guard.failed_event.wait()
        else:
            await self.wait_until(duration)
        self.raise_errors()

    async def wait_until(self, t: float) -> None:
        """Sleep until emulated time ``t`` (returns early if the fleet failed)."""
        failed = self._guard.failed_event
        while True:
            left = self.clock.wall_seconds(t - self.clock.now())
            if left <= 0 or failed.is_set():
                return
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(failed.wait(), timeout=left)

    async def freeze(self, grace_s: float = 0.5) -> None:
        """Stop the radio from starting new frames; wait ``grace_s`` (wall) for
        frames in flight to land (benchmarks count deliveries afterwards)."""
        self.medium.freeze()
        await asyncio.sleep(grace_s)

    def raise_errors(self) -> None:
        """Raise :class:`FleetError` if a core or hook raised inside the loop."""
        self._guard.raise_errors()
