"""PLACEHOLDER (engineer D replaces this): group management."""

from __future__ import annotations

from awaremw.protocol.collection import Collection
from awaremw.protocol.frames import ItemBody
from awaremw.protocol.mote import Component, MoteContext


class Groups(Component):
    def __init__(self, ctx: MoteContext, collection: Collection) -> None:
        super().__init__(ctx)
        self.collection = collection

    def define(self, group_type: int, item: ItemBody | None, now: float) -> None:
        pass
