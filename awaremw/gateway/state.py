"""Where a gateway keeps what it remembers: one directory per deployment.

A gateway's versions (``gateway.sqlite``) and its embedded broker (account,
port, retained messages: ``broker/``) belong to the deployment it runs, so a
run of another deployment starts clean and a restart on the same one keeps
them (docs/gateway.md, *State directories*)::

    $XDG_STATE_HOME/awaremw/deployments/<key>/      (~/.local/state/awaremw/...)
        deployment.json   which deployment this is (name and file)
        gateway.lock      held by the running gateway
        gateway.sqlite    versions, command slots, replay hashes
        broker/           the embedded broker's state

``<key>`` is the deployment's name for a shipped deployment, and the name and
a hash of the file's path for any other one (two ``test.toml`` in two folders
are two deployments). ``--state-dir DIR`` names the deployment's directory
itself; a directory that holds another deployment's state is refused (one
line) unless ``--fresh``, which forgets what the directory held (the embedded
broker's account and port stay: clients keep working).

:func:`open_state` checks at start that the directory can be created, locked
and written and has room (:data:`MIN_FREE_BYTES`); any failure is a
:class:`StateError` whose text is one line for the user.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import hashlib
import json
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

STATE_ENV = "XDG_STATE_HOME"
DEPLOYMENTS = "deployments"
MARK_FILE = "deployment.json"
LOCK_FILE = "gateway.lock"
STORE_FILE = "gateway.sqlite"
BROKER_DIR = "broker"
MIN_FREE_BYTES = 1 << 20  # below this a state directory is taken as full at start
# What --fresh removes: the versions and the retained messages (and their
# SQLite journals); the broker's account and port are kept.
FORGET = ("gateway.sqlite", "broker/retained.sqlite")
_JOURNALS = ("", "-wal", "-shm", "-journal")


class StateError(RuntimeError):
    """The state directory cannot be used; the text is one line for the user."""


def state_root() -> Path:
    """``$XDG_STATE_HOME/awaremw`` (``~/.local/state/awaremw``)."""
    base = os.environ.get(STATE_ENV) or str(Path.home() / ".local" / "state")
    return Path(base) / "awaremw"


def deployment_key(name: str, path: Path | None, shipped: Path | None) -> str:
    """The directory name of a deployment's state: its name (made safe) when it is
    shipped (``path`` in ``shipped``) or has no file, else name and path hash."""
    safe = re.sub(r"[^A-Za-z0-9_.-]+", "_", name).strip("._") or "deployment"
    if path is None:
        return safe
    resolved = path.resolve()
    if shipped is not None and resolved.parent == shipped.resolve():
        return safe
    return f"{safe}-{hashlib.sha256(str(resolved).encode()).hexdigest()[:10]}"


def default_dir(key: str) -> Path:
    return state_root() / DEPLOYMENTS / key


@dataclass(slots=True)
class DeploymentState:
    """An open, locked state directory of one deployment (close it, or ``with``)."""

    dir: Path
    key: str
    forgotten: tuple[str, ...] = ()  # files --fresh removed
    _lock_fd: int | None = field(default=None, repr=False)

    @property
    def store_path(self) -> Path:
        return self.dir / STORE_FILE

    @property
    def broker_dir(self) -> Path:
        return self.dir / BROKER_DIR

    def close(self) -> None:
        if self._lock_fd is not None:
            os.close(self._lock_fd)
            self._lock_fd = None

    def __enter__(self) -> DeploymentState:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_state(
    directory: Path, key: str, *, name: str, source: str, fresh: bool = False
) -> DeploymentState:
    """Create (0700), lock and check ``directory`` for deployment ``key``.

    Raises :class:`StateError` when it cannot be created or written, is full,
    is in use by another gateway, or holds another deployment's state (unless
    ``fresh``, which forgets that state).
    """
    d = directory
    try:
        d.mkdir(parents=True, exist_ok=True, mode=0o700)
    except OSError as e:
        raise StateError(f"cannot create the state directory {d}: {_why(e)}") from None
    if not d.is_dir():
        raise StateError(f"the state directory {d} is not a directory")
    try:
        fd = os.open(d / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o600)
    except OSError as e:
        raise StateError(f"cannot write in the state directory {d}: {_why(e)}") from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        raise StateError(
            f"the state directory {d} is in use by another gateway; "
            "give this one its own --state-dir"
        ) from None
    state = DeploymentState(d, key, _lock_fd=fd)
    try:
        held = _marked(d)
        if held is not None and held != key and not fresh:
            raise StateError(
                f"the state directory {d} holds the state of deployment {held!r}, not "
                f"{key!r}: give another --state-dir, or --fresh to forget what it holds"
            )
        if fresh:
            state.forgotten = forget(d)
        _check_room(d)
        _write_mark(d, key, name, source)
    except BaseException:
        state.close()
        raise
    return state


def forget(d: Path) -> tuple[str, ...]:
    """Remove the versions and retained messages kept in ``d``; what was removed."""
    gone = []
    for rel in FORGET:
        for suffix in _JOURNALS:
            p = d / (rel + suffix)
            try:
                p.unlink()
            except FileNotFoundError:
                continue
            except OSError as e:
                raise StateError(f"--fresh cannot remove {p}: {_why(e)}") from None
            gone.append(rel + suffix)
    return tuple(gone)


def _marked(d: Path) -> str | None:
    """The deployment key ``d`` was used for, or None (new, or written before marks)."""
    with contextlib.suppress(OSError, ValueError, TypeError, KeyError):
        key = json.loads((d / MARK_FILE).read_text(encoding="utf-8"))["key"]
        if isinstance(key, str):
            return key
    return None


def _write_mark(d: Path, key: str, name: str, source: str) -> None:
    """Write the mark through a temporary file: a probe that the directory takes writes."""
    tmp = d / (MARK_FILE + ".tmp")
    text = json.dumps({"key": key, "name": name, "source": source}) + "\n"
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, d / MARK_FILE)
    except OSError as e:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise StateError(f"cannot write in the state directory {d}: {_why(e)}") from None


def _check_room(d: Path) -> None:
    try:
        st = os.statvfs(d)
    except OSError as e:
        raise StateError(f"cannot read the state directory {d}: {_why(e)}") from None
    free = st.f_bavail * st.f_frsize
    if free < MIN_FREE_BYTES:
        raise StateError(
            f"the state directory {d} is full ({free // 1024} KiB free, "
            f"{MIN_FREE_BYTES // 1024} KiB needed): free some space or give another --state-dir"
        )


def _why(e: OSError) -> str:
    if e.errno in (errno.EROFS, errno.EACCES, errno.EPERM, errno.ENOSPC, errno.EDQUOT):
        return os.strerror(e.errno)
    return e.strerror or str(e)
