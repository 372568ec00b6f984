"""The values of group management: roles, the public records, the timers' names,
the constants and the pure rules (orders, conditions) that every part reads.

The bottom of the package: it imports no other module of it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum, StrEnum
from typing import NamedTuple

from awaremw.protocol.frames import Condition, Op

# A parked mote checks once every this many check periods even if nothing can
# change (see Conditions.quiet_until): a bound on the work of finding its schedule.
PARK_PERIODS = 256
MAX_GROUP_ID = 0xFFFE
MAX_WEIGHT = 0xFFFFFFFF
MAX_HOPS = 0xFF
ELECTION_BACKOFF_FACTOR = 3.0  # creation backoff after a lost leader, x create_backoff
TENTATIVE_CREATE_SPREAD = 0.5  # spontaneous creation backoff with tentative ids, x create_backoff
TENTATIVE_BEACONS = 2  # a would-be group announces its id this many times, evenly spread
MAX_COPIES = 8  # copies of one beacon seq remembered for the forward suppression
# Group links by RSSI under group_link_rssi_floor: down to BAND_2_DB under it is
# band 1, down to BAND_3_DB band 2, weaker band 3 (the floor and up: band 0).
# Counted per partial attempt on the CC2420 preset: 0.01-0.15 retransmissions
# per partial in bands 0-1, about 0.3 in band 2, 1 to 3 in band 3.
BAND_2_DB = 2.0
BAND_3_DB = 3.5


class Role(Enum):
    IDLE = "idle"
    WAITING = "waiting"
    MEMBER = "member"
    LEADER = "leader"
    HANDING_OVER = "handing_over"


class Tick(StrEnum):
    """The component's timers: ``CHECK`` alone, every other one per group type as
    ``(tick, group_type)``. A member equals (and hashes as) its string, so a timer
    set by name reads the same either way."""

    CHECK = "check"  # the membership checks (Conditions)
    BEACON = "beacon"  # the leader's next beacon (Pace)
    FWD = "fwd"  # a member's forward of the current seq (GroupTree)
    REBUT = "rebut"  # our current beacon again, to a lighter contender (GroupTree)
    LOST = "lost"  # no new seq from the leader for a timeout (Liveness)
    CLAIM = "claim"  # take the group of a lost leader over (Liveness)
    CREATE = "create"  # a waiting mote's backoff before creating (Election)
    CONFIRM = "confirm"  # a would-be group's id taken, or announced again (Election)
    ANNOUNCE = "announce"  # a would-be group's id announced again (Election)
    RELAY = "relay"  # the higher of two would-be groups relayed (Election)
    HANDOVER = "handover"  # the handover's grace time for a refusal (Handovers)


@dataclass(frozen=True, slots=True)
class Membership:
    """This mote's view of its group of one type."""

    group_type: int
    group_id: int
    leader: int
    is_leader: bool
    parent: int | None  # next hop towards the leader (None at the leader)
    hops: int  # distance to the leader in the group tree (0 at the leader)
    weight: int


@dataclass
class GroupStats:
    """Counters of one mote's group management (remote oddities included)."""

    beacons_sent: int = 0
    beacons_forwarded: int = 0
    beacons_suppressed: int = 0  # forwards skipped: enough members around had sent it
    beacons_rebutted: int = 0  # current beacon re-sent to a lighter contending group
    failovers: int = 0  # leader claims after the leader was lost (same id)
    tentative_sent: int = 0  # would-be groups announced (tentative beacons)
    tentative_withdrawn: int = 0  # ... given up for another group before being taken
    beacons_unknown_type: int = 0
    handovers_sent: int = 0
    handovers_failed: int = 0  # link failures and refusals
    handovers_accepted: int = 0
    handovers_refused: int = 0
    reports_refused: int = 0  # collection.submit said no
    types_refused: int = 0
    checks_parked: int = 0  # membership checks parked: nothing can change (quiet_until)
    leader_probes: int = 0  # settled leader asked after a partial it did not acknowledge


@dataclass(slots=True)
class Heard:
    """The best copy of the newest beacon of one nearby group."""

    leader: int
    weight: int
    seq: int
    hops: int  # hops field of the frame (the sender's distance to its leader)
    src: int
    t: float
    rssi: float = -math.inf


class Up(NamedTuple):
    """A group neighbour heard forwarding our group's beacon."""

    seq: int
    hops: int  # its distance to the leader (the frame's hops field)
    t: float
    rssi: float


def seq_newer(a: int, b: int) -> bool:
    """16-bit serial-number comparison: is ``a`` after ``b``?"""
    d = (a - b) & 0xFFFF
    return 0 < d < 0x8000


def heavier(w1: int, g1: int, w2: int, g2: int) -> bool:
    """The paper's order: weight first, then the higher group id."""
    return (w1, g1) > (w2, g2)


def condition_holds(c: Condition, value: float | None, relax: float) -> bool:
    """``value op threshold``, the threshold relaxed by ``relax`` (>= 0) for members.

    Relaxing moves the threshold so the condition is easier to meet: ``>``/``>=``
    accept ``relax`` less, ``<``/``<=`` accept ``relax`` more, ``==`` accepts
    ``|value - threshold| <= relax``; ``!=`` is not relaxed. An unavailable
    attribute (None) never meets a condition.
    """
    if value is None:
        return False
    thr = c.value
    op = c.op
    if op is Op.GT:
        return value > thr - relax
    if op is Op.GE:
        return value >= thr - relax
    if op is Op.LT:
        return value < thr + relax
    if op is Op.LE:
        return value <= thr + relax
    if op is Op.EQ:
        return abs(value - thr) <= relax
    return value != thr


def condition_may_hold(c: Condition, lo: float, hi: float, relax: float) -> bool:
    """Whether :func:`condition_holds` may be True for a value in ``[lo, hi]``
    (False: it is False for every such value; the comparisons are the same
    floating-point operations, which are monotonic)."""
    thr = c.value
    op = c.op
    if op is Op.GT:
        return hi > thr - relax
    if op is Op.GE:
        return hi >= thr - relax
    if op is Op.LT:
        return lo < thr + relax
    if op is Op.LE:
        return lo <= thr + relax
    if op is Op.EQ:
        return not (lo - thr > relax or thr - hi > relax)
    return True  # != (and anything else): read it
