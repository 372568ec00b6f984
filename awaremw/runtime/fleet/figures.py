"""What a fleet process measures for the metrics (docs/monitoring.md), when it
serves them (``FleetSettings.figures``): frames by kind and fate (a counting
tap on its medium), records its leaders produced, its timer lag as a
histogram, and radio energy by mote kind.

:class:`ProcessFigures` is plain frozen data, cumulative since the fleet
started: a worker sends it with its progress snapshot, and a launcher adds up
its workers' (:func:`merge_figures`), so one endpoint shows the whole fleet.
"""

from __future__ import annotations

import bisect
from collections.abc import Container, Iterable, Mapping
from dataclasses import dataclass

from awaremw.protocol.events import MoteEvent, RecordProduced
from awaremw.radio.counters import MoteCounters
from awaremw.radio.frame_counts import FrameCounts
from awaremw.runtime.deployment import Deployment
from awaremw.runtime.driver import LagStats

# Upper bounds of the timer-lag histogram, in seconds (Prometheus's ``le``).
LAG_BUCKETS_S = (0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0)


@dataclass(frozen=True, slots=True)
class ProcessFigures:
    """Cumulative figures of one fleet process (or, merged, of a whole fleet)."""

    frames: tuple[tuple[str, str, int], ...] = ()  # (kind, fate, count); fate "sent" or a cause
    lag_buckets: tuple[int, ...] = (0,) * len(LAG_BUCKETS_S)  # samples <= each bound
    lag_count: int = 0
    lag_sum_s: float = 0.0
    records_produced: int = 0
    energy_mj: tuple[tuple[str, float], ...] = ()  # (mote kind, radio energy so far)


def merge_figures(figs: Iterable[ProcessFigures]) -> ProcessFigures:
    frames: dict[tuple[str, str], int] = {}
    energy: dict[str, float] = {}
    buckets = [0] * len(LAG_BUCKETS_S)
    count = produced = 0
    total_s = 0.0
    for f in figs:
        for kind, fate, n in f.frames:
            frames[(kind, fate)] = frames.get((kind, fate), 0) + n
        for kind, mj in f.energy_mj:
            energy[kind] = energy.get(kind, 0.0) + mj
        buckets = [a + b for a, b in zip(buckets, f.lag_buckets, strict=True)]
        count += f.lag_count
        total_s += f.lag_sum_s
        produced += f.records_produced
    return ProcessFigures(
        frames=tuple(sorted((k, fate, n) for (k, fate), n in frames.items())),
        lag_buckets=tuple(buckets),
        lag_count=count,
        lag_sum_s=total_s,
        records_produced=produced,
        energy_mj=tuple(sorted(energy.items())),
    )


class FigureTaker:
    """Keeps one fleet process's figures; :meth:`take` reads them (cheap: the lag
    samples since the last take, one energy sum per mote)."""

    def __init__(
        self, deployment: Deployment, local: Container[int], lag: LagStats | None
    ) -> None:
        self.deployment = deployment
        self.frames = FrameCounts(local)
        self.lag = lag
        self._kind = {s.id: s.kind for s in deployment.nodes}
        self._power = {s.id: deployment.tx_power_of(s) for s in deployment.nodes}
        self._lag_mark = 0
        self._buckets = [0] * len(LAG_BUCKETS_S)
        self._lag_count = 0
        self._lag_sum_s = 0.0
        self.records_produced = 0

    def on_event(self, node: int, event: MoteEvent, now: float) -> None:
        """A fleet event hook: counts the records the motes produced."""
        if isinstance(event, RecordProduced):
            self.records_produced += 1

    def take(self, counters: Mapping[int, MoteCounters]) -> ProcessFigures:
        """The figures now; ``counters``: each local mote's radio counters."""
        self._read_lag()
        energy: dict[str, float] = {}
        preset = self.deployment.preset
        for node, c in counters.items():
            kind = self._kind.get(node, "other")
            mj = c.energy_mj(preset, self._power.get(node))
            energy[kind] = energy.get(kind, 0.0) + mj
        return ProcessFigures(
            frames=self.frames.as_rows(),
            lag_buckets=tuple(self._cumulative()),
            lag_count=self._lag_count,
            lag_sum_s=self._lag_sum_s,
            records_produced=self.records_produced,
            energy_mj=tuple(sorted(energy.items())),
        )

    def _read_lag(self) -> None:
        if self.lag is None:
            return
        if self.lag.count < self._lag_mark:  # cleared since (the start, a clock jump)
            self._lag_mark = 0
        for ms in self.lag.since(self._lag_mark):
            s = max(0.0, ms / 1000.0)
            i = bisect.bisect_left(LAG_BUCKETS_S, s)
            if i < len(self._buckets):
                self._buckets[i] += 1
            self._lag_count += 1
            self._lag_sum_s += s
        self._lag_mark = self.lag.count

    def _cumulative(self) -> list[int]:
        out, run = [], 0
        for n in self._buckets:
            run += n
            out.append(run)
        return out
