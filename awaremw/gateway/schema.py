"""IP-side JSON contract -> typed radio definitions, with specific refusals.

Every payload that reaches the gateway from MQTT or Zenoh goes through here
before anything is stored or injected: a payload is either turned whole into a
:class:`~awaremw.protocol.frames.GroupTypeDef`, ``ChannelDef`` or ``CommandDef``
that is known to fit the radio MTU, or refused with a :class:`SchemaError`
subclass whose ``code`` and message say exactly why. Nothing half-validated
leaves this module.

The JSON shapes (see docs/gateway.md):

* group type ``def/group/<type>``::

    {"conditions": [{"attr": "temperature", "op": ">", "value": 45}], "hysteresis": 1.0}

* channel ``def/channel/<id>``::

    {"attr": "temperature", "group_type": 1 | "*", "group_id": 513 | "*",
     "period_s": 2.0, "agg": "avg" | "min" | "max" | "sum" | "count"}

* command ``cmd/<name>``::

    {"target": "all" | {"node": 7} | {"group_type": 1, "group_id": 513}, "args": {"k": v}}

An empty payload on a definition topic deletes the definition; a JSON ``null``
is refused (``wrong_type``), never taken for a deletion. Before any parsing a
payload is bounded in size (``max_payload_bytes``) and in nesting depth
(``max_depth``): a deeply nested document is refused as ``payload_too_deep``
instead of exhausting the parser's recursion. See docs/robustness.md.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Collection, Mapping
from dataclasses import dataclass, field
from typing import Annotated, Any, ClassVar, Literal, TypeVar

import msgspec
from msgspec import UNSET, Meta, UnsetType

from awaremw.protocol.attributes import UnknownAttribute, attribute_id, attribute_name
from awaremw.protocol.config import MiddlewareConfig
from awaremw.protocol.frames import (
    ANY_GROUP_ID,
    ANY_GROUP_TYPE,
    BROADCAST,
    MAX_COMMAND_ARGS,
    MAX_COMMAND_NAME,
    MAX_CONDITIONS,
    MAX_NODE_ID,
    AggId,
    ChannelDef,
    CommandDef,
    Condition,
    DripItem,
    FrameTooLarge,
    GroupTypeDef,
    ItemBody,
    ItemKind,
    Op,
    TargetKind,
    encode,
)

AGG_NAMES: Mapping[str, int] = {a.name.lower(): int(a) for a in AggId}
ANY: Literal["*"] = "*"
MAX_VERSION = 0xFFFFFFFF
_NAME_RE = re.compile(r"^[A-Za-z0-9_.-]+$")


# --------------------------------------------------------------------------- errors


class SchemaError(ValueError):
    """A payload or topic from the IP side that the gateway refuses (a remote fault).

    ``code`` is a stable machine-readable token (published with the message on
    ``<prefix>/errors``); the message is for humans.
    """

    code: ClassVar[str] = "invalid"


class InvalidUtf8(SchemaError):
    code = "invalid_utf8"


class InvalidJson(SchemaError):
    code = "invalid_json"


class PayloadTooLarge(SchemaError):
    code = "payload_too_large"


class PayloadTooDeep(SchemaError):
    code = "payload_too_deep"


class TopicTooLong(SchemaError):
    code = "topic_too_long"


class WrongType(SchemaError):
    code = "wrong_type"


class MissingField(SchemaError):
    code = "missing_field"


class UnknownField(SchemaError):
    code = "unknown_field"


class UnknownAttributeName(SchemaError):
    code = "unknown_attribute"


class BadOperator(SchemaError):
    code = "bad_operator"


class BadValue(SchemaError):
    code = "bad_value"


class PeriodOutOfRange(SchemaError):
    code = "period_out_of_range"


class ChannelIdOutOfRange(SchemaError):
    code = "channel_id_out_of_range"


class GroupTypeOutOfRange(SchemaError):
    code = "group_type_out_of_range"


class GroupIdOutOfRange(SchemaError):
    code = "group_id_out_of_range"


class UnknownAggregation(SchemaError):
    code = "unknown_aggregation"


class UnknownTarget(SchemaError):
    code = "unknown_target"


class BadCommand(SchemaError):
    code = "bad_command"


class TooManyDefinitions(SchemaError):
    code = "too_many_definitions"


class DoesNotFitMtu(SchemaError):
    code = "does_not_fit_mtu"


class UnknownTopic(SchemaError):
    code = "unknown_topic"


# --------------------------------------------------------------------------- limits


@dataclass(frozen=True, slots=True)
class Limits:
    """What the gateway accepts; derived from the middleware configuration."""

    mtu: int = 100
    max_payload_bytes: int = 4096
    max_depth: int = 8  # nesting of JSON arrays/objects (the contract needs 3)
    max_group_type: int = 254  # 0xFF means "any" in a channel
    max_channel_id: int = 255
    max_group_types: int = 8  # how many may be defined at once (mote table size)
    max_channels: int = 8
    min_period_s: float = 0.5
    max_period_s: float = 86400.0
    gateway_node: int = 0  # source address used for the MTU check
    known_nodes: frozenset[int] | None = None  # command node targets, None = any valid id

    @classmethod
    def from_config(
        cls,
        config: MiddlewareConfig,
        *,
        known_nodes: Collection[int] | None = None,
        gateway_node: int = 0,
        **overrides: Any,
    ) -> Limits:
        return cls(
            mtu=config.mtu,
            max_group_types=config.max_group_types,
            max_channels=config.max_channels,
            min_period_s=config.min_period_s,
            gateway_node=gateway_node,
            known_nodes=None if known_nodes is None else frozenset(known_nodes),
            **overrides,
        )


# --------------------------------------------------------------------------- parsed forms


@dataclass(frozen=True, slots=True)
class Definition:
    """A validated definition (``body is None``: a deletion) with its IP-side JSON."""

    kind: ItemKind
    item_id: int
    body: ItemBody | None
    json: Mapping[str, Any] | None = field(default=None, compare=False)


@dataclass(frozen=True, slots=True)
class Command:
    name: str
    body: CommandDef
    json: Mapping[str, Any] = field(compare=False)


# --------------------------------------------------------------------------- payload helpers
# The JSON shapes as msgspec types: decoding checks object shape (unknown and
# missing fields), JSON types, the fixed ranges and lengths; the checks no
# static schema expresses (limits of the deployment, attribute names, the shape
# of a command target, the MTU, the motes' table sizes) follow by hand.

_GroupId = (
    Annotated[int, Meta(ge=1, lt=ANY_GROUP_ID)] | Annotated[float, Meta(ge=1, lt=ANY_GROUP_ID)]
)
_NodeId = Annotated[int, Meta(ge=0, le=MAX_NODE_ID)] | Annotated[float, Meta(ge=0, le=MAX_NODE_ID)]
_Args = dict[str, bool | int | float | str]


class _Object(msgspec.Struct, forbid_unknown_fields=True):
    pass


class _Condition(_Object):
    attr: str
    op: str
    value: float


class _GroupDoc(_Object):
    conditions: Annotated[list[_Condition], Meta(min_length=1, max_length=MAX_CONDITIONS)]
    hysteresis: Annotated[float, Meta(ge=0)] = 0.0


class _ChannelDoc(_Object):
    attr: str
    period_s: float
    group_type: int | float | Literal["*"] = ANY  # range: Limits.max_group_type
    group_id: _GroupId | Literal["*"] = ANY
    agg: str = "avg"


class _Target(_Object):
    node: _NodeId | UnsetType = UNSET
    group_type: int | float | UnsetType = UNSET
    group_id: _GroupId | Literal["*"] | UnsetType = UNSET


class _CommandDoc(_Object):
    target: Literal["all"] | _Target = "all"
    args: Annotated[_Args, Meta(max_length=MAX_COMMAND_ARGS)] = {}


_Doc = TypeVar("_Doc", _GroupDoc, _ChannelDoc, _CommandDoc)


_STRINGS = re.compile(r'"(?:[^"\\]|\\.)*"')
_NOT_BRACKETS = re.compile(r"[^\[\]{}]+")
_ERROR = re.compile(r"(?P<msg>.*?)(?: - at `\$\.?(?P<path>.*)`)?", re.S)
_TYPE_NAMES = {"str": "string", "int": "integer", "float": "number", "bool": "boolean"}
_EXPECTED = {
    "int | float": "an integer",
    "int | float | str": 'an integer or "*"',
    "bool | int | float | str": "a number, string or boolean",
    "object": "a JSON object",
    "array": "an array",
    "float": "a number",
    "str": "a string",
}
_WHAT = {_GroupDoc: "group definition", _ChannelDoc: "channel definition", _CommandDoc: "command"}
_SHAPES: Mapping[str, type[_Object]] = {"conditions[]": _Condition, "target": _Target}
_RANGE_CODES: Mapping[str, type[SchemaError]] = {
    "group_id": GroupIdOutOfRange,
    "args": BadCommand,
    "target.node": UnknownTarget,
    "target.group_id": UnknownTarget,
}


def is_empty(payload: bytes, limits: Limits) -> bool:
    """An empty (or all-whitespace, within the size limit) payload: a deletion."""
    return len(payload) <= limits.max_payload_bytes and not payload.strip()


def json_depth(text: str) -> int:
    """Greatest nesting of arrays/objects in ``text`` (strings skipped), without recursion."""
    depth = deepest = 0
    for ch in _NOT_BRACKETS.sub("", _STRINGS.sub("", text)):
        if ch in "[{":
            depth += 1
            deepest = max(deepest, depth)
        else:
            depth -= 1
    return deepest


def _checked_text(payload: bytes, limits: Limits) -> str:
    """Size, UTF-8 and depth checks, before any parser sees the payload."""
    if len(payload) > limits.max_payload_bytes:
        raise PayloadTooLarge(
            f"payload of {len(payload)} bytes exceeds the limit of {limits.max_payload_bytes}"
        )
    try:
        text = payload.decode("utf-8")
    except UnicodeDecodeError as e:
        raise InvalidUtf8(f"payload is not UTF-8: {e.reason} at byte {e.start}") from None
    depth = json_depth(text)
    if depth > limits.max_depth:
        raise PayloadTooDeep(
            f"payload nests arrays/objects {depth} deep, more than the limit of {limits.max_depth}"
        )
    return text


def decode_payload(payload: bytes, limits: Limits) -> Any:
    """Size, UTF-8, depth and JSON checks; returns the JSON value (None for ``null``)."""
    try:
        return json.loads(_checked_text(payload, limits), parse_constant=_no_constant)
    except (json.JSONDecodeError, ValueError) as e:
        raise InvalidJson(f"payload is not JSON: {e}") from None


def _no_constant(name: str) -> Any:
    raise ValueError(f"{name} is not allowed")


def _decode(payload: bytes, limits: Limits, doc_type: type[_Doc]) -> _Doc:
    text = _checked_text(payload, limits)
    try:
        return msgspec.json.decode(text, type=doc_type)
    except msgspec.ValidationError as e:
        raise _refusal(str(e), doc_type, text) from None
    except msgspec.DecodeError as e:
        raise InvalidJson(f"payload is not JSON: {e}") from None


def _refusal(error: str, root: type[_Object], text: str) -> SchemaError:
    """msgspec's message (``... - at `$.conditions[0].op```) -> the specific refusal."""
    m = _ERROR.fullmatch(error)
    assert m is not None
    msg, path = m["msg"], m["path"] or ""
    where, shape, quoted = path or _WHAT[root], re.sub(r"\[\d+\]", "[]", path), msg.split("`")
    if path == "target":
        target = json.dumps(_value_at(text, path))[:80]
        return UnknownTarget(
            f'unknown command target {target}; use "all", {{"node": ID}} or '
            '{"group_type": T, "group_id": G or "*"}'
        )
    if path == "args[...]":
        key, v = next((k, v) for k, v in json.loads(text)["args"].items() if not _scalar(v))
        return WrongType(f"args.{key} must be a number, string or boolean, got {_kind(v)}")
    if msg.startswith("Object contains unknown field"):
        allowed = ", ".join(sorted(_SHAPES.get(shape, root).__struct_fields__))
        return UnknownField(f"{where}: unknown field {quoted[1]!r}; allowed: {allowed}")
    if msg.startswith("Object missing required field"):
        return MissingField(f"{where}: missing field {quoted[1]!r}")
    if msg.startswith("Expected") and ", got " in msg:
        expected = _EXPECTED.get(quoted[1], quoted[1])
        return WrongType(f"{where} must be {expected}, got {_TYPE_NAMES.get(quoted[3], quoted[3])}")
    value = _value_at(text, path)
    if msg.startswith("Invalid enum value"):  # the literal "*" of a group type or id
        return WrongType(f'{where} must be an integer or "*", got {value!r}')
    why = "finite" if msg.startswith("Number out of range") else msg.split("` ", 1)[1]
    got = f"{len(value)} items" if isinstance(value, list | dict) else f"{value!r}"
    return _RANGE_CODES.get(shape, BadValue)(f"{where} must be {why}, got {got}")


def _value_at(text: str, path: str) -> Any:
    value = json.loads(text)
    for key, index in re.findall(r"([^.\[\]]+)|\[(\d+)\]", path):
        value = value[int(index)] if index else value[key]
    return value


def _scalar(v: object) -> bool:
    return isinstance(v, int | str) or (isinstance(v, float) and math.isfinite(v))


def _kind(v: object) -> str:
    if v is None:
        return "null"
    return {float: "number", list: "array", dict: "object"}.get(type(v), type(v).__name__)


def _whole(v: object, what: str) -> int:
    """An integer field (JSON Schema ``integer`` admits ``513.0``), as an int."""
    if isinstance(v, float) and v.is_integer():
        return int(v)
    if not isinstance(v, int):
        raise WrongType(f"{what} must be an integer, got {v!r}")
    return v


def _attribute(name: str, what: str) -> int:
    """Wire id of an attribute name; every bad name is ``unknown_attribute``."""
    prefix = f"{what}: " if what else ""
    if name.startswith("rssi:") and not name[5:].isascii():
        # str.isdigit() accepts Unicode digits ("rssi:\u00b2") that int() refuses.
        raise UnknownAttributeName(
            f"{prefix}{name!r}: rssi:<node id> needs a node id in 0..{MAX_NODE_ID}"
        )
    try:
        return attribute_id(name)
    except UnknownAttribute as e:
        raise UnknownAttributeName(f"{prefix}{e}") from None


def parse_id(text: str, what: str, lo: int, hi: int, err: type[SchemaError]) -> int:
    """A decimal id from a topic level, in ``[lo, hi]``."""
    if not text.isascii() or not text.isdigit():
        raise err(f"{what} {text!r} is not a decimal integer in {lo}..{hi}")
    v = int(text)
    if not lo <= v <= hi:
        raise err(f"{what} {v} out of range {lo}..{hi}")
    return v


def check_fits(kind: ItemKind, item_id: int, body: ItemBody, limits: Limits) -> None:
    """Refuse a definition whose Drip frame would exceed the radio MTU."""
    frame = DripItem(limits.gateway_node, BROADCAST, kind, item_id, MAX_VERSION, body)
    try:
        encode(frame, limits.mtu)
    except FrameTooLarge as e:
        raise DoesNotFitMtu(
            f"the definition encodes to a {e.size}-byte radio frame, more than the MTU of "
            f"{e.mtu} bytes; use fewer conditions or shorter names/arguments"
        ) from None


# --------------------------------------------------------------------------- group types


def group_type_id(text: str, limits: Limits) -> int:
    return parse_id(text, "group type", 0, limits.max_group_type, GroupTypeOutOfRange)


def parse_group_type(
    type_text: str, payload: bytes, limits: Limits, defined: Collection[int] = ()
) -> Definition:
    """``def/group/<type>``; ``defined`` lists the group types already defined."""
    gtype = group_type_id(type_text, limits)
    if is_empty(payload, limits):
        return Definition(ItemKind.GROUP_TYPE, gtype, None, None)
    doc = _decode(payload, limits, _GroupDoc)
    conds: list[Condition] = []
    for i, c in enumerate(doc.conditions):
        attr = _attribute(c.attr, f"conditions[{i}]")
        try:
            op = Op.from_symbol(c.op)
        except ValueError as e:
            raise BadOperator(f"conditions[{i}]: {e}") from None
        conds.append(Condition(attr, op, c.value))
    body = GroupTypeDef(tuple(conds), doc.hysteresis)
    check_fits(ItemKind.GROUP_TYPE, gtype, body, limits)
    if gtype not in defined and len(set(defined)) >= limits.max_group_types:
        raise TooManyDefinitions(
            f"{limits.max_group_types} group types are already defined (the motes' limit); "
            "delete one first"
        )
    return Definition(ItemKind.GROUP_TYPE, gtype, body, group_type_json(body))


def group_type_json(body: GroupTypeDef) -> dict[str, Any]:
    return {
        "conditions": [
            {"attr": attribute_name(c.attr), "op": c.op.symbol, "value": float(c.value)}
            for c in body.conditions
        ],
        "hysteresis": float(body.hysteresis),
    }


# --------------------------------------------------------------------------- channels


def channel_id(text: str, limits: Limits) -> int:
    return parse_id(text, "channel id", 0, limits.max_channel_id, ChannelIdOutOfRange)


def agg_name(agg: int) -> str:
    try:
        return AggId(agg).name.lower()
    except ValueError:
        return f"agg{agg}"


def parse_channel(
    id_text: str, payload: bytes, limits: Limits, defined: Collection[int] = ()
) -> Definition:
    """``def/channel/<id>``; ``defined`` lists the channel ids already defined."""
    ch = channel_id(id_text, limits)
    if is_empty(payload, limits):
        return Definition(ItemKind.CHANNEL, ch, None, None)
    doc = _decode(payload, limits, _ChannelDoc)
    attr = _attribute(doc.attr, "")
    if doc.group_type == ANY:
        gtype = ANY_GROUP_TYPE
    else:
        gtype = _whole(doc.group_type, "group_type")
        if not 0 <= gtype <= limits.max_group_type:
            raise GroupTypeOutOfRange(f"group_type {gtype} out of range 0..{limits.max_group_type}")
    gid = ANY_GROUP_ID if doc.group_id == ANY else _whole(doc.group_id, "group_id")
    period = doc.period_s
    if not limits.min_period_s <= period <= limits.max_period_s:
        raise PeriodOutOfRange(
            f"period_s {period:g} out of range {limits.min_period_s:g}..{limits.max_period_s:g}"
        )
    agg_text = doc.agg.lower()
    if agg_text not in AGG_NAMES:
        raise UnknownAggregation(f"unknown agg {agg_text!r}; use one of {', '.join(AGG_NAMES)}")
    body = ChannelDef(attr, gtype, gid, round(period * 1000), AGG_NAMES[agg_text])
    check_fits(ItemKind.CHANNEL, ch, body, limits)
    if ch not in defined and len(set(defined)) >= limits.max_channels:
        raise TooManyDefinitions(
            f"{limits.max_channels} channels are already defined (the motes' limit); "
            "delete one first"
        )
    return Definition(ItemKind.CHANNEL, ch, body, channel_json(body))


def channel_json(body: ChannelDef) -> dict[str, Any]:
    return {
        "attr": attribute_name(body.attr),
        "group_type": ANY if body.group_type == ANY_GROUP_TYPE else body.group_type,
        "group_id": ANY if body.group_id == ANY_GROUP_ID else body.group_id,
        "period_s": body.period_ms / 1000.0,
        "agg": agg_name(body.agg),
    }


# --------------------------------------------------------------------------- commands


def parse_command(
    name: str,
    payload: bytes,
    limits: Limits,
    group_types: Collection[int] | None = None,
) -> Command:
    """``cmd/<name>``. ``group_types``: defined group types (group targets must name one)."""
    if not 1 <= len(name) <= MAX_COMMAND_NAME or not _NAME_RE.match(name):
        raise BadCommand(
            f"command name {name!r} must be 1..{MAX_COMMAND_NAME} characters of "
            "letters, digits, '_', '-', '.'"
        )
    doc = _CommandDoc() if is_empty(payload, limits) else _decode(payload, limits, _CommandDoc)
    tk, ta, tb, tjson = _parse_target(doc.target, limits, group_types)
    body = CommandDef(name, tk, ta, tb, tuple(doc.args.items()))
    check_fits(ItemKind.COMMAND, 0, body, limits)
    return Command(name, body, {"target": tjson, "args": dict(doc.args)})


def _parse_target(
    target: Literal["all"] | _Target, limits: Limits, group_types: Collection[int] | None
) -> tuple[TargetKind, int, int, Any]:
    if target == "all":
        return TargetKind.ALL, 0, 0, "all"
    given = {f for f in _Target.__struct_fields__ if getattr(target, f) is not UNSET}
    if given == {"node"}:
        node = _whole(target.node, "target.node")
        if limits.known_nodes is not None and node not in limits.known_nodes:
            raise UnknownTarget(f"target node {node} is not in the deployment")
        return TargetKind.NODE, node, 0, {"node": node}
    if given == {"group_type", "group_id"}:
        gt = _whole(target.group_type, "target.group_type")
        any_id = target.group_id == ANY
        gid = ANY_GROUP_ID if any_id else _whole(target.group_id, "target.group_id")
        if not 0 <= gt <= limits.max_group_type:
            raise UnknownTarget(f"target group_type {gt} out of range 0..{limits.max_group_type}")
        if group_types is not None and gt not in group_types:
            raise UnknownTarget(f"target group_type {gt} is not defined")
        return TargetKind.GROUP, gt, gid, {"group_type": gt, "group_id": ANY if any_id else gid}
    raise UnknownTarget(
        f'unknown command target {msgspec.json.encode(target).decode()[:80]}; use "all", '
        '{"node": ID} or {"group_type": T, "group_id": G or "*"}'
    )


def command_json(body: CommandDef) -> dict[str, Any]:
    target: Any
    if body.target_kind is TargetKind.NODE:
        target = {"node": body.target_a}
    elif body.target_kind is TargetKind.GROUP:
        gid = ANY if body.target_b == ANY_GROUP_ID else body.target_b
        target = {"group_type": body.target_a, "group_id": gid}
    else:
        target = "all"
    return {"target": target, "args": dict(body.args)}


def definition_json(kind: ItemKind, body: ItemBody) -> dict[str, Any]:
    """The canonical IP-side JSON of a validated body."""
    if isinstance(body, GroupTypeDef):
        return group_type_json(body)
    if isinstance(body, ChannelDef):
        return channel_json(body)
    return command_json(body)
