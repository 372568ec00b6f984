"""The virtual clock's calendar queue gives exactly a heap's (time, push order)."""

from __future__ import annotations

import heapq
import random

import pytest

from awaremw.world.timerq import TimerQueue


@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize("slots_per_s", [1.0, 256.0, 1e6])
def test_same_order_as_a_heap(seed: int, slots_per_s: float) -> None:
    """Pushes at, before and after the current time (ties, the same slot, far
    slots) interleaved with pops up to moving limits: the same events in the
    same order as a binary heap of (time, seq)."""
    rng = random.Random(seed)
    q = TimerQueue(slots_per_s)
    heap: list[tuple[float, int, int, object, object]] = []
    seq = 0
    now = 0.0
    got: list[object] = []
    want: list[object] = []
    for step in range(4000):
        r = rng.random()
        if r < 0.55:
            # Mostly near the present (radio events, zero-delay timers), some ties,
            # some far ahead (timers), a few before now (an earlier limit's leftovers).
            t = rng.choice(
                [
                    now,
                    now + rng.random() * 0.004,
                    now + rng.random() * 3.0,
                    now + 100 * rng.random(),
                    round(now + rng.random(), 2),
                    max(0.0, now - rng.random() * 0.01),
                ]
            )
            seq += 1
            q.push(t, step % 6, None, step)
            heapq.heappush(heap, (t, seq, step % 6, None, step))
        else:
            limit = now + rng.random() * 0.05 * rng.choice([0, 1, 10])
            while (e := q.pop_until(limit)) is not None:
                got.append((e[0], e[4]))
                now = max(now, e[0])
            while heap and heap[0][0] <= limit:
                w = heapq.heappop(heap)
                want.append((w[0], w[4]))
            now = max(now, limit)
        assert len(q) == len(heap)
        nt = q.next_time()
        assert nt == (heap[0][0] if heap else None)
    while (e := q.pop_until(float("inf"))) is not None:
        got.append((e[0], e[4]))
    want.extend((w[0], w[4]) for w in sorted(heap))
    assert got == want
    assert len(q) == 0 and q.next_time() is None


def test_bad_width() -> None:
    with pytest.raises(ValueError, match="positive"):
        TimerQueue(0.0)
