"""Where a mote is at time t: static positions and waypoint paths.

Pure functions of t (emulated seconds since the fleet's start), so every
process computes the same position for the same mote at the same time.
"""

from __future__ import annotations

import bisect
import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

Point = tuple[float, float]


@runtime_checkable
class Mobility(Protocol):
    def position(self, t: float) -> Point: ...


def _point(p: Sequence[float], what: str) -> Point:
    if len(p) != 2:
        raise ValueError(f"{what} must be an (x, y) pair, got {p!r}")
    x, y = float(p[0]), float(p[1])
    if not (math.isfinite(x) and math.isfinite(y)):
        raise ValueError(f"{what} must be finite, got {p!r}")
    return x, y


@dataclass(frozen=True, slots=True)
class Static:
    """A mote that never moves."""

    x: float
    y: float

    def __post_init__(self) -> None:
        _point((self.x, self.y), "position")

    def position(self, t: float) -> Point:
        return self.x, self.y


def stays_put(position: object) -> bool:
    """Whether ``position`` (a position function, as node kinds hold it) is a
    :class:`Static` mote's: the same point at every time."""
    return isinstance(getattr(position, "__self__", None), Static)


@dataclass(frozen=True)
class Path:
    """Move along ``waypoints`` at ``speed_mps``, starting at ``start_s``.

    Before ``start_s`` the mote sits on the first waypoint. It pauses
    ``pause_s`` at every waypoint it reaches. Without ``loop`` it stays on the
    last waypoint; with ``loop`` it goes back to the first one and starts over.
    """

    waypoints: tuple[Point, ...]
    speed_mps: float
    start_s: float = 0.0
    loop: bool = False
    pause_s: float = 0.0
    # Derived: legs (from, to, depart time, arrive time) relative to start_s.
    _legs: tuple[tuple[Point, Point, float, float], ...] = field(
        init=False, repr=False, compare=False
    )
    _departs: tuple[float, ...] = field(init=False, repr=False, compare=False)
    _cycle: float = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        wps = tuple(_point(p, f"waypoints[{i}]") for i, p in enumerate(self.waypoints))
        if not wps:
            raise ValueError("a path needs at least one waypoint")
        if not (math.isfinite(self.speed_mps) and self.speed_mps > 0):
            raise ValueError(f"speed_mps must be > 0, got {self.speed_mps}")
        if not (math.isfinite(self.pause_s) and self.pause_s >= 0):
            raise ValueError(f"pause_s must be >= 0, got {self.pause_s}")
        if not math.isfinite(self.start_s):
            raise ValueError(f"start_s must be finite, got {self.start_s}")
        object.__setattr__(self, "waypoints", wps)
        stops = [*wps, wps[0]] if self.loop and len(wps) > 1 else list(wps)
        legs: list[tuple[Point, Point, float, float]] = []
        t = 0.0
        for a, b in itertools.pairwise(stops):
            arrive = t + math.dist(a, b) / self.speed_mps
            legs.append((a, b, t, arrive))
            t = arrive + self.pause_s
        object.__setattr__(self, "_legs", tuple(legs))
        object.__setattr__(self, "_departs", tuple(leg[2] for leg in legs))
        object.__setattr__(self, "_cycle", t)

    @property
    def duration_s(self) -> float:
        """Time of one pass (one cycle when looping); 0 for a single waypoint."""
        return self._cycle

    def position(self, t: float) -> Point:
        tau = t - self.start_s
        if tau <= 0.0 or not self._legs:
            return self.waypoints[0]
        if self.loop:
            if self._cycle <= 0.0:
                return self.waypoints[0]
            tau %= self._cycle
        elif tau >= self._cycle:
            return self.waypoints[-1]
        i = bisect.bisect_right(self._departs, tau) - 1
        (ax, ay), (bx, by), t0, t1 = self._legs[i]
        if tau >= t1:  # pausing at b
            return bx, by
        f = (tau - t0) / (t1 - t0)
        return ax + (bx - ax) * f, ay + (by - ay) * f


def square_loop(
    cx: float, cy: float, half: float, speed_mps: float, first_corner: int, corners: int
) -> list[tuple[float, float, float]]:
    """``corners`` keyframes ``(t, x, y)`` of an object looping anticlockwise around
    ``(cx, cy)`` on a square of half-side ``half`` at ``speed_mps``, from corner
    ``first_corner`` (0: lower left, then lower right, upper right, upper left)
    at t = 0: the fires of the large fields (bench aware workload, city.toml)."""
    square = ((cx - half, cy - half), (cx + half, cy - half),
              (cx + half, cy + half), (cx - half, cy + half))  # fmt: skip
    leg = 2 * half / speed_mps
    return [(i * leg, *square[(first_corner + i) % 4]) for i in range(corners)]
