"""The virtual clock's event queue: a calendar of time slots, O(1) at any size.

Events come out in ``(time, seq)`` order, ``seq`` being the order they were
pushed in -- exactly the order of a binary heap of ``(time, seq, ...)``
tuples, so a run is the same function of its seed whichever queue it uses.

Why not a heap: a heap of one entry per mote (its timer) is ``log2(motes)``
levels deep, and each level is a comparison that reads two tuples and their
time floats scattered over the interpreter's heap. At 10,000 motes those
reads miss the CPU's caches, and a pop cost several times what it did at
1,000 motes (docs/scale.md). Here an event goes to the slot of its time (a
list, appended to), slots are taken in order, and the current slot is sorted
once when it is reached and read front to back: the work per event does not
depend on how many events are queued. Only the numbers of the occupied slots
are kept in a heap (pushed once per slot, not per event).

The slot width suits the virtual driver's events (radio events a few
milliseconds ahead, timers up to a few seconds): about ten events a slot at
1,000 motes.
"""

from __future__ import annotations

import heapq
from bisect import insort

# (time, seq, kind, node, data): the driver's event; seq is the queue's.
Entry = tuple[float, int, int, object, object]

SLOTS_PER_S = 256.0  # slot width 1/256 s (about 3.9 ms)


class TimerQueue:
    """Events by virtual time; ties in push order (see the module)."""

    __slots__ = ("_cur", "_i", "_inv", "_keys", "_n", "_seq", "_slot", "_slots")

    def __init__(self, slots_per_s: float = SLOTS_PER_S) -> None:
        if not slots_per_s > 0:
            raise ValueError(f"slots_per_s must be positive, got {slots_per_s}")
        self._inv = float(slots_per_s)
        self._slots: dict[int, list[Entry]] = {}  # slot number -> its events, unsorted
        self._keys: list[int] = []  # heap of the numbers in _slots
        self._cur: list[Entry] = []  # the current slot, sorted, read from _i on
        self._i = 0
        self._slot = -(1 << 62)  # number of the current slot (none yet)
        self._seq = 0
        self._n = 0  # events queued

    def __len__(self) -> int:
        return self._n

    def push(self, t: float, kind: int, node: object, data: object) -> None:
        """Queue an event at time ``t`` (any time: one before the current slot's
        events comes out before them)."""
        self._seq += 1
        e = (t, self._seq, kind, node, data)
        k = int(t * self._inv)  # monotone in t: slots keep the events' order
        if k <= self._slot:
            # The current slot (or earlier): into its sorted remainder.
            insort(self._cur, e, self._i)
        else:
            lst = self._slots.get(k)
            if lst is None:
                self._slots[k] = [e]
                heapq.heappush(self._keys, k)
            else:
                lst.append(e)
        self._n += 1

    def pop_until(self, limit: float) -> Entry | None:
        """The first event if its time is at most ``limit`` (taken out), else None."""
        i = self._i
        cur = self._cur
        if i == len(cur):
            keys = self._keys
            if not keys:
                return None
            k = heapq.heappop(keys)
            cur = self._slots.pop(k)
            cur.sort()
            self._cur = cur
            self._slot = k
            i = 0
        e = cur[i]
        if e[0] > limit:
            self._i = i
            return None
        self._i = i + 1
        self._n -= 1
        return e

    def next_time(self) -> float | None:
        """Time of the first event (None: empty)."""
        if self._i < len(self._cur):
            return self._cur[self._i][0]
        if not self._keys:
            return None
        return min(e[0] for e in self._slots[self._keys[0]])
