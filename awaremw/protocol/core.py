"""The sans-IO contract between a mote's protocol core and whatever drives it.

A driver (the asyncio runtime over Zenoh, or the virtual-clock harness) owns
time and the radio; a core owns protocol state. The driver:

* calls :meth:`MoteCore.start` once, then :meth:`receive` for every frame the
  radio delivers (with its RSSI), :meth:`handle_timer` when
  :meth:`next_deadline` has passed, :meth:`link_result` with the outcome of
  every unicast after the link layer's ACK and retries;
* after each of those calls, takes :meth:`drain` (frames to transmit) and
  :meth:`events` (things that happened, for the application, gateway or
  observers) and re-arms its one timer at :meth:`next_deadline`.

``now`` is emulated seconds since the fleet's common start. Cores never read a
clock, never sleep and never use global randomness (they get a seeded
``random.Random``).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

from awaremw.protocol.events import CoreEvent
from awaremw.protocol.frames import BROADCAST

_tx_ids = itertools.count(1)


@dataclass(frozen=True, slots=True)
class Transmission:
    """Bytes to put on the air. ``dest`` is a node id for unicast, or BROADCAST.

    Unicasts are acknowledged by the link layer with bounded retries; the driver
    reports the outcome through :meth:`MoteCore.link_result` with this object.
    """

    frame: bytes
    dest: int = BROADCAST
    tx_id: int = 0

    @property
    def is_unicast(self) -> bool:
        return self.dest != BROADCAST

    @staticmethod
    def broadcast(frame: bytes) -> Transmission:
        return Transmission(frame, BROADCAST, next(_tx_ids))

    @staticmethod
    def unicast(frame: bytes, dest: int) -> Transmission:
        return Transmission(frame, dest, next(_tx_ids))


@runtime_checkable
class MoteCore(Protocol):
    """What the runtime drives. See the module docstring for the call order."""

    node_id: int

    def start(self, now: float) -> None: ...

    def receive(self, frame: bytes, rssi_dbm: float, now: float) -> None: ...

    def handle_timer(self, now: float) -> None: ...

    def next_deadline(self) -> float | None: ...

    def drain(self) -> list[Transmission]: ...

    def link_result(self, tx: Transmission, acked: bool, now: float) -> None: ...

    def events(self) -> list[CoreEvent]: ...


@runtime_checkable
class IdleCheck(Protocol):
    """Optional fast path of a core (the virtual driver uses it after a reception).

    ``idle()`` is True only if, since the driver last took them, the core has
    queued no frame and no event and its deadline has not changed: ``drain()``
    and ``events()`` would return ``[]`` and ``next_deadline()`` the value it
    returned last. A driver may then skip those three calls. It must be cheap
    (a few attribute reads) and may say False whenever in doubt.
    """

    def idle(self) -> bool: ...
