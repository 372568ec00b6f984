"""AwareMote: the middleware of one mote, composed of its components.

The mote is the :class:`~awaremw.protocol.core.MoteCore` the runtime drives. It
decodes frames once, keeps the RSSI table behind the ``rssi:<node>``
attributes, dispatches frames by type to the components, merges their timers
and routes link-layer outcomes back to the component that sent the frame.

Components (one module each) share a :class:`MoteContext` and talk to each
other through the small APIs they expose on the mote:

* ``dissemination`` (Drip) holds the versioned definitions and calls
  :meth:`AwareMote._on_item` when one changes;
* ``collection`` (CTP-like) carries payloads to the gateway roots;
* ``groups`` evaluates conditions, runs leader election, the group tree;
* ``channels`` samples, aggregates along the group tree, emits records;
* ``commands`` runs the node kind's handler for targeted commands.
"""

from __future__ import annotations

import random
from collections.abc import Callable

from mypy_extensions import mypyc_attr

from awaremw.protocol.attributes import Application
from awaremw.protocol.channels import Channels
from awaremw.protocol.collection import Collection
from awaremw.protocol.commands import Commands
from awaremw.protocol.component import Component, MoteContext, RssiSample
from awaremw.protocol.config import MiddlewareConfig
from awaremw.protocol.core import Transmission
from awaremw.protocol.dissemination import Dissemination
from awaremw.protocol.events import CoreEvent, MalformedFrame
from awaremw.protocol.frames import (
    BROADCAST,
    CtpBeacon,
    CtpData,
    DripItem,
    DripSig,
    DripSummary,
    FrameError,
    Handover,
    Hello,
    ItemBody,
    ItemKind,
    LeaderBeacon,
    Partial,
    decode_shared,
)
from awaremw.protocol.groups import Groups
from awaremw.protocol.timers import TimerSet

_INF = float("inf")

__all__ = ["AwareMote", "Component", "MoteContext", "RssiSample"]  # the contract is re-exported


# Subclassed by Python code (benchmarks, tests) in the compiled build (setup.py).
@mypyc_attr(allow_interpreted_subclasses=True)
class AwareMote:
    """One mote running the AWARE middleware (a :class:`MoteCore`)."""

    def __init__(
        self,
        node_id: int,
        app: Application | None = None,
        config: MiddlewareConfig | None = None,
        rng: random.Random | None = None,
    ) -> None:
        self.node_id = node_id
        self.config = config or MiddlewareConfig()
        self.ctx = MoteContext(node_id, self.config, rng or random.Random(node_id), app)
        # A version jump from the collection parent is taken (docs/protocol-dissemination.md).
        self.dissemination = Dissemination(
            self.ctx, on_item=self._on_item, parent=lambda: self.collection.parent
        )
        self.collection = Collection(self.ctx)
        self.groups = Groups(self.ctx, self.collection)
        self.channels = Channels(self.ctx, self.groups, self.collection)
        # Engineer C: Commands learns each slot's version from dissemination.
        self.commands = Commands(self.ctx, self.groups, self.dissemination.version_of)
        self.beacon = _HelloBeacon(self.ctx)
        self._components: tuple[Component, ...] = (
            self.dissemination,
            self.collection,
            self.groups,
            self.channels,
            self.commands,
            self.beacon,
        )
        self._by_type: dict[int, Component] = {
            Hello.TYPE: self.beacon,
            DripItem.TYPE: self.dissemination,
            DripSummary.TYPE: self.dissemination,
            DripSig.TYPE: self.dissemination,
            CtpBeacon.TYPE: self.collection,
            CtpData.TYPE: self.collection,
            LeaderBeacon.TYPE: self.groups,
            Handover.TYPE: self.groups,
            Partial.TYPE: self.channels,
        }
        self._timed = tuple((c, c.timers) for c in self._components)  # set once per component
        # The components whose timer set was ever armed, in the same order (the
        # others have no timer: the timer loops skip them); rebuilt on TimerWatch.grew.
        # Two flat tuples, not one of (component, set) pairs: a timer event reads
        # every live set's soonest, and a pair tuple each was one more object (a
        # cache line, scattered: built while running) per set per event.
        self._live_comps: tuple[Component, ...] = ()
        self._live_sets: tuple[TimerSet, ...] = ()
        self._timer_watch = self.ctx.watch
        for c in self._components:
            c.timers.watch(self._timer_watch)
        self._next_deadline: float | None = None  # valid while not _timer_watch.changed
        # Read on every frame heard (the config is frozen, the table never replaced).
        self._rssi = self.ctx.rssi
        self._rssi_alpha = self.config.rssi_alpha
        self._rssi_ttl = self.config.rssi_ttl
        self.started = False
        cls = type(self)
        self._idle_exact = (
            cls.next_deadline is AwareMote.next_deadline
            and cls.drain is AwareMote.drain
            and cls.events is AwareMote.events
        )

    # ----------------------------------------------------------------- MoteCore

    def start(self, now: float) -> None:
        self.started = True
        for c in self._components:
            c.start(now)

    def receive(self, frame: bytes, rssi_dbm: float, now: float) -> None:
        try:
            f = decode_shared(frame)
        except FrameError as e:
            self.ctx.emit(MalformedFrame(str(e), len(frame)))
            return
        dst = f.dst
        if dst != BROADCAST and dst != self.node_id:
            return  # overheard unicast for someone else
        # The RSSI EWMA of src (once per frame heard): its sample updated in place.
        src = f.src
        s = self._rssi.get(src)
        if s is None:
            self._rssi[src] = RssiSample(rssi_dbm, now)
            self.groups.heard_again(src, now)
        elif now - s.last_heard > self._rssi_ttl:
            s.dbm = rssi_dbm
            s.last_heard = now
            self.groups.heard_again(src, now)
        else:
            a = self._rssi_alpha
            s.dbm = a * rssi_dbm + (1 - a) * s.dbm
            s.last_heard = now
        self._by_type[f.TYPE].on_frame(f, rssi_dbm, now)

    def handle_timer(self, now: float) -> None:
        w = self._timer_watch
        if w.grew:
            self._relive()
        comps = self._live_comps
        for i, t in enumerate(self._live_sets):
            if t.soonest <= now:  # else (a lower bound of its earliest deadline) none due
                c = comps[i]
                for name in t.due(now):
                    c.on_timer(name, now)
                if w.grew:
                    # A component got its first timer meanwhile: go on over every
                    # component after this one, as a loop over all of them would.
                    self._relive()
                    for c2, t2 in self._timed[self._components.index(c) + 1 :]:
                        if t2.soonest <= now:
                            for name in t2.due(now):
                                c2.on_timer(name, now)
                    return

    def _relive(self) -> None:
        self._timer_watch.grew = False
        live = [(c, t) for c, t in self._timed if t.armed]
        self._live_comps = tuple(c for c, _t in live)
        self._live_sets = tuple(t for _c, t in live)

    def next_deadline(self) -> float | None:
        w = self._timer_watch
        if w.changed:
            w.changed = False
            if w.grew:
                self._relive()
            best = _INF
            for t in self._live_sets:  # the sets never armed are empty
                if t.stale:
                    t.next_deadline()  # refreshes soonest
                if t.soonest < best:
                    best = t.soonest  # exact: not stale
            if best == _INF and any(len(t) for t in self._live_sets):
                self._next_deadline = best  # a timer at infinity is still a timer
            else:
                self._next_deadline = None if best == _INF else best
        return self._next_deadline

    def idle(self) -> bool:
        """:class:`~awaremw.protocol.core.IdleCheck`: nothing queued, no timer changed
        (always False in a subclass that overrides what it vouches for)."""
        w = self._timer_watch  # its queued flag: a frame or an event may be waiting
        return self._idle_exact and not w.queued and not w.changed

    def drain(self) -> list[Transmission]:
        ctx = self.ctx
        out, ctx.outbox = ctx.outbox, []
        ctx.watch.queued = bool(ctx.event_list)
        return out

    def link_result(self, tx: Transmission, acked: bool, now: float) -> None:
        entry = self.ctx.pending.pop(tx.tx_id, None)
        if entry is None:
            raise KeyError(f"link result for unknown transmission {tx.tx_id}")
        owner, frame = entry
        owner.on_link_result(frame, acked, now)

    def events(self) -> list[CoreEvent]:
        ctx = self.ctx
        out, ctx.event_list = ctx.event_list, []
        ctx.watch.queued = bool(ctx.outbox)
        return out

    # ----------------------------------------------------------------- API for the gateway

    def inject(
        self,
        kind: ItemKind,
        item_id: int,
        version: int,
        item: ItemBody | None,
        now: float,
        signature: bytes | None = None,
    ) -> None:
        """Inject a definition, command or deletion (gateway motes). With signed
        items the signature is ``signature`` or made by ``dissemination.signer``."""
        self.dissemination.inject(kind, item_id, version, item, now, signature)

    # ----------------------------------------------------------------- internals

    def _on_item(self, kind: ItemKind, item_id: int, item: ItemBody | None, now: float) -> None:
        handler: Callable[[int, ItemBody | None, float], None] = {
            ItemKind.GROUP_TYPE: self.groups.define,
            ItemKind.CHANNEL: self.channels.define,
            ItemKind.COMMAND: self.commands.define,
        }[kind]
        handler(item_id, item, now)


class _HelloBeacon(Component):
    """Optional periodic Hello (the beacon of a robot's mote, for RSSI groups)."""

    def __init__(self, ctx: MoteContext) -> None:
        super().__init__(ctx)
        self.seq = 0

    def start(self, now: float) -> None:
        if self.ctx.config.hello_period:
            self.timers.set("hello", now + self.ctx.rng.uniform(0, self.ctx.config.hello_period))

    def on_timer(self, name: object, now: float) -> None:
        period = self.ctx.config.hello_period
        assert period
        self.seq = (self.seq + 1) & 0xFFFF
        self.send(Hello(self.ctx.node_id, BROADCAST, self.seq))
        self.timers.set("hello", now + period)
