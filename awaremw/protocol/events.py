"""Every event a mote's core reports, in one place: typed frozen dataclasses.

A core hands them out with ``events()`` (protocol/core.py); its driver passes
each, with the driver's own ``MoteUp`` / ``MoteDown`` (below), to the
``on_event(node_id, event, now)`` hooks. :data:`CoreEvent` is their union:
a consumer matches on it and ends with ``case _: assert_never(event)``, so that
mypy names every consumer a new event type has to be decided in.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum
from typing import TypeAlias

from awaremw.protocol.frames import DataRecord, ItemKind, Payload


# Any core (protocol/core.py, mote.py, hello.py)
@dataclass(frozen=True, slots=True)
class MalformedFrame:
    """Event: a frame from the radio could not be decoded (remote fault)."""

    error: str
    size: int


# Dissemination (protocol/dissemination.py)
@dataclass(frozen=True, slots=True)
class ItemAdopted:
    """Event: this mote now holds ``version`` of an item (``source`` None: injected)."""

    kind: ItemKind
    item_id: int
    version: int
    deleted: bool
    source: int | None


@dataclass(frozen=True, slots=True)
class ItemRefused:
    """Event: a newer item heard from the radio could not be stored (remote fault)."""

    kind: ItemKind
    item_id: int
    version: int
    source: int
    reason: str


@dataclass(frozen=True, slots=True)
class InjectSuperseded:
    """Event: an injected version was not newer than the version this mote holds
    (``held``, e.g. a foreign item heard from the radio): the injector, the source
    of truth, may inject again above ``held``."""

    kind: ItemKind
    item_id: int
    version: int
    held: int


# Collection tree (protocol/collection.py)
@dataclass(frozen=True, slots=True)
class Delivered:
    """Event at a root: ``payload`` from ``origin`` arrived after ``thl`` hops at ``t``."""

    origin: int
    payload: Payload
    thl: int
    t: float


@dataclass(frozen=True, slots=True)
class ParentChanged:
    """Event: the mote's parent changed (None: no route); ``cost`` is the new path cost."""

    old: int | None
    new: int | None
    cost: int


@dataclass(frozen=True, slots=True)
class DataDropped:
    """Event: a packet was given up (``reason``: queue full, thl, retries)."""

    origin: int
    seqno: int
    reason: str


# Groups (protocol/groups/)
class LeaveReason(Enum):
    CONDITION = "condition"  # stopped meeting the conditions
    SWITCHED = "switched"  # moved to a heavier group of the same type
    YIELDED = "yielded"  # a leader that heard a heavier leader (now a member of it)
    LEADER_LOST = "leader_lost"  # no beacon for the leader timeout
    HANDOVER = "handover"  # a leader that handed its group over
    DELETED = "deleted"  # the group type was deleted


class ElectionCause(Enum):
    CREATED = "created"  # a qualifying mote found no group nearby
    HANDOVER = "handover"  # took over a leaving leader's group (same id)
    ELECTION = "election"  # the leader was lost; a new group (new id) replaces it
    FAILOVER = "failover"  # the leader died: a member that was its neighbour took over (same id)


@dataclass(frozen=True, slots=True)
class GroupJoined:
    node: int
    group_type: int
    group_id: int
    leader: int
    t: float


@dataclass(frozen=True, slots=True)
class GroupLeft:
    node: int
    group_type: int
    group_id: int
    reason: LeaveReason
    t: float


@dataclass(frozen=True, slots=True)
class LeaderElected:
    """``node`` became the leader of ``group_id`` (membership implied)."""

    node: int
    group_type: int
    group_id: int
    weight: int
    cause: ElectionCause
    t: float


@dataclass(frozen=True, slots=True)
class LeaderYielded:
    node: int
    group_type: int
    group_id: int
    successor: int  # the heavier group's id (equal to group_id on an id clash)
    t: float


@dataclass(frozen=True, slots=True)
class HandoverSent:
    """A leaving leader's Handover was acknowledged and not refused."""

    node: int
    group_type: int
    group_id: int
    to: int
    t: float


@dataclass(frozen=True, slots=True)
class GroupTypeRefused:
    """A definition this mote cannot hold (too many types, reserved type id)."""

    node: int
    group_type: int
    reason: str


# Channels and commands (protocol/channels.py, commands.py)
@dataclass(frozen=True, slots=True)
class RecordProduced:
    """A leader finished an epoch: ``record`` went (or was offered) to the gateway."""

    record: DataRecord
    t: float


@dataclass(frozen=True, slots=True)
class ChannelRefused:
    """A channel definition this mote cannot run (bad id, unknown function, too many)."""

    node: int
    channel: int
    reason: str


@dataclass(frozen=True, slots=True)
class CommandExecuted:
    """Event: the application's handler ran ``name`` from ``slot`` at ``version``."""

    name: str
    slot: int
    version: int


# HelloMote (protocol/hello.py)
@dataclass(frozen=True, slots=True)
class NeighbourFound:
    node: int
    rssi_dbm: float


@dataclass(frozen=True, slots=True)
class NeighbourLost:
    node: int


@dataclass(frozen=True, slots=True)
class PingResult:
    """Outcome of :meth:`HelloMote.ping` after the link layer's ACK and retries."""

    dest: int
    acked: bool


# What an AwareMote reports, what a HelloMote reports, what any core reports.
AwareEvent: TypeAlias = (
    MalformedFrame | ItemAdopted | ItemRefused | InjectSuperseded | Delivered | ParentChanged
    | DataDropped | GroupJoined | GroupLeft | LeaderElected | LeaderYielded | HandoverSent
    | GroupTypeRefused | RecordProduced | ChannelRefused | CommandExecuted
)  # fmt: skip
HelloEvent: TypeAlias = MalformedFrame | NeighbourFound | NeighbourLost | PingResult
CoreEvent: TypeAlias = AwareEvent | HelloEvent


# The driver's own events about a mote, beside its core's: the asyncio driver
# (awaremw.runtime.driver) and the virtual medium (awaremw.radio.virtual_medium)
# emit the same types. Consumers dispatch on the type (``match event: case
# MoteDown(reason=r): ...``), never on class names.
@dataclass(frozen=True, slots=True)
class MoteUp:
    """The mote booted and is on the air."""


@dataclass(frozen=True, slots=True)
class MoteDown:
    """The mote was switched off: ``killed`` (by a user or a scenario),
    ``battery`` (its budget ran out), ``stopped`` (its fleet closed) or
    ``fault`` (a contained core bug)."""

    reason: str


# What a driver reports itself, and everything an on_event hook is given.
RuntimeEvent: TypeAlias = MoteUp | MoteDown
MoteEvent: TypeAlias = CoreEvent | RuntimeEvent
EventHook: TypeAlias = Callable[[int, MoteEvent, float], None]  # (node id, event, now)
