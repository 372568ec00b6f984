"""``awaremw keys init DIR``: every secret of a deployment, in one directory.

Layout (directories 0700, files 0600; see docs/security.md)::

    DIR/secrets.json            what was made, for which key prefix (no secret in it)
    DIR/radio/network.key       the radio network key: 16 (default) or 32 random bytes
    DIR/signing/gateway.key     the gateway's Ed25519 private key (PKCS#8 PEM)
    DIR/signing/gateway.pub     its public key (SubjectPublicKeyInfo PEM), for the motes
    DIR/zenoh/users.txt         Zenoh accounts, ``user:password`` (the router's dictionary)
    DIR/zenoh/router.json5      the router's config: usrpwd auth + access control by role,
                                mutual TLS for links to other routers
    DIR/zenoh/router.crt, .key  the routers' certificate (CN awaremw-router) and key
    DIR/zenoh/router-ca.crt     the CA that signed it (its key is not kept)
    DIR/zenoh/<role>.json5      a client config per role (fleet, gateway, app, operator)
    DIR/mqtt/passwd             Mosquitto password file (PBKDF2-SHA512, mosquitto's $7$)
    DIR/mqtt/acl                Mosquitto ACL of the accounts operator, gateway, viewer
    DIR/mqtt/accounts.json      the MQTT accounts' clear passwords, for their owners
    DIR/mqtt/ca.crt, ca.key     a small CA (ECDSA P-256) for the broker's TLS listener
    DIR/mqtt/server.crt, .key   the broker's certificate, signed by that CA (SAN: localhost,
                                127.0.0.1, ::1, broker, and every ``tls_hosts`` name)

Nothing is overwritten unless ``force``: without it, an existing file makes
the whole call fail before anything is written.
"""

from __future__ import annotations

import base64
import datetime
import hashlib
import ipaddress
import json
import os
import secrets
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from awaremw.security.zenoh_acl import (
    DEFAULT_PREFIX,
    ROLES,
    ROUTER_ACCOUNT,
    ROUTER_CN,
    Role,
    RouterLinkFiles,
    access_control,
    client_config,
    router_config,
)

FORMAT_VERSION: Final = 1
NETWORK_KEY_SIZES: Final = (16, 32)
MQTT_ACCOUNTS: Final = ("operator", "gateway", "viewer")  # as broker_cfg/
# Mosquitto's $7$ hashes: PBKDF2-HMAC-SHA512, 12-byte salt, 64-byte key. Mosquitto
# itself uses 101 iterations; any count is accepted when reading the file.
MQTT_PBKDF2_ITERATIONS: Final = 1000
MQTT_SALT_BYTES: Final = 12
# Names the broker's certificate is always valid for: the host itself and the
# compose service name (docker-compose.yml).
BROKER_TLS_HOSTS: Final = ("localhost", "127.0.0.1", "::1", "broker")
CA_DAYS: Final = 3650
SERVER_CERT_DAYS: Final = 825  # the longest validity browsers and Apple accept for a server


class SecretsExist(FileExistsError):
    """``keys init`` would overwrite files and ``force`` was not given."""

    def __init__(self, paths: list[Path]) -> None:
        self.paths = paths
        shown = ", ".join(str(p) for p in paths[:4]) + (" ..." if len(paths) > 4 else "")
        super().__init__(f"{len(paths)} secret file(s) exist already ({shown}); use --force")


@dataclass(frozen=True, slots=True)
class MqttFiles:
    """The MQTT broker's files under ``DIR/mqtt`` (Mosquitto accounts, ACL, TLS)."""

    root: Path

    @property
    def passwd(self) -> Path:
        return self.root / "passwd"

    @property
    def acl(self) -> Path:
        return self.root / "acl"

    @property
    def accounts(self) -> Path:
        return self.root / "accounts.json"

    @property
    def ca_cert(self) -> Path:
        return self.root / "ca.crt"

    @property
    def ca_key(self) -> Path:
        return self.root / "ca.key"

    @property
    def server_cert(self) -> Path:
        return self.root / "server.crt"

    @property
    def server_key(self) -> Path:
        return self.root / "server.key"

    def password(self, account: str) -> str:
        """The clear password of MQTT ``account`` (operator, gateway, viewer)."""
        accounts = json.loads(self.accounts.read_text())
        if not isinstance(accounts, dict) or not isinstance(accounts.get(account), str):
            raise ValueError(f"{self.accounts}: no MQTT account {account!r}")
        return str(accounts[account])


@dataclass(frozen=True, slots=True)
class SecretsDir:
    """Where each secret lives under ``root``."""

    root: Path

    @property
    def manifest(self) -> Path:
        return self.root / "secrets.json"

    @property
    def network_key(self) -> Path:
        return self.root / "radio" / "network.key"

    @property
    def signing_key(self) -> Path:
        return self.root / "signing" / "gateway.key"

    @property
    def signing_pub(self) -> Path:
        return self.root / "signing" / "gateway.pub"

    @property
    def zenoh_users(self) -> Path:
        return self.root / "zenoh" / "users.txt"

    @property
    def router_config(self) -> Path:
        return self.root / "zenoh" / "router.json5"

    @property
    def router_ca(self) -> Path:
        """The CA that signed the routers' certificate (its key is not kept)."""
        return self.root / "zenoh" / "router-ca.crt"

    @property
    def router_cert(self) -> Path:
        return self.root / "zenoh" / "router.crt"

    @property
    def router_key(self) -> Path:
        return self.root / "zenoh" / "router.key"

    def role_config(self, role: Role) -> Path:
        return self.root / "zenoh" / f"{role}.json5"

    @property
    def mqtt(self) -> MqttFiles:
        return MqttFiles(self.root / "mqtt")


def mosquitto_hash(
    password: str, *, salt: bytes | None = None, iterations: int = MQTT_PBKDF2_ITERATIONS
) -> str:
    """A password hash in the format of ``mosquitto_passwd`` (``$7$``, PBKDF2-SHA512)."""
    salt = secrets.token_bytes(MQTT_SALT_BYTES) if salt is None else salt
    dk = hashlib.pbkdf2_hmac("sha512", password.encode(), salt, iterations)
    b64 = base64.b64encode
    return f"$7${iterations}${b64(salt).decode()}${b64(dk).decode()}"


def mosquitto_acl(prefix: str = DEFAULT_PREFIX) -> str:
    """The ACL of broker_cfg/acl for topic prefix ``prefix``."""
    p = prefix
    return (
        f"# Mosquitto ACL for awaremw (topic prefix {p!r}), made by `awaremw keys init`.\n"
        "# operator: definitions and commands; gateway: what the sensor network says;\n"
        "# viewer: reads data, group state, gateway status and errors.\n\n"
        f"user operator\ntopic readwrite {p}/def/#\ntopic readwrite {p}/cmd/#\n"
        f"topic read {p}/#\n\n"
        f"user gateway\ntopic read {p}/def/#\ntopic read {p}/cmd/#\ntopic write {p}/data/#\n"
        f"topic write {p}/groups/#\ntopic write {p}/gateway/#\ntopic write {p}/errors\n\n"
        f"user viewer\ntopic read {p}/data/#\ntopic read {p}/groups/#\n"
        f"topic read {p}/gateway/#\ntopic read {p}/errors\n"
    )


def _san(host: str) -> x509.GeneralName:
    try:
        return x509.IPAddress(ipaddress.ip_address(host))
    except ValueError:
        pass
    if not host or any(c.isspace() or c in "/:@" for c in host):
        raise ValueError(f"bad TLS host name {host!r}")
    return x509.DNSName(host)


def _pem_key(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption(),
    )


def _key_usage(*, cert_sign: bool) -> x509.KeyUsage:
    return x509.KeyUsage(
        digital_signature=not cert_sign,
        content_commitment=False,
        key_encipherment=False,
        data_encipherment=False,
        key_agreement=False,
        key_cert_sign=cert_sign,
        crl_sign=cert_sign,
        encipher_only=False,
        decipher_only=False,
    )


def _make_ca(
    common_name: str, start: datetime.datetime
) -> tuple[ec.EllipticCurvePrivateKey, x509.Certificate]:
    """A small CA (ECDSA P-256, :data:`CA_DAYS`) named ``common_name`` and a random tag."""
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name(
        [
            x509.NameAttribute(NameOID.ORGANIZATION_NAME, "awaremw"),
            x509.NameAttribute(NameOID.COMMON_NAME, f"{common_name} {secrets.token_hex(4)}"),
        ]
    )
    ca = (
        x509.CertificateBuilder()
        .subject_name(ca_name)
        .issuer_name(ca_name)
        .public_key(ca_key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(start)
        .not_valid_after(start + datetime.timedelta(days=CA_DAYS))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(_key_usage(cert_sign=True), critical=True)
        .add_extension(
            x509.SubjectKeyIdentifier.from_public_key(ca_key.public_key()), critical=False
        )
        .sign(ca_key, hashes.SHA256())
    )
    return ca_key, ca


def _make_leaf(
    ca_key: ec.EllipticCurvePrivateKey,
    ca: x509.Certificate,
    common_name: str,
    sans: list[x509.GeneralName],
    usages: list[x509.ObjectIdentifier],
    start: datetime.datetime,
) -> tuple[ec.EllipticCurvePrivateKey, x509.Certificate]:
    """A key and a certificate signed by ``ca`` (:data:`SERVER_CERT_DAYS`)."""
    key = ec.generate_private_key(ec.SECP256R1())
    ca_ski = ca.extensions.get_extension_for_class(x509.SubjectKeyIdentifier).value
    cert = (
        x509.CertificateBuilder()
        .subject_name(
            x509.Name(
                [
                    x509.NameAttribute(NameOID.ORGANIZATION_NAME, "awaremw"),
                    x509.NameAttribute(NameOID.COMMON_NAME, common_name),
                ]
            )
        )
        .issuer_name(ca.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(start)
        .not_valid_after(start + datetime.timedelta(days=SERVER_CERT_DAYS))
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(_key_usage(cert_sign=False), critical=True)
        .add_extension(x509.ExtendedKeyUsage(usages), critical=False)
        .add_extension(x509.SubjectAlternativeName(sans), critical=False)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .add_extension(
            x509.AuthorityKeyIdentifier.from_issuer_subject_key_identifier(ca_ski),
            critical=False,
        )
        .sign(ca_key, hashes.SHA256())
    )
    return key, cert


def _start(now: datetime.datetime | None) -> datetime.datetime:
    return (now or datetime.datetime.now(datetime.UTC)) - datetime.timedelta(minutes=5)


def make_broker_tls(
    hosts: Iterable[str] = (), *, now: datetime.datetime | None = None
) -> dict[str, bytes]:
    """A CA and a server certificate signed by it, for the MQTT broker's TLS listener.

    Keys are ECDSA P-256. The server certificate is valid for
    :data:`BROKER_TLS_HOSTS` and ``hosts`` (DNS names or IP addresses). Returns the
    PEM bytes under ``ca.crt``, ``ca.key``, ``server.crt``, ``server.key``.
    """
    names = list(dict.fromkeys([*BROKER_TLS_HOSTS, *hosts]))
    sans = [_san(h) for h in names]
    start = _start(now)
    ca_key, ca = _make_ca("awaremw CA", start)
    key, server = _make_leaf(ca_key, ca, names[0], sans, [ExtendedKeyUsageOID.SERVER_AUTH], start)
    pem = serialization.Encoding.PEM
    return {
        "ca.crt": ca.public_bytes(pem),
        "ca.key": _pem_key(ca_key),
        "server.crt": server.public_bytes(pem),
        "server.key": _pem_key(key),
    }


def make_router_tls(*, now: datetime.datetime | None = None) -> dict[str, bytes]:
    """The routers' certificate for mutual TLS between routers (one for every router).

    Common name :data:`~awaremw.security.zenoh_acl.ROUTER_CN` (the access rules'
    router subject), usable as server and as client. The CA that signs it is
    thrown away: nothing else can ever carry a router's rights. Returns the PEM
    bytes under ``ca.crt``, ``router.crt``, ``router.key``.
    """
    start = _start(now)
    ca_key, ca = _make_ca("awaremw router CA", start)
    usages = [ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]
    key, cert = _make_leaf(ca_key, ca, ROUTER_CN, [x509.DNSName(ROUTER_CN)], usages, start)
    pem = serialization.Encoding.PEM
    return {
        "ca.crt": ca.public_bytes(pem),
        "router.crt": cert.public_bytes(pem),
        "router.key": _pem_key(key),
    }


def _json5(doc: Mapping[str, Any], what: str) -> bytes:
    head = f"// {what}\n// Made by `awaremw keys init`; secret: keep it 0600.\n"
    return (head + json.dumps(doc, indent=2) + "\n").encode()


def _password() -> str:
    return secrets.token_urlsafe(24)  # 32 characters of [A-Za-z0-9_-]: safe in URLs and files


def make_secrets(
    root: Path,
    *,
    prefix: str = DEFAULT_PREFIX,
    network_key_bytes: int = 16,
    tls_hosts: Iterable[str] = (),
) -> dict[Path, bytes]:
    """The contents of every secret file (nothing written)."""
    if network_key_bytes not in NETWORK_KEY_SIZES:
        raise ValueError(f"network key must be 16 or 32 bytes, not {network_key_bytes}")
    access_control(prefix)  # validates the prefix
    d = SecretsDir(root.resolve())
    files: dict[Path, bytes] = {}
    files[d.network_key] = secrets.token_bytes(network_key_bytes)
    sk = Ed25519PrivateKey.generate()
    files[d.signing_key] = sk.private_bytes(
        serialization.Encoding.PEM,
        serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption(),
    )
    files[d.signing_pub] = sk.public_key().public_bytes(
        serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo
    )
    zpw = {role: _password() for role in ROLES}
    router_pw = _password()
    users = [*zpw.items(), (ROUTER_ACCOUNT, router_pw)]
    files[d.zenoh_users] = "".join(f"{r}:{pw}\n" for r, pw in users).encode()
    rtls = make_router_tls()
    files[d.router_ca] = rtls["ca.crt"]
    files[d.router_cert] = rtls["router.crt"]
    files[d.router_key] = rtls["router.key"]
    links = RouterLinkFiles(router_pw, d.router_ca, d.router_cert, d.router_key)
    files[d.router_config] = _json5(
        router_config(d.zenoh_users, links, prefix),
        "Zenoh router: accounts, access control by role, mutual TLS between routers",
    )
    for role in ROLES:
        files[d.role_config(role)] = _json5(
            client_config(role, zpw[role]), f"Zenoh client config of role {role!r}"
        )
    mpw = {user: _password() for user in MQTT_ACCOUNTS}
    files[d.mqtt.passwd] = "".join(f"{u}:{mosquitto_hash(pw)}\n" for u, pw in mpw.items()).encode()
    files[d.mqtt.acl] = mosquitto_acl(prefix).encode()
    files[d.mqtt.accounts] = (json.dumps(mpw, indent=2) + "\n").encode()
    tls_hosts = list(dict.fromkeys([*BROKER_TLS_HOSTS, *tls_hosts]))
    tls = make_broker_tls(tls_hosts)
    files[d.mqtt.ca_cert] = tls["ca.crt"]
    files[d.mqtt.ca_key] = tls["ca.key"]
    files[d.mqtt.server_cert] = tls["server.crt"]
    files[d.mqtt.server_key] = tls["server.key"]
    manifest = {
        "format": FORMAT_VERSION,
        "prefix": prefix,
        "created": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "network_key_bytes": network_key_bytes,
        "zenoh_roles": list(ROLES),
        "zenoh_router_links": "mutual TLS, certificate CN " + ROUTER_CN,
        "mqtt_accounts": list(MQTT_ACCOUNTS),
        "mqtt_tls_hosts": tls_hosts,
    }
    files[d.manifest] = (json.dumps(manifest, indent=2) + "\n").encode()
    return files


def _private_dir(path: Path) -> None:
    path.mkdir(mode=0o700, parents=True, exist_ok=True)
    os.chmod(path, 0o700)


def _write_private(path: Path, data: bytes, force: bool) -> None:
    """Write ``data`` to ``path`` with mode 0600; replace an old file only if ``force``."""
    if not force:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
    else:
        tmp = path.with_name(f".{path.name}.{secrets.token_hex(4)}.tmp")
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(data)
            os.replace(tmp, path)
        except BaseException:
            tmp.unlink(missing_ok=True)
            raise
    os.chmod(path, 0o600)


def init_secrets(
    root: Path,
    *,
    force: bool = False,
    prefix: str = DEFAULT_PREFIX,
    network_key_bytes: int = 16,
    tls_hosts: Iterable[str] = (),
    exist_ok: bool = False,
) -> list[Path]:
    """Create every secret under ``root``; the files written.

    Raises :class:`SecretsExist` (and writes nothing) if one exists and not ``force``;
    with ``exist_ok`` a complete set is kept as it is (nothing written, ``[]``
    returned), while an incomplete one still raises.
    The manifest (``secrets.json``) is written last: once it exists, every other file
    is complete (containers wait for it).
    """
    files = make_secrets(
        Path(root), prefix=prefix, network_key_bytes=network_key_bytes, tls_hosts=tls_hosts
    )
    existing = [p for p in files if p.exists() or p.is_symlink()]
    if exist_ok and not force and len(existing) == len(files):
        return []
    if existing and not force:
        raise SecretsExist(existing)
    for p in files:
        _private_dir(p.parent)
    _private_dir(Path(root).resolve())
    for p, data in files.items():
        _write_private(p, data, force)
    return list(files)
