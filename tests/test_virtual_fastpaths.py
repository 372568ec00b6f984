"""The virtual driver's fast paths decide exactly what the slow paths decide.

Each fast path (docs/runtime.md, "Third round of speed-ups") skips work that
cannot change an outcome; these tests turn them off and compare, or compare
them with the formulas they shortcut.
"""

from __future__ import annotations

import math
import random

import pytest
from traces import aware_trace, record_events

from awaremw.bench import aware_load
from awaremw.experiments.scenario import load_scenario
from awaremw.experiments.virtual import VirtualRun
from awaremw.nodes import kinds
from awaremw.protocol.core import IdleCheck
from awaremw.protocol.frames import BROADCAST, Hello, encode
from awaremw.protocol.groups import conditions
from awaremw.protocol.mote import AwareMote
from awaremw.radio import reception
from awaremw.radio.mac import Air, _mw
from awaremw.radio.model import (
    CC2420,
    DOMAIN_FADING,
    DOMAIN_SHADOW,
    NORMAL,
    SHIFT,
    RadioModel,
    cell_of,
    link_hash,
)
from awaremw.world.fields import World, gauss_hash
from awaremw.world.mobility import Static


def _trace(motes: int, duration: float) -> list[str]:
    return aware_trace(motes, 3, duration)


@pytest.mark.pure_python
def test_the_fast_paths_change_no_event_and_no_counter(monkeypatch: pytest.MonkeyPatch) -> None:
    fast = _trace(120, 25.0)
    assert any("RecordProduced" in line for line in fast)
    # Off: every overlapping frame checked, every assessment asked of the Air,
    # every reception followed by drain/events/next_deadline.
    monkeypatch.setattr(reception, "reaching", lambda others, cell: others)
    monkeypatch.setattr(Air, "any_near", lambda self, rid, cell, t0, t1: True)
    monkeypatch.setattr(AwareMote, "idle", lambda self: False)
    slow = _trace(120, 25.0)
    assert slow == fast
    collisions = [line for line in fast if "collisions=" in line and "collisions=0," not in line]
    assert collisions  # the run exercised the survival checks


@pytest.mark.pure_python
def test_parked_membership_checks_change_no_event_and_no_counter(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    parked = aware_trace(400, 3, 40.0, deadlines=False)
    assert any("RecordProduced" in line for line in parked)
    # Off: no mote is static as far as its sensors know, so none parks.
    monkeypatch.setattr(kinds, "stays_put", lambda position: False)
    assert aware_trace(400, 3, 40.0, deadlines=False) == parked


def test_most_motes_of_the_aware_field_park_their_checks() -> None:
    load = aware_load.build(400, 3, 40.0)
    load.run_until(40.0)
    cores = [c for c in load.net.cores.values() if isinstance(c, AwareMote)]
    parked = sum(1 for c in cores if c.groups.stats.checks_parked)
    assert parked > len(cores) // 2  # the fire's reach is a band: most of the field is out


def _frames(rng: random.Random, air: Air, n: int, size: float) -> None:
    for src in range(1, n + 1):
        start = rng.uniform(0.0, 0.004)
        air.add(src, rng.uniform(0, size), rng.uniform(0, size), 0.0, start, start + 0.004)


def test_survival_against_the_reaching_frames_is_survival_against_all() -> None:
    rng = random.Random(5)
    model = RadioModel(CC2420, 9)
    cs = model.cell_size_m
    checked = {True: 0, False: 0}
    for _ in range(300):
        # Two Airs with the same frames: no cached power shared between the two ways.
        seed = rng.random()
        a, b = Air(model, 4.0, 0.01), Air(model, 4.0, 0.01)
        _frames(random.Random(seed), a, 6, 4 * cs)
        _frames(random.Random(seed), b, 6, 4 * cs)
        f, fb = a.frames[0], b.frames[0]
        rid = rng.choice([rng.randrange(100, 200), rng.randrange(2, 7)])  # some are deaf
        if rid < 100:
            rx, ry = a.frames[rid - 1].x, a.frames[rid - 1].y
        else:
            rx, ry = f.x + rng.uniform(-cs, cs), f.y + rng.uniform(-cs, cs)
        rssi = rng.uniform(-95.0, -60.0)
        whole = a.survives(f, rssi, rid, rx, ry, a.overlapping(f))
        rel = reception.reaching(b.overlapping(fb), cell_of(rx, ry, cs))
        fastway = not rel or b.survives(fb, rssi, rid, rx, ry, rel)
        assert fastway == whole
        checked[whole] += 1
    assert min(checked.values()) > 20


def test_no_reaching_frame_means_a_clear_channel() -> None:
    rng = random.Random(6)
    model = RadioModel(CC2420, 9)
    cs = model.cell_size_m
    skipped = 0
    for _ in range(300):
        air = Air(model, 4.0, 0.01)
        _frames(rng, air, 4, 6 * cs)
        x, y = rng.uniform(0, 6 * cs), rng.uniform(0, 6 * cs)
        t1 = rng.uniform(0.0, 0.01)
        if not air.any_near(500, cell_of(x, y, cs), t1 - 128e-6, t1):
            skipped += 1
            assert not air.busy(500, x, y, t1 - 128e-6, t1, -110.0, True)
    assert skipped > 50


def test_one_interferer_is_judged_at_its_power() -> None:
    model = RadioModel(CC2420, 2)
    air = Air(model, 4.0, 0.01)
    f = air.add(1, 0.0, 0.0, 0.0, 0.0, 0.004)
    o = air.add(2, 30.0, 0.0, 0.0, 0.001, 0.003)
    p = air.power_mw(o, 3, 10.0, 0.0)
    assert p > 0.0
    for rssi in (-90.0, -80.0, -70.0, -60.0):
        expect = _mw(rssi) >= air.capture_mw * (air._noise_mw + p)  # type: ignore[operator]
        assert air.survives(f, rssi, 3, 10.0, 0.0, [o]) is expect


@pytest.mark.parametrize("symmetric", [True, False])
def test_mean_rssi_and_link_hashes_are_the_formulas(symmetric: bool) -> None:
    rng = random.Random(7)
    model = RadioModel(CC2420, 12345, symmetric=symmetric)
    sigma = CC2420.shadowing_sigma_db
    for d in [0.0, 0.05, CC2420.d0_m * 0.1, 0.2, *(rng.uniform(0, 200) for _ in range(300))]:
        a, b = rng.randrange(1 << 16), rng.randrange(1 << 16)
        lo, hi = (min(a, b), max(a, b)) if symmetric else (a, b)
        shadow = sigma * NORMAL[link_hash(12345, DOMAIN_SHADOW, lo, hi) >> SHIFT]
        assert model.static_shadow_db(a, b) == shadow
        assert model.fading_link_hash(a, b) == link_hash(12345, DOMAIN_FADING, a, b)
        txp = rng.choice([0.0, -10.0, -25.0])
        assert model.mean_rssi(a, b, d, txp) == txp - model.path_loss_db(d) - shadow


def test_world_noise_is_the_gauss_hash_of_its_parts() -> None:
    rng = random.Random(8)
    w = World(seed=77)
    for _ in range(2000):
        node, t, sigma = rng.randrange(1 << 16), rng.uniform(0, 1e5), rng.uniform(0.01, 5.0)
        sensor = rng.choice(["temperature", "light", "humidity", "gas"])
        step = math.floor(t / w.noise_step)
        assert w.noise(node, sensor, t, sigma) == sigma * gauss_hash(77, node, sensor, step)


def test_an_aware_mote_is_idle_only_when_nothing_is_left_to_collect() -> None:
    m = AwareMote(4)
    assert isinstance(m, IdleCheck)
    m.start(0.0)
    assert not m.idle()  # timers were set
    m.drain(), m.events(), m.next_deadline()
    assert m.idle()
    dl = m.next_deadline()
    m.receive(encode(Hello(9, BROADCAST, 0)), -70.0, 0.5)  # noted, nothing to send
    if m.idle():
        assert m.drain() == [] and m.events() == [] and m.next_deadline() == dl
    m.receive(b"\xff\x00garbage", -70.0, 0.6)  # a MalformedFrame event
    assert not m.idle()
    m.events()
    assert m.idle() == (not m.ctx.outbox and not m._timer_watch.changed)


def test_a_subclass_that_moves_the_deadline_is_never_idle() -> None:
    class Later(AwareMote):
        def next_deadline(self) -> float | None:
            return 1.0

    m = Later(5)
    m.start(0.0)
    m.drain(), m.events(), m.next_deadline()
    assert not m.idle()


def test_a_hello_network_runs_without_the_idle_check() -> None:
    from awaremw.bench.virtual import build

    net = build(16, 1)
    assert all(not isinstance(c, IdleCheck) for c in net.cores.values())
    net.run_until(5.0)
    assert sum(c.frames_rx for c in net.counters.values()) > 0
    assert Static  # the bench grid is static


def _romeo4r_trace(duration: float) -> tuple[list[str], int]:
    """Every core event of a seeded romeo4r run (its robot group type has an
    rssi:<robot> condition), and how many membership checks were parked."""
    run = VirtualRun(load_scenario("romeo4r"))
    out = record_events(run.net)
    run.run(duration)
    for nid, c in sorted(run.net.counters.items()):
        out.append(f"{nid}|{c!r}")
    parked = sum(
        c.groups.stats.checks_parked for c in run.cores.values() if isinstance(c, AwareMote)
    )
    return out, parked


@pytest.mark.pure_python
def test_parking_on_an_unheard_rssi_node_changes_no_event(monkeypatch: pytest.MonkeyPatch) -> None:
    """A mote that has not heard the robot parks its checks of the robot's type until it
    hears it (issue 31); the run decides exactly what it decides when every mote checks."""
    parked, n_parked = _romeo4r_trace(60.0)
    assert any("GroupJoined" in line for line in parked)
    # Patched where the parking (Conditions) looks it up.
    monkeypatch.setattr(conditions, "unheard", lambda ctx, attr, now: False)
    ticking, n_ticking = _romeo4r_trace(60.0)
    assert ticking == parked
    assert n_parked > n_ticking
