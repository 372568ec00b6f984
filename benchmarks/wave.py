"""CPU and work per slice of emulated time of ``bench virtual --workload aware``.

    python benchmarks/wave.py [--motes 10000] [--until 4] [--step 0.1] [--seed 1] [--count]

Builds the aware workload of ``awaremw bench virtual`` (the definitions are
injected at every sink at 1 s) and runs it on the virtual clock ``--step``
emulated seconds at a time, printing one JSON line per slice: ``t`` (its end),
``cpu`` (this process's CPU seconds for the slice) and, with ``--count``, how
much happened in it: ``tx`` and ``tx:<frame type>`` (frames put on the air),
``rx`` (frames the cores took), ``decode`` (frames decoded: the receivers of
one frame share it), ``timer`` (timer firings of the cores) and
``timer:<component>`` (the component timers they ran), ``ev:<event>`` (core
events, ``ItemAdopted`` among them). The last line sums it up: ``total_cpu``,
``max_cpu`` (the costliest slice) and the totals. The counting wraps a few
public functions, so its CPU figures are a little higher: measure CPU without
``--count`` (and count with the pure-Python build: compiled classes cannot be
wrapped). At ``--speed 0.1`` a fleet has ``step / 0.1`` wall seconds for a
slice of ``step`` emulated seconds: a slice that costs more CPU than that
needs more than one core (docs/scale.md, "The real-time emulation at 10,000
motes").
"""

from __future__ import annotations

import argparse
import collections
import json
import time
from typing import Any

from awaremw.bench import aware_load
from awaremw.bench.virtual import settled_gc
from awaremw.protocol import frames
from awaremw.protocol.channels import Channels
from awaremw.protocol.collection import Collection
from awaremw.protocol.dissemination import Dissemination
from awaremw.protocol.groups import Groups
from awaremw.protocol.mote import AwareMote


def count_work(load: aware_load.AwareLoad, cnt: collections.Counter[str]) -> None:
    """Wrap the network's hooks and a few public functions to count into ``cnt``."""
    names = {cls.TYPE: cls.__name__ for cls in frames.FRAME_TYPES.values()}
    net = load.net

    def on_tx(nid: int, tx: Any, t: float) -> None:
        cnt["tx"] += 1
        cnt["tx:" + names.get(frames.peek_header(tx.frame)[0], "?")] += 1

    hook = net.on_event

    def on_event(nid: int, ev: object, t: float) -> None:
        cnt["ev:" + type(ev).__name__] += 1
        if hook is not None:
            hook(nid, ev, t)  # the workload's record tally

    net.on_transmit = on_tx
    net.on_event = on_event
    decode = frames.decode

    def counted_decode(data: bytes) -> frames.Frame:
        cnt["decode"] += 1
        return decode(data)

    frames.decode = counted_decode  # decode_shared looks it up at each call
    receive, handle_timer = AwareMote.receive, AwareMote.handle_timer

    def counted_receive(self: AwareMote, data: bytes, rssi: float, now: float) -> None:
        cnt["rx"] += 1
        receive(self, data, rssi, now)

    def counted_timer(self: AwareMote, now: float) -> None:
        cnt["timer"] += 1
        handle_timer(self, now)

    AwareMote.receive = counted_receive  # type: ignore[method-assign]
    AwareMote.handle_timer = counted_timer  # type: ignore[method-assign]
    for cls in (Dissemination, Collection, Groups, Channels):
        wrap_on_timer(cls, cnt)


def wrap_on_timer(cls: Any, cnt: collections.Counter[str]) -> None:
    on_timer = cls.on_timer

    def counted(self: Any, name: object, now: float) -> None:
        cnt[f"timer:{cls.__name__}:{name[0] if isinstance(name, tuple) else name}"] += 1
        on_timer(self, name, now)

    cls.on_timer = counted


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--motes", type=int, default=10000)
    ap.add_argument("--until", type=float, default=4.0, help="emulated s")
    ap.add_argument("--step", type=float, default=0.1, help="emulated s per slice")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--count", action="store_true", help="count frames, receptions, timers")
    a = ap.parse_args()
    load = aware_load.build(a.motes, a.seed, max(a.until, 20.0))
    cnt: collections.Counter[str] = collections.Counter()
    if a.count:
        count_work(load, cnt)
    cpus: list[float] = []
    with settled_gc():
        t = 0.0
        while t < a.until - 1e-9:
            t1 = round(t + a.step, 6)
            before = dict(cnt)
            c0 = time.process_time()
            load.run_until(t1)  # injects the definitions when it passes DEFINE_AT_S
            cpu = time.process_time() - c0
            cpus.append(cpu)
            row: dict[str, Any] = {"t": t1, "cpu": round(cpu, 3)}
            row.update({k: v - before.get(k, 0) for k, v in cnt.items() if v != before.get(k, 0)})
            print(json.dumps(row), flush=True)
            t = t1
    total = {"total_cpu": round(sum(cpus), 2), "max_cpu": round(max(cpus), 3)}
    print(json.dumps({**total, "totals": dict(cnt)}))


if __name__ == "__main__":
    main()
