"""A fleet's control service: the Zenoh queryable ``<prefix>/ctl/fleet/<name>``
behind ``awaremw fleet-ctl add|kill|list|stats|items`` (see ``docs/runtime.md``).

Requests arrive on a Zenoh thread and are answered on the event loop; a bad
request gets an answer with ``ok: false``, never an exception.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
from collections.abc import Mapping
from typing import Any

import zenoh

from awaremw.protocol.frames import ItemKind
from awaremw.protocol.mote import AwareMote
from awaremw.radio.zenoh_medium import ZenohMedium
from awaremw.runtime.deployment import DeploymentError, NodeSpec, parse_deployment
from awaremw.runtime.fleet.motes import FleetMotes
from awaremw.runtime.fleet.stats import FleetStats

log = logging.getLogger(__name__)

MAX_CONTROL_BYTES = 64 * 1024  # a control request is a few hundred bytes
_KIND_NAMES = {
    ItemKind.GROUP_TYPE: "group",
    ItemKind.CHANNEL: "channel",
    ItemKind.COMMAND: "command",
}


class ControlService:
    """Answers control requests about ``motes`` (add, kill, list, stats).

    :meth:`request` works as soon as the motes are attached; :meth:`open`
    declares the queryable (a fleet with ``control=False`` never does).
    """

    def __init__(self, name: str, prefix: str, motes: FleetMotes, stats: FleetStats) -> None:
        self.name = name
        self.key = f"{prefix}/ctl/fleet/{name}"
        self.motes = motes
        self.stats = stats
        self._medium: ZenohMedium | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._queryable: zenoh.Queryable[None] | None = None
        self._closed = False
        self.restarts = 0  # times the launcher started this worker again (in stats)

    def bind(self, medium: ZenohMedium, loop: asyncio.AbstractEventLoop) -> None:
        """Where faults are counted (the medium's fault log) and requests answered."""
        self._medium = medium
        self._loop = loop

    def open(self, session: zenoh.Session) -> None:
        """Declare the queryable on ``session``."""
        self._queryable = session.declare_queryable(
            self.key, zenoh.handlers.Callback(self._on_query, indirect=False)
        )

    def close(self) -> None:
        self._closed = True
        if self._queryable is not None:
            with contextlib.suppress(zenoh.ZError):
                self._queryable.undeclare()  # type: ignore[no-untyped-call]
            self._queryable = None

    # ------------------------------------------------------------------ requests

    def request(self, payload: bytes) -> dict[str, Any]:
        """Handle one control request (JSON). Bad requests are answered, never raised.

        ``{"op": "add", "node": {<a [[nodes]] entry>}}``,
        ``{"op": "kill", "id": N}``, ``{"op": "list"}``, ``{"op": "stats"}``,
        ``{"op": "items"}`` (each mote's definitions: a read-back).
        Replies carry ``fleet``, ``ok``, ``done`` (this fleet acted) and
        ``error`` or data.
        """
        base: dict[str, Any] = {"fleet": self.name, "pid": os.getpid()}
        if len(payload) > MAX_CONTROL_BYTES:
            return {**base, "ok": False, "done": False, "error": "request too large"}
        try:
            req = json.loads(payload)
        except (UnicodeDecodeError, json.JSONDecodeError) as e:
            return {**base, "ok": False, "done": False, "error": f"not JSON: {e}"}
        except RecursionError:
            return {**base, "ok": False, "done": False, "error": "not JSON: nested too deeply"}
        if not isinstance(req, dict) or not isinstance(req.get("op"), str):
            return {**base, "ok": False, "done": False, "error": 'expected {"op": ...}'}
        match req["op"]:
            case "list":
                t = self.stats.clock.now()
                pos = self.motes.positions(t)
                motes = {str(i): [round(x, 3), round(y, 3)] for i, (x, y) in pos.items()}
                return {**base, "ok": True, "done": True, "t": t, "motes": motes}
            case "stats":
                snap = self.stats.snapshot().as_dict()
                snap["restarts"] = self.restarts
                snap["pid"] = os.getpid()
                if self._medium is not None:  # remote garbage dropped, bugs contained
                    snap["rejected"] = self._medium.rejected.as_dict()
                    snap["faults"] = self._medium.faults.as_dict()
                    guard = self._medium.guard  # secured radio: frames refused, by reason
                    snap["refused"] = None if guard is None else guard.refused.as_dict()
                return {**base, "ok": True, "done": True, "snapshot": snap}
            case "items":
                return {**base, "ok": True, "done": True, "t": self.stats.clock.now(),
                        "items": self._items()}  # fmt: skip
            case "kill":
                nid = req.get("id")
                if not isinstance(nid, int) or isinstance(nid, bool):
                    return {**base, "ok": False, "done": False, "error": "kill needs an integer id"}
                return {**base, "ok": True, "done": self.motes.kill(nid), "id": nid}
            case "add":
                return {**base, **self._add(req.get("node"))}
            case op:
                return {**base, "ok": False, "done": False, "error": f"unknown op {op!r}"}

    def _items(self) -> dict[str, dict[str, list[Any]]]:
        """What each middleware mote on the air holds: ``{"<id>": {"channel/3":
        [version, wire body or None (deleted)]}}`` (group types as ``group/<t>``,
        command slots as ``command/<slot>``)."""
        out: dict[str, dict[str, list[Any]]] = {}
        for nid, core in self.motes.cores.items():
            if not isinstance(core, AwareMote):
                continue
            out[str(nid)] = {
                f"{_KIND_NAMES[kind]}/{item_id}": [
                    item.version, None if item.body is None else item.body.to_wire()
                ]
                for (kind, item_id), item in sorted(core.dissemination.items.items())
            }  # fmt: skip
        return out

    def parse_node(self, entry: object) -> NodeSpec:
        """Validate one ``[[nodes]]``-style entry against the deployment's area and radio."""
        if not isinstance(entry, Mapping):
            raise DeploymentError("add: 'node' must be an object like a [[nodes]] entry")
        dep = self.motes.deployment
        doc = {
            "name": dep.name,
            "radio": dep.radio,
            "seed": dep.seed,
            "tx_power_dbm": dep.tx_power_dbm,
            "area": list(dep.area),
            "nodes": [dict(entry)],
        }
        return parse_deployment(doc, None, self.motes.kinds).nodes[0]

    def _add(self, entry: object) -> dict[str, Any]:
        try:
            spec = self.parse_node(entry)
        except DeploymentError as e:
            return {"ok": False, "done": False, "error": str(e)}
        # Deployment motes belong to the process that owns their original spec;
        # new ids go by position. So exactly one process of a launcher acts.
        original = next((s for s in self.motes.deployment.nodes if s.id == spec.id), None)
        if not self.motes.owns(original or spec):
            return {"ok": True, "done": False, "id": spec.id}
        try:
            self.motes.add(spec)
        except (ValueError, DeploymentError) as e:
            return {"ok": False, "done": False, "error": str(e), "id": spec.id}
        return {"ok": True, "done": True, "id": spec.id}

    # ------------------------------------------------------------------ Zenoh side

    def _count_fault(self, what: str, e: Exception) -> None:
        if self._medium is not None:
            self._medium.faults.count(f"{what}: {type(e).__name__}", str(e), e)
        else:
            log.exception("%s failed", what)

    def _on_query(self, query: zenoh.Query) -> None:
        try:
            self._on_query_unguarded(query)
        except Exception as e:  # last guard: never raise into Zenoh's thread
            self._count_fault("control query", e)

    def _on_query_unguarded(self, query: zenoh.Query) -> None:
        # Zenoh thread: copy the payload and hand the query to the loop.
        payload = query.payload.to_bytes() if query.payload is not None else b""
        loop = self._loop
        if loop is None or self._closed:
            query.drop()  # type: ignore[no-untyped-call]
            return
        try:
            loop.call_soon_threadsafe(self._answer, query, payload)
        except RuntimeError:  # loop closed
            query.drop()  # type: ignore[no-untyped-call]

    def _answer(self, query: zenoh.Query, payload: bytes) -> None:
        try:
            try:
                reply = self.request(payload)
            except Exception as e:  # last guard: our bug, answered and counted
                self._count_fault("control", e)
                reply = {"fleet": self.name, "ok": False, "done": False, "error": "internal error"}
            query.reply(self.key, json.dumps(reply).encode())
        except zenoh.ZError as e:  # the asker went away
            log.debug("control reply failed: %s", e)
        finally:
            query.drop()  # type: ignore[no-untyped-call]
