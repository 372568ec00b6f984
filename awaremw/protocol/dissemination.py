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
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from types import MappingProxyType
from typing import NamedTuple

from awaremw.protocol.component import Component, MoteContext
from awaremw.protocol.events import InjectSuperseded, ItemAdopted, ItemRefused
from awaremw.protocol.frames import (
    BROADCAST,
    SIG_PART_BYTES,
    SIG_PARTS,
    DripItem,
    DripSig,
    DripSummary,
    Frame,
    FrameTooLarge,
    ItemBody,
    ItemKind,
    encode,
)
from awaremw.protocol.signing import ItemSigner, ItemVerifier
from awaremw.protocol.trickle import Trickle

OnItem = Callable[[ItemKind, int, ItemBody | None, float], None]
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


class Item(NamedTuple):
    """What a mote holds for one key: a version and a body (None: deleted)."""

    version: int
    body: ItemBody | None


_MISSING = object()  # a pending item whose DripItem has not been heard yet


class _Pending:
    """A newer item version heard, waiting for its signature (or its body)."""

    __slots__ = ("body", "parts", "source", "version")

    def __init__(self, version: int, source: int) -> None:
        self.version = version
        self.body: object = _MISSING  # ItemBody | None once heard
        self.parts: list[bytes | None] = [None] * SIG_PARTS
        self.source = source


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


class Dissemination(Component):
    """Drip: one Trickle per item, plus boot-time summaries for fast catch-up."""

    def __init__(
        self, ctx: MoteContext, on_item: OnItem, parent: Callable[[], int | None] | None = None
    ) -> None:
        super().__init__(ctx)
        self.on_item = on_item
        # The mote's collection-tree parent (its next hop to a gateway mote; None:
        # no route, or a root). A version jump heard from it is taken: see
        # _on_item_frame.
        self._parent = parent
        self._items: dict[ItemKey, Item] = {}
        self._view: Mapping[ItemKey, Item] = MappingProxyType(self._items)
        self._trickles: dict[ItemKey, Trickle] = {}
        self._changed: dict[ItemKey, float] = {}  # local time of the last change
        self._digest = 0
        self._summary_repeats_left = 0
        self._summary_spacing = 0.0
        self._last_summary = float("-inf")
        self._last_answer = float("-inf")
        # Summaries identical to the one we would send, heard since our digest last
        # changed or we last sent one: at drip_k of them ours is skipped (Trickle's
        # suppression, applied to summaries; see _send_summary).
        self._summary_echoes = 0
        self._summary_asks = False  # the summary timer is an ask (_summary_soon)
        self._wanted = 0  # the most items a neighbour's summary announced
        self._ask_retries = 0  # asks left while we hold fewer than that
        self._pending_asks = 0  # asks left while an item is pending (signed items)
        self._ask_gap = 0.0  # the gap before the next of those (doubles)
        # Items of an answer waiting for its jitter (see _on_summary); an item a
        # neighbour sends at our version meanwhile leaves it.
        self._answer: set[ItemKey] = set()
        self.refused = 0  # counters for observers
        self.item_tx = 0
        self.summary_tx = 0
        self.summaries_skipped = 0
        self.sig_tx = 0
        key = ctx.config.gateway_public_key
        self.verifier: ItemVerifier | None = None if key is None else ItemVerifier(key)
        # Gateway motes only: signs what is injected (set by whoever holds the key).
        self.signer: ItemSigner | None = None
        self._pending: dict[ItemKey, _Pending] = {}  # bound: config.max_pending_items
        self._sigs: dict[ItemKey, bytes] = {}  # the held version's signature (same keys)
        # Keys anchored in the network: another mote has sent us the version we
        # held, or the gateway injected one here. From then on only steps within
        # drip_max_version_step are taken; until then (a mote that booted into a
        # forged version, alone) any version its neighbours send replaces ours.
        self._anchored: set[ItemKey] = set()
        # Keys whose version we defended against a jump since we last sent it: our
        # next transmission point is not suppressed (see _on_item_frame).
        self._contested: set[ItemKey] = set()

    # ------------------------------------------------------------------ public API

    @property
    def items(self) -> Mapping[ItemKey, Item]:
        """Read-only live view of every held item, tombstones (body None) included."""
        return self._view

    @property
    def digest(self) -> int:
        return self._digest

    def version_of(self, kind: ItemKind, item_id: int) -> int | None:
        it = self._items.get((kind, item_id))
        return None if it is None else it.version

    def signature_of(self, kind: ItemKind, item_id: int) -> bytes | None:
        """The gateway's signature of the held version (None: unsigned items)."""
        return self._sigs.get((kind, item_id))

    def trickle(self, kind: ItemKind, item_id: int) -> Trickle | None:
        """The item's Trickle timer (for observers and tests; do not drive it)."""
        return self._trickles.get((kind, item_id))

    def capacity(self, kind: ItemKind) -> int:
        c = self.ctx.config
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
        cur = self._items.get((frame.kind, item_id))
        if cur is not None and not newer(version, cur.version):
            if version != cur.version:
                self.ctx.emit(InjectSuperseded(frame.kind, item_id, version, cur.version))
            return False
        if not self.accepts(frame.kind, item_id):
            raise ItemTableFull(
                f"{frame.kind.name} table full ({self.capacity(frame.kind)} live items)"
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
        cfg = self.ctx.config
        self._summary_repeats_left = cfg.drip_summary_repeats
        self._summary_spacing = cfg.drip_summary_spacing
        self.timers.set("summary", now + self.ctx.rng.uniform(0.0, cfg.drip_summary_delay))

    def on_frame(self, frame: Frame, rssi_dbm: float, now: float) -> None:
        if type(frame) is DripSummary:  # the most frequent, and most often a no-op
            self._on_summary(frame, now)
        elif isinstance(frame, DripItem):
            self._on_item_frame(frame, now)
        elif isinstance(frame, DripSummary):
            self._on_summary(frame, now)
        elif isinstance(frame, DripSig):
            self._on_sig(frame, now)

    def on_timer(self, name: object, now: float) -> None:
        if name == "summary":
            asked = self._summary_asks
            self._send_summary(now, may_skip=not asked)
            self._summary_asks = False
            if self._summary_repeats_left > 0:
                self._summary_repeats_left -= 1
                self.timers.set("summary", now + self._summary_spacing)
                self._summary_spacing *= 2.0
            if asked and len(self._items) < self._wanted and self._ask_retries > 0:
                # Still behind a neighbour that announced more: the answers to our
                # ask may all have been dropped for one we did not hear. Ask again.
                self._ask_retries -= 1
                self._summary_soon(now)
            elif asked and self._pending and self._pending_asks > 0:
                # An item still waits for a signature part: each answer is three
                # frames, all needed, from a neighbour as busy as the gateway mote
                # can be. Ask again, backing off (see _pending_for).
                self._pending_asks -= 1
                self._ask_gap *= 2.0
                self._summary_soon(now, self._ask_gap)
            return
        if name == "answer":
            # The items no neighbour sent at our version meanwhile, the last changed
            # first (what the asker lacks is most likely new: it goes out before a
            # busy channel drops the rest of the burst); ties in table order.
            keys = [k for k in self._items if k in self._answer]
            for k in sorted(keys, key=self._changed.__getitem__, reverse=True):
                self._broadcast(k)
            self._answer.clear()
            return
        assert isinstance(name, tuple) and name[0] == "item", name
        key: ItemKey = (name[1], name[2])
        trickle = self._trickles[key]
        if trickle.handle_timer(now):
            self._broadcast(key)
        self._arm(key)

    def _broadcast(self, key: ItemKey) -> None:
        """Put the item we hold for ``key`` on the air (and its signature parts)."""
        it = self._items[key]
        self._contested.discard(key)
        sig = self._sigs.get(key)
        nid = self.ctx.node_id
        self.send(DripItem(nid, BROADCAST, key[0], key[1], it.version, it.body))
        self.item_tx += 1
        if sig is not None:
            for p in range(SIG_PARTS):
                chunk = sig[p * SIG_PART_BYTES : (p + 1) * SIG_PART_BYTES]
                self.send(DripSig(nid, BROADCAST, key[0], key[1], it.version, p, chunk))
                self.sig_tx += 1

    # ------------------------------------------------------------------ internals

    def _on_item_frame(self, f: DripItem, now: float) -> None:
        key = (f.kind, f.item_id)
        cur = self._items.get(key)
        if cur is not None and f.version == cur.version:
            self._anchored.add(key)  # another mote holds our version: anchored
            if key not in self._contested:
                self._trickles[key].hear_consistent()
            self._answer.discard(key)  # a neighbour answered with it: ours is redundant
            return
        if cur is not None and self.verifier is None and self._is_jump(f.version, cur.version):
            if key in self._anchored and not self._from_parent(f.src):
                # A jump no gateway makes (a forged or garbled version): keep ours,
                # which our neighbours confirmed, and tell the sender soon, even if
                # neighbours say the same first: we may be the sender's parent, the
                # one it follows (below).
                self.refused += 1
                self.ctx.emit(ItemRefused(f.kind, f.item_id, f.version, f.src, "version jump"))
                self._contested.add(key)
                self._trickles[key].reset(now)
                self._arm(key)
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
            if self.verifier is None:
                self._adopt(f, now, source=f.src)
            else:
                pend = self._pending_for(key, f.version, f.src, now)
                if pend is not None:
                    pend.body = f.item
                    self._try_complete(key, pend, now)
        else:  # older (serial arithmetic): the sender is behind
            self._trickles[key].reset(now)
            self._arm(key)

    def _from_parent(self, src: int) -> bool:
        return self._parent is not None and src == self._parent()

    def _is_jump(self, heard: int, held: int) -> bool:
        """Whether ``heard`` lies more than ``drip_max_version_step`` versions away
        from ``held`` on the u32 circle, ahead or behind."""
        step = self.ctx.config.drip_max_version_step
        d = (heard - held) & _M32
        return step < d < (1 << 32) - step

    def _pending_for(self, key: ItemKey, version: int, src: int, now: float) -> _Pending | None:
        """The pending entry of ``key`` at ``version`` (made if newer than a pending
        one; None if an even newer version is pending already)."""
        pend = self._pending.get(key)
        if pend is not None:
            if pend.version == version:
                return pend
            if not newer(version, pend.version):
                return None
            del self._pending[key]
        cfg = self.ctx.config
        if len(self._pending) >= cfg.max_pending_items:
            del self._pending[next(iter(self._pending))]  # the oldest
        pend = self._pending[key] = _Pending(version, src)
        # A neighbour holds what we lack: ask (our summary), and again while it is
        # pending (drip_pending_asks times, backing off), so that a lost part comes
        # in an answer within drip_answer_delay rather than at the haves' next
        # Trickle point, which doubles away (romeo4r on the virtual clock: a
        # command waited next to the gateway mote for over 100 s). Normally the
        # parts follow at once, and the ask is the summary we send after adopting.
        self._pending_asks = cfg.drip_pending_asks
        self._ask_gap = cfg.drip_summary_min_gap
        self._summary_soon(now)
        return pend

    def _on_sig(self, f: DripSig, now: float) -> None:
        if self.verifier is None:
            return
        key = (f.kind, f.item_id)
        cur = self._items.get(key)
        if cur is not None and not newer(f.version, cur.version):
            return  # a signature of what we hold (or older)
        pend = self._pending_for(key, f.version, f.src, now)
        if pend is not None:
            pend.parts[f.part] = f.chunk
            self._try_complete(key, pend, now)

    def _try_complete(self, key: ItemKey, pend: _Pending, now: float) -> None:
        if pend.body is _MISSING or any(p is None for p in pend.parts):
            return
        del self._pending[key]
        body: ItemBody | None = pend.body  # type: ignore[assignment]
        sig = b"".join(p for p in pend.parts if p is not None)
        assert self.verifier is not None
        if not self.verifier.verify(key[0], key[1], pend.version, body, sig):
            self.refused += 1
            self.ctx.emit(ItemRefused(key[0], key[1], pend.version, pend.source, "bad signature"))
            return
        f = DripItem(self.ctx.node_id, BROADCAST, key[0], key[1], pend.version, body)
        self._adopt(f, now, source=pend.source, sig=sig)

    def _on_summary(self, f: DripSummary, now: float) -> None:
        n = len(self._items)
        if f.digest == self._digest and f.n_items == n:
            self._summary_echoes += 1
            return
        cfg = self.ctx.config
        if f.n_items > n:
            # The sender holds more: ask it to speak up (our summary, with fewer
            # items, makes it answer). Our Trickles stay as they are: resetting
            # them re-sent every item we hold, which the sender most likely holds
            # too (it cost three frames of old items for each new one spreading
            # through romeo4r). Should we hold a newer version of something, the
            # sender's answer carries its older copy, which resets that item here.
            self._wanted = max(self._wanted, f.n_items)
            self._ask_retries = cfg.drip_summary_repeats
            self._summary_soon(now)
            return
        if not n:
            return
        if f.n_items < n and now - self._last_answer >= cfg.drip_summary_min_gap:
            # The sender holds fewer items: it lacks some. Trickle would let our
            # neighbours' transmissions suppress ours for a whole interval, yet
            # the sender may hear only us (a hidden "have-not" at the edge of the
            # items' spread), so answer within drip_answer_delay, at most once
            # per min_gap. Every have of its neighbourhood heard the same summary:
            # an item one of them sends at our version during our wait is dropped
            # from our answer (the sender asks again if it still lacks it).
            self._last_answer = now
            self._answer = set(self._items)
            self.timers.set("answer", now + self.ctx.rng.uniform(0.0, cfg.drip_answer_delay))
            return
        # As many items, other versions (or an answer inside the rate limit): who
        # is ahead is unknown, so speak up about everything soon; neighbours that
        # say the same suppress each other, and whoever is behind adopts.
        for key, trickle in self._trickles.items():
            trickle.reset(now)
            self._arm(key)

    def _summary_soon(self, now: float, gap: float = 0.0) -> None:
        """Send a summary after a short random wait. Within the rate limit of our
        last summary (or ``gap`` after it, if longer), once the limit allows rather
        than not at all: a summary sent just before we learnt something told the
        neighbours nothing of it."""
        cfg = self.ctx.config
        earliest = self._last_summary + max(cfg.drip_summary_min_gap, gap)
        due = max(now, earliest) + self.ctx.rng.uniform(0.0, cfg.drip_summary_delay)
        cur = self.timers.get("summary")
        if cur is None or due < cur:
            self.timers.set("summary", due)
        # The next summary is an ask, even a boot repeat already due sooner: it is
        # not skipped, and it is repeated while we still lack items.
        self._summary_asks = True

    def _send_summary(self, now: float, may_skip: bool = False) -> None:
        echoes, self._summary_echoes = self._summary_echoes, 0
        if may_skip and echoes >= self.ctx.config.drip_k:
            # A boot summary or its repeat, and drip_k neighbours said the same
            # since our digest last changed: their summaries made the have-nots
            # around ask and the haves answer (a network that boots at once would
            # otherwise send a summary per mote, and the repeats 2 s later fall in
            # the wave of its first definitions). Asks and the summary announcing
            # an adoption (_summary_soon) are never skipped: they are how the
            # have-nots at a wave's edge learn of items and get them (skipping
            # those slowed a wave by half, bench dissemination).
            self.summaries_skipped += 1
            return
        self._last_summary = now
        self.summary_tx += 1
        n = min(len(self._items), 0xFFFF)
        self.send(DripSummary(self.ctx.node_id, BROADCAST, self._digest, n))

    def _adopt(self, f: DripItem, now: float, source: int | None, sig: bytes | None = None) -> None:
        key = (f.kind, f.item_id)
        cur = self._items.get(key)
        if source is not None:
            reason = self._refusal(f, cur)
            if reason is not None:
                self.refused += 1
                self.ctx.emit(ItemRefused(f.kind, f.item_id, f.version, source, reason))
                return
        if cur is None:
            self._make_room(f.kind)
        else:
            self._digest = (self._digest - digest_term(f.kind, f.item_id, cur.version)) & _M32
        self._digest = (self._digest + digest_term(f.kind, f.item_id, f.version)) & _M32
        self._summary_echoes = 0  # echoes of the digest we held no longer count
        self._items[key] = Item(f.version, f.item)
        if sig is None:
            self._sigs.pop(key, None)
        else:
            self._sigs[key] = sig
        self._changed[key] = now
        trickle = self._trickles.get(key)
        if trickle is None:
            cfg = self.ctx.config
            trickle = self._trickles[key] = Trickle(
                cfg.drip_tau_l, cfg.drip_tau_h, cfg.drip_k, self.ctx.rng
            )
        trickle.reset(now)
        self._arm(key)
        # Say so in a summary soon: a neighbour that finished its boot summaries
        # before this item existed learns it exists and asks for it (its own
        # summary, with fewer items, makes us answer unsuppressed).
        self._summary_soon(now)
        self.ctx.emit(ItemAdopted(f.kind, f.item_id, f.version, f.item is None, source))
        # Components hear about content changes only: a tombstone for a key we
        # never held live changes nothing for them.
        if f.item is not None or (cur is not None and cur.body is not None):
            self.on_item(f.kind, f.item_id, f.item, now)

    def _refusal(self, f: DripItem, cur: Item | None) -> str | None:
        if cur is None and not self.accepts(f.kind, f.item_id):
            return f"{f.kind.name} table full"
        try:
            encode(f, self.ctx.config.mtu)
        except FrameTooLarge as e:
            return str(e)  # could not pass it on
        return None

    def _make_room(self, kind: ItemKind) -> None:
        same = [k for k in self._items if k[0] == kind]
        if len(same) < self.capacity(kind):
            return
        tombs = [k for k in same if self._items[k].body is None]
        victim = min(tombs, key=self._changed.__getitem__)  # accepts() guaranteed one
        old = self._items.pop(victim)
        self._digest = (self._digest - digest_term(victim[0], victim[1], old.version)) & _M32
        del self._trickles[victim], self._changed[victim]
        self._sigs.pop(victim, None)
        self._anchored.discard(victim)
        self._contested.discard(victim)
        self.timers.cancel(("item", *victim))

    def _arm(self, key: ItemKey) -> None:
        d = self._trickles[key].next_deadline()
        name = ("item", key[0], key[1])
        if d is None:
            self.timers.cancel(name)
        else:
            self.timers.set(name, d)
