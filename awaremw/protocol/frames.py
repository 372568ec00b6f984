"""Radio frames: typed, validated, msgpack-encoded.

A frame is what a real mote would put on the air. On the wire it is a msgpack
array ``[type, src, dst, *body]``: integer type tag, 16-bit link addresses
(``dst == BROADCAST`` for broadcast) and the body fields in declaration order.
Nested objects (conditions, definitions, records) are arrays too; floats are
packed as float32. Nothing here knows about the emulator's envelope (sender
position, TX power): only these bytes count toward the MTU and the energy.

Construction validates every field (a local bug raises ``ValueError``);
:func:`decode` turns any malformed input into a :class:`FrameError` subclass
and nothing else (a remote fault, to be counted and reported, never a crash).
"""

from __future__ import annotations

import math
import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any, ClassVar, TypeAlias

import msgpack

BROADCAST = 0xFFFF
# Node ids are IEEE 802.15.4 short addresses: 0xFFFF is broadcast and 0xFFFE
# means "no short address", so 0..0xFFFD (65,534 motes) name motes.
MAX_NODE_ID = 0xFFFD
NODE_MASK = 0xFFFF  # the node id inside an rssi:<id> attribute id
# Attribute ids: standard and custom ones below RSSI_BASE; rssi:<id> is RSSI_BASE | id.
RSSI_BASE = 0x10000
MAX_ATTRIBUTE_ID = RSSI_BASE | MAX_NODE_ID
ANY_GROUP_TYPE = 0xFF
ANY_GROUP_ID = 0xFFFF  # never a real group id (real ids are 1..0xFFFE)
NO_ROUTE = 0xFFFF  # collection cost of a mote without a route
MAX_CONDITIONS = 8
MAX_COMMAND_NAME = 16
MAX_COMMAND_ARGS = 8


# --------------------------------------------------------------------------- errors


class FrameError(ValueError):
    """Malformed frame received from the radio (a remote fault)."""


class TruncatedFrame(FrameError):
    """The bytes are not one complete msgpack value."""


class NotAFrame(FrameError):
    """The msgpack value is not a frame array ``[type, src, dst, ...]``."""


class UnknownFrameType(FrameError):
    """The type tag names no frame this middleware knows."""


class BadField(FrameError):
    """A field has the wrong type, arity or range."""


class FrameTooLarge(ValueError):
    """Encoding would exceed the radio's MTU (a local error: we built it)."""

    def __init__(self, frame: Frame, size: int, mtu: int) -> None:
        super().__init__(f"{type(frame).__name__} encodes to {size} bytes > MTU {mtu}")
        self.frame, self.size, self.mtu = frame, size, mtu


# --------------------------------------------------------------------------- validators


def _int(name: str, v: object, lo: int, hi: int) -> None:
    if not isinstance(v, int) or isinstance(v, bool) or not lo <= v <= hi:
        raise ValueError(f"{name}={v!r} is not an integer in [{lo}, {hi}]")


def _u8(name: str, v: object) -> None:
    _int(name, v, 0, 0xFF)


def _u16(name: str, v: object) -> None:
    _int(name, v, 0, 0xFFFF)


def _u32(name: str, v: object) -> None:
    _int(name, v, 0, 0xFFFFFFFF)


def _real(name: str, v: object) -> None:
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        raise ValueError(f"{name}={v!r} is not a finite number")


_F32 = struct.Struct("<f")


def _wire_real(name: str, v: Any) -> Any:
    """A number read off the wire, as the wire carries it: floats go on the air as
    float32, so a float (a foreign encoder may send float64) is rounded to float32,
    and one that float32 cannot hold is refused. The decoded frame then equals its
    canonical re-encoding. Anything else is returned for the field's own check."""
    if isinstance(v, float):
        try:
            return float(_F32.unpack(_F32.pack(v))[0])
        except (OverflowError, struct.error):
            raise BadField(f"{name}={v!r} does not fit a float32") from None
    return v


def _node(name: str, v: object) -> None:
    _int(name, v, 0, MAX_NODE_ID)


def _addr(name: str, v: object) -> None:
    if v != BROADCAST:
        _node(name, v)


# --------------------------------------------------------------------------- enums


class Op(IntEnum):
    """Comparison operator of a group condition."""

    LT = 0
    LE = 1
    GT = 2
    GE = 3
    EQ = 4
    NE = 5

    @property
    def symbol(self) -> str:
        return ("<", "<=", ">", ">=", "==", "!=")[self]

    @classmethod
    def from_symbol(cls, s: str) -> Op:
        try:
            return cls(("<", "<=", ">", ">=", "==", "!=").index(s))
        except ValueError:
            raise ValueError(f"unknown operator {s!r}; use one of < <= > >= == !=") from None


class ItemKind(IntEnum):
    """Kinds of disseminated (Drip) items."""

    GROUP_TYPE = 0
    CHANNEL = 1
    COMMAND = 2


class TargetKind(IntEnum):
    ALL = 0
    NODE = 1
    GROUP = 2


class AggId(IntEnum):
    """Wire ids of the aggregation functions (see ``aggregation.py``)."""

    AVG = 0
    MIN = 1
    MAX = 2
    SUM = 3
    COUNT = 4


class GroupStatus(IntEnum):
    ALIVE = 0
    GONE = 1


# --------------------------------------------------------------------------- nested values


@dataclass(frozen=True, slots=True)
class Condition:
    """``attribute op value``; attribute ids per ``attributes.py``."""

    attr: int
    op: Op
    value: float

    def __post_init__(self) -> None:
        _int("attr", self.attr, 0, MAX_ATTRIBUTE_ID)
        if not isinstance(self.op, Op):
            object.__setattr__(self, "op", Op(self.op))
        _real("value", self.value)

    def to_wire(self) -> list[Any]:
        return [self.attr, int(self.op), float(self.value)]

    @classmethod
    def from_wire(cls, w: Any) -> Condition:
        a, o, v = _arity(w, 3, "condition")
        if not isinstance(o, int) or o not in Op._value2member_map_:
            raise BadField(f"condition operator {o!r}")
        return cls(a, Op(o), _wire_real("value", v))


@dataclass(frozen=True, slots=True)
class GroupTypeDef:
    """Conjunction of conditions; ``hysteresis`` relaxes thresholds for members."""

    conditions: tuple[Condition, ...]
    hysteresis: float = 0.0

    def __post_init__(self) -> None:
        if not 1 <= len(self.conditions) <= MAX_CONDITIONS:
            raise ValueError(f"a group type needs 1..{MAX_CONDITIONS} conditions")
        _real("hysteresis", self.hysteresis)
        if self.hysteresis < 0:
            raise ValueError("hysteresis must be >= 0")

    def to_wire(self) -> list[Any]:
        return [[c.to_wire() for c in self.conditions], float(self.hysteresis)]

    @classmethod
    def from_wire(cls, w: Any) -> GroupTypeDef:
        conds, hyst = _arity(w, 2, "group type")
        if not isinstance(conds, list):
            raise BadField("conditions is not an array")
        return cls(tuple(Condition.from_wire(c) for c in conds), _wire_real("hysteresis", hyst))


@dataclass(frozen=True, slots=True)
class ChannelDef:
    """Which attribute, from which groups, how often, aggregated how."""

    attr: int
    group_type: int  # ANY_GROUP_TYPE for any
    group_id: int  # ANY_GROUP_ID for any
    period_ms: int
    agg: int  # AggId or an extension id registered in aggregation.py

    def __post_init__(self) -> None:
        _int("attr", self.attr, 0, MAX_ATTRIBUTE_ID)
        _u8("group_type", self.group_type)
        _u16("group_id", self.group_id)
        _int("period_ms", self.period_ms, 1, 0xFFFFFFFF)
        _u8("agg", self.agg)

    def to_wire(self) -> list[Any]:
        return [self.attr, self.group_type, self.group_id, self.period_ms, self.agg]

    @classmethod
    def from_wire(cls, w: Any) -> ChannelDef:
        return cls(*_arity(w, 5, "channel"))


ArgValue: TypeAlias = int | float | str | bool


@dataclass(frozen=True, slots=True)
class CommandDef:
    """A command for the node kind's handler on each targeted mote."""

    name: str
    target_kind: TargetKind = TargetKind.ALL
    target_a: int = 0  # node id, or group type
    target_b: int = 0  # group id (TargetKind.GROUP)
    args: tuple[tuple[str, ArgValue], ...] = ()

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not 1 <= len(self.name) <= MAX_COMMAND_NAME:
            raise ValueError(f"command name must be 1..{MAX_COMMAND_NAME} characters")
        if not isinstance(self.target_kind, TargetKind):
            object.__setattr__(self, "target_kind", TargetKind(self.target_kind))
        _u16("target_a", self.target_a)
        _u16("target_b", self.target_b)
        if len(self.args) > MAX_COMMAND_ARGS:
            raise ValueError(f"at most {MAX_COMMAND_ARGS} command arguments")
        for k, v in self.args:
            if not isinstance(k, str) or not isinstance(v, int | float | str | bool):
                raise ValueError(f"command argument {k!r}={v!r} is not a scalar")

    def to_wire(self) -> list[Any]:
        return [
            self.name,
            int(self.target_kind),
            self.target_a,
            self.target_b,
            [[k, v] for k, v in self.args],
        ]

    @classmethod
    def from_wire(cls, w: Any) -> CommandDef:
        name, tk, a, b, args = _arity(w, 5, "command")
        if not isinstance(tk, int) or tk not in TargetKind._value2member_map_:
            raise BadField(f"command target kind {tk!r}")
        if not isinstance(args, list):
            raise BadField("command args is not an array")
        pairs = tuple(
            (p[0], _wire_real("command arg", p[1]))
            for p in (_arity(x, 2, "command arg") for x in args)
        )
        return cls(name, TargetKind(tk), a, b, pairs)


ItemBody: TypeAlias = GroupTypeDef | ChannelDef | CommandDef
_BODY_OF: dict[ItemKind, Callable[[Any], ItemBody]] = {
    ItemKind.GROUP_TYPE: GroupTypeDef.from_wire,
    ItemKind.CHANNEL: ChannelDef.from_wire,
    ItemKind.COMMAND: CommandDef.from_wire,
}
_BODY_TYPE: dict[ItemKind, type] = {
    ItemKind.GROUP_TYPE: GroupTypeDef,
    ItemKind.CHANNEL: ChannelDef,
    ItemKind.COMMAND: CommandDef,
}


@dataclass(frozen=True, slots=True)
class DataRecord:
    """One aggregated result of one channel, group and epoch, for the gateway."""

    channel: int
    group_type: int
    group_id: int
    epoch: int
    agg: int
    value: float
    count: int
    leader: int

    TAG: ClassVar[int] = 0

    def __post_init__(self) -> None:
        _u8("channel", self.channel)
        _u8("group_type", self.group_type)
        _u16("group_id", self.group_id)
        _u32("epoch", self.epoch)
        _u8("agg", self.agg)
        _real("value", self.value)
        _u32("count", self.count)
        _node("leader", self.leader)

    def to_wire(self) -> list[Any]:
        return [
            self.TAG,
            self.channel,
            self.group_type,
            self.group_id,
            self.epoch,
            self.agg,
            float(self.value),
            self.count,
            self.leader,
        ]


@dataclass(frozen=True, slots=True)
class GroupReport:
    """A leader's report of its group's state (heartbeat, or gone / merged)."""

    group_type: int
    group_id: int
    leader: int
    weight: int
    readings: int  # readings aggregated in the leader's last epoch, 0 when unknown
    status: GroupStatus = GroupStatus.ALIVE
    # GONE: the group id it merged into (0: dissolved); ALIVE: the id of the group
    # it split from (a group created when its members lost that group's leader), or 0
    successor: int = 0

    TAG: ClassVar[int] = 1

    def __post_init__(self) -> None:
        _u8("group_type", self.group_type)
        _u16("group_id", self.group_id)
        _node("leader", self.leader)
        _u32("weight", self.weight)
        _u16("readings", self.readings)
        if not isinstance(self.status, GroupStatus):
            object.__setattr__(self, "status", GroupStatus(self.status))
        _u16("successor", self.successor)

    def to_wire(self) -> list[Any]:
        return [
            self.TAG,
            self.group_type,
            self.group_id,
            self.leader,
            self.weight,
            self.readings,
            int(self.status),
            self.successor,
        ]


Payload: TypeAlias = DataRecord | GroupReport


def _payload_from_wire(w: Any) -> Payload:
    if not isinstance(w, list) or not w:
        raise BadField("collection payload is not a tagged array")
    tag, *rest = w
    if tag == DataRecord.TAG:
        ch, gt, gid, epoch, agg, value, count, leader = _arity(rest, 8, "data record")
        return DataRecord(ch, gt, gid, epoch, agg, _wire_real("value", value), count, leader)
    if tag == GroupReport.TAG:
        g = _arity(rest, 7, "group report")
        if not isinstance(g[5], int) or g[5] not in GroupStatus._value2member_map_:
            raise BadField(f"group status {g[5]!r}")
        return GroupReport(g[0], g[1], g[2], g[3], g[4], GroupStatus(g[5]), g[6])
    raise BadField(f"unknown collection payload tag {tag!r}")


# --------------------------------------------------------------------------- frames


@dataclass(frozen=True, slots=True)
class Frame:
    """Link header shared by every frame. Subclasses add body fields."""

    TYPE: ClassVar[int] = -1
    src: int
    dst: int

    def __post_init__(self) -> None:
        _node("src", self.src)
        _addr("dst", self.dst)

    def body(self) -> list[Any]:
        raise NotImplementedError

    @classmethod
    def from_body(cls, src: int, dst: int, body: list[Any]) -> Frame:
        raise NotImplementedError


@dataclass(frozen=True, slots=True)
class Hello(Frame):
    """Neighbour-discovery beacon; also the beacon a robot's mote emits."""

    TYPE: ClassVar[int] = 1
    seq: int = 0

    def __post_init__(self) -> None:
        Frame.__post_init__(self)
        _u16("seq", self.seq)

    def body(self) -> list[Any]:
        return [self.seq]

    @classmethod
    def from_body(cls, src: int, dst: int, body: list[Any]) -> Hello:
        return cls(src, dst, *_arity(body, 1, "hello"))


@dataclass(frozen=True, slots=True)
class DripItem(Frame):
    """One versioned item of epidemic dissemination; ``body=None`` deletes."""

    TYPE: ClassVar[int] = 2
    kind: ItemKind = ItemKind.GROUP_TYPE
    item_id: int = 0
    version: int = 0
    item: ItemBody | None = None

    def __post_init__(self) -> None:
        Frame.__post_init__(self)
        if not isinstance(self.kind, ItemKind):
            object.__setattr__(self, "kind", ItemKind(self.kind))
        _u16("item_id", self.item_id)
        _u32("version", self.version)
        if self.item is not None and not isinstance(self.item, _BODY_TYPE[self.kind]):
            raise ValueError(f"{self.kind.name} item carries a {type(self.item).__name__}")

    def body(self) -> list[Any]:
        return [
            int(self.kind),
            self.item_id,
            self.version,
            None if self.item is None else self.item.to_wire(),
        ]

    @classmethod
    def from_body(cls, src: int, dst: int, body: list[Any]) -> DripItem:
        kind, item_id, version, item = _arity(body, 4, "drip item")
        if not isinstance(kind, int) or kind not in ItemKind._value2member_map_:
            raise BadField(f"item kind {kind!r}")
        k = ItemKind(kind)
        return cls(src, dst, k, item_id, version, None if item is None else _BODY_OF[k](item))


SIG_PARTS = 2  # an Ed25519 signature (64 B) travels in two frames of 32 B
SIG_PART_BYTES = 32


@dataclass(frozen=True, slots=True)
class DripSig(Frame):
    """One part of the gateway's signature of a Drip item ``(kind, item_id, version)``.

    A 64-byte Ed25519 signature does not fit a CC1000 frame beside the item,
    so it travels in :data:`SIG_PARTS` frames of its own (docs/security.md,
    "Frames and items"); the largest encodes to 52 bytes."""

    TYPE: ClassVar[int] = 16
    kind: ItemKind = ItemKind.GROUP_TYPE
    item_id: int = 0
    version: int = 0
    part: int = 0
    chunk: bytes = b""

    def __post_init__(self) -> None:
        Frame.__post_init__(self)
        if not isinstance(self.kind, ItemKind):
            object.__setattr__(self, "kind", ItemKind(self.kind))
        _u16("item_id", self.item_id)
        _u32("version", self.version)
        _int("part", self.part, 0, SIG_PARTS - 1)
        if not isinstance(self.chunk, bytes) or len(self.chunk) != SIG_PART_BYTES:
            raise ValueError(f"a signature part is {SIG_PART_BYTES} bytes")

    def body(self) -> list[Any]:
        return [int(self.kind), self.item_id, self.version, self.part, self.chunk]

    @classmethod
    def from_body(cls, src: int, dst: int, body: list[Any]) -> DripSig:
        kind, item_id, version, part, chunk = _arity(body, 5, "drip signature")
        if not isinstance(kind, int) or kind not in ItemKind._value2member_map_:
            raise BadField(f"item kind {kind!r}")
        return cls(src, dst, ItemKind(kind), item_id, version, part, chunk)


@dataclass(frozen=True, slots=True)
class DripSummary(Frame):
    """Digest of everything a mote holds; a mismatch makes neighbours speak up."""

    TYPE: ClassVar[int] = 3
    digest: int = 0
    n_items: int = 0

    def __post_init__(self) -> None:
        Frame.__post_init__(self)
        _u32("digest", self.digest)
        _u16("n_items", self.n_items)

    def body(self) -> list[Any]:
        return [self.digest, self.n_items]

    @classmethod
    def from_body(cls, src: int, dst: int, body: list[Any]) -> DripSummary:
        return cls(src, dst, *_arity(body, 2, "drip summary"))


@dataclass(frozen=True, slots=True)
class CtpBeacon(Frame):
    """Collection-tree routing beacon: the sender's path cost to a root."""

    TYPE: ClassVar[int] = 4
    cost: int = NO_ROUTE  # path ETX x 10; 0 at a root
    parent: int = BROADCAST
    pull: bool = False  # "I have no route": neighbours answer soon

    def __post_init__(self) -> None:
        Frame.__post_init__(self)
        _u16("cost", self.cost)
        _addr("parent", self.parent)
        if not isinstance(self.pull, bool):
            raise ValueError("pull must be a bool")

    def body(self) -> list[Any]:
        return [self.cost, self.parent, self.pull]

    @classmethod
    def from_body(cls, src: int, dst: int, body: list[Any]) -> CtpBeacon:
        return cls(src, dst, *_arity(body, 3, "ctp beacon"))


@dataclass(frozen=True, slots=True)
class CtpData(Frame):
    """A payload travelling up the collection tree, hop by hop (unicast)."""

    TYPE: ClassVar[int] = 5
    origin: int = 0
    seqno: int = 0
    thl: int = 0  # time has lived: hops so far
    cost: int = NO_ROUTE  # the forwarder's cost, for loop detection
    payload: Payload | None = None

    def __post_init__(self) -> None:
        Frame.__post_init__(self)
        _node("origin", self.origin)
        _u16("seqno", self.seqno)
        _u8("thl", self.thl)
        _u16("cost", self.cost)
        if not isinstance(self.payload, DataRecord | GroupReport):
            raise ValueError("CtpData needs a DataRecord or GroupReport payload")

    def body(self) -> list[Any]:
        assert self.payload is not None
        return [self.origin, self.seqno, self.thl, self.cost, self.payload.to_wire()]

    @classmethod
    def from_body(cls, src: int, dst: int, body: list[Any]) -> CtpData:
        origin, seqno, thl, cost, payload = _arity(body, 5, "ctp data")
        return cls(src, dst, origin, seqno, thl, cost, _payload_from_wire(payload))


@dataclass(frozen=True, slots=True)
class LeaderBeacon(Frame):
    """A group leader's beacon, flooded by members (hops counts the flood)."""

    TYPE: ClassVar[int] = 6
    group_type: int = 0
    group_id: int = 1
    leader: int = 0
    weight: int = 0
    seq: int = 0
    hops: int = 0
    # A would-be group's announcement (docs/protocol-groups.md, "Tentative ids"):
    # nobody joins it or forwards it; an established group answers it.
    tentative: bool = False
    # A member's forward names the member it took the beacon from (its parent in
    # the group tree), which then keeps forwarding; BROADCAST: none (the leader).
    parent: int = BROADCAST

    def __post_init__(self) -> None:
        Frame.__post_init__(self)
        _u8("group_type", self.group_type)
        _int("group_id", self.group_id, 1, 0xFFFE)
        _node("leader", self.leader)
        _u32("weight", self.weight)
        _u16("seq", self.seq)
        _u8("hops", self.hops)
        if not isinstance(self.tentative, bool):
            raise ValueError("tentative must be a bool")
        _addr("parent", self.parent)

    def body(self) -> list[Any]:
        return [self.group_type, self.group_id, self.leader, self.weight, self.seq, self.hops,
                self.tentative, self.parent]  # fmt: skip

    @classmethod
    def from_body(cls, src: int, dst: int, body: list[Any]) -> LeaderBeacon:
        return cls(src, dst, *_arity(body, 8, "leader beacon"))


@dataclass(frozen=True, slots=True)
class Handover(Frame):
    """A leaving leader hands its group (id, weight, beacon seq) to a member."""

    TYPE: ClassVar[int] = 7
    group_type: int = 0
    group_id: int = 1
    weight: int = 0
    seq: int = 0

    def __post_init__(self) -> None:
        Frame.__post_init__(self)
        _u8("group_type", self.group_type)
        _int("group_id", self.group_id, 1, 0xFFFE)
        _u32("weight", self.weight)
        _u16("seq", self.seq)

    def body(self) -> list[Any]:
        return [self.group_type, self.group_id, self.weight, self.seq]

    @classmethod
    def from_body(cls, src: int, dst: int, body: list[Any]) -> Handover:
        return cls(src, dst, *_arity(body, 4, "handover"))


@dataclass(frozen=True, slots=True)
class Partial(Frame):
    """A partial aggregate of one channel epoch, sent up the group tree."""

    TYPE: ClassVar[int] = 8
    channel: int = 0
    group_type: int = 0
    group_id: int = 1
    epoch: int = 0
    agg: int = 0
    count: int = 0
    state: tuple[float, ...] = field(default=())

    def __post_init__(self) -> None:
        Frame.__post_init__(self)
        _u8("channel", self.channel)
        _u8("group_type", self.group_type)
        _int("group_id", self.group_id, 1, 0xFFFE)
        _u32("epoch", self.epoch)
        _u8("agg", self.agg)
        _u32("count", self.count)
        if len(self.state) > 4:
            raise ValueError("an aggregate state has at most 4 numbers")
        for i, v in enumerate(self.state):
            _real(f"state[{i}]", v)

    def body(self) -> list[Any]:
        return [
            self.channel,
            self.group_type,
            self.group_id,
            self.epoch,
            self.agg,
            self.count,
            [float(v) for v in self.state],
        ]

    @classmethod
    def from_body(cls, src: int, dst: int, body: list[Any]) -> Partial:
        ch, gt, gid, epoch, agg, count, state = _arity(body, 7, "partial")
        if not isinstance(state, list):
            raise BadField("partial state is not an array")
        return cls(
            src,
            dst,
            ch,
            gt,
            gid,
            epoch,
            agg,
            count,
            tuple(_wire_real("state", v) for v in state),
        )


# The frame types whose fields are all ints and bools: msgpack gives them back
# equal (a float field would come back rounded to float32).
_LOSSLESS: frozenset[type[Frame]] = frozenset(
    (Hello, DripSummary, CtpBeacon, LeaderBeacon, Handover)
)

FRAME_TYPES: dict[int, type[Frame]] = {
    t.TYPE: t
    for t in (
        Hello,
        DripItem,
        DripSummary,
        CtpBeacon,
        CtpData,
        LeaderBeacon,
        Handover,
        Partial,
        DripSig,
    )
}


# --------------------------------------------------------------------------- codec


def _arity(w: Any, n: int, what: str) -> list[Any]:
    if not isinstance(w, list) or len(w) != n:
        raise BadField(f"{what}: expected an array of {n} fields, got {w!r:.60}")
    return w


def encode(frame: Frame, mtu: int | None = None) -> bytes:
    """Encode ``frame``; raise :class:`FrameTooLarge` if it exceeds ``mtu`` bytes."""
    data: bytes = msgpack.packb(
        [frame.TYPE, frame.src, frame.dst, *frame.body()], use_single_float=True
    )
    if mtu is not None and len(data) > mtu:
        raise FrameTooLarge(frame, len(data), mtu)
    return data


def peek_header(data: bytes) -> tuple[int, int, int]:
    """Cheap ``(type, src, dst)`` of a frame, for filtering; raises FrameError."""
    f = _unpack(data)
    return f[0], f[1], f[2]


def _unpack(data: bytes) -> list[Any]:
    try:
        obj = msgpack.unpackb(data, raw=False, strict_map_key=True, use_list=True)
    except (msgpack.ExtraData, msgpack.FormatError, msgpack.StackError) as e:
        raise TruncatedFrame(f"not one msgpack value: {e}") from None
    except (ValueError, TypeError, UnicodeDecodeError) as e:
        # msgpack raises ValueError for truncated input ("Unpack failed: incomplete input").
        raise TruncatedFrame(f"undecodable: {e}") from None
    if not isinstance(obj, list) or len(obj) < 3:
        raise NotAFrame(f"expected [type, src, dst, ...], got {obj!r:.60}")
    for name, v in zip(("type", "src", "dst"), obj[:3], strict=True):
        if not isinstance(v, int) or isinstance(v, bool):
            raise NotAFrame(f"header field {name}={v!r:.30} is not an integer")
    return obj


def decode(data: bytes) -> Frame:
    """Decode one frame. Any malformed input raises a :class:`FrameError`."""
    t, src, dst, *body = _unpack(data)
    cls = FRAME_TYPES.get(t)
    if cls is None:
        raise UnknownFrameType(f"frame type {t}")
    try:
        return cls.from_body(src, dst, body)
    except FrameError:
        raise
    except (ValueError, TypeError, KeyError, IndexError, OverflowError) as e:
        raise BadField(f"{cls.__name__}: {e}") from None


# The frame a transmission carries is decoded once for all its receivers: a
# medium hands the same bytes to every receiver of a broadcast (and to every
# mote overhearing a unicast) one after another, and frames are immutable
# (frozen dataclasses whose fields are ints, floats, bytes, tuples and frozen
# records), so the receivers can share the decoded object. One entry, replaced
# atomically (a tuple), compared by value: no unbounded cache, no stale hit.
_last: tuple[bytes, Frame] | None = None

# Frames a mote of this process just encoded, by their bytes, when decoding the
# bytes gives back an equal frame (types whose fields are all ints and bools,
# exactly): their first receiver takes the object instead of decoding the
# bytes again. An entry leaves at its first use; bounded (oldest dropped).
_SENT_MAX = 4096
_sent: dict[bytes, Frame] = {}


def note_sent(data: bytes, frame: Frame) -> None:
    """``data`` is ``encode(frame)``, about to go on the air (see :data:`_sent`)."""
    if type(frame) not in _LOSSLESS or type(frame.src) is not int or type(frame.dst) is not int:
        return
    for v in frame.body():
        if type(v) is not int and type(v) is not bool:
            return  # e.g. an IntEnum: the decoded frame would hold a plain int
    if len(_sent) >= _SENT_MAX:
        del _sent[next(iter(_sent))]
    _sent[data] = frame


def decode_shared(data: bytes) -> Frame:
    """:func:`decode`, sharing the result with the previous call on equal bytes
    (and taking a frame :func:`note_sent` kept for them).

    Malformed input raises :class:`FrameError` every time (failures are not kept).
    """
    global _last
    last = _last
    if last is not None and last[0] == data:
        return last[1]
    f = _sent.pop(data, None)
    if f is None:
        f = decode(data)
    _last = (bytes(data), f)
    return f
