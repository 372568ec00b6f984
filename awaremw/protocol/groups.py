"""Group management (paper II-A, IV-B, IV-C): membership, leaders, group trees.

Per defined group type a mote is in one of five roles:

``IDLE``          not in a group of this type (it still listens to leader beacons
                  and remembers the groups nearby, but does not forward them);
``WAITING``       qualifies, heard no group nearby, waits a random backoff before
                  creating one (joins at once if a beacon of the type arrives);
``MEMBER``        in a group: forwards each new beacon of it once, keeps a parent
                  in the group tree (fewest hops to the leader for the newest seq);
``LEADER``        beacons every ``beacon_period`` and reports to the gateway;
``HANDING_OVER``  a leader that stopped qualifying and is handing its group over.

In short: membership is checked every ``check_period`` with hysteresis; a
qualifying mote joins the heaviest group of its type heard, else creates one
after a random backoff and a tentative id announcement (so contention ends
before any mote holds the losing id); members forward only the heaviest group
they know; a leader that stops qualifying hands its group over; members that
lose the leader claim the group with its id (failover) or, later, create one
with a new id (the paper's split rule). Every rule, with the ties and choices
the paper leaves open: docs/protocol-groups.md, "Groups".
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import Enum
from typing import NamedTuple

from awaremw.protocol.attributes import is_rssi
from awaremw.protocol.collection import Collection
from awaremw.protocol.component import Component, MoteContext
from awaremw.protocol.events import (
    ElectionCause,
    GroupJoined,
    GroupLeft,
    GroupTypeRefused,
    HandoverSent,
    LeaderElected,
    LeaderYielded,
    LeaveReason,
)
from awaremw.protocol.frames import (
    ANY_GROUP_TYPE,
    BROADCAST,
    NODE_MASK,
    Condition,
    Frame,
    GroupReport,
    GroupStatus,
    GroupTypeDef,
    Handover,
    ItemBody,
    LeaderBeacon,
    Op,
)

# A parked mote checks once every this many check periods even if nothing can
# change (see Groups._quiet_until): a bound on the work of finding its schedule.
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


# --------------------------------------------------------------------------- public values


class Role(Enum):
    IDLE = "idle"
    WAITING = "waiting"
    MEMBER = "member"
    LEADER = "leader"
    HANDING_OVER = "handing_over"


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


def unheard(ctx: MoteContext, attr: int, now: float) -> bool:
    """Whether an ``rssi:<node>`` reading is missing now (the node never heard, or not
    within the RSSI TTL): no condition on it holds until the node is heard again."""
    return ctx.read(attr, now) is None


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
    checks_parked: int = 0  # membership checks parked: nothing can change (_quiet_until)
    leader_probes: int = 0  # settled leader asked after a partial it did not acknowledge


# --------------------------------------------------------------------------- internals


@dataclass(slots=True)
class _Heard:
    """The best copy of the newest beacon of one nearby group."""

    leader: int
    weight: int
    seq: int
    hops: int  # hops field of the frame (the sender's distance to its leader)
    src: int
    t: float
    rssi: float = -math.inf


class _Up(NamedTuple):
    """A group neighbour heard forwarding our group's beacon."""

    seq: int
    hops: int  # its distance to the leader (the frame's hops field)
    t: float
    rssi: float


@dataclass(slots=True)
class _TypeState:
    gtype: int
    defn: GroupTypeDef
    role: Role = Role.IDLE
    gid: int = 0
    leader: int = 0
    weight: int = 0
    seq: int = 0
    hops: int = 0
    parent: int | None = None
    last_beacon: float = 0.0
    cause: ElectionCause = ElectionCause.CREATED
    beacons: int = 0  # beacons sent as leader of this group
    readings: int = 0  # readings in the leader's latest aggregated epoch
    nearby: dict[int, _Heard] = field(default_factory=dict)
    parent_rssi: float = -math.inf  # link RSSI (EWMA) of the parent when it was chosen
    forwarded: bool = True  # the current seq was re-broadcast (our hop count is public)
    # Copies of the current seq heard before our own forward, (sender, its hops):
    # counter-based suppression (see on_timer "fwd").
    copies: list[tuple[int, int]] = field(default_factory=list)
    must_forward: bool = False  # the beacon we joined on announces the group: no suppression
    # A member with children forwards every seq until then (see _covered): a child
    # named us in its forward, or sent us a partial, lately.
    child_until: float = -math.inf
    # Leader: its beacon interval now; member: the interval it saw between the
    # leader's beacons (0: none seen yet). See _gap and docs/protocol-groups.md.
    gap: float = 0.0
    settled: bool = False  # leader: nothing unsettled the group since the last beacon
    recorded: bool = False  # leader: a channel record was made since the last beacon
    peak: int = 0  # leader: most readings in one record since the beacon before last
    peak_prev: int = 0  # ... of the records between the last two beacons
    dips: int = 0  # leader: records in a row 10 % under the peak
    reported_at: float = -math.inf  # leader: last GroupReport ALIVE
    upstream: dict[int, _Up] = field(default_factory=dict)
    failed: dict[int, float] = field(default_factory=dict)  # neighbour -> last failed unicast
    # Member neighbours of a leader: handover candidates. n -> (t, readings, link RSSI)
    children: dict[int, tuple[float, int, float]] = field(default_factory=dict)
    candidates: list[int] = field(default_factory=list)
    handover_to: int | None = None
    handed: tuple[int, int] | None = None  # (group id, seq) of our last Handover
    # Failure detection of the leader (failover keeping the id):
    leader_ok: float = -math.inf  # last evidence it lives: a new seq, or an acked unicast to it
    leader_direct: float = -math.inf  # last time we heard it directly or it acked us
    suspect_at: float | None = None  # a unicast to the leader failed at this time
    rebutted: float = -math.inf  # last re-broadcast answering a lighter group's beacon
    split_from: int = 0  # the id whose leader we lost before creating this group
    split_t: float = -math.inf  # ... and when we lost it
    patience: bool = False  # the split route's extra beacon period was granted for this seq
    former: int = 0  # an established group (weight > 0) we left by a merge ...
    former_until: float = -math.inf  # ... and until when a split may take its id back
    tent_gid: int = 0  # WAITING: the id this mote announced tentatively (0: none)
    tent_sent: int = 0  # tentative beacons sent for tent_gid
    tent_heard: dict[int, float] = field(default_factory=dict)  # tentative id -> heard at
    tent_leader: dict[int, int] = field(default_factory=dict)  # tentative id -> announcer
    tent_relayed: int = 0  # the would-be id whose announcement we relayed last
    relay: tuple[int, int] | None = None  # (would-be id, announcer) of the pending relay

    def remembers_nothing(self) -> bool:
        """No table that the membership check purges holds an entry (most motes,
        hearing no group most of the time)."""
        return not (self.nearby or self.upstream or self.failed or self.children or self.tent_heard)


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


# --------------------------------------------------------------------------- the component


class Groups(Component):
    """Group management of one mote (all group types)."""

    def __init__(self, ctx: MoteContext, collection: Collection) -> None:
        super().__init__(ctx)
        self.collection = collection
        self.stats = GroupStats()
        self._types: dict[int, _TypeState] = {}
        self._echoed: tuple[int, int, int, int] | None = None  # last refusal sent back
        # Parked (see _quiet_until): the time of the last membership check run;
        # the skipped checks were due at it + k * check_period. None: not parked.
        self._parked_at: float | None = None
        # Parked: the nodes whose next frame can end it (an rssi:<node> condition
        # that no reading can meet until that node is heard again).
        self._awaiting: frozenset[int] = frozenset()
        # Called with ``now`` when this mote enters a group (as member or leader):
        # the channels start their epochs then (a mote in no group keeps no epoch timer).
        self.on_enter: Callable[[float], None] | None = None

    # ----------------------------------------------------------------- public API

    def define(self, group_type: int, item: ItemBody | None, now: float) -> None:
        """A group type was defined, changed (``item``) or deleted (``None``)."""
        if item is None:
            self._drop_type(group_type, now)
            return
        if not isinstance(item, GroupTypeDef):
            raise TypeError(f"group type {group_type} defined with a {type(item).__name__}")
        st = self._types.get(group_type)
        if st is None:
            reason = None
            if not 0 <= group_type < ANY_GROUP_TYPE:
                reason = f"group type {group_type} is not in 0..{ANY_GROUP_TYPE - 1}"
            elif len(self._types) >= self.ctx.config.max_group_types:
                reason = f"more than {self.ctx.config.max_group_types} group types"
            if reason is not None:
                self.stats.types_refused += 1
                self.ctx.emit(GroupTypeRefused(self.ctx.node_id, group_type, reason))
                return
            st = self._types[group_type] = _TypeState(group_type, item)
        else:
            st.defn = item
        self._wake(now)
        self._check(st, now)  # a changed definition takes effect at once
        if "check" not in self.timers:
            self.timers.set("check", now + self.ctx.rng.uniform(0, self.ctx.config.check_period))

    def membership(self, group_type: int) -> Membership | None:
        st = self._types.get(group_type)
        if st is None or st.role not in (Role.MEMBER, Role.LEADER):
            return None
        leader = st.role is Role.LEADER
        return Membership(
            group_type=st.gtype,
            group_id=st.gid,
            leader=self.ctx.node_id if leader else st.leader,
            is_leader=leader,
            parent=None if leader else st.parent,
            hops=0 if leader else st.hops,
            weight=st.weight,
        )

    def memberships(self) -> dict[int, Membership]:
        out: dict[int, Membership] = {}
        for g, st in self._types.items():
            if st.role is Role.MEMBER or st.role is Role.LEADER:  # else membership() is None
                m = self.membership(g)
                if m is not None:
                    out[g] = m
        return out

    def role(self, group_type: int) -> Role | None:
        st = self._types.get(group_type)
        return None if st is None else st.role

    def defined_types(self) -> dict[int, GroupTypeDef]:
        return {g: st.defn for g, st in self._types.items()}

    def add_weight(self, group_type: int, n: int) -> None:
        """The leader aggregated ``n`` readings of one epoch: its group gets heavier."""
        st = self._types.get(group_type)
        if st is None or st.role is not Role.LEADER or n <= 0:
            return
        st.weight = min(st.weight + n, MAX_WEIGHT)
        if n > st.peak:
            # More readings than the group gave lately (lost partials only ever
            # make fewer): new members, which need the tree and our pace.
            self._unsettle(st)
        # Fewer, twice in a row: a subtree's way up is broken (its partials fail
        # and its members know no other parent yet) or members left; a beacon
        # rebuilds the tree. Once is a lost frame: no beacon for that.
        st.dips = st.dips + 1 if n * 10 < st.peak * 9 else 0
        if st.dips >= 2:
            st.dips = 0
            self._unsettle(st)
        st.peak = max(st.peak, n)
        st.readings = n
        st.recorded = True

    def note_child(self, group_type: int, node: int, now: float, count: int = 0) -> None:
        """Channel data (``count`` readings) came from ``node``: a handover candidate
        of a leader; for a member, proof that it is a parent in the group tree."""
        st = self._types.get(group_type)
        if st is not None and st.role is Role.MEMBER:
            # A partial comes every epoch: proof for one beacon interval.
            st.child_until = max(st.child_until, now + self._gap(st))
            return
        if st is None or st.role is not Role.LEADER:
            return
        st.children[node] = (now, count, self._link_rssi(node, -math.inf))

    def upstream(self, group_type: int, now: float) -> list[int]:
        """The parent, then the other neighbours that forwarded the current beacon
        with fewer hops than ours (fewest hops, then strongest first)."""
        st = self._types.get(group_type)
        if st is None or st.role is not Role.MEMBER:
            return []
        head = [] if st.parent is None else [st.parent]
        return head + [n for n, _ in self._alternatives(st) if n != st.parent]

    def parent_failed(self, group_type: int, node: int, now: float) -> None:
        """A unicast to ``node`` failed after the link layer's retries: route the next
        partials through another neighbour of the current beacon, if there is one
        (the next beacon may choose ``node`` again only if nobody else is as close)."""
        st = self._types.get(group_type)
        if st is None or st.role is not Role.MEMBER:
            return
        st.failed[node] = now
        if node == st.leader:
            self._suspect(st, now)
        if st.parent != node:
            return
        alts = [(n, u) for n, u in self._alternatives(st) if n != node]
        if alts:
            n, u = alts[0]
            st.parent, st.hops, st.parent_rssi = n, u.hops + 1, u.rssi

    def parent_acked(self, group_type: int, node: int, now: float) -> None:
        """A unicast to ``node`` was acknowledged: if it is our leader, it lives."""
        st = self._types.get(group_type)
        if st is None or st.role is not Role.MEMBER or node != st.leader:
            return
        st.leader_ok = st.leader_direct = now
        self._clear_suspicion(st)

    # ----------------------------------------------------------------- failover

    def _unmerge_window(self) -> float:
        c = self.ctx.config
        return c.unmerge_window_periods * c.beacon_period

    def _gap(self, st: _TypeState) -> float:
        """The leader's beacon interval as this mote knows it (the base period
        until a member saw two beacons: a mote that joins a settled group adds
        readings to its records, which unsettles the leader, see add_weight)."""
        return st.gap if st.gap > 0 else self.ctx.config.beacon_period

    def _max_factor(self) -> float:
        return max(1.0, self.ctx.config.beacon_settled_factor)

    def _member_timeout(self, st: _TypeState) -> float:
        """No new seq for this long: the leader is lost (in gaps seen, not periods)."""
        return self.ctx.config.leader_timeout_periods * self._gap(st)

    def _unsettle(self, st: _TypeState) -> None:
        """Leader: the group changed; beacon at the base period again (and within one
        base period of the last beacon), so that the tree and members catch up."""
        base = self.ctx.config.beacon_period
        st.settled = False
        if st.gap <= base:
            return
        st.gap = base
        name = ("beacon", st.gtype)
        due = self.timers.get(name)
        if due is not None and due > st.last_beacon + base:
            self.timers.set(name, st.last_beacon + base)

    def _claim_after(self) -> float:
        """Hysteresis in time: a leader heard from this recently is not suspected."""
        return 1.25 * self.ctx.config.beacon_period

    def _suspect(self, st: _TypeState, now: float) -> None:
        """A partial to the leader was not acknowledged after the link retries
        (the data path as failure detector, as CTP does). Claim the group unless
        the leader gave a sign of life within ``_claim_after``; then claim when
        that evidence gets stale, unless new evidence arrives meanwhile."""
        if st.suspect_at is None:
            st.suspect_at = now
            if st.gap > self.ctx.config.beacon_period:
                # A settled leader beacons rarely: our ACKs are most of the signs
                # of life we get, and one partial lost to a collision is no death.
                # Ask it at once (a copy of its beacon, unicast: it acknowledges
                # it like any frame, and takes it as a member's forward) rather
                # than wait an epoch for the next partial; claim if that fails too.
                self._probe(st)
                return
        at = max(now, st.leader_ok + self._claim_after())
        self._schedule_claim(st, at)

    def _probe(self, st: _TypeState) -> None:
        self.stats.leader_probes += 1
        self.send(
            LeaderBeacon(
                self.ctx.node_id, st.leader, st.gtype, st.gid, st.leader, st.weight, st.seq,
                st.hops, parent=self._named_parent(st),
            )
        )  # fmt: skip

    def _schedule_claim(self, st: _TypeState, at: float) -> None:
        # A jitter of a few frame times: neighbours of the dead leader that detect
        # the loss together mostly hear the first claim and adopt it.
        name = ("claim", st.gtype)
        if name not in self.timers:
            self.timers.set(name, at + self.ctx.rng.uniform(0, 2 * self.ctx.config.forward_jitter))

    def _clear_suspicion(self, st: _TypeState) -> None:
        st.suspect_at = None
        self.timers.cancel(("claim", st.gtype))

    def _leader_was_neighbour(self, st: _TypeState, now: float) -> bool:
        return now - st.leader_direct <= 2 * self._timeout()

    def _claim(self, st: _TypeState, now: float) -> None:
        """Take over the group of a lost leader with its id: beacon seq + 1, the
        group's weight as last heard (docs/protocol-groups.md, Failover)."""
        if not self._qualifies(st, True, now):
            self._leave(st, now, LeaveReason.CONDITION)
            return
        self.stats.failovers += 1
        self._become_leader(st, st.gid, st.weight, st.seq, now, ElectionCause.FAILOVER)

    def _alternatives(self, st: _TypeState) -> list[tuple[int, _Up]]:
        # Only copies of the current seq with fewer hops than ours: a switch never
        # raises our advertised hop count, which keeps the tree loop-free.
        ups = [(n, u) for n, u in st.upstream.items() if u.seq == st.seq and u.hops < st.hops]
        ups.sort(key=lambda x: self._link_key(st, x[0], x[1].hops + 1, x[1].rssi))
        return ups

    def _link_key(
        self, st: _TypeState, node: int, hops: int, rssi: float
    ) -> tuple[bool, int, int, float]:
        """Order of parent candidates: not failed, link band, fewest hops, strongest."""
        return (node in st.failed, self._band(rssi), hops, -rssi)

    def _band(self, rssi: float) -> int:
        """0 for a good link, up to 3 for the weakest (BAND_2_DB, BAND_3_DB)."""
        under = self.ctx.config.group_link_rssi_floor - rssi
        return 0 if under <= 0 else 1 if under <= BAND_2_DB else 2 if under <= BAND_3_DB else 3

    def _link_rssi(self, node: int, rssi: float) -> float:
        # The mote's EWMA of everything heard from the node (updated with this
        # frame before dispatch) is steadier than one frame's RSSI.
        s = self.ctx.rssi.get(node)
        return rssi if s is None else s.dbm

    # ----------------------------------------------------------------- Component hooks

    def app_changed(self, now: float) -> None:
        """The application was sent a command: its readings may change (a sample
        period, say), so a parked mote checks again from its next regular check."""
        self._wake(now)

    def heard_again(self, node: int, now: float) -> None:
        """The mote hears ``node`` after a silence (its first frame, or the first after
        the RSSI TTL): an ``rssi:<node>`` condition may hold again, so a mote parked
        on it checks again from its next regular check."""
        if self._parked_at is not None and node in self._awaiting:
            self._wake(now)

    def on_frame(self, frame: Frame, rssi_dbm: float, now: float) -> None:
        self._wake(now)  # if parked: the frame may fill tables that the checks purge
        if isinstance(frame, LeaderBeacon):
            self._on_beacon(frame, rssi_dbm, now)
        elif isinstance(frame, Handover):
            self._on_handover(frame, now)

    def on_timer(self, name: object, now: float) -> None:
        if name == "check":
            self._parked_at = None  # a parked mote's horizon came
            for st in list(self._types.values()):
                self._check(st, now)
                self._purge(st, now)
            if not self._types:
                return
            nxt = now + self.ctx.config.check_period
            quiet = self._quiet_until(now)
            if quiet <= nxt:
                self.timers.set("check", nxt)
                return
            self._parked_at = now
            self.stats.checks_parked += 1
            # At most PARK_PERIODS at a time (then one check, "not in" again, and
            # park anew): finding the schedule's next instant walks its periods.
            horizon = now + PARK_PERIODS * self.ctx.config.check_period
            self.timers.set("check", self._regular_check_after(min(quiet, horizon)))
            return
        assert isinstance(name, tuple)
        kind, g = name
        ts = self._types.get(g)
        if ts is None:
            return
        st = ts
        if kind == "beacon" and st.role is Role.LEADER:
            self._beacon(st, now)
        elif kind == "fwd" and st.role is Role.MEMBER:
            if self._covered(st, now):
                # A leaf (no child named us or sent us a partial lately), and
                # members at least as far out as we are already carried this seq
                # to our neighbourhood: skip ours (counter-based flooding). Parents
                # always forward, so that the tree and its hop counts stay put and
                # a child that hears no other member keeps its group.
                self.stats.beacons_suppressed += 1
            else:
                self._forward(st)
        elif kind == "lost" and st.role is Role.MEMBER:
            self._leader_lost(st, now)
        elif kind == "claim" and st.role is Role.MEMBER:
            if st.suspect_at is not None and st.leader_ok > st.suspect_at:
                st.suspect_at = None  # the leader gave a sign of life meanwhile
            else:
                self._claim(st, now)
        elif kind == "rebut" and st.role in (Role.MEMBER, Role.LEADER):
            self._forward(st, count=False)
        elif kind == "relay" and st.role in (Role.IDLE, Role.WAITING) and not st.tent_gid:
            if st.relay is not None:
                (top, who), st.relay = st.relay, None
                me = self.ctx.node_id
                self.send(LeaderBeacon(me, BROADCAST, st.gtype, top, who, 0, 0, 1, True))
        elif kind == "announce" and st.role is Role.WAITING and st.tent_gid:
            self._send_tentative(st)
        elif kind == "create" and st.role is Role.WAITING:
            best = self._best_nearby(st, now)
            if best is not None:
                self._join(st, best[0], best[1], now)
            else:
                self._create(st, now)
        elif kind == "confirm" and st.role is Role.WAITING and st.tent_gid:
            if st.tent_sent < TENTATIVE_BEACONS:
                # Once more half-way: one lost frame (ours, or the answer) on a
                # marginal link must not let a contender take its id.
                self._send_tentative(st)
                self.timers.set(name, now + self._tentative_hold() / TENTATIVE_BEACONS)
                return
            # The would-be group heard no established group and no heavier
            # would-be group for a tentative period: its id is taken now.
            gid, st.tent_gid = st.tent_gid, 0
            self._become_leader(st, gid, 0, 0, now, st.cause)
        elif kind == "handover" and st.role is Role.HANDING_OVER:
            # Acknowledged and not refused within the grace time: done.
            assert st.handover_to is not None
            self.ctx.emit(HandoverSent(self.ctx.node_id, st.gtype, st.gid, st.handover_to, now))
            self._leave(st, now, LeaveReason.HANDOVER)

    def on_link_result(self, frame: Frame, acked: bool, now: float) -> None:
        if isinstance(frame, LeaderBeacon):  # a probe of a settled leader (_suspect)
            st = self._types.get(frame.group_type)
            if st is not None and st.gid == frame.group_id:
                (self.parent_acked if acked else self.parent_failed)(st.gtype, frame.dst, now)
            return
        if not isinstance(frame, Handover):
            return
        st = self._types.get(frame.group_type)
        if (
            st is None
            or st.role is not Role.HANDING_OVER
            or st.gid != frame.group_id
            or frame.dst != st.handover_to
            or frame.src != self.ctx.node_id
        ):
            return  # a refusal we sent, or a handover overtaken by events
        if acked:
            self.timers.set(("handover", st.gtype), now + self.ctx.config.handover_grace)
        else:
            self.stats.handovers_failed += 1
            self._next_candidate(st, now)

    # ----------------------------------------------------------------- membership check

    def _timeout(self) -> float:
        c = self.ctx.config
        return c.leader_timeout_periods * c.beacon_period

    def _qualifies(self, st: _TypeState, relaxed: bool, now: float) -> bool:
        relax = st.defn.hysteresis if relaxed else 0.0
        ctx = self.ctx
        for c in st.defn.conditions:
            # A reading certain to fail the condition is not taken (most motes,
            # far from what a group tracks, most of the time): the same answer.
            b = ctx.read_bounds(c.attr, now)
            if b is not None and not condition_may_hold(c, b.lo, b.hi, relax):
                return False
            if not condition_holds(c, ctx.read(c.attr, now), relax):
                return False
        return True

    def _quiet_until(self, now: float) -> float:
        """Until when the membership checks can change nothing (``now``: they may).

        A mote out of every group, with no group heard lately (nothing to purge),
        whose application rules a condition of every type out until a time
        (:class:`~awaremw.protocol.attributes.Bounds`), makes the same decision,
        "not in", at every check until then: it parks its checks (most motes of a
        large field, far from anything a group tracks). An ``rssi:<node>``
        condition is ruled out until ``node`` is heard again when it is not heard
        now (never, or not within the RSSI TTL). What could change that wakes it:
        a group frame, a definition, a command to the application, a frame from a
        node it awaits (:meth:`heard_again`).
        """
        until = math.inf
        awaiting: set[int] = set()
        for st in self._types.values():
            if st.role is not Role.IDLE or not st.remembers_nothing():
                return now
            ruled_out = now
            for c in st.defn.conditions:
                if is_rssi(c.attr):
                    if unheard(self.ctx, c.attr, now):
                        ruled_out = math.inf
                        awaiting.add(c.attr & NODE_MASK)
                    continue
                b = self.ctx.read_bounds(c.attr, now)
                if (
                    b is not None
                    and b.until > ruled_out
                    and not condition_may_hold(c, b.lo, b.hi, 0.0)
                ):
                    ruled_out = b.until
            until = min(until, ruled_out)
        self._awaiting = frozenset(awaiting)
        return until

    def _regular_check_after(self, t: float) -> float:
        """The first check, at or after ``t``, of the schedule the parked mote left:
        the same float sums as running every check, so the same instants (a loop
        over the periods parked, at most PARK_PERIODS: cheap beside a check each)."""
        p = self.ctx.config.check_period
        assert self._parked_at is not None
        due = self._parked_at + p
        while due < t:
            due += p
        return due

    def _wake(self, now: float) -> None:
        """Unpark: back to a check every period, on the schedule it left."""
        if self._parked_at is None:
            return
        self.timers.set("check", self._regular_check_after(now))
        self._parked_at = None

    def _check(self, st: _TypeState, now: float) -> None:
        role = st.role
        if role is Role.HANDING_OVER:
            return
        q = self._qualifies(st, role is Role.MEMBER or role is Role.LEADER, now)
        if role is Role.IDLE and q:
            self._join_or_wait(st, now, ElectionCause.CREATED)
        elif role is Role.WAITING and not q:
            self.timers.cancel(("create", st.gtype))
            if st.tent_gid:
                self._withdraw(st)
            st.role = Role.IDLE
        elif role is Role.MEMBER and not q:
            self._leave(st, now, LeaveReason.CONDITION)
        elif role is Role.LEADER and not q:
            self._start_handover(st, now)

    def _purge(self, st: _TypeState, now: float) -> None:
        if st.remembers_nothing():
            return
        ttl = self._timeout()
        if st.nearby:
            for gid in [g for g, h in st.nearby.items() if now - h.t > ttl]:
                del st.nearby[gid]
        if st.role is Role.MEMBER or st.role is Role.LEADER:
            ttl = max(ttl, self.ctx.config.leader_timeout_periods * self._gap(st))
        if st.upstream:
            for n in [n for n, u in st.upstream.items() if now - u.t > ttl]:
                del st.upstream[n]
        if st.failed:
            for n in [n for n, t in st.failed.items() if now - t > ttl]:
                del st.failed[n]
        if st.children:
            for n in [n for n, c in st.children.items() if now - c[0] > ttl]:
                del st.children[n]
        if st.tent_heard:
            for g in [g for g, t in st.tent_heard.items() if now - t > ttl]:
                del st.tent_heard[g]
                st.tent_leader.pop(g, None)

    def _best_nearby(self, st: _TypeState, now: float) -> tuple[int, _Heard] | None:
        ttl = self._timeout()
        fresh = [(h.weight, gid, h) for gid, h in st.nearby.items() if now - h.t <= ttl]
        if not fresh:
            return None
        _w, gid, h = max(fresh, key=lambda x: (x[0], x[1]))
        return gid, h

    def _join_or_wait(self, st: _TypeState, now: float, cause: ElectionCause) -> None:
        best = self._best_nearby(st, now)
        if best is not None:
            self._join(st, best[0], best[1], now)
            return
        st.role = Role.WAITING
        st.cause = cause
        # After a split every member of the leaderless part gives up on the same
        # last beacon: a wider backoff spreads their claims so that the first new
        # group's flood reaches the others before they create contenders.
        spread = ELECTION_BACKOFF_FACTOR if cause is ElectionCause.ELECTION else 1.0
        if cause is ElectionCause.CREATED and self._tentative_hold() > 0:
            # The tentative period resolves contention now: half the backoff
            # gives back part of the time it costs before the first record.
            spread = TENTATIVE_CREATE_SPREAD
        backoff = self.ctx.rng.uniform(0, spread * self.ctx.config.create_backoff)
        self.timers.set(("create", st.gtype), now + backoff)

    # ----------------------------------------------------------------- role changes

    def _become_member(
        self,
        st: _TypeState,
        gid: int,
        leader: int,
        weight: int,
        seq: int,
        hops: int,
        src: int,
        heard_at: float,
        rssi: float,
        now: float,
    ) -> None:
        self.timers.cancel(("create", st.gtype))
        if st.tent_gid:
            self._withdraw(st)
        st.role = Role.MEMBER
        st.gid, st.leader, st.weight, st.seq = gid, leader, weight, seq
        st.hops = min(hops + 1, MAX_HOPS)
        st.parent, st.parent_rssi = src, self._link_rssi(src, rssi)
        st.forwarded = True  # _adopt clears it: it forwards the beacon it joined on
        st.last_beacon = heard_at
        st.patience = False
        st.upstream = {src: _Up(seq, hops, heard_at, rssi)}
        st.failed = {}
        st.children = {}
        st.child_until = -math.inf
        st.suspect_at = None
        st.leader_ok = heard_at
        st.leader_direct = heard_at if src == leader else -math.inf
        self.timers.cancel(("claim", st.gtype))
        st.gap = 0.0  # not seen yet
        self.timers.set(("lost", st.gtype), heard_at + self._member_timeout(st))
        self.ctx.emit(GroupJoined(self.ctx.node_id, st.gtype, gid, leader, now))
        if self.on_enter is not None:
            self.on_enter(now)

    def _join(self, st: _TypeState, gid: int, h: _Heard, now: float) -> None:
        """Join a group remembered from an earlier beacon, and announce it: forward
        that (older) seq once, so that a waiting mote two hops away adopts the group
        now rather than creating a contender before the leader's next beacon."""
        self._become_member(st, gid, h.leader, h.weight, h.seq, h.hops, h.src, h.t, h.rssi, now)
        st.forwarded = False
        st.copies, st.must_forward = [], True
        self._schedule_forward(st, now)
        self._answer_tentatives(st, now)

    def _adopt(self, st: _TypeState, f: LeaderBeacon, rssi: float, now: float) -> None:
        """Join the group of beacon ``f`` just heard, and forward it."""
        self._become_member(
            st, f.group_id, f.leader, f.weight, f.seq, f.hops, f.src, now, rssi, now
        )
        st.forwarded = False
        st.copies, st.must_forward = [], False
        self._schedule_forward(st, now)
        self._answer_tentatives(st, now)

    def _answer_tentatives(self, st: _TypeState, now: float) -> None:
        """We joined a group after hearing a would-be group announce another id (as
        a waiting or idle mote, which does not answer): answer it, one more copy of
        our beacon after the forward, so that one lost forward (two forwarders
        colliding at the would-be group's radio) does not let it take its id."""
        hold = self._tentative_hold()
        if not any(g != st.gid and now - t <= hold for g, t in st.tent_heard.items()):
            return
        st.rebutted = now
        j = self.ctx.config.forward_jitter
        self.timers.set(("rebut", st.gtype), now + self.ctx.rng.uniform(j, 2 * j))

    def _create(self, st: _TypeState, now: float) -> None:
        taken = set(st.nearby) | {st.gid}
        if (
            st.cause is ElectionCause.ELECTION
            and st.former
            and now <= st.former_until
            and st.former not in taken
        ):
            # A part that lost the merged group's leader soon after the merge: the
            # merge did not hold, the part goes on under its own former id.
            self._become_leader(st, st.former, 0, 0, now, st.cause)
            return
        hold = self._tentative_hold()
        heard = [t for t in st.tent_heard.values() if now - t <= hold]
        if heard:
            # A neighbour announced a would-be group: wait for it to be taken
            # (its first beacon reaches us) rather than announce a contender.
            backoff = self.ctx.rng.uniform(0, self.ctx.config.create_backoff)
            self.timers.set(("create", st.gtype), max(heard) + hold + backoff)
            return
        taken |= set(st.tent_heard)
        gid = self.ctx.rng.randint(1, MAX_GROUP_ID)
        while gid in taken:
            gid = self.ctx.rng.randint(1, MAX_GROUP_ID)
        if hold <= 0:
            self._become_leader(st, gid, 0, 0, now, st.cause)
            return
        # Tentative ids: announce the id and take it one tentative period later
        # unless an established group answers or a heavier would-be group is heard.
        st.tent_gid, st.tent_sent = gid, 0
        self._send_tentative(st)
        self.timers.set(("confirm", st.gtype), now + hold / TENTATIVE_BEACONS)

    def _tentative_hold(self) -> float:
        c = self.ctx.config
        return c.tentative_periods * c.beacon_period

    def _send_tentative(self, st: _TypeState) -> None:
        me = self.ctx.node_id
        self.send(LeaderBeacon(me, BROADCAST, st.gtype, st.tent_gid, me, 0, 0, 0, True))
        st.tent_sent += 1
        self.stats.tentative_sent += 1

    def _jitter(self, st: _TypeState, kind: str, now: float) -> None:
        """An answer to a frame just heard goes out after U(0, forward_jitter): the
        motes that heard the same frame must not all answer at the same instant."""
        name = (kind, st.gtype)
        if name not in self.timers:
            self.timers.set(name, now + self.ctx.rng.uniform(0, self.ctx.config.forward_jitter))

    def _withdraw(self, st: _TypeState) -> None:
        """Give up our would-be group (nobody joined it, nothing was reported)."""
        st.tent_gid = 0
        self.timers.cancel(("confirm", st.gtype))
        self.timers.cancel(("announce", st.gtype))
        self.stats.tentative_withdrawn += 1

    def _on_tentative(self, st: _TypeState, f: LeaderBeacon, now: float) -> None:
        """A would-be group's announcement: never joined, never forwarded."""
        hold = self._tentative_hold()
        rivals = [g for g, t in st.tent_heard.items() if now - t <= hold and g != f.group_id]
        st.tent_heard[f.group_id] = now
        st.tent_leader[f.group_id] = f.leader
        role = st.role
        if role in (Role.IDLE, Role.WAITING) and not st.tent_gid and rivals:
            # Two would-be groups around us, maybe out of each other's range:
            # relay the higher one's announcement once, the lower one withdraws.
            top = max([*rivals, f.group_id])
            if top != st.tent_relayed:
                # After a jitter: every mote between the two heard the same frame
                # at the same instant; relaying at once, they collided.
                st.tent_relayed = top
                st.relay = (top, st.tent_leader.get(top, 0))
                self._jitter(st, "relay", now)
        if role in (Role.MEMBER, Role.LEADER):
            # An established group is in range: answer with our beacon, the
            # would-be group joins us instead of taking its id.
            self._rebut(st, now)
        elif role is Role.WAITING and st.tent_gid:
            if (f.group_id, f.leader) > (st.tent_gid, self.ctx.node_id):
                # The paper's order among weight-0 groups: the higher id goes on;
                # we wait for its first beacon (or announce again later).
                self._withdraw(st)
                backoff = self.ctx.rng.uniform(0, self.ctx.config.create_backoff)
                self.timers.set(("create", st.gtype), now + self._tentative_hold() + backoff)
            elif st.tent_sent <= TENTATIVE_BEACONS:
                self._jitter(st, "announce", now)  # it may not have heard ours: once more

    def _become_leader(
        self, st: _TypeState, gid: int, weight: int, seq: int, now: float, cause: ElectionCause
    ) -> None:
        for kind in ("create", "confirm", "lost", "fwd", "handover", "claim"):
            self.timers.cancel((kind, st.gtype))
        st.tent_gid = 0
        # A member taking over knows its member neighbours already (those it heard
        # forward the beacons): handover candidates before any partial arrives.
        known = {
            n: (u.t, 0, u.rssi)
            for n, u in st.upstream.items()
            if st.role is Role.MEMBER and st.gid == gid and n != st.leader
        }
        if cause is not ElectionCause.ELECTION:
            st.split_from = 0
        st.role = Role.LEADER
        st.gid, st.leader, st.weight, st.seq = gid, self.ctx.node_id, weight, seq
        st.hops, st.parent = 0, None
        st.beacons = 0
        st.gap, st.settled, st.recorded = 0.0, False, False
        st.peak = st.peak_prev = 0
        st.reported_at = -math.inf
        st.readings = 0
        st.upstream = {}
        st.children = known
        st.suspect_at = None
        self.ctx.emit(LeaderElected(self.ctx.node_id, st.gtype, gid, weight, cause, now))
        if self.on_enter is not None:
            self.on_enter(now)
        self._beacon(st, now)

    def _leave(self, st: _TypeState, now: float, reason: LeaveReason, into: int = 0) -> None:
        gid = st.gid
        window = self._unmerge_window()
        rejoined = into != 0 and into == st.split_from and now - st.split_t <= window
        if reason in (LeaveReason.SWITCHED, LeaveReason.YIELDED) and (st.weight > 0 or rejoined):
            # Merged into a heavier group: if the merge does not hold (the part
            # loses the merged group's leader soon), the part takes this id back.
            # The same for a part that split off and met its former group again
            # (a flapping bridge): when the split comes for good, it is that part.
            st.former, st.former_until = gid, now + window
        for kind in ("create", "confirm", "lost", "fwd", "beacon", "handover", "claim", "rebut"):
            self.timers.cancel((kind, st.gtype))
        st.role = Role.IDLE
        st.suspect_at = None
        st.parent = None
        st.upstream = {}
        st.children = {}
        st.candidates = []
        st.handover_to = None
        self.ctx.emit(GroupLeft(self.ctx.node_id, st.gtype, gid, reason, now))

    def _drop_type(self, group_type: int, now: float) -> None:
        st = self._types.pop(group_type, None)
        if st is None:
            return
        if st.role in (Role.LEADER, Role.HANDING_OVER):
            self._report(st, now, GroupStatus.GONE)
        if st.role in (Role.MEMBER, Role.LEADER, Role.HANDING_OVER):
            self._leave(st, now, LeaveReason.DELETED)
        for kind in (
            "create", "confirm", "lost", "fwd", "beacon", "handover", "claim", "rebut",
            "relay", "announce",
        ):  # fmt: skip
            self.timers.cancel((kind, group_type))
        if not self._types:
            self.timers.cancel("check")
            self._parked_at = None

    def _leader_lost(self, st: _TypeState, now: float) -> None:
        if self._leader_was_neighbour(st, now) and self._qualifies(st, True, now):
            # We heard the leader directly: most likely it died (a split leaves
            # its neighbours on its side). Take over with the id, after a jitter.
            st.suspect_at = st.suspect_at if st.suspect_at is not None else now
            self._schedule_claim(st, now)
            return
        if not st.patience:
            # Hysteresis in time on the split route: one more beacon period as a
            # member (a thin, flapping bridge to the leader often carries the next
            # beacon) before the group is given up for a new one.
            st.patience = True
            self.timers.set(("lost", st.gtype), now + self._gap(st))
            return
        dead = st.gid
        st.split_from, st.split_t = dead, now  # named by the group this mote may create now
        self._leave(st, now, LeaveReason.LEADER_LOST)
        st.nearby.pop(dead, None)
        if self._qualifies(st, True, now):
            self._join_or_wait(st, now, ElectionCause.ELECTION)

    # ----------------------------------------------------------------- beacons

    def _beacon(self, st: _TypeState, now: float) -> None:
        st.seq = (st.seq + 1) & 0xFFFF
        self.send(
            LeaderBeacon(
                self.ctx.node_id,
                BROADCAST,
                st.gtype,
                st.gid,
                self.ctx.node_id,
                st.weight,
                st.seq,
                0,
            )
        )
        self.stats.beacons_sent += 1
        st.beacons += 1
        c = self.ctx.config
        base = c.beacon_period
        if st.gap <= 0:
            st.gap = base
        elif st.settled and st.recorded:
            # Settled: a channel's records flow (the data path detects a dead
            # leader: its children's partials go unacknowledged) and nothing
            # changed since the last beacon. Beacons only refresh the tree.
            st.gap = min(2.0 * st.gap, base * self._max_factor())
        st.settled, st.recorded = True, False
        # The peak forgets records older than two beacons (members that left).
        st.peak, st.peak_prev = max(st.peak_prev, st.readings), st.readings
        st.last_beacon = now
        # Reports keep their pace in time whatever the beacons' (the gateway
        # expires a group unheard for a few report periods).
        if st.beacons == 1 or now + st.gap > st.reported_at + c.report_every_beacons * base:
            st.reported_at = now
            self._report(st, now, GroupStatus.ALIVE)
        self.timers.set(("beacon", st.gtype), now + st.gap)

    def _covered(self, st: _TypeState, now: float) -> bool:
        """Skip our forward of the current seq? Only a leaf (no child lately, see
        child_until) that heard ``beacon_forward_cover`` copies from members at
        least as far from the leader as we are (not our parent)."""
        k = self.ctx.config.beacon_forward_cover
        if k <= 0 or st.must_forward or now <= st.child_until:
            return False
        return sum(1 for src, h in st.copies if h >= st.hops and src != st.parent) >= k

    def _schedule_forward(self, st: _TypeState, now: float) -> None:
        name = ("fwd", st.gtype)
        if name not in self.timers:
            # The weaker the first copy's link, the longer we wait (one forward
            # jitter per band below group_link_rssi_floor): a copy over a better
            # link usually arrives meanwhile and can still become the parent.
            j = self.ctx.config.forward_jitter
            band = self._band(st.parent_rssi)
            self.timers.set(name, now + band * j + self.ctx.rng.uniform(0, j))

    def _named_parent(self, st: _TypeState) -> int:
        """The parent our forward names: only one we depend on (the only member we
        heard this seq from), which then keeps forwarding for us (_same_group). A
        member that heard others too ties no parent down (docs/protocol-groups.md)."""
        p = st.parent
        if p is None or any(src != p for src, _ in st.copies):
            return BROADCAST
        return p

    def _forward(self, st: _TypeState, count: bool = True) -> None:
        st.forwarded = True
        # Built at send time: carries the best hop count learnt during the jitter.
        self.send(
            LeaderBeacon(
                self.ctx.node_id,
                BROADCAST,
                st.gtype,
                st.gid,
                st.leader,
                st.weight,
                st.seq,
                0 if st.role is Role.LEADER else st.hops,
                parent=self._named_parent(st),
            )
        )
        if count:
            self.stats.beacons_forwarded += 1
        else:
            self.stats.beacons_rebutted += 1

    def _on_beacon(self, f: LeaderBeacon, rssi: float, now: float) -> None:
        st = self._types.get(f.group_type)
        if st is None:
            self.stats.beacons_unknown_type += 1
            return
        me = self.ctx.node_id
        if f.leader == me:
            # A member re-broadcasting our own beacon, heard directly: a member
            # neighbour (whatever its hops), hence a handover candidate.
            if st.role is Role.LEADER and f.group_id == st.gid:
                old = st.children.get(f.src)
                count = 0 if old is None else old[1]
                st.children[f.src] = (now, count, self._link_rssi(f.src, rssi))
            return
        if f.tentative:
            self._on_tentative(st, f, now)
            return
        self._note_nearby(st, f, rssi, now)
        role = st.role
        if role is Role.WAITING:
            self._adopt(st, f, rssi, now)
        elif role is Role.MEMBER:
            if f.group_id == st.gid:
                self._same_group(st, f, rssi, now)
            elif heavier(f.weight, f.group_id, st.weight, st.gid):
                self._leave(st, now, LeaveReason.SWITCHED, into=f.group_id)
                self._adopt(st, f, rssi, now)
            else:
                self._rebut(st, now)
        elif role is Role.LEADER:
            if f.group_id == st.gid:
                # Another leader with our id: a failover claim, an id clash or a
                # duplicated handover. The larger (weight, leader node) keeps it;
                # the winner's next beacon outnumbers the loser's seq.
                if (f.weight, f.leader) > (st.weight, me):
                    self._yield(st, f, rssi, now)
                else:
                    if seq_newer(f.seq, st.seq):
                        st.seq = f.seq
                    self._rebut(st, now)
            elif heavier(f.weight, f.group_id, st.weight, st.gid):
                self._yield(st, f, rssi, now)
            else:
                self._rebut(st, now)

    def _rebut(self, st: _TypeState, now: float) -> None:
        """A lighter contender (another group of our type, or a lighter leader of
        our id) is in range: re-send our current beacon soon, at most twice a beacon
        period, so that it yields within a flood rather than a beacon period."""
        if st.role is Role.LEADER:
            self._unsettle(st)  # a contender in range: beacon at the base period
        if now - st.rebutted < 0.5 * self.ctx.config.beacon_period:
            return
        if st.role is Role.MEMBER and now - st.last_beacon > 1.25 * self._gap(st):
            return  # our own news is stale: do not hold a new group back with it
        st.rebutted = now
        name = ("rebut", st.gtype)
        if name not in self.timers:
            self.timers.set(name, now + self.ctx.rng.uniform(0, self.ctx.config.forward_jitter))

    def _note_nearby(self, st: _TypeState, f: LeaderBeacon, rssi: float, now: float) -> None:
        h = st.nearby.get(f.group_id)
        if h is None or seq_newer(f.seq, h.seq) or h.leader != f.leader:
            st.nearby[f.group_id] = _Heard(f.leader, f.weight, f.seq, f.hops, f.src, now, rssi)
        elif f.seq == h.seq and (f.hops, -rssi) < (h.hops, -h.rssi):
            h.hops, h.src, h.t, h.rssi = f.hops, f.src, now, rssi

    def _same_group(self, st: _TypeState, f: LeaderBeacon, rssi: float, now: float) -> None:
        lr = self._link_rssi(f.src, rssi)
        hops = min(f.hops + 1, MAX_HOPS)
        if f.src == f.leader == st.leader:
            st.leader_direct = now
        # Beacons of one id are ordered by (seq, weight, leader): a newer seq, or
        # the same seq from a heavier claimant (two members took over together).
        newer = seq_newer(f.seq, st.seq) or (
            f.seq == st.seq and f.leader != st.leader
            and (f.weight, f.leader) > (st.weight, st.leader)
        )  # fmt: skip
        if not newer and f.leader != st.leader:
            return  # a stale beacon, or a lighter claimant of our id: not our tree
        if f.parent == self.ctx.node_id:
            # A child took the beacon from us: forward the next seqs for it, for
            # as long as it would wait for one before giving the leader up (a
            # copy or two lost on the way must not starve it). It names us again
            # at each forward while we are all it hears; a child that stops (it
            # left, took another parent, or hears other members) ages out.
            st.child_until = max(st.child_until, now + self._member_timeout(st))
        st.upstream[f.src] = _Up(f.seq, f.hops, now, lr)
        if newer:
            # The first copy of a new seq sets the parent ...
            if f.leader != st.leader:
                st.leader_direct = now if f.src == f.leader else -math.inf
                st.gap = 0.0  # another leader (a claimant): its pace is not known yet
            else:
                # The pace of the leader's beacons (a settled leader slows down,
                # at most doubling its interval per beacon: a timeout of 3.5 gaps
                # seen still covers the next one, a lost beacon too).
                steps = (f.seq - st.seq) & 0xFFFF
                base = self.ctx.config.beacon_period
                seen = (now - st.last_beacon) / max(1, steps)
                st.gap = min(max(seen, base), base * self._max_factor())
            st.leader_ok = now
            self._clear_suspicion(st)
            st.seq, st.leader, st.weight = f.seq, f.leader, f.weight
            st.patience = False
            st.hops = hops
            st.parent, st.parent_rssi = f.src, lr
            st.forwarded = False
            st.copies, st.must_forward = [], False
            st.last_beacon = now
            self.timers.set(("lost", st.gtype), now + self._member_timeout(st))
            self._schedule_forward(st, now)
        elif f.seq == st.seq and f.src != st.parent:
            if not st.forwarded and len(st.copies) < MAX_COPIES:
                st.copies.append((f.src, f.hops))
            # ... a later copy replaces it if better by _link_key (good links
            # first, then fewest hops); once our hop count is on the air it may
            # only stay or shrink (loop freedom, docs/protocol-groups.md).
            new = self._link_key(st, f.src, hops, lr)
            cur = self._link_key(st, st.parent or 0, st.hops, st.parent_rssi)
            if new < cur and (not st.forwarded or hops <= st.hops):
                st.hops = hops
                st.parent, st.parent_rssi = f.src, lr

    def _yield(self, st: _TypeState, f: LeaderBeacon, rssi: float, now: float) -> None:
        old = st.gid
        self.ctx.emit(LeaderYielded(self.ctx.node_id, st.gtype, old, f.group_id, now))
        if f.group_id != old:
            self._report(st, now, GroupStatus.GONE, successor=f.group_id)
        self._leave(st, now, LeaveReason.YIELDED, into=f.group_id)
        self._adopt(st, f, rssi, now)

    # ----------------------------------------------------------------- handover

    def _start_handover(self, st: _TypeState, now: float) -> None:
        fresh_for = 1.5 * self.ctx.config.beacon_period
        ttl = self._timeout()
        floor = self.ctx.config.group_link_rssi_floor
        ranked = sorted(
            (
                (now - t <= fresh_for, count, rssi >= floor, t, n)
                for n, (t, count, rssi) in st.children.items()
                if now - t <= ttl
            ),
            reverse=True,
        )
        st.candidates = [n for *_, n in ranked]
        self.timers.cancel(("beacon", st.gtype))
        st.role = Role.HANDING_OVER
        self._next_candidate(st, now)

    def _next_candidate(self, st: _TypeState, now: float) -> None:
        self.timers.cancel(("handover", st.gtype))
        if not st.candidates:
            # Nobody to hand over to: the group is gone; members will elect a new one.
            self._report(st, now, GroupStatus.GONE)
            self._leave(st, now, LeaveReason.CONDITION)
            return
        n = st.candidates.pop(0)
        st.handover_to = n
        st.handed = (st.gid, st.seq)
        self.stats.handovers_sent += 1
        self.send(Handover(self.ctx.node_id, n, st.gtype, st.gid, st.weight, st.seq))

    def _on_handover(self, f: Handover, now: float) -> None:
        st = self._types.get(f.group_type)
        if st is not None and st.handed == (f.group_id, f.seq):
            # Our own Handover sent back: the candidate cannot take the group.
            if st.role is Role.HANDING_OVER and f.src == st.handover_to:
                self.stats.handovers_failed += 1
                self._next_candidate(st, now)
            return  # else a late refusal of a candidate we gave up on: ignore
        if st is None or not self._can_take(st, f, now):
            self.stats.handovers_refused += 1
            echo = (f.src, f.group_type, f.group_id, f.seq)
            if echo != self._echoed:
                # Tell the leaving leader at once, once (a lost refusal only costs
                # the group its id: members time out and elect a new one).
                self._echoed = echo
                self.send(
                    Handover(self.ctx.node_id, f.src, f.group_type, f.group_id, f.weight, f.seq)
                )
            return
        if st.role is Role.LEADER:
            return  # a duplicate of a handover we already took
        seq = st.seq if st.role is Role.MEMBER and seq_newer(st.seq, f.seq) else f.seq
        weight = max(f.weight, st.weight) if st.role is Role.MEMBER else f.weight
        if st.role is Role.WAITING:
            self.timers.cancel(("create", st.gtype))
        self.stats.handovers_accepted += 1
        self._become_leader(st, f.group_id, weight, seq, now, ElectionCause.HANDOVER)

    def _can_take(self, st: _TypeState, f: Handover, now: float) -> bool:
        if st.role is Role.LEADER:
            return st.gid == f.group_id
        if st.role is Role.MEMBER:
            return st.gid == f.group_id and self._qualifies(st, True, now)
        if st.role in (Role.IDLE, Role.WAITING):
            return self._qualifies(st, False, now)
        return False

    # ----------------------------------------------------------------- reports

    def _report(self, st: _TypeState, now: float, status: GroupStatus, successor: int = 0) -> None:
        report = GroupReport(
            st.gtype,
            st.gid,
            self.ctx.node_id,
            min(st.weight, MAX_WEIGHT),
            min(st.readings, 0xFFFF),
            status,
            successor or (st.split_from if status is GroupStatus.ALIVE else 0),
        )
        if not self.collection.submit(report, now):
            self.stats.reports_refused += 1
