"""The shared MAC/channel core (awaremw/radio/mac.py) and the virtual medium using it."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import pytest
from test_virtual import Recorder

from awaremw.protocol.core import Transmission
from awaremw.radio.mac import GIVE_UP, SENSE, TRANSMIT, Air, MacSender, mac_params
from awaremw.radio.model import CC1000, CC2420, RadioModel
from awaremw.radio.virtual_medium import VirtualNetwork
from awaremw.runtime.deployment import DeploymentError, load_deployment
from awaremw.world.mobility import Static

# No shadowing, no fading: received power is a function of distance alone, so
# "equal power" and "10 dB stronger" are exact. With n = 3, a factor 10^(1/3) in
# distance is 10 dB.
FLAT = dataclasses.replace(CC2420, shadowing_sigma_db=0.0, fading_sigma_db=0.0)
AIRTIME = FLAT.airtime_s(100)


def flat_air(capture_db: float | None = FLAT.capture_threshold_db) -> tuple[RadioModel, Air]:
    model = RadioModel(FLAT, 1)
    return model, Air(model, capture_db, horizon_s=AIRTIME)


def rssi(model: RadioModel, src: int, dst: int, d: float) -> float:
    return model.mean_rssi(src, dst, d, 0.0)


def test_two_equal_power_overlapping_frames_are_both_lost() -> None:
    model, air = flat_air()
    # A (1) and C (3) at 10 m on either side of B (2); C starts 1 ms into A's frame.
    fa = air.add(1, 0.0, 0.0, 0.0, 0.0, AIRTIME)
    fc = air.add(3, 20.0, 0.0, 0.0, 0.001, 0.001 + AIRTIME)
    assert air.overlapping(fa) == [fc] and air.overlapping(fc) == [fa]
    s = rssi(model, 1, 2, 10.0)
    assert s == rssi(model, 3, 2, 10.0) > FLAT.sensitivity_dbm + 5
    assert not air.survives(fa, s, 2, 10.0, 0.0, air.overlapping(fa))
    assert not air.survives(fc, s, 2, 10.0, 0.0, air.overlapping(fc))
    # Alone (back to back: end == start is no overlap), each survives.
    fd = air.add(4, 20.0, 0.0, 0.0, AIRTIME, 2 * AIRTIME)
    assert fd not in air.overlapping(fa)


def test_a_frame_10_db_stronger_is_captured_the_weaker_lost() -> None:
    model, air = flat_air()
    near, far = 5.0, 5.0 * 10 ** (10 / 30)
    fa = air.add(1, 10.0 - near, 0.0, 0.0, 0.0, AIRTIME)
    fc = air.add(3, 10.0 + far, 0.0, 0.0, 0.0005, 0.0005 + AIRTIME)
    sa, sc = rssi(model, 1, 2, near), rssi(model, 3, 2, far)
    assert sa - sc == pytest.approx(10.0)
    assert air.survives(fa, sa, 2, 10.0, 0.0, air.overlapping(fa))
    assert not air.survives(fc, sc, 2, 10.0, 0.0, air.overlapping(fc))
    # 2 dB stronger is under the 4 dB threshold: both lost.
    mid = 5.0 * 10 ** (2 / 30)
    fe = air.add(5, 10.0 + mid, 0.0, 0.0, 1.0, 1.0 + AIRTIME)
    ff = air.add(6, 10.0 - near, 0.0, 0.0, 1.0, 1.0 + AIRTIME)
    assert not air.survives(ff, sa, 2, 10.0, 0.0, air.overlapping(ff))
    assert not air.survives(fe, rssi(model, 5, 2, mid), 2, 10.0, 0.0, air.overlapping(fe))


def test_sinr_uses_the_worst_instant_and_a_transmitting_radio_is_deaf() -> None:
    model, air = flat_air()
    # Two interferers, each 6 dB under A at B: one alone leaves SINR ~6 dB (captured),
    # both at once ~3 dB (< 4 dB: lost); overlapping A but not each other: captured.
    d_i = 5.0 * 10 ** (6 / 30)
    fa = air.add(1, 5.0, 0.0, 0.0, 0.0, AIRTIME)
    air.add(3, 10.0 + d_i, 0.0, 0.0, -AIRTIME + 0.0005, 0.0005)
    air.add(4, 10.0, d_i, 0.0, AIRTIME - 0.0005, 2 * AIRTIME)
    s = rssi(model, 1, 2, 5.0)
    assert air.survives(fa, s, 2, 10.0, 0.0, air.overlapping(fa))
    air.add(5, 10.0, -d_i, 0.0, 0.0001, 0.0002)  # now overlaps the first one
    assert not air.survives(fa, s, 2, 10.0, 0.0, air.overlapping(fa))
    # B transmits (even briefly) during A's frame: it hears nothing of it.
    model, air = flat_air()
    fa = air.add(1, 5.0, 0.0, 0.0, 0.0, AIRTIME)
    air.add(2, 10.0, 0.0, 0.0, AIRTIME - 1e-4, 2 * AIRTIME)
    assert not air.survives(fa, s, 2, 10.0, 0.0, air.overlapping(fa))
    # Without capture (bench mac's collision domain), any overlap destroys.
    model, air = flat_air(None)
    fa = air.add(1, 5.0, 0.0, 0.0, 0.0, AIRTIME)
    air.add(3, 30.0, 0.0, -25.0, 0.001, 0.002)  # 40 dB weaker, in the next cell
    assert not air.survives(fa, s, 2, 10.0, 0.0, air.overlapping(fa))


def test_csma_state_machine_follows_802_15_4_unslotted() -> None:
    p = mac_params(CC2420)
    assert (p.min_be, p.max_be, p.max_backoffs) == (3, 5, 4)
    assert (p.unit_backoff_s, p.cca_s, p.turnaround_s) == (320e-6, 128e-6, 192e-6)
    m = MacSender(p, RadioModel(CC2420, 1).backoff_link_hash(7))
    t = m.begin(seq=5, attempt=0, now=1.0)
    slots = (t - 1.0 - p.cca_s) / p.unit_backoff_s
    assert 0 <= round(slots) < 8 and slots == pytest.approx(round(slots))
    assert m.cca(False, t) == (TRANSMIT, t + p.turnaround_s)
    # Busy: back off with BE 4, 5, 5, 5, then give up after macMaxCSMABackoffs.
    m.begin(seq=5, attempt=0, now=1.0)
    now = 1.0
    for be in (4, 5, 5, 5):
        action, t = m.cca(True, now)
        assert action == SENSE and m.be == be
        assert -1e-6 <= (t - now - p.cca_s) / p.unit_backoff_s < 2**be
        now = t
    assert m.cca(True, now) == (GIVE_UP, now)
    # Same seed, same draws (both media decide alike); another attempt, another draw.
    m2 = MacSender(p, RadioModel(CC2420, 1).backoff_link_hash(7))
    assert m2.begin(5, 0, 1.0) == MacSender(p, m2.stream).begin(5, 0, 1.0)
    draws = {MacSender(p, m2.stream).begin(s, 0, 0.0) for s in range(50)}
    assert len(draws) == 8  # every one of the 2^3 initial slots is used
    # ALOHA: no assessment, the model's backoff as before.
    a = MacSender(mac_params(CC2420, "aloha"), m2.stream)
    assert not a.senses
    assert a.begin(5, 1, 2.0) == 2.0 + RadioModel(CC2420, 1).backoff_s(7, 5, 1)
    assert mac_params(CC1000).carrier_sense is False
    with pytest.raises(ValueError, match="unknown mac 'tdma'"):
        mac_params(CC2420, "tdma")


def line(xs: list[float], **medium: str) -> tuple[VirtualNetwork, list[Recorder]]:
    net = VirtualNetwork(RadioModel(FLAT, 3), 3, **medium)
    cores = [Recorder(i) for i in range(len(xs))]
    for c, x in zip(cores, xs, strict=True):
        net.add(c, Static(x, 0.0))
    return net, cores


def send_at(net: VirtualNetwork, core: Recorder, t: float, n: int = 100) -> None:
    frame = bytes([core.node_id]) * n

    def go() -> None:
        net.call(core.node_id, lambda: core.out.append(Transmission.broadcast(frame)))

    net.call_at(t, go)


def test_cca_defers_a_sender_that_hears_a_frame_in_progress() -> None:
    # A (0), B (1), C (2) within 10 m of each other; C wants to send 0.5 ms into A's frame.
    net, (a, b, c) = line([0.0, 5.0, 10.0])
    send_at(net, a, 0.0)
    while not net._air.frames:  # until A found the channel clear (start = that + 192 us)
        net.run_until(net.now + 1e-4)
    start_a = net._air.frames[0].start
    send_at(net, c, net.now + 0.0005)  # C's first assessment falls inside A's frame
    net.run_until(1.0)
    k = net.counters
    assert k[2].cca_busy >= 1 and k[0].cca_busy == 0
    assert sorted(g[0][0] for g in b.got) == [0, 2]  # B got both: no collision
    assert all(k[i].collisions == 0 for i in k)
    f_c = b.got[1][2] if b.got[1][0][0] == 2 else b.got[0][2]
    assert f_c >= start_a + 2 * AIRTIME  # C's frame ended at least an airtime after A's
    # The same with ALOHA: C does not listen, the frames overlap, B loses both.
    net, (a, b, c) = line([0.0, 5.0, 10.0], mac="aloha")
    send_at(net, a, 0.0)
    send_at(net, c, 0.0005)
    net.run_until(1.0)
    assert b.got == [] and net.counters[1].collisions == 2
    assert net.counters[0].collisions == 1 and net.counters[2].collisions == 1  # deaf
    # And with collisions off, everyone gets everything (the old medium).
    net, (a, b, c) = line([0.0, 5.0, 10.0], mac="aloha", collisions="none")
    send_at(net, a, 0.0)
    send_at(net, c, 0.0005)
    net.run_until(1.0)
    assert len(b.got) == 2 and len(a.got) == len(c.got) == 1


def test_a_hidden_terminal_collides() -> None:
    # A (0) and C (2) 24 m apart: beyond range (20.9 m without shadowing), so neither
    # senses the other; B (1) halfway hears both at equal power.
    assert FLAT.airtime_s(100) > 8 * 320e-6 + 128e-6  # initial backoffs cannot avoid overlap
    assert RadioModel(FLAT, 3).max_range_m(0.0) < 24.0
    net, (a, b, c) = line([0.0, 12.0, 24.0])
    send_at(net, a, 0.0)
    send_at(net, c, 0.0)
    net.run_until(1.0)
    k = net.counters
    assert k[0].cca_busy == k[2].cca_busy == 0  # both found the channel clear
    assert b.got == [] and k[1].collisions == 2 and k[1].frames_rx == 0
    assert k[0].frames_tx == k[2].frames_tx == 1
    # Move C within A's carrier sense range: the second one defers, B gets both.
    net, (a, b, c) = line([0.0, 8.0, 16.0])
    send_at(net, a, 0.0)
    send_at(net, c, 0.0)
    net.run_until(1.0)
    assert len(b.got) == 2 and net.counters[1].collisions == 0
    assert net.counters[0].cca_busy + net.counters[2].cca_busy >= 1


def test_channel_access_failure_drops_the_frame_and_reports_a_unicast() -> None:
    # A jammer (0) transmits back to back with ALOHA timing via inject; B (1) never
    # finds the channel clear within its 5 assessments.
    net, (_, b) = line([0.0, 3.0])
    p = net.mac_params
    for k in range(40):
        net.call_at(k * 0.001, lambda: net.inject(0, b"\xff" * 100))
    net.call_at(0.004, lambda: net.call(1, lambda: b.out.append(Transmission.unicast(b"x", 0))))
    net.run_until(1.0)
    c = net.counters[1]
    assert c.mac_drops == 1 and c.cca_busy == p.max_backoffs + 1 and c.frames_tx == 0
    assert [(tx.dest, ok) for tx, ok, _ in b.results] == [(0, False)]


def test_deployment_keys_mac_and_collisions(tmp_path: Path) -> None:
    base = 'area = [10.0, 10.0]\n[[nodes]]\nid = 1\nkind = "tmote"\nposition = [1.0, 1.0]\n'
    f = tmp_path / "d.toml"
    f.write_text(base)
    d = load_deployment(f)
    assert (d.mac, d.collisions) == ("csma", "sinr")
    f.write_text('mac = "aloha"\ncollisions = "none"\n' + base)
    d = load_deployment(f)
    assert (d.mac, d.collisions) == ("aloha", "none")
    net = VirtualNetwork(d.radio_model(), d.seed, mac=d.mac, collisions=d.collisions)
    assert net.mac_params.kind == "aloha" and net.collisions == "none"
    f.write_text('mac = "tdma"\n' + base)
    with pytest.raises(DeploymentError, match=r"d.toml: unknown mac 'tdma' \(known: csma, aloha\)"):
        load_deployment(f)
    f.write_text('collisions = "maybe"\n' + base)
    with pytest.raises(DeploymentError, match=r"unknown collisions 'maybe' \(known: sinr, none"):
        load_deployment(f)
    with pytest.raises(ValueError, match="unknown collisions 'x'"):
        VirtualNetwork(RadioModel(CC2420, 1), 1, collisions="x")
    assert math.isfinite(CC2420.capture_threshold_db)


def test_bench_mac_aloha_follows_theory_and_csma_doubles_it() -> None:
    from awaremw.bench import mac as bench

    r = bench.run(senders=30, frame_times=4000, sweep=(0.25, 0.5, 1.0, 1.5))
    for pt in r["aloha"]:
        assert abs(pt["S"] - pt["G"] * math.exp(-2 * pt["G"])) < 0.03, pt
        assert pt["G_tx"] == pytest.approx(pt["G"], abs=0.06)
    assert r["aloha_max_error"] < 0.03
    assert r["csma_best"] >= 2 * r["aloha_best"]
    assert r["theory"][1] == {"G": 0.5, "S": 0.5 * math.exp(-1.0)}


def test_air_decides_the_same_whatever_order_frames_are_learnt_in() -> None:
    # The Zenoh medium learns of frames late and out of order (envelopes from many
    # processes); deciding after end + guard must not depend on that order.
    import random

    rnd = random.Random(4)
    frames = [
        (i, rnd.uniform(0, 40), rnd.uniform(0, 40), rnd.choice((-10.0, -5.0, 0.0)),
         rnd.uniform(0, 0.02))
        for i in range(1, 30)
    ]  # fmt: skip
    receivers = [(100 + k, rnd.uniform(0, 40), rnd.uniform(0, 40)) for k in range(10)]

    def decisions(order: list[int]) -> list[bool]:
        model, air = flat_air()
        on = {}
        for j in order:
            src, x, y, txp, t0 = frames[j]
            on[src] = air.add(src, x, y, txp, t0, t0 + AIRTIME)
        out = []
        for src, x, y, txp, _ in frames:
            f = on[src]
            others = air.overlapping(f)
            for rid, rx, ry in receivers:
                s = model.mean_rssi(src, rid, math.hypot(rx - x, ry - y), txp)
                out.append(air.survives(f, s, rid, rx, ry, others))
        return out

    first = decisions(list(range(len(frames))))
    shuffled = list(range(len(frames)))
    rnd.shuffle(shuffled)
    assert decisions(shuffled) == first
    assert 0 < sum(first) < len(first)  # some captured, some lost: the test means something


def test_a_retransmission_backs_off_over_the_wide_window() -> None:
    """CC2420: a first attempt waits 0..7 unit backoffs (macMinBE 3); a retransmission
    0..31 (retry_be = macMaxBE 5), so that hidden senders that collided and retry
    after the same ACK timeout rarely meet again. ALOHA keeps its uniform backoff."""
    p = mac_params(CC2420, "csma")
    assert p.retry_be == 5 and p.min_be == 3
    first, retry = set(), set()
    for src in range(40):
        m = MacSender(p, src * 7919 + 1)
        for seq in range(50):
            first.add(round((m.begin(seq, 0, 1.0) - 1.0 - p.cca_s) / p.unit_backoff_s))
            retry.add(round((m.begin(seq, 1, 1.0) - 1.0 - p.cca_s) / p.unit_backoff_s))
    assert first == set(range(8))
    assert retry == set(range(32))
    a = mac_params(CC2420, "aloha")
    m = MacSender(a, 12345)
    assert 0.0 <= m.begin(3, 2, 0.0) < a.aloha_backoff_s
    with pytest.raises(ValueError, match="retry_be"):
        dataclasses.replace(p, retry_be=6)


def test_the_air_answers_from_the_cells_around_and_forgets_in_order() -> None:
    """Frames are kept by cell: overlapping and carrier sense see the same frames,
    in the order they were added, as a scan of every frame would; pruning forgets
    exactly the frames that ended before the horizon."""
    import random

    from awaremw.radio.model import cell_of

    rng = random.Random(4)
    model = RadioModel(CC2420, 5)
    cs = model.cell_size_m
    air = Air(model, 4.0, horizon_s=0.01)
    frames = []
    for i in range(400):
        t = rng.uniform(0.0, 0.05)
        x, y = rng.uniform(0, 12 * cs), rng.uniform(0, 12 * cs)
        frames.append(air.add(i, x, y, 0.0, t, t + rng.uniform(0.0005, 0.004)))
    assert len(air) == 400 and air.frames == frames
    for f in frames[:60]:
        want = [
            o
            for o in frames
            if o.end > f.start and o.start < f.end and o is not f
            and abs(o.cell[0] - f.cell[0]) <= 2 and abs(o.cell[1] - f.cell[1]) <= 2
        ]  # fmt: skip
        assert air.overlapping(f) == want
        c = cell_of(f.x, f.y, cs)
        near = any(
            o.end > f.start and o.start < f.end and o.src != f.src
            and abs(o.cell[0] - c[0]) <= 1 and abs(o.cell[1] - c[1]) <= 1
            for o in frames
        )  # fmt: skip
        assert air.any_near(f.src, c, f.start, f.end) == near
    air.prune(0.03)
    kept = [f for f in frames if f.end >= 0.02]
    assert air.frames == kept and len(air) == len(kept)


def test_a_static_senders_frames_share_its_mean_powers_but_not_a_moving_receivers() -> None:
    model = RadioModel(CC2420, 3)
    air = Air(model, 4.0, 0.01)
    shared: dict[int, float] = {}
    a = air.add(1, 0.0, 0.0, 0.0, 0.0, 0.004, mw=shared)
    b = air.add(1, 0.0, 0.0, 0.0, 0.01, 0.014, mw=shared)  # the same sender, standing still
    fresh = air.add(1, 0.0, 0.0, 0.0, 0.02, 0.024)  # its own map
    want = 10.0 ** (model.mean_rssi(1, 2, 10.0, 0.0) / 10.0)
    assert air.power_mw(a, 2, 10.0, 0.0) == want == air.power_mw(fresh, 2, 10.0, 0.0)
    assert shared == {2: want} and b.mw_cache is shared  # b reads what a computed
    # A moving receiver's power is kept for the frame only: the next frame of the
    # sender computes it where the receiver stands then.
    here = air.power_mw(a, 5, 20.0, 0.0, moving=True)
    there = air.power_mw(b, 5, 30.0, 0.0, moving=True)
    assert 5 not in shared and here > there > 0.0
    assert there == 10.0 ** (model.mean_rssi(1, 5, 30.0, 0.0) / 10.0)
