"""``awaremw bench links``: every directed link of a radio, measured beacon by beacon.

Every mote in turn sends ``--beacons`` beacons of
:data:`~awaremw.radio.links.REFERENCE_BYTES` bytes, one every ``--interval``
seconds, while the others listen: no two frames on the air at once, so there
are no collisions and every loss is the link's. Each beacon is decided at every
receiver by the radio model the media use (``RadioModel.decide`` with the
receiver's noise at the frame's end), from a deployment (``--deployment``:
its positions, radio, seed, noise, hardware variance and links) or from a
links file alone (``--links``: TOSSIM's ``gain``/``noise`` lines or
probability triples; ``--radio`` picks the preset). ``--noise`` and
``--hardware-variance`` override the deployment's keys.

JSON keys: ``links`` (``[sender, receiver, given, measured]`` for every pair
that has a link or delivered something; ``given`` is the file's probability or
gain in dBm, or null), ``within_ci`` (the fraction of the links with a given
probability above 0 whose measured delivery lies in the binomial 99 % interval
around it), ``asymmetric`` (the fraction of mote pairs, among those with a
delivery in either direction, whose two directions differ by more than 0.2),
``beta_median`` (the median beta-factor of burstiness over the links
delivering 10 % to 90 %: ``beta = 1 - mean_n C(n) / PRR`` where ``C(n)`` is the
delivery of a beacon after ``n`` consecutive losses, ``n`` = 1 to 20 with 20
samples or more; 0 for independent losses, towards 1 for bursty links, after
Srinivasan et al., SenSys 2008), ``transitional_m`` (the distances where
links deliver 10 % to 90 %, with positions), ``good_neighbours`` (the mean
number of motes a mote reaches *both ways* with at least
:data:`GOOD_DELIVERY` of the frames), ``largest_good_part`` (the most motes
that such links connect, directly or over several hops: when it is much
less than ``motes``, no protocol can hold a network together over these
links), ``isolated_motes`` (motes with no such link), ``settings``,
``wall_seconds``.
``--plot PATH`` draws measured against given, delivery against distance and
the two directions of every pair.
"""

from __future__ import annotations

import argparse
import math
import statistics
import time
from pathlib import Path
from typing import Any

from awaremw.experiments.truth import components
from awaremw.radio.environment import RadioSettings, environment_of, radio_model
from awaremw.radio.links import REFERENCE_BYTES, LinkFile, load_links
from awaremw.radio.model import PRESETS, Z_MAX, packet_key
from awaremw.runtime.deployment import DeploymentError, load

CI_TAIL = 0.005  # each tail of the binomial 99 % interval
ASYMMETRY = 0.2
BETA_BAND = (0.1, 0.9)
BETA_MAX_RUN = 20
BETA_MIN_SAMPLES = 20
GOOD_DELIVERY = 0.7  # a link a protocol can rely on, both ways (see good_parts)


def binomial_interval(n: int, p: float, tail: float = CI_TAIL) -> tuple[int, int]:
    """The smallest ``[lo, hi]`` with ``P(X < lo) <= tail`` and ``P(X > hi) <= tail``
    for ``X ~ Binomial(n, p)``."""
    if p <= 0.0:
        return 0, 0
    if p >= 1.0:
        return n, n
    lq, lr = math.log(p), math.log1p(-p)
    lg = math.lgamma(n + 1)
    cdf = 0.0
    lo = None
    for k in range(n + 1):
        cdf += math.exp(lg - math.lgamma(k + 1) - math.lgamma(n - k + 1) + k * lq + (n - k) * lr)
        if lo is None and cdf > tail:
            lo = k
        if cdf >= 1.0 - tail:
            return lo if lo is not None else k, k
    return lo if lo is not None else 0, n


def beta_factor(outcomes: list[bool]) -> float | None:
    """Burstiness of one link's outcomes (see the module's docstring); None if no
    run length has enough samples."""
    n = len(outcomes)
    prr = sum(outcomes) / n
    if prr <= 0.0:
        return None
    count = [0] * (BETA_MAX_RUN + 1)
    succ = [0] * (BETA_MAX_RUN + 1)
    run = 0
    for ok in outcomes:
        if ok:
            # This beacon follows `run` losses: it counts for every n <= run.
            for k in range(1, min(run, BETA_MAX_RUN) + 1):
                count[k] += 1
                succ[k] += 1
            run = 0
        else:
            for k in range(1, min(run, BETA_MAX_RUN) + 1):
                count[k] += 1
            run += 1
    c = [succ[k] / count[k] for k in range(1, BETA_MAX_RUN + 1) if count[k] >= BETA_MIN_SAMPLES]
    if not c:
        return None
    return 1.0 - (sum(c) / len(c)) / prr


def good_parts(
    ids: list[int], delivery: dict[tuple[int, int], float]
) -> tuple[dict[int, set[int]], list[int]]:
    """The links delivering at least :data:`GOOD_DELIVERY` both ways (mote ->
    its such neighbours), and the sizes of the parts they connect."""
    good: dict[int, set[int]] = {i: set() for i in ids}
    for (a, b), d in delivery.items():
        both = d >= GOOD_DELIVERY and delivery.get((b, a), 0.0) >= GOOD_DELIVERY
        if both and a in good and b in good:
            good[a].add(b)
    return good, [len(c) for c in components(ids, lambda a, b: b in good[a])]


def _setup(args: argparse.Namespace) -> tuple[Any, dict[int, tuple[float, float] | None],
                                              dict[int, float], LinkFile | None, str]:  # fmt: skip
    """(model, positions by id (None: none), TX power by id, links file, source)."""
    if (args.deployment is None) == (args.links is None):
        raise ValueError("give exactly one of --deployment or --links")
    if args.deployment is not None:
        try:
            dep = load(args.deployment)
        except DeploymentError as e:
            raise ValueError(f"{e}") from None
        s = dep.radio_settings
        settings = RadioSettings(
            args.noise if args.noise is not None else s.noise,
            args.hardware_variance if args.hardware_variance is not None else s.hardware_variance,
            s.links,
        )
        seed = dep.seed if args.seed is None else args.seed
        try:
            model = radio_model(dep.preset, seed, settings, links=dep.link_file)
        except ValueError as e:
            raise ValueError(f"{e}") from None
        pos: dict[int, tuple[float, float] | None] = {n.id: n.position for n in dep.nodes}
        txp = {n.id: dep.tx_power_of(n) for n in dep.nodes}
        return model, pos, txp, dep.link_file, dep.name
    try:
        f = load_links(args.links)
        settings = RadioSettings(args.noise or "white", False, str(args.links))
        model = radio_model(PRESETS[args.radio], args.seed or 0, settings, links=f)
    except ValueError as e:
        raise ValueError(f"{e}") from None
    ids = sorted(f.nodes())
    p = model.preset.tx_power_dbm
    return model, dict.fromkeys(ids), dict.fromkeys(ids, p), f, str(args.links)


def run(args: argparse.Namespace) -> dict[str, Any]:
    t0 = time.perf_counter()
    if not 1 <= args.beacons <= 100_000:
        raise ValueError("--beacons must be in 1..100000")
    model, pos, txp, f, source = _setup(args)
    preset = model.preset
    airtime = preset.airtime_s(REFERENCE_BYTES)
    interval = max(args.interval, airtime + 0.001)
    bits = 8 * (REFERENCE_BYTES + preset.phy_overhead_bytes)
    max_fade = preset.fading_sigma_db * Z_MAX
    sens = preset.sensitivity_dbm
    no = model.noise_over
    ids = sorted(pos)
    n = args.beacons
    measured: dict[tuple[int, int], list[bool]] = {}
    for i, s in enumerate(ids):
        start = i * n * interval  # sender s's burst
        ps = pos[s]
        rng = model.max_range_m(txp[s])
        receivers = []
        for r in ids:
            if r == s:
                continue
            pr = pos[r]
            d = 1.0 if ps is None or pr is None else math.hypot(ps[0] - pr[0], ps[1] - pr[1])
            if d > rng:
                continue
            mean = model.mean_rssi(s, r, d, txp[s])
            if mean + max_fade < sens:
                continue  # no draw delivers (the media count it lost without a draw)
            receivers.append((r, mean, model.fading_link_hash(s, r)))
        for r, mean, lh in receivers:
            out = []
            for k in range(n):
                t_end = start + k * interval + airtime
                noise = None if no is None else no(r, t_end - airtime, t_end)
                ok, _ = model.decide(lh, mean, bits, packet_key(k & 0xFFFF), noise)
                out.append(ok)
            measured[(s, r)] = out
    return _report(args, model, pos, f, source, measured, n, interval, t0)


def _report(
    args: argparse.Namespace,
    model: Any,
    pos: dict[int, tuple[float, float] | None],
    f: LinkFile | None,
    source: str,
    measured: dict[tuple[int, int], list[bool]],
    n: int,
    interval: float,
    t0: float,
) -> dict[str, Any]:
    env = environment_of(model)
    table = None if env is None else env.links
    rows = []
    delivery: dict[tuple[int, int], float] = {}
    for pair, out in measured.items():
        delivery[pair] = sum(out) / n
    pairs = set(delivery)
    if f is not None:
        pairs |= set(f.probabilities) | set(f.gains)
    inside = total = 0
    for a, b in sorted(pairs):
        if a not in pos or b not in pos:
            continue
        given = None if table is None else table.given(a, b)
        m = delivery.get((a, b), 0.0)
        if given is None and m == 0.0:
            continue
        rows.append([a, b, given, round(m, 4)])
        if f is not None and f.probabilities and given is not None and given > 0.0:
            lo, hi = binomial_interval(n, given)
            total += 1
            inside += lo <= round(m * n) <= hi
    asym = npairs = 0
    ids = sorted(pos)
    for i, a in enumerate(ids):
        for b in ids[i + 1 :]:
            x, y = delivery.get((a, b), 0.0), delivery.get((b, a), 0.0)
            if x > 0.0 or y > 0.0:
                npairs += 1
                asym += abs(x - y) > ASYMMETRY
    betas = []
    for pair, out in measured.items():
        if BETA_BAND[0] <= delivery[pair] <= BETA_BAND[1]:
            beta = beta_factor(out)
            if beta is not None:
                betas.append(beta)
    result: dict[str, Any] = {
        "source": source,
        "settings": "textbook" if env is None else env.settings.describe(),
        "radio": model.preset.name,
        "seed": model.seed,
        "motes": len(pos),
        "beacons": n,
        "interval_s": interval,
        "frame_bytes": REFERENCE_BYTES,
        "links": rows,
        "within_ci": None if not total else round(inside / total, 4),
        "within_ci_links": total,
        "asymmetric": None if not npairs else round(asym / npairs, 4),
        "asymmetric_pairs": npairs,
        "beta_median": None if not betas else round(statistics.median(betas), 4),
        "beta_links": len(betas),
    }  # fmt: skip
    good, parts = good_parts(ids, delivery)
    links = sum(len(v) for v in good.values())
    result["good_neighbours"] = round(links / len(ids), 2) if ids else 0.0
    result["largest_good_part"] = max(parts, default=0)
    result["isolated_motes"] = sum(1 for i in ids if not good[i])
    trans = [
        math.dist(pa, pb)
        for (a, b), d in delivery.items()
        if BETA_BAND[0] <= d <= BETA_BAND[1]
        and (pa := pos.get(a)) is not None
        and (pb := pos.get(b)) is not None
    ]
    if trans and table is None:
        result["transitional_m"] = [round(min(trans), 2), round(max(trans), 2)]
    if args.plot:
        given = table is not None and f is not None and bool(f.probabilities)
        result["figure"] = plot(rows, delivery, pos, given, args.plot, source, result)
    result["wall_seconds"] = round(time.perf_counter() - t0, 2)
    return result


def plot(
    rows: list[list[Any]],
    delivery: dict[tuple[int, int], float],
    pos: dict[int, tuple[float, float] | None],
    given_probabilities: bool,
    path: str,
    source: str,
    result: dict[str, Any],
) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = []
    if given_probabilities:
        panels.append("given")
    if any(p is not None for p in pos.values()):
        panels.append("distance")
    panels.append("asymmetry")
    fig, axes = plt.subplots(1, len(panels), figsize=(4.4 * len(panels), 4.0))
    if len(panels) == 1:
        axes = [axes]
    for ax, kind in zip(axes, panels, strict=True):
        if kind == "given":
            g = [r[2] for r in rows if r[2] is not None]
            m = [r[3] for r in rows if r[2] is not None]
            ax.scatter(g, m, s=5, alpha=0.5)
            ax.plot([0, 1], [0, 1], "k--", lw=0.8)
            ax.set_xlabel("given delivery (measured in the lab)")
            ax.set_ylabel("measured delivery (emulated)")
            ax.set_title(f"within the 99 % interval: {result['within_ci']}")
        elif kind == "distance":
            xs, ys = [], []
            for (a, b), d in delivery.items():
                pa, pb = pos.get(a), pos.get(b)
                if pa is not None and pb is not None:
                    xs.append(math.dist(pa, pb))
                    ys.append(d)
            ax.scatter(xs, ys, s=5, alpha=0.5)
            tr = result.get("transitional_m")
            if tr:
                ax.axvspan(tr[0], tr[1], color="orange", alpha=0.15, label="transitional region")
                ax.legend(loc="upper right")
            ax.set_xlabel("distance (m)")
            ax.set_ylabel("delivery")
            ax.set_title("delivery against distance")
        else:
            xs, ys = [], []
            ids = sorted(pos)
            for i, a in enumerate(ids):
                for b in ids[i + 1 :]:
                    x, y = delivery.get((a, b), 0.0), delivery.get((b, a), 0.0)
                    if x or y:
                        xs.append(x)
                        ys.append(y)
            ax.scatter(xs, ys, s=5, alpha=0.5)
            ax.plot([0, 1], [0, 1], "k--", lw=0.8)
            ax.set_xlabel("delivery a -> b")
            ax.set_ylabel("delivery b -> a")
            ax.set_title(f"asymmetric (> 0.2): {result['asymmetric']}")
    fig.suptitle(f"{Path(source).name}: {result['settings']}, beta median {result['beta_median']}",
                 fontsize=9)  # fmt: skip
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--deployment", metavar="NAME|PATH", help="a deployment (name or file)")
    parser.add_argument("--links", metavar="FILE", help="a links file alone (or a shipped name)")
    parser.add_argument("--beacons", type=int, default=1000, help="beacons per mote")
    parser.add_argument(
        "--interval",
        type=float,
        default=0.02,
        help="seconds between two beacons of a mote (at least the airtime + 1 ms)",
    )
    parser.add_argument("--radio", choices=sorted(PRESETS), default="cc2420",
                        help="with --links: the radio preset")  # fmt: skip
    parser.add_argument("--seed", type=int, default=None, help="default: the deployment's (or 0)")
    parser.add_argument(
        "--noise", default=None, help="override: white, a shipped trace or a trace file"
    )
    hv = parser.add_mutually_exclusive_group()
    hv.add_argument("--hardware-variance", dest="hardware_variance", action="store_true",
                    default=None, help="override: per-mote power and noise offsets")  # fmt: skip
    hv.add_argument("--no-hardware-variance", dest="hardware_variance", action="store_false")
    parser.add_argument("--plot", metavar="FILE", help="draw the links (PNG)")
