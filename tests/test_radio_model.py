"""The radio model against its formulas (docs/radio.md)."""

from __future__ import annotations

import dataclasses
import itertools
import math
import statistics

import pytest

from awaremw.radio.counters import Battery, MoteCounters
from awaremw.radio.model import (
    CC1000,
    CC2420,
    PRESETS,
    Z_MAX,
    RadioModel,
    ber_ncfsk,
    ber_oqpsk,
    cell_of,
    packet_key,
    preset,
)


def binomial_ok(successes: int, n: int, p: float, sigmas: float = 4.5) -> bool:
    sd = math.sqrt(max(n * p * (1 - p), 1e-9))
    return abs(successes - n * p) <= sigmas * sd + 1


@pytest.mark.parametrize("p", list(PRESETS.values()), ids=list(PRESETS))
def test_mean_rssi_is_log_distance_minus_static_shadow(p: object) -> None:
    assert isinstance(p, type(CC2420))
    m = RadioModel(p, seed=7)
    for d in (1.0, 2.5, 10.0, 33.0):
        pl = p.pl_d0_db + 10 * p.path_loss_exponent * math.log10(d / p.d0_m)
        assert m.path_loss_db(d) == pytest.approx(pl)
        assert m.mean_rssi(3, 4, d, -5.0) == pytest.approx(-5.0 - pl - m.static_shadow_db(3, 4))
    # Very short distances are clamped instead of blowing up.
    assert math.isfinite(m.path_loss_db(0.0))
    # Static shadowing is N(0, sigma) over links.
    shadows = [m.static_shadow_db(a, a + 1) for a in range(0, 8000, 2)]
    assert abs(statistics.fmean(shadows)) < 0.2
    assert statistics.pstdev(shadows) == pytest.approx(p.shadowing_sigma_db, rel=0.05)


def test_symmetry_option() -> None:
    sym = RadioModel(CC2420, seed=3, symmetric=True)
    asym = RadioModel(CC2420, seed=3, symmetric=False)
    pairs = [(a, a + 17) for a in range(200)]
    assert all(sym.mean_rssi(a, b, 12, 0) == sym.mean_rssi(b, a, 12, 0) for a, b in pairs)
    differ = sum(asym.mean_rssi(a, b, 12, 0) != asym.mean_rssi(b, a, 12, 0) for a, b in pairs)
    assert differ > 190
    # Per-packet fading is never symmetric.
    k = packet_key(5)
    assert sum(sym.rssi(a, b, 12, 0, k) != sym.rssi(b, a, 12, 0, k) for a, b in pairs) > 190


def test_reproducible_by_seed_and_only_by_seed() -> None:
    def outcomes(seed: int) -> list[tuple[bool, float]]:
        m = RadioModel(CC1000, seed)
        keys = [packet_key(s, a) for s in range(300) for a in (0, 1)]
        return [m.reception(1, 2, 28.0, 0.0, 30, k) for k in keys]

    first = outcomes(11)
    # A fresh model (another process would do the same) gives the same draws,
    # also after unrelated calls on the model in between.
    m = RadioModel(CC1000, 11)
    for s in range(50):
        m.reception(9, 8, 5.0, 0.0, 10, packet_key(s))
    again = [m.reception(1, 2, 28.0, 0.0, 30, packet_key(s, a)) for s in range(300) for a in (0, 1)]
    assert first == again == outcomes(11)
    assert first != outcomes(12)
    # Attempts of the same sequence are independent draws.
    assert len({r for _, r in first}) > 500


@pytest.mark.parametrize("p", list(PRESETS.values()), ids=list(PRESETS))
def test_prr_monotonic_in_rssi_and_length(p: object) -> None:
    assert isinstance(p, type(CC2420))
    m = RadioModel(p, seed=0)
    rssis = [p.sensitivity_dbm - 5 + 0.05 * i for i in range(600)]
    for n in (1, 30, p.mtu):
        values = [m.prr(r, n) for r in rssis]
        assert all(a <= b for a, b in itertools.pairwise(values))
        assert values[0] == 0.0 and values[-1] == 1.0
    for r in rssis:
        assert m.prr(r, 10) >= m.prr(r, p.mtu)
    assert m.prr(p.sensitivity_dbm - 0.01, 1) == 0.0


def test_prr_formula() -> None:
    m = RadioModel(CC1000, seed=0)
    rssi = -96.0
    snr = 10 ** ((rssi - CC1000.noise_floor_dbm) / 10)
    ber = 0.5 * math.exp(-snr / 2 * CC1000.noise_bandwidth_hz / CC1000.bitrate_bps)
    assert ber_ncfsk(snr, CC1000.noise_bandwidth_hz / CC1000.bitrate_bps) == pytest.approx(ber)
    assert m.prr(rssi, 20) == pytest.approx((1 - ber) ** (8 * (20 + CC1000.phy_overhead_bytes)))
    assert 0.1 < m.prr(rssi, 20) < 0.95  # the transitional region is real for the CC1000
    # 802.15.4 O-QPSK: BER 0.5 at SNR 0 (linear), falling fast above 0 dB.
    assert ber_oqpsk(0.0) == pytest.approx(0.5)
    assert ber_oqpsk(1.0) == pytest.approx(1.6e-4, rel=0.05)
    assert ber_oqpsk(10**0.3) < 1e-8


@pytest.mark.parametrize("fading", [0.0, 1.5])
def test_empirical_loss_matches_prr(fading: float) -> None:
    p = dataclasses.replace(CC1000, fading_sigma_db=fading)
    m = RadioModel(p, seed=5)
    frame_len = 24
    # Place the link so that its mean RSSI (with its static shadow) is -95.5 dBm.
    pl = 95.5 - m.static_shadow_db(1, 2)
    distance = p.d0_m * 10 ** ((pl - p.pl_d0_db) / (10 * p.path_loss_exponent))
    mean = m.mean_rssi(1, 2, distance, 0.0)
    assert mean == pytest.approx(-95.5)
    if fading == 0.0:
        expected = m.prr(mean, frame_len)
    else:
        # The fading index is uniform over the deviate table: exact expectation.
        from awaremw.radio import model as mod

        table = mod.NORMAL
        expected = statistics.fmean(m.prr(mean - fading * z, frame_len) for z in table)
    assert 0.05 < expected < 0.95, "pick a distance inside the transitional region"
    n = 20000
    ok = sum(m.reception(1, 2, distance, 0.0, frame_len, packet_key(s))[0] for s in range(n))
    assert binomial_ok(ok, n, expected)
    # The per-packet RSSI is N(mean, fading sigma).
    rssis = [m.rssi(1, 2, distance, 0.0, packet_key(s)) for s in range(5000)]
    assert statistics.fmean(rssis) == pytest.approx(mean, abs=0.1)
    assert statistics.pstdev(rssis) == pytest.approx(fading, abs=0.06)


def test_max_range_bounds_delivery() -> None:
    m = RadioModel(CC2420, seed=1)
    r0 = m.max_range_m(0.0)
    sigma = math.hypot(CC2420.shadowing_sigma_db, CC2420.fading_sigma_db)
    assert m.path_loss_db(r0) == pytest.approx(0.0 - CC2420.sensitivity_dbm + 3 * sigma)
    assert m.max_range_m(-10.0) < r0
    assert m.cell_size_m == m.max_range_m(CC2420.max_tx_power_dbm)
    # Nothing beyond the range, even on links with lucky shadowing.
    for a in range(300):
        for s in range(5):
            assert not m.reception(a, a + 1, r0 * 1.001, 0.0, 10, packet_key(s))[0]
    # never_delivers is exact: the best fading draw cannot reach sensitivity.
    limit = CC2420.sensitivity_dbm - CC2420.fading_sigma_db * Z_MAX
    assert m.never_delivers(limit - 0.01) and not m.never_delivers(limit + 0.01)
    assert cell_of(-0.5, 2 * r0 + 1, r0) == (-1, 2)


def test_ack_and_backoff_draws() -> None:
    m = RadioModel(CC2420, seed=4)
    key = packet_key(9, 2)
    assert packet_key(9, 2, ack=True) != key
    ok, _ = m.ack_reception(2, 1, 5.0, 0.0, packet_key(9, 2, ack=True))
    assert ok  # 5 m at 0 dBm on a CC2420 never fails
    b = [m.backoff_s(1, s, 0) for s in range(1000)]
    assert all(0 <= x < CC2420.mac_backoff_s for x in b)
    assert statistics.fmean(b) == pytest.approx(CC2420.mac_backoff_s / 2, rel=0.1)
    assert b == [RadioModel(CC2420, seed=4).backoff_s(1, s, 0) for s in range(1000)]
    with pytest.raises(ValueError):
        packet_key(1, 200)


def test_airtime_and_energy() -> None:
    p = CC2420
    assert p.airtime_s(100) == pytest.approx((100 + 17) * 8 / 250_000)
    assert p.tx_energy_mj(20) == pytest.approx(3.0 * 17.4 * (37 * 8 / 250_000))
    assert p.rx_energy_mj(20) == pytest.approx(3.0 * 18.8 * (37 * 8 / 250_000))
    assert p.tx_current_at(-25) == 8.5 and p.tx_current_at(-2) == pytest.approx((15.2 + 16.5) / 2)
    assert p.tx_current_at(None) == 17.4 and p.tx_current_at(-40) == 8.5
    c = MoteCounters(frames_tx=2, bytes_tx=40, frames_rx=3, bytes_rx=60, acks_tx=1, acks_rx=2)
    tx_bits = 8 * (40 + 2 * 17 + 1 * 11)
    rx_bits = 8 * (60 + 3 * 17 + 2 * 11)
    expected = 3.0 * (17.4 * tx_bits + 18.8 * rx_bits) / 250_000
    assert c.energy_mj(p) == pytest.approx(expected)
    assert c.energy_mj(p, -25.0) < c.energy_mj(p)
    assert c.as_dict()["frames_tx"] == 2 and len(c.as_dict()) == 17  # MAC counters too
    total = MoteCounters()
    total.add(c)
    total.add(c)
    assert total.bytes_rx == 120
    bat = Battery(budget_mj=expected * 1.5)
    assert not bat.is_dead(c, p)
    c.frames_tx += 10
    c.bytes_tx += 500
    assert bat.is_dead(c, p)
    with pytest.raises(ValueError):
        Battery(0)


def test_presets() -> None:
    assert preset("cc2420") is CC2420 and preset("cc1000") is CC1000
    with pytest.raises(ValueError, match="cc2420"):
        preset("nrf24")
    with pytest.raises(ValueError):
        CC2420.check_tx_power(3.0)
    CC1000.check_tx_power(3.0)
    assert CC2420.mtu + CC2420.phy_overhead_bytes <= 127 + 6  # fits an 802.15.4 PHY frame
    with pytest.raises(ValueError):
        dataclasses.replace(CC2420, modulation="ook")
