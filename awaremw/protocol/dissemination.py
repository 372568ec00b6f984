"""PLACEHOLDER (engineer C replaces this): Drip over Trickle."""

from __future__ import annotations

from collections.abc import Callable

from awaremw.protocol.frames import ItemBody, ItemKind
from awaremw.protocol.mote import Component, MoteContext

OnItem = Callable[[ItemKind, int, ItemBody | None, float], None]


class Dissemination(Component):
    def __init__(self, ctx: MoteContext, on_item: OnItem) -> None:
        super().__init__(ctx)
        self.on_item = on_item
        self.items: dict[tuple[ItemKind, int], tuple[int, ItemBody | None]] = {}

    def inject(
        self, kind: ItemKind, item_id: int, version: int, item: ItemBody | None, now: float
    ) -> None:
        self.items[(kind, item_id)] = (version, item)
        self.on_item(kind, item_id, item, now)
