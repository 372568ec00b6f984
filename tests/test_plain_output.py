"""What the verbs print when something is wrong (issue 33, items 4 and 5):
no password they were given in any output, and errors that say what to do
next, each with its exact line. Real processes, real brokers and routers on
loopback."""

from __future__ import annotations

import asyncio
import json
import logging
import os
import socket
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import aiomqtt
import pytest
from mosquitto import Mosquitto, mosquitto_fixture  # noqa: F401

from awaremw.cli.client import publish
from awaremw.gateway.broker import EmbeddedBroker
from awaremw.gateway.mqtt import MqttSettings
from awaremw.runtime.deployment import DeploymentError, parse_deployment
from awaremw.runtime.zenoh_session import free_tcp_endpoint
from awaremw.security.redact import mask_url, redact

SECRET = "s3cret-pw"


def _accepts(host: str, port: int) -> bool:
    with socket.socket() as s:
        return s.connect_ex((host, port)) == 0


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def awaremw(
    args: list[str], tmp: Path, timeout: float = 90.0
) -> tuple[int | None, str]:  # fmt: skip
    """Run a verb in a fresh state directory; (exit code or None if it ran on, output)."""
    env = {**os.environ, "XDG_STATE_HOME": str(tmp / "state")}
    try:
        done = subprocess.run(
            [sys.executable, "-m", "awaremw", *args],
            capture_output=True, text=True, timeout=timeout, env=env, cwd=tmp, check=False,
        )  # fmt: skip
    except subprocess.TimeoutExpired as e:  # a verb that runs on (view): what it printed
        out = (e.stdout or b"") + (e.stderr or b"")
        return None, out.decode() if isinstance(out, bytes) else out
    return done.returncode, done.stdout + done.stderr


def test_redact_masks_every_password_in_free_text() -> None:
    line = "cannot reach mqtt://viewer:s3cret-pw@host:1 nor mqtts://op:p@ss@10.0.0.1:8883 (x)"
    masked = "cannot reach mqtt://viewer:***@host:1 nor mqtts://op:***@10.0.0.1:8883 (x)"
    assert redact(line) == masked
    assert mask_url("mqtt://viewer@host:1") == "mqtt://viewer@host:1"  # no password: as it is
    assert mask_url("mqtt://host:1") == "mqtt://host:1"


@pytest.mark.timeout(300)
def test_no_verb_prints_a_password_it_was_given(tmp_path: Path) -> None:
    url = f"mqtt://viewer:{SECRET}@127.0.0.1:{_closed_port()}"
    nowhere = free_tcp_endpoint()
    runs = {
        "define": ["define", "group", "2", "temperature > 45", "--mqtt", url],
        "delete": ["delete", "group", "2", "--mqtt", url],
        "command": ["command", "led", "--target", "all", "--arg", "state=on", "--mqtt", url],
        "watch": ["watch", "x/#", "--count", "1", "--mqtt", url],
        "bad url": ["define", "group", "2", "temperature > 45", "--mqtt",
                    f"mqtt://viewer:{SECRET}@127.0.0.1:notaport"],
        "gateway": ["gateway", "grid_small", "--mqtt", url, "--connect", nowhere],
        "demo": ["demo", "--mqtt", url, "--duration", "5", "--plain"],
        "experiment": ["experiment", "romeo4r", "--mqtt", url, "--duration", "5", "--plain",
                       "--out", str(tmp_path / "exp")],
        "bench bridge": ["bench", "bridge", "--mqtt", url, "--json"],
        "view": ["view", "--mqtt", url, "--web", "127.0.0.1:0"],
    }  # fmt: skip
    outputs = {}
    for name, args in runs.items():
        code, out = awaremw(args, tmp_path, timeout=8.0 if name == "view" else 90.0)
        outputs[name] = out
        assert SECRET not in out, (name, out)
        if name != "view":
            assert code not in (0, None), (name, code, out)  # every one of them failed
    assert "viewer:***@" in outputs["define"]
    for path in (tmp_path / "exp").rglob("*"):
        if path.is_file() and path.suffix in (".json", ".txt"):
            assert SECRET not in path.read_text(encoding="utf-8"), path


def test_a_client_verb_with_no_broker_says_to_start_the_gateway(tmp_path: Path) -> None:
    if _accepts("127.0.0.1", 1883):
        pytest.skip("something listens on 127.0.0.1:1883, the client verbs' default")
    code, out = awaremw(["define", "group", "1", "temperature > 15"], tmp_path)
    assert code == 1
    assert out.strip().splitlines()[-1] == (
        "awaremw: MQTT mqtt://127.0.0.1:1883: [Errno 111] Connection refused; no broker answers "
        "there: start `awaremw gateway DEPLOYMENT` (it runs the embedded broker), or give --mqtt "
        "mqtt://USER:PASS@HOST:PORT"
    )


@pytest.mark.timeout(120)
def test_a_secured_router_that_refused_us_is_told_from_one_that_is_not_there(
    tmp_path: Path,
) -> None:
    secrets = tmp_path / "secrets"
    assert awaremw(["keys", "init", str(secrets)], tmp_path)[0] == 0
    ep = free_tcp_endpoint()
    env = {**os.environ, "XDG_STATE_HOME": str(tmp_path / "state")}
    router = subprocess.Popen(
        [sys.executable, "-m", "awaremw", "router", "--secrets", str(secrets), "--listen", ep],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env,
    )  # fmt: skip
    try:
        host, port = ep.removeprefix("tcp/").rsplit(":", 1)
        deadline = time.monotonic() + 30.0
        while not _accepts(host, int(port)):  # wait until the router listens
            assert router.poll() is None, router.stdout.read() if router.stdout else ""
            assert time.monotonic() < deadline, "the router did not listen within 30 s"
            time.sleep(0.05)
        code, out = awaremw(["fleet-ctl", "--connect", ep, "list"], tmp_path)
        assert code == 1
        assert out.strip().splitlines()[-1] == (
            f"awaremw fleet-ctl: cannot reach {ep}: a router listens there but refused the "
            "session: it is secured, give --secrets DIR (the directory of `awaremw keys init`)"
        )
    finally:
        router.terminate()
        router.wait(timeout=20)
    nothing = f"tcp/127.0.0.1:{_closed_port()}"
    code, out = awaremw(["fleet-ctl", "--connect", nothing, "list"], tmp_path)
    assert code == 1
    assert out.strip().splitlines()[-1] == (
        f"awaremw fleet-ctl: cannot reach {nothing}: nothing listens there (is `awaremw router` "
        "running? check --connect)"
    )


async def test_the_embedded_broker_does_not_log_a_silent_connection_as_an_error(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.DEBUG, logger="amqtt")
    async with EmbeddedBroker(state_dir=tmp_path / "b") as broker:
        for _ in range(3):  # a port probe: connect, say nothing, close
            _, w = await asyncio.open_connection("127.0.0.1", broker.port)
            w.close()
            await w.wait_closed()
        async with aiomqtt.Client("127.0.0.1", broker.port, username=broker.username,
                                  password=broker.password) as c:  # fmt: skip
            await c.publish("x/y", b"1", qos=1)  # the broker served the probes and this
    errors = [r for r in caplog.records if r.name.startswith("amqtt") and r.levelno >= 40]
    assert errors == [], [r.getMessage() for r in errors]


def test_experiment_takes_a_deployment_file(tmp_path: Path) -> None:
    romeo = (Path(__file__).resolve().parent.parent / "nodes" / "romeo4r.toml").read_text()
    plain = tmp_path / "plain.toml"
    plain.write_text(romeo, encoding="utf-8")
    code, out = awaremw(["experiment", str(plain), "--virtual"], tmp_path)
    assert code == 2
    assert out.strip().splitlines()[-1] == (
        f"awaremw experiment: {plain}: to run it as an experiment, its [experiment] table needs "
        "analysis = one of city, failover, fire, large, romeo4r"
    )
    mine = tmp_path / "mine.toml"
    mine.write_text(romeo.replace("[experiment]\n", '[experiment]\nanalysis = "romeo4r"\n'))
    code, out = awaremw(
        ["experiment", str(mine), "--virtual", "--seeds", "1", "--out", str(tmp_path / "o")],
        tmp_path,
    )
    assert code == 0, out
    assert json.loads((tmp_path / "o" / "summary.json").read_text())["n"] == 1


@pytest.mark.parametrize("key", ["tx_powr_dbm", "positon"])
def test_a_misspelt_node_key_is_refused_as_unknown_with_every_allowed_key(key: str) -> None:
    node = {"id": 1, "kind": "tmote", "position": [1.0, 1.0], key: 0}
    if key == "positon":
        node = {"id": 1, "kind": "tmote", "positon": [1.0, 1.0]}
    with pytest.raises(DeploymentError) as e:
        parse_deployment({"area": [10.0, 10.0], "nodes": [node]}, Path("x.toml"))
    assert str(e.value) == (
        f"x.toml: nodes[0] (id 1): unknown key(s) '{key}' (allowed: battery_mj, boot_s, id, "
        "kind, loop, middleware, noise, path, pause_s, position, speed_mps, start_s, tx_power_dbm)"
    )


async def test_watch_prints_utf8(tmp_path: Path) -> None:
    async with EmbeddedBroker(state_dir=tmp_path / "b") as broker:
        async with aiomqtt.Client("127.0.0.1", broker.port, username=broker.username,
                                  password=broker.password) as c:  # fmt: skip
            await c.publish("x/t", json.dumps({"unit": "°C"}).encode(), qos=1, retain=True)
        proc = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "awaremw", "watch", "x/#", "--count", "1", "--json",
            "--mqtt", broker.url, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
            env={**os.environ, "XDG_STATE_HOME": str(tmp_path / "state")},
        )  # fmt: skip
        out, err = await asyncio.wait_for(proc.communicate(), 60)
    assert proc.returncode == 0, err
    line = out.decode("utf-8").strip()
    assert '"unit": "°C"' in line and "\\u00b0" not in line


@pytest.mark.mosquitto
@pytest.mark.parametrize("wait", [[], ["--wait", "3"]], ids=["no-wait", "wait"])
def test_define_with_a_read_only_account_is_refused_in_one_line(
    mosquitto: Mosquitto, tmp_path: Path, wait: list[str]
) -> None:
    url = f"mqtt://viewer:viewer-pw@127.0.0.1:{mosquitto.port}"
    code, out = awaremw(["define", "group", "2", "temperature > 45", "--mqtt", url, *wait],
                        tmp_path)  # fmt: skip
    # Mosquitto speaks MQTT 5: its PUBACK says why.
    assert code == 1
    assert out.strip().splitlines() == [
        "awaremw: the broker refused aware/def/group/2 from the account 'viewer': Not authorized"
    ]
    # The operator, who may write definitions, is not refused.
    op = f"mqtt://operator:operator-pw@127.0.0.1:{mosquitto.port}"
    code, out = awaremw(["define", "group", "2", "temperature > 45", "--mqtt", op], tmp_path)
    assert code == 0, out


@pytest.mark.mosquitto
def test_define_wait_with_no_gateway_says_nobody_took_it(
    mosquitto: Mosquitto, tmp_path: Path
) -> None:
    """The broker keeps the definition, but no gateway republishes it with a version
    nor refuses it: --wait says so and exits 1; without --wait the client cannot tell."""
    op = f"mqtt://operator:operator-pw@127.0.0.1:{mosquitto.port}"
    code, out = awaremw(["define", "group", "3", "temperature > 45", "--mqtt", op,
                         "--wait", "1.5"], tmp_path)  # fmt: skip
    assert code == 1
    assert out.strip().splitlines() == [
        "awaremw: no gateway took aware/def/group/3 within 1.5 s (no version on the retained "
        "topic, no error on aware/errors): is `awaremw gateway` running on this broker with "
        "prefix 'aware'?"
    ]
    code, out = awaremw(["define", "group", "3", "temperature > 45", "--mqtt", op], tmp_path)
    assert code == 0 and out.startswith("aware/def/group/3 "), out


@pytest.mark.mosquitto
def test_a_refused_command_names_the_account_topic_and_reason(
    mosquitto: Mosquitto, tmp_path: Path
) -> None:
    url = f"mqtt://viewer:viewer-pw@127.0.0.1:{mosquitto.port}"
    code, out = awaremw(["command", "led", "--target", "all", "--arg", "state=on",
                         "--mqtt", url], tmp_path)  # fmt: skip
    assert code == 1
    assert out.strip().splitlines() == [
        "awaremw: the broker refused aware/cmd/led from the account 'viewer': Not authorized"
    ]


@pytest.mark.mosquitto
async def test_on_mqtt_3_1_1_the_read_back_is_the_check(mosquitto: Mosquitto) -> None:
    """MQTT 3.1.1 has no refusal in its PUBACK: Mosquitto acknowledges and drops the
    publish, and reading the retained message back is how the client tells."""
    s = MqttSettings.from_url(mosquitto.url("viewer"), protocol="3.1.1")
    answer = await publish(s, "def/group/4", b'{"conditions": [{"attr": "x", "op": ">", '
                           b'"value": 1}]}', retain=True)  # fmt: skip
    assert answer.error is not None and answer.error["code"] == "not_retained"
    five = await publish(replace(s, protocol="auto"), "def/group/4", b"", retain=True)
    assert five.error is not None and five.error["code"] == "refused_by_broker"
    assert five.error["error"].endswith("from the account 'viewer': Not authorized")
