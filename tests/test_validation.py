"""awaremw.protocol.validation: every form of msgspec's refusal it reads becomes
a path and a one-line reason (a msgspec release that rewords one fails here)."""

from __future__ import annotations

from typing import Annotated, Any

import pytest
from msgspec import Meta, Struct

from awaremw.protocol.validation import Finite, Invalid, convert


class _Inner(Struct, forbid_unknown_fields=True):
    t: Finite


class _Doc(Struct):
    name: Annotated[str, Meta(min_length=1)] = "n"
    count: Annotated[int, Meta(ge=1)] = 1
    speed: Annotated[float, Meta(gt=0)] = 1.0
    power: Finite | None = None
    on: bool = False
    point: tuple[float, float] = (0.0, 0.0)
    items: Annotated[list[_Inner], Meta(min_length=1)] | None = None
    table: dict[str, Any] = {}


@pytest.mark.parametrize(
    ("doc", "path", "why"),
    [
        ({"count": 1.5}, "count", "must be an integer, got 1.5"),
        ({"count": True}, "count", "must be an integer, got True"),
        ({"count": 0}, "count", "must be >= 1, got 0"),
        ({"speed": "fast"}, "speed", "must be a number, got 'fast'"),
        ({"speed": 0}, "speed", "must be > 0, got 0"),
        ({"power": "x"}, "power", "must be a number, got 'x'"),
        ({"power": float("inf")}, "power", "must be a finite number, got inf"),
        ({"on": 1}, "on", "must be true or false, got 1"),
        ({"name": ""}, "name", "must be a string of length >= 1, got ''"),
        ({"point": [1, 2, 3]}, "point", "must be an array of length 2, got [1, 2, 3]"),
        ({"point": [1, "y"]}, "point[1]", "must be a number, got 'y'"),
        ({"items": []}, "items", "must be an array of length >= 1, got []"),
        ({"items": [{"t": 0}, {}]}, "items[1]", "missing key 't'"),
        ({"items": [{"t": 0, "z": 1}]}, "items[0]", "unknown key 'z'"),
        ({"items": [{"t": float("nan")}]}, "items[0].t", "must be a finite number, got nan"),
        ({"table": 3}, "table", "must be a table, got 3"),
        ([1], "", "must be a table, got [1]"),
    ],
)
def test_each_refusal_names_the_path_and_why(doc: Any, path: str, why: str) -> None:
    with pytest.raises(Invalid) as e:
        convert(doc, _Doc)
    assert (e.value.path, e.value.why) == (path, why)
    assert str(e.value) == (f"{path}: {why}" if path else why)


def test_a_good_document_converts() -> None:
    d = convert({"count": 2, "speed": 3, "point": [1, 2], "items": [{"t": 1}]}, _Doc)
    assert (d.count, d.speed, d.point, d.items) == (2, 3.0, (1.0, 2.0), [_Inner(1.0)])
