"""Real links (docs/radio.md, "Noise", "Hardware variance", "Links files").

Noise from a trace by closest-pattern matching, per-mote hardware variance,
topologies from links files (TOSSIM's format and measured probabilities), the
deployment keys that choose them, and the benchmarks that hold the models
against reality: ``bench noise`` and ``bench links``.
"""

from __future__ import annotations

import argparse
import math
import random
import statistics
import subprocess
import sys
from pathlib import Path

import pytest

from awaremw.bench import links as bench_links
from awaremw.bench import noise as bench_noise
from awaremw.radio.environment import RadioSettings, environment_of, radio_model
from awaremw.radio.links import LinksError, load_links, parse_links
from awaremw.radio.model import CC1000, CC2420, NO_LINK_DBM
from awaremw.radio.noise import (
    HORIZON_MS,
    HardwareVariance,
    NoiseTraceError,
    TraceNoise,
    load_trace,
)
from awaremw.runtime.deployment import DeploymentError, load, parse_deployment

# --------------------------------------------------------------------------- traces


def bursty_trace(path: Path, n: int = 150_000, seed: int = 3) -> Path:
    """Another trace in TOSSIM's format: a quiet floor and noise bursts (a
    two-state Markov chain), a trailing space on every line and blank lines at
    the end, as meyer-heavy.txt has them."""
    rnd = random.Random(seed)
    s = 0
    out = []
    for _ in range(n):
        if s == 0 and rnd.random() < 0.003:
            s = 1
        elif s == 1 and rnd.random() < 0.02:
            s = 0
        out.append(round(rnd.gauss(-96, 1.0)) if s == 0 else round(rnd.gauss(-78, 4.0)))
    path.write_text("".join(f"{v} \n" for v in out) + "\n\n", encoding="utf-8")
    return path


def noise_args(trace: str, seconds: float, seed: int = 1) -> argparse.Namespace:
    return argparse.Namespace(trace=trace, seconds=seconds, seed=seed, seeds=None, plot=None)


def test_the_shipped_trace_is_matched_in_distribution_and_autocorrelation() -> None:
    r = bench_noise.run(noise_args("meyer-heavy", 200.0))
    assert r["readings"] == 200_000
    assert r["ks"] <= 0.05
    assert r["acf_max_diff"] <= 0.1
    # Not a flat line: the trace's lag-1 autocorrelation (about 0.48) is kept.
    assert r["acf_model"][0] > 0.4


def test_any_trace_in_that_format_is_matched_too(tmp_path: Path) -> None:
    path = bursty_trace(tmp_path / "bursty.txt")
    r = bench_noise.run(noise_args(str(path), 100.0, seed=2))
    assert r["ks"] <= 0.05
    assert r["acf_max_diff"] <= 0.1
    assert r["acf_trace"][0] > 0.8  # a strongly correlated trace, so the check can fail


def test_a_chain_asked_seldom_says_what_it_says_when_asked_every_millisecond() -> None:
    # The chain skips the readings nobody asks for (radio/noise.py, Cpm.advance):
    # asked within the horizon, it is the same chain as one asked every ms.
    trace = load_trace("meyer-heavy")
    every = TraceNoise(trace, 5, -98.0)
    seldom = TraceNoise(trace, 5, -98.0)
    dense = [every.reading(7, ms) for ms in range(20_000)]
    rnd = random.Random(1)
    ms = 0
    while ms < 20_000:
        assert seldom.reading(7, ms) == dense[ms]
        ms += rnd.randint(1, HORIZON_MS)


def test_the_receptions_fast_path_draws_what_the_general_one_draws() -> None:
    # TraceNoise.over inlines the forward question (the reception hot path): on
    # a twin source asked the same questions through at(), the same readings,
    # whatever the order (forward within and past the horizon, the same
    # instant again, slightly in the past, far in the past, a first question).
    trace = load_trace("meyer-heavy")
    hw = HardwareVariance(3)
    fast, general = TraceNoise(trace, 9, -98.0, hw), TraceNoise(trace, 9, -98.0, hw)
    rnd = random.Random(4)
    t = {m: 0.0 for m in range(5)}
    kinds = set()
    for _ in range(20_000):
        m = rnd.randrange(5)
        step = rnd.choice((0.0, 0.0004, 0.003, 0.02, 0.031, 0.2, -0.002, -5.0))
        t[m] = max(0.0, t[m] + step)
        kinds.add(step)
        assert fast.over(m, t[m] - 0.001, t[m]) == general.at(m, t[m])
    assert len(kinds) == 8


def test_noise_is_a_function_of_seed_mote_and_instant() -> None:
    trace = load_trace("meyer-heavy")
    a = [TraceNoise(trace, 1, -98.0).at(3, t / 100) for t in range(500)]
    b = [TraceNoise(trace, 1, -98.0).at(3, t / 100) for t in range(500)]
    c = [TraceNoise(trace, 2, -98.0).at(3, t / 100) for t in range(500)]
    assert a == b
    assert a != c
    # Placed at the preset's floor: the trace's most common reading is the floor.
    cc1000 = TraceNoise(trace, 1, CC1000.noise_floor_dbm)
    assert cc1000.level(3) == CC1000.noise_floor_dbm


@pytest.mark.parametrize(
    ("text", "error"),
    [
        ("-90\n" * 300 + "loud\n", "line 301: 'loud' is not a reading in dBm"),
        ("-90\n" * 300 + "nan\n", "line 301: 'nan' is not a finite reading"),
        ("-90\n" * 300 + "900\n", "reading 301 is 900.0, outside -200..50 dBm"),
        ("-90\n" * 10, "10 readings; a trace needs 200"),
    ],
)
def test_a_bad_trace_is_refused_with_where_and_why(tmp_path: Path, text: str, error: str) -> None:
    p = tmp_path / "t.txt"
    p.write_text(text, encoding="utf-8")
    with pytest.raises(NoiseTraceError) as e:
        load_trace(p)
    assert error in str(e.value)


# --------------------------------------------------------------------------- hardware


def test_hardware_offsets_have_linklayermodels_covariance() -> None:
    hw = HardwareVariance(seed=4)
    pairs = [hw.offsets(n) for n in range(4000)]
    noise = [p[0] for p in pairs]
    power = [p[1] for p in pairs]
    assert abs(statistics.fmean(noise)) < 0.15 and abs(statistics.fmean(power)) < 0.15
    assert statistics.variance(noise) == pytest.approx(3.7, rel=0.1)
    assert statistics.variance(power) == pytest.approx(6.0, rel=0.1)
    assert statistics.covariance(noise, power) == pytest.approx(-3.3, rel=0.15)
    assert HardwareVariance(seed=4).offsets(17) == pairs[17]  # seeded, per mote


def test_hardware_variance_makes_links_asymmetric() -> None:
    plain = radio_model(CC2420, 3)
    hw = radio_model(CC2420, 3, RadioSettings(hardware_variance=True))
    assert plain.mean_rssi(1, 2, 20.0, 0.0) == plain.mean_rssi(2, 1, 20.0, 0.0)
    assert hw.mean_rssi(1, 2, 20.0, 0.0) != hw.mean_rssi(2, 1, 20.0, 0.0)
    # Offsets spread the links: the range (and the cells) grow with them.
    assert hw.max_range_m() > plain.max_range_m()


def test_grid_links_turn_asymmetric_with_hardware_variance_and_bursty_with_a_trace() -> None:
    def measure(**kw: object) -> dict[str, object]:
        a = argparse.Namespace(deployment="grid_small", links=None, beacons=1000, interval=0.02,
                               radio="cc2420", seed=None, noise=None, hardware_variance=None,
                               plot=None)  # fmt: skip
        for k, v in kw.items():
            setattr(a, k, v)
        return bench_links.run(a)

    white = measure()
    hw = measure(hardware_variance=True)
    trace = measure(noise="meyer-heavy")
    assert white["asymmetric"] == 0.0
    assert hw["asymmetric"] >= 0.1
    assert white["beta_links"] >= 20 and trace["beta_links"] >= 20
    assert abs(white["beta_median"]) < 0.1  # independent losses
    assert trace["beta_median"] > white["beta_median"] + 0.2  # bursts


# --------------------------------------------------------------------------- links files


@pytest.mark.parametrize(
    ("text", "error"),
    [
        (" 1 2 0.5\n 1 2 0.6\n", "line 2: a second probability for 1 -> 2"),
        (" 1 2 1.5\n", "line 1: probability 1.5 is outside 0..1"),
        (" 0 31 \n", "line 1: expected 'gain SRC DST DBM'"),
        ("gain 1 2 -80\n 1 2 0.5\n", "gain lines and probability triples in one file"),
        ("gain 1 2\n", "line 1: a gain line is 'gain SRC DST DBM'"),
        ("gain 1 70000 -80\n", "line 1: mote id 70000 is outside 0..65533"),
        ("noise 1 -100 4\n", "no links"),
        (" 1 2 0.5\nnoise 1 -100 4\n", "noise lines go with gain lines"),
    ],
)
def test_a_bad_links_file_is_refused_with_its_line(text: str, error: str) -> None:
    with pytest.raises(LinksError) as e:
        parse_links(text, "f.txt")
    assert error in str(e.value)


def test_a_missing_link_never_delivers_and_a_given_gain_is_the_mean_rssi(tmp_path: Path) -> None:
    p = tmp_path / "topo.txt"
    p.write_text("gain 1 2 -70.5\ngain 2 1 -80.0\nnoise 1 -100 0\nnoise 2 -100 0\n")
    m = radio_model(CC2420, 1, RadioSettings(links=str(p)))
    assert m.mean_rssi(1, 2, 9999.0, 0.0) == -70.5  # positions say nothing
    assert m.mean_rssi(2, 1, 1.0, -5.0) == -85.0  # TX power adds to the gain
    assert m.mean_rssi(1, 3, 1.0, 0.0) == NO_LINK_DBM
    assert m.never_delivers(m.mean_rssi(1, 3, 1.0, 0.0))


def tossim_topology(path: Path) -> tuple[Path, dict[tuple[int, int], float]]:
    """A topology in TOSSIM's format: receivers 10 and 20 with different noise
    lines, senders 1..8 at gains from 25 dB above to 12 dB below each one's
    noise mean. Returns the path and every link's margin over its receiver's
    noise mean (dB)."""
    noise = {10: (-100.0, 4.0), 20: (-84.0, 4.0)}
    margins = (25.0, 20.0, 12.0, 6.0, 0.0, -5.0, -6.0, -12.0)
    lines = ["% written as TOSSIM's LinkLayerModel writes linkgain.out"]
    out = {}
    for rx, (mean, _) in noise.items():
        for k, margin in enumerate(margins, 1):
            lines.append(f"gain\t{k}\t{rx}\t{mean + margin:.2f}")
            out[(k, rx)] = margin
    for node in (*range(1, len(margins) + 1), *noise):
        mean, rng = noise.get(node, (-100.0, 4.0))
        lines.append(f"noise\t{node}\t{mean:.2f}\t{rng:.2f}")
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path, out


def test_a_tossim_topology_runs_as_given_with_each_receivers_noise_line(tmp_path: Path) -> None:
    path, margins = tossim_topology(tmp_path / "linkgain.out")
    a = argparse.Namespace(deployment=None, links=str(path), beacons=1000, interval=0.02,
                           radio="cc2420", seed=None, noise=None, hardware_variance=None,
                           plot=None)  # fmt: skip
    r = bench_links.run(a)
    measured = {(s, d): m for s, d, _, m in r["links"]}
    for pair, margin in margins.items():
        got = measured.get(pair, 0.0)
        if margin >= 20.0:
            assert got >= 0.9, (pair, margin, got)
        # A frame holds against the noise at its start and at its end, as TOSSIM
        # checks it (docs/radio.md, "Links files"): taken at its end only, a
        # +-4 dB range let 6-7 % through at -5 dB (the 802.15.4 O-QPSK curve
        # delivers half of the frames at -1.6 dB SNR).
        if margin <= -5.0:
            assert got <= 0.05, (pair, margin, got)
    # The same gain is heard at one receiver and lost at the other: its noise line.
    assert measured[(1, 20)] >= 0.9  # -59 dBm over a -84 dBm floor
    assert measured.get((8, 20), 0.0) == 0.0


def _links_of(
    deployment: str, noise: str | None, hw: bool | None, seed: int | None, beacons: int = 200
) -> dict:
    a = argparse.Namespace(deployment=deployment, links=None, beacons=beacons, interval=0.02,
                           radio="cc2420", seed=seed, noise=noise, hardware_variance=hw,
                           plot=None)  # fmt: skip
    return bench_links.run(a)


def test_the_intel_lab_links_deliver_what_was_measured() -> None:
    r = _links_of("intel_lab", None, None, None, beacons=1000)
    assert r["within_ci_links"] >= 2000  # every measured pair of the 54 motes with p > 0
    assert r["within_ci"] >= 0.95
    assert r["asymmetric"] is not None and r["beta_median"] is not None
    f = load_links("intel-lab")
    # Our copy is the original but for its one malformed line (" 0 31 ").
    assert len(f.probabilities) == 2969 - 53  # the self pairs (" 1 1 0.0") are ignored


def test_good_parts_join_motes_over_links_good_both_ways_only() -> None:
    delivery = {
        (1, 2): 0.9, (2, 1): 0.8,  # good both ways
        (2, 3): 0.95, (3, 2): 0.5,  # good one way only: no link
        (3, 4): 0.7, (4, 3): 0.75,
        (4, 5): 0.69, (5, 4): 1.0,
    }  # fmt: skip
    good, sizes = bench_links.good_parts([1, 2, 3, 4, 5], delivery)
    assert good == {1: {2}, 2: {1}, 3: {4}, 4: {3}, 5: set()}
    assert sorted(sizes) == [1, 2, 2]


def test_under_meyer_heavy_romeo4r_falls_apart_and_romeo4r_noisy_holds() -> None:
    """romeo4r's -20 dBm field under meyer-heavy: no network to speak of (what
    romeo4r_noisy is for, docs/radio.md); at 0 dBm every mote is in one part."""
    white = _links_of("romeo4r", None, None, 2)
    assert white["largest_good_part"] == white["motes"] and white["isolated_motes"] == 0
    noisy = _links_of("romeo4r", "meyer-heavy", True, 2)
    assert noisy["good_neighbours"] < 1.0 and noisy["largest_good_part"] <= 3
    sized = _links_of("romeo4r_noisy", None, None, 2)
    assert sized["settings"] == "noise meyer-heavy, hardware variance"
    assert sized["largest_good_part"] == sized["motes"] and sized["good_neighbours"] > 8


def test_binomial_interval_is_exact_at_the_edges() -> None:
    lo, hi = bench_links.binomial_interval(1000, 0.5)
    assert (lo, hi) == (459, 541)
    assert bench_links.binomial_interval(1000, 0.0) == (0, 0)
    lo, hi = bench_links.binomial_interval(1000, 0.001)
    assert lo == 0 and 3 <= hi <= 5


def test_beta_factor_is_zero_for_independent_and_high_for_bursty_losses() -> None:
    rnd = random.Random(2)
    independent = [rnd.random() < 0.5 for _ in range(5000)]
    bursty = []
    good = True
    for _ in range(5000):
        good = (rnd.random() < 0.95) == good
        bursty.append(good and rnd.random() < 0.9)
    bi = bench_links.beta_factor(independent)
    bb = bench_links.beta_factor(bursty)
    assert bi is not None and bb is not None
    assert abs(bi) < 0.05
    assert bb > 0.5


# --------------------------------------------------------------------------- deployments

BASE = {
    "area": [50.0, 50.0],
    "nodes": [
        {"id": 1, "kind": "tmote", "position": [1.0, 1.0]},
        {"id": 2, "kind": "tmote", "position": [5.0, 1.0]},
    ],
}


def test_a_trace_is_found_next_to_the_deployment_file(tmp_path: Path) -> None:
    bursty_trace(tmp_path / "mine.txt", n=1000)
    d = parse_deployment({**BASE, "noise": "mine.txt"}, tmp_path / "dep.toml")
    assert d.radio_settings.noise == str(tmp_path / "mine.txt")
    assert d.radio_model().noise_at is not None


@pytest.mark.parametrize(
    ("extra", "error"),
    [
        ({"noise": "meyer-light"}, "noise: "),
        ({"links": "nowhere.txt"}, "links: "),
        ({"links": "intel-lab", "hardware_variance": True}, "hardware_variance applies to links"),
        ({"links": "intel-lab", "noise": "meyer-heavy"}, "would count it twice"),
        ({"links": "intel-lab"}, "has no link of mote(s)"),
    ],
)
def test_bad_realism_keys_are_refused_naming_the_key(
    tmp_path: Path, extra: dict[str, object], error: str
) -> None:
    doc = {**BASE, **extra}
    if extra.get("links") == "intel-lab" and len(extra) == 1:
        doc["nodes"] = [{"id": 60, "kind": "mica2", "position": [1.0, 1.0]}]
    with pytest.raises(DeploymentError) as e:
        parse_deployment(doc, tmp_path / "dep.toml")
    assert error in str(e.value)


def test_a_links_deployment_refuses_a_moving_mote(tmp_path: Path) -> None:
    doc = {"area": [50.0, 50.0], "links": "intel-lab",
           "nodes": [{"id": 1, "kind": "mica2", "path": [[1.0, 1.0], [5.0, 5.0]]}]}  # fmt: skip
    with pytest.raises(DeploymentError, match="a links file fixes every link"):
        parse_deployment(doc, tmp_path / "dep.toml")


def test_the_intel_lab_deployment_has_the_labs_motes_and_links() -> None:
    d = load("intel_lab")
    assert len(d.nodes) == 54
    assert d.radio == "cc1000" and d.radio_settings.links == "intel-lab"
    m = d.radio_model()
    env = environment_of(m)
    assert env is not None and env.links is not None
    assert len(env.links.gains) > 2000
    assert math.isfinite(m.max_range_m())  # one cell for every mote, not an infinite one


def test_experiment_refuses_a_trace_that_cannot_be_read(tmp_path: Path) -> None:
    done = subprocess.run(
        [sys.executable, "-m", "awaremw", "experiment", "romeo4r", "--virtual",
         "--noise", str(tmp_path / "missing.txt"), "--out", str(tmp_path / "o")],
        capture_output=True, text=True, check=False, timeout=120,
    )  # fmt: skip
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "missing.txt: cannot read" in lines[0]


def test_a_trace_asked_for_with_a_tossim_file_sits_at_each_motes_noise_line(
    tmp_path: Path,
) -> None:
    p = tmp_path / "topo.txt"
    p.write_text("gain 1 2 -70\ngain 2 1 -70\nnoise 1 -100 4\nnoise 2 -90 4\n", encoding="utf-8")
    env = environment_of(radio_model(CC2420, 1, RadioSettings("meyer-heavy", False, str(p))))
    assert env is not None and isinstance(env.noise, TraceNoise)
    # The trace's floor (its most common reading) at each mote's mean; others at the preset's.
    assert env.noise.level(1) == -100.0
    assert env.noise.level(2) == -90.0
    assert env.noise.level(3) == CC2420.noise_floor_dbm
