"""Handovers: a leader that stops qualifying hands its group to a member
neighbour, best candidate first; a candidate takes it or sends the Handover
back (a refusal) (docs/protocol-groups.md, "Handover").

Candidates are the leader's member neighbours: those it heard forward its
beacons and those that sent it partials, ranked by freshness, readings, link.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from awaremw.protocol.events import ElectionCause, HandoverSent, LeaveReason
from awaremw.protocol.frames import GroupStatus, Handover
from awaremw.protocol.groups.conditions import Conditions
from awaremw.protocol.groups.kit import Kit, Moves
from awaremw.protocol.groups.pace import Pace
from awaremw.protocol.groups.standing import Standing
from awaremw.protocol.groups.values import Role, Tick, seq_newer

# A member neighbour of a leader: (last heard, readings in its partial, link RSSI).
Child = tuple[float, int, float]


@dataclass(slots=True)
class _Succession:
    children: dict[int, Child] = field(default_factory=dict)  # handover candidates
    candidates: list[int] = field(default_factory=list)  # yet to ask, best first
    handover_to: int | None = None
    handed: tuple[int, int] | None = None  # (group id, seq) of our last Handover
    early: bool = False  # handing over while still qualifying (relaxed): may stay
    early_after: float = -math.inf  # no early handover before (one found no taker)
    predecessor: int | None = None  # leader by handover: the node that handed us the group


class Handovers:
    """Handover of every group type (the ``handover`` timer's owner)."""

    def __init__(self, kit: Kit, conditions: Conditions, pace: Pace) -> None:
        self._kit = kit
        self._conditions = conditions
        self._pace = pace
        self._at: dict[int, _Succession] = {}
        self._echoed: tuple[int, int, int, int] | None = None  # last refusal sent back

    def add(self, gtype: int) -> None:
        self._at[gtype] = _Succession()

    def drop(self, gtype: int) -> None:
        del self._at[gtype]

    def seed(self, gtype: int, known: dict[int, Child]) -> None:
        """The member neighbours known when the mote enters a group."""
        h = self._at[gtype]
        h.children = known
        h.predecessor = None

    def from_predecessor(self, gtype: int, leader: int, seq: int, our_seq: int) -> bool:
        """A beacon of our id from the leader that handed us the group, not newer
        than ours: a copy of its last beacons still on the way, not a claimant."""
        h = self._at[gtype]
        return leader == h.predecessor and not seq_newer(seq, our_seq)

    def clear(self, gtype: int) -> None:
        """The mote left its group."""
        h = self._at[gtype]
        h.children = {}
        h.candidates = []
        h.handover_to = None

    def note_child(self, gtype: int, node: int, now: float, count: int) -> None:
        """A partial of ``count`` readings came from ``node`` (we lead)."""
        self._at[gtype].children[node] = (now, count, self._kit.link_rssi(node, -math.inf))

    def heard_member(self, gtype: int, src: int, rssi: float, now: float) -> None:
        """A member re-broadcasting our own beacon, heard directly: a member
        neighbour (whatever its hops), hence a handover candidate."""
        children = self._at[gtype].children
        old = children.get(src)
        count = 0 if old is None else old[1]
        children[src] = (now, count, self._kit.link_rssi(src, rssi))

    def start(self, s: Standing, now: float, moves: Moves, early: bool = False) -> None:
        """The leader stopped qualifying: hand the group over. ``early``: it still
        qualifies with the hysteresis but no longer without (it is at the group's
        edge, leaving it): hand over to a member heard lately, stay if none takes
        the group (docs/protocol-groups.md, "Handover")."""
        h = self._at[s.gtype]
        if early and now < h.early_after:
            return
        fresh_for = 1.5 * self._kit.ctx.config.beacon_period
        ttl = self._kit.timeout()
        floor = self._kit.ctx.config.group_link_rssi_floor
        ranked = sorted(
            (
                (now - t <= fresh_for, count, rssi >= floor, t, n)
                for n, (t, count, rssi) in h.children.items()
                if now - t <= ttl
            ),
            reverse=True,
        )
        h.candidates = [n for fresh, *_, n in ranked if fresh or not early]
        if not h.candidates and early:
            return
        h.early = early
        self._kit.timers.cancel((Tick.BEACON, s.gtype))
        s.move_to(Role.HANDING_OVER)
        self._next_candidate(s, now, moves)

    def on_frame(self, s: Standing | None, f: Handover, now: float, moves: Moves) -> None:
        h = None if s is None else self._at[s.gtype]
        if h is not None and h.handed == (f.group_id, f.seq):
            assert s is not None
            # Our own Handover sent back: the candidate cannot take the group.
            if s.role is Role.HANDING_OVER and f.src == h.handover_to:
                self._kit.stats.handovers_failed += 1
                self._next_candidate(s, now, moves)
            return  # else a late refusal of a candidate we gave up on: ignore
        if s is None or not self._can_take(s, f, now):
            self._kit.stats.handovers_refused += 1
            echo = (f.src, f.group_type, f.group_id, f.seq)
            if echo != self._echoed:
                # Tell the leaving leader at once, once (a lost refusal only costs
                # the group its id: members time out and elect a new one).
                self._echoed = echo
                me = self._kit.ctx.node_id
                self._kit.send(Handover(me, f.src, f.group_type, f.group_id, f.weight, f.seq))
            return
        if s.role is Role.LEADER:
            return  # a duplicate of a handover we already took
        member = s.role is Role.MEMBER
        seq = s.seq if member and seq_newer(s.seq, f.seq) else f.seq
        weight = max(f.weight, s.weight) if member else f.weight
        self._kit.stats.handovers_accepted += 1
        moves.become_leader(s, f.group_id, weight, seq, now, ElectionCause.HANDOVER)
        self._at[s.gtype].predecessor = f.src  # after: becoming leader seeds the succession

    def on_link_result(
        self, s: Standing, f: Handover, acked: bool, now: float, moves: Moves
    ) -> None:
        h = self._at[s.gtype]
        if (
            s.role is not Role.HANDING_OVER
            or s.gid != f.group_id
            or f.dst != h.handover_to
            or f.src != self._kit.ctx.node_id
        ):
            return  # a refusal we sent, or a handover overtaken by events
        if acked:
            grace = self._kit.ctx.config.handover_grace
            self._kit.timers.set((Tick.HANDOVER, s.gtype), now + grace)
        else:
            self._kit.stats.handovers_failed += 1
            self._next_candidate(s, now, moves)

    def on_timer(self, s: Standing, now: float, moves: Moves) -> None:
        """Acknowledged and not refused within the grace time: done."""
        to = self._at[s.gtype].handover_to
        assert to is not None
        self._kit.ctx.emit(HandoverSent(self._kit.ctx.node_id, s.gtype, s.gid, to, now))
        moves.leave(s, now, LeaveReason.HANDOVER)

    def purge(self, gtype: int, now: float, ttl: float) -> None:
        children = self._at[gtype].children
        if children:
            for n in [n for n, c in children.items() if now - c[0] > ttl]:
                del children[n]

    def remembers_nothing(self, gtype: int) -> bool:
        return not self._at[gtype].children

    def _next_candidate(self, s: Standing, now: float, moves: Moves) -> None:
        self._kit.timers.cancel((Tick.HANDOVER, s.gtype))
        h = self._at[s.gtype]
        if not h.candidates and h.early:
            # Nobody took it, and we still qualify (relaxed): lead on, and try
            # again a beacon period later.
            h.early, h.handover_to = False, None
            h.early_after = now + self._kit.ctx.config.beacon_period
            s.move_to(Role.LEADER)
            self._pace.resume(s.gtype, now)
            return
        if not h.candidates:
            # Nobody to hand over to: the group is gone; members will elect a new one.
            self._pace.report(s, now, GroupStatus.GONE)
            moves.leave(s, now, LeaveReason.CONDITION)
            return
        n = h.candidates.pop(0)
        h.handover_to = n
        h.handed = (s.gid, s.seq)
        self._kit.stats.handovers_sent += 1
        self._kit.send(Handover(self._kit.ctx.node_id, n, s.gtype, s.gid, s.weight, s.seq))

    def _can_take(self, s: Standing, f: Handover, now: float) -> bool:
        if s.role is Role.LEADER:
            return s.gid == f.group_id
        if s.role is Role.MEMBER:
            return s.gid == f.group_id and self._conditions.qualifies(s.defn, True, now)
        if s.role in (Role.IDLE, Role.WAITING):
            return self._conditions.qualifies(s.defn, False, now)
        return False
