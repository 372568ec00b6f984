"""The fleet, fleet-ctl, router and bench verbs, run as real processes."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from awaremw.runtime.deployment import load
from awaremw.runtime.partition import stripes
from awaremw.runtime.zenoh_session import free_tcp_endpoint

pytestmark = pytest.mark.zenoh

AWAREMW = [sys.executable, "-m", "awaremw"]


def run(*args: str, timeout: float = 60.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*AWAREMW, *args], capture_output=True, text=True, timeout=timeout, check=False
    )


def ctl(ep: str, *args: str) -> subprocess.CompletedProcess[str]:
    return run("fleet-ctl", "--connect", ep, "--timeout", "2", *args)


def test_fleet_duration_exits_0() -> None:
    ep = free_tcp_endpoint()
    p = run("fleet", "grid_small", "--duration", "3", "--speed", "6", "--listen", ep)
    assert p.returncode == 0, p.stderr
    assert "grid_small: 26 motes" in p.stdout
    last = [ln for ln in p.stdout.splitlines() if ln.startswith("[")][-1]
    assert last.startswith("[main] t=") and "motes=26" in last
    assert "done at" in p.stdout.strip().splitlines()[-1]


def test_fleet_with_two_processes_duration_exits_0() -> None:
    ep = free_tcp_endpoint()
    p = run(
        "fleet", "grid_small", "--processes", "2", "--duration", "3", "--speed", "6",
        "--listen", ep, "--hello",
    )  # fmt: skip
    assert p.returncode == 0, p.stderr
    assert f"reachable at {ep}" in p.stdout
    done = [ln for ln in p.stdout.splitlines() if "done at" in ln]
    assert done and "frames tx=" in done[0] and "tx=0 " not in done[0]


def test_bad_deployment_gives_a_clear_error_and_exit_2(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text(
        'area = [50.0, 50.0]\n[[nodes]]\nid = 1\nkind = "tmote"\nposition = [1.0, 1.0]\n'
        '[[nodes]]\nid = 3\nkind = "tmote"\nposition = [80.0, 1.0]\n'
    )
    p = run("fleet", str(bad), "--duration", "1")
    assert p.returncode == 2
    assert str(bad) in p.stderr and "nodes[1] (id 3)" in p.stderr
    assert "outside the area" in p.stderr and "Traceback" not in p.stderr
    p = run("fleet", "no-such-deployment", "--duration", "1")
    assert p.returncode == 2 and "no such deployment" in p.stderr


def test_fleet_ctl_adds_kills_and_lists_motes_of_a_running_fleet() -> None:
    ep = free_tcp_endpoint()
    fleet = subprocess.Popen(
        [*AWAREMW, "fleet", "grid_small", "--listen", ep, "--hello", "--progress", "60"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + 30
        while True:  # wait until the fleet answers (not a fixed sleep)
            listed = ctl(ep, "list")
            if listed.returncode == 0 or time.monotonic() > deadline:
                break
        assert listed.returncode == 0, listed.stderr
        assert len(listed.stdout.splitlines()) == 26
        p = ctl(ep, "add", "99", "--kind", "tmote", "--position", "30", "30")
        assert p.returncode == 0 and "node 99 added to fleet main" in p.stdout
        p = ctl(ep, "add", "99", "--kind", "tmote", "--position", "30", "30")
        assert p.returncode == 1 and "already running" in p.stderr
        p = ctl(ep, "add", "98", "--kind", "tmote", "--position", "300", "30")
        assert p.returncode == 1 and "outside the area" in p.stderr
        p = ctl(ep, "kill", "5")
        assert p.returncode == 0 and "node 5 killed" in p.stdout
        assert ctl(ep, "kill", "5").returncode == 1
        ids = {int(line.split()[0]) for line in ctl(ep, "list").stdout.splitlines()}
        assert 99 in ids and 5 not in ids and len(ids) == 26
        stats = json.loads(ctl(ep, "stats").stdout.splitlines()[0])
        assert stats["motes"] == 26 and stats["frames_tx"] > 0
    finally:
        fleet.send_signal(signal.SIGTERM)
        _, err = fleet.communicate(timeout=30)
    assert fleet.returncode == 0, err


def test_fleet_ctl_without_a_fleet_fails_clearly() -> None:
    p = ctl(free_tcp_endpoint(), "list")
    assert p.returncode == 1 and "cannot reach" in p.stderr


def test_router_runs_until_terminated() -> None:
    ep = free_tcp_endpoint()
    r = subprocess.Popen([*AWAREMW, "router", "--listen", ep], stdout=subprocess.PIPE, text=True)
    try:
        assert r.stdout is not None
        assert f"listening on {ep}" in r.stdout.readline()
    finally:
        r.send_signal(signal.SIGTERM)
        r.wait(timeout=20)
    assert r.returncode == 0
    assert run("router", "--listen", "nonsense").returncode == 2


def test_two_client_mode_fleets_hear_each_other_through_the_router(tmp_path: Path) -> None:
    """--zenoh-mode client: no direct link between fleets, the router carries every frame."""
    ep = free_tcp_endpoint()
    r = subprocess.Popen([*AWAREMW, "router", "--listen", ep], stdout=subprocess.PIPE, text=True)
    fleets: list[subprocess.Popen[bytes]] = []
    try:
        assert r.stdout is not None and "listening" in r.stdout.readline()
        start_at = f"{time.time() + 3.0:.3f}"
        for part in ("1/2", "2/2"):
            args = ["fleet", "grid_small", "--plain", "--hello", "--zenoh-mode", "client"]
            args += ["--part", part, "--connect", ep, "--start-at", start_at, "--duration", "6"]
            args += ["--links-json", str(tmp_path / f"{part[0]}.json")]
            fleets.append(subprocess.Popen([*AWAREMW, *args], stdout=subprocess.DEVNULL))
        for f in fleets:
            assert f.wait(timeout=60) == 0
    finally:
        for proc in (*fleets, r):
            if proc.poll() is None:
                proc.terminate()
                proc.wait(timeout=20)
    dep = load("grid_small")
    west = stripes(dep, 2)[0]
    side = {n.id: ("1" if west(n) else "2") for n in dep.nodes}
    for k in "12":
        rows = json.loads((tmp_path / f"{k}.json").read_text())
        assert all(side[dst] == k for _, dst, _ in rows)
        assert any(side[src] != k for src, _, _ in rows), f"fleet {k} heard no other-side mote"


def test_client_mode_needs_a_router() -> None:
    p = run("fleet", "grid_small", "--zenoh-mode", "client")
    assert p.returncode == 2 and "--zenoh-mode client needs --connect" in p.stderr
    p = run("gateway", "grid_small", "--zenoh-mode", "client")
    assert p.returncode == 2 and "--zenoh-mode client needs --connect" in p.stderr


def test_bench_verb_registry_and_scale_json() -> None:
    p = run("bench", "nope")
    assert p.returncode == 2 and "unknown benchmark 'nope'" in p.stderr
    p = run(
        "bench", "scale", "--motes", "30", "--duration", "2", "--speed", "4",
        "--warmup", "0.5", "--grace", "0.3", "--json",
    )  # fmt: skip
    assert p.returncode == 0, p.stderr
    out = json.loads(p.stdout)
    for key in ("motes", "processes", "timer_lag_p50_ms", "timer_lag_p99_ms", "delivery_ratio"):
        assert key in out
    assert out["motes"] == 30 and out["frames_tx"] > 0
    assert out["delivery_ratio"] == 1.0  # one process: nothing can get lost
