"""``awaremw bench aggregation``: what in-network aggregation saves, overhead included.

A square grid of AwareMotes (default 20 x 20 = 400, CC2420 preset with its
shadowing and fading, 10 m spacing) with the gateway's mote in one corner
(the collection root, where the definitions are injected and spread by Drip).
A disc-shaped "hot" region in the far part of the grid forms one group; one
AVG channel samples it every ``--period`` seconds. After ``--warmup`` seconds
(group formed, collection tree built, Trickle timers slowed down) every frame
any mote puts on the air during ``--epochs`` epochs is counted, retries
included, link-layer ACKs not (they are reported apart): leader beacons and
their re-broadcasts, partials, records and group reports on the collection
tree, CTP beacons, Drip traffic, everything.

Per epoch (one group):

* ``lower_bound`` = members + the leader's hops to the gateway: one
  transmission per member per epoch (every reading must leave its mote) plus
  the record's trip;
* ``no_aggregation`` = the sum over members of their hops to the gateway on
  the collection tree (every reading sent to the gateway on its own);
* ``measured`` = all frames of the window / epochs.

JSON keys: ``lower_bound_ratio`` (measured / lower bound; target <= 1.5),
``no_aggregation_ratio`` (no aggregation / measured; target >= 5),
``measured_per_epoch``, ``lower_bound_per_epoch``, ``no_aggregation_per_epoch``,
``by_frame_per_epoch`` (frames per epoch by frame type), ``acks_per_epoch``,
``members``, ``leader_hops``, ``mean_member_hops``, ``records``,
``completeness`` (mean record count / members), ``groups_seen`` (distinct
group ids that produced records in the window), ``beacon_period_s``,
``channel_period_s``, ``motes``, ``seed``, ``preset``, ``spacing_m``,
``sim_seconds``, ``wall_seconds``, ``meets_targets``; ``secure`` (``--secure``:
throw-away keys, every frame sealed with a frame counter and an 8-byte MIC,
definitions signed by the gateway), ``security_overhead_bytes`` (per frame),
``payload_mtu``, ``bytes_per_epoch`` (radio bytes of the counted frames,
overhead included) and ``energy_mj_per_epoch`` (radio energy of every mote,
ACKs included); ``mac`` and ``collisions_model`` (``--mac csma|aloha``,
``--collisions sinr|none``), ``collisions_per_epoch``, ``cca_busy_per_epoch``,
``mac_drops_per_epoch`` (the MAC counters of every mote over the window);
``energy_by_role`` (radio/energy.py, docs/energy.md): for each role found in
the window (``leader``, ``member``, ``forwarder``: in no group but data went
through it, ``idle``) ``motes``, ``mj_per_hour`` (mean) and
``mj_per_hour_max``, ``frames_per_hour`` and ``frames_per_hour_max``,
``lifetime_days_traffic`` and ``lifetime_days_lpl`` (two AA cells, the role's
most spending mote, traffic only / with a 1 % low-power-listening floor);
``window_s``; with ``--per-mote``, ``energy_per_mote``: node id ->
``[role, mJ per hour, frames per hour]``.

Beacons are paced to meet the targets: ``--beacon-factor 4`` makes the beacon
period 4 channel periods (8 s) and ``--settled-factor 4`` lets a settled
leader stretch its interval up to 4 beacon periods; the price is a slower
reaction to a split (docs/protocol-groups.md, "Benchmark").
``beacon_period_s`` and ``beacon_settled_factor`` say which pacing ran.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import random
import time
from collections import Counter
from typing import Any

from awaremw.bench.medium import (
    add_medium_arguments,
    add_radio_arguments,
    mac_totals,
    medium_of,
    radio_of,
)
from awaremw.protocol.attributes import TEMPERATURE
from awaremw.protocol.config import MiddlewareConfig
from awaremw.protocol.core import Transmission
from awaremw.protocol.events import RecordProduced
from awaremw.protocol.frames import (
    ANY_GROUP_ID,
    FRAME_TYPES,
    AggId,
    ChannelDef,
    CommandDef,
    Condition,
    DataRecord,
    GroupTypeDef,
    ItemKind,
    Op,
    peek_header,
)
from awaremw.protocol.mote import AwareMote
from awaremw.protocol.signing import ItemSigner
from awaremw.radio.energy import MoteEnergy, role_of, role_table
from awaremw.radio.environment import radio_model
from awaremw.radio.model import preset
from awaremw.radio.security import RadioSecurity
from awaremw.radio.virtual_medium import VirtualNetwork
from awaremw.world.mobility import Static

GROUP_TYPE = 1
CHANNEL = 1


class _RegionApp:
    """Temperature 80 degC inside the disc, 20 outside, plus a little per-mote spread."""

    def __init__(self, x: float, y: float, centre: tuple[float, float], radius: float) -> None:
        self.inside = math.hypot(x - centre[0], y - centre[1]) <= radius
        self.offset = (x * 7 + y * 3) % 5

    def offers(self, attr: int) -> bool:
        return attr == TEMPERATURE

    def read(self, attr: int, now: float) -> float | None:
        if attr != TEMPERATURE:
            return None
        return (80.0 if self.inside else 20.0) + self.offset

    def on_command(self, command: CommandDef, now: float) -> None:
        pass


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--side", type=int, default=20, help="grid side (motes = side^2)")
    parser.add_argument("--spacing", type=float, default=10.0, help="grid spacing, m")
    parser.add_argument("--radius", type=float, default=45.0, help="hot region radius, m")
    parser.add_argument("--period", type=float, default=2.0, help="channel period, s")
    parser.add_argument(
        "--beacon-factor", type=float, default=4.0, help="leader beacon period / channel period"
    )
    parser.add_argument(
        "--settled-factor",
        type=float,
        default=4.0,
        help="a settled leader's longest beacon interval, in beacon periods",
    )
    parser.add_argument("--warmup", type=float, default=150.0, help="s before measuring")
    parser.add_argument("--epochs", type=int, default=40, help="epochs measured")
    parser.add_argument("--radio", default="cc2420", help="radio preset")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument(
        "--secure",
        action="store_true",
        help="throw-away keys: authenticated frames (MIC-64 + counter), signed items",
    )
    parser.add_argument(
        "--per-mote",
        action="store_true",
        help="also give every mote's role, mJ per hour and frames per hour",
    )
    add_medium_arguments(parser)
    add_radio_arguments(parser)


def run(args: argparse.Namespace) -> dict[str, Any]:
    side, spacing = int(args.side), float(args.spacing)
    period = float(args.period)
    cfg = MiddlewareConfig(
        beacon_period=period * float(args.beacon_factor),
        beacon_settled_factor=float(args.settled_factor),
    )
    radio = preset(args.radio)
    seed = int(args.seed)
    secure = bool(getattr(args, "secure", False))
    security, signer = None, None
    if secure:
        security, key = RadioSecurity.throwaway()
        signer = ItemSigner(key)
        cfg = dataclasses.replace(cfg, gateway_public_key=security.gateway_public_key)
    mac, collisions = medium_of(args)
    net = VirtualNetwork(
        radio_model(radio, seed, radio_of(args)),
        seed,
        security=security,
        mac=mac,
        collisions=collisions,
    )
    cfg = dataclasses.replace(cfg, mtu=net.payload_mtu)
    far = spacing * (side - 1)
    centre = (far - float(args.radius) * 0.9, far - float(args.radius) * 0.9)
    motes: dict[int, AwareMote] = {}
    members_truth: set[int] = set()
    for j in range(side):
        for i in range(side):
            nid = j * side + i
            x, y = i * spacing, j * spacing
            app = _RegionApp(x, y, centre, float(args.radius))
            if app.inside:
                members_truth.add(nid)
            c = MiddlewareConfig(**{**_fields(cfg), "is_root": nid == 0})
            mote = AwareMote(nid, app, c, random.Random(seed * 1_000_003 + nid))
            if nid == 0:
                mote.dissemination.signer = signer
            motes[nid] = mote
            net.add(mote, Static(x, y))

    by_type: Counter[str] = Counter()
    records: list[DataRecord] = []
    window = [math.inf, math.inf]

    overhead = 0 if security is None else security.overhead
    nbytes = [0]

    def on_transmit(nid: int, tx: Transmission, t: float) -> None:
        if window[0] <= t < window[1]:
            by_type[FRAME_TYPES[peek_header(tx.frame)[0]].__name__] += 1
            nbytes[0] += len(tx.frame) + overhead

    def on_event(nid: int, ev: object, t: float) -> None:
        if isinstance(ev, RecordProduced) and window[0] <= t < window[1]:
            records.append(ev.record)

    net.on_transmit = on_transmit
    net.on_event = on_event

    t0 = time.perf_counter()
    net.run_until(1.0)
    root = motes[0]
    hot = GroupTypeDef((Condition(TEMPERATURE, Op.GT, 50.0),))
    chan = ChannelDef(TEMPERATURE, GROUP_TYPE, ANY_GROUP_ID, round(period * 1000), AggId.AVG)
    net.call(0, lambda: root.inject(ItemKind.GROUP_TYPE, GROUP_TYPE, 1, hot, net.now))
    net.call(0, lambda: root.inject(ItemKind.CHANNEL, CHANNEL, 1, chan, net.now))
    warmup = float(args.warmup)
    start = (math.floor(warmup / period) + 1) * period
    end = start + int(args.epochs) * period
    net.run_until(start)
    per0 = _per_mote(net)
    acks0 = _acks(net)
    mac0 = mac_totals(net.counters.values())
    energy0 = _energy(net)
    stats0 = _channel_stats(motes)
    window[0], window[1] = start, end
    net.run_until(end)
    acks = _acks(net) - acks0
    per1 = _per_mote(net)
    mac_window = {k: v - mac0[k] for k, v in mac_totals(net.counters.values()).items()}
    energy = _energy(net) - energy0
    stats = _channel_stats(motes) - stats0
    wall = time.perf_counter() - t0

    epochs = int(args.epochs)
    members = [n for n in motes if motes[n].groups.membership(GROUP_TYPE) is not None]
    leaders = [n for n in members if motes[n].groups.membership(GROUP_TYPE).is_leader]  # type: ignore[union-attr]
    hops = {n: _tree_hops(motes, n) for n in members}
    leader_hops = hops[leaders[0]] if leaders else 0
    n_members = len(members)
    lower = n_members + leader_hops
    no_agg = sum(hops.values())
    measured = sum(by_type.values()) / epochs
    counts = [r.count for r in records]
    window_s = end - start
    motes_energy = []
    for n, m in motes.items():
        mj1, fr1, ack1 = per1[n]
        mj0, fr0, ack0 = per0[n]
        ms = m.groups.membership(GROUP_TYPE)
        role = role_of(ms is not None and ms.is_leader, ms is not None, ack1 - ack0)
        motes_energy.append(MoteEnergy(n, role, mj1 - mj0, fr1 - fr0))
    out: dict[str, Any] = {
        "lower_bound_ratio": measured / lower if lower else math.inf,
        "no_aggregation_ratio": no_agg / measured if measured else math.inf,
        "measured_per_epoch": measured,
        "lower_bound_per_epoch": lower,
        "no_aggregation_per_epoch": no_agg,
        "by_frame_per_epoch": {k: v / epochs for k, v in sorted(by_type.items())},
        "acks_per_epoch": acks / epochs,
        "collisions_per_epoch": mac_window["collisions"] / epochs,
        "cca_busy_per_epoch": mac_window["cca_busy"] / epochs,
        "mac_drops_per_epoch": mac_window["mac_drops"] / epochs,
        "mac": mac,
        "collisions_model": collisions,
        "channel_stats": dict(sorted(stats.items())),
        "members": n_members,
        "members_expected": len(members_truth),
        "leaders": len(leaders),
        "leader_hops": leader_hops,
        "mean_member_hops": no_agg / n_members if n_members else 0.0,
        "records": len(records),
        "completeness": (sum(counts) / len(counts) / n_members) if counts and n_members else 0.0,
        "groups_seen": len({r.group_id for r in records}),
        "beacon_period_s": cfg.beacon_period,
        "beacon_settled_factor": cfg.beacon_settled_factor,
        "channel_period_s": period,
        "motes": len(motes),
        "seed": seed,
        "preset": radio.name,
        "spacing_m": spacing,
        "sim_seconds": end,
        "wall_seconds": wall,
        "secure": secure,
        "security_overhead_bytes": overhead,
        "payload_mtu": net.payload_mtu,
        "bytes_per_epoch": nbytes[0] / epochs,
        "energy_mj_per_epoch": energy / epochs,
        "energy_by_role": role_table(motes_energy, window_s, radio),
        "window_s": window_s,
    }
    if getattr(args, "per_mote", False):
        per_hour = 3600.0 / window_s
        out["energy_per_mote"] = {
            str(e.node): [e.role.value, round(e.mj * per_hour, 2), round(e.frames * per_hour, 1)]
            for e in motes_energy
        }
    out["meets_targets"] = out["lower_bound_ratio"] <= 1.5 and out["no_aggregation_ratio"] >= 5
    return out


def _fields(cfg: MiddlewareConfig) -> dict[str, Any]:
    return {f: getattr(cfg, f) for f in cfg.__dataclass_fields__}


def _energy(net: VirtualNetwork) -> float:
    return sum(net.energy_mj(n) for n in net.cores)


def _per_mote(net: VirtualNetwork) -> dict[int, tuple[float, int, int]]:
    """Each mote's radio energy (mJ), frames sent and ACKs sent so far."""
    c = net.counters
    return {n: (net.energy_mj(n), c[n].frames_tx, c[n].acks_tx) for n in net.cores}


def _acks(net: VirtualNetwork) -> int:
    return sum(c.acks_tx for c in net.counters.values())


def _tree_hops(motes: dict[int, AwareMote], n: int) -> int:
    """Hops from ``n`` to a root along the collection tree's parents (0 at a root)."""
    hops, cur, seen = 0, n, {n}
    while not motes[cur].collection.is_root:
        p = motes[cur].collection.parent
        if p is None or p in seen:
            return hops + 1  # no route (yet): count at least one hop
        seen.add(p)
        cur, hops = p, hops + 1
    return hops


def _channel_stats(motes: dict[int, AwareMote]) -> Counter[str]:
    total: Counter[str] = Counter()
    for m in motes.values():
        total.update(dataclasses.asdict(m.channels.stats))
    return total
