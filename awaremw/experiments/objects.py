"""The objects a network tracks (fires, robots) and which one a record is about.

A group follows an object; its leader stands near it. A data record carries its
leader's id, so a record is given to the object nearest its leader when the
record was produced, within :data:`TRACK_RADIUS_M` (else to none). The large
experiments (``city``) and the benchmarks' aware workload score tracking per
object with this one rule: records delivered per object, distinct group ids
per object (ideally one: a single group followed it), and whether the group
still followed it at the end of the run.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

from awaremw.runtime.deployment import Deployment
from awaremw.world.fields import Source, World
from awaremw.world.mobility import Point

# Fire radius (25 m) plus two grid steps of the large fields (12 m): a leader
# farther than this from every object follows none of them.
TRACK_RADIUS_M = 50.0


@dataclass(frozen=True)
class TrackedObject:
    """An object by name, with where it is at time t (None: not there then)."""

    name: str
    kind: str  # "fire" or "robot"
    where: Callable[[float], Point | None]


def fires_of(world: World) -> list[TrackedObject]:
    return [TrackedObject(f.name, "fire", _fire_centre(f)) for f in world.fires]


def robots_of(d: Deployment) -> list[TrackedObject]:
    return [
        TrackedObject(f"robot {s.id}", "robot", s.mobility().position) for s in d.of_kind("robot")
    ]


def nearest(
    objects: Sequence[TrackedObject], pos: Point | None, t: float, radius: float = TRACK_RADIUS_M
) -> int | None:
    """Index of the object nearest ``pos`` at ``t``, within ``radius`` (None: none)."""
    if pos is None:
        return None
    best, best_d = None, radius
    for n, o in enumerate(objects):
        at = o.where(t)
        if at is None:
            continue
        d = math.hypot(pos[0] - at[0], pos[1] - at[1])
        if d <= best_d:
            best, best_d = n, d
    return best


@dataclass(frozen=True)
class ObjectScore:
    """Per object: records delivered, distinct group ids, tracked at the end."""

    records: tuple[int, ...]
    ids: tuple[int, ...]
    tracked: tuple[bool, ...]
    unattributed: int

    def as_dict(self) -> dict[str, object]:
        return {
            "objects": len(self.records),
            "objects_tracked": sum(self.tracked),
            "records_per_object": list(self.records),
            "ids_per_object": list(self.ids),
            "records_unattributed": self.unattributed,
        }


def score(
    objects: Sequence[TrackedObject],
    records: Mapping[tuple[int, int, int, int], tuple[float, Point | None, bool]],
    late: float,
) -> ObjectScore:
    """``records``: key (channel, group type, group id, epoch) -> (time produced,
    the leader's position then, delivered). An object is ``tracked`` when a
    record about it produced at or after ``late`` was delivered."""
    per = [0] * len(objects)
    ids: list[set[int]] = [set() for _ in objects]
    tracked = [False] * len(objects)
    unattributed = 0
    for key, (t, pos, delivered) in records.items():
        obj = nearest(objects, pos, t)
        if obj is None:
            unattributed += 1
            continue
        if delivered:
            per[obj] += 1
            ids[obj].add(key[2])
            tracked[obj] = tracked[obj] or t >= late
    return ObjectScore(tuple(per), tuple(len(s) for s in ids), tuple(tracked), unattributed)


def _fire_centre(fire: Source) -> Callable[[float], Point | None]:
    def where(t: float) -> Point | None:
        s = fire.state(t)
        return None if s is None else (s.x, s.y)

    return where
