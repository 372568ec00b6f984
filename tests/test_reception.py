"""radio/reception.py: the one home of the reception rules.

Its broadcast loop inlines ``RadioModel.decide``; these tests hold the inlined
decision equal to the model's, and the cached way (a static sender's receiver
lists, far receivers counted in bulk) equal to evaluating every receiver
afresh. Both media run this code (tests/test_mac_zenoh.py compares them).
"""

from __future__ import annotations

import random

import pytest

from awaremw.radio.counters import MoteCounters
from awaremw.radio.linklayer import LinkStation
from awaremw.radio.mac import Air
from awaremw.radio.model import CC1000, CC2420, RadioModel, RadioPreset
from awaremw.radio.neighbourhood import Neighbourhood
from awaremw.radio.reception import Reception
from awaremw.world.mobility import Static

Got = list[tuple[int, int, float]]  # (receiver, seq, rssi)


def _field(
    preset: RadioPreset, seed: int, motes: int, ranges: float
) -> tuple[RadioModel, Reception[LinkStation], Got, list[LinkStation]]:
    """``motes`` static motes on a square of side ``ranges`` radio ranges."""
    model = RadioModel(preset, seed)
    rng = random.Random(seed)
    nb: Neighbourhood[LinkStation] = Neighbourhood(model)
    size = ranges * model.max_range_m()
    got: Got = []
    stations = []
    for nid in range(1, motes + 1):
        st = LinkStation(
            nid,
            Static(rng.uniform(0, size), rng.uniform(0, size)),
            preset.tx_power_dbm,
            model.max_range_m(),
            MoteCounters(),
            None,
        )
        st.alive = True
        nb.add(st, 0.0)
        stations.append(st)
    rx: Reception[LinkStation] = Reception(
        model,
        nb,
        Air(model, preset.capture_threshold_db, 0.01),
        None,
        lambda r, src, data, rssi, now: got.append((r.node_id, src, rssi)),
        lambda r, now: None,
    )
    return model, rx, got, stations


@pytest.mark.parametrize(("preset", "seed"), [(CC2420, 3), (CC1000, 8)])
def test_the_inlined_decision_is_the_models(preset: RadioPreset, seed: int) -> None:
    model, rx, got, stations = _field(preset, seed, 60, 1.0)
    s = stations[0]
    near = rx.nb.sender(s.node_id, s.x, s.y, s.tx_power).near
    assert len(near) > 10
    delivered = lost = 0
    for seq in range(300):
        frame = bytes(seq % preset.mtu)
        got.clear()
        rx.broadcast(s.node_id, s.x, s.y, s.tx_power, True, frame, seq, None, None, 0.0, None)
        bits = 8 * (len(frame) + preset.phy_overhead_bytes)
        expect = []
        for r, _, mean, lh in near:
            ok, rssi = model.decide(lh, mean, bits, seq << 8)
            if ok:
                expect.append((r.node_id, s.node_id, rssi))
        assert got == expect
        delivered += len(expect)
        lost += len(near) - len(expect)
    assert delivered > 1000 and lost > 100  # both outcomes, many times


def test_the_cached_way_counts_what_evaluating_afresh_counts() -> None:
    ways = []
    for cached in (True, False):
        _, rx, got, stations = _field(CC2420, 5, 150, 3.0)
        for seq in range(40):
            for s in stations[:10]:
                rx.broadcast(s.node_id, s.x, s.y, s.tx_power, cached, b"x" * 20, seq, None, None,
                             seq * 0.1, None)  # fmt: skip
        rx.nb.flush_all()
        ways.append((sorted(got), [st.counters.as_dict() for st in stations]))
    assert ways[0] == ways[1]
    counters = ways[0][1]
    assert sum(c["frames_rx"] for c in counters) > 1000
    assert sum(c["dropped_distance"] for c in counters) > 100  # the bulk counts folded in
    assert sum(c["dropped_loss"] for c in counters) > 100
