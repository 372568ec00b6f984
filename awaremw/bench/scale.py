"""``awaremw bench scale``: how many motes the real-time Zenoh emulation sustains.

Motes on a square grid (CC2420 preset: 12 m spacing, about ten neighbours
that hear each beacon), each running :class:`~awaremw.protocol.hello.HelloMote`
beaconing once per second, over real Zenoh sessions: in this process
(``--processes 1``) or spread over worker processes in x stripes joined by an
embedded router (``--processes N``), the same code either way
(:func:`~awaremw.runtime.fleet.open_fleet`). After ``--duration`` emulated seconds
every radio is frozen, frames in flight land for ``--grace`` wall seconds, and
the counters are gathered.

``--workload aware``: the whole middleware instead of Hello beacons, cores
from the fleet's core factory, one fire per region of about 1,000 motes
looping at 1 m/s, each tracked by a group, an AVG channel every 2 s,
collection to the nearest of the sinks (gateway motes on a lattice,
``--sinks N``), Drip (see :mod:`awaremw.bench.aware_load`); the definitions are
injected at every sink at 1 s. With ``--processes N`` the AwareMotes are split over
worker processes exactly as ``awaremw fleet --processes N`` runs them
(``FleetLauncher``, x stripes, one embedded router); each worker tallies the
records of its motes (:class:`~awaremw.bench.aware_load.AwarePlugin`) and the
tallies are merged, so a record produced in one process and delivered at the
sink in another counts; ``record_delivery`` (records that
reached a sink over records the leaders produced) replaces the
radio's ``delivery_ratio`` in the target (``frames_expected`` and
``delivery_ratio`` are None: the loss recount knows only Hello frames).
``--profile FILE``: cProfile of the run (this process only).

Target (``--search``): timer lag p99 below ``--max-p99-ms`` (50) and delivery
(``record_delivery`` with ``--workload aware``) at least ``--min-delivery``
(0.99); with ``--workload aware`` at least one record must have been produced
in the counted window (else ``record_delivery`` is None and the run fails
with ``reason`` ``"no_records"``). ``--search`` doubles ``--motes`` while the
target holds, then bisects between the last pass and the first failure.

JSON keys (one object; with ``--search`` the best passing run's keys plus
``search`` = the list of trials):

* ``motes``, ``processes``, ``duration_s``, ``speed``, ``handler``, ``layout``,
  ``preset``, ``seed``, ``spacing_m``;
* ``timer_lag_p50_ms``, ``timer_lag_p99_ms``, ``timer_lag_max_ms``: how late
  motes' timers ran (wall ms after their deadline), after ``--warmup``
  emulated seconds; ``timer_lag_p99_per_process_ms``: the p99 of each process;
* ``frames_tx``, ``frames_rx``; ``frames_expected``: receptions the loss model
  keeps among in-range receivers for the frames actually sent (recomputed
  from the seeded model, packet by packet); ``collisions`` (receptions the
  loss model kept that overlapping frames destroyed: the deployment's
  ``collisions = "sinr"``, docs/radio.md; ``--collisions none`` and ``--mac
  aloha`` switch them off, reported as ``mac`` and ``collisions_model``); ``delivery_ratio`` =
  ``(frames_rx + collisions) / frames_expected`` (below 1: frames lost by
  the emulation itself -- late subscriptions, dropped Zenoh samples);
  ``late`` (frames whose envelope came after their end + the guard, all
  processes: decided without waiting, maybe without an interferer);
  ``rx_per_tx`` (mean receivers per beacon);
* ``envelopes_rx`` (frames that crossed processes through Zenoh),
  ``malformed``; ``cpu_s`` (all processes), ``cpu_per_process``,
  ``wall_s``; ``meets_target``; ``reason``: why the target is missed (None
  when met), the first of ``"overload"`` (lag p99 at or above the target: the
  machine did not keep real time), ``"no_records"`` (aware: no record produced
  before ``duration - 10 s``), ``"records_lost"`` / ``"frames_lost"``
  (delivery below the target); ``workload``; with ``--workload aware``
  also ``records_produced``, ``records_delivered``, ``record_delivery`` (None
  when no record was produced), ``first_record_s`` (emulated time of the
  first record), ``leaders``, ``leaders_per_process``,
  ``records_untracked``, ``channel_period_s``, ``sinks``, ``objects``,
  ``objects_tracked``, ``records_per_object``, ``ids_per_object``,
  ``records_unattributed`` (as ``bench virtual``). The search's ``search`` list
  gives each trial's ``reason``.
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import gc
import math
import time
from typing import Any

from awaremw.bench import aware_load
from awaremw.bench.medium import medium_of
from awaremw.bench.profiling import build_facts, profiled
from awaremw.bench.virtual import WORKLOADS, add_workload_arguments, check_motes
from awaremw.nodes import KindsFactory
from awaremw.radio.counters import MoteCounters
from awaremw.radio.model import CC2420, RadioModel, cell_of, packet_key, preset
from awaremw.runtime.deployment import Deployment, NodeSpec
from awaremw.runtime.driver import percentile
from awaremw.runtime.fleet import LauncherSettings, open_fleet
from awaremw.runtime.fleet.motes import hello_core
from awaremw.runtime.fleet.stats import plugin_results

SPACING_M = 12.0  # CC2420 at 0 dBm: about ten neighbours hear each beacon


def grid_deployment(
    motes: int, seed: int = 1, radio: str = "cc2420", spacing: float | None = None
) -> Deployment:
    """``motes`` static motes on a square grid, spaced for about ten neighbours."""
    p = preset(radio)
    if spacing is None:
        # Scale the CC2420 spacing by the preset's range (same neighbour count).
        spacing = (
            SPACING_M * RadioModel(p, seed).max_range_m() / RadioModel(CC2420, 0).max_range_m()
        )
    cols = max(1, math.ceil(math.sqrt(motes)))
    rows = max(1, math.ceil(motes / cols))
    nodes = tuple(
        NodeSpec(
            id=i,
            kind="hello",
            position=(spacing * (0.5 + i % cols), spacing * (0.5 + i // cols)),
        )
        for i in range(motes)
    )
    return Deployment(
        name=f"scale-{motes}",
        area=(spacing * cols, spacing * rows),
        radio=radio,
        seed=seed,
        tx_power_dbm=p.tx_power_dbm,
        nodes=nodes,
    )


def expected_receptions(dep: Deployment, frames_tx: dict[int, int]) -> int:
    """Receptions the loss model keeps for every broadcast actually sent.

    For sender ``s`` that sent ``n`` frames (link sequence numbers 0..n-1, all
    broadcasts), every mote within one cell and within range is a receiver;
    each packet is decided by the same seeded model the media use.
    """
    model = dep.radio_model()
    size = model.cell_size_m
    grid: dict[tuple[int, int], list[NodeSpec]] = {}
    for s in dep.nodes:
        grid.setdefault(cell_of(*s.position, size), []).append(s)
    overhead = dep.preset.phy_overhead_bytes
    total = 0
    for s in dep.nodes:
        n = frames_tx.get(s.id, 0)
        if not n:
            continue
        txp = dep.tx_power_of(s)
        rng = model.max_range_m(txp)
        bits = [8 * (_hello_len(s.id, seq, dep.preset.mtu) + overhead) for seq in range(n)]
        cx, cy = cell_of(*s.position, size)
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                for r in grid.get((cx + dx, cy + dy), ()):
                    if r.id == s.id:
                        continue
                    d = math.dist(r.position, s.position)
                    if d > rng:
                        continue
                    mean = model.mean_rssi(s.id, r.id, d, txp)
                    if model.never_delivers(mean):
                        continue
                    lh = model.fading_link_hash(s.id, r.id)
                    for seq in range(n):
                        ok, _ = model.decide(lh, mean, bits[seq], packet_key(seq & 0xFFFF, 0))
                        total += ok
    return total


def _hello_len(src: int, seq: int, mtu: int) -> int:
    # The HelloMote's n-th beacon carries seq n (msgpack: its length grows with
    # seq), and it is also the n-th frame of its radio (link seq n).
    from awaremw.protocol.frames import BROADCAST, Hello, encode

    return len(encode(Hello(src, BROADCAST, seq & 0xFFFF), mtu))


async def run_once(
    motes: int,
    duration: float,
    *,
    processes: int = 1,
    speed: float = 1.0,
    seed: int = 1,
    radio: str = "cc2420",
    handler: str = "channel",
    layout: str = "stripes",
    warmup: float = 2.0,
    grace: float = 1.0,
    max_p99_ms: float = 50.0,
    min_delivery: float = 0.99,
    workload: str = "hello",
    profile: str | None = None,
    mac: str = "csma",
    collisions: str = "sinr",
    sinks: int | None = None,
) -> dict[str, Any]:
    """One measured run (see the module docstring for the keys)."""
    check_motes(motes)
    if workload not in WORKLOADS:
        raise ValueError(f"unknown workload {workload!r}; known: {', '.join(WORKLOADS)}")
    aware = workload == "aware"
    if aware and radio != "cc2420":
        raise ValueError("--workload aware uses the cc2420 preset")
    shortest = aware_load.GRACE_S + aware_load.DEFINE_AT_S
    if aware and duration <= shortest:
        raise ValueError(
            f"--workload aware needs --duration above {shortest:g} s: "
            f"records produced in the last {aware_load.GRACE_S:g} s do not count and the "
            f"definitions are injected at {aware_load.DEFINE_AT_S:g} s"
        )
    dep = (
        aware_load.deployment(motes, seed, duration, sinks=sinks)
        if aware
        else grid_deployment(motes, seed, radio)
    )
    # The medium's access and collision model (docs/radio.md), as a deployment sets it.
    dep = dataclasses.replace(dep, mac=mac, collisions=collisions)
    settings = LauncherSettings(
        processes=processes,
        speed=speed,
        handler="channel" if handler == "channel" else "callback",
        layout="interleaved" if layout == "interleaved" else "stripes",
        plugin=aware_load.AwarePlugin() if aware else None,
        control=False,
        lag_from_s=warmup,
    )
    t0 = time.perf_counter()
    with profiled(profile):  # this process only
        async with open_fleet(dep, KindsFactory() if aware else hello_core, settings) as fleet:
            await fleet.run(duration)
            await fleet.freeze(grace)
    gc.unfreeze()
    counters = fleet.counters()
    results = fleet.results
    for r in results:
        if r.error:
            raise RuntimeError(f"process {r.name}: {r.error}")
    tallies = plugin_results(results)
    if aware and len(tallies) != len(results):
        raise RuntimeError(f"{len(results) - len(tallies)} process(es) returned no tally")
    tally = aware_load.RecordTally().merge(tallies)
    lag = [v for r in results for v in r.lag_ms]
    wall = time.perf_counter() - t0
    tot = MoteCounters()
    for c in counters.values():
        tot.add(c)
    expected: int | None = None
    delivery: float | None = None
    records: dict[str, Any] = {}
    if aware:
        records = {
            **tally.results(duration),
            "sinks": len(aware_load.sinks_of(dep)),
            **aware_load.score_objects(tally, dep, duration),
        }
        ratio = records["record_delivery"]
        ok_delivery = ratio is not None and ratio >= min_delivery
        records["leaders_per_process"] = [len(t.leaders) for t in tallies]
    else:
        expected = expected_receptions(dep, {i: c.frames_tx for i, c in counters.items()})
        delivery = (tot.frames_rx + tot.collisions) / expected if expected else math.nan
        ok_delivery = delivery >= min_delivery
    p50, p99 = percentile(lag, 50), percentile(lag, 99)
    reason = failure_reason(p99, max_p99_ms, ok_delivery, records)
    out: dict[str, Any] = {
        "motes": motes,
        "processes": processes,
        "duration_s": duration,
        "speed": speed,
        "handler": settings.handler,
        "layout": settings.layout,
        "preset": dep.radio,
        "seed": seed,
        "spacing_m": round(dep.nodes[1].position[0] - dep.nodes[0].position[0], 3)
        if motes > 1
        else None,
        "timer_lag_p50_ms": round(p50, 3),
        "timer_lag_p99_ms": round(p99, 3),
        "timer_lag_max_ms": round(max(lag), 3) if lag else math.nan,
        "timer_samples": len(lag),
        "timer_lag_p99_per_process_ms": [round(percentile(r.lag_ms, 99), 1) for r in results],
        "frames_tx": tot.frames_tx,
        "frames_rx": tot.frames_rx,
        "frames_expected": expected,
        "mac": dep.mac,
        "collisions_model": dep.collisions,
        "collisions": tot.collisions,
        "late": sum(r.stats.get("late", 0) for r in results),
        "delivery_ratio": None if delivery is None else round(delivery, 5),
        "rx_per_tx": round(tot.frames_rx / tot.frames_tx, 2) if tot.frames_tx else 0.0,
        "envelopes_rx": sum(r.stats.get("envelopes_rx", 0) for r in results),
        "malformed": tot.malformed,
        "cpu_s": round(sum(r.cpu_s for r in results), 2),
        "cpu_per_process": [round(r.cpu_s, 2) for r in results],
        "wall_s": round(wall, 2),
        "meets_target": reason is None,
        "reason": reason,
        "workload": workload,
        **build_facts(),
    }
    if aware:
        out.update(records)
    return out


def failure_reason(
    p99: float, max_p99_ms: float, ok_delivery: bool, records: dict[str, Any]
) -> str | None:
    """Why a run misses the target (None: it meets it), the first that applies:

    * ``"overload"``: timer lag p99 at or above ``max_p99_ms`` (or no sample):
      the machine did not keep real time, whatever else was measured;
    * ``"no_records"`` (``--workload aware``): no leader produced a record
      before ``duration - GRACE_S``, so there is no delivery to measure (the
      run is too short for the time Drip, the collection tree and the group
      take to form on this grid; see ``first_record_s``);
    * ``"records_lost"`` / ``"frames_lost"``: delivery below ``--min-delivery``.
    """
    if not p99 < max_p99_ms:  # NaN (no sample) fails too
        return "overload"
    if records and not records["records_produced"]:
        return "no_records"
    if not ok_delivery:
        return "records_lost" if records else "frames_lost"
    return None


async def search(args: argparse.Namespace) -> dict[str, Any]:
    """Largest motes count meeting the target: double, then bisect (to ~5 %)."""
    trials: list[dict[str, Any]] = []

    async def trial(n: int) -> bool:
        r = await run_once(n, **_run_kwargs(args))
        trials.append(r)
        return bool(r["meets_target"])

    n = max(2, int(args.motes))
    best: int | None = None
    fail: int | None = None
    n = min(n, args.max_motes)
    while True:
        if not await trial(n):
            fail = n
            break
        best = n
        if n >= args.max_motes:
            break  # the bound itself passed: the answer is "at least max_motes"
        n = min(n * 2, args.max_motes)
    if best is not None and fail is not None:
        lo, hi = best, fail
        while hi - lo > max(50, lo // 20):
            mid = (lo + hi) // 2
            if await trial(mid):
                lo = mid
            else:
                hi = mid
        best = lo
    keys = (
        "motes",
        "timer_lag_p99_ms",
        "delivery_ratio",
        "records_produced",
        "record_delivery",
        "first_record_s",
        "meets_target",
        "reason",
    )
    summary = [{k: t[k] for k in keys if k in t} for t in trials]
    out: dict[str, Any]
    if best is None:
        out = dict(trials[0]) if trials else {"motes": 0}
        out["motes_max"] = 0
    else:
        out = dict(next(t for t in trials if t["motes"] == best and t["meets_target"]))
        out["motes_max"] = best
    out["search_bounded"] = best is not None and best >= args.max_motes
    out["search"] = summary
    return out


def _run_kwargs(args: argparse.Namespace) -> dict[str, Any]:
    mac, collisions = medium_of(args)
    return {
        "duration": float(args.duration),
        "processes": int(args.processes),
        "speed": float(args.speed),
        "seed": int(args.seed),
        "radio": str(args.radio),
        "handler": str(args.handler),
        "layout": str(args.layout),
        "warmup": float(args.warmup),
        "grace": float(args.grace),
        "max_p99_ms": float(args.max_p99_ms),
        "min_delivery": float(args.min_delivery),
        "workload": str(args.workload),
        "profile": args.profile,
        "mac": mac,
        "collisions": collisions,
        "sinks": args.sinks,
    }


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--motes", type=int, default=500, help="motes (start value with --search)")
    parser.add_argument("--duration", type=float, default=20.0, help="emulated seconds measured")
    parser.add_argument("--processes", type=int, default=1, help="worker processes")
    parser.add_argument("--speed", type=float, default=1.0, help="speed factor")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--radio", default="cc2420", help="radio preset")
    parser.add_argument(
        "--handler",
        choices=("callback", "channel"),
        default="channel",
        help="how Zenoh samples reach the loop: polled FIFO channel (default, faster) or "
        "callback batched into the loop",
    )
    parser.add_argument(
        "--layout",
        choices=("stripes", "interleaved"),
        default="stripes",
        help="how motes are spread over processes: x stripes (the product's way) or "
        "interleaved ids (worst case: most frames cross processes)",
    )
    parser.add_argument("--warmup", type=float, default=2.0, help="emulated s before lag counts")
    parser.add_argument("--grace", type=float, default=1.0, help="wall s for frames in flight")
    parser.add_argument("--max-p99-ms", type=float, default=50.0)
    parser.add_argument("--min-delivery", type=float, default=0.99)
    parser.add_argument("--search", action="store_true", help="find the largest N on target")
    parser.add_argument("--max-motes", type=int, default=16000, help="upper bound for --search")
    add_workload_arguments(parser)


def run(args: argparse.Namespace) -> dict[str, Any]:
    if args.search:
        return asyncio.run(search(args))
    return asyncio.run(run_once(int(args.motes), **_run_kwargs(args)))
