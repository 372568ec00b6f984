"""A fleet's figures: progress (:class:`FleetSnapshot`, taken by
:class:`FleetStats` in a process and merged over processes by
:class:`MergedStats`) and what each process returns when it stops
(:class:`WorkerResult`)."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Mapping
from dataclasses import asdict, dataclass, field
from typing import Any

from awaremw.radio.counters import MoteCounters
from awaremw.runtime.driver import LagStats, percentile
from awaremw.runtime.fleet.figures import FigureTaker, ProcessFigures, merge_figures
from awaremw.world.clock import EmulatedClock


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
    figures: ProcessFigures | None = None  # with FleetSettings.figures: for the metrics

    def line(self) -> str:
        def ms(v: float) -> str:
            return "-" if math.isnan(v) else f"{v:.1f}ms"

        return (
            f"[{self.name}] t={self.t:8.1f}s motes={self.motes} tx={self.frames_tx} "
            f"rx={self.frames_rx} uc_ok={self.unicast_ok} uc_fail={self.unicast_failed} "
            f"malformed={self.malformed} lag p50={ms(self.lag_p50_ms)} p99={ms(self.lag_p99_ms)}"
        )

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


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
        figures=(
            merge_figures(x.figures for x in s if x.figures is not None)
            if any(x.figures is not None for x in s)
            else None
        ),
    )


class FleetStats:
    """Takes a fleet's snapshots: counter totals so far, lag percentiles over
    the samples since the previous snapshot."""

    def __init__(
        self,
        name: str,
        clock: EmulatedClock,
        lag: LagStats | None,
        counters: Callable[[], Mapping[int, MoteCounters]],
        on_air: Callable[[], int],
        figures: FigureTaker | None = None,
    ) -> None:
        self.name = name
        self.clock = clock
        self.lag = lag
        self._counters = counters
        self._on_air = on_air
        self._figures = figures
        self._lag_mark = 0
        # Totals of earlier incarnations of this worker (a restarted one goes on from them).
        self.base: dict[str, int] = {}

    def snapshot(self, *, window: bool = True) -> FleetSnapshot:
        """Totals so far; lag percentiles over the samples since the last snapshot
        (``window=False``: a look that does not start a new window, e.g. a scrape)."""
        tot = MoteCounters()
        counters = self._counters()
        for c in counters.values():
            tot.add(c)
        p50 = p99 = math.nan
        if self.lag is not None:
            recent = self.lag.since(self._lag_mark)  # bounded: LagStats keeps a ring
            if window:
                self._lag_mark = self.lag.count
            p50, p99 = percentile(recent, 50), percentile(recent, 99)
        b = self.base
        return FleetSnapshot(
            name=self.name,
            t=self.clock.now(),
            motes=self._on_air(),
            frames_tx=tot.frames_tx + b.get("frames_tx", 0),
            frames_rx=tot.frames_rx + b.get("frames_rx", 0),
            unicast_ok=tot.unicast_ok + b.get("unicast_ok", 0),
            unicast_failed=tot.unicast_failed + b.get("unicast_failed", 0),
            malformed=tot.malformed + b.get("malformed", 0),
            lag_p50_ms=p50,
            lag_p99_ms=p99,
            figures=None if self._figures is None else self._figures.take(counters),
        )


class MergedStats:
    """A launcher's progress: the latest snapshot of each worker, merged."""

    def __init__(self) -> None:
        self.latest: dict[int, FleetSnapshot] = {}  # worker index -> its last snapshot

    def snapshot(self, *, window: bool = True) -> FleetSnapshot:
        """The workers' latest snapshots merged (taking it changes nothing)."""
        return merge_snapshots(self.latest.values())


@dataclass
class WorkerResult:
    """What one process of a fleet returns when it stops (a launcher's worker,
    or a fleet run in this process)."""

    name: str
    motes: int
    counters: dict[int, dict[str, int]]
    stats: dict[str, int]
    lag_ms: list[float]
    cpu_s: float
    wall_s: float
    error: str | None = None
    extra: dict[str, Any] = field(default_factory=dict)


def lost(name: str) -> WorkerResult:
    return WorkerResult(name, 0, {}, {}, [], 0.0, 0.0, error="no result (process lost)")


def merged_counters(results: Iterable[WorkerResult]) -> dict[int, MoteCounters]:
    """Per-mote counters over every process's result."""
    out: dict[int, MoteCounters] = {}
    for r in results:
        for nid, d in r.counters.items():
            out.setdefault(nid, MoteCounters()).add(MoteCounters(**d))
    return out


def plugin_results(results: Iterable[WorkerResult]) -> list[Any]:
    """Each process's ``plugin.result()`` in order (one that returned none left out)."""
    return [r.extra["plugin"] for r in results if "plugin" in r.extra]


def merged_links(results: Iterable[WorkerResult]) -> dict[tuple[int, int], int]:
    """Frames delivered per (src, dst) over every process (with ``track_links``)."""
    out: dict[tuple[int, int], int] = {}
    for r in results:
        for a, b, n in r.extra.get("links", ()):
            out[(a, b)] = out.get((a, b), 0) + n
    return out
