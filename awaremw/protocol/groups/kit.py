"""What the parts of one mote's group management share, and how they move roles.

:class:`Kit` carries the component's context, its one timer set (one set, so
that due timers keep the order they had in one class), its counters and its
send (the coordinator owns the unicasts' link results), plus the small rules
read from the configuration. :class:`Moves` is the interface of the role
changes (:class:`~awaremw.protocol.groups.roles.Roles`), given to the parts
that trigger one, so that no part imports the parts above it.
"""

from __future__ import annotations

from collections.abc import Callable, Hashable
from typing import Protocol

from awaremw.protocol.component import MoteContext
from awaremw.protocol.core import Transmission
from awaremw.protocol.events import ElectionCause, LeaveReason
from awaremw.protocol.frames import Frame, LeaderBeacon
from awaremw.protocol.groups.standing import Standing
from awaremw.protocol.groups.values import BAND_2_DB, BAND_3_DB, GroupStats, Heard
from awaremw.protocol.timers import TimerSet


class Kit:
    """The shared services of the parts (no state of the protocol's own)."""

    __slots__ = ("ctx", "send", "stats", "timers")

    def __init__(
        self,
        ctx: MoteContext,
        timers: TimerSet,
        stats: GroupStats,
        send: Callable[[Frame], Transmission],
    ) -> None:
        self.ctx = ctx
        self.timers = timers
        self.stats = stats
        self.send = send

    def timeout(self) -> float:
        """The leader timeout in base beacon periods (tables of groups heard)."""
        c = self.ctx.config
        return c.leader_timeout_periods * c.beacon_period

    def tentative_hold(self) -> float:
        c = self.ctx.config
        return c.tentative_periods * c.beacon_period

    def max_factor(self) -> float:
        return max(1.0, self.ctx.config.beacon_settled_factor)

    def soon(self, name: Hashable, at: float, spread: float = 1.0) -> None:
        """An answer to a frame just heard goes out after U(0, spread x
        forward_jitter): the motes that heard the same frame must not all answer
        at the same instant (an answer already due stays)."""
        if name not in self.timers:
            j = spread * self.ctx.config.forward_jitter
            self.timers.set(name, at + self.ctx.rng.uniform(0, j))

    def link_rssi(self, node: int, rssi: float) -> float:
        # The mote's EWMA of everything heard from the node (updated with this
        # frame before dispatch) is steadier than one frame's RSSI.
        s = self.ctx.rssi.get(node)
        return rssi if s is None else s.dbm

    def band(self, rssi: float) -> int:
        """0 for a good link, up to 3 for the weakest (BAND_2_DB, BAND_3_DB)."""
        under = self.ctx.config.group_link_rssi_floor - rssi
        return 0 if under <= 0 else 1 if under <= BAND_2_DB else 2 if under <= BAND_3_DB else 3


class PerType(Protocol):
    """A part that keeps a share of state per group type."""

    def add(self, gtype: int) -> None: ...

    def drop(self, gtype: int) -> None: ...


class Moves(Protocol):
    """The role changes a part may trigger (docs/protocol-groups.md, "Groups")."""

    def join_heard(self, s: Standing, gid: int, h: Heard, now: float) -> None:
        """Join a group remembered from an earlier beacon, and announce it."""

    def adopt(self, s: Standing, f: LeaderBeacon, rssi: float, now: float) -> None:
        """Join the group of beacon ``f`` just heard, and forward it."""

    def become_leader(
        self, s: Standing, gid: int, weight: int, seq: int, now: float, cause: ElectionCause
    ) -> None: ...

    def leave(self, s: Standing, now: float, reason: LeaveReason, into: int = 0) -> None: ...

    def join_or_wait(self, s: Standing, now: float, cause: ElectionCause) -> None:
        """Join the heaviest group heard, else wait to create one."""
