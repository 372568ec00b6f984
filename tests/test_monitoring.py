"""Operating it as a service (docs/monitoring.md): ``--metrics`` on the gateway and
the fleet, scraped and parsed with prometheus-client's own text parser;
``/readyz`` against a broker that is not there yet; the address rule; and a real
Prometheus (Debian's ``prometheus``) scraping both with the shipped configuration."""

from __future__ import annotations

import base64
import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
import urllib.error
import urllib.parse
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import pytest
from lines import Lines
from mosquitto import Mosquitto, free_port
from prometheus_client.parser import text_string_to_metric_families

from awaremw.runtime.zenoh_session import free_tcp_endpoint

pytestmark = [pytest.mark.zenoh]
ROOT = Path(__file__).resolve().parent.parent


def get(url: str, password: str | None = None) -> tuple[int, str]:
    req = urllib.request.Request(url)
    if password is not None:
        token = base64.b64encode(f"prometheus:{password}".encode()).decode()
        req.add_header("Authorization", f"Basic {token}")
    try:
        with urllib.request.urlopen(req, timeout=5) as r:
            return r.status, r.read().decode()
    except urllib.error.HTTPError as e:
        return e.code, e.read().decode()


def samples(text: str) -> dict[str, list[tuple[dict[str, str], float]]]:
    """Every sample by name, parsed the way Prometheus's own client parses it."""
    out: dict[str, list[tuple[dict[str, str], float]]] = {}
    for fam in text_string_to_metric_families(text):
        for s in fam.samples:
            out.setdefault(s.name, []).append((dict(s.labels), s.value))
    return out


def types(text: str) -> dict[str, str]:
    return {fam.name: fam.type for fam in text_string_to_metric_families(text)}


def until(cond: object, timeout: float, what: str) -> None:
    """Poll ``cond`` (an HTTP endpoint's answer) until it holds, within ``timeout``."""
    assert callable(cond)
    deadline = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < deadline, what
        time.sleep(0.2)  # polling an HTTP endpoint: it pushes nothing


@contextlib.contextmanager
def process(*args: str, env: dict[str, str] | None = None) -> Iterator[Lines]:
    proc = subprocess.Popen(
        [sys.executable, "-m", "awaremw", *args], stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT, text=True, env=env,
    )  # fmt: skip
    try:
        yield Lines(proc)
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)


def define(url: str) -> None:
    """A group on every mote with x > 3 and a channel of its temperature, as the operator."""
    for args in (
        ["define", "group", "1", "x > 3"],
        ["define", "channel", "1", "--attr", "temperature", "--group-type", "1", "--period", "1"],
    ):
        r = subprocess.run(
            [sys.executable, "-m", "awaremw", *args, "--mqtt", url, "--wait", "10"],
            capture_output=True, text=True, timeout=60, check=False,
        )  # fmt: skip
        assert r.returncode == 0, r


@pytest.mark.mosquitto
def test_gateway_and_fleet_serve_metrics_and_readiness(tmp_path: Path) -> None:
    (tmp_path / "mosquitto").mkdir()
    m = Mosquitto(tmp_path / "mosquitto")  # not started yet: the gateway cannot subscribe
    ep = free_tcp_endpoint()
    with (
        process("fleet", "grid_small", "--listen", ep, "--without-kind", "gateway", "--plain",
                "--speed", "2", "--progress", "0.5", "--metrics", "127.0.0.1:0") as fleet,
        process("gateway", "grid_small", "--connect", ep, "--mqtt", m.url("gateway"),
                "--state-dir", str(tmp_path / "state"), "--speed", "2",
                "--metrics", "127.0.0.1:0") as gw,
    ):  # fmt: skip
        fleet_url = fleet.wait_for(r"metrics on (http://\S+)/metrics", 60)[1]
        gw_url = gw.wait_for(r"metrics on (http://\S+)/metrics", 60)[1]
        assert get(f"{gw_url}/healthz") == (200, "ok\n")
        # Not subscribed (the broker is not there): not ready, and says why.
        gw.wait_for(r"awaremw gateway: motes", 60)
        code, text = get(f"{gw_url}/readyz")
        assert code == 503 and "not subscribed" in text, (code, text)
        m.start()
        try:
            until(lambda: get(f"{gw_url}/readyz")[0] == 200, 30, "gateway never ready")
            until(lambda: get(f"{fleet_url}/readyz")[0] == 200, 30, "fleet never ready")
            define(m.url("operator"))

            def delivered() -> float:
                s = samples(get(f"{gw_url}/metrics")[1])
                return sum(v for _, v in s.get("awaremw_records_delivered_total", []))

            until(lambda: delivered() > 0, 90, "no record delivered")
            gw_text = get(f"{gw_url}/metrics")[1]
            fleet_text = get(f"{fleet_url}/metrics")[1]
        finally:
            m.stop()
    for text in (gw_text, fleet_text):
        t, s = types(text), samples(text)
        assert t["awaremw_timer_lag_seconds"] == "histogram"
        assert s["awaremw_timer_lag_seconds_count"][0][1] > 0
        assert any(lb["le"] == "+Inf" for lb, _ in s["awaremw_timer_lag_seconds_bucket"])
        sent = {lb["kind"]: v for lb, v in s["awaremw_frames_sent_total"]}
        assert sent.get("ctp_beacon", 0) > 0 and sent.get("drip_summary", 0) + sent.get(
            "drip_item", 0
        ) > 0, sent
        heard = {(lb["kind"], lb["fate"]) for lb, v in s["awaremw_frames_heard_total"] if v > 0}
        assert ("ctp_beacon", "received") in heard, heard
    gs, fs = samples(gw_text), samples(fleet_text)
    assert gs["awaremw_records_delivered_total"][0][1] > 0
    assert ({"kind": "channel"}, 1.0) in gs["awaremw_definitions"]
    assert gs["awaremw_mqtt_connected"][0][1] == 1.0
    assert fs["awaremw_records_produced_total"][0][1] > 0
    assert fs["awaremw_motes_alive"][0][1] == 25  # grid_small: 26 motes, one the gateway
    energy = {lb["kind"]: v for lb, v in fs["awaremw_radio_energy_joules_total"]}
    assert energy and all(v > 0 for v in energy.values()), energy


@pytest.mark.parametrize("verb", ["gateway", "fleet"])
def test_metrics_beyond_loopback_need_a_password(verb: str, tmp_path: Path) -> None:
    env = {k: v for k, v in os.environ.items() if k != "AWAREMW_METRICS_PASSWORD"}
    port = free_port()
    r = subprocess.run(
        [sys.executable, "-m", "awaremw", verb, "grid_small", "--metrics", f"0.0.0.0:{port}"],
        capture_output=True, text=True, timeout=60, env=env, check=False,
    )  # fmt: skip
    assert r.returncode == 2
    assert (r.stdout + r.stderr).strip().splitlines() == [
        f"awaremw {verb}: refusing to serve metrics on 0.0.0.0:{port} without a password "
        "(they show the network's layout and load): set AWAREMW_METRICS_PASSWORD, or serve "
        "on 127.0.0.1"
    ]


def prometheus_binary() -> str | None:
    return shutil.which("prometheus")


@pytest.mark.mosquitto
def test_a_real_prometheus_scrapes_the_gateway_and_the_fleet(tmp_path: Path) -> None:
    """Debian's prometheus with the shipped monitoring/prometheus.yml (its loopback
    ports: gateway 9101, fleet 9102) answers a query for the records counter."""
    binary = prometheus_binary()
    if binary is None:
        if os.environ.get("AWAREMW_REQUIRE_PROMETHEUS") == "1":
            pytest.fail("prometheus is required here (apt-get install prometheus)")
        pytest.skip("no prometheus binary (Debian: apt-get install prometheus)")
    (tmp_path / "mosquitto").mkdir()
    m = Mosquitto(tmp_path / "mosquitto")
    m.start()
    ep = free_tcp_endpoint()
    web = f"127.0.0.1:{free_port()}"
    prom = subprocess.Popen(
        [binary, f"--config.file={ROOT / 'monitoring' / 'prometheus.yml'}",
         f"--storage.tsdb.path={tmp_path / 'tsdb'}", f"--web.listen-address={web}"],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
    )  # fmt: skip
    try:
        with (
            process("fleet", "grid_small", "--listen", ep, "--without-kind", "gateway",
                    "--plain", "--speed", "2", "--progress", "0.5",
                    "--metrics", "127.0.0.1:9102") as fleet,
            process("gateway", "grid_small", "--connect", ep, "--mqtt", m.url("gateway"),
                    "--state-dir", str(tmp_path / "state"), "--speed", "2",
                    "--metrics", "127.0.0.1:9101") as gw,
        ):  # fmt: skip
            fleet.wait_for(r"metrics on http://127.0.0.1:9102/metrics", 60)
            gw.wait_for(r"awaremw gateway: motes", 60)
            define(m.url("operator"))

            def queried() -> float:
                q = urllib.parse.quote("sum(awaremw_records_delivered_total)")
                code, body = get(f"http://{web}/api/v1/query?query={q}")
                if code != 200:
                    return 0.0
                result = json.loads(body)["data"]["result"]
                return float(result[0]["value"][1]) if result else 0.0

            until(lambda: queried() > 0, 120, "Prometheus never saw a record delivered")

            def up(job: str) -> bool:
                q = urllib.parse.quote(f'up{{job="{job}"}}')
                result = json.loads(get(f"http://{web}/api/v1/query?query={q}")[1])["data"]
                return bool(result["result"]) and result["result"][0]["value"][1] == "1"

            # Both targets scraped (the first scrape may come before a process listens).
            until(lambda: up("awaremw-gateway") and up("awaremw-fleet"), 30, "a target down")
    finally:
        prom.terminate()
        prom.wait(20)
        m.stop()


def test_json_logs_every_line_of_fleet_and_gateway(tmp_path: Path) -> None:
    """``--log-format json``: every line either verb writes, on stdout and stderr (its
    own lines, log records, warnings), is one JSON object with the four keys."""
    ep = free_tcp_endpoint()
    common = ["--log-format", "json", "--speed", "2", "--duration", "8"]
    fleet = subprocess.Popen(
        [sys.executable, "-m", "awaremw", "-v", "fleet", "grid_small", "--listen", ep, "--plain",
         "--without-kind", "gateway", "--progress", "0.5", *common],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    gw = subprocess.Popen(
        [sys.executable, "-m", "awaremw", "-v", "gateway", "grid_small", "--connect", ep,
         "--mqtt-port", "0", "--state-dir", str(tmp_path / "state"), *common],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    outputs = {}
    for name, proc in (("fleet", fleet), ("gateway", gw)):
        out, err = proc.communicate(timeout=120)
        assert proc.returncode == 0, (name, out, err)
        outputs[name] = (out + err).splitlines()
    for name, lines in outputs.items():
        assert len(lines) >= 5, (name, lines)
        levels = set()
        for line in lines:
            doc = json.loads(line)
            assert {"time", "level", "component", "message"} <= doc.keys(), line
            levels.add(doc["level"])
        assert "info" in levels and "warning" in levels, (name, levels)
    progress = [json.loads(ln) for ln in outputs["fleet"] if '"motes": ' in ln]
    assert progress and all(isinstance(p["motes"], int) for p in progress)


def test_router_and_demo_serve_metrics_and_readiness(tmp_path: Path) -> None:
    """``--metrics`` on the router (its own loop thread) and on the demo (the
    gateway's figures and every fleet's, together)."""
    ep = free_tcp_endpoint()
    with (
        process("router", "--listen", ep, "--metrics", "127.0.0.1:0") as router,
        process("demo", "--plain", "--speed", "4", "--duration", "60", "--mqtt-port", "0",
                "--summary", str(tmp_path / "summary.txt"), "--metrics", "127.0.0.1:0") as demo,
    ):  # fmt: skip
        router_url = router.wait_for(r"metrics on (http://\S+)/metrics", 60)[1]
        demo_url = demo.wait_for(r"metrics: (http://\S+)/metrics", 60)[1]
        assert get(f"{router_url}/readyz")[0] == 200
        rs = samples(get(f"{router_url}/metrics")[1])
        assert rs["awaremw_router_up"][0][1] == 1.0
        assert {lb["mode"] for lb, _ in rs["awaremw_router_sessions"]} == {
            "peer_or_client", "router"
        }
        until(lambda: get(f"{demo_url}/readyz")[0] == 200, 60, "demo never ready")
        ds = samples(get(f"{demo_url}/metrics")[1])
        assert ds["awaremw_motes_alive"][0][1] > 0
        assert ds["awaremw_mqtt_connected"][0][1] == 1.0

        def defined() -> float:  # the robot client's group and channel, once it has run
            s = samples(get(f"{demo_url}/metrics")[1])
            return sum(v for _, v in s.get("awaremw_definitions", []))

        until(lambda: defined() >= 2, 60, "the demo's definitions never showed")


def test_one_endpoint_for_a_fleets_worker_processes() -> None:
    """``fleet --processes 2 --metrics``: the launcher merges its workers' figures
    (sent with their progress snapshots) into one /metrics."""
    ep = free_tcp_endpoint()
    with process("fleet", "grid_small", "--processes", "2", "--listen", ep, "--plain",
                 "--progress", "0.5", "--metrics", "127.0.0.1:0") as fleet:  # fmt: skip
        url = fleet.wait_for(r"metrics on (http://\S+)/metrics", 60)[1]

        def both_workers() -> bool:
            s = samples(get(f"{url}/metrics")[1])
            sent = sum(v for _, v in s.get("awaremw_frames_sent_total", []))
            return s["awaremw_motes_alive"][0][1] == 26 and sent > 0

        until(both_workers, 60, "the two workers' motes never showed together")
        assert get(f"{url}/readyz")[0] == 200
        s = samples(get(f"{url}/metrics")[1])
        assert s["awaremw_timer_lag_seconds_count"][0][1] > 0
