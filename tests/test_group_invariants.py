"""Group invariants and the paper's group scenarios, on the virtual-clock driver.

Every scenario runs full AwareMotes (dissemination, collection, groups,
channels) on engineer A's VirtualNetwork with the LOSSLESS radio preset (see
tests/scenarios.py), so the ground truth of connectivity is exact: two motes
are neighbours iff they are at most 20 m apart.
"""

from __future__ import annotations

import math
import random
from collections.abc import Callable
from dataclasses import replace

from hypothesis import HealthCheck, Phase, example, given, settings
from hypothesis import strategies as st
from scenarios import LOSSLESS, Point, Scenario, ScriptedApp, in_disc, indicator, moving_disc

from awaremw.protocol.attributes import TEMPERATURE, rssi_attribute
from awaremw.protocol.events import (
    ElectionCause,
    GroupLeft,
    HandoverSent,
    LeaderElected,
    LeaderYielded,
)
from awaremw.protocol.frames import ANY_GROUP_ID, AggId, ChannelDef, Condition, GroupTypeDef, Op
from awaremw.protocol.groups import Role
from awaremw.protocol.mote import AwareMote
from awaremw.radio.model import PRESETS, RadioPreset
from awaremw.world.mobility import Path

HOT = GroupTypeDef((Condition(TEMPERATURE, Op.GT, 50.0),))
Region = Callable[[Point, float], bool]


def build(
    region: Region,
    nx: int,
    ny: int,
    *,
    seed: int = 3,
    channel: bool = True,
) -> Scenario:
    sc = Scenario(seed=seed)
    sc.grid(nx, ny, {TEMPERATURE: indicator(region)})
    sc.run_until(1.0)
    sc.define_group(1, HOT)
    if channel:
        sc.define_channel(1, ChannelDef(TEMPERATURE, 1, ANY_GROUP_ID, 2000, AggId.COUNT))
    return sc


def qualifying(sc: Scenario, region: Region, t: float | None = None) -> set[int]:
    when = sc.now if t is None else t
    return sc.qualifying(lambda n: region(sc.position(n), when))


# --------------------------------------------------------------------------- random topologies

LATTICE = 7.0  # pairwise distances are <= 19.8 m (lossless) or >= 21 m (out of range)


@st.composite
def topologies(
    draw: st.DrawFn,
) -> tuple[int, list[tuple[int, int]], list[tuple[float, float, float]]]:
    seed = draw(st.integers(0, 10_000))
    sites = draw(
        st.lists(
            st.tuples(st.integers(0, 13), st.integers(0, 13)), min_size=12, max_size=45, unique=True
        )
    )
    discs = draw(
        st.lists(
            st.tuples(st.floats(0, 91), st.floats(0, 91), st.floats(8, 35)), min_size=1, max_size=3
        )
    )
    return seed, sites, discs


def defined_on(
    topo: tuple[int, list[tuple[int, int]], list[tuple[float, float, float]]],
) -> tuple[Scenario, Region]:
    """Motes on the lattice ``sites``, hot inside the ``discs``; group type 1 (hot)
    defined at t = 1 s."""
    seed, sites, discs = topo

    def region(p: Point, t: float) -> bool:
        return any(math.hypot(p[0] - x, p[1] - y) <= r for x, y, r in discs)

    sc = Scenario(seed=seed)
    for i, (a, b) in enumerate(sites):
        sc.add(i + 1, (a * LATTICE, b * LATTICE), {TEMPERATURE: indicator(region)})
    sc.run_until(1.0)
    # Injected at one mote (as the gateway does), so that dissemination must carry
    # it: every mote connected to mote 1 must have learnt it (this can fail).
    sc.define_group(1, HOT, everywhere=False, at=[1])
    return sc, region


@settings(
    max_examples=30,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
    phases=[Phase.explicit, Phase.reuse, Phase.generate],  # shrinking a run costs minutes
)
@given(topologies())
# Mote 21 hears only mote 9. Its ask (9 announced an item) fell on a boot repeat
# already due, which was skipped as echoed and never repeated: it stayed without
# the definition.
@example(
    (
        35,
        [(5, 9), (10, 9), (5, 4), (7, 6), (10, 12), (2, 9), (4, 2), (9, 0), (2, 4), (9, 4),
         (13, 5), (5, 3), (2, 11), (5, 5), (7, 9), (11, 6), (9, 7), (0, 13), (6, 12), (2, 12),
         (0, 3), (4, 10), (8, 6), (7, 2), (2, 6), (8, 12), (1, 12), (3, 5), (11, 5)],
        [(15.206034007493068, 39.648524511701055, 11.925416349574),
         (86.91569273676691, 49.787418343165704, 11.358098140123975),
         (83.52170458344266, 83.37442098573094, 24.0)],
    )
)  # fmt: skip
def test_invariants_after_convergence_on_random_topologies(
    topo: tuple[int, list[tuple[int, int]], list[tuple[float, float, float]]],
) -> None:
    sc, region = defined_on(topo)
    for t in range(2, 41, 2):
        sc.run_until(float(t))
        assert sc.loops(1) == [], f"loop at t={t}"
    reach, todo = {1}, [1]
    while todo:
        a = todo.pop()
        for o in sc.motes:
            if o not in reach and math.dist(sc.position(a), sc.position(o)) <= sc.link_range:
                reach.add(o)
                todo.append(o)
    for n, mote in sc.motes.items():
        assert (1 in mote.groups.defined_types()) == (n in reach), n
    q = {n for n in qualifying(sc, region) if 1 in sc.motes[n].groups.defined_types()}
    assert sc.group_problems(1, q) == []
    # Ids are 16-bit and unique per component; every member agrees with its leader.
    for m in sc.memberships(1).values():
        assert 1 <= m.group_id <= 0xFFFE
        assert sc.motes[m.leader].groups.membership(1).group_id == m.group_id  # type: ignore[union-attr]


# ---------------------------------------------------------------------- tracking a moving region


def test_region_moving_across_the_grid_keeps_its_id_and_members_follow() -> None:
    region = moving_disc((30.0, 48.0), (1.0, 0.0), 28.0, t0=20.0)
    sc = build(region, 16, 9)
    ids: set[int] = set()
    lag = sc.config.check_period + 0.5  # membership follows within one check (plus a flood)
    for k in range(10, 141):
        t = float(k)
        sc.run_until(t)
        ids |= set(sc.leaders(1))
        members = set(sc.memberships(1))
        window = [qualifying(sc, region, t - lag * i / 4) for i in range(5)]
        always = set.intersection(*window)
        ever = set.union(*window)
        assert always <= members <= ever, (t, sorted(always - members), sorted(members - ever))
        handing = [n for n in sc.alive() if sc.motes[n].groups.role(1) is Role.HANDING_OVER]
        # One leader, or for a few ms one Handover in flight and none yet.
        leaders = sc.leader_nodes(1)
        assert len(leaders) == 1 or (not leaders and len(handing) == 1), t
    assert len(ids) == 1  # one id from start to end: handover, never re-creation
    causes = [e.cause for _, _, e in sc.of_type(LeaderElected)]
    assert causes.count(ElectionCause.HANDOVER) >= 5
    assert ElectionCause.ELECTION not in causes
    assert len(sc.of_type(HandoverSent)) == causes.count(ElectionCause.HANDOVER)
    # The region moved 120 m: none of the first members is still in the group.
    first = qualifying(sc, region, 10.0)
    assert not first & set(sc.memberships(1))


# --------------------------------------------------------------------------- merge and split


def test_two_regions_that_touch_merge_into_one_id() -> None:
    def region(p: Point, t: float) -> bool:
        bridge = t > 40 and 30 <= p[0] <= 120 and abs(p[1] - 40) <= 8
        return in_disc(30, 40, 22)(p) or in_disc(120, 40, 22)(p) or bridge

    sc = build(region, 14, 7)
    sc.run_until(39.0)
    assert sc.group_problems(1, qualifying(sc, region)) == []
    before = set(sc.leaders(1))
    assert len(before) == 2
    sc.run_until(60.0)
    assert sc.group_problems(1, qualifying(sc, region)) == []
    (after,) = sc.leaders(1)
    assert after in before  # one of the two ids survives


def test_region_cut_in_two_yields_two_groups_with_distinct_ids() -> None:
    def region(p: Point, t: float) -> bool:
        cut = t > 40 and 80 <= p[0] <= 100
        return 0 <= p[0] <= 170 and 20 <= p[1] <= 60 and not cut

    sc = build(region, 16, 7)
    sc.run_until(39.0)
    (old,) = sc.leaders(1)
    sc.run_until(70.0)
    assert sc.group_problems(1, qualifying(sc, region)) == []  # includes distinct ids
    ids = set(sc.leaders(1))
    assert len(ids) == 2 and old in ids  # the part that kept its leader keeps the id


# --------------------------------------------------------------------------- failures


def test_killing_the_leader_gives_a_new_leader_with_the_same_id_within_the_bound() -> None:
    """Failover without channels (no partials: the beacon timeout is the detector).
    Bound: the last beacon is at most one period old at the kill, the leader's
    neighbours claim leader_timeout_periods periods after it plus a jitter of two
    forward jitters: (3.5 + 1) periods = 9 s with the defaults; asserted: 5 periods.
    The group keeps its id, and is one group again (one leader) within 8 periods."""
    region = in_disc(60, 60, 40)
    for seed in (3, 4, 5):
        sc = build(lambda p, t: region(p), 11, 11, seed=seed)
        sc.run_until(30.0)
        ((gid, leader),) = sc.leaders(1).items()
        sc.kill(leader)
        cfg = sc.config
        bound = 5 * cfg.beacon_period
        assert (cfg.leader_timeout_periods + 1) * cfg.beacon_period + cfg.forward_jitter <= bound
        sc.run_until(30.0 + bound)
        elected = [e for _, _, e in sc.of_type(LeaderElected, 30.0)]
        assert elected, f"seed {seed}: no new leader within {bound} s"
        assert {e.cause for e in elected} == {ElectionCause.FAILOVER}, seed
        assert {e.group_id for e in elected} == {gid}, seed  # the id survives its leader
        sc.run_until(30.0 + 8 * cfg.beacon_period)  # one group again, everybody agrees
        assert sc.group_problems(1, qualifying(sc, lambda p, t: region(p))) == []
        assert list(sc.leaders(1)) == [gid], seed


def test_killing_30_percent_leaves_every_connected_group_working() -> None:
    def region(p: Point, t: float) -> bool:
        return in_disc(40, 40, 35)(p) or in_disc(150, 60, 35)(p)

    sc = build(region, 16, 9, seed=11)
    sc.run_until(30.0)
    assert len(sc.leaders(1)) == 2
    rng = random.Random(5)
    victims = rng.sample(sorted(sc.motes), k=int(0.3 * len(sc.motes)))
    for n in victims:
        sc.kill(n)
    sc.run_until(60.0)
    q = qualifying(sc, region)
    assert sc.group_problems(1, q) == []
    comps = sc.components(q)
    leaders = sc.leaders(1)
    assert len(leaders) == len(comps) >= 2
    # Every group delivers records that count all of its members.
    recs = [r for _, r in sc.records(since=56.0)]
    for comp in comps:
        (gid,) = {sc.motes[n].groups.membership(1).group_id for n in comp}  # type: ignore[union-attr]
        counts = [r.count for r in recs if r.group_id == gid]
        assert counts and counts[-1] == len(comp), (gid, counts, len(comp))


# --------------------------------------------------------------------------- a robot, by RSSI


def _robot_run(seed: int, preset: RadioPreset) -> tuple[Scenario, list[int]]:
    """The paper's experiment: a group of the motes that hear the robot's mote
    above -88 dBm (hysteresis 2 dB), the robot crossing a 12 x 5 grid at 1 m/s."""
    sc = Scenario(seed=seed, preset=preset)
    sc.grid(12, 5)
    path = Path(((-5.0, 24.0), (140.0, 24.0)), speed_mps=1.0, start_s=10.0)
    robot = AwareMote(500, None, replace(sc.config, hello_period=0.5), random.Random(seed))
    sc.motes[500] = robot
    sc.apps[500] = ScriptedApp(path, {})
    sc.net.add(robot, path)
    sc.run_until(1.0)
    near = GroupTypeDef((Condition(rssi_attribute(500), Op.GT, -88.0),), hysteresis=2.0)
    sc.define_group(1, near)
    leaders_per_second = []
    for k in range(20, 160):
        sc.run_until(float(k))
        leaders_per_second.append(len(sc.leader_nodes(1)))
    return sc, leaders_per_second


def test_group_follows_a_robot_by_rssi_keeping_its_id() -> None:
    sc, leaders = _robot_run(4, LOSSLESS)
    assert all(n == 1 for n in leaders)
    elected = [e for _, _, e in sc.of_type(LeaderElected)]
    assert len({e.group_id for e in elected}) == 1
    assert sum(e.cause is ElectionCause.HANDOVER for e in elected) >= 8
    # At the end the group is around the robot (x = 140 m): the last column.
    assert all(sc.position(n)[0] >= 108 for n in sc.memberships(1))


def test_robot_tracking_on_the_realistic_radio() -> None:
    """With shadowing and fading, a 4-6 mote group on weak links sometimes misses
    beacons for a leader timeout (a split by the paper's rules: new id); measured on
    seeds 1..10: 90-100 % of the seconds with exactly one leader, 1-3 ids per run."""
    for seed in (1, 2, 3):
        sc, leaders = _robot_run(seed, PRESETS["cc2420"])
        assert sum(n == 1 for n in leaders) >= 0.85 * len(leaders), seed
        assert len({e.group_id for _, _, e in sc.of_type(LeaderElected)}) <= 4, seed


# --------------------------------------------------------------------------- merges by weight


def _weights(sc: Scenario) -> dict[int, int]:
    """group id -> weight, as its leader holds it."""
    out = {}
    for gid, leader in sc.leaders(1).items():
        m = sc.motes[leader].groups.membership(1)
        assert m is not None
        out[gid] = m.weight
    return out


def test_merge_follows_weight_the_heavier_id_survives_even_when_lower() -> None:
    """The paper's merge rule: weight first, the id only breaks ties. The older
    (left) group aggregated for longer, so it is heavier; the seed is one where it
    also has the LOWER id, so a merge decided by id would keep the other one."""

    def region(p: Point, t: float) -> bool:
        left = in_disc(30, 40, 22)(p)
        right = t > 30 and in_disc(120, 40, 22)(p)
        bridge = t > 60 and 30 <= p[0] <= 120 and abs(p[1] - 40) <= 8
        return left or right or bridge

    sc = build(region, 14, 7, seed=SEED_LOWER_HEAVIER)
    sc.run_until(59.0)
    assert sc.group_problems(1, qualifying(sc, region)) == []
    w = _weights(sc)
    assert len(w) == 2
    heavy, light = sorted(w, key=lambda g: w[g], reverse=True)
    assert w[heavy] > w[light] > 0 and heavy < light  # id order and weight order disagree
    sc.run_until(80.0)
    assert sc.group_problems(1, qualifying(sc, region)) == []
    assert set(sc.leaders(1)) == {heavy}
    yields = [e for _, _, e in sc.of_type(LeaderYielded, since=59.0)]
    # The light group yields to the heavy one; any transient group that formed on
    # the bridge meanwhile yields to it too (never the other way).
    pairs = [(y.group_id, y.successor) for y in yields]
    assert (light, heavy) in pairs and all(succ == heavy for _, succ in pairs), pairs


SEED_LOWER_HEAVIER = 3


# Found by the test above (seed 4434): mote 21 at the field's edge reaches the
# group only through mote 25. Leader-beacon forwarding is counter-based: a member
# skips its forward when enough members as far out sent the beacon and no child
# depends on it. Children were known from their partials only: with no channel
# defined 25 took itself for a leaf and 21 missed beacons until it timed out
# (leader_lost) on a lossless link, about every 12 s. Now 21's forwards name 25
# (the only member it hears), and 25 keeps forwarding.
EDGE_MEMBER = (
    4434,
    [
        (10, 7),
        (10, 13),
        (2, 8),
        (6, 6),
        (3, 2),
        (6, 12),
        (4, 10),
        (5, 11),
        (9, 5),
        (4, 3),
        (1, 0),
        (13, 6),
        (0, 13),
        (6, 5),
        (13, 1),
        (9, 11),
        (3, 13),
        (4, 2),
        (12, 8),
        (12, 12),
        (0, 4),
        (6, 10),
        (7, 3),
        (12, 13),
        (1, 3),
        (12, 2),
        (6, 11),
        (3, 3),
        (2, 9),
        (11, 9),
        (12, 11),
        (7, 12),
        (8, 2),
        (11, 2),
        (4, 11),
        (3, 4),
        (8, 11),
        (10, 10),
        (3, 1),
        (9, 7),
        (9, 9),
    ],
    [(0.001, 20.040974953987917, 28.18449796431085)],
)


def test_a_member_whose_only_link_is_one_relay_keeps_its_group() -> None:
    sc, _ = defined_on(EDGE_MEMBER)
    sc.run_until(80.0)
    lost = [t for t, n, ev in sc.events if n == 21 and t > 30 and isinstance(ev, GroupLeft)]
    assert lost == []
