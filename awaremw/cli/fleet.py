"""``awaremw fleet`` (run a deployment's motes) and ``awaremw fleet-ctl`` (add/kill at run time).

::

    awaremw fleet grid_small --duration 30 --speed 2
    awaremw fleet large --processes 2 --listen tcp/127.0.0.1:7447
    awaremw fleet-ctl add 99 --kind tmote --position 20 30
    awaremw fleet-ctl kill 7
    awaremw fleet-ctl list

Without ``--connect`` the fleet is reachable on ``--listen`` (default
``tcp/127.0.0.1:7447``): its own session with one process, the embedded
router with ``--processes N``. With ``--connect`` it joins an existing router
(``awaremw router``). ``fleet-ctl`` asks every fleet process through the
Zenoh queryables ``<prefix>/ctl/fleet/*`` (docs/runtime.md).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import sys
from typing import Any

from awaremw.cli.friendly import (
    add_secrets_option,
    load_secrets,
    refuse,
    stop_event,
    zenoh_message,
    zenoh_unreachable,
)
from awaremw.cli.helptext import add_log_format, add_metrics_option, add_verb, add_zenoh_mode
from awaremw.runtime.zenoh_session import DEFAULT_ROUTER_ENDPOINT, SessionSettings


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = add_verb(
        subparsers,
        "fleet",
        "run a deployment's motes (one process or many)",
        "Run the motes of DEPLOYMENT (a shipped name or a .toml path) on the Zenoh\n"
        "radio medium until --duration emulated seconds or Ctrl-C.",
        [
            "awaremw fleet grid_small --plain",
            "awaremw fleet romeo4r --connect tcp/127.0.0.1:7447 --without-kind gateway --plain",
            "awaremw fleet large --processes 2 --duration 60",
        ],
    )
    p.add_argument(
        "deployment",
        metavar="DEPLOYMENT",
        help="path or shipped name (romeo4r, fire, grid_small, large)",
    )
    p.add_argument("--processes", type=int, default=1, metavar="N", help="worker processes")
    p.add_argument(
        "--connect", action="append", default=[], metavar="ENDPOINT", help="join this router"
    )
    p.add_argument(
        "--listen",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help=f"where gateways and fleet-ctl reach the fleet (default {DEFAULT_ROUTER_ENDPOINT} "
        "unless --connect)",
    )
    p.add_argument("--duration", type=float, default=None, metavar="S", help="emulated seconds")
    p.add_argument("--speed", type=float, default=1.0, metavar="X", help="speed factor")
    p.add_argument("--plain", action="store_true", help="plain log lines (no live view)")
    p.add_argument("--prefix", default="aware", help="Zenoh key prefix (default aware)")
    p.add_argument(
        "--progress", type=float, default=2.0, metavar="S", help="wall seconds between lines"
    )
    p.add_argument(
        "--hello", action="store_true", help="run the HelloMote stand-in instead of the node kinds"
    )
    p.add_argument(
        "--without-kind",
        action="append",
        default=[],
        metavar="KIND",
        help="do not run motes of this kind here (e.g. gateway, run by awaremw gateway)",
    )
    p.add_argument(
        "--part",
        default=None,
        metavar="K/N",
        help="run only stripe K of N along x (fleets on several hosts share one deployment)",
    )
    p.add_argument(
        "--start-at",
        type=float,
        default=None,
        metavar="UNIX_TIME",
        help="shared wall-clock start of emulated time (fleets on several hosts)",
    )
    add_zenoh_mode(p)
    p.add_argument(
        "--pcap",
        default=None,
        metavar="FILE",
        help="write the radio traffic to FILE (pcapng, IEEE 802.15.4; docs/capture.md)",
    )
    p.add_argument(
        "--links-json",
        default=None,
        metavar="PATH",
        help="at the end, write the frames delivered per (src, dst) link as JSON",
    )
    add_secrets_option(
        p,
        "connect with role fleet (DIR from awaremw keys init): to the router at "
        "--connect, else to an embedded router started here with DIR's access rules",
    )
    add_metrics_option(p)
    add_log_format(p)
    p.set_defaults(func=run_fleet)

    c = add_verb(
        subparsers,
        "fleet-ctl",
        "add, kill or list motes of running fleets",
        "Talk to running fleets through <prefix>/ctl/fleet/* on Zenoh.",
        [
            "awaremw fleet-ctl --connect tcp/127.0.0.1:7447 list",
            "awaremw fleet-ctl --connect tcp/127.0.0.1:7447 kill 7",
            "awaremw fleet-ctl add 99 --kind tmote --position 20 30",
        ],
    )
    c.add_argument(
        "--connect",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help=f"fleet or router endpoint (default {DEFAULT_ROUTER_ENDPOINT})",
    )
    c.add_argument("--prefix", default="aware", help="Zenoh key prefix (default aware)")
    c.add_argument("--timeout", type=float, default=3.0, metavar="S", help="wait for answers")
    add_secrets_option(c, "connect to the router with role operator (DIR from awaremw keys init)")
    csub = c.add_subparsers(dest="op", metavar="OP", required=True)
    a = csub.add_parser("add", help="add a mote (validated like a [[nodes]] entry)")
    a.add_argument("id", type=int)
    a.add_argument("--kind", required=True)
    a.add_argument("--position", type=float, nargs=2, metavar=("X", "Y"))
    a.add_argument("--path", nargs="+", metavar="X,Y", help="waypoints of a moving mote")
    a.add_argument("--speed-mps", type=float, default=None)
    a.add_argument("--loop", action="store_true")
    a.add_argument("--tx-power", type=float, default=None, metavar="DBM")
    a.add_argument("--battery", type=float, default=None, metavar="MJ")
    a.add_argument("--boot", type=float, default=None, metavar="S")
    k = csub.add_parser("kill", help="switch a mote off")
    k.add_argument("id", type=int)
    csub.add_parser("list", help="motes on the air and where they are")
    csub.add_parser("stats", help="counters and timer lag of every fleet process")
    csub.add_parser("items", help="the definitions every mote holds (version and body)")
    c.set_defaults(func=run_ctl)


# --------------------------------------------------------------------------- fleet


def _load(arg: str, hello: bool) -> Any:
    from awaremw import nodes
    from awaremw.runtime.deployment import load

    return load(arg, None if hello else nodes.kind_names())


def run_fleet(args: argparse.Namespace) -> int:
    from awaremw.runtime.deployment import DeploymentError

    if args.processes < 1:
        return refuse("awaremw fleet", "--processes must be >= 1")
    if not args.speed > 0:
        return refuse("awaremw fleet", "--speed must be > 0")
    try:
        dep = _load(args.deployment, args.hello)
    except DeploymentError as e:
        return refuse("awaremw fleet", e)
    try:
        args.part_filter = _part_filter(args.part, dep)
    except ValueError as e:
        return refuse("awaremw fleet", f"--part {args.part}: {e}")
    if args.zenoh_mode == "client" and (not args.connect or args.listen):
        return refuse("awaremw fleet", "--zenoh-mode client needs --connect and no --listen")
    if args.metrics is not None:
        from awaremw.ops.endpoint import metrics_address, metrics_password

        try:
            args.metrics = metrics_address(args.metrics, metrics_password())
        except ValueError as e:
            return refuse("awaremw fleet", e)
    args.role_config = args.router_config = args.security = None
    if args.secrets is not None:
        from awaremw.security.material import load_radio_security
        from awaremw.security.zenoh_acl import role_config_path, router_config_path

        loaded = load_secrets(
            "awaremw fleet",
            args.secrets,
            # The network key and the gateway's public key; never its signing key.
            lambda d: (
                str(role_config_path(d, "fleet")),
                None if args.connect else str(router_config_path(d)),
                load_radio_security(d),
            ),
        )
        if loaded is None:
            return 2
        args.role_config, args.router_config, args.security = loaded
    else:
        from awaremw.security.material import warn_open

        warn_open("awaremw fleet")
    try:
        return asyncio.run(_run_fleet(args, dep))
    except _StartError as e:
        return refuse("awaremw fleet", e)


class _StartError(Exception):
    pass


def _part_filter(part: str | None, dep: Any) -> Any:
    """The node filter of ``--part K/N``: stripe K (1-based) of N along x."""
    if part is None:
        return None
    from awaremw.runtime.partition import stripes

    k_s, sep, n_s = part.partition("/")
    if not sep or not k_s.isdigit() or not n_s.isdigit():
        raise ValueError("expected K/N with whole numbers, e.g. 1/2")
    k, n = int(k_s), int(n_s)
    if not 1 <= k <= n:
        raise ValueError(f"K must be in 1..N, got {k}/{n}")
    return stripes(dep, n)[k - 1]


async def _run_fleet(args: argparse.Namespace, dep: Any) -> int:
    import zenoh

    from awaremw.nodes import KindsFactory
    from awaremw.runtime.fleet import LauncherSettings, open_fleet
    from awaremw.runtime.fleet.motes import CoreFactory, hello_core
    from awaremw.runtime.fleet.pool import LaunchError
    from awaremw.runtime.fleet.stats import merged_links

    stop = stop_event()
    listen = args.listen or ([] if args.connect else [DEFAULT_ROUTER_ENDPOINT])
    factory: CoreFactory = hello_core if args.hello else KindsFactory(security=args.security)
    where = ", ".join(args.connect) if args.connect else ", ".join(listen)
    print(
        f"awaremw fleet: {dep.name}: {len(dep.nodes)} motes, {args.processes} process(es), "
        f"speed x{args.speed:g}, Zenoh {'via ' if args.connect else 'on '}{where}"
        f"{_secured(args.security)}",
        flush=True,
    )
    try:
        # With --secrets and no --connect the motes run behind an embedded router
        # that applies the access rules: worker processes, even with one.
        settings = LauncherSettings(
            processes=args.processes,
            speed=args.speed,
            prefix=args.prefix,
            connect=tuple(args.connect),
            listen=tuple(listen),
            progress_s=args.progress,
            track_links=args.links_json is not None,
            exclude_kinds=frozenset(args.without_kind),
            router_config_file=args.router_config,
            worker_config_file=args.role_config,
            security=args.security,
            pcap=args.pcap,
            start_wall=args.start_at,
            client=args.zenoh_mode == "client",
            figures=args.metrics is not None,
        )
        fleet = open_fleet(dep, factory, settings, part=args.part_filter)
    except ValueError as e:
        raise _StartError(str(e)) from None
    code = 0
    async with contextlib.AsyncExitStack() as stack:
        if args.metrics is not None:  # up first: /readyz says 503 until the motes run
            await _serve_fleet_metrics(stack, args.metrics, fleet)
        try:
            await stack.enter_async_context(fleet)
        except zenoh.ZError as e:
            if args.connect:
                why = zenoh_unreachable(list(args.connect), e, args.secrets is not None)
                raise _StartError(why) from None
            raise _StartError(f"cannot start Zenoh on {where}: {zenoh_message(e)}") from None
        except LaunchError as e:
            raise _StartError(str(e)) from None
        print(f"awaremw fleet: running, reachable at {fleet.endpoint}", flush=True)
        run = asyncio.create_task(fleet.run(args.duration))
        stopper = asyncio.create_task(stop.wait())
        while not run.done() and not stop.is_set():
            await asyncio.wait(
                {run, stopper}, timeout=args.progress, return_when=asyncio.FIRST_COMPLETED
            )
            if not run.done() and not stop.is_set():
                print(fleet.stats.snapshot().line(), flush=True)
        for t in (run, stopper):
            t.cancel()
        if run.done() and not run.cancelled() and run.exception() is not None:
            print(f"awaremw fleet: {run.exception()}", file=sys.stderr)
            code = 1
        print(fleet.stats.snapshot().line(), flush=True)
    tot = fleet.counters()
    tx = sum(c.frames_tx for c in tot.values())
    rx = sum(c.frames_rx for c in tot.values())
    print(f"awaremw fleet: done at t={fleet.now():.1f}s: frames tx={tx} rx={rx}", flush=True)
    for r in fleet.results:
        if r.error:
            print(f"awaremw fleet: process {r.name}: {r.error}", file=sys.stderr)
            code = 1
    if fleet.capture is not None:
        print(f"awaremw fleet: {fleet.capture.packets} packets to {args.pcap}", flush=True)
    if args.links_json is not None:
        links = merged_links(fleet.results)
        with open(args.links_json, "w", encoding="utf-8") as f:
            json.dump([[s, d, n] for (s, d), n in sorted(links.items())], f)
    return code


async def _serve_fleet_metrics(
    stack: contextlib.AsyncExitStack, address: tuple[str, int], fleet: Any
) -> None:
    """One endpoint for the fleet's processes together (a launcher merges its
    workers' figures, sent with their progress snapshots)."""
    from awaremw.ops.endpoint import OpsEndpoint, metrics_password
    from awaremw.ops.metrics import FleetMetrics, fleet_readiness, registry_of

    def snapshot() -> Any:
        return fleet.stats.snapshot(window=False)

    ops = OpsEndpoint(
        *address, registry_of(FleetMetrics(snapshot)), lambda: fleet_readiness(snapshot),
        metrics_password(),
    )  # fmt: skip
    try:
        await stack.enter_async_context(ops)
    except OSError as e:
        raise _StartError(f"cannot serve metrics on {address[0]}:{address[1]}: {e}") from None
    print(f"awaremw fleet: metrics on {ops.url}/metrics (/healthz, /readyz)", flush=True)


def _secured(security: Any) -> str:
    if security is None:
        return ""
    return (
        f" (role fleet, access control on; authenticated radio, {security.overhead} B "
        "per frame; signed items verified)"
    )


# --------------------------------------------------------------------------- fleet-ctl


def _node_entry(args: argparse.Namespace) -> dict[str, Any]:
    entry: dict[str, Any] = {"id": args.id, "kind": args.kind}
    if (args.position is None) == (args.path is None):
        raise ValueError("give exactly one of --position X Y or --path X,Y ...")
    if args.position is not None:
        entry["position"] = list(args.position)
    else:
        pts = []
        for w in args.path:
            try:
                x, y = (float(v) for v in w.split(","))
            except ValueError:
                raise ValueError(f"bad waypoint {w!r}: expected X,Y") from None
            pts.append([x, y])
        entry["path"] = pts
        if args.speed_mps is not None:
            entry["speed_mps"] = args.speed_mps
        if args.loop:
            entry["loop"] = True
    for key, val in (("tx_power_dbm", args.tx_power), ("battery_mj", args.battery)):
        if val is not None:
            entry[key] = val
    if args.boot is not None:
        entry["boot_s"] = args.boot
    return entry


def control_query(
    connect: list[str],
    prefix: str,
    request: dict[str, Any],
    timeout: float,
    config_file: str | None = None,
) -> list[dict[str, Any]]:
    """Send one control request to every fleet process; their JSON replies.

    ``config_file``: a Zenoh client config with credentials (role operator).
    """
    import zenoh

    from awaremw.runtime.zenoh_session import close_quietly, open_session

    session = open_session(
        SessionSettings("client", tuple(connect), connect_timeout_s=2.0, config_file=config_file)
    )
    out: list[dict[str, Any]] = []
    try:
        replies = session.get(
            f"{prefix}/ctl/fleet/*",
            payload=json.dumps(request).encode(),
            timeout=timeout,
            target=zenoh.QueryTarget.ALL,
        )
        for reply in replies:
            ok = reply.ok
            if ok is None:
                continue
            try:
                d = json.loads(ok.payload.to_bytes())
            except ValueError:
                continue
            if isinstance(d, dict):
                out.append(d)
    finally:
        close_quietly(session)
    return out


def run_ctl(args: argparse.Namespace) -> int:
    import zenoh

    connect = args.connect or [DEFAULT_ROUTER_ENDPOINT]
    config_file = None
    if args.secrets is not None:
        from awaremw.security.zenoh_acl import role_config_path

        config_file = load_secrets(
            "awaremw fleet-ctl", args.secrets, lambda d: str(role_config_path(d, "operator"))
        )
        if config_file is None:
            return 2
    if args.op == "add":
        try:
            req: dict[str, Any] = {"op": "add", "node": _node_entry(args)}
        except ValueError as e:
            return refuse("awaremw fleet-ctl", e)
    elif args.op == "kill":
        req = {"op": "kill", "id": args.id}
    else:
        req = {"op": args.op}
    try:
        replies = control_query(connect, args.prefix, req, args.timeout, config_file)
    except zenoh.ZError as e:
        print(
            f"awaremw fleet-ctl: {zenoh_unreachable(connect, e, args.secrets is not None)}",
            file=sys.stderr,
        )
        return 1
    if not replies:
        print(
            f"awaremw fleet-ctl: no fleet answered on {args.prefix}/ctl/fleet/* "
            f"via {', '.join(connect)}",
            file=sys.stderr,
        )
        return 1
    replies.sort(key=lambda d: str(d.get("fleet")))
    errors = [d for d in replies if not d.get("ok")]
    done = [d for d in replies if d.get("done")]
    if args.op in ("list", "stats", "items"):
        if args.op == "list" and sys.stdout.isatty():
            print("# node\tx (m)\ty (m)\tfleet")  # for a reader; piped output stays bare
        for d in replies:
            if args.op == "list":
                for nid, (x, y) in sorted(d.get("motes", {}).items(), key=lambda kv: int(kv[0])):
                    print(f"{nid}\t{x:.2f}\t{y:.2f}\t{d.get('fleet')}")
            elif args.op == "items":
                print(json.dumps({"fleet": d.get("fleet"), "items": d.get("items", {})}))
            else:
                print(json.dumps(d.get("snapshot", d)))
        return 0
    for d in errors:
        print(f"awaremw fleet-ctl: fleet {d.get('fleet')}: {d.get('error')}", file=sys.stderr)
    if errors:
        return 1
    if not done:
        what = "ran" if args.op == "kill" else "took"
        print(f"awaremw fleet-ctl: no fleet {what} node {args.id}", file=sys.stderr)
        return 1
    verb = "added to" if args.op == "add" else "killed in"
    print(f"node {args.id} {verb} fleet {', '.join(str(d.get('fleet')) for d in done)}")
    return 0
