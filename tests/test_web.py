"""The web dashboard (awaremw/view/web.py): its state from the public MQTT
contract (bounded), its HTTP API against a real broker, ``awaremw view`` on a
system it only knows through MQTT, and the page in a real headless Chromium
during ``awaremw demo --web`` (Debian's /usr/bin/chromium driven by Playwright;
no browser is ever downloaded)."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import aiohttp
import aiomqtt
import pytest

from awaremw.gateway.broker import EmbeddedBroker
from awaremw.gateway.mqtt import MqttSettings
from awaremw.runtime.deployment import load
from awaremw.view import web
from awaremw.view.web import Dashboard, DashboardState, deployment_field, unit_of

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
]  # fmt: skip
# CI (.ci/run) installs chromium and the browser extra: there the test must run.
REQUIRE_BROWSER = os.environ.get("AWAREMW_REQUIRE_BROWSER") == "1"
REPO = Path(__file__).resolve().parent.parent


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _wait(pred: Callable[[], Any], timeout: float, what: str, step: float = 0.2) -> Any:
    """Poll ``pred`` until it returns a truthy value (the event) or time runs out."""
    end = time.monotonic() + timeout
    while True:
        got = pred()
        if got:
            return got
        if time.monotonic() > end:
            raise AssertionError(f"timed out after {timeout:g} s waiting for {what}")
        time.sleep(step)


def _get_json(url: str) -> Any:
    import urllib.request

    try:
        with urllib.request.urlopen(url, timeout=2.0) as r:
            return json.loads(r.read())
    except OSError:
        return None


# --------------------------------------------------------------------------- state


def test_state_follows_the_contract_and_stays_bounded() -> None:
    dep = load("romeo4r")
    st = DashboardState(dep.area, "t", None)
    st.set_field(0.0, deployment_field(dep, 0.0))
    chan = {"attr": "humidity", "group_type": 1, "group_id": "*", "period_s": 2, "agg": "avg"}
    st.on_message("def/channel/3", json.dumps(chan).encode())
    group = {"leader": 7, "weight": 3, "readings": 4, "t": 10.0}
    st.on_message("groups/1/513", json.dumps(group).encode())
    for i in range(web.SERIES_POINTS + 50):
        kind = st.on_message("data/3/1/513", json.dumps({"value": 40.0 + i, "count": 4,
                                                         "agg": "avg", "epoch": i, "leader": 7,
                                                         "t": 10.0 + i}).encode())  # fmt: skip
        assert kind == "record"
    for i in range(web.MAX_ERRORS + 10):
        st.on_message("errors", json.dumps({"code": "bad", "error": f"e{i}"}).encode())
    assert st.on_message("data/3/1/513", b"{not json") is None  # remote garbage: ignored
    doc = st.state()
    assert len(st.series[3]) == web.SERIES_POINTS
    assert st.series[3][-1][1] == 40.0 + web.SERIES_POINTS + 49
    assert len(doc["errors"]) == web.MAX_ERRORS and doc["errors"][-1]["error"] == "e59"
    assert doc["channels"]["3"]["unit"] == "%RH"
    # Without the cores the map knows each group's leader, not its members.
    assert doc["groups"] == [{"type": 1, "id": 513, "leader": 7, "members": None, "weight": 3,
                              "readings": 4, "reported_t": 10.0}]  # fmt: skip
    lead = [m for m in doc["motes"] if m["leader"]]
    assert [(m["id"], m["group"]) for m in lead] == [(7, 513)]
    assert len(doc["motes"]) == len(dep.nodes)
    # A group gone (empty retained payload) leaves the map.
    st.on_message("groups/1/513", b"")
    assert st.state()["groups"] == [] and not any(m["leader"] for m in st.state()["motes"])
    assert st.heard_t == 10.0 + web.SERIES_POINTS + 49


def test_units() -> None:
    assert unit_of("temperature") == "°C"
    assert unit_of("light") == "lx"
    assert unit_of("battery") == "V"
    assert unit_of("x") == "m"
    assert unit_of("rssi:100") == "dBm"
    assert unit_of("temperature", "count") == "motes"


# --------------------------------------------------------------------------- server


async def test_api_publishes_on_the_contract_and_drops_slow_clients() -> None:
    dep = load("romeo4r")
    async with EmbeddedBroker(port=0, anonymous=True) as broker:
        st = DashboardState(dep.area, "t", 1)
        st.set_field(0.0, deployment_field(dep, 0.0))
        settings = MqttSettings.from_url(broker.url, client_id="web-test")
        async with Dashboard(st, settings, "127.0.0.1", 0) as dash, aiohttp.ClientSession() as http:
            base = dash.url.rstrip("/")
            page = await (await http.get(base + "/")).text()
            assert "channel-form" in page and "/static/dashboard.js" in page
            assert (await http.get(base + "/static/dashboard.js")).status == 200
            assert (await http.get(base + "/static/passwd")).status == 404

            async def until(pred: Callable[[], bool], what: str) -> None:
                async with asyncio.timeout(10):
                    while not pred():
                        await asyncio.sleep(0.05)

            await until(lambda: st.mqtt_connected, "the dashboard's MQTT connection")
            # Invalid requests are refused here; valid ones go out on the contract.
            r = await http.post(base + "/api/def/channel/abc", json={"attr": "light"})
            assert r.status == 400
            r = await http.post(base + "/api/def/channel/9", data=b"[1, 2]")
            assert r.status == 400
            r = await http.post(base + "/api/cmd/bad name!", json={"target": "all"})
            assert r.status == 400
            r = await http.post(base + "/api/def/channel/9", data=b"x" * (web.MAX_BODY + 1))
            assert r.status == 413
            body = {"attr": "light", "group_type": 1, "group_id": "*", "period_s": 2, "agg": "max"}
            r = await http.post(base + "/api/def/channel/9", json=body)
            assert r.status == 202 and (await r.json())["topic"] == "aware/def/channel/9"
            # The retained definition comes back through the broker: the page shows it.
            await until(lambda: st.defs["channel"].get("9") == body, "the retained definition")
            async with aiomqtt.Client("127.0.0.1", broker.port, identifier="probe") as probe:
                await probe.subscribe("aware/cmd/#", qos=1)
                r = await http.post(base + "/api/cmd/led", json={"target": "all",
                                                                 "args": {"on": True}})  # fmt: skip
                assert r.status == 202
                async with asyncio.timeout(10):
                    async for msg in probe.messages:  # amqtt may replay other retained ones
                        if str(msg.topic) == "aware/cmd/led":
                            break
                assert json.loads(bytes(msg.payload))["args"] == {"on": True}  # type: ignore[arg-type]
            r = await http.delete(base + "/api/def/channel/9")
            assert r.status == 202
            await until(lambda: "9" not in st.defs["channel"], "the deletion")

            # A live SSE client gets the state first, then records as they come.
            async with http.get(base + "/api/events") as sse:
                first = await sse.content.readuntil(b"\n\n")
                assert first.startswith(b"event: hello")
                hello = json.loads(first.split(b"data: ", 1)[1])
                assert len(hello["state"]["motes"]) == len(dep.nodes)
                async with aiomqtt.Client("127.0.0.1", broker.port, identifier="gw") as gw:
                    await gw.publish("aware/data/4/1/513", json.dumps(
                        {"value": 1.5, "count": 2, "agg": "sum", "epoch": 1, "leader": 3,
                         "t": 12.0}), qos=1)  # fmt: skip
                    async with asyncio.timeout(10):
                        while True:
                            ev = await sse.content.readuntil(b"\n\n")
                            if ev.startswith(b"event: record"):
                                break
                rec = json.loads(ev.split(b"data: ", 1)[1])
                assert rec["channel"] == "4" and rec["point"] == [12.0, 1.5, 513]
            # A client whose queue is full is dropped, not waited for.
            q: asyncio.Queue[bytes | None] = asyncio.Queue(maxsize=web.CLIENT_QUEUE)
            for _ in range(web.CLIENT_QUEUE):
                q.put_nowait(b"x")
            dash._clients.add(q)
            dash._broadcast("state", {})
            assert q not in dash._clients and st.dropped_clients == 1


# --------------------------------------------------------------------------- view


@pytest.mark.timeout(120)
async def test_view_shows_a_system_known_only_through_mqtt(tmp_path: Path) -> None:
    port = _free_port()
    group = {"leader": 17, "weight": 4, "readings": 3, "t": 40.0}
    async with (
        EmbeddedBroker(port=0, anonymous=True) as broker,
        aiomqtt.Client("127.0.0.1", broker.port, identifier="gw") as gw,
    ):
        await gw.publish("aware/gateway/status", b"online", qos=1, retain=True)
        await gw.publish("aware/groups/1/513", json.dumps(group), qos=1, retain=True)
        log = (tmp_path / "view.log").open("w")
        p = subprocess.Popen(
            [sys.executable, "-m", "awaremw", "view", "--web", f"127.0.0.1:{port}",
             "--mqtt", broker.url, "--deployment", "romeo4r", "--timeout", "60"],
            stdout=log, stderr=subprocess.STDOUT,
        )  # fmt: skip
        try:
            url = f"http://127.0.0.1:{port}/api/state"

            def led() -> Any:
                d = _get_json(url)
                return (
                    d if d and d["groups"] and d["gateway"] == "online" and d["t"] >= 40 else None
                )

            d = await asyncio.to_thread(_wait, led, 30, "the view's state")
            assert len(d["motes"]) == 22
            assert d["groups"][0]["leader"] == 17 and d["groups"][0]["id"] == 513
            assert [m["id"] for m in d["motes"] if m["leader"]] == [17]
            # The robot stands where its path puts it at the time the messages carry
            # (t = 40 s: 15 s into its crossing at 0.3 m/s, past x = 4.5 m).
            robot = next(m for m in d["motes"] if m["kind"] == "robot")
            assert robot["x"] > 4.0
        finally:
            p.send_signal(signal.SIGINT)
            p.wait(timeout=20)
            log.close()


def test_busy_or_bad_address_is_a_one_line_error() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        r = subprocess.run(
            [sys.executable, "-m", "awaremw", "view", "--web", f"127.0.0.1:{port}",
             "--mqtt", "mqtt://127.0.0.1:1", "--timeout", "5"],
            capture_output=True, text=True, timeout=60, check=False,
        )  # fmt: skip
    assert r.returncode == 2
    assert r.stderr.strip().startswith("awaremw view: cannot serve the dashboard on")
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1
    r = subprocess.run([sys.executable, "-m", "awaremw", "demo", "--web", "localhost", "--plain"],
                       capture_output=True, text=True, timeout=60, check=False)  # fmt: skip
    assert r.returncode == 2 and "expected HOST:PORT" in r.stderr


# --------------------------------------------------------------------------- browser


def _browser() -> Any:
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        if REQUIRE_BROWSER:
            raise
        pytest.skip("playwright not installed (pip install -e '.[test]')")
    if not Path(CHROMIUM).exists():
        if REQUIRE_BROWSER:
            raise AssertionError(f"{CHROMIUM} missing (apt-get install chromium)")
        pytest.skip(f"{CHROMIUM} missing (apt-get install chromium)")
    return sync_playwright


@contextlib.contextmanager
def _demo(tmp_path: Path, port: int) -> Iterator[subprocess.Popen[bytes]]:
    log = (tmp_path / "demo.log").open("w")
    p = subprocess.Popen(
        [sys.executable, "-m", "awaremw", "demo", "--web", f"127.0.0.1:{port}", "--plain",
         "--speed", "4", "--duration", "400", "--mqtt-port", "0"],
        stdout=log, stderr=subprocess.STDOUT,
    )  # fmt: skip
    try:
        yield p
    finally:
        if p.poll() is None:
            p.send_signal(signal.SIGINT)
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        log.close()


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_dashboard_in_headless_chromium(tmp_path: Path) -> None:
    sync_playwright = _browser()
    port = _free_port()
    shot = tmp_path / "dashboard.png"
    n_motes = len(load("romeo4r").nodes)
    with _demo(tmp_path, port) as demo:
        url = f"http://127.0.0.1:{port}"

        def led_group() -> Any:
            assert demo.poll() is None, (tmp_path / "demo.log").read_text()[-2000:]
            d = _get_json(url + "/api/state")
            return d if d and any(g["leader"] is not None for g in d["groups"]) else None

        state = _wait(led_group, 120, "a group with a leader in /api/state")
        assert len(state["motes"]) == n_motes
        assert {"id", "kind", "x", "y", "group", "leader"} <= set(state["motes"][0])
        g = next(g for g in state["groups"] if g["leader"] is not None)
        assert {"type", "id", "leader", "members"} <= set(g) and g["leader"] in g["members"]

        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
            try:
                page = browser.new_page(viewport={"width": 1400, "height": 1000})
                errors: list[str] = []
                page.on("pageerror", lambda e: errors.append(str(e)))
                page.goto(url + "/")
                page.wait_for_selector("#live.on", timeout=20_000)
                assert page.locator("[data-mote]").count() == n_motes
                # Type 2: every lit mote (all of them) -- a group that stays while the
                # robot comes and goes; then a channel counting its members each second.
                page.fill("#group-form input[name=type]", "2")
                page.fill("#group-form input[name=conditions]", "light > 0")
                page.click("#group-form button[type=submit]")
                page.wait_for_selector("#definitions:has-text('light')", timeout=20_000)
                page.fill("#channel-form input[name=id]", "5")
                page.fill("#channel-form input[name=attr]", "temperature")
                page.fill("#channel-form input[name=group_type]", "2")
                page.fill("#channel-form input[name=group_id]", "*")
                page.fill("#channel-form input[name=period_s]", "1")
                page.select_option("#channel-form select[name=agg]", "count")
                page.click("#channel-form button[type=submit]")
                page.wait_for_selector("#form-status:has-text('aware/def/channel/5')",
                                       timeout=10_000)  # fmt: skip
                page.select_option("#gtype", "2")
                page.wait_for_selector("[data-leader]", timeout=60_000)
                plot = "svg.plot[data-channel='5']"
                page.wait_for_selector(plot, timeout=60_000)

                def points() -> int:
                    return int(page.get_attribute(plot, "data-points") or 0)

                first = points()
                page.wait_for_function(
                    f'+document.querySelector("{plot}").dataset.points > {max(first, 1)}',
                    timeout=60_000,
                )
                assert points() > first
                assert "motes" in (page.text_content(".plot-box[data-channel='5']") or "")
                page.check("#show-tree")
                page.wait_for_selector("[data-link]", timeout=10_000)
                page.screenshot(path=str(shot), full_page=True)
                assert not errors, errors
            finally:
                browser.close()
    assert shot.stat().st_size > 10_000
    if os.environ.get("AWAREMW_UPDATE_SCREENSHOT") == "1":
        shutil.copy(shot, REPO / "docs" / "img" / "dashboard.png")
