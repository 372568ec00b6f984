"""The asyncio driver of one MoteCore on a radio medium, in emulated real time.

A :class:`MoteRunner` is the thin adapter between a sans-IO core
(:mod:`awaremw.protocol.core`) and the :class:`~awaremw.radio.zenoh_medium.ZenohMedium`:

* it calls ``core.start(now)`` when the mote boots, ``core.handle_timer(now)``
  when the core's deadline passes, ``core.receive`` for every frame the medium
  delivers and ``core.link_result`` for every unicast outcome;
* after every call it drains the core: frames go to the mote's radio, events go
  to the ``on_event(node_id, event, now)`` hook (``MalformedFrame`` events are
  also counted in the mote's counters), and its ONE loop timer is re-armed at
  ``core.next_deadline()`` (converted to loop time by the
  :class:`~awaremw.world.clock.EmulatedClock`), or cancelled;
* it records timer lag -- how late (in wall milliseconds) a timer ran compared
  with the deadline the core asked for (or with the moment it asked, for a
  deadline already past) -- into a shared :class:`LagStats`.

Every call happens on the event loop's thread; nothing here blocks.
"""

from __future__ import annotations

import asyncio
import logging
import math
from array import array
from collections.abc import Callable

from awaremw.protocol.core import MoteCore, Transmission
from awaremw.protocol.events import EventHook, MalformedFrame, MoteDown, MoteEvent, MoteUp
from awaremw.radio.counters import MoteCounters
from awaremw.radio.faults import FaultLog
from awaremw.radio.zenoh_medium import Radio, ZenohMedium
from awaremw.world.clock import EmulatedClock
from awaremw.world.mobility import Mobility

log = logging.getLogger(__name__)

_MAX_FIRINGS_AT_ONE_TIME = 10_000


# Samples kept (8 bytes each: 2 MiB per process). A benchmark's p99 is taken over
# every sample of its measured window: 10,000 AwareMotes over 8 workers take
# about 80,000 per worker in 40 emulated seconds (1 << 16 dropped the first ones).
LAG_WINDOW = 1 << 18


class LagStats:
    """Timer lag samples in wall milliseconds (late > 0), shared by a process's runners.

    Bounded: a ring of the latest :data:`LAG_WINDOW` samples (a fleet of
    1,000 AwareMotes takes about 1,500 a second at speed 1, so the window spans
    minutes), and a count
    of every sample ever added, so a reader can take "the samples since my last
    look" (:meth:`since`) -- exact percentiles over that window.
    """

    __slots__ = ("_buf", "_next", "count", "window")

    def __init__(self, window: int = LAG_WINDOW) -> None:
        if window < 1:
            raise ValueError("window must be >= 1")
        self.window = window
        self._buf = array("d")
        self._next = 0  # where the next sample goes once the ring is full
        self.count = 0  # samples ever added (since the last clear)

    def add(self, lag_ms: float) -> None:
        self.count += 1
        if len(self._buf) < self.window:
            self._buf.append(lag_ms)
            return
        self._buf[self._next] = lag_ms
        self._next = (self._next + 1) % self.window

    def clear(self) -> None:
        self._buf = array("d")
        self._next = 0
        self.count = 0

    @property
    def samples(self) -> list[float]:
        """The samples held, oldest first (at most :attr:`window`)."""
        b = self._buf
        return list(b[self._next :]) + list(b[: self._next])

    def since(self, mark: int) -> list[float]:
        """The samples added after the ``count`` was ``mark`` (the latest ones only,
        if more than the window were added since)."""
        n = min(self.count - mark, len(self._buf))
        return self.samples[len(self._buf) - n :] if n > 0 else []

    def percentile(self, q: float) -> float:
        """The ``q``-th percentile (0..100), nearest rank; NaN without samples."""
        return percentile(self.samples, q)


def percentile(samples: list[float], q: float) -> float:
    if not samples:
        return math.nan
    s = sorted(samples)
    k = min(len(s) - 1, max(0, math.ceil(q / 100.0 * len(s)) - 1))
    return s[k]


class MoteRunner:
    """Drives one core on a medium. Create, then :meth:`start` (or :meth:`start_at`)."""

    __slots__ = (
        "_armed",
        "_boot_t",
        "_due",
        "_fire_count",
        "_fire_t",
        "_handle",
        "_tx_power",
        "alive",
        "battery_mj",
        "clock",
        "core",
        "lag",
        "loop",
        "medium",
        "mobility",
        "node_id",
        "on_event",
        "radio",
        "stopped",
    )

    def __init__(
        self,
        core: MoteCore,
        medium: ZenohMedium,
        mobility: Mobility,
        *,
        tx_power_dbm: float | None = None,
        battery_mj: float | None = None,
        on_event: EventHook | None = None,
        lag: LagStats | None = None,
    ) -> None:
        self.core = core
        self.node_id: int = core.node_id
        self.medium = medium
        self.clock: EmulatedClock = medium.clock
        self.loop = medium.loop
        self.mobility = mobility
        self._tx_power = tx_power_dbm
        self.battery_mj = battery_mj
        self.on_event = on_event
        self.lag = lag
        self.radio: Radio | None = None
        self.alive = False
        self.stopped = False  # switched off for good (killed, battery, stopped)
        self._armed: float | None = None
        self._due = 0.0  # emulated time the armed timer could run at first (lag counts from it)
        self._handle: asyncio.TimerHandle | asyncio.Handle | None = None
        self._fire_t = -math.inf
        self._fire_count = 0
        self._boot_t: float | None = None  # emulated boot time while waiting to boot

    # ------------------------------------------------------------------ lifecycle

    def attach(self) -> None:
        """Put the mote's radio on the medium without booting the core yet (a
        launcher attaches every mote, primes the medium's caches, then boots)."""
        if self.radio is None:
            self.radio = self.medium.attach(
                self, self.mobility, tx_power_dbm=self._tx_power, battery_mj=self.battery_mj
            )

    def start(self) -> None:
        """Boot now: on the air, ``core.start(now)``."""
        if self.alive:
            raise RuntimeError(f"mote {self.node_id} already started")
        if self.stopped:
            raise RuntimeError(f"mote {self.node_id}: a runner is single-use; make a new one")
        self.attach()
        self.alive = True
        now = self.clock.now()
        self._emit(MoteUp(), now)
        try:
            self.core.start(now)
        except Exception as e:
            self._fault("start", e)
        self._after_guarded(now)

    def start_at(self, t: float) -> None:
        """Boot at emulated time ``t`` (now if it has passed)."""
        now = self.clock.now()
        if t <= now:
            self.start()
            return
        self._boot_t = t
        self._handle = self.loop.call_at(self.clock.to_monotonic(t), self._boot)

    def _boot(self) -> None:
        self._handle = None
        self.start()

    def stop(self, reason: str = "killed") -> None:
        """Switch the mote off (idempotent): timer cancelled, radio detached.
        A mote waiting to boot never boots."""
        self.stopped = True
        if self._handle is not None:
            self._handle.cancel()
            self._handle = None
        self._armed = None
        if self.radio is not None and self.radio.alive:
            self.medium.detach(self.node_id)  # attached, maybe not booted yet
        if not self.alive:
            return
        self.alive = False
        self._emit(MoteDown(reason), self.clock.now())

    @property
    def counters(self) -> MoteCounters | None:
        return None if self.radio is None else self.radio.counters

    def run_on(self, fn: Callable[[MoteCore, float], object]) -> None:
        """Run ``fn(core, now)`` now (on the loop's thread), then drain and re-arm.

        The gateway uses it to inject definitions into its mote's core.
        """
        if not self.alive:
            raise RuntimeError(f"mote {self.node_id} is not running")
        now = self.clock.now()
        fn(self.core, now)
        self._after_guarded(now)

    def rearm(self) -> None:
        """Arm the timer again after the clock was re-anchored (its loop instant
        was computed on the old origin); a mote waiting to boot waits for its boot
        time on the new origin."""
        if self.stopped:
            return
        if not self.alive:
            if self._handle is not None and self._boot_t is not None:
                self._handle.cancel()
                self._handle = None
                self.start_at(self._boot_t)
            return
        if self._handle is not None:
            self._handle.cancel()
            self._handle = None
        self._armed = None
        self._after_guarded(self.clock.now())

    # ------------------------------------------------------------------ last guards

    @property
    def faults(self) -> FaultLog:
        """Where contained faults are counted (the medium's, one per process)."""
        return self.medium.faults

    def _fault(self, where: str, e: Exception) -> None:
        """An exception escaped the core or a hook: our bug, contained (counted and
        logged, rate-limited) so that one mote's bug does not stop the fleet."""
        self.faults.count(f"{where}: {type(e).__name__}", f"mote {self.node_id}: {e}", e)

    def _after_guarded(self, now: float) -> None:
        try:
            self._after(now)
        except Exception as e:
            self._fault("after", e)

    # ------------------------------------------------------------------ RadioSink

    def radio_receive(self, frame: bytes, rssi_dbm: float, now: float) -> None:
        if not self.alive:
            return
        try:
            self.core.receive(frame, rssi_dbm, now)
        except Exception as e:
            self._fault("receive", e)
        self._after_guarded(now)

    def radio_link_result(self, tx: Transmission, acked: bool, now: float) -> None:
        if not self.alive:
            return
        try:
            self.core.link_result(tx, acked, now)
        except Exception as e:
            self._fault("link_result", e)
        self._after_guarded(now)

    def radio_down(self, reason: str, now: float) -> None:
        """The medium switched the mote off (battery spent)."""
        if not self.alive:
            return
        self.alive = False
        self.stopped = True
        if self._handle is not None:
            self._handle.cancel()
            self._handle = None
        self._armed = None
        self._emit(MoteDown(reason), now)

    # ------------------------------------------------------------------ the one timer

    def _after(self, now: float) -> None:
        """Collect what the core wants after any call into it; re-arm the timer."""
        core = self.core
        txs = core.drain()
        if txs and self.radio is not None:
            self.radio.send(txs)
        evs = core.events()
        if evs:
            for e in evs:
                self._emit(e, now)
        if not self.alive:
            return
        dl = core.next_deadline()
        if dl == self._armed and self._handle is not None:
            return
        if self._handle is not None:
            self._handle.cancel()
            self._handle = None
        self._armed = dl
        if dl is not None:
            # A deadline the core set in the past (an overdue epoch, a late link
            # result) can run no earlier than now: the loop is late only after that.
            self._due = max(dl, self.clock.now())
            self._handle = self.loop.call_at(self.clock.to_monotonic(dl), self._fire)

    def _fire(self) -> None:
        self._handle = None
        dl = self._armed
        self._armed = None
        if not self.alive or dl is None:
            return
        clock = self.clock
        now = clock.now()
        if self.lag is not None:
            self.lag.add((now - self._due) / clock.speed * 1000.0)
        # The loop may wake a hair early (clock resolution): never hand the core a
        # "now" before the deadline it asked for.
        if now < dl:
            now = dl
        if now == self._fire_t:
            self._fire_count += 1
            if self._fire_count > _MAX_FIRINGS_AT_ONE_TIME:
                # A core bug that would spin the loop: contained, the mote stops.
                self._fault("handle_timer", RuntimeError(f"core keeps its deadline at {now}"))
                self.stop("fault")
                return
        else:
            self._fire_t, self._fire_count = now, 0
        try:
            self.core.handle_timer(now)
        except Exception as e:
            self._fault("handle_timer", e)
            try:
                stuck = (nd := self.core.next_deadline()) is not None and nd <= dl
            except Exception:
                stuck = True
            if stuck:  # it would fire again at once, forever: this mote stops
                self.stop("fault")
                return
        self._after_guarded(now)

    def _emit(self, event: MoteEvent, now: float) -> None:
        if type(event) is MalformedFrame and self.radio is not None:
            self.radio.counters.malformed += 1
        hook = self.on_event
        if hook is not None:
            try:
                hook(self.node_id, event, now)
            except Exception as e:  # a hook's bug (e.g. the gateway's) must not stop the mote
                self._fault(f"event hook {type(event).__name__}", e)
