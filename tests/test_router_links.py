"""Routers linked to each other with the secrets on (one router per host, docs/hosts.md):
real ``awaremw router --secrets`` processes on loopback, linked over mutual TLS, and
real Zenoh sessions per role behind each of them."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
import zenoh

from awaremw.runtime.zenoh_session import free_tcp_endpoint
from awaremw.security.keys import SecretsDir, init_secrets
from awaremw.security.zenoh_acl import ROUTER_CN, Role, access_control

pytestmark = pytest.mark.zenoh

AWAREMW = [sys.executable, "-m", "awaremw"]
WAIT_S = 15.0


def _tls_endpoint() -> str:
    return "tls/" + free_tcp_endpoint().removeprefix("tcp/")


class Inbox:
    """Keys of the samples a subscriber got (from Zenoh's thread); wait with a timeout."""

    def __init__(self) -> None:
        self.keys: set[str] = set()
        self._cv = threading.Condition()

    def __call__(self, sample: zenoh.Sample) -> None:
        with self._cv:
            self.keys.add(str(sample.key_expr))
            self._cv.notify_all()

    def wait_for(self, key: str, timeout: float = WAIT_S) -> bool:
        with self._cv:
            return self._cv.wait_for(lambda: key in self.keys, timeout)


class Router:
    """One ``awaremw router --secrets`` process: clients on tcp/, routers on tls/."""

    def __init__(
        self,
        secrets: Path,
        connect: list[str],
        tmp: Path,
        name: str,
        *,
        link_ep: str | None = None,
        client_ep: str | None = None,
    ) -> None:
        self.secrets = secrets
        self.connect = connect
        self.client_ep = client_ep or free_tcp_endpoint()
        self.link_ep = link_ep or _tls_endpoint()
        cmd = [*AWAREMW, "router", "--secrets", str(secrets)]
        cmd += ["--listen", self.client_ep, "--listen", self.link_ep]
        for ep in connect:
            cmd += ["--connect", ep]
        self.log = tmp / f"{name}.log"
        self.proc = subprocess.Popen(
            cmd, stdout=subprocess.PIPE, stderr=self.log.open("w"), text=True
        )
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()  # blocks until the router listens (or exits)
        assert "authenticated, access control by role" in line, self.log.read_text()

    def open(self, role: Role) -> zenoh.Session:
        conf = zenoh.Config.from_file(str(SecretsDir(self.secrets).role_config(role)))
        conf.insert_json5("connect/endpoints", json.dumps([self.client_ep]))
        return zenoh.open(conf)

    def restart(self, tmp: Path, name: str) -> Router:
        """Stop this router and start another on the same endpoints."""
        self.stop()
        return Router(
            self.secrets, self.connect, tmp, name, link_ep=self.link_ep, client_ep=self.client_ep
        )

    def stop(self) -> None:
        self.proc.terminate()
        try:
            self.proc.wait(15)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(5)


@pytest.fixture
def secrets(tmp_path: Path) -> Path:
    root = tmp_path / "secrets"
    init_secrets(root)
    return root


@pytest.fixture
def routers(tmp_path: Path) -> Iterator[list[Router]]:
    made: list[Router] = []
    yield made
    for r in made:
        r.stop()


def _hears(listener: zenoh.Session, talker: zenoh.Session, key: str) -> bool:
    """Does ``listener`` hear ``talker``'s puts on ``key`` (put again until heard)?"""
    inbox = Inbox()
    sub = listener.declare_subscriber(key, inbox)
    try:
        for _ in range(int(WAIT_S / 0.5)):
            talker.put(key, b"x")
            if inbox.wait_for(key, 0.5):
                return True
        return False
    finally:
        sub.undeclare()  # type: ignore[no-untyped-call]


def test_the_secrets_give_routers_a_certificate_and_the_rules_a_router_subject(
    secrets: Path,
) -> None:
    d = SecretsDir(secrets)
    users = dict(ln.split(":", 1) for ln in d.zenoh_users.read_text().splitlines())
    assert "router" in users
    conf = zenoh.Config.from_file(str(d.router_config))
    assert conf.get_json("transport/link/tls/enable_mtls") == "true"
    assert json.loads(conf.get_json("transport/auth/usrpwd/user")) == "router"
    from cryptography import x509

    cert = x509.load_pem_x509_certificate(d.router_cert.read_bytes())
    ca = x509.load_pem_x509_certificate(d.router_ca.read_bytes())
    assert cert.subject.get_attributes_for_oid(x509.NameOID.COMMON_NAME)[0].value == ROUTER_CN
    assert cert.issuer == ca.subject
    assert not (d.root / "zenoh" / "router-ca.key").exists()  # nobody can sign another
    rules = access_control()
    router_subject = [s for s in rules["subjects"] if s["id"] == "router"]
    assert router_subject == [{"id": "router", "cert_common_names": [ROUTER_CN]}]


def test_three_linked_routers_carry_every_role_between_their_clients(
    secrets: Path, routers: list[Router], tmp_path: Path
) -> None:
    # a full mesh; c starts before b, which it also dials: routers start in any order
    a = Router(secrets, [], tmp_path, "a")
    routers.append(a)
    b_link = _tls_endpoint()
    c = Router(secrets, [a.link_ep, b_link], tmp_path, "c")
    routers.append(c)
    b = Router(secrets, [a.link_ep], tmp_path, "b", link_ep=b_link)
    routers.append(b)

    fleets = {name: r.open("fleet") for name, r in zip("abc", (a, b, c), strict=True)}
    gateway_a, app_c = a.open("gateway"), c.open("app")
    try:
        # the radio crosses every link, both ways
        for src in "abc":
            for dst in "abc":
                if src != dst:
                    key = f"aware/radio/0/0/{src}{dst}"
                    assert _hears(fleets[dst], fleets[src], key), f"{src} -> {dst}"
        # an app behind c defines things the gateway behind a receives
        assert _hears(gateway_a, app_c, "aware/hbn/def/group/1")
        # ... and the role rules still hold where a session enters: an app's radio
        # frame reaches no fleet, behind any router
        heard = Inbox()
        for f in fleets.values():
            f.declare_subscriber("aware/radio/**", heard)
        for _ in range(6):
            app_c.put("aware/radio/0/0/evil", b"x")
            fleets["c"].put("aware/radio/0/0/marker", b"x")
        assert heard.wait_for("aware/radio/0/0/marker")
        assert "aware/radio/0/0/evil" not in heard.keys
    finally:
        for s in (*fleets.values(), gateway_a, app_c):
            s.close()  # type: ignore[no-untyped-call]


def test_a_link_comes_back_when_either_end_restarts(
    secrets: Path, routers: list[Router], tmp_path: Path
) -> None:
    a = Router(secrets, [], tmp_path, "a")
    b = Router(secrets, [a.link_ep], tmp_path, "b")
    routers += [a, b]
    behind_a, behind_b = a.open("fleet"), b.open("fleet")
    try:
        assert _hears(behind_a, behind_b, "aware/radio/0/0/first")
        # the router dialled restarts, then the one dialling; the clients stay and
        # reconnect to their router on their own
        a = a.restart(tmp_path, "a2")
        routers.append(a)
        assert _hears(behind_a, behind_b, "aware/radio/0/0/a-restarted")
        b = b.restart(tmp_path, "b2")
        routers.append(b)
        assert _hears(behind_a, behind_b, "aware/radio/0/0/b-restarted")
    finally:
        behind_a.close()  # type: ignore[no-untyped-call]
        behind_b.close()  # type: ignore[no-untyped-call]


def test_a_router_without_the_routers_certificate_links_to_nothing(
    secrets: Path, routers: list[Router], tmp_path: Path
) -> None:
    a = Router(secrets, [], tmp_path, "a")
    routers.append(a)
    other = tmp_path / "other"
    init_secrets(other)  # another deployment's secrets: another CA, other accounts
    rogue = Router(other, [a.link_ep], tmp_path, "rogue")
    routers.append(rogue)
    inside, outside = a.open("fleet"), rogue.open("fleet")
    try:
        inbox = Inbox()
        inside.declare_subscriber("aware/radio/**", inbox)
        for _ in range(8):
            outside.put("aware/radio/0/0/rogue", b"x")
            inside.put("aware/radio/0/0/own", b"x")  # a's own traffic flows meanwhile
        assert inbox.wait_for("aware/radio/0/0/own")
        assert not inbox.wait_for("aware/radio/0/0/rogue", 3.0)
    finally:
        inside.close()  # type: ignore[no-untyped-call]
        outside.close()  # type: ignore[no-untyped-call]
    # a client account cannot use the routers' listener either (no certificate)
    conf = zenoh.Config.from_file(str(SecretsDir(secrets).role_config("fleet")))
    conf.insert_json5("connect/endpoints", json.dumps([a.link_ep]))
    with pytest.raises(zenoh.ZError, match="Unable to connect"):
        zenoh.open(conf)


def test_router_refuses_a_plain_link_with_secrets_in_one_line(secrets: Path) -> None:
    r = subprocess.run(
        [*AWAREMW, "router", "--secrets", str(secrets), "--listen", free_tcp_endpoint(),
         "--connect", "tcp/127.0.0.1:7447"],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert r.returncode == 2
    assert r.stderr.strip().splitlines() == [
        "awaremw router: cannot link to tcp/127.0.0.1:7447: with secrets, routers link over "
        "mutual TLS; use tls/HOST:PORT and let that router listen on tls/ too"
    ]


def test_router_with_secrets_made_before_router_links_says_so(secrets: Path) -> None:
    d = SecretsDir(secrets)
    text = d.router_config.read_text()
    doc = json.loads(text[text.index("{") :])
    del doc["transport"]["link"]  # what keys init wrote before routers had a certificate
    d.router_config.write_text(json.dumps(doc))
    r = subprocess.run(
        [*AWAREMW, "router", "--secrets", str(secrets), "--listen", free_tcp_endpoint(),
         "--connect", "tls/127.0.0.1:7448"],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert r.returncode == 2
    assert r.stderr.strip().splitlines() == [
        f"awaremw router: {d.router_config} has no router certificate (secrets made before "
        "router links existed): make new ones with `awaremw keys init DIR --force`"
    ]
