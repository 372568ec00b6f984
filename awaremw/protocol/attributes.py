"""Attributes: numeric values a mote offers, by wire id.

The IP side names attributes (``temperature``, ``rssi:12``); the wire carries
ids. Standard ids are fixed here; ``rssi:<node>`` is ``RSSI_BASE | node`` (0x10000 |
node: every 16-bit short address has its own) and is
served by the middleware itself from the frames it hears. Node kinds may offer
more attributes with ids from ``CUSTOM_BASE`` on, registered by name.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import NamedTuple, Protocol, runtime_checkable

from awaremw.protocol.frames import MAX_NODE_ID, NODE_MASK, CommandDef
from awaremw.protocol.frames import RSSI_BASE as RSSI_BASE  # rssi:<node> = RSSI_BASE | node

TEMPERATURE = 0  # deg C
HUMIDITY = 1  # %RH
LIGHT = 2  # lx
X = 3  # m
Y = 4  # m
BATTERY = 5  # V
GAS = 6  # ppm

STANDARD: Mapping[str, int] = {
    "temperature": TEMPERATURE,
    "humidity": HUMIDITY,
    "light": LIGHT,
    "x": X,
    "y": Y,
    "battery": BATTERY,
    "gas": GAS,
}
UNITS: Mapping[int, str] = {
    TEMPERATURE: "degC",
    HUMIDITY: "%RH",
    LIGHT: "lx",
    X: "m",
    Y: "m",
    BATTERY: "V",
    GAS: "ppm",
}


# Units as a reader expects them printed next to a value (records, plots, docs).
DISPLAY_UNITS: Mapping[str, str] = {
    "temperature": "°C",
    "humidity": "%RH",
    "light": "lx",
    "x": "m",
    "y": "m",
    "battery": "V",
    "gas": "ppm",
}


def unit_of(name: str | None, agg: str = "avg") -> str:
    """The unit of an aggregate of attribute ``name`` ("" if none: a COUNT, an unknown name)."""
    if name is None or agg == "count":
        return ""
    if name.startswith("rssi:"):
        return "dBm"
    return DISPLAY_UNITS.get(name, "")


class UnknownAttribute(ValueError):
    """An attribute name (IP side) or id (wire side) that nobody defines."""


def attribute_id(name: str) -> int:
    """Wire id of an IP-side attribute name; raises :class:`UnknownAttribute`."""
    if name in STANDARD:
        return STANDARD[name]
    if name.startswith("rssi:"):
        node = name[5:]
        # isascii: str.isdigit() also accepts Unicode digits ("rssi:\u00b2") that int() refuses.
        if node.isascii() and node.isdigit() and 0 <= int(node) <= MAX_NODE_ID:
            return RSSI_BASE | int(node)
        raise UnknownAttribute(f"{name!r}: rssi:<node id> needs a node id in 0..{MAX_NODE_ID}")
    known = ", ".join([*STANDARD, "rssi:<node id>"])
    raise UnknownAttribute(f"unknown attribute {name!r}; known: {known}")


def attribute_name(attr: int) -> str:
    """IP-side name of a wire id (inverse of :func:`attribute_id`)."""
    if attr & RSSI_BASE:
        return f"rssi:{attr & NODE_MASK}"
    for name, i in STANDARD.items():
        if i == attr:
            return name
    return f"attr{attr}"


def rssi_attribute(node: int) -> int:
    return RSSI_BASE | node


def is_rssi(attr: int) -> bool:
    return bool(attr & RSSI_BASE)


@runtime_checkable
class Application(Protocol):
    """The application layer of a mote (its node kind), seen by the middleware.

    ``read`` returns the attribute in SI units (the node kind converts raw
    readings), or None when the mote does not offer it right now. RSSI
    attributes are served by the middleware, not by the application.
    """

    def offers(self, attr: int) -> bool: ...

    def read(self, attr: int, now: float) -> float | None: ...

    def on_command(self, command: CommandDef, now: float) -> None: ...


class Bounds(NamedTuple):
    """What :class:`ReadBounds` promises: ``read(attr, t)`` returns a number in
    ``[lo, hi]`` and changes nothing by being read, at ``t = now`` and at every
    ``t`` before ``until`` (``until <= now``: at ``now`` only), as long as the
    application is sent no command meanwhile. A mote asks at times that never
    go back (an application may keep what it answered until ``until``)."""

    lo: float
    hi: float
    until: float


@runtime_checkable
class ReadBounds(Protocol):
    """Optional for an :class:`Application`: ``read_bounds(attr, now)`` gives the
    :class:`Bounds` of an attribute's readings (None: unknown). A group check
    skips a read whose interval cannot meet its condition (the same decision,
    without the sensor model's work), and a mote whose every group condition is
    ruled out until ``until`` checks again only then (docs/protocol-groups.md,
    "Membership checks")."""

    def read_bounds(self, attr: int, now: float) -> Bounds | None: ...
