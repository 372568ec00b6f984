"""A fleet over many processes: :class:`FleetLauncher`.

It spreads a deployment over N worker processes
(:class:`~awaremw.runtime.fleet.pool.WorkerPool`: real subprocesses talking to
it over a socket pair, each running :mod:`awaremw.runtime.fleet.worker`), in
spatial stripes along x so that most radio traffic stays inside a process,
joined through an embedded Zenoh router it starts (or an existing one).
Workers set up first (sessions, subscriptions, motes attached, receiver lists
primed), report ready, and are then given the shared start time: emulated time
0 is the same wall instant in every process.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import subprocess
import time
from typing import Any

from awaremw.radio.capture import Capture
from awaremw.radio.counters import MoteCounters
from awaremw.radio.sniffer import Sniffer
from awaremw.runtime.deployment import Deployment
from awaremw.runtime.fleet.motes import CoreFactory
from awaremw.runtime.fleet.pool import (
    LaunchError,
    RestartBudget,
    Resume,
    WorkerParams,
    WorkerPool,
    resume_counters,
)
from awaremw.runtime.fleet.settings import LauncherSettings
from awaremw.runtime.fleet.stats import MergedStats, WorkerResult, merged_counters
from awaremw.runtime.partition import partition
from awaremw.runtime.router import EmbeddedRouter
from awaremw.runtime.zenoh_session import (
    SessionSettings,
    close_quietly,
    free_tcp_endpoint,
    open_session,
)
from awaremw.world.clock import EmulatedClock

log = logging.getLogger(__name__)

_TOTALS = ("frames_tx", "frames_rx", "unicast_ok", "unicast_failed", "malformed")


class FleetLauncher:
    """Run a deployment over ``settings.processes`` worker processes joined by a
    Zenoh router.

    With ``settings.connect`` the workers join that router (e.g. ``awaremw
    router``); otherwise the launcher starts an embedded router listening on
    ``settings.listen`` (default: a free loopback port), available as
    :attr:`endpoint` for gateways and ``awaremw fleet-ctl``.
    :attr:`stats` merges the workers' latest snapshots (sent every
    ``settings.progress_s``). ``settings.plugin`` (a ``WorkerPlugin``,
    picklable) runs in every worker beside its fleet; each worker's
    ``plugin.result()`` is in its :class:`WorkerResult` in :attr:`results`
    after the launcher exited.
    """

    def __init__(
        self,
        deployment: Deployment,
        core_factory: CoreFactory,
        settings: LauncherSettings,
    ) -> None:
        self.deployment = deployment
        self.core_factory = core_factory
        self.settings = settings
        self.stats = MergedStats()
        self.capture: Capture | None = None  # with settings.pcap: the sniffer's
        self.clock = EmulatedClock(settings.speed)
        self.router: EmbeddedRouter | None = None
        self.endpoint = ""
        self.start_wall = 0.0
        self.results: list[WorkerResult] = []
        self.failures: list[WorkerResult] = []  # results of workers that stopped on their own
        self.motes_per_worker: list[int] = []
        self._pool: WorkerPool | None = None
        self._sniffer: Sniffer | None = None
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

    async def __aexit__(self, *exc: object) -> None:
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
        if s.pcap is not None:
            await self._sniff(s.pcap)

    async def _sniff(self, path: str) -> None:
        """A sniffer on the router: what goes through Zenoh (no receptions)."""
        s = self.settings
        settings = SessionSettings("peer", (self.endpoint,))
        if s.worker_config_file is not None:
            settings = SessionSettings("client", (self.endpoint,), config_file=s.worker_config_file)
        session = await asyncio.to_thread(open_session, settings)
        self.capture = Capture.to_file(path, receptions=False)
        self._sniffer = Sniffer(session, self.capture, prefix=s.prefix)
        self._sniffer.start()

    def _on_message(self, k: int, kind: str, arg: Any) -> bool:
        """Progress and frame counters are kept here (consumed); a failed result is
        noted when failed workers are not restarted."""
        if kind == "progress":
            self.stats.latest[k] = arg
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
        last = self.stats.latest.get(k)
        base = {} if last is None else {f: getattr(last, f) for f in _TOTALS}
        t, counters = self.frame_counters.get(k, (self.now(), {}))
        resume = Resume(n, resume_counters(counters, self.now() - t), base)
        log.warning(
            "worker %s exited unexpectedly (exit code %s); starting it again (restart %d)",
            name, code, n,
        )  # fmt: skip
        self.pool.respawn(k, resume)

    async def freeze(self, grace_s: float = 0.5) -> None:
        """Stop every worker's radio from starting new frames; wait ``grace_s`` (wall)
        for frames in flight to land (benchmarks count deliveries afterwards)."""
        self.pool.send_all("freeze")
        await asyncio.sleep(grace_s)

    async def _shutdown(self) -> None:
        if self._sniffer is not None:
            self._sniffer.close()
            await asyncio.to_thread(close_quietly, self._sniffer.session)
            self._sniffer = None
        if self._pool is not None:
            self._pool.send_all("stop")
            self.results = await self._pool.results(self.results, timeout=30.0)
            await self._pool.close()
        if self.router is not None:
            await asyncio.to_thread(self.router.close)
            self.router = None

    def counters(self) -> dict[int, MoteCounters]:
        """Per-mote counters merged from every worker (after the launcher exited)."""
        return merged_counters(self.results)
