"""Fleets: one process (add/kill/positions/control/battery) and many (real worker
processes joined by an embedded Zenoh router)."""

from __future__ import annotations

import asyncio
import json
import math
import time
from collections.abc import Callable

import pytest

from awaremw.cli.fleet import control_query
from awaremw.nodes import KindsFactory, app_of
from awaremw.protocol.core import MoteCore
from awaremw.protocol.events import MoteDown, MoteUp
from awaremw.protocol.hello import HelloMote
from awaremw.runtime.deployment import Deployment, NodeSpec, load, parse_deployment
from awaremw.runtime.fleet import (
    AnyFleet,
    Fleet,
    FleetLauncher,
    FleetSettings,
    LauncherSettings,
    open_fleet,
)
from awaremw.runtime.fleet.motes import hello_core
from awaremw.runtime.fleet.stats import merged_links
from awaremw.runtime.partition import stripes

pytestmark = pytest.mark.zenoh


def deployment(entries: list[dict[str, object]], area: float = 400.0) -> Deployment:
    return parse_deployment(
        {"name": "t", "seed": 3, "area": [area, area], "nodes": entries}, None, None
    )


def static(i: int, x: float, y: float, **kw: object) -> dict[str, object]:
    return {"id": i, "kind": "tmote", "position": [x, y], **kw}


async def wait_for(pred: Callable[[], bool], timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > deadline:
            raise AssertionError("condition not reached in time")
        await asyncio.sleep(0.01)


# --------------------------------------------------------------------------- one interface


async def drive(fleet: AnyFleet, duration: float) -> tuple[dict[int, int], int, int]:
    """The one code path both fleets run through: frames sent per mote, the
    processes that reported, the motes of the last snapshot."""
    async with fleet:
        await fleet.run(duration)
        assert fleet.now() >= duration
        await fleet.freeze(0.2)
    snap = fleet.stats.snapshot()
    tx = {n: c.frames_tx for n, c in fleet.counters().items()}
    assert sum(tx.values()) == snap.frames_tx or snap.t < duration  # a launcher's is older
    return tx, len(fleet.results), sum(r.motes for r in fleet.results)


@pytest.mark.parametrize("processes", [1, 2])
def test_one_process_or_many_through_one_interface(processes: int) -> None:
    dep = deployment([static(i, 20.0 + 15.0 * i, 50.0) for i in range(8)])
    settings = LauncherSettings(processes=processes, speed=4.0, progress_s=0.2, control=False)
    fleet = open_fleet(dep, hello_core, settings)
    assert isinstance(fleet, Fleet if processes == 1 else FleetLauncher)
    tx, reported, motes = asyncio.run(drive(fleet, 3.0))
    assert sorted(tx) == list(range(8)) and all(n >= 2 for n in tx.values()), tx
    assert (reported, motes) == (processes, 8)
    assert all(r.error is None and r.cpu_s > 0 for r in fleet.results)


def test_a_part_or_a_client_session_is_refused_over_processes() -> None:
    dep = deployment([static(1, 10.0, 10.0)])
    with pytest.raises(ValueError, match="one process"):
        LauncherSettings(processes=2, client=True, connect=("tcp/127.0.0.1:9",))
    with pytest.raises(ValueError, match="one process"):
        open_fleet(dep, hello_core, LauncherSettings(processes=2), part=stripes(dep, 2)[0])


# --------------------------------------------------------------------------- stripes


def test_stripes_split_along_x_with_open_ends() -> None:
    dep = deployment([static(i, 10.0 * (i % 8), 5.0 * (i // 8)) for i in range(32)])
    s = stripes(dep, 2)
    assert [sum(1 for n in dep.nodes if f(n)) for f in s] == [16, 16]
    assert s[0].lo == -math.inf and s[-1].hi == math.inf
    for n in dep.nodes:  # every mote has exactly one owner; equal x, same stripe
        assert sum(f(n) for f in s) == 1
    assert len(stripes(dep, 3)) == 3
    one_column = deployment([static(i, 7.0, 5.0 * i) for i in range(4)])
    s = stripes(one_column, 3)
    assert [sum(1 for n in one_column.nodes if f(n)) for f in s] == [4, 0, 0]


# --------------------------------------------------------------------------- two processes


async def test_two_processes_on_one_router_exchange_frames_only_within_range() -> None:
    # Stripe 0: x = 10..40; stripe 1: x = 50..80 and a far cluster at x = 300.
    # Range at 0 dBm is 54 m: near motes hear across the stripe boundary, the
    # far cluster hears only itself.
    entries = [static(i, 10.0 * (i + 1), 20.0) for i in range(8)]
    entries += [static(20 + i, 300.0 + 8.0 * i, 20.0) for i in range(3)]
    dep = deployment(entries)
    model = dep.radio_model()
    settings = LauncherSettings(processes=2, speed=4.0, track_links=True)
    async with FleetLauncher(dep, hello_core, settings) as launcher:
        assert launcher.motes_per_worker in ([4, 7], [5, 6], [6, 5], [7, 4])
        # Control plane: each request reaches both workers; exactly one acts.
        add = {"op": "add", "node": {"id": 50, "kind": "tmote", "position": [85.0, 30.0]}}
        replies = await asyncio.to_thread(control_query, [launcher.endpoint], "aware", add, 3.0)
        assert sorted(r["fleet"] for r in replies) == ["w0", "w1"]
        assert [r["fleet"] for r in replies if r["done"]] == ["w1"]
        replies = await asyncio.to_thread(
            control_query, [launcher.endpoint], "aware", {"op": "kill", "id": 1}, 3.0
        )
        assert [r["fleet"] for r in replies if r["done"]] == ["w0"]
        await launcher.run(6.0)
    assert all(r.error is None for r in launcher.results)
    links = merged_links(launcher.results)
    pos = {s.id: s.position for s in dep.nodes} | {50: (85.0, 30.0)}
    rng = model.max_range_m(0.0)
    for (a, b), n in links.items():
        assert n > 0 and math.dist(pos[a], pos[b]) <= rng, (a, b)
    owner = {s.id: (0 if f(s) else 1) for f in stripes(dep, 2)[:1] for s in dep.nodes}
    owner[50] = 1
    assert any(owner[a] != owner[b] for a, b in links)  # frames crossed processes
    far = {20, 21, 22}
    assert {(a, b) for a, b in links if a in far or b in far} == {
        (a, b) for a in far for b in far if a != b
    }
    assert stripes(dep, 2)[0].hi == 60.0
    assert (4, 5) in links and (5, 4) in links  # 10 m apart, on either side of the cut
    assert (50, 7) in links or (7, 50) in links  # the added mote is on the air
    counters = launcher.counters()
    assert counters[20].frames_tx > 0 and counters[50].frames_tx > 0


# --------------------------------------------------------------------------- one process


async def test_fleet_add_kill_positions_and_events() -> None:
    dep = deployment(
        [
            static(1, 10.0, 10.0),
            static(2, 20.0, 10.0),
            {"id": 3, "kind": "robot", "path": [[0.0, 0.0], [100.0, 0.0]], "speed_mps": 100.0},
        ]
    )
    events: list[tuple[int, object]] = []
    async with Fleet(dep, hello_core, FleetSettings(speed=10.0, control=False)) as f:
        f.on_event(lambda n, e, t: events.append((n, e)))
        assert set(f.cores) == {1, 2, 3}
        assert f.motes.positions(f.now())[1] == (10.0, 10.0)
        await f.wait_until(0.5)
        x, y = f.motes.positions(f.now())[3]
        assert 45.0 <= x <= 100.0 and y == 0.0
        spec = f.control.parse_node(static(9, 30.0, 10.0))
        f.motes.add(spec)
        assert 9 in f.cores and (9, MoteUp()) in events
        with pytest.raises(ValueError):
            f.motes.add(spec)
        assert f.motes.kill(2)
        assert not f.motes.kill(2) and not f.motes.kill(77)
        assert 2 not in f.cores and any(n == 2 and isinstance(e, MoteDown) for n, e in events)
        await wait_for(lambda: f.counters()[9].frames_tx >= 1)
        tx2 = f.counters()[2].frames_tx
        await f.wait_until(f.now() + 2.0)
        assert f.counters()[2].frames_tx == tx2  # killed: silent, counters kept
        f.motes.add(f.control.parse_node(static(2, 20.0, 12.0)))  # back again
        assert 2 in f.cores


async def test_control_requests_are_answered_never_raised() -> None:
    dep = deployment([static(1, 10.0, 10.0)], area=100.0)
    async with Fleet(dep, hello_core, FleetSettings(control=False)) as f:

        def ask(req: object) -> dict[str, object]:
            return f.control.request(json.dumps(req).encode() if req is not None else b"\xff")

        assert ask(None)["ok"] is False
        assert ask({"nope": 1})["ok"] is False
        assert ask({"op": "fly"})["error"] == "unknown op 'fly'"
        bad = ask({"op": "add", "node": {"id": 5, "kind": "tmote", "position": [500, 1]}})
        assert bad["ok"] is False and "nodes[0] (id 5)" in str(bad["error"])
        assert "outside the area" in str(bad["error"])
        assert ask({"op": "add", "node": {"id": 5, "kind": "tmote", "position": [50, 1]}})["done"]
        listed = ask({"op": "list"})
        assert set(listed["motes"]) == {"1", "5"}  # type: ignore[arg-type]
        assert ask({"op": "kill", "id": "x"})["ok"] is False
        assert ask({"op": "kill", "id": 5})["done"] is True
        assert ask({"op": "stats"})["snapshot"]["motes"] == 1  # type: ignore[index]


async def test_battery_death_switches_the_mote_off() -> None:
    # Each Hello costs about 3 V * 17.4 mA * 0.77 ms = 0.04 mJ on the air.
    dep = deployment([static(1, 10.0, 10.0, battery_mj=0.1), static(2, 15.0, 10.0)])
    downs: list[tuple[int, str]] = []
    async with Fleet(dep, hello_core, FleetSettings(speed=20.0, control=False)) as f:
        f.on_event(lambda n, e, t: downs.append((n, e.reason)) if isinstance(e, MoteDown) else None)
        await wait_for(lambda: bool(downs))
        assert downs == [(1, "battery")]
        assert not f.alive(1) and f.alive(2)
        spent = f.counters()[1].energy_mj(dep.preset, 0.0)
        assert 0.1 <= spent < 0.2
        tx = f.counters()[1].frames_tx
        await f.wait_until(f.now() + 3.0)
        assert f.counters()[1].frames_tx == tx


class Broken(HelloMote):
    def handle_timer(self, now: float) -> None:
        raise ZeroDivisionError("core bug")


async def test_a_core_bug_is_contained_counted_and_stops_only_that_mote() -> None:
    """The last guard: a core that raises is a counted fault, not a dead fleet.
    A timer handler that raises and keeps its deadline stops its own mote."""
    dep = deployment([static(1, 10.0, 10.0), static(2, 20.0, 10.0)])
    downs: list[tuple[int, str]] = []

    def make(spec: NodeSpec, d: Deployment) -> MoteCore:
        import random

        cls = Broken if spec.id == 1 else HelloMote
        return cls(spec.id, 0.1, random.Random(1))

    async with Fleet(dep, make, FleetSettings(speed=10.0, control=False)) as f:
        f.on_event(lambda n, e, t: downs.append((n, e.reason)) if isinstance(e, MoteDown) else None)
        await f.run(3.0)  # raises FleetError if anything escaped into the loop
        assert not f.failed
        assert downs == [(1, "fault")]
        assert f.medium.faults.get("handle_timer: ZeroDivisionError") == 1
        assert f.alive(2) and f.counters()[2].frames_tx > 0  # the other mote runs on


def test_default_core_factory_builds_the_node_kinds() -> None:
    from awaremw.protocol.mote import AwareMote

    dep = load("grid_small")
    make = KindsFactory()
    assert {"tmote", "mica2", "robot", "gateway"} <= make.kinds
    spec = dep.nodes[0]
    core = make(spec, dep)
    assert isinstance(core, AwareMote) and core.node_id == spec.id
    app = app_of(core)
    assert app is not None and app.node_id == spec.id and app.position(0.0) == spec.position
    hello = hello_core(spec, dep)
    assert isinstance(hello, HelloMote) and hello.node_id == spec.id


def test_settings_are_frozen_picklable_data_with_clear_errors() -> None:
    import dataclasses
    import pickle

    from awaremw.runtime.fleet.pool import WorkerParams
    from awaremw.runtime.partition import XStripe

    s = FleetSettings(connect=["tcp/127.0.0.1:7447"], speed=2.0)  # type: ignore[arg-type]
    assert s.connect == ("tcp/127.0.0.1:7447",) and s.listen == ()
    with pytest.raises(TypeError, match="not the string"):
        FleetSettings(connect="tcp/127.0.0.1:7447")  # type: ignore[arg-type]
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.speed = 3.0  # type: ignore[misc]
    with pytest.raises(ValueError, match="processes must be >= 1"):
        LauncherSettings(processes=0)
    ls = LauncherSettings(processes=2, speed=4.0, exclude_kinds=["gateway"])  # type: ignore[arg-type]
    w = ls.fleet("w1", ("tcp/127.0.0.1:9000",))
    assert (w.name, w.speed, w.connect, w.autostart, w.freeze_gc) == (
        "w1", 4.0, ("tcp/127.0.0.1:9000",), False, True,
    )  # fmt: skip
    dep = deployment([static(1, 10.0, 10.0)])
    params = WorkerParams(dep, hello_core, w, XStripe(0.0, 50.0), ls.exclude_kinds)
    back = pickle.loads(pickle.dumps(params))
    assert back.settings == w and back.name == "w1" and back.exclude_kinds == {"gateway"}
