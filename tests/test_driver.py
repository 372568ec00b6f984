"""The emulated clock and the asyncio MoteRunner (one timer per mote, drain after
every call, events, lag), on a real Zenoh session (alone: no endpoints)."""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator, Callable

import pytest

from awaremw.protocol.core import MoteCore, Transmission
from awaremw.protocol.events import MalformedFrame, MoteDown, MoteUp
from awaremw.protocol.frames import BROADCAST, Hello, encode
from awaremw.radio.model import CC2420, RadioModel
from awaremw.radio.zenoh_medium import ZenohMedium
from awaremw.runtime.driver import LagStats, MoteRunner, percentile
from awaremw.runtime.zenoh_session import close_quietly, open_session
from awaremw.world.clock import EmulatedClock
from awaremw.world.mobility import Static

# --------------------------------------------------------------------------- clock


class FakeMono:
    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


def test_clock_scales_wall_time_by_the_speed_factor() -> None:
    mono = FakeMono()
    c = EmulatedClock(10.0, time.time(), monotonic=mono)
    t0 = c.now()
    mono.t += 1.5
    assert c.now() - t0 == pytest.approx(15.0)
    assert c.to_monotonic(t0 + 10.0) - c.to_monotonic(t0) == pytest.approx(1.0)
    assert c.wall_seconds(20.0) == pytest.approx(2.0)


def test_clocks_with_a_shared_start_agree_and_restart_reanchors() -> None:
    start = time.time() - 3.0  # the fleet started 3 s ago
    a = EmulatedClock(2.0, start)
    b = EmulatedClock(2.0, start)
    assert a.now() == pytest.approx(6.0, abs=0.05)
    assert abs(a.now() - b.now()) < 0.01
    a.restart(time.time() + 1.0)  # time 0 is one second from now
    assert a.now() == pytest.approx(-2.0, abs=0.05)
    with pytest.raises(ValueError):
        EmulatedClock(0.0)


# --------------------------------------------------------------------------- cores


class Ticker:
    """Wakes at 1, 2, 3, ... (emulated s); records when (emulated, loop time)."""

    def __init__(self, node_id: int, on_tick: Callable[[float], None] | None = None) -> None:
        self.node_id = node_id
        self.ticks: list[float] = []
        self.next: float | None = None
        self.received: list[tuple[bytes, float]] = []
        self.out: list[Transmission] = []
        self.evs: list[object] = []
        self.on_tick = on_tick

    def start(self, now: float) -> None:
        self.next = float(int(now) + 1)
        self.evs.append(("started", now))

    def receive(self, frame: bytes, rssi_dbm: float, now: float) -> None:
        self.received.append((frame, rssi_dbm))
        if frame == b"\xc1":
            self.evs.append(MalformedFrame("bad", 1))

    def handle_timer(self, now: float) -> None:
        assert self.next is not None and now >= self.next
        self.ticks.append(now)
        if self.on_tick is not None:
            self.on_tick(now)
        self.next += 1.0

    def next_deadline(self) -> float | None:
        return self.next

    def drain(self) -> list[Transmission]:
        out, self.out = self.out, []
        return out

    def link_result(self, tx: Transmission, acked: bool, now: float) -> None:
        self.evs.append(("link", acked))

    def events(self) -> list[object]:
        ev, self.evs = self.evs, []
        return ev


@pytest.fixture
async def medium_factory() -> AsyncIterator[Callable[[float], ZenohMedium]]:
    session = open_session()
    made: list[ZenohMedium] = []

    def make(speed: float) -> ZenohMedium:
        m = ZenohMedium(session, RadioModel(CC2420, 3), EmulatedClock(speed))
        m.open()
        made.append(m)
        return m

    try:
        yield make
    finally:
        for m in made:
            m.close()
        close_quietly(session)


async def wait_for(pred: Callable[[], bool], timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > deadline:
            raise AssertionError("condition not reached in time")
        await asyncio.sleep(0.005)


# --------------------------------------------------------------------------- timers


async def test_speed_factor_10_runs_timers_10x_faster(
    medium_factory: Callable[[float], ZenohMedium],
) -> None:
    m = medium_factory(10.0)
    walls: list[float] = []
    core = Ticker(1, lambda now: walls.append(time.monotonic()))
    lag = LagStats()
    r = MoteRunner(core, m, Static(0.0, 0.0), lag=lag)
    r.start()
    await wait_for(lambda: len(core.ticks) >= 6)
    r.stop()
    # Deadlines 1, 2, 3, ... emulated seconds came 0.1 s of wall time apart.
    span_wall = walls[5] - walls[0]
    span_emulated = core.ticks[5] - core.ticks[0]
    assert span_emulated == pytest.approx(5.0, abs=0.1)
    assert span_emulated / span_wall == pytest.approx(10.0, rel=0.15)
    # Each timer ran at (or just after) the deadline the core asked for.
    for k, t in enumerate(core.ticks):
        assert t - (k + 1) < 0.5  # emulated s, i.e. under 50 ms of wall time late
    assert len(lag.samples) == len(core.ticks)
    # Each lag sample is how late (wall ms) the core's "now" came after its deadline.
    for k, ms in enumerate(lag.samples):
        assert max(ms, 0.0) == pytest.approx((core.ticks[k] - (k + 1)) / 10.0 * 1000.0, abs=1e-6)
    assert percentile(lag.samples, 50) < 50.0


async def test_a_deadline_already_past_counts_lag_from_when_it_was_asked(
    medium_factory: Callable[[float], ZenohMedium],
) -> None:
    m = medium_factory(1.0)
    core = Ticker(1)
    lag = LagStats()
    r = MoteRunner(core, m, Static(0.0, 0.0), lag=lag)
    r.start()

    def overdue(c: MoteCore, now: float) -> None:
        assert isinstance(c, Ticker)
        c.next = now - 3.0  # e.g. an epoch boundary that passed before the mote heard of it

    r.run_on(overdue)
    await wait_for(lambda: len(core.ticks) >= 3)  # now - 3, now - 2, now - 1: at once
    r.stop()
    assert core.ticks[2] - core.ticks[0] < 0.5  # emulated s: not a second apart each
    # The loop ran them as soon as it could: no 3,000 ms of "lag" the loop never had.
    assert max(lag.samples[:3]) < 500.0, lag.samples


async def test_one_timer_per_mote_rearmed_after_every_call(
    medium_factory: Callable[[float], ZenohMedium],
) -> None:
    m = medium_factory(20.0)
    core = Ticker(1)
    events: list[tuple[int, object, float]] = []
    r = MoteRunner(core, m, Static(0.0, 0.0), on_event=lambda n, e, t: events.append((n, e, t)))
    r.start()
    assert isinstance(events[0][1], MoteUp)
    assert events[1][1][0] == "started"  # type: ignore[index]
    # run_on: the function runs inside the loop with the current time, then the
    # runner drains the core (a frame goes on the air) and re-arms the timer.
    seen: list[float] = []

    def push(c: object, now: float) -> None:
        assert isinstance(c, Ticker)
        seen.append(now)
        c.next = now + 100.0  # postpone: the old timer must not fire
        c.out.append(Transmission.broadcast(encode(Hello(1, BROADCAST, 0), 100)))

    r.run_on(push)
    assert seen and r._armed == pytest.approx(seen[0] + 100.0)
    await wait_for(lambda: m.counters[1].frames_tx == 1)
    await asyncio.sleep(0.2)  # 4 emulated seconds: a stale timer would have ticked
    assert core.ticks == []
    r.stop()
    assert isinstance(events[-1][1], MoteDown) and events[-1][1].reason == "killed"
    with pytest.raises(RuntimeError):
        r.run_on(push)


async def test_malformed_frame_events_are_counted_and_forwarded(
    medium_factory: Callable[[float], ZenohMedium],
) -> None:
    m = medium_factory(1.0)
    core = Ticker(1)
    events: list[object] = []
    r = MoteRunner(core, m, Static(0.0, 0.0), on_event=lambda n, e, t: events.append(e))
    r.start()
    r.radio_receive(b"\xc1", -80.0, 0.0)
    assert r.counters is not None and r.counters.malformed == 1
    assert any(isinstance(e, MalformedFrame) for e in events)
    r.stop()


async def test_start_at_boots_later_and_stop_before_boot_cancels(
    medium_factory: Callable[[float], ZenohMedium],
) -> None:
    m = medium_factory(20.0)
    late, never = Ticker(1), Ticker(2)
    r1 = MoteRunner(late, m, Static(0.0, 0.0))
    r2 = MoteRunner(never, m, Static(5.0, 0.0))
    t0 = m.clock.now()
    r1.start_at(t0 + 2.0)
    r2.start_at(t0 + 2.0)
    r2.stop()
    assert not r1.alive and 1 not in m.radios
    await wait_for(lambda: r1.alive)
    assert m.clock.now() >= t0 + 2.0
    await asyncio.sleep(0.2)
    assert not r2.alive and 2 not in m.radios and never.ticks == []
    r1.stop()
    with pytest.raises(RuntimeError):
        r1.start()  # runners are single-use
