"""TimerSet: the named deadlines of one sans-IO component.

Components ask for timers (``set``), the mote asks the set for its earliest
deadline, and ``due(now)`` pops the names whose time has come, in time order.

The earliest deadline is cached (``soonest``: kept exact by ``set`` when it
can be, else a lower bound recomputed on the next ask), so ``next_deadline``
and a ``due`` with nothing due cost O(1): the mote asks both far more often than timers change. A
:class:`TimerWatch` shared by the sets of one mote is marked on every change,
so the mote can cache its own earliest deadline too.
"""

from __future__ import annotations

import math
from collections.abc import Hashable

_INF = math.inf


class TimerWatch:
    """Marked (``changed = True``) by every change of the sets watching it, and
    ``grew = True`` when one of them gets its first timer ever (``armed``).
    ``queued``: the mote's own flag, True when a frame or event may be waiting
    for its driver (set by :class:`~awaremw.protocol.component.MoteContext`), so
    that the mote says it is idle from this one object."""

    __slots__ = ("changed", "grew", "queued")

    def __init__(self) -> None:
        self.changed = True
        self.grew = True
        self.queued = False


class TimerSet:
    """Named deadlines. ``soonest`` is a lower bound of the earliest deadline
    (``inf`` when there is none), exact unless ``stale`` (a change moved the
    earliest one later; :meth:`next_deadline` refreshes it); a caller may skip
    the set when ``soonest > now`` (nothing is due) without a call. Both are
    read-only outside this class."""

    __slots__ = ("_deadlines", "_watch", "armed", "soonest", "stale")

    def __init__(self) -> None:
        self._deadlines: dict[Hashable, float] = {}
        self.soonest = _INF  # lower bound of the earliest deadline; exact unless stale
        self.stale = False
        self.armed = False  # ever set a timer (a set never armed is empty: skip it)
        self._watch = TimerWatch()

    def watch(self, w: TimerWatch) -> None:
        """Mark ``w`` (instead of a private watch) on every later change."""
        self._watch = w
        w.changed = True
        w.grew = True

    def set(self, name: Hashable, when: float) -> None:
        self._watch.changed = True
        if not self.armed:
            self.armed = True
            self._watch.grew = True
        d = self._deadlines
        old = d.get(name)
        d[name] = when
        m = self.soonest
        if when <= m:
            self.soonest = when  # a lower bound still; exact if it was
        elif old is not None and old <= m:
            self.stale = True  # the earliest timer moved later

    def cancel(self, name: Hashable) -> None:
        old = self._deadlines.pop(name, None)
        if old is None:
            return
        self._watch.changed = True
        if old <= self.soonest:
            self.stale = True

    def get(self, name: Hashable) -> float | None:
        return self._deadlines.get(name)

    def __contains__(self, name: Hashable) -> bool:
        return name in self._deadlines

    def __len__(self) -> int:
        return len(self._deadlines)

    def next_deadline(self) -> float | None:
        if self.stale:
            self.soonest = min(self._deadlines.values(), default=_INF)
            self.stale = False
        return self.soonest if self._deadlines else None

    def due(self, now: float) -> list[Hashable]:
        """Remove and return the names due at ``now``, earliest first (equal
        deadlines in the order they were first set)."""
        if self.soonest > now:  # a lower bound: nothing is due
            return []
        # One pass: the due names and the earliest of the others (the new soonest,
        # exact, so the mote's next_deadline needs no scan of this set).
        d = self._deadlines
        names: list[Hashable] = []
        rest = _INF
        for n, t in d.items():
            if t <= now:
                names.append(n)
            elif t < rest:
                rest = t
        self.soonest = rest
        self.stale = False
        if not names:  # soonest was a stale lower bound
            return names
        if len(names) > 1:
            names.sort(key=d.__getitem__)
        for n in names:
            del d[n]
        self._watch.changed = True
        return names
