"""The gateway service: gateway motes + bridge + MQTT + Zenoh HBN, wired together.

:class:`GatewayService` owns the :class:`GatewayBridge` (validation, versions,
group table) and the transports, and talks to the sensor network through two
callables the runtime provides:

* ``inject(node_id, Inject)`` -- put a versioned item into a gateway mote's
  core (inside the event loop that drives it);
* ``now()`` -- the fleet's emulated time.

The runtime calls :meth:`GatewayService.on_event` with every core event of
the gateway motes; ``Delivered`` events (from the collection tree's roots)
become data records and group states on MQTT and Zenoh.

Refusals go back to the transport the payload came from: ``<prefix>/errors``
on MQTT, ``<prefix>/hbn/errors`` on Zenoh.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import zenoh

from awaremw.gateway.bridge import (
    BridgePolicy,
    ErrorReport,
    GatewayBridge,
    Inject,
    Outcome,
    Publish,
)
from awaremw.gateway.hbn import HbnApi
from awaremw.gateway.inbox import Inbox, Incoming
from awaremw.gateway.mqtt import STATS_TOPIC, STATUS_TOPIC, MqttBridge, MqttSettings
from awaremw.gateway.schema import Limits
from awaremw.gateway.store import VersionStore, unwrap, wire_version
from awaremw.protocol.config import MiddlewareConfig
from awaremw.protocol.events import InjectSuperseded, ItemAdopted
from awaremw.protocol.frames import DataRecord, GroupReport, ItemBody, ItemKind
from awaremw.protocol.mote import AwareMote
from awaremw.runtime.events import MoteUp
from awaremw.runtime.fleet import Fleet

log = logging.getLogger(__name__)

InjectFn = Callable[[int, Inject], None]
BodyFn = Callable[[int, ItemKind, int], ItemBody | None]
ClockFn = Callable[[], float]
STORE_FILE = "gateway.sqlite"
INJECT_GAP_S = 0.5  # wall seconds between two injections of one definition (the newest wins)


@dataclass(frozen=True, slots=True)
class GatewaySettings:
    prefix: str = "aware"
    state_dir: Path | None = None  # None: versions kept in memory only
    expiry_periods: float = 3.0  # group reports missed before a group is taken as gone
    max_payload_bytes: int = 4096
    hbn: bool = True  # offer the Zenoh HBN API (needs a session)
    # Retained definitions replayed by the broker are taken only when they are one
    # of these (relative topic, payload) pairs; None: all. Live ones are always
    # taken. A demo on a user's broker inherits nothing but its own definitions.
    retained_only: frozenset[tuple[str, bytes]] | None = None


def deployment_definitions(groups: Any, channels: Any) -> list[tuple[str, bytes]]:
    """A deployment's ``[[groups]]`` / ``[[channels]]`` tables as (relative topic, JSON).

    Each entry is the MQTT payload plus its id (``type`` for a group, ``id`` for
    a channel); the result goes through the same validation as MQTT payloads.
    """
    out: list[tuple[str, bytes]] = []
    for what, key, entries in (("group", "type", groups), ("channel", "id", channels)):
        if entries is None:
            continue
        seq = [entries] if isinstance(entries, Mapping) else list(entries)
        for e in seq:
            if not isinstance(e, Mapping) or key not in e:
                raise ValueError(f"deployment {what}s entry {e!r:.60} has no {key!r}")
            body = {k: v for k, v in e.items() if k != key}
            out.append((f"def/{what}/{e[key]}", json.dumps(body).encode()))
    return out


class GatewayService:
    """See the module docstring. Use ``async with`` or :meth:`start` / :meth:`stop`."""

    def __init__(
        self,
        roots: Sequence[int],
        *,
        config: MiddlewareConfig | None = None,
        settings: GatewaySettings | None = None,
        mqtt: MqttSettings | None = None,
        zenoh_session: zenoh.Session | None = None,
        known_nodes: Iterable[int] | None = None,
        speed: float = 1.0,
    ) -> None:
        if not roots:
            raise ValueError("a gateway needs at least one gateway mote (collection root)")
        if not speed > 0:
            raise ValueError(f"speed must be > 0, got {speed!r}")
        self.roots = tuple(roots)
        self.speed = speed  # emulated seconds per real second (the fleet's)
        self.config = config or MiddlewareConfig()
        self.settings = s = settings or GatewaySettings()
        path = None if s.state_dir is None else Path(s.state_dir) / STORE_FILE
        self.store = VersionStore(path)
        limits = Limits.from_config(
            self.config,
            known_nodes=None if known_nodes is None else frozenset(known_nodes),
            gateway_node=self.roots[0],
            max_payload_bytes=s.max_payload_bytes,
        )
        self.bridge = GatewayBridge(
            self.store,
            limits,
            BridgePolicy(
                report_period_s=self.config.report_every_beacons * self.config.beacon_period,
                expiry_periods=s.expiry_periods,
                command_slots=self.config.max_command_slots,
            ),
        )
        self.mqtt: MqttBridge | None = None
        if mqtt is not None:
            self.mqtt = MqttBridge(
                MqttSettings(**{**_fields(mqtt), "prefix": s.prefix}),
                lambda rel, payload, retained, topic: self.handle(
                    rel, payload, retained=retained, topic=topic, via="mqtt"
                ),
                self._valid,
            )
        self._session = zenoh_session
        self.hbn: HbnApi | None = None
        self._inject: InjectFn | None = None
        self._body_of: BodyFn | None = None
        self._now: ClockFn | None = None
        self._tasks: list[asyncio.Task[None]] = []
        self.injected = 0
        self.inject_failures = 0
        self._refresh_due = False
        # Pacing of definition injections (bounded by the item ids: 255 + 256 keys).
        self._last_inject: dict[tuple[ItemKind, int], float] = {}
        self._deferred: dict[tuple[ItemKind, int], asyncio.TimerHandle] = {}
        # Set after every payload handled, version learned or paced injection made.
        self.handled = asyncio.Event()
        self.delivered = asyncio.Event()  # set after every record or report from the WSN

    # ----------------------------------------------------------------- lifecycle

    def bind(self, inject: InjectFn, now: ClockFn, body_of: BodyFn | None = None) -> None:
        """Connect to the sensor network: the runtime's injection and clock, and
        optionally a way to read the body a gateway mote holds for an item (to
        learn versions in force from the network)."""
        self._inject, self._now, self._body_of = inject, now, body_of

    async def start(self) -> None:
        """Re-inject the stored state, then open the transports."""
        if self._inject is None or self._now is None:
            raise RuntimeError("GatewayService.bind() must be called before start()")
        for inj in self.bridge.startup():
            self._inject_all(inj)
        if self.settings.hbn and self._session is not None:
            self.hbn = HbnApi(
                self._session,
                lambda rel, payload, retained, key, size: self.handle(
                    rel, payload, retained=retained, topic=key, via="hbn", size=size
                ),
                prefix=self.settings.prefix,
                max_payload_bytes=self.settings.max_payload_bytes,
                inbox=Inbox(valid=self._valid),
            )
            self.hbn.start()
            self._refresh_now()
            self.hbn.publish(Publish(STATUS_TOPIC, b"online", retain=True))
        if self.mqtt is not None:
            self._tasks.append(asyncio.create_task(self.mqtt.run(), name="gateway-mqtt"))
        self._tasks.append(asyncio.create_task(self._expiry_loop(), name="gateway-expiry"))
        log.info(
            "gateway up: motes %s, prefix %r, MQTT %s, Zenoh HBN %s",
            ",".join(map(str, self.roots)),
            self.settings.prefix,
            self.mqtt.settings.url if self.mqtt else "off",
            "on" if self.hbn else "off",
        )

    async def stop(self) -> None:
        for handle in self._deferred.values():  # the store has them: injected at next start
            handle.cancel()
        self._deferred.clear()
        if self.mqtt is not None:
            self.mqtt.stop()
        for t in self._tasks:
            if t.get_name() != "gateway-mqtt":
                t.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await asyncio.gather(*self._tasks, return_exceptions=True)
        self._tasks.clear()
        if self.hbn is not None:
            with contextlib.suppress(zenoh.ZError):
                self.hbn.publish(Publish(STATUS_TOPIC, b"offline", retain=True))
            self.hbn.close()
            self.hbn = None
        self.store.close()

    async def __aenter__(self) -> GatewayService:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

    # ----------------------------------------------------------------- IP -> WSN

    def handle(
        self,
        rel: str,
        payload: bytes,
        *,
        retained: bool = False,
        topic: str = "",
        via: str = "",
        size: int | None = None,
    ) -> Outcome:
        """One payload from an IP transport (``via``: ``mqtt``, ``hbn`` or ``local``);
        ``size``: the payload's size as sent, when the transport did not copy it whole."""
        only = self.settings.retained_only
        if retained and only is not None and (rel, payload) not in only:
            self.handled.set()
            return Outcome(replay=True)
        out = self.bridge.handle(rel, payload, source=topic or rel, retained=retained, size=size)
        if out.inject is not None:
            self._inject_paced(out.inject)
            self._refresh_hbn()
        if out.error is not None:
            self._report(out.error, via)
        self.handled.set()
        return out

    def _valid(self, m: Incoming) -> bool:
        """Whether a waiting definition is valid on its own (the inbox does not let a
        newer one replace an invalid one, so that it is refused in its turn). Pure:
        the HBN inbox calls it on Zenoh's threads."""
        return self.bridge.validate(m.rel, m.payload, source=m.topic, size=m.size) is None

    def _report(self, error: ErrorReport, via: str) -> None:
        """An error report on the errors topic of the transport it concerns."""
        if via == "mqtt" and self.mqtt is not None:
            self.mqtt.publish(Publish("errors", error.to_json()))
        elif via == "hbn" and self.hbn is not None:
            self.hbn.publish_error(error)

    def define_initial(self, definitions: Iterable[tuple[str, bytes]]) -> list[Outcome]:
        """Apply definitions that come with the deployment (as if published live)."""
        return [
            self.handle(rel, p, topic=f"deployment:{rel}", via="local") for rel, p in definitions
        ]

    def _inject_paced(self, inj: Inject) -> None:
        """Inject a new definition, at most once per ``INJECT_GAP_S`` per item: in a
        burst the newest version goes on the radio at the end of the gap (the motes
        would only pass superseded versions around, and the last one would queue
        behind them). Commands are events: injected at once."""
        if inj.kind is ItemKind.COMMAND:
            self._inject_all(inj)
            return
        key = (inj.kind, inj.item_id)
        if key in self._deferred:
            return  # the deferred injection takes the newest version from the store
        now = time.monotonic()
        wait = self._last_inject.get(key, -math.inf) + INJECT_GAP_S - now
        if wait <= 0:
            self._last_inject[key] = now
            self._inject_all(inj)
            return
        loop = asyncio.get_running_loop()
        self._deferred[key] = loop.call_later(wait, self._inject_deferred, key)

    def _inject_deferred(self, key: tuple[ItemKind, int]) -> None:
        del self._deferred[key]
        item = self.bridge.store.get(*key)
        if item is None:
            return
        self._last_inject[key] = time.monotonic()
        self._inject_all(Inject(item.kind, item.item_id, item.version, item.body))
        self.handled.set()

    def _inject_all(self, inj: Inject) -> None:
        for node in self.roots:
            self._inject_one(node, inj)

    def _inject_one(self, node: int, inj: Inject) -> None:
        assert self._inject is not None
        try:
            self._inject(node, inj)
            self.injected += 1
        except Exception:  # a mote refusing what the bridge accepted is our bug
            self.inject_failures += 1
            log.exception("injecting %s into mote %d failed", inj, node)

    # ----------------------------------------------------------------- WSN -> IP

    def on_event(self, node_id: int, event: object, now: float) -> None:
        """Hook for the runtime: every event of a gateway mote's core."""
        if node_id not in self.roots:
            return
        if isinstance(event, MoteUp) and self._inject is not None:
            # A gateway mote (re)booted with an empty memory: give it the state.
            for inj in self.bridge.startup():
                self._inject_one(node_id, inj)
            return
        if isinstance(event, ItemAdopted):
            if event.source is not None:  # heard from the radio, not injected by us
                self._learn(node_id, event)
            return
        if isinstance(event, InjectSuperseded):
            # Our mote holds a foreign version that ours does not supersede (serial
            # order is not transitive: forged versions can sit anywhere on the circle).
            self._supersede(event)
            return
        payload = getattr(event, "payload", None)
        if not isinstance(payload, DataRecord | GroupReport):
            return
        t = getattr(event, "t", now)
        for p in self.bridge.on_payload(payload, float(t)):
            self.publish(p)
        self.delivered.set()
        if isinstance(payload, GroupReport):
            self._refresh_hbn()

    def _supersede(self, ev: InjectSuperseded) -> None:
        """Re-inject our definition just above the version the mote holds."""
        cur = self.bridge.store.get(ev.kind, ev.item_id)
        if cur is None or wire_version(cur.version) != ev.version:
            return  # a later definition is on its way already
        # Step over it on the radio's circle: the next store version whose u32 is
        # ``held + 1``, newer than ``held`` for every mote (RFC 1982).
        target = cur.version + ((ev.held - ev.version) & 0xFFFFFFFF) + 1
        inj = self.bridge.supersede(ev.kind, ev.item_id, target)
        if inj is not None:
            self._inject_all(inj)

    def _learn(self, node_id: int, ev: ItemAdopted) -> None:
        body: ItemBody | None = None
        if not ev.deleted:
            if self._body_of is None:
                return  # cannot tell what the network holds: leave the store as it is
            body = self._body_of(node_id, ev.kind, ev.item_id)
            if body is None:
                return
        # The mote's u32 version, mapped into the store's non-wrapping count, so
        # that "newer" there is RFC 1982 "newer" on the radio (store.unwrap).
        cur = self.bridge.store.get(ev.kind, ev.item_id)
        version = unwrap(ev.version, None if cur is None else cur.version)
        inj = self.bridge.learn(ev.kind, ev.item_id, version, body)
        if inj is not None:
            self._inject_all(inj)
        self._refresh_hbn()
        self.handled.set()

    def publish(self, p: Publish) -> None:
        if self.mqtt is not None:
            self.mqtt.publish(p)
        if self.hbn is not None:
            try:
                self.hbn.publish(p)
            except zenoh.ZError as e:
                log.warning("Zenoh publish on %s failed: %s", p.topic, e)

    async def _expiry_loop(self) -> None:
        """Clear groups whose leader has not reported for a while (emulated time)."""
        assert self._now is not None
        period = max(0.05, self.bridge.report_period_s / 4)
        while True:
            now = self._now()
            expired = self.bridge.expire(now)
            for p in expired:
                self.publish(p)
            if expired:
                self._refresh_hbn()
            await asyncio.sleep(self._wall(period))

    def _wall(self, emulated: float) -> float:
        """Real seconds of an emulated span."""
        return emulated / self.speed

    # ----------------------------------------------------------------- views

    def state(self) -> dict[str, bytes]:
        """What the Zenoh queryable answers: definitions, groups, status and stats."""
        st: dict[str, bytes] = {
            rel: json.dumps(doc).encode() for rel, doc in self.bridge.definitions().items()
        }
        st.update(self.bridge.group_states())
        st[STATUS_TOPIC] = b"online"
        st[STATS_TOPIC] = json.dumps(self.stats()).encode()
        return st

    def stats(self) -> dict[str, Any]:
        out: dict[str, Any] = {"bridge": self.bridge.stats.as_dict(), "injected": self.injected}
        if self.mqtt is not None:
            out["mqtt"] = self.mqtt.stats.as_dict()
        if self.hbn is not None:
            out["hbn"] = {
                "received": self.hbn.received,
                "dropped": self.hbn.dropped,
                "queries": self.hbn.queries,
                "inbox": self.hbn.inbox.stats.as_dict(),
            }
        return out

    def _refresh_hbn(self) -> None:
        """Renew the queryable's snapshot once the loop is free: a burst of
        definitions makes one snapshot, not one per definition (each is a JSON
        dump of every definition and group)."""
        if self.hbn is None or self._refresh_due:
            return
        self._refresh_due = True
        asyncio.get_running_loop().call_soon(self._refresh_now)

    def _refresh_now(self) -> None:
        self._refresh_due = False
        if self.hbn is not None:
            self.hbn.set_state(self.state())


def _fields(s: MqttSettings) -> dict[str, Any]:
    return {f: getattr(s, f) for f in s.__slots__}


def attach_to_fleet(
    fleet: Fleet,
    *,
    settings: GatewaySettings | None = None,
    mqtt: MqttSettings | None = None,
    hbn: bool = True,
) -> GatewayService:
    """A :class:`GatewayService` on the gateway motes (collection roots) ``fleet`` runs.

    Call after entering the fleet (its cores exist); then ``async with`` the
    service. Items are injected with ``fleet.run_on``; a root that is not on
    the air yet gets the whole state when it boots (``MoteUp``).
    """
    cores = {i: r.core for i, r in fleet.runners.items()}
    roots = sorted(i for i, c in cores.items() if isinstance(c, AwareMote) and c.config.is_root)
    if not roots:
        raise ValueError(f"deployment {fleet.deployment.name!r} has no gateway mote here")
    core = cores[roots[0]]
    assert isinstance(core, AwareMote)
    svc = GatewayService(
        roots,
        config=core.config,
        settings=settings,
        mqtt=mqtt,
        zenoh_session=fleet.session if hbn else None,
        known_nodes=fleet.deployment.ids,
        speed=fleet.speed,
    )

    def inject(node: int, inj: Inject) -> None:
        if not fleet.alive(node):
            return  # not booted yet: MoteUp brings the whole state
        fleet.run_on(node, lambda c, now: _inject_core(c, inj, now))

    def body_of(node: int, kind: ItemKind, item_id: int) -> ItemBody | None:
        core = fleet.runners[node].core
        if not isinstance(core, AwareMote):
            return None
        item = core.dissemination.items.get((kind, item_id))
        return None if item is None else item.body

    svc.bind(inject, fleet.now, body_of)
    fleet.on_event(svc.on_event)
    return svc


def _inject_core(core: object, inj: Inject, now: float) -> None:
    if not isinstance(core, AwareMote):
        raise TypeError(f"gateway mote core is a {type(core).__name__}, not an AwareMote")
    core.inject(inj.kind, inj.item_id, wire_version(inj.version), inj.body, now)
