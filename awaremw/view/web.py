"""The web dashboard: the field, the groups, live plots of every channel, the
definitions, and a form that defines groups and channels and sends commands.

One :class:`Dashboard` per run, in the caller's asyncio loop:

* an aiohttp server (``GET /`` the page, ``GET /api/state`` the JSON state,
  ``GET /api/events`` Server-Sent Events, ``POST``/``DELETE /api/def/...`` and
  ``POST /api/cmd/<name>`` that publish on the public MQTT contract on the
  user's behalf);
* an MQTT subscriber to ``<prefix>/#`` (:class:`MqttFeed`): definitions
  (retained ``def/...``), group states (retained ``groups/...``), data records,
  refusals (``errors``) and the gateway's status; the same client publishes the
  page's definitions and commands, so the gateway validates them as it does any
  other client's and its refusals come back on ``<prefix>/errors``;
* the field: positions and, where the caller has the motes in its process
  (``awaremw demo``), every mote's group memberships and collection-tree parent
  read from the cores (:meth:`Dashboard.update_field`). Without the cores
  (``awaremw view``) positions come from the deployment's mobility (or from the
  fleets' control queryable) and group membership from the public contract,
  which names each group's leader but not its members.

Every buffer is bounded: plot history per channel (:data:`SERIES_POINTS`), the
number of channels and groups kept, the errors, the trail, the SSE clients and
their queues (a client that does not keep up is dropped).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import re
import time
from collections import deque
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from importlib import resources
from typing import Any

import aiohttp
import aiomqtt
import zenoh
from aiohttp import web

from awaremw.gateway.mqtt import MqttSettings
from awaremw.protocol.attributes import STANDARD, UNITS
from awaremw.protocol.core import MoteCore
from awaremw.protocol.mote import AwareMote
from awaremw.runtime.deployment import Deployment
from awaremw.view.guard import (
    MAX_CONNECTIONS,
    REQUEST_TIMEOUT_S,
    BoundedListener,
    InsecureBind,
    RequestGuard,
    check_bind,
    parse_host_port,
)
from awaremw.view.snapshot import MoteDot
from awaremw.world.fields import World

log = logging.getLogger(__name__)

SERIES_POINTS = 300  # plotted records kept per channel (ring)
MAX_CHANNELS = 64  # channels with a plot; the least recently fed is dropped beyond
MAX_GROUPS = 1024  # group states kept from the MQTT contract
MAX_ERRORS = 50  # refusals shown
MAX_DEFS = 128  # definitions of each kind kept
MAX_DEF_BYTES = 1000  # a definition kept larger than this is shown as its size only
MAX_ERROR_CHARS = 200  # of each field of a refusal shown
MAX_ERROR_FIELDS = 4  # fields of a refusal shown (the gateway's: topic, code, error, payload)
TRAIL_POINTS = 240  # positions kept per mobile mote (the robot's trail)
MAX_TRAILS = 16  # robots with a trail (the first seen)
MAX_CLIENTS = 32  # SSE clients at once; beyond, 503
CLIENT_QUEUE = 64  # events queued per SSE client; a client that falls behind is dropped
MAX_BODY = 4096  # bytes of a definition or command the page may post
CLOCK_RESTART_S = 30.0  # a live stamp this far behind the clock means the fleet restarted
STATE_INTERVAL_S = 0.5  # wall seconds between pushed state updates (at most)
FIELD_BUDGET = 64 * 1024  # bytes of changed motes in one ``field`` event; the rest go next
EVENT_BOUND = 256 * 1024  # no event after ``hello`` is larger (docs/dashboard.md)
PASSWORD_ENV = "AWAREMW_WEB_PASSWORD"  # the dashboard's password (Basic auth), beyond loopback
NAME_RE = re.compile(r"^[A-Za-z0-9_.-]{1,32}$")

UNIT_LABELS = {"degC": "°C"}


class DashboardError(RuntimeError):
    """The dashboard cannot serve (its address is taken or not this host's)."""


def unit_of(attr: str | None, agg: str | None = None) -> str:
    """The unit of a channel's values: ``°C``, ``%RH``, ``lx``, ``m``, ``V``, ``ppm``,
    ``dBm`` for ``rssi:<node>``; COUNT counts motes."""
    if agg == "count":
        return "motes"
    if attr is None:
        return ""
    if attr.startswith("rssi:"):
        return "dBm"
    u = UNITS.get(STANDARD.get(attr, -1), "")
    return UNIT_LABELS.get(u, u)


@dataclass(slots=True)
class MoteView:
    id: int
    kind: str
    x: float
    y: float
    alive: bool = True
    groups: dict[int, tuple[int, bool]] = field(default_factory=dict)  # type -> (gid, leader)
    parent: int | None = None  # collection tree
    leds: tuple[str, ...] = ()  # lit LEDs (where the cores are known)


@dataclass(frozen=True, slots=True)
class FieldMote:
    """One mote as the caller sees it: where it is, and (when known) its groups."""

    id: int
    kind: str
    x: float
    y: float
    alive: bool = True
    groups: Mapping[int, tuple[int, bool]] | None = None  # None: unknown here
    parent: int | None = None
    leds: tuple[str, ...] = ()  # lit LEDs, by colour


# One mote as the page draws it: kind, x, y, alive, parent (-1: none), lit LEDs,
# and its groups as (type, group id, leader 0/1).
Row = tuple[str, float, float, int, int, tuple[str, ...], tuple[tuple[int, int, int], ...]]


class DashboardState:
    """What the page shows; fed by the field source and the MQTT feed. Bounded."""

    def __init__(
        self,
        area: tuple[float, float],
        title: str = "awaremw",
        group_type: int | None = None,
        world: World | None = None,
    ) -> None:
        self.area = area
        self.title = title
        self.group_type = group_type  # the type the map colours by default
        self.world = world
        self.t = 0.0  # emulated time of the field shown
        self.heard_t = 0.0  # the fleet's emulated time, as last heard (see _clock)
        self.live_clock = False  # heard_t comes from a live message or the fleets themselves
        self.motes: dict[int, MoteView] = {}
        self.members_known = False  # memberships come from the cores (else leaders only)
        self.tree_known = False
        self.trails: dict[int, deque[tuple[float, float]]] = {}
        self.group_states: dict[tuple[int, int], dict[str, Any]] = {}
        self.defs: dict[str, dict[str, Any]] = {"group": {}, "channel": {}}
        self.series: dict[int, deque[list[float]]] = {}  # channel -> [t, value, gid]
        self.series_info: dict[int, dict[str, Any]] = {}
        self.errors: deque[dict[str, Any]] = deque(maxlen=MAX_ERRORS)
        self.gateway_status = "unknown"
        self.mqtt_connected = False
        self.records = 0
        self.dropped_clients = 0
        # Role -> {motes, mj_per_hour, frames_per_hour} (experiments.snapshot.role_energy)
        self.energy: dict[str, dict[str, float]] = {}
        self.version = 0  # bumped on every change
        self.defs_version = 0  # bumped when a definition changes

    # ------------------------------------------------------------------ field

    def set_field(self, now: float, motes: Iterable[FieldMote]) -> None:
        self.t = now
        seen: set[int] = set()
        for m in motes:
            seen.add(m.id)
            v = self.motes.get(m.id)
            if v is None:
                v = self.motes[m.id] = MoteView(m.id, m.kind, m.x, m.y)
            v.x, v.y, v.alive, v.kind, v.leds = m.x, m.y, m.alive, m.kind, m.leds
            if m.groups is not None:
                self.members_known = True
                v.groups = dict(m.groups)
                v.parent = m.parent
                self.tree_known = True
            if m.id in self.trails or (m.kind == "robot" and len(self.trails) < MAX_TRAILS):
                tr = self.trails.setdefault(m.id, deque(maxlen=TRAIL_POINTS))
                if not tr or (abs(tr[-1][0] - m.x) + abs(tr[-1][1] - m.y)) > 0.05:
                    tr.append((round(m.x, 2), round(m.y, 2)))
        for gone in set(self.motes) - seen:
            del self.motes[gone]
            self.trails.pop(gone, None)
        self.version += 1

    # ------------------------------------------------------------------ MQTT

    def on_message(self, rel: str, payload: bytes, retained: bool = False) -> str | None:
        """One message under the prefix (``rel`` without it); returns the kind of
        change (``"record"``, ``"error"``, ``"state"``) or None if ignored.
        ``retained``: replayed by the broker on subscription (maybe from an
        earlier run), so its time stamp does not set the clock once a live one has."""
        parts = rel.split("/")
        try:
            doc: Any = json.loads(payload) if payload else None
        except (UnicodeDecodeError, json.JSONDecodeError):
            doc = None
            if parts[0] not in ("gateway",):
                log.info("dashboard: not JSON on %s", rel)
                return None
        if parts[:2] == ["gateway", "status"]:
            self.gateway_status = payload.decode(errors="replace")[:20]
        elif len(parts) == 3 and parts[0] == "def" and parts[1] in ("group", "channel"):
            defs = self.defs[parts[1]]
            if doc is None:
                defs.pop(parts[2], None)
            elif len(defs) < MAX_DEFS or parts[2] in defs:
                defs[parts[2]] = doc if len(payload) <= MAX_DEF_BYTES else {
                    "too_large": len(payload)}  # fmt: skip
            self.defs_version += 1
            if parts[1] == "channel" and isinstance(doc, dict):
                self._channel_info(_int(parts[2]), doc.get("attr"), doc.get("agg"))
        elif len(parts) == 3 and parts[0] == "groups":
            key = (_int(parts[1]), _int(parts[2]))
            if key[0] < 0 or key[1] < 0:
                return None
            if not isinstance(doc, dict) or "merged_into" in doc:
                self.group_states.pop(key, None)
            else:
                if key not in self.group_states and len(self.group_states) >= MAX_GROUPS:
                    oldest = min(self.group_states, key=lambda k: self.group_states[k]["t"])
                    del self.group_states[oldest]
                self.group_states[key] = {
                    "leader": _int(doc.get("leader")), "weight": _num(doc.get("weight")),
                    "readings": _num(doc.get("readings")), "t": _float(doc.get("t")),
                }  # fmt: skip
                self._clock(_float(doc.get("t")), retained)
        elif len(parts) == 4 and parts[0] == "data" and isinstance(doc, dict):
            ch, gt, gid = (_int(p) for p in parts[1:])
            value, t = _float(doc.get("value")), _float(doc.get("t"))
            if ch < 0 or value != value:
                return None
            self._channel_info(ch, doc.get("attr"), doc.get("agg"), gt)
            ring = self.series.get(ch)
            if ring is None:
                if len(self.series) >= MAX_CHANNELS:
                    stale = min(self.series, key=lambda c: self.series[c][-1][0])
                    del self.series[stale]
                ring = self.series[ch] = deque(maxlen=SERIES_POINTS)
            ring.append([round(t, 3), value, gid])
            self.records += 1
            self._clock(t, retained)
            self.version += 1
            return "record"
        elif parts == ["errors"]:
            self.errors.append(_small(doc))
            self.version += 1
            return "error"
        else:
            return None
        self.version += 1
        return "state"

    def _clock(self, t: float, retained: bool) -> None:
        """The fleet's time from a message's stamp. Retained stamps may be an
        earlier run's: they count only until a live one is heard. Live stamps
        only move the clock forward (records of several leaders interleave),
        unless far behind: then the fleet was restarted."""
        if t != t:
            return
        if retained:
            if not self.live_clock and t > self.heard_t:
                self.heard_t = t
            return
        if not self.live_clock or t > self.heard_t or t < self.heard_t - CLOCK_RESTART_S:
            self.heard_t = t
        self.live_clock = True

    def fleet_time(self, t: float) -> None:
        """The fleets' own emulated time (their control queryable): it wins."""
        if t == t:
            self.heard_t = t
            self.live_clock = True

    def _channel_info(self, ch: int, attr: Any, agg: Any, gtype: int | None = None) -> None:
        if ch < 0:
            return
        info = self.series_info.setdefault(ch, {})
        if len(self.series_info) > MAX_CHANNELS * 2:
            self.series_info.pop(next(iter(self.series_info)))
        if isinstance(attr, str):
            info["attr"] = attr[:40]
        if isinstance(agg, str):
            info["agg"] = agg[:10]
        if gtype is not None:
            info["group_type"] = gtype
        info["unit"] = unit_of(info.get("attr"), info.get("agg"))

    # ------------------------------------------------------------------ views

    def leaders(self) -> dict[int, tuple[int, int]]:
        """Leader mote -> (type, gid), from the group states (view without cores)."""
        return {int(s["leader"]): k for k, s in self.group_states.items()}

    def groups(self, members: bool = True) -> list[dict[str, Any]]:
        """Every group known; with ``members`` their member lists, else their sizes
        (``members`` null where only the leader is known)."""
        out: dict[tuple[int, int], dict[str, Any]] = {}
        if self.members_known:
            for m in self.motes.values():
                for gt, (gid, lead) in m.groups.items():
                    g = out.setdefault((gt, gid), {"type": gt, "id": gid, "leader": None,
                                                   "members": []})  # fmt: skip
                    g["members"].append(m.id)
                    if lead:
                        g["leader"] = m.id
        for (gt, gid), s in self.group_states.items():
            if (gt, gid) not in out:
                if self.members_known:
                    continue  # reported but no longer on the air
                out[(gt, gid)] = {"type": gt, "id": gid, "leader": s["leader"], "members": None}
            out[(gt, gid)].update(weight=s["weight"], readings=s["readings"], reported_t=s["t"])
        docs = [out[k] for k in sorted(out)]
        if not members:
            for g in docs:
                g["size"] = None if g["members"] is None else len(g["members"])
                del g["members"]
        return docs

    def _colour_type(self) -> int | None:
        if self.group_type is not None:
            return self.group_type
        types = sorted({k[0] for k in self.group_states} | {
            t for m in self.motes.values() for t in m.groups})  # fmt: skip
        return types[0] if types else None

    def _groups_of(self, m: MoteView, leaders: Mapping[int, tuple[int, int]]) -> dict[
            int, tuple[int, bool]]:  # fmt: skip
        groups = m.groups
        if not self.members_known and m.id in leaders:
            gt, gid = leaders[m.id]
            groups = {**groups, gt: (gid, True)}
        return groups

    def rows(self) -> dict[int, Row]:
        """Every mote as the page draws it (the ``field`` events carry these)."""
        leaders = {} if self.members_known else self.leaders()
        out: dict[int, Row] = {}
        for m in self.motes.values():
            groups = self._groups_of(m, leaders)
            out[m.id] = (
                m.kind, round(m.x, 2), round(m.y, 2), int(m.alive),
                -1 if m.parent is None else m.parent, m.leds,
                tuple((t, gid, int(lead)) for t, (gid, lead) in sorted(groups.items())),
            )  # fmt: skip
        return out

    def fires(self) -> list[dict[str, Any]]:
        fires = []
        if self.world is not None:
            for f in self.world.fires:
                s = f.state(self.t)
                if s is not None:
                    fires.append({"name": f.name, "x": s.x, "y": s.y,
                                  "radius": s.radius + f.edge})  # fmt: skip
        return fires

    def meta(self) -> dict[str, Any]:
        """Everything the page shows but the motes and the definitions: the
        ``state`` events (bounded: groups by :data:`MAX_GROUPS`, errors cut)."""
        groups = self.groups(members=False)
        return {
            "title": self.title,
            "t": round(self.t, 2),
            "area": list(self.area),
            "group_type": self._colour_type(),
            "members_known": self.members_known,
            "tree_known": self.tree_known,
            "n_motes": len(self.motes),
            "groups": groups[:MAX_GROUPS],
            "groups_total": len(groups),
            "trails": {str(k): list(v) for k, v in self.trails.items()},
            "fires": self.fires(),
            "channels": {str(c): i for c, i in sorted(self.series_info.items())},
            "errors": list(self.errors),
            "gateway": self.gateway_status,
            "mqtt": self.mqtt_connected,
            "records": self.records,
            "energy": self.energy,
        }

    def state(self) -> dict[str, Any]:
        """The whole state (``GET /api/state``): every mote, groups with members."""
        leaders = {} if self.members_known else self.leaders()
        gtype = self._colour_type()
        motes = []
        for m in sorted(self.motes.values(), key=lambda m: m.id):
            groups = self._groups_of(m, leaders)
            g = groups.get(gtype) if gtype is not None else None
            motes.append({
                "id": m.id, "kind": m.kind, "x": round(m.x, 3), "y": round(m.y, 3),
                "alive": m.alive, "group": None if g is None else g[0],
                "leader": bool(g and g[1]),
                "groups": {str(t): {"id": gid, "leader": lead}
                           for t, (gid, lead) in sorted(groups.items())},
                "parent": m.parent, "leds": list(m.leds),
            })  # fmt: skip
        return {
            **self.meta(),
            "motes": motes,
            "groups": self.groups(),
            "definitions": self.defs,
        }

    def series_doc(self) -> dict[str, Any]:
        return {str(c): list(r) for c, r in self.series.items()}


def _small(doc: Any) -> dict[str, Any]:
    """A refusal from ``errors``, cut to a bounded size for the page."""
    if not isinstance(doc, dict):
        return {"error": str(doc)[:MAX_ERROR_CHARS]}
    out: dict[str, Any] = {}
    for k, v in list(doc.items())[:MAX_ERROR_FIELDS]:
        out[str(k)[:40]] = v if isinstance(v, int | float | bool) or v is None else (
            str(v)[:MAX_ERROR_CHARS])  # fmt: skip
    return out


def _num(v: Any) -> float | None:
    """A number from a remote document, or None (never a long string)."""
    return v if isinstance(v, int | float) and not isinstance(v, bool) else None


def _int(v: Any) -> int:
    try:
        return int(v)
    except (TypeError, ValueError):
        return -1


def _float(v: Any) -> float:
    try:
        return float(v)
    except (TypeError, ValueError):
        return float("nan")


def bounded_meta(meta: dict[str, Any], bound: int = EVENT_BOUND) -> str:
    """The JSON of a ``state`` event, at most ``bound`` bytes: beyond it (only
    with hundreds of groups and long refusals) the list of groups is cut."""
    text = json.dumps(meta, separators=(",", ":"))
    while len(text.encode()) > bound and meta["groups"]:
        meta["groups"] = meta["groups"][: len(meta["groups"]) // 2]
        text = json.dumps(meta, separators=(",", ":"))
    return text


def _row_json(i: int, r: Row) -> str:
    return json.dumps([i, *r], separators=(",", ":"))


class FieldStream:
    """The field on the SSE stream: all of it in ``hello``, then only the motes
    whose row changed since the last push, at most ``budget`` bytes of them per
    update; the rest stay different from what was sent and go next time."""

    def __init__(self, budget: int = FIELD_BUDGET) -> None:
        self.budget = budget
        self.sent: dict[int, Row] = {}

    @staticmethod
    def full(rows: Mapping[int, Row]) -> str:
        """Every row, as the JSON of a ``{"rows": [...]}`` document."""
        return '{"rows":[' + ",".join(_row_json(i, r) for i, r in sorted(rows.items())) + "]}"

    def delta(self, rows: Mapping[int, Row]) -> tuple[str | None, int]:
        """(the JSON of the next ``field`` event or None if nothing changed, the
        number of changed motes left for later)."""
        gone = [i for i in self.sent if i not in rows][: self.budget // 8]
        for i in gone:
            del self.sent[i]
        parts: list[str] = []
        used = 40 + sum(len(str(i)) + 1 for i in gone)
        left = 0
        for i, r in rows.items():
            if self.sent.get(i) == r:
                continue
            text = _row_json(i, r)
            if used + len(text) + 1 > self.budget:
                left += 1
                continue
            used += len(text) + 1
            parts.append(text)
            self.sent[i] = r
        left += sum(1 for i in self.sent if i not in rows)
        if not parts and not gone:
            return None, left
        doc = ('{"rows":[' + ",".join(parts) + '],"gone":' + json.dumps(gone) +
               f',"left":{left}}}')  # fmt: skip
        return doc, left


class MqttFeed:
    """Subscribes to ``<prefix>/#`` and publishes on the page's behalf; reconnects."""

    def __init__(self, settings: MqttSettings, on_message: Callable[[str, bytes, bool], None],
                 on_connected: Callable[[bool], None]) -> None:  # fmt: skip
        self.settings = settings
        self.on_message = on_message
        self.on_connected = on_connected
        self._client: aiomqtt.Client | None = None
        self._stop = asyncio.Event()

    async def run(self) -> None:
        s = self.settings
        delay = 0.2
        while not self._stop.is_set():
            try:
                async with s.client(s.client_id, max_queued_incoming_messages=1000) as client:
                    self._client = client
                    await client.subscribe(f"{s.prefix}/#", qos=1)
                    self.on_connected(True)
                    delay = 0.2
                    n = len(s.prefix) + 1
                    async for msg in client.messages:
                        payload = msg.payload if isinstance(msg.payload, bytes) else (
                            str(msg.payload or "").encode())  # fmt: skip
                        self.on_message(str(msg.topic)[n:], payload, bool(msg.retain))
            except aiomqtt.MqttError as e:
                log.warning("dashboard MQTT %s: %s (retrying)", s.url, e)
            finally:
                self._client = None
                self.on_connected(False)
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._stop.wait(), delay)
            delay = min(delay * 2, 5.0)

    def stop(self) -> None:
        self._stop.set()

    async def publish(self, rel: str, payload: bytes, retain: bool) -> None:
        if self._client is None:
            raise ConnectionError(f"not connected to the MQTT broker {self.settings.url}")
        await self._client.publish(f"{self.settings.prefix}/{rel}", payload, qos=1, retain=retain)


class Dashboard:
    """The dashboard server. ``async with Dashboard(...)`` serves until the block ends.

    Only its user drives it (:mod:`awaremw.view.guard`): loopback unless a
    ``password`` is given; every request names the dashboard in ``Host``; a
    definition or command must be same-origin and carry the page's token; at
    most :data:`~awaremw.view.guard.MAX_CONNECTIONS` connections at once."""

    def __init__(
        self,
        state: DashboardState,
        mqtt: MqttSettings,
        host: str = "127.0.0.1",
        port: int = 8080,
        password: str | None = None,
        *,
        max_connections: int = MAX_CONNECTIONS,
        request_timeout: float = REQUEST_TIMEOUT_S,
    ) -> None:
        self.state = state
        self.max_connections = max_connections
        self.request_timeout = request_timeout
        self.host = host
        self.port = port
        self.password = password or None
        self.feed = MqttFeed(mqtt, self._on_mqtt, self._on_connected)
        self.guard: RequestGuard | None = None
        self.listener: BoundedListener | None = None
        self._clients: set[asyncio.Queue[bytes | None]] = set()
        self._runner: web.AppRunner | None = None
        self._tasks: list[asyncio.Task[None]] = []
        self._pushed_version = -1
        self._pushed_defs = -1
        self._field = FieldStream()
        self._wake = asyncio.Event()

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}/"

    @property
    def token(self) -> str:
        """The per-server token the page sends with every definition and command."""
        assert self.guard is not None, "the dashboard is not serving"
        return self.guard.token

    # ------------------------------------------------------------------ lifecycle

    async def __aenter__(self) -> Dashboard:
        try:
            check_bind(self.host, self.port, self.password)
        except InsecureBind as e:
            raise DashboardError(str(e)) from None
        try:
            self.listener = BoundedListener(
                self.host, self.port, limit=self.max_connections, timeout=self.request_timeout
            )
        except OSError as e:
            raise DashboardError(f"cannot serve the dashboard on {self.host}:{self.port}: "
                                 f"{e.strerror or e}") from None  # fmt: skip
        self.port = self.listener.port
        self.guard = RequestGuard(self.host, self.port, self.password)
        app = web.Application(
            client_max_size=MAX_BODY * 2,
            middlewares=[self.listener.middleware, self.guard.middleware],
        )
        app.add_routes([
            web.get("/", self._index),
            web.get("/static/{name}", self._static),
            web.get("/api/state", self._api_state),
            web.get("/api/series", self._api_series),
            web.get("/api/events", self._events),
            web.post("/api/def/{kind}/{id}", self._define),
            web.delete("/api/def/{kind}/{id}", self._define),
            web.post("/api/cmd/{name}", self._command),
        ])  # fmt: skip
        self._runner = web.AppRunner(
            app, access_log=None, handle_signals=False, shutdown_timeout=1.0,
            keepalive_timeout=REQUEST_TIMEOUT_S, max_line_size=4096, max_field_size=4096,
        )  # fmt: skip
        await self._runner.setup()
        server = self._runner.server
        assert server is not None
        self.listener.start(server)
        self._tasks = [
            asyncio.create_task(self.feed.run(), name="dashboard-mqtt"),
            asyncio.create_task(self._pusher(), name="dashboard-push"),
        ]
        return self

    async def __aexit__(self, *exc: object) -> None:
        self.feed.stop()
        for q in list(self._clients):
            _offer(q, None)
        for t in self._tasks:
            t.cancel()
        for t in self._tasks:
            with contextlib.suppress(asyncio.CancelledError):
                await t
        if self.listener is not None:
            await self.listener.close()
        if self._runner is not None:
            await self._runner.cleanup()

    # ------------------------------------------------------------------ feeding

    def update_field(
        self,
        now: float,
        motes: Iterable[FieldMote],
        energy: dict[str, dict[str, float]] | None = None,
    ) -> None:
        self.state.set_field(now, motes)
        if energy is not None:
            self.state.energy = energy
        self._wake.set()

    def _on_mqtt(self, rel: str, payload: bytes, retained: bool) -> None:
        kind = self.state.on_message(rel, payload, retained)
        if kind == "record":
            ch = rel.split("/")[1]
            last = self.state.series.get(_int(ch))
            if last:
                info = self.state.series_info.get(_int(ch), {})
                self._broadcast("record", {"channel": ch, "point": last[-1], "info": info})
        elif kind is not None:
            self._wake.set()

    def _on_connected(self, up: bool) -> None:
        self.state.mqtt_connected = up
        self.state.version += 1
        self._wake.set()

    def _broadcast(self, event: str, doc: Any) -> None:
        self._send(event, json.dumps(doc, separators=(",", ":")))

    def _send(self, event: str, data: str) -> None:
        msg = f"event: {event}\ndata: {data}\n\n".encode()
        for q in list(self._clients):
            if not _offer(q, msg):
                self._clients.discard(q)  # a slow client: dropped, its stream ends
                self.state.dropped_clients += 1
                _offer(q, None, force=True)

    async def _pusher(self) -> None:
        while True:
            await self._wake.wait()
            self._wake.clear()
            if self._clients and self.state.version != self._pushed_version:
                self._pushed_version = self.state.version
                field_doc, left = self._field.delta(self.state.rows())
                if field_doc is not None:
                    self._send("field", field_doc)
                self._send("state", bounded_meta(self.state.meta()))
                if self.state.defs_version != self._pushed_defs:
                    self._pushed_defs = self.state.defs_version
                    self._broadcast("defs", self.state.defs)
                if left:  # the field's rest goes next time
                    self._pushed_version = -1
                    self._wake.set()
            await asyncio.sleep(STATE_INTERVAL_S)  # rate limit, not synchronisation

    # ------------------------------------------------------------------ handlers

    async def _index(self, request: web.Request) -> web.StreamResponse:
        page = _asset("index.html").replace(b"@TOKEN@", self.token.encode())
        return web.Response(body=page, content_type="text/html", charset="utf-8",
                            headers={"Cache-Control": "no-store",
                                     "X-Frame-Options": "DENY"})  # fmt: skip

    async def _static(self, request: web.Request) -> web.StreamResponse:
        name = request.match_info["name"]
        types = {"js": "text/javascript", "css": "text/css"}
        ext = name.rsplit(".", 1)[-1]
        if name not in ("dashboard.js", "dashboard.css"):
            raise web.HTTPNotFound()
        return web.Response(body=_asset(name), content_type=types[ext], charset="utf-8")

    async def _api_state(self, request: web.Request) -> web.StreamResponse:
        return web.json_response(self.state.state())

    async def _api_series(self, request: web.Request) -> web.StreamResponse:
        return web.json_response(self.state.series_doc())

    async def _events(self, request: web.Request) -> web.StreamResponse:
        if len(self._clients) >= MAX_CLIENTS:
            raise web.HTTPServiceUnavailable(text="too many dashboard clients")
        resp = web.StreamResponse(headers={"Content-Type": "text/event-stream",
                                           "Cache-Control": "no-cache"})  # fmt: skip
        await resp.prepare(request)
        q: asyncio.Queue[bytes | None] = asyncio.Queue(maxsize=CLIENT_QUEUE)
        meta = json.dumps(self.state.meta(), separators=(",", ":"))
        series = json.dumps(self.state.series_doc(), separators=(",", ":"))
        defs = json.dumps(self.state.defs, separators=(",", ":"))
        rows = self.state.rows()
        if not self._clients:  # the first reader: the next delta starts from what it got
            self._field.sent = dict(rows)
        first = (f'{{"state":{meta},"field":{FieldStream.full(rows)},'
                 f'"definitions":{defs},"series":{series}}}')  # fmt: skip
        await resp.write(f"event: hello\ndata: {first}\n\n".encode())
        self._clients.add(q)
        try:
            while True:
                msg = await q.get()
                if msg is None:
                    break
                await resp.write(msg)
        except (ConnectionResetError, aiohttp.ClientConnectionResetError):
            pass
        finally:
            self._clients.discard(q)
        return resp

    async def _body(self, request: web.Request) -> bytes:
        try:
            async with asyncio.timeout(REQUEST_TIMEOUT_S):  # a body that trickles in
                raw = await request.read()
        except TimeoutError:
            raise web.HTTPRequestTimeout(text="request body too slow") from None
        if len(raw) > MAX_BODY:
            raise web.HTTPRequestEntityTooLarge(max_size=MAX_BODY, actual_size=len(raw))
        try:
            doc = json.loads(raw)
        except (UnicodeDecodeError, json.JSONDecodeError) as e:
            raise web.HTTPBadRequest(text=f"not JSON: {e}") from None
        if not isinstance(doc, dict):
            raise web.HTTPBadRequest(text="expected a JSON object")
        return json.dumps(doc).encode()

    async def _publish(self, rel: str, payload: bytes, retain: bool) -> web.StreamResponse:
        try:
            await self.feed.publish(rel, payload, retain)
        except (ConnectionError, aiomqtt.MqttError) as e:
            raise web.HTTPBadGateway(text=str(e)) from None
        return web.json_response({"topic": f"{self.feed.settings.prefix}/{rel}"}, status=202)

    async def _define(self, request: web.Request) -> web.StreamResponse:
        kind, ident = request.match_info["kind"], request.match_info["id"]
        if kind not in ("group", "channel"):
            raise web.HTTPNotFound(text=f"no definition kind {kind!r}: group or channel")
        if not ident.isdigit() or not 0 < int(ident) <= 0xFFFF:
            raise web.HTTPBadRequest(text=f"{kind} id must be an integer in 1..65535")
        payload = b"" if request.method == "DELETE" else await self._body(request)
        return await self._publish(f"def/{kind}/{int(ident)}", payload, retain=True)

    async def _command(self, request: web.Request) -> web.StreamResponse:
        name = request.match_info["name"]
        if not NAME_RE.match(name):
            raise web.HTTPBadRequest(text="command name: 1-32 letters, digits, '_', '-', '.'")
        return await self._publish(f"cmd/{name}", await self._body(request), retain=False)


def _offer(q: asyncio.Queue[bytes | None], msg: bytes | None, force: bool = False) -> bool:
    try:
        q.put_nowait(msg)
        return True
    except asyncio.QueueFull:
        if force:
            with contextlib.suppress(asyncio.QueueEmpty):
                q.get_nowait()
            q.put_nowait(msg)
        return False


def field_of(dots: Iterable[MoteDot], cores: Mapping[int, MoteCore]) -> list[FieldMote]:
    """The field from a view snapshot's dots plus the cores of the motes in this
    process: every mote's memberships (all group types) and collection parent."""
    out = []
    for d in dots:
        core = cores.get(d.node)
        groups: dict[int, tuple[int, bool]] | None = None
        parent = None
        if isinstance(core, AwareMote):
            groups = {t: (m.group_id, m.is_leader) for t, m in core.groups.memberships().items()}
            parent = core.collection.parent
        out.append(FieldMote(d.node, d.kind, d.x, d.y, d.alive, groups, parent, d.leds))
    return out


def deployment_field(dep: Deployment, now: float) -> list[FieldMote]:
    """The field of a deployment at emulated time ``now`` (positions by mobility)."""
    return [FieldMote(s.id, s.kind, *s.mobility().position(now), alive=s.boot_s <= now)
            for s in dep.nodes]  # fmt: skip


def _asset(name: str) -> bytes:
    return resources.files("awaremw.view").joinpath("static", name).read_bytes()


def wall_clock_estimate(state: DashboardState, speed: float) -> Callable[[], float]:
    """Emulated time for a view without cores: the latest stamp heard, advanced by
    the wall clock times ``speed`` since it was heard."""
    seen = {"t": state.heard_t, "wall": time.monotonic()}

    def now() -> float:
        if state.heard_t != seen["t"]:
            seen["t"], seen["wall"] = state.heard_t, time.monotonic()
        return seen["t"] + (time.monotonic() - seen["wall"]) * speed

    return now


def dashboard_for(
    dep: Deployment,
    world: World | None,
    mqtt_url: str,
    web: str,
    title: str,
    group_type: int | None = None,
    prefix: str = "aware",
    password: str | None = None,
) -> Dashboard:
    """A dashboard of a deployment, listening on ``web`` (HOST:PORT), reading and
    publishing through the broker at ``mqtt_url`` (its account's rights apply).
    Beyond loopback it needs ``password`` (default: ``$AWAREMW_WEB_PASSWORD``)."""
    host, port = parse_host_port(web)
    settings = MqttSettings.from_url(mqtt_url, client_id=f"awaremw-web-{id(dep):x}",
                                      prefix=prefix)  # fmt: skip
    state = DashboardState(dep.area, f"awaremw {title}", group_type, world)
    state.set_field(0.0, deployment_field(dep, 0.0))
    if password is None:
        password = os.environ.get(PASSWORD_ENV) or None
    return Dashboard(state, settings, host, port, password)


FLEET_POLL_S = 2.0  # wall seconds between position queries to the fleets (view --connect)


def fleet_positions(
    connect: list[str], prefix: str, config_file: str | None, timeout: float = 2.0
) -> tuple[float, dict[int, tuple[float, float]]]:
    """Ask every fleet (``<prefix>/ctl/fleet/*``, op ``list``) where its motes are;
    blocking (run it in a thread). Returns (their emulated time, positions)."""
    from awaremw.runtime.zenoh_session import SessionSettings, close_quietly, open_session

    session = open_session(SessionSettings("client", tuple(connect), connect_timeout_s=timeout,
                                           config_file=config_file))  # fmt: skip
    t = float("nan")
    out: dict[int, tuple[float, float]] = {}
    try:
        for reply in session.get(f"{prefix}/ctl/fleet/*", payload=b'{"op": "list"}',
                                 timeout=timeout, target=zenoh.QueryTarget.ALL):  # fmt: skip
            ok = reply.ok
            if ok is None:
                continue
            try:
                d = json.loads(ok.payload.to_bytes())
                for k, (x, y) in d.get("motes", {}).items():
                    out[int(k)] = (float(x), float(y))
                t = max(float(d.get("t", t)), t) if t == t else float(d.get("t", t))
            except (ValueError, TypeError, AttributeError) as e:
                log.info("dashboard: bad fleet list reply: %s", e)
    finally:
        close_quietly(session)
    return t, out


async def run_view(
    dash: Dashboard,
    dep: Deployment,
    *,
    speed: float = 1.0,
    duration: float | None = None,
    connect: list[str] | None = None,
    prefix: str = "aware",
    config_file: str | None = None,
    announce: bool = False,
) -> None:
    """Serve a dashboard of a system running elsewhere until ``duration`` wall
    seconds pass (None: until cancelled). Positions come from the fleets'
    control queryable when ``connect`` is given, else from the deployment's
    mobility at the emulated time the messages carry (advanced by ``speed``)."""
    kinds = {s.id: s.kind for s in dep.nodes}
    clock = wall_clock_estimate(dash.state, speed)
    stop_at = None if duration is None else time.monotonic() + duration
    positions: dict[int, tuple[float, float]] | None = None
    polled = 0.0
    async with dash:
        if announce:
            print(f"web dashboard: {dash.url} (MQTT {dash.feed.settings.url})", flush=True)
        while stop_at is None or time.monotonic() < stop_at:
            if connect and time.monotonic() - polled >= FLEET_POLL_S:
                polled = time.monotonic()
                try:
                    t, positions = await asyncio.to_thread(
                        fleet_positions, connect, prefix, config_file)  # fmt: skip
                    dash.state.fleet_time(t)
                except (zenoh.ZError, OSError) as e:  # the router is away: keep the last field
                    log.warning("dashboard: cannot ask the fleets on %s: %s", connect, e)
            now = clock()
            if positions:
                field = [FieldMote(i, kinds.get(i, "mote"), x, y) for i, (x, y) in
                         sorted(positions.items())]  # fmt: skip
            else:
                field = deployment_field(dep, now)
            dash.update_field(now, field)
            await asyncio.sleep(0.5)  # refresh period of the positions
