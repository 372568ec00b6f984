"""Environmental fields: pure functions of (position, time, seed).

The world the motes sense. Every value here is computed, never stored or
drawn from a shared random generator, so motes in different processes (or on
different hosts) read one consistent world without talking to each other:

* **sources** (fires, gas leaks, lamps) follow a script of keyframes
  ``(t, x, y, radius, peak)`` linearly interpolated in time; a source grows,
  moves and fades by its keyframes, two sources that approach each other merge
  into one hot area and two that part split it;
* **fields** combine the sources over the ambient: temperature is ambient plus
  the *hottest* fire at that point (overlapping fires do not add up to an
  unphysical sum), gas concentrations and light add up, relative humidity
  follows temperature at constant absolute humidity (Magnus formula);
* **measurement noise** is a Gaussian drawn from a hash of
  ``(seed, node, sensor, time step)`` (:func:`gauss_hash`).

The deployment's ``[world]`` table configures it (see docs/world.md);
:func:`awaremw.world.table.world_from_table` reads it and reports a bad table
as :class:`WorldError` naming the offending key.
"""

from __future__ import annotations

import functools
import hashlib
import itertools
import math
import struct
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, NamedTuple

FIELDS = ("temperature", "humidity", "light", "gas")


class WorldError(ValueError):
    """A ``[world]`` table that cannot be understood (bad deployment file)."""


# --------------------------------------------------------------------------- seeded hashing


_M64 = 0xFFFFFFFFFFFFFFFF


@functools.lru_cache(maxsize=4096)
def _str_u64(s: str) -> int:
    return int.from_bytes(hashlib.blake2b(s.encode(), digest_size=8).digest(), "little")


def hash_u64(*parts: int | float | str) -> int:
    """A stable 64-bit hash of ``parts`` (same value in every process and run).

    Integers are mixed directly, floats by their IEEE bits, strings by a cached
    BLAKE2b digest; each part goes through a splitmix64 round.
    """
    h = 0x243F6A8885A308D3
    for p in parts:
        if type(p) is int:  # the common case first (same value as the else branch)
            v = p & _M64
        elif isinstance(p, str):
            v = _str_u64(p)
        elif isinstance(p, float):
            v = struct.unpack("<Q", struct.pack("<d", p))[0] ^ 0x5851F42D4C957F2D
        else:
            v = p & _M64
        # the splitmix64 finaliser of h ^ v, inlined (hot: every sensor read hashes its noise)
        x = ((h ^ v) + 0x9E3779B97F4A7C15) & _M64
        x = ((x ^ (x >> 30)) * 0xBF58476D1CE4E5B9) & _M64
        x = ((x ^ (x >> 27)) * 0x94D049BB133111EB) & _M64
        h = x ^ (x >> 31)
    return h


def uniform_hash(*parts: int | float | str) -> float:
    """A uniform number in [0, 1) from a hash of ``parts``."""
    return (hash_u64(*parts) >> 11) * (1.0 / (1 << 53))


def gauss_hash(*parts: int | float | str) -> float:
    """A standard normal number from a hash of ``parts`` (Box-Muller on 2 x 32 bits)."""
    return _gauss_of(hash_u64(*parts))


# |_gauss_of(v)| for any 64-bit v is below this: u1 >= 2**-33, so the radius
# sqrt(-2 ln u1) <= sqrt(66 ln 2) = 6.7637..., and |cos| <= 1.
GAUSS_BOUND = 6.77


def _gauss_of(v: int) -> float:
    u1 = ((v >> 32) + 0.5) / 4294967296.0  # in (0, 1): log never sees 0
    u2 = (v & 0xFFFFFFFF) / 4294967296.0
    return math.sqrt(-2.0 * math.log(u1)) * math.cos(2.0 * math.pi * u2)


@functools.lru_cache(maxsize=1 << 16, typed=True)
def _noise_prefix(seed: int, node: int, sensor: str) -> int:
    """:func:`hash_u64`'s state after the parts ``(seed, node, sensor)`` (one per
    sensor of a mote; the noise hash goes on from it with the time step)."""
    return hash_u64(seed, node, sensor)


def _hash_more(h: int, part: int) -> int:
    """:func:`hash_u64` continued from state ``h`` with one more integer ``part``."""
    x = ((h ^ (part & _M64)) + 0x9E3779B97F4A7C15) & _M64
    x = ((x ^ (x >> 30)) * 0xBF58476D1CE4E5B9) & _M64
    x = ((x ^ (x >> 27)) * 0x94D049BB133111EB) & _M64
    return x ^ (x >> 31)


# --------------------------------------------------------------------------- sources


@dataclass(frozen=True, slots=True)
class Keyframe:
    """State of a source at time ``t``; values between keyframes are interpolated."""

    t: float
    x: float
    y: float
    radius: float  # m: flat core of the profile (0 for a pure Gaussian plume)
    peak: float  # value at the core (deg C above ambient, ppm, lx)


class SourceState(NamedTuple):
    """A source at one instant (a tuple: one is built per sensor read)."""

    x: float
    y: float
    radius: float
    peak: float


@dataclass(frozen=True, slots=True)
class Source:
    """A scripted emitter. Profile: ``peak`` inside ``radius``, Gaussian falloff of
    width ``edge`` outside it. Absent before its first keyframe; after the last
    it holds its final state when ``hold`` (a fire keeps burning), else is gone.

    A fire also gives off ``gas`` (ppm at its core) and ``light`` (lx at its
    core) with the same profile.
    """

    name: str
    keyframes: tuple[Keyframe, ...]
    edge: float = 1.0
    hold: bool = True
    gas: float = 0.0
    light: float = 0.0

    def __post_init__(self) -> None:
        if not self.keyframes:
            raise WorldError(f"source {self.name!r} has no keyframes")
        ts = [k.t for k in self.keyframes]
        if any(b < a for a, b in itertools.pairwise(ts)):
            raise WorldError(f"source {self.name!r}: keyframe times must not decrease")
        if self.edge <= 0:
            raise WorldError(f"source {self.name!r}: edge must be > 0")
        for k in self.keyframes:
            if k.radius < 0:
                raise WorldError(f"source {self.name!r}: radius must be >= 0 (t={k.t})")

    @property
    def start(self) -> float:
        return self.keyframes[0].t

    @property
    def end(self) -> float | None:
        return None if self.hold else self.keyframes[-1].t

    def state(self, t: float) -> SourceState | None:
        """Interpolated state at ``t``, or None while the source does not exist."""
        s = self._at(t)
        return None if s is None else SourceState(*s)

    def _at(self, t: float) -> tuple[float, float, float, float] | None:
        """:meth:`state` as a plain tuple (cheaper to build: one per sensor read)."""
        ks = self.keyframes
        if t < ks[0].t:
            return None
        if t >= ks[-1].t:
            if not self.hold and t > ks[-1].t:
                return None
            k = ks[-1]
            return k.x, k.y, k.radius, k.peak
        lo, hi = 0, len(ks) - 1  # binary search: ks[lo].t <= t < ks[hi].t
        while hi - lo > 1:
            mid = (lo + hi) // 2
            if ks[mid].t <= t:
                lo = mid
            else:
                hi = mid
        a, b = ks[lo], ks[hi]
        f = 0.0 if b.t == a.t else (t - a.t) / (b.t - a.t)
        return (
            a.x + f * (b.x - a.x),
            a.y + f * (b.y - a.y),
            a.radius + f * (b.radius - a.radius),
            a.peak + f * (b.peak - a.peak),
        )

    def profile(self, x: float, y: float, t: float) -> float:
        """0..1 shape at (x, y): 1 in the core, Gaussian falloff outside it."""
        s = self._at(t)
        return 0.0 if s is None else self._shape(s[0], s[1], s[2], x, y)

    def value(self, x: float, y: float, t: float) -> float:
        s = self._at(t)
        return 0.0 if s is None else s[3] * self._shape(s[0], s[1], s[2], x, y)

    def _shape(self, sx: float, sy: float, radius: float, x: float, y: float) -> float:
        d = math.hypot(x - sx, y - sy) - radius
        if d <= 0:
            return 1.0
        z = d / self.edge
        return 0.0 if z > _CUT_EDGES else math.exp(-0.5 * z * z)

    def reaches(self, x: float, y: float) -> bool:
        """False when (x, y) is, at every time, so far from the source that its
        profile there is exactly 0 (beyond the cut of the Gaussian falloff at
        ``_CUT_EDGES`` edges from the largest radius, with a margin for
        rounding): a static mote then never needs to evaluate it."""
        ks = self.keyframes
        reach = max(k.radius for k in ks) + _CUT_EDGES * self.edge
        # The centre moves on the polyline of the keyframes (linear interpolation).
        pairs = zip(ks, ks[1:] or ks, strict=False)
        d = min(_to_segment(x, y, a.x, a.y, b.x, b.y) for a, b in pairs)
        return d <= _with_margin(reach)

    def cold_until(self, x: float, y: float, t: float) -> float:
        """A time before which, from ``t`` on, the profile at (x, y) is exactly 0
        (``t`` or earlier: it may not be 0 now; ``inf``: never again). Exact up to
        a margin: the centre moves on straight lines between keyframes, and the
        reach is the largest radius of each leg plus the falloff's cut."""
        ks = self.keyframes
        if not self.hold and t > ks[-1].t:
            return math.inf  # gone
        cut = _CUT_EDGES * self.edge
        for a, b in itertools.pairwise(ks):
            if b.t <= t:
                continue
            t0 = max(t, a.t)
            f = 0.0 if b.t == a.t else (t0 - a.t) / (b.t - a.t)
            cx, cy = a.x + f * (b.x - a.x), a.y + f * (b.y - a.y)
            reach = max(a.radius, b.radius) + cut
            s = _first_within(x - cx, y - cy, b.x - a.x, b.y - a.y, b.t - a.t, reach)
            if s is not None and t0 + s <= b.t:
                return max(t, t0 + s - 1e-6)
        # At its last keyframe (for good if held, else at that instant only; a
        # last leg of no duration jumps there).
        k = ks[-1]
        if math.hypot(x - k.x, y - k.y) <= _with_margin(k.radius + cut):
            return max(t, k.t - 1e-6)
        return math.inf


_CUT_EDGES = 8.0  # a source's falloff is cut (0) this many edges out of its radius


def _with_margin(reach: float) -> float:
    """A source's reach widened for rounding: a point this far is taken as reached."""
    return reach * (1.0 + 1e-9) + 1e-6


def _first_within(
    px: float, py: float, dx: float, dy: float, dt: float, reach: float
) -> float | None:
    """The first s >= 0 at which a point at (px, py) from a centre moving by
    (dx, dy) every dt seconds is within ``reach`` of it (None: never)."""
    r = _with_margin(reach)
    c = px * px + py * py - r * r
    if c <= 0:
        return 0.0
    if dt <= 0:
        return None
    vx, vy = dx / dt, dy / dt
    a = vx * vx + vy * vy
    b = px * vx + py * vy  # > 0: the centre moves towards the point
    disc = b * b - a * c
    if a == 0 or b <= 0 or disc < 0:
        return None
    return (b - math.sqrt(disc)) / a


def _to_segment(x: float, y: float, ax: float, ay: float, bx: float, by: float) -> float:
    """Distance from (x, y) to the segment from (ax, ay) to (bx, by)."""
    dx, dy = bx - ax, by - ay
    n = dx * dx + dy * dy
    f = 0.0 if n == 0 else min(1.0, max(0.0, ((x - ax) * dx + (y - ay) * dy) / n))
    return math.hypot(x - (ax + f * dx), y - (ay + f * dy))


# --------------------------------------------------------------------------- world


@functools.lru_cache(maxsize=65536)
def _lattice(seed: int, i: int, j: int) -> float:
    return 2.0 * uniform_hash(seed, "texture", i, j) - 1.0


def _magnus_psat(t_c: float) -> float:
    """Saturation vapour pressure (hPa) over water, Magnus formula (Sonntag 1990)."""
    return 6.112 * math.exp(17.62 * t_c / (243.12 + t_c))


@dataclass(frozen=True, slots=True)
class World:
    """The environment: ambient values, scripted sources, noise seed."""

    seed: int = 0
    ambient_temperature: float = 20.0  # deg C
    ambient_humidity: float = 50.0  # %RH at ambient temperature
    ambient_light: float = 400.0  # lx
    ambient_gas: float = 0.0  # ppm
    # Static spatial texture of the ambient temperature (deg C amplitude, m scale):
    # a smooth, seeded value-noise so that neighbouring motes differ a little.
    variation: float = 0.0
    variation_scale: float = 5.0
    noise_step: float = 0.5  # s: a sensor's noise changes once per step
    fires: tuple[Source, ...] = ()
    gas_sources: tuple[Source, ...] = ()
    lights: tuple[Source, ...] = ()
    extra: Mapping[str, Any] = field(default_factory=dict)  # unknown keys, kept for others

    # ------------------------------------------------------------------ noise-free fields

    def temperature(self, x: float, y: float, t: float) -> float:
        """Air temperature (deg C) at (x, y) at time t, without sensor noise."""
        return self.temperature_near(self.fires, x, y, t)

    def fires_reaching(self, x: float, y: float) -> tuple[Source, ...]:
        """The fires whose heat can ever reach (x, y) (:meth:`Source.reaches`)."""
        return tuple(f for f in self.fires if f.reaches(x, y))

    def temperature_near(self, fires: tuple[Source, ...], x: float, y: float, t: float) -> float:
        """:meth:`temperature` at (x, y), given ``fires_reaching(x, y)`` (the same
        value: every other fire contributes exactly 0 there, and the hottest
        fire's contribution is floored at 0)."""
        base = self.ambient_temperature + (self._texture(x, y) if self.variation else 0.0)
        if not fires:
            hottest = 0.0
        elif len(fires) == 1:
            hottest = fires[0].value(x, y, t)
        else:
            hottest = max(f.value(x, y, t) for f in fires)
        return base + max(0.0, hottest)

    def humidity(self, x: float, y: float, t: float) -> float:
        """Relative humidity (%RH): ambient absolute humidity at the local temperature."""
        ta = self.ambient_temperature
        tl = self.temperature(x, y, t)
        rh = self.ambient_humidity * _magnus_psat(ta) / _magnus_psat(tl)
        return min(100.0, max(0.0, rh))

    def light(self, x: float, y: float, t: float) -> float:
        """Illuminance (lx): ambient plus lamps plus the glow of fires."""
        v = self.ambient_light
        v += sum(s.value(x, y, t) for s in self.lights)
        v += sum(f.light * f.profile(x, y, t) for f in self.fires if f.light)
        return max(0.0, v)

    def gas(self, x: float, y: float, t: float) -> float:
        """Gas concentration (ppm): ambient plus leaks plus the smoke of fires."""
        v = self.ambient_gas
        v += sum(s.value(x, y, t) for s in self.gas_sources)
        v += sum(f.gas * f.profile(x, y, t) for f in self.fires if f.gas)
        return max(0.0, v)

    def value(self, name: str, x: float, y: float, t: float) -> float:
        """A field by name (one of :data:`FIELDS`)."""
        if name == "temperature":
            return self.temperature(x, y, t)
        if name == "humidity":
            return self.humidity(x, y, t)
        if name == "light":
            return self.light(x, y, t)
        if name == "gas":
            return self.gas(x, y, t)
        raise KeyError(f"unknown field {name!r}; known: {', '.join(FIELDS)}")

    # ------------------------------------------------------------------ noise

    def noise(self, node: int, sensor: str, t: float, sigma: float) -> float:
        """Measurement noise of ``node``'s ``sensor`` at ``t``: N(0, sigma), constant
        within one :attr:`noise_step`, identical in every process that asks."""
        if sigma == 0:
            return 0.0
        step = math.floor(t / self.noise_step)
        # gauss_hash(self.seed, node, sensor, step), the first three parts' rounds cached.
        return sigma * _gauss_of(_hash_more(_noise_prefix(self.seed, node, sensor), step))

    def noise_key(self, node: int, sensor: str) -> int:
        """The constant part of the noise hash of ``node``'s ``sensor``, for :meth:`noise_at`."""
        return hash_u64(self.seed, node, sensor)

    def noise_at(self, key: int, t: float, sigma: float) -> float:
        """:meth:`noise` with its ``noise_key`` (the same value, one lookup less)."""
        if sigma == 0:
            return 0.0
        return sigma * _gauss_of(_hash_more(key, math.floor(t / self.noise_step)))

    # ------------------------------------------------------------------ internals

    def _texture(self, x: float, y: float) -> float:
        if not self.variation:
            return 0.0
        # Bilinear value noise on a seeded lattice: smooth, static, bounded.
        gx, gy = x / self.variation_scale, y / self.variation_scale
        ix, iy = math.floor(gx), math.floor(gy)
        fx, fy = gx - ix, gy - iy
        fx, fy = fx * fx * (3 - 2 * fx), fy * fy * (3 - 2 * fy)

        def lat(i: int, j: int) -> float:
            return _lattice(self.seed, i, j)

        top = lat(ix, iy) * (1 - fx) + lat(ix + 1, iy) * fx
        bot = lat(ix, iy + 1) * (1 - fx) + lat(ix + 1, iy + 1) * fx
        return self.variation * (top * (1 - fy) + bot * fy)
