"""A fleet survives its workers: ``awaremw fleet --processes 2`` with one worker
killed with SIGKILL (real processes, a real gateway mote and service on Zenoh).

The gateway runs here (its mote in a Fleet of its own, as ``awaremw gateway``
runs it); group type 1 holds the motes of the west stripe and type 2 those of
the east one, each with a channel, so that records name leaders of both
stripes. The pure parts (restart budget, frame-counter margin) are checked
without processes.
"""

from __future__ import annotations

import asyncio
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Awaitable, Callable
from typing import Any

import pytest

from awaremw.cli.fleet import control_query
from awaremw.gateway.service import GatewaySettings, attach_to_fleet
from awaremw.nodes import KindsFactory, kind_names
from awaremw.protocol.frames import DataRecord
from awaremw.radio.security import RadioSecurity
from awaremw.runtime.deployment import load
from awaremw.runtime.fleet import Fleet, FleetLauncher, FleetSettings, LauncherSettings
from awaremw.runtime.fleet.clock import ClockSync
from awaremw.runtime.fleet.motes import hello_core
from awaremw.runtime.fleet.pool import MAX_FRAMES_PER_S, RestartBudget, resume_counters
from awaremw.runtime.partition import stripes
from awaremw.runtime.zenoh_session import free_tcp_endpoint
from awaremw.world.clock import EmulatedClock

AWAREMW = [sys.executable, "-m", "awaremw"]


def test_restart_budget_counts_per_worker_within_its_window() -> None:
    b = RestartBudget(2, 60.0)
    assert b.allow(1, 0.0) and b.allow(1, 10.0)
    assert not b.allow(1, 20.0)  # a third death within 60 s: give up
    assert b.allow(0, 20.0)  # another worker has its own budget
    assert b.allow(1, 61.0)  # the first restart left the window
    assert not RestartBudget(0, 60.0).enabled


def test_resumed_frame_counters_skip_every_frame_a_mote_could_have_sent() -> None:
    got = resume_counters({3: 100, 4: 0}, since_s=2.5)
    assert got == {3: 100 + int(3.5 * MAX_FRAMES_PER_S)}  # a mote that never sent: from 0
    assert resume_counters({3: 100}, since_s=-1.0) == {3: 100 + MAX_FRAMES_PER_S}


async def _ctl(ep: str, op: str) -> dict[str, dict[str, Any]]:
    """Each fleet process's reply by name (fleet-ctl's query, off the loop)."""
    try:
        replies = await asyncio.to_thread(control_query, [ep], "aware", {"op": op}, 2.0)
    except Exception:  # the router is not up yet
        return {}
    return {str(d["fleet"]): d for d in replies}


async def _until(cond: Callable[[], Awaitable[bool]], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not await cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"not within {timeout} s: {what}")
        await asyncio.sleep(0.2)


@pytest.mark.zenoh
@pytest.mark.slow
async def test_kill_9_of_a_worker_restarts_it_and_records_flow_from_both_stripes() -> None:
    dep = load("grid_small", kind_names())
    west, _ = stripes(dep, 2)
    stripe_of = {n.id: (0 if west(n) else 1) for n in dep.nodes}
    ep = free_tcp_endpoint()
    proc = subprocess.Popen(
        [*AWAREMW, "fleet", "grid_small", "--processes", "2", "--without-kind", "gateway",
         "--listen", ep, "--progress", "1"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    got: list[tuple[float, int]] = []  # (emulated t, stripe of the leader)
    listed: dict[str, dict[str, Any]] = {}
    try:

        async def answered() -> bool:
            nonlocal listed
            listed = await _ctl(ep, "list")
            return len(listed) == 2

        await _until(answered, 60, "both workers answer fleet-ctl")
        start_wall = time.time() - max(float(d["t"]) for d in listed.values())
        fleet = Fleet(
            dep,
            KindsFactory(),
            FleetSettings(name="gateway", connect=(ep,), start_wall=start_wall, control=False),
            node_filter=lambda s: s.kind == "gateway",
        )
        async with fleet:
            svc = attach_to_fleet(fleet, settings=GatewaySettings(hbn=False))

            def on_event(node: int, ev: object, now: float) -> None:
                p = getattr(ev, "payload", None)
                if isinstance(p, DataRecord):
                    got.append((now, stripe_of[p.leader]))

            fleet.on_event(on_event)
            async with svc:
                cut = west.hi  # the border of the stripes; no group straddles it
                defs = [
                    ("def/group/1", {"conditions": [{"attr": "x", "op": "<", "value": cut - 6}]}),
                    ("def/group/2", {"conditions": [{"attr": "x", "op": ">", "value": cut + 6}]}),
                    ("def/channel/1", {"attr": "temperature", "group_type": 1, "group_id": "*",
                                       "period_s": 2.0, "agg": "avg"}),
                    ("def/channel/2", {"attr": "temperature", "group_type": 2, "group_id": "*",
                                       "period_s": 2.0, "agg": "avg"}),
                ]  # fmt: skip
                for out in svc.define_initial((rel, json.dumps(d).encode()) for rel, d in defs):
                    assert out.accepted, out.error

                def both_since(t: float) -> Callable[[], Awaitable[bool]]:
                    async def check() -> bool:
                        return {s for when, s in got if when > t} == {0, 1}

                    return check

                await _until(both_since(0.0), 90, "records from both stripes")
                before = {k: d["snapshot"] for k, d in (await _ctl(ep, "stats")).items()}
                assert before["w1"]["restarts"] == 0
                os.kill(int(before["w1"]["pid"]), signal.SIGKILL)
                killed_at, wall_killed = fleet.now(), time.monotonic()

                async def restarted() -> bool:
                    w1 = (await _ctl(ep, "stats")).get("w1")
                    return w1 is not None and w1["snapshot"]["restarts"] == 1

                await _until(restarted, 30, "fleet-ctl stats shows w1 restarted")
                await _until(both_since(killed_at + 1.0), 40, "records from both stripes again")
                took = time.monotonic() - wall_killed
                assert proc.poll() is None, "the fleet exited"
                after = {k: d["snapshot"] for k, d in (await _ctl(ep, "stats")).items()}
                assert after["w1"]["pid"] != before["w1"]["pid"]
                assert after["w0"]["restarts"] == 0 and after["w0"]["pid"] == before["w0"]["pid"]
                # The figures go on from the dead incarnation's last report.
                assert after["w1"]["frames_tx"] >= before["w1"]["frames_tx"]
                # Read back: the restarted motes hold the definitions again.
                items = await asyncio.to_thread(
                    subprocess.run,
                    [*AWAREMW, "fleet-ctl", "--connect", ep, "--timeout", "2", "items"],
                    capture_output=True, text=True, timeout=60, check=False,
                )  # fmt: skip
                assert items.returncode == 0, items.stderr
                held = {d["fleet"]: d["items"] for d in map(json.loads, items.stdout.splitlines())}
                assert set(held) == {"w0", "w1"}
                assert all("channel/2" in motes for motes in held["w1"].values())
                print(f"records from both stripes {took:.1f} s after the kill")
                assert took <= 30
    finally:
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    assert "exited unexpectedly (exit code -9); starting it again (restart 1)" in err


# --------------------------------------------------------------------------- time origin


def test_clock_sync_moves_only_on_agreeing_evidence_and_only_forward() -> None:
    wall = [100.0]
    clock = EmulatedClock(2.0, start_wall=time.time())
    jumps: list[float] = []
    sync = ClockSync("t", clock, jumps.append, wall=lambda: wall[0])
    sync.on_early(80.0)
    assert not jumps  # not active before the fleet started
    sync.activate()
    origin = clock.start_wall
    sync.on_early(80.0)  # one stray frame...
    sync.on_early(-5.0)  # (a late frame is no evidence)
    wall[0] += 10  # ...and the evidence goes stale
    sync.on_early(80.0)
    sync.on_early(30.0)  # peers that disagree
    assert not jumps and clock.start_wall == origin
    # Envelopes that all carry one fixed time (a fuzzer's): the origin they imply
    # drifts with the wall clock, so they never agree for MIN_SPAN_S.
    wall[0] += 10
    for k in range(12):
        wall[0] += 0.2
        sync.on_early(500.0 - 2.0 * 0.2 * k)  # the same envelope time, 0.2 s later each
    assert not jumps and clock.start_wall == origin
    # A running peer: the same lead, frame after frame, over more than a second.
    wall[0] += 10
    for _ in range(3):
        sync.on_early(80.0)
        assert not jumps  # agreeing, but not yet for a second
    for _ in range(3):
        wall[0] += 0.4
        sync.on_early(80.0)
    assert jumps == [pytest.approx(80.0)] and sync.jumps == 1
    assert clock.start_wall == pytest.approx(origin - 40.0)  # 80 emulated s at x2
    assert clock.now() == pytest.approx(80.0, abs=0.5)


@pytest.mark.zenoh
@pytest.mark.parametrize("late", ["sensors", "gateway"])
async def test_a_process_started_under_running_peers_joins_their_time(late: str) -> None:
    """A fleet (or gateway) started with its own time origin under peers that have
    run for 40 s hears them within seconds, not after 40 s."""
    dep = load("grid_small", kind_names())
    ep = free_tcp_endpoint()
    t_start = time.time()
    older, newer = t_start - 40.0, t_start
    sensors = Fleet(
        dep,
        KindsFactory(),
        FleetSettings(
            name="sensors", listen=(ep,), start_wall=newer if late == "sensors" else older
        ),
        node_filter=lambda s: s.kind != "gateway",
    )
    async with sensors:
        gw = Fleet(
            dep,
            KindsFactory(),
            FleetSettings(
                name="gateway",
                connect=(ep,),
                start_wall=newer if late == "gateway" else older,
                control=False,
            ),
            node_filter=lambda s: s.kind == "gateway",
        )
        async with gw:
            svc = attach_to_fleet(gw, settings=GatewaySettings(hbn=False))
            records: list[float] = []

            def on_event(node: int, ev: object, now: float) -> None:
                if isinstance(getattr(ev, "payload", None), DataRecord):
                    records.append(time.monotonic())

            gw.on_event(on_event)
            async with svc:
                defs = [
                    ("def/group/1", {"conditions": [{"attr": "x", "op": ">", "value": 3}]}),
                    ("def/channel/1", {"attr": "temperature", "group_type": 1,
                                       "group_id": "*", "period_s": 2.0, "agg": "avg"}),
                ]  # fmt: skip
                w0 = time.monotonic()
                for out in svc.define_initial((rel, json.dumps(d).encode()) for rel, d in defs):
                    assert out.accepted

                async def any_record() -> bool:
                    return bool(records)

                await _until(any_record, 25, "a record at the gateway")
                took = records[0] - w0
                print(f"{late} started 40 s late: first record after {took:.1f} s")
            moved = sensors if late == "sensors" else gw
            assert moved.clock_sync.jumps == 1
            assert abs(sensors.clock.start_wall - gw.clock.start_wall) < 0.5
            assert took < 25


@pytest.mark.zenoh
@pytest.mark.slow
async def test_a_restarted_worker_on_a_secured_radio_goes_on_counting_its_frames() -> None:
    """The restarted worker's motes start their frame counters above what their
    neighbours last accepted: the other worker refuses none of their frames as
    a replay, and keeps hearing them."""
    dep = load("grid_small", kind_names())
    security, _ = RadioSecurity.throwaway()
    settings = LauncherSettings(
        processes=2, speed=4.0, progress_s=0.5, exclude_kinds=frozenset({"gateway"}),
        security=security,
    )  # fmt: skip
    async with FleetLauncher(dep, hello_core, settings) as launcher:
        run = asyncio.create_task(launcher.run(None))
        ep = launcher.endpoint

        async def stats() -> dict[str, dict[str, Any]]:
            return {k: d["snapshot"] for k, d in (await _ctl(ep, "stats")).items()}

        async def counters_high() -> bool:
            # Old counters well above what a restart from 0 would reach in the
            # window measured below: without the resume its frames would be replays.
            _, reported = launcher.frame_counters.get(1, (0.0, {}))
            return bool(reported) and min(reported.values()) >= 40

        await _until(counters_high, 40, "w1 reported frame counters of 40 and more")
        launcher.pool.procs[1].kill()

        async def restarted() -> bool:
            s = await stats()
            return s.get("w1", {}).get("restarts") == 1

        await _until(restarted, 30, "w1 restarted")
        # While the new worker's Zenoh links settle, a frame may arrive twice (a
        # true replay, refused); after that, nothing of the restarted motes is.
        await asyncio.sleep(2.0)
        first = (await stats())["w0"]
        await asyncio.sleep(4.0)  # the restarted motes beacon every second
        later = (await stats())["w0"]
        assert not run.done()
        run.cancel()
    replays = [(s["refused"] or {}).get("replay", 0) for s in (first, later)]
    print("replays refused by w0 after the restart:", replays)
    assert replays[1] == replays[0], replays
    assert later["frames_rx"] > first["frames_rx"]
    assert launcher.restarts == {1: 1}
