"""PLACEHOLDER (engineer C replaces this): CTP-like collection tree."""

from __future__ import annotations

from awaremw.protocol.frames import Payload
from awaremw.protocol.mote import Component


class Collection(Component):
    def submit(self, payload: Payload, now: float) -> bool:
        """Queue ``payload`` for the gateway roots; False if refused (no route, full)."""
        return False
