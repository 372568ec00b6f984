"""Zenoh authentication and access control by role.

Four roles, one Zenoh account each (``transport/auth/usrpwd``), checked by the
router against a dictionary file; the router's ``access_control`` block has
``default_permission: "deny"`` and allows per role only what that role does:

========  =====================================================================
fleet     put/delete/subscribe on ``<prefix>/radio/**``; declare its own
          control queryable ``<prefix>/ctl/fleet/<name>`` and answer queries
gateway   the radio, like fleet (it runs the gateway motes); its own control
          queryable, and it may ask ``<prefix>/ctl/fleet/**`` (it learns the
          running fleets' time origin there); puts data, group state, status
          and errors under ``<prefix>/hbn/**``, receives definitions and
          commands, serves the HBN queryable
app       puts definitions and commands (``<prefix>/hbn/def/**``,
          ``<prefix>/hbn/cmd/**``); subscribes to and queries
          ``<prefix>/hbn/**``; nothing on the radio or the fleet control
operator  queries ``<prefix>/ctl/fleet/**`` (``awaremw fleet-ctl``); nothing else
========  =====================================================================

A rule names Zenoh message kinds and a *flow*: ``ingress`` is what the role's
session sends to the router, ``egress`` what the router forwards to it. So
"app may not put on the radio" is the ``put``/``ingress`` rule fleets and
gateways have and apps lack, and "only fleets hear the radio" is the
``put``/``egress`` rule likewise.

Only sessions that go through the router are checked: with ``--secrets`` every
awaremw process connects in client mode (never peer-to-peer, which would
bypass the router) with its role's credentials.

Routers linked to each other (one per host, ``awaremw router --connect``) carry
every role's traffic between their clients, so their links get a subject of
their own, ``router``: mutual TLS with the routers' certificate (common name
:data:`ROUTER_CN`), allowed every message kind on the radio, fleet-control and
HBN key spaces; a role's rules are applied once, where its session enters its
own router. Why a certificate and not an account: docs/security.md, "Links
between routers".
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final, Literal

import zenoh

from awaremw.runtime.zenoh_session import DEFAULT_ROUTER_ENDPOINT, SessionSettings

Role = Literal["fleet", "gateway", "app", "operator"]
ROLES: Final[tuple[Role, ...]] = ("fleet", "gateway", "app", "operator")
DEFAULT_PREFIX = "aware"
# The account a router logs in with when it links to another router; its rights
# come from the certificate (ROUTER_CN), never from this account alone.
ROUTER_ACCOUNT: Final = "router"
# Common name of the routers' certificate: the ACL subject of router-to-router links.
ROUTER_CN: Final = "awaremw-router"

# (messages, flows, key expressions relative to the prefix)
_Grant = tuple[tuple[str, ...], tuple[str, ...], tuple[str, ...]]

_BOTH = ("ingress", "egress")
_IN = ("ingress",)
_OUT = ("egress",)

_RADIO: Final[tuple[_Grant, ...]] = (
    (("put", "delete", "declare_subscriber"), _BOTH, ("radio/**",)),
)
_CTL_SERVE: Final[tuple[_Grant, ...]] = (
    (("declare_queryable",), _BOTH, ("ctl/fleet/**",)),
    (("query",), _OUT, ("ctl/fleet/**",)),
    (("reply",), _IN, ("ctl/fleet/**",)),
)
_CTL_ASK: Final[tuple[_Grant, ...]] = (
    (("declare_queryable",), _OUT, ("ctl/fleet/**",)),
    (("query",), _IN, ("ctl/fleet/**",)),
    (("reply",), _OUT, ("ctl/fleet/**",)),
)
_HBN_INPUTS = ("hbn/def/**", "hbn/cmd/**")
_HBN_OUTPUTS = ("hbn/data/**", "hbn/groups/**", "hbn/gateway/**", "hbn/errors")

GRANTS: Final[dict[Role, tuple[_Grant, ...]]] = {
    "fleet": _RADIO + _CTL_SERVE,
    "gateway": _RADIO
    + _CTL_SERVE
    + _CTL_ASK
    + (
        (("put", "delete"), _IN, _HBN_OUTPUTS),
        (("put", "delete"), _OUT, _HBN_INPUTS),
        (("declare_subscriber", "declare_queryable"), _BOTH, ("hbn/**",)),
        (("query",), _OUT, ("hbn/**",)),
        (("reply",), _IN, ("hbn/**",)),
    ),
    "app": (
        (("put", "delete"), _IN, _HBN_INPUTS),
        (("put", "delete"), _OUT, ("hbn/**",)),
        (("declare_subscriber",), _BOTH, ("hbn/**",)),
        (("declare_queryable",), _OUT, ("hbn/**",)),
        (("query",), _IN, ("hbn/**",)),
        (("reply",), _OUT, ("hbn/**",)),
    ),
    "operator": _CTL_ASK,
}

# A router-to-router link: everything any role may send, both ways, on the key
# spaces awaremw uses (each role was checked where it entered the mesh).
_ROUTER_LINK: Final[tuple[_Grant, ...]] = (
    (
        ("put", "delete", "declare_subscriber", "declare_queryable", "query", "reply"),
        _BOTH,
        ("radio/**", "ctl/fleet/**", "hbn/**"),
    ),
)


def access_control(prefix: str = DEFAULT_PREFIX) -> dict[str, Any]:
    """The router's ``access_control`` block for key prefix ``prefix``."""
    if (
        not prefix
        or prefix.startswith("/")
        or prefix.endswith("/")
        or any(c in prefix for c in "*$?#")
    ):
        raise ValueError(f"bad key prefix {prefix!r}: expected e.g. 'aware' or 'site1/aware'")
    rules: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    granted: list[tuple[str, tuple[_Grant, ...]]] = [(role, GRANTS[role]) for role in ROLES]
    for role, grants in [*granted, (ROUTER_ACCOUNT, _ROUTER_LINK)]:
        ids = []
        for k, (messages, flows, keys) in enumerate(grants):
            rid = f"{role}-{k}"
            ids.append(rid)
            rules.append(
                {
                    "id": rid,
                    "messages": list(messages),
                    "flows": list(flows),
                    "permission": "allow",
                    "key_exprs": [f"{prefix}/{key}" for key in keys],
                }
            )
        policies.append({"id": f"{role}-policy", "rules": ids, "subjects": [role]})
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": [
            *({"id": role, "usernames": [role]} for role in ROLES),
            # the certificate, not the account: both ends of a link see it (mutual TLS)
            {"id": ROUTER_ACCOUNT, "cert_common_names": [ROUTER_CN]},
        ],
        "policies": policies,
    }


@dataclass(frozen=True, slots=True)
class RouterLinkFiles:
    """What a router needs to link to other routers: the ``router`` account's password
    and the routers' certificate, its key and the CA that signed it (PEM files)."""

    password: str
    ca_cert: Path
    cert: Path
    key: Path


def router_config(
    dictionary_file: Path, links: RouterLinkFiles, prefix: str = DEFAULT_PREFIX
) -> dict[str, Any]:
    """The router's Zenoh config: accounts from ``dictionary_file``, ACL by role, and
    mutual TLS with the routers' certificate for links to other routers (``tls/``
    endpoints; clients keep using ``tcp/`` with their accounts).

    Endpoints: ``awaremw router`` sets its ``--listen``; ``zenohd -c`` uses the
    default one below.
    """
    return {
        "mode": "router",
        "listen": {"endpoints": [DEFAULT_ROUTER_ENDPOINT]},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {
            "auth": {
                "usrpwd": {
                    "dictionary_file": str(dictionary_file),
                    "user": ROUTER_ACCOUNT,
                    "password": links.password,
                }
            },
            "link": {
                "tls": {
                    "root_ca_certificate": str(links.ca_cert),
                    "listen_certificate": str(links.cert),
                    "listen_private_key": str(links.key),
                    "connect_certificate": str(links.cert),
                    "connect_private_key": str(links.key),
                    "enable_mtls": True,
                    # routers dial each other by any name or address; the CA signs
                    # nothing but the routers' certificate, so the name is not checked
                    "verify_name_on_connect": False,
                }
            },
        },
        "access_control": access_control(prefix),
    }


def client_config(role: Role, password: str) -> dict[str, Any]:
    """A role's Zenoh client config: credentials, client mode, no multicast scouting.

    No endpoint: whoever connects sets ``connect/endpoints``.
    """
    return {
        "mode": "client",
        "scouting": {"multicast": {"enabled": False}},
        "transport": {"auth": {"usrpwd": {"user": role, "password": password}}},
    }


# ------------------------------------------------------------------ use by the processes


class SecretsError(ValueError):
    """A secrets directory that is missing, incomplete or unreadable."""


def _existing(secrets: Path | str, name: str) -> Path:
    path = Path(secrets) / "zenoh" / name
    if not path.is_file():
        raise SecretsError(f"{path} not found: make the secrets with `awaremw keys init {secrets}`")
    return path


def role_config_path(secrets: Path | str, role: Role) -> Path:
    """DIR/zenoh/<role>.json5, which must exist."""
    return _existing(secrets, f"{role}.json5")


def router_config_path(secrets: Path | str) -> Path:
    """DIR/zenoh/router.json5, which must exist."""
    return _existing(secrets, "router.json5")


def role_settings(
    secrets: Path | str,
    role: Role,
    connect: Sequence[str] = (),
    *,
    connect_timeout_s: float = 10.0,
) -> SessionSettings:
    """Client-mode session settings for ``role``, through the router at ``connect``
    (default ``tcp/127.0.0.1:7447``)."""
    return SessionSettings(
        "client",
        tuple(connect) or (DEFAULT_ROUTER_ENDPOINT,),
        (),
        connect_timeout_s,
        config_file=str(role_config_path(secrets, role)),
    )


def check_router_links(config_file: Path | str, connect: Sequence[str]) -> None:
    """Refuse links to other routers that the access rules would silently deny.

    With the secrets' rules a link is a ``router`` subject only when both ends see the
    routers' certificate, so every ``connect`` endpoint must be ``tls/`` and the config
    must hold that certificate (secrets made before router links existed do not).
    """
    plain = [ep for ep in connect if not ep.startswith("tls/")]
    if plain:
        raise SecretsError(
            f"cannot link to {', '.join(plain)}: with secrets, routers link over mutual TLS; "
            "use tls/HOST:PORT and let that router listen on tls/ too"
        )
    if connect:
        conf = zenoh.Config.from_file(str(config_file))
        if conf.get_json("transport/link/tls/enable_mtls") != "true":
            raise SecretsError(
                f"{config_file} has no router certificate (secrets made before router "
                "links existed): make new ones with `awaremw keys init DIR --force`"
            )
