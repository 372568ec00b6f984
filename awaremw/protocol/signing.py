"""Signatures of dissemination items by the gateway's Ed25519 key (pure functions).

What is signed is the item itself, not the frame that carries it: a domain
tag, then the msgpack array ``[kind, item_id, version, body]`` exactly as a
:class:`~awaremw.protocol.frames.DripItem` carries it (floats as float32), so
every mote re-derives the same bytes from the frame it decoded. A deletion
(``body`` None) is signed too. Verifying costs ~70 us of CPU per item version
a mote adopts (not per frame heard). See docs/security.md, "Frames and items".
"""

from __future__ import annotations

import msgpack
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives.asymmetric.ed25519 import (
    Ed25519PrivateKey,
    Ed25519PublicKey,
)

from awaremw.protocol.frames import ItemBody, ItemKind

DOMAIN = b"awaremw item v1\x00"
SIG_BYTES = 64
PUBLIC_KEY_BYTES = 32


def item_message(kind: ItemKind, item_id: int, version: int, body: ItemBody | None) -> bytes:
    """The bytes the gateway signs for one item version."""
    wire = None if body is None else body.to_wire()
    packed: bytes = msgpack.packb(
        [int(kind), item_id, version, wire], use_single_float=True, use_bin_type=True
    )
    return DOMAIN + packed


class ItemSigner:
    """The gateway's side: signs item versions (held by gateway motes only)."""

    __slots__ = ("_key",)

    def __init__(self, key: Ed25519PrivateKey) -> None:
        self._key = key

    def sign(self, kind: ItemKind, item_id: int, version: int, body: ItemBody | None) -> bytes:
        return self._key.sign(item_message(kind, item_id, version, body))

    def __repr__(self) -> str:
        return "ItemSigner(<private key>)"


class ItemVerifier:
    """Every mote's side: checks item signatures with the gateway's public key."""

    __slots__ = ("_key",)

    def __init__(self, public_key: bytes) -> None:
        if len(public_key) != PUBLIC_KEY_BYTES:
            raise ValueError(f"the gateway public key must be {PUBLIC_KEY_BYTES} raw bytes")
        self._key = Ed25519PublicKey.from_public_bytes(public_key)

    def verify(
        self, kind: ItemKind, item_id: int, version: int, body: ItemBody | None, sig: bytes
    ) -> bool:
        if len(sig) != SIG_BYTES:
            return False
        try:
            self._key.verify(sig, item_message(kind, item_id, version, body))
        except InvalidSignature:
            return False
        return True
