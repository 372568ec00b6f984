"""Embedded Zenoh router: a session in router mode, for multi-process fleets.

``awaremw router`` runs one until interrupted; the fleet launcher starts one
in its own process when it spreads motes over several worker processes. Other
hosts may use ``zenohd`` instead: nothing here is specific to awaremw except
the loopback-friendly defaults of :mod:`awaremw.runtime.zenoh_session`.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Sequence

import zenoh

from awaremw.runtime.zenoh_session import (
    DEFAULT_ROUTER_ENDPOINT,
    SessionSettings,
    close_quietly,
)

log = logging.getLogger(__name__)


class EmbeddedRouter:
    """A Zenoh router session listening on ``listen`` (and optionally linked to other routers).

    Use as a (sync) context manager, or :meth:`start` / :meth:`close`.
    """

    def __init__(
        self,
        listen: Sequence[str] = (DEFAULT_ROUTER_ENDPOINT,),
        connect: Sequence[str] = (),
        *,
        config_file: str | None = None,
    ) -> None:
        if not listen:
            raise ValueError("a router needs at least one listen endpoint")
        self.listen = tuple(listen)
        self.connect = tuple(connect)
        # e.g. DIR/zenoh/router.json5 of `awaremw keys init`: accounts and access control
        self.config_file = config_file
        self._session: zenoh.Session | None = None

    @property
    def endpoint(self) -> str:
        """The first listen endpoint, to hand to peers as their ``connect``."""
        return self.listen[0]

    def start(self) -> EmbeddedRouter:
        if self._session is None:
            config = SessionSettings(
                mode="router",
                listen=self.listen,
                connect=self.connect,
                config_file=self.config_file,
            ).config()
            if self.connect:
                # Linked routers start in any order and restart on their own: a router
                # keeps dialling the others in the background instead of giving up.
                config.insert_json5("connect/exit_on_failure", "false")
            self._session = zenoh.open(config)
            log.info("Zenoh router %s listening on %s", self._session.zid(), ", ".join(self.listen))
        return self

    @property
    def session(self) -> zenoh.Session:
        if self._session is None:
            raise RuntimeError("router not started")
        return self._session

    def close(self) -> None:
        if self._session is not None:
            close_quietly(self._session)
            self._session = None

    def __enter__(self) -> EmbeddedRouter:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def serve_forever(self, stop: threading.Event | None = None) -> None:
        """Block until ``stop`` is set (or KeyboardInterrupt), then close."""
        self.start()
        stop = stop or threading.Event()
        try:
            while not stop.wait(0.5):
                pass
        finally:
            self.close()
