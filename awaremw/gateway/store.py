"""SQLite store of the gateway's versioned items, so versions survive restarts.

Drip only spreads a version higher than the one a mote holds: if a restarted
gateway numbered its definitions from 1 again, the network would ignore it.
The store keeps, per ``(kind, item id)``, the current version, a hash of the
body and the body itself (radio form and IP-side JSON); deletions are
tombstones with a version of their own.

It also remembers the hash of the last payload seen on each source topic, so a
retained MQTT message replayed after a (re)connect is recognised and not
applied twice, and the command-name -> Drip slot map.

The store works on an in-memory copy and writes every change through to the
file. A write that fails (disk full, file system gone read-only) loses
nothing: the change stays in memory, marked, and is written again with the
next change or :meth:`VersionStore.retry`; each failure is counted
(``write_failures``), logged at most every :data:`WRITE_ERROR_INTERVAL_S`, and
handed to ``on_write_error`` (the gateway publishes it on ``<prefix>/errors``).
A file that cannot be opened at all is a :class:`StoreError` (one line).
"""

from __future__ import annotations

import hashlib
import json
import logging
import sqlite3
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgpack

from awaremw.gateway.schema import definition_json
from awaremw.protocol.frames import (
    ChannelDef,
    CommandDef,
    GroupTypeDef,
    ItemBody,
    ItemKind,
)

# The store counts versions without wrapping (a 63-bit SQLite integer); the
# radio carries them modulo 2**32 (``wire_version``) and motes compare them with
# RFC 1982 serial arithmetic, so the store never runs out: at one definition a
# millisecond it would take 292 million years. Versions heard from the network
# are mapped back into this count by :func:`unwrap`.
MAX_VERSION = (1 << 63) - 1
_M32 = 0xFFFFFFFF
_HALF = 1 << 31


def wire_version(v: int) -> int:
    """The u32 version the radio carries for store version ``v``."""
    return v & _M32


def unwrap(wire: int, ref: int | None) -> int:
    """The store version a u32 ``wire`` version heard from the network stands for,
    relative to the store's current version ``ref`` of that item: the nearest one
    in serial order (newer by 1 .. 2**31 - 1 or, exactly 2**31 apart, as the
    motes order them; otherwise older). With no ``ref``, ``wire`` itself."""
    if ref is None:
        return wire
    d = (wire - ref) & _M32
    if 0 < d < _HALF or (d == _HALF and wire > (ref & _M32)):
        return ref + d  # newer
    return ref - ((ref - wire) & _M32)  # older, or equal (d == 0)


MAX_SEEN = 4096  # source topics whose last payload hash is remembered (LRU beyond)
WRITE_ERROR_INTERVAL_S = 10.0  # at most one log line / error report per interval while failing

log = logging.getLogger(__name__)

_SCHEMA = """
CREATE TABLE IF NOT EXISTS items (
    kind INTEGER NOT NULL,
    item_id INTEGER NOT NULL,
    version INTEGER NOT NULL,
    hash TEXT NOT NULL,
    wire BLOB,             -- msgpack of body.to_wire(); NULL for a deletion
    json TEXT,             -- canonical IP-side JSON; NULL for a deletion
    updated REAL NOT NULL, -- wall clock, informational
    PRIMARY KEY (kind, item_id)
);
CREATE TABLE IF NOT EXISTS seen (
    source TEXT PRIMARY KEY,
    hash TEXT NOT NULL,
    used INTEGER NOT NULL DEFAULT 0  -- monotonic counter, for least-recently-used eviction
);
CREATE TABLE IF NOT EXISTS command_slots (
    name TEXT PRIMARY KEY,
    slot INTEGER NOT NULL UNIQUE,
    used INTEGER NOT NULL  -- monotonic use counter, for least-recently-used reuse
);
"""

_ITEM_COLS = "kind, item_id, version, hash, wire, json, updated"
_SEEN_COLS = "source, hash, used"
_SLOT_COLS = "name, slot, used"

_FROM_WIRE: dict[ItemKind, Callable[[Any], ItemBody]] = {
    ItemKind.GROUP_TYPE: GroupTypeDef.from_wire,
    ItemKind.CHANNEL: ChannelDef.from_wire,
    ItemKind.COMMAND: CommandDef.from_wire,
}


def body_hash(kind: ItemKind, body: ItemBody | None) -> str:
    """Stable hash of a body's radio form (equal definitions hash equal)."""
    wire = None if body is None else body.to_wire()
    packed: bytes = msgpack.packb([int(kind), wire], use_single_float=True)
    return hashlib.sha256(packed).hexdigest()[:32]


def payload_hash(payload: bytes) -> str:
    return hashlib.sha256(payload).hexdigest()[:32]


@dataclass(frozen=True, slots=True)
class StoredItem:
    kind: ItemKind
    item_id: int
    version: int
    body: ItemBody | None  # None: deleted
    json: dict[str, Any] | None

    @property
    def deleted(self) -> bool:
        return self.body is None


class StoreError(RuntimeError):
    """The version store's file cannot be opened or created (the text is one line)."""


class VersionOverflow(RuntimeError):
    """An item reached the largest store version (2**63 - 1: never expected)."""


class VersionStore:
    """Versions and bodies of the gateway's items; ``path=None`` keeps them in memory."""

    def __init__(
        self,
        path: str | Path | None = None,
        *,
        max_seen: int = MAX_SEEN,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if max_seen < 1:
            raise ValueError("max_seen must be >= 1")
        self.max_seen = max_seen
        self.path = None if path is None else Path(path)
        self.write_failures = 0  # writes to the file that failed (the change kept, retried)
        self.last_write_error: str | None = None
        # Told (rate-limited) what failed and what is kept; the gateway publishes it.
        self.on_write_error: Callable[[str], None] | None = None
        self._clock = clock
        self._last_report: float | None = None
        self._unreported = 0
        # Changes not yet in the file: item keys, seen sources (or all of them), slots.
        self._dirty_items: set[tuple[int, int]] = set()
        self._dirty_seen: set[str] = set()
        self._seen_all = False
        self._slots_dirty = False
        self._db = sqlite3.connect(":memory:")
        self._db.executescript(_SCHEMA)
        self._disk = False
        if self.path is not None:
            try:
                self._attach(self.path)
            except (sqlite3.Error, OSError) as e:
                self._db.close()
                raise StoreError(f"cannot open the version store {self.path}: {e}") from None
        row = self._db.execute("SELECT COALESCE(MAX(used), 0) FROM seen").fetchone()
        self._seen_tick = int(row[0])

    def _attach(self, path: Path) -> None:
        """Open (create) the file and load it into memory."""
        path.parent.mkdir(parents=True, exist_ok=True)
        db = self._db
        db.execute("ATTACH DATABASE ? AS disk", (str(path),))
        db.execute("PRAGMA disk.journal_mode=WAL")
        db.execute("PRAGMA disk.synchronous=NORMAL")
        db.executescript(_SCHEMA.replace("IF NOT EXISTS ", "IF NOT EXISTS disk."))
        cols = {r[1] for r in db.execute("PRAGMA disk.table_info(seen)")}
        if "used" not in cols:  # a store written before the bound existed
            db.execute("ALTER TABLE disk.seen ADD COLUMN used INTEGER NOT NULL DEFAULT 0")
        with db:
            db.execute(f"INSERT INTO main.items SELECT {_ITEM_COLS} FROM disk.items")
            db.execute(f"INSERT INTO main.seen SELECT {_SEEN_COLS} FROM disk.seen")
            db.execute(
                f"INSERT INTO main.command_slots SELECT {_SLOT_COLS} FROM disk.command_slots"
            )
        self._disk = True

    def close(self) -> None:
        if self.pending_writes:
            self.retry()
        if self.pending_writes:
            log.error(
                "version store %s: %d changes could not be written and are lost (%s)",
                self.path, self.pending_writes, self.last_write_error,
            )  # fmt: skip
        self._db.close()

    def __enter__(self) -> VersionStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ----------------------------------------------------------------- writing through

    @property
    def pending_writes(self) -> int:
        """Changes kept in memory that the file does not hold yet."""
        n = len(self._dirty_items) + len(self._dirty_seen) + int(self._slots_dirty)
        return n + (self.seen_count() if self._seen_all else 0)

    def retry(self) -> bool:
        """Write the pending changes; True when the file holds everything."""
        if not self._disk or not (
            self._dirty_items or self._dirty_seen or self._seen_all or self._slots_dirty
        ):
            return True
        db = self._db
        try:
            with db:
                for kind, item_id in self._dirty_items:
                    db.execute(
                        f"INSERT OR REPLACE INTO disk.items SELECT {_ITEM_COLS} FROM main.items "
                        "WHERE kind=? AND item_id=?",
                        (kind, item_id),
                    )
                if self._seen_all:
                    db.execute("DELETE FROM disk.seen")
                    db.execute(f"INSERT INTO disk.seen SELECT {_SEEN_COLS} FROM main.seen")
                else:
                    for source in self._dirty_seen:
                        db.execute("DELETE FROM disk.seen WHERE source=?", (source,))
                        db.execute(
                            f"INSERT INTO disk.seen SELECT {_SEEN_COLS} FROM main.seen "
                            "WHERE source=?",
                            (source,),
                        )
                if self._slots_dirty:
                    db.execute("DELETE FROM disk.command_slots")
                    db.execute(
                        f"INSERT INTO disk.command_slots SELECT {_SLOT_COLS} "
                        "FROM main.command_slots"
                    )
        except (sqlite3.Error, OSError) as e:
            self._write_failed(e)
            return False
        if self.last_write_error is not None:
            log.warning("version store %s: written again after %d failed writes",
                        self.path, self.write_failures)  # fmt: skip
            self.last_write_error = None
        self._dirty_items.clear()
        self._dirty_seen.clear()
        self._seen_all = self._slots_dirty = False
        return True

    def _write_failed(self, e: BaseException) -> None:
        self.write_failures += 1
        self.last_write_error = str(e)
        now = self._clock()
        if self._last_report is not None and now - self._last_report < WRITE_ERROR_INTERVAL_S:
            self._unreported += 1
            return
        self._last_report = now
        more = f"; {self._unreported} more failures not reported" if self._unreported else ""
        self._unreported = 0
        text = (
            f"the version store {self.path} cannot be written ({e}): {self.pending_writes} "
            f"changes kept in memory and retried ({self.write_failures} failed writes{more}); "
            "they are lost if the gateway stops before they are written"
        )
        log.error("%s", text)
        if self.on_write_error is not None:
            self.on_write_error(text)

    # ----------------------------------------------------------------- items

    def get(self, kind: ItemKind, item_id: int) -> StoredItem | None:
        row = self._db.execute(
            "SELECT kind, item_id, version, wire, json FROM items WHERE kind=? AND item_id=?",
            (int(kind), item_id),
        ).fetchone()
        return None if row is None else self._item(row)

    def items(
        self, kind: ItemKind | None = None, *, include_deleted: bool = True
    ) -> list[StoredItem]:
        """Current items (tombstones included unless asked), by kind then id."""
        sql = "SELECT kind, item_id, version, wire, json FROM items"
        params: tuple[Any, ...] = ()
        if kind is not None:
            sql += " WHERE kind=?"
            params = (int(kind),)
        rows = self._db.execute(sql + " ORDER BY kind, item_id", params).fetchall()
        out = [self._item(r) for r in rows]
        return out if include_deleted else [i for i in out if not i.deleted]

    def defined_ids(self, kind: ItemKind) -> set[int]:
        return {i.item_id for i in self.items(kind, include_deleted=False)}

    def apply(
        self, kind: ItemKind, item_id: int, body: ItemBody | None, js: dict[str, Any] | None
    ) -> StoredItem | None:
        """Record ``body`` as the item's new state; None when it is already the state.

        Deleting an item that never existed is also a no-op (there is nothing in
        the network to delete).
        """
        h = body_hash(kind, body)
        row = self._db.execute(
            "SELECT version, hash FROM items WHERE kind=? AND item_id=?", (int(kind), item_id)
        ).fetchone()
        if row is None and body is None:
            return None
        if row is not None and row[1] == h:
            return None
        return self._write(kind, item_id, 1 if row is None else row[0] + 1, h, body, js)

    def bump(
        self, kind: ItemKind, item_id: int, body: ItemBody | None, js: dict[str, Any] | None
    ) -> StoredItem:
        """Record ``body`` with a new version even if it equals the current one (commands)."""
        row = self._db.execute(
            "SELECT version FROM items WHERE kind=? AND item_id=?", (int(kind), item_id)
        ).fetchone()
        return self._write(
            kind, item_id, 1 if row is None else row[0] + 1, body_hash(kind, body), body, js
        )

    def bump_to(
        self,
        kind: ItemKind,
        item_id: int,
        version: int,
        body: ItemBody | None,
        js: dict[str, Any] | None,
    ) -> StoredItem:
        """Store ``body`` under ``version`` (which must be above the current one)."""
        cur = self.get(kind, item_id)
        if cur is not None and version <= cur.version:
            raise ValueError(f"version {version} is not above {cur.version}")
        return self._write(kind, item_id, version, body_hash(kind, body), body, js)

    def learn(
        self, kind: ItemKind, item_id: int, version: int, body: ItemBody | None
    ) -> StoredItem:
        """Take over ``version`` of an item the network holds (heard by a gateway
        mote), so the next definition gets a version the motes accept; the bridge
        decides when (``GatewayBridge._learn``)."""
        js = None if body is None else definition_json(kind, body)
        return self._write(kind, item_id, version, body_hash(kind, body), body, js)

    def _write(
        self,
        kind: ItemKind,
        item_id: int,
        version: int,
        h: str,
        body: ItemBody | None,
        js: dict[str, Any] | None,
    ) -> StoredItem:
        if version > MAX_VERSION:
            raise VersionOverflow(f"{kind.name} {item_id} reached version {MAX_VERSION}")
        wire = None if body is None else msgpack.packb(body.to_wire(), use_single_float=True)
        text = None if js is None else json.dumps(js, sort_keys=True)
        with self._db:
            self._db.execute(
                "INSERT OR REPLACE INTO items VALUES (?, ?, ?, ?, ?, ?, ?)",
                (int(kind), item_id, version, h, wire, text, time.time()),
            )
        if self._disk:
            self._dirty_items.add((int(kind), item_id))
            self.retry()
        return StoredItem(kind, item_id, version, body, None if js is None else dict(js))

    @staticmethod
    def _item(row: tuple[Any, ...]) -> StoredItem:
        kind = ItemKind(row[0])
        body = None if row[3] is None else _FROM_WIRE[kind](msgpack.unpackb(row[3]))
        js = None if row[4] is None else json.loads(row[4])
        return StoredItem(kind, row[1], row[2], body, js)

    # ----------------------------------------------------------------- replay dedupe

    def last_seen(self, source: str) -> str | None:
        row = self._db.execute("SELECT hash FROM seen WHERE source=?", (source,)).fetchone()
        return None if row is None else str(row[0])

    def set_seen(self, source: str, h: str) -> None:
        """Remember ``h`` for ``source``; beyond ``max_seen`` sources the least
        recently seen is forgotten (its next retained replay is applied again,
        which is harmless: an equal definition makes no new version)."""
        self._seen_tick += 1
        evicted: list[str] = []
        with self._db:
            self._db.execute(
                "INSERT OR REPLACE INTO seen VALUES (?, ?, ?)", (source, h, self._seen_tick)
            )
            if self.seen_count() > self.max_seen:
                evicted = [
                    str(r[0])
                    for r in self._db.execute(
                        "SELECT source FROM seen ORDER BY used DESC LIMIT -1 OFFSET ?",
                        (self.max_seen,),
                    )
                ]
                self._db.executemany("DELETE FROM seen WHERE source=?", [(e,) for e in evicted])
        if self._disk:
            if not self._seen_all:
                self._dirty_seen.add(source)
                self._dirty_seen.update(evicted)
                if len(self._dirty_seen) > self.max_seen:  # bounded: rewrite the table instead
                    self._dirty_seen.clear()
                    self._seen_all = True
            self.retry()

    def seen_count(self) -> int:
        return int(self._db.execute("SELECT COUNT(*) FROM seen").fetchone()[0])

    # ----------------------------------------------------------------- command slots

    def command_slot(self, name: str, n_slots: int) -> int:
        """The Drip slot of command ``name``: its own if it has one, else a free slot,
        else the least recently used one (taken over from its old name)."""
        if n_slots < 1:
            raise ValueError("n_slots must be >= 1")
        used = self._db.execute("SELECT COALESCE(MAX(used), 0) + 1 FROM command_slots").fetchone()
        tick = int(used[0])
        with self._db:
            row = self._db.execute(
                "SELECT slot FROM command_slots WHERE name=? AND slot<?", (name, n_slots)
            ).fetchone()
            if row is not None:
                self._db.execute("UPDATE command_slots SET used=? WHERE name=?", (tick, name))
                slot = int(row[0])
            else:
                slot = self._new_slot(name, n_slots, tick)
        self._slots_changed()
        return slot

    def _new_slot(self, name: str, n_slots: int, tick: int) -> int:
        self._db.execute("DELETE FROM command_slots WHERE name=?", (name,))
        taken = {
            int(r[0])
            for r in self._db.execute("SELECT slot FROM command_slots WHERE slot<?", (n_slots,))
        }
        free = [s for s in range(n_slots) if s not in taken]
        if free:
            slot = free[0]
        else:
            lru = self._db.execute(
                "SELECT slot FROM command_slots WHERE slot<? ORDER BY used LIMIT 1", (n_slots,)
            ).fetchone()
            slot = int(lru[0])
            self._db.execute("DELETE FROM command_slots WHERE slot=?", (slot,))
        self._db.execute("INSERT INTO command_slots VALUES (?, ?, ?)", (name, slot, tick))
        return slot

    def _slots_changed(self) -> None:
        if self._disk:
            self._slots_dirty = True
            self.retry()
