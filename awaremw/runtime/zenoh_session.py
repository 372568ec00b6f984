"""Zenoh session configuration: loopback, no multicast scouting, explicit endpoints.

Every process of the emulation opens exactly ONE Zenoh session (through
:func:`open_session`) and closes it explicitly. Defaults are chosen so that
nothing leaks onto the host's network and nothing needs a daemon:

* multicast scouting is off (peers find each other only through the endpoints
  we give them, so parallel test runs never join each other's emulations);
* a peer that is given neither ``listen`` nor ``connect`` endpoints is alone
  (one process, local pub/sub only);
* a peer that is given ``connect`` endpoints (the embedded router, ``awaremw
  router``) joins the emulation through them and, unless told otherwise,
  also listens on an ephemeral loopback port: measured with zenoh 1.10, a
  router routes nothing between peers that do not listen (samples published
  by one never reach the other), while peers that listen learn about each
  other from the router (gossip) and link directly. Across hosts, give an
  explicit ``listen`` endpoint or use client mode.

Endpoints are Zenoh locators such as ``tcp/127.0.0.1:7447``.
"""

from __future__ import annotations

import json
import socket
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import zenoh

Mode = Literal["peer", "client", "router"]

DEFAULT_ROUTER_ENDPOINT = "tcp/127.0.0.1:7447"
LOOPBACK_EPHEMERAL = "tcp/127.0.0.1:0"


@dataclass(frozen=True, slots=True)
class SessionSettings:
    """What a process needs to know to join (or host) an emulation."""

    mode: Mode = "peer"
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    connect_timeout_s: float = 10.0
    # A Zenoh json5 config to start from (credentials, access control: the role
    # configs of ``awaremw keys init``); mode and endpoints above override it.
    config_file: str | None = None

    def config(self) -> zenoh.Config:
        return make_config(
            self.mode,
            connect=self.connect,
            listen=self.listen,
            connect_timeout_s=self.connect_timeout_s,
            config_file=self.config_file,
        )


def make_config(
    mode: Mode = "peer",
    *,
    connect: Sequence[str] = (),
    listen: Sequence[str] = (),
    connect_timeout_s: float = 10.0,
    config_file: str | None = None,
) -> zenoh.Config:
    """A Zenoh config with multicast scouting off and exactly these endpoints.

    With ``connect`` endpoints, opening keeps trying for ``connect_timeout_s``
    (the router may still be starting), then fails. With ``config_file`` the
    config starts from that json5 file (e.g. credentials and access control).
    """
    for ep in (*connect, *listen):
        check_endpoint(ep)
    if mode == "peer" and connect and not listen:
        listen = (LOOPBACK_EPHEMERAL,)  # see the module docstring
    cfg = zenoh.Config() if config_file is None else zenoh.Config.from_file(config_file)
    cfg.insert_json5("mode", json.dumps(mode))
    cfg.insert_json5("scouting/multicast/enabled", "false")
    cfg.insert_json5("connect/endpoints", json.dumps(list(connect)))
    cfg.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if connect:
        cfg.insert_json5("connect/timeout_ms", str(int(connect_timeout_s * 1000)))
        cfg.insert_json5("connect/exit_on_failure", "true")
    return cfg


def open_session(settings: SessionSettings | None = None) -> zenoh.Session:
    """Open the process's one session. The caller closes it (``session.close()``)."""
    return zenoh.open((settings or SessionSettings()).config())


def close_quietly(obj: zenoh.Session | zenoh.Subscriber[object] | zenoh.Publisher) -> None:
    """Close a session or undeclare a subscriber/publisher (the stubs leave these untyped)."""
    if isinstance(obj, zenoh.Session):
        obj.close()  # type: ignore[no-untyped-call]
    else:
        obj.undeclare()  # type: ignore[no-untyped-call]


def check_endpoint(endpoint: str) -> None:
    """Reject obviously malformed locators early, with a clear message."""
    proto, sep, addr = endpoint.partition("/")
    if not sep or not proto or not addr:
        raise ValueError(f"bad Zenoh endpoint {endpoint!r}: expected e.g. tcp/127.0.0.1:7447")
    if proto in ("tcp", "udp", "tls", "quic", "ws"):
        host, colon, port = addr.rpartition(":")
        if not colon or not host or not port.split("#")[0].isdigit():
            raise ValueError(f"bad Zenoh endpoint {endpoint!r}: expected {proto}/HOST:PORT")


def free_tcp_endpoint(host: str = "127.0.0.1") -> str:
    """A ``tcp/host:port`` endpoint on a port that was free a moment ago (tests, launcher)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        port = s.getsockname()[1]
    return f"tcp/{host}:{port}"
