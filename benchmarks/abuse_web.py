"""Abuse of the web dashboard: thousands of half-open connections while the
fleet and the gateway run in the same process.

    python benchmarks/abuse_web.py [--connections 20000] [--attack-s 60] [--speed 1] [--json OUT]

Real processes: ``awaremw demo --web 127.0.0.1:PORT --plain`` (fleet, gateway,
embedded MQTT broker and dashboard in one process: the case where the web
server's sockets compete with the emulation's), records counted by
``mosquitto_sub`` on ``aware/data/#``. A group over every lit mote and a 1 s
COUNT channel on it are defined through the dashboard's own API (its token,
same origin), so records flow steadily.

The attack, from ``--workers`` processes (each with ``ulimit -n`` raised to
the hard limit, so together they exceed one process's): keep ``--connections``
TCP connections open to the dashboard, each sending an unfinished request
header and nothing more; every connection the server closes is replaced at
once. Sampled every 2 s: the demo alive, its resident memory
(``VmRSS``), its open file descriptors, records received. After the attack:
how long until the dashboard answers again, and the RSS 20 s later.

Verdict (exit 1 otherwise): the demo never exits, records arrive in every
10 s window of the attack, the demo's descriptors stay under its start plus
the dashboard's connection cap plus a margin, and the RSS after the attack is
within 20 MB of its start.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import json
import multiprocessing
import os
import re
import resource
import select
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path
from typing import Any

from awaremw.view.guard import MAX_CONNECTIONS

GROUP = {"conditions": [{"attr": "light", "op": ">", "value": 0}], "hysteresis": 1}
CHANNEL = {"attr": "temperature", "group_type": 2, "group_id": "*", "period_s": 1.0, "agg": "count"}
PARTIAL = b"GET /api/state HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: "  # never finished
FD_MARGIN = 64  # descriptors the demo may open beyond start + the dashboard's cap
RSS_MARGIN_KB = 20 * 1024


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def rss_kb(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise RuntimeError(f"no VmRSS for pid {pid}")


def fds(pid: int) -> int:
    return len(os.listdir(f"/proc/{pid}/fd"))


def raise_nofile() -> int:
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft < hard:
        resource.setrlimit(resource.RLIMIT_NOFILE, (hard, hard))
    return resource.getrlimit(resource.RLIMIT_NOFILE)[0]


def http(url: str, method: str = "GET", body: Any = None, headers: dict[str, str] | None = None,
         timeout: float = 3.0) -> tuple[int, bytes]:  # fmt: skip
    data = None if body is None else json.dumps(body).encode()
    req = urllib.request.Request(url, data=data, method=method, headers=headers or {})
    try:
        with urllib.request.urlopen(req, timeout=timeout) as r:
            return r.status, r.read()
    except urllib.error.HTTPError as e:
        return e.code, e.read()
    except OSError:
        return 0, b""


def wait_for(pred: Any, timeout: float, what: str, step: float = 0.5) -> Any:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        got = pred()
        if got:
            return got
        time.sleep(step)
    raise SystemExit(f"abuse_web: timed out after {timeout:g} s waiting for {what}")


class Records:
    """``mosquitto_sub`` on ``aware/data/#``: the arrival time of every record."""

    def __init__(self, port: int) -> None:
        self.times: list[float] = []
        self.proc = subprocess.Popen(
            ["mosquitto_sub", "-h", "127.0.0.1", "-p", str(port), "-t", "aware/data/#", "-q", "1"],
            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
        )  # fmt: skip
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for _ in self.proc.stdout:
            self.times.append(time.monotonic())

    def between(self, a: float, b: float) -> int:
        return sum(1 for t in self.times if a <= t < b)

    def stop(self) -> None:
        self.proc.terminate()
        self.proc.wait(timeout=10)


class Attack:
    """``n`` connections to (host, port) kept open with an unfinished header."""

    def __init__(self, host: str, port: int, n: int) -> None:
        self.addr = (host, port)
        self.n = n
        self.ep = select.epoll()
        self.socks: dict[int, tuple[socket.socket, bool]] = {}
        self.opened = self.connected = self.closed_by_server = self.open_failures = 0

    def fill(self) -> None:
        while len(self.socks) < self.n:
            try:
                s = socket.socket()
            except OSError:  # out of descriptors here: as many as this machine allows
                self.open_failures += 1
                return
            s.setblocking(False)
            err = s.connect_ex(self.addr)
            if err not in (0, errno.EINPROGRESS):
                s.close()
                self.open_failures += 1
                return
            self.ep.register(s.fileno(), select.EPOLLOUT | select.EPOLLRDHUP)
            self.socks[s.fileno()] = (s, False)
            self.opened += 1

    def step(self, timeout: float) -> None:
        for fd, ev in self.ep.poll(timeout):
            s, up = self.socks[fd]
            if ev & (select.EPOLLERR | select.EPOLLHUP | select.EPOLLRDHUP | select.EPOLLIN):
                if up:
                    self.closed_by_server += 1
                self._drop(fd)
            elif ev & select.EPOLLOUT and not up:
                self.connected += 1
                with contextlib.suppress(OSError):
                    s.send(PARTIAL)
                self.ep.modify(fd, select.EPOLLIN | select.EPOLLRDHUP)
                self.socks[fd] = (s, True)
        self.fill()

    def _drop(self, fd: int) -> None:
        s, _ = self.socks.pop(fd)
        self.ep.unregister(fd)
        s.close()

    def close(self) -> None:
        for fd in list(self.socks):
            self._drop(fd)
        self.ep.close()


HEADROOM_FDS = 100  # descriptors a worker keeps for itself


def attack_worker(port: int, n: int, seconds: float, out: Any, held: Any) -> None:
    """One attacking process: ``n`` connections for ``seconds``; its figures into ``out``."""
    n = min(n, raise_nofile() - HEADROOM_FDS)
    a = Attack("127.0.0.1", port, n)
    a.fill()
    end = time.monotonic() + seconds
    peak = 0
    while time.monotonic() < end:
        a.step(0.2)
        peak = max(peak, len(a.socks))
        held.value = len(a.socks)
    out.put({"opened": a.opened, "connected": a.connected, "closed_by_server":
             a.closed_by_server, "open_failures": a.open_failures, "max_open": peak})  # fmt: skip
    a.close()


def run(
    connections: int, attack_s: float, speed: float, workers: int = 2, warm_s: float = 20.0
) -> dict[str, Any]:
    nofile = raise_nofile()
    web_port, mqtt_port = free_port(), free_port()
    tmp = Path(tempfile.mkdtemp(prefix="abuse-web-"))
    log = (tmp / "demo.log").open("w")
    demo = subprocess.Popen(
        [sys.executable, "-m", "awaremw", "demo", "--web", f"127.0.0.1:{web_port}", "--plain",
         "--speed", str(speed), "--duration", "36000", "--mqtt-port", str(mqtt_port),
         "--mqtt-anonymous", "--summary", str(tmp / "summary.txt")],
        stdout=log, stderr=subprocess.STDOUT,
    )  # fmt: skip
    base = f"http://127.0.0.1:{web_port}"
    out: dict[str, Any] = {"connections": connections, "attack_s": attack_s, "speed": speed,
                           "nofile_limit": nofile, "dashboard_cap": MAX_CONNECTIONS}  # fmt: skip
    records: Records | None = None
    procs: list[multiprocessing.Process] = []
    try:
        page = wait_for(lambda: http(base + "/")[1], 60, "the dashboard").decode()
        m = re.search(r'name="awaremw-token" content="([^"]+)"', page)
        assert m is not None, "no token in the page"
        own = {"X-Awaremw-Token": m.group(1), "Content-Type": "application/json"}
        records = Records(mqtt_port)
        for path, body in (("/api/def/group/2", GROUP), ("/api/def/channel/5", CHANNEL)):
            st = wait_for(lambda p=path, b=body: http(base + p, "POST", b, own)[0] == 202, 30,
                          f"POST {path}")  # fmt: skip
            assert st
        wait_for(lambda: len(records.times) >= 10, 240, "ten records")
        time.sleep(warm_s)  # records settle to their steady rate (a measurement window)
        t0 = time.monotonic()
        out["rss_start_kb"], out["fds_start"] = rss_kb(demo.pid), fds(demo.pid)
        out["records_per_s_before"] = round(records.between(t0 - warm_s, t0) / warm_s, 2)
        ctx = multiprocessing.get_context("fork")
        results = ctx.Queue()
        open_now = [ctx.Value("i", 0) for _ in range(workers)]
        per = -(-connections // workers)
        procs = [ctx.Process(target=attack_worker, args=(web_port, per, attack_s, results, v),
                             daemon=True) for v in open_now]  # fmt: skip
        for p in procs:
            p.start()
        samples: list[dict[str, Any]] = []
        while any(p.is_alive() for p in procs) and demo.poll() is None:
            time.sleep(2.0)  # the sampling period
            samples.append({"t": round(time.monotonic() - t0, 1), "rss_kb": rss_kb(demo.pid),
                            "fds": fds(demo.pid), "attack_open": sum(v.value for v in open_now),
                            "records": records.between(t0, time.monotonic())})  # fmt: skip
        t1 = time.monotonic()
        out["alive_during"] = demo.poll() is None
        figs = [results.get(timeout=30) for _ in procs]
        for p in procs:
            p.join(timeout=30)
        out["attack"] = {k: sum(f[k] for f in figs) for k in figs[0]}
        out["attack"]["workers"] = workers
        out["attack"]["max_open_sampled"] = max((s["attack_open"] for s in samples), default=0)
        out["records_per_s_during"] = round(records.between(t0, t1) / (t1 - t0), 2)
        windows = [records.between(t0 + k, t0 + k + 10) for k in range(0, int(t1 - t0) - 9, 10)]
        out["records_min_per_10s_window"] = min(windows) if windows else 0
        out["rss_peak_kb"] = max((s["rss_kb"] for s in samples), default=0)
        out["fds_peak"] = max((s["fds"] for s in samples), default=0)
        t2 = time.monotonic()
        wait_for(lambda: http(base + "/api/state", timeout=2.0)[0] == 200, 120,
                 "the dashboard to answer again", step=0.2)  # fmt: skip
        out["dashboard_back_after_s"] = round(time.monotonic() - t2, 2)
        time.sleep(20.0)  # a measurement window after the attack
        out["rss_after_kb"] = rss_kb(demo.pid)
        out["fds_after"] = fds(demo.pid)
        t3 = time.monotonic()
        out["records_per_s_after"] = round(records.between(t3 - 20.0, t3) / 20.0, 2)
        out["alive_after"] = demo.poll() is None
        out["samples"] = samples
    finally:
        for p in procs:
            if p.is_alive():
                p.kill()
        if records is not None:
            records.stop()
        if demo.poll() is None:
            demo.send_signal(signal.SIGINT)
            try:
                demo.wait(timeout=60)
            except subprocess.TimeoutExpired:
                demo.kill()
                demo.wait()
        log.close()
    out["verdict"] = verdict(out)
    return out


def verdict(o: dict[str, Any]) -> list[str]:
    """What failed (empty: the fleet and gateway did not notice the attack)."""
    bad = []
    if not (o.get("alive_during") and o.get("alive_after")):
        bad.append("the demo exited")
    if not o.get("records_min_per_10s_window"):
        bad.append("a 10 s window of the attack without records")
    if o.get("fds_peak", 0) > o.get("fds_start", 0) + MAX_CONNECTIONS + FD_MARGIN:
        bad.append(f"descriptors grew from {o.get('fds_start')} to {o.get('fds_peak')}")
    if o.get("rss_after_kb", 0) > o.get("rss_start_kb", 0) + RSS_MARGIN_KB:
        bad.append(f"RSS {o.get('rss_start_kb')} -> {o.get('rss_after_kb')} KiB")
    return bad


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--connections", type=int, default=20_000)
    ap.add_argument("--attack-s", type=float, default=60.0)
    ap.add_argument("--speed", type=float, default=1.0)
    ap.add_argument("--workers", type=int, default=2, help="attacking processes")
    ap.add_argument("--json", type=Path, default=None, help="also write the figures here")
    a = ap.parse_args()
    out = run(a.connections, a.attack_s, a.speed, a.workers)
    brief = {k: v for k, v in out.items() if k != "samples"}
    print(json.dumps(brief, indent=1))
    if a.json is not None:
        a.json.write_text(json.dumps(out, indent=1) + "\n")
    return 1 if out["verdict"] else 0


if __name__ == "__main__":
    sys.exit(main())
