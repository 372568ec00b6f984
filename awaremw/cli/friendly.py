"""Errors a user can act on: one line, no Rust source paths, no traceback.

Zenoh's errors (``zenoh.ZError``) carry the Rust source location they were
raised at (``... at /root/.cargo/git/checkouts/.../orchestrator.rs:388.``);
:func:`zenoh_message` keeps the sentence and drops the location.
:func:`add_secrets_option` and :func:`load_secrets` are the one ``--secrets DIR``
option of every verb: its help, its check and its error line. :func:`refuse` is
how a verb turns down its command line: ``prog: why`` on stderr, exit status 2.
:func:`stop_event` is how a long-running verb hears Ctrl-C and SIGTERM.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import re
import signal
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

T = TypeVar("T")

# " at /path/to/file.rs:388." (possibly several, possibly without the final dot)
_RUST_AT = re.compile(r"\s+at\s+\S+\.rs:\d+(?::\d+)?\.?")
_MAX_LINE = 300


def zenoh_message(e: BaseException) -> str:
    """The text of a Zenoh error on one line, without Rust source locations."""
    text = _RUST_AT.sub("", str(e))
    text = " ".join(text.split())
    if len(text) > _MAX_LINE:
        text = text[: _MAX_LINE - 3] + "..."
    return text or type(e).__name__


def _listens(endpoint: str) -> bool | None:
    """Whether a TCP endpoint ``tcp/HOST:PORT`` accepts connections (None: not TCP)."""
    import socket

    proto, _, addr = endpoint.partition("/")
    host, _, port = addr.rpartition(":")
    if proto != "tcp" or not host or not port.isdigit():
        return None
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=0.5):
            return True
    except OSError:
        return False


def zenoh_unreachable(endpoints: list[str], e: BaseException, secrets_given: bool) -> str:
    """Why a Zenoh session to ``endpoints`` did not open, and what to do, on one line.

    Zenoh says the same ("Unable to connect ... Timeout!") of a router that is
    down and of a secured router that refused us; a TCP connection tells the two
    apart: something listens there (refused: ``--secrets``) or nothing does."""
    where = ", ".join(endpoints)
    text = zenoh_message(e)
    if "Unable to connect" not in text:
        return f"cannot reach {where}: {text}"
    listening = [_listens(ep) for ep in endpoints]
    if any(listening):
        if secrets_given:
            return (
                f"cannot reach {where}: a router listens there but refused the session: "
                "are --secrets the router's (the same `awaremw keys init` directory)?"
            )
        return (
            f"cannot reach {where}: a router listens there but refused the session: it is "
            "secured, give --secrets DIR (the directory of `awaremw keys init`)"
        )
    if all(v is False for v in listening):
        return (
            f"cannot reach {where}: nothing listens there (is `awaremw router` running? "
            "check --connect)"
        )
    return (
        f"cannot reach {where}: {text} (no router there, or a secured one that refused us: "
        "then give --secrets DIR)"
    )


def is_zenoh_error(e: BaseException) -> bool:
    """Whether ``e`` is a ``zenoh.ZError`` (without importing zenoh when unused)."""
    zenoh = sys.modules.get("zenoh")
    zerr = getattr(zenoh, "ZError", None) if zenoh is not None else None
    return isinstance(zerr, type) and isinstance(e, zerr)


def refuse(prog: str, why: object) -> int:
    """Print ``prog: why`` on stderr, any password in it masked; return 2, the exit
    status of a refused command line."""
    from awaremw.security.redact import redact

    print(f"{prog}: {redact(str(why))}", file=sys.stderr)
    return 2


def stop_event() -> asyncio.Event:
    """An event that SIGINT or SIGTERM sets (where the loop takes signal handlers)."""
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        with contextlib.suppress(NotImplementedError):
            loop.add_signal_handler(sig, stop.set)
    return stop


def add_secrets_option(p: argparse.ArgumentParser, help: str) -> None:
    """``--secrets DIR`` on a verb; ``help`` says what the verb does with DIR."""
    p.add_argument("--secrets", default=None, metavar="DIR", help=help)


def load_secrets(prog: str, secrets: str | Path, load: Callable[[Path], T]) -> T | None:
    """What a verb takes from ``--secrets DIR``: ``load(DIR)``, or None when DIR is not
    a directory or ``load`` raises :class:`~awaremw.security.zenoh_acl.SecretsError`
    (a missing or bad file); then the reason is on stderr in one line, ``prog: why``,
    and the verb exits 2."""
    from awaremw.security.zenoh_acl import SecretsError

    root = Path(secrets)
    try:
        if not root.is_dir():
            what = "not a directory" if root.exists() else "no such directory"
            raise SecretsError(
                f"--secrets {secrets}: {what}; make the secrets with `awaremw keys init {secrets}`"
            )
        return load(root)
    except SecretsError as e:
        refuse(prog, e)
        return None
