"""TimerSet: the named deadlines of one sans-IO component.

Components ask for timers (``set``), the mote asks the set for its earliest
deadline, and ``due(now)`` pops the names whose time has come, in time order.

The earliest deadline is cached (kept exact by ``set`` when it can be, else
recomputed on the next ask), so ``next_deadline`` and a ``due`` with nothing
due cost O(1): the mote asks both far more often than timers change. A
:class:`TimerWatch` shared by the sets of one mote is marked on every change,
so the mote can cache its own earliest deadline too.
"""

from __future__ import annotations

from collections.abc import Hashable


class TimerWatch:
    """Marked (``changed = True``) by every change of the sets watching it."""

    __slots__ = ("changed",)

    def __init__(self) -> None:
        self.changed = True


class TimerSet:
    __slots__ = ("_deadlines", "_min", "_stale", "_watch")

    def __init__(self) -> None:
        self._deadlines: dict[Hashable, float] = {}
        self._min: float | None = None  # the earliest deadline, when not _stale
        self._stale = False
        self._watch = TimerWatch()

    def watch(self, w: TimerWatch) -> None:
        """Mark ``w`` (instead of a private watch) on every later change."""
        self._watch = w
        w.changed = True

    def set(self, name: Hashable, when: float) -> None:
        self._watch.changed = True
        d = self._deadlines
        old = d.get(name)
        d[name] = when
        if self._stale:
            return
        m = self._min
        if m is None or when <= m:
            self._min = when
        elif old is not None and old <= m:
            self._stale = True  # the earliest timer moved later

    def cancel(self, name: Hashable) -> None:
        old = self._deadlines.pop(name, None)
        if old is None:
            return
        self._watch.changed = True
        if not self._stale and self._min is not None and old <= self._min:
            self._stale = True

    def get(self, name: Hashable) -> float | None:
        return self._deadlines.get(name)

    def __contains__(self, name: Hashable) -> bool:
        return name in self._deadlines

    def next_deadline(self) -> float | None:
        if self._stale:
            self._min = min(self._deadlines.values(), default=None)
            self._stale = False
        return self._min

    def due(self, now: float) -> list[Hashable]:
        """Remove and return the names due at ``now``, earliest first (equal
        deadlines in the order they were first set)."""
        if self._stale:  # next_deadline(), inlined: due() runs for every component
            self._min = min(self._deadlines.values(), default=None)
            self._stale = False
        m = self._min
        if m is None or m > now:
            return []
        d = self._deadlines
        names = [n for n, t in d.items() if t <= now]
        if len(names) > 1:
            names.sort(key=d.__getitem__)
        for n in names:
            del d[n]
        self._stale = True
        self._watch.changed = True
        return names
