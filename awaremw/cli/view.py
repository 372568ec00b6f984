"""``awaremw view --web HOST:PORT --mqtt URL [--deployment NAME] [--connect ENDPOINT]``

The web dashboard of a system started elsewhere (``awaremw fleet`` and
``awaremw gateway``, containers, other hosts). It reads the public MQTT
contract (``aware/#``: definitions, group states, data, errors, the gateway's
status) and publishes the page's definitions and commands with the account of
``--mqtt`` (use one with the operator's rights). Mote positions come from the
deployment (mobility at the emulated time the messages carry), or, with
``--connect``, from the fleets themselves (their ``<prefix>/ctl/fleet/*``
queryable, so motes added or killed at run time show). The public contract
names each group's leader but not its members: this view marks leaders and
colours them by group; ``awaremw demo --web`` shows every member and the
collection tree. Details: docs/dashboard.md.
"""

from __future__ import annotations

import argparse
import asyncio
import os
from typing import Any

from awaremw.cli.friendly import add_secrets_option, load_secrets, refuse
from awaremw.cli.helptext import add_log_format, add_verb, add_wall_timeout


def register(sub: Any) -> None:
    p = add_verb(
        sub,
        "view",
        "web dashboard of a running system (MQTT, optional Zenoh)",
        """\
The web dashboard of a system started elsewhere (awaremw fleet and awaremw
gateway, containers, other hosts). It reads the public MQTT contract and
publishes the page's definitions and commands with the account of --mqtt (use
one with the operator's rights). Mote positions come from the deployment, or,
with --connect, from the fleets themselves. The contract names each group's
leader but not its members: this view marks leaders; awaremw demo --web shows
every member. Details: docs/dashboard.md.""",
        [
            "awaremw view --web 127.0.0.1:8080 --mqtt mqtt://operator:PW@127.0.0.1:1883 "
            "--deployment romeo4r",
        ],
    )
    p.add_argument("--web", default="127.0.0.1:8080", metavar="HOST:PORT",
                   help="where to serve the page (default 127.0.0.1:8080; any other than "
                        "loopback needs the password in $AWAREMW_WEB_PASSWORD)")  # fmt: skip
    p.add_argument("--mqtt", required=True, help="broker mqtt[s]://[user:pass@]host:port")
    p.add_argument("--deployment", default="romeo4r", help="deployment name or path (the field)")
    p.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                   help="Zenoh endpoint of the router or a fleet: live positions")  # fmt: skip
    add_secrets_option(p, "with --connect: the operator's Zenoh account (keys init DIR)")
    p.add_argument("--prefix", default="aware", help="MQTT and Zenoh key prefix")
    p.add_argument("--speed", type=float, default=1.0,
                   help="the fleet's speed factor (moves mobile motes)")  # fmt: skip
    p.add_argument("--group-type", type=int, default=None,
                   help="the group type the map colours (default: the lowest seen)")  # fmt: skip
    add_wall_timeout(p, "stop serving")
    add_log_format(p)
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    from awaremw.gateway.mqtt import BadMqttUrl, MqttSettings
    from awaremw.nodes import world_of
    from awaremw.runtime.deployment import DeploymentError, load
    from awaremw.view.guard import check_bind, parse_host_port
    from awaremw.view.web import (
        PASSWORD_ENV,
        DashboardError,
        dashboard_for,
        run_view,
    )

    try:
        dep = load(args.deployment)
        check_bind(*parse_host_port(args.web), os.environ.get(PASSWORD_ENV))
        MqttSettings.from_url(args.mqtt)
    except (DeploymentError, BadMqttUrl, ValueError) as e:
        return refuse("awaremw view", e)
    if not args.speed > 0:
        return refuse("awaremw view", "--speed must be > 0")
    config_file = None
    if args.secrets is not None:
        from awaremw.security.zenoh_acl import role_config_path

        config_file = load_secrets(
            "awaremw view", args.secrets, lambda d: str(role_config_path(d, "operator"))
        )
        if config_file is None:
            return 2
    dash = dashboard_for(dep, world_of(dep), args.mqtt, args.web, dep.name, args.group_type,
                         prefix=args.prefix)  # fmt: skip

    async def serve() -> None:
        await run_view(dash, dep, speed=args.speed, duration=args.timeout,
                       connect=args.connect or None, prefix=args.prefix,
                       config_file=config_file, announce=True)  # fmt: skip

    try:
        asyncio.run(serve())
    except DashboardError as e:
        return refuse("awaremw view", e)
    except KeyboardInterrupt:
        return 130
    return 0
