"""What a mote holds of the disseminated items (:mod:`awaremw.protocol.dissemination`):
the version rules, the order-independent digest of the table, and the bounded
table itself.

Versions compare with RFC 1982 serial-number arithmetic (:func:`newer`): a
version is newer if it is ahead by less than 2**31 modulo 2**32, so no version
is ever the last one (``0xFFFFFFFF`` is followed by ``0``) and a foreign item
at any version can be superseded by the next one (the gateway's rule,
docs/protocol-dissemination.md, *Versions*).

Bounds: a mote holds at most ``max_group_types`` group types,
``max_channels`` channels and ``max_command_slots`` commands, tombstones
included. A new key on a full table evicts the tombstone of that kind changed
longest ago; with no tombstone to evict the item is refused.
"""

from __future__ import annotations

from collections.abc import Mapping, Set
from types import MappingProxyType
from typing import NamedTuple

from awaremw.protocol.config import MiddlewareConfig
from awaremw.protocol.frames import DripItem, FrameTooLarge, ItemBody, ItemKind, encode

ItemKey = tuple[ItemKind, int]

_M64 = 0xFFFFFFFFFFFFFFFF
_M32 = 0xFFFFFFFF
_HALF = 1 << 31


def newer(a: int, b: int) -> bool:
    """Whether u32 version ``a`` is newer than ``b``: RFC 1982 serial-number
    arithmetic (``a`` is ahead of ``b`` by 1 .. 2**31 - 1, modulo 2**32), so
    versions never overflow: ``0`` follows ``0xFFFFFFFF``. The pair RFC 1982
    leaves undefined (exactly 2**31 apart) is ordered by plain value, so that
    of two different versions exactly one is newer."""
    d = (a - b) & _M32
    return 0 < d < _HALF or (d == _HALF and a > b)


def next_version(v: int) -> int:
    """The version after ``v`` (wraps to 0 after 0xFFFFFFFF; always :func:`newer`)."""
    return (v + 1) & _M32


def is_jump(heard: int, held: int, step: int) -> bool:
    """Whether ``heard`` lies more than ``step`` versions away from ``held`` on
    the u32 circle, ahead or behind (``drip_max_version_step``: a jump no
    gateway makes)."""
    d = (heard - held) & _M32
    return step < d < (1 << 32) - step


class Item(NamedTuple):
    """What a mote holds for one key: a version and a body (None: deleted)."""

    version: int
    body: ItemBody | None


class ItemTableFull(ValueError):
    """``inject`` of a new key while the kind's table holds only live items."""


def _mix64(x: int) -> int:
    # splitmix64 finaliser: a well-mixed bijection, so digest terms look random.
    x = (x + 0x9E3779B97F4A7C15) & _M64
    x = ((x ^ (x >> 30)) * 0xBF58476D1CE4E5B9) & _M64
    x = ((x ^ (x >> 27)) * 0x94D049BB133111EB) & _M64
    return x ^ (x >> 31)


def digest_term(kind: ItemKind, item_id: int, version: int) -> int:
    """One item's contribution to the digest (a u32)."""
    return _mix64((int(kind) << 48) | (item_id << 32) | version) & _M32


def digest_of(entries: Mapping[ItemKey, Item]) -> int:
    """Order-independent digest: sum of the terms modulo 2**32 (0 when empty)."""
    return sum(digest_term(k, i, it.version) for (k, i), it in entries.items()) & _M32


class ItemTable:
    """The items a mote holds, tombstones included, with their signatures, the
    local time each last changed, and the digest of the table kept current."""

    def __init__(self, config: MiddlewareConfig) -> None:
        self._config = config
        self._items: dict[ItemKey, Item] = {}
        self._view: Mapping[ItemKey, Item] = MappingProxyType(self._items)
        self._changed: dict[ItemKey, float] = {}  # local time of the last change
        self._sigs: dict[ItemKey, bytes] = {}  # the held version's signature (same keys)
        self._digest = 0

    @property
    def items(self) -> Mapping[ItemKey, Item]:
        """Read-only live view of every held item, tombstones (body None) included."""
        return self._view

    @property
    def digest(self) -> int:
        return self._digest

    def __len__(self) -> int:
        return len(self._items)

    def get(self, key: ItemKey) -> Item | None:
        return self._items.get(key)

    def signature(self, key: ItemKey) -> bytes | None:
        """The gateway's signature of the held version (None: unsigned items)."""
        return self._sigs.get(key)

    def capacity(self, kind: ItemKind) -> int:
        c = self._config
        return {
            ItemKind.GROUP_TYPE: c.max_group_types,
            ItemKind.CHANNEL: c.max_channels,
            ItemKind.COMMAND: c.max_command_slots,
        }[kind]

    def accepts(self, kind: ItemKind, item_id: int) -> bool:
        """Whether an item for this key could be stored now (known key, free slot,
        or a tombstone of the same kind to evict)."""
        if (kind, item_id) in self._items:
            return True
        same = [it for (k, _), it in self._items.items() if k == kind]
        return len(same) < self.capacity(kind) or any(it.body is None for it in same)

    def refusal(self, f: DripItem, cur: Item | None) -> str | None:
        """Why ``f`` (a newer version than ``cur``, heard from the radio) cannot
        be held, or None: it can."""
        if cur is None and not self.accepts(f.kind, f.item_id):
            return f"{f.kind.name} table full"
        try:
            encode(f, self._config.mtu)
        except FrameTooLarge as e:
            return str(e)  # could not pass it on
        return None

    def make_room(self, kind: ItemKind) -> ItemKey | None:
        """Before a new key of ``kind``: evict, if the kind's table is full, its
        tombstone changed longest ago (:meth:`accepts` guaranteed one). Returns
        the key evicted, or None."""
        same = [k for k in self._items if k[0] == kind]
        if len(same) < self.capacity(kind):
            return None
        tombs = [k for k in same if self._items[k].body is None]
        victim = min(tombs, key=self._changed.__getitem__)
        old = self._items.pop(victim)
        self._digest = (self._digest - digest_term(victim[0], victim[1], old.version)) & _M32
        del self._changed[victim]
        self._sigs.pop(victim, None)
        return victim

    def put(self, f: DripItem, cur: Item | None, sig: bytes | None, now: float) -> None:
        """Hold ``f``'s version in place of ``cur`` (room made for a new key)."""
        key = (f.kind, f.item_id)
        if cur is not None:
            self._digest = (self._digest - digest_term(f.kind, f.item_id, cur.version)) & _M32
        self._digest = (self._digest + digest_term(f.kind, f.item_id, f.version)) & _M32
        self._items[key] = Item(f.version, f.item)
        if sig is None:
            self._sigs.pop(key, None)
        else:
            self._sigs[key] = sig
        self._changed[key] = now

    def last_changed_first(self, among: Set[ItemKey]) -> list[ItemKey]:
        """The held keys of ``among``, the last changed first (ties in table order)."""
        keys = [k for k in self._items if k in among]
        return sorted(keys, key=self._changed.__getitem__, reverse=True)
