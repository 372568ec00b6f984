"""PLACEHOLDER (engineer C replaces this): commands."""

from __future__ import annotations

from awaremw.protocol.frames import ItemBody
from awaremw.protocol.groups import Groups
from awaremw.protocol.mote import Component, MoteContext


class Commands(Component):
    def __init__(self, ctx: MoteContext, groups: Groups) -> None:
        super().__init__(ctx)
        self.groups = groups

    def define(self, slot: int, item: ItemBody | None, now: float) -> None:
        pass
