"""A CTP-like collection tree to the gateway roots (Gnawali et al., SenSys 2009).

Roots (``config.is_root``, any gateway mote; several are allowed) advertise
cost 0; every other mote picks as parent the neighbour minimising
``advertised cost + link cost`` (ETX x 10 integers), with hysteresis. Beacons
are paced by a Trickle reset only on what CTP resets on (a route found or lost,
a neighbour's ``pull``, the data path detecting a loop or an inconsistency), so
an idle network whispers. Link cost maps the EWMA RSSI through a cubic (as
MultiHopLQI maps LQI), corrected by unicast outcomes. A mote that loses its
parent poisons its route and, for ``ctp_holddown`` seconds, accepts only
neighbours heard since the loss with a lower cost, so the repair does not build
loops through a subtree whose information is stale. Data is unicast hop by
hop with link- and routing-level retries; forwarders drop duplicates by
``(origin, seqno, THL)`` and roots emit :class:`Delivered`. The rules, their
parameters and why each is as it is: docs/protocol-dissemination.md,
"Collection tree".
"""

from __future__ import annotations

from collections import OrderedDict, deque
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

from awaremw.protocol.component import Component, MoteContext
from awaremw.protocol.events import DataDropped, Delivered, ParentChanged
from awaremw.protocol.frames import BROADCAST, NO_ROUTE, CtpBeacon, CtpData, Frame, Payload
from awaremw.protocol.trickle import Trickle

ETX_ONE = 10  # ETX 1.0 in the x10 integer scale of costs
MAX_COST = NO_ROUTE - 1  # path costs saturate here (NO_ROUTE means "none")


# --------------------------------------------------------------------------- state


@dataclass(slots=True)
class Neighbour:
    """What a mote knows about one neighbour (mutable routing-table entry).

    ``link`` and ``path`` cache :meth:`Collection.link_cost` and the path cost
    through it (NO_ROUTE, or ``cost + link`` saturated at MAX_COST): the
    collection recomputes them whenever it changes ``cost``, ``rssi`` or
    ``ack_etx``, so the parent choice reads them instead of recomputing every
    neighbour's link cost on every beacon. Only the collection mutates entries.
    """

    node: int
    cost: int = NO_ROUTE  # its advertised path cost
    parent: int = BROADCAST  # its advertised parent
    rssi: float | None = None  # EWMA of the RSSI of its frames
    ack_etx: float = float(ETX_ONE)  # EWMA of unicast outcomes, x10
    failures: int = 0  # consecutive failed unicasts to it
    last_heard: float = 0.0
    link: int = 0  # cached link cost (set by the collection)
    path: int = NO_ROUTE  # cached path cost through it (set by the collection)


@dataclass(slots=True)
class CollectionStats:
    submitted: int = 0
    delivered: int = 0  # at a root
    forwarded: int = 0  # unicasts acknowledged (own and others' packets)
    duplicates: int = 0
    dropped: int = 0
    inconsistencies: int = 0  # data from a neighbour whose cost is not above ours
    loops: int = 0  # a packet came back to us: route poisoned
    parent_changes: int = 0
    evictions: int = 0
    beacons: int = 0
    data_tx: int = 0  # unicast attempts handed to the link layer


@dataclass(slots=True)
class _Packet:
    origin: int
    seqno: int
    thl: int
    payload: Payload
    attempts: int = 0
    rx_thl: int = field(default=-1)  # THL it arrived with, -1 if our own


class Collection(Component):
    """The collection-tree component of one mote."""

    def __init__(self, ctx: MoteContext) -> None:
        super().__init__(ctx)
        cfg = ctx.config
        # Beacons carry per-mote information, so there is no suppression (never
        # hear_consistent): k only has to be >= 1.
        self._trickle = Trickle(cfg.ctp_tau_l, cfg.ctp_tau_h, 1, ctx.rng)
        self._neighbours: dict[int, Neighbour] = {}
        self._parent: int | None = None
        self._cost = 0 if cfg.is_root else NO_ROUTE
        self._queue: deque[_Packet] = deque()
        self._in_flight: CtpData | None = None
        self._seqno = 0
        self._dups: OrderedDict[tuple[int, int], int] = OrderedDict()  # -> THL heard
        self._root_seen: dict[int, deque[int]] = {}
        self._lost_cost: int | None = None  # cost before the route was lost
        self._lost_parent: int | None = None  # not taken back during the hold-down
        # Neighbours must have been heard since our last route loss to be chosen:
        # older entries may be dead motes (a dead mote never says so).
        self._fresh_since = float("-inf")
        # The answer of _best() with its defaults and fresh_since=_fresh_since,
        # kept current entry by entry (_changed); None: recompute on next use.
        self._best_cache: tuple[Neighbour | None, int] | None = None
        self._holddown_until = float("-inf")
        self.stats = CollectionStats()
        # Read on every beacon heard (the config is frozen and never replaced).
        self._root = cfg.is_root
        self._rssi_alpha = cfg.ctp_rssi_alpha
        self._rssi_floor = cfg.ctp_rssi_floor
        self._rssi_good = cfg.ctp_rssi_good
        self._rssi_max_etx = cfg.ctp_rssi_max_etx
        self._switch = cfg.ctp_parent_switch_threshold

    # ------------------------------------------------------------------ public API

    @property
    def is_root(self) -> bool:
        return self.ctx.config.is_root

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

    @property
    def queue_length(self) -> int:
        return len(self._queue)

    @property
    def beacon_trickle(self) -> Trickle:
        return self._trickle

    def submit(self, payload: Payload, now: float) -> bool:
        """Queue ``payload`` for a root. False if refused (queue full); without a
        route it waits in the queue. At a root it is delivered at once."""
        self._seqno = (self._seqno + 1) & 0xFFFF
        if self.is_root:
            self.stats.submitted += 1
            self._deliver(self.ctx.node_id, self._seqno, payload, 0, now)
            return True
        if len(self._queue) >= self.ctx.config.ctp_queue:
            return False
        self.stats.submitted += 1
        self._queue.append(_Packet(self.ctx.node_id, self._seqno, 0, payload))
        self._pump(now)
        return True

    def link_cost(self, n: Neighbour) -> int:
        """ETX x 10 of the link to ``n``: max of the RSSI mapping and the ACK EWMA."""
        return max(self._rssi_cost(n.rssi), round(n.ack_etx))

    def _recost(self, n: Neighbour) -> None:
        """Refresh ``n``'s cached link and path costs (after any change of
        its cost, RSSI or ACK estimate)."""
        # _rssi_cost inlined (the same operations, once per beacon heard)
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

    # ------------------------------------------------------------------ Component hooks

    def start(self, now: float) -> None:
        self._trickle.start(now)
        self._arm_beacon()

    def on_frame(self, frame: Frame, rssi_dbm: float, now: float) -> None:
        if isinstance(frame, CtpBeacon):
            self._on_beacon(frame, rssi_dbm, now)
        elif isinstance(frame, CtpData):
            self._on_data(frame, rssi_dbm, now)

    def on_timer(self, name: object, now: float) -> None:
        if name == "beacon":
            if self._trickle.handle_timer(now):
                self._send_beacon()
            self._arm_beacon()
        elif name == "retry":
            self._pump(now)
        elif name == "holddown":
            self._update_route(now)
            self._pump(now)

    def on_link_result(self, frame: Frame, acked: bool, now: float) -> None:
        if not isinstance(frame, CtpData) or frame is not self._in_flight:
            return
        self._in_flight = None
        pkt = self._queue[0]
        n = self._neighbours.get(frame.dst)
        cfg = self.ctx.config
        a = cfg.ctp_etx_alpha
        if acked:
            self._queue.popleft()
            self.stats.forwarded += 1
            if n is not None:
                n.failures = 0
                n.ack_etx = (1 - a) * n.ack_etx + a * ETX_ONE
                self._recost(n)
                self._changed(n)
        else:
            pkt.attempts += 1
            if n is not None:
                n.failures += 1
                n.ack_etx = (1 - a) * n.ack_etx + a * cfg.ctp_fail_etx
                self._recost(n)
                self._changed(n)
                if n.failures >= cfg.ctp_evict_after_failures:
                    self._evict(n.node, now)
            if pkt.attempts >= cfg.ctp_max_retries:
                self._queue.popleft()
                self._drop(pkt, "retries")
            d = cfg.ctp_retry_delay
            self.timers.set("retry", now + self.ctx.rng.uniform(d / 2, d))
        self._update_route(now)  # the link estimate moved
        self._pump(now)

    # ------------------------------------------------------------------ routing

    def _on_beacon(self, b: CtpBeacon, rssi: float, now: float) -> None:
        n = self._neighbours.get(b.src)
        if n is None:
            self._note(b.src, rssi, now, b.cost, b.parent)
        else:  # _note of a known neighbour, inlined (once per beacon heard)
            n.cost, n.parent, n.last_heard = b.cost, b.parent, now
            a = self._rssi_alpha
            n.rssi = rssi if n.rssi is None else a * rssi + (1 - a) * n.rssi
            self._recost(n)
            self._changed(n)
        if b.pull and (self._root or self._parent is not None):
            self._reset_trickle(now)
        if b.src == self._parent and (b.cost >= NO_ROUTE or b.parent == self.ctx.node_id):
            self._lose_parent(now)
        self._update_route(now)
        if self._queue:  # else _pump has nothing to do
            self._pump(now)

    def _note(self, node: int, rssi: float, now: float, cost: int, parent: int) -> None:
        n = self._neighbours.get(node)
        if n is None:
            n = Neighbour(node, cost, parent, rssi, last_heard=now)
            self._recost(n)
            if len(self._neighbours) >= self.ctx.config.ctp_neighbours:
                # Full table: replace the worst entry (never the parent) if worse.
                others = [x for x in self._neighbours.values() if x.node != self._parent]
                if not others:
                    return
                worst = max(others, key=self._path_via)
                if self._path_via(n) >= self._path_via(worst):
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

    def _rssi_cost(self, rssi: float | None) -> int:
        cfg = self.ctx.config
        if rssi is None or rssi <= cfg.ctp_rssi_floor:
            return cfg.ctp_rssi_max_etx
        if rssi >= cfg.ctp_rssi_good:
            return ETX_ONE
        x = (cfg.ctp_rssi_good - rssi) / (cfg.ctp_rssi_good - cfg.ctp_rssi_floor)
        return ETX_ONE + round((cfg.ctp_rssi_max_etx - ETX_ONE) * x**3)

    def _path_via(self, n: Neighbour) -> int:
        return n.path  # kept current by _recost

    def _best(
        self,
        below: int | None = None,
        exclude: int | None = None,
        fresh_since: float = float("-inf"),
    ) -> tuple[Neighbour | None, int]:
        """The neighbour with the cheapest path among those heard since
        ``fresh_since`` and, during a hold-down, advertising a cost under
        ``below``, other than ``exclude``."""
        me = self.ctx.node_id
        best: Neighbour | None = None
        best_path = NO_ROUTE
        limit = NO_ROUTE if below is None else below
        for n in self._neighbours.values():
            if n.cost >= limit or n.parent == me or n.node == exclude:
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
        if n.cost >= NO_ROUTE or n.parent == self.ctx.node_id or n.last_heard < self._fresh_since:
            return
        p = n.path
        if p < best_path or (p == best_path and best is not None and n.node < best.node):
            self._best_cache = (n, p)

    def _update_route(self, now: float) -> None:
        if self._root:
            return
        cached = self._best_cache
        if cached is None:
            cached = self._best_cache = self._best(fresh_since=self._fresh_since)
        best, best_path = cached
        parent = self._parent
        if parent is not None:
            cur = self._neighbours[parent].path  # _path_via
            if best is not None and best.node != parent and best_path + self._switch < cur:
                self._set_parent(best, best_path, now)
            elif cur != self._cost:
                self._set_cost(cur, now)
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
        self._cost = path
        self._lost_cost = self._lost_parent = None
        self._holddown_until = float("-inf")
        self.timers.cancel("holddown")
        self.stats.parent_changes += 1
        self.ctx.emit(ParentChanged(old, n.node, path))
        if old is None:
            # A route found after none: the neighbours that pulled (our children
            # among them, poisoned with us) need it now. A switch between two
            # routes is not announced: stale costs downstream are harmless until
            # data flows, and then datapath validation asks for a beacon.
            self._announce(now)

    def _set_cost(self, cost: int, now: float) -> None:
        # No beacon for a cost that moved (the link estimates of a static network
        # wander with fading): CTP resets only on a loop, a lost route or a pull,
        # and the data path reports the costs that matter (see _on_data).
        self._cost = cost

    def _lose_parent(self, now: float) -> None:
        old = self._parent
        if old is None:
            return
        self._lost_cost = self._cost
        self._lost_parent = old
        self._fresh_since = now
        self._best_cache = None
        self._parent = None
        self._cost = NO_ROUTE
        self._holddown_until = now + self.ctx.config.ctp_holddown
        self.timers.set("holddown", self._holddown_until)
        self.stats.parent_changes += 1
        self.ctx.emit(ParentChanged(old, None, NO_ROUTE))
        self._announce(now)

    def _evict(self, node: int, now: float) -> None:
        self.stats.evictions += 1
        del self._neighbours[node]
        self._best_cache = None
        if node == self._parent:
            self._lose_parent(now)

    def _announce(self, now: float) -> None:
        """A route change: beacon within tau_l even if the Trickle is already at
        tau_l and has spoken in this interval (a plain reset would wait for the
        next one), so that poison and new costs travel one hop per ~tau_l."""
        self._trickle.start(now)
        self._arm_beacon()

    def _reset_trickle(self, now: float) -> None:
        self._trickle.reset(now)
        self._arm_beacon()

    def _arm_beacon(self) -> None:
        d = self._trickle.next_deadline()
        if d is not None:
            self.timers.set("beacon", d)

    def _send_beacon(self) -> None:
        self.stats.beacons += 1
        pull = not self.is_root and self._parent is None
        parent = BROADCAST if self._parent is None else self._parent
        self.send(CtpBeacon(self.ctx.node_id, BROADCAST, self._cost, parent, pull))

    # ------------------------------------------------------------------ data

    def _on_data(self, d: CtpData, rssi: float, now: float) -> None:
        me = self.ctx.node_id
        n = self._neighbours.get(d.src)
        if n is not None:
            # Data from a neighbour says it routes through us, at that cost.
            self._note(d.src, rssi, now, d.cost, me)
        assert d.payload is not None  # CtpData validates it
        if self.is_root:
            self._deliver(d.origin, d.seqno, d.payload, d.thl + 1, now)
            return
        if d.cost <= self._cost:
            # The sender thinks we are closer to a root than it is, and we are not:
            # our beacons are stale there. Tell it soon; still forward the packet.
            self.stats.inconsistencies += 1
            self._reset_trickle(now)
        key = (d.origin, d.seqno)
        heard = self._dups.get(key)
        if heard is None:
            heard = next((p.rx_thl for p in self._queue if (p.origin, p.seqno) == key), None)
        if heard == d.thl:
            self.stats.duplicates += 1  # a retransmission whose ACK was lost
            return
        if d.src == self._parent or d.origin == me:
            # Our own packet came back, or our parent routes through us: we are in
            # a loop. Poison and re-attach; keep the packet.
            self.stats.loops += 1
            self._lose_parent(now)
            self._update_route(now)
        elif heard is not None:
            # A packet we already forwarded, with another THL, and no sign of a
            # loop: a copy (a lost ACK, a parent change, two paths). Forwarding
            # every copy multiplies them at each lossy hop (meyer-heavy noise: 44
            # records, 4,363 forwards); one copy per forwarder is enough.
            self.stats.duplicates += 1
            return
        self._dups[key] = d.thl
        self._dups.move_to_end(key)
        if len(self._dups) > self.ctx.config.ctp_dup_cache:
            self._dups.popitem(last=False)
        pkt = _Packet(d.origin, d.seqno, d.thl + 1, d.payload, rx_thl=d.thl)
        if pkt.thl > self.ctx.config.ctp_max_thl:
            self._drop(pkt, "thl")
            return
        if len(self._queue) >= self.ctx.config.ctp_queue:
            self._drop(pkt, "queue full")
            return
        self._queue.append(pkt)
        self._pump(now)

    def _deliver(self, origin: int, seqno: int, payload: Payload, thl: int, now: float) -> None:
        seen = self._root_seen.get(origin)
        if seen is None:
            seen = self._root_seen[origin] = deque(maxlen=self.ctx.config.ctp_root_window)
        if seqno in seen:
            self.stats.duplicates += 1
            return
        seen.append(seqno)
        self.stats.delivered += 1
        self.ctx.emit(Delivered(origin, payload, thl, now))

    def _drop(self, pkt: _Packet, reason: str) -> None:
        self.stats.dropped += 1
        self.ctx.emit(DataDropped(pkt.origin, pkt.seqno, reason))

    def _pump(self, now: float) -> None:
        """Hand the head of the queue to the link layer if nothing is in flight."""
        if self._in_flight is not None or not self._queue or self._parent is None:
            return
        if "retry" in self.timers:
            return
        pkt = self._queue[0]
        cost = min(self._cost, MAX_COST)
        frame = CtpData(
            self.ctx.node_id, self._parent, pkt.origin, pkt.seqno, pkt.thl, cost, pkt.payload
        )
        self._in_flight = frame
        self.stats.data_tx += 1
        self.send(frame)
