"""Frame codec: every frame type round-trips; garbage only ever raises FrameError."""

from __future__ import annotations

from typing import Any

import msgpack
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from awaremw.protocol.frames import (
    BROADCAST,
    FRAME_TYPES,
    MAX_NODE_ID,
    AggId,
    ChannelDef,
    CommandDef,
    Condition,
    CtpBeacon,
    CtpData,
    DataRecord,
    DripItem,
    DripSig,
    DripSummary,
    Frame,
    FrameError,
    FrameTooLarge,
    GroupReport,
    GroupStatus,
    GroupTypeDef,
    Handover,
    Hello,
    ItemBody,
    ItemKind,
    LeaderBeacon,
    NotAFrame,
    Op,
    Partial,
    TargetKind,
    TruncatedFrame,
    UnknownFrameType,
    decode,
    encode,
    peek_header,
)

# --------------------------------------------------------------------------- strategies

u8 = st.integers(0, 0xFF)
u16 = st.integers(0, 0xFFFF)
u32 = st.integers(0, 0xFFFFFFFF)
node = st.integers(0, MAX_NODE_ID)
addr = st.one_of(node, st.just(BROADCAST))
gid = st.integers(1, 0xFFFE)
f32 = st.floats(width=32, allow_nan=False, allow_infinity=False)  # floats travel as float32

conditions = st.builds(Condition, u16, st.sampled_from(Op), f32)
group_types = st.builds(
    GroupTypeDef,
    st.lists(conditions, min_size=1, max_size=8).map(tuple),
    st.floats(0, 1e6, width=32),
)
channels = st.builds(ChannelDef, u16, u8, u16, st.integers(1, 0xFFFFFFFF), u8)
scalars = st.one_of(st.integers(-(2**31), 2**31 - 1), f32, st.text(max_size=8), st.booleans())
commands = st.builds(
    CommandDef,
    st.text(min_size=1, max_size=16),
    st.sampled_from(TargetKind),
    u16,
    u16,
    st.lists(st.tuples(st.text(max_size=8), scalars), max_size=8).map(tuple),
)


@st.composite
def drip_items(draw: st.DrawFn) -> DripItem:
    kind = draw(st.sampled_from(ItemKind))
    body: dict[ItemKind, st.SearchStrategy[ItemBody]] = {
        ItemKind.GROUP_TYPE: group_types,
        ItemKind.CHANNEL: channels,
        ItemKind.COMMAND: commands,
    }
    item = draw(st.none() | body[kind])
    return DripItem(draw(node), draw(addr), kind, draw(u16), draw(u32), item)


records = st.builds(DataRecord, u8, u8, u16, u32, u8, f32, u32, node)
reports = st.builds(GroupReport, u8, u16, node, u32, u16, st.sampled_from(GroupStatus), u16)

frames: st.SearchStrategy[Frame] = st.one_of(
    st.builds(Hello, node, addr, u16),
    drip_items(),
    st.builds(DripSummary, node, addr, u32, u16),
    st.builds(
        DripSig,
        node,
        addr,
        st.sampled_from(ItemKind),
        u16,
        u32,
        st.integers(0, 1),
        st.binary(min_size=32, max_size=32),
    ),
    st.builds(CtpBeacon, node, addr, u16, addr, st.booleans()),
    st.builds(CtpData, node, addr, node, u16, u8, u16, records | reports),
    st.builds(LeaderBeacon, node, addr, u8, gid, node, u32, u16, u8, st.booleans(), addr),
    st.builds(Handover, node, addr, u8, gid, u32, u16),
    st.builds(Partial, node, addr, u8, u8, gid, u32, u8, u32, st.lists(f32, max_size=4).map(tuple)),
)

msgpack_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(2**63), 2**64 - 1)
    | st.floats()
    | st.text(max_size=10)
    | st.binary(max_size=10),
    lambda inner: (
        st.lists(inner, max_size=6) | st.dictionaries(st.text(max_size=4), inner, max_size=4)
    ),
    max_leaves=25,
)


def expect_frame_or_frame_error(data: bytes) -> Frame | None:
    """decode() may succeed or raise FrameError; anything else is a bug."""
    try:
        f = decode(data)
    except FrameError:
        return None
    assert isinstance(f, Frame)
    assert decode(encode(f)) == f  # whatever was accepted is a valid frame
    return f


# --------------------------------------------------------------------------- round trips


@settings(max_examples=300, deadline=None)
@given(frames)
def test_every_frame_round_trips(f: Frame) -> None:
    data = encode(f)
    g = decode(data)
    assert g == f and type(g) is type(f)
    assert encode(g) == data  # canonical bytes
    assert peek_header(data) == (f.TYPE, f.src, f.dst)


def test_every_frame_type_is_covered() -> None:
    assert {t.__name__ for t in FRAME_TYPES.values()} == {
        "Hello",
        "DripItem",
        "DripSummary",
        "DripSig",
        "CtpBeacon",
        "CtpData",
        "LeaderBeacon",
        "Handover",
        "Partial",
    }


def test_mtu_is_enforced_on_encode() -> None:
    big = DripItem(
        1, BROADCAST, ItemKind.COMMAND, 1, 1, CommandDef("x" * 16, args=(("a" * 20, "b" * 40),))
    )
    assert len(encode(big)) > 64
    with pytest.raises(FrameTooLarge) as e:
        encode(big, 64)
    assert e.value.mtu == 64 and e.value.size == len(encode(big))
    assert encode(Hello(1, BROADCAST, 0), 64)


def test_typical_frames_fit_the_cc1000_mtu() -> None:
    beacon = LeaderBeacon(1, BROADCAST, 1, 0xFFFE, 32767, 0xFFFFFFFF, 0xFFFF, 255, parent=32767)
    data = CtpData(1, 2, 3, 4, 5, 6, DataRecord(1, 1, 513, 100, int(AggId.AVG), 21.5, 12, 7))
    for f in (beacon, data, Partial(1, 2, 0, 1, 513, 9, 0, 3, (1.0, 2.0))):
        assert len(encode(f, 64)) <= 64


# --------------------------------------------------------------------------- garbage


@settings(max_examples=600, deadline=None)
@given(st.binary(max_size=200))
def test_random_bytes_only_raise_frame_error(data: bytes) -> None:
    expect_frame_or_frame_error(data)


@settings(max_examples=300, deadline=None)
@given(msgpack_values)
def test_random_msgpack_only_raises_frame_error(value: Any) -> None:
    data = msgpack.packb(value, use_bin_type=True)
    assert expect_frame_or_frame_error(data) is None or isinstance(value, list)


@settings(max_examples=500, deadline=None)
@given(frames, st.data())
def test_mutated_frames_only_raise_frame_error(f: Frame, data: st.DataObject) -> None:
    # Replace one field (anywhere in the nested arrays) with a random value.
    wire = msgpack.unpackb(encode(f))
    path: list[int] = []
    cur: Any = wire
    while True:
        i = data.draw(st.integers(0, len(cur) - 1))
        path.append(i)
        if isinstance(cur[i], list) and cur[i] and data.draw(st.booleans()):
            cur = cur[i]
        else:
            break
    target = wire
    for i in path[:-1]:
        target = target[i]
    target[path[-1]] = data.draw(msgpack_values)
    expect_frame_or_frame_error(msgpack.packb(wire, use_bin_type=True))


@settings(max_examples=300, deadline=None)
@given(frames, st.integers(1, 10**6))
def test_truncated_and_extended_frames(f: Frame, cut: int) -> None:
    data = encode(f)
    assume(len(data) > 1)
    with pytest.raises(TruncatedFrame):
        decode(data[: 1 + cut % (len(data) - 1)])
    with pytest.raises(TruncatedFrame):
        decode(data + b"\x00")


def test_specific_errors() -> None:
    with pytest.raises(TruncatedFrame):
        decode(b"")
    with pytest.raises(TruncatedFrame):
        decode(b"\xc1")
    with pytest.raises(NotAFrame):
        decode(msgpack.packb({"type": 1}))
    with pytest.raises(NotAFrame):
        decode(msgpack.packb([1, "a", 2]))
    with pytest.raises(UnknownFrameType):
        decode(msgpack.packb([99, 1, 2]))
    with pytest.raises(FrameError):
        decode(msgpack.packb([1, 1, 2]))  # Hello without its seq
    with pytest.raises(FrameError):
        decode(msgpack.packb([1, 0xFFFE, 2, 0]))  # src out of range (0xFFFE: no short address)


def test_float64_on_the_wire_decodes_as_the_float32_it_will_be_re_sent_as() -> None:
    # Found by the mutation test: a foreign encoder sent a command argument as the
    # float64 16777217.0; we decoded it as such, and re-encoding (float32) gave
    # 16777216.0, so the frame a mote forwards differed from the one it adopted.
    args = [["a", 16777217.0]]
    body = [2, 1, 1, ["x", 0, 0, 0, args]]  # kind COMMAND, id, version, body
    data = msgpack.packb([DripItem.TYPE, 1, BROADCAST, *body], use_single_float=False)
    f = decode(data)
    assert isinstance(f, DripItem) and isinstance(f.item, CommandDef)
    assert f.item.args == (("a", 16777216.0),)
    assert decode(encode(f)) == f
    too_big = msgpack.packb(
        [DripItem.TYPE, 1, BROADCAST, 2, 1, 1, ["x", 0, 0, 0, [["a", 1e300]]]],
        use_single_float=False,
    )
    with pytest.raises(FrameError):
        decode(too_big)


def test_decode_shared_shares_equal_bytes_and_never_keeps_failures() -> None:
    """One transmission's receivers share the decoded frame; different bytes
    decode afresh; malformed bytes raise every time, and do not evict."""
    from awaremw.protocol.frames import CtpBeacon, FrameError, decode, decode_shared, encode

    a = encode(CtpBeacon(3, BROADCAST, 20, 1))
    b = encode(CtpBeacon(4, BROADCAST, 30, 1))
    fa = decode_shared(a)
    assert fa == decode(a)
    assert decode_shared(bytes(bytearray(a))) is fa  # equal bytes, another object
    for _ in range(2):
        with pytest.raises(FrameError):
            decode_shared(b"\xc1garbage")
    assert decode_shared(a) is fa  # the failure did not replace the entry
    fb = decode_shared(b)
    assert fb == decode(b) and fb is not fa


def test_a_frame_noted_as_sent_is_what_its_bytes_decode_to() -> None:
    from enum import IntEnum

    from awaremw.protocol import frames as F

    b = F.CtpBeacon(3, F.BROADCAST, 40, 7, True)
    data = F.encode(b)
    F.note_sent(data, b)
    got = F.decode_shared(data)
    assert got is b and got == F.decode(data)  # the first receiver takes the object
    assert data not in F._sent  # and the entry is gone

    class Small(IntEnum):
        SEVEN = 7

    odd = F.CtpBeacon(3, F.BROADCAST, 41, Small.SEVEN, False)  # decodes to a plain int
    F.note_sent(F.encode(odd), odd)
    assert F.encode(odd) not in F._sent
    item = F.DripSummary(4, F.BROADCAST, 1, 2)
    F.note_sent(F.encode(item), item)
    assert F.decode_shared(F.encode(item)) == item
    part = F.Partial(5, 6, 1, 1, 9, 3, 0, 1, (0.1,))  # a float field: never kept
    F.note_sent(F.encode(part), part)
    assert F.encode(part) not in F._sent
