"""PLACEHOLDER (engineer D replaces this): channels and aggregation."""

from __future__ import annotations

from awaremw.protocol.collection import Collection
from awaremw.protocol.frames import ItemBody
from awaremw.protocol.groups import Groups
from awaremw.protocol.mote import Component, MoteContext


class Channels(Component):
    def __init__(self, ctx: MoteContext, groups: Groups, collection: Collection) -> None:
        super().__init__(ctx)
        self.groups = groups
        self.collection = collection

    def define(self, channel_id: int, item: ItemBody | None, now: float) -> None:
        pass
