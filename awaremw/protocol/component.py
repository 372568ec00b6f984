"""The contract between the mote and its components: :class:`MoteContext` (what
the components of one mote share) and :class:`Component` (timers plus hooks).

A module of its own so that the components (dissemination, collection, groups,
channels, commands) and :mod:`awaremw.protocol.mote`, which composes them,
import it without importing each other in a circle.
"""

from __future__ import annotations

import random
from collections.abc import Callable

from awaremw.protocol.attributes import Application, Bounds, ReadBounds
from awaremw.protocol.config import MiddlewareConfig
from awaremw.protocol.core import Transmission
from awaremw.protocol.events import CoreEvent
from awaremw.protocol.frames import BROADCAST, NODE_MASK, RSSI_BASE, Frame, encode, note_sent
from awaremw.protocol.timers import TimerSet, TimerWatch


class RssiSample:
    """RSSI EWMA of one neighbour's frames. Mutable: the mote updates the sample
    of a neighbour in place on every frame heard (no allocation per frame);
    only :class:`~awaremw.protocol.mote.AwareMote` writes it, the components read it."""

    __slots__ = ("dbm", "last_heard")

    def __init__(self, dbm: float, last_heard: float) -> None:
        self.dbm = dbm  # EWMA of recent frames
        self.last_heard = last_heard

    def __repr__(self) -> str:
        return f"RssiSample(dbm={self.dbm!r}, last_heard={self.last_heard!r})"

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, RssiSample):
            return NotImplemented
        return self.dbm == other.dbm and self.last_heard == other.last_heard

    __hash__ = None  # type: ignore[assignment]  # mutable


class MoteContext:
    """What every component of one mote shares: identity, config, randomness,
    the application, the outbox and the event list."""

    def __init__(
        self,
        node_id: int,
        config: MiddlewareConfig,
        rng: random.Random,
        app: Application | None,
    ) -> None:
        self.node_id = node_id
        self.config = config
        self.rng = rng
        self.app = app
        self.rssi: dict[int, RssiSample] = {}
        self.outbox: list[Transmission] = []
        self.pending: dict[int, tuple[Component, Frame]] = {}
        self.event_list: list[CoreEvent] = []
        # The mote's timers mark it; send and emit set its ``queued`` (the mote's
        # idle check reads this one object, not the two lists).
        self.watch = TimerWatch()
        # The application's read_bounds (ReadBounds), looked up again if app changes.
        self._bounds_app: Application | None = None
        self._bounds: Callable[[int, float], Bounds | None] | None = None

    def send(self, owner: Component, frame: Frame) -> Transmission:
        """Encode ``frame`` (MTU enforced: an oversize frame is our bug) and queue it."""
        data = encode(frame, self.config.mtu)
        note_sent(data, frame)  # its receivers here need not decode it again
        if frame.dst == BROADCAST:
            tx = Transmission.broadcast(data)
        else:
            tx = Transmission.unicast(data, frame.dst)
            self.pending[tx.tx_id] = (owner, frame)
        self.outbox.append(tx)
        self.watch.queued = True
        return tx

    def emit(self, event: CoreEvent) -> None:
        self.event_list.append(event)
        self.watch.queued = True

    def read_bounds(self, attr: int, now: float) -> Bounds | None:
        """An interval :meth:`read` is certain to fall in, now and until a time,
        with no side effect (:class:`~awaremw.protocol.attributes.ReadBounds`),
        or None: unknown."""
        app = self.app
        if app is None or attr & RSSI_BASE:
            return None
        if app is not self._bounds_app:
            self._bounds_app = app
            self._bounds = app.read_bounds if isinstance(app, ReadBounds) else None
        b = self._bounds
        return None if b is None else b(attr, now)

    def read(self, attr: int, now: float) -> float | None:
        """An attribute's current value, or None if this mote cannot give it."""
        if attr & RSSI_BASE:
            s = self.rssi.get(attr & NODE_MASK)
            if s is None or now - s.last_heard > self.config.rssi_ttl:
                return None
            return s.dbm
        if self.app is None or not self.app.offers(attr):
            return None
        return self.app.read(attr, now)


class Component:
    """Base of the middleware's components: timers plus four hooks."""

    def __init__(self, ctx: MoteContext) -> None:
        self.ctx = ctx
        self.timers = TimerSet()

    def start(self, now: float) -> None:
        """Called once when the mote boots."""

    def on_frame(self, frame: Frame, rssi_dbm: float, now: float) -> None:
        """A decoded frame of a type this component owns."""

    def on_timer(self, name: object, now: float) -> None:
        """A timer this component set is due."""

    def on_link_result(self, frame: Frame, acked: bool, now: float) -> None:
        """Outcome of a unicast this component sent."""

    def send(self, frame: Frame) -> Transmission:
        return self.ctx.send(self, frame)
