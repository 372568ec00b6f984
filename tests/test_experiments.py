"""Experiments: ground truth, recorder/metrics, and the shipped scenarios on the
virtual clock against the issue's targets."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from awaremw.experiments import metrics as M
from awaremw.experiments import write_metrics
from awaremw.experiments.metrics import RunResult
from awaremw.experiments.scenario import load_scenario, scenario_of
from awaremw.experiments.truth import GroundTruth, TruthNode, components
from awaremw.experiments.virtual import VirtualRun
from awaremw.protocol.attributes import Application, attribute_id
from awaremw.protocol.events import (
    Delivered,
    ElectionCause,
    GroupJoined,
    GroupLeft,
    LeaderElected,
    LeaveReason,
    MoteDown,
)
from awaremw.protocol.frames import Condition, DataRecord, GroupTypeDef, Op
from awaremw.radio.model import CC2420, RadioModel
from awaremw.runtime.deployment import DeploymentError, parse_deployment
from awaremw.world.fields import Keyframe, Source, World
from awaremw.world.mobility import Mobility, Static
from awaremw.world.mobility import Path as MPath

# ---------------------------------------------------------------- ground truth


def hot(value: float) -> GroupTypeDef:
    return GroupTypeDef((Condition(attribute_id("temperature"), Op.GT, value),))


def truth_from(
    nodes: dict[int, tuple[Mobility, Application | None, float]], world: World, radio: RadioModel
) -> GroundTruth:
    """One radio model for every mote; ``nodes`` maps id -> (mobility, app, tx power)."""
    return GroundTruth((TruthNode(i, m, a, txp, radio) for i, (m, a, txp) in nodes.items()), world)


def test_truth_rssi_is_the_mean_of_the_radio_model_and_none_when_unheard() -> None:
    from awaremw.nodes.kinds import Mica2, Robot

    model = RadioModel(CC2420, 3)
    robot = MPath(((0.0, 0.0), (100.0, 0.0)), speed_mps=1.0)
    t = truth_from(
        {
            1: (Static(10, 0), Mica2(1, lambda _t: (10, 0)), 0.0),
            9: (robot, Robot(9, robot.position), 0.0),
        },
        World(),
        model,
    )
    assert t.value(1, attribute_id("rssi:9"), 0.0) == model.mean_rssi(9, 1, 10.0, 0.0)
    assert t.value(1, attribute_id("rssi:9"), 5.0) == model.mean_rssi(9, 1, 5.0, 0.0)
    assert t.value(1, attribute_id("rssi:9"), 10.0) == model.mean_rssi(9, 1, 0.0, 0.0)
    assert t.value(1, attribute_id("rssi:9"), 100.0) is None  # 90 m: below sensitivity
    assert t.value(9, attribute_id("rssi:9"), 0.0) is None  # own beacon
    assert t.value(9, attribute_id("temperature"), 0.0) is None  # robot has no sensor
    assert t.value(1, attribute_id("x"), 0.0) == 10


def test_truth_members_and_regions_follow_the_fire() -> None:
    from awaremw.nodes.kinds import TmoteSky

    fire = Source("f", (Keyframe(0, 0, 0, 1, 100), Keyframe(10, 30, 0, 1, 100)), edge=2.0)
    w = World(fires=(fire,))
    nodes = {
        i: (Static(3.0 * i, 0), TmoteSky(i, (lambda x: lambda _t: (x, 0.0))(3.0 * i), w), 0.0)
        for i in range(12)
    }
    t = truth_from(nodes, w, RadioModel(CC2420, 1))
    assert t.members(hot(45), 0.0) == {0, 1}
    assert t.members(hot(45), 10.0) == {9, 10, 11}
    assert t.regions(hot(45), 10.0) == [frozenset({9, 10, 11})]


def test_components() -> None:
    comps = components([1, 2, 3, 10, 11, 20], lambda a, b: abs(a - b) == 1)
    assert comps == [frozenset({1, 2, 3}), frozenset({10, 11}), frozenset({20})]


# ---------------------------------------------------------------- recorder and metrics


def test_recorder_replays_memberships() -> None:
    rec = M.Recorder()
    rec.on_event(1, LeaderElected(1, 1, 77, 0, ElectionCause.CREATED, 1.0), 1.0)
    rec.on_event(2, GroupJoined(2, 1, 77, 1, 2.0), 2.0)
    rec.on_event(2, GroupLeft(2, 1, 77, LeaveReason.CONDITION, 5.0), 5.0)
    rec.on_event(2, GroupJoined(2, 1, 88, 3, 5.0), 5.0)  # same instant: last one wins
    assert rec.members_at(1, 0.5) == {}
    assert set(rec.members_at(1, 2.0)) == {1, 2}
    assert rec.groups_at(1, 3.0) == {77: {1, 2}}
    assert rec.groups_at(1, 5.0) == {77: {1}, 88: {2}}
    assert rec.leaders_at(1, 3.0) == {77: 1}
    assert rec.group_ids(1, 0.0, 4.0) == {77}
    assert rec.group_ids(1, 4.0, 6.0) == {77, 88}
    # Dispatch is by type: a look-alike class named MoteDown is no mote down, and
    # no event at all (the match is exhaustive over MoteEvent).
    with pytest.raises(AssertionError):
        rec.on_event(1, type("MoteDown", (), {"reason": "killed"})(), 6.0)
    assert rec.down == {} and set(rec.members_at(1, 6.0)) == {1, 2}
    rec.on_event(1, MoteDown("killed"), 7.0)
    assert set(rec.members_at(1, 7.0)) == {2}
    assert rec.down == {1: 7.0}
    rec.on_event(2, MoteDown("battery"), 8.0)
    assert rec.members_at(1, 8.0) == {} and rec.down == {1: 7.0, 2: 8.0}


def test_score_and_delivery() -> None:
    series = [
        M.Instant(0, frozenset({1, 2}), frozenset({1, 2})),
        M.Instant(1, frozenset({1, 2, 3}), frozenset({1, 2})),
        M.Instant(2, frozenset({1}), frozenset({1, 4})),
    ]
    s = M.score(series)
    assert (s.tp, s.fp, s.fn) == (5, 1, 1)
    assert s.precision == pytest.approx(5 / 6) and s.recall == pytest.approx(5 / 6)
    assert s.f1 == pytest.approx(5 / 6)
    rec = M.Recorder()
    r1 = DataRecord(1, 1, 77, 3, 0, 21.5, 4, 1)
    r2 = DataRecord(1, 1, 77, 4, 0, 21.7, 4, 1)
    from awaremw.protocol.events import RecordProduced

    rec.on_event(1, RecordProduced(r1, 10.0), 10.0)
    rec.on_event(1, RecordProduced(r2, 12.0), 12.0)
    assert M.delivery_ratio(rec) == 0.0
    rec.on_event(0, Delivered(1, r1, 3, 10.4), 10.4)
    rec.on_record(11.0, r1, "mqtt")  # a second copy does not count twice
    assert M.delivery_ratio(rec) == 0.5
    a = M.first_arrival(rec, 9.0, channel=1)
    assert a is not None and a.t == 10.4 and a.via == "root"
    assert M.first_arrival(rec, 11.0) is None
    assert M.instants(0, 1, 0.25) == [0, 0.25, 0.5, 0.75, 1.0]


# ---------------------------------------------------------------- scenario loading


def test_scenario_definitions_use_the_gateway_schema() -> None:
    sc = load_scenario("romeo4r")
    assert sc.robot == 100 and sc.gateway == 0 and 0 not in sc.sensors
    assert {1, 4, 17} <= set(sc.sensors) and len(sc.sensors) == 20
    g = sc.group_def()
    assert g.conditions[0].attr == attribute_id("rssi:100") and g.hysteresis == 2.0
    assert sc.channel_def().period_ms == 2000


def test_bad_definitions_are_deployment_errors() -> None:
    base = {"area": [10, 10], "nodes": [{"id": 0, "kind": "gateway", "position": [1, 1]}]}
    bad = dict(base, groups=[{"type": 1, "conditions": [{"attr": "smell", "op": ">",
                                                         "value": 1}]}])  # fmt: skip
    with pytest.raises(DeploymentError, match="unknown attribute"):
        scenario_of(parse_deployment(bad))
    bad = dict(base, channels=[{"attr": "temperature", "period_s": 1}])
    with pytest.raises(DeploymentError, match="missing key 'id'"):
        scenario_of(parse_deployment(bad))
    bad = dict(base, experiment={"robbot": 3})
    with pytest.raises(DeploymentError, match=r"experiment\.robbot"):
        scenario_of(parse_deployment(bad))


# ---------------------------------------------------------------- the experiments (virtual)


@pytest.fixture(scope="module")
def romeo4r(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict[str, object], Path]:
    from awaremw.experiments.romeo4r import analyse

    out = tmp_path_factory.mktemp("romeo4r")
    res = VirtualRun(load_scenario("romeo4r")).run()
    m = analyse(res, out)
    write_metrics(out, m)
    return m, out


def test_romeo4r_tracks_the_robot_with_one_group_id(
    romeo4r: tuple[dict[str, object], Path],
) -> None:
    m, out = romeo4r
    # The Done-line: one group id over the pass, membership F1 >= 0.9.
    assert m["distinct_group_ids"] == 1
    assert isinstance(m["membership_f1"], float) and m["membership_f1"] >= 0.9
    assert isinstance(m["handovers"], int) and m["handovers"] >= 2  # the leader follows the robot
    first = m["first_record_s"]
    assert isinstance(first, float) and 0 < first < 10
    assert m["delivery_ratio"] == pytest.approx(1.0, abs=0.1)
    assert isinstance(m["energy_mj_per_mote"], float) and m["energy_mj_per_mote"] > 0
    keys = {"membership_precision", "membership_recall", "membership_f1", "distinct_group_ids",
            "handovers", "first_record_s", "delivery_ratio", "frames_per_mote",
            "energy_mj_per_mote"}  # fmt: skip
    saved = json.loads((out / "metrics.json").read_text())
    assert keys <= set(saved)
    for png in ("romeo4r_snapshots.png", "romeo4r_rssi.png", "romeo4r_membership.png"):
        data = (out / png).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000


def test_romeo4r_rssi_samples_follow_the_truth(romeo4r: tuple[dict[str, object], Path]) -> None:
    """The motes' RSSI estimates of the robot track the noise-free mean (Fig. 9)."""
    sc = load_scenario("romeo4r")
    truth = sc.truth()
    rec = M.Recorder()
    run = VirtualRun(sc, rec)
    run.run(70.0)
    errs = [
        abs(v - truth.mean_rssi(100, 1, t))
        for t, v in rec.rssi[1]
        if v is not None and 35 <= t <= 50
    ]
    assert len(errs) > 20
    assert sum(errs) / len(errs) < 3.0  # dB: fading 1 dB, EWMA lag while the robot moves
    assert not math.isnan(sum(errs))


def test_fire_merge_and_split(tmp_path: Path) -> None:
    from awaremw.experiments.fire import analyse

    res: RunResult = VirtualRun(load_scenario("fire")).run()
    m = analyse(res, tmp_path)
    assert m["two_fires_distinct_ids"] is True
    assert m["merge_single_id"] is True and m["merge_id_inherited"] is True
    assert m["split_leader_part_keeps_id"] is True
    assert m["split_new_id"] is True
    assert isinstance(m["membership_f1"], float) and m["membership_f1"] >= 0.9
    assert (tmp_path / "fire_snapshots.png").stat().st_size > 5000


def test_romeo4r_keeps_one_group_id_over_several_seeds(tmp_path: Path) -> None:
    """Not one lucky run: other radio/world seeds (docs/experiments.md, seed
    distributions) keep one id over the pass, with the same F1 target."""
    from awaremw.experiments.seeds import run_seed

    one_id = 0
    for seed in range(1, 9):
        m = run_seed("romeo4r", seed, tmp_path / str(seed))
        assert m["seed"] == seed
        assert isinstance(m["membership_f1"], float) and m["membership_f1"] >= 0.9, seed
        assert isinstance(m["handovers"], int) and m["handovers"] >= 1, seed  # it follows
        metrics = json.loads((tmp_path / str(seed) / "metrics.json").read_text())
        assert metrics["seed"] == seed
        # One id carries every record; a transient would-be group that yields within
        # seconds and never leads a record may add a raw id (docs/experiments.md gives
        # the fraction of seeds with exactly one raw id: 36 of 40). Over seeds 1-24,
        # 21 to 22 seeds carry their records under one id: a run per seed would pin
        # the luck of its seeds, not the rule.
        one_id += m["distinct_data_group_ids"] == 1 and m["distinct_group_ids"] <= 2
    assert one_id >= 7, one_id


# ---------------------------------------------------------------- tracking at scale


def test_experiment_large_virtual_writes_the_scale_metrics(tmp_path: Path) -> None:
    """``awaremw experiment large --virtual``: 1,024 motes track the robot; the
    metrics carry romeo4r's keys plus the run's cost (wall and CPU seconds)."""
    import subprocess
    import sys

    p = subprocess.run(
        [sys.executable, "-m", "awaremw", "experiment", "large", "--virtual",
         "--duration", "24", "--out", str(tmp_path)],
        capture_output=True, text=True, timeout=300, check=False,
    )  # fmt: skip
    assert p.returncode == 0, p.stderr[-2000:]
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert m["scenario"] == "large" and m["mode"] == "virtual"
    assert m["duration_s"] == 24.0 and m["motes_scored"] == 1024
    assert m["wall_s"] > 0 and m["cpu_s"] > 0
    assert m["speedup"] == pytest.approx(24.0 / m["wall_s"], rel=0.01)
    # The robot's group forms around it within seconds of the definitions and its
    # records reach the gateway's mote, across the field's multihop tree.
    assert m["distinct_data_group_ids"] >= 1 and m["distinct_group_ids"] >= 1
    assert m["records_delivered"] >= 3
    assert m["membership_f1"] >= 0.8
    assert m["command"].startswith("awaremw experiment large --virtual")
    for png in ("large_snapshots.png", "large_membership.png"):
        data = (tmp_path / png).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000


def test_truth_reach_shortcut_is_exact() -> None:
    """GroundTruth skips motes beyond any possible hearing; the answer is the slow one."""
    sc = load_scenario("large")
    truth = sc.truth()
    attr = attribute_id("rssi:2000")
    far_none = 0
    for t in (0.0, 41.0, 97.5):
        for n in sc.sensors[::3]:
            mean = truth.mean_rssi(2000, n, t)
            slow = mean if mean >= CC2420.sensitivity_dbm else None
            assert truth.value(n, attr, t) == slow
            far_none += slow is None
    assert far_none > 500  # most of the field cannot hear the robot
    defn = sc.group_def()
    for t in (0.0, 33.3, 60.0, 119.5):
        brute = frozenset(n for n in sc.sensors if truth.satisfies(n, defn, t))
        assert truth.members(defn, t, sc.sensors) == brute and 2 <= len(brute) <= 12


# ---------------------------------------------------------------- secured virtual runs


def test_virtual_experiment_with_secrets_seals_frames_and_signs_items(tmp_path: Path) -> None:
    """``awaremw experiment NAME --virtual --secrets DIR``: the radio authenticated
    with the network key and the definitions signed, as in a secured fleet; the
    robot is still tracked and its records arrive."""
    from awaremw.experiments.virtual import VirtualRun
    from awaremw.protocol.frames import ItemKind
    from awaremw.protocol.mote import AwareMote
    from awaremw.security.keys import init_secrets

    init_secrets(tmp_path / "sk")
    sc = load_scenario("romeo4r")
    run = VirtualRun(sc, secrets=tmp_path / "sk")
    res = run.run(70.0)
    assert run.net.guard is not None
    assert run.net.payload_mtu == sc.deployment.radio_model().preset.mtu - run.net.guard.overhead
    assert res.recorder.arrivals, "no record reached the gateway's mote"
    gw = run.cores[sc.gateway]
    assert isinstance(gw, AwareMote) and gw.dissemination.verifier is not None
    # Every mote holds the channel with the gateway's signature.
    held = [
        c.dissemination.signature_of(ItemKind.CHANNEL, d.item_id)
        for c in run.cores.values()
        if isinstance(c, AwareMote)
        for d in sc.definitions
        if d.kind is ItemKind.CHANNEL
    ]
    assert held and all(s is not None and len(s) == 64 for s in held)
    assert sum(c.refused for c in run.net.counters.values()) == 0


def test_virtual_experiment_reads_each_key_file_once(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """``experiment --virtual --secrets DIR`` checks and uses the keys it read once."""
    from collections import Counter

    from awaremw.cli import main
    from awaremw.security.keys import init_secrets

    init_secrets(tmp_path / "sk")
    reads: Counter[str] = Counter()
    read_bytes = Path.read_bytes

    def counted(self: Path) -> bytes:
        if (tmp_path / "sk") in self.parents:
            reads[self.name] += 1
        return read_bytes(self)

    monkeypatch.setattr(Path, "read_bytes", counted)
    out = tmp_path / "out"
    args = ["experiment", "romeo4r", "--virtual", "--duration", "5", "--out", str(out)]
    assert main([*args, "--secrets", str(tmp_path / "sk")]) == 0
    assert reads == {"network.key": 1, "gateway.pub": 1, "gateway.key": 1}
    assert json.loads((out / "metrics.json").read_text())["duration_s"] == 5.0
    capsys.readouterr()
    with pytest.raises(ValueError, match="secrets or keys"):
        VirtualRun(load_scenario("romeo4r"), secrets=tmp_path / "sk", keys=(None, b""))  # type: ignore[arg-type]


def test_experiment_secrets_refuses_seeds_and_missing_files(tmp_path: Path) -> None:
    import subprocess
    import sys

    def run(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [sys.executable, "-m", "awaremw", "experiment", "romeo4r", "--virtual", *args],
            capture_output=True, text=True, timeout=120, check=False,
        )  # fmt: skip

    p = run("--seeds", "1-2", "--secrets", str(tmp_path), "--out", str(tmp_path / "o"))
    assert p.returncode == 2 and "--secrets applies to one run" in p.stderr
    p = run("--secrets", str(tmp_path / "none"), "--out", str(tmp_path / "o"))
    assert p.returncode == 2 and "Traceback" not in p.stderr and p.stderr.count("\n") == 1


def test_the_shipped_city_is_the_generated_one() -> None:
    """city.toml is city_toml() written out: one home for its shape."""
    from awaremw.experiments.city import city_toml
    from awaremw.runtime.deployment import shipped_dir

    assert (shipped_dir() / "city.toml").read_text(encoding="utf-8") == city_toml()
    sc = load_scenario("city")
    assert len(sc.sensors) == 10_000 and len(sc.deployment.of_kind("gateway")) == 9
    assert len(sc.world.fires) == 9 and sc.robot == 40000


def test_experiment_city_scores_every_object(tmp_path: Path) -> None:
    """``awaremw experiment city --virtual`` on a smaller city of the same shape
    (40 x 40 motes, 2 x 2 districts): each of the four fires and the robot is
    followed by one group whose records reach one of the four sinks."""
    import subprocess
    import sys

    from awaremw.experiments.city import city_toml

    small = tmp_path / "city-small.toml"
    small.write_text(city_toml(40, 2), encoding="utf-8")
    p = subprocess.run(
        [sys.executable, "-m", "awaremw", "experiment", "city", "--virtual", "--deployment",
         str(small), "--duration", "30", "--out", str(tmp_path / "out")],
        capture_output=True, text=True, timeout=600, check=False,
    )  # fmt: skip
    assert p.returncode == 0, p.stderr[-2000:]
    m = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert m["sinks"] == 4 and len(m["objects"]) == 5  # four fires and the robot
    assert m["objects"][-1] == "robot 40000"
    assert all(n >= 3 for n in m["records_per_object"]), m["records_per_object"]
    assert m["ids_per_object"] == [1] * 5 and m["one_id_per_object"] is True
    assert m["objects_tracked"] == 5 and m["every_object_tracked"] is True
    assert m["membership_f1"] >= 0.9 and m["distinct_group_ids"] == 4
    data = (tmp_path / "out" / "city_field.png").read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000


@pytest.mark.parametrize("seed", [1, 6])
def test_a_settled_group_gets_a_leader_again_within_about_an_epoch(
    seed: int, tmp_path: Path
) -> None:
    """Issue 31: a member of a settled group waited for its next partial, an epoch
    later, before claiming a leader that did not acknowledge one (1.84 and 1.89
    epochs on seeds 1 and 6); it now asks the leader at once and claims when that
    fails too (1.04 and 1.08)."""
    from awaremw.experiments.seeds import run_seed

    m = run_seed("failover", seed, tmp_path)
    assert m["id_kept"] and m["failover_epochs"] is not None
    assert m["failover_epochs"] <= 1.2, m["failover_epochs"]


@pytest.mark.parametrize("seed", [1, 12])
def test_on_a_noisy_site_sized_for_its_noise_the_group_keeps_one_id(
    seed: int, tmp_path: Path
) -> None:
    """Issue 30: romeo4r_noisy is romeo4r under meyer-heavy noise with hardware
    variance, every mote at 0 dBm and the threshold 20 dB higher. The middleware
    copes with the bursty links once the field is connected: one id and the
    paper's membership. (Seed 12 is where the shipped romeo4r, at -20 dBm under
    that noise, formed no group at all: the gateway mote reached nobody.)"""
    from awaremw.experiments.scenario import load_scenario
    from awaremw.experiments.seeds import run_seed

    radio = load_scenario("romeo4r_noisy").deployment.radio_settings
    assert (radio.noise, radio.hardware_variance) == ("meyer-heavy", True)
    m = run_seed("romeo4r", seed, tmp_path, deployment="romeo4r_noisy")
    assert m["distinct_group_ids"] == 1, m["group_ids"]
    assert m["membership_f1"] >= 0.9, m["membership_f1"]
    assert m["delivery_ratio"] >= 0.9, m["delivery_ratio"]


@pytest.mark.parametrize("seed", [9, 17, 19])
def test_a_group_that_follows_the_robot_keeps_one_id(seed: int, tmp_path: Path) -> None:
    """Issue 31: in romeo4r seeds 9 and 19 the leader kept the group until it
    failed the relaxed condition, by then cut off from the members ahead of the
    robot, which elected a second id; a leader in the hysteresis band now hands
    over early. Seed 17 is where that exposed a new leader yielding to its
    predecessor's last beacons (the same id, a larger node), leaving the group
    leaderless: those copies are no contender."""
    from awaremw.experiments.seeds import run_seed

    m = run_seed("romeo4r", seed, tmp_path)
    assert m["distinct_group_ids"] == 1, m["distinct_group_ids"]
    assert m["membership_f1"] >= 0.94
