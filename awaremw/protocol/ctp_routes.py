"""The routing half of the collection tree (:mod:`awaremw.protocol.collection`):
the neighbour table with its link estimates, the parent choice with its
hold-down, and the Trickle that paces the beacons advertising the route.

Link cost maps the EWMA RSSI through a cubic (as MultiHopLQI maps LQI),
corrected by unicast outcomes; a mote picks as parent the neighbour minimising
``advertised cost + link cost`` (ETX x 10 integers), with hysteresis. A mote
that loses its parent poisons its route and, for ``ctp_holddown`` seconds,
accepts only neighbours heard since the loss with a lower cost. The rules and
why: docs/protocol-dissemination.md, "Collection tree".
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType

from awaremw.protocol.component import MoteContext
from awaremw.protocol.events import ParentChanged
from awaremw.protocol.frames import BROADCAST, NO_ROUTE, CtpBeacon, CtpData
from awaremw.protocol.timers import TimerSet
from awaremw.protocol.trickle import Trickle

ETX_ONE = 10  # ETX 1.0 in the x10 integer scale of costs
MAX_COST = NO_ROUTE - 1  # path costs saturate here (NO_ROUTE means "none")

BEACON_TIMER = "beacon"
HOLDDOWN_TIMER = "holddown"


@dataclass(slots=True)
class Neighbour:
    """What a mote knows about one neighbour (mutable routing-table entry).

    ``link`` and ``path`` cache :meth:`Routes.link_cost` and the path cost
    through it (NO_ROUTE, or ``cost + link`` saturated at MAX_COST): the
    routes recompute them whenever they change ``cost``, ``rssi`` or
    ``ack_etx``, so the parent choice reads them instead of recomputing every
    neighbour's link cost on every beacon. Only :class:`Routes` mutates entries.
    """

    node: int
    cost: int = NO_ROUTE  # its advertised path cost
    parent: int = BROADCAST  # its advertised parent
    rssi: float | None = None  # EWMA of the RSSI of its frames
    ack_etx: float = float(ETX_ONE)  # EWMA of unicast outcomes, x10
    failures: int = 0  # consecutive failed unicasts to it
    last_heard: float = 0.0
    link: int = 0  # cached link cost (set by the routes)
    path: int = NO_ROUTE  # cached path cost through it (set by the routes)


@dataclass(slots=True)
class CollectionStats:
    """The collection's counters: one record that every part of it counts in."""

    submitted: int = 0
    delivered: int = 0  # at a root
    forwarded: int = 0  # unicasts acknowledged (own and others' packets)
    duplicates: int = 0
    dropped: int = 0
    inconsistencies: int = 0  # data from a neighbour whose cost is not above ours
    loops: int = 0  # a packet came back to us: route poisoned
    parent_changes: int = 0
    evictions: int = 0
    switches_on_eviction: int = 0  # evicted parent replaced without losing the route
    switches_on_poison: int = 0  # parent without a route replaced without losing ours
    beacons: int = 0
    data_tx: int = 0  # unicast attempts handed to the link layer


class Beacons:
    """When to beacon: a Trickle reset only on what CTP resets on, so an idle
    network whispers. Beacons carry per-mote information, so there is no
    suppression (never ``hear_consistent``): k only has to be >= 1."""

    def __init__(self, ctx: MoteContext, timers: TimerSet) -> None:
        cfg = ctx.config
        self.trickle = Trickle(cfg.ctp_tau_l, cfg.ctp_tau_h, 1, ctx.rng)
        self._timers = timers

    def announce(self, now: float) -> None:
        """At boot, and on a route change: beacon within tau_l even if the
        Trickle is already at tau_l and has spoken in this interval (a plain
        reset would wait for the next one), so that poison and new costs
        travel one hop per ~tau_l."""
        self.trickle.start(now)
        self.arm()

    def reset(self, now: float) -> None:
        self.trickle.reset(now)
        self.arm()

    def arm(self) -> None:
        d = self.trickle.next_deadline()
        if d is not None:
            self._timers.set(BEACON_TIMER, d)


class Routes:
    """The neighbour table, its link estimates and the parent choice of one mote."""

    def __init__(
        self, ctx: MoteContext, timers: TimerSet, beacons: Beacons, stats: CollectionStats
    ) -> None:
        cfg = ctx.config
        self._ctx = ctx
        self._timers = timers
        self._beacons = beacons
        self._stats = stats
        self._neighbours: dict[int, Neighbour] = {}
        self._parent: int | None = None
        self._cost = 0 if cfg.is_root else NO_ROUTE
        self._lost_cost: int | None = None  # cost before the route was lost
        # The lowest cost we held since we took a route (a feasible distance, as
        # in DUAL): our descendants advertise more, so a neighbour advertising
        # less cannot be one of them.
        self._feasible = self._cost
        self._lost_parent: int | None = None  # not taken back during the hold-down
        # Neighbours must have been heard since our last route loss to be chosen:
        # older entries may be dead motes (a dead mote never says so).
        self._fresh_since = float("-inf")
        # The answer of _best() with its defaults and fresh_since=_fresh_since,
        # kept current entry by entry (_changed); None: recompute on next use.
        self._best_cache: tuple[Neighbour | None, int] | None = None
        self._holddown_until = float("-inf")
        # Read on every beacon heard (the config is frozen and never replaced).
        self._root = cfg.is_root
        self._rssi_alpha = cfg.ctp_rssi_alpha
        self._rssi_floor = cfg.ctp_rssi_floor
        self._rssi_good = cfg.ctp_rssi_good
        self._rssi_max_etx = cfg.ctp_rssi_max_etx
        self._switch = cfg.ctp_parent_switch_threshold

    @property
    def parent(self) -> int | None:
        return self._parent

    @property
    def cost(self) -> int:
        """Path cost to a root, ETX x 10 (0 at a root, NO_ROUTE without a route)."""
        return self._cost

    @property
    def neighbours(self) -> Mapping[int, Neighbour]:
        return MappingProxyType(self._neighbours)

    def beacon(self) -> CtpBeacon:
        """Our advertisement: our cost and parent, pulling while we have no route."""
        pull = not self._root and self._parent is None
        parent = BROADCAST if self._parent is None else self._parent
        return CtpBeacon(self._ctx.node_id, BROADCAST, self._cost, parent, pull)

    # ------------------------------------------------------------------ link estimates

    def link_cost(self, n: Neighbour) -> int:
        """ETX x 10 of the link to ``n``: max of the RSSI mapping and the ACK EWMA."""
        return max(self.rssi_cost(n.rssi), round(n.ack_etx))

    def rssi_cost(self, rssi: float | None) -> int:
        """ETX x 10 of a link heard at ``rssi``: 1 above ``ctp_rssi_good``, the
        maximum below ``ctp_rssi_floor``, a cubic between."""
        cfg = self._ctx.config
        if rssi is None or rssi <= cfg.ctp_rssi_floor:
            return cfg.ctp_rssi_max_etx
        if rssi >= cfg.ctp_rssi_good:
            return ETX_ONE
        x = (cfg.ctp_rssi_good - rssi) / (cfg.ctp_rssi_good - cfg.ctp_rssi_floor)
        return ETX_ONE + round((cfg.ctp_rssi_max_etx - ETX_ONE) * x**3)

    def _recost(self, n: Neighbour) -> None:
        """Refresh ``n``'s cached link and path costs (after any change of
        its cost, RSSI or ACK estimate)."""
        # rssi_cost inlined (the same operations, once per beacon heard)
        rssi = n.rssi
        if rssi is None or rssi <= self._rssi_floor:
            rc = self._rssi_max_etx
        elif rssi >= self._rssi_good:
            rc = ETX_ONE
        else:
            x = (self._rssi_good - rssi) / (self._rssi_good - self._rssi_floor)
            rc = ETX_ONE + round((self._rssi_max_etx - ETX_ONE) * x**3)
        ack = round(n.ack_etx)
        n.link = link = rc if rc >= ack else ack  # max(rc, ack)
        cost = n.cost
        if cost >= NO_ROUTE:
            n.path = NO_ROUTE
        else:
            p = cost + link
            n.path = p if p < MAX_COST else MAX_COST  # min(p, MAX_COST)

    def link_result(self, node: int, acked: bool, now: float) -> None:
        """A unicast to ``node`` was acknowledged or not: move its ACK estimate
        (evicting it after ``ctp_evict_after_failures`` failures in a row)."""
        n = self._neighbours.get(node)
        if n is None:
            return
        cfg = self._ctx.config
        a = cfg.ctp_etx_alpha
        if acked:
            n.failures = 0
            n.ack_etx = (1 - a) * n.ack_etx + a * ETX_ONE
            self._recost(n)
            self._changed(n)
            return
        n.failures += 1
        n.ack_etx = (1 - a) * n.ack_etx + a * cfg.ctp_fail_etx
        self._recost(n)
        self._changed(n)
        if n.failures >= cfg.ctp_evict_after_failures:
            if (
                node == self._parent
                and n.failures < cfg.ctp_poison_after_failures
                and self._alternative(node, now, routeless=False)[0] is None
            ):
                return
            self._evict(n.node, now)

    # ------------------------------------------------------------------ what we hear

    def hear_beacon(self, b: CtpBeacon, rssi: float, now: float) -> None:
        n = self._neighbours.get(b.src)
        if n is None:
            self.note(b.src, rssi, now, b.cost, b.parent)
        else:  # note of a known neighbour, inlined (once per beacon heard)
            n.cost, n.parent, n.last_heard = b.cost, b.parent, now
            a = self._rssi_alpha
            n.rssi = rssi if n.rssi is None else a * rssi + (1 - a) * n.rssi
            self._recost(n)
            self._changed(n)
        if b.pull and (self._root or self._parent is not None):
            self._beacons.reset(now)
        if b.src == self._parent and (b.cost >= NO_ROUTE or b.parent == self._ctx.node_id):
            self._parent_lost_route(b.src, now)
        self.update_route(now)

    def hear_data(self, d: CtpData, rssi: float, now: float) -> None:
        """Data from a known neighbour says it routes through us, at that cost."""
        if d.src in self._neighbours:
            self.note(d.src, rssi, now, d.cost, self._ctx.node_id)

    def note(self, node: int, rssi: float, now: float, cost: int, parent: int) -> None:
        n = self._neighbours.get(node)
        if n is None:
            n = Neighbour(node, cost, parent, rssi, last_heard=now)
            self._recost(n)
            if len(self._neighbours) >= self._ctx.config.ctp_neighbours:
                # Full table: replace the worst entry (never the parent) if worse.
                others = [x for x in self._neighbours.values() if x.node != self._parent]
                if not others:
                    return
                worst = max(others, key=_path_via)
                if n.path >= worst.path:
                    return
                del self._neighbours[worst.node]
                self._best_cache = None
            self._neighbours[node] = n
            self._changed(n)
            return
        n.cost, n.parent, n.last_heard = cost, parent, now
        a = self._rssi_alpha
        n.rssi = rssi if n.rssi is None else a * rssi + (1 - a) * n.rssi
        self._recost(n)
        self._changed(n)

    # ------------------------------------------------------------------ parent choice

    def _best(
        self,
        below: int | None = None,
        exclude: int | None = None,
        fresh_since: float = float("-inf"),
        not_via: int | None = None,
    ) -> tuple[Neighbour | None, int]:
        """The neighbour with the cheapest path among those heard since
        ``fresh_since`` and, during a hold-down, advertising a cost under
        ``below``, other than ``exclude`` and than those whose parent is
        ``not_via``."""
        me = self._ctx.node_id
        best: Neighbour | None = None
        best_path = NO_ROUTE
        limit = NO_ROUTE if below is None else below
        for n in self._neighbours.values():
            if n.cost >= limit or n.parent == me or n.node == exclude:
                continue
            if not_via is not None and n.parent == not_via:
                continue
            if n.last_heard < fresh_since:
                continue
            p = n.path  # cached (see _recost)
            if p < best_path or (p == best_path and best is not None and n.node < best.node):
                best, best_path = n, p
        return best, best_path

    def _changed(self, n: Neighbour) -> None:
        """Entry ``n`` (in the table) changed: keep the cached best choice.

        The choice is the entry with the smallest ``(path, node)`` among those
        that qualify, whatever the order of the table. If ``n`` was the choice,
        it may have got worse: recompute on next use. Otherwise only ``n``
        can have become the choice: compare it with the cached one.
        """
        c = self._best_cache
        if c is None:
            return
        best, best_path = c
        if best is n:
            self._best_cache = None
            return
        if n.cost >= NO_ROUTE or n.parent == self._ctx.node_id or n.last_heard < self._fresh_since:
            return
        p = n.path
        if p < best_path or (p == best_path and best is not None and n.node < best.node):
            self._best_cache = (n, p)

    def update_route(self, now: float) -> None:
        if self._root:
            return
        cached = self._best_cache
        if cached is None:
            cached = self._best_cache = self._best(fresh_since=self._fresh_since)
        best, best_path = cached
        parent = self._parent
        if parent is not None:
            cur = self._neighbours[parent].path
            if best is not None and best.node != parent and best_path + self._switch < cur:
                self._set_parent(best, best_path, now)
            elif cur != self._cost:
                # No beacon for a cost that moved (the link estimates of a static
                # network wander with fading): CTP resets only on a loop, a lost
                # route or a pull, and the data path reports the costs that matter.
                self._cost = cur
                if cur < self._feasible:
                    self._feasible = cur
            return
        if best is None:
            return
        if now < self._holddown_until:
            best, best_path = self._best(self._lost_cost, self._lost_parent, self._fresh_since)
        if best is not None:
            self._set_parent(best, best_path, now)

    def _set_parent(self, n: Neighbour, path: int, now: float) -> None:
        old = self._parent
        self._parent = n.node
        n.failures = 0  # "in a row" counts from now: failures to it before do not carry over
        self._cost = path
        self._feasible = path if old is None else min(self._feasible, path)
        self._lost_cost = self._lost_parent = None
        self._holddown_until = float("-inf")
        self._timers.cancel(HOLDDOWN_TIMER)
        self._stats.parent_changes += 1
        self._ctx.emit(ParentChanged(old, n.node, path))
        if old is None:
            # A route found after none: the neighbours that pulled (our children
            # among them, poisoned with us) need it now. A switch between two
            # routes is not announced: stale costs downstream are harmless until
            # data flows, and then datapath validation asks for a beacon.
            self._beacons.announce(now)

    def lose_parent(self, now: float) -> None:
        """Poison our route and hold down the repair (see the module docstring)."""
        old = self._parent
        if old is None:
            return
        self._lost_cost = self._cost
        self._lost_parent = old
        self._fresh_since = now
        self._best_cache = None
        self._parent = None
        self._cost = self._feasible = NO_ROUTE
        self._holddown_until = now + self._ctx.config.ctp_holddown
        self._timers.set(HOLDDOWN_TIMER, self._holddown_until)
        self._stats.parent_changes += 1
        self._ctx.emit(ParentChanged(old, None, NO_ROUTE))
        self._beacons.announce(now)

    def _parent_lost_route(self, parent: int, now: float) -> None:
        """Our parent advertises no route (or routes through us). A feasible
        neighbour that does not route through that parent takes over without a
        poison. A poison costs every mote below us its route, their pulls and
        a round of beacons at tau_l; under meyer-heavy these cascades were 277
        of the 394 route losses on the 1,000-mote grid (seed 1). Otherwise we
        poison too."""
        if self._replace_parent(parent, now, routeless=True):
            self._stats.switches_on_poison += 1

    def _evict(self, node: int, now: float) -> None:
        self._stats.evictions += 1
        del self._neighbours[node]
        self._best_cache = None
        if node != self._parent:
            return
        # The parent failed us, not necessarily the others: on bursty links a
        # noise burst at one end loses a few unicasts in a row. A neighbour
        # heard lately that advertises a cost below our feasible distance is
        # not one of our descendants: switch to it, as CTP does, without the
        # poison wave (every child's route lost, pulls, beacons at tau_l).
        if self._replace_parent(node, now, routeless=False):
            self._stats.switches_on_eviction += 1

    def _alternative(
        self, parent: int, now: float, routeless: bool
    ) -> tuple[Neighbour | None, int]:
        fresh = now - self._ctx.config.ctp_switch_fresh
        not_via = parent if routeless else None
        return self._best(self._feasible, parent, max(fresh, self._fresh_since), not_via)

    def _replace_parent(self, parent: int, now: float, routeless: bool) -> bool:
        """Switch to the best neighbour other than ``parent``, heard within
        ``ctp_switch_fresh`` (and since our last route loss), advertising a
        cost below our feasible distance (not one of our descendants) and,
        when the parent has no route (``routeless``), not routing through it
        (an evicted parent may serve its other children well). Without one,
        poison. True if switched."""
        alt, path = self._alternative(parent, now, routeless)
        if alt is None:
            self.lose_parent(now)
            return False
        self._set_parent(alt, path, now)
        return True


def _path_via(n: Neighbour) -> int:
    return n.path  # kept current by Routes._recost
