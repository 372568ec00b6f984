"""Multi-host integration: a Zenoh router and two fleets on three emulated hosts.

Docker is not available everywhere, so the compose topology
(docker-compose.yml) runs here as Linux network namespaces joined by veth
links to a bridge in a fourth "switch" namespace. Each host runs a real
``awaremw`` process; they meet only through the router's address on the
private test network. Needs root and iproute2: skipped otherwise, except when
``AWAREMW_REQUIRE_NETNS=1`` (CI), where that is a failure.
"""

from __future__ import annotations

import json
import math
import os
import re
import shlex
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from awaremw.runtime.deployment import load, load_deployment
from awaremw.runtime.partition import stripes

pytestmark = pytest.mark.slow

REQUIRED = os.environ.get("AWAREMW_REQUIRE_NETNS") == "1"

DEPLOYMENT = """
name = "netns"
radio = "cc2420"
seed = 7
tx_power_dbm = 0.0   # links up to about 25 m, none past 54 m
area = [200.0, 40.0]

[[grid]]
first_id = 1
kind = "tmote"
origin = [5.0, 10.0]
spacing = 15.0
cols = 12
rows = 2
"""


def _run(*cmd: str) -> None:
    subprocess.run(cmd, check=True, capture_output=True, timeout=10)


def _netns_usable() -> str | None:
    if sys.platform != "linux" or os.geteuid() != 0:
        return "needs root on Linux"
    if shutil.which("ip") is None:
        return "needs iproute2 (ip)"
    probe = f"awprobe{os.getpid()}"
    try:
        _run("ip", "netns", "add", probe)
    except (subprocess.SubprocessError, OSError) as e:
        return f"ip netns add failed: {e}"
    _run("ip", "netns", "del", probe)
    return None


class Hosts:
    """Hosts (by default: router, a, b; one-letter names) on 10.X.Y.0/24 behind a bridge."""

    def __init__(self, hosts: tuple[str, ...] = ("r", "a", "b")) -> None:
        tag = os.getpid() % 10000
        self.net = f"10.{200 + tag // 256 % 50}.{tag % 256}"
        self.names = {h: f"aw{h}{tag}" for h in hosts}
        self.switch = f"aws{tag}"
        self.addr = {h: f"{self.net}.{i + 1}" for i, h in enumerate(hosts)}

    def up(self) -> None:
        _run("ip", "netns", "add", self.switch)
        _run("ip", "-n", self.switch, "link", "add", "br0", "type", "bridge")
        _run("ip", "-n", self.switch, "link", "set", "br0", "up")
        for h, ns in self.names.items():
            _run("ip", "netns", "add", ns)
            _run("ip", "-n", ns, "link", "set", "lo", "up")
            _run(
                "ip",
                "link",
                "add",
                f"v{h}{ns[3:]}",
                "netns",
                ns,
                "type",
                "veth",
                "peer",
                "name",
                f"p{h}",
                "netns",
                self.switch,
            )
            _run("ip", "-n", ns, "link", "set", f"v{h}{ns[3:]}", "name", "eth0")
            _run("ip", "-n", ns, "addr", "add", f"{self.addr[h]}/24", "dev", "eth0")
            _run("ip", "-n", ns, "link", "set", "eth0", "up")
            _run("ip", "-n", self.switch, "link", "set", f"p{h}", "master", "br0")
            _run("ip", "-n", self.switch, "link", "set", f"p{h}", "up")

    def down(self) -> None:
        for ns in (*self.names.values(), self.switch):
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=10)

    def popen(
        self, host: str, *args: str, log: Path, cwd: Path | None = None
    ) -> subprocess.Popen[bytes]:
        """``python -m awaremw ARGS`` on ``host``, its output in ``log``; with ``cwd``,
        run there, the state a run keeps (XDG_STATE_HOME) under ``cwd/state-HOST``."""
        out = log.open("wb")
        env = None if cwd is None else {**os.environ, "XDG_STATE_HOME": str(cwd / f"state-{host}")}
        return subprocess.Popen(
            ["ip", "netns", "exec", self.names[host], sys.executable, "-m", "awaremw", *args],
            stdout=out,
            stderr=subprocess.STDOUT,
            cwd=cwd,
            env=env,
        )

    def wait_tcp(self, host: str, addr: str, port: int, timeout: float) -> None:
        """Wait until ``addr:port`` accepts a TCP connection from ``host``."""
        probe = (
            "import socket,sys\n"
            f"s=socket.create_connection(('{addr}',{port}),timeout=0.5); s.close()"
        )
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            r = subprocess.run(
                ["ip", "netns", "exec", self.names[host], sys.executable, "-c", probe],
                capture_output=True,
                timeout=10,
            )
            if r.returncode == 0:
                return
        raise TimeoutError(f"{addr}:{port} not reachable from host {host} in {timeout} s")


def _hosts(names: tuple[str, ...]) -> Iterator[Hosts]:
    why = _netns_usable()
    if why is not None:
        if REQUIRED:
            pytest.fail(f"network namespaces required but unusable: {why}")
        pytest.skip(why)
    h = Hosts(names)
    try:
        h.up()
        yield h
    finally:
        h.down()


@pytest.fixture
def hosts() -> Iterator[Hosts]:
    yield from _hosts(("r", "a", "b"))


@pytest.fixture
def sites() -> Iterator[Hosts]:
    """Three hosts a, b, c: a router and a fleet part on each."""
    yield from _hosts(("a", "b", "c"))


def test_router_and_two_fleets_on_three_hosts(hosts: Hosts, tmp_path: Path) -> None:
    dep_path = tmp_path / "netns.toml"
    dep_path.write_text(DEPLOYMENT)
    dep = load_deployment(dep_path)
    router_ep = f"tcp/{hosts.addr['r']}:7447"
    procs: list[subprocess.Popen[bytes]] = []
    try:
        procs.append(hosts.popen("r", "router", "--listen", router_ep, log=tmp_path / "r.log"))
        hosts.wait_tcp("a", hosts.addr["r"], 7447, timeout=20)
        start_at = time.time() + 4.0  # both fleets share emulated time zero
        for host, part in (("a", "1/2"), ("b", "2/2")):
            procs.append(
                hosts.popen(
                    host,
                    "fleet",
                    str(dep_path),
                    "--hello",
                    "--plain",
                    "--part",
                    part,
                    "--connect",
                    router_ep,
                    "--listen",
                    f"tcp/{hosts.addr[host]}:7447",
                    "--start-at",
                    f"{start_at:.3f}",
                    "--duration",
                    "8",
                    "--links-json",
                    str(tmp_path / f"{host}.json"),
                    log=tmp_path / f"{host}.log",
                )
            )
        for p, host in zip(procs[1:], ("a", "b"), strict=True):
            code = p.wait(timeout=60)
            assert code == 0, (tmp_path / f"{host}.log").read_text()
    finally:
        for p in procs:
            if p.poll() is None:
                p.terminate()
                try:
                    p.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    p.kill()

    pos = {n.id: n.position for n in dep.nodes}
    model = dep.radio_model()
    reach = model.max_range_m(dep.tx_power_dbm)
    links: dict[str, list[tuple[int, int, int]]] = {
        h: [tuple(x) for x in json.loads((tmp_path / f"{h}.json").read_text())] for h in "ab"
    }
    west, east = stripes(dep, 2)
    mine = {
        "a": {n.id for n in dep.nodes if west(n)},
        "b": {n.id for n in dep.nodes if east(n)},
    }
    assert len(mine["a"]) == len(mine["b"]) == 12
    crossing = 0
    for h, rows in links.items():
        assert rows, f"host {h} delivered no frame"
        for src, dst, n in rows:
            assert dst in mine[h], f"host {h} delivered to {dst}, a mote of the other host"
            d = math.dist(pos[src], pos[dst])
            assert d <= reach, f"{src}->{dst} delivered at {d:.1f} m > range {reach:.1f} m"
            assert n > 0
            if src not in mine[h]:
                crossing += 1
    # Frames crossed between the hosts, through the router, in both directions.
    assert any(src in mine["b"] for src, _, _ in links["a"])
    assert any(src in mine["a"] for src, _, _ in links["b"])
    assert crossing >= 4
    # And every in-range pair spanning the boundary at 15 m heard each other.
    boundary = [(s, d) for s in mine["a"] for d in mine["b"] if math.dist(pos[s], pos[d]) <= 16.0]
    heard_b = {(s, d) for s, d, _ in links["b"]}
    assert boundary and all(pair in heard_b for pair in boundary)


def _stop(procs: list[subprocess.Popen[bytes]]) -> None:
    for p in procs:
        if p.poll() is None:
            p.terminate()
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()


HOSTS_DOC = Path(__file__).resolve().parent.parent / "docs" / "hosts.md"


def hosts_recipe() -> tuple[list[str], dict[str, list[list[str]]]]:
    """The ```sh block of docs/hosts.md, "Run it": the lines before the first
    ``# host X:`` comment, and each host's command lines (``&`` dropped), split."""
    section = HOSTS_DOC.read_text(encoding="utf-8").split("## Run it", 1)[1]
    m = re.search(r"```sh\n(.*?)```", section, re.S)
    assert m is not None, "docs/hosts.md: no sh block under 'Run it'"
    first: list[list[str]] = []
    per_host: dict[str, list[list[str]]] = {}
    host = None
    for raw in m.group(1).splitlines():
        line = raw.strip()
        head = re.match(r"# host (\w):", line)
        if head:
            host = head.group(1)
            per_host[host] = []
        elif line and not line.startswith("#"):
            words = shlex.split(line.removesuffix("&"))
            assert words[0] == "awaremw", line
            (first if host is None else per_host[host]).append(words[1:])
    return [" ".join(w) for w in first], per_host


def test_the_hosts_recipe_three_routers_linked_secrets_on(sites: Hosts, tmp_path: Path) -> None:
    """docs/hosts.md as printed, on three namespaces: one router per host linked to the
    others over mutual TLS, the gateway and a fleet part on each host's own router."""
    first, recipe = hosts_recipe()
    assert sorted(recipe) == ["a", "b", "c"] and first == ["keys init secrets/"]
    keys = subprocess.run(
        [sys.executable, "-m", "awaremw", *first[0].split()],
        cwd=tmp_path, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert keys.returncode == 0, keys.stderr
    fill = {f"HOST_{h.upper()}": sites.addr[h] for h in "abc"}
    procs: list[subprocess.Popen[bytes]] = []
    try:
        for h, lines in recipe.items():
            for words in lines:
                if words[0] == "router":
                    procs.append(
                        sites.popen(h, *_fill(words, fill, ""), log=tmp_path / f"router-{h}.log",
                                    cwd=tmp_path)
                    )  # fmt: skip
        for h in "abc":
            sites.wait_tcp(h, "127.0.0.1", 7447, timeout=20)
        start = f"{time.time() + 6.0:.3f}"  # START: the same emulated time zero everywhere
        runs: dict[str, subprocess.Popen[bytes]] = {}
        for h, lines in recipe.items():
            for words in lines:
                if words[0] == "router":
                    continue
                name = f"{words[0]}-{h}"
                extra = ["--duration", "10"]
                if words[0] == "fleet":
                    extra += ["--links-json", str(tmp_path / f"{h}.json")]
                runs[name] = sites.popen(
                    h, *_fill(words, fill, start), *extra, log=tmp_path / f"{name}.log",
                    cwd=tmp_path,
                )  # fmt: skip
        procs += runs.values()
        assert sorted(runs) == ["fleet-a", "fleet-b", "fleet-c", "gateway-a"]
        for name, p in runs.items():
            assert p.wait(timeout=120) == 0, (tmp_path / f"{name}.log").read_text()
    finally:
        _stop(procs)
    for h in "abc":
        assert "authenticated, access control by role" in (tmp_path / f"router-{h}.log").read_text()

    dep = load("grid_small")
    pos = {n.id: n.position for n in dep.nodes}
    parts = zip("abc", stripes(dep, 3), strict=True)
    mine = {h: {n.id for n in dep.nodes if part(n) and n.kind != "gateway"} for h, part in parts}
    heard = {
        h: {(src, dst) for src, dst, _ in json.loads((tmp_path / f"{h}.json").read_text())}
        for h in "abc"
    }
    for h in "abc":
        assert all(dst in mine[h] for _, dst in heard[h]), f"{h} delivered to another host's mote"
    # Across both stripe boundaries, both ways, every pair the radio model makes a sure
    # link heard each other: fleet -> its router -> the other router -> the other fleet.
    model = dep.radio_model()

    def sure(src: int, dst: int) -> bool:
        rssi = model.mean_rssi(src, dst, math.dist(pos[src], pos[dst]), dep.tx_power_dbm)
        return model.prr(rssi, 40) > 0.99

    for west, east in (("a", "b"), ("b", "c")):
        pairs = [(s, d) for s in mine[west] for d in mine[east] if sure(s, d) and sure(d, s)]
        assert pairs, f"no sure link between {west} and {east}: the test has no teeth"
        assert all(p in heard[east] for p in pairs), (west, east)
        assert all((d, s) in heard[west] for s, d in pairs), (east, west)


def _fill(words: list[str], addresses: dict[str, str], start: str) -> list[str]:
    """A recipe line with the hosts' addresses and START filled in."""
    out = []
    for w in words:
        for placeholder, addr in addresses.items():
            w = w.replace(placeholder, addr)
        out.append(start if w == "START" else w)
    return out
