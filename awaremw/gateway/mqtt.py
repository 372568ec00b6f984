"""The MQTT side of the gateway: aiomqtt, a reconnect loop and an outage buffer.

:class:`MqttBridge` keeps one connection to the broker alive with aiomqtt's
documented pattern (``async with client`` inside ``while True``, sleeping with
exponential backoff after an ``MqttError``). Outgoing messages never wait for
the broker: stream messages (data records, errors) go through a bounded FIFO
that keeps the newest while the broker is away and lets a message go only once
the broker acknowledged it; retained state (group states, gateway status and
stats) is kept as the latest value per topic and re-published on every
connect. docs/gateway.md, "Broker outages", says what is kept, dropped and
resent.

Incoming messages on ``<prefix>/def/#`` and ``<prefix>/cmd/#`` are taken off
the connection as fast as they come into an
:class:`~awaremw.gateway.inbox.Inbox` and handed to a callback from there, a
slice at a time, so that reading never waits for handling; after a burst of
definitions the bridge subscribes again, so that the broker's retained
definitions are applied even where it dropped some on the way
(docs/robustness.md, "Reconcile"). The gateway uses a persistent session so
that definitions and deletions sent while it was disconnected are queued by
the broker for it.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
import secrets
import ssl
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal
from urllib.parse import unquote, urlsplit

import aiomqtt
from paho.mqtt.packettypes import PacketTypes
from paho.mqtt.properties import Properties

from awaremw.gateway.bridge import RateLimitedLog
from awaremw.gateway.echoes import Echoes
from awaremw.gateway.events import Publish
from awaremw.gateway.inbox import MAX_COMMANDS, MAX_DEFINITIONS, Inbox, Incoming, overflow_report
from awaremw.security.redact import mask_url, redact

log = logging.getLogger(__name__)

ProtocolChoice = Literal["auto", "5", "3.1.1"]
OnMessage = Callable[[str, bytes, bool, str], object]  # (rel_topic, payload, retained, topic)

STATUS_TOPIC = "gateway/status"
STATS_TOPIC = "gateway/stats"
ERRORS_TOPIC = "errors"
HANDLE_SLICE_S = 0.02  # handling yields to the connection this often (wall seconds)
MAX_PASSWORD_BYTES = 65_535  # MQTT's binary data: a 16-bit length


class BadMqttUrl(ValueError):
    """An MQTT URL the gateway cannot use (a configuration error)."""


async def mqtt_problem(url: str, timeout: float = 5.0) -> str | None:
    """Connect to the broker of ``url`` once; None if it accepts, else why not (one
    line, the password masked): a verb's check before a long run relies on it."""
    s = MqttSettings.from_url(url)
    client = s.client(f"awaremw-probe-{secrets.token_hex(4)}", timeout=timeout)
    try:
        async with asyncio.timeout(timeout + 1.0), client:
            return None
    except TimeoutError:
        return f"MQTT broker {mask_url(url)} did not answer within {timeout:g} s"
    except aiomqtt.MqttError as e:
        reason = " ".join(str(e).split()) or type(e).__name__
        return f"cannot connect to the MQTT broker {mask_url(url)}: {redact(reason)}"


class BadPasswordFile(ValueError):
    """A password file that is missing, unreadable or empty (a configuration error)."""


def read_password_file(path: str | Path) -> str:
    """The password kept in the file ``path``: its text less one trailing newline
    (``\\n`` or ``\\r\\n``, as ``echo`` and editors leave); everything else is kept."""
    where = f"MQTT password file {path}"
    try:
        # bytes: no newline translation inside the password; bounded (not /dev/zero)
        with Path(path).open("rb") as f:
            data = f.read(MAX_PASSWORD_BYTES + 3)
    except FileNotFoundError:
        raise BadPasswordFile(f"{where}: not found") from None
    except OSError as e:
        raise BadPasswordFile(f"{where}: cannot read: {e.strerror or e}") from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        raise BadPasswordFile(f"{where}: not UTF-8 text") from None
    password = text.removesuffix("\r\n") if text.endswith("\r\n") else text.removesuffix("\n")
    if not password:
        raise BadPasswordFile(f"{where}: empty")
    if len(password.encode()) > MAX_PASSWORD_BYTES:
        raise BadPasswordFile(f"{where}: longer than MQTT's {MAX_PASSWORD_BYTES} bytes")
    return password


@dataclass(frozen=True, slots=True)
class MqttSettings:
    """Everything about the broker connection; all of it is configuration."""

    host: str = "127.0.0.1"
    port: int = 1883
    username: str | None = None
    password: str | None = None
    tls: bool = False
    ca_file: str | None = None
    tls_insecure: bool = False  # skip hostname verification (self-signed test brokers)
    client_id: str = "awaremw-gateway"
    prefix: str = "aware"
    protocol: ProtocolChoice = "auto"  # MQTT 5 where the broker has it, else 3.1.1
    keepalive: int = 30
    timeout_s: float = 5.0
    reconnect_min_s: float = 0.1
    reconnect_max_s: float = 5.0
    buffer_size: int = 10_000  # stream messages kept while the broker is away
    session_expiry_s: int = 86_400
    persistent_session: bool = True
    drain_timeout_s: float = 2.0  # on stop, how long to try to deliver the backlog
    max_inflight: int = 16  # stream messages awaiting their PUBACK at once
    stats_interval_s: float = 5.0  # gateway/stats at most this often (and on drops)
    max_incoming: int = MAX_COMMANDS  # commands waiting to be handled (refused and reported beyond)
    max_definitions: int = MAX_DEFINITIONS  # distinct definition topics waiting (newest value each)
    reconcile_burst: int = 32  # live definitions since the last reconcile that make a burst
    reconcile_quiet_s: float = 1.0  # after a burst, re-read the retained definitions this long
    # after the last live one
    max_packet_bytes: int = 65_536  # MQTT 5: the broker sends the gateway nothing larger

    @classmethod
    def from_url(cls, url: str, **overrides: object) -> MqttSettings:
        """``mqtt://[user:pass@]host[:port]`` or ``mqtts://...`` (port 1883 / 8883)."""
        try:
            u = urlsplit(url)
            port = u.port
        except ValueError as e:
            raise BadMqttUrl(f"bad MQTT URL {mask_url(url)!r}: {redact(str(e))}") from None
        if u.scheme not in ("mqtt", "mqtts"):
            raise BadMqttUrl(
                f"bad MQTT URL {mask_url(url)!r}: the scheme must be mqtt:// or mqtts://"
            )
        if not u.hostname:
            raise BadMqttUrl(f"bad MQTT URL {mask_url(url)!r}: no host")
        if u.path not in ("", "/") or u.query or u.fragment:
            raise BadMqttUrl(
                f"bad MQTT URL {mask_url(url)!r}: only mqtt[s]://[user:pass@]host:port"
            )
        tls = u.scheme == "mqtts"
        base = cls(
            host=u.hostname,
            port=port if port is not None else (8883 if tls else 1883),
            username=None if u.username is None else unquote(u.username),
            password=None if u.password is None else unquote(u.password),
            tls=tls,
        )
        return replace(base, **overrides)  # type: ignore[arg-type]

    def with_password_file(self, path: str | Path) -> MqttSettings:
        """These settings with the password of the URL's user read from ``path``
        (:func:`read_password_file`), which keeps it off the command line: the URL
        must name the user and hold no password."""
        if self.username is None:
            raise BadMqttUrl(
                f"a password file is for the user of the MQTT URL, and {self.url} names none: "
                "mqtt[s]://USER@HOST:PORT"
            )
        if self.password is not None:
            raise BadMqttUrl("a password in the MQTT URL and a password file do not combine")
        return replace(self, password=read_password_file(path))

    def ssl_context(self) -> ssl.SSLContext | None:
        """The TLS context of an ``mqtts://`` connection (None for ``mqtt://``)."""
        if not self.tls:
            return None
        ctx = ssl.create_default_context(cafile=self.ca_file)
        if self.tls_insecure:
            ctx.check_hostname = False
            ctx.verify_mode = ssl.CERT_NONE
        return ctx

    def client(self, identifier: str, **options: Any) -> AckedClient:
        """An aiomqtt client of this broker with this account and TLS; MQTT 3.1.1
        (every broker speaks it) unless ``options`` name another ``protocol``."""
        options.setdefault("protocol", aiomqtt.ProtocolVersion.V311)
        return AckedClient(
            self.host,
            self.port,
            username=self.username,
            password=self.password,
            identifier=identifier,
            tls_context=self.ssl_context(),
            tls_insecure=self.tls_insecure if self.tls else None,
            **options,
        )

    @property
    def url(self) -> str:
        """The URL without the password (for logs)."""
        user = f"{self.username}@" if self.username else ""
        return f"{'mqtts' if self.tls else 'mqtt'}://{user}{self.host}:{self.port}"

    def topic(self, rel: str) -> str:
        return f"{self.prefix}/{rel}"


@dataclass(slots=True)
class MqttStats:
    connects: int = 0
    connect_failures: int = 0
    disconnects: int = 0
    published: int = 0  # stream messages acknowledged by the broker
    dropped: int = 0  # stream messages dropped because the buffer was full
    resent: int = 0  # in flight when the connection broke: sent again
    received: int = 0
    ignored: int = 0  # messages on topics the gateway did not subscribe to
    echoes: int = 0  # its own republished definitions heard back: not handled again
    reconciles: int = 0  # times the retained definitions were read again after a burst
    protocol: str = ""

    def as_dict(self) -> dict[str, int | str]:
        return {k: getattr(self, k) for k in self.__slots__}


@dataclass(slots=True)
class _Item:
    topic: str  # full topic
    payload: bytes
    qos: int
    enqueued: float = field(default_factory=time.monotonic)


async def speaks_mqtt5(s: MqttSettings) -> bool:
    """Whether the broker of ``s`` speaks MQTT 5 (OSError / TimeoutError: unreachable).

    Sends a bare MQTT 5 CONNECT (no credentials, no properties: some 3.1.1
    brokers, amqtt among them, hang on CONNECT properties) under a probe
    client id, so no real session is touched, and reads the CONNACK: a 3.1.1
    broker answers "unacceptable protocol version" (code 1) or just closes;
    any MQTT 5 reason code, even "not authorized", means the broker speaks 5.
    """
    cid = f"{s.client_id}-probe-{secrets.token_hex(3)}".encode()
    var = b"\x00\x04MQTT\x05\x02\x00\x0a\x00"  # name, level 5, clean start, keepalive, props
    body = var + len(cid).to_bytes(2, "big") + cid
    packet = bytes([0x10, len(body)]) + body  # len(body) < 128: one-byte length
    async with asyncio.timeout(s.timeout_s):
        reader, writer = await asyncio.open_connection(
            s.host, s.port, ssl=s.ssl_context(), server_hostname=s.host if s.tls else None
        )
        try:
            writer.write(packet)
            await writer.drain()
            head = await reader.read(4)
            if len(head) >= 4 and head[0] == 0x20 and head[3] not in (0x01, 0x84):
                writer.write(b"\xe0\x00")  # DISCONNECT
                await writer.drain()
                return True
            return False
        finally:
            writer.close()
            with contextlib.suppress(OSError):
                await writer.wait_closed()


class AckedClient(aiomqtt.Client):
    """aiomqtt's client, keeping the reason codes of the PUBACKs that refused a
    publish (MQTT 5: "Not authorized", "Quota exceeded", ...). aiomqtt 2.5 hands
    paho's reason code to its ``_on_publish`` and drops it; this override is the
    one place that reads it, bounded to the last ``MAX_REFUSALS``."""

    MAX_REFUSALS = 16

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.refusals: deque[str] = deque(maxlen=self.MAX_REFUSALS)

    def _on_publish(
        self, client: Any, userdata: Any, mid: int, reason_code: Any, properties: Any
    ) -> None:
        if getattr(reason_code, "is_failure", False):
            self.refusals.append(str(reason_code))
        super()._on_publish(client, userdata, mid, reason_code, properties)


class MqttBridge:
    """One resilient MQTT connection for the gateway."""

    def __init__(
        self,
        settings: MqttSettings,
        on_message: OnMessage,
        valid: Callable[[Incoming], bool] | None = None,
        is_copy: Callable[[Incoming], bool] | None = None,
    ) -> None:
        self.settings = settings
        self.on_message = on_message
        self.stats = MqttStats()
        self.connected = asyncio.Event()
        self.subscribed = asyncio.Event()  # set while connected and subscribed (ready)
        self.disconnected = asyncio.Event()  # set whenever not connected
        self.disconnected.set()
        self.changed = asyncio.Event()  # set at every connect, failed attempt and disconnect
        self._fifo: deque[_Item] = deque()
        self._retained: dict[str, bytes] = {}  # full topic -> latest payload
        # Definitions it sent and has not heard back yet: heard back live, each is
        # its own echo, never to take the place of a client's (monotonic clock).
        self._echoes = Echoes()
        self._dirty: dict[str, bytes] = {}  # retained topics still to (re)publish
        self._wakeup = asyncio.Event()
        self._stop = asyncio.Event()
        self._protocol: aiomqtt.ProtocolVersion | None = {
            "5": aiomqtt.ProtocolVersion.V5,
            "3.1.1": aiomqtt.ProtocolVersion.V311,
            "auto": None,
        }[settings.protocol]
        self._reported_dropped = 0
        self._last_error = ""
        # ``valid``: an invalid definition is not coalesced away (it is refused in its turn).
        self.inbox = Inbox(settings.max_definitions, settings.max_incoming, valid, is_copy)
        self._inbox_ready = asyncio.Event()
        self._burst = asyncio.Event()  # a reconcile is due once definitions go quiet
        self._live_defs = 0  # live definitions since the last reconcile
        self._last_def = -math.inf  # monotonic time of the last live definition
        self._overflow_log = RateLimitedLog(log)
        self._def_prefix = settings.topic("def/")
        self._cmd_prefix = settings.topic("cmd/")

    # ----------------------------------------------------------------- producer side

    def publish(self, p: Publish) -> None:
        """Queue ``p`` (topic relative to the prefix); never blocks."""
        topic = self.settings.topic(p.topic)
        if p.retain:
            if p.payload:
                self._retained[topic] = p.payload
            else:
                self._retained.pop(topic, None)
            self._dirty[topic] = p.payload
        else:
            if len(self._fifo) >= self.settings.buffer_size:
                self._fifo.popleft()
                self.stats.dropped += 1
            self._fifo.append(_Item(topic, p.payload, p.qos))
        self._wakeup.set()

    @property
    def backlog(self) -> int:
        """Stream messages not yet acknowledged by the broker."""
        return len(self._fifo)

    def stats_json(self) -> bytes:
        return json.dumps(
            {
                **self.stats.as_dict(),
                "buffered": len(self._fifo),
                "buffer_size": self.settings.buffer_size,
                "inbox": self.inbox.stats.as_dict(),
            }
        ).encode()

    # ----------------------------------------------------------------- connection loop

    def stop(self) -> None:
        """Ask :meth:`run` to deliver what it can, say ``offline`` and return."""
        self._stop.set()

    async def run(self) -> None:
        """Connect, serve, reconnect with backoff until :meth:`stop`."""
        s = self.settings
        backoff = s.reconnect_min_s
        while not self._stop.is_set():
            try:
                protocol = self._protocol or await self._probe()
                client = self._client(protocol)
                async with client:
                    self._on_connected(protocol)
                    backoff = s.reconnect_min_s
                    await self._serve(client)
                    return  # stopped cleanly
            except aiomqtt.MqttError as e:
                self._note_failure(e)
            finally:
                self.subscribed.clear()
                if self.connected.is_set():
                    self.connected.clear()
                    self.disconnected.set()
                    self.stats.disconnects += 1
                    self.changed.set()
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._stop.wait(), backoff)
            backoff = min(backoff * 2, s.reconnect_max_s)

    def _client(self, protocol: aiomqtt.ProtocolVersion) -> aiomqtt.Client:
        s = self.settings
        will = aiomqtt.Will(s.topic(STATUS_TOPIC), b"offline", qos=1, retain=True)
        kwargs: dict[str, object] = {}
        if protocol is aiomqtt.ProtocolVersion.V5:
            props = Properties(PacketTypes.CONNECT)  # type: ignore[no-untyped-call]
            props.SessionExpiryInterval = s.session_expiry_s if s.persistent_session else 0
            props.MaximumPacketSize = s.max_packet_bytes
            kwargs["properties"] = props
            kwargs["clean_start"] = not s.persistent_session
        else:
            kwargs["clean_session"] = not s.persistent_session
        client = s.client(
            s.client_id,
            protocol=protocol,
            will=will,
            keepalive=s.keepalive,
            timeout=s.timeout_s,
            queue_type=_take_all(self._take),
            **kwargs,
        )
        # aiomqtt warns above 10 pending calls; our in-flight window is the bound.
        client.pending_calls_threshold = s.max_inflight + 4
        return client

    async def _probe(self) -> aiomqtt.ProtocolVersion:
        """With ``protocol="auto"``: does the broker speak MQTT 5?"""
        try:
            five = await speaks_mqtt5(self.settings)
        except (OSError, TimeoutError) as e:
            raise aiomqtt.MqttError(f"cannot reach the broker: {e}") from None
        if five:
            return aiomqtt.ProtocolVersion.V5
        log.info("broker %s does not speak MQTT 5; using MQTT 3.1.1", self.settings.url)
        return aiomqtt.ProtocolVersion.V311

    def _on_connected(self, protocol: aiomqtt.ProtocolVersion) -> None:
        if self._protocol is None:
            self._protocol = protocol
        self.stats.connects += 1
        self._echoes.connected(time.monotonic())
        self.stats.protocol = "5" if protocol is aiomqtt.ProtocolVersion.V5 else "3.1.1"
        self.connected.set()
        self.disconnected.clear()
        self.changed.set()
        log.info("connected to %s (MQTT %s)", self.settings.url, self.stats.protocol)
        self._last_error = ""
        # The broker may have lost its retained messages: publish them all again.
        self._dirty = {**{t: p for t, p in self._retained.items()}, **self._dirty}

    def _note_failure(self, e: Exception) -> None:
        self.stats.connect_failures += 1
        self.changed.set()
        msg = str(e)
        if msg != self._last_error:  # do not flood the log while the broker is away
            log.warning("MQTT %s: %s; reconnecting", self.settings.url, msg)
            self._last_error = msg

    async def _serve(self, client: aiomqtt.Client) -> None:
        s = self.settings
        await client.subscribe([(s.topic("def/#"), 1), (s.topic("cmd/#"), 1)])
        # Online once subscribed: a definition published after "online" is heard live.
        await client.publish(s.topic(STATUS_TOPIC), b"online", qos=1, retain=True)
        self.subscribed.set()
        self._wakeup.set()
        handler = asyncio.create_task(self._handler())
        sender = asyncio.create_task(self._sender(client))
        reconciler = asyncio.create_task(self._reconciler(client))
        watcher = asyncio.create_task(_until_disconnected(client))
        stopper = asyncio.create_task(self._stop.wait())
        tasks = {handler, sender, reconciler, watcher, stopper}
        try:
            done, _ = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
        for t in done:
            if t is not stopper and (exc := t.exception()) is not None:
                raise exc
        # Stopping: deliver the backlog if the broker lets us, then say goodbye.
        with contextlib.suppress(TimeoutError, aiomqtt.MqttError):
            async with asyncio.timeout(s.drain_timeout_s):
                await self._flush(client)
        with contextlib.suppress(aiomqtt.MqttError):
            await client.publish(s.topic(STATS_TOPIC), self.stats_json(), qos=1, retain=True)
            await client.publish(s.topic(STATUS_TOPIC), b"offline", qos=1, retain=True)

    def _take(self, m: aiomqtt.Message) -> None:
        """Every message the connection delivers (on the loop, from aiomqtt's reader):
        into the inbox, never discarded silently."""
        topic = m.topic.value
        s = self.settings
        if not topic.startswith((self._def_prefix, self._cmd_prefix)):
            # Not ours: amqtt 0.12 sends a connecting client the retained
            # messages of every subscription in the broker (e.g. a viewer's
            # aware/groups/#), not only of its own.
            self.stats.ignored += 1
            return
        payload = m.payload if isinstance(m.payload, bytes) else str(m.payload or "").encode()
        if not m.retain and self._echoes.heard(topic, payload, time.monotonic()):
            # Its own republication heard back live: the broker got our newer ones
            # after it, in order. Taken in, it could replace a client's definition
            # that came meanwhile (the inbox keeps the newest per topic), or, as a
            # clearing (empty), delete what a client defined since.
            self.stats.echoes += 1
            return
        self.stats.received += 1
        item = Incoming(topic[len(s.prefix) + 1 :], payload, topic, bool(m.retain))
        if item.is_definition and not item.retained:
            self._live_defs += 1
            self._last_def = time.monotonic()
            if self._live_defs >= s.reconcile_burst:
                self._burst.set()
        refused = self.inbox.put(item)
        if refused is not None:
            self._overflow_log.warning(
                "input_overflow", "MQTT input full: %s not taken (reported on %s)",
                topic[:200], s.topic(ERRORS_TOPIC),
            )  # fmt: skip
            report = overflow_report(refused, "the MQTT inbox", refetched=True)
            self.publish(Publish(ERRORS_TOPIC, report.to_json()))
            if refused.is_definition:
                self._burst.set()  # the broker still retains it: read it again
        self._inbox_ready.set()

    async def _handler(self) -> None:
        """Hand the inbox to the gateway, a slice at a time (the connection keeps
        being read in between, and coalesces what comes meanwhile)."""
        while True:
            await self._inbox_ready.wait()
            await self._let_read()  # what is on the way coalesces before it is handled
            self._inbox_ready.clear()
            slice_end = time.monotonic() + HANDLE_SLICE_S
            while (m := self.inbox.pop()) is not None:
                try:
                    self.on_message(m.rel, m.payload, m.retained, m.topic)
                except Exception:  # a bug in the handler must not take the connection down
                    log.exception("handling %s failed", m.topic[:200])
                if time.monotonic() >= slice_end:
                    await self._let_read()
                    slice_end = time.monotonic() + HANDLE_SLICE_S

    async def _let_read(self) -> None:
        """Give the loop to the connection's reader while it takes messages (up to a
        slice): paho reads one packet per readable event, so a single yield would let
        one message in per slice, and the backlog would wait in the broker (which
        bounds it) instead of coalescing here."""
        end = time.monotonic() + HANDLE_SLICE_S
        while True:
            before = self.stats.received + self.stats.ignored
            for _ in range(2):  # the reader runs in the loop iteration after ours
                await asyncio.sleep(0)
            if self.stats.received + self.stats.ignored == before or time.monotonic() >= end:
                return

    async def _reconciler(self, client: aiomqtt.Client) -> None:
        """After a burst of definitions, once they went quiet: subscribe again, so the
        broker sends every retained definition once more (MQTT 3.1.1 and 5 both re-send
        the retained messages of a repeated subscription)."""
        s = self.settings
        while True:
            await self._burst.wait()
            while (left := self._last_def + s.reconcile_quiet_s - time.monotonic()) > 0:
                await asyncio.sleep(left)
            self._burst.clear()
            self._live_defs = 0
            await client.subscribe(s.topic("def/#"), qos=1)
            self.stats.reconciles += 1
            log.info("re-read the retained definitions after a burst")

    async def _sender(self, client: aiomqtt.Client) -> None:
        last_stats = -math.inf  # publish the stats at once after (re)connecting
        while True:
            await self._wakeup.wait()
            self._wakeup.clear()
            await self._flush(client)
            dropped = self.stats.dropped != self._reported_dropped
            if dropped:
                n = self.stats.dropped - self._reported_dropped
                self._reported_dropped = self.stats.dropped
                log.warning(
                    "%d messages dropped while the broker was away (buffer bound %d)",
                    n,
                    self.settings.buffer_size,
                )
            now = time.monotonic()
            if dropped or now - last_stats >= self.settings.stats_interval_s:
                last_stats = now
                await _publish(
                    client, self.settings.topic(STATS_TOPIC), self.stats_json(), qos=0, retain=True
                )

    async def _flush(self, client: aiomqtt.Client) -> None:
        """Publish dirty retained topics, then the FIFO in order, until both are empty.

        Up to ``max_inflight`` stream messages are in flight at once (paho sends
        them in order on the one connection); a message leaves the buffer when
        the broker acknowledged it and every older one. If the connection
        breaks, the unacknowledged ones go back to the head of the buffer, in
        order, to be sent first on the next connection.
        """
        inflight: deque[tuple[_Item, asyncio.Task[None]]] = deque()
        try:
            while self._dirty or self._fifo or inflight:
                if self._dirty and not inflight:
                    topic = next(iter(self._dirty))
                    payload = self._dirty.pop(topic)
                    if topic.startswith(self._def_prefix):  # back before the PUBACK, maybe
                        self._echoes.sent(topic, payload, time.monotonic())
                    try:
                        await _publish(client, topic, payload, qos=1, retain=True)
                    except BaseException:
                        self._dirty.setdefault(topic, payload)  # unless a newer value arrived
                        raise
                    continue
                while self._fifo and len(inflight) < self.settings.max_inflight:
                    item = self._fifo.popleft()
                    task = asyncio.ensure_future(
                        client.publish(item.topic, item.payload, qos=item.qos)
                    )
                    inflight.append((item, task))
                if inflight:
                    await _settled(inflight[0][1])
                    inflight.popleft()
                    self.stats.published += 1
        finally:
            self._requeue(inflight)

    def _requeue(self, inflight: deque[tuple[_Item, asyncio.Task[None]]]) -> None:
        for item, task in reversed(inflight):
            if task.done() and not task.cancelled() and task.exception() is None:
                self.stats.published += 1  # acknowledged: delivered, never again
                continue
            never_sent = (
                task.done()
                and not task.cancelled()
                and isinstance(task.exception(), aiomqtt.MqttCodeError)  # refused locally
            )
            task.cancel()
            self._fifo.appendleft(item)
            if not never_sent:
                # The broker may have had it before the break: the only case in
                # which a message can arrive twice. Counted.
                self.stats.resent += 1


def _take_all(take: Callable[[aiomqtt.Message], None]) -> type[asyncio.Queue[aiomqtt.Message]]:
    """aiomqtt's incoming queue class for one bridge: every message goes to ``take``
    at once (aiomqtt's own queue discards when full). The bridge never reads the
    queue (``client.messages``): it reads its inbox."""

    class TakeAll(asyncio.Queue[aiomqtt.Message]):
        def put_nowait(self, item: aiomqtt.Message) -> None:
            take(item)

    return TakeAll


async def _until_disconnected(client: aiomqtt.Client) -> None:
    """Raise :class:`aiomqtt.MqttError` when the connection breaks. aiomqtt's message
    iterator does so; it yields nothing here (every message went to the inbox)."""
    async for _ in client.messages:
        pass


async def _settled(task: asyncio.Task[None]) -> None:
    """Wait for ``task`` and return or raise its outcome.

    Unlike ``await task``, cancelling the waiter always raises here: Python
    3.11's ``asyncio.wait_for`` (inside aiomqtt's publish) swallows a
    cancellation that races with the completion of what it waits for, which
    would leave a cancelled sender running on a dead connection.
    """
    await asyncio.wait({task})
    task.result()


async def _publish(
    client: aiomqtt.Client, topic: str, payload: bytes, *, qos: int, retain: bool = False
) -> None:
    task = asyncio.ensure_future(client.publish(topic, payload, qos=qos, retain=retain))
    try:
        await _settled(task)
    except asyncio.CancelledError:
        task.cancel()
        raise
