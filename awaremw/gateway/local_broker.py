"""Find the embedded broker of a gateway on this machine, with its account.

``awaremw gateway`` (without ``--mqtt``) runs an embedded broker that takes an
account, user ``awaremw`` with a password generated at its first start. The
broker keeps the account (``mqtt-account``, ``user:password``, mode 0600) and
its port (``broker.json``) in its state directory, under
``$XDG_STATE_HOME/awaremw`` (``~/.local/state/awaremw``). Client verbs and
scripts on the same machine, run by the same user, read them there instead of
asking the user to copy a password::

    from awaremw.gateway.local_broker import find_local_broker

    b = find_local_broker()          # None when no embedded broker ran here
    aiomqtt.Client(b.host, b.port, username=b.username, password=b.password)

When several state directories hold an account (one per deployment, or a
``--state-dir`` of one's own under the same base), the broker whose port
answers wins, then the one that started last.
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
from dataclasses import dataclass
from pathlib import Path

from awaremw.gateway.broker import ACCOUNT_FILE, DEFAULT_PORT, PORT_FILE
from awaremw.gateway.state import state_root

LOOPBACK = frozenset({"127.0.0.1", "localhost", "::1"})
# How deep under the base to look for state directories (deployments/<key>/broker).
_MAX_DEPTH = 3
_MAX_CANDIDATES = 64


@dataclass(frozen=True, slots=True)
class LocalBroker:
    """An embedded broker's address and account, read from its state directory."""

    host: str
    port: int
    username: str
    password: str
    state_dir: Path

    @property
    def url(self) -> str:
        """``mqtt://user:password@host:port`` (give it to a client, never to a log)."""
        return f"mqtt://{self.username}:{self.password}@{self.host}:{self.port}"


def state_base() -> Path:
    """Where every embedded broker's state directory lives (``.../awaremw``; each
    deployment's under ``deployments/<key>/broker``, gateway/state.py)."""
    return state_root()


def find_local_broker(port: int | None = None, base: Path | None = None) -> LocalBroker | None:
    """The embedded broker on this machine (on ``port`` if given), or None.

    Looks at every ``mqtt-account`` under :func:`state_base` (a few levels deep);
    an unreadable or malformed file is skipped, never an error: the caller then
    connects without an account and the broker says why it refuses."""
    found = [b for b in _candidates(base or state_base()) if port is None or b.port == port]
    if not found:
        return None
    # A broker that answers now, then the most recent start.
    found.sort(key=lambda b: (_listening(b.host, b.port), _mtime(b.state_dir)), reverse=True)
    return found[0]


def _candidates(base: Path) -> list[LocalBroker]:
    out: list[LocalBroker] = []
    if not base.is_dir():
        return out
    for root, dirs, files in os.walk(base):
        depth = len(Path(root).relative_to(base).parts)
        if depth >= _MAX_DEPTH:
            dirs.clear()
        if ACCOUNT_FILE in files:
            b = _read(Path(root))
            if b is not None:
                out.append(b)
                if len(out) >= _MAX_CANDIDATES:
                    break
    return out


def _read(state: Path) -> LocalBroker | None:
    try:
        user, sep, password = (state / ACCOUNT_FILE).read_text().strip().partition(":")
    except (OSError, UnicodeDecodeError):
        return None
    if not sep or not user or not password:
        return None
    port = DEFAULT_PORT  # never started with a port file: the default port
    with contextlib.suppress(OSError, ValueError, KeyError, TypeError):
        port = int(json.loads((state / PORT_FILE).read_text())["port"])
    return LocalBroker("127.0.0.1", port, user, password, state)


def _listening(host: str, port: int) -> bool:
    try:
        with socket.create_connection((host, port), timeout=0.2):
            return True
    except OSError:
        return False


def _mtime(state: Path) -> float:
    for name in (PORT_FILE, ACCOUNT_FILE):
        try:
            return (state / name).stat().st_mtime
        except OSError:
            continue
    return 0.0
