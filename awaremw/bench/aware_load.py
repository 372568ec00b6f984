"""The ``--workload aware`` fleet of the benchmarks: the whole middleware on a
field that grows with the motes, in a world that does not speed up.

Motes on a square grid (CC2420 preset, 12 m spacing: about ten neighbours
each), built by the same core factory as a fleet's node kinds
(:class:`~awaremw.nodes.KindsFactory`: tmote sky applications over a world,
:class:`~awaremw.protocol.mote.AwareMote` cores). The field is cut into
``k x k`` regions of about :data:`MOTES_PER_REGION` motes each (``k`` the
nearest integer to ``sqrt(motes / 1000)``, at least 1):

* each region holds one fire (a disc 80 degC above ambient, 25 m in radius)
  that loops around the region's centre at :data:`OBJECT_SPEED_MPS`, a fire
  front's pace, whatever the run's duration or the field's size;
* collection roots (gateway motes, the sinks) stand on a lattice: one per
  region at its centre by default, or ``sinks`` of them on the lattice that
  ``sinks`` asks for (:func:`sink_lattice`), so that no record needs more hops
  than a region's half-diagonal, however large the field.

The sinks inject, as the gateway service does on every gateway mote, a
tracking group type (temperature above 50 degC) and an AVG temperature channel
every 2 s at :data:`DEFINE_AT_S`, and Drip spreads them. A group forms around
each fire and follows it; its leader produces one record per epoch, and
collection carries it to the nearest sink.

``record_delivery`` is the share of records the leaders produced (up to
:data:`GRACE_S` before the end, so records still in flight do not count
against it) that arrived at any sink; None when no record was produced in that
window, so that "none produced" never reads as "none delivered". Tracking per
object (:func:`score_objects`): a record belongs to the fire nearest its
leader (:mod:`awaremw.experiments.objects`); ``objects_tracked`` counts the fires
with a delivered record in the last quarter of the counted window (the group
still follows it), ``ids_per_object`` the distinct group ids each fire's
records carried.
"""

from __future__ import annotations

import asyncio
import functools
import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from awaremw.experiments import objects
from awaremw.experiments.objects import fires_of
from awaremw.nodes import KindsFactory, kind_names, world_of
from awaremw.protocol.attributes import TEMPERATURE
from awaremw.protocol.core import MoteCore
from awaremw.protocol.events import Delivered, RecordProduced
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
from awaremw.radio.environment import RadioSettings
from awaremw.radio.virtual_medium import VirtualNetwork
from awaremw.runtime.deployment import Deployment, parse_deployment
from awaremw.world.mobility import square_loop

if TYPE_CHECKING:
    from awaremw.runtime.fleet import Fleet

SPACING_M = 12.0
MOTES_PER_REGION = 1000  # one fire and (by default) one sink per region of about this many motes
OBJECT_SPEED_MPS = 1.0  # a fire front's pace: the world never speeds up with the field
LOOP_FRACTION = 0.25  # a fire loops at this fraction of its region's side from the centre
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


@dataclass(frozen=True, slots=True)
class Field:
    """The grid of a workload: ``cols x rows`` motes ``spacing`` apart, ``regions``
    per side (see the module docstring)."""

    motes: int
    spacing: float = SPACING_M

    @property
    def cols(self) -> int:
        return max(1, math.ceil(math.sqrt(self.motes)))

    @property
    def rows(self) -> int:
        return math.ceil(self.motes / self.cols)

    @property
    def size(self) -> tuple[float, float]:
        return self.spacing * self.cols, self.spacing * self.rows

    @property
    def regions(self) -> int:
        """Regions per side: about :data:`MOTES_PER_REGION` motes in each."""
        return max(1, round(math.sqrt(self.motes / MOTES_PER_REGION)))

    def position(self, i: int) -> tuple[float, float]:
        return self.spacing * (0.5 + i % self.cols), self.spacing * (0.5 + i // self.cols)

    def nearest(self, x: float, y: float) -> int:
        """The mote of the grid nearest (x, y)."""
        col = min(self.cols - 1, max(0, math.floor(x / self.spacing)))
        row = min(self.rows - 1, max(0, math.floor(y / self.spacing)))
        i = row * self.cols + col
        while i >= self.motes:  # the last row may be short
            i -= self.cols
        return i


def sink_lattice(grid: Field, sinks: int | None = None) -> list[int]:
    """The motes that are collection roots: by default one at the centre of every
    region; ``sinks`` N asks for N on the centres of a ``ceil(sqrt N)`` lattice
    (row by row, the first N). Distinct motes, sorted."""
    if sinks is None:
        k = grid.regions
        sinks, per_side = k * k, k
    else:
        if not 1 <= sinks <= grid.motes // 2:
            raise ValueError(
                f"--sinks {sinks}: needs 1 to {grid.motes // 2} sinks for {grid.motes} motes "
                "(at least as many sensing motes as sinks)"
            )
        per_side = math.ceil(math.sqrt(sinks))
    w, h = grid.size
    rows = math.ceil(sinks / per_side)
    chosen: list[int] = []
    for n in range(sinks):
        a, b = n % per_side, n // per_side
        x, y = w * (a + 0.5) / per_side, h * (b + 0.5) / rows
        i = grid.nearest(x, y)
        while i in chosen:  # a dense lattice on a small grid: take the next free mote
            i = (i + 1) % grid.motes
        chosen.append(i)
    return sorted(chosen)


def fire_loops(grid: Field, duration: float) -> list[dict[str, Any]]:
    """One fire per region, looping anticlockwise around the region's centre on a
    square of half-side ``LOOP_FRACTION x side`` at :data:`OBJECT_SPEED_MPS`, its
    keyframes covering ``duration`` (deployment ``[[world.fires]]`` tables)."""
    k = grid.regions
    w, h = grid.size
    fires: list[dict[str, Any]] = []
    for n in range(k * k):
        a, b = n % k, n // k
        cx, cy = w * (a + 0.5) / k, h * (b + 0.5) / k
        r = LOOP_FRACTION * min(w, h) / k
        legs = max(0, math.ceil(duration * OBJECT_SPEED_MPS / (2 * r)))  # to cover duration
        keys: list[dict[str, Any]] = [
            {"t": t, "x": x, "y": y}
            for t, x, y in square_loop(cx, cy, r, OBJECT_SPEED_MPS, 0, legs + 1)
        ]
        keys[0] |= {"radius": FIRE_RADIUS_M, "peak": FIRE_PEAK_C}
        fires.append({"name": f"fire-{n}", "edge": 4.0, "keyframes": keys})
    return fires


def deployment(
    motes: int,
    seed: int,
    duration: float,
    spacing: float = SPACING_M,
    mac: str = "csma",
    collisions: str = "sinr",
    sinks: int | None = None,
    radio: RadioSettings | None = None,
) -> Deployment:
    """``motes`` motes on a square grid, sinks on a lattice, one looping fire per region;
    ``radio``: noise and hardware variance (None: today's radio)."""
    if motes < 2:
        raise ValueError("the aware workload needs at least 2 motes (a gateway and a sensor)")
    grid = Field(motes, spacing)
    roots = set(sink_lattice(grid, sinks))
    nodes = [
        {"id": i, "kind": "gateway" if i in roots else "tmote", "position": list(grid.position(i))}
        for i in range(motes)
    ]
    doc = {
        "name": f"bench-aware-{motes}",
        "radio": "cc2420",
        "seed": seed,
        "tx_power_dbm": 0.0,
        "mac": mac,
        "collisions": collisions,
        "area": list(grid.size),
        **(
            {}
            if radio is None
            else {"noise": radio.noise, "hardware_variance": radio.hardware_variance}
        ),
        "world": {"ambient_temperature": 20.0, "fires": fire_loops(grid, duration)},
        "nodes": nodes,
    }
    return parse_deployment(doc, known_kinds=kind_names())


def sinks_of(d: Deployment) -> list[int]:
    """The collection roots of a deployment (its gateway motes), sorted."""
    return sorted(s.id for s in d.nodes if s.kind == "gateway")


@dataclass
class RecordTally:
    """Records produced by leaders and records arrived at a sink, from the core
    events (``on_event`` is an event hook of either driver). A record is known by
    its key; ``produced`` maps it to (time produced, leader)."""

    produced: dict[RecordKey, tuple[float, int]] = field(default_factory=dict)
    delivered: set[RecordKey] = field(default_factory=set)
    leaders: set[int] = field(default_factory=set)
    untracked: int = 0  # events past MAX_TRACKED, not counted

    def on_event(self, nid: int, ev: object, t: float) -> None:
        if isinstance(ev, RecordProduced):
            if len(self.produced) >= MAX_TRACKED:
                self.untracked += 1
                return
            self.produced.setdefault(_key(ev.record), (t, nid))
            self.leaders.add(nid)
        elif isinstance(ev, Delivered) and isinstance(ev.payload, DataRecord):
            # Delivered happens at a root only: any sink counts, a record once.
            if len(self.delivered) >= MAX_TRACKED:
                self.untracked += 1
                return
            self.delivered.add(_key(ev.payload))

    def merge(self, others: Iterable[RecordTally]) -> RecordTally:
        """Fold the tallies of other processes into this one (a record's
        production is the earliest any process saw); returns self."""
        for o in others:
            for k, made in o.produced.items():
                old = self.produced.get(k)
                if old is None:
                    if len(self.produced) >= MAX_TRACKED:
                        self.untracked += 1
                        continue
                    self.produced[k] = made
                elif made < old:
                    self.produced[k] = made
            room = MAX_TRACKED - len(self.delivered)
            new = o.delivered - self.delivered
            if len(new) > room:
                self.untracked += len(new) - room
                new = set(sorted(new)[:room])
            self.delivered |= new
            self.leaders |= o.leaders
            self.untracked += o.untracked
        return self

    def counted(self, end: float) -> list[RecordKey]:
        """The records produced early enough to have arrived by ``end``."""
        return [k for k, (t, _) in self.produced.items() if t <= end - GRACE_S]

    def results(self, end: float) -> dict[str, Any]:
        """``records_produced`` (up to ``end - GRACE_S``), ``records_delivered`` (of
        those), ``record_delivery`` (their ratio; None when none was produced in
        that window: no ratio, not a loss), ``first_record_s`` (emulated time of
        the earliest record produced, counted or not; None if none),
        ``leaders`` (distinct motes that led an epoch), ``records_untracked``
        (events past :data:`MAX_TRACKED`, 0 in any run of sensible length)."""
        counted = self.counted(end)
        got = sum(1 for k in counted if k in self.delivered)
        first = min((t for t, _ in self.produced.values()), default=None)
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


def score_objects(tally: RecordTally, d: Deployment, end: float) -> dict[str, Any]:
    """Tracking per fire of ``d``'s world (:func:`awaremw.experiments.objects.score`:
    a record belongs to the fire nearest its leader): ``objects``,
    ``objects_tracked`` (fires with a delivered record produced in the last
    quarter of the counted window, ``[0.75 (end - GRACE_S), end - GRACE_S]``),
    ``records_per_object`` and ``ids_per_object`` (delivered records and
    distinct group ids per fire, in the order of the deployment),
    ``records_unattributed`` (records whose leader was near no fire)."""
    where = {s.id: s.position for s in d.nodes}
    records = {
        k: (tally.produced[k][0], where.get(tally.produced[k][1]), k in tally.delivered)
        for k in tally.counted(end)
    }
    return objects.score(fires_of(world_of(d)), records, 0.75 * (end - GRACE_S)).as_dict()


def inject_definitions(root: MoteCore, now: float) -> None:
    """A sink injects the group type and the channel, as the gateway service does
    on every gateway mote (Drip spreads them; the same versions everywhere)."""
    if not isinstance(root, AwareMote):
        raise TypeError(f"a sink is not an AwareMote: {type(root).__name__}")
    hot = GroupTypeDef((Condition(TEMPERATURE, Op.GT, HOT_C),))
    period_ms = round(CHANNEL_PERIOD_S * 1000)
    chan = ChannelDef(TEMPERATURE, GROUP_TYPE, ANY_GROUP_ID, period_ms, AggId.AVG)
    root.inject(ItemKind.GROUP_TYPE, GROUP_TYPE, 1, hot, now)
    root.inject(ItemKind.CHANNEL, CHANNEL, 1, chan, now)


class AwarePlugin:
    """The aware load inside each worker process of a launcher
    (:class:`~awaremw.runtime.fleet.settings.WorkerPlugin`): tallies the records of
    the motes it runs and injects the definitions at :data:`DEFINE_AT_S` on the
    sinks it runs, exactly as in one process."""

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
        mine = [n for n in sinks_of(fleet.deployment) if n in fleet.runners]
        if mine:
            self._task = asyncio.get_running_loop().create_task(self._inject(fleet, mine))

    async def _inject(self, fleet: Fleet, sinks: list[int]) -> None:
        await fleet.wait_until(DEFINE_AT_S)
        for n in sinks:
            if fleet.alive(n):
                fleet.run_on(n, inject_definitions)

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
            for n in sinks_of(self.deployment):
                inject = functools.partial(inject_definitions, self.net.cores[n], self.net.now)
                self.net.call(n, inject)
        self.net.run_until(end)

    def results(self, end: float) -> dict[str, Any]:
        return {
            **self.tally.results(end),
            "sinks": len(sinks_of(self.deployment)),
            **score_objects(self.tally, self.deployment, end),
        }


def _key(r: DataRecord) -> RecordKey:
    return (r.channel, r.group_type, r.group_id, r.epoch)


def build(
    motes: int,
    seed: int,
    duration: float,
    mac: str = "csma",
    collisions: str = "sinr",
    sinks: int | None = None,
    radio: RadioSettings | None = None,
    spacing: float = SPACING_M,
) -> AwareLoad:
    """The network, every core from the fleet's :class:`KindsFactory`."""
    d = deployment(
        motes, seed, duration, spacing, mac=mac, collisions=collisions, sinks=sinks, radio=radio
    )
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
