"""Conditions: whether a mote qualifies for a group type, and the parking of
its membership checks when nothing can change (the ``check`` timer's owner).

A mote out of every group, with no group heard lately (nothing to purge), whose
application rules a condition of every type out until a time
(:class:`~awaremw.protocol.attributes.Bounds`), makes the same decision, "not
in", at every check until then: it parks its checks (most motes of a large
field, far from anything a group tracks). An ``rssi:<node>`` condition is ruled
out until ``node`` is heard again when it is not heard now (never, or not
within the RSSI TTL). What could change that wakes it: a group frame, a
definition, a command to the application, a frame from a node it awaits
(:meth:`Conditions.heard_again`).
"""

from __future__ import annotations

import math
from collections.abc import Iterable

from awaremw.protocol.attributes import is_rssi
from awaremw.protocol.component import MoteContext
from awaremw.protocol.frames import NODE_MASK, GroupTypeDef
from awaremw.protocol.groups.kit import Kit
from awaremw.protocol.groups.values import (
    PARK_PERIODS,
    Tick,
    condition_holds,
    condition_may_hold,
)


def unheard(ctx: MoteContext, attr: int, now: float) -> bool:
    """Whether an ``rssi:<node>`` reading is missing now (the node never heard, or not
    within the RSSI TTL): no condition on it holds until the node is heard again."""
    return ctx.read(attr, now) is None


class Conditions:
    """Qualifying (with hysteresis for members) and the schedule of the checks."""

    def __init__(self, kit: Kit) -> None:
        self._kit = kit
        # Parked: the time of the last membership check run; the skipped checks
        # were due at it + k * check_period. None: not parked.
        self._parked_at: float | None = None
        # Parked: the nodes whose next frame can end it (an rssi:<node> condition
        # that no reading can meet until that node is heard again).
        self._awaiting: frozenset[int] = frozenset()

    def qualifies(self, defn: GroupTypeDef, relaxed: bool, now: float) -> bool:
        relax = defn.hysteresis if relaxed else 0.0
        ctx = self._kit.ctx
        for c in defn.conditions:
            # A reading certain to fail the condition is not taken (most motes,
            # far from what a group tracks, most of the time): the same answer.
            b = ctx.read_bounds(c.attr, now)
            if b is not None and not condition_may_hold(c, b.lo, b.hi, relax):
                return False
            if not condition_holds(c, ctx.read(c.attr, now), relax):
                return False
        return True

    def start(self, now: float) -> None:
        """The first type was defined: checks every period from a random phase."""
        kit = self._kit
        if Tick.CHECK not in kit.timers:
            kit.timers.set(Tick.CHECK, now + kit.ctx.rng.uniform(0, kit.ctx.config.check_period))

    def stop(self) -> None:
        """No type is defined any more: no checks."""
        self._kit.timers.cancel(Tick.CHECK)
        self._parked_at = None

    def checking(self) -> None:
        """The check is due (a parked mote's horizon came, or the next period)."""
        self._parked_at = None

    def checked(self, defs: Iterable[GroupTypeDef] | None, now: float) -> None:
        """Every type was checked at ``now``: the next check, one period on, or
        parked. ``defs``: the definitions when every type is idle with nothing
        to purge (None: the checks may change something)."""
        kit = self._kit
        nxt = now + kit.ctx.config.check_period
        quiet = now if defs is None else self._quiet_until(defs, now)
        if quiet <= nxt:
            kit.timers.set(Tick.CHECK, nxt)
            return
        self._parked_at = now
        kit.stats.checks_parked += 1
        # At most PARK_PERIODS at a time (then one check, "not in" again, and
        # park anew): finding the schedule's next instant walks its periods.
        horizon = now + PARK_PERIODS * kit.ctx.config.check_period
        kit.timers.set(Tick.CHECK, self._regular_check_after(min(quiet, horizon)))

    def wake(self, now: float) -> None:
        """Unpark: back to a check every period, on the schedule it left."""
        if self._parked_at is None:
            return
        self._kit.timers.set(Tick.CHECK, self._regular_check_after(now))
        self._parked_at = None

    def heard_again(self, node: int, now: float) -> None:
        """The mote hears ``node`` after a silence: an ``rssi:<node>`` condition may
        hold again, so a mote parked on it checks again from its next regular check."""
        if self._parked_at is not None and node in self._awaiting:
            self.wake(now)

    def _quiet_until(self, defs: Iterable[GroupTypeDef], now: float) -> float:
        """Until when the checks of idle types with nothing to purge can change
        nothing (``now``: they may), and the nodes whose frames may end it."""
        ctx = self._kit.ctx
        until = math.inf
        awaiting: set[int] = set()
        for defn in defs:
            ruled_out = now
            for c in defn.conditions:
                if is_rssi(c.attr):
                    if unheard(ctx, c.attr, now):
                        ruled_out = math.inf
                        awaiting.add(c.attr & NODE_MASK)
                    continue
                b = ctx.read_bounds(c.attr, now)
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
        p = self._kit.ctx.config.check_period
        assert self._parked_at is not None
        due = self._parked_at + p
        while due < t:
            due += p
        return due
