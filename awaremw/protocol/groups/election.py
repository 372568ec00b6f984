"""Election: a qualifying mote out of any group joins the heaviest group heard,
else waits a random backoff and creates one -- with a tentative id first.

A would-be group announces its id (``tentative`` beacons, never joined, never
forwarded) ``TENTATIVE_BEACONS`` times over ``tentative_periods`` beacon periods
and takes it unless an established group answers or a heavier would-be group is
heard, so contention ends before any mote holds the losing id; a mote between
two would-be groups relays the higher one's announcement once
(docs/protocol-groups.md, "Vicinity, creation, group ids" and "Tentative ids").
"""

from __future__ import annotations

from dataclasses import dataclass, field

from awaremw.protocol.events import ElectionCause
from awaremw.protocol.frames import BROADCAST, LeaderBeacon
from awaremw.protocol.groups.flood import Flood
from awaremw.protocol.groups.kit import Kit, Moves
from awaremw.protocol.groups.lineage import Lineage
from awaremw.protocol.groups.standing import Standing
from awaremw.protocol.groups.values import (
    ELECTION_BACKOFF_FACTOR,
    MAX_GROUP_ID,
    TENTATIVE_BEACONS,
    TENTATIVE_CREATE_SPREAD,
    Heard,
    Role,
    Tick,
    seq_newer,
)


@dataclass(slots=True)
class _Ballot:
    cause: ElectionCause = ElectionCause.CREATED  # why this mote waits to create
    nearby: dict[int, Heard] = field(default_factory=dict)  # group id -> its newest beacon
    tent_gid: int = 0  # WAITING: the id this mote announced tentatively (0: none)
    tent_sent: int = 0  # tentative beacons sent for tent_gid
    tent_heard: dict[int, float] = field(default_factory=dict)  # tentative id -> heard at
    tent_leader: dict[int, int] = field(default_factory=dict)  # tentative id -> announcer
    tent_relayed: int = 0  # the would-be id whose announcement we relayed last
    relay: tuple[int, int] | None = None  # (would-be id, announcer) of the pending relay


class Election:
    """Groups heard, waiting, tentative ids and creation, for every group type
    (the ``create``, ``confirm``, ``announce`` and ``relay`` timers)."""

    def __init__(self, kit: Kit, lineage: Lineage, flood: Flood) -> None:
        self._kit = kit
        self._lineage = lineage
        self._flood = flood
        self._at: dict[int, _Ballot] = {}

    def add(self, gtype: int) -> None:
        self._at[gtype] = _Ballot()

    def drop(self, gtype: int) -> None:
        del self._at[gtype]

    def note_nearby(self, gtype: int, f: LeaderBeacon, rssi: float, now: float) -> None:
        """Remember the best copy of the newest beacon of each group heard."""
        nearby = self._at[gtype].nearby
        h = nearby.get(f.group_id)
        if h is None or seq_newer(f.seq, h.seq) or h.leader != f.leader:
            nearby[f.group_id] = Heard(f.leader, f.weight, f.seq, f.hops, f.src, now, rssi)
        elif f.seq == h.seq and (f.hops, -rssi) < (h.hops, -h.rssi):
            h.hops, h.src, h.t, h.rssi = f.hops, f.src, now, rssi

    def _best_nearby(self, gtype: int, now: float) -> tuple[int, Heard] | None:
        """The heaviest group heard within the leader timeout, if any."""
        ttl = self._kit.timeout()
        nearby = self._at[gtype].nearby
        fresh = [(h.weight, gid, h) for gid, h in nearby.items() if now - h.t <= ttl]
        if not fresh:
            return None
        _w, gid, h = max(fresh, key=lambda x: (x[0], x[1]))
        return gid, h

    def forget(self, gtype: int, gid: int) -> None:
        """A group whose leader is lost: not one to join."""
        self._at[gtype].nearby.pop(gid, None)

    def join_or_wait(self, s: Standing, now: float, cause: ElectionCause, moves: Moves) -> None:
        """Join the heaviest group heard, else wait a random backoff to create one."""
        best = self._best_nearby(s.gtype, now)
        if best is not None:
            moves.join_heard(s, best[0], best[1], now)
            return
        s.move_to(Role.WAITING)
        self._at[s.gtype].cause = cause
        # After a split every member of the leaderless part gives up on the same
        # last beacon: a wider backoff spreads their claims so that the first new
        # group's flood reaches the others before they create contenders.
        spread = ELECTION_BACKOFF_FACTOR if cause is ElectionCause.ELECTION else 1.0
        if cause is ElectionCause.CREATED and self._kit.tentative_hold() > 0:
            # The tentative period resolves contention now: half the backoff
            # gives back part of the time it costs before the first record.
            spread = TENTATIVE_CREATE_SPREAD
        backoff = self._kit.ctx.rng.uniform(0, spread * self._kit.ctx.config.create_backoff)
        self._kit.timers.set((Tick.CREATE, s.gtype), now + backoff)

    def quit(self, gtype: int) -> None:
        """No more waiting: the mote joined a group or stopped qualifying."""
        self._kit.timers.cancel((Tick.CREATE, gtype))
        if self._at[gtype].tent_gid:
            self._withdraw(gtype)

    def took_id(self, gtype: int) -> None:
        """The mote leads a group now: its would-be id (if any) is taken or moot."""
        self._at[gtype].tent_gid = 0

    def on_create(self, s: Standing, now: float, moves: Moves) -> None:
        """The backoff ended: join a group heard meanwhile, else create one."""
        best = self._best_nearby(s.gtype, now)
        if best is not None:
            moves.join_heard(s, best[0], best[1], now)
        else:
            self._create(s, now, moves)

    def on_confirm(self, s: Standing, now: float, moves: Moves) -> None:
        b = self._at[s.gtype]
        if not b.tent_gid:
            return
        if b.tent_sent < TENTATIVE_BEACONS:
            # Once more half-way: one lost frame (ours, or the answer) on a
            # marginal link must not let a contender take its id.
            self.on_announce(s)
            hold = self._kit.tentative_hold()
            self._kit.timers.set((Tick.CONFIRM, s.gtype), now + hold / TENTATIVE_BEACONS)
            return
        # The would-be group heard no established group and no heavier
        # would-be group for a tentative period: its id is taken now.
        gid, b.tent_gid = b.tent_gid, 0
        moves.become_leader(s, gid, 0, 0, now, b.cause)

    def on_announce(self, s: Standing) -> None:
        """Announce our would-be group's id (again)."""
        b = self._at[s.gtype]
        if not b.tent_gid:
            return
        me = self._kit.ctx.node_id
        self._kit.send(LeaderBeacon(me, BROADCAST, s.gtype, b.tent_gid, me, 0, 0, 0, True))
        b.tent_sent += 1
        self._kit.stats.tentative_sent += 1

    def on_relay(self, s: Standing) -> None:
        b = self._at[s.gtype]
        if b.tent_gid or b.relay is None:
            return
        (top, who), b.relay = b.relay, None
        me = self._kit.ctx.node_id
        self._kit.send(LeaderBeacon(me, BROADCAST, s.gtype, top, who, 0, 0, 1, True))

    def on_tentative(self, s: Standing, f: LeaderBeacon, now: float) -> None:
        """A would-be group's announcement: never joined, never forwarded."""
        b = self._at[s.gtype]
        hold = self._kit.tentative_hold()
        rivals = [g for g, t in b.tent_heard.items() if now - t <= hold and g != f.group_id]
        b.tent_heard[f.group_id] = now
        b.tent_leader[f.group_id] = f.leader
        role = s.role
        if role in (Role.IDLE, Role.WAITING) and not b.tent_gid and rivals:
            # Two would-be groups around us, maybe out of each other's range:
            # relay the higher one's announcement once, the lower one withdraws.
            top = max([*rivals, f.group_id])
            if top != b.tent_relayed:
                # After a jitter: every mote between the two heard the same frame
                # at the same instant; relaying at once, they collided.
                b.tent_relayed = top
                b.relay = (top, b.tent_leader.get(top, 0))
                self._kit.soon((Tick.RELAY, s.gtype), now)
        if role in (Role.MEMBER, Role.LEADER):
            # An established group is in range: answer with our beacon, the
            # would-be group joins us instead of taking its id.
            self._flood.rebut(s, now)
        elif role is Role.WAITING and b.tent_gid:
            if (f.group_id, f.leader) > (b.tent_gid, self._kit.ctx.node_id):
                # The paper's order among weight-0 groups: the higher id goes on;
                # we wait for its first beacon (or announce again later).
                self._withdraw(s.gtype)
                backoff = self._kit.ctx.rng.uniform(0, self._kit.ctx.config.create_backoff)
                at = now + self._kit.tentative_hold() + backoff
                self._kit.timers.set((Tick.CREATE, s.gtype), at)
            elif b.tent_sent <= TENTATIVE_BEACONS:
                self._kit.soon((Tick.ANNOUNCE, s.gtype), now)  # it may not have heard ours

    def answer(self, s: Standing, now: float) -> None:
        """We joined a group after hearing a would-be group announce another id (as
        a waiting or idle mote, which does not answer): answer it, one more copy of
        our beacon after the forward, so that one lost forward (two forwarders
        colliding at the would-be group's radio) does not let it take its id."""
        hold = self._kit.tentative_hold()
        heard = self._at[s.gtype].tent_heard
        if any(g != s.gid and now - t <= hold for g, t in heard.items()):
            self._flood.answer(s.gtype, now)

    def purge(self, gtype: int, now: float, nearby_ttl: float, ttl: float) -> None:
        b = self._at[gtype]
        if b.nearby:
            for gid in [g for g, h in b.nearby.items() if now - h.t > nearby_ttl]:
                del b.nearby[gid]
        if b.tent_heard:
            for g in [g for g, t in b.tent_heard.items() if now - t > ttl]:
                del b.tent_heard[g]
                b.tent_leader.pop(g, None)

    def remembers_nothing(self, gtype: int) -> bool:
        b = self._at[gtype]
        return not (b.nearby or b.tent_heard)

    def _create(self, s: Standing, now: float, moves: Moves) -> None:
        kit = self._kit
        b = self._at[s.gtype]
        taken = set(b.nearby) | {s.gid}
        if b.cause is ElectionCause.ELECTION:
            former = self._lineage.former(s.gtype, now, taken)
            if former:
                # A part that lost the merged group's leader soon after the merge:
                # the merge did not hold, the part goes on under its own former id.
                moves.become_leader(s, former, 0, 0, now, b.cause)
                return
        hold = kit.tentative_hold()
        heard = [t for t in b.tent_heard.values() if now - t <= hold]
        if heard:
            # A neighbour announced a would-be group: wait for it to be taken
            # (its first beacon reaches us) rather than announce a contender.
            backoff = kit.ctx.rng.uniform(0, kit.ctx.config.create_backoff)
            kit.timers.set((Tick.CREATE, s.gtype), max(heard) + hold + backoff)
            return
        taken |= set(b.tent_heard)
        gid = kit.ctx.rng.randint(1, MAX_GROUP_ID)
        while gid in taken:
            gid = kit.ctx.rng.randint(1, MAX_GROUP_ID)
        if hold <= 0:
            moves.become_leader(s, gid, 0, 0, now, b.cause)
            return
        # Tentative ids: announce the id and take it one tentative period later
        # unless an established group answers or a heavier would-be group is heard.
        b.tent_gid, b.tent_sent = gid, 0
        self.on_announce(s)
        kit.timers.set((Tick.CONFIRM, s.gtype), now + hold / TENTATIVE_BEACONS)

    def _withdraw(self, gtype: int) -> None:
        """Give up our would-be group (nobody joined it, nothing was reported)."""
        self._at[gtype].tent_gid = 0
        self._kit.timers.cancel((Tick.CONFIRM, gtype))
        self._kit.timers.cancel((Tick.ANNOUNCE, gtype))
        self._kit.stats.tentative_withdrawn += 1
