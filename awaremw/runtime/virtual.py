"""The virtual-clock driver: MoteCores on an in-memory medium, as fast as possible.

A discrete-event simulator: a heap of ``(time, seq, kind, node, data)``
entries, processed in order; ``seq`` (insertion order) breaks ties, so a run is
a deterministic function of the seed, the motes added and the calls made. The
medium applies exactly the rules of the Zenoh medium (``docs/radio.md``,
"Medium semantics"): same cells, same distance cut, same
:class:`~awaremw.radio.model.RadioModel` decisions keyed by
``(seed, src, dst, packet key)``, same link-layer ACK and retries, same
counters.

Speed (the virtual driver must run 1,000 motes at least 10x faster than real
time) comes from caching everything that does not change per packet: for a
static sender, the receivers in its 3x3 cells are split once into those that
may hear it (with their mean RSSI and link hash), those that never can (mean
RSSI too low for any fading draw) and those beyond range; the last two are
counted in bulk (``pending`` broadcasts, folded into the receivers' counters
when the topology changes or when counters are read). Moving motes are
evaluated afresh at every frame.
"""

from __future__ import annotations

import heapq
import math
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import TypeVar

from awaremw.protocol.core import MalformedFrame, MoteCore, Transmission
from awaremw.protocol.frames import BROADCAST, MAX_NODE_ID
from awaremw.radio.counters import Battery, MoteCounters
from awaremw.radio.model import (
    _GOLDEN,
    _M64,
    _MUL,
    _NORMAL,
    _SHIFT,
    _U32,
    RadioModel,
    cell_of,
    packet_hash,
    packet_key,
)
from awaremw.world.mobility import Mobility, Static

T = TypeVar("T")
EventHook = Callable[[int, object, float], None]
TransmitHook = Callable[[int, Transmission, float], None]

_TIMER, _TX_END, _UC_DONE, _START, _CALL = range(5)
_MAX_FIRINGS_AT_ONE_TIME = 100_000


@dataclass(frozen=True, slots=True)
class MoteDown:
    """Event (through ``on_event``): the mote was switched off."""

    reason: str  # "killed" or "battery"


class _Node:
    """Driver-side state of one mote incarnation."""

    __slots__ = (
        "alive",
        "armed",
        "backoff_h",
        "battery",
        "busy",
        "cell",
        "core",
        "counters",
        "cur",
        "cur_attempt",
        "cur_seq",
        "far_dist",
        "far_loss",
        "fire_count",
        "fire_t",
        "id",
        "last_useq",
        "links",
        "lists_ok",
        "mobility",
        "near",
        "pending",
        "pos_t",
        "queue",
        "range_m",
        "seq",
        "started",
        "static",
        "timer_gen",
        "tx_power",
        "x",
        "y",
    )

    def __init__(
        self,
        core: MoteCore,
        counters: MoteCounters,
        mobility: Mobility,
        tx_power: float,
        range_m: float,
        battery: Battery | None,
    ) -> None:
        self.id = core.node_id
        self.core = core
        self.counters = counters
        self.mobility = mobility
        self.static = isinstance(mobility, Static)
        self.tx_power = tx_power
        self.range_m = range_m
        self.battery = battery
        self.alive = False  # on the air: between start and death
        self.started = False
        self.x = 0.0
        self.y = 0.0
        self.cell = (0, 0)
        self.pos_t = -math.inf  # time x, y, cell were computed (moving motes)
        self.queue: deque[Transmission] = deque()
        self.busy = False
        # The frame on the air or awaiting its ACK (None when the radio is idle).
        self.cur: Transmission | None = None
        self.cur_seq = 0
        self.cur_attempt = 0
        self.seq = 0  # 16-bit link sequence number of the next transmission
        self.backoff_h = 0
        self.timer_gen = 0
        self.armed: float | None = None
        self.fire_t = -1.0
        self.fire_count = 0
        self.last_useq: dict[int, int] = {}  # src -> last unicast link seq (duplicates)
        # Static sender caches (see the module docstring).
        self.lists_ok = False
        # (receiver, its counters, its core, mean RSSI, fading link hash)
        self.near: list[tuple[_Node, MoteCounters, MoteCore, float, int]] = []
        self.far_loss: list[_Node] = []
        self.far_dist: list[_Node] = []
        self.pending = 0
        self.links: dict[int, tuple[_Node, float, float, int] | None] = {}


class VirtualNetwork:
    """Motes on a virtual clock, talking through the in-memory medium."""

    def __init__(self, model: RadioModel, seed: int | None = None) -> None:
        if seed is not None and seed != model.seed:
            raise ValueError(f"seed {seed} differs from the radio model's seed {model.seed}")
        self.model = model
        self.seed = model.seed
        self.preset = model.preset
        self.cell_size = model.cell_size_m
        self.on_event: EventHook | None = None
        self.on_transmit: TransmitHook | None = None
        self._now = 0.0
        self._heap: list[tuple[float, int, int, object, object]] = []
        self._seq = 0
        self._nodes: dict[int, _Node] = {}
        self._counters: dict[int, MoteCounters] = {}
        self._cores: dict[int, MoteCore] = {}
        self._grid: dict[tuple[int, int], list[_Node]] = {}
        self._moving: list[_Node] = []
        p = self.preset
        self._sens = p.sensitivity_dbm
        self._noise = p.noise_floor_dbm
        self._one_snr = model._one_snr_db
        self._sigma_f = p.fading_sigma_db
        self._overhead = p.phy_overhead_bytes
        self._byte_s = 8.0 / p.bitrate_bps
        self._backoff_max = p.mac_backoff_s
        self._mtu = p.mtu

    # ------------------------------------------------------------------ public API

    @property
    def now(self) -> float:
        return self._now

    @property
    def cores(self) -> dict[int, MoteCore]:
        """Every mote's current core by id (the driver's own dict: do not mutate)."""
        return self._cores

    @property
    def counters(self) -> dict[int, MoteCounters]:
        """Per-mote counters, up to date (folds the bulk-counted drops in first)."""
        self._flush_all()
        return self._counters

    def ids(self) -> list[int]:
        return list(self._nodes)

    def add(
        self,
        core: MoteCore,
        mobility: Mobility,
        tx_power_dbm: float | None = None,
        start_at: float | None = None,
        battery_mj: float | None = None,
    ) -> None:
        """Add a mote; it boots (``core.start``) at ``start_at`` (default: now).

        Re-adding the id of a dead mote switches it on again with the new core;
        its counters go on accumulating.
        """
        nid = core.node_id
        if not isinstance(nid, int) or not 0 <= nid <= MAX_NODE_ID:
            raise ValueError(f"node id {nid!r} outside 0..{MAX_NODE_ID}")
        old = self._nodes.get(nid)
        if old is not None and (old.alive or not old.started):
            raise ValueError(f"node {nid} is already in the network")
        txp = self.preset.tx_power_dbm if tx_power_dbm is None else float(tx_power_dbm)
        self.preset.check_tx_power(txp)
        t = self._now if start_at is None else float(start_at)
        if t < self._now:
            raise ValueError(f"start_at {t} is in the past (now {self._now})")
        counters = self._counters.setdefault(nid, MoteCounters())
        battery = None if battery_mj is None else Battery(battery_mj)
        node = _Node(core, counters, mobility, txp, self.model.max_range_m(txp), battery)
        node.backoff_h = self.model.backoff_link_hash(nid)
        self._nodes[nid] = node
        self._cores[nid] = core
        self._push(t, _START, node, None)

    def kill(self, node_id: int, reason: str = "killed") -> None:
        """Switch a mote off now (idempotent). Its pending frames are lost."""
        node = self._nodes[node_id]
        if not node.alive:
            node.started = True  # a mote killed before booting never boots
            return
        if node.pending:
            self._flush(node)
        node.lists_ok = False
        node.alive = False
        node.queue.clear()
        node.busy = False
        node.cur = None
        if node.static:
            self._grid_remove(node)
        else:
            self._moving.remove(node)
        self._touch(node.cell)
        if self.on_event is not None:
            self.on_event(node_id, MoteDown(reason), self._now)

    def alive(self, node_id: int) -> bool:
        n = self._nodes.get(node_id)
        return n is not None and n.alive

    def position(self, node_id: int) -> tuple[float, float]:
        return self._nodes[node_id].mobility.position(self._now)

    def set_mobility(self, node_id: int, mobility: Mobility) -> None:
        """Change how a mote moves from now on (a robot given a new path)."""
        node = self._nodes[node_id]
        was_in_grid = node.alive and node.static
        old_cell = node.cell
        if node.pending:
            self._flush(node)  # its bulk counts belong to its old lists
        node.lists_ok = False
        if was_in_grid:
            self._grid_remove(node)
        elif node.alive:
            self._moving.remove(node)
        node.mobility = mobility
        node.static = isinstance(mobility, Static)
        node.pos_t = -math.inf
        for n in self._nodes.values():  # cached unicast links may involve this mote
            n.links.clear()
        if node.alive:
            self._place(node)
            self._touch(old_cell)
            self._touch(node.cell)

    def energy_mj(self, node_id: int) -> float:
        n = self._nodes[node_id]
        return self.counters[node_id].energy_mj(self.preset, n.tx_power)

    def mean_rssi(self, src: int, dst: int) -> float:
        """Noise-free RSSI of the link now (ground truth for experiments)."""
        a, b = self._nodes[src], self._nodes[dst]
        ax, ay = a.mobility.position(self._now)
        bx, by = b.mobility.position(self._now)
        return self.model.mean_rssi(src, dst, math.hypot(ax - bx, ay - by), a.tx_power)

    def inject(self, src: int, frame: bytes, dest: int = BROADCAST) -> None:
        """Put raw bytes on the air from ``src`` as if its core had sent them."""
        node = self._nodes[src]
        if not node.alive:
            raise ValueError(f"node {src} is not on the air")
        tx = Transmission(frame, dest, 0)
        self._check_tx(node, tx)
        node.queue.append(tx)
        if not node.busy:
            self._start_next(node)

    def call(self, node_id: int, fn: Callable[[], T]) -> T:
        """Call into a mote's core from outside now (an application API, a
        gateway injecting a definition, a test), then collect what the core
        wants (frames, events, new deadline), as the asyncio runtime does."""
        node = self._nodes[node_id]
        out = fn()
        if node.started:
            self._after(node)
        return out

    def call_at(self, t: float, callback: Callable[[], None]) -> None:
        """Run ``callback()`` at virtual time ``t`` (scenario scripts)."""
        if t < self._now:
            raise ValueError(f"time {t} is in the past (now {self._now})")
        self._push(t, _CALL, None, callback)

    def run_for(self, dt: float) -> None:
        self.run_until(self._now + dt)

    def run_until(self, t: float) -> None:
        """Process every event up to and including virtual time ``t``."""
        heap = self._heap
        pop = heapq.heappop
        while heap and heap[0][0] <= t:
            when, _, kind, node, data = pop(heap)
            self._now = when
            if kind == _TX_END:
                self._tx_end(node)  # type: ignore[arg-type]
            elif kind == _TIMER:
                self._timer(node, data)  # type: ignore[arg-type]
            elif kind == _UC_DONE:
                self._uc_done(node, data)  # type: ignore[arg-type]
            elif kind == _START:
                self._start(node)  # type: ignore[arg-type]
            else:
                data()  # type: ignore[operator]
        if t > self._now:
            self._now = t

    # ------------------------------------------------------------------ scheduling

    def _push(self, t: float, kind: int, node: object, data: object) -> None:
        self._seq += 1
        heapq.heappush(self._heap, (t, self._seq, kind, node, data))

    def _after(self, node: _Node) -> None:
        """Collect what the core wants after any call into it."""
        core = node.core
        self._handle(node, core.drain(), core.events(), core.next_deadline())

    def _handle(
        self, node: _Node, txs: list[Transmission], evs: list[object], dl: float | None
    ) -> None:
        if txs:
            for tx in txs:
                self._check_tx(node, tx)
            node.queue.extend(txs)
            if not node.busy and node.alive:
                self._start_next(node)
        if evs:
            hook = self.on_event
            for e in evs:
                if type(e) is MalformedFrame:
                    node.counters.malformed += 1
                if hook is not None:
                    hook(node.id, e, self._now)
        if dl != node.armed:
            node.armed = dl
            node.timer_gen += 1
            if dl is not None and node.alive:
                self._push(dl if dl > self._now else self._now, _TIMER, node, node.timer_gen)

    def _check_tx(self, node: _Node, tx: Transmission) -> None:
        # A core that sends an oversize frame or to itself has a bug: raise.
        if len(tx.frame) > self._mtu:
            raise ValueError(f"node {node.id}: frame of {len(tx.frame)} bytes > MTU")
        d = tx.dest
        if d != BROADCAST and (not 0 <= d <= MAX_NODE_ID or d == node.id):
            raise ValueError(f"node {node.id}: bad destination {d}")

    def _start(self, node: _Node) -> None:
        if node.started:  # killed before it booted
            return
        node.started = True
        node.alive = True
        self._place(node)
        self._touch(node.cell)
        node.core.start(self._now)
        self._after(node)

    def _timer(self, node: _Node, gen: int) -> None:
        if not node.alive or gen != node.timer_gen:
            return  # stale entry
        now = self._now
        if node.fire_t == now:
            node.fire_count += 1
            if node.fire_count > _MAX_FIRINGS_AT_ONE_TIME:
                raise RuntimeError(f"node {node.id}: core keeps its deadline at {now}")
        else:
            node.fire_t, node.fire_count = now, 0
        node.armed = None
        node.core.handle_timer(now)
        self._after(node)

    def _start_next(self, node: _Node) -> None:
        if not node.queue:
            return
        tx = node.queue.popleft()
        seq = node.seq
        node.seq = (seq + 1) & 0xFFFF
        node.busy = True
        node.cur = tx
        node.cur_seq = seq
        node.cur_attempt = 0
        self._schedule_attempt(node, len(tx.frame), seq, 0)

    def _schedule_attempt(self, node: _Node, n: int, seq: int, attempt: int) -> None:
        h = packet_hash(node.backoff_h, (seq << 8) | (attempt << 1))  # packet_key(seq, attempt)
        t = (
            self._now
            + (h & 0xFFFFFFFF) * _U32 * self._backoff_max
            + (n + self._overhead) * self._byte_s
        )
        self._seq += 1
        heapq.heappush(self._heap, (t, self._seq, _TX_END, node, None))

    # ------------------------------------------------------------------ the medium

    def _tx_end(self, s: _Node) -> None:
        tx = s.cur
        if tx is None or not s.alive:
            return  # switched off while on the air
        seq = s.cur_seq
        frame = tx.frame
        n = len(frame)
        c = s.counters
        c.frames_tx += 1
        c.bytes_tx += n
        if self.on_transmit is not None:
            self.on_transmit(s.id, tx, self._now)
        if tx.dest == BROADCAST:
            s.busy = False
            s.cur = None
            self._broadcast(s, frame, n, seq << 8)  # packet_key(seq, 0)
            if s.battery is not None:
                self._check_battery(s)
            if s.queue and s.alive and not s.busy:
                self._start_next(s)
        else:
            self._unicast(s, tx, frame, n, seq, s.cur_attempt)
            self._check_battery(s)

    def _broadcast(self, s: _Node, frame: bytes, n: int, key: int) -> None:
        bits = 8 * (n + self._overhead)
        kg = (key * _GOLDEN) & _M64
        now = self._now
        if s.static:
            if not s.lists_ok:
                self._build_lists(s)
            s.pending += 1
            sens = self._sens
            noise = self._noise
            one = self._one_snr
            sf = self._sigma_f
            prr_bits = self.model.prr_bits
            normal = _NORMAL
            mask = _M64
            mul = _MUL
            shift = _SHIFT
            for r, rc, core, mean, lh in s.near:
                # Inlined RadioModel.decide(lh, mean, bits, key), the hot path.
                # packet_hash is z ^ (z >> 31): its top 12 bits (the normal
                # deviate) are z's, so the xorshift is only needed for the
                # uniform draw, inside the PRR's transitional band.
                z = ((lh ^ kg) * mul) & mask
                rssi = mean - sf * normal[z >> shift]
                if rssi < sens:
                    if r.alive:
                        rc.dropped_loss += 1
                    continue
                if rssi - noise < one:
                    z ^= z >> 31
                    if (z & 0xFFFFFFFF) * _U32 >= prr_bits(rssi, bits):
                        if r.alive:
                            rc.dropped_loss += 1
                        continue
                if not r.alive:
                    continue
                rc.frames_rx += 1
                rc.bytes_rx += n
                core.receive(frame, rssi, now)
                # Inlined _after(r): usually nothing to send, no event, same deadline.
                txs = core.drain()
                evs = core.events()
                dl = core.next_deadline()
                if txs or evs or dl != r.armed:
                    self._handle(r, txs, evs, dl)
                if r.battery is not None:
                    self._check_battery(r)
            if self._moving:
                for r in list(self._moving):
                    self._hear(s, s.x, s.y, s.cell, r, frame, n, bits, key)
        else:
            self._locate(s)
            for r in self._candidates(s):
                self._hear(s, s.x, s.y, s.cell, r, frame, n, bits, key)

    def _hear(
        self,
        s: _Node,
        sx: float,
        sy: float,
        scell: tuple[int, int],
        r: _Node,
        frame: bytes,
        n: int,
        bits: int,
        key: int,
    ) -> None:
        """One receiver of a broadcast, evaluated from scratch (moving motes)."""
        if r is s or not r.alive:
            return
        self._locate(r)
        if abs(r.cell[0] - scell[0]) > 1 or abs(r.cell[1] - scell[1]) > 1:
            return  # not subscribed to the sender's cell: hears nothing, counts nothing
        d = math.hypot(r.x - sx, r.y - sy)
        if d > s.range_m:
            r.counters.dropped_distance += 1
            return
        m = self.model
        ok, rssi = m.decide(
            m.fading_link_hash(s.id, r.id), m.mean_rssi(s.id, r.id, d, s.tx_power), bits, key
        )
        if not ok:
            r.counters.dropped_loss += 1
            return
        rc = r.counters
        rc.frames_rx += 1
        rc.bytes_rx += n
        r.core.receive(frame, rssi, self._now)
        self._after(r)
        self._check_battery(r)

    def _unicast(self, s: _Node, tx: Transmission, frame: bytes, n: int, seq: int, a: int) -> None:
        now = self._now
        p = self.preset
        m = self.model
        key = packet_key(seq, a)
        r = self._nodes.get(tx.dest)
        delivered = False
        rssi = 0.0
        link = None
        if r is not None and r.alive:
            link = self._link(s, r)
            if link is not None:
                _, d, mean, lh = link
                if d > s.range_m:
                    r.counters.dropped_distance += 1
                else:
                    ok, rssi = m.decide(lh, mean, 8 * (n + p.phy_overhead_bytes), key)
                    if ok:
                        delivered = True
                    else:
                        r.counters.dropped_loss += 1
        acked = False
        if delivered and r is not None and link is not None:
            rc = r.counters
            rc.frames_rx += 1
            rc.bytes_rx += n
            if r.last_useq.get(s.id) == seq:
                rc.duplicates += 1  # a retry of a frame already received: ACK, do not deliver
            else:
                r.last_useq[s.id] = seq
                r.core.receive(frame, rssi, now)
                self._after(r)
            if r.alive:
                # The hardware ACK, on the reverse link at the receiver's power.
                rc.acks_tx += 1
                d = link[1]
                if d <= r.range_m:
                    back = m.mean_rssi(r.id, s.id, d, r.tx_power)
                    acked, _ = m.decide(
                        m.fading_link_hash(r.id, s.id),
                        back,
                        8 * p.ack_bytes,
                        packet_key(seq, a, ack=True),
                    )
                self._check_battery(r)
        if acked:
            self._push(now + p.ack_turnaround_s + p.ack_airtime_s, _UC_DONE, s, True)
        else:
            self._push(now + p.ack_timeout_s, _UC_DONE, s, False)

    def _uc_done(self, s: _Node, acked: bool) -> None:
        tx = s.cur
        if tx is None or not s.alive:
            return
        seq = s.cur_seq
        attempt = s.cur_attempt
        c = s.counters
        if not acked and attempt < self.preset.max_retries:
            c.retries += 1
            s.cur_attempt = attempt + 1
            self._schedule_attempt(s, len(tx.frame), seq, attempt + 1)
            return
        if acked:
            c.acks_rx += 1
            c.unicast_ok += 1
        else:
            c.unicast_failed += 1
        s.busy = False
        s.cur = None
        s.core.link_result(tx, acked, self._now)
        self._after(s)
        if acked:
            self._check_battery(s)
        if s.alive and not s.busy:
            self._start_next(s)

    def _check_battery(self, node: _Node) -> None:
        b = node.battery
        if b is not None and node.alive and b.is_dead(node.counters, self.preset, node.tx_power):
            self.kill(node.id, "battery")

    # ------------------------------------------------------------------ geometry

    def _locate(self, node: _Node) -> None:
        """Refresh a moving mote's position and cell for the current time."""
        if node.static or node.pos_t == self._now:
            return
        node.x, node.y = node.mobility.position(self._now)
        node.cell = cell_of(node.x, node.y, self.cell_size)
        node.pos_t = self._now

    def _place(self, node: _Node) -> None:
        """Put a mote that came on the air (or changed mobility) in the grid or moving list."""
        node.x, node.y = node.mobility.position(self._now)
        node.cell = cell_of(node.x, node.y, self.cell_size)
        node.pos_t = self._now
        if node.static:
            self._grid.setdefault(node.cell, []).append(node)
        else:
            self._moving.append(node)

    def _grid_remove(self, node: _Node) -> None:
        self._grid[node.cell].remove(node)

    def _cells_around(self, cell: tuple[int, int]) -> Iterable[list[_Node]]:
        cx, cy = cell
        grid = self._grid
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                lst = grid.get((cx + dx, cy + dy))
                if lst:
                    yield lst

    def _candidates(self, s: _Node) -> list[_Node]:
        """Every mote that may hear a moving sender: static ones in its 3x3 cells
        and all moving ones (filtered by cell in _hear)."""
        out = [r for lst in self._cells_around(s.cell) for r in lst]
        out.extend(self._moving)
        return out

    def _touch(self, cell: tuple[int, int]) -> None:
        """The motes around ``cell`` changed: fold the bulk counts, rebuild lazily."""
        for lst in self._cells_around(cell):
            for s in lst:
                if s.pending:
                    self._flush(s)
                s.lists_ok = False
                s.links.clear()

    def _flush(self, s: _Node) -> None:
        k = s.pending
        for r in s.far_loss:
            r.counters.dropped_loss += k
        for r in s.far_dist:
            r.counters.dropped_distance += k
        s.pending = 0

    def _flush_all(self) -> None:
        for s in self._nodes.values():
            if s.pending:
                self._flush(s)

    def _build_lists(self, s: _Node) -> None:
        m = self.model
        near: list[tuple[_Node, MoteCounters, MoteCore, float, int]] = []
        far_loss: list[_Node] = []
        far_dist: list[_Node] = []
        for lst in self._cells_around(s.cell):
            for r in lst:
                if r is s:
                    continue
                d = math.hypot(r.x - s.x, r.y - s.y)
                if d > s.range_m:
                    far_dist.append(r)
                    continue
                mean = m.mean_rssi(s.id, r.id, d, s.tx_power)
                if m.never_delivers(mean):
                    far_loss.append(r)
                else:
                    near.append((r, r.counters, r.core, mean, m.fading_link_hash(s.id, r.id)))
        if s.pending:
            self._flush(s)
        s.near, s.far_loss, s.far_dist = near, far_loss, far_dist
        s.lists_ok = True

    def _link(self, s: _Node, r: _Node) -> tuple[_Node, float, float, int] | None:
        """(r, distance, mean RSSI, link hash) if ``r`` listens to ``s``'s cell, else None.
        Cached for pairs of static motes."""
        both_static = s.static and r.static
        if both_static:
            links = s.links
            if r.id in links:
                hit = links[r.id]
                if hit is None or hit[0] is r:
                    return hit
        self._locate(s)
        self._locate(r)
        out: tuple[_Node, float, float, int] | None = None
        if abs(r.cell[0] - s.cell[0]) <= 1 and abs(r.cell[1] - s.cell[1]) <= 1:
            d = math.hypot(r.x - s.x, r.y - s.y)
            m = self.model
            out = (r, d, m.mean_rssi(s.id, r.id, d, s.tx_power), m.fading_link_hash(s.id, r.id))
        if both_static:
            s.links[r.id] = out
        return out
