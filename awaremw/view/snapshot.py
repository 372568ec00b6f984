"""What a view shows at one instant, independent of how it is drawn.

A :class:`Snapshot` is built from any source (the virtual network's cores, a
fleet's event stream plus positions, an MQTT subscriber; an experiment run's is
built by :func:`awaremw.experiments.snapshot.snapshot_of`) and rendered by
:mod:`awaremw.view.render` (rich) or logged by :class:`awaremw.view.live.PlainLog`.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True, slots=True)
class MoteDot:
    node: int
    x: float
    y: float
    kind: str  # "mica2", "tmote", "robot", "gateway", ...
    group: int | None = None  # group id in the displayed group type
    leader: bool = False
    alive: bool = True


@dataclass(frozen=True, slots=True)
class RecordLine:
    """A data record as the IP side saw it."""

    t: float
    channel: int
    group_type: int
    group_id: int
    agg: str
    value: float
    count: int
    leader: int
    unit: str = ""  # of the value ("°C", "dBm"...; "" for a count or unknown)


@dataclass(frozen=True, slots=True)
class GroupLine:
    group_type: int
    group_id: int
    leader: int | None
    members: int


@dataclass(frozen=True, slots=True)
class Snapshot:
    t: float
    area: tuple[float, float, float, float]  # xmin, xmax, ymin, ymax
    motes: tuple[MoteDot, ...]
    groups: tuple[GroupLine, ...] = ()
    records: tuple[RecordLine, ...] = ()  # most recent last
    stats: dict[str, float | int | str] = field(default_factory=dict)
    title: str = "awaremw"
    group_type: int | None = None  # the group type the map colours
