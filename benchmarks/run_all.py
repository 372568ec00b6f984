"""Run every ``awaremw bench`` of the README in one session; medians of N runs.

    python benchmarks/run_all.py [--repeat 3] [--only scale,virtual] [--out benchmarks/results.json]

Each benchmark runs as its own process (``awaremw bench NAME --json ...``),
one after the other, so that they do not compete for the 2 cores. The JSON
file keeps every run and the median of each numeric key; the table printed at
the end is what the README's figures come from.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

# name -> (arguments, keys shown in the table)
SUITE: dict[str, tuple[list[str], list[str]]] = {
    "scale": (
        ["--motes", "2000", "--duration", "15", "--processes", "2"],
        ["motes", "timer_lag_p50_ms", "timer_lag_p99_ms", "delivery_ratio"],
    ),
    "virtual": (
        ["--motes", "1000", "--duration", "100"],
        ["motes", "sim_seconds", "wall_seconds", "speedup"],
    ),
    "aggregation": (
        [],
        ["lower_bound_ratio", "no_aggregation_ratio"],
    ),
    "dissemination": (
        [],
        ["seconds_per_hop", "tx_per_mote_per_hour"],
    ),
    "bridge": (
        [],
        ["latency_p50_ms", "latency_p99_ms", "records_per_s"],
    ),
}


def run_one(name: str, args: list[str]) -> dict[str, Any]:
    cmd = [sys.executable, "-m", "awaremw", "bench", name, "--json", *args]
    t0 = time.monotonic()
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=1800)
    if p.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({p.returncode}):\n{p.stderr[-2000:]}")
    result: dict[str, Any] = json.loads(p.stdout.strip().splitlines()[-1])
    result["_wall_s"] = round(time.monotonic() - t0, 1)
    return result


def median_of(runs: list[dict[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key in runs[0]:
        vals = [r.get(key) for r in runs]
        nums = [v for v in vals if isinstance(v, int | float) and not isinstance(v, bool)]
        out[key] = statistics.median(nums) if len(nums) == len(vals) else vals[0]
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--only", default=None, help="comma-separated subset of " + ", ".join(SUITE))
    ap.add_argument("--out", default="benchmarks/results.json")
    a = ap.parse_args()
    names = a.only.split(",") if a.only else list(SUITE)
    unknown = [n for n in names if n not in SUITE]
    if unknown:
        ap.error(f"unknown benchmark(s): {', '.join(unknown)}")
    report: dict[str, Any] = {"repeat": a.repeat, "benchmarks": {}}
    for name in names:
        args, keys = SUITE[name]
        runs = []
        for i in range(a.repeat):
            print(
                f"[{name} {i + 1}/{a.repeat}] awaremw bench {name} --json {' '.join(args)}",
                file=sys.stderr,
                flush=True,
            )
            runs.append(run_one(name, args))
        med = median_of(runs)
        report["benchmarks"][name] = {
            "command": f"awaremw bench {name} --json {' '.join(args)}".strip(),
            "median": med,
            "runs": runs,
        }
        print("  median: " + ", ".join(f"{k}={med.get(k)}" for k in keys), file=sys.stderr)
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(report, indent=1) + "\n")
    print("| benchmark | command | median of " + str(a.repeat) + " runs |")
    print("|---|---|---|")
    for name in names:
        b = report["benchmarks"][name]
        shown = ", ".join(f"`{k}` {b['median'].get(k)}" for k in SUITE[name][1])
        print(f"| {name} | `{b['command']}` | {shown} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
