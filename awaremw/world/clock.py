"""Emulated clock: wall time scaled by a speed factor from a shared start.

``now() = (wall - start_wall) * speed``, in emulated seconds. Processes of one
fleet get the same ``start_wall`` (a Unix epoch chosen by the launcher) and the
same ``speed``, so they agree on emulated time to within the host's clock
skew -- the stand-in for the FTSP-style time synchronisation the protocol's
epochs assume.

The clock progresses with the event loop's monotonic clock (immune to wall
clock steps after start); the Unix epoch is read once, at construction, to
anchor it. Conversions to and from loop time let the driver arm
``loop.call_at`` timers for emulated deadlines exactly.
"""

from __future__ import annotations

import time
from collections.abc import Callable


class EmulatedClock:
    """Emulated seconds since ``start_wall`` at ``speed`` x real time.

    ``monotonic`` must be the clock of the event loop that will run the timers
    (``loop.time``, which is ``time.monotonic`` by default).
    """

    __slots__ = ("_offset", "monotonic", "speed", "start_wall")

    def __init__(
        self,
        speed: float = 1.0,
        start_wall: float | None = None,
        *,
        monotonic: Callable[[], float] = time.monotonic,
    ) -> None:
        if not speed > 0:
            raise ValueError(f"speed factor must be > 0, got {speed!r}")
        self.speed = float(speed)
        self.monotonic = monotonic
        mono = monotonic()
        wall = time.time()
        self.start_wall = wall if start_wall is None else float(start_wall)
        # monotonic value at which emulated time is 0
        self._offset = mono - (wall - self.start_wall)

    def restart(self, start_wall: float) -> None:
        """Re-anchor emulated time 0 at ``start_wall`` (before anything is scheduled:
        a launcher's workers set up first and learn the shared start afterwards)."""
        mono = self.monotonic()
        self.start_wall = float(start_wall)
        self._offset = mono - (time.time() - self.start_wall)

    def now(self) -> float:
        """Emulated seconds since the shared start (negative before it)."""
        return (self.monotonic() - self._offset) * self.speed

    def to_monotonic(self, emulated: float) -> float:
        """The ``monotonic``/``loop.time()`` instant at which ``now()`` reaches ``emulated``."""
        return self._offset + emulated / self.speed

    def wall_seconds(self, emulated_span: float) -> float:
        """Real seconds an emulated span lasts."""
        return emulated_span / self.speed

    def emulated_seconds(self, wall_span: float) -> float:
        return wall_span * self.speed

    def __repr__(self) -> str:
        return f"EmulatedClock(speed={self.speed}, start_wall={self.start_wall:.6f})"
