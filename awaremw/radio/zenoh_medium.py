"""The Zenoh medium: an emulated radio channel carried over Zenoh pub/sub.

One :class:`ZenohMedium` per process. It owns the process's radio
subscriptions and a :class:`Radio` per local mote (its link layer: transmit
queue, MAC backoff, airtime, sequence numbers, ACK wait and retries, duplicate
filter, counters, battery). The rules are those of the virtual-clock driver
(``docs/radio.md``, "Medium semantics"; :mod:`awaremw.radio.virtual_medium`), and
the code that applies them is shared with it: who hears whom, cached receiver
lists and bulk-counted drops in :mod:`awaremw.radio.neighbourhood`, every
reception decision and its accounting in :mod:`awaremw.radio.reception`, the
link layer's state and rules in :mod:`awaremw.radio.linklayer`. So a run over
Zenoh and a virtual run of the same deployment count the same things the same
way.

What is left here is the Zenoh side, described in ``docs/runtime.md``, "The
medium": key expressions per grid cell and subscriptions per grid column,
local frames served without Zenoh, the two sample handlers (``"channel"``,
the default, and ``"callback"``), the ACK envelopes between processes and
their wall-time floor; and ``docs/radio.md``, "Across processes and hosts":
envelopes published at a frame's start, receptions decided ``guard_s`` of
wall time after its end, late envelopes decided at once
(``MediumStats.late``). Nothing touches asyncio from a Zenoh thread except
``call_soon_threadsafe``.
"""

from __future__ import annotations

import asyncio
import contextlib
import heapq
import logging
import math
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass
from typing import Any, Literal, Protocol

import zenoh

from awaremw.protocol.core import Transmission
from awaremw.protocol.frames import BROADCAST
from awaremw.radio import linklayer
from awaremw.radio.capture import RadioTap
from awaremw.radio.counters import Battery, MoteCounters
from awaremw.radio.envelope import (
    Envelope,
    EnvelopeLimits,
    Kind,
    MalformedEnvelope,
    decode_envelope,
    encode_envelope,
)
from awaremw.radio.environment import environment_of
from awaremw.radio.faults import FaultLog
from awaremw.radio.linklayer import LinkStation
from awaremw.radio.mac import (
    COLLISION_MODES,
    GIVE_UP,
    MAC_KINDS,
    MAX_ON_AIR,
    SENSE,
    TRANSMIT,
    Air,
    MacSender,
    OnAir,
    mac_params,
)
from awaremw.radio.model import RadioModel, cell_of, packet_key
from awaremw.radio.neighbourhood import Cell, Neighbourhood
from awaremw.radio.reception import Reception
from awaremw.radio.security import FrameGuard, RadioSecurity
from awaremw.world.clock import EmulatedClock
from awaremw.world.mobility import Mobility

log = logging.getLogger(__name__)

Handler = Literal["callback", "channel"]
# Measured with `awaremw bench scale --processes 2 --layout interleaved` (docs/runtime.md):
# the polled channel costs ~20 % less CPU than a callback that takes the GIL on
# Zenoh's thread for every sample, and gives a lower timer-lag p99.
DEFAULT_HANDLER: Handler = "channel"

DEFAULT_PREFIX = "aware"
DEFAULT_ACK_WAIT_FLOOR_S = 0.05  # wall seconds; see the module docstring
# Wall seconds after a frame's end before its receptions are decided, so that the
# envelopes of every frame that overlapped it have arrived (Zenoh latency, the
# channel poll, loop lag): docs/radio.md, "Medium access and collisions".
DEFAULT_GUARD_S = 0.01
# Frames stay in the Air this long (wall) beyond the longest airtime plus the
# guard: a decision that runs late by less than this still sees every interferer.
AIR_SLACK_S = 0.02
# An envelope whose frame starts more than this (wall) ahead of our clock is refused
# (``early``): nothing legitimate starts that far ahead (ALOHA's backoff, turnaround
# and clock skew are milliseconds), and it would pin the Air.
EARLY_LIMIT_S = 1.0
CHANNEL_POLL_MIN_S = 0.001  # wall seconds between polls in "channel" mode: after traffic,
CHANNEL_POLL_MAX_S = 0.004  # backing off to this while nothing arrives (at speed >= 1)
CHANNEL_CAPACITY = 1 << 16


class RadioSink(Protocol):
    """What a medium delivers to: the driver of one mote (``MoteRunner``)."""

    node_id: int

    def radio_receive(self, frame: bytes, rssi_dbm: float, now: float) -> None: ...

    def radio_link_result(self, tx: Transmission, acked: bool, now: float) -> None: ...

    def radio_down(self, reason: str, now: float) -> None: ...


@dataclass(slots=True)
class MediumStats:
    """Per-process figures (not per mote)."""

    envelopes_rx: int = 0  # envelopes taken from Zenoh
    malformed_envelopes: int = 0  # garbage on a radio key
    batches: int = 0  # loop wake-ups that drained the inbox
    max_batch: int = 0
    frames_published: int = 0
    acks_published: int = 0
    ignored: int = 0  # valid envelopes no local mote could hear (other cells / dest)
    subscriptions: int = 0
    late: int = 0  # frames whose envelope came after end + guard: decided at once
    early: int = 0  # envelopes refused: the frame starts too far ahead (EARLY_LIMIT_S)

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


class _OnAirFrame:
    """A frame (its envelope) whose local receptions are decided at ``end`` + guard."""

    __slots__ = ("cancelled", "end", "env", "f", "remote", "sender")

    def __init__(self, env: Envelope, end: float, f: OnAir | None, sender: Radio | None) -> None:
        self.env = env
        self.end = end
        self.f = f  # on the Air (None: carrier sense and collisions off)
        self.sender = sender  # the local sender of a unicast to a local mote, else None
        self.cancelled = False  # its local sender was switched off before its end
        self.remote = False  # from an envelope (another process's sender)


@dataclass(frozen=True, slots=True)
class MacSettings:
    """Channel access and collisions of a Zenoh medium (``docs/radio.md``, "Medium
    access and collisions"): ``mac`` ("csma" or "aloha"), ``collisions`` ("sinr"
    or "none"), and ``guard_s``, the wall seconds after a frame's end before its
    receptions are decided."""

    mac: str = "csma"
    collisions: str = "sinr"
    guard_s: float = DEFAULT_GUARD_S

    def __post_init__(self) -> None:
        if self.mac not in MAC_KINDS:
            raise ValueError(f"unknown mac {self.mac!r}; known: {', '.join(MAC_KINDS)}")
        if self.collisions not in COLLISION_MODES:
            raise ValueError(
                f"unknown collisions {self.collisions!r}; known: {', '.join(COLLISION_MODES)}"
            )
        if not 0.0 <= self.guard_s < 1.0:
            raise ValueError(f"guard_s {self.guard_s} outside [0, 1) s")


class Radio(LinkStation):
    """The link layer of one local mote. Created by :meth:`ZenohMedium.attach`."""

    __slots__ = ("handle", "medium", "on_air", "pub", "pub_cell", "sink")

    def __init__(
        self,
        medium: ZenohMedium,
        sink: RadioSink,
        mobility: Mobility,
        tx_power: float,
        range_m: float,
        battery: Battery | None,
        counters: MoteCounters,
    ) -> None:
        super().__init__(sink.node_id, mobility, tx_power, range_m, counters, battery)
        self.medium = medium
        self.sink = sink
        self.alive = True
        self.handle: asyncio.TimerHandle | None = None  # CCA, tx end or ACK wait
        self.on_air: _OnAirFrame | None = None  # the attempt on the air, until its end
        self.pub: zenoh.Publisher | None = None
        self.pub_cell: Cell | None = None

    def send(self, txs: Iterable[Transmission], now: float | None = None) -> None:
        """Queue frames the core drained; they go on the air one after another.
        ``now``: the emulated time they were handed over (default the clock's now;
        scripted tests pass exact times so that the MAC's times are exact too)."""
        if not self.alive:
            return
        m = self.medium
        mtu = m.payload_mtu
        for tx in txs:
            linklayer.check_transmission(self, tx, mtu)
            self.queue.append(tx)
        if not self.busy and self.queue:
            m._start_next(self, m.clock.now() if now is None else now)

    def position(self) -> tuple[float, float]:
        """Where the mote is now (refreshes a moving mote's cell)."""
        self.medium._nb.locate(self, self.medium.clock.now())
        return self.x, self.y

    def energy_mj(self) -> float:
        return self.counters.energy_mj(self.medium.model.preset, self.tx_power)


class ZenohMedium:
    """The radio medium of one process. Create, :meth:`open` inside the loop, attach radios.

    The session is the caller's (one per process); the medium only declares
    subscribers and publishers on it and undeclares them in :meth:`close`.
    """

    def __init__(
        self,
        session: zenoh.Session,
        model: RadioModel,
        clock: EmulatedClock,
        *,
        prefix: str = DEFAULT_PREFIX,
        handler: Handler = DEFAULT_HANDLER,
        ack_wait_floor_s: float = DEFAULT_ACK_WAIT_FLOOR_S,
        security: RadioSecurity | None = None,
        access: MacSettings | None = None,
    ) -> None:
        if "*" in prefix or prefix.endswith("/") or not prefix:
            raise ValueError(f"bad key prefix {prefix!r}")
        access = access or MacSettings()
        mac, collisions, guard_s = access.mac, access.collisions, access.guard_s
        if not guard_s < ack_wait_floor_s:
            raise ValueError(
                f"need guard_s ({guard_s}) < ack_wait_floor_s ({ack_wait_floor_s}): "
                "a remote ACK comes after the guard"
            )
        self.session = session
        self.model = model
        self.preset = model.preset
        self.clock = clock
        self.prefix = prefix
        self.handler: Handler = handler
        self.ack_wait_floor_s = ack_wait_floor_s
        self.guard_s = guard_s
        self.cell_size = model.cell_size_m
        # Medium access and collisions (radio/mac.py, driven through
        # radio/linklayer.py as the virtual medium drives them): each radio's
        # MacSender, and the frames on the air -- local ones and those of the
        # envelopes heard -- for carrier sense and the SINR decision, taken
        # ``guard_s`` (wall) after each frame's end.
        self.mac_params = mac_params(model.preset, mac)
        self.collisions = collisions
        self._sense = self.mac_params.kind == "csma"
        self._collide = collisions == "sinr"
        self._track = self._sense or self._collide
        self._decide_after = guard_s if self._collide else 0.0  # wall
        horizon = model.preset.airtime_s(model.preset.mtu) + clock.emulated_seconds(
            guard_s + AIR_SLACK_S
        )
        self._air = Air(model, model.preset.capture_threshold_db, horizon)
        # Frames awaiting their decision: (loop time due, order, frame); bound MAX_ON_AIR.
        self._decisions: list[tuple[float, int, _OnAirFrame]] = []
        self._decision_seq = 0
        self._decision_timer: asyncio.TimerHandle | None = None
        self._decision_at = 0.0
        self.stats = MediumStats()
        self.radios: dict[int, Radio] = {}
        self._counters: dict[int, MoteCounters] = {}
        # Local motes on the air, by cell; receiver caches of every sender heard.
        self._nb: Neighbourhood[Radio] = Neighbourhood(model, on_cell=self._ensure_columns)
        self._columns: set[int] = set()
        # With a links file (radio/links.py) positions say nothing of who hears
        # whom: a process subscribes to the keys of the senders its motes have a
        # link from, so a frame still goes only towards the motes that can hear it.
        env = environment_of(model)
        self._links = None if env is None else env.links
        self._link_senders: set[int] = set()
        self._subs: list[zenoh.Subscriber[Any]] = []
        self._chans: list[zenoh.Subscriber[zenoh.handlers.Handler[zenoh.Sample]]] = []
        self._inbox: deque[tuple[bytes, str]] = deque()  # bound: CHANNEL_CAPACITY
        self._wakeup = False
        self._loop: asyncio.AbstractEventLoop | None = None
        self._poll: asyncio.TimerHandle | None = None
        self._poll_min_s, self._poll_max_s = poll_bounds(
            clock.speed, model.preset.airtime_s(0), guard_s
        )
        self._poll_s = self._poll_min_s
        self._closed = False
        self._frozen = False
        self._mobility_handle: asyncio.TimerHandle | None = None
        p = self.preset
        self._overhead = p.phy_overhead_bytes
        self.on_malformed: Callable[[str, str], None] | None = None  # (key, reason)
        self.limits = EnvelopeLimits.of(self.preset)
        # Link-layer security (awaremw.radio.security): every frame sealed with
        # the network key and a frame counter; refusals counted per reason in
        # ``self.guard.refused`` and per mote in ``counters.refused``.
        self.guard: FrameGuard | None = None if security is None else FrameGuard(security)
        self.payload_mtu = p.mtu if security is None else security.payload_mtu(p.mtu)
        # Every reception decision and its accounting (radio/reception.py).
        self._rx: Reception[Radio] = Reception(
            model, self._nb, self._air, self.guard, self._deliver, self._battery_down
        )
        # Rejected envelopes by reason, and faults contained by the last guards
        # (an exception out of a Zenoh callback or a mote handler): counted,
        # logged at most once per reason every 10 s (awaremw.radio.faults).
        self.rejected = FaultLog("rejected envelope", log, logging.INFO)
        self.faults = FaultLog("contained fault", log, logging.ERROR)
        # Optional per-link delivery counts {(src, dst): frames}, for tests and
        # experiments (who heard whom); None = not tracked (the default). Bound:
        # senders (< 32768 ids) x local motes; only tests turn it on.
        self.links: dict[tuple[int, int], int] | None = None
        # A capture (awaremw.radio.capture): frames on the air here, local receptions.
        self.tap: RadioTap | None = None
        # Told how far ahead (emulated s) each frame refused as early starts: a
        # process started under running peers learns their time origin from it.
        self.on_early: Callable[[float], None] | None = None

    # ------------------------------------------------------------------ lifecycle

    def open(self) -> None:
        """Bind to the running loop (call from inside it)."""
        self._loop = asyncio.get_running_loop()

    @property
    def loop(self) -> asyncio.AbstractEventLoop:
        if self._loop is None:
            raise RuntimeError("ZenohMedium.open() was not called from the event loop")
        return self._loop

    def close(self) -> None:
        """Undeclare subscriptions and publishers; radios go silent."""
        if self._closed:
            return
        self._closed = True
        for r in list(self.radios.values()):
            self._silence(r)
        for sub in (*self._subs, *self._chans):
            with contextlib.suppress(zenoh.ZError):  # session already closed
                sub.undeclare()  # type: ignore[no-untyped-call]
        self._subs.clear()
        self._chans.clear()
        if self._poll is not None:
            self._poll.cancel()
        if self._mobility_handle is not None:
            self._mobility_handle.cancel()
        if self._decision_timer is not None:
            self._decision_timer.cancel()
            self._decision_timer = None
        self._decisions.clear()
        self._inbox.clear()

    def freeze(self) -> None:
        """Stop putting new frames on the air (benchmarks: let in-flight frames land)."""
        self._frozen = True

    # ------------------------------------------------------------------ motes

    def attach(
        self,
        sink: RadioSink,
        mobility: Mobility,
        *,
        tx_power_dbm: float | None = None,
        battery_mj: float | None = None,
    ) -> Radio:
        """Put a mote on the air. Re-attaching a dead mote's id keeps its counters."""
        nid = linklayer.check_node_id(sink.node_id)
        if nid in self.radios:
            raise ValueError(f"node {nid} is already on this medium")
        txp = linklayer.tx_power_of(self.preset, tx_power_dbm)
        counters = self._counters.setdefault(nid, MoteCounters())
        battery = None if battery_mj is None else Battery(battery_mj)
        r = Radio(self, sink, mobility, txp, self.model.max_range_m(txp), battery, counters)
        r.mac = MacSender(self.mac_params, self.model.backoff_link_hash(nid))
        self.radios[nid] = r
        self._nb.add(r, self.clock.now())
        if not r.static:
            self._ensure_mobility_tick()
        if self._links is None:
            self._ensure_columns(r.cell)
        else:
            for s in sorted(self._links.senders_to(nid) - self._link_senders):
                if not self._closed:
                    self._link_senders.add(s)
                    self._subscribe(f"{self.prefix}/radio/*/*/{s}")
        self._ensure_publisher(r)  # declared now rather than at the first frame (slow-ish)
        return r

    def detach(self, node_id: int) -> None:
        """Take a mote off the air (killed). Its counters stay readable."""
        r = self.radios.pop(node_id, None)
        if r is None:
            return
        self._silence(r)
        self._nb.remove(r)

    def prime(self, senders: Iterable[tuple[int, float, float, float]]) -> int:
        """Precompute receiver lists for static senders ``(id, x, y, tx_power)``
        (local ones and known remote ones), so the first frames do not pay for
        them. Returns how many lists were built."""
        n = 0
        nb = self._nb
        for src, x, y, txp in senders:
            if not nb.cached(src, x, y, txp) and nb.any_static_around(
                cell_of(x, y, self.cell_size)
            ):
                nb.sender(src, x, y, txp)
                n += 1
        return n

    @property
    def counters(self) -> dict[int, MoteCounters]:
        """Per-mote counters (every mote ever attached here), bulk drops folded in."""
        self._nb.flush_all()
        return self._counters

    @property
    def pending_decisions(self) -> int:
        """Frames on the air here whose receptions are still to be decided (their
        end + the guard not reached yet): 0 once every frame heard is decided."""
        return len(self._decisions)

    def positions(self) -> dict[int, tuple[float, float]]:
        return {nid: r.position() for nid, r in self.radios.items()}

    def key_for(self, cell: Cell, src: int) -> str:
        return f"{self.prefix}/radio/{cell[0]}/{cell[1]}/{src}"

    @property
    def columns(self) -> frozenset[int]:
        """Grid columns this process subscribes to."""
        return frozenset(self._columns)

    @property
    def link_senders(self) -> frozenset[int]:
        """With a links file: the senders this process subscribes to."""
        return frozenset(self._link_senders)

    # ------------------------------------------------------------------ subscriptions

    def _ensure_columns(self, cell: Cell) -> None:
        if self._links is not None:
            return  # subscribed by sender (attach)
        for cx in (cell[0] - 1, cell[0], cell[0] + 1):
            if cx not in self._columns and not self._closed:
                self._columns.add(cx)
                self._subscribe(f"{self.prefix}/radio/{cx}/*/*")

    def _subscribe(self, key: str) -> None:
        if self.handler == "callback":
            # indirect=False: run on Zenoh's own thread (no extra Python thread per
            # subscriber); the callback only copies bytes and maybe wakes the loop.
            self._subs.append(
                self.session.declare_subscriber(
                    key,
                    zenoh.handlers.Callback(self._on_sample, indirect=False),
                    allowed_origin=zenoh.Locality.REMOTE,
                )
            )
        else:
            self._chans.append(
                self.session.declare_subscriber(
                    key,
                    zenoh.handlers.FifoChannel(CHANNEL_CAPACITY),
                    allowed_origin=zenoh.Locality.REMOTE,
                )
            )
            if self._poll is None:
                self._poll = self.loop.call_later(self._poll_min_s, self._poll_channels)
        self.stats.subscriptions += 1

    def _on_sample(self, sample: zenoh.Sample) -> None:
        # Zenoh thread: copy the data out, wake the loop once per batch. Never
        # touch asyncio objects here except through call_soon_threadsafe.
        try:
            self._on_sample_unguarded(sample)
        except Exception as e:  # last guard: never raise into Zenoh's thread
            self.faults.count(f"zenoh callback: {type(e).__name__}", str(e), e)

    def _on_sample_unguarded(self, sample: zenoh.Sample) -> None:
        if len(self._inbox) >= CHANNEL_CAPACITY:
            self.rejected.count("inbox full", "the loop is not keeping up")
            return  # bound: CHANNEL_CAPACITY envelopes waiting
        self._inbox.append((sample.payload.to_bytes(), str(sample.key_expr)))
        if not self._wakeup:
            self._wakeup = True
            loop = self._loop
            if loop is None:
                return
            with contextlib.suppress(RuntimeError):  # loop closed while Zenoh still delivers
                loop.call_soon_threadsafe(self._drain_inbox)

    def _drain_inbox(self) -> None:
        self._wakeup = False  # before popping: a sample appended later schedules again
        inbox = self._inbox
        n = 0
        while inbox:
            data, key = inbox.popleft()
            n += 1
            self._receive_guarded(data, key)
        st = self.stats
        st.batches += 1
        if n > st.max_batch:
            st.max_batch = n

    def _poll_channels(self) -> None:
        self._poll = None
        if self._closed:
            return
        n = 0
        for sub in self._chans:
            while True:
                try:
                    s = sub.try_recv()
                except zenoh.ZError as e:  # channel closed under us
                    self.faults.count("zenoh channel", str(e))
                    break
                if s is None:
                    break
                n += 1
                self._receive_guarded(s.payload.to_bytes(), str(s.key_expr))
        if n:
            st = self.stats
            st.batches += 1
            st.max_batch = max(st.max_batch, n)
            self._poll_s = self._poll_min_s
        else:
            self._poll_s = min(self._poll_s * 2.0, self._poll_max_s)
        self._poll = self.loop.call_later(self._poll_s, self._poll_channels)

    # ------------------------------------------------------------------ receive side

    def _receive_guarded(self, data: bytes, key: str) -> None:
        """The last guard around one envelope: a bug becomes a counted fault."""
        try:
            self._receive_envelope(data, key)
        except Exception as e:
            self.faults.count(f"receive: {type(e).__name__}", f"on {key[:80]}: {e}", e)

    def _receive_envelope(self, data: bytes, key: str) -> None:
        if self._closed:
            return
        self.stats.envelopes_rx += 1
        try:
            env = decode_envelope(data, self.limits)
        except MalformedEnvelope as e:
            self.rejected.count(e.reason, f"on {key[:80]}: {e}")
            self._malformed(key, str(e))
            return
        now = self.clock.now()
        if env.kind is Kind.ACK:
            self._ack_in(env.src, env.x, env.y, env.tx_power, env.seq, env.attempt, env.dest, now,
                         env.t)  # fmt: skip
            return
        # A frame, published when it went on the air: it occupies the air of every
        # process that hears its cell (carrier sense, interference), and is decided
        # by the local motes it concerns at its end + the guard.
        start = env.t
        if start > now + self.clock.emulated_seconds(EARLY_LIMIT_S):
            self.stats.early += 1
            self.rejected.count("early", f"frame of {env.src} starts at {start:.3f}, now {now:.3f}")
            if self.on_early is not None:
                self.on_early(start - now)
            return
        end = linklayer.airtime_end(self.preset, start, len(env.frame))
        f = None
        if self._track:
            f = self._air_add(env.src, env.x, env.y, env.tx_power, start, end, env.seq, env.attempt)
            if f is None:
                return
        if env.dest != BROADCAST and env.dest not in self.radios:
            self.stats.ignored += 1  # a unicast to a mote elsewhere: only its airtime counts
            if self.tap is not None:
                self.tap.on_air(end, env.src, env.dest, env.seq, env.attempt, env.frame)
            return
        fr = _OnAirFrame(env, end, f, None)
        fr.remote = True  # captured (tap) when decided, as a local frame is at its end
        self._schedule_decision(fr)

    def _air_add(
        self, src: int, x: float, y: float, txp: float, start: float, end: float, seq: int,
        attempt: int,
    ) -> OnAir | None:  # fmt: skip
        """A remote frame on the Air; None (``rejected["air full"]``) if the Air is full."""
        air = self._air
        air.prune(self.clock.now())
        if len(air) >= MAX_ON_AIR:
            self.rejected.count("air full", f"{MAX_ON_AIR} frames on the air")
            return None
        return air.add(src, x, y, txp, start, end, packet_key(seq, attempt))

    def _schedule_decision(self, fr: _OnAirFrame) -> None:
        """Decide ``fr``'s local receptions at its end + the guard (at once if that is
        past). One heap of pending decisions and one loop timer for its head: far
        cheaper than a loop timer per frame (asyncio compares its handles in Python)."""
        due = self.clock.to_monotonic(fr.end) + self._decide_after
        loop = self.loop
        if due < loop.time() and self._collide:
            self.stats.late += 1
        q = self._decisions
        if len(q) >= MAX_ON_AIR:  # bound: a frame per envelope accepted
            self.rejected.count("decisions full", f"{MAX_ON_AIR} frames awaiting a decision")
            return
        self._decision_seq += 1
        heapq.heappush(q, (due, self._decision_seq, fr))
        h = self._decision_timer
        if h is None or due < self._decision_at:
            if h is not None:
                h.cancel()
            self._decision_at = due
            self._decision_timer = loop.call_at(due, self._run_decisions)

    def _run_decisions(self) -> None:
        """Decide every frame whose time has come, in order; re-arm for the next."""
        self._decision_timer = None
        q = self._decisions
        now = self.loop.time()
        while q and q[0][0] <= now:
            fr = heapq.heappop(q)[2]
            try:
                self._decide(fr)
            except Exception as e:
                self.faults.count(f"decide: {type(e).__name__}", f"frame of {fr.env.src}: {e}", e)
        if q and not self._closed:
            self._decision_at = q[0][0]
            self._decision_timer = self.loop.call_at(self._decision_at, self._run_decisions)

    def _decide(self, fr: _OnAirFrame) -> None:
        """Rules 3 to 7 for the local motes ``fr`` concerns, now that every frame
        that overlapped it is known (collisions: :meth:`Air.survives`)."""
        if self._closed or fr.cancelled:
            return
        now = self.clock.now()
        e = fr.env
        f = fr.f
        if fr.remote and self.tap is not None:
            self.tap.on_air(fr.end, e.src, e.dest, e.seq, e.attempt, e.frame)
        others = self._air.overlapping(f) if self._collide and f is not None else None
        rx = self._rx
        if e.dest == BROADCAST:
            if not rx.broadcast(e.src, e.x, e.y, e.tx_power, True, e.frame, e.seq, f,
                                others or None, now, self.tap, fr.end):  # fmt: skip
                self.stats.ignored += 1
            return
        r = self.radios.get(e.dest)
        got = False
        if r is not None and r.alive:
            link = rx.link(e.src, e.x, e.y, e.tx_power, r, now)
            if link is None:
                self.stats.ignored += 1  # not listening to the sender's cell
            else:
                rng = self.model.max_range_m(e.tx_power)
                got = rx.unicast(e.src, link, rng, e.frame, e.seq, e.attempt, f, others or None,
                                 now, self.tap, fr.end)  # fmt: skip
                if got:  # it sent its ACK (and may have spent its battery since)
                    self._check_battery(r, now)
        s = fr.sender
        if s is not None:  # a local sender: its outcome, as the virtual medium times it
            acked = (
                got
                and r is not None
                and self._ack_heard(r.node_id, r.x, r.y, r.tx_power, s, e.seq, e.attempt, fr.end)
            )
            if s.alive and s.cur is not None and (s.cur_seq, s.cur_attempt) == (e.seq, e.attempt):
                # The sender resumes when the virtual medium's sender would, unless
                # the decision itself came later (the guard is longer than the ACK
                # exchange): then now -- a radio does not act in the past.
                t = max(linklayer.outcome_time(self.preset, fr.end, acked), now)
                s.handle = self.loop.call_at(self.clock.to_monotonic(t), self._uc_done, s, acked, t)
        elif got and r is not None:
            # The destination got it: its auto-ACK goes back to the sender's process,
            # stamped with the data frame's end (when the sender's noise is taken).
            self._publish(r, Kind.ACK, e.seq, e.attempt, fr.end, e.src, b"")

    def _malformed(self, key: str, reason: str) -> None:
        """Garbage on a radio key: counted per process and at the local motes that
        listen to the cell named by the key (if the key names one)."""
        self.stats.malformed_envelopes += 1
        log.debug("malformed envelope on %s: %s", key, reason)
        if self.on_malformed is not None:
            self.on_malformed(key, reason)
        parts = key.split("/")
        if len(parts) < 4:
            return
        try:
            cx, cy = int(parts[-3]), int(parts[-2])
        except ValueError:
            return
        now = self.clock.now()
        for r in self._nb.listeners((cx, cy), now):
            r.counters.malformed += 1

    def _deliver(self, r: Radio, src: int, data: bytes, rssi: float, now: float) -> None:
        """A frame ``r`` took (radio/reception.py) goes to its runner."""
        if self.links is not None:
            _tally(self.links, src, r.node_id)
        r.sink.radio_receive(data, rssi, now)

    def _ack_in(
        self,
        acker: int,
        ax: float,
        ay: float,
        atxp: float,
        seq: int,
        attempt: int,
        dest: int,
        now: float,
        frame_end: float,
    ) -> None:
        s = self.radios.get(dest)
        if s is None or s.cur is None or not s.alive:
            self.stats.ignored += 1
            return
        if s.cur.dest != acker or s.cur_seq != seq or attempt > s.cur_attempt:
            self.stats.ignored += 1  # a late ACK of an earlier frame
            return
        self._nb.locate(s, now)
        if self._ack_heard(acker, ax, ay, atxp, s, seq, attempt, frame_end):
            if s.handle is not None:
                s.handle.cancel()
                s.handle = None
            self._uc_done(s, True, now)

    def _ack_heard(
        self,
        acker: int,
        ax: float,
        ay: float,
        atxp: float,
        s: Radio,
        seq: int,
        attempt: int,
        frame_end: float,
    ) -> bool:
        d = math.hypot(s.x - ax, s.y - ay)
        return linklayer.ack_heard(self.model, acker, atxp, s.node_id, d, seq, attempt,
                                   frame_end)  # fmt: skip

    # ------------------------------------------------------------------ send side

    # Every timer of a radio carries the emulated time it stands for, and the MAC
    # runs on that time, not on the (later) instant the loop runs it: so the MAC's
    # times are a function of the seed and of when the frames were handed over,
    # as in the virtual medium.

    def _start_next(self, r: Radio, now: float) -> None:
        if not r.queue or self._frozen or self._closed:
            return
        linklayer.begin_next(r, self.guard)
        self._schedule_attempt(r, now)

    def _schedule_attempt(self, r: Radio, now: float) -> None:
        """The MAC (radio/mac.py via linklayer.attempt) takes the attempt."""
        t = linklayer.attempt(r, now)
        if self._sense:
            r.handle = self.loop.call_at(self.clock.to_monotonic(t), self._cca, r, t)
        else:
            self._go(r, t)

    def _cca(self, r: Radio, t: float) -> None:
        """The clear channel assessment of ``r`` ending at ``t``, against the frames
        this process knows on the air: transmit, back off or give up."""
        r.handle = None
        if r.cur is None or not r.alive or self._closed:
            return
        self._nb.locate(r, t)
        action, t2 = linklayer.assess(r, self._air, self.mac_params, t)
        if action == TRANSMIT:
            self._go(r, t2)
        elif action == SENSE:
            r.handle = self.loop.call_at(self.clock.to_monotonic(t2), self._cca, r, t2)
        else:
            assert action == GIVE_UP
            tx = linklayer.give_up(r)
            if tx is not None and tx.dest != BROADCAST:
                r.sink.radio_link_result(tx, False, t)
            if r.alive and not r.busy:
                self._start_next(r, t)

    def _go(self, r: Radio, start: float) -> None:
        """The attempt goes on the air at ``start``: on the local Air, published
        (with its start time) to the other processes, its end timed, and its local
        receptions decided at the end + the guard."""
        tx = r.cur
        if tx is None or self._closed:
            return
        self._nb.locate(r, start)
        air = None
        if self._track:
            air = self._air
            air.prune(self.clock.now())
        end = linklayer.put_on_air(r, air, self.preset, start)
        seq, attempt = r.cur_seq, r.cur_attempt
        frame = r.air  # sealed when the medium is secured
        self._publish(r, Kind.FRAME, seq, attempt, start, tx.dest, frame)
        local_dest = tx.dest == BROADCAST or tx.dest in self.radios
        env = Envelope(Kind.FRAME, r.node_id, r.x, r.y, r.tx_power, seq, attempt, start, tx.dest,
                       frame)  # fmt: skip
        fr = _OnAirFrame(env, end, r.onair, r if local_dest and tx.dest != BROADCAST else None)
        r.on_air = fr
        r.handle = self.loop.call_at(self.clock.to_monotonic(end), self._tx_end, r, end)
        if local_dest:
            self._schedule_decision(fr)

    def _tx_end(self, r: Radio, end: float) -> None:
        """The attempt left the air at ``end``: counted; a broadcast frees the radio,
        a unicast waits for its outcome (the local decision, or an ACK envelope)."""
        r.handle = None
        tx = r.cur
        fr = r.on_air
        r.on_air = None
        r.onair = None
        if not r.alive or tx is None or self._closed:
            return
        c = r.counters
        c.frames_tx += 1
        c.bytes_tx += len(r.air)
        if self.tap is not None:
            self.tap.on_air(end, r.node_id, tx.dest, r.cur_seq, r.cur_attempt, r.air)
        if tx.dest == BROADCAST:
            r.busy = False
            r.cur = None
            if self._check_battery(r, end) and r.alive and not r.busy:
                self._start_next(r, end)
            return
        if not self._check_battery(r, end):
            return
        if fr is not None and fr.sender is r:
            return  # a local destination: the decision at end + guard gives the outcome
        p = self.preset
        wall = max(self.clock.wall_seconds(p.ack_timeout_s), self.ack_wait_floor_s)
        t = self.clock.emulated_seconds(wall) + end
        r.handle = self.loop.call_at(
            self.clock.to_monotonic(end) + wall, self._uc_done, r, False, t
        )

    def _uc_done(self, r: Radio, acked: bool, now: float) -> None:
        """The outcome of a unicast attempt, known at emulated ``now`` (the time
        the timer stands for: the sender resumes from it)."""
        r.handle = None
        tx = r.cur
        if not r.alive or tx is None or self._closed:
            return
        if linklayer.settle(r, acked, 0 if self._frozen else self.preset.max_retries):
            self._schedule_attempt(r, now)
            return
        r.sink.radio_link_result(tx, acked, now)
        if acked and not self._check_battery(r, now):
            return
        if r.alive and not r.busy:
            self._start_next(r, now)

    def _publish(
        self, r: Radio, kind: Kind, seq: int, attempt: int, now: float, dest: int, frame: bytes
    ) -> None:
        """Put one envelope from ``r`` on its current cell's key (remote processes only)."""
        if self._closed:
            return
        data = encode_envelope(
            kind, r.node_id, r.x, r.y, r.tx_power, seq, attempt, now, dest, frame
        )
        pub = r.pub
        if pub is None or r.pub_cell != r.cell:
            pub = self._ensure_publisher(r)
        pub.put(data)
        if kind is Kind.ACK:
            self.stats.acks_published += 1
        else:
            self.stats.frames_published += 1

    def _ensure_publisher(self, r: Radio) -> zenoh.Publisher:
        """The publisher of ``r``'s current cell key (re-declared when it moves)."""
        pub = r.pub
        if pub is None or r.pub_cell != r.cell:
            if pub is not None:
                pub.undeclare()  # type: ignore[no-untyped-call]
            pub = r.pub = self.session.declare_publisher(
                self.key_for(r.cell, r.node_id), allowed_destination=zenoh.Locality.REMOTE
            )
            r.pub_cell = r.cell
        return pub

    # ------------------------------------------------------------------ battery, death

    def _check_battery(self, r: Radio, now: float) -> bool:
        """False (and the mote is switched off) once its battery is spent."""
        if linklayer.battery_spent(r, self.preset):
            self._battery_down(r, now)
            return False
        return r.alive

    def _battery_down(self, r: Radio, now: float) -> None:
        self.detach(r.node_id)
        r.sink.radio_down("battery", now)

    def _silence(self, r: Radio) -> None:
        fr = r.on_air
        if fr is not None:
            # Switched off mid-frame: as in the virtual medium, nobody here receives
            # it (other processes, told nothing, decide the whole frame).
            fr.cancelled = True
            r.on_air = None
        if self._track:
            self._air.cut(r.node_id, self.clock.now())
        linklayer.silence(r)
        if r.handle is not None:
            r.handle.cancel()
            r.handle = None
        if r.pub is not None:
            with contextlib.suppress(zenoh.ZError):
                r.pub.undeclare()  # type: ignore[no-untyped-call]
            r.pub = None
            r.pub_cell = None

    # ------------------------------------------------------------------ geometry

    def _ensure_mobility_tick(self) -> None:
        # Moving receivers must be subscribed to the columns they move into even
        # if they neither send nor hear anything for a while.
        if self._mobility_handle is None and self._loop is not None:
            self._mobility_handle = self._loop.call_later(0.5, self._mobility_tick)

    def _mobility_tick(self) -> None:
        self._mobility_handle = None
        if self._closed or not self._nb.moving:
            return
        now = self.clock.now()
        nb = self._nb
        for r in nb.moving:
            nb.locate(r, now)
        self._mobility_handle = self.loop.call_later(0.5, self._mobility_tick)


def poll_bounds(speed: float, shortest_airtime_s: float, guard_s: float) -> tuple[float, float]:
    """Wall seconds between polls of the channels (``"channel"`` mode): after
    traffic, and at most while nothing arrives: :data:`CHANNEL_POLL_MIN_S` and
    :data:`CHANNEL_POLL_MAX_S` at every speed (the arguments are kept for the
    caller, which gives what a cadence could be derived from)."""
    # Not thinned below speed 1 after all: a remote envelope must be on this
    # process's Air before a local clear channel assessment that overlaps its
    # frame (CSMA across processes, tests/test_mac_zenoh.py), and at speed 0.05
    # polls every 20-25 ms wall (1 ms emulated) missed frames 0.5 ms into their
    # airtime. The CPU it saved (18 % at 1,000 motes, speed 0.2) is not worth it.
    del speed, shortest_airtime_s, guard_s
    return CHANNEL_POLL_MIN_S, CHANNEL_POLL_MAX_S


def _tally(links: dict[tuple[int, int], int], src: int, dst: int) -> None:
    """One more frame delivered on the link ``src -> dst`` (``ZenohMedium.links``)."""
    k = (src, dst)
    links[k] = links.get(k, 0) + 1
