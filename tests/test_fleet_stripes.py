"""A fleet's parts over several processes keep records flowing across stripe
boundaries: the aware load (full AwareMotes) split by ``FleetLauncher`` into x
stripes, real worker processes joined by an embedded Zenoh router.

600 motes in four stripes, one sink (gateway mote) at the centre, in the third;
the fire loops from the second, so its group (and its leader) stands there
and spans the first boundary, and every record it produces must cross the
second, by unicast collection hops acknowledged across processes, to reach
the sink.
"""

from __future__ import annotations

import asyncio

import pytest

from awaremw.bench import aware_load
from awaremw.bench.aware_load import AwarePlugin, RecordTally
from awaremw.nodes import KindsFactory
from awaremw.runtime.fleet import FleetLauncher, LauncherSettings
from awaremw.runtime.fleet.stats import plugin_results
from awaremw.runtime.partition import stripes

pytestmark = pytest.mark.zenoh

MOTES = 600
PROCESSES = 4
DURATION_S = 34.0
SPEED = 1.0


def test_records_cross_stripe_boundaries_to_the_sink() -> None:
    dep = aware_load.deployment(MOTES, 3, DURATION_S)
    cuts = stripes(dep, PROCESSES)
    where = {s.id: s for s in dep.nodes}

    def stripe_of(nid: int) -> int:
        return next(k for k, st in enumerate(cuts) if st(where[nid]))

    (sink,) = aware_load.sinks_of(dep)
    sink_k = stripe_of(sink)
    assert 0 < sink_k < PROCESSES - 1  # an inner stripe: a boundary on either side

    async def run() -> list[RecordTally]:
        settings = LauncherSettings(processes=PROCESSES, speed=SPEED, plugin=AwarePlugin())
        async with FleetLauncher(dep, KindsFactory(), settings) as launcher:
            await launcher.run(DURATION_S)
            await launcher.freeze(1.0)
        for r in launcher.results:
            assert r.error is None, f"{r.name}: {r.error}"
        tallies = plugin_results(launcher.results)
        assert len(tallies) == PROCESSES
        return tallies

    tallies = asyncio.run(run())
    merged = RecordTally().merge(tallies)
    counted = merged.counted(DURATION_S)
    # Records whose leader ran in another process than the sink.
    crossing = [k for k in counted if stripe_of(merged.produced[k][1]) != sink_k]
    assert len(crossing) >= 3, f"too few records from other stripes: {merged.results(DURATION_S)}"
    for k in crossing:  # worker k runs stripe k: the leader's process produced it
        assert k in tallies[stripe_of(merged.produced[k][1])].produced
    # Only the sink's process saw them delivered: they crossed to it.
    arrived = [k for k in crossing if k in tallies[sink_k].delivered]
    assert len(arrived) >= 0.9 * len(crossing), f"{len(arrived)} of {len(crossing)} arrived"
    assert all(not (set(crossing) & t.delivered) for k, t in enumerate(tallies) if k != sink_k)
