"""Run recording and metrics against ground truth.

:class:`Recorder` takes the motes' events (any driver: the virtual clock's
``on_event`` hook, the fleet's event stream) and the records that reached the
IP side, and keeps what the metrics need: every membership change of every
mote as a step function of time, leader elections, handovers, merges, records
produced by leaders and records delivered.

The metrics (docs/experiments.md defines each):

* membership precision / recall / F1, micro-averaged over sampling instants:
  the motes whose noise-free values meet the condition at ``t`` against the
  motes in a group of the type, allowing the protocol ``settle`` seconds (one
  leader-beacon period) to reach that state (:func:`membership_series`);
* distinct group ids seen over a window; handovers; time to the first record;
  record delivery ratio; frames and radio energy per mote.

:func:`scored` is the start every experiment's ``analyse`` shares: the ground
truth, the settle lag and the tracking group's membership scored against it.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, assert_never

from awaremw.experiments.scenario import Scenario
from awaremw.experiments.truth import GroundTruth
from awaremw.nodes import config_for
from awaremw.protocol import events as ev
from awaremw.protocol.events import MoteDown, MoteEvent, MoteUp
from awaremw.protocol.frames import DataRecord, GroupTypeDef

RecordKey = tuple[int, int, int, int]  # channel, group type, group id, epoch
SAMPLE_DT = 0.5  # s between scored instants


@dataclass(frozen=True, slots=True)
class State:
    """A mote's membership in one group type from time ``t`` on (gid None: none)."""

    t: float
    gid: int | None
    leader: bool


@dataclass(frozen=True, slots=True)
class Election:
    t: float
    node: int
    group_type: int
    group_id: int
    cause: str


@dataclass(frozen=True, slots=True)
class Arrival:
    """A data record that reached the IP side (first copy of its key)."""

    t: float
    record: DataRecord
    via: str  # "root" (Delivered at a gateway mote) or "mqtt"


class Recorder:
    """Collects a run's events into queryable timelines."""

    def __init__(self, record_sources: Iterable[str] = ("root", "mqtt")) -> None:
        # Where a record counts as arrived: "root" (Delivered at a gateway mote)
        # and/or "mqtt" (an MQTT subscriber). Others are kept in by_source only.
        self.record_sources = frozenset(record_sources)
        self.by_source: dict[str, dict[RecordKey, float]] = {}
        self.timeline: dict[tuple[int, int], list[State]] = {}  # (node, type) -> states
        self._times: dict[tuple[int, int], list[float]] = {}
        self.elections: list[Election] = []
        self.handovers: list[tuple[float, int, int, int, int]] = []  # t, type, gid, from, to
        self.yields: list[tuple[float, int, int, int, int]] = []  # t, node, type, gid, successor
        self.produced: dict[RecordKey, tuple[float, DataRecord]] = {}
        self.arrivals: dict[RecordKey, Arrival] = {}
        self.mqtt_messages = 0
        self.down: dict[int, float] = {}
        self.rssi: dict[int, list[tuple[float, float | None]]] = {}
        self.event_counts: dict[str, int] = {}

    # ------------------------------------------------------------------ inputs

    def on_event(self, node: int, event: MoteEvent, t: float) -> None:
        """Feed one event of ``node`` at time ``t`` (VirtualNetwork.on_event signature)."""
        name = type(event).__name__  # a statistic only; dispatch is by type
        self.event_counts[name] = self.event_counts.get(name, 0) + 1
        match event:
            case ev.GroupJoined():
                self._set(event.node, event.group_type, t, event.group_id, False)
            case ev.LeaderElected():
                self._set(event.node, event.group_type, t, event.group_id, True)
                self.elections.append(
                    Election(t, event.node, event.group_type, event.group_id, event.cause.value)
                )
            case ev.GroupLeft():
                self._set(event.node, event.group_type, t, None, False)
            case ev.HandoverSent():
                self.handovers.append((t, event.group_type, event.group_id, event.node, event.to))
            case ev.LeaderYielded():
                self.yields.append(
                    (t, event.node, event.group_type, event.group_id, event.successor)
                )
            case ev.RecordProduced(record=r):
                self.produced.setdefault(_key(r), (t, r))
            case ev.Delivered(payload=DataRecord() as r):
                self.on_record(t, r, "root")
            case MoteDown():
                self.down.setdefault(node, t)
                for (n, g), states in list(self.timeline.items()):
                    if n == node and states[-1].gid is not None:
                        self._set(n, g, t, None, False)
            case (
                ev.Delivered() | MoteUp() | ev.MalformedFrame() | ev.ItemAdopted()
                | ev.ItemRefused() | ev.InjectSuperseded() | ev.ParentChanged() | ev.DataDropped()
                | ev.GroupTypeRefused() | ev.ChannelRefused() | ev.CommandExecuted()
                | ev.NeighbourFound() | ev.NeighbourLost() | ev.PingResult()
            ):  # fmt: skip
                pass  # counted only
            case _:
                assert_never(event)

    def on_record(self, t: float, record: DataRecord, via: str = "mqtt") -> None:
        """A record reached the IP side (MQTT subscriber or a root's Delivered event)."""
        if via == "mqtt":
            self.mqtt_messages += 1
        self.by_source.setdefault(via, {}).setdefault(_key(record), t)
        if via in self.record_sources:
            self.arrivals.setdefault(_key(record), Arrival(t, record, via))

    def on_rssi(self, node: int, t: float, dbm: float | None) -> None:
        """A sample of what ``node`` believes the robot's RSSI is (for Fig. 9)."""
        self.rssi.setdefault(node, []).append((t, dbm))

    def _set(self, node: int, gtype: int, t: float, gid: int | None, leader: bool) -> None:
        k = (node, gtype)
        states = self.timeline.setdefault(k, [])
        times = self._times.setdefault(k, [])
        states.append(State(t, gid, leader))
        times.append(t)

    # ------------------------------------------------------------------ queries

    def state_at(self, node: int, gtype: int, t: float) -> State | None:
        """The last state of ``node`` at or before ``t`` (None: never in a group)."""
        k = (node, gtype)
        times = self._times.get(k)
        if not times:
            return None
        i = bisect.bisect_right(times, t)
        return self.timeline[k][i - 1] if i else None

    def members_at(self, gtype: int, t: float) -> dict[int, State]:
        """Motes in a group of type ``gtype`` at ``t``: node -> state (gid, leader)."""
        out: dict[int, State] = {}
        for node, g in self.timeline:
            if g != gtype:
                continue
            s = self.state_at(node, gtype, t)
            if s is not None and s.gid is not None:
                out[node] = s
        return out

    def groups_at(self, gtype: int, t: float) -> dict[int, set[int]]:
        """gid -> members at ``t``."""
        out: dict[int, set[int]] = {}
        for node, s in self.members_at(gtype, t).items():
            assert s.gid is not None
            out.setdefault(s.gid, set()).add(node)
        return out

    def leaders_at(self, gtype: int, t: float) -> dict[int, int]:
        """gid -> leader node at ``t`` (a group may briefly have none or two)."""
        return {
            s.gid: node
            for node, s in self.members_at(gtype, t).items()
            if s.leader and s.gid is not None
        }

    def group_ids(self, gtype: int, t0: float, t1: float) -> set[int]:
        """Every group id a mote of type ``gtype`` was in during [t0, t1]."""
        ids: set[int] = set()
        for (node, g), states in self.timeline.items():
            if g != gtype:
                continue
            s0 = self.state_at(node, g, t0)
            if s0 is not None and s0.gid is not None:
                ids.add(s0.gid)
            ids.update(s.gid for s in states if t0 <= s.t <= t1 and s.gid is not None)
        return ids


def lasting_group_ids(
    rec: Recorder, gtype: int, t0: float, t1: float, min_s: float, dt: float = 0.5
) -> dict[int, float]:
    """Group ids that had members for at least ``min_s`` (sampled every ``dt``) in
    [t0, t1], with how long: transient groups (a fringe mote that created one
    and yielded a moment later) are left out."""
    alive: dict[int, float] = {}
    for t in instants(t0, t1, dt):
        for gid in rec.groups_at(gtype, t):
            alive[gid] = alive.get(gid, 0.0) + dt
    return {g: s for g, s in sorted(alive.items()) if s >= min_s}


def led_group_ids(rec: Recorder, gtype: int) -> set[int]:
    """Group ids of type ``gtype`` whose leader produced at least one data record.

    A group that never led a record is a contender the merge rule absorbed before
    its first epoch closed (a spontaneous leader at a fringe or at a split): it
    never carried data to a client (docs/experiments.md, "data ids")."""
    return {k[2] for k in rec.produced if k[1] == gtype}


def _key(r: DataRecord) -> RecordKey:
    return (r.channel, r.group_type, r.group_id, r.epoch)


# --------------------------------------------------------------------------- metrics


@dataclass(frozen=True, slots=True)
class MembershipScore:
    tp: int
    fp: int
    fn: int
    instants: int

    @property
    def precision(self) -> float:
        return self.tp / (self.tp + self.fp) if self.tp + self.fp else 1.0

    @property
    def recall(self) -> float:
        return self.tp / (self.tp + self.fn) if self.tp + self.fn else 1.0

    @property
    def f1(self) -> float:
        p, r = self.precision, self.recall
        return 2 * p * r / (p + r) if p + r else 0.0


@dataclass(frozen=True, slots=True)
class Instant:
    """One scored instant: protocol members (within the settling time) and true
    members at t (see :func:`membership_series`)."""

    t: float
    members: frozenset[int]
    truth: frozenset[int]


def instants(start: float, end: float, dt: float) -> list[float]:
    n = max(0, math.floor((end - start) / dt + 1e-9))
    return [start + i * dt for i in range(n + 1)]


def membership_series(
    rec: Recorder,
    truth: GroundTruth,
    defn: GroupTypeDef,
    gtype: int,
    times: Iterable[float],
    settle: float,
    among: Iterable[int] | None = None,
    step: float = 0.25,
) -> list[Instant]:
    """Protocol membership against the truth with a tolerance of ``settle`` s.

    At each instant ``t`` a mote counts as a member if the truth says so and it
    was in a group of the type at some moment of ``[t, t + settle]`` (the
    protocol reached the true state within the settling time), or if the truth
    says no and it stayed in a group through the whole of ``[t, t + settle]``
    (it did not leave in time). Membership is sampled every ``step`` s.
    """
    pool = None if among is None else frozenset(among)
    n = max(1, round(settle / step))
    out: list[Instant] = []
    for t in times:
        want = truth.members(defn, t, pool)
        seen = [frozenset(rec.members_at(gtype, t + settle * k / n)) for k in range(n + 1)]
        ever = frozenset().union(*seen)
        always = frozenset.intersection(*seen)
        got = (want & ever) | (always - want)
        if pool is not None:
            got &= pool
        out.append(Instant(t, got, want))
    return out


def score(series: Sequence[Instant]) -> MembershipScore:
    tp = sum(len(i.members & i.truth) for i in series)
    fp = sum(len(i.members - i.truth) for i in series)
    fn = sum(len(i.truth - i.members) for i in series)
    return MembershipScore(tp, fp, fn, len(series))


def handover_count(rec: Recorder, gtype: int, t0: float, t1: float) -> int:
    """Leader changes that kept the group id (handovers) in [t0, t1]."""
    return sum(
        1
        for e in rec.elections
        if e.group_type == gtype and t0 <= e.t <= t1 and e.cause == ev.ElectionCause.HANDOVER.value
    )


def first_arrival(
    rec: Recorder, after: float, channel: int | None = None, gtype: int | None = None
) -> Arrival | None:
    """The first record (of ``channel`` / group type) that arrived at or after ``after``."""
    best: Arrival | None = None
    for a in rec.arrivals.values():
        r = a.record
        if a.t < after or (channel is not None and r.channel != channel):
            continue
        if gtype is not None and r.group_type != gtype:
            continue
        if best is None or a.t < best.t:
            best = a
    return best


def delivery_ratio(rec: Recorder, until: float | None = None) -> float | None:
    """Records that arrived / records leaders produced (produced before ``until``)."""
    keys = [k for k, (t, _) in rec.produced.items() if until is None or t <= until]
    if not keys:
        return None
    return sum(1 for k in keys if k in rec.arrivals) / len(keys)


@dataclass(frozen=True, slots=True)
class Traffic:
    frames_tx: float
    frames_rx: float
    energy_mj: float
    per_mote: Mapping[int, tuple[int, int, float]] = field(default_factory=dict)


def traffic(per_mote: Mapping[int, tuple[int, int, float]], among: Iterable[int]) -> Traffic:
    """Means over ``among`` of (frames sent, frames received, radio energy mJ)."""
    ids = [i for i in among if i in per_mote]
    if not ids:
        return Traffic(0.0, 0.0, 0.0, {})
    n = len(ids)
    return Traffic(
        sum(per_mote[i][0] for i in ids) / n,
        sum(per_mote[i][1] for i in ids) / n,
        sum(per_mote[i][2] for i in ids) / n,
        {i: per_mote[i] for i in ids},
    )


@dataclass
class RunResult:
    """What one run of a scenario produced (virtual or real time): the input of the metrics."""

    scenario: Scenario
    recorder: Recorder
    duration: float
    traffic: dict[int, tuple[int, int, float]] = field(default_factory=dict)  # tx, rx, mJ
    mode: str = "virtual"
    speed: float | None = None


def run_metrics(
    result: RunResult,
    s: MembershipScore,
    gtype: int,
    t0: float,
    t_end: float,
    settle: float,
) -> dict[str, Any]:
    """The metrics every scenario reports, over the scored window [t0, t_end]:
    membership score, group ids, leader changes, first record, delivery, traffic."""
    sc, rec = result.scenario, result.recorder
    ids = rec.group_ids(gtype, t0, t_end + settle)
    first = first_arrival(rec, t0, channel=sc.channel, gtype=gtype)
    tr = traffic(result.traffic, sc.sensors)
    return {
        "scenario": sc.name,
        "mode": result.mode,
        "speed": result.speed,
        "duration_s": result.duration,
        "settle_s": settle,
        "membership_precision": s.precision,
        "membership_recall": s.recall,
        "membership_f1": s.f1,
        "membership_instants": s.instants,
        "membership_tp_fp_fn": [s.tp, s.fp, s.fn],
        "distinct_group_ids": len(ids),
        "group_ids": sorted(ids),
        "lasting_group_ids": list(lasting_group_ids(rec, gtype, t0, t_end + settle, 2 * settle)),
        "data_group_ids": sorted(data_ids := ids & led_group_ids(rec, gtype)),
        "distinct_data_group_ids": len(data_ids),
        "handovers": handover_count(rec, gtype, t0, t_end + settle),
        "elections": len([e for e in rec.elections if e.group_type == gtype]),
        "first_record_s": None if first is None else first.t - t0,
        "first_record_via": None if first is None else first.via,
        "delivery_ratio": delivery_ratio(rec, result.duration - 5.0),
        "records_produced": len(rec.produced),
        "records_delivered": len(rec.arrivals),
        "frames_per_mote": tr.frames_tx,
        "frames_rx_per_mote": tr.frames_rx,
        "energy_mj_per_mote": tr.energy_mj,
        "motes_scored": len(sc.sensors),
    }


def settle_time(sc: Scenario) -> float:
    """One leader-beacon period of the sensing motes: the lag the scoring allows."""
    spec = sc.deployment.node(sc.sensors[0])
    return config_for(spec, sc.deployment).beacon_period


@dataclass(frozen=True, slots=True)
class Scored:
    """A finished run with its tracking group scored against the ground truth over
    the sensed window [t0, t1] (:func:`scored`): what every analysis starts from."""

    result: RunResult
    truth: GroundTruth
    settle: float  # s the protocol is allowed to reach a state (:func:`settle_time`)
    t0: float  # first instant the truth has members (else the definition time)
    t1: float  # the last scored instant
    series: list[Instant]
    score: MembershipScore

    @property
    def sc(self) -> Scenario:
        return self.result.scenario

    @property
    def rec(self) -> Recorder:
        return self.result.recorder

    @property
    def gtype(self) -> int:
        """The tracking group's type."""
        return self.sc.tracking_group

    @property
    def defn(self) -> GroupTypeDef:
        """The tracking group's definition."""
        return self.sc.group_def()

    @property
    def end(self) -> float:
        """The last instant scorable: the run's end less ``settle``."""
        return self.result.duration - self.settle

    def metrics(self) -> dict[str, Any]:
        """:func:`run_metrics` over the scored window."""
        return run_metrics(self.result, self.score, self.gtype, self.t0, self.t1, self.settle)


def scored(result: RunResult, *, through_last_sensed: bool = False) -> Scored:
    """Score the tracking group of ``result`` every :data:`SAMPLE_DT` from the first
    instant the ground truth has members (else the definition time) to the end of
    the run less the settle lag, or, with ``through_last_sensed``, to the last
    instant the truth has members (a pass of a robot)."""
    sc = result.scenario
    truth = sc.truth()
    defn = sc.group_def()
    sensors = sc.sensors
    settle = settle_time(sc)
    end = result.duration - settle
    grid = instants(sc.define_at, end, SAMPLE_DT)
    sensed = [t for t in grid if truth.members(defn, t, sensors)]
    t0 = sensed[0] if sensed else sc.define_at
    t1 = sensed[-1] if sensed and through_last_sensed else end
    gtype = sc.tracking_group
    series = membership_series(
        result.recorder, truth, defn, gtype, instants(t0, t1, SAMPLE_DT), settle, sensors
    )
    return Scored(result, truth, settle, t0, t1, series, score(series))


def rounded(d: Mapping[str, Any], digits: int = 4) -> dict[str, Any]:
    """Round floats in a (nested) metrics dict for stable, readable JSON."""
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, float):
            out[k] = round(v, digits)
        elif isinstance(v, Mapping):
            out[k] = rounded(v, digits)
        else:
            out[k] = v
    return out
