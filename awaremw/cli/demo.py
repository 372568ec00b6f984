"""``awaremw demo [--deployment PATH] [--duration S] [--speed X] [--mqtt URL] [--plain]``

Everything on one machine with nothing else installed: the fleet, the gateway
with an embedded MQTT broker (unless --mqtt) and the robot's client, with a
live map (--plain: log lines), then a summary. Secure by default: without
--secrets the demo makes throw-away secrets (as ``awaremw keys init``) in a
temporary directory removed at the end; --insecure runs it all open. The
verb's --help (:func:`register`) says the rest.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import os
import sys
import tempfile
from pathlib import Path
from typing import Any

from rich.console import Console
from rich.table import Table

from awaremw.cli.friendly import add_secrets_option, load_secrets, refuse
from awaremw.cli.helptext import add_log_format, add_metrics_option, add_verb


def register(sub: Any) -> None:
    p = add_verb(
        sub,
        "demo",
        "the whole system here: fleet, gateway, MQTT, robot, live map",
        """\
Everything on one machine with nothing else installed: the fleet of motes over
Zenoh on loopback, the gateway with an embedded MQTT broker (unless --mqtt),
and the robot's client, which defines the tracking group and a channel over
MQTT and prints the data it receives, with a live map (--plain: log lines).
The run ends after the scenario's duration (or --duration emulated seconds)
with a summary, also written to --summary FILE. Exit status 1 when the broker
cannot be reached or the robot received no record.

Secure by default: throw-away secrets, Zenoh access control by role,
authenticated radio frames, signed definitions; --insecure runs it all open.""",
        [
            "awaremw demo",
            "awaremw demo --deployment fire --speed 5",
            "awaremw demo --duration 60 --plain",
            "awaremw demo --web 127.0.0.1:8080",
        ],
    )
    p.add_argument("--deployment", default="romeo4r", help="deployment name or path")
    p.add_argument("--duration", type=float, default=None, help="emulated seconds to run")
    p.add_argument("--speed", type=float, default=1.0, help="emulated seconds per wall second")
    p.add_argument("--mqtt", default=None, help="broker mqtt[s]://[user:pass@]host:port")
    p.add_argument(
        "--robot-mqtt",
        default=None,
        metavar="URL",
        help="the robot client's own broker account (default: the --mqtt URL)",
    )
    add_secrets_option(
        p, "use these secrets (DIR from awaremw keys init; default: throw-away ones)"
    )
    p.add_argument(
        "--insecure",
        "--no-secrets",
        dest="insecure",
        action="store_true",
        help="run without secrets: open Zenoh, unauthenticated radio, unsigned items",
    )
    p.add_argument(
        "--mqtt-port",
        type=int,
        default=None,
        metavar="PORT",
        help="embedded broker port (default 1883 when free, else a free one)",
    )
    p.add_argument(
        "--mqtt-anonymous",
        action="store_true",
        help="let the embedded broker accept clients without an account",
    )
    p.add_argument("--plain", action="store_true", help="log lines instead of the live view")
    p.add_argument(
        "--web",
        default=None,
        metavar="HOST:PORT",
        help="also serve the web dashboard there (e.g. 127.0.0.1:8080; beyond loopback the "
        "password in $AWAREMW_WEB_PASSWORD; docs/dashboard.md)",
    )
    p.add_argument(
        "--summary",
        default=None,
        metavar="FILE",
        help="also write the summary here (default $XDG_STATE_HOME/awaremw/demo-summary.txt)",
    )
    add_metrics_option(p)
    add_log_format(p)
    p.set_defaults(func=main)


def summary_path(arg: str | None) -> Path:
    """Where the summary is written: ``arg``, else next to the gateway's state."""
    if arg is not None:
        return Path(arg)
    from awaremw.gateway.state import state_root

    return state_root() / "demo-summary.txt"


def main(args: argparse.Namespace) -> int:
    if getattr(args, "verbose", 0) < 2:
        # The embedded broker logs every refused protocol probe at WARNING.
        logging.getLogger("amqtt").setLevel(logging.ERROR)
    from awaremw.experiments.scenario import load_scenario
    from awaremw.gateway.mqtt import BadMqttUrl, MqttSettings
    from awaremw.runtime.deployment import DeploymentError

    try:
        sc = load_scenario(args.deployment)
    except DeploymentError as e:
        return refuse("awaremw demo", e)
    if not args.speed > 0 or (args.duration is not None and not args.duration > 0):
        return refuse("awaremw demo", "--speed and --duration must be > 0")
    if args.mqtt is not None and (args.mqtt_port is not None or args.mqtt_anonymous):
        return refuse("awaremw demo", "--mqtt-port and --mqtt-anonymous cannot go with --mqtt")
    for url in (args.mqtt, args.robot_mqtt):
        if url is not None:
            try:
                MqttSettings.from_url(url)
            except BadMqttUrl as e:
                return refuse("awaremw demo", e)
    if args.web is not None:
        from awaremw.view.guard import check_bind, parse_host_port
        from awaremw.view.web import PASSWORD_ENV

        try:
            check_bind(*parse_host_port(args.web), os.environ.get(PASSWORD_ENV))
        except ValueError as e:
            return refuse("awaremw demo", e)
    if args.metrics is not None:
        from awaremw.ops.endpoint import metrics_address, metrics_password

        try:
            args.metrics = metrics_address(args.metrics, metrics_password())
        except ValueError as e:
            return refuse("awaremw demo", e)
    if not sc.deployment.of_kind("gateway"):
        return refuse("awaremw demo", f"{sc.name} has no gateway mote")
    if args.insecure and args.secrets is not None:
        return refuse("awaremw demo", "--insecure and --secrets do not combine")
    if args.secrets is not None:
        from awaremw.security.material import check_secrets

        if load_secrets("awaremw demo", args.secrets, check_secrets) is None:
            return 2
    # A live view needs a terminal: piped or redirected output gets log lines.
    plain = args.plain or not sys.stdout.isatty()
    from awaremw.gateway.broker import BrokerError
    from awaremw.gateway.mqtt import mqtt_problem
    from awaremw.view.web import DashboardError

    for url in dict.fromkeys(u for u in (args.mqtt, args.robot_mqtt) if u is not None):
        if (why := asyncio.run(mqtt_problem(url))) is not None:
            print(f"awaremw demo: {why}", file=sys.stderr)
            return 1
    with contextlib.ExitStack() as stack:
        secrets = _secrets(args, stack)
        try:
            summary = asyncio.run(
                run_demo(
                    sc,
                    args.duration,
                    args.speed,
                    args.mqtt,
                    plain,
                    args.robot_mqtt,
                    secrets,
                    mqtt_port=args.mqtt_port,
                    mqtt_anonymous=args.mqtt_anonymous,
                    web=args.web,
                    metrics=args.metrics,
                )
            )
        except (BrokerError, DashboardError) as e:
            return refuse("awaremw demo", e)
    print_summary(summary, plain=plain)
    path = summary_path(args.summary)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(summary_text(summary), encoding="utf-8")
        print(f"awaremw demo: summary written to {path}", flush=True)
    except OSError as e:
        print(f"awaremw demo: cannot write the summary to {path}: {e}", file=sys.stderr)
    if summary["records_received"] == 0:
        print(f"awaremw demo: {no_record_reason(summary, args.mqtt is not None)}",
              file=sys.stderr)  # fmt: skip
        return 1
    return 0


def no_record_reason(s: dict[str, Any], external: bool) -> str:
    """One line on why the robot may have received nothing."""
    if s["errors"]:
        return f"the robot received no record; the gateway reported: {s['errors'][0][:200]}"
    if s["records_produced"] and external:
        return (
            f"the robot received no record although the leaders produced {s['records_produced']}: "
            "the gateway cannot publish them or the robot cannot read them (with broker_cfg/: "
            "--mqtt needs the gateway account, --robot-mqtt the operator's)"
        )
    if s["records_produced"]:
        return f"the robot received none of the {s['records_produced']} records produced"
    if s.get("group_types") == [] or s.get("channels") == []:
        missing = "group type" if s.get("group_types") == [] else "channel"
        return (
            f"no record can come: {s['deployment']} defines no {missing} ([[groups]] and "
            "[[channels]] in the deployment file, docs/deployments.md), so no group "
            "sends data, however long it runs; use a deployment with both (romeo4r, fire, "
            "large) or define them over MQTT while it runs (awaremw define)"
        )
    return "no record was produced: no group formed in the time run (try a longer --duration)"


def summary_text(s: dict[str, Any]) -> str:
    return "".join(f"{k}: {v}\n" for k, v in summary_rows(s))


def _secrets(args: argparse.Namespace, stack: contextlib.ExitStack) -> str | None:
    """The secrets directory the demo runs with: --secrets DIR (checked by the caller),
    throw-away ones made now (removed when ``stack`` closes), or None with --insecure."""
    from awaremw.security.material import warn_open

    if args.insecure:
        warn_open("awaremw demo")
        return None
    if args.secrets is not None:
        return str(args.secrets)
    from awaremw.security.keys import init_secrets

    tmp = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="awaremw-demo-")))
    init_secrets(tmp / "secrets")
    print(
        f"awaremw demo: throw-away secrets in {tmp / 'secrets'} (removed at the end): Zenoh "
        "access control by role, authenticated radio, signed items; --insecure runs open",
        flush=True,
    )
    return str(tmp / "secrets")


async def run_demo(
    sc: Any,
    duration: float | None,
    speed: float,
    mqtt: str | None,
    plain: bool,
    robot_mqtt: str | None = None,
    secrets: str | None = None,
    *,
    mqtt_port: int | None = 0,
    mqtt_anonymous: bool = False,
    web: str | None = None,
    fresh_broker: bool = False,
    metrics: tuple[str, int] | None = None,
) -> dict[str, Any]:
    """Run the demo; returns the summary figures.

    Without ``mqtt`` an embedded broker runs for the demo's length, with a
    generated account (printed once) that the gateway and the robot client use;
    ``mqtt_port=None`` asks for 1883 when free, 0 for any free port.
    """
    if mqtt is None:
        from awaremw.gateway.broker import EmbeddedBroker

        async with EmbeddedBroker(port=mqtt_port, anonymous=mqtt_anonymous) as broker:
            account = "anonymous access" if broker.anonymous else (
                f"account {broker.username!r}, password {broker.password} (this run only)"
            )  # fmt: skip
            print(f"embedded MQTT broker: mqtt://{broker.host}:{broker.port} {account}",
                  flush=True)  # fmt: skip
            return await run_demo(sc, duration, speed, broker.url, plain, robot_mqtt, secrets,
                                  web=web, fresh_broker=True, metrics=metrics)  # fmt: skip
    from awaremw.experiments import metrics as M
    from awaremw.experiments.client import Received
    from awaremw.experiments.realtime import RealtimeRun, RealtimeSettings, RunHooks
    from awaremw.experiments.snapshot import record_line as to_line
    from awaremw.experiments.snapshot import role_energy, snapshot_of
    from awaremw.protocol.events import MoteEvent
    from awaremw.security.redact import mask_url
    from awaremw.view.live import LiveView, PlainLog, View, describe, record_line
    from awaremw.view.snapshot import with_leds

    view: View = PlainLog(every=10.0) if plain else LiveView()
    dash = None
    if web is not None:
        from awaremw.view.web import dashboard_for

        dash = dashboard_for(sc.deployment, sc.world, robot_mqtt or mqtt, web, sc.name,
                             sc.tracking_group if sc.group_json else None)  # fmt: skip
        await dash.__aenter__()
        print(f"web dashboard: {dash.url}", flush=True)

    def tick(now: float, run: RealtimeRun) -> None:
        cores = run.cores()
        traffic, fwd = run.traffic(), run.forwarders()
        snap = snapshot_of(sc, run.recorder, now, run.live, traffic, forwarders=fwd)
        snap = with_leds(snap, cores)
        view.update(snap)
        if dash is not None:
            from awaremw.view.web import field_of

            energy = role_energy(sc, run.recorder, now, traffic, fwd)
            dash.update_field(now, field_of(snap.motes, cores), energy)

    def event(node: int, ev: MoteEvent, t: float) -> None:
        line = describe(node, ev, t)
        if line is not None:
            view.log(t, line)

    def record(r: Received) -> None:
        view.log(r.t, "robot got " + record_line(to_line(r)))

    run = RealtimeRun(
        sc,
        RealtimeSettings(speed=speed, mqtt=mqtt, fresh_broker=fresh_broker,
                         robot_mqtt=robot_mqtt, secrets=secrets, metrics=metrics),
        hooks=RunHooks(on_tick=tick, on_event=event, on_record=record),
    )
    end = sc.duration if duration is None else duration
    view.log(0.0, f"demo {sc.name}: {len(sc.deployment.nodes)} motes, {end:g} s at speed "
                  f"{speed:g} (MQTT {mask_url(mqtt)})")  # fmt: skip
    for line in waiting_lines(sc, end):
        view.log(0.0, line)
    view.start()
    try:
        result = await run.run(end)
    finally:
        view.stop()
        if dash is not None:
            await dash.__aexit__(None, None, None)
    rec = result.recorder
    gtype = sc.tracking_group if sc.group_json else None
    traffic = M.traffic(result.traffic, sc.sensors)
    out: dict[str, Any] = {
        "deployment": sc.name,
        "emulated_s": end,
        "speed": speed,
        "mqtt": None if run.broker_url is None else mask_url(run.broker_url),
        # Distinct records (channel, group, epoch), as the delivery ratio counts them;
        # at a handover or a merge two leaders may both close an epoch: "repeated".
        "records_received": len(rec.arrivals),
        "records_repeated": len(run.live.records) - len(rec.arrivals),
        "records_produced": len(rec.produced),
        "delivery_ratio": M.delivery_ratio(rec, end - 5.0),
        "groups": sorted(rec.group_ids(gtype, 0.0, end)) if gtype is not None else [],
        # ids that had members for at least two beacon periods (not a fringe mote's
        # group that yielded a moment later)
        "lasting_groups": sorted(M.lasting_group_ids(rec, gtype, 0.0, end, LASTING_S))
        if gtype is not None
        else [],
        "handovers": len(rec.handovers),
        "elections": len(rec.elections),
        "frames_per_mote": traffic.frames_tx,
        "energy_mj_per_mote": traffic.energy_mj,
        "errors": list(run.live.errors),
        # what the robot's client defined: none means no group can form, however long
        "group_types": sorted(sc.group_json),
        "channels": sorted(sc.channel_json),
    }
    if gtype is not None and sc.robot is not None and run.live.records:
        first = run.live.records[0]
        out["first_record_at_s"] = first.t
    return out


LASTING_S = 4.0  # two leader-beacon periods: shorter-lived ids are a fringe mote's transient


def waiting_lines(sc: Any, end: float) -> list[str]:
    """What the first seconds wait for (the map stays idle until a group forms)."""
    if not sc.group_json:
        return ["no group type defined by this deployment: the map shows the motes only"]
    types = ", ".join(map(str, sc.group_json))
    chans = ", ".join(map(str, sc.channel_json)) or "none"
    lines = [f"at t={sc.define_at:g} s the robot's client defines group type(s) {types} and "
             f"channel(s) {chans} over MQTT"]  # fmt: skip
    first = sc.robot_entry(sc.truth())
    what = f"the robot (mote {sc.robot}) to come into range" if sc.robot is not None else (
        "the condition to hold at a mote"
    )  # fmt: skip
    if first is None or first > end:
        lines.append(f"waiting for {what}: not expected within the {end:g} s run")
    else:
        lines.append(f"waiting for {what}: expected at t~{first:g} s (the map stays idle "
                     "until a group forms)")  # fmt: skip
    return lines


def summary_rows(s: dict[str, Any]) -> list[tuple[str, Any]]:
    rows: list[tuple[str, Any]] = [
        ("deployment", s["deployment"]),
        ("emulated time", f"{s['emulated_s']:g} s at speed {s['speed']:g}"),
        ("MQTT broker", s["mqtt"]),
        ("records received (MQTT)", s["records_received"]),
        ("records repeated (MQTT)", s.get("records_repeated", 0)),
        ("records produced (leaders)", s["records_produced"]),
        (
            "delivery ratio (produced > 5 s before the end)",
            "-" if s["delivery_ratio"] is None else f"{s['delivery_ratio']:.3f}",
        ),
        ("group ids seen", ", ".join(map(str, s["groups"])) or "none"),
        (
            f"group ids lasting >= {LASTING_S:g} s",
            ", ".join(map(str, s.get("lasting_groups", []))) or "none",
        ),
        ("handovers", s["handovers"]),
        ("leader elections", s["elections"]),
        ("frames sent per mote", f"{s['frames_per_mote']:.1f}"),
        ("radio energy per mote", f"{s['energy_mj_per_mote']:.1f} mJ"),
    ]
    if s.get("first_record_at_s") is not None:
        rows.append(("first record at", f"{s['first_record_at_s']:.1f} s"))
    if s["errors"]:
        rows.append(("errors", "; ".join(s["errors"])[:200]))
    return rows


def print_summary(s: dict[str, Any], plain: bool = False) -> None:
    rows = summary_rows(s)
    if plain:
        for k, v in rows:
            print(f"summary {k}: {v}")
        return
    t = Table(title="awaremw demo: summary", show_header=False)
    t.add_column(style="bold")
    t.add_column()
    for k, v in rows:
        t.add_row(k, str(v))
    Console().print(t)
