"""Channels (paper II-B, IV-D..F): sampling, TAG-style epochs, in-network aggregation.

A channel ``(attr, group type|any, group id|any, period, agg)`` makes every
member of a matching group sample ``attr`` once per epoch and send one partial
aggregate up its group tree; the leader does the final aggregation and hands
one :class:`~awaremw.protocol.frames.DataRecord` per epoch to the collection
tree (and emits :class:`RecordProduced`).

Epochs are ``e = floor(now / period)`` on the fleet's shared clock (the
emulation shares time the way FTSP would). Within an epoch the period is cut
into ``max_group_depth + 1`` slots, TAG style: a mote ``h`` hops from its
leader samples at the epoch start and sends in slot ``D - h`` (deeper motes
first, at a uniform offset in the first ``slot_jitter`` (0.8) of the slot, so
that the motes of one ring rarely contend for the channel at once; the rest
is left for CSMA and retries), merging whatever its children sent before; the
leader finalises in the middle of slot ``D``.
An epoch runs on the group tree as it stood when it began at this mote: its
partial goes to that parent in that slot, whatever beacon arrives meanwhile
(every member does the same, so an epoch's partials meet on one tree), unless
a unicast to that parent failed since.
A partial that arrives after its receiver already sent is forwarded on alone
(and counted as late); one that reaches the leader after the record went out
is counted and dropped.

Partials are unicast to the parent. A unicast that fails after the driver's
ACK retries is dropped and counted, NOT resent through another neighbour: an
unacknowledged frame has often been delivered (its ACKs were lost), and a
second copy would count its readings twice, so a record's ``count`` would no
longer say how many readings it includes. Instead the group component moves
the parent to another neighbour that forwarded the current beacon, so the
next partials take another way (see docs/protocol-groups.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from awaremw.protocol import aggregation
from awaremw.protocol.collection import Collection
from awaremw.protocol.component import Component, MoteContext
from awaremw.protocol.events import ChannelRefused, RecordProduced
from awaremw.protocol.frames import (
    ANY_GROUP_ID,
    ANY_GROUP_TYPE,
    ChannelDef,
    DataRecord,
    Frame,
    ItemBody,
    Partial,
)
from awaremw.protocol.groups import Groups, Membership

MAX_CHANNEL_ID = 0xFF
KEEP_EPOCHS = 3  # pending state kept this many epochs back (late partials)
LEAF_EPOCHS = 2  # epochs without a child's partial after which a member is a leaf

_Key = tuple[int, int, int, int]  # (channel, group type, group id, epoch)


@dataclass
class ChannelStats:
    samples: int = 0
    unavailable: int = 0  # the attribute could not be read (None or not finite)
    partials_sent: int = 0
    partials_received: int = 0
    merged: int = 0
    late_forwarded: int = 0
    late_dropped: int = 0  # reached the leader after its record went out
    link_dropped: int = 0  # unacknowledged after the link layer's retries
    orphan_dropped: int = 0  # sender left its group before its slot
    foreign_dropped: int = 0  # for a group this mote is not in (any more)
    bad_partials: int = 0  # unknown channel/function, wrong state shape, absurd epoch
    records: int = 0
    records_refused: int = 0  # collection.submit said no
    refused: int = 0


@dataclass(slots=True)
class _Pending:
    agg: int
    # The group tree when the epoch began here: its partial goes to this parent
    # (None: the current one) in this hop count's slot.
    parent: int | None
    hops: int
    count: int = 0
    state: tuple[float, ...] = ()
    sent: bool = False  # sent up (member) or finalised (leader)


def channel_matches(d: ChannelDef, m: Membership) -> bool:
    return (d.group_type in (ANY_GROUP_TYPE, m.group_type)) and (
        d.group_id in (ANY_GROUP_ID, m.group_id)
    )


class Channels(Component):
    """The channels of one mote."""

    def __init__(self, ctx: MoteContext, groups: Groups, collection: Collection) -> None:
        super().__init__(ctx)
        self.groups = groups
        self.collection = collection
        self.stats = ChannelStats()
        self._defs: dict[int, ChannelDef] = {}
        self._next_epoch: dict[int, int] = {}  # channels whose epoch timer is armed
        self._pending: dict[_Key, _Pending] = {}
        # (channel, group type) -> the last epoch a child's partial came for (or the
        # first epoch scheduled): a member that had none for LEAF_EPOCHS epochs
        # since is a leaf (_send_time).
        # Bounded by the channels defined times the group types held.
        self._fed: dict[tuple[int, int], int] = {}
        # Epochs tick only while this mote is in a group: in a large field most
        # motes are in none, and their timers all firing at each epoch boundary
        # were work for nothing (10,000 at once every 2 s at 10,000 motes).
        groups.on_enter = self._wake

    # ----------------------------------------------------------------- public API

    def define(self, channel_id: int, item: ItemBody | None, now: float) -> None:
        """A channel was defined, changed (effective at once) or deleted (``None``)."""
        if item is None:
            self._stop(channel_id)
            self._defs.pop(channel_id, None)
            return
        if not isinstance(item, ChannelDef):
            raise TypeError(f"channel {channel_id} defined with a {type(item).__name__}")
        reason = None
        if not 0 <= channel_id <= MAX_CHANNEL_ID:
            reason = f"channel id {channel_id} is not in 0..{MAX_CHANNEL_ID}"
        elif aggregation.get(item.agg) is None:
            reason = f"unknown aggregation function id {item.agg}"
        elif channel_id not in self._defs and len(self._defs) >= self.ctx.config.max_channels:
            reason = f"more than {self.ctx.config.max_channels} channels"
        if reason is not None:
            self.stats.refused += 1
            self.ctx.emit(ChannelRefused(self.ctx.node_id, channel_id, reason))
            return
        if self._defs.get(channel_id) == item:
            return  # the same definition again: keep the epochs running
        self._stop(channel_id)
        self._defs[channel_id] = item
        if self.groups.memberships():
            self._arm(channel_id, now)

    def period(self, channel_id: int) -> float:
        """Sampling period in seconds (never below ``min_period_s``)."""
        return max(self._defs[channel_id].period_ms / 1000.0, self.ctx.config.min_period_s)

    def defined(self) -> dict[int, ChannelDef]:
        return dict(self._defs)

    def slot_time(self, channel_id: int, epoch: int, hops: int) -> float:
        """When a mote ``hops`` from its leader sends (0: when the leader finalises)."""
        p = self.period(channel_id)
        d = max(1, self.ctx.config.max_group_depth)
        slot = p / (d + 1)
        start = epoch * p
        if hops <= 0:
            return start + (d + 0.5) * slot
        return start + (d - min(hops, d)) * slot

    # ----------------------------------------------------------------- hooks

    def on_timer(self, name: object, now: float) -> None:
        assert isinstance(name, tuple)
        kind = name[0]
        if kind == "epoch":
            self._epoch(name[1], now)
        elif kind == "send":
            self._send(name[1], now)
        elif kind == "final":
            self._final(name[1], now)

    def on_frame(self, frame: Frame, rssi_dbm: float, now: float) -> None:
        if isinstance(frame, Partial):
            self._on_partial(frame, now)

    def on_link_result(self, frame: Frame, acked: bool, now: float) -> None:
        if not isinstance(frame, Partial):
            return
        if acked:
            self.groups.parent_acked(frame.group_type, frame.dst, now)
            return
        self.stats.link_dropped += 1
        self.groups.parent_failed(frame.group_type, frame.dst, now)
        for key, p in self._pending.items():
            if key[1] == frame.group_type and p.parent == frame.dst:
                p.parent = None  # pending epochs follow the tree the group moved to

    # ----------------------------------------------------------------- epochs

    def _arm(self, channel_id: int, now: float) -> None:
        """Tick ``channel_id``'s epochs from the next boundary after ``now``."""
        p = self.period(channel_id)
        e = math.floor(now / p) + 1
        self._next_epoch[channel_id] = e
        self.timers.set(("epoch", channel_id), e * p)

    def _wake(self, now: float) -> None:
        """This mote entered a group: every channel not ticking starts its epochs."""
        for cid in self._defs:
            if cid not in self._next_epoch:
                self._arm(cid, now)

    def _stop(self, channel_id: int) -> None:
        self.timers.cancel(("epoch", channel_id))
        self._next_epoch.pop(channel_id, None)
        for fed in [k for k in self._fed if k[0] == channel_id]:
            del self._fed[fed]
        for key in [k for k in self._pending if k[0] == channel_id]:
            self._forget(key)

    def _forget(self, key: _Key) -> None:
        del self._pending[key]
        self.timers.cancel(("send", key))
        self.timers.cancel(("final", key))

    def _epoch(self, cid: int, now: float) -> None:
        d = self._defs.get(cid)
        if d is None:
            return
        e = self._next_epoch[cid]
        if self._pending:
            for key in [k for k in self._pending if k[0] == cid and k[3] < e - KEEP_EPOCHS]:
                self._forget(key)
        ms = self.groups.memberships()
        if not ms and not any(k[0] == cid for k in self._pending):
            del self._next_epoch[cid]  # in no group: no more epochs until it enters one (_wake)
            return
        self._next_epoch[cid] = e + 1
        self.timers.set(("epoch", cid), (e + 1) * self.period(cid))
        if not ms:
            return
        agg = aggregation.by_id(d.agg)
        for m in ms.values():
            if not channel_matches(d, m):
                continue
            key = (cid, m.group_type, m.group_id, e)
            p = self._pending.get(key)
            if p is None:
                p = self._pending[key] = _Pending(d.agg, m.parent, m.hops)
            v = self.ctx.read(d.attr, now)
            if v is None or not math.isfinite(v):
                self.stats.unavailable += 1
            else:
                self.stats.samples += 1
                part = agg.init(v)
                p.count, p.state = part if p.count == 0 else agg.merge((p.count, p.state), part)
            self._schedule(key, m)

    def _schedule(self, key: _Key, m: Membership) -> None:
        cid, gtype, _, e = key
        if m.is_leader:
            self.timers.set(("final", key), self.slot_time(cid, e, 0))
        elif ("send", key) not in self.timers:
            p = self._pending[key]
            # A mote new to the channel counts as fed now: a parent until proven a leaf.
            leaf = e - self._fed.setdefault((cid, gtype), e) > LEAF_EPOCHS
            self.timers.set(("send", key), self._send_time(cid, e, p.hops, leaf))

    def _send_time(self, cid: int, epoch: int, hops: int, leaf: bool = False) -> float:
        """A member's send time: its slot, plus a uniform offset in the slot's jitter.

        A leaf (no child's partial for LEAF_EPOCHS epochs) merges nothing, so it
        sends at a uniform time from the epoch's start to the end of its slot's
        jitter: a dense group's leaves no longer crowd into their ring's slot
        (romeo4r, every mote in one group, a count every second: 29 % of the
        partials were lost after the link layer's retries). A child it gains
        meanwhile has its partial forwarded on alone (late_forwarded).

        Members deeper than ``max_group_depth`` share the first slot with the
        members at that depth: they send in its first half, those at the depth
        in its second half, so that a partial from one hop deeper still merges.
        """
        cfg = self.ctx.config
        d = max(1, cfg.max_group_depth)
        period = self.period(cid)
        slot = period / (d + 1)
        frac = min(max(cfg.slot_jitter, 0.0), 1.0)
        t = self.slot_time(cid, epoch, hops)
        if hops >= d:
            half = slot / 2
            return t + (0.0 if hops > d else half) + self.ctx.rng.uniform(0, half * frac)
        if leaf:
            start = epoch * period
            return start + self.ctx.rng.uniform(0, t + slot * frac - start)
        return t + self.ctx.rng.uniform(0, slot * frac)

    def _claim(self, key: _Key) -> tuple[_Pending, Membership] | None:
        """The epoch's unsent partial and the membership it is still for, or None.

        A mote that left the group since the epoch started drops its partial
        (counted): it no longer has a route up that group's tree.
        """
        p = self._pending.get(key)
        if p is None or p.sent:
            return None
        _, gtype, gid, _ = key
        m = self.groups.membership(gtype)
        if m is None or m.group_id != gid:
            p.sent = True
            if p.count:
                self.stats.orphan_dropped += 1
            return None
        return p, m

    def _send(self, key: _Key, now: float) -> None:
        claimed = self._claim(key)
        if claimed is None:
            return
        p, m = claimed
        cid, gtype, gid, e = key
        if m.is_leader:  # took the group over since the epoch started
            self._final(key, now)
            return
        p.sent = True
        parent = m.parent if p.parent is None else p.parent
        if p.count == 0 or parent is None:
            return
        self._send_partial(
            Partial(self.ctx.node_id, parent, cid, gtype, gid, e, p.agg, p.count, p.state)
        )

    def _send_partial(self, frame: Partial) -> None:
        self.stats.partials_sent += 1
        self.send(frame)

    def _final(self, key: _Key, now: float) -> None:
        claimed = self._claim(key)
        if claimed is None:
            return
        p, m = claimed
        cid, gtype, gid, e = key
        if not m.is_leader:  # handed over or yielded within the group id: pass it up
            self._send(key, now)
            return
        p.sent = True
        if p.count == 0:
            return
        agg = aggregation.get(p.agg)
        value = None if agg is None else agg.result(p.count, p.state)
        if value is None or not math.isfinite(value):
            self.stats.bad_partials += 1
            return
        record = DataRecord(
            cid, gtype, gid, e, p.agg, value, min(p.count, 0xFFFFFFFF), self.ctx.node_id
        )
        self.stats.records += 1
        if not self.collection.submit(record, now):
            self.stats.records_refused += 1
        self.ctx.emit(RecordProduced(record, now))
        self.groups.add_weight(gtype, p.count)

    # ----------------------------------------------------------------- partials

    def _on_partial(self, f: Partial, now: float) -> None:
        self.stats.partials_received += 1
        d = self._defs.get(f.channel)
        agg = aggregation.get(f.agg)
        if (
            d is None
            or f.agg != d.agg
            or agg is None
            or not agg.valid_state(f.state)
            or f.count == 0
            or f.epoch * self.period(f.channel) > now + self.period(f.channel)
        ):
            self.stats.bad_partials += 1
            return
        m = self.groups.membership(f.group_type)
        if m is None or m.group_id != f.group_id:
            self.stats.foreign_dropped += 1
            return
        self.groups.note_child(f.group_type, f.src, now, f.count)
        fed = (f.channel, f.group_type)
        if f.epoch > self._fed.get(fed, f.epoch - 1):
            self._fed[fed] = f.epoch
        key = (f.channel, f.group_type, f.group_id, f.epoch)
        p = self._pending.get(key)
        if p is None and now < self.slot_time(f.channel, f.epoch, m.hops):
            p = self._pending[key] = _Pending(f.agg, m.parent, m.hops)
            self._schedule(key, m)
        if p is not None and not p.sent:
            self.stats.merged += 1
            part = (f.count, f.state)
            p.count, p.state = part if p.count == 0 else agg.merge((p.count, p.state), part)
            return
        if m.is_leader or m.parent is None or m.parent == f.src:
            self.stats.late_dropped += 1
            return
        self.stats.late_forwarded += 1
        self._send_partial(replace(f, src=self.ctx.node_id, dst=m.parent))
