"""Channel access and collisions over Zenoh (issue 13, item 5), against the virtual medium.

The Zenoh medium drives the same MacSender and Air (radio/mac.py, through
radio/linklayer.py) as the virtual medium: frames are published when they go
on the air, with their start time, and decided at their end + a wall-time
guard. Real Zenoh sessions on loopback, multicast scouting off. The clocks run
slower than real time (speed 0.05) so that the loop's own lag (a millisecond
or so of wall time) is a few tens of microseconds of emulated time, well
under the MAC's backoff slot (the MAC's times do not depend on the lag: every
timer carries the emulated time it stands for; the lag only decides whether a
frame is known in time).
"""

from __future__ import annotations

import asyncio
import dataclasses
import random
import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest
import zenoh

from awaremw.protocol.core import Transmission
from awaremw.protocol.frames import BROADCAST
from awaremw.radio.counters import MoteCounters
from awaremw.radio.envelope import Kind, encode_envelope
from awaremw.radio.model import CC2420, RadioModel, cell_of
from awaremw.radio.virtual_medium import VirtualNetwork
from awaremw.radio.zenoh_medium import MacSettings, Radio, ZenohMedium
from awaremw.runtime.router import EmbeddedRouter
from awaremw.runtime.zenoh_session import (
    SessionSettings,
    close_quietly,
    free_tcp_endpoint,
    open_session,
)
from awaremw.world.clock import EmulatedClock
from awaremw.world.mobility import Static

pytestmark = pytest.mark.zenoh

SPEED = 0.05
FLAT = dataclasses.replace(CC2420, shadowing_sigma_db=0.0, fading_sigma_db=0.0)
Reception = tuple[int, int, int]  # (src, dst, frame number k)
Script = list[tuple[float, int, int, int]]  # (emulated time, src, dest, frame number k)
FIELDS = (
    "frames_tx", "frames_rx", "collisions", "dropped_loss", "dropped_distance", "cca_busy",
    "mac_drops", "retries", "unicast_ok", "unicast_failed", "acks_tx", "acks_rx", "duplicates",
)  # fmt: skip


def frame_of(src: int, k: int, n: int = 60) -> bytes:
    return bytes([src, k]) + bytes(n - 2)


class Sink:
    """A silent mote on either medium: records (src, dst, k) of what it receives."""

    def __init__(self, node_id: int, got: set[Reception]) -> None:
        self.node_id = node_id
        self.got = got
        self.out: list[Transmission] = []
        self.results: list[tuple[int, bool]] = []

    # MoteCore side (virtual medium)
    def start(self, now: float) -> None:
        pass

    def receive(self, frame: bytes, rssi_dbm: float, now: float) -> None:
        self.got.add((frame[0], self.node_id, frame[1]))

    def handle_timer(self, now: float) -> None:
        pass

    def next_deadline(self) -> float | None:
        return None

    def drain(self) -> list[Transmission]:
        out, self.out = self.out, []
        return out

    def link_result(self, tx: Transmission, acked: bool, now: float) -> None:
        self.results.append((tx.frame[1], acked))

    def events(self) -> list[object]:
        return []

    # RadioSink side (Zenoh medium)
    def radio_receive(self, frame: bytes, rssi_dbm: float, now: float) -> None:
        self.receive(frame, rssi_dbm, now)

    def radio_link_result(self, tx: Transmission, acked: bool, now: float) -> None:
        self.link_result(tx, acked, now)

    def radio_down(self, reason: str, now: float) -> None:
        pass


def tx_of(src: int, dest: int, k: int) -> Transmission:
    f = frame_of(src, k)
    return Transmission.broadcast(f) if dest == BROADCAST else Transmission.unicast(f, dest)


def counted(counters: dict[int, MoteCounters]) -> dict[int, tuple[int, ...]]:
    return {i: tuple(getattr(c, k) for k in FIELDS) for i, c in sorted(counters.items())}


def run_virtual(
    model: RadioModel, pos: dict[int, tuple[float, float]], script: Script, mac: str
) -> tuple[set[Reception], dict[int, tuple[int, ...]], dict[int, list[tuple[int, bool]]]]:
    net = VirtualNetwork(model, model.seed, mac=mac, collisions="sinr")
    got: set[Reception] = set()
    sinks = {i: Sink(i, got) for i in pos}
    for i, (x, y) in pos.items():
        net.add(sinks[i], Static(x, y))  # type: ignore[arg-type]

    def send(src: int, dest: int, k: int) -> Callable[[], None]:
        return lambda: net.call(src, lambda: sinks[src].out.append(tx_of(src, dest, k)))

    for t, src, dest, k in script:
        net.call_at(t, send(src, dest, k))
    net.run_until(max(t for t, *_ in script) + 1.0)
    return got, counted(net.counters), {i: s.results for i, s in sinks.items()}


async def wait_for(pred: Callable[[], bool], timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > deadline:
            raise AssertionError("condition not reached in time")
        await asyncio.sleep(0.01)


class Media:
    """Zenoh media (one per session: a "process" each) sharing one emulated clock."""

    def __init__(self, model: RadioModel, sessions: list[zenoh.Session], prefix: str,
                 **kw: Any) -> None:  # fmt: skip
        self.clock = EmulatedClock(SPEED)
        self.media = [ZenohMedium(s, model, self.clock, prefix=prefix, **kw) for s in sessions]
        access: MacSettings = kw.get("access", MacSettings())
        self.guard = access.guard_s * SPEED  # emulated seconds
        self.got: set[Reception] = set()
        self.sinks: dict[int, Sink] = {}
        self.radios: dict[int, Radio] = {}

    def attach(self, m: int, pos: dict[int, tuple[float, float]]) -> None:
        medium = self.media[m]
        medium.open()
        for i, (x, y) in pos.items():
            self.sinks[i] = Sink(i, self.got)
            self.radios[i] = medium.attach(self.sinks[i], Static(x, y))

    def play(self, script: Script) -> float:
        """Anchor emulated 0 a little ahead and schedule the script; returns its end."""
        self.clock.restart(time.time() + 0.1)
        loop = asyncio.get_running_loop()
        for t, src, dest, k in script:
            r = self.radios[src]
            loop.call_at(self.clock.to_monotonic(t), r.send, [tx_of(src, dest, k)], t)
        return max(t for t, *_ in script)

    async def settle(self, t_end: float) -> None:
        """Wait until the script is played and every radio is idle, then for the
        last decisions: every medium has decided every frame it holds, and twice
        the guard (2 ms emulated at least) has passed since the last frame ended
        (by then every envelope reached every process, or it is late and decided
        at once). Waiting one guard exactly raced the last decision on a loaded
        machine: a collision across processes found nothing received (CI,
        compiled build)."""
        rs = self.radios.values()
        await wait_for(lambda: self.clock.now() > t_end and not any(r.busy or r.queue for r in rs))
        t = self.clock.now() + max(0.002, 2 * self.guard)
        await wait_for(
            lambda: self.clock.now() > t and not any(m.pending_decisions for m in self.media)
        )

    def counters(self) -> dict[int, tuple[int, ...]]:
        out: dict[int, MoteCounters] = {}
        for m in self.media:
            out.update({i: c for i, c in m.counters.items() if i in m.radios})
        return counted(out)

    def close(self) -> None:
        for m in self.media:
            m.close()


Outcome = tuple[set[Reception], dict[int, tuple[int, ...]], dict[int, list[tuple[int, bool]]]]


async def run_zenoh(
    router: str, model: RadioModel, pos: dict[int, tuple[float, float]], script: Script, mac: str,
    prefix: str,
) -> Outcome:  # fmt: skip
    """:func:`run_virtual`'s script on a Zenoh medium in one session (one process).

    Guard 5 ms wall = 0.25 ms emulated: shorter than the ACK exchange (0.54 ms),
    so an acknowledged sender resumes when the virtual one does (with a longer
    guard it resumes at end + guard: same rules, later times)."""
    session = open_session(SessionSettings("peer", (router,)))
    z = Media(model, [session], prefix, access=MacSettings(mac, "sinr", 0.005))
    try:
        z.attach(0, pos)
        t_end = z.play(script)
        await z.settle(t_end)
        counts = z.counters()  # (late decisions cannot matter: no frame comes from elsewhere)
    finally:
        z.close()
        close_quietly(session)
    return z.got, counts, {i: s.results for i, s in z.sinks.items()}


@pytest.fixture(scope="module")
def router() -> Iterator[str]:
    ep = free_tcp_endpoint()
    with EmbeddedRouter([ep]):
        yield ep


def scripted(pos: dict[int, tuple[float, float]], n: int, seed: int) -> Script:
    """``n`` frames at random times in 40 ms from random motes; one in four a unicast."""
    rnd = random.Random(seed)
    ids = sorted(pos)
    out: Script = []
    for k in range(n):
        src = rnd.choice(ids)
        dest = rnd.choice([i for i in ids if i != src]) if k % 4 == 3 else BROADCAST
        out.append((0.002 + rnd.random() * 0.04, src, dest, k))
    return sorted(out)


@pytest.mark.parametrize("mac", ["csma", "aloha"])
async def test_same_seed_same_collisions_virtual_and_zenoh_in_one_process(
    router: str, mac: str
) -> None:
    # Eight motes in two clusters 30 m apart (CC2420 with shadowing and fading):
    # neighbours, hidden terminals, captures and plain collisions in one script.
    model = RadioModel(CC2420, 11)
    rnd = random.Random(5)
    pos = {i: (rnd.uniform(0, 15) + 30 * (i % 2), rnd.uniform(0, 15)) for i in range(8)}
    script = scripted(pos, 40, 3)
    v_got, v_counts, v_results = run_virtual(model, pos, script, mac)
    z_got, z_counts, z_results = await run_zenoh(router, model, pos, script, mac, f"t1{mac}")
    # Not a trivial script: frames collided, captured or not, and CSMA deferred.
    total = {f: sum(c[FIELDS.index(f)] for c in v_counts.values()) for f in FIELDS}
    assert total["collisions"] >= 5 and total["frames_rx"] >= 20
    if mac == "csma":
        assert total["cca_busy"] >= 3
    assert z_got == v_got
    assert z_counts == v_counts
    assert z_results == v_results


async def routed(session: zenoh.Session, medium: ZenohMedium, cell: tuple[int, int]) -> None:
    """Wait until ``session`` sees ``medium``'s subscription of ``cell``'s column."""
    pub = session.declare_publisher(
        medium.key_for(cell, 9999), allowed_destination=zenoh.Locality.REMOTE
    )
    try:
        await wait_for(lambda: bool(getattr(pub.matching_status, "matching", False)))
    finally:
        close_quietly(pub)


async def two_processes(
    router: str, prefix: str, pos1: dict[int, tuple[float, float]],
    pos2: dict[int, tuple[float, float]], script: Script, mac: str,
) -> tuple[Media, list[MoteCounters]]:  # fmt: skip
    """Motes ``pos1`` on one session's medium, ``pos2`` on another's; play ``script``."""
    s1 = open_session(SessionSettings("peer", (router,)))
    s2 = open_session(SessionSettings("peer", (router,)))
    # A 40 ms wall guard (2 ms emulated): a loaded test machine's loop lag must not
    # make an envelope late (which would be counted, and decided without waiting).
    z = Media(RadioModel(FLAT, 4), [s1, s2], prefix, access=MacSettings(mac, "sinr", 0.04))
    try:
        z.attach(0, pos1)
        z.attach(1, pos2)
        cell = cell_of(0.0, 0.0, z.media[0].cell_size)
        await routed(s1, z.media[1], cell)
        await routed(s2, z.media[0], cell)
        t_end = z.play(script)
        await z.settle(t_end)
        return z, [z.media[m].counters[i] for m in (0, 1) for i in sorted(z.media[m].radios)]
    finally:
        z.close()
        close_quietly(s1)
        close_quietly(s2)


async def test_a_collision_across_processes_is_decided_the_same_at_both_receivers(
    router: str,
) -> None:
    # A (1) in process 1, B (2) in process 2, at equal distance from R1 (11, in
    # process 1) and R2 (12, in process 2). ALOHA: both start at the same time.
    script: Script = [(0.01, 1, BROADCAST, 0), (0.01, 2, BROADCAST, 1)]
    pos1 = {1: (0.0, 0.0), 11: (5.0, 3.0)}
    pos2 = {2: (10.0, 0.0), 12: (5.0, -3.0)}
    z, _ = await two_processes(router, "t2a", pos1, pos2, script, "aloha")
    k = {i: z.media[0 if i in pos1 else 1].counters[i] for i in (1, 2, 11, 12)}
    assert z.got == set()
    assert k[11].collisions == k[12].collisions == 2  # both frames lost at both
    assert k[1].collisions == k[2].collisions == 1  # each sender deaf to the other
    assert all(m.stats.late == 0 for m in z.media)
    # B 9 dB weaker at both receivers (A 3.2 m from them, B 6.4 m, path loss
    # exponent 3): A's frame is captured at both, B's lost at both.
    pos1 = {1: (0.0, 0.0), 11: (3.0, 1.0)}
    pos2 = {2: (9.3, 0.0), 12: (3.0, -1.0)}
    z, _ = await two_processes(router, "t2b", pos1, pos2, script, "aloha")
    k = {i: z.media[0 if i in pos1 else 1].counters[i] for i in (11, 12)}
    assert z.got == {(1, 11, 0), (1, 12, 0)}
    assert k[11].collisions == k[12].collisions == 1
    # CSMA across processes: C (3, process 2) is due 0.5 ms into A's frame; its
    # assessment sees A's envelope, it defers, and both receivers get both frames.
    script = [(0.01, 1, BROADCAST, 0), (0.0105, 3, BROADCAST, 1)]
    pos1 = {1: (0.0, 0.0), 11: (5.0, 3.0)}
    pos2 = {3: (10.0, 0.0), 12: (5.0, -3.0)}
    z, _ = await two_processes(router, "t2c", pos1, pos2, script, "csma")
    assert z.media[1].counters[3].cca_busy >= 1
    assert z.got == {(1, 11, 0), (1, 12, 0), (1, 3, 0), (3, 11, 1), (3, 12, 1), (3, 1, 1)}
    assert all(m.counters[i].collisions == 0 for m in z.media for i in m.radios)


async def test_a_late_envelope_is_counted_and_decided_at_once_an_early_one_refused(
    router: str,
) -> None:
    s1 = open_session(SessionSettings("peer", (router,)))
    s2 = open_session(SessionSettings("peer", (router,)))
    clock = EmulatedClock(1.0)
    medium = ZenohMedium(s1, RadioModel(FLAT, 4), clock, prefix="t3")
    try:
        medium.open()
        got: set[Reception] = set()
        medium.attach(Sink(11, got), Static(3.0, 0.0))
        cell = cell_of(0.0, 0.0, medium.cell_size)
        await routed(s2, medium, cell)
        key = medium.key_for(cell, 5)
        now = clock.now()
        late = encode_envelope(Kind.FRAME, 5, 0.0, 0.0, 0.0, 0, 0, now - 1.0, BROADCAST,
                               frame_of(5, 7))  # fmt: skip
        early = encode_envelope(Kind.FRAME, 5, 0.0, 0.0, 0.0, 1, 0, now + 100.0, BROADCAST,
                                frame_of(5, 8))  # fmt: skip
        s2.put(key, late)
        s2.put(key, early)
        await wait_for(lambda: medium.stats.envelopes_rx == 2 and bool(got))
        assert got == {(5, 11, 7)}  # the late frame delivered (nothing overlapped it)
        assert medium.stats.late == 1 and medium.stats.early == 1
        assert medium.rejected.get("early") == 1
        assert len(medium._air.frames) <= 1  # the early frame was never put on the air
        with pytest.raises(ValueError, match="guard_s"):  # a remote ACK must beat the wait
            ZenohMedium(s1, medium.model, clock, prefix="t3b", ack_wait_floor_s=0.01,
                        access=MacSettings(guard_s=0.02))  # fmt: skip
    finally:
        medium.close()
        close_quietly(s2)
        close_quietly(s1)


async def test_a_fleet_takes_mac_and_collisions_from_its_deployment(router: str) -> None:
    from awaremw.runtime.deployment import parse_deployment
    from awaremw.runtime.fleet import Fleet, FleetSettings

    def dep(**keys: str) -> Any:
        nodes = [{"id": 1, "kind": "x", "position": [0.0, 0.0]}]
        return parse_deployment(
            {"name": "m", "seed": 1, "area": [10.0, 10.0], "nodes": nodes, **keys}
        )

    def silent(spec: Any, d: Any) -> Sink:
        return Sink(spec.id, set())

    for keys, kind, coll in (({}, "csma", "sinr"), ({"mac": "aloha", "collisions": "none"},
                             "aloha", "none")):  # fmt: skip
        settings = FleetSettings(connect=(router,), control=False)
        async with Fleet(dep(**keys), silent, settings) as f:  # type: ignore[arg-type]
            assert f.medium.mac_params.kind == kind and f.medium.collisions == coll
