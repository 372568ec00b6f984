"""Merge: what a mote in or near a group makes of a beacon of its type -- the
same group (the tree and the leader's liveness), a heavier group (switch, or a
leader yields: the merge), a lighter one (rebut), another leader of our id
(a failover claim, an id clash or a duplicated handover).

Order of groups: ``(weight, group id)`` (the paper: weight, then the higher
id); of beacons of one id: ``(seq, weight, leader)`` (docs/protocol-groups.md,
"Beacons and the heaviest group").
"""

from __future__ import annotations

from awaremw.protocol.events import LeaderYielded, LeaveReason
from awaremw.protocol.frames import GroupStatus, LeaderBeacon
from awaremw.protocol.groups.election import Election
from awaremw.protocol.groups.flood import Flood
from awaremw.protocol.groups.handover import Handovers
from awaremw.protocol.groups.kit import Kit, Moves
from awaremw.protocol.groups.liveness import Liveness
from awaremw.protocol.groups.pace import Pace
from awaremw.protocol.groups.standing import Standing
from awaremw.protocol.groups.tree import GroupTree
from awaremw.protocol.groups.values import MAX_HOPS, Role, Up, heavier, seq_newer


class Merge:
    """Leader beacons heard, by the role of their group type (stateless: the
    parts keep what a beacon changes)."""

    def __init__(
        self,
        kit: Kit,
        moves: Moves,
        parts: tuple[Pace, GroupTree, Flood, Election, Liveness, Handovers],
    ) -> None:
        self._kit = kit
        self._moves = moves
        self._pace, self._tree, self._flood, self._election, self._liveness, self._handovers = parts

    def on_beacon(self, s: Standing, f: LeaderBeacon, rssi: float, now: float) -> None:
        me = self._kit.ctx.node_id
        if f.leader == me:
            if s.role is Role.LEADER and f.group_id == s.gid:
                self._handovers.heard_member(s.gtype, f.src, rssi, now)
            return
        if f.tentative:
            self._election.on_tentative(s, f, now)
            return
        self._election.note_nearby(s.gtype, f, rssi, now)
        role = s.role
        if role is Role.WAITING:
            self._moves.adopt(s, f, rssi, now)
        elif role is Role.MEMBER:
            if f.group_id == s.gid:
                self._same_group(s, f, rssi, now)
            elif heavier(f.weight, f.group_id, s.weight, s.gid):
                self._moves.leave(s, now, LeaveReason.SWITCHED, into=f.group_id)
                self._moves.adopt(s, f, rssi, now)
            else:
                self._flood.rebut(s, now)
        elif role is Role.LEADER:
            if f.group_id == s.gid and self._handovers.from_predecessor(
                s.gtype, f.leader, f.seq, s.seq
            ):
                return  # our predecessor's last beacons, forwarded: not a contender
            if f.group_id == s.gid:
                # Another leader with our id: a failover claim, an id clash or a
                # duplicated handover. The larger (weight, leader node) keeps it;
                # the winner's next beacon outnumbers the loser's seq.
                if (f.weight, f.leader) > (s.weight, me):
                    self._yield(s, f, rssi, now)
                else:
                    if seq_newer(f.seq, s.seq):
                        s.catch_up(f.seq)
                    self._flood.rebut(s, now)
            elif heavier(f.weight, f.group_id, s.weight, s.gid):
                self._yield(s, f, rssi, now)
            else:
                self._flood.rebut(s, now)

    def _same_group(self, s: Standing, f: LeaderBeacon, rssi: float, now: float) -> None:
        g = s.gtype
        lr = self._kit.link_rssi(f.src, rssi)
        hops = min(f.hops + 1, MAX_HOPS)
        if f.src == f.leader == s.leader:
            self._liveness.heard_leader(g, now)
        # Beacons of one id are ordered by (seq, weight, leader): a newer seq, or
        # the same seq from a heavier claimant (two members took over together).
        newer = seq_newer(f.seq, s.seq) or (
            f.seq == s.seq and f.leader != s.leader
            and (f.weight, f.leader) > (s.weight, s.leader)
        )  # fmt: skip
        if not newer and f.leader != s.leader:
            return  # a stale beacon, or a lighter claimant of our id: not our tree
        if f.parent == self._kit.ctx.node_id:
            # A child took the beacon from us: forward the next seqs for it, for
            # as long as it would wait for one before giving the leader up (a
            # copy or two lost on the way must not starve it). It names us again
            # at each forward while we are all it hears; a child that stops (it
            # left, took another parent, or hears other members) ages out.
            self._tree.note_child(g, now + self._pace.member_timeout(g))
        self._tree.heard(g, f.src, Up(f.seq, f.hops, now, lr))
        if newer:
            # The first copy of a new seq sets the parent ...
            self._liveness.new_seq(s, f, now)
            self._pace.observe(g, f.leader == s.leader, (f.seq - s.seq) & 0xFFFF, now)
            s.follow(f.seq, f.leader, f.weight)
            self._tree.choose_parent(g, f.src, hops, lr, first=True, forwarded=True)
            self._liveness.arm(g, now)
            self._flood.announce(s, now, must=False)
        elif f.seq == s.seq and f.src != self._tree.route(g)[0]:
            # ... a later copy may replace it (GroupTree.choose_parent).
            self._flood.copy_heard(g, f.src, f.hops)
            forwarded = self._flood.forwarded(g)
            self._tree.choose_parent(g, f.src, hops, lr, first=False, forwarded=forwarded)

    def _yield(self, s: Standing, f: LeaderBeacon, rssi: float, now: float) -> None:
        old = s.gid
        self._kit.ctx.emit(LeaderYielded(self._kit.ctx.node_id, s.gtype, old, f.group_id, now))
        if f.group_id != old:
            self._pace.report(s, now, GroupStatus.GONE, successor=f.group_id)
        self._moves.leave(s, now, LeaveReason.YIELDED, into=f.group_id)
        self._moves.adopt(s, f, rssi, now)
