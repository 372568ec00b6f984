"""HelloMote, the stand-in core, driven by hand (no driver)."""

from __future__ import annotations

import itertools
import random

from hypothesis import given, settings
from hypothesis import strategies as st

from awaremw.protocol.core import MoteCore, Transmission
from awaremw.protocol.events import MalformedFrame, NeighbourFound, NeighbourLost, PingResult
from awaremw.protocol.frames import BROADCAST, DripSummary, Hello, decode, encode
from awaremw.protocol.hello import HelloMote


def mote(node_id: int = 1, period: float = 1.0, **kw: float) -> HelloMote:
    m = HelloMote(node_id, period, random.Random(node_id), 100, **kw)
    m.start(0.0)
    return m


def run_timers(m: HelloMote, until: float) -> list[tuple[float, Transmission]]:
    sent: list[tuple[float, Transmission]] = []
    while (t := m.next_deadline()) is not None and t <= until:
        m.handle_timer(t)
        sent.extend((t, tx) for tx in m.drain())
    return sent


def test_is_a_mote_core() -> None:
    assert isinstance(mote(), MoteCore)


def test_beacons_periodically_with_jitter() -> None:
    m = mote(7, period=2.0, jitter=0.1)
    sent = run_timers(m, 200.0)
    assert 95 <= len(sent) <= 105
    times = [t for t, _ in sent]
    assert 0.0 <= times[0] <= 2.0
    gaps = [b - a for a, b in itertools.pairwise(times)]
    assert all(1.8 <= g <= 2.2 for g in gaps)
    assert len(set(gaps)) > 50  # jittered, not a fixed period
    for i, (_, tx) in enumerate(sent):
        assert tx.dest == BROADCAST and not tx.is_unicast
        assert tx.frame == encode(Hello(7, BROADCAST, i))  # the fast path is the codec's bytes
    # Nothing happens before the deadline.
    m2 = mote(3)
    dl = m2.next_deadline()
    assert dl is not None
    m2.handle_timer(dl - 1e-6)
    assert m2.drain() == []


def test_neighbour_table_and_expiry() -> None:
    m = mote(1, period=1.0, expiry_s=3.0)
    m.receive(encode(Hello(2, BROADCAST, 0)), -70.0, 0.5)
    m.receive(encode(Hello(3, BROADCAST, 0)), -80.0, 0.6)
    m.receive(encode(Hello(2, BROADCAST, 1)), -72.0, 1.5)
    assert m.table == {2: (-72.0, 1.5), 3: (-80.0, 0.6)}
    assert m.events() == [NeighbourFound(2, -70.0), NeighbourFound(3, -80.0)]
    assert m.hellos_rx == 3
    assert set(m.neighbours(3.7)) == {2}  # 3 last heard 3.1 s ago
    # Entries expire at beacon times (at least one per 1.1 s with 10 % jitter).
    last = run_timers(m, 5.0)[-1][0]
    assert 3 not in m.table
    assert (2 in m.table) == (last - 1.5 <= 3.0)
    ev = m.events()
    assert ev[0] == NeighbourLost(3)
    run_timers(m, 10.0)
    ev += m.events()
    assert m.table == {} and ev == [NeighbourLost(3), NeighbourLost(2)]


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=120))
def test_garbage_is_reported_and_changes_nothing(data: bytes) -> None:
    m = mote(1)
    m.receive(encode(Hello(2, BROADCAST, 0)), -70.0, 0.1)
    m.events()
    before = (dict(m.table), m.hellos_rx, m.pings_rx, m.next_deadline())
    m.receive(data, -60.0, 0.2)
    evs = m.events()
    try:
        f = decode(data)
    except ValueError:
        assert len(evs) == 1 and isinstance(evs[0], MalformedFrame)
        assert evs[0].size == len(data)
        assert (dict(m.table), m.hellos_rx, m.pings_rx, m.next_deadline()) == before
    else:  # hypothesis found a valid frame: it must be treated as one
        assert not any(isinstance(e, MalformedFrame) for e in evs)
        assert isinstance(f, Hello) or m.ignored == 1
    assert m.drain() == []


def test_other_frames_and_stray_unicasts_are_ignored() -> None:
    m = mote(1)
    m.receive(encode(DripSummary(2, BROADCAST, 5, 1)), -70.0, 0.1)
    m.receive(encode(Hello(2, 9, 0)), -70.0, 0.2)  # unicast for mote 9
    assert m.ignored == 2 and m.table == {} and m.events() == []
    m.receive(encode(Hello(2, 1, 0)), -71.0, 0.3)  # a ping for us
    assert m.pings_rx == 1 and m.table == {2: (-71.0, 0.3)}


def test_ping_reports_link_result() -> None:
    m = mote(1)
    tx = m.ping(4)
    assert m.drain() == [tx]
    assert tx.dest == 4 and tx.is_unicast and decode(tx.frame) == Hello(1, 4, 0)
    m.link_result(tx, False, 1.0)
    assert m.events() == [PingResult(4, False)]
    other = Transmission.unicast(b"x", 4)  # not ours: no event
    m.link_result(other, True, 1.0)
    assert m.events() == []
