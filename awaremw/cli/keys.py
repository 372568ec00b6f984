"""``awaremw keys init DIR [--force]``: the secrets of a deployment (docs/security.md).

::

    awaremw keys init secrets/
    awaremw router --secrets secrets/
    awaremw fleet romeo4r --connect tcp/127.0.0.1:7447 --secrets secrets/ --without-kind gateway
    awaremw gateway romeo4r --connect tcp/127.0.0.1:7447 --secrets secrets/
    awaremw fleet-ctl --secrets secrets/ list
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from awaremw.cli.friendly import refuse
from awaremw.cli.helptext import add_verb
from awaremw.security.zenoh_acl import DEFAULT_PREFIX


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = add_verb(
        sub,
        "keys",
        "create the secrets (radio key, signing key, accounts, TLS)",
        "The secrets of a deployment (docs/security.md): give the directory to every\n"
        "process with --secrets DIR.",
        [
            "awaremw keys init secrets/",
            "awaremw router --secrets secrets/",
            "awaremw gateway romeo4r --connect tcp/127.0.0.1:7447 --secrets secrets/",
        ],
    )
    ksub = p.add_subparsers(dest="keys_op", metavar="OP", required=True)
    i = add_verb(
        ksub,
        "init",
        "create every secret in DIR (files 0600, directories 0700)",
        "Create in DIR: the radio network key, the gateway's Ed25519 key pair, Zenoh\n"
        "accounts per role with the router's config (authentication, access control)\n"
        "and one client config per role, the routers' certificate for links between\n"
        "routers (mutual TLS), the Mosquitto password and ACL files, a CA and the\n"
        "broker's TLS certificate.",
        ["awaremw keys init secrets/", "awaremw keys init secrets/ --force"],
    )
    i.add_argument("dir", type=Path, metavar="DIR")
    i.add_argument("--force", action="store_true", help="replace existing secret files")
    i.add_argument(
        "--exist-ok",
        action="store_true",
        help="keep a complete set of secrets already in DIR and exit 0 (containers that "
        "make their secrets at every start); an incomplete set is still an error",
    )
    i.add_argument(
        "--tls-host",
        action="append",
        default=[],
        metavar="NAME",
        help="another DNS name or IP address for the MQTT broker's certificate (repeatable; "
        "always: localhost, 127.0.0.1, ::1 and broker, the compose service)",
    )
    i.add_argument(
        "--prefix",
        default=DEFAULT_PREFIX,
        help=f"key and topic prefix the access rules are written for (default {DEFAULT_PREFIX})",
    )
    i.add_argument(
        "--network-key-bytes",
        type=int,
        choices=(16, 32),
        default=16,
        help="size of the radio network key (default 16, AES-128 as IEEE 802.15.4)",
    )
    i.set_defaults(func=run_init)


def run_init(args: argparse.Namespace) -> int:
    from awaremw.security.keys import SecretsExist, init_secrets

    try:
        written = init_secrets(
            args.dir,
            force=args.force,
            prefix=args.prefix,
            network_key_bytes=args.network_key_bytes,
            tls_hosts=args.tls_host,
            exist_ok=args.exist_ok,
        )
    except SecretsExist as e:
        print(f"awaremw keys init: {e}", file=sys.stderr)
        return 1
    except (OSError, ValueError) as e:
        return refuse("awaremw keys init", e)
    root = args.dir.resolve()
    if not written:
        print(f"awaremw keys init: {root} holds a complete set of secrets already; kept")
        return 0
    print(f"awaremw keys init: wrote {len(written)} files under {root} (mode 0600):")
    for p in written:
        print(f"  {p.relative_to(root)}")
    return 0
