"""What a view shows at one instant, independent of how it is drawn.

A :class:`Snapshot` is built from any source (the virtual network's cores, a
fleet's event stream plus positions, an MQTT subscriber; an experiment run's is
built by :func:`awaremw.experiments.snapshot.snapshot_of`) and rendered by
:mod:`awaremw.view.render` (rich) or logged by :class:`awaremw.view.live.PlainLog`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace

from awaremw.nodes.kinds import NodeApp
from awaremw.protocol.core import MoteCore
from awaremw.protocol.mote import AwareMote


@dataclass(frozen=True, slots=True)
class MoteDot:
    node: int
    x: float
    y: float
    kind: str  # "mica2", "tmote", "robot", "gateway", ...
    group: int | None = None  # group id in the displayed group type
    leader: bool = False
    alive: bool = True
    leds: tuple[str, ...] = ()  # lit LEDs by colour (where the motes' cores are known)


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


def lit_leds(core: MoteCore | None) -> tuple[str, ...]:
    """The colours of the LEDs lit on a mote (the ``led`` command's effect)."""
    app = core.ctx.app if isinstance(core, AwareMote) else None
    if not isinstance(app, NodeApp):
        return ()
    return tuple(c for c in app.LEDS if app.leds.get(c))


def with_leds(snap: Snapshot, cores: Mapping[int, MoteCore]) -> Snapshot:
    """``snap`` with every mote's lit LEDs read from the cores in this process."""
    dots = tuple(
        d if d.leds == (leds := lit_leds(cores.get(d.node))) else replace(d, leds=leds)
        for d in snap.motes
    )
    lit = sum(1 for d in dots if d.leds)
    return replace(snap, motes=dots, stats={**snap.stats, "LEDs lit": lit})
