"""Who may drive the web dashboard, and how many sockets it may hold.

* :class:`RequestGuard` (an aiohttp middleware): every request must name the
  dashboard itself in ``Host`` (DNS rebinding); with a password, HTTP Basic
  authentication; a state-changing request (``POST``, ``DELETE``) must also be
  same-origin (``Origin``, ``Sec-Fetch-Site``), carry the per-server token the
  page received (``X-Awaremw-Token``), and send JSON as ``application/json``.
* :class:`BoundedListener`: accepts at most :data:`MAX_CONNECTIONS` connections
  at once (beyond, they wait in the kernel's backlog and cost this process no
  file descriptor) and closes a connection that does not complete a request
  within :data:`REQUEST_TIMEOUT_S` of opening or of its previous answer (slow
  headers, idle keep-alive). So no number of clients can take the descriptors
  the fleet and the gateway need in the same process.
"""

from __future__ import annotations

import asyncio
import base64
import binascii
import contextlib
import hmac
import ipaddress
import logging
import secrets
import socket
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass

from aiohttp import web

log = logging.getLogger(__name__)

MAX_CONNECTIONS = 128  # HTTP connections held at once (SSE streams included)
LISTEN_BACKLOG = 64  # completed handshakes the kernel keeps waiting beyond that
REQUEST_TIMEOUT_S = 10.0  # a connection not being answered must finish a request by then
SWEEP_S = 1.0  # how often connections are checked against the timeout
TOKEN_HEADER = "X-Awaremw-Token"
STATE_CHANGING = frozenset({"POST", "DELETE", "PUT", "PATCH"})
WILDCARDS = frozenset({"0.0.0.0", "::", ""})
LOG_EVERY_S = 10.0  # accept failures (EMFILE...) logged at most this often


class InsecureBind(ValueError):
    """A non-loopback dashboard address without a password."""


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def check_bind(
    host: str,
    port: int,
    password: str | None,
    *,
    what: str = "the dashboard",
    risk: str = "anyone reaching it could define groups and send commands",
    env: str = "AWAREMW_WEB_PASSWORD",
) -> None:
    """Refuse to serve beyond this machine without a password."""
    if not is_loopback(host) and not password:
        raise InsecureBind(
            f"refusing to serve {what} on {host}:{port} without a password ({risk}): "
            f"set {env}, or serve on 127.0.0.1"
        )


def parse_host_port(text: str, option: str = "--web") -> tuple[str, int]:
    """``HOST:PORT`` (``[::1]:8080`` for IPv6); port 0 picks a free one."""
    host, sep, port = text.rpartition(":")
    host = host.strip("[]")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ValueError(f"bad {option} address {text!r}: expected HOST:PORT, e.g. 127.0.0.1:8080")
    return host, int(port)


def _split_host(value: str) -> tuple[str, int | None]:
    """``name:port`` / ``[v6]:port`` / ``name`` -> (name, port or None)."""
    value = value.strip().lower()
    if value.startswith("["):
        name, _, rest = value[1:].partition("]")
        port = rest[1:] if rest.startswith(":") else ""
    elif value.count(":") == 1:
        name, _, port = value.partition(":")
    else:
        name, port = value, ""
    if port and not port.isdigit():
        return name, -1
    return name, int(port) if port else None


@dataclass(slots=True)
class RequestGuard:
    """The checks every request passes (an aiohttp middleware: ``guard.middleware``)."""

    host: str
    port: int
    password: str | None = None
    token: str = ""

    def __post_init__(self) -> None:
        if not self.token:
            self.token = secrets.token_urlsafe(24)

    def own_host(self, value: str | None) -> bool:
        """``Host`` (or an origin's host part) names this dashboard."""
        if not value:
            return False
        name, port = _split_host(value)
        if (port or 80) != self.port:
            return False
        bound = self.host.strip("[]").lower()
        if bound in WILDCARDS:
            return True  # any of this machine's names; the password guards it
        if name == bound:
            return True
        return is_loopback(bound) and is_loopback(name)

    def refusal(self, request: web.Request) -> web.HTTPException | None:
        """Why ``request`` may not go on (None: it may)."""
        if not self.own_host(request.headers.get("Host")):
            return web.HTTPForbidden(text="foreign Host: this dashboard answers only to its "
                                          "own address")  # fmt: skip
        if self.password is not None and not self._authenticated(request):
            return web.HTTPUnauthorized(
                text="password required", headers={"WWW-Authenticate": 'Basic realm="awaremw"'}
            )
        if request.method not in STATE_CHANGING:
            return None
        origin = request.headers.get("Origin")
        if origin is not None:
            scheme, sep, rest = origin.partition("://")
            if not sep or scheme.lower() != "http" or not self.own_host(rest):
                return web.HTTPForbidden(text=f"cross-origin request from {origin[:80]!r}")
            if _split_host(rest)[0] != _split_host(request.headers.get("Host", ""))[0]:
                return web.HTTPForbidden(text="Origin and Host differ")
        site = request.headers.get("Sec-Fetch-Site")
        if site is not None and site not in ("same-origin", "none"):
            return web.HTTPForbidden(text=f"cross-site request ({site})")
        given = request.headers.get(TOKEN_HEADER, "")
        if not hmac.compare_digest(given.encode(), self.token.encode()):
            return web.HTTPForbidden(text=f"missing or wrong {TOKEN_HEADER} (reload the page)")
        if request.method == "POST" and request.content_type != "application/json":
            return web.HTTPUnsupportedMediaType(text="send JSON as application/json")
        return None

    def _authenticated(self, request: web.Request) -> bool:
        kind, _, value = request.headers.get("Authorization", "").partition(" ")
        if kind.lower() != "basic" or self.password is None:
            return False
        try:
            _user, _, given = base64.b64decode(value, validate=True).decode().partition(":")
        except (binascii.Error, UnicodeDecodeError):
            return False
        return hmac.compare_digest(given.encode(), self.password.encode())

    @web.middleware
    async def middleware(
        self, request: web.Request, handler: Callable[[web.Request], Awaitable[web.StreamResponse]]
    ) -> web.StreamResponse:
        refused = self.refusal(request)
        if refused is not None:
            raise refused
        return await handler(request)


@dataclass(slots=True)
class _Conn:
    last: float  # when it opened, or when its last answer ended
    busy: int = 0  # requests being answered on it now


class BoundedListener:
    """Serves aiohttp's protocol factory on a socket it accepts from itself, at
    most ``limit`` connections at once, each closed when it does not finish a
    request within ``timeout`` seconds (unless it is being answered)."""

    def __init__(
        self,
        host: str,
        port: int,
        *,
        limit: int = MAX_CONNECTIONS,
        timeout: float = REQUEST_TIMEOUT_S,
        backlog: int = LISTEN_BACKLOG,
    ) -> None:
        self.factory: Callable[[], asyncio.BaseProtocol] | None = None
        self.limit = limit
        self.timeout = timeout
        family = socket.AF_INET6 if ":" in host.strip("[]") else socket.AF_INET
        try:
            infos = socket.getaddrinfo(
                host.strip("[]") or None, port, family=family, type=socket.SOCK_STREAM,
                flags=socket.AI_PASSIVE,
            )  # fmt: skip
            self.sock = socket.create_server(infos[0][4][:2], family=infos[0][0], backlog=backlog)
        except socket.gaierror as e:
            raise OSError(e.errno, e.strerror) from None
        self.sock.setblocking(False)
        self.port = int(self.sock.getsockname()[1])
        self._conns: dict[asyncio.BaseTransport, _Conn] = {}
        self._room = asyncio.Event()
        self._tasks: list[asyncio.Task[None]] = []
        self.accepted = 0
        self.timed_out = 0
        self._logged = 0.0

    @property
    def open_connections(self) -> int:
        return len(self._conns)

    def start(self, factory: Callable[[], asyncio.BaseProtocol]) -> None:
        """Start accepting; ``factory`` makes each connection's protocol (aiohttp's server)."""
        self.factory = factory
        self._tasks = [asyncio.create_task(self._accept(), name="dashboard-accept"),
                       asyncio.create_task(self._sweeper(), name="dashboard-sweep")]  # fmt: skip

    async def close(self) -> None:
        for t in self._tasks:
            t.cancel()
        for t in self._tasks:
            with contextlib.suppress(asyncio.CancelledError):
                await t
        self.sock.close()
        for tr in list(self._conns):
            tr.abort() if isinstance(tr, asyncio.Transport) else tr.close()
        self._conns.clear()

    # ------------------------------------------------------------------ requests

    def request_started(self, transport: asyncio.BaseTransport | None) -> None:
        c = self._conns.get(transport) if transport is not None else None
        if c is not None:
            c.busy += 1

    def request_ended(self, transport: asyncio.BaseTransport | None) -> None:
        c = self._conns.get(transport) if transport is not None else None
        if c is not None:
            c.busy = max(0, c.busy - 1)
            c.last = time.monotonic()

    @web.middleware
    async def middleware(
        self, request: web.Request, handler: Callable[[web.Request], Awaitable[web.StreamResponse]]
    ) -> web.StreamResponse:
        self.request_started(request.transport)
        try:
            return await handler(request)
        finally:
            self.request_ended(request.transport)

    # ------------------------------------------------------------------ loops

    async def _accept(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            while len(self._conns) >= self.limit:
                self._room.clear()
                self._sweep()
                if len(self._conns) >= self.limit:
                    await self._room.wait()
            try:
                sock, _addr = await loop.sock_accept(self.sock)
            except OSError as e:  # EMFILE, ENOBUFS...: the others in this process come first
                self._log(f"dashboard: cannot accept a connection: {e}")
                await asyncio.sleep(0.1)  # back-off, not synchronisation
                continue
            try:
                assert self.factory is not None
                transport, _ = await loop.connect_accepted_socket(self.factory, sock)
            except OSError as e:
                sock.close()
                self._log(f"dashboard: dropped a connection: {e}")
                continue
            self.accepted += 1
            self._conns[transport] = _Conn(time.monotonic())

    async def _sweeper(self) -> None:
        while True:
            await asyncio.sleep(SWEEP_S)  # periodic check, not synchronisation
            self._sweep()

    def _sweep(self) -> None:
        now = time.monotonic()
        for tr, c in list(self._conns.items()):
            if tr.is_closing():
                del self._conns[tr]
            elif not c.busy and now - c.last > self.timeout:
                self.timed_out += 1
                del self._conns[tr]
                tr.abort() if isinstance(tr, asyncio.Transport) else tr.close()
        if len(self._conns) < self.limit:
            self._room.set()

    def _log(self, line: str) -> None:
        now = time.monotonic()
        if now - self._logged >= LOG_EVERY_S:
            self._logged = now
            log.warning(line)
