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
from typing import Any, ClassVar

from awaremw.nodes.kinds import COMMANDS
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
    ArgValue,
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
ANY = "*"
MAX_VERSION = 0xFFFFFFFF
# A definition's declared ``version`` (the store's count, not the radio's u32):
# at most the largest integer every JSON reader (JavaScript too) holds exactly.
MAX_DECLARED_VERSION = (1 << 53) - 1
MAX_COPY_BYTES = 65_536  # a larger payload is no copy of ours (it is refused in its turn)
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


class UnknownCommand(SchemaError):
    code = "unknown_command"


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
    # Command names motes accept (awaremw.nodes.kinds.COMMANDS), None = any valid name.
    commands: frozenset[str] | None = None

    @classmethod
    def from_config(
        cls,
        config: MiddlewareConfig,
        *,
        known_nodes: Collection[int] | None = None,
        gateway_node: int = 0,
        commands: Collection[str] | None = tuple(COMMANDS),
        **overrides: Any,
    ) -> Limits:
        return cls(
            mtu=config.mtu,
            max_group_types=config.max_group_types,
            max_channels=config.max_channels,
            min_period_s=config.min_period_s,
            gateway_node=gateway_node,
            known_nodes=None if known_nodes is None else frozenset(known_nodes),
            commands=None if commands is None else frozenset(commands),
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
    # The version the payload says it has: the gateway's own retained copy of a
    # definition (or a copy of it) carries one; a user's definition does not.
    version: int | None = None


@dataclass(frozen=True, slots=True)
class Command:
    name: str
    body: CommandDef
    json: Mapping[str, Any] = field(compare=False)


# --------------------------------------------------------------------------- payload helpers


_STRINGS = re.compile(r'"(?:[^"\\]|\\.)*"')
_NOT_BRACKETS = re.compile(r"[^\[\]{}]+")


def is_empty(payload: bytes, limits: Limits) -> bool:
    """An empty (or all-whitespace, within the size limit) payload: a deletion."""
    return len(payload) <= limits.max_payload_bytes and not payload.strip()


def is_copy(payload: bytes) -> bool:
    """Whether a definition payload carries a ``version``: a gateway's copy of a
    definition (docs/gateway.md, One truth). Pure and cheap (the inboxes ask it in
    bursts); a payload that is not a JSON object is no copy (refused in its turn)."""
    if len(payload) > MAX_COPY_BYTES or b'"version"' not in payload:
        return False
    try:
        doc = json.loads(payload)
    except (ValueError, RecursionError):
        return False
    return isinstance(doc, dict) and "version" in doc


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


def decode_payload(payload: bytes, limits: Limits) -> Any:
    """Size, UTF-8, depth and JSON checks; returns the JSON value.

    The caller handles the empty payload (:func:`is_empty`) first: here it is
    not JSON. A JSON ``null`` comes back as None, for the caller to refuse.
    """
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
    try:
        return json.loads(text, parse_constant=_no_constant)
    except (json.JSONDecodeError, ValueError, RecursionError) as e:
        raise InvalidJson(f"payload is not JSON: {e}") from None


def _no_constant(name: str) -> Any:
    raise ValueError(f"{name} is not allowed")


def _type_name(v: object) -> str:
    if v is None:
        return "null"
    return {
        bool: "boolean",
        int: "integer",
        float: "number",
        str: "string",
        list: "array",
        dict: "object",
    }.get(type(v), type(v).__name__)


def _object(
    v: object, what: str, allowed: Collection[str], required: Collection[str]
) -> dict[str, Any]:
    if not isinstance(v, dict):
        raise WrongType(f"{what} must be a JSON object, got {_type_name(v)}")
    extra = sorted(set(v) - set(allowed))
    if extra:
        raise UnknownField(
            f"{what}: unknown field {extra[0]!r}; allowed: {', '.join(sorted(allowed))}"
        )
    missing = [k for k in required if k not in v]
    if missing:
        raise MissingField(f"{what}: missing field {missing[0]!r}")
    return v


def _number(v: object, what: str) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise WrongType(f"{what} must be a number, got {_type_name(v)}")
    if not math.isfinite(v):
        raise BadValue(f"{what} must be finite")
    return float(v)


def _integer(v: object, what: str, *, or_any: bool = False) -> int:
    if isinstance(v, float) and v.is_integer():
        v = int(v)
    if isinstance(v, bool) or not isinstance(v, int):
        kind = 'an integer or "*"' if or_any else "an integer"
        raise WrongType(f"{what} must be {kind}, got {_type_name(v)}")
    return v


def _version(v: object) -> int | None:
    """The optional ``version`` of a definition: what the gateway published it under."""
    if v is None:
        return None
    n = _integer(v, "version")
    if not 1 <= n <= MAX_DECLARED_VERSION:
        raise BadValue(f"version {n} out of range 1..{MAX_DECLARED_VERSION}")
    return n


def _string(v: object, what: str) -> str:
    if not isinstance(v, str):
        raise WrongType(f"{what} must be a string, got {_type_name(v)}")
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
    doc = decode_payload(payload, limits)
    obj = _object(doc, "group definition", ("conditions", "hysteresis", "version"), ("conditions",))
    conds_doc = obj["conditions"]
    if not isinstance(conds_doc, list):
        raise WrongType(f"conditions must be an array, got {_type_name(conds_doc)}")
    if not 1 <= len(conds_doc) <= MAX_CONDITIONS:
        raise BadValue(f"a group needs 1..{MAX_CONDITIONS} conditions, got {len(conds_doc)}")
    conds: list[Condition] = []
    for i, c in enumerate(conds_doc):
        what = f"conditions[{i}]"
        co = _object(c, what, ("attr", "op", "value"), ("attr", "op", "value"))
        attr = _attribute(_string(co["attr"], f"{what}.attr"), what)
        op_text = _string(co["op"], f"{what}.op")
        try:
            op = Op.from_symbol(op_text)
        except ValueError as e:
            raise BadOperator(f"{what}: {e}") from None
        value = _number(co["value"], f"{what}.value")
        conds.append(Condition(attr, op, value))
    hyst = _number(obj.get("hysteresis", 0.0), "hysteresis")
    if hyst < 0:
        raise BadValue(f"hysteresis must be >= 0, got {hyst}")
    body = GroupTypeDef(tuple(conds), hyst)
    check_fits(ItemKind.GROUP_TYPE, gtype, body, limits)
    if gtype not in defined and len(set(defined)) >= limits.max_group_types:
        raise TooManyDefinitions(
            f"{limits.max_group_types} group types are already defined (the motes' limit); "
            "delete one first"
        )
    return Definition(
        ItemKind.GROUP_TYPE, gtype, body, group_type_json(body), _version(obj.get("version"))
    )


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
    doc = decode_payload(payload, limits)
    keys = ("attr", "group_type", "group_id", "period_s", "agg", "version")
    obj = _object(doc, "channel definition", keys, ("attr", "period_s"))
    attr = _attribute(_string(obj["attr"], "attr"), "")
    gt_doc = obj.get("group_type", ANY)
    if gt_doc == ANY:
        gtype = ANY_GROUP_TYPE
    else:
        gtype = _integer(gt_doc, "group_type", or_any=True)
        if not 0 <= gtype <= limits.max_group_type:
            raise GroupTypeOutOfRange(f"group_type {gtype} out of range 0..{limits.max_group_type}")
    gid_doc = obj.get("group_id", ANY)
    if gid_doc == ANY:
        gid = ANY_GROUP_ID
    else:
        gid = _integer(gid_doc, "group_id", or_any=True)
        if not 1 <= gid < ANY_GROUP_ID:
            raise GroupIdOutOfRange(f"group_id {gid} out of range 1..{ANY_GROUP_ID - 1}")
    period = _number(obj["period_s"], "period_s")
    if not limits.min_period_s <= period <= limits.max_period_s:
        raise PeriodOutOfRange(
            f"period_s {period:g} out of range {limits.min_period_s:g}..{limits.max_period_s:g}"
        )
    agg_text = _string(obj.get("agg", "avg"), "agg").lower()
    if agg_text not in AGG_NAMES:
        raise UnknownAggregation(f"unknown agg {agg_text!r}; use one of {', '.join(AGG_NAMES)}")
    body = ChannelDef(attr, gtype, gid, round(period * 1000), AGG_NAMES[agg_text])
    check_fits(ItemKind.CHANNEL, ch, body, limits)
    if ch not in defined and len(set(defined)) >= limits.max_channels:
        raise TooManyDefinitions(
            f"{limits.max_channels} channels are already defined (the motes' limit); "
            "delete one first"
        )
    return Definition(ItemKind.CHANNEL, ch, body, channel_json(body), _version(obj.get("version")))


def parse_definition(
    rel_topic: str,
    payload: bytes,
    limits: Limits,
    groups: Collection[int] = (),
    channels: Collection[int] = (),
) -> Definition:
    """``def/group/<type>`` or ``def/channel/<id>`` (relative to the prefix) parsed;
    ``groups`` / ``channels``: the ids defined already (table sizes)."""
    parts = rel_topic.split("/")
    if len(parts) == 3 and parts[:2] == ["def", "group"]:
        return parse_group_type(parts[2], payload, limits, groups)
    if len(parts) == 3 and parts[:2] == ["def", "channel"]:
        return parse_channel(parts[2], payload, limits, channels)
    raise UnknownTopic(
        f"unknown topic {rel_topic!r}; use def/group/<type>, def/channel/<id> or cmd/<name>"
    )


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
    if limits.commands is not None and name not in limits.commands:
        raise UnknownCommand(
            f"unknown command {name!r}; motes accept: {', '.join(sorted(limits.commands))}"
        )
    doc = {} if is_empty(payload, limits) else decode_payload(payload, limits)
    obj = _object(doc, "command", ("target", "args"), ())
    target = obj.get("target", "all")
    tk, ta, tb, tjson = _parse_target(target, limits, group_types)
    args_doc = obj.get("args", {})
    if not isinstance(args_doc, dict):
        raise WrongType(f"args must be a JSON object, got {_type_name(args_doc)}")
    if len(args_doc) > MAX_COMMAND_ARGS:
        raise BadCommand(f"at most {MAX_COMMAND_ARGS} command arguments, got {len(args_doc)}")
    args: list[tuple[str, ArgValue]] = []
    for k, v in args_doc.items():
        if not isinstance(v, int | float | str | bool) or (
            isinstance(v, float) and not math.isfinite(v)
        ):
            raise WrongType(f"args.{k} must be a number, string or boolean, got {_type_name(v)}")
        args.append((k, v))
    body = CommandDef(name, tk, ta, tb, tuple(args))
    check_fits(ItemKind.COMMAND, 0, body, limits)
    return Command(name, body, {"target": tjson, "args": dict(args)})


def _parse_target(
    target: object, limits: Limits, group_types: Collection[int] | None
) -> tuple[TargetKind, int, int, Any]:
    if target == "all":
        return TargetKind.ALL, 0, 0, "all"
    if isinstance(target, dict) and set(target) == {"node"}:
        node = _integer(target["node"], "target.node")
        if not 0 <= node <= MAX_NODE_ID:
            raise UnknownTarget(f"target node {node} out of range 0..{MAX_NODE_ID}")
        if limits.known_nodes is not None and node not in limits.known_nodes:
            raise UnknownTarget(f"target node {node} is not in the deployment")
        return TargetKind.NODE, node, 0, {"node": node}
    if isinstance(target, dict) and set(target) == {"group_type", "group_id"}:
        gt = _integer(target["group_type"], "target.group_type")
        any_id = target["group_id"] == ANY
        gid = (
            ANY_GROUP_ID if any_id else _integer(target["group_id"], "target.group_id", or_any=True)
        )
        if not 0 <= gt <= limits.max_group_type:
            raise UnknownTarget(f"target group_type {gt} out of range 0..{limits.max_group_type}")
        if not any_id and not 1 <= gid < ANY_GROUP_ID:
            raise UnknownTarget(f"target group_id {gid} out of range 1..{ANY_GROUP_ID - 1}")
        if group_types is not None and gt not in group_types:
            raise UnknownTarget(f"target group_type {gt} is not defined")
        return TargetKind.GROUP, gt, gid, {"group_type": gt, "group_id": ANY if any_id else gid}
    raise UnknownTarget(
        f'unknown command target {json.dumps(target)[:80]}; use "all", '
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
