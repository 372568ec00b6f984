"""Commands: exactly once per (slot, version) on each targeted mote."""

from __future__ import annotations

import random
from dataclasses import dataclass
from typing import cast

import pytest

from awaremw.bench.dissemination import RecordingApp, TrafficMote, build_grid, inject_at
from awaremw.protocol.commands import Commands
from awaremw.protocol.config import MiddlewareConfig
from awaremw.protocol.events import CommandExecuted
from awaremw.protocol.frames import (
    ANY_GROUP_ID,
    ChannelDef,
    CommandDef,
    ItemKind,
    TargetKind,
)
from awaremw.protocol.groups import Groups
from awaremw.protocol.mote import AwareMote, MoteContext
from awaremw.world.mobility import Static

CMD = ItemKind.COMMAND
BEEP = CommandDef("beep", args=(("ms", 200),))


@dataclass(frozen=True)
class FakeMembership:
    group_id: int


class FakeGroups:
    def __init__(self, member_of: dict[int, int]) -> None:
        self.member_of = member_of
        self.app_changes: list[float] = []

    def membership(self, group_type: int) -> FakeMembership | None:
        gid = self.member_of.get(group_type)
        return None if gid is None else FakeMembership(gid)

    def app_changed(self, now: float) -> None:
        self.app_changes.append(now)


def make(
    node: int = 4, groups: object = None, versions: dict[int, int] | None = None
) -> tuple[Commands, MoteContext, RecordingApp]:
    app = RecordingApp()
    ctx = MoteContext(node, MiddlewareConfig(), random.Random(0), app)
    table = versions if versions is not None else {}
    c = Commands(ctx, cast(Groups, groups or FakeGroups({})), lambda k, i: table.get(i))
    return c, ctx, app


def test_runs_once_per_slot_version() -> None:
    versions = {0: 1}
    c, ctx, app = make(versions=versions)
    c.define(0, BEEP, 1.0)
    c.define(0, BEEP, 2.0)  # same version again: not re-run
    assert app.commands == [(BEEP, 1.0)]
    assert ctx.event_list == [CommandExecuted("beep", 0, 1)]
    versions[0] = 2
    c.define(0, BEEP, 3.0)
    assert app.commands[-1] == (BEEP, 3.0) and ctx.event_list[-1] == CommandExecuted("beep", 0, 2)
    c.define(0, None, 4.0)  # slot deleted: nothing to run
    assert len(app.commands) == 2


def test_without_version_source_each_define_is_new() -> None:
    app = RecordingApp()
    ctx = MoteContext(1, MiddlewareConfig(), random.Random(0), app)
    c = Commands(ctx, cast(Groups, FakeGroups({})))
    c.define(3, BEEP, 0.0)
    c.define(3, BEEP, 1.0)
    assert ctx.event_list == [
        CommandExecuted("beep", 3, 1),
        CommandExecuted("beep", 3, 2),
    ]


def test_node_target() -> None:
    c, _, app = make(node=4, versions={0: 1, 1: 1})
    c.define(0, CommandDef("led", TargetKind.NODE, 5), 0.0)
    c.define(1, CommandDef("led", TargetKind.NODE, 4), 0.0)
    assert [cmd.target_a for cmd, _ in app.commands] == [4]


@pytest.mark.parametrize(
    ("member_of", "target_b", "runs"),
    [
        ({2: 513}, 513, True),
        ({2: 514}, 513, False),
        ({2: 514}, ANY_GROUP_ID, True),
        ({3: 513}, 513, False),
        ({}, ANY_GROUP_ID, False),
    ],
)
def test_group_target(member_of: dict[int, int], target_b: int, runs: bool) -> None:
    c, _, app = make(groups=FakeGroups(member_of), versions={0: 1})
    c.define(0, CommandDef("sample", TargetKind.GROUP, 2, target_b), 0.0)
    assert bool(app.commands) is runs


def test_group_target_without_group_support_runs_nowhere() -> None:
    c, _, app = make(groups=object(), versions={0: 1})
    c.define(0, CommandDef("sample", TargetKind.GROUP, 2, 513), 0.0)
    assert not app.commands


def test_no_application_no_event_and_wrong_body_is_our_bug() -> None:
    ctx = MoteContext(1, MiddlewareConfig(), random.Random(0), None)
    c = Commands(ctx, cast(Groups, FakeGroups({})), lambda k, i: 1)
    c.define(0, BEEP, 0.0)
    assert ctx.event_list == []
    with pytest.raises(TypeError):
        c.define(0, ChannelDef(0, 1, 1, 1000, 0), 0.0)


def test_aware_mote_passes_the_disseminated_version() -> None:
    app = RecordingApp()
    m = AwareMote(3, app, MiddlewareConfig(), random.Random(0))
    m.start(0.0)
    m.inject(CMD, 2, 7, BEEP, 1.0)
    m.inject(CMD, 2, 7, BEEP, 2.0)  # idempotent
    m.inject(CMD, 2, 9, CommandDef("beep", args=(("ms", 50),)), 3.0)
    execs = [e for e in m.events() if isinstance(e, CommandExecuted)]
    assert execs == [CommandExecuted("beep", 2, 7), CommandExecuted("beep", 2, 9)]
    assert [t for _, t in app.commands] == [1.0, 3.0]


def test_commands_reach_targets_over_the_network_once() -> None:
    net, motes, events = build_grid(6, 12.0, {0}, seed=5)
    net.run_until(10.0)
    inject_at(net, motes[0], 10.0, CMD, 0, 1, CommandDef("beep"))
    inject_at(net, motes[0], 10.0, CMD, 1, 1, CommandDef("led", TargetKind.NODE, 35))
    net.run_until(60.0)
    for i, m in motes.items():
        names = sorted(c.name for c, _ in m.app.commands)  # two items: any order
        assert names == (["beep", "led"] if i == 35 else ["beep"]), (i, names)
    # A mote added late finds the commands still in their slots and runs the
    # one that targets it once (docs/protocol-dissemination.md, "Commands").
    late = TrafficMote(50, MiddlewareConfig(), seed=5)
    net.add(late, Static(30.0, 30.0))
    net.run_until(70.0)
    assert [c.name for c, _ in late.app.commands] == ["beep"]
    execs = [(n, e) for n, e, _ in events if isinstance(e, CommandExecuted)]
    assert len(execs) == len(motes) + 2  # every mote, plus 35's led, plus the late mote


def test_group_commands_run_on_the_members_of_real_groups() -> None:
    """Two groups formed by the protocol (two hot discs): a command aimed at one
    group id runs on exactly that group's members, one aimed at any id of the type
    on the members of both, and never on a mote outside them."""
    from scenarios import Scenario, in_disc, indicator

    from awaremw.protocol.attributes import TEMPERATURE
    from awaremw.protocol.frames import Condition, GroupTypeDef, Op

    def hot(p: tuple[float, float], t: float) -> bool:
        return in_disc(24, 24, 14)(p) or in_disc(96, 24, 14)(p)

    sc = Scenario(seed=4)
    sc.grid(10, 5, {TEMPERATURE: indicator(hot)})
    sc.run_until(1.0)
    sc.define_group(1, GroupTypeDef((Condition(TEMPERATURE, Op.GT, 50.0),)))
    sc.run_until(30.0)
    members = sc.memberships(1)
    by_gid: dict[int, set[int]] = {}
    for n, m in members.items():
        by_gid.setdefault(m.group_id, set()).add(n)
    assert len(by_gid) == 2 and all(len(v) >= 3 for v in by_gid.values())
    left = next(g for g, ns in by_gid.items() if all(sc.position(n)[0] < 60 for n in ns))
    sc.define(CMD, 0, CommandDef("sample", TargetKind.GROUP, 1, left), everywhere=False, at=[1])
    sc.define(CMD, 1, CommandDef("blink", TargetKind.GROUP, 1, ANY_GROUP_ID), everywhere=False,
              at=[1])  # fmt: skip
    sc.run_until(60.0)
    ran = {name: {n for n, app in sc.apps.items() if any(c.name == name for c, _ in app.commands)}
           for name in ("sample", "blink")}  # fmt: skip
    assert ran["sample"] == by_gid[left]
    assert ran["blink"] == set(members)
    assert len(sc.motes) - len(members) >= 30  # most motes are outside both groups


def test_a_command_run_tells_the_groups_that_readings_may_change() -> None:
    groups = FakeGroups({})
    c, _ctx, app = make(node=4, groups=groups, versions={0: 1, 1: 1})
    c.define(0, CommandDef("led", TargetKind.NODE, 5), 1.0)  # for mote 5: not run here
    assert groups.app_changes == []
    c.define(1, CommandDef("led", TargetKind.NODE, 4), 2.0)
    assert len(app.commands) == 1 and groups.app_changes == [2.0]
