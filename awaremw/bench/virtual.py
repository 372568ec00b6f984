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
alone), ``frames_tx``, ``frames_by_kind`` (``frames_tx`` by frame
kind, as the metrics name them: ``ctp_beacon``, ``drip_item``, ...),
``deliveries`` (frames received by a core), ``mean_neighbours`` (table size
at the end), ``dropped_loss``, ``dropped_distance``, ``collisions``,
``cca_busy``, ``mac_drops`` (totals of the counters), ``mac`` and
``collisions_model`` (``--mac csma|aloha``, ``--collisions sinr|none``),
``preset``, ``seed``, ``spacing_m``, ``workload``. With
``--workload aware`` also ``records_produced``, ``records_delivered``,
``record_delivery`` (delivered / produced, records produced in the last 10 s
left out; null when none was produced before that), ``first_record_s``
(emulated time of the first record), ``leaders``, ``records_untracked``, ``channel_period_s``;
``mean_neighbours`` is then the mean collection-tree neighbour table size.
``build`` (``python``, or ``mypyc`` for the compiled build of ``setup.py``) and
``compiled_modules`` (how many of the hot modules run compiled) say what ran.

``--sizes 1000,10000``: the same run at every size, each in a fresh process
(so that its memory is its own), and how the cost grows: one JSON object with
``sizes`` (the runs, each with ``cpu_per_mote_s_us``: CPU microseconds per mote
per emulated second, and ``rss_per_mote_kb``: resident memory per mote, the
interpreter's own before the build left out) and ``cpu_per_mote_ratio`` (the
largest size's CPU per mote-second over the smallest's); ``--plot FILE`` draws
both against the number of motes. ``--sinks N`` (aware): collection roots on a
lattice (default one per region of about 1,000 motes). With
``--workload aware`` the JSON also has ``sinks``, ``objects`` (fires, one per
region), ``objects_tracked``, ``records_per_object``, ``ids_per_object`` and
``records_unattributed`` (:func:`awaremw.bench.aware_load.score_objects`).

``--networks K``: K independent networks of ``--motes`` each (seeds ``--seed``
on) in turns in one process (:func:`run_networks`; keys ``networks``,
``cpu_per_mote_s_us`` over all of their motes, ``record_delivery_min``).
``--sizes ... --control`` adds such a run with the largest size's motes in
networks of the smallest (``control``), ``cpu_per_mote_ratio_vs_control``
(the largest size's cost over the control's: what the large network's own
tables and queues add) and ``control_ratio`` (the control's over the
smallest size's: what the memory the motes span adds, the CPU's caches).

``--spacing M``: the grid's spacing (default 12 m; ``spacing_m``).
``--against-white`` with a realistic radio (``--noise TRACE``,
``--hardware-variance``): that run and the same run on today's radio,
``--repeats N`` times each (default 3), interleaved, every run in a fresh
process (:func:`run_against_white`). Keys ``cpu_seconds`` (every run's, per
radio: ``realistic`` and ``white``), ``cpu_seconds_median``, ``cpu_ratio``
(realistic over white, of the medians), ``frames_tx``, ``frames_ratio``,
``deliveries``, ``cpu_per_frame_us`` (the emulator's cost of a frame under
each radio, apart from how many frames the middleware sends),
``frames_by_kind`` (kind -> frames under each radio, the largest excess
first), with ``--workload aware`` also ``records_delivered``,
``records_produced`` and ``record_delivery`` per radio. ``--plot FILE``
draws ``frames_by_kind`` (PNG).
"""

from __future__ import annotations

import argparse
import gc
import json
import math
import os
import random
import resource
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

from awaremw.bench import aware_load
from awaremw.bench.medium import add_medium_arguments, add_radio_arguments, radio_of
from awaremw.bench.profiling import build_facts, profiled
from awaremw.protocol.core import Transmission
from awaremw.protocol.frames import MAX_NODE_ID
from awaremw.protocol.hello import HelloMote
from awaremw.protocol.mote import AwareMote
from awaremw.radio.environment import RadioSettings, radio_model
from awaremw.radio.frame_counts import frame_kind
from awaremw.radio.model import preset
from awaremw.radio.virtual_medium import VirtualNetwork
from awaremw.world.mobility import Static

SPACING_M = 12.0
WORKLOADS = ("hello", "aware")
# Emulated seconds between two explicit collections of the young generations
# during a run (the automatic collector is off meanwhile, see settled_gc).
GC_EVERY_S = 10.0
# --networks: emulated seconds each network runs in its turn (short: the networks'
# memory is touched in turn about as a large network's is, mote after mote).
INTERLEAVE_S = 0.01


@contextmanager
def settled_gc() -> Iterator[Callable[[], None]]:
    """The cyclic collector during a run on a network just built (restored after).

    The network lives for the whole run: it is frozen out of the collector
    (``gc.freeze()``, as a fleet does after setup), or every full collection
    walks all of it: they come every 70,000 net allocations or so, ten times
    as often at ten times the motes, each walking ten times the objects (a
    cost that grows with the square of the network). The automatic collector
    is then off, and the run calls the ``collect`` this yields every
    :data:`GC_EVERY_S` emulated seconds (:func:`run_collecting`): a
    collection by allocation counts reads the header of every old object a
    young one refers to, which at 10,000 motes misses the CPU's caches, and
    the workload makes no cyclic garbage to speak of (none was left after
    120 s at 10,000 motes; the oldest generation, what survived two of these
    collections, waits for the run's end). At 10,000 motes GC took about 12 % of the CPU with
    the young generation collected every 100,000 allocations, 3 % this way
    (docs/scale.md).
    """
    was_enabled = gc.isenabled()
    gc.collect()
    gc.freeze()
    gc.disable()
    try:
        yield _collect_young
    finally:
        if was_enabled:
            gc.enable()
        gc.unfreeze()


def _collect_young() -> None:
    gc.collect(1)


def run_collecting(
    run_until: Callable[[float], None], end: float, collect: Callable[[], None]
) -> None:
    """``run_until(end)`` in slices of :data:`GC_EVERY_S` emulated seconds,
    ``collect()`` after each (the same events: a slice ends where the next begins)."""
    k = 1
    while (t := k * GC_EVERY_S) < end:
        run_until(t)
        collect()
        k += 1
    run_until(end)


def build(
    motes: int,
    seed: int,
    radio: str = "cc2420",
    spacing: float = SPACING_M,
    mac: str = "csma",
    collisions: str = "sinr",
    settings: RadioSettings | None = None,
) -> VirtualNetwork:
    """A grid of HelloMotes (period 1 s) on a fresh virtual network."""
    p = preset(radio)
    net = VirtualNetwork(radio_model(p, seed, settings), seed, mac=mac, collisions=collisions)
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
    sinks: int | None = None,
    radio: RadioSettings | None = None,
    spacing: float = SPACING_M,
) -> dict[str, Any]:
    """Run the benchmark. Also accepts the parsed CLI arguments (bench registry)."""
    if isinstance(motes, argparse.Namespace):
        ns = motes
        check_spacing(ns.spacing)
        if ns.against_white:
            return run_against_white(ns)
        if ns.sizes and ns.networks != 1:
            raise ValueError("--networks is for one run; with --sizes, --control runs networks")
        if ns.control and not ns.sizes:
            raise ValueError("--control compares sizes: give --sizes (for example 1000,10000)")
        if ns.sizes:
            return run_sizes(ns)
        motes, duration, seed = int(ns.motes), float(ns.duration), int(ns.seed)
        workload, profile = str(ns.workload), ns.profile
        mac, collisions, sinks = str(ns.mac), str(ns.collisions), ns.sinks
        radio, spacing = radio_of(ns), float(ns.spacing)
        if ns.networks < 1:
            raise ValueError(f"--networks {ns.networks}: at least 1")
        if ns.networks > 1:
            return run_networks(
                motes, ns.networks, duration, seed, workload, mac, collisions, sinks, profile,
                radio, spacing,
            )  # fmt: skip
    check_run(workload, motes)
    rss0 = resident_kb()
    load = (
        aware_load.build(motes, seed, duration, mac, collisions, sinks, radio, spacing)
        if workload == "aware"
        else None
    )
    net = (
        load.net
        if load is not None
        else build(motes, seed, spacing=spacing, mac=mac, collisions=collisions, settings=radio)
    )
    by_kind = count_kinds(net)
    with settled_gc() as collect:
        t0 = time.perf_counter()
        c0 = time.process_time()
        with profiled(profile):
            run_until = load.run_until if load is not None else net.run_until
            run_collecting(run_until, duration, collect)
        wall = time.perf_counter() - t0
        cpu = time.process_time() - c0
    rss1 = max(resident_kb(), peak_kb())
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
        "cpu_per_mote_s_us": round(1e6 * cpu / (motes * duration), 3),
        "rss_per_mote_kb": round((rss1 - rss0) / motes, 2),
        "frames_tx": frames_tx,
        "frames_by_kind": dict(sorted(by_kind.items())),
        "deliveries": deliveries,
        "mean_neighbours": round(sum(tables) / max(1, len(tables)), 2),
        "dropped_loss": sum(c.dropped_loss for c in counters.values()),
        "dropped_distance": sum(c.dropped_distance for c in counters.values()),
        "collisions": sum(c.collisions for c in counters.values()),
        "cca_busy": sum(c.cca_busy for c in counters.values()),
        "mac_drops": sum(c.mac_drops for c in counters.values()),
        "mac": mac,
        "collisions_model": collisions,
        "radio_settings": (radio or RadioSettings()).describe(),
        "preset": net.preset.name,
        "seed": seed,
        "spacing_m": spacing,
        "workload": workload,
        **build_facts(),
    }
    if load is not None:
        out.update(load.results(duration))
    return out


def count_kinds(net: VirtualNetwork) -> dict[str, int]:
    """Frames put on the air by kind (``ctp_data``, ``drip_item``, ... as the
    metrics name them), retries included: a dict the run fills through the
    network's transmit hook (a dict lookup per frame, well under 1 % of a run)."""
    kinds: dict[str, int] = {}

    def on_transmit(nid: int, tx: Transmission, t: float) -> None:
        k = frame_kind(tx.frame)
        kinds[k] = kinds.get(k, 0) + 1

    net.on_transmit = on_transmit
    return kinds


def run_networks(
    motes: int,
    networks: int,
    duration: float,
    seed: int,
    workload: str = "aware",
    mac: str = "csma",
    collisions: str = "sinr",
    sinks: int | None = None,
    profile: str | None = None,
    radio: RadioSettings | None = None,
    spacing: float = SPACING_M,
) -> dict[str, Any]:
    """``--networks K``: K independent networks of ``motes`` each (seeds ``seed``
    on), run in one process in turns of :data:`INTERLEAVE_S` emulated seconds.

    The control of ``--sizes ... --control``: the same number of motes as one
    network K times larger, and so as much memory touched in turn, but no table,
    cell grid or timer queue larger than a small network's. What one large
    network costs beyond it is the emulator's doing; what the control costs
    beyond one small network is the memory the motes span (the CPU's caches)."""
    check_run(workload, motes)
    rss0 = resident_kb()
    loads: list[aware_load.AwareLoad] = []
    nets: list[VirtualNetwork] = []
    for k in range(networks):
        if workload == "aware":
            loads.append(
                aware_load.build(motes, seed + k, duration, mac, collisions, sinks, radio, spacing)
            )
            nets.append(loads[-1].net)
        else:
            net = build(
                motes, seed + k, spacing=spacing, mac=mac, collisions=collisions, settings=radio
            )
            nets.append(net)
    steps = [load.run_until for load in loads] if loads else [net.run_until for net in nets]
    turn = 0

    def in_turns(end: float) -> None:
        """Every network up to ``end``, INTERLEAVE_S emulated seconds at a time."""
        nonlocal turn
        while turn * INTERLEAVE_S < end:
            turn += 1
            t = min(end, turn * INTERLEAVE_S)
            for step in steps:
                step(t)

    with settled_gc() as collect, profiled(profile):
        c0 = time.process_time()
        run_collecting(in_turns, duration, collect)
        cpu = time.process_time() - c0
    rss1 = max(resident_kb(), peak_kb())
    counters = [c for n in nets for c in n.counters.values()]
    out: dict[str, Any] = {
        "motes": motes,
        "networks": networks,
        "sim_seconds": duration,
        "cpu_seconds": round(cpu, 3),
        "cpu_per_mote_s_us": round(1e6 * cpu / (motes * networks * duration), 3),
        "rss_per_mote_kb": round((rss1 - rss0) / (motes * networks), 2),
        "frames_tx": sum(c.frames_tx for c in counters),
        "deliveries": sum(c.frames_rx for c in counters),
        "workload": workload,
        "seed": seed,
        **build_facts(),
    }
    if workload == "aware":
        ratios = [load.tally.results(duration)["record_delivery"] for load in loads]
        known = [r for r in ratios if r is not None]
        out["record_delivery_min"] = min(known) if known else None
    return out


def check_spacing(spacing: float) -> None:
    """One line for a grid spacing no grid has."""
    if not (math.isfinite(spacing) and spacing > 0):
        raise ValueError(f"--spacing {spacing}: a grid spacing in metres, above 0")


def check_run(workload: str, motes: int) -> None:
    """One line for an unknown workload or a network too large (see check_motes)."""
    if workload not in WORKLOADS:
        raise ValueError(f"unknown workload {workload!r}; known: {', '.join(WORKLOADS)}")
    check_motes(motes)


def check_motes(motes: int) -> None:
    """One line for a network the address space cannot hold (IEEE 802.15.4 short
    addresses: 0xFFFF is broadcast, 0xFFFE means "no short address")."""
    if motes < 1:
        raise ValueError("--motes must be at least 1")
    if motes > MAX_NODE_ID + 1:
        raise ValueError(
            f"--motes {motes}: one network holds at most {MAX_NODE_ID + 1} motes "
            f"(16-bit short addresses 0..{MAX_NODE_ID}; 0xFFFE and 0xFFFF are reserved "
            "by IEEE 802.15.4)"
        )


def resident_kb() -> int:
    """This process's resident memory now, in KiB (0 where /proc is missing)."""
    try:
        with open("/proc/self/statm") as f:
            pages = int(f.read().split()[1])
    except (OSError, ValueError, IndexError):
        return 0
    return pages * (os.sysconf("SC_PAGE_SIZE") // 1024)


def peak_kb() -> int:
    """This process's peak resident memory, in KiB (Linux reports ru_maxrss in KiB)."""
    return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)


def parse_sizes(text: str) -> list[int]:
    """``"1000,10000"`` -> [1000, 10000] (sorted, distinct), one line on bad input."""
    try:
        sizes = sorted({int(x) for x in text.split(",") if x.strip()})
    except ValueError:
        raise ValueError(f"--sizes {text!r}: a comma-separated list of mote counts") from None
    if not sizes:
        raise ValueError("--sizes needs at least one mote count")
    for n in sizes:
        check_motes(n)
    return sizes


def run_sizes(ns: argparse.Namespace) -> dict[str, Any]:
    """``--sizes``: the run at every size, each in a fresh interpreter."""
    sizes = parse_sizes(str(ns.sizes))
    if ns.control and (len(sizes) < 2 or sizes[-1] % sizes[0]):
        raise ValueError(
            f"--control runs the largest size as networks of the smallest: "
            f"--sizes {ns.sizes} needs two sizes, the largest a multiple of the smallest"
        )
    runs: list[dict[str, Any]] = []
    sinks = [] if ns.sinks is None else ["--sinks", str(ns.sinks)]
    for n in sizes:
        if not ns.json:
            print(f"bench virtual: {n} motes ...", file=sys.stderr, flush=True)
        runs.append(_child(ns, n, sinks))
    first, last = runs[0], runs[-1]
    out: dict[str, Any] = {
        "sizes": runs,
        "cpu_per_mote_ratio": round(last["cpu_per_mote_s_us"] / first["cpu_per_mote_s_us"], 3),
        "rss_per_mote_ratio": round(last["rss_per_mote_kb"] / first["rss_per_mote_kb"], 3)
        if first["rss_per_mote_kb"] > 0
        else None,
        **build_facts(),
    }
    if ns.control:
        k = last["motes"] // first["motes"]
        if not ns.json:
            print(f"bench virtual: control, {k} networks of {first['motes']} motes ...",
                  file=sys.stderr, flush=True)  # fmt: skip
        control = _child(ns, first["motes"], ["--networks", str(k), *sinks])
        out["control"] = control
        # Above 1: the large network costs more than as many motes in small ones.
        out["cpu_per_mote_ratio_vs_control"] = round(
            last["cpu_per_mote_s_us"] / control["cpu_per_mote_s_us"], 3
        )
        out["control_ratio"] = round(control["cpu_per_mote_s_us"] / first["cpu_per_mote_s_us"], 3)
    if ns.plot:
        plot_sizes(runs, ns.plot, out.get("control"))
        out["plot"] = str(ns.plot)
    return out


def run_against_white(ns: argparse.Namespace) -> dict[str, Any]:
    """``--against-white``: the run ``ns`` asks for (a realistic radio) and the
    same run on today's radio (white noise, no hardware variance), ``--repeats``
    times each, interleaved, every run in a fresh interpreter: what the
    realistic radio costs, as a ratio measured in one invocation on one
    machine's load (docs/radio.md, "What it costs")."""
    asked = radio_of(ns)
    if asked.textbook:
        raise ValueError(
            "--against-white compares a realistic radio with today's: "
            "give --noise TRACE and/or --hardware-variance"
        )
    if ns.sizes or ns.networks != 1 or ns.profile:
        raise ValueError(
            "--against-white is one run per radio: no --sizes, --networks or --profile"
        )
    if ns.repeats < 1:
        raise ValueError(f"--repeats {ns.repeats}: at least 1")
    white = RadioSettings()
    runs: dict[str, list[dict[str, Any]]] = {"realistic": [], "white": []}
    for i in range(ns.repeats):
        for name, radio in (("realistic", asked), ("white", white)):
            if not ns.json:
                print(f"bench virtual: {name} radio, run {i + 1} of {ns.repeats} ...",
                      file=sys.stderr, flush=True)  # fmt: skip
            runs[name].append(_child(ns, int(ns.motes), [], radio))
    cpu = {k: statistics.median(r["cpu_seconds"] for r in v) for k, v in runs.items()}
    frames = {k: v[0]["frames_tx"] for k, v in runs.items()}  # a seed's frames are its own
    real, white_kinds = runs["realistic"][0]["frames_by_kind"], runs["white"][0]["frames_by_kind"]
    # Where the realistic radio's extra frames go: the largest excess first.
    by_kind = {
        k: {"realistic": real.get(k, 0), "white": white_kinds.get(k, 0)}
        for k in sorted(set(real) | set(white_kinds),
                        key=lambda k: (white_kinds.get(k, 0) - real.get(k, 0), k))
    }  # fmt: skip
    out: dict[str, Any] = {
        "motes": int(ns.motes),
        "sim_seconds": float(ns.duration),
        "seed": int(ns.seed),
        "workload": str(ns.workload),
        "spacing_m": float(ns.spacing),
        "radio_settings": asked.describe(),
        "repeats": int(ns.repeats),
        "cpu_seconds": {k: [r["cpu_seconds"] for r in v] for k, v in runs.items()},
        "cpu_seconds_median": cpu,
        "cpu_ratio": round(cpu["realistic"] / cpu["white"], 3) if cpu["white"] > 0 else None,
        "frames_tx": frames,
        "frames_ratio": (
            round(frames["realistic"] / frames["white"], 3) if frames["white"] else None
        ),
        "frames_by_kind": by_kind,
        "deliveries": {k: v[0]["deliveries"] for k, v in runs.items()},
        # Microseconds of CPU per frame put on the air: the emulator's cost of a
        # frame under each radio, apart from how many frames the middleware sends.
        "cpu_per_frame_us": {
            k: round(1e6 * cpu[k] / frames[k], 1) if frames[k] else None for k in runs
        },
        **build_facts(),
    }
    if ns.workload == "aware":
        for key in ("records_delivered", "records_produced", "record_delivery"):
            out[key] = {k: v[0][key] for k, v in runs.items()}
    if ns.plot:
        plot_kinds(out, ns.plot)
        out["plot"] = str(ns.plot)
    return out


def _child(
    ns: argparse.Namespace, motes: int, extra: list[str], radio: RadioSettings | None = None
) -> dict[str, Any]:
    """One run of ``ns`` at ``motes`` in a fresh interpreter (its memory its own);
    ``radio``: another radio than ``ns`` asks for."""
    r = radio_of(ns) if radio is None else radio
    argv = [
        sys.executable, "-m", "awaremw", "bench", "virtual", "--json",
        "--motes", str(motes), "--duration", str(ns.duration), "--seed", str(ns.seed),
        "--workload", str(ns.workload), "--mac", str(ns.mac),
        "--collisions", str(ns.collisions), "--spacing", str(ns.spacing), "--noise", r.noise,
        *(["--hardware-variance"] if r.hardware_variance else []), *extra,
    ]  # fmt: skip
    done = subprocess.run(argv, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        tail = (done.stderr.strip().splitlines() or ["no output"])[-1]
        raise RuntimeError(f"bench virtual at {motes} motes failed: {tail}")
    result: dict[str, Any] = json.loads(done.stdout)
    return result


def plot_sizes(
    runs: list[dict[str, Any]], path: str, control: dict[str, Any] | None = None
) -> None:
    """CPU per mote-second and memory per mote against the number of motes (with
    ``control``: its CPU at the largest size, as networks of the smallest)."""
    from matplotlib.figure import Figure  # no pyplot: no global state, no display

    motes = [r["motes"] for r in runs]
    fig = Figure(figsize=(6.4, 3.8), dpi=120)
    ax = fig.subplots()
    ax.plot(motes, [r["cpu_per_mote_s_us"] for r in runs], "o-", color="tab:red", label="CPU")
    if control is not None:
        n = control["motes"] * control["networks"]
        ax.plot([n], [control["cpu_per_mote_s_us"]], "D", mfc="white", ms=8, color="tab:red",
                label=f"CPU, {control['networks']} networks of {control['motes']:,}")  # fmt: skip
        ax.legend(loc="lower right", fontsize="small")
    ax.set_xscale("log")
    ax.set_xticks(motes, [f"{m:,}" for m in motes])
    ax.minorticks_off()
    ax.set_xlabel("motes")
    ax.set_ylabel("CPU per mote per emulated second (µs)", color="tab:red")
    cpus = [r["cpu_per_mote_s_us"] for r in runs]
    if control is not None:
        cpus.append(control["cpu_per_mote_s_us"])
    ax.set_ylim(0, 1.15 * max(cpus))
    mem = ax.twinx()
    mem.plot(motes, [r["rss_per_mote_kb"] for r in runs], "s--", color="tab:blue")
    mem.set_ylabel("memory per mote (KiB)", color="tab:blue")
    mem.set_ylim(0, 1.25 * max(r["rss_per_mote_kb"] for r in runs))
    ax.set_zorder(mem.get_zorder() + 1)  # the CPU points over the memory line
    ax.patch.set_visible(False)
    w = runs[0]["workload"]
    ax.set_title(f"bench virtual --workload {w}: cost per mote as the network grows")
    fig.tight_layout()
    fig.savefig(path)


def plot_kinds(out: dict[str, Any], path: str) -> None:
    """``--against-white --plot FILE``: the frames of each kind under both radios
    (bars, the largest excess on top), titled with the CPU and frame ratios."""
    from matplotlib.figure import Figure  # no pyplot: no global state, no display

    kinds = list(out["frames_by_kind"])[::-1]  # barh draws the first at the bottom
    real = [out["frames_by_kind"][k]["realistic"] for k in kinds]
    white = [out["frames_by_kind"][k]["white"] for k in kinds]
    fig = Figure(figsize=(6.4, 0.45 * len(kinds) + 1.6), dpi=120)
    ax = fig.subplots()
    y = range(len(kinds))
    ax.barh([i + 0.2 for i in y], white, height=0.4, color="tab:blue", label="today's radio")
    ax.barh([i - 0.2 for i in y], real, height=0.4, color="tab:red",
            label=out["radio_settings"])  # fmt: skip
    ax.set_yticks(list(y), kinds)
    ax.set_xlabel(f"frames on the air in {out['sim_seconds']:g} s (retries included)")
    ax.legend(loc="lower right", fontsize="small")
    ax.set_title(
        f"{out['workload']}, {out['motes']:,} motes, {out['spacing_m']:g} m: "
        f"CPU x{out['cpu_ratio']}, frames x{out['frames_ratio']}",
        fontsize="medium",
    )
    fig.tight_layout()
    fig.savefig(path)


def add_workload_arguments(parser: argparse.ArgumentParser) -> None:
    """The workload options bench virtual and bench scale share (and --mac, --collisions)."""
    parser.add_argument(
        "--workload",
        choices=WORKLOADS,
        default="hello",
        help="hello: beacons only (the radio); aware: the whole middleware tracking fires",
    )
    parser.add_argument("--profile", metavar="FILE", help="write a cProfile of the run to FILE")
    add_medium_arguments(parser)
    parser.add_argument(
        "--sinks",
        type=int,
        default=None,
        metavar="N",
        help="aware: collection roots on a lattice (default: one per ~1,000 motes)",
    )


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--motes", type=int, default=1000, help="number of motes (grid)")
    parser.add_argument("--duration", type=float, default=100.0, help="simulated seconds")
    parser.add_argument("--seed", type=int, default=1)
    add_workload_arguments(parser)
    add_radio_arguments(parser)
    parser.add_argument(
        "--sizes",
        metavar="N,N,...",
        help="run at each of these sizes (fresh process each) and compare the cost per mote",
    )
    parser.add_argument(
        "--plot",
        metavar="FILE",
        help="with --sizes: draw the cost curve; with --against-white: the frames of each "
        "kind under both radios (PNG)",
    )
    parser.add_argument(
        "--networks",
        type=int,
        default=1,
        metavar="K",
        help="K independent networks of --motes each, in turns in one process",
    )
    parser.add_argument(
        "--control",
        action="store_true",
        help="with --sizes: also run the largest size as networks of the smallest (--networks)",
    )
    parser.add_argument(
        "--spacing",
        type=float,
        default=SPACING_M,
        metavar="M",
        help=f"grid spacing in metres (default {SPACING_M:g}: about ten neighbours each "
        "on today's radio)",
    )
    parser.add_argument(
        "--against-white",
        action="store_true",
        help="also run the same command on today's radio (white noise, no hardware "
        "variance), interleaved, each run in a fresh process; report the cost ratio",
    )
    parser.add_argument(
        "--repeats",
        type=int,
        default=3,
        metavar="N",
        help="with --against-white: runs of each radio (CPU medians reported)",
    )
