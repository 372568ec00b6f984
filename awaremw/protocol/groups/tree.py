"""GroupTree: a member's way to its leader -- parent, hop count and the group
neighbours that forwarded the current beacon (the partials' way up).

The first copy of a new seq sets the parent; a later copy of the same seq
replaces it if better by :meth:`GroupTree.link_key` (good links first, then
fewest hops), and once our hop count is on the air it may only stay or shrink:
the tree stays loop-free (docs/protocol-groups.md, "The group tree").
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from awaremw.protocol.groups.kit import Kit
from awaremw.protocol.groups.standing import Standing
from awaremw.protocol.groups.values import MAX_HOPS, Up


@dataclass(slots=True)
class _Branch:
    hops: int = 0
    parent: int | None = None
    parent_rssi: float = -math.inf  # link RSSI (EWMA) of the parent when it was chosen
    upstream: dict[int, Up] = field(default_factory=dict)
    failed: dict[int, float] = field(default_factory=dict)  # neighbour -> last failed unicast
    # A member with children forwards every seq until then (see Flood): a child
    # named us in its forward, or sent us a partial, lately.
    child_until: float = -math.inf


class GroupTree:
    """The group tree of every group type, as this mote sees it."""

    def __init__(self, kit: Kit) -> None:
        self._kit = kit
        self._at: dict[int, _Branch] = {}

    def add(self, gtype: int) -> None:
        self._at[gtype] = _Branch()

    def drop(self, gtype: int) -> None:
        del self._at[gtype]

    def route(self, gtype: int) -> tuple[int | None, int]:
        """(parent, hops): the next hop towards the leader and our distance to it."""
        b = self._at[gtype]
        return b.parent, b.hops

    def has_child(self, gtype: int, now: float) -> bool:
        """A child named us or sent us a partial lately: we are a parent."""
        return now <= self._at[gtype].child_until

    def parent_band(self, gtype: int) -> int:
        """The link band of the copy that set the parent (Kit.band)."""
        return self._kit.band(self._at[gtype].parent_rssi)

    def upstream(self, s: Standing) -> list[int]:
        """The parent, then the other neighbours that forwarded the current beacon
        with fewer hops than ours (fewest hops, then strongest first)."""
        b = self._at[s.gtype]
        head = [] if b.parent is None else [b.parent]
        return head + [n for n, _ in self._alternatives(s) if n != b.parent]

    def neighbours(self, gtype: int) -> list[tuple[int, Up]]:
        """The group neighbours heard forwarding our group's beacon lately."""
        return list(self._at[gtype].upstream.items())

    def start_member(
        self, gtype: int, src: int, hops: int, seq: int, heard_at: float, rssi: float
    ) -> None:
        """A member by the beacon ``src`` forwarded with ``hops`` (heard at ``rssi``)."""
        b = self._at[gtype]
        b.hops = min(hops + 1, MAX_HOPS)
        b.parent, b.parent_rssi = src, self._kit.link_rssi(src, rssi)
        b.upstream = {src: Up(seq, hops, heard_at, rssi)}
        b.failed = {}
        b.child_until = -math.inf

    def clear(self, gtype: int, leading: bool = False) -> None:
        """The mote left its group, or leads one (``leading``: the root, 0 hops)."""
        b = self._at[gtype]
        if leading:
            b.hops = 0
        b.parent = None
        b.upstream = {}

    def failed(self, s: Standing, node: int, now: float) -> None:
        """A unicast to ``node`` failed: if it is the parent, the best other neighbour
        of the current beacon takes its place (if there is one)."""
        b = self._at[s.gtype]
        b.failed[node] = now
        if b.parent != node:
            return
        alts = [(n, u) for n, u in self._alternatives(s) if n != node]
        if alts:
            n, u = alts[0]
            b.parent, b.hops, b.parent_rssi = n, u.hops + 1, u.rssi

    def note_child(self, gtype: int, until: float) -> None:
        """A child depends on us until ``until`` (at least)."""
        b = self._at[gtype]
        b.child_until = max(b.child_until, until)

    def heard(self, gtype: int, src: int, up: Up) -> None:
        """``src`` forwarded our group's beacon."""
        self._at[gtype].upstream[src] = up

    def choose_parent(
        self, gtype: int, src: int, hops: int, rssi: float, first: bool, forwarded: bool
    ) -> None:
        """A copy of the current seq from ``src`` (``hops``: ours through it). The
        first copy of a new seq sets the parent; a later one replaces it if better
        by the link key, and, once our hop count is on the air (``forwarded``),
        only if it keeps it or shrinks it (loop freedom)."""
        b = self._at[gtype]
        if first:
            b.hops = hops
            b.parent, b.parent_rssi = src, rssi
            return
        new = self._link_key(b, src, hops, rssi)
        cur = self._link_key(b, b.parent or 0, b.hops, b.parent_rssi)
        if new < cur and (not forwarded or hops <= b.hops):
            b.hops = hops
            b.parent, b.parent_rssi = src, rssi

    def purge(self, gtype: int, now: float, ttl: float) -> None:
        b = self._at[gtype]
        if b.upstream:
            for n in [n for n, u in b.upstream.items() if now - u.t > ttl]:
                del b.upstream[n]
        if b.failed:
            for n in [n for n, t in b.failed.items() if now - t > ttl]:
                del b.failed[n]

    def remembers_nothing(self, gtype: int) -> bool:
        b = self._at[gtype]
        return not (b.upstream or b.failed)

    def _alternatives(self, s: Standing) -> list[tuple[int, Up]]:
        # Only copies of the current seq with fewer hops than ours: a switch never
        # raises our advertised hop count, which keeps the tree loop-free.
        b = self._at[s.gtype]
        ups = [(n, u) for n, u in b.upstream.items() if u.seq == s.seq and u.hops < b.hops]
        ups.sort(key=lambda x: self._link_key(b, x[0], x[1].hops + 1, x[1].rssi))
        return ups

    def _link_key(
        self, b: _Branch, node: int, hops: int, rssi: float
    ) -> tuple[bool, int, int, float]:
        """Order of parent candidates: not failed, link band, fewest hops, strongest."""
        return (node in b.failed, self._kit.band(rssi), hops, -rssi)
