"""Reception: how a frame that just left the air is heard, by both radio media.

``docs/radio.md`` ("Medium semantics") rules 3 to 6 and 9, in one place: the
frame's opening (its MIC checked once per transmission), which of a medium's
motes it reaches, and for each of them the reception decision and its
accounting -- beyond range (``dropped_distance``), lost (``dropped_loss``),
destroyed by overlapping frames (``collisions``), received (``frames_rx``,
``bytes_rx``), refused by link security (a bad MIC, a replay), a unicast's
duplicate filter and auto-ACK, the capture tap's record of each, and the
battery check after each reception. The virtual medium
(:mod:`awaremw.radio.virtual_medium`) and the Zenoh medium
(:mod:`awaremw.radio.zenoh_medium`) both call a :class:`Reception` for every
frame; what stays theirs is when a frame is decided (an event heap, or a
Zenoh envelope and a guard timer) and what a delivery does (a core's
``receive``, or a runner's ``radio_receive``): the ``deliver`` and ``down``
callbacks.

Who hears whom comes from :mod:`awaremw.radio.neighbourhood` (cells, the
receiver caches of static senders, bulk-counted far receivers); the link
layer's state from :mod:`awaremw.radio.linklayer`. The loop over a static
sender's near receivers is the hot path of both media: it inlines
:meth:`RadioModel.decide <awaremw.radio.model.RadioModel.decide>` (tests hold
the two equal) and makes no call per receiver but the delivery itself.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Generic, TypeVar

from awaremw.protocol.frames import BROADCAST
from awaremw.radio import linklayer
from awaremw.radio.capture import RadioTap, refused
from awaremw.radio.counters import MoteCounters
from awaremw.radio.linklayer import LinkStation
from awaremw.radio.mac import Air, OnAir
from awaremw.radio.model import (
    GOLDEN,
    M64,
    MUL,
    NORMAL,
    SHIFT,
    U32,
    RadioModel,
    cell_of,
    packet_key,
)
from awaremw.radio.neighbourhood import Cell, Link, Neighbourhood, adjacent
from awaremw.radio.security import FrameGuard, Opened

R = TypeVar("R", bound=LinkStation)


def reaching(others: list[OnAir], cell: Cell) -> list[OnAir]:
    """The frames of ``others`` sent from ``cell`` or the 8 cells around it: the
    only ones that reach a receiver in ``cell`` (``Air.power_mw`` is 0 for the
    rest, and a receiver's own frame is in its cell)."""
    cx, cy = cell
    return [o for o in others if -1 <= o.cell[0] - cx <= 1 and -1 <= o.cell[1] - cy <= 1]


class Reception(Generic[R]):
    """The reception rules of one medium, over its :class:`Neighbourhood`.

    ``deliver(r, src, data, rssi, now)`` hands a frame ``r`` took to its mote;
    ``down(r, now)`` switches off a mote whose battery is spent. ``guard``
    (link security) opens frames and refuses bad ones; ``air`` answers the
    collision checks (frames overlapping the one decided: ``others``).
    """

    __slots__ = (
        "air", "deliver", "down", "guard", "model", "nb", "noise", "one_snr", "overhead",
        "preset", "sens", "sigma_f",
    )  # fmt: skip

    def __init__(
        self,
        model: RadioModel,
        nb: Neighbourhood[R],
        air: Air,
        guard: FrameGuard | None,
        deliver: Callable[[R, int, bytes, float, float], None],
        down: Callable[[R, float], None],
    ) -> None:
        self.model = model
        self.nb = nb
        self.air = air
        self.guard = guard
        self.deliver = deliver
        self.down = down
        p = self.preset = model.preset
        self.sens = p.sensitivity_dbm
        self.noise = p.noise_floor_dbm
        self.one_snr = model.one_snr_db
        self.sigma_f = p.fading_sigma_db
        self.overhead = p.phy_overhead_bytes

    # ------------------------------------------------------------------ broadcast

    def broadcast(
        self,
        src: int,
        sx: float,
        sy: float,
        txp: float,
        cached: bool,
        frame: bytes,
        seq: int,
        f: OnAir | None,
        others: list[OnAir] | None,
        now: float,
        tap: RadioTap | None,
        at: float | None = None,
    ) -> bool:
        """Rules 3 to 5 for broadcast ``seq`` of ``src`` (at ``(sx, sy)``, power
        ``txp``) that just ended; ``others``: the frames that overlapped it (None:
        none, or collisions off). ``cached``: the static receivers through the
        sender's receiver cache (a sender standing still), else each evaluated
        afresh. ``at``: the frame's end, when the receivers' noise is taken
        (default ``now``). True if any mote here listens to the sender's cell."""
        t = now if at is None else at
        g = self.guard
        op = None if g is None else g.open(src, BROADCAST, seq, frame)  # once per frame
        n = len(frame)
        bits = 8 * (n + self.overhead)
        key = seq << 8  # packet_key(seq, 0)
        nb = self.nb
        heard = False
        if not cached:
            scell = cell_of(sx, sy, nb.cell_size)
            rng = self.model.max_range_m(txp)
            candidates = [r for lst in nb.cells_around(scell) for r in lst]
            candidates.extend(nb.moving)
            for r in candidates:
                heard = self._hear(src, sx, sy, scell, txp, rng, r, frame, n, bits, key, op, f,
                                   others, now, tap, t) or heard  # fmt: skip
            return heard
        c = nb.sender(src, sx, sy, txp)
        if c.near or c.far_loss or c.far_dist:
            heard = True
            c.pending += 1  # one more broadcast for the far_* receivers (counted in bulk)
        air = self.air
        deliver = self.deliver
        sens = self.sens
        noise = self.noise
        one = self.one_snr
        sf = self.sigma_f
        prr_bits = self.model.prr_bits
        memo = self.model.prr_memo
        nz = self.model.noise_over  # None: the preset's constant floor
        t0 = t - bits / self.preset.bitrate_bps  # the frame's start
        noise_mw: float | None = None
        normal = NORMAL
        mask = M64
        mul = MUL
        shift = SHIFT
        kg = (key * GOLDEN) & M64
        rel_by_cell: dict[Cell, list[OnAir]] | None = None if others is None else {}
        for r, rc, mean, lh in c.near:
            # RadioModel.decide(lh, mean, bits, key) inlined, the hot path.
            # packet_hash is z ^ (z >> 31): its top 12 bits (the normal deviate)
            # are z's, so the xorshift is only needed for the uniform draw,
            # inside the PRR's transitional band.
            z = ((lh ^ kg) * mul) & mask
            rssi = mean - sf * normal[z >> shift]
            if rssi < sens:
                if r.alive:
                    rc.dropped_loss += 1
                    if tap is not None:
                        tap.reception(now, src, r.node_id, rssi, "path_loss")
                continue
            if nz is not None:
                noise = nz(r.node_id, t0, t)
            snr = rssi - noise
            if snr < one:
                z ^= z >> 31
                # prr_bits(rssi, bits, noise), its cache looked up inline first.
                pv = memo.get((round(snr * 1000.0) << 16) | bits)
                if pv is None:
                    pv = prr_bits(rssi, bits, noise)
                if (z & 0xFFFFFFFF) * U32 >= pv:
                    if r.alive:
                        rc.dropped_loss += 1
                        if tap is not None:
                            tap.reception(now, src, r.node_id, rssi, "path_loss")
                    continue
            if not r.alive:
                continue
            if rel_by_cell is not None:  # others is not None
                # Only the overlapping frames that reach r count: none left means
                # the frame survived.
                rel = rel_by_cell.get(r.cell)
                if rel is None:
                    rel = rel_by_cell[r.cell] = reaching(others, r.cell)  # type: ignore[arg-type]
                if nz is not None:
                    noise_mw = 10.0 ** (noise / 10.0)
                if rel and not air.survives(f, rssi, r.node_id, r.x, r.y, rel,  # type: ignore[arg-type]
                                            False, noise_mw):  # fmt: skip
                    rc.collisions += 1
                    if tap is not None:
                        tap.reception(now, src, r.node_id, rssi, "collision")
                    continue
            rc.frames_rx += 1
            rc.bytes_rx += n
            data = frame if g is None else g.accept(r.node_id, rc, src, op)  # type: ignore[arg-type]
            if tap is not None:
                tap.reception(now, src, r.node_id, rssi, refused(data, op))
            if data is not None:
                deliver(r, src, data, rssi, now)
            if r.battery is not None and linklayer.battery_spent(r, self.preset):
                self.down(r, now)
        if nb.moving:
            scell = c.cell
            rng = self.model.max_range_m(txp)
            for r in list(nb.moving):
                heard = self._hear(src, sx, sy, scell, txp, rng, r, frame, n, bits, key, op, f,
                                   others, now, tap, t) or heard  # fmt: skip
        return heard

    def _hear(
        self,
        src: int,
        sx: float,
        sy: float,
        scell: Cell,
        txp: float,
        rng: float,
        r: R,
        frame: bytes,
        n: int,
        bits: int,
        key: int,
        op: Opened | None,
        f: OnAir | None,
        others: list[OnAir] | None,
        now: float,
        tap: RadioTap | None,
        t: float,
    ) -> bool:
        """One receiver of a broadcast evaluated afresh (moving motes, or any mote
        when the sender moves). False if it does not listen to the sender's cell."""
        if r.node_id == src or not r.alive:
            return False
        self.nb.locate(r, now)
        if not adjacent(r.cell, scell):
            return False  # not subscribed to the sender's cell: hears nothing, counts nothing
        rc = r.counters
        d = math.hypot(r.x - sx, r.y - sy)
        if d > rng:
            rc.dropped_distance += 1
            if tap is not None:
                tap.reception(now, src, r.node_id, None, "distance")
            return True
        m = self.model
        rssi = self._decide(rc, r, m.mean_rssi(src, r.node_id, d, txp),
                            m.fading_link_hash(src, r.node_id), n, bits, key, f, others, src, now,
                            tap, t)  # fmt: skip
        if rssi is None:
            return True
        g = self.guard
        data = frame if g is None or op is None else g.accept(r.node_id, rc, src, op)
        if tap is not None:
            tap.reception(now, src, r.node_id, rssi, refused(data, op))
        if data is not None:
            self.deliver(r, src, data, rssi, now)
        if linklayer.battery_spent(r, self.preset):
            self.down(r, now)
        return True

    def _decide(
        self,
        rc: MoteCounters,
        r: R,
        mean: float,
        link_h: int,
        n: int,
        bits: int,
        key: int,
        f: OnAir | None,
        others: list[OnAir] | None,
        src: int,
        now: float,
        tap: RadioTap | None,
        t: float,
    ) -> float | None:
        """Rule 5 for one receiver in range: the model decides (the noise at ``r``
        at ``t``); lost -> ``dropped_loss``; destroyed by the ``others`` ->
        ``collisions``; received -> ``frames_rx``, ``bytes_rx``, and the packet's
        RSSI is returned."""
        no = self.model.noise_over
        noise = None if no is None else no(r.node_id, t - bits / self.preset.bitrate_bps, t)
        ok, rssi = self.model.decide(link_h, mean, bits, key, noise)
        if not ok:
            rc.dropped_loss += 1
            if tap is not None:
                tap.reception(now, src, r.node_id, None, "path_loss")
            return None
        if (
            f is not None
            and others
            and not self.air.survives(
                f, rssi, r.node_id, r.x, r.y, others, not r.static,
                None if noise is None else 10.0 ** (noise / 10.0),
            )
        ):
            rc.collisions += 1
            if tap is not None:
                tap.reception(now, src, r.node_id, None, "collision")
            return None
        rc.frames_rx += 1
        rc.bytes_rx += n
        return rssi

    # ------------------------------------------------------------------ unicast

    def link(self, src: int, sx: float, sy: float, txp: float, r: R, now: float) -> Link[R] | None:
        """``(r, distance, mean RSSI, fading link hash)`` of a sender at ``(sx, sy)``
        to ``r`` at ``now``, evaluated afresh; None if ``r`` does not listen to the
        sender's cell (:meth:`Neighbourhood.link` caches it between static motes)."""
        self.nb.locate(r, now)
        if not adjacent(r.cell, cell_of(sx, sy, self.nb.cell_size)):
            return None
        d = math.hypot(r.x - sx, r.y - sy)
        m = self.model
        return r, d, m.mean_rssi(src, r.node_id, d, txp), m.fading_link_hash(src, r.node_id)

    def unicast(
        self,
        src: int,
        link: Link[R],
        range_m: float,
        frame: bytes,
        seq: int,
        attempt: int,
        f: OnAir | None,
        others: list[OnAir] | None,
        now: float,
        tap: RadioTap | None,
        at: float | None = None,
    ) -> bool:
        """Rules 4 to 6 for attempt ``(seq, attempt)`` of a unicast from ``src``
        (range ``range_m``) at its destination, on ``link``: the destination hears
        it (or not), checks its MIC, filters a duplicate, takes it, and ACKs
        whatever it got. True if it sent the ACK (the caller decides whether the
        sender hears it and checks the destination's battery). ``at``: the
        frame's end, when the noise is taken (default ``now``)."""
        r, d, mean, link_h = link
        rc = r.counters
        if d > range_m:
            rc.dropped_distance += 1
            if tap is not None:
                tap.reception(now, src, r.node_id, None, "distance")
            return False
        n = len(frame)
        key = packet_key(seq, attempt)
        rssi = self._decide(rc, r, mean, link_h, n, 8 * (n + self.overhead), key, f, others,
                            src, now, tap, now if at is None else at)  # fmt: skip
        if rssi is None:
            return False
        g = self.guard
        op = None if g is None else g.open(src, r.node_id, seq, frame)
        if g is not None and op is not None and op.payload is None:
            # Bad MIC: dropped before the duplicate filter (it cannot poison it); the
            # hardware ACK goes out all the same (802.15.4 ACKs are not secured).
            g.accept(r.node_id, rc, src, op)
            if tap is not None:
                tap.reception(now, src, r.node_id, rssi, "mic")
        elif linklayer.accept_unicast(r, src, seq):
            data = frame if g is None or op is None else g.accept(r.node_id, rc, src, op)
            if tap is not None:
                tap.reception(now, src, r.node_id, rssi, refused(data, op))
            if data is not None:
                self.deliver(r, src, data, rssi, now)
        elif tap is not None:
            tap.reception(now, src, r.node_id, rssi, "duplicate")
        return linklayer.send_ack(r)  # False: switched off by whoever handled the frame
