"""TimerSet: the named deadlines of one sans-IO component.

Components ask for timers (``set``), the mote asks the set for its earliest
deadline, and ``due(now)`` pops the names whose time has come, in time order.
"""

from __future__ import annotations

from collections.abc import Hashable


class TimerSet:
    __slots__ = ("_deadlines",)

    def __init__(self) -> None:
        self._deadlines: dict[Hashable, float] = {}

    def set(self, name: Hashable, when: float) -> None:
        self._deadlines[name] = when

    def cancel(self, name: Hashable) -> None:
        self._deadlines.pop(name, None)

    def get(self, name: Hashable) -> float | None:
        return self._deadlines.get(name)

    def __contains__(self, name: Hashable) -> bool:
        return name in self._deadlines

    def next_deadline(self) -> float | None:
        return min(self._deadlines.values(), default=None)

    def due(self, now: float) -> list[Hashable]:
        """Remove and return the names due at ``now``, earliest first."""
        names = sorted(
            (n for n, t in self._deadlines.items() if t <= now), key=self._deadlines.__getitem__
        )
        for n in names:
            del self._deadlines[n]
        return names
