"""Soak: a fleet and a gateway at speed 5 for a long while; resident memory every minute.

    python benchmarks/soak.py [--minutes 30] [--warmup 5] [--speed 5] [--deployment grid_small]
                              [--interval 60] [--json OUT]

Real processes, as a user runs them: ``awaremw fleet DEPLOYMENT --without-kind
gateway`` and ``awaremw gateway DEPLOYMENT`` joined over Zenoh on loopback,
the gateway bridged to a Mosquitto broker on a free port (anonymous, started
here; Debian package ``mosquitto``). A client defines a group over every
sensing mote ("x > 3") and a 2 s AVG channel on it, then counts the records.

Every ``--interval`` seconds the resident set size (``VmRSS`` of
``/proc/PID/status``) of the fleet and of the gateway is sampled and printed.
The verdict is the growth of each after the warm-up: the largest sample after
``--warmup`` minutes minus the sample at ``--warmup`` minutes (target: under
5 MB over the next 25 minutes). The JSON keeps every sample.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import aiomqtt

GROUP = {"conditions": [{"attr": "x", "op": ">", "value": 3}]}
CHANNEL = {"attr": "temperature", "group_type": 1, "group_id": "*", "period_s": 2.0, "agg": "avg"}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def rss_kb(pid: int) -> int:
    """Resident set size of a live process, in KiB (Linux)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise RuntimeError(f"no VmRSS for pid {pid}")


def mosquitto_binary() -> str:
    for p in (shutil.which("mosquitto"), "/usr/sbin/mosquitto"):
        if p and os.access(p, os.X_OK):
            return p
    sys.exit("soak: needs the mosquitto broker (apt-get install mosquitto)")


async def wait_port(port: int, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while True:
        try:
            _, w = await asyncio.open_connection("127.0.0.1", port)
            w.close()
            return
        except OSError:
            if time.monotonic() > deadline:
                raise TimeoutError(f"nothing listens on port {port}") from None
            await asyncio.sleep(0.1)


async def count_records(port: int, counter: list[int], ready: asyncio.Event) -> None:
    async with aiomqtt.Client("127.0.0.1", port, identifier="soak-client") as mqtt:
        await mqtt.subscribe("aware/data/#", qos=1)
        await mqtt.publish("aware/def/group/1", json.dumps(GROUP), qos=1, retain=True)
        await mqtt.publish("aware/def/channel/1", json.dumps(CHANNEL), qos=1, retain=True)
        ready.set()
        async for _ in mqtt.messages:
            counter[0] += 1


async def soak(args: argparse.Namespace) -> dict[str, Any]:
    work = Path(tempfile.mkdtemp(prefix="awaremw-soak-"))
    port, zport = free_port(), free_port()
    (work / "mosquitto.conf").write_text(
        f"listener {port} 127.0.0.1\nallow_anonymous true\npersistence false\n"
    )
    procs: dict[str, subprocess.Popen[bytes]] = {}
    logs = {name: open(work / f"{name}.log", "wb") for name in ("broker", "fleet", "gateway")}  # noqa: SIM115

    def spawn(name: str, cmd: list[str]) -> None:
        procs[name] = subprocess.Popen(cmd, stdout=logs[name], stderr=subprocess.STDOUT)

    aw = [sys.executable, "-m", "awaremw"]
    ep = f"tcp/127.0.0.1:{zport}"
    speed = str(args.speed)
    spawn("broker", [mosquitto_binary(), "-c", str(work / "mosquitto.conf")])
    spawn("fleet", [*aw, "fleet", args.deployment, "--without-kind", "gateway", "--plain",
                    "--speed", speed, "--listen", ep, "--progress", "60"])  # fmt: skip
    records = [0]
    samples: list[dict[str, Any]] = []
    try:
        await wait_port(port, 10)
        await wait_port(zport, 30)
        mqtt_url = f"mqtt://127.0.0.1:{port}"
        spawn("gateway", [*aw, "gateway", args.deployment, "--connect", ep, "--speed", speed,
                          "--mqtt", mqtt_url, "--state-dir", str(work / "state")])  # fmt: skip
        ready = asyncio.Event()
        counter = asyncio.create_task(count_records(port, records, ready))
        await asyncio.wait_for(ready.wait(), 30)
        t0 = time.monotonic()
        n_samples = int(args.minutes * 60 / args.interval)
        for i in range(n_samples + 1):
            await asyncio.sleep(max(0.0, t0 + i * args.interval - time.monotonic()))
            for name in ("fleet", "gateway"):
                if procs[name].poll() is not None:
                    raise RuntimeError(f"{name} exited with {procs[name].returncode} (log: {work})")
            s = {
                "minute": round(i * args.interval / 60, 2),
                "fleet_rss_mb": rss_kb(procs["fleet"].pid) / 1024,
                "gateway_rss_mb": rss_kb(procs["gateway"].pid) / 1024,
                "records": records[0],
            }
            samples.append(s)
            print(
                f"minute {s['minute']:6.2f}: fleet {s['fleet_rss_mb']:7.1f} MB   "
                f"gateway {s['gateway_rss_mb']:7.1f} MB   records {records[0]}",
                file=sys.stderr,
                flush=True,
            )
            if counter.done():
                counter.result()  # raises the client's error
        counter.cancel()
        with contextlib.suppress(asyncio.CancelledError, aiomqtt.MqttError):
            await counter
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        for p in procs.values():
            try:
                p.wait(20)
            except subprocess.TimeoutExpired:
                p.kill()
        for f in logs.values():
            f.close()
    warm = [s for s in samples if s["minute"] >= args.warmup]
    growth = {
        name: max(s[f"{name}_rss_mb"] for s in warm) - warm[0][f"{name}_rss_mb"]
        for name in ("fleet", "gateway")
    }
    return {
        "deployment": args.deployment,
        "speed": args.speed,
        "minutes": args.minutes,
        "warmup_minutes": args.warmup,
        "interval_s": args.interval,
        "fleet_growth_mb": round(growth["fleet"], 2),
        "gateway_growth_mb": round(growth["gateway"], 2),
        "records": records[0],
        "samples": samples,
        "logs": str(work),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=int, default=30)
    ap.add_argument("--warmup", type=int, default=5, help="minutes before the growth is measured")
    ap.add_argument("--speed", type=float, default=5.0)
    ap.add_argument("--deployment", default="grid_small")
    ap.add_argument("--interval", type=float, default=60.0, help="seconds between samples")
    ap.add_argument("--json", type=Path, help="also write the result to this file")
    args = ap.parse_args()
    if not 0 <= args.warmup < args.minutes:
        ap.error("--warmup must be below --minutes")
    result = asyncio.run(soak(args))
    text = json.dumps(result, indent=2)
    print(text)
    if args.json:
        args.json.write_text(text + "\n")
    ok = result["records"] > 0
    sys.exit(0 if ok else 1)


if __name__ == "__main__":
    main()
