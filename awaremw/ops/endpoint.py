"""The operations endpoint of a long-running process (``--metrics HOST:PORT``).

* ``/metrics``: every metric of the process in the Prometheus text format
  (prometheus-client renders the registry; docs/monitoring.md lists each one);
* ``/healthz``: 200 while the process runs (its loop answers);
* ``/readyz``: 200 when it does its job, else 503 with the reason (a gateway that
  has subscribed and holds its definitions; a fleet whose motes run and whose
  clock keeps up).

The dashboard's rules apply (:mod:`awaremw.view.guard`): loopback by default;
any other address needs a password (HTTP Basic, ``$AWAREMW_METRICS_PASSWORD``),
or it is refused (:class:`~awaremw.view.guard.InsecureBind`); requests must
name the endpoint in ``Host``; at most ``MAX_CONNECTIONS`` connections at once.
``/healthz`` and ``/readyz`` answer without the password (an orchestrator's
probe; they tell nothing but "up" and "ready").
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import threading
from collections.abc import Awaitable, Callable
from dataclasses import dataclass

from aiohttp import web
from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, generate_latest

from awaremw.view.guard import BoundedListener, RequestGuard, check_bind, parse_host_port

PASSWORD_ENV = "AWAREMW_METRICS_PASSWORD"
HEALTH_PATHS = frozenset({"/healthz", "/readyz"})


@dataclass(frozen=True, slots=True)
class Readiness:
    """Whether a process does its job; ``why`` says what it waits for."""

    ready: bool
    why: str = ""


def metrics_address(text: str, password: str | None) -> tuple[str, int]:
    """``--metrics HOST:PORT`` checked by the address rules (ValueError, one line)."""
    host, port = parse_host_port(text, "--metrics")
    check_bind(
        host,
        port,
        password,
        what="metrics",
        risk="they show the network's layout and load",
        env=PASSWORD_ENV,
    )
    return host, port


def metrics_password() -> str | None:
    return os.environ.get(PASSWORD_ENV) or None


class OpsEndpoint:
    """``async with OpsEndpoint(host, port, registry, ready)``: serves until closed;
    :attr:`port` is the bound port (``port=0`` picks a free one)."""

    def __init__(
        self,
        host: str,
        port: int,
        registry: CollectorRegistry,
        ready: Callable[[], Readiness],
        password: str | None = None,
    ) -> None:
        check_bind(
            host,
            port,
            password,
            what="metrics",
            env=PASSWORD_ENV,
            risk="they show the network's layout and load",
        )
        self.host, self.port = host, port
        self.registry = registry
        self.ready = ready
        self.password = password
        self.scrapes = 0
        self._listener: BoundedListener | None = None
        self._runner: web.AppRunner | None = None

    async def start(self) -> None:
        listener = BoundedListener(self.host, self.port)
        self.port = listener.port
        guard = RequestGuard(self.host, self.port, self.password)

        @web.middleware
        async def guarded(
            request: web.Request, handler: Callable[[web.Request], Awaitable[web.StreamResponse]]
        ) -> web.StreamResponse:
            # Health answers say nothing but "up" and "ready": an orchestrator's probe
            # asks them without the password (the Host check still holds).
            if request.path in HEALTH_PATHS and guard.own_host(request.headers.get("Host")):
                return await handler(request)
            refused = guard.refusal(request)
            if refused is not None:
                raise refused
            return await handler(request)

        app = web.Application(middlewares=[listener.middleware, guarded])
        app.router.add_get("/metrics", self._metrics)
        app.router.add_get("/healthz", self._healthz)
        app.router.add_get("/readyz", self._readyz)
        runner = web.AppRunner(
            app,
            access_log=None,
            handle_signals=False,
            shutdown_timeout=1.0,
            max_line_size=4096,
            max_field_size=4096,
        )
        await runner.setup()
        server = runner.server
        assert server is not None
        listener.start(server)
        self._listener, self._runner = listener, runner

    async def close(self) -> None:
        if self._listener is not None:
            await self._listener.close()
            self._listener = None
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None

    async def __aenter__(self) -> OpsEndpoint:
        await self.start()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}"

    async def _metrics(self, request: web.Request) -> web.Response:
        self.scrapes += 1
        body = generate_latest(self.registry)
        return web.Response(body=body, headers={"Content-Type": CONTENT_TYPE_LATEST})

    async def _healthz(self, request: web.Request) -> web.Response:
        return web.Response(text="ok\n")

    async def _readyz(self, request: web.Request) -> web.Response:
        r = self.ready()
        if r.ready:
            return web.Response(text="ready\n")
        return web.Response(status=503, text=f"not ready: {r.why}\n")


class EndpointThread:
    """An :class:`OpsEndpoint` on an event loop of its own, in a daemon thread: for a
    process without asyncio (the router). ``start()`` returns once it listens (or
    raises what binding raised); ``stop()`` closes it."""

    def __init__(self, endpoint: OpsEndpoint) -> None:
        self.endpoint = endpoint
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, daemon=True)

    def start(self) -> OpsEndpoint:
        self._thread.start()
        asyncio.run_coroutine_threadsafe(self.endpoint.start(), self._loop).result(10)
        return self.endpoint

    def stop(self) -> None:
        with contextlib.suppress(Exception):  # leaving anyway: nothing to report to
            asyncio.run_coroutine_threadsafe(self.endpoint.close(), self._loop).result(5)
        self._loop.call_soon_threadsafe(self._loop.stop)
