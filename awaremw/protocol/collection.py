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

The routing half (beacons, neighbour table, parent choice) is
:mod:`awaremw.protocol.ctp_routes`, the data half (the forwarding queue)
:mod:`awaremw.protocol.ctp_forwarding`; :class:`Collection` composes them.
"""

from __future__ import annotations

from collections.abc import Mapping

from awaremw.protocol.component import Component, MoteContext
from awaremw.protocol.ctp_forwarding import RETRY_TIMER, Forwarder
from awaremw.protocol.ctp_routes import (
    BEACON_TIMER,
    ETX_ONE,
    HOLDDOWN_TIMER,
    MAX_COST,
    Beacons,
    CollectionStats,
    Neighbour,
    Routes,
)
from awaremw.protocol.frames import CtpBeacon, CtpData, Frame, Payload
from awaremw.protocol.trickle import Trickle

# The records and constants of the tree, where its users have always found them.
__all__ = ["ETX_ONE", "MAX_COST", "Collection", "CollectionStats", "Neighbour"]


class Collection(Component):
    """The collection-tree component of one mote: the facade the mote holds,
    routing frames, timers and link results to its parts -- the beacons'
    pacing (:class:`Beacons`), the neighbour table and parent choice
    (:class:`Routes`) and the forwarding queue (:class:`Forwarder`)."""

    def __init__(self, ctx: MoteContext) -> None:
        super().__init__(ctx)
        self.stats = CollectionStats()
        self._beacons = Beacons(ctx, self.timers)
        self._routes = Routes(ctx, self.timers, self._beacons, self.stats)
        self._forward = Forwarder(
            ctx, self.timers, self.send, self._routes, self._beacons, self.stats
        )

    # ------------------------------------------------------------------ public API

    @property
    def is_root(self) -> bool:
        return self.ctx.config.is_root

    @property
    def parent(self) -> int | None:
        return self._routes.parent

    @property
    def cost(self) -> int:
        """Path cost to a root, ETX x 10 (0 at a root, NO_ROUTE without a route)."""
        return self._routes.cost

    @property
    def neighbours(self) -> Mapping[int, Neighbour]:
        return self._routes.neighbours

    @property
    def queue_length(self) -> int:
        return len(self._forward)

    @property
    def beacon_trickle(self) -> Trickle:
        return self._beacons.trickle

    def submit(self, payload: Payload, now: float) -> bool:
        """Queue ``payload`` for a root. False if refused (queue full); without a
        route it waits in the queue. At a root it is delivered at once."""
        return self._forward.submit(payload, now)

    def link_cost(self, n: Neighbour) -> int:
        """ETX x 10 of the link to ``n``: max of the RSSI mapping and the ACK EWMA."""
        return self._routes.link_cost(n)

    # ------------------------------------------------------------------ Component hooks

    def start(self, now: float) -> None:
        self._beacons.announce(now)

    def on_frame(self, frame: Frame, rssi_dbm: float, now: float) -> None:
        if isinstance(frame, CtpBeacon):
            self._routes.hear_beacon(frame, rssi_dbm, now)
            if len(self._forward):  # else pump has nothing to do
                self._forward.pump(now)
        elif isinstance(frame, CtpData):
            self._forward.on_data(frame, rssi_dbm, now)

    def on_timer(self, name: object, now: float) -> None:
        if name == BEACON_TIMER:
            if self._beacons.trickle.handle_timer(now):
                self.stats.beacons += 1
                self.send(self._routes.beacon())
            self._beacons.arm()
        elif name == RETRY_TIMER:
            self._forward.pump(now)
        elif name == HOLDDOWN_TIMER:
            self._routes.update_route(now)
            self._forward.pump(now)

    def on_link_result(self, frame: Frame, acked: bool, now: float) -> None:
        self._forward.on_link_result(frame, acked, now)
