"""TimerSet's cached minimum and TimerWatch agree with a plain dict model."""

from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from awaremw.protocol.timers import TimerSet, TimerWatch

NAMES = st.sampled_from("abcde")
TIMES = st.integers(0, 20).map(float)
OPS = st.lists(
    st.one_of(
        st.tuples(st.just("set"), NAMES, TIMES),
        st.tuples(st.just("cancel"), NAMES, TIMES),
        st.tuples(st.just("due"), NAMES, TIMES),
        st.tuples(st.just("next"), NAMES, TIMES),
    ),
    max_size=60,
)


@settings(max_examples=300, derandomize=True, deadline=None)
@given(OPS)
def test_cached_minimum_matches_the_model(ops: list[tuple[str, str, float]]) -> None:
    ts, model, watch = TimerSet(), dict[str, float](), TimerWatch()
    ts.watch(watch)
    for op, name, t in ops:
        watch.changed = False
        before = dict(model)
        if op == "set":
            ts.set(name, t)
            model[name] = t
        elif op == "cancel":
            ts.cancel(name)
            model.pop(name, None)
        elif op == "due":
            # Earliest first, equal deadlines in the order they were first set.
            want = sorted((n for n, w in model.items() if w <= t), key=model.__getitem__)
            assert ts.due(t) == want
            for n in want:
                del model[n]
        assert ts.next_deadline() == min(model.values(), default=None)
        if model != before or list(model) != list(before):
            assert watch.changed  # every change is seen by the mote's cache
        assert (name in ts) == (name in model) and ts.get(name) == model.get(name)


def test_equal_deadlines_come_out_in_insertion_order() -> None:
    ts = TimerSet()
    for n in ("x", "y", "z"):
        ts.set(n, 5.0)
    ts.set("w", 4.0)
    assert ts.due(3.0) == [] and ts.next_deadline() == 4.0
    assert ts.due(5.0) == ["w", "x", "y", "z"]
    assert ts.next_deadline() is None
