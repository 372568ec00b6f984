"""Trickle timer on a fake clock: doubling, suppression, reset (RFC 6206 semantics)."""

from __future__ import annotations

import random

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from awaremw.protocol.trickle import Trickle


def run_until(t: Trickle, end: float) -> list[float]:
    """Drive ``t`` on a fake clock up to ``end``; return the transmission times."""
    sent: list[float] = []
    while (d := t.next_deadline()) is not None and d <= end:
        if t.handle_timer(d):
            sent.append(d)
    return sent


def test_rejects_bad_parameters() -> None:
    rng = random.Random(0)
    with pytest.raises(ValueError):
        Trickle(0.0, 1.0, 1, rng)
    with pytest.raises(ValueError):
        Trickle(2.0, 1.0, 1, rng)
    with pytest.raises(ValueError):
        Trickle(1.0, 2.0, 0, rng)


def test_not_running_until_started() -> None:
    t = Trickle(1.0, 8.0, 1, random.Random(0))
    assert t.next_deadline() is None and not t.running
    assert t.handle_timer(100.0) is False
    t.start(10.0)
    assert t.interval == 1.0
    d = t.next_deadline()
    assert d is not None and 10.5 <= d < 11.0


def test_interval_doubles_up_to_tau_h_with_one_tx_per_interval() -> None:
    t = Trickle(1.0, 8.0, 1, random.Random(1))
    t.start(0.0)
    intervals: list[float] = []
    sent: list[float] = []
    # Interval boundaries: 0,1,3,7,15,23,31 (1,2,4,8,8,8 ...)
    while (d := t.next_deadline()) is not None and d < 47.0:
        i = t.interval
        assert i is not None
        if t.handle_timer(d):
            sent.append(d)
            intervals.append(i)
    assert intervals == [1.0, 2.0, 4.0, 8.0, 8.0, 8.0, 8.0, 8.0]
    starts = [0.0, 1.0, 3.0, 7.0, 15.0, 23.0, 31.0, 39.0]
    for s, i, x in zip(starts, intervals, sent, strict=True):
        assert s + i / 2 <= x < s + i  # transmission point in [I/2, I)


def test_suppression_when_k_consistent_heard() -> None:
    t = Trickle(1.0, 1.0, 2, random.Random(2))  # fixed 1 s intervals
    t.start(0.0)
    t.hear_consistent()
    t.hear_consistent()  # c = 2 = k: this interval stays silent
    assert run_until(t, 0.99) == []
    # counter resets each interval: the next one transmits
    assert len(run_until(t, 1.99)) == 1
    t.hear_consistent()  # c = 1 < k: still transmits
    assert len(run_until(t, 2.99)) == 1


def test_reset_returns_to_tau_l_only_when_larger() -> None:
    t = Trickle(1.0, 64.0, 1, random.Random(3))
    t.start(0.0)
    run_until(t, 40.0)
    assert t.interval is not None and t.interval > 1.0
    t.reset(40.0)
    assert t.interval == 1.0
    d = t.next_deadline()
    assert d is not None and 40.5 <= d < 41.0
    # Another inconsistency while already at tau_l: nothing changes.
    t.reset(40.2)
    assert t.next_deadline() == d and t.interval_end == 41.0


def test_reset_starts_a_stopped_timer() -> None:
    t = Trickle(0.5, 4.0, 1, random.Random(4))
    t.reset(3.0)
    assert t.running and t.interval == 0.5
    t.stop()
    assert t.next_deadline() is None


def test_early_call_changes_nothing_late_call_still_transmits() -> None:
    t = Trickle(1.0, 4.0, 1, random.Random(5))
    t.start(0.0)
    d = t.next_deadline()
    assert d is not None
    assert t.handle_timer(d - 0.1) is False and t.next_deadline() == d
    # Way past the end of the interval: report the transmission, open a new one.
    assert t.handle_timer(100.0) is True
    assert t.interval == 2.0
    end = t.interval_end
    assert end is not None and end > 100.0


@settings(max_examples=50, deadline=None)
@given(
    seed=st.integers(0, 2**32),
    tau_l=st.floats(0.1, 2.0),
    doublings=st.integers(0, 6),
    k=st.integers(1, 3),
)
def test_at_most_one_tx_per_interval(seed: int, tau_l: float, doublings: int, k: int) -> None:
    t = Trickle(tau_l, tau_l * 2**doublings, k, random.Random(seed))
    t.start(0.0)
    horizon = tau_l * 2 ** (doublings + 3)
    windows: list[tuple[float, float]] = []
    sent: list[float] = []
    while (d := t.next_deadline()) is not None and d <= horizon:
        start = t.interval_end
        i = t.interval
        assert start is not None and i is not None
        if t.handle_timer(d):
            sent.append(d)
            windows.append((start - i, start))
    assert len(set(windows)) == len(windows)  # never two transmissions in one interval
    for (lo, hi), x in zip(windows, sent, strict=True):
        assert lo + (hi - lo) / 2 <= x <= hi
