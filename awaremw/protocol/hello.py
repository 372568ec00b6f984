"""HelloMote: a stand-in MoteCore that only discovers its neighbours.

It beacons a :class:`~awaremw.protocol.frames.Hello` every ``period_s``
(with jitter), keeps a neighbour table ``{id: (rssi, last_heard)}`` whose
entries expire, and can ping a neighbour by unicast (the link layer's ACK
tells whether it got there). It exercises the runtime, the medium and the
benchmarks before the real middleware exists, and stays useful as the
simplest core to test drivers with. Garbage from the radio becomes a
:class:`~awaremw.protocol.events.MalformedFrame` event and changes nothing else.
"""

from __future__ import annotations

import random

import msgpack

from awaremw.protocol.core import Transmission
from awaremw.protocol.events import (
    CoreEvent,
    MalformedFrame,
    NeighbourFound,
    NeighbourLost,
    PingResult,
)
from awaremw.protocol.frames import BROADCAST, MAX_NODE_ID, Frame, FrameError, Hello, decode

_packb = msgpack.Packer(use_single_float=True).pack


class _LastDecoded:
    """The last frame decoded, by identity of its bytes: a broadcast reaches
    many motes one after the other as the same bytes object, so each distinct
    frame is decoded once. Frames are immutable, so sharing them is safe."""

    __slots__ = ("data", "frame")

    def __init__(self) -> None:
        self.data: bytes | None = None
        self.frame: Frame | None = None


_last = _LastDecoded()


class HelloMote:
    """Neighbour discovery by periodic Hello beacons. Implements MoteCore."""

    def __init__(
        self,
        node_id: int,
        period_s: float,
        rng: random.Random,
        mtu: int = 100,
        *,
        jitter: float = 0.1,
        expiry_s: float | None = None,
    ) -> None:
        if not 0 <= node_id <= MAX_NODE_ID:
            raise ValueError(f"node id {node_id} outside 0..{MAX_NODE_ID}")
        if period_s <= 0 or not 0 <= jitter < 1:
            raise ValueError("period_s must be > 0 and jitter in [0, 1)")
        self.node_id = node_id
        self.period_s = period_s
        self.rng = rng
        self.mtu = mtu
        self.jitter = jitter
        self.expiry_s = 3.5 * period_s if expiry_s is None else expiry_s
        self.table: dict[int, tuple[float, float]] = {}  # id -> (rssi dBm, last heard)
        self.seq = 0
        self.hellos_rx = 0
        self.pings_rx = 0
        self.ignored = 0  # valid frames of other types
        self._next_beacon: float | None = None
        self._out: list[Transmission] = []
        self._events: list[CoreEvent] = []
        self._pings: dict[int, int] = {}  # tx_id -> dest

    # ------------------------------------------------------------ MoteCore

    def start(self, now: float) -> None:
        # A random phase so that motes booted together do not beacon together.
        self._next_beacon = now + self.rng.uniform(0.0, self.period_s)

    def receive(self, frame: bytes, rssi_dbm: float, now: float) -> None:
        last = _last
        if frame is last.data:
            f = last.frame
        else:
            try:
                f = decode(frame)
            except FrameError as e:
                self._events.append(MalformedFrame(str(e), len(frame)))
                return
            last.data, last.frame = frame, f
        if type(f) is not Hello:
            self.ignored += 1
            return
        if f.dst != BROADCAST:
            if f.dst != self.node_id:
                self.ignored += 1  # the medium filters these; a stray one changes nothing
                return
            self.pings_rx += 1
        else:
            self.hellos_rx += 1
        src = f.src
        if src not in self.table:
            self._events.append(NeighbourFound(src, rssi_dbm))
        self.table[src] = (rssi_dbm, now)

    def handle_timer(self, now: float) -> None:
        nb = self._next_beacon
        if nb is None or now < nb:
            return
        self._expire(now)
        self._send(BROADCAST)
        j = self.jitter
        self._next_beacon = now + self.period_s * (1.0 + self.rng.uniform(-j, j))

    def next_deadline(self) -> float | None:
        return self._next_beacon

    def drain(self) -> list[Transmission]:
        out, self._out = self._out, []
        return out

    def link_result(self, tx: Transmission, acked: bool, now: float) -> None:
        dest = self._pings.pop(tx.tx_id, None)
        if dest is not None:
            self._events.append(PingResult(dest, acked))

    def events(self) -> list[CoreEvent]:
        ev, self._events = self._events, []
        return ev

    # ------------------------------------------------------------ API

    def ping(self, dest: int) -> Transmission:
        """Send a unicast Hello to ``dest``; a PingResult event follows."""
        if not 0 <= dest <= MAX_NODE_ID or dest == self.node_id:
            raise ValueError(f"cannot ping {dest}")
        tx = self._send(dest)
        self._pings[tx.tx_id] = dest
        return tx

    def neighbours(self, now: float | None = None) -> dict[int, tuple[float, float]]:
        """The table; with ``now``, without the entries that have expired by then."""
        if now is None:
            return dict(self.table)
        return {k: v for k, v in self.table.items() if now - v[1] <= self.expiry_s}

    # ------------------------------------------------------------ internals

    def _send(self, dest: int) -> Transmission:
        # Byte-for-byte what encode(Hello(...)) gives (tests check it), without
        # building and validating a frame object: beaconing is the benchmark's
        # hot path and every field here is valid by construction.
        data: bytes = _packb([Hello.TYPE, self.node_id, dest, self.seq])
        tx = Transmission.broadcast(data) if dest == BROADCAST else Transmission.unicast(data, dest)
        self._out.append(tx)
        self.seq = (self.seq + 1) & 0xFFFF
        return tx

    def _expire(self, now: float) -> None:
        stale = [k for k, (_, t) in self.table.items() if now - t > self.expiry_s]
        for k in stale:
            del self.table[k]
            self._events.append(NeighbourLost(k))
