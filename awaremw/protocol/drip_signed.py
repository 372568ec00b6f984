"""Signed items on their way in (:mod:`awaremw.protocol.dissemination`, with
``config.gateway_public_key`` set): a newer item version heard from the radio
is held *pending* (at most ``max_pending_items``, the oldest evicted) until
its :data:`~awaremw.protocol.frames.SIG_PARTS` signature parts are in, then
verified; only a verified version is adopted.
"""

from __future__ import annotations

from typing import NamedTuple

from awaremw.protocol.config import MiddlewareConfig
from awaremw.protocol.drip_gossip import Summaries
from awaremw.protocol.drip_items import ItemKey, newer
from awaremw.protocol.frames import SIG_PARTS, DripItem, DripSig, ItemBody
from awaremw.protocol.signing import ItemVerifier

_MISSING = object()  # a pending item whose DripItem has not been heard yet


class _Pending:
    """A newer item version heard, waiting for its signature (or its body)."""

    __slots__ = ("body", "parts", "source", "version")

    def __init__(self, version: int, source: int) -> None:
        self.version = version
        self.body: object = _MISSING  # ItemBody | None once heard
        self.parts: list[bytes | None] = [None] * SIG_PARTS
        self.source = source


class Signed(NamedTuple):
    """A pending version complete (body and every signature part), checked."""

    key: ItemKey
    version: int
    body: ItemBody | None
    sig: bytes
    source: int  # the neighbour it was first heard from
    valid: bool  # the signature is the gateway's


class PendingItems:
    """The pending versions, one per key, and their check."""

    def __init__(
        self, verifier: ItemVerifier, config: MiddlewareConfig, summaries: Summaries
    ) -> None:
        self._verifier = verifier
        self._bound = config.max_pending_items
        self._summaries = summaries  # asked to ask while a version is pending
        self._pending: dict[ItemKey, _Pending] = {}

    def __len__(self) -> int:
        return len(self._pending)

    def __contains__(self, key: object) -> bool:
        return key in self._pending

    def hear_item(self, f: DripItem, now: float) -> Signed | None:
        """``f`` is newer than what we hold: its body. The version once complete."""
        key = (f.kind, f.item_id)
        pend = self._entry(key, f.version, f.src, now)
        if pend is None:
            return None
        pend.body = f.item
        return self._complete(key, pend)

    def hear_sig(self, f: DripSig, now: float) -> Signed | None:
        """A signature part of a version newer than what we hold. The version
        once complete."""
        key = (f.kind, f.item_id)
        pend = self._entry(key, f.version, f.src, now)
        if pend is None:
            return None
        pend.parts[f.part] = f.chunk
        return self._complete(key, pend)

    def _entry(self, key: ItemKey, version: int, src: int, now: float) -> _Pending | None:
        """The pending entry of ``key`` at ``version`` (made if newer than a pending
        one; None if an even newer version is pending already)."""
        pend = self._pending.get(key)
        if pend is not None:
            if pend.version == version:
                return pend
            if not newer(version, pend.version):
                return None
            del self._pending[key]
        if len(self._pending) >= self._bound:
            del self._pending[next(iter(self._pending))]  # the oldest
        pend = self._pending[key] = _Pending(version, src)
        # A neighbour holds what we lack: ask for it (see ask_while_pending).
        self._summaries.ask_while_pending(now)
        return pend

    def _complete(self, key: ItemKey, pend: _Pending) -> Signed | None:
        if pend.body is _MISSING or any(p is None for p in pend.parts):
            return None
        del self._pending[key]
        body: ItemBody | None = pend.body  # type: ignore[assignment]
        sig = b"".join(p for p in pend.parts if p is not None)
        valid = self._verifier.verify(key[0], key[1], pend.version, body, sig)
        return Signed(key, pend.version, body, sig, pend.source, valid)
