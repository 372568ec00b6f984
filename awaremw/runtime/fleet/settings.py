"""Settings of a fleet (:class:`FleetSettings`) and of a launcher of worker
processes (:class:`LauncherSettings`): plain frozen data, picklable, so a
launcher hands a worker its fleet's settings as they are."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

from awaremw.radio.security import RadioSecurity
from awaremw.radio.zenoh_medium import DEFAULT_HANDLER, DEFAULT_PREFIX, Handler
from awaremw.runtime.partition import Layout
from awaremw.runtime.zenoh_session import SessionSettings


def _endpoints(v: Iterable[str]) -> tuple[str, ...]:
    """A tuple of endpoints (a caller may hand a list); a lone string is a bug."""
    if isinstance(v, str):
        raise TypeError(f"endpoints must be a sequence of strings, not the string {v!r}")
    return tuple(v)


class WorkerPlugin(Protocol):
    """Code a launcher runs inside every worker beside its fleet (picklable: each
    worker gets its own copy), e.g. a benchmark's event tally.

    ``fleet`` is the process's :class:`~awaremw.runtime.fleet.local.Fleet` (typed
    ``Any`` here: this module is below it). ``setup(fleet)`` once the
    fleet is set up (motes built, before the start): register event hooks
    here. ``started(fleet)`` right after the shared start
    (schedule work on the loop here). ``result()`` when the worker stops: a
    picklable summary, returned in ``WorkerResult.extra["plugin"]``. An
    exception in any of them fails the worker (it is our bug, or the plugin's).
    """

    def setup(self, fleet: Any) -> None: ...

    def started(self, fleet: Any) -> None: ...

    def result(self) -> Any: ...


@dataclass(frozen=True, slots=True)
class FleetSettings:
    """How one fleet runs (one process).

    ``connect``/``listen``: endpoints of the session the fleet opens (peer
    mode, multicast scouting off) when it is not given one. ``autostart``
    False: ``async with`` only sets up; the caller calls ``start(start_wall)``
    (a launcher's worker, a gateway joining a running emulation).
    ``control``: declare the control queryable ``<prefix>/ctl/fleet/<name>``.
    ``freeze_gc``: ``gc.freeze()`` after setup (CLI, workers, benchmarks).
    ``track_links``: count deliveries per (src, dst) on the medium.
    ``session``: full session settings instead of ``connect``/``listen`` (e.g.
    a role's client settings with ``--secrets``, or client mode).
    ``security``: the radio is secured (frames sealed and checked with its
    network key; docs/security.md). The core factory must then build motes
    for the payload MTU (``awaremw.nodes.KindsFactory(security=...)``).
    ``plugin``: a :class:`WorkerPlugin` run beside the fleet. ``pcap``: the
    medium's tap writes every frame and reception to this file (pcapng).
    ``lag_from_s``: timer lag is sampled from this emulated time on (a warm-up).
    ``figures``: measure what the metrics show (frames by kind on a counting tap,
    records produced, a timer-lag histogram, energy by mote kind): sent with
    every progress snapshot (:mod:`awaremw.runtime.fleet.figures`).
    """

    name: str = "main"
    speed: float = 1.0
    prefix: str = DEFAULT_PREFIX
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    handler: Handler = DEFAULT_HANDLER
    start_wall: float | None = None
    autostart: bool = True
    control: bool = True
    collect_lag: bool = True
    freeze_gc: bool = False
    track_links: bool = False
    session: SessionSettings | None = None
    security: RadioSecurity | None = None
    plugin: WorkerPlugin | None = None
    pcap: str | None = None
    figures: bool = False
    lag_from_s: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "connect", _endpoints(self.connect))
        object.__setattr__(self, "listen", _endpoints(self.listen))


@dataclass(frozen=True, slots=True)
class LauncherSettings:
    """How a fleet runs over ``processes`` processes (:func:`~awaremw.runtime.fleet.open_fleet`):
    one runs in this process, more are the workers of a
    :class:`~awaremw.runtime.fleet.launcher.FleetLauncher`.

    ``connect``: join that router (e.g. ``awaremw router``) instead of starting
    an embedded one on ``listen`` (default: a free loopback port).
    ``progress_s``: workers report a snapshot that often (wall seconds).
    ``exclude_kinds``: kinds no worker runs (another process runs them).
    ``layout``: "stripes" along x, or "interleaved" by id (benchmarks only).
    ``router_config_file``: the embedded router starts from this Zenoh config
    (``awaremw keys init``'s router.json5: authentication, access control);
    ``worker_config_file``: a role's client config; the workers then join the
    router in client mode with it. ``security``: every worker's radio is
    secured with it (as :attr:`FleetSettings.security`). ``plugin``: a
    :class:`WorkerPlugin` each worker runs a copy of
    (pickled to it) beside its fleet (benchmarks: tallies, injections).
    ``max_restarts``: a worker that dies is started again, at most this many
    times within ``restart_window_s`` wall seconds (then the run fails); 0: a
    dead worker fails the run at once. ``pcap``: a capture of the radio (one
    process: the medium's tap, receptions included; more: a sniffer on the
    router, docs/capture.md). ``lag_from_s``, ``figures``: as in
    :class:`FleetSettings`.

    In this process only (one process, no ``router_config_file``):
    ``start_wall`` (the shared start of fleets on several hosts) and
    ``client`` (the session in Zenoh client mode through ``connect``).
    """

    processes: int = 1
    speed: float = 1.0
    prefix: str = DEFAULT_PREFIX
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    handler: Handler = DEFAULT_HANDLER
    progress_s: float | None = None
    collect_lag: bool = True
    track_links: bool = False
    exclude_kinds: frozenset[str] = field(default_factory=frozenset)
    layout: Layout = "stripes"
    ready_timeout_s: float = 120.0
    start_delay_s: float = 0.3
    router_config_file: str | None = None
    worker_config_file: str | None = None
    security: RadioSecurity | None = None
    plugin: WorkerPlugin | None = None
    max_restarts: int = 5
    restart_window_s: float = 600.0
    control: bool = True
    pcap: str | None = None
    lag_from_s: float = 0.0
    start_wall: float | None = None
    client: bool = False
    figures: bool = False

    def __post_init__(self) -> None:
        if self.max_restarts < 0:
            raise ValueError("max_restarts must be >= 0")
        if self.processes < 1:
            raise ValueError("processes must be >= 1")
        if not self.local and (self.client or self.start_wall is not None):
            raise ValueError(
                "Zenoh client mode and a start time are for one process without a router "
                "of its own (no more processes, no access rules here)"
            )
        object.__setattr__(self, "connect", _endpoints(self.connect))
        object.__setattr__(self, "listen", _endpoints(self.listen))
        object.__setattr__(self, "exclude_kinds", frozenset(self.exclude_kinds))

    @property
    def local(self) -> bool:
        """The fleet runs in this process: one process, and no router of its own
        to apply access rules."""
        return self.processes == 1 and self.router_config_file is None

    def fleet(self, name: str, connect: tuple[str, ...]) -> FleetSettings:
        """The settings of worker ``name``'s fleet, joined to ``connect``."""
        return FleetSettings(
            name=name,
            speed=self.speed,
            prefix=self.prefix,
            connect=connect,
            listen=("tcp/127.0.0.1:0",),  # lets peers link directly (gossip)
            handler=self.handler,
            autostart=False,
            control=self.control,
            collect_lag=self.collect_lag,
            freeze_gc=True,
            track_links=self.track_links,
            session=self._client(connect),
            security=self.security,
            plugin=self.plugin,
            lag_from_s=self.lag_from_s,
            figures=self.figures,
        )

    def in_process(self) -> FleetSettings:
        """The settings of the one fleet when it runs in this process (:attr:`local`)."""
        client = SessionSettings("client", self.connect) if self.client else None
        return replace(
            self.fleet("main", self.connect),
            listen=self.listen,
            autostart=True,
            start_wall=self.start_wall,
            session=self._client(self.connect) or client,
            pcap=self.pcap,
        )

    def _client(self, connect: tuple[str, ...]) -> SessionSettings | None:
        if self.worker_config_file is None:
            return None
        return SessionSettings("client", connect, config_file=self.worker_config_file)
