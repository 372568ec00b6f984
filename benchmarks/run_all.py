"""Every figure of the figures table (docs/figures.md), in one session, from the commands it names.

    python benchmarks/run_all.py [--repeat 3] [--only KEY,...] [--out benchmarks/results.json]
    python benchmarks/run_all.py --only KEY,... --merge   # re-measure some rows, keep the others
    python benchmarks/run_all.py --markdown [--results FILE]  # the full table from results
    python benchmarks/run_all.py --write-docs [--results FILE]  # docs/figures.md and the README
    python benchmarks/run_all.py --quick --out /tmp/r.json     # tiny sizes: checks the structure

Each row of :data:`ROWS` is one line of docs/figures.md's table and names its
command. Every command runs as its own process, one after the other (they do
not compete for the cores), ``--repeat`` times; the row reports the *median
run as a whole*: the runs are ordered by the row's headline metric and the
middle one is kept with all its keys (never medians of keys taken from
different runs). Rows on the virtual clock whose figures are counts (seeded,
deterministic: the same numbers every run) run once (``repeat = 1`` in the
row, said in the table). ``results.json`` keeps every run, the chosen one,
the headline values of all runs, and the machine (cores, CPU model, Python,
package versions, load average before and after). ``--markdown`` prints the
table docs/figures.md embeds between ``<!-- run_all:begin -->`` and
``<!-- run_all:end -->``; ``--write-docs`` (also ``--write-readme``) writes it
there and the README's short table (the rows of :data:`BRIEF`, one headline
each) between the same markers in README.md; ``tests/test_run_all.py`` checks
that both are exactly what the script makes of ``results.json``. At
``--repeat 3`` the whole session takes about 11 minutes on a quiet 2-core
machine (budget: 15); progress goes to stderr, one line per run.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.metadata
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
README = HERE.parent / "README.md"
FIGURES = HERE.parent / "docs" / "figures.md"
BEGIN, END = "<!-- run_all:begin -->", "<!-- run_all:end -->"
RUN_TIMEOUT_S = 900.0
PACKAGES = ("awaremw", "eclipse-zenoh", "msgpack", "aiomqtt", "amqtt", "msgspec", "matplotlib",
            "cryptography")  # fmt: skip

Result = dict[str, Any]


def _n(v: Any, digits: int = 2) -> str:
    """A figure for the table: thousands separators, ``digits`` decimals at most."""
    if isinstance(v, bool) or v is None:
        return str(v).lower() if isinstance(v, bool) else "-"
    if isinstance(v, int):
        return f"{v:,}"
    if isinstance(v, float):
        s = f"{v:,.{digits}f}"
        return s.rstrip("0").rstrip(".") if "." in s else s
    return str(v)


def _ratio(a: Any, b: Any) -> str:
    try:
        return _n(float(a) / float(b), 1)
    except (TypeError, ValueError, ZeroDivisionError):
        return "-"


@dataclass(frozen=True)
class Row:
    """One line of the figures table (docs/figures.md) and how to make it."""

    key: str
    label: str
    argv: tuple[str, ...]  # after "awaremw" (or a script path under benchmarks/)
    quick: tuple[str, ...]  # the same command at tiny sizes (--quick)
    headline: str  # the key that picks the median run
    cell: Callable[[Result], str]  # the figures column, from the chosen run
    target: str = ""
    repeat: int | None = None  # None: --repeat; 1: deterministic figures, one run
    why_once: str = ""
    kind: str = "bench"  # bench: JSON on stdout; experiment: --out DIR/metrics.json
    build: str = "python"  # python: this interpreter's awaremw; mypyc: the compiled build

    @property
    def command(self) -> str:
        return "awaremw " + " ".join(self.argv)


def _scale_cell(r: Result) -> str:
    return (
        f"{_n(r.get('motes'))} motes beaconing 1/s, ~10 neighbours, {_n(r.get('processes'))} "
        f"process(es): timer lag p50 **{_n(r.get('timer_lag_p50_ms'))} ms**, p99 "
        f"**{_n(r.get('timer_lag_p99_ms'))} ms**; delivery ratio "
        f"**{_n(r.get('delivery_ratio'), 3)}** ({_n(r.get('frames_rx'))} of "
        f"{_n(r.get('frames_expected'))} receptions the loss model "
        f"keeps); {_n(r.get('collisions'))} receptions destroyed by collisions (model "
        f"`{r.get('collisions_model')}`), CPU {_n(r.get('cpu_s'), 1)} s; "
        f"on target: {_n(r.get('meets_target'))}"
    )


def _aware_what(r: Result) -> str:
    """The aware workload of a result, as it ran (bench/aware_load.py)."""
    if "objects" not in r:  # results of the earlier workload: one fire crossing the grid
        return (
            "a fire tracked by a group, AVG channel every 2 s, collection to the gateway's "
            "mote, Drip"
        )
    return (
        f"{_n(r.get('objects'))} fire(s) looping at 1 m/s, one per ~1,000 motes, "
        f"{_n(r.get('objects_tracked'))} tracked by a group; AVG channel every 2 s; collection "
        f"to {_n(r.get('sinks'))} sink(s); Drip"
    )


def _scale_aware_cell(r: Result) -> str:
    return (
        f"{_n(r.get('motes'))} full AwareMotes ({_aware_what(r)}) in "
        f"{_n(r.get('processes'))} process(es): timer lag p99 "
        f"**{_n(r.get('timer_lag_p99_ms', r.get('lag_p99_ms')))} ms**; record delivery "
        f"**{_n(r.get('record_delivery'), 3)}** ({_n(r.get('records_delivered'))} of "
        f"{_n(r.get('records_produced'))}); on target: {_n(r.get('meets_target'))}"
        + (f" (`{r['reason']}`)" if r.get("reason") else "")
    )


def _virtual_cell(r: Result) -> str:
    what = "HelloMotes beaconing 1/s (the radio alone)" if r.get("workload") == "hello" else (
        f"full AwareMotes ({_aware_what(r)})"
    )  # fmt: skip
    out = (
        f"{_n(r.get('motes'))} {what} x {_n(r.get('sim_seconds'))} s simulated in "
        f"{_n(r.get('wall_seconds'))} s: **{_n(r.get('speedup'), 1)}x** real time "
        f"(**{_ratio(r.get('sim_seconds'), r.get('cpu_seconds'))}x per CPU second**, "
        f"{_n(r.get('cpu_seconds'))} s CPU, build `{r.get('build', 'python')}`); "
        f"{_n(r.get('frames_tx'))} frames, {_n(r.get('deliveries'))} receptions"
    )
    if r.get("workload") == "aware":
        out += (
            f"; **{_n(r.get('records_delivered'))} of {_n(r.get('records_produced'))} records** "
            f"delivered (`record_delivery` {_n(r.get('record_delivery'), 3)})"
        )
    return out + _medium(r, "collisions", "in all")


def _large_cell(r: Result) -> str:
    return (
        f"{_n(r.get('motes_scored'))} tmote sky motes track the robot (group on its RSSI, AVG and "
        f"COUNT channels): {_n(r.get('duration_s'))} s emulated in **{_n(r.get('wall_s'))} s** "
        f"wall, setup, analysis and figures included: **{_n(r.get('speedup'), 1)}x** real time "
        f"({_n(r.get('cpu_s'))} s CPU); membership F1 {_n(r.get('membership_f1'), 3)}, "
        f"{_n(r.get('distinct_group_ids'))} group id(s), {_n(r.get('records_delivered'))} of "
        f"{_n(r.get('records_produced'))} records delivered"
    )


def _aggregation_cell(r: Result) -> str:
    sec = (
        f"every frame authenticated (+{_n(r.get('security_overhead_bytes'))} B, payload MTU "
        f"{_n(r.get('payload_mtu'))} B) and signed definitions; "
        if r.get("secure")
        else ""
    )
    return (
        f"{_n(r.get('motes'))}-mote grid, one {_n(r.get('members'))}-member group, "
        f"{_n(r.get('channel_period_s'))} s channel, beacons every {_n(r.get('beacon_period_s'))} s"
        f", {sec}everything counted: {_n(r.get('measured_per_epoch'), 1)} frames per epoch "
        f"against a lower bound of {_n(r.get('lower_bound_per_epoch'))}: `lower_bound_ratio` "
        f"**{_n(r.get('lower_bound_ratio'))}**; without aggregation "
        f"{_n(r.get('no_aggregation_per_epoch'))}: `no_aggregation_ratio` "
        f"**{_n(r.get('no_aggregation_ratio'), 1)}**; {_n(r.get('bytes_per_epoch'), 0)} radio bytes"
        f" and {_n(r.get('energy_mj_per_epoch'), 1)} mJ per epoch; records carry "
        f"{_n(100 * float(r.get('completeness') or 0), 1)} % of the members' readings"
        f"{_medium(r, 'collisions_per_epoch', 'per epoch')}"
    )


def _medium(r: Result, key: str, per: str) -> str:
    """The medium of a run (``--mac``, ``--collisions``) and its collision count."""
    if r.get("collisions_model") is None:
        return ""
    return (
        f"; medium `{r.get('mac')}`, collisions `{r.get('collisions_model')}`: "
        f"{_n(r.get(key), 1)} collisions {per}"
    )


def _dissemination_cell(r: Result) -> str:
    sec = "authenticated frames and signed items: " if r.get("secure") else ""
    return (
        f"{_n(r.get('motes'))}-mote grid, {_n(r.get('max_hops'))} hops, {sec}Trickle propagation "
        f"**{_n(r.get('seconds_per_hop'))} s per hop** ({_n(r.get('propagation_max_s'), 1)} s to "
        f"the farthest mote, {_n(r.get('propagation_drip_frames_per_mote'), 1)} Drip frames per "
        f"mote); steady state **{_n(r.get('tx_per_mote_per_hour'), 1)} transmissions per mote per "
        f"hour** (Drip {_n(r.get('drip_tx_per_mote_per_hour'), 1)}, collection beacons "
        f"{_n(r.get('ctp_beacons_per_mote_per_hour'), 1)}), "
        f"{_n(r.get('bytes_tx_per_mote_per_hour'), 0)} radio bytes per mote per hour"
        f"{_medium(r, 'window_collisions', 'in the steady-state window')}"
    )


def _bridge_cell(r: Result) -> str:
    return (
        f"gateway hand-over to an MQTT subscriber (embedded broker), "
        f"{_n(r.get('bridge_samples'))} records at {_n(r.get('bridge_rate_per_s'))}/s: p50 "
        f"**{_n(r.get('bridge_p50_ms'))} ms**, p99 **{_n(r.get('bridge_p99_ms'))} ms** (max "
        f"{_n(r.get('bridge_max_ms'))}); end to end on `grid_small` ({_n(r.get('latency_records'))}"
        f" records): sample at the leader to subscriber p50 {_n(r.get('latency_p50_ms'), 0)} ms "
        f"(the TAG schedule: the leader closes its aggregate at the end of the "
        f"{_n(r.get('period_s'))} s epoch), record at the leader to subscriber p50 "
        f"{_n(r.get('delivery_p50_ms'), 0)} ms; sustained **{_n(r.get('records_per_s'), 0)} "
        f"records/s**"
    )


def _mac_cell(r: Result) -> str:
    a = r.get("aloha") or [{}]
    c = r.get("csma") or [{}]
    best_a = max(a, key=lambda q: q.get("S", 0))
    best_c = max(c, key=lambda q: q.get("S", 0))
    return (
        f"{_n(r.get('senders'))} senders in one collision domain, {_n(r.get('frame_bytes'))} B "
        f"frames, Poisson traffic, G = {_n(a[0].get('G'))}..{_n(a[-1].get('G'))}: pure ALOHA "
        f"within **{_n(r.get('aloha_max_error'), 3)}** of G e^(-2G) (best S "
        f"{_n(r.get('aloha_best'), 3)} at G = {_n(best_a.get('G'))}); 802.15.4 CSMA/CA best S "
        f"**{_n(r.get('csma_best'), 3)}** at G = {_n(best_c.get('G'))} "
        f"(**{_n(r.get('csma_over_aloha'), 1)}x** ALOHA's best); figure "
        f"`docs/img/mac_throughput.png`"
    )


_ONCE = "virtual clock, seeded: the same counts every run"

ROWS: tuple[Row, ...] = (
    Row("scale-hello", "scale (real time, Zenoh), hello beacons",
        ("bench", "scale", "--motes", "2000", "--duration", "15", "--processes", "2", "--json"),
        ("bench", "scale", "--motes", "30", "--duration", "2", "--processes", "1", "--json"),
        "timer_lag_p99_ms", _scale_cell, "p99 < 50 ms, > 99 %"),
    Row("scale-hello-no-collisions", "scale (real time, Zenoh), hello beacons, no collisions",
        ("bench", "scale", "--motes", "2000", "--duration", "15", "--processes", "2",
         "--collisions", "none", "--json"),
        ("bench", "scale", "--motes", "30", "--duration", "2", "--processes", "1",
         "--collisions", "none", "--json"),
        "timer_lag_p99_ms", _scale_cell, "p99 < 50 ms, > 99 %"),
    Row("scale-hello-7000", "largest real-time fleet, hello beacons",
        ("bench", "scale", "--motes", "7000", "--duration", "15", "--processes", "2", "--json"),
        ("bench", "scale", "--motes", "60", "--duration", "2", "--processes", "1", "--json"),
        "timer_lag_p99_ms", _scale_cell, "p99 < 50 ms, > 99 %"),
    Row("scale-aware", "scale (real time, Zenoh), whole middleware",
        ("bench", "scale", "--workload", "aware", "--motes", "2000", "--duration", "30",
         "--processes", "2", "--json"),
        ("bench", "scale", "--workload", "aware", "--motes", "30", "--duration", "24",
         "--speed", "4", "--processes", "1", "--json"),
        "timer_lag_p99_ms", _scale_aware_cell, "p99 < 50 ms, >= 0.99"),
    Row("virtual-hello", "virtual clock, hello beacons",
        ("bench", "virtual", "--motes", "1000", "--duration", "120", "--json"),
        ("bench", "virtual", "--motes", "50", "--duration", "5", "--json"),
        "speedup", _virtual_cell, ">= 10x"),
    Row("virtual-aware", "virtual clock, whole middleware",
        ("bench", "virtual", "--workload", "aware", "--motes", "1000", "--duration", "120",
         "--json"),
        ("bench", "virtual", "--workload", "aware", "--motes", "50", "--duration", "12", "--json"),
        "speedup", _virtual_cell, "20x per CPU s, >= 0.99"),
    Row("virtual-aware-60", "virtual clock, whole middleware, 60 s",
        ("bench", "virtual", "--workload", "aware", "--motes", "1000", "--duration", "60",
         "--json"),
        ("bench", "virtual", "--workload", "aware", "--motes", "50", "--duration", "12", "--json"),
        "cpu_seconds", _virtual_cell, "20x per CPU s, >= 0.99"),
    Row("virtual-aware-60-compiled",
        "virtual clock, whole middleware, 60 s, compiled build (`AWAREMW_USE_MYPYC=1`)",
        ("bench", "virtual", "--workload", "aware", "--motes", "1000", "--duration", "60",
         "--json"),
        ("bench", "virtual", "--workload", "aware", "--motes", "50", "--duration", "12", "--json"),
        "cpu_seconds", _virtual_cell, "20x per CPU s, >= 0.99", build="mypyc"),
    Row("virtual-aware-no-collisions", "virtual clock, whole middleware, no collisions",
        ("bench", "virtual", "--workload", "aware", "--motes", "1000", "--duration", "120",
         "--collisions", "none", "--json"),
        ("bench", "virtual", "--workload", "aware", "--motes", "50", "--duration", "12",
         "--collisions", "none", "--json"),
        "speedup", _virtual_cell, "20x per CPU s, >= 0.99"),
    Row("experiment-large", "tracking at scale (`large.toml`)",
        ("experiment", "large", "--virtual", "--duration", "120"),
        ("experiment", "large", "--virtual", "--duration", "3"),
        "speedup", _large_cell, ">= 15x wall", kind="experiment"),
    Row("aggregation", "aggregation",
        ("bench", "aggregation", "--json"),
        ("bench", "aggregation", "--side", "6", "--radius", "12", "--warmup", "30", "--epochs",
         "3", "--json"),
        "lower_bound_ratio", _aggregation_cell, "<= 1.5, >= 5", repeat=1, why_once=_ONCE),
    Row("aggregation-no-collisions", "aggregation, no collisions",
        ("bench", "aggregation", "--collisions", "none", "--json"),
        ("bench", "aggregation", "--collisions", "none", "--side", "6", "--radius", "12",
         "--warmup", "30", "--epochs", "3", "--json"),
        "lower_bound_ratio", _aggregation_cell, "<= 1.5, >= 5", repeat=1, why_once=_ONCE),
    Row("aggregation-secure", "aggregation, secured",
        ("bench", "aggregation", "--secure", "--json"),
        ("bench", "aggregation", "--secure", "--side", "6", "--radius", "12", "--warmup", "30",
         "--epochs", "3", "--json"),
        "lower_bound_ratio", _aggregation_cell, "<= 1.5, >= 5", repeat=1, why_once=_ONCE),
    Row("dissemination", "dissemination",
        ("bench", "dissemination", "--json"),
        ("bench", "dissemination", "--side", "5", "--warmup", "20", "--settle", "30", "--window",
         "60", "--json"),
        "seconds_per_hop", _dissemination_cell, "", repeat=1, why_once=_ONCE),
    Row("dissemination-no-collisions", "dissemination, no collisions",
        ("bench", "dissemination", "--collisions", "none", "--json"),
        ("bench", "dissemination", "--collisions", "none", "--side", "5", "--warmup", "20",
         "--settle", "30", "--window", "60", "--json"),
        "seconds_per_hop", _dissemination_cell, "", repeat=1, why_once=_ONCE),
    Row("dissemination-secure", "dissemination, secured",
        ("bench", "dissemination", "--secure", "--json"),
        ("bench", "dissemination", "--secure", "--side", "5", "--warmup", "20", "--settle", "30",
         "--window", "60", "--json"),
        "seconds_per_hop", _dissemination_cell, "", repeat=1, why_once=_ONCE),
    Row("mac", "MAC against theory",
        ("bench", "mac", "--json", "--plot", "docs/img/mac_throughput.png"),
        ("bench", "mac", "--senders", "20", "--frame-times", "500", "--sweep", "0.25,1", "--json"),
        "csma_over_aloha", _mac_cell, "within 0.03; >= 2x", repeat=1, why_once=_ONCE),
    Row("bridge", "bridge (MQTT)",
        ("bench", "bridge", "--json"),
        ("bench", "bridge", "--duration", "14", "--records", "300", "--samples", "100", "--rate",
         "50", "--json"),
        "bridge_p99_ms", _bridge_cell, ">= 1,000 samples"),
)  # fmt: skip

# The README's short table: these rows, one headline each, in ROWS order.
BRIEF: dict[str, Callable[[Result], str]] = {
    "scale-hello": lambda r: (
        f"{_n(r.get('motes'))} motes in real time over Zenoh ({_n(r.get('processes'))} processes):"
        f" timer lag p99 **{_n(r.get('timer_lag_p99_ms'))} ms**, delivery "
        f"**{_n(r.get('delivery_ratio'), 3)}**"
    ),
    "scale-aware": lambda r: (
        f"{_n(r.get('motes'))} full motes in real time: timer lag p99 "
        f"**{_n(r.get('timer_lag_p99_ms', r.get('lag_p99_ms')))} ms**, record delivery "
        f"**{_n(r.get('record_delivery'), 3)}**"
    ),
    "virtual-aware": lambda r: (
        f"{_n(r.get('motes'))} full motes on the virtual clock: **{_n(r.get('speedup'), 1)}x** "
        f"real time, {_n(r.get('records_delivered'))} of {_n(r.get('records_produced'))} records"
    ),
    "virtual-aware-60-compiled": lambda r: (
        f"the same, 60 s, compiled build: **{_ratio(r.get('sim_seconds'), r.get('cpu_seconds'))}x"
        f"** per CPU second"
    ),
    "experiment-large": lambda r: (
        f"{_n(r.get('motes_scored'))} motes track the robot: **{_n(r.get('speedup'), 1)}x** real "
        f"time, F1 {_n(r.get('membership_f1'), 3)}"
    ),
    "aggregation": lambda r: (
        f"in-network aggregation: `lower_bound_ratio` **{_n(r.get('lower_bound_ratio'))}**, "
        f"`no_aggregation_ratio` **{_n(r.get('no_aggregation_ratio'), 1)}**"
    ),
    "dissemination": lambda r: (
        f"Drip over Trickle: **{_n(r.get('seconds_per_hop'))} s per hop**, "
        f"{_n(r.get('tx_per_mote_per_hour'), 1)} transmissions per mote per hour"
    ),
    "bridge": lambda r: (
        f"gateway to MQTT subscriber: p99 **{_n(r.get('bridge_p99_ms'))} ms**, "
        f"{_n(r.get('records_per_s'), 0)} records/s"
    ),
}


# --------------------------------------------------------------------------- running


def machine() -> dict[str, Any]:
    """What the figures were measured on."""
    model = platform.processor() or "unknown"
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    versions: dict[str, str | None] = {}
    for pkg in PACKAGES:
        try:
            versions[pkg] = importlib.metadata.version(pkg)
        except importlib.metadata.PackageNotFoundError:
            versions[pkg] = None
    commit = None
    with contextlib.suppress(OSError, subprocess.SubprocessError):
        p = subprocess.run(["git", "-C", str(HERE), "rev-parse", "--short", "HEAD"],
                           capture_output=True, text=True, timeout=10, check=False)  # fmt: skip
        commit = p.stdout.strip() or None
    return {
        "cores": os.cpu_count(),
        "cores_usable": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "cpu_model": model,
        "python": platform.python_version(),
        "implementation": platform.python_implementation(),
        "platform": platform.platform(),
        "packages": versions,
        "commit": commit,
        "loadavg_start": _loadavg(),
        "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }


def _loadavg() -> list[float] | None:
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return None


def run_one(row: Row, argv: Sequence[str], compiled: Path | None = None) -> Result:
    """One run of ``row``'s command (``argv`` after ``awaremw``): its JSON result.
    A ``mypyc`` row runs the compiled build installed in ``compiled`` (see
    :func:`build_compiled`), from a directory outside the checkout so that the
    sources do not shadow it."""
    with tempfile.TemporaryDirectory(prefix="awaremw-run-all-") as tmp:
        cmd = [sys.executable, "-m", "awaremw", *argv]
        env = None
        cwd = None
        if row.build == "mypyc":
            if compiled is None:
                raise RuntimeError("a compiled-build row needs the compiled build (build_compiled)")
            env = {**os.environ, "PYTHONPATH": str(compiled)}
            cwd = tmp
        if row.kind == "experiment":
            cmd += ["--out", tmp]
        t0 = time.monotonic()
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=RUN_TIMEOUT_S, check=False,
                           env=env, cwd=cwd)  # fmt: skip
        wall = round(time.monotonic() - t0, 2)
        if p.returncode != 0:
            raise RuntimeError(f"exit {p.returncode}: {p.stderr.strip()[-1500:]}")
        if row.kind == "experiment":
            result: Result = json.loads((Path(tmp) / "metrics.json").read_text())
        else:
            result = json.loads(p.stdout.strip().splitlines()[-1])
    if row.kind == "bench" and result.get("build", "python") != row.build:
        raise RuntimeError(f"the row wants the {row.build} build; {result.get('build')} ran")
    result["_process_wall_s"] = wall
    return result


def build_compiled(dest: Path) -> float:
    """Install the compiled build (setup.py, ``AWAREMW_USE_MYPYC=1``) of this checkout
    into ``dest`` with this interpreter's pip and mypy; returns the seconds it took."""
    t0 = time.monotonic()
    env = {**os.environ, "AWAREMW_USE_MYPYC": "1"}
    cmd = [sys.executable, "-m", "pip", "install", "-q", "--no-build-isolation", "--no-deps",
           "--target", str(dest), str(HERE.parent)]  # fmt: skip
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=RUN_TIMEOUT_S, check=False,
                       env=env)  # fmt: skip
    if p.returncode != 0:
        raise RuntimeError(f"compiled build failed: {p.stderr.strip()[-1500:]}")
    return round(time.monotonic() - t0, 1)


def median_run(runs: Sequence[Result], headline: str) -> tuple[int, list[Any]]:
    """Index of the median run by ``headline`` (the lower middle for an even count;
    runs without a number for it sort last) and the headline values in run order."""
    values = [r.get(headline) for r in runs]

    def order(i: int) -> tuple[int, float]:
        v = values[i]
        if isinstance(v, int | float) and not isinstance(v, bool):
            return (0, float(v))
        return (1, 0.0)

    ranked = sorted(range(len(runs)), key=order)
    return ranked[(len(ranked) - 1) // 2], values


@dataclass
class Session:
    repeat: int
    quick: bool
    rows: list[Row]
    compiled: Path | None = None  # the compiled build's directory (None: built when needed)
    report: dict[str, Any] = field(default_factory=dict)

    def run(self) -> dict[str, Any]:
        plan = [(row, self.repeat if row.repeat is None else min(row.repeat, self.repeat))
                for row in self.rows]  # fmt: skip
        total = sum(n for _, n in plan)
        self.report = {"repeat": self.repeat, "quick": self.quick, "machine": machine(),
                       "rows": {}}  # fmt: skip
        started = time.monotonic()
        with contextlib.ExitStack() as stack:
            compiled = self.compiled
            if compiled is None and any(row.build == "mypyc" for row, _ in plan):
                compiled = Path(stack.enter_context(tempfile.TemporaryDirectory(
                    prefix="awaremw-compiled-")))  # fmt: skip
                print("building the compiled build (setup.py, AWAREMW_USE_MYPYC=1) ...",
                      file=sys.stderr, flush=True)  # fmt: skip
                try:
                    self.report["machine"]["compiled_build_s"] = build_compiled(compiled)
                except (RuntimeError, OSError, subprocess.TimeoutExpired) as e:
                    # Its rows report the failure; the others still run.
                    print(f"    failed: {str(e)[-300:]}", file=sys.stderr, flush=True)
                    self.report["machine"]["compiled_build_error"] = str(e)[-1500:]
                    compiled = None
            self._rows(plan, total, started, compiled)
        self.report["machine"]["loadavg_end"] = _loadavg()
        self.report["session_s"] = round(time.monotonic() - started, 1)
        return self.report

    def _rows(self, plan: list[tuple[Row, int]], total: int, started: float,
              compiled: Path | None) -> None:  # fmt: skip
        k = 0
        for row, n in plan:
            argv = row.quick if self.quick else row.argv
            runs: list[Result] = []
            errors: list[str] = []
            for i in range(n):
                k += 1
                print(f"[{k}/{total}] {row.key} run {i + 1}/{n}: awaremw {' '.join(argv)}",
                      file=sys.stderr, flush=True)  # fmt: skip
                try:
                    r = run_one(row, argv, compiled)
                except (RuntimeError, ValueError, OSError, subprocess.TimeoutExpired) as e:
                    errors.append(str(e))
                    print(f"    failed: {str(e)[-300:]}", file=sys.stderr, flush=True)
                    continue
                runs.append(r)
                print(f"    {row.headline} = {r.get(row.headline)} ({r['_process_wall_s']} s; "
                      f"session {time.monotonic() - started:.0f} s)", file=sys.stderr,
                      flush=True)  # fmt: skip
            entry: dict[str, Any] = {
                "label": row.label,
                "command": "awaremw " + " ".join(argv),
                "headline": row.headline,
                "planned_runs": n,
                "errors": errors,
                "runs": runs,
            }
            if row.why_once and n == 1:
                entry["one_run"] = row.why_once
            if runs:
                i, values = median_run(runs, row.headline)
                entry["median_index"] = i
                entry["headline_values"] = values
                entry["median"] = runs[i]
            self.report["rows"][row.key] = entry


# --------------------------------------------------------------------------- the table


def merged(old: dict[str, Any], new: dict[str, Any]) -> dict[str, Any]:
    """``old`` with the rows of ``new`` in place of its own (``--merge``): each new
    row keeps when and on what load it was measured; ``merges`` lists the sessions."""
    m = new.get("machine", {})
    for e in new["rows"].values():
        e["measured_utc"] = m.get("started_utc")
        e["measured_loadavg"] = [m.get("loadavg_start"), m.get("loadavg_end")]
    out = dict(old)
    out["rows"] = {**old.get("rows", {}), **new["rows"]}
    session = {"rows": sorted(new["rows"]), "repeat": new.get("repeat"), "machine": m}
    out["merges"] = [*old.get("merges", []), session]
    return out


def markdown(report: dict[str, Any], rows: Sequence[Row] = ROWS) -> str:
    """The README's figures table (and a line on the machine) from a results report."""
    lines = [
        "| benchmark | command | figures (the median run) | target |",
        "|---|---|---|---|",
    ]
    for row in rows:
        e = report.get("rows", {}).get(row.key)
        if e is None or "median" not in e:
            why = "; ".join(e["errors"])[:200] if e and e.get("errors") else "not run"
            cell = f"no figure ({why})"
        else:
            vals = ", ".join(_n(v) for v in e["headline_values"])
            n = len(e["runs"])
            how = (f"median of {n} by `{row.headline}`: {vals}" if n > 1 else
                   f"one run: {e['one_run']}" if "one_run" in e else "one run")  # fmt: skip
            cell = f"{row.cell(e['median'])} ({how})"
            if e.get("measured_utc"):  # re-measured by a later session (--merge)
                cell += f"; re-measured {e['measured_utc']}, load {e['measured_loadavg'][0]}"
        command = e["command"] if e is not None else row.command
        lines.append(f"| {row.label} | `{command}` | {cell.replace('|', '/')} | {row.target} |")
    m = report.get("machine", {})
    if m:
        pk = m.get("packages", {})
        lines.append("")
        lines.append(
            f"Measured {m.get('started_utc', '?')} on {m.get('cores', '?')} cores "
            f"({m.get('cpu_model', '?')}), {m.get('implementation', 'Python')} "
            f"{m.get('python', '?')}, eclipse-zenoh {pk.get('eclipse-zenoh')}, msgpack "
            f"{pk.get('msgpack')}, aiomqtt {pk.get('aiomqtt')}, amqtt {pk.get('amqtt')}; load "
            f"average {m.get('loadavg_start')} before, {m.get('loadavg_end')} after; "
            f"`python benchmarks/run_all.py --repeat {report.get('repeat')}` "
            f"({report.get('session_s', '?')} s, commit {m.get('commit')})."
        )
    return "\n".join(lines) + "\n"


def brief_markdown(report: dict[str, Any], rows: Sequence[Row] = ROWS) -> str:
    """The README's short table: one headline per row of :data:`BRIEF`."""
    lines = ["| benchmark | figures (the median run) | target |", "|---|---|---|"]
    for row in rows:
        brief = BRIEF.get(row.key)
        if brief is None:
            continue
        e = report.get("rows", {}).get(row.key)
        cell = brief(e["median"]) if e is not None and "median" in e else "not run"
        lines.append(f"| {row.label} | {cell.replace('|', '/')} | {row.target} |")
    m = report.get("machine", {})
    lines.append("")
    again = [
        f"{', '.join(g['rows'])} re-measured {g['machine'].get('started_utc', '?')} (load "
        f"{g['machine'].get('loadavg_start', '?')}, wall-clock figures slower for it)"
        for g in report.get("merges", [])
    ]
    lines.append(
        f"Measured {m.get('started_utc', '?')} on {m.get('cores', '?')} cores"
        + "".join(f"; {a}" for a in again)
        + "; every row, its command and the machine: [docs/figures.md](docs/figures.md)."
    )
    return "\n".join(lines) + "\n"


def write_between_markers(table: str, path: Path) -> None:
    text = path.read_text(encoding="utf-8")
    a, b = text.find(BEGIN), text.find(END)
    if a < 0 or b < a:
        raise SystemExit(f"{path}: markers {BEGIN} ... {END} not found")
    path.write_text(text[: a + len(BEGIN)] + "\n" + table + text[b:], encoding="utf-8")


def write_docs(report: dict[str, Any], figures: Path = FIGURES, readme: Path = README) -> None:
    """The full table into docs/figures.md, the short one into the README."""
    write_between_markers(markdown(report), figures)
    write_between_markers(brief_markdown(report), readme)


COMPILED_HELP = (
    "the compiled build, installed in DIR (pip install --target DIR with AWAREMW_USE_MYPYC=1); "
    "default: built into a temporary directory"
)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--repeat", type=int, default=None, help="runs per row (default 3; 1 --quick)")
    ap.add_argument("--only", default=None, help="comma-separated row keys: " +
                    ", ".join(r.key for r in ROWS))  # fmt: skip
    ap.add_argument("--out", default=None, help="results file (default benchmarks/results.json)")
    ap.add_argument("--quick", action="store_true", help="tiny sizes, one run: the structure only")
    ap.add_argument("--merge", action="store_true",
                    help="with --only: put the new rows into the existing results file (each "
                    "re-measured row says when) instead of replacing it")  # fmt: skip
    ap.add_argument("--markdown", action="store_true", help="print the table from --results")
    ap.add_argument("--write-docs", "--write-readme", action="store_true",
                    help="write the table into docs/figures.md and the short one into README.md")
    ap.add_argument("--results", default=str(HERE / "results.json"), help="for --markdown")
    ap.add_argument("--compiled", default=None, metavar="DIR", help=COMPILED_HELP)
    a = ap.parse_args(argv)
    if a.markdown or a.write_docs:
        report = json.loads(Path(a.results).read_text(encoding="utf-8"))
        if a.write_docs:
            write_docs(report)
        else:
            print(markdown(report), end="")
        return 0
    repeat = a.repeat if a.repeat is not None else 1 if a.quick else 3
    if repeat < 1:
        ap.error("--repeat must be >= 1")
    keys = a.only.split(",") if a.only else [r.key for r in ROWS]
    by_key = {r.key: r for r in ROWS}
    unknown = [k for k in keys if k not in by_key]
    if unknown:
        ap.error(f"unknown row(s): {', '.join(unknown)}")
    if a.quick and a.out is None:
        ap.error("--quick needs --out (it must not overwrite benchmarks/results.json)")
    compiled = Path(a.compiled).resolve() if a.compiled else None
    report = Session(repeat, a.quick, [by_key[k] for k in keys], compiled).run()
    out = Path(a.out) if a.out else HERE / "results.json"
    if a.merge and out.exists():
        report = merged(json.loads(out.read_text(encoding="utf-8")), report)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=1) + "\n", encoding="utf-8")
    print(markdown(report, [by_key[k] for k in keys]), end="")
    print(f"wrote {out}", file=sys.stderr)
    failed = [k for k, e in report["rows"].items() if e["errors"]]
    if failed:
        print(f"rows with failed runs: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
