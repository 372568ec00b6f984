"""``awaremw experiment NAME [--out DIR] [--speed X] [--virtual]``: the paper's
section V, with figures and metrics against ground truth (docs/experiments.md).

Without ``--virtual`` the scenario runs in real time: the fleet over Zenoh,
the gateway with the embedded MQTT broker, records taken from an MQTT
subscriber (``--speed`` scales emulated time). ``--virtual`` runs the same
motes on the virtual clock, as fast as the CPU allows.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path
from typing import Any

from awaremw.cli.friendly import add_secrets_option, load_secrets, refuse
from awaremw.cli.helptext import add_verb
from awaremw.experiments import EXPERIMENTS, analysis, write_metrics
from awaremw.radio.mac import COLLISION_MODES, MAC_KINDS

REALTIME = ("romeo4r", "fire", "large")  # experiments that also run in real time over Zenoh


def register(sub: Any) -> None:
    p = add_verb(
        sub,
        "experiment",
        "run an experiment of the paper, with figures and metrics",
        "Experiments: " + ", ".join(sorted(EXPERIMENTS)) + ".\n\n"
        """\
The paper's section V, with figures and metrics against ground truth
(docs/experiments.md). Without --virtual the scenario runs in real time: the
fleet over Zenoh, the gateway with the embedded MQTT broker, records taken
from an MQTT subscriber (--speed scales emulated time). --virtual runs the
same motes on the virtual clock, as fast as the CPU allows; --seeds A-B runs
several seeds and reports their distribution.""",
        [
            "awaremw experiment romeo4r --out out/romeo4r",
            "awaremw experiment fire --speed 5",
            "awaremw experiment romeo4r --virtual --seeds 1-40 --jobs 2",
            "awaremw experiment city --virtual --seeds 1-10 --jobs 2",
        ],
    )
    p.add_argument(
        "name",
        metavar="NAME|FILE",
        help=f"which experiment ({', '.join(sorted(EXPERIMENTS))}), or a deployment file "
        "whose [experiment] analysis names one",
    )
    p.add_argument("--out", type=Path, default=None, help="output folder (default: out/NAME)")
    p.add_argument(
        "--speed", type=float, default=1.0, help="emulated seconds per wall second (real time)"
    )
    p.add_argument("--virtual", action="store_true", help="run on the virtual clock")
    p.add_argument("--deployment", default=None, help="another deployment file of the same shape")
    p.add_argument("--duration", type=float, default=None, help="emulated seconds to run")
    p.add_argument("--mqtt", default=None, help="broker URL (default: embedded broker)")
    p.add_argument(
        "--robot-mqtt",
        default=None,
        metavar="URL",
        help="the robot client's own broker account (default: the --mqtt URL)",
    )
    add_secrets_option(
        p,
        "authenticated radio frames and signed items (DIR from awaremw keys init); in "
        "real time also Zenoh with authentication and access control by role",
    )
    p.add_argument("--plain", action="store_true", help="log lines instead of a live view")
    p.add_argument(
        "--seeds",
        default=None,
        metavar="A-B",
        help="with --virtual: run every seed (A-B, or a comma list) and summarise (summary.json)",
    )
    p.add_argument("--jobs", type=int, default=1, help="parallel processes for --seeds")
    p.add_argument(
        "--mac",
        choices=MAC_KINDS,
        default=None,
        help="override the deployment's medium access (csma: 802.15.4 CSMA/CA; aloha)",
    )
    p.add_argument(
        "--collisions",
        choices=COLLISION_MODES,
        default=None,
        help="override the deployment's collision model (sinr: overlap and capture; none)",
    )
    p.add_argument(
        "--noise",
        default=None,
        help="override the deployment's noise: white, a shipped trace (meyer-heavy) or a file",
    )
    hv = p.add_mutually_exclusive_group()
    hv.add_argument(
        "--hardware-variance",
        dest="hardware_variance",
        action="store_true",
        default=None,
        help="override: per-mote TX power and noise floor offsets (docs/radio.md)",
    )
    hv.add_argument("--no-hardware-variance", dest="hardware_variance", action="store_false")
    p.add_argument(
        "--pcap",
        default=None,
        metavar="FILE",
        help="write the radio traffic to FILE (pcapng, IEEE 802.15.4; docs/capture.md)",
    )
    p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
    # wall_s and cpu_s count everything from here: loading the deployment,
    # building the motes, the run, the analysis and the figures.
    started = time.monotonic()
    cpu0 = time.process_time()
    if getattr(args, "verbose", 0) < 2:
        # The embedded broker logs every refused protocol probe at WARNING.
        logging.getLogger("amqtt").setLevel(logging.ERROR)
    from awaremw.experiments.scenario import load_scenario, scenario_of
    from awaremw.runtime.deployment import DeploymentError

    try:
        name = _experiment_of(args)
    except (DeploymentError, ValueError) as e:
        return refuse("awaremw experiment", e)
    out: Path = args.out or Path("out") / name
    try:
        sc = load_scenario(args.deployment or EXPERIMENTS[name][0])
    except DeploymentError as e:
        return refuse("awaremw experiment", e)
    try:
        medium = _medium(args)
    except ValueError as e:
        return refuse("awaremw experiment", e)
    if medium:
        from awaremw.experiments.seeds import with_medium

        try:
            sc = scenario_of(with_medium(sc.deployment, medium))
        except ValueError as e:
            return refuse("awaremw experiment", e)
    if args.speed <= 0:
        return refuse("awaremw experiment", "--speed must be > 0")
    if args.seeds is not None:
        if args.pcap is not None or args.secrets is not None:
            flag = "--pcap" if args.pcap is not None else "--secrets"
            return refuse("awaremw experiment", f"{flag} applies to one run, not --seeds")
        return _main_seeds(args, name, out)
    keys = None
    if args.secrets is not None:
        from awaremw.security.material import check_secrets, load_gateway_keys

        prog = "awaremw experiment"
        if args.virtual:  # the radio key and the signing pair, read once; no Zenoh configs
            if (keys := load_secrets(prog, args.secrets, load_gateway_keys)) is None:
                return 2
        elif load_secrets(prog, args.secrets, check_secrets) is None:
            return 2
    if args.virtual:
        import importlib

        from awaremw.experiments.virtual import VirtualRun

        run = VirtualRun(sc, keys=keys)
        prepare = getattr(importlib.import_module(EXPERIMENTS[name][1]), "prepare", None)
        if prepare is not None:
            prepare(run)
        capture = None
        if args.pcap is not None:
            from awaremw.radio.capture import Capture

            capture = run.net.tap = Capture.to_file(args.pcap)
        try:
            result = run.run(args.duration)
        finally:
            if capture is not None:
                capture.close()
                print(f"wrote {capture.packets} packets to {args.pcap}", file=sys.stderr)
    else:
        if name not in REALTIME:
            return refuse("awaremw experiment", f"{name} runs only with --virtual")
        import asyncio

        from awaremw.gateway.mqtt import mqtt_problem

        for url in dict.fromkeys(u for u in (args.mqtt, args.robot_mqtt) if u is not None):
            if (why := asyncio.run(mqtt_problem(url))) is not None:
                print(f"awaremw experiment: {why}", file=sys.stderr)
                return 1
        from awaremw.experiments.realtime import run_realtime

        result = run_realtime(
            sc,
            speed=args.speed,
            duration=args.duration,
            mqtt=args.mqtt,
            plain=args.plain,
            robot_mqtt=args.robot_mqtt,
            secrets=args.secrets,
            pcap=args.pcap,
        )
    metrics = analysis(name)(result, out)
    metrics["mac"] = sc.deployment.mac
    metrics["collisions"] = sc.deployment.collisions
    metrics["radio_settings"] = sc.deployment.radio_settings.describe()
    metrics["wall_s"] = round(time.monotonic() - started, 2)
    metrics["cpu_s"] = round(time.process_time() - cpu0, 2)
    if metrics.get("duration_s"):
        metrics["speedup"] = round(float(metrics["duration_s"]) / max(metrics["wall_s"], 1e-3), 2)
    from awaremw.security.redact import redact

    metrics["command"] = redact(
        " ".join(["awaremw", "experiment", *sys.argv[2:]])
        if sys.argv[1:2] == ["experiment"]
        else f"awaremw experiment {name}"
    )
    path = write_metrics(out, metrics)
    print(json.dumps(metrics, indent=2))
    print(f"wrote {path} and the figures in {out}/", file=sys.stderr)
    return 0


def _main_seeds(args: argparse.Namespace, name: str, out: Path) -> int:
    from awaremw.experiments.seeds import SeedSpecError, parse_seeds, run_seeds

    if not args.virtual:
        return refuse("awaremw experiment", "--seeds needs --virtual")
    if args.jobs < 1:
        return refuse("awaremw experiment", "--jobs must be >= 1")
    try:
        seeds = parse_seeds(args.seeds)
    except SeedSpecError as e:
        return refuse("awaremw experiment", e)
    try:
        medium = _medium(args)
    except ValueError as e:
        return refuse("awaremw experiment", e)

    def progress(m: dict[str, Any]) -> None:
        print(
            f"seed {m['seed']}: F1 {m['membership_f1']:.3f}, ids {m['distinct_group_ids']}",
            file=sys.stderr,
        )

    started = time.monotonic()
    summary = run_seeds(
        name, seeds, out, args.jobs, args.deployment, args.duration, progress, medium
    )
    summary["wall_s"] = round(time.monotonic() - started, 2)
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n", encoding="utf-8")
    print(json.dumps(summary, indent=2))
    print(f"wrote {out}/summary.json, {out}/seeds.png and seed-*/metrics.json", file=sys.stderr)
    return 0


def _experiment_of(args: argparse.Namespace) -> str:
    """The experiment to run: the positional is a name (``romeo4r``), or a
    deployment file whose ``[experiment] analysis`` names one (then it is the
    deployment, and ``--deployment`` must not be given too)."""
    from awaremw.experiments.scenario import load_scenario
    from awaremw.runtime.deployment import find_deployment

    given: str = args.name
    if given in EXPERIMENTS:
        return given
    known = ", ".join(sorted(EXPERIMENTS))
    try:
        path = find_deployment(given)
    except ValueError:
        raise ValueError(
            f"{given!r} is no experiment ({known}) and no deployment file"
        ) from None
    if args.deployment is not None:
        raise ValueError(f"give the deployment once: {given} or --deployment {args.deployment}")
    settings = load_scenario(path).deployment.experiment
    name = settings.get("analysis")
    if name not in EXPERIMENTS:
        raise ValueError(
            f"{path}: to run it as an experiment, its [experiment] table needs "
            f"analysis = one of {known}" + (f" (it has {name!r})" if name is not None else "")
        )
    args.deployment = str(path)
    return str(name)


def _medium(args: argparse.Namespace) -> dict[str, str]:
    """The deployment keys ``--mac``, ``--collisions``, ``--noise`` and
    ``--hardware-variance`` override (only those given). A trace file's path is
    made absolute here, so that every seed's process finds it."""
    out = {k: v for k in ("mac", "collisions") if (v := getattr(args, k, None)) is not None}
    noise = getattr(args, "noise", None)
    if noise is not None:
        from awaremw.radio.noise import SHIPPED, load_trace

        if noise != "white" and noise not in SHIPPED:
            noise = str(Path(noise).resolve())
            load_trace(noise)  # NoiseTraceError (a ValueError) names the problem
        out["noise"] = noise
    hv = getattr(args, "hardware_variance", None)
    if hv is not None:
        out["hardware_variance"] = "true" if hv else "false"
    return out
