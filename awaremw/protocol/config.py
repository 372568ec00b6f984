"""MiddlewareConfig: every timing and size of the middleware, in one place.

Defaults follow the paper and TinyOS where those say something (Drip's Trickle
1 s .. 17.5 min, k = 1) and are otherwise chosen for the emulation; all of them
are configuration, not constants (a deployment may override any).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

from awaremw.protocol.validation import Invalid, convert


@dataclass(frozen=True, slots=True)
class MiddlewareConfig:
    mtu: int = 100  # largest encoded frame (radio preset)

    # Epidemic dissemination (Drip over Trickle)
    drip_tau_l: float = 1.0
    drip_tau_h: float = 1050.0  # 17.5 min
    drip_k: int = 1
    drip_summary_delay: float = 0.5  # boot summary after a uniform wait in [0, this] s
    drip_summary_repeats: int = 2  # boot summary sent again this many times (lost frames)
    drip_summary_spacing: float = 2.0  # s before the first repeat; doubles for each next one
    drip_summary_min_gap: float = 1.0  # s between two summaries answering summaries
    # A mote that hears a summary with fewer items than it holds answers after a
    # uniform wait in [0, this] s, leaving out what a neighbour sent meanwhile.
    drip_answer_delay: float = 0.05
    # A mote holding a signed item pending (a signature part missed) asks again this
    # many times, each gap twice the last (1, 2, 4, ... s), while it is pending.
    drip_pending_asks: int = 5
    # Unsigned items only: a version heard more than this many steps away from the
    # one held (either way) is a jump no gateway makes; it is refused unless no
    # other mote ever echoed the held version (docs/protocol-dissemination.md).
    drip_max_version_step: int = 1 << 16
    max_command_slots: int = 8  # command items (slots) a mote holds, tombstones included

    # Collection tree (CTP-like)
    ctp_tau_l: float = 0.5
    # CTP beacons: 0.5 s .. 1 h, reset only on route trouble (docs/energy.md)
    ctp_tau_h: float = 3600.0
    ctp_queue: int = 16
    ctp_max_thl: int = 32
    ctp_parent_switch_threshold: int = 15  # ETX x 10 improvement needed to switch parent
    ctp_evict_after_failures: int = 2  # failed unicasts (after retries) before dropping a parent
    # ... before a parent no feasible neighbour can replace is given up (poisoning the
    # route); below ctp_max_retries, so that the packet at the head waits for the repair
    ctp_poison_after_failures: int = 5
    ctp_switch_fresh: float = 30.0  # s: a neighbour heard within it may replace a lost parent
    ctp_neighbours: int = 16  # routing table size (the parent is never the one replaced)
    ctp_rssi_good: float = -90.0  # dBm at or above which a link costs ETX 1 (CC2420: sens. + 5)
    ctp_rssi_floor: float = -95.0  # dBm at or below which a link costs ctp_rssi_max_etx (sens.)
    ctp_rssi_alpha: float = 0.2  # EWMA weight of a frame's RSSI in the link estimate
    ctp_rssi_max_etx: int = 100  # ETX x 10 of a link at the floor (cubic in between)
    ctp_etx_alpha: float = 0.25  # EWMA weight of one unicast outcome in the link ETX
    ctp_fail_etx: int = 60  # ETX x 10 sample for a unicast that failed all link retries
    ctp_max_retries: int = 6  # routing-level attempts of one packet before it is dropped
    ctp_retry_delay: float = 0.2  # s; wait uniform in [d/2, d] after a failed attempt
    ctp_holddown: float = 2.0  # s without route (poisoned) before accepting a costlier parent
    ctp_dup_cache: int = 32  # (origin, seqno, thl) entries remembered by a forwarder
    ctp_root_window: int = 32  # per-origin seqnos remembered by a root for delivery
    # s; a copy of a packet is a duplicate only this long after the first: later,
    # the same (origin, seqno) is a new packet of an origin that rebooted (its
    # seqnos start again at 1), not a retransmission whose ACK was lost.
    ctp_dup_ttl: float = 10.0

    # Groups
    check_period: float = 1.0  # membership check
    beacon_period: float = 2.0  # leader beacon
    leader_timeout_periods: float = 3.5  # no beacon for this many periods: leader lost
    create_backoff: float = 2.0  # max random wait for a nearby group before creating one
    tentative_periods: float = 1.0  # a new group's id is announced this long before it is taken
    unmerge_window_periods: float = 15.0  # a part losing a merged group this soon takes its id back
    forward_jitter: float = 0.05  # max random delay before re-broadcasting a leader beacon
    # A member skips re-broadcasting a leader beacon when it heard this many copies
    # from members at least as far from the leader during its jitter (0: always).
    beacon_forward_cover: int = 1
    # A leader whose channel records flow and whose group is unchanged doubles its
    # beacon interval at each beacon, up to this many beacon periods (1: never).
    beacon_settled_factor: float = 2.0
    report_every_beacons: int = 5  # leader's GroupReport to the gateway, in beacon periods
    max_group_types: int = 8
    # Hops; TAG slots per epoch are planned for this depth (docs/protocol-groups.md,
    # "Epochs and slots": 8, not 16, so that a slot is wide enough to spread a ring's
    # partials under carrier sense and collisions).
    max_group_depth: int = 8
    handover_grace: float = 0.2  # after the ACK, wait this long for a refusal before leaving
    group_link_rssi_floor: float = -90.0  # dBm; weaker links are a group parent of last resort

    # Channels
    max_channels: int = 8
    # A member sends its partial at a uniform offset in the first ``slot_jitter`` of
    # its TAG slot; the rest of the slot is left for CSMA and the link layer's retries.
    slot_jitter: float = 0.8
    min_period_s: float = 0.5

    # Attributes served by the middleware
    rssi_ttl: float = 5.0  # an rssi:<node> reading older than this is "not available"
    rssi_alpha: float = 0.5  # EWMA weight of the newest frame's RSSI

    # Stand-in beacon (a robot's mote): period of Hello frames, None = off
    hello_period: float | None = None

    # Role
    is_root: bool = False  # a gateway mote: root of the collection tree

    # Signed dissemination (docs/security.md, "Frames and items"): the gateway's raw
    # 32-byte Ed25519 public key; items are verified before being applied or
    # forwarded. None: items are not signed (security off).
    gateway_public_key: bytes | None = None
    max_pending_items: int = 4  # items waiting for their signature (evicts the oldest)

    def with_overrides(self, overrides: dict[str, Any]) -> MiddlewareConfig:
        """A copy with ``overrides`` applied. Unknown keys and values of the wrong
        type (checked against the annotations by msgspec, strictly: no bool for a
        number, no float for an int) raise ValueError naming the setting."""
        values = {f.name: getattr(self, f.name) for f in fields(self)}
        unknown = sorted(set(overrides) - set(values))
        if unknown:
            raise ValueError(f"unknown middleware settings: {', '.join(unknown)}")
        try:
            return convert({**values, **overrides}, MiddlewareConfig)
        except Invalid as e:
            raise ValueError(f"middleware setting {e.path!r}: {e.why}") from None
