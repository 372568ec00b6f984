"""The radio model: presets, path loss, shadowing, packet reception, energy.

Pure and deterministic: no I/O, no clock, no global random. Every random
quantity (static shadowing of a link, per-packet fading, the uniform draw that
decides a loss, MAC backoff) is a function of a seeded 64-bit hash of
``(seed, link, packet key)``, so every process that shares the seed takes the
same decision for the same packet, whatever else it did before. That is what
lets the Zenoh medium (receivers in many processes) and the virtual-clock
driver give identical results. See ``docs/radio.md`` for the formulas and the
sources of the preset numbers.

Sign conventions: path loss and shadowing are losses in dB;
``RSSI = P_tx - PL(d) - X_static - X_packet`` with ``X ~ N(0, sigma)``.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from statistics import NormalDist
from typing import Final, Protocol

# --------------------------------------------------------------------------- hashing

# Public: radio/reception.py inlines packet_hash and decide with them (the hot path).

M64: Final = 0xFFFFFFFFFFFFFFFF
GOLDEN: Final = 0x9E3779B97F4A7C15
MUL: Final = 0xBF58476D1CE4E5B9

# Hash domains: independent streams for independent random quantities.
DOMAIN_SHADOW: Final = 1
DOMAIN_FADING: Final = 2
DOMAIN_BACKOFF: Final = 3


def splitmix64(x: int) -> int:
    """The splitmix64 finaliser: a fast, well-mixed 64-bit bijection."""
    x = (x + GOLDEN) & M64
    x = ((x ^ (x >> 30)) * 0xBF58476D1CE4E5B9) & M64
    x = ((x ^ (x >> 27)) * 0x94D049BB133111EB) & M64
    return x ^ (x >> 31)


def link_hash(seed: int, domain: int, a: int, b: int) -> int:
    """64-bit hash of ``(seed, domain, a, b)``; ``a`` and ``b`` are 16-bit ids."""
    return splitmix64(
        splitmix64(seed & M64) ^ ((domain << 40) | ((a & 0xFFFF) << 16) | (b & 0xFFFF))
    )


def packet_hash(link_h: int, packet_key: int) -> int:
    """64-bit hash of a packet on a link (``link_h`` from :func:`link_hash`).

    One multiply-xorshift round: ``link_h`` is already a well-mixed random
    word per link and ``packet_key * golden`` spreads the key, so one round is
    enough here, and this is the per-packet, per-receiver hot path.
    """
    z = ((link_h ^ ((packet_key * GOLDEN) & M64)) * MUL) & M64
    return z ^ (z >> 31)


def packet_key(seq: int, attempt: int = 0, ack: bool = False) -> int:
    """The packet key of a frame: sender's link sequence, attempt (0 = first), ACK flag.

    ``seq`` is the sender's per-mote transmission counter (carried in the
    emulator envelope); retries of a unicast keep ``seq`` and bump ``attempt``;
    the link-layer ACK of an attempt uses the same key with ``ack=True``.
    """
    if not 0 <= attempt < 128:
        raise ValueError(f"attempt={attempt} is outside 0..127")
    return (seq << 8) | (attempt << 1) | int(ack)


# Inverse normal CDF sampled at 2**12 mid-points: z = NORMAL[h >> 52]. The table
# bounds every deviate to |z| <= _Z_MAX (about 3.49), which keeps the set of
# links that can ever deliver small (see max_range_m and never_delivers).
_NORMAL_BITS: Final = 12
NORMAL: Final[tuple[float, ...]] = tuple(
    NormalDist().inv_cdf((i + 0.5) / (1 << _NORMAL_BITS)) for i in range(1 << _NORMAL_BITS)
)
Z_MAX: Final = NORMAL[-1]
SHIFT: Final = 64 - _NORMAL_BITS
U32: Final = 1.0 / 4294967296.0


def uniform(h: int) -> float:
    """Uniform deviate in [0, 1) from the low 32 bits of a 64-bit hash."""
    return (h & 0xFFFFFFFF) * U32


# --------------------------------------------------------------------------- presets


@dataclass(frozen=True)
class RadioPreset:
    """Everything the emulator needs to know about one radio chip and its MAC.

    ``mtu`` is the largest msgpack frame (our bytes); ``phy_overhead_bytes``
    (preamble, sync, length, MAC header, FCS) is added for airtime, energy and
    PRR. ``ack_bytes`` is the whole ACK on the air. Currents are at
    ``voltage_v``; ``tx_current_table`` maps TX power (dBm) to current (mA)
    and is interpolated linearly (empty: ``tx_current_ma`` at any power).
    """

    name: str
    freq_mhz: float
    bitrate_bps: float
    modulation: str  # "oqpsk" (802.15.4 DSSS) or "ncfsk" (non-coherent FSK)
    noise_bandwidth_hz: float  # Bn, used by the FSK BER formula
    tx_power_dbm: float
    min_tx_power_dbm: float
    max_tx_power_dbm: float
    sensitivity_dbm: float
    noise_floor_dbm: float
    d0_m: float
    pl_d0_db: float
    path_loss_exponent: float
    shadowing_sigma_db: float
    fading_sigma_db: float
    mtu: int
    phy_overhead_bytes: int
    ack_bytes: int
    max_retries: int
    ack_timeout_s: float
    ack_turnaround_s: float
    mac_backoff_s: float
    voltage_v: float
    tx_current_ma: float
    rx_current_ma: float
    tx_current_table: tuple[tuple[float, float], ...] = field(default=())
    # SINR (dB) a frame needs, at every instant of its reception, to survive
    # overlapping frames (capture; radio/mac.py). Son, Krishnamachari and
    # Heidemann (SenSys 2006) measured a threshold of a few dB on CC1000 motes,
    # with a grey region of about 6 dB across radios: docs/radio.md.
    capture_threshold_db: float = 4.0

    def __post_init__(self) -> None:
        if self.modulation not in ("oqpsk", "ncfsk"):
            raise ValueError(f"unknown modulation {self.modulation!r}")
        if not self.min_tx_power_dbm <= self.tx_power_dbm <= self.max_tx_power_dbm:
            raise ValueError("default tx power outside [min, max]")
        for name in ("bitrate_bps", "d0_m", "path_loss_exponent", "voltage_v"):
            if getattr(self, name) <= 0:
                raise ValueError(f"{name} must be > 0")
        if self.mtu <= 0 or self.phy_overhead_bytes < 0 or self.ack_bytes <= 0:
            raise ValueError("mtu, phy_overhead_bytes, ack_bytes out of range")
        if not 0 <= self.max_retries < 127:
            raise ValueError("max_retries must be in 0..126")
        if list(self.tx_current_table) != sorted(self.tx_current_table):
            raise ValueError("tx_current_table must be sorted by power")

    def check_tx_power(self, dbm: float) -> None:
        """Raise ValueError if ``dbm`` is outside the chip's programmable range."""
        if not self.min_tx_power_dbm <= dbm <= self.max_tx_power_dbm:
            raise ValueError(
                f"tx power {dbm} dBm outside {self.name}'s "
                f"[{self.min_tx_power_dbm}, {self.max_tx_power_dbm}] dBm"
            )

    def tx_current_at(self, dbm: float | None = None) -> float:
        """TX current (mA) at ``dbm`` (default power when None), interpolated."""
        t = self.tx_current_table
        if dbm is None or not t:
            return self.tx_current_ma
        if dbm <= t[0][0]:
            return t[0][1]
        for (p0, i0), (p1, i1) in itertools.pairwise(t):
            if dbm <= p1:
                return i0 + (i1 - i0) * (dbm - p0) / (p1 - p0)
        return t[-1][1]

    def airtime_s(self, frame_len: int) -> float:
        """Seconds on the air for a frame of ``frame_len`` bytes (ours) plus overhead."""
        return (frame_len + self.phy_overhead_bytes) * 8.0 / self.bitrate_bps

    @property
    def ack_airtime_s(self) -> float:
        return self.ack_bytes * 8.0 / self.bitrate_bps

    def tx_energy_mj(self, frame_len: int, tx_power_dbm: float | None = None) -> float:
        """E = V * I_tx * t (V * mA * s = mJ)."""
        return self.voltage_v * self.tx_current_at(tx_power_dbm) * self.airtime_s(frame_len)

    def rx_energy_mj(self, frame_len: int) -> float:
        return self.voltage_v * self.rx_current_ma * self.airtime_s(frame_len)


# CC2420 (Tmote Sky, MicaZ, TelosB): 802.15.4 O-QPSK at 2.4 GHz. TX currents at the
# eight PA_LEVEL settings of the datasheet (SWRS041, "Output power programming").
CC2420 = RadioPreset(
    name="cc2420",
    freq_mhz=2405.0,
    bitrate_bps=250_000.0,
    modulation="oqpsk",
    noise_bandwidth_hz=2_000_000.0,
    tx_power_dbm=0.0,
    min_tx_power_dbm=-25.0,
    max_tx_power_dbm=0.0,
    sensitivity_dbm=-95.0,
    noise_floor_dbm=-98.0,
    d0_m=1.0,
    pl_d0_db=55.4,
    path_loss_exponent=3.0,
    shadowing_sigma_db=4.0,
    fading_sigma_db=1.0,
    mtu=100,
    # 4 preamble + 1 SFD + 1 length + 9 MAC header (FCF, DSN, PAN, dst, src) + 2 FCS
    phy_overhead_bytes=17,
    ack_bytes=11,  # 6 PHY header + 5 MPDU (FCF, DSN, FCS)
    max_retries=3,  # macMaxFrameRetries of 802.15.4
    ack_timeout_s=0.008,  # TinyOS 2 CC2420_ACK_WAIT_DELAY: 256 / 32768 s
    ack_turnaround_s=0.000192,  # aTurnaroundTime: 12 symbols of 16 us
    mac_backoff_s=0.0098,  # TinyOS 2 CC2420 initial backoff up to ~10 ms
    voltage_v=3.0,
    tx_current_ma=17.4,
    rx_current_ma=18.8,
    tx_current_table=(
        (-25.0, 8.5),
        (-15.0, 9.9),
        (-10.0, 11.2),
        (-7.0, 12.5),
        (-5.0, 13.9),
        (-3.0, 15.2),
        (-1.0, 16.5),
        (0.0, 17.4),
    ),
)

# CC1000 (Mica2): 868 MHz, 38.4 kBaud Manchester-coded FSK = 19.2 kbps. The MTU of
# 64 bytes assumes TOSH_DATA_LENGTH raised from TinyOS's default of 29.
CC1000 = RadioPreset(
    name="cc1000",
    freq_mhz=868.0,
    bitrate_bps=19_200.0,
    modulation="ncfsk",
    noise_bandwidth_hz=30_000.0,  # Bn/R = 1/0.64 as in Zuniga & Krishnamachari
    tx_power_dbm=0.0,
    min_tx_power_dbm=-20.0,
    max_tx_power_dbm=5.0,
    sensitivity_dbm=-98.0,
    noise_floor_dbm=-105.0,
    d0_m=1.0,
    pl_d0_db=55.0,
    path_loss_exponent=3.0,
    shadowing_sigma_db=3.8,
    fading_sigma_db=1.0,
    mtu=64,
    # 8 preamble + 2 sync + 5 TOS_Msg header (addr, type, group, length) + 2 CRC
    phy_overhead_bytes=17,
    ack_bytes=12,  # 8 preamble + 2 sync + 2 ACK code (TinyOS 1 software ACK)
    max_retries=3,
    ack_timeout_s=0.02,
    ack_turnaround_s=0.0005,
    mac_backoff_s=0.0128,  # B-MAC initial backoff up to ~13 ms (assumption)
    voltage_v=3.0,
    tx_current_ma=16.5,
    rx_current_ma=9.6,
    tx_current_table=((-20.0, 8.6), (-5.0, 13.8), (0.0, 16.5), (5.0, 25.4)),
)

PRESETS: Final[dict[str, RadioPreset]] = {p.name: p for p in (CC2420, CC1000)}


def preset(name: str) -> RadioPreset:
    """The preset called ``name``; ValueError naming the known ones otherwise."""
    try:
        return PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown radio preset {name!r}; known: {', '.join(PRESETS)}") from None


# A links file (radio/links.py) fixes who hears whom: positions say nothing of it,
# so the range is this (every mote in one cell) and a pair without a link has
# this mean RSSI (no draw delivers it).
LINKS_RANGE_M: Final = 1e7
NO_LINK_DBM: Final = -1e9


class Realism(Protocol):
    """What a realistic radio adds to the model (``radio/environment.py``'s
    ``RadioEnvironment`` is the one kind): this module stays the bottom of the
    radio, importing nothing of the modules that build it."""

    @property
    def noise_at(self) -> Callable[[int, float], float] | None:
        """The noise (dBm) at a mote at an instant; None: the preset's floor."""
        ...

    @property
    def noise_over(self) -> Callable[[int, float, float], float] | None:
        """The noise a frame on the air from ``t0`` to ``t1`` is received against
        at a mote (``noise_over(node, t0, t1)``); None: the preset's floor."""
        ...

    @property
    def tx_offset(self) -> Callable[[int], float] | None:
        """A mote's output power offset (dB); None: none."""
        ...

    @property
    def tx_sigma_db(self) -> float:
        """The deviation of the output power offsets (0 without)."""
        ...

    @property
    def gains(self) -> dict[tuple[int, int], float] | None:
        """Every link's gain (dB at 0 dBm) from a links file; None: from positions."""
        ...


# --------------------------------------------------------------------------- cells


def cell_of(x: float, y: float, cell_size_m: float) -> tuple[int, int]:
    """Grid cell of a position; cells are squares of side ``cell_size_m`` from (0, 0)."""
    return math.floor(x / cell_size_m), math.floor(y / cell_size_m)


# --------------------------------------------------------------------------- BER / PRR

# Below this BER * bits, the PRR differs from 1 by less than 1e-12: we return 1.0
# exactly (part of the model's definition, so prr() and reception() agree).
_PRR_ONE_EPS: Final = 1e-12
_PRR_CACHE_MAX: Final = 1 << 17
_RANGE_CACHE_MAX: Final = 64  # distinct tx powers (a mote uses one; presets a handful)
_OQPSK_COEF: Final[tuple[tuple[float, float], ...]] = tuple(
    ((-1) ** k * math.comb(16, k), 20.0 * (1.0 / k - 1.0)) for k in range(2, 17)
)


def ber_oqpsk(snr: float) -> float:
    """IEEE 802.15.4-2006 (E.4.1.8) BER of 2.4 GHz O-QPSK DSSS; ``snr`` is linear."""
    s = 0.0
    for c, e in _OQPSK_COEF:
        s += c * math.exp(e * snr)
    return min(0.5, max(0.0, s * (8.0 / 15.0) / 16.0))


def ber_ncfsk(snr: float, bn_over_r: float) -> float:
    """Non-coherent FSK: BER = 0.5 exp(-SNR/2 * Bn/R); ``snr`` is linear."""
    return 0.5 * math.exp(-0.5 * snr * bn_over_r)


class RadioModel:
    """Log-distance path loss, log-normal shadowing, PRR from SNR, seeded decisions.

    ``symmetric`` makes the static shadowing of a link the same in both
    directions (per-packet fading never is). Airtime and energy depend on the
    preset alone: ``model.preset.airtime_s(n)``, ``.tx_energy_mj``, ``.rx_energy_mj``.

    ``env`` (:mod:`awaremw.radio.environment`) makes the radio realistic:
    noise that varies per mote and in time (``noise_at(node, t)``; None: the
    preset's constant floor), per-mote transmit power offsets (hardware
    variance), or a links file that gives every link's gain instead of
    positions. None is today's textbook radio, bit for bit.
    """

    __slots__ = (
        "_ber_memo",
        "_bn_over_r",
        "_d0",
        "_d_min",
        "_links",
        "_max_fade",
        "_pl_d0",
        "_range_cache",
        "_seed_mix",
        "_ten_n",
        "_tx_offset",
        "_tx_sigma",
        "env",
        "noise_at",
        "noise_over",
        "one_snr_db",
        "preset",
        "prr_memo",
        "seed",
        "symmetric",
    )

    def __init__(
        self,
        preset: RadioPreset,
        seed: int,
        symmetric: bool = True,
        env: Realism | None = None,
    ) -> None:
        self.preset = preset
        self.seed = seed
        self.symmetric = symmetric
        self.env = env
        # The noise at a receiver at an instant (dBm); None: preset.noise_floor_dbm.
        self.noise_at: Callable[[int, float], float] | None = None
        # The noise a frame is received against, from its start to its end.
        self.noise_over: Callable[[int, float, float], float] | None = None
        self._tx_offset = None if env is None else env.tx_offset
        self._tx_sigma = 0.0 if env is None else env.tx_sigma_db
        self._links = None if env is None else env.gains
        if env is not None:
            self.noise_at = env.noise_at
            self.noise_over = env.noise_over
        self._bn_over_r = preset.noise_bandwidth_hz / preset.bitrate_bps
        # Bounds (entries; each cache is cleared when full, its values are pure
        # functions, so clearing only costs recomputation):
        self._range_cache: dict[float, float] = {}  # per tx power heard: _RANGE_CACHE_MAX
        # prr_bits' cache, also read by a caller's inlined lookup (read only): the PRR
        # at snr_db = rssi - noise floor (below the PRR-one SNR) of `bits` bits is
        # prr_memo[(round(snr_db * 1000.0) << 16) | bits] when present, else call
        # prr_bits. The same dict for the model's life (cleared when full).
        self.prr_memo: dict[int, float] = {}
        self._ber_memo: dict[int, float] = {}  # round(snr_db * 1000) -> BER
        self._max_fade = preset.fading_sigma_db * Z_MAX
        self._seed_mix = splitmix64(seed & M64)  # link_hash's first round
        # path_loss_db's constants (mean_rssi inlines it).
        self._d0 = preset.d0_m
        self._d_min = preset.d0_m * 0.1
        self._pl_d0 = preset.pl_d0_db
        self._ten_n = 10.0 * preset.path_loss_exponent
        self.one_snr_db = self._snr_db_for_prr_one()

    # ---------------------------------------------------------------- geometry

    def path_loss_db(self, distance_m: float) -> float:
        """PL(d) = PL(d0) + 10 n log10(d / d0), with d clamped to >= d0 / 10."""
        p = self.preset
        d = max(distance_m, p.d0_m * 0.1)
        return p.pl_d0_db + 10.0 * p.path_loss_exponent * math.log10(d / p.d0_m)

    def static_shadow_db(self, src: int, dst: int) -> float:
        """The per-link, time-invariant shadowing loss (dB).

        Computed, not cached: its callers keep what they need (a sender's
        receiver cache, the Air's mean powers), and a table of every link heard
        grew with the network (6 KiB a mote) and missed the CPU's caches."""
        if src > dst and self.symmetric:
            a, b = dst, src
        else:
            a, b = src, dst
        # link_hash(self.seed, DOMAIN_SHADOW, a, b), the seed's round done once.
        h = splitmix64(
            self._seed_mix ^ ((DOMAIN_SHADOW << 40) | ((a & 0xFFFF) << 16) | (b & 0xFFFF))
        )
        return self.preset.shadowing_sigma_db * NORMAL[h >> SHIFT]

    def fading_link_hash(self, src: int, dst: int) -> int:
        """Hash of the directed link for per-packet draws (computed: callers keep it)."""
        # link_hash(self.seed, DOMAIN_FADING, src, dst), the seed's round done once.
        return splitmix64(
            self._seed_mix ^ ((DOMAIN_FADING << 40) | ((src & 0xFFFF) << 16) | (dst & 0xFFFF))
        )

    def mean_rssi(self, src: int, dst: int, distance: float, tx_power: float) -> float:
        """Noise-free ground truth: P_tx - PL(d) - static shadow (no per-packet part);
        with a links file, P_tx + the file's gain (:data:`NO_LINK_DBM` without one);
        with hardware variance, plus the sender's output power offset."""
        links = self._links
        if links is not None:
            g = links.get((src, dst))
            return NO_LINK_DBM if g is None else tx_power + g
        # path_loss_db inlined (the same operations in the same order: same bits).
        d = distance if distance > self._d_min else self._d_min
        pl = self._pl_d0 + self._ten_n * math.log10(d / self._d0)
        off = self._tx_offset
        if off is not None:
            return tx_power + off(src) - pl - self.static_shadow_db(src, dst)
        return tx_power - pl - self.static_shadow_db(src, dst)

    def rssi(self, src: int, dst: int, distance: float, tx_power: float, packet_key: int) -> float:
        """RSSI of one packet: mean RSSI minus the packet's fading draw."""
        h = packet_hash(self.fading_link_hash(src, dst), packet_key)
        return (
            self.mean_rssi(src, dst, distance, tx_power)
            - self.preset.fading_sigma_db * NORMAL[h >> SHIFT]
        )

    def max_range_m(self, tx_power: float | None = None) -> float:
        """Distance beyond which nothing is delivered (the mean RSSI + 3 sigma_total
        would still be below sensitivity). Receivers drop by distance beyond it."""
        p = self.preset
        tx = p.tx_power_dbm if tx_power is None else tx_power
        r = self._range_cache.get(tx)
        if r is None:
            p.check_tx_power(tx)  # remote powers are checked by the envelope decoder
            if self._links is not None:
                return LINKS_RANGE_M
            sigma = math.hypot(p.shadowing_sigma_db, p.fading_sigma_db)
            if self._tx_sigma:  # the output power offsets spread the links further
                sigma = math.hypot(sigma, self._tx_sigma)
            budget = tx - p.sensitivity_dbm + 3.0 * sigma - p.pl_d0_db
            r = p.d0_m * 10.0 ** (budget / (10.0 * p.path_loss_exponent))
            if len(self._range_cache) >= _RANGE_CACHE_MAX:
                self._range_cache.clear()  # cheap to recompute; senders use few powers
            self._range_cache[tx] = r
        return r

    @property
    def cell_size_m(self) -> float:
        """Side of the key-expression grid: the max range at the chip's max power."""
        return self.max_range_m(self.preset.max_tx_power_dbm)

    def never_delivers(self, mean_rssi_dbm: float) -> bool:
        """True if no fading draw can lift this link's mean RSSI to sensitivity."""
        return mean_rssi_dbm + self._max_fade < self.preset.sensitivity_dbm

    # ---------------------------------------------------------------- reception

    def _ber(self, snr_db: float) -> float:
        snr = 10.0 ** (snr_db / 10.0)
        if self.preset.modulation == "oqpsk":
            return ber_oqpsk(snr)
        return ber_ncfsk(snr, self._bn_over_r)

    def _snr_db_for_prr_one(self) -> float:
        # Smallest SNR (to 0.001 dB) where BER * max frame bits < eps: BER falls
        # monotonically with SNR, so bisect.
        bits = 8 * (self.preset.mtu + self.preset.phy_overhead_bytes + 64)
        lo, hi = -20.0, 60.0
        while hi - lo > 1e-3:
            mid = (lo + hi) / 2
            if self._ber(mid) * bits < _PRR_ONE_EPS:
                hi = mid
            else:
                lo = mid
        return hi

    def prr_bits(self, rssi_dbm: float, bits: int, noise_dbm: float | None = None) -> float:
        """PRR = (1 - BER(SNR))^bits; 0 below sensitivity.

        The SNR is rounded to 0.001 dB so that the values can be cached (the
        O-QPSK BER is a 15-term sum): a step far below any physical meaning.
        """
        p = self.preset
        if rssi_dbm < p.sensitivity_dbm:
            return 0.0
        noise = p.noise_floor_dbm if noise_dbm is None else noise_dbm
        return self._prr_snr(rssi_dbm - noise, bits)

    def _prr_snr(self, snr_db: float, bits: int) -> float:
        """PRR of ``bits`` bits at ``snr_db`` (the sensitivity is the caller's check)."""
        if snr_db >= self.one_snr_db:
            return 1.0
        milli = round(snr_db * 1000.0)
        k = (milli << 16) | bits
        v = self.prr_memo.get(k)
        if v is None:
            if len(self.prr_memo) >= _PRR_CACHE_MAX:
                self.prr_memo.clear()
            # The BER depends on the SNR alone: frames of other lengths share it.
            ber = self._ber_memo.get(milli)
            if ber is None:
                if len(self._ber_memo) >= _PRR_CACHE_MAX:
                    self._ber_memo.clear()
                ber = self._ber_memo[milli] = self._ber(milli / 1000.0)
            v = (1.0 - ber) ** bits
            self.prr_memo[k] = v
        return v

    def prr(self, rssi_dbm: float, frame_len: int) -> float:
        """PRR of a frame of ``frame_len`` bytes (ours; PHY overhead is added)."""
        return self.prr_bits(rssi_dbm, 8 * (frame_len + self.preset.phy_overhead_bytes))

    def decide(
        self,
        link_h: int,
        mean_rssi_dbm: float,
        bits: int,
        packet_key: int,
        noise_dbm: float | None = None,
    ) -> tuple[bool, float]:
        """The per-packet decision from cached link data (the hot path).

        ``link_h`` is :meth:`fading_link_hash`, ``mean_rssi_dbm`` :meth:`mean_rssi`;
        ``noise_dbm`` the receiver's noise then (None: the preset's floor).
        """
        h = packet_hash(link_h, packet_key)
        rssi = mean_rssi_dbm - self.preset.fading_sigma_db * NORMAL[h >> SHIFT]
        return (h & 0xFFFFFFFF) * U32 < self.prr_bits(rssi, bits, noise_dbm), rssi


    def reception(
        self,
        src: int,
        dst: int,
        distance: float,
        tx_power: float,
        frame_len: int,
        packet_key: int,
        t: float = 0.0,
    ) -> tuple[bool, float]:
        """(delivered?, rssi) of one frame from ``src`` heard at ``dst`` (ending at ``t``).

        Deterministic in (seed, src, dst, distance, tx_power, frame_len,
        packet_key) and the noise at ``dst`` at ``t``. Beyond
        :meth:`max_range_m` nothing is delivered.
        """
        bits = 8 * (frame_len + self.preset.phy_overhead_bytes)
        return self._reception_bits(src, dst, distance, tx_power, bits, packet_key, t)

    def ack_reception(
        self,
        src: int,
        dst: int,
        distance: float,
        tx_power: float,
        packet_key: int,
        t: float = 0.0,
    ) -> tuple[bool, float]:
        """(delivered?, rssi) of the link-layer ACK that ``src`` sends back to ``dst``.

        ``packet_key`` must be the data attempt's key with ``ack=True``.
        """
        return self._reception_bits(
            src, dst, distance, tx_power, 8 * self.preset.ack_bytes, packet_key, t
        )

    def _reception_bits(
        self,
        src: int,
        dst: int,
        distance: float,
        tx_power: float,
        bits: int,
        packet_key: int,
        t: float,
    ) -> tuple[bool, float]:
        mean = self.mean_rssi(src, dst, distance, tx_power)
        no = self.noise_over
        t0 = t - bits / self.preset.bitrate_bps
        ok, rssi = self.decide(
            self.fading_link_hash(src, dst), mean, bits, packet_key,
            None if no is None else no(dst, t0, t),
        )  # fmt: skip
        if distance > self.max_range_m(tx_power):
            return False, rssi
        return ok, rssi

    def backoff_link_hash(self, src: int) -> int:
        """Hash of ``src``'s backoff stream (cache it per mote)."""
        return link_hash(self.seed, DOMAIN_BACKOFF, src, 0)

    def backoff_s(self, src: int, seq: int, attempt: int) -> float:
        """Seeded random MAC backoff before an attempt, in [0, mac_backoff_s)."""
        h = packet_hash(self.backoff_link_hash(src), packet_key(seq, attempt))
        return uniform(h) * self.preset.mac_backoff_s
