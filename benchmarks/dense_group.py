"""romeo4r with every mote in one group: how fast a command reaches every mote,
what it costs in Drip frames, and how many readings the group's count gets.

The romeo4r deployment on the virtual clock, secured (throw-away keys), with
what the dashboard test (tests/test_web.py) defines at ``--define-at``: group
type 2 (``light > 0``, every mote) and channel 5 (a count every second), then
a ``led`` command for every mote at ``--command-at``. Per seed: when each mote
ran the command and the Drip frames (items, signature parts, summaries) sent
in the 30 s after it; the median count of channel 5's records produced in the
60 s after it (the group has 20 members), and the partials sent and lost
after the link layer's retries over the whole run (the motes' channel
counters). ``--no-defs`` leaves the group type and channel out.

    python benchmarks/dense_group.py --seeds 1-14 [--no-defs] [--json]

docs/protocol-dissemination.md and docs/protocol-groups.md give the figures.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import sys
import tempfile
from pathlib import Path
from typing import Any

from awaremw.experiments.scenario import load_scenario, scenario_of
from awaremw.experiments.seeds import parse_seeds
from awaremw.experiments.virtual import VirtualRun
from awaremw.gateway import schema
from awaremw.protocol.core import Transmission
from awaremw.protocol.events import CommandExecuted
from awaremw.protocol.frames import DripItem, DripSig, DripSummary, ItemKind, peek_header
from awaremw.protocol.mote import AwareMote
from awaremw.security.keys import init_secrets

DRIP = (DripItem.TYPE, DripSig.TYPE, DripSummary.TYPE)
WINDOW_S = 30.0


def one_seed(seed: int, secrets: str, defs: bool, define_at: float, command_at: float,
             end: float) -> dict[str, Any]:  # fmt: skip
    sc = load_scenario("romeo4r")
    sc = scenario_of(dataclasses.replace(sc.deployment, seed=seed))
    run = VirtualRun(sc, secrets=secrets)
    net = run.net
    lim = schema.Limits()
    group = schema.parse_group_type(
        "2", b'{"conditions": [{"attr": "light", "op": ">", "value": 0}]}', lim
    )
    chan = schema.parse_channel(
        "5",
        b'{"attr": "temperature", "group_type": 2, "group_id": "*", "period_s": 1, "agg": "count"}',
        lim,
    )
    led = schema.parse_command(
        "led", b'{"target": "all", "args": {"color": "green", "state": "on"}}', lim
    )
    gateways = [run.cores[r] for r in run.roots]
    assert all(isinstance(g, AwareMote) for g in gateways)

    def inject(items: list[tuple[ItemKind, int, Any]]) -> None:
        for r, g in zip(run.roots, gateways, strict=True):
            for kind, item_id, body in items:
                net.call(r, lambda g=g, k=kind, i=item_id, b=body: g.inject(k, i, 1, b, net.now))

    if defs:
        net.call_at(define_at, lambda: inject([(group.kind, group.item_id, group.body),
                                               (chan.kind, chan.item_id, chan.body)]))  # fmt: skip
    net.call_at(command_at, lambda: inject([(ItemKind.COMMAND, 0, led.body)]))
    ran: dict[int, float] = {}
    recorder = net.on_event

    def on_event(node: int, ev: Any, t: float) -> None:
        if recorder is not None:
            recorder(node, ev, t)
        if isinstance(ev, CommandExecuted):
            ran.setdefault(node, t - command_at)

    net.on_event = on_event
    frames = [0]

    def on_transmit(node: int, tx: Transmission, t: float) -> None:
        if command_at <= t <= command_at + WINDOW_S and peek_header(tx.frame)[0] in DRIP:
            frames[0] += 1

    net.on_transmit = on_transmit
    net.run_until(end)
    delays = sorted(ran.values())
    n = len(sc.deployment.nodes)
    counts = [
        r.count
        for t, r in run.recorder.produced.values()
        if r.channel == chan.item_id and command_at <= t <= command_at + 60.0
    ]
    stats = [c.channels.stats for c in run.cores.values() if isinstance(c, AwareMote)]
    return {
        "seed": seed,
        "motes": n,
        "ran": len(delays),
        "half_s": round(delays[n // 2], 2) if len(delays) > n // 2 else None,
        "all_s": round(delays[-1], 2) if len(delays) == n else None,
        "drip_frames": frames[0],
        "count_median": statistics.median(counts) if counts else None,
        "partials_sent": sum(st.partials_sent for st in stats),
        "partials_lost": sum(st.link_dropped for st in stats),
    }


def _mean(values: Any) -> float | None:
    got = [v for v in values if v is not None]
    return round(statistics.mean(got), 2) if got else None


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seeds", default="1-6", help="e.g. 1-14 or 1,3,5")
    p.add_argument("--no-defs", action="store_true", help="only the command")
    p.add_argument("--define-at", type=float, default=40.0)
    p.add_argument("--command-at", type=float, default=100.0)
    p.add_argument("--end", type=float, default=250.0)
    p.add_argument("--json", action="store_true")
    a = p.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        secrets = Path(tmp) / "secrets"
        init_secrets(secrets)
        for seed in parse_seeds(a.seeds):
            row = one_seed(seed, str(secrets), not a.no_defs, a.define_at, a.command_at, a.end)
            rows.append(row)
            if not a.json:
                print(row, flush=True)
    reached = [r["all_s"] for r in rows if r["all_s"] is not None]
    summary = {
        "seeds": len(rows),
        "defs": not a.no_defs,
        "every_mote_ran": len(reached),
        "all_s_median": statistics.median(reached) if reached else None,
        "all_s_range": [min(reached), max(reached)] if reached else None,
        "drip_frames_median": statistics.median(r["drip_frames"] for r in rows),
        "drip_frames_mean": round(statistics.mean(r["drip_frames"] for r in rows), 1),
        "count_median_mean": _mean(r["count_median"] for r in rows),
        "partials_sent_mean": _mean(r["partials_sent"] for r in rows),
        "partials_lost_mean": _mean(r["partials_lost"] for r in rows),
        "rows": rows,
    }
    print(json.dumps(summary) if a.json else {k: v for k, v in summary.items() if k != "rows"})
    return 0


if __name__ == "__main__":
    sys.exit(main())
