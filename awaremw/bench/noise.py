"""``awaremw bench noise``: the CPM noise model (radio/noise.py) against its trace.

Draws ``--seconds`` of emulated noise for one mote (one reading a millisecond,
asked for every millisecond, as a mote that hears frames all the time asks)
with the model and compares the readings with the trace they were learnt from:

* ``ks``: the Kolmogorov-Smirnov distance between the two distributions (the
  largest gap between their cumulative distribution functions);
* ``acf_max_diff``: the largest difference between their autocorrelations at
  lags 1 to 20 readings (``acf_model``, ``acf_trace``).

``--seeds A-B`` repeats the draw for every seed and adds the distribution
(``ks_seeds``, ``ks_max``, ``ks_within``: the fraction of seeds with ``ks``
at most 0.05). ``--plot PATH`` draws both histograms and autocorrelations.
"""

from __future__ import annotations

import argparse
import time
from collections import Counter
from collections.abc import Sequence
from typing import Any

from awaremw.experiments.seeds import parse_seeds
from awaremw.radio.noise import SHIPPED, TraceNoise, load_trace

LAGS = 20
KS_BOUND = 0.05


def ks_distance(a: Sequence[float], b: Sequence[float]) -> float:
    """Largest gap between the empirical CDFs of ``a`` and ``b``."""
    ca, cb = Counter(a), Counter(b)
    fa = fb = 0.0
    worst = 0.0
    for v in sorted(set(ca) | set(cb)):
        fa += ca.get(v, 0) / len(a)
        fb += cb.get(v, 0) / len(b)
        worst = max(worst, abs(fa - fb))
    return worst


def acf(x: Sequence[float], lags: int = LAGS) -> list[float]:
    """Autocorrelation at lags 1..``lags`` (each lag over the pairs it has)."""
    n = len(x)
    m = sum(x) / n
    d = [v - m for v in x]
    var = sum(v * v for v in d) / n
    if var == 0.0:
        return [1.0] * lags
    out = []
    for k in range(1, lags + 1):
        out.append(sum(a * b for a, b in zip(d, d[k:], strict=False)) / (n - k) / var)
    return out


def draw(trace_name: str, seconds: float, seed: int, node: int = 1) -> list[float]:
    """``seconds`` of one mote's readings (trace dBm), asked of the model the media
    use (:class:`TraceNoise`) every millisecond."""
    trace = load_trace(trace_name)
    noise = TraceNoise(trace, seed, trace.mode)
    return [noise.reading(node, ms) for ms in range(int(seconds * 1000))]


def run(args: argparse.Namespace) -> dict[str, Any]:
    t0 = time.perf_counter()
    if args.seconds <= 0 or args.seconds > 100_000:
        raise ValueError("--seconds must be in (0, 100000]")
    trace = load_trace(args.trace)
    ref = trace.readings
    ref_acf = acf(ref)
    # The experiments' seed lists ("1-40", "1,4,7"); a bad one is a ValueError, one line.
    seeds = parse_seeds(args.seeds) if args.seeds else [args.seed]
    per_seed: list[dict[str, Any]] = []
    first: list[float] = []
    for s in seeds:
        x = draw(args.trace, args.seconds, s)
        if not first:
            first = x
        model_acf = acf(x)
        per_seed.append(
            {
                "seed": s,
                "ks": round(ks_distance(x, ref), 4),
                "acf_max_diff": round(
                    max(abs(a - b) for a, b in zip(model_acf, ref_acf, strict=True)), 4
                ),
                "acf_model": [round(v, 4) for v in model_acf],
            }
        )
    out: dict[str, Any] = {
        "trace": trace.name,
        "trace_readings": len(ref),
        "readings": len(first),
        "seconds": args.seconds,
        "seed": seeds[0],
        "ks": per_seed[0]["ks"],
        "acf_max_diff": per_seed[0]["acf_max_diff"],
        "acf_model": per_seed[0]["acf_model"],
        "acf_trace": [round(v, 4) for v in ref_acf],
        "mean_model": round(sum(first) / len(first), 3),
        "mean_trace": round(sum(ref) / len(ref), 3),
    }
    if args.seeds:
        ks = [p["ks"] for p in per_seed]
        acfd = [p["acf_max_diff"] for p in per_seed]
        out.update(
            {
                "seeds": len(seeds),
                "ks_seeds": ks,
                "ks_mean": round(sum(ks) / len(ks), 4),
                "ks_max": max(ks),
                "ks_within": round(sum(k <= KS_BOUND for k in ks) / len(ks), 4),
                "acf_max_diff_max": max(acfd),
            }
        )
    if args.plot:
        out["figure"] = plot(first, ref, per_seed[0]["acf_model"], ref_acf, args.plot, trace.name)
    out["wall_seconds"] = round(time.perf_counter() - t0, 2)
    return out


def plot(
    model: Sequence[float],
    trace: Sequence[float],
    acf_model: Sequence[float],
    acf_trace: Sequence[float],
    path: str,
    name: str,
) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 3.6))
    lo = min(min(model), min(trace))
    hi = max(max(model), max(trace))
    bins = [lo - 0.5 + i for i in range(int(hi - lo) + 2)]
    a.hist(trace, bins=bins, density=True, log=True, alpha=0.6, label="trace")
    a.hist(model, bins=bins, density=True, log=True, histtype="step", lw=1.5, label="CPM model")
    a.set_xlabel("noise (dBm)")
    a.set_ylabel("fraction of readings (log)")
    a.set_title(f"distribution: {name.rsplit('/', 1)[-1]}")
    a.legend()
    lags = list(range(1, len(acf_trace) + 1))
    b.plot(lags, acf_trace, "o-", label="trace")
    b.plot(lags, acf_model, "s--", label="CPM model")
    b.set_xlabel("lag (readings, 1 ms)")
    b.set_ylabel("autocorrelation")
    b.set_ylim(0, 1)
    b.set_title("autocorrelation")
    b.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--trace",
        default="meyer-heavy",
        help=f"a shipped trace ({', '.join(SHIPPED)}) or a trace file: one reading (dBm) a line",
    )
    parser.add_argument("--seconds", type=float, default=200.0, help="emulated seconds to draw")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--seeds", default=None, metavar="A-B",
                        help="draw once per seed and report the distribution")  # fmt: skip
    parser.add_argument("--plot", metavar="FILE", help="draw histograms and autocorrelations (PNG)")
