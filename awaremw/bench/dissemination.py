"""``awaremw bench dissemination``: Trickle propagation per hop, steady-state cost.

A square grid of :class:`~awaremw.protocol.mote.AwareMote` cores (default 400
motes, 20 x 20, CC2420 preset, 15 m spacing) on the virtual-clock driver, one
gateway mote (collection root) in a corner. After ``--warmup`` seconds (tree
formed) the gateway injects one channel definition; every mote's adoption time
is recorded and set against its hop distance from the gateway in the radio
graph (links whose mean RSSI is at least ``--hop-rssi`` dBm both ways, default
-93 dBm: PRR about 0.9 on CC2420). Then
the network is left alone until ``--settle`` seconds after the injection
(every Trickle back near tau_h) and the dissemination frames (DripItem,
DripSummary) and collection beacons are counted for ``--window`` seconds.
No data is submitted: this is the control-plane cost of an idle network.
``--held K``: the gateway injects K other channels at t = 1 s, so every mote
holds them when the measured one spreads (what a wave costs in a network that
has definitions already; ``held_items`` in the JSON).

JSON keys:

* ``motes``, ``grid``, ``spacing_m``, ``seed``, ``preset``;
* ``seconds_per_hop``: least-squares slope of adoption delay against hop
  distance; ``propagation_max_s`` (last mote's delay), ``max_hops``,
  ``mean_delay_per_hop_s`` (mean of delay / hops), ``coverage`` (fraction of
  motes that adopted the item within ``--propagation-timeout``);
* ``tx_per_mote_per_hour``: dissemination frames plus collection beacons per
  mote per hour in the window; ``drip_tx_per_mote_per_hour`` and
  ``ctp_beacons_per_mote_per_hour`` split it; ``window_s``;
* ``wall_seconds``;
* ``secure`` (``--secure``: throw-away keys, every frame sealed with a
  counter and an 8-byte MIC, items signed by the gateway and verified by every
  mote; the signature travels in 2 DripSig frames, counted in the Drip
  figures), ``security_overhead_bytes`` (per frame; 0 when off),
  ``payload_mtu`` (the MTU the middleware's frames get),
  ``bytes_tx_per_mote_per_hour`` (radio bytes in the window, overhead included);
* ``mac``, ``collisions_model`` (``--mac csma|aloha``, ``--collisions
  sinr|none``), ``window_collisions``, ``window_cca_busy``,
  ``window_mac_drops`` (MAC counters of every mote over the window);
* ``energy_by_role``: the window's radio energy and frames per hour by role,
  with the lifetime on two AA cells (radio/energy.py, docs/energy.md; in this
  idle network every mote is ``idle``);
* with ``--parent-death``, ``parent_death``: :func:`parent_death_repair` for
  the seed (``victim``, ``children``, ``repair_s`` per child, ``repair_max_s``,
  ``routes_ok``).

The scenario helpers (grid of motes with optional periodic traffic, route and
connectivity checks) are shared with the tests.
"""

from __future__ import annotations

import argparse
import random
import time
from collections import deque
from collections.abc import Iterable
from typing import Any

from awaremw.bench.medium import (
    add_medium_arguments,
    add_radio_arguments,
    mac_totals,
    medium_of,
    radio_of,
)
from awaremw.protocol.config import MiddlewareConfig
from awaremw.protocol.core import Transmission
from awaremw.protocol.events import ItemAdopted, ParentChanged
from awaremw.protocol.frames import (
    ChannelDef,
    CommandDef,
    CtpBeacon,
    DataRecord,
    DripItem,
    DripSig,
    DripSummary,
    ItemBody,
    ItemKind,
    peek_header,
)
from awaremw.protocol.mote import AwareMote
from awaremw.protocol.signing import ItemSigner
from awaremw.radio.energy import MoteEnergy, role_of, role_table
from awaremw.radio.environment import RadioSettings, radio_model
from awaremw.radio.model import preset
from awaremw.radio.security import RadioSecurity
from awaremw.radio.virtual_medium import VirtualNetwork
from awaremw.world.mobility import Static

Event = tuple[int, object, float]


class RecordingApp:
    """An application offering no attribute; it records the commands it runs."""

    def __init__(self) -> None:
        self.commands: list[tuple[CommandDef, float]] = []

    def offers(self, attr: int) -> bool:
        return False

    def read(self, attr: int, now: float) -> float | None:
        return None

    def on_command(self, command: CommandDef, now: float) -> None:
        self.commands.append((command, now))


class TrafficMote(AwareMote):
    """An AwareMote that also submits one DataRecord every ``period`` seconds
    (from ``first`` on) to the collection tree, through the driver contract
    (its own deadline), as a group leader would. ``value`` is the submit time."""

    def __init__(
        self,
        node_id: int,
        config: MiddlewareConfig,
        period: float | None = None,
        first: float = 0.0,
        seed: int = 0,
    ) -> None:
        self.app = RecordingApp()
        super().__init__(node_id, self.app, config, random.Random(seed * 1_000_003 + node_id))
        self.period = period
        self.next_submit = first
        self.submitted = 0
        self.refused = 0

    def next_deadline(self) -> float | None:
        d = super().next_deadline()
        if self.period is None:
            return d
        return self.next_submit if d is None else min(d, self.next_submit)

    def handle_timer(self, now: float) -> None:
        if self.period is not None and now >= self.next_submit:
            rec = DataRecord(1, 1, 1, self.submitted & 0xFFFFFFFF, 0, now, 1, self.node_id)
            if self.collection.submit(rec, now):
                self.submitted += 1
            else:
                self.refused += 1
            self.next_submit += self.period
        super().handle_timer(now)


# Channels a mote may hold besides the measured one (config.max_channels is 8).
MAX_HELD = 7


def inject_at(
    net: VirtualNetwork,
    mote: AwareMote,
    t: float,
    kind: ItemKind,
    item_id: int,
    version: int,
    item: ItemBody | None,
) -> None:
    """At virtual time ``t``, inject an item into (gateway) ``mote``."""
    net.call_at(
        t, lambda: net.call(mote.node_id, lambda: mote.inject(kind, item_id, version, item, t))
    )


def build_grid(
    side: int,
    spacing: float,
    roots: Iterable[int] = (0,),
    seed: int = 1,
    period: float | None = None,
    first: float = 20.0,
    radio: str = "cc2420",
    overrides: dict[str, Any] | None = None,
    security: RadioSecurity | None = None,
    signer: ItemSigner | None = None,
    mac: str = "csma",
    collisions: str = "sinr",
    realism: RadioSettings | None = None,
) -> tuple[VirtualNetwork, dict[int, TrafficMote], list[Event]]:
    """``side`` x ``side`` TrafficMotes (ids row by row); returns the network, the
    motes and the list the network's events are appended to. With ``security``
    the radio is secured, the motes get the payload MTU and verify items with
    its gateway public key, and the roots sign with ``signer``."""
    net = VirtualNetwork(
        radio_model(preset(radio), seed, realism),
        seed,
        security=security,
        mac=mac,
        collisions=collisions,
    )
    events: list[Event] = []
    net.on_event = lambda node, e, t: events.append((node, e, t))
    rng = random.Random(seed)
    root_set = set(roots)
    sec: dict[str, Any] = {"mtu": net.payload_mtu}
    if security is not None:
        sec["gateway_public_key"] = security.gateway_public_key
    base = MiddlewareConfig().with_overrides({**sec, **(overrides or {})})
    motes: dict[int, TrafficMote] = {}
    for i in range(side * side):
        cfg = base.with_overrides({"is_root": i in root_set})
        p = None if i in root_set else period
        m = TrafficMote(i, cfg, p, first + rng.uniform(0.0, period or 0.0), seed)
        if i in root_set:
            m.dissemination.signer = signer
        motes[i] = m
        net.add(m, Static((i % side) * spacing, (i // side) * spacing))
    return net, motes, events


def route_of(motes: dict[int, TrafficMote], node: int) -> list[int]:
    """The parent chain from ``node``; it stops at a mote without parent or at the
    first repeated mote (then the last element repeats an earlier one: a loop)."""
    route = [node]
    seen = {node}
    while (p := motes[route[-1]].collection.parent) is not None:
        route.append(p)
        if p in seen:
            break
        seen.add(p)
    return route


def hop_distances(
    net: VirtualNetwork, ids: Iterable[int], src: int, min_rssi: float
) -> dict[int, int]:
    """BFS hop counts from ``src`` over links with mean RSSI >= ``min_rssi`` both ways."""
    nodes = list(ids)
    dist = {src: 0}
    todo = deque([src])
    while todo:
        a = todo.popleft()
        for b in nodes:
            if b in dist or b == a:
                continue
            if net.mean_rssi(a, b) >= min_rssi and net.mean_rssi(b, a) >= min_rssi:
                dist[b] = dist[a] + 1
                todo.append(b)
    return dist


def mesh_connected(net: VirtualNetwork, ids: Iterable[int], root: int, min_rssi: float) -> set[int]:
    """The motes among ``ids`` joined to ``root`` by links of mean RSSI >= ``min_rssi``."""
    return set(hop_distances(net, ids, root, min_rssi))


def parent_death_repair(
    seed: int,
    side: int = 10,
    spacing: float = 15.0,
    period: float = 5.0,
    settle: float = 600.0,
    horizon: float = 30.0,
) -> dict[str, Any]:
    """Route repair after a parent dies in a steady-state network.

    A ``side`` x ``side`` grid (root in a corner) where every mote submits one
    record every ``period`` s is left ``settle`` s to quiet down; then the
    non-root mote with the most children in the tree dies. Each of its
    children has a new route when it takes a parent other than the dead mote
    (ParentChanged); the victim is chosen among the parents whose death cuts
    none of their children off the root. ``repair_s`` lists those delays (None: none within
    ``horizon``), ``routes_ok`` says whether every child's parent chain ends
    at the root ``horizon`` s after the death.
    """
    net, motes, events = build_grid(side, spacing, (0,), seed, period=period)
    net.run_until(settle)
    kids: dict[int, list[int]] = {}
    for i, m in motes.items():
        p = m.collection.parent
        if p is not None and p != 0:
            kids.setdefault(p, []).append(i)
    # The parent with the most children whose death leaves them a way to the
    # root (links of mean RSSI >= -94 dBm, PRR about 0.8): no partition.
    victim, children = -1, []
    for v in sorted(kids, key=lambda v: (-len(kids[v]), v)):
        reach = mesh_connected(net, [i for i in motes if i != v], 0, -94.0)
        if all(c in reach for c in kids[v]):
            victim, children = v, sorted(kids[v])
            break
    if victim < 0:
        raise ValueError(f"seed {seed}: every parent's death cuts a child off the root")
    n_before = len(events)
    t_kill = net.now
    net.kill(victim)
    net.run_until(t_kill + horizon)
    repaired: dict[int, float] = {}
    for node, e, t in events[n_before:]:
        if (
            isinstance(e, ParentChanged)
            and node in children
            and e.new is not None
            and e.new != victim
        ):
            repaired.setdefault(node, round(t - t_kill, 3))
    delays = [repaired.get(c) for c in children]
    got = [d for d in delays if d is not None]
    return {
        "seed": seed,
        "victim": victim,
        "children": len(children),
        "repair_s": delays,
        "repair_max_s": max(got) if len(got) == len(children) else None,
        "routes_ok": all(route_of(motes, c)[-1] == 0 for c in children),
    }


def _slope(xs: list[float], ys: list[float]) -> float:
    n = len(xs)
    mx, my = sum(xs) / n, sum(ys) / n
    sxx = sum((x - mx) ** 2 for x in xs)
    if sxx == 0:
        return 0.0
    return sum((x - mx) * (y - my) for x, y in zip(xs, ys, strict=True)) / sxx


def run(args: argparse.Namespace) -> dict[str, Any]:
    side = int(args.side)
    seed = int(args.seed)
    held = int(getattr(args, "held", 0))
    if not 0 <= held <= MAX_HELD:
        raise ValueError(f"--held {held}: 0..{MAX_HELD} (channels 2..{MAX_HELD + 1})")
    t_wall = time.perf_counter()
    secure = bool(getattr(args, "secure", False))
    security, signer = None, None
    if secure:
        security, key = RadioSecurity.throwaway()
        signer = ItemSigner(key)
    mac, collisions = medium_of(args)
    net, motes, events = build_grid(
        side,
        float(args.spacing),
        (0,),
        seed,
        radio=args.radio,
        security=security,
        signer=signer,
        mac=mac,
        collisions=collisions,
        realism=radio_of(args),
    )
    counts = {"drip": 0, "ctp": 0, "wave": 0}
    counting = [False]

    wave = [False]

    def on_transmit(node: int, tx: Transmission, t: float) -> None:
        if wave[0] and peek_header(tx.frame)[0] in (DripItem.TYPE, DripSummary.TYPE, DripSig.TYPE):
            counts["wave"] += 1
        if counting[0]:
            ftype = peek_header(tx.frame)[0]
            if ftype in (DripItem.TYPE, DripSummary.TYPE, DripSig.TYPE):
                counts["drip"] += 1
            elif ftype == CtpBeacon.TYPE:
                counts["ctp"] += 1

    net.on_transmit = on_transmit
    for i in range(held):  # items every mote holds before the measured one
        old = ChannelDef(attr=0, group_type=1, group_id=0xFFFF, period_ms=4000 + i, agg=0)
        inject_at(net, motes[0], 1.0, ItemKind.CHANNEL, 2 + i, 1, old)
    net.run_until(float(args.warmup))
    # Propagation of one injected item.
    t_inj = net.now
    chan = ChannelDef(attr=0, group_type=1, group_id=0xFFFF, period_ms=2000, agg=0)
    inject_at(net, motes[0], t_inj, ItemKind.CHANNEL, 1, 1, chan)
    wave[0] = True
    net.run_until(t_inj + float(args.propagation_timeout))
    wave[0] = False
    adopted: dict[int, float] = {}
    for node, e, t in events:
        if isinstance(e, ItemAdopted) and (e.kind, e.item_id) == (ItemKind.CHANNEL, 1) and node:
            adopted.setdefault(node, t - t_inj)
    hops = hop_distances(net, motes, 0, float(args.hop_rssi))
    pts = [(hops[n], d) for n, d in adopted.items() if n in hops and hops[n] > 0]
    xs = [float(h) for h, _ in pts]
    ys = [d for _, d in pts]
    # Steady state: control-plane frames over the window.
    net.run_until(t_inj + float(args.settle))
    counting[0] = True
    window = float(args.window)
    bytes0 = sum(c.bytes_tx for c in net.counters.values())
    mac0 = mac_totals(net.counters.values())
    c = net.counters
    per0 = {i: (net.energy_mj(i), c[i].frames_tx, c[i].acks_tx) for i in motes}
    net.run_until(net.now + window)
    energy = [
        MoteEnergy(
            i,
            role_of(False, False, net.counters[i].acks_tx - per0[i][2]),
            net.energy_mj(i) - per0[i][0],
            net.counters[i].frames_tx - per0[i][1],
        )
        for i in motes
    ]
    counting[0] = False
    bytes_tx = sum(c.bytes_tx for c in net.counters.values()) - bytes0
    mac_window = {k: v - mac0[k] for k, v in mac_totals(net.counters.values()).items()}
    n = len(motes)
    per_hour = 3600.0 / window / n
    parent_changes = sum(1 for _, e, _ in events if isinstance(e, ParentChanged))
    out: dict[str, Any] = {
        "motes": n,
        "grid": f"{side}x{side}",
        "spacing_m": float(args.spacing),
        "seed": seed,
        "preset": args.radio,
        "seconds_per_hop": round(_slope(xs, ys), 3) if pts else None,
        "mean_delay_per_hop_s": round(sum(d / h for h, d in zip(xs, ys, strict=True)) / len(pts), 3)
        if pts
        else None,
        "propagation_max_s": round(max(adopted.values()), 3) if adopted else None,
        # Drip frames (items, summaries, signature parts) sent while the item spread
        # (the propagation timeout after the injection), per mote: the wave's cost.
        "propagation_drip_frames_per_mote": round(counts["wave"] / len(motes), 2),
        "held_items": held,
        "max_hops": max(hops.values()),
        "coverage": round(len(adopted) / (n - 1), 4),
        "tx_per_mote_per_hour": round((counts["drip"] + counts["ctp"]) * per_hour, 3),
        "drip_tx_per_mote_per_hour": round(counts["drip"] * per_hour, 3),
        "ctp_beacons_per_mote_per_hour": round(counts["ctp"] * per_hour, 3),
        "window_s": window,
        "bytes_tx_per_mote_per_hour": round(bytes_tx * per_hour, 1),
        "secure": secure,
        "security_overhead_bytes": 0 if security is None else security.overhead,
        "payload_mtu": net.payload_mtu,
        "parent_changes": parent_changes,
        "mac": mac,
        "collisions_model": collisions,
        "window_collisions": mac_window["collisions"],
        "window_cca_busy": mac_window["cca_busy"],
        "window_mac_drops": mac_window["mac_drops"],
        "energy_by_role": role_table(energy, window, net.preset),
        "wall_seconds": round(time.perf_counter() - t_wall, 2),
    }
    if getattr(args, "parent_death", False):
        out["parent_death"] = parent_death_repair(seed)
    return out


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--side", type=int, default=20, help="grid side (motes = side^2)")
    parser.add_argument("--spacing", type=float, default=15.0, help="grid spacing, m")
    parser.add_argument("--radio", default="cc2420", help="radio preset")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--warmup", type=float, default=60.0, help="s before the injection")
    parser.add_argument(
        "--propagation-timeout", type=float, default=120.0, help="s to wait for every mote"
    )
    parser.add_argument(
        "--settle", type=float, default=3600.0, help="s after the injection before counting"
    )
    parser.add_argument("--window", type=float, default=3600.0, help="s of steady state counted")
    parser.add_argument(
        "--hop-rssi", type=float, default=-93.0, help="dBm: a link counts as one hop above this"
    )
    parser.add_argument(
        "--secure",
        action="store_true",
        help="throw-away keys: authenticated frames (MIC-64 + counter), signed items",
    )
    parser.add_argument(
        "--held",
        type=int,
        default=0,
        help=f"items (0..{MAX_HELD}) every mote holds before the measured one spreads",
    )
    parser.add_argument(
        "--parent-death",
        action="store_true",
        help="also kill a parent in a 10 x 10 grid with traffic and time the repair",
    )
    add_medium_arguments(parser)
    add_radio_arguments(parser)
