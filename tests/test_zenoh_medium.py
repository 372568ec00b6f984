"""The Zenoh medium against the radio model, over real Zenoh sessions on loopback.

Each "process" here is a Fleet with its own Zenoh session (peer mode,
multicast scouting off) connected to an embedded router on a free port; the
two-process case with real worker processes is in test_fleet.py.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Callable, Iterator

import msgpack
import pytest
import zenoh

from awaremw.protocol.core import Transmission
from awaremw.protocol.events import MalformedFrame
from awaremw.protocol.frames import BROADCAST, FrameError, Hello, decode, encode
from awaremw.radio.envelope import Kind, MalformedEnvelope, decode_envelope, encode_envelope
from awaremw.radio.model import NORMAL, RadioModel, cell_of, packet_key
from awaremw.radio.zenoh_medium import Handler
from awaremw.runtime.deployment import Deployment, NodeSpec, parse_deployment
from awaremw.runtime.fleet import Fleet, FleetSettings
from awaremw.runtime.router import EmbeddedRouter
from awaremw.runtime.zenoh_session import (
    SessionSettings,
    close_quietly,
    free_tcp_endpoint,
    open_session,
)

pytestmark = pytest.mark.zenoh


# --------------------------------------------------------------------------- helpers


class Recorder:
    """A test core: beacons Hello(seq) every ``period`` (None: silent), records
    what it hears and the outcome of its unicasts."""

    def __init__(self, node_id: int, period: float | None = None, mtu: int = 100) -> None:
        self.node_id = node_id
        self.period = period
        self.mtu = mtu
        self.seq = 0
        self.heard: list[tuple[int, int, float, int]] = []  # (src, seq, rssi, frame len)
        self.bad: list[bytes] = []
        self.results: list[tuple[int, bool]] = []  # (dest, acked)
        self._next: float | None = None
        self._out: list[Transmission] = []
        self._events: list[object] = []

    def start(self, now: float) -> None:
        if self.period is not None:
            self._next = now

    def receive(self, frame: bytes, rssi_dbm: float, now: float) -> None:
        try:
            f = decode(frame)
        except FrameError as e:
            self.bad.append(frame)
            self._events.append(MalformedFrame(str(e), len(frame)))
            return
        assert isinstance(f, Hello)
        self.heard.append((f.src, f.seq, rssi_dbm, len(frame)))

    def handle_timer(self, now: float) -> None:
        if self._next is not None and now >= self._next and self.period is not None:
            self.send(BROADCAST)
            self._next += self.period

    def next_deadline(self) -> float | None:
        return self._next

    def drain(self) -> list[Transmission]:
        out, self._out = self._out, []
        return out

    def link_result(self, tx: Transmission, acked: bool, now: float) -> None:
        self.results.append((tx.dest, acked))

    def events(self) -> list[object]:
        ev, self._events = self._events, []
        return ev

    def send(self, dest: int) -> Transmission:
        data = encode(Hello(self.node_id, dest, self.seq), self.mtu)
        self.seq += 1
        tx = Transmission.broadcast(data) if dest == BROADCAST else Transmission.unicast(data, dest)
        self._out.append(tx)
        return tx


def deployment(nodes: list[tuple[int, float, float]], radio: str = "cc2420") -> Deployment:
    return parse_deployment(
        {
            "name": "t",
            "radio": radio,
            "seed": 7,
            "area": [400.0, 400.0],
            "nodes": [{"id": i, "kind": "x", "position": [x, y]} for i, x, y in nodes],
        }
    )


def factory(periods: dict[int, float]) -> Callable[[NodeSpec, Deployment], Recorder]:
    def make(spec: NodeSpec, dep: Deployment) -> Recorder:
        return Recorder(spec.id, periods.get(spec.id), dep.preset.mtu)

    return make


async def wait_for(pred: Callable[[], bool], timeout: float = 10.0) -> None:
    """Wait (polling the loop) until ``pred()`` holds; fail after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > deadline:
            raise AssertionError("condition not reached in time")
        await asyncio.sleep(0.01)


@pytest.fixture(scope="module")
def router() -> Iterator[str]:
    """One router for the module (opening one takes half a second); every test
    closes its fleets, so nothing crosses from one test to the next."""
    ep = free_tcp_endpoint()
    with EmbeddedRouter([ep]):
        yield ep


def two_fleets(
    dep: Deployment, ep: str, a_ids: set[int], periods: dict[int, float], speed: float = 1.0
) -> tuple[Fleet, Fleet]:
    """Fleet A runs ``a_ids``, fleet B the others; both joined through router ``ep``."""
    mk = factory(periods)
    # Not started on entry: joined() starts both together.
    sa = FleetSettings(name="a", speed=speed, connect=(ep,), autostart=False)
    sb = FleetSettings(name="b", speed=speed, connect=(ep,), autostart=False)
    a = Fleet(dep, mk, sa, node_filter=lambda s: s.id in a_ids)
    b = Fleet(dep, mk, sb, node_filter=lambda s: s.id not in a_ids)
    return a, b


async def routed(session: zenoh.Session, fleet: Fleet) -> None:
    """Wait until ``session`` sees a subscriber of ``fleet``'s radio columns."""
    cx = min(fleet.medium.columns) + 1
    pub = session.declare_publisher(
        f"{fleet.prefix}/radio/{cx}/0/probe", allowed_destination=zenoh.Locality.REMOTE
    )
    try:
        # matching_status is a MatchingStatus object (despite the stub's bool)
        await wait_for(lambda: bool(getattr(pub.matching_status, "matching", False)))
    finally:
        close_quietly(pub)


async def joined(a: Fleet, b: Fleet) -> None:
    """Enter both fleets; start them together once each sees the other's subscriptions."""
    await a.__aenter__()
    await b.__aenter__()
    await routed(a.session, b)
    await routed(b.session, a)
    t0 = time.time()
    a.start(t0)
    b.start(t0)


def core(fleet: Fleet, node_id: int) -> Recorder:
    c = fleet.runners[node_id].core
    assert isinstance(c, Recorder)
    return c


# --------------------------------------------------------------------------- envelope


def test_envelope_round_trip_and_garbage() -> None:
    data = encode_envelope(Kind.FRAME, 3, 1.5, -2.0, -5.0, 65535, 2, 12.5, 9, b"\x93\x01")
    env = decode_envelope(data)
    assert (env.kind, env.src, env.x, env.y, env.tx_power) == (Kind.FRAME, 3, 1.5, -2.0, -5.0)
    assert (env.seq, env.attempt, env.t, env.dest, env.frame) == (65535, 2, 12.5, 9, b"\x93\x01")
    assert decode_envelope(env.encode()) == env
    bad = [
        b"",
        b"\xc1",
        msgpack.packb([1, 2, 3]),
        msgpack.packb([2, 0, 1, 0.0, 0.0, 0.0, 0, 0, 0.0, 1, b""]),  # version
        msgpack.packb([1, 5, 1, 0.0, 0.0, 0.0, 0, 0, 0.0, 1, b""]),  # kind
        msgpack.packb([1, 0, 0xFFFE, 0.0, 0.0, 0.0, 0, 0, 0.0, 1, b""]),  # src
        msgpack.packb([1, 0, 1, float("nan"), 0.0, 0.0, 0, 0, 0.0, 1, b""]),  # x
        msgpack.packb([1, 0, 1, 0.0, 0.0, 0.0, 70000, 0, 0.0, 1, b""]),  # seq
        msgpack.packb([1, 0, 1, 0.0, 0.0, 0.0, 0, 0, 0.0, 1, "text"]),  # frame
        msgpack.packb([1, 1, 1, 0.0, 0.0, 0.0, 0, 0, 0.0, 0xFFFF, b""]),  # broadcast ACK
    ]
    for b in bad:
        with pytest.raises(MalformedEnvelope):
            decode_envelope(b)


# --------------------------------------------------------------------------- RSSI


async def test_rssi_follows_the_model_and_the_formula(router: str) -> None:
    d = 10.0
    dep = deployment([(1, 10.0, 10.0), (2, 10.0 + d, 10.0)])
    a, b = two_fleets(dep, router, {1}, {1: 0.02}, speed=5.0)
    await joined(a, b)
    try:
        rx = core(b, 2)
        await wait_for(lambda: len(rx.heard) >= 150)
    finally:
        await a.aclose()
        await b.aclose()
    model = RadioModel(dep.preset, dep.seed)
    p = dep.preset
    for src, seq, rssi, _ in rx.heard:
        assert src == 1
        assert rssi == pytest.approx(model.rssi(1, 2, d, 0.0, packet_key(seq)), abs=1e-9)
    # The formula: P_tx - (PL(d0) + 10 n log10(d / d0)) - static shadow; per-packet
    # fading has mean ~0 and sigma fading_sigma_db.
    mean_formula = 0.0 - (p.pl_d0_db + 10 * p.path_loss_exponent * math.log10(d / p.d0_m))
    mean_formula -= model.static_shadow_db(1, 2)
    got = [r for _, _, r, _ in rx.heard]
    n = len(got)
    mean = sum(got) / n
    sd = math.sqrt(sum((g - mean) ** 2 for g in got) / (n - 1))
    assert abs(mean - mean_formula) < 4 * p.fading_sigma_db / math.sqrt(n)
    assert 0.6 * p.fading_sigma_db < sd < 1.4 * p.fading_sigma_db
    # The sender's own counters: every beacon went on the air once. A frame is
    # published when it starts and counted by its sender when it ends: the one on
    # the air when fleet a closed may have been heard by b and never counted by a.
    assert a.counters()[1].frames_tx >= n - 1


# --------------------------------------------------------------------------- loss


def _distance_for_prr(model: RadioModel, src: int, dst: int, bits: int, target: float) -> float:
    """Distance at which the fading-averaged PRR of link src->dst is ``target``."""
    sf = model.preset.fading_sigma_db

    def p(d: float) -> float:
        mean = model.mean_rssi(src, dst, d, 0.0)
        return sum(model.prr_bits(mean - sf * z, bits) for z in NORMAL) / len(NORMAL)

    lo, hi = 1.0, model.max_range_m(0.0)
    for _ in range(60):
        mid = (lo + hi) / 2
        if p(mid) > target:
            lo = mid
        else:
            hi = mid
    return lo


async def test_loss_rate_matches_the_prr_curve(router: str) -> None:
    base = deployment([(1, 5.0, 5.0), (2, 6.0, 5.0)], radio="cc1000")
    model = RadioModel(base.preset, base.seed)
    bits = 8 * (7 + base.preset.phy_overhead_bytes)  # Hello(seq >= 128) is 7 bytes
    d = _distance_for_prr(model, 1, 2, bits, 0.5)
    dep = deployment([(1, 5.0, 5.0), (2, 5.0 + d, 5.0)], radio="cc1000")
    a, b = two_fleets(dep, router, {1}, {1: 0.05}, speed=20.0)
    await joined(a, b)
    n_sent = 400
    try:
        tx = core(a, 1)
        await wait_for(lambda: a.counters()[1].frames_tx >= n_sent, timeout=30)
        a.medium.freeze()  # no new frame; the one on the air still lands
        await wait_for(lambda: not a.medium.radios[1].busy)
        sent = a.counters()[1].frames_tx
        await wait_for(
            lambda: sum(b.counters()[2].as_dict()[k] for k in ("frames_rx", "dropped_loss")) >= sent
        )
    finally:
        await a.aclose()
        await b.aclose()
    rx = core(b, 2)
    assert tx.seq >= sent
    # Exactly the packets the model keeps (same seeded decision in every process) ...
    kept = {
        seq
        for seq in range(sent)
        if model.reception(
            1, 2, d, 0.0, len(encode(Hello(1, BROADCAST, seq), 64)), packet_key(seq)
        )[0]
    }
    assert {seq for _, seq, _, _ in rx.heard} == kept
    assert b.counters()[2].dropped_loss == sent - len(kept)
    # ... and their rate follows the PRR curve within statistical tolerance.
    sf = model.preset.fading_sigma_db
    probs = []
    for seq in range(sent):
        nb = 8 * (len(encode(Hello(1, BROADCAST, seq), 64)) + model.preset.phy_overhead_bytes)
        mean = model.mean_rssi(1, 2, d, 0.0)
        probs.append(sum(model.prr_bits(mean - sf * z, nb) for z in NORMAL) / len(NORMAL))
    expect = sum(probs)
    sigma = math.sqrt(sum(q * (1 - q) for q in probs))
    assert abs(len(kept) - expect) < 4 * sigma
    assert 0.3 < len(kept) / sent < 0.7  # really in the transitional region


# --------------------------------------------------------------------------- unicast


async def test_unicast_out_of_range_fails_after_retries_in_range_succeeds_once(
    router: str,
) -> None:
    # 1 sends; 2 is 80 m away (beyond the 54 m range, in the neighbouring cell);
    # 3 is 8 m away. 2 and 3 run in the other process.
    dep = deployment([(1, 60.0, 5.0), (2, 140.0, 5.0), (3, 68.0, 5.0)])
    a, b = two_fleets(dep, router, {1}, {})
    size = a.model.cell_size_m
    assert cell_of(140.0, 5.0, size)[0] - cell_of(60.0, 5.0, size)[0] == 1
    await joined(a, b)
    try:
        s = core(a, 1)
        a.run_on(1, lambda c, now: c.send(2))  # type: ignore[attr-defined]
        await wait_for(lambda: len(s.results) == 1)
        assert s.results == [(2, False)]
        c1 = a.counters()[1]
        retries = dep.preset.max_retries
        assert (c1.frames_tx, c1.retries, c1.unicast_failed, c1.unicast_ok) == (
            1 + retries,
            retries,
            1,
            0,
        )
        assert b.counters()[2].frames_rx == 0
        assert b.counters()[2].dropped_distance == 1 + retries

        a.run_on(1, lambda c, now: c.send(3))  # type: ignore[attr-defined]
        await wait_for(lambda: len(s.results) == 2)
        assert s.results[1] == (3, True)
        c1 = a.counters()[1]
        assert (c1.unicast_ok, c1.acks_rx) == (1, 1)
        r3 = core(b, 3)
        assert [(src, seq) for src, seq, _, _ in r3.heard] == [(1, 1)]  # delivered once
        assert b.counters()[3].acks_tx == b.counters()[3].frames_rx
        assert b.counters()[3].frames_rx - b.counters()[3].duplicates == 1
    finally:
        await a.aclose()
        await b.aclose()


async def test_unicast_inside_one_process_and_duplicates_on_a_lossy_link(router: str) -> None:
    # A link where some ACKs get lost: retries happen, and each frame reaches
    # the core at most once whatever the number of attempts it took.
    base = deployment([(1, 5.0, 5.0), (2, 6.0, 5.0)], radio="cc1000")
    model = RadioModel(base.preset, base.seed)
    d = _distance_for_prr(model, 1, 2, 8 * (7 + base.preset.phy_overhead_bytes), 0.6)
    dep = deployment([(1, 5.0, 5.0), (2, 5.0 + d, 5.0)], radio="cc1000")
    async with Fleet(dep, factory({}), FleetSettings(speed=10.0, connect=(router,))) as f:
        s = core(f, 1)
        n = 40
        for _ in range(n):
            f.run_on(1, lambda c, now: c.send(2))  # type: ignore[attr-defined]
        await wait_for(lambda: len(s.results) == n, timeout=30)
        c1, c2 = f.counters()[1], f.counters()[2]
        r2 = core(f, 2)
        seqs = [seq for _, seq, _, _ in r2.heard]
        assert len(seqs) == len(set(seqs))  # never twice to the core
        assert c2.frames_rx == len(seqs) + c2.duplicates
        assert c1.unicast_ok + c1.unicast_failed == n
        assert c1.unicast_ok == sum(1 for _, ok in s.results if ok)
        assert c1.frames_tx == n + c1.retries
        assert c1.retries > 0 and c1.unicast_ok > 0
        assert c1.acks_rx == c1.unicast_ok


# --------------------------------------------------------------------------- garbage


@pytest.mark.parametrize("handler", ["channel", "callback"])
async def test_garbage_on_a_radio_key_is_counted_malformed_and_changes_nothing_else(
    router: str, handler: Handler
) -> None:
    # 1 and 2 stand in cell (0, 0); 3 stands three cells away.
    dep = deployment([(1, 5.0, 5.0), (2, 15.0, 5.0), (3, 250.0, 250.0)])
    async with Fleet(dep, factory({}), FleetSettings(connect=(router,), handler=handler)) as f:
        other = open_session(SessionSettings(connect=(router,)))
        try:
            await routed(other, f)
            before = {i: c.as_dict() for i, c in f.counters().items()}
            other.put("aware/radio/0/0/77", b"\xc1 not an envelope")
            await wait_for(lambda: f.medium.stats.malformed_envelopes == 1)
            after = {i: c.as_dict() for i, c in f.counters().items()}
            for i in (1, 2):
                assert after[i].pop("malformed") == before[i].pop("malformed") + 1
                assert after[i] == before[i]
            assert after[3] == before[3]
            assert core(f, 1).heard == [] and core(f, 2).heard == []

            # A valid envelope carrying garbage frame bytes: delivered like any
            # frame, the core reports it, the driver counts it as malformed.
            env = encode_envelope(
                Kind.FRAME, 77, 10.0, 5.0, 0.0, 0, 0, f.now(), BROADCAST, b"\xc1\xc1"
            )
            other.put("aware/radio/0/0/77", env)
            c = f.counters()
            await wait_for(lambda: c[1].malformed == 2 and c[2].malformed == 2)
            assert core(f, 1).bad == [b"\xc1\xc1"]
            assert f.medium.stats.malformed_envelopes == 1
        finally:
            close_quietly(other)


# --------------------------------------------------------------------------- cells


async def test_subscriptions_are_per_column_not_per_mote(router: str) -> None:
    # 30 motes in one cell column need 3 subscriptions (their column and the
    # two beside it); a moving mote adds the columns it enters.
    nodes = [(i, 5.0 + (i % 5) * 8.0, 5.0 + (i // 5) * 50.0) for i in range(30)]
    dep = deployment(nodes)
    async with Fleet(
        dep, factory({99: 0.05}), FleetSettings(connect=(router,), control=False)
    ) as f:
        assert f.medium.stats.subscriptions == 3
        assert f.medium.columns == frozenset({-1, 0, 1})
        spec = f.control.parse_node(
            {"id": 99, "kind": "x", "path": [[5.0, 5.0], [300.0, 5.0]], "speed_mps": 2000.0}
        )
        f.motes.add(spec)
        await wait_for(lambda: 6 in f.medium.columns, timeout=5)  # it stands in column 5
        x, _ = f.motes.positions(f.now())[99]
        assert x > 5 * f.model.cell_size_m
        # Its frames now go out on its new cell's key.
        radio = f.medium.radios[99]
        await wait_for(lambda: radio.pub_cell is not None and radio.pub_cell[0] >= 5)
        assert f.medium.stats.subscriptions == len(f.medium.columns) >= 7


# --------------------------------------------------------------------------- capture tap


class TapLog:
    """A RadioTap (awaremw.radio.capture) that keeps every call."""

    def __init__(self) -> None:
        self.air: list[tuple[int, int, int, int]] = []  # (src, dest, seq, attempt)
        self.rx: list[tuple[int, int, float | None, str | None]] = []  # (src, dst, rssi, cause)

    def on_air(self, t: float, src: int, dest: int, seq: int, attempt: int, frame: bytes) -> None:
        self.air.append((src, dest, seq, attempt))

    def reception(
        self, t: float, src: int, dst: int, rssi: float | None, cause: str | None
    ) -> None:
        self.rx.append((src, dst, rssi, cause))


async def test_tap_reports_every_attempt_and_reception_across_processes(router: str) -> None:
    # 1 (process a) broadcasts and unicasts to 2 over a lossy link (retries,
    # duplicates); 2 and 3 (process b) only listen. Each medium reports what it
    # sends and decides; the counts equal the counters.
    base = deployment([(1, 5.0, 5.0), (2, 6.0, 5.0)], radio="cc1000")
    model = RadioModel(base.preset, base.seed)
    d = _distance_for_prr(model, 1, 2, 8 * (7 + base.preset.phy_overhead_bytes), 0.6)
    dep = deployment([(1, 5.0, 5.0), (2, 5.0 + d, 5.0), (3, 5.0, 5.0 + d / 2)], radio="cc1000")
    a, b = two_fleets(dep, router, {1}, {1: 0.05}, speed=10.0)
    ta, tb = TapLog(), TapLog()
    try:
        await a.__aenter__()
        await b.__aenter__()
        a.medium.tap, b.medium.tap = ta, tb  # before the start: nothing sent untapped
        await routed(a.session, b)
        await routed(b.session, a)
        t0 = time.time()
        a.start(t0)
        b.start(t0)
        s = core(a, 1)
        for _ in range(30):
            a.run_on(1, lambda c, now: c.send(2))  # type: ignore[attr-defined]
        await wait_for(lambda: len(s.results) == 30, timeout=30)
        await wait_for(lambda: sum(1 for x in tb.rx if x[1] == 3) >= 20, timeout=30)
    finally:
        await a.aclose()
        await b.aclose()
    # Counters and tap calls change together (same code path), so they agree
    # whatever was still in flight when the fleets closed.
    c1 = a.counters()[1]
    assert [x for x in ta.air if x[0] == 1] == ta.air and len(ta.air) == c1.frames_tx
    assert any(att > 0 for *_, att in ta.air)  # retries are attempts on the air
    # b saw 1's frames (as it decided them); a frame is published at its start and
    # tapped by its sender at its end: the one on the air when a closed may be b's only.
    assert len(set(tb.air) - set(ta.air)) <= 1 and tb.air
    lost_total = 0
    for mote in (2, 3):
        c = b.counters()[mote]
        mine = [(rssi, cause) for src, dst, rssi, cause in tb.rx if dst == mote and src == 1]
        got = [r for r, cause in mine if cause in (None, "duplicate")]
        assert len(got) == c.frames_rx > 0 and all(r is not None for r in got)
        assert sum(1 for _, cause in mine if cause == "duplicate") == c.duplicates
        lost = sum(1 for _, cause in mine if cause in ("path_loss", "distance"))
        assert lost <= c.dropped_loss + c.dropped_distance
        lost_total += lost
    assert lost_total > 0


def test_channel_polls_keep_their_cadence_on_a_slowed_clock() -> None:
    """Speed 1 and above: polls every 1 ms after traffic, at most 4 ms apart. A
    slowed clock polls less often (each wake-up of the loop costs CPU), but
    never later than half the wall time a remote frame's envelope has before
    its receptions are decided (shortest airtime, slowed, plus the guard)."""
    from awaremw.radio.model import CC2420
    from awaremw.radio.zenoh_medium import CHANNEL_POLL_MAX_S, CHANNEL_POLL_MIN_S, poll_bounds

    shortest, guard = CC2420.airtime_s(0), 0.01
    # The same cadence at every speed: a slowed clock must not let a remote frame
    # reach the Air after a local assessment that overlaps it.
    for speed in (20.0, 2.0, 1.0, 0.5, 0.1, 0.05, 0.01):
        assert poll_bounds(speed, shortest, guard) == (CHANNEL_POLL_MIN_S, CHANNEL_POLL_MAX_S)
