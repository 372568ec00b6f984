"""The virtual medium: MoteCores on an in-memory radio and a virtual clock, as
fast as possible (the Zenoh medium's twin: :mod:`awaremw.radio.zenoh_medium`).

A discrete-event simulator: a queue of ``(time, seq, kind, node, data)``
entries, processed in order; ``seq`` (insertion order) breaks ties, so a run is
a deterministic function of the seed, the motes added and the calls made. The
medium applies exactly the rules of the Zenoh medium (``docs/radio.md``,
"Medium semantics"): same cells, same distance cut, same
:class:`~awaremw.radio.model.RadioModel` decisions keyed by
``(seed, src, dst, packet key)``, same link-layer ACK and retries, same
counters.

Who hears whom (cells, cached receiver lists of static senders, bulk-counted
drops) is :mod:`awaremw.radio.neighbourhood`; every reception decision and its
accounting :mod:`awaremw.radio.reception`; the link layer's state and rules
(sequence numbers, duplicates, ACKs, retries) :mod:`awaremw.radio.linklayer`:
the same code the Zenoh medium runs. What is this driver's own is the event
queue (:mod:`awaremw.world.timerq`, a calendar of time slots), and what a
delivery does (the receiver's core takes the frame).

Channel access and collisions are :mod:`awaremw.radio.mac`'s, driven through
:mod:`awaremw.radio.linklayer` as the Zenoh medium drives them: each mote's
:class:`~awaremw.radio.mac.MacSender` says when to assess the channel and
when its attempt goes on the air; the
network's :class:`~awaremw.radio.mac.Air` holds the frames on the air, answers
the assessments, and at each frame's end says which receptions survived
(``VirtualNetwork(..., mac="csma"|"aloha", collisions="sinr"|"none")``).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from typing import TypeVar

from awaremw.protocol.core import IdleCheck, MoteCore, Transmission
from awaremw.protocol.events import CoreEvent, EventHook, MalformedFrame, MoteDown
from awaremw.protocol.frames import BROADCAST
from awaremw.radio import linklayer
from awaremw.radio.capture import RadioTap
from awaremw.radio.counters import Battery, MoteCounters
from awaremw.radio.faults import FaultLog
from awaremw.radio.linklayer import LinkStation
from awaremw.radio.mac import (
    COLLISION_MODES,
    GIVE_UP,
    SENSE,
    TRANSMIT,
    Air,
    MacSender,
    OnAir,
    mac_params,
)
from awaremw.radio.model import RadioModel
from awaremw.radio.neighbourhood import Neighbourhood
from awaremw.radio.reception import Reception
from awaremw.radio.security import FrameGuard, RadioSecurity
from awaremw.world.mobility import Mobility, Static
from awaremw.world.timerq import TimerQueue

log = logging.getLogger(__name__)

T = TypeVar("T")
TransmitHook = Callable[[int, Transmission, float], None]

_TIMER, _TX_END, _UC_DONE, _START, _CALL, _CCA = range(6)
_MAX_FIRINGS_AT_ONE_TIME = 100_000


class _Node(LinkStation):
    """Driver-side state of one mote incarnation: its radio, core and timer."""

    __slots__ = ("armed", "core", "fire_count", "fire_t", "idle", "started", "timer_gen")

    def __init__(
        self,
        core: MoteCore,
        counters: MoteCounters,
        mobility: Mobility,
        tx_power: float,
        range_m: float,
        battery: Battery | None,
    ) -> None:
        super().__init__(core.node_id, mobility, tx_power, range_m, counters, battery)
        self.core = core
        # The core's IdleCheck (protocol/core.py), if it has one: after a reception
        # that changed nothing, drain/events/next_deadline are not called.
        self.idle: Callable[[], bool] | None = core.idle if isinstance(core, IdleCheck) else None
        self.started = False
        self.timer_gen = 0
        self.armed: float | None = None
        self.fire_t = -1.0
        self.fire_count = 0


class VirtualNetwork:
    """Motes on a virtual clock, talking through the in-memory medium."""

    def __init__(
        self,
        model: RadioModel,
        seed: int | None = None,
        *,
        security: RadioSecurity | None = None,
        mac: str = "csma",
        collisions: str = "sinr",
    ) -> None:
        if seed is not None and seed != model.seed:
            raise ValueError(f"seed {seed} differs from the radio model's seed {model.seed}")
        if collisions not in COLLISION_MODES:
            raise ValueError(
                f"unknown collisions {collisions!r}; known: {', '.join(COLLISION_MODES)}"
            )
        self.model = model
        self.seed = model.seed
        self.preset = model.preset
        self.cell_size = model.cell_size_m
        self.on_event: EventHook | None = None
        self.on_transmit: TransmitHook | None = None
        self.tap: RadioTap | None = None  # a capture (awaremw.radio.capture)
        # Last guard around every core call: an exception out of a core is our
        # bug; it is counted here (and logged, rate-limited) instead of stopping
        # the whole run. ``strict`` re-raises it (tests that hunt bugs).
        self.faults = FaultLog("contained fault", log, logging.ERROR)
        self.strict = False
        self._now = 0.0
        self._queue = TimerQueue()  # (time, seq, kind, node, data) events
        self._nodes: dict[int, _Node] = {}
        self._counters: dict[int, MoteCounters] = {}
        self._cores: dict[int, MoteCore] = {}
        self._nb: Neighbourhood[_Node] = Neighbourhood(model)
        p = self.preset
        # Medium access and collisions (radio/mac.py): the MAC of every mote, and
        # the frames on the air when anything needs them (carrier sense, SINR).
        self.mac_params = mac_params(p, mac)
        self.collisions = collisions
        self._sense = self.mac_params.kind == "csma"
        self._collide = collisions == "sinr"
        self._track = self._sense or self._collide
        self._air = Air(model, p.capture_threshold_db, p.airtime_s(p.mtu) + 1e-3)
        # Link-layer security (awaremw.radio.security): frames sealed on the air,
        # opened and checked for replays off it; the cores get mtu - overhead bytes.
        self.guard: FrameGuard | None = None if security is None else FrameGuard(security)
        self._mtu = p.mtu if security is None else security.payload_mtu(p.mtu)
        # Every reception decision and its accounting (radio/reception.py).
        self._rx: Reception[_Node] = Reception(
            model, self._nb, self._air, self.guard, self._deliver, self._battery_down
        )

    # ------------------------------------------------------------------ public API

    @property
    def now(self) -> float:
        return self._now

    @property
    def payload_mtu(self) -> int:
        """The largest frame a core may send (the preset's MTU less the security overhead)."""
        return self._mtu

    @property
    def cores(self) -> dict[int, MoteCore]:
        """Every mote's current core by id (the driver's own dict: do not mutate)."""
        return self._cores

    @property
    def counters(self) -> dict[int, MoteCounters]:
        """Per-mote counters, up to date (folds the bulk-counted drops in first)."""
        self._nb.flush_all()
        return self._counters

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
        nid = linklayer.check_node_id(core.node_id)
        old = self._nodes.get(nid)
        if old is not None and (old.alive or not old.started):
            raise ValueError(f"node {nid} is already in the network")
        txp = linklayer.tx_power_of(self.preset, tx_power_dbm)
        t = self._now if start_at is None else float(start_at)
        if t < self._now:
            raise ValueError(f"start_at {t} is in the past (now {self._now})")
        counters = self._counters.setdefault(nid, MoteCounters())
        battery = None if battery_mj is None else Battery(battery_mj)
        node = _Node(core, counters, mobility, txp, self.model.max_range_m(txp), battery)
        node.mac = MacSender(self.mac_params, self.model.backoff_link_hash(nid))
        self._nodes[nid] = node
        self._cores[nid] = core
        self._push(t, _START, node, None)

    def kill(self, node_id: int, reason: str = "killed") -> None:
        """Switch a mote off now (idempotent). Its pending frames are lost."""
        node = self._nodes[node_id]
        if not node.alive:
            node.started = True  # a mote killed before booting never boots
            return
        linklayer.silence(node)
        if self._track:
            self._air.cut(node_id, self._now)
            node.onair = None
        self._nb.remove(node)
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
        if node.alive:
            self._nb.remove(node)  # drops the cached lists and links it is part of
        node.mobility = mobility
        node.static = isinstance(mobility, Static)
        node.pos_t = -math.inf
        if node.alive:
            self._nb.add(node, self._now)

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
        linklayer.check_transmission(node, tx, self._mtu)
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

    def run_until(self, t: float) -> None:
        """Process every event up to and including virtual time ``t``."""
        pop = self._queue.pop_until
        while (e := pop(t)) is not None:
            when, _, kind, node, data = e
            self._now = when
            if kind == _TIMER:  # the most frequent first
                self._timer(node, data)  # type: ignore[arg-type]
            elif kind == _TX_END:
                self._tx_end(node)  # type: ignore[arg-type]
            elif kind == _UC_DONE:
                self._uc_done(node, data)  # type: ignore[arg-type]
            elif kind == _CCA:
                self._cca(node)  # type: ignore[arg-type]
            elif kind == _START:
                self._start(node)  # type: ignore[arg-type]
            else:
                data()  # type: ignore[operator]
        if t > self._now:
            self._now = t

    # ------------------------------------------------------------------ scheduling

    def _push(self, t: float, kind: int, node: object, data: object) -> None:
        self._queue.push(t, kind, node, data)

    def _contain(self, node: _Node, where: str, e: Exception) -> None:
        """A core raised: count it (rate-limited log); re-raise in strict mode."""
        self.faults.count(f"{where}: {type(e).__name__}", f"node {node.node_id}: {e}", e)
        if self.strict:
            raise e

    def _after(self, node: _Node) -> None:
        """Collect what the core wants after any call into it."""
        core = node.core
        self._handle(node, core.drain(), core.events(), core.next_deadline())

    def _handle(
        self, node: _Node, txs: list[Transmission], evs: list[CoreEvent], dl: float | None
    ) -> None:
        if txs:
            for tx in txs:
                linklayer.check_transmission(node, tx, self._mtu)
            node.queue.extend(txs)
            if not node.busy and node.alive:
                self._start_next(node)
        if evs:
            hook = self.on_event
            for e in evs:
                if type(e) is MalformedFrame:
                    node.counters.malformed += 1
                if hook is not None:
                    hook(node.node_id, e, self._now)
        if dl != node.armed:
            node.armed = dl
            node.timer_gen += 1
            if dl is not None and node.alive:
                self._push(dl if dl > self._now else self._now, _TIMER, node, node.timer_gen)

    def _start(self, node: _Node) -> None:
        if node.started:  # killed before it booted
            return
        node.started = True
        node.alive = True
        self._nb.add(node, self._now)
        node.core.start(self._now)
        self._after(node)

    def _timer(self, node: _Node, gen: int) -> None:
        if not node.alive or gen != node.timer_gen:
            return  # stale entry
        now = self._now
        if node.fire_t == now:
            node.fire_count += 1
            if node.fire_count > _MAX_FIRINGS_AT_ONE_TIME:
                raise RuntimeError(f"node {node.node_id}: core keeps its deadline at {now}")
        else:
            node.fire_t, node.fire_count = now, 0
        node.armed = None
        core = node.core
        try:
            core.handle_timer(now)
        except Exception as e:
            self._contain(node, "handle_timer", e)
        # Inlined _after(node): with nothing sent and no event, only re-arm.
        idle = node.idle
        txs: list[Transmission] | None
        evs: list[CoreEvent] | None
        if idle is None:
            txs = core.drain()
            evs = core.events()
            dl = core.next_deadline()
        else:
            # An IdleCheck core: its deadline first; idle then means nothing was
            # queued and no event emitted (drain and events would return []).
            dl = core.next_deadline()
            if idle():
                txs = evs = None
            else:
                txs = core.drain()
                evs = core.events()
        if txs or evs:
            self._handle(node, txs or [], evs or [], dl)
        elif dl is not None:  # armed is None: the deadline changed
            node.armed = dl
            node.timer_gen += 1
            if node.alive:
                self._queue.push(dl if dl > now else now, _TIMER, node, node.timer_gen)

    def _start_next(self, node: _Node) -> None:
        if not node.queue:
            return
        linklayer.begin_next(node, self.guard)
        self._schedule_attempt(node, len(node.air), node.cur_seq, 0)

    def _schedule_attempt(self, node: _Node, n: int, seq: int, attempt: int) -> None:
        """The MAC (radio/mac.py via linklayer.attempt) takes the attempt: its first
        assessment, or ALOHA's start."""
        t = linklayer.attempt(node, self._now)
        if self._sense:
            self._push(t, _CCA, node, None)
        else:
            self._go(node, t)

    def _go(self, node: _Node, start: float) -> None:
        """The attempt goes on the air at ``start`` (known to the Air from now on)."""
        air = None
        mw = None
        if self._track:
            air = self._air
            air.prune(self._now)
            if node.static:  # its frames share its mean powers at static receivers
                mw = self._nb.sender(node.node_id, node.x, node.y, node.tx_power).mw
            else:
                self._nb.locate(node, self._now)
        end = linklayer.put_on_air(node, air, self.preset, start, mw)
        self._queue.push(end, _TX_END, node, None)

    def _cca(self, node: _Node) -> None:
        """A clear channel assessment of ``node`` ends now: transmit, back off or give up."""
        if node.cur is None or not node.alive:
            return  # switched off while backing off
        now = self._now
        if not node.static:
            self._nb.locate(node, now)
        action, t = linklayer.assess(node, self._air, self.mac_params, now)
        if action == TRANSMIT:
            self._go(node, t)
        elif action == SENSE:
            self._push(t, _CCA, node, None)
        else:
            assert action == GIVE_UP
            tx = linklayer.give_up(node)
            if tx is not None and tx.dest != BROADCAST:
                try:
                    node.core.link_result(tx, False, now)
                except Exception as e:
                    self._contain(node, "link_result", e)
                self._after(node)
            if node.alive and not node.busy:
                self._start_next(node)

    # ------------------------------------------------------------------ the medium

    def _tx_end(self, s: _Node) -> None:
        tx = s.cur
        if tx is None or not s.alive:
            return  # switched off while on the air
        seq = s.cur_seq
        frame = s.air
        n = len(frame)
        c = s.counters
        f = s.onair
        s.onair = None
        others = self._air.overlapping(f) if self._collide and f is not None else None
        c.frames_tx += 1
        c.bytes_tx += n
        if self.on_transmit is not None:
            self.on_transmit(s.node_id, tx, self._now)
        if self.tap is not None:
            self.tap.on_air(self._now, s.node_id, tx.dest, seq, s.cur_attempt, frame)
        if tx.dest == BROADCAST:
            s.busy = False
            s.cur = None
            if not s.static:
                self._nb.locate(s, self._now)
            self._rx.broadcast(s.node_id, s.x, s.y, s.tx_power, s.static, frame, seq, f,
                               others or None, self._now, self.tap)  # fmt: skip
            if s.battery is not None:
                self._check_battery(s)
            if s.queue and s.alive and not s.busy:
                self._start_next(s)
        else:
            self._unicast(s, tx, frame, seq, s.cur_attempt, f, others or None)
            self._check_battery(s)

    def _deliver(self, r: _Node, src: int, data: bytes, rssi: float, now: float) -> None:
        """A frame ``r`` took (radio/reception.py) goes to its core."""
        core = r.core
        try:
            core.receive(data, rssi, now)
        except Exception as e:
            self._contain(r, "receive", e)
        # _after(r), inlined: usually nothing to send, no event, the same deadline
        # (an IdleCheck core says so without the three calls).
        idle = r.idle
        if idle is None or not idle():
            txs = core.drain()
            evs = core.events()
            dl = core.next_deadline()
            if txs or evs or dl != r.armed:
                self._handle(r, txs, evs, dl)

    def _battery_down(self, r: _Node, now: float) -> None:
        self.kill(r.node_id, "battery")

    def _unicast(
        self,
        s: _Node,
        tx: Transmission,
        frame: bytes,
        seq: int,
        a: int,
        f: OnAir | None,
        others: list[OnAir] | None,
    ) -> None:
        now = self._now
        r = self._nodes.get(tx.dest)
        acked = False
        if r is not None and r.alive:
            link = self._nb.link(s, r, now)  # None: r does not listen to s's cell
            if link is not None and self._rx.unicast(
                s.node_id, link, s.range_m, frame, seq, a, f, others, now, self.tap
            ):
                # The hardware ACK, on the reverse link at the receiver's power.
                acked = linklayer.ack_heard(
                    self.model, r.node_id, r.tx_power, s.node_id, link[1], seq, a, now
                )
                self._check_battery(r)
        self._push(linklayer.outcome_time(self.preset, now, acked), _UC_DONE, s, acked)

    def _uc_done(self, s: _Node, acked: bool) -> None:
        tx = s.cur
        if tx is None or not s.alive:
            return
        if linklayer.settle(s, acked, self.preset.max_retries):
            self._schedule_attempt(s, len(s.air), s.cur_seq, s.cur_attempt)
            return
        try:
            s.core.link_result(tx, acked, self._now)
        except Exception as e:
            self._contain(s, "link_result", e)
        self._after(s)
        if acked:
            self._check_battery(s)
        if s.alive and not s.busy:
            self._start_next(s)

    def _check_battery(self, node: _Node) -> None:
        if linklayer.battery_spent(node, self.preset):
            self.kill(node.node_id, "battery")
