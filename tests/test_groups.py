"""Unit tests of group management: one Groups component on a fake clock."""

from __future__ import annotations

import math
import random
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from awaremw.protocol.attributes import HUMIDITY, TEMPERATURE, Bounds, rssi_attribute
from awaremw.protocol.commands import Commands
from awaremw.protocol.component import RssiSample
from awaremw.protocol.config import MiddlewareConfig
from awaremw.protocol.events import (
    ElectionCause,
    GroupJoined,
    GroupLeft,
    GroupTypeRefused,
    HandoverSent,
    LeaderElected,
    LeaderYielded,
    LeaveReason,
)
from awaremw.protocol.frames import (
    BROADCAST,
    CommandDef,
    Condition,
    Frame,
    GroupReport,
    GroupStatus,
    GroupTypeDef,
    Handover,
    LeaderBeacon,
    Op,
    Payload,
    decode,
)
from awaremw.protocol.groups import (
    ELECTION_BACKOFF_FACTOR,
    PARK_PERIODS,
    Groups,
    Role,
    condition_holds,
    condition_may_hold,
    heavier,
    seq_newer,
)
from awaremw.protocol.groups import conditions as conditions_module
from awaremw.protocol.mote import MoteContext

T = TEMPERATURE
HOT = GroupTypeDef((Condition(T, Op.GT, 50.0),))


class App:
    def __init__(self, **values: float | None) -> None:
        self.values: dict[int, float | None] = {T: values.get("t", 80.0)}
        if "h" in values:
            self.values[HUMIDITY] = values["h"]

    def offers(self, attr: int) -> bool:
        return attr in self.values

    def read(self, attr: int, now: float) -> float | None:
        return self.values.get(attr)

    def on_command(self, command: CommandDef, now: float) -> None:
        pass


class FakeCollection:
    def __init__(self) -> None:
        self.submitted: list[Payload] = []
        self.accept = True

    def submit(self, payload: Payload, now: float) -> bool:
        self.submitted.append(payload)
        return self.accept


class H:
    """One Groups component, its context and a hand-driven clock."""

    def __init__(self, nid: int = 10, temp: float | None = 80.0, **cfg: Any) -> None:
        # The rules are tested with ids taken at once; the tentative period has
        # its own tests (they pass tentative_periods).
        cfg.setdefault("tentative_periods", 0.0)
        self.app = App(t=temp)
        self.ctx = MoteContext(nid, MiddlewareConfig(**cfg), random.Random(nid), self.app)
        self.coll = FakeCollection()
        self.g = Groups(self.ctx, self.coll)  # type: ignore[arg-type]
        self.now = 0.0
        self.cfg = self.ctx.config

    @property
    def temp(self) -> float | None:
        return self.app.values[T]

    @temp.setter
    def temp(self, v: float | None) -> None:
        self.app.values[T] = v

    def advance(self, t: float) -> None:
        while (d := self.g.timers.next_deadline()) is not None and d <= t:
            self.now = d
            for name in self.g.timers.due(d):
                self.g.on_timer(name, d)
        self.now = t

    def hear(self, frame: Frame, rssi: float = -70.0) -> None:
        self.g.on_frame(frame, rssi, self.now)

    def sent(self) -> list[Frame]:
        out = [decode(tx.frame) for tx in self.ctx.outbox]
        self.ctx.outbox.clear()
        return out

    def link(self, frame: Frame, acked: bool) -> None:
        for k, (_, f) in list(self.ctx.pending.items()):
            if f == frame:
                del self.ctx.pending[k]
        self.g.on_link_result(frame, acked, self.now)

    def events(self, cls: type | None = None) -> list[Any]:
        evs = list(self.ctx.event_list)
        self.ctx.event_list.clear()
        return [e for e in evs if cls is None or isinstance(e, cls)]

    def reports(self) -> list[GroupReport]:
        return [p for p in self.coll.submitted if isinstance(p, GroupReport)]

    def lead(self, defn: GroupTypeDef = HOT) -> LeaderBeacon:
        """Define ``defn`` and let this mote create a group; returns its first beacon."""
        self.g.define(1, defn, self.now)
        self.advance(self.now + self.cfg.create_backoff + 0.001)
        (b,) = self.sent()
        assert isinstance(b, LeaderBeacon)
        return b


def beacon(
    src: int,
    gid: int = 500,
    leader: int = 2,
    weight: int = 0,
    seq: int = 1,
    hops: int = 0,
    gtype: int = 1,
    parent: int = BROADCAST,
) -> LeaderBeacon:
    return LeaderBeacon(src, BROADCAST, gtype, gid, leader, weight, seq, hops, parent=parent)


# --------------------------------------------------------------------------- helpers


@pytest.mark.parametrize(
    ("op", "thr", "value", "relax", "expected"),
    [
        (Op.GT, 50, 50.5, 0, True),
        (Op.GT, 50, 50.0, 0, False),
        (Op.GT, 50, 48.0, 3, True),
        (Op.GT, 50, 47.0, 3, False),
        (Op.GE, 50, 50.0, 0, True),
        (Op.GE, 50, 47.0, 3, True),
        (Op.LT, -80, -81, 0, True),
        (Op.LT, -80, -78, 0, False),
        (Op.LT, -80, -78, 3, True),
        (Op.LE, 10, 12, 2, True),
        (Op.LE, 10, 12.5, 2, False),
        (Op.EQ, 3, 3.0, 0, True),
        (Op.EQ, 3, 3.2, 0, False),
        (Op.EQ, 3, 3.2, 0.5, True),
        (Op.NE, 3, 3.0, 5, False),
        (Op.NE, 3, 4.0, 0, True),
    ],
)
def test_condition_with_hysteresis(
    op: Op, thr: float, value: float, relax: float, expected: bool
) -> None:
    assert condition_holds(Condition(T, op, thr), value, relax) is expected


def test_unavailable_attribute_never_qualifies() -> None:
    assert not condition_holds(Condition(T, Op.NE, 3), None, 0)


def test_seq_and_weight_order() -> None:
    assert seq_newer(2, 1) and not seq_newer(1, 2) and not seq_newer(5, 5)
    assert seq_newer(0, 0xFFFF) and seq_newer(3, 0xFFF0)  # wrap-around
    assert heavier(1, 5, 0, 9) and heavier(3, 9, 3, 5) and not heavier(3, 5, 3, 5)


# --------------------------------------------------------------------------- creation and joining


def test_qualifying_mote_alone_creates_a_group_after_backoff() -> None:
    h = H()
    h.g.define(1, HOT, 0.0)
    assert h.g.role(1) is Role.WAITING and h.sent() == []
    h.advance(h.cfg.create_backoff + 0.001)
    (b,) = h.sent()
    assert isinstance(b, LeaderBeacon)
    assert (b.leader, b.weight, b.seq, b.hops) == (10, 0, 1, 0)
    assert 1 <= b.group_id <= 0xFFFE
    (e,) = h.events(LeaderElected)
    assert e.cause is ElectionCause.CREATED and e.group_id == b.group_id
    m = h.g.membership(1)
    assert m is not None and m.is_leader and m.group_id == b.group_id and m.parent is None
    assert h.reports()[0].status is GroupStatus.ALIVE  # the gateway learns at once
    # It beacons every beacon period with a growing seq.
    h.advance(h.now + h.cfg.beacon_period * 3)
    seqs = [f.seq for f in h.sent() if isinstance(f, LeaderBeacon)]
    assert seqs == [2, 3, 4]


# --------------------------------------------------------------------------- tentative ids


def tentative(src: int, gid: int, gtype: int = 1) -> LeaderBeacon:
    return LeaderBeacon(src, BROADCAST, gtype, gid, src, 0, 0, 0, True)


def announce(h: H) -> LeaderBeacon:
    """Define HOT; run to this mote's first frame, its tentative announcement."""
    h.g.define(1, HOT, h.now)
    while not h.ctx.outbox:
        d = h.g.timers.next_deadline()
        assert d is not None and d < h.now + h.cfg.create_backoff + 1.5
        h.advance(d)
    (a,) = h.sent()
    assert isinstance(a, LeaderBeacon) and a.tentative
    return a


def test_a_new_id_is_announced_for_one_beacon_period_before_it_is_taken() -> None:
    h = H(tentative_periods=1.0)
    hold = h.cfg.beacon_period
    a = announce(h)
    assert h.now <= h.cfg.create_backoff / 2  # half the creation backoff
    assert (a.leader, a.weight, a.seq, a.hops) == (10, 0, 0, 0)
    t_announce = h.now + hold / 2  # the second announcement
    # Not a group yet: no membership, no event, nothing reported.
    assert h.g.role(1) is Role.WAITING and h.g.membership(1) is None
    assert h.events() == [] and h.reports() == []
    h.advance(t_announce - 0.001)
    assert h.sent() == []
    h.advance(t_announce + 0.001)  # half-way: announced once more
    (a2,) = h.sent()
    assert isinstance(a2, LeaderBeacon) and a2.tentative and a2.group_id == a.group_id
    assert h.events() == []
    h.advance(t_announce + hold / 2 + 0.001)  # the tentative period is over: taken
    (b,) = h.sent()
    assert isinstance(b, LeaderBeacon) and not b.tentative
    assert (b.group_id, b.seq) == (a.group_id, 1)
    (e,) = h.events(LeaderElected)
    assert e.cause is ElectionCause.CREATED and e.group_id == a.group_id
    assert [r.group_id for r in h.reports()] == [a.group_id]
    m = h.g.membership(1)
    assert m is not None and m.is_leader and m.group_id == a.group_id


@pytest.mark.parametrize("their_gid", [1, 0xFFFE])
def test_a_would_be_group_that_hears_a_group_joins_it_and_its_id_never_appears(
    their_gid: int,
) -> None:
    """A fringe mote ahead of the group (romeo4r seeds 5, 18): it announces an id,
    a member of the group comes in range. Whatever the ids, the established group
    wins and the would-be id is never held, reported or yielded."""
    h = H(tentative_periods=1.0)
    h.g.define(1, HOT, 0.0)
    h.advance(h.cfg.create_backoff)  # past the creation backoff: it announced an id
    assert h.g.role(1) is Role.WAITING and h.g.membership(1) is None
    mine = [f for f in h.sent() if isinstance(f, LeaderBeacon) and f.leader == 10]
    assert mine and {f.group_id for f in mine} != {their_gid}
    h.hear(beacon(src=7, gid=their_gid, leader=2, weight=0, seq=4, hops=1))
    h.advance(h.now + 3 * h.cfg.beacon_period)
    m = h.g.membership(1)
    assert m is not None and m.group_id == their_gid and not m.is_leader
    evs = h.events()
    assert [type(e) for e in evs] == [GroupJoined]
    assert h.reports() == []  # the gateway never heard of the would-be id
    assert all(not (isinstance(f, LeaderBeacon) and f.leader == 10) for f in h.sent())
    assert h.g.stats.tentative_withdrawn == 1


def test_an_established_group_answers_a_tentative_announcement() -> None:
    h = H()
    b = h.lead()
    h.advance(h.now + 0.1)
    h.hear(tentative(src=30, gid=0xFFFE))  # a higher id, but only a would-be group
    h.advance(h.now + h.cfg.forward_jitter + 0.001)
    (r,) = h.sent()
    assert isinstance(r, LeaderBeacon) and not r.tentative
    assert (r.group_id, r.leader, r.seq) == (b.group_id, 10, b.seq)
    assert h.g.membership(1) is not None and h.events(LeaderYielded) == []


def test_of_two_would_be_groups_the_higher_id_goes_on_and_the_other_joins_it() -> None:
    h = H(tentative_periods=1.0)
    a = announce(h)
    assert a.group_id < 0xFFFE
    h.hear(tentative(src=30, gid=0xFFFE))
    assert h.g.role(1) is Role.WAITING
    h.advance(h.now + h.cfg.beacon_period * 0.9)  # no own id taken meanwhile
    assert h.sent() == [] and h.events() == []
    h.hear(beacon(src=30, gid=0xFFFE, leader=30, seq=1))  # the winner took its id
    m = h.g.membership(1)
    assert m is not None and m.group_id == 0xFFFE
    # The lower one, heard by the winner, is answered with the winner's announcement.
    w = H(nid=30, tentative_periods=1.0)
    wa = announce(w)
    w.hear(tentative(src=10, gid=1 if wa.group_id > 1 else 2))
    w.advance(w.now + w.cfg.forward_jitter + 0.001)  # after a jitter
    ((again),) = w.sent()
    assert isinstance(again, LeaderBeacon) and again.tentative and again.group_id == wa.group_id


def test_a_mote_between_two_would_be_groups_relays_the_higher_announcement_once() -> None:
    """Fire seed 15: two motes of a leaderless part, two hops apart, announce at
    once; the mote between them hears both."""
    h = H(temp=20.0, tentative_periods=1.0)
    h.g.define(1, HOT, 0.0)
    h.advance(1.0)
    h.hear(tentative(src=30, gid=900))
    assert h.sent() == []  # one announcement: nothing to relay
    h.hear(tentative(src=31, gid=400))
    h.advance(h.now + h.cfg.forward_jitter + 0.001)  # after a jitter
    (r,) = h.sent()
    assert isinstance(r, LeaderBeacon) and r.tentative
    assert (r.src, r.group_id, r.leader, r.hops) == (10, 900, 30, 1)
    h.hear(tentative(src=31, gid=400))  # repeated: relayed once only
    h.hear(tentative(src=30, gid=900))
    h.advance(h.now + h.cfg.forward_jitter + 0.001)
    assert h.sent() == []
    # The lower announcer withdraws on the relayed copy.
    low = H(nid=31, tentative_periods=1.0)
    a = announce(low)
    relayed = LeaderBeacon(10, BROADCAST, 1, 0xFFFE, 30, 0, 0, 1, True)
    assert a.group_id < 0xFFFE
    low.hear(relayed)
    assert low.g.stats.tentative_withdrawn == 1
    low.advance(low.now + low.cfg.beacon_period)
    assert low.events() == [] and low.g.membership(1) is None


def _first_send_time(h: H, until: float) -> float | None:
    """Advance ``h`` deadline by deadline up to ``until``; the time of its first frame."""
    while not h.ctx.outbox:
        d = h.g.timers.next_deadline()
        if d is None or d > until:
            h.advance(until)
            return None
        h.advance(d)
    return h.now


def test_motes_that_heard_the_same_announcements_relay_them_at_different_times() -> None:
    """Fire seeds with collisions on: every mote between two would-be groups hears
    the same frame at the same instant; answering at once, their relays overlap on
    the air and the announcer hears none of them."""
    times = []
    for nid in (11, 12, 13):
        h = H(nid=nid, temp=20.0, tentative_periods=1.0)
        h.g.define(1, HOT, 0.0)
        h.advance(1.0)
        h.hear(tentative(src=30, gid=900))
        h.hear(tentative(src=31, gid=400))
        t = _first_send_time(h, 1.0 + h.cfg.forward_jitter)
        assert t is not None  # relayed within the forward jitter
        times.append(t)
    airtime = 0.002  # a LeaderBeacon on the CC2420 with its PHY overhead is < 2 ms
    gaps = [b - a for a, b in zip(sorted(times), sorted(times)[1:], strict=False)]
    assert min(gaps) > airtime / 10 and max(times) - min(times) > airtime


def test_a_mote_that_joins_after_hearing_an_announcement_answers_it() -> None:
    """Fire seed 6 with collisions on: two motes joined a group after hearing a
    would-be group's announcement (as waiting motes, which do not answer); their
    forwards of the group's beacon collided at the would-be mote, which took its
    id. A joiner that heard an announcement sends a second, later copy."""
    h = H(temp=20.0, tentative_periods=1.0)
    h.g.define(1, HOT, 0.0)
    h.advance(1.0)
    h.hear(tentative(src=30, gid=900))
    h.temp = 80.0
    h.advance(2.2)  # qualifies at its next check; waits for the announced group
    assert h.g.role(1) is Role.WAITING and h.sent() == []
    h.hear(beacon(src=4, gid=500, leader=2, seq=3, hops=1))
    assert h.g.membership(1) is not None
    h.advance(h.now + 3 * h.cfg.forward_jitter)
    copies = [f for f in h.sent() if isinstance(f, LeaderBeacon) and f.group_id == 500]
    assert len(copies) == 2 and all(not f.tentative and f.seq == 3 for f in copies)
    # Without an announcement heard, a joiner forwards once only.
    q = H(temp=80.0, tentative_periods=1.0)
    q.g.define(1, HOT, 0.0)
    q.hear(beacon(src=4, gid=500, leader=2, seq=3, hops=1))
    q.advance(q.now + 3 * q.cfg.forward_jitter)
    assert len([f for f in q.sent() if isinstance(f, LeaderBeacon)]) == 1


def test_a_part_that_split_off_and_rejoined_keeps_its_split_id_for_the_real_split() -> None:
    """Fire seed 1 with collisions on: the bridge to the leader flaps; a part takes
    a split and a new id, hears the old group again and rejoins it, and splits for
    good a few beacon periods later. It goes on under the id it split off with,
    not a third one."""
    h = H()
    h.g.define(1, HOT, 0.0)
    h.hear(beacon(src=4, gid=500, leader=2, weight=40, seq=17, hops=1))  # 2 hops away
    timeout = h.cfg.leader_timeout_periods * h.cfg.beacon_period
    h.advance(timeout + h.cfg.beacon_period + ELECTION_BACKOFF_FACTOR * h.cfg.create_backoff)
    (e,) = h.events(LeaderElected)
    split_id = e.group_id
    assert e.cause is ElectionCause.ELECTION and split_id != 500
    h.advance(h.now + 0.5)
    h.hear(beacon(src=4, gid=500, leader=2, weight=44, seq=22, hops=1))  # the bridge again
    (y,) = h.events(LeaderYielded)
    assert y.successor == 500 and h.g.membership(1).group_id == 500  # type: ignore[union-attr]
    for k in range(2):
        h.advance(h.now + h.cfg.beacon_period)
        h.hear(beacon(src=4, gid=500, leader=2, weight=45 + k, seq=23 + k, hops=1))
    h.events()
    backoff = ELECTION_BACKOFF_FACTOR * h.cfg.create_backoff
    h.advance(h.now + timeout + h.cfg.beacon_period + backoff)
    (e2,) = h.events(LeaderElected)
    assert e2.cause is ElectionCause.ELECTION and e2.group_id == split_id


def test_a_waiting_mote_that_heard_an_announcement_does_not_announce_a_contender() -> None:
    h = H(temp=20.0, tentative_periods=1.0)
    h.g.define(1, HOT, 0.0)
    h.advance(1.0)
    h.hear(tentative(src=30, gid=700))
    h.temp = 80.0
    h.advance(1.0 + h.cfg.beacon_period - 0.01)  # it would have created by now
    assert h.sent() == [] and h.g.role(1) is Role.WAITING
    h.hear(beacon(src=30, gid=700, leader=30, seq=1))
    m = h.g.membership(1)
    assert m is not None and m.group_id == 700
    assert [type(e) for e in h.events()] == [GroupJoined]


def test_non_qualifying_mote_does_nothing() -> None:
    h = H(temp=20.0)
    h.g.define(1, HOT, 0.0)
    h.advance(30.0)
    assert h.g.role(1) is Role.IDLE and h.g.membership(1) is None and h.sent() == []


def test_joins_a_group_heard_recently_instead_of_creating() -> None:
    h = H(temp=20.0)
    h.g.define(1, HOT, 0.0)
    h.advance(1.0)
    h.hear(beacon(src=7, gid=500, leader=2, weight=4, seq=9, hops=2))
    assert h.sent() == []  # a non-member listens but does not forward
    h.temp = 80.0
    h.advance(3.0)  # next membership checks
    m = h.g.membership(1)
    assert m is not None and (m.group_id, m.leader, m.parent, m.hops, m.weight) == (500, 2, 7, 3, 4)
    assert not m.is_leader
    evs = h.events()
    assert [type(e) for e in evs] == [GroupJoined]
    # It announces the group once (the remembered seq, its own hop count), so that a
    # waiting mote out of the leader's reach adopts it rather than creating a contender.
    sent = [(f.group_id, f.leader, f.seq, f.hops) for f in h.sent() if isinstance(f, LeaderBeacon)]
    assert sent == [(500, 2, 9, 3)]


def test_group_heard_too_long_ago_is_not_joined() -> None:
    h = H(temp=20.0)
    h.g.define(1, HOT, 0.0)
    h.hear(beacon(src=7))
    timeout = h.cfg.leader_timeout_periods * h.cfg.beacon_period
    h.advance(timeout + 0.5)
    h.temp = 80.0
    h.advance(h.now + 1.0 + h.cfg.create_backoff + 0.01)
    m = h.g.membership(1)
    assert m is not None and m.is_leader and m.group_id != 500


def test_waiting_mote_joins_on_beacon_and_forwards_it_once() -> None:
    h = H()
    h.g.define(1, HOT, 0.0)
    assert h.g.role(1) is Role.WAITING
    h.hear(beacon(src=7, seq=3, hops=1))
    assert h.g.role(1) is Role.MEMBER
    h.advance(h.cfg.forward_jitter)
    (f,) = h.sent()
    assert isinstance(f, LeaderBeacon)
    assert (f.src, f.group_id, f.leader, f.seq, f.hops) == (10, 500, 2, 3, 2)
    h.hear(beacon(src=8, seq=3, hops=1))  # the same beacon from another neighbour
    h.advance(h.now + 1.0)
    assert h.sent() == []
    h.hear(beacon(src=8, seq=4, hops=1))
    h.advance(h.now + h.cfg.forward_jitter)
    assert [f.seq for f in h.sent() if isinstance(f, LeaderBeacon)] == [4]
    # The create backoff was cancelled: no group of its own.
    h.advance(h.now + 2 * h.cfg.create_backoff)
    assert h.events(LeaderElected) == []


def test_parent_is_first_sender_of_newest_seq_then_fewest_hops() -> None:
    h = H()
    h.g.define(1, HOT, 0.0)
    h.hear(beacon(src=7, seq=3, hops=3))
    h.hear(beacon(src=8, seq=3, hops=1))  # same seq, fewer hops: better parent
    h.advance(h.cfg.forward_jitter)
    (f,) = h.sent()
    assert isinstance(f, LeaderBeacon) and f.hops == 2  # forwarded with the best count
    m = h.g.membership(1)
    assert m is not None and (m.parent, m.hops) == (8, 2)
    h.hear(beacon(src=9, seq=4, hops=4))  # newer seq wins even with more hops
    m = h.g.membership(1)
    assert m is not None and (m.parent, m.hops) == (9, 5)
    h.hear(beacon(src=7, seq=4, hops=5))  # not better: ignored
    assert h.g.membership(1).parent == 9  # type: ignore[union-attr]
    assert h.g.upstream(1, h.now) == [9]  # 8 and 7 only sent the older seq
    h.hear(beacon(src=8, seq=4, hops=1))
    assert h.g.membership(1).parent == 8  # type: ignore[union-attr]


def test_equal_hops_prefer_the_stronger_link_and_avoid_failed_parents() -> None:
    h = H()
    h.g.define(1, HOT, 0.0)
    h.hear(beacon(src=7, seq=3, hops=1), rssi=-90.0)
    h.hear(beacon(src=8, seq=3, hops=1), rssi=-80.0)
    h.hear(beacon(src=9, seq=3, hops=1), rssi=-85.0)
    h.hear(beacon(src=6, seq=3, hops=2), rssi=-50.0)  # more hops: never, however strong
    m = h.g.membership(1)
    assert m is not None and (m.parent, m.hops) == (8, 2)
    assert h.g.upstream(1, h.now) == [8, 9, 7]
    h.g.parent_failed(1, 8, h.now)  # unicasts to 8 failed: next best of this seq
    assert h.g.membership(1).parent == 9  # type: ignore[union-attr]
    h.hear(beacon(src=8, seq=3, hops=1), rssi=-79.0)  # stronger, but it failed us
    assert h.g.membership(1).parent == 9  # type: ignore[union-attr]
    h.hear(beacon(src=8, seq=4, hops=1), rssi=-80.0)  # first copy of a new seq: the rule
    assert h.g.membership(1).parent == 8  # type: ignore[union-attr]
    h.hear(beacon(src=9, seq=4, hops=1), rssi=-85.0)  # weaker, but 8 failed recently
    assert h.g.membership(1).parent == 9  # type: ignore[union-attr]
    h.g.parent_failed(1, 9, h.now)  # nobody else for seq 4: stays
    assert h.g.membership(1).parent == 8  # type: ignore[union-attr]


def test_good_link_beats_fewer_hops_until_the_hop_count_is_on_the_air() -> None:
    h = H()  # floor -90 dBm
    h.g.define(1, HOT, 0.0)
    h.hear(beacon(src=2, seq=3, hops=0), rssi=-94.0)  # the leader, over a weak link
    m = h.g.membership(1)
    assert m is not None and (m.parent, m.hops) == (2, 1)
    h.advance(h.cfg.forward_jitter * 0.99)
    assert h.sent() == []  # a weak parent: it waits longer before forwarding
    h.advance(h.cfg.forward_jitter * 2.99)
    assert h.sent() == []  # the weaker, the longer
    h.hear(beacon(src=7, seq=3, hops=1), rssi=-80.0)  # a good link, one hop more
    m = h.g.membership(1)
    assert m is not None and (m.parent, m.hops) == (7, 2)
    h.advance(4 * h.cfg.forward_jitter)  # -94 dBm: three bands under the floor
    (f,) = h.sent()
    assert isinstance(f, LeaderBeacon) and f.hops == 2
    # Our hop count is public now: it may not grow any more, even for a good link.
    h.hear(beacon(src=8, seq=4, hops=0), rssi=-93.0)
    h.advance(h.now + 2 * h.cfg.forward_jitter * 0.99)
    assert h.sent() == []  # two bands under the floor: two jitters at least
    h.advance(h.now + 2 * h.cfg.forward_jitter)
    (f,) = h.sent()
    assert f.hops == 1
    h.hear(beacon(src=9, seq=4, hops=1), rssi=-70.0)
    assert h.g.membership(1).parent == 8  # type: ignore[union-attr]


def test_a_leaf_skips_covered_forwards_but_not_while_a_child_depends_on_it() -> None:
    """Counter-based forwarding without partials: a forward names the parent only
    when it was the only member heard with that seq; the parent then forwards for
    a leader timeout even when covered (docs/protocol-groups.md, Quiet beacons)."""
    h = H()
    h.g.define(1, HOT, 0.0)
    period, jitter = h.cfg.beacon_period, h.cfg.forward_jitter

    def seq(n: int, covered: bool, child: bool = False) -> list[LeaderBeacon]:
        h.advance((n - 1) * period)
        h.hear(beacon(src=7, seq=n, hops=1))  # our parent
        if covered:
            h.hear(beacon(src=8, seq=n, hops=2))  # a member as far out as we are
        h.advance(h.now + jitter)
        sent = [f for f in h.sent() if isinstance(f, LeaderBeacon)]
        if child and sent:
            h.hear(beacon(src=30, seq=n, hops=3, parent=10))  # it took it from us
        return sent

    (f,) = seq(1, covered=False)
    assert (f.hops, f.parent) == (2, 7)  # 7 was all we heard: we depend on it
    assert seq(2, covered=True) == []  # a leaf, covered: skipped
    (f,) = seq(3, covered=False, child=True)
    assert f.parent == 7
    # Covered now, but a child named us: forward for a leader timeout (3.5
    # periods) after its last naming; a forward that heard 8 too names nobody.
    for n in (4, 5, 6):
        (f,) = seq(n, covered=True)
        assert f.parent == BROADCAST
    assert seq(7, covered=True) == []
    assert h.g.stats.beacons_suppressed == 2


def test_member_switches_to_heavier_group_and_ignores_lighter() -> None:
    h = H()
    h.g.define(1, HOT, 0.0)
    h.hear(beacon(src=7, gid=500, leader=2, weight=10, seq=3, hops=1))
    h.advance(0.1)
    h.sent()
    h.events()
    h.hear(beacon(src=8, gid=900, leader=3, weight=5, seq=1, hops=0))  # lighter
    h.advance(0.2)
    # It stays, and answers the contender with its own current beacon (once), so
    # that the lighter group's motes hear the heavier one within a flood.
    (rebut,) = h.sent()
    assert isinstance(rebut, LeaderBeacon)
    assert (rebut.group_id, rebut.seq, rebut.weight, rebut.hops) == (500, 3, 10, 2)
    assert h.g.membership(1).group_id == 500  # type: ignore[union-attr]
    h.hear(beacon(src=8, gid=900, leader=3, weight=5, seq=2, hops=0))
    h.advance(0.22)
    assert h.sent() == []  # rate-limited: at most twice a beacon period
    h.hear(beacon(src=8, gid=100, leader=3, weight=11, seq=1, hops=0))  # heavier
    evs = h.events()
    assert [type(e) for e in evs] == [GroupLeft, GroupJoined]
    assert evs[0].reason is LeaveReason.SWITCHED and evs[1].group_id == 100
    h.advance(0.3)
    (f,) = h.sent()
    assert isinstance(f, LeaderBeacon) and (f.group_id, f.hops) == (100, 1)


def test_equal_weights_the_higher_group_id_wins() -> None:
    h = H()
    h.g.define(1, HOT, 0.0)
    h.hear(beacon(src=7, gid=500, weight=3))
    h.hear(beacon(src=8, gid=499, leader=3, weight=3))
    assert h.g.membership(1).group_id == 500  # type: ignore[union-attr]
    h.hear(beacon(src=8, gid=501, leader=3, weight=3))
    assert h.g.membership(1).group_id == 501  # type: ignore[union-attr]


def test_leader_yields_to_heavier_leader_and_reports_gone() -> None:
    h = H()
    mine = h.lead()
    h.events()
    other = mine.group_id % 0xFFFE + 1
    h.hear(beacon(src=7, gid=other, leader=3, weight=1, seq=6, hops=2))
    evs = h.events()
    assert isinstance(evs[0], LeaderYielded) and evs[0].successor == other
    m = h.g.membership(1)
    assert m is not None and not m.is_leader and (m.group_id, m.parent, m.hops) == (other, 7, 3)
    gone = h.reports()[-1]
    assert (gone.status, gone.group_id, gone.successor) == (GroupStatus.GONE, mine.group_id, other)
    h.advance(h.now + 0.1)
    assert [f.group_id for f in h.sent() if isinstance(f, LeaderBeacon)] == [other]
    h.advance(h.now + 3 * h.cfg.beacon_period)  # no beacons of its own any more
    assert all(f.leader != 10 for f in h.sent() if isinstance(f, LeaderBeacon))


def test_leader_ignores_lighter_leader() -> None:
    h = H()
    mine = h.lead()
    h.g.add_weight(1, 5)
    h.hear(beacon(src=7, gid=0xFFFE, leader=3, weight=4, seq=6))
    m = h.g.membership(1)
    assert m is not None and m.is_leader and m.group_id == mine.group_id
    assert h.events(LeaderYielded) == []


def test_weight_grows_with_data_and_reports_are_periodic() -> None:
    h = H(report_every_beacons=3)
    h.lead()
    h.g.add_weight(1, 7)
    h.g.add_weight(1, 5)
    h.advance(h.now + h.cfg.beacon_period * 6 + 0.001)
    bs = [f for f in h.sent() if isinstance(f, LeaderBeacon)]
    assert [b.weight for b in bs][-1] == 12
    alive = [r for r in h.reports() if r.status is GroupStatus.ALIVE]
    assert len(alive) == 3  # beacons 1, 4, 7
    assert (alive[-1].weight, alive[-1].readings) == (12, 5)


def test_refused_report_is_counted() -> None:
    h = H()
    h.coll.accept = False
    h.lead()
    assert h.g.stats.reports_refused == 1


# ------------------------------------------------------------------------- hysteresis, definitions


def test_hysteresis_keeps_members_and_needs_strict_condition_to_join() -> None:
    h = H(temp=49.0)
    defn = GroupTypeDef((Condition(T, Op.GT, 50.0),), hysteresis=2.0)
    h.g.define(1, defn, 0.0)
    h.hear(beacon(src=7))
    h.advance(1.5)
    assert h.g.membership(1) is None  # 49 > 50 - 2 but a newcomer needs 50
    h.temp = 51.0
    h.hear(beacon(src=7, seq=2))
    h.advance(2.5)
    assert h.g.membership(1) is not None
    h.temp = 48.5  # still > 48: stays
    h.hear(beacon(src=7, seq=3))
    h.advance(3.5)
    assert h.g.membership(1) is not None
    h.temp = 47.9
    h.advance(4.5)
    assert h.g.membership(1) is None
    (e,) = h.events(GroupLeft)
    assert e.reason is LeaveReason.CONDITION


def test_changed_definition_takes_effect_at_once_and_deletion_leaves() -> None:
    h = H(temp=60.0)
    h.g.define(1, HOT, 0.0)
    h.hear(beacon(src=7))
    assert h.g.membership(1) is not None
    h.g.define(1, GroupTypeDef((Condition(T, Op.GT, 70.0),)), 0.01)
    assert h.g.membership(1) is None  # no wait for the next check
    h.g.define(1, HOT, 0.02)
    assert h.g.membership(1) is not None  # the beacon heard earlier is still fresh
    h.events()
    h.g.define(1, None, 0.03)
    assert h.g.membership(1) is None and h.g.defined_types() == {}
    (e,) = h.events(GroupLeft)
    assert e.reason is LeaveReason.DELETED
    h.advance(60.0)
    assert h.sent() == [] and h.g.timers.next_deadline() is None


def test_deleting_a_type_makes_its_leader_report_gone() -> None:
    h = H()
    b = h.lead()
    h.g.define(1, None, h.now)
    assert (h.reports()[-1].status, h.reports()[-1].group_id) == (GroupStatus.GONE, b.group_id)


def test_several_types_at_once() -> None:
    h = H()
    h.app.values[HUMIDITY] = 30.0
    h.g.define(1, HOT, 0.0)
    h.g.define(2, GroupTypeDef((Condition(HUMIDITY, Op.LT, 40.0),)), 0.0)
    h.g.define(3, GroupTypeDef((Condition(HUMIDITY, Op.GT, 40.0),)), 0.0)
    h.hear(beacon(src=7, gtype=2, gid=77))
    h.advance(h.cfg.create_backoff + 0.01)
    ms = h.g.memberships()
    assert set(ms) == {1, 2}
    assert ms[1].is_leader and not ms[2].is_leader and ms[2].group_id == 77


def test_too_many_types_are_refused() -> None:
    h = H(max_group_types=2)
    for g in (1, 2, 3):
        h.g.define(g, HOT, 0.0)
    h.g.define(ANY := 0xFF, HOT, 0.0)
    refused = h.events(GroupTypeRefused)
    assert [e.group_type for e in refused] == [3, ANY]
    assert h.g.stats.types_refused == 2
    h.g.define(1, HOT, 0.1)  # redefining a held type is fine
    assert h.g.stats.types_refused == 2


def test_beacon_of_unknown_type_is_counted() -> None:
    h = H()
    h.hear(beacon(src=7, gtype=9))
    assert h.g.stats.beacons_unknown_type == 1 and h.sent() == []


def test_new_group_after_leader_loss_never_reuses_the_dead_id() -> None:
    class Rigged(random.Random):
        def __init__(self, ids: list[int]) -> None:
            super().__init__(1)
            self.ids = ids

        def randint(self, a: int, b: int) -> int:
            return self.ids.pop(0)

    h = H()
    h.ctx.rng = Rigged([500, 500, 321])
    h.g.define(1, HOT, 0.0)
    h.hear(beacon(src=3, gid=500, hops=1))  # the leader is not a neighbour: a split
    h.advance(30.0)
    m = h.g.membership(1)
    assert m is not None and m.is_leader and m.group_id == 321


# --------------------------------------------------------------------------- handover


def _leader_with_children(h: H, children: list[int], defn: GroupTypeDef = HOT) -> LeaderBeacon:
    b = h.lead(defn)
    for c in children:
        h.hear(beacon(src=c, gid=b.group_id, leader=10, seq=b.seq, hops=1))
    h.events()
    return b


def test_leaving_leader_hands_over_to_a_child() -> None:
    h = H()
    b = _leader_with_children(h, [21])
    h.g.note_child(1, 22, h.now, count=9)  # biggest subtree: first candidate
    h.g.add_weight(1, 9)
    h.temp = 20.0
    h.advance(h.now + h.cfg.check_period)
    (ho,) = h.sent()
    assert isinstance(ho, Handover)
    assert (ho.dst, ho.group_id, ho.weight, ho.seq) == (22, b.group_id, 9, b.seq)
    assert h.g.membership(1) is None and h.g.role(1) is Role.HANDING_OVER
    h.link(ho, acked=True)
    assert h.events(HandoverSent) == []  # waits for a refusal first
    h.advance(h.now + h.cfg.handover_grace)
    (e,) = h.events(HandoverSent)
    assert e.to == 22
    assert h.g.role(1) is Role.IDLE
    assert all(r.status is GroupStatus.ALIVE for r in h.reports())  # the group lives on


def test_handover_tries_next_candidate_on_link_failure_and_refusal() -> None:
    h = H()
    b = _leader_with_children(h, [21, 22, 23])
    h.temp = 20.0
    h.advance(h.now + h.cfg.check_period)
    (first,) = h.sent()
    assert isinstance(first, Handover)
    h.link(first, acked=False)
    (second,) = h.sent()
    assert isinstance(second, Handover) and second.dst != first.dst
    h.link(second, acked=True)
    # The candidate cannot take it: it sends the Handover back.
    h.hear(Handover(second.dst, 10, 1, b.group_id, second.weight, second.seq))
    (third,) = h.sent()
    assert isinstance(third, Handover) and third.dst not in (first.dst, second.dst)
    h.link(third, acked=False)
    # Nobody left: the group is gone.
    assert h.g.role(1) is Role.IDLE
    assert h.reports()[-1].status is GroupStatus.GONE
    assert h.g.stats.handovers_failed == 3


def test_any_member_heard_forwarding_is_a_candidate_good_links_first() -> None:
    h = H()
    b = h.lead()
    h.hear(beacon(src=21, gid=b.group_id, leader=10, seq=b.seq, hops=1), rssi=-93.0)
    h.hear(beacon(src=22, gid=b.group_id, leader=10, seq=b.seq, hops=2), rssi=-75.0)
    h.temp = 20.0
    h.advance(h.now + h.cfg.check_period)
    (ho,) = h.sent()
    assert isinstance(ho, Handover) and ho.dst == 22  # a neighbour, over a good link
    h.link(ho, acked=False)
    (ho2,) = h.sent()
    assert isinstance(ho2, Handover) and ho2.dst == 21


WARM = GroupTypeDef((Condition(T, Op.GT, 50.0),), hysteresis=2.0)


def test_a_leader_in_the_hysteresis_band_hands_over_while_it_still_qualifies() -> None:
    """Issue 31 (romeo4r, seed 9): a leader that keeps its group until it fails
    the relaxed condition is left behind by a moving group, cut off from the
    members ahead, which then elect a new id. Out of the strict condition it is
    at the group's edge: it hands over to a member heard lately."""
    h = H()
    b = _leader_with_children(h, [21], WARM)
    h.temp = 49.0  # > 50 - 2: still a member's value, no longer a newcomer's
    h.advance(h.now + h.cfg.check_period)
    (ho,) = h.sent()
    assert isinstance(ho, Handover) and (ho.dst, ho.group_id) == (21, b.group_id)
    assert h.g.role(1) is Role.HANDING_OVER
    h.link(ho, acked=True)
    h.advance(h.now + h.cfg.handover_grace)
    (e,) = h.events(HandoverSent)
    assert e.to == 21 and h.g.role(1) is Role.IDLE
    assert all(r.status is GroupStatus.ALIVE for r in h.reports())


def test_an_early_handover_nobody_takes_leaves_the_leader_leading() -> None:
    h = H()
    b = _leader_with_children(h, [21], WARM)
    h.temp = 49.0
    h.advance(h.now + h.cfg.check_period)
    (ho,) = h.sent()
    h.link(ho, acked=True)
    h.hear(Handover(21, 10, 1, b.group_id, ho.weight, ho.seq))  # refused
    m = h.g.membership(1)
    assert m is not None and m.is_leader  # still qualifies: leads on
    assert all(r.status is GroupStatus.ALIVE for r in h.reports())
    h.advance(h.now + h.cfg.beacon_period)
    beacons = [f for f in h.sent() if isinstance(f, LeaderBeacon)]
    assert beacons and beacons[0].group_id == b.group_id and beacons[0].seq > b.seq
    # Without the hysteresis band (fails the relaxed condition too) it hands over
    # to a stale member as well, and the group is gone if none takes it.
    h.temp = 20.0
    h.advance(h.now + h.cfg.check_period)
    (last,) = [f for f in h.sent() if isinstance(f, Handover)]
    h.link(last, acked=False)
    assert h.g.role(1) is Role.IDLE and h.reports()[-1].status is GroupStatus.GONE


def test_a_leader_in_the_band_with_no_member_heard_lately_leads_on() -> None:
    h = H()
    _leader_with_children(h, [21], WARM)
    h.advance(h.now + 3 * h.cfg.beacon_period)  # 21 not heard since: stale
    h.sent()
    h.temp = 49.0
    h.advance(h.now + h.cfg.check_period)
    assert not [f for f in h.sent() if isinstance(f, Handover)]
    m = h.g.membership(1)
    assert m is not None and m.is_leader


def test_a_new_leader_by_handover_does_not_yield_to_its_predecessors_last_beacons() -> None:
    """Issue 31 (romeo4r, seed 17): a member forwarding the old leader's last beacon
    reached the new leader after the handover; the old leader's id (the larger node)
    won the tie of weights and the new leader yielded, leaving the group leaderless."""
    h = H()
    h.g.define(1, HOT, 0.0)
    h.hear(beacon(src=12, gid=500, leader=12, weight=40, seq=17, hops=0))
    h.hear(Handover(12, 10, 1, 500, 40, 17))
    (e,) = h.events(LeaderElected)
    assert e.cause is ElectionCause.HANDOVER
    h.sent()
    h.hear(beacon(src=5, gid=500, leader=12, weight=40, seq=17, hops=1))  # forwarded late
    m = h.g.membership(1)
    assert m is not None and m.is_leader and h.events(LeaderYielded) == []
    # A claimant of our id that is not our predecessor still wins the tie.
    h.hear(beacon(src=13, gid=500, leader=13, weight=40, seq=18, hops=0))
    assert h.g.role(1) is Role.MEMBER and len(h.events(LeaderYielded)) == 1


def test_leader_without_known_member_reports_gone() -> None:
    h = H()
    h.lead()
    h.temp = 20.0
    h.advance(h.now + h.cfg.check_period)
    assert h.sent() == [] and h.reports()[-1].status is GroupStatus.GONE
    (e,) = h.events(GroupLeft)
    assert e.reason is LeaveReason.CONDITION


def test_member_takes_over_on_handover() -> None:
    h = H()
    h.g.define(1, HOT, 0.0)
    h.hear(beacon(src=2, gid=500, leader=2, weight=40, seq=17, hops=0))
    h.events()
    h.hear(Handover(2, 10, 1, 500, 41, 17))
    (e,) = h.events(LeaderElected)
    assert (e.cause, e.group_id, e.weight) == (ElectionCause.HANDOVER, 500, 41)
    (b,) = h.sent()
    assert isinstance(b, LeaderBeacon) and (b.group_id, b.leader, b.weight, b.seq) == (
        500,
        10,
        41,
        18,
    )
    m = h.g.membership(1)
    assert m is not None and m.is_leader
    # The leader reports itself at once.
    assert (h.reports()[-1].leader, h.reports()[-1].status) == (10, GroupStatus.ALIVE)
    # A duplicate of the same handover is harmless.
    h.hear(Handover(2, 10, 1, 500, 41, 17))
    assert h.sent() == [] and h.events(LeaderElected) == []


def test_non_qualifying_candidate_refuses_handover() -> None:
    h = H(temp=20.0)
    h.g.define(1, HOT, 0.0)
    h.hear(Handover(2, 10, 1, 500, 41, 17))
    (back,) = h.sent()
    assert isinstance(back, Handover) and (back.dst, back.group_id) == (2, 500)
    assert h.g.membership(1) is None and h.g.stats.handovers_refused == 1


def test_late_refusal_after_leaving_is_not_bounced_back() -> None:
    h = H()
    b = _leader_with_children(h, [21])
    h.temp = 20.0
    h.advance(h.now + h.cfg.check_period)
    (ho,) = h.sent()
    h.link(ho, acked=True)
    h.advance(h.now + h.cfg.handover_grace)
    h.hear(Handover(21, 10, 1, b.group_id, 0, b.seq))  # a refusal that came too late
    assert h.sent() == []  # not bounced back (no ping-pong), no new leader
    assert h.g.role(1) is Role.IDLE and h.events(LeaderElected) == []


def test_refusal_is_sent_back_once() -> None:
    h = H(temp=20.0)
    h.g.define(1, HOT, 0.0)
    h.hear(Handover(2, 10, 1, 500, 41, 17))
    h.hear(Handover(2, 10, 1, 500, 41, 17))
    assert len(h.sent()) == 1 and h.g.stats.handovers_refused == 2


# --------------------------------------------------------------------------- leader loss


def test_members_elect_a_new_group_when_a_distant_leader_is_lost() -> None:
    """A member that never heard the leader directly cannot tell its death from a
    split: the paper's split rule, a new id."""
    h = H()
    h.g.define(1, HOT, 0.0)
    h.hear(beacon(src=3, gid=500, leader=2, weight=40, seq=17, hops=1))
    h.events()
    timeout = h.cfg.leader_timeout_periods * h.cfg.beacon_period
    # Hysteresis in time on the split route: one more beacon period as a member.
    patience = timeout + h.cfg.beacon_period
    h.advance(patience - 0.01)
    assert h.g.membership(1) is not None and h.events(GroupLeft) == []
    h.advance(patience + 0.01)
    (left,) = h.events(GroupLeft)
    assert left.reason is LeaveReason.LEADER_LOST
    h.advance(patience + ELECTION_BACKOFF_FACTOR * h.cfg.create_backoff + 0.02)
    (e,) = h.events(LeaderElected)
    assert e.cause is ElectionCause.ELECTION and e.group_id != 500 and e.weight == 0


def test_a_beacon_during_the_patience_keeps_the_member_in_its_group() -> None:
    h = H()
    h.g.define(1, HOT, 0.0)
    h.hear(beacon(src=3, gid=500, leader=2, weight=40, seq=17, hops=1))
    timeout = h.cfg.leader_timeout_periods * h.cfg.beacon_period
    h.advance(timeout + 0.5 * h.cfg.beacon_period)
    h.hear(beacon(src=3, gid=500, leader=2, weight=44, seq=18, hops=1))  # the bridge is back
    h.advance(2 * timeout)
    m = h.g.membership(1)
    assert m is not None and m.group_id == 500 and m.weight == 44
    assert h.events(GroupLeft) == [] and h.events(LeaderElected) == []


def test_orphan_joins_a_new_group_heard_meanwhile() -> None:
    h = H()
    h.g.define(1, HOT, 0.0)
    h.hear(beacon(src=4, gid=500, leader=2, weight=40, seq=17, hops=1))
    timeout = h.cfg.leader_timeout_periods * h.cfg.beacon_period
    h.advance(timeout - 1)
    h.hear(beacon(src=3, gid=600, leader=3, weight=0, seq=1))  # a lighter new group
    assert h.g.membership(1).group_id == 500  # type: ignore[union-attr]
    h.advance(timeout + h.cfg.beacon_period + 0.01)
    m = h.g.membership(1)
    assert m is not None and m.group_id == 600 and not m.is_leader


def test_neighbour_of_a_silent_leader_takes_over_with_the_id() -> None:
    """Beacon timeout as the fallback detector: a member that heard the leader
    directly claims the group with its id, weight and a newer seq."""
    h = H()
    h.g.define(1, HOT, 0.0)
    h.hear(beacon(src=2, gid=500, leader=2, weight=40, seq=17))
    h.events()
    h.sent()
    timeout = h.cfg.leader_timeout_periods * h.cfg.beacon_period
    h.advance(timeout - 0.01)
    assert h.g.membership(1).leader == 2  # type: ignore[union-attr]
    h.advance(timeout + 2 * h.cfg.forward_jitter + 0.01)
    (e,) = h.events(LeaderElected)
    assert (e.cause, e.group_id, e.weight) == (ElectionCause.FAILOVER, 500, 40)
    assert h.events(GroupLeft) == []
    b = [f for f in h.sent() if isinstance(f, LeaderBeacon)]
    assert (b[-1].group_id, b[-1].leader, b[-1].seq, b[-1].hops) == (500, 10, 18, 0)


def test_unacked_partial_to_the_leader_triggers_failover_unless_it_was_heard() -> None:
    """The data path as failure detector: a partial to the leader not acknowledged
    after the retries makes the member claim the group once the leader's last sign
    of life is older than 1.25 beacon periods; a sign of life meanwhile cancels."""
    h = H()
    h.g.define(1, HOT, 0.0)
    h.hear(beacon(src=2, gid=500, leader=2, weight=40, seq=17))
    h.advance(0.5)
    h.g.parent_failed(1, 2, h.now)  # 0.5 s after the beacon: evidence is fresh
    claim_at = 1.25 * h.cfg.beacon_period
    h.advance(claim_at - 0.01)
    h.g.parent_acked(1, 2, h.now)  # the leader acked a retry later: alive
    h.advance(claim_at + 1.0)
    assert h.events(LeaderElected) == []
    assert h.g.membership(1).leader == 2  # type: ignore[union-attr]
    # Now it really is gone: the next failed partial claims at once (evidence stale).
    h.advance(h.now + 1.3 * claim_at)
    h.g.parent_failed(1, 2, h.now)
    h.advance(h.now + 2 * h.cfg.forward_jitter + 0.01)
    (e,) = h.events(LeaderElected)
    assert (e.cause, e.group_id) == (ElectionCause.FAILOVER, 500)
    assert h.g.stats.failovers == 1


def test_two_claimants_converge_on_the_heavier_then_higher_node() -> None:
    """Two members claimed the same id: a member follows the (seq, weight, leader)
    order, the lighter claimant yields without a GONE report and adopts the winner."""
    h = H()  # node 10
    h.g.define(1, HOT, 0.0)
    h.hear(beacon(src=2, gid=500, leader=2, weight=40, seq=17))
    h.hear(beacon(src=7, gid=500, leader=7, weight=40, seq=18))  # claimant 7
    assert h.g.membership(1).leader == 7  # type: ignore[union-attr]
    h.hear(beacon(src=12, gid=500, leader=12, weight=40, seq=18))  # claimant 12, same seq
    assert h.g.membership(1).leader == 12  # type: ignore[union-attr]
    h.hear(beacon(src=7, gid=500, leader=7, weight=40, seq=18))  # stale now
    assert h.g.membership(1).leader == 12  # type: ignore[union-attr]
    # As a claimant itself, node 10 yields to 12 (same weight, higher node id) ...
    h2 = H()
    h2.g.define(1, HOT, 0.0)
    h2.hear(beacon(src=2, gid=500, leader=2, weight=40, seq=17))
    timeout = h2.cfg.leader_timeout_periods * h2.cfg.beacon_period
    h2.advance(timeout + 0.2)
    assert h2.g.membership(1).is_leader  # type: ignore[union-attr]
    h2.events()
    h2.hear(beacon(src=12, gid=500, leader=12, weight=40, seq=18))
    (y,) = h2.events(LeaderYielded)
    assert y.successor == 500 and h2.g.membership(1).leader == 12  # type: ignore[union-attr]
    assert not [r for r in h2.reports() if r.status is GroupStatus.GONE]
    # ... and beats 7: it keeps the group and outnumbers 7's seq.
    h3 = H()
    h3.g.define(1, HOT, 0.0)
    h3.hear(beacon(src=2, gid=500, leader=2, weight=40, seq=17))
    h3.advance(timeout + 0.2)
    h3.hear(beacon(src=7, gid=500, leader=7, weight=40, seq=30))
    assert h3.g.membership(1).is_leader  # type: ignore[union-attr]
    h3.sent()
    h3.advance(h3.now + h3.cfg.beacon_period + 0.01)
    b = [f for f in h3.sent() if isinstance(f, LeaderBeacon) and f.leader == 10]
    assert b and b[-1].seq > 30


def _merged_then_lost(gap: float) -> tuple[H, float]:
    """A member of group 600 (weight 10) swept into the heavier 500 (weight 40),
    whose distant leader is then lost ``gap`` s after the merge."""
    h = H()
    h.g.define(1, HOT, 0.0)
    h.hear(beacon(src=3, gid=600, leader=3, weight=10, seq=5, hops=0))
    h.advance(1.0)
    h.hear(beacon(src=4, gid=500, leader=2, weight=40, seq=17, hops=1))  # the merge
    m = h.g.membership(1)
    assert m is not None and m.group_id == 500
    for k in range(int(gap // h.cfg.beacon_period)):
        h.advance(h.now + h.cfg.beacon_period)
        h.hear(beacon(src=4, gid=500, leader=2, weight=40 + k, seq=18 + k, hops=1))
    h.events()
    timeout = h.cfg.leader_timeout_periods * h.cfg.beacon_period
    lost = h.now + timeout + h.cfg.beacon_period
    h.advance(lost + ELECTION_BACKOFF_FACTOR * h.cfg.create_backoff + 0.02)
    return h, lost


def test_a_part_that_loses_the_merged_group_soon_takes_its_former_id_back() -> None:
    h, _ = _merged_then_lost(gap=4.0)
    (e,) = h.events(LeaderElected)
    assert e.cause is ElectionCause.ELECTION and e.group_id == 600 and e.weight == 0


def test_a_split_long_after_the_merge_gets_a_new_id() -> None:
    h, _ = _merged_then_lost(gap=h_window() + 2.0)
    (e,) = h.events(LeaderElected)
    assert e.cause is ElectionCause.ELECTION and e.group_id not in (500, 600)


def h_window() -> float:
    cfg = H().cfg
    return cfg.unmerge_window_periods * cfg.beacon_period


@settings(max_examples=400, deadline=None)
@given(
    st.sampled_from(list(Op)),
    st.floats(-100, 100),
    st.floats(0, 5),
    st.floats(-100, 100),
    st.floats(0, 30),
    st.floats(0, 1),
)
def test_a_condition_that_may_not_hold_on_an_interval_fails_everywhere_in_it(
    op: Op, thr: float, relax: float, lo: float, width: float, f: float
) -> None:
    # Group checks skip a read when condition_may_hold says no (ReadBounds).
    c = Condition(TEMPERATURE, op, thr)
    hi = lo + width
    if not condition_may_hold(c, lo, hi, relax):
        for v in (lo, hi, lo + f * width, thr, thr - relax, thr + relax):
            if lo <= v <= hi:
                assert not condition_holds(c, v, relax)
    if condition_holds(c, lo + f * width, relax):
        assert condition_may_hold(c, lo, hi, relax)


class Bounded(App):
    """Says its readings stay within a degree of their value until ``until``
    (the default, -inf: at the time asked only); counts the reads."""

    def __init__(self, until: float = -math.inf, **values: float | None) -> None:
        super().__init__(**values)
        self.until = until
        self.reads = 0

    def read(self, attr: int, now: float) -> float | None:
        self.reads += 1
        return super().read(attr, now)

    def read_bounds(self, attr: int, now: float) -> Bounds | None:
        v = self.values.get(attr)
        return None if v is None else Bounds(v - 1.0, v + 1.0, self.until)


def bounded(temp: float, until: float = -math.inf) -> tuple[H, Bounded]:
    h = H()
    app = Bounded(until, t=temp)
    h.ctx.app = app
    return h, app


def test_a_group_check_takes_no_reading_outside_what_can_qualify() -> None:
    for temp, reads in ((20.0, 0), (80.0, 1)):
        h, app = bounded(temp)
        h.g.define(1, HOT, 0.0)
        assert app.reads == reads  # the hot mote read (and qualifies); the cold one did not
        assert h.g.role(1) is (Role.IDLE if temp == 20.0 else Role.WAITING)


def test_a_mote_whose_conditions_are_ruled_out_for_good_parks_its_checks() -> None:
    parked, _ = bounded(20.0, until=math.inf)
    ticking, _ = bounded(20.0)  # bounds for the moment only
    firsts = []
    for h in (parked, ticking):
        h.g.define(1, HOT, 0.0)
        firsts.append(h.g.timers.get("check"))
        h.advance(500.0)
        assert h.g.role(1) is Role.IDLE
    assert firsts[0] == firsts[1] is not None
    schedule = [firsts[0]]  # the checks' instants: sums of periods, as the mote adds
    while schedule[-1] < 600.0:
        schedule.append(schedule[-1] + parked.cfg.check_period)
    # Parked: one check every PARK_PERIODS periods ("not in", parks again).
    assert parked.g.stats.checks_parked == 2
    assert parked.g.timers.next_deadline() == schedule[2 * PARK_PERIODS]
    assert ticking.g.stats.checks_parked == 0
    assert ticking.g.timers.next_deadline() == next(t for t in schedule if t > 500.0)


def test_a_parked_mote_checks_until_a_finite_horizon_then_on_its_old_schedule() -> None:
    parked, app = bounded(20.0, until=50.25)
    ticking, _ = bounded(20.0)
    for h in (parked, ticking):
        h.g.define(1, HOT, 0.0)
        h.advance(10.0)
    wake = parked.g.timers.get("check")
    assert wake is not None and 50.25 <= wake < 51.25
    ticking.advance(wake - 0.01)
    assert ticking.g.timers.get("check") == wake  # the instant it would have checked anyway
    app.until = -math.inf  # from then on, bounds for the moment only: no more parking
    parked.advance(wake)
    assert parked.g.timers.get("check") == wake + parked.cfg.check_period


def test_a_mote_parked_until_the_fire_comes_joins_when_a_ticking_one_would() -> None:
    parked, papp = bounded(20.0, until=30.2)
    ticking, tapp = bounded(20.0)
    for h, app in ((parked, papp), (ticking, tapp)):
        h.g.define(1, HOT, 0.0)
        h.advance(30.1)
        app.until = -math.inf
        app.values[T] = 80.0  # the fire arrives as foretold
        h.advance(40.0)
        assert h.g.role(1) is not Role.IDLE
    assert parked.g.stats.checks_parked == 1
    assert parked.events() == ticking.events()  # the same decisions at the same instants
    assert parked.g.timers.get("create") == ticking.g.timers.get("create")


def test_a_group_frame_wakes_a_parked_mote_on_the_schedule_it_left() -> None:
    parked, papp = bounded(20.0, until=math.inf)
    ticking, tapp = bounded(20.0)
    for h in (parked, ticking):
        h.g.define(1, HOT, 0.0)
        h.advance(37.3)
        h.hear(beacon(4, gid=500, leader=4))
    assert parked.g.timers.get("check") == ticking.g.timers.get("check")
    for h, app in ((parked, papp), (ticking, tapp)):
        app.values[T] = 80.0  # the fire comes
        h.advance(38.5)
        h.hear(beacon(4, gid=500, leader=4, seq=2))
        assert h.g.role(1) is Role.MEMBER
    assert parked.events(GroupJoined) == ticking.events(GroupJoined)


def test_a_command_wakes_a_parked_mote() -> None:
    h, app = bounded(20.0, until=math.inf)
    h.g.define(1, HOT, 0.0)
    h.advance(20.0)
    parked_until = h.g.timers.get("check")
    assert parked_until is not None and parked_until > h.now + 100 * h.cfg.check_period
    Commands(h.ctx, h.g).define(0, CommandDef("set_rate", args=(("period_s", 2.0),)), h.now)
    due = h.g.timers.get("check")
    assert due is not None and h.now <= due < h.now + h.cfg.check_period
    app.until = -math.inf
    app.values[T] = 80.0  # what the command changed: readings now qualify
    h.advance(due)
    assert h.g.role(1) is Role.WAITING


def test_a_definition_wakes_a_parked_mote_without_a_new_phase() -> None:
    parked, _ = bounded(20.0, until=math.inf)
    ticking, _ = bounded(20.0)
    other = GroupTypeDef((Condition(HUMIDITY, Op.GT, 50.0),))
    for h in (parked, ticking):
        h.g.define(1, HOT, 0.0)
        h.advance(12.6)
        h.g.define(2, other, h.now)
    assert parked.g.timers.get("check") == ticking.g.timers.get("check")


NEAR_ROBOT = GroupTypeDef((Condition(rssi_attribute(7), Op.GT, -70.0),))


@pytest.mark.pure_python
def test_a_mote_that_never_heard_the_node_of_an_rssi_condition_parks_until_it_does(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """rssi:<node> cannot hold before the node is heard: a mote parks its checks of
    such a type, and the node's first frame (heard_again) puts it back on the
    schedule it left, to decide as a mote that never parked."""
    parked, ticking = H(), H()

    def until_the_robot(h: H) -> None:
        h.g.define(2, NEAR_ROBOT, 0.0)
        h.advance(40.0)
        assert h.g.role(2) is Role.IDLE

    with monkeypatch.context() as m:  # the ticking mote: no RSSI parking
        m.setattr(conditions_module, "unheard", lambda ctx, attr, now: False)
        until_the_robot(ticking)
    until_the_robot(parked)
    assert ticking.g.stats.checks_parked == 0
    assert parked.g.stats.checks_parked == 1  # parked at its first check, for good
    first = parked.g.timers.get("check")
    assert first is not None and first > 40.0 + parked.cfg.check_period
    parked.g.heard_again(9, 40.0)  # another node: still parked
    assert parked.g.timers.get("check") == first
    for h in (parked, ticking):
        h.ctx.rssi[7] = RssiSample(-60.0, 40.0)  # the robot's first frame, heard strongly
        h.g.heard_again(7, 40.0)
    assert parked.g.timers.get("check") == ticking.g.timers.get("check")
    for h in (parked, ticking):
        h.advance(45.0)
        assert h.g.role(2) is not Role.IDLE
    assert parked.events() == ticking.events()


@pytest.mark.parametrize("acked", [True, False])
def test_a_settled_member_probes_its_leader_after_one_unacknowledged_partial(
    acked: bool,
) -> None:
    """In a settled group (beacons every two periods) one partial the leader did not
    acknowledge is no death (a collision): the member asks the leader at once with a
    unicast copy of its beacon; an ACK keeps the leader, a failed probe is the second
    failure and the member claims -- within the epoch, not at its next partial."""
    h = H()
    p = h.cfg.beacon_period
    h.g.define(1, HOT, 0.0)
    h.hear(beacon(src=2, gid=500, leader=2, weight=40, seq=17))
    h.advance(2 * p)
    h.hear(beacon(src=2, gid=500, leader=2, weight=40, seq=18))  # a settled pace: 2 periods
    h.sent()
    h.events()
    h.advance(h.now + 1.3 * 1.25 * p)  # the leader's last sign of life is stale now
    h.g.parent_failed(1, 2, h.now)
    (probe,) = [f for f in h.sent() if isinstance(f, LeaderBeacon) and f.dst == 2]
    assert (probe.group_id, probe.leader, probe.seq) == (500, 2, 18)
    assert h.g.stats.leader_probes == 1
    h.advance(h.now + 2 * h.cfg.forward_jitter + 0.01)
    assert h.events(LeaderElected) == []  # one failure: no claim yet
    h.link(probe, acked)
    h.advance(h.now + 2 * h.cfg.forward_jitter + 0.01)
    elected = h.events(LeaderElected)
    if acked:
        assert elected == [] and h.g.membership(1).leader == 2  # type: ignore[union-attr]
    else:
        (e,) = elected
        assert (e.cause, e.group_id) == (ElectionCause.FAILOVER, 500)
