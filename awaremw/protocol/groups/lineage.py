"""Lineage: the group ids a mote may take back after a merge or a split.

A part that merged into a heavier group keeps its former id for
``unmerge_window_periods`` beacon periods: if the merge does not hold (the part
loses the merged group's leader soon), it goes on under that id. A group created
after losing a leader names the lost id (``split_from``) in its reports, and a
part that split off and met its former group again (a flapping bridge) keeps
that id too (docs/protocol-groups.md, "Leader death").
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from awaremw.protocol.events import ElectionCause, LeaveReason
from awaremw.protocol.groups.kit import Kit


@dataclass(slots=True)
class _Ids:
    split_from: int = 0  # the id whose leader we lost before creating this group
    split_t: float = -math.inf  # ... and when we lost it
    former: int = 0  # an established group (weight > 0) we left by a merge ...
    former_until: float = -math.inf  # ... and until when a split may take its id back


class Lineage:
    """The former and split ids of every group type."""

    def __init__(self, kit: Kit) -> None:
        self._kit = kit
        self._ids: dict[int, _Ids] = {}

    def add(self, gtype: int) -> None:
        self._ids[gtype] = _Ids()

    def drop(self, gtype: int) -> None:
        del self._ids[gtype]

    def split_from(self, gtype: int) -> int:
        """The id whose leader this mote lost before it created its group (0: none)."""
        return self._ids[gtype].split_from

    def lost_leader(self, gtype: int, gid: int, now: float) -> None:
        """The leader of ``gid`` is given up: a group created now splits from it."""
        ids = self._ids[gtype]
        ids.split_from, ids.split_t = gid, now

    def leading(self, gtype: int, cause: ElectionCause) -> None:
        """This mote leads a group now: only an election splits one from a lost id."""
        if cause is not ElectionCause.ELECTION:
            self._ids[gtype].split_from = 0

    def left(
        self, gtype: int, gid: int, weight: int, reason: LeaveReason, into: int, now: float
    ) -> None:
        """The mote left ``gid`` (``into``: the group it merged into, or 0)."""
        ids = self._ids[gtype]
        window = self._window()
        rejoined = into != 0 and into == ids.split_from and now - ids.split_t <= window
        if reason in (LeaveReason.SWITCHED, LeaveReason.YIELDED) and (weight > 0 or rejoined):
            # Merged into a heavier group: if the merge does not hold (the part
            # loses the merged group's leader soon), the part takes this id back.
            # The same for a part that split off and met its former group again
            # (a flapping bridge): when the split comes for good, it is that part.
            ids.former, ids.former_until = gid, now + window

    def former(self, gtype: int, now: float, taken: set[int]) -> int:
        """The id of a group this mote left by a merge, if it may take it back now
        (not taken by a group heard), else 0."""
        ids = self._ids[gtype]
        if ids.former and now <= ids.former_until and ids.former not in taken:
            return ids.former
        return 0

    def _window(self) -> float:
        c = self._kit.ctx.config
        return c.unmerge_window_periods * c.beacon_period
