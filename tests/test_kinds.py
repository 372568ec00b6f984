"""Node kinds: raw-ADC <-> SI conversions, sensing the world, commands, registry."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from awaremw.nodes.kinds import (
    KINDS,
    S1087,
    Battery,
    Gateway,
    Mica2,
    Mts310Photocell,
    Mts310Thermistor,
    Robot,
    SensorNoise,
    Sht11,
    TmoteSky,
    kind_info,
)
from awaremw.protocol import attributes as A
from awaremw.protocol.attributes import Application, ReadBounds
from awaremw.protocol.frames import CommandDef
from awaremw.world.fields import Keyframe, Source, World
from awaremw.world.mobility import Path, Static


def at(x: float, y: float):  # type: ignore[no-untyped-def]
    return lambda t: (x, y)


# ---------------------------------------------------------------- datasheet conversions


def test_sht11_datasheet_points() -> None:
    # SHT1x datasheet: SO_T = 6000 -> 20.3 degC (d1 = -39.7, d2 = 0.01)
    assert Sht11.temperature_si(6000) == pytest.approx(20.3)
    # RH linear at SO_RH = 1500 and 25 degC: -2.0468 + 0.0367*1500 - 1.5955e-6*1500^2
    assert Sht11.humidity_si(1500, 25.0) == pytest.approx(49.4, abs=0.05)
    assert Sht11.humidity_si(4095, 25.0) == 100.0  # saturated clip
    assert Sht11.temperature_raw(500.0) == 0x3FFF  # out of range saturates


def test_s1087_datasheet_slope_and_saturation() -> None:
    assert S1087.lux_si(4096) == pytest.approx(9375.0)
    assert S1087.lux_si(1) == pytest.approx(2.2888, rel=1e-3)
    assert S1087.lux_raw(1e6) == 4095


def test_thermistor_reference_point() -> None:
    # 10 kOhm NTC in a divider with 10 kOhm: adc = 511.5 at 25 degC
    assert Mts310Thermistor.temperature_si(512) == pytest.approx(25.0, abs=0.1)


@settings(max_examples=100, deadline=None)
@given(t=st.floats(-20, 100))
def test_temperature_roundtrip_within_one_count(t: float) -> None:
    assert abs(Sht11.temperature_si(Sht11.temperature_raw(t)) - t) <= 0.006
    # 10-bit thermistor: resolution worst about 0.5 degC at the ends of this range
    assert abs(Mts310Thermistor.temperature_si(Mts310Thermistor.temperature_raw(t)) - t) < 0.6


@settings(max_examples=100, deadline=None)
@given(rh=st.floats(1, 99), t=st.floats(0, 60))
def test_humidity_roundtrip(rh: float, t: float) -> None:
    assert abs(Sht11.humidity_si(Sht11.humidity_raw(rh, t), t) - rh) < 0.1


@settings(max_examples=100, deadline=None)
@given(lx=st.floats(5, 9000))
def test_light_roundtrips(lx: float) -> None:
    assert abs(S1087.lux_si(S1087.lux_raw(lx)) - lx) <= 1.2
    assert abs(Mts310Photocell.lux_si(Mts310Photocell.lux_raw(lx)) - lx) / lx < 0.15


# ---------------------------------------------------------------- sensing the world


def test_kinds_offer_their_attributes() -> None:
    t = TmoteSky(1, at(0, 0))
    m = Mica2(2, at(0, 0))
    r = Robot(3, at(0, 0))
    g = Gateway(4, at(0, 0))
    for app in (t, m, r, g):
        assert isinstance(app, Application)
        assert all(app.offers(a) for a in (A.X, A.Y, A.BATTERY))
    assert t.offers(A.HUMIDITY) and not m.offers(A.HUMIDITY)
    assert m.offers(A.TEMPERATURE) and m.offers(A.LIGHT)
    assert not r.offers(A.TEMPERATURE) and r.read(A.TEMPERATURE, 0) is None
    assert t.attributes == ["temperature", "humidity", "light", "x", "y", "battery"]


def test_reading_follows_the_world_with_noise_and_quantisation() -> None:
    w = World(seed=3, fires=(Source("f", (Keyframe(10, 0, 0, 2, 80),)),))
    t = TmoteSky(5, at(1, 0), w)
    before = [t.read(A.TEMPERATURE, s * 0.5) for s in range(20)]  # fire not yet lit
    assert all(v is not None and abs(v - 20) < 1 for v in before)
    assert len(set(before)) > 3  # noisy
    hot = t.read(A.TEMPERATURE, 11)
    assert hot is not None and abs(hot - 100) < 1
    # quantised to SHT11 counts: (v - d1) / d2 is an integer
    assert (hot - Sht11.D1) / Sht11.D2 == pytest.approx(round((hot - Sht11.D1) / Sht11.D2))
    assert t.read(A.HUMIDITY, 11) is not None and t.read(A.HUMIDITY, 11) < 10  # type: ignore[operator]


def test_same_reading_in_two_instances() -> None:
    """Two processes building the same mote read the same value at the same time."""
    w = World(seed=11)
    a, b = TmoteSky(7, at(2, 3), w), TmoteSky(7, at(2, 3), World(seed=11))
    assert [a.read(A.LIGHT, s) for s in range(10)] == [b.read(A.LIGHT, s) for s in range(10)]


def test_noise_override_and_mica2_saturation() -> None:
    w = World(fires=(Source("f", (Keyframe(0, 0, 0, 2, 500),)),))
    quiet = Mica2(1, at(10, 10), w, noise={"temperature": SensorNoise(0.0)})
    assert quiet.read(A.TEMPERATURE, 0) == pytest.approx(20, abs=0.3)
    assert quiet.read(A.TEMPERATURE, 0) == quiet.read(A.TEMPERATURE, 7)
    hot = Mica2(1, at(0, 0), w)
    v = hot.read(A.TEMPERATURE, 0)
    assert v is not None and 100 < v < 300  # thermistor divider saturates well below 520


def test_position_and_battery() -> None:
    spent = [0.0]
    m = Mica2(1, lambda t: (t, 2 * t), battery=Battery(3.0, 2.0, 100.0))
    m.energy = lambda: spent[0]
    assert (m.read(A.X, 4), m.read(A.Y, 4)) == (4, 8)
    assert m.read(A.BATTERY, 0) == 3.0
    spent[0] = 50.0
    assert m.read(A.BATTERY, 0) == pytest.approx(2.5)
    assert Gateway(2, at(0, 0)).read(A.BATTERY, 0) == 3.0


# ---------------------------------------------------------------- commands


def cmd(name: str, **args: object) -> CommandDef:
    return CommandDef(name, args=tuple(args.items()))  # type: ignore[arg-type]


def test_led_command_records_state() -> None:
    m = Mica2(1, at(0, 0))
    m.on_command(cmd("led", color="red", state="on"), 1.0)
    m.on_command(cmd("led", color="green"), 2.0)
    assert m.leds == {"red": True, "green": True, "yellow": False}
    m.on_command(cmd("led", color="all", state="off"), 3.0)
    assert not any(m.leds.values())
    m.on_command(cmd("led", color="blue"), 4.0)
    assert [a.done for a in m.actions] == [True, True, True, False]
    assert m.actions[0].t == 1.0 and m.actions[0].node == 1
    assert "no blue LED" in m.actions[-1].effect


def test_beep_only_where_there_is_a_sounder() -> None:
    m, t = Mica2(1, at(0, 0)), TmoteSky(2, at(0, 0))
    m.on_command(cmd("beep", duration_ms=250), 0)
    t.on_command(cmd("beep"), 0)
    assert m.actions[-1].done and "250" in m.actions[-1].effect
    assert not t.actions[-1].done and "no sounder" in t.actions[-1].effect


def test_set_rate_holds_samples_and_rejects_bad_args() -> None:
    t = TmoteSky(1, at(0, 0), World(seed=1))
    t.on_command(cmd("set_rate", period_s=5), 0)
    v0 = t.read(A.TEMPERATURE, 0)
    assert t.read(A.TEMPERATURE, 4.9) == v0
    assert [t.read(A.TEMPERATURE, 5 + s) for s in range(0, 20, 5)] != [v0] * 4
    t.on_command(cmd("set_rate", period_s="fast"), 1)
    t.on_command(cmd("self_destruct"), 2)
    assert [a.done for a in t.actions] == [True, False, False]
    assert "unknown command" in t.actions[-1].effect


def test_registry() -> None:
    assert set(KINDS) >= {"tmote", "mica2", "robot", "gateway"}
    assert kind_info("telosb").app is TmoteSky
    assert kind_info("robot").config["hello_period"] > 0
    assert kind_info("gateway").config["is_root"] is True
    assert kind_info("mica2").radio == "cc1000" and kind_info("tmote").radio == "cc2420"
    with pytest.raises(KeyError, match="known: tmote"):
        kind_info("arduino")


# ---------------------------------------------------------------- read bounds (group checks)


def test_a_gaussian_draw_stays_within_its_bound() -> None:
    from awaremw.world.fields import GAUSS_BOUND, _gauss_of

    # The extremes: u1 at its smallest (the top 32 bits 0), cos at +1 and -1.
    top = _gauss_of(0)
    assert 6.76 < top < GAUSS_BOUND
    assert -GAUSS_BOUND < _gauss_of(1 << 31) < -6.76


@settings(max_examples=200, deadline=None)
@given(
    st.floats(0, 400),
    st.floats(0, 400),
    st.floats(0, 60),
    st.floats(0, 3.0),
    st.floats(0, 0.05),
    st.integers(0, 5),
)
def test_temperature_read_bounds_hold_every_read(
    x: float, y: float, t: float, sigma: float, rel: float, seed: int
) -> None:
    fire = Source("f", (Keyframe(0, 100, 100, 25, 80), Keyframe(60, 300, 300, 25, 80)), edge=4.0)
    w = World(seed=seed, ambient_temperature=20.0, variation=1.5, fires=(fire,))
    app = TmoteSky(3, Static(x, y).position, w, noise={"temperature": SensorNoise(sigma, rel)})
    b = app.read_bounds(A.TEMPERATURE, t)
    if b is None:  # the fire may heat it now: no bounds, read
        assert fire.reaches(x, y) and fire.profile(x, y, t + 1e-3) > 0.0
        return
    assert b.until > t and (b.until == math.inf or fire.reaches(x, y))
    for dt in (0.0, 0.25, 0.5, 7.3, 33.0, 120.0):
        if t + dt >= b.until:
            assert fire.profile(x, y, b.until + 1e-3) > 0.0  # a horizon no later than needed
            break
        v = app.read(A.TEMPERATURE, t + dt)
        assert v is not None and b.lo <= v <= b.hi
        assert app.read_bounds(A.TEMPERATURE, t + dt) == b  # static: the same interval


def test_read_bounds_of_a_static_mote_hold_for_ever_and_of_a_moving_one_for_now() -> None:
    still = TmoteSky(3, Static(5.0, 5.0).position, World())
    b = still.read_bounds(A.TEMPERATURE, 2.0)
    assert b is not None and b.until == math.inf
    path = Path(((5.0, 5.0), (50.0, 5.0)), speed_mps=1.0)
    moving = TmoteSky(4, path.position, World())
    for t in (2.0, 3.5):
        b = moving.read_bounds(A.TEMPERATURE, t)
        assert b is not None and b.until <= t  # where it is now, not where it goes


def test_read_bounds_end_when_the_fire_comes_and_come_back_when_it_has_passed() -> None:
    fire = Source("f", (Keyframe(0, 0, 50, 5, 80), Keyframe(100, 200, 50, 5, 80)), edge=2.0,
                  hold=False)  # fmt: skip
    app = TmoteSky(3, Static(100.0, 50.0).position, World(fires=(fire,)))
    b = app.read_bounds(A.TEMPERATURE, 0.0)
    assert b is not None and 20.0 < b.until < 50.0  # 2 m/s: 100 m less 5 + 16 m of reach
    assert app.read_bounds(A.TEMPERATURE, b.until - 1.0) == b  # kept until then
    assert app.read_bounds(A.TEMPERATURE, b.until) is None  # the fire may heat it now
    assert app.read_bounds(A.TEMPERATURE, 50.0) is None
    after = app.read_bounds(A.TEMPERATURE, 70.0)  # passed, and gone at t = 100 s
    assert after is not None and after.until == math.inf and (after.lo, after.hi) == (b.lo, b.hi)


def test_no_read_bounds_with_a_held_sample_or_another_attribute() -> None:
    app = TmoteSky(3, at(5.0, 5.0), World())
    assert app.read_bounds(A.TEMPERATURE, 1.0) is not None
    assert app.read_bounds(A.HUMIDITY, 1.0) is None
    app.sample_period = 2.0  # a read now would update the held sample
    assert app.read_bounds(A.TEMPERATURE, 1.0) is None
    assert not isinstance(Mica2(4, at(5.0, 5.0), World()), ReadBounds)  # reads every time
