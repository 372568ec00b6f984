"""The data half of the collection tree (:mod:`awaremw.protocol.collection`):
the forwarding queue. Data is unicast hop by hop to the parent the routes
chose, with link- and routing-level retries; forwarders drop duplicates by
``(origin, seqno, THL)``, detect loops and stale costs on the data path, and
roots emit :class:`Delivered`. Why each rule is as it is:
docs/protocol-dissemination.md, "Collection tree".
"""

from __future__ import annotations

from collections import OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass, field

from awaremw.protocol.component import MoteContext
from awaremw.protocol.core import Transmission
from awaremw.protocol.ctp_routes import MAX_COST, Beacons, CollectionStats, Routes
from awaremw.protocol.events import DataDropped, Delivered
from awaremw.protocol.frames import CtpData, Frame, Payload
from awaremw.protocol.timers import TimerSet

RETRY_TIMER = "retry"


@dataclass(slots=True)
class _Packet:
    origin: int
    seqno: int
    thl: int
    payload: Payload
    attempts: int = 0
    rx_thl: int = field(default=-1)  # THL it arrived with, -1 if our own


class Forwarder:
    """The queue of packets on their way to a root, at most one in flight."""

    def __init__(
        self,
        ctx: MoteContext,
        timers: TimerSet,
        send: Callable[[Frame], Transmission],
        routes: Routes,
        beacons: Beacons,
        stats: CollectionStats,
    ) -> None:
        self._ctx = ctx
        self._timers = timers
        self._send = send
        self._routes = routes
        self._beacons = beacons
        self._stats = stats
        self._root = ctx.config.is_root
        self._queue: deque[_Packet] = deque()
        self._in_flight: CtpData | None = None
        self._seqno = 0
        # (origin, seqno) -> (THL heard, when): copies within ctp_dup_ttl are duplicates.
        self._dups: OrderedDict[tuple[int, int], tuple[int, float]] = OrderedDict()
        # Root: origin -> seqno -> when delivered (the last ctp_root_window seqnos).
        self._root_seen: dict[int, OrderedDict[int, float]] = {}

    def __len__(self) -> int:
        return len(self._queue)

    def submit(self, payload: Payload, now: float) -> bool:
        """See :meth:`Collection.submit`."""
        self._seqno = (self._seqno + 1) & 0xFFFF
        if self._root:
            self._stats.submitted += 1
            self._deliver(self._ctx.node_id, self._seqno, payload, 0, now)
            return True
        if len(self._queue) >= self._ctx.config.ctp_queue:
            return False
        self._stats.submitted += 1
        self._queue.append(_Packet(self._ctx.node_id, self._seqno, 0, payload))
        self.pump(now)
        return True

    def on_data(self, d: CtpData, rssi: float, now: float) -> None:
        me = self._ctx.node_id
        routes = self._routes
        routes.hear_data(d, rssi, now)
        assert d.payload is not None  # CtpData validates it
        if self._root:
            self._deliver(d.origin, d.seqno, d.payload, d.thl + 1, now)
            return
        if d.cost <= routes.cost:
            # The sender thinks we are closer to a root than it is, and we are not:
            # our beacons are stale there. Tell it soon; still forward the packet.
            self._stats.inconsistencies += 1
            self._beacons.reset(now)
        key = (d.origin, d.seqno)
        entry = self._dups.get(key)
        heard = None if entry is None or now - entry[1] > self._ctx.config.ctp_dup_ttl else entry[0]
        if heard is None:
            heard = next((p.rx_thl for p in self._queue if (p.origin, p.seqno) == key), None)
        if heard == d.thl:
            self._stats.duplicates += 1  # a retransmission whose ACK was lost
            return
        if d.src == routes.parent or d.origin == me:
            # Our own packet came back, or our parent routes through us: we are in
            # a loop. Poison and re-attach; keep the packet.
            self._stats.loops += 1
            routes.lose_parent(now)
            routes.update_route(now)
        elif heard is not None:
            # A packet we already forwarded, with another THL, and no sign of a
            # loop: a copy (a lost ACK, a parent change, two paths). Forwarding
            # every copy multiplies them at each lossy hop (meyer-heavy noise: 44
            # records, 4,363 forwards); one copy per forwarder is enough.
            self._stats.duplicates += 1
            return
        self._dups[key] = (d.thl, now)
        self._dups.move_to_end(key)
        if len(self._dups) > self._ctx.config.ctp_dup_cache:
            self._dups.popitem(last=False)
        pkt = _Packet(d.origin, d.seqno, d.thl + 1, d.payload, rx_thl=d.thl)
        if pkt.thl > self._ctx.config.ctp_max_thl:
            self._drop(pkt, "thl")
            return
        if len(self._queue) >= self._ctx.config.ctp_queue:
            self._drop(pkt, "queue full")
            return
        self._queue.append(pkt)
        self.pump(now)

    def on_link_result(self, frame: Frame, acked: bool, now: float) -> None:
        """The outcome of the unicast in flight (other frames are not ours)."""
        if not isinstance(frame, CtpData) or frame is not self._in_flight:
            return
        self._in_flight = None
        pkt = self._queue[0]
        if acked:
            self._queue.popleft()
            self._stats.forwarded += 1
        self._routes.link_result(frame.dst, acked, now)
        if not acked:
            pkt.attempts += 1
            cfg = self._ctx.config
            if pkt.attempts >= cfg.ctp_max_retries:
                self._queue.popleft()
                self._drop(pkt, "retries")
            d = cfg.ctp_retry_delay
            self._timers.set(RETRY_TIMER, now + self._ctx.rng.uniform(d / 2, d))
        self._routes.update_route(now)  # the link estimate moved
        self.pump(now)

    def pump(self, now: float) -> None:
        """Hand the head of the queue to the link layer if nothing is in flight."""
        parent = self._routes.parent
        if self._in_flight is not None or not self._queue or parent is None:
            return
        if RETRY_TIMER in self._timers:
            return
        pkt = self._queue[0]
        cost = min(self._routes.cost, MAX_COST)
        frame = CtpData(
            self._ctx.node_id, parent, pkt.origin, pkt.seqno, pkt.thl, cost, pkt.payload
        )
        self._in_flight = frame
        self._stats.data_tx += 1
        self._send(frame)

    def _deliver(self, origin: int, seqno: int, payload: Payload, thl: int, now: float) -> None:
        cfg = self._ctx.config
        seen = self._root_seen.get(origin)
        if seen is None:
            seen = self._root_seen[origin] = OrderedDict()
        at = seen.get(seqno)
        if at is not None and now - at <= cfg.ctp_dup_ttl:
            self._stats.duplicates += 1
            return
        seen[seqno] = now
        seen.move_to_end(seqno)
        if len(seen) > cfg.ctp_root_window:
            seen.popitem(last=False)
        self._stats.delivered += 1
        self._ctx.emit(Delivered(origin, payload, thl, now))

    def _drop(self, pkt: _Packet, reason: str) -> None:
        self._stats.dropped += 1
        self._ctx.emit(DataDropped(pkt.origin, pkt.seqno, reason))
