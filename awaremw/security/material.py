"""Load the radio's key material from a secrets directory (``awaremw keys init DIR``).

One loader for every process that ``--secrets DIR`` secures:

* :func:`load_radio_security` -- what every fleet, gateway, demo and real-time
  experiment needs: the network key (``DIR/radio/network.key``) and the
  gateway's *public* key (``DIR/signing/gateway.pub``) as a
  :class:`~awaremw.radio.security.RadioSecurity` (raw bytes, picklable: it goes
  to worker processes inside the fleet settings);
* :func:`load_signing_key` -- the gateway's Ed25519 *private* key as 32 raw
  bytes; only the gateway process loads it (fleets get the public key only);
  :func:`load_gateway_keys` loads both, once.

Missing or malformed files raise :class:`~awaremw.security.zenoh_acl.SecretsError`
with the path and what to do. :data:`OPEN_WARNING` is the one line a process
run without ``--secrets`` prints on stderr.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Final, TextIO

from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey

from awaremw.radio.security import RadioSecurity
from awaremw.security.keys import SecretsDir
from awaremw.security.zenoh_acl import SecretsError

OPEN_WARNING: Final = (
    "warning: no --secrets: the radio and the control plane are open (any Zenoh client can "
    "inject frames and drive the fleet); make secrets with `awaremw keys init DIR`"
)


def warn_open(prog: str, stream: TextIO | None = None) -> None:
    """Say once, on stderr, that this process runs without secrets."""
    print(f"{prog}: {OPEN_WARNING}", file=stream or sys.stderr, flush=True)


def _read(path: Path, secrets: Path | str) -> bytes:
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise SecretsError(
            f"{path} not found: make the secrets with `awaremw keys init {secrets}`"
        ) from None
    except OSError as e:
        raise SecretsError(f"{path}: cannot read: {e.strerror or e}") from None


def load_radio_security(secrets: Path | str, *, mic_bytes: int = 8) -> RadioSecurity:
    """The network key and the gateway's public key of ``secrets`` (no private key)."""
    d = SecretsDir(Path(secrets))
    key = _read(d.network_key, secrets)
    pem = _read(d.signing_pub, secrets)
    try:
        pub = serialization.load_pem_public_key(pem)
    except ValueError as e:
        raise SecretsError(f"{d.signing_pub}: not a PEM public key ({e})") from None
    if not isinstance(pub, Ed25519PublicKey):
        raise SecretsError(f"{d.signing_pub}: not an Ed25519 public key")
    raw = pub.public_bytes(serialization.Encoding.Raw, serialization.PublicFormat.Raw)
    try:
        return RadioSecurity(key, raw, mic_bytes)
    except ValueError as e:
        raise SecretsError(f"{d.network_key}: {e} (it has {len(key)})") from None


def load_signing_key(secrets: Path | str, public_key: bytes | None = None) -> bytes:
    """The gateway's Ed25519 private key as 32 raw bytes (the gateway process only).

    ``public_key``: the raw public key the motes verify with; a private key that
    does not match it (files from two ``keys init`` runs) is refused."""
    d = SecretsDir(Path(secrets))
    try:
        key = serialization.load_pem_private_key(_read(d.signing_key, secrets), password=None)
    except (ValueError, TypeError) as e:
        raise SecretsError(f"{d.signing_key}: {e}") from None
    if not isinstance(key, Ed25519PrivateKey):
        raise SecretsError(f"{d.signing_key}: not an Ed25519 private key")
    mine = key.public_key().public_bytes(serialization.Encoding.Raw, serialization.PublicFormat.Raw)
    if public_key is not None and mine != public_key:
        raise SecretsError(
            f"{d.signing_key} does not match {d.signing_pub}: motes would refuse every "
            "definition; make the pair again with `awaremw keys init --force`"
        )
    return key.private_bytes(
        serialization.Encoding.Raw,
        serialization.PrivateFormat.Raw,
        serialization.NoEncryption(),
    )


def load_gateway_keys(secrets: Path | str) -> tuple[RadioSecurity, bytes]:
    """What a gateway's motes need: the radio security of :func:`load_radio_security`
    and the signing key of :func:`load_signing_key`, checked to match it."""
    security = load_radio_security(secrets)
    return security, load_signing_key(secrets, security.gateway_public_key)


def check_secrets(secrets: Path | str) -> RadioSecurity:
    """Check that ``secrets`` holds everything a whole-system run needs (the router's
    and the roles' Zenoh configs, the radio key, the signing pair); its radio
    security. Raises :class:`SecretsError` naming the first missing or bad file."""
    from awaremw.security.zenoh_acl import role_config_path, router_config_path

    router_config_path(secrets)
    for role in ("fleet", "gateway"):
        role_config_path(secrets, role)
    return load_gateway_keys(secrets)[0]
