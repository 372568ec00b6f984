"""How the items spread (:mod:`awaremw.protocol.dissemination`): each held
item's Trickle, which paces its broadcasts (Drip's design), and the summaries
(a digest of the table and its size) by which neighbours find out who lacks
what: the rules of the *Catching up* paragraphs of docs/protocol-dissemination.md.
"""

from __future__ import annotations

from collections.abc import Callable

from awaremw.protocol.component import MoteContext
from awaremw.protocol.core import Transmission
from awaremw.protocol.drip_items import ItemKey, ItemTable
from awaremw.protocol.frames import (
    BROADCAST,
    SIG_PART_BYTES,
    SIG_PARTS,
    DripItem,
    DripSig,
    DripSummary,
    Frame,
)
from awaremw.protocol.timers import TimerSet
from awaremw.protocol.trickle import Trickle

ITEM_TIMER = "item"  # an item's timer is named (ITEM_TIMER, kind, item_id)
SUMMARY_TIMER = "summary"
ANSWER_TIMER = "answer"


class ItemTrickles:
    """One Trickle per held item, and the broadcasts of the item it paces."""

    def __init__(
        self,
        ctx: MoteContext,
        timers: TimerSet,
        send: Callable[[Frame], Transmission],
        table: ItemTable,
    ) -> None:
        self._ctx = ctx
        self._timers = timers
        self._send = send
        self._table = table
        self._trickles: dict[ItemKey, Trickle] = {}
        # Keys whose version we defended against a jump since we last sent it: our
        # next transmission point is not suppressed (see Dissemination._on_item_frame).
        self._contested: set[ItemKey] = set()
        self.item_tx = 0  # counters for observers
        self.sig_tx = 0

    def get(self, key: ItemKey) -> Trickle | None:
        return self._trickles.get(key)

    def hear_consistent(self, key: ItemKey) -> None:
        """A neighbour sent the version we hold (counts toward suppression,
        unless we defend that version)."""
        if key not in self._contested:
            self._trickles[key].hear_consistent()

    def reset(self, key: ItemKey, now: float) -> None:
        self._trickles[key].reset(now)
        self._arm(key)

    def contest(self, key: ItemKey, now: float) -> None:
        """We keep our version against a jump: speak up soon, unsuppressed."""
        self._contested.add(key)
        self.reset(key, now)

    def reset_all(self, now: float) -> None:
        for key, trickle in self._trickles.items():
            trickle.reset(now)
            self._arm(key)

    def adopted(self, key: ItemKey, now: float) -> None:
        """The table holds a new version of ``key``: pass it on soon."""
        trickle = self._trickles.get(key)
        if trickle is None:
            cfg = self._ctx.config
            trickle = self._trickles[key] = Trickle(
                cfg.drip_tau_l, cfg.drip_tau_h, cfg.drip_k, self._ctx.rng
            )
        trickle.reset(now)
        self._arm(key)

    def forget(self, key: ItemKey) -> None:
        """The table evicted ``key``."""
        del self._trickles[key]
        self._contested.discard(key)
        self._timers.cancel((ITEM_TIMER, *key))

    def on_timer(self, name: object, now: float) -> None:
        assert isinstance(name, tuple) and name[0] == ITEM_TIMER, name
        key: ItemKey = (name[1], name[2])
        trickle = self._trickles[key]
        if trickle.handle_timer(now):
            self.broadcast(key)
        self._arm(key)

    def broadcast(self, key: ItemKey) -> None:
        """Put the item we hold for ``key`` on the air (and its signature parts)."""
        it = self._table.items[key]
        self._contested.discard(key)
        sig = self._table.signature(key)
        nid = self._ctx.node_id
        self._send(DripItem(nid, BROADCAST, key[0], key[1], it.version, it.body))
        self.item_tx += 1
        if sig is not None:
            for p in range(SIG_PARTS):
                chunk = sig[p * SIG_PART_BYTES : (p + 1) * SIG_PART_BYTES]
                self._send(DripSig(nid, BROADCAST, key[0], key[1], it.version, p, chunk))
                self.sig_tx += 1

    def _arm(self, key: ItemKey) -> None:
        d = self._trickles[key].next_deadline()
        name = (ITEM_TIMER, key[0], key[1])
        if d is None:
            self._timers.cancel(name)
        else:
            self._timers.set(name, d)


class Summaries:
    """The summaries a mote sends (at boot, to ask, after adopting) and what it
    does on hearing one: answer, ask, or reset every item's Trickle."""

    def __init__(
        self,
        ctx: MoteContext,
        timers: TimerSet,
        send: Callable[[Frame], Transmission],
        table: ItemTable,
        trickles: ItemTrickles,
    ) -> None:
        self._ctx = ctx
        self._timers = timers
        self._send = send
        self._table = table
        self._trickles = trickles
        self._repeats_left = 0
        self._spacing = 0.0
        self._last_summary = float("-inf")
        self._last_answer = float("-inf")
        # Summaries identical to the one we would send, heard since our digest last
        # changed or we last sent one: at drip_k of them ours is skipped (Trickle's
        # suppression, applied to summaries; see _send_summary).
        self._echoes = 0
        self._asks = False  # the summary timer is an ask (soon)
        self._wanted = 0  # the most items a neighbour's summary announced
        self._ask_retries = 0  # asks left while we hold fewer than that
        self._pending_asks = 0  # asks left while an item is pending (signed items)
        self._ask_gap = 0.0  # the gap before the next of those (doubles)
        # Items of an answer waiting for its jitter (see hear); an item a
        # neighbour sends at our version meanwhile leaves it.
        self._answer: set[ItemKey] = set()
        self.summary_tx = 0  # counters for observers
        self.skipped = 0

    def start(self, now: float) -> None:
        cfg = self._ctx.config
        self._repeats_left = cfg.drip_summary_repeats
        self._spacing = cfg.drip_summary_spacing
        self._timers.set(SUMMARY_TIMER, now + self._ctx.rng.uniform(0.0, cfg.drip_summary_delay))

    def hear(self, f: DripSummary, now: float) -> None:
        n = len(self._table)
        if f.digest == self._table.digest and f.n_items == n:
            self._echoes += 1
            return
        cfg = self._ctx.config
        if f.n_items > n:
            # The sender holds more: ask it to speak up (our summary, with fewer
            # items, makes it answer). Our Trickles stay as they are: resetting
            # them re-sent every item we hold, which the sender most likely holds
            # too (it cost three frames of old items for each new one spreading
            # through romeo4r). Should we hold a newer version of something, the
            # sender's answer carries its older copy, which resets that item here.
            self._wanted = max(self._wanted, f.n_items)
            self._ask_retries = cfg.drip_summary_repeats
            self.soon(now)
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
            self._answer = set(self._table.items)
            self._timers.set(ANSWER_TIMER, now + self._ctx.rng.uniform(0.0, cfg.drip_answer_delay))
            return
        # As many items, other versions (or an answer inside the rate limit): who
        # is ahead is unknown, so speak up about everything soon; neighbours that
        # say the same suppress each other, and whoever is behind adopts.
        self._trickles.reset_all(now)

    def answered(self, key: ItemKey) -> None:
        """A neighbour sent ``key`` at our version: our answer need not."""
        self._answer.discard(key)

    def soon(self, now: float, gap: float = 0.0) -> None:
        """Send a summary after a short random wait. Within the rate limit of our
        last summary (or ``gap`` after it, if longer), once the limit allows rather
        than not at all: a summary sent just before we learnt something told the
        neighbours nothing of it."""
        cfg = self._ctx.config
        earliest = self._last_summary + max(cfg.drip_summary_min_gap, gap)
        due = max(now, earliest) + self._ctx.rng.uniform(0.0, cfg.drip_summary_delay)
        cur = self._timers.get(SUMMARY_TIMER)
        if cur is None or due < cur:
            self._timers.set(SUMMARY_TIMER, due)
        # The next summary is an ask, even a boot repeat already due sooner: it is
        # not skipped, and it is repeated while we still lack items.
        self._asks = True

    def changed(self, now: float) -> None:
        """The table adopted an item: say so in a summary soon, so that a
        neighbour that finished its boot summaries before this item existed
        learns it exists and asks for it (its own summary, with fewer items,
        makes us answer unsuppressed). Echoes of the old digest no longer count."""
        self._echoes = 0
        self.soon(now)

    def ask_while_pending(self, now: float) -> None:
        """A signed item became pending: a neighbour holds what we lack. Ask, and
        again while it is pending (drip_pending_asks times, backing off), so that
        a lost part comes in an answer within drip_answer_delay rather than at
        the haves' next Trickle point, which doubles away (romeo4r on the virtual
        clock: a command waited next to the gateway mote for over 100 s).
        Normally the parts follow at once, and the ask is the summary we send
        after adopting."""
        cfg = self._ctx.config
        self._pending_asks = cfg.drip_pending_asks
        self._ask_gap = cfg.drip_summary_min_gap
        self.soon(now)

    def on_summary_timer(self, now: float, pending: bool) -> None:
        """Our summary is due (``pending``: a signed item waits for parts)."""
        asked = self._asks
        self._send_summary(now, may_skip=not asked)
        self._asks = False
        if self._repeats_left > 0:
            self._repeats_left -= 1
            self._timers.set(SUMMARY_TIMER, now + self._spacing)
            self._spacing *= 2.0
        if asked and len(self._table) < self._wanted and self._ask_retries > 0:
            # Still behind a neighbour that announced more: the answers to our
            # ask may all have been dropped for one we did not hear. Ask again.
            self._ask_retries -= 1
            self.soon(now)
        elif asked and pending and self._pending_asks > 0:
            # An item still waits for a signature part: each answer is three
            # frames, all needed, from a neighbour as busy as the gateway mote
            # can be. Ask again, backing off (see ask_while_pending).
            self._pending_asks -= 1
            self._ask_gap *= 2.0
            self.soon(now, self._ask_gap)

    def on_answer_timer(self) -> None:
        # The items no neighbour sent at our version meanwhile, the last changed
        # first (what the asker lacks is most likely new: it goes out before a
        # busy channel drops the rest of the burst); ties in table order.
        for k in self._table.last_changed_first(self._answer):
            self._trickles.broadcast(k)
        self._answer.clear()

    def _send_summary(self, now: float, may_skip: bool) -> None:
        echoes, self._echoes = self._echoes, 0
        if may_skip and echoes >= self._ctx.config.drip_k:
            # A boot summary or its repeat, and drip_k neighbours said the same
            # since our digest last changed: their summaries made the have-nots
            # around ask and the haves answer (a network that boots at once would
            # otherwise send a summary per mote, and the repeats 2 s later fall in
            # the wave of its first definitions). Asks and the summary announcing
            # an adoption (soon) are never skipped: they are how the have-nots at
            # a wave's edge learn of items and get them (skipping those slowed a
            # wave by half, bench dissemination).
            self.skipped += 1
            return
        self._last_summary = now
        self.summary_tx += 1
        n = min(len(self._table), 0xFFFF)
        self._send(DripSummary(self._ctx.node_id, BROADCAST, self._table.digest, n))
