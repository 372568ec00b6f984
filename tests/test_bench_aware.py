"""``awaremw bench virtual --workload aware``: the whole middleware on the virtual clock."""

from __future__ import annotations

import asyncio
import itertools
import math
import pstats
from pathlib import Path

import pytest
from traces import aware_trace

from awaremw import compiled_modules
from awaremw.bench import aware_load
from awaremw.bench.virtual import run
from awaremw.nodes import KindsFactory, world_of
from awaremw.protocol.mote import AwareMote

KEYS = {
    "motes",
    "sim_seconds",
    "wall_seconds",
    "cpu_seconds",
    "speedup",
    "frames_tx",
    "frames_by_kind",
    "deliveries",
    "mean_neighbours",
    "dropped_loss",
    "dropped_distance",
    "collisions",
    "cca_busy",
    "mac_drops",
    "mac",
    "collisions_model",
    "radio_settings",
    "preset",
    "seed",
    "spacing_m",
    "workload",
    "build",
    "compiled_modules",
    "records_produced",
    "records_delivered",
    "record_delivery",
    "first_record_s",
    "leaders",
    "records_untracked",
    "channel_period_s",
    "cpu_per_mote_s_us",
    "rss_per_mote_kb",
    "sinks",
    "objects",
    "objects_tracked",
    "records_per_object",
    "ids_per_object",
    "records_unattributed",
}
TIMING = ("wall_seconds", "cpu_seconds", "speedup", "cpu_per_mote_s_us", "rss_per_mote_kb")


def test_aware_workload_tracks_and_delivers(tmp_path: Path) -> None:
    prof = tmp_path / "run.prof"
    out = run(100, 30.0, 3, workload="aware", profile=str(prof))
    assert set(out) == KEYS
    assert out["workload"] == "aware" and out["motes"] == 100 and out["sim_seconds"] == 30.0
    assert out["cpu_seconds"] > 0 and out["wall_seconds"] > 0
    # The group formed on the fire and its leaders produced records every epoch.
    assert out["records_produced"] >= 5 and out["leaders"] >= 1
    assert out["record_delivery"] > 0.9
    assert out["records_delivered"] <= out["records_produced"]
    assert out["records_untracked"] == 0
    assert out["mac"] == "csma" and out["collisions_model"] == "sinr" and out["collisions"] > 0
    assert out["radio_settings"] == "noise white"  # the textbook radio unless asked
    # The profile holds the protocol's own functions (the run went through them);
    # compiled functions are invisible to it, their time charged to the caller.
    stats = pstats.Stats(str(prof))
    funcs = {f"{Path(file).name}:{name}" for file, _, name in stats.stats}  # type: ignore[attr-defined]
    compiled = compiled_modules()
    assert out["build"] == ("mypyc" if compiled else "python")
    assert out["compiled_modules"] == len(compiled)
    if "awaremw.protocol.mote" not in compiled:
        assert "mote.py:receive" in funcs and "ctp_forwarding.py:_deliver" in funcs
    assert "aware_load.py:on_event" in funcs  # the tally of the events (never compiled)
    # Same seed, same counters.
    again = run(100, 30.0, 3, workload="aware")
    assert {k: v for k, v in again.items() if k not in TIMING} == {
        k: v for k, v in out.items() if k not in TIMING
    }


def test_aware_cores_come_from_the_fleet_factory() -> None:
    load = aware_load.build(9, 1, 10.0)
    d = load.deployment
    ref = KindsFactory()
    for spec in d.nodes:
        core = load.net.cores[spec.id]
        assert isinstance(core, AwareMote)
        assert core.ctx.config == ref(spec, d).ctx.config  # type: ignore[attr-defined]
    (sink,) = aware_load.sinks_of(d)
    assert load.net.cores[sink].collection.is_root  # type: ignore[attr-defined]


def test_unknown_workload_and_tiny_fleet_are_refused() -> None:
    with pytest.raises(ValueError, match="unknown workload 'x'"):
        run(4, 1.0, 1, workload="x")
    with pytest.raises(ValueError, match="at least 2 motes"):
        aware_load.deployment(1, 1, 1.0)


def test_scale_aware_workload_over_zenoh() -> None:
    """The same load in a real-time fleet (one process, real Zenoh), at 5x speed.
    40 s gives 11 to 13 records here (8 on the virtual clock in 30 s; in real time
    the timers' jitter may split the first group and merge it back, costing epochs),
    so the bound of 5 is the middleware failing, not a busy machine."""
    from awaremw.bench.scale import run_once

    out = asyncio.run(run_once(64, 40.0, speed=5.0, seed=2, workload="aware"))
    assert out["workload"] == "aware" and out["motes"] == 64
    assert out["delivery_ratio"] is None and out["frames_expected"] is None
    assert out["records_produced"] >= 5 and out["record_delivery"] > 0.9
    assert out["timer_samples"] > 0 and out["frames_rx"] > out["frames_tx"]


def test_scale_aware_over_two_worker_processes() -> None:
    """Full AwareMotes split over two worker processes (FleetLauncher, real Zenoh
    through an embedded router): records produced in either process and
    delivered at the gateway's mote (in worker 0) are counted across them."""
    from awaremw.bench.scale import run_once

    out = asyncio.run(run_once(60, 40.0, processes=2, speed=5.0, seed=2, workload="aware"))
    assert out["workload"] == "aware" and out["motes"] == 60 and out["processes"] == 2
    assert len(out["cpu_per_process"]) == 2 and out["envelopes_rx"] > 0  # frames crossed
    assert out["records_produced"] >= 5 and out["record_delivery"] >= 0.9
    assert out["records_delivered"] <= out["records_produced"]
    assert out["timer_samples"] > 0 and out["frames_rx"] > out["frames_tx"]
    for key in ("timer_lag_p50_ms", "timer_lag_p99_ms", "leaders", "meets_target"):
        assert key in out


def test_tallies_merge_across_processes() -> None:
    """A record produced in one worker and delivered in another counts once;
    its production time is the earliest seen."""
    from awaremw.bench.aware_load import RecordTally

    a, b = RecordTally(), RecordTally()
    k1, k2, k3 = (1, 1, 7, 3), (1, 1, 7, 4), (1, 1, 9, 4)
    a.produced = {k1: (6.0, 5), k2: (8.0, 5)}
    a.leaders = {5}
    b.produced = {k2: (7.5, 31), k3: (40.0, 31)}
    b.delivered = {k1, k2}
    b.leaders = {31}
    b.untracked = 2
    merged = RecordTally().merge([a, b])
    assert merged.produced == {k1: (6.0, 5), k2: (7.5, 31), k3: (40.0, 31)}
    assert merged.delivered == {k1, k2} and merged.leaders == {5, 31}
    assert merged.untracked == 2
    res = merged.results(30.0)  # k3 is within GRACE_S of the end: not counted
    assert res["records_produced"] == 2 and res["record_delivery"] == 1.0


def test_tally_is_bounded(monkeypatch: pytest.MonkeyPatch) -> None:
    from awaremw.protocol.events import RecordProduced
    from awaremw.protocol.frames import DataRecord

    monkeypatch.setattr(aware_load, "MAX_TRACKED", 2)
    tally = aware_load.RecordTally()
    for epoch in range(5):
        rec = DataRecord(1, 1, 7, epoch, 0, 20.0, 3, 5)
        tally.on_event(5, RecordProduced(rec, float(epoch)), float(epoch))
    out = tally.results(100.0)
    assert out["records_produced"] == 2 and out["records_untracked"] == 3
    assert out["records_delivered"] == 0 and out["record_delivery"] == 0.0


def _trace(motes: int, duration: float) -> list[str]:
    return aware_trace(motes, 1, duration)


def test_same_seed_same_events_and_records() -> None:
    first = _trace(100, 30.0)
    assert any("RecordProduced" in line for line in first)
    assert _trace(100, 30.0) == first


def test_scale_collisions_switch_over_zenoh() -> None:
    """`bench scale --collisions none|sinr`: the Zenoh medium destroys overlapping
    frames only with the SINR model; every kept reception is accounted for either way."""
    from awaremw.bench.scale import run_once

    on = asyncio.run(run_once(120, 6.0, speed=2.0, seed=3))
    off = asyncio.run(run_once(120, 6.0, speed=2.0, seed=3, collisions="none"))
    assert (on["mac"], on["collisions_model"]) == ("csma", "sinr")
    assert off["collisions_model"] == "none" and off["collisions"] == 0
    assert on["collisions"] > 0
    assert on["delivery_ratio"] >= 0.99 and off["delivery_ratio"] >= 0.99


def test_scale_aware_run_without_records_says_so() -> None:
    """A run whose counted window (up to ``duration - GRACE_S``) closes before the
    first record (here 12.5 s: the window ends at 2.5 s, the first record comes
    at about 5.9 s) has no delivery to measure: ``record_delivery`` is None, not
    0.0, and the run fails for that reason, not as a loss (issue 14's 4,000-mote
    trial). The lag target is lifted so that a loaded machine cannot mask it."""
    from awaremw.bench.scale import run_once

    out = asyncio.run(run_once(16, 12.5, speed=5.0, seed=2, workload="aware", max_p99_ms=1e9))
    assert out["records_produced"] == 0 and out["records_delivered"] == 0
    assert out["record_delivery"] is None
    assert out["reason"] == "no_records" and out["meets_target"] is False
    # Records did come, after the window: produced late, not lost.
    assert out["first_record_s"] is not None and out["first_record_s"] > 12.5 - aware_load.GRACE_S


def test_scale_aware_refuses_a_duration_with_no_window() -> None:
    from awaremw.bench.scale import run_once

    with pytest.raises(ValueError, match="--duration above 11 s"):
        asyncio.run(run_once(16, 11.0, workload="aware"))


def test_tally_without_records_has_no_ratio() -> None:
    res = aware_load.RecordTally().results(30.0)
    assert res["records_produced"] == 0 and res["record_delivery"] is None
    assert res["first_record_s"] is None


def test_failure_reason_order() -> None:
    from awaremw.bench.scale import failure_reason

    none = {"records_produced": 0}
    some = {"records_produced": 4}
    assert failure_reason(10.0, 50.0, True, some) is None
    assert failure_reason(10.0, 50.0, True, {}) is None
    # Overload first: a machine that did not keep real time explains the rest.
    assert failure_reason(314.0, 50.0, False, none) == "overload"
    assert failure_reason(math.nan, 50.0, True, some) == "overload"
    assert failure_reason(10.0, 50.0, False, none) == "no_records"
    assert failure_reason(10.0, 50.0, False, some) == "records_lost"
    assert failure_reason(10.0, 50.0, False, {}) == "frames_lost"


def test_search_fails_a_trial_without_records_and_says_why(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """``--search``: a trial with no record produced is a failure, its reason in
    the list of trials; the answer is the largest trial that met the target."""
    import argparse

    from awaremw.bench import scale

    async def fake(n: int, **kw: object) -> dict[str, object]:
        ok = n <= 1000
        return {
            "motes": n,
            "timer_lag_p99_ms": 20.0,
            "delivery_ratio": None,
            "records_produced": 6 if ok else 0,
            "record_delivery": 1.0 if ok else None,
            "first_record_s": 6.0 if ok else None,
            "meets_target": ok,
            "reason": None if ok else "no_records",
        }

    monkeypatch.setattr(scale, "run_once", fake)
    parser = argparse.ArgumentParser()
    scale.add_arguments(parser)
    args = parser.parse_args(["--workload", "aware", "--motes", "500", "--search"])
    out = asyncio.run(scale.search(args))
    assert out["motes_max"] == 1000 and out["meets_target"] is True
    failed = [t for t in out["search"] if not t["meets_target"]]
    assert failed and all(t["reason"] == "no_records" for t in failed)
    assert all(t["record_delivery"] is None for t in failed)


# --------------------------------------------------------------- the field at scale


@pytest.mark.parametrize(("motes", "regions"), [(100, 1), (1000, 1), (4000, 2), (10000, 3)])
def test_one_sink_and_one_fire_per_region_of_about_1000_motes(motes: int, regions: int) -> None:
    d = aware_load.deployment(motes, 1, 120.0)
    sinks = aware_load.sinks_of(d)
    assert len(sinks) == regions**2
    fires = world_of(d).fires
    assert len(fires) == regions**2
    grid = aware_load.Field(motes)
    w, h = grid.size
    for n, (sink, fire) in enumerate(zip(sinks, sorted(fires, key=_region_order), strict=True)):
        # Every sink stands within a grid step of its region's centre, and its
        # region's fire loops around that centre at walking pace, inside the region.
        a, b = n % regions, n // regions
        cx, cy = w * (a + 0.5) / regions, h * (b + 0.5) / regions
        sx, sy = grid.position(sink)
        assert math.hypot(sx - cx, sy - cy) <= aware_load.SPACING_M
        keys = fire.keyframes
        assert keys[-1].t >= 120.0
        for k0, k1 in itertools.pairwise(keys):
            speed = math.hypot(k1.x - k0.x, k1.y - k0.y) / (k1.t - k0.t)
            assert speed == pytest.approx(aware_load.OBJECT_SPEED_MPS)
        for k in keys:
            assert w * a / regions < k.x < w * (a + 1) / regions
            assert h * b / regions < k.y < h * (b + 1) / regions


def _region_order(fire: object) -> tuple[float, float]:
    k = fire.keyframes[0]  # type: ignore[attr-defined]
    return (k.y, k.x)


def test_the_world_does_not_speed_up_with_the_run() -> None:
    short = world_of(aware_load.deployment(1000, 1, 30.0)).fires[0]
    long = world_of(aware_load.deployment(1000, 1, 600.0)).fires[0]
    for t in (0.0, 10.0, 29.0):
        assert short.state(t) == long.state(t)


def test_sinks_on_request_and_out_of_range() -> None:
    d = aware_load.deployment(400, 1, 30.0, sinks=5)
    sinks = aware_load.sinks_of(d)
    assert len(sinks) == 5 == len(set(sinks))
    with pytest.raises(ValueError, match="--sinks 0: needs 1 to 200 sinks for 400 motes"):
        aware_load.deployment(400, 1, 30.0, sinks=0)
    with pytest.raises(ValueError, match="--sinks 201"):
        aware_load.deployment(400, 1, 30.0, sinks=201)


def test_records_reach_the_nearest_of_several_sinks() -> None:
    """Two sinks: records are delivered at either, each counted once, and the
    tracking score gives them to the one fire."""
    out = run(400, 40.0, 2, workload="aware", sinks=2)
    assert out["sinks"] == 2 and out["objects"] == 1
    assert out["records_produced"] >= 5 and out["record_delivery"] >= 0.95
    assert out["objects_tracked"] == 1 and out["records_per_object"][0] == out["records_delivered"]
    assert out["records_unattributed"] == 0


def test_score_objects_attributes_records_to_the_fire_near_their_leader() -> None:
    d = aware_load.deployment(1000, 1, 60.0)
    fire = world_of(d).fires[0]
    grid = aware_load.Field(1000)
    at = fire.state(40.0)
    assert at is not None
    near = grid.nearest(at.x, at.y)
    far = grid.nearest(1.0, 1.0)
    tally = aware_load.RecordTally()
    tally.produced = {
        (1, 1, 9, 1): (20.0, near),  # produced early: counted, not "late"
        (1, 1, 9, 2): (40.0, near),  # in the last quarter of the window (37.5..50)
        (1, 1, 4, 3): (40.0, far),  # its leader is near no fire
        (1, 1, 9, 4): (55.0, near),  # within GRACE_S of the end: not counted
    }
    tally.delivered = {(1, 1, 9, 2), (1, 1, 4, 3), (1, 1, 9, 4)}
    score = aware_load.score_objects(tally, d, 60.0)
    assert score == {
        "objects": 1,
        "objects_tracked": 1,
        "records_per_object": [1],
        "ids_per_object": [1],
        "records_unattributed": 1,
    }
    tally.delivered = {(1, 1, 9, 1)}  # only the early one arrived: no longer tracked
    assert aware_load.score_objects(tally, d, 60.0)["objects_tracked"] == 0


def test_more_motes_than_short_addresses_is_one_line() -> None:
    from awaremw.bench.virtual import check_motes, parse_sizes

    check_motes(65534)
    with pytest.raises(ValueError, match=r"at most 65534 motes \(16-bit short addresses"):
        check_motes(65535)
    assert parse_sizes("10000, 1000,1000") == [1000, 10000]
    with pytest.raises(ValueError, match="comma-separated"):
        parse_sizes("1k")
    with pytest.raises(ValueError, match="at most 65534"):
        parse_sizes("1000,70000")


def test_a_network_beyond_the_address_space_is_refused_in_one_line() -> None:
    import subprocess
    import sys

    for bench in ("virtual", "scale"):
        p = subprocess.run(
            [sys.executable, "-m", "awaremw", "bench", bench, "--workload", "aware",
             "--motes", "70000", "--duration", "20"],
            capture_output=True, text=True, timeout=120, check=False,
        )  # fmt: skip
        assert p.returncode == 2 and p.stdout == ""
        assert p.stderr == (
            f"awaremw bench {bench}: --motes 70000: one network holds at most 65534 motes "
            "(16-bit short addresses 0..65533; 0xFFFE and 0xFFFF are reserved by IEEE 802.15.4)\n"
        )
