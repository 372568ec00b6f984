"""Node kinds: the application layer of a mote.

A kind says which attributes a mote offers and how it obtains them: it reads
the world (:mod:`awaremw.world.fields`) at the mote's current position, adds
the sensor's noise, quantises to the raw ADC word the real chip would return,
and converts that raw word back to SI units with the datasheet formula, as the
TinySchema attribute functions on the paper's motes did. So readings carry the
chip's resolution, range and saturation, not just Gaussian noise.

Kinds:

* :class:`TmoteSky` (tmote sky / TelosB): Sensirion SHT11 temperature and
  humidity, Hamamatsu S1087 light photodiode on the 12-bit ADC;
* :class:`Mica2` with an MTS310-like board: thermistor on the 10-bit ADC,
  CdSe photocell, a sounder;
* :class:`Robot`: the mote carried by a robot (Romeo 4R); offers its position
  and battery, and its middleware emits Hello beacons (``hello_period``) that
  the others turn into the ``rssi:<robot id>`` attribute;
* :class:`Gateway`: the mote attached to the gateway, root of the collection
  tree (``is_root``), mains powered.

Every kind offers ``x``, ``y`` (m) and ``battery`` (V). Command handlers
(``led``, ``set_rate``, ``beep``) record what they did in
:attr:`NodeApp.actions`; a command a kind cannot execute is recorded as
refused, never raised (commands come from the network: remote input).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar

from awaremw.protocol import attributes as A
from awaremw.protocol.frames import CommandDef
from awaremw.world.fields import GAUSS_BOUND, Source, World
from awaremw.world.mobility import stays_put

Position = Callable[[float], tuple[float, float]]
EnergyProbe = Callable[[], float]  # joules spent so far by this mote

# The commands motes accept (every kind has these handlers; a kind without the
# hardware refuses on the mote): name -> arguments and what it does. The gateway
# and ``awaremw command`` refuse any other name with this list.
COMMANDS: Mapping[str, str] = {
    "led": "color=red|green|blue|all state=on|off|toggle (default all, toggle): set LEDs",
    "set_rate": "period_s=S (0..86400): hold each sensor reading for S seconds",
    "beep": "duration_ms=MS (1..10000): sound the sounder (mica2 only)",
}

# --------------------------------------------------------------------------- raw <-> SI


class Sht11:
    """Sensirion SHT1x (datasheet V5, 2011): 14-bit temperature, 12-bit humidity."""

    D1 = -39.7  # deg C at VDD = 3.5 V (tmote sky runs at 3 V: -39.66, same to 0.05)
    D2 = 0.01  # deg C per count, 14 bit
    C1, C2, C3 = -2.0468, 0.0367, -1.5955e-6  # 12-bit RH linearisation
    T1, T2 = 0.01, 0.00008  # temperature compensation of RH
    T_MAX, RH_MAX = 0x3FFF, 0x0FFF

    @classmethod
    def temperature_si(cls, so_t: int) -> float:
        return cls.D1 + cls.D2 * so_t

    @classmethod
    def temperature_raw(cls, t_c: float) -> int:
        return _clip(round((t_c - cls.D1) / cls.D2), 0, cls.T_MAX)

    @classmethod
    def humidity_si(cls, so_rh: int, t_c: float) -> float:
        lin = cls.C1 + cls.C2 * so_rh + cls.C3 * so_rh * so_rh
        true = (t_c - 25.0) * (cls.T1 + cls.T2 * so_rh) + lin
        return min(100.0, max(0.0, true))  # datasheet: values above 99 %RH mean saturated air

    @classmethod
    def humidity_raw(cls, rh: float, t_c: float) -> int:
        # Invert humidity_si: c3 so^2 + (c2 + (T-25) t2) so + (c1 + (T-25) t1 - rh) = 0.
        a = cls.C3
        b = cls.C2 + (t_c - 25.0) * cls.T2
        c = cls.C1 + (t_c - 25.0) * cls.T1 - rh
        disc = b * b - 4 * a * c
        if disc < 0:
            return cls.RH_MAX
        so = (-b + math.sqrt(disc)) / (2 * a)  # a < 0: this root is the small, physical one
        return _clip(round(so), 0, cls.RH_MAX)


class S1087:
    """Hamamatsu S1087 photodiode on the tmote sky: 100 kOhm load, 12-bit ADC, 1.5 V ref.

    lx = 0.625e6 * I[A] * 1000 with I = V / 100 kOhm (tmote sky datasheet), i.e.
    about 2.29 lx per count, saturating near 9.4 klx.
    """

    VREF, BITS, R_LOAD = 1.5, 12, 100e3
    FULL = (1 << BITS) - 1

    @classmethod
    def lux_si(cls, raw: int) -> float:
        v = raw / 4096.0 * cls.VREF
        return 0.625e6 * (v / cls.R_LOAD) * 1000.0

    @classmethod
    def lux_raw(cls, lux: float) -> int:
        v = lux / (0.625e6 * 1000.0) * cls.R_LOAD
        return _clip(round(v / cls.VREF * 4096.0), 0, cls.FULL)


class Mts310Thermistor:
    """MTS310 thermistor (Panasonic ERT-J1VR103J) in a divider with 10 kOhm, 10-bit ADC.

    R = R1 (1023 - adc) / adc; 1/T[K] = a + b ln R + c (ln R)^3 (MTS/MDA manual).
    """

    A, B, C = 0.00130705, 0.000214381, 0.000000093
    R1 = 10e3
    FULL = 1023

    @classmethod
    def temperature_si(cls, adc: int) -> float:
        adc = _clip(adc, 1, cls.FULL - 1)
        r = cls.R1 * (cls.FULL - adc) / adc
        ln = math.log(r)
        return 1.0 / (cls.A + cls.B * ln + cls.C * ln**3) - 273.15

    @classmethod
    def temperature_raw(cls, t_c: float) -> int:
        # Invert Steinhart-Hart: c x^3 + b x + (a - 1/T) = 0, x = ln R (Cardano, one real root).
        inv_t = 1.0 / (t_c + 273.15)
        y = (cls.A - inv_t) / cls.C
        xq = math.sqrt((cls.B / (3 * cls.C)) ** 3 + y * y / 4)
        x = math.cbrt(xq - y / 2) - math.cbrt(xq + y / 2)
        r = math.exp(x)
        return _clip(round(cls.FULL * cls.R1 / (cls.R1 + r)), 1, cls.FULL - 1)


class Mts310Photocell:
    """MTS310-like CdSe photocell in a divider with 10 kOhm, 10-bit ADC.

    The MTS310 manual gives no lux formula; we use the usual CdSe power law
    R = R10 (lx / 10)^-gamma with R10 = 40 kOhm, gamma = 0.7 (typical photocell
    datasheet values), so the reading rises with light and saturates in sunlight.
    """

    R_FIXED, R10, GAMMA = 10e3, 40e3, 0.7
    FULL = 1023

    @classmethod
    def lux_si(cls, adc: int) -> float:
        adc = _clip(adc, 1, cls.FULL - 1)
        r = cls.R_FIXED * (cls.FULL - adc) / adc
        return float(10.0 * (r / cls.R10) ** (-1.0 / cls.GAMMA))

    @classmethod
    def lux_raw(cls, lux: float) -> int:
        lux = max(lux, 1e-3)
        r = cls.R10 * (lux / 10.0) ** (-cls.GAMMA)
        return _clip(round(cls.FULL * cls.R_FIXED / (cls.R_FIXED + r)), 1, cls.FULL - 1)


def _clip(v: int, lo: int, hi: int) -> int:
    return lo if v < lo else hi if v > hi else v


# --------------------------------------------------------------------------- battery


@dataclass(frozen=True, slots=True)
class Battery:
    """Battery voltage from the energy a mote has spent (linear discharge model).

    ``capacity_j`` None means mains powered (constant ``v_full``). Two AA cells:
    about 2 x 1.5 V x 2.5 Ah = 27 kJ.
    """

    v_full: float = 3.0
    v_empty: float = 2.1
    capacity_j: float | None = 27_000.0

    def voltage(self, spent_j: float) -> float:
        if self.capacity_j is None:
            return self.v_full
        f = min(1.0, max(0.0, spent_j / self.capacity_j))
        return self.v_full - f * (self.v_full - self.v_empty)


# --------------------------------------------------------------------------- applications


@dataclass(frozen=True, slots=True)
class CommandAction:
    """What a command handler did on a mote (for tests, views and experiments)."""

    t: float
    node: int
    command: str
    args: tuple[tuple[str, Any], ...]
    done: bool  # False: refused (unknown command, bad argument, no such hardware)
    effect: str


@dataclass(frozen=True, slots=True)
class SensorNoise:
    """One sensor's measurement noise: N(0, sigma) plus a fraction of the value."""

    sigma: float = 0.0
    relative: float = 0.0


class NodeApp:
    """Base node kind: position, battery, command handlers; subclasses add sensors.

    Implements :class:`awaremw.protocol.attributes.Application`.
    """

    KIND: ClassVar[str] = "base"
    LEDS: ClassVar[tuple[str, ...]] = ("red", "green", "blue")
    HAS_SOUNDER: ClassVar[bool] = False
    DEFAULT_NOISE: ClassVar[Mapping[str, SensorNoise]] = {}
    DEFAULT_BATTERY: ClassVar[Battery] = Battery()

    def __init__(
        self,
        node_id: int,
        position: Position,
        world: World | None = None,
        *,
        battery: Battery | None = None,
        noise: Mapping[str, SensorNoise] | None = None,
        energy: EnergyProbe | None = None,
    ) -> None:
        self.node_id = node_id
        self.position = position
        self.world = world if world is not None else World()
        self.battery = battery or self.DEFAULT_BATTERY
        self.noise = {**self.DEFAULT_NOISE, **(noise or {})}
        self.energy = energy  # set later by the runtime when it has the counters
        self.actions: list[CommandAction] = []
        self.leds: dict[str, bool] = dict.fromkeys(self.LEDS, False)
        self.sample_period: float = 0.0  # "set_rate": sample-and-hold period, 0 = every read
        self._held: dict[int, tuple[float, float | None]] = {}
        # Sensor-read caches (group checks read a sensor every check period):
        # the fires that can reach the mote where it last was, and each noisy
        # sensor's constant part of its noise hash (World.noise_key).
        self._near: tuple[float, float, tuple[Source, ...]] | None = None
        self._noise_keys: dict[str, int] = {}
        self._readers: dict[int, Callable[[float], float | None]] = {
            A.X: lambda t: self.position(t)[0],
            A.Y: lambda t: self.position(t)[1],
            A.BATTERY: self._battery,
        }

    # ------------------------------------------------------------------ Application

    def offers(self, attr: int) -> bool:
        return attr in self._readers

    def read(self, attr: int, now: float) -> float | None:
        reader = self._readers.get(attr)
        if reader is None:
            return None
        if self.sample_period > 0 and attr not in (A.X, A.Y):
            held = self._held.get(attr)
            if held is not None and now - held[0] < self.sample_period:
                return held[1]
            value = reader(now)
            self._held[attr] = (now, value)
            return value
        return reader(now)

    def on_command(self, command: CommandDef, now: float) -> None:
        handler = {"led": self._cmd_led, "set_rate": self._cmd_set_rate, "beep": self._cmd_beep}
        args = dict(command.args)
        h = handler.get(command.name)
        if h is None:
            self._record(now, command, False, f"unknown command {command.name!r}")
            return
        done, effect = h(args)
        self._record(now, command, done, effect)

    # ------------------------------------------------------------------ helpers

    @property
    def attributes(self) -> list[str]:
        """IP-side names of the attributes this mote offers."""
        return [A.attribute_name(a) for a in sorted(self._readers)]

    def true_value(self, name: str, now: float) -> float:
        """The noise-free world value this mote's sensor for ``name`` would see."""
        x, y = self.position(now)
        if name == "temperature":
            return self.world.temperature_near(self._fires_at(x, y), x, y, now)
        return self.world.value(name, x, y, now)

    def _fires_at(self, x: float, y: float) -> tuple[Source, ...]:
        """``World.fires_reaching(x, y)``, kept for the position of the last call."""
        near = self._near
        if near is None or near[0] != x or near[1] != y:  # moved (or first call)
            near = self._near = (x, y, self.world.fires_reaching(x, y))
        return near[2]

    def _sensed(self, name: str, now: float) -> tuple[float, float]:
        """(noise-free value, noisy value) of field ``name`` at this mote, now."""
        true = self.true_value(name, now)
        n = self.noise.get(name)
        if n is None:
            return true, true
        key = self._noise_keys.get(name)
        if key is None:
            key = self._noise_keys[name] = self.world.noise_key(self.node_id, name)
        sigma = n.sigma + n.relative * abs(true)
        return true, true + self.world.noise_at(key, now, sigma)

    def _battery(self, now: float) -> float:
        spent = self.energy() if self.energy is not None else 0.0
        return self.battery.voltage(spent)

    def _record(self, now: float, cmd: CommandDef, done: bool, effect: str) -> None:
        self.actions.append(CommandAction(now, self.node_id, cmd.name, cmd.args, done, effect))

    # ------------------------------------------------------------------ commands

    def _cmd_led(self, args: dict[str, Any]) -> tuple[bool, str]:
        """``led`` {color: red|green|blue|all, state: on|off|toggle} (default: all, toggle)."""
        color = str(args.get("color", "all"))
        state = args.get("state", "toggle")
        colors = list(self.LEDS) if color == "all" else [color]
        if any(c not in self.leds for c in colors):
            return False, f"no {color} LED (has {', '.join(self.LEDS)})"
        if state in (True, "on", 1):
            for c in colors:
                self.leds[c] = True
        elif state in (False, "off", 0):
            for c in colors:
                self.leds[c] = False
        elif state == "toggle":
            for c in colors:
                self.leds[c] = not self.leds[c]
        else:
            return False, f"bad LED state {state!r} (on, off or toggle)"
        lit = ",".join(c for c in self.LEDS if self.leds[c]) or "none"
        return True, f"LEDs lit: {lit}"

    def _cmd_set_rate(self, args: dict[str, Any]) -> tuple[bool, str]:
        """``set_rate`` {period_s: float >= 0}: sensor sample-and-hold period."""
        p = args.get("period_s")
        if isinstance(p, bool) or not isinstance(p, int | float) or not 0 <= p < 86400:
            return False, f"set_rate needs period_s in [0, 86400), got {p!r}"
        self.sample_period = float(p)
        self._held.clear()
        return True, f"sensor sample period {self.sample_period:g} s"

    def _cmd_beep(self, args: dict[str, Any]) -> tuple[bool, str]:
        """``beep`` {duration_ms: int}: sound the sounder (mica2 sensor board only)."""
        if not self.HAS_SOUNDER:
            return False, f"{self.KIND} has no sounder"
        ms = args.get("duration_ms", 100)
        if isinstance(ms, bool) or not isinstance(ms, int | float) or not 0 < ms <= 10_000:
            return False, f"beep needs duration_ms in (0, 10000], got {ms!r}"
        return True, f"beeped {ms:g} ms"


class _ColdSpot:
    """A tmote's temperature bounds at one position and noise setting while no
    fire heats it, and until when they hold (``fresh_until``: recomputed after)."""

    __slots__ = ("bounds", "fires", "fresh_until", "hi", "lo", "noise", "x", "y")

    def __init__(
        self,
        x: float,
        y: float,
        noise: SensorNoise | None,
        lo: float,
        hi: float,
        fires: tuple[Source, ...],
    ) -> None:
        self.x, self.y, self.noise = x, y, noise
        self.lo, self.hi = lo, hi
        self.fires = fires  # those that can ever reach (x, y)
        self.bounds: A.Bounds | None = None
        self.fresh_until = -math.inf


class TmoteSky(NodeApp):
    """tmote sky: SHT11 temperature + humidity, S1087 light (12-bit ADC)."""

    KIND = "tmote"
    DEFAULT_NOISE: ClassVar[Mapping[str, SensorNoise]] = {
        "temperature": SensorNoise(sigma=0.15),  # SHT11: +-0.4 degC typical accuracy
        "humidity": SensorNoise(sigma=1.0),  # +-3 %RH
        "light": SensorNoise(sigma=3.0, relative=0.02),
    }

    def __init__(
        self, node_id: int, position: Position, world: World | None = None, **kw: Any
    ) -> None:
        super().__init__(node_id, position, world, **kw)
        self._readers[A.TEMPERATURE] = self._temperature
        self._readers[A.HUMIDITY] = self._humidity
        self._readers[A.LIGHT] = self._light
        self._spot: _ColdSpot | None = None  # read_bounds at the last position

    def read_bounds(self, attr: int, now: float) -> A.Bounds | None:
        """:class:`~awaremw.protocol.attributes.ReadBounds`: the temperature of a
        mote no fire heats (ambient, plus noise of at most ``GAUSS_BOUND`` sigmas,
        through the SHT11 conversion, which is monotonic), until a fire may come
        near (:meth:`~awaremw.world.fields.Source.cold_until`; for ever if none
        can) if the mote is static, else at ``now`` only. None while a fire may
        heat it, for other attributes, and with a sample-and-hold period (a read
        then updates the held sample)."""
        if attr != A.TEMPERATURE or self.sample_period > 0:
            return None
        x, y = self.position(now)
        n = self.noise.get("temperature")
        spot = self._spot
        if spot is None or spot.x != x or spot.y != y or spot.noise is not n:
            spot = self._spot = self._cold_spot(x, y, now, n)
        if now < spot.fresh_until:
            return spot.bounds
        # The horizon passed (or held at one instant only): when may a fire come?
        cold = min((f.cold_until(x, y, now) for f in spot.fires), default=math.inf)
        if cold <= now:
            spot.bounds, spot.fresh_until = None, now
        else:
            until = cold if stays_put(self.position) else now
            spot.bounds, spot.fresh_until = A.Bounds(spot.lo, spot.hi, until), until
        return spot.bounds

    def _cold_spot(self, x: float, y: float, now: float, n: SensorNoise | None) -> _ColdSpot:
        """The bounds at (x, y) while no fire heats it."""
        fires = self._fires_at(x, y)
        # The noise-free value is then the same at every time: ambient (+ texture).
        true = self.world.temperature_near((), x, y, now)
        # _sensed adds sigma * g with |g| < GAUSS_BOUND (rounding is monotonic).
        spread = 0.0 if n is None else (n.sigma + n.relative * abs(true)) * GAUSS_BOUND
        lo = Sht11.temperature_si(Sht11.temperature_raw(true - spread))
        hi = Sht11.temperature_si(Sht11.temperature_raw(true + spread))
        return _ColdSpot(x, y, n, lo, hi, fires)

    def raw_temperature(self, now: float) -> int:
        return Sht11.temperature_raw(self._sensed("temperature", now)[1])

    def raw_humidity(self, now: float) -> int:
        t = Sht11.temperature_si(self.raw_temperature(now))
        return Sht11.humidity_raw(self._sensed("humidity", now)[1], t)

    def raw_light(self, now: float) -> int:
        return S1087.lux_raw(self._sensed("light", now)[1])

    def _temperature(self, now: float) -> float:
        return Sht11.temperature_si(self.raw_temperature(now))

    def _humidity(self, now: float) -> float:
        t = Sht11.temperature_si(self.raw_temperature(now))
        return Sht11.humidity_si(self.raw_humidity(now), t)

    def _light(self, now: float) -> float:
        return S1087.lux_si(self.raw_light(now))


class Mica2(NodeApp):
    """Mica2 with an MTS310-like sensor board: thermistor, photocell, sounder."""

    KIND = "mica2"
    LEDS = ("red", "green", "yellow")
    HAS_SOUNDER = True
    DEFAULT_NOISE: ClassVar[Mapping[str, SensorNoise]] = {
        "temperature": SensorNoise(sigma=0.3),
        "light": SensorNoise(sigma=5.0, relative=0.05),
    }

    def __init__(
        self, node_id: int, position: Position, world: World | None = None, **kw: Any
    ) -> None:
        super().__init__(node_id, position, world, **kw)
        self._readers[A.TEMPERATURE] = self._temperature
        self._readers[A.LIGHT] = self._light

    def raw_temperature(self, now: float) -> int:
        return Mts310Thermistor.temperature_raw(self._sensed("temperature", now)[1])

    def raw_light(self, now: float) -> int:
        return Mts310Photocell.lux_raw(self._sensed("light", now)[1])

    def _temperature(self, now: float) -> float:
        return Mts310Thermistor.temperature_si(self.raw_temperature(now))

    def _light(self, now: float) -> float:
        return Mts310Photocell.lux_si(self.raw_light(now))


class Robot(NodeApp):
    """The mote carried by a robot: position (the robot's) and battery; its
    middleware beacons Hello frames (see :data:`KIND_CONFIG`)."""

    KIND = "robot"
    DEFAULT_BATTERY = Battery(v_full=12.6, v_empty=10.5, capacity_j=None)  # robot's supply


class Gateway(NodeApp):
    """The gateway's mote: collection root, mains powered."""

    KIND = "gateway"
    DEFAULT_BATTERY = Battery(capacity_j=None)


# --------------------------------------------------------------------------- registry


@dataclass(frozen=True, slots=True)
class KindInfo:
    """A node kind: its application class, default radio preset and the
    middleware settings it implies (a deployment may override them)."""

    name: str
    app: type[NodeApp]
    radio: str
    config: Mapping[str, Any] = field(default_factory=dict)
    description: str = ""


DEFAULT_HELLO_PERIOD = 0.5  # s: the robot mote's beacon (Romeo 4R's mote beaconed a few Hz)

KINDS: dict[str, KindInfo] = {
    "tmote": KindInfo("tmote", TmoteSky, "cc2420", {}, "tmote sky: SHT11, S1087"),
    "mica2": KindInfo("mica2", Mica2, "cc1000", {}, "Mica2 + MTS310-like board"),
    "robot": KindInfo(
        "robot",
        Robot,
        "cc1000",
        {"hello_period": DEFAULT_HELLO_PERIOD},
        "mote on a robot; emits Hello beacons",
    ),
    "gateway": KindInfo("gateway", Gateway, "cc2420", {"is_root": True}, "collection root"),
}
ALIASES: dict[str, str] = {"tmote-sky": "tmote", "telosb": "tmote"}


def kind_info(name: str) -> KindInfo:
    """Look a kind up by name or alias; unknown names raise KeyError with the list."""
    key = ALIASES.get(name, name)
    if key not in KINDS:
        known = ", ".join([*KINDS, *ALIASES])
        raise KeyError(f"unknown node kind {name!r}; known: {known}")
    return KINDS[key]
