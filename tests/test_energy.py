"""Energy a user can read: per-role rates and lifetimes (radio/energy.py), the
figures of a real virtual run by role (experiments.snapshot.role_energy), and
the dashboard state that carries them."""

from __future__ import annotations

import pytest

from awaremw.experiments.scenario import load_scenario
from awaremw.experiments.snapshot import role_energy, snapshot_of
from awaremw.experiments.virtual import VirtualRun
from awaremw.radio.energy import (
    AA2_MJ,
    EnergyRole,
    MoteEnergy,
    by_role,
    lifetime_days,
    listen_mj_per_hour,
    role_of,
    role_table,
)
from awaremw.radio.model import CC2420
from awaremw.view.web import DashboardState


def test_roles_in_order_of_precedence() -> None:
    assert role_of(True, True, 5) is EnergyRole.LEADER
    assert role_of(False, True, 5) is EnergyRole.MEMBER
    assert role_of(False, False, 1) is EnergyRole.FORWARDER
    assert role_of(False, False, 0) is EnergyRole.IDLE


def test_rates_per_hour_and_lifetime_on_two_aa_cells() -> None:
    motes = [
        MoteEnergy(1, EnergyRole.LEADER, 30.0, 60),
        MoteEnergy(2, EnergyRole.MEMBER, 10.0, 40),
        MoteEnergy(3, EnergyRole.MEMBER, 20.0, 20),
        MoteEnergy(4, EnergyRole.IDLE, 0.0, 0),
    ]
    roles = by_role(motes, 1800.0, CC2420)  # half an hour: rates are twice the sums
    assert set(roles) == {EnergyRole.LEADER, EnergyRole.MEMBER, EnergyRole.IDLE}
    m = roles[EnergyRole.MEMBER]
    assert m.motes == 2 and m.mj_per_hour == pytest.approx(30.0)
    assert m.mj_per_hour_max == pytest.approx(40.0) and m.frames_per_hour == pytest.approx(60.0)
    assert m.frames_per_hour_max == pytest.approx(80.0)
    # The role's most spending mote: 40 mJ/h from 27 kJ.
    assert round(AA2_MJ) == 27_000_000
    assert m.lifetime_days_traffic == pytest.approx(27e6 / 40.0 / 24.0)
    floor = listen_mj_per_hour(CC2420)  # 1 % of 18.8 mA at 3 V: 0.564 mW
    assert floor == pytest.approx(0.01 * 3.0 * 18.8 * 3600.0)
    assert m.lifetime_days_lpl == pytest.approx(27e6 / (40.0 + floor) / 24.0)
    idle = roles[EnergyRole.IDLE]
    assert idle.lifetime_days_traffic is None  # spent nothing
    assert idle.lifetime_days_lpl == pytest.approx(27e6 / floor / 24.0)
    assert lifetime_days(0.0) is None
    table = role_table(motes, 1800.0, CC2420)
    assert table["leader"]["mj_per_hour"] == 60.0 and table["idle"]["motes"] == 1
    with pytest.raises(ValueError, match="window must be > 0 s"):
        by_role(motes, 0.0, CC2420)


@pytest.fixture(scope="module")
def romeo_run() -> VirtualRun:
    run = VirtualRun(load_scenario("romeo4r"))
    run.run(60.0)
    return run


def test_a_virtual_run_gives_energy_by_role(romeo_run: VirtualRun) -> None:
    run = romeo_run
    sc, now = run.scenario, run.net.now
    traffic = {
        n: (c.frames_tx, c.frames_rx, run.net.energy_mj(n)) for n, c in run.net.counters.items()
    }
    fwd = {n for n, c in run.net.counters.items() if c.acks_tx > 0}
    energy = role_energy(sc, run.recorder, now, traffic, fwd)
    assert {"leader", "member", "idle"} <= set(energy)
    assert sum(int(e["motes"]) for e in energy.values()) == len(
        [n for n in sc.sensors if n in traffic]
    )
    # A leader aggregates, beacons and sends records: it spends more than an idle mote.
    assert energy["leader"]["mj_per_hour"] > energy["idle"]["mj_per_hour"] > 0
    assert energy["member"]["frames_per_hour"] > energy["idle"]["frames_per_hour"]
    snap = snapshot_of(sc, run.recorder, now, None, traffic, forwarders=fwd)
    assert snap.stats["mJ/h leader"] == pytest.approx(energy["leader"]["mj_per_hour"])
    assert snap.stats["frames/h idle"] == pytest.approx(energy["idle"]["frames_per_hour"])
    assert role_energy(sc, run.recorder, 0.0, traffic, fwd) == {}


def test_the_dashboard_state_carries_the_energy_by_role() -> None:
    st = DashboardState((100.0, 100.0))
    assert st.state()["energy"] == {}
    st.energy = {"leader": {"motes": 1, "mj_per_hour": 12.5, "frames_per_hour": 900.0}}
    assert st.state()["energy"]["leader"]["mj_per_hour"] == 12.5


def test_an_idle_network_whispers() -> None:
    """`bench dissemination` on a 10 x 10 grid: after an hour, at most 3 frames
    per mote per hour (CTP beacons and Drip), and still well under 1 s per hop
    for a new item; the window's energy is given by role (every mote idle)."""
    import argparse

    from awaremw.bench import dissemination

    parser = argparse.ArgumentParser()
    dissemination.add_arguments(parser)
    out = dissemination.run(parser.parse_args(["--side", "10", "--seed", "2"]))
    # Seed 2's corner mote 90 hears its best neighbour at -96 dBm (below the
    # CC2420's sensitivity on average): it may miss the item for the whole hour.
    assert out["coverage"] >= 0.98
    assert out["seconds_per_hop"] is not None and out["seconds_per_hop"] <= 1.0
    assert 0 < out["tx_per_mote_per_hour"] <= 3.0, out
    assert out["tx_per_mote_per_hour"] == pytest.approx(
        out["drip_tx_per_mote_per_hour"] + out["ctp_beacons_per_mote_per_hour"], abs=0.01
    )
    idle = out["energy_by_role"]["idle"]
    assert idle["motes"] == 100 and idle["frames_per_hour"] > 0
