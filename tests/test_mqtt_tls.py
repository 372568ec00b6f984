"""MQTT over TLS with the certificates of ``awaremw keys init``: a real Mosquitto run
from ``broker_cfg/mosquitto.conf`` pointed at ``DIR/mqtt`` (plain and TLS listener,
the generated accounts and ACL), the ``awaremw`` client verbs and a real gateway
(an ``awaremw gateway`` process beside a sensor fleet on Zenoh) over ``mqtts://``."""

from __future__ import annotations

import asyncio
import contextlib
import datetime
import json
import os
import socket
import ssl
import stat
import subprocess
import sys
import time
from collections.abc import AsyncIterator, Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import aiomqtt
import pytest
from cryptography import x509
from cryptography.hazmat.primitives import hashes
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID
from mosquitto import free_port, require

from awaremw.cli import main as cli_main
from awaremw.nodes import KindsFactory, kind_names
from awaremw.runtime.deployment import load
from awaremw.runtime.fleet import Fleet, FleetSettings
from awaremw.runtime.zenoh_session import free_tcp_endpoint
from awaremw.security.keys import SecretsDir, SecretsExist, init_secrets, make_broker_tls

ROOT = Path(__file__).resolve().parent.parent
AWAREMW = [sys.executable, "-m", "awaremw"]
SPEED = 4.0


def san_of(cert: x509.Certificate) -> tuple[list[str], list[str]]:
    san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    return san.get_values_for_type(x509.DNSName), [
        str(a) for a in san.get_values_for_type(x509.IPAddress)
    ]


def test_keys_init_makes_a_ca_and_a_broker_certificate(tmp_path: Path) -> None:
    d = SecretsDir(tmp_path / "s")
    assert (
        cli_main(["keys", "init", str(d.root), "--tls-host", "mqtt.lab", "--tls-host", "10.1.2.3"])
        == 0
    )
    for key in (d.mqtt.ca_key, d.mqtt.server_key, d.mqtt.ca_cert, d.mqtt.server_cert):
        assert stat.S_IMODE(key.stat().st_mode) == 0o600, key
    ca = x509.load_pem_x509_certificate(d.mqtt.ca_cert.read_bytes())
    server = x509.load_pem_x509_certificate(d.mqtt.server_cert.read_bytes())
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    assert not server.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    eku = server.extensions.get_extension_for_class(x509.ExtendedKeyUsage).value
    assert list(eku) == [ExtendedKeyUsageOID.SERVER_AUTH]
    dns, ips = san_of(server)
    assert dns == ["localhost", "broker", "mqtt.lab"] and ips == ["127.0.0.1", "::1", "10.1.2.3"]
    # signed by the CA (and the CA by itself); valid now
    ca_pub = ca.public_key()
    assert isinstance(ca_pub, ec.EllipticCurvePublicKey)
    assert server.issuer == ca.subject
    ca_pub.verify(server.signature, server.tbs_certificate_bytes, ec.ECDSA(hashes.SHA256()))
    ca_pub.verify(ca.signature, ca.tbs_certificate_bytes, ec.ECDSA(hashes.SHA256()))
    now = datetime.datetime.now(datetime.UTC)
    assert server.not_valid_before_utc < now < server.not_valid_after_utc
    assert json.loads(d.manifest.read_text())["mqtt_tls_hosts"][-2:] == ["mqtt.lab", "10.1.2.3"]
    # --exist-ok keeps a complete set (containers run it at every start)...
    before = d.mqtt.server_key.read_bytes()
    assert cli_main(["keys", "init", str(d.root), "--exist-ok"]) == 0
    assert d.mqtt.server_key.read_bytes() == before
    # ...but not an incomplete one
    d.mqtt.ca_key.unlink()
    assert cli_main(["keys", "init", str(d.root), "--exist-ok"]) == 1
    with pytest.raises(SecretsExist):
        init_secrets(d.root, exist_ok=True)
    with pytest.raises(ValueError, match="bad TLS host"):
        make_broker_tls(["mqtt://x"])


@dataclass
class TlsBroker:
    secrets: SecretsDir
    port: int
    tls_port: int
    passwords: dict[str, str]

    def url(self, user: str, host: str = "127.0.0.1") -> str:
        return f"mqtts://{user}:{self.passwords[user]}@{host}:{self.tls_port}"

    @property
    def ca(self) -> str:
        return str(self.secrets.mqtt.ca_cert)


def broker_conf(d: SecretsDir, port: int, tls_port: int, log: Path) -> str:
    """broker_cfg/mosquitto.conf pointed at DIR/mqtt as docs/security.md says: its
    /mosquitto/secrets/ paths replaced, ports on loopback, persistence off."""
    out = []
    for line in (ROOT / "broker_cfg" / "mosquitto.conf").read_text().splitlines():
        line = line.replace("/mosquitto/secrets/", f"{d.root / 'mqtt'}/")
        if line == "listener 1883":
            line = f"listener {port} 127.0.0.1"
        elif line == "listener 8883":
            line = f"listener {tls_port} 127.0.0.1"
        elif line.startswith(("persistence", "log_dest")):
            continue
        out.append(line)
    assert f"listener {tls_port} 127.0.0.1" in out and any(ln.startswith("certfile") for ln in out)
    out.append(f"log_dest file {log}")
    if os.geteuid() == 0:
        out.append("user root")  # else mosquitto drops to a user that cannot read 0600 files
    return "\n".join(out) + "\n"


@pytest.fixture(scope="module")
def tls_broker(tmp_path_factory: pytest.TempPathFactory) -> Iterator[TlsBroker]:
    binary = require("mosquitto")
    tmp = tmp_path_factory.mktemp("tls")
    d = SecretsDir(tmp / "secrets")
    init_secrets(d.root)
    port, tls_port = free_port(), free_port()
    conf = tmp / "mosquitto.conf"
    log = tmp / "mosquitto.log"
    conf.write_text(broker_conf(d, port, tls_port, log))
    proc = subprocess.Popen([binary, "-c", str(conf)], stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 10
        while True:  # the broker gives no readiness signal: poll its TLS port
            assert proc.poll() is None, (proc.stderr.read() if proc.stderr else b"").decode()
            with (
                contextlib.suppress(OSError),
                socket.create_connection(("127.0.0.1", tls_port), 0.2),
            ):
                break
            assert time.monotonic() < deadline, "mosquitto did not open its TLS listener"
            time.sleep(0.02)
        yield TlsBroker(d, port, tls_port, json.loads(d.mqtt.accounts.read_text()))
    finally:
        proc.terminate()
        proc.wait(10)


def cli(*args: str, timeout: float = 30) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*AWAREMW, *args], capture_output=True, text=True, timeout=timeout, check=False
    )


@pytest.mark.mosquitto
def test_client_verbs_over_mqtts_verify_the_broker(tls_broker: TlsBroker) -> None:
    b = tls_broker
    # the certificate names localhost and 127.0.0.1: both verify with DIR/mqtt/ca.crt
    r = cli("define", "group", "7", "x > 3", "--mqtt", b.url("operator", "localhost"),
            "--ca-file", b.ca)  # fmt: skip
    assert r.returncode == 0, r.stderr
    r = cli("watch", "aware/def/group/#", "--count", "1", "--timeout", "15",
            "--mqtt", b.url("operator"), "--ca-file", b.ca)  # fmt: skip
    assert r.returncode == 0, r.stderr
    topic, payload = r.stdout.strip().split(" ", 1)
    assert topic == "aware/def/group/7" and json.loads(payload)["conditions"][0]["attr"] == "x"
    # without the CA the broker's certificate is not trusted: nothing is sent
    r = cli("define", "group", "8", "x > 3", "--mqtt", b.url("operator"))
    assert r.returncode == 1 and "certificate verify failed" in r.stderr, r.stderr
    # a wrong password is refused on the TLS listener too (the same accounts)
    bad = f"mqtts://operator:wrong@127.0.0.1:{b.tls_port}"
    r = cli("define", "group", "8", "x > 3", "--mqtt", bad, "--ca-file", b.ca)
    assert r.returncode == 1 and "not authori" in r.stderr.lower(), r.stderr


@contextlib.asynccontextmanager
async def sensor_fleet() -> AsyncIterator[tuple[Fleet, str]]:
    """The 25 sensor motes of grid_small, listening on a loopback Zenoh endpoint."""
    dep = load("grid_small", kind_names())
    ep = free_tcp_endpoint()
    settings = FleetSettings(name="sensors", speed=SPEED, listen=(ep,))
    async with Fleet(dep, KindsFactory(), settings, node_filter=lambda s: s.kind != "gateway") as f:
        yield f, ep


def tls_client(b: TlsBroker, user: str) -> aiomqtt.Client:
    return aiomqtt.Client(
        "localhost",
        b.tls_port,
        username=user,
        password=b.passwords[user],
        identifier=f"test-{user}",
        tls_context=ssl.create_default_context(cafile=b.ca),
    )


@pytest.mark.mosquitto
@pytest.mark.zenoh
@pytest.mark.slow
async def test_gateway_over_mqtts_delivers_records(tls_broker: TlsBroker) -> None:
    b = tls_broker
    seen: list[tuple[str, bytes]] = []
    changed = asyncio.Event()

    async def until(pred: Callable[[], bool], timeout: float) -> None:
        async def loop() -> None:
            while not pred():
                changed.clear()
                await changed.wait()

        try:
            await asyncio.wait_for(loop(), timeout)
        except TimeoutError:
            raise AssertionError(f"timed out; seen {seen[-5:]!r}") from None

    async with sensor_fleet() as (fleet, ep), tls_client(b, "viewer") as viewer:
        await viewer.subscribe("aware/#", qos=1)

        async def collect() -> None:
            async for m in viewer.messages:
                seen.append((m.topic.value, m.payload if isinstance(m.payload, bytes) else b""))
                changed.set()

        collector = asyncio.create_task(collect())
        gw = await asyncio.create_subprocess_exec(
            *AWAREMW, "gateway", "grid_small", "--connect", ep,
            "--mqtt", b.url("gateway", "localhost"), "--ca-file", b.ca,
            "--speed", str(SPEED), "--start-wall", repr(fleet.clock.start_wall),
            stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.PIPE,
        )  # fmt: skip
        try:
            await until(lambda: ("aware/gateway/status", b"online") in seen, 30)
            async with tls_client(b, "operator") as op:
                group = {"conditions": [{"attr": "x", "op": ">", "value": 3}]}
                chan = {"attr": "temperature", "group_type": 1, "group_id": "*",
                        "period_s": 1.0, "agg": "avg"}  # fmt: skip
                await op.publish("aware/def/group/1", json.dumps(group), qos=1, retain=True)
                await op.publish("aware/def/channel/1", json.dumps(chan), qos=1, retain=True)

            def records() -> list[dict[str, object]]:
                return [json.loads(p) for t, p in seen if t.startswith("aware/data/1/1/")]

            await until(lambda: len(records()) >= 2, 60)
            assert all(r["agg"] == "avg" and 15 < float(str(r["value"])) < 40 for r in records())
            assert not [t for t, _ in seen if t == "aware/errors"]
        finally:
            collector.cancel()
            with contextlib.suppress(asyncio.CancelledError, aiomqtt.MqttError):
                await collector
            if gw.returncode is None:
                gw.terminate()
                await asyncio.wait_for(gw.wait(), 15)
