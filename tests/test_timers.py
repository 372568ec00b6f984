"""TimerSet's cached minimum and TimerWatch agree with a plain dict model."""

from __future__ import annotations

from collections.abc import Callable

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from awaremw.protocol.mote import AwareMote
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


@pytest.mark.pure_python
def test_a_set_armed_during_a_firing_fires_in_it_when_later_in_order(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # AwareMote's timer loops skip the sets never armed (TimerSet.armed); a set
    # armed by another component's timer must still fire as a loop over every
    # component in order would: in the same call if it comes later, else next.
    m = AwareMote(1)
    fired: list[tuple[str, object]] = []

    def on_collection(name: object, now: float) -> None:
        fired.append(("collection", name))
        m.commands.timers.set("later", now)  # after collection, never armed before
        m.dissemination.timers.set("earlier", now)  # before collection

    def recorder(label: str) -> Callable[[object, float], None]:
        return lambda name, now: fired.append((label, name))

    monkeypatch.setattr(m.dissemination, "on_timer", recorder("dissemination"))
    monkeypatch.setattr(m.commands, "on_timer", recorder("commands"))
    monkeypatch.setattr(m.collection, "on_timer", on_collection)
    assert m.next_deadline() is None and not m.commands.timers.armed
    m.collection.timers.set("x", 1.0)
    assert m.next_deadline() == 1.0
    m.handle_timer(1.0)
    assert fired == [("collection", "x"), ("commands", "later")]
    assert m.next_deadline() == 1.0
    m.handle_timer(1.0)
    assert fired[2:] == [("dissemination", "earlier")]
    assert m.next_deadline() is None
