"""Epidemic dissemination of versioned items, in the style of Drip (Tolle & Culler).

Every item is keyed ``(ItemKind, item_id)`` and carries a u32 version and a
body (:class:`GroupTypeDef`, :class:`ChannelDef`, :class:`CommandDef`) or
``None``: a deletion is a version too, kept as a tombstone so that an older
copy still held by a mote that was off cannot come back to life.

Versions compare with RFC 1982 serial-number arithmetic (:func:`newer`): a
version is newer if it is ahead by less than 2**31 modulo 2**32, so no version
is ever the last one (``0xFFFFFFFF`` is followed by ``0``) and a foreign item
at any version can be superseded by the next one (the gateway's rule,
docs/protocol-dissemination.md, *Versions*).

Each item has its own :class:`~awaremw.protocol.trickle.Trickle` (Drip's
design). On hearing ``DripItem``:

* an older version: the sender is behind, reset that item's Trickle (we will
  tell it soon);
* a newer version: adopt it, tell the mote (``on_item``), reset the Trickle
  (we pass it on soon);
* the same version: a consistent transmission (counts toward suppression).

Catching up without the gateway: at boot a mote broadcasts a
:class:`DripSummary` (an order-independent digest of every ``(kind, id,
version)`` it holds, and their number) after a short random wait, and repeats
it a couple of times in case it was lost. A neighbour whose digest differs
acts on who holds more: if the sender holds fewer items, it *answers* within
``drip_answer_delay`` with every item it holds, the last changed first,
leaving out what another answered meanwhile; if the sender holds more, it
*asks* (its own summary, rate-limited, again if the answers miss it); if both
hold as many, it resets every item's Trickle, so within about ``drip_tau_l``
both re-broadcast and whoever is behind adopts. A mote that adopts an item
says so in a summary, so the neighbours that lack it ask. A mote holding a
signed item pending (a signature part missed) asks too, and again with
doubling gaps while it is pending. A boot summary echoed by ``drip_k``
neighbours is skipped. See docs/protocol-dissemination.md.

Signed items (``config.gateway_public_key`` set): every item version carries
the gateway's Ed25519 signature (:mod:`awaremw.protocol.signing`), sent after
the item in :data:`~awaremw.protocol.frames.SIG_PARTS` :class:`DripSig`
frames. A mote holds a newer item heard from the radio *pending* (at most
``max_pending_items``, the oldest evicted) until its signature parts are in,
verifies it, and only then adopts it, applies it and passes it on (with its
signature); a bad signature is an :class:`ItemRefused` event (``"bad
signature"``). Versions and Trickle suppression work as before on DripItem
frames.

Bounds: a mote holds at most ``max_group_types`` group types,
``max_channels`` channels and ``max_command_slots`` commands, tombstones
included. A new key on a full table evicts the tombstone of that kind changed
longest ago; with no tombstone to evict the item is refused (an
:class:`ItemRefused` event; :meth:`Dissemination.inject` raises instead,
because the gateway should have checked :meth:`Dissemination.accepts`).

:class:`Dissemination` is the facade the mote holds; its parts have a module
each: the version rules and the item table (:mod:`~awaremw.protocol.drip_items`),
the item Trickles and the summaries (:mod:`~awaremw.protocol.drip_gossip`), the
signed items pending (:mod:`~awaremw.protocol.drip_signed`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

from awaremw.protocol.component import Component, MoteContext
from awaremw.protocol.drip_gossip import (
    ANSWER_TIMER,
    SUMMARY_TIMER,
    ItemTrickles,
    Summaries,
)
from awaremw.protocol.drip_items import (
    Item,
    ItemKey,
    ItemTable,
    ItemTableFull,
    digest_of,
    digest_term,
    is_jump,
    newer,
    next_version,
)
from awaremw.protocol.drip_signed import PendingItems, Signed
from awaremw.protocol.events import InjectSuperseded, ItemAdopted, ItemRefused
from awaremw.protocol.frames import (
    BROADCAST,
    DripItem,
    DripSig,
    DripSummary,
    Frame,
    ItemBody,
    ItemKind,
    encode,
)
from awaremw.protocol.signing import ItemSigner, ItemVerifier
from awaremw.protocol.trickle import Trickle

OnItem = Callable[[ItemKind, int, ItemBody | None, float], None]

# The version rules and records, where the users of dissemination have always found them.
__all__ = [
    "Dissemination",
    "Item",
    "ItemKey",
    "ItemTableFull",
    "OnItem",
    "digest_of",
    "digest_term",
    "newer",
    "next_version",
]


class Dissemination(Component):
    """Drip: one Trickle per item, plus boot-time summaries for fast catch-up.

    The facade the mote holds: it routes frames and timers to its parts and
    decides, for every version heard or injected, whether to take it."""

    def __init__(
        self, ctx: MoteContext, on_item: OnItem, parent: Callable[[], int | None] | None = None
    ) -> None:
        super().__init__(ctx)
        self.on_item = on_item
        # The mote's collection-tree parent (its next hop to a gateway mote; None:
        # no route, or a root). A version jump heard from it is taken: see
        # _on_item_frame.
        self._parent = parent
        cfg = ctx.config
        self._table = ItemTable(cfg)
        self._trickles = ItemTrickles(ctx, self.timers, self.send, self._table)
        self._summaries = Summaries(ctx, self.timers, self.send, self._table, self._trickles)
        self.refused = 0  # counter for observers
        key = cfg.gateway_public_key
        self.verifier: ItemVerifier | None = None if key is None else ItemVerifier(key)
        # Gateway motes only: signs what is injected (set by whoever holds the key).
        self.signer: ItemSigner | None = None
        self._pending: PendingItems | None = (
            None if self.verifier is None else PendingItems(self.verifier, cfg, self._summaries)
        )
        # Keys anchored in the network: another mote has sent us the version we
        # held, or the gateway injected one here. From then on only steps within
        # drip_max_version_step are taken; until then (a mote that booted into a
        # forged version, alone) any version its neighbours send replaces ours.
        self._anchored: set[ItemKey] = set()

    # ------------------------------------------------------------------ public API

    @property
    def items(self) -> Mapping[ItemKey, Item]:
        """Read-only live view of every held item, tombstones (body None) included."""
        return self._table.items

    @property
    def digest(self) -> int:
        return self._table.digest

    @property
    def item_tx(self) -> int:
        return self._trickles.item_tx

    @property
    def sig_tx(self) -> int:
        return self._trickles.sig_tx

    @property
    def summary_tx(self) -> int:
        return self._summaries.summary_tx

    @property
    def summaries_skipped(self) -> int:
        return self._summaries.skipped

    def version_of(self, kind: ItemKind, item_id: int) -> int | None:
        it = self._table.get((kind, item_id))
        return None if it is None else it.version

    def signature_of(self, kind: ItemKind, item_id: int) -> bytes | None:
        """The gateway's signature of the held version (None: unsigned items)."""
        return self._table.signature((kind, item_id))

    def trickle(self, kind: ItemKind, item_id: int) -> Trickle | None:
        """The item's Trickle timer (for observers and tests; do not drive it)."""
        return self._trickles.get((kind, item_id))

    def capacity(self, kind: ItemKind) -> int:
        return self._table.capacity(kind)

    def accepts(self, kind: ItemKind, item_id: int) -> bool:
        """Whether an item for this key could be stored now (known key, free slot,
        or a tombstone of the same kind to evict)."""
        return self._table.accepts(kind, item_id)

    def inject(
        self,
        kind: ItemKind,
        item_id: int,
        version: int,
        item: ItemBody | None,
        now: float,
        signature: bytes | None = None,
    ) -> bool:
        """Inject an item at this (gateway) mote. Versions not newer than the one held
        are ignored (returns False), so re-injecting is harmless.

        With signed items, ``signature`` is the gateway's (made by :attr:`signer`
        when not given). Raises ValueError for a body of the wrong kind or
        out-of-range fields, or a missing or wrong signature, :class:`FrameTooLarge`
        if it cannot fit the MTU, :class:`ItemTableFull` if the kind's table has
        no room (see :meth:`accepts`).
        """
        frame = DripItem(self.ctx.node_id, BROADCAST, kind, item_id, version, item)
        encode(frame, self.ctx.config.mtu)  # raises FrameTooLarge before we keep it
        cur = self._table.get((frame.kind, item_id))
        if cur is not None and not newer(version, cur.version):
            if version != cur.version:
                self.ctx.emit(InjectSuperseded(frame.kind, item_id, version, cur.version))
            return False
        if not self._table.accepts(frame.kind, item_id):
            raise ItemTableFull(
                f"{frame.kind.name} table full ({self._table.capacity(frame.kind)} live items)"
            )
        sig = None
        if self.verifier is not None:
            sig = signature
            if sig is None and self.signer is not None:
                sig = self.signer.sign(frame.kind, item_id, version, item)
            if sig is None:
                raise ValueError(
                    "signed dissemination: an injected item needs the gateway's signature"
                )
            if not self.verifier.verify(frame.kind, item_id, version, item, sig):
                raise ValueError(
                    "signed dissemination: the signature does not match the gateway key"
                )
        self._adopt(frame, now, source=None, sig=sig)
        self._anchored.add((frame.kind, item_id))  # the source of truth's own version
        return True

    # ------------------------------------------------------------------ Component hooks

    def start(self, now: float) -> None:
        self._summaries.start(now)

    def on_frame(self, frame: Frame, rssi_dbm: float, now: float) -> None:
        if type(frame) is DripSummary:  # the most frequent, and most often a no-op
            self._summaries.hear(frame, now)
        elif isinstance(frame, DripItem):
            self._on_item_frame(frame, now)
        elif isinstance(frame, DripSummary):
            self._summaries.hear(frame, now)
        elif isinstance(frame, DripSig):
            self._on_sig(frame, now)

    def on_timer(self, name: object, now: float) -> None:
        if name == SUMMARY_TIMER:
            pending = self._pending is not None and len(self._pending) > 0
            self._summaries.on_summary_timer(now, pending)
        elif name == ANSWER_TIMER:
            self._summaries.on_answer_timer()
        else:
            self._trickles.on_timer(name, now)

    # ------------------------------------------------------------------ internals

    def _on_item_frame(self, f: DripItem, now: float) -> None:
        key = (f.kind, f.item_id)
        cur = self._table.get(key)
        if cur is not None and f.version == cur.version:
            self._anchored.add(key)  # another mote holds our version: anchored
            self._trickles.hear_consistent(key)
            self._summaries.answered(key)  # a neighbour answered with it: ours is redundant
            return
        step = self.ctx.config.drip_max_version_step
        if cur is not None and self.verifier is None and is_jump(f.version, cur.version, step):
            if key in self._anchored and not (self._parent is not None and f.src == self._parent()):
                # A jump no gateway makes (a forged or garbled version): keep ours,
                # which our neighbours confirmed, and tell the sender soon, even if
                # neighbours say the same first: we may be the sender's parent, the
                # one it follows (below).
                self.refused += 1
                self.ctx.emit(ItemRefused(f.kind, f.item_id, f.version, f.src, "version jump"))
                self._trickles.contest(key, now)
                return
            # Nobody ever echoed a version of ours (we took it alone, e.g. a forged
            # one at boot), or our parent holds the other one: the network's
            # version replaces ours, older or not. An attacker can anchor a forged
            # version at a few motes (its repeats echo it), and the gateway mote
            # never takes it, so nothing supersedes it there; the tree's version
            # flows down from the gateway mote, parent to child, and dissolves it.
            self._adopt(f, now, source=f.src)
            return
        if cur is None or newer(f.version, cur.version):
            if self._pending is None:
                self._adopt(f, now, source=f.src)
            else:
                self._verified(self._pending.hear_item(f, now), now)
        else:  # older (serial arithmetic): the sender is behind
            self._trickles.reset(key, now)

    def _on_sig(self, f: DripSig, now: float) -> None:
        if self._pending is None:
            return
        cur = self._table.get((f.kind, f.item_id))
        if cur is not None and not newer(f.version, cur.version):
            return  # a signature of what we hold (or older)
        self._verified(self._pending.hear_sig(f, now), now)

    def _verified(self, s: Signed | None, now: float) -> None:
        """A pending version complete (None: not yet): adopt it, or refuse it."""
        if s is None:
            return
        kind, item_id = s.key
        if not s.valid:
            self.refused += 1
            self.ctx.emit(ItemRefused(kind, item_id, s.version, s.source, "bad signature"))
            return
        f = DripItem(self.ctx.node_id, BROADCAST, kind, item_id, s.version, s.body)
        self._adopt(f, now, source=s.source, sig=s.sig)

    def _adopt(self, f: DripItem, now: float, source: int | None, sig: bytes | None = None) -> None:
        key = (f.kind, f.item_id)
        table = self._table
        cur = table.get(key)
        if source is not None:
            reason = table.refusal(f, cur)
            if reason is not None:
                self.refused += 1
                self.ctx.emit(ItemRefused(f.kind, f.item_id, f.version, source, reason))
                return
        if cur is None:
            victim = table.make_room(f.kind)
            if victim is not None:  # its tombstone goes, and all we knew of it
                self._trickles.forget(victim)
                self._anchored.discard(victim)
        table.put(f, cur, sig, now)
        self._trickles.adopted(key, now)
        self._summaries.changed(now)
        self.ctx.emit(ItemAdopted(f.kind, f.item_id, f.version, f.item is None, source))
        # Components hear about content changes only: a tombstone for a key we
        # never held live changes nothing for them.
        if f.item is not None or (cur is not None and cur.body is not None):
            self.on_item(f.kind, f.item_id, f.item, now)
