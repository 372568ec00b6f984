"""Groups: the component the mote holds -- it keeps each group type's
:class:`~.standing.Standing` and routes frames, link results and timers to the
parts (the package's docstring lists them).
"""

from __future__ import annotations

from collections.abc import Callable

from awaremw.protocol.collection import Collection
from awaremw.protocol.component import Component, MoteContext
from awaremw.protocol.events import GroupTypeRefused, LeaveReason
from awaremw.protocol.frames import (
    ANY_GROUP_TYPE,
    Frame,
    GroupStatus,
    GroupTypeDef,
    Handover,
    ItemBody,
    LeaderBeacon,
)
from awaremw.protocol.groups.conditions import Conditions
from awaremw.protocol.groups.election import Election
from awaremw.protocol.groups.flood import Flood
from awaremw.protocol.groups.handover import Handovers
from awaremw.protocol.groups.kit import Kit
from awaremw.protocol.groups.lineage import Lineage
from awaremw.protocol.groups.liveness import Liveness
from awaremw.protocol.groups.merge import Merge
from awaremw.protocol.groups.pace import Pace
from awaremw.protocol.groups.roles import Parts, Roles
from awaremw.protocol.groups.standing import Standing
from awaremw.protocol.groups.tree import GroupTree
from awaremw.protocol.groups.values import GroupStats, Membership, Role, Tick


class Groups(Component):
    """Group management of one mote (all group types)."""

    def __init__(self, ctx: MoteContext, collection: Collection) -> None:
        super().__init__(ctx)
        self.collection = collection
        self.stats = GroupStats()
        self._types: dict[int, Standing] = {}
        # Called with ``now`` when this mote enters a group (as member or leader):
        # the channels start their epochs then (a mote in no group keeps no epoch timer).
        self.on_enter: Callable[[float], None] | None = None
        kit = Kit(ctx, self.timers, self.stats, self.send)
        conditions = Conditions(kit)
        lineage = Lineage(kit)
        pace = Pace(kit, lineage, collection)
        tree = GroupTree(kit)
        flood = Flood(kit, tree, pace)
        election = Election(kit, lineage, flood)
        liveness = Liveness(kit, (conditions, pace, tree, flood), lineage, election)
        handovers = Handovers(kit, conditions, pace)
        parts = Parts(conditions, lineage, pace, tree, flood, election, liveness, handovers)
        self._conditions, self._pace, self._tree, self._flood = conditions, pace, tree, flood
        self._election, self._liveness, self._handovers = election, liveness, handovers
        self._roles = Roles(kit, parts, self._entered)
        self._merge = Merge(kit, self._roles, (pace, tree, flood, election, liveness, handovers))

    # ----------------------------------------------------------------- public API

    def define(self, group_type: int, item: ItemBody | None, now: float) -> None:
        """A group type was defined, changed (``item``) or deleted (``None``)."""
        if item is None:
            self._drop_type(group_type, now)
            return
        if not isinstance(item, GroupTypeDef):
            raise TypeError(f"group type {group_type} defined with a {type(item).__name__}")
        s = self._types.get(group_type)
        if s is None:
            reason = None
            if not 0 <= group_type < ANY_GROUP_TYPE:
                reason = f"group type {group_type} is not in 0..{ANY_GROUP_TYPE - 1}"
            elif len(self._types) >= self.ctx.config.max_group_types:
                reason = f"more than {self.ctx.config.max_group_types} group types"
            if reason is not None:
                self.stats.types_refused += 1
                self.ctx.emit(GroupTypeRefused(self.ctx.node_id, group_type, reason))
                return
            s = self._types[group_type] = Standing(group_type, item)
            self._roles.add(group_type)
        else:
            s.redefine(item)
        self._conditions.wake(now)
        self._roles.check(s, now)  # a changed definition takes effect at once
        self._conditions.start(now)

    def membership(self, group_type: int) -> Membership | None:
        s = self._types.get(group_type)
        if s is None or s.role not in (Role.MEMBER, Role.LEADER):
            return None
        leader = s.role is Role.LEADER
        parent, hops = self._tree.route(group_type)
        return Membership(
            group_type=s.gtype,
            group_id=s.gid,
            leader=self.ctx.node_id if leader else s.leader,
            is_leader=leader,
            parent=None if leader else parent,
            hops=0 if leader else hops,
            weight=s.weight,
        )

    def memberships(self) -> dict[int, Membership]:
        out: dict[int, Membership] = {}
        for g, s in self._types.items():
            if s.role is Role.MEMBER or s.role is Role.LEADER:  # else membership() is None
                m = self.membership(g)
                if m is not None:
                    out[g] = m
        return out

    def role(self, group_type: int) -> Role | None:
        s = self._types.get(group_type)
        return None if s is None else s.role

    def defined_types(self) -> dict[int, GroupTypeDef]:
        return {g: s.defn for g, s in self._types.items()}

    def add_weight(self, group_type: int, n: int) -> None:
        """The leader aggregated ``n`` readings of one epoch: its group gets heavier."""
        s = self._types.get(group_type)
        if s is None or s.role is not Role.LEADER or n <= 0:
            return
        self._pace.add_weight(s, n)

    def note_child(self, group_type: int, node: int, now: float, count: int = 0) -> None:
        """Channel data (``count`` readings) came from ``node``: a handover candidate
        of a leader; for a member, proof that it is a parent in the group tree."""
        s = self._types.get(group_type)
        if s is not None and s.role is Role.MEMBER:
            # A partial comes every epoch: proof for one beacon interval.
            self._tree.note_child(group_type, now + self._pace.gap(group_type))
        elif s is not None and s.role is Role.LEADER:
            self._handovers.note_child(group_type, node, now, count)

    def upstream(self, group_type: int, now: float) -> list[int]:
        """The parent, then the other neighbours that forwarded the current beacon
        with fewer hops than ours (fewest hops, then strongest first)."""
        s = self._types.get(group_type)
        if s is None or s.role is not Role.MEMBER:
            return []
        return self._tree.upstream(s)

    def parent_failed(self, group_type: int, node: int, now: float) -> None:
        """A unicast to ``node`` failed after the link layer's retries: route the next
        partials through another neighbour of the current beacon, if there is one
        (the next beacon may choose ``node`` again only if nobody else is as close)."""
        s = self._types.get(group_type)
        if s is None or s.role is not Role.MEMBER:
            return
        if node == s.leader:
            self._liveness.suspect(s, now)  # before the tree moves: a probe names the parent
        self._tree.failed(s, node, now)

    def parent_acked(self, group_type: int, node: int, now: float) -> None:
        """A unicast to ``node`` was acknowledged: if it is our leader, it lives."""
        s = self._types.get(group_type)
        if s is not None and s.role is Role.MEMBER:
            self._liveness.acked(s, node, now)

    # ----------------------------------------------------------------- Component hooks

    def app_changed(self, now: float) -> None:
        """The application was sent a command: its readings may change (a sample
        period, say), so a parked mote checks again from its next regular check."""
        self._conditions.wake(now)

    def heard_again(self, node: int, now: float) -> None:
        """The mote hears ``node`` after a silence (its first frame, or the first after
        the RSSI TTL): an ``rssi:<node>`` condition may hold again."""
        self._conditions.heard_again(node, now)

    def on_frame(self, frame: Frame, rssi_dbm: float, now: float) -> None:
        self._conditions.wake(now)  # if parked: the frame may fill tables that the checks purge
        if isinstance(frame, LeaderBeacon):
            s = self._types.get(frame.group_type)
            if s is None:
                self.stats.beacons_unknown_type += 1
            else:
                self._merge.on_beacon(s, frame, rssi_dbm, now)
        elif isinstance(frame, Handover):
            s = self._types.get(frame.group_type)
            self._handovers.on_frame(s, frame, now, self._roles)

    def on_timer(self, name: object, now: float) -> None:
        if name == Tick.CHECK:
            self._check_all(now)
            return
        assert isinstance(name, tuple)
        tick, g = name
        s = self._types.get(g)
        if s is not None:
            self._on_type_timer(tick, s, now)

    def on_link_result(self, frame: Frame, acked: bool, now: float) -> None:
        if isinstance(frame, LeaderBeacon):  # a probe of a settled leader (Liveness)
            s = self._types.get(frame.group_type)
            if s is not None and s.gid == frame.group_id:
                (self.parent_acked if acked else self.parent_failed)(s.gtype, frame.dst, now)
        elif isinstance(frame, Handover):
            s = self._types.get(frame.group_type)
            if s is not None:
                self._handovers.on_link_result(s, frame, acked, now, self._roles)

    # ----------------------------------------------------------------- routing

    def _on_type_timer(self, tick: object, s: Standing, now: float) -> None:
        role = s.role
        if tick == Tick.BEACON and role is Role.LEADER:
            self._pace.beacon(s, now)
        elif tick == Tick.FWD and role is Role.MEMBER:
            self._flood.on_timer(s, now)
        elif tick == Tick.LOST and role is Role.MEMBER:
            self._liveness.on_lost(s, now, self._roles)
        elif tick == Tick.CLAIM and role is Role.MEMBER:
            self._liveness.on_claim(s, now, self._roles)
        elif tick == Tick.REBUT and role in (Role.MEMBER, Role.LEADER):
            self._flood.forward(s, count=False)
        elif tick == Tick.RELAY and role in (Role.IDLE, Role.WAITING):
            self._election.on_relay(s)
        elif tick == Tick.ANNOUNCE and role is Role.WAITING:
            self._election.on_announce(s)
        elif tick == Tick.CREATE and role is Role.WAITING:
            self._election.on_create(s, now, self._roles)
        elif tick == Tick.CONFIRM and role is Role.WAITING:
            self._election.on_confirm(s, now, self._roles)
        elif tick == Tick.HANDOVER and role is Role.HANDING_OVER:
            self._handovers.on_timer(s, now, self._roles)

    def _entered(self, now: float) -> None:
        if self.on_enter is not None:
            self.on_enter(now)

    def _check_all(self, now: float) -> None:
        """The membership checks of every type, the purge of their tables, and the
        next check (or parked: Conditions)."""
        self._conditions.checking()
        roles = self._roles
        for s in list(self._types.values()):
            roles.check(s, now)
            roles.purge(s, now)
        if not self._types:
            return
        quiet = all(
            s.role is Role.IDLE and roles.remembers_nothing(s.gtype) for s in self._types.values()
        )
        self._conditions.checked([s.defn for s in self._types.values()] if quiet else None, now)

    def _drop_type(self, group_type: int, now: float) -> None:
        s = self._types.pop(group_type, None)
        if s is None:
            return
        if s.role in (Role.LEADER, Role.HANDING_OVER):
            self._pace.report(s, now, GroupStatus.GONE)
        if s.role in (Role.MEMBER, Role.LEADER, Role.HANDING_OVER):
            self._roles.leave(s, now, LeaveReason.DELETED)
        self._roles.drop(group_type)
        if not self._types:
            self._conditions.stop()
