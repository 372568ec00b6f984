"""The noise a mote's receiver hears: a constant floor, a Gaussian per mote, or a trace.

Three sources, one contract: :meth:`NoiseSource.at` gives the noise (dBm) at
mote ``node`` at emulated time ``t``; the receiver's SNR and SINR use it, and
so does its clear channel assessment (``docs/radio.md``, "Noise").

* :class:`WhiteNoise`: the preset's floor, plus the mote's hardware offset
  (:class:`HardwareVariance`). Today's radio when no offset is set.
* :class:`LineNoise`: per mote a mean and a range, one uniform draw per
  instant: the ``noise NODE MEAN RANGE`` lines of a TOSSIM topology file.
* :class:`TraceNoise`: closest-pattern matching (CPM; Lee, Cerpa and Levis,
  IPSN 2007) on a noise trace, as TOSSIM's ``sim_noise.c`` does it: one reading
  per millisecond; the last :data:`HISTORY` readings, binned by
  :data:`BIN_DB`, select the readings that followed the same binned history in
  the trace, and the next reading is one of them, drawn uniformly.

A CPM chain is a walk over trace positions: at position ``p`` the next
reading is ``trace[q]`` for ``q`` drawn among the positions whose binned
history equals ``p``'s, and the walk goes on at ``q + 1`` (the history of
``q + 1`` is ``p``'s shifted by ``trace[q]``'s bin, which is TOSSIM's update).
Where every such ``q`` is followed by a reading of the same bin the draw can
not change the history, so the walk follows the trace reading for reading;
:class:`Cpm` precomputes where the next real choice is and jumps there.

Cost and determinism. Every draw is a seeded hash of ``(seed, mote, ms)``,
nothing else: a process that asks for the same instants gets the same noise.
A mote's chain is only run when its noise is asked for (a mote that receives
nothing costs nothing), and it is not run across a silence longer than
:data:`HORIZON_MS`: the next question restarts the chain at a position drawn
uniformly from the trace, a draw from the chain's stationary distribution
(uniform over positions), as the chain itself would be after a long silence
up to the correlation the trace keeps at that lag (measured in
``docs/radio.md``). A question up to ``HORIZON_MS`` after the last one costs
the choices on the way (about one every 8 ms on ``meyer-heavy``).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from functools import lru_cache
from importlib import resources
from pathlib import Path
from typing import Final, Protocol

from awaremw.radio.model import GOLDEN, M64, MUL, NORMAL, SHIFT, link_hash, packet_hash
from awaremw.radio.textfile import read_bounded

HISTORY: Final = 20  # readings of history (TOSSIM's NOISE_HISTORY)
BIN_DB: Final = 5.0  # bin width (TOSSIM's NOISE_QUANTIZE_INTERVAL)
BIN_MIN_DBM: Final = -120.0  # readings below fall in the lowest bin (TOSSIM's NOISE_MIN)
HORIZON_MS: Final = 32  # a silence longer than this restarts a mote's chain (ms)
MIN_READINGS: Final = 10 * HISTORY
MAX_READINGS: Final = 4_000_000  # about 16 hours at one reading a millisecond
MAX_TRACE_BYTES: Final = 64 << 20
READING_RANGE: Final = (-200.0, 50.0)  # dBm a trace reading may hold

DOMAIN_NOISE: Final = 4  # the hash domains of radio/model.py, continued
DOMAIN_HARDWARE: Final = 5
_RESTART: Final = 0x5BD1E9955BD1E995  # salt of the restart draws (another stream)

# The shipped traces, by name: noise = "meyer-heavy" in a deployment.
SHIPPED: Final[dict[str, str]] = {"meyer-heavy": "meyer-heavy.txt"}


class NoiseTraceError(ValueError):
    """A noise trace that cannot be used; the message names the file and the line."""


class NoiseSource(Protocol):
    def at(self, node: int, t: float) -> float:
        """The noise (dBm) at mote ``node``'s receiver at emulated time ``t`` (s)."""
        ...

    def over(self, node: int, t0: float, t1: float) -> float:
        """The noise a frame on the air from ``t0`` to ``t1`` is received against."""
        ...

    def level(self, node: int) -> float:
        """The noise ``node`` hears most of the time (dBm): its floor, for the
        benchmarks and for turning a delivery probability into a gain."""
        ...


# --------------------------------------------------------------------------- traces


class NoiseTrace:
    """Noise readings in dBm, one a millisecond, as TOSSIM reads them."""

    __slots__ = ("mode", "name", "readings")

    def __init__(self, readings: Iterable[float], name: str = "trace") -> None:
        r = [float(x) for x in readings]
        if len(r) < MIN_READINGS:
            raise NoiseTraceError(f"{name}: {len(r)} readings; a trace needs {MIN_READINGS}")
        if len(r) > MAX_READINGS:
            raise NoiseTraceError(f"{name}: more than {MAX_READINGS} readings")
        lo, hi = READING_RANGE
        for i, x in enumerate(r):
            if not lo <= x <= hi:  # NaN fails too
                raise NoiseTraceError(
                    f"{name}: reading {i + 1} is {x!r}, outside {lo:g}..{hi:g} dBm"
                )
        self.readings = r
        self.name = name
        counts: dict[float, int] = {}
        for x in r:
            counts[x] = counts.get(x, 0) + 1
        # The reading heard most often: the trace's quiet floor (ties: the lowest).
        self.mode = min(counts, key=lambda k: (-counts[k], k))

    @classmethod
    def load(cls, path: str | Path) -> NoiseTrace:
        """Read a trace file: one reading (dBm) a line; blank lines are skipped."""
        p = Path(path)
        text = read_bounded(p, MAX_TRACE_BYTES, NoiseTraceError, "a trace")
        out: list[float] = []
        for n, line in enumerate(text.splitlines(), 1):
            s = line.strip()
            if not s:
                continue
            try:
                v = float(s)
            except ValueError:
                raise NoiseTraceError(
                    f"{p}: line {n}: {s[:40]!r} is not a reading in dBm"
                ) from None
            if not math.isfinite(v):
                raise NoiseTraceError(f"{p}: line {n}: {s[:40]!r} is not a finite reading")
            out.append(v)
        return cls(out, str(p))


def shipped_trace_path(name: str) -> Path:
    """The file of a shipped trace (``"meyer-heavy"``)."""
    return Path(str(resources.files("awaremw.radio") / "data" / SHIPPED[name]))


@lru_cache(maxsize=4)
def _load_cached(path: str, mtime_ns: int) -> NoiseTrace:
    return NoiseTrace.load(path)


def load_trace(name_or_path: str | Path) -> NoiseTrace:
    """A shipped trace by name, or a trace file (read once per process)."""
    key = str(name_or_path)
    p = shipped_trace_path(key) if key in SHIPPED else Path(key)
    try:
        mtime = p.stat().st_mtime_ns
    except OSError as e:
        known = ", ".join(SHIPPED)
        raise NoiseTraceError(
            f"{p}: cannot read: {e.strerror or e} (shipped traces: {known})"
        ) from None
    return _load_cached(str(p), mtime)


def bin_of(reading: float) -> int:
    """TOSSIM's bin of a reading (``search_bin_num``: below the range, the lowest)."""
    if reading < BIN_MIN_DBM:
        return 0
    return int((reading - BIN_MIN_DBM) // BIN_DB)


class Cpm:
    """The CPM tables of one trace (built once, shared by every mote).

    Positions ``p`` run from :data:`HISTORY` to ``n - 1``: the history of ``p``
    is ``trace[p - HISTORY:p]``, binned. ``nxt[p]`` is the first position
    ``>= p`` where the draw matters (the positions with the same binned history
    are followed by readings of two bins or more), ``n`` if none; at such a
    position ``pool[p]`` are those positions, to draw from (elsewhere empty).
    """

    __slots__ = ("n", "nxt", "pool", "values")

    def __init__(self, trace: NoiseTrace) -> None:
        v = trace.readings
        n = self.n = len(v)
        self.values = v
        bins = [bin_of(x) for x in v]
        ids: dict[tuple[int, ...], int] = {}
        cls = [0] * n
        members: list[list[int]] = []
        key = tuple(bins[:HISTORY])
        for p in range(HISTORY, n):
            if p > HISTORY:
                key = (*key[1:], bins[p - 1])
            c = ids.get(key)
            if c is None:
                c = ids[key] = len(members)
                members.append([])
            members[c].append(p)
            cls[p] = c
        choice = [len({bins[q] for q in m}) > 1 for m in members]
        nxt = [n] * (n + 1)
        for p in range(n - 1, HISTORY - 1, -1):
            nxt[p] = p if choice[cls[p]] else nxt[p + 1]
        self.nxt = nxt
        # The positions to draw from at each position where a draw matters.
        empty: list[int] = []
        self.pool = [members[cls[p]] if nxt[p] == p else empty for p in range(n)]

    def start(self, h: int, t: int) -> int:
        """A position drawn uniformly (the chain's stationary distribution)."""
        span = self.n - HISTORY
        return HISTORY + (packet_hash(h ^ _RESTART, t) & 0xFFFFFFFF) * span // (1 << 32)

    def pick(self, p: int, h: int, t: int) -> int:
        """The reading's position at ``p`` and ms ``t``: a draw among ``p``'s class."""
        m = self.pool[p]
        if not m:
            return p
        return m[(packet_hash(h, t) & 0xFFFFFFFF) * len(m) >> 32]

    def advance(self, p: int, t: int, t1: int, h: int) -> int:
        """The position at ms ``t1`` of the chain that is at ``p`` at ms ``t`` (``t1 >= t``)."""
        n = self.n
        nxt = self.nxt
        pool = self.pool
        while t < t1:
            b = nxt[p]
            if b - p >= t1 - t:  # no choice before t1: follow the trace
                p += t1 - t
                t = t1
            elif b == n:  # the trace ends first: a fresh start where the walk falls off
                t += n - p
                p = self.start(h, t)
                continue
            else:
                t += b - p
                # pick(b, h, t) inlined (packet_hash too): one draw per choice.
                m = pool[b]
                z = ((h ^ ((t * GOLDEN) & M64)) * MUL) & M64
                p = m[((z ^ (z >> 31)) & 0xFFFFFFFF) * len(m) >> 32] + 1
                t += 1
            if p >= n:  # off the trace's end: a fresh start where the walk fell off
                t -= p - n
                p = self.start(h, t)
        return p


@lru_cache(maxsize=4)
def cpm_of(trace: NoiseTrace) -> Cpm:
    return Cpm(trace)


# --------------------------------------------------------------------------- hardware


class HardwareVariance:
    """Per-mote offsets of the noise floor and of the transmit power (dB), as
    TOSSIM's ``LinkLayerModel`` draws them (Zuniga and Krishnamachari, SECON
    2004): a bivariate normal with covariance ``[[s11, s12], [s12, s22]]``
    (noise floor, output power), through its Cholesky factor. The defaults
    are LinkLayerModel's (``mica2grid.txt``): a mote with a high floor tends to
    have a low output power. Seeded per mote: a pure function of
    ``(seed, node)``."""

    __slots__ = ("_cache", "_seed", "s11", "s12", "s22", "t11", "t12", "t22")

    def __init__(self, seed: int, s11: float = 3.7, s12: float = -3.3, s22: float = 6.0) -> None:
        if s11 < 0 or s22 < 0 or abs(s12) > math.sqrt(s11 * s22):
            raise ValueError("hardware variance: need s11, s22 >= 0 and |s12| <= sqrt(s11 s22)")
        self._seed = seed
        self.s11, self.s12, self.s22 = s11, s12, s22
        self.t11 = math.sqrt(s11)
        self.t12 = s12 / self.t11 if s11 else 0.0
        self.t22 = math.sqrt((s11 * s22 - s12 * s12) / s11) if s11 else math.sqrt(s22)
        self._cache: dict[int, tuple[float, float]] = {}

    def offsets(self, node: int) -> tuple[float, float]:
        """(noise floor offset, output power offset) of ``node``, in dB."""
        o = self._cache.get(node)
        if o is None:
            z1 = NORMAL[link_hash(self._seed, DOMAIN_HARDWARE, node, 1) >> SHIFT]
            z2 = NORMAL[link_hash(self._seed, DOMAIN_HARDWARE, node, 2) >> SHIFT]
            o = (self.t11 * z1, self.t12 * z1 + self.t22 * z2)
            if len(self._cache) < 1 << 17:
                self._cache[node] = o
        return o

    def noise_offset(self, node: int) -> float:
        return self.offsets(node)[0]

    def tx_offset(self, node: int) -> float:
        return self.offsets(node)[1]

    @property
    def tx_sigma_db(self) -> float:
        return math.sqrt(self.s22)


# --------------------------------------------------------------------------- sources


class WhiteNoise:
    """A constant floor (the preset's), plus each mote's hardware offset."""

    __slots__ = ("floor_dbm", "hw")

    def __init__(self, floor_dbm: float, hw: HardwareVariance | None = None) -> None:
        self.floor_dbm = floor_dbm
        self.hw = hw

    def at(self, node: int, t: float) -> float:
        hw = self.hw
        return self.floor_dbm if hw is None else self.floor_dbm + hw.noise_offset(node)

    def over(self, node: int, t0: float, t1: float) -> float:
        return self.at(node, t1)

    def level(self, node: int) -> float:
        return self.at(node, 0.0)


class LineNoise:
    """Per mote a mean and a range (TOSSIM's ``noise NODE MEAN RANGE`` lines):
    a draw uniform in ``[mean - range, mean + range]``, as TOSSIM's
    ``sim_gain_sample_noise`` takes it, one per instant (microsecond) from
    ``(seed, node, t)``; motes without a line hear ``default``."""

    __slots__ = ("_seed", "default", "per_node")

    def __init__(
        self, seed: int, per_node: dict[int, tuple[float, float]], default: tuple[float, float]
    ) -> None:
        self._seed = seed
        self.per_node = per_node
        self.default = default

    def at(self, node: int, t: float) -> float:
        mean, rng = self.per_node.get(node, self.default)
        if rng == 0.0:
            return mean
        h = packet_hash(link_hash(self._seed, DOMAIN_NOISE, node, 0), int(t * 1e6) & M64)
        return mean + rng * (2.0 * (h & 0xFFFFFFFF) / 4294967296.0 - 1.0)

    def over(self, node: int, t0: float, t1: float) -> float:
        """The louder of the draws at the frame's start and at its end: TOSSIM
        checks a reception when the frame begins and again when it ends."""
        return max(self.at(node, t0), self.at(node, t1))

    def level(self, node: int) -> float:
        return self.per_node.get(node, self.default)[0]


class _Chain:
    """One mote's CPM chain: where it was at the last two instants asked, the
    reading at the last one, and the mote's offset (dB added to readings)."""

    __slots__ = ("h", "off", "p", "p0", "t", "t0", "v")

    def __init__(self, h: int, p: int, t: int, off: float) -> None:
        self.h = h
        self.p = p
        self.t = t
        self.p0 = p  # the instant before the last (a question slightly in the past)
        self.t0 = t
        self.v = float("nan")  # the reading at t (nan: not drawn yet)
        self.off = off


class TraceNoise:
    """CPM noise from a trace, per mote, placed at the preset's floor.

    The trace's most common reading (its quiet floor) is placed at
    ``floor_dbm``, the rest follows it (``shift = floor_dbm - trace.mode``):
    a trace recorded on another chip keeps its shape. ``levels`` places it at
    another floor for some motes (a TOSSIM file's noise means). Hardware
    offsets add on. Each mote runs its own chain.
    """

    __slots__ = ("_chains", "_seed", "cpm", "hw", "levels", "shift", "trace")

    MAX_CHAINS: Final = 1 << 20

    def __init__(
        self,
        trace: NoiseTrace,
        seed: int,
        floor_dbm: float,
        hw: HardwareVariance | None = None,
        levels: dict[int, float] | None = None,
    ) -> None:
        self.trace = trace
        self.cpm = cpm_of(trace)
        self._seed = seed
        self.shift = floor_dbm - trace.mode
        self.hw = hw
        self.levels = {n: v - trace.mode for n, v in (levels or {}).items()}
        self._chains: dict[int, _Chain] = {}

    def _offset(self, node: int) -> float:
        """dB added to ``node``'s trace readings: its level, and its hardware offset."""
        off = self.levels.get(node, self.shift)
        return off if self.hw is None else off + self.hw.noise_offset(node)

    def _chain(self, node: int, ms: int) -> _Chain:
        c = self._chains.get(node)
        if c is None:
            if len(self._chains) >= self.MAX_CHAINS:
                self._chains.clear()
            h = link_hash(self._seed, DOMAIN_NOISE, node, 0)
            c = self._chains[node] = _Chain(h, self.cpm.start(h, ms), ms, self._offset(node))
        return c

    def reading(self, node: int, ms: int) -> float:
        """The chain's reading (trace dBm, unshifted) at millisecond ``ms``."""
        return self._read(self._chain(node, ms), ms)

    def _read(self, c: _Chain, ms: int) -> float:
        cpm = self.cpm
        if ms >= c.t:
            if ms == c.t and c.v == c.v:  # asked again at the same instant (not nan)
                return c.v
            if ms > c.t:
                c.p0, c.t0 = c.p, c.t
                if ms - c.t > HORIZON_MS:
                    c.p = cpm.start(c.h, ms)
                else:
                    c.p = cpm.advance(c.p, c.t, ms, c.h)
                c.t = ms
        elif ms >= c.t0:  # slightly in the past: from the instant before, state kept
            return cpm.values[cpm.pick(cpm.advance(c.p0, c.t0, ms, c.h), c.h, ms)]
        else:  # further back than anything kept: a stationary draw
            return cpm.values[cpm.pick(cpm.start(c.h, ms), c.h, ms)]
        v = c.v = cpm.values[cpm.pick(c.p, c.h, ms)]
        return v

    def at(self, node: int, t: float) -> float:
        ms = int(t * 1000.0)
        c = self._chain(node, ms)
        return self._read(c, ms) + c.off

    def over(self, node: int, t0: float, t1: float) -> float:
        """The reading at the frame's end: the chain is one reading per ms with
        the readings before it as its state, asked in time order.

        The reception hot path (every receiver a frame reaches above the
        sensitivity): a question later than the chain's last is
        :meth:`_read`'s forward branch with :meth:`Cpm.start` and
        :meth:`Cpm.pick` inlined, the same draws (a test holds it equal to
        :meth:`at`); any other question takes :meth:`at`'s path. It was a
        sixth of a noisy ``bench virtual --workload aware`` run's CPU.
        """
        ms = int(t1 * 1000.0)
        c = self._chains.get(node)
        if c is None or ms <= c.t:
            return self.at(node, t1)
        cpm = self.cpm
        h = c.h
        c.p0 = p = c.p
        c.t0 = t = c.t
        if ms - t > HORIZON_MS:  # cpm.start(h, ms)
            z = (((h ^ _RESTART) ^ ((ms * GOLDEN) & M64)) * MUL) & M64
            p = HISTORY + (((z ^ (z >> 31)) & 0xFFFFFFFF) * (cpm.n - HISTORY) >> 32)
        else:
            p = cpm.advance(p, t, ms, h)
        c.p = p
        c.t = ms
        m = cpm.pool[p]
        if m:  # cpm.pick(p, h, ms)
            z = ((h ^ ((ms * GOLDEN) & M64)) * MUL) & M64
            p = m[((z ^ (z >> 31)) & 0xFFFFFFFF) * len(m) >> 32]
        v = c.v = cpm.values[p]
        return v + c.off

    def level(self, node: int) -> float:
        return self.trace.mode + self._offset(node)
