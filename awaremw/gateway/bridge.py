"""The gateway's logic, independent of any transport (sans-IO): events in,
actions out (gateway/events.py).

:class:`GatewayBridge` is fed with what arrives from the IP side (a topic
relative to the prefix, e.g. ``def/channel/3``, its payload and the transport it
came by: :meth:`~GatewayBridge.handle`), with every event of a gateway mote
(records and group reports the collection tree delivers, versions the mote
adopted from the network, a reboot: :meth:`~GatewayBridge.on_mote_event`) and
with the time (:meth:`~GatewayBridge.tick`). It answers with actions:
:class:`Publish`, :class:`Inject`, :class:`Report`, :class:`StateChanged`.

One truth: the store is the only source of the definitions in force. Both
transports show them in the same bytes (:meth:`~GatewayBridge.definition_payloads`:
the canonical JSON with its ``version``); a payload that carries a ``version``
is such a copy, so an older one is stale and changes nothing.

It owns the version store (every version decision: the store's count against
the radio's u32 serial numbers, what the network holds, what to re-assert) and
the table of live groups; it never blocks, sleeps or talks to a socket.
"""

from __future__ import annotations

import json
import logging
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any, assert_never

from awaremw.gateway.events import (
    Action,
    ErrorReport,
    Inject,
    Outcome,
    Publish,
    Report,
    StateChanged,
    Transport,
)
from awaremw.gateway.schema import (
    BadValue,
    Definition,
    Limits,
    PayloadTooLarge,
    SchemaError,
    TopicTooLong,
    UnknownTopic,
    agg_name,
    channel_id,
    group_type_id,
    parse_command,
    parse_definition,
)
from awaremw.gateway.store import StoredItem, VersionStore, payload_hash, unwrap, wire_version
from awaremw.protocol import events as ev
from awaremw.protocol.attributes import attribute_name, unit_of
from awaremw.protocol.events import MoteDown, MoteEvent, MoteUp
from awaremw.protocol.frames import (
    ANY_GROUP_TYPE,
    ChannelDef,
    DataRecord,
    GroupReport,
    GroupStatus,
    ItemBody,
    ItemKind,
)

log = logging.getLogger(__name__)
BodyFn = Callable[[int, ItemKind, int], ItemBody | None]  # (node, kind, item id): what it holds

MAX_ERROR_PAYLOAD = 512  # characters of the refused payload echoed on the errors topic
MAX_ERROR_TOPIC = 200  # characters of the topic echoed on the errors topic and in the log
WAITS_FOR_GROUP_TYPE = "waits_for_group_type"  # warning code: a channel on an undefined type
MAX_TOPIC = 256  # longest IP-side topic accepted (the contract's are < 40 characters)
MAX_GROUPS = 4096  # live groups tracked; beyond it the longest-unheard one is dropped
REFUSAL_LOG_INTERVAL_S = 10.0  # at most one refusal log line per code in this span
# A declared version is taken in only this far above the store's: a larger jump
# would read as older on the radio's u32 circle (RFC 1982), and would let one
# payload use up the store's count.
MAX_VERSION_JUMP = (1 << 31) - 1


def clip(text: str, n: int) -> str:
    """``text`` cut to ``n`` characters, with a marker saying how much was cut."""
    return text if len(text) <= n else f"{text[:n]}...(+{len(text) - n} chars)"


class RateLimitedLog:
    """Log refusals at WARNING, at most once per ``interval_s`` per code.

    The lines skipped in between are counted and reported with the next line,
    so a flood of garbage costs a log line per code per interval, not one each.
    """

    def __init__(
        self,
        logger: logging.Logger,
        interval_s: float = REFUSAL_LOG_INTERVAL_S,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.logger = logger
        self.interval_s = interval_s
        self.clock = clock
        self._last: dict[str, float] = {}  # bounded by the set of error codes
        self._skipped: dict[str, int] = {}

    def warning(self, code: str, msg: str, *args: object) -> bool:
        """Log unless ``code`` was logged less than ``interval_s`` ago; True if logged."""
        now = self.clock()
        last = self._last.get(code)
        if last is not None and now - last < self.interval_s:
            self._skipped[code] = self._skipped.get(code, 0) + 1
            return False
        self._last[code] = now
        skipped = self._skipped.pop(code, 0)
        suffix = f" ({skipped} more {code} refusals not logged)" if skipped else ""
        self.logger.warning(msg + suffix, *args)
        return True


@dataclass(slots=True)
class GroupState:
    group_type: int
    group_id: int
    leader: int
    weight: int
    readings: int  # readings in the leader's last aggregated epoch (not a member count)
    t: float  # emulated time of the last report
    last_heard: float  # emulated time of the last report or record
    split_from: int = 0  # the group id this one split from (its leader was lost), or 0

    def to_json(self) -> bytes:
        return json.dumps(
            {
                "group_type": self.group_type,
                "group_id": self.group_id,
                "leader": self.leader,
                "weight": self.weight,
                "readings": self.readings,
                "t": round(self.t, 3),
            }
            | ({"split_from": self.split_from} if self.split_from else {})
        ).encode()


@dataclass(slots=True)
class BridgeStats:
    accepted: int = 0
    unchanged: int = 0  # valid payloads equal to the current state: no new version
    replays: int = 0  # retained payloads seen before: ignored
    stale: int = 0  # copies of a definition under another version than the store's: ignored
    refused: int = 0
    refused_by_code: dict[str, int] = field(default_factory=dict)  # bounded: one key per code
    records: int = 0
    duplicate_records: int = 0
    group_reports: int = 0
    groups_gone: int = 0
    groups_expired: int = 0
    groups_evicted: int = 0  # dropped because MAX_GROUPS were tracked
    learned: int = 0  # item versions learned from the network
    reasserted: int = 0  # our newer definitions re-sent above the network's version
    waiting_channels: int = 0  # channels accepted on a group type not defined (yet)

    def as_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {k: getattr(self, k) for k in self.__slots__}
        out["refused_by_code"] = dict(sorted(self.refused_by_code.items()))
        return out


def group_topic(group_type: int, group_id: int) -> str:
    return f"groups/{group_type}/{group_id}"


def data_topic(channel: int, group_type: int, group_id: int) -> str:
    return f"data/{channel}/{group_type}/{group_id}"


@dataclass(frozen=True, slots=True)
class BridgePolicy:
    """The bridge's tunables: how often leaders report their group (emulated
    seconds) and after how many silent report periods a group is taken as gone;
    command slots the motes keep; the de-duplication window of records; the
    bound of the live-groups table."""

    report_period_s: float = 10.0
    expiry_periods: float = 3.0
    command_slots: int = 16
    dedupe_window: int = 4096
    max_groups: int = MAX_GROUPS
    # Retained definitions replayed by the broker are taken only when they are one
    # of these (relative topic, payload) pairs; None: all. Live ones are always taken.
    retained_only: frozenset[tuple[str, bytes]] | None = None


class GatewayBridge:
    """Validation, versions and the IP-side view of the WSN, without I/O.

    ``report_period_s`` is how often leaders report their group (emulated
    seconds); a group unheard for ``expiry_periods`` of them is taken as gone.
    A group merged into another keeps a retained ``{"merged_into": id}`` state for
    one report period (so that live and late subscribers learn the successor; the
    MQTT side coalesces retained topics, so a notice and its clearing sent together
    would reach clients as the clearing alone), then it is cleared.
    """

    def __init__(
        self,
        store: VersionStore,
        limits: Limits | None = None,
        policy: BridgePolicy | None = None,
        refusal_log: RateLimitedLog | None = None,
    ) -> None:
        self.store = store
        self.limits = limits or Limits()
        self.policy = policy or BridgePolicy()
        self.refusal_log = refusal_log or RateLimitedLog(log)
        self.groups: dict[tuple[int, int], GroupState] = {}
        # key -> since: groups that merged, cleared after a report period (at most max_groups)
        self.merged: dict[tuple[int, int], float] = {}
        self.stats = BridgeStats()
        self._recent: OrderedDict[DataRecord, None] = OrderedDict()
        self._defined_here: set[tuple[ItemKind, int]] = set()

    @property
    def report_period_s(self) -> float:
        return self.policy.report_period_s

    # ----------------------------------------------------------------- IP -> WSN

    def startup(self) -> list[Inject]:
        """The stored state, to inject into the gateway motes when they start."""
        return [_inject(i) for i in self.store.items()]

    def handle(
        self,
        rel_topic: str,
        payload: bytes,
        *,
        source: str,
        retained: bool = False,
        size: int | None = None,
        via: Transport = Transport.LOCAL,
    ) -> Outcome:
        """One payload from the IP side on ``rel_topic`` (relative to the prefix),
        come by ``via`` (where a refusal is reported).

        ``source`` is the full topic as the sender saw it (echoed in errors and
        used to recognise replays); ``retained`` marks a payload replayed by
        the broker from its retained store rather than published just now: one
        equal to the last payload seen on that topic is ignored, so a
        reconnect or restart never applies a definition twice. ``size``, when
        given, is the payload's size as sent (a transport that did not copy an
        oversize payload passes it empty with its size).
        """
        only = self.policy.retained_only
        if retained and only is not None and (rel_topic, payload) not in only:
            return Outcome(replay=True)  # not one of ours: inherited from the broker
        if (early := self._precheck(source, size)) is not None:
            # Refused before anything is remembered: a long topic is never stored.
            return self._refuse(source, payload, early, via)
        h = payload_hash(payload)
        if retained and self.store.last_seen(source) == h:
            self.stats.replays += 1
            return Outcome(replay=True)
        try:
            inj = self._apply(rel_topic, payload)
        except SchemaError as e:
            self.store.set_seen(source, h)
            return self._refuse(source, payload, e, via)
        self.store.set_seen(source, h)
        if inj is None:
            return Outcome()
        w = self._waiting(inj, source, payload)
        return Outcome((inj, StateChanged()) + (() if w is None else (Report(w, via),)))

    def _precheck(self, source: str, size: int | None) -> SchemaError | None:
        if size is not None and size > self.limits.max_payload_bytes:
            return PayloadTooLarge(
                f"payload of {size} bytes exceeds the limit of {self.limits.max_payload_bytes}"
            )
        if len(source) > MAX_TOPIC:
            n = len(source)
            return TopicTooLong(f"topic of {n} characters exceeds the limit of {MAX_TOPIC}")
        return None

    def validate(
        self, rel_topic: str, payload: bytes, *, source: str, size: int | None = None
    ) -> SchemaError | None:
        """Why a definition payload is invalid on its own (size, topic, schema), or None.

        Pure (reads only the limits, never the store): a transport's inbox may call it
        on its own thread, to keep an invalid definition from being replaced by a
        newer one before :meth:`handle` refuses it. Checks that need the gateway's
        state (how many are defined) are left to :meth:`handle`.
        """
        if (early := self._precheck(source, size)) is not None:
            return early
        try:
            parse_definition(rel_topic, payload, self.limits)
        except SchemaError as e:
            return e
        return None

    def _waiting(self, inj: Inject, source: str, payload: bytes) -> ErrorReport | None:
        """A warning when a channel names a group type nobody defined: the channel is
        accepted (the motes keep it until the type comes), but no data flows until then."""
        body = inj.body
        if inj.kind is not ItemKind.CHANNEL or not isinstance(body, ChannelDef):
            return None
        gt = body.group_type
        if gt == ANY_GROUP_TYPE or gt in self.store.defined_ids(ItemKind.GROUP_TYPE):
            return None
        self.stats.waiting_channels += 1
        msg = (
            f"channel {inj.item_id} accepted, but group type {gt} is not defined: it waits "
            f"for def/group/{gt} and produces no data until then"
        )
        self.refusal_log.warning(WAITS_FOR_GROUP_TYPE, "%s: %s", clip(source, MAX_ERROR_TOPIC), msg)
        text = payload[:MAX_ERROR_PAYLOAD].decode("utf-8", errors="replace")
        return ErrorReport(clip(source, MAX_ERROR_TOPIC), WAITS_FOR_GROUP_TYPE, msg, text, True)

    def _refuse(self, source: str, payload: bytes, e: SchemaError, via: Transport) -> Outcome:
        """Count, log (rate-limited) and report a refusal; the echoes are truncated."""
        self.stats.refused += 1
        self.stats.refused_by_code[e.code] = self.stats.refused_by_code.get(e.code, 0) + 1
        topic = clip(source, MAX_ERROR_TOPIC)
        text = payload[:MAX_ERROR_PAYLOAD].decode("utf-8", errors="replace")
        if len(payload) > MAX_ERROR_PAYLOAD:
            text += f"...(+{len(payload) - MAX_ERROR_PAYLOAD} bytes)"
        error = clip(str(e), MAX_ERROR_PAYLOAD)
        self.refusal_log.warning(e.code, "refused %s: %s", topic, error)
        return Outcome((Report(ErrorReport(topic, e.code, error, text), via),))

    def _apply(self, rel_topic: str, payload: bytes) -> Inject | None:
        parts = rel_topic.split("/")
        if parts[0] == "def":
            d = parse_definition(
                rel_topic,
                payload,
                self.limits,
                self.store.defined_ids(ItemKind.GROUP_TYPE),
                self.store.defined_ids(ItemKind.CHANNEL),
            )
            return self._define(d)
        if len(parts) == 2 and parts[0] == "cmd":
            c = parse_command(
                parts[1], payload, self.limits, self.store.defined_ids(ItemKind.GROUP_TYPE)
            )
            slot = self.store.command_slot(c.name, self.policy.command_slots)
            item = self.store.bump(ItemKind.COMMAND, slot, c.body, {"name": c.name, **c.json})
            self.stats.accepted += 1
            self._defined_here.add((ItemKind.COMMAND, slot))
            log.info("command %s -> slot %d version %d", c.name, slot, item.version)
            return _inject(item)
        raise UnknownTopic(
            f"unknown topic {rel_topic!r}; use def/group/<type>, def/channel/<id> or cmd/<name>"
        )

    def _define(self, d: Definition) -> Inject | None:
        """A valid definition; one with a declared version is a copy of what a gateway
        published (a retained message, a dashboard's echo): an older copy is stale,
        a newer one (the store lost, or behind the broker) is taken in under its
        version, and one at the store's version is a change like any other."""
        if d.version is None:
            return self._store(d.kind, d.item_id, d.body, d.json)
        cur = self.store.get(d.kind, d.item_id)
        held = 0 if cur is None else cur.version
        if d.version < held or (d.version > held and cur is not None and cur.body == d.body):
            self.stats.stale += 1
            return None
        if d.version == held:
            return self._store(d.kind, d.item_id, d.body, d.json)
        if d.version - held > MAX_VERSION_JUMP:
            raise BadValue(
                f"version {d.version} is more than {MAX_VERSION_JUMP} above the gateway's "
                f"{held}: leave the version out to define it anew"
            )
        item = self.store.bump_to(d.kind, d.item_id, d.version, d.body, dict(d.json or {}))
        self.stats.accepted += 1
        self._defined_here.add((d.kind, d.item_id))
        log.info("%s %d taken in at its version %d", d.kind.name.lower(), d.item_id, d.version)
        return _inject(item)

    def _store(self, kind: ItemKind, item_id: int, body: ItemBody | None, js: Any) -> Inject | None:
        item = self.store.apply(kind, item_id, body, None if js is None else dict(js))
        if item is None:
            self.stats.unchanged += 1
            return None
        self.stats.accepted += 1
        self._defined_here.add((kind, item_id))
        what = "deleted" if body is None else "defined"
        log.info("%s %d %s, version %d", kind.name.lower(), item_id, what, item.version)
        return _inject(item)

    # ----------------------------------------------------------------- WSN -> IP

    def on_mote_event(
        self, node: int, event: MoteEvent, body_of: BodyFn | None = None
    ) -> list[Action]:
        """An event of gateway mote ``node``; ``body_of`` reads the body a gateway
        mote holds for an item (None: the gateway cannot learn what the network holds)."""
        match event:
            case MoteUp():  # (re)booted with an empty memory: give it the state
                return [replace(i, node=node) for i in self.startup()]
            case ev.ItemAdopted(source=None):
                return []  # injected by us
            case ev.ItemAdopted():
                return self._learn(node, event, body_of)
            case ev.InjectSuperseded():
                return self._supersede(event)
            case ev.Delivered(payload=payload, t=t):
                out: list[Action] = [*self.on_payload(payload, t)]
                return out if isinstance(payload, DataRecord) else [*out, StateChanged()]
            case (
                MoteDown() | ev.MalformedFrame() | ev.ItemRefused() | ev.ParentChanged()
                | ev.DataDropped() | ev.GroupJoined() | ev.GroupLeft() | ev.LeaderElected()
                | ev.LeaderYielded() | ev.HandoverSent() | ev.GroupTypeRefused()
                | ev.RecordProduced() | ev.ChannelRefused() | ev.CommandExecuted()
                | ev.NeighbourFound() | ev.NeighbourLost() | ev.PingResult()
            ):  # fmt: skip
                return []
            case _:
                assert_never(event)

    def _learn(self, node: int, adopted: ev.ItemAdopted, body_of: BodyFn | None) -> list[Action]:
        """Gateway mote ``node`` adopted ``adopted.version`` of an item from the network.

        A gateway that lost its store (or shares the network with another)
        learns the versions in force this way. If the item was (re)defined
        through this gateway since it started and the network holds another
        body under a version at least as high (so it ignored ours), our
        definition is the newer intent: it is stored again above the network's
        version and injected. Otherwise the network's state is taken over.
        """
        kind, item_id = adopted.kind, adopted.item_id
        body: ItemBody | None = None
        if not adopted.deleted and (
            body_of is None or (body := body_of(node, kind, item_id)) is None
        ):
            return []  # cannot tell what the network holds: the store stays as it is
        cur = self.store.get(kind, item_id)
        # The mote's u32 version, mapped into the store's non-wrapping count, so
        # that "newer" there is RFC 1982 "newer" on the radio (store.unwrap).
        version = unwrap(adopted.version, None if cur is None else cur.version)
        if cur is not None and (
            cur.version > version or (cur.version == version and cur.body == body)
        ):
            return []  # the store is ahead, or agrees
        if cur is not None and (kind, item_id) in self._defined_here and cur.body != body:
            item = self.store.bump_to(kind, item_id, version + 1, cur.body, cur.json)
            self.stats.reasserted += 1
            log.info(
                "%s %d: the network holds version %d; ours is re-sent as version %d",
                kind.name.lower(), item_id, version, item.version,
            )  # fmt: skip
            return [_inject(item), StateChanged()]
        self.store.learn(kind, item_id, version, body)
        self.stats.learned += 1
        log.info("learned %s %d version %d from the network", kind.name.lower(), item_id, version)
        return [StateChanged()]

    def _supersede(self, sup: ev.InjectSuperseded) -> list[Action]:
        """Our mote holds a foreign version that ours does not supersede (serial
        order is not transitive: forged versions can sit anywhere on the circle):
        store our definition again just above it, and inject it."""
        cur = self.store.get(sup.kind, sup.item_id)
        if cur is None or wire_version(cur.version) != sup.version:
            return []  # a later definition is on its way already
        # Step over it on the radio's circle: the next store version whose u32 is
        # ``held + 1``, newer than ``held`` for every mote (RFC 1982).
        version = cur.version + ((sup.held - sup.version) & 0xFFFFFFFF) + 1
        item = self.store.bump_to(sup.kind, sup.item_id, version, cur.body, cur.json)
        self.stats.reasserted += 1
        log.info("%s %d: re-sent as version %d over a foreign one", sup.kind.name.lower(),
                 sup.item_id, item.version)  # fmt: skip
        return [_inject(item), StateChanged()]

    def on_payload(self, payload: DataRecord | GroupReport, now: float) -> list[Publish]:
        """A payload the collection tree delivered at a gateway mote at emulated ``now``."""
        if isinstance(payload, DataRecord):
            return self.on_record(payload, now)
        return self.on_report(payload, now)

    def on_record(self, r: DataRecord, now: float) -> list[Publish]:
        # A copy of a record (several gateway roots, or a link-layer retry whose
        # ACK was lost) is equal field by field. The epoch alone is not a key:
        # after a period change the epochs are counted in the new period.
        if r in self._recent:
            self.stats.duplicate_records += 1
            return []
        self._recent[r] = None
        if len(self._recent) > self.policy.dedupe_window:
            self._recent.popitem(last=False)
        self.stats.records += 1
        g = self.groups.get((r.group_type, r.group_id))
        if g is not None:
            g.last_heard = max(g.last_heard, now)
        doc: dict[str, Any] = {
            "value": r.value,
            "count": r.count,
            "agg": agg_name(r.agg),
            "epoch": r.epoch,
            "leader": r.leader,
            "t": round(now, 3),
        }
        ch = self.store.get(ItemKind.CHANNEL, r.channel)
        if ch is not None and isinstance(ch.body, ChannelDef):
            doc["attr"] = name = attribute_name(ch.body.attr)
            if unit := unit_of(name, doc["agg"]):
                doc["unit"] = unit
        return [Publish(data_topic(r.channel, r.group_type, r.group_id), json.dumps(doc).encode())]

    def on_report(self, r: GroupReport, now: float) -> list[Publish]:
        self.stats.group_reports += 1
        key = (r.group_type, r.group_id)
        if r.status is GroupStatus.GONE:
            if self.groups.pop(key, None) is None:
                return []
            self.stats.groups_gone += 1
            log.info(
                "group %d/%d gone%s", *key, f" (merged into {r.successor})" if r.successor else ""
            )
            if not r.successor:
                return [Publish(group_topic(*key), b"", retain=True)]
            # A merge: the retained state names the successor until expire() clears it.
            if len(self.merged) >= self.policy.max_groups:
                del self.merged[min(self.merged, key=self.merged.__getitem__)]
            self.merged[key] = now
            doc = {"group_type": r.group_type, "group_id": r.group_id,
                   "merged_into": r.successor, "t": round(now, 3)}  # fmt: skip
            return [Publish(group_topic(*key), json.dumps(doc).encode(), retain=True)]
        self.merged.pop(key, None)
        g = GroupState(
            r.group_type, r.group_id, r.leader, r.weight, r.readings, now, now, r.successor
        )
        out = []
        if key not in self.groups and len(self.groups) >= self.policy.max_groups:
            oldest = min(self.groups, key=lambda k: self.groups[k].last_heard)
            del self.groups[oldest]
            self.stats.groups_evicted += 1
            out.append(Publish(group_topic(*oldest), b"", retain=True))
        self.groups[key] = g
        out.append(Publish(group_topic(*key), g.to_json(), retain=True))
        return out

    def tick(self, now: float) -> list[Action]:
        """The time (emulated): clear the groups gone silent (:meth:`expire`)."""
        expired: list[Action] = [*self.expire(now)]
        return [*expired, StateChanged()] if expired else []

    def expire(self, now: float) -> list[Publish]:
        """Clear the groups not heard from for ``expiry_periods`` report periods."""
        limit = self.policy.expiry_periods * self.report_period_s
        out = []
        for key, since in list(self.merged.items()):
            if now - since >= self.report_period_s:
                del self.merged[key]
                out.append(Publish(group_topic(*key), b"", retain=True))
        for key, g in list(self.groups.items()):
            if now - g.last_heard > limit:
                del self.groups[key]
                self.stats.groups_expired += 1
                log.info("group %d/%d expired (unheard for %.1f s)", *key, now - g.last_heard)
                out.append(Publish(group_topic(*key), b"", retain=True))
        return out

    # ----------------------------------------------------------------- views

    def group_states(self) -> dict[str, bytes]:
        """Retained state of every live group, by relative topic."""
        return {group_topic(*k): g.to_json() for k, g in sorted(self.groups.items())}

    def definitions(self) -> dict[str, dict[str, Any]]:
        """Current definitions by relative topic (``def/group/1``: JSON, with its version)."""
        return {
            definition_topic(item.kind, item.item_id): _document(item)
            for item in self.store.items(include_deleted=False)
            if item.kind is not ItemKind.COMMAND
        }

    def definition_payload(self, rel_topic: str) -> bytes | None:
        """What the transports should show on ``rel_topic``: its definition's payload
        (``b""`` when deleted or never defined); None if it names no definition."""
        parts = rel_topic.split("/")
        try:
            if len(parts) == 3 and parts[:2] == ["def", "group"]:
                key = (ItemKind.GROUP_TYPE, group_type_id(parts[2], self.limits))
            elif len(parts) == 3 and parts[:2] == ["def", "channel"]:
                key = (ItemKind.CHANNEL, channel_id(parts[2], self.limits))
            else:
                return None
        except SchemaError:
            return None
        return _payload(self.store.get(*key))

    def definition_payloads(self) -> dict[str, bytes]:
        """What both transports show of every definition the store has, by relative
        topic: the JSON document with its version (MQTT retains it, a Zenoh ``get``
        answers it), or ``b""`` for a deleted one (no retained message, no answer)."""
        return {
            definition_topic(item.kind, item.item_id): _payload(item)
            for item in self.store.items()
            if item.kind is not ItemKind.COMMAND
        }

    def item(self, kind: ItemKind, item_id: int) -> StoredItem | None:
        return self.store.get(kind, item_id)


def definition_topic(kind: ItemKind, item_id: int) -> str:
    """``def/group/<type>`` or ``def/channel/<id>`` (relative to the prefix)."""
    return f"def/{'group' if kind is ItemKind.GROUP_TYPE else 'channel'}/{item_id}"


def _document(item: StoredItem) -> dict[str, Any]:
    return {**(item.json or {}), "version": item.version}


def _payload(item: StoredItem | None) -> bytes:
    """A definition as both transports show it: its document, or b"" (deleted, or none)."""
    return b"" if item is None or item.deleted else json.dumps(_document(item)).encode()


def _inject(item: StoredItem) -> Inject:
    return Inject(item.kind, item.item_id, item.version, item.body)
