"""The mote composition: decoding, RSSI attributes, timers, link results."""

from __future__ import annotations

import random

import pytest

from awaremw.protocol.attributes import (
    RSSI_BASE,
    UnknownAttribute,
    attribute_id,
    attribute_name,
)
from awaremw.protocol.config import MiddlewareConfig
from awaremw.protocol.core import Transmission
from awaremw.protocol.events import MalformedFrame
from awaremw.protocol.frames import BROADCAST, Hello, decode, encode
from awaremw.protocol.mote import AwareMote
from awaremw.protocol.timers import TimerSet


def test_attribute_names_round_trip() -> None:
    for name in ("temperature", "humidity", "light", "x", "y", "battery", "rssi:17"):
        assert attribute_name(attribute_id(name)) == name
    assert attribute_id("rssi:17") == RSSI_BASE | 17


@pytest.mark.parametrize("bad", ["temp", "rssi:", "rssi:x", "rssi:65534", ""])
def test_unknown_attribute_is_a_specific_error(bad: str) -> None:
    with pytest.raises(UnknownAttribute, match=r"rssi|unknown attribute"):
        attribute_id(bad)


def test_garbage_frame_is_reported_not_raised() -> None:
    m = AwareMote(5, rng=random.Random(1))
    m.start(0.0)
    m.receive(b"\xc1\xff garbage", -70.0, 1.0)
    events = m.events()
    assert len(events) == 1 and isinstance(events[0], MalformedFrame)
    assert m.ctx.rssi == {}  # nothing else changed


def test_rssi_attribute_is_an_ewma_that_expires() -> None:
    cfg = MiddlewareConfig(rssi_alpha=0.5, rssi_ttl=2.0)
    m = AwareMote(5, config=cfg, rng=random.Random(1))
    m.start(0.0)
    attr = RSSI_BASE | 9
    assert m.ctx.read(attr, 0.0) is None
    m.receive(encode(Hello(9, BROADCAST, 1)), -60.0, 1.0)
    assert m.ctx.read(attr, 1.0) == -60.0
    m.receive(encode(Hello(9, BROADCAST, 2)), -70.0, 1.5)
    assert m.ctx.read(attr, 1.5) == pytest.approx(-65.0)
    assert m.ctx.read(attr, 3.6) is None  # older than rssi_ttl


def test_hello_beacon_period() -> None:
    m = AwareMote(3, config=MiddlewareConfig(hello_period=0.5), rng=random.Random(2))
    m.start(0.0)
    sent: list[Transmission] = []
    now = 0.0
    while now < 5.0:
        d = m.next_deadline()
        assert d is not None
        now = d
        m.handle_timer(now)
        sent += [t for t in m.drain() if isinstance(decode(t.frame), Hello)]
    assert 9 <= len(sent) <= 11
    assert all(t.dest == BROADCAST for t in sent)


def test_timerset_fires_in_time_order() -> None:
    t = TimerSet()
    t.set("b", 2.0)
    t.set("a", 1.0)
    t.set("c", 5.0)
    assert t.next_deadline() == 1.0
    assert t.due(3.0) == ["a", "b"]
    assert t.next_deadline() == 5.0


def test_unicode_digits_are_an_unknown_attribute_not_a_crash() -> None:
    # str.isdigit() accepts "²" and "٣" while int() refuses them: the name must be
    # refused as unknown (the specific error), not end in a ValueError traceback.
    import pytest

    from awaremw.protocol.attributes import UnknownAttribute, attribute_id

    for name in ("rssi:²", "rssi:٣", "rssi:1²"):
        with pytest.raises(UnknownAttribute):
            attribute_id(name)
    assert attribute_id("rssi:100") == attribute_id("rssi:0100")


@pytest.mark.parametrize("node", [0, 32767, 32768, 50000, 65533])
def test_every_short_address_has_its_rssi_attribute(node: int) -> None:
    """rssi:<id> covers the whole 16-bit short address space (0xFFFE and 0xFFFF
    are reserved by IEEE 802.15.4), round-trips, and rides in a condition frame."""
    from awaremw.protocol.attributes import attribute_name, is_rssi
    from awaremw.protocol.frames import Condition, GroupTypeDef, Op

    attr = attribute_id(f"rssi:{node}")
    assert is_rssi(attr) and attribute_name(attr) == f"rssi:{node}"
    assert Condition(attr, Op.GT, -70.0).attr == attr
    assert GroupTypeDef((Condition(attr, Op.GT, -70.0),)).conditions[0].attr == attr
