"""Liveness: a member's evidence that its leader lives, its suspicion, the
claim of a lost leader's group (failover with the same id) and, later, the
split (docs/protocol-groups.md, "Leader death").

Evidence of life: a new seq, a beacon heard from the leader itself, or an
acknowledged unicast to it. A partial the leader did not acknowledge after the
link retries (the data path as failure detector, as CTP does) makes the member
suspect it; no new seq for ``leader_timeout_periods`` gaps seen loses it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from awaremw.protocol.events import ElectionCause, LeaveReason
from awaremw.protocol.frames import LeaderBeacon
from awaremw.protocol.groups.conditions import Conditions
from awaremw.protocol.groups.election import Election
from awaremw.protocol.groups.flood import Flood
from awaremw.protocol.groups.kit import Kit, Moves
from awaremw.protocol.groups.lineage import Lineage
from awaremw.protocol.groups.pace import Pace
from awaremw.protocol.groups.standing import Standing
from awaremw.protocol.groups.tree import GroupTree
from awaremw.protocol.groups.values import Tick


@dataclass(slots=True)
class _Pulse:
    leader_ok: float = -math.inf  # last evidence it lives: a new seq, or an acked unicast to it
    leader_direct: float = -math.inf  # last time we heard it directly or it acked us
    suspect_at: float | None = None  # a unicast to the leader failed at this time
    patience: bool = False  # the split route's extra beacon period was granted for this seq


class Liveness:
    """Failure detection of the leaders of every group type (the ``lost`` and
    ``claim`` timers)."""

    def __init__(
        self,
        kit: Kit,
        parts: tuple[Conditions, Pace, GroupTree, Flood],
        lineage: Lineage,
        election: Election,
    ) -> None:
        self._kit = kit
        self._conditions, self._pace, self._tree, self._flood = parts
        self._lineage = lineage
        self._election = election
        self._at: dict[int, _Pulse] = {}

    def add(self, gtype: int) -> None:
        self._at[gtype] = _Pulse()

    def drop(self, gtype: int) -> None:
        del self._at[gtype]

    def start_member(self, s: Standing, src: int, heard_at: float) -> None:
        """A member by a beacon ``src`` forwarded, heard at ``heard_at``."""
        p = self._at[s.gtype]
        p.patience = False
        p.suspect_at = None
        p.leader_ok = heard_at
        p.leader_direct = heard_at if src == s.leader else -math.inf
        self._kit.timers.cancel((Tick.CLAIM, s.gtype))
        self.arm(s.gtype, heard_at)

    def clear(self, gtype: int) -> None:
        """No leader to suspect (the mote leads, or left)."""
        self._at[gtype].suspect_at = None

    def arm(self, gtype: int, heard_at: float) -> None:
        """A new seq heard at ``heard_at``: the leader is lost a timeout later."""
        self._kit.timers.set((Tick.LOST, gtype), heard_at + self._pace.member_timeout(gtype))

    def heard_leader(self, gtype: int, now: float) -> None:
        """The leader itself was heard (its own beacon)."""
        self._at[gtype].leader_direct = now

    def new_seq(self, s: Standing, f: LeaderBeacon, now: float) -> None:
        """A newer beacon of our group (``s`` not updated yet): the leader lives."""
        p = self._at[s.gtype]
        if f.leader != s.leader:
            p.leader_direct = now if f.src == f.leader else -math.inf
        p.leader_ok = now
        self._clear_suspicion(s.gtype)
        p.patience = False

    def acked(self, s: Standing, node: int, now: float) -> None:
        """A unicast to ``node`` was acknowledged: if it is our leader, it lives."""
        if node != s.leader:
            return
        p = self._at[s.gtype]
        p.leader_ok = p.leader_direct = now
        self._clear_suspicion(s.gtype)

    def suspect(self, s: Standing, now: float) -> None:
        """A partial to the leader was not acknowledged after the link retries.
        Claim the group unless the leader gave a sign of life within
        ``_claim_after``; then claim when that evidence gets stale, unless new
        evidence arrives meanwhile."""
        p = self._at[s.gtype]
        if p.suspect_at is None:
            p.suspect_at = now
            if self._pace.gap(s.gtype) > self._kit.ctx.config.beacon_period:
                # A settled leader beacons rarely: our ACKs are most of the signs
                # of life we get, and one partial lost to a collision is no death.
                # Ask it at once (a copy of its beacon, unicast: it acknowledges
                # it like any frame, and takes it as a member's forward) rather
                # than wait an epoch for the next partial; claim if that fails too.
                self._probe(s)
                return
        at = max(now, p.leader_ok + self._claim_after())
        self._schedule_claim(s.gtype, at)

    def on_claim(self, s: Standing, now: float, moves: Moves) -> None:
        p = self._at[s.gtype]
        if p.suspect_at is not None and p.leader_ok > p.suspect_at:
            p.suspect_at = None  # the leader gave a sign of life meanwhile
            return
        # Take over the group of the lost leader with its id: beacon seq + 1, the
        # group's weight as last heard (docs/protocol-groups.md, Failover).
        if not self._conditions.qualifies(s.defn, True, now):
            moves.leave(s, now, LeaveReason.CONDITION)
            return
        self._kit.stats.failovers += 1
        moves.become_leader(s, s.gid, s.weight, s.seq, now, ElectionCause.FAILOVER)

    def on_lost(self, s: Standing, now: float, moves: Moves) -> None:
        """No new seq for the member timeout."""
        p = self._at[s.gtype]
        neighbour = now - p.leader_direct <= 2 * self._kit.timeout()
        if neighbour and self._conditions.qualifies(s.defn, True, now):
            # We heard the leader directly: most likely it died (a split leaves
            # its neighbours on its side). Take over with the id, after a jitter.
            p.suspect_at = p.suspect_at if p.suspect_at is not None else now
            self._schedule_claim(s.gtype, now)
            return
        if not p.patience:
            # Hysteresis in time on the split route: one more beacon period as a
            # member (a thin, flapping bridge to the leader often carries the next
            # beacon) before the group is given up for a new one.
            p.patience = True
            self._kit.timers.set((Tick.LOST, s.gtype), now + self._pace.gap(s.gtype))
            return
        dead = s.gid
        self._lineage.lost_leader(s.gtype, dead, now)  # named by the group created now
        moves.leave(s, now, LeaveReason.LEADER_LOST)
        self._election.forget(s.gtype, dead)
        if self._conditions.qualifies(s.defn, True, now):
            moves.join_or_wait(s, now, ElectionCause.ELECTION)

    def _probe(self, s: Standing) -> None:
        kit = self._kit
        kit.stats.leader_probes += 1
        kit.send(
            LeaderBeacon(
                kit.ctx.node_id, s.leader, s.gtype, s.gid, s.leader, s.weight, s.seq,
                self._tree.route(s.gtype)[1], parent=self._flood.named_parent(s.gtype),
            )
        )  # fmt: skip

    def _claim_after(self) -> float:
        """Hysteresis in time: a leader heard from this recently is not suspected."""
        return 1.25 * self._kit.ctx.config.beacon_period

    def _schedule_claim(self, gtype: int, at: float) -> None:
        # A jitter of a few frame times: neighbours of the dead leader that detect
        # the loss together mostly hear the first claim and adopt it.
        self._kit.soon((Tick.CLAIM, gtype), at, spread=2.0)

    def _clear_suspicion(self, gtype: int) -> None:
        self._at[gtype].suspect_at = None
        self._kit.timers.cancel((Tick.CLAIM, gtype))
