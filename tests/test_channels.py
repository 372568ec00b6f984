"""Unit tests of channels (one component, fake groups, fake clock) and frame sizes."""

from __future__ import annotations

import dataclasses
import random
from typing import Any

import pytest
from scenarios import LOSSLESS, Scenario, in_disc

from awaremw.protocol.attributes import HUMIDITY, TEMPERATURE
from awaremw.protocol.channels import Channels
from awaremw.protocol.config import MiddlewareConfig
from awaremw.protocol.events import ChannelRefused, ItemAdopted, RecordProduced
from awaremw.protocol.frames import (
    ANY_GROUP_ID,
    ANY_GROUP_TYPE,
    BROADCAST,
    MAX_NODE_ID,
    AggId,
    ChannelDef,
    CommandDef,
    Condition,
    CtpData,
    DataRecord,
    DripItem,
    Frame,
    GroupReport,
    GroupStatus,
    GroupTypeDef,
    Handover,
    ItemKind,
    LeaderBeacon,
    Op,
    Partial,
    Payload,
    decode,
    encode,
)
from awaremw.protocol.groups import Membership
from awaremw.protocol.mote import MoteContext
from awaremw.radio.model import PRESETS

T = TEMPERATURE


class App:
    def __init__(self) -> None:
        self.values: dict[int, float | None] = {T: 21.5, HUMIDITY: 40.0}

    def offers(self, attr: int) -> bool:
        return attr in self.values

    def read(self, attr: int, now: float) -> float | None:
        return self.values.get(attr)

    def on_command(self, command: CommandDef, now: float) -> None:
        pass


class FakeGroups:
    def __init__(self) -> None:
        self.ms: dict[int, Membership] = {}
        self.ups: list[int] = []
        self.children: list[tuple[int, int, int]] = []
        self.weight: dict[int, int] = {}
        self.failed: list[tuple[int, int]] = []
        self.acked: list[tuple[int, int]] = []

    def set(self, gtype: int, gid: int, hops: int, parent: int | None = 5) -> None:
        leader = hops == 0
        self.ms[gtype] = Membership(
            gtype, gid, 10 if leader else 1, leader, None if leader else parent, hops, 0
        )

    def membership(self, gtype: int) -> Membership | None:
        return self.ms.get(gtype)

    def memberships(self) -> dict[int, Membership]:
        return dict(self.ms)

    def upstream(self, gtype: int, now: float) -> list[int]:
        return list(self.ups)

    def note_child(self, gtype: int, node: int, now: float, count: int = 0) -> None:
        self.children.append((gtype, node, count))

    def parent_failed(self, gtype: int, node: int, now: float) -> None:
        self.failed.append((gtype, node))

    def parent_acked(self, gtype: int, node: int, now: float) -> None:
        self.acked.append((gtype, node))

    def add_weight(self, gtype: int, n: int) -> None:
        self.weight[gtype] = self.weight.get(gtype, 0) + n


class FakeCollection:
    def __init__(self) -> None:
        self.submitted: list[Payload] = []

    def submit(self, payload: Payload, now: float) -> bool:
        self.submitted.append(payload)
        return True


class H:
    def __init__(self, nid: int = 10, **cfg: Any) -> None:
        self.app = App()
        self.ctx = MoteContext(nid, MiddlewareConfig(**cfg), random.Random(nid), self.app)
        self.groups = FakeGroups()
        self.coll = FakeCollection()
        self.c = Channels(self.ctx, self.groups, self.coll)  # type: ignore[arg-type]
        self.now = 0.0

    def advance(self, t: float) -> None:
        while (d := self.c.timers.next_deadline()) is not None and d <= t:
            self.now = d
            for name in self.c.timers.due(d):
                self.c.on_timer(name, d)
        self.now = t

    def hear(self, f: Frame) -> None:
        self.c.on_frame(f, -70.0, self.now)

    def sent(self) -> list[Frame]:
        out = [decode(tx.frame) for tx in self.ctx.outbox]
        self.ctx.outbox.clear()
        return out

    def records(self) -> list[DataRecord]:
        evs = [e for e in self.ctx.event_list if isinstance(e, RecordProduced)]
        return [e.record for e in evs]


def chan(
    agg: int = AggId.AVG,
    period_ms: int = 2000,
    gtype: int = 1,
    gid: int = ANY_GROUP_ID,
    attr: int = T,
) -> ChannelDef:
    return ChannelDef(attr, gtype, gid, period_ms, agg)


def partial(
    src: int,
    dst: int = 10,
    epoch: int = 1,
    count: int = 1,
    state: tuple[float, ...] = (20.0,),
    agg: int = AggId.AVG,
    gid: int = 500,
    channel: int = 1,
) -> Partial:
    return Partial(src, dst, channel, 1, gid, epoch, agg, count, state)


# --------------------------------------------------------------------------- slots


def test_slots_deeper_first_all_within_the_period() -> None:
    h = H()
    h.c.define(1, chan(), 0.0)
    d = h.ctx.config.max_group_depth
    times = [h.c.slot_time(1, 7, hops) for hops in range(d, 0, -1)] + [h.c.slot_time(1, 7, 0)]
    assert times == sorted(times) and len(set(times)) == len(times)
    assert times[0] >= 14.0 and times[-1] < 16.0
    assert h.c.slot_time(1, 7, d + 5) == h.c.slot_time(1, 7, d)  # deeper motes share slot 0


def test_partials_spread_over_the_slot_jitter_and_leave_the_rest_for_retries() -> None:
    """A ring's members pick their send times over the first ``slot_jitter`` of the
    slot (not half of it): under CSMA, siblings that start within one backoff unit
    of each other collide (docs/protocol-groups.md, "Epochs and slots")."""
    offsets = []
    for nid in range(300):
        h = H(nid)
        h.groups.set(1, 500, hops=2, parent=5)
        h.c.define(1, chan(period_ms=2000), 0.0)
        h.advance(2.0)  # epoch 1 starts: the send timer is set
        t = h.c.timers.get(("send", (1, 1, 500, 1)))
        assert t is not None
        offsets.append(t - h.c.slot_time(1, 1, 2))
    d = MiddlewareConfig().max_group_depth
    slot = 2.0 / (d + 1)
    frac = MiddlewareConfig().slot_jitter
    assert 0.5 < frac < 1.0
    assert min(offsets) >= 0.0 and max(offsets) < frac * slot
    assert max(offsets) > 0.9 * frac * slot  # the whole window is used
    assert sum(o > slot / 2 for o in offsets) > 0.2 * len(offsets)  # beyond half a slot


def test_a_leaf_spreads_its_partial_from_the_epoch_start_and_a_parent_keeps_its_slot() -> None:
    """A member that got no child's partial for LEAF_EPOCHS epochs merges nothing:
    it sends at any time from the epoch's start to the end of its slot's jitter,
    so that a dense group's leaves do not crowd into one slot. A member that did
    (or is new to the channel) waits for its slot, so its children's partials merge."""
    from awaremw.protocol.channels import LEAF_EPOCHS

    period, hops = 2.0, 2
    d = MiddlewareConfig().max_group_depth
    window = (d - hops) * period / (d + 1) + MiddlewareConfig().slot_jitter * period / (d + 1)
    first = LEAF_EPOCHS + 2  # epochs 1..LEAF_EPOCHS+1 without a child: a leaf from here
    leaf, parent = [], []
    for nid in range(200):
        for fed in (False, True):
            h = H(nid)
            h.groups.set(1, 500, hops=hops, parent=5)
            h.c.define(1, chan(period_ms=int(period * 1000)), 0.0)
            for e in range(1, first):
                h.advance(e * period)
                if fed:
                    h.hear(partial(31, epoch=e))
            h.advance(first * period)
            t = h.c.timers.get(("send", (1, 1, 500, first)))
            assert t is not None
            (parent if fed else leaf).append(t - first * period)
    slot_start = h.c.slot_time(1, first, hops) - first * period
    assert min(parent) >= slot_start  # its slot, as before
    assert min(leaf) >= 0.0 and max(leaf) < window
    assert sum(t < slot_start for t in leaf) > 0.5 * len(leaf)  # mostly before the slot


# --------------------------------------------------------------------------- members


def test_member_samples_at_epoch_and_sends_partial_in_its_slot() -> None:
    h = H()
    h.groups.set(1, 500, hops=3, parent=5)
    h.c.define(1, chan(), 0.3)
    h.advance(h.c.slot_time(1, 1, 3) - 0.001)
    assert h.sent() == []
    h.advance(2.0 + 2.0 * 0.99)
    (p,) = h.sent()
    assert isinstance(p, Partial)
    assert (p.dst, p.channel, p.group_type, p.group_id, p.epoch, p.count, p.state) == (
        5,
        1,
        1,
        500,
        1,
        1,
        (21.5,),
    )
    assert p.agg == AggId.AVG


def test_member_merges_children_before_its_slot_and_forwards_late_ones() -> None:
    h = H()
    h.groups.set(1, 500, hops=2, parent=5)
    h.c.define(1, chan(AggId.MAX), 0.0)
    h.advance(2.0)  # epoch 1 starts: own reading
    h.hear(partial(31, epoch=1, count=4, state=(30.0,), agg=AggId.MAX))
    h.hear(partial(32, epoch=1, count=2, state=(25.0,), agg=AggId.MAX))
    assert h.groups.children == [(1, 31, 4), (1, 32, 2)]
    h.advance(4.0 - 0.001)
    (p,) = h.sent()
    assert isinstance(p, Partial) and (p.count, p.state) == (7, (30.0,))
    h.hear(partial(33, epoch=1, count=1, state=(99.0,), agg=AggId.MAX))  # late
    (late,) = h.sent()
    assert isinstance(late, Partial)
    assert (late.src, late.dst, late.count, late.state) == (10, 5, 1, (99.0,))
    assert h.c.stats.late_forwarded == 1 and h.c.stats.merged == 2


def test_an_epoch_runs_on_the_tree_it_began_with() -> None:
    """A beacon mid-epoch (new parent, new hop count) takes effect at the next
    epoch: this epoch's partial goes to the parent, in the slot, it began with,
    so that the children that planned their slots on that tree still merge."""
    h = H()
    h.groups.set(1, 500, hops=2, parent=5)
    h.c.define(1, chan(AggId.SUM), 0.0)
    h.advance(2.0)  # epoch 1 begins: parent 5, hop 2
    h.groups.set(1, 500, hops=1, parent=6)  # a beacon came through a shorter way
    h.advance(h.c.slot_time(1, 1, 2) + 0.001)
    h.hear(partial(31, epoch=1, count=3, state=(9.0,), agg=AggId.SUM))  # a hop-3 child
    assert h.sent() == []
    h.advance(h.c.slot_time(1, 1, 1) - 0.001)  # the end of the hop-2 slot
    (p,) = h.sent()
    assert isinstance(p, Partial) and (p.dst, p.count) == (5, 4)
    assert h.c.stats.late_forwarded == 0
    h.advance(4.0 + h.c.slot_time(1, 1, 0) - 2.0)  # epoch 2: the new tree
    (p,) = h.sent()
    assert isinstance(p, Partial) and (p.dst, p.epoch) == (6, 2)


def test_a_parent_that_failed_is_left_by_the_pending_epochs() -> None:
    h = H()
    h.groups.set(1, 500, hops=2, parent=5)
    h.c.define(1, chan(AggId.SUM), 0.0)
    h.advance(2.0)  # epoch 1 begins on parent 5
    failed = partial(10, dst=5, epoch=0)  # an older epoch's partial to 5 failed ...
    h.groups.set(1, 500, hops=2, parent=6)  # ... and groups moved the parent
    h.c.on_link_result(failed, False, h.now)
    h.advance(3.99)
    (p,) = h.sent()
    assert isinstance(p, Partial) and (p.dst, p.epoch) == (6, 1)


def test_partial_before_own_epoch_start_is_kept_for_the_slot() -> None:
    h = H()
    h.groups.set(1, 500, hops=1, parent=5)
    h.c.define(1, chan(AggId.SUM), 0.0)
    h.advance(1.99)
    h.hear(partial(31, epoch=1, count=3, state=(9.0,), agg=AggId.SUM))
    h.advance(3.99)
    (p,) = h.sent()
    assert isinstance(p, Partial) and (p.count, p.state) == (4, (30.5,))


def test_unavailable_attribute_still_relays_children() -> None:
    h = H()
    h.app.values[T] = None
    h.groups.set(1, 500, hops=1, parent=5)
    h.c.define(1, chan(AggId.SUM), 0.0)
    h.advance(2.0)
    h.hear(partial(31, epoch=1, count=3, state=(9.0,), agg=AggId.SUM))
    h.advance(3.99)
    (p,) = h.sent()
    assert isinstance(p, Partial) and (p.count, p.state) == (3, (9.0,))
    assert h.c.stats.unavailable == 1
    h.advance(5.99)
    assert h.sent() == []  # nothing to say: no empty partial


def test_link_failure_drops_the_partial_and_tells_groups() -> None:
    """No resend through another neighbour: the lost frame may have arrived."""
    h = H()
    h.groups.set(1, 500, hops=2, parent=5)
    h.c.define(1, chan(), 0.0)
    h.advance(3.99)
    (p,) = h.sent()
    assert isinstance(p, Partial) and p.dst == 5
    h.c.on_link_result(p, True, h.now)
    assert h.groups.failed == []
    h.c.on_link_result(p, False, h.now)
    assert h.sent() == [] and h.c.stats.link_dropped == 1
    assert h.groups.failed == [(1, 5)]


def test_member_that_left_its_group_drops_its_partial() -> None:
    h = H()
    h.groups.set(1, 500, hops=2)
    h.c.define(1, chan(), 0.0)
    h.advance(2.0)
    del h.groups.ms[1]
    h.advance(3.99)
    assert h.sent() == [] and h.c.stats.orphan_dropped == 1


def test_foreign_and_malformed_partials_are_counted() -> None:
    h = H()
    h.groups.set(1, 500, hops=1)
    h.c.define(1, chan(), 0.0)
    h.advance(2.0)
    h.hear(partial(31, gid=501))  # another group of the type
    h.hear(partial(31, channel=9))  # unknown channel
    h.hear(partial(31, agg=AggId.MAX))  # not this channel's function
    h.hear(partial(31, state=(1.0, 2.0)))  # wrong state shape
    h.hear(partial(31, epoch=1000))  # far future epoch
    h.hear(partial(31, count=0))
    assert h.c.stats.foreign_dropped == 1 and h.c.stats.bad_partials == 5
    assert h.groups.children == []


# --------------------------------------------------------------------------- leader


def test_leader_finalises_once_per_epoch() -> None:
    h = H()
    h.groups.set(1, 500, hops=0)
    h.c.define(1, chan(AggId.AVG), 0.0)
    h.advance(2.0)
    h.hear(partial(31, epoch=1, count=3, state=(60.0,)))
    h.advance(3.999)
    (r,) = h.records()
    assert r == DataRecord(1, 1, 500, 1, AggId.AVG, (60.0 + 21.5) / 4, 4, 10)
    assert h.coll.submitted == [r]
    assert h.groups.weight == {1: 4}
    assert h.sent() == []
    h.hear(partial(32, epoch=1, count=1, state=(1.0,)))  # after the record went out
    assert h.c.stats.late_dropped == 1
    h.advance(5.999)
    assert [r.epoch for r in h.records()] == [1, 2]


def test_leader_with_no_reading_produces_no_record() -> None:
    h = H()
    h.app.values[T] = None
    h.groups.set(1, 500, hops=0)
    h.c.define(1, chan(), 0.0)
    h.advance(10.0)
    assert h.records() == [] and h.coll.submitted == []


def test_every_function_and_any_group_matching() -> None:
    h = H()
    h.groups.set(1, 500, hops=0)
    h.groups.set(2, 700, hops=0)
    for cid, agg in enumerate(AggId):
        h.c.define(cid, chan(agg, gtype=ANY_GROUP_TYPE), 0.0)
    h.c.define(9, chan(AggId.SUM, gtype=2, gid=701), 0.0)  # matches no group
    h.advance(3.999)
    got = {(r.channel, r.group_type): r.value for r in h.records()}
    expect = {AggId.AVG: 21.5, AggId.MIN: 21.5, AggId.MAX: 21.5, AggId.SUM: 21.5, AggId.COUNT: 1}
    assert got == {(int(a), g): v for a, v in expect.items() for g in (1, 2)}


# --------------------------------------------------------------------------- definitions


def test_period_change_takes_effect_at_once_and_delete_stops() -> None:
    h = H()
    h.groups.set(1, 500, hops=0)
    h.c.define(1, chan(period_ms=10_000), 0.0)
    h.advance(10.0 + 9.99)
    assert [r.epoch for r in h.records()] == [1]
    h.c.define(1, chan(period_ms=1000), 21.5)
    h.advance(25.0)
    assert [r.epoch for r in h.records()] == [1, 22, 23, 24]
    h.c.define(1, chan(period_ms=1000), 25.0)  # the same definition again: no change
    h.advance(26.99)
    assert [r.epoch for r in h.records()][-2:] == [25, 26]
    h.c.define(1, None, 27.0)
    h.advance(60.0)
    assert [r.epoch for r in h.records()][-1] == 26
    assert h.c.timers.next_deadline() is None


def test_period_is_never_below_the_minimum() -> None:
    h = H(min_period_s=0.5)
    h.c.define(1, chan(period_ms=1), 0.0)
    assert h.c.period(1) == 0.5


def test_channels_that_cannot_run_are_refused() -> None:
    h = H(max_channels=2)
    h.c.define(1, chan(agg=77), 0.0)  # unknown function
    h.c.define(300, chan(), 0.0)  # channel id beyond a u8
    h.c.define(1, chan(), 0.0)
    h.c.define(2, chan(), 0.0)
    h.c.define(3, chan(), 0.0)  # one too many
    refused = [e for e in h.ctx.event_list if isinstance(e, ChannelRefused)]
    assert [e.channel for e in refused] == [1, 300, 3]
    assert set(h.c.defined()) == {1, 2}


# --------------------------------------------------------------------------- frame sizes


def _largest_frames() -> list[Frame]:
    """The largest instance of every frame groups and channels send or define.

    (Group-type definitions are Drip items sized by dissemination: with
    worst-case float32 thresholds 7 conditions fit 100 bytes, 4 fit 64.)
    """
    n = MAX_NODE_ID
    big = 3.4e38
    rec = DataRecord(0xFF, 0xFE, 0xFFFE, 0xFFFFFFFF, 0xFF, -big, 0xFFFFFFFF, n)
    rep = GroupReport(0xFE, 0xFFFE, n, 0xFFFFFFFF, 0xFFFF, GroupStatus.GONE, 0xFFFE)
    return [
        LeaderBeacon(n, BROADCAST, 0xFE, 0xFFFE, n, 0xFFFFFFFF, 0xFFFF, 0xFF, parent=n),
        Handover(n, n, 0xFE, 0xFFFE, 0xFFFFFFFF, 0xFFFF),
        Partial(n, n, 0xFF, 0xFE, 0xFFFE, 0xFFFFFFFF, 0xFF, 0xFFFFFFFF, (-big,) * 4),
        CtpData(n, n, n, 0xFFFF, 0xFF, 0xFFFF, rec),
        CtpData(n, n, n, 0xFFFF, 0xFF, 0xFFFF, rep),
        DripItem(
            n,
            BROADCAST,
            ItemKind.CHANNEL,
            0xFFFF,
            0xFFFFFFFF,
            ChannelDef(0xFFFF, 0xFF, 0xFFFF, 0xFFFFFFFF, 0xFF),
        ),
    ]


@pytest.mark.parametrize("preset", ["cc2420", "cc1000"])
def test_largest_frames_of_groups_and_channels_fit_the_mtu(preset: str) -> None:
    mtu = PRESETS[preset].mtu
    assert MiddlewareConfig().mtu <= PRESETS["cc2420"].mtu
    sizes = {
        type(f).__name__ + str(i): len(encode(f, mtu)) for i, f in enumerate(_largest_frames())
    }
    assert max(sizes.values()) <= mtu, sizes


# --------------------------------------------------------------------------- scenarios


HOT = GroupTypeDef((Condition(T, Op.GT, 50.0),))


def test_every_function_equals_ground_truth_per_epoch_on_lossless_links() -> None:
    inside = in_disc(48, 48, 30)

    def temperature(p: tuple[float, float], t: float) -> float:
        if not inside(p):
            return 20.0
        return 60.0 + p[0] / 10 + p[1] / 7 + (t % 5)  # differs per mote and per epoch

    sc = Scenario(seed=5, preset=LOSSLESS)
    sc.grid(9, 9, {T: temperature})
    sc.run_until(1.0)
    sc.define_group(1, HOT)
    for cid, agg in enumerate(AggId):
        sc.define_channel(cid, chan(agg, period_ms=2000))
    sc.run_until(60.0)
    members = {n for n in sc.motes if inside(sc.position(n))}
    assert len(members) >= 20
    assert set(sc.memberships(1)) == members
    truth_fns = {
        AggId.AVG: lambda v: sum(v) / len(v),
        AggId.MIN: min,
        AggId.MAX: max,
        AggId.SUM: sum,
        AggId.COUNT: len,
    }
    recs = [r for _, r in sc.records() if r.epoch >= 10]
    assert len(recs) == 5 * 20  # epochs 10..29, one record per channel and epoch
    for r in recs:
        values = [temperature(sc.position(n), r.epoch * 2.0) for n in members]
        assert r.count == len(members)
        # float32 on the wire: relative error ~1e-7 per addition
        assert r.value == pytest.approx(truth_fns[AggId(r.agg)](values), rel=1e-5), r
    stats = [m.channels.stats for m in sc.motes.values()]
    # Nothing lost (a partial late for its parent, after a beacon changed the tree
    # mid-epoch, is forwarded on its own and still makes the leader's deadline).
    assert sum(s.late_dropped + s.link_dropped + s.orphan_dropped for s in stats) == 0
    # Late partials are rare: the tree settles before the channels start (1.3 % at
    # seed 5 since summaries follow each adopted item: the run's timing changed).
    assert sum(s.late_forwarded for s in stats) <= 0.02 * sum(s.partials_sent for s in stats)


@pytest.mark.parametrize("seed", [5, 7])
def test_five_channels_at_once_under_csma_and_collisions_lose_almost_nothing(seed: int) -> None:
    """The lossless grid with carrier sense and SINR collisions on: every member sends
    five partials per epoch and siblings two cells apart are hidden from each other.
    Spreading partials over the TAG slot and the wide backoff of retransmissions
    (docs/protocol-groups.md, "Epochs and slots") keep almost every reading: before
    them 5-19 % were lost (link failures after four colliding attempts)."""
    inside = in_disc(48, 48, 30)

    def temperature(p: tuple[float, float], t: float) -> float:
        return 60.0 + p[0] / 10 if inside(p) else 20.0

    sc = Scenario(seed=seed, preset=LOSSLESS, mac="csma", collisions="sinr")
    sc.grid(9, 9, {T: temperature})
    sc.run_until(1.0)
    sc.define_group(1, HOT)
    for cid, agg in enumerate(AggId):
        sc.define_channel(cid, chan(agg, period_ms=2000))
    sc.run_until(60.0)
    members = {n for n in sc.motes if inside(sc.position(n))}
    assert set(sc.memberships(1)) == members
    recs = [r for _, r in sc.records() if r.epoch >= 10]
    assert len(recs) == 5 * 20
    assert all(r.count <= len(members) for r in recs)
    missing = sum(len(members) - r.count for r in recs)
    assert missing <= 0.01 * len(members) * len(recs), missing
    assert sum(r.count == len(members) for r in recs) >= 0.95 * len(recs)
    c = sc.net.counters.values()
    assert sum(x.collisions for x in c) > 0 and sum(x.cca_busy for x in c) > 0  # contended


def test_under_loss_the_count_says_which_readings_were_included() -> None:
    """Each member reads a distinct power of two, so a SUM names exactly the readings
    it includes (exact in float32 below 2**24): its popcount must equal the count."""
    # Lossy enough that partials are lost although the group tree avoids weak links.
    lossy = dataclasses.replace(PRESETS["cc2420"], shadowing_sigma_db=6.0)
    spacing = 15.0
    inside = in_disc(2.5 * spacing, 2.5 * spacing, 2.6 * spacing)
    index: dict[tuple[float, float], int] = {}
    for j in range(6):
        for i in range(6):
            p = (i * spacing, j * spacing)
            if inside(p):
                index[p] = len(index)
    assert len(index) <= 24

    def power(p: tuple[float, float], t: float) -> float:
        return float(2 ** index.get(p, 0))

    def hot(p: tuple[float, float], t: float) -> float:
        return 80.0 if inside(p) else 20.0

    sc = Scenario(seed=2, preset=lossy)
    sc.grid(6, 6, {T: hot, HUMIDITY: power}, spacing=spacing)
    sc.run_until(1.0)
    sc.define_group(1, HOT)
    sc.define_channel(1, chan(AggId.SUM, period_ms=2000, attr=HUMIDITY))
    sc.run_until(200.0)
    recs = [r for _, r in sc.records(since=20.0)]
    assert len(recs) >= 85
    for r in recs:
        assert bin(int(r.value)).count("1") == r.count, r
        assert r.count <= len(index)
    assert any(r.count < len(index) for r in recs)  # the links did lose data
    assert sum(m.channels.stats.link_dropped for m in sc.motes.values()) > 0


def test_period_changed_on_line_takes_effect_within_one_dissemination_round() -> None:
    inside = in_disc(70, 70, 30)
    sc = Scenario(seed=9)
    sc.add(0, (0.0, 0.0), is_root=True)  # the gateway's mote, in a corner
    sc.grid(9, 9, {T: lambda p, t: 80.0 if inside(p) else 20.0}, spacing=12.0, first_id=1)
    sc.run_until(1.0)
    sc.define_group(1, HOT, everywhere=False, at=[0])
    sc.define_channel(1, chan(AggId.COUNT, period_ms=4000), everywhere=False, at=[0])
    sc.run_until(40.0)
    before = [r for _, r in sc.records(since=30.0)]
    assert before and all(r.count == len(sc.memberships(1)) for r in before)
    change = 40.0
    sc.define_channel(1, chan(AggId.COUNT, period_ms=1000), everywhere=False, at=[0])
    sc.run_until(70.0)
    members = set(sc.memberships(1))
    got = {
        n: t
        for t, n, e in sc.of_type(ItemAdopted, change)
        if e.kind is ItemKind.CHANNEL and e.version == 2
    }
    assert members <= set(got)
    spread = max(got[n] for n in members)  # one dissemination round reaches the group
    recs = sc.records(since=change)
    new = [(t, r) for t, r in recs if r.epoch * 1.0 >= change]
    # The first record of the new period comes within one new period of the round.
    assert new[0][0] <= spread + 1.0 + 0.01, (new[0], spread)
    # From then on one complete record per second.
    steady = [r for t, r in new if t > spread + 2.0]
    epochs = [r.epoch for r in steady]
    assert epochs == list(range(epochs[0], epochs[0] + len(epochs)))
    assert all(r.count == len(members) for r in steady)
    # And no record of the old period after the round plus an old period.
    old = [t for t, r in recs if r.epoch * 4.0 < change + 4.0 and r.epoch < 20]
    assert all(t <= spread + 4.0 for t in old)


def test_two_group_types_at_once_with_a_channel_on_any_type() -> None:
    hot_zone = in_disc(30, 30, 22)
    wet_zone = in_disc(60, 60, 30)  # overlaps the hot one: some motes are in both groups
    sc = Scenario(seed=12)
    sc.grid(
        8,
        8,
        {
            T: lambda p, t: 80.0 if hot_zone(p) else 20.0,
            HUMIDITY: lambda p, t: 90.0 if wet_zone(p) else 30.0,
        },
    )
    sc.run_until(1.0)
    sc.define_group(1, HOT)
    sc.define_group(2, GroupTypeDef((Condition(HUMIDITY, Op.GE, 85.0),)))
    sc.define_channel(7, chan(AggId.COUNT, gtype=ANY_GROUP_TYPE, attr=T))
    sc.run_until(40.0)
    hot = {n for n in sc.motes if hot_zone(sc.position(n))}
    wet = {n for n in sc.motes if wet_zone(sc.position(n))}
    assert hot & wet
    assert set(sc.memberships(1)) == hot and set(sc.memberships(2)) == wet
    last = {r.group_type: r for _, r in sc.records(since=30.0)}
    assert last[1].count == len(hot) and last[2].count == len(wet)
    assert last[1].group_id == sc.motes[min(hot)].groups.membership(1).group_id  # type: ignore[union-attr]


def test_a_mote_in_no_group_keeps_no_epoch_timer() -> None:
    """Epochs tick only while a mote is in a group: a channel defined on a mote in
    none arms nothing; entering a group starts the epochs at the next boundary;
    leaving every group stops them once its pending partials are forgotten."""

    class FakeGroups:
        def __init__(self) -> None:
            self.ms: dict[int, Membership] = {}
            self.on_enter: object = None

        def memberships(self) -> dict[int, Membership]:
            return dict(self.ms)

    ctx = MoteContext(5, MiddlewareConfig(), random.Random(1), None)
    groups = FakeGroups()
    ch = Channels(ctx, groups, None)  # type: ignore[arg-type]
    assert groups.on_enter == ch._wake  # the hook Groups calls on entering a group
    ch.define(1, ChannelDef(TEMPERATURE, 1, ANY_GROUP_ID, 2000, AggId.AVG), 3.1)
    assert ch.timers.next_deadline() is None  # in no group: nothing armed
    groups.ms = {1: Membership(1, 77, 9, False, 9, 1, 0)}
    ch._wake(5.3)
    assert ch.timers.next_deadline() == 6.0  # the next epoch boundary
    groups.ms = {}
    for _ in range(10):  # left the group: the epochs run out, then stop
        t = ch.timers.next_deadline()
        if t is None:
            break
        for name in ch.timers.due(t):
            ch.on_timer(name, t)
    assert ch.timers.next_deadline() is None
