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
from dataclasses import dataclass, field, fields
from enum import IntEnum
from operator import attrgetter
from typing import Annotated, Any, ClassVar, NamedTuple, Self, TypeAlias, get_type_hints

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


def _range(lo: int, hi: int) -> Callable[[str, object], None]:
    return lambda name, v: _int(name, v, lo, hi)


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


def _addr(name: str, v: object) -> None:
    if v != BROADCAST:
        _int(name, v, 0, MAX_NODE_ID)


def _bool(name: str, v: object) -> None:
    if not isinstance(v, bool):
        raise ValueError(f"{name} must be a bool")


# Field types that carry their check: every value's construction runs it.
U8: TypeAlias = Annotated[int, _range(0, 0xFF)]
U16: TypeAlias = Annotated[int, _range(0, 0xFFFF)]
U32: TypeAlias = Annotated[int, _range(0, 0xFFFFFFFF)]
NodeId: TypeAlias = Annotated[int, _range(0, MAX_NODE_ID)]
Addr: TypeAlias = Annotated[int, _addr]  # a node id or BROADCAST
GroupId: TypeAlias = Annotated[int, _range(1, 0xFFFE)]  # real group ids (no ANY_GROUP_ID)
AttrId: TypeAlias = Annotated[int, _range(0, MAX_ATTRIBUTE_ID)]
Real: TypeAlias = Annotated[float, _real]
Bool: TypeAlias = Annotated[bool, _bool]


# --------------------------------------------------------------------------- wire codec


def _arity(w: Any, n: int, what: str) -> list[Any]:
    if not isinstance(w, list) or len(w) != n:
        raise BadField(f"{what}: expected an array of {n} fields, got {w!r:.60}")
    return w


class _Codec(NamedTuple):
    """How a field that is not a plain int, bool, str or bytes goes on the wire."""

    put: Callable[[Any], Any]  # field value -> wire value
    take: Callable[[Any], Any]  # wire value -> field value; a malformed one raises BadField


def _real_codec(name: str) -> _Codec:
    # float(): an int in a float field still goes on the air as a float32
    return _Codec(float, lambda v: _wire_real(name, v))


def _enum_codec(enum: type[IntEnum], what: str) -> _Codec:
    def take(v: Any) -> IntEnum:
        # isinstance first: 1.0 would find Op.LE in the value map
        if not isinstance(v, int) or v not in enum._value2member_map_:
            raise BadField(f"{what} {v!r}")
        return enum(v)

    return _Codec(int, take)


def _array_codec(item: _Codec, what: str) -> _Codec:
    def take(w: Any) -> tuple[Any, ...]:
        if not isinstance(w, list):
            raise BadField(f"{what} is not an array")
        return tuple(item.take(v) for v in w)

    return _Codec(lambda vs: [item.put(v) for v in vs], take)


class _Fields:
    """A value whose fields are checked by their types (:data:`U8` ...) and whose
    wire form is the array of its dataclass fields in declaration order, each as
    is or through its class's ``WIRE`` codec. :func:`_bind` fills the per-class
    tables once the dataclass exists."""

    __slots__ = ()
    WIRE: ClassVar[dict[str, _Codec]] = {}
    _checks: ClassVar[tuple[tuple[str, Callable[[str, Any], None]], ...]]
    _get: ClassVar[Callable[[Any], tuple[Any, ...]]]
    _puts: ClassVar[tuple[tuple[int, Callable[[Any], Any]], ...]]
    _takes: ClassVar[tuple[tuple[int, Callable[[Any], Any]], ...]]
    _arity: ClassVar[int]

    def __post_init__(self) -> None:
        for name, check in self._checks:
            check(name, getattr(self, name))

    def to_wire(self) -> list[Any]:
        vals = list(type(self)._get(self))
        for i, put in self._puts:
            vals[i] = put(vals[i])
        return vals

    @classmethod
    def from_wire(cls, w: Any) -> Self:
        _arity(w, cls._arity, cls.__name__)
        if cls._takes:
            w = list(w)  # the caller's array stays as it was
            for i, take in cls._takes:
                w[i] = take(w[i])
        return cls(*w)


def _bind(cls: type[_Fields]) -> None:
    names = [f.name for f in fields(cls)]  # type: ignore[arg-type]
    assert len(names) >= 2 and set(cls.WIRE) <= set(names), cls  # attrgetter gives a tuple
    cls._get = attrgetter(*names)
    cls._puts = tuple((i, cls.WIRE[n].put) for i, n in enumerate(names) if n in cls.WIRE)
    cls._takes = tuple((i, cls.WIRE[n].take) for i, n in enumerate(names) if n in cls.WIRE)
    cls._arity = len(names)
    hints = get_type_hints(cls, include_extras=True)
    cls._checks = tuple((n, c) for n in names for c in getattr(hints[n], "__metadata__", ()))


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
class Condition(_Fields):
    """``attribute op value``; attribute ids per ``attributes.py``."""

    attr: AttrId
    op: Op
    value: Real

    WIRE: ClassVar[dict[str, _Codec]] = {
        "op": _enum_codec(Op, "condition operator"),
        "value": _real_codec("value"),
    }

    def __post_init__(self) -> None:
        _Fields.__post_init__(self)
        if not isinstance(self.op, Op):
            object.__setattr__(self, "op", Op(self.op))


@dataclass(frozen=True, slots=True)
class GroupTypeDef(_Fields):
    """Conjunction of conditions; ``hysteresis`` relaxes thresholds for members."""

    conditions: tuple[Condition, ...]
    hysteresis: Real = 0.0

    WIRE: ClassVar[dict[str, _Codec]] = {
        "conditions": _array_codec(_Codec(Condition.to_wire, Condition.from_wire), "conditions"),
        "hysteresis": _real_codec("hysteresis"),
    }

    def __post_init__(self) -> None:
        _Fields.__post_init__(self)
        if not 1 <= len(self.conditions) <= MAX_CONDITIONS:
            raise ValueError(f"a group type needs 1..{MAX_CONDITIONS} conditions")
        if self.hysteresis < 0:
            raise ValueError("hysteresis must be >= 0")


@dataclass(frozen=True, slots=True)
class ChannelDef(_Fields):
    """Which attribute, from which groups, how often, aggregated how."""

    attr: AttrId
    group_type: U8  # ANY_GROUP_TYPE for any
    group_id: U16  # ANY_GROUP_ID for any
    period_ms: int
    agg: U8  # AggId or an extension id registered in aggregation.py

    def __post_init__(self) -> None:
        _Fields.__post_init__(self)
        _int("period_ms", self.period_ms, 1, 0xFFFFFFFF)


ArgValue: TypeAlias = int | float | str | bool


def _take_arg(w: Any) -> tuple[Any, Any]:
    k, v = _arity(w, 2, "command arg")
    return k, _wire_real("command arg", v)


@dataclass(frozen=True, slots=True)
class CommandDef(_Fields):
    """A command for the node kind's handler on each targeted mote."""

    name: str
    target_kind: TargetKind = TargetKind.ALL
    target_a: U16 = 0  # node id, or group type
    target_b: U16 = 0  # group id (TargetKind.GROUP)
    args: tuple[tuple[str, ArgValue], ...] = ()

    WIRE: ClassVar[dict[str, _Codec]] = {
        "target_kind": _enum_codec(TargetKind, "command target kind"),
        "args": _array_codec(_Codec(list, _take_arg), "command args"),
    }

    def __post_init__(self) -> None:
        _Fields.__post_init__(self)
        if not isinstance(self.name, str) or not 1 <= len(self.name) <= MAX_COMMAND_NAME:
            raise ValueError(f"command name must be 1..{MAX_COMMAND_NAME} characters")
        if not isinstance(self.target_kind, TargetKind):
            object.__setattr__(self, "target_kind", TargetKind(self.target_kind))
        if len(self.args) > MAX_COMMAND_ARGS:
            raise ValueError(f"at most {MAX_COMMAND_ARGS} command arguments")
        for k, v in self.args:
            if not isinstance(k, str) or not isinstance(v, int | float | str | bool):
                raise ValueError(f"command argument {k!r}={v!r} is not a scalar")


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
class DataRecord(_Fields):
    """One aggregated result of one channel, group and epoch, for the gateway."""

    channel: U8
    group_type: U8
    group_id: U16
    epoch: U32
    agg: U8
    value: Real
    count: U32
    leader: NodeId

    TAG: ClassVar[int] = 0  # its payload tag in a CtpData frame
    WIRE: ClassVar[dict[str, _Codec]] = {"value": _real_codec("value")}


@dataclass(frozen=True, slots=True)
class GroupReport(_Fields):
    """A leader's report of its group's state (heartbeat, or gone / merged)."""

    group_type: U8
    group_id: U16
    leader: NodeId
    weight: U32
    readings: U16  # readings aggregated in the leader's last epoch, 0 when unknown
    status: GroupStatus = GroupStatus.ALIVE
    # GONE: the group id it merged into (0: dissolved); ALIVE: the id of the group
    # it split from (a group created when its members lost that group's leader), or 0
    successor: U16 = 0

    TAG: ClassVar[int] = 1
    WIRE: ClassVar[dict[str, _Codec]] = {"status": _enum_codec(GroupStatus, "group status")}

    def __post_init__(self) -> None:
        _Fields.__post_init__(self)
        if not isinstance(self.status, GroupStatus):
            object.__setattr__(self, "status", GroupStatus(self.status))


Payload: TypeAlias = DataRecord | GroupReport


def _payload_from_wire(w: Any) -> Payload:
    if not isinstance(w, list) or not w:
        raise BadField("collection payload is not a tagged array")
    tag, *rest = w
    if tag == DataRecord.TAG:
        return DataRecord.from_wire(rest)
    if tag == GroupReport.TAG:
        return GroupReport.from_wire(rest)
    raise BadField(f"unknown collection payload tag {tag!r}")


_PAYLOAD = _Codec(lambda p: [p.TAG, *p.to_wire()], _payload_from_wire)
_ITEM_KIND = _enum_codec(ItemKind, "item kind")


# --------------------------------------------------------------------------- frames


@dataclass(frozen=True, slots=True)
class Frame(_Fields):
    """Link header shared by every frame. Subclasses add body fields."""

    TYPE: ClassVar[int] = -1
    src: NodeId
    dst: Addr


@dataclass(frozen=True, slots=True)
class Hello(Frame):
    """Neighbour-discovery beacon; also the beacon a robot's mote emits."""

    TYPE: ClassVar[int] = 1
    seq: U16 = 0


@dataclass(frozen=True, slots=True)
class DripItem(Frame):
    """One versioned item of epidemic dissemination; ``body=None`` deletes."""

    TYPE: ClassVar[int] = 2
    kind: ItemKind = ItemKind.GROUP_TYPE
    item_id: U16 = 0
    version: U32 = 0
    item: ItemBody | None = None

    # the item's decoding depends on the kind: from_wire below
    WIRE: ClassVar[dict[str, _Codec]] = {
        "kind": _ITEM_KIND,
        "item": _Codec(lambda b: None if b is None else b.to_wire(), lambda w: w),
    }

    def __post_init__(self) -> None:
        Frame.__post_init__(self)
        if not isinstance(self.kind, ItemKind):
            object.__setattr__(self, "kind", ItemKind(self.kind))
        if self.item is not None and not isinstance(self.item, _BODY_TYPE[self.kind]):
            raise ValueError(f"{self.kind.name} item carries a {type(self.item).__name__}")

    @classmethod
    def from_wire(cls, w: Any) -> Self:
        src, dst, kind, item_id, version, item = _arity(w, 6, "DripItem")
        k = _ITEM_KIND.take(kind)
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
    item_id: U16 = 0
    version: U32 = 0
    part: int = 0
    chunk: bytes = b""

    WIRE: ClassVar[dict[str, _Codec]] = {"kind": _ITEM_KIND}

    def __post_init__(self) -> None:
        Frame.__post_init__(self)
        if not isinstance(self.kind, ItemKind):
            object.__setattr__(self, "kind", ItemKind(self.kind))
        _int("part", self.part, 0, SIG_PARTS - 1)
        if not isinstance(self.chunk, bytes) or len(self.chunk) != SIG_PART_BYTES:
            raise ValueError(f"a signature part is {SIG_PART_BYTES} bytes")


@dataclass(frozen=True, slots=True)
class DripSummary(Frame):
    """Digest of everything a mote holds; a mismatch makes neighbours speak up."""

    TYPE: ClassVar[int] = 3
    digest: U32 = 0
    n_items: U16 = 0


@dataclass(frozen=True, slots=True)
class CtpBeacon(Frame):
    """Collection-tree routing beacon: the sender's path cost to a root."""

    TYPE: ClassVar[int] = 4
    cost: U16 = NO_ROUTE  # path ETX x 10; 0 at a root
    parent: Addr = BROADCAST
    pull: Bool = False  # "I have no route": neighbours answer soon


@dataclass(frozen=True, slots=True)
class CtpData(Frame):
    """A payload travelling up the collection tree, hop by hop (unicast)."""

    TYPE: ClassVar[int] = 5
    origin: NodeId = 0
    seqno: U16 = 0
    thl: U8 = 0  # time has lived: hops so far
    cost: U16 = NO_ROUTE  # the forwarder's cost, for loop detection
    payload: Payload | None = None

    WIRE: ClassVar[dict[str, _Codec]] = {"payload": _PAYLOAD}

    def __post_init__(self) -> None:
        Frame.__post_init__(self)
        if not isinstance(self.payload, DataRecord | GroupReport):
            raise ValueError("CtpData needs a DataRecord or GroupReport payload")


@dataclass(frozen=True, slots=True)
class LeaderBeacon(Frame):
    """A group leader's beacon, flooded by members (hops counts the flood)."""

    TYPE: ClassVar[int] = 6
    group_type: U8 = 0
    group_id: GroupId = 1
    leader: NodeId = 0
    weight: U32 = 0
    seq: U16 = 0
    hops: U8 = 0
    # A would-be group's announcement (docs/protocol-groups.md, "Tentative ids"):
    # nobody joins it or forwards it; an established group answers it.
    tentative: Bool = False
    # A member's forward names the member it took the beacon from (its parent in
    # the group tree), which then keeps forwarding; BROADCAST: none (the leader).
    parent: Addr = BROADCAST


@dataclass(frozen=True, slots=True)
class Handover(Frame):
    """A leaving leader hands its group (id, weight, beacon seq) to a member."""

    TYPE: ClassVar[int] = 7
    group_type: U8 = 0
    group_id: GroupId = 1
    weight: U32 = 0
    seq: U16 = 0


@dataclass(frozen=True, slots=True)
class Partial(Frame):
    """A partial aggregate of one channel epoch, sent up the group tree."""

    TYPE: ClassVar[int] = 8
    channel: U8 = 0
    group_type: U8 = 0
    group_id: GroupId = 1
    epoch: U32 = 0
    agg: U8 = 0
    count: U32 = 0
    state: tuple[float, ...] = field(default=())

    WIRE: ClassVar[dict[str, _Codec]] = {
        "state": _array_codec(_real_codec("state"), "partial state")
    }

    def __post_init__(self) -> None:
        Frame.__post_init__(self)
        if len(self.state) > 4:
            raise ValueError("an aggregate state has at most 4 numbers")
        for i, v in enumerate(self.state):
            _real(f"state[{i}]", v)


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


# The frame types whose fields are all ints and bools (no codec): msgpack gives
# them back equal (a float field would come back rounded to float32).
_LOSSLESS: frozenset[type[Frame]] = frozenset(t for t in FRAME_TYPES.values() if not t.WIRE)

for _cls in (Condition, GroupTypeDef, ChannelDef, CommandDef, DataRecord, GroupReport,
             *FRAME_TYPES.values()):  # fmt: skip
    _bind(_cls)


# --------------------------------------------------------------------------- codec


def encode(frame: Frame, mtu: int | None = None) -> bytes:
    """Encode ``frame``; raise :class:`FrameTooLarge` if it exceeds ``mtu`` bytes."""
    data: bytes = msgpack.packb([frame.TYPE, *frame.to_wire()], use_single_float=True)
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
    obj = _unpack(data)
    cls = FRAME_TYPES.get(obj[0])
    if cls is None:
        raise UnknownFrameType(f"frame type {obj[0]}")
    try:
        return cls.from_wire(obj[1:])
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
    for v in frame.to_wire():
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
