"""``--secrets DIR`` wired into every process: the loader, the core factory, and
real ``awaremw router`` + ``fleet`` + ``gateway`` processes with a real Mosquitto,
a definition over MQTT yielding records (sealed frames across processes, items
signed by the gateway and verified by every mote) and a rogue radio (the fleet's
Zenoh account, no network key) whose replays are refused and counted in
``awaremw fleet-ctl stats``."""

from __future__ import annotations

import asyncio
import json
import os
import pickle
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh
from mosquitto import Mosquitto, MosquittoSub, mosquitto_fixture, pub  # noqa: F401

from awaremw.gateway.service import attach_to_fleet
from awaremw.nodes import KindsFactory, kind_names
from awaremw.protocol.mote import AwareMote
from awaremw.radio.envelope import Kind, decode_envelope, encode_envelope
from awaremw.runtime.deployment import load
from awaremw.runtime.fleet import Fleet, FleetSettings
from awaremw.runtime.zenoh_session import free_tcp_endpoint
from awaremw.security.keys import SecretsDir, init_secrets
from awaremw.security.material import (
    OPEN_WARNING,
    check_secrets,
    load_radio_security,
    load_signing_key,
)
from awaremw.security.zenoh_acl import SecretsError

AWAREMW = [sys.executable, "-m", "awaremw"]
SPEED = 4.0
GROUP = json.dumps({"conditions": [{"attr": "x", "op": ">", "value": 3}]})
CHANNEL = json.dumps(
    {"attr": "temperature", "group_type": 1, "group_id": "*", "period_s": 1.0, "agg": "avg"}
)


@pytest.fixture(scope="module")
def secrets(tmp_path_factory: pytest.TempPathFactory) -> SecretsDir:
    d = SecretsDir(tmp_path_factory.mktemp("sec") / "secrets")
    init_secrets(d.root)
    return d


# --------------------------------------------------------------------------- the loader


def test_loader_gives_the_fleets_the_public_key_and_only_the_gateway_the_private_one(
    secrets: SecretsDir, tmp_path: Path
) -> None:
    sec = load_radio_security(secrets.root)
    assert sec.network_key == secrets.network_key.read_bytes() and sec.overhead == 12
    assert sec.gateway_public_key is not None and len(sec.gateway_public_key) == 32
    assert check_secrets(secrets.root) == sec
    key = load_signing_key(secrets.root, sec.gateway_public_key)
    assert len(key) == 32
    # a private key from another `keys init` does not match the motes' public key
    other = SecretsDir(tmp_path / "other")
    init_secrets(other.root)
    with pytest.raises(SecretsError, match="does not match"):
        load_signing_key(other.root, sec.gateway_public_key)
    # a missing or damaged file is named, with what to do
    other.network_key.unlink()
    with pytest.raises(SecretsError, match=r"network\.key not found.*keys init"):
        load_radio_security(other.root)
    other.network_key.write_bytes(b"x" * 20)
    with pytest.raises(SecretsError, match="16 raw bytes"):
        load_radio_security(other.root)
    other.signing_pub.write_bytes(b"not pem")
    with pytest.raises(SecretsError, match=r"gateway\.pub"):
        load_radio_security(other.root)
    # a 32-byte network key (`keys init --network-key-bytes 32`) is AES-256-CCM
    big = SecretsDir(tmp_path / "big")
    init_secrets(big.root, network_key_bytes=32)
    assert len(load_radio_security(big.root).network_key) == 32


def test_kinds_factory_builds_secured_motes_and_only_a_signing_factory_signs(
    secrets: SecretsDir,
) -> None:
    dep = load("grid_small", kind_names())  # CC2420: 100-byte MTU
    sec = load_radio_security(secrets.root)
    fleet_factory = pickle.loads(pickle.dumps(KindsFactory(security=sec)))  # to a worker
    gw_factory = KindsFactory(security=sec, signing_key=load_signing_key(secrets.root))
    gw_spec = next(s for s in dep.nodes if s.kind == "gateway")
    sensor = next(s for s in dep.nodes if s.kind != "gateway")
    for factory, spec, signs in (
        (fleet_factory, gw_spec, False),
        (fleet_factory, sensor, False),
        (gw_factory, gw_spec, True),
        (gw_factory, sensor, False),
    ):
        core = factory(spec, dep)
        assert isinstance(core, AwareMote)
        assert core.config.mtu == 88  # 100 - 4-byte counter - 8-byte MIC
        assert core.config.gateway_public_key == sec.gateway_public_key
        assert (core.dissemination.signer is not None) is signs, (spec.kind, signs)
    assert "signing" not in repr(gw_factory) and not fleet_factory.signs
    with pytest.raises(ValueError, match="needs the radio security"):
        KindsFactory(signing_key=b"k" * 32)
    plain = KindsFactory()(sensor, dep)
    assert isinstance(plain, AwareMote) and plain.config.mtu == 100
    assert plain.config.gateway_public_key is None


@pytest.mark.zenoh
async def test_gateway_service_checks_definitions_against_the_secured_mtu(
    secrets: SecretsDir,
) -> None:
    """romeo4r (CC1000, 64-byte MTU): 52 bytes left; a definition that fits 64 bytes
    unsecured (5 conditions: a 60-byte frame) is refused with does_not_fit_mtu."""
    dep = load("romeo4r", kind_names())
    sec = load_radio_security(secrets.root)
    settings = FleetSettings(
        name="gw", listen=(free_tcp_endpoint(),), control=False, autostart=False, security=sec
    )
    factory = KindsFactory(security=sec, signing_key=load_signing_key(secrets.root))
    async with Fleet(dep, factory, settings, node_filter=lambda s: s.kind == "gateway") as fleet:
        assert fleet.medium.payload_mtu == 52 and fleet.medium.guard is not None
        svc = attach_to_fleet(fleet, hbn=False)
        assert svc.config.mtu == 52
        conds = [{"attr": "temperature", "op": ">", "value": 20.123 + i} for i in range(5)]
        out = svc.handle("def/group/3", json.dumps({"conditions": conds}).encode())
        assert out.error is not None and out.error.code == "does_not_fit_mtu", out
        ok = svc.handle("def/group/3", json.dumps({"conditions": conds[:4]}).encode())
        assert ok.error is None


# --------------------------------------------------------------------------- processes


class Proc:
    """A CLI subprocess whose stdout lines are collected by a thread."""

    def __init__(self, *args: str) -> None:
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        self.p = subprocess.Popen(
            [*AWAREMW, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env
        )
        self.lines: list[str] = []
        self._cv = threading.Condition()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.p.stdout is not None
        for line in self.p.stdout:
            with self._cv:
                self.lines.append(line)
                self._cv.notify_all()
        with self._cv:
            self._cv.notify_all()

    def wait_line(self, needle: str, timeout: float = 60.0) -> str:
        def found() -> str | None:
            return next((ln for ln in self.lines if needle in ln), None)

        with self._cv:
            ok = self._cv.wait_for(
                lambda: found() is not None or self.p.poll() is not None, timeout
            )
            line = found()
        if not ok or line is None:
            err = self.p.stderr.read() if self.p.poll() is not None and self.p.stderr else ""
            raise AssertionError(f"no line {needle!r}; got {self.lines[-5:]!r} {err[-2000:]}")
        return line

    def stop(self) -> str:
        if self.p.poll() is None:
            self.p.terminate()
        try:
            _, err = self.p.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            self.p.kill()
            _, err = self.p.communicate()
        return err


def ctl_stats(ep: str, sec: Path) -> list[dict[str, Any]]:
    r = subprocess.run(
        [*AWAREMW, "fleet-ctl", "--connect", ep, "--secrets", str(sec), "--timeout", "2", "stats"],
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    return [json.loads(ln) for ln in r.stdout.splitlines() if ln.strip()]


def refused(snaps: list[dict[str, Any]]) -> dict[str, int]:
    out: dict[str, int] = {}
    for s in snaps:
        for reason, n in (s.get("refused") or {}).items():
            out[reason] = out.get(reason, 0) + n
    return out


class Rogue:
    """A Zenoh session with the fleet's credentials but no network key: it hears
    the radio and puts captured frames back."""

    def __init__(self, secrets: SecretsDir, ep: str) -> None:
        conf = zenoh.Config.from_file(str(secrets.role_config("fleet")))
        conf.insert_json5("connect/endpoints", json.dumps([ep]))
        self.session = zenoh.open(conf)
        self.captured: list[tuple[str, bytes]] = []
        self._cv = threading.Condition()
        self.sub = self.session.declare_subscriber("aware/radio/**", self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        with self._cv:
            if len(self.captured) < 200:
                self.captured.append((str(sample.key_expr), sample.payload.to_bytes()))
            self._cv.notify_all()

    def wait(self, cond: Callable[[], bool], timeout: float) -> bool:
        with self._cv:
            return self._cv.wait_for(cond, timeout)

    def replay(self) -> int:
        """Put back every captured frame twice: as it was, and with a fresh link
        sequence number (the MIC covers it). The number of envelopes put."""
        n = 0
        for key, data in list(self.captured):
            env = decode_envelope(data)
            if env.kind != Kind.FRAME:
                continue
            fresh = encode_envelope(Kind.FRAME, env.src, env.x, env.y, env.tx_power,
                                    (env.seq + 0x4000) & 0xFFFF, 0, env.t, env.dest,
                                    env.frame)  # fmt: skip
            for d in (data, fresh):
                self.session.put(key, d)
                n += 1
        return n

    def close(self) -> None:
        self.sub.undeclare()
        self.session.close()


@pytest.fixture
def procs() -> Iterator[list[Proc]]:
    started: list[Proc] = []
    yield started
    for p in reversed(started):
        p.stop()


@pytest.mark.zenoh
@pytest.mark.slow
@pytest.mark.mosquitto
@pytest.mark.timeout(240)
async def test_router_fleet_and_gateway_with_secrets_bring_records_and_refuse_a_rogue_radio(
    secrets: SecretsDir, mosquitto: Mosquitto, procs: list[Proc]
) -> None:
    ep, sec = free_tcp_endpoint(), str(secrets.root)
    router = Proc("router", "--secrets", sec, "--listen", ep)
    procs.append(router)
    router.wait_line("authenticated, access control by role", 30)
    fleet = Proc(
        "fleet", "grid_small", "--connect", ep, "--secrets", sec, "--processes", "2",
        "--without-kind", "gateway", "--speed", str(SPEED), "--progress", "600",
    )  # fmt: skip
    procs.append(fleet)
    assert "authenticated radio, 12 B per frame" in fleet.wait_line("awaremw fleet: grid_small")
    fleet.wait_line("awaremw fleet: running", 90)
    gateway = Proc(
        "gateway", "grid_small", "--connect", ep, "--secrets", sec,
        "--mqtt", mosquitto.url("gateway"), "--speed", str(SPEED), "--no-hbn",
    )  # fmt: skip
    procs.append(gateway)
    line = gateway.wait_line("awaremw gateway: motes 0 of grid_small", 60)
    assert "authenticated radio (payload MTU 88 B), items signed" in line
    async with MosquittoSub(mosquitto, "viewer", "aware/data/#") as data:
        # Over MQTT: the gateway signs both items, every mote verifies them before
        # it applies or forwards them, and the leader's records cross processes.
        assert pub(mosquitto, "operator", "aware/def/group/1", GROUP).returncode == 0
        assert pub(mosquitto, "operator", "aware/def/channel/1", CHANNEL).returncode == 0
        await data.wait_for(lambda ls: any(t.startswith("aware/data/1/1/") for t, _ in ls), 90)
        before = refused(await asyncio.to_thread(ctl_stats, ep, secrets.root))
        rogue = await asyncio.to_thread(Rogue, secrets, ep)
        try:
            assert await asyncio.to_thread(rogue.wait, lambda: len(rogue.captured) >= 60, 30)
            put = await asyncio.to_thread(rogue.replay)
            assert put >= 60

            async def counted() -> dict[str, int]:
                end = time.monotonic() + 30
                while True:
                    now = refused(await asyncio.to_thread(ctl_stats, ep, secrets.root))
                    if now.get("mic", 0) > before.get("mic", 0) and now.get("replay", 0) > 0:
                        return now
                    assert time.monotonic() < end, f"refusals not counted: {now}"
                    await asyncio.sleep(0.5)

            after = await counted()
        finally:
            await asyncio.to_thread(rogue.close)
        # Records keep arriving after the attack.
        n = len(data.lines)
        await data.wait_for(lambda ls: len(ls) > n, 30)
    # Frames from the legitimate processes were never refused for their MIC before.
    assert before.get("mic", 0) == 0, before
    assert set(after) <= {"mic", "replay", "short", "senders"}
    for p in (fleet, gateway):
        assert p.p.poll() is None, p.stop()[-2000:]
    err = gateway.stop() + fleet.stop() + router.stop()
    assert OPEN_WARNING not in err and "Traceback" not in err, err[-2000:]


def test_open_processes_say_once_that_radio_and_control_plane_are_open() -> None:
    r = subprocess.run(
        [*AWAREMW, "fleet", "grid_small", "--hello", "--duration", "0.5", "--speed", "4",
         "--listen", free_tcp_endpoint(), "--plain"],
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert r.stderr.count(OPEN_WARNING) == 1 and "awaremw fleet: warning" in r.stderr
    r = subprocess.run(
        [*AWAREMW, "demo", "--insecure", "--secrets", "x", "--plain"],
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert r.returncode == 2 and "do not combine" in r.stderr
