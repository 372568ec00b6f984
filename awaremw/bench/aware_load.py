"""The ``--workload aware`` fleet of the scale benchmarks: the whole middleware.

Motes on a square grid (CC2420 preset, 12 m spacing: about ten neighbours
each), built by the same core factory as a fleet's node kinds
(:class:`~awaremw.nodes.KindsFactory`: tmote sky applications over a world,
:class:`~awaremw.protocol.mote.AwareMote` cores); node 0, in a corner, is the
gateway's mote (collection root). A fire (a disc about 80 degC above ambient,
25 m radius) crosses the field diagonally during the run; the gateway mote
injects, as the gateway would, a tracking group type (temperature above 50
degC) and an AVG temperature channel every 2 s, and Drip spreads them. The
group forms around the fire and follows it, its leader produces one record
per epoch, and collection carries it to the gateway mote.

``record_delivery`` is the share of records the leaders produced (up to
:data:`GRACE_S` before the end, so records still in flight do not count
against it) that arrived at the gateway mote; None when no record was
produced in that window (a run too short for its grid: Drip, the collection
tree and the group take longer to form on a larger grid, see
``first_record_s``), so that "none produced" never reads as "none delivered".
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from awaremw.nodes import KindsFactory, kind_names
from awaremw.protocol.attributes import TEMPERATURE
from awaremw.protocol.channels import RecordProduced
from awaremw.protocol.collection import Delivered
from awaremw.protocol.core import MoteCore
from awaremw.protocol.frames import (
    ANY_GROUP_ID,
    AggId,
    ChannelDef,
    Condition,
    DataRecord,
    GroupTypeDef,
    ItemKind,
    Op,
)
from awaremw.protocol.mote import AwareMote
from awaremw.runtime.deployment import Deployment, parse_deployment
from awaremw.runtime.virtual import VirtualNetwork

if TYPE_CHECKING:
    from awaremw.runtime.fleet import Fleet

SPACING_M = 12.0
GATEWAY = 0
GROUP_TYPE = 1
CHANNEL = 1
CHANNEL_PERIOD_S = 2.0
DEFINE_AT_S = 1.0
GRACE_S = 10.0  # records produced this close to the end may still be in flight
FIRE_RADIUS_M = 25.0
FIRE_PEAK_C = 80.0
HOT_C = 50.0
MAX_TRACKED = 200_000  # records remembered by the tally (a 2 s channel: ~110 h per group)

RecordKey = tuple[int, int, int, int]  # channel, group type, group id, epoch


def deployment(
    motes: int,
    seed: int,
    duration: float,
    spacing: float = SPACING_M,
    mac: str = "csma",
    collisions: str = "sinr",
) -> Deployment:
    """``motes`` motes on a square grid, the gateway's at (0, 0)-ish, a fire crossing."""
    if motes < 2:
        raise ValueError("the aware workload needs at least 2 motes (a gateway and a sensor)")
    cols = max(1, math.ceil(math.sqrt(motes)))
    rows = math.ceil(motes / cols)
    w, h = spacing * cols, spacing * rows
    nodes: list[dict[str, Any]] = []
    for i in range(motes):
        pos = [spacing * (0.5 + i % cols), spacing * (0.5 + i // cols)]
        nodes.append({"id": i, "kind": "gateway" if i == GATEWAY else "tmote", "position": pos})
    # The fire crosses from one quarter of the diagonal to three quarters, away
    # from the gateway's corner at the start, over the run.
    fire = {
        "name": "front",
        "edge": 4.0,
        "keyframes": [
            {"t": 0.0, "x": 0.3 * w, "y": 0.7 * h, "radius": FIRE_RADIUS_M, "peak": FIRE_PEAK_C},
            {"t": max(duration, 1.0), "x": 0.7 * w, "y": 0.3 * h},
        ],
    }
    doc = {
        "name": f"bench-aware-{motes}",
        "radio": "cc2420",
        "seed": seed,
        "tx_power_dbm": 0.0,
        "mac": mac,
        "collisions": collisions,
        "area": [w, h],
        "world": {"ambient_temperature": 20.0, "fires": [fire]},
        "nodes": nodes,
    }
    return parse_deployment(doc, known_kinds=kind_names())


@dataclass
class RecordTally:
    """Records produced by leaders and records arrived at the gateway mote, from
    the core events (``on_event`` is an event hook of either driver)."""

    produced: dict[RecordKey, float] = field(default_factory=dict)  # key -> time produced
    delivered: set[RecordKey] = field(default_factory=set)
    leaders: set[int] = field(default_factory=set)
    untracked: int = 0  # events past MAX_TRACKED, not counted

    def on_event(self, nid: int, ev: object, t: float) -> None:
        if isinstance(ev, RecordProduced):
            if len(self.produced) >= MAX_TRACKED:
                self.untracked += 1
                return
            self.produced.setdefault(_key(ev.record), t)
            self.leaders.add(nid)
        elif isinstance(ev, Delivered) and nid == GATEWAY and isinstance(ev.payload, DataRecord):
            if len(self.delivered) >= MAX_TRACKED:
                self.untracked += 1
                return
            self.delivered.add(_key(ev.payload))

    def merge(self, others: Iterable[RecordTally]) -> RecordTally:
        """Fold the tallies of other processes into this one (a record's
        production time is the earliest any process saw); returns self."""
        for o in others:
            for k, t in o.produced.items():
                old = self.produced.get(k)
                if old is None:
                    if len(self.produced) >= MAX_TRACKED:
                        self.untracked += 1
                        continue
                    self.produced[k] = t
                elif t < old:
                    self.produced[k] = t
            room = MAX_TRACKED - len(self.delivered)
            new = o.delivered - self.delivered
            if len(new) > room:
                self.untracked += len(new) - room
                new = set(sorted(new)[:room])
            self.delivered |= new
            self.leaders |= o.leaders
            self.untracked += o.untracked
        return self

    def results(self, end: float) -> dict[str, Any]:
        """``records_produced`` (up to ``end - GRACE_S``), ``records_delivered`` (of
        those), ``record_delivery`` (their ratio; None when none was produced in
        that window: no ratio, not a loss), ``first_record_s`` (emulated time of
        the earliest record produced, counted or not; None if none),
        ``leaders`` (distinct motes that led an epoch), ``records_untracked``
        (events past :data:`MAX_TRACKED`, 0 in any run of sensible length)."""
        counted = [k for k, t in self.produced.items() if t <= end - GRACE_S]
        got = sum(1 for k in counted if k in self.delivered)
        first = min(self.produced.values(), default=None)
        return {
            "workload": "aware",
            "records_produced": len(counted),
            "records_delivered": got,
            "record_delivery": round(got / len(counted), 4) if counted else None,
            "first_record_s": None if first is None else round(first, 3),
            "leaders": len(self.leaders),
            "records_untracked": self.untracked,
            "channel_period_s": CHANNEL_PERIOD_S,
        }


def inject_definitions(root: MoteCore, now: float) -> None:
    """The gateway mote injects the group type and the channel (Drip spreads them)."""
    if not isinstance(root, AwareMote):
        raise TypeError(f"node {GATEWAY} is not an AwareMote: {type(root).__name__}")
    hot = GroupTypeDef((Condition(TEMPERATURE, Op.GT, HOT_C),))
    period_ms = round(CHANNEL_PERIOD_S * 1000)
    chan = ChannelDef(TEMPERATURE, GROUP_TYPE, ANY_GROUP_ID, period_ms, AggId.AVG)
    root.inject(ItemKind.GROUP_TYPE, GROUP_TYPE, 1, hot, now)
    root.inject(ItemKind.CHANNEL, CHANNEL, 1, chan, now)


class AwarePlugin:
    """The aware load inside each worker process of a launcher
    (:class:`~awaremw.runtime.fleet_settings.WorkerPlugin`): tallies the records of
    the motes it runs and, in the worker running the gateway's mote, injects
    the definitions at :data:`DEFINE_AT_S`, exactly as in one process."""

    def __init__(self) -> None:
        self.tally = RecordTally()
        self._task: asyncio.Task[None] | None = None

    def __getstate__(self) -> dict[str, Any]:
        return {"tally": self.tally}  # a running task never travels

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.tally = state["tally"]
        self._task = None

    def setup(self, fleet: Fleet) -> None:
        fleet.on_event(self.tally.on_event)

    def started(self, fleet: Fleet) -> None:
        if GATEWAY in fleet.runners:
            self._task = asyncio.get_running_loop().create_task(self._inject(fleet))

    async def _inject(self, fleet: Fleet) -> None:
        await fleet.wait_until(DEFINE_AT_S)
        if fleet.alive(GATEWAY):
            fleet.run_on(GATEWAY, inject_definitions)

    def result(self) -> RecordTally:
        if self._task is not None:
            if self._task.done() and not self._task.cancelled():
                self._task.result()  # an injection that raised fails the worker
            self._task.cancel()
        return self.tally


@dataclass
class AwareLoad:
    """A virtual network of full AwareMotes with the tracking load (see the module)."""

    net: VirtualNetwork
    deployment: Deployment
    tally: RecordTally = field(default_factory=RecordTally)

    def run_until(self, end: float) -> None:
        if self.net.now < DEFINE_AT_S <= end:
            self.net.run_until(DEFINE_AT_S)
            root = self.net.cores[GATEWAY]
            self.net.call(GATEWAY, lambda: inject_definitions(root, self.net.now))
        self.net.run_until(end)

    def results(self, end: float) -> dict[str, Any]:
        return self.tally.results(end)


def _key(r: DataRecord) -> RecordKey:
    return (r.channel, r.group_type, r.group_id, r.epoch)


def build(
    motes: int, seed: int, duration: float, mac: str = "csma", collisions: str = "sinr"
) -> AwareLoad:
    """The network, every core from the fleet's :class:`KindsFactory`."""
    d = deployment(motes, seed, duration, mac=mac, collisions=collisions)
    factory = KindsFactory()
    net = VirtualNetwork(d.radio_model(), d.seed, mac=d.mac, collisions=d.collisions)
    load = AwareLoad(net, d)
    net.on_event = load.tally.on_event
    for spec in d.nodes:
        net.add(
            factory(spec, d),
            spec.mobility(),
            tx_power_dbm=d.tx_power_of(spec),
            start_at=spec.boot_s,
            battery_mj=spec.battery_mj,
        )
    return load
