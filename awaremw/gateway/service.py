"""The gateway service: gateway motes + bridge + MQTT + Zenoh HBN, wired together.

:class:`GatewayService` only wires: what the transports hand it (:meth:`handle`,
with their :class:`~awaremw.gateway.events.Transport`), the gateway motes'
events (:meth:`on_event`) and the time go to the :class:`GatewayBridge`, which
makes every decision; its actions go out (:meth:`_apply`): publications on MQTT
and Zenoh, injections into the gateway motes, refusals on the errors topic of
the transport the payload came by (``<prefix>/errors``, ``<prefix>/hbn/errors``),
a new snapshot for the Zenoh queryable. The runtime provides two callables
(:meth:`bind`): ``inject(node_id, Inject)`` puts an item into a gateway mote's
core (inside the loop that drives it), ``now()`` is the fleet's emulated time.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, assert_never

import zenoh

from awaremw.gateway.bridge import BodyFn, BridgePolicy, GatewayBridge
from awaremw.gateway.events import (
    Action,
    Inject,
    Outcome,
    Publish,
    Report,
    StateChanged,
    Transport,
)
from awaremw.gateway.hbn import HbnApi
from awaremw.gateway.inbox import Inbox, Incoming
from awaremw.gateway.mqtt import (
    ERRORS_TOPIC,
    STATS_TOPIC,
    STATUS_TOPIC,
    MqttBridge,
    MqttSettings,
)
from awaremw.gateway.schema import Limits, is_copy
from awaremw.gateway.store import VersionStore, wire_version
from awaremw.protocol.config import MiddlewareConfig
from awaremw.protocol.events import MoteEvent
from awaremw.protocol.frames import ItemBody, ItemKind
from awaremw.protocol.mote import AwareMote
from awaremw.runtime.fleet import Fleet

log = logging.getLogger(__name__)

InjectFn = Callable[[int, Inject], None]
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
                retained_only=s.retained_only,
            ),
        )
        self.mqtt: MqttBridge | None = None
        if mqtt is not None:
            self.mqtt = MqttBridge(
                replace(mqtt, prefix=s.prefix),
                lambda rel, payload, retained, topic: self.handle(
                    rel, payload, retained=retained, topic=topic, via=Transport.MQTT
                ),
                self._valid,
                self._is_copy,
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
        # What MQTT was last given of each definition (bounded by the item ids).
        self._mirrored: dict[str, bytes] = {}
        # Pacing of definition injections (bounded by the item ids: 255 + 256 keys).
        self._last_inject: dict[tuple[ItemKind, int], float] = {}
        self._deferred: dict[tuple[ItemKind, int], asyncio.TimerHandle] = {}
        # Set after every payload handled, version learned or paced injection made.
        self.handled = asyncio.Event()
        self.delivered = asyncio.Event()  # set after every publication (records, groups)

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
        self._apply(self.bridge.startup())
        if self.settings.hbn and self._session is not None:
            self.hbn = HbnApi(
                self._session,
                lambda rel, payload, retained, key, size: self.handle(
                    rel, payload, retained=retained, topic=key, via=Transport.HBN, size=size
                ),
                prefix=self.settings.prefix,
                max_payload_bytes=self.settings.max_payload_bytes,
                inbox=Inbox(valid=self._valid, is_copy=self._is_copy),
            )
            self.hbn.start()
            self.hbn.publish(Publish(STATUS_TOPIC, b"online", retain=True))
        # Both transports show the store from the start: the query's snapshot, and
        # on MQTT every definition retained with its version (a deleted one cleared),
        # over whatever the broker kept while the gateway was away.
        self._sync_views()
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
        via: Transport = Transport.LOCAL,
        size: int | None = None,
    ) -> Outcome:
        """One payload from an IP transport; ``size``: the payload's size as sent,
        when the transport did not copy it whole."""
        out = self.bridge.handle(
            rel, payload, source=topic or rel, retained=retained, size=size, via=via
        )
        self._apply(out.actions, paced=True)
        if via is Transport.MQTT and not (out.replay and self.settings.retained_only is not None):
            self._answer_retained(rel, payload)
        self.handled.set()
        return out

    def _answer_retained(self, rel: str, payload: bytes) -> None:
        """The broker now retains ``payload`` on ``rel``: if that is not what the store
        holds there (a plain definition, one refused, an older copy, one changed
        while the gateway was away and replayed), publish the store's over it. The
        gateway hears its own publication back equal to the store: no loop."""
        want = self.bridge.definition_payload(rel)
        if want is None or self.mqtt is None:
            return
        # Either way MQTT ends up holding ``want``: the views' sync need not send it
        # again (a client's deletion is on the broker already, with nothing to add).
        self._mirrored[rel] = want
        if payload != want:
            self.mqtt.publish(Publish(rel, want, retain=True))

    def _valid(self, m: Incoming) -> bool:
        """Whether a waiting definition is valid on its own (the inbox does not let a
        newer one replace an invalid one, so that it is refused in its turn). Pure:
        the HBN inbox calls it on Zenoh's threads."""
        return self.bridge.validate(m.rel, m.payload, source=m.topic, size=m.size) is None

    @staticmethod
    def _is_copy(m: Incoming) -> bool:
        """Whether a waiting definition is a copy with its version (pure: the HBN inbox
        calls it on Zenoh's threads)."""
        return is_copy(m.payload)

    def _apply(self, actions: Iterable[Action], *, paced: bool = False) -> None:
        """Carry out the bridge's actions; ``paced``: injections of definitions
        from the IP side (a burst goes on the radio as its newest version)."""
        for a in actions:
            match a:
                case Publish():
                    self.publish(a)
                    self.delivered.set()
                case Inject() if a.node is not None:
                    self._inject_one(a.node, a)
                case Inject():
                    (self._inject_paced if paced else self._inject_all)(a)
                case Report(via=Transport.MQTT) if self.mqtt is not None:
                    self.mqtt.publish(Publish(ERRORS_TOPIC, a.error.to_json()))
                case Report(via=Transport.HBN) if self.hbn is not None:
                    self.hbn.publish_error(a.error)
                case Report():
                    pass  # a local payload, or its transport is off: the Outcome has it
                case StateChanged():
                    self._views_changed()
                    self.handled.set()
                case _:
                    assert_never(a)

    def define_initial(self, definitions: Iterable[tuple[str, bytes]]) -> list[Outcome]:
        """Apply definitions that come with the deployment (as if published live)."""
        return [self.handle(rel, p, topic=f"deployment:{rel}") for rel, p in definitions]

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
        item = self.bridge.item(*key)
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

    def on_event(self, node_id: int, event: MoteEvent, now: float) -> None:
        """Hook for the runtime: every event of a gateway mote's core."""
        if node_id not in self.roots:
            return
        self._apply(self.bridge.on_mote_event(node_id, event, self._body_of))

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
            self._apply(self.bridge.tick(self._now()))
            await asyncio.sleep(self._wall(period))

    def _wall(self, emulated: float) -> float:
        """Real seconds of an emulated span."""
        return emulated / self.speed

    # ----------------------------------------------------------------- views

    def state(self, definitions: Mapping[str, bytes] | None = None) -> dict[str, bytes]:
        """What the Zenoh queryable answers: definitions (``definitions``: the bridge's
        payloads when already taken), groups, status and stats."""
        if definitions is None:
            definitions = self.bridge.definition_payloads()
        st = {rel: p for rel, p in definitions.items() if p}
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

    def _views_changed(self) -> None:
        """Renew what the transports show once the loop is free: a burst of
        definitions makes one snapshot, not one per definition (each is a JSON
        dump of every definition and group)."""
        if self._refresh_due or (self.hbn is None and self.mqtt is None):
            return
        self._refresh_due = True
        asyncio.get_running_loop().call_soon(self._sync_views)

    def _sync_views(self) -> None:
        """The store, shown on both transports: the Zenoh queryable's snapshot, and
        each definition that changed retained on MQTT in the same bytes."""
        self._refresh_due = False
        definitions = self.bridge.definition_payloads()  # one store read for both
        if self.hbn is not None:
            self.hbn.set_state(self.state(definitions))
        if self.mqtt is None:
            return
        for rel, payload in definitions.items():
            if self._mirrored.get(rel) != payload:
                self._mirrored[rel] = payload
                self.mqtt.publish(Publish(rel, payload, retain=True))


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
