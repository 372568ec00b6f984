"""Roles: the role changes of a group type (the :class:`~.kit.Moves` the parts
trigger) and the membership check, over every part's share of the type.

A role change touches every part's state; this is the one place that says
which, in one order (docs/protocol-groups.md, "Groups"): a member takes the
tree from the beacon it joined on, a leader starts its pace and keeps its
member neighbours as handover candidates, a mote that leaves forgets its tree.
"""

from __future__ import annotations

from collections.abc import Callable

from awaremw.protocol.events import (
    ElectionCause,
    GroupJoined,
    GroupLeft,
    LeaderElected,
    LeaveReason,
)
from awaremw.protocol.frames import LeaderBeacon
from awaremw.protocol.groups.conditions import Conditions
from awaremw.protocol.groups.election import Election
from awaremw.protocol.groups.flood import Flood
from awaremw.protocol.groups.handover import Handovers
from awaremw.protocol.groups.kit import Kit, PerType
from awaremw.protocol.groups.lineage import Lineage
from awaremw.protocol.groups.liveness import Liveness
from awaremw.protocol.groups.pace import Pace
from awaremw.protocol.groups.standing import Standing
from awaremw.protocol.groups.tree import GroupTree
from awaremw.protocol.groups.values import Heard, Role, Tick

# The timers a role change stops (relay and announce run on while idle or waiting).
_LEADING_STOPS = (Tick.CREATE, Tick.CONFIRM, Tick.LOST, Tick.FWD, Tick.HANDOVER, Tick.CLAIM)
_LEAVING_STOPS = (*_LEADING_STOPS, Tick.BEACON, Tick.REBUT)


class Parts:
    """The parts of group management a role change reaches (built by the
    coordinator, read-only here)."""

    __slots__ = (
        "conditions", "election", "flood", "handovers", "lineage", "liveness", "pace", "tree",
    )  # fmt: skip

    def __init__(
        self,
        conditions: Conditions,
        lineage: Lineage,
        pace: Pace,
        tree: GroupTree,
        flood: Flood,
        election: Election,
        liveness: Liveness,
        handovers: Handovers,
    ) -> None:
        self.conditions = conditions
        self.lineage = lineage
        self.pace = pace
        self.tree = tree
        self.flood = flood
        self.election = election
        self.liveness = liveness
        self.handovers = handovers


class Roles:
    """Role changes and the membership check (implements :class:`~.kit.Moves`)."""

    def __init__(self, kit: Kit, parts: Parts, entered: Callable[[float], None]) -> None:
        self._kit = kit
        self._p = parts
        self._entered = entered  # this mote entered a group (the coordinator's on_enter)

    def add(self, gtype: int) -> None:
        """A new group type: every part's share of it."""
        for part in self._shares():
            part.add(gtype)

    def drop(self, gtype: int) -> None:
        """A deleted type (after its leave): every part forgets it and its timers."""
        for part in self._shares():
            part.drop(gtype)
        for tick in (*_LEAVING_STOPS, Tick.RELAY, Tick.ANNOUNCE):
            self._kit.timers.cancel((tick, gtype))

    def check(self, s: Standing, now: float) -> None:
        """The membership check of one type (hysteresis for members and leaders)."""
        role = s.role
        if role is Role.HANDING_OVER:
            return
        p = self._p
        q = p.conditions.qualifies(s.defn, role is Role.MEMBER or role is Role.LEADER, now)
        if role is Role.IDLE and q:
            self.join_or_wait(s, now, ElectionCause.CREATED)
        elif role is Role.WAITING and not q:
            p.election.quit(s.gtype)
            s.move_to(Role.IDLE)
        elif role is Role.MEMBER and not q:
            self.leave(s, now, LeaveReason.CONDITION)
        elif role is Role.LEADER and not q:
            p.handovers.start(s, now, self)
        elif (
            role is Role.LEADER
            and s.defn.hysteresis > 0
            and not p.conditions.qualifies(s.defn, False, now)
        ):
            # In the hysteresis band: the leader is at the group's edge, leaving
            # it. It hands over now, while members around it still qualify and
            # hear it: a group that moves (a robot, a spreading fire) otherwise
            # leaves its leader behind, cut off from the members ahead, and they
            # elect a new id (the split rule).
            p.handovers.start(s, now, self, early=True)

    def purge(self, s: Standing, now: float) -> None:
        """Forget the groups and neighbours not heard for a leader timeout."""
        g = s.gtype
        if self.remembers_nothing(g):
            return
        p = self._p
        ttl = self._kit.timeout()
        nearby_ttl = ttl
        if s.role is Role.MEMBER or s.role is Role.LEADER:
            ttl = max(ttl, p.pace.member_timeout(g))
        p.tree.purge(g, now, ttl)
        p.handovers.purge(g, now, ttl)
        p.election.purge(g, now, nearby_ttl, ttl)

    def remembers_nothing(self, gtype: int) -> bool:
        """No table that the check purges holds an entry (most motes, hearing no
        group most of the time)."""
        p = self._p
        return (
            p.election.remembers_nothing(gtype)
            and p.tree.remembers_nothing(gtype)
            and p.handovers.remembers_nothing(gtype)
        )

    def join_or_wait(self, s: Standing, now: float, cause: ElectionCause) -> None:
        self._p.election.join_or_wait(s, now, cause, self)

    def join_heard(self, s: Standing, gid: int, h: Heard, now: float) -> None:
        """Join a group remembered from an earlier beacon, and announce it: forward
        that (older) seq once, so that a waiting mote two hops away adopts the group
        now rather than creating a contender before the leader's next beacon."""
        self._become_member(s, gid, h, now)
        self._p.flood.announce(s, now, must=True)
        self._p.election.answer(s, now)

    def adopt(self, s: Standing, f: LeaderBeacon, rssi: float, now: float) -> None:
        """Join the group of beacon ``f`` just heard, and forward it."""
        h = Heard(f.leader, f.weight, f.seq, f.hops, f.src, now, rssi)
        self._become_member(s, f.group_id, h, now)
        self._p.flood.announce(s, now, must=False)
        self._p.election.answer(s, now)

    def become_leader(
        self, s: Standing, gid: int, weight: int, seq: int, now: float, cause: ElectionCause
    ) -> None:
        g = s.gtype
        p = self._p
        for tick in _LEADING_STOPS:
            self._kit.timers.cancel((tick, g))
        p.election.took_id(g)
        # A member taking over knows its member neighbours already (those it heard
        # forward the beacons): handover candidates before any partial arrives.
        known = {
            n: (u.t, 0, u.rssi)
            for n, u in p.tree.neighbours(g)
            if s.role is Role.MEMBER and s.gid == gid and n != s.leader
        }
        p.lineage.leading(g, cause)
        me = self._kit.ctx.node_id
        s.join(Role.LEADER, gid, me, weight, seq)
        p.tree.clear(g, leading=True)
        p.pace.lead(g)
        p.handovers.seed(g, known)
        p.liveness.clear(g)
        self._kit.ctx.emit(LeaderElected(me, g, gid, weight, cause, now))
        self._entered(now)
        p.pace.beacon(s, now)

    def leave(self, s: Standing, now: float, reason: LeaveReason, into: int = 0) -> None:
        g = s.gtype
        gid = s.gid
        p = self._p
        p.lineage.left(g, gid, s.weight, reason, into, now)
        for tick in _LEAVING_STOPS:
            self._kit.timers.cancel((tick, g))
        s.move_to(Role.IDLE)
        p.liveness.clear(g)
        p.tree.clear(g)
        p.handovers.clear(g)
        self._kit.ctx.emit(GroupLeft(self._kit.ctx.node_id, g, gid, reason, now))

    def _shares(self) -> tuple[PerType, ...]:
        p = self._p
        return (p.lineage, p.pace, p.tree, p.flood, p.election, p.liveness, p.handovers)

    def _become_member(self, s: Standing, gid: int, h: Heard, now: float) -> None:
        """Member of ``gid`` by the beacon ``h`` (heard at ``h.t``)."""
        g = s.gtype
        heard_at = h.t
        p = self._p
        p.election.quit(g)
        s.join(Role.MEMBER, gid, h.leader, h.weight, h.seq)
        p.tree.start_member(g, h.src, h.hops, h.seq, heard_at, h.rssi)
        p.flood.joined(g)
        p.handovers.seed(g, {})
        p.pace.follow(g, heard_at)
        p.liveness.start_member(s, h.src, heard_at)  # after follow: the timeout in its gap
        self._kit.ctx.emit(GroupJoined(self._kit.ctx.node_id, g, gid, h.leader, now))
        self._entered(now)
