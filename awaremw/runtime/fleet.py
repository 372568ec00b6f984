"""Fleets of motes: one process (:class:`Fleet`) or many (:class:`FleetLauncher`).

A :class:`Fleet` runs the motes of a deployment (those passing ``node_filter``)
as loop timers in this process, each a :class:`~awaremw.runtime.driver.MoteRunner`
on one shared :class:`~awaremw.radio.zenoh_medium.ZenohMedium`, over this
process's one Zenoh session. At run time motes can be added and killed, from
Python (:meth:`Fleet.add_mote`, :meth:`Fleet.kill`) or from anywhere on the
Zenoh network through the control queryable ``<prefix>/ctl/fleet/<name>``
(``awaremw fleet-ctl add|kill|list``; see ``docs/runtime.md``).

A :class:`FleetLauncher` spreads a deployment over N worker processes (real
subprocesses talking to it over a socket pair), in spatial stripes along x so
that most radio traffic stays inside a process, joined through an embedded Zenoh router it
starts (or an existing one). Workers set up first (sessions, subscriptions,
motes attached, receiver lists primed), report ready, and are then given the
shared start time: emulated time 0 is the same wall instant in every process.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import json
import logging
import math
import multiprocessing
import multiprocessing.connection
import os
import random
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from types import TracebackType
from typing import Any, Literal

import zenoh

from awaremw.protocol.core import MoteCore
from awaremw.radio.counters import MoteCounters
from awaremw.radio.model import RadioModel
from awaremw.radio.zenoh_medium import DEFAULT_HANDLER, DEFAULT_PREFIX, Handler, ZenohMedium
from awaremw.runtime.clock import EmulatedClock
from awaremw.runtime.deployment import (
    Deployment,
    DeploymentError,
    NodeSpec,
    parse_deployment,
)
from awaremw.runtime.driver import EventHook, LagStats, MoteRunner, percentile
from awaremw.runtime.router import EmbeddedRouter
from awaremw.runtime.zenoh_session import (
    SessionSettings,
    close_quietly,
    free_tcp_endpoint,
    open_session,
)

log = logging.getLogger(__name__)

CoreFactory = Callable[[NodeSpec, Deployment], MoteCore]
NodeFilter = Callable[[NodeSpec], bool]

HELLO_PERIOD_S = 1.0


# --------------------------------------------------------------------------- cores


def hello_core(spec: NodeSpec, deployment: Deployment) -> MoteCore:
    """The stand-in core: a HelloMote beaconing every second."""
    from awaremw.protocol.hello import HelloMote

    rng = random.Random(f"awaremw:{deployment.seed}:{spec.id}")
    return HelloMote(spec.id, HELLO_PERIOD_S, rng, deployment.preset.mtu)


def default_core_factory(world: object | None = None) -> CoreFactory:
    """``awaremw.nodes.build_core`` (the node kinds) when available, else :func:`hello_core`.

    One world is shared by every mote the factory builds (built lazily from the
    first deployment it sees when ``world`` is None).
    """
    try:
        from awaremw import nodes
    except ImportError:  # node kinds not installed in this tree
        return hello_core
    build = getattr(nodes, "build_core", None)
    if build is None:
        return hello_core
    cache: dict[str, object] = {}

    def factory(spec: NodeSpec, deployment: Deployment) -> MoteCore:
        w = world
        if w is None:
            w = cache.get("world")
            if w is None:
                w = cache["world"] = nodes.world_of(deployment)
        core: MoteCore = build(spec, deployment, w)
        return core

    return factory


# --------------------------------------------------------------------------- stripes


@dataclass(frozen=True, slots=True)
class XStripe:
    """Node filter: motes whose position (first waypoint) has ``lo <= x < hi``."""

    lo: float
    hi: float

    def __call__(self, spec: NodeSpec) -> bool:
        return self.lo <= spec.position[0] < self.hi


@dataclass(frozen=True, slots=True)
class IdModulo:
    """Node filter: motes with ``id % n == k`` (the worst case for cross-process
    traffic: neighbours mostly live in other processes; benchmarks only)."""

    k: int
    n: int

    def __call__(self, spec: NodeSpec) -> bool:
        return spec.id % self.n == self.k


Layout = Literal["stripes", "interleaved"]


def partition(
    deployment: Deployment, n: int, layout: Layout = "stripes"
) -> list[XStripe | IdModulo]:
    """The node filters of ``n`` workers."""
    if layout == "interleaved":
        return [IdModulo(k, n) for k in range(n)]
    return list(stripes(deployment, n))


def stripes(deployment: Deployment, n: int) -> list[XStripe]:
    """Split the deployment into ``n`` stripes along x holding about as many motes each.

    Motes with the same x always fall in the same stripe; the first and last
    stripes are open-ended, so motes added later anywhere have an owner.
    """
    if n < 1:
        raise ValueError("need at least one stripe")
    xs = sorted(spec.position[0] for spec in deployment.nodes)
    cuts: list[float] = []
    for k in range(1, n):
        x = xs[min(len(xs) - 1, (k * len(xs)) // n)]
        if x > (cuts[-1] if cuts else xs[0]):  # no empty stripe in front
            cuts.append(x)
    bounds = [-math.inf, *cuts, math.inf]
    out = [XStripe(bounds[i], bounds[i + 1]) for i in range(len(bounds) - 1)]
    while len(out) < n:  # fewer distinct x than processes: empty stripes
        out.append(XStripe(math.inf, math.inf))
    return out


# --------------------------------------------------------------------------- snapshot


@dataclass(frozen=True, slots=True)
class FleetSnapshot:
    """Progress figures of one fleet (one process)."""

    name: str
    t: float  # emulated seconds
    motes: int  # on the air
    frames_tx: int
    frames_rx: int
    unicast_ok: int
    unicast_failed: int
    malformed: int
    lag_p50_ms: float  # over the samples since the previous snapshot
    lag_p99_ms: float

    def line(self) -> str:
        def ms(v: float) -> str:
            return "-" if math.isnan(v) else f"{v:.1f}ms"

        return (
            f"[{self.name}] t={self.t:8.1f}s motes={self.motes} tx={self.frames_tx} "
            f"rx={self.frames_rx} uc_ok={self.unicast_ok} uc_fail={self.unicast_failed} "
            f"malformed={self.malformed} lag p50={ms(self.lag_p50_ms)} p99={ms(self.lag_p99_ms)}"
        )


def merge_snapshots(snaps: Iterable[FleetSnapshot], name: str = "fleet") -> FleetSnapshot:
    s = list(snaps)
    return FleetSnapshot(
        name=name,
        t=max((x.t for x in s), default=0.0),
        motes=sum(x.motes for x in s),
        frames_tx=sum(x.frames_tx for x in s),
        frames_rx=sum(x.frames_rx for x in s),
        unicast_ok=sum(x.unicast_ok for x in s),
        unicast_failed=sum(x.unicast_failed for x in s),
        malformed=sum(x.malformed for x in s),
        lag_p50_ms=max((x.lag_p50_ms for x in s if not math.isnan(x.lag_p50_ms)), default=0.0),
        lag_p99_ms=max((x.lag_p99_ms for x in s if not math.isnan(x.lag_p99_ms)), default=0.0),
    )


# --------------------------------------------------------------------------- Fleet


class FleetError(RuntimeError):
    """A local bug surfaced inside the fleet's event loop (a core or hook raised)."""


class Fleet:
    """The motes of ``deployment`` that pass ``node_filter``, run in this process.

    ``async with Fleet(dep) as fleet:`` sets up and starts at once (emulated time
    0 = ``start_wall``, default now). A launcher passes ``autostart=False``,
    reports ready, then calls :meth:`start` with the shared start time.

    Zenoh: pass an open ``session`` to share the process's session (it is then
    not closed here), or ``connect``/``listen`` endpoints (peer mode, multicast
    scouting off) for a session the fleet opens and closes.
    """

    def __init__(
        self,
        deployment: Deployment,
        core_factory: CoreFactory | None = None,
        *,
        speed: float = 1.0,
        prefix: str = DEFAULT_PREFIX,
        connect: Sequence[str] = (),
        listen: Sequence[str] = (),
        session: zenoh.Session | None = None,
        node_filter: NodeFilter | None = None,
        world: object | None = None,
        start_wall: float | None = None,
        autostart: bool = True,
        name: str = "main",
        handler: Handler = DEFAULT_HANDLER,
        control: bool = True,
        collect_lag: bool = True,
        freeze_gc: bool = False,
        radio_model: RadioModel | None = None,
        track_links: bool = False,
        zenoh_mode: Literal["peer", "client"] = "peer",
    ) -> None:
        self.deployment = deployment
        self.track_links = track_links
        self.core_factory = core_factory or default_core_factory(world)
        self.speed = speed
        self.prefix = prefix
        self.node_filter = node_filter
        self.name = name
        self.handler: Handler = handler
        self.control = control
        self.freeze_gc = freeze_gc
        self.model = radio_model or deployment.radio_model()
        self._settings = SessionSettings(
            zenoh_mode, tuple(connect), () if zenoh_mode == "client" else tuple(listen)
        )
        self._session = session
        self._own_session = session is None
        self._start_wall = start_wall
        self._autostart = autostart
        self.clock = EmulatedClock(speed)
        self.lag = LagStats() if collect_lag else None
        self._lag_mark = 0
        self.runners: dict[int, MoteRunner] = {}
        self._boot_of: dict[int, float] = {}
        self._hooks: list[EventHook] = []
        self._medium: ZenohMedium | None = None
        self._queryable: zenoh.Queryable[None] | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._errors: list[BaseException] = []
        self._failed = asyncio.Event()
        self._old_handler: Any = None
        self.started = False
        self._closed = False

    # ------------------------------------------------------------------ properties

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

    def now(self) -> float:
        """Emulated seconds since the fleet's start."""
        return self.clock.now()

    @property
    def cores(self) -> dict[int, MoteCore]:
        """Cores of the motes on the air in this process."""
        return {i: r.core for i, r in self.runners.items() if r.alive}

    @property
    def counters(self) -> dict[int, MoteCounters]:
        """Per-mote counters of every mote this process ever ran."""
        return self.medium.counters

    def positions(self) -> dict[int, tuple[float, float]]:
        """Where each mote on the air is now (moving motes follow their paths)."""
        t = self.clock.now()
        return {i: r.mobility.position(t) for i, r in self.runners.items() if r.alive}

    def alive(self, node_id: int) -> bool:
        r = self.runners.get(node_id)
        return r is not None and r.alive

    def on_event(self, hook: EventHook) -> None:
        """Register ``hook(node_id, event, now)`` for every core event (and MoteUp/Down)."""
        self._hooks.append(hook)

    def remove_event_hook(self, hook: EventHook) -> None:
        self._hooks.remove(hook)

    def owns(self, spec: NodeSpec) -> bool:
        """Whether this fleet runs ``spec`` (its node filter)."""
        return self.node_filter is None or self.node_filter(spec)

    # ------------------------------------------------------------------ lifecycle

    async def __aenter__(self) -> Fleet:
        try:
            await self.setup()
            if self._autostart:
                self.start(self._start_wall)
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
        loop = asyncio.get_running_loop()
        self._loop = loop
        self._old_handler = loop.get_exception_handler()
        loop.set_exception_handler(self._loop_exception)
        if self._session is None:
            self._session = await asyncio.to_thread(open_session, self._settings)
        self._medium = ZenohMedium(
            self._session, self.model, self.clock, prefix=self.prefix, handler=self.handler
        )
        self._medium.open()
        if self.track_links:
            self._medium.links = {}
        for spec in self.deployment.nodes:
            if self.owns(spec):
                r = self._make_runner(spec)
                if spec.boot_s <= 0.0:
                    r.attach()
        self.prime()
        if self.control:
            self._queryable = self._session.declare_queryable(
                f"{self.prefix}/ctl/fleet/{self.name}",
                zenoh.handlers.Callback(self._on_query, indirect=False),
            )

    def prime(self) -> int:
        """Precompute receiver lists for every static deployment mote near ours."""
        dep = self.deployment
        return self.medium.prime(
            (s.id, s.position[0], s.position[1], dep.tx_power_of(s))
            for s in dep.nodes
            if not s.is_mobile
        )

    def start(self, start_wall: float | None = None) -> None:
        """Anchor emulated time 0 at ``start_wall`` (default now) and boot the motes."""
        if self.started:
            raise RuntimeError("fleet already started")
        self.started = True
        self.clock.restart(time.time() if start_wall is None else start_wall)
        if self.freeze_gc:
            # Setup made many long-lived objects: keep the collector off them.
            gc.collect()
            gc.freeze()
        for r in list(self.runners.values()):
            if not r.stopped:  # killed before the start: never boots
                r.start_at(self._boot_of.get(r.node_id, 0.0))

    async def aclose(self) -> None:
        if self._closed:
            return
        self._closed = True
        for r in self.runners.values():
            r.stop("stopped")
        if self._queryable is not None:
            with contextlib.suppress(zenoh.ZError):
                self._queryable.undeclare()  # type: ignore[no-untyped-call]
        if self._medium is not None:
            self._medium.close()
        if self._own_session and self._session is not None:
            await asyncio.to_thread(close_quietly, self._session)
        loop = self._loop
        if loop is not None and loop.get_exception_handler() == self._loop_exception:
            loop.set_exception_handler(self._old_handler)
        # else another fleet chained its handler on top of ours: ours stays in the
        # chain but, closed, only forwards.

    async def run(self, duration: float | None = None) -> None:
        """Run until emulated time ``duration`` (forever if None).

        Raises :class:`FleetError` if a core or hook raised inside the loop.
        """
        if duration is None:
            await self._failed.wait()
        else:
            await self.wait_until(duration)
        self.raise_errors()

    async def wait_until(self, t: float) -> None:
        """Sleep until emulated time ``t`` (returns early if the fleet failed)."""
        while True:
            left = self.clock.wall_seconds(t - self.clock.now())
            if left <= 0 or self._failed.is_set():
                return
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._failed.wait(), timeout=left)

    @property
    def failed(self) -> bool:
        """True once a core or hook raised inside the loop (see :meth:`raise_errors`)."""
        return self._failed.is_set()

    def raise_errors(self) -> None:
        if self._errors:
            e = self._errors[0]
            raise FleetError(f"fleet {self.name}: {type(e).__name__}: {e}") from e

    def _loop_exception(self, loop: asyncio.AbstractEventLoop, ctx: dict[str, Any]) -> None:
        exc = ctx.get("exception")
        if isinstance(exc, Exception) and not self._closed:
            # A core or hook raised in a loop callback: our bug. Stop and report.
            self._errors.append(exc)
            self._failed.set()
        if self._old_handler is not None:
            self._old_handler(loop, ctx)
        else:
            loop.default_exception_handler(ctx)

    # ------------------------------------------------------------------ motes

    def _make_runner(self, spec: NodeSpec) -> MoteRunner:
        core = self.core_factory(spec, self.deployment)
        r = MoteRunner(
            core,
            self.medium,
            spec.mobility(),
            tx_power_dbm=self.deployment.tx_power_of(spec),
            battery_mj=spec.battery_mj,
            on_event=self._dispatch,
            lag=self.lag,
        )
        self.runners[spec.id] = r
        self._boot_of[spec.id] = spec.boot_s
        return r

    def add_mote(self, spec: NodeSpec) -> MoteRunner:
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

    def _dispatch(self, node_id: int, event: object, now: float) -> None:
        for h in self._hooks:
            h(node_id, event, now)

    # ------------------------------------------------------------------ progress

    def snapshot(self) -> FleetSnapshot:
        """Totals so far; lag percentiles over the samples since the last snapshot."""
        tot = MoteCounters()
        for c in self.counters.values():
            tot.add(c)
        p50 = p99 = math.nan
        if self.lag is not None:
            recent = self.lag.samples[self._lag_mark :]
            self._lag_mark = len(self.lag.samples)
            p50, p99 = percentile(recent, 50), percentile(recent, 99)
        return FleetSnapshot(
            name=self.name,
            t=self.clock.now(),
            motes=sum(1 for r in self.runners.values() if r.alive),
            frames_tx=tot.frames_tx,
            frames_rx=tot.frames_rx,
            unicast_ok=tot.unicast_ok,
            unicast_failed=tot.unicast_failed,
            malformed=tot.malformed,
            lag_p50_ms=p50,
            lag_p99_ms=p99,
        )

    # ------------------------------------------------------------------ control plane

    def _on_query(self, query: zenoh.Query) -> None:
        # Zenoh thread: copy the payload and hand the query to the loop.
        payload = query.payload.to_bytes() if query.payload is not None else b""
        loop = self._loop
        if loop is None or self._closed:
            query.drop()  # type: ignore[no-untyped-call]
            return
        try:
            loop.call_soon_threadsafe(self._answer, query, payload)
        except RuntimeError:  # loop closed
            query.drop()  # type: ignore[no-untyped-call]

    def _answer(self, query: zenoh.Query, payload: bytes) -> None:
        try:
            reply = self.control_request(payload)
            query.reply(f"{self.prefix}/ctl/fleet/{self.name}", json.dumps(reply).encode())
        except zenoh.ZError as e:  # the asker went away
            log.debug("control reply failed: %s", e)
        finally:
            query.drop()  # type: ignore[no-untyped-call]

    def control_request(self, payload: bytes) -> dict[str, Any]:
        """Handle one control request (JSON). Bad requests are answered, never raised.

        ``{"op": "add", "node": {<a [[nodes]] entry>}}``,
        ``{"op": "kill", "id": N}``, ``{"op": "list"}``, ``{"op": "stats"}``.
        Replies carry ``fleet``, ``ok``, ``done`` (this fleet acted) and
        ``error`` or data.
        """
        base: dict[str, Any] = {"fleet": self.name, "pid": os.getpid()}
        try:
            req = json.loads(payload)
        except (UnicodeDecodeError, json.JSONDecodeError) as e:
            return {**base, "ok": False, "done": False, "error": f"not JSON: {e}"}
        if not isinstance(req, dict) or not isinstance(req.get("op"), str):
            return {**base, "ok": False, "done": False, "error": 'expected {"op": ...}'}
        op = req["op"]
        if op == "list":
            pos = self.positions()
            return {
                **base,
                "ok": True,
                "done": True,
                "t": self.clock.now(),
                "motes": {str(i): [round(x, 3), round(y, 3)] for i, (x, y) in pos.items()},
            }
        if op == "stats":
            snap = self.snapshot()
            return {**base, "ok": True, "done": True, "snapshot": _snap_dict(snap)}
        if op == "kill":
            nid = req.get("id")
            if not isinstance(nid, int) or isinstance(nid, bool):
                return {**base, "ok": False, "done": False, "error": "kill needs an integer id"}
            done = self.kill(nid)
            return {**base, "ok": True, "done": done, "id": nid}
        if op == "add":
            return {**base, **self._control_add(req.get("node"))}
        return {**base, "ok": False, "done": False, "error": f"unknown op {op!r}"}

    def _control_add(self, entry: object) -> dict[str, Any]:
        try:
            spec = self.parse_node(entry)
        except DeploymentError as e:
            return {"ok": False, "done": False, "error": str(e)}
        # Deployment motes belong to the process that owns their original spec;
        # new ids go by position. So exactly one process of a launcher acts.
        original = next((s for s in self.deployment.nodes if s.id == spec.id), None)
        if not self.owns(original or spec):
            return {"ok": True, "done": False, "id": spec.id}
        try:
            self.add_mote(spec)
        except (ValueError, DeploymentError) as e:
            return {"ok": False, "done": False, "error": str(e), "id": spec.id}
        return {"ok": True, "done": True, "id": spec.id}

    def parse_node(self, entry: object) -> NodeSpec:
        """Validate one ``[[nodes]]``-style entry against this deployment's area and radio."""
        if not isinstance(entry, Mapping):
            raise DeploymentError("add: 'node' must be an object like a [[nodes]] entry")
        dep = self.deployment
        doc = {
            "name": dep.name,
            "radio": dep.radio,
            "seed": dep.seed,
            "tx_power_dbm": dep.tx_power_dbm,
            "area": list(dep.area),
            "nodes": [dict(entry)],
        }
        # Known node kinds, plus whatever kinds this deployment already runs
        # (a custom core factory may use its own).
        kinds = {s.kind for s in dep.nodes}
        with contextlib.suppress(ImportError):
            from awaremw.nodes import kind_names

            kinds.update(kind_names())
        spec = parse_deployment(doc, None, kinds).nodes[0]
        return spec


def _snap_dict(s: FleetSnapshot) -> dict[str, Any]:
    return {
        "name": s.name,
        "t": s.t,
        "motes": s.motes,
        "frames_tx": s.frames_tx,
        "frames_rx": s.frames_rx,
        "unicast_ok": s.unicast_ok,
        "unicast_failed": s.unicast_failed,
        "malformed": s.malformed,
        "lag_p50_ms": s.lag_p50_ms,
        "lag_p99_ms": s.lag_p99_ms,
    }


# --------------------------------------------------------------------------- workers


@dataclass(frozen=True)
class WorkerParams:
    """Everything a worker process needs (pickled to it)."""

    name: str
    deployment: Deployment
    stripe: XStripe | IdModulo
    connect: tuple[str, ...]
    listen: tuple[str, ...]
    speed: float
    prefix: str
    handler: Handler
    core_factory: CoreFactory | None
    progress_s: float | None
    collect_lag: bool
    exclude_kinds: frozenset[str] = frozenset()
    track_links: bool = False


@dataclass(frozen=True, slots=True)
class WorkerFilter:
    """A worker's node filter: its stripe, minus the excluded kinds (picklable)."""

    stripe: XStripe | IdModulo
    exclude_kinds: frozenset[str] = frozenset()

    def __call__(self, spec: NodeSpec) -> bool:
        return spec.kind not in self.exclude_kinds and self.stripe(spec)


@dataclass
class WorkerResult:
    """What a worker sends back when it stops."""

    name: str
    motes: int
    counters: dict[int, dict[str, int]]
    stats: dict[str, int]
    lag_ms: list[float]
    cpu_s: float
    wall_s: float
    error: str | None = None
    extra: dict[str, Any] = field(default_factory=dict)


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
        speed=p.speed,
        prefix=p.prefix,
        connect=p.connect,
        listen=p.listen,
        node_filter=WorkerFilter(p.stripe, p.exclude_kinds),
        autostart=False,
        name=p.name,
        handler=p.handler,
        collect_lag=p.collect_lag,
        freeze_gc=True,
        track_links=p.track_links,
    )
    cpu0 = time.process_time()
    wall0 = time.perf_counter()
    error: str | None = None
    progress: asyncio.Task[None] | None = None
    try:
        await fleet.setup()
        conn.send(("ready", len(fleet.runners)))
        while True:
            kind, arg = await inbox.get()
            if kind == "start":
                fleet.start(float(arg))
                cpu0, wall0 = time.process_time(), time.perf_counter()
                if fleet.lag is not None:
                    fleet.lag.clear()
                if p.progress_s:
                    progress = asyncio.create_task(_report(fleet, conn, p.progress_s))
            elif kind == "lagreset":
                if fleet.lag is not None:
                    fleet.lag.clear()
            elif kind == "freeze":
                fleet.medium.freeze()
                conn.send(("frozen", fleet.now()))
            elif kind == "stop":
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
        counters = {i: c.as_dict() for i, c in fleet.counters.items()} if fleet._medium else {}
        stats = fleet.medium.stats.as_dict() if fleet._medium else {}
        extra: dict[str, Any] = {}
        if fleet._medium is not None and fleet.medium.links is not None:
            extra["links"] = [(a, b, n) for (a, b), n in sorted(fleet.medium.links.items())]
        result = WorkerResult(
            name=p.name,
            motes=len(fleet.runners),
            counters=counters,
            stats=stats,
            lag_ms=list(fleet.lag.samples) if fleet.lag is not None else [],
            cpu_s=time.process_time() - cpu0,
            wall_s=time.perf_counter() - wall0,
            error=error,
            extra=extra,
        )
        await fleet.aclose()
        with contextlib.suppress(OSError, BrokenPipeError):
            conn.send(("result", result))


async def _report(fleet: Fleet, conn: multiprocessing.connection.Connection, every: float) -> None:
    while True:
        await asyncio.sleep(every)
        with contextlib.suppress(OSError, BrokenPipeError):
            conn.send(("progress", fleet.snapshot()))


# --------------------------------------------------------------------------- launcher


_WORKER_CMD = "from awaremw.runtime.fleet import worker_entry; worker_entry()"


class LaunchError(RuntimeError):
    """A worker process failed to start, to set up or to run."""


class FleetLauncher:
    """Run a deployment over ``processes`` worker processes joined by a Zenoh router.

    With ``connect`` the workers join that router (e.g. ``awaremw router``);
    otherwise the launcher starts an embedded router listening on ``listen``
    (default: a free loopback port), available as :attr:`endpoint` for
    gateways and ``awaremw fleet-ctl``.
    """

    def __init__(
        self,
        deployment: Deployment,
        *,
        processes: int,
        core_factory: CoreFactory | None = None,
        speed: float = 1.0,
        prefix: str = DEFAULT_PREFIX,
        connect: Sequence[str] = (),
        listen: Sequence[str] = (),
        handler: Handler = DEFAULT_HANDLER,
        progress_s: float | None = None,
        on_progress: Callable[[FleetSnapshot], None] | None = None,
        collect_lag: bool = True,
        ready_timeout_s: float = 120.0,
        start_delay_s: float = 0.3,
        exclude_kinds: Iterable[str] = (),
        track_links: bool = False,
        layout: Layout = "stripes",
    ) -> None:
        if processes < 1:
            raise ValueError("processes must be >= 1")
        self.deployment = deployment
        self.processes = processes
        self.core_factory = core_factory
        self.speed = speed
        self.prefix = prefix
        self.connect = tuple(connect)
        self.listen = tuple(listen)
        self.handler: Handler = handler
        self.progress_s = progress_s
        self.on_progress = on_progress
        self.collect_lag = collect_lag
        self.ready_timeout_s = ready_timeout_s
        self.start_delay_s = start_delay_s
        self.exclude_kinds = frozenset(exclude_kinds)
        self.track_links = track_links
        self.layout: Layout = layout
        self.clock = EmulatedClock(speed)
        self.router: EmbeddedRouter | None = None
        self.endpoint = ""
        self.start_wall = 0.0
        self.results: list[WorkerResult] = []
        self.motes_per_worker: list[int] = []
        self._procs: list[subprocess.Popen[bytes]] = []
        self._conns: list[multiprocessing.connection.Connection] = []
        self._progress: dict[str, FleetSnapshot] = {}
        self._msgs: asyncio.Queue[tuple[int, str, Any]] = asyncio.Queue()
        self._failed: str | None = None

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
        if self.connect:
            self.endpoint = self.connect[0]
        else:
            listen = self.listen or (free_tcp_endpoint(),)
            self.router = EmbeddedRouter(listen)
            await asyncio.to_thread(self.router.start)
            self.endpoint = listen[0]
        loop = asyncio.get_running_loop()
        for k, stripe in enumerate(partition(self.deployment, self.processes, self.layout)):
            params = WorkerParams(
                name=f"w{k}",
                deployment=self.deployment,
                stripe=stripe,
                connect=(self.endpoint,),
                listen=("tcp/127.0.0.1:0",),  # lets peers link directly (gossip)
                speed=self.speed,
                prefix=self.prefix,
                handler=self.handler,
                core_factory=self.core_factory,
                progress_s=self.progress_s,
                collect_lag=self.collect_lag,
                exclude_kinds=self.exclude_kinds,
                track_links=self.track_links,
            )
            psock, csock = socket.socketpair()
            proc = subprocess.Popen(
                [sys.executable, "-c", _WORKER_CMD, str(csock.fileno())],
                pass_fds=(csock.fileno(),),
            )
            csock.close()
            conn = multiprocessing.connection.Connection(psock.detach())
            self._procs.append(proc)
            self._conns.append(conn)
            conn.send(params)
            loop.add_reader(conn.fileno(), self._readable, k)
        ready: dict[int, int] = {}
        deadline = loop.time() + self.ready_timeout_s
        while len(ready) < len(self._procs):
            k, kind, arg = await self._next(deadline, "set up")
            if kind == "ready":
                ready[k] = int(arg)
            elif kind == "result":
                raise LaunchError(f"worker w{k} failed during setup: {arg.error}")
        self.motes_per_worker = [ready[k] for k in range(len(self._procs))]
        # Routes propagate through the router in a moment; start shortly after.
        self.start_wall = time.time() + self.start_delay_s
        self.clock.restart(self.start_wall)
        for c in self._conns:
            c.send(("start", self.start_wall))

    def _readable(self, k: int) -> None:
        conn = self._conns[k]
        try:
            kind, arg = conn.recv()
        except (EOFError, OSError):
            asyncio.get_running_loop().remove_reader(conn.fileno())
            self._msgs.put_nowait((k, "gone", None))
            return
        if kind == "progress":
            self._progress[arg.name] = arg
            if self.on_progress is not None and len(self._progress) == len(self._procs):
                self.on_progress(merge_snapshots(self._progress.values()))
                self._progress.clear()
            return
        if kind == "result" and arg.error:
            self._failed = f"worker {arg.name}: {arg.error}"
        self._msgs.put_nowait((k, kind, arg))

    async def _next(self, deadline: float, doing: str) -> tuple[int, str, Any]:
        loop = asyncio.get_running_loop()
        try:
            k, kind, arg = await asyncio.wait_for(self._msgs.get(), deadline - loop.time())
        except TimeoutError:
            raise LaunchError(f"workers did not {doing} within the time limit") from None
        if kind == "gone":
            code = self._procs[k].poll()
            raise LaunchError(f"worker w{k} exited unexpectedly (exit code {code})")
        return k, kind, arg

    async def run(self, duration: float | None = None) -> None:
        """Wait until emulated time ``duration`` (forever if None) or a worker fails."""
        while True:
            if self._failed:
                raise LaunchError(self._failed)
            left = math.inf if duration is None else self.clock.wall_seconds(duration - self.now())
            if left <= 0:
                return
            try:
                k, kind, arg = await asyncio.wait_for(self._msgs.get(), min(left, 3600.0))
            except TimeoutError:
                continue
            if kind == "gone":
                raise LaunchError(f"worker w{k} exited unexpectedly")
            if kind == "result":
                raise LaunchError(f"worker {arg.name} stopped: {arg.error or 'no reason'}")

    def reset_lag(self) -> None:
        """Workers drop the timer-lag samples taken so far (end of a warm-up)."""
        for c in self._conns:
            with contextlib.suppress(OSError):
                c.send(("lagreset", None))

    async def freeze(self, grace_s: float = 0.5) -> None:
        """Stop every worker's radio from starting new frames; wait ``grace_s`` (wall)
        for frames in flight to land (benchmarks count deliveries afterwards)."""
        for c in self._conns:
            with contextlib.suppress(OSError):
                c.send(("freeze", None))
        await asyncio.sleep(grace_s)

    async def _shutdown(self) -> None:
        loop = asyncio.get_running_loop()
        for c in self._conns:
            with contextlib.suppress(OSError):
                c.send(("stop", None))
        got: dict[str, WorkerResult] = {r.name: r for r in self.results}
        deadline = loop.time() + 30.0
        while len(got) < len(self._procs) and loop.time() < deadline:
            try:
                k, kind, arg = await asyncio.wait_for(self._msgs.get(), deadline - loop.time())
            except TimeoutError:
                break
            if kind == "result":
                got[arg.name] = arg
            elif kind == "gone":
                got.setdefault(f"w{k}", _lost(f"w{k}"))
        self.results = [got.get(f"w{k}") or _lost(f"w{k}") for k in range(len(self._procs))]
        for c in self._conns:
            with contextlib.suppress(OSError, ValueError):
                loop.remove_reader(c.fileno())
            c.close()
        for k, p in enumerate(self._procs):
            try:
                await asyncio.to_thread(p.wait, 10.0)
            except subprocess.TimeoutExpired:
                log.warning("worker w%d did not stop; terminating it", k)
                p.terminate()
                try:
                    await asyncio.to_thread(p.wait, 5.0)
                except subprocess.TimeoutExpired:
                    p.kill()
                    await asyncio.to_thread(p.wait)
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

    def counters(self) -> dict[int, MoteCounters]:
        """Per-mote counters merged from every worker (after the launcher exited)."""
        out: dict[int, MoteCounters] = {}
        for r in self.results:
            for nid, d in r.counters.items():
                out.setdefault(nid, MoteCounters()).add(MoteCounters(**d))
        return out


def _lost(name: str) -> WorkerResult:
    return WorkerResult(name, 0, {}, {}, [], 0.0, 0.0, error="no result (process lost)")
