"""The SQLite version store and the transport-independent bridge."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from awaremw.gateway.bridge import BridgePolicy, GatewayBridge
from awaremw.gateway.events import Inject
from awaremw.gateway.schema import Limits
from awaremw.gateway.store import VersionStore
from awaremw.protocol.frames import (
    ChannelDef,
    CommandDef,
    Condition,
    DataRecord,
    GroupReport,
    GroupStatus,
    GroupTypeDef,
    ItemKind,
    Op,
    TargetKind,
)

G1 = GroupTypeDef((Condition(0, Op.GT, 45.0),), 1.0)
G2 = GroupTypeDef((Condition(0, Op.GT, 50.0),), 1.0)
C1 = ChannelDef(0, 1, 0xFFFF, 2000, 0)


def j(obj: Any) -> bytes:
    return json.dumps(obj).encode()


GROUP = j({"conditions": [{"attr": "temperature", "op": ">", "value": 45}], "hysteresis": 1})
CHANNEL = j({"attr": "temperature", "group_type": 1, "group_id": "*", "period_s": 2, "agg": "avg"})


def test_versions_increase_and_survive_reopen(tmp_path: Path) -> None:
    path = tmp_path / "state" / "gw.sqlite"
    with VersionStore(path) as s:
        a = s.apply(ItemKind.GROUP_TYPE, 1, G1, {"a": 1})
        assert a is not None and a.version == 1
        assert s.apply(ItemKind.GROUP_TYPE, 1, G1, {"a": 1}) is None  # same body: no version
        b = s.apply(ItemKind.GROUP_TYPE, 1, G2, {"a": 2})
        assert b is not None and b.version == 2
        c = s.apply(ItemKind.CHANNEL, 1, C1, None)
        assert c is not None and c.version == 1
    with VersionStore(path) as s:
        got = s.get(ItemKind.GROUP_TYPE, 1)
        assert got is not None and got.version == 2 and got.body == G2 and got.json == {"a": 2}
        d = s.apply(ItemKind.GROUP_TYPE, 1, None, None)  # deletion is a version too
        assert d is not None and d.version == 3 and d.deleted
    with VersionStore(path) as s:
        assert [(i.kind, i.item_id, i.version, i.body) for i in s.items()] == [
            (ItemKind.GROUP_TYPE, 1, 3, None),
            (ItemKind.CHANNEL, 1, 1, C1),
        ]
        assert s.defined_ids(ItemKind.GROUP_TYPE) == set()
        e = s.apply(ItemKind.GROUP_TYPE, 1, G1, None)  # redefined after deletion
        assert e is not None and e.version == 4


def test_deleting_what_never_existed_is_a_no_op() -> None:
    with VersionStore() as s:
        assert s.apply(ItemKind.CHANNEL, 9, None, None) is None
        assert s.items() == []


def test_bump_always_makes_a_version() -> None:
    cmd = CommandDef("blink")
    with VersionStore() as s:
        assert s.bump(ItemKind.COMMAND, 0, cmd, None).version == 1
        assert s.bump(ItemKind.COMMAND, 0, cmd, None).version == 2


def test_command_slots_reuse_least_recently_used(tmp_path: Path) -> None:
    with VersionStore(tmp_path / "s.db") as s:
        assert [s.command_slot(n, 2) for n in ("a", "b", "a")] == [0, 1, 0]
        assert s.command_slot("c", 2) == 1  # b is the least recently used
        assert s.command_slot("b", 2) == 0  # now a is
    with VersionStore(tmp_path / "s.db") as s:
        assert s.command_slot("b", 2) == 0
        assert s.command_slot("c", 2) == 1


# --------------------------------------------------------------------------- bridge


def bridge(store: VersionStore | None = None, **kw: Any) -> GatewayBridge:
    return GatewayBridge(store or VersionStore(), Limits(), BridgePolicy(**kw))


def test_definition_accepted_then_unchanged_then_changed() -> None:
    b = bridge()
    o = b.handle("def/group/1", GROUP, source="aware/def/group/1")
    assert o.inject == Inject(ItemKind.GROUP_TYPE, 1, 1, G1)
    # Same definition, different spelling: no new version, nothing to inject.
    o = b.handle("def/group/1", GROUP.replace(b" ", b""), source="aware/def/group/1")
    assert o.inject is None and o.error is None and not o.replay
    o = b.handle("def/channel/3", CHANNEL, source="aware/def/channel/3")
    assert o.inject == Inject(ItemKind.CHANNEL, 3, 1, C1)
    o = b.handle("def/channel/3", b"", source="aware/def/channel/3")
    assert o.inject == Inject(ItemKind.CHANNEL, 3, 2, None)
    assert b.definitions() == {
        "def/group/1": {
            "conditions": [{"attr": "temperature", "op": ">", "value": 45.0}],
            "hysteresis": 1.0,
            "version": 1,
        }
    }


def test_refusal_leaves_definitions_unchanged() -> None:
    b = bridge()
    b.handle("def/channel/3", CHANNEL, source="t")
    before = b.store.items()
    bad = j({"attr": "temperature", "period_s": 0.001})
    o = b.handle("def/channel/3", bad, source="aware/def/channel/3")
    assert o.inject is None and o.error is not None
    assert o.error.code == "period_out_of_range"
    assert o.error.topic == "aware/def/channel/3"
    assert json.loads(o.error.to_json())["payload"] == bad.decode()
    assert b.store.items() == before
    o = b.handle("def/nonsense/3", CHANNEL, source="aware/def/nonsense/3")
    assert o.error is not None and o.error.code == "unknown_topic"


def test_retained_replay_is_not_applied_twice(tmp_path: Path) -> None:
    path = tmp_path / "gw.sqlite"
    b = bridge(VersionStore(path))
    assert b.handle("def/group/1", GROUP, source="aware/def/group/1", retained=True).accepted
    b.store.close()
    # Restart: the broker replays the retained definition.
    b = bridge(VersionStore(path))
    assert b.startup() == [Inject(ItemKind.GROUP_TYPE, 1, 1, G1)]
    o = b.handle("def/group/1", GROUP, source="aware/def/group/1", retained=True)
    assert o.replay and o.inject is None
    # Changed through another transport meanwhile: the stale retained replay
    # does not revert it, but a live republish of the old body does.
    g2 = GROUP.replace(b"45", b"50")
    assert b.handle("def/group/1", g2, source="aware/hbn/def/group/1").accepted
    assert b.handle("def/group/1", GROUP, source="aware/def/group/1", retained=True).replay
    o = b.handle("def/group/1", GROUP, source="aware/def/group/1", retained=False)
    assert o.inject == Inject(ItemKind.GROUP_TYPE, 1, 3, G1)


def test_refused_retained_payload_is_reported_once() -> None:
    b = bridge()
    first = b.handle("def/group/1", b"{", source="s", retained=True).error
    assert first is not None and first.code == "invalid_json"
    assert b.handle("def/group/1", b"{", source="s", retained=True).replay


def test_commands_get_fresh_versions_in_their_slot() -> None:
    b = bridge(command_slots=4)
    o1 = b.handle("cmd/blink", j({"target": {"node": 3}, "args": {"n": 2}}), source="s")
    o2 = b.handle("cmd/blink", j({"target": {"node": 3}, "args": {"n": 2}}), source="s")
    o3 = b.handle("cmd/reset", b"", source="s2")
    assert o1.inject is not None and o2.inject is not None and o3.inject is not None
    assert (o1.inject.item_id, o1.inject.version) == (0, 1)
    assert (o2.inject.item_id, o2.inject.version) == (0, 2)
    assert (o3.inject.item_id, o3.inject.version) == (1, 1)
    assert o1.inject.body == CommandDef("blink", TargetKind.NODE, 3, 0, (("n", 2),))
    o = b.handle("cmd/alarm", j({"target": {"group_type": 1, "group_id": 2}}), source="s")
    assert o.error is not None and o.error.code == "unknown_target"


def test_records_published_once_with_contract_fields() -> None:
    b = bridge()
    b.handle("def/channel/3", CHANNEL, source="t")
    r = DataRecord(3, 1, 513, 42, 0, 21.5, 4, 17)
    [p] = b.on_payload(r, 100.25)
    assert p.topic == "data/3/1/513" and p.qos == 1 and not p.retain
    assert json.loads(p.payload) == {
        "value": 21.5,
        "count": 4,
        "agg": "avg",
        "epoch": 42,
        "leader": 17,
        "t": 100.25,
        "attr": "temperature",
        "unit": "°C",
    }
    assert b.on_payload(r, 100.5) == []  # delivered twice (two roots): published once
    assert b.stats.duplicate_records == 1
    # Same epoch number, other content: a new period counts epochs anew.
    [p2] = b.on_payload(DataRecord(3, 1, 513, 42, 0, 20.0, 4, 17), 101.0)
    assert json.loads(p2.payload)["value"] == 20.0


def test_group_state_retained_then_cleared_when_gone_or_unheard() -> None:
    b = bridge(report_period_s=10.0, expiry_periods=3)
    [p] = b.on_payload(GroupReport(1, 513, 17, 4, 3), 5.0)
    assert p.topic == "groups/1/513" and p.retain
    assert json.loads(p.payload) == {
        "group_type": 1,
        "group_id": 513,
        "leader": 17,
        "weight": 4,
        "readings": 3,
        "t": 5.0,
    }
    # Merged into 600: the successor is published (retained), the state cleared one
    # report period later.
    [merged] = b.on_payload(GroupReport(1, 513, 17, 4, 0, GroupStatus.GONE, 600), 6.0)
    assert (merged.topic, merged.retain) == ("groups/1/513", True)
    assert json.loads(merged.payload) == {
        "group_type": 1,
        "group_id": 513,
        "merged_into": 600,
        "t": 6.0,
    }
    assert b.on_payload(GroupReport(1, 513, 17, 4, 0, GroupStatus.GONE, 600), 6.5) == []
    assert b.expire(15.9) == []
    [cleared] = b.expire(16.0)
    assert (cleared.topic, cleared.payload, cleared.retain) == ("groups/1/513", b"", True)
    # A group that split off names its parent; a dissolved one is only cleared.
    [p] = b.on_payload(GroupReport(1, 900, 5, 0, 2, GroupStatus.ALIVE, 513), 7.0)
    assert json.loads(p.payload)["split_from"] == 513
    [p] = b.on_payload(GroupReport(1, 900, 5, 0, 2, GroupStatus.GONE, 0), 8.0)
    assert (p.topic, p.payload) == ("groups/1/900", b"")

    b.on_payload(GroupReport(1, 7, 2, 1, 1), 10.0)
    b.on_payload(GroupReport(2, 8, 3, 1, 1), 20.0)
    assert b.expire(39.0) == []
    b.on_payload(DataRecord(0, 1, 7, 1, 0, 1.0, 1, 2), 30.0)  # records keep a group alive
    assert [p.topic for p in b.expire(55.0)] == ["groups/2/8"]
    assert [p.topic for p in b.expire(61.0)] == ["groups/1/7"]
    assert b.group_states() == {}
