"""``awaremw router [--listen ENDPOINT]...``: run an embedded Zenoh router until interrupted."""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING

from awaremw.cli.friendly import add_secrets_option, load_secrets, refuse
from awaremw.cli.helptext import add_log_format, add_metrics_option, add_verb
from awaremw.runtime.zenoh_session import DEFAULT_ROUTER_ENDPOINT

if TYPE_CHECKING:
    from awaremw.ops.endpoint import EndpointThread
    from awaremw.runtime.router import EmbeddedRouter

CLOSE_TIMEOUT_S = 5.0


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = add_verb(
        subparsers,
        "router",
        "run a Zenoh router (multi-process or multi-host fleets)",
        "Run a Zenoh session in router mode until interrupted (Ctrl-C or SIGTERM).\n"
        "Fleets and gateways join it with --connect ENDPOINT.",
        [
            "awaremw router --listen tcp/127.0.0.1:7447",
            "awaremw router --listen tcp/0.0.0.0:7447 --secrets secrets/",
        ],
    )
    p.add_argument(
        "--listen",
        action="append",
        metavar="ENDPOINT",
        help=f"endpoint to listen on (repeatable; default {DEFAULT_ROUTER_ENDPOINT})",
    )
    p.add_argument(
        "--connect",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="another router to link to (repeatable); with --secrets a tls/ endpoint "
        "(mutual TLS with the routers' certificate), and the other router listens on tls/",
    )
    add_secrets_option(
        p,
        "authenticate every session and apply the access rules of DIR/zenoh/router.json5 "
        "(from awaremw keys init DIR)",
    )
    add_metrics_option(p)
    add_log_format(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from awaremw.runtime.router import EmbeddedRouter

    listen = args.listen or [DEFAULT_ROUTER_ENDPOINT]
    stop = threading.Event()

    def on_signal(signum: int, frame: FrameType | None) -> None:
        stop.set()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    config_file: str | None = None
    if args.secrets is not None:
        from awaremw.security.zenoh_acl import check_router_links, router_config_path

        def linkable(d: Path) -> str:
            path = router_config_path(d)
            check_router_links(path, args.connect)
            return str(path)

        config_file = load_secrets("awaremw router", args.secrets, linkable)
        if config_file is None:
            return 2
    metrics = None
    if args.metrics is not None:
        from awaremw.ops.endpoint import metrics_address, metrics_password

        try:
            metrics = metrics_address(args.metrics, metrics_password())
        except ValueError as e:
            return refuse("awaremw router", e)
    try:
        router = EmbeddedRouter(listen, args.connect, config_file=config_file).start()
    except Exception as e:  # bad endpoint, port in use: the user's input, not our bug
        from awaremw.cli.friendly import zenoh_message

        return refuse("awaremw router", f"cannot start: {zenoh_message(e)}")
    mode = "authenticated, access control by role" if config_file else "open to every client"
    print(f"awaremw router listening on {', '.join(listen)} ({mode})", flush=True)
    if config_file is None:
        from awaremw.security.material import warn_open

        warn_open("awaremw router")
    ops = None
    if metrics is not None:
        try:
            ops = _serve_metrics(router, metrics)
        except OSError as e:
            router.close()
            return refuse(
                "awaremw router", f"cannot serve metrics on {metrics[0]}:{metrics[1]}: {e}"
            )
        print(f"awaremw router: metrics on {ops.endpoint.url}/metrics (/healthz, /readyz)",
              flush=True)  # fmt: skip
    # serve_forever closes the session once ``stop`` is set; on a loaded machine a Zenoh
    # close can stall, so it runs in a thread and the process leaves after a bounded wait.
    server = threading.Thread(target=router.serve_forever, args=(stop,), daemon=True)
    server.start()
    while not stop.wait(0.5):
        pass
    if ops is not None:
        ops.stop()
    server.join(CLOSE_TIMEOUT_S)
    if server.is_alive():
        print(
            f"awaremw router: session did not close within {CLOSE_TIMEOUT_S:.0f} s; exiting",
            file=sys.stderr,
            flush=True,
        )
        sys.stdout.flush()
        os._exit(0)
    return 0


def _serve_metrics(router: EmbeddedRouter, address: tuple[str, int]) -> EndpointThread:
    """/metrics, /healthz, /readyz on a thread of their own (the router has no loop)."""
    from awaremw.ops.endpoint import EndpointThread, OpsEndpoint, Readiness, metrics_password
    from awaremw.ops.metrics import RouterMetrics, registry_of

    def linked() -> tuple[int, int]:
        info = router.session.info
        return len(list(info.peers_zid())), len(list(info.routers_zid()))

    endpoint = OpsEndpoint(
        *address, registry_of(RouterMetrics(linked)), lambda: Readiness(True),
        metrics_password(),
    )  # fmt: skip
    thread = EndpointThread(endpoint)
    thread.start()
    return thread
