"""The virtual-clock driver and its in-memory medium (docs/radio.md semantics)."""

from __future__ import annotations

import dataclasses
import functools
import math
import pathlib
import random

import pytest

from awaremw.protocol.core import Transmission
from awaremw.protocol.events import MoteDown, PingResult
from awaremw.protocol.frames import BROADCAST, Hello, encode
from awaremw.protocol.hello import HelloMote
from awaremw.radio.environment import RadioSettings
from awaremw.radio.model import CC2420, RadioModel, cell_of, packet_key
from awaremw.radio.virtual_medium import VirtualNetwork
from awaremw.world.mobility import Path, Static

# --------------------------------------------------------------------------- helpers


class Recorder:
    """A silent core that records what it receives; can send on demand."""

    def __init__(self, node_id: int) -> None:
        self.node_id = node_id
        self.got: list[tuple[bytes, float, float]] = []
        self.results: list[tuple[Transmission, bool, float]] = []
        self.out: list[Transmission] = []
        self.started_at: float | None = None

    def start(self, now: float) -> None:
        self.started_at = now

    def receive(self, frame: bytes, rssi_dbm: float, now: float) -> None:
        self.got.append((frame, rssi_dbm, now))

    def handle_timer(self, now: float) -> None:
        pass

    def next_deadline(self) -> float | None:
        return None

    def drain(self) -> list[Transmission]:
        out, self.out = self.out, []
        return out

    def link_result(self, tx: Transmission, acked: bool, now: float) -> None:
        self.results.append((tx, acked, now))

    def events(self) -> list[object]:
        return []


def hello(i: int, seed: int = 0, period: float = 1.0) -> HelloMote:
    return HelloMote(i, period, random.Random(seed * 100_003 + i), CC2420.mtu)


def grid_net(n: int, seed: int, spacing: float = 12.0, **medium: str) -> VirtualNetwork:
    net = VirtualNetwork(RadioModel(CC2420, seed), seed, **medium)
    cols = math.ceil(math.sqrt(n))
    for i in range(n):
        net.add(hello(i, seed), Static(spacing * (i % cols), spacing * (i // cols)))
    return net


def send(net: VirtualNetwork, core: Recorder, frame: bytes, dest: int = BROADCAST) -> None:
    """Make a Recorder transmit now (through the driver, like any core)."""
    tx = Transmission.broadcast(frame) if dest == BROADCAST else Transmission.unicast(frame, dest)
    net.call(core.node_id, lambda: core.out.append(tx))


# --------------------------------------------------------------------------- mobility


def test_mobility_paths() -> None:
    assert Static(3, 4).position(100.0) == (3.0, 4.0)
    p = Path(((0, 0), (10, 0), (10, 10)), speed_mps=2.0, start_s=1.0, pause_s=1.0)
    assert p.position(0.0) == (0.0, 0.0)
    assert p.position(3.5) == pytest.approx((5.0, 0.0))
    assert p.position(6.5) == (10.0, 0.0)  # pausing at the waypoint
    assert p.position(9.5) == pytest.approx((10.0, 5.0))
    assert p.position(1000.0) == (10.0, 10.0)
    loop = Path(((0, 0), (10, 0)), speed_mps=1.0, loop=True)
    assert loop.duration_s == 20.0
    assert loop.position(15.0) == pytest.approx((5.0, 0.0))  # on the way back
    assert loop.position(25.0) == pytest.approx((5.0, 0.0))
    with pytest.raises(ValueError):
        Path((), 1.0)
    with pytest.raises(ValueError):
        Path(((0, 0),), 0.0)


# --------------------------------------------------------------------------- medium


def test_range_cells_and_rssi_follow_the_model() -> None:
    model = RadioModel(CC2420, seed=3)
    net = VirtualNetwork(model, 3)
    r = model.max_range_m(0.0)
    assert model.cell_size_m == pytest.approx(r)
    cores = {i: Recorder(i) for i in range(5)}
    # 0 sends; 1 is close; 2 is beyond range but in a neighbouring cell;
    # 3 is two cells away; 4 is close but never switched on.
    x0 = r * 1.5
    pos = {0: (x0, 10.0), 1: (x0 + 5, 10.0), 2: (x0 + 1.2 * r, 10.0), 3: (x0 + 2.6 * r, 10.0)}
    assert cell_of(*pos[2], r)[0] - cell_of(*pos[0], r)[0] == 1
    assert cell_of(*pos[3], r)[0] - cell_of(*pos[0], r)[0] >= 2
    for i, p in pos.items():
        net.add(cores[i], Static(*p))
    net.add(cores[4], Static(x0, 12.0), start_at=1e9)
    net.run_until(0.0)
    assert all(cores[i].started_at == 0.0 for i in range(4)) and cores[4].started_at is None
    frames = [encode(Hello(0, BROADCAST, k)) for k in range(20)]
    for f in frames:
        send(net, cores[0], f)
        net.run_until(net.now + 0.1)
    c = net.counters
    assert c[0].frames_tx == 20 and c[0].bytes_tx == sum(map(len, frames))
    assert c[1].frames_rx == 20 and [g[0] for g in cores[1].got] == frames
    assert c[2].dropped_distance == 20 and c[2].frames_rx == 0 and not cores[2].got
    assert c[3].as_dict() == c[4].as_dict() == dataclasses.asdict(type(c[3])())
    # The RSSI the core gets is the model's, for the frame's packet key (link seq k).
    for k, (_, rssi, _) in enumerate(cores[1].got):
        assert rssi == model.rssi(0, 1, 5.0, 0.0, packet_key(k))
    assert net.mean_rssi(0, 1) == model.mean_rssi(0, 1, 5.0, 0.0)


def check_accounting(
    net: VirtualNetwork, before: dict[int, dict[str, int]]
) -> dict[int, dict[str, int]]:
    """Every frame a mote sent since ``before`` was counted by every mote on the
    air in its 3x3 cells: received or lost within range, dropped beyond it."""
    now = {i: c.as_dict() for i, c in net.counters.items()}
    delta = {i: {k: v - before.get(i, {}).get(k, 0) for k, v in now[i].items()} for i in now}
    r = net.model.max_range_m(0.0)
    cs = net.cell_size
    on = [i for i in now if net.alive(i)]
    pos = {i: net.position(i) for i in on}
    for i in on:
        in_range = in_cells_beyond = 0
        for j in on:
            if j == i:
                continue
            d = math.dist(pos[i], pos[j])
            ci, cj = cell_of(*pos[i], cs), cell_of(*pos[j], cs)
            if d <= r:
                in_range += delta[j]["frames_tx"]
            elif abs(ci[0] - cj[0]) <= 1 and abs(ci[1] - cj[1]) <= 1:
                in_cells_beyond += delta[j]["frames_tx"]
        got = delta[i]["frames_rx"] + delta[i]["dropped_loss"] + delta[i]["collisions"]
        assert got == in_range
        assert delta[i]["dropped_distance"] == in_cells_beyond
    assert sum(d["frames_rx"] for d in delta.values()) > 0
    assert sum(d["dropped_loss"] for d in delta.values()) > 0
    return now


def test_every_frame_in_range_is_received_or_lost_and_bulk_counts_add_up() -> None:
    # A frame is counted by its sender and its receivers in the same event, so
    # the books balance exactly at any time.
    net = grid_net(64, seed=5, spacing=9.0)
    net.run_until(20.0)
    snap = check_accounting(net, {})
    # Topology changes at the window's start...
    net.kill(9)
    net.set_mobility(20, Static(3.0, 60.0))
    net.add(hello(70), Static(30.0, 30.0))
    # ... and mote 30 changes from static to moving (not yet) and back, in place,
    # in the middle of windows: its bulk-counted drops must be folded in.
    x, y = net.position(30)
    later = Path(((x, y), (0.0, 0.0)), 1.0, start_s=1000.0)
    net.call_at(30.0, lambda: net.set_mobility(30, later))
    net.call_at(50.0, lambda: net.set_mobility(30, Static(x, y)))
    net.run_until(40.0)
    snap = check_accounting(net, snap)
    net.run_until(60.0)
    check_accounting(net, snap)


def test_unicast_success_is_counted_once() -> None:
    net = VirtualNetwork(RadioModel(CC2420, 1), 1)
    a, b = hello(1), hello(2)
    net.add(a, Static(0, 0))
    net.add(b, Static(3, 0))
    events: list[tuple[int, object, float]] = []
    net.on_event = lambda n, e, t: events.append((n, e, t))
    net.run_until(0.0)
    tx = net.call(1, lambda: a.ping(2))
    assert tx.dest == 2
    net.run_until(0.5)
    ca, cb = net.counters[1], net.counters[2]
    assert (ca.unicast_ok, ca.unicast_failed, ca.retries, ca.acks_rx) == (1, 0, 0, 1)
    assert (cb.acks_tx, cb.duplicates, b.pings_rx) == (1, 0, 1)
    assert [e for n, e, _ in events if isinstance(e, PingResult)] == [PingResult(2, True)]


def test_unicast_out_of_range_fails_after_max_retries() -> None:
    model = RadioModel(CC2420, 1)
    net = VirtualNetwork(model, 1)
    a, b = Recorder(1), Recorder(2)
    net.add(a, Static(0, 0))
    net.add(b, Static(model.max_range_m() * 1.1, 0))  # neighbouring cell, beyond range
    net.run_until(0.0)
    sent: list[tuple[int, float]] = []
    net.on_transmit = lambda n, tx, t: sent.append((n, t))
    send(net, a, b"\x94\x01\x01\x02\x00", dest=2)
    net.run_until(1.0)
    ca, cb = net.counters[1], net.counters[2]
    p = CC2420
    assert ca.frames_tx == 1 + p.max_retries == len(sent)
    assert (ca.retries, ca.unicast_failed, ca.unicast_ok, ca.acks_rx) == (p.max_retries, 1, 0, 0)
    assert cb.dropped_distance == 1 + p.max_retries and cb.frames_rx == 0 and cb.acks_tx == 0
    [(tx, acked, t)] = a.results
    assert not acked and tx.dest == 2
    attempts = 1 + p.max_retries
    air = p.airtime_s(5)
    assert (
        attempts * (air + p.ack_timeout_s)
        <= t
        <= attempts * (air + p.ack_timeout_s + p.mac_backoff_s)
    )


def test_lost_acks_cause_retries_and_duplicates_are_dropped() -> None:
    # The receiver transmits at -25 dBm: its ACKs cannot cover the distance.
    model = RadioModel(CC2420, 2)
    d = 10.0
    assert model.max_range_m(-25.0) < d
    assert model.mean_rssi(1, 2, d, 0.0) > -88  # the data link itself is good
    net = VirtualNetwork(model, 2)
    a, b = Recorder(1), Recorder(2)
    net.add(a, Static(0, 0))
    net.add(b, Static(d, 0), tx_power_dbm=-25.0)
    net.run_until(0.0)
    send(net, a, b"\x94\x01\x01\x02\x07", dest=2)
    net.run_until(1.0)
    ca, cb = net.counters[1], net.counters[2]
    n = 1 + CC2420.max_retries
    assert len(b.got) == 1  # the core sees the frame once
    assert (cb.frames_rx, cb.duplicates, cb.acks_tx) == (n, n - 1, n)
    assert (ca.frames_tx, ca.unicast_failed, ca.acks_rx) == (n, 1, 0)
    assert a.results[0][1] is False
    # The next frame (new link sequence number) is delivered again.
    send(net, a, b"\x94\x01\x01\x02\x08", dest=2)
    net.run_until(2.0)
    assert len(b.got) == 2


def test_same_seed_same_counters() -> None:
    def run(seed: int) -> dict[int, dict[str, int]]:
        net = grid_net(100, seed)
        net.run_until(15.0)
        return {i: c.as_dict() for i, c in net.counters.items()}

    first = run(7)
    assert first == run(7)
    assert first != run(8)
    assert sum(c["frames_rx"] for c in first.values()) > 100 * 14 * 5


def test_garbage_is_counted_as_malformed_and_changes_nothing_else() -> None:
    def run(inject: bool) -> tuple[VirtualNetwork, dict[int, HelloMote]]:
        # About parsing garbage, not the channel: without carrier sense and
        # collisions, the injected frames change no other frame's fate.
        net = grid_net(25, seed=4, spacing=10.0, mac="aloha", collisions="none")
        jammer = Recorder(99)
        net.add(jammer, Static(20.0, 20.0))
        cores = {i: c for i, c in net.cores.items() if isinstance(c, HelloMote)}
        if inject:
            for k in range(10):
                garbage = bytes([0xC1, k])  # 0xC1 is never valid msgpack
                net.call_at(2.0 + k, functools.partial(net.inject, 99, garbage))
                net.call_at(2.5 + k, functools.partial(net.inject, 99, b"\x93\x01\x02"))
        net.run_until(15.0)
        return net, cores

    clean, clean_cores = run(False)
    dirty, dirty_cores = run(True)
    c0, c1 = clean.counters, dirty.counters
    heard = [i for i in c1 if i != 99 and c1[i].malformed]
    assert len(heard) >= 5
    assert c1[99].frames_tx == 20
    for i in c1:
        if i == 99:
            continue
        a, b = c0[i].as_dict(), c1[i].as_dict()
        extra = b["malformed"]
        assert b.pop("malformed") - a.pop("malformed") == extra <= 20
        assert b.pop("frames_rx") - a.pop("frames_rx") == extra
        assert b.pop("bytes_rx") >= a.pop("bytes_rx")
        assert b.pop("dropped_loss") + b.pop("dropped_distance") + extra >= a.pop(
            "dropped_loss"
        ) + a.pop("dropped_distance")
        assert a == b
        assert clean_cores[i].table == dirty_cores[i].table


def test_kill_and_add_at_runtime() -> None:
    net = grid_net(9, seed=1, spacing=8.0)
    cores = {i: c for i, c in net.cores.items() if isinstance(c, HelloMote)}
    downs: list[tuple[int, object]] = []
    net.on_event = lambda n, e, t: downs.append((n, e)) if isinstance(e, MoteDown) else None
    net.run_until(5.0)
    assert 4 in cores[0].table
    net.kill(4)
    assert not net.alive(4) and downs == [(4, MoteDown("killed"))]
    tx_at_kill = net.counters[4].frames_tx
    net.run_until(12.0)
    assert net.counters[4].frames_tx == tx_at_kill
    assert 4 not in cores[0].table  # expired after 3.5 periods
    # A new mote, and the dead one switched on again with a fresh core.
    net.add(hello(20), Static(8.0, 8.0))
    fresh = hello(4)
    net.add(fresh, Static(8.0, 8.0), start_at=13.0)
    with pytest.raises(ValueError):
        net.add(hello(20), Static(0.0, 0.0))
    net.run_until(20.0)
    assert 20 in cores[0].table and 4 in cores[0].table
    assert net.alive(4) and 0 in fresh.table
    assert net.counters[4].frames_tx > tx_at_kill  # the counters go on


def test_mobility_changes_neighbours() -> None:
    # A line of motes 10 m apart; a robot drives along it at 2 m/s.
    net = VirtualNetwork(RadioModel(CC2420, 6), 6)
    for i in range(12):
        net.add(hello(i), Static(10.0 * i, 0.0))
    robot = hello(100)
    net.add(robot, Path(((0.0, 2.0), (110.0, 2.0)), speed_mps=2.0, start_s=5.0))
    net.run_until(5.0)
    assert 0 in robot.table and 11 not in robot.table
    assert 100 in net.cores[0].table  # type: ignore[attr-defined]
    net.run_until(70.0)
    assert 11 in robot.table and 0 not in robot.table
    assert 100 not in net.cores[0].table  # type: ignore[attr-defined]
    assert net.position(100) == (110.0, 2.0)
    # A new path takes it back.
    net.set_mobility(100, Static(0.0, 2.0))
    net.run_until(80.0)
    assert 0 in robot.table and 11 not in robot.table


def test_battery_death() -> None:
    net = VirtualNetwork(RadioModel(CC2420, 1), 1)
    per_beacon = CC2420.tx_energy_mj(len(encode(Hello(1, BROADCAST, 0))))
    net.add(hello(1), Static(0, 0), battery_mj=per_beacon * 5.5)
    net.add(hello(2), Static(50, 0))  # out of range: the battery only pays for TX
    downs: list[tuple[int, object, float]] = []
    net.on_event = lambda n, e, t: downs.append((n, e, t)) if isinstance(e, MoteDown) else None
    net.run_until(20.0)
    assert not net.alive(1) and net.alive(2)
    assert net.counters[1].frames_tx == 6
    assert [(n, e) for n, e, _ in downs] == [(1, MoteDown("battery"))]
    assert 5.0 < downs[0][2] < 7.0
    assert net.energy_mj(1) >= per_beacon * 5.5


def test_local_bugs_raise() -> None:
    net = VirtualNetwork(RadioModel(CC2420, 1), 1)
    with pytest.raises(ValueError):
        VirtualNetwork(RadioModel(CC2420, 1), 2)
    with pytest.raises(ValueError):
        net.add(hello(1), Static(0, 0), tx_power_dbm=10.0)
    a = Recorder(1)
    net.add(a, Static(0, 0))
    net.run_until(1.0)
    with pytest.raises(ValueError):
        send(net, a, b"\x00" * (CC2420.mtu + 1))
    with pytest.raises(ValueError):
        send(net, a, b"\x00", dest=1)
    with pytest.raises(ValueError):
        net.call_at(0.5, lambda: None)
    events: list[object] = []
    net.on_event = lambda n, e, t: events.append(e)
    net.kill(1)
    net.kill(1)  # idempotent
    assert events == [MoteDown("killed")]


def test_bench_smoke() -> None:
    from awaremw.bench.virtual import run

    out = run(36, 5.0, 2)
    assert out["motes"] == 36 and out["sim_seconds"] == 5.0
    assert out["frames_by_kind"] == {"hello": out["frames_tx"]}
    assert out["frames_tx"] >= 36 * 4 and out["deliveries"] > out["frames_tx"]
    assert out["speedup"] > 0 and 3 <= out["mean_neighbours"] <= 14
    assert out == {
        **run(36, 5.0, 2),
        "wall_seconds": out["wall_seconds"],
        "cpu_seconds": out["cpu_seconds"],
        "speedup": out["speedup"],
        "cpu_per_mote_s_us": out["cpu_per_mote_s_us"],
        "rss_per_mote_kb": out["rss_per_mote_kb"],
    }


@pytest.mark.parametrize("workload", ["hello", "aware"])
def test_networks_in_turns_run_as_they_would_alone(workload: str) -> None:
    """The control of ``--sizes --control``: K networks in turns, each the run it
    would be alone (the turns and the collections between them change nothing)."""
    from awaremw.bench.virtual import run, run_networks

    both = run_networks(49, 2, 25.0, 3, workload)
    alone = [run(49, 25.0, s, workload) for s in (3, 4)]
    assert both["networks"] == 2 and both["motes"] == 49
    assert both["frames_tx"] == sum(r["frames_tx"] for r in alone) > 0
    assert both["deliveries"] == sum(r["deliveries"] for r in alone)
    if workload == "aware":
        assert all(r["records_produced"] > 0 for r in alone)
        assert both["record_delivery_min"] == min(r["record_delivery"] for r in alone)


def test_sizes_with_control_compare_one_large_network_with_small_ones_in_turns() -> None:
    import json
    import subprocess
    import sys

    argv = [sys.executable, "-m", "awaremw", "bench", "virtual", "--json", "--sizes", "25,50",
            "--control", "--duration", "4"]  # fmt: skip
    out = json.loads(subprocess.run(argv, capture_output=True, text=True, check=True).stdout)
    small, large = out["sizes"]
    control = out["control"]
    assert (small["motes"], large["motes"]) == (25, 50)
    assert control["motes"] == 25 and control["networks"] == 2
    assert control["frames_tx"] > small["frames_tx"]  # two networks' frames
    ratio = large["cpu_per_mote_s_us"] / control["cpu_per_mote_s_us"]
    assert out["cpu_per_mote_ratio_vs_control"] == round(ratio, 3)
    assert out["control_ratio"] == round(
        control["cpu_per_mote_s_us"] / small["cpu_per_mote_s_us"], 3
    )


def test_options_are_refused_where_they_mean_nothing() -> None:
    import argparse

    from awaremw.bench.virtual import add_arguments, run

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    parser.add_argument("--json", action="store_true")
    for argv, words in (
        (["--control"], "give --sizes"),
        (["--sizes", "100,250", "--control"], "a multiple of the smallest"),
        (["--sizes", "100,200", "--networks", "2"], "for one run"),
        (["--networks", "0"], "at least 1"),
        (["--against-white"], "give --noise TRACE and/or --hardware-variance"),
        (["--against-white", "--hardware-variance", "--sizes", "10,20"], "one run per radio"),
        (["--against-white", "--hardware-variance", "--repeats", "0"], "at least 1"),
        (["--spacing", "0"], "above 0"),
        (["--spacing", "nan"], "above 0"),
    ):
        with pytest.raises(ValueError, match=words):
            run(parser.parse_args(argv))


def test_a_wider_spacing_spreads_the_grid_and_thins_the_neighbourhoods() -> None:
    from awaremw.bench.virtual import run

    near, far = run(49, 5.0, 2, spacing=8.0), run(49, 5.0, 2, spacing=16.0)
    assert (near["spacing_m"], far["spacing_m"]) == (8.0, 16.0)
    assert near["mean_neighbours"] > far["mean_neighbours"] > 0
    assert far["dropped_distance"] > near["dropped_distance"]


def test_against_white_runs_the_same_command_on_both_radios_in_fresh_processes(
    tmp_path: pathlib.Path,
) -> None:
    import json
    import subprocess
    import sys

    from awaremw.bench.virtual import run

    plot = tmp_path / "kinds.png"
    argv = [sys.executable, "-m", "awaremw", "bench", "virtual", "--json", "--motes", "36",
            "--duration", "4", "--seed", "2", "--spacing", "10", "--noise", "meyer-heavy",
            "--hardware-variance", "--against-white", "--repeats", "2",
            "--plot", str(plot)]  # fmt: skip
    out = json.loads(subprocess.run(argv, capture_output=True, text=True, check=True).stdout)
    assert out["repeats"] == 2 and out["spacing_m"] == 10.0
    assert out["radio_settings"] == "noise meyer-heavy, hardware variance"
    assert [len(v) for v in out["cpu_seconds"].values()] == [2, 2]
    # Each side is the run bench virtual makes alone with that radio (frames are a
    # seed's own), and the ratios are of those figures.
    alone = {
        "realistic": run(36, 4.0, 2, spacing=10.0, radio=RadioSettings("meyer-heavy", True)),
        "white": run(36, 4.0, 2, spacing=10.0),
    }
    assert out["frames_tx"] == {k: r["frames_tx"] for k, r in alone.items()}
    assert out["deliveries"] == {k: r["deliveries"] for k, r in alone.items()}
    assert out["deliveries"]["realistic"] < out["deliveries"]["white"]  # the noise loses frames
    assert out["frames_ratio"] == round(
        alone["realistic"]["frames_tx"] / alone["white"]["frames_tx"], 3
    )
    med = out["cpu_seconds_median"]
    assert out["cpu_ratio"] == round(med["realistic"] / med["white"], 3)
    assert out["frames_by_kind"] == {"hello": {k: r["frames_tx"] for k, r in alone.items()}}
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and out["plot"] == str(plot)


def test_frames_by_kind_count_every_frame_of_the_whole_middleware() -> None:
    from awaremw.bench.virtual import run

    out = run(64, 12.0, 1, "aware")
    kinds = out["frames_by_kind"]
    assert sum(kinds.values()) == out["frames_tx"]
    assert {"ctp_beacon", "drip_item", "drip_summary"} <= set(kinds)
    assert all(n > 0 for n in kinds.values())
