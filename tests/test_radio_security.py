"""Authenticated frames (MIC + frame counter) and signed dissemination items, on a
virtual clock: the guard's rules, the frame budget, a secured network end to end
and a compromised mote (network key, no gateway signing key)."""

from __future__ import annotations

import itertools
import os
import random

import pytest
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
from test_channels import _largest_frames

from awaremw.bench.dissemination import Event, TrafficMote, build_grid, inject_at
from awaremw.protocol.config import MiddlewareConfig
from awaremw.protocol.core import Transmission
from awaremw.protocol.dissemination import Dissemination
from awaremw.protocol.events import ItemAdopted, ItemRefused
from awaremw.protocol.frames import (
    BROADCAST,
    MAX_NODE_ID,
    SIG_PART_BYTES,
    SIG_PARTS,
    ChannelDef,
    CommandDef,
    DripItem,
    DripSig,
    DripSummary,
    ItemBody,
    ItemKind,
    decode,
    encode,
)
from awaremw.protocol.mote import MoteContext
from awaremw.protocol.signing import ItemSigner, item_message
from awaremw.radio.counters import MoteCounters
from awaremw.radio.model import PRESETS
from awaremw.radio.security import MAX_SENDERS, FrameGuard, RadioSecurity
from awaremw.radio.virtual_medium import VirtualNetwork

KEY = bytes(range(16))
SEC = RadioSecurity(KEY)
CHAN = ChannelDef(attr=0, group_type=1, group_id=0xFFFF, period_ms=2000, agg=0)
CMD = CommandDef("blink")


# --------------------------------------------------------------------------- MIC and counter


def test_sealed_frame_carries_counter_and_mic_and_opens() -> None:
    g = FrameGuard(SEC)
    air = g.seal(3, BROADCAST, 7, b"hello")
    assert len(air) == len(b"hello") + SEC.overhead == 5 + 4 + 8
    o = g.open(3, BROADCAST, 7, air)
    assert (o.payload, o.counter, o.reason) == (b"hello", 1, "")
    assert g.accept(9, MoteCounters(), 3, o) == b"hello"
    assert g.seal(3, BROADCAST, 8, b"x")[1:5] == (2).to_bytes(4, "big")  # next counter
    assert g.counter_of(3) == 2


def test_any_altered_byte_or_header_field_or_key_fails_the_mic() -> None:
    g = FrameGuard(SEC)
    air = g.seal(3, 4, 7, b"payload")
    for i in range(len(air)):
        bad = bytearray(air)
        bad[i] ^= 0x01
        assert g.open(3, 4, 7, bytes(bad)).reason == "mic", i
    assert g.open(5, 4, 7, air).reason == "mic"  # another sender claimed
    assert g.open(3, 6, 7, air).reason == "mic"  # another destination
    assert g.open(3, 4, 8, air).reason == "mic"  # a fresh link sequence number
    assert FrameGuard(RadioSecurity(os.urandom(16))).open(3, 4, 7, air).reason == "mic"
    assert g.open(3, 4, 7, air[:11]).reason == "short"
    assert g.open(3, 4, 7, air).payload == b"payload"


def test_replay_refused_per_receiver_and_counted_by_reason() -> None:
    g = FrameGuard(SEC)
    o1 = g.open(3, BROADCAST, 0, g.seal(3, BROADCAST, 0, b"one"))
    o2 = g.open(3, BROADCAST, 1, g.seal(3, BROADCAST, 1, b"two"))
    c9, c10 = MoteCounters(), MoteCounters()
    assert g.accept(9, c9, 3, o1) == b"one"
    assert g.accept(9, c9, 3, o1) is None  # the same frame again
    assert g.accept(10, c10, 3, o1) == b"one"  # another receiver has its own table
    assert g.accept(9, c9, 3, o2) == b"two"
    assert g.accept(9, c9, 3, o1) is None  # older than the last accepted
    assert (c9.refused, c10.refused) == (2, 0)
    assert g.refused.get("replay") == 2
    bad = g.open(3, BROADCAST, 2, b"\x00" * 20)
    assert g.accept(9, c9, 3, bad) is None and g.refused.get("mic") == 1
    assert c9.refused == 3


def test_replay_table_is_bounded_and_refuses_new_senders_when_full() -> None:
    g = FrameGuard(SEC)
    c = MoteCounters()
    for s in range(MAX_SENDERS):
        assert g.accept(1, c, s, g.open(s, BROADCAST, 0, g.seal(s, BROADCAST, 0, b"x")))
    new = MAX_SENDERS + 1
    assert g.accept(1, c, new, g.open(new, BROADCAST, 0, g.seal(new, BROADCAST, 0, b"x"))) is None
    assert g.refused.get("senders") == 1
    assert g.accept(1, c, 0, g.open(0, BROADCAST, 1, g.seal(0, BROADCAST, 1, b"y"))) == b"y"


def test_key_material_and_sizes() -> None:
    assert SEC.overhead == 12 and RadioSecurity(KEY, mic_bytes=4).overhead == 8
    assert SEC.payload_mtu(PRESETS["cc2420"].mtu) == 88
    assert SEC.payload_mtu(PRESETS["cc1000"].mtu) == 52
    with pytest.raises(ValueError, match="16 raw bytes"):
        RadioSecurity(b"short")
    with pytest.raises(ValueError, match="4 or 8"):
        RadioSecurity(KEY, mic_bytes=16)
    with pytest.raises(ValueError, match="32 raw bytes"):
        RadioSecurity(KEY, b"x")
    assert "network_key" not in repr(SEC)


@pytest.mark.parametrize("preset", ["cc2420", "cc1000"])
def test_largest_frames_and_signature_parts_fit_the_secured_payload_mtu(preset: str) -> None:
    mtu = SEC.payload_mtu(PRESETS[preset].mtu)
    n = MAX_NODE_ID
    sig = DripSig(n, BROADCAST, ItemKind.COMMAND, 0xFFFF, 0xFFFFFFFF, 1, b"\xff" * 32)
    sizes = {type(f).__name__ + str(i): len(encode(f)) for i, f in enumerate(_largest_frames())}
    sizes["DripSig"] = len(encode(sig))
    assert max(sizes.values()) <= mtu, sizes


# --------------------------------------------------------------------------- signed items


def _signed(
    *, signer: bool = False, **cfg: object
) -> tuple[Dissemination, MoteContext, ItemSigner]:
    sk = Ed25519PrivateKey.generate()
    sec = RadioSecurity(KEY, sk.public_key().public_bytes_raw())
    conf = MiddlewareConfig().with_overrides({"gateway_public_key": sec.gateway_public_key, **cfg})
    ctx = MoteContext(1, conf, random.Random(0), None)
    d = Dissemination(ctx, lambda k, i, b, t: None)
    if signer:
        d.signer = ItemSigner(sk)
    return d, ctx, ItemSigner(sk)


def _sig_frames(src: int, kind: ItemKind, iid: int, ver: int, sig: bytes) -> list[DripSig]:
    return [
        DripSig(
            src, BROADCAST, kind, iid, ver, p, sig[p * SIG_PART_BYTES : (p + 1) * SIG_PART_BYTES]
        )
        for p in range(SIG_PARTS)
    ]


def test_item_adopted_only_with_both_signature_parts_in_any_order() -> None:
    d, ctx, signer = _signed()
    sig = signer.sign(ItemKind.CHANNEL, 2, 5, CHAN)
    p0, p1 = _sig_frames(7, ItemKind.CHANNEL, 2, 5, sig)
    d.on_frame(p1, -60.0, 0.0)
    d.on_frame(DripItem(7, BROADCAST, ItemKind.CHANNEL, 2, 5, CHAN), -60.0, 0.1)
    assert d.version_of(ItemKind.CHANNEL, 2) is None  # pending: part 0 missing
    d.on_frame(p0, -60.0, 0.2)
    assert d.items[(ItemKind.CHANNEL, 2)] == (5, CHAN)
    assert d.signature_of(ItemKind.CHANNEL, 2) == sig
    adopted = [e for e in ctx.event_list if isinstance(e, ItemAdopted)]
    assert [(e.item_id, e.version, e.source) for e in adopted] == [(2, 5, 7)]


def test_a_pending_item_asks_so_a_lost_signature_part_is_answered_at_once() -> None:
    d, ctx, signer = _signed()
    d.start(0.0)
    d.on_frame(DripSummary(7, BROADCAST, d.digest, 0), -60.0, 0.0)  # boot summaries echoed
    for _ in range(3):  # through the boot summaries
        t = d.timers.next_deadline()
        assert t is not None
        for name in d.timers.due(t):
            d.on_timer(name, t)
    ctx.outbox.clear()
    assert d.timers.get("summary") is None
    sig = signer.sign(ItemKind.COMMAND, 0, 1, CMD)
    d.on_frame(DripItem(7, BROADCAST, ItemKind.COMMAND, 0, 1, CMD), -60.0, 20.0)
    d.on_frame(_sig_frames(7, ItemKind.COMMAND, 0, 1, sig)[0], -60.0, 20.0)  # part 1 lost
    due = d.timers.get("summary")
    assert due is not None and due <= 20.0 + ctx.config.drip_summary_delay
    for name in d.timers.due(due):
        d.on_timer(name, due)
    (ask,) = [decode(tx.frame) for tx in ctx.outbox]
    # It holds nothing yet: a neighbour holding the command answers this ask.
    assert isinstance(ask, DripSummary) and ask.n_items == 0
    # No answer came: it asks again, each gap twice the last, while it is pending.
    asks = [due]
    for _ in range(3):
        t = d.timers.get("summary")
        assert t is not None
        for name in d.timers.due(t):
            d.on_timer(name, t)
        asks.append(t)
    gaps = [b - a for a, b in itertools.pairwise(asks)]
    delay = ctx.config.drip_summary_delay
    assert all(g <= gap <= g + delay for g, gap in zip((2.0, 4.0, 8.0), gaps, strict=True)), gaps
    assert len([tx for tx in ctx.outbox if isinstance(decode(tx.frame), DripSummary)]) == 4
    # The part comes: adopted, and the asking stops after the adoption's summary.
    d.on_frame(_sig_frames(7, ItemKind.COMMAND, 0, 1, sig)[1], -60.0, asks[-1] + 1.0)
    assert d.version_of(ItemKind.COMMAND, 0) == 1
    t = d.timers.get("summary")
    assert t is not None
    for name in d.timers.due(t):
        d.on_timer(name, t)
    assert d.timers.get("summary") is None


def test_forged_pending_items_make_a_mote_ask_at_most_once_per_min_gap() -> None:
    """Each new pending item asks, but asks share the summary's rate limit: a
    forger sending a new version every 10 ms for 20 s draws at most one summary
    per drip_summary_min_gap (docs/security.md)."""
    d, ctx, _ = _signed()
    d.start(0.0)
    gap = ctx.config.drip_summary_min_gap
    t, end, version = 0.0, 20.0, 1
    while t < end:
        d.on_frame(DripItem(7, BROADCAST, ItemKind.COMMAND, 0, version, CMD), -60.0, t)
        version += 1
        t = round(t + 0.01, 2)
        while (due := d.timers.next_deadline()) is not None and due <= t:
            for name in d.timers.due(due):
                d.on_timer(name, due)
    asks = [tx for tx in ctx.outbox if isinstance(decode(tx.frame), DripSummary)]
    assert len(asks) >= end / (gap + ctx.config.drip_summary_delay) - 1  # it does ask
    assert len(asks) <= end / gap + 1


def test_forwarded_item_carries_its_signature() -> None:
    d, ctx, _ = _signed(signer=True)
    d.inject(ItemKind.CHANNEL, 2, 1, CHAN, 0.0)  # the gateway mote signs
    # Run the timers until the item's Trickle fires (a summary may go first).
    while not any(isinstance(decode(tx.frame), DripItem) for tx in ctx.outbox):
        t = d.timers.next_deadline()
        assert t is not None and t < 10.0
        for name in d.timers.due(t):
            d.on_timer(name, t)
    frames = [f for f in (decode(tx.frame) for tx in ctx.outbox) if not isinstance(f, DripSummary)]
    assert [type(f).__name__ for f in frames] == ["DripItem", "DripSig", "DripSig"]
    sig = b"".join(f.chunk for f in frames if isinstance(f, DripSig))
    assert sig == d.signature_of(ItemKind.CHANNEL, 2)


def test_bad_signature_refused_and_the_right_one_still_accepted_later() -> None:
    d, ctx, signer = _signed()
    item = DripItem(7, BROADCAST, ItemKind.COMMAND, 0, 1, CMD)
    d.on_frame(item, -60.0, 0.0)
    for f in _sig_frames(7, ItemKind.COMMAND, 0, 1, os.urandom(64)):
        d.on_frame(f, -60.0, 0.0)
    refused = [e for e in ctx.event_list if isinstance(e, ItemRefused)]
    assert [(e.item_id, e.reason) for e in refused] == [(0, "bad signature")]
    assert d.version_of(ItemKind.COMMAND, 0) is None
    d.on_frame(item, -60.0, 1.0)
    for f in _sig_frames(7, ItemKind.COMMAND, 0, 1, signer.sign(ItemKind.COMMAND, 0, 1, CMD)):
        d.on_frame(f, -60.0, 1.0)
    assert d.version_of(ItemKind.COMMAND, 0) == 1


def test_signature_binds_kind_id_version_and_body() -> None:
    d, ctx, signer = _signed()
    sig = signer.sign(ItemKind.CHANNEL, 2, 5, CHAN)
    other = ChannelDef(attr=1, group_type=1, group_id=0xFFFF, period_ms=2000, agg=0)
    tries: list[tuple[ItemKind, int, int, ItemBody | None]] = [
        (ItemKind.CHANNEL, 2, 5, other),  # another body
        (ItemKind.CHANNEL, 3, 5, CHAN),  # another id
        (ItemKind.CHANNEL, 2, 6, CHAN),  # another version
        (ItemKind.CHANNEL, 2, 7, None),  # a deletion
    ]
    for kind, iid, ver, body in tries:
        d.on_frame(DripItem(7, BROADCAST, kind, iid, ver, body), -60.0, 0.0)
        for f in _sig_frames(7, kind, iid, ver, sig):
            d.on_frame(f, -60.0, 0.0)
    assert not d.items
    assert sum(isinstance(e, ItemRefused) for e in ctx.event_list) == len(tries)
    assert item_message(ItemKind.CHANNEL, 2, 5, CHAN) != item_message(ItemKind.CHANNEL, 2, 5, other)


def test_inject_needs_a_valid_signature_and_pending_items_are_bounded() -> None:
    d, _, signer = _signed(max_pending_items=2)
    with pytest.raises(ValueError, match="needs the gateway's signature"):
        d.inject(ItemKind.CHANNEL, 1, 1, CHAN, 0.0)
    with pytest.raises(ValueError, match="does not match"):
        d.inject(ItemKind.CHANNEL, 1, 1, CHAN, 0.0, os.urandom(64))
    assert d.inject(ItemKind.CHANNEL, 1, 1, CHAN, 0.0, signer.sign(ItemKind.CHANNEL, 1, 1, CHAN))
    for iid in (5, 6, 7):  # unsigned items from a forger: only the 2 newest stay pending
        d.on_frame(DripItem(9, BROADCAST, ItemKind.CHANNEL, iid, 1, CHAN), -60.0, 0.0)
    assert len(d._pending) == 2 and (ItemKind.CHANNEL, 5) not in d._pending


# --------------------------------------------------------------------------- networks


def _secured_grid(
    side: int = 4,
) -> tuple[VirtualNetwork, dict[int, TrafficMote], list[Event], RadioSecurity]:
    security, sk = RadioSecurity.throwaway()
    net, motes, events = build_grid(
        side, 15.0, (0,), seed=3, security=security, signer=ItemSigner(sk)
    )
    return net, motes, events, security


def test_secured_network_spreads_signed_items_and_counts_the_overhead() -> None:
    net, motes, _, security = _secured_grid()
    sent: list[int] = []
    net.on_transmit = lambda n, tx, t: sent.append(len(tx.frame))
    inject_at(net, motes[0], 20.0, ItemKind.CHANNEL, 1, 1, CHAN)
    net.run_until(80.0)
    for m in motes.values():
        it = m.dissemination.items.get((ItemKind.CHANNEL, 1))
        assert it is not None and it.body == CHAN, m.node_id
        assert m.dissemination.signature_of(ItemKind.CHANNEL, 1) is not None
        assert m.config.mtu == 88
    counters = net.counters.values()
    assert sum(c.refused for c in counters) == 0
    assert sum(c.bytes_tx for c in counters) == sum(sent) + security.overhead * len(sent)
    assert sum(c.frames_rx for c in counters) > 0


def test_compromised_mote_cannot_forge_definitions_or_commands() -> None:
    """A mote with the network key but not the gateway's signing key: its forged
    items (random signature, its own key's signature, none at all) are refused by
    every mote; the gateway's own later version of the same key still spreads."""
    net, motes, events, _ = _secured_grid()
    evil = 15
    mine = ItemSigner(Ed25519PrivateKey.generate())
    forged: list[tuple[ItemKind, int, ItemBody]] = [
        (ItemKind.CHANNEL, 3, CHAN),
        (ItemKind.COMMAND, 0, CMD),
        (ItemKind.COMMAND, 1, CMD),
    ]

    def forge() -> None:
        for i, (kind, iid, body) in enumerate(forged):
            frames: list[DripItem | DripSig] = [DripItem(evil, BROADCAST, kind, iid, 1, body)]
            if i == 0:
                frames += _sig_frames(evil, kind, iid, 1, os.urandom(64))
            elif i == 1:
                frames += _sig_frames(evil, kind, iid, 1, mine.sign(kind, iid, 1, body))
            for f in frames:
                net.inject(evil, encode(f))

    for t in (20.0, 25.0, 30.0, 40.0):
        net.call_at(t, forge)
    net.run_until(60.0)
    for nid, m in motes.items():
        for kind, iid, _ in forged:
            assert m.dissemination.version_of(kind, iid) is None, (nid, kind, iid)
        assert m.app.commands == []
    refusals = [(n, e) for n, e, _ in events if isinstance(e, ItemRefused)]
    assert {e.reason for _, e in refusals} == {"bad signature"}
    assert {e.source for _, e in refusals} == {evil}
    assert len({n for n, _ in refusals}) >= 2  # every neighbour of the forger refused
    assert not any(isinstance(e, ItemAdopted) and e.source == evil for _, e, _ in events)
    # The gateway's real version of the same key reaches everyone afterwards.
    inject_at(net, motes[0], 61.0, ItemKind.CHANNEL, 3, 1, CHAN)
    net.run_until(120.0)
    assert all(m.dissemination.version_of(ItemKind.CHANNEL, 3) == 1 for m in motes.values())


def test_transmission_hook_sees_the_plain_frame() -> None:
    net, _, _, _ = _secured_grid(2)
    seen: list[Transmission] = []
    net.on_transmit = lambda n, tx, t: seen.append(tx)
    net.run_until(5.0)
    assert seen and all(decode(tx.frame) for tx in seen)
