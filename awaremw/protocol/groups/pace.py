"""Pace: the leader's beacons and reports, and the beacon interval a member sees.

A leader beacons every ``beacon_period``; settled (a channel's records flow and
nothing changed since the last beacon) it doubles its interval, up to
``beacon_settled_factor`` periods, and anything that unsettles the group brings
it back to the base period. A member measures the interval between its leader's
beacons (``gap``): its timeouts count in gaps seen, not periods
(docs/protocol-groups.md, "Quiet beacons" and "Reports").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from awaremw.protocol.collection import Collection
from awaremw.protocol.frames import BROADCAST, GroupReport, GroupStatus, LeaderBeacon
from awaremw.protocol.groups.kit import Kit
from awaremw.protocol.groups.lineage import Lineage
from awaremw.protocol.groups.standing import Standing
from awaremw.protocol.groups.values import MAX_WEIGHT, Tick


@dataclass(slots=True)
class _PaceState:
    # Leader: its beacon interval now; member: the interval it saw between the
    # leader's beacons (0: none seen yet). See gap().
    gap: float = 0.0
    last_beacon: float = 0.0  # leader: its last beacon; member: the last new seq heard
    beacons: int = 0  # beacons sent as leader of this group
    readings: int = 0  # readings in the leader's latest aggregated epoch
    settled: bool = False  # leader: nothing unsettled the group since the last beacon
    recorded: bool = False  # leader: a channel record was made since the last beacon
    peak: int = 0  # leader: most readings in one record since the beacon before last
    peak_prev: int = 0  # ... of the records between the last two beacons
    dips: int = 0  # leader: records in a row 10 % under the peak
    reported_at: float = -math.inf  # leader: last GroupReport ALIVE


class Pace:
    """The beacon pace of every group type (the ``beacon`` timer's owner)."""

    def __init__(self, kit: Kit, lineage: Lineage, collection: Collection) -> None:
        self._kit = kit
        self._lineage = lineage
        self._collection = collection
        self._at: dict[int, _PaceState] = {}

    def add(self, gtype: int) -> None:
        self._at[gtype] = _PaceState()

    def drop(self, gtype: int) -> None:
        del self._at[gtype]

    def gap(self, gtype: int) -> float:
        """The leader's beacon interval as this mote knows it (the base period
        until a member saw two beacons: a mote that joins a settled group adds
        readings to its records, which unsettles the leader, see add_weight)."""
        gap = self._at[gtype].gap
        return gap if gap > 0 else self._kit.ctx.config.beacon_period

    def member_timeout(self, gtype: int) -> float:
        """No new seq for this long: the leader is lost (in gaps seen, not periods)."""
        return self._kit.ctx.config.leader_timeout_periods * self.gap(gtype)

    def stale(self, gtype: int, now: float) -> bool:
        """A member's news of its group is stale: no new seq for 1.25 gaps."""
        return now - self._at[gtype].last_beacon > 1.25 * self.gap(gtype)

    def follow(self, gtype: int, heard_at: float) -> None:
        """A member from the beacon heard at ``heard_at``: its pace is not seen yet."""
        p = self._at[gtype]
        p.last_beacon = heard_at
        p.gap = 0.0

    def observe(self, gtype: int, same_leader: bool, steps: int, now: float) -> None:
        """A member heard a new seq, ``steps`` after the last one it heard."""
        p = self._at[gtype]
        if not same_leader:
            p.gap = 0.0  # another leader (a claimant): its pace is not known yet
        else:
            # The pace of the leader's beacons (a settled leader slows down,
            # at most doubling its interval per beacon: a timeout of 3.5 gaps
            # seen still covers the next one, a lost beacon too).
            base = self._kit.ctx.config.beacon_period
            seen = (now - p.last_beacon) / max(1, steps)
            p.gap = min(max(seen, base), base * self._kit.max_factor())
        p.last_beacon = now

    def lead(self, gtype: int) -> None:
        """A new leader: base pace, no records yet, a report with its first beacon."""
        p = self._at[gtype]
        p.beacons = 0
        p.gap, p.settled, p.recorded = 0.0, False, False
        p.peak = p.peak_prev = 0
        p.reported_at = -math.inf
        p.readings = 0

    def add_weight(self, s: Standing, n: int) -> None:
        """The leader aggregated ``n`` (> 0) readings of one epoch."""
        p = self._at[s.gtype]
        s.gain(n)
        if n > p.peak:
            # More readings than the group gave lately (lost partials only ever
            # make fewer): new members, which need the tree and our pace.
            self.unsettle(s.gtype)
        # Fewer, twice in a row: a subtree's way up is broken (its partials fail
        # and its members know no other parent yet) or members left; a beacon
        # rebuilds the tree. Once is a lost frame: no beacon for that.
        p.dips = p.dips + 1 if n * 10 < p.peak * 9 else 0
        if p.dips >= 2:
            p.dips = 0
            self.unsettle(s.gtype)
        p.peak = max(p.peak, n)
        p.readings = n
        p.recorded = True

    def unsettle(self, gtype: int) -> None:
        """Leader: the group changed; beacon at the base period again (and within one
        base period of the last beacon), so that the tree and members catch up."""
        p = self._at[gtype]
        base = self._kit.ctx.config.beacon_period
        p.settled = False
        if p.gap <= base:
            return
        p.gap = base
        name = (Tick.BEACON, gtype)
        timers = self._kit.timers
        due = timers.get(name)
        if due is not None and due > p.last_beacon + base:
            timers.set(name, p.last_beacon + base)

    def resume(self, gtype: int, now: float) -> None:
        """A leader back from an early handover that nobody took: its next beacon
        when it was due (at once if that passed)."""
        p = self._at[gtype]
        self._kit.timers.set((Tick.BEACON, gtype), max(now, p.last_beacon + self.gap(gtype)))

    def beacon(self, s: Standing, now: float) -> None:
        kit = self._kit
        p = self._at[s.gtype]
        me = kit.ctx.node_id
        seq = s.next_seq()
        kit.send(LeaderBeacon(me, BROADCAST, s.gtype, s.gid, me, s.weight, seq, 0))
        kit.stats.beacons_sent += 1
        p.beacons += 1
        c = kit.ctx.config
        base = c.beacon_period
        if p.gap <= 0:
            p.gap = base
        elif p.settled and p.recorded:
            # Settled: a channel's records flow (the data path detects a dead
            # leader: its children's partials go unacknowledged) and nothing
            # changed since the last beacon. Beacons only refresh the tree.
            p.gap = min(2.0 * p.gap, base * kit.max_factor())
        p.settled, p.recorded = True, False
        # The peak forgets records older than two beacons (members that left).
        p.peak, p.peak_prev = max(p.peak_prev, p.readings), p.readings
        p.last_beacon = now
        # Reports keep their pace in time whatever the beacons' (the gateway
        # expires a group unheard for a few report periods).
        if p.beacons == 1 or now + p.gap > p.reported_at + c.report_every_beacons * base:
            p.reported_at = now
            self.report(s, now, GroupStatus.ALIVE)
        kit.timers.set((Tick.BEACON, s.gtype), now + p.gap)

    def report(self, s: Standing, now: float, status: GroupStatus, successor: int = 0) -> None:
        split = self._lineage.split_from(s.gtype) if status is GroupStatus.ALIVE else 0
        report = GroupReport(
            s.gtype,
            s.gid,
            self._kit.ctx.node_id,
            min(s.weight, MAX_WEIGHT),
            min(self._at[s.gtype].readings, 0xFFFF),
            status,
            successor or split,
        )
        if not self._collection.submit(report, now):
            self._kit.stats.reports_refused += 1
