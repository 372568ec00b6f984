"""The shared MAC and channel core: CSMA/CA or ALOHA, airtime, SINR collisions.

Sans-IO, like the protocol core: time goes in, decisions and deadlines come
out, nothing here reads a clock, sleeps or draws from a global random. Both
radio media (the virtual-clock driver, :mod:`awaremw.radio.virtual_medium`, and
the Zenoh medium) drive the same two objects, so that from the same seed they
decide the same things (``docs/radio.md``, "Medium access and collisions"):

* :class:`MacSender`, one per mote: the channel-access state machine of one
  frame attempt. :meth:`MacSender.begin` says when to do the first clear
  channel assessment (CSMA) or when the frame goes on the air (ALOHA);
  :meth:`MacSender.cca` takes the assessment's outcome and says: transmit at
  ``t``, sense again at ``t``, or give up (channel access failure). Random
  backoffs come from the model's seeded hashes (the ``BACKOFF`` stream of the
  sender, keyed by its link sequence number, attempt and backoff round), never
  from a shared generator.
* :class:`Air`, one per medium: the frames on the air (sender, position,
  power, start, end). It answers the carrier sense (:meth:`Air.busy`) and,
  once a frame has ended, whether it survived at a receiver
  (:meth:`Air.survives`): a transmitting radio is deaf, and a frame survives
  iff its SINR -- signal over the noise floor plus the linear (mW) sum of the
  frames overlapping it, at its worst instant -- stays at or above the
  preset's capture threshold for its whole reception. Frames may be added in
  any order (the Zenoh medium learns of them late, from envelopes); a
  decision only needs every frame that started before the decided frame
  ended, so the Zenoh medium decides after ``end + guard``.

Interferers are taken at their mean received power (path loss and static
shadowing, no per-packet fading); the decided frame at its packet's RSSI.
Only senders within one cell of the receiver interfere (what a receiver of
the Zenoh medium hears); beyond the max range an interferer is at least
3 sigma below sensitivity, under the noise floor. Link-layer ACKs are not put
on the air here (short, sent a turnaround after a frame the sender's
neighbours just heard end): they neither collide nor make the channel busy.
"""

from __future__ import annotations

import heapq
import math
import operator
from dataclasses import dataclass
from typing import Final

from awaremw.radio.model import (
    RadioModel,
    RadioPreset,
    cell_of,
    packet_hash,
    packet_key,
    uniform,
)

MAC_KINDS: Final = ("csma", "aloha")
COLLISION_MODES: Final = ("sinr", "none")

# What MacSender.cca asks the medium to do next.
TRANSMIT: Final = 0  # put the frame on the air at the returned time
SENSE: Final = 1  # do another clear channel assessment, ending at the returned time
GIVE_UP: Final = 2  # channel access failure: drop the frame (mac_drops += 1)


@dataclass(frozen=True, slots=True)
class MacParams:
    """Channel access of one radio. Times in seconds, powers in dBm.

    CSMA/CA (IEEE 802.15.4-2006 7.5.1.4, unslotted): before each attempt,
    ``NB = 0, BE = min_be``; wait ``randint(0, 2^BE - 1)`` unit backoff
    periods, assess the channel for ``cca_s``; clear: turn the radio around
    (``turnaround_s``) and transmit; busy: ``NB += 1``, ``BE = min(BE + 1,
    max_be)``, and if ``NB > max_backoffs`` give up, else back off again.
    A retransmission (``attempt >= 1``) starts with ``BE = retry_be`` instead
    (``None``: ``min_be``), so that two hidden senders that collided, and
    retry after the same ACK timeout, draw from a wider window.
    The channel is busy when the energy on it reaches ``cca_threshold_dbm``
    or, with ``carrier_sense``, when a frame at or above the sensitivity is
    being received. ALOHA (``kind = "aloha"``): no assessment; the attempt
    goes on the air after a uniform ``[0, aloha_backoff_s)`` delay.
    """

    kind: str
    unit_backoff_s: float
    min_be: int
    max_be: int
    max_backoffs: int
    cca_s: float
    turnaround_s: float
    cca_threshold_dbm: float
    carrier_sense: bool
    aloha_backoff_s: float
    # BE of a retransmission's first backoff (attempt >= 1); None: min_be, as
    # 802.15.4-2006 has it for every attempt.
    retry_be: int | None = None
    # When the noise varies (radio/noise.py): None, the threshold is fixed and the
    # noise's energy counts with the frames' (a CC2420's CCA_THR); a margin, the
    # threshold is that many dB above the noise heard then (B-MAC's outlier test
    # against a noise floor estimate that follows the noise).
    cca_margin_db: float | None = None

    def __post_init__(self) -> None:
        if self.kind not in MAC_KINDS:
            raise ValueError(f"unknown mac {self.kind!r}; known: {', '.join(MAC_KINDS)}")
        if not 0 <= self.min_be <= self.max_be <= 16 or self.max_backoffs < 0:
            raise ValueError("need 0 <= min_be <= max_be <= 16 and max_backoffs >= 0")
        if self.retry_be is not None and not self.min_be <= self.retry_be <= self.max_be:
            raise ValueError("need min_be <= retry_be <= max_be")
        for name in ("unit_backoff_s", "cca_s", "turnaround_s", "aloha_backoff_s"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0")


def mac_params(preset: RadioPreset, kind: str = "csma") -> MacParams:
    """The MAC of ``preset`` (``docs/radio.md`` gives the numbers' sources).

    ``cc2420``: 802.15.4 unslotted CSMA/CA defaults (macMinBE 3, macMaxBE 5,
    macMaxCSMABackoffs 4, aUnitBackoffPeriod 20 symbols = 320 us, CCA over
    8 symbols = 128 us, aTurnaroundTime 12 symbols = 192 us), except that a
    retransmission's first backoff uses macMaxBE (0..31 unit backoffs, 0..9.9
    ms, the range of TinyOS 2's CC2420 initial backoff): with macMinBE, hidden
    senders that collided re-collide on most retries (docs/radio.md), CCA threshold
    -77 dBm (the chip's reset CCA_THR) in CCA mode 3 (energy or a frame being
    received). Any other preset (``cc1000``): a B-MAC-like CSMA, a fixed
    window of 32 slots of one byte time (about the preset's 12.8 ms initial
    backoff) for the initial and the congestion backoffs, 7 rounds, energy
    threshold 10 dB above the noise floor (B-MAC's outlier detection, an
    assumption), no carrier detection.
    """
    if kind not in MAC_KINDS:
        raise ValueError(f"unknown mac {kind!r}; known: {', '.join(MAC_KINDS)}")
    if preset.modulation == "oqpsk":
        return MacParams(
            kind=kind,
            unit_backoff_s=320e-6,
            min_be=3,
            max_be=5,
            max_backoffs=4,
            cca_s=128e-6,
            turnaround_s=preset.ack_turnaround_s,
            cca_threshold_dbm=-77.0,
            carrier_sense=True,
            aloha_backoff_s=preset.mac_backoff_s,
            retry_be=5,
        )
    byte_s = 8.0 / preset.bitrate_bps
    return MacParams(
        kind=kind,
        unit_backoff_s=byte_s,
        min_be=5,
        max_be=5,
        max_backoffs=7,
        cca_s=byte_s,
        turnaround_s=preset.ack_turnaround_s,
        cca_threshold_dbm=preset.noise_floor_dbm + 10.0,
        carrier_sense=False,
        aloha_backoff_s=preset.mac_backoff_s,
        cca_margin_db=10.0,
    )


class MacSender:
    """One mote's channel access for its current attempt (sans-IO)."""

    __slots__ = ("be", "h", "nb", "params", "stream")

    def __init__(self, params: MacParams, stream: int) -> None:
        self.params = params
        self.stream = stream  # model.backoff_link_hash(src)
        self.h = 0  # hash of the current attempt
        self.nb = 0  # backoff rounds so far (NB)
        self.be = params.min_be  # backoff exponent (BE)

    @property
    def senses(self) -> bool:
        """True for CSMA (the medium must call :meth:`cca` at each returned time)."""
        return self.params.kind == "csma"

    def begin(self, seq: int, attempt: int, now: float) -> float:
        """A frame attempt ``(seq, attempt)`` is ready at ``now``. Returns when
        its first assessment ends (CSMA) or when it goes on the air (ALOHA):
        ``model.backoff_s(src, seq, attempt)`` later, as before collisions."""
        p = self.params
        h = packet_hash(self.stream, packet_key(seq, attempt))
        if p.kind == "aloha":
            return now + uniform(h) * p.aloha_backoff_s
        self.h = h
        self.nb = 0
        self.be = p.min_be if attempt == 0 or p.retry_be is None else p.retry_be
        return self._backoff(now)

    def _backoff(self, now: float) -> float:
        p = self.params
        slots = int(uniform(packet_hash(self.h, self.nb + 1)) * (1 << self.be))
        return now + slots * p.unit_backoff_s + p.cca_s

    def cca(self, busy: bool, now: float) -> tuple[int, float]:
        """The assessment ending at ``now`` found the channel ``busy`` or clear:
        ``(TRANSMIT, start)``, ``(SENSE, next assessment end)`` or ``(GIVE_UP, now)``."""
        p = self.params
        if not busy:
            return TRANSMIT, now + p.turnaround_s
        self.nb += 1
        if self.nb > p.max_backoffs:
            return GIVE_UP, now
        self.be = min(self.be + 1, p.max_be)
        return SENSE, self._backoff(now)


class OnAir:
    """A frame on the air: who sent it, from where, at what power, when.

    ``mw_cache`` maps a receiver id to the frame's mean power there (mW). A
    static sender's frames share one (``shared``, its receiver cache's: the
    value is a pure function of two fixed positions and the power), so each
    link is computed once, not once per frame; a moving receiver's values then
    go to the frame's own ``mw_moving``.
    """

    __slots__ = (
        "cell", "end", "key", "mw_cache", "mw_moving", "n", "shared", "src", "start", "tx_power",
        "x", "y",
    )  # fmt: skip

    def __init__(
        self,
        src: int,
        x: float,
        y: float,
        tx_power: float,
        start: float,
        end: float,
        key: int = 0,
        mw: dict[int, float] | None = None,
    ) -> None:
        self.src = src
        self.x = x
        self.y = y
        self.cell: tuple[int, int] = (0, 0)  # the Air's cell for it (Air.add sets it)
        self.tx_power = tx_power
        self.start = start
        self.end = end
        self.key = key  # the sender's link sequence number << 8 | attempt << 1 (packet_key)
        # receiver id -> mean received power (mW): the sender's (shared) or this frame's
        self.mw_cache: dict[int, float] = {} if mw is None else mw
        self.shared = mw is not None
        self.mw_moving: dict[int, float] | None = None  # moving receivers' (shared only)
        self.n = 0  # the Air's insertion number (its frames' order, whatever their cells)


_ORDER = operator.attrgetter("n")  # a frame's insertion number: the Air's order


def _mw(dbm: float) -> float:
    return float(10.0 ** (dbm / 10.0))


# Bound of Air's list: one frame per sender on the air plus those kept for late
# decisions; a medium with more concurrent frames than this has a bug.
MAX_ON_AIR: Final = 1 << 16


class Air:
    """The frames on (or lately off) the air of one medium, and the SINR rule.

    ``capture_db``: the SINR threshold (dB) a frame needs; None means no
    capture at all (any overlap destroys both frames; the ``bench mac``
    collision domain). ``horizon_s``: how long after its end a frame is kept
    (at least the longest airtime plus, for the Zenoh medium, the guard).

    Frames are kept by their sender's cell, so that every question (who
    overlaps a frame, is the channel busy here) looks at the cells around one
    place only: the work per frame does not grow with the network.
    """

    __slots__ = (
        "_by_cell", "_count", "_ends", "_n", "_noise_mw", "_sens", "_sens_mw", "capture_mw",
        "cell_size", "horizon_s", "model",
    )  # fmt: skip

    def __init__(self, model: RadioModel, capture_db: float | None, horizon_s: float) -> None:
        self.model = model
        self.cell_size = model.cell_size_m
        self.capture_mw = None if capture_db is None else _mw(capture_db)  # linear ratio
        self.horizon_s = horizon_s
        self._noise_mw = _mw(model.preset.noise_floor_dbm)
        self._sens = model.preset.sensitivity_dbm
        self._sens_mw = _mw(self._sens)  # for carrier sense (once, not per assessment)
        self._by_cell: dict[tuple[int, int], list[OnAir]] = {}  # sender cell -> frames, in order
        self._ends: list[tuple[float, int, OnAir]] = []  # heap of (end, n, frame): pruning
        self._count = 0
        self._n = 0

    def __len__(self) -> int:
        return self._count

    @property
    def frames(self) -> list[OnAir]:
        """Every frame kept, in the order they were added (tests, inspection)."""
        return sorted((f for fs in self._by_cell.values() for f in fs), key=_ORDER)

    def add(
        self,
        src: int,
        x: float,
        y: float,
        tx_power: float,
        start: float,
        end: float,
        key: int = 0,
        mw: dict[int, float] | None = None,
    ) -> OnAir:
        """Put a frame on the air (in any order of start times). ``mw``: the mean
        powers of a static sender's frames at static receivers, shared by its
        frames while it stands still (:attr:`OnAir.mw_cache`; None: the frame's own)."""
        if end < start:
            raise ValueError(f"frame of {src} ends ({end}) before it starts ({start})")
        if self._count >= MAX_ON_AIR:
            raise RuntimeError(f"more than {MAX_ON_AIR} frames on the air: frames never pruned")
        f = OnAir(src, x, y, tx_power, start, end, key, mw)
        f.cell = cell_of(x, y, self.cell_size)
        self._n += 1
        f.n = self._n
        lst = self._by_cell.get(f.cell)
        if lst is None:
            self._by_cell[f.cell] = [f]
        else:
            lst.append(f)
        self._count += 1
        heapq.heappush(self._ends, (end, f.n, f))
        return f

    def prune(self, now: float) -> None:
        """Forget the frames that ended more than ``horizon_s`` before ``now``."""
        cut = now - self.horizon_s
        ends = self._ends
        while ends and ends[0][0] < cut:
            f = heapq.heappop(ends)[2]
            self._forget(f)

    def _forget(self, f: OnAir) -> None:
        lst = self._by_cell.get(f.cell)
        if lst is None:
            return
        for i, o in enumerate(lst):
            if o is f:
                del lst[i]
                self._count -= 1
                if not lst:
                    del self._by_cell[f.cell]
                return

    def cut(self, src: int, now: float) -> None:
        """``src`` was switched off at ``now``: its frame stops there (or never starts)."""
        gone = []
        for lst in self._by_cell.values():
            for f in lst:
                if f.src == src and f.end > now:
                    if f.start >= now:
                        gone.append(f)
                    else:
                        f.end = now  # its heap entry keeps the later end: pruned later, harmless
        for f in gone:
            self._forget(f)

    def near(self, cell: tuple[int, int], reach: int) -> list[OnAir]:
        """The frames sent from the cells within ``reach`` cells of ``cell``, in order."""
        cx, cy = cell
        by_cell = self._by_cell
        if len(by_cell) <= 64:  # few cells on the air: scanning them beats 9 or 25 lookups
            out = [
                f
                for (x, y), fs in by_cell.items()
                if -reach <= x - cx <= reach and -reach <= y - cy <= reach
                for f in fs
            ]
        else:
            out = []
            for dx in range(-reach, reach + 1):
                for dy in range(-reach, reach + 1):
                    fs = by_cell.get((cx + dx, cy + dy))
                    if fs:
                        out.extend(fs)
        if len(out) > 1:
            out.sort(key=_ORDER)
        return out

    def overlapping(self, f: OnAir) -> list[OnAir]:
        """The other frames on the air during ``f`` whose sender is near enough
        (within two cells) to reach a receiver of ``f``."""
        s, e = f.start, f.end
        return [
            o
            for o in self.near(f.cell, 2)
            if o.end > s  # the test most frames fail first (they ended before f began)
            and o.start < e
            and o is not f
        ]

    def any_near(self, rid: int, cell: tuple[int, int], t0: float, t1: float) -> bool:
        """True if a frame of another mote than ``rid`` is on the air during
        ``(t0, t1)`` from ``cell`` or the 8 around it (the only frames
        :meth:`busy` gives power to at a receiver in ``cell``)."""
        cx, cy = cell
        by_cell = self._by_cell
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                fs = by_cell.get((cx + dx, cy + dy))
                if fs:
                    for o in fs:
                        if o.end > t0 and o.start < t1 and o.src != rid:
                            return True
        return False

    def power_mw(self, o: OnAir, rid: int, rx: float, ry: float, moving: bool = False) -> float:
        """Mean power (mW) of frame ``o`` at receiver ``rid`` standing at ``(rx, ry)``;
        0 if ``rid`` does not listen to ``o``'s cell. ``moving``: the receiver
        moves (its value is kept for this frame only)."""
        cache = o.mw_cache
        if moving and o.shared:
            m = o.mw_moving
            if m is None:
                m = o.mw_moving = {}
            cache = m
        v = cache.get(rid)
        if v is None:
            # cell_of and _mw inlined (the same operations).
            cs = self.cell_size
            oc = o.cell
            if abs(math.floor(rx / cs) - oc[0]) > 1 or abs(math.floor(ry / cs) - oc[1]) > 1:
                v = 0.0
            else:
                d = math.hypot(rx - o.x, ry - o.y)
                v = 10.0 ** (self.model.mean_rssi(o.src, rid, d, o.tx_power) / 10.0)
            cache[rid] = v
        return v

    def busy(self, rid: int, x: float, y: float, t0: float, t1: float, threshold_dbm: float,
             carrier_sense: bool, moving: bool = False, noise_mw: float = 0.0) -> bool:  # fmt: skip
        """Carrier sense by ``rid`` at ``(x, y)`` over ``[t0, t1]``: the energy of the
        frames of others on the air then (plus ``noise_mw``, the noise the radio
        hears then, when the noise varies) reaches ``threshold_dbm``, or (with
        ``carrier_sense``) one of them is received at or above the sensitivity.
        ``moving``: ``rid`` moves (:meth:`power_mw`)."""
        total = noise_mw
        sens = self._sens_mw
        cs = self.cell_size
        # power_mw is 0 beyond one cell of the receiver's: only those frames count.
        for o in self.near((math.floor(x / cs), math.floor(y / cs)), 1):
            if o.end <= t0 or o.start >= t1 or o.src == rid:  # most frames ended before t0
                continue
            p = self.power_mw(o, rid, x, y, moving)
            if carrier_sense and p >= sens:
                return True
            total += p
        return total > 0.0 and total >= _mw(threshold_dbm)

    def survives(
        self,
        f: OnAir,
        rssi_dbm: float,
        rid: int,
        rx: float,
        ry: float,
        others: list[OnAir],
        moving: bool = False,
        noise_mw: float | None = None,
    ) -> bool:
        """Did frame ``f``, received at ``rssi_dbm`` by ``rid`` at ``(rx, ry)``, survive
        the ``others`` (:meth:`overlapping`)? False if ``rid`` itself transmitted
        during it (deaf) or its SINR fell below the capture threshold at any instant.
        ``moving``: ``rid`` moves (:meth:`power_mw`); ``noise_mw``: the noise at
        ``rid`` then (None: the preset's floor)."""
        nm = self._noise_mw if noise_mw is None else noise_mw
        if len(others) == 1:  # the usual case (after the driver's cell filter): no spans
            o = others[0]
            if o.src == rid:
                return False  # half duplex: a transmitting radio hears nothing
            p1 = self.power_mw(o, rid, rx, ry, moving)
            if p1 <= 0.0:
                return True
            cap1 = self.capture_mw
            # One interferer: it is the worst instant (as below).
            return cap1 is not None and _mw(rssi_dbm) >= cap1 * (nm + p1)
        spans = []
        for o in others:
            if o.src == rid:
                return False  # half duplex: a transmitting radio hears nothing
            p = self.power_mw(o, rid, rx, ry, moving)
            if p > 0.0:
                spans.append((max(o.start, f.start), min(o.end, f.end), p))
        if not spans:
            return True
        cap = self.capture_mw
        if cap is None:
            return False
        if len(spans) == 1:  # one interferer: it is the worst instant
            return _mw(rssi_dbm) >= cap * (nm + spans[0][2])
        # Worst instant: the interference is piecewise constant and peaks at the start
        # of some overlap.
        worst = 0.0
        for t, _, _ in spans:
            i = sum(p for s, e, p in spans if s <= t < e)
            worst = max(worst, i)
        return _mw(rssi_dbm) >= cap * (nm + worst)
