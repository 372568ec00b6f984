"""``awaremw gateway DEPLOYMENT``: run the gateway motes and bridge them to MQTT and Zenoh.

The gateway runs the deployment's gateway motes (collection roots) in this
process, joined to the emulation through ``--connect`` (a router or a fleet
that listens), and serves the MQTT contract and the Zenoh HBN API
(docs/gateway.md). What it keeps (versions, the embedded broker's account,
port and retained messages) lives in the deployment's state directory
(awaremw/gateway/state.py; docs/gateway.md, *State directories*). Emulated
time is taken from a running fleet when one answers on its control key (so
record times and epochs agree), else it starts at 0 now.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import logging
import sys
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

from awaremw.cli.friendly import add_secrets_option, load_secrets, refuse, stop_event
from awaremw.cli.helptext import add_log_format, add_metrics_option, add_verb, add_zenoh_mode
from awaremw.gateway.mqtt import BadMqttUrl, BadPasswordFile, MqttSettings

if TYPE_CHECKING:
    from awaremw.gateway.broker import EmbeddedBroker
    from awaremw.gateway.leftovers import Leftovers
    from awaremw.gateway.service import GatewayService
    from awaremw.gateway.state import DeploymentState

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = add_verb(
        sub,
        "gateway",
        "run the gateway motes and the MQTT / Zenoh bridge",
        "Run the deployment's gateway motes and bridge them to MQTT (an embedded\n"
        "broker with an account when --mqtt is not given) and to the Zenoh HBN API.",
        [
            "awaremw gateway romeo4r --connect tcp/127.0.0.1:7447",
            "awaremw gateway romeo4r --mqtt mqtt://gateway:PW@127.0.0.1:1884",
        ],
    )
    p.add_argument("deployment", metavar="DEPLOYMENT", help="deployment name or .toml path")
    p.add_argument(
        "--mqtt",
        default=None,
        metavar="URL",
        help="broker mqtt[s]://[user:pass@]host:port (default: embedded broker)",
    )
    p.add_argument(
        "--mqtt-password-file",
        default=None,
        metavar="FILE",
        help="the password of the --mqtt URL's user (given as mqtt[s]://USER@host:port), "
        "read from FILE less one trailing newline: not in the process list",
    )
    p.add_argument(
        "--mqtt-port",
        type=int,
        default=None,
        metavar="PORT",
        help="embedded broker port (default: the port used last time, else 1883 when free, "
        "else a free one, printed)",
    )
    p.add_argument(
        "--mqtt-anonymous",
        action="store_true",
        help="let the embedded broker accept clients without an account",
    )
    p.add_argument(
        "--connect",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="Zenoh endpoint of the emulation (repeatable)",
    )
    p.add_argument(
        "--listen",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="Zenoh endpoint to listen on (repeatable)",
    )
    add_zenoh_mode(p)
    p.add_argument("--prefix", default="aware", help="topic prefix (default aware)")
    add_secrets_option(
        p,
        "connect to the router at --connect (default tcp/127.0.0.1:7447) with role "
        "gateway (DIR from awaremw keys init)",
    )
    p.add_argument(
        "--state-dir",
        default=None,
        metavar="DIR",
        help="the deployment's state directory: versions in DIR/gateway.sqlite, the embedded "
        "broker's account, port and retained messages in DIR/broker (default: "
        "$XDG_STATE_HOME/awaremw/deployments/<deployment>, i.e. ~/.local/state/...)",
    )
    p.add_argument(
        "--fresh",
        action="store_true",
        help="forget the versions and retained messages kept for this deployment (the "
        "embedded broker's account and port stay)",
    )
    p.add_argument("--speed", type=float, default=1.0, help="emulation speed factor")
    p.add_argument(
        "--duration",
        type=float,
        default=None,
        metavar="S",
        help="stop after S emulated seconds (default: run until interrupted)",
    )
    p.add_argument(
        "--start-wall",
        type=float,
        default=None,
        metavar="UNIX_TIME",
        help="the emulation's time origin (default: ask a running fleet, else now)",
    )
    p.add_argument("--radio-prefix", default=None, help="Zenoh prefix of the emulated radio")
    p.add_argument("--client-id", default="awaremw-gateway", help="MQTT client id")
    p.add_argument("--ca-file", default=None, help="CA bundle for mqtts://")
    p.add_argument("--tls-insecure", action="store_true", help="do not verify the broker's name")
    p.add_argument(
        "--buffer",
        type=int,
        default=10_000,
        metavar="N",
        help="records kept while the broker is away (default 10000)",
    )
    p.add_argument("--no-hbn", action="store_true", help="no Zenoh HBN API")
    p.add_argument(
        "--pcap",
        default=None,
        metavar="FILE",
        help="write the radio traffic the gateway's motes send and hear to FILE (pcapng)",
    )
    p.add_argument(
        "--define-initial",
        action="store_true",
        help="apply the deployment's [[groups]] and [[channels]] at start",
    )
    add_metrics_option(p)
    add_log_format(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    try:
        mqtt = (
            None
            if args.mqtt is None
            else MqttSettings.from_url(
                args.mqtt,
                client_id=args.client_id,
                ca_file=args.ca_file,
                tls_insecure=args.tls_insecure,
                buffer_size=args.buffer,
            )
        )
        if args.mqtt_password_file is not None:
            if mqtt is None:
                raise BadMqttUrl(
                    "--mqtt-password-file is for the user of --mqtt mqtt[s]://USER@HOST:PORT; "
                    "the embedded broker has its own account"
                )
            mqtt = mqtt.with_password_file(args.mqtt_password_file)
    except (BadMqttUrl, BadPasswordFile) as e:
        return refuse("awaremw gateway", e)
    args.session_settings = args.security = args.signing_key = None
    if args.secrets is not None:
        from awaremw.security.material import load_gateway_keys
        from awaremw.security.zenoh_acl import role_settings

        if args.listen:
            return refuse("awaremw gateway", "--listen and --secrets do not combine")
        # Only the gateway holds the signing key: its motes sign what they inject.
        loaded = load_secrets(
            "awaremw gateway",
            args.secrets,
            lambda d: (role_settings(d, "gateway", args.connect), load_gateway_keys(d)),
        )
        if loaded is None:
            return 2
        args.session_settings, (args.security, args.signing_key) = loaded
    elif args.zenoh_mode == "client":  # everything through the router (e.g. across networks)
        if not args.connect or args.listen:
            return refuse("awaremw gateway", "--zenoh-mode client needs --connect and no --listen")
        from awaremw.runtime.zenoh_session import SessionSettings

        args.session_settings = SessionSettings("client", tuple(args.connect))
    if args.speed <= 0 or args.buffer < 1:
        return refuse("awaremw gateway", "--speed must be > 0 and --buffer >= 1")
    if args.mqtt is not None and (args.mqtt_port is not None or args.mqtt_anonymous):
        return refuse(
            "awaremw gateway",
            "--mqtt-port and --mqtt-anonymous are for the embedded broker; "
            "they cannot go with --mqtt",
        )
    if args.mqtt_port is not None and not 0 <= args.mqtt_port <= 65535:
        return refuse("awaremw gateway", "--mqtt-port must be in 0..65535")
    if args.metrics is not None:
        from awaremw.ops.endpoint import metrics_address, metrics_password

        try:
            args.metrics = metrics_address(args.metrics, metrics_password())
        except ValueError as e:
            return refuse("awaremw gateway", e)
    try:
        return asyncio.run(_main(args, mqtt))
    except KeyboardInterrupt:
        return 130


async def _main(args: argparse.Namespace, mqtt: MqttSettings | None) -> int:
    from awaremw.gateway.broker import BrokerError, EmbeddedBroker
    from awaremw.gateway.events import Publish
    from awaremw.gateway.service import GatewaySettings, attach_to_fleet, deployment_definitions
    from awaremw.gateway.state import StateError
    from awaremw.gateway.store import StoreError
    from awaremw.nodes import KindsFactory, kind_names
    from awaremw.ops.metrics import show_gateway, starting_endpoint
    from awaremw.radio.zenoh_medium import DEFAULT_PREFIX
    from awaremw.runtime.deployment import DeploymentError, load
    from awaremw.runtime.fleet import Fleet, FleetSettings

    try:
        dep = load(args.deployment, kind_names())
    except (DeploymentError, OSError) as e:
        return refuse("awaremw gateway", e)
    if not any(s.kind == "gateway" for s in dep.nodes):
        return refuse("awaremw gateway", f"{dep.name} has no mote of kind 'gateway'")
    if args.secrets is None:  # after the input checks: a refused run says one thing
        from awaremw.security.material import warn_open

        warn_open("awaremw gateway")
    radio_prefix = args.radio_prefix or DEFAULT_PREFIX
    stop = stop_event()

    async with contextlib.AsyncExitStack() as stack:
        try:
            state = stack.enter_context(_open_state(dep, args.state_dir, args.fresh))
        except StateError as e:
            return refuse("awaremw gateway", e)
        print(
            f"awaremw gateway: state of {dep.name} in {state.dir}"
            + (f" (--fresh: forgot {', '.join(state.forgotten)})" if state.forgotten else ""),
            flush=True,
        )
        ops = None
        if args.metrics is not None:  # up first: /readyz says 503 until the gateway is
            try:
                ops = await stack.enter_async_context(starting_endpoint(args.metrics))
            except OSError as e:
                where = f"{args.metrics[0]}:{args.metrics[1]}"
                return refuse("awaremw gateway", f"cannot serve metrics on {where}: {e}")
            print(f"awaremw gateway: metrics on {ops.url}/metrics (/healthz, /readyz)", flush=True)
        broker: EmbeddedBroker | None = None
        if mqtt is None:
            try:
                broker = await stack.enter_async_context(
                    EmbeddedBroker(
                        port=args.mqtt_port,
                        state_dir=state.broker_dir,
                        anonymous=args.mqtt_anonymous,
                    )
                )
            except (BrokerError, OSError) as e:
                return refuse("awaremw gateway", e)
            print_broker(broker)
            mqtt = MqttSettings.from_url(
                broker.url, client_id=args.client_id, buffer_size=args.buffer
            )
        fleet = Fleet(
            dep,
            KindsFactory(security=args.security, signing_key=args.signing_key),
            FleetSettings(
                name="gateway",
                speed=args.speed,
                prefix=radio_prefix,
                connect=tuple(args.connect),
                listen=tuple(args.listen),
                autostart=False,
                session=args.session_settings,
                security=args.security,
                figures=ops is not None,
            ),
            node_filter=lambda s: s.kind == "gateway",
        )
        await stack.enter_async_context(fleet)
        start_wall = args.start_wall
        if start_wall is None and (args.connect or args.session_settings is not None):
            start_wall = await _fleet_start_wall(fleet, radio_prefix, args.speed)
        fleet.start(start_wall)
        if args.pcap is not None:
            from awaremw.radio.capture import Capture
            from awaremw.radio.frame_counts import with_tap

            capture = Capture.to_file(args.pcap, epoch=fleet.clock.start_wall)
            stack.callback(capture.close)  # closed before the fleet: later taps are ignored
            fleet.medium.tap = with_tap(fleet.medium.tap, capture)
        settings = GatewaySettings(prefix=args.prefix, state_dir=state.dir)
        try:
            svc = attach_to_fleet(fleet, settings=settings, mqtt=mqtt, hbn=not args.no_hbn)
        except StoreError as e:
            return refuse("awaremw gateway", e)
        leftovers = await _leftovers(replace(mqtt, prefix=args.prefix), set(dep.ids))
        await stack.enter_async_context(svc)
        if ops is not None:
            show_gateway(ops, svc, lambda: fleet.stats.snapshot(window=False))
        _report_write_errors(svc, broker)
        if leftovers is not None:
            for rel in leftovers.foreign:  # led by a mote this network does not have
                svc.publish(Publish(rel, b"", retain=True))
            if leftovers.kept:
                task = asyncio.create_task(_clear_unheard(svc, leftovers.kept, args.speed))
                stack.push_async_callback(_cancelled, task)
        stack.push_async_callback(_cancelled, asyncio.create_task(_retry_writes(svc, broker)))
        if args.define_initial:
            for out in svc.define_initial(deployment_definitions(dep.groups, dep.channels)):
                if out.error is not None:
                    what = "warning on" if out.error.warning else "refused"
                    print(
                        f"awaremw gateway: deployment definition {what}: {out.error.topic}: "
                        f"{out.error.error}",
                        file=sys.stderr,
                    )
        print(
            f"awaremw gateway: motes {','.join(map(str, svc.roots))} of {dep.name}; "
            f"MQTT {mqtt.url} prefix {args.prefix!r}; Zenoh HBN "
            f"{'off' if args.no_hbn else args.prefix + '/hbn/**'}"
            + (
                ""
                if args.security is None
                else f"; authenticated radio (payload MTU {svc.config.mtu} B), items signed"
            ),
            flush=True,
        )
        waiters = [asyncio.create_task(stop.wait()), asyncio.create_task(fleet.run(args.duration))]
        done, pending = await asyncio.wait(waiters, return_when=asyncio.FIRST_COMPLETED)
        for t in pending:
            t.cancel()
        for t in done:
            if (exc := t.exception()) is not None:
                raise exc
    return 0


RETRY_WRITES_S = 5.0  # how often changes a full or read-only disk refused are written again


def _open_state(dep: object, state_dir: str | None, fresh: bool) -> DeploymentState:
    """The deployment's state directory, opened and locked (StateError: one line)."""
    from awaremw.gateway.state import default_dir, deployment_key, open_state
    from awaremw.runtime.deployment import Deployment, shipped_dir

    assert isinstance(dep, Deployment)
    key = deployment_key(dep.name, dep.path, shipped_dir())
    d = default_dir(key) if state_dir is None else Path(state_dir)
    return open_state(d, key, name=dep.name, source=str(dep.path or dep.name), fresh=fresh)


def _report_write_errors(svc: GatewayService, broker: EmbeddedBroker | None) -> None:
    """Failed writes of the state directory go to <prefix>/errors (rate-limited by their
    sources), besides the log."""
    from awaremw.gateway.events import ErrorReport, Publish

    def report(where: str) -> Callable[[str], None]:
        def publish(text: str) -> None:
            err = ErrorReport(topic=where, code="state_write_failed", error=text, payload="")
            svc.publish(Publish("errors", err.to_json()))

        return publish

    svc.store.on_write_error = report(f"state:{svc.store.path}")
    if broker is not None:
        broker.on_write_error = report(f"state:{broker.state_dir}")


async def _retry_writes(svc: GatewayService, broker: EmbeddedBroker | None) -> None:
    while True:
        await asyncio.sleep(RETRY_WRITES_S)  # a retry period, not a synchronisation
        svc.store.retry()
        if broker is not None:
            broker.retry_writes()


async def _leftovers(mqtt: MqttSettings, motes: set[int]) -> Leftovers | None:
    """The retained group states left on the broker, sorted; None when it cannot say."""
    import aiomqtt

    from awaremw.gateway.leftovers import retained_groups, sort_leftovers

    try:
        states = await retained_groups(mqtt)
    except (aiomqtt.MqttError, TimeoutError, OSError) as e:
        log.warning("cannot read the retained group states on %s (%s): left as they are",
                    mqtt.url, e)  # fmt: skip
        return None
    found = sort_leftovers(states, motes)
    if found.foreign:
        log.info("clearing %d retained group states led by motes not in this network",
                 len(found.foreign))  # fmt: skip
    return found


async def _clear_unheard(svc: GatewayService, topics: tuple[str, ...], speed: float) -> None:
    """Clear the retained group states kept from the last run that the network has
    not reported again within the bridge's expiry (their group is gone)."""
    from awaremw.gateway.events import Publish

    policy = svc.bridge.policy
    await asyncio.sleep(policy.report_period_s * policy.expiry_periods / speed)  # the expiry
    live = svc.bridge.group_states()
    for rel in topics:
        if rel not in live:
            svc.publish(Publish(rel, b"", retain=True))
            log.info("cleared %s: its group was not reported since the gateway started", rel)


async def _cancelled(task: asyncio.Task[None]) -> None:
    task.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await task


def print_broker(broker: object) -> None:
    """Say where the embedded broker is and how to log in (the password once only)."""
    from awaremw.gateway.broker import EmbeddedBroker

    assert isinstance(broker, EmbeddedBroker)
    where = f"mqtt://{broker.host}:{broker.port}"
    if broker.moved_from is not None:
        print(
            f"embedded MQTT broker: port {broker.moved_from} is in use, so the broker is on "
            f"port {broker.port} instead (kept for the next start)",
            flush=True,
        )
    if broker.anonymous:
        print(f"embedded MQTT broker: {where} (anonymous access allowed)", flush=True)
        return
    print(f"embedded MQTT broker: {where} account {broker.username!r}", flush=True)
    if broker.password_generated:
        print(
            f"embedded MQTT broker: generated password {broker.password} (shown once; "
            f"kept in {broker.account_file}, mode 0600)",
            flush=True,
        )
    else:
        print(f"embedded MQTT broker: password in {broker.account_file}", flush=True)


async def _fleet_start_wall(fleet: object, radio_prefix: str, speed: float) -> float | None:
    """Ask running fleets for their emulated time; the time origin it implies, or None."""
    from awaremw.runtime.fleet import Fleet

    assert isinstance(fleet, Fleet)
    session = fleet.session
    request = json.dumps({"op": "list"}).encode()

    def ask() -> float | None:
        for _ in range(6):  # routes may take a moment after connecting
            t_sent = time.time()
            for reply in session.get(f"{radio_prefix}/ctl/fleet/**", payload=request, timeout=0.5):
                if reply.ok is None:
                    continue
                try:
                    doc = json.loads(reply.ok.payload.to_bytes())
                except ValueError:
                    continue
                t = doc.get("t")
                if doc.get("fleet") != fleet.name and isinstance(t, int | float):
                    t_recv = time.time()
                    return (t_sent + t_recv) / 2 - float(t) / speed
        return None

    start = await asyncio.to_thread(ask)
    if start is None:
        log.warning("no fleet answered on %s/ctl/fleet: emulated time starts now", radio_prefix)
    return start
