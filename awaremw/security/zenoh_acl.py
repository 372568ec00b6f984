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
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any, Final, Literal

from awaremw.runtime.zenoh_session import DEFAULT_ROUTER_ENDPOINT, SessionSettings

Role = Literal["fleet", "gateway", "app", "operator"]
ROLES: Final[tuple[Role, ...]] = ("fleet", "gateway", "app", "operator")
DEFAULT_PREFIX = "aware"

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
    for role in ROLES:
        ids = []
        for k, (messages, flows, keys) in enumerate(GRANTS[role]):
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
        "subjects": [{"id": role, "usernames": [role]} for role in ROLES],
        "policies": policies,
    }


def router_config(dictionary_file: Path, prefix: str = DEFAULT_PREFIX) -> dict[str, Any]:
    """The router's Zenoh config: accounts from ``dictionary_file``, ACL by role.

    Endpoints: ``awaremw router`` sets its ``--listen``; ``zenohd -c`` uses the
    default one below.
    """
    return {
        "mode": "router",
        "listen": {"endpoints": [DEFAULT_ROUTER_ENDPOINT]},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {"auth": {"usrpwd": {"dictionary_file": str(dictionary_file)}}},
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
