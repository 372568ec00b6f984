"""One mote's link layer, as both media run it (``docs/radio.md`` rules 2, 6, 7, 9).

The Zenoh medium (:mod:`awaremw.radio.zenoh_medium`) and the virtual-clock
driver (:mod:`awaremw.radio.virtual_medium`) schedule differently (asyncio timers
vs. an event heap) but keep the same per-mote state, :class:`LinkStation`,
and change it through these functions only: taking the next frame and its
link sequence number, the attempt's channel access (:func:`attempt`,
:func:`assess`, :func:`put_on_air`, :func:`give_up`: the
:class:`~awaremw.radio.mac.MacSender` and :class:`~awaremw.radio.mac.Air` of
:mod:`awaremw.radio.mac`), the receiver's duplicate filter and ACK decision,
when a unicast attempt's outcome is known (:func:`outcome_time`), the
sender's retry-or-settle decision after an attempt, and switching off. A
medium only turns the times these return into its own timers.
"""

from __future__ import annotations

from collections import deque

from mypy_extensions import mypyc_attr

from awaremw.protocol.core import Transmission
from awaremw.protocol.frames import BROADCAST, MAX_NODE_ID
from awaremw.radio.counters import Battery, MoteCounters
from awaremw.radio.mac import Air, MacParams, MacSender, OnAir
from awaremw.radio.model import RadioModel, RadioPreset, packet_key
from awaremw.radio.neighbourhood import Station
from awaremw.radio.security import FrameGuard
from awaremw.world.mobility import Mobility


# The Zenoh medium's Radio (not compiled) subclasses it in the compiled build (setup.py).
@mypyc_attr(allow_interpreted_subclasses=True)
class LinkStation(Station):
    """A mote's radio: where it is (:class:`Station`) and its link-layer state."""

    __slots__ = (
        "air", "battery", "busy", "cur", "cur_attempt", "cur_seq", "last_useq", "mac", "onair",
        "queue", "seq",
    )  # fmt: skip

    def __init__(
        self,
        node_id: int,
        mobility: Mobility,
        tx_power: float,
        range_m: float,
        counters: MoteCounters,
        battery: Battery | None,
    ) -> None:
        super().__init__(node_id, mobility, tx_power, range_m, counters)
        self.battery = battery
        self.queue: deque[Transmission] = deque()  # drained from the core, not yet on the air
        self.busy = False
        # The frame on the air or awaiting its ACK (None when the radio is idle),
        # its link sequence number and attempt (0 = first transmission).
        self.cur: Transmission | None = None
        self.cur_seq = 0
        self.cur_attempt = 0
        # The bytes of ``cur`` on the air: its frame, sealed (counter + MIC) when
        # the medium has a FrameGuard (awaremw.radio.security), else the frame itself.
        self.air = b""
        self.seq = 0  # 16-bit link sequence number of the next frame
        self.last_useq: dict[int, int] = {}  # src -> seq of the last unicast delivered
        self.mac: MacSender | None = None  # channel access (set by the medium on attach/add)
        self.onair: OnAir | None = None  # the attempt on the Air now (None: none, or untracked)


def check_node_id(nid: object) -> int:
    """A mote id the frames can carry, else ValueError (a local bug)."""
    if not isinstance(nid, int) or not 0 <= nid <= MAX_NODE_ID:
        raise ValueError(f"node id {nid!r} outside 0..{MAX_NODE_ID}")
    return nid


def tx_power_of(preset: RadioPreset, tx_power_dbm: float | None) -> float:
    """The TX power a mote uses (the preset's default if None), checked against the chip."""
    txp = preset.tx_power_dbm if tx_power_dbm is None else float(tx_power_dbm)
    preset.check_tx_power(txp)
    return txp


def check_transmission(st: LinkStation, tx: Transmission, mtu: int) -> None:
    """Rule 2: a core that sends an oversize frame, or to itself, has a bug: raise."""
    if len(tx.frame) > mtu:
        raise ValueError(f"node {st.node_id}: frame of {len(tx.frame)} bytes > MTU")
    d = tx.dest
    if d != BROADCAST and (not 0 <= d <= MAX_NODE_ID or d == st.node_id):
        raise ValueError(f"node {st.node_id}: bad destination {d}")


def begin_next(st: LinkStation, guard: FrameGuard | None = None) -> Transmission:
    """Rule 2: the next queued frame goes on the air with the next link sequence
    number, attempt 0 (the caller schedules the attempt; the queue is not empty).
    With a ``guard`` the bytes on the air (``st.air``) are the frame sealed with
    the sender's next frame counter and a MIC; retries send the same bytes."""
    tx = st.queue.popleft()
    seq = st.seq
    st.seq = (seq + 1) & 0xFFFF
    st.busy = True
    st.cur = tx
    st.cur_seq = seq
    st.cur_attempt = 0
    st.air = tx.frame if guard is None else guard.seal(st.node_id, tx.dest, seq, tx.frame)
    return tx


def attempt(st: LinkStation, now: float) -> float:
    """The current attempt ``(cur_seq, cur_attempt)`` is ready at ``now``: when its
    first clear channel assessment ends (CSMA) or when it goes on the air (ALOHA)."""
    mac = st.mac
    if mac is None:
        raise RuntimeError(f"node {st.node_id}: no MacSender (the medium did not set one)")
    return mac.begin(st.cur_seq, st.cur_attempt, now)


def assess(st: LinkStation, air: Air, p: MacParams, now: float) -> tuple[int, float]:
    """The clear channel assessment of ``st`` ending at ``now`` (``st`` located):
    busy if the frames ``air`` knows of reach ``st`` over ``[now - cca_s, now]``
    (``cca_busy += 1``). Returns :meth:`MacSender.cca`'s ``(action, t)``:
    ``TRANSMIT`` (call :func:`put_on_air` with ``t``), ``SENSE`` (assess again,
    ending at ``t``) or ``GIVE_UP`` (call :func:`give_up`)."""
    t0 = now - p.cca_s
    nz = air.model.noise_at
    threshold = p.cca_threshold_dbm
    noise_mw = 0.0
    if nz is not None:  # the noise varies: the radio hears it too (MacParams.cca_margin_db)
        noise = nz(st.node_id, now)
        noise_mw = 10.0 ** (noise / 10.0)
        if p.cca_margin_db is not None:
            threshold = noise + p.cca_margin_db
    if st.static and not air.any_near(st.node_id, st.cell, t0, now):
        # No frame of another mote near enough during the assessment: the noise alone.
        busy = noise_mw > 0.0 and noise_mw >= 10.0 ** (threshold / 10.0)
    else:
        busy = air.busy(st.node_id, st.x, st.y, t0, now, threshold, p.carrier_sense,
                        not st.static, noise_mw)  # fmt: skip
    if busy:
        st.counters.cca_busy += 1
    return st.mac.cca(busy, now)  # type: ignore[union-attr]


def airtime_end(preset: RadioPreset, start: float, n: int) -> float:
    """When an attempt of ``n`` bytes started at ``start`` leaves the air (both
    media use this one expression, so that they compute the same float)."""
    return start + (n + preset.phy_overhead_bytes) * (8.0 / preset.bitrate_bps)


def put_on_air(
    st: LinkStation,
    air: Air | None,
    preset: RadioPreset,
    start: float,
    mw: dict[int, float] | None = None,
) -> float:
    """The current attempt goes on the air at ``start`` (``st`` located): with an
    ``air`` (carrier sense or collisions on) it is added to it as ``st.onair``
    (``mw``: a static sender's shared mean powers, :meth:`Air.add`).
    Returns its end."""
    end = airtime_end(preset, start, len(st.air))
    if air is not None:
        key = packet_key(st.cur_seq, st.cur_attempt)
        st.onair = air.add(st.node_id, st.x, st.y, st.tx_power, start, end, key, mw)
    return end


def outcome_time(preset: RadioPreset, end: float, acked: bool) -> float:
    """Rule 7: when the sender of a unicast attempt that ended at ``end`` knows its
    outcome (the ACK heard, or the ACK wait expired)."""
    if acked:
        return end + preset.ack_turnaround_s + preset.ack_airtime_s
    return end + preset.ack_timeout_s


def accept_unicast(st: LinkStation, src: int, seq: int) -> bool:
    """Rule 6, duplicate filter: False (and ``duplicates += 1``) if ``(src, seq)`` is
    the last unicast delivered from ``src`` (our ACK was lost and it retried)."""
    if st.last_useq.get(src) == seq:
        st.counters.duplicates += 1
        return False
    st.last_useq[src] = seq
    return True


def send_ack(st: LinkStation) -> bool:
    """Rule 6: a destination still on the air ACKs every unicast it got, duplicates
    included (``acks_tx += 1``). False if it was switched off meanwhile."""
    if not st.alive:
        return False
    st.counters.acks_tx += 1
    return True


def ack_heard(
    model: RadioModel,
    acker: int,
    acker_txp: float,
    dst: int,
    d: float,
    seq: int,
    attempt: int,
    t: float = 0.0,
) -> bool:
    """Rule 6, the ACK of attempt ``(seq, attempt)`` on the reverse link: does
    ``dst`` hear the ACK that ``acker`` sends at its own power from distance ``d``?
    ``t``: the data frame's end (the noise at ``dst`` is taken then)."""
    if d > model.max_range_m(acker_txp):
        return False
    ok, _ = model.ack_reception(acker, dst, d, acker_txp, packet_key(seq, attempt, ack=True), t)
    return ok


def settle(st: LinkStation, acked: bool, max_retries: int) -> bool:
    """Rule 7 after a unicast attempt. True: retry (``retries += 1``, same ``seq``,
    next attempt; the caller schedules it). False: the frame is done
    (``acks_rx`` and ``unicast_ok``, or ``unicast_failed``) and the radio idle;
    the caller reports the outcome to the core (read ``st.cur`` before)."""
    c = st.counters
    if not acked and st.cur_attempt < max_retries:
        c.retries += 1
        st.cur_attempt += 1
        return True
    if acked:
        c.acks_rx += 1
        c.unicast_ok += 1
    else:
        c.unicast_failed += 1
    st.busy = False
    st.cur = None
    st.air = b""
    return False


def give_up(st: LinkStation) -> Transmission | None:
    """Channel access failure (radio/mac.py: too many busy assessments): the frame
    on the air is dropped (``mac_drops += 1``, no retry) and the radio is idle.
    Returns it (a unicast's outcome goes to the core as not acknowledged)."""
    tx = st.cur
    st.counters.mac_drops += 1
    st.busy = False
    st.cur = None
    st.air = b""
    st.onair = None
    return tx


def battery_spent(st: LinkStation, preset: RadioPreset) -> bool:
    """Rule 9: a mote on the air whose battery budget is spent (checked after each
    of its transmissions and receptions); the caller switches it off."""
    b = st.battery
    return b is not None and st.alive and b.is_dead(st.counters, preset, st.tx_power)


def silence(st: LinkStation) -> None:
    """Rules 1 and 9: off the air; queued frames and the frame on the air are lost."""
    st.alive = False
    st.queue.clear()
    st.busy = False
    st.cur = None
    st.air = b""
    st.onair = None
