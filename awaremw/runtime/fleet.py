"""Fleets of motes: one process (:class:`Fleet`) or many (:class:`FleetLauncher`).

A :class:`Fleet` runs the motes of a deployment (those passing ``node_filter``)
as loop timers in this process, each a :class:`~awaremw.runtime.driver.MoteRunner`
on one shared :class:`~awaremw.radio.zenoh_medium.ZenohMedium`, over this
process's one Zenoh session. It is composed of parts with one job each:

* :class:`~awaremw.runtime.fleet_motes.FleetMotes` (``fleet.motes``): builds the
  motes from the deployment with the caller's core factory; add, kill, run_on;
* :class:`~awaremw.runtime.fleet_control.ControlService` (``fleet.control``):
  the control queryable ``<prefix>/ctl/fleet/<name>`` (``awaremw fleet-ctl
  add|kill|list|stats``; see ``docs/runtime.md``);
* :class:`~awaremw.runtime.fleet_stats.FleetStats` (``fleet.stats``): snapshots;
* :class:`~awaremw.runtime.fleet_guard.LoopGuard`: a core or hook that raises
  in the loop fails the fleet (:class:`FleetError`);

and the Fleet itself only opens, starts and closes them in order.

A :class:`FleetLauncher` spreads a deployment over N worker processes
(:class:`~awaremw.runtime.workers.WorkerPool`: real subprocesses talking to it
over a socket pair), in spatial stripes along x so that most radio traffic
stays inside a process, joined through an embedded Zenoh router it starts (or
an existing one). Workers set up first (sessions, subscriptions, motes
attached, receiver lists primed), report ready, and are then given the shared
start time: emulated time 0 is the same wall instant in every process.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import logging
import math
import multiprocessing.connection
import subprocess
import sys
import time
from collections.abc import Callable
from types import TracebackType
from typing import Any

import zenoh

from awaremw.protocol.core import MoteCore
from awaremw.radio.counters import MoteCounters
from awaremw.radio.model import RadioModel
from awaremw.radio.zenoh_medium import MacSettings, ZenohMedium
from awaremw.runtime.deployment import Deployment
from awaremw.runtime.driver import LagStats
from awaremw.runtime.events import EventHook
from awaremw.runtime.fleet_clock import ClockSync
from awaremw.runtime.fleet_control import MAX_CONTROL_BYTES, ControlService
from awaremw.runtime.fleet_guard import FleetError, LoopGuard
from awaremw.runtime.fleet_motes import (
    HELLO_PERIOD_S,
    CoreFactory,
    FleetMotes,
    NodeFilter,
    hello_core,
)
from awaremw.runtime.fleet_settings import FleetSettings, LauncherSettings, WorkerPlugin
from awaremw.runtime.fleet_stats import FleetSnapshot, FleetStats, merge_snapshots
from awaremw.runtime.partition import (
    IdModulo,
    Layout,
    WorkerFilter,
    XStripe,
    partition,
    stripes,
)
from awaremw.runtime.router import EmbeddedRouter
from awaremw.runtime.workers import (
    LaunchError,
    RestartBudget,
    Resume,
    WorkerParams,
    WorkerPool,
    WorkerResult,
    resume_counters,
)
from awaremw.runtime.zenoh_session import (
    SessionSettings,
    close_quietly,
    free_tcp_endpoint,
    open_session,
)
from awaremw.world.clock import EmulatedClock

__all__ = [
    "HELLO_PERIOD_S",
    "MAX_CONTROL_BYTES",
    "ControlService",
    "CoreFactory",
    "Fleet",
    "FleetError",
    "FleetLauncher",
    "FleetMotes",
    "FleetSettings",
    "FleetSnapshot",
    "FleetStats",
    "IdModulo",
    "LaunchError",
    "LauncherSettings",
    "Layout",
    "NodeFilter",
    "WorkerFilter",
    "WorkerParams",
    "WorkerPlugin",
    "WorkerResult",
    "XStripe",
    "hello_core",
    "merge_snapshots",
    "partition",
    "stripes",
    "worker_entry",
    "worker_main",
]

log = logging.getLogger(__name__)

COUNTERS_EVERY_S = 1.0  # a secured worker without progress reports its frame counters this often
_TOTALS = ("frames_tx", "frames_rx", "unicast_ok", "unicast_failed", "malformed")


# --------------------------------------------------------------------------- Fleet


class Fleet:
    """The motes of ``deployment`` that pass ``node_filter``, run in this process.

    ``async with Fleet(dep, factory, FleetSettings(...)) as fleet:`` sets up and
    starts at once (emulated time 0 = ``settings.start_wall``, default now).
    A launcher's worker sets ``autostart=False``, reports ready, then calls
    :meth:`start` with the shared start time.

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
        self.stats = FleetStats(s.name, self.clock, self.lag, self._counters, self.motes.on_air)
        self.control = ControlService(s.name, s.prefix, self.motes, self.stats)
        self._guard = LoopGuard(s.name)
        self.clock_sync = ClockSync(s.name, self.clock, self._rearm)
        self._session = session
        self._own_session = session is None
        self._medium: ZenohMedium | None = None
        self.started = False
        self._closed = False

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

    @property
    def counters(self) -> dict[int, MoteCounters]:
        """Per-mote counters of every mote this process ever ran."""
        return self.medium.counters

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
            await self.setup()
            if self.settings.autostart:
                self.start(self.settings.start_wall)
        except BaseException:
            await self.aclose()  # no half-open session or stray loop handler
            raise
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.aclose()

    async def setup(self) -> None:
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
        self.clock.restart(time.time() if start_wall is None else start_wall)
        self.motes.start()
        self.clock_sync.activate()

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
        self.motes.stop_all("stopped")
        self.control.close()
        if self._medium is not None:
            self._medium.close()
        if self._own_session and self._session is not None:
            await asyncio.to_thread(close_quietly, self._session)
        self._guard.uninstall()

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

    def raise_errors(self) -> None:
        """Raise :class:`FleetError` if a core or hook raised inside the loop."""
        self._guard.raise_errors()

    def _counters(self) -> dict[int, MoteCounters]:
        return self._medium.counters if self._medium is not None else {}


# --------------------------------------------------------------------------- workers


def worker_entry() -> None:
    """``python -c "...; worker_entry()" FD``: a worker process started by the launcher.

    Real processes started with ``subprocess`` (not multiprocessing's spawn, which
    re-imports the parent's ``__main__``): the launcher passes one end of a socket
    pair as FD and sends the pickled :class:`WorkerParams` over it.
    """
    conn = multiprocessing.connection.Connection(int(sys.argv[1]))
    params = conn.recv()
    if not isinstance(params, WorkerParams):
        raise SystemExit("awaremw worker: bad parameters from the launcher")
    worker_main(params, conn)


def worker_main(params: WorkerParams, conn: multiprocessing.connection.Connection) -> None:
    """Run one worker until the launcher says stop (or goes away)."""
    logging.basicConfig(level=logging.WARNING, format=f"%(asctime)s {params.name} %(message)s")
    try:
        asyncio.run(_worker(params, conn))
    except KeyboardInterrupt:
        pass
    finally:
        conn.close()


async def _worker(p: WorkerParams, conn: multiprocessing.connection.Connection) -> None:
    loop = asyncio.get_running_loop()
    inbox: asyncio.Queue[tuple[str, Any]] = asyncio.Queue()

    def readable() -> None:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            loop.remove_reader(conn.fileno())
            inbox.put_nowait(("stop", None))  # the parent is gone
            return
        inbox.put_nowait(msg)

    loop.add_reader(conn.fileno(), readable)
    fleet = Fleet(
        p.deployment,
        p.core_factory,
        p.settings,
        node_filter=WorkerFilter(p.stripe, p.exclude_kinds),
    )
    cpu0 = time.process_time()
    wall0 = time.perf_counter()
    error: str | None = None
    progress: asyncio.Task[None] | None = None
    try:
        await fleet.setup()
        _resume(fleet, p.resume)
        if p.plugin is not None:
            p.plugin.setup(fleet)
        conn.send(("ready", len(fleet.runners)))
        while True:
            kind, arg = await inbox.get()
            match kind:
                case "start":
                    fleet.start(float(arg))
                    cpu0, wall0 = time.process_time(), time.perf_counter()
                    if fleet.lag is not None:
                        fleet.lag.clear()
                    if p.plugin is not None:
                        p.plugin.started(fleet)
                    secured = fleet.medium.guard is not None
                    if p.progress_s or secured:
                        every = p.progress_s or COUNTERS_EVERY_S
                        progress = asyncio.create_task(
                            _report(fleet, conn, every, bool(p.progress_s), secured)
                        )
                case "lagreset":
                    if fleet.lag is not None:
                        fleet.lag.clear()
                case "freeze":
                    fleet.medium.freeze()
                    conn.send(("frozen", fleet.now()))
                case "stop":
                    break
            fleet.raise_errors()
    except Exception as e:  # reported to the parent, which fails the run
        log.exception("worker %s failed", p.name)
        error = f"{type(e).__name__}: {e}"
    finally:
        if progress is not None:
            progress.cancel()
        with contextlib.suppress(OSError):
            loop.remove_reader(conn.fileno())
        medium = fleet._medium
        extra: dict[str, Any] = {}
        if medium is not None and medium.links is not None:
            extra["links"] = [(a, b, n) for (a, b), n in sorted(medium.links.items())]
        if p.plugin is not None:
            try:
                extra["plugin"] = p.plugin.result()
            except Exception as e:
                log.exception("worker %s: plugin result failed", p.name)
                error = error or f"plugin result: {type(e).__name__}: {e}"
        result = WorkerResult(
            name=p.name,
            motes=len(fleet.runners),
            counters={i: c.as_dict() for i, c in medium.counters.items()} if medium else {},
            stats=medium.stats.as_dict() if medium else {},
            lag_ms=list(fleet.lag.samples) if fleet.lag is not None else [],
            cpu_s=time.process_time() - cpu0,
            wall_s=time.perf_counter() - wall0,
            error=error,
            extra=extra,
        )
        await fleet.aclose()
        with contextlib.suppress(OSError, BrokenPipeError):
            conn.send(("result", result))


def _resume(fleet: Fleet, r: Resume) -> None:
    """A restarted worker goes on from its dead incarnations (see :class:`Resume`)."""
    fleet.control.restarts = r.restarts
    fleet.stats.base = dict(r.base)
    guard = fleet.medium.guard
    if guard is not None:
        for node, counter in r.frame_counters.items():
            guard.resume(node, counter)


async def _report(
    fleet: Fleet,
    conn: multiprocessing.connection.Connection,
    every: float,
    progress: bool,
    counters: bool,
) -> None:
    """Every ``every`` wall seconds: a progress snapshot, and the motes' frame
    counters on a secured radio (what a restart goes on from)."""
    guard = fleet.medium.guard
    while True:
        await asyncio.sleep(every)
        with contextlib.suppress(OSError, BrokenPipeError):
            if progress:
                conn.send(("progress", fleet.stats.snapshot()))
            if counters and guard is not None:
                ids = list(fleet.runners)
                conn.send(("counters", (fleet.now(), {i: guard.counter_of(i) for i in ids})))


# --------------------------------------------------------------------------- launcher


class FleetLauncher:
    """Run a deployment over ``settings.processes`` worker processes joined by a
    Zenoh router.

    With ``settings.connect`` the workers join that router (e.g. ``awaremw
    router``); otherwise the launcher starts an embedded router listening on
    ``settings.listen`` (default: a free loopback port), available as
    :attr:`endpoint` for gateways and ``awaremw fleet-ctl``.
    ``on_progress`` gets the merged snapshot of all workers every
    ``settings.progress_s``. ``settings.plugin`` (a :class:`WorkerPlugin`,
    picklable) runs in every worker beside its fleet; each worker's
    ``plugin.result()`` is in :meth:`plugin_results` after the launcher exited.
    """

    def __init__(
        self,
        deployment: Deployment,
        core_factory: CoreFactory,
        settings: LauncherSettings,
        *,
        on_progress: Callable[[FleetSnapshot], None] | None = None,
    ) -> None:
        self.deployment = deployment
        self.core_factory = core_factory
        self.settings = settings
        self.on_progress = on_progress
        self.clock = EmulatedClock(settings.speed)
        self.router: EmbeddedRouter | None = None
        self.endpoint = ""
        self.start_wall = 0.0
        self.results: list[WorkerResult] = []
        self.failures: list[WorkerResult] = []  # results of workers that stopped on their own
        self.motes_per_worker: list[int] = []
        self._pool: WorkerPool | None = None
        self._progress: dict[str, FleetSnapshot] = {}
        self._last: dict[int, FleetSnapshot] = {}  # each worker's latest snapshot
        # Each worker's last report on a secured radio: (emulated t, {node: frame counter}).
        self.frame_counters: dict[int, tuple[float, dict[int, int]]] = {}
        self._budget = RestartBudget(settings.max_restarts, settings.restart_window_s)
        self.restarts: dict[int, int] = {}  # worker index -> times it was started again
        self._failed: str | None = None

    @property
    def pool(self) -> WorkerPool:
        if self._pool is None:
            raise RuntimeError("launcher not entered")
        return self._pool

    def now(self) -> float:
        return self.clock.now()

    async def __aenter__(self) -> FleetLauncher:
        try:
            await self._launch()
        except BaseException:
            await self._shutdown()
            raise
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self._shutdown()

    async def _launch(self) -> None:
        s = self.settings
        if s.connect:
            self.endpoint = s.connect[0]
        else:
            listen = s.listen or (free_tcp_endpoint(),)
            self.router = EmbeddedRouter(listen, config_file=s.router_config_file)
            await asyncio.to_thread(self.router.start)
            self.endpoint = listen[0]
        pool = self._pool = WorkerPool(self._on_message)
        for k, stripe in enumerate(partition(self.deployment, s.processes, s.layout)):
            pool.spawn(
                WorkerParams(
                    deployment=self.deployment,
                    core_factory=self.core_factory,
                    settings=s.fleet(f"w{k}", (self.endpoint,)),
                    stripe=stripe,
                    exclude_kinds=s.exclude_kinds,
                    progress_s=s.progress_s,
                    plugin=s.plugin,
                )
            )
        loop = asyncio.get_running_loop()
        ready: dict[int, int] = {}
        deadline = loop.time() + s.ready_timeout_s
        while len(ready) < len(pool):
            k, kind, arg = await self._next(deadline, "set up")
            if kind == "ready":
                ready[k] = int(arg)
            elif kind == "result":
                raise LaunchError(f"worker w{k} failed during setup: {arg.error}")
        self.motes_per_worker = [ready[k] for k in range(len(pool))]
        # Routes propagate through the router in a moment; start shortly after.
        self.start_wall = time.time() + s.start_delay_s
        self.clock.restart(self.start_wall)
        pool.send_all("start", self.start_wall)

    def _on_message(self, k: int, kind: str, arg: Any) -> bool:
        """Progress and frame counters are kept here (consumed); a failed result is
        noted when failed workers are not restarted."""
        if kind == "progress":
            self._last[k] = arg
            self._progress[arg.name] = arg
            if self.on_progress is not None and len(self._progress) == len(self.pool):
                self.on_progress(merge_snapshots(self._progress.values()))
                self._progress.clear()
            return True
        if kind == "counters":
            self.frame_counters[k] = arg
            return True
        if kind == "result" and arg.error and not self._budget.enabled:
            self._failed = f"worker {arg.name}: {arg.error}"
        return False

    async def _next(self, deadline: float, doing: str) -> tuple[int, str, Any]:
        loop = asyncio.get_running_loop()
        try:
            k, kind, arg = await self.pool.next(deadline - loop.time())
        except TimeoutError:
            raise LaunchError(f"workers did not {doing} within the time limit") from None
        if kind == "gone":
            code = self.pool.procs[k].poll()
            raise LaunchError(f"worker w{k} exited unexpectedly (exit code {code})")
        return k, kind, arg

    async def run(self, duration: float | None = None) -> None:
        """Wait until emulated time ``duration`` (forever if None).

        A worker that dies (killed, crashed, failed) is started again with its
        motes (:meth:`_restart`); the others go on. Only a worker that keeps
        dying (more than ``settings.max_restarts`` times within
        ``settings.restart_window_s``) ends the run with :class:`LaunchError`.
        """
        while True:
            if self._failed:
                raise LaunchError(self._failed)
            left = math.inf if duration is None else self.clock.wall_seconds(duration - self.now())
            if left <= 0:
                return
            try:
                k, kind, arg = await self.pool.next(min(left, 3600.0))
            except TimeoutError:
                continue
            match kind:
                case "gone":
                    await self._restart(k)
                case "result":  # a worker that stopped on its own; its pipe closes next
                    self.failures.append(arg)
                    if not self._budget.enabled:
                        raise LaunchError(f"worker {arg.name} stopped: {arg.error or 'no reason'}")
                    log.warning("worker %s stopped: %s", arg.name, arg.error or "no reason")
                case "ready":  # a restarted worker: on the launcher's emulated time
                    self.pool.send(k, "start", self.start_wall)
                    log.warning("worker w%d restarted with %d motes", k, int(arg))

    async def _restart(self, k: int) -> None:
        """Start worker ``k`` again after it died: same motes, booted now as after a
        power cycle, frame counters and figures going on (:class:`Resume`)."""
        proc = self.pool.procs[k]
        with contextlib.suppress(subprocess.TimeoutExpired):
            await asyncio.to_thread(proc.wait, 5.0)  # its pipe closed first: reap it
        code = proc.poll()
        name = f"w{k}"
        if not self._budget.allow(k, time.monotonic()):
            raise LaunchError(
                f"worker {name} exited unexpectedly (exit code {code}) more than "
                f"{self._budget.limit} times in {self._budget.window_s:g} s; giving up"
            )
        self.restarts[k] = n = self.restarts.get(k, 0) + 1
        last = self._last.get(k)
        base = {} if last is None else {f: getattr(last, f) for f in _TOTALS}
        t, counters = self.frame_counters.get(k, (self.now(), {}))
        resume = Resume(n, resume_counters(counters, self.now() - t), base)
        log.warning(
            "worker %s exited unexpectedly (exit code %s); starting it again (restart %d)",
            name, code, n,
        )  # fmt: skip
        self.pool.respawn(k, resume)

    def reset_lag(self) -> None:
        """Workers drop the timer-lag samples taken so far (end of a warm-up)."""
        self.pool.send_all("lagreset")

    async def freeze(self, grace_s: float = 0.5) -> None:
        """Stop every worker's radio from starting new frames; wait ``grace_s`` (wall)
        for frames in flight to land (benchmarks count deliveries afterwards)."""
        self.pool.send_all("freeze")
        await asyncio.sleep(grace_s)

    async def _shutdown(self) -> None:
        if self._pool is not None:
            self._pool.send_all("stop")
            self.results = await self._pool.results(self.results, timeout=30.0)
            await self._pool.close()
        if self.router is not None:
            await asyncio.to_thread(self.router.close)
            self.router = None

    def links(self) -> dict[tuple[int, int], int]:
        """Frames delivered per (src, dst) over all workers (with ``track_links``)."""
        out: dict[tuple[int, int], int] = {}
        for r in self.results:
            for a, b, n in r.extra.get("links", ()):
                out[(a, b)] = out.get((a, b), 0) + n
        return out

    def plugin_results(self) -> list[Any]:
        """Each worker's ``plugin.result()``, in worker order (after the launcher
        exited; a worker that returned none is left out)."""
        return [r.extra["plugin"] for r in self.results if "plugin" in r.extra]

    def counters(self) -> dict[int, MoteCounters]:
        """Per-mote counters merged from every worker (after the launcher exited)."""
        out: dict[int, MoteCounters] = {}
        for r in self.results:
            for nid, d in r.counters.items():
                out.setdefault(nid, MoteCounters()).add(MoteCounters(**d))
        return out
