"""Every deployment shipped in nodes/ loads, validates, builds and runs.

Each one is run briefly on the virtual clock with the cores the fleet uses
(:func:`awaremw.nodes.build_core`), its definitions injected at the gateway
mote; the checks are what any healthy run shows: every mote boots, the
collection tree forms, the definitions reach the motes, and nothing malformed
is ever heard.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from awaremw.experiments.scenario import load_scenario
from awaremw.experiments.virtual import VirtualRun
from awaremw.nodes import app_of, build_core, kind_names
from awaremw.protocol.mote import AwareMote
from awaremw.runtime.deployment import load, shipped_dir

SHIPPED = sorted(shipped_dir().glob("*.toml"))
# Emulated seconds of the smoke run: long enough for trees and dissemination,
# short for the 1,024 motes of large.toml and the 10,000 of city.toml.
RUN_S = {"large": 3.0, "city": 3.0}


def test_the_brief_s_deployments_are_shipped() -> None:
    assert {"romeo4r", "fire", "large"} <= {p.stem for p in SHIPPED}


@pytest.mark.parametrize("path", SHIPPED, ids=[p.stem for p in SHIPPED])
def test_shipped_deployment_runs(path: Path) -> None:
    d = load(path, kind_names())
    sc = load_scenario(path)  # validates nodes, world, definitions, [experiment]
    assert sc.gateway in d.ids
    for spec in d.nodes[:50]:
        core = build_core(spec, d, sc.world)
        app = app_of(core)
        assert isinstance(core, AwareMote) and app is not None
        assert core.config.mtu <= d.preset.mtu
        assert app.read(3, 0.0) == spec.position[0]  # attribute x
    robots = d.of_kind("robot")
    for r in robots:
        core = build_core(r, d, sc.world)
        assert isinstance(core, AwareMote) and core.config.hello_period
    gw = build_core(d.node(sc.gateway), d, sc.world)
    assert isinstance(gw, AwareMote) and gw.config.is_root

    run_s = RUN_S.get(path.stem, 25.0)
    run = VirtualRun(sc)
    res = run.run(run_s)
    counts = res.recorder.event_counts
    assert counts.get("MalformedFrame", 0) == 0
    booted = [n for n in d.ids if run.net.alive(n)]
    assert len(booted) == len([s for s in d.nodes if s.boot_s <= run_s])
    # Most motes found a route to the gateway.
    routed = {
        n
        for n, core in run.cores.items()
        if isinstance(core, AwareMote) and core.collection.parent is not None
    }
    assert len(routed) >= 0.5 * (len(d.ids) - 1), f"{len(routed)} of {len(d.ids)} routed"
    if sc.definitions and run_s > sc.define_at + 15:
        # The definitions reached (nearly) every mote by dissemination.
        n_defs = len(sc.definitions)
        have = [
            n
            for n, core in run.cores.items()
            if isinstance(core, AwareMote) and len(core.dissemination.items) >= n_defs
        ]
        assert len(have) >= 0.9 * len(d.ids)
