"""Flood: a member's forward of each new beacon of its group, once, and its
suppression; and the re-sent beacon that answers a lighter contender.

A leaf (no child named us or sent us a partial lately) that heard
``beacon_forward_cover`` copies of the current seq from members at least as
far out as it is skips its forward (counter-based flooding). Parents always
forward, so that the tree and its hop counts stay put and a child that hears no
other member keeps its group (docs/protocol-groups.md, "Quiet beacons").
"""

from __future__ import annotations

from dataclasses import dataclass, field

from awaremw.protocol.frames import BROADCAST, LeaderBeacon
from awaremw.protocol.groups.kit import Kit
from awaremw.protocol.groups.pace import Pace
from awaremw.protocol.groups.standing import Standing
from awaremw.protocol.groups.tree import GroupTree
from awaremw.protocol.groups.values import MAX_COPIES, Role, Tick


@dataclass(slots=True)
class _Forwards:
    forwarded: bool = True  # the current seq was re-broadcast (our hop count is public)
    # Copies of the current seq heard before our own forward, (sender, its hops):
    # counter-based suppression (see Flood.on_timer).
    copies: list[tuple[int, int]] = field(default_factory=list)
    must_forward: bool = False  # the beacon we joined on announces the group: no suppression
    rebutted: float = float("-inf")  # last re-broadcast answering a lighter group's beacon


class Flood:
    """The beacon forwards of every group type (the ``fwd`` and ``rebut`` timers)."""

    def __init__(self, kit: Kit, tree: GroupTree, pace: Pace) -> None:
        self._kit = kit
        self._tree = tree
        self._pace = pace
        self._at: dict[int, _Forwards] = {}

    def add(self, gtype: int) -> None:
        self._at[gtype] = _Forwards()

    def drop(self, gtype: int) -> None:
        del self._at[gtype]

    def forwarded(self, gtype: int) -> bool:
        """Our hop count of the current seq is on the air."""
        return self._at[gtype].forwarded

    def joined(self, gtype: int) -> None:
        # announce() clears it: a new member forwards the beacon it joined on.
        self._at[gtype].forwarded = True

    def announce(self, s: Standing, now: float, must: bool) -> None:
        """A new seq (or a group just joined) to forward; ``must``: the beacon
        announces a group nearby motes may not know yet, never suppressed."""
        fw = self._at[s.gtype]
        fw.forwarded = False
        fw.copies, fw.must_forward = [], must
        name = (Tick.FWD, s.gtype)
        timers = self._kit.timers
        if name not in timers:
            # The weaker the first copy's link, the longer we wait (one forward
            # jitter per band below group_link_rssi_floor): a copy over a better
            # link usually arrives meanwhile and can still become the parent.
            j = self._kit.ctx.config.forward_jitter
            band = self._tree.parent_band(s.gtype)
            timers.set(name, now + band * j + self._kit.ctx.rng.uniform(0, j))

    def copy_heard(self, gtype: int, src: int, hops: int) -> None:
        """Another member's copy of the current seq (``hops``: its frame's)."""
        fw = self._at[gtype]
        if not fw.forwarded and len(fw.copies) < MAX_COPIES:
            fw.copies.append((src, hops))

    def on_timer(self, s: Standing, now: float) -> None:
        """The forward of the current seq is due."""
        if self._covered(s, now):
            # A leaf, and members at least as far out as we are already carried
            # this seq to our neighbourhood: skip ours.
            self._kit.stats.beacons_suppressed += 1
        else:
            self.forward(s)

    def forward(self, s: Standing, count: bool = True) -> None:
        self._at[s.gtype].forwarded = True
        kit = self._kit
        # Built at send time: carries the best hop count learnt during the jitter.
        kit.send(
            LeaderBeacon(
                kit.ctx.node_id,
                BROADCAST,
                s.gtype,
                s.gid,
                s.leader,
                s.weight,
                s.seq,
                0 if s.role is Role.LEADER else self._tree.route(s.gtype)[1],
                parent=self.named_parent(s.gtype),
            )
        )
        if count:
            kit.stats.beacons_forwarded += 1
        else:
            kit.stats.beacons_rebutted += 1

    def named_parent(self, gtype: int) -> int:
        """The parent our forward names: only one we depend on (the only member we
        heard this seq from), which then keeps forwarding for us. A member that
        heard others too ties no parent down (docs/protocol-groups.md)."""
        p, _hops = self._tree.route(gtype)
        if p is None or any(src != p for src, _ in self._at[gtype].copies):
            return BROADCAST
        return p

    def rebut(self, s: Standing, now: float) -> None:
        """A lighter contender (another group of our type, or a lighter leader of
        our id) is in range: re-send our current beacon soon, at most twice a beacon
        period, so that it yields within a flood rather than a beacon period."""
        if s.role is Role.LEADER:
            self._pace.unsettle(s.gtype)  # a contender in range: beacon at the base period
        fw = self._at[s.gtype]
        if now - fw.rebutted < 0.5 * self._kit.ctx.config.beacon_period:
            return
        if s.role is Role.MEMBER and self._pace.stale(s.gtype, now):
            return  # our own news is stale: do not hold a new group back with it
        fw.rebutted = now
        self._kit.soon((Tick.REBUT, s.gtype), now)

    def answer(self, gtype: int, now: float) -> None:
        """One more copy of our beacon after the forward, to a would-be group heard
        before we joined (see Election.answer)."""
        self._at[gtype].rebutted = now
        j = self._kit.ctx.config.forward_jitter
        self._kit.timers.set((Tick.REBUT, gtype), now + self._kit.ctx.rng.uniform(j, 2 * j))

    def _covered(self, s: Standing, now: float) -> bool:
        """Skip our forward of the current seq? Only a leaf (no child lately) that
        heard ``beacon_forward_cover`` copies from members at least as far from the
        leader as we are (not our parent)."""
        fw = self._at[s.gtype]
        k = self._kit.ctx.config.beacon_forward_cover
        if k <= 0 or fw.must_forward or self._tree.has_child(s.gtype, now):
            return False
        parent, hops = self._tree.route(s.gtype)
        return sum(1 for src, h in fw.copies if h >= hops and src != parent) >= k
