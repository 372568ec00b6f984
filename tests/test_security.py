"""Secrets (``awaremw keys init``) and Zenoh access control by role, with a real
``awaremw router --secrets`` process and real Zenoh sessions per role on loopback,
and the generated Mosquitto accounts on a real Mosquitto."""

from __future__ import annotations

import json
import os
import re
import shutil
import socket
import stat
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import zenoh
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey

from awaremw.cli import main as cli_main
from awaremw.runtime.zenoh_session import free_tcp_endpoint
from awaremw.security.keys import SecretsDir, SecretsExist, init_secrets, mosquitto_hash
from awaremw.security.material import load_radio_security, load_signing_key
from awaremw.security.zenoh_acl import ROLES, Role

AWAREMW = [sys.executable, "-m", "awaremw"]
DOCS = Path(__file__).resolve().parent.parent / "docs" / "security.md"
WAIT_S = 10.0


# --------------------------------------------------------------------------- keys init


def test_keys_init_makes_private_files_and_never_overwrites(tmp_path: Path) -> None:
    root = tmp_path / "secrets"
    assert cli_main(["keys", "init", str(root)]) == 0
    d = SecretsDir(root.resolve())
    files = [p for p in root.rglob("*") if p.is_file()]
    assert len(files) == 20
    for p in files:
        assert stat.S_IMODE(p.stat().st_mode) == 0o600, p
    for p in [root, *(p for p in root.rglob("*") if p.is_dir())]:
        assert stat.S_IMODE(p.stat().st_mode) == 0o700, p
    assert len(load_radio_security(root).network_key) == 16
    # the signing pair matches: a signature by the private key verifies with the public one
    pub = serialization.load_pem_public_key(d.signing_pub.read_bytes())
    assert isinstance(pub, Ed25519PublicKey)
    signing = Ed25519PrivateKey.from_private_bytes(load_signing_key(root))
    pub.verify(signing.sign(b"item"), b"item")
    users = dict(ln.split(":", 1) for ln in d.zenoh_users.read_text().splitlines())
    # one account per role, and the one routers log in with when they link to each other
    assert sorted(users) == sorted([*ROLES, "router"]) and len(set(users.values())) == 5
    for role in ROLES:
        zenoh.Config.from_file(str(d.role_config(role)))  # the Python package accepts each
    zenoh.Config.from_file(str(d.router_config))

    before = {p: p.read_bytes() for p in files}
    with pytest.raises(SecretsExist):
        init_secrets(root)
    assert cli_main(["keys", "init", str(root)]) == 1
    assert {p: p.read_bytes() for p in files} == before  # nothing touched
    assert cli_main(["keys", "init", str(root), "--force", "--network-key-bytes", "32"]) == 0
    assert len(load_radio_security(root).network_key) == 32
    assert d.zenoh_users.read_bytes() != before[d.zenoh_users]
    assert stat.S_IMODE(d.network_key.stat().st_mode) == 0o600


def test_keys_init_refuses_when_a_single_file_exists(tmp_path: Path) -> None:
    (tmp_path / "zenoh").mkdir()
    (tmp_path / "zenoh" / "app.json5").write_text("{}")
    with pytest.raises(SecretsExist) as e:
        init_secrets(tmp_path)
    assert e.value.paths == [(tmp_path / "zenoh" / "app.json5").resolve()]
    assert not (tmp_path / "radio").exists()  # nothing written before the check


def test_mosquitto_hash_is_mosquitto_passwd_format() -> None:
    # the test account of broker_cfg/passwd, made by mosquitto_passwd itself
    line = (Path(__file__).parent.parent / "broker_cfg" / "passwd").read_text().splitlines()[0]
    user, stored = line.split(":", 1)
    _, seven, iters, salt, _ = stored.split("$")
    import base64

    ours = mosquitto_hash(f"{user}-pw", salt=base64.b64decode(salt), iterations=int(iters))
    assert seven == "7" and ours == stored


@pytest.mark.mosquitto
def test_mosquitto_accepts_the_generated_accounts_and_acl(tmp_path: Path) -> None:
    broker, pub, sub = (shutil.which(b) for b in ("mosquitto", "mosquitto_pub", "mosquitto_sub"))
    broker = broker or ("/usr/sbin/mosquitto" if Path("/usr/sbin/mosquitto").exists() else None)
    if not (broker and pub and sub):
        pytest.skip("mosquitto not installed")
    d = SecretsDir(tmp_path / "s")
    init_secrets(d.root)
    pw = json.loads(d.mqtt.accounts.read_text())
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    conf = tmp_path / "m.conf"
    lines = [
        "per_listener_settings false",
        "allow_anonymous false",
        f"password_file {d.mqtt.passwd}",
        f"acl_file {d.mqtt.acl}",
        f"listener {port} 127.0.0.1",
    ]
    if os.geteuid() == 0:
        lines.append("user root")  # else mosquitto drops to a user that cannot read 0600 files
    conf.write_text("\n".join(lines) + "\n")
    proc = subprocess.Popen([broker, "-c", str(conf)], stderr=subprocess.PIPE)
    try:

        def mqtt(
            tool: str, user: str, password: str, *args: str
        ) -> subprocess.CompletedProcess[str]:
            return subprocess.run(
                [tool, "-h", "127.0.0.1", "-p", str(port), "-u", user, "-P", password, *args],
                capture_output=True, text=True, timeout=20, check=False,
            )  # fmt: skip

        deadline = time.monotonic() + WAIT_S
        while True:  # until the broker listens
            r = mqtt(pub, "operator", pw["operator"], "-t", "aware/def/group/1", "-r", "-m", "{}")
            if r.returncode == 0 or time.monotonic() > deadline:
                break
        assert r.returncode == 0, r.stderr
        bad = mqtt(pub, "operator", "wrong", "-t", "aware/def/group/2", "-m", "{}")
        assert bad.returncode != 0 and "not authori" in bad.stderr.lower()
        got = mqtt(sub, "gateway", pw["gateway"], "-t", "aware/def/#", "-C", "1", "-W", "10")
        assert got.returncode == 0 and got.stdout.strip() == "{}"  # the ACL lets it read
        # the viewer may not read definitions: nothing arrives before the timeout
        none = mqtt(sub, "viewer", pw["viewer"], "-t", "aware/def/#", "-C", "1", "-W", "2")
        assert none.stdout.strip() == ""
    finally:
        proc.terminate()
        proc.wait(10)


# --------------------------------------------------------------------------- Zenoh roles


class Router:
    def __init__(self, secrets: SecretsDir, endpoint: str, proc: subprocess.Popen[str]) -> None:
        self.secrets = secrets
        self.endpoint = endpoint
        self.proc = proc

    def config(self, role: Role | None) -> zenoh.Config:
        if role is None:
            conf = zenoh.Config()
            conf.insert_json5("mode", '"client"')
            conf.insert_json5("scouting/multicast/enabled", "false")
        else:
            conf = zenoh.Config.from_file(str(self.secrets.role_config(role)))
        conf.insert_json5("connect/endpoints", json.dumps([self.endpoint]))
        return conf

    def open(self, role: Role | None) -> zenoh.Session:
        return zenoh.open(self.config(role))


@pytest.fixture(scope="module")
def router(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Router]:
    d = SecretsDir(tmp_path_factory.mktemp("sec") / "secrets")
    init_secrets(d.root)
    ep = free_tcp_endpoint()
    proc = subprocess.Popen(
        [*AWAREMW, "router", "--secrets", str(d.root), "--listen", ep],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    assert proc.stdout is not None
    line = proc.stdout.readline()  # blocks until the router listens (or exits)
    assert "authenticated, access control by role" in line, (
        proc.stderr.read() if proc.stderr else ""
    )
    try:
        yield Router(d, ep, proc)
    finally:
        proc.terminate()
        proc.wait(15)


class Inbox:
    """Samples from a Zenoh callback thread; wait for one with a timeout."""

    def __init__(self) -> None:
        self.keys: list[str] = []
        self._cv = threading.Condition()

    def __call__(self, sample: zenoh.Sample) -> None:
        with self._cv:
            self.keys.append(str(sample.key_expr))
            self._cv.notify_all()

    def wait_for(self, key: str, timeout: float = WAIT_S) -> bool:
        with self._cv:
            return self._cv.wait_for(lambda: key in self.keys, timeout)


def barrier(session: zenoh.Session, router: Router) -> None:
    """A round trip through the router: what ``session`` sent before has been routed."""
    list(session.get(f"aware/hbn/barrier/{time.monotonic_ns()}", timeout=2.0))


@pytest.mark.zenoh
def test_a_client_without_credentials_or_with_a_wrong_password_is_refused(router: Router) -> None:
    with pytest.raises(zenoh.ZError, match="Unable to connect"):
        router.open(None)
    conf = router.config("app")
    conf.insert_json5("transport/auth/usrpwd/password", '"not-the-password"')
    with pytest.raises(zenoh.ZError, match="Unable to connect"):
        zenoh.open(conf)
    router.open("app").close()  # the right password gets in


@pytest.mark.zenoh
def test_only_fleet_and_gateway_roles_touch_the_radio(router: Router) -> None:
    fleet, gateway, app, operator = (
        router.open(r) for r in ("fleet", "gateway", "app", "operator")
    )
    try:
        heard = Inbox()
        fleet.declare_subscriber("aware/radio/**", heard)
        app_heard = Inbox()
        app.declare_subscriber(  # denied by the router
            "aware/radio/**", app_heard, allowed_origin=zenoh.Locality.REMOTE
        )
        barrier(fleet, router)
        barrier(app, router)
        for who, s in (("app", app), ("operator", operator)):
            s.put(f"aware/radio/1/1/{who}", b"rogue frame")
            barrier(s, router)
        gateway.put("aware/radio/1/1/gateway", b"frame")
        assert heard.wait_for("aware/radio/1/1/gateway")
        assert heard.keys == ["aware/radio/1/1/gateway"]  # the app's and operator's were dropped
        barrier(app, router)  # the router handled the gateway's frame before this reply
        assert app_heard.keys == []  # and the app hears nothing of the radio
    finally:
        for s in (fleet, gateway, app, operator):
            s.close()


@pytest.mark.zenoh
def test_only_the_operator_reaches_the_fleet_control(router: Router) -> None:
    fleet, app, operator = (router.open(r) for r in ("fleet", "app", "operator"))
    try:
        asked: list[str] = []

        def answer(query: zenoh.Query) -> None:
            asked.append(str(query.key_expr))
            query.reply("aware/ctl/fleet/f1", b'{"ok": true}')

        fleet.declare_queryable("aware/ctl/fleet/f1", answer)
        deadline = time.monotonic() + WAIT_S
        got: list[zenoh.Reply] = []
        while not got and time.monotonic() < deadline:  # until the queryable is routed
            got = [r for r in operator.get("aware/ctl/fleet/*", timeout=1.0) if r.ok]
        assert got and got[0].ok is not None and got[0].ok.payload.to_bytes() == b'{"ok": true}'
        n = len(asked)
        assert [r for r in app.get("aware/ctl/fleet/*", timeout=2.0)] == []
        assert len(asked) == n  # the app's query never reached the fleet
        app.put("aware/ctl/fleet/f1", b'{"op": "kill", "id": 1}')  # no effect, no reply
    finally:
        for s in (fleet, app, operator):
            s.close()


@pytest.mark.zenoh
def test_app_puts_definitions_but_only_the_gateway_puts_data(router: Router) -> None:
    gateway, app = router.open("gateway"), router.open("app")
    try:
        gw_in, app_in = Inbox(), Inbox()
        gateway.declare_subscriber("aware/hbn/**", gw_in)
        app.declare_subscriber("aware/hbn/**", app_in, allowed_origin=zenoh.Locality.REMOTE)
        barrier(gateway, router)
        deadline = time.monotonic() + WAIT_S
        while not gw_in.keys and time.monotonic() < deadline:  # until routes are in place
            app.put("aware/hbn/def/group/1", b"{}")
            gw_in.wait_for("aware/hbn/def/group/1", 0.5)
        assert "aware/hbn/def/group/1" in gw_in.keys
        app.put("aware/hbn/data/1/1/513", b'{"value": 92.6}')  # a forged record
        barrier(app, router)
        gateway.put("aware/hbn/data/1/1/514", b'{"value": 20.0}')
        assert app_in.wait_for("aware/hbn/data/1/1/514")
        # the forged record reached neither the gateway nor another app's subscriber
        assert "aware/hbn/data/1/1/513" not in app_in.keys + gw_in.keys
    finally:
        gateway.close()
        app.close()


def _docs_client() -> str:
    text = DOCS.read_text()
    section = text.split("## A client with a role's config", 1)[1]
    m = re.search(r"```python\n(.*?)```", section, re.S)
    assert m is not None
    return m.group(1)


@pytest.mark.zenoh
def test_the_ten_line_client_of_the_docs_works_with_each_role(
    router: Router, tmp_path: Path
) -> None:
    code = _docs_client()
    assert len([ln for ln in code.splitlines() if ln.strip()]) <= 10
    client = tmp_path / "client.py"
    client.write_text(code)
    gateway = router.open("gateway")
    try:
        gateway.declare_queryable(
            "aware/hbn/**", lambda q: q.reply("aware/hbn/gateway/status", b"online")
        )
        out: dict[str, str] = {}
        for role in ROLES:
            deadline = time.monotonic() + WAIT_S
            while True:
                p = subprocess.run(
                    [sys.executable, str(client), str(router.secrets.root), role, router.endpoint],
                    capture_output=True, text=True, timeout=30, check=False,
                )  # fmt: skip
                assert p.returncode == 0, (role, p.stderr)
                out[role] = p.stdout
                if role != "app" or p.stdout or time.monotonic() > deadline:
                    break
        assert out["app"].split() == ["aware/hbn/gateway/status"]
        assert out["fleet"] == out["operator"] == ""  # connected, but the rules give them nothing
    finally:
        gateway.close()


# --------------------------------------------------------------------------- CLI end to end


def _run(*args: str, timeout: float = 60.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*AWAREMW, *args], capture_output=True, text=True, timeout=timeout, check=False
    )


@pytest.mark.zenoh
def test_operator_uses_fleet_ctl_against_a_fleet_run_with_secrets(router: Router) -> None:
    sec, ep = str(router.secrets.root), router.endpoint
    fleet = subprocess.Popen(
        [*AWAREMW, "fleet", "grid_small", "--connect", ep, "--secrets", sec, "--hello",
         "--progress", "60"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 30
        while True:  # until the fleet answers
            listed = _run("fleet-ctl", "--connect", ep, "--secrets", sec, "--timeout", "2", "list")
            if listed.returncode == 0 or time.monotonic() > deadline:
                break
        assert listed.returncode == 0, listed.stderr
        assert len(listed.stdout.splitlines()) == 26
        killed = _run("fleet-ctl", "--connect", ep, "--secrets", sec, "kill", "5")
        assert killed.returncode == 0 and "node 5 killed" in killed.stdout
        # without an account fleet-ctl cannot even connect
        open_ctl = _run("fleet-ctl", "--connect", ep, "--timeout", "2", "list")
        assert open_ctl.returncode == 1 and "cannot reach" in open_ctl.stderr
    finally:
        fleet.terminate()
        fleet.wait(20)


@pytest.mark.zenoh
def test_demo_with_secrets_runs_the_whole_system_through_the_rules(tmp_path: Path) -> None:
    init_secrets(tmp_path / "s")
    p = _run(
        "demo", "--secrets", str(tmp_path / "s"), "--duration", "45", "--speed", "10", "--plain",
        timeout=120,
    )  # fmt: skip
    assert p.returncode == 0, p.stderr[-2000:]
    lines = dict(
        ln.removeprefix("summary ").split(": ", 1)
        for ln in p.stdout.splitlines()
        if ln.startswith("summary ")
    )
    # radio between fleets and the gateway's motes, and the gateway to MQTT, all went through
    assert int(lines["records received (MQTT)"]) >= 2, p.stdout[-2000:]


# Every verb with --secrets DIR: its arguments before DIR and after it.
SECRETS_VERBS: tuple[tuple[list[str], list[str]], ...] = (
    (["router"], []),
    (["fleet", "grid_small", "--duration", "1"], []),
    (["fleet-ctl"], ["list"]),
    (["gateway", "romeo4r"], []),
    (["sniff", "--connect", "tcp/127.0.0.1:1", "--pcap", "x.pcapng"], []),
    (["view", "--mqtt", "mqtt://127.0.0.1:1"], []),
    (["experiment", "romeo4r", "--virtual"], []),
    (["experiment", "romeo4r"], []),
    (["demo", "--plain"], []),
)


@pytest.mark.parametrize(("before", "after"), SECRETS_VERBS, ids=lambda v: "-".join(v))
def test_secrets_flags_report_a_missing_directory_or_file_in_one_line(
    before: list[str], after: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """One check and one error line for --secrets DIR (awaremw.cli.friendly.load_secrets)."""

    def refused(root: Path) -> list[str]:
        assert cli_main([*before, "--secrets", str(root), *after]) == 2
        return capsys.readouterr().err.strip().splitlines()

    prog = f"awaremw {before[0]}"
    missing = tmp_path / "nope"
    assert refused(missing) == [
        f"{prog}: --secrets {missing}: no such directory; make the secrets with "
        f"`awaremw keys init {missing}`"
    ]
    missing.write_text("a file\n")
    assert refused(missing) == [
        f"{prog}: --secrets {missing}: not a directory; make the secrets with "
        f"`awaremw keys init {missing}`"
    ]
    empty = tmp_path / "empty"
    empty.mkdir()
    err = refused(empty)
    assert len(err) == 1 and err[0].startswith(f"{prog}: {empty}/"), err
    assert err[0].endswith(f" not found: make the secrets with `awaremw keys init {empty}`")
