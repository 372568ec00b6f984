"""The Zenoh side of the gateway: the HBN API under ``<prefix>/hbn/**``.

Same contract as MQTT, on key expressions instead of topics (the table of
keys: docs/gateway.md, "Zenoh HBN API"): definitions and commands are put
under ``aware/hbn/def/`` and ``aware/hbn/cmd/``, records and group states are
put under ``aware/hbn/data/`` and ``aware/hbn/groups/``, refusals on
``aware/hbn/errors``, and a ``get`` on ``aware/hbn/**`` answers with the
current state (Zenoh's stand-in for retained messages). A payload larger than
``max_payload_bytes`` is not copied out of Zenoh at all; what arrives waits
for the loop in a bounded :class:`~awaremw.gateway.inbox.Inbox`, and what
does not fit is reported with code ``input_overflow``, never dropped silently.

zenoh-python calls back on its own threads: the subscriber copies key, kind
and payload out of the sample and hands them to the event loop with
``call_soon_threadsafe``; the queryable answers from an immutable snapshot
the loop replaces wholesale, so no asyncio or SQLite object is touched from a
Zenoh thread.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from types import MappingProxyType

import zenoh

from awaremw.gateway.bridge import RateLimitedLog
from awaremw.gateway.events import ErrorReport, Publish
from awaremw.gateway.inbox import (
    OVERFLOW,
    Inbox,
    Incoming,
    overflow_report,
)

log = logging.getLogger(__name__)

# (rel_topic, payload, retained, key, size): ``size`` is the payload's size as
# put; a payload over the limit arrives empty, to be refused by its size alone.
OnMessage = Callable[[str, bytes, bool, str, int], object]
MAX_REPORTS = 1_000  # refusals of the Zenoh threads waiting to be reported by the loop
HANDLE_SLICE_S = 0.02  # the loop handles the inbox in slices this long (wall seconds)


class HbnApi:
    """Subscriber, queryable and publications of the gateway on one Zenoh session.

    The session belongs to the caller (one session per process); :meth:`close`
    only undeclares what this object declared.
    """

    def __init__(
        self,
        session: zenoh.Session,
        on_message: OnMessage,
        *,
        prefix: str = "aware",
        loop: asyncio.AbstractEventLoop | None = None,
        max_payload_bytes: int = 4096,
        inbox: Inbox | None = None,
    ) -> None:
        self.session = session
        self.on_message = on_message
        self.base = f"{prefix}/hbn"
        self.loop = loop or asyncio.get_running_loop()
        self._snapshot: Mapping[str, bytes] = MappingProxyType({})
        self._decls: list[zenoh.Subscriber[None] | zenoh.Queryable[None]] = []
        self._inputs = (f"{self.base}/def/", f"{self.base}/cmd/")
        self.max_payload_bytes = max_payload_bytes
        self.received = 0  # samples handed to the gateway
        self.queries = 0
        # Written on Zenoh threads and read on the loop: guarded by _lock.
        self.inbox = inbox if inbox is not None else Inbox()  # (an empty one is falsy)
        # Its ``valid`` (if any) runs on Zenoh's threads, under the lock: it must be pure.
        self._refused: deque[Incoming] = deque()  # bounded by MAX_REPORTS
        self.unreported = 0  # refusals beyond MAX_REPORTS: counted, summed up in the log
        self._scheduled = False  # a drain is due on the loop
        self._lock = threading.Lock()
        self._overflow_log = RateLimitedLog(log)

    @property
    def dropped(self) -> int:
        """Samples the gateway could not take (the inbox was full); each reported."""
        return self.inbox.stats.dropped

    def key(self, rel: str) -> str:
        return f"{self.base}/{rel}"

    # ----------------------------------------------------------------- lifecycle

    def start(self) -> None:
        # One subscriber, so definitions and commands keep the order they were put
        # in (each callback subscriber has its own thread); our own publications
        # are not looped back.
        self._decls.append(
            self.session.declare_subscriber(
                self.key("**"), self._on_sample, allowed_origin=zenoh.Locality.REMOTE
            )
        )
        self._decls.append(self.session.declare_queryable(self.key("**"), self._on_query))
        log.info("Zenoh HBN API on %s/**", self.base)

    def close(self) -> None:
        decls, self._decls = self._decls, []
        for d in decls:
            try:
                d.undeclare()  # type: ignore[no-untyped-call]
            except zenoh.ZError as e:  # the session may already be closed
                log.debug("undeclare: %s", e)

    # ----------------------------------------------------------------- out

    def publish(self, p: Publish) -> None:
        key = self.key(p.topic)
        if p.retain and not p.payload:
            self.session.delete(key)
        else:
            self.session.put(key, p.payload)

    def publish_error(self, e: ErrorReport) -> None:
        self.session.put(self.key("errors"), e.to_json())

    def set_state(self, state: Mapping[str, bytes]) -> None:
        """Replace what the queryable answers (relative keys -> JSON payloads)."""
        self._snapshot = MappingProxyType(dict(state))

    # ----------------------------------------------------------------- in (Zenoh threads)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        if not key.startswith(self._inputs):
            return  # data, groups, errors: output of this or another gateway
        deleted = sample.kind == zenoh.SampleKind.DELETE
        size = 0 if deleted else len(sample.payload)
        # An oversize payload is not copied out of Zenoh: its size is enough to refuse it.
        payload = b"" if deleted or size > self.max_payload_bytes else sample.payload.to_bytes()
        item = Incoming(key[len(self.base) + 1 :], payload, key, False, size)
        with self._lock:
            refused = self.inbox.put(item)
            if refused is not None:
                if len(self._refused) < MAX_REPORTS:
                    self._refused.append(refused)
                else:
                    self.unreported += 1
            if self._scheduled:
                return
            self._scheduled = True
        # RuntimeError: the loop closed while Zenoh was still delivering.
        with contextlib.suppress(RuntimeError):
            self.loop.call_soon_threadsafe(self._drain)

    def _drain(self) -> None:
        """On the loop: report refusals, then hand the inbox to the gateway for one
        slice; call again soon if entries are left (Zenoh keeps delivering meanwhile)."""
        with self._lock:
            refused, self._refused = self._refused, deque()
            unreported, self.unreported = self.unreported, 0
        for r in refused:
            self._report_overflow(r)

        if unreported:
            # Beyond MAX_REPORTS waiting reports: one report says how many, not which.
            self._overflow_log.warning(
                "input_overflow_more", "Zenoh HBN input full: %d more samples not taken", unreported
            )
            summary = ErrorReport(
                f"{self.base}/**", OVERFLOW, f"{unreported} more samples not taken: inbox full", ""
            )
            with contextlib.suppress(zenoh.ZError):
                self.publish_error(summary)
        end = time.monotonic() + HANDLE_SLICE_S
        while True:
            with self._lock:
                m = self.inbox.pop()
                if m is None:
                    # Refusals made since this drain took them would wait for the
                    # next sample, which may never come: report them now.
                    if self._refused or self.unreported:
                        self.loop.call_soon(self._drain)
                    else:
                        self._scheduled = False
                    return
            self._deliver(m)
            if time.monotonic() >= end:
                self.loop.call_soon(self._drain)  # the rest in the next slice
                return

    def _report_overflow(self, m: Incoming) -> None:
        self._overflow_log.warning(
            "input_overflow", "Zenoh HBN input full: %s not taken (reported on %s/errors)",
            m.topic[:200], self.base,
        )  # fmt: skip
        try:
            self.publish_error(overflow_report(m, "the Zenoh HBN inbox", refetched=False))
        except zenoh.ZError as e:
            log.debug("overflow report: %s", e)

    def _deliver(self, m: Incoming) -> None:
        self.received += 1
        try:
            self.on_message(m.rel, m.payload, False, m.topic, m.size or 0)
        except Exception:  # a bug in the handler must not kill the subscription
            log.exception("handling %s failed", m.topic[:200])

    def _on_query(self, query: zenoh.Query) -> None:
        self.queries += 1
        asked = query.key_expr
        snapshot = self._snapshot  # one atomic read of the current state
        for rel, payload in snapshot.items():
            key = self.key(rel)
            try:
                if asked.intersects(zenoh.KeyExpr(key)):
                    query.reply(key, payload)
            except zenoh.ZError as e:
                log.debug("query reply on %s: %s", key, e)


def wait_for_gateway(session: zenoh.Session, prefix: str = "aware", timeout: float = 10.0) -> None:
    """Return once a gateway answers a ``get`` on ``<prefix>/hbn/gateway/status``
    through ``session``: the session is routed to the gateway, so the puts that
    follow reach it and the gets are answered. TimeoutError after ``timeout``.

    A client that opens a session and puts or gets at once may be faster than
    Zenoh's routing: its puts go nowhere and its gets find no answer
    (docs/gateway.md, "Zenoh HBN API")."""
    deadline = time.monotonic() + timeout
    key = f"{prefix}/hbn/gateway/status"
    while True:
        left = deadline - time.monotonic()
        if left <= 0:
            raise TimeoutError(f"no gateway answered on {key} within {timeout:g} s")
        if any(r.ok is not None for r in session.get(key, timeout=min(1.0, left))):
            return
        time.sleep(min(0.05, max(0.0, deadline - time.monotonic())))  # poll, not a sync
