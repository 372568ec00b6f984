"""Abuse and faults, as an attacker or bad luck would bring them (issue 22's table).

    python benchmarks/abuse.py mqtt-burst  [--count 20000] [--seeds 1-3] [--json OUT] [--bound S]
    python benchmarks/abuse.py hbn-burst   [--count 50000] [--seeds 1-3] [--json OUT] [--bound S]
    python benchmarks/abuse.py kill-worker [--seeds 1-3] [--json OUT]
    python benchmarks/abuse.py restart-fleet [--seeds 1-3] [--json OUT]

Real processes, as a user runs them: ``awaremw router``, ``awaremw fleet
grid_small --without-kind gateway`` and ``awaremw gateway grid_small --mqtt
...`` on loopback, and Mosquitto (Debian package ``mosquitto``) on a free port
with its default queue bounds (``max_queued_messages 1000``, ``max_inflight_messages
20``), anonymous, no persistence.

* ``mqtt-burst``: ``--count`` retained redefinitions of channels 1-8 (random
  period 1.0-5.0 s and aggregate, seeded), published over MQTT as fast as the
  broker acknowledges them (QoS 1, 200 in flight). Then, every 0.5 s, every
  mote's definitions are read back (``awaremw fleet-ctl items``) and compared
  with the broker's retained value of each channel. Verdict: all equal within
  10 s after the last acknowledgement, and every message the gateway could not
  take is on ``aware/errors`` (``input_overflow`` reports == the gateway's
  ``inbox.dropped``).
* ``hbn-burst``: the same with ``--count`` puts on ``aware/hbn/def/channel/<c>``
  (Zenoh, congestion control ``block``: the publisher loses nothing), compared
  with the last value put on each key; reports on ``aware/hbn/errors``.
* ``kill-worker``: ``awaremw fleet --processes 2``; once records come from
  groups in both stripes, ``kill -9`` of worker ``w1`` at a random moment
  (seeded). Verdict: ``fleet-ctl stats`` shows it restarted, records come from
  both stripes again within 30 s, the fleet never exits.
* ``restart-fleet``: once records flow, the peers run on for 20-40 s (seeded);
  then the fleet is killed and started again under the running gateway.
  Verdict: records again within 30 s (the new fleet joins the peers' time).

Each seed is one run from scratch; the summary gives mean and spread over the
seeds. Timings depend on the machine's load (this one has 2 cores shared).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import random
import shutil
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import aiomqtt
import zenoh

from awaremw.cli.fleet import control_query
from awaremw.gateway.schema import Limits, is_copy, parse_channel
from awaremw.runtime.deployment import load
from awaremw.runtime.partition import stripes
from awaremw.runtime.zenoh_session import SessionSettings, close_quietly, open_session

AW = [sys.executable, "-m", "awaremw"]
DEPLOYMENT = "grid_small"
CHANNELS = range(1, 9)  # the motes hold 8 channels (MiddlewareConfig.max_channels)
AGGS = ("avg", "min", "max", "sum", "count")
CONVERGE_S = 10.0  # the bound the docs state, after the last message (--bound)
GROUP_ALL = {"conditions": [{"attr": "x", "op": ">", "value": 3}]}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def mosquitto_binary() -> str:
    for p in (shutil.which("mosquitto"), "/usr/sbin/mosquitto"):
        if p and os.access(p, os.X_OK):
            return p
    sys.exit("abuse: needs the mosquitto broker (apt-get install mosquitto)")


def seeds(text: str) -> list[int]:
    a, _, b = text.partition("-")
    return list(range(int(a), int(b or a) + 1))


def channel_doc(rng: random.Random) -> dict[str, Any]:
    return {
        "attr": "temperature",
        "group_type": 1,
        "group_id": "*",
        "period_s": round(1.0 + rng.randrange(41) / 10, 1),
        "agg": rng.choice(AGGS),
    }


def wire_of(channel: int, payload: bytes) -> list[Any] | None:
    """What a mote holds for a channel defined by ``payload`` (the gateway's schema)."""
    d = parse_channel(str(channel), payload, Limits())
    return None if d.body is None else d.body.to_wire()


class Run:
    """Router, Mosquitto, fleet and gateway of one run, in a scratch directory."""

    def __init__(self, processes: int = 1) -> None:
        self.work = Path(tempfile.mkdtemp(prefix="awaremw-abuse-"))
        self.port = free_port()
        self.ep = f"tcp/127.0.0.1:{free_port()}"
        self.processes = processes
        self.procs: dict[str, subprocess.Popen[bytes]] = {}
        self.logs: dict[str, Any] = {}
        self.fleet_cmd = [*AW, "fleet", DEPLOYMENT, "--without-kind", "gateway", "--plain",
                          "--connect", self.ep, "--processes", str(processes),
                          "--progress", "60"]  # fmt: skip

    def spawn(self, name: str, cmd: list[str]) -> None:
        if name in self.logs:
            self.logs[name].close()  # started again: one log, appended
        self.logs[name] = open(self.work / f"{name}.log", "ab")  # noqa: SIM115
        self.procs[name] = subprocess.Popen(cmd, stdout=self.logs[name], stderr=subprocess.STDOUT)

    def log(self, name: str) -> str:
        return (self.work / f"{name}.log").read_text(errors="replace")

    def alive(self, name: str) -> bool:
        return self.procs[name].poll() is None

    @contextlib.asynccontextmanager
    async def up(self) -> AsyncIterator[Run]:
        (self.work / "mosquitto.conf").write_text(
            f"listener {self.port} 127.0.0.1\nallow_anonymous true\npersistence false\n"
            "max_queued_messages 1000\nmax_inflight_messages 20\n"
        )
        try:
            self.spawn("broker", [mosquitto_binary(), "-c", str(self.work / "mosquitto.conf")])
            self.spawn("router", [*AW, "router", "--listen", self.ep])
            await wait_port(self.port, 10)
            await wait_port(int(self.ep.rsplit(":", 1)[1]), 30)
            self.spawn("fleet", self.fleet_cmd)
            await until(lambda: len(fleet_replies(self.ep, "list")) >= self.processes, 60, "fleet")
            self.spawn("gateway", [*AW, "gateway", DEPLOYMENT, "--connect", self.ep,
                                   "--mqtt", f"mqtt://127.0.0.1:{self.port}",
                                   "--state-dir", str(self.work / "state")])  # fmt: skip
            async with aiomqtt.Client("127.0.0.1", self.port) as c:
                await c.subscribe("aware/gateway/status", qos=1)
                async with asyncio.timeout(60):
                    async for m in c.messages:
                        if m.payload == b"online":
                            break
            yield self
        finally:
            for p in self.procs.values():
                if p.poll() is None:
                    p.send_signal(signal.SIGTERM)
            for p in self.procs.values():
                try:
                    p.wait(20)
                except subprocess.TimeoutExpired:
                    p.kill()
            for f in self.logs.values():
                f.close()


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


async def until(cond: Callable[[], object], timeout: float, what: str) -> float:
    """Poll ``cond`` (run in a thread: it may query Zenoh) until true; seconds taken."""
    t0 = time.monotonic()
    while not await asyncio.to_thread(cond):
        if time.monotonic() - t0 > timeout:
            raise TimeoutError(f"not within {timeout} s: {what}")
        await asyncio.sleep(0.5)
    return time.monotonic() - t0


def fleet_replies(ep: str, op: str) -> list[dict[str, Any]]:
    try:
        return control_query([ep], "aware", {"op": op}, 2.0)
    except zenoh.ZError:
        return []


def mismatches(ep: str, expected: dict[int, list[Any] | None]) -> tuple[int, int]:
    """(motes read back, motes whose channels differ from ``expected``)."""
    motes = bad = 0
    for reply in fleet_replies(ep, "items"):
        for items in reply.get("items", {}).values():
            motes += 1
            held = {c: (items.get(f"channel/{c}") or [None, None])[1] for c in CHANNELS}
            bad += any(held[c] != expected.get(c) for c in CHANNELS)
    return motes, bad


def gateway_holds(ep: str, expected: dict[int, list[Any] | None]) -> bool:
    """Whether the gateway's definitions (its HBN queryable) are ``expected``."""
    session = open_session(SessionSettings("client", (ep,)))
    try:
        held: dict[int, list[Any] | None] = {}
        for r in session.get("aware/hbn/def/channel/*", timeout=2.0):
            if r.ok is None:
                continue
            doc = json.loads(r.ok.payload.to_bytes())
            doc.pop("version", None)
            c = int(str(r.ok.key_expr).rsplit("/", 1)[1])
            held[c] = wire_of(c, json.dumps(doc).encode())
        return all(held.get(c) == w for c, w in expected.items())
    finally:
        close_quietly(session)


class Errors:
    """Counts what arrives on an errors topic, by code."""

    def __init__(self) -> None:
        self.by_code: dict[str, int] = {}

    def add(self, payload: bytes) -> None:
        try:
            code = str(json.loads(payload).get("code"))
        except (ValueError, AttributeError):
            code = "?"
        self.by_code[code] = self.by_code.get(code, 0) + 1


async def _collect_errors(port: int, errors: Errors, ready: asyncio.Event) -> None:
    async with aiomqtt.Client("127.0.0.1", port, max_queued_incoming_messages=0) as c:
        await c.subscribe("aware/errors", qos=1)
        ready.set()
        async for m in c.messages:
            errors.add(m.payload if isinstance(m.payload, bytes) else b"")


async def _retained(port: int, topic: str, n: int) -> dict[str, bytes]:
    out: dict[str, bytes] = {}
    async with aiomqtt.Client("127.0.0.1", port) as c:
        await c.subscribe(topic, qos=1)
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(5):
                async for m in c.messages:
                    if m.retain and isinstance(m.payload, bytes):
                        out[m.topic.value] = m.payload
                    if len(out) >= n:
                        break
    return out


# --------------------------------------------------------------------------- bursts


async def mqtt_burst(seed: int, count: int, bound: float) -> dict[str, Any]:
    rng = random.Random(seed)
    async with Run().up() as run:
        errors, ready = Errors(), asyncio.Event()
        collector = asyncio.create_task(_collect_errors(run.port, errors, ready))
        await ready.wait()
        async with aiomqtt.Client("127.0.0.1", run.port) as op:
            op.pending_calls_threshold = 250
            await op.publish("aware/def/group/1", json.dumps(GROUP_ALL), qos=1, retain=True)
            t0 = time.monotonic()
            pending = []
            last: dict[int, str] = {}
            for _ in range(count):
                c = rng.choice(CHANNELS)
                last[c] = doc = json.dumps(channel_doc(rng))
                pending.append(op.publish(f"aware/def/channel/{c}", doc, qos=1, retain=True))
                if len(pending) == 200:
                    await asyncio.gather(*pending)
                    pending.clear()
            await asyncio.gather(*pending)
            t_last = time.monotonic()
        # What the client said last on each topic (one connection: in order). The
        # broker's retained copy is the gateway's to set (One truth), not the target.
        expected = {c: wire_of(c, p.encode()) for c, p in last.items()}
        out = await _verdict(
            run, t0, t_last, count, expected, errors, collector, "mqtt", bound=bound
        )
        # One truth: once converged, the broker retains the gateway's copy (with its
        # version) of what the client said last on each topic.
        retained = await _retained(run.port, "aware/def/channel/#", len(expected))
        copies = {int(t.rsplit("/", 1)[1]): p for t, p in retained.items()}
        out["retained_agrees"] = all(
            c in copies and is_copy(copies[c]) and wire_of(c, copies[c]) == w
            for c, w in expected.items()
        )
        out["ok"] = out["ok"] and out["retained_agrees"]
        return out


async def hbn_burst(seed: int, count: int, bound: float) -> dict[str, Any]:
    rng = random.Random(seed)
    async with Run().up() as run:
        errors = Errors()
        session = await asyncio.to_thread(open_session, SessionSettings("client", (run.ep,)))
        loop = asyncio.get_running_loop()
        sub = session.declare_subscriber(
            "aware/hbn/errors",
            lambda s: loop.call_soon_threadsafe(errors.add, s.payload.to_bytes()),
        )
        try:
            session.put("aware/hbn/def/group/1", json.dumps(GROUP_ALL))
            last: dict[int, bytes] = {}

            def burst() -> tuple[float, float]:
                t0 = time.monotonic()
                for _ in range(count):
                    c = rng.choice(CHANNELS)
                    last[c] = json.dumps(channel_doc(rng)).encode()
                    session.put(f"aware/hbn/def/channel/{c}", last[c],
                                congestion_control=zenoh.CongestionControl.BLOCK)  # fmt: skip
                return t0, time.monotonic()

            t0, t_last = await asyncio.to_thread(burst)
            expected = {c: wire_of(c, p) for c, p in last.items()}
            return await _verdict(
                run, t0, t_last, count, expected, errors, None, "hbn", session, bound
            )
        finally:
            sub.undeclare()  # type: ignore[no-untyped-call]
            await asyncio.to_thread(close_quietly, session)


async def _verdict(
    run: Run,
    t0: float,
    t_last: float,
    count: int,
    expected: dict[int, list[Any] | None],
    errors: Errors,
    collector: asyncio.Task[None] | None,
    via: str,
    session: zenoh.Session | None = None,
    bound: float = CONVERGE_S,
) -> dict[str, Any]:
    converged: float | None = None
    gateway_s: float | None = None  # when the gateway's own definitions were the expected ones
    last_seen = (0, 0)
    deadline = t_last + 60.0
    while time.monotonic() < deadline:
        if gateway_s is None and await asyncio.to_thread(gateway_holds, run.ep, expected):
            gateway_s = time.monotonic() - t_last
        last_seen = await asyncio.to_thread(mismatches, run.ep, expected)
        if last_seen[0] > 0 and last_seen[1] == 0:
            converged = time.monotonic() - t_last
            break
        await asyncio.sleep(0.5)
    await asyncio.sleep(1.0)  # errors still on their way
    stats = await _gateway_stats(run.port, via, session)
    if collector is not None:
        collector.cancel()
        with contextlib.suppress(asyncio.CancelledError, aiomqtt.MqttError):
            await collector
    log = run.log("gateway")
    inbox = stats.get("inbox", {})
    return {
        "messages": count,
        "publish_s": round(t_last - t0, 2),
        "rate_per_s": round(count / max(t_last - t0, 1e-9)),
        "motes_read_back": last_seen[0],
        "motes_differing": last_seen[1],
        "converged_s": None if converged is None else round(converged, 2),
        "gateway_s": None if gateway_s is None else round(gateway_s, 2),
        "ok": converged is not None
        and converged <= bound
        and errors.by_code.get("input_overflow", 0) >= inbox.get("dropped", 0),
        "inbox": inbox,
        "reconciles": stats.get("reconciles"),
        "errors_by_code": errors.by_code,
        "gateway_alive": run.alive("gateway"),
        "fleet_alive": run.alive("fleet"),
        "gateway_log_lines": log.count("\n"),
        "gateway_log_tracebacks": log.count("Traceback"),
        "gateway_log_discarding": log.count("Discarding message"),
    }


async def _gateway_stats(port: int, via: str, session: zenoh.Session | None) -> dict[str, Any]:
    if via == "hbn" and session is not None:

        def ask() -> dict[str, Any]:
            for r in session.get("aware/hbn/gateway/stats", timeout=3.0):
                if r.ok is not None:
                    doc: dict[str, Any] = json.loads(r.ok.payload.to_bytes())
                    return dict(doc.get("hbn", {}))
            return {}

        return await asyncio.to_thread(ask)
    got = await _retained(port, "aware/gateway/stats", 1)
    return dict(json.loads(next(iter(got.values())))) if got else {}


# --------------------------------------------------------------------------- kill -9


async def kill_worker(seed: int) -> dict[str, Any]:
    rng = random.Random(seed)
    dep = load(DEPLOYMENT)
    west, _ = stripes(dep, 2)
    stripe_of = {n.id: 0 if west(n) else 1 for n in dep.nodes}
    async with Run(processes=2).up() as run:
        got: list[tuple[float, int]] = []  # (wall, stripe of the record's leader)
        ready = asyncio.Event()

        async def records() -> None:
            async with aiomqtt.Client("127.0.0.1", run.port, max_queued_incoming_messages=0) as c:
                await c.subscribe("aware/data/#", qos=0)
                ready.set()
                async for m in c.messages:
                    doc = json.loads(m.payload if isinstance(m.payload, bytes) else b"{}")
                    got.append((time.monotonic(), stripe_of.get(int(doc.get("leader", -1)), -1)))

        task = asyncio.create_task(records())
        await ready.wait()
        cut = west.hi
        async with aiomqtt.Client("127.0.0.1", run.port) as op:
            for gt, cond in ((1, {"attr": "x", "op": "<", "value": cut - 6}),
                             (2, {"attr": "x", "op": ">", "value": cut + 6})):  # fmt: skip
                await op.publish(f"aware/def/group/{gt}", json.dumps({"conditions": [cond]}),
                                 qos=1, retain=True)  # fmt: skip
                ch = {"attr": "temperature", "group_type": gt, "group_id": "*",
                      "period_s": 2.0, "agg": "avg"}  # fmt: skip
                await op.publish(f"aware/def/channel/{gt}", json.dumps(ch), qos=1, retain=True)

        def both_since(t: float) -> Callable[[], bool]:
            return lambda: {s for w, s in got if w > t} >= {0, 1}

        await until(both_since(0.0), 120, "records from both stripes")
        await asyncio.sleep(rng.uniform(0.0, 5.0))  # a random moment
        snaps = {d["fleet"]: d["snapshot"] for d in fleet_replies(run.ep, "stats")}
        os.kill(int(snaps["w1"]["pid"]), signal.SIGKILL)
        killed = time.monotonic()

        def restarted() -> bool:
            s = {d["fleet"]: d["snapshot"] for d in fleet_replies(run.ep, "stats")}
            return "w1" in s and s["w1"]["restarts"] == 1

        await until(restarted, 60, "w1 restarted")
        restart_s = time.monotonic() - killed  # polled every 0.5 s: an upper bound
        await until(both_since(killed + 1.0), 60, "records from both stripes again")
        # Both stripes again: the later of each stripe's first record after the kill.
        records_s = max(min(w for w, s in got if w > killed + 1.0 and s == k) for k in (0, 1))
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError, aiomqtt.MqttError):
            await task
        alive = run.alive("fleet")
        return {
            "restarted_s": round(restart_s, 2),
            "records_both_stripes_s": round(records_s - killed, 2),
            "fleet_alive": alive,
            "ok": alive and records_s - killed <= 30.0,
        }


# --------------------------------------------------------------------------- restart


async def restart_fleet(seed: int) -> dict[str, Any]:
    """The fleet killed and started again under the running gateway (issue 22: no
    definitions and no records for ~110 s): how long until records come back."""
    rng = random.Random(seed)
    async with Run().up() as run:
        got: list[float] = []  # wall times of records
        ready = asyncio.Event()

        async def records() -> None:
            async with aiomqtt.Client("127.0.0.1", run.port, max_queued_incoming_messages=0) as c:
                await c.subscribe("aware/data/#", qos=0)
                ready.set()
                async for _ in c.messages:
                    got.append(time.monotonic())

        task = asyncio.create_task(records())
        await ready.wait()
        async with aiomqtt.Client("127.0.0.1", run.port) as op:
            ch = {"attr": "temperature", "group_type": 1, "group_id": "*", "period_s": 2.0}
            await op.publish("aware/def/group/1", json.dumps(GROUP_ALL), qos=1, retain=True)
            await op.publish("aware/def/channel/1", json.dumps(ch), qos=1, retain=True)
        started = time.monotonic()
        await until(lambda: bool(got), 120, "records")
        # The peers run a while (a random span): a new fleet would count from 0 behind them.
        await asyncio.sleep(rng.uniform(20.0, 40.0))
        uptime = time.monotonic() - started
        run.procs["fleet"].kill()
        run.procs["fleet"].wait(10)
        restarted = time.monotonic()
        run.spawn("fleet", run.fleet_cmd)
        await until(lambda: any(w > restarted for w in got), 120, "records after the restart")
        records_s = min(w for w in got if w > restarted) - restarted
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError, aiomqtt.MqttError):
            await task
        joined = "joining it" in run.log("fleet")
        return {
            "peers_ahead_s": round(uptime, 1),
            "records_after_restart_s": round(records_s, 2),
            "clock_joined": joined,
            "gateway_alive": run.alive("gateway"),
            "ok": records_s <= 30.0 and run.alive("gateway"),
        }


# --------------------------------------------------------------------------- main


def summary(runs: list[dict[str, Any]], key: str) -> dict[str, float] | None:
    xs = [r[key] for r in runs if isinstance(r.get(key), int | float)]
    if not xs:
        return None
    return {
        "mean": round(statistics.fmean(xs), 2),
        "min": round(min(xs), 2),
        "max": round(max(xs), 2),
        "stdev": round(statistics.stdev(xs), 2) if len(xs) > 1 else 0.0,
    }


async def main_async(args: argparse.Namespace) -> dict[str, Any]:
    runs = []
    for seed in seeds(args.seeds):
        match args.attack:
            case "mqtt-burst":
                r = await mqtt_burst(seed, args.count or 20_000, args.bound)
            case "hbn-burst":
                r = await hbn_burst(seed, args.count or 50_000, args.bound)
            case "restart-fleet":
                r = await restart_fleet(seed)
            case _:
                r = await kill_worker(seed)
        r["seed"] = seed
        print(json.dumps(r), file=sys.stderr, flush=True)
        runs.append(r)
    keys = {
        "mqtt-burst": ("converged_s", "rate_per_s"),
        "hbn-burst": ("converged_s", "rate_per_s"),
        "kill-worker": ("restarted_s", "records_both_stripes_s"),
        "restart-fleet": ("records_after_restart_s",),
    }[args.attack]
    return {
        "attack": args.attack,
        "runs": runs,
        "ok_fraction": sum(bool(r["ok"]) for r in runs) / len(runs),
        **{k: summary(runs, k) for k in keys},
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("attack", choices=("mqtt-burst", "hbn-burst", "kill-worker", "restart-fleet"))
    ap.add_argument("--count", type=int, default=None, help="messages in a burst")
    ap.add_argument("--seeds", default="1-3", help="A-B: one run per seed")
    ap.add_argument("--json", type=Path, help="also write the result to this file")
    ap.add_argument(
        "--bound",
        type=float,
        default=CONVERGE_S,
        metavar="S",
        help=f"bursts: every mote holds the final definitions within S s ({CONVERGE_S:g})",
    )
    args = ap.parse_args()
    result = asyncio.run(main_async(args))
    text = json.dumps(result, indent=2)
    print(text)
    if args.json:
        args.json.write_text(text + "\n")
    sys.exit(0 if result["ok_fraction"] == 1.0 else 1)


if __name__ == "__main__":
    main()
