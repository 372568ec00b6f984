"""Fleets of motes on the Zenoh radio: one interface, one process or many.

:func:`open_fleet` gives an :class:`AnyFleet`: a
:class:`~awaremw.runtime.fleet.local.Fleet` when the motes run in this process,
a :class:`~awaremw.runtime.fleet.launcher.FleetLauncher` of worker processes
otherwise, used the same way (docs/runtime.md, "One interface"). The modules:
``local``, ``launcher``, ``worker`` and ``pool`` (the processes),
``settings``, ``stats``, and the parts of a fleet (``motes``, ``control``,
``clock``, ``guard``).
"""

from __future__ import annotations

import math
from typing import Protocol, Self

from awaremw.radio.capture import Capture
from awaremw.radio.counters import MoteCounters
from awaremw.runtime.deployment import Deployment
from awaremw.runtime.fleet.launcher import FleetLauncher
from awaremw.runtime.fleet.local import Fleet
from awaremw.runtime.fleet.motes import CoreFactory
from awaremw.runtime.fleet.settings import FleetSettings, LauncherSettings
from awaremw.runtime.fleet.stats import FleetSnapshot, WorkerResult
from awaremw.runtime.partition import WorkerFilter, XStripe

__all__ = ["AnyFleet", "Fleet", "FleetLauncher", "FleetSettings", "LauncherSettings", "open_fleet"]


class Snapshots(Protocol):
    def snapshot(self) -> FleetSnapshot: ...


class AnyFleet(Protocol):
    """What every fleet offers, in this process or many (docs/runtime.md)."""

    endpoint: str  # where gateways, sniffers and fleet-ctl reach it
    results: list[WorkerResult]  # each process's figures, after the fleet closed
    capture: Capture | None  # the radio capture of settings.pcap

    @property
    def stats(self) -> Snapshots: ...  # progress: counter totals, recent timer lag

    async def __aenter__(self) -> Self: ...
    async def __aexit__(self, *exc: object) -> None: ...
    async def run(self, duration: float | None = None) -> None: ...
    def now(self) -> float: ...
    def counters(self) -> dict[int, MoteCounters]: ...  # a launcher's: after it closed
    async def freeze(self, grace_s: float = 0.5) -> None: ...


def open_fleet(
    deployment: Deployment,
    core_factory: CoreFactory,
    settings: LauncherSettings,
    *,
    part: XStripe | None = None,
) -> AnyFleet:
    """The fleet ``settings`` asks for, not entered yet: in this process when
    :attr:`LauncherSettings.local`, else worker processes. ``part`` (only in
    this process) keeps one stripe of the deployment, e.g. one host's;
    ``settings.exclude_kinds`` applies either way."""
    if not settings.local:
        if part is not None:
            raise ValueError("a part of a deployment runs in one process without a router here")
        return FleetLauncher(deployment, core_factory, settings)
    keep = WorkerFilter(part or XStripe(-math.inf, math.inf), settings.exclude_kinds)
    return Fleet(deployment, core_factory, settings.in_process(), node_filter=keep)
