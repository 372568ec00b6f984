"""CLI: client verbs against Mosquitto, the gateway verb with its embedded broker, bench."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from mosquitto import PASSWORDS, Mosquitto, mosquitto_fixture, require  # noqa: F401

from awaremw.bench import bridge as bench_bridge
from awaremw.cli import main
from awaremw.cli.client import UsageError, parse_arg, parse_conditions, parse_target
from awaremw.gateway.mqtt import (
    MAX_PASSWORD_BYTES,
    BadPasswordFile,
    MqttSettings,
    read_password_file,
)


def retained(m: Mosquitto, topic: str) -> list[str]:
    """Retained messages under ``topic`` (mosquitto_sub exits after the retained burst)."""
    r = subprocess.run(
        [require("mosquitto_sub"), "-p", str(m.port), "-u", "operator", "-P",
         PASSWORDS["operator"], "-t", topic, "-v", "--retained-only", "-W", "1"],
        capture_output=True, timeout=10, check=False,
    )  # fmt: skip
    return r.stdout.decode().splitlines()


def test_condition_target_and_argument_parsing() -> None:
    assert parse_conditions(["temperature > 45"]) == [
        {"attr": "temperature", "op": ">", "value": 45}
    ]
    assert parse_conditions(["temperature", ">", "45.5"]) == [
        {"attr": "temperature", "op": ">", "value": 45.5}
    ]
    assert parse_conditions(["x<3 and rssi:100>=-80"]) == [
        {"attr": "x", "op": "<", "value": 3},
        {"attr": "rssi:100", "op": ">=", "value": -80},
    ]
    with pytest.raises(UsageError):
        parse_conditions(["temperature is hot"])
    assert parse_target("node:7") == {"node": 7}
    assert parse_target("group:1/*") == {"group_type": 1, "group_id": "*"}
    assert parse_target("group:1/513") == {"group_type": 1, "group_id": 513}
    with pytest.raises(UsageError):
        parse_target("robot:1")
    assert [parse_arg(a) for a in ("on=true", "n=3", "r=0.5", "c=red")] == [
        ("on", True),
        ("n", 3),
        ("r", 0.5),
        ("c", "red"),
    ]


@pytest.mark.mosquitto
def test_client_verbs_publish_the_contract(
    mosquitto: Mosquitto, capsys: pytest.CaptureFixture[str]
) -> None:
    url = ["--mqtt", mosquitto.url("operator")]
    assert main(["define", "group", "1", "temperature > 45", "--hysteresis", "1", *url]) == 0
    assert main(["define", "channel", "2", "--attr", "light", "--group-type", "1",
                 "--period", "2", "--agg", "max", *url]) == 0  # fmt: skip
    lines = retained(mosquitto, "aware/def/#")
    docs = {ln.split(" ", 1)[0]: json.loads(ln.split(" ", 1)[1]) for ln in lines}
    assert docs == {
        "aware/def/group/1": {
            "conditions": [{"attr": "temperature", "op": ">", "value": 45}],
            "hysteresis": 1.0,
        },
        "aware/def/channel/2": {
            "attr": "light",
            "group_type": 1,
            "group_id": "*",
            "period_s": 2.0,
            "agg": "max",
        },
    }
    assert main(["delete", "channel", "2", *url]) == 0
    assert [ln.split(" ")[0] for ln in retained(mosquitto, "aware/def/#")] == ["aware/def/group/1"]
    # `watch` prints what is there (here: the retained definition), as JSON lines.
    capsys.readouterr()
    assert main(["watch", "aware/def/#", "--count", "1", "--json", *url]) == 0
    out = json.loads(capsys.readouterr().out.strip())
    assert out["topic"] == "aware/def/group/1" and out["retain"] is True
    # Mistakes are reported locally, before anything is sent.
    assert main(["define", "group", "1", "temp > 45", *url]) == 2
    assert "unknown attribute 'temp'" in capsys.readouterr().err
    assert main(["command", "led", "--target", "robot:1", *url]) == 2
    assert main(["define", "channel", "1", "--attr", "x", "--period", "0.1", *url]) == 2
    # A viewer may not define: the broker drops it (nothing new retained), and the
    # verb says so (tests/test_plain_output.py has its line).
    viewer = ["--mqtt", mosquitto.url("viewer")]
    assert main(["define", "group", "3", "x > 1", *viewer]) == 1
    assert [ln.split(" ")[0] for ln in retained(mosquitto, "aware/def/#")] == ["aware/def/group/1"]


def test_gateway_verb_starts_an_embedded_broker(tmp_path: Path) -> None:
    r = subprocess.run(
        [sys.executable, "-m", "awaremw", "gateway", "grid_small", "--duration", "2",
         "--speed", "4", "--mqtt-port", "0", "--state-dir", str(tmp_path)],
        capture_output=True, timeout=60, check=False,
    )  # fmt: skip
    out = r.stdout.decode()
    assert r.returncode == 0, r.stderr.decode()[-2000:]
    assert "embedded MQTT broker: mqtt://127.0.0.1:" in out
    assert "awaremw gateway: motes 0 of grid_small" in out


def test_gateway_verb_refuses_bad_input() -> None:
    r = subprocess.run(
        [sys.executable, "-m", "awaremw", "gateway", "grid_small", "--mqtt", "http://x"],
        capture_output=True,
        timeout=60,
        check=False,
    )
    assert r.returncode == 2 and b"scheme must be mqtt:// or mqtts://" in r.stderr


def _gateway(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "awaremw", "gateway", "grid_small", *args],
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip


@pytest.mark.mosquitto
def test_gateway_takes_its_mqtt_password_from_a_file(mosquitto: Mosquitto, tmp_path: Path) -> None:
    """--mqtt-password-file: the password stays off the command line, and only the
    right one lets the gateway in (its retained status shows it was connected)."""
    url = f"mqtt://gateway@127.0.0.1:{mosquitto.port}"
    wrong = tmp_path / "wrong"
    wrong.write_text("not-the-password\n")
    r = _gateway("--mqtt", url, "--mqtt-password-file", str(wrong), "--duration", "2",
                 "--speed", "4", "--no-hbn")  # fmt: skip
    assert r.returncode == 0, r.stderr[-2000:]
    assert retained(mosquitto, "aware/gateway/status") == []  # refused: never connected
    right = tmp_path / "pw"
    right.write_text(PASSWORDS["gateway"] + "\n")  # as `echo PW > FILE` writes it
    right.chmod(0o600)
    r = _gateway("--mqtt", url, "--mqtt-password-file", str(right), "--duration", "2",
                 "--speed", "4", "--no-hbn")  # fmt: skip
    assert r.returncode == 0, r.stderr[-2000:]
    assert f"MQTT {url} prefix" in r.stdout and PASSWORDS["gateway"] not in r.stdout + r.stderr
    assert retained(mosquitto, "aware/gateway/status") == ["aware/gateway/status offline"]


def test_gateway_password_file_errors(tmp_path: Path) -> None:
    url = "mqtt://gateway@127.0.0.1:1"
    empty, newline, unreadable = tmp_path / "empty", tmp_path / "newline", tmp_path / "locked"
    empty.write_bytes(b"")
    newline.write_bytes(b"\n")
    unreadable.write_text("pw")
    unreadable.chmod(0)
    cases = [
        ([url, str(tmp_path / "none")], f"MQTT password file {tmp_path / 'none'}: not found"),
        ([url, str(empty)], f"MQTT password file {empty}: empty"),
        ([url, str(newline)], f"MQTT password file {newline}: empty"),
        ([url, str(tmp_path)], f"MQTT password file {tmp_path}: cannot read: Is a directory"),
        (["mqtt://gateway:pw@127.0.0.1:1", str(empty)], "do not combine"),
        (["mqtt://127.0.0.1:1", str(empty)], "names none: mqtt[s]://USER@HOST:PORT"),
    ]
    if os.geteuid() != 0:  # root reads any file
        cases.append(([url, str(unreadable)], "cannot read: Permission denied"))
    for (mqtt, path), why in cases:
        r = _gateway("--mqtt", mqtt, "--mqtt-password-file", path)
        assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
        assert r.stderr.startswith("awaremw gateway: ") and why in r.stderr, (why, r.stderr)
    r = _gateway("--mqtt-password-file", str(empty))  # the embedded broker has its own account
    assert r.returncode == 2 and "--mqtt-password-file is for the user of --mqtt" in r.stderr


def test_password_file_strips_one_trailing_newline_only(tmp_path: Path) -> None:
    f = tmp_path / "pw"
    for data, password in ((b"pw\n", "pw"), (b"pw\r\n", "pw"), (b"pw", "pw"),
                           (b"pw\n\n", "pw\n"), (b" p\rw \n", " p\rw ")):  # fmt: skip
        f.write_bytes(data)
        assert read_password_file(f) == password, data
    f.write_bytes(b"\xff\n")
    with pytest.raises(BadPasswordFile, match="not UTF-8"):
        read_password_file(f)
    f.write_bytes(b"x" * (MAX_PASSWORD_BYTES + 1))
    with pytest.raises(BadPasswordFile, match="longer than"):
        read_password_file(f)
    settings = MqttSettings.from_url("mqtts://gateway@broker:8883")
    f.write_bytes(b"secret\n")
    assert settings.with_password_file(f).password == "secret"


def test_bench_bridge_throughput_keys() -> None:
    p = argparse.ArgumentParser()
    bench_bridge.add_arguments(p)
    out = bench_bridge.run(
        p.parse_args(["--no-fleet", "--records", "300", "--samples", "120", "--rate", "60"])
    )
    assert out["records_per_s"] > 0 and out["throughput_records"] == 300
    assert {"latency_p50_ms", "latency_p99_ms", "records_per_s"} <= set(out)
    assert out["latency_p50_ms"] is None  # no fleet: no end-to-end latency
    # The paced run times every one of its records through the bridge.
    assert out["bridge_samples"] == 120 and out["bridge_rate_per_s"] == 60
    assert 0 < out["bridge_p50_ms"] <= out["bridge_p99_ms"] <= out["bridge_max_ms"]
