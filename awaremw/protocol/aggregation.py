"""Aggregation functions for channels: partial states merged along the group tree.

An aggregation function is a small class (TAG's decomposable aggregates): a
reading becomes a partial ``(count, state)`` with :meth:`Aggregator.init`, two
partials combine with :meth:`Aggregator.merge` (associative and commutative, so
the shape of the group tree does not matter), and the leader turns the final
partial into the published number with :meth:`Aggregator.result`.

``count`` is always the number of readings included: it travels in every
``Partial`` and every ``DataRecord`` whatever the function, so a user can tell
how many members contributed (fewer than the group's size under loss). The
state is at most 4 numbers (``Partial`` carries them as float32).

The paper specifies AVG (sum and count); MIN, MAX, SUM and COUNT come with it.
Another function is one more subclass registered under a free wire id (see
:class:`Variance`, shipped but not registered, and docs/protocol-groups.md).
"""

from __future__ import annotations

from collections.abc import Iterable

from awaremw.protocol.frames import AggId

State = tuple[float, ...]
PartialAgg = tuple[int, State]  # (count of readings, state)

MAX_STATE = 4  # numbers a Partial frame can carry


class UnknownAggregation(ValueError):
    """No aggregation function has this wire id or name."""


class Aggregator:
    """Interface of an aggregation function. Subclasses set ``id`` and ``name``."""

    id: int = -1
    name: str = ""

    def init(self, value: float) -> PartialAgg:
        """The partial of one reading."""
        raise NotImplementedError

    def merge(self, a: PartialAgg, b: PartialAgg) -> PartialAgg:
        """Combine two partials (associative, commutative)."""
        raise NotImplementedError

    def result(self, count: int, state: State) -> float:
        """The published value of a final partial with ``count`` >= 1 readings."""
        raise NotImplementedError

    def merge_all(self, parts: Iterable[PartialAgg]) -> PartialAgg | None:
        """Merge any number of partials (None when there are none)."""
        acc: PartialAgg | None = None
        for p in parts:
            acc = p if acc is None else self.merge(acc, p)
        return acc

    def valid_state(self, state: State) -> bool:
        """Whether ``state`` has the shape this function produces (remote input check)."""
        return len(state) == len(self.init(0.0)[1])

    def __repr__(self) -> str:
        return f"<{type(self).__name__} {self.name}:{self.id}>"


class _OneNumber(Aggregator):
    """A state of one number: two partials' numbers combine with :meth:`fold`,
    and the result is that number."""

    def fold(self, x: float, y: float) -> float:
        raise NotImplementedError

    def init(self, value: float) -> PartialAgg:
        return 1, (float(value),)

    def merge(self, a: PartialAgg, b: PartialAgg) -> PartialAgg:
        return a[0] + b[0], (self.fold(a[1][0], b[1][0]),)

    def result(self, count: int, state: State) -> float:
        return state[0]


class Avg(_OneNumber):
    """The paper's AVG: members add their readings and count them; the leader divides."""

    id = AggId.AVG
    name = "avg"

    def fold(self, x: float, y: float) -> float:
        return x + y

    def result(self, count: int, state: State) -> float:
        return state[0] / count


class Sum(_OneNumber):
    id = AggId.SUM
    name = "sum"

    def fold(self, x: float, y: float) -> float:
        return x + y


class Min(_OneNumber):
    id = AggId.MIN
    name = "min"

    def fold(self, x: float, y: float) -> float:
        return min(x, y)


class Max(_OneNumber):
    id = AggId.MAX
    name = "max"

    def fold(self, x: float, y: float) -> float:
        return max(x, y)


class Count(Aggregator):
    """Number of readings: the count itself is the whole state."""

    id = AggId.COUNT
    name = "count"

    def init(self, value: float) -> PartialAgg:
        return 1, ()

    def merge(self, a: PartialAgg, b: PartialAgg) -> PartialAgg:
        return a[0] + b[0], ()

    def result(self, count: int, state: State) -> float:
        return float(count)


class Variance(Aggregator):
    """Population variance from (sum, sum of squares): an example extension.

    Not registered by default; ``register(Variance())`` makes it available
    under wire id 16 and name ``variance`` (the gateway must know it too).
    float32 on the wire limits its precision for large means (sum of squares).
    """

    id = 16
    name = "variance"

    def init(self, value: float) -> PartialAgg:
        v = float(value)
        return 1, (v, v * v)

    def merge(self, a: PartialAgg, b: PartialAgg) -> PartialAgg:
        return a[0] + b[0], (a[1][0] + b[1][0], a[1][1] + b[1][1])

    def result(self, count: int, state: State) -> float:
        mean = state[0] / count
        return max(0.0, state[1] / count - mean * mean)


_BY_ID: dict[int, Aggregator] = {}
_BY_NAME: dict[str, Aggregator] = {}


def register(agg: Aggregator, *, replace: bool = False) -> Aggregator:
    """Make ``agg`` available by wire id and name. Raises on a clash unless ``replace``."""
    if not 0 <= agg.id <= 0xFF:
        raise ValueError(f"aggregation id {agg.id} is not a u8")
    if not agg.name:
        raise ValueError("an aggregation function needs a name")
    if len(agg.init(0.0)[1]) > MAX_STATE:
        raise ValueError(f"{agg.name}: a state has at most {MAX_STATE} numbers")
    if not replace:
        other = _BY_ID.get(agg.id) or _BY_NAME.get(agg.name)
        if other is not None and other is not agg:
            raise ValueError(f"{agg!r} clashes with registered {other!r}")
    old = _BY_ID.pop(agg.id, None)
    if old is not None:
        _BY_NAME.pop(old.name, None)
    _BY_NAME.pop(agg.name, None)
    _BY_ID[agg.id] = agg
    _BY_NAME[agg.name] = agg
    return agg


def unregister(agg_id: int) -> None:
    old = _BY_ID.pop(agg_id, None)
    if old is not None:
        _BY_NAME.pop(old.name, None)


def by_id(agg_id: int) -> Aggregator:
    try:
        return _BY_ID[agg_id]
    except KeyError:
        raise UnknownAggregation(f"no aggregation function with id {agg_id}") from None


def by_name(name: str) -> Aggregator:
    try:
        return _BY_ID[_BY_NAME[name.lower()].id]
    except KeyError:
        known = ", ".join(sorted(_BY_NAME))
        raise UnknownAggregation(f"unknown aggregation {name!r}; known: {known}") from None


def get(agg_id: int) -> Aggregator | None:
    """The function with wire id ``agg_id``, or None (for remote input)."""
    return _BY_ID.get(agg_id)


for _a in (Avg(), Min(), Max(), Sum(), Count()):
    register(_a)
