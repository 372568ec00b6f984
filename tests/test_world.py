"""The world model: scripted sources, fields, seeded noise, [world] parsing."""

from __future__ import annotations

import itertools
import math
import subprocess
import sys

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from awaremw.world.fields import Keyframe, Source, World, WorldError, gauss_hash
from awaremw.world.table import world_from_table


def fire(name: str, *keys: tuple[float, float, float, float, float], edge: float = 1.0) -> Source:
    return Source(name, tuple(Keyframe(*k) for k in keys), edge=edge)


def test_source_absent_before_first_keyframe_and_holds_after_last() -> None:
    s = fire("a", (10, 0, 0, 1, 100), (20, 10, 0, 3, 200))
    assert s.state(9.99) is None
    mid = s.state(15)
    assert mid is not None
    assert (mid.x, mid.radius, mid.peak) == pytest.approx((5, 2, 150))
    late = s.state(1000)
    assert late is not None and late.x == 10
    gone = Source("g", s.keyframes, hold=False)
    assert gone.state(20) is not None and gone.state(20.1) is None


def test_profile_flat_core_and_gaussian_edge() -> None:
    s = fire("a", (0, 0, 0, 2, 100), edge=1.5)
    assert s.value(1.9, 0, 0) == 100
    assert s.value(2 + 1.5, 0, 0) == pytest.approx(100 * math.exp(-0.5))
    assert s.value(100, 0, 0) == 0


def test_temperature_takes_hottest_fire_not_the_sum() -> None:
    w = World(fires=(fire("a", (0, 0, 0, 2, 300)), fire("b", (0, 0, 0, 2, 300))))
    assert w.temperature(0, 0, 0) == pytest.approx(20 + 300)


def test_two_fires_merge_then_split_in_the_field() -> None:
    """The hot area (T > 45) along the line between the fires is connected exactly
    while the fires overlap."""
    w = World(
        fires=(
            fire("a", (0, 2, 5, 1, 300)),
            fire("b", (0, 14, 5, 1, 300), (50, 7, 5, 1, 300), (100, 18, 5, 1, 300)),
        )
    )

    def hot_runs(t: float) -> int:
        hot = [w.temperature(x / 4, 5, t) > 45 for x in range(0, 81)]
        return sum(1 for i, h in enumerate(hot) if h and (i == 0 or not hot[i - 1]))

    assert hot_runs(0) == 2
    assert hot_runs(50) == 1
    assert hot_runs(100) == 2


def test_humidity_drops_as_temperature_rises() -> None:
    w = World(ambient_humidity=60, fires=(fire("a", (0, 0, 0, 1, 30)),))
    assert w.humidity(50, 50, 0) == pytest.approx(60)
    assert w.humidity(0, 0, 0) < 20


def test_gas_and_light_come_from_fires_and_sources() -> None:
    w = world_from_table(
        {
            "ambient_light": 300,
            "fires": [
                {
                    "name": "f",
                    "gas": 80,
                    "light": 1000,
                    "keyframes": [{"t": 0, "x": 0, "y": 0, "peak": 300}],
                }
            ],
            "gas": [
                {"name": "leak", "keyframes": [{"t": 0, "x": 10, "y": 0, "peak": 50, "radius": 1}]}
            ],
            "lights": [{"keyframes": [{"t": 0, "x": 20, "y": 0, "peak": 500}]}],
        }
    )
    assert w.gas(0, 0, 0) == pytest.approx(80)
    assert w.gas(10, 0, 0) == pytest.approx(50)
    assert w.light(0, 0, 0) == pytest.approx(1300)
    assert w.light(20, 0, 0) == pytest.approx(800)
    assert w.value("gas", 100, 100, 0) == 0


def test_noise_is_a_pure_function_of_seed_node_sensor_step() -> None:
    w = World(seed=7, noise_step=0.5)
    a = w.noise(3, "temperature", 10.1, 1.0)
    assert a == w.noise(3, "temperature", 10.4, 1.0)  # same step
    assert a != w.noise(3, "temperature", 10.6, 1.0)  # next step
    assert a != w.noise(4, "temperature", 10.1, 1.0)
    assert a != World(seed=8).noise(3, "temperature", 10.1, 1.0)
    assert w.noise(3, "temperature", 10.1, 0.0) == 0.0


def test_noise_identical_in_another_process() -> None:
    code = (
        "from awaremw.world.fields import World; "
        "print(repr(World(seed=5).noise(9, 'light', 3.3, 2.0)))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert float(out.stdout) == World(seed=5).noise(9, "light", 3.3, 2.0)


def test_gauss_hash_is_roughly_standard_normal() -> None:
    xs = [gauss_hash(1, i) for i in range(20000)]
    mean = sum(xs) / len(xs)
    var = sum((x - mean) ** 2 for x in xs) / len(xs)
    assert abs(mean) < 0.03
    assert 0.95 < var < 1.05


def test_texture_is_small_smooth_and_seeded() -> None:
    w = World(seed=1, variation=0.5, variation_scale=5)
    vals = [w.temperature(x * 0.5, 3, 0) for x in range(40)]
    assert all(19.5 <= v <= 20.5 for v in vals)
    assert max(abs(a - b) for a, b in itertools.pairwise(vals)) < 0.2
    assert len(set(vals)) > 10
    assert World(seed=2, variation=0.5).temperature(1, 3, 0) != vals[2]


@settings(max_examples=60, deadline=None)
@given(
    x=st.floats(-50, 50),
    y=st.floats(-50, 50),
    t=st.floats(0, 500),
)
def test_fields_are_finite_and_in_range(x: float, y: float, t: float) -> None:
    w = world_from_table(
        {
            "variation": 0.3,
            "fires": [
                {
                    "keyframes": [{"t": 0, "x": 0, "y": 0, "peak": 400}, {"t": 300, "radius": 5}],
                    "gas": 10,
                }
            ],
        }
    )
    assert 19 < w.temperature(x, y, t) <= 421
    assert 0 <= w.humidity(x, y, t) <= 100
    assert w.light(x, y, t) >= 0 and w.gas(x, y, t) >= 0


@pytest.mark.parametrize(
    ("table", "needle"),
    [
        ({"ambient_temperature": "hot"}, "world.ambient_temperature"),
        ({"fires": {"x": 1}}, r"world.fires: must be an array, got \{'x': 1\}"),
        ({"fires": [{"keyframes": []}]}, "keyframes"),
        (
            {"fires": [{"keyframes": [{"x": 1, "y": 1, "peak": 3}]}]},
            r"world.fires\[0\].keyframes\[0\]: missing key 't'",
        ),
        ({"fires": [{"keyframes": [{"t": 0, "x": 1, "peak": 3}]}]}, "needs y"),
        (
            {"fires": [{"name": "f", "keyframes": [{"t": 0, "x": 1, "y": 1, "peak": 3, "z": 1}]}]},
            r"world.fires\[0\].keyframes\[0\]: unknown key 'z'",
        ),
        (
            {
                "fires": [
                    {
                        "name": "f",
                        "color": "red",
                        "keyframes": [{"t": 0, "x": 1, "y": 1, "peak": 3}],
                    }
                ]
            },
            "color",
        ),
        (
            {"fires": [{"keyframes": [{"t": 5, "x": 1, "y": 1, "peak": 3}, {"t": 1}]}]},
            "must not decrease",
        ),
        ({"noise_step": 0}, "noise_step"),
    ],
)
def test_bad_world_tables_are_clear_errors(table: dict[str, object], needle: str) -> None:
    with pytest.raises(WorldError, match=needle):
        world_from_table(table)


def test_unknown_world_keys_are_kept_for_others() -> None:
    w = world_from_table({"area": [12.5, 11]}, seed=3)
    assert w.extra == {"area": [12.5, 11]} and w.seed == 3


@settings(max_examples=300, deadline=None)
@given(
    st.floats(-200, 200),
    st.floats(-200, 200),
    st.floats(0, 80),
    st.floats(0.1, 20),
    st.floats(0, 30),
)
def test_a_source_that_never_reaches_a_point_gives_it_exactly_zero(
    x: float, y: float, t: float, edge: float, radius: float
) -> None:
    # The sensor-read fast path (World.fires_reaching) skips the fires for which
    # Source.reaches is False: they must contribute exactly 0 at every time.
    s = fire("f", (10.0, -50.0, 30.0, radius, 80.0), (70.0, 60.0, -20.0, 2.0, 40.0), edge=edge)
    w = World(fires=(s,))
    if not s.reaches(x, y):
        assert s.value(x, y, t) == 0.0
        assert w.fires_reaching(x, y) == ()
    assert w.temperature_near(w.fires_reaching(x, y), x, y, t) == w.temperature(x, y, t)


def test_reaches_is_tight_enough_to_skip_far_motes() -> None:
    s = fire("f", (0.0, 0.0, 0.0, 5.0, 80.0), (60.0, 100.0, 0.0, 5.0, 80.0), edge=2.0)
    assert s.reaches(100.0, 0.0)  # 5 + 16 m of falloff from the path's end
    assert s.reaches(100.0 + 20.9, 0.0)
    assert not s.reaches(100.0 + 21.1, 0.0)
    assert not s.reaches(50.0, 40.0)  # beside the segment, 40 m off it


@settings(max_examples=300, deadline=None)
@given(
    st.lists(
        st.tuples(st.floats(0, 60), st.floats(0, 200), st.floats(0, 200), st.floats(0, 20)),
        min_size=1,
        max_size=5,
    ),
    st.floats(0.5, 5),
    st.booleans(),
    st.floats(-50, 250),
    st.floats(-50, 250),
    st.floats(0, 200),
)
def test_a_source_gives_a_point_exactly_zero_until_its_cold_horizon(
    legs: list[tuple[float, float, float, float]],
    edge: float,
    hold: bool,
    x: float,
    y: float,
    t: float,
) -> None:
    # Membership checks park until then (docs/protocol-groups.md): no heat before.
    ts = list(itertools.accumulate(leg[0] for leg in legs))
    keys = tuple(Keyframe(tk, lx, ly, r, 80.0) for tk, (_, lx, ly, r) in zip(ts, legs, strict=True))
    s = Source("f", keys, edge=edge, hold=hold)
    until = s.cold_until(x, y, t)
    end = min(until, t + 300.0)
    for k in range(100):
        tk = t + (end - t) * k / 100
        if tk < until:
            assert s.profile(x, y, tk) == 0.0
    if hold and t < until < math.inf and all(r == legs[0][3] for *_, r in legs):
        assert s.profile(x, y, until + 1e-4) > 0.0  # not later than the heat comes


def test_a_source_that_is_not_held_is_still_there_at_its_last_keyframe() -> None:
    once = Source("f", (Keyframe(10, 0, 0, 5, 80),), hold=False)
    jump = Source("j", (Keyframe(0, 100, 0, 5, 80), Keyframe(10, 100, 0, 5, 80),
                        Keyframe(10, 0, 0, 5, 80)), hold=False)  # fmt: skip
    for s in (once, jump):
        assert s.profile(0, 0, 10) == 1.0
        assert 9.0 < s.cold_until(0, 0, 0) <= 10.0
        assert s.cold_until(0, 0, 10.5) == math.inf  # gone


def test_a_sensor_read_is_the_world_value_plus_the_seeded_noise() -> None:
    from awaremw.nodes.kinds import TmoteSky

    w = World(seed=3, fires=(fire("f", (0.0, 0.0, 0.0, 5.0, 60.0), (100.0, 50.0, 0.0, 5.0, 60.0)),))
    app = TmoteSky(7, lambda t: (48.0, 3.0), w)
    for t in (0.0, 20.0, 49.7, 50.2, 80.0):
        true, noisy = app._sensed("temperature", t)
        assert true == w.temperature(48.0, 3.0, t)
        assert noisy == true + w.noise(7, "temperature", t, app.noise["temperature"].sigma)
