"""One way to check a document's shape: msgspec types, refusals in our words.

A document (the dicts, lists and scalars a TOML or JSON parser gives) is
checked against a msgspec ``Struct`` by :func:`convert`, strictly: no bool for
a number, no float for an integer, no string for a number. msgspec reports a
refusal as one string (``Expected `float`, got `str` - at `$.keyframes[1].t```);
this module is the one place that reads it, and turns it into :class:`Invalid`
with the path (``keyframes[1].t``) and a one-line reason (``must be a number,
got 'fast'``). tests/test_validation.py pins every form it reads.
"""

from __future__ import annotations

import re
import sys
from typing import Annotated, Any, TypeVar

import msgspec

T = TypeVar("T")

# A float that is neither NaN nor infinite (TOML has nan and inf).
_MAX = sys.float_info.max
Finite = Annotated[float, msgspec.Meta(ge=-_MAX, le=_MAX)]
_FINITE = tuple(f"Expected `float` {op} {v!r}" for op, v in ((">=", -_MAX), ("<=", _MAX)))

_ERROR = re.compile(r"(?P<msg>.*?)(?: - at `\$\.?(?P<path>.*)`)?", re.S)
_NAMES = {
    "int": "an integer",
    "float": "a number",
    "bool": "true or false",
    "str": "a string",
    "object": "a table",
    "array": "an array",
}


class Invalid(ValueError):
    """A document that does not fit its type: ``path`` (empty: the document
    itself) and ``why``, e.g. ``must be a number, got 'fast'``."""

    def __init__(self, path: str, why: str) -> None:
        super().__init__(f"{path}: {why}" if path else why)
        self.path = path
        self.why = why


def convert(doc: Any, type_: type[T]) -> T:
    """``doc`` as a ``type_``, or :class:`Invalid`."""
    try:
        return msgspec.convert(doc, type_, strict=True)
    except msgspec.ValidationError as e:
        m = _ERROR.fullmatch(str(e))
        assert m is not None  # the pattern matches any string
        raise _invalid(m["msg"], m["path"] or "", doc) from None


def _invalid(msg: str, path: str, doc: Any) -> Invalid:
    quoted = msg.split("`")
    if msg.startswith("Object missing required field"):
        return Invalid(path, f"missing key {quoted[1]!r}")
    if msg.startswith("Object contains unknown field"):
        return Invalid(path, f"unknown key {quoted[1]!r}")
    if msg.startswith(_FINITE):
        expected = "a finite number"
    elif ", got `" in msg:  # the wrong type: "Expected `int | null`, got `str`"
        expected = " or ".join(_NAMES.get(t, t) for t in quoted[1].split(" | ") if t != "null")
    elif " of length " in msg:  # "Expected `array` of length >= 1"
        expected = f"{_NAMES[quoted[1]]} of length {msg.split(' of length ')[1].split(',')[0]}"
    else:  # a bound: "Expected `float` > 0.0"
        expected = f"{quoted[2].strip().removesuffix('.0')}"
    return Invalid(path, f"must be {expected}, got {_at(doc, path)!r}")


def _at(doc: Any, path: str) -> Any:
    """The value at a msgspec path (``a.b[2]``; ``[...]``, a dict's value, stops)."""
    for key, index in re.findall(r"([^.\[\]]+)|\[(\d+)\]", path):
        doc = doc[int(index)] if index else doc[key]
    return doc
