"""A seeded whole-middleware run written out line by line, for identity checks."""

from __future__ import annotations

from awaremw.bench import aware_load
from awaremw.protocol.mote import AwareMote
from awaremw.radio.virtual_medium import VirtualNetwork


def aware_trace(motes: int, seed: int, duration: float, deadlines: bool = True) -> list[str]:
    """Every core event of a seeded aware run (mote, time, event), then every
    mote's radio counters and (``deadlines``) next deadline."""
    load = aware_load.build(motes, seed, duration)
    out = record_events(load.net)
    load.run_until(duration)
    for nid, core in sorted(load.net.cores.items()):
        assert isinstance(core, AwareMote)
        deadline = core.next_deadline() if deadlines else None
        out.append(f"{nid}|{load.net.counters[nid]!r}|{deadline!r}")
    return out


def record_events(net: VirtualNetwork) -> list[str]:
    """The list every core event of ``net`` is written to from now on (mote, time,
    event), beside the hook it had."""
    out: list[str] = []
    tally = net.on_event
    assert tally is not None

    def hook(nid: int, ev: object, t: float) -> None:
        out.append(f"{nid}|{t!r}|{ev!r}")
        tally(nid, ev, t)

    net.on_event = hook
    return out


def experiment_trace(name: str, seed: int) -> list[str]:
    """Every core event of a seeded virtual run of experiment ``name`` (its
    shipped deployment, its own ``prepare``), then every mote's radio counters."""
    from awaremw.experiments.seeds import seeded_run

    run = seeded_run(name, seed)
    out = record_events(run.net)
    run.run(None)
    for nid, c in sorted(run.net.counters.items()):
        out.append(f"{nid}|{c!r}")
    return out
