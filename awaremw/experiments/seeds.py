"""One experiment over many seeds (``awaremw experiment NAME --virtual --seeds A-B``).

Every seed is an independent virtual-clock run of the scenario with the
deployment's ``seed`` replaced (radio losses, shadowing, the motes' random
choices and the world's texture all derive from it). Runs go to parallel
processes (``jobs``); each writes ``seed-<n>/metrics.json`` (and its figures)
under the output folder, and the folder gets:

* ``summary.json``: per metric the mean and 95 % confidence interval over the
  seeds (Student's t), the distribution of distinct group ids, the fraction of
  seeds with the experiment's ideal id count (``IDEAL_IDS`` of its analysis
  module), failover times when the experiment has them;
* ``seeds.png``: the distribution of F1 and of the id count over the seeds.
"""

from __future__ import annotations

import dataclasses
import importlib
import json
import math
import statistics
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Any

from awaremw.experiments import EXPERIMENTS, analysis, write_metrics
from awaremw.radio.environment import RadioSettings
from awaremw.runtime.deployment import Deployment

if TYPE_CHECKING:
    from awaremw.experiments.virtual import VirtualRun

MAX_SEEDS = 1000


class SeedSpecError(ValueError):
    """A ``--seeds`` value that is not ``N``, ``A-B`` or a comma list of those."""


def parse_seeds(spec: str) -> list[int]:
    """``"1-40"``, ``"3"``, ``"1-5,9,12-13"`` -> sorted distinct seeds."""
    seeds: set[int] = set()
    for part in spec.split(","):
        part = part.strip()
        try:
            if "-" in part:
                a, b = (int(x) for x in part.split("-", 1))
            else:
                a = b = int(part)
        except ValueError:
            raise SeedSpecError(f"--seeds: {part!r} is not N or A-B") from None
        if a < 0 or b < a:
            raise SeedSpecError(f"--seeds: {part!r} is not a range of seeds >= 0")
        seeds.update(range(a, b + 1))
        if len(seeds) > MAX_SEEDS:
            raise SeedSpecError(f"--seeds: more than {MAX_SEEDS} seeds")
    return sorted(seeds)


def ideal_ids(name: str) -> int | None:
    """The experiment's ideal count of distinct group ids (None: not defined)."""
    module = importlib.import_module(EXPERIMENTS[name][1])
    v = getattr(module, "IDEAL_IDS", None)
    return None if v is None else int(v)


def run_seed(
    name: str,
    seed: int,
    out: Path,
    deployment: str | None = None,
    duration: float | None = None,
    medium: Mapping[str, str] | None = None,
) -> dict[str, Any]:
    """One virtual run of experiment ``name`` with the deployment's seed set to ``seed``
    (and its ``mac`` / ``collisions`` keys replaced by ``medium``'s, if given)."""
    run = seeded_run(name, seed, deployment, medium)
    result = run.run(duration)
    metrics = analysis(name)(result, out)
    metrics["seed"] = seed
    metrics["mac"] = run.scenario.deployment.mac
    metrics["collisions"] = run.scenario.deployment.collisions
    write_metrics(out, metrics)
    return metrics


def seeded_run(
    name: str,
    seed: int,
    deployment: str | None = None,
    medium: Mapping[str, str] | None = None,
) -> VirtualRun:
    """The virtual run of experiment ``name`` that :func:`run_seed` runs: its
    deployment (or ``deployment``) with ``seed`` and ``medium``'s keys, prepared
    by the experiment's own ``prepare`` if it has one; not started."""
    from awaremw.experiments.scenario import load_scenario, scenario_of
    from awaremw.experiments.virtual import VirtualRun

    sc = load_scenario(deployment or EXPERIMENTS[name][0])
    d = with_medium(dataclasses.replace(sc.deployment, seed=seed), medium)
    run = VirtualRun(scenario_of(d))
    prepare = getattr(importlib.import_module(EXPERIMENTS[name][1]), "prepare", None)
    if prepare is not None:
        prepare(run)
    return run


def with_medium(d: Deployment, medium: Mapping[str, str] | None) -> Deployment:
    """``d`` with its ``mac``, ``collisions``, ``noise`` and ``hardware_variance``
    keys replaced by ``medium``'s (if any; ``hardware_variance`` as "true"/"false")."""
    if not medium:
        return d
    rs = d.radio_settings
    hv = medium.get("hardware_variance")
    radio = RadioSettings(
        medium.get("noise", rs.noise),
        rs.hardware_variance if hv is None else hv == "true",
        rs.links,
    )
    radio.check()
    return dataclasses.replace(
        d,
        mac=medium.get("mac", d.mac),
        collisions=medium.get("collisions", d.collisions),
        radio_settings=radio,
    )


def _run_one(
    args: tuple[str, int, Path, str | None, float | None, Mapping[str, str] | None],
) -> dict[str, Any]:
    return run_seed(*args)


def run_seeds(
    name: str,
    seeds: Sequence[int],
    out: Path,
    jobs: int = 1,
    deployment: str | None = None,
    duration: float | None = None,
    progress: Callable[[dict[str, Any]], None] | None = None,
    medium: Mapping[str, str] | None = None,
) -> dict[str, Any]:
    """Run every seed (``jobs`` processes), write the per-seed metrics, the summary
    and the figure; return the summary. ``medium``: deployment keys ``mac`` and
    ``collisions`` to override."""
    if jobs < 1:
        raise ValueError(f"jobs must be >= 1, got {jobs}")
    med = dict(medium) if medium else None
    tasks = [(name, s, out / f"seed-{s}", deployment, duration, med) for s in seeds]
    per_seed: list[dict[str, Any]] = []
    if jobs == 1 or len(tasks) == 1:
        for t in tasks:
            per_seed.append(_run_one(t))
            if progress is not None:
                progress(per_seed[-1])
    else:
        with ProcessPoolExecutor(max_workers=jobs) as pool:
            for m in pool.map(_run_one, tasks):
                per_seed.append(m)
                if progress is not None:
                    progress(m)
    summary = summarise(name, per_seed)
    for key in ("mac", "collisions"):
        summary[key] = sorted({str(m.get(key)) for m in per_seed})[0] if per_seed else None
    out.mkdir(parents=True, exist_ok=True)
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n", encoding="utf-8")
    figure(out / "seeds.png", name, per_seed, summary)
    return summary


# --------------------------------------------------------------------------- statistics

# Two-sided 95 % quantiles of Student's t for 1..30 degrees of freedom.
_T95 = (12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228, 2.201, 2.179,
        2.160, 2.145, 2.131, 2.120, 2.110, 2.101, 2.093, 2.086, 2.080, 2.074, 2.069, 2.064,
        2.060, 2.056, 2.052, 2.048, 2.045, 2.042)  # fmt: skip


def t95(df: int) -> float:
    if df < 1:
        return math.nan
    if df <= len(_T95):
        return _T95[df - 1]
    return 1.960 + 2.4 / df  # within 0.002 of the exact quantile beyond 30


def mean_ci(values: Sequence[float]) -> dict[str, float | int | None]:
    """Mean, 95 % CI half-width and bounds (t distribution), min, max, n."""
    xs = [float(v) for v in values if v is not None]
    n = len(xs)
    if n == 0:
        return {"n": 0, "mean": None, "ci95": None, "low": None, "high": None}
    m = statistics.fmean(xs)
    half = t95(n - 1) * statistics.stdev(xs) / math.sqrt(n) if n > 1 else math.nan
    return {
        "n": n,
        "mean": round(m, 4),
        "ci95": None if math.isnan(half) else round(half, 4),
        "low": None if math.isnan(half) else round(m - half, 4),
        "high": None if math.isnan(half) else round(m + half, 4),
        "min": round(min(xs), 4),
        "median": round(statistics.median(xs), 4),
        "max": round(max(xs), 4),
    }


def summarise(name: str, per_seed: Sequence[dict[str, Any]]) -> dict[str, Any]:
    ideal = ideal_ids(name)
    ids = [int(m["distinct_group_ids"]) for m in per_seed]
    key = "distinct_data_group_ids"
    data_ids = [int(m[key]) for m in per_seed if key in m]
    n = len(per_seed)
    s: dict[str, Any] = {
        "experiment": name,
        "seeds": [m["seed"] for m in per_seed],
        "n": n,
        "membership_f1": mean_ci([m["membership_f1"] for m in per_seed]),
        "distinct_group_ids": mean_ci(ids),
        "ids_histogram": {str(k): v for k, v in sorted(Counter(ids).items())},
        "ideal_ids": ideal,
        "ideal_ids_fraction": (
            None if ideal is None or n == 0 else round(sum(i == ideal for i in ids) / n, 4)
        ),
        "seeds_not_ideal": [
            m["seed"] for m in per_seed if ideal is not None and m["distinct_group_ids"] != ideal
        ],
        # The same over the ids that led at least one data record (absorbed
        # contenders left out; docs/experiments.md, "data ids").
        "data_ids_histogram": {str(k): v for k, v in sorted(Counter(data_ids).items())},
        "ideal_data_ids_fraction": (
            None
            if ideal is None or not data_ids
            else round(sum(i == ideal for i in data_ids) / len(data_ids), 4)
        ),
        "seeds_not_ideal_data": [
            m["seed"]
            for m in per_seed
            if ideal is not None and m.get("distinct_data_group_ids", ideal) != ideal
        ],
        "elections": mean_ci([m["elections"] for m in per_seed]),
        "delivery_ratio": mean_ci([m["delivery_ratio"] for m in per_seed]),
        "frames_per_mote": mean_ci([m["frames_per_mote"] for m in per_seed]),
    }
    for key in ("merge_id_inherited", "merge_single_id", "split_leader_part_keeps_id",
                "split_new_id", "two_fires_distinct_ids", "id_kept", "second_group",
                "one_id_per_object", "every_object_tracked"):  # fmt: skip
        vals = [m[key] for m in per_seed if key in m]
        if vals:
            s[f"{key}_fraction"] = round(sum(bool(v) for v in vals) / len(vals), 4)
    for key in ("failover_s", "failover_epochs"):
        vals = [m[key] for m in per_seed if m.get(key) is not None]
        if any(key in m for m in per_seed):
            s[key] = mean_ci(vals)
            s[f"{key}_missing"] = sum(1 for m in per_seed if m.get(key) is None)
    return s


def figure(path: Path, name: str, per_seed: Sequence[dict[str, Any]], s: dict[str, Any]) -> None:
    """F1 per seed, the histogram of distinct ids and (failover) the time to a new leader."""
    from matplotlib.figure import Figure  # no pyplot: no global state, no display

    fo = [m["failover_epochs"] for m in per_seed if m.get("failover_epochs") is not None]
    cols = 3 if fo else 2
    fig = Figure(figsize=(4.2 * cols, 3.6))
    axes = fig.subplots(1, cols)
    ax = axes[0]
    f1 = [m["membership_f1"] for m in per_seed]
    ax.plot([m["seed"] for m in per_seed], f1, "o", ms=4)
    mc = s["membership_f1"]
    if mc["mean"] is not None:
        ax.axhline(mc["mean"], color="k", lw=1, label=f"mean {mc['mean']:.3f}")
        if mc["ci95"] is not None:
            ax.axhspan(mc["low"], mc["high"], color="k", alpha=0.12, label="95 % CI")
        ax.legend(fontsize=8)
    ax.set_xlabel("seed")
    ax.set_ylabel("membership F1")
    ax.set_title(f"{name}: F1 over {len(per_seed)} seeds", fontsize=10)
    ax = axes[1]
    hist = Counter(int(m["distinct_group_ids"]) for m in per_seed)
    xs = list(range(1, max(hist, default=1) + 1))
    ideal = s.get("ideal_ids")
    ax.bar(xs, [hist.get(x, 0) for x in xs],
           color=["tab:green" if x == ideal else "tab:grey" for x in xs])  # fmt: skip
    ax.set_xticks(xs)
    ax.set_xlabel("distinct group ids in the run")
    ax.set_ylabel("seeds")
    ax.set_title(f"ideal {ideal}: {s.get('ideal_ids_fraction')} of seeds", fontsize=10)
    if fo:
        ax = axes[2]
        ax.hist(fo, bins=max(3, min(20, len(fo))), color="tab:blue")
        ax.set_xlabel("time to the new leader (channel epochs)")
        ax.set_ylabel("seeds")
        ax.set_title(f"failover: median {statistics.median(fo):.2f} epochs", fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
