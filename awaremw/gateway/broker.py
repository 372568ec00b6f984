"""Embedded MQTT broker (amqtt 0.12): nothing to install or run, and safe by default.

When the gateway gets no ``--mqtt`` URL it starts this in-process broker. What
it does beyond plain amqtt, each point described in docs/robustness.md,
"Embedded MQTT broker":

* **an account by default** (user ``awaremw``, a generated password kept in
  the state directory; anonymous clients refused unless ``anonymous=True``);
* **a fixed port** (the one used last time, else 1883 when free, else a free
  one: :attr:`EmbeddedBroker.moved_from`; an explicit busy port is
  :class:`BrokerPortInUse`);
* **limits** on packet size and on the retained store, every refusal counted
  in :attr:`EmbeddedBroker.stats`;
* **offline sessions expire** (``BrokerLimits.session_expiry_s``): amqtt has
  no bound on the queue of a persistent client that is away;
* **MQTT's retained-message rules, as Mosquitto keeps them**, where amqtt
  0.12.1 breaks them (MQTT 3.1.1 3.3.1-6 and 3.3.1-9; docs/gateway.md "The
  embedded broker's amqtt patch");
* **retained messages survive a restart** (``retained.sqlite``, restored
  before the listener opens).

amqtt speaks MQTT 3.1.1 only (the gateway falls back to it).
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import fcntl
import json
import logging
import os
import secrets
import socket
import sqlite3
import tempfile
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar
from urllib.parse import quote

from amqtt.adapters import ReaderAdapter, StreamReaderAdapter, StreamWriterAdapter
from amqtt.broker import Broker, RetainedApplicationMessage
from amqtt.contexts import Action
from amqtt.events import BrokerEvents

from awaremw.security.redact import mask_url

log = logging.getLogger(__name__)

DEFAULT_PORT = 1883
DEFAULT_USER = "awaremw"
MAX_MESSAGE_BYTES = 65_536  # one MQTT packet; the gateway's payloads are <= 4 KiB
MAX_RETAINED = 10_000  # retained topics
MAX_RETAINED_BYTES = 16 * 1024 * 1024  # sum of retained payloads
SESSION_EXPIRY_S = 3600  # a persistent client away longer loses its session and queue
ACCOUNT_FILE = "mqtt-account"  # user:password, 0600
PASSWD_FILE = "mqtt.passwd"  # user:argon2-hash, 0600 (amqtt FileAuthPlugin)
PORT_FILE = "broker.json"
RETAINED_FILE = "retained.sqlite"
LOCK_FILE = "broker.lock"
REFUSAL_LOG_INTERVAL_S = 10.0
_REFUSED = 0x80  # SUBACK return code of a refused filter


class BrokerError(RuntimeError):
    """The embedded broker cannot start as asked (a local configuration error)."""


class BrokerPortInUse(BrokerError):
    pass


class BrokerStateInUse(BrokerError):
    pass


def account_for_port(port: int, root: Path | None = None) -> tuple[str, str] | None:
    """``(user, password)`` of the embedded broker a gateway of this machine keeps on
    ``port`` (its state under ``root``, default :func:`state.state_root`), or None.
    For clients on this machine (no password to copy by hand)."""
    from awaremw.gateway.state import BROKER_DIR, DEPLOYMENTS, state_root

    base = (root or state_root()) / DEPLOYMENTS
    for saved in sorted(base.glob(f"*/{BROKER_DIR}/{PORT_FILE}")):
        with contextlib.suppress(OSError, ValueError, KeyError, TypeError):
            if int(json.loads(saved.read_text())["port"]) != port:
                continue
            user, sep, password = (saved.parent / ACCOUNT_FILE).read_text().strip().partition(":")
            if sep and user and password:
                return user, password
    return None


class _NoDataFilter(logging.Filter):
    """Drops amqtt's "No data from (client ...)" (logged at ERROR for every
    connection that closes before a CONNECT: a port probe, a client that gave up):
    a connection's noise, not an error of the broker."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not record.getMessage().startswith("No data from")


def quiet_connections(logger: logging.Logger) -> None:
    """Install :class:`_NoDataFilter` on ``logger`` once."""
    if not any(isinstance(f, _NoDataFilter) for f in logger.filters):
        logger.addFilter(_NoDataFilter())


@dataclass(frozen=True, slots=True)
class BrokerLimits:
    """What the embedded broker holds at most (module docstring, docs/robustness.md)."""

    max_message_bytes: int = MAX_MESSAGE_BYTES  # one packet
    max_retained: int = MAX_RETAINED  # retained topics
    max_retained_bytes: int = MAX_RETAINED_BYTES  # their payloads
    session_expiry_s: int = SESSION_EXPIRY_S  # how long an away client's session is kept

    def __post_init__(self) -> None:
        if self.max_message_bytes < 1024:
            raise ValueError("broker limits: max_message_bytes >= 1024")
        if min(self.max_retained, self.max_retained_bytes, self.session_expiry_s) < 1:
            raise ValueError(
                "broker limits: max_retained, max_retained_bytes and session_expiry_s >= 1"
            )


@dataclass(slots=True)
class BrokerStats:
    oversize: int = 0  # packets refused by size (the client was disconnected)
    retained_refused: int = 0  # retained messages not retained (store full)
    retained: int = 0  # topics retained now
    retained_bytes: int = 0  # their payload bytes
    write_failures: int = 0  # writes to retained.sqlite that failed (kept in memory, retried)
    pending_writes: int = 0  # retained topics whose change the file does not hold yet

    def as_dict(self) -> dict[str, int]:
        return {k: getattr(self, k) for k in self.__slots__}


class MessageTooLarge(Exception):
    """A client sent a packet over the limit; amqtt's reader loop ends the connection."""


class _LimitedReader(StreamReaderAdapter):  # type: ignore[misc]
    """Refuses a read (a packet body) over the limit before a byte of it is buffered."""

    def __init__(self, reader: asyncio.StreamReader, owner: _LimitedBroker) -> None:
        super().__init__(reader)
        self._owner = owner

    async def read(self, n: int = -1) -> bytes:
        if n > self._owner.max_message_bytes:
            self._owner.note_oversize(n)
            raise MessageTooLarge(f"{n} bytes over the limit of {self._owner.max_message_bytes}")
        data: bytes = await super().read(n)
        return data


class _LimitedBroker(Broker):  # type: ignore[misc]
    """amqtt's broker with a packet size limit, a bounded and persistent retained store."""

    _sql: ClassVar[str] = (
        "CREATE TABLE IF NOT EXISTS retained (topic TEXT PRIMARY KEY, data BLOB, qos INTEGER)"
    )

    def __init__(
        self,
        config: dict[str, Any],
        *,
        max_message_bytes: int,
        max_retained: int,
        max_retained_bytes: int,
        db_path: Path | None,
        stats: BrokerStats,
    ) -> None:
        super().__init__(config)
        self.max_message_bytes = max_message_bytes
        self.max_retained = max_retained
        self.max_retained_bytes = max_retained_bytes
        self.stats = stats
        self._db: sqlite3.Connection | None = None
        self._db_path = db_path
        # Retained topics changed in memory but not in the file (a write failed);
        # beyond 2 * max_retained the whole table is rewritten instead.
        self._dirty: set[str] = set()
        self._dirty_all = False
        self.on_write_error: Callable[[str], None] | None = None
        if db_path is not None:
            try:
                self._db = sqlite3.connect(str(db_path))
                os.chmod(db_path, 0o600)
                self._db.execute("PRAGMA journal_mode=WAL")
                self._db.execute(self._sql)
                self._db.commit()
            except (sqlite3.Error, OSError) as e:
                self.close_store()
                raise BrokerError(f"cannot open the retained store {db_path}: {e}") from None
        self._last_log = -REFUSAL_LOG_INTERVAL_S
        self._last_write_log = -REFUSAL_LOG_INTERVAL_S

    def _rate_limited(self, msg: str, *args: object) -> None:
        now = time.monotonic()
        if now - self._last_log >= REFUSAL_LOG_INTERVAL_S:
            self._last_log = now
            log.warning(msg, *args)

    def note_oversize(self, n: int) -> None:
        self.stats.oversize += 1
        self._rate_limited(
            "embedded broker: refused a %d-byte MQTT packet (limit %d); %d so far",
            n, self.max_message_bytes, self.stats.oversize,
        )  # fmt: skip

    async def stream_connected(
        self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, listener_name: str
    ) -> None:
        limited: ReaderAdapter = _LimitedReader(reader, self)
        await self._client_connected(listener_name, limited, StreamWriterAdapter(writer))

    # ----------------------------------------------------------------- retained delivery
    # amqtt 0.12.1 calls _publish_retained_messages_for_subscription from two
    # places: after a SUBSCRIBE (right) and on every CONNECT for every filter in
    # the broker, whoever holds it (wrong: MQTT sends retained messages only for
    # a new subscription). The hook is silenced and SUBSCRIBE does its own.

    async def _publish_retained_messages_for_subscription(
        self, subscription: tuple[str, int], session: Any
    ) -> None:
        return None

    async def _handle_subscription(
        self, client_session: Any, handler: Any, subscribe_waiter: asyncio.Future[Any]
    ) -> None:
        subscriptions = subscribe_waiter.result()
        codes = [await self.add_subscription(s, client_session) for s in subscriptions.topics]
        await handler.mqtt_acknowledge_subscription(subscriptions.packet_id, codes)
        for (topic_filter, _), code in zip(subscriptions.topics, codes, strict=True):
            if code == _REFUSED:
                continue
            await self.plugins_manager.fire_event(
                BrokerEvents.CLIENT_SUBSCRIBED,
                client_id=client_session.client_id,
                topic=topic_filter,
                qos=code,
            )
            await self._send_retained(topic_filter, code, client_session, handler)

    async def _send_retained(self, topic_filter: str, qos: int, session: Any, handler: Any) -> None:
        """The retained messages ``topic_filter`` matches, once each, retain flag set."""
        sends = []
        for topic, msg in list(self._retained_messages.items()):
            if not self._matches(topic, topic_filter):
                continue
            if not await self._topic_filtering(session, topic, Action.RECEIVE):
                continue  # amqtt forgets this check for retained messages too
            sends.append(
                asyncio.ensure_future(
                    handler.mqtt_publish(topic, msg.data, min(qos, msg.qos or 0), retain=True)
                )
            )
        if sends:
            await asyncio.wait(sends)

    async def _publish_session_retained_messages(self, session: Any) -> None:
        """What an away persistent session missed: live messages, so retain 0
        (amqtt 0.12.1 sets it, and the gateway would take them for replays)."""
        handler = self._get_handler(session)
        sends = []
        if handler is not None:
            while not session.retained_messages.empty():
                msg = session.retained_messages.get_nowait()
                sends.append(
                    asyncio.ensure_future(
                        handler.mqtt_publish(msg.topic, msg.data, msg.qos, retain=False)
                    )
                )
        if sends:
            await asyncio.wait(sends)

    async def _start_listeners(self) -> None:
        # start() has just cleared the retained store: put back the persisted one
        # before any client can connect.
        if self._db is not None:
            rows = self._db.execute("SELECT topic, data, qos FROM retained").fetchall()
            for topic, data, qos in rows[: self.max_retained]:
                self._retained_messages[topic] = RetainedApplicationMessage(
                    None, topic, bytes(data), qos
                )
            self._recount()
            log.info("embedded broker: %d retained messages restored", len(rows))
        await super()._start_listeners()

    def _recount(self) -> None:
        self.stats.retained = len(self._retained_messages)
        msgs = self._retained_messages.values()
        self.stats.retained_bytes = sum(len(m.data or b"") for m in msgs)

    async def retain_message(
        self,
        source_session: Any,
        topic_name: str | None,
        data: bytes | bytearray | None,
        qos: int | None = None,
    ) -> None:
        if data and topic_name is not None:
            old = self._retained_messages.get(topic_name)
            old_len = 0 if old is None else len(old.data or b"")
            if (old is None and self.stats.retained >= self.max_retained) or (
                self.stats.retained_bytes - old_len + len(data) > self.max_retained_bytes
            ):
                self.stats.retained_refused += 1
                self._rate_limited(
                    "embedded broker: retained store full (%d topics, %d bytes; limits %d, %d): "
                    "%s delivered but not retained",
                    self.stats.retained, self.stats.retained_bytes, self.max_retained,
                    self.max_retained_bytes, topic_name[:200],
                )  # fmt: skip
                return
        known = topic_name is not None and topic_name in self._retained_messages
        await super().retain_message(source_session, topic_name, data, qos)
        self._recount()
        if self._db is not None and topic_name is not None and (data or known):
            if not self._dirty_all:
                self._dirty.add(topic_name)
                if len(self._dirty) > 2 * self.max_retained:
                    self._dirty.clear()
                    self._dirty_all = True
            self.retry_writes()

    def retry_writes(self) -> bool:
        """Write the retained changes the file lacks; True when it holds them all.
        A failure keeps them (in memory, served as usual) for the next try."""
        db = self._db
        if db is None or not (self._dirty or self._dirty_all):
            return True
        try:
            with db:
                if self._dirty_all:
                    db.execute("DELETE FROM retained")
                    topics: Iterable[str] = list(self._retained_messages)
                else:
                    topics = self._dirty
                for topic in topics:
                    m = self._retained_messages.get(topic)
                    if m is None or not m.data:
                        db.execute("DELETE FROM retained WHERE topic=?", (topic,))
                    else:
                        db.execute(
                            "INSERT OR REPLACE INTO retained VALUES (?, ?, ?)",
                            (topic, bytes(m.data), m.qos or 0),
                        )
        except (sqlite3.Error, OSError) as e:
            self.stats.write_failures += 1
            self.stats.pending_writes = (
                len(self._retained_messages) if self._dirty_all else len(self._dirty)
            )
            now = time.monotonic()
            if now - self._last_write_log >= REFUSAL_LOG_INTERVAL_S:
                self._last_write_log = now
                text = (
                    f"the embedded broker's retained store {self._db_path} cannot be written "
                    f"({e}): {self.stats.pending_writes} retained topics kept in memory and "
                    f"retried ({self.stats.write_failures} failed writes); they are lost if the "
                    "broker stops before they are written"
                )
                log.error("%s", text)
                if self.on_write_error is not None:
                    self.on_write_error(text)
            return False
        if self.stats.pending_writes:
            log.warning("embedded broker: retained store written again")
        self._dirty.clear()
        self._dirty_all = False
        self.stats.pending_writes = 0
        return True

    async def shutdown(self) -> None:
        # amqtt's shutdown forgets the retained messages: write what is pending first.
        if not self.retry_writes():
            log.error(
                "embedded broker: %d retained changes could not be written and are lost",
                self.stats.pending_writes,
            )
        self._dirty.clear()
        self._dirty_all = False
        await super().shutdown()

    def close_store(self) -> None:
        if self._db is not None:
            self._db.close()
            self._db = None


class EmbeddedBroker:
    """``async with EmbeddedBroker() as b: b.url`` (the URL carries the account).

    ``port=0`` picks a free port; ``port=None`` the saved port, else 1883 when
    free, else a free one. ``state_dir=None`` keeps the account and the retained
    messages in memory only.
    """

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int | None = 0,
        *,
        state_dir: str | Path | None = None,
        anonymous: bool = False,
        username: str = DEFAULT_USER,
        limits: BrokerLimits | None = None,
    ) -> None:
        self.host = host
        self.port = 0 if port is None else port
        self._requested_port = port
        self.state_dir = None if state_dir is None else Path(state_dir)
        self.anonymous = anonymous
        self.username = username
        self.password = ""
        self.password_generated = False  # True when this start made a new password
        self.moved_from: int | None = None  # the busy port this start did not get
        self.limits = limits or BrokerLimits()
        self.stats = BrokerStats()
        self._on_write_error: Callable[[str], None] | None = None
        self._broker: _LimitedBroker | None = None
        self._tmp: tempfile.TemporaryDirectory[str] | None = None
        self._lock_fd: int | None = None

    # ----------------------------------------------------------------- addresses

    @property
    def url(self) -> str:
        """The broker's URL with the account (give it to clients, never to a log)."""
        if self.anonymous:
            return f"mqtt://{self.host}:{self.port}"
        user, password = quote(self.username, safe=""), quote(self.password, safe="")
        return f"mqtt://{user}:{password}@{self.host}:{self.port}"

    @property
    def public_url(self) -> str:
        """:attr:`url` with the password masked (for logs and summaries)."""
        return mask_url(self.url)

    @property
    def account_file(self) -> Path | None:
        return None if self.state_dir is None else self.state_dir / ACCOUNT_FILE

    # ----------------------------------------------------------------- lifecycle

    async def start(self) -> None:
        amqtt_log = logging.getLogger("amqtt")
        if amqtt_log.level == logging.NOTSET:
            # amqtt warns about every client it refuses (the gateway's MQTT 5 probe
            # included) and about harmless protocol quirks: keep its errors only.
            amqtt_log.setLevel(logging.ERROR)
        quiet_connections(logging.getLogger("amqtt.broker"))
        state = self._open_state()
        if not self.anonymous:
            self._account(state)
        self.port = self._choose_port(state)
        plugins: dict[str, Any] = {
            "amqtt.plugins.authentication.AnonymousAuthPlugin": {"allow_anonymous": self.anonymous},
        }
        if not self.anonymous:
            plugins["amqtt.plugins.authentication.FileAuthPlugin"] = {
                "password_file": str(state / PASSWD_FILE)
            }
        config: dict[str, Any] = {
            "listeners": {"default": {"type": "tcp", "bind": f"{self.host}:{self.port}"}},
            # No $SYS publisher, no per-packet logging.
            "plugins": plugins,
            # amqtt checks every second; it bounds the offline queues in time only.
            "session_expiry_interval": self.limits.session_expiry_s,
        }
        try:
            broker = _LimitedBroker(
                config,
                max_message_bytes=self.limits.max_message_bytes,
                max_retained=self.limits.max_retained,
                max_retained_bytes=self.limits.max_retained_bytes,
                db_path=None if self.state_dir is None else state / RETAINED_FILE,
                stats=self.stats,
            )
        except BrokerError:
            self._release()
            raise
        broker.on_write_error = self._on_write_error
        try:
            await broker.start()
        except Exception as e:
            broker.close_store()
            self._release()
            where = f"{self.host}:{self.port}"
            raise BrokerError(f"embedded MQTT broker cannot listen on {where}: {e}") from e
        self._broker = broker
        if self.port == 0:
            self.port = _bound_port(broker)
        if self.state_dir is not None:
            try:
                _write_private(state / PORT_FILE, json.dumps({"port": self.port}) + "\n")
            except OSError as e:
                await self.stop()
                raise BrokerError(f"cannot write {state / PORT_FILE}: {e.strerror or e}") from None
        log.info("embedded MQTT broker listening on %s", self.public_url)

    async def stop(self) -> None:
        if self._broker is not None:
            broker, self._broker = self._broker, None
            try:
                await broker.shutdown()
            finally:
                broker.close_store()
        self._release()

    async def __aenter__(self) -> EmbeddedBroker:
        await self.start()
        return self

    @property
    def on_write_error(self) -> Callable[[str], None] | None:
        """Told (rate-limited) when retained.sqlite cannot be written."""
        return self._on_write_error

    @on_write_error.setter
    def on_write_error(self, fn: Callable[[str], None] | None) -> None:
        self._on_write_error = fn
        if self._broker is not None:
            self._broker.on_write_error = fn

    def retry_writes(self) -> bool:
        """Write what retained.sqlite lacks after failed writes; True when nothing is pending."""
        return True if self._broker is None else self._broker.retry_writes()

    def queued_for(self, client_id: str) -> int | None:
        """Messages queued for the persistent client ``client_id`` while it is away;
        None when the broker holds no session of it (never seen, clean, or expired)."""
        if self._broker is None:
            raise RuntimeError("the embedded broker is not running")
        entry = self._broker.sessions.get(client_id)  # (session, handler)
        return None if entry is None else int(entry[0].retained_messages.qsize())

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()

    # ----------------------------------------------------------------- state

    def _open_state(self) -> Path:
        """The state directory (created 0700 and locked), or a private temporary one."""
        if self.state_dir is None:
            self._tmp = tempfile.TemporaryDirectory(prefix="awaremw-broker-")
            return Path(self._tmp.name)
        d = self.state_dir
        d.mkdir(parents=True, exist_ok=True, mode=0o700)
        fd = os.open(d / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o600)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise BrokerStateInUse(
                f"the broker state {d} is in use by another embedded broker; "
                "give this one its own --state-dir"
            ) from None
        self._lock_fd = fd
        return d

    def _release(self) -> None:
        if self._lock_fd is not None:
            os.close(self._lock_fd)
            self._lock_fd = None
        if self._tmp is not None:
            self._tmp.cleanup()
            self._tmp = None

    def _account(self, state: Path) -> None:
        """Read the saved account, or make one (password generated once)."""
        from pwdlib import PasswordHash
        from pwdlib.hashers.argon2 import Argon2Hasher

        account = state / ACCOUNT_FILE
        if self.state_dir is not None and account.exists():
            user, sep, password = account.read_text().strip().partition(":")
            if not sep or not user or not password:
                raise BrokerError(f"{account} is not user:password; delete it to make a new one")
            self.username, self.password = user, password
        else:
            self.password = secrets.token_urlsafe(18)
            self.password_generated = True
            _write_private(account, f"{self.username}:{self.password}\n")
        digest = PasswordHash((Argon2Hasher(),)).hash(self.password)
        _write_private(state / PASSWD_FILE, f"{self.username}:{digest}\n")

    def _choose_port(self, state: Path) -> int:
        if self._requested_port is not None:
            if self._requested_port and not _port_free(self.host, self._requested_port):
                raise BrokerPortInUse(
                    f"port {self._requested_port} on {self.host} is in use; choose another "
                    "--mqtt-port or leave it out to take a free one"
                )
            return self._requested_port
        wanted = DEFAULT_PORT
        with contextlib.suppress(OSError, ValueError, KeyError, TypeError):
            wanted = int(json.loads((state / PORT_FILE).read_text())["port"])
        if _port_free(self.host, wanted):
            return wanted
        self.moved_from = wanted
        return 0


def _port_free(host: str, port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
        except OSError as e:
            if e.errno in (errno.EADDRINUSE, errno.EACCES):
                return False
            raise
    return True


def _write_private(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` with mode 0600 from the first byte."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(text)
    os.chmod(path, 0o600)


def _bound_port(broker: Broker) -> int:
    server = broker._servers["default"].instance  # amqtt keeps the asyncio.Server here
    for sock in server.sockets:
        name = sock.getsockname()
        if sock.family in (socket.AF_INET, socket.AF_INET6):
            return int(name[1])
    raise RuntimeError("embedded broker has no bound TCP socket")
