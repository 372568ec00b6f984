"""Aggregation functions: ground truth, tree-shape independence, registry, wire."""

from __future__ import annotations

import random
import statistics

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from awaremw.protocol import aggregation
from awaremw.protocol.aggregation import Aggregator, PartialAgg, Variance
from awaremw.protocol.frames import BROADCAST, AggId, Partial, decode, encode

TRUTH = {
    AggId.AVG: statistics.fmean,
    AggId.MIN: min,
    AggId.MAX: max,
    AggId.SUM: sum,
    AggId.COUNT: len,
}
readings = st.lists(
    st.floats(min_value=-1e4, max_value=1e4, allow_nan=False), min_size=1, max_size=60
)


def tree_merge(agg: Aggregator, parts: list[PartialAgg], rng: random.Random) -> PartialAgg:
    """Merge partials in a random tree shape (what a group tree does)."""
    parts = list(parts)
    while len(parts) > 1:
        i, j = sorted(rng.sample(range(len(parts)), 2))
        b = parts.pop(j)
        a = parts.pop(i)
        parts.append(agg.merge(a, b))
    return parts[0]


@pytest.mark.parametrize("agg_id", list(TRUTH))
@settings(max_examples=40, deadline=None)
@given(values=readings, seed=st.integers(0, 2**16))
def test_functions_equal_ground_truth_whatever_the_tree(
    agg_id: AggId, values: list[float], seed: int
) -> None:
    agg = aggregation.by_id(agg_id)
    count, state = tree_merge(agg, [agg.init(v) for v in values], random.Random(seed))
    assert count == len(values)
    assert agg.result(count, state) == pytest.approx(TRUTH[agg_id](values), rel=1e-9, abs=1e-6)


def test_registry_by_id_and_name() -> None:
    for agg_id, name in [(0, "avg"), (1, "min"), (2, "max"), (3, "sum"), (4, "count")]:
        assert aggregation.by_id(agg_id).name == name
        assert aggregation.by_name(name).id == agg_id
        assert aggregation.by_name(name.upper()).id == agg_id
    with pytest.raises(aggregation.UnknownAggregation, match="known: avg, count"):
        aggregation.by_name("median")
    with pytest.raises(aggregation.UnknownAggregation):
        aggregation.by_id(99)
    assert aggregation.get(99) is None


def test_extension_registers_and_clashes_are_refused() -> None:
    var = Variance()
    assert aggregation.get(var.id) is None  # not registered by default
    aggregation.register(var)
    try:
        assert aggregation.by_name("variance") is var
        vals = [1.0, 2.0, 4.0, 7.0]
        c, s = aggregation.by_id(var.id).merge_all(var.init(v) for v in vals)  # type: ignore[misc]
        assert var.result(c, s) == pytest.approx(statistics.pvariance(vals))
        with pytest.raises(ValueError, match="clashes"):
            aggregation.register(Variance())  # another object under the same id
    finally:
        aggregation.unregister(var.id)
    assert aggregation.get(var.id) is None

    class Big(Aggregator):
        id = 200
        name = "big"

        def init(self, value: float) -> PartialAgg:
            return 1, (value,) * 5

    with pytest.raises(ValueError, match="at most 4"):
        aggregation.register(Big())


def test_valid_state_shape() -> None:
    assert aggregation.by_id(AggId.AVG).valid_state((1.0,))
    assert not aggregation.by_id(AggId.AVG).valid_state(())
    assert aggregation.by_id(AggId.COUNT).valid_state(())


def test_partial_state_survives_the_wire_as_float32() -> None:
    agg = aggregation.by_id(AggId.SUM)
    c, s = agg.merge_all(agg.init(v) for v in [21.3, 22.7, 19.9])  # type: ignore[misc]
    f = Partial(3, BROADCAST, 1, 1, 77, 12, AggId.SUM, c, s)
    g = decode(encode(f))
    assert isinstance(g, Partial) and g.count == 3
    assert g.state[0] == pytest.approx(s[0], rel=1e-6)


def test_aggregation_bench_smoke() -> None:
    """The bench's documented keys on a small grid (the figures come from the CLI)."""
    import argparse

    from awaremw.bench import aggregation as bench

    parser = argparse.ArgumentParser()
    bench.add_arguments(parser)
    args = parser.parse_args(
        ["--side", "8", "--radius", "18", "--warmup", "40", "--epochs", "5", "--seed", "2"]
    )
    out = bench.run(args)
    for key in (
        "lower_bound_ratio",
        "no_aggregation_ratio",
        "measured_per_epoch",
        "lower_bound_per_epoch",
        "no_aggregation_per_epoch",
        "by_frame_per_epoch",
        "members",
        "leader_hops",
        "records",
        "completeness",
        "meets_targets",
    ):
        assert key in out
    assert out["members"] == out["members_expected"] > 0 and out["leaders"] == 1
    assert out["records"] == 5 and out["by_frame_per_epoch"]["Partial"] >= out["members"] - 1
    # The values, not only the keys: the bound and the ratios follow from the counts.
    assert out["lower_bound_per_epoch"] == out["members"] + out["leader_hops"]
    by_frame = out["by_frame_per_epoch"]
    assert out["measured_per_epoch"] == pytest.approx(sum(by_frame.values()))
    assert out["lower_bound_ratio"] == pytest.approx(
        out["measured_per_epoch"] / out["lower_bound_per_epoch"]
    )
    assert out["no_aggregation_ratio"] == pytest.approx(
        out["no_aggregation_per_epoch"] / out["measured_per_epoch"]
    )
    assert out["no_aggregation_per_epoch"] >= out["members"]  # every member at least 1 hop
    # Every member sampled every epoch; in-network merging folded all but the
    # leader's own partials (one record per epoch), and nearly all readings arrived.
    cs = out["channel_stats"]
    assert cs["samples"] == out["members"] * out["records"]
    assert cs["records"] == out["records"] and cs["partials_received"] <= cs["partials_sent"]
    assert 0.9 <= out["completeness"] <= 1.0
    # Energy by role over the window: every mote in one role, one leader, the
    # members as counted, and a leader that spends more than an idle mote.
    roles = out["energy_by_role"]
    assert sum(r["motes"] for r in roles.values()) == 64
    assert roles["leader"]["motes"] == 1 and roles["member"]["motes"] == out["members"] - 1
    assert roles["leader"]["mj_per_hour"] > roles["idle"]["mj_per_hour"] > 0
    assert roles["member"]["frames_per_hour"] >= 3600.0 / 2.0 * 0.9  # a partial per epoch
    assert out["meets_targets"] is (
        out["lower_bound_ratio"] <= 1.5 and out["no_aggregation_ratio"] >= 5
    )
