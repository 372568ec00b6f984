"""``awaremw bench virtual``: how much faster than real time the virtual driver runs.

Motes on a square grid (CC2420 preset, 12 m spacing: about ten neighbours
each). ``--workload hello`` (the default, the radio alone): every one runs
:class:`~awaremw.protocol.hello.HelloMote` beaconing once per second.
``--workload aware``: the whole middleware, cores from the fleet's core
factory, a fire crossing the field tracked by a group, an AVG channel every
2 s, collection to the gateway's mote, Drip (see
:mod:`awaremw.bench.aware_load`). Two runs with the same seed give identical
counters (``tests/test_virtual.py`` checks it on a smaller grid).
``--profile FILE``: cProfile of the run (setup excluded) to FILE.

JSON keys: ``motes``, ``sim_seconds``, ``wall_seconds``, ``speedup``
(simulated / wall seconds), ``cpu_seconds`` (this process's CPU time: on a
shared machine, ``sim_seconds / cpu_seconds`` is the speed-up it would have
alone), ``frames_tx``, ``deliveries`` (frames received by
a core), ``mean_neighbours`` (table size at the end), ``dropped_loss``,
``dropped_distance``, ``collisions``, ``cca_busy``, ``mac_drops`` (totals of
the counters), ``mac`` and ``collisions_model`` (``--mac csma|aloha``,
``--collisions sinr|none``), ``preset``, ``seed``, ``spacing_m``, ``workload``. With
``--workload aware`` also ``records_produced``, ``records_delivered``,
``record_delivery`` (delivered / produced, records produced in the last 10 s
left out; null when none was produced before that), ``first_record_s``
(emulated time of the first record), ``leaders``, ``records_untracked``, ``channel_period_s``;
``mean_neighbours`` is then the mean collection-tree neighbour table size.
``build`` (``python``, or ``mypyc`` for the compiled build of ``setup.py``) and
``compiled_modules`` (how many of the hot modules run compiled) say what ran.
"""

from __future__ import annotations

import argparse
import math
import random
import time
from typing import Any

from awaremw.bench import aware_load
from awaremw.bench.profiling import build_facts, profiled
from awaremw.protocol.hello import HelloMote
from awaremw.protocol.mote import AwareMote
from awaremw.radio.model import RadioModel, preset
from awaremw.runtime.virtual import VirtualNetwork
from awaremw.world.mobility import Static

SPACING_M = 12.0
WORKLOADS = ("hello", "aware")


def build(
    motes: int,
    seed: int,
    radio: str = "cc2420",
    spacing: float = SPACING_M,
    mac: str = "csma",
    collisions: str = "sinr",
) -> VirtualNetwork:
    """A grid of HelloMotes (period 1 s) on a fresh virtual network."""
    p = preset(radio)
    net = VirtualNetwork(RadioModel(p, seed), seed, mac=mac, collisions=collisions)
    cols = max(1, math.ceil(math.sqrt(motes)))
    for i in range(motes):
        core = HelloMote(i, 1.0, random.Random(seed * 1_000_003 + i), p.mtu)
        x = spacing * (0.5 + i % cols)
        y = spacing * (0.5 + i // cols)
        net.add(core, Static(x, y))
    return net


def run(
    motes: int | argparse.Namespace = 1000,
    duration: float = 100.0,
    seed: int = 1,
    workload: str = "hello",
    profile: str | None = None,
    mac: str = "csma",
    collisions: str = "sinr",
) -> dict[str, Any]:
    """Run the benchmark. Also accepts the parsed CLI arguments (bench registry)."""
    if isinstance(motes, argparse.Namespace):
        ns = motes
        motes, duration, seed = int(ns.motes), float(ns.duration), int(ns.seed)
        workload, profile = str(ns.workload), ns.profile
        mac, collisions = str(ns.mac), str(ns.collisions)
    if workload not in WORKLOADS:
        raise ValueError(f"unknown workload {workload!r}; known: {', '.join(WORKLOADS)}")
    load = aware_load.build(motes, seed, duration, mac, collisions) if workload == "aware" else None
    net = load.net if load is not None else build(motes, seed, mac=mac, collisions=collisions)
    t0 = time.perf_counter()
    c0 = time.process_time()
    with profiled(profile):
        if load is not None:
            load.run_until(duration)
        else:
            net.run_until(duration)
    wall = time.perf_counter() - t0
    cpu = time.process_time() - c0
    counters = net.counters
    frames_tx = sum(c.frames_tx for c in counters.values())
    deliveries = sum(c.frames_rx for c in counters.values())
    tables = [
        len(core.table) if isinstance(core, HelloMote) else len(core.collection.neighbours)
        for core in net.cores.values()
        if isinstance(core, HelloMote | AwareMote)
    ]
    out: dict[str, Any] = {
        "motes": motes,
        "sim_seconds": duration,
        "wall_seconds": round(wall, 3),
        "cpu_seconds": round(cpu, 3),
        "speedup": round(duration / wall, 2) if wall > 0 else math.inf,
        "frames_tx": frames_tx,
        "deliveries": deliveries,
        "mean_neighbours": round(sum(tables) / max(1, len(tables)), 2),
        "dropped_loss": sum(c.dropped_loss for c in counters.values()),
        "dropped_distance": sum(c.dropped_distance for c in counters.values()),
        "collisions": sum(c.collisions for c in counters.values()),
        "cca_busy": sum(c.cca_busy for c in counters.values()),
        "mac_drops": sum(c.mac_drops for c in counters.values()),
        "mac": mac,
        "collisions_model": collisions,
        "preset": net.preset.name,
        "seed": seed,
        "spacing_m": SPACING_M,
        "workload": workload,
        **build_facts(),
    }
    if load is not None:
        out.update(load.results(duration))
    return out


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--motes", type=int, default=1000, help="number of motes (grid)")
    parser.add_argument("--duration", type=float, default=100.0, help="simulated seconds")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument(
        "--workload",
        choices=WORKLOADS,
        default="hello",
        help="hello: beacons only (the radio); aware: the whole middleware tracking a fire",
    )
    parser.add_argument("--profile", metavar="FILE", help="write a cProfile of the run to FILE")
    parser.add_argument("--mac", choices=("csma", "aloha"), default="csma", help="medium access")
    parser.add_argument(
        "--collisions", choices=("sinr", "none"), default="sinr", help="collision model"
    )
