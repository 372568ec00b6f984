"""Validation of the IP-side JSON contract (awaremw.gateway.schema)."""

from __future__ import annotations

import contextlib
import json
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from awaremw.gateway import schema
from awaremw.gateway.schema import Limits, SchemaError
from awaremw.protocol.attributes import RSSI_BASE, TEMPERATURE, X
from awaremw.protocol.frames import (
    ANY_GROUP_ID,
    ANY_GROUP_TYPE,
    AggId,
    ChannelDef,
    CommandDef,
    GroupTypeDef,
    ItemKind,
    Op,
    TargetKind,
)

LIM = Limits()


def j(obj: Any) -> bytes:
    return json.dumps(obj).encode()


GROUP_OK = {"conditions": [{"attr": "temperature", "op": ">", "value": 45}], "hysteresis": 1}
CHANNEL_OK = {"attr": "temperature", "group_type": 1, "group_id": "*", "period_s": 2, "agg": "avg"}


def test_group_definition_parses_to_radio_form() -> None:
    d = schema.parse_group_type("1", j(GROUP_OK), LIM)
    assert d.kind is ItemKind.GROUP_TYPE and d.item_id == 1
    assert isinstance(d.body, GroupTypeDef)
    assert d.body.conditions[0].attr == TEMPERATURE
    assert d.body.conditions[0].op is Op.GT
    assert d.body.conditions[0].value == 45.0
    assert d.body.hysteresis == 1.0
    assert d.json == {
        "conditions": [{"attr": "temperature", "op": ">", "value": 45.0}],
        "hysteresis": 1.0,
    }


def test_rssi_attribute_and_several_conditions() -> None:
    doc = {
        "conditions": [
            {"attr": "rssi:12", "op": ">=", "value": -80},
            {"attr": "x", "op": "<", "value": 10.5},
        ]
    }
    d = schema.parse_group_type("3", j(doc), LIM)
    assert isinstance(d.body, GroupTypeDef)
    assert [c.attr for c in d.body.conditions] == [RSSI_BASE | 12, X]
    assert d.body.hysteresis == 0.0


def test_channel_definition_parses_with_wildcards() -> None:
    d = schema.parse_channel("2", j(CHANNEL_OK), LIM)
    assert d.body == ChannelDef(TEMPERATURE, 1, ANY_GROUP_ID, 2000, AggId.AVG)
    d = schema.parse_channel("0", j({"attr": "x", "period_s": 0.5}), LIM)
    assert d.body == ChannelDef(X, ANY_GROUP_TYPE, ANY_GROUP_ID, 500, AggId.AVG)
    assert d.json == {
        "attr": "x",
        "group_type": "*",
        "group_id": "*",
        "period_s": 0.5,
        "agg": "avg",
    }


def test_empty_payload_deletes() -> None:
    assert schema.parse_group_type("4", b"", LIM).body is None
    assert schema.parse_channel("4", b"  ", LIM).body is None


def test_command_targets() -> None:
    c = schema.parse_command("blink", j({"target": "all", "args": {"n": 3, "on": True}}), LIM)
    assert c.body == CommandDef("blink", TargetKind.ALL, 0, 0, (("n", 3), ("on", True)))
    c = schema.parse_command("blink", j({"target": {"node": 7}}), LIM)
    assert (c.body.target_kind, c.body.target_a) == (TargetKind.NODE, 7)
    c = schema.parse_command(
        "alarm", j({"target": {"group_type": 1, "group_id": 513}}), LIM, group_types={1}
    )
    assert (c.body.target_kind, c.body.target_a, c.body.target_b) == (TargetKind.GROUP, 1, 513)
    assert schema.parse_command("ping", b"", LIM).body.target_kind is TargetKind.ALL
    c = schema.parse_command("alarm", j({"target": {"group_type": 1, "group_id": "*"}}), LIM)
    assert (c.body.target_a, c.body.target_b) == (1, ANY_GROUP_ID)
    assert c.json["target"] == {"group_type": 1, "group_id": "*"}


# (parser, topic id, payload, expected error class). Every entry is one malformed
# input of the list in docs/gateway.md.
MALFORMED: list[tuple[str, str, bytes, type[SchemaError]]] = [
    ("group", "1", b"\xff\xfe{", schema.InvalidUtf8),
    ("group", "1", b'{"conditions": [', schema.InvalidJson),
    ("group", "1", b"NaN", schema.InvalidJson),
    ("group", "1", b" " + b"x" * 5000, schema.PayloadTooLarge),
    ("group", "1", j([1, 2]), schema.WrongType),
    ("group", "1", j({"conditions": "temperature > 45"}), schema.WrongType),
    (
        "group",
        "1",
        j({"conditions": [{"attr": "temp", "op": ">", "value": 4}]}),
        schema.UnknownAttributeName,
    ),
    (
        "group",
        "1",
        j({"conditions": [{"attr": "rssi:99999", "op": ">", "value": 4}]}),
        schema.UnknownAttributeName,
    ),
    ("group", "1", j({"conditions": [{"attr": "x", "op": "=>", "value": 4}]}), schema.BadOperator),
    ("group", "1", j({"conditions": [{"attr": "x", "op": ">", "value": "4"}]}), schema.WrongType),
    ("group", "1", j({"conditions": [{"attr": "x", "op": ">", "value": True}]}), schema.WrongType),
    ("group", "1", j({"conditions": [{"attr": "x", "op": ">"}]}), schema.MissingField),
    ("group", "1", j({"conditions": []}), schema.BadValue),
    ("group", "1", j({**GROUP_OK, "hysteresis": -1}), schema.BadValue),
    ("group", "1", j({**GROUP_OK, "colour": "red"}), schema.UnknownField),
    ("group", "255", j(GROUP_OK), schema.GroupTypeOutOfRange),
    ("group", "-1", j(GROUP_OK), schema.GroupTypeOutOfRange),
    ("group", "one", j(GROUP_OK), schema.GroupTypeOutOfRange),
    ("channel", "256", j(CHANNEL_OK), schema.ChannelIdOutOfRange),
    ("channel", "x", j(CHANNEL_OK), schema.ChannelIdOutOfRange),
    ("channel", "1", j({**CHANNEL_OK, "period_s": 0.01}), schema.PeriodOutOfRange),
    ("channel", "1", j({**CHANNEL_OK, "period_s": 1e9}), schema.PeriodOutOfRange),
    ("channel", "1", j({**CHANNEL_OK, "period_s": "2"}), schema.WrongType),
    ("channel", "1", j({**CHANNEL_OK, "agg": "median"}), schema.UnknownAggregation),
    ("channel", "1", j({**CHANNEL_OK, "attr": "pressure"}), schema.UnknownAttributeName),
    ("channel", "1", j({**CHANNEL_OK, "group_type": 300}), schema.GroupTypeOutOfRange),
    ("channel", "1", j({**CHANNEL_OK, "group_type": "any"}), schema.WrongType),
    ("channel", "1", j({**CHANNEL_OK, "group_id": 0}), schema.GroupIdOutOfRange),
    ("channel", "1", j({**CHANNEL_OK, "group_id": 65535}), schema.GroupIdOutOfRange),
    ("channel", "1", j({"attr": "x"}), schema.MissingField),
    ("command", "blink", j({"target": "some"}), schema.UnknownTarget),
    ("command", "blink", j({"target": {"robot": 3}}), schema.UnknownTarget),
    ("command", "blink", j({"target": {"node": 65534}}), schema.UnknownTarget),
    ("command", "blink", j({"args": [1]}), schema.WrongType),
    ("command", "blink", j({"args": {"a": {"b": 1}}}), schema.WrongType),
    ("command", "blink", j({"args": {"msg": "x" * 90}}), schema.DoesNotFitMtu),
    ("command", "a" * 17, j({}), schema.BadCommand),
    ("command", "bl ink", j({}), schema.BadCommand),
]


def _parse(kind: str, ident: str, payload: bytes, limits: Limits = LIM) -> object:
    if kind == "group":
        return schema.parse_group_type(ident, payload, limits)
    if kind == "channel":
        return schema.parse_channel(ident, payload, limits)
    return schema.parse_command(ident, payload, limits)


@pytest.mark.parametrize(("kind", "ident", "payload", "err"), MALFORMED)
def test_malformed_payload_gets_a_specific_error(
    kind: str, ident: str, payload: bytes, err: type[SchemaError]
) -> None:
    with pytest.raises(err) as e:
        _parse(kind, ident, payload)
    assert type(e.value) is err  # the specific class, not a parent
    assert str(e.value)  # a message for humans
    assert e.value.code != SchemaError.code


def test_error_codes_are_distinct() -> None:
    classes = [
        c for c in vars(schema).values() if isinstance(c, type) and issubclass(c, SchemaError)
    ]
    codes = [c.code for c in classes]
    assert len(codes) == len(set(codes))


def test_unknown_command_node_when_deployment_known() -> None:
    lim = Limits(known_nodes=frozenset({1, 2, 3}))
    schema.parse_command("blink", j({"target": {"node": 2}}), lim)
    with pytest.raises(schema.UnknownTarget, match="not in the deployment"):
        schema.parse_command("blink", j({"target": {"node": 9}}), lim)


def test_group_target_must_name_a_defined_type() -> None:
    with pytest.raises(schema.UnknownTarget, match="not defined"):
        schema.parse_command(
            "a", j({"target": {"group_type": 2, "group_id": 5}}), LIM, group_types={1}
        )


def test_too_many_definitions() -> None:
    lim = Limits(max_channels=2, max_group_types=1)
    schema.parse_channel("5", j(CHANNEL_OK), lim, defined={5, 6})  # redefining is fine
    with pytest.raises(schema.TooManyDefinitions):
        schema.parse_channel("7", j(CHANNEL_OK), lim, defined={5, 6})
    with pytest.raises(schema.TooManyDefinitions):
        schema.parse_group_type("2", j(GROUP_OK), lim, defined={1})


def test_smaller_mtu_refuses_what_a_larger_accepts() -> None:
    doc = {"conditions": [{"attr": "temperature", "op": ">", "value": 1.5}] * 4}
    schema.parse_group_type("1", j(doc), Limits(mtu=100))
    with pytest.raises(schema.DoesNotFitMtu, match="MTU of 30"):
        schema.parse_group_type("1", j(doc), Limits(mtu=30))


json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=8),
    lambda kids: (
        st.lists(kids, max_size=4) | st.dictionaries(st.text(max_size=8), kids, max_size=4)
    ),
    max_leaves=12,
)
nice_keys = st.sampled_from(
    [
        "conditions",
        "hysteresis",
        "attr",
        "op",
        "value",
        "group_type",
        "group_id",
        "period_s",
        "agg",
        "target",
        "args",
        "node",
    ]
)
near_miss = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-2, 70000)
    | st.floats(allow_nan=False)
    | st.sampled_from(["temperature", "x", "rssi:3", ">", "<=", "*", "avg", "all", "=="]),
    lambda kids: st.lists(kids, max_size=4) | st.dictionaries(nice_keys, kids, max_size=5),
    max_leaves=14,
)


@settings(max_examples=300, deadline=None)
@given(
    kind=st.sampled_from(["group", "channel", "command"]),
    ident=st.sampled_from(["0", "1", "254", "255", "blink", "x"]),
    doc=json_values | near_miss,
)
def test_any_json_is_parsed_or_refused_never_crashes(kind: str, ident: str, doc: Any) -> None:
    with contextlib.suppress(SchemaError):
        _parse(kind, ident, json.dumps(doc).encode())


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=64))
def test_any_bytes_are_parsed_or_refused(data: bytes) -> None:
    for kind in ("group", "channel", "command"):
        with contextlib.suppress(SchemaError):
            _parse(kind, "1", data)


# Edge cases where a schema library's defaults differ from the contract (found while
# measuring a msgspec version, benchmarks/schema_speed.py): each keeps its code.
EDGES: list[tuple[str, bytes, str]] = [
    ("channel", j({"attr": "x", "period_s": 2, "group_id": 513.0}), "ok"),  # JSON integer
    ("channel", j({"attr": "x", "period_s": 2, "group_id": 1.5}), "wrong_type"),
    ("channel", j({"attr": "x", "period_s": 2, "group_type": True}), "wrong_type"),
    ("channel", j({"attr": "x", "period_s": 2, "agg": "MAX"}), "ok"),  # case-insensitive
    ("channel", j({"attr": "x", "period_s": 2, "group_id": 1e300}), "group_id_out_of_range"),
    ("group", b'{"conditions": [{"attr": "x", "op": ">", "value": 1e999}]}', "bad_value"),
    ("group", j({"conditions": [{"attr": "x", "op": ">", "value": 1}] * 9}), "bad_value"),
    ("group", j({"conditions": [{"attr": "x", "op": ">", "value": 1, "q": 2}]}), "unknown_field"),
    ("command", j({"target": {"node": 7.0}}), "ok"),
    ("command", j({"target": {"node": "7"}}), "wrong_type"),
    ("command", j({"target": 5}), "unknown_target"),
    ("command", j({"target": {"group_type": 1}}), "unknown_target"),
    ("command", j({"target": {"node": 1, "group_type": 1}}), "unknown_target"),
    ("command", j({"target": {"group_type": 1, "group_id": 0}}), "unknown_target"),
    ("command", b'{"args": {"a": 1e999}}', "wrong_type"),
    ("command", j({"args": {"a": None}}), "wrong_type"),
    ("command", j({"args": {str(i): i for i in range(9)}}), "bad_command"),
]


@pytest.mark.parametrize(("kind", "payload", "code"), EDGES)
def test_edge_payloads_keep_their_code(kind: str, payload: bytes, code: str) -> None:
    try:
        _parse(kind, "blink" if kind == "command" else "1", payload)
        got = "ok"
    except SchemaError as e:
        got = e.code
        assert str(e)
    assert got == code
