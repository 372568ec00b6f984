"""``awaremw bench mac``: the shared MAC core (radio/mac.py) against ALOHA theory.

``--senders`` motes (default 50) stand within 2 m of one sink, so that every
one senses every other (one collision domain, no hidden terminal); every
overlap destroys both frames (no capture). Each sender gets Poisson traffic of
fixed-length frames (``--bytes``, default the preset's MTU) and queues what it
cannot send yet; the offered load ``G`` (frames per frame time, all senders
together) is swept, and the throughput ``S`` (frame times per frame time
delivered to the sink) measured, for ``mac = "aloha"`` (pure ALOHA: no
backoff, no carrier sense) and ``mac = "csma"`` (the preset's CSMA/CA). Pure
ALOHA must follow ``S = G e^(-2G)``. The senders run the medium's own
:class:`~awaremw.radio.mac.MacSender` and :class:`~awaremw.radio.mac.Air`;
only the traffic and this small event loop are the benchmark's.

JSON keys: ``aloha`` and ``csma`` (lists of ``{"G", "S", "G_tx"}``; ``G_tx``
is the measured attempt rate, ``drops`` the frames CSMA gave up), ``theory``
(``{"G", "S"}`` of ``G e^(-2G)``), ``aloha_max_error`` (largest
``|S - G e^(-2G)|``), ``aloha_best``, ``csma_best``, ``csma_over_aloha``,
``senders``, ``frame_bytes``, ``airtime_s``, ``frame_times`` (per point),
``preset``, ``seed``, ``wall_seconds``; ``figure`` with ``--plot PATH``.
"""

from __future__ import annotations

import argparse
import dataclasses
import heapq
import math
import random
import time
from collections import deque
from typing import Any

from awaremw.radio.mac import GIVE_UP, SENSE, TRANSMIT, Air, MacSender, mac_params
from awaremw.radio.model import RadioModel, preset

SWEEP = (0.1, 0.2, 0.3, 0.4, 0.5, 0.75, 1.0, 1.25, 1.5, 2.0)
SINK = 0
MAX_QUEUE = 64  # frames a sender keeps waiting (more: dropped, counted)

_ARRIVAL, _CCA, _END = range(3)


def run_point(
    kind: str,
    g: float,
    senders: int = 50,
    frame_times: float = 20_000.0,
    radio: str = "cc2420",
    frame_bytes: int | None = None,
    seed: int = 1,
) -> dict[str, float]:
    """One point of the sweep: ``{"G", "S", "G_tx", "drops"}``."""
    p = preset(radio)
    n = p.mtu if frame_bytes is None else frame_bytes
    model = RadioModel(p, seed)
    params = mac_params(p, kind)
    if kind == "aloha":
        params = dataclasses.replace(params, aloha_backoff_s=0.0)  # pure ALOHA
    t_frame = p.airtime_s(n)
    air = Air(model, None, horizon_s=2 * t_frame)
    rate = g / (senders * t_frame)  # arrivals per second per sender
    rng = random.Random(seed * 7919 + round(g * 1000))
    pos = [
        (math.cos(2 * math.pi * i / senders), math.sin(2 * math.pi * i / senders))
        for i in range(senders)
    ]
    ids = [i + 1 for i in range(senders)]
    macs = [MacSender(params, model.backoff_link_hash(i)) for i in ids]
    queues: list[deque[float]] = [deque() for _ in ids]
    busy = [False] * senders
    seqs = [0] * senders
    heap: list[tuple[float, int, int, int]] = []
    order = 0
    warm = 50 * t_frame
    t_stop = warm + frame_times * t_frame
    ok = attempts = drops = 0

    def push(t: float, kind_: int, i: int) -> None:
        nonlocal order
        order += 1
        heapq.heappush(heap, (t, order, kind_, i))

    def begin(i: int, now: float) -> None:
        queues[i].popleft()
        busy[i] = True
        seqs[i] = (seqs[i] + 1) & 0xFFFF
        t = macs[i].begin(seqs[i], 0, now)
        if params.kind == "csma":
            push(t, _CCA, i)
        else:
            go(i, t)

    def go(i: int, start: float) -> None:
        air.prune(start - params.turnaround_s)  # not later than the decision time
        air.add(ids[i], pos[i][0], pos[i][1], p.tx_power_dbm, start, start + t_frame)
        push(start + t_frame, _END, i)

    def done(i: int, now: float) -> None:
        busy[i] = False
        if queues[i]:
            begin(i, now)

    for i in range(senders):
        push(rng.expovariate(rate), _ARRIVAL, i)
    while heap:
        now, _, kind_, i = heapq.heappop(heap)
        if now > t_stop:
            break
        if kind_ == _ARRIVAL:
            push(now + rng.expovariate(rate), _ARRIVAL, i)
            if len(queues[i]) < MAX_QUEUE:
                queues[i].append(now)
            if not busy[i]:
                begin(i, now)
        elif kind_ == _CCA:
            x, y = pos[i]
            b = air.busy(ids[i], x, y, now - params.cca_s, now, params.cca_threshold_dbm,
                         params.carrier_sense)  # fmt: skip
            action, t = macs[i].cca(b, now)
            if action == TRANSMIT:
                go(i, t)
            elif action == SENSE:
                push(t, _CCA, i)
            else:
                assert action == GIVE_UP
                if now >= warm:
                    drops += 1
                done(i, now)
        else:
            f = next(f for f in air.frames if f.src == ids[i] and f.end == now)
            if now - t_frame >= warm:
                attempts += 1
                if air.survives(f, 0.0, SINK, 0.0, 0.0, air.overlapping(f)):
                    ok += 1
            done(i, now)
    span = (t_stop - warm) / t_frame
    return {"G": g, "S": ok / span, "G_tx": attempts / span, "drops": drops}


def aloha_theory(g: float) -> float:
    return g * math.exp(-2.0 * g)


def run(
    ns: argparse.Namespace | None = None,
    *,
    senders: int = 50,
    frame_times: float = 20_000.0,
    sweep: tuple[float, ...] = SWEEP,
    radio: str = "cc2420",
    seed: int = 1,
    plot: str | None = None,
) -> dict[str, Any]:
    """Run the sweep (also takes the parsed CLI arguments, bench registry)."""
    if ns is not None:
        senders, frame_times, radio = int(ns.senders), float(ns.frame_times), str(ns.radio)
        seed, plot = int(ns.seed), ns.plot
        if ns.sweep:
            sweep = tuple(float(v) for v in ns.sweep.split(","))
    t0 = time.perf_counter()
    out: dict[str, Any] = {}
    for kind in ("aloha", "csma"):
        out[kind] = [run_point(kind, g, senders, frame_times, radio, None, seed) for g in sweep]
    p = preset(radio)
    out["theory"] = [{"G": g, "S": aloha_theory(g)} for g in sweep]
    out["aloha_max_error"] = max(abs(pt["S"] - aloha_theory(pt["G"])) for pt in out["aloha"])
    out["aloha_best"] = max(pt["S"] for pt in out["aloha"])
    out["csma_best"] = max(pt["S"] for pt in out["csma"])
    out["csma_over_aloha"] = out["csma_best"] / out["aloha_best"]
    out.update(
        senders=senders,
        frame_bytes=p.mtu,
        airtime_s=p.airtime_s(p.mtu),
        frame_times=frame_times,
        preset=radio,
        seed=seed,
        wall_seconds=round(time.perf_counter() - t0, 2),
    )
    if plot:
        out["figure"] = figure(out, plot)
    return out


def figure(result: dict[str, Any], path: str) -> str:
    """Both measured curves and ``G e^(-2G)`` to ``path`` (PNG)."""
    from matplotlib.figure import Figure  # no pyplot: no global state, no display

    fig = Figure(figsize=(6.4, 4.0))
    ax = fig.subplots()
    gs = [i / 100 for i in range(1, 201)]
    ax.plot(gs, [aloha_theory(g) for g in gs], "k--", lw=1, label="pure ALOHA theory $Ge^{-2G}$")
    for kind, style, label in (("aloha", "o-", "ALOHA (measured)"), ("csma", "s-", "CSMA/CA")):
        pts = result[kind]
        ax.plot([q["G"] for q in pts], [q["S"] for q in pts], style, ms=4, label=label)
    ax.set_xlabel("offered load G (frames per frame time)")
    ax.set_ylabel("throughput S")
    ax.set_title(
        f"awaremw bench mac: {result['senders']} senders, {result['preset']}, "
        f"{result['frame_bytes']} B frames"
    )
    ax.set_ylim(0, 1)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return path


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--senders", type=int, default=50, help="senders in the collision domain")
    p.add_argument(
        "--frame-times", type=float, default=20_000.0, help="measured frame times per point"
    )
    p.add_argument("--sweep", default="", help="offered loads G, comma-separated")
    p.add_argument("--radio", default="cc2420", help="radio preset")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--plot", metavar="PNG", default=None, help="write the figure there")
